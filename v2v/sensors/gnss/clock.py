"""Two-state GNSS receiver clock (bias, drift) driven by oscillator Allan parameters.

State ``x = [b, d]``: clock bias ``b = c*dT`` (metres) and drift ``d = c*dT/dt`` (m/s).
Continuous model (Brown & Hwang 2012, §9.3, "two-state clock model")::

    db/dt = d + w_f        E[w_f w_f] = c^2 * S_f * delta(t),   S_f = h0 / 2
    dd/dt =     w_g        E[w_g w_g] = c^2 * S_g * delta(t),   S_g = 2 pi^2 h_-2

with ``h0`` (white frequency noise) and ``h_-2`` (random-walk frequency noise) the
power-law coefficients of the fractional-frequency PSD ``S_y(f) = h0 + h_-2 f^-2``
(flicker ``h_-1`` is neglected, as in the two-state model). Exact discretization over
``dt`` (Brown & Hwang eq. 9.3.11 without the flicker terms)::

    Phi = [[1, dt], [0, 1]]
    Q   = c^2 [[S_f dt + S_g dt^3 / 3, S_g dt^2 / 2],
               [S_g dt^2 / 2,          S_g dt      ]]

The Allan variance of this process is ``sigma_y^2(tau) = h0 / (2 tau) + (2 pi^2 / 3) h_-2 tau``
(IEEE Std 1139; Brown & Hwang table 9.2), which the tests check.

Millisecond clock jumps: many receivers keep their clock within +-0.5 ms of GPS time
by jumping it by whole milliseconds (pseudorange and phase jump by ~299.8 km together).
Enabled by ``ms_jump_threshold_s``; every jump is logged as a :class:`ClockJump`.

References
----------
Brown, R. G. & Hwang, P. Y. C. (2012), *Introduction to Random Signals and Applied Kalman
Filtering*, 4th ed., Wiley, §9.3 (p. 327) and table 9.1 (oscillator h-coefficients:
TCXO h0 = 2e-19, h-2 = 2e-20; OCXO h0 = 2e-25, h-2 = 6e-25).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from v2v.errors import UserError
from v2v.sensors.measurements import SPEED_OF_LIGHT_MPS

F64 = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class OscillatorClass:
    """Power-law coefficients of an oscillator (fractional frequency PSD), Brown & Hwang table 9.1.

    Parameters
    ----------
    name : str
    h0 : float
        White frequency noise coefficient, s (i.e. 1/Hz).
    h_m2 : float
        Random-walk frequency noise coefficient ``h_-2``, 1/s (i.e. Hz).
    """

    name: str
    h0: float
    h_m2: float


# Brown & Hwang (2012) table 9.1 (flicker h_-1 omitted in the two-state model).
TCXO = OscillatorClass(name="TCXO", h0=2e-19, h_m2=2e-20)
OCXO = OscillatorClass(name="OCXO", h0=2e-25, h_m2=6e-25)


@dataclass(frozen=True, kw_only=True)
class ClockConfig:
    """Receiver clock model parameters.

    Parameters
    ----------
    enabled : bool
        False: bias and drift are exactly zero (an ideal clock).
    oscillator : OscillatorClass
        Default TCXO (a NovAtel OEM4-class receiver, paper §4).
    initial_bias_max_s : float
        Initial bias drawn uniform in ``[-max, +max]``, seconds. 0.5 ms mimics a receiver
        that keeps its clock within half a millisecond of GPS time.
    initial_drift_sigma : float
        1-sigma initial fractional frequency offset (dimensionless; 1e-6 = 1 ppm ~ 300 m/s).
    ms_jump_threshold_s : float | None
        When ``|bias| > threshold`` the receiver jumps its clock by whole milliseconds back
        towards zero. None disables jumps (default: the paper's filter has no jump handling).
    """

    enabled: bool = True
    oscillator: OscillatorClass = TCXO
    initial_bias_max_s: float = 0.5e-3
    initial_drift_sigma: float = 1e-6
    ms_jump_threshold_s: float | None = None

    def __post_init__(self) -> None:
        if self.oscillator.h0 < 0 or self.oscillator.h_m2 < 0:
            raise UserError("oscillator h-coefficients must be >= 0", field="gnss.clock.oscillator",
                            fix="use values from Brown & Hwang table 9.1, e.g. h0=2e-19, h_m2=2e-20")
        if self.initial_bias_max_s < 0 or self.initial_drift_sigma < 0:
            raise UserError("initial clock bias/drift spreads must be >= 0", field="gnss.clock",
                            fix="set initial_bias_max_s and initial_drift_sigma to 0 or positive")
        if self.ms_jump_threshold_s is not None and not 0 < self.ms_jump_threshold_s < 1e-3:
            raise UserError("ms_jump_threshold_s must be in (0, 1e-3) seconds",
                            field="gnss.clock.ms_jump_threshold_s", fix="use 0.5e-3 or None (no jumps)")


def clock_spectral_densities(osc: OscillatorClass) -> tuple[float, float]:
    """Continuous white-noise spectral densities ``(q_bias m^2/s, q_drift m^2/s^3)``.

    ``q_bias = c^2 h0 / 2``, ``q_drift = c^2 2 pi^2 h_-2`` (Brown & Hwang eq. 9.3.8).
    """
    c2 = SPEED_OF_LIGHT_MPS**2
    return c2 * osc.h0 / 2.0, c2 * 2.0 * np.pi**2 * osc.h_m2


def clock_transition(dt_s: float) -> F64:
    """State transition ``Phi = [[1, dt], [0, 1]]`` of the two-state clock."""
    return np.array([[1.0, dt_s], [0.0, 1.0]])


def clock_process_noise(osc: OscillatorClass, dt_s: float) -> F64:
    """Exact discrete process noise ``Q`` (m^2, m^2/s, m^2/s^2) of the two-state clock over ``dt_s``.

    ``Q = [[q_b dt + q_d dt^3/3, q_d dt^2/2], [q_d dt^2/2, q_d dt]]`` (Brown & Hwang §9.3).
    """
    qb, qd = clock_spectral_densities(osc)
    return np.array(
        [
            [qb * dt_s + qd * dt_s**3 / 3.0, qd * dt_s**2 / 2.0],
            [qd * dt_s**2 / 2.0, qd * dt_s],
        ]
    )


def allan_variance_theory(osc: OscillatorClass, tau_s: float | F64) -> F64:
    """Allan variance ``sigma_y^2(tau) = h0/(2 tau) + (2 pi^2/3) h_-2 tau`` (IEEE Std 1139)."""
    tau = np.asarray(tau_s, dtype=float)
    return osc.h0 / (2.0 * tau) + (2.0 * np.pi**2 / 3.0) * osc.h_m2 * tau


@functools.lru_cache(maxsize=1024)
def _process_noise_cholesky(osc: OscillatorClass, dt_s: float) -> tuple[float, float, float]:
    """Cholesky factor ``(l11, l21, l22)`` of :func:`clock_process_noise` (cached: a run uses one ``dt``).

    ``q_drift`` may be 0 (pure white FM): the semidefinite case gives ``l22 = 0``.
    """
    q = clock_process_noise(osc, dt_s)
    l11 = np.sqrt(q[0, 0])
    l21 = q[1, 0] / l11 if l11 > 0 else 0.0
    l22 = np.sqrt(max(q[1, 1] - l21**2, 0.0))
    return l11, l21, l22


def step_clock_states(state: F64, dt_s: float, osc: OscillatorClass, rng: np.random.Generator) -> F64:
    """Propagate clock state(s) ``(..., 2)`` = (bias m, drift m/s) by ``dt_s`` with exact noise.

    ``x_{k+1} = Phi x_k + w_k``, ``w_k ~ N(0, Q)`` (see :func:`clock_process_noise`).
    Vectorized over leading dimensions (independent clocks).
    """
    x = np.asarray(state, dtype=float)
    if dt_s <= 0.0:
        return x.copy()
    l11, l21, l22 = _process_noise_cholesky(osc, float(dt_s))
    z = rng.standard_normal(x.shape)
    w0 = l11 * z[..., 0]
    w1 = l21 * z[..., 0] + l22 * z[..., 1]
    out = np.empty_like(x)
    out[..., 0] = x[..., 0] + dt_s * x[..., 1] + w0
    out[..., 1] = x[..., 1] + w1
    return out


@dataclass(frozen=True, slots=True)
class ClockJump:
    """A receiver millisecond clock jump (``jump_m`` added to the bias at ``t_s``)."""

    t_s: float
    jump_m: float


@dataclass
class ReceiverClock:
    """Streaming two-state receiver clock for one receiver.

    Use :meth:`advance_to` with non-decreasing times; read ``bias_m``/``drift_mps``.
    """

    config: ClockConfig
    rng: np.random.Generator
    t_s: float = 0.0
    state: F64 = field(default_factory=lambda: np.zeros(2))
    jumps: list[ClockJump] = field(default_factory=list)

    @classmethod
    def start(cls, config: ClockConfig, rng: np.random.Generator, t_s: float) -> ReceiverClock:
        """Draw the initial bias (uniform) and drift (normal) and return a clock at ``t_s``."""
        state = np.zeros(2)
        if config.enabled:
            state[0] = rng.uniform(-1.0, 1.0) * config.initial_bias_max_s * SPEED_OF_LIGHT_MPS
            state[1] = rng.standard_normal() * config.initial_drift_sigma * SPEED_OF_LIGHT_MPS
        return cls(config=config, rng=rng, t_s=t_s, state=state)

    @property
    def bias_m(self) -> float:
        return float(self.state[0])

    @property
    def drift_mps(self) -> float:
        return float(self.state[1])

    def advance_to(self, t_s: float) -> None:
        """Propagate to ``t_s`` (exact discrete model) and apply a millisecond jump if due."""
        dt = t_s - self.t_s
        if dt < -1e-9:
            raise ValueError(f"clock cannot go back in time ({self.t_s} -> {t_s})")
        if self.config.enabled and dt > 0:
            # step_clock_states for one clock, in scalars (same draws and arithmetic).
            l11, l21, l22 = _process_noise_cholesky(self.config.oscillator, float(dt))
            z0, z1 = self.rng.standard_normal(2)
            b, d = self.state
            self.state = np.array([b + dt * d + l11 * z0, d + (l21 * z0 + l22 * z1)])
            thr = self.config.ms_jump_threshold_s
            if thr is not None and abs(self.state[0]) > thr * SPEED_OF_LIGHT_MPS:
                n_ms = np.round(self.state[0] / (1e-3 * SPEED_OF_LIGHT_MPS))
                jump = -n_ms * 1e-3 * SPEED_OF_LIGHT_MPS
                self.state[0] += jump
                self.jumps.append(ClockJump(t_s=t_s, jump_m=float(jump)))
        self.t_s = max(t_s, self.t_s)
