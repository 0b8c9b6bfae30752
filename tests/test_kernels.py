"""Compiled batch kernels (v2v.estimation.kernels) against hand computation and finite differences.

Each batch kernel builds its own Jacobian row inside the compiled loop, so its rows are
checked here the way STYLE.md asks for every Jacobian: one update of a single measurement
is compared with the textbook sequential update (MacGougan (2009) table 3.1:
``S = H P H^T + R``, ``K = P H^T / S``, ``x+ = x + K nu``, ``P+ = P - K S K^T``) built
from a *central finite-difference* Jacobian of the measurement function written out here
from the physics (range, bearing, SD range rate, SD range). Central differences with step
``1e-6 * max(1, |x_i|)`` have truncation error ~h^2 f''' and round-off ~eps f / h,
i.e. ~1e-9 relative on these smooth functions, so updates are compared to 1e-6 relative.
The second-order mean/variance (Gelb 1974 sec. 6.1) use a finite-difference Hessian of
``f(d)`` the same way.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from v2v.estimation import kernels
from v2v.estimation.filter import cond_sym
from v2v.frames import wrap_angle

R_UWB = 0.5**2
R_BRG = math.radians(0.5) ** 2
GATE = 3.2905
ONE_TENTH = np.array([0.1])  # the filter's nonlinear_fraction, one per measurement


def _fd_jac(f, x, step=1e-6):
    j = np.zeros(len(x))
    for i in range(len(x)):
        h = step * max(1.0, abs(x[i]))
        xp, xm = x.copy(), x.copy()
        xp[i] += h
        xm[i] -= h
        j[i] = (f(xp) - f(xm)) / (2 * h)
    return j


def _fd_hess_d(f_d, d, step=1e-4):
    """Hessian of f(d), d in R^3, by central differences of f."""
    hmat = np.zeros((3, 3))
    for i in range(3):
        for k in range(3):
            e_i, e_k = np.eye(3)[i] * step, np.eye(3)[k] * step
            hmat[i, k] = (f_d(d + e_i + e_k) - f_d(d + e_i - e_k) - f_d(d - e_i + e_k) + f_d(d - e_i - e_k)) / (
                4 * step * step)
    return hmat


def _textbook(x, P, hrow, nu, r_var):
    s = float(hrow @ P @ hrow) + r_var
    k = P @ hrow / s
    return x + k * nu, P - np.outer(k, k) * s, s


def _spd(rng, n, scale):
    a = rng.normal(size=(n, n)) * scale
    return a @ a.T + np.eye(n) * scale**2


def test_scalar_update_by_hand_two_nonzeros():
    """x = [1, 2, 3], P = diag(4, 2, 1) + P01 = 1, h = [1, -1, 0] (a difference), z - h x = 0.5, r = 1:
    S = 4 + 2 - 2*1 + 1 = 5; P h^T = [4 - 1, 1 - 2, 0] = [3, -1, 0]; K = [0.6, -0.2, 0];
    x+ = [1.3, 1.9, 3]; P+ = P - K K^T S = P - [[1.8, -0.6, 0], [-0.6, 0.2, 0], [0, 0, 0]]."""
    x = np.array([1.0, 2.0, 3.0])
    P = np.array([[4.0, 1.0, 0.0], [1.0, 2.0, 0.0], [0.0, 0.0, 1.0]])
    s, st = kernels.scalar_update(x, P, np.array([0, 1]), np.array([1.0, -1.0]), 2, 0.5, 1.0, GATE, True)
    assert st == kernels.ACCEPTED and s == pytest.approx(5.0, abs=1e-15)
    np.testing.assert_allclose(x, [1.3, 1.9, 3.0], atol=1e-15)
    np.testing.assert_allclose(P, [[2.2, 1.6, 0.0], [1.6, 1.8, 0.0], [0.0, 0.0, 1.0]], atol=1e-14)
    assert np.array_equal(P, P.T)  # q_i q_j == q_j q_i: exactly symmetric


def test_scalar_update_gate_and_nonfinite_leave_state():
    """|nu| / sqrt(S) = 7.5 / sqrt(5) = 3.354 > 3.29 (alpha = 0.001): rejected; NaN: non-finite."""
    x = np.array([1.0, 2.0])
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    x0, p0 = x.copy(), P.copy()
    idx, val = np.array([0]), np.array([1.0])
    assert kernels.scalar_update(x, P, idx, val, 1, 7.5, 1.0, GATE, True)[1] == kernels.REJECTED
    assert kernels.scalar_update(x, P, idx, val, 1, math.nan, 1.0, GATE, True)[1] == kernels.NONFINITE
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(P, p0)
    assert kernels.scalar_update(x, P, idx, val, 1, 7.5, 1.0, GATE, False)[1] == kernels.ACCEPTED  # untested


@pytest.mark.parametrize("x", [math.pi, -math.pi, 3 * math.pi, 0.1, -2.5, 7.0])
def test_wrap_angle_matches_frames_at_pi(x):
    """(-pi, pi]: +pi stays +pi, -pi maps to +pi (the measurement owns its residual)."""
    assert kernels.wrap_angle(x) == pytest.approx(float(wrap_angle(x)), abs=1e-15)
    assert kernels.wrap_angle(-math.pi) == math.pi


def _uwb_state(rng, lead_a: bool, bias_scale: bool):
    # layout: [p_a (3), p_b (3), bias, scale]; a may be the lead (origin)
    x = np.array([3.0, -2.0, 0.2, 20.0, 15.0, -0.1, 0.25, 0.003])
    P = _spd(rng, 8, 0.02)
    P[6:, :] *= 0.5
    P[:, 6:] *= 0.5
    P[7, :] *= 0.01
    P[:, 7] *= 0.01
    sa = -1 if lead_a else 0
    ib, isc = (6, 7) if bias_scale else (-1, -1)

    def f(xx):
        pa = np.zeros(3) if lead_a else xx[0:3]
        rho = np.linalg.norm(xx[3:6] - pa)
        return (1.0 + xx[7]) * rho + xx[6] if bias_scale else rho

    return x, P, sa, ib, isc, f


@pytest.mark.parametrize("lead_a", [False, True])
@pytest.mark.parametrize("bias_scale", [False, True])
def test_uwb_batch_single_range_matches_textbook_with_fd_jacobian(lead_a, bias_scale):
    rng = np.random.default_rng(7)
    x, P, sa, ib, isc, f = _uwb_state(rng, lead_a, bias_scale)
    hrow = _fd_jac(f, x)
    if lead_a:
        hrow[0:3] = 0.0  # a is the lead: those entries are not states of the range
    pa = np.zeros(3) if lead_a else x[0:3]
    d = x[3:6] - pa
    pd = P[3:6, 3:6] + (0.0 if lead_a else P[0:3, 0:3] - P[0:3, 3:6] - P[3:6, 0:3])
    h2 = _fd_hess_d(np.linalg.norm, d)
    m = h2 @ pd
    h2_mean, h2_var = 0.5 * np.trace(m), 0.5 * np.trace(m @ m)
    z = f(x) + h2_mean + 0.3
    x_exp, p_exp, s_exp = _textbook(x, P, hrow, z - f(x) - h2_mean, R_UWB + h2_var)
    xk, pk = x.copy(), P.copy()
    n_rec, kind, meas, nu, s, st = kernels.uwb_batch(
        xk, pk, np.array([sa]), np.array([3]), np.array([ib]), np.array([isc]), np.array([z]), R_UWB, GATE, ONE_TENTH,
        False, 0.0, 0.0, False, 0.0, 0.0)
    assert n_rec == 1 and st[0] == kernels.ACCEPTED and kind[0] == kernels.REC_UWB
    assert nu[0] == pytest.approx(0.3, rel=1e-6)
    assert s[0] == pytest.approx(s_exp, rel=1e-6)
    np.testing.assert_allclose(xk, x_exp, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(pk, p_exp, rtol=1e-6, atol=1e-9 * np.abs(P).max())


def test_uwb_batch_defers_when_second_order_variance_is_large():
    """P_d ~ (10 m)^2 at 20 m: tr((H2 P_d)^2)/2 ~ (100/20)^2 = 25 m^2 >> 0.1 * 0.25 m^2: deferred."""
    rng = np.random.default_rng(3)
    x, P, sa, ib, isc, f = _uwb_state(rng, False, False)
    P[:6, :6] += np.eye(6) * 100.0
    x0, p0 = x.copy(), P.copy()
    n_rec, _, _, _, _, st = kernels.uwb_batch(x, P, np.array([0]), np.array([3]), np.array([-1]), np.array([-1]),
                                              np.array([f(x)]), R_UWB, GATE, ONE_TENTH, False, 0.0, 0.0, False, 0.0, 0.0)
    assert n_rec == 1 and st[0] == kernels.DEFERRED
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(P, p0)


def test_uwb_constraint_moves_bias_exactly_onto_its_bound():
    """MacGougan (2009) eq. 3.19-3.22: a bias above max gets a pseudo-measurement at *min*
    with variance P_ii (max - min) / (x - max), which puts the updated bias exactly on max."""
    rng = np.random.default_rng(11)
    x, P, sa, ib, isc, f = _uwb_state(rng, False, True)
    P[6, 6] += 0.25  # bias sigma ~0.5 m: the range pulls it well past the bound
    z = f(x) + 1.0  # pulls the bias (0.25) up past the bound 0.26
    n_rec, kind, _, _, _, st = kernels.uwb_batch(
        x, P, np.array([0]), np.array([3]), np.array([6]), np.array([7]), np.array([z]), R_UWB, 10.0, ONE_TENTH,
        True, -0.26, 0.26, False, 0.0, 0.0)
    assert st[0] == kernels.ACCEPTED
    assert list(kind[1:n_rec]) == [kernels.REC_CONSTRAINT] * (n_rec - 1) and n_rec >= 2
    assert x[6] == pytest.approx(0.26, abs=1e-12)


def _bearing_state(estimated: bool):
    # layout: [p_a (3), p_b (3), alpha_a]
    x = np.array([2.0, 1.0, 0.0, 12.0, 25.0, 0.3, 0.2])
    P = _spd(np.random.default_rng(5), 7, 0.02)
    az_rep = 0.15

    def f(xx):
        d = xx[3:6] - xx[0:3]
        return math.atan2(d[0], d[1]) - (xx[6] if estimated else az_rep)

    return x, P, az_rep, f


@pytest.mark.parametrize("estimated", [False, True], ids=["azimuth_known", "azimuth_estimated"])
def test_bearing_batch_single_bearing_matches_textbook_with_fd_jacobian(estimated):
    x, P, az_rep, f = _bearing_state(estimated)
    hrow = _fd_jac(f, x)
    d = x[3:6] - x[0:3]
    pd = P[0:3, 0:3] + P[3:6, 3:6] - P[0:3, 3:6] - P[3:6, 0:3]
    m = _fd_hess_d(lambda dd: math.atan2(dd[0], dd[1]), d) @ pd
    h2_mean, h2_var = 0.5 * np.trace(m), 0.5 * np.trace(m @ m)
    z = float(wrap_angle(f(x) + h2_mean + 0.01))
    x_exp, p_exp, s_exp = _textbook(x, P, hrow, 0.01, R_BRG + h2_var)
    ready = np.array([False] * 6 + [True])
    nu, s, st = kernels.bearing_batch(x, P, np.array([0]), np.array([3]), np.array([6 if estimated else -1]), ready,
                                      np.array([z]), np.array([az_rep]), R_BRG, GATE, ONE_TENTH, 1.0)
    assert st[0] == kernels.ACCEPTED
    assert nu[0] == pytest.approx(0.01, rel=1e-6)
    assert s[0] == pytest.approx(s_exp, rel=1e-6)
    np.testing.assert_allclose(x, x_exp, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(P, p_exp, rtol=1e-6, atol=1e-9 * np.abs(p_exp).max())


def test_bearing_first_use_initializes_azimuth_with_zero_innovation():
    """alpha0 = atan2(dE, dN) - beta: the first bearing has zero innovation (up to the second-order
    mean) and the azimuth's variance drops from the diffuse prior."""
    x, P, _, _ = _bearing_state(True)
    ready = np.zeros(7, dtype=bool)
    nu, s, st = kernels.bearing_batch(x, P, np.array([0]), np.array([3]), np.array([6]), ready, np.array([0.4]),
                                      np.array([np.nan]), R_BRG, GATE, ONE_TENTH, 1.0)
    assert st[0] == kernels.ACCEPTED and ready[6]
    assert abs(nu[0]) < 1e-3 and P[6, 6] < 1e-2


