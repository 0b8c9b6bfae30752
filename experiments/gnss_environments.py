"""GNSS in three kinds of street: open highway, urban canyon, residential (foliage).

The same small cluster (default 3 vehicles, one lane, 120 s) drives ``open_highway``,
``urban_canyon`` and ``residential``; the GNSS measurements of each run
(``measurements.parquet``) are summarized per net:

* satellites geometrically above the elevation mask (open sky, from the ephemeris at the
  lead's antenna) vs. satellites tracked (LOS + echo-only NLOS) and LOS only, per vehicle
  mean and minimum;
* the fraction of tracked signals that are NLOS (echo only, MacGougan (2009) section 3.5.1);
* the receiver-local pseudorange error ``multipath + noise + nlos`` (what single differences
  between nearby receivers do not cancel) by LOS / NLOS, and the NLOS excess path;
* C/N0 by LOS / NLOS, and the fraction of signals whose C/N0 is below the open-sky
  elevation model by more than 0.5 dB (canopy attenuation) with the mean loss;
* an independent check of the building blocking: for the lead vehicle once per second,
  the building "horizon" at each satellite's azimuth is computed here from the footprints
  with shapely (``max_b atan((h_b - z_a) / d_b)``, ``d_b`` the horizontal distance to the
  ray's entry into footprint ``b``; exact for flat-roofed extruded footprints), and every
  satellite above its horizon must be tracked LOS, every one below it NLOS or not tracked.

Outputs in ``--out``: ``gnss_environments.md`` / ``.csv`` (per net), ``gnss_per_vehicle.csv``,
``gnss_sats_and_nlos.png`` (satellites over time per net + NLOS error histogram),
``gnss_skyplot_<net>.png`` (one epoch: LOS / NLOS / blocked satellites and the building
horizon), and ``runs/<net>/`` (the simulator's run folders).

Run::

    .venv/bin/python experiments/gnss_environments.py --out /tmp/gnss_env
    .venv/bin/python experiments/gnss_environments.py --out /tmp/gnss_env_rinex \\
        --rinex /work/shared/data/gnss_2021-04-28/brdc1180.21n --start-utc 2021-04-28T19:00:00Z
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd

NETS = ("open_highway", "urban_canyon", "residential")


@dataclass(frozen=True)
class NetRun:
    net: str
    folder: Path
    scenario: object
    meas: pd.DataFrame  # pseudorange rows of measurements.parquet
    truth: pd.DataFrame
    epoch_times: np.ndarray  # GNSS epoch times (s)


def _overrides(net: str, args: argparse.Namespace) -> list[str]:
    ov = [
        f'network.name="{net}"',
        f"duration_s={args.duration_s}",
        f"seed={args.seed}",
        f"clusters.0.vehicles={args.vehicles}",
        "solutions=[]",
    ]
    if args.start_utc:
        ov.append(f'start_utc="{args.start_utc}"')
    if args.rinex:
        ov.append(f'sensors.gnss.ephemeris="{Path(args.rinex).resolve()}"')
    return ov


# the scenario fields the options set (an error naming one names the option: v2v.errors.script_options)
OPTIONS = {"network.name": "--nets", "duration_s": "--duration-s", "seed": "--seed", "clusters.0.vehicles": "--vehicles",
           "start_utc": "--start-utc", "sensors.gnss.ephemeris": "--rinex"}


def run_net(net: str, args: argparse.Namespace, out: Path) -> NetRun:
    from v2v.config.scenario import load_scenario
    from v2v.errors import script_options
    from v2v.run import run_scenario

    folder = out / "runs" / net
    with script_options(OPTIONS):
        sc = load_scenario(None, _overrides(net, args))
        run_scenario(sc, folder, quiet=True, replay=False, save_measurements=True)
    m = pd.read_parquet(folder / "measurements.parquet")
    truth = pd.read_parquet(folder / "truth.parquet")
    # SUMO's clock carries float rounding (0.30000000000000007): key every row by whole
    # milliseconds and use the GNSS epoch grid k / rate_hz as the time axis.
    truth["t_s"] = np.round(truth["t_s"].to_numpy() * 1000.0) / 1000.0
    m["t_s"] = np.round(m["t_s"].to_numpy() * 1000.0) / 1000.0
    rate = sc.sensors.gnss.rate_hz
    t = np.unique(truth["t_s"].to_numpy())
    k = np.round(t * rate)
    epochs = t[np.abs(t * rate - k) < 1e-6]
    return NetRun(net=net, folder=folder, scenario=sc, meas=m[m["type"] == "pseudorange"].copy(), truth=truth,
                  epoch_times=epochs)


# ------------------------------------------------------------------------------------ geometry


def _world(sc):
    from v2v.run import resolve_network
    from v2v.world.buildings import World, load_polygons
    from v2v.world.occlusion import OcclusionGeometry

    net = resolve_network(sc)
    world = load_polygons(list(net.poly_paths)) if net.poly_paths else World()
    return net.georef, world, OcclusionGeometry(world)


def building_horizon_rad(world, antenna_xyz_m: np.ndarray, grid_az_rad: np.ndarray, max_dist_m: float = 500.0) -> np.ndarray:
    """Elevation of the building skyline at each grid azimuth, independent of v2v.world.occlusion.

    For a flat-roofed footprint ``b`` the ray at elevation ``el`` is blocked iff it enters the
    footprint at horizontal distance ``d_b`` below the roof: ``z_a + d_b tan(el) < h_b``. The
    skyline is therefore ``max_b atan2(h_b - z_a, d_b)`` (-pi/2 where no building is hit).
    ``d_b`` is shapely's distance from the antenna to the ray-footprint intersection.
    """
    import shapely

    xa = np.asarray(antenna_xyz_m, dtype=float)
    az = np.atleast_1d(np.asarray(grid_az_rad, dtype=float))
    out = np.full(az.size, -np.pi / 2)
    if not world.buildings:
        return out
    polys = [shapely.Polygon(b.footprint_xy_m) for b in world.buildings]
    heights = np.array([b.height_m for b in world.buildings])
    tree = shapely.STRtree(polys)
    origin = shapely.Point(xa[0], xa[1])
    for i, a in enumerate(az):
        end = (xa[0] + max_dist_m * np.sin(a), xa[1] + max_dist_m * np.cos(a))
        ray = shapely.LineString([(xa[0], xa[1]), end])
        for j in tree.query(ray, predicate="intersects"):
            d = shapely.distance(origin, ray.intersection(polys[j]))
            out[i] = max(out[i], float(np.arctan2(heights[j] - xa[2], d)))
    return out


def sky_above_mask(sc, truth_lead: pd.DataFrame, times: np.ndarray) -> tuple[np.ndarray, list[dict]]:
    """Satellites above the elevation mask at the lead's antenna (no buildings), per epoch.

    Returns the count per epoch and, per epoch, ``{prn: (az_true_rad, el_rad)}``.
    """
    from v2v.frames import ecef_to_enu
    from v2v.pipeline import build_ephemeris
    from v2v.sensors.gnss.time import utc_to_gps_s

    gps0 = float(utc_to_gps_s(sc.start_utc))
    eph = build_ephemeris(sc, gps0)
    prns = np.asarray(eph.prns())
    mask = np.radians(sc.sensors.gnss.elevation_mask_deg)
    tl = truth_lead.set_index("t_s")
    counts, skies = [], []
    for t in times:
        row = tl.loc[t]
        rx = row[["ecef_x_m", "ecef_y_m", "ecef_z_m"]].to_numpy(dtype=float)
        st = eph.sv_states(prns, gps0 + t - 0.075)
        enu = ecef_to_enu(st.pos_ecef_m, np.radians(row["lat_deg"]), np.radians(row["lon_deg"]), rx)
        el = np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))
        az = np.arctan2(enu[:, 0], enu[:, 1]) % (2 * np.pi)
        ok = np.isfinite(el) & np.asarray(st.healthy) & (el >= mask)
        counts.append(int(ok.sum()))
        skies.append({int(p): (float(a), float(e)) for p, a, e in zip(prns[ok], az[ok], el[ok], strict=True)})
    return np.asarray(counts), skies


# ------------------------------------------------------------------------------------ statistics


def tracked_counts(r: NetRun) -> pd.DataFrame:
    """Satellites tracked (all / LOS) per (epoch, vehicle), zero-filled over the truth rows."""
    tr = r.truth[np.isin(r.truth["t_s"], r.epoch_times)][["t_s", "vehicle"]]
    g = r.meas.groupby(["t_s", "vehicle"])
    cnt = pd.DataFrame({"tracked": g.size(), "los": g["los"].sum()}).reset_index()
    out = tr.merge(cnt, on=["t_s", "vehicle"], how="left").fillna({"tracked": 0, "los": 0})
    out["tracked"] = out["tracked"].astype(int)
    out["los"] = out["los"].astype(int)
    return out


def horizon_check(r: NetRun, world, occl, georef, skies: list[dict], times: np.ndarray) -> tuple[int, int, int]:
    """(agreements, checks, foliage dropouts): satellite above the independent skyline <=> tracked LOS.

    A satellite above the skyline that is not tracked at all while its ray crosses canopy
    (C/N0 pushed below the tracking threshold) is a foliage dropout, not a disagreement.
    """
    lead = r.truth[r.truth["is_lead"]].set_index("t_s")
    m = r.meas
    agree = total = dropouts = 0
    for t, sky in zip(times, skies, strict=True):
        if not sky or t not in lead.index:
            continue
        row = lead.loc[t]
        xyz = row[["x_m", "y_m", "z_m"]].to_numpy(dtype=float)
        conv = georef.grid_convergence_rad(float(xyz[0]), float(xyz[1]))
        prns = np.array(list(sky))
        az = np.array([sky[p][0] for p in prns])
        el = np.array([sky[p][1] for p in prns])
        hor = building_horizon_rad(world, xyz, az - conv)
        mm = m[(m["t_s"] == t) & (m["vehicle"] == row["vehicle"])]
        los_prns = set(mm.loc[mm["los"], "prn"].astype(int))
        # 0.05 deg guard: the ephemeris look-up here skips the light-time iteration.
        clear = el > hor + np.radians(0.05)
        hidden = el < hor - np.radians(0.05)
        decided = clear | hidden
        is_los = np.array([p in los_prns for p in prns])
        untracked = ~np.isin(prns, mm["prn"].astype(int).to_numpy())
        drop = clear & untracked
        if drop.any():
            fol = occl.sky(xyz, az[drop] - conv, el[drop]).foliage_loss_db
            drop[np.flatnonzero(drop)] = fol > 0.0
        agree += int(np.sum((clear & is_los) | (hidden & ~is_los)))
        dropouts += int(drop.sum())
        total += int(decided.sum() - drop.sum())
    return agree, total, dropouts


def net_statistics(r: NetRun, above: np.ndarray, agree: int, checks: int, dropouts: int) -> dict:
    m = r.meas
    cnt = tracked_counts(r)
    local = m["err_multipath_m"] + m["err_noise_m"] + m["err_nlos_m"]
    los = m["los"].to_numpy(dtype=bool)
    nlos_exc = m.loc[~los, "err_nlos_m"].to_numpy()

    def st(x: np.ndarray, f) -> float:
        return float(f(x)) if x.size else float("nan")

    # C/N0 below the open-sky elevation model (minus the echo loss for NLOS) = canopy loss.
    from v2v.sensors.gnss.errors import TrackingConfig, cn0_dbhz

    open_sky = cn0_dbhz(m["elevation_rad"].to_numpy(), TrackingConfig(), 0.0, ~los)
    deficit = open_sky - m["cn0_dbhz"].to_numpy()
    per_v = cnt.groupby("vehicle")["tracked"]
    return {
        "net": r.net,
        "vehicles": int(cnt["vehicle"].nunique()),
        "epochs": int(r.epoch_times.size),
        "sats_above_mask_mean": float(np.mean(above)),
        "tracked_mean": float(cnt["tracked"].mean()),
        "tracked_min_vehicle_mean": float(per_v.mean().min()),
        "tracked_min": int(cnt["tracked"].min()),
        "los_mean": float(cnt["los"].mean()),
        "epochs_lt4_fraction": float((cnt["tracked"] < 4).mean()),
        "nlos_fraction": float((~los).mean()) if los.size else float("nan"),
        "local_err_mean_los_m": st(local[los].to_numpy(), np.mean),
        "local_err_std_los_m": st(local[los].to_numpy(), np.std),
        "local_err_mean_nlos_m": st(local[~los].to_numpy(), np.mean),
        "local_err_std_nlos_m": st(local[~los].to_numpy(), np.std),
        "nlos_excess_min_m": st(nlos_exc, np.min),
        "nlos_excess_median_m": st(nlos_exc, np.median),
        "nlos_excess_max_m": st(nlos_exc, np.max),
        "cn0_los_mean_dbhz": st(m.loc[los, "cn0_dbhz"].to_numpy(), np.mean),
        "cn0_nlos_mean_dbhz": st(m.loc[~los, "cn0_dbhz"].to_numpy(), np.mean),
        "foliage_attenuated_fraction": float(np.mean(deficit > 0.5)) if los.size else float("nan"),
        "foliage_loss_mean_db": st(deficit[deficit > 0.5], np.mean),
        "skyline_checks": checks,
        "skyline_foliage_dropouts": dropouts,
        "skyline_agreement": agree / checks if checks else float("nan"),
    }


# ------------------------------------------------------------------------------------ figures


def _plot_overview(runs: list[NetRun], counts: dict[str, pd.DataFrame], above: dict[str, np.ndarray],
                   path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = len(runs)
    fig, axes = plt.subplots(1, n + 1, figsize=(4.2 * (n + 1), 4.0))
    for ax, r in zip(axes[:n], runs, strict=True):
        c = counts[r.net]
        lead = r.truth.loc[r.truth["is_lead"], "vehicle"].iloc[0]
        cl = c[c["vehicle"] == lead]
        ax.step(r.epoch_times, above[r.net], where="post", color="k", lw=1.2, label="above mask (open sky)")
        ax.step(cl["t_s"], cl["tracked"], where="post", color="C1", label=f"tracked, lead {lead}")
        ax.step(cl["t_s"], cl["los"], where="post", color="C0", ls="--", label="LOS only, lead")
        mean_all = c.groupby("t_s")["tracked"].mean()
        ax.plot(mean_all.index, mean_all.to_numpy(), color="C2", lw=0.8, alpha=0.8, label="tracked, cluster mean")
        ax.set_title(r.net)
        ax.set_xlabel("t (s)")
        ax.set_ylabel("satellites")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="lower left")
    ax = axes[n]
    bins = np.linspace(0.0, max(5.0, max((float(r.meas.loc[~r.meas["los"], "err_nlos_m"].max())
                                          if (~r.meas["los"]).any() else 0.0) for r in runs)), 40)
    for i, r in enumerate(runs):
        e = r.meas.loc[~r.meas["los"], "err_nlos_m"].to_numpy()
        if e.size:
            ax.hist(e, bins=bins, alpha=0.6, color=f"C{i}", label=f"{r.net} (n={e.size})")
    ax.set_xlabel("NLOS pseudorange excess (m)")
    ax.set_ylabel("signals")
    ax.set_title("echo-only (NLOS) errors")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def _plot_skyplot(r: NetRun, world, occl, georef, path: Path) -> dict:
    """Skyplot of the lead at the middle epoch: LOS / NLOS (echo) / blocked satellites + skyline."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = float(r.epoch_times[len(r.epoch_times) // 2])
    lead = r.truth[r.truth["is_lead"] & (r.truth["t_s"] == t)].iloc[0]
    _, skies = sky_above_mask(r.scenario, r.truth[r.truth["is_lead"]], np.array([t]))
    sky = skies[0]
    xyz = lead[["x_m", "y_m", "z_m"]].to_numpy(dtype=float)
    conv = georef.grid_convergence_rad(float(xyz[0]), float(xyz[1]))
    prns = np.array(sorted(sky), dtype=int)
    az = np.array([sky[p][0] for p in prns])
    el = np.array([sky[p][1] for p in prns])
    res = occl.sky(xyz, az - conv, el)
    state = np.where(~res.blocked, "LOS", np.where(np.isfinite(res.echo_excess_m), "NLOS (echo)", "blocked"))
    grid = np.radians(np.arange(0.0, 360.0, 1.0))
    hor = building_horizon_rad(world, xyz, grid - conv)
    fig = plt.figure(figsize=(5.5, 5.5))
    ax = fig.add_subplot(projection="polar")
    ax.set_theta_zero_location("N")
    ax.set_theta_direction(-1)
    hz = 90.0 - np.degrees(np.clip(hor, 0.0, None))
    ax.fill_between(np.append(grid, grid[0]), np.append(hz, hz[0]), 90.0, color="0.6", alpha=0.5,
                    label="buildings")
    colors = {"LOS": "C2", "NLOS (echo)": "C1", "blocked": "C3"}
    for s, c in colors.items():
        k = state == s
        if k.any():
            ax.scatter(az[k], 90.0 - np.degrees(el[k]), s=60, color=c, label=s, zorder=3)
    for p, a, e in zip(prns, az, el, strict=True):
        ax.annotate(str(p), (a, 90.0 - np.degrees(e)), fontsize=8, xytext=(4, 4), textcoords="offset points")
    mask = r.scenario.sensors.gnss.elevation_mask_deg
    ax.plot(grid, np.full(grid.size, 90.0 - mask), "k:", lw=0.8, label=f"mask {mask:.0f} deg")
    ax.set_rlim(0, 90)
    ax.set_yticks([0, 30, 60, 90])
    ax.set_yticklabels(["90", "60", "30", "0"])
    ax.set_title(f"{r.net}: {lead['vehicle']} at t = {t:.1f} s", fontsize=10)
    ax.legend(fontsize=7, loc="lower left", bbox_to_anchor=(-0.12, -0.12))
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return {"net": r.net, "t_s": t, "vehicle": lead["vehicle"],
            **{s: int(np.sum(state == s)) for s in colors}}


