"""End to end on the real components: libsumo, netconvert-built net, pyarrow Parquet, rerun .rrd."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from v2v.config.scenario import load_scenario
from v2v.errors import UserError
from v2v.frames import ecef_to_enu, enu_to_lead_frame
from v2v.run import run_scenario

pytestmark = pytest.mark.sumo

SHORT = [
    "duration_s=8.0",
    'solutions=[{name="GPS", sensors=["gnss"]}, {name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]',
]
VOLATILE = {"wall_s", "real_time_factor", "timing_s"}


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs") / "short"
    res = run_scenario(load_scenario(None, SHORT), out, quiet=True, replay=True, save_measurements=True)
    return out, res.summary


def test_nees_and_lead_frame_sigmas_follow_from_the_epoch_rows(short_run):
    """epochs.parquet carries the whole ENU position covariance (ee, en, nn, eu, nu, uu), so a
    user can recompute each row's position NEES, e^T C^-1 e with e = est - true (ENU at the lead),
    and its along/across sigmas, C rotated into the lead's frame by its azimuth from
    truth.parquet (along = (sin az, cos az, 0), left = (-cos az, sin az, 0)). (Without eu and nu
    the NEES could not be recomputed: the up axis correlates with the horizontal ones.)"""
    out, _ = short_run
    ep = pd.read_parquet(out / "epochs.parquet")
    ep = ep[ep.initialized]
    lead = pd.read_parquet(out / "truth.parquet").query("is_lead")[["t_s", "azimuth_rad"]]
    ep = ep.merge(lead, on="t_s", how="left", validate="many_to_one")
    assert len(ep) > 100 and ep.azimuth_rad.notna().all()
    c = np.stack([np.stack([ep.cov_ee_m2, ep.cov_en_m2, ep.cov_eu_m2], -1),
                  np.stack([ep.cov_en_m2, ep.cov_nn_m2, ep.cov_nu_m2], -1),
                  np.stack([ep.cov_eu_m2, ep.cov_nu_m2, ep.cov_uu_m2], -1)], 1)
    e = ep[["est_e_m", "est_n_m", "est_u_m"]].to_numpy() - ep[["true_e_m", "true_n_m", "true_u_m"]].to_numpy()
    nees = np.einsum("ki,ki->k", e, np.linalg.solve(c, e[..., None])[..., 0])
    np.testing.assert_allclose(nees, ep.nees_pos, rtol=1e-9)
    az = ep.azimuth_rad.to_numpy()
    along = np.stack([np.sin(az), np.cos(az), np.zeros_like(az)], -1)
    left = np.stack([-np.cos(az), np.sin(az), np.zeros_like(az)], -1)
    np.testing.assert_allclose(np.sqrt(np.einsum("ki,kij,kj->k", along, c, along)), ep.sigma_along_m, rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(np.einsum("ki,kij,kj->k", left, c, left)), ep.sigma_across_m, rtol=1e-9)
    np.testing.assert_allclose(np.sqrt(ep.cov_uu_m2), ep.sigma_up_m, rtol=1e-12)


def test_run_folder_contents(short_run):
    out, summary = short_run
    names = sorted(p.name for p in out.iterdir())
    assert names == ["epochs.parquet", "measurements.parquet", "replay.rrd", "scenario.resolved.toml", "summary.json", "truth.parquet"]
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["scenario"] == "default" and on_disk["seed"] == 7
    assert on_disk["simulated_s"] == pytest.approx(8.0)
    assert set(on_disk["statistics"]) == {"GPS", "GPS+UWB+Bearing"}
    # the resolved scenario reproduces the run's configuration
    again = load_scenario(out / "scenario.resolved.toml")
    assert again == load_scenario(None, SHORT)



def test_readme_names_every_summary_key_and_filter_counter(short_run):
    """The README's key list is the reference for code that reads ``summary.json``: every
    top-level key a run writes, and every counter name the filter can write, is named there."""
    import re
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    _, summary = short_run
    missing = [k for k in [*summary, "note"] if f"`{k}`" not in readme]
    assert not missing, f"summary.json keys not in the README: {missing}"
    src = "\n".join(p.read_text() for p in (root / "v2v" / "estimation").glob("*.py"))
    names = set(re.findall(r'_count\(f?"([a-z_{}]+)"', src))
    names |= set(re.findall(r'counters\[\s*"([a-z_]+)"\s*\]', src))
    assert len(names) >= 15  # the regexes still find the counters
    documented = {n.replace("{kind}", "<kind>") for n in names}
    missing = sorted(n for n in documented if f"`{n}`" not in readme)
    assert not missing, f"filter counters not in the README: {missing}"


def _readme_column_names(text: str) -> tuple[set[str], list[str]]:
    """The column names a README text gives in backticks: plain names (several to a pair of
    backticks, space-separated), ``true_e/n/u_m`` expanded to ``true_e_m true_n_m true_u_m``,
    and the patterns ``ecef_*_m`` / ``err_<component>_m`` as regular expressions."""
    import re

    names, patterns = set(), []
    for token in re.findall(r"`([^`]+)`", text):
        for part in token.split():
            if "*" in part or "<" in part:
                patterns.append("^" + "[a-z_]+".join(re.escape(x) for x in re.split(r"\*|<[a-z]+>", part)) + "$")
            elif "/" in part:
                pieces = part.split("/")
                prefix = pieces[0][: pieces[0].rindex("_") + 1]
                suffix = pieces[-1][pieces[-1].index("_"):]
                alts = [pieces[0][len(prefix):], *pieces[1:-1], pieces[-1][: -len(suffix)]]
                names |= {prefix + a + suffix for a in alts}
            else:
                names.add(part)
    return names, patterns


def test_readme_names_every_column_of_the_tables(short_run):
    """README, Outputs: every column truth.parquet, epochs.parquet and measurements.parquet hold
    is named in the table's row of its file (the reference for code that reads them)."""
    import re
    from pathlib import Path

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    rows = {line.split("|")[1].strip(" `"): line for line in readme.splitlines() if line.startswith("| `")}
    out, _ = short_run
    for name in ("truth.parquet", "epochs.parquet", "measurements.parquet"):
        names, patterns = _readme_column_names(rows[name])
        assert {"t_s", "vehicle"} <= names and (name != "measurements.parquet" or patterns)
        columns = pd.read_parquet(out / name).columns
        missing = [c for c in columns if c not in names and not any(re.match(p, c) for p in patterns)]
        assert not missing, f"{name}: columns not in the README: {missing}"


