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
  1e-60), or the window's mean NIS (each test's capped at the gate, k^2) exceeds
  ``divergence_mean_nis`` (under H0 N times it is chi-square(N): P(mean of 50 > 5) ~ 2e-28;
  a state 50 m off with a metre-level covariance keeps most tests inside the gate, the SD
  clock absorbing their common part, so the rejected fraction alone missed it in ~9 of 10
  geometries, while its capped mean NIS is ~7), or the position standard deviation exceeds
  ``divergence_position_sigma_m``, the vehicle is reset. The covariance's growth resets it
  at once to the uninitialized prior, re-initialized by the snapshot least squares of its
  next GNSS epoch. The window's tests make it suspect (``divergence_suspected``): its
  covariance is scaled by the window's capped mean NIS (covariance matching: the window
  said P covered the innovations short by that factor), and since the test fires on wrong
  pseudoranges (an echo-only sky) as well as on a wrong state, the block is reset
  (``divergence_reset``) to the first snapshot that can be trusted (>= 5 satellites after
  the blunder screen, residuals inside their chi-square bound) and disagrees with the
  state (chi-square, 3 dof, both covariances), or after ``divergence_confirm_s`` to the
  first snapshot there is; a trusted one that agrees clears it (``divergence_cleared``)
  (:meth:`_confirm_divergence`). The window's
  mean NIS is available as :meth:`ClusterFilterBase.window_mean_nis` for diagnostics.

