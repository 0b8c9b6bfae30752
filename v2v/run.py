"""One run of the simulator: scenario in, run folder out.

Pipeline, streamed in chunks of simulated time (``DEFAULT_CHUNK_S``)::

    traffic (SUMO truth) -> sensors -> exchange -> estimation -> metrics -> outputs

Each chunk: SUMO advances, the sensors synthesize the chunk (random streams and states carry
over), the V2V exchange delivers it (messages in flight carry over), every solution's filter
(kept across chunks) consumes what is complete, and the rows go to disk; then the chunk's
objects are dropped. Memory does not grow with the run; outputs do not depend on the chunk
length.

Outputs in the run folder (the folder is built under a hidden temporary name and
renamed when complete, so an interrupted or failed run leaves nothing that looks whole):

* ``scenario.resolved.toml``: the fully layered scenario, enough to rerun it;
* ``truth.parquet``: one row per (time, vehicle): antenna position, velocity, azimuth, lane, edge;
* ``summary.json``: scenario name, seed, simulated and wall seconds, vehicles, events.
"""

from __future__ import annotations

import contextlib
import gc
import math
import shutil
import sys
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from v2v import __version__
from v2v.config.scenario import Scenario, save_resolved
from v2v.errors import UserError, check_interrupt, not_a_file
from v2v.exchange import ExchangeStats
from v2v.frames import GeoReference
from v2v.io.atomic import RunFolder, atomic_write_json, atomic_write_parquet
from v2v.io.tables import ParquetStream
from v2v.sensors.measurements import GnssEpoch
from v2v.traffic.snapshot import EventKind, TrafficStep

