"""End-to-end speed: real-time factor (simulated s / wall s) vs cluster size, and where the time goes.

Configuration (issue 7): 10 Hz GNSS, UWB between all pairs at ~3 Hz, bearings from every
vehicle, one GPS+UWB+Bearing solution, replay off and on, on `open_highway` (lanes 0-2;
one lane for N <= 3). Each cluster size runs in a fresh process, one after another, with
BLAS and numba limited to one thread and the process with all its threads (rerun's encoder and
file writer among them) pinned to one CPU (``--cpu``; the first this process may use by
default, ``--cpu -1`` leaves the placement to the OS as before 2026-12-04), so the numbers are
single-core times measured in this one invocation. In that process the runs follow each other (libsumo: one simulation at a
time): *cold*, the first run (replay off; it also loads the compiled kernels and pays the
lazy imports: what a single ``v2v run`` pays), with the replay on the same seed again (the
first replay-on run: rerun's import and the blueprint's build, ~0.25 s, paid once per process;
before 2026-12-04's ninth session it fell in the first warm pair), then ``--repeat`` pairs of *warm* runs (the
steady state of a sweep worker), each pair one seed with the replay off and on, back to back
(off first in even pairs, on first in odd ones: the machine's speed drifts). Warm figures are
the fastest of the repeats (the machine may be shared: the minimum is the least disturbed run);
the replay's share is given three ways: the fastest replay-on run against the fastest
replay-off one of the same process, the median over the pairs of each pair's share (robust to
a disturbed run), and the median over the replay-on runs of the time spent inside the replay's
code (``timing_s`` ``replay`` + ``replay_static_truth``, timed in the run itself: immune to the
machine's drift between two runs, but blind to what the replay costs the rest of the run, e.g.
in caches). Per run: wall time and stage breakdown
(``summary.json`` ``wall_s``, ``timing_s``) and CPU time; per process: the start-up
(interpreter + imports, before ``run_scenario``).

Monte Carlo (issue 7 item 3): ``--mc-runs`` runs of ``--mc-duration`` s at N = 3 (seeds
1..mc-runs, same scenario) through the sweep machinery (:func:`v2v.sweep.run_study`: a
Dask ``LocalCluster`` with ``--mc-workers`` single-threaded worker processes); the wall
time of the whole study, start-up of the cluster included, is printed.

    .venv/bin/python benchmarks/bench_run.py [--sizes 3 10 20 40] [--duration 60] [--repeat 3] [--cpu K] [--out DIR]
    .venv/bin/python benchmarks/bench_run.py --sizes --mc-runs 100     # Monte Carlo only

Prints tables; nothing is asserted. The machine may be shared: compare CPU and wall. A
machine reference (a fixed pure-Python loop and a fixed matrix product, timed before and
after) is printed too: the same VM has run them up to 2.5x slower on some days.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ONE_THREAD = {k: "1" for k in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS")}


def overrides(n: int, duration_s: float) -> list[str]:
    """The benchmark scenario as ``--set`` overrides of the default scenario."""
    lanes = "[0]" if n <= 3 else "[0,1,2]"
    return ['network.name="open_highway"', f"clusters.0.vehicles={n}", f"clusters.0.lanes={lanes}",
            "clusters.0.time_gap_s=1.5", f"duration_s={duration_s}", "vehicle_types.passenger.max_speed_mps=25.0",
            'solutions=[{name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]']


CASE = r"""
import time
t_start = time.perf_counter()
import json, sys
from v2v.config.scenario import load_scenario
from v2v.run import run_scenario
n, replay_on, out, repeat = int(sys.argv[1]), sys.argv[2] == "1", sys.argv[3], int(sys.argv[5])
if int(sys.argv[6]) >= 0:  # one core for the process and every thread it starts
    import os
    os.sched_setaffinity(0, {int(sys.argv[6])})
ov = json.loads(sys.argv[4])
sc = load_scenario(None, ov)
t_imports = time.perf_counter() - t_start
res = {"startup_s": t_imports, "warm_off": [], "warm_on": []}

def one(scn, replay, tag):
    c0 = time.process_time()
    s = run_scenario(scn, f"{out}_{tag}", quiet=True, replay=replay).summary
    return {"simulated_s": s["simulated_s"], "wall_s": s["wall_s"], "cpu_s": time.process_time() - c0,
            "timing_s": s["timing_s"]}

# cold: the first run of the process (and the first with the replay on: rerun's import, the
# blueprint's build); warm: next seeds in the same process, replay off then on
res["cold"] = one(sc, False, "cold")
if replay_on:
    res["cold_on"] = one(sc, True, "cold_on")
for k in range(repeat):  # pair k: one seed, replay off then on (on then off for odd k: the machine drifts)
    scn = load_scenario(None, ov + [f"seed={sc.seed + 1 + k}"])
    if replay_on and k % 2:
        res["warm_on"].append(one(scn, True, f"on{k}"))
    res["warm_off"].append(one(scn, False, f"off{k}"))
    if replay_on and not k % 2:
        res["warm_on"].append(one(scn, True, f"on{k}"))
