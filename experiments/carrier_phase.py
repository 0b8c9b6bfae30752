"""Carrier-phase relative positioning: fixing, slips, and UWB aiding in a degraded sky.

Three parts, each run with every seed given (one run folder per part and seed under
``--out/runs``):

1. **Initialization drive** (``scenarios/phase_init_drive.toml``): 1.2 km of open sky, then
   the downtown canyon of ``urban_canyon``, as in MacGougan (2009) chapters 4-5 (an
   initialization walk in the open, then the survey among buildings). Code-only GPS against
   GPS-phase, GPS-phase+UWB and GPS-phase+UWB+Bearing, scored per segment (open / canyon, by
   the edge each car is on): fix rate, partial-fix rate, wrong-fix rate (the simulator knows
   the integers), time to first fix, along/across errors.
2. **Degraded sky** (MacGougan (2009) chapter 4: "a degraded GPS signal environment created
   artificially by excluding GPS satellites ... using elevation masking": a 40 deg mask left
   4 satellites): ``open_highway``, three cars in lanes 0, 2, 1 departing 0.5 s apart (so
   that each sees the others' radios from different directions, as the thesis's rover saw its
   UWB stations; in line, UWB constrains only the along-track direction), with only the
   ``--keep`` highest satellites (a
   ``satellites_lost`` fault; the equivalent mask angle is reported), either from the start
   (time to first fix, fix rate) or after 60 s of full-sky initialization, followed by a slip
   of every satellite of both followers (their ambiguities must be found again). GPS-phase against GPS-phase+UWB: fix rate and
   errors in the degraded window, time to re-fix after the slip.
3. **Slips in the open** (part 2's first 60 s): one satellite of one follower and every
   satellite of the other slip (``cycle_slip`` faults); detection counts, re-fix times,
   wrong fixes.

Outputs in ``--out``: ``carrier_phase.md`` (all tables), one CSV per table,
``carrier_phase_timeline.png`` (fix state and errors of part 1, first seed).

Run::

    .venv/bin/python experiments/carrier_phase.py --out /tmp/phase --seeds 1 2 3
    .venv/bin/python experiments/carrier_phase.py --out /tmp/phase41 --parts init_drive --solution-set gnss_cn0_mask_dbhz=41
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).resolve().parent
SCENARIO = HERE.parent / "scenarios" / "phase_init_drive.toml"
OPEN_EDGE_PREFIX = "w_far"  # the open-sky approach of urban_canyon's init_drive route


def _phase_solutions(uwb_sigma_m: float, bearing: bool = True, extra: tuple[str, ...] = ()) -> str:
    """The solutions as a ``solutions=[...]`` override; ``extra``: ``key=value`` fields added
    to every one (``--solution-set``)."""
    common = 'carrier_phase=true, pseudorange_sigma_m=1.0'
    items = [
        '{name="GPS", sensors=["gnss"]}',
        '{name="GPS-phase", sensors=["gnss"], ' + common + '}',
        '{name="GPS-phase+UWB", sensors=["gnss", "uwb"], uwb_error_states=true, '
        f'uwb_sigma_m={uwb_sigma_m}, ' + common + '}',
    ]
    if bearing:
        items.append('{name="GPS-phase+UWB+Bearing", sensors=["gnss", "uwb", "bearing"], uwb_error_states=true, '
                     f'uwb_sigma_m={uwb_sigma_m}, ' + common + '}')
    if extra:
        items = [it[:-1] + ", " + ", ".join(extra) + "}" for it in items]
    return "solutions=[" + ", ".join(items) + "]"


def check_solution_set(items: tuple[str, ...]) -> None:
    """Each ``--solution-set`` item is one ``field=value`` (TOML value) of a solution, other than
    its ``name`` and ``sensors`` (which define the script's solutions) and the fields the script
    sets itself, checked before any run."""
    import tomllib

    from v2v.config.sections import SolutionSection
    from v2v.errors import UserError

    own = {"carrier_phase", "pseudorange_sigma_m", "uwb_error_states", "uwb_sigma_m"}  # what _phase_solutions sets
    fields = sorted(set(SolutionSection.model_fields) - {"name", "sensors"} - own)
    for item in items:
        key = item.split("=", 1)[0].strip()
        try:
            ok = "=" in item and len(tomllib.loads(item)) == 1
        except tomllib.TOMLDecodeError:
            ok = False
        if not ok:
            raise UserError(f"{item!r} is not one KEY=VALUE (a TOML value, strings in quotes)", field="--solution-set",
                            fix="write e.g. gnss_cn0_mask_dbhz=41 or ar_ratio=3.0")
        if key in own:
            raise UserError(f"{key!r} is set by the script for its solutions", field="--solution-set",
                            fix="leave it out" + (" and use --uwb-sigma-m" if key == "uwb_sigma_m" else ""))
        if key not in fields:
            raise UserError(f"{key!r} is not a solution field this script lets you set", field="--solution-set",
                            fix=f"use one of {', '.join(fields)}")


# the scenario fields the options set, in every part (an error naming one names the option:
# v2v.errors.script_options); --solution-set's items go into every solution of parts 1-2
OPTIONS = {"seed": "--seeds", "clusters.0.lanes": "--lanes", "clusters.0.time_gap_s": "--time-gap-s",
           "sensors.uwb.profile": "--uwb-profile", "solutions.*.uwb_sigma_m": "--uwb-sigma-m",
           "solutions.*": "--solution-set"}


def _run(overrides: list[str], folder: Path, scenario: Path | None = None, save: bool = False) -> Path:
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options
    from v2v.run import run_scenario

    with script_options(OPTIONS):
        run_scenario(load_scenario(scenario, overrides), folder, quiet=True, replay=False, save_measurements=save)
    return folder


def _segment(folder: Path) -> pd.DataFrame:
    """epochs.parquet of a run with a ``segment`` column (open / canyon: the car's own edge)."""
    e = pd.read_parquet(folder / "epochs.parquet")
    tr = pd.read_parquet(folder / "truth.parquet", columns=["t_s", "vehicle", "edge"])
    tr["t_key"] = np.round(tr["t_s"], 3)
    e["t_key"] = np.round(e["t_s"], 3)
    e = e.merge(tr[["t_key", "vehicle", "edge"]], on=["t_key", "vehicle"], how="left")
    e["segment"] = np.where(e["edge"].astype(str).str.startswith(OPEN_EDGE_PREFIX), "open", "canyon")
    return e


def _scores(g: pd.DataFrame) -> dict[str, float]:
    ok = g[g["initialized"].astype(bool)]
    out = {
        "epochs": len(g),
        "along_rms_m": float(np.sqrt(np.mean(ok["along_err_m"] ** 2))) if len(ok) else np.nan,
        "across_rms_m": float(np.sqrt(np.mean(ok["across_err_m"] ** 2))) if len(ok) else np.nan,
        "horiz_p95_m": float(np.percentile(np.hypot(ok["along_err_m"], ok["across_err_m"]), 95)) if len(ok) else np.nan,
    }
    if "phase_state" in g and g["phase_state"].notna().any():
        ph = ok[ok["phase_state"].notna() & (ok["phase_state"] != "")]
        fixed = ph["phase_state"] == "fixed"
        wf = ph["wrong_fix"].dropna()
        out.update({
            "fix_rate": float(fixed.mean()) if len(ph) else np.nan,
            "partial_rate": float((ph["phase_state"] == "partial").mean()) if len(ph) else np.nan,
            "wrong_fix_rate": float((wf > 0.5).mean()) if len(wf) else np.nan,
            "epochs_with_fix": int(len(wf)),
            "fixed_horiz_rms_m": float(np.sqrt(np.mean(ph.loc[fixed, "along_err_m"] ** 2
                                                       + ph.loc[fixed, "across_err_m"] ** 2))) if fixed.any() else np.nan,
        })
    return out


def _ttff(g: pd.DataFrame, t0: float) -> float:
    fixed = g[(g["phase_state"] == "fixed")]
    return float(fixed["t_s"].min() - t0) if len(fixed) else np.nan


def _mean_table(rows: list[dict], keys: list[str]) -> pd.DataFrame:
    """Mean over seeds of every numeric column per ``keys`` group."""
    df = pd.DataFrame(rows)
    num = [c for c in df.columns if c not in keys + ["seed"] and pd.api.types.is_numeric_dtype(df[c])]
    return df.groupby(keys, sort=False)[num].mean().reset_index()


# ------------------------------------------------------------------------------------ part 1
def part_init_drive(args: argparse.Namespace, out: Path) -> tuple[pd.DataFrame, pd.DataFrame, Path]:
    rows, ttff_rows = [], []
    first = None
    for seed in args.seeds:
        ov = [f"seed={seed}", f"sensors.uwb.profile=\"{args.uwb_profile}\"",
              _phase_solutions(args.uwb_sigma_m, extra=args.solution_set)]
        if args.quick:
            ov.append("duration_s=90")
        folder = _run(ov, out / "runs" / f"init_drive_seed{seed}", SCENARIO)
        first = first or folder
        e = _segment(folder)
        for (sol, seg), g in e.groupby(["solution", "segment"], sort=False):
            rows.append({"solution": sol, "segment": seg, "seed": seed, **_scores(g)})
        for (sol, veh), g in e[e["phase_state"].notna()].groupby(["solution", "vehicle"], sort=False):
            if (g["phase_state"] == "").all():
                continue
            ttff_rows.append({"solution": sol, "vehicle": veh, "seed": seed,
                              "ttff_s": _ttff(g, float(g.loc[g["initialized"].astype(bool), "t_s"].min()))})
    assert first is not None
    return _mean_table(rows, ["solution", "segment"]), pd.DataFrame(ttff_rows), first


# ------------------------------------------------------------------------------------ part 2
def _low_prns(folder: Path, t0: float, keep: int) -> tuple[list[int], float]:
    """PRNs to remove so that only the ``keep`` highest satellites (at t0, lead vehicle) stay,
    and the equivalent elevation mask (deg, halfway between the last kept and the first removed)."""
    m = pd.read_parquet(folder / "measurements.parquet", columns=["t_s", "type", "vehicle", "prn", "elevation_rad"])
    m = m[(m["type"] == "pseudorange") & np.isclose(m["t_s"], t0)]
    el = m.groupby("prn")["elevation_rad"].max().sort_values(ascending=False)
    low = sorted(int(p) for p in el.index[keep:])
    mask = float(np.degrees(0.5 * (el.iloc[keep - 1] + el.iloc[keep]))) if len(el) > keep else 0.0
    return low, mask


def _degraded_duration_s(args: argparse.Namespace) -> float:
    return 100.0 if args.quick else 180.0


def _degraded_base(args: argparse.Namespace) -> list[str]:
    """The degraded-sky runs' overrides (without seed, solutions and faults)."""
    return ['network.name="open_highway"', f"duration_s={_degraded_duration_s(args)}", "clusters.0.vehicles=3",
            f"clusters.0.lanes={args.lanes}", f"clusters.0.time_gap_s={args.time_gap_s}",
            f"sensors.uwb.profile=\"{args.uwb_profile}\"", "background.vehicles_per_hour=0.0"]


def check_degraded_options(args: argparse.Namespace) -> None:
    """The UserError a degraded-sky run would raise for the options only it uses (--lanes,
    --time-gap-s) or for its solutions: found before any part runs, not after the first part's
    runs and files."""
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options
    from v2v.run import check_scenario

    sols = _phase_solutions(args.uwb_sigma_m, bearing=False, extra=args.solution_set)
    with script_options(OPTIONS):
        for seed in args.seeds:
            sc = load_scenario(None, [*_degraded_base(args), f"seed={seed}", sols])
        check_scenario(sc)  # (the net and the lanes on its route: the same for every seed)


def part_degraded(args: argparse.Namespace, out: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Two variants per seed, both with only the ``keep`` highest satellites:

    * ``masked from the start`` (thesis section 4.1.2: the whole test under a 40 deg mask):
      time to first fix and fix rate; the UWB error states start uncalibrated;
    * ``masked after init``: 60 s of full sky (initialization: fix, UWB calibration), then
      the mask; later every satellite of both followers slips (the ambiguities must be found
      again with the satellites left).
    """
    dur = _degraded_duration_s(args)
    t_mask, t_slip = 60.0, 60.0 + (20.0 if args.quick else 40.0)
    base = _degraded_base(args)
    rows, ttff = [], []
    for seed in args.seeds:
        probe = _run(base + [f"seed={seed}", "solutions=[]"], out / "runs" / f"degraded_probe_seed{seed}", save=True)
        variants = [("masked from the start", 0.0, None)] + ([] if args.quick else [("masked after init", t_mask, t_slip)])
        for variant, t0, t_sl in variants:
            low, mask_deg = _low_prns(probe, t0, args.keep)
            if not low:  # (the sky is known from the probe run only)
                from v2v.errors import UserError

                raise UserError(f"keeps every satellite the lead sees at t = {t0:g} s (seed {seed}): none to remove",
                                field="--keep", fix="give --keep below the satellites in view (e.g. 4)")
            faults = [f"{{kind=\"satellites_lost\", start_s={t0}, duration_s={dur - t0 + 1.0}, prns={low}}}"]
            if t_sl is not None:
                faults.append(f"{{kind=\"cycle_slip\", start_s={t_sl}, vehicles=[\"c1.1\", \"c1.2\"], size_cycles=3}}")
            tag = "start" if t0 == 0.0 else "init"
            folder = _run(base + [f"seed={seed}", _phase_solutions(args.uwb_sigma_m, bearing=False, extra=args.solution_set),
                                  "faults=[" + ", ".join(faults) + "]"], out / "runs" / f"degraded_{tag}_seed{seed}")
            e = pd.read_parquet(folder / "epochs.parquet")
            n_sat = int(e.loc[(e["t_s"] > t0 + 1.0) & (e["solution"] == "GPS"), "used_pr"].median())  # SD pseudoranges = satellites
            windows = ([("whole run", 0.0, dur + 1)] if t_sl is None else
                       [("full sky", 10.0, t0), ("masked", t0, t_sl), ("masked, after slip", t_sl, dur + 1)])
            for sol, g in e.groupby("solution", sort=False):
                for win, lo, hi in windows:
                    gw = g[(g["t_s"] >= lo) & (g["t_s"] < hi)]
                    rows.append({"variant": variant, "solution": sol, "window": win, "seed": seed,
                                 "satellites_left": n_sat, "mask_deg": mask_deg, **_scores(gw)})
                if (g["phase_state"].fillna("") != "").any():
                    t_ref = 0.0 if t_sl is None else t_sl
                    for veh, gv in g.groupby("vehicle"):
                        ttff.append({"variant": variant, "solution": sol, "vehicle": veh, "seed": seed,
                                     "first_fix_after_s": _ttff(gv[gv["t_s"] >= t_ref], t_ref),
                                     "from": "start" if t_sl is None else "slip"})
    return _mean_table(rows, ["variant", "solution", "window"]), pd.DataFrame(ttff)


# ------------------------------------------------------------------------------------ part 3
def part_slips(args: argparse.Namespace, out: Path) -> pd.DataFrame:
    rows = []
    t1, t2 = 30.0, 45.0
    for seed in args.seeds:
        ov = ['network.name="open_highway"', "duration_s=60", "clusters.0.vehicles=3", "clusters.0.lanes=[0]",
              f"seed={seed}", "background.vehicles_per_hour=0.0",
              'solutions=[{name="GPS-phase", sensors=["gnss"], carrier_phase=true, pseudorange_sigma_m=1.0}]',
              # one satellite of c1.1 (the first PRN it tracks at t1 is taken below), then all of c1.2
              f'faults=[{{kind="cycle_slip", start_s={t1}, vehicles=["c1.1"], prns=[PRN], size_cycles=1}}, '
              f'{{kind="cycle_slip", start_s={t2}, vehicles=["c1.2"], size_cycles=-2}}]']
        probe = _run(ov[:-2] + ["solutions=[]"], out / "runs" / f"slips_probe_seed{seed}", save=True)
        m = pd.read_parquet(probe / "measurements.parquet", columns=["t_s", "type", "vehicle", "prn", "elevation_rad"])
        m = m[(m["type"] == "pseudorange") & (m["vehicle"] == "c1.1") & np.isclose(m["t_s"], t1)]
        prn = int(m.sort_values("elevation_rad")["prn"].iloc[-1])  # the highest: the DD reference
        ov[-1] = ov[-1].replace("PRN", str(prn))
        folder = _run(ov, out / "runs" / f"slips_seed{seed}")
        s = json.loads((folder / "summary.json").read_text())
        e = pd.read_parquet(folder / "epochs.parquet")
        counters = s["filter_counters"]["GPS-phase"]
        for veh, t_slip, what in (("c1.1", t1, f"1 cycle on PRN {prn} (the highest)"), ("c1.2", t2, "-2 cycles on all")):
            g = e[e["vehicle"] == veh]
            after = g[g["t_s"] >= t_slip]
            wf = g["wrong_fix"].dropna()
            rows.append({"seed": seed, "vehicle": veh, "slip": what, "slip_detections_run_total": counters.get("phase_slip", 0),
                         "refix_s": _ttff(after, t_slip), "wrong_fix_epochs": int((wf > 0.5).sum()),
                         "max_horiz_err_after_m": float(np.max(np.hypot(after["along_err_m"], after["across_err_m"])))})
    return pd.DataFrame(rows)


# ------------------------------------------------------------------------------------ output
def _timeline(folder: Path, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    e = _segment(folder)
    sols = [s for s in e["solution"].unique()]
    fig, axes = plt.subplots(2, 1, figsize=(10, 6.5), sharex=True)
    v = sorted(e["vehicle"].unique())[-1]
    codes = {"float": 0, "partial": 1, "fixed": 2}
    for k, sol in enumerate(sols):
        g = e[(e["solution"] == sol) & (e["vehicle"] == v)]
        color = f"C{k}"  # the same colour for a solution in both panels
        axes[0].semilogy(g["t_s"], np.hypot(g["along_err_m"], g["across_err_m"]).clip(lower=1e-3), lw=0.8,
                         label=sol, color=color)
        if g["phase_state"].notna().any():
            st = g["phase_state"].map(codes)
            axes[1].plot(g["t_s"], st + 0.08 * k, ".", ms=1.5, label=sol, color=color)
    t_open = e.loc[(e["segment"] == "canyon") & (e["vehicle"] == v), "t_s"].min()
    for ax in axes:
        ax.axvline(t_open, color="k", lw=0.8, ls="--")
    axes[0].set_ylabel(f"horizontal error of {v} (m)")
    axes[0].legend(fontsize=8)
    axes[0].set_title("open sky | urban canyon (dashed: the car enters the canyon)")
    axes[1].set_yticks([0, 1, 2], ["float", "partial", "fixed"])
    axes[1].set_xlabel("t (s)")
    axes[1].legend(fontsize=8, markerscale=6)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _md(df: pd.DataFrame) -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, r in df.iterrows():
        cells = [f"{v:.3f}" if isinstance(v, float) else str(v) for v in r.tolist()]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from v2v.errors import ScriptArgumentParser

    ap = ScriptArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--seeds", type=int, nargs="+", default=[1, 2, 3])
    ap.add_argument("--uwb-profile", default="tdc", choices=["tdc", "mssi", "ideal"])
    ap.add_argument("--uwb-sigma-m", type=float, default=0.03,
                    help="filter's UWB sigma with bias/scale states (TDC radio: 1-3 cm, MacGougan 2009 sec. 2.11)")
    ap.add_argument("--keep", type=int, default=4,
                    help="degraded sky: satellites kept (the highest; thesis ch. 4: a 40 deg mask left 4)")
    ap.add_argument("--lanes", default="[0, 2, 1]",
                    help="degraded sky: the cluster's lanes (TOML list; [0] = in line: UWB sees along-track only)")
    ap.add_argument("--time-gap-s", type=float, default=0.5, help="degraded sky: departure gap between the cars")
    ap.add_argument("--parts", nargs="+", default=["init_drive", "degraded", "slips"],
                    choices=["init_drive", "degraded", "slips"])
    ap.add_argument("--quick", action="store_true", help="one seed, shorter runs (smoke test)")
    ap.add_argument("--solution-set", nargs="+", default=[], metavar="KEY=VALUE",
                    help="solution fields added to every solution of parts 1-2, e.g. gnss_cn0_mask_dbhz=41 "
                         "or gnss_min_satellites=4 (TOML values)")
    args = ap.parse_args(argv)
    args.solution_set = tuple(args.solution_set)
    check_solution_set(args.solution_set)
    from v2v.errors import check_positive

    check_positive(args.keep, "--keep")
    if args.quick:
        args.seeds = args.seeds[:1]
    if "degraded" in args.parts:
        check_degraded_options(args)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)
    md = [f"# Carrier phase (seeds {args.seeds}, UWB profile {args.uwb_profile}"
          + (f"; every solution with {', '.join(args.solution_set)}" if args.solution_set else "") + ")", ""]
    if "init_drive" in args.parts:
        t1, ttff, first = part_init_drive(args, out)
        t1.to_csv(out / "init_drive.csv", index=False)
        ttff.to_csv(out / "init_drive_ttff.csv", index=False)
        _timeline(first, out / "carrier_phase_timeline.png")
        md += ["## 1. Initialization drive: open sky, then the urban canyon", "", _md(t1), "",
               "Time to first fix (s, from the vehicle's first estimate):", "",
               _md(ttff.groupby("solution", sort=False)["ttff_s"].describe()[["count", "mean", "min", "max"]]
                   .reset_index()), ""]
    if "degraded" in args.parts:
        t2, refix = part_degraded(args, out)
        t2.to_csv(out / "degraded.csv", index=False)
        refix.to_csv(out / "degraded_refix.csv", index=False)
        md += [f"## 2. Degraded sky: only the {args.keep} highest satellites", "",
               _md(t2), "", "First fix (s after the start, or after the all-satellite slip; NaN: never):", "",
               _md(refix.groupby(["variant", "solution"], sort=False)["first_fix_after_s"]
                   .agg(["count", "mean", "min", "max", lambda s: int(s.isna().sum())])
                   .rename(columns={"<lambda_0>": "never"}).reset_index()), ""]
    if "slips" in args.parts:
        t3 = part_slips(args, out)
        t3.to_csv(out / "slips.csv", index=False)
        md += ["## 3. Cycle slips in the open (GPS-phase)", "", _md(t3), ""]
    (out / "carrier_phase.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "carrier_phase.py"))
