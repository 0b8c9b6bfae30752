"""The SUMO boundary: the only module in v2v that imports libsumo.

:class:`SumoSimulation` owns one libsumo simulation (libsumo allows one per process and
is not thread-safe), builds the clusters, steps SUMO and returns typed
:class:`~v2v.traffic.snapshot.TrafficStep` snapshots. SUMO's conventions stop here:

* ``vehicle.getPosition`` is the **front-bumper centre** in net XY; the antenna is
  ``front_bumper + R(azimuth) @ lever_arm`` with the lever arm in the body frame
  (x forward, y left, z up, ISO 8855) from the front-bumper centre at road level.
* ``vehicle.getAngle`` is **degrees clockwise from the net's +y axis** (grid north). The
  true azimuth adds the projection's grid convergence (zero on a tangent projection's
  central meridian; ~2.3 deg at a UTM zone's edge at 51 deg N).
* ``vehicle.getSpeed`` is the front bumper's speed along its lane *at* the step (SUMO
  moves it by the mean of the old and new speed). The antenna velocity is the rigid-body
  ``v_front + omega x r``: lane tangent times speed, plus SUMO's lateral speed during a lane
  change (SUMO slides the whole car sideways while its heading, a smoothed rear-to-front
  chord, lags), plus the lever arm swinging with the azimuth rate. Net-XY vectors go to ENU
  through the projection's local Jacobian (convergence and scale at each vehicle).
* libsumo raises ``libsumo.TraCIException`` (which does not pickle); errors that are the
  user's fault become :class:`~v2v.errors.UserError` here, the rest become events.

Cluster formation: each cluster's vehicles depart one after another from the start of
the route, ``time_gap_s / len(lanes)`` apart, round robin over the configured lanes, at
the maximum safe insertion speed. The simulation is warmed up until every cluster
vehicle is on the road; ``t_s = 0`` is that moment (``warmup_s`` is reported).
"""

from __future__ import annotations

import bisect
import math
import os
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit

from v2v.errors import UserError
from v2v.frames import WGS84_A_M, WGS84_E2, GeoReference, wrap_angle_scalar
from v2v.nets import check_cluster_lanes
from v2v.traffic.snapshot import EventKind, TrafficEvent, TrafficStep, VehicleState

if TYPE_CHECKING:
    from v2v.config.scenario import Scenario

_ACTIVE = False  # one simulation per process


@dataclass(frozen=True, kw_only=True)
class NetFiles:
    """The files a simulation needs: the net, building/foliage polygons, the route edges."""

    net_path: Path
    poly_paths: tuple[Path, ...] = ()
    route_edges: tuple[str, ...] = ()


@dataclass
class _VehicleMeta:
    cluster: str
    is_lead: bool
    lever_arm_m: np.ndarray
    length_m: float
    width_m: float
    height_m: float
    lead_id: str
    max_separation_m: float
    prev_azimuth_rad: float | None = None
    prev_t_s: float | None = None
    in_cluster: bool = True
    lane_index: int | None = None


@dataclass(slots=True)
class RawStep:
    """One step's truth as libsumo gives it (:meth:`SumoSimulation.raw_snapshot`), not yet
    converted (:meth:`SumoSimulation.convert`): the cluster vehicles present (``ids``, in
    cluster order), per vehicle its ``getPosition3D`` (front bumper), ``getAngle`` (deg
    clockwise from grid north) and ``more`` = (speed m/s, slope deg, lane id, lane position
    m, lateral speed m/s, lane index, acceleration m/s^2, edge id, lateral lane position m);
    the step's SUMO events so far and the background boxes."""

    t_s: float
    ids: list[str]
    events: list[TrafficEvent]
    background: np.ndarray
    front: list[tuple[float, float, float]]
    angle_deg: list[float]
    more: list[tuple[Any, ...]]


@dataclass
class TrafficStats:
    warmup_s: float = 0.0
    teleports: int = 0
    collisions: int = 0
    arrived: list[str] = field(default_factory=list)


def sumo_binary() -> str:
    import sumo  # eclipse-sumo wheel

    return os.path.join(sumo.SUMO_HOME, "bin", "sumo")


