"""Standalone (single-point) GPS position: weighted Gauss-Newton least squares with FDE.

Used for the lead vehicle's base position: the paper's eq. 7 (Tang 1996) shows that a
base error ``|dr_base|`` perturbs a baseline ``|dr|`` by only ``~1e-9 |dr_base| / |dr|``-
class amounts, so a metre-level standalone fix is ample.

Model (MacGougan 2009 eq. 3.1, with the broadcast satellite clock applied)::

    P_i + sv_clock_m_i - I_i - T_i = |x_sv,i - x| + b + v_i,   v_i ~ N(0, sigma_i^2)

unknowns ``x`` (ECEF, m) and ``b = c dT`` (m); ``I``/``T`` are the optional broadcast
ionosphere (Klobuchar) and Saastamoinen troposphere corrections evaluated at the current
estimate. Gauss-Newton: ``dx = (H' W H)^-1 H' W (y - h(x))`` with rows
``H_i = [-(x_sv,i - x)' / rho_i, 1]`` (thesis eq. 3.3), iterated until ``|dx| < tol``.
Weights ``sigma_i = sigma0 / sin(E_i)`` (elevation weighting) or ``sigma0``.

Residual test (global test, Teunissen; Kaplan & Hegarty 2006 §7.5 RAIM): with ``n > 4``
satellites the weighted sum of squared residuals ``r' W r`` is chi-square with ``n - 4``
degrees of freedom; if it exceeds the ``1 - alpha`` quantile and ``n - 1 >= 5`` (so the
reduced set can still be tested), the satellite with the largest standardized residual
``|r_i| / sqrt(sigma_i^2 - (H (H'WH)^-1 H')_ii)`` (w-test, Baarda) is excluded and the
solution recomputed.

Outcomes never contain NaN: when no solution exists (< 4 satellites, singular geometry,
no convergence) ``status`` says why, ``valid`` is False and ``position_ecef_m`` is the a
priori position (or zeros).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import special

from v2v.frames import ecef_to_enu_rotation, ecef_to_geodetic
from v2v.sensors.gnss.atmosphere import (
    KLOBUCHAR_ALPHA_2021_04_28,
    KLOBUCHAR_BETA_2021_04_28,
    klobuchar_delay_s,
    saastamoinen_zenith_delay_m,
    tropo_mapping,
)
from v2v.sensors.measurements import SPEED_OF_LIGHT_MPS, GnssEpoch

F64 = NDArray[np.float64]


class SppStatus(StrEnum):
    OK = "ok"
    OK_EXCLUDED = "ok_excluded"  # passed the test after excluding satellites
    RESIDUAL_TEST_FAILED = "residual_test_failed"  # failed, nothing left to exclude (solution returned)
    TOO_FEW_SATELLITES = "too_few_satellites"
    SINGULAR_GEOMETRY = "singular_geometry"
    NOT_CONVERGED = "not_converged"


@dataclass(frozen=True, kw_only=True)
class SppConfig:
    """Standalone solution settings.

    Parameters
    ----------
    sigma0_m : float
        Zenith pseudorange 1-sigma (paper Table 1 assumes 5 m undifferenced).
    elevation_weighting : bool
        ``sigma_i = sigma0 / sin(E_i)`` if True, else ``sigma0``.
    alpha : float
        False-alarm probability of the chi-square residual test.
    exclude : bool
        Exclude the worst satellite when the test fails (needs >= 6 satellites).
    max_iter, tol_m : Gauss-Newton limits.
    correct_iono, correct_tropo : apply Klobuchar / Saastamoinen corrections.
    klobuchar_alpha, klobuchar_beta : broadcast ionosphere coefficients.
    """

    sigma0_m: float = 5.0
    elevation_weighting: bool = True
    alpha: float = 1e-3
    exclude: bool = True
    max_iter: int = 15
    tol_m: float = 1e-4
    correct_iono: bool = False
    correct_tropo: bool = False
    klobuchar_alpha: tuple[float, float, float, float] = KLOBUCHAR_ALPHA_2021_04_28
    klobuchar_beta: tuple[float, float, float, float] = KLOBUCHAR_BETA_2021_04_28


@dataclass(frozen=True, kw_only=True)
class SppResult:
    """Standalone solution.

    ``residuals_m`` (n,) are ``y - h(x)`` for every input satellite (excluded ones too),
    ``used`` (n,) marks the satellites in the final solution. DOPs are from the unweighted
    geometry of the used satellites in the local ENU frame (zeros when invalid).
    """

    valid: bool
    status: SppStatus
    reason: str
    position_ecef_m: F64
    clock_bias_m: float
    n_used: int
    iterations: int
    gdop: float
    pdop: float
    hdop: float
    vdop: float
    tdop: float
    residuals_m: F64
    used: NDArray[np.bool_]
    chi2: float
    chi2_threshold: float


def _elevation(sv: F64, x: F64) -> F64:
    lat, lon, _ = ecef_to_geodetic(x)
    enu = (sv - x) @ ecef_to_enu_rotation(float(lat), float(lon)).T
    return np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))


def _corrections(sv: F64, x: F64, t_gps_s: float, cfg: SppConfig) -> F64:
    corr = np.zeros(sv.shape[0])
    if not (cfg.correct_iono or cfg.correct_tropo) or np.linalg.norm(x) < 6.0e6:
        return corr  # far from the Earth's surface (first iterations): no atmosphere yet
    lat, lon, h = ecef_to_geodetic(x)
    enu = (sv - x) @ ecef_to_enu_rotation(float(lat), float(lon)).T
    el = np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))
    az = np.arctan2(enu[:, 0], enu[:, 1])
    el_c = np.clip(el, 1e-3, None)
    if cfg.correct_iono:
        corr += SPEED_OF_LIGHT_MPS * klobuchar_delay_s(lat, lon, el_c, az, t_gps_s, cfg.klobuchar_alpha,
                                                       cfg.klobuchar_beta)
    if cfg.correct_tropo:
        corr += tropo_mapping(el_c) * saastamoinen_zenith_delay_m(lat, h)
    return corr


def solve_spp(
    sv_pos_ecef_m: ArrayLike,
    pseudorange_m: ArrayLike,
    sv_clock_m: ArrayLike,
    *,
    config: SppConfig | None = None,
    x0_ecef_m: ArrayLike | None = None,
    t_gps_s: float = 0.0,
) -> SppResult:
    """Least-squares position and clock from ``n`` pseudoranges (see module docstring).

    Parameters
    ----------
    sv_pos_ecef_m : (n, 3) broadcast satellite positions at transmit time, reception ECEF frame.
    pseudorange_m : (n,) measured pseudoranges.
    sv_clock_m : (n,) broadcast satellite clock corrections (added to the pseudorange).
    config : SppConfig
    x0_ecef_m : (3,) a priori position (default: Earth's centre, which converges for GPS).
    t_gps_s : GPS seconds (only for the Klobuchar correction).
    """
    cfg = config or SppConfig()
    sv = np.asarray(sv_pos_ecef_m, dtype=float).reshape(-1, 3)
    y_all = np.asarray(pseudorange_m, dtype=float).reshape(-1) + np.asarray(sv_clock_m, dtype=float).reshape(-1)
    n = y_all.shape[0]
    x_prior = np.zeros(3) if x0_ecef_m is None else np.asarray(x0_ecef_m, dtype=float).reshape(3)
    finite = np.all(np.isfinite(sv), axis=1) & np.isfinite(y_all)
    used = finite.copy()

    def fail(status: SppStatus, reason: str, it: int = 0) -> SppResult:
        return SppResult(
            valid=False, status=status, reason=reason, position_ecef_m=x_prior.copy(), clock_bias_m=0.0,
            n_used=int(used.sum()), iterations=it, gdop=0.0, pdop=0.0, hdop=0.0, vdop=0.0, tdop=0.0,
            residuals_m=np.zeros(n), used=np.zeros(n, dtype=bool), chi2=0.0, chi2_threshold=0.0,
        )

    excluded_any = False
    while True:
        if used.sum() < 4:
            return fail(SppStatus.TOO_FEW_SATELLITES, f"{int(used.sum())} usable satellites, need >= 4")
        x = np.append(x_prior, 0.0)
        converged = False
        it = 0
        for it in range(1, cfg.max_iter + 1):
            d = sv[used] - x[:3]
            rho = np.linalg.norm(d, axis=1)
            h_mat = np.column_stack([-d / rho[:, None], np.ones(rho.size)])
            corr = _corrections(sv[used], x[:3], t_gps_s, cfg)
            v = y_all[used] - corr - (rho + x[3])
            w = _weights(sv[used], x[:3], cfg)
            nmat = h_mat.T @ (w[:, None] * h_mat)
            if np.linalg.cond(nmat) > 1e12:
                return fail(SppStatus.SINGULAR_GEOMETRY, "satellite geometry is singular", it)
            dx = np.linalg.solve(nmat, h_mat.T @ (w * v))
            x = x + dx
            if np.linalg.norm(dx) < cfg.tol_m:
                converged = True
                break
        if not converged or not np.all(np.isfinite(x)):
            return fail(SppStatus.NOT_CONVERGED, f"no convergence in {cfg.max_iter} iterations", it)

        # Final residuals and covariance at the solution.
        d_all = sv - x[:3]
        rho_all = np.linalg.norm(d_all, axis=1)
        corr_all = _corrections(sv, x[:3], t_gps_s, cfg)
        res = np.where(finite, y_all - corr_all - (rho_all + x[3]), 0.0)
        h_mat = np.column_stack([-d_all[used] / rho_all[used, None], np.ones(int(used.sum()))])
        w = _weights(sv[used], x[:3], cfg)
        nmat = h_mat.T @ (w[:, None] * h_mat)
        n_used = int(used.sum())
        dof = n_used - 4
        chi2 = float(np.sum(w * res[used] ** 2))
        thr = float(2.0 * special.gammaincinv(dof / 2.0, 1.0 - cfg.alpha)) if dof > 0 else 0.0  # chi2.ppf
        if dof > 0 and chi2 > thr:
            if cfg.exclude and n_used - 1 >= 5:
                q_v = 1.0 / w - np.einsum("ij,jk,ik->i", h_mat, np.linalg.inv(nmat), h_mat)
                std_res = np.abs(res[used]) / np.sqrt(np.maximum(q_v, 1e-12))
                worst = np.flatnonzero(used)[int(np.argmax(std_res))]
                used[worst] = False
                excluded_any = True
                continue
            status, reason = SppStatus.RESIDUAL_TEST_FAILED, f"chi2 {chi2:.1f} > {thr:.1f} ({dof} dof)"
            valid = False
        else:
            status = SppStatus.OK_EXCLUDED if excluded_any else SppStatus.OK
            reason = f"{int((~used & finite).sum())} excluded" if excluded_any else ""
            valid = True
        dops = _dops(h_mat, x[:3])
        return SppResult(
            valid=valid, status=status, reason=reason, position_ecef_m=x[:3].copy(), clock_bias_m=float(x[3]),
            n_used=n_used, iterations=it, gdop=dops[0], pdop=dops[1], hdop=dops[2], vdop=dops[3], tdop=dops[4],
            residuals_m=res, used=used.copy(), chi2=chi2, chi2_threshold=thr,
        )


def _weights(sv: F64, x: F64, cfg: SppConfig) -> F64:
    if not cfg.elevation_weighting or np.linalg.norm(x) < 6.0e6:
        return np.full(sv.shape[0], 1.0 / cfg.sigma0_m**2)
    s = np.clip(np.sin(_elevation(sv, x)), 0.05, 1.0)  # 0.05 caps low/negative elevations at 20x sigma
    return (s / cfg.sigma0_m) ** 2


def _dops(h_ecef: F64, x: F64) -> tuple[float, float, float, float, float]:
    """GDOP, PDOP, HDOP, VDOP, TDOP from ``(H'H)^-1`` with H rotated to local ENU."""
    lat, lon, _ = ecef_to_geodetic(x)
    rot = ecef_to_enu_rotation(float(lat), float(lon))
    h = h_ecef.copy()
    h[:, :3] = h[:, :3] @ rot.T
    q = np.linalg.inv(h.T @ h)
    dg = np.diag(q)
    return (
        float(np.sqrt(np.trace(q))),
        float(np.sqrt(dg[:3].sum())),
        float(np.sqrt(dg[:2].sum())),
        float(np.sqrt(dg[2])),
        float(np.sqrt(dg[3])),
    )


def spp_from_epoch(epoch: GnssEpoch, *, config: SppConfig | None = None, x0_ecef_m: ArrayLike | None = None,
                   gps_start_s: float = 0.0) -> SppResult:
    """:func:`solve_spp` on a :class:`GnssEpoch` (uses only measured and broadcast fields)."""
    return solve_spp(epoch.sv_pos_ecef_m, epoch.pseudorange_m, epoch.sv_clock_m, config=config,
                     x0_ecef_m=x0_ecef_m, t_gps_s=gps_start_s + epoch.t_s)
