"""Fault injection on synthesized measurements: each fault does exactly what it says."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from v2v.faults import (
    FaultLog,
    FaultSection,
    apply_bearing_faults,
    apply_gnss_faults,
    apply_uwb_faults,
    dropping_fault,
)
from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M, Bearings, GnssEpoch, UwbRanges


def _epoch(t: float, v: str, n: int = 6) -> GnssEpoch:
    z = np.zeros(n)
    return GnssEpoch(
        t_s=t, vehicle_id=v, prn=np.arange(1, n + 1), pseudorange_m=np.full(n, 2.2e7), doppler_mps=z.copy(),
        carrier_cycles=np.full(n, 1.1e8), lock_time_s=np.full(n, 100.0), cn0_dbhz=np.full(n, 45.0),
        sv_pos_ecef_m=np.zeros((n, 3)), sv_vel_ecef_mps=np.zeros((n, 3)), sv_clock_m=z.copy(), elevation_rad=z.copy(),
        azimuth_rad=z.copy(), los=np.ones(n, bool), true_range_m=np.full(n, 2.2e7), ambiguity_cycles=np.zeros(n, np.int64),
        errors_m={"noise": z.copy()},
    )


def _stream(n_epochs=100, rate=10.0):
    return [(k / rate, {v: _epoch(k / rate, v) for v in ("c1.0", "c1.1")}) for k in range(n_epochs)]


def test_clock_jump_is_one_millisecond_on_code_and_phase_from_its_start():
    f = FaultSection(kind="clock_jump", start_s=5.0, vehicles=["c1.1"])
    out = apply_gnss_faults(_stream(), [f], np.random.default_rng(0), FaultLog())
    for t, eps in out:
        d_pr = eps["c1.1"].pseudorange_m - 2.2e7
        d_ph = (eps["c1.1"].carrier_cycles - 1.1e8) * GPS_L1_WAVELENGTH_M
        expect = 299_792.458 if t >= 5.0 else 0.0  # c * 1 ms, exactly
        np.testing.assert_allclose(d_pr, expect, atol=1e-6)
        np.testing.assert_allclose(d_ph, expect, atol=1e-6)
        np.testing.assert_array_equal(eps["c1.0"].pseudorange_m, 2.2e7)
        np.testing.assert_allclose(eps["c1.1"].errors_m.get("clock_jump", np.zeros(6)), expect, atol=1e-6)


def test_outage_and_lost_satellites_drop_measurements():
    fs = [FaultSection(kind="gnss_outage", start_s=2.0, duration_s=1.0, vehicles=["c1.1"]),
          FaultSection(kind="satellites_lost", start_s=4.0, duration_s=1.0, prns=[2, 5])]
    out = apply_gnss_faults(_stream(), fs, np.random.default_rng(0), FaultLog())
    for t, eps in out:
        assert ("c1.1" in eps) == (not 2.0 <= t < 3.0)
        if 4.0 <= t < 5.0:
            assert list(eps["c1.0"].prn) == [1, 3, 4, 6]
        else:
            assert eps["c1.0"].n == 6


def test_cycle_slip_is_an_integer_step_with_lock_reset_once():
    f = FaultSection(kind="cycle_slip", start_s=3.0, vehicles=["c1.0"], prns=[4], size_cycles=7)
    out = apply_gnss_faults(_stream(), [f], np.random.default_rng(0), FaultLog())
    lock = [eps["c1.0"].lock_time_s[3] for t, eps in out if t >= 3.0]
    assert lock[0] == 0.0 and all(x == 100.0 for x in lock[1:])
    for t, eps in out:
        d = eps["c1.0"].carrier_cycles - 1.1e8
        assert d[3] == (7.0 if t >= 3.0 else 0.0) and np.all(d[[0, 1, 2, 4, 5]] == 0.0)
        assert eps["c1.0"].ambiguity_cycles[3] == (7 if t >= 3.0 else 0)


def test_blunder_rate_within_binomial_bounds():
    f = FaultSection(kind="pr_blunder", start_s=0.0, duration_s=1000.0, size_m=30.0, probability=0.05)
    out = apply_gnss_faults(_stream(1000), [f], np.random.default_rng(3), FaultLog())
    hits = sum(int((eps[v].errors_m["fault"] == 30.0).sum()) for _, eps in out for v in eps)
    n = 1000 * 2 * 6
    lo, hi = stats.binom.interval(0.999, n, 0.05)  # false failure 0.1 %
    assert lo <= hits <= hi


def test_uwb_replacement_and_drift_and_nan():
    k = 50
    t = np.linspace(0.0, 49.0, k)
    r = UwbRanges(t_s=t, true_t_s=t, a=("c1.0",) * k, b=("c1.1",) * k, range_m=np.full(k, 30.0),
                  true_range_m=np.full(k, 30.0), los=np.ones(k, bool), errors_m={"noise": np.zeros(k)})
    fs = [FaultSection(kind="uwb_replace", start_s=20.0, vehicles=["c1.0"], size_m=0.4, scale_ppm=3000.0),
          FaultSection(kind="nonfinite", sensor="uwb", start_s=40.0, duration_s=5.0)]
    out = apply_uwb_faults(r, fs, np.random.default_rng(0), FaultLog())
    after = (t >= 20.0) & ~((t >= 40.0) & (t < 45.0))
    np.testing.assert_allclose(out.range_m[after], 30.0 + 0.4 + 3000e-6 * 30.0)
    np.testing.assert_allclose(out.range_m[t < 20.0], 30.0)
    assert np.isnan(out.range_m[(t >= 40.0) & (t < 45.0)]).all()


def test_bearing_outage_and_message_bursts():
    k = 20
    t = np.arange(k, dtype=float)
    b = Bearings(t_s=t, a=("c1.1",) * k, b=("c1.0",) * k, bearing_rad=np.zeros(k), true_bearing_rad=np.zeros(k),
                 azimuth_reported_rad=np.zeros(k), true_azimuth_rad=np.zeros(k), los=np.ones(k, bool))
    out = apply_bearing_faults(b, [FaultSection(kind="bearing_outage", start_s=5.0, duration_s=5.0)],
                               np.random.default_rng(0), FaultLog())
    assert list(out.t_s) == [x for x in t if not 5.0 <= x < 10.0]
    fs = [FaultSection(kind="message_loss", start_s=1.0, duration_s=2.0, vehicles=["c1.2"])]
    assert dropping_fault(fs, "c1.2", 1.5) == 0 and dropping_fault(fs, "c1.2", 3.0) is None
    assert dropping_fault(fs, "c1.1", 1.5) is None


def _sky_in_view(sc) -> set[int]:
    """PRNs above the mask at the scenario's start and origin (what `v2v sky --scenario` lists)."""
    from v2v.run import resolve_network
    from v2v.sensors.gnss.constellation import NominalConstellation
    from v2v.sensors.gnss.sky import sky_view
    from v2v.sensors.gnss.time import utc_to_gps_s

    lat, lon = resolve_network(sc).georef.xy_to_geodetic(0.0, 0.0)
    t = utc_to_gps_s(sc.start_utc)
    df = sky_view(float(lat), float(lon), sc.network.origin_h_m, t, NominalConstellation(t),
                  np.radians(sc.sensors.gnss.elevation_mask_deg))
    return set(df["prn"].astype(int))