if TYPE_CHECKING:
    import pandas as pd


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
        known = nets.edge_ids(built.net_path)
        missing = [e for e in edges if e not in known]
        if missing:  # (what SUMO's set-up refuses too; here before it starts)
            raise UserError(f"route edge(s) {missing[:3]} are not in the net", field="network.route_edges",
                            fix=f"use edge ids of this net ({len(known)}: {', '.join(sorted(known)[:6])}"
                                f"{', ...' if len(known) > 6 else ''})")
    else:
        routes = built.routes or {}
        if cfg.route not in routes:
            raise UserError(
                f"the net has no route named {cfg.route!r} (it has: {', '.join(sorted(routes)) or 'none'})",
                field="network.route",
                fix="name one of its routes, or list edge ids in network.route_edges",
            )
        edges = tuple(routes[cfg.route])
        if not edges:  # (a net's automatic route: no edge there allows passenger cars; checked before SUMO starts)
            raise UserError(f"route {cfg.route!r} of the net has no edges (no edge of it allows passenger cars)",
                            field="network.route", fix="name a route of the net or set network.route_edges")
    proj, offset, _ = nets.read_location(built.net_path)
    georef = GeoReference(
        proj=proj,
        net_offset_m=(float(offset[0]), float(offset[1])),
        origin_lat_deg=cfg.georef_lat_deg,
        origin_lon_deg=cfg.georef_lon_deg,
        origin_h_m=cfg.origin_h_m,  # (net z = 0's height: xyz_to_ecef; the truth adds it itself)
    )
    if cfg.polygon_files:
        polys = tuple(Path(p) for p in cfg.polygon_files)
        for i, p in enumerate(polys):
            why = not_a_file(p) if cfg.polygon_files[i].strip() else "is empty"
            if why:
                raise UserError(f"polygon file {cfg.polygon_files[i]!r} {why}", field=f"network.polygon_files.{i}",
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
    """One truth row per vehicle of a step, as columns (Python scalars; degrees as ``np.degrees``)."""
    t = step.t_s
    rows = [
        (t, v.vehicle_id, v.cluster, v.is_lead, *v.xyz_m.tolist(), math.degrees(v.lat_rad), math.degrees(v.lon_rad),
         v.h_m, *v.ecef_m.tolist(), *v.vel_enu_mps.tolist(), v.speed_mps, v.accel_mps2, v.azimuth_rad, v.yaw_rate_rps,
         *v.front_bumper_xy_m.tolist(), v.edge_id, v.lane_id, v.lane_index, v.lane_width_m, v.lateral_offset_m,
         v.length_m, v.width_m, v.height_m)
        for v in step.vehicles.values()
    ]
    if not rows:
        return {k: [] for k in TRUTH_COLUMNS}
    return dict(zip(TRUTH_COLUMNS, map(list, zip(*rows, strict=True)), strict=True))


DEFAULT_CHUNK_S = 30.0  # simulated seconds per chunk (memory vs. per-chunk overhead; outputs do not depend on it)


# SUMO steps converted to truth together (SumoSimulation.convert): the per-call costs of the
# frame conversions spread over many steps, the transient arrays bounded (~0.3 MB per vehicle)
_CONVERT_STEPS = 256


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


_PROGRESS_EVERY_S = 10.0  # wall seconds between progress lines when stderr is not a terminal


class _ProgressLines:
    """Progress of a run whose stderr is not a terminal (a log file, CI, nohup: no tqdm bar
    there), one line after a chunk at most every :data:`_PROGRESS_EVERY_S` wall seconds:
    simulated time so far, wall time, and the remaining wall time at the pace of the chunks
    since the first (the first alone until there are more; a first chunk that held the kernels'
    compilation gives no estimate, and its line says so)."""

    def __init__(self, quiet: bool, name: str, duration_s: float, compiling: bool = False):
        self.on = not quiet and not sys.stderr.isatty()
        self.name, self.duration_s, self.compiling = name, duration_s, compiling
        self.t0 = self.last = time.perf_counter()
        self.first: tuple[float, float] | None = None  # (simulated s, wall s) at the end of the first chunk

    def chunk_done(self, t_s: float) -> None:
        now = time.perf_counter()
        wall = now - self.t0
        first = self.first
        if first is None:
            self.first = (t_s, wall)
        if not self.on or now - self.last < _PROGRESS_EVERY_S or not 0.0 < t_s < self.duration_s - 1e-6:
            return
        self.last = now
        if first is not None and t_s > first[0]:  # the pace since the first chunk
            pace = (wall - first[1]) / (t_s - first[0])
        else:
            pace = wall / t_s
        if first is None and self.compiling:  # that pace is the compilation's, not the run's
            to_go = "this includes compiling the kernels; the time to go follows after the next chunk"
        else:
            to_go = f"~{pace * max(self.duration_s - t_s, 0.0):.0f} s to go"
        print(f"{self.name}: {t_s:.0f} of {self.duration_s:.0f} s simulated, {wall:.0f} s wall, {to_go}",
              file=sys.stderr, flush=True)


def _fault_needs_whole_run(scenario: Scenario) -> str | None:
    """Why this scenario's faults cannot be streamed bit-identically (None: they can).

    ``v2v.faults`` draws a UWB / bearing fault's random numbers for the whole run at once
    (after every GNSS draw, from one stream), and a cycle slip's "first epoch" is remembered
    only within one call: such runs are processed as one chunk.
    """
    for f in scenario.faults:
        if f.kind == "uwb_blunder" or (f.kind == "nonfinite" and f.sensor in ("uwb", "bearing")) or f.kind == "cycle_slip":
            return f"fault {f.kind}"
    return None


@dataclass
class _ClusterRun:
    """The streaming state of one cluster: exchange, pending events / output epochs, one runner per solution."""

    name: str
    lead: str
    members: list[str]
    stream: Any  # pipeline.ExchangeStream
    runners: list[Any]  # pipeline.SolutionRunner, one per solution
    keys: list[str]
    parts: list[Path]
    events: list[Any]
    out_times: list[float]  # output epochs not yet filtered
    exchange: Any


@contextlib.contextmanager
def _gc_for_a_run() -> Iterator[None]:
    """Cyclic garbage collection tuned for one run, restored afterwards: the objects that
    exist before the run (imported modules, the scenario) are frozen out of the collector's
    scans, and the youngest generation is collected every 1 000 000 allocations (net of
    deallocations) instead of 700. A run allocates millions of small acyclic objects
    (measurement records, rows), and with the defaults the collector's passes over everything
    alive took ~15 % of a 20-vehicle run (benchmarks/bench_run.py); reference counting still
    frees them at once. Each pass visits the young objects still alive (what a chunk
    accumulates), so fewer passes cost less: every 50 000 allocations a 60 s run made 8 passes
    (~40 ms) at N = 20 and 18 (~94 ms) at N = 40, every 1 000 000 none. Cyclic garbage, the
    only thing a pass frees, is ~1,000 objects per simulated minute at N = 20 (counted with
    the collector off), so memory does not wait on it (bench_memory.py: flat either way)."""
    threshold = gc.get_threshold()
    gc.freeze()
    gc.set_threshold(1_000_000, max(threshold[1], 20), max(threshold[2], 100))
    try:
        yield
    finally:
        gc.set_threshold(*threshold)
        gc.unfreeze()


def absolute_paths(scenario: Scenario, base_dir: Path | None) -> Scenario:
    """The scenario with its relative file paths made absolute against ``base_dir`` (else the
    working directory); the built-in names ("nominal" ephemeris, empty net_file) are kept."""
    base = Path(base_dir) if base_dir is not None else Path.cwd()

    def absolute(p: str) -> str:
        return p if not p or Path(p).is_absolute() else str((base / p).resolve())

    net = scenario.network
    new_net = net.model_copy(update={"net_file": absolute(net.net_file),
                                     "polygon_files": [absolute(p) for p in net.polygon_files]})
    gnss = scenario.sensors.gnss
    new_gnss = gnss if gnss.ephemeris == "nominal" else gnss.model_copy(update={"ephemeris": absolute(gnss.ephemeris)})
    if new_net == net and new_gnss is gnss:
        return scenario
    sensors = scenario.sensors.model_copy(update={"gnss": new_gnss})
    return scenario.model_copy(update={"network": new_net, "sensors": sensors})


def check_scenario(scenario: Scenario, base_dir: Path | None = None) -> None:
    """Check, without running, what a run of ``scenario`` checks in its set-up beyond the
    scenario schema (which :func:`v2v.config.scenario.load_scenario` applies, the sensors' own
    rules among it: UWB radio types and pairs, the bearing sensor's values): the network, built
    from its sources if it is not yet (its route, the clusters' lanes on its first edge, its
    polygon files and their buildings), the
    sky (a RINEX file: present, readable, spanning the run) and the faults' PRNs (in that sky).
    Raises the :class:`UserError` the run would; ``base_dir`` as for :func:`run_scenario`.
    ``v2v scenario check`` and ``v2v sweep`` call it, so a study's bad value stops the study
    before any run instead of failing each one. Neither the filter nor a compiled sensor
    module is imported (a sweep's own process stays small)."""
    from v2v import nets
    from v2v.sensors.gnss.source import ephemeris_source
    from v2v.sensors.gnss.time import utc_to_gps_s
    from v2v.world.buildings import load_polygons

    scenario = absolute_paths(scenario, base_dir)
    net = resolve_network(scenario)
    nets.check_cluster_lanes(scenario.clusters, nets.lane_count(net.net_path, net.route_edges[0]))
    if net.poly_paths:
        load_polygons(list(net.poly_paths))
    eph = ephemeris_source(scenario.sensors.gnss.ephemeris, float(utc_to_gps_s(scenario.start_utc)), scenario.duration_s)
    check_min_satellites(scenario, eph.prns())
    if scenario.faults:
        from v2v.faults import check_fault_prns

        check_fault_prns(list(scenario.faults), eph.prns())


def check_min_satellites(scenario: Scenario, sky_prns) -> None:
    """UserError naming ``solutions.<i>.gnss_min_satellites`` when it exceeds the satellites
    of the run's sky (``sky_prns``: the ephemeris' PRNs, e.g. a RINEX file's): no epoch could
    then have that many in common with the lead, and the solution would use no GNSS at all.
    (The schema checks the nominal sky's 27; this is the same bound for a RINEX file.)"""
    n = len({int(p) for p in sky_prns})
    for i, sol in enumerate(scenario.solutions):
        if sol.gnss_min_satellites > n:
            raise UserError(f"{sol.gnss_min_satellites} satellites in common can never be met: the run's sky "
                            f"(sensors.gnss.ephemeris) has {n}, so every epoch's GNSS would be left out",
                            field=f"solutions.{i}.gnss_min_satellites",
                            fix=f"give 0 .. {n} (0: every SD is used)")


def run_scenario(
    scenario: Scenario,
    out_dir: Path,
    *,
    quiet: bool = False,
    replay: bool = True,
    save_measurements: bool = False,
    base_dir: Path | None = None,
    chunk_s: float | None = None,
) -> RunResult:
    """Run one scenario end to end and write its run folder. Returns the summary.

    The run is processed in chunks of ``chunk_s`` simulated seconds (default
    :data:`DEFAULT_CHUNK_S`; ``math.inf`` = one chunk): SUMO advances a chunk, the sensors
    synthesize it (their random streams and states continue across chunks), the V2V exchange
    delivers it (messages in flight carry over), every solution's filter (one per cluster,
    kept across chunks) consumes it, and its truth / epoch rows go to disk; then the chunk is
    dropped, so memory does not grow with the run (apart from the small per-run outputs). The
    outputs do not depend on ``chunk_s``. Runs with faults that draw random numbers for a
    whole sensor stream at once, or with ``save_measurements``, are one chunk (see
    :func:`_fault_needs_whole_run`).

    Relative file paths of the scenario (``network.net_file``, ``network.polygon_files``,
    ``sensors.gnss.ephemeris``) are relative to ``base_dir`` (the scenario file's folder; the
    working directory without one); the run uses, and saves in ``scenario.resolved.toml``,
    their absolute form, so the resolved scenario reruns from anywhere.

    Stage wall times (summed over chunks) are reported in ``summary.json`` under ``timing_s``.
    """
    scenario = absolute_paths(scenario, base_dir)
    with _gc_for_a_run():
        return _run_scenario(scenario, out_dir, quiet=quiet, replay=replay, save_measurements=save_measurements,
                             chunk_s=chunk_s)


def _run_scenario(scenario: Scenario, out_dir: Path, *, quiet: bool, replay: bool, save_measurements: bool,
                  chunk_s: float | None) -> RunResult:
    """:func:`run_scenario` (outside its garbage-collection settings)."""
    import pickle

    import pandas as pd

    import v2v.pipeline as pipeline  # run_solution via the module: tools may wrap it (experiments/fault_campaign.py)
    from v2v.exchange import V2VExchange
    from v2v.faults import check_fault_prns
    from v2v.metrics.summary import json_safe, paper_table, solution_statistics
    from v2v.pipeline import (
        STREAM_BEARING,
        STREAM_EXCHANGE,
        STREAM_FAULTS,
        STREAM_GNSS,
        STREAM_UWB,
        ExchangeStream,
        SolutionRunner,
        build_bearing,
        build_filter,
        build_gnss,
        build_uwb,
        child_seeds,
        empty_epochs_frame,
        kind_statistics_of,
    )
    from v2v.sensors.gnss.spp import SppChain
    from v2v.sensors.gnss.time import utc_to_gps_s
    from v2v.sensors.uwb import concat_ranges
    from v2v.traffic.sumo import NetFiles, RawStep, SumoSimulation
    from v2v.world.buildings import World, load_polygons
    from v2v.world.occlusion import OcclusionGeometry

    wall0 = time.perf_counter()
    # stages (wall s), disjoint. The replay's time is replay_static_truth (the calls logging truth,
    # links, sky) plus replay (world, estimates and errors, closing the file); the split is by call
    # site: buffered rows are encoded by whichever call sends them, mostly the close. The
    # estimates' logging is not in estimation. occlusion: the sensors' line-of-sight tests
    # (satellite rays, UWB and bearing links), taken out of gnss, uwb and bearing.
    timing: dict[str, float] = dict.fromkeys(("traffic", "world", "gnss", "uwb", "bearing", "occlusion",
                                              "replay_static_truth", "estimation", "replay", "metrics_io"), 0.0)
    net = resolve_network(scenario)
    seeds = child_seeds(scenario.seed)
    gps_start = float(utc_to_gps_s(scenario.start_utc))
    n_steps = int(round(scenario.duration_s / scenario.step_length_s))
    chunk = DEFAULT_CHUNK_S if chunk_s is None else float(chunk_s)
    if not chunk > 0.0:
        raise UserError(f"chunk length must be > 0 s, got {chunk_s!r}", field="chunk_s", fix="give a positive number of seconds")
    if save_measurements or _fault_needs_whole_run(scenario):
        chunk = math.inf
    events_log: list[dict[str, Any]] = []
    event_counts = {k.value: 0 for k in EventKind}
    filtered = {s for sol in scenario.solutions for s in sol.sensors}  # the sensors whose messages go to the lead
    used = set(filtered)  # the sensors synthesized
    if save_measurements:  # a user saving measurements wants every enabled sensor's
        used |= {name for name in ("uwb", "bearing") if getattr(scenario.sensors, name).enabled}
    with RunFolder(Path(out_dir)) as tmp:
        save_resolved(scenario, tmp / "scenario.resolved.toml")
        parts_dir = tmp / ".parts"
        parts_dir.mkdir()

        t0 = time.perf_counter()
        world = load_polygons(list(net.poly_paths)) if net.poly_paths else World()
        occlusion = OcclusionGeometry(world)
        timing["world"] += time.perf_counter() - t0

        truth = ParquetStream(tmp / "truth.parquet", batch_rows=10_000)  # also flushed at every chunk
        files = NetFiles(net_path=net.net_path, poly_paths=net.poly_paths, route_edges=net.route_edges)
        t0 = time.perf_counter()
        logger = _make_logger(tmp, replay)  # the recording's file and threads: the replay's time too
        if replay:
            timing["replay"] += time.perf_counter() - t0
        log_epochs = _epoch_logger(logger, net.georef, timing) if replay else None
        acc = _RunAccumulators()
        fault_log = None
        frng = None
        if scenario.faults:
            from v2v.faults import (
                FaultLog,
                apply_bearing_faults,
                apply_gnss_faults,
                apply_uwb_faults,
                dropping_fault,
            )

            fault_log = FaultLog()
            frng = np.random.default_rng(seeds[STREAM_FAULTS])
        measurements: list[Any] = []  # save_measurements (one chunk): (gnss epochs, uwb, bearings)
        n_filters = len(scenario.clusters) * len(scenario.solutions)
        with SumoSimulation(scenario, files, net.georef, seed=scenario.seed) as sim, logger:
            t0 = time.perf_counter()
            step = sim.snapshot()
            vehicles = sim.cluster_vehicle_ids()
            lanes, lane_widths = sim.lane_geometry()
            t1 = time.perf_counter()
            timing["traffic"] += t1 - t0
            logger.log_world(lanes, lane_widths, world.buildings, world.foliage, net.georef)
            if replay:  # (no replay: the stage stays 0, not the NullLogger's microseconds)
                timing["replay"] += time.perf_counter() - t1
            _say(quiet, f"{scenario.name}: {len(vehicles)} vehicles, {scenario.duration_s:.0f} s in chunks of "
                        f"{chunk if math.isfinite(chunk) else scenario.duration_s:.0f} s ...")
            _say(quiet or n_filters == 0, f"filtering: {len(scenario.solutions)} solution(s) x {len(scenario.clusters)} cluster(s)")
            from v2v.estimation import kernels

            compiling = n_filters > 0 and kernels.cache_missing()
            _say(quiet or not compiling,
                 "compiling the filter's kernels (numba): the first run on this machine takes about a minute longer")

            # sensors -------------------------------------------------------------------
            gnss = build_gnss(scenario, gps_start, seeds[STREAM_GNSS], occlusion, net.georef)
            check_min_satellites(scenario, gnss.eph.prns())
            if scenario.faults:
                check_fault_prns(list(scenario.faults), gnss.eph.prns())
            uwb_net = build_uwb(scenario, vehicles, seeds[STREAM_UWB]) if "uwb" in used else None
            uwb_rng = np.random.default_rng(seeds[STREAM_UWB].spawn(2)[1]) if uwb_net is not None else None
            uwb_stream = None
            bearing_stream = (build_bearing(scenario).stream(np.random.default_rng(seeds[STREAM_BEARING]), occlusion)
                              if "bearing" in used else None)

            # exchange and filters, per cluster ---------------------------------------------
            clusters: list[_ClusterRun] = []
            for ci, cluster in enumerate(scenario.clusters):
                lead = f"{cluster.name}.{cluster.lead}"
                members = [f"{cluster.name}.{i}" for i in range(cluster.vehicles)]
                others = [v for v in members if v != lead]
                exch = V2VExchange(scenario.exchange, lead, np.random.default_rng(seeds[STREAM_EXCHANGE].spawn(ci + 1)[ci]))
                lead_bases = SppChain(gps_start_s=gps_start).many  # each epoch's SPP from the last valid one

                dropped = None
                if scenario.faults:
                    fault_list = list(scenario.faults)

                    def dropped(sender: str, t: float, _f=fault_list, _lead=lead, _log=fault_log) -> bool:
                        i = dropping_fault(_f, sender, t, _lead)
                        if i is not None and _f[i].kind == "message_loss" and _log is not None:
                            _log.add(i, "message_loss")  # (a vehicle_leaves' removals are counted at its sensors)
                        return i is not None

                bearing_vehicles = members if scenario.sensors.bearing.measuring == "all" else [
                    v for v in scenario.sensors.bearing.measuring if v in members]
                uwb_pairs = _uwb_pairs(scenario, members)
                antenna_heights = {v: h for v, h in sim.antenna_heights_m().items() if v in members}
                runners, keys, parts = [], [], []
                for si, sol in enumerate(scenario.solutions):
                    ekf = build_filter(sol, lead, others, bearing_vehicles, uwb_pairs, antenna_heights)
                    runners.append(SolutionRunner(sol, ekf, lead, others))
                    runners[-1].rec.log.keep_recent = replay  # the replay's per-epoch NIS (log_epochs)
                    keys.append(sol.name if len(scenario.clusters) == 1 else f"{cluster.name}/{sol.name}")
                    parts.append(parts_dir / f"epochs_{ci}_{si}.pkl")
                clusters.append(_ClusterRun(name=cluster.name, lead=lead, members=members,
                                            stream=ExchangeStream(exch, lead_bases, dropped), runners=runners, keys=keys,
                                            parts=parts, events=[], out_times=[], exchange=exch))

            window: dict[int, TrafficStep] = {}  # truth steps still needed (by round(t * 1e6))
            replay_state = _ReplayState()
            chunk_steps: list[TrafficStep] = []

            def truth_at(t: float) -> TrafficStep | None:
                return window.get(round(t * 1e6))

            def process(final: bool) -> None:
                nonlocal uwb_stream, chunk_steps
                steps = chunk_steps
                chunk_steps = []
                # sensors
                t0, occ0 = time.perf_counter(), occlusion.time_s
                epochs: list[tuple[float, dict[str, GnssEpoch]]] = []
                for eps in gnss.feed_many(steps):  # the chunk's steps, synthesized together
                    if eps:
                        epochs.append((next(iter(eps.values())).t_s, eps))
                t0, occ0 = _sensor_stage(timing, "gnss", t0, occ0, occlusion)
                uwb = None
                if uwb_net is not None:
                    if uwb_stream is None:
                        t_first = steps[0].t_s if steps else 0.0
                        t_end = steps[-1].t_s if final and steps else round(t_first + n_steps * scenario.step_length_s, 6)
                        uwb_stream = uwb_net.stream(uwb_rng, occlusion=occlusion, t_start_s=t_first, t_end_s=t_end)
                    parts_u = [uwb_stream.push(steps)]
                    if final:
                        parts_u.append(uwb_stream.finish())
                    uwb = concat_ranges(parts_u)
                t0, occ0 = _sensor_stage(timing, "uwb", t0, occ0, occlusion)
                bearings = bearing_stream.push(steps) if bearing_stream is not None else None
                if final and bearing_stream is not None:
                    bearing_stream.finish()
                _sensor_stage(timing, "bearing", t0, occ0, occlusion)
                grid_times = [t for t, _ in epochs]  # output epochs: the GNSS grid before faults
                if fault_log is not None:
                    assert frng is not None  # (made with the fault log)
                    epochs = apply_gnss_faults(epochs, list(scenario.faults), frng, fault_log)
                    uwb = apply_uwb_faults(uwb, list(scenario.faults), frng, fault_log)
                    bearings = apply_bearing_faults(bearings, list(scenario.faults), frng, fault_log)
                # sensors.gnss.enabled = false (no solution: the scenario refuses one that would use it):
                # the receivers still run, as they set the output epochs, but nothing of theirs is reported
                reported = epochs if scenario.sensors.gnss.enabled else []
                if save_measurements:
                    measurements.append((reported, uwb, bearings))
                acc.add_sensors(reported, uwb, bearings)
                # the measurements are known up to: the last step (GNSS, bearings), the UWB horizon
                known = steps[-1].t_s if steps else -np.inf
                if uwb_stream is not None and not final:
                    known = min(known, uwb_stream.complete_until_s)
                # replay: truth, links and sky up to the known horizon
                t0 = time.perf_counter()
                replay_state.add(logger, steps, uwb, bearings, epochs)
                replay_state.flush(logger, np.inf if final else known)
                timing["replay_static_truth"] += time.perf_counter() - t0
                # exchange and filters (less the estimates' logging: log_epochs adds it to replay)
                t0 = time.perf_counter()
                replay_before = timing["replay"]
                for cl in clusters:
                    for t, eps in epochs:
                        cl.stream.add_gnss(t, {v: e for v, e in eps.items() if v in cl.members})
                    # only what a solution uses goes on the V2V link: the measurements saved for the user
                    # alone would take the exchange's loss / latency draws and change the epochs
                    cl.stream.add_uwb(uwb if "uwb" in filtered else None)
                    cl.stream.add_bearings(bearings if "bearing" in filtered else None)
                    for t in grid_times:
                        st = truth_at(t)
                        if st is not None and cl.lead in st.vehicles:
                            cl.stream.add_output_time(t)
                            cl.out_times.append(t)
                    cl.events += cl.stream.advance(known, final=final)
                    # filter the output epochs whose events are all delivered
                    ready = len(cl.out_times) if final else _count_before(cl.out_times, cl.stream)
                    times = cl.out_times[:ready]
                    consumed = 0
                    for runner, part in zip(cl.runners, cl.parts, strict=True):
                        rec = pipeline.run_solution(runner.sol, runner.ekf, cl.events, times, truth_at, cl.lead,
                                                    runner.vehicles, runner=runner)
                        consumed = runner.consumed
                        frame = rec.take_frame()
                        updates = rec.log.take_recent()  # (the replay's: none without it)
                        if frame is not None:
                            if log_epochs is not None:
                                log_epochs(runner.sol.name, cl.lead, frame, truth_at,
                                           cl.name if len(clusters) > 1 else "", updates, times)
                            with open(part, "ab") as f:
                                pickle.dump(frame, f, protocol=pickle.HIGHEST_PROTOCOL)
                    del cl.events[:consumed]
                    del cl.out_times[:ready]
                timing["estimation"] += time.perf_counter() - t0 - (timing["replay"] - replay_before)
                # forget the truth no cluster / the replay needs any more
                need = min([cl.out_times[0] for cl in clusters if cl.out_times] + [replay_state.oldest()], default=np.inf)
                for key in [k for k, st in window.items() if st.t_s < need - 1e-6]:
                    del window[key]

            def add_step(st: TrafficStep) -> None:
                window[round(st.t_s * 1e6)] = st
                chunk_steps.append(st)
                truth.extend(_truth_rows(st))

            t0 = time.perf_counter()
            for e in _event_rows(step):
                _log_event(e, events_log, event_counts)
            add_step(step)
            t_end = step.t_s
            next_cut = step.t_s + chunk
            lines = _ProgressLines(quiet, scenario.name, scenario.duration_s, compiling)
            raw: list[RawStep] = []  # SUMO steps not yet converted to truth (one chunk at a time, sim.convert)

            def add_raw() -> None:
                for st in sim.convert(raw):
                    for e in _event_rows(st):
                        _log_event(e, events_log, event_counts)
                    if st.vehicles:
                        add_step(st)
                raw.clear()

            with _progress(n_steps, quiet, f"SUMO {scenario.name}") as bar:
                for _ in range(n_steps):
                    raw.append(sim.step_raw())
                    if not raw[-1].ids:
                        break  # every cluster vehicle has arrived
                    t_end = raw[-1].t_s
                    bar.update(1)
                    check_interrupt()  # (a signal a ctypes callback swallowed: numba compiling)
                    cut = t_end >= next_cut - 1e-9
                    if cut or len(raw) >= _CONVERT_STEPS:
                        add_raw()
                    if cut:
                        timing["traffic"] += time.perf_counter() - t0
                        process(final=False)
                        truth.flush()  # one row group per chunk: memory O(chunk), not O(10 000 rows)
                        lines.chunk_done(t_end)
                        t0 = time.perf_counter()
                        next_cut += chunk
            add_raw()
            stats = sim.stats
            timing["traffic"] += time.perf_counter() - t0
            process(final=True)
            check_interrupt()
            truth.close()
            window.clear()
            t0 = time.perf_counter()
            logger.close()  # (the with block's exit: a no-op now, or abort on an error before)
            if replay:
                timing["replay"] += time.perf_counter() - t0
            records_meta = []
            membership: dict[str, list[dict[str, Any]]] = {}
            filter_counters: dict[str, dict[str, int]] = {}
            recs: dict[str, Any] = {}
            exchange_stats = ExchangeStats()  # every cluster's links added up (each has its own exchange)
            for cl in clusters:
                for runner, key, part in zip(cl.runners, cl.keys, cl.parts, strict=True):
                    rec = runner.finish()
                    recs[key] = rec
                    filter_counters[key] = rec.counters
                    if rec.membership:
                        membership[key] = [{"t_s": t, "vehicle": v, "change": c} for t, v, c in rec.membership]
                    records_meta.append((cl.name, part))
                exchange_stats += cl.exchange.stats

        # metrics and outputs -------------------------------------------------------------
        t0 = time.perf_counter()
        records = []
        for cname, part in records_meta:
            dfs = _read_pickles(part)
            if dfs:
                df = pd.concat(dfs, ignore_index=True) if len(dfs) > 1 else dfs[0]
                df.insert(1, "cluster", cname)
                records.append(df)
        shutil.rmtree(parts_dir)
        if save_measurements:  # one chunk (see above)
            t1 = time.perf_counter()
            from v2v.io.measurements import measurements_table

            m_epochs, m_uwb, m_b = measurements[0] if measurements else ([], None, None)
            atomic_write_parquet(tmp / "measurements.parquet", measurements_table(m_epochs, m_uwb, m_b))
            measurements.clear()
            timing["measurements_io"] = time.perf_counter() - t1
        epochs_df = pd.concat(records, ignore_index=True) if records else pd.DataFrame()
        records.clear()
        lane_records: list[dict[str, Any]] = []
        # (nothing estimated: the table without rows, so that every run has one)
        atomic_write_parquet(tmp / "epochs.parquet", epochs_df if len(epochs_df) else empty_epochs_frame())
        if len(epochs_df):
            # per-update statistics from the compact logs, one kind of one solution at a time
            # (a solution's over every cluster: the epochs' statistics are per solution, the
            # clusters' vehicles side by side, and so are its measurements')
            logs: dict[str, list[Any]] = {}
            for cl in clusters:
                for runner, key in zip(cl.runners, cl.keys, strict=True):
                    logs.setdefault(runner.sol.name, []).append(recs[key].log)
            meas = {name: kind_statistics_of(group) for name, group in logs.items()}
            sol_stats = solution_statistics(epochs_df, {}, measurements=meas, azimuth_solutions={
                s.name for s in scenario.solutions if s.azimuth == "estimated"})
            from v2v.metrics.lane import lane_level_rows

            truth_cols = ["t_s", "vehicle", "cluster", "is_lead", "edge", "azimuth_rad"]  # what attach_truth reads
            lane_records = lane_level_rows(epochs_df, pd.read_parquet(tmp / "truth.parquet", columns=truth_cols))
        else:
            sol_stats = {}
        timing["metrics_io"] = time.perf_counter() - t0
        wall = time.perf_counter() - wall0
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
            "gnss": acc.gnss_summary(),
            "uwb": acc.uwb_summary(),
            "bearing": {"measurements": acc.n_bearings},
            "exchange": {"sent": exchange_stats.sent, "lost": exchange_stats.lost, "late": exchange_stats.late}
            if scenario.clusters else {},
            "event_counts": event_counts,
            "faults_injected": fault_log.counts if fault_log is not None else {},
            "events": events_log[:1000],
            "truth_rows": truth.rows_written,
            "statistics": sol_stats,
            "lane_level": lane_records,
            "filter_membership": membership,
            "filter_counters": filter_counters,  # e.g. clock_jump_detected, divergence_reset, nonfinite_*  # vehicles the lead's filter dropped (silent) and re-added
        }
        note = _run_note(scenario, t_end, fault_log, sol_stats, summary["gnss"], summary["exchange"], summary["uwb"],
                         summary["bearing"], filter_counters)
        if note:
            summary["note"] = note
        summary["table"] = paper_table(sol_stats) if sol_stats else ""
        atomic_write_json(tmp / "summary.json", json_safe(summary))
    return RunResult(out_dir=Path(out_dir), summary=summary)


