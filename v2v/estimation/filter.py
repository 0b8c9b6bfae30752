"""Lead-vehicle-relative cluster EKF (production engine).

Sequential discrete-time EKF of MacGougan (2009) table 3.1 on the state of
:mod:`v2v.estimation.layout` (Petovello et al. section 3): one scalar update per
measurement, each innovation tested before use (thesis eq. 3.23-3.27)::

    S = h P h^T + sigma^2                  (3.23)
    t = nu / sqrt(S) ~ N(0, 1) under H0    (3.26-3.27)
    reject if |t| > k,  k = Phi^-1(1 - alpha/2)   (alpha = 0.001 -> k = 3.29)

    k_i = P h^T / S,  x += k_i nu,  P -= k_i k_i^T S   (3.16-3.18, symmetric rank-1 form)

Update order per epoch (thesis section 3.5.1, "the order of the sequential updates"):
SD pseudoranges per vehicle from the highest to the lowest elevation, then SD
pseudoranges between two non-lead vehicles (satellites the lead does not see), then SD
Dopplers, then UWB ranges, then bearings (each type through its own method; call them
in that order, or use :meth:`ClusterFilterBase.update_epoch`).

First-update clock problem (thesis eq. 3.28-3.29): the SD clock is re-estimated every
epoch (drift GM sigma = 1000 m/s), so the first pseudorange of a vehicle has
``S ~ P_clk`` and its test has almost no power. Following the thesis, a parallel
per-vehicle least-squares solution (position + clock, linearized at the prediction)
screens that epoch's pseudoranges with Baarda's w-test; the first pseudorange used is
the highest-elevation one *not* flagged, so a blunder-free measurement observes the
clock and the rest are tested with a meaningful S. Flagged ones still go through the
normal innovation test later in the sequence. With fewer than 4 + 2 satellites the
screening cannot identify a blunder (the thesis notes it fails below 4) and plain
elevation order is used. Dopplers get the same treatment for the drift.

Initialization: a vehicle block starts uninitialized (mean 0, large variance) and is
not used by UWB or bearing updates. At the first epoch with >= ``init_min_satellites``
SD pseudoranges it is set by Gauss-Newton least squares (w-test screened) on those
pseudoranges: position + clock with covariance ``sigma_sd^2 (H^T H)^-1``; velocity +
drift from the SD Dopplers the same way when >= 4 are available, else zero with the
process model's steady-state GM variances. An estimated azimuth is initialized at its
first bearing: ``alpha = atan2(dE, dN) - beta`` with a diffuse variance, then that
bearing is applied normally (zero innovation; equivalent to the update from a flat prior).

Nonlinear measurements (UWB ranges, bearings over ~30 m): the neglected second-order
term of ``f(d)``, ``d = p_b - p_a`` with covariance ``P_d``, has mean ``tr(H2 P_d)/2`` and
variance ``tr((H2 P_d)^2)/2`` (H2 = Hessian; Gelb 1974, second-order filter). A range or
bearing is deferred (counted) while that variance exceeds ``nonlinear_fraction`` of its
measurement variance, e.g. just after a metre-level GNSS initialization; when used, the
mean is added to h(x) and the variance to R. Without this the EKF was measurably
overconfident in Monte Carlo (average NEES 43 instead of 16 in the first seconds).

Fault handling (issue 8):

* Multiple blunders: when the epoch's w-test screen (above) flags more than one
  pseudorange (or Doppler) of a vehicle, all flagged ones are excluded (reported as
  rejected, counted ``excluded_screened``) instead of going through the sequential test,
  where an earlier accepted blunder would bias the S of the later ones.
  ``integrity_available[v]`` is False for an epoch whose screen could not isolate faults:
  fewer than 4 + 2 measurements, or the screen stopped at redundancy < 2 or at singular
  geometry while a |w| > k remained.
* Receiver clock jump: a step ``d`` of one receiver's clock (e.g. 1 ms = 299 792.458 m)
  shifts every SD pseudorange of that vehicle by the same ``d``. Before the sequential
  updates, the innovations ``nu_i`` (with variances ``S_i``) of the vehicle are checked
  for a common mode: more than half fail the gate, all of those with the same sign, and
  after removing ``m = median(nu)`` a majority pass ``|nu_i - m| <= k sqrt(S_i)``. Then
  only the clock state is re-initialized, ``clk += m`` with variance
  ``clock_reset_sigma_m^2`` and zero correlations (the baseline is untouched), counted
  ``clock_jump_detected``; the epoch's pseudoranges are then used normally.
* Divergence: the last ``divergence_window`` SD-pseudorange tests of each vehicle are
  kept; when more than ``divergence_reject_fraction`` of a full window was rejected
  (under H0 the rejections are Binomial(N, alpha): P(> N/2 of 50 at alpha = 0.001) ~
  1e-60), or the position standard deviation exceeds ``divergence_position_sigma_m``, the
  vehicle's block is reset to the uninitialized prior (counted ``divergence_reset``) and
  re-initialized by the snapshot least squares of its next GNSS epoch. The window's
  mean NIS is available as :meth:`ClusterFilterBase.window_mean_nis` for diagnostics.

Noise model: every SD measurement is treated as independent with variance 2 sigma^2
(paper Table 1: undifferenced pseudorange sigma = 5 m). Two SDs of one satellite share
the lead's error, so they are in truth correlated (covariance sigma^2); the paper's
filter, and this one, ignore that.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections import deque
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2, norm

from v2v.errors import UserError
from v2v.estimation import models
from v2v.estimation.layout import AZIMUTH, AZIMUTH_RATE, UWB, VEHICLE, StateLayout, uwb_pair_key
from v2v.estimation.models import GnssGeometry, Row
from v2v.estimation.process import (
    ProcessNoiseConfig,
    azimuth_block,
    azimuth_pairs,
    random_walk_indices,
    random_walk_variances,
    vehicle_block,
)
from v2v.frames import wrap_angle
from v2v.measmodels import bearing_rad
from v2v.sensors.measurements import Bearings, GnssEpoch, UwbRanges

F64 = NDArray[np.float64]

KIND_SD_PR = "sd_pseudorange"
KIND_SD_PR_PAIR = "sd_pseudorange_pair"
KIND_SD_DOPPLER = "sd_doppler"
KIND_UWB = "uwb"
KIND_BEARING = "bearing"
KIND_CONSTRAINT = "uwb_constraint"
KIND_HEIGHT = "height_aiding"


@dataclass(frozen=True, kw_only=True)
class MeasurementNoiseConfig:
    """Filter measurement standard deviations (paper Table 1 defaults).

    ``doppler_sigma_mps``: undifferenced pseudorange-rate sigma. The paper gives none;
    0.1 m/s is a conservative L1 value for a car receiver at 10-20 Hz (carrier-loop
    Doppler noise is a few cm/s, vehicle vibration and multipath add more).
    """

    pseudorange_sigma_m: float = 5.0
    doppler_sigma_mps: float = 0.1
    uwb_sigma_m: float = 0.5
    bearing_sigma_rad: float = float(np.radians(0.5))

    def __post_init__(self) -> None:
        for name in ("pseudorange_sigma_m", "doppler_sigma_mps", "uwb_sigma_m", "bearing_sigma_rad"):
            if not getattr(self, name) > 0.0:
                raise UserError(f"must be > 0, got {getattr(self, name)!r}", field=f"noise.{name}")

    @property
    def sd_pseudorange_var_m2(self) -> float:
        """Variance of a between-receiver SD pseudorange: 2 sigma^2."""
        return 2.0 * self.pseudorange_sigma_m**2

    @property
    def sd_doppler_var_m2ps2(self) -> float:
        return 2.0 * self.doppler_sigma_mps**2


@dataclass(frozen=True, kw_only=True)
class FilterConfig:
    """Cluster EKF settings.

    Parameters
    ----------
    significance : two-sided significance alpha of the innovation test (thesis eq. 3.26).
    use_doppler, use_pair_sd : process SD Dopplers / SDs between two non-lead vehicles.
    use_uwb_bias_scale : use the pair's bias/scale states when the layout has them.
    uwb_bias_bounds_m, uwb_scale_bounds : (min, max) inequality constraints applied as
        pseudo-measurements after each UWB update (thesis eq. 3.19-3.22); None = off.
    uwb_bias_sigma0_m, uwb_scale_sigma0 : prior std of the UWB bias / scale states.
    init_min_satellites : SD pseudoranges needed to initialize a vehicle.
    azimuth_sigma0_rad : diffuse prior std of an estimated azimuth at its first bearing.
    uninitialized_variance : variance of a block before it is initialized.
    nonlinear_fraction : a UWB range or bearing is deferred while its neglected
        second-order variance exceeds this fraction of its measurement variance.
    height_aiding_sigma_m : when set, epochs without GNSS add a pseudo-measurement
        "relative up = 0 +- sigma" per vehicle (cars on one locally flat road). UWB and
        bearings carry no vertical information, so without it the relative height random-
        walks (1 m/s GM: ~11 m after 30 s) and the range becomes too nonlinear to use.
    """

    process: ProcessNoiseConfig = field(default_factory=ProcessNoiseConfig)
    noise: MeasurementNoiseConfig = field(default_factory=MeasurementNoiseConfig)
    significance: float = 0.001
    use_doppler: bool = True
    use_pair_sd: bool = True
    use_uwb_bias_scale: bool = True
    uwb_bias_bounds_m: tuple[float, float] | None = None
    uwb_scale_bounds: tuple[float, float] | None = None
    uwb_bias_sigma0_m: float = 1.0
    uwb_scale_sigma0: float = 0.01
    init_min_satellites: int = 4
    azimuth_sigma0_rad: float = 1.0
    uninitialized_variance: float = 1e8
    nonlinear_fraction: float = 0.1
    height_aiding_sigma_m: float | None = None
    clock_jump_detection: bool = True
    clock_reset_sigma_m: float = 100.0
    divergence_window: int = 50
    divergence_reject_fraction: float = 0.5
    divergence_position_sigma_m: float = 1000.0

    def __post_init__(self) -> None:
        if not 0.0 < self.significance < 1.0:
            raise UserError(f"must be in (0, 1), got {self.significance!r}", field="filter.significance",
                            fix="e.g. 0.001 for a 3.29-sigma innovation test")
        if self.init_min_satellites < 4:
            raise UserError("needs >= 4 satellites (3 position + clock)", field="filter.init_min_satellites")
        for name in ("uwb_bias_bounds_m", "uwb_scale_bounds"):
            b = getattr(self, name)
            if b is not None and not b[0] < b[1]:
                raise UserError(f"needs min < max, got {b!r}", field=f"filter.{name}")
        if self.divergence_window < 1 or not 0.0 < self.divergence_reject_fraction <= 1.0:
            raise UserError("needs window >= 1 and 0 < reject fraction <= 1", field="filter.divergence_window")

    @property
    def gate_k(self) -> float:
        """Two-sided normal critical value: alpha = 0.001 -> 3.2905."""
        return float(norm.isf(self.significance / 2.0))


@dataclass(frozen=True, slots=True)
class UpdateInfo:
    """What one scalar update did. ``nis = innovation^2 / variance``."""

    kind: str
    vehicles: tuple[str, ...]
    innovation: float
    variance: float
    nis: float
    accepted: bool
    prn: int = -1


def scalar_update(x: F64, P: F64, idx: NDArray[np.int64], val: F64, innovation: float, r_var: float,
                  gate_k: float | None = None) -> tuple[float, bool]:
    """In-place sequential scalar EKF update with a sparse design row; returns (S, accepted).

    ``p = P h^T`` uses only the columns ``idx`` (O(n k)); ``S = h p + r`` (thesis eq. 3.23);
    rejected without touching x, P if ``|nu| > gate_k sqrt(S)`` (eq. 3.27) or anything is
    non-finite; else ``x += p nu / S``, ``P -= q q^T`` with ``q = p / sqrt(S)`` (= ``k k^T S``
    with ``k = p / S``: eq. 3.16-3.18 in a form that keeps P exactly symmetric). The O(n^2)
    rank-1 step runs in place through BLAS ``dger`` (one pass over P, no temporaries) when
    :func:`_symmetric_blas_rank1` found it exactly symmetric, else through numpy.
    """
    p = P[:, idx] @ val
    s = float(val @ p[idx]) + r_var
    innovation = float(innovation)
    if not (math.isfinite(innovation) and math.isfinite(s) and s > 0.0 and np.isfinite(p).all()):
        return s, False
    if gate_k is not None and abs(innovation) > gate_k * math.sqrt(s):
        return s, False
    x += p * (innovation / s)
    # P -= q q^T with q = p / sqrt(S): q_i q_j == q_j q_i exactly, so P stays symmetric
    q = p * math.sqrt(1.0 / s)
    if _DGER is not None and P.dtype == np.float64 and P.flags.c_contiguous and P.flags.writeable:
        out = _DGER(1.0, -q, q, a=P.T, overwrite_a=1)  # BLAS rank-1, in place: one pass over P
        if not np.may_share_memory(out, P):  # pragma: no cover - f2py made a copy
            P[...] = out.T
    else:
        P -= np.multiply.outer(q, q)
    return s, True


def _symmetric_blas_rank1():
    """scipy's BLAS ``dger`` when it keeps a symmetric matrix exactly symmetric under
    ``A -= q q^T`` (checked once on odd sizes that exercise the kernels' tails), else None."""
    try:
        from scipy.linalg.blas import dger
    except ImportError:  # pragma: no cover
        return None
    rng = np.random.default_rng(12345)
    for n in (1, 3, 7, 13, 37, 77, 157, 401):
        a = rng.normal(size=(n, n))
        a = a + a.T
        for _ in range(3):
            q = rng.normal(size=n) * 10.0 ** rng.uniform(-3.0, 3.0)
            out = dger(1.0, -q, q, a=a.T, overwrite_a=1)
            if not np.may_share_memory(out, a) or not np.array_equal(a, a.T):
                return None
    return dger


_DGER = _symmetric_blas_rank1()


def screen_blunders(h: F64, r: F64, sigma: float, k: float) -> NDArray[np.bool_]:
    """Least-squares data snooping (Baarda w-test) of one epoch's measurements.

    ``h`` (m, p) design matrix, ``r`` (m,) residuals at the linearization point. Iteratively
    removes the largest ``|w_i| = |e_i| / (sigma sqrt(Q_e,ii))`` > k, ``Q_e = I - H N^-1 H^T``,
    while the redundancy is >= 2 (with 1 a blunder is detectable but not identifiable).
    Returns the flagged mask.
    """
    return screen_blunders_status(h, r, sigma, k)[0]


def screen_blunders_status(h: F64, r: F64, sigma: float, k: float) -> tuple[NDArray[np.bool_], bool]:
    """:func:`screen_blunders` plus whether it isolated every fault: True when it stopped
    because all remaining ``|w| <= k``; False when it stopped at redundancy < 2 or at a
    singular geometry (a fault may remain), or never had redundancy >= 2."""
    m, npar = h.shape
    flagged = np.zeros(m, dtype=bool)
    while (~flagged).sum() - npar >= 2:
        use = np.flatnonzero(~flagged)
        hu, ru = h[use], r[use]
        n_mat = hu.T @ hu
        sv = np.linalg.svd(n_mat, compute_uv=False)
        with np.errstate(divide="ignore", invalid="ignore"):
            cond = sv[0] / sv[-1]  # = np.linalg.cond(n_mat) (0/0 -> NaN counts as singular, as there)
        if not cond <= 1e12:
            return flagged, False
        sol = np.linalg.solve(n_mat, hu.T)  # N^-1 H^T: one factorization for dx and Q_e
        e = ru - hu @ (sol @ ru)
        qe = 1.0 - np.einsum("ij,ji->i", hu, sol)
        w = np.abs(e) / (sigma * np.sqrt(np.maximum(qe, 1e-12)))
        j = int(np.argmax(w))
        if w[j] <= k:
            return flagged, True
        flagged[use[j]] = True
    return flagged, False


class ClusterFilterBase(ABC):
    """Sequencing, gating and initialization shared by both engines.

    Engines implement: ``_predict_core(dt)``, ``_apply(row, z, r_var, wrap, test)``,
    ``_set_block(s, mean, cov)``, ``_get_x()``, ``_get_P()``, ``_replace(x, P)``.
    """

    def __init__(self, layout: StateLayout, config: FilterConfig | None = None):
        self.layout = layout
        self.config = config or FilterConfig()
        self._k = self.config.gate_k
        self.counters: dict[str, int] = {}
        self.integrity_available: dict[str, bool] = {}
        self._nis_window: dict[str, deque[tuple[float, bool]]] = {}
        self._vehicle_ready = {v: False for v in layout.vehicles}
        self._azimuth_ready = {v: False for v in layout.azimuth_vehicles}
        x0, p0 = self._prior(layout)
        self._replace(x0, p0)

    # ----------------------------------------------------------------- state
    def _prior(self, layout: StateLayout) -> tuple[F64, F64]:
        n = layout.n
        var = np.full(n, self.config.uninitialized_variance)
        for v in layout.azimuth_rate_vehicles:
            var[layout.azimuth_rate(v)] = self.config.process.yaw_rate_sigma_rps**2  # GM steady state
        for pair in layout.uwb_pairs:
            var[layout.uwb_bias(pair)] = self.config.uwb_bias_sigma0_m**2
            var[layout.uwb_scale(pair)] = self.config.uwb_scale_sigma0**2
        return np.zeros(n), np.diag(var)

    @property
    def x(self) -> F64:
        return self._get_x().copy()

    @property
    def P(self) -> F64:
        return self._get_P().copy()

    def is_initialized(self, v: str) -> bool:
        return v == self.layout.lead or self._vehicle_ready.get(v, False)

    def is_azimuth_initialized(self, v: str) -> bool:
        return self._azimuth_ready.get(v, False)

    def azimuth_rad(self, v: str) -> float:
        return float(wrap_angle(self._get_x()[self.layout.azimuth(v)]))

    def azimuth_rate_rps(self, v: str) -> float:
        """Estimated azimuth rate of ``v`` (rad/s); NaN when the layout has no rate state."""
        if not self.layout.has(AZIMUTH_RATE, v):
            return float("nan")
        return float(self._get_x()[self.layout.azimuth_rate(v)])

    def _count(self, key: str) -> None:
        self.counters[key] = self.counters.get(key, 0) + 1

    def add_vehicle(self, v: str) -> None:
        """Add a vehicle block (uninitialized until its next GNSS epoch)."""
        new, remap = self.layout.add_vehicle(v, mean=np.zeros(8), variance=self.config.uninitialized_variance)
        x, P = remap(self._get_x(), self._get_P())
        self.layout = new
        self._vehicle_ready[v] = False
        self._replace(x, P)

    def remove_vehicle(self, v: str) -> None:
        """Remove a vehicle with its azimuth and UWB-pair states (marginalization)."""
        new, remap = self.layout.without_vehicle(v)
        x, P = remap(self._get_x(), self._get_P())
        self.layout = new
        self._vehicle_ready.pop(v, None)
        self._azimuth_ready.pop(v, None)
        self._nis_window.pop(v, None)
        self.integrity_available.pop(v, None)
        self._replace(x, P)

    # ----------------------------------------------------------------- predict
    def predict(self, dt_s: float) -> None:
        """Propagate x and P over dt_s seconds (exact GM / random-walk discretization)."""
        if not np.isfinite(dt_s) or dt_s < 0.0:
            raise ValueError(f"dt_s must be finite and >= 0, got {dt_s!r}")
        if dt_s > 0.0:
            self._predict_core(float(dt_s))

    # ----------------------------------------------------------------- one scalar
    def _scalar(self, kind: str, vehicles: tuple[str, ...], row: Row, z: float, r_var: float, *,
                wrap: bool = False, test: bool = True, prn: int = -1) -> UpdateInfo | None:
        nu, s, accepted = self._apply(row, z, r_var, wrap, test)
        if not (math.isfinite(nu) and math.isfinite(s) and s > 0.0):
            self._count(f"nonfinite_{kind}")
            return None
        if not accepted:
            self._count(f"rejected_{kind}")
        return UpdateInfo(kind, vehicles, nu, s, nu * nu / s, accepted, prn)

    # ----------------------------------------------------------------- GNSS
    def update_gnss(self, epochs: dict[str, GnssEpoch], lead_base_ecef_m: F64,
                    lead_base_vel_ecef_mps: F64 | None = None) -> list[UpdateInfo]:
        """SD pseudorange (and Doppler) updates from one epoch of every vehicle's receiver.

        ``lead_base_ecef_m``: the lead's standalone position (paper eq. 7: its error barely
        matters). Vehicles outside the layout are ignored; uninitialized vehicles are
        initialized from this epoch when possible.
        """
        geo = GnssGeometry(base_ecef_m=np.asarray(lead_base_ecef_m, dtype=float),
                           base_vel_ecef_mps=np.zeros(3) if lead_base_vel_ecef_mps is None
                           else np.asarray(lead_base_vel_ecef_mps, dtype=float))
        lay = self.layout
        lead_ep = epochs.get(lay.lead)
        infos: list[UpdateInfo] = []
        just_initialized: set[str] = set()
        self.integrity_available = dict.fromkeys(lay.vehicles, False)
        for v in lay.vehicles:  # covariance growth beyond any use: start again from this snapshot
            if self._vehicle_ready[v] and self._position_sigma_m(v) > self.config.divergence_position_sigma_m:
                self._reset_vehicle(v)
        per_vehicle: dict[str, tuple[GnssEpoch, NDArray, NDArray, F64]] = {}
        for v in lay.vehicles:
            ep = epochs.get(v)
            if ep is None or lead_ep is None:
                continue
            prns, iv, il = np.intersect1d(ep.prn, lead_ep.prn, return_indices=True)
            ok = np.isfinite(ep.pseudorange_m[iv]) & np.isfinite(lead_ep.pseudorange_m[il])
            n_bad = int((~ok).sum())
            for _ in range(n_bad):
                self._count(f"nonfinite_{KIND_SD_PR}")
            iv, il = iv[ok], il[ok]
            el = _elevations(geo, lead_ep.sv_pos_ecef_m[il])
            order = np.argsort(-el, kind="stable")
            iv, il = iv[order], il[order]
            per_vehicle[v] = (ep, iv, il, el[order])
            if not self._vehicle_ready[v]:
                if self._initialize_vehicle(v, geo, ep, lead_ep, iv, il):
                    just_initialized.add(v)
                continue
            infos += self._sd_pseudoranges(v, geo, ep, lead_ep, iv, il)
            if self._window_diverged(v):
                self._reset_vehicle(v)  # re-initialized by the next epoch's snapshot
        if self.config.use_pair_sd:
            infos += self._pair_sds(epochs, lead_ep, geo)
        if self.config.use_doppler:
            for v, (ep, iv, il, _) in per_vehicle.items():
                if self._vehicle_ready[v] and v not in just_initialized:
                    infos += self._sd_dopplers(v, geo, ep, lead_ep, iv, il)
        return infos

    def _first_unflagged_order(self, h_pred: F64, val: F64, z: F64, sigma: float,
                               cols: int) -> tuple[NDArray[np.int64], NDArray[np.bool_], bool]:
        """Elevation order with the highest-elevation w-test-clean measurement moved first.

        ``h_pred`` (m,) predicted measurements, ``val`` (m, k) their Jacobian rows (one
        vehicle's rows: same indices); the screen uses the last ``cols`` columns.
        Returns (order, excluded, isolated): ``excluded`` marks the flagged measurements when
        more than one was flagged (all left out); ``isolated`` is the screen's
        :func:`screen_blunders_status` (False when it could not run).
        """
        m = len(h_pred)
        order = np.arange(m)
        excluded = np.zeros(m, dtype=bool)
        if m < cols + 2:
            return order, excluded, False
        h = val[:, -cols:]
        res = z - h_pred
        flagged, isolated = screen_blunders_status(h, res, sigma, self._k)
        if flagged.any():
            for _ in range(int(flagged.sum())):
                self._count("screened_first_update")
            first = int(np.flatnonzero(~flagged)[0]) if (~flagged).any() else 0
            order = np.concatenate([[first], np.delete(order, first)])
            if flagged.sum() > 1:
                excluded = flagged
        return order, excluded, isolated

    def _excluded(self, kind: str, vehicles: tuple[str, ...], row: Row, z: float, r_var: float,
                  prn: int) -> UpdateInfo | None:
        """Report a measurement left out by the screen as rejected (x, P untouched)."""
        nu = float(z - row.h)
        P = self._get_P()
        s = float(row.val @ P[np.ix_(row.idx, row.idx)] @ row.val) + r_var
        if not (np.isfinite(nu) and np.isfinite(s) and s > 0.0):
            self._count(f"nonfinite_{kind}")
            return None
        self._count(f"rejected_{kind}")
        self._count("excluded_screened")
        return UpdateInfo(kind, vehicles, nu, s, nu * nu / s, False, prn)

    # ----------------------------------------------------------------- fault detection
    def _clock_jump(self, v: str, h_pred: F64, val: F64, idx: NDArray[np.int64], z: F64, r_var: float) -> bool:
        """Common-mode test of one vehicle's SD pseudorange innovations (module docstring);
        on a detection re-initialize only its SD clock state at ``clk + median(nu)``.
        ``h_pred`` (m,), ``val`` (m, k): the rows, all on the state indices ``idx``."""
        n = len(h_pred)
        if n < 3:
            return False
        pb = self._get_P()[np.ix_(idx, idx)]
        nu = z - h_pred
        s = np.einsum("ij,jk,ik->i", val, pb, val) + r_var
        gate = self._k * np.sqrt(s)
        fail = np.abs(nu) > gate
        if 2 * int(fail.sum()) <= n or not (np.all(nu[fail] > 0.0) or np.all(nu[fail] < 0.0)):
            return False
        m = float(np.median(nu))
        if 2 * int((np.abs(nu - m) <= gate).sum()) <= n:
            return False
        i = self.layout.clock(v)
        clk = float(self._get_x()[i])
        self._set_block(slice(i, i + 1), np.array([clk + m]), np.array([[self.config.clock_reset_sigma_m**2]]))
        self._nis_window.pop(v, None)
        self._count("clock_jump_detected")
        return True

    def _record_test(self, v: str, info: UpdateInfo) -> None:
        w = self._nis_window.setdefault(v, deque(maxlen=self.config.divergence_window))
        w.append((info.nis, info.accepted))

    def window_mean_nis(self, v: str) -> float:
        """Mean NIS of the last ``divergence_window`` SD-pseudorange tests of ``v`` (NaN if none)."""
        w = self._nis_window.get(v)
        return float(np.mean([n for n, _ in w])) if w else float("nan")

    def window_nis_band(self, v: str, prob: float = 0.999) -> tuple[float, float]:
        """Two-sided ``prob`` chi-square band of :meth:`window_mean_nis` under H0."""
        n = len(self._nis_window.get(v, ())) or 1
        lo, hi = chi2.ppf([(1.0 - prob) / 2.0, (1.0 + prob) / 2.0], n) / n
        return float(lo), float(hi)

    def _window_diverged(self, v: str) -> bool:
        w = self._nis_window.get(v)
        if w is None or len(w) < self.config.divergence_window:
            return False
        n_rej = sum(1 for _, ok in w if not ok)
        return n_rej > self.config.divergence_reject_fraction * len(w)

    def _position_sigma_m(self, v: str) -> float:
        sl = self.layout.position(v)
        return float(np.sqrt(max(float(np.trace(self._get_P()[sl, sl])), 0.0)))

    def _reset_vehicle(self, v: str) -> None:
        """Back to the uninitialized prior; the next GNSS snapshot re-initializes the block."""
        self._set_block(self.layout.block(VEHICLE, v), np.zeros(8),
                        np.eye(8) * self.config.uninitialized_variance)
        self._vehicle_ready[v] = False
        self._nis_window.pop(v, None)
        self._count("divergence_reset")

    def _sd_pseudoranges(self, v: str, geo: GnssGeometry, ep: GnssEpoch, lead_ep: GnssEpoch,
                         iv: NDArray, il: NDArray) -> list[UpdateInfo]:
        # all rows of the vehicle in one numpy step (screen, clock test); each sequential
        # update relinearizes its own row at the current state (models.SdPseudorangeRows)
        rows = models.SdPseudorangeRows(self.layout, geo, v, ep.sv_pos_ecef_m[iv], lead_ep.sv_pos_ecef_m[il])
        z = ep.pseudorange_m[iv] - lead_ep.pseudorange_m[il]
        h_pred, val = rows.all(self._get_x())
        r_var = self.config.noise.sd_pseudorange_var_m2
        if self.config.clock_jump_detection and self._clock_jump(v, h_pred, val, rows.idx, z, r_var):
            h_pred, val = rows.all(self._get_x())
        order, excluded, isolated = self._first_unflagged_order(h_pred, val, z, np.sqrt(r_var), 4)
        self.integrity_available[v] = isolated
        out = []
        zl = z.tolist()
        prns = ep.prn[iv].tolist()
        for o in order.tolist():
            row = rows.row(self._get_x(), o)
            if excluded[o]:
                info = self._excluded(KIND_SD_PR, (v,), row, zl[o], r_var, prns[o])
            else:
                info = self._scalar(KIND_SD_PR, (v,), row, zl[o], r_var, prn=prns[o])
            if info is not None:
                out.append(info)
                self._record_test(v, info)
        return out

    def _sd_dopplers(self, v: str, geo: GnssGeometry, ep: GnssEpoch, lead_ep: GnssEpoch,
                     iv: NDArray, il: NDArray) -> list[UpdateInfo]:
        lay = self.layout
        ok = np.isfinite(ep.doppler_mps[iv]) & np.isfinite(lead_ep.doppler_mps[il])
        for _ in range(int((~ok).sum())):
            self._count(f"nonfinite_{KIND_SD_DOPPLER}")
        iv, il = iv[ok], il[ok]
        z = ep.doppler_mps[iv] - lead_ep.doppler_mps[il]
        r_var = self.config.noise.sd_doppler_var_m2ps2
        rows = models.SdDopplerRows(lay, geo, v, ep.sv_pos_ecef_m[iv], ep.sv_vel_ecef_mps[iv],
                                    lead_ep.sv_pos_ecef_m[il], lead_ep.sv_vel_ecef_mps[il])
        h_pred, val = rows.all(self._get_x())
        # screen on (velocity, drift): the last 4 entries of the row
        order, excluded, _ = self._first_unflagged_order(h_pred, val, z, np.sqrt(r_var), 4)
        out = []
        zl = z.tolist()
        prns = ep.prn[iv].tolist()
        for o in order.tolist():
            row = rows.row(self._get_x(), o)
            if excluded[o]:
                info = self._excluded(KIND_SD_DOPPLER, (v,), row, zl[o], r_var, prns[o])
            else:
                info = self._scalar(KIND_SD_DOPPLER, (v,), row, zl[o], r_var, prn=prns[o])
            if info is not None:
                out.append(info)
        return out

    def _pair_sds(self, epochs: dict[str, GnssEpoch], lead_ep: GnssEpoch | None,
                  geo: GnssGeometry) -> list[UpdateInfo]:
        """SDs between two non-lead vehicles for satellites the lead does not see."""
        lay = self.layout
        ready = [v for v in lay.vehicles if self._vehicle_ready[v] and v in epochs]
        if len(ready) < 2:
            return []
        lead_seen = set()
        if lead_ep is not None:
            lead_seen = set(lead_ep.prn[np.isfinite(lead_ep.pseudorange_m)].tolist())
        # prn -> list of (vehicle, index), vehicles in layout order
        seen: dict[int, list[tuple[str, int]]] = {}
        for v in ready:
            ep = epochs[v]
            for i in np.flatnonzero(np.isfinite(ep.pseudorange_m)):
                prn = int(ep.prn[i])
                if prn not in lead_seen:
                    seen.setdefault(prn, []).append((v, int(i)))
        jobs = []
        for prn, lst in seen.items():
            if len(lst) < 2:
                continue
            ref_v, ref_i = lst[0]
            el = float(_elevations(geo, epochs[ref_v].sv_pos_ecef_m[ref_i][None, :])[0])
            jobs.append((-el, prn, ref_v, ref_i, lst[1:]))
        jobs.sort()
        out = []
        r_var = self.config.noise.sd_pseudorange_var_m2
        for _, prn, b, bi, others in jobs:
            eb = epochs[b]
            for a, ai in others:
                ea = epochs[a]
                row = models.sd_pseudorange_pair(self._get_x(), lay, geo, a, b, ea.sv_pos_ecef_m[ai],
                                                 eb.sv_pos_ecef_m[bi])
                z = float(ea.pseudorange_m[ai] - eb.pseudorange_m[bi])
                info = self._scalar(KIND_SD_PR_PAIR, (a, b), row, z, r_var, prn=prn)
                if info is not None:
                    out.append(info)
        return out

    def _initialize_vehicle(self, v: str, geo: GnssGeometry, ep: GnssEpoch, lead_ep: GnssEpoch,
                            iv: NDArray, il: NDArray) -> bool:
        """Snapshot least squares for position + clock (and velocity + drift from Doppler)."""
        if len(iv) < self.config.init_min_satellites:
            self._count("init_too_few_satellites")
            return False
        lay = self.layout
        sig_pr = np.sqrt(self.config.noise.sd_pseudorange_var_m2)
        z = ep.pseudorange_m[iv] - lead_ep.pseudorange_m[il]
        xt = np.zeros(lay.n)
        pc = np.r_[np.arange(lay.position(v).start, lay.position(v).stop), lay.clock(v)]
        use = np.ones(len(iv), dtype=bool)
        h = np.zeros((0, 4))
        for it in range(6):
            rows = [models.sd_pseudorange(xt, lay, geo, v, ep.sv_pos_ecef_m[i], lead_ep.sv_pos_ecef_m[j])
                    for i, j in zip(iv, il, strict=True)]
            h = np.array([r.val for r in rows])
            res = z - np.array([r.h for r in rows])
            if it == 2:  # screen once the linearization point is good
                use = ~screen_blunders(h, res, sig_pr, self._k)
            n_mat = h[use].T @ h[use]
            if use.sum() < 4 or np.linalg.cond(n_mat) > 1e10:
                self._count("init_bad_geometry")
                return False
            xt[pc] += np.linalg.solve(n_mat, h[use].T @ res[use])
        cov_pc = sig_pr**2 * np.linalg.inv(h[use].T @ h[use])
        mean = np.zeros(8)
        cov = np.zeros((8, 8))
        mean[[0, 1, 2, 6]] = xt[pc]
        cov[np.ix_([0, 1, 2, 6], [0, 1, 2, 6])] = cov_pc
        pcfg = self.config.process
        cov[3, 3] = cov[4, 4] = pcfg.vel_sigma_horizontal_mps**2
        cov[5, 5] = pcfg.vel_sigma_vertical_mps**2
        cov[7, 7] = pcfg.drift_sigma_mps**2
        okd = np.isfinite(ep.doppler_mps[iv]) & np.isfinite(lead_ep.doppler_mps[il])
        if self.config.use_doppler and okd.sum() >= 4:
            sig_d = np.sqrt(self.config.noise.sd_doppler_var_m2ps2)
            zd = (ep.doppler_mps[iv] - lead_ep.doppler_mps[il])[okd]
            rows = [models.sd_doppler(xt, lay, geo, v, ep.sv_pos_ecef_m[i], ep.sv_vel_ecef_mps[i],
                                      lead_ep.sv_pos_ecef_m[j], lead_ep.sv_vel_ecef_mps[j])
                    for i, j in zip(iv[okd], il[okd], strict=True)]
            hd = np.array([_compact(r, 4) for r in rows])
            rd = zd - np.array([r.h for r in rows])
            used = ~screen_blunders(hd, rd, sig_d, self._k)
            nd = hd[used].T @ hd[used]
            if used.sum() >= 4 and np.linalg.cond(nd) < 1e10:
                # linear in velocity and drift (the tiny position term is held at the PR fix)
                mean[[3, 4, 5, 7]] = np.linalg.solve(nd, hd[used].T @ rd[used])
                cov[np.ix_([3, 4, 5, 7], [3, 4, 5, 7])] = sig_d**2 * np.linalg.inv(nd)
        self._set_block(lay.block(VEHICLE, v), mean, 0.5 * (cov + cov.T))
        self._vehicle_ready[v] = True
        self._count("initialized_vehicles")
        return True

    def _pair_usable(self, kind: str, a: str, b: str, z: float, known: set[str]) -> bool:
        """A measurement between vehicles a and b can be used: finite, both in the cluster and
        initialized. Counts the reason when not (``nonfinite_<kind>``, ``<kind>_unknown_vehicle``,
        ``<kind>_uninitialized``)."""
        if not np.isfinite(z):
            self._count(f"nonfinite_{kind}")
            return False
        if a not in known or b not in known or a == b:
            self._count(f"{kind}_unknown_vehicle")
            return False
        if not (self.is_initialized(a) and self.is_initialized(b)):
            self._count(f"{kind}_uninitialized")
            return False
        return True

    # ----------------------------------------------------------------- UWB
    def update_uwb(self, ranges: UwbRanges) -> list[UpdateInfo]:
        """One scalar update per UWB range (the caller has predicted to the time tag)."""
        lay = self.layout
        known = {lay.lead, *lay.vehicles}
        r_var = self.config.noise.uwb_sigma_m**2
        out = []
        for k in range(ranges.n):
            a, b = ranges.a[k], ranges.b[k]
            z = float(ranges.range_m[k])
            if not self._pair_usable(KIND_UWB, a, b, z, known):
                continue
            x = self._get_x()
            d = models.rel_position(x, lay, b) - models.rel_position(x, lay, a)
            m, h2_var = self._second_order(a, b, _range_hessian(d))
            if not h2_var <= self.config.nonlinear_fraction * r_var:  # _linear_enough
                self._count("uwb_deferred_nonlinear")
                continue
            row = models.uwb_range(x, lay, a, b, use_bias_scale=self.config.use_uwb_bias_scale)
            # second-order EKF terms (Gelb 1974 sec. 6.1): E[f(d)] ~ f + tr(H2 P_d)/2 and the
            # neglected term's variance tr((H2 P_d)^2)/2 added to R
            row = Row(row.h + 0.5 * float(m.trace()), row.idx, row.val)
            info = self._scalar(KIND_UWB, (a, b), row, z, r_var + h2_var)
            if info is None:
                continue
            out.append(info)
            if info.accepted and self.config.use_uwb_bias_scale and lay.has(UWB, uwb_pair_key(a, b)):
                out += self._apply_constraints(uwb_pair_key(a, b))
        return out

    def _apply_constraints(self, pair: tuple[str, str]) -> list[UpdateInfo]:
        """Inequality constraints as pseudo-measurements (MacGougan (2009) eq. 3.19-3.22).

        If a state exceeds its max, a pseudo-measurement at the *min* with variance
        ``P_ii (max - min) / (x - max)`` moves it exactly onto the max (and vice versa);
        other states move through their correlations. Repeated (at most 4 passes) since
        one constraint can push the other state out of bounds.
        """
        lay = self.layout
        checks = []
        if self.config.uwb_bias_bounds_m is not None:
            checks.append((lay.uwb_bias(pair), self.config.uwb_bias_bounds_m))
        if self.config.uwb_scale_bounds is not None:
            checks.append((lay.uwb_scale(pair), self.config.uwb_scale_bounds))
        out = []
        for _ in range(4):
            changed = False
            for i, (lo, hi) in checks:
                xi = float(self._get_x()[i])
                pii = float(self._get_P()[i, i])
                if xi > hi:
                    z, r_var = lo, pii * (hi - lo) / (xi - hi)
                elif xi < lo:
                    z, r_var = hi, pii * (hi - lo) / (lo - xi)
                else:
                    continue
                row = Row(xi, np.array([i]), np.array([1.0]))
                info = self._scalar(KIND_CONSTRAINT, pair, row, z, r_var, test=False)
                if info is not None:
                    out.append(info)
                    changed = True
            if not changed:
                break
        return out

    # ----------------------------------------------------------------- bearings
    def update_bearings(self, bearings: Bearings) -> list[UpdateInfo]:
        """One scalar update per bearing; azimuth known (reported) unless a has an azimuth state."""
        lay = self.layout
        known = {lay.lead, *lay.vehicles}
        r_var = self.config.noise.bearing_sigma_rad**2
        out = []
        for k in range(bearings.n):
            a, b = bearings.a[k], bearings.b[k]
            z = float(bearings.bearing_rad[k])
            if not self._pair_usable(KIND_BEARING, a, b, z, known):
                continue
            x = self._get_x()
            d = models.rel_position(x, lay, b) - models.rel_position(x, lay, a)
            if np.hypot(d[0], d[1]) < 1.0:
                self._count("bearing_degenerate_geometry")
                continue
            m, h2_var = self._second_order(a, b, _bearing_hessian(d))
            if not h2_var <= self.config.nonlinear_fraction * r_var:  # _linear_enough
                self._count("bearing_deferred_nonlinear")
                continue
            h2_bias = 0.5 * float(m.trace())
            if lay.has(AZIMUTH, a):
                if not self._azimuth_ready[a]:
                    alpha0 = float(bearing_rad(d, z))  # atan2(dE, dN) - beta, wrapped
                    s = slice(lay.azimuth(a), lay.azimuth(a) + 1)
                    self._set_block(s, np.array([alpha0]), np.array([[self.config.azimuth_sigma0_rad**2]]))
                    self._azimuth_ready[a] = True
                row = models.bearing(self._get_x(), lay, a, b, None)
            else:
                az = float(bearings.azimuth_reported_rad[k])
                if not np.isfinite(az):
                    self._count(f"nonfinite_{KIND_BEARING}")
                    continue
                row = models.bearing(x, lay, a, b, az)
            row = Row(row.h + h2_bias, row.idx, row.val)
            info = self._scalar(KIND_BEARING, (a, b), row, z, r_var + h2_var, wrap=True)
            if info is not None:
                out.append(info)
        return out

    def _linear_enough(self, a: str, b: str, hess: F64, r_var: float) -> bool:
        """Is the first-order (EKF) model adequate for a function of d = p_b - p_a?

        The neglected second-order term of ``f(d)`` has variance ``1/2 tr((H2 P_d)^2)`` for
        Gaussian ``d`` with covariance ``P_d`` (H2 = Hessian of f). A UWB range or bearing
        is used only when that is <= ``nonlinear_fraction`` of its measurement variance;
        right after a GNSS initialization (metre-level P) ranges and bearings over
        ~30 m are deferred until GNSS has shrunk P, which keeps the EKF consistent.
        """
        return self._second_order(a, b, hess)[1] <= self.config.nonlinear_fraction * r_var

    def _second_order(self, a: str, b: str, hess: F64) -> tuple[F64, float]:
        """``(H2 P_d, tr((H2 P_d)^2) / 2)``: the product (its half trace is the second-order
        mean) and the neglected second-order variance of :meth:`_linear_enough`."""
        m = hess @ self._rel_cov(a, b)
        return m, 0.5 * float((m @ m).trace())

    def _rel_cov(self, a: str, b: str) -> F64:
        """Covariance of d = p_b - p_a."""
        lay = self.layout
        P = self._get_P()
        pd = np.zeros((3, 3))
        sa = lay.position(a) if a != lay.lead else None
        sb = lay.position(b) if b != lay.lead else None
        if sa is not None:
            pd += P[sa, sa]
        if sb is not None:
            pd += P[sb, sb]
        if sa is not None and sb is not None:
            pd -= P[sa, sb] + P[sb, sa]
        return pd

    def update_height_aiding(self, sigma_m: float) -> list[UpdateInfo]:
        """Pseudo-measurement ``p_v,up = 0`` (variance sigma^2) for every initialized vehicle.

        Tested like any measurement, so a real height difference (a ramp) is rejected
        rather than forced in.
        """
        lay = self.layout
        out = []
        for v in lay.vehicles:
            if not self._vehicle_ready[v]:
                continue
            i = lay.position(v).start + 2
            row = Row(float(self._get_x()[i]), np.array([i]), np.array([1.0]))
            info = self._scalar(KIND_HEIGHT, (v,), row, 0.0, sigma_m**2)
            if info is not None:
                out.append(info)
        return out

    # ----------------------------------------------------------------- all at once
    def update_epoch(self, *, gnss: dict[str, GnssEpoch] | None = None, lead_base_ecef_m: F64 | None = None,
                     uwb: UwbRanges | None = None, bearings: Bearings | None = None) -> list[UpdateInfo]:
        """GNSS, then UWB, then bearings (thesis section 3.5.1 order)."""
        out: list[UpdateInfo] = []
        if gnss:
            if lead_base_ecef_m is None:
                raise ValueError("lead_base_ecef_m is required with GNSS epochs")
            out += self.update_gnss(gnss, lead_base_ecef_m)
        elif self.config.height_aiding_sigma_m is not None:
            out += self.update_height_aiding(self.config.height_aiding_sigma_m)
        if uwb is not None:
            out += self.update_uwb(uwb)
        if bearings is not None:
            out += self.update_bearings(bearings)
        return out

    # ----------------------------------------------------------------- engine hooks
    @abstractmethod
    def _predict_core(self, dt_s: float) -> None:
        """Engine hook."""

    @abstractmethod
    def _apply(self, row: Row, z: float, r_var: float, wrap: bool, test: bool) -> tuple[float, float, bool]:
        """Engine hook: innovation (wrapped if ``wrap``), its variance S, accepted."""

    @abstractmethod
    def _set_block(self, s: slice, mean: F64, cov: F64) -> None:
        """Engine hook."""

    @abstractmethod
    def _get_x(self) -> F64:
        """Engine hook."""

    @abstractmethod
    def _get_P(self) -> F64:
        """Engine hook."""

    @abstractmethod
    def _replace(self, x: F64, P: F64) -> None:
        """Engine hook."""


def _range_hessian(d: F64) -> F64:
    """Hessian of |d|: (I - u u^T) / |d|."""
    dx, dy, dz = d.tolist()
    r = math.sqrt(dx * dx + dy * dy + dz * dz)
    u = d / r
    h = np.multiply.outer(u, -u)
    h += _EYE3
    h /= r
    return h


_EYE3 = np.eye(3)


def _bearing_hessian(d: F64) -> F64:
    """Hessian of atan2(E, N) in (E, N, U): [[-2EN, E^2-N^2], [E^2-N^2, 2EN]] / r^4."""
    e, n = float(d[0]), float(d[1])
    r4 = (e * e + n * n) ** 2
    h = np.zeros((3, 3))
    h[0, 0] = -2.0 * e * n / r4
    h[1, 1] = 2.0 * e * n / r4
    h[0, 1] = h[1, 0] = (e * e - n * n) / r4
    return h


def _compact(row: Row, cols: int) -> F64:
    """Last ``cols`` Jacobian entries of a single-vehicle row (velocity + drift of a Doppler row)."""
    return row.val[-cols:]


def _elevations(geo: GnssGeometry, sv_ecef_m: F64) -> F64:
    """Satellite elevations (rad) seen from the lead base."""
    d = (np.asarray(sv_ecef_m, dtype=float) - geo.base_ecef_m) @ geo.rot_ecef_to_enu.T
    return np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))


