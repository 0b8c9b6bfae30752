"""Smoke tests of the sensor experiments (``--quick``): they run, and what they write is physics.

Each experiment is loaded from its file (``experiments/`` is a folder of scripts, not a
package) and its ``main`` called with an output folder; the checks read the written files.
"""

from __future__ import annotations

import json

import pandas as pd
import pytest
from expkit import assert_png, load_experiment

pytestmark = pytest.mark.sumo


def test_gnss_environments_quick(tmp_path):
    mod = load_experiment("gnss_environments")
    assert mod.main(["--quick", "--out", str(tmp_path), "--nets", "open_highway", "urban_canyon"]) == 0
    t = pd.read_csv(tmp_path / "gnss_environments.csv").set_index("net")
    hw, cy = t.loc["open_highway"], t.loc["urban_canyon"]
    # Highway: nothing above the mask is hidden (sheds stay below 3.4 deg): tracked == in view.
    assert hw["nlos_fraction"] == 0.0
    assert hw["tracked_mean"] == pytest.approx(hw["sats_above_mask_mean"], abs=1e-9)
    # Canyon: fewer satellites, some echo-only with positive metre-level excess.
    assert cy["tracked_mean"] < hw["tracked_mean"] - 1.0
    assert cy["nlos_fraction"] > 0.05
    assert cy["nlos_excess_min_m"] > 0.0
    assert cy["local_err_mean_nlos_m"] > 1.0
    assert cy["cn0_nlos_mean_dbhz"] < cy["cn0_los_mean_dbhz"]
    # The simulator's blocking agrees with the independent shapely skyline for every decided case.
    assert (t["skyline_checks"] > 0).all()
    assert (t["skyline_agreement"] == 1.0).all()
    pv = pd.read_csv(tmp_path / "gnss_per_vehicle.csv")
    assert set(pv["net"]) == {"open_highway", "urban_canyon"} and len(pv) == 6
    for name in ("gnss_sats_and_nlos.png", "gnss_skyplot_open_highway.png", "gnss_skyplot_urban_canyon.png"):
        assert_png(tmp_path / name)
    assert "| quantity | open_highway | urban_canyon |" in (tmp_path / "gnss_environments.md").read_text()


def test_paper_uwb_errors_quick(tmp_path):
    mod = load_experiment("paper_uwb_errors")
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    fits = pd.read_csv(tmp_path / "uwb_pair_fits.csv")
    assert len(fits) >= 2
    assert (fits["d_max_m"] - fits["d_min_m"] > 30.0).all(), "each pair must sweep a range of distances"
    assert (fits["d_max_m"] <= 100.0 + 1.0).all(), "MSSI ranges stop at 100 m (+ a few cm of error)"
    # Slope = scale factor: MSSI walk 3900-4700 ppm + oscillator |e| <= 8 ppm. The fit recovers the
    # pair's configured value within 4 standard errors plus 300 ppm for the bias random walk
    # (0.002 m/sqrt(s): ~0.015 m over the run, spread over ~80 m of range change -> ~200 ppm).
    diff = (fits["fit_scale_ppm"] - fits["model_scale_ppm"]).abs()
    assert (diff < 4.0 * fits["fit_scale_se_ppm"] + 300.0).all(), fits
    assert ((fits["model_scale_ppm"] > 3880) & (fits["model_scale_ppm"] < 4710)).all()
    # Intercept = turn-around bias 1/2 (e_A - e_B) t_ta c, |.| <= 0.49 m for +-8 ppm and 205 us.
    assert ((fits["fit_bias_m"] - fits["model_bias_m"]).abs() < 4.0 * fits["fit_bias_se_m"] + 0.05).all(), fits
    assert (fits["model_bias_m"].abs() < 0.5).all()
    # Detrended scatter: noise 6 cm, multipath 5 cm, quantization 4 cm, time-tag sync at a few m/s.
    assert (fits["resid_std_m"] < 0.2).all() and (fits["resid_std_m"] > 0.05).all()
    summary = json.loads((tmp_path / "uwb_pair_fits.json").read_text())["summary"]
    assert summary["pooled_scale_ppm"] == pytest.approx(summary["mean_model_scale_ppm"], abs=600.0)
    for name in ("uwb_errors_fig16_17.png", "uwb_error_vs_range.png", "uwb_error_vs_10log_d2.png"):
        assert_png(tmp_path / name)


def test_uwb_nlos_canyon_quick(tmp_path):
    mod = load_experiment("uwb_nlos_canyon")
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    r = json.loads((tmp_path / "uwb_nlos_canyon.json").read_text())
    f = r["census_fraction"]
    assert sum(f.values()) == pytest.approx(1.0)
    assert f["car"] == 0.0, "a 1.5 m car cannot cut a straight link between 1.55 m roof antennas"
    assert f["building"] > 0.0 and f["truck"] > 0.0
    assert r["uwb_nlos_ranges"] > 0
    assert r["nlos_error_median_m"] > 0.5
    assert r["nlos_error_positive_fraction"] > 0.95  # a tiny excess can sit under a negative pair bias
    nl = pd.read_csv(tmp_path / "uwb_nlos_ranges.csv")
    assert (nl["nlos_excess_m"] > 0.0).all()
    # Bearings exist exactly on unblocked lines of sight: availability == census LOS share
    # (same geometry; the census samples every 0.5 s instead of every tick).
    assert r["bearing"]["availability"] == pytest.approx(r["bearing_expected_from_census"], abs=0.03)
    census = pd.read_csv(tmp_path / "uwb_link_census.csv")
    assert (census["distance_m"] <= 100.0).all()
    assert_png(tmp_path / "uwb_nlos_canyon.png")
