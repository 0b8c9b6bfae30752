"""UWB and bearing links in an urban canyon with background traffic and trucks.

A cluster (default 6 vehicles, three lanes) drives ``urban_canyon`` among background traffic
(``background.vehicles_per_hour``, ``truck_fraction``). Three views of the same drive:

1. **Link census** (geometry only): every ``--census-every-s`` seconds, every UWB pair within
   the radio's maximum range is tested with :meth:`v2v.world.occlusion.OcclusionGeometry.links`
   (buildings and vehicle boxes, the end vehicles excluded): line of sight, blocked by a
   building, blocked by a truck/bus (box height >= 3 m) or by a car, and whether a blocked link
   has a single-bounce wall reflection (what a UWB radio would then measure, MacGougan (2009)
   §2.8, §2.11.3). Note: a passenger car (1.5 m) never blocks a link between two roof antennas
   at 1.55 m in this straight-ray model (Fresnel-zone obstruction is not modelled).
2. **UWB ranges** as synthesized for the run (MSSI profile): share of NLOS ranges and their
   error ``range - true range`` (positive: the reflected path is longer), split by what blocks
   the direct path (re-tested at the step nearest each range).
3. **Bearings**: availability = delivered bearings / (ordered pairs within the bearing
   sensor's range at its ticks); a bearing exists only on an unblocked line of sight.

Outputs in ``--out``: ``uwb_nlos_canyon.md`` / ``.json``, ``uwb_link_census.csv``,
``uwb_nlos_ranges.csv`` and ``uwb_nlos_canyon.png`` (link states + NLOS error histogram).
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parent))
from paper_uwb_errors import Drive, drive, markdown, synthesize_bearings, synthesize_uwb  # noqa: E402

TRUCK_MIN_HEIGHT_M = 3.0  # box heights: passenger 1.5 m, truck 3.8 m (v2v/config/default.toml)


def _links_at_step(d: Drive, step, pairs: list[tuple[str, str]]):
    from v2v.sensors.uwb import vehicle_boxes

    boxes, row = vehicle_boxes(step)
    p0 = np.array([step.vehicles[a].xyz_m for a, _ in pairs], dtype=float)
    p1 = np.array([step.vehicles[b].xyz_m for _, b in pairs], dtype=float)
    excl = np.array([[row[a], row[b]] for a, b in pairs], dtype=np.int64)
    res = d.occlusion.links(p0, p1, boxes if len(boxes) else None, excl)
    kind = np.asarray(res.blocker_kind).astype(object)
    veh = kind == "vehicle"
    if veh.any():
        rows = np.asarray(res.blocker_id)[veh].astype(int)
        kind[veh] = np.where(boxes[rows, 5] >= TRUCK_MIN_HEIGHT_M, "truck", "car")
    kind[~np.asarray(res.blocked, dtype=bool)] = "los"
    return kind.astype(str), np.asarray(res.reflection_excess_m, dtype=float), np.linalg.norm(p1 - p0, axis=1)


def link_census(d: Drive, pairs: list[tuple[str, str]], max_range_m: float, every_s: float) -> pd.DataFrame:
    rows = []
    next_t = -math.inf
    for st in d.steps:
        if st.t_s + 1e-9 < next_t:
            continue
        next_t = st.t_s + every_s
        present = [(a, b) for a, b in pairs if a in st.vehicles and b in st.vehicles]
        if not present:
            continue
        kind, refl, dist = _links_at_step(d, st, present)
        for (a, b), k, r, dd in zip(present, kind, refl, dist, strict=True):
            if dd <= max_range_m:
                rows.append({"t_s": st.t_s, "a": a, "b": b, "distance_m": dd, "state": k,
                             "has_reflection": bool(np.isfinite(r)), "reflection_excess_m": r})
    return pd.DataFrame(rows)


def nlos_ranges(d: Drive, ranges) -> pd.DataFrame:
    """NLOS ranges with their error and the blocker at the step nearest their true time."""
    idx = np.flatnonzero(~np.asarray(ranges.los, dtype=bool))
    if idx.size == 0:
        return pd.DataFrame(columns=["t_s", "a", "b", "true_range_m", "error_m", "nlos_excess_m", "blocker"])
    t_steps = np.array([s.t_s for s in d.steps])
    k = np.clip(np.searchsorted(t_steps, ranges.true_t_s[idx]), 0, len(t_steps) - 1)
    kp = np.clip(k - 1, 0, len(t_steps) - 1)
    k = np.where(np.abs(t_steps[kp] - ranges.true_t_s[idx]) < np.abs(t_steps[k] - ranges.true_t_s[idx]), kp, k)
    blocker = np.empty(idx.size, dtype=object)
    for s in np.unique(k):
        sel = np.flatnonzero(k == s)
        pairs = [(ranges.a[idx[i]], ranges.b[idx[i]]) for i in sel]
        kind, _, _ = _links_at_step(d, d.steps[int(s)], pairs)
        blocker[sel] = kind
    return pd.DataFrame({
        "t_s": ranges.t_s[idx], "a": [ranges.a[i] for i in idx], "b": [ranges.b[i] for i in idx],
        "true_range_m": ranges.true_range_m[idx], "error_m": ranges.range_m[idx] - ranges.true_range_m[idx],
        "nlos_excess_m": ranges.errors_m["nlos"][idx], "blocker": blocker.astype(str),
    })


def bearing_availability(d: Drive, bearings, sensor) -> dict:
    """Delivered bearings over opportunities (ordered pairs within range and field of view at ticks)."""
    from v2v.frames import ecef_to_enu
    from v2v.measmodels import bearing_rad

    opp = 0
    t0 = d.steps[0].t_s
    last = None
    for st in d.steps:
        if sensor.rate_hz is not None:
            tick = math.floor((st.t_s - t0) * sensor.rate_hz + 1e-9)
            if tick == last:
                continue
            last = tick
        ids = sorted(st.vehicles)
        meas = ids if sensor.measuring == "all" else [v for v in sensor.measuring if v in st.vehicles]
        for a in meas:
            others = [b for b in ids if b != a]
            if not others:
                continue
            va = st.vehicles[a]
            enu = ecef_to_enu(np.array([st.vehicles[b].ecef_m for b in others]), va.lat_rad, va.lon_rad, va.ecef_m)
            beta = bearing_rad(enu, np.full(len(others), va.azimuth_rad))
            ok = (np.linalg.norm(enu, axis=1) <= sensor.max_range_m) & (
                np.abs(beta) <= 0.5 * sensor.field_of_view_rad + 1e-12)
            opp += int(ok.sum())
    return {"bearings": int(bearings.n), "opportunities": opp, "availability": bearings.n / opp if opp else float("nan")}


def plot(census: pd.DataFrame, nl: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(12, 4.5))
    states = ["los", "building", "truck", "car"]
    frac = [float((census["state"] == s).mean()) if len(census) else 0.0 for s in states]
    refl = [float(((census["state"] == s) & census["has_reflection"]).mean()) if len(census) else 0.0 for s in states]
    x = np.arange(len(states))
    axes[0].bar(x, frac, color=["C2", "C7", "C3", "C1"], label="share of links")
    axes[0].bar(x, refl, color="none", edgecolor="k", hatch="//", label="... with a wall reflection (ranged as NLOS)")
    axes[0].set_xticks(x, ["line of sight", "building", "truck/bus", "car"])
    axes[0].set_ylabel("fraction of pair-epochs within range")
    axes[0].set_title(f"UWB link census ({len(census)} pair-epochs)")
    axes[0].legend(fontsize=8)
    axes[0].grid(alpha=0.3, axis="y")
    if len(nl):
        bins = np.linspace(min(0.0, nl["error_m"].min()), nl["error_m"].max() + 1e-6, 40)
        for s, c in (("building", "C7"), ("truck", "C3"), ("car", "C1")):
            e = nl.loc[nl["blocker"] == s, "error_m"]
            if len(e):
                axes[1].hist(e, bins=bins, histtype="step", lw=1.8, color=c, label=f"blocked by {s} (n={len(e)})")
        axes[1].set_yscale("log")
    axes[1].axvline(0.0, color="k", lw=0.8)
    axes[1].set_xlabel("NLOS range error: measured - true (m)")
    axes[1].set_ylabel("ranges")
    axes[1].set_title("UWB ranges through a reflection")
    if len(nl):
        axes[1].legend(fontsize=8)
    axes[1].grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    from v2v.errors import ScriptArgumentParser

    ap = ScriptArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path)
    ap.add_argument("--net", default="urban_canyon")
    ap.add_argument("--vehicles", type=int, default=6)
    ap.add_argument("--duration-s", dest="duration_s", type=float, default=120.0)
    ap.add_argument("--time-gap-s", dest="time_gap_s", type=float, default=3.0,
                    help="cluster departure gap: background vehicles (and trucks) insert between members")
    ap.add_argument("--vehicles-per-hour", dest="vph", type=float, default=2000.0)
    ap.add_argument("--truck-fraction", dest="truck_fraction", type=float, default=0.4)
    ap.add_argument("--census-every-s", dest="census_every_s", type=float, default=0.5)
    ap.add_argument("--profile", default="mssi")
    ap.add_argument("--seed", type=int, default=3)
    ap.add_argument("--quick", action="store_true")
    args = ap.parse_args(argv)
    from v2v.errors import check_positive

    check_positive(args.census_every_s, "--census-every-s")
    if args.quick:
        args.duration_s = min(args.duration_s, 60.0)
        args.census_every_s = max(args.census_every_s, 1.0)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options
    from v2v.pipeline import build_bearing
    from v2v.sensors.uwb import profile_by_name

    with script_options({"network.name": "--net", "duration_s": "--duration-s", "seed": "--seed",
                         "clusters.0.vehicles": "--vehicles", "clusters.0.time_gap_s": "--time-gap-s",
                         "background.vehicles_per_hour": "--vehicles-per-hour",
                         "background.truck_fraction": "--truck-fraction", "sensors.uwb.profile": "--profile"}):
        sc = load_scenario(None, [
            f'network.name="{args.net}"', f"duration_s={args.duration_s}", f"seed={args.seed}",
            f"clusters.0.vehicles={args.vehicles}", "clusters.0.lanes=[0,1,2]", f"clusters.0.time_gap_s={args.time_gap_s}",
            f"background.vehicles_per_hour={args.vph}", f"background.truck_fraction={args.truck_fraction}",
            f'sensors.uwb.profile="{args.profile}"', "solutions=[]",
        ])
        d = drive(sc)
    network, ranges = synthesize_uwb(d)
    bearings = synthesize_bearings(d)
    max_range = profile_by_name(args.profile).max_range_m
    census = link_census(d, list(network.pairs), max_range, args.census_every_s)
    census.to_csv(out / "uwb_link_census.csv", index=False)
    nl = nlos_ranges(d, ranges)
    nl.to_csv(out / "uwb_nlos_ranges.csv", index=False)
    ba = bearing_availability(d, bearings, build_bearing(sc))
    plot(census, nl, out / "uwb_nlos_canyon.png")

    n_bg = [len(s.background) for s in d.steps]
    n_truck = [int(np.sum(np.asarray(s.background).reshape(-1, 6)[:, 5] >= TRUCK_MIN_HEIGHT_M)) for s in d.steps]
    states = {s: float((census["state"] == s).mean()) if len(census) else 0.0 for s in ("los", "building", "truck", "car")}
    blocked = census["state"] != "los" if len(census) else pd.Series(dtype=bool)
    err = nl["error_m"].to_numpy()
    los = np.asarray(ranges.los, dtype=bool)
    los_err = ranges.range_m[los] - ranges.true_range_m[los]
    result = {
        "net": args.net, "vehicles": args.vehicles, "duration_s": float(d.steps[-1].t_s),
        "background_mean": float(np.mean(n_bg)), "trucks_mean": float(np.mean(n_truck)),
        "census_pair_epochs": int(len(census)),
        "census_fraction": states,
        "census_blocked_fraction": float(blocked.mean()) if len(census) else 0.0,
        "census_blocked_with_reflection": float(census.loc[blocked, "has_reflection"].mean()) if blocked.any() else None,
        "uwb_ranges": int(ranges.n), "uwb_los_ranges": int(los.sum()), "uwb_nlos_ranges": int((~los).sum()),
        "uwb_nlos_fraction": float((~los).mean()) if ranges.n else None,
        "uwb_los_error_mean_m": float(los_err.mean()) if los_err.size else None,
        "uwb_los_error_std_m": float(los_err.std()) if los_err.size else None,
        "nlos_error_mean_m": float(err.mean()) if err.size else None,
        "nlos_error_median_m": float(np.median(err)) if err.size else None,
        "nlos_error_p95_m": float(np.percentile(err, 95)) if err.size else None,
        "nlos_error_min_m": float(err.min()) if err.size else None,
        "nlos_error_max_m": float(err.max()) if err.size else None,
        "nlos_error_positive_fraction": float((err > 0).mean()) if err.size else None,
        "nlos_by_blocker": nl["blocker"].value_counts().to_dict() if len(nl) else {},
        "bearing": ba,
        "bearing_expected_from_census": None,
    }
    # Cross-check: bearing availability ~ unblocked share of ordered pairs within the bearing range.
    bs = build_bearing(sc)
    cb = link_census(d, [(a, b) for a in d.vehicles for b in d.vehicles if a != b], bs.max_range_m, 0.5)
    result["bearing_expected_from_census"] = float((cb["state"] == "los").mean()) if len(cb) else None
    (out / "uwb_nlos_canyon.json").write_text(json.dumps(result, indent=2, default=float), encoding="utf-8")

    tab = pd.DataFrame([
        ("UWB pair-epochs within range (census)", f"{result['census_pair_epochs']}"),
        ("line of sight", f"{states['los']:.3f}"),
        ("blocked by building", f"{states['building']:.3f}"),
        ("blocked by truck/bus", f"{states['truck']:.3f}"),
        ("blocked by car", f"{states['car']:.3f}"),
        ("blocked links with a wall reflection", f"{result['census_blocked_with_reflection']}"),
        ("UWB ranges delivered (LOS / NLOS)", f"{result['uwb_los_ranges']} / {result['uwb_nlos_ranges']}"),
        ("NLOS share of delivered ranges", f"{result['uwb_nlos_fraction']}"),
        ("LOS range error mean / std (m)", f"{result['uwb_los_error_mean_m']} / {result['uwb_los_error_std_m']}"),
        ("NLOS range error mean / median / p95 (m)",
         f"{result['nlos_error_mean_m']} / {result['nlos_error_median_m']} / {result['nlos_error_p95_m']}"),
        ("NLOS range error min / max (m)", f"{result['nlos_error_min_m']} / {result['nlos_error_max_m']}"),
        ("NLOS ranges with error > 0", f"{result['nlos_error_positive_fraction']}"),
        ("NLOS ranges by blocker", json.dumps(result["nlos_by_blocker"])),
        ("bearings delivered / opportunities", f"{ba['bearings']} / {ba['opportunities']}"),
        ("bearing availability (census LOS share)", f"{ba['availability']:.3f} ({result['bearing_expected_from_census']:.3f})"
         if ba["opportunities"] else "n/a"),
        ("background vehicles / trucks in the net (mean)", f"{result['background_mean']:.1f} / {result['trucks_mean']:.1f}"),
    ], columns=["quantity", "value"])
    md = [
        f"# UWB / bearing links in {args.net} with background traffic",
        "",
        f"{args.vehicles} cluster vehicles (lanes 0-2), {result['duration_s']:.0f} s, background "
        f"{args.vph:.0f} veh/h with {args.truck_fraction:.0%} trucks, profile {args.profile}, seed {args.seed}.",
        "",
        markdown(tab),
        "",
        "Figure: `uwb_nlos_canyon.png`.",
        "",
    ]
    (out / "uwb_nlos_canyon.md").write_text("\n".join(md), encoding="utf-8")
    print("\n".join(md))
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "uwb_nlos_canyon.py"))
