"""Filter algebra: process discretization, the scalar update, gating, layout surgery."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import binom

from v2v.errors import UserError
from v2v.estimation.filter import ClusterEkf, FilterConfig, MeasurementNoiseConfig, scalar_update
from v2v.estimation.layout import StateLayout
from v2v.estimation.process import ProcessNoiseConfig, azimuth_block, transition, vehicle_block
from v2v.estimation.simulate import SimScenario, run_filter, simulate, vehicle_ids
from v2v.sensors.measurements import UwbRanges


# --------------------------------------------------------------------------- process model
def _gm_closed_form(tau, sigma, dt):
    """Integrated first-order Gauss-Markov, q = 2 sigma^2 / tau, beta = 1 / tau:

    F  = [[1, (1 - e^-b dt) / b], [0, e^-b dt]]
    Qvv = sigma^2 (1 - e^-2b dt)
    Qpv = q/b [ (1 - e^-b dt)/b - (1 - e^-2b dt)/(2b) ]
    Qpp = q/b^2 [ dt - 2 (1 - e^-b dt)/b + (1 - e^-2b dt)/(2b) ]
    (integrals of e^-b u and (1 - e^-b u)/b over u in [0, dt]).
    """
    b = 1.0 / tau
    q = 2.0 * sigma**2 / tau
    # 1 - e^-x evaluated as -expm1(-x): the plain form loses ~1e-13/x relative accuracy,
    # which the cancellation in Qpp amplifies to 1e-7 at dt = 0.01 s.
    m1, m2 = -np.expm1(-b * dt), -np.expm1(-2 * b * dt)
    f = np.array([[1.0, m1 / b], [0.0, 1.0 - m1]])
    qvv = sigma**2 * m2
    qpv = q / b * (m1 / b - m2 / (2 * b))
    qpp = q / b**2 * (dt - 2 * m1 / b + m2 / (2 * b))
    return f, np.array([[qpp, qpv], [qpv, qvv]])


@pytest.mark.parametrize("dt", [0.01, 0.1, 1.0, 7.0])
def test_vehicle_block_matches_hand_derived_gauss_markov(dt):
    cfg = ProcessNoiseConfig()
    f, q = vehicle_block(cfg, dt)
    cases = [
        ([0, 3], cfg.vel_tau_s, cfg.vel_sigma_horizontal_mps),
        ([1, 4], cfg.vel_tau_s, cfg.vel_sigma_horizontal_mps),
        ([2, 5], cfg.vel_tau_s, cfg.vel_sigma_vertical_mps),
        ([6, 7], cfg.drift_tau_s, cfg.drift_sigma_mps),
    ]
    for idx, tau, sigma in cases:
        f_ref, q_ref = _gm_closed_form(tau, sigma, dt)
        # vehicle_block evaluates the same closed form in another arrangement (process.py:
        # series for small dt / tau): F agrees to a few ulp. Q is compared relative to each
        # element; the reference's direct formula for Qpp (O(dt^3 / tau^2) from O(dt)
        # terms) loses ~eps (tau / dt)^2 to cancellation (1e-11 at dt = 0.01 s for the 2 s
        # velocity, 2e-10 for the 10 s drift): rtol 10 eps (tau / dt)^2, at least 1e-13.
        np.testing.assert_allclose(f[np.ix_(idx, idx)], f_ref, rtol=1e-13, atol=1e-15)
        rtol = max(1e-13, 10 * np.finfo(float).eps * (tau / dt) ** 2)
        np.testing.assert_allclose(q[np.ix_(idx, idx)], q_ref, rtol=rtol, atol=0)
    # blocks are independent: nothing couples axes or position to the clock
    mask = np.zeros((8, 8), dtype=bool)
    for idx, *_ in cases:
        mask[np.ix_(idx, idx)] = True
    assert np.all(f[~mask] == 0.0) and np.all(q[~mask] == 0.0)


@pytest.mark.parametrize("dt", [0.01, 0.1, 1.0, 7.0])
def test_azimuth_rate_block_is_integrated_gauss_markov_plus_random_walk(dt):
    """[azimuth, yaw rate]: the yaw rate is GM (sigma, tau) and the azimuth integrates it plus a
    random walk q_a, so F and Q are the velocity-axis closed form with q_a dt added to Q_aa."""
    cfg = ProcessNoiseConfig(azimuth_rw_rad_per_sqrt_s=0.01, yaw_rate_sigma_rps=0.3, yaw_rate_tau_s=3.0)
    f, q = azimuth_block(cfg, dt)
    f_ref, q_ref = _gm_closed_form(3.0, 0.3, dt)
    q_ref[0, 0] += 0.01**2 * dt
    np.testing.assert_allclose(f, f_ref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(q, q_ref, rtol=1e-9, atol=0)


def test_transition_with_azimuth_rates_couples_only_azimuth_and_its_rate():
    cfg = ProcessNoiseConfig(azimuth_rw_rad_per_sqrt_s=0.02, yaw_rate_sigma_rps=0.2, yaw_rate_tau_s=2.0)
    lay = StateLayout.build(lead="L", vehicles=["A"], azimuth_vehicles=["L", "A"], uwb_pairs=[("L", "A")],
                            azimuth_rates=True)
    assert lay.n == 8 + 2 * (1 + 1) + 2 and lay.azimuth_rate_vehicles == ("L", "A")
    f, q = transition(lay, cfg, 0.5)
    fa, qa = azimuth_block(cfg, 0.5)
    for v in ("L", "A"):
        ix = np.ix_([lay.azimuth(v), lay.azimuth_rate(v)], [lay.azimuth(v), lay.azimuth_rate(v)])
        np.testing.assert_array_equal(f[ix], fa)
        np.testing.assert_array_equal(q[ix], qa)
    i, j = lay.azimuth("L"), lay.azimuth_rate("A")
    assert f[i, j] == 0.0 and q[i, j] == 0.0
    # the production engine's in-place pair propagation equals F P F^T + Q
    rng = np.random.default_rng(3)
    a = rng.standard_normal((lay.n, lay.n))
    p0 = a @ a.T
    x0 = rng.standard_normal(lay.n)
    ekf = ClusterEkf(lay, FilterConfig(process=cfg))
    ekf._replace(x0, p0)
    ekf.predict(0.5)
    np.testing.assert_allclose(ekf.x, f @ x0, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(ekf.P, f @ p0 @ f.T + q, rtol=1e-12, atol=1e-12)
    # removing a vehicle removes its azimuth-rate block too
    gone, _ = lay.without_vehicle("A")
    assert gone.azimuth_rate_vehicles == ("L",) and gone.uwb_pairs == ()
    with pytest.raises(UserError, match="no azimuth block"):
        StateLayout(lead="L", blocks=(("az_rate", "L"),))


def test_dense_transition_is_block_diagonal_with_random_walks():
    cfg = ProcessNoiseConfig(azimuth_rw_rad_per_sqrt_s=0.02, uwb_bias_rw_m_per_sqrt_s=0.01,
                             uwb_scale_rw_per_sqrt_s=1e-5)
    lay = StateLayout.build(lead="L", vehicles=["A", "B"], azimuth_vehicles=["L"], uwb_pairs=[("L", "A")])
    f, q = transition(lay, cfg, 0.5)
    fb, qb = vehicle_block(cfg, 0.5)
    np.testing.assert_array_equal(f[lay.block("vehicle", "B"), lay.block("vehicle", "B")], fb)
    assert q[lay.azimuth("L"), lay.azimuth("L")] == pytest.approx(0.02**2 * 0.5, rel=1e-15)
    assert q[lay.uwb_scale(("A", "L")), lay.uwb_scale(("A", "L"))] == pytest.approx(1e-10 * 0.5, rel=1e-15)
    assert f[lay.azimuth("L"), lay.azimuth("L")] == 1.0


# --------------------------------------------------------------------------- scalar update
def test_scalar_update_worked_by_hand():
    """Two states, observe the first (MacGougan (2009) table 3.1):

    x = [1, 2], P = [[4, 1], [1, 2]], h = [1, 0], z = 3, r = 1
    nu = 3 - 1 = 2;  S = h P h^T + r = 4 + 1 = 5
    k = P h^T / S = [4, 1] / 5 = [0.8, 0.2]
    x+ = x + k nu = [1 + 1.6, 2 + 0.4] = [2.6, 2.4]
    P+ = P - k k^T S = [[4 - 3.2, 1 - 0.8], [1 - 0.8, 2 - 0.2]] = [[0.8, 0.2], [0.2, 1.8]]
    """
    x = np.array([1.0, 2.0])
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    s, ok = scalar_update(x, P, np.array([0]), np.array([1.0]), innovation=2.0, r_var=1.0, gate_k=3.29)
    assert ok and s == pytest.approx(5.0, abs=1e-15)
    np.testing.assert_allclose(x, [2.6, 2.4], atol=1e-15)
    np.testing.assert_allclose(P, [[0.8, 0.2], [0.2, 1.8]], atol=1e-15)


def test_scalar_update_gate_rejects_without_touching_state():
    """|nu| / sqrt(S) = 7.5 / sqrt(5) = 3.354 > 3.29 (alpha = 0.001): rejected, x and P untouched."""
    x = np.array([1.0, 2.0])
    P = np.array([[4.0, 1.0], [1.0, 2.0]])
    x0, p0 = x.copy(), P.copy()
    s, ok = scalar_update(x, P, np.array([0]), np.array([1.0]), innovation=7.5, r_var=1.0, gate_k=3.2905)
    assert not ok and s == pytest.approx(5.0)
    np.testing.assert_array_equal(x, x0)
    np.testing.assert_array_equal(P, p0)
    # just inside: 7.3 / sqrt(5) = 3.265 < 3.29
    assert scalar_update(x, P, np.array([0]), np.array([1.0]), 7.3, 1.0, 3.2905)[1]


def test_gate_constant_from_significance():
    """alpha = 0.001 two-sided -> 3.2905 (standard normal table); alpha = 0.0026 -> 3.0 (thesis)."""
    assert FilterConfig().gate_k == pytest.approx(3.2905, abs=1e-4)
    assert FilterConfig(significance=0.0026998).gate_k == pytest.approx(3.0, abs=1e-4)


# --------------------------------------------------------------------------- the engine
def _layout3(azimuth=("lead", "v1"), uwb_pairs=(("lead", "v1"),)):
    ids = vehicle_ids(3)
    return StateLayout.build(lead="lead", vehicles=ids[1:], azimuth_vehicles=azimuth, uwb_pairs=uwb_pairs)


def test_covariance_stays_symmetric_pd_after_1000_updates():
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=3, duration_s=8.0, turn_rate_rps=0.05, bearing_vehicles=("lead", "v1"),
                      uwb_state_pairs=(("lead", "v1"),))
    ekf = ClusterEkf(_layout3(), cfg)
    n_updates = 0
    for _, infos in run_filter(ekf, simulate(scn, cfg, np.random.default_rng(3)), scn.dt_s):
        n_updates += sum(i.accepted for i in infos)
        assert np.all(np.isfinite(ekf.x))
    assert n_updates >= 1000
    P = ekf.P
    np.testing.assert_array_equal(P, P.T)  # rank-1 form and symmetrized prediction: exact
    assert np.linalg.eigvalsh(P).min() > 0.0
    np.linalg.cholesky(P)


def test_gating_rejects_10_sigma_blunders_and_accepts_inliers():
    """Process-model world (filter exactly right), 20 s at 10 Hz, all measurement types.

    Inliers: every innovation test but the SD Dopplers' is a Bernoulli(alpha = 0.001) false
    rejection under H0, so their rejection count is <= the binomial 99.99 % quantile
    (false-failure rate 1e-4). A vehicle's SD Dopplers of one epoch are not independent tests:
    once one is rejected the clock drift it would have corrected stays off for the rest, so a
    rejection comes with its epoch's others (SD Doppler rejections ran at 2.3 alpha, in
    clusters, over 100 seeds). They are counted as events, (epoch, vehicle) groups with a
    rejection, each of probability <= m alpha for a group of m tests (the union bound), so
    the events are <= the 99.99 % quantile of Binomial(groups, m_max alpha).
    Blunders: +10 sigma on one UWB range and on one (not first) SD pseudorange after
    convergence; both must be rejected (a 10-sigma error with S ~ sigma^2 gives |t| ~ 10),
    and the epoch's clean pseudoranges are false rejections at most as often as the
    binomial 99.99 % quantile allows.
    """
    cfg = FilterConfig(process=ProcessNoiseConfig(vel_sigma_horizontal_mps=1.0, vel_sigma_vertical_mps=0.1))
    scn = SimScenario(n_vehicles=3, duration_s=20.0, truth="process", bearing_vehicles=("lead",))
    ekf = ClusterEkf(_layout3(azimuth=(), uwb_pairs=()), cfg)
    tests = rejects = 0
    groups: dict[tuple[int, tuple[str, ...]], list[bool]] = {}  # (epoch, vehicles): Doppler tests accepted
    eps = simulate(scn, cfg, np.random.default_rng(11))
    for k, (_ep, infos) in enumerate(run_filter(ekf, eps, scn.dt_s)):
        for i in infos:
            if i.kind == "sd_doppler":
                groups.setdefault((k, i.vehicles), []).append(i.accepted)
            else:
                tests += 1
                rejects += not i.accepted
    assert tests > 3000 and len(groups) > 300
    assert rejects <= binom.ppf(0.9999, tests, cfg.significance)
    m_max = max(len(g) for g in groups.values())
    events = sum(not all(g) for g in groups.values())
    assert events <= binom.ppf(0.9999, len(groups), m_max * cfg.significance)

    # UWB blunder: true range + 10 sigma
    last = eps[-1]
    k = last.uwb.a.index("lead") if "lead" in last.uwb.a else 0
    bad = UwbRanges(t_s=last.uwb.t_s[:1], true_t_s=last.uwb.t_s[:1], a=(last.uwb.a[k],), b=(last.uwb.b[k],),
                    range_m=last.uwb.true_range_m[k:k + 1] + 10 * cfg.noise.uwb_sigma_m,
                    true_range_m=last.uwb.true_range_m[k:k + 1], los=np.array([True]))
    info = ekf.update_uwb(bad)
    assert len(info) == 1 and not info[0].accepted and abs(info[0].innovation) / np.sqrt(info[0].variance) > 8
    # an inlier at the same geometry is accepted
    good = replace(bad, range_m=last.uwb.true_range_m[k:k + 1] + 0.5 * cfg.noise.uwb_sigma_m)
    assert ekf.update_uwb(good)[0].accepted

    # SD pseudorange blunder on the lowest-elevation satellite of v1 (processed last)
    gnss = dict(last.gnss)
    g = gnss["v1"]
    low = int(np.argmin(g.elevation_rad))
    pr = g.pseudorange_m.copy()
    pr[low] += 10 * np.sqrt(cfg.noise.sd_pseudorange_var_m2)
    gnss["v1"] = replace(g, pseudorange_m=pr)
    infos = [i for i in ekf.update_gnss(gnss, last.lead_base_ecef_m) if i.kind == "sd_pseudorange"]
    blunder = [i for i in infos if i.vehicles == ("v1",) and i.prn == int(g.prn[low])]
    assert len(blunder) == 1 and not blunder[0].accepted
    assert sum(not i.accepted for i in infos) - 1 <= binom.ppf(0.9999, len(infos) - 1, cfg.significance)


def test_first_update_uses_a_screened_clean_pseudorange():
    """Thesis eq. 3.28-3.29: the first PR of a vehicle mostly observes the clock, so a blunder
    there would pass its weak test. A +100 m blunder on the *highest*-elevation satellite is
    caught by the parallel least-squares w-test and not used first; it is rejected later."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=2, duration_s=2.0, uwb=False, bearing_vehicles=())
    lay = StateLayout.build(lead="lead", vehicles=["v1"])
    ekf = ClusterEkf(lay, cfg)
    eps = simulate(scn, cfg, np.random.default_rng(5))
    for _ in run_filter(ekf, eps[:-1], scn.dt_s):
        pass
    ekf.predict(scn.dt_s)
    last = eps[-1]
    g = last.gnss["v1"]
    hi = int(np.argmax(g.elevation_rad))
    pr = g.pseudorange_m.copy()
    pr[hi] += 100.0
    infos = ekf.update_gnss({**last.gnss, "v1": replace(g, pseudorange_m=pr)}, last.lead_base_ecef_m)
    prs = [i for i in infos if i.kind == "sd_pseudorange"]
    assert prs[0].prn != int(g.prn[hi]) and prs[0].accepted
    bad = [i for i in prs if i.prn == int(g.prn[hi])]
    assert len(bad) == 1 and not bad[0].accepted
    assert ekf.counters.get("screened_first_update", 0) >= 1


