"""Forward collision warning (v2v.apps.fcw) on synthetic kinematics with analytic answers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from v2v.apps.fcw import (
    BrakingEvent,
    BrakingInjector,
    FcwConfig,
    antenna_arms_x_m,
    causal_slope,
    compare_warnings,
    detect_braking_events,
    fcw_study,
    following_pairs,
    pair_kinematics,
    time_to_collision_s,
    warning_intervals,
)

DT = 0.1
L_AHEAD = 4.8


def _pair_epochs(t: np.ndarray, gap_true: np.ndarray, closing_true: np.ndarray, *,
                 gap_est: np.ndarray | None = None, closing_est: np.ndarray | None = None,
                 with_velocity: bool = True, solution: str = "S") -> pd.DataFrame:
    """Follower c1.1 straight behind the lead c1.0 (heading north): relative position
    (0, -(gap + L)), relative velocity (0, +closing) (the follower is faster)."""
    ge = gap_true if gap_est is None else gap_est
    ce = closing_true if closing_est is None else closing_est
    z = np.zeros(t.size)
    df = pd.DataFrame({
        "t_s": t, "solution": solution, "vehicle": "c1.1", "initialized": True,
        "true_e_m": z, "true_n_m": -(gap_true + L_AHEAD), "true_u_m": z,
        "est_e_m": z, "est_n_m": -(ge + L_AHEAD), "est_u_m": z,
        "true_ve_mps": z, "true_vn_mps": closing_true, "est_ve_mps": z, "est_vn_mps": ce,
    })
    if not with_velocity:
        df = df.drop(columns=["true_ve_mps", "true_vn_mps", "est_ve_mps", "est_vn_mps"])
    return df


def _decelerating_lead(g0: float, a: float, t_end: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Both at the same speed at t = 0; the lead brakes at a (m/s^2), the follower keeps its speed."""
    t = DT * np.arange(int(round(t_end / DT)) + 1)
    return t, g0 - 0.5 * a * t**2, a * t


def test_ttc_edge_cases():
    np.testing.assert_array_equal(time_to_collision_s([10.0, 10.0, 10.0, -1.0], [2.0, 0.0, -1.0, 3.0]),
                                  [5.0, np.inf, np.inf, 0.0])


def test_constant_decel_lead_warns_at_the_analytic_ttc_crossing():
    """g(t) = g0 - a t^2 / 2, c(t) = a t: TTC = T at t* = -T + sqrt(T^2 + 2 g0 / a).
    The first warning sample is the first grid time >= t* (NHTSA NCAP decelerating-lead test:
    both at 72 km/h, 30 m apart, lead braking 0.3 g)."""
    g0, a, T = 30.0, 0.3 * 9.80665, 2.5
    t, g, c = _decelerating_lead(g0, a, 4.0)  # contact at sqrt(2 g0 / a) = 4.5 s
    k = pair_kinematics(_pair_epochs(t, g, c), "S", "c1.1", "c1.0", "c1.0", source="est",
                        length_ahead_m=L_AHEAD, config=FcwConfig(ttc_threshold_s=T, velocity="filter"))
    np.testing.assert_allclose(k["gap_m"], g, atol=1e-9)
    np.testing.assert_allclose(k["closing_mps"], c, atol=1e-9)
    t_star = -T + np.sqrt(T**2 + 2 * g0 / a)
    t_warn = k["t_s"][k["warn"]].iloc[0]
    assert t_star <= t_warn < t_star + DT + 1e-9
    assert k["warn"].to_numpy()[k["t_s"].to_numpy() >= t_warn].all()  # stays on: TTC keeps falling


def test_finite_difference_velocity_lags_by_half_the_window():
    """Without filter velocities the closing speed is the causal LS slope of the range over W:
    exact at t - tau for a quadratic, tau = (n - 1) dt / 2, so the warning moves to
    t* = -T + sqrt(T^2 + 2 (g0 + a T tau) / a)."""
    g0, a, T, w = 30.0, 3.0, 2.5, 0.5
    t, g, c = _decelerating_lead(g0, a, 4.0)  # contact at 4.5 s
    cfg = FcwConfig(ttc_threshold_s=T, velocity="auto", fd_window_s=w)
    k = pair_kinematics(_pair_epochs(t, g, c, with_velocity=False), "S", "c1.1", "c1.0", "c1.0",
                        source="true", length_ahead_m=L_AHEAD, config=cfg)
    n = int(round(w / DT))
    tau = (n - 1) * DT / 2
    late = t >= w
    np.testing.assert_allclose(k["closing_mps"][late], a * (t[late] - tau), atol=1e-9)
    t_star = -T + np.sqrt(T**2 + 2 * (g0 + a * T * tau) / a)
    t_warn = k["t_s"][k["warn"]].iloc[0]
    assert t_star <= t_warn < t_star + DT + 1e-9


