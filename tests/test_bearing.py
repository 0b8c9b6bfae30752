"""Bearing sensor against Petovello et al. §2.2 (eq. 3-5) and its configured noise.

Truth comes from :func:`make_steps` (same helper as tests/test_uwb.py, repeated here so each
test file stands alone): ``TrafficStep`` sequences built from net-XY trajectories on a
tangent-plane net at height 0, where net XY axes are east/north at the origin. Bounds quote
their false-failure rate; every random test is seeded.
"""

from __future__ import annotations

import dataclasses
import math
import types

import numpy as np
import pytest
from scenekit import LinksOnly, crossing_scene
from scipy import stats

from v2v.errors import UserError
from v2v.frames import GeoReference, wrap_angle
from v2v.sensors.bearing import BearingSensor
from v2v.sensors.measurements import Bearings
from v2v.traffic.snapshot import TrafficStep, VehicleState
from v2v.world.buildings import World
from v2v.world.occlusion import OcclusionGeometry

GEO = GeoReference(proj=None, origin_lat_deg=51.08, origin_lon_deg=-114.13, origin_h_m=0.0)
DEG = math.pi / 180.0


def make_steps(
    t_s: np.ndarray, xy_by_vehicle: dict[str, np.ndarray], az_by_vehicle: dict[str, float] | None = None,
    z_m: float = 1.5,
) -> list[TrafficStep]:
    """Fake truth from net-XY positions (n, 2); azimuth from the XY velocity unless given, true
    and grid alike (GEO is tangent at its origin: < 1e-4 rad of grid convergence within 1 km)."""
    az_by_vehicle = az_by_vehicle or {}
    states: dict[str, list[VehicleState]] = {}
    for vid, xy in xy_by_vehicle.items():
        xy = np.asarray(xy, dtype=float)
        lat, lon = GEO.xy_to_geodetic(xy[:, 0], xy[:, 1])
        ecef = GEO.xyz_to_ecef(xy[:, 0], xy[:, 1], np.full(len(xy), z_m))
        v = np.gradient(xy, t_s, axis=0)
        speed = np.hypot(v[:, 0], v[:, 1])
        if vid in az_by_vehicle:
            az = np.full(len(xy), az_by_vehicle[vid])
        else:
            az = np.where(speed > 1e-9, np.arctan2(v[:, 0], v[:, 1]) % (2 * np.pi), 0.0)
        fwd = np.stack([np.sin(az), np.cos(az)], axis=1)
        states[vid] = [
            VehicleState(
                vehicle_id=vid, cluster="c0", is_lead=False, t_s=float(t_s[i]),
                xyz_m=np.array([xy[i, 0], xy[i, 1], z_m]), lat_rad=float(lat[i]), lon_rad=float(lon[i]),
                h_m=z_m, ecef_m=ecef[i], vel_enu_mps=np.array([v[i, 0], v[i, 1], 0.0]),
                speed_mps=float(speed[i]), accel_mps2=0.0, azimuth_rad=float(az[i]), grid_azimuth_rad=float(az[i]), yaw_rate_rps=0.0,
                front_bumper_xy_m=xy[i] + 2.25 * fwd[i], edge_id="e0", lane_id="e0_0", lane_index=0,
                lane_width_m=3.5, lateral_offset_m=0.0, length_m=4.5, width_m=1.8, height_m=1.5,
            )
            for i in range(len(t_s))
        ]
    return [TrafficStep(t_s=float(t), vehicles={vid: s[i] for vid, s in states.items()}) for i, t in enumerate(t_s)]


def chi2_sigma_bounds(n: int, sigma: float, alpha: float = 1e-3) -> tuple[float, float]:
    """Two-sided (1 - alpha) bounds of the sample std of n iid normal values with std sigma."""
    return (
        sigma * math.sqrt(stats.chi2.ppf(alpha / 2, n - 1) / (n - 1)),
        sigma * math.sqrt(stats.chi2.ppf(1 - alpha / 2, n - 1) / (n - 1)),
    )


