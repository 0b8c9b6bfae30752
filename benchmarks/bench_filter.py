"""Benchmark: production cluster EKF vs the filterpy reference engine.

Both engines (:class:`v2v.estimation.filter.ClusterEkf`, sparse rows and block-wise
prediction; :class:`v2v.estimation.reference.ReferenceClusterEkf`, dense filterpy) filter
the *same* simulated measurements (:mod:`v2v.estimation.simulate`: an in-line cluster on
a gentle arc, GNSS + UWB between every pair + bearings from the lead and v1 with their
azimuths and yaw rates estimated) for N = 3, 10, 20, 40 vehicles. Printed per N: state size,
measurement updates per epoch, CPU time per epoch of each engine (best of ``--repeat``
runs), the speed ratio measured in this run, and the largest
state / covariance difference between the engines relative to each quantity's scale
(``|a - b| / (|b| + sigma)``; they must agree to 1e-9: tests/test_engines_agree.py).

Plain Python, no asserts: numbers depend on the machine; compare ratios, not seconds.
Both engines share the epoch sequencing of the base class (satellite pairing, screening,
clock-jump test, initialization), which runs as compiled kernels for both; the production
engine also runs each vehicle's whole SD pseudorange / SD Doppler epoch (rows, clock-jump
test, screen, order, sequential updates) in one kernel call, the UWB and bearing batches and the
prediction as compiled kernels, the reference one Python scalar update (dense filterpy) per
measurement. Compare the production column against an earlier run too.
``--profile N`` prints the cProfile top functions of the production engine at N vehicles
(where the remaining time goes) instead of the table.

One core: BLAS is limited to one thread (set before numpy is imported) and times are the
process's CPU seconds (``time.process_time``), which on a shared machine are far steadier
than wall seconds for a single-threaded loop. The production engine's compiled kernels
(:mod:`v2v.estimation.kernels`, numba ``cache=True``) are loaded or compiled by a warm-up
run before timing; that one-off cost is printed separately. The reference is O(n^3) per
scalar update, so for N >= 40 both engines are timed on the first ``--large-duration``
seconds only (the ``epochs`` column).

    .venv/bin/python benchmarks/bench_filter.py [--sizes 3 10 20 40] [--duration 5] [--repeat 3]
    .venv/bin/python benchmarks/bench_filter.py --profile 10
"""

from __future__ import annotations

import argparse
import cProfile
import os
import pstats
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

from v2v.estimation.filter import ClusterEkf, FilterConfig  # noqa: E402
from v2v.estimation.layout import StateLayout  # noqa: E402
from v2v.estimation.reference import ReferenceClusterEkf  # noqa: E402
from v2v.estimation.simulate import SimScenario, run_filter, simulate, vehicle_ids  # noqa: E402


def _setup(n: int, duration_s: float, seed: int):
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=n, duration_s=duration_s, turn_rate_rps=0.05, bearing_vehicles=("lead", "v1"),
                      lane_offsets_m=(0.0, 3.5, -3.5))
    ids = vehicle_ids(n)
    lay = StateLayout.build(lead="lead", vehicles=ids[1:], azimuth_vehicles=("lead", "v1"), azimuth_rates=True)
    eps = simulate(scn, cfg, np.random.default_rng(seed))
    return cfg, scn, lay, eps


def _run(engine_cls, cfg, lay, eps, dt_s):
    ekf = engine_cls(lay, cfg)
    n_upd = 0
    t0 = time.process_time()
    states = []
    for _ep, infos in run_filter(ekf, eps, dt_s):
        n_upd += len(infos)
        states.append((ekf.x, ekf.P))
    cpu = time.process_time() - t0
    return cpu, n_upd, states


def _rel_diff(a: np.ndarray, b: np.ndarray, scale: np.ndarray) -> float:
    return float(np.max(np.abs(a - b) / (np.abs(b) + scale + 1e-300)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[3, 10, 20, 40], help="cluster sizes N (vehicles)")
    ap.add_argument("--duration", type=float, default=5.0, help="simulated seconds per run (10 Hz epochs)")
    ap.add_argument("--large-duration", type=float, default=1.0,
                    help="simulated seconds for N >= 40 (the dense reference is O(n^3) per update)")
    ap.add_argument("--repeat", type=int, default=3, help="timing repeats (best is reported)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--profile", type=int, metavar="N", help="profile the production engine at N vehicles")
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    cfg, scn, lay, eps = _setup(3, 1.0, args.seed)
    _run(ClusterEkf, cfg, lay, eps, scn.dt_s)  # load (or compile, first time on this machine) the kernels
    print(f"kernel load/compile + 1 s warm-up run: {time.perf_counter() - t0:.2f} s wall")

    if args.profile is not None:
        cfg, scn, lay, eps = _setup(args.profile, args.duration, args.seed)
        prof = cProfile.Profile()
        prof.enable()
        _run(ClusterEkf, cfg, lay, eps, scn.dt_s)
        prof.disable()
        pstats.Stats(prof).sort_stats("tottime").print_stats(20)
        return 0

    print(f"{'N':>3} {'states':>6} {'epochs':>6} {'upd/ep':>7} {'prod ms/ep':>11} {'ref ms/ep':>10} {'speed-up':>9} "
          f"{'max dx rel':>11} {'max dP rel':>11}", flush=True)
    table = []
    for n in args.sizes:
        cfg, scn, lay, eps = _setup(n, args.large_duration if n >= 40 else args.duration, args.seed)
        best = {}
        for name, cls in (("prod", ClusterEkf), ("ref", ReferenceClusterEkf)):
            walls = []
            for _ in range(args.repeat if name == "prod" or n < 40 else 1):
                wall, n_upd, states = _run(cls, cfg, lay, eps, scn.dt_s)
                walls.append(wall)
            best[name] = (min(walls), n_upd, states)
        (tp, n_upd, sp), (tr, _, sr) = best["prod"], best["ref"]
        dx = dp = 0.0
        for (xp, pp), (xr, pr) in zip(sp, sr, strict=True):
            sd = np.sqrt(np.abs(np.diag(pr)))
            dx = max(dx, _rel_diff(xp, xr, sd))
            dp = max(dp, _rel_diff(pp, pr, np.outer(sd, sd)))
        n_ep = len(eps)
        flag = "" if max(dx, dp) <= 1e-9 else "  <-- engines DISAGREE (> 1e-9)"
        table.append((n, tr / tp))
        print(f"{n:>3} {lay.n:>6} {n_ep:>6} {n_upd / n_ep:>7.1f} {1e3 * tp / n_ep:>11.3f} {1e3 * tr / n_ep:>10.3f} "
              f"{tr / tp:>8.1f}x {dx:>11.1e} {dp:>11.1e}{flag}", flush=True)
    print("\nspeed-up of the production engine over the filterpy reference (CPU time per epoch, one thread):")
    print("  " + "  ".join(f"N={n}: {r:.0f}x" for n, r in table))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