Noise model: every SD measurement is treated as independent with variance 2 sigma^2
(paper Table 1: undifferenced pseudorange sigma = 5 m). Two SDs of one satellite share
the lead's error, so they are in truth correlated (covariance sigma^2); the paper's
filter, and this one, ignore that.
"""

from __future__ import annotations

import functools
import itertools
import math
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from itertools import compress, repeat
from operator import eq, itemgetter
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import special

from v2v.errors import UserError, check_sigmas
from v2v.estimation import kernels, models
from v2v.estimation.layout import AMBIGUITY, AZIMUTH, AZIMUTH_RATE, UWB, VEHICLE, StateLayout, uwb_pair_key
from v2v.estimation.models import GnssGeometry, Row
from v2v.estimation.phase import (
    LAMBDA_L1_M,
    PhaseConfig,
    PhaseStatus,
    SlipDetector,
    resolve_vehicle,
    sd_phase_row,
    sd_range_row,
)
from v2v.estimation.process import (
    ProcessNoiseConfig,
    azimuth_pairs,
    random_walk_indices,
    random_walk_variances,
)
from v2v.frames import wrap_angle
from v2v.measmodels import bearing_rad
from v2v.sensors.measurements import Bearings, GnssEpoch, UwbRanges
from v2v.smallmat import cond2_symmetric

F64 = NDArray[np.float64]

KIND_SD_PR = "sd_pseudorange"
KIND_SD_PR_PAIR = "sd_pseudorange_pair"
KIND_SD_DOPPLER = "sd_doppler"
KIND_UWB = "uwb"
KIND_BEARING = "bearing"
KIND_CONSTRAINT = "uwb_constraint"
KIND_HEIGHT = "height_aiding"
KIND_SD_PHASE = "sd_phase"
KIND_AMB_FIX = "ambiguity_fix"


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
        check_sigmas(self, "noise", ("pseudorange_sigma_m", "doppler_sigma_mps", "uwb_sigma_m", "bearing_sigma_rad"))

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
    phase : carrier-phase settings (:class:`v2v.estimation.phase.PhaseConfig`); None = the
        solution does not use carrier phase.
    height_aiding_sigma_m : when set, epochs without GNSS add a pseudo-measurement
        "relative up = h_v - h_lead +- sigma" per vehicle (cars on one locally flat road;
        ``h`` from ``antenna_heights_m``). UWB and bearings carry no vertical information,
        so without it the relative height random-walks (1 m/s GM: ~11 m after 30 s) and the
        range becomes too nonlinear to use.
    gnss_min_satellites : a vehicle with fewer satellites in common with the lead leaves its
        GNSS (SD pseudoranges, pair SDs, Dopplers) out of that epoch, like an outage (height
        aiding, UWB and bearings carry it; counted ``gnss_too_few_satellites``). With 2-3
        satellites, mostly echoes, the innovation test cannot single out the bad ones (no
        redundancy) and they pull the solution off. 0 (default): every SD is used, as in the
        paper's filter.
    gnss_cn0_mask_dbhz : SD pseudoranges, pair SDs and SD Dopplers use only signals with
        C/N0 >= this at both receivers (an SNR mask, as GNSS engines apply to code; counted
        ``gnss_cn0_masked`` per receiver signal and epoch). Echoes arrive ``echo_loss_db``
        (6-10 dB: reflection + LHCP rejection) below their direct signal, so a mask above
        ``cn0_zenith_dbhz - echo_loss_db`` (49 - 8 = 41 dB-Hz by default) leaves none, at the
        price of the weak direct signals (the default C/N0 model gives 40 dB-Hz at 18 deg
        elevation). Applied before ``gnss_min_satellites`` and the "fewer than 4" height
        aiding. The carrier phase still sees every signal (its slip detector needs the whole
        epoch) but uses only the phases of accepted SD pseudoranges: a masked satellite's
        ambiguity is dropped (counted ``phase_lost``) and starts afresh when it is back above
        the mask. Foliage-attenuated direct signals are masked at any elevation. A satellite
        masked only at the lead can still give an SD between two followers. 0 (default): no
        mask, as in the paper's filter.
    antenna_heights_m : each vehicle's GNSS antenna height above the road (m), static
        installation data a vehicle can broadcast; the relative up of two antennas on a flat
        road is the difference (a truck's 3.9 m and a car's 1.55 m: 2.35 m, which "relative
        up = 0" would force in: the innovation test passes offsets below ~3.3 sigma). None,
        or a vehicle missing from it: no difference.
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
    antenna_heights_m: Mapping[str, float] | None = None
    gnss_min_satellites: int = 0
    gnss_cn0_mask_dbhz: float = 0.0
    clock_jump_detection: bool = True
    clock_reset_sigma_m: float = 100.0
    divergence_window: int = 50
    divergence_reject_fraction: float = 0.5
    divergence_mean_nis: float = 5.0
    divergence_position_sigma_m: float = 1000.0
    divergence_confirm_s: float = 2.0
    phase: PhaseConfig | None = None

    def __post_init__(self) -> None:
        if not 0.0 < self.significance < 1.0:
            raise UserError(f"must be in (0, 1), got {self.significance!r}", field="filter.significance",
                            fix="e.g. 0.001 for a 3.29-sigma innovation test")
        check_sigmas(self, "filter", ("uwb_bias_sigma0_m", "uwb_scale_sigma0", "azimuth_sigma0_rad", "clock_reset_sigma_m")
                     + (("height_aiding_sigma_m",) if self.height_aiding_sigma_m is not None else ()))
        if self.init_min_satellites < 4:
            raise UserError("needs >= 4 satellites (3 position + clock)", field="filter.init_min_satellites")
        for name in ("uwb_bias_bounds_m", "uwb_scale_bounds"):
            b = getattr(self, name)
            if b is not None and not b[0] < b[1]:
                raise UserError(f"needs min < max, got {b!r}", field=f"filter.{name}")
        mask = self.gnss_cn0_mask_dbhz
        if isinstance(mask, bool) or not isinstance(mask, (int, float)) or not (math.isfinite(mask) and mask >= 0.0):
            raise UserError(f"must be a finite C/N0 >= 0 dB-Hz, got {self.gnss_cn0_mask_dbhz!r}",
                            field="filter.gnss_cn0_mask_dbhz", fix="e.g. 0 (no mask) or 41 (no echoes)")
        if not self.divergence_mean_nis > 1.0:
            raise UserError(f"must exceed 1 (the NIS expectation), got {self.divergence_mean_nis!r}",
                            field="filter.divergence_mean_nis", fix="e.g. 5 (use inf to test the rejected fraction only)")
        if not (math.isfinite(self.divergence_confirm_s) and self.divergence_confirm_s >= 0.0):
            raise UserError(f"must be a finite time >= 0 s, got {self.divergence_confirm_s!r}",
                            field="filter.divergence_confirm_s", fix="e.g. 2 (0: reset at the next snapshot)")
        if self.divergence_window < 1 or not 0.0 < self.divergence_reject_fraction <= 1.0:
            raise UserError("needs window >= 1 and 0 < reject fraction <= 1", field="filter.divergence_window")

    @property
    def gate_k(self) -> float:
        """Two-sided normal critical value: alpha = 0.001 -> 3.2905."""
        # = scipy.stats.norm.isf(alpha / 2) (same ndtri, bit for bit) without importing scipy.stats
        return float(-special.ndtri(self.significance / 2.0))


class UpdateInfo(NamedTuple):
    """What one scalar update did. ``nis = innovation^2 / variance``.

    A named tuple (immutable, attribute access): tens of thousands are made per simulated
    minute of a large cluster, and a tuple is built ~3x faster than a frozen dataclass."""

    kind: str
    vehicles: tuple[str, ...]
    innovation: float
    variance: float
    nis: float
    accepted: bool
    prn: int = -1


#: ``UpdateInfo`` from a 7-tuple without a Python-level call (``tuple.__new__``): the compiled
#: engines build their records with ``map(_info_from_tuple, zip(...))`` (same fields, same values)
_info_from_tuple = partial(tuple.__new__, UpdateInfo)
_nis_accepted = itemgetter(4, 5)  # (nis, accepted) of an UpdateInfo


class UpdateBatch(Sequence[UpdateInfo]):
    """Accepted updates of one kind from one compiled call, kept as columns: a read-only
    sequence of :class:`UpdateInfo` (built only when iterated or indexed; then kept).

    ``vehicles`` one tuple per update; ``innovation`` / ``variance`` float arrays;
    ``prn`` the satellite numbers (None: -1 for all). ``nis = innovation^2 / variance``
    elementwise (the same two IEEE operations as on Python floats). The per-epoch consumers
    (counts, the update log, the NIS windows) read the columns; nothing else needs to know.
    """

    __slots__ = ("kind", "vehicles", "innovation", "variance", "prn", "_nis", "_recs")

    def __init__(self, kind: str, vehicles: Sequence[tuple[str, ...]], innovation: F64, variance: F64,
                 prn: Sequence[int] | None = None) -> None:
        self.kind, self.vehicles, self.innovation, self.variance, self.prn = kind, vehicles, innovation, variance, prn
        self._nis: F64 | None = None
        self._recs: list[UpdateInfo] | None = None

    @property
    def nis(self) -> F64:
        if self._nis is None:
            nu = self.innovation
            self._nis = nu * nu / self.variance
        return self._nis

    def records(self) -> list[UpdateInfo]:
        if self._recs is None:
            self._recs = list(map(_info_from_tuple, zip(
                repeat(self.kind), self.vehicles, self.innovation.tolist(), self.variance.tolist(), self.nis.tolist(),
                repeat(True), repeat(-1) if self.prn is None else self.prn)))
        return self._recs

    def __len__(self) -> int:
        return len(self.vehicles)

    def __iter__(self) -> Iterator[UpdateInfo]:
        return iter(self.records())

    def __getitem__(self, i):
        if isinstance(i, slice):  # a batch of the selected updates (views of the columns)
            b = UpdateBatch(self.kind, self.vehicles[i], self.innovation[i], self.variance[i],
                            None if self.prn is None else self.prn[i])
            if self._nis is not None:
                b._nis = self._nis[i]
            return b
        return self.records()[i]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and not isinstance(other, str) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"UpdateBatch({self.kind!r}, n={len(self)})"


class Updates(Sequence[UpdateInfo]):
    """The update records of one call, in update order: a read-only sequence of
    :class:`UpdateInfo` made of segments (lists of records and :class:`UpdateBatch` columns),
    extended with ``+=`` without building the batches' records. ``list(updates)`` gives the
    plain list; ``==`` compares element by element with any sequence."""

    __slots__ = ("parts", "_n")

    def __init__(self, parts: Iterable[Sequence[UpdateInfo]] = ()) -> None:
        self.parts: list[Sequence[UpdateInfo]] = []
        self._n = 0
        for p in parts:
            self += p

    def __iadd__(self, other: Iterable[UpdateInfo]) -> Updates:
        if isinstance(other, Updates):
            self.parts += other.parts
            self._n += other._n
        elif isinstance(other, UpdateBatch):
            if len(other):
                self.parts.append(other)
                self._n += len(other)
        else:
            recs = list(other)  # a copy: the caller may go on appending to its list
            if recs:
                self.parts.append(recs)
                self._n += len(recs)
        return self

    def __len__(self) -> int:
        return self._n

    def __iter__(self) -> Iterator[UpdateInfo]:
        return itertools.chain.from_iterable(self.parts)

    def __getitem__(self, i):
        return list(self)[i]

    def __add__(self, other: Iterable[UpdateInfo]) -> list[UpdateInfo]:
        return [*self, *other]

    def __radd__(self, other: Iterable[UpdateInfo]) -> list[UpdateInfo]:
        return [*other, *self]

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Sequence) and not isinstance(other, str) and list(self) == list(other)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"Updates({list(self)!r})"

    def counts(self) -> Counter[tuple[tuple[str, ...], str, bool]]:
        """Number of updates per (vehicles, kind, accepted), batches counted from their columns."""
        return Counter(itertools.chain.from_iterable(
            zip(p.vehicles, repeat(p.kind), repeat(True)) if isinstance(p, UpdateBatch) else map(_VEHICLES_KIND_ACCEPTED, p)
            for p in self.parts))


_VEHICLES_KIND_ACCEPTED = itemgetter(1, 0, 5)  # (vehicles, kind, accepted) of an UpdateInfo


def scalar_update(x: F64, P: F64, idx: NDArray[np.int64], val: F64, innovation: float, r_var: float,
                  gate_k: float | None = None) -> tuple[float, bool]:
    """In-place sequential scalar EKF update with a sparse design row; returns (S, accepted).

    ``p = P h^T`` uses only the columns ``idx`` (O(n k)); ``S = h p + r`` (thesis eq. 3.23);
    rejected without touching x, P if ``|nu| > gate_k sqrt(S)`` (eq. 3.27) or anything is
    non-finite; else ``x += p nu / S``, ``P -= q q^T`` with ``q = p / sqrt(S)`` (= ``k k^T S``
    with ``k = p / S``: eq. 3.16-3.18 in a form that keeps P exactly symmetric). Runs the
    compiled :func:`v2v.estimation.kernels.scalar_update` (one pass over P, no
    temporaries); x and P must be writable C-contiguous float64 arrays, P symmetric.
    """
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    val = np.ascontiguousarray(val, dtype=np.float64)
    s, status = kernels.scalar_update(x, P, idx, val, len(idx), float(innovation), float(r_var),
                                      0.0 if gate_k is None else float(gate_k), gate_k is not None)
    return s, status == kernels.ACCEPTED


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
    # compiled (v2v.estimation.kernels.screen_blunders): per iteration N = H^T H, its
    # condition number (Jacobi eigenvalues), N^-1 H^T (small LU), the residuals and w of
    # the remaining measurements
    flagged, isolated = kernels.screen_blunders(np.ascontiguousarray(h, dtype=np.float64),
                                                np.ascontiguousarray(r, dtype=np.float64), float(sigma), float(k))
    return flagged, bool(isolated)


def cond_sym(a: F64) -> float:
    """2-norm condition number of a small symmetric matrix: ``np.linalg.cond(a)`` to round-off
    (compiled Jacobi rotations, :func:`v2v.smallmat.cond2_symmetric`, instead of an SVD); inf
    when ``a`` is singular or not finite."""
    a = np.ascontiguousarray(a, dtype=np.float64)
    if not np.isfinite(a).all():
        return math.inf
    c = float(cond2_symmetric(a))
    return c if c == c else math.inf  # 0 / 0 of a zero matrix


class NisWindow:
    """The last ``size`` SD-pseudorange innovation tests of one vehicle, ``(NIS, accepted)``
    oldest first (:attr:`tests`), how many of them were rejected (:attr:`rejected`) and the
    sum of their NIS, each capped at ``cap`` (:attr:`nis_sum`), both kept up to date as tests
    enter and leave: the divergence test reads them instead of going through the window
    every epoch. The filter's cap is its gate, k^2: a rejected test (a blunder of any size, a
    1 ms clock jump's NIS of ~1e9) counts as the largest NIS a test can pass with, so a
    few blunders cannot make the mean, and the sum's additions and subtractions stay among
    numbers of one size."""

    __slots__ = ("tests", "rejected", "nis_sum", "cap")

    def __init__(self, size: int, cap: float = math.inf) -> None:
        self.tests: deque[tuple[float, bool]] = deque(maxlen=size)
        self.rejected = 0
        self.nis_sum = 0.0
        self.cap = cap

    def __len__(self) -> int:
        return len(self.tests)

    def add(self, nis: float, accepted: bool) -> None:
        t = self.tests
        if len(t) == t.maxlen:  # the oldest leaves
            old, ok = t[0]
            self.nis_sum -= self._capped(old)
            if not ok:
                self.rejected -= 1
        t.append((nis, accepted))
        self.nis_sum += self._capped(nis)
        if not accepted:
            self.rejected += 1

    def add_accepted(self, nis: list[float]) -> None:
        """Accepted tests with these NIS values, in order."""
        t = self.tests
        leaving = len(t) + len(nis) - (t.maxlen or 0)  # the oldest tests pushed out
        if leaving > 0:
            for old, ok in itertools.islice(t, min(leaving, len(t))):
                self.nis_sum -= self._capped(old)
                if not ok:
                    self.rejected -= 1
        kept = nis[-t.maxlen:] if t.maxlen is not None and len(nis) > t.maxlen else nis
        self.nis_sum += sum(map(self._capped, kept))
        t.extend(zip(nis, repeat(True)))

    def _capped(self, nis: float) -> float:
        return nis if nis <= self.cap else self.cap  # (NaN: not <=, capped too)


class ClusterFilterBase(ABC):
    """Sequencing, gating and initialization shared by both engines.

    Engines implement: ``_predict_core(dt)``, ``_apply(row, z, r_var, wrap, test)``,
    ``_set_block(s, mean, cov)``, ``_get_x()``, ``_get_P()``, ``_replace(x, P)``; and may
    replace the per-measurement Python sequences ``_uwb_sequence``, ``_bearing_sequence``
    (one call per batch, same records), ``update_uwb_events`` and the per-epoch GNSS hooks
    ``_sd_pseudoranges_all``, ``_sd_dopplers_all`` (all vehicles in one call).
    """

    def __init__(self, layout: StateLayout, config: FilterConfig | None = None):
        self.layout = layout
        self.config = config or FilterConfig()
        self._k = self.config.gate_k
        self.counters: dict[str, int] = {}
        self.integrity_available: dict[str, bool] = {}
        self._nis_window: dict[str, NisWindow] = {}
        # divergence test fired (vehicle -> its epoch time then): reset once a snapshot confirms it
        self._suspect: dict[str, float] = {}
        self._vehicle_ready = {v: False for v in layout.vehicles}
        self._azimuth_ready = {v: False for v in layout.azimuth_vehicles}
        pc = self.config.phase
        self._slips = SlipDetector(pc.slip_threshold_m, pc.max_gap_s) if pc is not None else None
        self._phase_streak: dict[tuple[str, int], int] = {}
        self._amb_since: dict[tuple[str, int], float] = {}  # time each SD ambiguity was added
        #: ambiguity-resolution status per vehicle after the last GNSS epoch (carrier-phase solutions)
        self.phase_status: dict[str, PhaseStatus] = {}
        #: vehicles whose last GNSS epoch gave fewer than 4 accepted SD pseudoranges
        self.gnss_weak: dict[str, bool] = {}
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

    def state_arrays(self) -> tuple[F64, F64]:
        """The state and covariance arrays themselves, not copies (:attr:`x` and :attr:`P` copy):
        for a reader that neither modifies nor keeps them (the per-epoch error rows)."""
        return self._get_x(), self._get_P()

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
        self._suspect.pop(v, None)
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
                    lead_base_vel_ecef_mps: F64 | None = None) -> Updates:
        """SD pseudorange (and Doppler) updates from one epoch of every vehicle's receiver.

        ``lead_base_ecef_m``: the lead's standalone position (paper eq. 7: its error barely
        matters). Vehicles outside the layout are ignored; uninitialized vehicles are
        initialized from this epoch when possible.
        """
        all_epochs = epochs  # (the carrier phase's slip detector sees every signal)
        if self.config.gnss_cn0_mask_dbhz > 0.0:
            epochs = self._cn0_masked(epochs)
        geo = GnssGeometry(base_ecef_m=np.asarray(lead_base_ecef_m, dtype=float),
                           base_vel_ecef_mps=np.zeros(3) if lead_base_vel_ecef_mps is None
                           else np.asarray(lead_base_vel_ecef_mps, dtype=float))
        lay = self.layout
        lead_ep = epochs.get(lay.lead)
        infos = Updates()
        just_initialized: set[str] = set()
        self.integrity_available = dict.fromkeys(lay.vehicles, False)
        # covariance growth beyond any use (position sigma = sqrt of the position block's trace
        # above divergence_position_sigma_m): start again from this snapshot; a reset erases
        # only its own block, so all vehicles' sigmas are read first
        ready = [v for v in lay.vehicles if self._vehicle_ready[v]]
        if ready:  # (scalar floats: the same sums and square roots as array ufuncs, without their overhead)
            d = np.diagonal(self._get_P()).tolist()
            thr = self.config.divergence_position_sigma_m
            starts = lay.position_starts
            diverged = [v for v in ready if math.sqrt(max(d[starts[v]] + d[starts[v] + 1] + d[starts[v] + 2], 0.0)) > thr]
            for v in diverged:
                self._reset_vehicle(v)
        per_vehicle: dict[str, tuple[GnssEpoch, NDArray, NDArray, F64]] = {}
        skipped: set[str] = set()  # ready vehicles with fewer common satellites than gnss_min_satellites
        pr_jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]] = []  # ready vehicles: (v, epoch, iv, il)
        if lead_ep is not None:
            lead_prn = np.asarray(lead_ep.prn, dtype=np.int64)
            lead_pr = np.asarray(lead_ep.pseudorange_m, dtype=np.float64)
            lead_sv = np.ascontiguousarray(lead_ep.sv_pos_ecef_m, dtype=np.float64).reshape(-1, 3)
        have = [v for v in lay.vehicles if v in epochs] if lead_ep is not None else []
        if have:
            # every vehicle's common satellites with the lead (np.intersect1d order), finite
            # pseudoranges, highest elevation first: kernels.pair_satellites, all in one call
            eps_v = [epochs[v] for v in have]
            prn_cat, pr_cat, row0 = _cati([ep.prn for ep in eps_v]), _cat1([ep.pseudorange_m for ep in eps_v]), \
                _offsets([len(ep.prn) for ep in eps_v])
            iv_cat, il_cat, el_cat, moff_v, bad_v = kernels.pair_satellites_all(
                prn_cat, pr_cat, row0, lead_prn, lead_pr, lead_sv, geo.base_ecef_m, geo.rot_ecef_to_enu)
            mo = moff_v.tolist()
        for j, v in enumerate(have):
            assert lead_ep is not None  # (have is empty without the lead's epoch)
            ep = epochs[v]
            a, b = mo[j], mo[j + 1]
            iv, il, el = iv_cat[a:b], il_cat[a:b], el_cat[a:b]
            for _ in range(int(bad_v[j])):
                self._count(f"nonfinite_{KIND_SD_PR}")
            per_vehicle[v] = (ep, iv, il, el)
            if not self._vehicle_ready[v]:
                if self._initialize_vehicle(v, geo, ep, lead_ep, iv, il):
                    just_initialized.add(v)
                continue
            if v in self._suspect and self._confirm_divergence(v, geo, ep, lead_ep, iv, il):
                just_initialized.add(v)  # reset to this epoch's snapshot
                continue
            if len(iv) < self.config.gnss_min_satellites:
                skipped.add(v)  # too few to screen: its GNSS is left out of this epoch
                self._count("gnss_too_few_satellites")
                continue
            pr_jobs.append((v, ep, iv, il))
        # (an initialization sets a block uncorrelated with the others, and a divergence reset
        # erases one: neither changes another vehicle's update, so they may come first / last)
        if pr_jobs and lead_ep is not None:
            # every paired vehicle a job (the usual epoch): the jobs' gathers are the pairing's
            pairing = _Pairing(prn_cat, pr_cat, row0, iv_cat, il_cat, moff_v) if len(pr_jobs) == len(have) else None
            infos += self._sd_pseudoranges_all(geo, lead_ep, pr_jobs, pairing)
        for v, ep, *_ in pr_jobs:
            if self._window_diverged(v):
                self._inflate(v)
                # reset when a snapshot confirms it (_confirm_divergence); a second trip while
                # suspect inflates again and keeps the first trip's time
                self._suspect.setdefault(v, ep.t_s)
                self._count("divergence_suspected")
        # pair SDs need a satellite the lead does not see (finite); none when the pairing kept
        # every satellite of every vehicle (the usual open-sky epoch): nothing to look for. (A
        # vehicle's kept satellites are a subset of its rows, so equal totals mean every
        # vehicle kept all of its rows.)
        if self.config.use_pair_sd and not (have and int(moff_v[-1]) == int(row0[-1])):
            infos += self._pair_sds({v: e for v, e in epochs.items() if v not in skipped} if skipped else epochs,
                                    lead_ep, geo)
        if self.config.use_doppler and lead_ep is not None:
            jobs = [(v, ep, iv, il) for v, (ep, iv, il, _) in per_vehicle.items()
                    if self._vehicle_ready[v] and v not in just_initialized and v not in skipped]
            if jobs:
                infos += self._sd_dopplers_all(geo, lead_ep, jobs)
        code_ok: dict[str, set[int]] = {}  # accepted SD pseudoranges: only the carrier phase uses them
        code_rejected: dict[str, set[int]] = {}  # tested and rejected (not masked, not missing)
        if self.config.phase is not None:
            for info in infos:
                if info.kind == KIND_SD_PR:
                    (code_ok if info.accepted else code_rejected).setdefault(info.vehicles[0], set()).add(info.prn)
        # Fewer than 4 SD pseudoranges (satellites seen by both): the epoch cannot fix the
        # relative position, so add "relative up = h_v - h_lead" as in epochs without GNSS (MacGougan
        # (2009) section 5: "a height constraint was employed when fewer than 4 GPS satellites
        # were available"); UWB and bearings are then no longer deferred for nonlinearity
        # (:meth:`_nonlinear_fraction`).
        self.gnss_weak = {v: v not in per_vehicle or len(per_vehicle[v][1]) < 4 or v in skipped for v in lay.vehicles}
        if self.config.height_aiding_sigma_m is not None:
            weak = [v for v in lay.vehicles if self.gnss_weak[v] and v not in just_initialized]
            if weak:
                infos += self.update_height_aiding(self.config.height_aiding_sigma_m, weak)
        if self.config.phase is not None:
            infos += self._update_phase(all_epochs, all_epochs.get(lay.lead), geo, code_ok, code_rejected)
        return infos

    def _cn0_masked(self, epochs: dict[str, GnssEpoch]) -> dict[str, GnssEpoch]:
        """Each receiver's epoch without its signals below ``config.gnss_cn0_mask_dbhz``
        (counted ``gnss_cn0_masked``); epochs with none below are passed on as they are."""
        mask = self.config.gnss_cn0_mask_dbhz
        out: dict[str, GnssEpoch] = {}
        for v, ep in epochs.items():
            keep = np.asarray(ep.cn0_dbhz, dtype=float) >= mask  # (NaN C/N0: masked)
            n_drop = ep.n - int(np.count_nonzero(keep))
            if n_drop:
                self.counters["gnss_cn0_masked"] = self.counters.get("gnss_cn0_masked", 0) + n_drop
                ep = ep.select(keep)
            out[v] = ep
        return out

    def gnss_unavailable(self) -> None:
        """No usable GNSS epoch in this output interval (an outage of everyone, or the lead
        without a fix): no vehicle has integrity (no screen ran) until the next
        :meth:`update_gnss`.

        :attr:`gnss_weak` keeps the last epoch's value on purpose: ranges and bearings stay
        deferred while P is too wide for their linearization, and the solution dead-reckons.
        Treating an outage like a weak epoch (no deferral) was measured worse: in a 10 s
        outage of 3 cars on open_highway, GPS+Bearing's along-track error reached 190 m at
        sigma 30 m and GPS+UWB's 45 m at sigma 23 m (deferring: 5 m and 0.2 m, sigma ~50 m);
        GPS+UWB+Bearing, never deferred, was the same either way."""
        self.integrity_available = dict.fromkeys(self.layout.vehicles, False)

    # ----------------------------------------------------------------- carrier phase
    def _update_phase(self, epochs: dict[str, GnssEpoch], lead_ep: GnssEpoch | None,
                      geo: GnssGeometry, code_ok: dict[str, set[int]],
                      code_rejected: dict[str, set[int]] | None = None) -> list[UpdateInfo]:
        """SD carrier-phase updates of every vehicle, then ambiguity resolution
        (:mod:`v2v.estimation.phase`: lifecycle, slips, LAMBDA, fix-and-hold).

        ``code_ok[v]``: satellites whose SD pseudorange of ``v`` passed its innovation test
        this epoch. Only their phases are used: an echo-only signal has the same excess
        path on code and carrier, and a fresh ambiguity on it would absorb that excess and
        be "fixed" at once when the position is already fixed; its code, metres off, is
        what the innovation test catches. ``code_rejected[v]``: those whose SD pseudorange was
        tested and rejected. An existing ambiguity whose code is rejected while
        both receivers keep tracking the satellite without a slip keeps its state (counted
        ``phase_skipped_code_rejected``) and its phase is left out of the epoch: at alpha =
        0.001 a clean code fails ~1 test in 1000, and dropping the arc for it restarted that
        satellite's minimum lock time. A real change of path (a LOS <-> echo switch, an echo
        moving to another wall) starts a new carrier arc at the receiver, which the slip
        detector's loss of lock catches; an undetected one is caught by the phases' own
        test (``reset_after_rejections``)."""
        pc = self.config.phase
        assert pc is not None and self._slips is not None
        slipped = {v: set(ep.prn[self._slips.update(ep)].tolist()) for v, ep in epochs.items()}
        self.phase_status = {}
        lay = self.layout

        def usable(ep: GnssEpoch) -> dict[int, int]:
            ok = (np.isfinite(ep.carrier_cycles) & np.isfinite(ep.pseudorange_m)
                  & (ep.elevation_rad >= pc.elevation_mask_rad) & (ep.cn0_dbhz >= pc.cn0_mask_dbhz))
            bad = slipped.get(ep.vehicle_id, set())
            return {p: i for i, p in enumerate(ep.prn.tolist()) if ok[i] and p not in bad}

        lead_ok = usable(lead_ep) if lead_ep is not None else {}
        drop: list[tuple[str, tuple[str, int]]] = []
        adds: list[tuple[tuple[str, int], Row, float]] = []
        plan: dict[str, tuple[GnssEpoch, dict[int, int]]] = {}
        x = self._get_x()
        for v in lay.vehicles:
            have = {k[1] for k in lay.ambiguity_keys(v)}
            ep = epochs.get(v)
            if ep is None or lead_ep is None or not self._vehicle_ready[v]:
                drop += [(AMBIGUITY, (v, p)) for p in have]
                continue
            ok_code = code_ok.get(v, set())
            both = {p: i for p, i in usable(ep).items() if p in lead_ok}
            mine = {p: i for p, i in both.items() if p in ok_code}
            rejected = code_rejected.get(v, set()) if code_rejected else set()
            for p in have - mine.keys():
                if p in both and p in rejected:  # tracked without a slip, its code tested and rejected:
                    # the arc is kept, its phase unused this epoch
                    self._count("phase_skipped_code_rejected")
                    continue
                drop.append((AMBIGUITY, (v, p)))
                self._count("phase_slip" if p in slipped.get(v, set()) | slipped.get(lay.lead, set())
                            else "phase_lost")
            for p in sorted(mine.keys() - have):
                i, j = mine[p], lead_ok[p]
                r = sd_range_row(x, lay, geo, v, ep.sv_pos_ecef_m[i], lead_ep.sv_pos_ecef_m[j])
                z = LAMBDA_L1_M * (float(ep.carrier_cycles[i]) - float(lead_ep.carrier_cycles[j]))
                adds.append(((v, p), r, z - r.h))
                self._amb_since[(v, p)] = float(ep.t_s)
            plan[v] = (ep, mine)
        self._drop_ambiguities(drop)
        self._add_ambiguities(adds, pc.sd_phase_var_m2)
        new_now = {key for key, _, _ in adds}
        if lead_ep is None:
            return []
        out: list[UpdateInfo] = []
        r_var = pc.sd_phase_var_m2
        for v, (ep, mine) in plan.items():
            order, flagged = self._phase_order(v, ep, lead_ep, geo, mine, lead_ok, r_var)
            self._phase_common_mode(v, ep, lead_ep, geo, mine, lead_ok, r_var,
                                    [p for p in order if (v, p) not in new_now and p not in flagged])
            results = []
            for p in order:
                if (v, p) in new_now:
                    continue  # its first measurement made the ambiguity (_add_ambiguities)
                i, j = mine[p], lead_ok[p]
                row = sd_phase_row(self._get_x(), self.layout, geo, v, p, ep.sv_pos_ecef_m[i],
                                   lead_ep.sv_pos_ecef_m[j])
                z = LAMBDA_L1_M * (float(ep.carrier_cycles[i]) - float(lead_ep.carrier_cycles[j]))
                if p in flagged:
                    info = self._excluded(KIND_SD_PHASE, (v,), row, z, r_var, p)
                else:
                    info = self._scalar(KIND_SD_PHASE, (v,), row, z, r_var, prn=p)
                if info is None:
                    continue
                out.append(info)
                results.append((p, info.accepted))
                key = (v, p)
                self._phase_streak[key] = 0 if info.accepted else self._phase_streak.get(key, 0) + 1
            n_rej = sum(not a for _, a in results)
            if len(results) >= 2 and 2 * n_rej > len(results):
                # most of the vehicle's phases disagree with its state: a wrong fix or an
                # undetected slip of the first one -> restart all its ambiguities
                self._count("ambiguity_reset")
                self._drop_ambiguities([(AMBIGUITY, k) for k in self.layout.ambiguity_keys(v)])
            else:
                stale = [(AMBIGUITY, (v, p)) for p, _ in results
                         if self._phase_streak.get((v, p), 0) >= pc.reset_after_rejections]
                if stale:
                    self._count("phase_reset_rejected")
                    self._drop_ambiguities(stale)
        if pc.resolve:
            out += self._resolve_ambiguities(plan)
        return out

    def _phase_order(self, v: str, ep: GnssEpoch, lead_ep: GnssEpoch, geo: GnssGeometry, mine: dict[int, int],
                     lead_ok: dict[int, int], r_var: float) -> tuple[list[int], set[int]]:
        """Order of v's phase updates and the phases the screen leaves out.

        The first-update clock problem (thesis eq. 3.28-3.29) is worse for phase than for
        code: after the code updates the SD clock is known to decimetres, so the first two or
        three phases are tested against decimetre S and a slip of one cycle (0.19 m) that both
        slip tests missed would pass and corrupt the clock. So, as for the pseudoranges, the
        phases of satellites whose ambiguity is already resolved (variance < 0.05^2 cycles^2)
        are screened together first by data snooping (:func:`screen_blunders_status` on
        position + clock, ambiguities held at their values); flagged ones are left out (and
        counted rejected, so that ``reset_after_rejections`` replaces their ambiguity). Order:
        the resolved ones from the highest elevation down, then the float ones.
        """
        x, P = self._get_x(), self._get_P()
        el = {p: float(ep.elevation_rad[i]) for p, i in mine.items()}
        by_el = sorted(mine, key=lambda p: -el[p])
        # resolved = DD ambiguity against the highest satellite known to < 0.05 cycles (the SD
        # ambiguities themselves share the SD clock's uncertainty: only differences are sharp)
        ia = {p: self.layout.ambiguity(v, p) for p in by_el}
        q = ia[by_el[0]] if by_el else 0
        held = [p for p in by_el[1:] if P[ia[p], ia[p]] + P[q, q] - 2.0 * P[ia[p], q] < 0.05**2]
        held = [by_el[0]] + held if held else []
        flagged: set[int] = set()
        if len(held) >= 6:  # position + clock + redundancy 2 (as the code screen)
            h = np.empty((len(held), 4))
            res = np.empty(len(held))
            for k, p in enumerate(held):
                i, j = mine[p], lead_ok[p]
                row = sd_phase_row(x, self.layout, geo, v, p, ep.sv_pos_ecef_m[i], lead_ep.sv_pos_ecef_m[j])
                h[k] = row.val[:4]
                res[k] = LAMBDA_L1_M * (float(ep.carrier_cycles[i]) - float(lead_ep.carrier_cycles[j])) - row.h
            mask, _ = screen_blunders_status(h, res, math.sqrt(r_var), self._k)
            flagged = {p for p, f in zip(held, mask.tolist(), strict=True) if f}
            if flagged:
                self._count("phase_screened")
        rest = [p for p in by_el if p not in held]
        return held + rest, flagged

    def _phase_common_mode(self, v: str, ep: GnssEpoch, lead_ep: GnssEpoch, geo: GnssGeometry,
                           mine: dict[int, int], lead_ok: dict[int, int], r_var: float, prns: list[int]) -> bool:
        """Common-mode test of ``v``'s SD phase innovations before their sequential tests.

        The SD clock is re-estimated from this epoch's code (the loose clock model forgets the
        phase-derived clock in one 0.1 s prediction: sigma ~8 m), so every phase innovation
        carries the code clock's error (~0.25 m with 8 satellites) and they are ~100 %
        correlated until the first phase is used. The first phase's gate is then a test of the
        *code* clock: it fails at rate alpha per vehicle-epoch under H0, every other phase is
        rejected with it, and the "most phases rejected" rule reads one 3.3-sigma code event
        as a wrong fix. A common mode cannot come from a wrong DD integer (it is absorbed by
        the SD clock). So, as :meth:`_clock_jump` for pseudoranges: when more than half fail the
        gate with one sign and a majority pass after removing the median ``m``, the clock's
        variance is widened by ``m^2`` (additive, like process noise; correlations kept) and the
        phases then go through the normal sequential tests (the first sets the clock, the
        others are tested at millimetre S, so a DD fault is still caught). Counted
        ``phase_clock_common_mode``."""
        if len(prns) < 3:
            return False
        lay = self.layout
        x = self._get_x()
        rows = [sd_phase_row(x, lay, geo, v, p, ep.sv_pos_ecef_m[mine[p]], lead_ep.sv_pos_ecef_m[lead_ok[p]])
                for p in prns]
        n = len(rows)
        idx = np.r_[rows[0].idx[:4], [int(r.idx[4]) for r in rows]].astype(np.int64)  # position, clock, ambiguities
        val = np.zeros((n, 4 + n))
        for k, r in enumerate(rows):
            val[k, :4] = r.val[:4]
            val[k, 4 + k] = r.val[4]
        h = np.array([r.h for r in rows])
        z = np.array([LAMBDA_L1_M * (float(ep.carrier_cycles[mine[p]]) - float(lead_ep.carrier_cycles[lead_ok[p]]))
                      for p in prns])
        jump, m = kernels.clock_jump_test(self._get_P(), idx, h, val, z, float(r_var), self._k)
        if not jump:
            return False
        i = lay.clock(v)
        x2, P2 = self._get_x().copy(), self._get_P().copy()
        P2[i, i] += float(m) ** 2
        self._replace(x2, P2)
        self._count("phase_clock_common_mode")
        return True

    def _resolve_ambiguities(self, plan: dict[str, tuple[GnssEpoch, dict[int, int]]]) -> list[UpdateInfo]:
        """LAMBDA partial fixing per vehicle and fix-and-hold (:func:`v2v.estimation.phase.resolve_vehicle`)."""
        pc = self.config.phase
        assert pc is not None
        out: list[UpdateInfo] = []
        hold_var = pc.fix_hold_sigma_cycles**2
        for v, (ep, mine) in plan.items():
            el = {p: float(ep.elevation_rad[i]) for p, i in mine.items()}
            t = float(ep.t_s)
            old = {p for _, p in self.layout.ambiguity_keys(v)
                   if t - self._amb_since.get((v, p), t) >= pc.ar_min_lock_s - 1e-9}
            st, todo = resolve_vehicle(self._get_x(), self._get_P(), self.layout, v, el, pc, old)
            self.phase_status[v] = st
            for idx, coef, val in todo:
                row = Row(float(coef @ self._get_x()[idx]), idx, coef)
                info = self._scalar(KIND_AMB_FIX, (v,), row, val, hold_var, test=False)
                if info is not None:
                    self._count("ambiguity_fix_applied")
        return out

    def _drop_ambiguities(self, drop: list[tuple[str, tuple[str, int]]]) -> None:
        """Remove (marginalize) SD ambiguity blocks."""
        if not drop:
            return
        new, remap = self.layout.without_blocks(drop)
        x, P = remap(self._get_x(), self._get_P())
        self.layout = new
        self._replace(x, P)
        for _, key in drop:
            self._phase_streak.pop(key, None)
            self._amb_since.pop(key, None)

    def _add_ambiguities(self, adds: list[tuple[tuple[str, int], Row, float]], r_var: float) -> None:
        """New SD ambiguities from their first phase: ``a = nu / lambda`` (``nu = z - h_0(x)``),
        ``Cov(a, .) = -P H^T / lambda``, ``Var(a) = (H P H^T + r) / lambda^2`` (module
        :mod:`v2v.estimation.phase`). Taken in turn, so two new ambiguities of one vehicle get
        their covariance ``H_i P H_j^T / lambda^2`` through the rows already set."""
        if not adds:
            return
        keys = [k for k, _, _ in adds]
        new, remap = self.layout.with_blocks(AMBIGUITY, keys, mean=np.zeros(len(keys)), variance=np.zeros(len(keys)))
        x, P = remap(self._get_x(), self._get_P())
        self.layout = new
        lam = LAMBDA_L1_M
        for key, row, nu in adds:
            ia = new.ambiguity(*key)
            ph = P[:, row.idx] @ row.val
            x[ia] = nu / lam
            P[ia, :] = -ph / lam
            P[:, ia] = -ph / lam
            P[ia, ia] = (float(row.val @ ph[row.idx]) + r_var) / lam**2
        self._replace(x, P)

    def _first_unflagged_order(self, h_pred: F64, val: F64, z: F64, sigma: float,
                               cols: int) -> tuple[NDArray[np.int64], NDArray[np.bool_], bool]:
        """Elevation order with the highest-elevation w-test-clean measurement moved first.

        ``h_pred`` (m,) predicted measurements, ``val`` (m, k) their Jacobian rows (one
        vehicle's rows: same indices); the screen uses the last ``cols`` columns.
        Returns (order, excluded, isolated): ``excluded`` marks the flagged measurements when
        more than one was flagged (all left out); ``isolated`` is the screen's
        :func:`screen_blunders_status` (False when it could not run).
        """
        order, excluded, isolated, n_flagged = kernels.first_unflagged_order(
            np.ascontiguousarray(h_pred, dtype=np.float64), np.ascontiguousarray(val, dtype=np.float64),
            np.ascontiguousarray(z, dtype=np.float64), float(sigma), self._k, int(cols))
        if n_flagged:
            self.counters["screened_first_update"] = self.counters.get("screened_first_update", 0) + int(n_flagged)
        return order, excluded, bool(isolated)

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
        jump, m = kernels.clock_jump_test(self._get_P(), np.ascontiguousarray(idx, dtype=np.int64), h_pred, val,
                                          np.ascontiguousarray(z, dtype=np.float64), float(r_var), self._k)
        if not jump:
            return False
        m = float(m)
        i = self.layout.clock(v)
        clk = float(self._get_x()[i])
        self._set_block(slice(i, i + 1), np.array([clk + m]), np.array([[self.config.clock_reset_sigma_m**2]]))
        self._nis_window.pop(v, None)
        self._count("clock_jump_detected")
        return True

    def _window(self, v: str) -> NisWindow:
        w = self._nis_window.get(v)
        if w is None:
            w = self._nis_window[v] = NisWindow(self.config.divergence_window, self._k**2)
        return w

    def _record_test(self, v: str, info: UpdateInfo) -> None:
        self._window(v).add(info.nis, info.accepted)

    def _record_tests(self, v: str, infos: Sequence[UpdateInfo]) -> None:
        """:meth:`_record_test` of several records in order."""
        if isinstance(infos, UpdateBatch):
            self._record_accepted_nis(v, infos.nis.tolist())
        else:
            w = self._window(v)
            for nis, accepted in map(_nis_accepted, infos):
                w.add(nis, accepted)

    def _record_accepted_nis(self, v: str, nis: list[float]) -> None:
        """:meth:`_record_tests` of accepted records given by their NIS values."""
        self._window(v).add_accepted(nis)

    def window_mean_nis(self, v: str) -> float:
        """Mean NIS of the last ``divergence_window`` SD-pseudorange tests of ``v`` (NaN if none)."""
        w = self._nis_window.get(v)
        return float(np.mean([n for n, _ in w.tests])) if w else float("nan")

    def window_nis_band(self, v: str, prob: float = 0.999) -> tuple[float, float]:
        """Two-sided ``prob`` chi-square band of :meth:`window_mean_nis` under H0."""
        n = len(self._nis_window.get(v, ())) or 1
        # chi-square quantiles 2 gammaincinv(n/2, p) (= scipy.stats.chi2.ppf, without its import cost)
        lo, hi = 2.0 * special.gammaincinv(n / 2.0, np.array([(1.0 - prob) / 2.0, (1.0 + prob) / 2.0])) / n
        return float(lo), float(hi)

    def _window_diverged(self, v: str) -> bool:
        w = self._nis_window.get(v)
        if w is None or len(w.tests) < self.config.divergence_window:
            return False
        n = len(w.tests)
        return w.rejected > self.config.divergence_reject_fraction * n or w.nis_sum > self.config.divergence_mean_nis * n

    def _reset_vehicle(self, v: str) -> None:
        """Back to the uninitialized prior; the next GNSS snapshot re-initializes the block."""
        self._set_block(self.layout.block(VEHICLE, v), np.zeros(8),
                        np.eye(8) * self.config.uninitialized_variance)
        self._vehicle_ready[v] = False
        self._nis_window.pop(v, None)
        self._suspect.pop(v, None)
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
        out = self._pseudorange_sequence(v, rows, z, order, excluded, ep.prn[iv], r_var)
        for info in out:
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
        return self._doppler_sequence(v, rows, z, order, excluded, ep.prn[iv], r_var)

    def _pseudorange_sequence(self, v: str, rows: models.SdPseudorangeRows, z: F64, order: NDArray[np.int64],
                              excluded: NDArray[np.bool_], prns: NDArray, r_var: float) -> list[UpdateInfo]:
        """Engine hook (default: :meth:`_row_sequence`). Same records as the loop of
        :meth:`_sd_pseudoranges` (which records the tests in the NIS window afterwards)."""
        return self._row_sequence(KIND_SD_PR, v, rows, z, order, excluded, prns, r_var)

    def _doppler_sequence(self, v: str, rows: models.SdDopplerRows, z: F64, order: NDArray[np.int64],
                          excluded: NDArray[np.bool_], prns: NDArray, r_var: float) -> list[UpdateInfo]:
        """Engine hook (default: :meth:`_row_sequence`)."""
        return self._row_sequence(KIND_SD_DOPPLER, v, rows, z, order, excluded, prns, r_var)

    def _row_sequence(self, kind: str, v: str, rows: models.SdPseudorangeRows | models.SdDopplerRows, z: F64,
                      order: NDArray[np.int64], excluded: NDArray[np.bool_], prns: NDArray,
                      r_var: float) -> list[UpdateInfo]:
        """One Python scalar update per measurement of one vehicle: ``rows`` in ``order``, each
        re-linearized at the current state; ``excluded`` ones reported as rejected."""
        out = []
        zl = z.tolist()
        prn_l = prns.tolist()
        for o in order.tolist():
            row = rows.row(self._get_x(), o)
            if excluded[o]:
                info = self._excluded(kind, (v,), row, zl[o], r_var, prn_l[o])
            else:
                info = self._scalar(kind, (v,), row, zl[o], r_var, prn=prn_l[o])
            if info is not None:
                out.append(info)
        return out

    def _sd_pseudoranges_all(self, geo: GnssGeometry, lead_ep: GnssEpoch,
                             jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]],
                             pairing: _Pairing | None = None) -> Sequence[UpdateInfo]:
        """Engine hook: :meth:`_sd_pseudoranges` of every ``(v, epoch, iv, il)`` in order
        (``pairing``: the epoch's satellite pairing, when the jobs are all its vehicles in its order)."""
        return [info for v, ep, iv, il in jobs for info in self._sd_pseudoranges(v, geo, ep, lead_ep, iv, il)]

    def _sd_dopplers_all(self, geo: GnssGeometry, lead_ep: GnssEpoch,
                         jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]]) -> Sequence[UpdateInfo]:
        """Engine hook: :meth:`_sd_dopplers` of every ``(v, epoch, iv, il)`` in order."""
        return [info for v, ep, iv, il in jobs for info in self._sd_dopplers(v, geo, ep, lead_ep, iv, il)]

    def _pair_sds(self, epochs: dict[str, GnssEpoch], lead_ep: GnssEpoch | None,
                  geo: GnssGeometry) -> list[UpdateInfo]:
        """SDs between two non-lead vehicles for satellites the lead does not see (or, with
        ``gnss_cn0_mask_dbhz``, sees below the mask)."""
        lay = self.layout
        ready = [v for v in lay.vehicles if self._vehicle_ready[v] and v in epochs]
        if len(ready) < 2:
            return []
        lead_seen: set[int] = set()
        if lead_ep is not None:
            lead_seen = set(lead_ep.prn[np.isfinite(lead_ep.pseudorange_m)].tolist())
        # candidates of all ready vehicles at once: finite, a satellite the lead does not see
        prn_cat = _cati([epochs[v].prn for v in ready])
        seen_by_lead = np.fromiter(map(lead_seen.__contains__, prn_cat.tolist()), dtype=np.bool_, count=len(prn_cat))
        cand = np.flatnonzero(np.isfinite(_cat1([epochs[v].pseudorange_m for v in ready])) & ~seen_by_lead)
        if len(cand) < 2:
            return []
        row0 = _offsets([len(epochs[v].prn) for v in ready])
        veh = np.searchsorted(row0, cand, side="right") - 1
        # prn -> list of (vehicle, index), vehicles in layout order
        seen: dict[int, list[tuple[str, int]]] = {}
        for j, r, prn in zip(veh.tolist(), cand.tolist(), prn_cat[cand].tolist(), strict=True):
            seen.setdefault(prn, []).append((ready[j], r - int(row0[j])))
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
        snap = self._snapshot(v, geo, ep, lead_ep, iv, il, count=True)
        if snap is None:
            return False
        self._set_block(self.layout.block(VEHICLE, v), snap[0], snap[1])
        self._vehicle_ready[v] = True
        self._count("initialized_vehicles")
        return True

    def _confirm_divergence(self, v: str, geo: GnssGeometry, ep: GnssEpoch, lead_ep: GnssEpoch,
                            iv: NDArray, il: NDArray) -> bool:
        """A suspect vehicle (its divergence test fired and inflated its covariance) against
        this epoch's snapshot. Reset to the snapshot (True, counted ``divergence_reset``: this
        epoch's pseudoranges and Dopplers are in the block's covariance and are not used again
        in an update, as after an initialization) when it can be trusted and disagrees with the
        state, or, ``divergence_confirm_s`` after the trip, to any snapshot (the
        ``init_min_satellites`` of an initialization). A trusted snapshot that agrees clears
        the suspicion (``divergence_cleared``) and the state is kept with its inflated
        covariance. Else wait (False both times).

        Trusted: at least 5 satellites left after the blunder screen (one redundant, so that a
        single echo or blunder shows) and its residuals' sum of squares inside the chi-square
        bound (1 - alpha, n - 4 dof). Disagrees: the position difference's Mahalanobis
        distance, with the state's and the snapshot's covariances added, beyond the chi-square
        (1 - alpha, 3 dof) bound. Why wait: the test fires on wrong pseudoranges as well as on
        a wrong state (an echo-only sky trips the window's mean NIS), and in a street canyon a
        snapshot of 2-4 satellites, mostly echoes, can be worse than a state that UWB ranges
        and bearings hold. Why not for ever: where the state itself has gone (code-only
        solutions among echoes), a trusted snapshot may not come for minutes. Measured (README
        "Fault injection"): immediate reset, no timeout and 1 / 2 / 5 s on the carrier-phase
        canyon drive and ab_compare's urban and faults scenarios; 2 s keeps the canyon's
        gain and most of the urban one."""
        if ep.t_s - self._suspect[v] >= self.config.divergence_confirm_s - 1e-9:
            # waited long enough: the first snapshot there is (init_min_satellites), as a reset
            # to the uninitialized prior would give
            snap = self._snapshot(v, geo, ep, lead_ep, iv, il, count=False)
            if snap is None:
                return False
            mean, cov = snap[0], snap[1]
        else:
            snap = self._snapshot(v, geo, ep, lead_ep, iv, il, count=False, min_used=5)
            if snap is None:
                return False
            mean, cov, chi2_res, dof = snap
            if chi2_res > _chi2_upper(self.config.significance, dof):
                return False
            sl = self.layout.position(v)
            d = self._get_x()[sl] - mean[:3]
            if float(d @ np.linalg.solve(self._get_P()[sl, sl] + cov[:3, :3], d)) <= _chi2_upper(
                    self.config.significance, 3):
                # agrees: the state is kept, with the covariance the trip inflated, and this
                # epoch's pseudoranges update it as usual
                self._suspect.pop(v, None)
                self._count("divergence_cleared")
                return False
        # a reset: the block loses its correlations, and its carrier-phase ambiguities,
        # estimated with them, start afresh (as after a reset to the uninitialized prior)
        if self.config.phase is not None:
            self._drop_ambiguities([(AMBIGUITY, k) for k in self.layout.ambiguity_keys(v)])
        self._reset_vehicle(v)
        self._set_block(self.layout.block(VEHICLE, v), mean, cov)
        self._vehicle_ready[v] = True
        return True

    def _inflate(self, v: str) -> None:
        """Scale v's covariance by its window's capped mean NIS m (its rows and columns by
        sqrt(m)) and empty the window."""
        w = self._nis_window.pop(v, None)
        m = w.nis_sum / len(w.tests) if w is not None and w.tests else 1.0
        if m > 1.0:
            blk = self.layout.block(VEHICLE, v)
            P = self._get_P().copy()
            r = math.sqrt(m)
            P[blk, :] *= r
            P[:, blk] *= r
            self._replace(self._get_x().copy(), P)

    def _snapshot(self, v: str, geo: GnssGeometry, ep: GnssEpoch, lead_ep: GnssEpoch, iv: NDArray, il: NDArray,
                  count: bool, min_used: int = 4) -> tuple[F64, F64, float, int] | None:
        """The snapshot least squares of :meth:`_initialize_vehicle`: the vehicle block's mean and
        covariance, the used pseudoranges' residual sum of squares over their variance and its
        degrees of freedom; None (counted when ``count``) with too few satellites or a bad
        geometry."""
        if len(iv) < max(self.config.init_min_satellites, min_used):
            if count:
                self._count("init_too_few_satellites")
            return None
        lay = self.layout
        sig_pr = np.sqrt(self.config.noise.sd_pseudorange_var_m2)
        z = ep.pseudorange_m[iv] - lead_ep.pseudorange_m[il]
        xt = np.zeros(lay.n)
        pc = np.r_[np.arange(lay.position(v).start, lay.position(v).stop), lay.clock(v)]
        use = np.ones(len(iv), dtype=bool)
        h = np.zeros((0, 4))
        pr_rows = models.SdPseudorangeRows(lay, geo, v, ep.sv_pos_ecef_m[iv], lead_ep.sv_pos_ecef_m[il])
        for it in range(6):
            h_pred, h = pr_rows.all(xt)  # every models.sd_pseudorange row at xt, one compiled call
            res = z - h_pred
            if it == 2:  # screen once the linearization point is good
                use = ~screen_blunders(h, res, sig_pr, self._k)
            n_mat = h[use].T @ h[use]
            if use.sum() < min_used or cond_sym(n_mat) > 1e10:
                if count:
                    self._count("init_bad_geometry")
                return None
            xt[pc] += np.linalg.solve(n_mat, h[use].T @ res[use])
        cov_pc = sig_pr**2 * np.linalg.inv(h[use].T @ h[use])
        h_pred, _ = pr_rows.all(xt)
        chi2_res = float(np.sum((z - h_pred)[use] ** 2)) / sig_pr**2
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
            ivd, ild = iv[okd], il[okd]
            d_rows = models.SdDopplerRows(lay, geo, v, ep.sv_pos_ecef_m[ivd], ep.sv_vel_ecef_mps[ivd],
                                          lead_ep.sv_pos_ecef_m[ild], lead_ep.sv_vel_ecef_mps[ild])
            hd_pred, hd_full = d_rows.all(xt)  # models.sd_doppler rows at xt
            hd = np.ascontiguousarray(hd_full[:, -4:])  # the (velocity, drift) columns
            rd = zd - hd_pred
            used = ~screen_blunders(hd, rd, sig_d, self._k)
            nd = hd[used].T @ hd[used]
            if used.sum() >= 4 and cond_sym(nd) < 1e10:
                # linear in velocity and drift (the tiny position term is held at the PR fix)
                mean[[3, 4, 5, 7]] = np.linalg.solve(nd, hd[used].T @ rd[used])
                cov[np.ix_([3, 4, 5, 7], [3, 4, 5, 7])] = sig_d**2 * np.linalg.inv(nd)
        return mean, 0.5 * (cov + cov.T), chi2_res, int(use.sum()) - 4

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
    def update_uwb(self, ranges: UwbRanges) -> Updates:
        """One scalar update per UWB range (the caller has predicted to the time tag).

        Usable ranges (:meth:`_pair_usable`) go, in measurement order, through the engine's
        :meth:`_uwb_sequence`.
        """
        use = self._usable_pairs(KIND_UWB, ranges.a, ranges.b, ranges.range_m)
        if not use:
            return Updates()
        return Updates([self._uwb_sequence([ranges.a[k] for k in use], [ranges.b[k] for k in use],
                                           np.asarray(ranges.range_m, dtype=float)[use])])

    def update_uwb_events(self, dts_s: Sequence[float], events: Sequence[UwbRanges]) -> list[Sequence[UpdateInfo]]:
        """Several UWB events in a row: for each, :meth:`predict` over ``dts_s[e]`` then
        :meth:`update_uwb` of ``events[e]``; the update records of each event.
        (The production engine runs the whole sequence as one compiled call.)"""
        out: list[Sequence[UpdateInfo]] = []
        for dt, ranges in zip(dts_s, events, strict=True):
            self.predict(dt)
            out.append(self.update_uwb(ranges))
        return out

    def update_uwb_run(self, dts_s: Sequence[float], a: Sequence[str], b: Sequence[str],
                       z: F64) -> tuple[list[int], Sequence[UpdateInfo]]:
        """UWB events of one range each: for each ``e``, :meth:`predict` over ``dts_s[e]`` then
        :meth:`update_uwb` of the range ``a[e]`` -> ``b[e]``, ``z[e]`` (m). Returns the event of
        each update record and the records, in update order (what :meth:`update_uwb_events`
        gives per event, without the per-event range objects). The production engine runs
        the whole run as one compiled call."""
        zf = np.asarray(z, dtype=float)
        event_of: list[int] = []
        out = Updates()
        for e, dt in enumerate(dts_s):
            self.predict(dt)
            ze = zf[e:e + 1]
            if self._usable_pairs(KIND_UWB, (a[e],), (b[e],), ze):
                recs = self._uwb_sequence([a[e]], [b[e]], ze)
                event_of += [e] * len(recs)
                out += recs
        return event_of, out

    def _usable_pairs(self, kind: str, a: tuple[str, ...], b: tuple[str, ...], z: F64) -> list[int]:
        """Indices of the measurements that pass :meth:`_pair_usable` (which counts the others)."""
        lay = self.layout
        ready = {lay.lead, *compress(lay.vehicles, map(self._vehicle_ready.get, lay.vehicles))}
        zf = np.asarray(z, dtype=float)
        # the usual case, tested on whole tuples at C speed: every measurement usable
        if ready.issuperset(a) and ready.issuperset(b) and not any(map(eq, a, b)) and np.isfinite(zf).all():
            return list(range(len(a)))
        known = {lay.lead, *lay.vehicles}
        zl = zf.tolist()
        isfinite = math.isfinite
        # fast path: finite, both known and initialized, a != b; the rest through _pair_usable (counts why)
        return [k for k, zk in enumerate(zl)
                if (isfinite(zk) and a[k] in ready and b[k] in ready and a[k] != b[k])
                or self._pair_usable(kind, a[k], b[k], zk, known)]

    def _uwb_sequence(self, a_list: list[str], b_list: list[str], z: F64) -> Sequence[UpdateInfo]:
        """Engine hook (default: one Python scalar update per range): sequential updates of
        usable ranges, each re-linearized at the current state, with the second-order terms
        and deferral rule of :meth:`_linear_enough`, then the bound constraints."""
        lay = self.layout
        r_var = self.config.noise.uwb_sigma_m**2
        out = []
        for a, b, zk in zip(a_list, b_list, z.tolist(), strict=True):
            x = self._get_x()
            d = models.rel_position(x, lay, b) - models.rel_position(x, lay, a)
            m, h2_var = self._second_order(a, b, _range_hessian(d))
            if not h2_var <= self._nonlinear_fraction(a, b) * r_var:  # _linear_enough
                self._count("uwb_deferred_nonlinear")
                continue
            row = models.uwb_range(x, lay, a, b, use_bias_scale=self.config.use_uwb_bias_scale)
            # second-order EKF terms (Gelb 1974 sec. 6.1): E[f(d)] ~ f + tr(H2 P_d)/2 and the
            # neglected term's variance tr((H2 P_d)^2)/2 added to R. H2 is the Hessian of |d|
            # alone: with UWB bias / scale states (h = (1 + s)|d| + b, MacGougan (2009) eq. 3.5)
            # the exact terms would scale it by 1 + s and add the cross term u . P[d, s];
            # left out (an audit's Monte Carlo at |d| = 26 m, sigma_d = 1 m per axis, sigma_s =
            # 0.01, correlation -0.5: mean 0.038 m here against 0.034 m, ~1 % of the 0.5 m sigma)
            row = Row(row.h + 0.5 * float(m.trace()), row.idx, row.val)
            info = self._scalar(KIND_UWB, (a, b), row, zk, r_var + h2_var)
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
                tol = kernels.BOUND_TOL * (hi - lo)  # (on its bound up to round-off: no pull)
                if xi > hi + tol:
                    z, r_var = lo, pii * (hi - lo) / (xi - hi)
                elif xi < lo - tol:
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
    def update_bearings(self, bearings: Bearings) -> Updates:
        """One scalar update per bearing; azimuth known (reported) unless a has an azimuth state.

        Usable bearings (:meth:`_pair_usable`) go, in measurement order, through the engine's
        :meth:`_bearing_sequence`.
        """
        use = self._usable_pairs(KIND_BEARING, bearings.a, bearings.b, bearings.bearing_rad)
        if not use:
            return Updates()
        z = np.asarray(bearings.bearing_rad, dtype=float)
        az = np.asarray(bearings.azimuth_reported_rad, dtype=float)
        if len(use) == len(bearings.a):  # the usual case: every bearing usable (use is 0, 1, ..., m - 1)
            return Updates([self._bearing_sequence(bearings.a, bearings.b, z, az)])
        return Updates([self._bearing_sequence([bearings.a[k] for k in use], [bearings.b[k] for k in use], z[use],
                                               az[use])])

    def _bearing_sequence(self, a_list: Sequence[str], b_list: Sequence[str], z: F64,
                          az_reported: F64) -> Sequence[UpdateInfo]:
        """Engine hook (default: one Python scalar update per bearing): sequential updates,
        each re-linearized at the current state (second-order terms and deferral as for UWB;
        an estimated azimuth is initialized at its first bearing)."""
        lay = self.layout
        r_var = self.config.noise.bearing_sigma_rad**2
        out = []
        for a, b, zk, az in zip(a_list, b_list, z.tolist(), az_reported.tolist(), strict=True):
            x = self._get_x()
            d = models.rel_position(x, lay, b) - models.rel_position(x, lay, a)
            if np.hypot(d[0], d[1]) < 1.0:
                self._count("bearing_degenerate_geometry")
                continue
            m, h2_var = self._second_order(a, b, _bearing_hessian(d))
            if not h2_var <= self._nonlinear_fraction(a, b) * r_var:  # _linear_enough
                self._count("bearing_deferred_nonlinear")
                continue
            h2_bias = 0.5 * float(m.trace())
            if lay.has(AZIMUTH, a):
                if not self._azimuth_ready[a]:
                    alpha0 = float(bearing_rad(d, zk))  # atan2(dE, dN) - beta, wrapped
                    s = slice(lay.azimuth(a), lay.azimuth(a) + 1)
                    self._set_block(s, np.array([alpha0]), np.array([[self.config.azimuth_sigma0_rad**2]]))
                    self._azimuth_ready[a] = True
                row = models.bearing(self._get_x(), lay, a, b, None)
            else:
                if not np.isfinite(az):
                    self._count(f"nonfinite_{KIND_BEARING}")
                    continue
                row = models.bearing(x, lay, a, b, az)
            row = Row(row.h + h2_bias, row.idx, row.val)
            info = self._scalar(KIND_BEARING, (a, b), row, zk, r_var + h2_var, wrap=True)
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
        return self._second_order(a, b, hess)[1] <= self._nonlinear_fraction(a, b) * r_var

    def _nonlinear_fraction(self, a: str, b: str) -> float:
        """The deferral limit of a range or bearing between a and b (a fraction of R).

        Deferring waits for GNSS to shrink P. When the last GNSS epoch of a or b had fewer
        than 4 usable SD pseudoranges (:attr:`gnss_weak`: an urban canyon), GNSS will not
        shrink it, and deferring would let the solution drift while the ranges that could
        hold it are thrown away: then the measurement is used with its second-order mean
        and variance (R inflated) whatever their size (inf)."""
        if self.gnss_weak.get(a, False) or self.gnss_weak.get(b, False):
            return math.inf
        return self.config.nonlinear_fraction

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

    def update_height_aiding(self, sigma_m: float, vehicles: list[str] | None = None) -> list[UpdateInfo]:
        """Pseudo-measurement ``p_v,up = h_v - h_lead`` (variance sigma^2; the antennas'
        heights above a locally flat road, ``FilterConfig.antenna_heights_m``) for every
        initialized vehicle (or those in ``vehicles``); MacGougan (2009) section 5's height
        constraint.

        Tested like any measurement, so a large height difference (a steep ramp: beyond
        ~3.3 sigma) is rejected rather than forced in; smaller ones are not.
        """
        lay = self.layout
        heights = self.config.antenna_heights_m or {}
        h_lead = heights.get(lay.lead)
        out = []
        for v in lay.vehicles:
            if not self._vehicle_ready[v] or (vehicles is not None and v not in vehicles):
                continue
            i = lay.position(v).start + 2
            row = Row(float(self._get_x()[i]), np.array([i]), np.array([1.0]))
            h_v = heights.get(v)
            z = h_v - h_lead if h_v is not None and h_lead is not None else 0.0
            info = self._scalar(KIND_HEIGHT, (v,), row, z, sigma_m**2)
            if info is not None:
                out.append(info)
        return out

    # ----------------------------------------------------------------- all at once
    def update_epoch(self, *, gnss: dict[str, GnssEpoch] | None = None, lead_base_ecef_m: F64 | None = None,
                     uwb: UwbRanges | None = None, bearings: Bearings | None = None) -> Updates:
        """GNSS, then UWB, then bearings (thesis section 3.5.1 order)."""
        out = Updates()
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


