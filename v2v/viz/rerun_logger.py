"""The rerun implementation of :class:`~v2v.viz.logger.ReplayLogger` (rerun-sdk 0.41).

The only module of v2v, with :mod:`v2v.viz.blueprint`, that imports rerun. The entity
layout is documented in :mod:`v2v.viz.blueprint`.

How it writes
-------------
* A private ``rr.RecordingStream(application_id="v2v")`` (never the global one), saved
  with ``RecordingStream.save`` to a hidden temporary file beside the target; no viewer is
  spawned and nothing touches the network. :meth:`RerunReplayLogger.close` flushes, sends
  the default blueprint (built from the solutions and vehicles actually logged, active and
  default; its chunks made once per process and arguments, :func:`blueprint_chunks`),
  closes the file and renames it to the target with ``os.replace``; on any error, or on
  :meth:`~RerunReplayLogger.abort`, the temporary file is removed and the target is not
  touched.
* Static geometry is logged once with ``static=True``.
* Scene data (boxes, points, ellipses, links, sky plots) is buffered in memory as plain
  numpy rows and sent column-wise with ``RecordingStream.send_columns``
  (``Archetype.columns(...)``; per-instance components ``.partition(lengths)`` with the
  row's instance count, per-row constants such as ``radii`` or a single colour as
  unit-length rows, exactly what ``log`` of the same archetype would have stored) once
  ``flush_rows`` rows are waiting and at close. Building one archetype and calling
  ``log`` per call cost ~0.4 ms (most of the replay's overhead); the recording's content
  is the same: same entity paths, components, values and ``sim_time`` stamps.
* Work is batched, not done per call: the ``*_many`` methods (``log_truth_many``,
  ``log_links_many``, ``log_satellites_many``) and ``log_epochs`` (a solution's estimates
  and errors of many epochs) turn many steps into rows with one vectorized pass per
  entity, and the single-step methods are the same code with one row; ``log_estimates``
  only checks and copies its arguments, the points and
  uncertainty ellipses of all waiting calls are computed together when the scene is sent
  (one batched ``eigh``: the same per-matrix LAPACK call, so the same values). What a
  sweep's runs share is built once and cached: the static scene by its geometry
  (:func:`static_world`: lane triangulation, extruded buildings), the sky-plot grid and
  the default blueprint.
* Error time series are buffered per (solution, vehicle) as blocks of rows of the eight
  series and sent with ``RecordingStream.send_columns(path, [rr.TimeColumn(TIMELINE, duration=t)],
  [column])``, ``column`` the ``rr.ComponentColumn`` of ``Scalars:scalars`` that
  ``rr.Scalars.columns(scalars=...)`` would build (made directly: ~30 us less per entity).

Geometry
--------
* Vehicle box: centre = front bumper - L/2 · heading, at height H/2 above the road
  (z = 0, as for the buildings of :mod:`v2v.world.buildings`); half sizes (L/2, W/2, H/2);
  rotation about +z by the yaw ``psi = pi/2 - alpha_grid`` counter-clockwise from +x, where
  ``alpha_grid`` is the vehicle's grid azimuth (``VehicleState.grid_azimuth_rad``, SUMO's
  angle; the background boxes' too): its true azimuth less the grid convergence at the
  vehicle (:meth:`v2v.frames.GeoReference.grid_convergence_rad`).
* Uncertainty ellipse of probability ``p`` for a 2-D Gaussian: the points ``d`` with
  ``d^T C^-1 d = k^2``, ``k^2 = -2 ln(1 - p)`` (the chi-square quantile with 2 degrees
  of freedom in closed form; p = 0.95 gives k = 2.4477), i.e. semi-axes ``k sqrt(lambda)``
  along the eigenvectors of ``C = V diag(lambda) V^T`` (:func:`ellipse_axes`). It is logged
  as a flat ``Ellipsoids3D`` (half sizes ``(k sqrt(lambda_max), k sqrt(lambda_min), 1 mm)``,
  turned about +z by the major axis's angle, fill mode ``MajorWireframe``) that the viewer
  draws exactly: its three principal cross-sections are the ellipse and, flattened, its
  major and minor axes. 40 bytes per ellipse instead of a 37-vertex outline (444 bytes):
  a 60 s 10-car replay is 3.2 MB instead of 4.8 MB.
  ``C`` is given east/north and rotated into net XY: ``C_xy = R(gamma) C_en R(gamma)^T``,
  ``R`` the counter-clockwise rotation (a true-azimuth direction turns by +gamma
  counter-clockwise in the grid).
* Sky plot: ``x = (90 - el_deg) sin(az)``, ``y = -(90 - el_deg) cos(az)`` (rerun's 2-D
  views have +y pointing down, so the minus puts north at the top and east on the right,
  the usual sky plot); rings at elevations 0, 30, 60 deg.
"""

from __future__ import annotations

import functools
import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from operator import attrgetter
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import rerun as rr
import shapely
from numpy.typing import ArrayLike, NDArray
from rerun.chunk import Chunk

from v2v.frames import GeoReference
from v2v.io.atomic import publish
from v2v.traffic.snapshot import TrafficStep
from v2v.viz import blueprint as bp
from v2v.viz.logger import LINK_STATUSES, Footprint, ReplayLogger

FloatArray = NDArray[np.float64]

LOS_RGB = (40, 200, 80)
NLOS_RGB = (255, 150, 30)
REJECTED_RGB = (230, 30, 30)
STATUS_RGB = {"los": LOS_RGB, "nlos": NLOS_RGB, "rejected": REJECTED_RGB}
LEAD_RGB = (255, 140, 0)
FOLLOWER_RGB = (40, 120, 255)
BACKGROUND_RGB = (150, 150, 150)
BUILDING_RGBA = (200, 200, 205, 255)
FOLIAGE_RGBA = (50, 150, 60, 90)
LANE_SURFACE_RGBA = (70, 70, 75, 255)
LANE_LINE_RGB = (235, 235, 235)
SOLUTION_RGB = (
    (230, 25, 75),
    (60, 180, 75),
    (0, 130, 200),
    (245, 130, 48),
    (145, 30, 180),
    (70, 240, 240),
    (240, 50, 230),
)


@dataclass(frozen=True, kw_only=True)
class RerunReplayParams:
    """How the replay is written.

    Parameters
    ----------
    application_id : str
        rerun application id (the viewer keys blueprints by it).
    recording_id : str | None
        Fixed recording id (e.g. derived from the run's seed); ``None``: random.
    flush_rows : int
        Rows (error-series rows; scene rows, one per step and entity) buffered before
        they are sent with ``send_columns``. Every send costs ~0.5 ms per entity whatever
        its size, so a short run is best sent once, at close (8192 rows: ~100 s of a
        3-car run; at 40 cars with all-pairs bearings ~55 MB of buffered links).
    ellipse_probability : float
        Probability mass inside the drawn uncertainty ellipse (0.95: the 95 % ellipse,
        k = 2.4477 sigma; 1 - exp(-1/2) = 0.3935 gives the 1-sigma ellipse).
    estimate_z_m : float
        Height at which 2-D estimates and their ellipses are drawn (just above the road).
    show_map : bool
        Log geodetic positions and add the MapView to the blueprint.
    """

    application_id: str = "v2v"
    recording_id: str | None = None
    flush_rows: int = 8192
    ellipse_probability: float = 0.95
    estimate_z_m: float = 0.2
    show_map: bool = True

    def __post_init__(self) -> None:
        if not 0.0 < self.ellipse_probability < 1.0:
            raise ValueError(f"ellipse_probability must be in (0, 1), got {self.ellipse_probability}")
        if self.flush_rows < 1:
            raise ValueError(f"flush_rows must be >= 1, got {self.flush_rows}")