# ------------------------------------------------------------------------------------ main


def _markdown(df: pd.DataFrame) -> str:
    cols = list(df.columns)
    lines = ["| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
    for _, row in df.iterrows():
        cells = [f"{v:.3g}" if isinstance(v, float) else str(v) for v in row]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    from v2v.errors import ScriptArgumentParser

    ap = ScriptArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", required=True, type=Path, help="output folder")
    ap.add_argument("--nets", nargs="+", default=list(NETS), choices=NETS)
    ap.add_argument("--duration-s", dest="duration_s", type=float, default=120.0)
    ap.add_argument("--vehicles", type=int, default=3)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--rinex", type=Path, default=None, help="RINEX nav file instead of the nominal constellation")
    ap.add_argument("--start-utc", dest="start_utc", default="", help="scenario start (ISO 8601 UTC)")
    ap.add_argument("--quick", action="store_true", help="short drive (smoke test)")
    args = ap.parse_args(argv)
    if args.quick:
        args.duration_s = min(args.duration_s, 15.0)
    out: Path = args.out
    from v2v.io.atomic import make_folder

    make_folder(out)

    runs, rows, per_vehicle, skyplots = [], [], [], []
    counts: dict[str, pd.DataFrame] = {}
    above: dict[str, np.ndarray] = {}
    for net in args.nets:
        r = run_net(net, args, out)
        runs.append(r)
        georef, world, occl = _world(r.scenario)
        lead_truth = r.truth[r.truth["is_lead"]]
        lead_t = np.intersect1d(r.epoch_times, lead_truth["t_s"].to_numpy())
        above[net], _ = sky_above_mask(r.scenario, lead_truth, r.epoch_times[np.isin(r.epoch_times, lead_t)])
        check_t = lead_t[np.abs(lead_t - np.round(lead_t)) < 1e-6]  # once per second
        _, skies = sky_above_mask(r.scenario, lead_truth, check_t)
        agree, checks, dropouts = horizon_check(r, world, occl, georef, skies, check_t)
        counts[net] = tracked_counts(r)
        rows.append(net_statistics(r, above[net], agree, checks, dropouts))
        pv = counts[net].groupby("vehicle").agg(tracked_mean=("tracked", "mean"), tracked_min=("tracked", "min"),
                                                los_mean=("los", "mean")).reset_index()
        pv.insert(0, "net", net)
        per_vehicle.append(pv)
        skyplots.append(_plot_skyplot(r, world, occl, georef, out / f"gnss_skyplot_{net}.png"))

    table = pd.DataFrame(rows)
    table.to_csv(out / "gnss_environments.csv", index=False)
    pv_all = pd.concat(per_vehicle, ignore_index=True)
    pv_all.to_csv(out / "gnss_per_vehicle.csv", index=False)
    _plot_overview(runs, counts, above, out / "gnss_sats_and_nlos.png")
    sky_df = pd.DataFrame(skyplots)
    ephem = str(args.rinex) if args.rinex else "nominal 27-slot constellation"
    md = [
        "# GNSS in three kinds of street",
        "",
        f"{args.vehicles} vehicles, {args.duration_s:.0f} s, seed {args.seed}, ephemeris: {ephem}.",
        "Local error = multipath + noise + NLOS excess (metres). Skyline agreement: fraction of",
        "(lead, satellite, 1 Hz epoch) where the independent shapely skyline and the simulator agree",
        "on LOS vs. not LOS (satellites lost to canopy attenuation are counted apart as foliage dropouts).",
        "",
        "## Per net",
        "",
        _markdown(table.T.reset_index().rename(columns={"index": "quantity"}).set_axis(
            ["quantity"] + list(table["net"]), axis=1).iloc[1:]),
        "",
        "## Per vehicle",
        "",
        _markdown(pv_all),
        "",
        "## Skyplot epochs (lead)",
        "",
        _markdown(sky_df),
        "",
        "Figures: `gnss_sats_and_nlos.png`, " + ", ".join(f"`gnss_skyplot_{n}.png`" for n in args.nets),
        "",
    ]
    (out / "gnss_environments.md").write_text("\n".join(md), encoding="utf-8")
    (out / "gnss_environments.json").write_text(json.dumps({"nets": rows, "skyplots": skyplots}, indent=2,
                                                           default=float), encoding="utf-8")
    print((out / "gnss_environments.md").read_text(encoding="utf-8"))
    return 0


if __name__ == "__main__":
    from v2v.errors import script_main

    sys.exit(script_main(main, "gnss_environments.py"))
