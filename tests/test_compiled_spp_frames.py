"""The compiled standalone-position solver and the scalar frame helpers, against the array forms.

The compiled pieces repeat formulas of array functions (frames, atmosphere): these tests check
that the two agree to float rounding, and that the solver's cheap singular-geometry test takes
the same decision as ``np.linalg.cond(N) > 1e12``, also in the band where only the exact
condition number can decide. Seeded; no SUMO.
"""

from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest

from v2v.frames import (
    ecef_to_enu_rotation,
    ecef_to_geodetic,
    ecef_to_geodetic_point,
    geodetic_to_ecef,
    wrap_angle,
    wrap_angle_scalar,
)
from v2v.sensors.gnss.atmosphere import klobuchar_delay_s, saastamoinen_zenith_delay_m, tropo_mapping
from v2v.sensors.gnss.spp import SppConfig, SppStatus, solve_spp, spp_from_epoch, spp_position
from v2v.sensors.measurements import SPEED_OF_LIGHT_MPS
from v2v.smallmat import cond2_symmetric, solve_small

RNG = np.random.default_rng(20260)


def test_ecef_to_geodetic_point_matches_array_form():
    lat = RNG.uniform(-np.pi / 2, np.pi / 2, 500)
    lon = RNG.uniform(-np.pi, np.pi, 500)
    h = RNG.uniform(-500.0, 2.5e7, 500)  # ground to GNSS orbit
    ecef = geodetic_to_ecef(lat, lon, h)
    ref = ecef_to_geodetic(ecef)
    got = np.array([ecef_to_geodetic_point(*p) for p in ecef.tolist()])
    # the same Bowring iterations: only last-bit differences of atan2/hypot/pow remain
    assert np.max(np.abs(got[:, 0] - ref[0])) < 1e-14
    assert np.max(np.abs(got[:, 1] - ref[1])) < 1e-14
    assert np.max(np.abs(got[:, 2] - ref[2])) < 1e-7  # metres; ulp of 2.6e7 m is 4e-9


def test_wrap_angle_scalar_is_wrap_angle_bit_for_bit():
    a = np.concatenate([RNG.uniform(-20.0, 20.0, 20000), [math.pi, -math.pi, 0.0, -0.0, 3 * math.pi, -3 * math.pi]])
    got = np.array([wrap_angle_scalar(float(x)) for x in a])
    assert np.array_equal(got, wrap_angle(a))
    assert wrap_angle_scalar(-math.pi) == math.pi  # (-pi, pi]


@pytest.mark.parametrize("log_cond", [0.0, 2.0, 8.0, 11.0, 11.99, 12.01, 14.0])
def test_condition_number_and_solve_match_lapack(log_cond):
    """SPD 4x4 matrices with a prescribed condition number (eigenvalues 1 .. 10^log_cond): the
    Jacobi condition number agrees with numpy's SVD one to ~cond * eps (relative), so the
    singular-geometry decision (cond > 1e12) is the same outside a band of that width; the
    LU solve agrees with LAPACK's to the same order."""
    q, _ = np.linalg.qr(RNG.standard_normal((4, 4)))
    eig = np.array([1.0, 10 ** (log_cond / 3), 10 ** (2 * log_cond / 3), 10**log_cond]) * 0.01
    n = q @ np.diag(eig) @ q.T
    n = 0.5 * (n + n.T)
    ref = np.linalg.cond(n)
    assert cond2_symmetric(n) == pytest.approx(ref, rel=1e-15 * ref + 1e-13)
    assert (cond2_symmetric(n) > 1e12) == (ref > 1e12)
    b = RNG.standard_normal((4, 2))
    x = solve_small(n, b)
    assert np.max(np.abs(x - np.linalg.solve(n, b))) <= 1e-14 * ref * np.max(np.abs(x))


def _sky(x_ecef: np.ndarray, n: int = 8) -> np.ndarray:
    """Satellites 20,200 km up, spread in azimuth, elevations 15-80 deg, seen from ``x_ecef``."""
    lat, lon, _ = ecef_to_geodetic(x_ecef)
    rot = ecef_to_enu_rotation(float(lat), float(lon))
    az = np.linspace(0.0, 2 * np.pi, n, endpoint=False) + 0.3
    el = np.radians(np.linspace(15.0, 80.0, n))
    u = np.column_stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)])
    r = 6378137.0
    # range to a 26,560 km orbit radius along each line of sight
    s = -r * u[:, 2] + np.sqrt((r * u[:, 2]) ** 2 + 26_560_000.0**2 - r**2)
    return x_ecef + (s[:, None] * u) @ rot