def test_causal_slope_exact_on_a_ramp_and_ignores_the_future():
    t = DT * np.arange(50)
    y = 3.0 - 1.5 * t
    s = causal_slope(t, y, 0.5)
    assert np.isnan(s[0])
    np.testing.assert_allclose(s[1:], -1.5, atol=1e-12)
    y2 = y.copy()
    y2[30:] += 100.0  # a future jump does not change the past slopes
    np.testing.assert_array_equal(causal_slope(t, y2, 0.5)[:30], s[:30])


def test_noisy_closing_speed_gives_the_predicted_false_warning_rate():
    """Truth: gap 20 m, closing 5 m/s (TTC 4 s > 2.5 s: never warns). Estimate: closing + N(0, 2^2)
    iid per epoch. An epoch warns iff c + n > g / T = 8 m/s: p = Q((8 - 5) / 2) = Q(1.5) = 6.68 %.
    Warning onsets (false warnings) per epoch: p (1 - p). n = 20 000: the epoch count's std is 35,
    the onset count's < 33; tolerance 5 std (false failure ~1e-6)."""
    rng = np.random.default_rng(5)
    n = 20_000
    t = DT * np.arange(n)
    g = np.full(n, 20.0)
    c = np.full(n, 5.0)
    ce = c + rng.normal(0.0, 2.0, n)
    cfg = FcwConfig(ttc_threshold_s=2.5, velocity="filter")
    ep = _pair_epochs(t, g, c, closing_est=ce)
    k = pair_kinematics(ep, "S", "c1.1", "c1.0", "c1.0", source="est", length_ahead_m=L_AHEAD, config=cfg)
    p = stats.norm.sf(1.5)
    assert abs(k["warn"].sum() - n * p) < 5 * np.sqrt(n * p * (1 - p))
    kt = pair_kinematics(ep, "S", "c1.1", "c1.0", "c1.0", source="true", length_ahead_m=L_AHEAD, config=cfg)
    assert not kt["warn"].any()
    cmp = compare_warnings(t, kt["warn"], k["warn"], tolerance_s=1.0)
    assert cmp.truth_warnings == 0 and cmp.missed == 0
    expected_onsets = n * p * (1 - p)
    assert abs(cmp.false - expected_onsets) < 5 * np.sqrt(expected_onsets)


def test_compare_warnings_by_hand():
    t = DT * np.arange(100)
    wt = (t >= 2.0) & (t < 3.0) | (t >= 6.0) & (t < 6.5)
    we = (t >= 2.3) & (t < 2.8) | (t >= 8.5) & (t < 8.7)
    cmp = compare_warnings(t, wt, we, tolerance_s=1.0)
    assert (cmp.truth_warnings, cmp.estimated_warnings) == (2, 2)
    assert (cmp.detected, cmp.missed, cmp.false) == (1, 1, 1)
    assert cmp.time_errors_s == pytest.approx((0.3,))
    # an early estimate inside the tolerance: negative error
    cmp2 = compare_warnings(t, wt, (t >= 1.5) & (t < 2.5), tolerance_s=1.0)
    assert cmp2.time_errors_s == pytest.approx((-0.5,)) and cmp2.false == 0
    np.testing.assert_allclose(warning_intervals(t, wt), [(2.0, 2.9), (6.0, 6.4)])


def test_braking_events_from_truth_acceleration():
    t = DT * np.arange(100)
    acc = np.where((t >= 2.0) & (t < 3.5), -4.0, 0.0) + np.where((t >= 6.0) & (t < 6.2), -5.0, 0.0)
    truth = pd.DataFrame({"t_s": t, "vehicle": "c1.0", "accel_mps2": acc, "speed_mps": 10.0})
    ev = detect_braking_events(truth)
    assert len(ev) == 1  # the 0.2 s blip is shorter than the 0.3 s minimum
    assert ev.loc[0, "t_start_s"] == pytest.approx(2.0) and ev.loc[0, "t_end_s"] == pytest.approx(3.4)
    assert ev.loc[0, "min_accel_mps2"] == -4.0


