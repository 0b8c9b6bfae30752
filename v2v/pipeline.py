"""Builders from scenario sections to sensor / filter objects, and the per-solution
processing of one synthesized measurement stream.

Randomness: one ``numpy.random.SeedSequence(seed)`` per run, spawned into child streams
by fixed index (0 traffic/background, 1 GNSS, 2 UWB, 3 bearing, 4 V2V exchange, 5 faults), and the
same seed handed to SUMO's ``--seed``. The same seed therefore gives bit-identical outputs,
and changing one component's settings leaves the other components' draws unchanged.

Every solution processes the *same* measurements (and the same exchange losses).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from v2v.config.scenario import Scenario
from v2v.config.sections import SolutionSection
from v2v.errors import UserError
from v2v.estimation.filter import (
    KIND_BEARING,
    KIND_SD_PR,
    KIND_SD_PR_PAIR,
    KIND_UWB,
    ClusterEkf,
    FilterConfig,
    MeasurementNoiseConfig,
    UpdateInfo,
)
from v2v.estimation.layout import StateLayout
from v2v.estimation.phase import PhaseConfig, wrong_fix
from v2v.estimation.process import ProcessNoiseConfig
from v2v.exchange import Message, V2VExchange
from v2v.frames import ecef_to_enu, ecef_to_enu_rotation
from v2v.metrics.errors import lead_frame_errors, lead_frame_rotation
from v2v.sensors.measurements import Bearings, GnssEpoch, UwbRanges
from v2v.traffic.snapshot import TrafficStep

LEAVE_AFTER_S = 5.0  # a vehicle the lead has not heard from for this long has left the cluster

STREAM_TRAFFIC, STREAM_GNSS, STREAM_UWB, STREAM_BEARING, STREAM_EXCHANGE, STREAM_FAULTS = range(6)
N_STREAMS = 6


def child_seeds(seed: int) -> list[np.random.SeedSequence]:
    return np.random.SeedSequence(seed).spawn(N_STREAMS)


# --------------------------------------------------------------------------- sensors


def build_ephemeris(scenario: Scenario, gps_start_s: float, base_dir: Path | None = None):
    sec = scenario.sensors.gnss
    if sec.ephemeris == "nominal":
        from v2v.sensors.gnss.constellation import NominalConstellation

        return NominalConstellation(gps_start_s)
    from v2v.sensors.gnss.rinex import read_rinex_nav

    path = Path(sec.ephemeris)
    if not path.is_absolute() and base_dir is not None:
        path = base_dir / path
    if not path.is_file():
        raise UserError(f"RINEX navigation file {str(path)!r} not found", field="sensors.gnss.ephemeris",
                        fix='give an existing RINEX 2/3 nav file, or "nominal"')
    eph = read_rinex_nav(path)
    lo, hi = eph.validity()
    end = gps_start_s + scenario.duration_s
    if gps_start_s < lo or end > hi:
        from v2v.sensors.gnss.time import gps_s_to_utc

        raise UserError(
            f"the run ({gps_s_to_utc(gps_start_s):%Y-%m-%d %H:%M:%S} UTC + {scenario.duration_s:.0f} s) is outside "
            f"the ephemeris ({gps_s_to_utc(lo):%Y-%m-%d %H:%M} to {gps_s_to_utc(hi):%H:%M} UTC)",
            field="start_utc", fix="pick a start time inside the navigation file's span",
        )
    return eph


def build_gnss(scenario: Scenario, gps_start_s: float, seed: np.random.SeedSequence, occlusion, georef,
               base_dir: Path | None = None):
    from v2v.sensors.gnss.atmosphere import IonosphereConfig, SatelliteErrorConfig, TroposphereConfig
    from v2v.sensors.gnss.clock import OCXO, TCXO, ClockConfig
    from v2v.sensors.gnss.errors import GnssErrorConfig, MultipathConfig, TrackingConfig
    from v2v.sensors.gnss.receiver import GnssReceiverConfig, GnssSynthesizer

    sec = scenario.sensors.gnss
    e = sec.errors
    errors = GnssErrorConfig(
        clock=ClockConfig(enabled=e.receiver_clock, oscillator=TCXO if sec.oscillator == "TCXO" else OCXO),
        iono=IonosphereConfig(enabled=e.ionosphere),
        tropo=TroposphereConfig(enabled=e.troposphere),
        satellite=SatelliteErrorConfig(orbit_enabled=e.satellite_orbit, clock_enabled=e.satellite_clock),
        multipath=MultipathConfig(enabled=e.multipath),
        tracking=TrackingConfig(noise_enabled=e.noise, foliage_enabled=e.foliage, nlos_enabled=e.nlos),
    )
    cfg = GnssReceiverConfig(rate_hz=sec.rate_hz, elevation_mask_rad=float(np.radians(sec.elevation_mask_deg)), errors=errors)
    eph = build_ephemeris(scenario, gps_start_s, base_dir)
    return GnssSynthesizer(eph, cfg, seed, gps_start_s, occlusion=occlusion, georef=georef if occlusion is not None else None)


def build_uwb(scenario: Scenario, vehicle_ids: Sequence[str], seed: np.random.SeedSequence):
    from v2v.sensors.uwb import UwbNetwork

    sec = scenario.sensors.uwb
    pairs: Any = "all" if sec.pairs == "all" else [tuple(p) for p in sec.pairs]
    return UwbNetwork(vehicle_ids=vehicle_ids, rng=np.random.default_rng(seed.spawn(1)[0]), profile=sec.profile,
                      vehicle_profiles=dict(sec.vehicle_profiles) or None, pairs=pairs)


def build_bearing(scenario: Scenario):
    from v2v.sensors.bearing import BearingSensor

    sec = scenario.sensors.bearing
    return BearingSensor(
        sigma_rad=float(np.radians(sec.sigma_deg)),
        field_of_view_rad=float(np.radians(sec.field_of_view_deg)),
        max_range_m=sec.max_range_m,
        rate_hz=sec.rate_hz,
        azimuth_sigma_rad=float(np.radians(sec.azimuth_sigma_deg)),
        measuring="all" if sec.measuring == "all" else tuple(sec.measuring),
    )


# --------------------------------------------------------------------------- filters


def build_filter(sol: SolutionSection, lead: str, vehicles: Sequence[str], bearing_vehicles: Sequence[str],
                 uwb_pairs: Sequence[tuple[str, str]]) -> ClusterEkf:
    """The production EKF for one solution."""
    az = tuple(bearing_vehicles) if sol.azimuth == "estimated" else ()
    pairs = tuple(uwb_pairs) if sol.uwb_error_states else ()
    layout = StateLayout.build(lead=lead, vehicles=tuple(vehicles), azimuth_vehicles=az, uwb_pairs=pairs,
                               azimuth_rates=sol.yaw_rate_sigma_deg_s > 0.0)
    cfg = FilterConfig(
        process=ProcessNoiseConfig(
            vel_tau_s=sol.velocity_tau_s,
            vel_sigma_horizontal_mps=sol.velocity_sigma_horizontal_mps,
            vel_sigma_vertical_mps=sol.velocity_sigma_vertical_mps,
            drift_tau_s=sol.clock_drift_tau_s,
            drift_sigma_mps=sol.clock_drift_sigma_mps,
            azimuth_rw_rad_per_sqrt_s=float(np.radians(sol.azimuth_rw_deg_per_sqrt_s)),
            yaw_rate_sigma_rps=float(np.radians(sol.yaw_rate_sigma_deg_s)),
            yaw_rate_tau_s=sol.yaw_rate_tau_s,
        ),
        noise=MeasurementNoiseConfig(
            pseudorange_sigma_m=sol.pseudorange_sigma_m,
            doppler_sigma_mps=sol.doppler_sigma_mps,
            uwb_sigma_m=sol.uwb_sigma_m,
            bearing_sigma_rad=float(np.radians(sol.bearing_sigma_deg)),
        ),
        significance=sol.significance,
        use_uwb_bias_scale=sol.uwb_error_states,
        height_aiding_sigma_m=sol.height_aiding_sigma_m,
        phase=PhaseConfig(
            phase_sigma_m=sol.phase_sigma_m,
            elevation_mask_rad=float(np.radians(sol.phase_elevation_mask_deg)),
            resolve=sol.ambiguity_resolution,
            ar_min_success=sol.ar_min_success,
            ar_ratio=sol.ar_ratio,
        ) if sol.carrier_phase else None,
    )
    return ClusterEkf(layout, cfg)


# --------------------------------------------------------------------------- the stream


@dataclass(frozen=True)
class Event:
    """A batch of measurements with one time tag, as the lead's filter receives it."""

    t_s: float
    kind: str  # "gnss" | "uwb" | "bearing"
    gnss: dict[str, GnssEpoch] | None = None
    uwb: UwbRanges | None = None
    bearings: Bearings | None = None
    lead_base_ecef_m: np.ndarray | None = None