def _run_note(scenario: Scenario, t_end: float, fault_log: Any, sol_stats: dict[str, Any], gnss: dict[str, Any],
              exchange: dict[str, int], uwb: dict[str, Any], bearing: dict[str, Any],
              filter_counters: dict[str, dict[str, int]] | None = None) -> str:
    """summary.json's ``note`` ("" if none), what a user should know about a run that completed:
    a sensor so slow that the run has fewer than 2 of its epochs
    (:meth:`Scenario.sparse_sensor_warnings`, also printed as the run starts), it ended early
    (every cluster vehicle at the end of its route), a fault could not act (it
    starts after the run's end, or changed no measurement), no solution estimated any vehicle
    (:func:`_why_nothing_estimated`), a solution's UWB or bearing sensor measured nothing, a
    vehicle's filter was badly overconfident (:func:`_overconfident`), a solution restarted its
    vehicles so often that its estimates are snapshots rather than filtered
    (:func:`_reset_note`), most V2V messages arrived after the filter had passed their time tag."""
    from v2v.faults import unreachable_faults

    notes = list(scenario.sparse_sensor_warnings())
    if t_end + 1e-9 < scenario.duration_s - scenario.step_length_s:
        notes.append(f"all cluster vehicles reached the end of the route at t = {t_end:.1f} s")
    never = unreachable_faults(list(scenario.faults), scenario.duration_s)
    if never:
        notes.append(f"{len(never)} fault(s) start at or after the run's end (duration_s = {scenario.duration_s:g} s) "
                     f"and were never injected: {', '.join(never)}")
    idle = [f"faults.{i} ({f.kind})" for i, f in enumerate(scenario.faults)
            if f.start_s < scenario.duration_s - 1e-9 and fault_log is not None
            and not fault_log.counts.get(f"{i}:{f.kind}")]
    if idle:
        notes.append(f"{', '.join(idle)} changed no measurement (its PRNs not in view, its vehicles without such "
                     "measurements in its window, or its probability drew none)")
    nothing = _why_nothing_estimated(scenario, sol_stats, gnss, exchange)
    if nothing:
        notes.append(nothing)
    used = {s for sol in scenario.solutions for s in sol.sensors}
    for sensor, n, why in (("uwb", uwb.get("ranges", 0), "every pair out of range, blocked or lost"),
                           ("bearing", bearing.get("measurements", 0), "sensors.bearing.measuring, field of view, range")):
        if sensor in used and not n:
            sols = [sol.name for sol in scenario.solutions if sensor in sol.sensors]
            notes.append(f"the run measured no {'UWB ranges' if sensor == 'uwb' else 'bearings'} ({why}): "
                         f"{', '.join(sols)} had none to use")
    over = _overconfident(sol_stats)
    if over:
        notes.append(_overconfident_note(scenario, over, gnss))
    resets = _reset_note(scenario, sol_stats, filter_counters or {})
    if resets:
        notes.append(resets)
    if exchange and exchange["late"] > 0.5 * (exchange["sent"] - exchange["lost"]):
        notes.append(f"{exchange['late']} of the {exchange['sent'] - exchange['lost']} V2V messages not lost arrived after "
                     f"the filter had passed their time tag and were dropped (exchange.latency_s = "
                     f"{scenario.exchange.latency_s:g} s > exchange.filter_lag_s = {scenario.exchange.lag_s:g} s)")
    return "; ".join(notes)


