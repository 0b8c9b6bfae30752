"""Lane-level relative positioning of a two-lane cluster for the four sensor combinations.

A cluster (default 4 vehicles, lanes 0 and 1 round robin, so relative lanes are 0 and +-1)
drives ``urban_canyon`` (default); every run processes the same measurements with GPS,
GPS+UWB, GPS+Bearing and GPS+UWB+Bearing (azimuth known). Two variants of the same streets:

* ``canyon``: the net with its buildings (the GNSS and radio environment of the net);
* ``open``: the same net and traffic with the buildings removed (an empty polygon file), to
  separate what the canyon does from what the sensors do.

Scored with :func:`v2v.metrics.lane.lane_level_table` (definitions, alert limits and the
lead-azimuth caveat there): correct relative lane against the lane truth and against the
geometric lane, |across error| 50/95/99 %, misleading-information rates at 3 sigma and at
the 1e-3 protection level, availability and HMI at the 1.0 m across alert limit.

Outputs in ``--out``: ``lane_level.md`` / ``.csv`` (per variant, solution and vehicle),
``lane_level_solutions.csv`` (vehicles pooled), ``lane_level_across_cdf.png`` and
``runs/<variant>/`` (the simulator's run folders).

Run::

    .venv/bin/python experiments/lane_level.py --out /tmp/lane_level
    .venv/bin/python experiments/lane_level.py --out /tmp/lane_level_rinex \\
        --rinex /work/shared/data/gnss_2021-04-28/brdc1180.21n
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

SOLUTIONS = (("GPS", ("gnss",)), ("GPS+UWB", ("gnss", "uwb")), ("GPS+Bearing", ("gnss", "bearing")),
             ("GPS+UWB+Bearing", ("gnss", "uwb", "bearing")))
VARIANTS = ("canyon", "open")
EMPTY_POLY = '<additional>\n</additional>\n'


def solutions_override() -> str:
    """The ``solutions=[...]`` scenario override for the four paper sensor sets (azimuth known)."""
    items = ", ".join("{name=\"" + n + "\", sensors=[" + ", ".join(f'"{s}"' for s in ss) + "]}" for n, ss in SOLUTIONS)
    return f"solutions=[{items}]"


def scenario_overrides(args: argparse.Namespace, variant: str, out: Path, lanes: list[int]) -> list[str]:
    """Scenario overrides shared by the lane-level and FCW experiments."""
    ov = [
        f'network.name="{args.net}"', f"duration_s={args.duration_s}", f"seed={args.seed}",
        f"clusters.0.vehicles={args.vehicles}", f"clusters.0.lanes={lanes}", solutions_override(),
    ]
    if variant == "open":
        empty = out / "no_buildings.poly.xml"
        empty.write_text(EMPTY_POLY, encoding="utf-8")
        ov.append(f'network.polygon_files=["{empty.resolve()}"]')
    if args.rinex:
        ov.append(f'sensors.gnss.ephemeris="{Path(args.rinex).resolve()}"')
    if args.start_utc:
        ov.append(f'start_utc="{args.start_utc}"')
    return ov


# the scenario fields the common options set (an error naming one names the option: v2v.errors.script_options)
COMMON_OPTIONS = {"network.name": "--net", "duration_s": "--duration-s", "seed": "--seed",
                  "clusters.0.vehicles": "--vehicles", "sensors.gnss.ephemeris": "--rinex", "start_utc": "--start-utc"}


def run_variant(args: argparse.Namespace, variant: str, out: Path, lanes: list[int], lanes_option: str | None = None) -> Path:
    """One variant's run; ``lanes_option``: the option ``lanes`` came from, if any."""
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options
    from v2v.run import run_scenario

    folder = out / "runs" / variant
    with script_options(COMMON_OPTIONS | ({"clusters.0.lanes": lanes_option} if lanes_option else {})):
        run_scenario(load_scenario(None, scenario_overrides(args, variant, out, lanes)), folder, quiet=True, replay=False)
    return folder