def test_stays_uninitialized_with_three_satellites_and_predicts():
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=2, duration_s=1.0, uwb=False, bearing_vehicles=(),
                      sat_az_el_rad=SimScenario().sat_az_el_rad[:3])
    ekf = ClusterEkf(StateLayout.build(lead="lead", vehicles=["v1"]), cfg)
    for _, infos in run_filter(ekf, simulate(scn, cfg, np.random.default_rng(0)), scn.dt_s):
        assert infos == []
    assert not ekf.is_initialized("v1")
    assert ekf.counters["init_too_few_satellites"] == 11
    assert np.all(np.isfinite(ekf.P))


def test_nonfinite_measurements_are_skipped_and_counted():
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=2, duration_s=1.0, bearing_vehicles=())
    ekf = ClusterEkf(StateLayout.build(lead="lead", vehicles=["v1"]), cfg)
    eps = simulate(scn, cfg, np.random.default_rng(0))
    for _ in run_filter(ekf, eps, scn.dt_s):
        pass
    last = eps[-1]
    g = last.gnss["v1"]
    pr = g.pseudorange_m.copy()
    pr[0] = np.nan
    ekf.update_gnss({**last.gnss, "v1": replace(g, pseudorange_m=pr)}, last.lead_base_ecef_m)
    ekf.update_uwb(replace(last.uwb, range_m=np.array([np.inf])))
    assert ekf.counters["nonfinite_sd_pseudorange"] == 1
    assert ekf.counters["nonfinite_uwb"] == 1
    assert np.all(np.isfinite(ekf.x)) and np.all(np.isfinite(ekf.P))