def test_stage_timings_are_disjoint_and_the_replay_has_its_own(short_run, tmp_path):
    """summary.json's stages are disjoint parts of the wall time (their sum cannot exceed it;
    measurements_io, with --save-measurements, is the part of metrics_io that writes them),
    and the replay's work (its own stage, plus truth / links / sky) is zero without a replay."""
    _, summary = short_run
    t = summary["timing_s"]
    assert {"traffic", "gnss", "uwb", "bearing", "occlusion", "estimation", "replay", "replay_static_truth", "metrics_io"} <= set(t)
    assert all(v >= 0.0 for v in t.values())
    assert t["measurements_io"] <= t["metrics_io"]
    assert sum(v for k, v in t.items() if k != "measurements_io") <= summary["wall_s"]
    assert t["replay"] > 0.0 and t["replay_static_truth"] > 0.0
    off = run_scenario(load_scenario(None, SHORT[:1]), tmp_path / "off", quiet=True, replay=False).summary["timing_s"]
    assert off["replay"] == 0.0 and off["replay_static_truth"] == 0.0  # (not timed without a replay)
    assert sum(off.values()) > 0.0


def _slowed(monkeypatch, owner, name: str, seconds: float) -> list[int]:
    """Patches the method ``owner.name`` to sleep ``seconds`` before each call; returns the
    list that gets one entry per call."""
    import time

    calls: list[int] = []
    orig = getattr(owner, name)

    def slow(self, *args, **kwargs):
        calls.append(1)
        time.sleep(seconds)
        return orig(self, *args, **kwargs)

    monkeypatch.setattr(owner, name, slow)
    return calls


def test_estimates_logging_is_timed_as_replay_not_estimation(tmp_path, monkeypatch):
    """The replay logging of each chunk's estimates runs inside the filter loop but is timed
    into the replay stage: with every log_epochs call (one per solution and chunk) slowed by
    50 ms, the replay stage holds at least calls x 50 ms, and estimation grows by well under
    that against the same run without replay."""
    from v2v.viz.rerun_logger import RerunReplayLogger

    calls = _slowed(monkeypatch, RerunReplayLogger, "log_epochs", 0.05)
    sc = load_scenario(None, ["duration_s=3.0", 'solutions=[{name="GPS", sensors=["gnss"]}]'])
    on = run_scenario(sc, tmp_path / "on", quiet=True, replay=True, chunk_s=0.5).summary["timing_s"]
    off = run_scenario(sc, tmp_path / "off", quiet=True, replay=False, chunk_s=0.5).summary["timing_s"]
    slept = 0.05 * len(calls)
    assert len(calls) >= 4  # one per chunk with estimates (0.5 s chunks of a 3 s run)
    assert on["replay"] >= slept
    assert on["estimation"] - off["estimation"] < 0.5 * slept


def test_occlusion_tests_are_their_own_stage(tmp_path, monkeypatch):
    """The sensors' line-of-sight tests (satellite rays, UWB and bearing links) are timed into
    the ``occlusion`` stage and out of gnss / uwb / bearing: with every building test inside
    them slowed, the occlusion stage holds at least the time slept, and the three sensor
    stages together grow by well under that against the same run at full speed (20 ms per
    call: far above the run-to-run spread of those stages, ~25 ms in all here)."""
    from v2v.world.occlusion import OcclusionGeometry

    sc = load_scenario(None, ["duration_s=4.0", 'solutions=[{name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]'])
    fast = run_scenario(sc, tmp_path / "fast", quiet=True, replay=False).summary["timing_s"]
    calls = _slowed(monkeypatch, OcclusionGeometry, "_building_hits", 0.02)
    t = run_scenario(sc, tmp_path / "slow", quiet=True, replay=False).summary["timing_s"]
    slept = 0.02 * len(calls)
    assert len(calls) >= 3  # at least one per sensor: satellite rays, UWB links, bearing links
    assert t["occlusion"] >= slept
    sensors = ("gnss", "uwb", "bearing")
    assert sum(t[k] for k in sensors) - sum(fast[k] for k in sensors) < 0.5 * slept


def test_epochs_table_is_consistent_with_truth(short_run):
    out, _ = short_run
    ep = pd.read_parquet(out / "epochs.parquet")
    truth = pd.read_parquet(out / "truth.parquet")
    # one row per (epoch, solution, non-lead vehicle): 10 Hz over 8 s -> 81 epochs, 2 solutions, 2 vehicles
    assert len(ep) == 81 * 2 * 2
    assert set(ep["vehicle"]) == {"c1.1", "c1.2"}
    # true relative ENU recomputed from truth.parquet ECEF at the lead
    t = ep["t_s"].iloc[-1]
    lead = truth[(truth.t_s == t) & (truth.vehicle == "c1.0")].iloc[0]
    veh = truth[(truth.t_s == t) & (truth.vehicle == "c1.1")].iloc[0]
    rel = ecef_to_enu(veh[["ecef_x_m", "ecef_y_m", "ecef_z_m"]].to_numpy(float), np.radians(lead.lat_deg),
                      np.radians(lead.lon_deg), lead[["ecef_x_m", "ecef_y_m", "ecef_z_m"]].to_numpy(float))
    row = ep[(ep.t_s == t) & (ep.vehicle == "c1.1")].iloc[0]
    np.testing.assert_allclose(row[["true_e_m", "true_n_m", "true_u_m"]].to_numpy(float), rel, atol=1e-6)
    _assert_true_relative_velocity(ep, truth.set_index(["t_s", "vehicle"]), "c1.0")
    err = enu_to_lead_frame(row[["est_e_m", "est_n_m", "est_u_m"]].to_numpy(float) - rel, lead.azimuth_rad)
    np.testing.assert_allclose(row[["along_err_m", "across_err_m", "up_err_m"]].to_numpy(float), err, atol=1e-9)
    ok = ep[ep.initialized]
    assert len(ok) > 0.9 * len(ep)
    assert np.isfinite(ok[["est_e_m", "est_n_m", "sigma_along_m", "sigma_across_m"]].to_numpy()).all()
    assert (ok[["sigma_along_m", "sigma_across_m", "sigma_up_m"]] > 0).all().all()


