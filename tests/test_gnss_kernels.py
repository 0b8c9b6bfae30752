"""The compiled GNSS synthesis path (numba kernels of v2v.sensors.gnss.receiver) against the
reference algorithms it replaces: IS-GPS-200 satellite states at the light-time-solved
transmit time, the array forms of the atmosphere models (themselves checked against
published values in test_gnss_receiver.py), and numpy's Generator streams that the
pre-drawn random blocks rely on. Every random test is seeded.
"""

from __future__ import annotations

import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from v2v.sensors.gnss import receiver as rx_mod
from v2v.sensors.gnss.atmosphere import (
    IonosphereConfig,
    IonosphereField,
    TroposphereConfig,
    TroposphereField,
    iono_slant_delay_scalar_m,
    klobuchar_delay_s,
    klobuchar_delay_scalar_s,
    tropo_slant_delay_scalar_m,
)
from v2v.sensors.gnss.constellation import NominalConstellation
from v2v.sensors.gnss.ephemeris import sv_states_at_reception
from v2v.sensors.gnss.errors import GnssErrorConfig, TrackingConfig
from v2v.sensors.gnss.receiver import GnssReceiverConfig, GnssSynthesizer

sys.path.insert(0, str(Path(__file__).parent))
from test_gnss_receiver import GPS0, steps, synth, vstate  # noqa: E402

# A GPS epoch of ~2e5 s (January 1980) resolves time to 3e-11 s (1e-7 m of satellite motion),
# so the direct evaluation is an exact reference; at today's ~1.3e9 s it resolves only 2.4e-7 s.
T_SMALL = 2.0e5


def test_interpolated_satellite_states_match_direct_evaluation():
    """Ranges, satellite positions/velocities and clocks vs. IS-GPS-200 at the light-time instant.

    The synthesizer interpolates ephemeris states between evaluations every 5 s (cubic
    Hermite): error ``h^4 |x''''| / 384 ~ 2e-8 m`` with ``|x''''| ~ a n^4 ~ 1.3e-8 m/s^4``.
    The reference (``sv_states_at_reception``) solves the same light-time equation to
    1e-12 s by evaluating the ephemeris at the transmit time. Bounds: 1e-6 m (position,
    range), 1e-6 m/s (velocity), 1e-6 m (clock x c): 50x the interpolation error, and
    above the reference's own time resolution at 2e5 s (3e-11 s x 3.9 km/s = 1e-7 m).
    """
    eph = NominalConstellation(T_SMALL)
    syn = GnssSynthesizer(eph, GnssReceiverConfig(errors=GnssErrorConfig.ideal()), np.random.SeedSequence(1),
                          T_SMALL)
    worst = np.zeros(4)
    for t in (0.0, 1.3, 2.5, 4.9, 5.0, 7.77, 123.4):  # inside intervals and on grid nodes
        v = vstate("a", t, 0.0, 0.0)
        e = syn.epoch(t, {"a": v})["a"]
        ref, tau = sv_states_at_reception(eph, e.prn, v.ecef_m, T_SMALL + t)
        rho = np.linalg.norm(ref.pos_ecef_m - v.ecef_m, axis=1)
        worst = np.maximum(worst, [
            np.abs(e.true_range_m - rho).max(),
            np.abs(e.sv_pos_ecef_m - ref.pos_ecef_m).max(),
            np.abs(e.sv_vel_ecef_mps - ref.vel_ecef_mps).max(),
            np.abs(e.sv_clock_m - 299_792_458.0 * ref.clock_bias_s).max(),
        ])
    print("max |interpolated - direct|: range, pos (m), vel (m/s), clock (m):", worst)
    assert worst[0] < 1e-6 and worst[1] < 1e-6 and worst[2] < 1e-6 and worst[3] < 1e-6


def test_interpolated_states_real_broadcast_ephemeris(shared_gnss_day):
    """The same with eccentric real orbits (2021-04-28 broadcast file) at GPS ~1.3e9 s.

    The reference evaluates at absolute GPS seconds resolved to 2.4e-7 s, i.e. up to ~1 mm
    of satellite motion (3.9 km/s), so the bound is 2 mm; broadcast record changes every
    2 h are avoided by the times chosen (the interpolation blends records within one 5 s
    interval, see GnssSynthesizer._geometry).
    """
    from v2v.sensors.gnss.rinex import read_rinex_nav

    eph = read_rinex_nav(shared_gnss_day / "brdc1180.21n")
    syn = synth(eph, GnssErrorConfig.ideal())
    worst = 0.0
    for t in (0.0, 2.2, 33.3):
        v = vstate("a", t, 0.0, 0.0)
        e = syn.epoch(t, {"a": v})["a"]
        ref, _ = sv_states_at_reception(eph, e.prn, v.ecef_m, GPS0 + t)
        worst = max(worst, np.abs(e.true_range_m - np.linalg.norm(ref.pos_ecef_m - v.ecef_m, axis=1)).max())
    print(f"RINEX: max |range interpolated - direct| = {worst * 1e3:.3f} mm")
    assert worst < 2e-3