def test_gnss_epoch_select_selects_every_per_satellite_field():
    """``GnssEpoch.select`` keeps every (n,)-shaped field and error component aligned (a field
    added later and forgotten there would fail here), and the scalars as they are."""
    import dataclasses

    cfg = FilterConfig()
    g = simulate(SimScenario(n_vehicles=2, duration_s=0.1, bearing_vehicles=()), cfg, np.random.default_rng(1))[0].gnss["v1"]
    g = replace(g, errors_m={"multipath": np.arange(g.n, dtype=float)})
    keep = np.arange(g.n) % 2 == 0
    sub = g.select(keep)
    for f in dataclasses.fields(g):
        a, b = getattr(g, f.name), getattr(sub, f.name)
        if isinstance(a, np.ndarray):
            np.testing.assert_array_equal(b, a[keep], err_msg=f.name)
        elif f.name == "errors_m":
            assert set(b) == set(a) and all(np.array_equal(b[k], a[k][keep]) for k in a)
        else:
            assert b == a, f.name
    with pytest.raises(ValueError, match="shape"):
        g.select(keep[:-1])


def test_cn0_mask_leaves_out_signals_weak_at_either_receiver():
    """``gnss_cn0_mask_dbhz``: an SD (pseudorange, Doppler) is formed only from signals at or
    above the mask at *both* receivers. Every simulated signal has 45 dB-Hz; one satellite is
    weakened to 30 dB-Hz at the follower, another at the lead. With a 40 dB-Hz mask neither
    satellite gives an SD, every other one does, the two weak signals are counted per epoch,
    and the estimate equals that of an unmasked filter given epochs without those two
    satellites (what a mask means). A mask equal to the C/N0 (45) keeps every signal."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=2, duration_s=2.0, uwb=False, bearing_vehicles=())
    eps = simulate(scn, cfg, np.random.default_rng(3))
    prns = [int(p) for p in eps[0].gnss["v1"].prn]
    weak_v, weak_l = prns[1], prns[4]

    def weakened(gnss, drop=False):
        out = {}
        for v, g in gnss.items():
            p = weak_v if v == "v1" else weak_l
            weak = g.prn == p
            out[v] = g.select(~weak) if drop else replace(g, cn0_dbhz=np.where(weak, 30.0, g.cn0_dbhz))
        return out

    def run(mask, drop=False, feed=None):
        ekf = ClusterEkf(StateLayout.build(lead="lead", vehicles=["v1"]), replace(cfg, gnss_cn0_mask_dbhz=mask))
        recs = []
        for k, ep in enumerate(eps):
            if k:
                ekf.predict(scn.dt_s)
            recs.append(list(ekf.update_gnss(weakened(ep.gnss, drop) if feed is None else feed(ep.gnss),
                                             ep.lead_base_ecef_m)))
        return ekf, recs

    masked, recs = run(40.0)
    for k, infos in enumerate(recs[1:], start=1):  # (epoch 0 initializes the follower)
        sd = [i for i in infos if i.kind in ("sd_pseudorange", "sd_doppler")]
        assert {i.prn for i in sd} == set(prns) - {weak_v, weak_l}, k
        assert len([i for i in sd if i.kind == "sd_pseudorange"]) == len(prns) - 2
    assert masked.counters["gnss_cn0_masked"] == 2 * len(eps)
    dropped, _ = run(0.0, drop=True)
    np.testing.assert_array_equal(masked.x, dropped.x)
    np.testing.assert_array_equal(masked.P, dropped.P)
    at_cn0, recs45 = run(45.0, feed=lambda gnss: gnss)
    plain, recs0 = run(0.0, feed=lambda gnss: gnss)
    assert recs45 == recs0 and "gnss_cn0_masked" not in at_cn0.counters
    np.testing.assert_array_equal(at_cn0.x, plain.x)


def test_cn0_mask_counts_only_strong_satellites_for_the_weak_epoch_height_aiding():
    """With fewer than 4 SD pseudoranges an epoch cannot fix the relative position, so height
    aiding is added ("relative up"); with a C/N0 mask the count is of the signals that pass it.
    After 1 s of full-strength epochs, all but 3 of the follower's satellites drop to 30 dB-Hz:
    with a 40 dB-Hz mask each such epoch has 3 SD pseudoranges and one height-aiding update of
    the follower; without the mask it has every SD and no height aiding."""
    cfg = FilterConfig(height_aiding_sigma_m=1.0)
    scn = SimScenario(n_vehicles=2, duration_s=2.0, uwb=False, bearing_vehicles=())
    eps = simulate(scn, cfg, np.random.default_rng(4))
    strong = set(int(p) for p in eps[0].gnss["v1"].prn[:3])

    def weakened(gnss):
        g = gnss["v1"]
        weak = ~np.isin(g.prn, list(strong))
        return {**gnss, "v1": replace(g, cn0_dbhz=np.where(weak, 30.0, g.cn0_dbhz))}

    for mask, n_pr, n_height in ((40.0, 3, 1), (0.0, len(eps[0].gnss["v1"].prn), 0)):
        ekf = ClusterEkf(StateLayout.build(lead="lead", vehicles=["v1"]), replace(cfg, gnss_cn0_mask_dbhz=mask))
        for k, ep in enumerate(eps):
            if k:
                ekf.predict(scn.dt_s)
            late = ep.t_s > 1.0 + 1e-9
            infos = list(ekf.update_gnss(weakened(ep.gnss) if late else ep.gnss, ep.lead_base_ecef_m))
            if late:
                assert len([i for i in infos if i.kind == "sd_pseudorange"]) == n_pr, (mask, k)
                assert len([i for i in infos if i.kind == "height_aiding" and i.vehicles == ("v1",)]) == n_height
                assert ekf.gnss_weak["v1"] == (n_height == 1)


def test_uwb_inequality_constraint_lands_on_the_bound():
    """Thesis eq. 3.19: bias above max -> pseudo-measurement at min with variance
    P (max - min) / (x - max); gain P / (P + r) = (x - max) / (x - min) moves x exactly to max."""
    cfg = FilterConfig(uwb_bias_bounds_m=(-0.5, 0.5))
    lay = StateLayout.build(lead="L", vehicles=["A"], uwb_pairs=[("L", "A")])
    ekf = ClusterEkf(lay, cfg)
    i = lay.uwb_bias(("L", "A"))
    ekf._set_block(slice(i, i + 1), np.array([0.8]), np.array([[0.04]]))
    infos = ekf._apply_constraints(("A", "L"))
    assert len(infos) == 1 and infos[0].kind == "uwb_constraint"
    assert ekf.x[i] == pytest.approx(0.5, abs=1e-12)
    # r = 0.04 * 1.0 / 0.3;  P+ = P r / (P + r) = 0.04 / (1 + 0.3) = 0.04 / 1.3
    assert ekf.P[i, i] == pytest.approx(0.04 / 1.3, rel=1e-12)


def test_a_state_on_its_bound_up_to_round_off_is_not_pulled_again():
    """After a pull, round-off can leave the bias an ulp past its bound (0.5 -> 0.5000000000000001):
    that is on the bound, no second pseudo-measurement (the compiled engine, rounding otherwise,
    logged one of NIS ~1e-50 where the Python one did not). A state past the bound by more than
    1e-9 of the bounds' width is pulled."""
    cfg = FilterConfig(uwb_bias_bounds_m=(-0.5, 0.5))
    lay = StateLayout.build(lead="L", vehicles=["A"], uwb_pairs=[("L", "A")])
    i = lay.uwb_bias(("L", "A"))
    for x0, pulled in ((np.nextafter(0.5, 1.0), False), (-np.nextafter(0.5, 1.0), False), (0.5 + 1e-8, True)):
        ekf = ClusterEkf(lay, cfg)
        ekf._set_block(slice(i, i + 1), np.array([x0]), np.array([[0.04]]))
        assert len(ekf._apply_constraints(("A", "L"))) == int(pulled), x0