def test_fcw_study_end_to_end_on_a_braking_lead():
    """Lead brakes at 3 m/s^2 from t = 1 s; perfect estimate: every truth warning detected, no
    false warnings, zero warning-time error; the braking event is a 'hit'."""
    g0, a = 30.0, 3.0
    t = DT * np.arange(45)  # contact at 1 + sqrt(2 g0 / a) = 5.5 s
    tb = np.clip(t - 1.0, 0.0, None)
    g, c = g0 - 0.5 * a * tb**2, a * tb
    ep = _pair_epochs(t, g, c).assign(cluster="c1")
    truth = pd.concat([
        pd.DataFrame({"t_s": t, "vehicle": "c1.0", "cluster": "c1", "is_lead": True, "length_m": L_AHEAD,
                      "accel_mps2": np.where(t >= 1.0, -a, 0.0), "speed_mps": 15.0 - a * tb,
                      "x_m": 0.0, "y_m": 0.0, "front_x_m": 0.0, "front_y_m": 2.0, "azimuth_rad": 0.0, "lane": "E_0"}),
        pd.DataFrame({"t_s": t, "vehicle": "c1.1", "cluster": "c1", "is_lead": False, "length_m": L_AHEAD,
                      "accel_mps2": 0.0, "speed_mps": 15.0, "x_m": 0.0, "y_m": -(g + L_AHEAD),
                      "front_x_m": 0.0, "front_y_m": 2.0 - (g + L_AHEAD), "azimuth_rad": 0.0, "lane": "E_0"}),
    ], ignore_index=True)
    assert following_pairs(truth) == [("c1.1", "c1.0")]
    res = fcw_study(ep, truth, config=FcwConfig(velocity="filter"))
    s = res["solutions"].iloc[0]
    assert s["truth_warnings"] == 1 and s["detected"] == 1 and s["missed"] == 0 and s["false"] == 0
    assert s["events_hit"] == 1 and s["event_warn_time_err_mean_s"] == 0.0
    assert s["gap_err_rms_m"] == pytest.approx(0.0, abs=1e-9)


def test_gap_of_a_car_behind_a_truck_with_different_antenna_setbacks():
    """A car (antenna 2.0 m behind its front bumper) 8 m behind a 12 m truck (antenna 1.0 m
    behind), both heading east, closing at 5 m/s: car front at x = 0, antenna at -2; truck rear
    at 8, front at 20, antenna at 19. Antennas 21 m apart; gap 21 - 12 - (-1 - (-2)) = 8 m,
    TTC 8 / 5 = 1.6 s (with the lever arms taken as equal: 9 m and 1.8 s)."""
    truth = pd.DataFrame({"t_s": 0.0, "vehicle": ["c1.0", "c1.1"], "x_m": [19.0, -2.0], "y_m": 5.0,
                          "front_x_m": [20.0, 0.0], "front_y_m": 5.0, "azimuth_rad": np.pi / 2})
    arms = antenna_arms_x_m(truth)
    assert arms == {"c1.0": pytest.approx(-1.0), "c1.1": pytest.approx(-2.0)}
    ep = pd.DataFrame({"t_s": [0.0], "solution": "S", "vehicle": "c1.1", "initialized": True,
                       "true_e_m": -21.0, "true_n_m": 0.0, "true_u_m": 0.0, "true_ve_mps": 5.0, "true_vn_mps": 0.0})
    k = pair_kinematics(ep, "S", "c1.1", "c1.0", "c1.0", source="true", length_ahead_m=12.0,
                        arm_x_ahead_m=arms["c1.0"], arm_x_follower_m=arms["c1.1"], config=FcwConfig(velocity="filter"))
    assert k["gap_m"].tolist() == pytest.approx([8.0]) and k["ttc_s"].tolist() == pytest.approx([1.6])
    k_equal = pair_kinematics(ep, "S", "c1.1", "c1.0", "c1.0", source="true", length_ahead_m=12.0,
                              config=FcwConfig(velocity="filter"))
    assert k_equal["gap_m"].tolist() == pytest.approx([9.0]) and k_equal["ttc_s"].tolist() == pytest.approx([1.8])


def test_braking_injector_ramps_down_and_releases():
    inj = BrakingInjector([BrakingEvent(t_s=1.0, vehicle="v", decel_mps2=6.0, duration_s=2.0)])
    assert inj.commands(0.9, {"v": 12.0}) == {}
    assert inj.commands(1.0, {"v": 12.0}) == {"v": 12.0}  # v0 recorded at the start
    assert inj.commands(1.5, {"v": 99.0}) == {"v": pytest.approx(9.0)}  # from v0, not the current speed
    assert inj.commands(2.9, {"v": 0.6}) == {"v": pytest.approx(0.6)}
    assert inj.commands(3.0, {"v": 0.6}) == {"v": -1.0}  # released to the car-following model
    assert inj.commands(3.1, {"v": 5.0}) == {}

    class Api:
        def __init__(self) -> None:
            self.calls: list[tuple] = []

        def setSpeed(self, vid, v):  # noqa: N802
            self.calls.append(("speed", vid, v))

        def setSpeedMode(self, vid, m):  # noqa: N802
            self.calls.append(("mode", vid, m))

    api = Api()
    inj2 = BrakingInjector([BrakingEvent(t_s=0.0, vehicle="v", decel_mps2=20.0, duration_s=0.5)])
    inj2.apply(api, 0.0, {"v": 5.0})
    inj2.apply(api, 0.3, {"v": 5.0})
    inj2.apply(api, 0.5, {"v": 0.0})
    assert api.calls == [("mode", "v", 27), ("speed", "v", 5.0), ("mode", "v", 27), ("speed", "v", 0.0),
                         ("mode", "v", 31), ("speed", "v", -1.0)]
    with pytest.raises(ValueError):
        BrakingEvent(t_s=0.0, vehicle="v", decel_mps2=-1.0, duration_s=1.0)


