"""Smoke test of experiments/fault_campaign.py --quick (3 faults x 2 solutions, 40 s runs, ~15 s).

Content checks (physics, not just files):
* clock jump (1 ms = 299 792.458 m on every pseudorange of c1.1 from 15 s): handled within
  1 s (pseudoranges used again), and the baseline never leaves 3 sigma and stays at the
  metre level (the jump absorbed into the baseline would be ~1e5 m);
* pseudorange blunders (30 m, p = 0.1, ~4 innovation sigma): rejections happen, and every
  rejection is a true one (a false-alarm count of a few per run is the alpha = 0.001
  expectation on ~6000 clean tests, so allow <= 20);
* 5 s GNSS outage of everyone: seen at its first epoch, and the filters recover (errors
  within 3 sigma, pseudoranges used) within 5 s of its end.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd

ROOT = Path(__file__).resolve().parents[1]


def _load():
    spec = importlib.util.spec_from_file_location("fault_campaign", ROOT / "experiments" / "fault_campaign.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_fault_campaign_quick(tmp_path):
    mod = _load()
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    table = pd.read_csv(tmp_path / "fault_campaign.csv")
    assert (tmp_path / "fault_campaign.png").stat().st_size > 10_000
    md = (tmp_path / "fault_campaign.md").read_text()
    assert "clock_jump" in md and "| fault |" in md
    assert set(table["fault"]) == {"clock_jump", "pr_blunder", "gnss_outage"}
    assert set(table["solution"]) == {"GPS", "GPS+UWB+Bearing"}
    by = {(r.fault, r.solution): r for r in table.itertuples()}
    for sol in ("GPS", "GPS+UWB+Bearing"):
        cj = by["clock_jump", sol]
        assert cj.detected == "y" and cj.latency_s <= 1.0
        assert cj.exceed_3sigma_fault == 0.0
        assert cj.max_along_fault_m < 3.0 and cj.max_across_fault_m < 3.0
        assert cj.recovery_s <= 1.0
        assert cj.injected > 0
        pb = by["pr_blunder", sol]
        assert pb.detected == "y" and pb.true_rej > 0
        assert pb.false_rej <= 20
        assert pb.exceed_3sigma_fault < 0.05
        go = by["gnss_outage", sol]
        assert go.detected == "y" and go.latency_s <= 0.1 + 1e-9
        assert np.isfinite(go.recovery_s) and go.recovery_s <= 5.0
