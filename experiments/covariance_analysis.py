"""Covariance analysis (Petovello et al. section 3.3): the filter's predicted along/across 1-sigma.

The paper summarizes a covariance study (Petovello et al. 2012) whose results it does not
print: adding UWB ranges improves the predicted *along-track* accuracy, adding bearings the
*across-track* accuracy (vehicles in line on one road: a range measures the separation
along the road, a bearing the angle across it), and with three or more vehicles making both
UWB and bearing measurements those two alone determine the horizontal relative solution.
This experiment repeats that study with the simulator: the filter's own predicted 1-sigma
(``epochs.parquet`` columns ``sigma_along_m`` / ``sigma_across_m``, the lead-frame rotation
of the position block of P), averaged over the initialized epochs after ``--converge-s``
and over the follower vehicles, for the four solutions GPS, GPS+UWB, GPS+Bearing and
GPS+UWB+Bearing (azimuths known) versus

(a) the number of vehicles (``clusters.0.vehicles``), in one lane and in three lanes;
(b) the number of lanes (``clusters.0.lanes`` = [0], [0,1], [0,1,2], ``--lanes-vehicles`` cars);
(c) measurement quality: the UWB radio (world profile ``tdc`` / ``mssi``) x the filter's
    ``uwb_sigma_m``, and the bearing sigma (filter ``bearing_sigma_deg`` and world
    ``sensors.bearing.sigma_deg`` set equal);
(d) a GNSS outage (``faults = [{kind = "gnss_outage", ...}]``, every vehicle) with height
    aiding (``height_aiding_sigma_m = 1``): does the horizontal sigma stay bounded?

All runs drive ``open_highway`` (open sky, 3 lanes a direction), one seed, no replay.
The actual-error RMS of the same epochs is tabulated beside each sigma as a consistency
check (the predicted sigma is only meaningful if the errors agree with it).

GNSS outage
-----------
``run_scenario`` writes an epoch at every GNSS tick of an outage and applies the solution's
``height_aiding_sigma_m`` (relative up = 0) before UWB and bearing updates while no GNSS
arrives (``v2v.pipeline.run_solution``). Without height aiding the relative height random-walks,
ranges and bearings are deferred as too nonlinear, and the horizontal solution drifts like GPS
alone. The ``pipeline`` and ``height-aided`` variants of the outage table now run the same code
(they differed while the pipeline lacked both features).

Outputs in ``--out``: ``covariance_vs_vehicles``, ``covariance_vs_lanes``,
``covariance_vs_quality``, ``gnss_outage`` (``.md`` + ``.csv`` each), ``covariance_runs.csv``
(per run, solution and vehicle), ``gnss_outage_timeseries.csv``, figures
``sigma_vs_vehicles.png``, ``sigma_vs_lanes.png``, ``sigma_vs_quality.png``,
``gnss_outage.png``, and ``runs/<case>/`` (the simulator's run folders).

Run::

    .venv/bin/python experiments/covariance_analysis.py --out /tmp/cov
    .venv/bin/python experiments/covariance_analysis.py --out /tmp/cov_quick --quick
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

NET = "open_highway"
SOLUTIONS: dict[str, tuple[str, ...]] = {
    "GPS": ("gnss",),
    "GPS+UWB": ("gnss", "uwb"),
    "GPS+Bearing": ("gnss", "bearing"),
    "GPS+UWB+Bearing": ("gnss", "uwb", "bearing"),
}
COLORS = {"GPS": "tab:gray", "GPS+UWB": "tab:blue", "GPS+Bearing": "tab:orange", "GPS+UWB+Bearing": "tab:green"}


@dataclass(frozen=True, kw_only=True)
class Case:
    """One simulator run of a sweep: its label, x value and scenario overrides."""

    sweep: str
    label: str
    x: float
    vehicles: int
    lanes: tuple[int, ...] = (0,)
    duration_s: float
    uwb_profile: str = "mssi"
    uwb_sigma_m: float = 0.5
    bearing_sigma_deg: float = 0.5
    height_aiding_sigma_m: float | None = None
    outage: tuple[float, float] | None = None  # (start_s, duration_s), every vehicle
    solutions: tuple[str, ...] = tuple(SOLUTIONS)
    extra: dict[str, str] = field(default_factory=dict)
    vehicles_option: str | None = None  # the option ``vehicles`` came from (None: the script's own)

    def options(self) -> dict[str, str]:
        """The scenario fields the script's options set (an error naming one names the option:
        v2v.errors.script_options)."""
        out = {"seed": "--seed"} | ({"clusters.0.vehicles": self.vehicles_option} if self.vehicles_option else {})
        if self.outage is None:
            return out | {"duration_s": "--duration-s"}
        return out | {"duration_s": "--outage-start-s, --outage-duration-s", "faults.0.start_s": "--outage-start-s",
                      "faults.0.duration_s": "--outage-duration-s"}

    def overrides(self, seed: int) -> list[str]:
        h = "" if self.height_aiding_sigma_m is None else f", height_aiding_sigma_m = {self.height_aiding_sigma_m}"
        sols = ", ".join(
            f'{{name = "{s}", sensors = {json.dumps(list(SOLUTIONS[s]))}, '
            f"uwb_sigma_m = {self.uwb_sigma_m}, bearing_sigma_deg = {self.bearing_sigma_deg}{h}}}"
            for s in self.solutions)
        out = [f'network.name = "{NET}"', f"seed = {seed}", f"duration_s = {self.duration_s}",
               f"clusters.0.vehicles = {self.vehicles}", f"clusters.0.lanes = {list(self.lanes)}",
               f'sensors.uwb.profile = "{self.uwb_profile}"', f"sensors.bearing.sigma_deg = {self.bearing_sigma_deg}",
               f"solutions = [{sols}]"]
        if self.outage is not None:
            out.append(f'faults = [{{kind = "gnss_outage", start_s = {self.outage[0]}, duration_s = {self.outage[1]}}}]')
        return out


# ------------------------------------------------------------------------------ GNSS outage


@contextmanager
def height_aided_pipeline() -> Iterator[None]:
    """Kept for the two outage variants' names: ``v2v.pipeline.run_solution`` itself now writes
    epochs through GNSS outages and applies the solution's height aiding, so both variants run
    the same code (an earlier workaround patched the pipeline here)."""
    yield


# ------------------------------------------------------------------------------ runs and statistics


def run_case(case: Case, seed: int, out: Path, *, aided: bool = False) -> Path:
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options
    from v2v.run import run_scenario

    folder = out / "runs" / f"{case.sweep}_{case.label}"
    t0 = time.perf_counter()
    with script_options(case.options()):
        sc = load_scenario(None, case.overrides(seed))
        if aided:
            with height_aided_pipeline():
                run_scenario(sc, folder, quiet=True, replay=False)
        else:
            run_scenario(sc, folder, quiet=True, replay=False)
    print(f"  {case.sweep}/{case.label}: {time.perf_counter() - t0:.1f} s", file=sys.stderr, flush=True)
    return folder


def converged_statistics(folder: Path, converge_s: float) -> pd.DataFrame:
    """Per (solution, vehicle): mean predicted sigma and actual-error RMS over the initialized
    epochs at t >= converge_s, and the UWB / bearing updates used and rejected."""
    ep = pd.read_parquet(folder / "epochs.parquet")
    ep = ep[ep["initialized"] & (ep["t_s"] >= converge_s)]
    rows = []
    for (sol, veh), g in ep.groupby(["solution", "vehicle"], sort=False):
        rows.append({
            "solution": sol, "vehicle": veh, "epochs": len(g),
            "sigma_along_m": g["sigma_along_m"].mean(), "sigma_across_m": g["sigma_across_m"].mean(),
            "rms_along_m": float(np.sqrt((g["along_err_m"] ** 2).mean())),
            "rms_across_m": float(np.sqrt((g["across_err_m"] ** 2).mean())),
            "range_m": float(np.hypot(g["true_e_m"], g["true_n_m"]).mean()),
            "used_uwb": int(g["used_uwb"].sum()), "rejected_uwb": int(g["rejected_uwb"].sum()),
            "used_bearing": int(g["used_bearing"].sum()), "rejected_bearing": int(g["rejected_bearing"].sum()),
        })
    return pd.DataFrame(rows)


def per_solution(per_vehicle: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """Average over the followers; ``worst_*`` = the follower with the largest mean sigma."""
    agg = per_vehicle.groupby(keys, sort=False).agg(
        followers=("vehicle", "count"), epochs=("epochs", "sum"),
        sigma_along_m=("sigma_along_m", "mean"), sigma_across_m=("sigma_across_m", "mean"),
        worst_sigma_along_m=("sigma_along_m", "max"), worst_sigma_across_m=("sigma_across_m", "max"),
        rms_along_m=("rms_along_m", lambda s: float(np.sqrt((s**2).mean()))),
        rms_across_m=("rms_across_m", lambda s: float(np.sqrt((s**2).mean()))),
        used_uwb=("used_uwb", "sum"), rejected_uwb=("rejected_uwb", "sum"),
        used_bearing=("used_bearing", "sum"), rejected_bearing=("rejected_bearing", "sum"),
    ).reset_index()
    return agg


def sweep(cases: list[Case], seed: int, converge_s: float, out: Path) -> pd.DataFrame:
    frames = []
    for c in cases:
        s = converged_statistics(run_case(c, seed, out), converge_s)
        for k, v in (("sweep", c.sweep), ("case", c.label), ("x", c.x), ("vehicles", c.vehicles),
                     ("lanes", len(c.lanes)), ("uwb_profile", c.uwb_profile), ("uwb_sigma_m", c.uwb_sigma_m),
                     ("bearing_sigma_deg", c.bearing_sigma_deg))[::-1]:
            s.insert(0, k, v)
        frames.append(s)
    return pd.concat(frames, ignore_index=True)


def lane_spread(folder: Path) -> float:
    """Mean number of distinct lanes the cluster occupies (SUMO may change lanes)."""
    tr = pd.read_parquet(folder / "truth.parquet", columns=["t_s", "lane_index"])
    return float(tr.groupby("t_s")["lane_index"].nunique().mean())


# ------------------------------------------------------------------------------ GNSS outage


def outage_statistics(folder: Path, start_s: float, end_s: float, variant: str) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Per solution: horizontal sigma (sqrt(sigma_along^2 + sigma_across^2), worst follower)
    before, during and after the outage, and the error/sigma consistency during it."""
    ep = pd.read_parquet(folder / "epochs.parquet")
    ep = ep[ep["initialized"]].copy()
    ep["sigma_h_m"] = np.hypot(ep["sigma_along_m"], ep["sigma_across_m"])
    ep["err_h_m"] = np.hypot(ep["along_err_m"], ep["across_err_m"])
    ts = ep.groupby(["solution", "t_s"], sort=False).agg(
        sigma_along_m=("sigma_along_m", "max"), sigma_across_m=("sigma_across_m", "max"),
        sigma_h_m=("sigma_h_m", "max"), err_h_m=("err_h_m", "max")).reset_index()
    ts.insert(0, "variant", variant)
    rows = []
    for sol, g in ts.groupby("solution", sort=False):
        pre = g[(g["t_s"] >= start_s - 10.0) & (g["t_s"] < start_s)]
        dur = g[(g["t_s"] >= start_s) & (g["t_s"] < end_s)]
        post = g[g["t_s"] >= end_s]
        e = ep[(ep["solution"] == sol) & (ep["t_s"] >= start_s) & (ep["t_s"] < end_s)]
        rows.append({
            "variant": variant, "solution": sol,
            "sigma_h_before_m": pre["sigma_h_m"].mean() if len(pre) else np.nan,
            "epochs_during": len(dur),
            "sigma_along_mean_during_m": dur["sigma_along_m"].mean() if len(dur) else np.nan,
            "sigma_across_mean_during_m": dur["sigma_across_m"].mean() if len(dur) else np.nan,
            "sigma_along_max_during_m": dur["sigma_along_m"].max() if len(dur) else np.nan,
            "sigma_across_max_during_m": dur["sigma_across_m"].max() if len(dur) else np.nan,
            "sigma_h_max_during_m": dur["sigma_h_m"].max() if len(dur) else np.nan,
            "sigma_h_end_m": dur["sigma_h_m"].iloc[-1] if len(dur) else np.nan,
            "err_h_max_during_m": dur["err_h_m"].max() if len(dur) else np.nan,
            "frac_err_within_3sigma_during": float((e["err_h_m"] <= 3.0 * e["sigma_h_m"]).mean()) if len(e) else np.nan,
            "sigma_h_first_after_m": post["sigma_h_m"].iloc[0] if len(post) else np.nan,
        })
    return pd.DataFrame(rows), ts