# --------------------------------------------------------------------------- layout
def test_layout_named_slices_and_add_remove_remap():
    lay = StateLayout.build(lead="L", vehicles=["A", "B"], azimuth_vehicles=["L", "A"], uwb_pairs=[("A", "L")])
    assert lay.n == 8 + 8 + 1 + 1 + 2
    assert lay.position("B") == slice(8, 11) and lay.clock("A") == 6 and lay.drift("B") == 15
    assert lay.uwb_bias(("L", "A")) == lay.uwb_bias(("A", "L"))
    assert lay.position_starts == {"A": 0, "B": 8} and lay.velocity_starts == {"A": 3, "B": 11}  # the blocks' 8 states: p v c d
    rng = np.random.default_rng(1)
    x = rng.standard_normal(lay.n)
    a = rng.standard_normal((lay.n, lay.n))
    P = a @ a.T
    new, remap = lay.add_vehicle("C", mean=np.arange(8.0), variance=1e6)
    x2, p2 = remap(x, P)
    assert new.vehicles == ("A", "B", "C") and new.n == lay.n + 8
    np.testing.assert_array_equal(x2[new.position("A")], x[lay.position("A")])
    np.testing.assert_array_equal(x2[new.block("vehicle", "C")], np.arange(8.0))
    assert p2[new.clock("C"), new.clock("C")] == 1e6 and np.all(p2[new.block("vehicle", "C"), :16] == 0)
    np.testing.assert_array_equal(p2[new.azimuth("L"), new.uwb_scale(("A", "L"))],
                                  P[lay.azimuth("L"), lay.uwb_scale(("A", "L"))])
    gone, remap2 = lay.without_vehicle("A")
    x3, p3 = remap2(x, P)
    assert gone.vehicles == ("B",) and gone.azimuth_vehicles == ("L",) and gone.uwb_pairs == ()
    keep = np.r_[np.arange(8, 16), lay.azimuth("L")]
    np.testing.assert_array_equal(x3, x[keep])
    np.testing.assert_array_equal(p3, P[np.ix_(keep, keep)])


