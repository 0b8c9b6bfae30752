"""Frames against pymap3d reference values, round trips, and the angle conventions."""

from __future__ import annotations

import numpy as np
import pymap3d
import pyproj
import pytest

from v2v.frames import (
    GeoReference,
    azimuth_elevation,
    ecef_to_enu,
    ecef_to_geodetic,
    enu_to_lead_frame,
    geodetic_to_ecef,
    heading_unit_vectors,
    wrap_angle,
)

POINTS_DEG = [(51.0775, -114.1295, 1100.0), (0.0, 0.0, 0.0), (-33.9, 151.2, 50.0), (89.9, 10.0, 3000.0), (45.0, 179.99, 20_200_000.0)]


@pytest.mark.parametrize(("lat", "lon", "h"), POINTS_DEG)
def test_geodetic_to_ecef_matches_pymap3d(lat, lon, h):
    ref = np.array(pymap3d.geodetic2ecef(lat, lon, h))
    got = geodetic_to_ecef(np.radians(lat), np.radians(lon), h)
    # Same closed-form WGS-84 formula: agreement to floating-point rounding of ~2e7 m values.
    np.testing.assert_allclose(got, ref, atol=1e-6)


@pytest.mark.parametrize(("lat", "lon", "h"), POINTS_DEG)
def test_ecef_geodetic_round_trip(lat, lon, h):
    lat_r, lon_r, h_r = ecef_to_geodetic(geodetic_to_ecef(np.radians(lat), np.radians(lon), h))
    # 1e-11 rad is 0.06 mm on the ground; the iteration converges far below that.
    assert abs(float(lat_r) - np.radians(lat)) < 1e-11
    assert abs(float(wrap_angle(lon_r - np.radians(lon)))) < 1e-11
    assert abs(float(h_r) - h) < 1e-4


def test_ecef_to_enu_matches_pymap3d():
    lat0, lon0, h0 = 51.0775, -114.1295, 1100.0
    ref_ecef = geodetic_to_ecef(np.radians(lat0), np.radians(lon0), h0)
    p = geodetic_to_ecef(np.radians(51.08), np.radians(-114.12), 1130.0)
    e, n, u = pymap3d.ecef2enu(*p, lat0, lon0, h0)
    got = ecef_to_enu(p, np.radians(lat0), np.radians(lon0), ref_ecef)
    np.testing.assert_allclose(got, [e, n, u], atol=1e-6)


def test_wrap_angle_half_open_interval():
    vals = wrap_angle([np.pi, -np.pi, 3 * np.pi, -3 * np.pi / 2, 0.0, 2 * np.pi])
    np.testing.assert_allclose(vals, [np.pi, np.pi, np.pi, np.pi / 2, 0.0, 0.0], atol=1e-12)
    assert np.all(vals > -np.pi) and np.all(vals <= np.pi)


def test_azimuth_elevation_conventions():
    az, el = azimuth_elevation(np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 1.0], [-1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(az, [np.pi / 2, 0.0, 3 * np.pi / 2])  # east = 90 deg clockwise from north
    np.testing.assert_allclose(el, [0.0, np.pi / 4, 0.0])


def test_lead_frame_is_iso8855_left_positive():
    east = np.pi / 2  # lead heading east
    # North of an east-heading vehicle is to its left: across-track positive.
    np.testing.assert_allclose(enu_to_lead_frame([0.0, 3.0, 0.5], east), [0.0, 3.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(enu_to_lead_frame([10.0, 0.0, 0.0], east), [10.0, 0.0, 0.0], atol=1e-12)
    # Heading north: east is to the right (negative across).
    np.testing.assert_allclose(enu_to_lead_frame([2.0, 5.0, 0.0], 0.0), [5.0, -2.0, 0.0], atol=1e-12)
    fwd, left = heading_unit_vectors(np.radians(30.0))
    assert abs(float(fwd @ left)) < 1e-15
    # left = forward rotated +90 deg counter-clockwise: z-component of fwd x left is +1.
    assert np.isclose(fwd[0] * left[1] - fwd[1] * left[0], 1.0)


def test_georeference_tangent_plane_distances():
    proj = "+proj=tmerc +lat_0=51.0775 +lon_0=-114.1295 +k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
    g = GeoReference(proj=proj, net_offset_m=(100.0, -50.0))
    lat, lon = g.xy_to_geodetic(100.0, -50.0)
    assert np.degrees(lat) == pytest.approx(51.0775, abs=1e-12)
    assert np.degrees(lon) == pytest.approx(-114.1295, abs=1e-12)
    # 1 km north on the central meridian of a k=1 transverse Mercator is 1 km of geodesic.
    lat2, lon2 = g.xy_to_geodetic(100.0, 950.0)
    _, _, dist = pyproj.Geod(ellps="WGS84").inv(np.degrees(lon), np.degrees(lat), np.degrees(lon2), np.degrees(lat2))
    assert dist == pytest.approx(1000.0, abs=1e-3)
    x, y = g.geodetic_to_xy(lat2, lon2)
    assert float(x) == pytest.approx(100.0, abs=1e-6) and float(y) == pytest.approx(950.0, abs=1e-6)
    # Grid convergence of TM ~ dlon * sin(lat) (first-order term; the next term is
    # O(dlon^3), ~1e-9 relative here): 2 km east of the central meridian.
    gamma = g.grid_convergence_rad(2100.0, -50.0)
    lat_e, lon_e = g.xy_to_geodetic(2100.0, -50.0)
    expected = float(lon_e - np.radians(-114.1295)) * np.sin(float(lat_e))
    assert gamma == pytest.approx(expected, rel=1e-4)
    # A true-north heading there appears in the grid rotated by -gamma: walk 100 m true north.
    lat_n = lat_e + 100.0 / 6_371_000.0
    xn, yn = g.geodetic_to_xy(lat_n, lon_e)
    grid_az = np.arctan2(float(xn) - 2100.0, float(yn) + 50.0)
    assert grid_az == pytest.approx(-gamma, rel=1e-3)


def test_georeference_without_projection_uses_scenario_origin():
    g = GeoReference(proj=None, origin_lat_deg=10.0, origin_lon_deg=20.0)
    lat, lon = g.xy_to_geodetic(0.0, 0.0)
    assert np.degrees(lat) == pytest.approx(10.0, abs=1e-12)
    assert np.degrees(lon) == pytest.approx(20.0, abs=1e-12)