_KIND_RANK = {"gnss": 0, "uwb": 1, "bearing": 2}


def _subset_bearings(b: Bearings, idx: np.ndarray) -> Bearings:
    return Bearings(
        t_s=b.t_s[idx], a=tuple(b.a[i] for i in idx), b=tuple(b.b[i] for i in idx), bearing_rad=b.bearing_rad[idx],
        true_bearing_rad=b.true_bearing_rad[idx], azimuth_reported_rad=b.azimuth_reported_rad[idx],
        true_azimuth_rad=b.true_azimuth_rad[idx], los=b.los[idx],
    )


def exchange_stream(gnss_epochs: Sequence[tuple[float, dict[str, GnssEpoch]]], uwb: UwbRanges | None,
                    bearings: Bearings | None, exchange: V2VExchange, lead_base: Callable[[GnssEpoch], np.ndarray | None],
                    output_times: Sequence[float],
                    dropped: Callable[[str, float], bool] | None = None) -> tuple[list[Event], list[float]]:
    """Send every measurement through the V2V exchange and return the delivered events
    (time-tag order, GNSS before UWB before bearings at equal tags) and the output epochs.

    A UWB range travels with its initiator ``a``; a bearing with its measuring vehicle.
    """
    from v2v.sensors.uwb import select_ranges

    msgs: list[Message] = []
    for t, eps in gnss_epochs:
        msgs += [Message(t, v, "gnss", ep) for v, ep in eps.items()]
    if uwb is not None:
        msgs += [Message(float(uwb.t_s[k]), uwb.a[k], "uwb", k) for k in range(uwb.n)]
    if bearings is not None:
        msgs += [Message(float(bearings.t_s[k]), bearings.a[k], "bearing", k) for k in range(bearings.n)]
    if dropped is not None:
        msgs = [m for m in msgs if not dropped(m.sender, m.t_s)]
    msgs.sort(key=lambda m: (m.t_s, _KIND_RANK[m.kind]))
    delivered: list[Message] = []
    i = 0
    for now in list(output_times) + [np.inf]:
        while i < len(msgs) and msgs[i].t_s <= now + 1e-9:
            exchange.send(msgs[i])
            i += 1
        delivered += exchange.deliver(now if np.isfinite(now) else 1e18)
    delivered.sort(key=lambda m: (m.t_s, _KIND_RANK[m.kind]))
    events: list[Event] = []
    j = 0
    while j < len(delivered):
        m = delivered[j]
        k = j
        while k < len(delivered) and delivered[k].t_s == m.t_s and delivered[k].kind == m.kind:
            k += 1
        group = delivered[j:k]
        if m.kind == "gnss":
            eps = {g.sender: g.payload for g in group}
            base = lead_base(eps[exchange.lead_id]) if exchange.lead_id in eps else None
            events.append(Event(m.t_s, "gnss", gnss=eps, lead_base_ecef_m=base))
        elif m.kind == "uwb" and uwb is not None:
            for g in group:
                events.append(Event(m.t_s, "uwb", uwb=select_ranges(uwb, np.array([g.payload]))))
        elif m.kind == "bearing" and bearings is not None:
            events.append(Event(m.t_s, "bearing", bearings=_subset_bearings(bearings, np.array([g.payload for g in group]))))
        j = k
    return events, list(output_times)


