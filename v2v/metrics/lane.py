"""Lane-level relative positioning: relative lane, where-in-lane error and integrity.

Inputs are the run folder's ``epochs.parquet`` rows (one per time, solution and non-lead
vehicle; relative positions are *vehicle minus lead* in ENU at the lead) and, optionally,
``truth.parquet`` (edges and azimuths). Frame: along = the lead's heading, across = 90 deg
to its left (ISO 8855), as in :mod:`v2v.metrics.errors`.

Relative lane (positive = the other vehicle is to the lead's left; SUMO lane index 0 is the
rightmost lane, so index differences have the same sign):

* **true** relative lane: ``lane_index(vehicle) - lane_index(lead)`` when both are on the same
  (non-internal) edge; unknown (NaN) when the truth table puts them on different edges or on
  a junction-internal lane (lane indices of two edges need not correspond, and after a turn
  the follower is in no lane of the lead's road), so ``correct_lane``, ``lane_model_ok`` and
  ``wrong_lane_by_2plus`` count the epochs on the lead's edge only (``same_edge`` is their
  share). Before 2026-12-06 such epochs took the geometric lane below as their truth, which
  scored them against the straight-road model they may break (a follower on the approach
  to a right turn while the lead has turned, both in lane 0, counted as right with the
  geometry saying -1 to -6). Without a truth table (``edge`` / ``lead_edge`` columns) the
  geometric lane stands in for the truth on every epoch;
* **geometric** relative lane: ``round(true_across / lane_width)`` always — what a perfect
  relative position estimate would give under the straight-road lane model below;
* **estimated** relative lane: ``round(est_across / lane_width)``, ``est_across`` the estimated
  relative position rotated into the lead frame.

The lane model assumes a straight road: on a curve or after a turn the across-track offset
of a vehicle 30 m behind is not its lane offset, so ``lane_model_ok`` (geometric = true)
reports how often the model itself holds, and two correct-lane rates are given: against the
lane truth (what an application gets) and against the geometric lane (the positioning
error alone). ``round`` is symmetric round-half-away-from-zero: an across-track offset of
exactly half a lane width is assigned to the neighbouring lane (``sign(x) floor(|x| + 1/2)``).
Lateral offsets inside the lane (SUMO's sublane offset) are not removed: a real system
would not know the other car's offset either.

Rotation into the lead frame: this module uses the lead's **true** azimuth (from
``truth.parquet``, a ``lead_azimuth_rad`` column, or recovered from the rows' own error
rotation, see :func:`lead_azimuth_from_errors`), consistently with ``along_err_m`` /
``across_err_m``; it therefore scores the relative *position* only. A deployed lead rotates
with its *own* azimuth estimate; an azimuth error ``d_alpha`` adds ``along * d_alpha`` to the
across-track offset (0.1 m at 30 m for 0.2 deg, Petovello et al. fig. 14), which is not
included here.

Integrity (per axis, Gaussian error model of the filter's own 1-sigma):

* misleading-information rate at ``k = 3``: fraction of initialized epochs with
  ``|error| > 3 sigma`` (0.27 % expected for a consistent Gaussian filter);
* protection level ``PL = k_PL sigma`` with ``k_PL = Phi^-1(1 - P_IR / 2)`` for the two-sided
  integrity risk ``P_IR`` (3.29 for 1e-3); MI at the PL = ``|error| > PL``;
* availability = fraction of all epochs (uninitialized ones count as unavailable) with
  ``PL <= AL``; hazardously misleading information (HMI) = ``|error| > AL`` while
  ``PL <= AL`` (fraction of all epochs). Stanford-diagram classes after the civil-aviation
  convention (RTCA DO-229), applied to relative positioning.

Alert limits are parameters. Defaults: **across 1.0 m** — with 3.2-3.7 m lanes, the relative
lane flips at half a lane width (1.6-1.85 m); 1.0 m leaves 0.6 m or more for the cars'
lateral offsets inside their lanes (lane level, "which lane"); **along 2.0 m** — about 0.4 car
lengths, the scale at which a following-distance application misjudges the gap. Both are
choices documented here, not a standard's numbers.
"""

