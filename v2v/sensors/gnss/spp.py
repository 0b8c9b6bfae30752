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
from functools import lru_cache
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray
from scipy import special

from v2v.frames import ecef_to_geodetic_point
from v2v.sensors.gnss.atmosphere import (
    KLOBUCHAR_ALPHA_2021_04_28,
    KLOBUCHAR_BETA_2021_04_28,
    klobuchar_delay_scalar_s,
    tropo_slant_delay_scalar_m,
)
from v2v.sensors.measurements import SPEED_OF_LIGHT_MPS, GnssEpoch
from v2v.smallmat import cond2_symmetric, solve_small

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


_DEFAULT_CONFIG = SppConfig()


# --------------------------------------------------------------------------- compiled solver
# One kernel runs the whole solution (Gauss-Newton, residual test, exclusions, DOPs) for one
# epoch (~20 us): the numpy formulation (one array call per step: geodetic conversion,
# weights, H'WH, its SVD condition number, LAPACK solve) cost ~0.2 ms per epoch, which the
# lead's base position pays at every GNSS epoch. Same iteration, weighting, corrections,
# convergence, singularity and exclusion rules as the module docstring. The numbers equal the
# numpy formulation's to float rounding, not bit for bit (numpy's vectorized atan2/hypot and
# LAPACK round differently in the last bit): statuses, exclusions and iteration counts agree,
# positions within ~2e-8 m, which is the solution's own float resolution (residuals are
# differences of ~2e7 m ranges, 4e-9 m apart, times the DOP).

_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}
_geodetic = njit(**_JIT)(ecef_to_geodetic_point)
_STATUS = (SppStatus.OK, SppStatus.OK_EXCLUDED, SppStatus.RESIDUAL_TEST_FAILED, SppStatus.TOO_FEW_SATELLITES,
           SppStatus.SINGULAR_GEOMETRY, SppStatus.NOT_CONVERGED)  # kernel status codes 0..5
_VALID = (True, True, False, False, False, False)  # SppResult.valid of each kernel status code
_COND_MAX = 1e12  # (H'WH) with a larger 2-norm condition number is "singular geometry"


@njit(**_JIT, inline="always")
def _to_enu(dx, dy, dz, lat, lon):  # pragma: no cover - compiled
    """An ECEF vector in ENU at (lat, lon): ``ecef_to_enu_rotation(lat, lon) @ d``."""
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return -so * dx + co * dy, -sl * co * dx - sl * so * dy + cl * dz, cl * co * dx + cl * so * dy + sl * dz


@njit(**_JIT, inline="always")
def _elevation(sv, i, x, lat, lon):  # pragma: no cover - compiled
    """Elevation and azimuth (rad) of satellite ``i`` seen from ``x`` at geodetic (lat, lon)."""
    e, n, u = _to_enu(sv[i, 0] - x[0], sv[i, 1] - x[1], sv[i, 2] - x[2], lat, lon)
    return np.arctan2(u, np.hypot(e, n)), np.arctan2(e, n)


@njit(**_JIT)
def _weights(sv, x, sigma0_m, elevation_weighting):  # pragma: no cover - compiled
    """``1 / sigma_i^2`` with ``sigma_i = sigma0 / clip(sin E_i, 0.05, 1)`` (0.05 caps low/negative
    elevations at 20x sigma), or ``1 / sigma0^2`` (no weighting, or still far from the Earth)."""
    w = np.full(sv.shape[0], 1.0 / sigma0_m**2)
    if not elevation_weighting or np.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2) < 6.0e6:
        return w
    lat, lon, _ = _geodetic(x[0], x[1], x[2])
    for i in range(sv.shape[0]):
        s = min(max(np.sin(_elevation(sv, i, x, lat, lon)[0]), 0.05), 1.0)
        w[i] = (s / sigma0_m) ** 2
    return w


