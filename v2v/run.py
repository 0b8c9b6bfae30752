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

import json
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
from v2v.io.atomic import RunFolder, atomic_write_json
from v2v.io.tables import ParquetStream
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
    built = nets.resolve_net(name=cfg.name or None, net_file=cfg.net_file or None, polygon_files=cfg.polygon_files)
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
    polys = tuple(Path(p) for p in built.poly_paths)
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


def _progress(total_steps: int, quiet: bool, desc: str):
    from tqdm import tqdm

    return tqdm(total=total_steps, desc=desc, unit="step", disable=quiet or not sys.stderr.isatty(), leave=False)


def run_scenario(scenario: Scenario, out_dir: Path, *, quiet: bool = False) -> RunResult:
    """Run one scenario end to end and write its run folder. Returns the summary."""
    from v2v.traffic.sumo import NetFiles, SumoSimulation

    wall0 = time.perf_counter()
    net = resolve_network(scenario)
    n_steps = int(round(scenario.duration_s / scenario.step_length_s))
    events: list[dict[str, Any]] = []
    with RunFolder(Path(out_dir)) as tmp:
        save_resolved(scenario, tmp / "scenario.resolved.toml")
        truth = ParquetStream(tmp / "truth.parquet")
        files = NetFiles(net_path=net.net_path, poly_paths=net.poly_paths, route_edges=net.route_edges)
        t_end = 0.0
        with SumoSimulation(scenario, files, net.georef, seed=scenario.seed) as sim:
            step = sim.snapshot()
            truth.extend(_truth_rows(step))
            vehicles = sim.cluster_vehicle_ids()
            with _progress(n_steps, quiet, f"v2v {scenario.name}") as bar:
                for _ in range(n_steps):
                    step = sim.step()
                    truth.extend(_truth_rows(step))
                    events.extend({"t_s": e.t_s, "kind": e.kind.value, "vehicle": e.vehicle_id, "detail": e.detail} for e in step.events)
                    bar.update(1)
                    t_end = step.t_s
                    if not step.vehicles:
                        break  # every cluster vehicle has arrived
            stats = sim.stats
        truth.close()
        wall = time.perf_counter() - wall0
        counts = {k.value: sum(1 for e in events if e["kind"] == k.value) for k in EventKind}
        summary = {
            "v2v_version": __version__,
            "scenario": scenario.name,
            "seed": scenario.seed,
            "network": str(net.net_path.name),
            "simulated_s": round(t_end, 6),
            "requested_s": scenario.duration_s,
            "wall_s": round(wall, 3),
            "real_time_factor": round(t_end / wall, 2) if wall > 0 else None,
            "warmup_s": stats.warmup_s,
            "vehicles": vehicles,
            "leads": [f"{c.name}.{c.lead}" for c in scenario.clusters],
            "event_counts": counts,
            "events": events[:1000],
            "truth_rows": truth.rows_written,
        }
        if t_end + 1e-9 < scenario.duration_s - scenario.step_length_s:
            summary["note"] = f"all cluster vehicles reached the end of the route at t = {t_end:.1f} s"
        atomic_write_json(tmp / "summary.json", json.loads(json.dumps(summary, default=float)))
    return RunResult(out_dir=Path(out_dir), summary=summary)