print(json.dumps(res))
"""


def run_case(n: int, duration: float, replay_on: bool, repeat: int, out: Path, cpu: int = -1) -> dict:
    """One fresh process: start-up (interpreter + imports), a cold run (compiled kernels
    loaded, lazy imports paid), then ``repeat`` warm runs with the replay off (and each paired
    with the same seed with the replay on, before it for odd pairs); ``warm`` / ``warm_replay``
    are the fastest, ``replay_share_paired_median`` the median of the pairs' shares,
    ``replay_share_in_run_median`` the median of :func:`_in_run_share` over the replay-on runs.
    ``cpu`` >= 0: the process (all its threads) runs on that CPU only."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-c", CASE, str(n), "1" if replay_on else "0", str(out),
                        json.dumps(overrides(n, duration)), str(repeat), str(cpu)],
                       capture_output=True, text=True, check=True, env={**os.environ, **ONE_THREAD})
    r = json.loads(p.stdout.strip().splitlines()[-1])
    r["process_s"] = time.perf_counter() - t0
    r["warm"] = min(r["warm_off"], key=lambda c: c["wall_s"])
    if r["warm_on"]:
        r["warm_replay"] = min(r["warm_on"], key=lambda c: c["wall_s"])
        r["replay_share_paired_median"] = statistics.median(
            1.0 - a["wall_s"] / b["wall_s"] for a, b in zip(r["warm_off"], r["warm_on"], strict=True))
        r["replay_share_in_run_median"] = statistics.median(_in_run_share(c) for c in r["warm_on"])
    return r


def _in_run_share(c: dict) -> float:
    """The replay's stages (``timing_s`` ``replay`` + ``replay_static_truth``: the time spent
    in the replay's code, timed inside the run) over the run's wall time."""
    t = c["timing_s"]
    if "replay" not in t:  # (a revision before the replay stage: its share is not known)
        return float("nan")
    return (t["replay"] + t["replay_static_truth"]) / c["wall_s"]


REFERENCE = r"""
import json, time
import numpy as np
t = time.perf_counter()
s = 0
for i in range(10_000_000):
    s += i
py_s = time.perf_counter() - t
a = np.linalg.qr(np.random.default_rng(0).normal(size=(156, 156)))[0]  # orthogonal: b keeps its norm
b = a.copy()
t = time.perf_counter()
for _ in range(2000):
    b = a @ b
blas_s = time.perf_counter() - t
print(json.dumps({"python_loop_s": py_s, "matmul_s": blas_s}))
"""


def machine_reference() -> dict:
    """Two fixed workloads, the same code every day, in a fresh one-thread process: 10^7
    pure-Python integer additions (what the interpreter-bound part of a run scales with) and
    2000 products of 156 x 156 float64 matrices (BLAS, one thread: the N = 20 filter's
    covariance updates are this kind of work). Printed before and after the cases, so runs
    on different days (or a machine that slows down midway) can be compared."""
    p = subprocess.run([sys.executable, "-c", REFERENCE], capture_output=True, text=True, check=True,
                       env={**os.environ, **ONE_THREAD})
    return json.loads(p.stdout.strip().splitlines()[-1])


def interpreter() -> dict:
    """This interpreter: version, executable, and whether libpython is a shared library
    (pyenv's default ``--enable-shared`` build, no PGO) or linked into the executable (a
    distribution's build, PGO + LTO). Interpreter-bound figures, the machine reference's
    Python loop among them, are only comparable between runs on the same kind of build."""
    try:
        with open("/proc/self/maps") as f:
            shared: bool | None = any("libpython" in line for line in f)
    except OSError:  # (not Linux)
        shared = None
    return {"version": sys.version.split()[0], "executable": os.path.realpath(sys.executable), "libpython_shared": shared}


def _print_reference(tag: str, ref: dict) -> None:
    print(f"machine reference ({tag}): 10^7 Python additions {ref['python_loop_s']:.2f} s, "
          f"2000 x (156 x 156) matmul {ref['matmul_s']:.2f} s", flush=True)


