"""One run of the simulator: scenario in, run folder out.

Pipeline (streaming, one SUMO step at a time)::

    traffic (SUMO truth) -> sensors -> exchange -> estimation -> metrics -> outputs

Outputs in the run folder (the folder is built under a hidden temporary name and
renamed when complete, so an interrupted or failed run leaves nothing that looks whole):

* ``scenario.resolved.toml``: the fully layered scenario, enough to rerun it;
* ``truth.parquet``: one row per (time, vehicle): antenna position, velocity, azimuth, lane, edge;
* ``summary.json``: scenario name, seed, simulated and wall seconds, vehicles, events.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from v2v import __version__
from v2v.config.scenario import Scenario, save_resolved
from v2v.errors import UserError
from v2v.frames import GeoReference
from v2v.io.atomic import RunFolder, atomic_write_json, atomic_write_parquet
from v2v.io.tables import ParquetStream
from v2v.sensors.measurements import GnssEpoch
from v2v.traffic.snapshot import EventKind, TrafficStep


@dataclass(frozen=True, kw_only=True)
class ResolvedNetwork:
    net_path: Path
    poly_paths: tuple[Path, ...]
    route_edges: tuple[str, ...]
    georef: GeoReference


def resolve_network(scenario: Scenario) -> ResolvedNetwork:
    """Find (and build if needed) the scenario's net, its polygons, route and geo-reference."""
    from v2v import nets

    cfg = scenario.network
    built = nets.resolve_net({"name": cfg.name or None, "net_file": cfg.net_file or None})
    if cfg.route_edges:
        edges = tuple(cfg.route_edges)
    else:
        routes = built.routes or {}
        if cfg.route not in routes:
            raise UserError(
                f"the net has no route named {cfg.route!r} (it has: {', '.join(sorted(routes)) or 'none'})",
                field="network.route",
                fix="name one of its routes, or list edge ids in network.route_edges",
            )
        edges = tuple(routes[cfg.route])
    proj, offset, _ = nets.read_location(built.net_path)
    georef = GeoReference(
        proj=proj,
        net_offset_m=(float(offset[0]), float(offset[1])),
        origin_lat_deg=cfg.georef_lat_deg,
        origin_lon_deg=cfg.georef_lon_deg,
        origin_h_m=0.0,
    )
    if cfg.polygon_files:
        polys = tuple(Path(p) for p in cfg.polygon_files)
        for i, p in enumerate(polys):
            if not p.is_file():
                raise UserError(f"polygon file {str(p)!r} not found", field=f"network.polygon_files.{i}",
                                fix="give an existing SUMO .poly.xml/.add.xml, or leave the list empty")
    else:
        polys = (Path(built.poly_path),) if built.poly_path else ()
    return ResolvedNetwork(net_path=Path(built.net_path), poly_paths=polys, route_edges=edges, georef=georef)


TRUTH_COLUMNS = (
    "t_s", "vehicle", "cluster", "is_lead", "x_m", "y_m", "z_m", "lat_deg", "lon_deg", "h_m",
    "ecef_x_m", "ecef_y_m", "ecef_z_m", "vel_e_mps", "vel_n_mps", "vel_u_mps", "speed_mps",
    "accel_mps2", "azimuth_rad", "yaw_rate_rps", "front_x_m", "front_y_m", "edge", "lane",
    "lane_index", "lane_width_m", "lateral_offset_m", "length_m", "width_m", "height_m",
)


def _truth_rows(step: TrafficStep) -> dict[str, list[Any]]:
    cols: dict[str, list[Any]] = {k: [] for k in TRUTH_COLUMNS}
    for v in step.vehicles.values():
        vals = (
            step.t_s, v.vehicle_id, v.cluster, v.is_lead, v.xyz_m[0], v.xyz_m[1], v.xyz_m[2],
            float(np.degrees(v.lat_rad)), float(np.degrees(v.lon_rad)), v.h_m,
            v.ecef_m[0], v.ecef_m[1], v.ecef_m[2], v.vel_enu_mps[0], v.vel_enu_mps[1], v.vel_enu_mps[2],
            v.speed_mps, v.accel_mps2, v.azimuth_rad, v.yaw_rate_rps, v.front_bumper_xy_m[0],
            v.front_bumper_xy_m[1], v.edge_id, v.lane_id, v.lane_index, v.lane_width_m,
            v.lateral_offset_m, v.length_m, v.width_m, v.height_m,
        )
        for k, x in zip(TRUTH_COLUMNS, vals, strict=True):
            cols[k].append(float(x) if isinstance(x, np.floating) else x)
    return cols


