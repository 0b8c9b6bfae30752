"""Relative-position errors in the lead vehicle's frame, their statistics, and consistency.

Lead frame (ISO 8855, see :mod:`v2v.frames`): along-track = the lead's heading,
across-track = 90 deg to its left (positive left), up. An error is *estimate minus
truth* of the relative position (other vehicle minus lead), expressed in that frame.

The statistics are those of Petovello et al. tables 3-8 (mean, std) plus RMS, the
95th percentile of the absolute error and the maximum absolute error.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from v2v.frames import enu_to_lead_frame

F64 = NDArray[np.float64]


def lead_frame_rotation(lead_azimuth_rad: float) -> F64:
    """Rows = along, across (left), up unit vectors expressed in ENU."""
    s, c = np.sin(lead_azimuth_rad), np.cos(lead_azimuth_rad)
    return np.array([[s, c, 0.0], [-c, s, 0.0], [0.0, 0.0, 1.0]])


def lead_frame_errors(est_rel_enu_m: ArrayLike, true_rel_enu_m: ArrayLike, lead_azimuth_rad: ArrayLike) -> F64:
    """(along, across, up) errors, metres, of estimated relative positions; shape (..., 3)."""
    e = np.asarray(est_rel_enu_m, dtype=float) - np.asarray(true_rel_enu_m, dtype=float)
    return enu_to_lead_frame(e, lead_azimuth_rad)


def lead_frame_sigmas(cov_enu_m2: ArrayLike, lead_azimuth_rad: float) -> F64:
    """1-sigma (along, across, up) from a 3x3 ENU position covariance: sqrt(diag(R P R^T))."""
    r = lead_frame_rotation(lead_azimuth_rad)
    p = np.asarray(cov_enu_m2, dtype=float)
    return np.sqrt(np.clip(np.diag(r @ p @ r.T), 0.0, None))


def nees(error: ArrayLike, cov: ArrayLike) -> float:
    """Normalized estimation error squared e^T P^-1 e (chi-square with dim(e) dof if consistent)."""
    e = np.asarray(error, dtype=float)
    p = np.asarray(cov, dtype=float)
    return float(e @ np.linalg.solve(p, e))


def error_statistics(err_m: ArrayLike) -> dict[str, float]:
    """mean, std (ddof=1), RMS, 95th percentile of |err|, max |err|, sample count."""
    e = np.asarray(err_m, dtype=float)
    e = e[np.isfinite(e)]
    if e.size == 0:
        return {"n": 0, "mean": float("nan"), "std": float("nan"), "rms": float("nan"), "p95_abs": float("nan"), "max_abs": float("nan")}
    return {
        "n": int(e.size),
        "mean": float(np.mean(e)),
        "std": float(np.std(e, ddof=1)) if e.size > 1 else 0.0,
        "rms": float(np.sqrt(np.mean(e * e))),
        "p95_abs": float(np.percentile(np.abs(e), 95.0)),
        "max_abs": float(np.max(np.abs(e))),
    }


def chi2_band(dof: int, n_runs: int = 1, confidence: float = 0.95) -> tuple[float, float]:
    """Two-sided band for the *average* of ``n_runs`` chi-square(dof) values.

    ``n_runs * mean`` is chi-square with ``n_runs * dof`` degrees of freedom
    (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2).
    """
    a = (1.0 - confidence) / 2.0
    k = dof * n_runs
    # chi-square quantile = 2 gammaincinv(k/2, p): what scipy.stats.chi2.ppf evaluates (bit for
    # bit), without importing scipy.stats (~0.6 s per process, on every `v2v run`)
    return float(2.0 * special.gammaincinv(k / 2.0, a) / n_runs), float(2.0 * special.gammaincinv(k / 2.0, 1.0 - a) / n_runs)


def consistency_summary(values: ArrayLike, dof: int, confidence: float = 0.95) -> dict[str, Any]:
    """Mean of NEES/NIS samples and the fraction of samples inside the single-run chi-square band."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return {"n": 0, "mean": float("nan"), "frac_in_band": float("nan"), "dof": dof}
    lo, hi = chi2_band(dof, 1, confidence)
    return {"n": int(v.size), "mean": float(v.mean()), "frac_in_band": float(np.mean((v >= lo) & (v <= hi))), "dof": dof, "band": [lo, hi]}
