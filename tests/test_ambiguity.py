"""Integer ambiguity resolution (v2v.estimation.ambiguity): LAMBDA against the published
example and brute force, success rates against Monte Carlo, partial fixing, SD -> DD."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from scipy.special import erf
from scipy.stats import binom, norm

from v2v.estimation.ambiguity import (
    bootstrap,
    bootstrapped_success_rate,
    decorrelate,
    fixed_solution,
    lambda_resolve,
    ldl_decompose,
    partial_fix,
    reference_satellite,
    sd_to_dd,
    search,
)

# de Jonge & Tiberius (1996), 3-D example of their sections 3.8 / 4.12 (the same Q, a_hat
# and truth [5, 3, 4] are in the LAMBDA demo script distributed with the method).
Q_DJT = np.array([[6.290, 5.978, 0.544], [5.978, 6.292, 2.340], [0.544, 2.340, 6.288]])
A_DJT = np.array([5.45, 3.10, 2.97])

L1_WAVELENGTH_M = 0.190293672798365


def _random_q(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    """A correlated SPD ambiguity covariance: scale * (A^T A)^-1, A (n+3, n) Gaussian."""
    A = rng.normal(size=(n + 3, n))
    return scale * np.linalg.inv(A.T @ A)


def _sq_norm(a_hat: np.ndarray, Q: np.ndarray, cands: np.ndarray) -> np.ndarray:
    """(a_hat - c)^T Q^-1 (a_hat - c) for each column c (or row block) of cands."""
    e = a_hat[:, None] - cands
    return np.einsum("ik,ik->k", e, np.linalg.solve(Q, e))


def _brute_force(a_hat: np.ndarray, Q: np.ndarray, chi2: float, k: int):
    """The k best integer vectors by enumerating the box that contains the ellipsoid
    (a - a_hat)^T Q^-1 (a - a_hat) <= chi2 (half-widths sqrt(chi2 Q_ii), exact)."""
    half = np.sqrt(chi2 * np.diag(Q)) + 1e-9
    axes = [np.arange(np.ceil(c - h), np.floor(c + h) + 1) for c, h in zip(a_hat, half, strict=True)]
    grid = np.array(list(itertools.product(*axes))).T
    norms = _sq_norm(a_hat, Q, grid)
    order = np.argsort(norms, kind="stable")[:k]
    return grid[:, order].astype(np.int64), norms[order], grid.shape[1]


def _decorrelation_number(Q: np.ndarray) -> float:
    """r = sqrt(det(R)), R the correlation matrix: 1 for uncorrelated, -> 0 for fully
    correlated (Teunissen 1995; de Jonge & Tiberius 1996)."""
    s = np.sqrt(np.diag(Q))
    return float(np.sqrt(np.linalg.det(Q / np.outer(s, s))))


# --------------------------------------------------------------------------- SD -> DD
def test_sd_to_dd_hand_computed_three_satellites():
    # State: [pos_e (m), clock (m), a1, a2, a3 (cycles)]; satellite 2 is the highest.
    el = np.deg2rad([20.0, 75.0, 40.0])
    ref = reference_satellite(el)
    assert ref == 1
    x = np.array([1.5, 30.0, 10.2, 7.1, -3.4])
    P = np.diag([0.04, 100.0, 1.0, 2.0, 3.0])
    P[0, 2] = P[2, 0] = 0.1  # position correlated with a1
    dd = sd_to_dd(x, P, amb_idx=[2, 3, 4], ref=ref, drop_idx=[1])
    D_hand = np.array(
        [
            [1, 0, 0, 0, 0],  # position kept
            [0, 0, 1, -1, 0],  # a1 - a2
            [0, 0, 0, -1, 1],  # a3 - a2
        ],
        dtype=float,
    )
    np.testing.assert_array_equal(dd.D, D_hand)
    np.testing.assert_allclose(dd.x, [1.5, 10.2 - 7.1, -3.4 - 7.1])
    # P_dd by hand: var(a1 - a2) = 1 + 2, var(a3 - a2) = 3 + 2, cov = var(a2) = 2 (the
    # common reference), cov(pos, a1 - a2) = 0.1.
    P_hand = np.array([[0.04, 0.1, 0.0], [0.1, 3.0, 2.0], [0.0, 2.0, 5.0]])
    np.testing.assert_allclose(dd.P, P_hand, atol=1e-15)
    np.testing.assert_array_equal(dd.b_idx, [0])
    np.testing.assert_array_equal(dd.amb_idx, [1, 2])
    np.testing.assert_array_equal(dd.sd_pairs, [[0, 1], [2, 1]])


def test_sd_to_dd_removes_the_clock_ambiguity_common_mode():
    """An SD float solution cannot separate the SD clock from a common shift of all SD
    ambiguities (thesis section 3.6): add a huge variance along that direction (clock in
    cycles for simplicity) and the DD covariance must not see it."""
    rng = np.random.default_rng(11)
    n_amb = 5
    B = rng.normal(size=(4 + n_amb, 4 + n_amb))
    P_well = B @ B.T * 0.01
    common = np.r_[0.0, 0.0, 0.0, 1.0, np.ones(n_amb)]  # clock + every ambiguity
    P_sd = P_well + 1e8 * np.outer(common, common)
    kwargs = dict(amb_idx=np.arange(4, 4 + n_amb), ref=2, drop_idx=[3])
    dd_well = sd_to_dd(np.zeros(4 + n_amb), P_well, **kwargs)
    dd_sd = sd_to_dd(np.zeros(4 + n_amb), P_sd, **kwargs)
    # 1e8 * (1 - 1) cancels exactly in D P D^T up to round-off of 1e8 * eps ~ 1e-8.
    np.testing.assert_allclose(dd_sd.P, dd_well.P, atol=1e-6)


def test_sd_to_dd_rejects_bad_input():
    with pytest.raises(ValueError):
        sd_to_dd(np.zeros(3), np.eye(3), amb_idx=[2], ref=0)
    with pytest.raises(ValueError):
        sd_to_dd(np.zeros(3), np.eye(3), amb_idx=[1, 2], ref=2)
    with pytest.raises(ValueError):
        sd_to_dd(np.zeros(3), np.eye(3), amb_idx=[1, 2], ref=0, drop_idx=[2])


# --------------------------------------------------------------------------- LDL, decorrelation
def test_ldl_reconstructs_and_gives_conditional_variances():
    rng = np.random.default_rng(5)
    Q = _random_q(rng, 6, 2.0)
    L, d = ldl_decompose(Q)
    np.testing.assert_allclose(L.T @ np.diag(d) @ L, Q, rtol=1e-12, atol=1e-14)
    np.testing.assert_array_equal(np.diag(L), np.ones(6))
    assert np.all(np.triu(L, 1) == 0.0)
    # d[-1] is unconditional; d[0] is the variance of a_0 given all others = 1 / (Q^-1)_00;
    # d[i] = variance of a_i given a_{i+1..n}: Schur complement.
    assert d[-1] == pytest.approx(Q[-1, -1], rel=1e-14)
    assert d[0] == pytest.approx(1.0 / np.linalg.inv(Q)[0, 0], rel=1e-10)
    i = 2
    J = slice(i + 1, 6)
    schur = Q[i, i] - Q[i, J] @ np.linalg.solve(Q[J, J], Q[J, i])
    assert d[i] == pytest.approx(schur, rel=1e-10)
    with pytest.raises(ValueError):
        ldl_decompose(np.array([[1.0, 2.0], [2.0, 1.0]]))


def test_de_jonge_tiberius_example():
    r = lambda_resolve(A_DJT, Q_DJT)
    np.testing.assert_array_equal(r.fixed, [5, 3, 4])
    # Published minimum squared norm 0.2183; verified here by brute force as well.
    assert r.sq_norms[0] == pytest.approx(0.2183, abs=5e-5)
    cands, norms, n_box = _brute_force(A_DJT, Q_DJT, r.sq_norms[1] * 1.001, 2)
    np.testing.assert_array_equal(cands, r.candidates)
    np.testing.assert_allclose(norms, r.sq_norms, rtol=1e-10)
    np.testing.assert_allclose(_sq_norm(A_DJT, Q_DJT, r.candidates), r.sq_norms, rtol=1e-10)
    assert r.ratio == pytest.approx(r.sq_norms[1] / r.sq_norms[0])
    # Z integer unimodular; Q_z, z_hat consistent with it.
    assert r.Z.dtype.kind == "i"
    assert round(abs(np.linalg.det(r.Z))) == 1
    np.testing.assert_allclose(r.Qz, r.Z.T @ Q_DJT @ r.Z, atol=1e-12)
    np.testing.assert_allclose(r.z_float, r.Z.T @ A_DJT, atol=1e-12)
    # Q_z up to the sign of a column of Z: the decorrelated matrix of the example
    # (diagonal 4.476, 1.146, 0.626). Integer Z on a 3-decimal Q gives it exactly.
    np.testing.assert_allclose(
        np.abs(r.Qz), [[4.476, 0.334, 0.230], [0.334, 1.146, 0.082], [0.230, 0.082, 0.626]], atol=1e-12
    )
    # Much less correlated: decorrelation number 0.11 -> 0.98, condition 322 -> 7.5.
    r_a, r_z = _decorrelation_number(Q_DJT), _decorrelation_number(r.Qz)
    assert r_a < 0.15 and r_z > 0.95
    assert np.linalg.cond(r.Qz) < np.linalg.cond(Q_DJT) / 20
    # Search volume is preserved (det Z = 1) but the conditional variances are spread
    # far less: max/min of d drops from ~70 to < 8.
    _, d_a = ldl_decompose(Q_DJT)
    _, d_z = ldl_decompose(r.Qz)
    assert np.prod(d_z) == pytest.approx(np.prod(d_a), rel=1e-10)
    assert d_z.max() / d_z.min() < 8 < d_a.max() / d_a.min()


def test_large_ambiguities_shift_exactly():
    """Real SD/DD ambiguities are ~1e6 cycles: an integer shift of the float moves the
    solution by the same integers and leaves norms, ratio and success rate unchanged
    (the search runs on the fractional part)."""
    shift = np.array([1_000_000, -2_345_678, 3_000_001])
    r0 = lambda_resolve(A_DJT, Q_DJT)
    r1 = lambda_resolve(A_DJT + shift, Q_DJT)
    np.testing.assert_array_equal(r1.fixed, r0.fixed + shift)
    np.testing.assert_allclose(r1.sq_norms, r0.sq_norms, rtol=1e-8)
    a_near = np.array([5.03, 2.98, 4.01])
    p0 = partial_fix(a_near, Q_DJT * 0.001)
    p1 = partial_fix(a_near + shift, Q_DJT * 0.001)
    assert p0.n_fixed == p1.n_fixed == 3
    np.testing.assert_allclose(p1.a_cond, p0.a_cond + shift, atol=1e-6)


@pytest.mark.parametrize("n", [2, 4, 6, 8])
def test_decorrelation_properties_random(n):
    rng = np.random.default_rng(100 + n)
    Q = _random_q(rng, n, 5.0)
    a = rng.normal(size=n) * 10
    Z, Qz, z = decorrelate(Q, a)
    assert round(abs(np.linalg.det(Z))) == 1
    np.testing.assert_allclose(np.linalg.inv(Z), np.rint(np.linalg.inv(Z)), atol=1e-9)  # Z^-1 integer
    np.testing.assert_allclose(Qz, Z.T @ Q @ Z, rtol=1e-9, atol=1e-12 * np.abs(Qz).max())
    np.testing.assert_allclose(z, Z.T @ a, atol=1e-9)
    L, d = ldl_decompose(Qz)
    # LLL-type end conditions: size-reduced L, and no adjacent swap would lower d[i+1].
    assert np.abs(np.tril(L, -1)).max() <= 0.5 + 1e-9
    assert np.all(d[1:] <= (d[:-1] + np.diag(L, -1) ** 2 * d[1:]) * (1 + 1e-9))
    assert _decorrelation_number(Qz) > _decorrelation_number(Q)


# --------------------------------------------------------------------------- search
@pytest.mark.parametrize("n", [1, 2, 3, 5, 8])
def test_search_equals_brute_force(n):
    """ILS result (best k) equals exhaustive enumeration over the box enclosing the
    ellipsoid of the k-th claimed norm: the claimed candidates are genuine integer
    vectors, so the true k best lie inside that ellipsoid."""
    rng = np.random.default_rng(200 + n)
    for trial in range(6):
        Q = _random_q(rng, n, 10.0 ** rng.uniform(-1.5, 0.5))
        a = rng.normal(size=n) * 50
        k = 2 if trial % 2 == 0 else 4
        r = lambda_resolve(a, Q, n_cands=k)
        np.testing.assert_allclose(_sq_norm(a, Q, r.candidates), r.sq_norms, rtol=1e-8)
        cands, norms, n_box = _brute_force(a, Q, r.sq_norms[-1] * (1 + 1e-6), k)
        assert n_box < 2_000_000
        np.testing.assert_allclose(r.sq_norms, norms, rtol=1e-8)
        np.testing.assert_array_equal(r.candidates[:, 0], cands[:, 0])
        # search() without decorrelation finds the same (slower, same answer).
        c_plain, n_plain = search(Q, a, n_cands=k)
        np.testing.assert_allclose(n_plain, r.sq_norms, rtol=1e-8)
        np.testing.assert_array_equal(c_plain[:, 0], r.fixed)


# --------------------------------------------------------------------------- success rates
def _bootstrap_by_regression(z_hat: np.ndarray, Qz: np.ndarray) -> np.ndarray:
    """Bootstrapping written independently of the LDL: z_n rounded, then each z_i from its
    conditional estimate z_i - Q_iJ Q_JJ^-1 (z_J - round_J), J = {i+1..n}.
    z_hat: (N, n) samples."""
    n = Qz.shape[0]
    out = np.zeros_like(z_hat)
    out[:, n - 1] = np.rint(z_hat[:, n - 1])
    for i in range(n - 2, -1, -1):
        J = slice(i + 1, n)
        g = np.linalg.solve(Qz[J, J], Qz[J, i])
        out[:, i] = np.rint(z_hat[:, i] - (z_hat[:, J] - out[:, J]) @ g)
    return out


def test_bootstrapped_success_rate_formula():
    # Diagonal Q: conditional = marginal; P = prod (2 Phi(1/(2 sigma)) - 1).
    s = np.array([0.1, 0.2, 0.3])
    expected = np.prod(2 * norm.cdf(1 / (2 * s)) - 1)
    assert bootstrapped_success_rate(np.diag(s**2)) == pytest.approx(expected, rel=1e-12)
    # Same value as erf form, through the LDL of a correlated Q.
    _, d = ldl_decompose(Q_DJT)
    assert bootstrapped_success_rate(Q_DJT) == pytest.approx(np.prod(erf(1 / (2 * np.sqrt(2 * d)))))


def test_bootstrapped_success_rate_matches_monte_carlo_and_bounds_ils():
    """Monte Carlo with a_hat ~ N(a, Q): sequential rounding in z-space succeeds with the
    rate of eq. 3.36 (two-sided binomial 99 % interval: 1 % false-failure rate); ILS (LAMBDA)
    on the same samples succeeds at least as often (Teunissen 1999)."""
    rng = np.random.default_rng(42)
    Q = 0.05 * Q_DJT
    a_true = np.array([5, 3, 4])
    Z, Qz, _ = decorrelate(Q, np.zeros(3))
    p_b = bootstrapped_success_rate(Qz)
    assert 0.6 < p_b < 0.8  # a regime where failures are frequent and measurable
    n_mc = 20_000
    a_hat = rng.multivariate_normal(a_true, Q, size=n_mc)
    z_hat = a_hat @ Z
    z_true = Z.T @ a_true
    ok_bs = np.all(_bootstrap_by_regression(z_hat, Qz) == z_true, axis=1)
    lo, hi = binom.interval(0.99, n_mc, p_b)
    assert lo <= ok_bs.sum() <= hi
    # The library's LDL bootstrap agrees sample by sample with the regression form.
    L, d = ldl_decompose(Qz)
    lib = np.array([bootstrap(zh, L, d) for zh in z_hat[:2000]])
    np.testing.assert_array_equal(lib, _bootstrap_by_regression(z_hat[:2000], Qz))
    # Decorrelation helps bootstrapping: in a-space it is much worse.
    assert bootstrapped_success_rate(Q) < p_b - 0.2
    # ILS: lower bound holds (binomial 99 % one-sided lower limit on 3000 samples).
    n_ils = 3000
    ok_ils = np.array([np.array_equal(lambda_resolve(a, Q).fixed, a_true) for a in a_hat[:n_ils]])
    assert ok_ils.sum() >= binom.ppf(0.01, n_ils, p_b)
    assert ok_ils.sum() >= ok_bs[:n_ils].sum()


def test_ils_beats_bootstrapping_pairwise_in_8d():
    """8-D correlated Q: on the same samples ILS is never worse in total than bootstrapping
    (optimality of ILS); here the gap is resolvable."""
    rng = np.random.default_rng(7)
    n = 8
    Q = _random_q(rng, n, 0.25)
    a_true = rng.integers(-20, 20, n)
    r0 = lambda_resolve(a_true.astype(float), Q)
    p_b = r0.success_rate_bootstrap
    assert 0.3 < p_b < 0.95
    n_mc = 2000
    a_hat = rng.multivariate_normal(a_true, Q, size=n_mc)
    z_hat = a_hat @ r0.Z
    ok_bs = np.all(_bootstrap_by_regression(z_hat, r0.Qz) == r0.Z.T @ a_true, axis=1)
    ok_ils = np.array([np.array_equal(lambda_resolve(a, Q).fixed, a_true) for a in a_hat])
    lo, hi = binom.interval(0.99, n_mc, p_b)
    assert lo <= ok_bs.sum() <= hi
    # Paired difference: samples where only one method is right.
    assert ok_ils.sum() >= ok_bs.sum()


# --------------------------------------------------------------------------- ratio test
def test_ratio_test_behaviour():
    rng = np.random.default_rng(3)
    Q = 0.002 * Q_DJT  # sigma ~ 0.11 cycle, strongly correlated; P_B > 0.99999
    a_true = np.array([105, -42, 7])
    # Typical floats a_hat ~ N(a, Q): the best norm is ~chi-square(3) (median 2.4) while
    # the second is ~ the squared metric distance to the nearest other lattice point
    # (116 here), so the median ratio is ~ 116 / 2.4 ~ 50; with Q / 4 it is ~4x larger.
    med = []
    for scale in (1.0, 0.25):
        a_hat = rng.multivariate_normal(a_true, scale * Q, size=200)
        res = [lambda_resolve(a, scale * Q) for a in a_hat]
        assert all(np.array_equal(r.fixed, a_true) for r in res)
        med.append(np.median([r.ratio for r in res]))
    assert med[0] > 10.0
    assert 2.5 < med[1] / med[0] < 6.0
    # Moving the float along its least precise direction, away from the truth, lowers it.
    direction = np.array([1.0, 1.0, 0.0]) / np.sqrt(2.0)
    ratios = [lambda_resolve(a_true + step * direction, Q).ratio for step in (0.05, 0.1, 0.2)]
    assert ratios[0] > ratios[1] > ratios[2] > 3.0
    r = lambda_resolve(a_true.astype(float), Q)
    # Float exactly halfway between the two best integer vectors: ratio -> 1.
    mid = 0.5 * (r.candidates[:, 0] + r.candidates[:, 1]).astype(float)
    assert lambda_resolve(mid, Q).ratio == pytest.approx(1.0, abs=1e-9)
    # 1-D: a_hat = 0.5 -> ratio 1; a_hat = 0.1 -> ratio (0.9 / 0.1)^2 = 81.
    assert lambda_resolve([0.5], [[0.04]]).ratio == pytest.approx(1.0)
    assert lambda_resolve([0.1], [[0.04]]).ratio == pytest.approx(81.0)
    # Exact integer float: ratio infinite.
    assert lambda_resolve([3.0, 4.0], np.eye(2) * 0.01).ratio == np.inf


# --------------------------------------------------------------------------- fixed solution
def test_fixed_solution_equals_eq_3_37():
    rng = np.random.default_rng(9)
    n_b, n_a = 4, 3
    B = rng.normal(size=(n_b + n_a, n_b + n_a))
    P = B @ B.T + np.eye(n_b + n_a)
    x = rng.normal(size=n_b + n_a)
    amb = np.arange(n_b, n_b + n_a)
    a_fix = np.rint(x[amb]) + np.array([1, 0, -1])
    fs = fixed_solution(x, P, amb, a_fix)
    Qb, Qba, Qa = P[:n_b, :n_b], P[:n_b, n_b:], P[n_b:, n_b:]
    b_hand = x[:n_b] - Qba @ np.linalg.inv(Qa) @ (x[amb] - a_fix)
    Pb_hand = Qb - Qba @ np.linalg.inv(Qa) @ Qba.T
    np.testing.assert_allclose(fs.x[:n_b], b_hand, rtol=1e-10)
    np.testing.assert_allclose(fs.P[:n_b, :n_b], Pb_hand, rtol=1e-10, atol=1e-12)
    np.testing.assert_array_equal(fs.x[amb], a_fix)
    assert np.all(fs.P[amb] == 0.0)
    assert np.all(np.linalg.eigvalsh(fs.P[:n_b, :n_b]) > 0)
    # Fixing all z = Z^T a through transform=Z is the same constraint set as fixing a.
    Z, _, _ = decorrelate(P[n_b:, n_b:], x[amb])
    fz = fixed_solution(x, P, amb, Z.T @ a_fix, transform=Z)
    np.testing.assert_allclose(fz.x, fs.x, atol=1e-9)
    np.testing.assert_allclose(fz.P, fs.P, atol=1e-9)


def _sd_float_solution(rng, *, n_sat, n_epochs, sigma_code_m, sigma_phase_m):
    """Weighted LS float solution of a static baseline from SD code + phase: unknowns
    [b_enu (3, m), SD clock per epoch (m), SD ambiguities (cycles)]. Satellites drift
    1.5 deg/epoch in azimuth. Returns x, P, truth, indices and elevations."""
    el = np.deg2rad(rng.uniform(15, 85, n_sat))
    az = rng.uniform(0, 2 * np.pi, n_sat)
    b_true = np.array([12.0, -25.0, 0.8])
    n_true = rng.integers(-1000, 1000, n_sat)
    nx = 3 + n_epochs + n_sat
    H, y, w = [], [], []
    for k in range(n_epochs):
        a_k = az + k * np.deg2rad(1.5)
        u = np.column_stack([np.cos(el) * np.sin(a_k), np.cos(el) * np.cos(a_k), np.sin(el)])
        clk = 3.7 + 0.1 * k
        for j in range(n_sat):
            h = np.zeros(nx)
            h[:3] = -u[j]
            h[3 + k] = 1.0
            H.append(h.copy())
            y.append(-u[j] @ b_true + clk + sigma_code_m * rng.normal())
            w.append(sigma_code_m**-2)
            h[3 + n_epochs + j] = L1_WAVELENGTH_M
            H.append(h)
            y.append(-u[j] @ b_true + clk + L1_WAVELENGTH_M * n_true[j] + sigma_phase_m * rng.normal())
            w.append(sigma_phase_m**-2)
    H, y, w = np.array(H), np.array(y), np.array(w)
    P = np.linalg.inv(H.T @ (w[:, None] * H))
    x = P @ H.T @ (w * y)
    return x, P, b_true, n_true, np.arange(3 + n_epochs, nx), np.arange(3, 3 + n_epochs), el


def test_end_to_end_sd_float_to_fixed_baseline():
    """SD float (2 epochs, 8 satellites, code 10 cm, phase 3 mm) -> DD (clocks dropped,
    highest-elevation reference) -> LAMBDA -> eq. 3.37: the DD integers are the true ones
    and the baseline error drops from decimetres to millimetres, within its fixed sigma."""
    rng = np.random.default_rng(3)
    x, P, b_true, n_true, amb, clk, el = _sd_float_solution(
        rng, n_sat=8, n_epochs=2, sigma_code_m=0.1, sigma_phase_m=0.003
    )
    ref = reference_satellite(el)
    dd = sd_to_dd(x, P, amb, ref, drop_idx=clk)
    Qa = dd.P[np.ix_(dd.amb_idx, dd.amb_idx)]
    r = lambda_resolve(dd.x[dd.amb_idx], Qa)
    assert r.success_rate_bootstrap > 0.9999
    assert r.ratio > 3.0
    true_dd = n_true[dd.sd_pairs[:, 0]] - n_true[dd.sd_pairs[:, 1]]
    np.testing.assert_array_equal(r.fixed, true_dd)
    fs = fixed_solution(dd.x, dd.P, dd.amb_idx, r.fixed)
    err_float = np.linalg.norm(dd.x[:3] - b_true)
    err_fixed = np.linalg.norm(fs.x[:3] - b_true)
    assert err_float > 0.03 and err_fixed < 0.01
    # Fixed error consistent with its covariance: chi-square(3) below its 99.9 % point 16.3.
    e = fs.x[:3] - b_true
    assert e @ np.linalg.solve(fs.P[:3, :3], e) < 16.3


# --------------------------------------------------------------------------- partial fixing
def test_partial_fix_all_when_precise():
    rng = np.random.default_rng(21)
    Q = _random_q(rng, 6, 0.002)
    a_true = rng.integers(-50, 50, 6)
    a_hat = rng.multivariate_normal(a_true, Q)
    res = partial_fix(a_hat, Q)
    assert res.n_fixed == 6 and res.success_rate >= 0.999 and res.ratio >= 3.0
    np.testing.assert_allclose(res.a_cond, a_true, atol=1e-9)
    np.testing.assert_allclose(res.Qa_cond, 0.0, atol=1e-12)
    np.testing.assert_array_equal(res.z_fixed, res.Z.T @ a_true)


def test_partial_fix_subset_when_some_noisy():
    """Three precise (sigma 0.05 cycle) and two noisy (2 cycles) ambiguities, mildly
    correlated across the groups: the decorrelation puts the precise combinations last and
    exactly three are fixed, correctly; the noisy ones are conditioned on them (eq. 3.40)."""
    rng = np.random.default_rng(22)
    s = np.array([2.0, 0.05, 2.0, 0.05, 0.05])
    R = np.eye(5)
    R[0, 1] = R[1, 0] = 0.3
    R[2, 3] = R[3, 2] = -0.2
    Q = R * np.outer(s, s)
    a_true = np.array([10, -3, 7, 22, 0])
    a_hat = rng.multivariate_normal(a_true, Q)
    res = partial_fix(a_hat, Q)
    assert res.n_fixed == 3
    assert res.success_rate >= 0.999 and res.ratio >= 3.0
    Zs = res.Z[:, res.fixed_mask]
    np.testing.assert_array_equal(res.z_fixed, Zs.T @ a_true)
    # The fixed combinations span exactly the precise ambiguities.
    assert np.all(Zs[[0, 2], :] == 0)
    precise = [1, 3, 4]
    np.testing.assert_allclose(res.a_cond[precise], a_true[precise], atol=1e-9)
    # Unfixed ones: conditioned (eq. 3.40) = a_hat - Q Zs (Zs^T Q Zs)^-1 (Zs^T a_hat - z_s).
    G = Q @ Zs @ np.linalg.inv(Zs.T @ Q @ Zs)
    np.testing.assert_allclose(res.a_cond, a_hat - G @ (Zs.T @ a_hat - res.z_fixed), atol=1e-9)
    np.testing.assert_allclose(res.Qa_cond, Q - G @ Zs.T @ Q, atol=1e-9)
    # and the noisy ones got more precise by the correlation (1 - rho^2).
    assert res.Qa_cond[0, 0] == pytest.approx(Q[0, 0] * (1 - 0.3**2), rel=1e-9)


def test_partial_fix_none_when_all_noisy():
    rng = np.random.default_rng(23)
    Q = _random_q(rng, 5, 30.0)
    a_hat = rng.normal(size=5) * 10
    res = partial_fix(a_hat, Q)
    assert res.n_fixed == 0 and res.z_fixed.size == 0 and np.isnan(res.ratio)
    np.testing.assert_allclose(res.a_cond, a_hat, atol=1e-9)
    np.testing.assert_allclose(res.Qa_cond, Q, rtol=1e-9)


def test_partial_fix_ratio_failure_shrinks_the_subset():
    """Success threshold met by all three, but the full set fails the ratio test (the
    least precise is near a half-integer); dropping it leaves two that pass."""
    Q = np.diag([0.3, 0.05, 0.05]) ** 2
    a_hat = np.array([0.45, 0.01, -0.01])
    res = partial_fix(a_hat, Q, min_success=0.5, ratio_threshold=3.0)
    # Full set: norms 0.45^2/0.09 + 0.08 vs 0.55^2/0.09 + 0.08 -> ratio 1.44 < 3.
    assert res.n_fixed == 2
    np.testing.assert_array_equal(res.Z, np.eye(3, dtype=int))  # already decorrelated
    np.testing.assert_array_equal(res.z_fixed, [0, 0])
    assert res.a_cond[0] == pytest.approx(0.45)


def test_partial_fix_on_weak_geometry_improves_baseline():
    """Single epoch, 8 satellites, 40 cm code: the full set is not fixable at 99.9 %, a
    z-space subset is; the subset is correct and conditioning the state on it (eq. 3.40
    via fixed_solution(transform=Z_s)) reduces the baseline sigma."""
    rng = np.random.default_rng(5)
    x, P, b_true, n_true, amb, clk, el = _sd_float_solution(
        rng, n_sat=8, n_epochs=1, sigma_code_m=0.4, sigma_phase_m=0.003
    )
    dd = sd_to_dd(x, P, amb, reference_satellite(el), drop_idx=clk)
    Qa = dd.P[np.ix_(dd.amb_idx, dd.amb_idx)]
    res = partial_fix(dd.x[dd.amb_idx], Qa)
    assert bootstrapped_success_rate(res.Qz) < 0.999
    assert 0 < res.n_fixed < dd.amb_idx.size
    true_dd = n_true[dd.sd_pairs[:, 0]] - n_true[dd.sd_pairs[:, 1]]
    Zs = res.Z[:, res.fixed_mask]
    np.testing.assert_array_equal(res.z_fixed, Zs.T @ true_dd)
    fs = fixed_solution(dd.x, dd.P, dd.amb_idx, res.z_fixed, transform=Zs)
    sig_float = np.sqrt(np.trace(dd.P[:3, :3]))
    sig_fixed = np.sqrt(np.trace(fs.P[:3, :3]))
    assert sig_fixed < 0.8 * sig_float
    e = fs.x[:3] - b_true
    assert e @ np.linalg.solve(fs.P[:3, :3], e) < 16.3  # chi-square(3) 99.9 %