class SumoSimulation:
    """Context manager owning one libsumo simulation.

    Parameters
    ----------
    scenario : Scenario
        Resolved scenario (clusters, vehicle types, duration, step length, seed).
    net : NetFiles
        Net, polygons and the route (edge ids) the clusters drive.
    georef : GeoReference
        Net XY -> geodetic mapping (from the net's ``<location>``).
    seed : int
        Passed to SUMO's ``--seed`` (also drives background-traffic draws here).
    """

    def __init__(self, scenario: Scenario, net: NetFiles, georef: GeoReference, seed: int):
        self.scenario = scenario
        self.net = net
        self.georef = georef
        self.seed = int(seed)
        self.dt_s = float(scenario.step_length_s)
        self.stats = TrafficStats()
        self._meta: dict[str, _VehicleMeta] = {}
        self._t0_sumo_s = 0.0
        self._rng = np.random.default_rng(np.random.SeedSequence(self.seed).spawn(1)[0])
        self._bg_counter = 0
        self._bg_next_s = math.inf
        self._pending_events: list[TrafficEvent] = []
        self._traci: Any = None
        self._lanes: dict[str, tuple[list[tuple[float, float]], list[float], float]] = {}
        self._lane_widths: dict[str, float] = {}
        self._arms_key: tuple[str, ...] = ()
        self._arms = np.zeros((0, 3))
        self._pairs_key: tuple[str, ...] = ()
        self._pairs: tuple[list[int], np.ndarray, np.ndarray] = ([], np.zeros(0, np.intp), np.zeros(0, np.intp))

    # ------------------------------------------------------------------ lifecycle
    def __enter__(self) -> SumoSimulation:
        global _ACTIVE
        if _ACTIVE:
            raise RuntimeError("libsumo allows one simulation per process; run sweeps in separate processes")
        import libsumo

        self._traci = libsumo
        args = [
            sumo_binary(),
            "-n", str(self.net.net_path),
            "--step-length", repr(self.dt_s),
            "--seed", str(self.seed),
            "--no-step-log", "true",
            "--no-warnings", "true",
            "--duration-log.disable", "true",
            "--lanechange.duration", "3",
            "--collision.action", "warn",
            "--time-to-teleport", "120",
            "--default.action-step-length", repr(self.dt_s),
        ]
        try:
            libsumo.start(args)
        except Exception as exc:  # libsumo.TraCIException / FatalTraCIError
            raise UserError(
                f"SUMO could not load {self.net.net_path}: {_one_line(exc)}",
                field="network.net_file",
                fix="give a valid SUMO .net.xml (build the shipped nets with `v2v nets build`)",
            ) from None
        _ACTIVE = True
        try:
            self._build_clusters()
            self._warm_up()
        except BaseException:
            self.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        global _ACTIVE
        if _ACTIVE and self._traci is not None:
            try:
                self._traci.close()
            finally:
                _ACTIVE = False

    # ------------------------------------------------------------------ setup
    def _build_clusters(self) -> None:
        tc = self._traci
        sc = self.scenario
        edges = list(self.net.route_edges)
        if not edges:
            raise UserError("no route edges", field="network.route", fix="name a route of the net or set network.route_edges")
        known = set(tc.edge.getIDList())
        missing = [e for e in edges if e not in known]
        if missing:
            normal = sorted(e for e in known if not e.startswith(":"))  # (not the junctions' internal edges)
            raise UserError(
                f"route edge(s) {missing[:3]} are not in the net",
                field="network.route_edges",
                fix=f"use edge ids of this net ({len(normal)}: {', '.join(normal[:6])}{', ...' if len(normal) > 6 else ''})",
            )
        try:
            tc.route.add("v2v_route", edges)
        except Exception as exc:
            raise UserError(f"SUMO rejected the route: {_one_line(exc)}", field="network.route_edges", fix="list connected edges") from None
        # Check connectivity with SUMO's own router, edge pair by pair.
        for a, b in zip(edges[:-1], edges[1:], strict=True):
            r = tc.simulation.findRoute(a, b)
            if len(r.edges) == 0 or (len(r.edges) > 2 and a != b):
                raise UserError(
                    f"SUMO cannot connect edge {a!r} directly to {b!r}",
                    field="network.route_edges",
                    fix="list consecutive, connected edges (or use a named route of the net)",
                )
        n_lanes_first = tc.edge.getLaneNumber(edges[0])
        for tname, vt in sc.vehicle_types.items():
            vid = f"v2v_{tname}"
            tc.vehicletype.copy("DEFAULT_VEHTYPE", vid)
            tc.vehicletype.setLength(vid, vt.length_m)
            tc.vehicletype.setWidth(vid, vt.width_m)
            tc.vehicletype.setHeight(vid, vt.height_m)
            tc.vehicletype.setMaxSpeed(vid, vt.max_speed_mps)
            tc.vehicletype.setAccel(vid, vt.accel_mps2)
            tc.vehicletype.setDecel(vid, vt.decel_mps2)
            tc.vehicletype.setImperfection(vid, vt.driver_imperfection)
            tc.vehicletype.setSpeedFactor(vid, 1.0)
            tc.vehicletype.setSpeedDeviation(vid, 0.0)
            tc.vehicletype.setMinGap(vid, 2.0)
            if vt.length_m > 7.0:
                tc.vehicletype.setVehicleClass(vid, "truck")
        check_cluster_lanes(sc.clusters, n_lanes_first)
        for c in sc.clusters:
            ids = [f"{c.name}.{i}" for i in range(c.vehicles)]
            lead_id = ids[c.lead]
            gap = c.time_gap_s / len(c.lanes)
            for i, vid in enumerate(ids):
                tname = c.type_of(i)
                vt = sc.vehicle_types[tname]
                lane = c.lanes[i % len(c.lanes)]
                tc.vehicle.add(
                    vid,
                    "v2v_route",
                    typeID=f"v2v_{tname}",
                    depart=f"{c.depart_s + i * gap:.3f}",
                    departLane=str(lane),
                    departPos="base",
                    departSpeed="max",
                )
                self._meta[vid] = _VehicleMeta(
                    cluster=c.name,
                    is_lead=(vid == lead_id),
                    lever_arm_m=np.asarray(vt.antenna_lever_arm_m, dtype=float),
                    length_m=vt.length_m,
                    width_m=vt.width_m,
                    height_m=vt.height_m,
                    lead_id=lead_id,
                    max_separation_m=c.max_separation_m,
                )
        if sc.background.vehicles_per_hour > 0:
            self._bg_next_s = self._draw_bg_gap()

    def _draw_bg_gap(self) -> float:
        return float(self._rng.exponential(3600.0 / self.scenario.background.vehicles_per_hour))

    def _spawn_background(self, now_s: float) -> None:
        tc = self._traci
        while self._bg_next_s <= now_s:
            truck = self._rng.random() < self.scenario.background.truck_fraction
            tname = "truck" if truck and "truck" in self.scenario.vehicle_types else "passenger"
            if tname not in self.scenario.vehicle_types:
                tname = next(iter(self.scenario.vehicle_types))
            vid = f"bg.{self._bg_counter}"
            self._bg_counter += 1
            try:
                tc.vehicle.add(vid, "v2v_route", typeID=f"v2v_{tname}", depart="now", departLane="random", departSpeed="max")
            except Exception as exc:
                self._pending_events.append(TrafficEvent(t_s=now_s - self._t0_sumo_s, kind=EventKind.TELEPORT, vehicle_id=vid, detail=f"background insert failed: {_one_line(exc)}"))
            self._bg_next_s += self._draw_bg_gap()

    def _warm_up(self) -> None:
        """Step until every cluster vehicle has departed (t_s = 0 is then)."""
        tc = self._traci
        waiting = set(self._meta)
        limit_s = max(c.depart_s + c.vehicles * c.time_gap_s for c in self.scenario.clusters) + 120.0
        while waiting:
            tc.simulationStep()
            now = tc.simulation.getTime()
            self._spawn_background(now)
            self._record_sumo_events(now)  # SUMO time; shifted to t_s (< 0) below
            for vid in tc.simulation.getDepartedIDList():
                waiting.discard(vid)
            if now > limit_s:
                raise UserError(
                    f"{len(waiting)} cluster vehicle(s) could not be inserted within {limit_s:.0f} s of SUMO time",
                    field="clusters",
                    fix="use fewer vehicles per lane, more lanes, or a longer first edge",
                )
        self._t0_sumo_s = tc.simulation.getTime()
        self.stats.warmup_s = self._t0_sumo_s
        self._pending_events = [replace(e, t_s=round(e.t_s - self._t0_sumo_s, 6)) for e in self._pending_events]

    # ------------------------------------------------------------------ stepping
    @property
    def t_s(self) -> float:
        # SUMO's clock is integer milliseconds; round off the float noise of the difference
        # (38.1 - 3.6 = 34.49999999999999) so t_s values are exact step multiples to 1 us.
        return round(self._traci.simulation.getTime() - self._t0_sumo_s, 6)

    def snapshot(self) -> TrafficStep:
        """The current truth (after the last step): :meth:`convert` of :meth:`raw_snapshot`."""
        return self.convert([self.raw_snapshot()])[0]

    def raw_snapshot(self) -> RawStep:
        """What the current truth needs from libsumo, read now (the getters only): a
        :class:`RawStep` for :meth:`convert`, which may run later on many steps at once."""
        veh = self._traci.vehicle
        present = set(veh.getIDList())
        events = list(self._pending_events)
        self._pending_events.clear()
        ids = [v for v in self._meta if v in present]
        return RawStep(
            t_s=self.t_s, ids=ids, events=events, background=self._background_boxes(present),
            front=[veh.getPosition3D(v) for v in ids], angle_deg=[veh.getAngle(v) for v in ids],
            more=[(veh.getSpeed(v), veh.getSlope(v), veh.getLaneID(v), veh.getLanePosition(v), veh.getLateralSpeed(v),
                   veh.getLaneIndex(v), veh.getAcceleration(v), veh.getRoadID(v), veh.getLateralLanePosition(v))
                  for v in ids])

    def convert(self, raws: list[RawStep]) -> list[TrafficStep]:
        """Truth snapshots of consecutive raw steps (:meth:`raw_snapshot`, in step order, each
        converted once: the yaw rate, lane-change and cluster-membership events carry state from
        one step to the next).

        Per vehicle only the scalar rigid-body velocity and the bookkeeping run in Python; the
        frame conversions run on every vehicle of every step at once (one projection call for
        the antennas and their Jacobian probes, two compiled kernels, element for element the
        arithmetic of one step at a time, so the truth does not depend on how many steps are
        converted together).
        """
        full = [r for r in raws if r.ids]
        if full:
            xyz_front = np.array([p for r in full for p in r.front], dtype=float)  # x, y as getPosition's
            grid_az_deg = np.array([a for r in full for a in r.angle_deg], dtype=float)
            arms = np.concatenate([self._lever_arms(r.ids) for r in full])
            fwd, ant_xy, ant_z, h, probe_x, probe_y = _antenna_kernel(xyz_front, grid_az_deg, arms,
                                                                     self.scenario.network.origin_h_m)
            lat3, lon3 = self.georef.xy_to_geodetic(probe_x, probe_y)  # antennas, then 1 m east / north probes
            ecef, jac, fwd_enu = _enu_kernel(lat3, lon3, h, fwd)  # jac (n, 3, 2): net-XY vector -> ENU
            n_all = len(h)
            lat, lon = lat3[:n_all], lon3[:n_all]
            # True azimuth of the body axis: the grid angle plus the projection's convergence at
            # the vehicle's own position.
            az_list = (np.arctan2(fwd_enu[:, 0], fwd_enu[:, 1]) % (2 * math.pi)).tolist()
            ant_list, xy = ant_xy.tolist(), xyz_front[:, :2]
            xy_list = xy.tolist()
            v_grid, climb, yaw = [], [], []
            k = 0
            for r in full:
                t = r.t_s
                for vid, a_deg, (speed, slope_deg, lane_id, lane_pos, lat_speed, lane_index, *_) in zip(
                        r.ids, r.angle_deg, r.more, strict=True):
                    m = self._meta[vid]
                    az = az_list[k]
                    continuing = m.prev_t_s is not None and abs(t - m.prev_t_s - self.dt_s) < 1e-6
                    yaw_rate = wrap_angle_scalar(az - m.prev_azimuth_rad) / self.dt_s if continuing else 0.0
                    m.prev_azimuth_rad, m.prev_t_s = az, t
                    yaw.append(yaw_rate)
                    slope = math.radians(slope_deg)
                    arm = (ant_list[k][0] - xy_list[k][0], ant_list[k][1] - xy_list[k][1])
                    v_grid.append(self._grid_velocity(lane_id, lane_pos, a_deg, lat_speed, speed, slope, yaw_rate, arm))
                    climb.append(speed * math.sin(slope))
                    if m.lane_index is not None and lane_index != m.lane_index and not lane_id.startswith(":"):
                        r.events.append(TrafficEvent(t_s=t, kind=EventKind.LANE_CHANGE, vehicle_id=vid,
                                                     detail=f"{m.lane_index}->{lane_index}"))
                    if not lane_id.startswith(":"):
                        m.lane_index = lane_index
                    k += 1
            vel = np.matmul(jac, np.array(v_grid)[:, :, None])[:, :, 0]  # one (3, 2) @ (2,) per vehicle
            vel[:, 2] += climb
            xyz = np.empty((n_all, 3))
            xyz[:, :2], xyz[:, 2] = ant_xy, ant_z
            lat_l, lon_l, h_l = lat.tolist(), lon.tolist(), h.tolist()
            grid_az = (np.radians(grid_az_deg) % (2 * math.pi)).tolist()  # (the background boxes' convention)
        out: list[TrafficStep] = []
        k = 0
        for r in raws:
            if not r.ids:
                out.append(TrafficStep(t_s=r.t_s, vehicles={}, events=tuple(r.events), background=r.background))
                continue
            t, k0 = r.t_s, k
            states: dict[str, VehicleState] = {}
            for vid, (speed, _, lane_id, _, _, lane_index, accel, road_id, lat_pos) in zip(r.ids, r.more, strict=True):
                m = self._meta[vid]
                states[vid] = VehicleState(
                    vehicle_id=vid,
                    cluster=m.cluster,
                    is_lead=m.is_lead,
                    t_s=t,
                    xyz_m=xyz[k],
                    lat_rad=lat_l[k],
                    lon_rad=lon_l[k],
                    h_m=h_l[k],
                    ecef_m=ecef[k],
                    vel_enu_mps=vel[k],
                    speed_mps=speed,
                    accel_mps2=accel,
                    azimuth_rad=az_list[k],
                    grid_azimuth_rad=grid_az[k],
                    yaw_rate_rps=yaw[k],
                    front_bumper_xy_m=xy[k],
                    edge_id=road_id,
                    lane_id=lane_id,
                    lane_index=lane_index,
                    lane_width_m=self._lane_width(lane_id),
                    lateral_offset_m=lat_pos,
                    length_m=m.length_m,
                    width_m=m.width_m,
                    height_m=m.height_m,
                )
                k += 1
            self._update_membership(r.ids, [self._meta[v] for v in r.ids], ecef[k0:k], t, r.events)
            out.append(TrafficStep(t_s=t, vehicles=states, events=tuple(r.events), background=r.background))
        return out

    def _update_membership(self, ids: list[str], metas: list[_VehicleMeta], ecef: np.ndarray, t: float,
                           events: list[TrafficEvent]) -> None:
        """Cluster membership by the antenna separation from the lead (events on leaving / rejoining)."""
        key = tuple(ids)
        if self._pairs_key != key:  # rows of the non-lead vehicles whose lead is present, and of their leads
            row = {vid: k for k, vid in enumerate(ids)}
            ks = [k for k, (vid, m) in enumerate(zip(ids, metas, strict=True)) if vid != m.lead_id and m.lead_id in row]
            self._pairs_key, self._pairs = key, (ks, np.array(ks, dtype=np.intp),
                                                 np.array([row[metas[k].lead_id] for k in ks], dtype=np.intp))
        ks, rows, lead_rows = self._pairs
        if not ks:
            return
        d = ecef[rows] - ecef[lead_rows]
        # |d| as np.linalg.norm computes it (a dot product per vehicle), for all vehicles at once
        seps = np.sqrt(np.matmul(d[:, None, :], d[:, :, None])[:, 0, 0]).tolist()
        for k, sep in zip(ks, seps, strict=True):
            m = metas[k]
            inside = sep <= m.max_separation_m
            if m.in_cluster and not inside:
                events.append(TrafficEvent(t_s=t, kind=EventKind.LEFT_CLUSTER, vehicle_id=ids[k], detail=f"{sep:.0f} m from {m.lead_id}"))
            elif not m.in_cluster and inside:
                events.append(TrafficEvent(t_s=t, kind=EventKind.REJOINED_CLUSTER, vehicle_id=ids[k], detail=f"{sep:.0f} m from {m.lead_id}"))
            m.in_cluster = inside

    def _lane_width(self, lane_id: str) -> float:
        """``lane.getWidth`` (m), cached per lane (3.2 m when off the road)."""
        if not lane_id:
            return 3.2
        w = self._lane_widths.get(lane_id)
        if w is None:
            w = self._lane_widths[lane_id] = self._traci.lane.getWidth(lane_id)
        return w

    def _lever_arms(self, ids: list[str]) -> np.ndarray:
        """Body-frame antenna lever arms (n, 3) of these vehicles (cached per vehicle set)."""
        key = tuple(ids)
        if self._arms_key != key:
            self._arms_key, self._arms = key, np.array([self._meta[v].lever_arm_m for v in ids])
        return self._arms

    def _lane_tangent(self, lane_id: str, lane_pos_m: float) -> tuple[tuple[float, float], float] | None:
        """Unit tangent (net XY) of a lane's centre-line at a lane position, and the lane's
        geometry factor (shape length / SUMO lane length: SUMO moves a vehicle by
        ``speed * dt`` lane metres, i.e. ``factor * speed * dt`` along the drawn shape)."""
        if not lane_id:
            return None
        lane = self._lanes.get(lane_id)
        if lane is None:
            shape = np.asarray(self._traci.lane.getShape(lane_id), dtype=float)[:, :2]
            seg = np.diff(shape, axis=0)
            seg_len = np.linalg.norm(seg, axis=1)
            keep = seg_len > 1e-9
            if not keep.any():
                return None
            seg, seg_len = seg[keep], seg_len[keep]
            length = float(self._traci.lane.getLength(lane_id))
            factor = float(seg_len.sum()) / length if length > 0 else 1.0
            units = [(float(u[0]), float(u[1])) for u in seg / seg_len[:, None]]
            lane = self._lanes[lane_id] = (units, np.cumsum(seg_len).tolist(), factor)
        units, cum, factor = lane
        return units[min(bisect.bisect_right(cum, lane_pos_m * factor), len(cum) - 1)], factor

    def _grid_velocity(self, lane_id: str, lane_pos_m: float, angle_deg: float, lateral_speed_mps: float,
                       speed: float, slope: float, yaw_rate: float, arm_xy: tuple[float, float]) -> tuple[float, float]:
        """Horizontal velocity of the antenna in net XY (m/s), consistent with the antenna track.

        Rigid body: ``v_ant = v_front + omega x r`` with ``r = antenna - front bumper``.
        The front bumper runs along its lane's centre-line (tangent at its lane position,
        times the lane's geometry factor) plus, during a lane change, SUMO's lateral speed
        along the lane's left normal (SUMO translates the whole vehicle sideways: its
        heading is a smoothed chord and does *not* point along that motion). ``omega`` is
        the azimuth rate (clockwise). SUMO integrates speed trapezoidally within a step, so
        ``getSpeed`` is the speed *at* the step, not its mean. The caller maps it to ENU
        with the projection's Jacobian and adds the climb ``speed sin(slope)``.
        """
        tan = self._lane_tangent(lane_id, lane_pos_m)
        if tan is None:
            a = math.radians(angle_deg)
            (t0, t1), factor = (math.sin(a), math.cos(a)), 1.0
        else:
            (t0, t1), factor = tan
        along = speed * math.cos(slope) * factor
        lateral = lateral_speed_mps  # along the left normal (-t1, t0)
        return (along * t0 + lateral * -t1 + yaw_rate * arm_xy[1],
                along * t1 + lateral * t0 + yaw_rate * -arm_xy[0])

    def _background_boxes(self, present: set[str]) -> np.ndarray:
        """Boxes (k, 6) of the non-cluster vehicles, sorted: centre x, y, azimuth, length, width, height."""
        others = present.difference(self._meta)
        if not others:
            return np.zeros((0, 6))
        tc = self._traci
        rows = []
        for vid in others:
            x, y = tc.vehicle.getPosition(vid)
            a = math.radians(tc.vehicle.getAngle(vid))
            length = tc.vehicle.getLength(vid)
            # getPosition is the front bumper: the box centre is half a length behind.
            rows.append((x - 0.5 * length * math.sin(a), y - 0.5 * length * math.cos(a), a, length, tc.vehicle.getWidth(vid), tc.vehicle.getHeight(vid)))
        rows.sort()
        return np.array(rows, dtype=float).reshape(-1, 6)

    def _record_sumo_events(self, t: float) -> None:
        """Teleports, collisions and arrivals of cluster vehicles in the last SUMO step."""
        tc = self._traci
        for vid in tc.simulation.getStartingTeleportIDList():
            if vid in self._meta:
                self.stats.teleports += 1
                self._pending_events.append(TrafficEvent(t_s=t, kind=EventKind.TELEPORT, vehicle_id=vid, detail="SUMO teleported the vehicle (jam/deadlock)"))
        for vid in tc.simulation.getCollidingVehiclesIDList():
            if vid in self._meta:
                self.stats.collisions += 1
                self._pending_events.append(TrafficEvent(t_s=t, kind=EventKind.COLLISION, vehicle_id=vid))
        for vid in tc.simulation.getArrivedIDList():
            if vid in self._meta:
                self.stats.arrived.append(vid)
                self._pending_events.append(TrafficEvent(t_s=t, kind=EventKind.ARRIVED, vehicle_id=vid, detail="reached the end of its route"))

    def step(self) -> TrafficStep:
        """Advance SUMO by one step and return the truth snapshot."""
        return self.convert([self.step_raw()])[0]

    def step_raw(self) -> RawStep:
        """Advance SUMO by one step and return what its truth needs from libsumo: a run of
        these converted together (:meth:`convert`) gives what :meth:`step` gives one by one,
        at a fraction of the per-step cost (``v2v.run`` converts each chunk's steps so)."""
        tc = self._traci
        tc.simulationStep()
        now = tc.simulation.getTime()
        self._spawn_background(now)
        self._record_sumo_events(self.t_s)
        return self.raw_snapshot()

    def cluster_vehicle_ids(self) -> list[str]:
        return list(self._meta)

    def antenna_heights_m(self) -> dict[str, float]:
        """Each cluster vehicle's antenna height above the road (the z of its vehicle type's
        ``antenna_lever_arm_m``), metres."""
        return {v: float(m.lever_arm_m[2]) for v, m in self._meta.items()}

    def lane_geometry(self) -> tuple[dict[str, np.ndarray], dict[str, float]]:
        """Centre-line polylines (net XY) and widths (m) of every non-internal lane."""
        tc = self._traci
        ids = [lid for lid in tc.lane.getIDList() if not lid.startswith(":")]
        return (
            {lid: np.asarray(tc.lane.getShape(lid), dtype=float) for lid in ids},
            {lid: float(tc.lane.getWidth(lid)) for lid in ids},
        )