@njit(**_JIT)
def _corrections(sv, x, t_gps_s, iono, tropo, klob_alpha, klob_beta):  # pragma: no cover - compiled
    """Broadcast ionosphere (Klobuchar) plus Saastamoinen troposphere delays (m) at the estimate
    ``x``, elevations clipped to >= 1e-3 rad; zeros far from the Earth's surface (first iterations)."""
    corr = np.zeros(sv.shape[0])
    if not (iono or tropo) or np.sqrt(x[0] ** 2 + x[1] ** 2 + x[2] ** 2) < 6.0e6:
        return corr
    lat, lon, h = _geodetic(x[0], x[1], x[2])
    for i in range(sv.shape[0]):
        el, az = _elevation(sv, i, x, lat, lon)
        el_c = max(el, 1e-3)
        if iono:
            corr[i] += SPEED_OF_LIGHT_MPS * klobuchar_delay_scalar_s(lat, lon, el_c, az, t_gps_s, klob_alpha, klob_beta)
        if tropo:  # mapping x zenith delay; 15 C / 50 % are saastamoinen_zenith_delay_m's standard atmosphere
            corr[i] += tropo_slant_delay_scalar_m(lat, lon, h, el_c, 15.0, 0.5, 0.0, 0.0, 0.0, lat, lon)
    return corr


@njit(**_JIT)
def _design(sv, x):  # pragma: no cover - compiled
    """Geometric ranges ``rho_i`` and design rows ``H_i = [-(x_sv,i - x)' / rho_i, 1]`` (thesis eq. 3.3)."""
    k = sv.shape[0]
    rho = np.empty(k)
    h = np.empty((k, 4))
    for i in range(k):
        dx, dy, dz = sv[i, 0] - x[0], sv[i, 1] - x[1], sv[i, 2] - x[2]
        rho[i] = np.sqrt(dx * dx + dy * dy + dz * dz)
        h[i, 0], h[i, 1], h[i, 2], h[i, 3] = -dx / rho[i], -dy / rho[i], -dz / rho[i], 1.0
    return rho, h


@njit(**_JIT)
def _normal_matrix(h, w):  # pragma: no cover - compiled
    """``H' W H`` (4, 4), W = diag(w)."""
    n = np.zeros((4, 4))
    for i in range(h.shape[0]):
        for a in range(4):
            wa = w[i] * h[i, a]
            for b in range(4):
                n[a, b] += wa * h[i, b]
    return n


@njit(**_JIT)
def _dops(h_ecef, x):  # pragma: no cover - compiled
    """GDOP, PDOP, HDOP, VDOP, TDOP from ``(H'H)^-1`` with H rotated to local ENU at ``x``."""
    lat, lon, _ = _geodetic(x[0], x[1], x[2])
    h = h_ecef.copy()
    for i in range(h.shape[0]):
        h[i, 0], h[i, 1], h[i, 2] = _to_enu(h_ecef[i, 0], h_ecef[i, 1], h_ecef[i, 2], lat, lon)
    q = solve_small(_normal_matrix(h, np.ones(h.shape[0])), np.eye(4))
    out = np.empty(5)
    out[0] = np.sqrt(q[0, 0] + q[1, 1] + q[2, 2] + q[3, 3])
    out[1] = np.sqrt(q[0, 0] + q[1, 1] + q[2, 2])
    out[2] = np.sqrt(q[0, 0] + q[1, 1])
    out[3] = np.sqrt(q[2, 2])
    out[4] = np.sqrt(q[3, 3])
    return out


