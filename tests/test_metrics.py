"""Metrics: lead-frame errors and sigmas, statistics, chi-square bands."""

from __future__ import annotations

import numpy as np
import pytest

from v2v.metrics.errors import chi2_band, error_statistics, lead_frame_errors, lead_frame_sigmas, nees


def test_errors_in_lead_frame_signs():
    # Lead heading north-east (45 deg). Estimate 1 m too far along the heading and 0.5 m to the left.
    a = np.radians(45.0)
    fwd = np.array([np.sin(a), np.cos(a), 0.0])
    left = np.array([-np.cos(a), np.sin(a), 0.0])
    truth = np.array([10.0, 20.0, 0.3])
    est = truth + 1.0 * fwd + 0.5 * left + np.array([0, 0, -0.2])
    np.testing.assert_allclose(lead_frame_errors(est, truth, a), [1.0, 0.5, -0.2], atol=1e-12)


def test_sigmas_rotate_covariance():
    # Position covariance with 4 m^2 east, 1 m^2 north: for an east-heading lead, along=2 m, across=1 m.
    p = np.diag([4.0, 1.0, 9.0])
    np.testing.assert_allclose(lead_frame_sigmas(p, np.pi / 2), [2.0, 1.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(lead_frame_sigmas(p, 0.0), [1.0, 2.0, 3.0], atol=1e-12)


def test_statistics_of_known_sample():
    s = error_statistics([1.0, -1.0, 3.0, -3.0])
    assert s["mean"] == 0.0
    assert s["rms"] == pytest.approx(np.sqrt(5.0))
    assert s["std"] == pytest.approx(np.sqrt(20.0 / 3.0))
    assert s["max_abs"] == 3.0
    assert error_statistics([np.nan])["n"] == 0


def test_chi2_band_textbook_values():
    # chi-square(3): 2.5 % = 0.2158, 97.5 % = 9.348 (standard tables).
    lo, hi = chi2_band(3)
    assert lo == pytest.approx(0.2158, abs=1e-4) and hi == pytest.approx(9.348, abs=1e-3)
    # Average of 50 runs of chi2(3) is chi2(150)/50. Independent check: the Wilson-Hilferty
    # cube approximation, accurate to ~1e-3 relative at 150 dof.
    lo, hi = chi2_band(3, 50)
    k, z = 150, 1.959964
    wh = [k * (1 - 2 / (9 * k) + s * z * np.sqrt(2 / (9 * k))) ** 3 / 50 for s in (-1, 1)]
    assert lo == pytest.approx(wh[0], rel=2e-3) and hi == pytest.approx(wh[1], rel=2e-3)


def test_nees_of_consistent_gaussian_is_chi2():
    rng = np.random.default_rng(1)
    p = np.array([[2.0, 0.3, 0.0], [0.3, 1.0, 0.1], [0.0, 0.1, 0.5]])
    l_chol = np.linalg.cholesky(p)
    vals = [nees(l_chol @ rng.standard_normal(3), p) for _ in range(4000)]
    # mean of 4000 chi2(3) samples: sd = sqrt(6/4000) = 0.039; 4 sigma -> 0.15 (false failure ~6e-5)
    assert abs(np.mean(vals) - 3.0) < 0.16


def test_compiled_epoch_errors_equal_the_numpy_definitions():
    """The pipeline's per-epoch numbers come from one compiled call
    (v2v.metrics.errors.epoch_errors). Check it against the definitions it replaces
    (frames.ecef_to_enu, enu_to_ecef_vector, lead_frame_errors, lead_frame_sigmas, nees) on
    random clusters: the same formulas summed in the same order, so they may differ only where
    BLAS fuses a multiply-add: a few ulps of the largest term (ECEF differences ~1e3 m ->
    ~1e-13 m; covariances ~1 m^2 -> ~1e-16). Tolerance 1e-12 relative to each quantity's scale."""
    from v2v.frames import (
        ecef_to_enu,
        ecef_to_enu_rotation,
        ecef_to_geodetic,
        enu_to_ecef_vector,
        geodetic_to_ecef,
    )
    from v2v.metrics.errors import EPOCH_COLUMNS, epoch_errors, lead_frame_errors, lead_frame_sigmas, nees

    rng = np.random.default_rng(3)
    for _ in range(20):
        n = int(rng.integers(1, 6))
        lat, lon, az = rng.uniform(-1.4, 1.4), rng.uniform(-3.1, 3.1), rng.uniform(-np.pi, np.pi)
        lead = np.asarray(geodetic_to_ecef(lat, lon, 1000.0))
        ecef = lead + rng.normal(scale=50.0, size=(n, 3))
        nx = 8 * n + 3
        x = rng.normal(scale=30.0, size=nx)
        a = rng.normal(size=(nx, nx))
        P = a @ a.T + np.eye(nx)
        ipos, ivel = 8 * np.arange(n), 8 * np.arange(n) + 3
        vel, lead_vel = rng.normal(size=(n, 3)), rng.normal(size=3)
        lat_k, lon_k, _ = ecef_to_geodetic(ecef)
        ready = rng.random(n) < 0.7
        rot = ecef_to_enu_rotation(lat, lon)
        out = epoch_errors(x, P, ipos, ivel, ecef, lead, rot, vel, np.stack([lat_k, lon_k], axis=1), lead_vel,
                           float(np.sin(az)), float(np.cos(az)), ready)
        assert out.shape == (n, len(EPOCH_COLUMNS))
        for k in range(n):
            true = ecef_to_enu(ecef[k], lat, lon, lead)
            true_vel = rot @ (enu_to_ecef_vector(vel[k], lat_k[k], lon_k[k]) - enu_to_ecef_vector(lead_vel, lat, lon))
            est = x[ipos[k]:ipos[k] + 3]
            cov = P[ipos[k]:ipos[k] + 3, ipos[k]:ipos[k] + 3]
            ref = np.concatenate([true, est, true_vel, x[ivel[k]:ivel[k] + 3],
                                  lead_frame_errors(est, true, az), lead_frame_sigmas(cov, az),
                                  [cov[0, 0], cov[0, 1], cov[1, 1], cov[0, 2], cov[1, 2], cov[2, 2],
                                   nees(est - true, cov)]])
            if not ready[k]:  # not initialized: the truth only (true position and velocity)
                ref[[*range(3, 6), *range(9, 25)]] = np.nan
            np.testing.assert_allclose(out[k], ref, rtol=1e-12, atol=1e-12 * 100.0, equal_nan=True)


def _true_rel_vel(lead_lat_lon_deg, lead_vel_enu, lat_lon_deg, vel_enu):
    """``true_ve/vn/vu_mps`` of vehicles at ``lat_lon_deg`` (n, 2), each velocity ENU at its own
    position, from :func:`v2v.metrics.errors.epoch_errors` (truth only: no vehicle ready)."""
    from v2v.frames import ecef_to_enu_rotation, geodetic_to_ecef
    from v2v.metrics.errors import EPOCH_COLUMNS, epoch_errors

    lat0, lon0 = np.radians(lead_lat_lon_deg)
    ll = np.radians(np.asarray(lat_lon_deg, dtype=float).reshape(-1, 2))
    n = ll.shape[0]
    ecef = np.asarray(geodetic_to_ecef(ll[:, 0], ll[:, 1], 1100.0)).reshape(n, 3)
    out = epoch_errors(np.zeros(6), np.eye(6), np.zeros(n, dtype=np.int64), np.full(n, 3, dtype=np.int64), ecef,
                       np.asarray(geodetic_to_ecef(lat0, lon0, 1100.0)), ecef_to_enu_rotation(lat0, lon0),
                       np.asarray(vel_enu, dtype=float).reshape(n, 3), ll, np.asarray(lead_vel_enu, dtype=float),
                       0.0, 1.0, np.zeros(n, dtype=bool))
    i = EPOCH_COLUMNS.index("true_ve_mps")
    assert EPOCH_COLUMNS[i:i + 3] == ("true_ve_mps", "true_vn_mps", "true_vu_mps")
    return out[:, i:i + 3]


def test_true_relative_velocity_of_a_common_ecef_velocity_is_zero():
    """Two vehicles 0.1 deg of longitude apart (7 km at 51 deg N) moving with one ECEF velocity
    have no relative velocity, in any frame. Their ENU velocities (pymap3d, each at its own
    position) differ by the frames' turn, 0.1 deg * (sin 51 deg about up, cos 51 deg tilt):
    ~4 cm/s at 25 m/s, what differencing them directly (the former formula) reported."""
    import pymap3d

    lead_ll, veh_ll = (51.0775, -114.1295), (51.0775, -114.0295)
    v_ecef = np.array(pymap3d.enu2ecefv(20.0, 15.0, 0.3, *lead_ll))  # 25 m/s north-east at the lead
    lead_enu = np.array(pymap3d.ecef2enuv(*v_ecef, *lead_ll))
    veh_enu = np.array(pymap3d.ecef2enuv(*v_ecef, *veh_ll))
    rel = _true_rel_vel(lead_ll, lead_enu, [veh_ll], [veh_enu])[0]
    np.testing.assert_allclose(rel, 0.0, atol=1e-12)  # rounding of 25 m/s through two rotations: ~1e-14
    old = veh_enu - lead_enu  # each in its own frame: not zero
    assert np.linalg.norm(old) > 0.02


def test_true_relative_velocity_along_a_meridian_by_hand():
    """Lead and follower on one meridian, the follower delta = 3.75e-5 rad (~240 m) of geodetic
    latitude north, both driving due north at 25 m/s level in their own ENU frames. The
    follower's north is the lead's north turned by delta towards the lead's down:
    ``N(phi + delta) = N cos delta - U sin delta``, so in the lead's frame its velocity is
    ``(0, 25 cos delta, -25 sin delta)`` and the relative one ``(0, 25 (cos delta - 1),
    -25 sin delta)`` = (0, -1.76e-8, -9.375e-4) m/s (it descends relative to the lead's level,
    following the Earth's curvature). The former formula gave zero."""
    delta = 3.75e-5
    lat0 = 51.0775
    rel = _true_rel_vel((lat0, -114.1295), [0.0, 25.0, 0.0], [(lat0 + np.degrees(delta), -114.1295)],
                        [[0.0, 25.0, 0.0]])[0]
    np.testing.assert_allclose(rel, [0.0, 25.0 * (np.cos(delta) - 1.0), -25.0 * np.sin(delta)], rtol=0, atol=1e-13)
    assert abs(rel[2]) > 9e-4


def test_true_relative_velocity_against_pymap3d():
    """General case, pymap3d as the independent reference: each velocity to ECEF at its own
    position (``enu2ecefv``), the difference back to ENU at the lead (``ecef2enuv``). Three
    followers 0.002-0.05 deg away from the lead with velocities that climb and turn; the
    former formula (ENU differences) is off by 0.8-18 mm/s here, the tolerance 1e-12 m/s is
    rounding of ~30 m/s velocities."""
    import pymap3d

    lead_ll, lead_v = (-33.87, 151.21), np.array([-12.0, 21.0, 0.4])
    ll = np.array([[-33.868, 151.21], [-33.87, 151.26], [-33.92, 151.17]])
    vel = np.array([[-11.0, 22.5, -0.2], [3.0, -27.0, 1.1], [18.0, 9.0, 0.0]])
    rel = _true_rel_vel(lead_ll, lead_v, ll, vel)
    lead_ecef = np.array(pymap3d.enu2ecefv(*lead_v, *lead_ll))
    for k in range(3):
        d = np.array(pymap3d.enu2ecefv(*vel[k], *ll[k])) - lead_ecef
        ref = np.array(pymap3d.ecef2enuv(*d, *lead_ll))
        np.testing.assert_allclose(rel[k], ref, rtol=0, atol=1e-12)
        assert np.abs((vel[k] - lead_v) - ref).max() > 1e-4  # the former formula fails this


def test_update_kind_statistics_by_hand():
    """Six updates worked by hand. The 95 % chi-square(1) band is [0.000982, 5.0239]
    (0.025 / 0.975 quantiles: 0.0313^2 / 2.2414^2 of a standard normal's |z|).

    ====  ========  ======  =====  =================
    #     accepted  faulty  NIS    counts as
    ====  ========  ======  =====  =================
    0     yes       no      0.5    clean, in band
    1     yes       no      6.0    clean, out of band
    2     no        no      12.0   false rejection (clean)
    3     no        yes     40.0   true rejection
    4     yes       yes     3.0    missed fault
    5     yes       no      0.0001 clean, below band
    ====  ========  ======  =====  =================
    """
    from v2v.metrics.summary import update_kind_statistics

    acc = np.array([True, True, False, False, True, True])
    faulty = np.array([False, False, False, True, True, False])
    nis = np.array([0.5, 6.0, 12.0, 40.0, 3.0, 0.0001])
    got = update_kind_statistics(acc, faulty, nis)
    assert {k: got[k] for k in ("used", "rejected", "true_rejections", "false_rejections", "missed_faults", "faulty")} \
        == {"used": 4, "rejected": 2, "true_rejections": 1, "false_rejections": 1, "missed_faults": 1, "faulty": 2}
    # clean updates: #0, 1, 2, 5 -> mean (0.5 + 6 + 12 + 0.0001) / 4; in band: only #0
    assert got["nis_mean_clean"] == pytest.approx((0.5 + 6.0 + 12.0 + 0.0001) / 4, rel=1e-15)
    assert got["nis_frac_in_band_clean"] == 0.25
    none_clean = update_kind_statistics(np.array([False]), np.array([True]), np.array([9.0]))
    assert np.isnan(none_clean["nis_mean_clean"]) and np.isnan(none_clean["nis_frac_in_band_clean"])


def test_solution_statistics_by_hand():
    """Per solution (order of first appearance) and vehicle (sorted), over the initialized
    epochs only: the error statistics, the mean sigma with missing sigmas left out, the
    3-sigma exceedance rate and the NEES summary, computed by hand on six rows."""
    import pandas as pd

    from v2v.metrics.summary import solution_statistics

    nan = float("nan")
    rows = [  # solution, vehicle, initialized, along, sigma_along, nees
        ("S2", "c1.2", True, 1.0, 0.25, 2.0),
        ("S2", "c1.1", True, -2.0, 1.0, 1.0),
        ("S2", "c1.2", True, 3.0, nan, 4.0),
        ("S2", "c1.2", False, 99.0, 0.1, 99.0),  # not initialized: left out
        ("S1", "c1.1", True, 0.5, 1.0, 3.0),
        ("S1", "c1.1", False, 7.0, 1.0, nan),
    ]
    df = pd.DataFrame(rows, columns=["solution", "vehicle", "initialized", "along_err_m", "sigma_along_m", "nees_pos"])
    for comp in ("across", "up"):
        df[f"{comp}_err_m"] = 0.0
        df[f"sigma_{comp}_m"] = 1.0
    df["azimuth_err_rad"] = [np.radians(1.0), nan, np.radians(-3.0), 0.0, nan, 0.0]
    out = solution_statistics(df, {})
    assert list(out) == ["S2", "S1"]
    assert list(out["S2"]["vehicles"]) == ["c1.1", "c1.2"]
    v = out["S2"]["vehicles"]["c1.2"]
    assert v["epochs"] == 3 and v["availability"] == 2 / 3
    assert v["along"]["n"] == 2 and v["along"]["mean"] == 2.0 and v["along"]["max_abs"] == 3.0
    assert v["along_sigma_mean_m"] == 0.25  # the NaN sigma left out
    assert v["along_exceeds_3sigma"] == 0.5  # |1| > 0.75; |3| > 3 NaN is false: 1 of 2
    assert v["nees_pos"]["n"] == 2 and v["nees_pos"]["mean"] == 3.0 and v["nees_pos"]["dof"] == 3
    lo, hi = chi2_band(3)
    assert v["nees_pos"]["frac_in_band"] == np.mean([lo <= 2.0 <= hi, lo <= 4.0 <= hi])
    assert v["azimuth_err_deg"]["n"] == 2 and v["azimuth_err_deg"]["mean"] == pytest.approx(-1.0, abs=1e-12)
    w = out["S1"]["vehicles"]["c1.1"]
    assert w["availability"] == 0.5 and w["along"]["mean"] == 0.5
    assert np.isnan(w["along"]["std"])  # one sample: the sample std (ddof = 1) is undefined, as with none
    assert np.isnan(out["S2"]["vehicles"]["c1.1"]["azimuth_err_deg"]["mean"])  # its one initialized azimuth is NaN
    # only the solutions named as estimating azimuths get the azimuth statistics (the column is NaN for the others)
    # (the lead's azimuth error is the epoch's, repeated on each of its vehicle rows: counted once an epoch)
    df["t_s"] = [0.0, 0.0, 0.1, 0.2, 0.0, 0.1]
    df["lead_azimuth_err_rad"] = np.where(df["solution"] == "S2", np.radians([0.5, 0.5, 1.0, 3.0, 0, 0]), nan)
    named = solution_statistics(df, {}, azimuth_solutions={"S2"})
    assert "lead_azimuth_err_deg" not in named["S1"] and "azimuth_err_deg" not in named["S1"]["vehicles"]["c1.1"]
    assert named["S2"]["lead_azimuth_err_deg"]["n"] == 3 and named["S2"]["lead_azimuth_err_deg"]["mean"] == pytest.approx(1.5)
    assert named["S2"]["vehicles"]["c1.2"]["azimuth_err_deg"] == v["azimuth_err_deg"]
    # a vehicle with no initialized epoch: NaN statistics, no exceedance rate
    df.loc[df["solution"] == "S1", "initialized"] = False
    w = solution_statistics(df, {})["S1"]["vehicles"]["c1.1"]
    assert w["availability"] == 0.0 and w["along"]["n"] == 0 and np.isnan(w["along_sigma_mean_m"])
    assert "along_exceeds_3sigma" not in w


def test_printed_table_lists_vehicles_in_departure_order():
    """c1.1 ... c1.12: departure order is numeric; text order would put c1.10-c1.12 before c1.2."""
    from v2v.metrics.summary import paper_table

    e = {"along": {"mean": 0.0, "std": 0.0}, "across": {"mean": 0.0, "std": 0.0}, "availability": 1.0}
    ids = [f"c1.{k}" for k in range(1, 13)]
    table = paper_table({"GPS": {"vehicles": {v: e for v in sorted(ids)}}})
    assert [ln.split()[1] for ln in table.splitlines()[1:]] == ids


def test_epoch_nis_sums_by_hand():
    """Per-epoch NIS, worked by hand: three output epochs (0.1, 0.2, 0.3 s), vehicles a and b.

    ====  ========  ==============  ===========  ========  ====  =============================
    #     t_s       kind            vehicles     accepted  NIS   counts for
    ====  ========  ==============  ===========  ========  ====  =============================
    0     0.05      sd_pseudorange  a            yes       0.5   epoch 0, a
    1     0.1       uwb             a, b         yes       2.0   epoch 0, a and b (a pair)
    2     0.1+5e-10 sd_doppler      b            yes       4.0   epoch 0, b (within 1e-9)
    3     0.15      bearing         b, lead      yes       1.0   epoch 1, b (the lead: no row)
    4     0.15      sd_pseudorange  a            no        30.0  nothing: rejected
    5     0.2       height_aiding   a            yes       0.25  nothing: a pseudo-measurement
    6     0.2       uwb_constraint  a, b         yes       9.0   nothing: a constraint
    7     0.2       sd_phase        a            yes       3.0   epoch 1, a
    8     0.35      sd_pseudorange  a            yes       1.0   nothing: after the last epoch
    9     0.2       sd_doppler      b            yes       NaN   nothing: not a number
    ====  ========  ==============  ===========  ========  ====  =============================

    Means: epoch 0 a (0.5 + 2) / 2 = 1.25, b (2 + 4) / 2 = 3; epoch 1 a 3, b 1; epoch 2 none (NaN).
    """
    from v2v.metrics.errors import epoch_nis_sums

    kinds = ["bearing", "height_aiding", "sd_doppler", "sd_phase", "sd_pseudorange", "uwb", "uwb_constraint"]
    sets = [("a",), ("a", "b"), ("b",), ("b", "lead")]
    t = [0.05, 0.1, 0.1 + 5e-10, 0.15, 0.15, 0.2, 0.2, 0.2, 0.35, 0.2]
    kind = [4, 5, 2, 0, 4, 1, 6, 3, 4, 2]
    veh = [0, 1, 2, 3, 0, 0, 1, 0, 0, 2]
    acc = [True, True, True, True, False, True, True, True, True, True]
    nis = [0.5, 2.0, 4.0, 1.0, 30.0, 0.25, 9.0, 3.0, 1.0, np.nan]
    sums, counts = epoch_nis_sums([0.1, 0.2, 0.3], ["a", "b"], t, nis, acc, kind, kinds, veh, sets)
    np.testing.assert_array_equal(counts, [[2, 2], [1, 1], [0, 0]])
    np.testing.assert_allclose(sums, [[2.5, 6.0], [3.0, 1.0], [0.0, 0.0]], rtol=1e-15, atol=0)
    # the vehicles reported are the caller's: b alone gets b's column
    sums_b, counts_b = epoch_nis_sums([0.1, 0.2, 0.3], ["b"], t, nis, acc, kind, kinds, veh, sets)
    np.testing.assert_array_equal(counts_b, counts[:, 1:])
    np.testing.assert_array_equal(sums_b, sums[:, 1:])
    # no updates: zero sums and counts of the right shape
    s0, n0 = epoch_nis_sums([0.1, 0.2], ["a"], [], [], [], [], [], [], [])
    assert s0.shape == n0.shape == (2, 1) and not s0.any() and not n0.any()