# --------------------------------------------------------------------------- compiled frame conversions
# The per-step conversions of all cluster vehicles: numpy on a few-element array costs ~1 us a
# call, and the conversion took a few dozen calls a step. Each kernel does, element for
# element, the arithmetic of the numpy formulation it replaces (same libm sin/cos, same
# operation order, no fused multiply-add), so the truth is the same to the last bit.

_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def _antenna_kernel(front, grid_az_deg, arms, origin_h_m):  # pragma: no cover - compiled
    """Antenna positions from SUMO's front-bumper positions ``front`` (n, 3) and grid angles.

    ``fwd = (sin a, cos a)``, ``left = (-cos a, sin a)`` (grid azimuth ``a``, clockwise from
    +y), ``antenna = front_bumper + fwd * arm_x + left * arm_y`` (body frame: x forward, y
    left), height ``z + arm_z`` above the net's origin, ``h = z + arm_z + origin_h`` above the
    ellipsoid. Returns ``(fwd (n, 2), antenna_xy (n, 2), antenna_z (n,), h (n,), probe_x (3n,),
    probe_y (3n,))``: the probes are the antennas, then 1 m east, then 1 m
    north of them (the points :func:`_enu_kernel` needs through the projection).
    """
    n = front.shape[0]
    fwd = np.empty((n, 2))
    ant = np.empty((n, 2))
    ant_z = np.empty(n)
    h = np.empty(n)
    px = np.empty(3 * n)
    py = np.empty(3 * n)
    for k in range(n):
        a = grid_az_deg[k] * (np.pi / 180.0)  # np.radians
        s, c = np.sin(a), np.cos(a)
        fwd[k, 0], fwd[k, 1] = s, c
        ant[k, 0] = front[k, 0] + s * arms[k, 0] + -c * arms[k, 1]
        ant[k, 1] = front[k, 1] + c * arms[k, 0] + s * arms[k, 1]
        ant_z[k] = front[k, 2] + arms[k, 2]
        h[k] = ant_z[k] + origin_h_m
        px[k], px[n + k], px[2 * n + k] = ant[k, 0], ant[k, 0] + 1.0, ant[k, 0] + 0.0
        py[k], py[n + k], py[2 * n + k] = ant[k, 1], ant[k, 1] + 0.0, ant[k, 1] + 1.0
    return fwd, ant, ant_z, h, px, py