@functools.lru_cache(maxsize=64)
def _chi2_upper(alpha: float, dof: int) -> float:
    """The chi-square(dof) quantile exceeded with probability ``alpha`` (scipy.stats.chi2.isf,
    as 2 gammainccinv(dof/2, alpha), without importing scipy.stats)."""
    return float(2.0 * special.gammainccinv(dof / 2.0, alpha))


def _bearing_hessian(d: F64) -> F64:
    """Hessian of atan2(E, N) in (E, N, U): [[-2EN, E^2-N^2], [E^2-N^2, 2EN]] / r^4."""
    e, n = float(d[0]), float(d[1])
    r4 = (e * e + n * n) ** 2
    h = np.zeros((3, 3))
    h[0, 0] = -2.0 * e * n / r4
    h[1, 1] = 2.0 * e * n / r4
    h[0, 1] = h[1, 0] = (e * e - n * n) / r4
    return h


def _elevations(geo: GnssGeometry, sv_ecef_m: F64) -> F64:
    """Satellite elevations (rad) seen from the lead base."""
    d = (np.asarray(sv_ecef_m, dtype=float) - geo.base_ecef_m) @ geo.rot_ecef_to_enu.T
    return np.arctan2(d[..., 2], np.hypot(d[..., 0], d[..., 1]))


