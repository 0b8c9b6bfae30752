"""End-to-end speed: real-time factor (simulated s / wall s) vs cluster size, and where the time goes.

Configuration (issue 7): 10 Hz GNSS, UWB between all pairs at ~3 Hz, bearings from every
vehicle, one GPS+UWB+Bearing solution, replay off and on, on `open_highway` (lanes 0-2).
Each case runs in a fresh process (libsumo: one simulation per process), one after
another, so the numbers are single-core wall times measured in this one invocation.

    .venv/bin/python benchmarks/bench_run.py [--sizes 3 10 20 40] [--duration 60] [--out DIR]

Prints a table; nothing is asserted.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CASE = r"""
import json, sys, time
from v2v.config.scenario import load_scenario
from v2v.run import run_scenario
n, dur, replay, out = int(sys.argv[1]), float(sys.argv[2]), sys.argv[3] == "1", sys.argv[4]
lanes = "[0]" if n <= 3 else "[0,1,2]"
sc = load_scenario(None, [
    'network.name="open_highway"', f"clusters.0.vehicles={n}", f"clusters.0.lanes={lanes}",
    "clusters.0.time_gap_s=1.5", f"duration_s={dur}", "vehicle_types.passenger.max_speed_mps=25.0",
    'solutions=[{name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]',
])
r = run_scenario(sc, out, quiet=True, replay=replay)
s = r.summary
print(json.dumps({"simulated_s": s["simulated_s"], "wall_s": s["wall_s"], "timing_s": s["timing_s"]}))
"""


def run_case(n: int, duration: float, replay: bool, out: Path) -> dict:
    p = subprocess.run([sys.executable, "-c", CASE, str(n), str(duration), "1" if replay else "0", str(out)],
                       capture_output=True, text=True, check=True)
    return json.loads(p.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[3, 10, 20, 40])
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=None, help="write results.json here")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for n in args.sizes:
            for replay in (False, True):
                r = run_case(n, args.duration, replay, Path(tmp) / f"n{n}_{int(replay)}")
                r.update(n=n, replay=replay, rtf=r["simulated_s"] / r["wall_s"])
                rows.append(r)
                t = r["timing_s"]
                print(f"N={n:3d} replay={'on ' if replay else 'off'} simulated {r['simulated_s']:6.1f} s  wall {r['wall_s']:7.1f} s  "
                      f"RTF {r['rtf']:7.2f}x  | " + "  ".join(f"{k} {v:.2f}" for k, v in t.items()), flush=True)
    print("\nreal-time factor (simulated s / wall s), one core:")
    print(f"{'N':>4s} {'replay off':>11s} {'replay on':>10s} {'replay share':>13s}")
    for n in args.sizes:
        off = next(r for r in rows if r["n"] == n and not r["replay"])
        on = next(r for r in rows if r["n"] == n and r["replay"])
        share = 1.0 - off["wall_s"] / on["wall_s"]
        print(f"{n:4d} {off['rtf']:11.2f} {on['rtf']:10.2f} {share:13.1%}")
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "bench_run.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
