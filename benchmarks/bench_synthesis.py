"""GNSS measurement synthesis speed: milliseconds per receiver-epoch, open sky vs. urban canyon.

Configuration (issue 7): a cluster of ``--vehicles`` vehicles on lanes 0 and 1, 10 Hz GNSS,
no estimation (``solutions=[]``), replay off. Each network runs in a fresh process
(libsumo: one simulation per process), one after another, so the numbers are single-core
wall times measured in this one invocation. The GNSS time is the run's own
``timing_s["gnss"]`` plus its ``occlusion`` stage (light-time geometry, common errors, sky
queries and per-receiver synthesis; without UWB and bearings the occlusion stage is the sky
queries alone); the sky column is the part spent in ``OcclusionGeometry.sky_many`` (building
blocking, canopy, wall echoes). A receiver-epoch is one vehicle at one GNSS epoch. The CPU
columns are the process CPU time of the same parts (robust when the machine is shared);
the compiled occlusion and GNSS kernels are loaded (or, on the first run after an install,
compiled) before the timed region: ``warm_up_cpu_s`` and ``gnss_warm_up_cpu_s``.

    .venv/bin/python benchmarks/bench_synthesis.py [--nets open_highway urban_canyon]
        [--vehicles 20] [--duration 60] [--out DIR]

Prints a table (and writes ``synthesis.md`` / ``synthesis.csv`` with ``--out``); nothing is
asserted.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
from pathlib import Path

CASE = r"""
import json, sys, time
from v2v.config.scenario import load_scenario
from v2v.run import run_scenario
from v2v.sensors.gnss import receiver
from v2v.world import occlusion

net, n, dur, out = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4]
stats = {"receiver_epochs": 0, "sky_s": 0.0, "rays": 0, "gnss_cpu_s": 0.0, "sky_cpu_s": 0.0}
epochs = receiver.GnssSynthesizer._epochs  # every batch of epochs (feed_many, feed, epoch) goes through it
sky_many = occlusion.OcclusionGeometry.sky_many


def counted_epochs(self, due):
    stats["receiver_epochs"] += sum(len(v) for _, v in due)
    c0 = time.process_time()
    out = epochs(self, due)
    stats["gnss_cpu_s"] += time.process_time() - c0
    return out


def timed_sky_many(self, *args, **kwargs):
    t0, c0 = time.perf_counter(), time.process_time()
    res = sky_many(self, *args, **kwargs)
    stats["sky_s"] += time.perf_counter() - t0
    stats["sky_cpu_s"] += time.process_time() - c0
    stats["rays"] += res.blocked.size
    return res


# Compiled kernels (numba) are loaded from their on-disk cache, or compiled on the very first
# run after an install: warm them up outside the timed region (a one-time cost, reported).
c0 = time.process_time()
getattr(occlusion, "warm_up", lambda: None)()  # absent before the compiled kernels
stats["warm_up_cpu_s"] = time.process_time() - c0
c0 = time.process_time()
getattr(receiver, "warm_up", lambda: None)()  # GNSS kernels (absent before they were compiled)
stats["gnss_warm_up_cpu_s"] = time.process_time() - c0


