"""The filter's compiled kernels on captured real calls: this tree's against another revision's.

A fresh process per cluster size runs the ``bench_run.py`` scenario (``open_highway``, 10 Hz
GNSS, UWB all pairs ~3 Hz, bearings from every vehicle, one GPS+UWB+Bearing solution) with
the named kernels of :mod:`v2v.estimation.kernels` wrapped, and keeps copies of the arguments
of ``--calls`` consecutive calls of each (from call ``--skip`` on: the filter has converged
and the cluster is spread out). It then times those calls, each on fresh copies of its
arrays, with this tree's kernels and, with ``--base REV``, with that revision's
``v2v/estimation/kernels.py`` (compiled in the process, uncached), in ``--passes``
interleaved passes (alternating order: the machine drifts). Printed per kernel: the fastest
and median pass (mean us per call), the ratio of the fastest passes, and the largest
difference of the updated x and P between the two versions (0 = bit-identical).

End-to-end runs of this VM differ by 20-40 % from one run to the next, which hides a change
worth a few percent of a run; the same captured calls timed back to back in one process
resolve a few percent of one kernel. Nothing is asserted.

    .venv/bin/python benchmarks/bench_kernels.py --base HEAD~1 [--sizes 20 40] [--kernels uwb_event_run bearing_batch]
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_run import ONE_THREAD, overrides  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
KERNELS = ("bearing_batch", "uwb_event_run", "sd_pseudorange_vehicles", "sd_doppler_vehicles")

CAPTURE = r"""
import pickle, sys, json
import numpy as np
from v2v.config.scenario import load_scenario
from v2v.estimation import kernels
from v2v.run import run_scenario
n, duration, names, skip, calls, out, run_dir = (int(sys.argv[1]), float(sys.argv[2]), sys.argv[3].split(","),
                                                int(sys.argv[4]), int(sys.argv[5]), sys.argv[6], sys.argv[7])
ov = json.loads(sys.argv[8])
cap = {k: [] for k in names}
count = dict.fromkeys(names, 0)

def wrap(name):
    f = getattr(kernels, name)
    def w(*a):
        count[name] += 1
        if skip < count[name] <= skip + calls:
            cap[name].append(tuple(x.copy() if isinstance(x, np.ndarray) else x for x in a))
        return f(*a)
    return w

for k in names:
    setattr(kernels, k, wrap(k))  # the filter calls them as kernels.<name>
run_scenario(load_scenario(None, ov), run_dir, quiet=True, replay=False)
with open(out, "wb") as fh:
    pickle.dump({"calls": cap, "count": count}, fh)
"""

TIME = r"""
import importlib.util, json, pickle, sys, time
import numpy as np
from v2v.estimation import kernels
cap_path, base_path, passes = sys.argv[1], sys.argv[2], int(sys.argv[3])
with open(cap_path, "rb") as fh:
    cap = pickle.load(fh)["calls"]