# ---------------------------------------------------------------------------- geometry


def triangulate_polygon(xy_m: ArrayLike) -> FloatArray:
    """Triangles ``(T, 3, 2)`` covering a simple polygon ``(K, 2)``, each counter-clockwise.

    Constrained Delaunay triangulation (``shapely.constrained_delaunay_triangles``, GEOS
    >= 3.10): no Steiner points, works for non-convex footprints; the triangle areas add
    up to the polygon's area.
    """
    poly = shapely.Polygon(np.asarray(xy_m, dtype=float)[:, :2])
    if not poly.is_valid:
        poly = shapely.make_valid(poly)
    tris = shapely.get_parts(shapely.constrained_delaunay_triangles(poly))
    if len(tris) == 0:
        return np.zeros((0, 3, 2))
    coords = shapely.get_coordinates(tris).reshape(-1, 4, 2)[:, :3]  # closed rings of 3 + 1 vertices
    e1 = coords[:, 1] - coords[:, 0]
    e2 = coords[:, 2] - coords[:, 0]
    cw = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 0.0
    coords[cw] = coords[cw][:, ::-1]
    return coords


def lane_surface_triangles(lanes: Sequence[tuple[float, FloatArray]]) -> FloatArray:
    """Triangle vertices ``(3 T, 2)`` covering the lane surfaces.

    ``lanes``: per lane its width in metres and its centre line ``(k, 2)`` net XY. Each
    lane is the centre line buffered by half its width (flat caps, mitre joins),
    triangulated with :func:`triangulate_polygon`.
    """
    tris = []
    for width_m, xy in lanes:
        poly = shapely.LineString(xy).buffer(0.5 * width_m, cap_style="flat", join_style="mitre", mitre_limit=3.0)
        for part in shapely.get_parts(poly):
            if part.area > 0.0:
                tris.append(triangulate_polygon(np.asarray(part.exterior.coords)[:-1]))
    return np.concatenate(tris).reshape(-1, 2) if tris else np.zeros((0, 2))


def _time_index(t_s: ArrayLike) -> list[rr.TimeColumn]:
    """The ``sim_time`` index of rows at ``t_s`` (s): durations in nanoseconds, rounded as
    ``set_time(duration=t)`` does (a float array would be truncated)."""
    ns = np.round(np.asarray(t_s, dtype=np.float64) * 1e9).astype(np.int64)
    return [rr.TimeColumn(bp.TIMELINE, duration=ns.astype("timedelta64[ns]"))]


@functools.lru_cache(maxsize=2)
def static_world(
    lanes: tuple[tuple[float, bytes], ...],
    buildings: tuple[tuple[bytes, float], ...],
    foliage: tuple[tuple[bytes, float], ...],
    geo: GeoReference,
    show_map: bool,
) -> tuple[tuple[str, rr.AsComponents], ...]:
    """The static scene as ``(entity path, archetype)`` pairs, to be logged with ``static=True``.

    Lanes: per lane its width in metres and its centre line ``(k, 2)`` net XY; buildings
    and foliage: per area its footprint ``(K, 2)`` net XY and its height in metres; arrays
    as the bytes of float64 arrays, so that the arguments are hashable: the runs of a sweep
    share the network and the scene is built once (lane triangulation and extrusion,
    geodetic lane lines) and only logged again.
    """

    def xy_of(raw: bytes) -> FloatArray:
        return np.frombuffer(raw, dtype=np.float64).reshape(-1, 2)

    # net XY is east-ish / north-ish and z up: said once, so the viewer need not guess the up axis
    out: list[tuple[str, rr.AsComponents]] = [(bp.WORLD, rr.ViewCoordinates.RIGHT_HAND_Z_UP)]
    lane_xy = [xy_of(raw) for _, raw in lanes]
    if lane_xy:
        strips = [np.column_stack([xy, np.full(len(xy), 0.02)]) for xy in lane_xy]
        out.append((bp.LANES, rr.LineStrips3D(strips, radii=0.05, colors=LANE_LINE_RGB)))
        tri = lane_surface_triangles([(w, xy) for (w, _), xy in zip(lanes, lane_xy, strict=True)])
        if len(tri):
            verts = np.column_stack([tri, np.zeros(len(tri))])
            out.append((
                bp.LANE_SURFACE,
                rr.Mesh3D(
                    vertex_positions=verts,
                    triangle_indices=np.arange(len(verts), dtype=np.uint32).reshape(-1, 3),
                    albedo_factor=LANE_SURFACE_RGBA,
                ),
            ))
        if show_map:
            allpts = np.concatenate(lane_xy)
            lat, lon = geo.xy_to_geodetic(allpts[:, 0], allpts[:, 1])
            latlon = np.degrees(np.column_stack([lat, lon]))
            geo_strips = np.split(latlon, np.cumsum([len(xy) for xy in lane_xy])[:-1])
            out.append((
                bp.MAP_LANES,
                rr.GeoLineStrings(lat_lon=geo_strips, radii=rr.Radius.ui_points(1.5), colors=BACKGROUND_RGB),
            ))
    for path, items, rgba in ((bp.BUILDINGS, buildings, BUILDING_RGBA), (bp.FOLIAGE, foliage, FOLIAGE_RGBA)):
        if items:
            v, t, n = extrude_footprints([xy_of(raw) for raw, _ in items], [h for _, h in items])
            out.append((path, rr.Mesh3D(vertex_positions=v, triangle_indices=t, vertex_normals=n, albedo_factor=rgba)))
    return tuple(out)


@functools.lru_cache(maxsize=1)
def sky_grid() -> rr.LineStrips2D:
    """Sky-plot grid (the same for every vehicle): elevation rings 0, 30, 60 deg, N-S and E-W axes."""
    t = np.linspace(0.0, 2.0 * np.pi, 73)
    rings = [np.column_stack([r * np.sin(t), -r * np.cos(t)]) for r in (90.0, 60.0, 30.0)]
    axes = [np.array([[0.0, -90.0], [0.0, 90.0]]), np.array([[-90.0, 0.0], [90.0, 0.0]])]
    return rr.LineStrips2D(
        rings + axes, radii=0.3, colors=(120, 120, 120), labels=["0°", "30°", "60°", "N-S", "E-W"], draw_order=1.0
    )