def _plot_cdf(epochs_by_variant: dict[str, pd.DataFrame], path: Path, alert_limit_m: float) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(epochs_by_variant)
    fig, axes = plt.subplots(1, n, figsize=(5.5 * n, 4.2), squeeze=False)
    for ax, (variant, ep) in zip(axes[0], epochs_by_variant.items(), strict=True):
        ok = ep[ep["initialized"]]
        for i, (sol, g) in enumerate(ok.groupby("solution", sort=False)):
            e = np.sort(np.abs(g["across_err_m"].to_numpy()))
            if e.size:
                ax.plot(e, np.arange(1, e.size + 1) / e.size, color=f"C{i}", label=sol)
        w = float(ep["lane_width_m"].median()) if len(ep) else 3.2
        ax.axvline(alert_limit_m, color="k", ls="--", lw=0.8, label=f"alert limit {alert_limit_m:g} m")
        ax.axvline(w / 2, color="C3", ls=":", lw=0.8, label=f"half lane {w / 2:.2f} m")
        ax.set_xscale("log")
        ax.set_xlabel("|across-track error| (m)")
        ax.set_ylabel("fraction of initialized epochs")
        ax.set_title(variant)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def add_common_arguments(ap: argparse.ArgumentParser, *, duration_s: float, vehicles: int) -> None:
    ap.add_argument("--out", required=True, type=Path, help="output folder")
    ap.add_argument("--net", default="urban_canyon", help="sumo_nets/ name")
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=VARIANTS)
    ap.add_argument("--duration-s", dest="duration_s", type=float, default=duration_s)
    ap.add_argument("--vehicles", type=int, default=vehicles)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--rinex", type=Path, default=None, help="RINEX nav file instead of the nominal constellation")
    ap.add_argument("--start-utc", dest="start_utc", default="", help="scenario start (ISO 8601 UTC)")
    ap.add_argument("--quick", action="store_true", help="short drive (smoke test)")


def main(argv: list[str] | None = None) -> int:
    from v2v.apps.fcw import to_markdown
    from v2v.errors import ScriptArgumentParser
    from v2v.metrics.lane import ACROSS_ALERT_LIMIT_M, lane_level_table


    ap = ScriptArgumentParser(description=__doc__.split("\n\n")[0])
    add_common_arguments(ap, duration_s=120.0, vehicles=4)
    ap.add_argument("--lanes", nargs="+", type=int, default=[0, 1])
    ap.add_argument("--across-alert-limit-m", dest="al", type=float, default=ACROSS_ALERT_LIMIT_M)
    args = ap.parse_args(argv)
    from v2v.errors import check_positive

    check_positive(args.al, "--across-alert-limit-m")
    if args.quick:
        args.duration_s = min(args.duration_s, 20.0)
        args.vehicles = min(args.vehicles, 3)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)

    tables, pooled, epochs_by_variant = [], [], {}
    for variant in args.variants:
        folder = run_variant(args, variant, out, args.lanes, "--lanes")
        ep_path = folder / "epochs.parquet"
        ep = pd.read_parquet(ep_path) if ep_path.is_file() else pd.DataFrame()
        truth = pd.read_parquet(folder / "truth.parquet")
        if ep.empty:
            continue
        epochs_by_variant[variant] = ep
        t = lane_level_table(ep, truth, across_alert_limit_m=args.al)
        t.insert(0, "variant", variant)
        tables.append(t)
        p = lane_level_table(ep, truth, across_alert_limit_m=args.al, pool_vehicles=True)
        p.insert(0, "variant", variant)
        pooled.append(p)
    table = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    sol_table = pd.concat(pooled, ignore_index=True) if pooled else pd.DataFrame()
    table.to_csv(out / "lane_level.csv", index=False)
    sol_table.to_csv(out / "lane_level_solutions.csv", index=False)
    if epochs_by_variant:
        _plot_cdf(epochs_by_variant, out / "lane_level_across_cdf.png", args.al)
    short = ["variant", "solution", "initialized", "lane_model_ok", "correct_lane", "correct_lane_geom",
             "across_abs_p50_m", "across_abs_p95_m", "across_abs_p99_m", "across_mi_rate_3sigma",
             "across_mi_rate_pl", "across_pl_mean_m", "across_availability", "across_hmi_rate"]
    sky = str(args.rinex) if args.rinex else "nominal 27-slot constellation"
    md = [
        "# Lane-level relative positioning",
        "",
        f"net {args.net}, {args.vehicles} vehicles in lanes {args.lanes}, {args.duration_s:g} s, seed {args.seed}, "
        f"ephemeris: {sky}. Variants: canyon = with the net's buildings, open = buildings removed.",
        f"Across alert limit {args.al:g} m, integrity risk 1e-3 (k_PL = 3.29). Rates are fractions of",
        "initialized epochs, availability / HMI fractions of all epochs (v2v.metrics.lane).",
        "",
        "## Per solution (vehicles pooled)",
        "",
        to_markdown(sol_table[[c for c in short if c in sol_table]]) if len(sol_table) else "(no estimates)",
        "",
        "## Per vehicle",
        "",
        to_markdown(table) if len(table) else "(no estimates)",
        "",
        "Figure: `lane_level_across_cdf.png`.",
        "",
    ]
    (out / "lane_level.md").write_text("\n".join(md), encoding="utf-8")
    print((out / "lane_level.md").read_text(encoding="utf-8"))
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "lane_level.py"))
