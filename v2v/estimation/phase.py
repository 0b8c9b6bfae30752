"""Single-difference carrier phase in the cluster EKF: slips, ambiguity states, fixing.

MacGougan (2009) sections 3.4-3.7, applied to the lead-relative cluster of Petovello et
al.: every non-lead vehicle ``v`` gets one SD ambiguity state ``a_v^j = N_v^j - N_lead^j``
(L1 cycles) per satellite ``j`` both receivers track with continuous lock.

Measurement (thesis eq. 3.2-3.3 for phase, lead = reference receiver)::

    lambda (Phi_v^j - Phi_lead^j) = rho_v^j - rho_lead^j + clk_v + lambda a_v^j + e
    h(x) = sd_pseudorange(x) + lambda a_v^j,   d h / d a_v^j = lambda

The SD clock is the pseudorange's (code and carrier share the receiver clock); the SD
ionosphere is ~0 over tens of metres, so it is not modelled. Noise: ``2 sigma_phi^2``.

Ambiguity lifecycle (per epoch, before the phase updates of vehicle ``v``):

* **added** for a satellite tracked by both receivers above the phase elevation mask, from
  its first measurement: ``a = (z - h_0(x)) / lambda`` with ``h_0`` the SD range + clock
  (:func:`sd_range_row`, Jacobian ``H``), so ``a`` is correlated with the state:
  ``Cov(a, x) = -P H^T / lambda``, ``Var(a) = (H P H^T + 2 sigma_phi^2) / lambda^2``. That
  is exactly the limit of a diffuse prior followed by the update with ``z`` (so ``z`` is not
  applied again), without putting a huge variance next to millimetre ones in P (the two
  engines would then disagree by round-off);
* **removed** (marginalized) when the satellite is lost by either receiver, drops below the
  mask, or either receiver slips. Slips are detected per receiver, from measured fields
  only: the receiver's loss-of-lock indicator (``lock_time_s`` did not grow by the epoch
  interval: RINEX LLI) and the carrier-minus-Doppler test (:class:`SlipDetector`); a slip
  that escapes both shows up as rejected innovations (3 epochs in a row: removed).

Ambiguity resolution (after every epoch's phase updates, per vehicle, in state order):

1. the SD float solution of ``v`` is double-differenced against its highest-elevation
   satellite (:func:`v2v.estimation.ambiguity.sd_to_dd`, thesis eq. 3.30-3.31);
2. LAMBDA partial fixing in the decorrelated space (:func:`~v2v.estimation.ambiguity.partial_fix`,
   eq. 3.32-3.36, 3.39): the largest subset with bootstrapped success rate >=
   ``ar_min_success`` that passes the ratio test (``ar_ratio``, default 3.0);
3. the fixed subset ``Z_s^T a_dd = z_s`` is applied to the *SD* state as pseudo-measurements
   of variance ``fix_hold_sigma_cycles^2`` (the conditioning of eq. 3.37/3.40, written on
   the SD state: conditioning is parametrization-free, and the SD clock is untouched because
   the rows only difference ambiguities). They stay in the state (fix-and-hold: the fixed
   ambiguities are carried forward until a slip removes one of the ambiguities), and later
   epochs only apply the combinations whose variance is still above ``(2 sigma_h)^2``
   (``sigma_h = fix_hold_sigma_cycles``: a held combination's variance stays near
   ``sigma_h^2``; the factor keeps round-off and the slow growth between epochs from
   re-applying it every epoch). A vehicle with fewer than ``ar_min_dd`` DD ambiguities may
   keep (not start) a fix when every fixed combination's variance is within ``(4 sigma_h)^2``
   (:func:`_held`: a looser test, as it only asks whether the combinations are still the
   held ones, not whether to pull them again).

A vehicle is *fixed* at an epoch when every one of its DD ambiguities old enough to be
searched is in the fixed set (``n_fixed == n_eligible >= 3``, i.e. at least 4 satellites),
*partial* when some are, *float* otherwise. The filter never sees the true integers; :class:`PhaseStatus` carries the fixed
combinations (``Z_s``, ``z_s``) so the metrics can score wrong fixes against the truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from v2v.errors import check_sigmas
from v2v.estimation.ambiguity import bootstrapped_success_rate, partial_fix, reference_satellite, sd_to_dd
from v2v.estimation.layout import AMBIGUITY, StateLayout
from v2v.estimation.models import GnssGeometry, Row
from v2v.measmodels import range_difference_m, range_jacobian
from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M, GnssEpoch

F64 = NDArray[np.float64]
LAMBDA_L1_M = GPS_L1_WAVELENGTH_M


@dataclass(frozen=True, kw_only=True)
class PhaseConfig:
    """Carrier-phase processing settings of a solution.

    Parameters
    ----------
    phase_sigma_m : undifferenced carrier-phase sigma the filter assumes (m). PLL jitter is
        1-2 mm at 40-45 dB-Hz and carrier multipath a few mm (MacGougan (2009) section 3.3
        uses mm-level values); 5 mm leaves room for both.
    elevation_mask_rad : satellites below are not used for phase (low satellites carry the
        most multipath and the echo-only signals: thesis section 3.5.1).
    cn0_mask_dbhz : minimum C/N0 for phase use.
    slip_threshold_m : carrier-minus-Doppler slip test threshold, metres per epoch (one L1
        cycle is 0.19 m; the test's noise at 10 Hz is a few mm, see :class:`SlipDetector`).
    max_gap_s : a satellite unseen for longer starts a new ambiguity (lock cannot be trusted).
    resolve : run LAMBDA after each epoch (False: float solution only).
    ar_min_success : bootstrapped success rate the fixed subset must reach (eq. 3.39).
    ar_ratio : ratio-test threshold (eq. 3.35, Omega = 0).
    fix_hold_sigma_cycles : sigma of the fix-and-hold pseudo-measurement (0.01 cycle = 2 mm:
        "known", below the SD phase noise, without making P needlessly ill-conditioned).
    ar_min_lock_s : an ambiguity joins the integer search only after this long in the state
        (RTKLIB's "min lock"): an arc that starts on an echo-only signal usually ends or
        slips within seconds as the car moves, before it can be fixed at a biased value.
    ar_min_dd : a vehicle's first fix needs at least this many eligible DD ambiguities (4:
        position + one redundant, so one biased satellite shows in the ratio test). A solution
        with UWB ranges has redundancy from them (MacGougan (2009) section 4.3.2: with a 40 deg
        mask "only 4 satellites are available and thus the GPS only solution has no
        redundancy" while GPS+UWB fixes): the pipeline uses 3 there.
    reset_after_rejections : consecutive rejected epochs after which an ambiguity is removed.
    """

    phase_sigma_m: float = 0.005
    elevation_mask_rad: float = math.radians(15.0)
    cn0_mask_dbhz: float = 30.0
    slip_threshold_m: float = 0.08
    max_gap_s: float = 1.0
    resolve: bool = True
    ar_min_success: float = 0.999
    ar_ratio: float = 3.0
    fix_hold_sigma_cycles: float = 0.01
    ar_min_lock_s: float = 5.0
    ar_min_dd: int = 4
    reset_after_rejections: int = 3

    def __post_init__(self) -> None:
        check_sigmas(self, "phase", ("phase_sigma_m", "fix_hold_sigma_cycles"))

    @property
    def sd_phase_var_m2(self) -> float:
        return 2.0 * self.phase_sigma_m**2


@dataclass
class PhaseStatus:
    """Ambiguity-resolution outcome of one vehicle at one epoch.

    ``prns`` the satellites whose SD ambiguities took part in the search (DD order: every
    one but ``ref_prn``, in this order, is differenced against ``ref_prn``); ``n_dd`` counts
    all of the vehicle's DD ambiguities, ``n_eligible`` those in the search (old enough:
    ``PhaseConfig.ar_min_lock_s``); ``Zs`` (n_eligible, n_fixed) integer and ``z_fixed``
    (n_fixed,) the fixed combinations ``Zs^T a_dd = z_fixed``. ``state`` is "fixed" when
    every eligible DD ambiguity is fixed and there are >= 3 (>= 4 satellites; a satellite
    just acquired joins after the minimum lock time, as in RTKLIB), "partial" when some
    combinations are fixed, else "float".
    """

    n_dd: int = 0
    n_eligible: int = 0
    n_fixed: int = 0
    ratio: float = float("nan")
    success_rate: float = float("nan")
    ref_prn: int = -1
    prns: tuple[int, ...] = ()
    Zs: NDArray[np.int64] = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    z_fixed: NDArray[np.int64] = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    @property
    def state(self) -> str:
        if self.n_eligible >= 3 and self.n_fixed >= self.n_eligible:
            return "fixed"
        return "partial" if self.n_fixed > 0 else "float"

    def dd_prns(self) -> tuple[int, ...]:
        """PRNs of the DD ambiguities in order (``a^j - a^ref`` for j in this tuple)."""
        return tuple(p for p in self.prns if p != self.ref_prn)


class SlipDetector:
    """Per-receiver cycle-slip detection from measured fields only.

    For satellite ``j`` tracked at consecutive epochs ``t0 < t1`` of one receiver:

    * loss of lock: ``lock_time(t1) < lock_time(t0) + (t1 - t0)`` (the receiver restarted
      its lock-time counter: the RINEX loss-of-lock indicator);
    * carrier minus Doppler: ``s_j = lambda (Phi(t1) - Phi(t0)) - (t1 - t0) (D(t0) + D(t1)) / 2``.
      Both terms contain the same range change; what differs is the slip ``lambda dN`` and
      the receiver clock's phase jitter over the interval, which the instantaneous Doppler
      does not see (white frequency noise of a TCXO: ~3 cm per 0.1 s, measured on the
      simulated receivers). The jitter is common to every satellite of the receiver, so with
      >= 3 satellites the median over satellites is removed first: ``|s_j - median(s)| >
      threshold`` flags a slip. What remains is Doppler noise (0.03 m/s at 45 dB-Hz,
      0.17 m/s at 30 dB-Hz, times dt / sqrt 2), mm of phase noise and the trapezoid error
      ``dt^3/12 * range jerk``: < 2 cm at 10 Hz, so a 0.08 m threshold is > 4 sigma of the
      noise and < half a 0.19 m cycle. A slip common to *every* satellite is invisible here
      and harmless to double differences (the SD clock absorbs it);
    * gap: unseen for more than ``max_gap_s`` -> new arc.
    """

    def __init__(self, threshold_m: float, max_gap_s: float):
        self.threshold_m = float(threshold_m)
        self.max_gap_s = float(max_gap_s)
        self._last: dict[str, dict[int, tuple[float, float, float, float]]] = {}

    def update(self, ep: GnssEpoch) -> NDArray[np.bool_]:
        """Slip / new-arc flag per satellite of ``ep`` (True when continuity is not proven)."""
        hist = self._last.setdefault(ep.vehicle_id, {})
        flags = np.ones(ep.n, dtype=bool)
        new: dict[int, tuple[float, float, float, float]] = {}
        t1 = float(ep.t_s)
        cand: list[int] = []
        stat: list[float] = []
        for i, prn in enumerate(ep.prn.tolist()):
            phi, dop, lock = float(ep.carrier_cycles[i]), float(ep.doppler_mps[i]), float(ep.lock_time_s[i])
            if not (math.isfinite(phi) and math.isfinite(dop)):
                continue
            new[prn] = (t1, phi, dop, lock)
            prev = hist.get(prn)
            if prev is None:
                continue
            t0, phi0, dop0, lock0 = prev
            dt = t1 - t0
            if not 0.0 < dt <= self.max_gap_s or lock + 1e-6 < lock0 + dt:
                continue
            cand.append(i)
            stat.append(LAMBDA_L1_M * (phi - phi0) - 0.5 * (dop0 + dop) * dt)
        if cand:
            s = np.asarray(stat)
            if s.size >= 3:
                s = s - np.median(s)
            flags[np.asarray(cand)[np.abs(s) <= self.threshold_m]] = False
        hist.update(new)  # satellites not in this epoch keep their history (gap test on return)
        return flags


def sd_range_row(x: F64, layout: StateLayout, geo: GnssGeometry, v: str, sv_v_ecef_m: F64,
                 sv_lead_ecef_m: F64) -> Row:
    """SD geometric range plus SD clock, ``rho_v - rho_lead + clk_v`` (the SD phase without
    its ambiguity term; see :func:`sd_phase_row`), rows on (position of v, clock of v)."""
    p = x[layout.position(v)]
    rot = geo.rot_ecef_to_enu
    d = p @ rot  # R^T p: the vehicle's offset from the base, ECEF
    sv_v = np.asarray(sv_v_ecef_m, dtype=float)
    drho = float(range_difference_m(geo.base_ecef_m, d, sv_v, np.asarray(sv_lead_ecef_m, dtype=float)))
    u_enu = rot @ range_jacobian(geo.base_ecef_m + d, sv_v)
    ps = layout.position(v)
    idx = np.array([ps.start, ps.start + 1, ps.start + 2, layout.clock(v)], dtype=np.int64)
    return Row(drho + float(x[layout.clock(v)]), idx, np.array([-u_enu[0], -u_enu[1], -u_enu[2], 1.0]))


def sd_phase_row(x: F64, layout: StateLayout, geo: GnssGeometry, v: str, prn: int, sv_v_ecef_m: F64,
                 sv_lead_ecef_m: F64) -> Row:
    """SD carrier phase (metres) of ``v`` minus the lead (see the module docstring)::

        h = rho(base + R^T p_v, sv_v) - rho(base, sv_lead) + clk_v + lambda a_v
        dh/dp_v = -R u_v,  dh/dclk_v = 1,  dh/da_v = lambda

    The same model as the SD pseudorange (:func:`v2v.estimation.models.sd_pseudorange`) plus
    the ambiguity, with the range difference evaluated without cancellation
    (:func:`v2v.measmodels.range_difference_m`): a millimetre measurement must not be
    predicted to the 4e-9 m ulp of a 2.2e7 m range.
    """
    r = sd_range_row(x, layout, geo, v, sv_v_ecef_m, sv_lead_ecef_m)
    ia = layout.ambiguity(v, prn)
    return Row(r.h + LAMBDA_L1_M * float(x[ia]), np.append(r.idx, ia), np.append(r.val, LAMBDA_L1_M))


def resolve_vehicle(x: F64, P: F64, layout: StateLayout, v: str, el_by_prn: dict[int, float],
                    cfg: PhaseConfig, eligible: set[int] | None = None,
                    ) -> tuple[PhaseStatus, list[tuple[NDArray[np.int64], F64, float]]]:
    """LAMBDA partial fixing of vehicle ``v``'s DD ambiguities (thesis eq. 3.30-3.40).

    ``eligible``: PRNs whose ambiguities may take part (old enough: ``ar_min_lock_s``);
    None = all. Returns the status and the fix-and-hold pseudo-measurements still to apply:
    ``(state indices, coefficients, integer value)`` per fixed z-space combination whose
    variance is above ``(2 sigma_h)^2`` (module docstring). ``n_dd`` counts every DD ambiguity of
    ``v``; ineligible ones (too new to be searched) stay float and do not count against the
    state: with every eligible one fixed the vehicle is "fixed" (``n_fixed == n_eligible``,
    :class:`PhaseStatus`), also when ``n_dd > n_eligible``.
    """
    keys = layout.ambiguity_keys(v)
    all_prns = [int(k[1]) for k in keys]
    prns = [p for p in all_prns if eligible is None or p in eligible]
    st = PhaseStatus(prns=tuple(prns), n_dd=max(len(all_prns) - 1, 0), n_eligible=max(len(prns) - 1, 0))
    if len(prns) < 2:
        return st, []
    ref = reference_satellite(np.array([el_by_prn.get(p, -1.0) for p in prns]))
    idx = np.array([layout.ambiguity(v, p) for p in prns], dtype=np.int64)
    clk = layout.clock(v)
    sub = np.r_[np.arange(layout.position(v).start, layout.position(v).stop), clk, idx]
    # the thesis's D on v's sub-state [position, SD clock, SD ambiguities] (eq. 3.30-3.31)
    dd = sd_to_dd(x[sub], P[np.ix_(sub, sub)], amb_idx=list(range(4, 4 + len(prns))), ref=ref, drop_idx=[3])
    a_hat = dd.x[dd.amb_idx]
    Qa = dd.P[np.ix_(dd.amb_idx, dd.amb_idx)]
    st.ref_prn = prns[ref]
    if not (np.all(np.isfinite(a_hat)) and np.all(np.isfinite(Qa))):
        return st, []
    try:
        res = partial_fix(a_hat, Qa, min_success=cfg.ar_min_success, ratio_threshold=cfg.ar_ratio)
    except np.linalg.LinAlgError:
        return st, []
    st.n_fixed = res.n_fixed
    st.ratio = res.ratio
    # of the fixed subset (eq. 3.39); with nothing fixed, of the whole set (eq. 3.36)
    st.success_rate = res.success_rate if res.n_fixed else bootstrapped_success_rate(res.Qz)
    if res.n_fixed == 0:
        return st, []
    if len(prns) - 1 < cfg.ar_min_dd and not _held(Qa, res, cfg):
        st.n_fixed, st.ratio = 0, float("nan")  # too few for a first fix; keep what is held
        return st, []
    Zs = res.Z[:, res.fixed_mask].astype(np.int64)
    st.Zs = Zs
    st.z_fixed = res.z_fixed.astype(np.int64)
    # rows on the SD ambiguities (B = the ambiguity rows of the thesis's D): with every DD
    # ambiguity fixed, hold the DDs themselves, a_dd = Z^-T z (integers; each DD then has the
    # hold sigma, and P stays better conditioned than with combinations of large Z^-T
    # entries); with a partial fix, hold the fixed z-space combinations z_s = Zs^T B a_sd
    # (eq. 3.40).
    B = dd.D[np.ix_(dd.amb_idx, np.arange(4, 4 + len(prns)))]
    if res.n_fixed == len(prns) - 1:
        coef = B
        values = np.rint(res.a_cond)
    else:
        coef = Zs.T.astype(float) @ B  # (s, m) on idx
        values = st.z_fixed.astype(float)
    qz = np.einsum("ij,jk,ik->i", coef, P[np.ix_(idx, idx)], coef)
    hold_var = cfg.fix_hold_sigma_cycles**2
    todo = []
    for i in range(coef.shape[0]):
        if qz[i] > 4.0 * hold_var:
            nz = np.flatnonzero(coef[i])
            todo.append((idx[nz], coef[i, nz], float(values[i])))
    return st, todo


def _held(Qa: F64, res, cfg: PhaseConfig) -> bool:
    """Is every fixed z combination already held: its variance within ``(4 sigma_h)^2``, four
    times the ``(2 sigma_h)^2`` above which :func:`resolve_vehicle` pulls a combination again
    (module docstring)?"""
    Zs = res.Z[:, res.fixed_mask].astype(float)
    qz = np.einsum("ij,jk,ik->i", Zs.T, Qa, Zs.T)
    return bool(np.all(qz <= 4.0 * (2.0 * cfg.fix_hold_sigma_cycles) ** 2))


def true_dd(st: PhaseStatus, ep_v: GnssEpoch, ep_lead: GnssEpoch) -> NDArray[np.int64] | None:
    """True DD integers of ``st``'s ambiguities (from the epochs' truth fields), or None when a
    PRN is missing from either epoch."""
    def n_of(ep: GnssEpoch) -> dict[int, int]:
        return dict(zip(ep.prn.tolist(), ep.ambiguity_cycles.tolist(), strict=True))

    nv, nl = n_of(ep_v), n_of(ep_lead)
    try:
        sd = {p: nv[p] - nl[p] for p in st.prns}
    except KeyError:
        return None
    return np.array([sd[p] - sd[st.ref_prn] for p in st.dd_prns()], dtype=np.int64)


def wrong_fix(st: PhaseStatus, ep_v: GnssEpoch | None, ep_lead: GnssEpoch | None) -> bool | None:
    """Did any fixed combination take a wrong integer? None when there is no fix or no truth."""
    if st.n_fixed == 0 or ep_v is None or ep_lead is None:
        return None
    dd = true_dd(st, ep_v, ep_lead)
    if dd is None:
        return None
    return bool(np.any(st.Zs.T @ dd != st.z_fixed))


__all__ = [
    "AMBIGUITY",
    "LAMBDA_L1_M",
    "PhaseConfig",
    "PhaseStatus",
    "SlipDetector",
    "resolve_vehicle",
    "sd_phase_row",
    "sd_range_row",
    "true_dd",
    "wrong_fix",
]
