"""GNSS receiver synthesis, error models and standalone positioning, checked against theory.

Statistical tests use bounds with their false-failure rate written beside them; every
random test is seeded. Open-sky tests use the built-in nominal constellation (no
/work/shared needed).
"""

from __future__ import annotations

from dataclasses import replace
from datetime import datetime

import numpy as np
import pytest
from scipy import stats

from v2v.frames import GeoReference, ecef_to_enu_rotation, ecef_to_geodetic
from v2v.sensors.gnss.atmosphere import klobuchar_delay_s, saastamoinen_zenith_delay_m
from v2v.sensors.gnss.clock import TCXO, ClockConfig, ReceiverClock, allan_variance_theory
from v2v.sensors.gnss.constellation import NominalConstellation
from v2v.sensors.gnss.errors import (
    GnssErrorConfig,
    MultipathConfig,
    TrackingConfig,
    dll_jitter_m,
    multipath_sigma_m,
    pll_jitter_m,
)
from v2v.sensors.gnss.receiver import ERROR_KEYS, GnssReceiverConfig, GnssSynthesizer
from v2v.sensors.gnss.spp import SppChain, SppConfig, SppStatus, solve_spp
from v2v.sensors.gnss.time import utc_to_gps_s
from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M, SPEED_OF_LIGHT_MPS
from v2v.traffic.snapshot import TrafficStep, VehicleState
from v2v.world.buildings import Building, World

GPS0 = utc_to_gps_s(datetime(2021, 4, 28, 18, 0, 0))  # the paper-like Calgary afternoon
GEO = GeoReference(proj=None, origin_lat_deg=51.08, origin_lon_deg=-114.13, origin_h_m=1100.0)
ANTENNA_Z_M = 1.5
COMMON_KEYS = ("iono", "tropo", "orbit", "sv_clock", "sv_clock_error")


@pytest.fixture(scope="module")
def eph():
    return NominalConstellation(GPS0)


def vstate(vid: str, t_s: float, x_m: float, y_m: float = 0.0, vel_enu=(0.0, 0.0, 0.0)) -> VehicleState:
    """Truth at net XY (x, y) at t = 0, then a straight ECEF line with ENU velocity ``vel_enu``
    (at the start point): position and velocity are exactly consistent."""
    v0 = np.asarray(vel_enu, dtype=float)
    lat0, lon0 = GEO.xy_to_geodetic(x_m, y_m)
    v_ecef = v0 @ ecef_to_enu_rotation(float(lat0), float(lon0))
    ecef = GEO.xyz_to_ecef(x_m, y_m, ANTENNA_Z_M) + v_ecef * t_s
    lat, lon, h = ecef_to_geodetic(ecef)
    v = ecef_to_enu_rotation(float(lat), float(lon)) @ v_ecef
    x, y, z = x_m + v0[0] * t_s, y_m + v0[1] * t_s, ANTENNA_Z_M + v0[2] * t_s
    return VehicleState(
        vehicle_id=vid, cluster="c0", is_lead=False, t_s=t_s, xyz_m=np.array([x, y, z]),
        lat_rad=float(lat), lon_rad=float(lon), h_m=float(h), ecef_m=ecef, vel_enu_mps=v,
        speed_mps=float(np.hypot(v[0], v[1])), accel_mps2=0.0, azimuth_rad=0.0, grid_azimuth_rad=0.0, yaw_rate_rps=0.0,
        front_bumper_xy_m=np.array([x, y]), edge_id="e", lane_id="e_0", lane_index=0, lane_width_m=3.5,
        lateral_offset_m=0.0, length_m=4.5, width_m=1.8, height_m=1.5,
    )


def steps(positions: dict[str, tuple[float, float]], n: int, dt_s: float, vel=(0.0, 0.0, 0.0)):
    for k in range(n):
        t = k * dt_s
        yield TrafficStep(t_s=t, vehicles={v: vstate(v, t, *xy, vel_enu=vel) for v, xy in positions.items()})


def synth(eph, errors: GnssErrorConfig | None = None, seed: int = 1, rate_hz: float = 10.0, **kw) -> GnssSynthesizer:
    cfg = GnssReceiverConfig(rate_hz=rate_hz, errors=errors or GnssErrorConfig())
    return GnssSynthesizer(eph, cfg, np.random.SeedSequence(seed), GPS0, **kw)


def chi2_var_bounds(dof: float, p: float = 1e-3) -> tuple[float, float]:
    """Two-sided (1 - p) bounds on sample variance / true variance with ``dof`` degrees of freedom."""
    return stats.chi2.ppf(p / 2, dof) / dof, stats.chi2.ppf(1 - p / 2, dof) / dof


# ----------------------------------------------------------------------------- identity


def test_pseudorange_identity_and_phase_sign(eph):
    """P - rho - sum(errors) = 0; code-minus-carrier = 2I + code errors (MacGougan eq. 5.1)."""
    syn = synth(eph)
    eps = syn.run(steps({"a": (0, 0), "b": (30, 0)}, 50, 0.1, vel=(10.0, 5.0, 0.0)))
    worst_id = worst_cmc = 0.0
    for e in eps:
        assert e.n >= 4
        total = sum(e.errors_m[k] for k in ERROR_KEYS)
        # float64 rounding of ~2e7 m sums: a few ulp of 2e7 (3.7e-9 m each).
        worst_id = max(worst_id, np.max(np.abs(e.pseudorange_m - e.true_range_m - total)))
        # eq. 5.1: P - lambda (Phi - N) = 2I + eps_P - eps_Phi; eps_Phi = phase multipath + PLL
        # noise is mm-level: 0.01 * sigma_mp (<= 9 mm) + ~1 mm, so 3 cm is > 3 sigma of it.
        cmc = e.pseudorange_m - GPS_L1_WAVELENGTH_M * (e.carrier_cycles - e.ambiguity_cycles)
        d = cmc - 2 * e.errors_m["iono"] - e.errors_m["multipath"] - e.errors_m["noise"]
        worst_cmc = max(worst_cmc, np.max(np.abs(d)))
        for f in (e.pseudorange_m, e.doppler_mps, e.carrier_cycles, e.cn0_dbhz, e.sv_pos_ecef_m):
            assert np.all(np.isfinite(f))
    print(f"identity max {worst_id:.2e} m, |CMC - 2I - eps_P| max {worst_cmc * 1e3:.2f} mm")
    assert worst_id < 1e-7
    assert worst_cmc < 0.03


