"""Process model of the cluster filter: exact (Van Loan) discretization per block.

Continuous-time model (Petovello et al. section 3.2), per non-lead vehicle and per ENU axis::

    d/dt p = v,             d/dt v   = -v / tau_v + w_v,      E[w_v w_v] = q_v delta(t)
    d/dt b = d,             d/dt d   = -d / tau_d + w_d,      E[w_d w_d] = q_d delta(t)

with first-order Gauss-Markov (GM) velocity and clock drift whose steady-state standard
deviation sigma gives the white-noise spectral density ``q = 2 sigma^2 / tau``. The
paper's values: tau_v = 2 s, sigma_v = 10 m/s horizontal, 1 m/s vertical; clock drift
sigma_d = 1000 m/s, tau_d = 10 s. The clock bias integrates the drift (plus optional
white noise, zero by default). UWB bias and UWB scale-factor states are random
walks (MacGougan (2009) section 3.4.2, eq. 3.12-3.13): ``d/dt a = w_a``.

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

Discretization uses the continuous noise model (Pabolleta (2020) eq. 3.6,
``Q = int_0^dt Phi(t) G Qc G^T Phi(t)^T dt``) evaluated exactly with Van Loan's
matrix exponential (Van Loan 1978)::

    M = [[-A, G Qc G^T], [0, A^T]] dt,   expm(M) = [[., Phi^-1 Q], [0, Phi^T]]
    Phi = (lower-right block)^T,         Q = Phi (upper-right block)

Blocks are independent, so each block type is discretized once per dt (cached) and the
full F, Q are block diagonal.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import expm

from v2v.errors import UserError
from v2v.estimation.layout import AZIMUTH, UWB, VEHICLE, StateLayout

F64 = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class ProcessNoiseConfig:
    """Process-noise parameters (defaults: Petovello et al. section 3.2).

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
    azimuth_rw_rad_per_sqrt_s: float = np.radians(5.0)
    yaw_rate_sigma_rps: float = np.radians(30.0)
    yaw_rate_tau_s: float = 1.0
    uwb_bias_rw_m_per_sqrt_s: float = 0.01
    uwb_scale_rw_per_sqrt_s: float = 1e-5

    def __post_init__(self) -> None:
        for name in ("vel_tau_s", "drift_tau_s", "yaw_rate_tau_s"):
            if not getattr(self, name) > 0.0:
                raise UserError(f"must be > 0, got {getattr(self, name)!r}", field=f"process.{name}",
                                fix="give a positive correlation time in seconds")
        for name in ("vel_sigma_horizontal_mps", "vel_sigma_vertical_mps", "drift_sigma_mps",
                     "clock_bias_psd_m2ps", "azimuth_rw_rad_per_sqrt_s", "yaw_rate_sigma_rps",
                     "uwb_bias_rw_m_per_sqrt_s",
                     "uwb_scale_rw_per_sqrt_s"):
            if not getattr(self, name) >= 0.0:
                raise UserError(f"must be >= 0, got {getattr(self, name)!r}", field=f"process.{name}")


def van_loan(a: F64, gqg: F64, dt_s: float) -> tuple[F64, F64]:
    """Exact discretization (Phi, Q) of ``dx/dt = A x + w``, ``E[w w^T] = G Qc G^T delta``.

    Van Loan (1978), "Computing integrals involving the matrix exponential".
    """
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


@lru_cache(maxsize=64)
def _vehicle_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    """(F, Q) of one 8-state vehicle block [p(3), v(3), clk, drift]."""
    f = np.zeros((8, 8))
    q = np.zeros((8, 8))
    sig = (cfg.vel_sigma_horizontal_mps, cfg.vel_sigma_horizontal_mps, cfg.vel_sigma_vertical_mps)
    for axis in range(3):
        phi, qd = van_loan(*_gm_integrated(cfg.vel_tau_s, sig[axis]), dt_s)
        idx = [axis, 3 + axis]
        f[np.ix_(idx, idx)] = phi
        q[np.ix_(idx, idx)] = qd
    phi, qd = van_loan(*_gm_integrated(cfg.drift_tau_s, cfg.drift_sigma_mps, cfg.clock_bias_psd_m2ps), dt_s)
    f[6:8, 6:8] = phi
    q[6:8, 6:8] = qd
    f.setflags(write=False)
    q.setflags(write=False)
    return f, q


def vehicle_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    """(F, Q) of one vehicle block, cached per (config, dt). Read-only arrays."""
    return _vehicle_block(cfg, float(dt_s))


@lru_cache(maxsize=64)
def _azimuth_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    f, q = van_loan(*_gm_integrated(cfg.yaw_rate_tau_s, cfg.yaw_rate_sigma_rps, cfg.azimuth_rw_rad_per_sqrt_s**2), dt_s)
    f.setflags(write=False)
    q.setflags(write=False)
    return f, q


def azimuth_block(cfg: ProcessNoiseConfig, dt_s: float) -> tuple[F64, F64]:
    """(F, Q) of an [azimuth, azimuth rate] pair, cached per (config, dt). Read-only arrays.

    Closed form (same as a velocity axis): ``F = [[1, tau (1 - e)], [0, e]]``,
    ``e = exp(-dt / tau)``; Q from Van Loan with ``G Qc G^T = diag(q_alpha, 2 sigma^2 / tau)``.
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