versions = [("head", kernels)]
if base_path:
    spec = importlib.util.spec_from_file_location("base_kernels", base_path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    versions.append(("base", mod))

def fresh(a):
    return tuple(x.copy() if isinstance(x, np.ndarray) else x for x in a)

res = {}
for name, calls in cap.items():
    if not calls:
        continue
    out = {}
    ref = []
    for a in calls:  # (also compiles / loads both versions)
        b = fresh(a)
        getattr(kernels, name)(*b)
        ref.append(b)
    if len(versions) > 1:
        d = 0.0
        for a, r in zip(calls, ref):
            b = fresh(a)
            getattr(versions[1][1], name)(*b)
            d = max(d, float(np.max(np.abs(b[0] - r[0]), initial=0.0)), float(np.max(np.abs(b[1] - r[1]), initial=0.0)))
        out["max_diff_x_P"] = d
    t = {tag: [] for tag, _ in versions}
    for p in range(passes):
        for tag, mod in (versions if p % 2 == 0 else versions[::-1]):
            f = getattr(mod, name)
            s = 0.0
            for a in calls:
                b = fresh(a)
                t0 = time.perf_counter()
                f(*b)
                s += time.perf_counter() - t0
            t[tag].append(s / len(calls))
    out["times_s"] = t
    out["n_state"] = int(calls[0][0].shape[0])
    out["calls"] = len(calls)
    res[name] = out
print(json.dumps(res))
"""


def base_kernels(rev: str, tmp: Path) -> Path:
    """``v2v/estimation/kernels.py`` of ``rev``, with numba's cache off (it would share this
    tree's cache index), written to ``tmp``."""
    src = subprocess.run(["git", "-C", str(ROOT), "show", f"{rev}:v2v/estimation/kernels.py"], capture_output=True,
                         text=True)
    if src.returncode != 0:
        sys.exit(f"--base: git cannot show v2v/estimation/kernels.py at {rev!r}: {src.stderr.strip()}")
    text = src.stdout.replace('"cache": True', '"cache": False')
    if text == src.stdout:
        sys.exit(f"--base: kernels.py of {rev!r} has no '\"cache\": True' setting to turn off; pick a newer revision")
    path = tmp / "base_kernels.py"
    path.write_text(text)
    return path


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[20, 40])
    ap.add_argument("--duration", type=float, default=30.0, help="simulated seconds of the captured run")
    ap.add_argument("--kernels", nargs="+", default=list(KERNELS), choices=KERNELS)
    ap.add_argument("--skip", type=int, default=200, help="calls of each kernel let through before capturing")
    ap.add_argument("--calls", type=int, default=30, help="calls captured per kernel")
    ap.add_argument("--passes", type=int, default=15, help="timed passes over the captured calls per version")
    ap.add_argument("--base", default=None, help="git revision whose kernels.py to time against (default: none)")
    args = ap.parse_args(argv)
    for name, v in (("--calls", args.calls), ("--passes", args.passes)):
        if v < 1:
            sys.exit(f"{name} must be >= 1, got {v}")
    if args.skip < 0 or not args.duration > 0:
        sys.exit("--skip must be >= 0 and --duration > 0")
    env = {**os.environ, **ONE_THREAD}
    with tempfile.TemporaryDirectory(prefix="v2v-bench-kernels-") as tmp_s:
        tmp = Path(tmp_s)
        base = str(base_kernels(args.base, tmp)) if args.base else ""
        print(f"kernels of this tree{' against ' + args.base if args.base else ''}: {args.calls} captured calls "
              f"each (after {args.skip}), {args.passes} passes, one thread", flush=True)
        print(f"{'N':>3} {'kernel':24s} {'states':>6} {'head us (min / median)':>24} "
              f"{'base us (min / median)':>24} {'head/base':>9} {'max |dx|,|dP|':>13}")
        for n in args.sizes:
            cap_path = tmp / f"cap{n}.pkl"
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-c", CAPTURE, str(n), str(args.duration), ",".join(args.kernels),
                            str(args.skip), str(args.calls), str(cap_path), str(tmp / f"run{n}"),
                            json.dumps(overrides(n, args.duration))], check=True, env=env)
            with open(cap_path, "rb") as fh:
                count = pickle.load(fh)["count"]
            p = subprocess.run([sys.executable, "-c", TIME, str(cap_path), base, str(args.passes)], check=True,
                               capture_output=True, text=True, env=env)
            res = json.loads(p.stdout.strip().splitlines()[-1])
            for name in args.kernels:
                if name not in res:
                    print(f"{n:3d} {name:24s} only {count[name]} calls in the run (<= --skip {args.skip})")
                    continue
                r = res[name]
                h = r["times_s"]["head"]
                line = f"{n:3d} {name:24s} {r['n_state']:6d} {1e6 * min(h):11.1f} / {1e6 * statistics.median(h):10.1f}"
                if "base" in r["times_s"]:
                    b = r["times_s"]["base"]
                    line += (f" {1e6 * min(b):11.1f} / {1e6 * statistics.median(b):10.1f} {min(h) / min(b):9.3f}"
                             f" {r['max_diff_x_P']:13.2e}")
                print(line, flush=True)
            print(f"    (N = {n}: capture run and timing {time.perf_counter() - t0:.0f} s)", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