def gm_drift_m(t_s: float, sigma_v_mps: float = 10.0, tau_s: float = 2.0) -> float:
    """Position std per axis after t_s of a first-order Gauss-Markov velocity (steady state
    sigma_v, correlation time tau) with no measurement: var = 2 sigma_v^2 tau (t - tau (1 - e^(-t/tau)))."""
    return float(np.sqrt(2.0 * sigma_v_mps**2 * tau_s * (t_s - tau_s * (1.0 - np.exp(-t_s / tau_s)))))


# ------------------------------------------------------------------------------ tables


def _fmt(v) -> str:
    if isinstance(v, float | np.floating):
        return "nan" if not np.isfinite(v) else f"{v:.3f}"
    return str(v)


def markdown_table(df: pd.DataFrame, cols: list[str]) -> str:
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for i in range(len(df)):  # column by column: iterrows would turn integer columns into floats
        lines.append("| " + " | ".join(_fmt(df[c].iloc[i]) for c in cols) + " |")
    return "\n".join(lines)


def wide(agg: pd.DataFrame, index: list[str]) -> pd.DataFrame:
    """Rows = cases, columns = '<solution> along' / '<solution> across' (mean sigma, m)."""
    w = agg.pivot_table(index=index, columns="solution", values=["sigma_along_m", "sigma_across_m"], sort=False)
    cols = {}
    for sol in SOLUTIONS:
        for q, name in (("sigma_along_m", "along"), ("sigma_across_m", "across")):
            if (q, sol) in w.columns:
                cols[f"{sol} {name}"] = w[(q, sol)]
    return pd.DataFrame(cols).reset_index()


