"""A/B of the working tree against another revision: are the outputs identical, and which is faster?

A speed change must leave the simulation's results alone, and on this project's shared VMs a
few-percent speed difference is only visible when the two versions run interleaved in the
same minutes. This script does both against ``--base`` (a git revision, checked out as a
temporary worktree; or ``--base-dir``, an existing checkout whose compiled kernels are kept
between invocations: a fresh tree compiles its numba kernels on first use, 1-2 min).

``outputs``: runs the comparison scenarios (the default scenario, ``open_highway`` with 3 and
20 vehicles, the urban canyon, residential, hospital loop, carrier-phase and highway drives,
a lossy exchange, four injected faults; each a few tens of simulated seconds, replay off)
with both versions in fresh processes, and compares ``truth.parquet`` and ``epochs.parquet``
(same columns, dtypes and values; floats bit for bit, so -0.0 differs from 0.0, NaN equals
NaN), ``summary.json`` apart from the wall times, and every solution's per-update log (columns
of :attr:`v2v.pipeline.SolutionRecord.updates`), values and types alike. Exit status 1 if any
differ. (The update logs are read through ``v2v.pipeline.run_solution``, which ``run.py``
calls through the module, and ``SolutionRecord.log``, both from 551735d on; an older base is
refused with a one-line error.)

``speed``: per cluster size (the ``bench_run.py`` scenario), ``--rounds`` rounds in which each
version runs in a fresh process (the two in alternating order): a cold run, then ``--repeat``
warm runs of other seeds; prints each round's fastest and median warm wall times and the
ratio head / base of the medians of the rounds' fastest runs. Nothing is asserted.

    .venv/bin/python benchmarks/ab_compare.py outputs --base HEAD~3
    .venv/bin/python benchmarks/ab_compare.py speed --base HEAD~3 --sizes 3 20 --rounds 3 --repeat 8
    .venv/bin/python benchmarks/ab_compare.py outputs --base-dir /tmp/v2v-base --only demo hw3
"""

from __future__ import annotations

import argparse
import json
import math
import os
import pickle
import statistics
import struct
import subprocess
import sys
import tempfile
from contextlib import contextmanager
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))
from bench_run import ONE_THREAD, overrides  # noqa: E402

SCEN = ROOT / "scenarios"
_HW = ['network.name="open_highway"', "clusters.0.time_gap_s=1.5", "vehicle_types.passenger.max_speed_mps=25.0"]
_FAULTS = ('faults=[{kind="clock_jump", start_s=10.0, vehicles=["c1.1"]}, {kind="gnss_outage", start_s=15.0, '
           'duration_s=5.0}, {kind="pr_blunder", start_s=20.0, duration_s=10.0, size_m=30.0, probability=0.2}, '
           '{kind="uwb_blunder", start_s=5.0, duration_s=20.0, size_m=5.0, probability=0.1}]')
#: name -> (scenario file or None for the built-in default, --set overrides)
CASES: dict[str, tuple[str | None, list[str]]] = {
    "demo": (None, ["duration_s=30.0"]),
    "hw20": (None, [*_HW, "clusters.0.vehicles=20", "clusters.0.lanes=[0,1,2]", "duration_s=20.0"]),
    "hw3": (None, [*_HW, "clusters.0.vehicles=3", "clusters.0.lanes=[0]", "duration_s=60.0"]),
    "urban": (str(SCEN / "urban_canyon.toml"), ["duration_s=30.0"]),
    "residential": (str(SCEN / "residential.toml"), ["duration_s=30.0"]),
    "hospital": (str(SCEN / "hospital_loop.toml"), ["duration_s=30.0"]),
    "phase": (str(SCEN / "phase_init_drive.toml"), ["duration_s=30.0"]),
    "open_highway": (str(SCEN / "open_highway.toml"), ["duration_s=30.0"]),
    "lossy": (None, ["duration_s=30.0", "exchange.loss_probability=0.2", "exchange.latency_s=0.05"]),
    "faults": (None, ["duration_s=40.0", _FAULTS]),
}

