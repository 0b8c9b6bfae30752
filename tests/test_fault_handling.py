"""Fault handling of the cluster EKF in the simulate.py world (issue 8).

The simulate.py world draws measurements with exactly the filter's noise model, so the
filter is consistent there and the textbook statistics hold:

* innovation test, k = 3.2905 (alpha = 0.001): a blunder of b innovation sigmas is detected
  with probability P(|N(b, 1)| > k) = 0.761 / 0.956 / 0.9966 for b = 4 / 5 / 6; a clean
  measurement is rejected with probability alpha. The innovations of a consistent KF are
  white, so the trials (one per epoch) are independent Bernoulli draws; each observed rate
  is checked against its binomial 99.75 % interval, and the false-alarm count against its own
  (four checks: a false failure with probability <= 1 % for the family, Bonferroni; the seeds
  are fixed).
* the clock jump, outage and divergence checks compare with 3-sigma / chi-square bounds
  at a fixed seed; P must be symmetric positive definite after every epoch.
"""

from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import binom, chi2, norm

from v2v.estimation.faultsim import (
    blunder_trials,
    fault_run,
    sim_layout,
    uwb_bias_step_run,
    uwb_blunder_trials,
    with_pr_offset,
)
from v2v.estimation.filter import KIND_SD_PR, ClusterEkf, FilterConfig
from v2v.estimation.simulate import SimScenario, simulate


def _assert_spd(P: np.ndarray) -> None:
    assert np.max(np.abs(P - P.T)) <= 1e-12 * np.max(np.abs(P))
    np.linalg.cholesky(P)  # raises if not positive definite


def _spd(ekf: ClusterEkf) -> None:
    _assert_spd(ekf.P)


def _subset(ep, mask: np.ndarray):
    """The satellites ``mask`` of one GnssEpoch (every per-satellite array)."""
    fields = ("prn", "pseudorange_m", "doppler_mps", "carrier_cycles", "lock_time_s", "cn0_dbhz", "sv_pos_ecef_m",
              "sv_vel_ecef_mps", "sv_clock_m", "elevation_rad", "azimuth_rad", "los", "true_range_m",
              "ambiguity_cycles")
    return replace(ep, **{f: getattr(ep, f)[mask] for f in fields},
                   errors_m={k: v[mask] for k, v in ep.errors_m.items()})


def _nees(ekf: ClusterEkf, ep, v: str) -> float:
    sl = ekf.layout.position(v)
    e = ekf.x[sl] - ep.rel_state[v][:3]
    return float(e @ np.linalg.solve(ekf.P[sl, sl], e))


def _check_rates(det, n_clean, n_rej, k):
    """Each detection rate and the false-alarm count inside its binomial interval; the
    intervals' level makes the family's false-failure probability 1 % (Bonferroni)."""
    level = 1.0 - 0.01 / (len(det) + 1)
    for b, hits in det.items():
        p = norm.sf(k - b) + norm.cdf(-k - b)
        lo, hi = binom.interval(level, len(hits), p)
        assert lo <= sum(hits) <= hi, (b, sum(hits), len(hits), p)
    alpha = 0.001
    lo, hi = binom.interval(level, n_clean, alpha)
    assert lo <= n_rej <= hi, (n_rej, n_clean)


def test_blunder_detection_and_false_alarm_rates():
    """Measured with 3000 trials per size (slow test below): 0.764 / 0.956 / 0.9963 and a false-
    alarm rate of 144 / 144 000 = 0.0010. 300 trials per size: the 99.75 % binomial intervals of
    0.761 / 0.956 / 0.9966 are [0.683, 0.833] / [0.917, 0.987] / [0.983, 1]; ~14 000 clean tests:
    4-27 rejections (expected 14)."""
    det, n_clean, n_rej = blunder_trials(300, seed=7, check=_spd)
    _check_rates(det, n_clean, n_rej, FilterConfig().gate_k)


@pytest.mark.slow
def test_blunder_detection_and_false_alarm_rates_long():
    det, n_clean, n_rej = blunder_trials(3000, seed=8, check=_spd)
    _check_rates(det, n_clean, n_rej, FilterConfig().gate_k)