def test_doppler_is_range_rate_plus_clock_drift(eph):
    """Noise-free Doppler equals the central finite difference of rho + c dT - c dt_sv."""
    err = replace(GnssErrorConfig(), tracking=TrackingConfig(noise_enabled=False))
    syn = synth(eph, err, rate_hz=20.0)
    eps = [e for e in syn.run(steps({"a": (0, 0)}, 41, 0.05, vel=(15.0, -8.0, 0.3)))]
    mid, before, after = eps[20], eps[19], eps[21]
    common = np.intersect1d(np.intersect1d(before.prn, mid.prn), after.prn)

    def f(e):
        i = np.searchsorted(e.prn, common)
        return e.true_range_m[i] + e.errors_m["clock"][i] + e.errors_m["sv_clock"][i]

    fd = (f(after) - f(before)) / 0.1
    dop = mid.doppler_mps[np.searchsorted(mid.prn, common)]
    # Central difference error ~ d3(rho)/dt3 dt^2/6 plus clock noise over 0.1 s
    # (TCXO: sqrt(q_b 0.1) / 0.1 ~ 0.3 m/s): bound 1.5 m/s = 5 sigma of the clock term.
    print("Doppler - finite difference (m/s):", np.round(dop - fd, 4))
    assert np.all(np.abs(dop - fd) < 1.5)
    # The clock-free geometric part is exact to mm/s:
    syn2 = synth(eph, GnssErrorConfig.ideal(), rate_hz=20.0)
    eps2 = syn2.run(steps({"a": (0, 0)}, 41, 0.05, vel=(15.0, -8.0, 0.3)))
    fd2 = (eps2[21].true_range_m - eps2[19].true_range_m) / 0.1
    # Central-difference truncation d3(rho)/dt3 dt^2/6 is ~1e-5 m/s at most (d3(rho)/dt3 ~ 1e-3
    # m/s^3 with the car's motion), float rounding of the ~2e7 m ranges 4e-9 m / 0.1 s = 4e-8
    # m/s: bound 1e-4 m/s (measured < 1e-6 m/s). Before the synthesizer split the transmit time
    # exactly (absolute GPS seconds resolve 2.4e-7 s, ~1 mm of satellite motion) this was 3 mm/s.
    print("ideal Doppler - finite difference (mm/s):", np.round(1e3 * (eps2[20].doppler_mps - fd2), 6))
    assert np.max(np.abs(eps2[20].doppler_mps - fd2)) < 1e-4


def test_true_range_is_smooth_at_the_micrometre_level(eph):
    """The synthesized geometric range is a smooth function of time (no time-quantization steps).

    Third differences at 10 Hz equal ``d3(rho)/dt3 dt^3``: for a GPS orbit seen from a static
    antenna ``|d3(rho)/dt3| <~ (2 pi / 43082 s)^3 a ~ 1e-4 m/s^3``, i.e. ~1e-7 m, plus float
    rounding of ~2e7 m ranges (8 x 3.7e-9 m). Bound 1e-6 m; evaluating the ephemeris at the
    rounded absolute GPS time (2.4e-7 s steps at 1.3e9 s) gave 0.2 mm RMS, 0.6 mm worst.
    """
    syn = synth(eph, GnssErrorConfig.ideal())
    eps = syn.run(steps({"a": (0, 0)}, 100, 0.1))
    prns = eps[0].prn
    rho = np.array([[e.true_range_m[np.searchsorted(e.prn, p)] for p in prns] for e in eps])
    d3 = np.diff(rho, 3, axis=0)
    print(f"third differences of range: RMS {np.sqrt(np.mean(d3**2)):.2e} m, max {np.abs(d3).max():.2e} m")
    assert np.abs(d3).max() < 1e-6


# ----------------------------------------------------------------------------- (a) SD


def test_single_difference_cancels_common_errors(eph):
    """Two receivers 30 m apart: SD of iono+tropo+orbit+sat clock < 1 cm, undifferenced >= 1 m."""
    syn = synth(eph, seed=7)
    ep = syn.epoch(0.0, {"a": vstate("a", 0.0, 0.0), "b": vstate("b", 0.0, 30.0)})
    a, b = ep["a"], ep["b"]
    common, ia, ib = np.intersect1d(a.prn, b.prn, return_indices=True)
    assert common.size >= 5
    und = sum(a.errors_m[k][ia] for k in COMMON_KEYS)
    sd = und - sum(b.errors_m[k][ib] for k in COMMON_KEYS)
    per_key = {k: np.max(np.abs(a.errors_m[k][ia] - b.errors_m[k][ib])) for k in COMMON_KEYS}
    print("max |undifferenced common| (m):", np.round(np.abs(und), 3))
    print("max |SD| per component (m):", {k: f"{v:.2e}" for k, v in per_key.items()})
    assert np.all(np.abs(und) >= 1.0)  # the cancellation is real: iono+tropo alone are metres
    assert np.max(np.abs(sd)) < 0.01