# A vehicle's mean position NEES this many times its expectation (3 degrees of freedom) is
# noted. Not a statistical test: a run's NEES samples are strongly correlated in time, so the
# chi-square band of their mean (summary.json's frac_in_band uses each sample's band) would flag
# ordinary runs; an average of 10x means errors sustained at ~3 sigma per axis.
NEES_NOTE_FACTOR = 10.0


def _overconfident(sol_stats: dict[str, Any]) -> list[tuple[float, str, str]]:
    """(mean position NEES, solution, vehicle) of the vehicles whose mean NEES is above
    :data:`NEES_NOTE_FACTOR` times 3, worst first."""
    over = [(float(v["nees_pos"]["mean"]), sol, veh) for sol, st in sol_stats.items()
            for veh, v in st.get("vehicles", {}).items()
            if v.get("nees_pos", {}).get("n", 0) and float(v["nees_pos"]["mean"]) > NEES_NOTE_FACTOR * 3.0]
    return sorted(over, key=lambda o: -o[0])


def _overconfident_note(scenario: Scenario, over: list[tuple[float, str, str]], gnss: dict[str, Any],
                        listed: int = 3) -> str:
    """The note on :func:`_overconfident`'s vehicles (``listed`` of them, then how many more),
    with the likely causes the run can name: UWB solutions without bias states, NLOS-only GNSS."""
    text = ", ".join(f"{sol} {veh} ({m:.0f})" for m, sol, veh in over[:listed])
    text += f" and {len(over) - listed} more" if len(over) > listed else ""
    named = {sol for _, sol, _ in over}
    hints = []
    biased = sorted(s.name for s in scenario.solutions if s.name in named and "uwb" in s.sensors and not s.uwb_error_states)
    if biased:
        hints.append(f"{', '.join(biased)} leave{'s' if len(biased) == 1 else ''} the UWB ranges' biases (decimetres) "
                     "unestimated: uwb_error_states = true models them")
    nlos = gnss.get("nlos_fraction")
    if nlos is not None and float(nlos) >= 0.1:
        hints.append(f"{100.0 * float(nlos):.0f} % of the tracked GNSS signals were NLOS-only")
    return (f"the filter is overconfident: mean position NEES above {NEES_NOTE_FACTOR * 3:g} ({NEES_NOTE_FACTOR:g} "
            f"times its expectation of 3) for {text}: the errors exceed what it assumes "
            f"({'; '.join(hints) if hints else 'see the *_sigma_* fields; unmodelled multipath'}); see nees_pos in statistics")