@dataclass(frozen=True, kw_only=True)
class RunResult:
    out_dir: Path
    summary: dict[str, Any]


def _progress(total: int, quiet: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, disable=quiet or not sys.stderr.isatty(), leave=False)


def _say(quiet: bool, msg: str) -> None:
    if not quiet:
        print(msg, file=sys.stderr, flush=True)


def run_scenario(
    scenario: Scenario,
    out_dir: Path,
    *,
    quiet: bool = False,
    replay: bool = True,
    save_measurements: bool = False,
    base_dir: Path | None = None,
) -> RunResult:
    """Run one scenario end to end and write its run folder. Returns the summary.

    Stages (wall time of each is reported in ``summary.json`` under ``timing_s``):
    traffic (SUMO) -> world geometry -> sensors (GNSS, UWB, bearing) -> V2V exchange ->
    one EKF per (cluster, solution) on the same measurements -> metrics -> outputs.
    """
    import pandas as pd

    from v2v.exchange import V2VExchange
    from v2v.metrics.summary import json_safe, paper_table, solution_statistics
    from v2v.pipeline import (
        STREAM_BEARING,
        STREAM_EXCHANGE,
        STREAM_FAULTS,
        STREAM_GNSS,
        STREAM_UWB,
        build_bearing,
        build_filter,
        build_gnss,
        build_uwb,
        child_seeds,
        exchange_stream,
        run_solution,
    )
    from v2v.sensors.gnss.spp import spp_from_epoch
    from v2v.sensors.gnss.time import utc_to_gps_s
    from v2v.traffic.sumo import NetFiles, SumoSimulation
    from v2v.world.buildings import World, load_polygons
    from v2v.world.occlusion import OcclusionGeometry

    wall0 = time.perf_counter()
    timing: dict[str, float] = {}
    net = resolve_network(scenario)
    seeds = child_seeds(scenario.seed)
    gps_start = float(utc_to_gps_s(scenario.start_utc))
    n_steps = int(round(scenario.duration_s / scenario.step_length_s))
    events_log: list[dict[str, Any]] = []
    with RunFolder(Path(out_dir)) as tmp:
        save_resolved(scenario, tmp / "scenario.resolved.toml")

        # 1. traffic ------------------------------------------------------------------
        t0 = time.perf_counter()
        truth = ParquetStream(tmp / "truth.parquet")
        files = NetFiles(net_path=net.net_path, poly_paths=net.poly_paths, route_edges=net.route_edges)
        steps: list[TrafficStep] = []
        with SumoSimulation(scenario, files, net.georef, seed=scenario.seed) as sim:
            step = sim.snapshot()
            steps.append(step)
            truth.extend(_truth_rows(step))
            events_log.extend(_event_rows(step))
            vehicles = sim.cluster_vehicle_ids()
            lanes, lane_widths = sim.lane_geometry()
            with _progress(n_steps, quiet, f"SUMO {scenario.name}") as bar:
                for _ in range(n_steps):
                    step = sim.step()
                    events_log.extend(_event_rows(step))
                    if not step.vehicles:
                        break  # every cluster vehicle has arrived
                    steps.append(step)
                    truth.extend(_truth_rows(step))
                    bar.update(1)
            stats = sim.stats
        truth.close()
        t_end = steps[-1].t_s
        timing["traffic"] = time.perf_counter() - t0

        # 2. world --------------------------------------------------------------------
        t0 = time.perf_counter()
        world = load_polygons(list(net.poly_paths)) if net.poly_paths else World()
        occlusion = OcclusionGeometry(world)
        timing["world"] = time.perf_counter() - t0

        # 3. sensors ------------------------------------------------------------------
        used = {s for sol in scenario.solutions for s in sol.sensors}
        if save_measurements:  # a user saving measurements wants every enabled sensor's
            used |= {name for name in ("uwb", "bearing") if getattr(scenario.sensors, name).enabled}
        t0 = time.perf_counter()
        _say(quiet, f"synthesizing measurements for {len(vehicles)} vehicles over {t_end:.1f} s ...")
        gnss = build_gnss(scenario, gps_start, seeds[STREAM_GNSS], occlusion, net.georef, base_dir)
        gnss_epochs: list[tuple[float, dict[str, GnssEpoch]]] = []
        for st in steps:
            for eps in gnss.feed(st):
                if eps:
                    t_e = next(iter(eps.values())).t_s
                    gnss_epochs.append((t_e, eps))
        timing["gnss"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        uwb = None
        if "uwb" in used:
            network = build_uwb(scenario, vehicles, seeds[STREAM_UWB])
            uwb = network.simulate(steps, np.random.default_rng(seeds[STREAM_UWB].spawn(2)[1]), occlusion=occlusion)
        timing["uwb"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        bearings = None
        if "bearing" in used:
            bearings = build_bearing(scenario).simulate(steps, np.random.default_rng(seeds[STREAM_BEARING]), occlusion=occlusion)
        timing["bearing"] = time.perf_counter() - t0
        # Output epochs: the GNSS grid as synthesized, before faults (so they continue through outages).
        grid_times = [t for t, _ in gnss_epochs]
        fault_log = None
        if scenario.faults:
            from v2v.faults import FaultLog, apply_bearing_faults, apply_gnss_faults, apply_uwb_faults

            fault_log = FaultLog()
            frng = np.random.default_rng(seeds[STREAM_FAULTS])
            gnss_epochs = apply_gnss_faults(gnss_epochs, list(scenario.faults), frng, fault_log)
            uwb = apply_uwb_faults(uwb, list(scenario.faults), frng, fault_log)
            bearings = apply_bearing_faults(bearings, list(scenario.faults), frng, fault_log)
        if save_measurements:
            t0 = time.perf_counter()
            from v2v.io.measurements import measurements_table

            atomic_write_parquet(tmp / "measurements.parquet", measurements_table(gnss_epochs, uwb, bearings))
            timing["measurements_io"] = time.perf_counter() - t0

        # 4-5. exchange and estimation, per cluster -----------------------------------
        truth_by_t = {round(st.t_s * 1e6): st for st in steps}

        def truth_at(t: float) -> TrafficStep | None:
            return truth_by_t.get(round(t * 1e6))

        logger = _make_logger(tmp, replay)
        t0 = time.perf_counter()
        with logger:
            logger.log_world(lanes, lane_widths, world.buildings, world.foliage, net.georef)
            _log_truth_and_links(logger, steps, uwb, bearings, gnss_epochs)
            timing["replay_static_truth"] = time.perf_counter() - t0
            records = []
            updates: dict[str, pd.DataFrame] = {}
            membership: dict[str, list[dict[str, Any]]] = {}
            filter_counters: dict[str, dict[str, int]] = {}
            t0 = time.perf_counter()
            on_epoch = _epoch_logger(logger, net.georef) if replay else None
            n_filters = len(scenario.clusters) * len(scenario.solutions)
            _say(quiet or n_filters == 0, f"filtering: {len(scenario.solutions)} solution(s) x {len(scenario.clusters)} cluster(s) ...")
            fbar = _progress(n_filters, quiet, "filters")
            for ci, cluster in enumerate(scenario.clusters):
                lead = f"{cluster.name}.{cluster.lead}"
                members = [f"{cluster.name}.{i}" for i in range(cluster.vehicles)]
                others = [v for v in members if v != lead]
                exch = V2VExchange(scenario.exchange, lead, np.random.default_rng(seeds[STREAM_EXCHANGE].spawn(ci + 1)[ci]))
                base_state: dict[str, Any] = {"x": None}

                def lead_base(ep: GnssEpoch, _s=base_state) -> np.ndarray | None:
                    res = spp_from_epoch(ep, x0_ecef_m=_s["x"], gps_start_s=gps_start)
                    if res.valid:
                        _s["x"] = res.position_ecef_m
                    return _s["x"]

                cl_epochs = [(t, {v: e for v, e in eps.items() if v in members}) for t, eps in gnss_epochs]
                output_times = [t for t in grid_times if (st := truth_at(t)) is not None and lead in st.vehicles]
                dropped = None
                if scenario.faults:
                    from v2v.faults import message_dropped

                    faults = list(scenario.faults)

                    def dropped(sender: str, t: float, _f=faults) -> bool:
                        return message_dropped(_f, sender, t)

                events, _ = exchange_stream(cl_epochs, uwb, bearings, exch, lead_base, output_times, dropped)
                bearing_vehicles = members if scenario.sensors.bearing.measuring == "all" else [
                    v for v in scenario.sensors.bearing.measuring if v in members]
                uwb_pairs = _uwb_pairs(scenario, members)
                for sol in scenario.solutions:
                    ekf = build_filter(sol, lead, others, bearing_vehicles, uwb_pairs)
                    rec = run_solution(sol, ekf, events, output_times, truth_at, lead, others, on_epoch=on_epoch)
                    if rec.rows:
                        df = pd.DataFrame(rec.rows)
                        df.insert(1, "cluster", cluster.name)
                        records.append(df)
                    key = sol.name if len(scenario.clusters) == 1 else f"{cluster.name}/{sol.name}"
                    updates[key] = pd.DataFrame(rec.updates)
                    filter_counters[key] = rec.counters
                    if rec.membership:
                        membership[key] = [{"t_s": t, "vehicle": v, "change": c} for t, v, c in rec.membership]
                    fbar.update(1)
                exchange_stats = exch.stats
            fbar.close()
            timing["estimation"] = time.perf_counter() - t0
        epochs = pd.concat(records, ignore_index=True) if records else pd.DataFrame()
        # Memory: the whole-run inputs (SUMO steps, GNSS epochs, UWB/bearing records, the
        # exchange's delivered events) are not needed by the metrics: reduce them to their
        # summary numbers now and free them before the metrics build their tables.
        n_gnss_epochs = len(gnss_epochs)
        n_sats = [ep.n for _, eps in gnss_epochs for ep in eps.values()]
        nlos = sum(int((~ep.los).sum()) for _, eps in gnss_epochs for ep in eps.values())
        uwb_summary = _uwb_summary(uwb)
        n_bearings = int(bearings.n) if bearings is not None else 0
        records.clear()
        steps.clear()
        truth_by_t.clear()
        gnss_epochs = cl_epochs = events = uwb = bearings = rec = ekf = None  # noqa: F841 (released)

        # 6. metrics and outputs -------------------------------------------------------
        t0 = time.perf_counter()
        lane_records: list[dict[str, Any]] = []
        if len(epochs):
            atomic_write_parquet(tmp / "epochs.parquet", epochs)
            sol_stats = solution_statistics(epochs, updates)
            from v2v.metrics.lane import lane_level_table

            lane_records = lane_level_table(epochs, pd.read_parquet(tmp / "truth.parquet")).to_dict("records")
        else:
            sol_stats = {}
        timing["metrics_io"] = time.perf_counter() - t0
        wall = time.perf_counter() - wall0
        counts = {k.value: sum(1 for e in events_log if e["kind"] == k.value) for k in EventKind}
        summary: dict[str, Any] = {
            "v2v_version": __version__,
            "scenario": scenario.name,
            "seed": scenario.seed,
            "network": net.net_path.name,
            "simulated_s": round(t_end, 6),
            "requested_s": scenario.duration_s,
            "wall_s": round(wall, 3),
            "real_time_factor": round(t_end / wall, 2) if wall > 0 else None,
            "timing_s": {k: round(v, 3) for k, v in timing.items()},
            "warmup_s": stats.warmup_s,
            "vehicles": vehicles,
            "leads": [f"{c.name}.{c.lead}" for c in scenario.clusters],
            "solutions": [s.name for s in scenario.solutions],
            "gnss": {
                "epochs": n_gnss_epochs,
                "satellites_tracked_mean": float(np.mean(n_sats)) if n_sats else 0.0,
                "nlos_fraction": nlos / max(sum(n_sats), 1),
            },
            "uwb": uwb_summary,
            "bearing": {"measurements": n_bearings},
            "exchange": {"sent": exchange_stats.sent, "lost": exchange_stats.lost, "late": exchange_stats.late}
            if scenario.clusters else {},
            "event_counts": counts,
            "faults_injected": fault_log.counts if fault_log is not None else {},
            "events": events_log[:1000],
            "truth_rows": truth.rows_written,
            "statistics": sol_stats,
            "lane_level": lane_records,
            "filter_membership": membership,
            "filter_counters": filter_counters,  # e.g. clock_jump_detected, divergence_reset, nonfinite_*  # vehicles the lead's filter dropped (silent) and re-added
        }
        if t_end + 1e-9 < scenario.duration_s - scenario.step_length_s:
            summary["note"] = f"all cluster vehicles reached the end of the route at t = {t_end:.1f} s"
        summary["table"] = paper_table(sol_stats) if sol_stats else ""
        atomic_write_json(tmp / "summary.json", json_safe(summary))
    return RunResult(out_dir=Path(out_dir), summary=summary)


def _event_rows(step: TrafficStep) -> list[dict[str, Any]]:
    return [{"t_s": e.t_s, "kind": e.kind.value, "vehicle": e.vehicle_id, "detail": e.detail} for e in step.events]


def _uwb_pairs(scenario: Scenario, members: list[str]) -> list[tuple[str, str]]:
    from itertools import combinations

    sec = scenario.sensors.uwb
    if sec.pairs == "all":
        return list(combinations(members, 2))
    return [(a, b) for a, b in sec.pairs if a in members and b in members]


def _uwb_summary(uwb) -> dict[str, Any]:
    if uwb is None or uwb.n == 0:
        return {"ranges": 0}
    err = uwb.range_m - uwb.true_range_m
    nlos = ~uwb.los
    return {
        "ranges": int(uwb.n),
        "nlos_fraction": float(nlos.mean()),
        "error_mean_m": float(err.mean()),
        "error_std_m": float(err.std()),
        "nlos_error_mean_m": float(err[nlos].mean()) if nlos.any() else None,
    }


def _make_logger(folder: Path, replay: bool):
    if not replay:
        from v2v.viz.logger import NullLogger

        return NullLogger()
    from v2v.viz.rerun_logger import RerunReplayLogger

    return RerunReplayLogger(folder / "replay.rrd")


def _log_truth_and_links(logger, steps, uwb, bearings, gnss_epochs) -> None:
    from v2v.viz.logger import NullLogger

    if isinstance(logger, NullLogger):
        return
    # records in time order, so each step's window is a searchsorted slice (not a scan of the run)
    series = []
    for kind, meas in (("uwb", uwb), ("bearing", bearings)):
        if meas is not None and meas.n:
            order = np.argsort(meas.t_s, kind="stable")
            series.append((kind, meas, order, meas.t_s[order]))
    sky_every = {round(t * 1e6): eps for t, eps in gnss_epochs if abs(t - round(t)) < 1e-6}  # 1 Hz sky plots
    prev = -np.inf
    for st in steps:
        logger.log_truth(st.t_s, st)
        for kind, meas, order, tt in series:
            lo, hi = np.searchsorted(tt, prev, side="right"), np.searchsorted(tt, st.t_s + 1e-9, side="right")
            idx = [int(k) for k in order[lo:hi] if meas.a[k] in st.vehicles and meas.b[k] in st.vehicles]
            if idx:
                a = np.array([st.vehicles[meas.a[k]].xyz_m for k in idx])
                b = np.array([st.vehicles[meas.b[k]].xyz_m for k in idx])
                logger.log_links(st.t_s, kind, a, b, ["los" if meas.los[k] else "nlos" for k in idx])
        eps = sky_every.get(round(st.t_s * 1e6))
        if eps:
            for v, ep in eps.items():
                logger.log_satellites(st.t_s, v, ep.prn, ep.azimuth_rad, ep.elevation_rad, ep.los)
        prev = st.t_s


def _epoch_logger(logger, georef: GeoReference):
    """Callback logging each solution's estimates (net XY, around the lead's true antenna) and errors."""
    cache: dict[str, float] = {}

    def on_epoch(t_s: float, solution: str, ekf, step: TrafficStep, rows: list[dict[str, Any]]) -> None:
        lead = ekf.layout.lead
        lst = step.vehicles[lead]
        if "gamma" not in cache:
            cache["gamma"] = georef.grid_convergence_rad(float(lst.xyz_m[0]), float(lst.xyz_m[1]))
        g = cache["gamma"]
        c, s = np.cos(g), np.sin(g)
        ids, xy, cov = [], [], []
        for r in rows:
            if not r["initialized"]:
                continue
            e, n = r["est_e_m"], r["est_n_m"]
            ids.append(r["vehicle"])
            xy.append([lst.xyz_m[0] + e * c - n * s, lst.xyz_m[1] + e * s + n * c])
            cov.append([[r["cov_ee_m2"], r["cov_en_m2"]], [r["cov_en_m2"], r["cov_nn_m2"]]])
            logger.log_errors(t_s, solution, r["vehicle"], r["along_err_m"], r["across_err_m"], r["sigma_along_m"],
                              r["sigma_across_m"], r["nees_pos"], float("nan"), int(r["used_pr"]),
                              int(r["rejected_pr"] + r["rejected_uwb"] + r["rejected_bearing"] + r["rejected_doppler"]))
        if ids:
            logger.log_estimates(t_s, solution, ids, np.array(xy), np.array(cov))

    return on_epoch