@njit(**_JIT)
def _enu_kernel(lat3, lon3, h, fwd):  # pragma: no cover - compiled
    """ECEF of the antennas, the net-XY -> ENU Jacobian (n, 3, 2) and the ENU forward vectors.

    ``lat3``/``lon3`` (3n,): the geodetic antennas, then their 1 m east and 1 m north probes
    (:func:`_antenna_kernel`). ECEF as :func:`v2v.frames.geodetic_to_ecef`; Jacobian column j
    ``= R(lat, lon) (ecef(probe_j) - ecef)`` with ``R`` the ECEF -> ENU rotation
    (:func:`v2v.frames.ecef_to_enu_rotation`): it carries the grid convergence (rotation)
    and the projection's scale factor, so a net-XY vector maps to the true ENU vector
    (``azimuth = atan2(E, N)``); its linearization error over 1 m is ~1e-7 (Earth
    curvature). The 3-term rotation sums are added as numpy's ``einsum`` adds them here
    (terms 0 and 2 first), so the results equal the array formulation bit for bit.
    """
    n = h.shape[0]
    ecef3 = np.empty((3 * n, 3))
    for k in range(3 * n):
        hk = h[k % n]
        sin_lat = np.sin(lat3[k])
        nrad = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * (sin_lat * sin_lat))
        ecef3[k, 0] = (nrad + hk) * np.cos(lat3[k]) * np.cos(lon3[k])
        ecef3[k, 1] = (nrad + hk) * np.cos(lat3[k]) * np.sin(lon3[k])
        ecef3[k, 2] = (nrad * (1.0 - WGS84_E2) + hk) * sin_lat
    jac = np.empty((n, 3, 2))
    fwd_enu = np.empty((n, 3))
    rot = np.zeros((3, 3))
    for k in range(n):
        sl, cl, so, co = np.sin(lat3[k]), np.cos(lat3[k]), np.sin(lon3[k]), np.cos(lon3[k])
        rot[0, 0], rot[0, 1] = -so, co
        rot[1, 0], rot[1, 1], rot[1, 2] = -sl * co, -sl * so, cl
        rot[2, 0], rot[2, 1], rot[2, 2] = cl * co, cl * so, sl
        for j in range(2):
            p = (j + 1) * n + k
            d0, d1, d2 = ecef3[p, 0] - ecef3[k, 0], ecef3[p, 1] - ecef3[k, 1], ecef3[p, 2] - ecef3[k, 2]
            for i in range(3):
                jac[k, i, j] = (rot[i, 0] * d0 + rot[i, 2] * d2) + rot[i, 1] * d1
        for i in range(3):
            fwd_enu[k, i] = jac[k, i, 0] * fwd[k, 0] + jac[k, i, 1] * fwd[k, 1]
    return ecef3[:n], jac, fwd_enu


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())[:300]
