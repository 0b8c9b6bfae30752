"""experiments/fault_campaign.py: smoke test of ``--quick`` (CI subset) and the full campaign (slow).

``--quick``: the filter-level rows (simulate.py world = the filter's model; 300 blunder trials
per size) and 3 real-scenario faults x 2 solutions (30 s runs, fault from 12 s). Every row
carries its pass figure (see the experiment's docstring); the test requires every row to
pass, plus content checks that are physics, not files:

* blunder detection: the three sizes are 4 / 5 / 6 innovation sigma, whose theoretical rates
  0.761 / 0.956 / 0.9966 sit inside each row's 99 % binomial interval (false-failure rate of
  each check <= 1 %; the seeds are fixed);
* clock jump (1 ms = 299 792.458 m on every pseudorange of c1.1): pseudoranges used again
  within 1 s, the baseline at the metre level (absorbed it would be ~1e5 m);
* 50 m pseudorange blunders (>= 5 innovation sigma): >= 0.956 rejected; every rejection a
  true one up to the alpha = 0.001 false-alarm expectation (a few on ~4000 clean tests: <= 20);
* 5 s GNSS outage of everyone: seen at its first epoch, recovered within 5 s of its end.
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _load():
    spec = importlib.util.spec_from_file_location("fault_campaign", ROOT / "experiments" / "fault_campaign.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.sumo
def test_fault_campaign_quick(tmp_path):
    mod = _load()
    assert mod.main(["--quick", "--out", str(tmp_path)]) == 0
    table = pd.read_csv(tmp_path / "fault_campaign.csv")
    assert (tmp_path / "fault_campaign.png").stat().st_size > 10_000
    md = (tmp_path / "fault_campaign.md").read_text()
    assert "| fault |" in md and "0 failing" in md
    assert (table["pass"] == "PASS").all(), table.loc[table["pass"] != "PASS", ["fault", "solution", "measured"]]
    real = table[table["world"] == "real"]
    assert set(real["fault"]) == {"clock_jump", "pr_blunder", "gnss_outage"}
    assert set(real["solution"]) == {"GPS", "GPS+UWB+Bearing"}
    model = table[table["world"] == "model"].set_index("fault")
    for b, p in ((4, 0.761), (5, 0.956), (6, 0.9966)):
        figure = model.loc[f"pr_blunder {b} innov. sigma", "figure"]
        assert float(figure.split("P_D = ")[1].split(",")[0]) == pytest.approx(p, abs=1e-3)
    by = {(r.fault, r.solution): r for r in real.itertuples()}
    for sol in ("GPS", "GPS+UWB+Bearing"):
        cj = by["clock_jump", sol]
        assert cj.detected == "y" and cj.latency_s <= 1.0 and cj.injected > 0
        assert cj.max_along_fault_m < 3.0 and cj.max_across_fault_m < 3.0
        pb = by["pr_blunder", sol]
        assert pb.det_frac >= 0.956 and pb.false_rej <= 20
        go = by["gnss_outage", sol]
        assert go.latency_s <= 0.1 + 1e-9 and np.isfinite(go.recovery_s) and go.recovery_s <= 5.0


@pytest.mark.slow
@pytest.mark.sumo
def test_fault_campaign_full(tmp_path):
    """Every fault kind, 3000 blunder trials per size, clean runs with multipath on and off:
    every row passes its figure (measured: 41 rows, all PASS; ~9 min wall on a shared 2-core box)."""
    mod = _load()
    assert mod.main(["--out", str(tmp_path)]) == 0
    table = pd.read_csv(tmp_path / "fault_campaign.csv")
    assert set(table.loc[table["world"] == "real", "fault"]) >= set(mod.FAULTS)
    assert (table["pass"] == "PASS").all(), table.loc[table["pass"] != "PASS", ["fault", "solution", "measured"]]