@njit(**_JIT)
def _spp_kernel(sv, y_all, finite, x_prior, sigma0_m, elevation_weighting, alpha_thresholds, exclude, max_iter,
                tol_m, t_gps_s, iono, tropo, klob_alpha, klob_beta):  # pragma: no cover - compiled
    """The whole solution of :func:`solve_spp` (module docstring) for one epoch.

    ``alpha_thresholds[dof]``: the chi-square ``1 - alpha`` quantiles (0 at dof 0). Returns
    ``(status code (index of _STATUS), iterations, x (4,), used (n,), residuals (n,), chi2,
    threshold, dops (5,))``; on failure x, residuals, chi2 and dops are not meaningful.
    """
    n = y_all.shape[0]
    used = finite.copy()
    excluded_any = False
    x = np.zeros(4)
    res = np.zeros(n)
    while True:
        idx = np.flatnonzero(used)
        n_used = idx.shape[0]
        if n_used < 4:
            return 3, 0, x, used, res, 0.0, 0.0, np.zeros(5)
        sv_u = sv[idx]
        y_u = y_all[idx]
        x[:3] = x_prior
        x[3] = 0.0
        converged = False
        it = 0
        for it in range(1, max_iter + 1):
            rho, h = _design(sv_u, x)
            v = y_u - _corrections(sv_u, x, t_gps_s, iono, tropo, klob_alpha, klob_beta) - (rho + x[3])
            w = _weights(sv_u, x, sigma0_m, elevation_weighting)
            nmat = _normal_matrix(h, w)
            if cond2_symmetric(nmat) > _COND_MAX:
                return 4, it, x, used, res, 0.0, 0.0, np.zeros(5)
            rhs = np.zeros((4, 1))  # H' W v
            for i in range(n_used):
                for a in range(4):
                    rhs[a, 0] += h[i, a] * (w[i] * v[i])
            dx = solve_small(nmat, rhs)[:, 0]
            x += dx
            if np.sqrt(np.sum(dx * dx)) < tol_m:
                converged = True
                break
        if not converged or not np.all(np.isfinite(x)):
            return 5, it, x, used, res, 0.0, 0.0, np.zeros(5)

        # Final residuals (every finite satellite) and weights at the solution.
        fidx = np.flatnonzero(finite)
        rho_f, _ = _design(sv[fidx], x)
        corr_f = _corrections(sv[fidx], x, t_gps_s, iono, tropo, klob_alpha, klob_beta)
        res[:] = 0.0
        res[fidx] = y_all[fidx] - corr_f - (rho_f + x[3])
        _, h = _design(sv_u, x)
        w = _weights(sv_u, x, sigma0_m, elevation_weighting)
        res_u = res[idx]
        chi2 = np.sum(w * res_u**2)
        dof = n_used - 4
        thr = alpha_thresholds[dof]
        if dof > 0 and chi2 > thr:
            if exclude and n_used - 1 >= 5:
                # w-test (Baarda): |r_i| / sqrt(sigma_i^2 - (H (H'WH)^-1 H')_ii)
                n_inv = solve_small(_normal_matrix(h, w), np.eye(4))
                std_res = np.empty(n_used)
                for i in range(n_used):
                    q_v = 1.0 / w[i]
                    for a in range(4):
                        for b in range(4):
                            q_v -= h[i, a] * n_inv[a, b] * h[i, b]
                    std_res[i] = abs(res_u[i]) / np.sqrt(max(q_v, 1e-12))
                used[idx[np.argmax(std_res)]] = False
                excluded_any = True
                continue
            status = 2
        else:
            status = 1 if excluded_any else 0
        return status, it, x, used, res, chi2, thr, _dops(h, x)


@lru_cache(maxsize=64)
def _chi2_thresholds(alpha: float, n: int) -> F64:
    """``2 * gammaincinv(dof / 2, 1 - alpha)`` (the chi-square quantile) for dof = 0..n, 0 at dof 0."""
    thr = np.zeros(n + 1)
    for dof in range(1, n + 1):
        thr[dof] = float(2.0 * special.gammaincinv(dof / 2.0, 1.0 - alpha))
    thr.setflags(write=False)
    return thr


def _kernel_rows(sv_pos_ecef_m: ArrayLike, pseudorange_m: ArrayLike,
                 sv_clock_m: ArrayLike) -> tuple[F64, F64, NDArray[np.bool_]]:
    """The kernels' rows: satellite positions ``(n, 3)``, pseudoranges with the broadcast
    satellite clock applied ``(n,)``, and which rows are finite."""
    sv = np.ascontiguousarray(sv_pos_ecef_m, dtype=float).reshape(-1, 3)
    y_all = np.asarray(pseudorange_m, dtype=float).reshape(-1) + np.asarray(sv_clock_m, dtype=float).reshape(-1)
    return sv, y_all, np.all(np.isfinite(sv), axis=1) & np.isfinite(y_all)


def _kernel_config(cfg: SppConfig, n_max: int, t_gps: float | F64) -> tuple:
    """The arguments of :func:`_spp_kernel` (and :func:`_spp_chain_kernel`) after the a priori
    position, for epochs of at most ``n_max`` satellites at GPS time(s) ``t_gps``."""
    return (float(cfg.sigma0_m), bool(cfg.elevation_weighting), _chi2_thresholds(cfg.alpha, n_max), bool(cfg.exclude),
            int(cfg.max_iter), float(cfg.tol_m), t_gps, bool(cfg.correct_iono), bool(cfg.correct_tropo),
            np.asarray(cfg.klobuchar_alpha, dtype=float), np.asarray(cfg.klobuchar_beta, dtype=float))