# A solution that reset its vehicles at more than this fraction of their estimated epochs is
# noted. A healthy run resets a vehicle rarely or never (0-2 times in the shipped scenarios'
# runs of 120-300 s, all in the urban canyon); a filter whose assumed noises let its
# covariance grow past divergence_position_sigma_m between GNSS epochs resets at every one.
RESET_NOTE_FRACTION = 0.1


def _reset_note(scenario: Scenario, sol_stats: dict[str, Any], filter_counters: dict[str, dict[str, int]]) -> str | None:
    """A note naming the solutions whose ``divergence_reset`` count is above
    :data:`RESET_NOTE_FRACTION` of their vehicles' estimated output epochs, or None. Each reset
    restarts a vehicle from the next GNSS snapshot (least squares of one epoch), so such a
    solution's errors are those of single-epoch snapshots: its table looks plausible while the
    filter's own sigmas (``*_sigma_mean_m``) may be kilometres."""
    found = []
    for sol in scenario.solutions:
        n = int(filter_counters.get(sol.name, {}).get("divergence_reset", 0))
        epochs = sum(int(v.get("epochs", 0) * v.get("availability", 0.0) + 0.5)
                     for v in sol_stats.get(sol.name, {}).get("vehicles", {}).values())
        if n and epochs and n > RESET_NOTE_FRACTION * epochs:
            found.append(f"{sol.name} ({n} resets in {epochs} vehicle-epochs)")
    if not found:
        return None
    from v2v.estimation.filter import FilterConfig

    fc = FilterConfig()
    return (f"{', '.join(found)} restarted {'its' if len(found) == 1 else 'their'} vehicles from single-epoch GNSS "
            "snapshots again and again "
            f"(divergence_reset in filter_counters: a vehicle is reset when its position sigma exceeds "
            f"{fc.divergence_position_sigma_m:g} m or its pseudorange tests say it diverged), so its errors are "
            "the snapshots', not a filter's; check the solution's *_sigma_* fields (the filter's assumed noises) "
            "against the sensors'")