# Runs in a fresh interpreter with PYTHONPATH = the tree under test.
_OUTPUTS = r"""
import json, pickle, sys
from pathlib import Path
import v2v, v2v.pipeline as pl
from v2v.config.scenario import load_scenario
from v2v.run import run_scenario
out, cases = Path(sys.argv[1]), json.loads(sys.argv[2])
store = []
orig = pl.run_solution
def wrapped(*a, **k):  # the solutions' records (the same object every chunk)
    rec = orig(*a, **k)
    if all(r is not rec for r in store):
        store.append(rec)
    return rec
pl.run_solution = wrapped
for name, (path, sets) in cases.items():
    store.clear()
    run_scenario(load_scenario(path, sets), out / name, quiet=True, replay=False)
    if not store or not all(hasattr(r, "log") for r in store):  # (both from 551735d on)
        raise SystemExit("its update logs cannot be read (run.py calls v2v.pipeline.run_solution through the "
                         "module, and SolutionRecord keeps a log, from 551735d on): compare with a newer revision")
    with open(out / name / "updates.pkl", "wb") as f:
        pickle.dump([(r.name, r.log.columns()) for r in store], f)
print(json.dumps({"v2v": v2v.__file__}))
"""

_SPEED = r"""
import json, statistics, sys, time
from v2v.config.scenario import load_scenario
from v2v.run import run_scenario
out, sets, repeat = sys.argv[1], json.loads(sys.argv[2]), int(sys.argv[3])
run_scenario(load_scenario(None, sets), f"{out}/cold", quiet=True, replay=False)
walls = []
for k in range(repeat):
    t = time.perf_counter()
    run_scenario(load_scenario(None, sets + [f"seed={k + 2}"]), f"{out}/w{k % 2}", quiet=True, replay=False)
    walls.append(time.perf_counter() - t)
print(json.dumps({"min": min(walls), "median": statistics.median(walls)}))
"""


@contextmanager
def base_tree(rev: str | None, base_dir: Path | None):
    """The base version's source tree: ``base_dir`` as it is, or a temporary worktree of ``rev``."""
    if base_dir is not None:
        if not (base_dir / "v2v" / "__init__.py").is_file():
            raise SystemExit(f"ab_compare: --base-dir {base_dir} is not a v2v checkout (no v2v/__init__.py)")
        yield base_dir
        return
    with tempfile.TemporaryDirectory(prefix="v2v-ab-") as tmp:
        tree = Path(tmp) / "base"
        try:
            p = subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", str(tree), rev or "HEAD"],
                               capture_output=True, text=True)
            if p.returncode:
                why = (p.stderr.strip().splitlines() or ["git worktree add failed"])[-1]
                raise SystemExit(f"ab_compare: --base {rev}: {why}")
            yield tree
        finally:  # (also after Ctrl-C; prune forgets a worktree whose folder is already gone)
            subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(tree)], capture_output=True)
            subprocess.run(["git", "-C", str(ROOT), "worktree", "prune"], capture_output=True)