def _run(scn: SimScenario, seed: int, cfg: FilterConfig | None = None, jump_at_s: float | None = None,
         corrupt_at_s: float | None = None):
    """Run with a 1 ms clock jump of v1 and/or a +50 m east state corruption of v1
    (:func:`v2v.estimation.faultsim.fault_run`); per-epoch log."""
    log = []
    ekf = None
    for ep, ekf, infos in fault_run(scn, seed, cfg=cfg, jump_at_s=jump_at_s, corrupt_at_s=corrupt_at_s,
                                    check=_spd):
        sl = ekf.layout.position("v1")
        log.append({
            "t": ep.t_s, "ready": ekf.is_initialized("v1"),
            "err_over_sigma": (ekf.x[sl] - ep.rel_state["v1"][:3]) / np.sqrt(np.diag(ekf.P[sl, sl])),
            "nees": _nees(ekf, ep, "v1") if ekf.is_initialized("v1") else np.nan,
            "pr_v1": [i for i in infos if i.kind == KIND_SD_PR and i.vehicles == ("v1",)],
            "pr_nis": [i.nis for i in infos if i.kind == KIND_SD_PR],
            "resets": ekf.counters.get("divergence_reset", 0),
            "jumps": ekf.counters.get("clock_jump_detected", 0),
        })
    return ekf, log


def test_clock_jump_detected_baseline_kept_and_pseudoranges_used_again():
    """A 1 ms clock jump of v1 at 20 s is detected at its epoch. (The simulated world draws the
    clocks from the filter's deliberately loose drift model, whose increments can shift all of
    a vehicle's SD pseudoranges together: the detector re-initializes the clock for those too,
    ~1 in 600 s of clean data, which is its designed response; so the count is checked at the
    jump's epoch.) The baseline is not corrupted: the mean position NEES over the 6 s after
    the jump, one number with at most a chi-square(3) sample's variance, is below
    chi2_3(0.999) = 16.3 (a baseline moved by the 300 km jump would be ~1e10)."""
    scn = SimScenario(n_vehicles=3, duration_s=26.0)
    ekf, log = _run(scn, seed=11, jump_at_s=20.0)
    at = next(k for k, r in enumerate(log) if r["t"] >= 20.0 - 1e-9)
    assert log[at]["jumps"] - log[at - 1]["jumps"] == 1
    assert ekf.counters.get("divergence_reset", 0) == 0
    after = [r for r in log if 20.0 - 1e-9 <= r["t"]]
    assert np.mean([r["nees"] for r in after]) < chi2.ppf(0.999, 3)
    # pseudoranges accepted again within 1 s (here: already at the jump epoch)
    first_ok = next(r["t"] for r in after if sum(i.accepted for i in r["pr_v1"]) >= 4)
    assert first_ok - 20.0 <= 1.0
    assert all(sum(i.accepted for i in r["pr_v1"]) >= 4 for r in after if r["t"] >= 21.0)


def test_clock_jump_without_detection_rejects_every_pseudorange():
    """The test above has power: without the detector the jump epoch's pseudoranges all fail."""
    scn = SimScenario(n_vehicles=3, duration_s=20.5, uwb=False, bearing_vehicles=())
    ekf, log = _run(scn, seed=11, cfg=FilterConfig(clock_jump_detection=False), jump_at_s=20.0)
    jump = next(r for r in log if r["t"] >= 20.0 - 1e-9)
    assert jump["pr_v1"] and not any(i.accepted for i in jump["pr_v1"])


def test_nis_back_in_band_within_5_s_after_10_s_outage():
    """Mean NIS of all SD pseudoranges over [25 + 4, 25 + 5) s, n ~ 160 tests, in the 99.9 %
    band of chi2(n)/n."""
    scn = SimScenario(n_vehicles=3, duration_s=32.0, gnss_outage_s=(15.0, 25.0))
    ekf, log = _run(scn, seed=12)
    nis = [x for r in log if 29.0 - 1e-9 <= r["t"] < 30.0 - 1e-9 for x in r["pr_nis"]]
    n = len(nis)
    assert n >= 100
    lo, hi = chi2.ppf([0.0005, 0.9995], n) / n
    assert lo <= np.mean(nis) <= hi
    assert ekf.counters.get("divergence_reset", 0) == 0