def _c3(a: F64) -> F64:
    """``a`` as a C-contiguous (m, 3) float64 array (no copy when it already is one)."""
    return np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3)


def _c1(a: F64) -> F64:
    return np.ascontiguousarray(a, dtype=np.float64)


def _offsets(lengths: list[int]) -> NDArray[np.int64]:
    """Start offsets of concatenated pieces, with the total last (``len(lengths) + 1`` values)."""
    return np.array([0, *itertools.accumulate(lengths)], dtype=np.int64)


def _cat3(parts: list[F64]) -> F64:
    """The (m_i, 3) float64 pieces one after another (C-contiguous; one piece: no copy if it is)."""
    if len(parts) == 1:
        return _c3(parts[0])
    if all(p.ndim == 2 and p.shape[1] == 3 for p in parts):  # the usual case: every piece already (m_i, 3)
        return np.concatenate(parts, dtype=np.float64)
    return np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1, 3) for p in parts])


def _cat1(parts: list[F64]) -> F64:
    if len(parts) == 1:
        return _c1(parts[0])
    return np.concatenate([np.asarray(p, dtype=np.float64).reshape(-1) for p in parts])


def _cati(parts: list[NDArray]) -> NDArray[np.int64]:
    if len(parts) == 1:
        return np.ascontiguousarray(parts[0], dtype=np.int64)
    return np.concatenate(parts, dtype=np.int64, casting="same_kind")


