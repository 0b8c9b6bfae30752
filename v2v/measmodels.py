"""Geometric measurement functions shared by the sensors (which generate measurements)
and the estimator (which predicts them): one model, two users (see STYLE.md).

Everything here is pure numpy on ENU/ECEF vectors; no SUMO, no filter state layout.
Jacobians are analytic and are checked against finite differences in
``tests/test_jacobians.py``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from v2v.frames import wrap_angle

F64 = NDArray[np.float64]


def range_m(p_a: ArrayLike, p_b: ArrayLike) -> F64:
    """Geometric distance between points a and b, metres (paper eq. 1 without errors)."""
    d = np.asarray(p_b, dtype=float) - np.asarray(p_a, dtype=float)
    return np.sqrt(np.sum(d * d, axis=-1))


def range_jacobian(p_a: ArrayLike, p_b: ArrayLike) -> F64:
    """d range / d p_b (the unit line-of-sight vector a->b); d/d p_a is its negative.

    Paper eq. 2: "a row matrix containing direction cosines".
    """
    d = np.asarray(p_b, dtype=float) - np.asarray(p_a, dtype=float)
    return d / np.sqrt(np.sum(d * d, axis=-1, keepdims=True))


def range_difference_m(p_ref: ArrayLike, d_m: ArrayLike, sv_a: ArrayLike, sv_ref: ArrayLike) -> F64:
    """``|sv_a - (p_ref + d)| - |sv_ref - p_ref|`` without cancellation (single differences).

    Subtracting two ~2.2e7 m ranges keeps only ~4e-9 m of precision (their ulp), which is
    1e-6 of a carrier-phase sigma and makes two algebraically equal filters drift apart by
    round-off. With ``e = sv_ref - p_ref`` and ``w = (sv_a - sv_ref) - d`` (both differences
    of nearby vectors, exact or nearly so):
    ``|e + w| - |e| = (2 e.w + w.w) / (|e + w| + |e|)``, accurate to ~1e-16 of the result.
    ``d`` is the small offset of receiver a from the reference receiver (e.g. ``R^T p``).
    """
    e = np.asarray(sv_ref, dtype=float) - np.asarray(p_ref, dtype=float)
    w = (np.asarray(sv_a, dtype=float) - np.asarray(sv_ref, dtype=float)) - np.asarray(d_m, dtype=float)
    num = 2.0 * np.sum(e * w, axis=-1) + np.sum(w * w, axis=-1)
    return num / (np.sqrt(np.sum((e + w) ** 2, axis=-1)) + np.sqrt(np.sum(e * e, axis=-1)))


def bearing_rad(delta_enu_ab: ArrayLike, azimuth_a_rad: ArrayLike) -> F64:
    """Bearing from vehicle a to b relative to a's forward axis (Petovello et al. eq. 5).

    ``beta_ab = atan2(dE_ab, dN_ab) - alpha_a``, wrapped to (-pi, pi]. Positive = b is
    clockwise (to the right) of a's heading, consistent with azimuths clockwise from north.
    """
    d = np.asarray(delta_enu_ab, dtype=float)
    return wrap_angle(np.arctan2(d[..., 0], d[..., 1]) - np.asarray(azimuth_a_rad, dtype=float))


def bearing_jacobian(delta_enu_ab: ArrayLike) -> F64:
    """d bearing / d (dE, dN, dU) of the a->b vector (eq. 6's H_beta); d/d alpha_a = -1.

    d atan2(E, N)/dE = N / (E^2 + N^2); d/dN = -E / (E^2 + N^2); d/dU = 0.
    """
    d = np.asarray(delta_enu_ab, dtype=float)
    e, n = d[..., 0], d[..., 1]
    r2 = e * e + n * n
    return np.stack([n / r2, -e / r2, np.zeros_like(e)], axis=-1)


def sd_pseudorange_m(r_a_ecef_m: ArrayLike, sv_a_ecef_m: ArrayLike, r_b_ecef_m: ArrayLike,
                     sv_b_ecef_m: ArrayLike) -> F64:
    """Between-receiver single-difference geometric range ``rho_a - rho_b``, metres.

    MacGougan (2009) eq. 3.2 without the clock term: ``Delta P = Delta rho + c Delta T``.
    Each receiver uses the satellite position it computed for its own transmit time
    (``sv_a``, ``sv_b``), so the difference is exact even when the epochs differ slightly.
    d/d r_a is ``-range_jacobian(r_a, sv_a)`` (minus the unit line of sight a->satellite).
    """
    return range_m(r_a_ecef_m, sv_a_ecef_m) - range_m(r_b_ecef_m, sv_b_ecef_m)


def range_rate_mps(r_rx_ecef_m: ArrayLike, v_rx_ecef_mps: ArrayLike, sv_ecef_m: ArrayLike,
                   sv_vel_ecef_mps: ArrayLike) -> F64:
    """Geometric range rate receiver->satellite, m/s: ``u . (v_sv - v_rx)``, ``u = (r_sv - r_rx)/rho``.

    A pseudorange rate (``GnssEpoch.doppler_mps``) adds the receiver minus satellite clock drift.
    """
    u = range_jacobian(r_rx_ecef_m, sv_ecef_m)
    dv = np.asarray(sv_vel_ecef_mps, dtype=float) - np.asarray(v_rx_ecef_mps, dtype=float)
    return np.sum(u * dv, axis=-1)


def range_rate_jacobians(r_rx_ecef_m: ArrayLike, v_rx_ecef_mps: ArrayLike, sv_ecef_m: ArrayLike,
                         sv_vel_ecef_mps: ArrayLike) -> tuple[F64, F64]:
    """(d rate / d r_rx, d rate / d v_rx) of :func:`range_rate_mps`.

    d/d v_rx = -u; d/d r_rx = -(I - u u^T)(v_sv - v_rx) / rho (the line of sight turns as
    the receiver moves; about |v_sv|/rho = 2e-4 per second for GPS).
    """
    d = np.asarray(sv_ecef_m, dtype=float) - np.asarray(r_rx_ecef_m, dtype=float)
    rho = np.sqrt(np.sum(d * d, axis=-1, keepdims=True))
    u = d / rho
    dv = np.asarray(sv_vel_ecef_mps, dtype=float) - np.asarray(v_rx_ecef_mps, dtype=float)
    d_r = -(dv - u * np.sum(u * dv, axis=-1, keepdims=True)) / rho
    return d_r, -u