SIGMA_COLS = ["solution", "sigma_along_m", "sigma_across_m", "worst_sigma_along_m", "worst_sigma_across_m",
              "rms_along_m", "rms_across_m", "used_uwb", "rejected_uwb", "used_bearing", "rejected_bearing"]


def write_sweep(agg: pd.DataFrame, index: list[str], name: str, title: str, note: str, out: Path) -> None:
    agg.to_csv(out / f"{name}.csv", index=False)
    w = wide(agg, index)
    text = [f"# {title}\n", note + "\n", "## Mean predicted 1-sigma over the followers (m)\n",
            markdown_table(w, list(w.columns)), "\n## Per solution: sigma, worst follower, actual RMS, updates\n",
            markdown_table(agg, index + SIGMA_COLS)]
    (out / f"{name}.md").write_text("\n".join(text) + "\n")


# ------------------------------------------------------------------------------ figures


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def figure_vs(agg: pd.DataFrame, x: str, group: str | None, xlabel: str, title: str, path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharex=True)
    styles = ["-o", "--s", ":^"]
    groups = [None] if group is None else list(dict.fromkeys(agg[group]))
    for ax, q, name in ((axes[0], "sigma_along_m", "along-track"), (axes[1], "sigma_across_m", "across-track")):
        for gi, gv in enumerate(groups):
            d = agg if gv is None else agg[agg[group] == gv]
            for sol in SOLUTIONS:
                s = d[d["solution"] == sol].sort_values(x)
                if len(s):
                    lab = sol if gv is None else f"{sol} ({group} {gv})"
                    ax.plot(s[x], s[q], styles[gi % 3], color=COLORS[sol], label=lab, ms=4)
        ax.set_yscale("log")
        ax.set_xlabel(xlabel)
        ax.set_ylabel(f"predicted {name} 1-sigma (m)")
        ax.grid(alpha=0.3, which="both")
    axes[1].legend(fontsize=7, loc="best")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_quality(uwb: pd.DataFrame, brg: pd.DataFrame, path: Path) -> None:
    plt = _plt()
    fig, axes = plt.subplots(2, 2, figsize=(11, 7.5))
    styles = {"tdc": "--s", "mssi": "-o"}
    for col, (q, name) in enumerate((("sigma_along_m", "along-track"), ("sigma_across_m", "across-track"))):
        ax = axes[0, col]
        for prof in dict.fromkeys(uwb["uwb_profile"]):
            d = uwb[uwb["uwb_profile"] == prof]
            for sol in SOLUTIONS:
                s = d[d["solution"] == sol].sort_values("uwb_sigma_m")
                if len(s):
                    ax.plot(s["uwb_sigma_m"], s[q], styles.get(prof, "-x"), color=COLORS[sol], ms=4,
                            label=f"{sol} ({prof} radio)")
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("filter UWB sigma (m)")
        ax.set_ylabel(f"predicted {name} 1-sigma (m)")
        ax.grid(alpha=0.3, which="both")
        ax = axes[1, col]
        for sol in SOLUTIONS:
            s = brg[brg["solution"] == sol].sort_values("bearing_sigma_deg")
            if len(s):
                ax.plot(s["bearing_sigma_deg"], s[q], "-o", color=COLORS[sol], ms=4, label=sol)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_xlabel("bearing sigma, filter = world (deg)")
        ax.set_ylabel(f"predicted {name} 1-sigma (m)")
        ax.grid(alpha=0.3, which="both")
    axes[0, 1].legend(fontsize=7)
    axes[1, 1].legend(fontsize=7)
    fig.suptitle("Predicted sigma vs measurement quality (3 vehicles in line)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_outage(ts: pd.DataFrame, start_s: float, end_s: float, path: Path) -> None:
    plt = _plt()
    variants = list(dict.fromkeys(ts["variant"]))
    fig, axes = plt.subplots(len(variants), 1, figsize=(10, 3.6 * len(variants)), sharex=True, squeeze=False)
    for ax, var in zip(axes[:, 0], variants, strict=True):
        d = ts[ts["variant"] == var]
        for sol in SOLUTIONS:
            s = d[d["solution"] == sol]
            if len(s):
                ax.plot(s["t_s"], s["sigma_h_m"], ".", ms=2, color=COLORS[sol], label=sol)
        ax.axvspan(start_s, end_s, color="k", alpha=0.08, label="GNSS outage")
        ax.set_yscale("log")
        ax.set_ylabel("horizontal 1-sigma,\nworst follower (m)")
        ax.set_title(f"{var}", fontsize=9)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="upper left", markerscale=4)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ------------------------------------------------------------------------------ main


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    from v2v.errors import ScriptArgumentParser

    ap = ScriptArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True, help="output folder")
    ap.add_argument("--seed", type=int, default=1)
    full = {"duration_s": 45.0, "converge_s": 20.0, "vehicles": list(range(2, 11)), "vehicles_3lanes": [3, 6, 9],
            "outage_vehicles": [3, 5], "outage_start_s": 30.0, "outage_duration_s": 30.0}
    quick = {"duration_s": 30.0, "converge_s": 18.0, "vehicles": [2, 3], "vehicles_3lanes": [],
             "outage_vehicles": [3], "outage_start_s": 20.0, "outage_duration_s": 10.0}
    # (defaults None: what is not given comes from the full or the --quick set; what is given wins)
    ap.add_argument("--duration-s", type=float, help="per sweep run (default 45; --quick 30)")
    ap.add_argument("--converge-s", type=float, help="average sigma over t >= this (default 20; --quick 18)")
    ap.add_argument("--vehicles", type=int, nargs="+", help="cluster sizes of the vehicle sweep (default 2..10; --quick 2 3)")
    ap.add_argument("--vehicles-3lanes", type=int, nargs="*",
                    help="vehicle counts of the three-lane vehicle sweep (default 3 6 9; none or --quick: skip)")
    ap.add_argument("--lanes-vehicles", type=int, default=6, help="cluster size of the lane sweep")
    ap.add_argument("--outage-vehicles", type=int, nargs="+", help="(default 3 5; --quick 3)")
    ap.add_argument("--outage-start-s", type=float, help="(default 30; --quick 20)")
    ap.add_argument("--outage-duration-s", type=float, help="(default 30; --quick 10)")
    ap.add_argument("--quick", action="store_true",
                    help="smoke test: 2 and 3 vehicles for 30 s, one 32 s outage run; no lane/quality sweeps "
                         "(the options above that are given still apply)")
    args = ap.parse_args(argv)
    for key, value in (quick if args.quick else full).items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    return args