T = np.arange(0.0, 60.0 + 1e-9, 0.1)
Z = np.zeros_like(T)
# Three cars on a curving platoon-like path: a lead, one behind, one in the next lane.
XY3 = {
    "lead": np.stack([30.0 * np.sin(0.02 * T) * 20, 30.0 * (1 - np.cos(0.02 * T)) * 20], 1),
    "v1": np.stack([30.0 * np.sin(0.02 * T) * 20 - 28.0, 30.0 * (1 - np.cos(0.02 * T)) * 20 - 2.0], 1),
    "v2": np.stack([30.0 * np.sin(0.02 * T) * 20 - 14.0, 30.0 * (1 - np.cos(0.02 * T)) * 20 + 3.5], 1),
}


def test_sign_convention_right_is_positive():
    """a heads north; b 20 m east is to its right: bearing +90 deg; c 20 m west: -90 deg; d north: 0
    (paper eq. 5, azimuths clockwise from north). Exact to 1e-6 rad (tangent projection at the origin)."""
    t = np.arange(0.0, 1.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([z, z], 1), "b": np.stack([z + 20, z], 1), "c": np.stack([z - 20, z], 1), "d": np.stack([z, z + 20], 1)}
    br = BearingSensor(sigma_rad=0.0, azimuth_sigma_rad=0.0, measuring=("a",)).simulate(
        make_steps(t, xy, {k: 0.0 for k in xy}), np.random.default_rng(0)
    )
    got = {b: br.true_bearing_rad[i] for i, b in enumerate(br.b)}
    assert got["b"] == pytest.approx(math.pi / 2, abs=1e-6)
    assert got["c"] == pytest.approx(-math.pi / 2, abs=1e-6)
    assert got["d"] == pytest.approx(0.0, abs=1e-6)
    np.testing.assert_array_equal(br.bearing_rad, br.true_bearing_rad)


def test_error_statistics_match_sigma():
    """sigma = 0.5 deg, azimuth sigma = 0.1 deg: means within 3.29 sigma/sqrt(n) of 0 and stds inside
    chi-square bounds (each 99.9 %, so ~0.4 % for the four checks together). The azimuth report
    is one value per vehicle and epoch, so its statistics use unique (vehicle, epoch) samples."""
    sensor = BearingSensor()
    br = sensor.simulate(make_steps(T, XY3), np.random.default_rng(2024))
    err = wrap_angle(br.bearing_rad - br.true_bearing_rad)
    n = err.size
    print(f"\nbearing: n={n}, mean {err.mean() / DEG:.4f} deg, std {err.std(ddof=1) / DEG:.4f} deg (0.5)")
    assert n == 601 * 6  # 10 Hz at 10 Hz steps, 3 vehicles x 2 targets, all in range and view
    assert abs(err.mean()) < 3.29 * sensor.sigma_rad / math.sqrt(n)
    lo, hi = chi2_sigma_bounds(n, sensor.sigma_rad)
    assert lo < err.std(ddof=1) < hi
    _, first = np.unique(np.stack([br.t_s, [hash(a) for a in br.a]], 1), axis=0, return_index=True)
    az_err = wrap_angle(br.azimuth_reported_rad[first] - br.true_azimuth_rad[first])
    m = az_err.size
    assert m == 601 * 3
    assert abs(az_err.mean()) < 3.29 * sensor.azimuth_sigma_rad / math.sqrt(m)
    lo, hi = chi2_sigma_bounds(m, sensor.azimuth_sigma_rad)
    assert lo < az_err.std(ddof=1) < hi