# --------------------------------------------------------------------------- processing


@dataclass
class SolutionRecord:
    """Per-epoch estimates and per-update diagnostics of one solution."""

    name: str
    rows: dict[str, list[Any]] = field(default_factory=dict)
    membership: list[tuple[float, str, str]] = field(default_factory=list)  # (t_s, vehicle, left|joined)
    counters: dict[str, int] = field(default_factory=dict)  # the filter's event counters at the end
    updates: dict[str, list[Any]] = field(default_factory=lambda: {"t_s": [], "kind": [], "vehicles": [], "prn": [], "nis": [], "accepted": [], "faulty": []})

    def add_row(self, row: dict[str, Any]) -> None:
        if not self.rows:
            self.rows = {k: [] for k in row}
        n = len(next(iter(self.rows.values())))
        for k in row:
            if k not in self.rows:  # a column that appears later (e.g. after a vehicle rejoined)
                self.rows[k] = [float("nan")] * n
        for k, col in self.rows.items():
            col.append(row.get(k, float("nan")))


def _faulty(info: UpdateInfo, ev: Event) -> bool:
    """Did the simulator corrupt this measurement beyond the filter's model (NLOS or an injected fault)?"""
    if info.kind in (KIND_SD_PR, KIND_SD_PR_PAIR) and ev.gnss is not None:
        for v in info.vehicles:
            ep = ev.gnss.get(v)
            if ep is None:
                continue
            hit = np.flatnonzero(ep.prn == info.prn)
            if hit.size and (not bool(ep.los[hit[0]]) or ep.errors_m.get("fault", np.zeros(ep.n))[hit[0]] != 0.0):
                return True
        return False
    if info.kind == KIND_UWB and ev.uwb is not None:
        return not bool(ev.uwb.los[0]) or float(ev.uwb.errors_m.get("fault", np.zeros(1))[0]) != 0.0
    if info.kind == KIND_BEARING and ev.bearings is not None:
        return not bool(np.all(ev.bearings.los))
    return False


