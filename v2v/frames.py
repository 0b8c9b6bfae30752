"""Coordinate frames and conversions (WGS-84).

Conventions used everywhere in v2v
----------------------------------
* **Net XY**: the SUMO network's Cartesian plane, metres. ``x`` grows east-ish,
  ``y`` north-ish (exactly east/north only where the projection's grid
  convergence is zero). Heights ``z`` are metres above the ellipsoid-referenced
  road surface the net gives (SUMO nets are usually flat: z = 0).
* **Geodetic**: latitude/longitude in radians, ellipsoidal height in metres (WGS-84).
* **ECEF**: WGS-84 Earth-centred Earth-fixed, metres.
* **ENU**: local-level east/north/up at a reference point, metres.
* **Azimuth**: radians clockwise from (true) north. SUMO's ``getAngle`` is degrees clockwise
  from *grid* north, the net's +y: true azimuth = grid azimuth + the grid convergence
  (:meth:`GeoReference.grid_convergence_rad`; up to 2.9e-4 rad on the shipped nets).
* **Lead frame** (ISO 8855): along-track = the lead vehicle's heading, across-track
  = 90 deg to the *left* of it, up = up.

The projection between net XY and geodetic is the net's ``<location>`` element:
``xy_net = xy_projected + netOffset`` where ``xy_projected`` comes from the PROJ
string ``projParameter``. Nets without a projection ("!") get an explicit
geo-reference from the scenario and are treated as a transverse-Mercator plane
tangent at that origin (scale 1): over a few km the difference to a true local
ENU plane is below a millimetre per metre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

# WGS-84 (NIMA TR8350.2)
WGS84_A_M = 6378137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
WGS84_B_M = WGS84_A_M * (1.0 - WGS84_F)

FloatArray = NDArray[np.float64]


def geodetic_to_ecef(lat_rad: ArrayLike, lon_rad: ArrayLike, h_m: ArrayLike) -> FloatArray:
    """Geodetic (WGS-84) to ECEF. Returns an array of shape ``(..., 3)`` in metres."""
    lat = np.asarray(lat_rad, dtype=float)
    lon = np.asarray(lon_rad, dtype=float)
    h = np.asarray(h_m, dtype=float)
    sin_lat = np.sin(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - WGS84_E2) + h) * sin_lat
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(ecef_m: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """ECEF to geodetic (lat_rad, lon_rad, h_m), Bowring's method with two iterations.

    Accurate to well below a millimetre for terrestrial and GNSS-orbit points.
    """
    p_ecef = np.asarray(ecef_m, dtype=float)
    x, y, z = p_ecef[..., 0], p_ecef[..., 1], p_ecef[..., 2]
    lon = np.arctan2(y, x)
    p = np.hypot(x, y)
    ep2 = WGS84_E2 / (1.0 - WGS84_E2)
    beta = np.arctan2(z, p * (1.0 - WGS84_F))
    lat = np.arctan2(z + ep2 * WGS84_B_M * np.sin(beta) ** 3, p - WGS84_E2 * WGS84_A_M * np.cos(beta) ** 3)
    for _ in range(2):
        beta = np.arctan2((1.0 - WGS84_F) * np.sin(lat), np.cos(lat))
        lat = np.arctan2(
            z + ep2 * WGS84_B_M * np.sin(beta) ** 3, p - WGS84_E2 * WGS84_A_M * np.cos(beta) ** 3
        )
    sin_lat = np.sin(lat)
    n = WGS84_A_M / np.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    # Height, well conditioned at all latitudes.
    h = p * np.cos(lat) + (z + WGS84_E2 * n * sin_lat) * sin_lat - n
    return lat, lon, h


def ecef_to_geodetic_point(x_m: float, y_m: float, z_m: float) -> tuple[float, float, float]:
    """:func:`ecef_to_geodetic` of one point, in scalar ``math`` (the same Bowring iterations).

    Plain Python, and written so that numba can compile it into a kernel
    (:mod:`v2v.sensors.gnss.spp` does). Agrees with the array form to float rounding (its
    ``arctan2``/``hypot``/``**`` may be vectorized library variants), not bit for bit.
    """
    lon = math.atan2(y_m, x_m)
    p = math.hypot(x_m, y_m)
    ep2 = WGS84_E2 / (1.0 - WGS84_E2)
    beta = math.atan2(z_m, p * (1.0 - WGS84_F))
    lat = math.atan2(z_m + ep2 * WGS84_B_M * math.sin(beta) ** 3, p - WGS84_E2 * WGS84_A_M * math.cos(beta) ** 3)
    for _ in range(2):
        beta = math.atan2((1.0 - WGS84_F) * math.sin(lat), math.cos(lat))
        lat = math.atan2(z_m + ep2 * WGS84_B_M * math.sin(beta) ** 3, p - WGS84_E2 * WGS84_A_M * math.cos(beta) ** 3)
    sin_lat = math.sin(lat)
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sin_lat**2)
    h = p * math.cos(lat) + (z_m + WGS84_E2 * n * sin_lat) * sin_lat - n
    return lat, lon, h


def ecef_to_enu_rotation(lat_rad: float, lon_rad: float) -> FloatArray:
    """Rotation matrix ``R`` with ``enu = R @ (ecef - ecef_ref)`` at one point (scalar
    ``math`` sines and cosines: several are built per epoch)."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    so, co = math.sin(lon_rad), math.cos(lon_rad)
    return np.array(
        [
            [-so, co, 0.0],
            [-sl * co, -sl * so, cl],
            [cl * co, cl * so, sl],
        ]
    )


