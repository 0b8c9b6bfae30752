"""Closed-form discretization of the integrated Gauss-Markov blocks (v2v.estimation.process).

The filter's process blocks ([p, v] per axis, [clk, drift], [azimuth, yaw rate]) are
discretized by :func:`gm_integrated_block` in closed form. Checked here against three
independent things: Van Loan's matrix-exponential algorithm (scipy ``expm``), a 60-digit
decimal evaluation of the exact integrals (round-off of the cancelling brackets), and the
theory of the process (semigroup property of an exact discretization, the white-noise
acceleration limit for dt << tau, the GM steady state for dt >> tau).
"""

from __future__ import annotations

import math
from decimal import Decimal, getcontext

import numpy as np
import pytest

from v2v.estimation.process import (
    ProcessNoiseConfig,
    _gm_integrated,
    azimuth_block,
    gm_integrated_block,
    van_loan,
    vehicle_block,
)

EPS = np.finfo(float).eps
DTS = np.geomspace(1e-4, 10.0, 61)  # s
# (tau s, sigma, white PSD on the level): paper velocity (horizontal, vertical), clock drift,
# the default azimuth / yaw-rate block, and a clock with bias white noise
CASES = [(2.0, 10.0, 0.0), (2.0, 1.0, 0.0), (10.0, 1000.0, 0.0), (1.0, math.radians(30.0), math.radians(5.0) ** 2),
         (10.0, 1000.0, 3.0)]


def _exact_decimal(tau: float, sigma: float, dt: float, q0: float) -> np.ndarray:
    """Q of the integrated GM from its integrals, evaluated with 60 significant digits:
    Q11 = q0 dt + q tau^2 int_0^dt (1 - e^-s/tau)^2 ds, Q12 = q tau int (1 - e^-s/tau) e^-s/tau ds,
    Q22 = q int e^-2s/tau ds."""
    getcontext().prec = 60
    tau_d, sig_d, dt_d, q0_d = (Decimal(float(v)) for v in (tau, sigma, dt, q0))
    q = 2 * sig_d * sig_d / tau_d
    e1, e2 = (-dt_d / tau_d).exp(), (-2 * dt_d / tau_d).exp()
    q11 = q0_d * dt_d + q * tau_d**2 * (dt_d - 2 * tau_d * (1 - e1) + tau_d * (1 - e2) / 2)
    q12 = q * tau_d**2 * ((1 - e1) - (1 - e2) / 2)
    q22 = q * tau_d * (1 - e2) / 2
    return np.array([[float(q11), float(q12)], [float(q12), float(q22)]])


def _expm_atol(q_ref: np.ndarray) -> float:
    """Absolute tolerance on F from Van Loan's expm: expm computes all blocks of exp(M)
    together, so its round-off in any entry (the exact-zero F21 included) scales with the
    size of exp(M)'s entries: the O(1) F block, or the Q side (Phi^-1 Q, ~|Q| for dt <~ tau;
    sigma = 1000 m/s gives |Q| ~ 1e4). Measured: |F21| <= 0.7 eps max|Q| over the cases and
    dt below on an AMD EPYC (-1.1e-13 for the clock drift at dt = 0.08 s), ~1e-15 on the CPU
    these tests were first run on. 4 eps max(1, |Q|): a margin >= 5x over what was measured."""
    return 4.0 * EPS * max(1.0, float(np.abs(q_ref).max()))


@pytest.mark.parametrize("tau,sigma,q0", CASES)
def test_closed_form_matches_van_loan_expm(tau, sigma, q0):
    """Same F and Q as Van Loan (1978) with scipy's expm over dt in [1e-4, 10] s.

    Tolerance: 1e-12 relative per element, loosened where expm itself loses digits: Van
    Loan's upper-right block is Phi^-1 Q, which grows as e^(2 dt/tau) relative to Q, so the
    product Phi (Phi^-1 Q) carries ~eps e^(2a) relative round-off (measured 4e-9 at a = 10;
    the decimal test below shows that error is expm's, not the closed form's)."""
    for dt in DTS:
        f, q = gm_integrated_block(tau, sigma, dt, q0)
        f_ref, q_ref = van_loan(*_gm_integrated(tau, sigma, q0), dt)
        a = dt / tau
        rtol = max(1e-12, 4.0 * EPS * math.exp(2.0 * a))
        np.testing.assert_allclose(q, q_ref, rtol=rtol, atol=0.0, err_msg=f"Q at dt={dt}")
        np.testing.assert_allclose(f, f_ref, rtol=rtol, atol=_expm_atol(q_ref), err_msg=f"F at dt={dt}")
        assert f[1, 0] == 0.0


@pytest.mark.parametrize("tau,sigma,q0", CASES)
def test_closed_form_round_off_against_60_digit_integrals(tau, sigma, q0):
    """The Q11 and Q12 brackets cancel to O(a^3) and O(a^2): evaluated naively in double
    they lose ~eps / a^2 (1e-8 relative at dt/tau = 1e-4). The series branch and expm1 must
    keep every element within a few ulps (1e-14 relative) of the 60-digit value."""
    for dt in DTS:
        q = gm_integrated_block(tau, sigma, dt, q0)[1]
        np.testing.assert_allclose(q, _exact_decimal(tau, sigma, dt, q0), rtol=1e-14, atol=0.0,
                                   err_msg=f"dt={dt}")