def run_solution(sol: SolutionSection, ekf: ClusterEkf, events: Sequence[Event], output_times: Sequence[float],
                 truth_at: Callable[[float], TrafficStep | None], lead: str, vehicles: Sequence[str],
                 on_epoch: Callable[[float, str, ClusterEkf, TrafficStep, list[dict[str, Any]]], None] | None = None) -> SolutionRecord:
    """Filter the delivered events with one solution and record an estimate at every output epoch.

    Output epochs are the GNSS epoch grid (they continue through GNSS outages). In an
    output interval with no usable GNSS, a solution with ``height_aiding_sigma_m`` adds the
    "relative up = 0" pseudo-measurement once, before its UWB and bearing updates (UWB and
    bearings carry no vertical information; see ``FilterConfig.height_aiding_sigma_m``).
    """
    rec = SolutionRecord(sol.name)
    use = set(sol.sensors)
    t_filter: float | None = None
    ei = 0
    pending: list[UpdateInfo] = []
    last_gnss: tuple[float, dict[str, GnssEpoch]] | None = None  # for the phase truth (wrong fixes)
    n_events = len(events)
    t_prev_out: float | None = None
    members = set(vehicles)
    last_heard: dict[str, float] = {}
    for t_out in output_times:
        # Cluster membership as the lead sees it: a vehicle silent for LEAVE_AFTER_S has left
        # (its block is marginalized out); its next GNSS message adds it back (re-initialized).
        for v in list(ekf.layout.vehicles):
            if t_out - last_heard.setdefault(v, t_out) > LEAVE_AFTER_S:
                ekf.remove_vehicle(v)
                rec.membership.append((t_out, v, "left"))
        has_gnss = True
        if sol.height_aiding_sigma_m is not None:  # look ahead only within this output interval
            has_gnss = False
            k = ei
            while k < n_events and events[k].t_s <= t_out + 1e-9:
                if events[k].kind == "gnss" and events[k].lead_base_ecef_m is not None:
                    has_gnss = True
                    break
                k += 1
        aided = False
        while ei < n_events and events[ei].t_s <= t_out + 1e-9:
            ev = events[ei]
            ei += 1
            # any message counts as "heard", whatever sensors this solution uses
            heard = (ev.gnss or {}).keys() if ev.kind == "gnss" else (
                set(ev.uwb.a) | set(ev.uwb.b) if ev.kind == "uwb" and ev.uwb is not None else
                set(ev.bearings.a) if ev.bearings is not None else set())
            for v in heard:
                last_heard[v] = ev.t_s
            if ev.kind not in use:
                continue
            if ev.kind == "gnss":
                for v in heard:
                    if v in members and v != lead and v not in ekf.layout.vehicles:
                        ekf.add_vehicle(v)
                        rec.membership.append((ev.t_s, v, "joined"))
            if t_filter is None:
                t_filter = ev.t_s
            ekf.predict(max(0.0, ev.t_s - t_filter))
            t_filter = max(t_filter, ev.t_s)
            infos = []
            if not has_gnss and not aided and sol.height_aiding_sigma_m is not None:
                infos += ekf.update_height_aiding(sol.height_aiding_sigma_m)
                aided = True
            if ev.kind == "gnss":
                if ev.lead_base_ecef_m is None:
                    continue
                infos = ekf.update_gnss(ev.gnss or {}, ev.lead_base_ecef_m)
                last_gnss = (ev.t_s, ev.gnss or {})
            elif ev.kind == "uwb":
                infos += ekf.update_uwb(ev.uwb)  # type: ignore[arg-type]
            else:
                infos += ekf.update_bearings(ev.bearings)  # type: ignore[arg-type]
            for info in infos:
                u = rec.updates
                u["t_s"].append(ev.t_s)
                u["kind"].append(info.kind)
                u["vehicles"].append(",".join(info.vehicles))
                u["prn"].append(info.prn)
                u["nis"].append(info.nis)
                u["accepted"].append(info.accepted)
                u["faulty"].append(_faulty(info, ev))
            pending += infos
        if t_filter is None:
            continue
        ekf.predict(max(0.0, t_out - t_filter))
        t_filter = max(t_filter, t_out)
        step = truth_at(t_out)
        if step is None or lead not in step.vehicles:
            pending = []
            continue
        rows = _epoch_rows(sol.name, t_out, ekf, step, lead, vehicles, pending)
        if ekf.config.phase is not None:
            # the status belongs to a GNSS epoch delivered in this output interval (t_prev_out, t_out]
            fresh = last_gnss is not None and (t_prev_out is None or last_gnss[0] > t_prev_out + 1e-9)
            _phase_columns(rows, ekf, last_gnss[1] if fresh and last_gnss is not None else None, lead)
        t_prev_out = t_out
        for r in rows:
            rec.add_row(r)
        if on_epoch is not None:
            on_epoch(t_out, sol.name, ekf, step, rows)
        pending = []
    rec.counters = dict(ekf.counters)
    return rec