from __future__ import annotations

from collections.abc import Mapping
from itertools import repeat
from typing import Any

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray
from scipy import special

F64 = NDArray[np.float64]

ACROSS_ALERT_LIMIT_M = 1.0
ALONG_ALERT_LIMIT_M = 2.0
INTEGRITY_RISK = 1e-3
K_SIGMA = 3.0


def round_half_away(x: ArrayLike) -> F64:
    """Symmetric rounding, ties away from zero: 0.5 -> 1, -0.5 -> -1, 1.49 -> 1 (NaN stays NaN).

    Values within 1e-9 of a tie count as the tie (a rotated half lane width is 0.4999999999...).
    """
    a = np.asarray(x, dtype=float)
    return np.sign(a) * np.floor(np.abs(a) + 0.5 + 1e-9)


def protection_factor(integrity_risk: float) -> float:
    """Two-sided Gaussian multiplier ``k`` with ``P(|e| > k sigma) = integrity_risk`` (3.29 for 1e-3)."""
    if not 0.0 < integrity_risk < 1.0:
        raise ValueError(f"integrity_risk must be in (0, 1), got {integrity_risk!r}")
    return float(-special.ndtri(integrity_risk / 2.0))  # norm.isf


def lead_azimuth_from_errors(err_e_m: ArrayLike, err_n_m: ArrayLike, along_err_m: ArrayLike,
                             across_err_m: ArrayLike) -> F64:
    """Recover the lead azimuth used to rotate an ENU error into (along, across).

    With ``along = e sin(a) + n cos(a)`` and ``across = -e cos(a) + n sin(a)``,
    ``along - i across = (n + i e) exp(-i a)``, hence ``a = arg(n + i e) - arg(along - i across)``.
    Exact whenever the horizontal error is not zero; NaN where it is below 1 nm.
    """
    z_enu = np.asarray(err_n_m, dtype=float) + 1j * np.asarray(err_e_m, dtype=float)
    z_lf = np.asarray(along_err_m, dtype=float) - 1j * np.asarray(across_err_m, dtype=float)
    a = np.angle(z_enu) - np.angle(z_lf)
    a = np.mod(a, 2.0 * np.pi)
    return np.where(np.abs(z_enu) > 1e-9, a, np.nan)


def _across(e_m: F64, n_m: F64, azimuth_rad: F64) -> F64:
    return -e_m * np.cos(azimuth_rad) + n_m * np.sin(azimuth_rad)


def _along(e_m: F64, n_m: F64, azimuth_rad: F64) -> F64:
    return e_m * np.sin(azimuth_rad) + n_m * np.cos(azimuth_rad)


def _time_key(t_s: ArrayLike) -> NDArray[np.int64]:
    """SUMO's clock carries float rounding: join tables on whole milliseconds."""
    return np.round(np.asarray(t_s, dtype=float) * 1000.0).astype(np.int64)