def test_series_and_closed_branches_join_continuously():
    """Either side of the branch point a = 0.5 both expressions are the same function."""
    tau = 2.0
    lo = gm_integrated_block(tau, 10.0, 0.5 * tau * (1 - 1e-12))[1]
    hi = gm_integrated_block(tau, 10.0, 0.5 * tau * (1 + 1e-12))[1]
    np.testing.assert_allclose(lo, hi, rtol=1e-11)


@pytest.mark.parametrize("tau,sigma,q0", CASES)
def test_exact_discretization_is_a_semigroup(tau, sigma, q0):
    """An exact discretization composes: two steps of dt equal one step of 2 dt,
    F(2dt) = F(dt)^2 and Q(2dt) = F(dt) Q(dt) F(dt)^T + Q(dt) (to round-off)."""
    for dt in (1e-3, 0.05, 0.1, 0.7, 3.0):
        f1, q1 = gm_integrated_block(tau, sigma, dt, q0)
        f2, q2 = gm_integrated_block(tau, sigma, 2 * dt, q0)
        np.testing.assert_allclose(f1 @ f1, f2, rtol=1e-13, atol=1e-300)
        np.testing.assert_allclose(f1 @ q1 @ f1.T + q1, q2, rtol=1e-12)


def test_short_step_is_the_white_noise_acceleration_model():
    """dt << tau: the GM rate is a random walk and Q tends to Pabolleta (2021)'s continuous
    white-noise model q [[dt^3/3, dt^2/2], [dt^2/2, dt]] (relative corrections O(dt/tau))."""
    tau, sigma, dt = 2.0, 10.0, 1e-4
    q = 2.0 * sigma**2 / tau
    got = gm_integrated_block(tau, sigma, dt)[1]
    wna = q * np.array([[dt**3 / 3, dt**2 / 2], [dt**2 / 2, dt]])
    np.testing.assert_allclose(got, wna, rtol=2 * dt / tau)


def test_long_step_reaches_the_gauss_markov_steady_state():
    """dt >> tau: the rate forgets its past (F22 -> 0) and its noise is the GM steady-state
    variance sigma^2; the level integrates it like a random walk of PSD q tau^2 = 2 sigma^2 tau."""
    tau, sigma, dt = 2.0, 10.0, 200.0
    f, q = gm_integrated_block(tau, sigma, dt)
    assert f[1, 1] < 1e-40
    assert q[1, 1] == pytest.approx(sigma**2, rel=1e-15)
    assert q[0, 0] / dt == pytest.approx(2.0 * sigma**2 * tau, rel=2 * tau / dt)


def test_blocks_are_assembled_from_the_closed_form():
    """vehicle_block / azimuth_block place each axis' [level, rate] pair (paper section 3.2 values)."""
    cfg = ProcessNoiseConfig()
    f, q = vehicle_block(cfg, 0.1)
    for i, j, tau, sig in ((0, 3, 2.0, 10.0), (1, 4, 2.0, 10.0), (2, 5, 2.0, 1.0), (6, 7, 10.0, 1000.0)):
        fr, qr = van_loan(*_gm_integrated(tau, sig), 0.1)
        ix = np.ix_([i, j], [i, j])
        np.testing.assert_allclose(f[ix], fr, rtol=1e-12, atol=_expm_atol(qr))
        np.testing.assert_allclose(q[ix], qr, rtol=1e-12)
    fa, qa = azimuth_block(cfg, 0.1)
    fr, qr = van_loan(*_gm_integrated(cfg.yaw_rate_tau_s, cfg.yaw_rate_sigma_rps, cfg.azimuth_rw_rad_per_sqrt_s**2), 0.1)
    np.testing.assert_allclose(fa, fr, rtol=1e-12, atol=_expm_atol(qr))
    np.testing.assert_allclose(qa, qr, rtol=1e-12)


def test_compiled_blocks_are_the_python_closed_form_bit_for_bit():
    """The production filter predicts with F, Q computed inside a kernel
    (kernels.vehicle_fq / gm_block_into). They evaluate gm_integrated_block's expressions
    with the same operations in the same order and the same libm (expm1, exp, pow), so the
    result must be *equal*, not close: any difference would mean two process models."""
    from v2v.estimation import kernels

    cfg = ProcessNoiseConfig()
    vpar = np.array([cfg.vel_tau_s, cfg.vel_sigma_horizontal_mps, cfg.vel_sigma_vertical_mps, cfg.drift_tau_s,
                     cfg.drift_sigma_mps, 3.0])
    cfg3 = ProcessNoiseConfig(clock_bias_psd_m2ps=3.0)
    fb, qb, fa, qa = np.empty((8, 8)), np.empty((8, 8)), np.empty((2, 2)), np.empty((2, 2))
    for dt in np.concatenate([DTS, [0.3333333333333333, 0.5, 1.0, 2.0]]):  # both branches of the series switch
        kernels.vehicle_fq(vpar, float(dt), fb, qb)
        f, q = vehicle_block(cfg3, float(dt))
        assert np.array_equal(fb, f) and np.array_equal(qb, q), dt
        kernels.gm_block_into(cfg.yaw_rate_tau_s, cfg.yaw_rate_sigma_rps, float(dt), cfg.azimuth_rw_rad_per_sqrt_s**2,
                              fa, qa, 0, 1)
        f, q = azimuth_block(cfg, float(dt))
        assert np.array_equal(fa, f) and np.array_equal(qa, q), dt
