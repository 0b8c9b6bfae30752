"""Process model of the cluster filter: exact (Van Loan) discretization per block.

Continuous-time model (Petovello et al. section 3.2), per non-lead vehicle and per ENU axis::

    d/dt p = v,             d/dt v   = -v / tau_v + w_v,      E[w_v w_v] = q_v delta(t)
    d/dt b = d,             d/dt d   = -d / tau_d + w_d,      E[w_d w_d] = q_d delta(t)

with first-order Gauss-Markov (GM) velocity and clock drift whose steady-state standard
deviation sigma gives the white-noise spectral density ``q = 2 sigma^2 / tau``. The
paper's values: tau_v = 2 s, sigma_v = 10 m/s horizontal, 1 m/s vertical; clock drift
sigma_d = 1000 m/s, tau_d = 10 s. The clock bias integrates the drift (plus optional
white noise, zero by default). UWB bias and UWB scale-factor states are random
walks (MacGougan (2009) section 3.4.2, eq. 3.12-3.13): ``d/dt a = w_a``, discretized as
``Q = q dt`` (``q`` the spectral density; the thesis writes ``(q dt)^2``, which does not
add up over sub-steps: two steps of dt/2 would give half the variance of one of dt).

An estimated azimuth (paper section 5.3) is a random walk, or, when the layout gives it
an azimuth-rate block, the integral of a first-order GM yaw rate plus a random walk::

    d/dt alpha = omega + w_alpha,   d/dt omega = -omega / tau_w + w_omega,
    E[w_alpha^2] = q_alpha (= azimuth_rw^2),   E[w_omega^2] = 2 sigma_w^2 / tau_w

The paper does not state its azimuth process model; it reports azimuth errors "typically
less than 0.2 deg with larger errors occurring during rapid vehicle manoeuvres" (Fig. 14,
which plots the azimuth rate beside the error). A random walk lags a sustained turn by
about ``omega dt`` per prediction; the bearing innovations that lag causes are then
shared between the azimuth and the (loosely modelled, sigma 10 m/s) relative positions,
which rotates the estimated cluster. With the yaw-rate state the prediction follows the
turn (see the README's azimuth study for the numbers).

What limits the estimated azimuth is not this model but what the measurements say about it:
with the cars in line, the lead's bearings fix the cluster's shape and the azimuth only
together, and the rotation of the whole cluster about the lead is seen by GPS alone, so the
azimuth error is about (GPS across-track error) / (distance). Measured on the paper's in-line
3-car cluster (experiments/RESULTS.md section 2): looser (0.5 deg/sqrt(s), 20 deg/s, 2 s) and
tighter (0.2-0.3 deg/sqrt(s), 10-30 deg/s, 3-10 s) settings leave the across-track error
unchanged, and the tighter ones lag a sustained 16 deg/s turn (azimuth std 1.5-4.3 deg instead
of 0.38 deg). Averaging the GPS rotation over longer would need a measured yaw rate.

Discretization uses the continuous noise model (Pabolleta (2021) eq. 3.6,
``Q = int_0^dt Phi(t) G Qc G^T Phi(t)^T dt``) evaluated exactly with Van Loan's
matrix exponential (Van Loan 1978)::

    M = [[-A, G Qc G^T], [0, A^T]] dt,   expm(M) = [[., Phi^-1 Q], [0, Phi^T]]
    Phi = (lower-right block)^T,         Q = Phi (upper-right block)

Every 2x2 block here ([p, v] per axis, [clk, drift], [azimuth, rate]) is an integrated
first-order GM process, whose Van Loan integral has a closed form (:func:`gm_integrated_block`,
Pabolleta (2021) eq. 3.6 evaluated analytically; Gelb (1974) table 4.4-1 gives the same
transition matrix). With ``a = dt / tau``, ``e = exp(-a)``, ``q = 2 sigma^2 / tau`` and white
noise ``q0`` on the level::

    F   = [[1, tau (1 - e)], [0, e]]
    Q11 = q0 dt + q tau^2 (dt - 2 tau (1 - e) + tau (1 - e^2) / 2)
    Q12 = q tau^2 ((1 - e) - (1 - e^2) / 2)
    Q22 = q tau (1 - e^2) / 2

The Q11 and Q12 brackets cancel to O(a^3) and O(a^2) for small ``a`` (relative round-off
~ 1e-16 / a^2 in the closed form), so below ``a = 0.5`` they are summed from their Taylor
series (coefficients in :func:`gm_integrated_block`). It is ~15x faster than
``scipy.linalg.expm`` (the filter predicts to every UWB / bearing time tag, so dt varies);
:func:`van_loan` is kept as the reference (tests/test_process_closed_form.py checks the two
to ~1e-12 relative over dt in [1e-4, 10] s).

Blocks are independent, so each block type is discretized once per dt (cached) and the
full F, Q are block diagonal.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from v2v.errors import UserError, check_sigmas, tau_problem
from v2v.estimation.layout import AZIMUTH, UWB, VEHICLE, StateLayout

F64 = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class ProcessNoiseConfig:
    """Process-noise parameters. The relative velocity and clock drift defaults are Petovello
    et al. section 3.2's; the azimuth, yaw-rate and UWB random walks are v2v's (the azimuth's
    equals the scenario default, ``solutions.N.azimuth_rw_deg_per_sqrt_s = 2``).

    Parameters
    ----------
    vel_tau_s : GM correlation time of the relative velocity.
    vel_sigma_horizontal_mps, vel_sigma_vertical_mps : GM steady-state std of the
        relative velocity, east/north and up.
    drift_tau_s, drift_sigma_mps : GM correlation time and steady-state std of the
        single-difference clock drift.
    clock_bias_psd_m2ps : white-noise PSD added directly to the clock bias (m^2/s);
        0 = bias is the pure integral of the drift.
    azimuth_rw_rad_per_sqrt_s : azimuth random-walk strength (rad/sqrt(s)).
    yaw_rate_sigma_rps, yaw_rate_tau_s : GM steady-state std (rad/s) and correlation time
        (s) of the azimuth rate, used for azimuths that have an azimuth-rate block.
    uwb_bias_rw_m_per_sqrt_s, uwb_scale_rw_per_sqrt_s : UWB bias (m/sqrt(s)) and scale
        factor (1/sqrt(s)) random walks (MacGougan (2009): bias drifts slowly with
        temperature, the scale factor is almost a random constant).
    """

    vel_tau_s: float = 2.0
    vel_sigma_horizontal_mps: float = 10.0
    vel_sigma_vertical_mps: float = 1.0
    drift_tau_s: float = 10.0
    drift_sigma_mps: float = 1000.0
    clock_bias_psd_m2ps: float = 0.0
    azimuth_rw_rad_per_sqrt_s: float = np.radians(2.0)
    yaw_rate_sigma_rps: float = np.radians(30.0)
    yaw_rate_tau_s: float = 1.0
    uwb_bias_rw_m_per_sqrt_s: float = 0.01
    uwb_scale_rw_per_sqrt_s: float = 1e-5

    def __post_init__(self) -> None:
        for name in ("vel_tau_s", "drift_tau_s", "yaw_rate_tau_s"):
            why = tau_problem(getattr(self, name))
            if why:
                raise UserError(f"{getattr(self, name)!r} {why}", field=f"process.{name}",
                                fix="give a positive correlation time in seconds")
        check_sigmas(self, "process", ("vel_sigma_horizontal_mps", "vel_sigma_vertical_mps", "drift_sigma_mps"))
        # random-walk strengths and the yaw-rate sigma: 0 turns the term off
        check_sigmas(self, "process", ("azimuth_rw_rad_per_sqrt_s", "yaw_rate_sigma_rps", "uwb_bias_rw_m_per_sqrt_s",
                                       "uwb_scale_rw_per_sqrt_s"), zero_is_off=True)
        psd = self.clock_bias_psd_m2ps  # (a variance per second already, not a sigma)
        if not (math.isfinite(psd) and psd >= 0.0):
            raise UserError(f"must be a finite number >= 0, got {psd!r}", field="process.clock_bias_psd_m2ps")


def van_loan(a: F64, gqg: F64, dt_s: float) -> tuple[F64, F64]:
    """Exact discretization (Phi, Q) of ``dx/dt = A x + w``, ``E[w w^T] = G Qc G^T delta``.

    Van Loan (1978), "Computing integrals involving the matrix exponential".
    """
    from scipy.linalg import expm  # only the reference path needs scipy.linalg (import cost)

    n = a.shape[0]
    m = np.zeros((2 * n, 2 * n))
    m[:n, :n] = -a
    m[:n, n:] = gqg
    m[n:, n:] = a.T
    e = expm(m * dt_s)
    phi = e[n:, n:].T
    q = phi @ e[:n, n:]
    return phi, 0.5 * (q + q.T)


def _gm_integrated(tau_s: float, sigma: float, extra_psd_level0: float = 0.0) -> tuple[F64, F64]:
    """Continuous (A, G Qc G^T) of [level, rate] with rate a GM process (q = 2 sigma^2 / tau)."""
    a = np.array([[0.0, 1.0], [0.0, -1.0 / tau_s]])
    gqg = np.diag([extra_psd_level0, 2.0 * sigma**2 / tau_s])
    return a, gqg


# Taylor coefficients (n = 0..19) of the two cancelling brackets of gm_integrated_block, in a = dt/tau:
#   B11(a) = a - 2 (1 - e^-a) + (1 - e^-2a) / 2 = sum_n (-1)^(n+1) (2^(n-1) - 2) / n! a^n  (n >= 3)
#   B12(a) = (1 - e^-a) - (1 - e^-2a) / 2       = sum_n (-1)^(n+1) (1 - 2^(n-1)) / n! a^n  (n >= 2)
# (from 1 - e^-x = sum_{n>=1} (-1)^(n+1) x^n / n!): 1/3 a^3 - 1/4 a^4 + 7/60 a^5 - 1/24 a^6 + ...
# and 1/2 a^2 - 1/2 a^3 + 7/24 a^4 - 1/8 a^5 + 31/720 a^6 - ...
_SERIES_N = 20
_B11 = tuple(reversed([0.0] * 3 + [(-1.0) ** (n + 1) * (2.0 ** (n - 1) - 2.0) / math.factorial(n)
                                   for n in range(3, _SERIES_N)]))
_B12 = tuple(reversed([0.0] * 2 + [(-1.0) ** (n + 1) * (1.0 - 2.0 ** (n - 1)) / math.factorial(n)
                                   for n in range(2, _SERIES_N)]))
_SERIES_MAX_A = 0.5  # last term at a = 0.5: ~0.5 / 19! ~ 4e-18, 1e-16 of B11(0.5) ~ 0.03


def _poly(c_high_first: tuple[float, ...], a: float) -> float:
    """Polynomial in ``a`` with coefficients from the highest power down (Horner)."""
    acc = 0.0
    for cn in c_high_first:
        acc = acc * a + cn
    return acc


def gm_integrated_block(tau_s: float, sigma: float, dt_s: float, extra_psd_level0: float = 0.0) -> tuple[F64, F64]:
    """Closed-form exact discretization (F, Q) of [level, rate], rate a first-order GM.

    ``d/dt level = rate + w0``, ``d/dt rate = -rate / tau + w``, ``E[w^2] = q = 2 sigma^2 / tau``,
    ``E[w0^2] = extra_psd_level0``: the relative-velocity and clock-drift models of Petovello
    et al. section 3.2 (and the azimuth-rate model of this module). ``Q`` is Pabolleta (2021)
    eq. 3.6, ``Q = int_0^dt Phi(s) G Qc G^T Phi(s)^T ds``, with ``Phi(s) = [[1, tau (1 - e_s)],
    [0, e_s]]``, ``e_s = exp(-s / tau)`` integrated term by term (the integral Van Loan (1978)
    computes with the matrix exponential, :func:`van_loan`)::

        Q11 = q0 dt + q tau^2 int (1 - e_s)^2 ds = q0 dt + q tau^3 B11(a)
        Q12 = q tau int (1 - e_s) e_s ds        = q tau^2 B12(a)
        Q22 = q int e_s^2 ds                      = q tau (1 - e^2) / 2

    with ``a = dt / tau``, ``B11 = a - 2 (1 - e) + (1 - e^2) / 2``, ``B12 = (1 - e) - (1 - e^2) / 2``
    (``1 - e`` and ``1 - e^2`` through ``expm1``). Below ``a = 0.5`` the brackets are summed
    from their Taylor series (to a^19: ``B11 = a^3/3 - a^4/4 + 7a^5/60 - a^6/24 + 31a^7/2520 -
    ...``, ``B12 = a^2/2 - a^3/2 + 7a^4/24 - a^5/8 + 31a^6/720 - ...``), which avoids the
    cancellation of the closed form (relative error ~ 1e-16 / a^2).
    """
    tau = float(tau_s)
    dt = float(dt_s)
    q = 2.0 * float(sigma) ** 2 / tau
    a = dt / tau
    u1 = -math.expm1(-a)  # 1 - e
    u2 = -math.expm1(-2.0 * a)  # 1 - e^2
    if a < _SERIES_MAX_A:
        b11, b12 = _poly(_B11, a), _poly(_B12, a)
    else:
        b11, b12 = a - 2.0 * u1 + 0.5 * u2, u1 - 0.5 * u2
    f = np.array([[1.0, tau * u1], [0.0, math.exp(-a)]])
    q11 = float(extra_psd_level0) * dt + q * tau**3 * b11
    q12 = q * tau**2 * b12
    q22 = q * tau * 0.5 * u2
    return f, np.array([[q11, q12], [q12, q22]])


@lru_cache(maxsize=256)
def _vehicle_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    """(F, Q) of one 8-state vehicle block [p(3), v(3), clk, drift] (closed form, :func:`gm_integrated_block`)."""
    f = np.zeros((8, 8))
    q = np.zeros((8, 8))
    sig = (cfg.vel_sigma_horizontal_mps, cfg.vel_sigma_horizontal_mps, cfg.vel_sigma_vertical_mps)
    blocks = [(axis, 3 + axis, gm_integrated_block(cfg.vel_tau_s, sig[axis], dt_s)) for axis in range(3)]
    blocks.append((6, 7, gm_integrated_block(cfg.drift_tau_s, cfg.drift_sigma_mps, dt_s, cfg.clock_bias_psd_m2ps)))
    for i, j, (phi, qd) in blocks:
        f[i, i], f[i, j], f[j, j] = phi[0, 0], phi[0, 1], phi[1, 1]
        q[i, i], q[i, j], q[j, i], q[j, j] = qd[0, 0], qd[0, 1], qd[1, 0], qd[1, 1]
    f.setflags(write=False)
    q.setflags(write=False)
    return f, q


def vehicle_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    """(F, Q) of one vehicle block, cached per (config, dt). Read-only arrays."""
    return _vehicle_block(cfg, float(dt_s))


@lru_cache(maxsize=256)
def _azimuth_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    f, q = gm_integrated_block(cfg.yaw_rate_tau_s, cfg.yaw_rate_sigma_rps, dt_s, cfg.azimuth_rw_rad_per_sqrt_s**2)
    f.setflags(write=False)
    q.setflags(write=False)
    return f, q


def azimuth_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    """(F, Q) of an [azimuth, azimuth rate] pair, cached per (config, dt). Read-only arrays.

    Closed form (same as a velocity axis, :func:`gm_integrated_block`): ``F = [[1, tau (1 - e)],
    [0, e]]``, ``e = exp(-dt / tau)``, Q with ``G Qc G^T = diag(q_alpha, 2 sigma^2 / tau)``.
    """
    return _azimuth_block(cfg, float(dt_s))


def random_walk_variances(cfg: ProcessNoiseConfig, kind: str, dt_s: float) -> F64:
    """Per-state Q diagonal of a random-walk block (F = I): ``q dt``."""
    if kind == AZIMUTH:
        return np.array([cfg.azimuth_rw_rad_per_sqrt_s**2 * dt_s])
    if kind == UWB:
        return np.array([cfg.uwb_bias_rw_m_per_sqrt_s**2 * dt_s, cfg.uwb_scale_rw_per_sqrt_s**2 * dt_s])
    raise ValueError(f"{kind!r} is not a random-walk block")


def azimuth_pairs(layout: StateLayout) -> list[tuple[int, int]]:
    """(azimuth index, azimuth-rate index) of every azimuth that has a rate block."""
    return [(layout.azimuth(v), layout.azimuth_rate(v)) for v in layout.azimuth_rate_vehicles]


def random_walk_indices(layout: StateLayout) -> list[tuple[slice, str]]:
    """(slice, kind) of every random-walk block: UWB pairs and azimuths without a rate."""
    rated = set(layout.azimuth_rate_vehicles)
    return [(layout.block(kind, key), kind) for kind, key in layout.blocks
            if kind == UWB or (kind == AZIMUTH and key not in rated)]


def transition(layout: StateLayout, cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    """Dense block-diagonal (F, Q) for the whole state (used by the reference engine)."""
    n = layout.n
    f = np.eye(n)
    q = np.zeros((n, n))
    fb, qb = vehicle_block(cfg, dt_s)
    for kind, key in layout.blocks:
        s = layout.block(kind, key)
        if kind == VEHICLE:
            f[s, s] = fb
            q[s, s] = qb
    for s, kind in random_walk_indices(layout):
        q[s, s] = np.diag(random_walk_variances(cfg, kind, dt_s))
    if layout.azimuth_rate_vehicles:
        fa, qa = azimuth_block(cfg, dt_s)
        for ia, ir in azimuth_pairs(layout):
            ix = np.ix_([ia, ir], [ia, ir])
            f[ix] = fa
            q[ix] = qa
    return f, q
