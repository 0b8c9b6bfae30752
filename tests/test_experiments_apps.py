"""Smoke tests of experiments/lane_level.py and experiments/fcw_study.py (--quick), content checked.

Both run the ``open`` variant (urban_canyon streets, buildings removed) so that GNSS works
with the nominal constellation; the canyon itself denies GNSS (about 2 satellites tracked).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from v2v.apps.fcw import FcwConfig, pair_kinematics
from v2v.metrics.lane import protection_factor

EXP = Path(__file__).resolve().parents[1] / "experiments"
SOLS = ["GPS", "GPS+UWB", "GPS+Bearing", "GPS+UWB+Bearing"]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(f"exp_{name}", EXP / f"{name}.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.sumo
def test_lane_level_quick(tmp_path: Path):
    assert _load("lane_level").main(["--quick", "--variants", "open", "--out", str(tmp_path)]) == 0
    t = pd.read_csv(tmp_path / "lane_level.csv")
    pooled = pd.read_csv(tmp_path / "lane_level_solutions.csv")
    assert (tmp_path / "lane_level_across_cdf.png").stat().st_size > 10_000
    assert "correct_lane" in (tmp_path / "lane_level.md").read_text()
    assert sorted(t["solution"].unique()) == sorted(SOLS) and list(pooled["solution"]) == SOLS
    assert set(t["vehicle"]) == {"c1.1", "c1.2"}
    # independent recomputation from the run folder: rotate with the lead's true azimuth by hand
    folder = tmp_path / "runs" / "open"
    ep = pd.read_parquet(folder / "epochs.parquet")
    tr = pd.read_parquet(folder / "truth.parquet")
    lead = tr[tr["is_lead"]].assign(k=lambda d: np.round(d["t_s"] * 1000).astype(int)).set_index("k")["azimuth_rad"]
    ep = ep[ep["initialized"]].copy()
    az = lead.reindex(np.round(ep["t_s"] * 1000).astype(int)).to_numpy()
    for src in ("true", "est"):
        ep[f"{src}_lat"] = -ep[f"{src}_e_m"] * np.cos(az) + ep[f"{src}_n_m"] * np.sin(az)
    geom = np.round(ep["true_lat"] / ep["lane_width_m"])
    est = np.round(ep["est_lat"] / ep["lane_width_m"])
    for sol in SOLS:
        m = (ep["solution"] == sol).to_numpy()
        row = pooled[pooled["solution"] == sol].iloc[0]
        assert row["correct_lane_geom"] == pytest.approx(np.mean(est[m] == geom[m]), abs=1e-12)
        assert row["across_pl_mean_m"] == pytest.approx(protection_factor(1e-3) * ep.loc[m, "sigma_across_m"].mean())
        # open sky: the across error stays well inside half a lane (1.6 m) -> right lane almost always
        assert row["across_abs_p95_m"] < 1.0 and row["correct_lane_geom"] > 0.95
        assert row["across_abs_p50_m"] <= row["across_abs_p95_m"] <= row["across_abs_p99_m"]
    # lanes 0 and 1 round robin: c1.1 departs in the lane left of the lead (relative lane +1)
    assert tr.loc[tr["vehicle"] == "c1.1", "lane_index"].iloc[0] == 1
    assert (t.loc[t["vehicle"] == "c1.1", "same_edge"] > 0.5).all()
    assert (t["lane_model_ok"] > 0.8).all()


@pytest.mark.sumo
def test_fcw_study_quick(tmp_path: Path):
    assert _load("fcw_study").main(["--quick", "--variants", "open", "--out", str(tmp_path)]) == 0
    sol = pd.read_csv(tmp_path / "fcw_solutions.csv")
    pairs = pd.read_csv(tmp_path / "fcw_pairs.csv")
    br = pd.read_csv(tmp_path / "fcw_braking.csv")
    ev = pd.read_csv(tmp_path / "fcw_events.csv")
    assert (tmp_path / "fcw_ttc_open.png").stat().st_size > 10_000
    assert list(sol["solution"]) == SOLS
    # in-line cluster: c1.1 follows c1.0, c1.2 follows c1.1
    assert set(zip(pairs["follower"], pairs["ahead"], strict=True)) == {("c1.1", "c1.0"), ("c1.2", "c1.1")}
    # the first traffic light: the lead brakes hard (SUMO decel 4.5 m/s^2 bound) within 30 s
    lead_br = br[br["vehicle"] == "c1.0"]
    assert len(lead_br) >= 1 and (lead_br["min_accel_mps2"] < -2.0).all() and (lead_br["min_accel_mps2"] >= -4.5 - 1e-6).all()
    assert (sol["detected"] + sol["missed"] == sol["truth_warnings"]).all()
    # a truth warning in an event window means the true TTC dropped below the threshold there
    warned = ev["outcome"].isin(["hit", "missed"])
    assert (ev.loc[warned, "min_ttc_true_s"] < FcwConfig().ttc_threshold_s).all()
    assert (ev.loc[~warned, "min_ttc_true_s"].fillna(np.inf) >= 0).all()
    # open sky, all sensors: metre-free gap, decimetre-per-second closing speed
    best = sol[sol["solution"] == "GPS+UWB+Bearing"].iloc[0]
    assert best["gap_err_rms_m"] < 1.0 and best["closing_err_rms_mps"] < 0.5
    # truth closing speed = speed difference along a straight lane (independent of the ENU algebra)
    folder = tmp_path / "runs" / "open"
    ep = pd.read_parquet(folder / "epochs.parquet")
    tr = pd.read_parquet(folder / "truth.parquet")
    k = pair_kinematics(ep, "GPS", "c1.1", "c1.0", "c1.0", source="true", length_ahead_m=4.8)
    tk = tr.assign(k=np.round(tr["t_s"] * 1000).astype(int)).set_index(["vehicle", "k"])
    kk = np.round(k["t_s"] * 1000).astype(int)
    v_f = tk.loc["c1.1", "speed_mps"].reindex(kk).to_numpy()
    v_a = tk.loc["c1.0", "speed_mps"].reindex(kk).to_numpy()
    same_edge = tk.loc["c1.1", "edge"].reindex(kk).to_numpy() == tk.loc["c1.0", "edge"].reindex(kk).to_numpy()
    straight = same_edge & ~pd.Series(tk.loc["c1.0", "edge"].reindex(kk).to_numpy()).str.startswith(":").to_numpy()
    assert straight.sum() > 50
    np.testing.assert_allclose(k["closing_mps"].to_numpy()[straight], (v_f - v_a)[straight], atol=0.05)


@pytest.mark.parametrize(("script", "args", "field"), [
    ("covariance_analysis.py", ["--quick"], "--out"),  # --out below a file (every script makes it the same way)
    ("fault_campaign.py", ["--quick", "--trials", "0"], "--trials"),  # (0 meant the default, 300)
    ("lane_level.py", ["--quick", "--across-alert-limit-m", "-1"], "--across-alert-limit-m"),
    # argparse's own errors: one line with a fix, not its usage block (and --settle-s's was one of those)
    ("fcw_study.py", ["--quick", "--seed", "1.5"], "argument --seed"),
    ("carrier_phase.py", ["--parts", "nope"], "argument --parts"),
    ("paper_sensor_combinations.py", ["--quick", "--settle-s", "-1"], "--settle-s"),
    # options used only by a later part are checked before the first part runs and writes its tables
    ("covariance_analysis.py", ["--quick", "--outage-start-s", "inf"], "--outage-start-s"),
    ("covariance_analysis.py", ["--quick", "--converge-s", "40"], "--converge-s"),
    # --solution-set: not KEY=VALUE, a field that names or defines the script's solutions, an unknown one
    ("carrier_phase.py", ["--quick", "--solution-set", "nokey"], "--solution-set"),
    ("carrier_phase.py", ["--quick", "--solution-set", 'name="x"'], "--solution-set"),
    ("carrier_phase.py", ["--quick", "--solution-set", "pseudorange_sigma_m=2"], "--solution-set"),
    ("carrier_phase.py", ["--quick", "--solution-set", "gnss_cn0_mask=41"], "--solution-set"),
])
def test_experiment_scripts_refuse_bad_input_in_one_line(tmp_path, script, args, field):
    """An experiment run as a script treats a user's mistake as `v2v` does: one line naming the
    field and the fix on stderr, exit status 2, no traceback, nothing written: the --out folder
    (and its runs/) the script made before the mistake was found is taken away again."""
    import subprocess
    import sys

    out = tmp_path / "out"
    if field == "--out":
        out.write_text("mine")
        out = out / "sub"
    p = subprocess.run([sys.executable, str(EXP / script), "--out", str(out), *args], capture_output=True, text=True,
                       timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert len(lines) == 1 and lines[0].startswith(f"{script}: error: {field}: ") and "fix:" in lines[0], lines
    assert not out.exists()


@pytest.mark.parametrize(("script", "args", "option", "field"), [
    ("fcw_study.py", ["--vehicles", "1"], "--vehicles", "clusters.0.vehicles"),
    ("lane_level.py", ["--rinex", "/nonexistent/brdc.nav", "--duration-s", "2"], "--rinex", "sensors.gnss.ephemeris"),
    ("lane_level.py", ["--quick", "--lanes", "-1"], "--lanes", "clusters.0.lanes.0"),
    ("carrier_phase.py", ["--seeds", "-1"], "--seeds", "seed"),
    ("carrier_phase.py", ["--quick", "--uwb-sigma-m", "1e-300"], "--uwb-sigma-m", "solutions.2.uwb_sigma_m"),
    ("carrier_phase.py", ["--quick", "--solution-set", "gnss_min_satellites=28"], "--solution-set",
     "solutions.0.gnss_min_satellites"),
    ("covariance_analysis.py", ["--quick", "--vehicles", "1"], "--vehicles", "clusters.0.vehicles"),
    ("gnss_environments.py", ["--vehicles", "1"], "--vehicles", "clusters.0.vehicles"),
    ("gnss_environments.py", ["--start-utc", "1970-01-01T00:00:00Z"], "--start-utc", "start_utc"),
    ("paper_uwb_errors.py", ["--vehicles", "-1"], "--vehicles", "clusters.0.vehicles"),  # (was numpy's traceback)
    ("paper_uwb_errors.py", ["--quick", "--max-speed-mps", "80"], "--max-speed-mps, --speed-step-mps",
     "vehicle_types.v0.max_speed_mps"),
    ("uwb_nlos_canyon.py", ["--truck-fraction", "2"], "--truck-fraction", "background.truck_fraction"),
    ("foundation_check.py", ["--quick", "--duration", "-5"], "--duration", "duration_s"),
    # found by the run's set-up (the net's lanes), not the scenario's schema
    ("carrier_phase.py", ["--quick", "--lanes", "[9]"], "--lanes", "clusters.0.lanes"),
    ("carrier_phase.py", ["--quick", "--time-gap-s", "0"], "--time-gap-s", "clusters.0.time_gap_s"),
    # options used by a later part or run are checked before the first one runs
    ("covariance_analysis.py", ["--quick", "--outage-vehicles", "1"], "--outage-vehicles", "clusters.0.vehicles"),
    ("paper_sensor_combinations.py", ["--quick", "--seeds", "1", "-1"], "--seeds", "seed"),
])
def test_a_scenario_field_an_option_set_is_blamed_on_the_option(tmp_path, script, args, option, field):
    """An experiment passes its options into a scenario; the scenario's check (or the run's
    set-up) then refuses a field. The one line names the option the user typed, the scenario
    field after the message (v2v.errors.script_options), not the field alone, nor "the command
    line's --set"; exit status 2, nothing written."""
    import subprocess
    import sys

    out = tmp_path / "out"
    p = subprocess.run([sys.executable, str(EXP / script), "--out", str(out), *args], capture_output=True, text=True,
                       timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and "Traceback" not in p.stderr, p.stderr
    assert len(lines) == 1 and lines[0].startswith(f"{script}: error: {option}: "), lines
    assert f"({field}) -- fix: " in lines[0] and "--set" not in lines[0], lines
    assert not out.exists()


def test_carrier_phase_keep_above_the_satellites_in_view_names_keep(tmp_path):
    """--keep 40 leaves no satellite to remove: known after the degraded part's probe run (the
    sky), refused there in one line naming --keep (it was a satellites_lost fault without PRNs,
    blamed on faults.0.prns and the command line's --set)."""
    import subprocess
    import sys

    p = subprocess.run([sys.executable, str(EXP / "carrier_phase.py"), "--out", str(tmp_path / "out"), "--quick",
                        "--parts", "degraded", "--keep", "40"], capture_output=True, text=True, timeout=300)
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert p.returncode == 2 and len(lines) == 1 and "Traceback" not in p.stderr, p.stderr
    assert lines[0].startswith("carrier_phase.py: error: --keep: ") and " -- fix: " in lines[0], lines