def _ccw(xy: FloatArray) -> FloatArray:
    x, y = xy[:, 0], xy[:, 1]
    area2 = float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))
    return xy if area2 >= 0.0 else xy[::-1]


def extrude_footprints(
    footprints: Sequence[ArrayLike], heights_m: Sequence[float]
) -> tuple[FloatArray, NDArray[np.uint32], FloatArray]:
    """One triangle mesh for prisms standing on z = 0: roof + walls (no floor).

    Returns ``(vertex_positions (V, 3), triangle_indices (T, 3), vertex_normals (V, 3))``.
    Faces are counter-clockwise seen from outside (front faces in rerun). Vertices are
    not shared between faces, so every face is shaded flat with its own normal: roof
    normal +z, wall normal ``(dy, -dx, 0) / |d|`` for the counter-clockwise edge ``d``.
    """
    pos: list[FloatArray] = []
    nrm: list[FloatArray] = []
    for xy_raw, h in zip(footprints, heights_m, strict=True):
        xy = np.asarray(xy_raw, dtype=float)[:, :2]
        if np.allclose(xy[0], xy[-1]) and len(xy) > 3:
            xy = xy[:-1]
        if len(xy) < 3:
            continue
        xy = _ccw(xy)
        roof = triangulate_polygon(xy).reshape(-1, 2)
        pos.append(np.column_stack([roof, np.full(len(roof), float(h))]))
        nrm.append(np.tile([0.0, 0.0, 1.0], (len(roof), 1)))
        if h <= 0.0:
            continue
        p = xy
        q = np.roll(xy, -1, axis=0)
        d = q - p
        length = np.hypot(d[:, 0], d[:, 1])
        keep = length > 0.0
        p, q, d, length = p[keep], q[keep], d[keep], length[keep]
        z0 = np.zeros(len(p))
        z1 = np.full(len(p), float(h))
        p0, q0 = np.column_stack([p, z0]), np.column_stack([q, z0])
        p1, q1 = np.column_stack([p, z1]), np.column_stack([q, z1])
        # two triangles per wall: (p0, q0, q1) and (p0, q1, p1)
        wall = np.stack([p0, q0, q1, p0, q1, p1], axis=1).reshape(-1, 3)
        n = np.column_stack([d[:, 1] / length, -d[:, 0] / length, z0])
        pos.append(wall)
        nrm.append(np.repeat(n, 6, axis=0))
    if not pos:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.uint32), np.zeros((0, 3))
    vertices = np.concatenate(pos)
    normals = np.concatenate(nrm)
    triangles = np.arange(len(vertices), dtype=np.uint32).reshape(-1, 3)
    return vertices, triangles, normals


def ellipse_scale(probability: float) -> float:
    """``k`` such that a 2-D Gaussian lies inside ``d^T C^-1 d <= k^2`` with ``probability``.

    The Mahalanobis distance squared of a 2-D Gaussian is chi-square with 2 degrees of
    freedom, whose CDF is ``1 - exp(-k^2 / 2)``; hence ``k = sqrt(-2 ln(1 - p))``.
    """
    return math.sqrt(-2.0 * math.log1p(-probability))


def ellipse_axes(cov_m2: ArrayLike, k: float) -> tuple[FloatArray, FloatArray]:
    """Semi-axes ``(n, 2)`` (major, minor) and major-axis angles ``(n,)`` (rad, counter-clockwise
    from +x) of the ellipses ``d^T C^-1 d = k^2``: ``k sqrt(lambda)`` along the eigenvectors of
    ``C = V diag(lambda) V^T`` (``numpy.linalg.eigh``, negative round-off clipped to 0)."""
    cov = np.asarray(cov_m2, dtype=float).reshape(-1, 2, 2)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    lam, vec = np.linalg.eigh(cov)  # ascending: column 1 is the major axis
    half = k * np.sqrt(np.clip(lam[:, ::-1], 0.0, None))
    return half, np.arctan2(vec[:, 1, 1], vec[:, 0, 1])


# half size of the flat ellipsoid drawn as an ellipse, along z: 1 mm rather than 0 keeps the
# instance's scale invertible; its two vertical cross-sections are then lines along the axes
ELLIPSE_HALF_THICKNESS_M = 1e-3
# the ellipses' fill mode as the component's arrow value (uint8): rerun parses a name per row
_MAJOR_WIREFRAME = pa.scalar(rr.components.FillMode.MajorWireframe.value, pa.uint8())


def quaternions_about_z(angle_rad: ArrayLike) -> FloatArray:
    """Unit quaternions ``(n, 4)``, rerun's (x, y, z, w) order, of rotations by ``angle_rad``
    counter-clockwise about +z."""
    half = 0.5 * np.asarray(angle_rad, dtype=float).reshape(-1)
    return np.column_stack([np.zeros((len(half), 2)), np.sin(half), np.cos(half)])


def rotation_2d(angle_rad: float) -> FloatArray:
    """Counter-clockwise rotation matrix."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s], [s, c]])


def sky_xy(az_rad: ArrayLike, el_rad: ArrayLike) -> FloatArray:
    """Sky-plot coordinates ``(k, 2)`` in degrees of zenith distance, north up (y down)."""
    az = np.asarray(az_rad, dtype=float)
    zen_deg = 90.0 - np.degrees(np.asarray(el_rad, dtype=float))
    return np.column_stack([zen_deg * np.sin(az), -zen_deg * np.cos(az)])


def _offset_lines(xy: FloatArray, width_m: float) -> list[FloatArray]:
    line = shapely.LineString(xy)
    out: list[FloatArray] = []
    for side in (0.5 * width_m, -0.5 * width_m):
        off = line.offset_curve(side)
        out.extend(np.asarray(g.coords) for g in shapely.get_parts(off) if not g.is_empty)
    return out


# ---------------------------------------------------------------------------- scene buffer

# rerun.components.LineStrip3D's arrow type (rerun-sdk 0.41): a list of non-null
# FixedSizeList<float32, 3> points
_VEC3_ARROW = pa.list_(pa.field("item", pa.float32(), nullable=False), 3)
_STRIP3_ARROW = pa.list_(pa.field("item", _VEC3_ARROW, nullable=False))


def strips3d_arrow(strips: NDArray[np.floating]) -> pa.Array:
    """Line strips of equal length, ``(n_strips, n_points, 3)``, as the ``LineStrip3D``
    arrow array rerun builds from that array (points cast to float32, offsets
    ``n_points`` apart), without rerun's Python loop over the strips' offsets (one ``len``
    call per strip, ~0.4-1.5 us: links and ellipses are tens of thousands of strips a
    minute). rerun uses an arrow array of its component's type as it is."""
    if strips.ndim != 3 or strips.shape[2] != 3:
        raise ValueError(f"strips must be (n_strips, n_points, 3), got shape {strips.shape}")
    n, k, _ = strips.shape
    points = pa.FixedSizeListArray.from_arrays(np.ascontiguousarray(strips, dtype=np.float32).reshape(-1), type=_VEC3_ARROW)
    return pa.ListArray.from_arrays(np.arange(n + 1, dtype=np.int32) * np.int32(k), points, type=_STRIP3_ARROW)