def _epoch_rows(name: str, t_s: float, ekf: ClusterEkf, step: TrafficStep, lead: str, vehicles: Sequence[str],
                infos: Iterable[UpdateInfo]) -> list[dict[str, Any]]:
    lead_st = step.vehicles[lead]
    x, P = ekf.x, ekf.P
    lay = ekf.layout
    r_lead = lead_frame_rotation(lead_st.azimuth_rad)
    rows = []
    counts: dict[str, dict[str, int]] = {}
    for info in infos:
        for v in info.vehicles:
            c = counts.setdefault(v, {})
            key = ("used_" if info.accepted else "rejected_") + _short(info.kind)
            c[key] = c.get(key, 0) + 1
    for v in vehicles:
        st = step.vehicles.get(v)
        if st is None:
            continue
        if v not in lay.vehicles:  # left the cluster (as the lead sees it): a row without an estimate
            rows.append({"t_s": t_s, "solution": name, "vehicle": v, "initialized": False})
            continue
        true_rel = ecef_to_enu(st.ecef_m, lead_st.lat_rad, lead_st.lon_rad, lead_st.ecef_m)
        ready = ekf.is_initialized(v)
        sl = lay.position(v)
        est = x[sl]
        cov = P[sl, sl]
        err = lead_frame_errors(est, true_rel, lead_st.azimuth_rad)
        sig = np.sqrt(np.clip(np.diag(r_lead @ cov @ r_lead.T), 0.0, None))
        e_enu = est - true_rel
        nees = float(e_enu @ np.linalg.solve(cov, e_enu)) if ready else float("nan")
        c = counts.get(v, {})
        row = {
            "t_s": t_s, "solution": name, "vehicle": v, "initialized": ready,
            "true_e_m": true_rel[0], "true_n_m": true_rel[1], "true_u_m": true_rel[2],
            "est_e_m": est[0], "est_n_m": est[1], "est_u_m": est[2],
            "true_ve_mps": st.vel_enu_mps[0] - lead_st.vel_enu_mps[0],
            "true_vn_mps": st.vel_enu_mps[1] - lead_st.vel_enu_mps[1],
            "true_vu_mps": st.vel_enu_mps[2] - lead_st.vel_enu_mps[2],
            "est_ve_mps": x[lay.velocity(v)][0], "est_vn_mps": x[lay.velocity(v)][1], "est_vu_mps": x[lay.velocity(v)][2],
            "along_err_m": err[0], "across_err_m": err[1], "up_err_m": err[2],
            "sigma_along_m": sig[0], "sigma_across_m": sig[1], "sigma_up_m": sig[2],
            "cov_ee_m2": cov[0, 0], "cov_en_m2": cov[0, 1], "cov_nn_m2": cov[1, 1],
            "nees_pos": nees,
            "true_lane_index": st.lane_index, "lead_lane_index": lead_st.lane_index, "lane_width_m": st.lane_width_m,
        }
        for kind in ("pr", "doppler", "uwb", "bearing") + (("phase",) if ekf.config.phase is not None else ()):
            row[f"used_{kind}"] = c.get(f"used_{kind}", 0)
            row[f"rejected_{kind}"] = c.get(f"rejected_{kind}", 0)
        row["integrity_available"] = bool(getattr(ekf, "integrity_available", {}).get(v, False))
        if lay.has("azimuth", v):
            row["azimuth_err_rad"] = float(_wrap(ekf.azimuth_rad(v) - st.azimuth_rad)) if ekf.is_azimuth_initialized(v) else float("nan")
        rows.append(row)
    if lay.has("azimuth", lead):
        for r in rows:
            r["lead_azimuth_err_rad"] = float(_wrap(ekf.azimuth_rad(lead) - lead_st.azimuth_rad)) if ekf.is_azimuth_initialized(lead) else float("nan")
    return rows