def ecef_to_enu(ecef_m: ArrayLike, ref_lat_rad: float, ref_lon_rad: float, ref_ecef_m: ArrayLike) -> FloatArray:
    """ECEF point(s) to ENU at a reference point. Shape ``(..., 3)``."""
    r = ecef_to_enu_rotation(ref_lat_rad, ref_lon_rad)
    d = np.asarray(ecef_m, dtype=float) - np.asarray(ref_ecef_m, dtype=float)
    return d @ r.T


def enu_to_ecef_vector(enu: ArrayLike, ref_lat_rad: float, ref_lon_rad: float) -> FloatArray:
    """Rotate ENU *vector(s)* (not points) to ECEF. Shape ``(..., 3)``."""
    r = ecef_to_enu_rotation(ref_lat_rad, ref_lon_rad)
    return np.asarray(enu, dtype=float) @ r


def azimuth_elevation(enu: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Azimuth (clockwise from north) and elevation, radians, of ENU line-of-sight vector(s)."""
    v = np.asarray(enu, dtype=float)
    az = np.arctan2(v[..., 0], v[..., 1]) % (2.0 * np.pi)
    el = np.arctan2(v[..., 2], np.hypot(v[..., 0], v[..., 1]))
    return az, el


def wrap_angle(angle_rad: ArrayLike) -> FloatArray:
    """Wrap angle(s) to the half-open interval (-pi, pi]."""
    a = np.asarray(angle_rad, dtype=float)
    w = np.mod(a + np.pi, 2.0 * np.pi) - np.pi
    # mod maps +pi to -pi; the convention here keeps +pi.
    return np.where(w == -np.pi, np.pi, w)


def wrap_angle_scalar(angle_rad: float) -> float:
    """:func:`wrap_angle` of one Python float (same result, bit for bit: Python's float ``%``
    is the same fmod-based remainder as ``np.mod``), without numpy's per-call overhead."""
    w = (angle_rad + math.pi) % (2.0 * math.pi) - math.pi
    return math.pi if w == -math.pi else w


def heading_unit_vectors(azimuth_rad: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Forward and left unit vectors in the EN plane for an azimuth (clockwise from north).

    forward = (sin a, cos a); left = forward rotated 90 deg counter-clockwise = (-cos a, sin a).
    """
    a = np.asarray(azimuth_rad, dtype=float)
    fwd = np.stack([np.sin(a), np.cos(a)], axis=-1)
    left = np.stack([-np.cos(a), np.sin(a)], axis=-1)
    return fwd, left


def enu_to_lead_frame(delta_enu: ArrayLike, lead_azimuth_rad: ArrayLike) -> FloatArray:
    """Express ENU vector(s) in the lead vehicle's frame: (along, across-left, up).

    ``along = dE sin a + dN cos a``; ``across = -dE cos a + dN sin a`` (positive to the left).
    """
    d = np.asarray(delta_enu, dtype=float)
    a = np.asarray(lead_azimuth_rad, dtype=float)
    s, c = np.sin(a), np.cos(a)
    along = d[..., 0] * s + d[..., 1] * c
    across = -d[..., 0] * c + d[..., 1] * s
    return np.stack([along, across, d[..., 2]], axis=-1)


@dataclass(frozen=True, kw_only=True)
class GeoReference:
    """Maps net XY (metres) to geodetic coordinates.

    Parameters
    ----------
    proj : str | None
        PROJ string of the net's projection (SUMO ``projParameter``). ``None`` means
        the net has no projection and the tangent origin below is used instead.
    net_offset_m : (float, float)
        SUMO ``netOffset``: ``xy_net = xy_projected + net_offset``.
    origin_lat_deg, origin_lon_deg, origin_h_m : float
        Tangent origin for nets without a projection: net XY = ``net_offset_m`` sits here (the
        offset is taken off first, as for a projected net), so XY (0, 0) does only for a net
        without an offset. ``origin_h_m``: the ellipsoidal height of net z = 0
        (:meth:`xyz_to_ecef`).
    """

    proj: str | None
    net_offset_m: tuple[float, float] = (0.0, 0.0)
    origin_lat_deg: float = 0.0
    origin_lon_deg: float = 0.0
    origin_h_m: float = 0.0

    @cached_property
    def _transformer(self):  # pyproj.Transformer (projected -> lon/lat)
        import pyproj

        if self.proj is None:
            crs = pyproj.CRS.from_proj4(
                f"+proj=tmerc +lat_0={self.origin_lat_deg!r} +lon_0={self.origin_lon_deg!r} "
                "+k=1 +x_0=0 +y_0=0 +ellps=WGS84 +units=m +no_defs"
            )
        else:
            crs = pyproj.CRS.from_proj4(self.proj)
        return pyproj.Transformer.from_crs(crs, crs.geodetic_crs, always_xy=True)

    def xy_to_geodetic(self, x_m: ArrayLike, y_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """Net XY to (lat_rad, lon_rad)."""
        x = np.asarray(x_m, dtype=float) - self.net_offset_m[0]
        y = np.asarray(y_m, dtype=float) - self.net_offset_m[1]
        lon_deg, lat_deg = self._transformer.transform(x, y)
        return np.radians(lat_deg), np.radians(lon_deg)

    def geodetic_to_xy(self, lat_rad: ArrayLike, lon_rad: ArrayLike) -> tuple[FloatArray, FloatArray]:
        """(lat_rad, lon_rad) to net XY."""
        x, y = self._transformer.transform(
            np.degrees(np.asarray(lon_rad, dtype=float)),
            np.degrees(np.asarray(lat_rad, dtype=float)),
            direction="INVERSE",
        )
        return np.asarray(x) + self.net_offset_m[0], np.asarray(y) + self.net_offset_m[1]

    def xyz_to_ecef(self, x_m: ArrayLike, y_m: ArrayLike, z_m: ArrayLike) -> FloatArray:
        """Net XY plus height (metres above the ellipsoid origin height) to ECEF."""
        lat, lon = self.xy_to_geodetic(x_m, y_m)
        return geodetic_to_ecef(lat, lon, np.asarray(z_m, dtype=float) + self.origin_h_m)

    def grid_convergence_rad(self, x_m: float, y_m: float) -> float:
        """Meridian (grid) convergence at a net point, radians.

        ``gamma`` is the angle from grid north (+y) to true north, counter-clockwise
        positive (~ dlon * sin(lat) for transverse Mercator: positive east of the central
        meridian in the northern hemisphere). Hence::

            true_azimuth = grid_azimuth + gamma,   grid_azimuth = true_azimuth - gamma

        Computed numerically from the projection (a ~1 m step north).
        """
        lat, lon = self.xy_to_geodetic(x_m, y_m)
        dlat = 1.0 / 6378137.0
        x2, y2 = self.geodetic_to_xy(lat + dlat, lon)
        # Grid azimuth of true north is atan2(dx, dy); gamma is its negative.
        return -float(np.arctan2(float(x2) - x_m, float(y2) - y_m))