def test_a_braking_run_of_exactly_the_minimum_duration_is_an_event():
    """Three samples at 0.1 s of -4 m/s^2 are 0.3 s of braking (each sample stands for its
    interval), the minimum: an event (it was dropped, its first-to-last span being 0.2 s)."""
    t = DT * np.arange(50)
    acc = np.where((t > 1.95) & (t < 2.25), -4.0, 0.0)  # samples at 2.0, 2.1, 2.2 s
    ev = detect_braking_events(pd.DataFrame({"t_s": t, "vehicle": "c1.0", "accel_mps2": acc, "speed_mps": 10.0}))
    assert len(ev) == 1 and ev.loc[0, "t_start_s"] == pytest.approx(2.0) and ev.loc[0, "t_end_s"] == pytest.approx(2.2)


def test_solution_totals_pool_the_pairs_samples():
    """Pair A: RMS 1 m over the 10 of its 100 epochs with an estimate; pair B: 0 m over 100 of 100;
    pair C: no estimate at all. Pooled over the 110 samples: sqrt(10 * 1^2 / 110) = 0.3015 m (the
    pairs' epochs as weights gave sqrt(100 / 200) = 0.707 m, and C's NaN made it NaN)."""
    from v2v.apps.fcw import PAIR_COLUMNS, _solution_totals

    base = dict.fromkeys(PAIR_COLUMNS, 0)
    rows = [{**base, "solution": "S", "follower": f, "ahead": "c1.0", "epochs": 100, "available": av,
             "gap_err_rms_m": r, "closing_err_rms_mps": r, "gap_err_n": n, "closing_err_n": n, "epoch_agreement": 1.0}
            for f, av, r, n in (("a", 0.1, 1.0, 10), ("b", 1.0, 0.0, 100), ("c", 0.0, float("nan"), 0))]
    tot = _solution_totals(pd.DataFrame(rows, columns=PAIR_COLUMNS), pd.DataFrame(columns=["solution", "warn_time_err_s",
                                                                                           "outcome"]))
    assert tot.loc[0, "gap_err_rms_m"] == pytest.approx(np.sqrt(10.0 / 110.0), rel=1e-12)
    assert tot.loc[0, "closing_err_rms_mps"] == pytest.approx(np.sqrt(10.0 / 110.0), rel=1e-12)
    assert tot.loc[0, "available"] == pytest.approx(1.1 / 3.0, rel=1e-12)  # epochs-weighted: (10 + 100 + 0) / 300


def test_fcw_study_without_pairs_or_epochs_gives_empty_tables():
    """No following pair (or a run that estimated nothing): empty tables with their columns,
    not a KeyError."""
    from v2v.apps.fcw import PAIR_COLUMNS, SOLUTION_COLUMNS

    t = DT * np.arange(10)
    ep = _pair_epochs(t, np.full(t.size, 20.0), np.zeros(t.size)).assign(cluster="c1")
    truth = pd.DataFrame({"t_s": np.tile(t, 2), "vehicle": np.repeat(["c1.0", "c1.1"], t.size), "cluster": "c1",
                          "is_lead": np.repeat([True, False], t.size), "length_m": L_AHEAD, "accel_mps2": 0.0,
                          "speed_mps": 10.0, "x_m": np.repeat([0.0, 3.2], t.size), "y_m": 0.0, "front_x_m":
                          np.repeat([0.0, 3.2], t.size), "front_y_m": 2.0, "azimuth_rad": 0.0,
                          "lane": np.repeat(["E_0", "E_1"], t.size)})  # side by side: nobody follows anybody
    for epochs, pairs in ((ep, None), (ep.iloc[:0], None), (ep, [])):
        res = fcw_study(epochs, truth, pairs=pairs)
        assert res["pairs"].empty and list(res["pairs"].columns) == list(PAIR_COLUMNS)
        assert res["solutions"].empty and list(res["solutions"].columns) == list(SOLUTION_COLUMNS)