def test_engine_add_and_remove_vehicle_keeps_filtering():
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=3, duration_s=2.0, bearing_vehicles=())
    ekf = ClusterEkf(StateLayout.build(lead="lead", vehicles=["v1"]), cfg)
    eps = simulate(scn, cfg, np.random.default_rng(2))
    for k, (_, _) in enumerate(run_filter(ekf, eps, scn.dt_s)):
        if k == 5:
            ekf.add_vehicle("v2")
        if k == 15:
            ekf.remove_vehicle("v1")
    assert ekf.layout.vehicles == ("v2",) and ekf.is_initialized("v2")
    e = ekf.x[ekf.layout.position("v2")] - eps[-1].rel_state["v2"][:3]
    assert np.all(np.abs(e) < 5 * np.sqrt(np.diag(ekf.P)[ekf.layout.position("v2")]))


def test_bad_configuration_is_a_user_error():
    with pytest.raises(UserError, match="significance"):
        FilterConfig(significance=0.0)
    with pytest.raises(UserError, match="vel_tau_s"):
        ProcessNoiseConfig(vel_tau_s=0.0)
    with pytest.raises(UserError, match="uwb_sigma_m"):
        MeasurementNoiseConfig(uwb_sigma_m=-1.0)
    with pytest.raises(UserError, match="uwb_pairs"):
        StateLayout.build(lead="L", vehicles=["A"], uwb_pairs=[("A", "X")])
    for bad in (-1.0, float("nan"), "41", None, True):
        with pytest.raises(UserError, match="gnss_cn0_mask_dbhz"):
            FilterConfig(gnss_cn0_mask_dbhz=bad)