def test_divergence_reset_and_nees_back_in_band():
    """State of v1 pushed 50 m east at t = 10 s with an unchanged (metre-level) P, in 20 seeds.

    In most geometries only some pseudoranges fail their test (the SD clock takes the offset's
    common part; 5 of 8 pass in seed 1), so the window's rejected fraction stays below 1/2:
    before the mean-NIS test, v1 stayed ~30 sigma off for the rest of the run in 18 of these
    20 seeds. The window's mean NIS (each capped at the gate, 10.8) is ~7 (at most 1.9 in the
    same runs without the fault; chi-square(50)/50 under H0: P(> 5) < 2e-28), so
    each seed must reset exactly once, within 2 s (the window is 50 tests, ~0.6 s at 8 SVs,
    10 Hz), and the next snapshot re-initializes v1.

    Back in band: each seed's mean position NEES over the epochs from 10 s after its reset is
    one number whose variance is at most a single chi-square(3) sample's (a mean of identically
    distributed, correlated samples varies no more than one of them), so the average of the 20
    seeds' means must lie inside the 99.9 % band of chi-square(60)/20, a band at least as wide
    as the true one."""
    scn = SimScenario(n_vehicles=3, duration_s=25.0)
    means = []
    for seed in range(20):
        ekf, log = _run(scn, seed=seed, corrupt_at_s=10.0)
        assert ekf.counters.get("divergence_reset", 0) == 1, seed
        t_reset = next(r["t"] for r in log if r["resets"] >= 1)
        assert 10.0 < t_reset < 12.0, seed
        late = np.array([r["nees"] for r in log if r["t"] >= t_reset + 10.0 - 1e-9])
        assert len(late) and np.all(np.isfinite(late)), seed
        means.append(late.mean())
        # before the reset the corrupted state is far outside (the check has power)
        assert max(r["nees"] for r in log if 10.0 <= r["t"] < t_reset) > 100.0, seed
    lo, hi = chi2.ppf([0.0005, 0.9995], 3 * len(means)) / len(means)
    assert lo <= np.mean(means) <= hi, (np.mean(means), lo, hi)



def _suspect_run(seed: int, *, suspect_at_s: float, corrupt_m: float = 0.0, four_until_s: float | None = None,
                 duration_s: float = 14.0):
    """A GNSS-only run in which v1's divergence test is made to fire at ``suspect_at_s`` (its
    state moved ``corrupt_m`` east at that epoch, its P unchanged); until ``four_until_s`` v1
    keeps only its 4 highest satellites from that epoch on. Per epoch: (t, counters)."""
    def before(ep, ekf, gnss):
        if four_until_s is not None and suspect_at_s - 1e-9 <= ep.t_s < four_until_s - 1e-9:
            g = gnss["v1"]
            gnss = {**gnss, "v1": _subset(g, g.elevation_rad >= np.sort(g.elevation_rad)[-4])}
        if abs(ep.t_s - suspect_at_s) < 1e-6:
            ekf._get_x()[ekf.layout.position("v1").start] += corrupt_m
            ekf._suspect["v1"] = ep.t_s  # as the window's test does (_window_diverged)
        return gnss

    scn = SimScenario(n_vehicles=3, duration_s=duration_s, uwb=False, bearing_vehicles=())
    return [(ep.t_s, dict(ekf.counters)) for ep, ekf, _ in fault_run(scn, seed, check=_spd, before=before)]


def test_a_suspect_state_that_a_trusted_snapshot_agrees_with_is_kept():
    """The divergence test fires on wrong pseudoranges as well as on a wrong state, so a reset
    waits for a snapshot it can trust (>= 5 satellites after the blunder screen, residuals
    inside their chi-square bound) that disagrees with the state (chi-square, 3 dof, alpha =
    0.001). Here the state is right: the next epoch's 8-satellite snapshot agrees, the
    suspicion is cleared and nothing is reset. Both the state and the snapshot are consistent
    in this world, so a false reset has probability alpha per seed: over 10 seeds P(any) ~ 1 %."""
    for seed in range(10):
        counters = _suspect_run(seed, suspect_at_s=8.0)[-1][1]
        assert counters.get("divergence_cleared", 0) == 1, seed
        assert counters.get("divergence_reset", 0) == 0, seed


