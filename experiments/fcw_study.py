"""Forward collision warning from V2V relative positioning, against truth, at traffic lights.

An in-line cluster (default 4 vehicles, one lane: vehicle i+1 follows i) drives the
``urban_canyon`` main-street rectangle, whose traffic lights make the cluster brake hard
(truth ``accel_mps2`` down to -4.5 m/s^2) and close on the queue ahead. Each follower runs
the FCW of :mod:`v2v.apps.fcw` (TTC < 2.5 s and closing > 0.5 m/s; NHTSA NCAP / ISO 15623
basis there) on the relative position and velocity of the vehicle ahead, once from truth
and once from each solution (GPS, GPS+UWB, GPS+Bearing, GPS+UWB+Bearing; the filter's
velocity states). Braking events are detected from truth (< -2 m/s^2 for >= 0.3 s).
Variants ``canyon`` (with buildings) and ``open`` (buildings removed) as in
``experiments/lane_level.py``.

Reported per solution: gap and closing-speed RMS errors, truth warnings detected / missed,
false warnings, and per braking event of the vehicle ahead the outcome (hit, missed, false)
and the warning-time error (estimate minus truth, negative = earlier).

Outputs in ``--out``: ``fcw.md``, ``fcw_solutions.csv``, ``fcw_pairs.csv``, ``fcw_events.csv``,
``fcw_braking.csv``, ``fcw_ttc_<variant>.png`` and ``runs/<variant>/``.

Run::

    .venv/bin/python experiments/fcw_study.py --out /tmp/fcw
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pandas as pd


def _lane_level_module():
    spec = importlib.util.spec_from_file_location("v2v_exp_lane_level", Path(__file__).with_name("lane_level.py"))
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def _plot_ttc(epochs: pd.DataFrame, res: dict, pair: tuple[str, str], lead: str, geometry: dict, cfg,
              path: Path, title: str) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from v2v.apps.fcw import pair_kinematics

    f, a = pair
    fig, axes = plt.subplots(2, 1, figsize=(10, 6), sharex=True)
    sols = list(epochs["solution"].drop_duplicates())
    kt = pair_kinematics(epochs, sols[0], f, a, lead, source="true", **geometry, config=cfg)
    axes[0].plot(kt["t_s"], kt["ttc_s"], color="k", lw=1.6, label="truth")
    axes[1].plot(kt["t_s"], kt["gap_m"], color="k", lw=1.6, label="truth")
    for i, sol in enumerate(sols):
        ke = pair_kinematics(epochs, sol, f, a, lead, source="est", **geometry, config=cfg)
        axes[0].plot(ke["t_s"], ke["ttc_s"], color=f"C{i}", lw=0.8, label=sol)
        axes[1].plot(ke["t_s"], ke["gap_m"], color=f"C{i}", lw=0.8, label=sol)
    axes[0].axhline(cfg.ttc_threshold_s, color="C3", ls="--", lw=0.8, label=f"TTC {cfg.ttc_threshold_s:g} s")
    br = res["braking"]
    for ax in axes:
        for ev in br[br["vehicle"] == a].itertuples():
            ax.axvspan(ev.t_start_s, ev.t_end_s, color="0.85", lw=0)
        ax.grid(alpha=0.3)
    axes[0].set_ylim(0, 10)
    axes[0].set_ylabel("TTC (s)")
    axes[1].set_ylabel("gap (m)")
    axes[1].set_xlabel("t (s)   (grey: braking of the vehicle ahead)")
    axes[0].set_title(f"{title}: {f} behind {a}")
    axes[0].legend(fontsize=7, ncol=3, loc="upper right")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from v2v.apps.fcw import FcwConfig, antenna_arms_x_m, fcw_study, to_markdown

    ll = _lane_level_module()
    from v2v.errors import ScriptArgumentParser

    ap = ScriptArgumentParser(description=__doc__.split("\n\n")[0])
    ll.add_common_arguments(ap, duration_s=180.0, vehicles=4)
    ap.add_argument("--ttc-threshold-s", dest="ttc", type=float, default=FcwConfig().ttc_threshold_s)
    args = ap.parse_args(argv)
    from v2v.errors import check_positive

    check_positive(args.ttc, "--ttc-threshold-s")
    if args.quick:
        args.duration_s = min(args.duration_s, 30.0)
        args.vehicles = min(args.vehicles, 3)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)
    cfg = FcwConfig(ttc_threshold_s=args.ttc)

    sols, pairs, events, braking = [], [], [], []
    for variant in args.variants:
        folder = ll.run_variant(args, variant, out, [0])
        truth = pd.read_parquet(folder / "truth.parquet")
        ep_path = folder / "epochs.parquet"
        if not ep_path.is_file():
            continue
        ep = pd.read_parquet(ep_path)
        res = fcw_study(ep, truth, config=cfg)
        for df, acc in ((res["solutions"], sols), (res["pairs"], pairs), (res["events"], events),
                        (res["braking"], braking)):
            acc.append(df.assign(variant=variant)[["variant", *df.columns]])
        lead = str(truth.loc[truth["is_lead"].astype(bool), "vehicle"].iloc[0])
        if len(res["pairs"]):
            first = (str(res["pairs"]["follower"].iloc[0]), str(res["pairs"]["ahead"].iloc[0]))
            arms = antenna_arms_x_m(truth)
            geometry = {"length_ahead_m": float(truth.loc[truth["vehicle"] == first[1], "length_m"].iloc[0]),
                        "arm_x_ahead_m": arms[first[1]], "arm_x_follower_m": arms[first[0]]}
            _plot_ttc(ep, res, first, lead, geometry, cfg, out / f"fcw_ttc_{variant}.png", f"{args.net} ({variant})")

    def cat(x: list[pd.DataFrame]) -> pd.DataFrame:
        return pd.concat(x, ignore_index=True) if x else pd.DataFrame()

    sol_df, pair_df, ev_df, br_df = cat(sols), cat(pairs), cat(events), cat(braking)
    sol_df.to_csv(out / "fcw_solutions.csv", index=False)
    pair_df.to_csv(out / "fcw_pairs.csv", index=False)
    ev_df.to_csv(out / "fcw_events.csv", index=False)
    br_df.to_csv(out / "fcw_braking.csv", index=False)
    sky = str(args.rinex) if args.rinex else "nominal 27-slot constellation"
    n_brk = int(len(br_df))
    md = [
        "# Forward collision warning from V2V relative positioning",
        "",
        f"net {args.net}, {args.vehicles} vehicles in one lane, {args.duration_s:g} s, seed {args.seed}, "
        f"ephemeris: {sky}. FCW: TTC < {cfg.ttc_threshold_s:g} s and closing > {cfg.min_closing_speed_mps:g} m/s;",
        f"matching tolerance {cfg.match_tolerance_s:g} s; braking events from truth accel < "
        f"{cfg.braking_threshold_mps2:g} m/s^2 ({n_brk} over all vehicles and variants); event window = braking + "
        f"{cfg.braking_horizon_s:g} s.",
        "",
        "## Per solution",
        "",
        to_markdown(sol_df) if len(sol_df) else "(no estimates)",
        "",
        "## Per pair",
        "",
        to_markdown(pair_df) if len(pair_df) else "(no estimates)",
        "",
        "## Braking events of the vehicle ahead",
        "",
        to_markdown(ev_df) if len(ev_df) else "(none)",
        "",
        "Figures: " + ", ".join(f"`fcw_ttc_{v}.png`" for v in args.variants),
        "",
    ]
    (out / "fcw.md").write_text("\n".join(md), encoding="utf-8")
    print("\n".join(md[:12 + (len(sol_df) + 2 if len(sol_df) else 1)]))
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "fcw_study.py"))