def test_bearing_degenerate_geometry():
    x, P, _, _ = _bearing_state(False)
    x[3:6] = x[0:3] + [0.3, 0.4, 5.0]  # horizontal distance 0.5 m < 1 m
    _, _, st = kernels.bearing_batch(x, P, np.array([0]), np.array([3]), np.array([-1]), np.zeros(7, dtype=bool),
                                     np.array([0.1]), np.array([0.0]), R_BRG, GATE, ONE_TENTH, 1.0)
    assert st[0] == kernels.DEGENERATE


def _assert_update_close(x, P, x_exp, p_exp, tol=1e-6):
    """GNSS rows: the ECEF positions are ~2e7 m, so a finite-difference step must be ~1 cm
    (round-off eps * 2e7 / h), which leaves ~1e-7 relative error in the small position
    Jacobian entries. Compared to ``tol`` (default 1e-6) of each quantity's own standard
    deviation."""
    sd = np.sqrt(np.diag(p_exp))
    np.testing.assert_array_less(np.abs(x - x_exp), tol * sd)
    np.testing.assert_array_less(np.abs(P - p_exp), tol * np.outer(sd, sd))


def _gnss_geometry(rng):
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    base = np.array([-2.69e6, -4.29e6, 3.86e6])
    sv = base + rng.normal(size=(4, 3)) * 1.5e7
    svv = rng.normal(size=(4, 3)) * 3e3
    return rot, base, sv, svv