def attach_truth(epochs: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """Add ``lead_azimuth_rad``, ``edge``, ``lead_edge`` to epoch rows from ``truth.parquet``.

    The lead of a row is the truth vehicle flagged ``is_lead`` in the row's cluster at the
    same time (``lead`` column if the epochs have one). A left join: rows keep their order;
    a row without its truth gets NaN.
    """
    cols = _truth_columns(epochs, truth)
    if cols is None:  # repeated keys: the join multiplies rows
        return _attach_truth_merge(epochs, truth)
    out = epochs.drop(columns=[c for c in ("edge", "lead_edge", "lead_azimuth_rad") if c in epochs]).reset_index(drop=True)
    for k, v in cols.items():
        out[k] = v
    return out


def _truth_columns(epochs: pd.DataFrame, truth: pd.DataFrame) -> dict[str, ArrayLike] | None:
    """``edge``, ``lead_edge``, ``lead_azimuth_rad`` of every epoch row, the left join of
    :func:`attach_truth` done by key lookup; None if the truth repeats a (time, vehicle) or
    a (time, cluster) lead key (the join would then add rows)."""
    tk = _time_key(truth["t_s"])
    ek = _time_key(epochs["t_s"])
    is_lead = truth["is_lead"].astype(bool).to_numpy()
    if "cluster" in epochs:
        lead_keys = list(zip(tk[is_lead].tolist(), truth["cluster"].to_numpy()[is_lead].tolist(), strict=True))
        row_lead_keys = list(zip(ek.tolist(), epochs["cluster"].tolist(), strict=True))
    else:  # the first lead of each time
        lead_keys, row_lead_keys = tk[is_lead].tolist(), ek.tolist()
    veh_keys = list(zip(tk.tolist(), truth["vehicle"].tolist(), strict=True))
    first_lead = dict(zip(reversed(lead_keys), reversed(np.flatnonzero(is_lead).tolist()), strict=True))
    vrow = dict(zip(veh_keys, range(len(veh_keys)), strict=True))
    if len(vrow) != len(veh_keys) or ("cluster" in epochs and len(first_lead) != len(lead_keys)):
        return None
    n = len(epochs)
    iv = np.fromiter(map(vrow.get, zip(ek.tolist(), epochs["vehicle"].tolist(), strict=True), repeat(-1)), np.int64, n)
    il = np.fromiter(map(first_lead.get, row_lead_keys, repeat(-1)), np.int64, n)
    return {"edge": _take(truth["edge"], iv), "lead_edge": _take(truth["edge"], il),
            "lead_azimuth_rad": _take(truth["azimuth_rad"], il)}


def _take(col: pd.Series, idx: NDArray[np.int64]) -> ArrayLike:
    """``col`` at positions ``idx`` (-1: missing, NaN in the column's own dtype), as a left join gives it."""
    return pd.api.extensions.take(col.array, idx, allow_fill=True)


def _attach_truth_merge(epochs: pd.DataFrame, truth: pd.DataFrame) -> pd.DataFrame:
    """:func:`attach_truth` as two left merges (truth with repeated time / vehicle keys)."""
    tr = truth.copy()
    tr["_tk"] = _time_key(tr["t_s"])
    out = epochs.copy()
    out["_tk"] = _time_key(out["t_s"])
    veh = tr[["_tk", "vehicle", "edge"]]
    out = out.drop(columns=[c for c in ("edge", "lead_edge", "lead_azimuth_rad") if c in out], errors="ignore")
    out = out.merge(veh, on=["_tk", "vehicle"], how="left")
    leads = tr[tr["is_lead"].astype(bool)][["_tk", "cluster", "edge", "azimuth_rad"]].rename(
        columns={"edge": "lead_edge", "azimuth_rad": "lead_azimuth_rad"})
    if "cluster" in out:
        out = out.merge(leads, on=["_tk", "cluster"], how="left")
    else:
        out = out.merge(leads.drop(columns="cluster").drop_duplicates("_tk"), on="_tk", how="left")
    return out.drop(columns="_tk")


def _fill_azimuth(df: pd.DataFrame, az: F64) -> F64:
    """Fill azimuths the error rotation cannot give (zero error) from the same epoch's other rows
    (one lead, one azimuth per time and cluster), then from the nearest earlier (else later) epoch."""
    cl = df["cluster"].astype(str).to_numpy() if "cluster" in df else np.zeros(len(df), dtype=str)
    tab = pd.DataFrame({"c": cl, "k": _time_key(df["t_s"]), "az": az})
    per_t = tab.groupby(["c", "k"], sort=True)["az"].first()  # first non-NaN per epoch
    per_t = per_t.groupby(level="c").transform(lambda x: x.ffill().bfill())
    return per_t.reindex(pd.MultiIndex.from_arrays([tab["c"], tab["k"]])).to_numpy(float)


def lane_quantities(epochs: pd.DataFrame, truth: pd.DataFrame | None = None) -> pd.DataFrame:
    """Per-row lane-level quantities (adds columns; rows and order kept).

    Added: ``lead_azimuth_rad`` (if missing), ``true_across_m``, ``est_across_m``,
    ``true_along_m``, ``est_along_m``, ``same_edge``, ``rel_lane_true``, ``rel_lane_geom``,
    ``rel_lane_est``.
    """
    df = epochs.reset_index(drop=True)
    if truth is not None:
        df = attach_truth(df, truth)
    if "lead_azimuth_rad" not in df:
        df = df.copy()
        az = lead_azimuth_from_errors(
            df["est_e_m"] - df["true_e_m"], df["est_n_m"] - df["true_n_m"], df["along_err_m"], df["across_err_m"])
        df["lead_azimuth_rad"] = _fill_azimuth(df, az)
    out = df.copy()
    for k, v in _lane_columns(df, len(df)).items():
        out[k] = v
    return out


#: the epoch columns :func:`_lane_columns` reads
_LANE_INPUTS = ("lead_azimuth_rad", "true_e_m", "true_n_m", "est_e_m", "est_n_m", "lane_width_m", "edge", "lead_edge",
                "true_lane_index", "lead_lane_index")


def _lane_columns(df: Mapping[str, pd.Series] | pd.DataFrame, n: int) -> dict[str, NDArray]:
    """The columns :func:`lane_quantities` adds, from the epoch columns ``df`` (a frame or a
    dict of ``n``-row series; ``lead_azimuth_rad`` present)."""
    az = df["lead_azimuth_rad"].to_numpy(float)
    te, tn = df["true_e_m"].to_numpy(float), df["true_n_m"].to_numpy(float)
    ee, en = df["est_e_m"].to_numpy(float), df["est_n_m"].to_numpy(float)
    w = df["lane_width_m"].to_numpy(float)
    out = {"true_across_m": _across(te, tn, az), "est_across_m": _across(ee, en, az),
           "true_along_m": _along(te, tn, az), "est_along_m": _along(ee, en, az)}
    has_truth = "edge" in df and "lead_edge" in df
    if has_truth:
        edge = df["edge"].astype(str)
        same = (edge == df["lead_edge"].astype(str)) & ~edge.str.startswith(":") & df["edge"].notna()
        same &= df["true_lane_index"].notna() & df["lead_lane_index"].notna()
        out["same_edge"] = same.to_numpy(bool)
    else:
        out["same_edge"] = np.zeros(n, dtype=bool)
    geom = round_half_away(out["true_across_m"] / w)
    idx_diff = df["true_lane_index"].to_numpy(float) - df["lead_lane_index"].to_numpy(float) if (
        "true_lane_index" in df and "lead_lane_index" in df) else np.full(n, np.nan)
    out["rel_lane_geom"] = geom
    out["rel_lane_true"] = np.where(out["same_edge"], idx_diff, np.nan) if has_truth else geom
    out["rel_lane_est"] = round_half_away(out["est_across_m"] / w)
    return out


def integrity_counts(err_m: ArrayLike, sigma_m: ArrayLike, available: ArrayLike | None = None, *,
                     alert_limit_m: float, integrity_risk: float = INTEGRITY_RISK,
                     k_sigma: float = K_SIGMA) -> dict[str, float]:
    """Integrity of one axis over a set of epochs.

    ``available`` marks epochs with an estimate (default: all); rates with ``_all`` suffix
    are over all epochs, the others over the epochs with an estimate.
    """
    e = np.abs(np.asarray(err_m, dtype=float))
    s = np.asarray(sigma_m, dtype=float)
    ok = np.ones(e.shape, bool) if available is None else np.asarray(available, dtype=bool)
    ok = ok & np.isfinite(e) & np.isfinite(s)
    n_all = e.size
    k_pl = protection_factor(integrity_risk)
    pl = k_pl * s
    within = ok & (pl <= alert_limit_m)
    n_ok = int(ok.sum())

    def rate(mask: NDArray[np.bool_], n: int) -> float:
        return float(mask.sum() / n) if n else float("nan")

    return {
        "n": n_ok,
        "mi_rate_ksigma": rate(ok & (e > k_sigma * s), n_ok),
        "mi_rate_pl": rate(ok & (e > pl), n_ok),
        "pl_mean_m": float(np.mean(pl[ok])) if n_ok else float("nan"),
        "pl_p95_m": float(np.percentile(pl[ok], 95.0)) if n_ok else float("nan"),
        "availability": rate(within, n_all),
        "hmi_rate": rate(within & (e > alert_limit_m), n_all),
        "k_pl": k_pl,
    }


def _pct(a: F64, p: float) -> float:
    return float(np.percentile(a, p)) if a.size else float("nan")


def _pct3(a: F64) -> list[float]:
    """The 50th, 95th and 99th percentiles of ``a`` (NaN if empty), in one call: each the same
    number as its own :func:`_pct` (the same order statistics, interpolated alike)."""
    return np.percentile(a, (50.0, 95.0, 99.0)).tolist() if a.size else [float("nan")] * 3


def lane_level_table(epochs: pd.DataFrame, truth: pd.DataFrame | None = None, *,
                     across_alert_limit_m: float = ACROSS_ALERT_LIMIT_M,
                     along_alert_limit_m: float = ALONG_ALERT_LIMIT_M,
                     integrity_risk: float = INTEGRITY_RISK, k_sigma: float = K_SIGMA,
                     pool_vehicles: bool = False) -> pd.DataFrame:
    """Lane-level table, one row per (solution, vehicle), in order of first appearance (with
    ``pool_vehicles``: one row per solution, vehicle ``"all"``, over every vehicle's epochs, each
    compared with its own vehicle's truth).

    Columns: ``epochs``, ``initialized`` (fraction), ``same_edge`` (fraction of initialized
    epochs on the lead's edge), ``lane_model_ok`` (geometric = true relative lane),
    ``correct_lane`` (estimated = true relative lane), ``correct_lane_geom`` (estimated =
    geometric), ``wrong_lane_by_2plus`` (the three with the true lane: fractions of the
    initialized epochs that have one, on the lead's edge; NaN without any); where-in-lane ``across_abs_p50/p95/p99_m`` (|across
    error|) and ``along_abs_p95_m``; integrity per axis (``across_``/``along_`` prefixes): the
    k-sigma and PL misleading-information rates, mean PL, availability at the alert limit
    and HMI rate (see the module docstring). Fractions of initialized epochs unless noted.
    """
    out = pd.DataFrame(lane_level_rows(epochs, truth, across_alert_limit_m=across_alert_limit_m,
                                       along_alert_limit_m=along_alert_limit_m, integrity_risk=integrity_risk,
                                       k_sigma=k_sigma, pool_vehicles=pool_vehicles))
    out.attrs.update({"across_alert_limit_m": across_alert_limit_m, "along_alert_limit_m": along_alert_limit_m,
                      "integrity_risk": integrity_risk, "k_pl": protection_factor(integrity_risk), "k_sigma": k_sigma})
    return out


def lane_level_rows(epochs: pd.DataFrame, truth: pd.DataFrame | None = None, *,
                    across_alert_limit_m: float = ACROSS_ALERT_LIMIT_M,
                    along_alert_limit_m: float = ALONG_ALERT_LIMIT_M,
                    integrity_risk: float = INTEGRITY_RISK, k_sigma: float = K_SIGMA,
                    pool_vehicles: bool = False) -> list[dict[str, Any]]:
    """The rows of :func:`lane_level_table` as dicts of Python scalars (what ``summary.json``
    stores), without building the frame."""
    df = epochs.reset_index(drop=True)
    truth_cols = _truth_columns(df, truth) if truth is not None else None
    if truth_cols is not None:  # lane_quantities' columns without building its frame
        src: dict[str, pd.Series] = {c: df[c] for c in _LANE_INPUTS if c in df}
        src.update({k: pd.Series(v) for k, v in truth_cols.items()})
        q: Mapping[str, Any] = {**{c: df[c] for c in ("solution", "vehicle", "initialized", "across_err_m", "along_err_m",
                                                      "sigma_across_m", "sigma_along_m")}, **_lane_columns(src, len(df))}
    else:
        q = lane_quantities(df, truth)
    col = {c: np.asarray(q[c]) for c in ("initialized", "across_err_m", "along_err_m", "sigma_across_m", "sigma_along_m",
                                         "same_edge", "rel_lane_geom", "rel_lane_true", "rel_lane_est")}
    # the rows of each (solution, vehicle) in order of first appearance, as groupby(sort=False)
    # gives them (rows with a missing key belong to no group)
    sol_code, sols = pd.factorize(np.asarray(q["solution"], dtype=object))
    veh_code, vehs = pd.factorize(np.asarray(q["vehicle"], dtype=object))
    if pool_vehicles:  # (after the truth join, which is by vehicle)
        veh_code, vehs = np.where(veh_code >= 0, 0, -1), pd.Index(["all"])
    n_veh = max(len(vehs), 1)  # pair code = solution code * n_veh + vehicle code; -1: a key missing
    pair_code, pairs = pd.factorize(np.where((sol_code >= 0) & (veh_code >= 0), sol_code * n_veh + veh_code, -1))
    rows = []
    for k, pair in enumerate(pairs.tolist()):
        if pair < 0:
            continue
        sol, veh = sols[pair // n_veh], vehs[pair % n_veh]
        g = np.flatnonzero(pair_code == k)
        init = col["initialized"][g].astype(bool)
        ok = g[init]
        n = len(ok)

        def frac(mask: NDArray, _n: int = n) -> float:
            return float(np.sum(mask) / _n) if _n else float("nan")

        across = np.abs(col["across_err_m"][ok].astype(float))
        along = np.abs(col["along_err_m"][ok].astype(float))
        geom, true, est = col["rel_lane_geom"][ok], col["rel_lane_true"][ok], col["rel_lane_est"][ok]
        known = np.isfinite(true)  # (a lane truth: on the lead's edge, or no truth table)
        n_known = int(known.sum())
        row = {
            "solution": sol, "vehicle": veh, "epochs": int(len(g)), "initialized": float(init.mean()) if len(g) else float("nan"),
            "same_edge": frac(col["same_edge"][ok]),
            "lane_model_ok": frac(known & (geom == true), n_known),
            "correct_lane": frac(known & (est == true), n_known),
            "correct_lane_geom": frac(est == geom),
            "wrong_lane_by_2plus": frac(known & (np.abs(est - true) >= 2), n_known),
            **dict(zip(("across_abs_p50_m", "across_abs_p95_m", "across_abs_p99_m"), _pct3(across), strict=True)),
            "along_abs_p95_m": _pct(along, 95.0),
        }
        for axis, limit in (("across", across_alert_limit_m), ("along", along_alert_limit_m)):
            ic = integrity_counts(col[f"{axis}_err_m"][g], col[f"sigma_{axis}_m"][g], init, alert_limit_m=limit,
                                  integrity_risk=integrity_risk, k_sigma=k_sigma)
            row[f"{axis}_mi_rate_{k_sigma:g}sigma"] = ic["mi_rate_ksigma"]
            row[f"{axis}_mi_rate_pl"] = ic["mi_rate_pl"]
            row[f"{axis}_pl_mean_m"] = ic["pl_mean_m"]
            row[f"{axis}_availability"] = ic["availability"]
            row[f"{axis}_hmi_rate"] = ic["hmi_rate"]
        rows.append(row)
    return rows
