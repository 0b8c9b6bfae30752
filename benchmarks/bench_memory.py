"""Memory of a long run: resident set size (RSS) vs simulated time, 10 vehicles, 1 hour.

Issue 8: "a 1-hour, 10-vehicle run keeps memory flat (measure)". One run of
:func:`v2v.run.run_scenario` (open_highway, 10 cars in lanes 0-2, the default route
repeated so it lasts the whole run, one GPS+UWB+Bearing solution, replay off) in this
process. A sampler thread reads the RSS (psutil, else /proc/self/statm, else
``resource.getrusage`` peak) every 0.2 wall seconds; light hooks on
``SumoSimulation.step`` / ``step_raw`` and the solution's ``truth_at`` callback tag each sample with the
stage (traffic, sensors/exchange, filter; "outputs" for the end-of-run tables of a streamed
run, excluded from the slopes) and the simulated time it has reached.

Prints, per stage, the RSS when the simulated time crosses each ``--every`` seconds, the
least-squares slope of RSS vs simulated time (MB per simulated hour) and the peak.
Memory that grows with run length shows up as a positive slope in the traffic and
filter stages. Nothing is asserted.

The run is streamed in chunks of ``--chunk`` simulated seconds (default: the library's
``v2v.run.DEFAULT_CHUNK_S``), so the stages interleave: each sample is tagged with the
stage running when it was taken ("traffic" while SUMO steps, "filter" while a solution
filters a chunk). ``--chunk inf`` processes the run as one chunk (the pre-streaming
memory profile, apart from the per-update logs, which are spilled to disk either way).

    .venv/bin/python benchmarks/bench_memory.py [--duration 3600] [--vehicles 10] [--every 300] [--chunk 30]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def rss_mb() -> float:
    """Current resident set size in MB (1e6 bytes)."""
    try:
        import psutil

        return psutil.Process().memory_info().rss / 1e6
    except ImportError:  # pragma: no cover - psutil is in the lock file
        pass
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    except OSError:  # pragma: no cover - not Linux
        import resource

        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e3  # peak, kB on Linux


class Sampler:
    """Background RSS sampler; ``stage`` / ``sim_t`` are set by the hooks."""

    def __init__(self, period_s: float = 0.2):
        self.period_s = period_s
        self.stage = "setup"
        self.sim_t = 0.0
        self.samples: list[tuple[float, str, float, float]] = []  # (wall s, stage, sim t, RSS MB)
        self._stop = threading.Event()
        self._t0 = time.perf_counter()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def mark(self, stage: str, sim_t: float) -> None:
        self.stage, self.sim_t = stage, sim_t

    def sample(self) -> None:
        self.samples.append((time.perf_counter() - self._t0, self.stage, self.sim_t, rss_mb()))

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self.sample()

    def __enter__(self) -> Sampler:
        self.sample()
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.sample()


def install_hooks(sampler: Sampler) -> None:
    """Tag samples with the stage and simulated time (wraps two library callables)."""
    import v2v.pipeline as pipeline
    from v2v.traffic import sumo

    # v2v.run steps SUMO with step_raw (the truth converted 256 steps at a time); step for
    # callers stepping one converted snapshot at a time
    def tagged(f):
        def step(self, *a, **k):
            st = f(self, *a, **k)
            sampler.mark("traffic", float(st.t_s))
            return st

        return step

    for name in ("step", "step_raw"):
        setattr(sumo.SumoSimulation, name, tagged(getattr(sumo.SumoSimulation, name)))
    run0 = pipeline.run_solution

    def run_solution(sol, ekf, events, output_times, truth_at, *a, **k):
        def tagged(t):
            sampler.mark("filter", float(t))
            return truth_at(t)

        sampler.mark("filter", 0.0)
        return run0(sol, ekf, events, output_times, tagged, *a, **k)

    pipeline.run_solution = run_solution
    bg0 = pipeline.build_gnss

    def build_gnss(*a, **k):
        sampler.mark("sensors+exchange", sampler.sim_t)
        return bg0(*a, **k)

    pipeline.build_gnss = build_gnss
    import v2v.run as run_mod

    if hasattr(run_mod, "_read_pickles"):  # streamed runs: the end-of-run outputs (epochs table, summary)
        rp0 = run_mod._read_pickles

        def read_pickles(*a, **k):
            sampler.mark("outputs", sampler.sim_t)
            return rp0(*a, **k)

        run_mod._read_pickles = read_pickles


def scenario(duration_s: float, vehicles: int):
    from v2v import nets
    from v2v.config.scenario import load_scenario

    built = nets.resolve_net({"name": "open_highway", "net_file": None})
    route = list(built.routes["default"])  # the circuit twice, 15.1 km: repeat to last the run
    reps = max(1, int(np.ceil(duration_s * 25.0 / 15_100.0)) + 1)
    edges = route * reps
    return load_scenario(None, [
        'network.name="open_highway"', f"network.route_edges={json.dumps(edges)}",
        f"clusters.0.vehicles={vehicles}", "clusters.0.lanes=[0,1,2]", "clusters.0.time_gap_s=1.5",
        f"duration_s={duration_s}", "vehicle_types.passenger.max_speed_mps=25.0",
        'solutions=[{name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]',
    ])


def table(samples, every_s: float) -> tuple[list[str], dict[str, float]]:
    lines = [f"{'stage':<18} {'sim t (s)':>9} {'RSS (MB)':>9}"]
    slopes: dict[str, float] = {}
    for stage in ("traffic", "filter"):
        s = [(t, r) for _, st, t, r in samples if st == stage]
        if len(s) < 3:
            continue
        t = np.array([x[0] for x in s])
        r = np.array([x[1] for x in s])
        nxt = 0.0
        for ti, ri in s:
            if ti >= nxt - 1e-9:
                lines.append(f"{stage:<18} {ti:9.0f} {ri:9.1f}")
                nxt = (np.floor(ti / every_s) + 1) * every_s
        lines.append(f"{stage:<18} {t[-1]:9.0f} {r[-1]:9.1f}  (last)")
        keep = t >= 0.1 * t.max()  # skip start-up allocations
        slopes[stage] = float(np.polyfit(t[keep], r[keep], 1)[0] * 3600.0) if keep.sum() > 2 else float("nan")
    return lines, slopes


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=3600.0, help="simulated seconds")
    ap.add_argument("--vehicles", type=int, default=10)
    ap.add_argument("--every", type=float, default=300.0, help="table row every this many simulated seconds")
    ap.add_argument("--json", type=Path, default=None, help="write the samples and slopes here")
    ap.add_argument("--chunk", type=float, default=None, help="chunk length, simulated s (inf: one chunk)")
    args = ap.parse_args(argv)
    from v2v.run import run_scenario

    sampler = Sampler()
    install_hooks(sampler)
    sc = scenario(args.duration, args.vehicles)
    with tempfile.TemporaryDirectory() as tmp, sampler:
        kw = {} if args.chunk is None else {"chunk_s": args.chunk}
        res = run_scenario(sc, Path(tmp) / "run", quiet=True, replay=False, **kw)
        sampler.mark("done", float(res.summary["simulated_s"]))
        sizes = {p.name: p.stat().st_size / 1e6 for p in (Path(tmp) / "run").iterdir()}
    lines, slopes = table(sampler.samples, args.every)
    peak = max(r for *_, r in sampler.samples)
    outputs = [r for _, st, _, r in sampler.samples if st == "outputs"]
    if outputs:
        lines.append(f"{'outputs (end)':<18} {'':>9} {max(outputs):9.1f}  (peak while writing epochs / summary)")
    print(f"{args.vehicles} vehicles, {res.summary['simulated_s']:.0f} s simulated, chunk {args.chunk or 'default'} s, wall {res.summary['wall_s']:.0f} s, "
          f"timing {res.summary['timing_s']}")
    print("\n".join(lines))
    for k, v in slopes.items():
        print(f"slope {k}: {v:+.1f} MB per simulated hour")
    print(f"peak RSS {peak:.1f} MB; outputs (MB): " + ", ".join(f"{k} {v:.1f}" for k, v in sorted(sizes.items())))
    if args.json:
        args.json.write_text(json.dumps({"samples": sampler.samples, "slopes_mb_per_h": slopes, "peak_mb": peak,
                                         "outputs_mb": sizes, "summary_timing_s": res.summary["timing_s"]}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