def _solve(sv_pos_ecef_m: ArrayLike, pseudorange_m: ArrayLike, sv_clock_m: ArrayLike, cfg: SppConfig,
           x0_ecef_m: ArrayLike | None, t_gps_s: float) -> tuple[int, F64, NDArray[np.bool_], tuple]:
    """``(n, a priori position, finite rows, _spp_kernel's outputs)`` of :func:`solve_spp`'s inputs."""
    sv, y_all, finite = _kernel_rows(sv_pos_ecef_m, pseudorange_m, sv_clock_m)
    n = y_all.shape[0]
    x_prior = np.zeros(3) if x0_ecef_m is None else np.asarray(x0_ecef_m, dtype=float).reshape(3)
    out = _spp_kernel(sv, y_all, finite, x_prior, *_kernel_config(cfg, n, float(t_gps_s)))
    return n, x_prior, finite, out


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
    cfg = config or _DEFAULT_CONFIG
    n, x_prior, finite, (code, it, x, used, res, chi2, thr, dops) = _solve(
        sv_pos_ecef_m, pseudorange_m, sv_clock_m, cfg, x0_ecef_m, t_gps_s)
    status = _STATUS[code]
    n_used = int(used.sum())
    if code >= 3:
        reason = {
            SppStatus.TOO_FEW_SATELLITES: f"{n_used} usable satellites, need >= 4",
            SppStatus.SINGULAR_GEOMETRY: "satellite geometry is singular",
            SppStatus.NOT_CONVERGED: f"no convergence in {cfg.max_iter} iterations",
        }[status]
        return SppResult(
            valid=False, status=status, reason=reason, position_ecef_m=x_prior.copy(), clock_bias_m=0.0,
            n_used=n_used, iterations=int(it), gdop=0.0, pdop=0.0, hdop=0.0, vdop=0.0, tdop=0.0,
            residuals_m=np.zeros(n), used=np.zeros(n, dtype=bool), chi2=0.0, chi2_threshold=0.0,
        )
    if status is SppStatus.RESIDUAL_TEST_FAILED:
        reason = f"chi2 {chi2:.1f} > {thr:.1f} ({n_used - 4} dof)"
    elif status is SppStatus.OK_EXCLUDED:
        reason = f"{int((~used & finite).sum())} excluded"
    else:
        reason = ""
    return SppResult(
        valid=_VALID[code], status=status, reason=reason,
        position_ecef_m=x[:3].copy(), clock_bias_m=float(x[3]), n_used=n_used, iterations=int(it),
        gdop=float(dops[0]), pdop=float(dops[1]), hdop=float(dops[2]), vdop=float(dops[3]), tdop=float(dops[4]),
        residuals_m=res, used=used, chi2=float(chi2), chi2_threshold=float(thr),
    )


def spp_from_epoch(epoch: GnssEpoch, *, config: SppConfig | None = None, x0_ecef_m: ArrayLike | None = None,
                   gps_start_s: float = 0.0) -> SppResult:
    """:func:`solve_spp` on a :class:`GnssEpoch` (uses only measured and broadcast fields)."""
    return solve_spp(epoch.sv_pos_ecef_m, epoch.pseudorange_m, epoch.sv_clock_m, config=config,
                     x0_ecef_m=x0_ecef_m, t_gps_s=gps_start_s + epoch.t_s)


def spp_position(epoch: GnssEpoch, *, config: SppConfig | None = None, x0_ecef_m: ArrayLike | None = None,
                 gps_start_s: float = 0.0) -> F64 | None:
    """``spp_from_epoch(...).position_ecef_m`` when that solution is valid, else None: the same
    kernel call without the result record (DOPs, reason, residuals), for a caller that needs
    only the position (the lead's base of every GNSS epoch, paper eq. 7)."""
    cfg = config or _DEFAULT_CONFIG
    _, _, _, (code, _, x, *_) = _solve(epoch.sv_pos_ecef_m, epoch.pseudorange_m, epoch.sv_clock_m, cfg, x0_ecef_m,
                                      gps_start_s + epoch.t_s)
    return x[:3].copy() if _VALID[code] else None