@pytest.mark.sumo
def test_faults_that_cannot_act_are_refused_or_noted(tmp_path):
    """A fault that would silently do nothing is not silent: PRNs none of which the sky has are
    a one-line error of the check and of the run (faults.<i>.prns; some missing is allowed); a
    fault that starts after the run's end, and one whose satellites are all below the horizon in
    its window, are named in the run's note; one on a satellite in view drops its signals
    (counted) and is not."""
    from v2v.config.scenario import load_scenario
    from v2v.errors import UserError
    from v2v.run import check_scenario, run_scenario

    base = ["duration_s=3.0", 'solutions=[{name="GPS", sensors=["gnss"]}]']
    sc = load_scenario(None, base)
    up = _sky_in_view(sc)
    down = min(set(range(1, 28)) - up)  # a PRN of the 27-slot nominal sky that is below the horizon
    bad = load_scenario(None, [*base, 'faults=[{kind="satellites_lost", start_s=1.0, duration_s=1.0, prns=[30]}]'])
    for check in (lambda: check_scenario(bad), lambda: run_scenario(bad, tmp_path / "bad", quiet=True, replay=False)):
        with pytest.raises(UserError) as ei:
            check()
        assert ei.value.field == "faults.0.prns" and "[30]" in ei.value.message
    assert not (tmp_path / "bad").exists()
    sc = load_scenario(None, [*base, "faults=[" + ", ".join([
        '{kind="clock_jump", start_s=120.0, vehicles=["c1.1"]}',
        f'{{kind="satellites_lost", start_s=1.0, duration_s=1.0, prns=[{down}]}}',
        f'{{kind="satellites_lost", start_s=1.0, duration_s=1.0, prns=[{min(up)}, 30]}}']) + "]"])
    res = run_scenario(sc, tmp_path / "r", quiet=True, replay=False)
    note = res.summary["note"]
    assert "never injected: faults.0 (clock_jump at 120 s)" in note
    assert "faults.1 (satellites_lost) changed no measurement" in note and "faults.2" not in note
    assert res.summary["faults_injected"].get("2:satellites_lost", 0) > 0