def _phase_columns(rows: list[dict[str, Any]], ekf: ClusterEkf, gnss: dict[str, GnssEpoch] | None,
                   lead: str) -> None:
    """Ambiguity-resolution columns of a carrier-phase solution: ``phase_state`` (fixed /
    partial / float; "" without a GNSS epoch in this output interval), ``n_dd``, ``n_fixed``,
    ``ar_ratio``, ``ar_success_rate`` and ``wrong_fix`` (a fixed combination differs from the
    true integers: the simulator knows them; NaN when nothing is fixed)."""
    for r in rows:
        if "est_e_m" not in r:
            continue
        st = ekf.phase_status.get(r["vehicle"]) if gnss is not None else None
        if st is None:
            r.update(phase_state="", n_dd=0, n_eligible=0, n_fixed=0, ar_ratio=float("nan"), ar_success_rate=float("nan"),
                     wrong_fix=float("nan"))
            continue
        wf = wrong_fix(st, gnss.get(r["vehicle"]), gnss.get(lead)) if gnss is not None else None
        r.update(phase_state=st.state, n_dd=st.n_dd, n_eligible=st.n_eligible, n_fixed=st.n_fixed, ar_ratio=st.ratio,
                 ar_success_rate=st.success_rate, wrong_fix=float("nan") if wf is None else float(wf))


def _wrap(a: float) -> float:
    from v2v.frames import wrap_angle

    return float(wrap_angle(a))


def _short(kind: str) -> str:
    return {"sd_pseudorange": "pr", "sd_pseudorange_pair": "pr", "sd_doppler": "doppler", "sd_phase": "phase"}.get(
        kind, kind)


def enu_rotation(lat_rad: float, lon_rad: float) -> np.ndarray:
    return ecef_to_enu_rotation(lat_rad, lon_rad)