def test_every_filter_sigma_must_give_a_positive_normal_variance():
    """The filter's own configuration objects apply the scenario's rule (v2v.errors.sigma_problem)
    to every sigma they square into a variance, in radians where that is their unit: sigma in
    [2^-511, sqrt(float max / 2)] (0 also where it turns a term off), tau finite and normal.
    The largest and smallest accepted sigma and the floats just outside them."""
    import math

    from v2v.errors import SIGMA_MAX, SIGMA_MIN
    from v2v.estimation.phase import PhaseConfig

    makers = {"noise": MeasurementNoiseConfig, "process": ProcessNoiseConfig, "filter": FilterConfig,
              "phase": PhaseConfig}
    sigmas = {"noise": ["pseudorange_sigma_m", "doppler_sigma_mps", "uwb_sigma_m", "bearing_sigma_rad"],
              "process": ["vel_sigma_horizontal_mps", "vel_sigma_vertical_mps", "drift_sigma_mps",
                          "azimuth_rw_rad_per_sqrt_s", "yaw_rate_sigma_rps", "uwb_bias_rw_m_per_sqrt_s",
                          "uwb_scale_rw_per_sqrt_s"],
              "filter": ["uwb_bias_sigma0_m", "uwb_scale_sigma0", "azimuth_sigma0_rad", "clock_reset_sigma_m",
                         "height_aiding_sigma_m"],
              "phase": ["phase_sigma_m", "fix_hold_sigma_cycles"]}
    off = {"azimuth_rw_rad_per_sqrt_s", "yaw_rate_sigma_rps", "uwb_bias_rw_m_per_sqrt_s", "uwb_scale_rw_per_sqrt_s"}
    for prefix, names in sigmas.items():
        for name in names:
            make = makers[prefix]
            for good in (SIGMA_MIN, SIGMA_MAX, 1.0) + ((0.0,) if name in off else ()):
                assert getattr(make(**{name: good}), name) == good
            for bad in (math.nextafter(SIGMA_MIN, 0.0), math.nextafter(SIGMA_MAX, math.inf), 1e-300, 1e200,
                        math.inf, math.nan, -1.0) + (() if name in off else (0.0,)):
                with pytest.raises(UserError) as e:
                    make(**{name: bad})
                assert e.value.field == f"{prefix}.{name}" and "\n" not in e.value.one_line(), e.value.one_line()
    for name in ("vel_tau_s", "drift_tau_s", "yaw_rate_tau_s"):
        assert getattr(ProcessNoiseConfig(**{name: 2.2250738585072014e-308}), name) > 0.0
        for bad in (math.inf, math.nan, 0.0, 1e-310):
            with pytest.raises(UserError, match=f"process.{name}"):
                ProcessNoiseConfig(**{name: bad})