def _assert_true_relative_velocity(ep, truth, lead: str) -> None:
    """``true_ve/vn/vu_mps`` of every row of ``ep`` against truth.parquet with pymap3d: each
    vehicle's ``vel_e/n/u_mps`` (ENU at its own position) to ECEF, minus the lead's, to ENU at
    the lead. The frames of vehicles tens of metres apart turn ~5 urad apart, ~1e-4 m/s at
    these speeds, so the former ENU difference fails the 1e-9 m/s tolerance (which is the
    rounding of lat/lon through degrees and the parquet)."""
    import pymap3d

    vel, ll = ["vel_e_mps", "vel_n_mps", "vel_u_mps"], ["lat_deg", "lon_deg"]
    veh = truth.loc[list(zip(ep.t_s, ep.vehicle, strict=True))]
    lead = truth.loc[list(zip(ep.t_s, [lead] * len(ep), strict=True))]
    d = (np.array(pymap3d.enu2ecefv(*veh[vel].to_numpy(float).T, *veh[ll].to_numpy(float).T))
         - np.array(pymap3d.enu2ecefv(*lead[vel].to_numpy(float).T, *lead[ll].to_numpy(float).T)))
    ref = np.array(pymap3d.ecef2enuv(*d, *lead[ll].to_numpy(float).T)).T
    np.testing.assert_allclose(ep[["true_ve_mps", "true_vn_mps", "true_vu_mps"]].to_numpy(float), ref, rtol=0, atol=1e-9)
    assert np.abs(veh[vel].to_numpy(float) - lead[vel].to_numpy(float) - ref).max() > 1e-6


def test_replay_has_the_run(short_run):
    from rerun.chunk import RrdReader

    out, _ = short_run
    paths = {c.entity_path for c in RrdReader(str(out / "replay.rrd")).stream()}
    assert any(p.startswith("/world/buildings") for p in paths)
    assert any(p.startswith("/world/vehicles/truth") for p in paths)
    assert any(p.startswith("/errors/GPS/c1.1/along") for p in paths)


