"""Relative-position errors in the lead vehicle's frame, their statistics, and consistency.

Lead frame (ISO 8855, see :mod:`v2v.frames`): along-track = the lead's heading,
across-track = 90 deg to its left (positive left), up. An error is *estimate minus
truth* of the relative position (other vehicle minus lead), expressed in that frame.

The statistics are those of Petovello et al. tables 3-8 (mean, std) plus RMS, the
95th percentile of the absolute error and the maximum absolute error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy import special

from v2v.estimation.filter import (
    KIND_BEARING,
    KIND_SD_DOPPLER,
    KIND_SD_PHASE,
    KIND_SD_PR,
    KIND_SD_PR_PAIR,
    KIND_UWB,
)
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
        "std": float(np.std(e, ddof=1)) if e.size > 1 else float("nan"),  # (undefined for one sample)
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


#: The update kinds averaged by :func:`epoch_nis_sums`: the measurements an epoch row counts in
#: its ``used_*`` / ``rejected_*`` columns (pr, doppler, uwb, bearing, phase). Left out are the
#: pseudo-measurements, which no row counts: height aiding (its sigma is the assumed flatness
#: of the road, not a sensor's noise), the UWB bias/scale bound pulls and the ambiguity holds
#: (constraints, applied without a test).
EPOCH_NIS_KINDS = frozenset({KIND_SD_PR, KIND_SD_PR_PAIR, KIND_SD_DOPPLER, KIND_UWB, KIND_BEARING, KIND_SD_PHASE})


def epoch_nis_sums(
    epoch_t_s: ArrayLike,
    vehicle_ids: Sequence[str],
    t_s: ArrayLike,
    nis: ArrayLike,
    accepted: ArrayLike,
    kind_code: ArrayLike,
    kind_names: Sequence[str],
    set_code: ArrayLike,
    vehicle_sets: Sequence[Sequence[str]],
) -> tuple[F64, NDArray[np.int64]]:
    """Sum and number of the accepted measurement NIS of each output epoch and vehicle.

    The per-epoch NIS of vehicle ``v`` at output epoch ``k`` is ``sums[k, v] / counts[k, v]``:
    the mean NIS ``nu^2 / S`` of the scalar updates that

    * the filter processed in the epoch's output interval, i.e. with a time tag in
      ``(epoch_t_s[k-1] + 1e-9, epoch_t_s[k] + 1e-9]`` (the first epoch: up to its time;
      updates after the last epoch are left out). ``epoch_t_s`` must be the filter's output
      epochs of the updates' span, rows or not: these are the updates an epoch row's
      ``used_*`` counts count (``v2v.pipeline.SolutionRunner``);
    * are of a kind in :data:`EPOCH_NIS_KINDS`;
    * were accepted. A rejected update's NIS (an innovation beyond the gate: 10.8 and up, a
      blunder's 10^6) would swamp the mean of an epoch's few updates; the rejections are the
      ``rejected_*`` counts (the replay's ``rejections`` series);
    * name ``v``: a pair measurement (a UWB range, a bearing, a pair SD pseudorange: two
      vehicles) counts once for each of its vehicles, as the ``used_*`` counts do. Its
      innovation depends on both states (the relative position), and it is not known which
      of the two a large one indicts.

    For a consistent filter each accepted NIS is chi-square with 1 dof, truncated at the gate
    k^2 (mean 0.988 at the default significance 1e-3), and the scalar innovations of a
    sequential update are independent, so the mean of ``n`` of them has expectation ~1 and
    variance ~2 / n (Bar-Shalom, Li & Kirubarajan 2001, sec. 5.4.2). The mean is NaN (0 / 0)
    where ``counts`` is 0: the vehicle had no accepted update in that interval. (A non-finite
    NIS, which the filter never records, would be left out.)

    Parameters
    ----------
    epoch_t_s : (K,) float, increasing
        Output epochs, s.
    vehicle_ids : sequence of str, length V
        The vehicles to report; other vehicles an update names are skipped.
    t_s, nis, accepted : (M,) arrays
        Per update: time tag (s), NIS, accepted flag.
    kind_code, kind_names : (M,) int array, sequence of str
        Per update its kind as an index into ``kind_names``.
    set_code, vehicle_sets : (M,) int array, sequence of tuples of str
        Per update the vehicles it names, as an index into ``vehicle_sets``.

    Returns
    -------
    sums : (K, V) float
    counts : (K, V) int64
    """
    epochs = np.asarray(epoch_t_s, dtype=float).reshape(-1)
    n_ep, n_sets = len(epochs), len(vehicle_sets)
    t = np.asarray(t_s, dtype=float).reshape(-1)
    values = np.asarray(nis, dtype=float).reshape(-1)
    # each update's epoch: the first with t_s <= epoch + 1e-9 (n_ep: after the last), looked up
    # once per run of equal time tags (a GNSS epoch's updates share one)
    starts = np.flatnonzero(np.concatenate([[True], t[1:] != t[:-1]])) if len(t) else np.zeros(0, dtype=np.intp)
    ep = np.repeat(np.searchsorted(epochs, t[starts] - 1e-9, side="left"), np.diff(starts, append=len(t)))
    kinds = np.fromiter((k in EPOCH_NIS_KINDS for k in kind_names), dtype=bool, count=len(kind_names))
    ok = np.asarray(accepted, dtype=bool).reshape(-1) & (ep < n_ep) & np.isfinite(values)
    ok &= kinds[np.asarray(kind_code, dtype=np.intp).reshape(-1)] if len(kinds) else False
    # sum and count per (epoch, vehicle set), the updates left out in a last bin ...
    key = np.where(ok, ep * n_sets + np.asarray(set_code, dtype=np.intp).reshape(-1), n_ep * n_sets)
    by_set = np.bincount(key, weights=np.where(ok, values, 0.0), minlength=n_ep * n_sets + 1)[:-1]
    n_by_set = np.bincount(key, minlength=n_ep * n_sets + 1)[:-1].astype(float)
    # ... then onto each vehicle a set names: times the (sets x vehicles) membership matrix
    index = {v: i for i, v in enumerate(vehicle_ids)}
    member = np.zeros((n_sets, len(vehicle_ids)))
    for i, vs in enumerate(vehicle_sets):
        for v in vs:
            if v in index:
                member[i, index[v]] = 1.0
    sums = by_set.reshape(n_ep, n_sets) @ member
    counts = np.rint(n_by_set.reshape(n_ep, n_sets) @ member).astype(np.int64)
    return sums, counts


# ------------------------------------------------------------------ one output epoch, compiled
EPOCH_COLUMNS = ("true_e_m", "true_n_m", "true_u_m", "est_e_m", "est_n_m", "est_u_m", "true_ve_mps", "true_vn_mps",
                 "true_vu_mps", "est_ve_mps", "est_vn_mps", "est_vu_mps", "along_err_m", "across_err_m", "up_err_m",
                 "sigma_along_m", "sigma_across_m", "sigma_up_m", "cov_ee_m2", "cov_en_m2", "cov_nn_m2", "cov_eu_m2",
                 "cov_nu_m2", "cov_uu_m2", "nees_pos")


_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def epoch_errors(x, P, ipos, ivel, ecef, lead_ecef, rot, vel_enu, lat_lon, lead_vel_enu, sin_az, cos_az, ready):
    """Every number of one output epoch's rows, for ``n`` vehicles at once (compiled).

    Per vehicle ``k`` (columns :data:`EPOCH_COLUMNS`): the true relative position (ENU at the
    lead, ``rot @ (ecef_k - lead_ecef)``, as :func:`v2v.frames.ecef_to_enu`), the estimate
    ``x[ipos[k]:+3]``, the true relative velocity (ENU at the lead, as the estimate
    ``x[ivel[k]:+3]`` is: ``rot @ (R_k^T vel_enu[k] - rot^T lead_vel_enu)``, where ``R_k`` is
    :func:`v2v.frames.ecef_to_enu_rotation` at vehicle ``k``'s ``lat_lon[k]``, since each
    vehicle's true velocity is given in the ENU frame at its own position) and the estimated
    one, the error in the lead's frame
    (:func:`lead_frame_errors`), the 1-sigma in that frame (:func:`lead_frame_sigmas`), the
    ENU covariance entries ee, en, nn, eu, nu, uu (the position block, so that the NEES can be
    recomputed from the rows), and the position NEES ``e^T C^-1 e`` (:func:`nees`).
    Where ``ready[k]`` is false (the vehicle is not initialized) only the truth is given: the
    estimate, its errors, sigmas, covariance and NEES are NaN. The same formulas as those functions, summed in their
    order; results agree with the numpy versions to a few ulps (BLAS may fuse multiply-adds).
    ``sin_az``, ``cos_az``: the lead azimuth's sine and cosine (numpy's, as the frame helpers use).
    ``rot``: :func:`v2v.frames.ecef_to_enu_rotation` at the lead; ``vel_enu`` (n, 3) and
    ``lat_lon`` (n, 2, rad): each vehicle's true velocity in the ENU frame at its own position
    and that position's latitude and longitude; ``lead_vel_enu``: the lead's, ENU at the lead.
    (Differencing the ENU velocities directly would mix frames that turn apart by the
    baseline over the Earth's radius: 38 urad, ~1 mm/s at 25 m/s, for vehicles 240 m apart.)
    """
    n = ipos.shape[0]
    out = np.empty((n, 25))
    e = np.empty(3)
    m = np.empty((3, 3))
    c = np.empty((3, 3))
    r = np.array([[sin_az, cos_az, 0.0], [-cos_az, sin_az, 0.0], [0.0, 0.0, 1.0]])  # lead_frame_rotation
    lv = np.empty(3)  # the lead's velocity in ECEF: rot^T lead_vel_enu (frames.enu_to_ecef_vector)
    for j in range(3):
        lv[j] = rot[0, j] * lead_vel_enu[0] + rot[1, j] * lead_vel_enu[1] + rot[2, j] * lead_vel_enu[2]
    dv = np.empty(3)
    for k in range(n):
        d0, d1, d2 = ecef[k, 0] - lead_ecef[0], ecef[k, 1] - lead_ecef[1], ecef[k, 2] - lead_ecef[2]
        # vehicle k's velocity to ECEF with the rotation at its own position (frames.ecef_to_enu_rotation),
        # minus the lead's
        sl, cl = math.sin(lat_lon[k, 0]), math.cos(lat_lon[k, 0])
        so, co = math.sin(lat_lon[k, 1]), math.cos(lat_lon[k, 1])
        ve, vn, vu = vel_enu[k, 0], vel_enu[k, 1], vel_enu[k, 2]
        dv[0] = -so * ve - sl * co * vn + cl * co * vu - lv[0]
        dv[1] = co * ve - sl * so * vn + cl * so * vu - lv[1]
        dv[2] = cl * vn + sl * vu - lv[2]
        for i in range(3):
            t = rot[i, 0] * d0 + rot[i, 1] * d1 + rot[i, 2] * d2  # frames.ecef_to_enu
            out[k, i] = t
            out[k, 3 + i] = x[ipos[k] + i]
            out[k, 6 + i] = rot[i, 0] * dv[0] + rot[i, 1] * dv[1] + rot[i, 2] * dv[2]  # ECEF -> ENU at the lead
            out[k, 9 + i] = x[ivel[k] + i]
            e[i] = out[k, 3 + i] - t
        out[k, 12] = e[0] * sin_az + e[1] * cos_az  # frames.enu_to_lead_frame
        out[k, 13] = -e[0] * cos_az + e[1] * sin_az
        out[k, 14] = e[2]
        for i in range(3):
            for j in range(3):
                c[i, j] = P[ipos[k] + i, ipos[k] + j]
        for i in range(3):  # diag(R C R^T)
            for j in range(3):
                m[i, j] = r[i, 0] * c[0, j] + r[i, 1] * c[1, j] + r[i, 2] * c[2, j]
            v = m[i, 0] * r[i, 0] + m[i, 1] * r[i, 1] + m[i, 2] * r[i, 2]
            out[k, 15 + i] = math.sqrt(v) if v > 0.0 else 0.0
        out[k, 18] = c[0, 0]
        out[k, 19] = c[0, 1]
        out[k, 20] = c[1, 1]
        out[k, 21] = c[0, 2]
        out[k, 22] = c[1, 2]
        out[k, 23] = c[2, 2]
        if ready[k]:
            out[k, 24] = _nees3(c, e)
        else:  # no estimate yet: its state is the filter's placeholder, not a number to score
            for i in range(3):
                out[k, 3 + i] = np.nan
                out[k, 9 + i] = np.nan
            for i in range(12, 25):
                out[k, i] = np.nan
    return out


@njit(**_JIT)
def _nees3(c, e):
    """``e^T C^-1 e`` for a 3x3 C: Gaussian elimination with partial pivoting (LAPACK gesv's
    algorithm); NaN when C is singular."""
    a = c.copy()
    b = e.copy()
    for col in range(3):
        p = col
        for i in range(col + 1, 3):
            if abs(a[i, col]) > abs(a[p, col]):
                p = i
        if a[p, col] == 0.0:
            return np.nan
        if p != col:
            for j in range(3):
                a[col, j], a[p, j] = a[p, j], a[col, j]
            b[col], b[p] = b[p], b[col]
        for i in range(col + 1, 3):
            f = a[i, col] / a[col, col]
            for j in range(col, 3):
                a[i, j] -= f * a[col, j]
            b[i] -= f * b[col]
    y = np.empty(3)
    for i in range(2, -1, -1):
        s = b[i]
        for j in range(i + 1, 3):
            s -= a[i, j] * y[j]
        y[i] = s / a[i, i]
    return e[0] * y[0] + e[1] * y[1] + e[2] * y[2]