class _SceneRows:
    """Rows of one archetype on one entity path, waiting for ``send_columns``.

    ``per_instance`` components hold one array per row (leading axis = the row's
    instance count, equal across those components; ``labels``: a list of str, which every
    caller converts them to); ``per_row`` components hold one
    value per row (logged as a unit-length batch, like a scalar passed to ``log``).
    ``key`` is the archetype plus both component-name sets: a row with another key
    cannot share the columns and makes the caller flush this buffer first.
    """

    __slots__ = ("archetype", "key", "times", "lengths", "per_instance", "per_row")

    def __init__(self, archetype: type[Any], per_instance: Mapping[str, object], per_row: Mapping[str, object]):
        self.archetype = archetype
        self.key = (archetype, tuple(per_instance), tuple(per_row))
        self.times: list[float] = []
        self.lengths: list[int] = []
        self.per_instance: dict[str, list] = {name: [] for name in per_instance}
        self.per_row: dict[str, list] = {name: [] for name in per_row}

    def add(
        self, t_s: float, n: int, per_instance: Mapping[str, object], per_row: Mapping[str, object]
    ) -> None:
        self.times.append(t_s)
        self.lengths.append(n)
        for name, value in per_instance.items():
            self.per_instance[name].append(value)
        for name, value in per_row.items():
            self.per_row[name].append(value)

    def add_many(
        self,
        t_s: Sequence[float],
        lengths: Sequence[int],
        per_instance: Mapping[str, object],
        per_row: Mapping[str, object],
    ) -> None:
        """Rows one after another: ``per_instance`` components hold all the rows' instances
        concatenated (``sum(lengths)`` long), ``per_row`` components one value for every row."""
        self.times.extend(t_s)
        self.lengths.extend(lengths)
        for name, value in per_instance.items():
            self.per_instance[name].append(value)
        n = len(t_s)
        for name, value in per_row.items():
            self.per_row[name].extend([value] * n)

    def send(self, rec: rr.RecordingStream, path: str) -> int:
        n_rows = len(self.times)
        if n_rows == 0:
            return 0
        # nanoseconds rounded as ``set_time(duration=t)`` does (``rerun.time.to_nanos``); a
        # float array given to ``TimeColumn`` would be truncated instead (4.1 s -> 4099999999 ns)
        index = _time_index(self.times)
        cols: list[rr.ComponentColumn] = []
        if self.per_instance:
            merged: dict[str, object] = {}
            for name, rows in self.per_instance.items():
                if name == "labels":  # one utf8 array, which rerun takes as it is (it would str() each label)
                    merged[name] = pa.array([x for row in rows for x in row], type=pa.utf8())
                else:
                    cat = np.concatenate(rows)
                    merged[name] = strips3d_arrow(cat) if name == "strips" and self.archetype is rr.LineStrips3D else cat
            cols.extend(self.archetype.columns(**merged).partition(np.asarray(self.lengths)))
        if self.per_row:
            cols.extend(self.archetype.columns(**{
                # an arrow scalar (an enum's raw value) goes to rerun as arrow, which it takes as it is
                name: pa.array(v, type=v[0].type) if isinstance(v[0], pa.Scalar) else np.asarray(v)
                for name, v in self.per_row.items()
            }))
        rec.send_columns(path, indexes=index, columns=cols)
        self.times.clear()
        self.lengths.clear()
        for rows in (*self.per_instance.values(), *self.per_row.values()):
            rows.clear()
        return n_rows


# log_errors' value order (along, across, sigma_along, sigma_across, nees, nis, n_sats,
# rejections) -> bp.ERROR_SERIES order (along, along_sigma, across, across_sigma, ...)
_N_ERROR_VALUES = 8
_ERROR_COLUMNS = [0, 2, 1, 3, 4, 5, 6, 7]


class _ErrorRows:
    """Error time-series rows of one (solution, vehicle), waiting for ``send_columns``:
    blocks of times ``(k,)`` and rows ``(k, 8)``, one value per series per row, in
    :meth:`RerunReplayLogger.log_errors`' order."""

    __slots__ = ("paths", "times", "rows")

    def __init__(self, paths: tuple[str, ...]):
        self.paths = paths
        self.times: list[FloatArray] = []
        self.rows: list[FloatArray] = []


# ---------------------------------------------------------------------------- blueprint


@functools.lru_cache(maxsize=8)
def blueprint_chunks(
    application_id: str,
    solutions: tuple[str, ...],
    vehicle_ids: tuple[str, ...],
    sky_vehicle_ids: tuple[str, ...],
    show_map: bool,
) -> tuple[Chunk, ...]:
    """The chunks of the default blueprint (:func:`v2v.viz.blueprint.default_blueprint`), made
    once per process and arguments: what ``RecordingStream.send_blueprint`` would store.

    ``send_blueprint`` builds the blueprint's archetypes in Python and logs them anew for
    every recording (13-28 ms at 20 vehicles, 4-7 ms at 3), and rerun drains the in-memory
    blueprint it sends, so it cannot be sent twice. Here it is built once with rerun's own
    helper (``create_in_memory_blueprint``, which ``send_blueprint`` calls), encoded, and read
    back as chunks (``rerun.chunk.RrdReader``), which every later recording of the process (a
    sweep worker's runs) re-sends with :func:`send_blueprint_chunks` in ~1-3 ms. The content
    is the same as ``send_blueprint``'s, the blueprint's ``log_time`` stamps aside (those of the
    first build; test: ``test_blueprint_chunks_are_what_send_blueprint_stores``).
    """
    from rerun.blueprint.api import create_in_memory_blueprint
    from rerun.chunk import RrdReader

    blueprint = bp.default_blueprint(solutions, vehicle_ids, sky_vehicle_ids, show_map=show_map)
    encoded = create_in_memory_blueprint(application_id=application_id, blueprint=blueprint).storage.drain_as_bytes()
    with tempfile.TemporaryDirectory(prefix="v2v-blueprint-") as folder:
        path = Path(folder) / "default.rbl"
        path.write_bytes(encoded)
        reader = RrdReader(path)
        (store,) = reader.blueprints()
        return tuple(reader.stream(store=store))


@functools.lru_cache(maxsize=1024)
def series_style_chunks(solution: str, vehicle_id: str, rgb: tuple[int, int, int]) -> tuple[Chunk, ...]:
    """The static styles of (``solution``, ``vehicle_id``)'s error series
    (:func:`v2v.viz.blueprint.series_style` on each :func:`v2v.viz.blueprint.error_path`), one
    chunk per series: what ``rec.log(path, style, static=True)`` stores, made once per process
    and arguments. Logging the 8 styles of a vehicle costs ~1.3 ms (12 ms of a 10-car run's
    replay, ~100 ms in all); a sweep worker's later runs send the same chunks in ~30 us."""
    out = []
    for series in bp.ERROR_SERIES:
        style = bp.series_style(series, solution, vehicle_id, rgb)
        columns = [b.partition([len(b.as_arrow_array())]) for b in style.as_component_batches()]  # one row each
        out.append(Chunk.from_columns(bp.error_path(solution, vehicle_id, series), indexes=[], columns=columns))
    return tuple(out)


