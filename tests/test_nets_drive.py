"""Clusters driven by the real libsumo on the shipped nets (and an OSM import) produce
trustworthy truth: on the road, azimuth along the direction of travel, velocity that is the
derivative of position, reproducible by seed (issue 2).

The measurements come from ``experiments/foundation_check.py`` (one implementation, used by
the experiment and these tests); the tolerances are explained where they are asserted.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

pytestmark = pytest.mark.sumo
REPO = Path(__file__).resolve().parents[1]


def _load_experiment():
    spec = importlib.util.spec_from_file_location("foundation_check", REPO / "experiments" / "foundation_check.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod


fc = _load_experiment()


def _drive(case, out: Path) -> pd.DataFrame:
    from v2v.run import run_scenario

    run_scenario(fc.scenario_for(case), out, quiet=True, replay=False)
    return pd.read_parquet(out / "truth.parquet")


def _assert_trustworthy(row) -> None:
    """The issue's criteria, with the physics behind each bound.

    * Front bumper: SUMO's ``getPosition`` is on the lane centre-line (0 up to the 0.01 m
      rounding of the net's shapes); only a lane change (3 s) carries it across, up to half
      a lane width (1.6 m). Outside lane changes: < 0.5 m.
    * Antenna, 2 m behind the bumper on the body axis: SUMO's heading is the chord from the
      rear to the front bumper, so in a sharp junction corner (radius ~ vehicle length) the
      antenna cuts inside by up to ~1.3 m, during a lane change it is up to 1.6 m off. < 2 m.
    * Azimuth vs the ECEF direction of travel on straight driving (|yaw rate| < 1 deg/s):
      0 on a straight lane; SUMO's heading relaxes over ~ a vehicle length after a lane
      change, leaving < 1 deg while the yaw rate is already small. < 2 deg.
    """
    assert row.front_max_no_lc_m < 0.5, row
    assert row.front_max_m < 0.5 * 3.2 + 0.05, row
    assert row.ant_max_m < 2.0, row
    assert row.az_samples > 100, row
    assert row.az_err_max_deg < 2.0, row
    assert row.teleports == 0 and row.collisions == 0, row


@pytest.mark.parametrize("net", ["hospital_loop", "open_highway"])  # the two cheapest to run
def test_three_cars_30_s_on_the_road_with_true_azimuth(net, tmp_path):
    case = fc.Case(label=f"{net}/3", net=net, vehicles=3, lanes=(0,), duration_s=30.0)
    row = fc.run_case(case, tmp_path / net)
    _assert_trustworthy(row)
    assert row.simulated_s == pytest.approx(30.0)
    assert row.truth_rows == 3 * 301  # every car present at every step, t = 0 included


def test_velocity_is_the_derivative_of_position(tmp_path):
    """SUMO moves a car by the mean of its old and new speed over a step (trapezoid), so the
    ECEF displacement / dt equals the mean of the two truth velocities to rounding where the
    path is smooth (median < 1 mm/s). Left over: polyline vertices of the lane shapes (the
    direction jumps by ~1 deg: ~0.1 m/s at 14 m/s) and lane-change kinks (SUMO switches
    the lateral speed, 1.07 m/s, on and off within one step), excluded by the mask.
    """
    case = fc.Case(label="hospital_loop/3", net="hospital_loop", vehicles=3, lanes=(0,), duration_s=30.0)
    truth = _drive(case, tmp_path / "run")
    err, lc = fc.velocity_errors_mps(truth)
    assert lc.any(), "the convoy changes lane on the approach (strategic, for the 1-lane loop)"
    assert np.median(err[~lc]) < 1e-3
    assert err[~lc].max() < 0.15
    # Velocity is along the azimuth on straight driving (same 2 deg criterion as azimuth).
    v = truth[np.degrees(truth["yaw_rate_rps"].abs()) < 0.01][["vel_e_mps", "vel_n_mps", "azimuth_rad"]].to_numpy()
    course = np.arctan2(v[:, 0], v[:, 1])
    from v2v.frames import wrap_angle

    assert np.degrees(np.abs(wrap_angle(course - v[:, 2]))).max() < 0.1


def test_same_seed_same_truth_other_seed_other_truth(tmp_path):
    def run(seed: int, name: str) -> pd.DataFrame:
        case = fc.Case(label="h", net="hospital_loop", vehicles=3, lanes=(0,), duration_s=20.0, seed=seed)
        return _drive(case, tmp_path / name)

    a, b, c = run(5, "a"), run(5, "b"), run(6, "c")
    assert a.equals(b), "same seed: identical truth, bit for bit"
    # Krauss driver imperfection (sigma 0.5) draws from SUMO's --seed: speeds, hence positions, differ.
    assert len(a) == len(c)
    assert not np.allclose(a["x_m"].to_numpy(), c["x_m"].to_numpy(), atol=0.01)


def test_osm_import_drives(tmp_path):
    case = fc.osm_case(tmp_path / "nets", duration_s=30.0)
    row = fc.run_case(case, tmp_path / "run")
    _assert_trustworthy(row)


def test_experiment_quick_writes_physical_table(tmp_path):
    assert fc.main(["--quick", "--out", str(tmp_path)]) == 0
    df = pd.read_csv(tmp_path / "foundation_check.csv")
    assert list(df["run"]) == ["hospital_loop/3"]
    row = df.iloc[0]
    _assert_trustworthy(row)
    assert bool(row.on_road_ok) and bool(row.azimuth_ok)
    # Warm-up: 3 cars 2 s apart in one lane are all on the road after 2 * 2 s plus one step.
    assert row.warmup_s == pytest.approx(4.1)
    md = (tmp_path / "foundation_check.md").read_text()
    assert "| hospital_loop/3 |" in md


@pytest.mark.slow
@pytest.mark.parametrize("net", fc.SHIPPED)
@pytest.mark.parametrize("vehicles", [3, 20])
def test_all_nets_120_s(net, vehicles, tmp_path):
    lanes = (0, 1) if vehicles == 20 and fc.first_edge_lanes(net) >= 2 else (0,)
    case = fc.Case(label=f"{net}/{vehicles}", net=net, vehicles=vehicles, lanes=lanes, duration_s=120.0)
    row = fc.run_case(case, tmp_path / "run")
    _assert_trustworthy(row)
    assert row.truth_rows == vehicles * 1201  # nobody teleported away or arrived
    # Insertion on time: cars depart time_gap / lanes (2 s / lanes) apart, round robin over
    # the lanes (each lane keeps the two-second rule); the last is on the road one step
    # after its departure time, (n - 1) * 2 s / lanes.
    assert row.warmup_s == pytest.approx((vehicles - 1) * 2.0 / len(lanes) + 0.1, abs=0.15)