class ClusterEkf(ClusterFilterBase):
    """Production engine: sparse rows, O(n) P h^T, symmetric rank-1 covariance update,
    block-wise prediction (each vehicle block shares one cached 8x8 F and Q).

    Example
    -------
    >>> ekf = ClusterEkf(StateLayout.build(lead="L", vehicles=["A", "B"]))  # doctest: +SKIP
    >>> ekf.predict(0.1); infos = ekf.update_gnss(epochs, lead_base_ecef_m)  # doctest: +SKIP
    """

    def _replace(self, x: F64, P: F64) -> None:
        self._x = np.array(x, dtype=float)
        self._P = np.array(P, dtype=float)
        self._veh0, self._nveh = self.layout.vehicle_blocks_contiguous()
        self._rw_index = random_walk_indices(self.layout)
        self._az_pairs = np.array(azimuth_pairs(self.layout), dtype=np.int64).reshape(-1, 2)

    def _get_x(self) -> F64:
        return self._x

    def _get_P(self) -> F64:
        return self._P

    def _predict_core(self, dt_s: float) -> None:
        fb, qb = vehicle_block(self.config.process, dt_s)
        s0, m = self._veh0, self._nveh
        n = self.layout.n
        if m:
            vs = slice(s0, s0 + 8 * m)
            xv = self._x[vs].reshape(m, 8)
            self._x[vs] = (xv @ fb.T).ravel()
            rows = self._P[vs, :].reshape(m, 8, n)
            self._P[vs, :] = np.einsum("ij,ajn->ain", fb, rows).reshape(8 * m, n)
            cols = self._P[:, vs].reshape(n, m, 8)
            self._P[:, vs] = (cols @ fb.T).reshape(n, 8 * m)
            blk = self._P[vs, vs].reshape(m, 8, m, 8)
            idx = np.arange(m)
            blk[idx, :, idx, :] += qb
            self._P[vs, vs] = blk.reshape(8 * m, 8 * m)
        for s, kind in self._rw_index:
            q = random_walk_variances(self.config.process, kind, dt_s)
            self._P[s, s] += np.diag(q)
        if len(self._az_pairs):
            fa, qa = azimuth_block(self.config.process, dt_s)
            ia, ir = self._az_pairs[:, 0], self._az_pairs[:, 1]
            xa, xr = self._x[ia].copy(), self._x[ir].copy()
            self._x[ia] = fa[0, 0] * xa + fa[0, 1] * xr
            self._x[ir] = fa[1, 0] * xa + fa[1, 1] * xr
            ra, rr = self._P[ia, :].copy(), self._P[ir, :].copy()
            self._P[ia, :] = fa[0, 0] * ra + fa[0, 1] * rr
            self._P[ir, :] = fa[1, 0] * ra + fa[1, 1] * rr
            ca, cr = self._P[:, ia].copy(), self._P[:, ir].copy()
            self._P[:, ia] = ca * fa[0, 0] + cr * fa[0, 1]
            self._P[:, ir] = ca * fa[1, 0] + cr * fa[1, 1]
            self._P[ia, ia] += qa[0, 0]
            self._P[ia, ir] += qa[0, 1]
            self._P[ir, ia] += qa[1, 0]
            self._P[ir, ir] += qa[1, 1]
        self._P = 0.5 * (self._P + self._P.T)

    def _apply(self, row: Row, z: float, r_var: float, wrap: bool, test: bool) -> tuple[float, float, bool]:
        nu = float(wrap_angle(z - row.h)) if wrap else float(z - row.h)
        s, ok = scalar_update(self._x, self._P, row.idx, row.val, nu, r_var, self._k if test else None)
        return nu, s, ok

    def _set_block(self, s: slice, mean: F64, cov: F64) -> None:
        self._x[s] = mean
        self._P[s, :] = 0.0
        self._P[:, s] = 0.0
        self._P[s, s] = cov