def _all_accepted_records(kind: str, vehicles: list[str], bat: _GnssBatch, order: NDArray[np.int64], nu: F64,
                          s: F64, st: NDArray[np.int64]) -> UpdateBatch | None:
    """The records of an all-vehicle GNSS kernel call (outputs sliced by ``bat.moff``, ``order``
    local to each vehicle) when every measurement was accepted, as ``ClusterEkf._records``
    builds them vehicle by vehicle; None if any was not (then the per-vehicle path counts why)."""
    if np.count_nonzero(st):
        return None
    jrep = bat.vehicle_of
    prn = bat.prn_cat[bat.row0[jrep] + bat.iv_cat[bat.moff[jrep] + order]]  # satellite of each output: prns[j][iv_j[order]]
    veh = list(itertools.chain.from_iterable(map(repeat, [(v,) for v in vehicles], bat.counts)))
    return UpdateBatch(kind, veh, nu, s, prn.tolist())


class _Pairing(NamedTuple):
    """One epoch's satellite pairing (:func:`v2v.estimation.kernels.pair_satellites_all`) of
    its vehicles: their receivers' PRNs and pseudoranges one after another (rows
    ``row0[j]:row0[j+1]``), the common satellites ``iv_cat`` / ``il_cat`` sliced by ``moff``."""

    prn_cat: NDArray[np.int64]
    pr_cat: F64
    row0: NDArray[np.int64]
    iv_cat: NDArray[np.int64]
    il_cat: NDArray[np.int64]
    moff: NDArray[np.int64]


