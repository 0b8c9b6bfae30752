"""Statistical consistency (NEES/NIS) and the paper's qualitative findings.

World: :mod:`v2v.estimation.simulate` in "process" mode, i.e. the truth is drawn from the
filter's own process model and the measurement noise is exactly the filter's, so an
exact filter gives NEES ~ chi2(n) per run and NIS ~ chi2(1) per scalar innovation.
The process velocity sigmas are reduced (1 m/s horizontal, 0.1 m/s vertical, same in
world and filter) so that the drawn relative motion keeps a 28 m in-line formation for
10 s; everything else is the paper's model.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from v2v.estimation.filter import ClusterEkf, FilterConfig
from v2v.estimation.layout import StateLayout
from v2v.estimation.process import ProcessNoiseConfig
from v2v.estimation.simulate import SimScenario, run_filter, simulate
from v2v.frames import heading_unit_vectors, wrap_angle

CFG = FilterConfig(process=ProcessNoiseConfig(vel_sigma_horizontal_mps=1.0, vel_sigma_vertical_mps=0.1))
SCN = SimScenario(n_vehicles=3, duration_s=10.0, truth="process", bearing_vehicles=("lead", "v1"))
LAYOUT = StateLayout.build(lead="lead", vehicles=("v1", "v2"), azimuth_vehicles=("lead",))
# azimuth + GM yaw-rate states (the pipeline's default az-est model), truth drawn from the same model
SCN_RATE = SimScenario(n_vehicles=3, duration_s=10.0, truth="process", bearing_vehicles=("lead", "v1"),
                       azimuth_rates=True)
LAYOUT_RATE = StateLayout.build(lead="lead", vehicles=("v1", "v2"), azimuth_vehicles=("lead", "v1"),
                                azimuth_rates=True)


def _monte_carlo(n_runs: int, layout: StateLayout = LAYOUT, scn: SimScenario = SCN, seed: int = 2024):
    n_ep = int(round(scn.duration_s / scn.dt_s)) + 1
    nees = np.full((n_runs, n_ep), np.nan)
    nis: dict[str, list[float]] = {}
    for r in range(n_runs):
        ekf = ClusterEkf(layout, CFG)
        eps = simulate(scn, CFG, np.random.default_rng(np.random.SeedSequence(seed).spawn(n_runs)[r]))
        for k, (ep, infos) in enumerate(run_filter(ekf, eps, scn.dt_s)):
            for i in infos:
                nis.setdefault(i.kind, []).append(i.nis)
            if not all(ekf.is_azimuth_initialized(v) for v in layout.azimuth_vehicles):
                continue  # the azimuth is diffuse until its first usable bearing
            e = ekf.x - ep.truth_vector(layout)
            for v in layout.azimuth_vehicles:
                e[layout.azimuth(v)] = wrap_angle(e[layout.azimuth(v)])
            nees[r, k] = e @ np.linalg.solve(ekf.P, e)
    return nees, nis


GNSS_LAYOUT = StateLayout.build(lead="lead", vehicles=("v1", "v2"))
GNSS_SCN = SimScenario(n_vehicles=3, duration_s=10.0, truth="process", uwb=False, bearing_vehicles=())
SIGMA_TOLERANCE = 1.15  # the calibration criterion of the full filter: sigmas right to within 15 %


def _nis_in_band(nis: dict[str, list[float]], kinds: tuple[str, ...]) -> None:
    """Per measurement type the mean of all M scalar NIS values inside the two-sided 99.9 %
    band [chi2_0.0005(M)/M, chi2_0.9995(M)/M] (sequential innovations are independent under H0)."""
    for kind in kinds:
        v = np.asarray(nis[kind])
        m = len(v)
        assert m > 1000
        lo_m, hi_m = chi2.ppf(0.0005, m) / m, chi2.ppf(0.9995, m) / m
        assert lo_m <= v.mean() <= hi_m, f"{kind}: mean NIS {v.mean():.4f} outside [{lo_m:.4f}, {hi_m:.4f}]"


def _check(n_runs: int, layout: StateLayout = GNSS_LAYOUT, scn: SimScenario = GNSS_SCN, min_valid: float = 0.9,
           seed: int = 2024) -> None:
    """Exact consistency of the GNSS-only filter: the average NEES over runs inside its
    two-sided 95 % band [chi2_0.025(N n)/N, chi2_0.975(N n)/N] in >= 90 % of epochs, and the SD
    pseudoranges' NIS in its 99.9 % band (:func:`_nis_in_band`); the SD Dopplers' NIS, 1.2-1.6 %
    high because of the innovation test (see :func:`_check_calibrated`), to within the 15 %
    variance criterion.

    False-failure rate of the NEES criterion, measured by running it with 100 other seed
    bases: 8 / 100 and, with the Doppler criterion as here, 7 / 100 (mean NEES 1.008 n). Had epochs been
    independent, the count outside would be Binomial(K ~ 95, 0.05) and P(> 10 % outside) =
    2.5 %; the epochs of one run are positively correlated, which widens that distribution.
    """
    nees, nis = _monte_carlo(n_runs, layout, scn, seed)
    n = layout.n
    valid = ~np.isnan(nees).any(axis=0)
    assert valid.sum() >= min_valid * nees.shape[1]
    avg = nees[:, valid].mean(axis=0)
    lo, hi = chi2.ppf(0.025, n_runs * n) / n_runs, chi2.ppf(0.975, n_runs * n) / n_runs
    frac = float(np.mean((avg >= lo) & (avg <= hi)))
    assert frac >= 0.9, f"NEES inside [{lo:.2f}, {hi:.2f}] in {frac:.0%} of epochs (mean {avg.mean():.2f}, n={n})"
    _nis_in_band(nis, ("sd_pseudorange",))
    dop = float(np.mean(nis["sd_doppler"]))
    assert SIGMA_TOLERANCE**-2 <= dop <= SIGMA_TOLERANCE**2, f"sd_doppler mean NIS {dop:.4f}"


def _check_calibrated(n_runs: int, layout: StateLayout = LAYOUT, scn: SimScenario = SCN, min_valid: float = 0.9,
                      seed: int = 2024) -> None:
    """The filter with UWB ranges and bearings is NOT exactly consistent, and this says how far:
    its NEES, averaged over runs and epochs, is 1.079 n (100 seed bases x 20 runs; per seed base
    0.98-1.30 n): the reported sigmas are ~4 % too small. The exact check above fails for 64 /
    100 seed bases. The cause is the range nonlinearity: with the vertical relative position
    known to only ~1-2 m, the second-order mean term tr(H2 P_d)/2 that the range model adds
    (Gelb 1974) pulls the range estimates short (mean normalized error -0.3 to -0.5 along the
    three UWB lines); without it the range bias goes but the ranges' vertical partial makes the
    up axis overconfident instead (position NEES 1.34 per dof instead of 1.11). Checked here:
    sigmas right to within 15 % (mean NEES between n / 1.15^2 and 1.15^2 n), and the NIS of
    pseudoranges, UWB and bearings exact (:func:`_nis_in_band`). The SD Dopplers' NIS is
    1.2-1.6 % high in every configuration (1.0158 GNSS-only, 1.0176 here, over 160 000
    updates each), so it is held to the same 15 % variance criterion, not the band. That is
    the innovation test, not the model: without it (significance 1e-15) the mean is 1.002.
    In this world the clock drift moves as the filter's deliberately loose model says (sigma
    141 m/s per 0.1 s); when one increment exceeds the gate, every Doppler of that vehicle
    fails the test together (0.18 % rejected instead of 0.1 %, NIS 12.6 on average), and
    those rejected values enter the mean; the accepted ones average 0.9945.
    False-failure rates, measured with 100 other seed bases: 1 / 100 for 20 runs (a mean NEES
    of 1.38 n), 2 / 100 for the 10-run azimuth + yaw-rate variant (bearing NIS 1.079 and 1.088
    against a band ending at 1.078)."""
    nees, nis = _monte_carlo(n_runs, layout, scn, seed)
    n = layout.n
    valid = ~np.isnan(nees).any(axis=0)
    assert valid.sum() >= min_valid * nees.shape[1]
    ratio = float(nees[:, valid].mean()) / n
    assert SIGMA_TOLERANCE**-2 <= ratio <= SIGMA_TOLERANCE**2, f"mean NEES {ratio:.3f} n (n={n})"
    _nis_in_band(nis, ("sd_pseudorange", "uwb", "bearing"))
    dop = float(np.mean(nis["sd_doppler"]))
    assert SIGMA_TOLERANCE**-2 <= dop <= SIGMA_TOLERANCE**2, f"sd_doppler mean NIS {dop:.4f}"


def test_nees_nis_consistency_gnss_only_20_runs():
    _check(20)


@pytest.mark.slow
def test_nees_nis_consistency_gnss_only_50_runs():
    _check(50)


def test_uwb_and_bearing_filter_calibrated_within_15_percent_20_runs():
    _check_calibrated(20)


def test_azimuth_and_yaw_rate_states_calibrated_within_15_percent_10_runs():
    """The same with two estimated azimuths, each with its GM yaw-rate state (sigma 30 deg/s,
    tau 1 s: the pipeline default) drawn from that model; 10 runs keep it short. NEES starts
    once both azimuths are initialized in every run: a bearing waits until the GNSS-initialized
    relative covariance is small enough for the linear model (~1 s), so >= 85 % of the epochs."""
    _check_calibrated(10, LAYOUT_RATE, SCN_RATE, min_valid=0.85)


def test_replay_epoch_nis_time_mean_inside_its_chi_square_band_20_runs():
    """The replay's per-epoch NIS (:func:`v2v.pipeline.epoch_nis_of_rows`, what ``v2v run``
    logs as ``errors/<sol>/<veh>/nis``) of the filter with UWB and bearings in the world whose
    noise is the filter's own: per vehicle, its time mean over the epochs of 20 runs lies in
    the two-sided 99.9 % band of its distribution under H0.

    Under H0 an accepted NIS is chi-square(1) truncated at the gate c = k^2 = 10.83 (rejected
    ones are left out): with F_k the chi-square(k) cdf and x f_1(x) = f_3(x),
    x^2 f_1(x) = 3 f_5(x), its mean is mu = F_3(c) / F_1(c) = 0.9883 and its second moment
    3 F_5(c) / F_1(c); a sequential update's scalar innovations are independent. An epoch's
    value is the mean of its n_k accepted NIS (k = 1..K, those with n_k > 0), so the time
    mean T has mean mu and variance V = var / K^2 sum_k 1 / n_k. The band is that of the
    scaled chi-square a chi2(nu) with the same two moments (Satterthwaite 1946):
    nu = 2 mu^2 / V, a = mu / nu. Here K = 2000, n_k ~ 20, sqrt(V) ~ 0.007.

    False-failure rate: nominal 0.1 % per vehicle, 0.2 % for the two. Measured with 100 other
    seed bases (10 000 + i): 0 / 200 outside; T sat 0.33 sqrt(V) above mu on average (sd
    1.04), which makes it ~0.15 % per vehicle: the SD Dopplers' accepted NIS average 0.9945,
    not 0.988 (the innovation test, see :func:`_check_calibrated`)."""
    from scipy import special

    from v2v.metrics.errors import EPOCH_NIS_KINDS
    from v2v.pipeline import UpdateLog, epoch_nis_of_rows

    n_runs, vehicles = 20, ("v1", "v2")
    seeds = np.random.SeedSequence(2024).spawn(n_runs)
    values: dict[str, list[np.ndarray]] = {v: [] for v in vehicles}
    counts: dict[str, list[int]] = {v: [] for v in vehicles}
    for r in range(n_runs):
        ekf = ClusterEkf(LAYOUT, CFG)
        log = UpdateLog()
        log.keep_recent = True
        times = []
        for ep, infos in run_filter(ekf, simulate(SCN, CFG, np.random.default_rng(seeds[r])), SCN.dt_s):
            log.add(ep.t_s, infos, [False] * len(infos))
            times.append(ep.t_s)
            for v in vehicles:  # n_k straight from the records
                counts[v].append(sum(i.accepted and i.kind in EPOCH_NIS_KINDS and v in i.vehicles for i in infos))
        log.flush()
        nis = epoch_nis_of_rows(log.take_recent(), times, np.repeat(times, len(vehicles)), list(vehicles) * len(times))
        for j, v in enumerate(vehicles):
            values[v].append(nis[j :: len(vehicles)])
    c = CFG.gate_k**2
    f1, f3, f5 = (special.gammainc(k / 2.0, c / 2.0) for k in (1, 3, 5))
    mu, var = f3 / f1, 3.0 * f5 / f1 - (f3 / f1) ** 2
    assert mu == pytest.approx(0.9883, abs=1e-4)
    for v in vehicles:
        x, n = np.concatenate(values[v]), np.array(counts[v])
        np.testing.assert_array_equal(np.isnan(x), n == 0)
        x, n = x[n > 0], n[n > 0]
        assert len(x) >= 0.95 * len(counts[v])
        big_v = var * np.sum(1.0 / n) / len(x) ** 2
        nu = 2.0 * mu**2 / big_v
        lo, hi = mu / nu * chi2.ppf(0.0005, nu), mu / nu * chi2.ppf(0.9995, nu)
        assert lo <= x.mean() <= hi, f"{v}: time mean of the epoch NIS {x.mean():.4f} outside [{lo:.4f}, {hi:.4f}]"


# --------------------------------------------------------------------------- paper findings
def _lead_frame_sigmas(ekf: ClusterEkf, v: str, lead_azimuth_rad: float) -> tuple[float, float]:
    fwd, left = heading_unit_vectors(lead_azimuth_rad)
    s = ekf.layout.position(v)
    ph = ekf.P[s, s][:2, :2]
    return float(np.sqrt(fwd @ ph @ fwd)), float(np.sqrt(left @ ph @ left))


def test_uwb_improves_along_track_and_bearing_improves_across_track():
    """Petovello et al. sections 3.3 and 5: on an in-line cluster UWB mainly shrinks the
    along-track sigma and bearings the across-track sigma (from the filter covariance
    after 10 s, paper defaults). Measured (seed 0): GPS-only along/across 0.70/0.67 m;
    +UWB 0.19/0.63; +bearing 0.69/0.14 (v1). Thresholds: the helped axis shrinks by more
    than half, the other by less than 15 % (geometry: UWB's line of sight is along-track,
    the bearing's sensitivity is across-track)."""
    cfg = FilterConfig()
    lay = StateLayout.build(lead="lead", vehicles=("v1", "v2"))
    sig = {}
    for name, kw in [("gps", dict(uwb=False, bearing_vehicles=())), ("uwb", dict(bearing_vehicles=())),
                     ("brg", dict(uwb=False))]:
        scn = SimScenario(n_vehicles=3, duration_s=10.0, **kw)
        ekf = ClusterEkf(lay, cfg)
        eps = simulate(scn, cfg, np.random.default_rng(0))
        for _ in run_filter(ekf, eps, scn.dt_s):
            pass
        ep = eps[-1]
        sig[name] = {v: _lead_frame_sigmas(ekf, v, ep.lead_azimuth_rad) for v in lay.vehicles}
    for v in lay.vehicles:
        (ga, gc), (ua, uc), (ba, bc) = sig["gps"][v], sig["uwb"][v], sig["brg"][v]
        assert ua < 0.5 * ga and uc > 0.85 * gc, (v, sig)
        assert bc < 0.5 * gc and ba > 0.85 * ga, (v, sig)


def test_uwb_and_bearings_carry_the_horizontal_solution_through_30_s_without_gnss():
    """Petovello et al. section 3.3: with three vehicles making UWB and bearing
    measurements the horizontal relative solution is determined without GNSS. GNSS for
    10 s, then none for 30 s; height aiding (relative up = 0 +- 1 m) replaces the vertical
    information GNSS gave. In 5 seeds: horizontal sigma must stay bounded (<= 0.5 m at every
    epoch; measured ~0.3 m, vs. 4-5 m at GNSS initialization and growing without bound if
    the measurements were not used), and the horizontal errors must be as large as those
    sigmas say: each run's mean horizontal NEES (chi-square(2) per epoch and vehicle if the
    filter is right) over the outage is one number with at most a single sample's variance
    (a mean of identically distributed, correlated samples varies no more than one of them),
    so the average of the 5 runs' means must lie in the 99.9 % band of chi-square(10)/5.
    (The check this replaces, |error| <= 3 sigma at each of 1204 samples of one seed, fails
    in 82 of 100 seeds with the filter consistent: pooled, 0.15 % of samples exceed 3 sigma
    against 0.27 % expected.)"""
    cfg = FilterConfig(height_aiding_sigma_m=1.0)
    lay = StateLayout.build(lead="lead", vehicles=("v1", "v2"))
    scn = SimScenario(n_vehicles=3, duration_s=40.0, gnss_outage_s=(10.0, 41.0),
                      bearing_vehicles=("lead", "v1", "v2"))
    run_means = []
    for seed in range(5):
        ekf = ClusterEkf(lay, cfg)
        n_outage, nees = 0, []
        for ep, _ in run_filter(ekf, simulate(scn, cfg, np.random.default_rng(seed)), scn.dt_s):
            if ep.gnss is not None:
                continue
            n_outage += 1
            for v in lay.vehicles:
                s = lay.position(v)
                c = ekf.P[s, s][:2, :2]
                err = (ekf.x[s] - ep.rel_state[v][:3])[:2]
                assert np.all(np.sqrt(np.diag(c)) <= 0.5), (seed, ep.t_s, v, np.sqrt(np.diag(c)))
                nees.append(float(err @ np.linalg.solve(c, err)))
        assert n_outage == 301  # t = 10.0 ... 40.0 s at 10 Hz
        run_means.append(np.mean(nees))
    lo, hi = chi2.ppf([0.0005, 0.9995], 2 * len(run_means)) / len(run_means)
    assert lo <= np.mean(run_means) <= hi, (run_means, lo, hi)
