"""The paper's sensor combinations (Petovello et al. section 5, Tables 3-8, Fig. 14).

Three vehicles in line on one lane (the paper's configuration, "two-second rule" gaps:
28 m at 50 km/h, paper section 4.3) drive the ``hospital_loop`` net (section 5.1: the 180 deg loop in front of the Children's
hospital) and the ``residential`` net (section 5.2: foliage), once per seed. Every run
filters the same measurements with the six paper solutions (``paper_solutions()``):
GPS, GPS+UWB, GPS+Bearing, GPS+UWB+Bearing with the measuring vehicles' azimuths known,
and GPS+Bearing / GPS+UWB+Bearing with the azimuth estimated (section 5.3).

The paper's bearing configuration is reproduced (``PAPER_BEARING_OVERRIDES``):

* only the **lead vehicle** measures bearings, to vehicles 1 and 2 (section 5.3: "the lead
  vehicle (i.e., the vehicle making the bearing observations)"; "two bearing measurements
  were available at all times"), so the az-est solutions estimate one azimuth, the lead's;
* the bearings were computed from the reference trajectories (section 4.3), accurate to
  "about 0.3 degrees" (conservatively, for 14 cm horizontal over 28 m): the simulated
  bearing noise is 0.3 deg, while the filter assumes 0.5 deg as in the paper (section 4.4);
* the known azimuth came from the inertially aided reference (SPAN; section 4.4): the
  default 0.1 deg white azimuth noise is kept.

Per (net, seed, solution, vehicle) the along- and across-track error mean and std are
computed over the initialized epochs of ``epochs.parquet`` after a settling time
(``--settle-s``, default 10 s from the first output epoch): every run starts cold, from a
single-epoch least-squares fix with metre-level errors, and the paper's segments were cut
from a drive whose filters had long converged; with the transient included, the across-
track std of a 30 s run measures the convergence, not the sensors; the tables give their mean
over the seeds with a 95 % confidence interval from the t-distribution
(``t_0.975(n - 1) s / sqrt(n)``, n = number of seeds; none with one seed). "Vehicle 1"
is the first follower (``c1.1``), "vehicle 2" the second, as in the paper.

Outputs in ``--out``:

* ``paper_tables.md`` / ``paper_tables.csv``: Tables 3-6 shaped (per net and vehicle:
  solution x {along mean, along std, across mean, across std}), with the paper's numbers
  beside them for reference (they come from one real 2010 drive, so they are a scale,
  not a target);
* ``azimuth_known_vs_unknown.md`` / ``.csv``: Tables 7-8 shaped (bearing solutions with
  the azimuth known and estimated, per vehicle) plus the lead-azimuth error statistics
  of the az-est solutions (mean, std, max, fraction of epochs under 0.2 deg);
* ``azimuth_error_<net>.png``: Fig. 14: lead-vehicle azimuth error of the az-est
  solutions and the lead's azimuth rate vs time (first seed);
* ``runs/<net>_seed<k>/``: the simulator's run folders.

``--nets open_highway`` adds an open-sky run (no paper table of its own; the paper's
Tables 7-8 and Fig. 14 cover the first half of its drive, much of it open sky).

Run::

    .venv/bin/python experiments/paper_sensor_combinations.py --out /tmp/paper --seeds 1 2 3
    .venv/bin/python experiments/paper_sensor_combinations.py --out /tmp/paper_open --nets open_highway
    .venv/bin/python experiments/paper_sensor_combinations.py --out /tmp/paper_quick --quick
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd
from scipy import stats

NETS = ("hospital_loop", "residential")
# Optional (--nets): open sky, like much of the first half of the paper's drive (section 4.1:
# Shaganappi Trail), over which its Tables 7-8 and Fig. 14 were computed.
EXTRA_NETS = ("open_highway",)
LEAD_ID = "c1.0"  # the cluster's lead (index 0 in departure order)
# Paper sections 4.3-4.4 and 5.3 (see the module docstring).
PAPER_BEARING_OVERRIDES = (f'sensors.bearing.measuring=["{LEAD_ID}"]', "sensors.bearing.sigma_deg=0.3")
STATS = ("along_mean", "along_std", "across_mean", "across_std")
KNOWN_VS_EST = ("GPS+Bearing", "GPS+Bearing az-est", "GPS+UWB+Bearing", "GPS+UWB+Bearing az-est")

# Petovello et al. Tables 3-6 (section 5.1 hospital, 5.2 residential) and 7-8 (section 5.3),
# metres: (along mean, along std, across mean, across std) per paper vehicle.
PAPER = {
    "hospital_loop": {
        1: {"GPS": (-0.03, 0.12, 0.07, 0.19), "GPS+UWB": (0.07, 0.22, -0.08, 0.23),
            "GPS+Bearing": (-0.03, 0.09, 0.06, 0.15), "GPS+UWB+Bearing": (0.06, 0.14, -0.09, 0.21)},
        2: {"GPS": (0.00, 0.12, -0.05, 0.17), "GPS+UWB": (-0.01, 0.23, 0.13, 0.29),
            "GPS+Bearing": (0.01, 0.07, -0.04, 0.10), "GPS+UWB+Bearing": (-0.05, 0.17, 0.10, 0.23)},
    },
    "residential": {
        1: {"GPS": (0.14, 0.43, 0.09, 0.29), "GPS+UWB": (0.01, 0.23, -0.01, 0.24),
            "GPS+Bearing": (0.10, 0.22, -0.01, 0.05), "GPS+UWB+Bearing": (0.01, 0.16, 0.00, 0.06)},
        2: {"GPS": (0.02, 0.32, 0.34, 0.45), "GPS+UWB": (0.00, 0.19, 0.25, 0.22),
            "GPS+Bearing": (-0.07, 0.10, 0.01, 0.05), "GPS+UWB+Bearing": (-0.04, 0.11, 0.01, 0.04)},
    },
}
PAPER_AZ = {  # Tables 7 (vehicle 1) and 8 (vehicle 2), first half of the test
    1: {"GPS+Bearing": (-0.02, 0.13, 0.00, 0.14), "GPS+Bearing az-est": (-0.04, 0.15, 0.00, 0.15),
        "GPS+UWB+Bearing": (0.00, 0.16, 0.00, 0.19), "GPS+UWB+Bearing az-est": (0.00, 0.18, 0.00, 0.19)},
    2: {"GPS+Bearing": (0.16, 0.60, 0.04, 0.48), "GPS+Bearing az-est": (0.06, 0.53, 0.05, 0.42),
        "GPS+UWB+Bearing": (0.06, 0.29, 0.02, 0.21), "GPS+UWB+Bearing az-est": (0.02, 0.24, 0.00, 0.17)},
}


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from v2v.errors import ScriptArgumentParser

    ap = ScriptArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    # (defaults None: what is not given comes from the full or the --quick set; what is given wins)
    ap.add_argument("--seeds", type=int, nargs="+", help="(default 1 2 3; --quick 1)")
    ap.add_argument("--nets", nargs="+", choices=NETS + EXTRA_NETS, help=f"(default {' '.join(NETS)}; --quick hospital_loop)")
    ap.add_argument("--duration-s", type=float, help="(default 60; --quick 25)")
    ap.add_argument("--settle-s", type=float, default=10.0, help="seconds after the first epoch left out of the statistics")
    ap.add_argument("--quick", action="store_true",
                    help="1 seed, 25 s, hospital_loop only (smoke test; the options above that are given still apply)")
    args = ap.parse_args(argv)
    chosen = {"seeds": [1], "duration_s": 25.0, "nets": ["hospital_loop"]} if args.quick else \
        {"seeds": [1, 2, 3], "duration_s": 60.0, "nets": list(NETS)}
    for key, value in chosen.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    from v2v.errors import UserError, check_positive

    check_positive(args.duration_s, "--duration-s")
    if not 0.0 <= args.settle_s < args.duration_s:
        raise UserError(f"{args.settle_s:g} s is not in [0, duration) = [0, {args.duration_s:g})", field="--settle-s",
                        fix=f"give 0 <= --settle-s < --duration-s ({args.duration_s:g} s)")
    for net in args.nets:  # every run's scenario, before the first run: a bad later --seeds was found after runs
        for seed in args.seeds:
            scenario_of(net, seed, args.duration_s)
    return args


# ------------------------------------------------------------------------------ runs

# the scenario fields the options set (an error naming one names the option: v2v.errors.script_options)
OPTIONS = {"network.name": "--nets", "seed": "--seeds", "duration_s": "--duration-s"}


def scenario_of(net: str, seed: int, duration_s: float):
    """The scenario of one run: the paper's three-vehicle, one-lane cluster with the paper's solutions."""
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options

    with script_options(OPTIONS):
        return load_scenario(None, [f'network.name="{net}"', f"seed={seed}", f"duration_s={duration_s}",
                                    "clusters.0.vehicles=3", "clusters.0.lanes=[0]", *PAPER_BEARING_OVERRIDES])


def run_one(net: str, seed: int, duration_s: float, out: Path) -> Path:
    """One simulator run of the paper's three-vehicle, one-lane cluster with the paper's solutions."""
    from v2v.errors import script_options
    from v2v.run import run_scenario

    folder = out / "runs" / f"{net}_seed{seed}"
    with script_options(OPTIONS):
        run_scenario(scenario_of(net, seed, duration_s), folder, quiet=True, replay=False)
    return folder


def run_statistics(folder: Path, settle_s: float) -> pd.DataFrame:
    """Along/across mean and std per (solution, vehicle) over the initialized epochs of one run
    from ``settle_s`` after its first epoch."""
    ep = pd.read_parquet(folder / "epochs.parquet")
    ep = ep[ep["t_s"] >= ep["t_s"].min() + settle_s]
    summary = json.loads((folder / "summary.json").read_text())
    lead = summary["leads"][0]
    followers = sorted(v for v in summary["vehicles"] if v != lead and v.split(".")[0] == lead.split(".")[0])
    ep = ep[ep["initialized"]]
    rows = []
    for (sol, veh), g in ep.groupby(["solution", "vehicle"], sort=False):
        rows.append({
            "solution": sol, "vehicle": followers.index(veh) + 1, "vehicle_id": veh, "epochs": len(g),
            "along_mean": g["along_err_m"].mean(), "along_std": g["along_err_m"].std(ddof=1),
            "across_mean": g["across_err_m"].mean(), "across_std": g["across_err_m"].std(ddof=1),
        })
    return pd.DataFrame(rows)


def azimuth_statistics(folder: Path, settle_s: float) -> pd.DataFrame:
    """Lead-azimuth error statistics (deg) of every az-est solution of one run (after ``settle_s``)."""
    ep = pd.read_parquet(folder / "epochs.parquet")
    ep = ep[ep["t_s"] >= ep["t_s"].min() + settle_s]
    rows = []
    if "lead_azimuth_err_rad" not in ep:
        return pd.DataFrame(rows)
    for sol, g in ep.groupby("solution", sort=False):
        # one value per epoch (the lead's azimuth is repeated on every vehicle's row)
        a = np.degrees(g.drop_duplicates("t_s")["lead_azimuth_err_rad"].dropna().to_numpy())
        if a.size == 0:
            continue
        rows.append({"solution": sol, "az_mean_deg": a.mean(), "az_std_deg": a.std(ddof=1),
                     "az_max_abs_deg": np.abs(a).max(), "az_frac_below_0p2deg": float(np.mean(np.abs(a) < 0.2))})
    return pd.DataFrame(rows)


def across_seeds(per_seed: pd.DataFrame, keys: list[str], cols: list[str]) -> pd.DataFrame:
    """Mean over seeds and the 95 % t-interval half-width (NaN with one seed)."""
    rows = []
    for k, g in per_seed.groupby(keys, sort=False):
        k = k if isinstance(k, tuple) else (k,)
        row = dict(zip(keys, k, strict=True))
        n = len(g)
        row["n_seeds"] = n
        for c in cols:
            v = g[c].to_numpy(dtype=float)
            row[c] = float(v.mean())
            row[f"{c}_ci95"] = float(stats.t.ppf(0.975, n - 1) * v.std(ddof=1) / np.sqrt(n)) if n > 1 else float("nan")
        rows.append(row)
    return pd.DataFrame(rows)


# ------------------------------------------------------------------------------ tables


def _cell(mean: float, ci: float, signed: bool = True) -> str:
    m = f"{mean:+.3f}" if signed else f"{mean:.3f}"
    return m if not np.isfinite(ci) else f"{m} ± {ci:.3f}"


def _paper_cell(vals: tuple[float, float, float, float] | None, i: int) -> str:
    return "" if vals is None else (f"{vals[i]:+.2f}" if i % 2 == 0 else f"{vals[i]:.2f}")


def tables_markdown(agg: pd.DataFrame, nets: list[str], seeds: list[int], duration_s: float, settle_s: float) -> str:
    lines = ["# Paper sensor combinations: along/across-track errors (m)\n",
             f"Seeds {seeds}, {duration_s:.0f} s per run (statistics from t = {settle_s:.0f} s), 3 vehicles in line "
             "on one lane. Cells: mean over seeds "
             "± 95 % t-interval half-width of the per-run statistic. `paper` columns: Petovello et al. "
             "(hospital: Tables 3-4; residential: Tables 5-6), one real drive, for scale.\n"]
    for net in nets:
        for veh in (1, 2):
            g = agg[(agg["net"] == net) & (agg["vehicle"] == veh)]
            if g.empty:
                continue
            lines.append(f"\n## {net}, vehicle {veh}\n")
            lines.append("| solution | along mean | along std | across mean | across std | paper along mean | "
                         "paper along std | paper across mean | paper across std |")
            lines.append("|---|---|---|---|---|---|---|---|---|")
            for _, r in g.iterrows():
                p = PAPER.get(net, {}).get(veh, {}).get(r["solution"])
                cells = [_cell(r[c], r[f"{c}_ci95"], c.endswith("mean")) for c in STATS]
                lines.append(f"| {r['solution']} | " + " | ".join(cells) + " | "
                             + " | ".join(_paper_cell(p, i) for i in range(4)) + " |")
    return "\n".join(lines) + "\n"


def azimuth_markdown(agg: pd.DataFrame, az: pd.DataFrame, nets: list[str]) -> str:
    lines = ["# Azimuth known vs estimated (paper Tables 7-8, section 5.3)\n",
             "Cells as in `paper_tables.md`; `diff std` = std(az-est) - std(az known) of the same combination. "
             "`paper` columns: Tables 7 (vehicle 1) and 8 (vehicle 2), the first half of the paper's drive "
             "(all environments), shown beside both nets for scale.\n"]
    for net in nets:
        for veh in (1, 2):
            g = agg[(agg["net"] == net) & (agg["vehicle"] == veh) & agg["solution"].isin(KNOWN_VS_EST)]
            if g.empty:
                continue
            g = g.set_index("solution")
            lines.append(f"\n## {net}, vehicle {veh}\n")
            lines.append("| solution | along mean | along std | across mean | across std | diff along std | "
                         "diff across std | paper along std | paper across std |")
            lines.append("|---|---|---|---|---|---|---|---|---|")
            for sol in KNOWN_VS_EST:
                if sol not in g.index:
                    continue
                r = g.loc[sol]
                base = sol.replace(" az-est", "")
                diff = ["", ""]
                if sol != base and base in g.index:
                    diff = [f"{r['along_std'] - g.loc[base, 'along_std']:+.3f}",
                            f"{r['across_std'] - g.loc[base, 'across_std']:+.3f}"]
                p = PAPER_AZ.get(veh, {}).get(sol)
                lines.append(f"| {sol} | " + " | ".join(_cell(r[c], r[f'{c}_ci95'], c.endswith("mean")) for c in STATS) + " | "
                             + " | ".join(diff) + f" | {_paper_cell(p, 1)} | {_paper_cell(p, 3)} |")
    lines.append("\n## Lead-vehicle azimuth error (deg)\n")
    lines.append("Paper Fig. 14: typically < 0.2 deg, larger during rapid manoeuvres.\n")
    lines.append("| net | solution | mean | std | max abs | fraction < 0.2 deg |")
    lines.append("|---|---|---|---|---|---|")
    for _, r in az.iterrows():
        lines.append(f"| {r['net']} | {r['solution']} | {_cell(r['az_mean_deg'], r['az_mean_deg_ci95'])} | "
                     f"{_cell(r['az_std_deg'], r['az_std_deg_ci95'], False)} | "
                     f"{_cell(r['az_max_abs_deg'], r['az_max_abs_deg_ci95'], False)} | "
                     f"{_cell(r['az_frac_below_0p2deg'], r['az_frac_below_0p2deg_ci95'], False)} |")
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------ figure


def azimuth_figure(folder: Path, net: str, path: Path) -> None:
    """Fig. 14: lead azimuth error of the az-est solutions and the lead's azimuth rate vs time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ep = pd.read_parquet(folder / "epochs.parquet")
    truth = pd.read_parquet(folder / "truth.parquet")
    lead = truth[truth["is_lead"]].sort_values("t_s")
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    if "lead_azimuth_err_rad" in ep:
        for sol, g in ep.groupby("solution", sort=False):
            g = g.drop_duplicates("t_s").dropna(subset=["lead_azimuth_err_rad"])
            if len(g):
                ax1.plot(g["t_s"], np.degrees(g["lead_azimuth_err_rad"]), lw=1.0, label=sol)
    for y in (-0.2, 0.2):
        ax1.axhline(y, color="k", lw=0.6, ls="--")
    ax1.set_ylabel("lead azimuth error (deg)")
    ax1.legend(loc="upper right", fontsize=8)
    ax1.set_title(f"{net}: lead-vehicle azimuth error (dashed: paper's typical 0.2 deg) and azimuth rate")
    ax1.grid(alpha=0.3)
    ax2.plot(lead["t_s"], np.degrees(lead["yaw_rate_rps"]), color="tab:gray", lw=1.0)
    ax2.set_ylabel("lead azimuth rate (deg/s)")
    ax2.set_xlabel("time (s)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------ main


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)
    per_run, per_az = [], []
    for net in args.nets:
        for i, seed in enumerate(args.seeds):
            print(f"{net} seed {seed} ({args.duration_s:.0f} s) ...", file=sys.stderr, flush=True)
            folder = run_one(net, seed, args.duration_s, out)
            s = run_statistics(folder, args.settle_s)
            s.insert(0, "seed", seed)
            s.insert(0, "net", net)
            per_run.append(s)
            a = azimuth_statistics(folder, args.settle_s)
            if len(a):
                a.insert(0, "seed", seed)
                a.insert(0, "net", net)
                per_az.append(a)
            if i == 0:
                azimuth_figure(folder, net, out / f"azimuth_error_{net}.png")
    runs = pd.concat(per_run, ignore_index=True)
    runs.to_csv(out / "paper_runs.csv", index=False)
    agg = across_seeds(runs, ["net", "solution", "vehicle"], list(STATS))
    agg.to_csv(out / "paper_tables.csv", index=False)
    (out / "paper_tables.md").write_text(tables_markdown(agg, args.nets, args.seeds, args.duration_s, args.settle_s))
    az_runs = pd.concat(per_az, ignore_index=True) if per_az else pd.DataFrame()
    az_cols = ["az_mean_deg", "az_std_deg", "az_max_abs_deg", "az_frac_below_0p2deg"]
    az = across_seeds(az_runs, ["net", "solution"], az_cols) if len(az_runs) else pd.DataFrame(columns=["net", "solution"])
    known = agg[agg["solution"].isin(KNOWN_VS_EST)]
    known.to_csv(out / "azimuth_known_vs_unknown.csv", index=False)
    az.to_csv(out / "azimuth_error.csv", index=False)
    (out / "azimuth_known_vs_unknown.md").write_text(azimuth_markdown(agg, az, args.nets))
    print((out / "paper_tables.md").read_text())
    print((out / "azimuth_known_vs_unknown.md").read_text())
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "paper_sensor_combinations.py"))
