"""Lane-level metrics (v2v.metrics.lane) on hand-made epoch tables with known answers."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy import stats

from v2v.metrics.errors import lead_frame_errors
from v2v.metrics.lane import (
    attach_truth,
    integrity_counts,
    lane_level_table,
    lane_quantities,
    lead_azimuth_from_errors,
    protection_factor,
    round_half_away,
)

W = 3.2  # lane width (m)


def _epochs(true_enu: np.ndarray, est_enu: np.ndarray, az_rad: np.ndarray, *, sigma_m: float = 0.2,
            lane_v: int = 0, lane_lead: int = 0, solution: str = "S", vehicle: str = "c1.1") -> pd.DataFrame:
    """Epoch rows as the pipeline writes them (errors rotated with the lead's true azimuth)."""
    n = len(true_enu)
    err = np.array([lead_frame_errors(e, t, a) for e, t, a in zip(est_enu, true_enu, az_rad, strict=True)])
    return pd.DataFrame({
        "t_s": 0.1 * np.arange(n), "cluster": "c1", "solution": solution, "vehicle": vehicle,
        "initialized": True,
        "true_e_m": true_enu[:, 0], "true_n_m": true_enu[:, 1], "true_u_m": true_enu[:, 2],
        "est_e_m": est_enu[:, 0], "est_n_m": est_enu[:, 1], "est_u_m": est_enu[:, 2],
        "along_err_m": err[:, 0], "across_err_m": err[:, 1], "up_err_m": err[:, 2],
        "sigma_along_m": sigma_m, "sigma_across_m": sigma_m,
        "true_lane_index": lane_v, "lead_lane_index": lane_lead, "lane_width_m": W,
    })


def _left_unit(az: float) -> np.ndarray:
    return np.array([-np.cos(az), np.sin(az), 0.0])


def _fwd_unit(az: float) -> np.ndarray:
    return np.array([np.sin(az), np.cos(az), 0.0])


def test_round_half_away_is_symmetric():
    np.testing.assert_array_equal(round_half_away([0.5, -0.5, 0.49, -0.49, 1.5, -1.5, 0.0]),
                                  [1, -1, 0, 0, 2, -2, 0])


def test_half_lane_across_error_flips_the_lane():
    """A vehicle 25 m behind in the lead's lane: across error 0.49 w keeps the lane, 0.5 w flips it
    (to the left for +, right for -), at any lead heading."""
    az = np.radians(37.0)
    true = -25.0 * _fwd_unit(az)
    offsets = np.array([0.0, 0.49, 0.5, -0.5, 1.2]) * W
    est = np.array([true + d * _left_unit(az) for d in offsets])
    df = _epochs(np.tile(true, (len(offsets), 1)), est, np.full(len(offsets), az))
    q = lane_quantities(df)
    np.testing.assert_allclose(q["true_across_m"], 0.0, atol=1e-9)
    np.testing.assert_allclose(q["est_across_m"], offsets, atol=1e-9)
    np.testing.assert_array_equal(q["rel_lane_est"], [0, 0, 1, -1, 1])
    np.testing.assert_array_equal(q["rel_lane_true"], 0)
    t = lane_level_table(df)
    assert t.loc[0, "correct_lane"] == pytest.approx(2 / 5)
    assert t.loc[0, "correct_lane_geom"] == pytest.approx(2 / 5)
    assert t.loc[0, "lane_model_ok"] == 1.0
    # where-in-lane percentiles of |across error| = |offsets| (numpy's linear interpolation)
    assert t.loc[0, "across_abs_p50_m"] == pytest.approx(np.percentile(np.abs(offsets), 50))
    assert t.loc[0, "across_abs_p99_m"] == pytest.approx(np.percentile(np.abs(offsets), 99))


def test_azimuth_recovered_from_the_error_rotation():
    rng = np.random.default_rng(3)
    az = rng.uniform(0, 2 * np.pi, 200)
    e = rng.normal(size=(200, 3))
    lf = np.array([lead_frame_errors(ei, np.zeros(3), a) for ei, a in zip(e, az, strict=True)])
    rec = lead_azimuth_from_errors(e[:, 0], e[:, 1], lf[:, 0], lf[:, 1])
    np.testing.assert_allclose(np.angle(np.exp(1j * (rec - az))), 0.0, atol=1e-12)
    assert np.isnan(lead_azimuth_from_errors([0.0], [0.0], [0.0], [0.0])[0])


def test_neighbouring_lane_on_the_same_edge_uses_lane_indices():
    """Vehicle in the lane left of the lead (index 1 vs 0): the true relative lane is +1 from the
    indices on the same edge; on another edge it is unknown (NaN: another edge's lane indices
    need not correspond to the lead's), and the lane-truth rates count the epoch on the lead's
    edge only."""
    az = 0.3
    true = -20.0 * _fwd_unit(az) + 0.7 * W * _left_unit(az)  # 0.7 w: lane model disagrees (rounds to 1 anyway)
    est = true + 0.2 * _left_unit(az)
    df = _epochs(np.array([true, true]), np.array([est, est]), np.array([az, az]), lane_v=1, lane_lead=0)
    truth = pd.DataFrame({
        "t_s": [0.0, 0.0, 0.1, 0.1], "vehicle": ["c1.0", "c1.1", "c1.0", "c1.1"], "cluster": "c1",
        "is_lead": [True, False, True, False], "edge": ["A", "A", "A", "B"], "azimuth_rad": az,
    })
    q = lane_quantities(df, truth)
    assert list(q["same_edge"]) == [True, False]
    np.testing.assert_array_equal(q["rel_lane_true"], [1, np.nan])
    np.testing.assert_array_equal(q["rel_lane_geom"], [1, 1])
    np.testing.assert_array_equal(q["rel_lane_est"], [1, 1])
    t1 = lane_level_table(df, truth)
    assert t1.loc[0, ["lane_model_ok", "correct_lane", "wrong_lane_by_2plus"]].tolist() == [1.0, 1.0, 0.0]
    # two lanes to the left by index while the geometry says one: the lane model fails on the
    # epoch with a lane truth (the other epoch's geometric lane is not taken for the truth)
    df2 = df.assign(true_lane_index=2)
    q2 = lane_quantities(df2, truth)
    np.testing.assert_array_equal(q2["rel_lane_true"], [2, np.nan])
    t = lane_level_table(df2, truth)
    assert t.loc[0, "lane_model_ok"] == 0.0
    assert t.loc[0, "correct_lane"] == 0.0
    assert t.loc[0, "correct_lane_geom"] == 1.0  # (over both epochs: the geometry needs no lane truth)
    assert t.loc[0, "same_edge"] == pytest.approx(0.5)
    # no epoch on the lead's edge: no lane truth, the rates that need it are NaN
    t3 = lane_level_table(df2.iloc[1:], truth)
    assert np.isnan(t3.loc[0, ["lane_model_ok", "correct_lane", "wrong_lane_by_2plus"]].astype(float)).all()
    assert t3.loc[0, "same_edge"] == 0.0 and t3.loc[0, "correct_lane_geom"] == 1.0


def test_integrity_counts_by_hand():
    """sigma = 0.2 m, AL = 1 m, k_PL(1e-3) = 3.29: PL = 0.658 m <= AL for the first five epochs;
    the last one (sigma 0.4 m, PL 1.316 m) is unavailable; the seventh is not initialized."""
    err = np.array([0.1, 0.59, 0.61, 0.7, 1.1, 0.5, 9.0])
    sig = np.array([0.2, 0.2, 0.2, 0.2, 0.2, 0.4, 0.2])
    avail = np.array([True] * 6 + [False])
    k = protection_factor(1e-3)
    assert k == pytest.approx(3.2905, abs=1e-4)
    ic = integrity_counts(err, sig, avail, alert_limit_m=1.0, integrity_risk=1e-3, k_sigma=3.0)
    assert ic["n"] == 6
    assert ic["mi_rate_ksigma"] == pytest.approx(3 / 6)  # 0.61, 0.7, 1.1 > 0.6 (3 sigma)
    assert ic["mi_rate_pl"] == pytest.approx(2 / 6)  # 0.7, 1.1 > 0.658
    assert ic["availability"] == pytest.approx(5 / 7)
    assert ic["hmi_rate"] == pytest.approx(1 / 7)  # 1.1 > AL while PL <= AL
    assert ic["pl_mean_m"] == pytest.approx(k * np.mean(sig[:6]))


def test_consistent_gaussian_errors_give_the_nominal_misleading_rates():
    """Errors ~ N(0, sigma^2) with the filter's sigma: P(|e| > 3 sigma) = 0.27 %, P(|e| > PL) = 1e-3.
    n = 400 000: binomial std of the counts 33 and 20; tolerance 5 std (false failure ~1e-6)."""
    rng = np.random.default_rng(11)
    n = 400_000
    sig = rng.uniform(0.1, 0.5, n)
    err = rng.normal(0.0, sig)
    ic = integrity_counts(err, sig, alert_limit_m=1.0, integrity_risk=1e-3)
    p3 = 2 * stats.norm.sf(3.0)
    assert abs(ic["mi_rate_ksigma"] * n - p3 * n) < 5 * np.sqrt(n * p3 * (1 - p3))
    assert abs(ic["mi_rate_pl"] * n - 1e-3 * n) < 5 * np.sqrt(n * 1e-3 * (1 - 1e-3))
    # availability = P(3.29 sigma <= 1) for sigma ~ U(0.1, 0.5): (1/3.29 - 0.1) / 0.4
    p_av = (1.0 / protection_factor(1e-3) - 0.1) / 0.4
    assert abs(ic["availability"] - p_av) < 5 * np.sqrt(p_av * (1 - p_av) / n)


def test_table_rows_per_solution_and_vehicle_and_uninitialized_epochs():
    az = 0.0
    true = np.tile(-20.0 * _fwd_unit(az), (4, 1))
    a = _epochs(true, true.copy(), np.full(4, az), solution="A", vehicle="c1.1")
    b = _epochs(true, true + 2.0 * _left_unit(az), np.full(4, az), solution="B", vehicle="c1.1")
    b.loc[0, "initialized"] = False
    t = lane_level_table(pd.concat([a, b], ignore_index=True))
    assert list(t["solution"]) == ["A", "B"]
    assert t.loc[0, "correct_lane"] == 1.0 and t.loc[1, "correct_lane"] == 0.0
    assert t.loc[1, "initialized"] == pytest.approx(0.75)
    # uninitialized epochs count as unavailable: 3 of 4 epochs with PL = 0.66 m <= 1 m
    assert t.loc[1, "across_availability"] == pytest.approx(0.75)
    assert t.loc[1, "across_hmi_rate"] == pytest.approx(0.75)  # 2 m > AL at every available epoch
    assert t.attrs["k_pl"] == pytest.approx(protection_factor(1e-3))


def test_attach_truth_is_a_left_join_on_time_and_vehicle_and_the_cluster_lead():
    """By hand: each epoch row gets its own truth edge and its cluster lead's edge and azimuth
    at the same time (times joined on whole milliseconds); a row with no truth gets NaN; rows
    keep their order. Truth that repeats a (time, vehicle) key multiplies the row, as a join does."""
    truth = pd.DataFrame({
        "t_s": [0.0, 0.0, 0.1, 0.1, 0.1], "vehicle": ["L", "A", "L", "A", "M"], "cluster": ["c1", "c1", "c1", "c1", "c2"],
        "is_lead": [True, False, True, False, True], "edge": ["e0", "e1", "e2", "e3", "e9"],
        "azimuth_rad": [0.5, 0.6, 0.7, 0.8, 0.9],
    })
    epochs = pd.DataFrame({"t_s": [0.1 + 1e-7, 0.0, 0.2], "cluster": ["c1", "c1", "c1"], "vehicle": ["A", "A", "A"]},
                          index=[7, 3, 5])
    out = attach_truth(epochs, truth)
    assert list(out.index) == [0, 1, 2] and list(out["t_s"]) == list(epochs["t_s"])
    assert list(out["edge"][:2]) == ["e3", "e1"] and list(out["lead_edge"][:2]) == ["e2", "e0"]
    np.testing.assert_array_equal(out["lead_azimuth_rad"], [0.7, 0.5, np.nan])
    assert out[["edge", "lead_edge"]].iloc[2].isna().all()  # no truth at 0.2 s
    no_cluster = attach_truth(epochs.drop(columns="cluster"), truth)  # the first lead of each time
    assert list(no_cluster["lead_edge"][:2]) == ["e2", "e0"]
    twice = attach_truth(epochs, pd.concat([truth, truth.iloc[[3]]], ignore_index=True))
    assert len(twice) == 4 and list(twice["edge"][:3]) == ["e3", "e3", "e1"]


def test_rows_skip_missing_keys_and_match_the_table():
    """A row without a solution or vehicle belongs to no group (as in pandas' groupby); the
    groups keep their order of first appearance; ``lane_level_rows`` is the table's rows."""
    from v2v.metrics.lane import lane_level_rows

    az = 0.0
    true = np.tile(-20.0 * _fwd_unit(az), (3, 1))
    parts = [_epochs(true, true.copy(), np.full(3, az), solution=s, vehicle=v)
             for s, v in (("B", "c1.2"), ("A", "c1.1"), ("B", "c1.1"))]
    df = pd.concat(parts, ignore_index=True)
    df.loc[1, "vehicle"] = None
    df.loc[4, "solution"] = None
    rows = lane_level_rows(df)
    assert [(r["solution"], r["vehicle"], r["epochs"]) for r in rows] == [("B", "c1.2", 2), ("A", "c1.1", 2), ("B", "c1.1", 3)]
    pd.testing.assert_frame_equal(pd.DataFrame(rows), lane_level_table(df))  # (NaN-aware: zero errors give no azimuth)


def test_pooled_rows_count_each_vehicle_against_its_own_truth():
    """Two followers on the lead's edge: c1.1 in the lane left of the lead (index 1) with 0.7 w of
    across offset (the geometry rounds to 1: lane model right), c1.2 two lanes left by index with
    1.2 w (the geometry says 1: lane model wrong); both estimated at the geometric lane. Pooled:
    lane_model_ok 1/2, correct_lane 1/2, correct_lane_geom 1, same_edge 1; the per-vehicle rows
    recounted over both vehicles."""
    az = 0.0
    t1 = -20.0 * _fwd_unit(az) + 0.7 * W * _left_unit(az)
    t2 = -40.0 * _fwd_unit(az) + 1.2 * W * _left_unit(az)
    df = pd.concat([_epochs(np.array([t1]), np.array([t1]), np.array([az]), lane_v=1, vehicle="c1.1"),
                    _epochs(np.array([t2]), np.array([t2]), np.array([az]), lane_v=2, vehicle="c1.2")],
                   ignore_index=True)
    truth = pd.DataFrame({"t_s": 0.0, "vehicle": ["c1.0", "c1.1", "c1.2"], "cluster": "c1",
                          "is_lead": [True, False, False], "edge": "A", "azimuth_rad": az})
    per = lane_level_table(df, truth)
    pooled = lane_level_table(df, truth, pool_vehicles=True)
    assert list(per["lane_model_ok"]) == [1.0, 0.0] and list(pooled["vehicle"]) == ["all"]
    assert pooled.loc[0, ["same_edge", "lane_model_ok", "correct_lane", "correct_lane_geom"]].tolist() == [1.0, 0.5, 0.5, 1.0]
    assert pooled.loc[0, "epochs"] == 2
