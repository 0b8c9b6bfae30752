"""Petovello et al. figs. 16-17: UWB range error vs. distance and vs. 10 log10(d^2).

A cluster drives ``open_highway`` in two lanes with the MSSI radio profile; the vehicles
have different top speeds (the lead fastest), so every pair's separation sweeps from the
departure gap (~10-20 m) out past the radios' 100 m limit: each pair sees a range of
distances, as the paper's vehicles did during relative motion.

Only line-of-sight ranges are used (the highway has no walls near the road; a link through
another vehicle's body is blocked and yields no range). Per requester->responder pair a
least-squares line ``error = intercept + slope * d`` is fitted and compared with the pair's
configured error model (:meth:`v2v.sensors.uwb.UwbNetwork.pair_model`):

* intercept vs. ``bias_m`` (turn-around-time bias, MacGougan (2009) eq. 2.25);
* slope vs. ``scale_ppm = oscillator_ppm + walk_ppm`` (eq. 2.25 scale term + geometric walk,
  §2.11.1). The truth the fit should recover exactly in expectation: the other error terms
  (multipath, noise, time-tag sync, quantization, bias random walk) are zero-mean.

The pooled fit over all pairs (what a figure of all ranges shows) is reported too: its
slope is the mean scale factor only if the pair biases do not correlate with distance.

Outputs in ``--out``: ``uwb_pair_fits.md`` / ``.csv``, ``uwb_errors_fig16_17.png`` (per-pair
points, fitted and configured lines, vs. d and vs. 10 log10(d^2)) and the library's pooled
``uwb_error_vs_range.png`` / ``uwb_error_vs_10log_d2.png``.

The sensors are synthesized exactly as :func:`v2v.run.run_scenario` does (same seeds, same
order), without the estimation stage.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class Drive:
    scenario: object
    steps: list
    vehicles: list[str]
    world: object
    occlusion: object
    georef: object


def drive(scenario) -> Drive:
    """Drive the scenario in SUMO (stage 1 of ``run_scenario``) and load its world (stage 2)."""
    from v2v.run import resolve_network
    from v2v.traffic.sumo import NetFiles, SumoSimulation
    from v2v.world.buildings import World, load_polygons
    from v2v.world.occlusion import OcclusionGeometry

    net = resolve_network(scenario)
    files = NetFiles(net_path=net.net_path, poly_paths=net.poly_paths, route_edges=net.route_edges)
    n_steps = int(round(scenario.duration_s / scenario.step_length_s))
    with SumoSimulation(scenario, files, net.georef, seed=scenario.seed) as sim:
        steps = [sim.snapshot()]
        vehicles = sim.cluster_vehicle_ids()
        for _ in range(n_steps):
            st = sim.step()
            if not st.vehicles:
                break
            steps.append(st)
    world = load_polygons(list(net.poly_paths)) if net.poly_paths else World()
    return Drive(scenario=scenario, steps=steps, vehicles=vehicles, world=world,
                 occlusion=OcclusionGeometry(world), georef=net.georef)


def synthesize_uwb(d: Drive):
    """The UWB network and its ranges, with the seeds and call order of ``run_scenario``."""
    from v2v.pipeline import STREAM_UWB, build_uwb, child_seeds

    seeds = child_seeds(d.scenario.seed)
    network = build_uwb(d.scenario, d.vehicles, seeds[STREAM_UWB])
    ranges = network.simulate(d.steps, np.random.default_rng(seeds[STREAM_UWB].spawn(2)[1]), occlusion=d.occlusion)
    return network, ranges


def synthesize_bearings(d: Drive):
    from v2v.pipeline import STREAM_BEARING, build_bearing, child_seeds

    seeds = child_seeds(d.scenario.seed)
    return build_bearing(d.scenario).simulate(d.steps, np.random.default_rng(seeds[STREAM_BEARING]),
                                              occlusion=d.occlusion)


def markdown(df: pd.DataFrame, fmt: str = "{:.4g}") -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, row in df.iterrows():
        cells = [fmt.format(v) if isinstance(v, float) else str(v) for v in row]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------ fits


def line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float, float, float]:
    """Least-squares ``y = a + b x``: (a, b, se_a, se_b) with the residual-based standard errors.

    The standard errors assume independent residuals; UWB multipath is time-correlated
    (tau 5 s), so they are optimistic by roughly sqrt(samples per correlation time).
    """
    n = x.size
    xm = x.mean()
    sxx = float(np.sum((x - xm) ** 2))
    b = float(np.sum((x - xm) * (y - y.mean())) / sxx)
    a = float(y.mean() - b * xm)
    s2 = float(np.sum((y - a - b * x) ** 2) / max(n - 2, 1))
    return a, b, float(np.sqrt(s2 * (1.0 / n + xm**2 / sxx))), float(np.sqrt(s2 / sxx))


def pair_fits(network, ranges, min_ranges: int, min_span_m: float) -> pd.DataFrame:
    los = np.asarray(ranges.los, dtype=bool)
    a = np.asarray(ranges.a)
    b = np.asarray(ranges.b)
    d = ranges.true_range_m
    err = ranges.range_m - ranges.true_range_m
    rows = []
    for pa, pb in network.pairs:
        k = los & (a == pa) & (b == pb)
        if k.sum() < min_ranges or np.ptp(d[k]) < min_span_m:
            continue
        icpt, slope, se_i, se_s = line_fit(d[k], err[k])
        pm = network.pair_model(pa, pb)
        rows.append({
            "pair": f"{pa}->{pb}", "ranges": int(k.sum()), "d_min_m": float(d[k].min()), "d_max_m": float(d[k].max()),
            "fit_bias_m": icpt, "fit_bias_se_m": se_i, "model_bias_m": pm.bias_m,
            "fit_scale_ppm": slope * 1e6, "fit_scale_se_ppm": se_s * 1e6, "model_scale_ppm": pm.scale_ppm,
            "model_osc_ppm": pm.oscillator_ppm, "model_walk_ppm": pm.walk_ppm,
            "resid_std_m": float(np.std(err[k] - icpt - slope * d[k])),
        })
    return pd.DataFrame(rows)


# ------------------------------------------------------------------------------------ figure


def plot_pairs(network, ranges, fits: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    los = np.asarray(ranges.los, dtype=bool)
    a, b = np.asarray(ranges.a), np.asarray(ranges.b)
    d = ranges.true_range_m
    err = ranges.range_m - d
    fig, axes = plt.subplots(1, 2, figsize=(13, 5))
    for i, row in enumerate(fits.itertuples()):
        pa, pb = row.pair.split("->")
        k = los & (a == pa) & (b == pb)
        c = f"C{i % 10}"
        xs = np.linspace(row.d_min_m, row.d_max_m, 20)
        axes[0].plot(d[k], err[k], ".", ms=2, color=c, alpha=0.5)
        axes[0].plot(xs, row.fit_bias_m + row.fit_scale_ppm * 1e-6 * xs, "-", color=c, lw=1.2,
                     label=f"{row.pair}: fit {row.fit_bias_m:+.2f} m, {row.fit_scale_ppm:.0f} ppm "
                           f"(model {row.model_bias_m:+.2f} m, {row.model_scale_ppm:.0f} ppm)")
        axes[0].plot(xs, row.model_bias_m + row.model_scale_ppm * 1e-6 * xs, "--", color=c, lw=0.8)
        axes[1].plot(10 * np.log10(d[k] ** 2), err[k], ".", ms=2, color=c, alpha=0.5)
    if los.any():
        x = 10 * np.log10(d[los] ** 2)
        c1, c0 = np.polyfit(x, err[los], 1)
        xs = np.linspace(x.min(), x.max(), 20)
        axes[1].plot(xs, c0 + c1 * xs, "k-", lw=1.2, label=f"pooled fit: {c0:+.2f} m + {c1:.4f} m/dB")
    axes[0].set_xlabel("true range d (m)")
    axes[0].set_title("UWB error vs. range (fig. 16): solid = fit, dashed = configured model")
    axes[1].set_xlabel("10 log10(d^2) (dB m^2)")
    axes[1].set_title("UWB error vs. 10 log10(d^2) (fig. 17)")
    for ax in axes:
        ax.set_ylabel("range error (m)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="upper left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ------------------------------------------------------------------------------------ main


def scenario_overrides(args: argparse.Namespace) -> list[str]:
    speeds = np.linspace(args.max_speed_mps, args.max_speed_mps - args.speed_step_mps * (args.vehicles - 1),
                         max(args.vehicles, 0))  # (a negative count: the scenario's check names --vehicles)
    ov = [
        'network.name="open_highway"', f"duration_s={args.duration_s}", f"seed={args.seed}",
        f"clusters.0.vehicles={args.vehicles}", "clusters.0.lanes=[0,1]", f"clusters.0.time_gap_s={args.time_gap_s}",
        f'sensors.uwb.profile="{args.profile}"', "solutions=[]",
    ]
    for i, v in enumerate(speeds):
        ov.append(f"vehicle_types.v{i}={{length_m=4.8, width_m=1.9, height_m=1.5, max_speed_mps={v:.3f}, "
                  "accel_mps2=2.6, decel_mps2=4.5, driver_imperfection=0.2, antenna_lever_arm_m=[-2.0, 0.0, 1.55]}")
    ov.append("clusters.0.vehicle_type=[" + ",".join(f'"v{i}"' for i in range(args.vehicles)) + "]")
    return ov


def main(argv: list[str] | None = None) -> int:
    from v2v.errors import ScriptArgumentParser

    ap = ScriptArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--vehicles", type=int, default=5)
    ap.add_argument("--duration-s", dest="duration_s", type=float, default=150.0)
    ap.add_argument("--time-gap-s", dest="time_gap_s", type=float, default=1.0)
    ap.add_argument("--max-speed-mps", dest="max_speed_mps", type=float, default=18.0)
    ap.add_argument("--speed-step-mps", dest="speed_step_mps", type=float, default=1.0,
                    help="top-speed difference between consecutive vehicles")
    ap.add_argument("--profile", default="mssi")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    from v2v.errors import check_positive

    check_positive(args.speed_step_mps, "--speed-step-mps")
    if args.quick:
        args.duration_s = min(args.duration_s, 45.0)
        args.vehicles = min(args.vehicles, 3)
        args.speed_step_mps = max(args.speed_step_mps, 2.0)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options
    from v2v.sensors.uwb import plot_uwb_error_figures

    speed = "--max-speed-mps, --speed-step-mps"  # (each vehicle type's top speed comes from both)
    with script_options({"duration_s": "--duration-s", "seed": "--seed", "clusters.0.vehicles": "--vehicles",
                         "clusters.0.vehicle_type": "--vehicles", "clusters.0.time_gap_s": "--time-gap-s",
                         "sensors.uwb.profile": "--profile", "vehicle_types.*.max_speed_mps": speed}):
        sc = load_scenario(None, scenario_overrides(args))
        d = drive(sc)
    network, ranges = synthesize_uwb(d)
    fits = pair_fits(network, ranges, min_ranges=20, min_span_m=10.0)
    fits.to_csv(out / "uwb_pair_fits.csv", index=False)
    los = np.asarray(ranges.los, dtype=bool)
    err = ranges.range_m - ranges.true_range_m
    pooled = line_fit(ranges.true_range_m[los], err[los]) if los.sum() > 2 else (np.nan,) * 4
    plot_pairs(network, ranges, fits, out / "uwb_errors_fig16_17.png")
    plot_uwb_error_figures(ranges, out)
    summary = {
        "ranges": int(ranges.n), "los_ranges": int(los.sum()),
        "d_min_m": float(ranges.true_range_m[los].min()) if los.any() else None,
        "d_max_m": float(ranges.true_range_m[los].max()) if los.any() else None,
        "pooled_bias_m": pooled[0], "pooled_scale_ppm": pooled[1] * 1e6,
        "mean_model_bias_m": float(fits["model_bias_m"].mean()) if len(fits) else None,
        "mean_model_scale_ppm": float(fits["model_scale_ppm"].mean()) if len(fits) else None,
        "max_abs_bias_diff_m": float((fits["fit_bias_m"] - fits["model_bias_m"]).abs().max()) if len(fits) else None,
        "max_abs_scale_diff_ppm": float((fits["fit_scale_ppm"] - fits["model_scale_ppm"]).abs().max())
        if len(fits) else None,
    }
    (out / "uwb_pair_fits.json").write_text(json.dumps({"summary": summary, "pairs": fits.to_dict("records")},
                                                       indent=2), encoding="utf-8")
    show = fits[["pair", "ranges", "d_min_m", "d_max_m", "fit_bias_m", "fit_bias_se_m", "model_bias_m",
                 "fit_scale_ppm", "fit_scale_se_ppm", "model_scale_ppm", "resid_std_m"]]
    md = [
        "# UWB range errors vs. distance (Petovello et al. figs. 16-17)",
        "",
        f"{args.vehicles} vehicles on open_highway (lanes 0-1), {args.duration_s:.0f} s, profile {args.profile}, "
        f"seed {args.seed}; {summary['los_ranges']} LOS ranges of {summary['ranges']}, "
        f"d = {summary['d_min_m']:.1f}-{summary['d_max_m']:.1f} m.",
        "",
        "Per pair: fitted line vs. configured model (bias = intercept, scale = slope). Standard",
        "errors assume independent residuals (optimistic: multipath is correlated over ~5 s).",
        "",
        markdown(show),
        "",
        f"Pooled over all pairs: bias {summary['pooled_bias_m']:+.3f} m, scale {summary['pooled_scale_ppm']:.0f} ppm "
        f"(mean of the pair models: {summary['mean_model_bias_m']:+.3f} m, {summary['mean_model_scale_ppm']:.0f} ppm).",
        "",
        "Figures: `uwb_errors_fig16_17.png`, `uwb_error_vs_range.png`, `uwb_error_vs_10log_d2.png`.",
        "",
    ]
    (out / "uwb_pair_fits.md").write_text("\n".join(md), encoding="utf-8")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "paper_uwb_errors.py"))