class _GnssBatch:
    """The concatenated gathers of one epoch's all-vehicle GNSS kernel call: per job
    ``(v, epoch, iv, il)`` its receiver's rows start at ``row0[j]``, its common satellites are
    ``iv_cat[moff[j]:moff[j+1]]`` (into its rows) and ``il_cat[...]`` (into the lead's);
    ``sv_cat`` the receivers' satellite positions one after another. Built once for the SD
    pseudoranges and reused by the SD Dopplers when their jobs are the same objects."""

    __slots__ = ("lead_ep", "jobs", "row0", "counts", "moff", "iv_cat", "il_cat", "sv_cat", "_vehicle_of", "_prn_cat")
    lead_ep: GnssEpoch
    jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]]
    row0: NDArray[np.int64]
    counts: list[int]
    moff: NDArray[np.int64]
    iv_cat: NDArray[np.int64]
    il_cat: NDArray[np.int64]
    sv_cat: F64
    _vehicle_of: NDArray[np.int64] | None
    _prn_cat: NDArray[np.int64] | None

    @classmethod
    def of(cls, lead_ep: GnssEpoch, jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]],
           pairing: _Pairing | None = None) -> _GnssBatch:
        """The gathers of ``jobs``; given the epoch's ``pairing`` (the jobs are its vehicles in
        its order, their ``iv`` / ``il`` its slices), its arrays are taken as they are."""
        b = cls()
        b.lead_ep, b.jobs = lead_ep, list(jobs)
        b._vehicle_of = b._prn_cat = None
        if pairing is not None:
            b.row0, b.moff, b.iv_cat, b.il_cat = pairing.row0, pairing.moff, pairing.iv_cat, pairing.il_cat
            b.counts = np.diff(pairing.moff).tolist()
            b._prn_cat = pairing.prn_cat
        else:
            b.row0 = _offsets([len(ep.prn) for _, ep, _, _ in jobs])
            b.counts = [len(iv) for _, _, iv, _ in jobs]  # common satellites per job
            b.moff = _offsets(b.counts)
            b.iv_cat = _cati([iv for _, _, iv, _ in jobs])
            b.il_cat = _cati([il for _, _, _, il in jobs])
        b.sv_cat = _cat3([ep.sv_pos_ecef_m for _, ep, _, _ in jobs])
        return b

    def same(self, lead_ep: GnssEpoch, jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]]) -> bool:
        """Built from these very objects (identity: the batch holds them, so none was reused)."""
        return lead_ep is self.lead_ep and len(jobs) == len(self.jobs) and all(
            v == w and ep is e and iv is i and il is k for (v, ep, iv, il), (w, e, i, k) in zip(jobs, self.jobs, strict=True))

    @property
    def vehicle_of(self) -> NDArray[np.int64]:
        """Job index of each gathered measurement."""
        if self._vehicle_of is None:
            self._vehicle_of = np.repeat(np.arange(len(self.jobs)), self.counts)
        return self._vehicle_of

    @property
    def prn_cat(self) -> NDArray[np.int64]:
        """The receivers' satellite numbers one after another (rows like ``sv_cat``)."""
        if self._prn_cat is None:
            self._prn_cat = _cati([ep.prn for _, ep, _, _ in self.jobs])
        return self._prn_cat