def test_a_divergence_trip_scales_the_vehicle_covariance_by_the_window_mean_nis():
    """The trip's covariance-matching step: v1's rows and columns of P scaled by sqrt(m) (its
    block by m), every other entry unchanged, m = the window's mean NIS with each capped at
    the gate's k^2. Here 49 tests of NIS 6 and one blunder of NIS 1000 (capped):
    m = (49 * 6 + k^2) / 50, computed by hand."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=3, duration_s=8.0, uwb=False, bearing_vehicles=())
    *_, (_, ekf, _) = fault_run(scn, 5, cfg=cfg)
    w = ekf._nis_window["v1"]
    for nis in [6.0] * 49 + [1000.0]:
        w.add(nis, nis < cfg.gate_k**2)
    m = (49 * 6.0 + cfg.gate_k**2) / 50
    p0 = ekf.P.copy()
    ekf._inflate("v1")
    d = np.ones(len(p0))
    d[ekf.layout.block("vehicle", "v1")] = np.sqrt(m)
    np.testing.assert_allclose(ekf.P, p0 * np.outer(d, d), rtol=1e-12, atol=0.0)
    assert "v1" not in ekf._nis_window  # the window starts again
    _spd(ekf)


def test_a_reset_waits_for_a_snapshot_it_can_trust():
    """v1's state is 50 m off while it tracks only 4 satellites: a 4-satellite snapshot has no
    redundancy (an echo or blunder in it cannot show), so the suspect state is neither reset
    nor cleared; the first epoch with its 8 satellites back (1.5 s later, inside
    ``divergence_confirm_s`` = 2 s) resets it."""
    log = _suspect_run(3, suspect_at_s=8.0, corrupt_m=50.0, four_until_s=9.5)
    during = [c for t, c in log if 8.0 - 1e-9 <= t < 9.5 - 1e-9]
    assert during and all(c.get("divergence_reset", 0) == 0 and c.get("divergence_cleared", 0) == 0 for c in during)
    first_back = next(c for t, c in log if t >= 9.5 - 1e-9)
    assert first_back.get("divergence_reset", 0) == 1


def test_a_reset_without_a_trusted_snapshot_comes_after_divergence_confirm_s():
    """The same 50 m off state with 4 satellites for 5 s: no trusted snapshot comes, and
    ``divergence_confirm_s`` (2 s) after the trip the 4-satellite snapshot resets it (the
    first epoch at or after 10.0 s), as a reset to the uninitialized prior would."""
    log = _suspect_run(3, suspect_at_s=8.0, corrupt_m=50.0, four_until_s=13.0)
    before = [c for t, c in log if t < 10.0 - 1e-9]
    assert all(c.get("divergence_reset", 0) == 0 for c in before)
    at = next(c for t, c in log if t >= 10.0 - 1e-9)
    assert at.get("divergence_reset", 0) == 1 and at.get("divergence_cleared", 0) == 0
    assert log[-1][1].get("divergence_reset", 0) == 1


def test_two_blunders_excluded_and_integrity_flag():
    """Two 60 m (8.5 sigma) blunders in one epoch of 8 SVs: both flagged by the w-test and left
    out, the baseline is not pulled (iterative data snooping cannot separate every pair: for
    two low satellites close in azimuth it may flag only one); with only 5 SVs the screen cannot run: integrity unavailable."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=3, duration_s=6.0, uwb=False, bearing_vehicles=())
    eps = simulate(scn, cfg, np.random.default_rng(21))
    ekf = ClusterEkf(sim_layout(3), cfg)
    for k, ep in enumerate(eps[:-1]):
        if k:
            ekf.predict(scn.dt_s)
        ekf.update_gnss(ep.gnss, ep.lead_base_ecef_m)
    ep = eps[-1]
    ekf.predict(scn.dt_s)
    g = ep.gnss["v1"]
    bad_prns = np.array([2, 3])  # az 80 / 150 deg: separable (two low SVs close in azimuth may not be)
    before = ekf.counters.get("excluded_screened", 0)
    trial = copy.deepcopy(ekf)
    infos = trial.update_gnss(with_pr_offset(ep.gnss, "v1", np.where(np.isin(g.prn, bad_prns), 60.0, 0.0)),
                              ep.lead_base_ecef_m)
    v1 = {i.prn: i for i in infos if i.kind == KIND_SD_PR and i.vehicles == ("v1",)}
    assert not any(v1[int(p)].accepted for p in bad_prns)
    assert trial.counters.get("excluded_screened", 0) - before == 2
    assert trial.integrity_available["v1"]
    sl = trial.layout.position("v1")
    assert np.all(np.abs(trial.x[sl] - ep.rel_state["v1"][:3]) < 3.0 * np.sqrt(np.diag(trial.P[sl, sl])))
    few = dict(ep.gnss)
    keep = np.argsort(-g.elevation_rad)[:5]
    mask = np.zeros(g.n, dtype=bool)
    mask[keep] = True
    few["v1"] = _subset(g, mask)
    trial = copy.deepcopy(ekf)
    trial.update_gnss(few, ep.lead_base_ecef_m)
    assert not trial.integrity_available["v1"]
    assert trial.integrity_available["v2"]