def test_rerun_verifies_the_replay(short_run, tmp_path):
    """rerun's own loader accepts the run's recording (`rerun rrd verify`: every chunk decoded
    and every column checked against its component's arrow type, the file's footer present);
    it rejects, e.g., half sizes stored as float64 instead of 3 x float32."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun")
    assert exe is not None, "rerun-sdk's `rerun` command is missing (it ships with the pinned wheel)"
    out, _ = short_run
    p = subprocess.run([exe, "rrd", "verify", str(out / "replay.rrd")], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stdout + p.stderr
    # the check has teeth: a column of the wrong arrow type is refused
    import rerun as rr

    bad = tmp_path / "bad.rrd"
    rec = rr.RecordingStream("v2v", recording_id="bad", send_properties=False)
    rec.save(bad)
    col = rr.ComponentColumn(rr.Ellipsoids3D.descriptor_half_sizes(), rr.components.ScalarBatch(np.ones(3)))
    rec.send_columns("x", indexes=[rr.TimeColumn("sim_time", duration=np.arange(3.0))], columns=[col])
    rec.disconnect()
    p = subprocess.run([exe, "rrd", "verify", str(bad)], capture_output=True, text=True, timeout=300)
    assert p.returncode != 0 and "half_sizes" in p.stdout + p.stderr


def test_replay_error_series_are_the_epochs_table(short_run):
    """Each error series in the replay is the epochs table's column of that name (along,
    across, their sigmas (+sigma, -sigma), NEES, SD pseudoranges used, all rejections) at the
    same times, for every initialized epoch of each solution and vehicle."""
    from rerun.chunk import RrdReader

    from v2v.viz.blueprint import error_path

    out, _ = short_run
    ep = pd.read_parquet(out / "epochs.parquet")
    ep = ep[ep.initialized]
    series: dict[str, dict[float, list]] = {}
    for c in RrdReader(str(out / "replay.rrd")).stream():
        if c.is_static or not c.entity_path.startswith("/errors/"):
            continue
        rb = c.to_record_batch()
        t = rb.column("sim_time").cast("int64").to_pylist()
        v = rb.column("Scalars:scalars").to_pylist()
        series.setdefault(c.entity_path, {}).update({round(ns * 1e-9, 6): x for ns, x in zip(t, v, strict=True)})
    rejected = ep[["rejected_pr", "rejected_uwb", "rejected_bearing", "rejected_doppler"]].sum(axis=1)
    expected = {"along": ep.along_err_m, "across": ep.across_err_m, "nees": ep.nees_pos, "n_sats": ep.used_pr,
                "rejections": rejected}
    for (sol, veh), g in ep.groupby(["solution", "vehicle"]):
        times = g.t_s.round(6)
        for name, col in expected.items():
            got = series[error_path(sol, veh, name)]
            assert [got[t] for t in times] == [[float(x)] for x in col[g.index]], (sol, veh, name)
        for name, col in (("along_sigma", g.sigma_along_m), ("across_sigma", g.sigma_across_m)):
            got = series[error_path(sol, veh, name)]
            assert [got[t] for t in times] == [[float(x), -float(x)] for x in col], (sol, veh, name)


def _tables(out):
    return {n: pd.read_parquet(out / n) for n in ("truth.parquet", "epochs.parquet", "measurements.parquet")}


def test_same_seed_bit_identical_outputs(short_run, tmp_path):
    out, summary = short_run
    out2 = tmp_path / "again"
    res2 = run_scenario(load_scenario(None, SHORT), out2, quiet=True, replay=False, save_measurements=True)
    a, b = _tables(out), _tables(out2)
    for name in a:
        pd.testing.assert_frame_equal(a[name], b[name], check_exact=True)
    strip = lambda s: {k: v for k, v in s.items() if k not in VOLATILE}  # noqa: E731
    assert json.dumps(strip(summary), default=str) == json.dumps(strip(res2.summary), default=str)


def test_saving_measurements_does_not_change_the_estimates(tmp_path):
    """``--save-measurements`` only adds a file: the epochs and truth are those of the same run
    without it (README, Conventions: same seed, same outputs), also when it synthesizes the
    UWB ranges and bearings of sensors no solution uses and the V2V link loses and delays
    messages (the exchange draws a loss and a latency per message it carries)."""
    sets = ["duration_s=8.0", 'solutions=[{name="GPS", sensors=["gnss"]}]', "exchange.loss_probability=0.3",
            "exchange.latency_s=0.05"]
    off = run_scenario(load_scenario(None, sets), tmp_path / "off", quiet=True, replay=False)
    on = run_scenario(load_scenario(None, sets), tmp_path / "on", quiet=True, replay=False, save_measurements=True)
    types = set(pd.read_parquet(tmp_path / "on" / "measurements.parquet")["type"])
    assert {"pseudorange", "uwb", "bearing"} <= types  # the file has the sensors no solution uses
    for name in ("epochs.parquet", "truth.parquet"):
        pd.testing.assert_frame_equal(pd.read_parquet(tmp_path / "off" / name), pd.read_parquet(tmp_path / "on" / name),
                                      check_exact=True)
    assert on.summary["exchange"] == off.summary["exchange"]  # only GNSS messages on the link either way
    assert on.summary["statistics"] == off.summary["statistics"]


def test_disabled_gnss_reports_no_pseudoranges(tmp_path):
    """``sensors.gnss.enabled = false`` (possible only without a solution: every solution uses
    GNSS) means no such measurements (README, the scenario's fields): a UWB / bearing data set
    with ``--save-measurements`` has no pseudorange row and the summary counts no GNSS epoch,
    while the other sensors are those of the same run with GNSS on (their own seed streams)."""
    sets = ["duration_s=4.0", "solutions=[]"]
    off = run_scenario(load_scenario(None, [*sets, "sensors.gnss.enabled=false"]), tmp_path / "off", quiet=True,
                       replay=False, save_measurements=True)
    run_scenario(load_scenario(None, sets), tmp_path / "on", quiet=True, replay=False, save_measurements=True)
    m_off = pd.read_parquet(tmp_path / "off" / "measurements.parquet")
    m_on = pd.read_parquet(tmp_path / "on" / "measurements.parquet")
    assert set(m_off["type"]) == {"uwb", "bearing"} and "pseudorange" in set(m_on["type"])
    assert off.summary["gnss"]["epochs"] == 0
    pd.testing.assert_frame_equal(m_off.reset_index(drop=True)[["t_s", "type", "vehicle", "value"]],
                                  m_on[m_on["type"] != "pseudorange"].reset_index(drop=True)[["t_s", "type", "vehicle", "value"]],
                                  check_exact=True)


def test_other_seed_changes_measurements(short_run, tmp_path):
    out, _ = short_run
    out3 = tmp_path / "seed8"
    run_scenario(load_scenario(None, [*SHORT, "seed=8", "solutions=[]"]), out3, quiet=True, replay=False, save_measurements=True)
    m1 = pd.read_parquet(out / "measurements.parquet")
    m3 = pd.read_parquet(out3 / "measurements.parquet")
    assert not m1["value"].equals(m3["value"])
    # the sensors' own noise follows the seed, not only the traffic: the pseudorange noise of the
    # same (time, receiver, satellite) in the two runs is uncorrelated. Independent draws give a
    # sample correlation ~ N(0, 1/n); |r| < 4 / sqrt(n) fails with probability 6e-5.
    key = ["t_s", "vehicle", "prn"]
    pr = [m[m["type"] == "pseudorange"].set_index(key)["err_noise_m"] for m in (m1, m3)]
    both = pd.concat(pr, axis=1, join="inner").dropna()
    n = len(both)
    assert n > 500
    r = np.corrcoef(both.iloc[:, 0], both.iloc[:, 1])[0, 1]
    assert abs(r) < 4 / np.sqrt(n), (r, n)
    # no solution: the epochs table is still there, without rows, with the columns of the one above
    e1, e3 = pd.read_parquet(out / "epochs.parquet"), pd.read_parquet(out3 / "epochs.parquet")
    assert len(e3) == 0 and set(e3.columns) <= set(e1.columns) and {"along_err_m", "cluster", "nees_pos"} <= set(e3.columns)
    assert dict(e3.dtypes) == {c: e1.dtypes[c] for c in e3.columns}


def test_injected_error_columns_are_zero_where_no_fault_acted_and_the_components_add_up(tmp_path):
    """A pseudorange blunder on one vehicle in a window and a clock jump on another: their
    columns, err_fault_m and err_clock_jump_m, are 0 on every other pseudorange row (they were NaN
    there), so on every pseudorange and UWB row the err_* components add up to value - true_value
    (the README's rule), and only bearing rows, where no component applies, have them NaN."""
    sc = load_scenario(None, ["duration_s=6.0", 'solutions=[{name="G", sensors=["gnss"]}]',
                              'faults=[{kind="pr_blunder", start_s=2.0, duration_s=2.0, size_m=40.0, vehicles=["c1.1"]},'
                              ' {kind="clock_jump", start_s=3.0, vehicles=["c1.2"]}]'])
    run_scenario(sc, tmp_path / "r", quiet=True, replay=False, save_measurements=True)
    m = pd.read_parquet(tmp_path / "r" / "measurements.parquet")
    pr = m[m.type == "pseudorange"]
    hit = (pr.vehicle == "c1.1") & (pr.t_s >= 2.0 - 1e-9) & (pr.t_s < 4.0 - 1e-9)
    assert (pr.err_fault_m[hit] == 40.0).all() and (pr.err_fault_m[~hit] == 0.0).all()
    jumped = (pr.vehicle == "c1.2") & (pr.t_s >= 3.0 - 1e-9)
    assert (pr.err_clock_jump_m[jumped] == 299792.458).all() and (pr.err_clock_jump_m[~jumped] == 0.0).all()
    err = [c for c in m.columns if c.startswith("err_")]
    for kind in ("pseudorange", "uwb"):
        rows = m[m.type == kind]
        total = rows[err].sum(axis=1, min_count=1, skipna=True)
        np.testing.assert_allclose(total, rows.value - rows.true_value, atol=1e-6)
    assert m.loc[m.type == "bearing", ["err_fault_m", "err_clock_jump_m"]].isna().all().all()


@pytest.mark.parametrize("vehicles", ['["c1.2"]', '"all"'])
def test_a_message_loss_burst_counts_the_messages_it_dropped_and_spares_the_lead(tmp_path, vehicles):
    """The messages a message_loss burst drops are the ones its run did not send: faults_injected
    counts exactly the difference of exchange.sent against the same run without it (it counted
    nothing, and the run's note called the fault idle). The lead's own measurements reach its
    filter on board, not over a V2V link: with vehicles = "all" they are not dropped (they were,
    and the filter lost every GNSS epoch), so the count is still the difference."""
    base = ["duration_s=12.0", 'solutions=[{name="G", sensors=["gnss", "uwb", "bearing"]}]']
    clean = run_scenario(load_scenario(None, base), tmp_path / "a", quiet=True, replay=False).summary
    sc = load_scenario(None, [*base, f'faults=[{{kind="message_loss", start_s=4.0, duration_s=3.0, vehicles={vehicles}}}]'])
    hit = run_scenario(sc, tmp_path / "b", quiet=True, replay=False).summary
    n = hit["faults_injected"]["0:message_loss"]
    assert n > 0 and n == clean["exchange"]["sent"] - hit["exchange"]["sent"]
    assert "changed no measurement" not in hit.get("note", "")
    ep = pd.read_parquet(tmp_path / "b" / "epochs.parquet")
    window = ep[(ep.t_s > 4.5) & (ep.t_s < 6.9)]
    assert (window.groupby("vehicle").used_pr.sum() == 0).all() == (vehicles == '"all"')  # (c1.1 still heard)
    assert window[window.vehicle == "c1.2"].used_pr.sum() == 0


def test_vehicle_leaving_and_rejoining_the_cluster(tmp_path):
    """A vehicle that leaves (no GNSS, UWB, bearing or message for 15 s) is dropped from the
    filter after LEAVE_AFTER_S of silence and re-initialized from its first GNSS epoch back."""
    from v2v.pipeline import LEAVE_AFTER_S

    sc = load_scenario(None, [
        "duration_s=45.0", 'solutions=[{name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]',
        'faults=[{kind="vehicle_leaves", start_s=15.0, duration_s=15.0, vehicles=["c1.2"]}]',
    ])
    run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    ep = pd.read_parquet(tmp_path / "r" / "epochs.parquet")
    v2 = ep[ep.vehicle == "c1.2"].set_index("t_s")
    gone = v2.loc[15.0 + LEAVE_AFTER_S + 0.2: 29.9]
    assert len(gone) > 0 and not gone["initialized"].any()
    back = v2.loc[31.0:]
    assert back["initialized"].all()
    # re-initialized from a GNSS snapshot and then filtered: decimetre-level again
    assert back["across_err_m"].abs().max() < 1.0
    # the other follower never left
    assert ep[ep.vehicle == "c1.1"]["initialized"].iloc[20:].all()
    # README (Outputs): a row with initialized False has the truth only. While the vehicle is out of
    # the filter its rows keep the truth (relative ENU at the lead, from truth.parquet's ECEF), its
    # lanes, no update and no integrity, and the table keeps its types: whole counts, flags as bool
    truth = pd.read_parquet(tmp_path / "r" / "truth.parquet").set_index(["t_s", "vehicle"])
    for t, row in gone.iloc[[0, -1]].iterrows():
        lead, veh = truth.loc[(t, "c1.0")], truth.loc[(t, "c1.2")]
        ecef = ["ecef_x_m", "ecef_y_m", "ecef_z_m"]
        rel = ecef_to_enu(veh[ecef].to_numpy(float), np.radians(lead.lat_deg), np.radians(lead.lon_deg),
                          lead[ecef].to_numpy(float))
        np.testing.assert_allclose(row[["true_e_m", "true_n_m", "true_u_m"]].to_numpy(float), rel, atol=1e-6)
        assert row["true_lane_index"] == veh.lane_index and row["lane_width_m"] == veh.lane_width_m
    _assert_true_relative_velocity(gone.reset_index(), truth, "c1.0")  # (the rows of vehicles out of the filter)
    assert gone[["est_e_m", "along_err_m", "sigma_along_m", "cov_ee_m2", "nees_pos"]].isna().all().all()
    assert (gone.filter(regex="^(used|rejected)_").to_numpy() == 0).all() and not gone["integrity_available"].any()
    assert ep.dtypes["integrity_available"] == np.bool_ and ep.dtypes["initialized"] == np.bool_
    ints = ["true_lane_index", "lead_lane_index", *ep.filter(regex="^(used|rejected)_").columns]
    assert all(ep.dtypes[c] == np.int64 for c in ints), ep.dtypes[ints]


def test_gnss_outage_height_aiding_on_and_off(tmp_path):
    """A 4 s GNSS outage of everyone, GPS+UWB with height aiding (the default) and without.

    * Aided: "relative up = 0 +- 1 m" once per output interval bounds the vertical sigma: an
      update with R = 1 m^2 leaves sigma_up <= 1 m, and the next 0.1 s prediction integrates
      the vertical velocity, whose Gauss-Markov sigma is 1 m/s: sigma_up <= 1 m + 1 m/s * 0.1 s
      (Cauchy-Schwarz on the position-velocity cross term; the driving noise's own share of
      position variance over 0.1 s is ~1e-4 m^2).
    * Off: nothing measures height, so its sigma only grows, epoch after epoch.
    * Either way no vehicle has integrity in an epoch without GNSS (no screen ran).
    """
    sc = load_scenario(None, [
        'network.name="open_highway"', "clusters.0.vehicles=2", "duration_s=12.0",
        'faults=[{kind="gnss_outage", start_s=4.0, duration_s=4.0}]',
        'solutions=[{name="aided", sensors=["gnss","uwb"]},'
        ' {name="free", sensors=["gnss","uwb"], height_aiding=false}]',
    ])
    assert sc.solutions[0].height_aiding and not sc.solutions[1].height_aiding
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    ep = pd.read_parquet(tmp_path / "r" / "epochs.parquet")
    out = ep[(ep.t_s > 4.05) & (ep.t_s < 7.95)]
    aided, free = (out[out.solution == s].set_index("t_s") for s in ("aided", "free"))
    assert len(aided) == len(free) > 30
    assert (aided.used_pr == 0).all() and not out.integrity_available.any()
    assert aided.sigma_up_m.max() <= 1.1
    assert (np.diff(free.sigma_up_m.to_numpy()) > 0).all()
    meas = res.summary["statistics"]
    assert meas["aided"]["measurements"]["height_aiding"]["used"] > 0
    assert "height_aiding" not in meas["free"]["measurements"]
    # the resolved scenario keeps it off (TOML has no null: the switch is a boolean)
    again = load_scenario(tmp_path / "r" / "scenario.resolved.toml")
    assert [s.height_aiding for s in again.solutions] == [True, False]


def test_height_aiding_uses_the_antenna_height_difference(tmp_path):
    """A truck between two cars (antennas 3.9 m and 1.55 m above the road: the truck's is
    2.35 m higher on this flat highway) through a 6 s GNSS outage, GPS+UWB+Bearing. The
    height aiding's pseudo-measurement is "relative up = h_v - h_lead" (MacGougan (2009)
    section 5's height constraint with the known installation heights), so the truck's
    vertical error stays inside 3 sigma at every outage epoch, as a consistent filter's
    must at the 99.7 % level (the error is 0.00 m measured). "Relative up = 0" would pass
    the innovation test (2.35 m < 3.29 x 1 m) and force the truck down: -2.35 m at
    sigma 0.44 m measured before."""
    sc = load_scenario(None, [
        'network.name="open_highway"', "clusters.0.vehicles=3", "duration_s=16.0",
        'clusters.0.vehicle_type=["passenger", "truck", "passenger"]',
        'faults=[{kind="gnss_outage", start_s=8.0, duration_s=6.0}]',
        'solutions=[{name="GPS+UWB+Bearing", sensors=["gnss","uwb","bearing"]}]',
    ])
    run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    ep = pd.read_parquet(tmp_path / "r" / "epochs.parquet")
    truck = ep[(ep.vehicle == "c1.1") & (ep.t_s > 8.05) & (ep.t_s < 13.95)]
    assert len(truck) > 50 and (truck.used_pr == 0).all()
    assert truck.true_u_m.between(2.3, 2.4).all()  # 3.9 - 1.55 m on the flat road
    assert (truck.up_err_m.abs() <= 3 * truck.sigma_up_m).all(), truck.up_err_m.abs().max()


def test_uwb_constraints_from_the_scenario(tmp_path):
    """``uwb_constraints = true`` switches on the thesis's inequality constraints (eq. 3.19-3.22)
    of the UWB bias / scale states. Bounds tighter than the world's pair biases (+-1 cm
    here; the built-in radios' fixed and oscillator biases are decimetres) must be hit, so
    pulls onto them appear as ``uwb_constraint`` updates, without a NIS (not measurements);
    the same solution without constraints has none. Constraints without error states are
    refused with the field named."""
    common = 'sensors=["gnss","uwb"], uwb_error_states=true'
    sc = load_scenario(None, [
        'network.name="open_highway"', "clusters.0.vehicles=3", "duration_s=15.0",
        f'solutions=[{{name="free", {common}}}, {{name="bounded", {common}, uwb_constraints=true,'
        ' uwb_bias_bounds_m=[-0.01, 0.01]}]',
    ])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    meas = res.summary["statistics"]
    assert "uwb_constraint" not in meas["free"]["measurements"]
    pulls = meas["bounded"]["measurements"]["uwb_constraint"]
    assert pulls["used"] > 0 and np.isnan(pulls["nis_mean_clean"])
    with pytest.raises(UserError, match="uwb_error_states"):
        load_scenario(None, ['solutions=[{name="x", sensors=["gnss","uwb"], uwb_constraints=true}]'])


def test_gnss_min_satellites_leaves_weak_gnss_out(tmp_path):
    """``gnss_min_satellites``: a vehicle with fewer satellites in common with the lead leaves
    its GNSS out of the epoch, as in an outage. With the threshold at the whole nominal
    constellation (27, which no place sees at once; the largest value the scenario accepts with
    that sky) every
    follower is initialized from its first epochs (initialization is not affected) and then
    uses no pseudorange, counted per vehicle-epoch, while height aiding bounds its vertical
    (sigma_up <= 1 m + 1 m/s x 0.1 s, the outage test's bound) and UWB and bearings carry the
    horizontal (every epoch has an estimate). The same solution with 0 uses them."""
    sc = load_scenario(None, [
        'network.name="open_highway"', "clusters.0.vehicles=3", "duration_s=8.0",
        'solutions=[{name="all", sensors=["gnss","uwb","bearing"]},'
        ' {name="none", sensors=["gnss","uwb","bearing"], gnss_min_satellites=27}]',
    ])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    ep = pd.read_parquet(tmp_path / "r" / "epochs.parquet")
    late = ep[ep.t_s > 1.0]
    none, every = (late[late.solution == s] for s in ("none", "all"))
    assert (none.used_pr == 0).all() and (every.used_pr >= 4).all()
    assert none.initialized.all() and none.sigma_up_m.max() <= 1.1
    assert res.summary["filter_counters"]["none"]["gnss_too_few_satellites"] >= 2 * 70  # 2 followers, 10 Hz
    assert "gnss_too_few_satellites" not in res.summary["filter_counters"]["all"]


def test_cn0_mask_above_every_echo_leaves_no_echo_in_the_filter(tmp_path):
    """An echo arrives ``echo_loss_db`` (8 dB) below its direct signal, whose C/N0 is at most
    the zenith's 49 dB-Hz, so no echo is stronger than 41 dB-Hz. In the residential streets
    (houses reflect) the unmasked solution uses echo-only SD pseudoranges and Dopplers that
    its innovation test lets through; with ``gnss_cn0_mask_dbhz = 41`` (an echo reaches exactly
    41 only from a satellite at 90 deg elevation) the same run offers the filter none (faulty = 0 for every SD kind) and it still estimates every epoch. A
    user's mask outside [0, 60] dB-Hz is a one-line error naming the field."""
    sc = load_scenario(None, [
        'network.name="residential"', "clusters.0.vehicles=3", "duration_s=15.0",
        'solutions=[{name="all", sensors=["gnss","uwb","bearing"]},'
        ' {name="masked", sensors=["gnss","uwb","bearing"], gnss_cn0_mask_dbhz=41}]',
    ])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    stats = res.summary["statistics"]
    every, masked = stats["all"]["measurements"], stats["masked"]["measurements"]
    assert every["sd_pseudorange"]["faulty"] > 0 and every["sd_pseudorange"]["missed_faults"] > 0
    sd_kinds = [k for k in masked if k.startswith("sd_")]
    assert "sd_pseudorange" in sd_kinds and all(masked[k]["faulty"] == 0 for k in sd_kinds)
    assert masked["sd_pseudorange"]["used"] > 0
    assert all(v["availability"] == 1.0 for v in stats["masked"]["vehicles"].values())
    assert res.summary["filter_counters"]["masked"]["gnss_cn0_masked"] > 0
    assert "gnss_cn0_masked" not in res.summary["filter_counters"]["all"]
    with pytest.raises(UserError, match="gnss_cn0_mask_dbhz"):
        load_scenario(None, ['solutions=[{name="x", sensors=["gnss"], gnss_cn0_mask_dbhz=-3}]'])


def test_height_aiding_sigma_none_means_off():
    """From Python, ``height_aiding_sigma_m=None`` (the filter's own "off") is the same as
    ``height_aiding=False``, and it survives the resolved-TOML round trip."""
    from v2v.config.sections import SolutionSection

    sol = SolutionSection(name="x", sensors=["gnss"], height_aiding_sigma_m=None)
    assert sol.height_aiding is False and sol.height_aiding_sigma is None
    assert SolutionSection(name="x", sensors=["gnss"]).height_aiding_sigma == 1.0


@pytest.mark.parametrize(("sets", "cause"), [
    # no GPS satellite within 1 deg of the zenith over Calgary at the default start: nothing to start a filter from
    (["sensors.gnss.elevation_mask_deg=89"], "tracked 0.0 satellites on average (sensors.gnss.elevation_mask_deg = 89"),
    # the followers' epochs never reach the lead
    (["exchange.loss_probability=1.0"], "every V2V message was lost (exchange.loss_probability = 1)"),
])
def test_a_run_that_estimates_nothing_says_why(tmp_path, sets, cause):
    """A run whose filters never start (every availability 0) ends with a note naming the
    cause, in summary.json and on the console, instead of a silent table of NaN; a run that
    estimates has no such note (the default scenario: ``short_run``)."""
    sc = load_scenario(None, ["duration_s=3.0", 'solutions=[{name="GPS", sensors=["gnss"]}]', *sets])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    avail = [v["availability"] for v in res.summary["statistics"]["GPS"]["vehicles"].values()]
    assert avail and not any(avail)
    note = res.summary["note"]
    assert note.startswith("no solution estimated any vehicle") and cause in note
    assert json.loads((tmp_path / "r" / "summary.json").read_text())["note"] == note


def test_messages_the_filter_has_passed_are_noted(tmp_path):
    """latency 0.5 s with the filter not waiting (filter_lag_s = 0): every follower message
    arrives after its time tag was processed and is dropped as late; the run says so."""
    sc = load_scenario(None, ["duration_s=3.0", 'solutions=[{name="GPS", sensors=["gnss"]}]',
                              "exchange.latency_s=0.5", "exchange.filter_lag_s=0.0"])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    ex = res.summary["exchange"]
    assert ex["late"] > 0.5 * (ex["sent"] - ex["lost"])
    assert f"{ex['late']} of the {ex['sent'] - ex['lost']} V2V messages not lost arrived after" in res.summary["note"]


def test_a_solution_whose_sensor_measured_nothing_is_noted(tmp_path):
    """No vehicle measures bearings (sensors.bearing.measuring = []): the bearing solution runs
    on GNSS alone, and the note says it had no bearings to use."""
    sc = load_scenario(None, ["duration_s=2.0", 'solutions=[{name="GPS+B", sensors=["gnss","bearing"]}]',
                              "sensors.bearing.measuring=[]"])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    assert res.summary["bearing"]["measurements"] == 0
    assert "the run measured no bearings" in res.summary["note"] and "GPS+B had none to use" in res.summary["note"]


def test_an_overconfident_filter_is_noted(tmp_path):
    """The filter told its pseudoranges are good to 5 cm (the world's SD code errors are
    decimetres to metres): its covariance shrinks far below its errors and the position NEES,
    chi-square with 3 dof if the filter were right (mean 3), averages in the hundreds. The run
    says so, worst vehicle first, instead of a quiet table."""
    sc = load_scenario(None, ["duration_s=10.0", 'solutions=[{name="GPS", sensors=["gnss"], pseudorange_sigma_m=0.05}]'])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    nees = {v: s["nees_pos"]["mean"] for v, s in res.summary["statistics"]["GPS"]["vehicles"].items()}
    assert min(nees.values()) > 30.0
    worst = max(nees, key=nees.__getitem__)
    note = res.summary["note"]
    assert note.startswith("the filter is overconfident: mean position NEES above 30") and f"GPS {worst} (" in note
    assert note.index(f"GPS {worst} (") < min(note.index(f"GPS {v} (") for v in nees if v != worst)


def test_a_solution_that_resets_at_every_epoch_is_noted(tmp_path):
    """Pseudoranges assumed good to 1000 km: the snapshot that initializes a vehicle has a
    position sigma of ~1e6 m times its DOP, above divergence_position_sigma_m (1000 m), so the
    next GNSS epoch resets it again, and the next. The table's errors are then those of
    single-epoch snapshots; the run says so (the other solution, with the default 5 m, is
    never reset and not named)."""
    sc = load_scenario(None, ["duration_s=3.0", 'solutions=[{name="G", sensors=["gnss"], pseudorange_sigma_m=1e6}, '
                              '{name="G5", sensors=["gnss"]}]'])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    counters = res.summary["filter_counters"]
    epochs = sum(v["epochs"] for v in res.summary["statistics"]["G"]["vehicles"].values())
    assert counters["G"]["divergence_reset"] > 0.9 * epochs  # every epoch after the first of each vehicle
    assert counters.get("G5", {}).get("divergence_reset", 0) == 0
    note = res.summary["note"]
    assert note.startswith(f"G ({counters['G']['divergence_reset']} resets in ") and "G5" not in note
    assert "restarted its vehicles from single-epoch GNSS snapshots" in note and "1000 m" in note


def test_the_overconfidence_note_names_the_causes_the_run_knows():
    """The note names the UWB solutions without bias states among those listed (MSSI ranges
    carry decimetre biases the default filter treats as white noise: a 20-car open_highway run's
    farthest car reached mean NEES ~50) and the NLOS-only share of the GNSS signals when it is
    10 % or more."""
    from v2v.run import _overconfident, _overconfident_note

    sc = load_scenario(None, ['solutions=[{name="U", sensors=["gnss","uwb"]}, {name="Us", sensors=["gnss","uwb"], '
                              'uwb_error_states=true}, {name="G", sensors=["gnss"]}]'])
    stats = {sol: {"vehicles": {"c1.1": {"nees_pos": {"n": 10, "mean": m}}}} for sol, m in (("U", 51.0), ("Us", 40.0), ("G", 2.9))}
    over = _overconfident(stats)
    assert over == [(51.0, "U", "c1.1"), (40.0, "Us", "c1.1")]
    note = _overconfident_note(sc, over, {"nlos_fraction": 0.65})
    assert "for U c1.1 (51), Us c1.1 (40):" in note
    assert "(U leaves the UWB ranges' biases (decimetres) unestimated: uwb_error_states = true models them; " \
           "65 % of the tracked GNSS signals were NLOS-only)" in note
    assert "UWB" not in _overconfident_note(sc, [(40.0, "Us", "c1.1")], {"nlos_fraction": 0.05})


def test_a_run_that_estimates_has_no_note(short_run):
    assert "note" not in short_run[1]


def test_a_run_logged_to_a_file_reports_progress(tmp_path, monkeypatch, capsys):
    """With stderr not a terminal (pytest's capture, as a log file or CI) there is no tqdm bar;
    a run reports after its chunks instead (here after every one: 10 s chunks of a 30 s run),
    simulated time increasing, with the remaining wall time; when the kernels compile in this
    run (cache_missing, forced here) the first line says its time includes that."""
    import re

    import v2v.run as run_mod
    from v2v.estimation import kernels

    monkeypatch.setattr(run_mod, "_PROGRESS_EVERY_S", 0.0)
    sc = load_scenario(None, ["duration_s=30.0", 'solutions=[{name="GPS", sensors=["gnss"]}]'])
    for compiling in (False, True):
        monkeypatch.setattr(kernels, "cache_missing", lambda c=compiling: c)
        run_scenario(sc, tmp_path / f"r{compiling}", quiet=False, replay=False, chunk_s=10.0)
        found = [re.fullmatch(r"default: (\d+) of 30 s simulated, \d+ s wall, (this includes compiling the kernels; the time "
                              r"to go follows after the next chunk|~\d+ s to go)", ln) for ln in capsys.readouterr().err.splitlines()]
        t = [(int(m.group(1)), m.group(2).startswith("this")) for m in found if m]
        assert t == [(10, compiling), (20, False)], t  # (the last chunk ends the run: its summary follows)


def test_first_run_on_a_machine_says_the_kernels_compile(tmp_path, monkeypatch, capsys):
    """Before a run's long first-use compilation (numba, ~1 min, silent otherwise) the run says
    so; with the kernels cached it does not. ``cache_missing`` reads numba's cache: empty in a
    fresh cache folder (NUMBA_CACHE_DIR), present here once a run has compiled the kernels."""
    import os
    import subprocess
    import sys

    from v2v.estimation import kernels

    sc = load_scenario(None, ["duration_s=1.0", 'solutions=[{name="GPS", sensors=["gnss"]}]'])
    run_scenario(sc, tmp_path / "a", quiet=False, replay=False)
    assert not kernels.cache_missing()
    assert "compiling the filter's kernels" not in capsys.readouterr().err
    monkeypatch.setattr(kernels, "cache_missing", lambda: True)
    run_scenario(sc, tmp_path / "b", quiet=False, replay=False)
    assert "compiling the filter's kernels (numba)" in capsys.readouterr().err
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "empty_cache")}
    p = subprocess.run([sys.executable, "-c", "from v2v.estimation import kernels; print(kernels.cache_missing())"],
                       env=env, capture_output=True, text=True, timeout=120)
    assert p.stdout.strip() == "True", p.stderr