def _why_nothing_estimated(scenario: Scenario, sol_stats: dict[str, Any], gnss: dict[str, Any],
                           exchange: dict[str, int]) -> str | None:
    """A note for a run in which no solution ever estimated a vehicle (every availability 0),
    naming the likely cause; None otherwise. A vehicle's filter starts at its first GNSS epoch
    with >= 4 satellites in common with the lead (``FilterConfig.init_min_satellites``), from
    messages the exchange delivered."""
    avail = [v.get("availability") for st in sol_stats.values() for v in st.get("vehicles", {}).values()]
    if not scenario.solutions or not avail or any(a for a in avail):
        return None
    why = []
    tracked = float(gnss.get("satellites_tracked_mean", 0.0))
    if tracked < 4.0:
        why.append(f"the receivers tracked {tracked:.1f} satellites on average (sensors.gnss.elevation_mask_deg = "
                   f"{scenario.sensors.gnss.elevation_mask_deg:g}, start_utc {scenario.start_utc:%Y-%m-%dT%H:%M:%SZ})")
    sent, lost = int(exchange.get("sent", 0)), int(exchange.get("lost", 0))
    if sent and lost == sent:
        why.append(f"every V2V message was lost (exchange.loss_probability = {scenario.exchange.loss_probability:g})")
    return ("no solution estimated any vehicle: a vehicle's filter starts at its first GNSS epoch with >= 4 "
            "satellites in common with the lead; " + ("; ".join(why) if why else "see filter_counters in summary.json"))


def _sensor_stage(timing: dict[str, float], stage: str, t0: float, occ0: float,
                  occlusion: Any) -> tuple[float, float]:
    """Adds the wall time since ``t0`` to ``timing[stage]``, less the occlusion tests' share
    (what :attr:`OcclusionGeometry.time_s` grew by since ``occ0``), which goes to
    ``timing["occlusion"]``. Returns the next stage's start ``(t0, occ0)``."""
    t1, occ_now = time.perf_counter(), occlusion.time_s
    occ = occ_now - occ0
    timing[stage] += t1 - t0 - occ
    timing["occlusion"] += occ
    return t1, occ_now


def _count_before(times: list[float], stream: Any) -> int:
    """How many leading output epochs can be filtered: every event up to ``t + 1e-9`` is delivered."""
    horizon = stream.exchange.processed_until_s - 2e-9  # later events have t_s >= this
    n = 0
    while n < len(times) and times[n] + 1e-9 < horizon:
        n += 1
    return n


def _read_pickles(path: Path) -> list[Any]:
    import pickle

    out: list[Any] = []
    if not path.exists():
        return out
    with open(path, "rb") as f:
        while True:
            try:
                out.append(pickle.load(f))
            except EOFError:
                break
    return out


def _log_event(e: dict[str, Any], log: list[dict[str, Any]], counts: dict[str, int]) -> None:
    counts[e["kind"]] = counts.get(e["kind"], 0) + 1
    if len(log) < 1000:
        log.append(e)