def test_single_difference_multipath_and_noise_do_not_cancel(eph):
    """SD of multipath/noise between receivers: variance = sigma_a^2 + sigma_b^2 (independent).

    100 pairs 30 m apart (pairs 1 km apart), one epoch: every receiver-satellite
    multipath and noise state is a fresh stationary draw, so the normalized squares are
    independent and sum to chi-square(N). Two-sided 99.9 % bounds: false-failure 1e-3 each.
    """
    syn = synth(eph, seed=11)
    veh = {}
    for p in range(100):
        veh[f"p{p}a"] = vstate(f"p{p}a", 0.0, 1000.0 * (p % 10), 1000.0 * (p // 10))
        veh[f"p{p}b"] = vstate(f"p{p}b", 0.0, 1000.0 * (p % 10) + 30.0, 1000.0 * (p // 10))
    ep = syn.epoch(0.0, veh)
    tr = syn.config.errors.tracking
    mp_cfg = syn.config.errors.multipath
    s_mp, s_n = [], []
    raw_mp = []
    for p in range(100):
        a, b = ep[f"p{p}a"], ep[f"p{p}b"]
        _, ia, ib = np.intersect1d(a.prn, b.prn, return_indices=True)
        va = multipath_sigma_m(a.elevation_rad[ia], mp_cfg) ** 2 + multipath_sigma_m(b.elevation_rad[ib], mp_cfg) ** 2
        d = a.errors_m["multipath"][ia] - b.errors_m["multipath"][ib]
        s_mp.append(d**2 / va)
        raw_mp.append(np.column_stack([d, multipath_sigma_m(a.elevation_rad[ia], mp_cfg)]))
        vn = dll_jitter_m(a.cn0_dbhz[ia], tr) ** 2 + dll_jitter_m(b.cn0_dbhz[ib], tr) ** 2
        s_n.append((a.errors_m["noise"][ia] - b.errors_m["noise"][ib]) ** 2 / vn)
    s_mp, s_n = np.concatenate(s_mp), np.concatenate(s_n)
    lo, hi = chi2_var_bounds(s_mp.size)
    r = np.concatenate(raw_mp)
    print(f"N={s_mp.size}: SD multipath var/(sa^2+sb^2) = {s_mp.mean():.3f}, noise {s_n.mean():.3f},"
          f" bounds [{lo:.3f}, {hi:.3f}]; SD mp std / single sigma (RMS) = "
          f"{np.std(r[:, 0]) / np.sqrt(np.mean(r[:, 1] ** 2)):.3f} (sqrt 2 = 1.414)")
    assert lo < s_mp.mean() < hi
    assert lo < s_n.mean() < hi


# ----------------------------------------------------------------------------- (b) statistics


def _track_series(eps, key: str, norm) -> list[np.ndarray]:
    """Per (vehicle, prn) contiguous series of ``errors_m[key] / norm(epoch, idx)``."""
    series: dict[tuple[str, int], list[float]] = {}
    for e in eps:
        z = e.errors_m[key] / norm(e)
        for p, v in zip(e.prn, z, strict=True):
            series.setdefault((e.vehicle_id, int(p)), []).append(float(v))
    return [np.asarray(s) for s in series.values() if len(s) > 50]


def _ar1_checks(series: list[np.ndarray], phi: float, lag: int) -> tuple[float, float, float, float]:
    """Pooled variance and lag-``lag`` autocorrelation; 4-sigma half-widths from AR(1) theory.

    Variance of the sample variance of an AR(1): 2 s^4 (1 + phi^2) / (N (1 - phi^2)).
    Bartlett: var(rho_hat(L)) = [(1 + phi^2)(1 - phi^2L)/(1 - phi^2) - 2 L phi^2L] / N.
    4 sigma, normal approximation (N_eff in the thousands): false failure ~6e-5 each.
    """
    n = sum(s.size for s in series)
    var = sum(np.sum(s**2) for s in series) / n
    num = sum(np.sum(s[:-lag] * s[lag:]) for s in series)
    den = sum(np.sum(s[:-lag] ** 2) for s in series)
    rho = num / den
    sd_var = np.sqrt(2 * (1 + phi**2) / (n * (1 - phi**2)))
    sd_rho = np.sqrt(((1 + phi**2) * (1 - phi ** (2 * lag)) / (1 - phi**2) - 2 * lag * phi ** (2 * lag)) / n)
    return var, 4 * sd_var, rho, 4 * sd_rho


def test_dll_pll_jitter_worked_values():
    """Hand-computed DLL/PLL jitter at 45 dB-Hz (d=0.1 chip, B_L=0.5 Hz, T=20 ms, B_n=15 Hz).

    DLL: C/N0 = 31622.78 Hz; B_L d/(2 C/N0) = 7.9057e-7; 1 + 2/((2-d) T C/N0) = 1.0016644;
    sqrt(7.9189e-7) = 8.8988e-4 chip * 293.052 m = 0.26078 m.
    PLL: sqrt(15/31622.78 * (1 + 1/(2*0.02*31622.78))) = 0.021788 rad * 0.190294/(2 pi) = 0.65988 mm.
    """
    tr = TrackingConfig()
    assert dll_jitter_m(45.0, tr) == pytest.approx(0.26078, rel=1e-4)
    assert pll_jitter_m(45.0, tr) == pytest.approx(0.65988e-3, rel=1e-4)


def test_noise_std_and_correlation_match_dll_model(eph):
    """DLL noise: variance = sigma_DLL(C/N0)^2 and lag-5 (0.5 s = 1/(4 B_L)) autocorrelation e^-1."""
    syn = synth(eph, seed=3, rate_hz=10.0)
    pos = {f"v{i}": (100.0 * i, 0.0) for i in range(8)}
    eps = syn.run(steps(pos, 900, 0.1))  # 90 s at 10 Hz
    tr = syn.config.errors.tracking
    series = _track_series(eps, "noise", lambda e: dll_jitter_m(e.cn0_dbhz, tr))
    phi = np.exp(-0.1 / tr.dll_correlation_time_s)
    var, dvar, rho, drho = _ar1_checks(series, phi, lag=5)
    print(f"noise: var ratio {var:.4f} +- {dvar:.4f}; rho(0.5 s) {rho:.4f} vs e^-1 = {np.exp(-1):.4f} +- {drho:.4f};"
          f" samples {sum(s.size for s in series)}")
    assert abs(var - 1.0) < dvar
    assert abs(rho - np.exp(-1)) < drho


def test_multipath_std_and_correlation_match_gauss_markov(eph):
    """Multipath: variance = sigma(E)^2 and autocorrelation at lag tau = e^-1 (1 Hz, 30 min)."""
    mp = MultipathConfig()
    syn = synth(eph, seed=5, rate_hz=1.0)
    pos = {f"v{i}": (100.0 * i, 0.0) for i in range(6)}
    eps = syn.run(steps(pos, 1800, 1.0))
    series = _track_series(eps, "multipath", lambda e: multipath_sigma_m(e.elevation_rad, mp))
    phi = np.exp(-1.0 / mp.tau_s)
    var, dvar, rho, drho = _ar1_checks(series, phi, lag=int(mp.tau_s))
    print(f"multipath: var ratio {var:.4f} +- {dvar:.4f}; rho(tau) {rho:.4f} vs {np.exp(-1):.4f} +- {drho:.4f};"
          f" samples {sum(s.size for s in series)}")
    assert abs(var - 1.0) < dvar
    assert abs(rho - np.exp(-1)) < drho


def test_adding_a_vehicle_does_not_change_others(eph):
    a1 = synth(eph, seed=9).run(steps({"a": (0, 0), "b": (30, 0)}, 20, 0.1))
    a2 = synth(eph, seed=9).run(steps({"a": (0, 0), "zz": (50, 0), "b": (30, 0)}, 20, 0.1))
    b1 = [e for e in a1 if e.vehicle_id == "b"]
    b2 = [e for e in a2 if e.vehicle_id == "b"]
    for e1, e2 in zip(b1, b2, strict=True):
        np.testing.assert_array_equal(e1.pseudorange_m, e2.pseudorange_m)
        np.testing.assert_array_equal(e1.carrier_cycles, e2.carrier_cycles)


# ----------------------------------------------------------------------------- (c) clock


def test_clock_allan_variance_matches_h_coefficients():
    """Allan variance at tau = 1 s of the simulated clock vs h0/(2 tau) + (2 pi^2/3) h_-2 tau.

    The second difference x(t+2 tau) - 2 x(t+tau) + x(t) depends only on the noise inside
    [t, t + 2 tau], so disjoint windows are independent Gaussians with variance
    2 tau^2 sigma_y^2(tau): their mean square / (2 tau^2) is sigma_y^2 chi2(N)/N.
    Two-sided 99.9 % chi-square bounds: false failure 1e-3.
    """
    cfg = ClockConfig(oscillator=TCXO)
    clk = ReceiverClock.start(cfg, np.random.default_rng(2024), 0.0)
    dt, n_steps = 0.5, 40_000  # tau = 1 s = 2 steps; 20 000 s
    bias = np.empty(n_steps + 1)
    bias[0] = clk.bias_m
    for k in range(1, n_steps + 1):
        clk.advance_to(k * dt)
        bias[k] = clk.bias_m
    x = bias / SPEED_OF_LIGHT_MPS
    w = x[: n_steps - 3 : 4], x[2 : n_steps - 1 : 4], x[4 : n_steps + 1 : 4]  # windows of 2 s, disjoint
    d2 = w[2] - 2 * w[1] + w[0]
    avar = np.mean(d2**2) / (2 * 1.0**2)
    theory = float(allan_variance_theory(TCXO, 1.0))
    lo, hi = chi2_var_bounds(d2.size)
    print(f"Allan var tau=1 s: sim {avar:.4e}, theory {theory:.4e} (ratio {avar / theory:.4f},"
          f" bounds [{lo:.4f}, {hi:.4f}], N={d2.size})")
    assert lo < avar / theory < hi


def test_clock_millisecond_jumps():
    """With jumps enabled the bias stays within the threshold and every jump is whole ms."""
    cfg = ClockConfig(initial_drift_sigma=0.0, ms_jump_threshold_s=0.5e-3, initial_bias_max_s=0.0)
    clk = ReceiverClock.start(cfg, np.random.default_rng(1), 0.0)
    clk.state[1] = 2e-6 * SPEED_OF_LIGHT_MPS  # 2 ppm: 1 ms every 500 s
    for k in range(1, 2001):
        clk.advance_to(float(k))
        assert abs(clk.bias_m) <= 0.5e-3 * SPEED_OF_LIGHT_MPS
    ms = np.array([j.jump_m for j in clk.jumps]) / (1e-3 * SPEED_OF_LIGHT_MPS)
    print("jumps at", [j.t_s for j in clk.jumps], "ms", ms)
    assert len(clk.jumps) == 4  # 2000 s at 2 ppm = 4 ms, first jump at 250 s then every 500 s
    np.testing.assert_allclose(ms, np.round(ms), atol=1e-12)


# ----------------------------------------------------------------------------- atmosphere


def test_klobuchar_and_saastamoinen_reference_values():
    """Published/independent values.

    Klobuchar: at night (local time far from 14 h) the model is the 5 ns floor times the
    obliquity F = 1 + 16 (0.53 - E)^3: at zenith E = 0.5 sc -> F = 1.000432.
    Saastamoinen at sea level, 45 deg latitude, 15 C, RH 0: ZHD = 0.0022768 * 1013.25 /
    (1 - 0.00266 cos 90 deg) = 2.3070 m (the well-known ~2.3 m zenith hydrostatic delay).
    """
    t_night = 2 * 3600.0  # 02:00 at longitude 0
    d = klobuchar_delay_s(0.0, 0.0, np.pi / 2, 0.0, t_night, (1e-8, 0, 0, 0), (1e5, 0, 0, 0))
    assert d == pytest.approx(5e-9 * (1 + 16 * 0.03**3), rel=1e-12)
    zhd = saastamoinen_zenith_delay_m(np.pi / 4, 0.0, relative_humidity=0.0)
    assert zhd == pytest.approx(0.0022768 * 1013.25, rel=1e-9)


def test_klobuchar_daytime_and_obliquity_by_hand():
    """IS-GPS-200 20.3.3.5.2.5 worked by hand at chosen points.

    * User at (0, 0), zenith (E = 0.5 sc): psi = 0.0137 / 0.61 - 0.022 = 4.59e-4 sc, A = 0 so
      lambda_i = 0 and local time t = t_gps. At t = 50400 s (14:00) x = 0:
      T = F (5 ns + A0) with F = 1 + 16 (0.03)^3 = 1.000432; AMP = alpha_0 for
      alpha = (A0, 0, 0, 0) whatever phi_m.
    * Same point at 16:00 with PER = 72000 s: x = 2 pi 7200 / 72000 = pi / 5,
      T = F (5 ns + A0 (1 - x^2/2 + x^4/24)).
    * E = 10 deg (1/18 sc) at 02:00, A = 90 deg: lambda_i = psi = 0.0137 / (1/18 + 0.11) - 0.022
      = 0.06075 sc, t = 43200 * 0.06075 + 7200 = 9824 s, x = -3.54: the 5 ns night floor times
      F = 1 + 16 (0.53 - 1/18)^3 = 2.70874.
    """
    a0 = 2e-8
    alpha, beta = (a0, 0.0, 0.0, 0.0), (72000.0, 0.0, 0.0, 0.0)
    f_zen = 1.000432
    assert klobuchar_delay_s(0.0, 0.0, np.pi / 2, 0.0, 50400.0, alpha, beta) == pytest.approx(f_zen * (5e-9 + a0), rel=1e-12)
    x = np.pi / 5
    got = klobuchar_delay_s(0.0, 0.0, np.pi / 2, 0.0, 50400.0 + 7200.0, alpha, beta)
    assert got == pytest.approx(f_zen * (5e-9 + a0 * (1 - x**2 / 2 + x**4 / 24)), rel=1e-12)
    low = klobuchar_delay_s(0.0, 0.0, np.deg2rad(10.0), np.pi / 2, 7200.0, alpha, beta)
    assert low == pytest.approx(5e-9 * (1 + 16 * (0.53 - 1 / 18) ** 3), rel=1e-12)
    assert 1 + 16 * (0.53 - 1 / 18) ** 3 == pytest.approx(2.70874, abs=1e-5)


def test_tropo_mapping_limits():
    """RTCA DO-229 A.4.2.4 m(E) = 1.001 / sqrt(0.002001 + sin^2 E): exactly 1 at zenith
    (1.001^2 = 1.002001); at 5 deg
    1.001 / sqrt(0.002001 + 0.0075961) = 10.218 (bounded below 1/sin 5 deg = 11.474); within
    0.3 % of 1/sin E above 30 deg (the 0.002001 term is < 0.8 % of sin^2 E there, halved by the root)."""
    from v2v.sensors.gnss.atmosphere import tropo_mapping

    assert float(tropo_mapping(np.pi / 2)) == pytest.approx(1.0, abs=1e-15)
    assert float(tropo_mapping(np.deg2rad(5.0))) == pytest.approx(10.218, abs=1e-3)
    el = np.deg2rad(np.arange(30.0, 90.0, 5.0))
    assert np.all(np.abs(tropo_mapping(el) * np.sin(el) - 1.0) < 3e-3)


# ----------------------------------------------------------------------------- (d) SPP


def _clean_epoch(eph):
    err = replace(GnssErrorConfig.ideal(), clock=ClockConfig())  # keep a real receiver clock
    syn = synth(eph, err, seed=21)
    truth = vstate("a", 0.0, 0.0)
    return syn.epoch(0.0, {"a": truth})["a"], truth


def test_spp_noise_free_is_exact(eph):
    ep, truth = _clean_epoch(eph)
    r = solve_spp(ep.sv_pos_ecef_m, ep.pseudorange_m, ep.sv_clock_m)
    err = np.linalg.norm(r.position_ecef_m - truth.ecef_m)
    print(f"noise-free SPP: {ep.n} sats, error {err * 1e3:.4f} mm, clock error "
          f"{(r.clock_bias_m - ep.errors_m['clock'][0]) * 1e3:.4f} mm, PDOP {r.pdop:.2f}, iter {r.iterations}")
    assert r.status == SppStatus.OK and r.valid
    assert err < 1e-3
    assert abs(r.clock_bias_m - ep.errors_m["clock"][0]) < 1e-3


def test_spp_error_scales_with_pdop(eph):
    """Equal-weight LS with iid N(0, s^2) pseudoranges: e' (s^2 Q_pos)^-1 e ~ chi2(3) per fix.

    Sum over K fixes ~ chi2(3K); two-sided 99.9 % bounds (false failure 1e-3). Also
    E|e|^2 = s^2 PDOP^2 (reported).
    """
    ep, truth = _clean_epoch(eph)
    rng = np.random.default_rng(77)
    sigma, k_runs = 3.0, 400
    cfg = SppConfig(sigma0_m=sigma, elevation_weighting=False, exclude=False, alpha=1e-12)
    h = ep.sv_pos_ecef_m - truth.ecef_m
    h = np.column_stack([-h / np.linalg.norm(h, axis=1)[:, None], np.ones(ep.n)])
    q_pos = np.linalg.inv(h.T @ h)[:3, :3]
    stat, sq = 0.0, 0.0
    pdop = 0.0
    for _ in range(k_runs):
        r = solve_spp(ep.sv_pos_ecef_m, ep.pseudorange_m + sigma * rng.standard_normal(ep.n), ep.sv_clock_m,
                      config=cfg, x0_ecef_m=truth.ecef_m + 100.0)
        e = r.position_ecef_m - truth.ecef_m
        stat += e @ np.linalg.solve(sigma**2 * q_pos, e)
        sq += e @ e
        pdop = r.pdop
    lo, hi = stats.chi2.ppf(5e-4, 3 * k_runs), stats.chi2.ppf(1 - 5e-4, 3 * k_runs)
    rms = np.sqrt(sq / k_runs)
    print(f"SPP MC: chi2 {stat:.0f} in [{lo:.0f}, {hi:.0f}]; RMS 3D {rms:.3f} m vs sigma*PDOP "
          f"{sigma * pdop:.3f} m (ratio {rms / (sigma * pdop):.3f})")
    assert lo < stat < hi


def test_spp_too_few_satellites_and_exclusion(eph):
    ep, truth = _clean_epoch(eph)
    r = solve_spp(ep.sv_pos_ecef_m[:3], ep.pseudorange_m[:3], ep.sv_clock_m[:3])
    assert r.status == SppStatus.TOO_FEW_SATELLITES and not r.valid
    assert np.all(np.isfinite(r.position_ecef_m)) and np.isfinite(r.clock_bias_m)
    r0 = solve_spp(np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    assert r0.status == SppStatus.TOO_FEW_SATELLITES
    # A 200 m blunder on one of >= 6 satellites with 1 m noise is found and excluded.
    assert ep.n >= 6
    rng = np.random.default_rng(5)
    pr = ep.pseudorange_m + rng.standard_normal(ep.n)
    pr[2] += 200.0
    r = solve_spp(ep.sv_pos_ecef_m, pr, ep.sv_clock_m, config=SppConfig(sigma0_m=1.0, elevation_weighting=False))
    print("exclusion:", r.status, r.reason, "error", np.linalg.norm(r.position_ecef_m - truth.ecef_m))
    assert r.status == SppStatus.OK_EXCLUDED and not r.used[2]
    assert np.linalg.norm(r.position_ecef_m - truth.ecef_m) < 20.0  # ~1 m * PDOP, far below 200 m


# ----------------------------------------------------------------------------- (e) NLOS


def _street_world() -> World:
    """A 12 m building 10 m south of the antenna (blocks the southern sky below ~45 deg)
    and a 60 m building whose south wall is 15 m north of it (the reflector)."""
    south = Building(id="south", footprint_xy_m=np.array([[-300, -40], [300, -40], [300, -10], [-300, -10.0]]),
                     height_m=12.0, height_source="height")
    north = Building(id="north", footprint_xy_m=np.array([[-300, 15], [300, 15], [300, 45], [-300, 45.0]]),
                     height_m=60.0, height_source="height")
    return World(buildings=(south, north))


def test_nlos_echo_errors_equal_excess_path(eph):
    """Echo-only signals: nlos error = 2 d_w cos(E) cos(A - A_n) > 0 (image method, wall at
    d_w = 15 m facing south, A_n = 180 deg), C/N0 lowered by the echo loss; LOS signals 0."""
    from v2v.world.occlusion import OcclusionGeometry

    occ = OcclusionGeometry(_street_world())
    syn = synth(eph, seed=4, occlusion=occ, georef=GEO)
    ep = None
    for t in np.arange(0.0, 4 * 3600.0, 600.0):  # find an epoch with an echo-only satellite
        e = syn.epoch(float(t), {"a": vstate("a", float(t), 0.0)})["a"]
        if np.any(~e.los):
            ep = e
            break
    assert ep is not None, "no echo-only satellite in 4 h"
    nl = ~ep.los
    expected = 2 * 15.0 * np.cos(ep.elevation_rad[nl]) * np.cos(ep.azimuth_rad[nl] - np.pi)
    print("NLOS prn", ep.prn[nl], "el", np.round(np.degrees(ep.elevation_rad[nl]), 1), "nlos m",
          np.round(ep.errors_m["nlos"][nl], 4), "expected", np.round(expected, 4))
    # grid convergence is 0 at the tangent origin; 1e-6 m covers float rounding of the image method
    np.testing.assert_allclose(ep.errors_m["nlos"][nl], expected, atol=1e-6)
    assert np.all(ep.errors_m["nlos"][nl] > 0)
    assert np.all(ep.errors_m["nlos"][~nl] == 0)
    tr = TrackingConfig()
    base = tr.cn0_zenith_dbhz - (tr.cn0_zenith_dbhz - tr.cn0_horizon_dbhz) * (1 - np.sin(ep.elevation_rad))
    np.testing.assert_allclose(ep.cn0_dbhz[nl], base[nl] - tr.echo_loss_db, atol=1e-9)


def test_echo_doppler_follows_the_reflected_path(eph):
    """An echo-only signal's Doppler is the rate of its whole path, reflection included: for
    the wall echo ``2 d_w cos(E) cos(A - A_n)`` of the street world (d_w = 15 m - y, facing
    south) and an antenna driving north at v_N, the echo adds ``-2 v_N cos(E) cos(A - pi)``
    (up to 2 v_N) to the range rate. So Doppler = carrier-phase rate for every signal, LOS
    or echo, as in a receiver. Error-free receiver with echoes on. Tolerance 0.01 m/s: the
    echo's change with the satellite's motion, left out (2 d_w |ds/dt| <= 2 x 15 m x
    2.2e-4 rad/s = 6.6e-3 m/s; the central difference itself is exact to ~1e-5 m/s)."""
    from v2v.world.occlusion import OcclusionGeometry

    occ = OcclusionGeometry(_street_world())
    err = replace(GnssErrorConfig.ideal(), tracking=TrackingConfig(noise_enabled=False, foliage_enabled=False))
    t_c = None
    for t in np.arange(0.0, 4 * 3600.0, 600.0):  # an epoch with echo-only satellites
        if np.any(~synth(eph, err, occlusion=occ, georef=GEO).epoch(float(t), {"a": vstate("a", float(t), 0.0)})["a"].los):
            t_c = float(t)
            break
    assert t_c is not None, "no echo-only satellite in 4 h"
    v_n = 12.0
    syn = synth(eph, err, occlusion=occ, georef=GEO)
    # at y = v_n (t - t_c): 1.2 m south of the centre point, at it, 1.2 m north of it
    before, mid, after = (syn.epoch(t, {"a": vstate("a", t, 0.0, -v_n * t_c, vel_enu=(0.0, v_n, 0.0))})["a"]
                          for t in (t_c - 0.1, t_c, t_c + 0.1))
    common = np.intersect1d(np.intersect1d(before.prn, mid.prn), after.prn)
    i_b, i_m, i_a = (np.searchsorted(e.prn, common) for e in (before, mid, after))
    nl = ~mid.los[i_m]
    assert nl.any() and np.array_equal(before.los[i_b], mid.los[i_m]) and np.array_equal(after.los[i_a], mid.los[i_m])
    phase_rate = GPS_L1_WAVELENGTH_M * (after.carrier_cycles[i_a] - before.carrier_cycles[i_b]) / 0.2
    range_rate = (after.true_range_m[i_a] - before.true_range_m[i_b]) / 0.2
    dop = mid.doppler_mps[i_m]
    el, az = mid.elevation_rad[i_m], mid.azimuth_rad[i_m]
    echo_rate = np.where(nl, -2.0 * v_n * np.cos(el) * np.cos(az - np.pi), 0.0)
    print("prn", common, "echo", nl, "Doppler - phase rate (m/s)", np.round(dop - phase_rate, 4),
          "echo rate expected", np.round(echo_rate, 3), "measured", np.round(dop - range_rate, 3))
    assert np.all(np.abs(dop - phase_rate) < 0.01)
    assert np.all(np.abs(dop - range_rate - echo_rate) < 0.01)
    assert np.all(np.abs(echo_rate[nl]) > 1.0)  # the term is metres per second, not a rounding


def test_echo_doppler_off_the_central_meridian(eph):
    """The echo's path rate is computed from the antenna's velocity turned into net XY by the
    grid convergence (true azimuth = grid azimuth + gamma). Off the projection's central
    meridian (transverse Mercator 2 deg east of the site: gamma = -1.55 deg) the truth is
    built consistently (net XY track -> ECEF by the projection, ENU velocity from the ECEF
    track), and Doppler must still equal the carrier-phase rate for echoes. Tolerance: the
    6.6e-3 m/s of the satellite's motion (test above) plus the projection's scale error of
    net-XY geometry, (k - 1) |echo rate| (k measured here, 2.4e-4 expected); a turn of the
    wrong sign would be off by 2 |gamma| |echo rate| (~0.7 m/s at 13 m/s)."""
    from v2v.world.occlusion import OcclusionGeometry

    geo = GeoReference(proj="+proj=tmerc +lat_0=51.08 +lon_0=-112.13 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m",
                       net_offset_m=(0.0, 0.0))
    x0, y0 = (float(v) for v in geo.geodetic_to_xy(np.radians(51.08), np.radians(-114.13)))
    gamma = geo.grid_convergence_rad(x0, y0)
    assert np.degrees(gamma) == pytest.approx(-1.55, abs=0.02)
    k_scale = np.linalg.norm(geo.xyz_to_ecef(x0 + 1.0, y0, 1.5) - geo.xyz_to_ecef(x0, y0, 1.5))
    k_scale = 1.0 / k_scale  # net-XY metres per true metre
    world = World(buildings=tuple(
        Building(id=b.id, footprint_xy_m=b.footprint_xy_m + [x0, y0], height_m=b.height_m, height_source="height")
        for b in _street_world().buildings))
    occ = OcclusionGeometry(world)
    err = replace(GnssErrorConfig.ideal(), tracking=TrackingConfig(noise_enabled=False, foliage_enabled=False))
    v_n = 12.0  # grid north, toward the reflecting wall

    def state(t: float, t_c: float) -> VehicleState:
        xy = np.array([x0, y0 + v_n * (t - t_c)])
        ecef = geo.xyz_to_ecef(xy[0], xy[1], ANTENNA_Z_M)
        v_ecef = (geo.xyz_to_ecef(xy[0], xy[1] + v_n * 1e-3, ANTENNA_Z_M)
                  - geo.xyz_to_ecef(xy[0], xy[1] - v_n * 1e-3, ANTENNA_Z_M)) / 2e-3
        lat, lon, h = ecef_to_geodetic(ecef)
        v = ecef_to_enu_rotation(float(lat), float(lon)) @ v_ecef
        return VehicleState(vehicle_id="a", cluster="c0", is_lead=False, t_s=t, xyz_m=np.array([*xy, ANTENNA_Z_M]),
                            lat_rad=float(lat), lon_rad=float(lon), h_m=float(h), ecef_m=ecef, vel_enu_mps=v,
                            speed_mps=float(np.hypot(v[0], v[1])), accel_mps2=0.0, azimuth_rad=0.0, grid_azimuth_rad=0.0, yaw_rate_rps=0.0,
                            front_bumper_xy_m=xy, edge_id="e", lane_id="e_0", lane_index=0, lane_width_m=3.5,
                            lateral_offset_m=0.0, length_m=4.5, width_m=1.8, height_m=1.5)

    checked = 0
    for t_c in np.arange(600.0, 4 * 3600.0, 600.0):
        syn = synth(eph, err, occlusion=occ, georef=geo)
        before, mid, after = (syn.epoch(t, {"a": state(t, t_c)})["a"] for t in (t_c - 0.1, t_c, t_c + 0.1))
        common = np.intersect1d(np.intersect1d(before.prn, mid.prn), after.prn)
        i_b, i_m, i_a = (np.searchsorted(e.prn, common) for e in (before, mid, after))
        nl = ~mid.los[i_m] & ~before.los[i_b] & ~after.los[i_a]
        same = (before.ambiguity_cycles[i_b] == after.ambiguity_cycles[i_a]) & (after.lock_time_s[i_a] > 0.15)
        phase_rate = GPS_L1_WAVELENGTH_M * (after.carrier_cycles[i_a] - before.carrier_cycles[i_b]) / 0.2
        echo_rate = mid.doppler_mps[i_m] - (after.true_range_m[i_a] - before.true_range_m[i_b]) / 0.2
        sel = nl & same & (np.abs(echo_rate) > 1.0)
        tol = 6.6e-3 + abs(k_scale - 1.0) * np.abs(echo_rate[sel])
        assert np.all(np.abs(mid.doppler_mps[i_m][sel] - phase_rate[sel]) < tol), (t_c, mid.doppler_mps[i_m][sel] - phase_rate[sel])
        checked += int(sel.sum())
    print(f"gamma {np.degrees(gamma):.3f} deg, k - 1 = {k_scale - 1:.2e}, echo Dopplers checked: {checked}")
    assert checked >= 3


@pytest.mark.parametrize("far_y_m", [25.0, 15.0])
def test_carrier_arcs_are_continuous_through_echo_changes(eph, far_y_m):
    """A tracked carrier arc (one integer ambiguity) must be continuous: its phase advances by
    the integral of the Doppler, ``lambda dPhi = (D1 + D2) dt / 2`` to within a phase-lock
    loop's pull-in (lambda / 4, 4.8 cm). The car drives 60 m east past two north-side blocks
    that meet at x = 0 (the southern sky blocked).

    * Blocks 15 m and 25 m from the road: an echo-only satellite's reflection moves from one
      wall to the other and its path jumps by metres; that must start a new arc (a receiver
      loses lock), as a LOS <-> echo switch does.
    * Both 15 m from the road (one facade in two buildings): the path is continuous and no
      arc may restart between two echoes.

    Error-free receiver with echoes; the trapezoid's own error is ~1e-4 m at 10 Hz."""
    from v2v.world.occlusion import OcclusionGeometry

    blocks = (Building(id="south", footprint_xy_m=np.array([[-300, -40], [300, -40], [300, -10], [-300, -10.0]]),
                       height_m=12.0, height_source="height"),
              Building(id="near", footprint_xy_m=np.array([[-300, 15], [0, 15], [0, 45], [-300, 45.0]]),
                       height_m=60.0, height_source="height"),
              Building(id="far", footprint_xy_m=np.array([[0, far_y_m], [300, far_y_m], [300, 55], [0, 55.0]]),
                       height_m=60.0, height_source="height"))
    occ = OcclusionGeometry(World(buildings=blocks))
    err = replace(GnssErrorConfig.ideal(), tracking=TrackingConfig(noise_enabled=False, foliage_enabled=False))
    v_e, n_ep = 10.0, 61
    n_switch = n_echo_pairs = 0
    for t0 in np.arange(0.0, 4 * 3600.0, 900.0):
        syn = synth(eph, err, occlusion=occ, georef=GEO)
        eps = [syn.epoch(t, {"a": vstate("a", t, -30.0 - v_e * t0, 0.0, vel_enu=(v_e, 0.0, 0.0))})["a"]
               for t in t0 + 0.1 * np.arange(n_ep)]
        for p in sorted(set(np.concatenate([e.prn for e in eps]).tolist())):
            for e1, e2 in zip(eps[:-1], eps[1:], strict=True):
                if p not in e1.prn or p not in e2.prn:
                    continue
                i1, i2 = int(np.flatnonzero(e1.prn == p)[0]), int(np.flatnonzero(e2.prn == p)[0])
                both_echoes = not e1.los[i1] and not e2.los[i2]
                n_echo_pairs += both_echoes
                if e1.ambiguity_cycles[i1] != e2.ambiguity_cycles[i2] or e2.lock_time_s[i2] < 0.05:
                    n_switch += both_echoes  # a new arc between two echoes
                    continue
                jump = GPS_L1_WAVELENGTH_M * (e2.carrier_cycles[i2] - e1.carrier_cycles[i1]) \
                    - 0.5 * (e1.doppler_mps[i1] + e2.doppler_mps[i2]) * (e2.t_s - e1.t_s)
                assert abs(jump) < GPS_L1_WAVELENGTH_M / 4, (t0, p, e2.t_s, jump)
    print(f"far facade at {far_y_m} m: {n_echo_pairs} echo-echo epoch pairs, {n_switch} new arcs between them")
    assert n_echo_pairs > 100
    assert (n_switch > 0) if far_y_m != 15.0 else (n_switch == 0)


def test_no_gnss_epoch_is_clean(eph):
    """Everything blocked without echoes: an n = 0 epoch, no NaN, no exception."""

    class Dome:
        def sky(self, antenna_xyz_m, azimuth_grid_rad, elevation_rad):
            n = np.asarray(elevation_rad).size
            from v2v.world.occlusion import SkyResult

            return SkyResult(blocked=np.ones(n, bool), blocker_id=np.full(n, "dome"), foliage_path_m=np.zeros(n),
                             foliage_loss_db=np.zeros(n), echo_excess_m=np.full(n, np.nan))

    syn = synth(eph, occlusion=Dome(), georef=GEO)
    e = syn.epoch(0.0, {"a": vstate("a", 0.0, 0.0)})["a"]
    assert e.n == 0 and e.pseudorange_m.shape == (0,) and e.sv_pos_ecef_m.shape == (0, 3)
    assert all(v.shape == (0,) for v in e.errors_m.values())
    r = solve_spp(e.sv_pos_ecef_m, e.pseudorange_m, e.sv_clock_m)
    assert r.status == SppStatus.TOO_FEW_SATELLITES


def test_cycle_slip_after_outage(eph):
    """A satellite lost for > 1 epoch comes back with a new ambiguity and lock_time 0."""
    syn = synth(eph, seed=8)
    veh = {"a": vstate("a", 0.0, 0.0)}
    e0 = syn.epoch(0.0, veh)["a"]
    e1 = syn.epoch(0.1, {"a": vstate("a", 0.1, 0.0)})["a"]
    np.testing.assert_array_equal(e0.ambiguity_cycles, e1.ambiguity_cycles)
    assert np.allclose(e1.lock_time_s, 0.1)
    e2 = syn.epoch(5.0, {"a": vstate("a", 5.0, 0.0)})["a"]  # 4.9 s outage (vehicle absent)
    assert np.all(e2.lock_time_s == 0.0)
    # new uniform integers in +-1e6: P(equal) = 1/(2e6+1) per satellite
    assert np.all(e2.ambiguity_cycles != e0.ambiguity_cycles)


def test_real_broadcast_clocks_noise_free_spp(shared_gnss_day):
    """With a real RINEX ephemeris (non-zero satellite clocks up to ~1 ms = 300 km), adding
    ``sv_clock_m`` back gives an exact noise-free fix: checks the satellite-clock sign."""
    from v2v.sensors.gnss.rinex import read_rinex_nav

    eph = read_rinex_nav(shared_gnss_day / "brdc1180.21n")
    err = replace(GnssErrorConfig.ideal(), clock=ClockConfig())
    syn = synth(eph, err, seed=13)
    truth = vstate("a", 0.0, 0.0)
    ep = syn.epoch(0.0, {"a": truth})["a"]
    r = solve_spp(ep.sv_pos_ecef_m, ep.pseudorange_m, ep.sv_clock_m)
    err_m = np.linalg.norm(r.position_ecef_m - truth.ecef_m)
    print(f"RINEX: {ep.n} sats, max |sv_clock| {np.max(np.abs(ep.sv_clock_m)) / 1e3:.1f} km, "
          f"SPP error {err_m * 1e3:.4f} mm, PDOP {r.pdop:.2f}")
    assert ep.n >= 6 and np.max(np.abs(ep.sv_clock_m)) > 1e3
    assert r.status == SppStatus.OK and err_m < 1e-3


class _FakeSky:
    """Deterministic sky for the batching test: rays with azimuth in (1, 2) rad are blocked,
    those above 0.5 rad of elevation among them arrive as 5 m echoes, some foliage loss."""

    def _one(self, az, el):
        from types import SimpleNamespace

        az, el = np.asarray(az, float), np.asarray(el, float)
        b = (az % (2 * np.pi) > 1.0) & (az % (2 * np.pi) < 2.0)
        return SimpleNamespace(blocked=b, echo_excess_m=np.where(b & (el > 0.5), 5.0 + el, np.nan),
                               foliage_loss_db=np.where(az > 4.0, 3.0 * el, 0.0))

    def sky(self, xyz, az, el):
        return self._one(az, el)


class _FakeSkyMany(_FakeSky):
    def sky_many(self, xyz, ai, az, el):
        return self._one(az, el)


@pytest.mark.parametrize("dt_s,sky", [(0.1, None), (0.25, _FakeSky()), (0.1, _FakeSkyMany())],
                         ids=["open-0.1s", "per-antenna-sky-0.25s", "sky_many-0.1s"])
def test_batched_synthesis_equals_step_by_step(dt_s, sky):
    """A streamed run synthesizes a whole chunk of traffic steps in one batch
    (GnssSynthesizer.feed_many); step by step (feed) must give the same epochs, field for
    field and bit for bit: every receiver draws its random numbers in the same order and
    the batch only changes how the same per-epoch arithmetic is grouped. Exercised with
    vehicles leaving, joining and a step without vehicles, random cycle slips and
    millisecond clock jumps (ClockConfig.ms_jump_threshold_s below the initial bias)."""
    err = replace(GnssErrorConfig(), tracking=replace(TrackingConfig(), random_slip_rate_hz=0.5),
                  clock=ClockConfig(ms_jump_threshold_s=0.5e-3, initial_bias_max_s=3e-3))
    steps = []
    for k in range(int(12 / dt_s)):
        t = round(k * dt_s, 9)
        veh = {"a": (0.0, 0.0), "b": (30.0, 3.5), "c": (60.0, 0.0)}
        if 3.0 <= t < 5.0:
            veh.pop("b")
        if t >= 6.0:
            veh["d"] = (90.0, 0.0)
        if 8.0 <= t < 8.5:
            veh = {}
        steps.append(TrafficStep(t_s=t, vehicles={v: vstate(v, t, *xy, vel_enu=(10.0, 0.0, 0.0))
                                                  for v, xy in veh.items()}))

    def run(batched: bool):
        cfg = GnssReceiverConfig(rate_hz=10.0, errors=err, elevation_mask_rad=np.deg2rad(10.0))
        kw = {"occlusion": sky, "georef": GEO} if sky is not None else {}
        syn = GnssSynthesizer(NominalConstellation(GPS0), cfg, np.random.SeedSequence(5), GPS0, **kw)
        eps = (syn.feed_many(steps[:37]) + syn.feed_many(steps[37:])) if batched else [e for st in steps
                                                                                      for e in syn.feed(st)]
        return eps, {v: [(j.t_s, j.jump_m) for j in r.clock.jumps] for v, r in syn.receivers.items()}

    (a, jumps_a), (b, jumps_b) = run(False), run(True)
    assert len(a) == len(b) > 0 and jumps_a == jumps_b and sum(map(len, jumps_a.values())) > 0
    n = 0
    for ea, eb in zip(a, b, strict=True):
        assert list(ea) == list(eb)
        for v in ea:
            x, y = vars(ea[v]), vars(eb[v])
            assert list(x) == list(y)
            for key in x:
                if key == "errors_m":
                    assert list(x[key]) == list(y[key])
                    assert all(np.array_equal(x[key][q], y[key][q], equal_nan=True) for q in x[key])
                elif isinstance(x[key], np.ndarray):
                    assert x[key].dtype == y[key].dtype and np.array_equal(x[key], y[key], equal_nan=x[key].dtype.kind == "f"), key
                else:
                    assert x[key] == y[key], key
            n += 1
    assert n > 100


def test_spp_chain_batch_equals_epoch_by_epoch(eph):
    """The lead's base (paper eq. 7) is solved for a whole delivery of epochs at once
    (SppChain.many, one compiled call); each epoch must get what one call per epoch gives
    (spp_position from the last valid position), bit for bit, also across epochs with too few
    satellites (no solution: the last valid position is kept, None before the first). Without
    errors beyond the receiver clock (and no corrections) each valid position is the truth, as in
    test_spp_noise_free_is_exact."""
    syn = synth(eph, replace(GnssErrorConfig.ideal(), clock=ClockConfig()), seed=3)
    cfg = SppConfig(correct_iono=False, correct_tropo=False)
    eps, truth = [], []
    for k in range(40):
        st = vstate("a", 0.1 * k, 0.0, vel_enu=(20.0, 5.0, 0.0))
        ep = syn.epoch(0.1 * k, {"a": st})["a"]
        if k in (0, 1, 17, 18, 30):  # too few satellites: 3 rows
            ep = ep.select(np.arange(ep.n) < 3)
        eps.append(ep)
        truth.append(st.ecef_m)
    one = SppChain(gps_start_s=GPS0, config=cfg)
    a = [one(ep) for ep in eps]
    a = [None if x is None else x.copy() for x in a]
    for split in (len(eps), 11):  # one delivery; two, the second starting from the first's last position
        chain = SppChain(gps_start_s=GPS0, config=cfg)
        b = chain.many(eps[:split]) + chain.many(eps[split:])
        assert a[:2] == [None, None] and b[:2] == [None, None]
        for k in range(2, len(eps)):
            assert b[k] is not None and np.array_equal(a[k], b[k]), k
        assert np.array_equal(chain.x, a[-1])
    for k in (17, 18):
        assert np.array_equal(a[k], a[16])  # no solution: the last valid position
    errs = [np.linalg.norm(a[k] - truth[k]) for k in range(2, len(eps)) if k not in (17, 18, 30)]
    print(f"SPP chain: 3-D error max {max(errs) * 1e3:.4f} mm over {len(errs)} epochs")
    assert max(errs) < 1e-3