receiver.GnssSynthesizer._epochs = counted_epochs
occlusion.OcclusionGeometry.sky_many = timed_sky_many
sc = load_scenario(None, [
    f'network.name="{net}"', f"clusters.0.vehicles={n}", "clusters.0.lanes=[0,1]", f"duration_s={dur}",
    "solutions=[]",
])
r = run_scenario(sc, out, quiet=True, replay=False)
s = r.summary
# the run times its sky queries as their own stage (occlusion; with no UWB or bearings nothing
# else is): GNSS synthesis is gnss + occlusion (older revisions: gnss alone, no occlusion key)
stats.update(gnss_s=s["timing_s"]["gnss"] + s["timing_s"].get("occlusion", 0.0), simulated_s=s["simulated_s"], nlos_fraction=s["gnss"]["nlos_fraction"])
print(json.dumps(stats))
"""

COLUMNS = ("network", "vehicles", "simulated_s", "receiver_epochs", "rays", "gnss_s", "gnss_ms_per_rx_epoch",
           "sky_ms_per_rx_epoch", "other_ms_per_rx_epoch", "gnss_cpu_s", "cpu_ms_per_rx_epoch",
           "sky_cpu_ms_per_rx_epoch", "warm_up_cpu_s", "gnss_warm_up_cpu_s", "nlos_fraction")


def run_case(net: str, n: int, duration: float, out: Path) -> dict:
    p = subprocess.run([sys.executable, "-c", CASE, net, str(n), str(duration), str(out)],
                       capture_output=True, text=True, check=True)
    r = json.loads(p.stdout.strip().splitlines()[-1])
    k = max(r["receiver_epochs"], 1)
    return {
        "network": net,
        "vehicles": n,
        "simulated_s": r["simulated_s"],
        "receiver_epochs": r["receiver_epochs"],
        "rays": r["rays"],
        "gnss_s": r["gnss_s"],
        "gnss_ms_per_rx_epoch": 1e3 * r["gnss_s"] / k,
        "sky_ms_per_rx_epoch": 1e3 * r["sky_s"] / k,
        "other_ms_per_rx_epoch": 1e3 * (r["gnss_s"] - r["sky_s"]) / k,
        "gnss_cpu_s": r["gnss_cpu_s"],
        "cpu_ms_per_rx_epoch": 1e3 * r["gnss_cpu_s"] / k,
        "sky_cpu_ms_per_rx_epoch": 1e3 * r["sky_cpu_s"] / k,
        "warm_up_cpu_s": r["warm_up_cpu_s"],
        "gnss_warm_up_cpu_s": r.get("gnss_warm_up_cpu_s", 0.0),
        "nlos_fraction": r["nlos_fraction"],
    }


def markdown(rows: list[dict]) -> str:
    head = "| " + " | ".join(COLUMNS) + " |\n|" + "---|" * len(COLUMNS) + "\n"
    fmt = {"simulated_s": "{:.1f}", "gnss_s": "{:.2f}", "gnss_cpu_s": "{:.2f}", "warm_up_cpu_s": "{:.2f}", "gnss_warm_up_cpu_s": "{:.2f}",
           "nlos_fraction": "{:.3f}"}

    def cell(key: str, v) -> str:
        if key.endswith("_ms_per_rx_epoch"):
            return f"{v:.3f}"
        return fmt.get(key, "{}").format(v)

    return head + "".join("| " + " | ".join(cell(c, r[c]) for c in COLUMNS) + " |\n" for r in rows)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nets", nargs="+", default=["open_highway", "urban_canyon"])
    ap.add_argument("--vehicles", type=int, default=20)
    ap.add_argument("--duration", type=float, default=60.0)
    ap.add_argument("--out", type=Path, default=None, help="write synthesis.md and synthesis.csv here")
    args = ap.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for net in args.nets:
            r = run_case(net, args.vehicles, args.duration, Path(tmp) / net)
            rows.append(r)
            print(f"{net:14s} N={r['vehicles']:3d} {r['receiver_epochs']:6d} receiver-epochs  GNSS {r['gnss_s']:6.2f} s  "
                  f"= {r['gnss_ms_per_rx_epoch']:.3f} ms/rx-epoch (sky {r['sky_ms_per_rx_epoch']:.3f}, "
                  f"other {r['other_ms_per_rx_epoch']:.3f}); CPU {r['gnss_cpu_s']:.2f} s = "
                  f"{r['cpu_ms_per_rx_epoch']:.3f} ms/rx-epoch (sky {r['sky_cpu_ms_per_rx_epoch']:.3f})  "
                  f"NLOS {r['nlos_fraction']:.2f}", flush=True)
    table = markdown(rows)
    print()
    print(table, end="")
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "synthesis.md").write_text(table)
        with open(args.out / "synthesis.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=COLUMNS)
            w.writeheader()
            w.writerows(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