def test_spp_atmosphere_corrections_match_the_array_models():
    """Pseudoranges carrying the broadcast Klobuchar and Saastamoinen delays at the true position
    (array forms) are solved exactly by the compiled solver with both corrections on."""
    truth = geodetic_to_ecef(np.radians(51.08), np.radians(-114.13), 1100.0)
    sv = _sky(truth)
    lat, lon, h = ecef_to_geodetic(truth)
    enu = (sv - truth) @ ecef_to_enu_rotation(float(lat), float(lon)).T
    el = np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))
    az = np.arctan2(enu[:, 0], enu[:, 1])
    cfg = SppConfig(correct_iono=True, correct_tropo=True)
    t_gps = 1.3e9 + 70_000.0  # local afternoon in Calgary: a large ionosphere
    iono = SPEED_OF_LIGHT_MPS * klobuchar_delay_s(lat, lon, el, az, t_gps, cfg.klobuchar_alpha, cfg.klobuchar_beta)
    tropo = tropo_mapping(el) * saastamoinen_zenith_delay_m(lat, h)
    clock_m = 1234.5
    pr = np.linalg.norm(sv - truth, axis=1) + clock_m + iono + tropo
    r = solve_spp(sv, pr, np.zeros(len(pr)), config=cfg, t_gps_s=t_gps)
    assert r.status == SppStatus.OK
    assert np.linalg.norm(r.position_ecef_m - truth) < 1e-6
    assert abs(r.clock_bias_m - clock_m) < 1e-6
    uncorrected = solve_spp(sv, pr, np.zeros(len(pr)), t_gps_s=t_gps)
    assert np.linalg.norm(uncorrected.position_ecef_m - truth) > 1.0  # the delays matter


def test_spp_singular_geometry_and_dops():
    truth = geodetic_to_ecef(np.radians(51.08), np.radians(-114.13), 1100.0)
    sv = _sky(truth)
    pr = np.linalg.norm(sv - truth, axis=1)
    r = solve_spp(sv, pr, np.zeros(len(pr)))
    assert r.status == SppStatus.OK and r.n_used == len(pr) and r.chi2 < 1e-9
    assert r.gdop**2 == pytest.approx(r.pdop**2 + r.tdop**2) and r.pdop**2 == pytest.approx(r.hdop**2 + r.vdop**2)
    # four satellites in one direction (1 mm apart): no position fix
    one = np.repeat(sv[:1], 4, axis=0) + RNG.standard_normal((4, 3)) * 1e-3
    r = solve_spp(one, np.linalg.norm(one - truth, axis=1), np.zeros(4), x0_ecef_m=truth + 10.0)
    assert r.status == SppStatus.SINGULAR_GEOMETRY and not r.valid
    assert np.array_equal(r.position_ecef_m, truth + 10.0)  # the a priori position, no NaN


def test_spp_position_is_the_valid_solutions_position_else_none():
    """The lead's base (:func:`spp_position`) is :func:`spp_from_epoch`'s position exactly when
    that solution is valid: a noiseless fix (the truth), a blunder the residual test flags but
    cannot exclude (``exclude=False``: invalid), and a singular geometry (invalid)."""
    truth = geodetic_to_ecef(np.radians(51.08), np.radians(-114.13), 1100.0)
    sv = _sky(truth)

    def epoch(sv_pos, pr):
        return SimpleNamespace(sv_pos_ecef_m=sv_pos, pseudorange_m=pr, sv_clock_m=np.zeros(len(pr)), t_s=12.3)

    ok = epoch(sv, np.linalg.norm(sv - truth, axis=1) + 50.0)
    r = spp_from_epoch(ok, gps_start_s=1.3e9)
    x = spp_position(ok, gps_start_s=1.3e9)
    assert r.valid and x is not None and np.array_equal(x, r.position_ecef_m)
    assert np.linalg.norm(x - truth) < 1e-6
    blunder = np.linalg.norm(sv - truth, axis=1)
    blunder[2] += 300.0  # 300 m against sigma0 = 5 m: far beyond the chi-square threshold
    cfg = SppConfig(exclude=False)
    r = spp_from_epoch(epoch(sv, blunder), config=cfg, x0_ecef_m=truth)
    assert r.status == SppStatus.RESIDUAL_TEST_FAILED and not r.valid
    assert spp_position(epoch(sv, blunder), config=cfg, x0_ecef_m=truth) is None
    one = np.repeat(sv[:1], 4, axis=0) + RNG.standard_normal((4, 3)) * 1e-3
    single = epoch(one, np.linalg.norm(one - truth, axis=1))
    assert spp_from_epoch(single, x0_ecef_m=truth).status == SppStatus.SINGULAR_GEOMETRY
    assert spp_position(single, x0_ecef_m=truth) is None