def _flushed(batch, x, P, *args):
    """A GNSS batch kernel with a fresh deferred-update buffer, applied to P afterwards
    (the filter shares one buffer across vehicles and applies it once per epoch)."""
    Q = np.empty((kernels.LAZY_RANK, x.shape[0]))
    *out, kq = batch(x, P, Q, 0, *args)
    kernels.lazy_flush(P, Q, kq)
    return out


def test_sd_pseudorange_batch_matches_textbook_with_fd_jacobian():
    """h = |sv - (base + R^T p)| - rho_lead + clk (MacGougan (2009) eq. 3.2-3.3)."""
    rng = np.random.default_rng(21)
    rot, base, sv, _ = _gnss_geometry(rng)
    x = np.array([10.0, -5.0, 1.0, 0.0, 0.0, 0.0, 30.0, 0.2])  # [p, v, clk, drift]
    P = _spd(rng, 8, 0.5)
    rho_lead = np.linalg.norm(sv - base, axis=1)

    def f(xx, o=0):
        return np.linalg.norm(sv[o] - (base + xx[0:3] @ rot)) - rho_lead[o] + xx[6]

    z = np.array([f(x) + 1.0, 0, 0, 0])
    # the range is ~2e7 m: round-off eps * 2e7 / h needs a step of ~1 cm (truncation ~h^2 / rho^2: nil)
    x_exp, p_exp, s_exp = _textbook(x, P, _fd_jac(f, x, step=1e-3), 1.0, 50.0)
    nu, s, st = _flushed(kernels.sd_pseudorange_batch, x, P, base, rot, 0, 6, sv, rho_lead, z, np.array([0]),
                         np.zeros(4, dtype=bool), 50.0, GATE)
    assert st[0] == kernels.ACCEPTED and nu[0] == pytest.approx(1.0, rel=1e-6) and s[0] == pytest.approx(s_exp)
    _assert_update_close(x, P, x_exp, p_exp)


def test_sd_doppler_batch_matches_textbook_with_fd_jacobian():
    """h = u . (vsv - (vb + R^T dv)) - rate_lead + drift, u the unit line of sight from the vehicle."""
    rng = np.random.default_rng(22)
    rot, base, sv, svv = _gnss_geometry(rng)
    base_vel = np.array([10.0, -3.0, 0.5])
    x = np.array([10.0, -5.0, 1.0, 1.5, -0.5, 0.1, 30.0, 0.2])
    P = _spd(rng, 8, 0.3)
    rate_lead = np.array([-250.0, 10.0, 0.0, 0.0])

    def f(xx, o=0):
        r = base + xx[0:3] @ rot
        v = base_vel + xx[3:6] @ rot
        u = (sv[o] - r) / np.linalg.norm(sv[o] - r)
        return u @ (svv[o] - v) - rate_lead[o] + xx[7]

    z = np.array([f(x) + 0.05, 0, 0, 0])
    x_exp, p_exp, s_exp = _textbook(x, P, _fd_jac(f, x, step=1e-3), 0.05, 0.02)
    nu, s, st = _flushed(kernels.sd_doppler_batch, x, P, base, base_vel, rot, 0, 3, 7, sv, svv, rate_lead, z,
                         np.array([0]), np.zeros(4, dtype=bool), 0.02, GATE)
    assert st[0] == kernels.ACCEPTED and nu[0] == pytest.approx(0.05, rel=1e-6) and s[0] == pytest.approx(s_exp)
    _assert_update_close(x, P, x_exp, p_exp)