class _RunAccumulators:
    """The run's sensor summary numbers, kept as counts and compact arrays (not measurement objects)."""

    def __init__(self) -> None:
        self.n_epochs = 0
        self.n_sats = 0
        self.n_sat_obs = 0
        self.nlos = 0
        self.n_bearings = 0
        self._uwb_err: list[np.ndarray] = []
        self._uwb_los: list[np.ndarray] = []

    def add_sensors(self, epochs, uwb, bearings) -> None:
        self.n_epochs += len(epochs)
        recv = [ep for _, eps in epochs for ep in eps.values()]  # every receiver-epoch of the chunk
        if recv:  # (one concatenation instead of small-array reductions per receiver and epoch)
            self.n_sat_obs += len(recv)
            self.n_sats += sum([ep.prn.shape[0] for ep in recv])
            los = np.concatenate([ep.los for ep in recv])
            self.nlos += int(los.size - np.count_nonzero(los))  # echo-only signals (los False)
        if uwb is not None and uwb.n:
            self._uwb_err.append(uwb.range_m - uwb.true_range_m)
            self._uwb_los.append(np.asarray(uwb.los, dtype=bool))
        if bearings is not None:
            self.n_bearings += int(bearings.n)

    def gnss_summary(self) -> dict[str, Any]:
        return {
            "epochs": self.n_epochs,
            "satellites_tracked_mean": float(np.float64(self.n_sats) / self.n_sat_obs) if self.n_sat_obs else 0.0,
            "nlos_fraction": self.nlos / max(self.n_sats, 1),
        }

    def uwb_summary(self) -> dict[str, Any]:
        if not self._uwb_err:
            return {"ranges": 0}
        err = np.concatenate(self._uwb_err)
        nlos = ~np.concatenate(self._uwb_los)
        n = int(err.size)
        ok = np.isfinite(err)  # (a nonfinite fault's ranges: counted, not averaged)
        if not ok.all():
            err, nlos = err[ok], nlos[ok]
        return {
            "ranges": n,
            "nonfinite": n - int(err.size),
            "nlos_fraction": float(nlos.mean()) if err.size else None,
            "error_mean_m": float(err.mean()) if err.size else None,
            "error_std_m": float(err.std()) if err.size else None,
            "nlos_error_mean_m": float(err[nlos].mean()) if nlos.any() else None,
        }


def _event_rows(step: TrafficStep) -> list[dict[str, Any]]:
    return [{"t_s": e.t_s, "kind": e.kind.value, "vehicle": e.vehicle_id, "detail": e.detail} for e in step.events]


def _uwb_pairs(scenario: Scenario, members: list[str]) -> list[tuple[str, str]]:
    from itertools import combinations

    sec = scenario.sensors.uwb
    if sec.pairs == "all":
        return list(combinations(members, 2))
    return [(a, b) for a, b in sec.pairs if a in members and b in members]


def _make_logger(folder: Path, replay: bool):
    if not replay:
        from v2v.viz.logger import NullLogger

        return NullLogger()
    from v2v.viz.rerun_logger import RerunReplayLogger

    return RerunReplayLogger(folder / "replay.rrd")


class _ReplayState:
    """Truth, radio/bearing links and sky plots waiting to be logged to the replay, chunk by chunk."""

    def __init__(self) -> None:
        self.steps: list[TrafficStep] = []
        self.uwb: list[Any] = []
        self.bearings: list[Any] = []
        self.sky: dict[int, dict[str, GnssEpoch]] = {}
        self.prev = -np.inf

    def add(self, logger, steps, uwb, bearings, epochs) -> None:
        from v2v.viz.logger import NullLogger

        if isinstance(logger, NullLogger):
            return
        self.steps += steps
        if uwb is not None and uwb.n:
            self.uwb.append(uwb)
        if bearings is not None and bearings.n:
            self.bearings.append(bearings)
        self.sky.update({round(t * 1e6): eps for t, eps in epochs if abs(t - round(t)) < 1e-6})  # 1 Hz sky plots

    def oldest(self) -> float:
        return self.steps[0].t_s if self.steps else np.inf

    def flush(self, logger, upto_s: float) -> None:
        """Log the steps up to ``upto_s`` (every link measured up to then is known)."""
        from v2v.pipeline import _concat_bearings
        from v2v.sensors.uwb import concat_ranges

        k = 0
        while k < len(self.steps) and self.steps[k].t_s <= upto_s:
            k += 1
        if k == 0:
            return
        steps, self.steps = self.steps[:k], self.steps[k:]
        uwb = concat_ranges(self.uwb) if self.uwb else None
        parts = [b for b in self.bearings if b.n]  # the chunk's part and what the last flush left
        bearings = (parts[0] if len(parts) == 1 else _concat_bearings(parts)) if parts else None
        self.prev = _log_truth_and_links(logger, steps, uwb, bearings, self.sky, self.prev)
        last = self.prev
        from v2v.sensors.uwb import select_ranges

        self.uwb = [select_ranges(uwb, uwb.t_s > last)] if uwb is not None else []
        self.bearings = [bearings.take(np.flatnonzero(bearings.t_s > last))] if bearings is not None else []
        self.sky = {key: v for key, v in self.sky.items() if key > round(last * 1e6)}


def _log_truth_and_links(logger, steps, uwb, bearings, sky_every: dict[int, Any], prev: float = -np.inf) -> float:
    """Log truth, links measured in (previous step, step] and the 1 Hz sky plots; returns the last step time.

    Links of a kind are logged at every step of a chunk that has any, a step without links as an
    empty row (which clears them in the viewer).

    All steps go to the logger in one batch per entity (``log_truth_many``, ``log_links_many``,
    ``log_satellites_many``): the same rows as one ``log_truth`` / ``log_links`` /
    ``log_satellites`` call per step.
    """
    from itertools import repeat

    if not steps:
        return prev
    logger.log_truth_many(steps)
    t_steps = np.array([st.t_s for st in steps])
    # antenna of every vehicle at every step, NaN where absent
    vehicle_index: dict[str, int] = {}
    js = np.repeat(np.arange(len(steps)), [len(st.vehicles) for st in steps])
    vs = np.fromiter((vehicle_index.setdefault(v, len(vehicle_index)) for st in steps for v in st.vehicles),
                     dtype=np.intp, count=len(js))
    xyz = np.full((len(steps), len(vehicle_index), 3), np.nan)
    present = np.zeros((len(steps), len(vehicle_index)), dtype=bool)
    if len(js):
        xyz[js, vs] = np.concatenate([s.xyz_m for st in steps for s in st.vehicles.values()]).reshape(-1, 3)
        present[js, vs] = True
    for kind, meas in (("uwb", uwb), ("bearing", bearings)):
        if meas is None or not meas.n:
            continue
        # records in time order; step j takes those in (t[j-1], t[j] + 1e-9] (t[-1] = prev)
        order = np.argsort(meas.t_s, kind="stable")
        tt = meas.t_s[order]
        lo = np.searchsorted(tt, np.concatenate([[prev], t_steps[:-1]]), side="right")
        hi = np.searchsorted(tt, t_steps + 1e-9, side="right")
        n = np.maximum(hi - lo, 0)
        step_of = np.repeat(np.arange(len(steps)), n)
        rec = order[np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n) + np.repeat(lo, n)]
        ia, ib = (np.fromiter(map(vehicle_index.get, ends, repeat(-1)), dtype=np.intp, count=meas.n)[rec]
                  for ends in (meas.a, meas.b))
        keep = (ia >= 0) & (ib >= 0)
        keep[keep] = present[step_of[keep], ia[keep]] & present[step_of[keep], ib[keep]]
        step_of, rec, ia, ib = step_of[keep], rec[keep], ia[keep], ib[keep]
        counts = np.bincount(step_of, minlength=len(steps))
        # every step, also one without links (an empty row clears the kind's links): the viewer shows
        # the latest row, so a step's links would stay drawn where the vehicles were until the next
        # measured step (a 2 Hz bearing: 0.4 s, 10 m at 25 m/s)
        logger.log_links_many(t_steps, kind, counts, xyz[step_of, ia], xyz[step_of, ib],
                              np.where(meas.los[rec], "los", "nlos"))
    sky = [(st.t_s, v, ep) for st in steps for v, ep in sky_every.get(round(st.t_s * 1e6), {}).items()]
    if sky:
        logger.log_satellites_many([t for t, _, _ in sky], [v for _, v, _ in sky], [len(ep.prn) for _, _, ep in sky],
                                   *(np.concatenate([getattr(ep, f) for _, _, ep in sky])
                                     for f in ("prn", "azimuth_rad", "elevation_rad", "los")))
    return steps[-1].t_s