def test_target_directly_behind_wraps_at_pi():
    """b 30 m straight behind a: true bearing is pi (numerically +-pi: dE is +-1e-12 m after the ECEF
    round trip); noisy bearings straddle +-pi, yet wrapped errors have mean ~0 (3.29 sigma/sqrt(n),
    99.9 %) and the configured std."""
    t = np.arange(0.0, 100.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([z, 10.0 * t], 1), "b": np.stack([z, 10.0 * t - 30.0], 1)}
    sensor = BearingSensor(sigma_rad=0.5 * DEG, measuring=("a",))
    br = sensor.simulate(make_steps(t, xy), np.random.default_rng(7))
    np.testing.assert_allclose(wrap_angle(br.true_bearing_rad - math.pi), 0.0, atol=1e-6)
    assert np.all(np.abs(br.true_bearing_rad) <= math.pi)
    assert (br.bearing_rad > 0).any() and (br.bearing_rad < 0).any()  # both sides of the cut
    assert np.all(np.abs(br.bearing_rad) > math.pi - 6 * sensor.sigma_rad)
    err = wrap_angle(br.bearing_rad - br.true_bearing_rad)
    assert abs(err.mean()) < 3.29 * sensor.sigma_rad / math.sqrt(err.size)
    lo, hi = chi2_sigma_bounds(err.size, sensor.sigma_rad)
    assert lo < err.std(ddof=1) < hi
    assert abs(np.mean(br.bearing_rad)) < 1.0  # the naive mean is meaningless near +-pi (shows the wrap)


def test_field_of_view_and_max_range():
    """120 deg forward field of view: the car 30 m ahead is seen, 30 m behind is not; 200 m ahead is
    beyond the 150 m default range."""
    t = np.arange(0.0, 2.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([z, z], 1), "f": np.stack([z, z + 30], 1), "r": np.stack([z, z - 30], 1), "far": np.stack([z, z + 200], 1)}
    br = BearingSensor(field_of_view_rad=120 * DEG, measuring=("a",)).simulate(
        make_steps(t, xy, {k: 0.0 for k in xy}), np.random.default_rng(1)
    )
    assert set(br.b) == {"f"}


def test_rate_and_every_step():
    """2 Hz on 10 Hz steps over 0..10 s: ticks at 0, 0.5, ..., 10 -> 21 epochs; rate None -> 101."""
    t = np.arange(0.0, 10.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([z, z], 1), "b": np.stack([z, z + 20], 1)}
    steps = make_steps(t, xy, {"a": 0.0, "b": 0.0})
    assert BearingSensor(rate_hz=2.0, measuring=("a",)).simulate(steps, np.random.default_rng(0)).n == 21
    assert BearingSensor(rate_hz=None, measuring=("a",)).simulate(steps, np.random.default_rng(0)).n == 101


def test_occluded_link_gives_no_bearing():
    """A stand-in of the occlusion interface blocking every link to 'b': only 'c' is measured."""
    t = np.arange(0.0, 1.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([z, z], 1), "b": np.stack([z + 10, z], 1), "c": np.stack([z, z + 10], 1)}

    class BlockEast:
        def links(self, p0, p1, boxes, exclude):
            blocked = p1[:, 0] > 5.0
            return types.SimpleNamespace(blocked=blocked, reflection_excess_m=np.full(len(p0), np.nan))

    br = BearingSensor(measuring=("a",)).simulate(make_steps(t, xy, {k: 0.0 for k in xy}), np.random.default_rng(0), BlockEast())
    assert set(br.b) == {"c"}


def test_real_occlusion_car_in_between():
    """v2v.world.occlusion: a 1.5 m car parked between a and b blocks the 1.0 m high sight line."""
    import v2v.world.occlusion as occ
    from v2v.world.buildings import World

    t = np.arange(0.0, 1.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([z, z], 1), "m": np.stack([z, z + 15], 1), "b": np.stack([z, z + 30], 1)}
    br = BearingSensor(measuring=("a",)).simulate(
        make_steps(t, xy, {k: 0.0 for k in xy}, z_m=1.0), np.random.default_rng(0), occ.OcclusionGeometry(World())
    )
    assert set(br.b) == {"m"}