def run_monte_carlo(n_runs: int, duration: float, workers: int, out: Path) -> dict:
    """``n_runs`` seeds of the N = 3 case through :func:`v2v.sweep.run_study`."""
    os.environ.update(ONE_THREAD)  # inherited by the LocalCluster's worker processes
    from v2v.sweep import load_study, run_study

    study = out / "mc_study.toml"
    lines = [f"seeds = {{start = 1, count = {n_runs}}}", "replay = false", "", "[set]"]
    for o in overrides(3, duration):
        key, val = o.split("=", 1)
        lines.append(f'"{key}" = {val}')
    study.write_text("\n".join(lines) + "\n")
    t0 = time.perf_counter()
    res = run_study(load_study(study), out / "mc", workers=workers, quiet=True)
    wall = time.perf_counter() - t0
    df = res.table
    ok = df[df["status"] == "ok"]
    return {"runs": n_runs, "failed": res.failed, "duration_s": duration, "workers": workers, "wall_s": wall,
            "per_run_wall_mean_s": float(ok["wall_s"].mean()) if len(ok) else float("nan")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="*", default=[3, 10, 20, 40])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--no-replay-on", action="store_true", help="only the replay-off cases")
    ap.add_argument("--repeat", type=int, default=3, help="warm runs per case (the fastest is reported)")
    ap.add_argument("--mc-runs", type=int, default=0, help="Monte Carlo runs at N = 3 (0 = skip; issue 7: 100)")
    ap.add_argument("--mc-duration", type=float, default=60.0)
    ap.add_argument("--mc-workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=None, help="write bench_run.json here")
    ap.add_argument("--cpu", type=int, default=None,
                    help="pin each case's process to this CPU (default: the first this process may use; -1: do not pin)")
    args = ap.parse_args(argv)
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    cpu = (allowed[0] if allowed else -1) if args.cpu is None else args.cpu
    if cpu >= 0 and allowed and cpu not in allowed:
        print(f"bench_run: error: --cpu {cpu}: this process may run on CPUs {allowed} only -- fix: give one of them, "
              "or -1 not to pin", file=sys.stderr)
        return 2
    rows = []
    mc = None
    refs = {"before": machine_reference()}
    interp = interpreter()
    link = {True: "shared libpython", False: "libpython linked in", None: "libpython linkage unknown"}[interp["libpython_shared"]]
    print(f"interpreter: Python {interp['version']} {interp['executable']} ({link})", flush=True)
    _print_reference("before", refs["before"])
    print(f"cases pinned to CPU {cpu} (the process and all its threads)" if cpu >= 0 else "cases not pinned", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            r = run_case(n, args.duration, not args.no_replay_on, max(1, args.repeat), Path(tmp) / f"n{n}", cpu)
            r["n"] = n
            for tag, label in (("cold", "replay=off cold"), ("cold_on", "replay=on  cold"), ("warm", "replay=off warm"),
                               ("warm_replay", "replay=on  warm")):
                if tag not in r:
                    continue
                c = r[tag]
                c["rtf"] = c["simulated_s"] / c["wall_s"]
                t = c["timing_s"]
                print(f"N={n:3d} {label}: simulated {c['simulated_s']:6.1f} s  "
                      f"wall {c['wall_s']:7.2f} s  cpu {c['cpu_s']:7.2f} s  RTF {c['rtf']:7.1f}x  | "
                      + "  ".join(f"{k} {v:.2f}" for k, v in t.items()), flush=True)
            walls = "  ".join(f"{c['wall_s']:.2f}" for c in r["warm_off"])
            walls_on = "  ".join(f"{c['wall_s']:.2f}" for c in r["warm_on"])
            print(f"        warm walls off: {walls}" + (f"; on: {walls_on}" if walls_on else "")
                  + f"; start-up (interpreter + imports) {r['startup_s']:.2f} s, whole process {r['process_s']:.2f} s",
                  flush=True)
            rows.append(r)
        if args.mc_runs:
            mc = run_monte_carlo(args.mc_runs, args.mc_duration, args.mc_workers, Path(tmp))
    refs["after"] = machine_reference()
    _print_reference("after", refs["after"])
    if rows:
        print("\nreal-time factor (simulated s / wall s of the run), one core; cold = first run of a fresh")
        print(f"process (kernels loaded, lazy imports), warm = fastest of {max(1, args.repeat)} further runs in the "
              "same process (a sweep worker):")
        print(f"{'N':>4s} {'off, cold':>10s} {'off, warm':>10s} {'on, warm':>9s} {'replay share':>13s} "
              f"{'paired median':>14s} {'in-run median':>14s}")
        for r in rows:
            on = r.get("warm_replay")
            share = f"{1.0 - r['warm']['wall_s'] / on['wall_s']:13.1%}" if on else f"{'-':>13s}"
            paired = f"{r['replay_share_paired_median']:14.1%}" if on else f"{'-':>14s}"
            in_run = f"{r['replay_share_in_run_median']:14.1%}" if on and math.isfinite(
                r["replay_share_in_run_median"]) else f"{'-':>14s}"
            rtf_on = f"{on['rtf']:9.1f}" if on else f"{'-':>9s}"
            print(f"{r['n']:4d} {r['cold']['rtf']:10.1f} {r['warm']['rtf']:10.1f} {rtf_on} {share} {paired} {in_run}")
        print("replay share: 1 - fastest off / fastest on; paired median: the median over the seeds of "
              "1 - off / on of the same seed (each pair run back to back, in alternating order); in-run median: "
              "the median over the replay-on runs of the time inside the replay's code (timing_s replay + "
              "replay_static_truth) over the run's wall time")
    if mc:
        print(f"\nMonte Carlo: {mc['runs']} runs x {mc['duration_s']:.0f} s, N = 3, {mc['workers']} worker processes: "
              f"{mc['wall_s']:.1f} s wall ({mc['failed']} failed; mean run wall {mc['per_run_wall_mean_s']:.2f} s)")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "bench_run.json").write_text(json.dumps({"cases": rows, "monte_carlo": mc, "machine_reference": refs, "interpreter": interp,
                                                           "cpu": cpu}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