def _error_gap_starts(t_s: pd.Series, vehicles: pd.Series, initialized: np.ndarray,
                      estimated: dict[tuple[str, str], bool], solution: str) -> tuple[list[float], list[str]]:
    """(times, vehicles) of the rows (in order) where a vehicle's estimate stops: uninitialized
    after an initialized row of it, in this chunk or the last one logged (``estimated``, kept
    across chunks and updated here). The replay's error series get a hole there."""
    if initialized.all():  # (the usual chunk)
        for v in vehicles.unique().tolist():
            estimated[(solution, v)] = True
        return [], []
    times: list[float] = []
    which: list[str] = []
    for t, v, ok in zip(t_s.tolist(), vehicles.tolist(), initialized.tolist(), strict=True):
        if not ok and estimated.get((solution, v), False):
            times.append(t)
            which.append(v)
        estimated[(solution, v)] = ok
    return times, which


def _epoch_logger(logger, georef: GeoReference, timing: dict[str, float]):
    """Callback logging a chunk of one solution's epoch rows (the frame of ``take_frame``) to the
    replay: each epoch's estimates of the initialized vehicles (net XY, around the lead's true
    antenna at that epoch, ``truth_at``) and their errors, in one :meth:`log_epochs` call; its
    time is added to ``timing["replay"]``. The ``nis`` series is each row's per-epoch NIS
    (:func:`v2v.pipeline.epoch_nis_of_rows`) from the chunk's update-log columns ``updates``
    (:meth:`v2v.pipeline.UpdateLog.take_recent`) and its output epochs ``output_times``."""
    from v2v.pipeline import epoch_nis_of_rows

    cache: dict[str, tuple[float, float]] = {}  # cos, sin of the grid convergence at the first lead position
    shown: set[tuple[str, str]] = set()  # (solution, cluster) with estimates logged
    estimated: dict[tuple[str, str], bool] = {}  # (solution, vehicle): initialized in its last row logged
    error_columns = ("along_err_m", "across_err_m", "sigma_along_m", "sigma_across_m", "nees_pos")
    rejected = ("rejected_pr", "rejected_uwb", "rejected_bearing", "rejected_doppler", "rejected_phase")  # (phase: if any)

    def log_epochs(solution: str, lead: str, frame: pd.DataFrame, truth_at, cluster: str,
                   updates: Sequence[dict[str, Any]], output_times: Sequence[float]) -> None:
        t0 = time.perf_counter()
        try:
            log_frame(solution, lead, frame, truth_at, cluster, updates, output_times)
        finally:
            timing["replay"] += time.perf_counter() - t0

    def log_frame(solution: str, lead: str, frame: pd.DataFrame, truth_at, cluster: str,
                  updates: Sequence[dict[str, Any]], output_times: Sequence[float]) -> None:
        if "cos_sin" not in cache and len(frame):  # the first epoch logged, initialized vehicles or not
            x0, y0 = truth_at(float(frame["t_s"].iat[0])).vehicles[lead].xyz_m[:2]
            g = georef.grid_convergence_rad(float(x0), float(y0))
            cache["cos_sin"] = (np.cos(g), np.sin(g))
        ini = frame["initialized"].to_numpy(dtype=bool)
        gap_t, gap_v = _error_gap_starts(frame["t_s"], frame["vehicle"], ini, estimated, solution)
        if gap_v:
            logger.log_error_gaps(gap_t, solution, gap_v)
        rows = frame[ini]
        # every epoch, one without an initialized vehicle too (an empty row: the viewer shows the
        # latest row, so the estimates drawn before would stay), once a vehicle has been
        t_all = frame["t_s"].to_numpy(dtype=float)
        new_epoch = np.concatenate([[True], t_all[1:] != t_all[:-1]]) if len(t_all) else np.zeros(0, dtype=bool)
        epoch_of = np.cumsum(new_epoch) - 1
        counts = np.bincount(epoch_of[ini], minlength=int(new_epoch.sum()))
        if rows.empty and (solution, cluster) not in shown:
            return
        shown.add((solution, cluster))
        t = rows["t_s"].to_numpy(dtype=float)
        t_epochs = t_all[new_epoch]
        # each estimate is drawn at its vehicle's true antenna plus the error (est - true, ENU turned by
        # the grid convergence): the drawn gap to the true antenna is the epochs' error. The lead's
        # antenna plus the ENU baseline would put it off by the baseline times the scale between ENU
        # metres and net XY metres (the projection's, and R / (R + h) at the net's height: 1.7e-4 at
        # 1100 m, 4 cm at 240 m) and by the grid convergence's change since the first epoch
        steps = [truth_at(float(te)).vehicles for te in t_epochs]
        vehicles = rows["vehicle"].tolist()
        c, s = cache["cos_sin"]
        e, n = rows["est_e_m"].to_numpy(dtype=float), rows["est_n_m"].to_numpy(dtype=float)
        te_, tn_ = rows["true_e_m"].to_numpy(dtype=float), rows["true_n_m"].to_numpy(dtype=float)
        states = [steps[k].get(v) for k, v in zip(np.repeat(np.arange(len(steps)), counts).tolist(), vehicles,
                                                   strict=True)]
        base = np.array([st.xyz_m[:2] if st is not None else (np.nan, np.nan) for st in states],
                        dtype=float).reshape(-1, 2)
        known = np.isfinite(base).all(axis=1) & np.isfinite(te_) & np.isfinite(tn_)
        if not known.all():  # no true antenna at the epoch: the lead's plus the ENU baseline
            lead_xy = np.repeat(np.array([st[lead].xyz_m[:2] for st in steps], dtype=float), counts, axis=0)
            base[~known] = lead_xy[~known]
            te_, tn_ = np.where(known, te_, 0.0), np.where(known, tn_, 0.0)
        de, dn = e - te_, n - tn_
        xy = np.column_stack([base[:, 0] + de * c - dn * s, base[:, 1] + de * s + dn * c])
        cee, cen, cnn = (rows[k].to_numpy(dtype=float) for k in ("cov_ee_m2", "cov_en_m2", "cov_nn_m2"))
        cov = np.stack([cee, cen, cen, cnn], axis=1).reshape(-1, 2, 2)
        nis = epoch_nis_of_rows(updates, output_times, t, vehicles) if len(t) else np.zeros(0)
        errors = np.column_stack([*(rows[k].to_numpy(dtype=float) for k in error_columns), nis,
                                  rows["used_pr"].to_numpy(dtype=float),
                                  sum(rows[k].to_numpy(dtype=float) for k in rejected if k in rows)])
        logger.log_epochs(t_epochs, solution, counts, vehicles, xy, cov, errors, cluster)

    return log_epochs