@njit(**_JIT)
def _spp_chain_kernel(sv_cat, y_cat, finite_cat, row0, x_prior, sigma0_m, elevation_weighting, alpha_thresholds,
                      exclude, max_iter, tol_m, t_gps, iono, tropo, klob_alpha,
                      klob_beta):  # pragma: no cover - compiled
    """:func:`_spp_kernel` of epochs ``k`` (rows ``row0[k]:row0[k+1]`` of the concatenated
    inputs, GPS time ``t_gps[k]``) one after another, each from the last valid position before
    it (``x_prior`` for the first). Returns ``(positions (K, 3), valid (K,))``; an invalid
    epoch's row is left NaN."""
    k_n = row0.shape[0] - 1
    pos = np.full((k_n, 3), np.nan)
    ok = np.zeros(k_n, dtype=np.bool_)
    xp = x_prior.copy()
    for k in range(k_n):
        a, b = row0[k], row0[k + 1]
        code, _, x, _, _, _, _, _ = _spp_kernel(
            np.ascontiguousarray(sv_cat[a:b]), y_cat[a:b].copy(), finite_cat[a:b].copy(), xp, sigma0_m,
            elevation_weighting, alpha_thresholds, exclude, max_iter, tol_m, t_gps[k], iono, tropo, klob_alpha,
            klob_beta)
        if code <= 1:  # (_VALID)
            xp = x[:3].copy()
            pos[k] = xp
            ok[k] = True
    return pos, ok


class SppChain:
    """The standalone positions of one receiver's successive epochs, each solved from the
    last valid one (:func:`spp_position` with ``x0_ecef_m`` the previous valid position):
    the lead's base of every GNSS epoch (paper eq. 7).

    ``chain(epoch)`` returns the epoch's position if valid, else the last valid one (None
    before any); :meth:`many` does the same for a list of epochs in one compiled call, with
    the same results as calling the chain on each in turn (the same kernel, the same priors).
    """

    def __init__(self, *, gps_start_s: float = 0.0, config: SppConfig | None = None,
                 x0_ecef_m: ArrayLike | None = None) -> None:
        self.config = config or _DEFAULT_CONFIG
        self.gps_start_s = gps_start_s
        self.x: F64 | None = None if x0_ecef_m is None else np.asarray(x0_ecef_m, dtype=float).reshape(3).copy()

    def __call__(self, epoch: GnssEpoch) -> F64 | None:
        x = spp_position(epoch, config=self.config, x0_ecef_m=self.x, gps_start_s=self.gps_start_s)
        if x is not None:
            self.x = x
        return self.x

    def many(self, epochs: list[GnssEpoch]) -> list[F64 | None]:
        """``[self(ep) for ep in epochs]`` in one kernel call (a returned position is an
        array of its own; an invalid epoch's entry is the last valid position before it)."""
        if len(epochs) < 2:
            return [self(ep) for ep in epochs]
        counts = [len(ep.pseudorange_m) for ep in epochs]
        row0 = np.zeros(len(epochs) + 1, dtype=np.int64)
        np.cumsum(counts, out=row0[1:])
        sv, y, finite = _kernel_rows(  # (elementwise: each epoch's rows as _solve forms them)
            np.concatenate([np.asarray(ep.sv_pos_ecef_m, dtype=float).reshape(-1, 3) for ep in epochs]),
            np.concatenate([np.asarray(ep.pseudorange_m, dtype=float).reshape(-1) for ep in epochs]),
            np.concatenate([np.asarray(ep.sv_clock_m, dtype=float).reshape(-1) for ep in epochs]))
        t_gps = np.array([self.gps_start_s + ep.t_s for ep in epochs], dtype=float)
        x_prior = np.zeros(3) if self.x is None else self.x
        pos, ok = _spp_chain_kernel(sv, y, finite, row0, x_prior, *_kernel_config(self.config, max(counts), t_gps))
        out: list[F64 | None] = []
        for k, valid in enumerate(ok.tolist()):
            if valid:
                self.x = pos[k].copy()
            out.append(self.x)
        return out