class ClusterEkf(ClusterFilterBase):
    """Production engine: sparse rows, O(n) P h^T, symmetric rank-1 covariance update,
    block-wise prediction (each vehicle block shares one cached 8x8 F and Q), all in the
    compiled kernels of :mod:`v2v.estimation.kernels`: every UWB and bearing batch, and all
    vehicles' SD pseudoranges and Dopplers of an epoch, run in one kernel call each that
    re-linearizes each measurement at the current state.

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
        # random-walk diagonal: state indices and PSD (= random_walk_variances(cfg, kind, 1 s))
        rw = [(i, q) for sl, kind in self._rw_index
              for i, q in zip(range(sl.start, sl.stop), random_walk_variances(self.config.process, kind, 1.0).tolist(),
                              strict=True)]
        self._rw_diag = np.array([i for i, _ in rw], dtype=np.int64)
        self._rw_psd = np.array([q for _, q in rw], dtype=np.float64)
        self._az_pairs = np.array(azimuth_pairs(self.layout), dtype=np.int64).reshape(-1, 2)
        self._az_ia = np.ascontiguousarray(self._az_pairs[:, 0])
        self._az_ir = np.ascontiguousarray(self._az_pairs[:, 1])
        lay = self.layout
        # kernel indices: position-slice start per vehicle (-1 = lead at the origin)
        self._pos0 = {**lay.position_starts, lay.lead: -1}
        self._clk = {v: lay.clock(v) for v in lay.vehicles}  # kernel indices per vehicle (as the layout's)
        self._vel0 = {v: lay.velocity(v).start for v in lay.vehicles}
        self._drift = {v: lay.drift(v) for v in lay.vehicles}
        self._last_batch: _GnssBatch | None = None
        self._az_index = {v: lay.azimuth(v) for v in lay.azimuth_vehicles}
        # the last bearing batch's (a, b) names and their kernel indices (the same every epoch of a steady cluster)
        self._bearing_cache: tuple[tuple[tuple[str, ...], tuple[str, ...]], tuple[
            NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], tuple[tuple[str, str], ...]]] | None = None
        pc = self.config.process  # kernels.predict_all's parameter vectors
        self._vpar = np.array([pc.vel_tau_s, pc.vel_sigma_horizontal_mps, pc.vel_sigma_vertical_mps, pc.drift_tau_s,
                               pc.drift_sigma_mps, pc.clock_bias_psd_m2ps])
        self._apar = np.array([pc.yaw_rate_tau_s, pc.yaw_rate_sigma_rps, pc.azimuth_rw_rad_per_sqrt_s**2])
        self._fq_scratch = (np.empty((8, 8)), np.empty((8, 8)), np.empty((2, 2)), np.empty((2, 2)))

    @staticmethod
    def _indices(index: dict[str, int], names: list[str]) -> NDArray[np.int64]:
        """``index[v]`` of each name, as an int64 array."""
        return np.fromiter(map(index.__getitem__, names), dtype=np.int64, count=len(names))

    def _get_x(self) -> F64:
        return self._x

    def _get_P(self) -> F64:
        return self._P

    def _predict_core(self, dt_s: float) -> None:
        # F P F^T + Q over the contiguous vehicle blocks, the random walks and the azimuth
        # pairs, then symmetrized: one compiled call (F and Q as process.vehicle_block and
        # process.azimuth_block, computed in the kernel), in place
        kernels.predict_all(self._x, self._P, dt_s, self._veh0, self._nveh, self._vpar, self._rw_diag, self._rw_psd,
                            self._az_ia, self._az_ir, self._apar, *self._fq_scratch)

    def _apply(self, row: Row, z: float, r_var: float, wrap: bool, test: bool) -> tuple[float, float, bool]:
        nu = float(wrap_angle(z - row.h)) if wrap else float(z - row.h)
        s, ok = scalar_update(self._x, self._P, row.idx, row.val, nu, r_var, self._k if test else None)
        return nu, s, ok

    def _set_block(self, s: slice, mean: F64, cov: F64) -> None:
        self._x[s] = mean
        self._P[s, :] = 0.0
        self._P[:, s] = 0.0
        self._P[s, s] = cov

    # ----------------------------------------------------------------- compiled batches
    def _nl_fractions(self, a_list: Sequence[str], b_list: Sequence[str]) -> F64:
        """:meth:`_nonlinear_fraction` of every measurement of a batch."""
        if not any(self.gnss_weak.values()):  # no weak vehicle: the configured fraction for all
            return np.full(len(a_list), self.config.nonlinear_fraction)
        return np.fromiter((self._nonlinear_fraction(a, b) for a, b in zip(a_list, b_list, strict=True)),
                           dtype=float, count=len(a_list))

    def _uwb_kernel_args(self, a_list: list[str], b_list: list[str], z: F64) -> tuple[list[tuple[str, str]], tuple]:
        """(pair keys, the arguments of :func:`v2v.estimation.kernels.uwb_batch` after ``x, P``)
        of a sequence of ranges; pair keys only with UWB bias/scale states (constraint records name them)."""
        lay, cfg = self.layout, self.config
        m = len(a_list)
        pos0 = self._pos0
        sa = np.fromiter(map(pos0.__getitem__, a_list), dtype=np.int64, count=m)
        sb = np.fromiter(map(pos0.__getitem__, b_list), dtype=np.int64, count=m)
        ib = np.full(m, -1, dtype=np.int64)
        isc = np.full(m, -1, dtype=np.int64)
        pairs: list[tuple[str, str]] = []
        if cfg.use_uwb_bias_scale and lay.uwb_pairs:
            pairs = [uwb_pair_key(a, b) for a, b in zip(a_list, b_list, strict=True)]
            for k, pair in enumerate(pairs):
                if lay.has(UWB, pair):
                    ib[k], isc[k] = lay.uwb_bias(pair), lay.uwb_scale(pair)
        bb = cfg.uwb_bias_bounds_m or (0.0, 0.0)
        sbnd = cfg.uwb_scale_bounds or (0.0, 0.0)
        return pairs, (sa, sb, ib, isc, np.ascontiguousarray(z, dtype=float), cfg.noise.uwb_sigma_m**2, self._k,
                       self._nl_fractions(a_list, b_list), cfg.uwb_bias_bounds_m is not None, float(bb[0]),
                       float(bb[1]), cfg.uwb_scale_bounds is not None, float(sbnd[0]), float(sbnd[1]))

    def _uwb_records(self, recs: tuple, a_list: list[str], b_list: list[str],
                     pairs: list[tuple[str, str]]) -> tuple[list[int], Sequence[UpdateInfo]]:
        """(range index of each record, the records) of a UWB kernel's output (counters as
        :meth:`_record`); the range indices never decrease (the kernel goes through the ranges
        in order; a range's bound-constraint records follow it)."""
        n_rec, kind, meas, nu, s, st = recs
        nu, s, st, meas = nu[:n_rec], s[:n_rec], st[:n_rec], meas[:n_rec].tolist()
        if not kind[:n_rec].any():  # ranges only (REC_UWB == 0), no constraint records
            deferred = st == kernels.DEFERRED
            n_def = int(np.count_nonzero(deferred))
            if np.count_nonzero(st) == n_def:  # all accepted (ACCEPTED == 0) or deferred (a counter, no record)
                if n_def:
                    self.counters["uwb_deferred_nonlinear"] = self.counters.get("uwb_deferred_nonlinear", 0) + n_def
                    keep = ~deferred
                    meas = list(compress(meas, keep.tolist()))
                    nu, s = nu[keep], s[keep]
                ab = list(zip(a_list, b_list, strict=True))
                # one record per range, in order, when none was deferred: meas is 0, 1, ..., m - 1
                veh = ab if not n_def and n_rec == len(ab) else list(map(ab.__getitem__, meas))
                return meas, UpdateBatch(KIND_UWB, veh, nu, s, None)
        ks, out = [], []
        for kd, k, nuk, sk, stk in zip(kind[:n_rec].tolist(), meas, nu.tolist(), s.tolist(), st.tolist(), strict=True):
            if kd == kernels.REC_UWB:
                info = self._record(KIND_UWB, (a_list[k], b_list[k]), nuk, sk, stk, -1, "uwb_deferred_nonlinear")
            else:
                info = self._record(KIND_CONSTRAINT, pairs[k], nuk, sk, stk, -1, "")
            if info is not None:
                ks.append(k)
                out.append(info)
        return ks, out

    def _uwb_sequence(self, a_list: list[str], b_list: list[str], z: F64) -> Sequence[UpdateInfo]:
        """All usable ranges in one :func:`v2v.estimation.kernels.uwb_batch` call."""
        pairs, args = self._uwb_kernel_args(a_list, b_list, z)
        recs = kernels.uwb_batch(self._x, self._P, *args)
        return self._uwb_records(recs, a_list, b_list, pairs)[1]

    def update_uwb_events(self, dts_s: Sequence[float], events: Sequence[UwbRanges]) -> list[Sequence[UpdateInfo]]:
        """:meth:`ClusterFilterBase.update_uwb_events` in one
        :func:`v2v.estimation.kernels.uwb_event_run` call (the same predictions and batches)."""
        a_list: list[str] = []
        b_list: list[str] = []
        z_parts = []
        starts = [0]
        for ranges in events:  # usable ranges (readiness does not change within a run of UWB events)
            use = self._usable_pairs(KIND_UWB, ranges.a, ranges.b, ranges.range_m)
            a_list += [ranges.a[k] for k in use]
            b_list += [ranges.b[k] for k in use]
            z_parts.append(np.asarray(ranges.range_m, dtype=float)[use])
            starts.append(len(a_list))
        z = np.concatenate(z_parts) if z_parts else np.zeros(0)
        ks, infos = self._uwb_event_kernel(dts_s, np.asarray(starts, dtype=np.int64), a_list, b_list, z)
        # the records of event e: those whose range index ks lies in [starts[e], starts[e + 1])
        # (ks increases: one contiguous slice per event)
        cut = np.searchsorted(np.asarray(ks, dtype=np.int64), np.asarray(starts, dtype=np.int64)).tolist()
        return [infos[cut[e]:cut[e + 1]] for e in range(len(events))]

    def update_uwb_run(self, dts_s: Sequence[float], a: Sequence[str], b: Sequence[str],
                       z: F64) -> tuple[list[int], Sequence[UpdateInfo]]:
        """:meth:`ClusterFilterBase.update_uwb_run` in one
        :func:`v2v.estimation.kernels.uwb_event_run` call (the same predictions and updates as
        :meth:`update_uwb_events` of one-range events). The usable ranges are chosen for the
        whole run at once: readiness does not change within a run of UWB events."""
        zf = np.asarray(z, dtype=float)
        use = self._usable_pairs(KIND_UWB, tuple(a), tuple(b), zf)
        n = len(dts_s)
        if len(use) == n:  # the usual case: every range usable, event e's range is range e
            a_list, b_list, zu = list(a), list(b), zf
            starts = np.arange(n + 1, dtype=np.int64)
        else:
            a_list, b_list, zu = [a[k] for k in use], [b[k] for k in use], zf[use]
            starts = np.searchsorted(np.asarray(use, dtype=np.int64), np.arange(n + 1, dtype=np.int64)).astype(np.int64)
        ks, infos = self._uwb_event_kernel(dts_s, starts, a_list, b_list, zu)
        return (ks if len(use) == n else [use[k] for k in ks]), infos

    def _uwb_event_kernel(self, dts_s: Sequence[float], starts: NDArray[np.int64], a_list: list[str],
                          b_list: list[str], z: F64) -> tuple[list[int], Sequence[UpdateInfo]]:
        """:func:`v2v.estimation.kernels.uwb_event_run` of usable ranges (event ``e``: predict
        over ``dts_s[e]``, then ranges ``starts[e]:starts[e + 1]``); (range index of each record,
        the records)."""
        for dt in dts_s:
            if not (math.isfinite(dt) and dt >= 0.0):
                raise ValueError(f"dt_s must be finite and >= 0, got {dt!r}")
        pairs, args = self._uwb_kernel_args(a_list, b_list, z)
        recs = kernels.uwb_event_run(self._x, self._P, np.asarray(dts_s, dtype=float), starts,
                                     *args, self._veh0, self._nveh, self._vpar, self._rw_diag, self._rw_psd,
                                     self._az_ia, self._az_ir, self._apar)
        return self._uwb_records(recs, a_list, b_list, pairs)

    def _bearing_sequence(self, a_list: Sequence[str], b_list: Sequence[str], z: F64,
                          az_reported: F64) -> Sequence[UpdateInfo]:
        """All usable bearings in one :func:`v2v.estimation.kernels.bearing_batch` call."""
        cfg = self.config
        sa, sb, iaz, pair_names = self._bearing_indices(tuple(a_list), tuple(b_list))
        ready = np.zeros(self.layout.n, dtype=np.bool_)
        for v, i in self._az_index.items():
            ready[i] = self._azimuth_ready[v]
        nu, s, st = kernels.bearing_batch(self._x, self._P, sa, sb, iaz, ready, np.ascontiguousarray(z, dtype=float),
                                          np.ascontiguousarray(az_reported, dtype=float),
                                          cfg.noise.bearing_sigma_rad**2, self._k, self._nl_fractions(a_list, b_list),
                                          cfg.azimuth_sigma0_rad**2)
        for v, i in self._az_index.items():
            self._azimuth_ready[v] = bool(ready[i])
        pairs = list(pair_names)
        if not st.any():  # all accepted: no counters
            return UpdateBatch(KIND_BEARING, pairs, nu, s, None)
        return self._record_runs(KIND_BEARING, pairs, nu, s, st, "bearing_deferred_nonlinear")

    def _bearing_indices(self, a: tuple[str, ...], b: tuple[str, ...]) -> tuple[
            NDArray[np.int64], NDArray[np.int64], NDArray[np.int64], tuple[tuple[str, str], ...]]:
        """Position-slice starts of a and b, a's azimuth state (-1: none) and the (a, b) pairs of a
        bearing batch; those of the last batch when its names are the same (kept until the
        layout changes: the kernels only read them)."""
        if self._bearing_cache is None or self._bearing_cache[0] != (a, b):
            m = len(a)
            self._bearing_cache = ((a, b), (np.fromiter(map(self._pos0.__getitem__, a), dtype=np.int64, count=m),
                                            np.fromiter(map(self._pos0.__getitem__, b), dtype=np.int64, count=m),
                                            np.fromiter(map(self._az_index.get, a, repeat(-1)), dtype=np.int64, count=m),
                                            tuple(zip(a, b, strict=True))))
        return self._bearing_cache[1]

    def _record_runs(self, kind: str, vehicles: Sequence[tuple[str, ...]], nu: F64, s: F64, st: NDArray[np.int64],
                     deferred_key: str) -> Updates:
        """The records of a kernel batch (no PRNs) in update order, as :meth:`_record` makes them
        one by one (counters included), with each run of accepted updates between the others kept
        as one :class:`UpdateBatch` (its columns are views of ``nu``, ``s``): a batch of a few
        hundred bearings with a few rejected or deferred then stays columns instead of a few
        hundred records."""
        out = Updates()
        recs: list[UpdateInfo] = []
        a = 0
        for k in np.flatnonzero(st).tolist():  # the updates that were not accepted (ACCEPTED == 0)
            if k > a:  # the accepted run before it
                if recs:
                    out += recs
                    recs = []
                out += UpdateBatch(kind, vehicles[a:k], nu[a:k], s[a:k], None)
            info = self._record(kind, vehicles[k], float(nu[k]), float(s[k]), int(st[k]), -1, deferred_key)
            if info is not None:
                recs.append(info)
            a = k + 1
        if recs:
            out += recs
        if a < len(vehicles):
            out += UpdateBatch(kind, vehicles[a:], nu[a:], s[a:], None)
        return out

    def _sd_pseudoranges_all(self, geo: GnssGeometry, lead_ep: GnssEpoch,
                             jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]],
                             pairing: _Pairing | None = None) -> Sequence[UpdateInfo]:
        """:meth:`ClusterFilterBase._sd_pseudoranges` of every vehicle in one compiled call
        (:func:`v2v.estimation.kernels.sd_pseudorange_vehicles`: per vehicle the same row,
        clock-jump, screen and batch kernels in the same order, on one shared deferred-update
        buffer); counters, NIS windows and records as there."""
        cfg = self.config
        names = [v for v, *_ in jobs]
        bat = _GnssBatch.of(lead_ep, jobs, pairing)
        self._last_batch = bat  # the epoch's Doppler call reuses the gathers when its jobs are the same
        jump, isolated, n_flagged, order, nu, s, st = kernels.sd_pseudorange_vehicles(
            self._x, self._P, geo.base_ecef_m, geo.rot_ecef_to_enu, self._indices(self._pos0, names),
            self._indices(self._clk, names), bat.sv_cat,
            _cat1([ep.pseudorange_m for _, ep, _, _ in jobs]) if pairing is None else pairing.pr_cat,
            bat.row0, _c3(lead_ep.sv_pos_ecef_m), _c1(lead_ep.pseudorange_m), bat.iv_cat, bat.il_cat, bat.moff,
            cfg.noise.sd_pseudorange_var_m2, self._k, cfg.clock_jump_detection, cfg.clock_reset_sigma_m**2)
        moff = bat.moff
        recs_all = _all_accepted_records(KIND_SD_PR, names, bat, order, nu, s, st)
        out = Updates()
        mo = moff.tolist()
        nis = recs_all.nis.tolist() if recs_all is not None else None
        for j, ((v, ep, iv, _), jp, iso, nf) in enumerate(zip(jobs, jump.tolist(), isolated.tolist(), n_flagged.tolist(),
                                                             strict=True)):
            if jp:
                self._nis_window.pop(v, None)
                self._count("clock_jump_detected")
            if nf:
                self.counters["screened_first_update"] = self.counters.get("screened_first_update", 0) + nf
            self.integrity_available[v] = iso
            a, b = mo[j], mo[j + 1]
            if nis is not None:  # all accepted: the NIS window from the batch's column
                self._record_accepted_nis(v, nis[a:b])
            else:
                recs = self._records(KIND_SD_PR, (v,), order[a:b], nu[a:b], s[a:b], st[a:b], ep.prn[iv])
                self._record_tests(v, recs)
                out += recs
        return out if recs_all is None else Updates([recs_all])

    def _sd_dopplers_all(self, geo: GnssGeometry, lead_ep: GnssEpoch,
                         jobs: list[tuple[str, GnssEpoch, NDArray, NDArray]]) -> Sequence[UpdateInfo]:
        """:meth:`ClusterFilterBase._sd_dopplers` of every vehicle in one compiled call
        (:func:`v2v.estimation.kernels.sd_doppler_vehicles`); satellites with a non-finite
        Doppler are left out (and counted) first, as there."""
        bat = self._last_batch
        if bat is None or not bat.same(lead_ep, jobs):
            bat = _GnssBatch.of(lead_ep, jobs)
        # SD Dopplers of all vehicles: d_v[iv] - d_lead[il], gathered from the concatenated rows
        zd = _cat1([ep.doppler_mps for _, ep, _, _ in jobs])[bat.row0[bat.vehicle_of] + bat.iv_cat] \
            - np.asarray(lead_ep.doppler_mps, dtype=np.float64)[bat.il_cat]
        if np.isfinite(zd).all():  # (= both Dopplers finite: a difference of finite values is finite)
            kept = jobs
        else:  # leave out (and count) the satellites with a non-finite Doppler, vehicle by vehicle
            kept = []
            for v, ep, iv, il in jobs:
                ok = np.isfinite(ep.doppler_mps[iv]) & np.isfinite(lead_ep.doppler_mps[il])
                for _ in range(int((~ok).sum())):
                    self._count(f"nonfinite_{KIND_SD_DOPPLER}")
                kept.append((v, ep, iv[ok], il[ok]))
            bat = _GnssBatch.of(lead_ep, kept)
            zd = _cat1([ep.doppler_mps[iv] - lead_ep.doppler_mps[il] for _, ep, iv, il in kept])
        names = [v for v, *_ in kept]
        moff = bat.moff
        n_flagged, order, nu, s, st = kernels.sd_doppler_vehicles(
            self._x, self._P, geo.base_ecef_m, geo.base_vel_ecef_mps, geo.rot_ecef_to_enu,
            self._indices(self._pos0, names), self._indices(self._vel0, names), self._indices(self._drift, names),
            bat.sv_cat, _cat3([ep.sv_vel_ecef_mps for _, ep, _, _ in kept]), bat.row0,
            _c3(lead_ep.sv_pos_ecef_m), _c3(lead_ep.sv_vel_ecef_mps), zd, bat.iv_cat, bat.il_cat, moff,
            self.config.noise.sd_doppler_var_m2ps2, self._k)
        recs_all = _all_accepted_records(KIND_SD_DOPPLER, names, bat, order, nu, s, st)
        out = Updates()
        mo = moff.tolist()
        for j, ((v, ep, iv, _), nf) in enumerate(zip(kept, n_flagged.tolist(), strict=True)):
            if nf:
                self.counters["screened_first_update"] = self.counters.get("screened_first_update", 0) + nf
            if recs_all is None:
                a, b = mo[j], mo[j + 1]
                out += self._records(KIND_SD_DOPPLER, (v,), order[a:b], nu[a:b], s[a:b], st[a:b], ep.prn[iv])
        return out if recs_all is None else Updates([recs_all])

    def _records(self, kind: str, vehicles: tuple[str, ...], order: NDArray[np.int64], nu: F64, s: F64,
                 st: NDArray[np.int64], prns: NDArray[np.int64]) -> Sequence[UpdateInfo]:
        """The records of one vehicle's GNSS batch (``prns`` indexed like the rows, the
        kernel outputs like ``order``): accepted ones built directly, the others by :meth:`_record`."""
        if not st.any():  # all accepted (kernels.ACCEPTED == 0): the common case, no counters
            return UpdateBatch(kind, [vehicles] * len(nu), nu, s, prns[order].tolist())
        out = []
        accepted = kernels.ACCEPTED
        for o, nuk, sk, stk in zip(prns[order].tolist(), nu.tolist(), s.tolist(), st.tolist(), strict=True):
            if stk == accepted:
                out.append(UpdateInfo(kind, vehicles, nuk, sk, nuk * nuk / sk, True, o))
            else:
                info = self._record(kind, vehicles, nuk, sk, stk, o, "")
                if info is not None:
                    out.append(info)
        return out

    def _record(self, kind: str, vehicles: tuple[str, ...], nu: float, s: float, status: int, prn: int,
                deferred_key: str) -> UpdateInfo | None:
        """The UpdateInfo / counters of one kernel record, as :meth:`_scalar` and the Python
        sequences produce them."""
        if status == kernels.ACCEPTED:
            return UpdateInfo(kind, vehicles, nu, s, nu * nu / s, True, prn)
        if status == kernels.REJECTED or status == kernels.EXCLUDED:
            self._count(f"rejected_{kind}")
            if status == kernels.EXCLUDED:
                self._count("excluded_screened")
            return UpdateInfo(kind, vehicles, nu, s, nu * nu / s, False, prn)
        if status == kernels.DEFERRED:
            self._count(deferred_key)
        elif status == kernels.DEGENERATE:
            self._count("bearing_degenerate_geometry")
        else:  # NONFINITE, NONFINITE_INPUT
            self._count(f"nonfinite_{kind}")
        return None
