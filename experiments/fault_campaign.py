"""Fault campaign (issue 8): one short real scenario per fault kind, how the filters cope.

For each fault kind, one run of the default scenario (hospital_loop, 3 cars; 60 s, the
fault from 20 s; ``--quick``: 40 s, 3 faults from 15 s) through :func:`v2v.run.run_scenario`
with the solutions GPS and GPS+UWB+Bearing (replay off). From its ``epochs.parquet`` and
``summary.json``, per (fault, solution), for the fault's target vehicles:

* ``detected`` / ``latency_s``: how the filter noticed. Measurement faults (blunders, UWB
  radio replaced or drifting): the first rejected measurement of that type of a target in
  the window. Clock jump: the target's pseudoranges are used again (>= 4 in one epoch)
  after the jump (the filter's common-mode detector re-initialized its clock; without it
  every pseudorange is rejected). Missing data (outages, lost satellites, message loss, a
  vehicle leaving): the first epoch with no measurement of that type used. Non-finite
  values: skipped by the filter (never used): "skipped". Cycle slips: carrier phase is not
  used by this filter: "n/a".
* ``max_along_before_m`` / ``max_along_fault_m`` (and across): max |error| in the 10 s
  before the fault vs in the fault window (from start to 5 s after its end; to the end of
  the run for step faults).
* ``exceed_3sigma_fault``: fraction of the fault window's initialized epochs with |along| or
  |across| > 3 sigma; ``uninitialized_frac``: fraction of its epochs with the target not
  in the filter (a silent vehicle is removed, and re-initialized when it is heard again).
* ``recovery_s``: time from the end of the fault (its start for step faults) to the first
  epoch from which on, for 3 s, the errors stay within 3 sigma and the fault's measurement
  type is used again; NaN if never.
* ``true_rej`` / ``missed`` / ``false_rej``: the summary's rejection counts for the
  measurement kind (faulty = injected error or NLOS).

Writes ``fault_campaign.md``, ``fault_campaign.csv`` and ``fault_campaign.png`` (along
error of the first target vehicle around each fault) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

SOLUTIONS = ('solutions=[{name="GPS", sensors=["gnss"]}, '
             '{name="GPS+UWB+Bearing", sensors=["gnss", "uwb", "bearing"]}]')
LEAD = "c1.0"
NON_LEAD = ("c1.1", "c1.2")

# kind -> (fault table entry without start_s, measurement type column, summary measurement kind)
FAULTS: dict[str, tuple[str, str, str]] = {
    "gnss_outage": ('duration_s=10.0, vehicles="all"', "pr", "sd_pseudorange"),
    "satellites_lost": ('duration_s=10.0, vehicles=["c1.1"], prns=[' + ", ".join(str(p) for p in range(1, 33, 2)) + "]",
                        "pr", "sd_pseudorange"),
    "clock_jump": ('vehicles=["c1.1"]', "pr", "sd_pseudorange"),
    "cycle_slip": ('vehicles=["c1.1"], size_cycles=5', "pr", "sd_pseudorange"),
    "pr_blunder": ('duration_s=10.0, vehicles=["c1.1"], size_m=30.0, probability=0.1', "pr", "sd_pseudorange"),
    "nonfinite": ('duration_s=10.0, vehicles=["c1.1"], probability=0.2, sensor="gnss"', "pr", "sd_pseudorange"),
    "uwb_blunder": ('duration_s=10.0, vehicles=["c1.1"], size_m=5.0, probability=0.2', "uwb", "uwb"),
    "uwb_replace": ('vehicles=["c1.1"], size_m=1.0', "uwb", "uwb"),
    "uwb_scale_drift": ('vehicles=["c1.1"], scale_ppm=1000.0', "uwb", "uwb"),
    "bearing_outage": ('duration_s=10.0, vehicles="all"', "bearing", "bearing"),
    "message_loss": ('duration_s=5.0, vehicles=["c1.1"]', "pr", "sd_pseudorange"),
    "vehicle_leaves": ('duration_s=10.0, vehicles=["c1.2"]', "pr", "sd_pseudorange"),
}
QUICK = ("clock_jump", "pr_blunder", "gnss_outage")
QUICK_OVERRIDES = {"gnss_outage": 'duration_s=5.0, vehicles="all"'}
STEP_KINDS = ("clock_jump", "cycle_slip", "uwb_replace", "uwb_scale_drift")
MISSING_KINDS = ("gnss_outage", "satellites_lost", "bearing_outage", "message_loss", "vehicle_leaves")
MEASUREMENT_KINDS = ("pr_blunder", "uwb_blunder", "uwb_replace", "uwb_scale_drift")


def _targets(entry: str) -> tuple[str, ...]:
    for v in NON_LEAD:
        if f'"{v}"' in entry:
            return (v,)
    return NON_LEAD


def analyse(kind: str, entry: str, mtype: str, mkind: str, start_s: float, duration_s: float, t_end_s: float,
            epochs: pd.DataFrame, summary: dict[str, Any]) -> list[dict[str, Any]]:
    """One table row per solution for one fault run (see the module docstring)."""
    step = kind in STEP_KINDS
    fault_end = t_end_s if step else start_s + duration_s
    window_end = t_end_s if step else min(fault_end + 5.0, t_end_s)
    recover_from = start_s if step else fault_end
    targets = _targets(entry)
    rows = []
    for sol, df in epochs.groupby("solution", sort=False):
        df = df[df["vehicle"].isin(targets)].sort_values("t_s")
        used_col, rej_col = f"used_{mtype}", f"rejected_{mtype}"
        sensors_used = mtype == "pr" or sol == "GPS+UWB+Bearing"
        t = df["t_s"].to_numpy()
        before = df[(t >= start_s - 10.0) & (t < start_s)]
        inwin = df[(t >= start_s - 1e-9) & (t <= window_end + 1e-9)]
        det, lat = "n", float("nan")
        if not sensors_used:
            det = "n/a"
        elif kind == "cycle_slip":
            det = "n/a"
        elif kind == "nonfinite":
            det = "skipped"
        elif kind == "clock_jump":
            ok = inwin[inwin[used_col] >= 4]
            if len(ok):
                det, lat = "y", float(ok["t_s"].iloc[0] - start_s)
        elif kind in MISSING_KINDS:
            # fewer used than the fewest in the 10 s before (none at all for an outage)
            floor = before[used_col].min() if len(before) else 1
            miss = inwin[(inwin[used_col] < max(floor, 1)) & (inwin["t_s"] < fault_end)]
            if len(miss):
                det, lat = "y", float(miss["t_s"].iloc[0] - start_s)
        elif kind in MEASUREMENT_KINDS:
            rej = inwin[inwin[rej_col] > 0]
            if len(rej):
                det, lat = "y", float(rej["t_s"].iloc[0] - start_s)
        valid = df["initialized"].astype(bool) & np.isfinite(df["along_err_m"])
        ok_err = ((df["along_err_m"].abs() <= 3 * df["sigma_along_m"])
                  & (df["across_err_m"].abs() <= 3 * df["sigma_across_m"]))
        # per epoch: every target within 3 sigma; the measurement type used at least once
        # by every target in the 3 s hold (UWB and bearings may come slower than GNSS)
        g = (ok_err & valid).groupby(df["t_s"]).all()
        used = df[used_col].groupby([df["t_s"], df["vehicle"]]).sum().unstack(fill_value=0)
        times = g.index.to_numpy()
        rec = float("nan")
        cand = times[times >= recover_from - 1e-9]
        for tt in cand:
            hold = cand[(cand >= tt) & (cand < tt + 3.0)]
            if not g.loc[hold].all():
                continue
            if sensors_used and not (used.loc[hold].sum(axis=0) > 0).all():
                continue
            rec = float(tt - recover_from)
            break
        meas = summary["statistics"].get(sol, {}).get("measurements", {}).get(mkind, {})
        fw = inwin.index[valid.loc[inwin.index].to_numpy()]
        exceed = float(np.mean(~ok_err.loc[fw])) if len(fw) else float("nan")
        not_init = float(np.mean(~valid.loc[inwin.index])) if len(inwin) else float("nan")
        rows.append({
            "fault": kind, "solution": sol, "targets": ",".join(targets), "detected": det,
            "latency_s": lat,
            "max_along_before_m": float(before["along_err_m"].abs().max()) if len(before) else float("nan"),
            "max_along_fault_m": float(inwin["along_err_m"].abs().max()) if len(inwin) else float("nan"),
            "max_across_before_m": float(before["across_err_m"].abs().max()) if len(before) else float("nan"),
            "max_across_fault_m": float(inwin["across_err_m"].abs().max()) if len(inwin) else float("nan"),
            "exceed_3sigma_fault": exceed,
            "uninitialized_frac": not_init,
            "recovery_s": rec,
            "true_rej": int(meas.get("true_rejections", 0)), "missed": int(meas.get("missed_faults", 0)),
            "false_rej": int(meas.get("false_rejections", 0)),
            "injected": int(sum(v for k, v in summary.get("faults_injected", {}).items() if k.endswith(kind))),
        })
    return rows


def run_fault(kind: str, out: Path, *, quick: bool) -> list[dict[str, Any]]:
    from v2v.config.scenario import load_scenario
    from v2v.run import run_scenario

    entry, mtype, mkind = FAULTS[kind]
    if quick:
        entry = QUICK_OVERRIDES.get(kind, entry)
    duration_s, start_s = (40.0, 15.0) if quick else (60.0, 20.0)
    fault = f'{{kind="{kind}", start_s={start_s}, {entry}}}'
    sc = load_scenario(None, ["clusters.0.vehicles=3", f"duration_s={duration_s}", SOLUTIONS, f"faults=[{fault}]"])
    run_dir = out / "runs" / kind
    res = run_scenario(sc, run_dir, quiet=True, replay=False)
    epochs = pd.read_parquet(run_dir / "epochs.parquet")
    summary = json.loads((run_dir / "summary.json").read_text())
    f = sc.faults[0]
    t_end = float(epochs["t_s"].max())
    rows = analyse(kind, entry, mtype, mkind, f.start_s, f.duration_s, t_end, epochs, summary)
    del res
    return rows


def _plot(out: Path, kinds: list[str], quick: bool) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(kinds), 1, figsize=(8, 2.2 * len(kinds)), sharex=True, squeeze=False)
    start_s = 15.0 if quick else 20.0
    for ax, kind in zip(axes[:, 0], kinds, strict=True):
        ep = pd.read_parquet(out / "runs" / kind / "epochs.parquet")
        v = _targets(FAULTS[kind][0])[0]
        for sol, df in ep[ep["vehicle"] == v].groupby("solution", sort=False):
            ax.plot(df["t_s"], df["along_err_m"], lw=0.8, label=f"{sol} along error")
            ax.fill_between(df["t_s"], -3 * df["sigma_along_m"], 3 * df["sigma_along_m"], alpha=0.15)
        ax.axvline(start_s, color="k", ls="--", lw=0.8)
        ax.set_ylabel("m")
        ax.set_title(f"{kind} ({v}); shaded: +-3 sigma", fontsize=9)
    axes[0, 0].legend(fontsize=7)
    axes[-1, 0].set_xlabel("t (s)")
    fig.tight_layout()
    path = out / "fault_campaign.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _fmt(x: Any) -> str:
    if isinstance(x, float):
        return "nan" if not np.isfinite(x) else f"{x:.2f}"
    return str(x)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--quick", action="store_true", help="3 faults, 40 s runs (smoke test)")
    ap.add_argument("--faults", nargs="*", choices=sorted(FAULTS), help="subset of fault kinds")
    args = ap.parse_args(argv)
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    kinds = list(args.faults or (QUICK if args.quick else FAULTS))
    rows: list[dict[str, Any]] = []
    for kind in kinds:
        rows += run_fault(kind, out, quick=args.quick)
    table = pd.DataFrame(rows)
    table.to_csv(out / "fault_campaign.csv", index=False)
    cols = list(table.columns)
    md = ["# Fault campaign", "",
          f"hospital_loop, 3 cars, {'40' if args.quick else '60'} s, fault from {'15' if args.quick else '20'} s; "
          "errors of the fault's target vehicle(s), lead frame. See experiments/fault_campaign.py for definitions.",
          "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    md += ["| " + " | ".join(_fmt(r[c]) for c in cols) + " |" for r in rows]
    (out / "fault_campaign.md").write_text("\n".join(md) + "\n")
    _plot(out, kinds, args.quick)
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    sys.exit(main())