def _run(tree: Path, code: str, args: list[str]) -> dict:
    env = {**os.environ, **ONE_THREAD, "PYTHONPATH": str(tree)}
    p = subprocess.run([sys.executable, "-c", code, *args], capture_output=True, text=True, env=env, cwd=str(tree))
    if p.returncode:
        last = (p.stderr.strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"ab_compare: the run in {tree} failed: {last}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def identical(x, y) -> bool:
    """Bit for bit: the same types, floats with the same bits (NaN equal to NaN, -0.0 not
    equal to 0.0), containers element by element."""
    if type(x) is not type(y):
        return False
    if isinstance(x, float):
        return struct.pack("<d", x) == struct.pack("<d", y) or (math.isnan(x) and math.isnan(y))
    if isinstance(x, list | tuple):
        return len(x) == len(y) and all(identical(p, q) for p, q in zip(x, y, strict=True))
    if isinstance(x, dict):
        return x.keys() == y.keys() and all(identical(x[k], y[k]) for k in x)
    return x == y


def _frames_identical(a, b) -> bool:
    """Two tables with the same columns, dtypes and values, float columns bit for bit (NaN
    where NaN)."""
    import numpy as np

    if list(a.columns) != list(b.columns) or list(a.dtypes) != list(b.dtypes) or len(a) != len(b):
        return False
    for c in a.columns:
        x, y = a[c].to_numpy(), b[c].to_numpy()
        if x.dtype.kind == "f":
            nan = np.isnan(x)
            bits = f"i{x.dtype.itemsize}"
            if not (np.array_equal(nan, np.isnan(y))
                    and np.array_equal(np.ascontiguousarray(x[~nan]).view(bits), np.ascontiguousarray(y[~nan]).view(bits))):
                return False
        elif not identical(x.tolist(), y.tolist()):
            return False
    return True


def relative_difference(x, y) -> float:
    """The largest ``|x - y|`` over the numbers of two equally shaped values (arrays, lists,
    dicts of them; NaN equal to NaN), each array or list relative to its largest magnitude
    (a column's scale: an error that crosses zero would make elementwise ratios meaningless);
    inf when anything else differs (a different shape, key, type or non-numeric value): how
    far a change that is not bit-identical moved the numbers."""
    import numpy as np

    if isinstance(x, dict) and isinstance(y, dict):
        if x.keys() != y.keys():
            return math.inf
        return max((relative_difference(x[k], y[k]) for k in x), default=0.0)
    if isinstance(x, list | tuple) and isinstance(y, list | tuple) and not (
            all(isinstance(v, int | float) for v in x) and all(isinstance(v, int | float) for v in y)):
        if len(x) != len(y):
            return math.inf
        return max((relative_difference(p, q) for p, q in zip(x, y, strict=True)), default=0.0)
    try:
        xa, ya = np.asarray(x), np.asarray(y)
    except (TypeError, ValueError):
        return 0.0 if x == y else math.inf
    if xa.shape != ya.shape:
        return math.inf
    if xa.dtype.kind not in "fiub" or ya.dtype.kind not in "fiub":
        return 0.0 if identical(xa.tolist(), ya.tolist()) else math.inf
    xa, ya = xa.astype(float), ya.astype(float)
    finite = np.isfinite(xa)  # NaN and infinities must match where they are
    if not (np.array_equal(finite, np.isfinite(ya)) and np.array_equal(xa[~finite], ya[~finite], equal_nan=True)):
        return math.inf
    xa, ya = xa[finite], ya[finite]
    diff = float(np.abs(xa - ya).max(initial=0.0))
    return diff / float(np.maximum(np.abs(xa), np.abs(ya)).max()) if diff else 0.0


def _rel(v: float) -> str:
    return "other values" if math.isinf(v) else f"largest relative difference {v:.1e}"


def compare_run(a: Path, b: Path) -> list[str]:
    """What differs between two run folders of the same scenario (empty: identical); each
    difference with its largest relative difference (:func:`relative_difference`)."""
    import pandas as pd

    diffs = []
    for f in ("truth.parquet", "epochs.parquet"):
        fa, fb = pd.read_parquet(a / f), pd.read_parquet(b / f)
        if not _frames_identical(fa, fb):
            same = list(fa.columns) == list(fb.columns) and len(fa) == len(fb)
            if not same:
                diffs.append(f"{f} (other columns or rows)")
                continue
            # the columns that differ, each with its largest relative difference
            cols = {c: relative_difference(fa[c].to_numpy(), fb[c].to_numpy()) for c in fa.columns
                    if not _frames_identical(fa[[c]], fb[[c]])}
            diffs.append(f"{f}: " + ", ".join(f"{c} ({_rel(v)})" for c, v in cols.items()))
    sa, sb = (json.loads((d / "summary.json").read_text()) for d in (a, b))
    for s in (sa, sb):
        for k in ("wall_s", "real_time_factor", "timing_s"):
            s.pop(k, None)
    if not identical(sa, sb):
        keys = sorted(k for k in sa.keys() | sb.keys() if not identical(sa.get(k), sb.get(k)))
        diffs.append(f"summary.json: {', '.join(keys)} ({_rel(relative_difference(sa, sb))})")
    ua, ub = (pickle.loads((d / "updates.pkl").read_bytes()) for d in (a, b))
    if [n for n, _ in ua] != [n for n, _ in ub]:
        diffs.append("update logs: other solutions")
    else:
        for (name, ca), (_, cb) in zip(ua, ub, strict=True):
            bad = sorted(k for k in ca.keys() | cb.keys() if not identical(ca.get(k), cb.get(k)))
            if bad:
                worst = max(relative_difference(ca.get(k), cb.get(k)) for k in bad)
                diffs.append(f"update log of {name}: {', '.join(bad)} ({_rel(worst)})")
    return diffs


def cmd_outputs(args: argparse.Namespace) -> int:
    cases = {k: CASES[k] for k in (args.only or CASES)}
    with tempfile.TemporaryDirectory(prefix="v2v-ab-out-") as tmp, base_tree(args.base, args.base_dir) as base:
        out = Path(tmp)
        for tag, tree in (("base", base), ("head", ROOT)):
            print(f"{tag}: running {len(cases)} scenarios ({tree})", flush=True)
            used = Path(_run(tree, _OUTPUTS, [str(out / tag), json.dumps(cases)])["v2v"]).resolve()
            if not used.is_relative_to(tree.resolve()):
                raise SystemExit(f"ab_compare: the {tag} run imported {used}, not the tree {tree}")
        n_diff = 0
        for name in cases:
            diffs = compare_run(out / "base" / name, out / "head" / name)
            n_diff += bool(diffs)
            print(f"{name:14s} {'identical' if not diffs else 'DIFFERENT: ' + '; '.join(diffs)}")
    print(f"{len(cases) - n_diff} of {len(cases)} scenarios identical")
    return 1 if n_diff else 0


def cmd_speed(args: argparse.Namespace) -> int:
    with tempfile.TemporaryDirectory(prefix="v2v-ab-speed-") as tmp, base_tree(args.base, args.base_dir) as base:
        for n in args.sizes:
            sets = overrides(n, args.duration)
            fastest: dict[str, list[float]] = {"base": [], "head": []}
            for r in range(args.rounds):
                order = [("base", base), ("head", ROOT)] if r % 2 == 0 else [("head", ROOT), ("base", base)]
                for tag, tree in order:
                    res = _run(tree, _SPEED, [f"{tmp}/{tag}{n}_{r}", json.dumps(sets), str(args.repeat)])
                    fastest[tag].append(res["min"])
                    print(f"N={n:3d} round {r + 1} {tag}: fastest {res['min']:.4f} s, median {res['median']:.4f} s "
                          f"of {args.repeat} warm runs", flush=True)
            b, h = statistics.median(fastest["base"]), statistics.median(fastest["head"])
            print(f"N={n:3d} head / base = {h / b:.3f} (medians of the rounds' fastest: {h:.4f} / {b:.4f} s; "
                  f"rounds' fastest base {min(fastest['base']):.4f}-{max(fastest['base']):.4f}, "
                  f"head {min(fastest['head']):.4f}-{max(fastest['head']):.4f} s)")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("outputs", "speed"):
        p = sub.add_parser(name)
        g = p.add_mutually_exclusive_group()
        g.add_argument("--base", default="HEAD", help="git revision to compare with (default HEAD)")
        g.add_argument("--base-dir", type=Path, help="an existing checkout to compare with (its compiled kernels kept)")
        if name == "outputs":
            p.add_argument("--only", nargs="+", choices=sorted(CASES), help="these scenarios only")
        else:
            p.add_argument("--sizes", type=int, nargs="+", default=[3, 20])
            p.add_argument("--duration", type=float, default=60.0)
            p.add_argument("--rounds", type=int, default=3)
            p.add_argument("--repeat", type=int, default=8)
    args = ap.parse_args(argv)
    if args.base_dir is not None:
        args.base = None
    return cmd_outputs(args) if args.cmd == "outputs" else cmd_speed(args)


if __name__ == "__main__":
    sys.exit(main())