def test_uwb_blunder_detection_rate():
    """5 innovation-sigma UWB blunders: P_D = P(|N(5, 1)| > 3.29) = 0.956; 300 trials, 99 %
    binomial interval [0.923, 0.983] (measured 0.967). Clean UWB tests of the same run: 900,
    expected 0.9 rejections; <= 5 is the 99.8 % Poisson quantile."""
    hits, n_clean, n_rej = uwb_blunder_trials(300, 5.0, seed=5, check=_spd)
    k = FilterConfig().gate_k
    p = norm.sf(k - 5.0) + norm.cdf(-k - 5.0)
    lo, hi = binom.interval(0.99, len(hits), p)
    assert lo <= sum(hits) <= hi, (sum(hits), len(hits), p)
    assert n_rej <= binom.ppf(0.998, n_clean, 0.001), (n_rej, n_clean)


def test_uwb_bias_step_without_uwb_states_is_not_detected_but_biases_the_baseline():
    """A replaced UWB radio (every range involving v1 + 1 m from 15 s; sigma_uwb = 0.5 m), filter
    without UWB bias/scale states: the per-range test cannot see it (even unabsorbed, 1 m is
    <= 2 innovation sigma: P_D <= P(|N(2, 1)| > 3.29) = 0.099; the filter then absorbs the bias
    into v1's position), and the UWB NIS barely moves; the harm shows only against the truth:
    v1's position NEES (3 dof) averages above chi2_3(0.999) = 16.3 after the step (measured
    ~31: 1 m along the baseline over a ~0.2 m sigma), below it before (measured 9.7 over
    5-15 s: one run's NEES is strongly time-correlated, the 5-seed mean is 2.9). This is the documented limitation (issue 8): without UWB
    error states such faults are undetected."""
    cfg = FilterConfig()
    rec = uwb_bias_step_run(6, bias_m=1.0, t_step_s=15.0)  # 30 s, the filter's model world
    after = [i for t, us, _ in rec if 15.0 - 1e-9 <= t < 20.0 for i in us]
    rej = sum(not i.accepted for i in after)
    assert rej <= binom.ppf(0.99, len(after), norm.sf(cfg.gate_k - 2.0) + norm.cdf(-cfg.gate_k - 2.0))
    nees_before = np.mean([x for t, _, x in rec if 5.0 <= t < 15.0])
    nees_after = np.mean([x for t, _, x in rec if 20.0 <= t < 30.0])
    assert nees_before < chi2.ppf(0.999, 3) < nees_after, (nees_before, nees_after)


def test_nis_window_rejection_count_and_capped_sum_are_the_windows_own():
    """NisWindow keeps the number of rejected tests among the last ``size`` (the divergence
    test's numerator) and the sum of their NIS capped at ``cap`` (the mean-NIS test's) as
    tests enter and push the oldest out; after every operation of a random sequence (single
    tests, some far above the cap or NaN, runs of accepted ones longer and shorter than the
    window) both equal a recount over the window's contents, which are the last ``size``
    tests given. (The sum is kept by additions and subtractions of values <= cap = 10.8: its
    round-off after 2000 operations is ~2000 ulp of ~50 * 10.8, far below 1e-9.)"""
    from collections import deque

    from v2v.estimation.filter import NisWindow

    rng = np.random.default_rng(5)
    cap = 3.29**2
    for size in (1, 3, 50):
        w, ref = NisWindow(size, cap), deque(maxlen=size)
        for _ in range(2000):
            if rng.random() < 0.5:
                ok = bool(rng.random() < 0.7)
                nis = float(rng.choice([rng.chisquare(1), 3e9, np.nan]))
                w.add(nis, ok)
                ref.append((nis, ok))
            else:
                nis = rng.chisquare(1, int(rng.integers(0, 2 * size + 2))).tolist()
                w.add_accepted(nis)
                ref.extend((n, True) for n in nis)
            assert [ok for _, ok in w.tests] == [ok for _, ok in ref]
            assert w.rejected == sum(not ok for _, ok in ref)
            capped = [n if n <= cap else cap for n, _ in ref]
            assert abs(w.nis_sum - sum(capped)) < 1e-9