def test_compiled_atmosphere_equals_array_models():
    """Scalar kernels = the array models (Klobuchar IS-GPS-200 20.3.3.5.2.5, thin-shell residual,
    Saastamoinen + mapping) to float rounding: relative 1e-12 (a few ulp through ~30 operations)."""
    rng = np.random.default_rng(5)
    n = 200
    lat = np.deg2rad(rng.uniform(-70, 70, n))
    lon = np.deg2rad(rng.uniform(-180, 180, n))
    el = np.deg2rad(rng.uniform(1, 90, n))
    az = rng.uniform(0, 2 * np.pi, n)
    h = rng.uniform(-50, 3000, n)
    t = 1.3e9 + rng.uniform(0, 86400, n)
    ic = IonosphereConfig()
    alpha, beta = np.asarray(ic.klobuchar_alpha, float), np.asarray(ic.klobuchar_beta, float)
    klob = klobuchar_delay_s(lat, lon, el, az, t, ic.klobuchar_alpha, ic.klobuchar_beta)
    kk = np.array([klobuchar_delay_scalar_s(*a, alpha, beta) for a in zip(lat, lon, el, az, t, strict=True)])
    np.testing.assert_allclose(kk, klob, rtol=1e-12)
    f = IonosphereField(ic, np.random.default_rng(1), lat[0], lon[0])
    for i in range(20):
        ref = f.slant_delay_m(lat[i:i + 1], lon[i:i + 1], el[i:i + 1], az[i:i + 1], float(t[i]))[0]
        got = iono_slant_delay_scalar_m(lat[i], lon[i], el[i], az[i], float(t[i]), ic.klobuchar_scale, alpha, beta,
                                        ic.shell_height_m, f.ref_lat_rad, f.ref_lon_rad, f.k_en, f.omega_radps,
                                        f.phase_rad, f.amp_m)
        assert got == pytest.approx(ref, rel=1e-12, abs=1e-12)
    tc = TroposphereConfig()
    tf = TroposphereField(tc, np.random.default_rng(2), lat[0], lon[0])
    ref = tf.slant_delay_m(lat, lon, h, el)
    got = np.array([tropo_slant_delay_scalar_m(lat[i], lon[i], h[i], el[i], tc.temperature_sea_level_c,
                                               tc.relative_humidity, tf.zenith_residual_m, tf.gradient_en[0],
                                               tf.gradient_en[1], tf.ref_lat_rad, tf.ref_lon_rad) for i in range(n)])
    np.testing.assert_allclose(got, ref, rtol=1e-12)


def test_generator_streams_are_chunk_invariant():
    """What the pre-drawn blocks rely on: numpy's Generator gives the same standard normals and
    uniforms whether drawn in pieces or at once (ziggurat / 53-bit doubles keep no cached state)."""
    sizes = [3, 7, 1, 20, 2, 2, 100, 0, 31]
    for method in ("standard_normal", "random"):
        a, b = np.random.default_rng(11), np.random.default_rng(11)
        pieces = np.concatenate([getattr(a, method)(s) for s in sizes])
        np.testing.assert_array_equal(pieces, getattr(b, method)(sum(sizes)))


def test_outputs_do_not_depend_on_draw_block_size(monkeypatch):
    """Same seed -> bit-identical epochs whatever the pre-drawn block size (refills at other
    times), with slips on so that every stream is used."""
    err = replace(GnssErrorConfig(), tracking=replace(TrackingConfig(), random_slip_rate_hz=0.5))
    pos = {"a": (0.0, 0.0), "b": (30.0, 3.5), "c": (60.0, 0.0)}
    ref = synth(NominalConstellation(GPS0), err, seed=4).run(steps(pos, 80, 0.1))
    monkeypatch.setattr(rx_mod, "_DRAW_BLOCK", 97)  # > worst need 2 x 32 candidates
    got = synth(NominalConstellation(GPS0), err, seed=4).run(steps(pos, 80, 0.1))
    assert len(got) == len(ref)
    for e1, e2 in zip(ref, got, strict=True):
        for f in ("pseudorange_m", "carrier_cycles", "doppler_mps", "ambiguity_cycles", "lock_time_s"):
            np.testing.assert_array_equal(getattr(e1, f), getattr(e2, f))


def test_ambiguities_uniform_integers_in_range():
    """New ambiguities are integers in [-max, max]; with max = 2 the 5 values are equally likely:
    chi-square (4 dof) below its 99.9 % point 18.47 (false failure 1e-3)."""
    err = replace(GnssErrorConfig(), tracking=replace(TrackingConfig(), ambiguity_max_cycles=2))
    veh = {f"v{i}": vstate(f"v{i}", 0.0, 40.0 * i) for i in range(150)}
    ep = synth(NominalConstellation(GPS0), err, seed=21).epoch(0.0, veh)
    amb = np.concatenate([e.ambiguity_cycles for e in ep.values()])
    assert amb.dtype == np.int64 and amb.min() >= -2 and amb.max() <= 2
    counts = np.bincount(amb + 2, minlength=5)
    chi2 = np.sum((counts - amb.size / 5) ** 2 / (amb.size / 5))
    print(f"{amb.size} ambiguities, counts {counts}, chi2 {chi2:.2f}")
    assert chi2 < 18.47


def test_epoch_fast_construction_equals_dataclass():
    """The epochs built without the frozen dataclass's __init__ are ordinary, complete GnssEpochs."""
    from dataclasses import fields

    from v2v.sensors.measurements import GnssEpoch

    e = synth(NominalConstellation(GPS0), seed=2).epoch(0.0, {"a": vstate("a", 0.0, 0.0)})["a"]
    assert isinstance(e, GnssEpoch)
    again = GnssEpoch(**{f.name: getattr(e, f.name) for f in fields(GnssEpoch)})
    assert again.n == e.n > 4
    # every per-satellite column has one row per satellite (the constructor would not check)
    for f in fields(GnssEpoch):
        v = getattr(e, f.name)
        if isinstance(v, np.ndarray):
            assert v.shape[0] == e.n, f.name
    assert e.sv_pos_ecef_m.shape == (e.n, 3) and e.prn.dtype.kind == "i" and e.los.dtype == bool
    with pytest.raises(AttributeError):
        e.t_s = 1.0  # still frozen