def test_azimuth_bias_is_gauss_markov():
    """Slowly varying azimuth bias (sigma 1 deg, tau 300 s, no white part): increments over dt = 0.1 s
    have variance 2 (1 - exp(-dt/tau)) sigma^2 (first-order Gauss-Markov); chi-square 99.9 % bounds."""
    t = np.arange(0.0, 200.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    xy = {"a": np.stack([z, z], 1), "b": np.stack([z, z + 20], 1)}
    sensor = BearingSensor(azimuth_sigma_rad=0.0, azimuth_bias_sigma_rad=1 * DEG, azimuth_bias_tau_s=300.0, measuring=("a",))
    br = sensor.simulate(make_steps(t, xy, {"a": 0.5, "b": 0.0}), np.random.default_rng(3))
    bias = wrap_angle(br.azimuth_reported_rad - br.true_azimuth_rad)
    inc = np.diff(bias)
    sd = 1 * DEG * math.sqrt(2 * (1 - math.exp(-0.1 / 300.0)))
    lo, hi = chi2_sigma_bounds(inc.size, sd)
    assert lo < inc.std(ddof=1) < hi


@pytest.mark.parametrize(
    ("kw", "field"),
    [
        ({"sigma_rad": -0.1}, "bearing.sigma_rad"),
        ({"rate_hz": -10.0}, "bearing.rate_hz"),
        ({"field_of_view_rad": 7.0}, "bearing.field_of_view_rad"),
        ({"max_range_m": 0.0}, "bearing.max_range_m"),
        ({"measuring": "some"}, "sensors.bearing.measuring"),
    ],
)
def test_bad_settings_are_user_errors(kw, field):
    with pytest.raises(UserError) as ei:
        BearingSensor(**kw)
    assert ei.value.field == field


def test_unknown_measuring_vehicle_is_user_error():
    t = np.arange(0.0, 1.0 + 1e-9, 0.1)
    z = np.zeros_like(t)
    steps = make_steps(t, {"a": np.stack([z, z], 1), "b": np.stack([z, z + 20], 1)})
    with pytest.raises(UserError) as ei:
        BearingSensor(measuring=("a", "ghost")).simulate(steps, np.random.default_rng(0))
    assert ei.value.field == "sensors.bearing.measuring" and "ghost" in str(ei.value)


# ------------------------------------------------------------------ batched occlusion query vs per-step path
@pytest.mark.parametrize(
    "kw",
    [
        {},
        {"rate_hz": None, "azimuth_bias_sigma_rad": 0.01},
        {"measuring": ("b", "c"), "rate_hz": 3.0, "field_of_view_rad": 2.0},
    ],
    ids=["default", "every-step-bias", "subset-fov"],
)
def test_batched_occlusion_equals_per_step_links(kw):
    """Bearings with the real ``OcclusionGeometry`` (one ``links_many`` query per chunk, each link
    against its own step's boxes) and with :class:`LinksOnly` (``links`` step by step) must be
    identical, whole-run and in 4 s chunks. Equality, not closeness: both paths synthesize the same
    geometry and noise, and the blocked decision of a link is per link (``links_many`` gives exactly
    ``links``' answer, tests/test_occlusion.py), so a single differing value means a link was tested
    against the wrong step's boxes or exclusions, or the random draws were split differently.
    """
    steps, occ = crossing_scene(make_steps)
    sensor = BearingSensor(**kw)
    open_sky = sensor.simulate(steps, np.random.default_rng(3))
    fields = [f.name for f in dataclasses.fields(Bearings)]
    for chunk in (len(steps), 40):
        outs = []
        for o in (occ, LinksOnly(occ)):
            stream = sensor.stream(np.random.default_rng(3), o)
            parts = [stream.push(steps[i:i + chunk]) for i in range(0, len(steps), chunk)]
            stream.finish()
            outs.append({f: np.concatenate([np.asarray(getattr(p, f)) for p in parts]) for f in fields})
        for f in fields:
            np.testing.assert_array_equal(outs[0][f], outs[1][f], err_msg=f"chunk {chunk}, {f}")
    # The scene exercises the occlusion: vehicles alone remove some bearings, buildings more, not all.
    cars_only = sensor.simulate(steps, np.random.default_rng(3), OcclusionGeometry(World()))
    assert 0 < outs[0]["t_s"].size < cars_only.n < open_sky.n