def send_blueprint_chunks(rec: rr.RecordingStream, application_id: str, chunks: Sequence[Chunk]) -> None:
    """Send ``chunks`` (:func:`blueprint_chunks`) to ``rec`` as a new blueprint, made active and
    default: what ``rec.send_blueprint(..., make_active=True, make_default=True)`` does, the
    chunks going into a fresh blueprint store (rerun's ``new_blueprint``) instead of being
    logged from the Python objects."""
    from rerun import bindings
    from rerun.recording_stream import RecordingStream

    stream = RecordingStream._from_native(
        bindings.new_blueprint(application_id=application_id, make_default=False, make_thread_default=False,
                               default_enabled=True)
    )
    storage = stream.memory_recording()
    rr.send_chunks(chunks, recording=stream)
    bindings.send_blueprint(storage.storage, make_active=True, make_default=True, recording=rec.to_native())


# ---------------------------------------------------------------------------- logger


class RerunReplayLogger(ReplayLogger):
    """Writes a run's replay to ``path`` (an ``.rrd``), atomically on :meth:`close`."""

    def __init__(self, path: str | Path, *, params: RerunReplayParams | None = None) -> None:
        self.path = Path(path)
        self.params = params or RerunReplayParams()
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        os.close(fd)
        self._tmp_path = Path(tmp)
        self._rec = rr.RecordingStream(
            application_id=self.params.application_id,
            recording_id=self.params.recording_id,
            send_properties=False,
        )
        self._rec.set_log_time_enabled(False)  # wall-clock timelines would make files differ run to run
        self._rec.set_log_tick_enabled(False)
        self._rec.save(self._tmp_path)
        self._closed = False
        self._k = ellipse_scale(self.params.ellipse_probability)
        self._gamma_rad = 0.0
        self._rot_en_to_xy = np.eye(2)
        # error series buffers: (solution, vehicle) -> its ERROR_SERIES paths, times, value rows
        self._errors: dict[tuple[str, str], _ErrorRows] = {}
        self._buffered_rows = 0
        # estimates not yet turned into rows: (times, vehicles per time, (solution, cluster), labels, xy, cov_en)
        self._estimates: list[tuple[list[float], list[int], tuple[str, str], list[str], FloatArray, FloatArray]] = []
        self._estimate_times = 0  # times waiting in _estimates (each makes a points and an ellipses row)
        self._scene: dict[str, _SceneRows] = {}
        self._scene_rows = 0
        self.scene_rows_sent = 0  # scene rows (one per logging call and entity) sent with send_columns
        self.rows_sent = 0  # scalar rows sent with send_columns, summed over all errors/** entities
        self._solutions: dict[str, None] = {}
        self._error_vehicles: dict[str, None] = {}
        self._sky_vehicles: dict[str, None] = {}
        self._solution_rgb: dict[str, tuple[int, int, int]] = {}

    # -- helpers ------------------------------------------------------------------

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"replay logger for {self.path} is closed")

    def _at(self, t_s: float) -> None:
        self._check_open()

    def _add_row(
        self,
        path: str,
        archetype: type,
        t_s: float,
        n: int,
        per_instance: Mapping[str, object],
        per_row: Mapping[str, object],
    ) -> None:
        """Buffer one row of ``archetype`` at ``path`` (what one ``log`` at ``t_s`` would store)."""
        self._scene_buffer(path, archetype, per_instance, per_row).add(float(t_s), int(n), per_instance, per_row)
        self._scene_rows += 1
        if self._scene_rows >= self.params.flush_rows:
            self._flush_scene()

    def _add_rows(
        self,
        path: str,
        archetype: type,
        t_s: Sequence[float],
        lengths: Sequence[int],
        per_instance: Mapping[str, object],
        per_row: Mapping[str, object],
    ) -> None:
        """Buffer rows at the times ``t_s`` with ``lengths`` instances each: what one ``log``
        per row would store (see :meth:`_SceneRows.add_many` for the layout)."""
        if len(t_s) == 0:
            return
        self._scene_buffer(path, archetype, per_instance, per_row).add_many(t_s, lengths, per_instance, per_row)
        self._scene_rows += len(t_s)
        if self._scene_rows >= self.params.flush_rows:
            self._flush_scene()

    def _scene_buffer(
        self, path: str, archetype: type, per_instance: Mapping[str, object], per_row: Mapping[str, object]
    ) -> _SceneRows:
        """The buffer of ``path``; rows with other components send the waiting ones first."""
        buf = self._scene.get(path)
        if buf is not None and buf.key != (archetype, tuple(per_instance), tuple(per_row)):
            self.scene_rows_sent += buf.send(self._rec, path)
            buf = None
        if buf is None:
            buf = self._scene[path] = _SceneRows(archetype, per_instance, per_row)
        return buf

    def _flush_scene(self) -> None:
        self._estimate_rows()
        for path, buf in self._scene.items():
            self.scene_rows_sent += buf.send(self._rec, path)
        self._scene_rows = 0

    def _color_of(self, solution: str) -> tuple[int, int, int]:
        if solution not in self._solution_rgb:
            self._solution_rgb[solution] = SOLUTION_RGB[len(self._solution_rgb) % len(SOLUTION_RGB)]
        return self._solution_rgb[solution]

    # -- static world ---------------------------------------------------------------

    def log_world(
        self,
        lanes: Mapping[str, ArrayLike],
        lane_widths: Mapping[str, float],
        buildings: Sequence[Footprint],
        foliage: Sequence[Footprint],
        geo: GeoReference,
    ) -> None:
        self._check_open()
        lane_xy = {
            lid: np.asarray(xy, dtype=float).reshape(-1, np.shape(xy)[-1])[:, :2] for lid, xy in lanes.items()
        }
        lane_xy = {lid: xy for lid, xy in lane_xy.items() if len(xy) >= 2}
        if lane_xy:
            allpts = np.concatenate(list(lane_xy.values()))
            cx, cy = (allpts.min(axis=0) + allpts.max(axis=0)) / 2.0
            self._estimate_rows()  # estimates logged before keep the rotation they were logged with
            self._gamma_rad = geo.grid_convergence_rad(float(cx), float(cy))
            self._rot_en_to_xy = rotation_2d(self._gamma_rad)

        def areas(items: Sequence[Footprint]) -> tuple[tuple[bytes, float], ...]:
            return tuple(
                (np.ascontiguousarray(np.asarray(b.footprint_xy_m, dtype=float)[:, :2]).tobytes(), float(b.height_m))
                for b in items
            )

        world = static_world(
            tuple((float(lane_widths.get(lid, 3.2)), xy.tobytes()) for lid, xy in lane_xy.items()),
            areas(buildings),
            areas(foliage),
            geo,
            self.params.show_map,
        )
        for path, archetype in world:
            self._rec.log(path, archetype, static=True)

    # -- truth ----------------------------------------------------------------------

    def log_truth(self, t_s: float, step: TrafficStep) -> None:
        self._truth_rows([float(t_s)], [step])

    def log_truth_many(self, steps: Sequence[TrafficStep]) -> None:
        """All steps' truth rows in a few vectorized calls (the same rows as :meth:`log_truth`)."""
        steps = list(steps)
        self._truth_rows([float(st.t_s) for st in steps], steps)

    def _truth_rows(self, times: list[float], steps: list[TrafficStep]) -> None:
        self._check_open()
        if not steps:
            return
        # runs of steps with and without cluster vehicles: an empty step stores only
        # ``half_sizes`` (as ``log`` would), which sends the rows waiting before it
        start = 0
        for k in range(1, len(steps) + 1):
            if k == len(steps) or bool(steps[k].vehicles) != bool(steps[start].vehicles):
                if steps[start].vehicles:
                    self._vehicle_rows(times[start:k], steps[start:k])
                else:
                    self._add_rows(bp.TRUTH, rr.Boxes3D, times[start:k], [0] * (k - start),
                                   {"half_sizes": np.zeros((0, 3))}, {})
                start = k
        bgs = [np.asarray(st.background, dtype=float).reshape(-1, 6) for st in steps]
        bg = np.concatenate(bgs)
        yaw_bg = 0.5 * np.pi - bg[:, 2]  # (their angle is SUMO's: already the grid azimuth)
        self._add_rows(
            bp.BACKGROUND,
            rr.Boxes3D,
            times,
            [len(b) for b in bgs],
            {
                "half_sizes": 0.5 * bg[:, 3:6],
                "centers": np.column_stack([bg[:, :2], 0.5 * bg[:, 5]]),
                "quaternions": quaternions_about_z(yaw_bg),
            },
            {"colors": np.array(BACKGROUND_RGB, dtype=np.uint8)},
        )

    def _vehicle_rows(self, times: list[float], steps: list[TrafficStep]) -> None:
        """Boxes, antennas (and map points) of steps that all have cluster vehicles."""
        states = [s for st in steps for s in st.vehicles.values()]
        lengths = [len(st.vehicles) for st in steps]
        n = len(states)

        def column(name: str, dtype: type = float) -> NDArray[Any]:
            return np.fromiter(map(attrgetter(name), states), dtype=dtype, count=n)

        grid_az = column("grid_azimuth_rad")
        fwd = np.column_stack([np.sin(grid_az), np.cos(grid_az)])
        size = np.column_stack([column("length_m"), column("width_m"), column("height_m")])
        front = np.concatenate([s.front_bumper_xy_m for s in states]).reshape(-1, 2)
        centre_xy = front - 0.5 * size[:, :1] * fwd
        centres = np.column_stack([centre_xy, 0.5 * size[:, 2]])
        yaw = 0.5 * np.pi - grid_az
        quat = quaternions_about_z(yaw)
        colors = np.where(column("is_lead", bool)[:, None], np.array(LEAD_RGB, dtype=np.uint8),
                          np.array(FOLLOWER_RGB, dtype=np.uint8))
        self._add_rows(
            bp.TRUTH,
            rr.Boxes3D,
            times,
            lengths,
            {
                "half_sizes": 0.5 * size,
                "centers": centres,
                "quaternions": quat,
                "colors": colors,
                "labels": [s.vehicle_id for s in states],
            },
            {},
        )
        antennas = np.concatenate([s.xyz_m for s in states]).reshape(-1, 3).astype(float, copy=False)
        self._add_rows(
            bp.TRUTH_ANTENNAS, rr.Points3D, times, lengths, {"positions": antennas, "colors": colors}, {"radii": 0.1}
        )
        if self.params.show_map:
            latlon = np.degrees(np.column_stack([column("lat_rad"), column("lon_rad")]))
            self._add_rows(
                bp.MAP_VEHICLES,
                rr.GeoPoints,
                times,
                lengths,
                {"positions": latlon, "colors": colors},
                # rerun annotates ui_points as returning ArrayLike (it is a 0-d float32 array)
                {"radii": float(rr.Radius.ui_points(5.0))},  # type: ignore[arg-type]
            )

    # -- estimates --------------------------------------------------------------------

    def log_estimates(
        self,
        t_s: float,
        solution: str,
        vehicle_ids: Sequence[str],
        est_xy_m: ArrayLike,
        cov_en_m2: ArrayLike,
        cluster: str = "",
    ) -> None:
        """Checked and copied now; points and ellipses are made for all waiting calls at
        once (:meth:`_estimate_rows`) when the scene is sent."""
        self._check_open()
        xy = np.array(est_xy_m, dtype=float).reshape(-1, 2)
        cov = np.array(cov_en_m2, dtype=float).reshape(-1, 2, 2)
        if not (len(xy) == len(cov) == len(vehicle_ids)):
            raise ValueError(
                f"log_estimates: {len(vehicle_ids)} ids, {len(xy)} positions, {len(cov)} covariances"
            )
        self._add_estimates([float(t_s)], [len(xy)], solution, [str(v) for v in vehicle_ids], xy, cov, cluster)

    def _add_estimates(self, times: list[float], lengths: list[int], solution: str, labels: list[str],
                       xy: FloatArray, cov: FloatArray, cluster: str = "") -> None:
        self._solutions.setdefault(solution)
        self._color_of(solution)
        self._estimates.append((times, lengths, (solution, str(cluster)), labels, xy, cov))
        self._estimate_times += len(times)
        if self._scene_rows + 2 * self._estimate_times >= self.params.flush_rows:  # a points and an ellipses row
            self._flush_scene()

    def _estimate_rows(self) -> None:
        """Turn the waiting :meth:`log_estimates` calls into points and ellipse rows, one
        vectorized pass per solution (rows in call order)."""
        if not self._estimates:
            return
        pending, self._estimates = self._estimates, []
        self._estimate_times = 0
        by_solution: dict[tuple[str, str], list[tuple[list[float], list[int], tuple[str, str], list[str],
                                                      FloatArray, FloatArray]]] = {}
        for e in pending:
            by_solution.setdefault(e[2], []).append(e)
        r = self._rot_en_to_xy
        z = self.params.estimate_z_m
        for (solution, cluster), calls in by_solution.items():
            times = [t for c in calls for t in c[0]]
            lengths = np.array([n for c in calls for n in c[1]], dtype=int)
            xy = np.concatenate([c[4] for c in calls])
            cov_xy = r @ np.concatenate([c[5] for c in calls]) @ r.T
            rgb_u8 = np.array(self._color_of(solution), dtype=np.uint8)
            self._add_rows(
                bp.estimates_path(solution, cluster),
                rr.Points3D,
                times,
                lengths.tolist(),
                {"positions": np.column_stack([xy, np.full(len(xy), z)]), "labels": [v for c in calls for v in c[3]]},
                {"radii": 0.12, "colors": rgb_u8},
            )
            ok = np.all(np.isfinite(cov_xy), axis=(1, 2)) & np.all(np.isfinite(xy), axis=1)
            ok_before = np.concatenate([[0], np.cumsum(ok)])  # drawn ellipses before each instance
            ends = np.cumsum(lengths)
            n_ok = ok_before[ends] - ok_before[ends - lengths]
            half, yaw = ellipse_axes(cov_xy[ok], self._k)
            n = len(half)
            self._add_rows(
                bp.ellipses_path(solution, cluster),
                rr.Ellipsoids3D,
                times,
                n_ok.tolist(),
                {
                    "half_sizes": np.column_stack([half, np.full(n, ELLIPSE_HALF_THICKNESS_M)]),
                    "centers": np.column_stack([xy[ok], np.full(n, z)]),
                    "quaternions": quaternions_about_z(yaw),
                },
                {"line_radii": 0.03, "colors": rgb_u8, "fill_mode": _MAJOR_WIREFRAME},
            )

    # -- links ------------------------------------------------------------------------

    def log_links(
        self, t_s: float, kind: str, a_xyz_m: ArrayLike, b_xyz_m: ArrayLike, status: Sequence[str]
    ) -> None:
        status_arr = np.asarray(status, dtype=str).reshape(-1)
        self.log_links_many([t_s], kind, [len(status_arr)], a_xyz_m, b_xyz_m, status_arr)

    def log_links_many(
        self,
        t_s: ArrayLike,
        kind: str,
        counts: ArrayLike,
        a_xyz_m: ArrayLike,
        b_xyz_m: ArrayLike,
        status: Sequence[str] | NDArray[np.str_],
    ) -> None:
        self._check_open()
        times = np.asarray(t_s, dtype=float).reshape(-1).tolist()
        lengths = np.asarray(counts, dtype=int).reshape(-1).tolist()
        a = np.asarray(a_xyz_m, dtype=float).reshape(-1, 3)
        b = np.asarray(b_xyz_m, dtype=float).reshape(-1, 3)
        status_arr = np.asarray(status, dtype=str).reshape(-1)
        if not (len(a) == len(b) == len(status_arr) == sum(lengths)) or len(times) != len(lengths):
            raise ValueError(
                f"log_links: {len(a)} starts, {len(b)} ends, {len(status_arr)} statuses, "
                f"{sum(lengths)} links in {len(lengths)} counts for {len(times)} times"
            )
        code = np.full(len(status_arr), -1)
        for i, name in enumerate(LINK_STATUSES):
            code[status_arr == name] = i
        if (code < 0).any():
            bad = sorted(set(status_arr[code < 0].tolist()))
            raise ValueError(f"log_links: unknown status {bad}; expected one of {LINK_STATUSES}")
        colors = np.array([STATUS_RGB[s] for s in LINK_STATUSES], dtype=np.uint8)[code]
        self._add_rows(
            bp.links_path(kind),
            rr.LineStrips3D,
            times,
            lengths,
            {"strips": np.stack([a, b], axis=1), "colors": colors},
            {"radii": 0.04},
        )

    # -- satellites --------------------------------------------------------------------

    def log_satellites(
        self,
        t_s: float,
        vehicle_id: str,
        prn: ArrayLike,
        az_rad: ArrayLike,
        el_rad: ArrayLike,
        los: ArrayLike,
    ) -> None:
        prn = np.asarray(prn).reshape(-1)
        self.log_satellites_many([t_s], [vehicle_id], [len(prn)], prn, az_rad, el_rad, los)

    def log_satellites_many(
        self,
        t_s: ArrayLike,
        vehicle_ids: Sequence[str],
        counts: ArrayLike,
        prn: ArrayLike,
        az_rad: ArrayLike,
        el_rad: ArrayLike,
        los: ArrayLike,
    ) -> None:
        self._check_open()
        times = np.asarray(t_s, dtype=float).reshape(-1).tolist()
        lengths = np.asarray(counts, dtype=int).reshape(-1)
        vehicle_ids = list(vehicle_ids)
        for v in vehicle_ids:
            if v not in self._sky_vehicles:
                self._sky_vehicles[v] = None
                self._log_sky_grid(v)
        xy = sky_xy(az_rad, el_rad)
        los_b = np.asarray(los, dtype=bool).reshape(-1)
        labels = [str(p) for p in np.asarray(prn).reshape(-1)]
        if not (len(xy) == len(los_b) == len(labels) == lengths.sum()) or not (
            len(times) == len(lengths) == len(vehicle_ids)
        ):
            raise ValueError(
                f"log_satellites: {len(labels)} PRNs, {len(xy)} directions, {len(los_b)} LOS flags, "
                f"{lengths.sum()} satellites in {len(lengths)} counts for {len(times)} times"
            )
        colors = np.where(los_b[:, None], np.array(LOS_RGB), np.array(NLOS_RGB)).astype(np.uint8)
        rows_of: dict[str, list[int]] = {}
        for j, v in enumerate(vehicle_ids):
            rows_of.setdefault(v, []).append(j)
        starts = np.cumsum(lengths) - lengths
        for v, rows in rows_of.items():
            if len(rows) == len(vehicle_ids):  # one vehicle: all instances, in order
                inst = np.arange(len(labels))
            else:
                inst = np.concatenate([np.arange(starts[j], starts[j] + lengths[j]) for j in rows])
            self._add_rows(
                bp.sky_path(v),
                rr.Points2D,
                [times[j] for j in rows],
                lengths[rows].tolist(),
                {"positions": xy[inst], "colors": colors[inst], "labels": [labels[i] for i in inst.tolist()]},
                {"radii": 2.5, "draw_order": 10.0},
            )

    def _log_sky_grid(self, vehicle_id: str) -> None:
        self._rec.log(bp.sky_grid_path(vehicle_id), sky_grid(), static=True)

    # -- error time series --------------------------------------------------------------

    def log_errors(
        self,
        t_s: float,
        solution: str,
        vehicle_id: str,
        along_m: float,
        across_m: float,
        sigma_along_m: float,
        sigma_across_m: float,
        nees: float,
        nis: float,
        n_sats: int,
        rejections: int,
    ) -> None:
        self.log_errors_many(t_s, solution, [vehicle_id], [(along_m, across_m, sigma_along_m, sigma_across_m, nees,
                                                             nis, n_sats, rejections)])

    def log_errors_many(self, t_s: float, solution: str, vehicle_ids: Sequence[str],
                        rows: Sequence[Sequence[float]]) -> None:
        """:meth:`log_errors` of several vehicles at one time, the rows copied as float64 now."""
        self._check_open()
        try:
            values = np.array(rows, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"log_errors_many: rows must be {_N_ERROR_VALUES} numbers each ({exc})") from None
        if values.shape != (len(vehicle_ids), _N_ERROR_VALUES):
            raise ValueError(f"log_errors_many: {len(vehicle_ids)} vehicle ids and {len(rows)} rows "
                             f"of {_N_ERROR_VALUES} numbers each expected, got rows of shape {values.shape}")
        self._add_errors(np.full(len(values), float(t_s)), solution, list(vehicle_ids), values)

    def log_epochs(
        self,
        t_s: ArrayLike,
        solution: str,
        counts: ArrayLike,
        vehicle_ids: Sequence[str],
        est_xy_m: ArrayLike,
        cov_en_m2: ArrayLike,
        errors: ArrayLike,
        cluster: str = "",
    ) -> None:
        """Estimates and errors of many epochs of one solution (of ``cluster``) (see
        :meth:`v2v.viz.logger.ReplayLogger.log_epochs`): the same rows as a
        :meth:`log_errors_many` and a :meth:`log_estimates` per epoch, buffered in a few
        vectorized steps (``v2v.run`` logs each 30 s chunk of a solution so)."""
        self._check_open()
        times = np.asarray(t_s, dtype=float).reshape(-1)
        lengths = np.asarray(counts, dtype=int).reshape(-1)
        ids = [str(v) for v in vehicle_ids]
        xy = np.array(est_xy_m, dtype=float).reshape(-1, 2)
        cov = np.array(cov_en_m2, dtype=float).reshape(-1, 2, 2)
        values = np.array(errors, dtype=np.float64).reshape(-1, _N_ERROR_VALUES)
        if not (len(times) == len(lengths) and (lengths >= 0).all()
                and len(ids) == len(xy) == len(cov) == len(values) == lengths.sum()):
            raise ValueError(f"log_epochs: {len(times)} times and {len(lengths)} counts (adding up to "
                             f"{lengths.sum()}) for {len(ids)} vehicle ids, {len(xy)} positions, {len(cov)} "
                             f"covariances and {len(values)} error rows of {_N_ERROR_VALUES} numbers")
        self._add_errors(np.repeat(times, lengths), solution, ids, values)
        self._add_estimates(times.tolist(), lengths.tolist(), solution, ids, xy, cov, cluster)

    def log_error_gaps(self, t_s: ArrayLike, solution: str, vehicle_ids: Sequence[str]) -> None:
        """A non-recursive ``Clear`` on each of the vehicle's error series at each gap's start:
        rerun's time-series plots draw a clear as a hole in the line (``rr.Clear``'s docs),
        where without it the line would join the rows before and after the gap."""
        self._check_open()
        times = np.asarray(t_s, dtype=float).reshape(-1)
        ids = [str(v) for v in vehicle_ids]
        if len(times) != len(ids):
            raise ValueError(f"log_error_gaps: {len(times)} times for {len(ids)} vehicle ids")
        for v in dict.fromkeys(ids):
            sel = np.array([x == v for x in ids])
            index = _time_index(times[sel])
            columns = rr.Clear.columns(is_recursive=[False] * int(sel.sum()))
            for series in bp.ERROR_SERIES:
                self._rec.send_columns(bp.error_path(solution, v, series), indexes=index, columns=columns)

    def _add_errors(self, times: FloatArray, solution: str, vehicle_ids: list[str], values: FloatArray) -> None:
        """Rows ``values[j]`` of ``vehicle_ids[j]`` at ``times[j]``, sorted into each vehicle's
        buffer (in order; a vehicle's first row logs its series' styles)."""
        errors = self._errors
        code = {v: k for k, v in enumerate(dict.fromkeys(vehicle_ids))}  # vehicles by first appearance
        of = np.fromiter(map(code.__getitem__, vehicle_ids), dtype=np.intp, count=len(vehicle_ids))
        order = np.argsort(of, kind="stable")
        bounds = np.searchsorted(of[order], np.arange(len(code) + 1))
        for k, v in enumerate(code):
            buf = errors.get((solution, v)) or self._error_rows(solution, v)
            rows = order[bounds[k] : bounds[k + 1]]
            buf.times.append(times[rows])
            buf.rows.append(values[rows])
        self._buffered_rows += len(vehicle_ids)
        if self._buffered_rows >= self.params.flush_rows:
            self._flush_series()

    def _error_rows(self, solution: str, vehicle_id: str) -> _ErrorRows:
        """The new series buffer of (solution, vehicle), its series' styles sent (static: the
        default blueprint's look, :func:`series_style_chunks`)."""
        self._solutions.setdefault(solution)
        self._error_vehicles.setdefault(vehicle_id)
        paths = tuple(bp.error_path(solution, vehicle_id, series) for series in bp.ERROR_SERIES)
        rr.send_chunks(series_style_chunks(solution, vehicle_id, self._color_of(solution)), recording=self._rec)
        buf = self._errors[(solution, vehicle_id)] = _ErrorRows(paths)
        return buf

    def _flush_series(self) -> None:
        for buf in self._errors.values():
            if not buf.times:
                continue
            times = np.concatenate(buf.times)
            n = len(times)
            values = np.concatenate(buf.rows)[:, _ERROR_COLUMNS]  # (n, len(ERROR_SERIES))
            # rounded nanoseconds, like the scene columns (a float array would be truncated)
            index = _time_index(times)
            # the column rr.Scalars.columns(scalars=...) builds, without the archetype's overhead
            descriptor = rr.Scalars.descriptor_scalars()
            for j, (path, series) in enumerate(zip(buf.paths, bp.ERROR_SERIES, strict=True)):
                if series.endswith("_sigma"):  # two lines per row: [+sigma, -sigma]
                    v = values[:, j]
                    col = rr.ComponentColumn(descriptor, rr.components.ScalarBatch(np.column_stack([v, -v]).reshape(-1)))
                    col = col.partition(np.full(n, 2))
                else:
                    col = rr.ComponentColumn(descriptor, rr.components.ScalarBatch(np.ascontiguousarray(values[:, j])))
                self._rec.send_columns(path, indexes=index, columns=[col])
                self.rows_sent += n
            buf.times.clear()
            buf.rows.clear()
        self._buffered_rows = 0

    # -- closing --------------------------------------------------------------------------

    def close(self) -> None:
        """Send buffered series and the blueprint, close the file, rename it into place."""
        if self._closed:
            return
        try:
            self._flush_series()
            self._flush_scene()
            chunks = blueprint_chunks(
                self.params.application_id,
                tuple(self._solutions),
                tuple(self._error_vehicles),
                tuple(self._sky_vehicles),
                self.params.show_map,
            )
            send_blueprint_chunks(self._rec, self.params.application_id, chunks)
            self._rec.flush()
            self._rec.disconnect()
            publish(self._tmp_path, self.path)
        except BaseException:
            self._discard()
            raise
        self._closed = True

    def abort(self) -> None:
        """Stop writing and delete the temporary file; the target path is not touched."""
        if self._closed:
            return
        self._discard()

    def _discard(self) -> None:
        self._closed = True
        try:
            self._rec.disconnect()
        finally:
            self._tmp_path.unlink(missing_ok=True)