def test_predict_vehicle_blocks_is_f_p_ft_plus_q():
    """Block-diagonal F (two 8x8 vehicle blocks after one other state), dense F P F^T + Q."""
    rng = np.random.default_rng(9)
    n = 17
    P = _spd(rng, n, 1.0)
    x = rng.normal(size=n)
    fb = np.eye(8) + rng.normal(size=(8, 8)) * 0.1
    qb = _spd(rng, 8, 0.1)
    f = np.eye(n)
    q = np.zeros((n, n))
    for s in (1, 9):
        f[s:s + 8, s:s + 8] = fb
        q[s:s + 8, s:s + 8] = qb
    x_exp, p_exp = f @ x, f @ P @ f.T + q
    kernels.predict_vehicle_blocks(x, P, 1, 2, fb, qb)
    kernels.symmetrize(P)
    np.testing.assert_allclose(x, x_exp, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(P, p_exp, rtol=1e-12, atol=1e-12)
    assert np.array_equal(P, P.T)


def test_bearing_batch_deferred_rank_k_equals_sequential_updates():
    """70 bearings (> LAZY_RANK = 32, so the deferred covariance is flushed mid-batch) among 8
    vehicles: the batch equals 70 textbook sequential updates (dense P, each re-linearized at
    the current x, with the second-order terms), to round-off (1e-9 of each quantity's sd)."""
    rng = np.random.default_rng(4)
    nveh = 8
    n = 3 * nveh
    x = np.concatenate([[3.5 * (v % 3), -20.0 * (v // 3) - 12.0, 0.0] for v in range(nveh)])
    P = _spd(rng, n, 0.05)
    pairs = [(a, b) for a in range(nveh) for b in range(nveh) if a != b][:70]
    z = np.array([math.atan2(*(x[3 * b:3 * b + 2] - x[3 * a:3 * a + 2])) + rng.normal() * 0.003 for a, b in pairs])
    xe, pe = x.copy(), P.copy()
    for (a, b), zk in zip(pairs, z, strict=True):
        d = xe[3 * b:3 * b + 3] - xe[3 * a:3 * a + 3]
        r2 = d[0] ** 2 + d[1] ** 2
        j = np.array([d[1] / r2, -d[0] / r2, 0.0])
        hrow = np.zeros(n)
        hrow[3 * a:3 * a + 3], hrow[3 * b:3 * b + 3] = -j, j
        pd = pe[3 * a:3 * a + 3, 3 * a:3 * a + 3] + pe[3 * b:3 * b + 3, 3 * b:3 * b + 3] \
            - pe[3 * a:3 * a + 3, 3 * b:3 * b + 3] - pe[3 * b:3 * b + 3, 3 * a:3 * a + 3]
        e, nn = d[0], d[1]
        h2 = np.array([[-2 * e * nn, e * e - nn * nn, 0], [e * e - nn * nn, 2 * e * nn, 0], [0, 0, 0]]) / r2**2
        m = h2 @ pd
        nu = float(wrap_angle(zk - math.atan2(e, nn) - 0.5 * np.trace(m)))
        xe, pe, _ = _textbook(xe, pe, hrow, nu, R_BRG + 0.5 * np.trace(m @ m))
    sa = np.array([3 * a for a, _ in pairs])
    sb = np.array([3 * b for _, b in pairs])
    m_ = len(pairs)
    _, _, st = kernels.bearing_batch(x, P, sa, sb, -np.ones(m_, dtype=np.int64), np.zeros(n, dtype=bool), z,
                                     np.zeros(m_), R_BRG, 100.0, np.full(m_, 1e6), 1.0)
    assert (st == kernels.ACCEPTED).all()
    _assert_update_close(x, P, xe, pe, tol=1e-9)
    assert np.array_equal(P, P.T)


def _bearing_case(rng, nveh=7, n_az=2):
    """Vehicles 1..nveh (the lead, 0, at the origin: a bearing to or from it has one slice),
    3 states each, then azimuth states of vehicles 1..n_az (initialized), a dense SPD P, and
    every ordered pair's bearing with noise; returns (x, P, pairs, sa, sb, iaz, z, az_rep)."""
    n = 3 * nveh + n_az
    x = np.zeros(n)
    for v in range(1, nveh + 1):
        x[3 * (v - 1):3 * v] = [3.5 * (v % 3), -20.0 * (v // 3) - 12.0, 0.3 * v]
    az_state = {v: 3 * nveh + v - 1 for v in range(1, n_az + 1)}
    x[3 * nveh:] = rng.normal(size=n_az) * 0.02
    P = _spd(rng, n, 0.05)
    pairs = [(a, b) for a in range(nveh + 1) for b in range(nveh + 1) if a != b]
    az_rep = rng.normal(size=len(pairs)) * 0.01

    def pos(xx, v):
        return np.zeros(3) if v == 0 else xx[3 * (v - 1):3 * v]

    z = np.array([math.atan2(*(pos(x, b) - pos(x, a))[:2]) - (x[az_state[a]] if a in az_state else az_rep[k])
                  + rng.normal() * 0.003 for k, (a, b) in enumerate(pairs)])
    sa = np.array([3 * (a - 1) if a else -1 for a, _ in pairs])
    sb = np.array([3 * (b - 1) if b else -1 for _, b in pairs])
    iaz = np.array([az_state.get(a, -1) for a, _ in pairs])
    return x, P, pairs, sa, sb, iaz, z, az_rep, az_state, pos


def test_bearing_batch_subspace_equals_sequential_updates_with_azimuths_and_a_blunder():
    """56 bearings among the lead and 7 vehicles, two of them with (initialized) azimuth
    states, one bearing a 0.3 rad blunder: the batch (which runs in the subspace of the 14
    horizontal positions and 2 azimuths, kernels._bearing_batch_subspace) equals textbook
    sequential updates on the dense P (MacGougan (2009) eq. 3.16-3.18, each bearing
    re-linearized at the current x with its second-order terms and tested with |nu| <= k sqrt(S),
    eq. 3.26-3.27) to round-off: the same statuses, x and P to 1e-9 of each quantity's sd,
    P exactly symmetric."""
    rng = np.random.default_rng(11)
    x, P, pairs, sa, sb, iaz, z, az_rep, az_state, pos = _bearing_case(rng)
    z[17] += 0.3
    n = len(x)
    xe, pe = x.copy(), P.copy()
    st_exp = []
    for k, (a, b) in enumerate(pairs):
        d = pos(xe, b) - pos(xe, a)
        r2 = d[0] ** 2 + d[1] ** 2
        j = np.array([d[1] / r2, -d[0] / r2, 0.0])
        hrow = np.zeros(n)
        if a:
            hrow[3 * (a - 1):3 * a] = -j
        if b:
            hrow[3 * (b - 1):3 * b] = j
        alpha = xe[az_state[a]] if a in az_state else az_rep[k]
        if a in az_state:
            hrow[az_state[a]] = -1.0
        ca = np.zeros((3, n))
        if a:
            ca[:, 3 * (a - 1):3 * a] = -np.eye(3)
        if b:
            ca[:, 3 * (b - 1):3 * b] += np.eye(3)
        pd = ca @ pe @ ca.T
        e, nn = d[0], d[1]
        h2 = np.array([[-2 * e * nn, e * e - nn * nn, 0], [e * e - nn * nn, 2 * e * nn, 0], [0, 0, 0]]) / r2**2
        m = h2 @ pd
        nu = float(wrap_angle(z[k] - (wrap_angle(math.atan2(e, nn) - alpha) + 0.5 * np.trace(m))))
        r = R_BRG + 0.5 * np.trace(m @ m)
        if abs(nu) > GATE * math.sqrt(float(hrow @ pe @ hrow) + r):
            st_exp.append(kernels.REJECTED)
            continue
        xe, pe, _ = _textbook(xe, pe, hrow, nu, r)
        st_exp.append(kernels.ACCEPTED)
    ready = np.zeros(n, dtype=bool)
    ready[list(az_state.values())] = True
    m_ = len(pairs)
    xs, ps = x.copy(), P.copy()  # (the subspace path itself, to show the batch took it)
    ok, *out_sub = kernels._bearing_batch_subspace(xs, ps, sa, sb, iaz, z, az_rep, R_BRG, GATE, np.full(m_, 1e6))
    out = kernels.bearing_batch(x, P, sa, sb, iaz, ready, z, az_rep, R_BRG, GATE, np.full(m_, 1e6), 1.0)
    assert ok and all(np.array_equal(a, b) for a, b in zip((xs, ps, *out_sub), (x, P, *out), strict=True))
    st = out[2]
    assert st.tolist() == st_exp and st[17] == kernels.REJECTED and (st == kernels.ACCEPTED).sum() == m_ - 1
    sd = np.sqrt(np.diag(pe))
    np.testing.assert_array_less(np.abs(x - xe), 1e-9 * sd)
    np.testing.assert_allclose(P, pe, rtol=1e-9, atol=1e-12 * np.abs(pe).max())
    assert np.array_equal(P, P.T)


@pytest.mark.parametrize("case", ["uninitialized_azimuth", "nonfinite_row"])
def test_bearing_batch_falls_back_to_the_full_state_path(case):
    """A batch that initializes an azimuth (it changes P outside the subspace), or whose
    covariance rows of the touched states are not all finite, runs on the lazily updated full
    covariance: bit for bit what kernels._bearing_batch_lazy gives."""
    rng = np.random.default_rng(12)
    x, P, pairs, sa, sb, iaz, z, az_rep, az_state, _ = _bearing_case(rng)
    ready = np.zeros(len(x), dtype=bool)
    if case == "uninitialized_azimuth":
        ready[az_state[1]] = True  # vehicle 2's azimuth is initialized by its first bearing
    else:
        ready[list(az_state.values())] = True
        P[0, 5] = P[5, 0] = np.inf  # (a covariance no filter should hold; the batch must not spread it)
    m_ = len(pairs)
    args = (sa, sb, iaz, None, z, az_rep, R_BRG, GATE, np.full(m_, 1e6), 1.0)
    x1, p1, r1 = x.copy(), P.copy(), ready.copy()
    out1 = kernels.bearing_batch(x1, p1, *args[:3], r1, *args[4:])
    x2, p2, r2 = x.copy(), P.copy(), ready.copy()
    out2 = kernels._bearing_batch_lazy(x2, p2, *args[:3], r2, *args[4:])
    for a, b in zip((x1, p1, r1, *out1), (x2, p2, r2, *out2), strict=True):
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    if case == "uninitialized_azimuth":
        assert r1[az_state[2]]


# --------------------------------------------------------------------------- GNSS epoch sequencing
def _sd_pr_model(rot, base, sv, rho_lead, ps=0, iclk=3):
    def f(xx, o):
        return np.linalg.norm(sv[o] - (base + xx[ps:ps + 3] @ rot)) - rho_lead[o] + xx[iclk]
    return f


@pytest.mark.parametrize("with_rejection", [False, True])
def test_sd_pseudorange_batch_equals_sequential_textbook_updates(with_rejection):
    """9 SD pseudoranges of one vehicle (the batch defers the covariance updates,
    kernels.lazy_scalar_update) equal 9 textbook sequential updates on the dense P, each
    re-linearized at the current x (row: minus the ENU unit line of sight, 1 for the clock;
    checked against finite differences above). Only the summation order differs, so they
    agree to round-off: P to 1e-9 of each sd product (the clock variance drops by ~1e3 in
    the first update, which costs ~3 digits); x to 2e-8 of its sd (~1 m here), because the
    predicted ~2e7 m ranges themselves carry ~4e-9 m of round-off (their ulp), which every
    innovation inherits. Other states move only through their correlations.
    With a 60 m blunder the test rejects it and x, P are what the other 8 updates make them."""
    rng = np.random.default_rng(31)
    rot = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    base = np.array([-2.69e6, -4.29e6, 3.86e6])
    sv = base + rng.normal(size=(9, 3)) * 1.5e7
    rho_lead = np.linalg.norm(sv - base, axis=1)
    n = 12  # [p (3), clk, other states (8)]
    x = np.concatenate([[8.0, -3.0, 0.5, 40.0], rng.normal(size=8)])
    P = _spd(rng, n, 0.7)
    P[3, :] *= 30.0  # clock much less known than the rest, as after a prediction
    P[:, 3] *= 30.0
    f = _sd_pr_model(rot, base, sv, rho_lead)
    truth = x + rng.normal(size=n) * np.sqrt(np.diag(P)) * 0.5
    z = np.array([f(truth, o) for o in range(9)]) + rng.normal(size=9) * 0.5
    if with_rejection:
        z[4] += 60.0
    r_var = 2.0 * 0.5**2
    xe, pe = x.copy(), P.copy()
    for o in range(9):
        los = sv[o] - (base + xe[0:3] @ rot)
        hrow = np.zeros(n)
        hrow[0:3] = -rot @ (los / np.linalg.norm(los))
        hrow[3] = 1.0
        nu = z[o] - f(xe, o)
        s = float(hrow @ pe @ hrow) + r_var
        if abs(nu) > GATE * math.sqrt(s):
            continue
        xe, pe, _ = _textbook(xe, pe, hrow, nu, r_var)
    _, _, st = _flushed(kernels.sd_pseudorange_batch, x, P, base, rot, 0, 3, sv, rho_lead, z, np.arange(9),
                        np.zeros(9, dtype=bool), r_var, GATE)
    assert (st == kernels.REJECTED).sum() == (1 if with_rejection else 0)
    if with_rejection:
        assert st[4] == kernels.REJECTED
    sd = np.sqrt(np.diag(pe))
    np.testing.assert_array_less(np.abs(x - xe), 2e-8 * sd)
    np.testing.assert_array_less(np.abs(P - pe), 1e-9 * np.outer(sd, sd))
    assert np.array_equal(P, P.T)


def _textbook_snooping(h, r, sigma, k):
    """Baarda data snooping written out (MacGougan (2009) section 3.5.1 screen): while the
    redundancy is >= 2, w_i = |e_i| / (sigma sqrt(Q_e,ii)) with e = (I - H (H^T H)^-1 H^T) r;
    flag the largest w > k."""
    m, npar = h.shape
    flagged = np.zeros(m, dtype=bool)
    while (~flagged).sum() - npar >= 2:
        use = np.flatnonzero(~flagged)
        hu = h[use]
        proj = hu @ np.linalg.inv(hu.T @ hu) @ hu.T
        e = (np.eye(len(use)) - proj) @ r[use]
        w = np.abs(e) / (sigma * np.sqrt(np.maximum(1.0 - np.diag(proj), 1e-12)))
        j = int(np.argmax(w))
        if w[j] <= k:
            return flagged, True
        flagged[use[j]] = True
    return flagged, False


def _los_design(rng, m):
    """(m, 4) pseudorange design rows [-u_enu, 1], satellites above 10 deg elevation."""
    az = rng.uniform(0, 2 * np.pi, m)
    el = rng.uniform(np.radians(10), np.radians(85), m)
    u = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=1)
    return np.hstack([-u, np.ones((m, 1))])


@pytest.mark.parametrize("n_blunders", [0, 1, 2, 3])
def test_screen_blunders_flags_what_data_snooping_flags(n_blunders):
    """200 seeded epochs of 7-11 satellites, sigma = 7 m residuals plus 0-3 blunders of
    15-40 sigma: the compiled screen flags exactly what the written-out w-test flags (same
    isolated status). Physics: a single blunder of >= 15 sigma is found; without blunders
    or with one, clean measurements are flagged at about alpha = 0.001 per test (<= 1 %
    allowed). With 2-3 blunders at 7-11 satellites, data snooping also flags clean ones
    (swamping: a blunder's residual leaks into the others through Q_e) and can miss one
    (masking), so only the equality is checked there."""
    rng = np.random.default_rng(100 + n_blunders)
    sigma, k = 7.0, 3.2905
    found = clean_flags = total_clean = 0
    for _ in range(200):
        m = int(rng.integers(7, 12))
        h = _los_design(rng, m)
        r = rng.normal(size=m) * sigma
        bad = rng.choice(m, n_blunders, replace=False)
        r[bad] += rng.choice([-1, 1], n_blunders) * rng.uniform(15, 40, n_blunders) * sigma
        got, iso = kernels.screen_blunders(h, r, sigma, k)
        exp, iso_exp = _textbook_snooping(h, r, sigma, k)
        np.testing.assert_array_equal(got, exp)
        assert iso == iso_exp
        found += int(got[bad].all())
        clean_flags += int(got.sum() - got[bad].sum())
        total_clean += m - n_blunders
    if n_blunders == 1:
        assert found >= 190
    if n_blunders <= 1:
        assert clean_flags <= max(3, 0.01 * total_clean)


def test_cond_sym_equals_numpy_cond_to_round_off():
    """Symmetric positive (semi-)definite 3x3 to 6x6 matrices with condition numbers 1 to 1e14
    (Q diag(lambda) Q^T, lambda chosen): the Jacobi-based condition number equals
    np.linalg.cond (SVD) and the constructed lambda_max / lambda_min. Both know the smallest
    eigenvalue only to ~eps * lambda_max, so they agree to a relative ~eps * cond (1e-13 * cond
    allowed: a few hundred eps of the matrix scale). Singular or non-finite: inf."""
    rng = np.random.default_rng(11)
    for _ in range(300):
        p = int(rng.integers(3, 7))
        cond = 10.0 ** rng.uniform(0, 14)
        lam = np.sort(np.exp(rng.uniform(0, np.log(cond), p)))
        lam[0], lam[-1] = 1.0, cond
        q, _ = np.linalg.qr(rng.normal(size=(p, p)))
        a = (q * (lam * 10.0 ** rng.uniform(-6, 6))) @ q.T
        a = 0.5 * (a + a.T)
        got = cond_sym(a)
        tol = 1e-13 * cond
        assert abs(got / np.linalg.cond(a) - 1.0) <= tol
        assert abs(got / cond - 1.0) <= tol
    assert cond_sym(np.diag([1.0, 2.0, 0.0])) == np.inf
    assert cond_sym(np.array([[1.0, np.nan], [np.nan, 1.0]])) == np.inf


def test_screen_blunders_singular_geometry_is_not_isolated():
    """Coplanar satellites at one elevation: H^T H is singular (clock and up are not
    separable): the screen stops without flagging and reports not isolated."""
    az = np.linspace(0, 2 * np.pi, 8, endpoint=False)
    el = np.radians(30.0)
    h = np.stack([-np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), -np.full(8, np.sin(el)), np.ones(8)], axis=1)
    flagged, iso = kernels.screen_blunders(h, np.zeros(8), 7.0, 3.29)
    assert not flagged.any() and not iso


def test_first_unflagged_order_moves_the_first_clean_measurement_first():
    """Elevation order 0..m-1; a blunder on the highest satellite: the second one goes first,
    the rest keep their order, nothing is excluded (one flag); two blunders: both excluded."""
    rng = np.random.default_rng(5)
    val = _los_design(rng, 9)
    z = rng.normal(size=9) * 7.0
    h_pred = np.zeros(9)
    z1 = z.copy()
    z1[0] += 300.0
    order, excluded, iso, n_flag = kernels.first_unflagged_order(h_pred, val, z1, 7.0, 3.2905, 4)
    assert n_flag == 1 and iso and not excluded.any()
    np.testing.assert_array_equal(order, [1, 0, 2, 3, 4, 5, 6, 7, 8])
    z2 = z1.copy()
    z2[1] -= 300.0
    order, excluded, iso, n_flag = kernels.first_unflagged_order(h_pred, val, z2, 7.0, 3.2905, 4)
    assert n_flag == 2 and excluded[0] and excluded[1] and excluded.sum() == 2
    np.testing.assert_array_equal(order, [2, 0, 1, 3, 4, 5, 6, 7, 8])
    # fewer than cols + 2 measurements: no screen, plain order, not isolated
    order, excluded, iso, n_flag = kernels.first_unflagged_order(h_pred[:5], val[:5], z1[:5], 7.0, 3.2905, 4)
    assert n_flag == 0 and not iso and list(order) == [0, 1, 2, 3, 4]


def test_clock_jump_test_finds_a_common_step():
    """A 1 ms receiver clock jump (299 792.458 m) on every SD pseudorange: detected, with the
    median innovation as the step; ordinary noise and a single blunder are not a jump."""
    rng = np.random.default_rng(8)
    val = _los_design(rng, 8)
    P = np.diag([1.0, 1.0, 2.0, 4.0])
    idx = np.arange(4)
    h_pred = np.zeros(8)
    noise = rng.normal(size=8) * 7.0
    jump, med = kernels.clock_jump_test(P, idx, h_pred, val, noise + 299792.458, 50.0, 3.2905)
    assert jump and med == pytest.approx(299792.458 + np.median(noise))
    assert not kernels.clock_jump_test(P, idx, h_pred, val, noise, 50.0, 3.2905)[0]
    one = noise.copy()
    one[3] += 1e4
    assert not kernels.clock_jump_test(P, idx, h_pred, val, one, 50.0, 3.2905)[0]


def test_pair_satellites_is_intersect_finite_and_elevation_order():
    """Common PRNs of vehicle and lead (first occurrence), both pseudoranges finite (the
    others counted), sorted by decreasing elevation from the base (up = 3rd ENU axis)."""
    rot = np.eye(3)  # ENU = ECEF axes here: elevation = atan2(z, hypot(x, y)) of sv - base
    base = np.zeros(3)
    prn_lead = np.array([3, 7, 12, 19, 25, 30], dtype=np.int64)
    el_deg = np.array([20.0, 70.0, 45.0, 10.0, 85.0, 50.0])
    sv_lead = np.stack([np.cos(np.radians(el_deg)), np.zeros(6), np.sin(np.radians(el_deg))], axis=1) * 2e7
    pr_lead = np.array([1.0, 2.0, 3.0, np.nan, 5.0, 6.0])
    prn_v = np.array([30, 25, 19, 12, 4, 3], dtype=np.int64)
    pr_v = np.array([1.0, np.inf, 1.0, 1.0, 1.0, 1.0])
    iv, il, el, n_bad = kernels.pair_satellites(prn_v, prn_lead, pr_v, pr_lead, sv_lead, base, rot)
    # common: 3, 12, 19 (lead NaN), 25 (vehicle inf), 30 -> kept 30 (50 deg), 12 (45), 3 (20)
    assert n_bad == 2
    np.testing.assert_array_equal(prn_v[iv], [30, 12, 3])
    np.testing.assert_array_equal(prn_lead[il], [30, 12, 3])
    np.testing.assert_allclose(np.degrees(el), [50.0, 45.0, 20.0], atol=1e-9)


def test_pair_satellites_all_vehicles_in_one_call():
    """The case above for three vehicles in one call (the second sees nothing in common, the
    third a subset in another order): per vehicle the same common satellites, counts and
    elevation order, ``iv`` into the vehicle's own rows."""
    rot, base = np.eye(3), np.zeros(3)
    prn_lead = np.array([3, 7, 12, 19, 25, 30], dtype=np.int64)
    el_deg = np.array([20.0, 70.0, 45.0, 10.0, 85.0, 50.0])
    sv_lead = np.stack([np.cos(np.radians(el_deg)), np.zeros(6), np.sin(np.radians(el_deg))], axis=1) * 2e7
    pr_lead = np.array([1.0, 2.0, 3.0, np.nan, 5.0, 6.0])
    prns = [np.array([30, 25, 19, 12, 4, 3]), np.array([1, 2]), np.array([7, 25, 3])]
    prs = [np.array([1.0, np.inf, 1.0, 1.0, 1.0, 1.0]), np.array([1.0, 1.0]), np.array([1.0, 1.0, 1.0])]
    iv, il, el, moff, n_bad = kernels.pair_satellites_all(
        np.concatenate(prns), np.concatenate(prs), np.array([0, 6, 8, 11]), prn_lead, pr_lead, sv_lead, base, rot)
    np.testing.assert_array_equal(moff, [0, 3, 3, 6])
    np.testing.assert_array_equal(n_bad, [2, 0, 0])
    np.testing.assert_array_equal(prns[0][iv[0:3]], [30, 12, 3])
    np.testing.assert_array_equal(prns[2][iv[3:6]], [25, 7, 3])  # 85, 70, 20 deg
    np.testing.assert_array_equal(prn_lead[il], [30, 12, 3, 25, 7, 3])
    np.testing.assert_allclose(np.degrees(el), [50.0, 45.0, 20.0, 85.0, 70.0, 20.0], atol=1e-9)


def test_predict_with_the_process_model_f_is_f_p_ft_plus_q():
    """The process model's own vehicle-block F (position integrates velocity, clock integrates
    drift: the in-place fast path) and an [azimuth, rate] pair: dense F P F^T + Q (round-off)."""
    from v2v.estimation.process import ProcessNoiseConfig, azimuth_block, vehicle_block

    cfg = ProcessNoiseConfig()
    fb, qb = vehicle_block(cfg, 0.1)
    fa, qa = azimuth_block(cfg, 0.1)
    rng = np.random.default_rng(10)
    n = 21  # [other, vehicle (8), vehicle (8), azimuth, other, rate, other]
    P = _spd(rng, n, 1.0)
    x = rng.normal(size=n)
    f = np.eye(n)
    q = np.zeros((n, n))
    for s in (1, 9):
        f[s:s + 8, s:s + 8] = fb
        q[s:s + 8, s:s + 8] = qb
    ix = np.ix_([17, 19], [17, 19])
    f[ix] = fa
    q[ix] = qa
    x_exp, p_exp = f @ x, f @ P @ f.T + q
    kernels.predict_vehicle_blocks(x, P, 1, 2, np.ascontiguousarray(fb), np.ascontiguousarray(qb))
    kernels.predict_pairs(x, P, np.array([17]), np.array([19]), np.ascontiguousarray(fa), np.ascontiguousarray(qa))
    kernels.symmetrize(P)
    np.testing.assert_allclose(x, x_exp, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(P, p_exp, rtol=1e-12, atol=1e-12)
    assert np.array_equal(P, P.T)


@pytest.mark.parametrize("n", [12, 20, 100, 127, 128, 156, 316])
def test_lazy_flush_is_p_minus_qt_q_and_exactly_symmetric(n):
    """Both flush forms (one block below 128 states, column panels from 128; in-place dgemm
    with alpha = -1, beta = 1 on C-contiguous arrays, np.dot products subtracted otherwise):
    P - Q^T Q of the buffered rows (dense product: round-off of the ~kq-term sums, 1e-12 of
    the scale), bit-for-bit symmetric, and the two forms bit-for-bit equal (the same dgemm
    sums, subtracted once); an empty buffer leaves P untouched."""
    rng = np.random.default_rng(n)
    P = _spd(rng, n, 1.0)
    Q = rng.normal(size=(kernels.LAZY_RANK, n)) * 0.05
    for kq in (0, 1, 7, 31, kernels.LAZY_RANK):
        p = P.copy()
        assert kernels.lazy_flush(p, Q, kq) == 0
        expected = P - Q[:kq].T @ Q[:kq]
        np.testing.assert_allclose(p, expected, rtol=0, atol=1e-12 * np.abs(P).max())
        assert np.array_equal(p, p.T)
        if kq == 0:
            assert np.array_equal(p, P)
            continue
        p_dot = P.copy()
        kernels._lazy_flush_dot(p_dot, Q, kq)
        assert np.array_equal(p, p_dot)
        p_f = np.asfortranarray(P)  # not C-contiguous: the np.dot form
        kernels.lazy_flush(p_f, Q, kq)
        assert np.array_equal(p_f, p_dot)


@pytest.mark.parametrize("lead_a", [False, True], ids=["two_followers", "from_the_lead"])
def test_bearing_second_order_needs_only_the_horizontal_covariance(lead_a):
    """A bearing's Hessian atan2(E, N) has no U row or column, so Gelb's second-order mean
    tr(H2 P_d) / 2 and variance tr((H2 P_d)^2) / 2 depend on the horizontal 2 x 2 block of
    P_d only: the bearing kernel's horizontal-only relative covariance gives the same two
    numbers, to the bit, as the full 3 x 3 one (and both match P_d = J P J^T written out), on a
    lazily updated covariance with a partly filled buffer."""
    rng = np.random.default_rng(5)
    n = 20
    P = _spd(rng, n, 4.0)
    Q = np.zeros((kernels.LAZY_RANK, n))
    Q[:5] = rng.normal(size=(5, n)) * 0.3
    sa, sb = (-1, 8) if lead_a else (0, 8)
    x = rng.normal(size=n) * 30.0
    d = np.empty(3)
    kernels._delta(x, sa, sb, d)
    hess = np.empty((3, 3))
    kernels.bearing_hessian(d, hess)
    assert not hess[2].any() and not hess[:, 2].any()
    full, horiz = np.empty((3, 3)), np.empty((3, 3))
    kernels._rel_cov_lazy(P, Q, 5, sa, sb, full)
    kernels._rel_cov_block(P, Q, 5, sa, sb, horiz, 2)
    assert np.array_equal(horiz[:2, :2], full[:2, :2]) and not horiz[2].any() and not horiz[:, 2].any()
    assert kernels._second_order(hess, horiz) == kernels._second_order(hess, full)
    pl = P - Q[:5].T @ Q[:5]
    j = np.zeros((3, n))
    j[:, sb:sb + 3] = np.eye(3)
    if sa >= 0:
        j[:, sa:sa + 3] = -np.eye(3)
    np.testing.assert_allclose(full, j @ pl @ j.T, rtol=1e-12, atol=1e-12)