def outage_duration_s(args: argparse.Namespace) -> float:
    """An outage run's length: the outage's end and 2 s (--quick) or 15 s after it."""
    return args.outage_start_s + args.outage_duration_s + (2.0 if args.quick else 15.0)


def check_options(args: argparse.Namespace) -> None:
    """The UserError a run of any part would raise for the options, before the first part runs
    (a bad --outage-start-s was found after the vehicle, lane and quality sweeps had run and written
    their tables); --converge-s must leave epochs to average."""
    import math

    from v2v.config.scenario import load_scenario
    from v2v.errors import UserError, check_positive, script_options

    check_positive(args.duration_s, "--duration-s")
    check_positive(args.outage_duration_s, "--outage-duration-s")
    if not (args.outage_start_s >= 0.0 and math.isfinite(args.outage_start_s)):
        raise UserError(f"{args.outage_start_s!r} is not a time >= 0 s", field="--outage-start-s",
                        fix="give --outage-start-s >= 0 (seconds after the cluster is on the road)")
    if not 0.0 <= args.converge_s < args.duration_s:
        raise UserError(f"{args.converge_s:g} s is not in [0, duration) = [0, {args.duration_s:g})", field="--converge-s",
                        fix=f"give 0 <= --converge-s < --duration-s ({args.duration_s:g} s)")
    cases = [Case(sweep="vehicles", label="check", x=n, vehicles=n, lanes=lanes, duration_s=args.duration_s,
                  vehicles_option=opt)
             for ns, lanes, opt in ((args.vehicles, (0,), "--vehicles"), (args.vehicles_3lanes, (0, 1, 2), "--vehicles-3lanes"))
             for n in ns]
    if not args.quick:
        cases.append(Case(sweep="lanes", label="check", x=3, vehicles=args.lanes_vehicles, lanes=(0, 1, 2),
                          duration_s=args.duration_s, vehicles_option="--lanes-vehicles"))
    cases += [Case(sweep="outage", label="check", x=n, vehicles=n, lanes=(0,), duration_s=outage_duration_s(args),
                   height_aiding_sigma_m=1.0, outage=(args.outage_start_s, args.outage_duration_s),
                   vehicles_option="--outage-vehicles")
              for n in args.outage_vehicles]
    for c in cases:
        with script_options(c.options()):
            load_scenario(None, c.overrides(args.seed))


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    check_options(args)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)
    dur, seed, conv = args.duration_s, args.seed, args.converge_s
    keys = ["sweep", "case", "x", "vehicles", "lanes", "uwb_profile", "uwb_sigma_m", "bearing_sigma_deg", "solution"]
    per_vehicle = []

    # (a) number of vehicles, one lane (and three lanes)
    print("(a) vehicles", file=sys.stderr)
    cases = [Case(sweep="vehicles", label=f"n{n}_1lane", x=n, vehicles=n, lanes=(0,), duration_s=dur,
                  vehicles_option="--vehicles")
             for n in args.vehicles]
    cases += [Case(sweep="vehicles", label=f"n{n}_3lanes", x=n, vehicles=n, lanes=(0, 1, 2), duration_s=dur,
                   vehicles_option="--vehicles-3lanes")
              for n in args.vehicles_3lanes]
    pv = sweep(cases, seed, conv, out)
    per_vehicle.append(pv)
    agg_n = per_solution(pv, keys)
    write_sweep(agg_n, ["vehicles", "lanes"], "covariance_vs_vehicles", "Predicted sigma vs number of vehicles",
                f"`{NET}`, seed {seed}, {dur:.0f} s runs, sigma averaged over initialized epochs at t >= {conv:.0f} s "
                "and over the followers; `lanes` = lanes the cluster is spread over (round robin). MSSI radios, "
                "filter UWB sigma 0.5 m, bearing sigma 0.5 deg (paper Table 1).", out)
    figure_vs(agg_n, "vehicles", "lanes", "vehicles in the cluster", f"Predicted sigma vs cluster size ({NET})",
              out / "sigma_vs_vehicles.png")

    tables = {"vehicles": agg_n}
    if not args.quick:
        # (b) lanes
        print("(b) lanes", file=sys.stderr)
        n = args.lanes_vehicles
        cases = [Case(sweep="lanes", label=f"{len(ln)}lanes_n{n}", x=len(ln), vehicles=n, lanes=ln, duration_s=dur,
                      vehicles_option="--lanes-vehicles")
                 for ln in ((0,), (0, 1), (0, 1, 2))]
        pv = sweep(cases, seed, conv, out)
        per_vehicle.append(pv)
        agg_l = per_solution(pv, keys)
        spread = {c.x: lane_spread(out / "runs" / f"lanes_{c.label}") for c in cases}
        agg_l.insert(agg_l.columns.get_loc("lanes") + 1, "lanes_occupied_mean",
                     agg_l["lanes"].map(spread))
        write_sweep(agg_l, ["lanes", "lanes_occupied_mean"], "covariance_vs_lanes", "Predicted sigma vs lanes",
                    f"`{NET}`, {n} vehicles round robin over 1-3 lanes, otherwise as the vehicle sweep. "
                    "`lanes_occupied_mean`: distinct lanes the cluster occupies, mean over time (SUMO lane changes).",
                    out)
        figure_vs(agg_l, "lanes", None, "lanes", f"Predicted sigma vs lanes ({n} vehicles, {NET})",
                  out / "sigma_vs_lanes.png")
        tables["lanes"] = agg_l

        # (c) quality
        print("(c) quality", file=sys.stderr)
        cases = [Case(sweep="uwb", label=f"{p}_{s:g}m", x=s, vehicles=3, duration_s=dur, uwb_profile=p, uwb_sigma_m=s)
                 for p in ("tdc", "mssi") for s in (0.1, 0.5, 1.0)]
        cases += [Case(sweep="bearing", label=f"{s:g}deg", x=s, vehicles=3, duration_s=dur, bearing_sigma_deg=s)
                  for s in (0.1, 0.5, 2.0)]
        pv = sweep(cases, seed, conv, out)
        per_vehicle.append(pv)
        agg_q = per_solution(pv, keys)
        write_sweep(agg_q, ["sweep", "uwb_profile", "uwb_sigma_m", "bearing_sigma_deg"], "covariance_vs_quality",
                    "Predicted sigma vs measurement quality",
                    f"`{NET}`, 3 vehicles in line, otherwise as the vehicle sweep. `uwb` rows: world radio profile "
                    "(tdc: 1 Hz, 70 m, ~3 cm precision; mssi: 3 Hz, 100 m, ~9 cm) x the filter's UWB sigma (bearing "
                    "0.5 deg). `bearing` rows: bearing sigma, filter = world (MSSI radios, UWB sigma 0.5 m). The "
                    "filter models neither UWB bias nor scale factor, so a filter sigma below the world's errors "
                    "shows up as rejected ranges.", out)
        figure_quality(agg_q[agg_q["sweep"] == "uwb"], agg_q[agg_q["sweep"] == "bearing"], out / "sigma_vs_quality.png")
        tables["quality"] = agg_q

    runs = pd.concat(per_vehicle, ignore_index=True)
    runs.to_csv(out / "covariance_runs.csv", index=False)

    # (d) GNSS outage
    print("(d) GNSS outage", file=sys.stderr)
    t0, t1 = args.outage_start_s, args.outage_start_s + args.outage_duration_s
    odur = outage_duration_s(args)
    stats, series = [], []
    variants = [("height-aided", True)] + ([] if args.quick else [("pipeline", False)])
    for n in args.outage_vehicles:
        for variant, aided in variants:
            if variant == "pipeline" and n != args.outage_vehicles[0]:
                continue
            c = Case(sweep="outage", label=f"n{n}_{variant}", x=n, vehicles=n, lanes=(0,), duration_s=odur,
                     height_aiding_sigma_m=1.0, outage=(t0, args.outage_duration_s), vehicles_option="--outage-vehicles")
            s, ts = outage_statistics(run_case(c, seed, out, aided=aided), t0, t1, f"{variant}, {n} vehicles")
            s.insert(1, "vehicles", n)
            stats.append(s)
            series.append(ts)
    ost = pd.concat(stats, ignore_index=True)
    ots = pd.concat(series, ignore_index=True)
    ost.to_csv(out / "gnss_outage.csv", index=False)
    ots.to_csv(out / "gnss_outage_timeseries.csv", index=False)
    (out / "gnss_outage.md").write_text(
        "# GNSS outage: UWB + bearings alone (Petovello et al. section 3.3)\n\n"
        f"`{NET}`, vehicles in line, GNSS of every vehicle out for t in [{t0:.0f}, {t1:.0f}) s, height aiding "
        "(relative up = 0 +- 1 m) in every solution. Horizontal sigma = sqrt(sigma_along^2 + sigma_across^2) of "
        "the worst follower at each epoch. `height-aided`: the pipeline with the workaround of the module docstring "
        "(epochs through the outage, height aiding applied); `pipeline`: `run_scenario` unchanged (no epochs "
        "during the outage, height aiding never applied: see the first epoch after). Reference for GPS alone "
        "(no measurement at all): free drift of the Gauss-Markov relative velocity (10 m/s, tau 2 s), "
        f"sigma per axis = sqrt(2 sigma_v^2 tau (T - tau (1 - exp(-T/tau)))) = {gm_drift_m(t1 - t0 - 0.1):.1f} m "
        f"at the last epoch of the outage.\n\n"
        + markdown_table(ost, list(ost.columns)) + "\n")
    figure_outage(ots, t0, t1, out / "gnss_outage.png")

    for name in ("covariance_vs_vehicles", "covariance_vs_lanes", "covariance_vs_quality", "gnss_outage"):
        p = out / f"{name}.md"
        if p.is_file():
            print(p.read_text())
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "covariance_analysis.py"))
