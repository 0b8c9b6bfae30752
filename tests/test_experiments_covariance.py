"""Smoke test of ``experiments/covariance_analysis.py --quick``: it runs, and the filter's
predicted sigmas it writes follow the geometry of Petovello et al. section 3.3."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from expkit import assert_png, load_experiment

pytestmark = pytest.mark.sumo


def test_covariance_analysis_quick(tmp_path):
    """Cars in line on one lane, ~28 m apart (two-second rule at 50 km/h).

    * A UWB range's gradient is the unit line of sight, which here is the road direction:
      it informs the along-track position and nothing across. One range of sigma_UWB = 0.5 m
      (the filter's, paper Table 1) bounds the along-track sigma by 0.5 m; the filter fuses
      several (3 Hz), so GPS+UWB along must be below that, far below GPS-only (~0.8 m from
      5 m pseudoranges), and its across-track sigma within 5 % of GPS-only.
    * A bearing's gradient is perpendicular to the line of sight, of magnitude 1/d: it
      informs the across-track position with sigma d * sigma_bearing (27.7 m x 0.5 deg =
      0.24 m for one bearing) and nothing along. GPS+Bearing across must be below that (10 Hz,
      both directions of each pair), far below GPS-only (~0.67 m), and along within 5 %.
    * GPS+UWB+Bearing takes the better of both in each direction (within 5 %).
    * GNSS outage of every vehicle for 10 s (height aiding on): nothing but the process model
      holds GPS-only, whose position sigma per axis then grows like the integral of the
      first-order Gauss-Markov relative velocity (sigma_v = 10 m/s, tau = 2 s):
      var = 2 sigma_v^2 tau (T - tau (1 - exp(-T/tau))) -> 56 m at T = 9.9 s; the filter's
      value may sit up to 20 % lower (the converged position-velocity cross-covariance at
      the start of the outage). UWB + bearings alone keep the horizontal solution: sigma
      bounded by a few metres (the along-track sawtooths between 3 Hz ranges, with no
      Doppler holding the velocity), across-track still bearing-sized, and the true error
      inside 3 sigma.
    """
    mod = load_experiment("covariance_analysis")
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0

    per = pd.read_csv(tmp_path / "covariance_vs_vehicles.csv")
    assert set(per["vehicles"]) == {2, 3}
    assert set(per["solution"]) == set(mod.SOLUTIONS)
    for col in ("sigma_along_m", "sigma_across_m", "rms_along_m", "rms_across_m"):
        assert np.all(np.isfinite(per[col])) and np.all(per[col] > 0.0), col
    runs = pd.read_csv(tmp_path / "covariance_runs.csv")
    for n, g in per.groupby("vehicles"):
        s = g.set_index("solution")
        gps, uwb, brg, both = (s.loc[k] for k in ("GPS", "GPS+UWB", "GPS+Bearing", "GPS+UWB+Bearing"))
        assert uwb["sigma_along_m"] < 0.5 and uwb["sigma_along_m"] < 0.6 * gps["sigma_along_m"], (n, s)
        assert uwb["sigma_across_m"] == pytest.approx(gps["sigma_across_m"], rel=0.05)
        r = runs[(runs["vehicles"] == n) & (runs["solution"] == "GPS+Bearing") & (runs["vehicle"] == "c1.1")]
        one_bearing_m = float(r["range_m"].iloc[0]) * np.radians(0.5)
        assert brg["sigma_across_m"] < one_bearing_m and brg["sigma_across_m"] < 0.5 * gps["sigma_across_m"], (n, s)
        assert brg["sigma_along_m"] == pytest.approx(gps["sigma_along_m"], rel=0.05)
        assert both["sigma_along_m"] < 1.05 * uwb["sigma_along_m"]
        assert both["sigma_across_m"] < 1.05 * brg["sigma_across_m"]
        assert s["used_uwb"].loc["GPS+UWB"] > 0 and s["used_bearing"].loc["GPS+Bearing"] > 0

    out = pd.read_csv(tmp_path / "gnss_outage.csv").set_index("solution")
    assert (out["epochs_during"] == 100).all()  # 10 s at 10 Hz, every follower's worst row per epoch
    drift_m = mod.gm_drift_m(9.9)
    assert drift_m == pytest.approx(56.26, abs=0.01)  # by hand: sqrt(400 (9.9 - 2 (1 - e^-4.95)))
    assert out.loc["GPS", "sigma_along_max_during_m"] > 0.8 * drift_m
    assert out.loc["GPS", "sigma_along_max_during_m"] < 1.1 * drift_m
    both = out.loc["GPS+UWB+Bearing"]
    assert both["sigma_h_max_during_m"] < 5.0 < 0.1 * drift_m
    assert both["sigma_across_mean_during_m"] < 0.3
    assert both["frac_err_within_3sigma_during"] > 0.95
    assert both["sigma_h_first_after_m"] < 1.0  # UWB + bearings carried it: no re-convergence from 5 m

    for name in ("sigma_vs_vehicles.png", "gnss_outage.png"):
        assert_png(tmp_path / name)
    assert "| vehicles | lanes | GPS along |" in (tmp_path / "covariance_vs_vehicles.md").read_text()


@pytest.mark.parametrize(("script", "given", "key", "expect"), [
    ("covariance_analysis", [], "vehicles", [2, 3]),
    ("covariance_analysis", ["--vehicles", "4", "5"], "vehicles", [4, 5]),
    ("covariance_analysis", ["--duration-s", "40"], "duration_s", 40.0),
    ("covariance_analysis", ["--vehicles-3lanes"], "vehicles_3lanes", []),
    ("paper_sensor_combinations", [], "seeds", [1]),
    ("paper_sensor_combinations", ["--seeds", "4", "5"], "seeds", [4, 5]),
    ("paper_sensor_combinations", ["--nets", "open_highway"], "nets", ["open_highway"]),
])
def test_quick_fills_only_the_options_not_given(script, given, key, expect):
    """--quick chooses the smoke-test size of what the command line leaves open; an option the
    user gives is kept (before, --quick replaced it silently)."""
    args = load_experiment(script).parse_args(["--out", "x", "--quick", *given])
    assert getattr(args, key) == expect
