"""Smoke tests of experiments/carrier_phase.py (--quick), content checked against physics.

Real SUMO + the real receiver model (not the filter's test world): the initialization drive's
open-sky segment must give validated fixes with centimetre errors and no wrong integer; the
other parts run in the slow suite (they add ~2 min).
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd
import pytest
from expkit import assert_png, load_experiment

pytestmark = pytest.mark.sumo


def test_carrier_phase_init_drive_quick(tmp_path: Path):
    exp = load_experiment("carrier_phase")
    assert exp.main(["--quick", "--parts", "init_drive", "--out", str(tmp_path)]) == 0
    t = pd.read_csv(tmp_path / "init_drive.csv")
    open_sky = t[t["segment"] == "open"].set_index("solution")
    for sol in ("GPS-phase", "GPS-phase+UWB", "GPS-phase+UWB+Bearing"):
        r = open_sky.loc[sol]
        # 8 satellites in the open, 5 s minimum lock: fixed well before the canyon (~70 s in)
        assert r["fix_rate"] > 0.8
        # the simulator knows the integers: a validated fix (P_B >= 0.999, ratio >= 3) is right
        assert r["wrong_fix_rate"] == 0.0
        # SD phase noise ~2 mm, multipath 1 % of the code's: fixed baselines at the cm level,
        # against ~0.2-0.4 m for the code-only GPS solution in the same epochs
        assert r["fixed_horiz_rms_m"] < 0.03
    assert open_sky.loc["GPS", "across_rms_m"] > 5 * open_sky.loc["GPS-phase", "fixed_horiz_rms_m"]
    ttff = pd.read_csv(tmp_path / "init_drive_ttff.csv")
    assert (ttff["ttff_s"] <= 15.0).all()  # 5 s minimum lock + convergence with 8 satellites
    assert_png(tmp_path / "carrier_phase_timeline.png")
    assert "Initialization drive" in (tmp_path / "carrier_phase.md").read_text()


@pytest.mark.slow
def test_carrier_phase_degraded_and_slips_quick(tmp_path: Path):
    exp = load_experiment("carrier_phase")
    assert exp.main(["--quick", "--parts", "degraded", "slips", "--out", str(tmp_path)]) == 0
    slips = pd.read_csv(tmp_path / "slips.csv")
    assert (slips["wrong_fix_epochs"] == 0).all()
    assert (slips["slip_detections_run_total"] >= 1).all()
    assert slips["refix_s"].notna().all()
    deg = pd.read_csv(tmp_path / "degraded.csv")
    full = deg[(deg["window"] == "full sky") & deg["solution"].str.contains("phase")]
    assert (full["fix_rate"] > 0.8).all()
