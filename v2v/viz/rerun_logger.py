"""The rerun implementation of :class:`~v2v.viz.logger.ReplayLogger` (rerun-sdk 0.41).

The only module of v2v, with :mod:`v2v.viz.blueprint`, that imports rerun. The entity
layout is documented in :mod:`v2v.viz.blueprint`.

How it writes
-------------
* A private ``rr.RecordingStream(application_id="v2v")`` (never the global one), saved
  with ``RecordingStream.save`` to a hidden temporary file beside the target; no viewer is
  spawned and nothing touches the network. :meth:`RerunReplayLogger.close` flushes, sends
  the default blueprint (built from the solutions and vehicles actually logged), closes
  the file and renames it to the target with ``os.replace``; on any error, or on
  :meth:`~RerunReplayLogger.abort`, the temporary file is removed and the target is not
  touched.
* Static geometry is logged once with ``static=True``.
* Scene data (boxes, points, ellipses, links, sky plots) is buffered in memory as plain
  numpy rows, one row per call, and sent column-wise with ``RecordingStream.send_columns``
  (``Archetype.columns(...)``; per-instance components ``.partition(lengths)`` with the
  row's instance count, per-row constants such as ``radii`` or a single colour as
  unit-length rows, exactly what ``log`` of the same archetype would have stored) once
  ``flush_rows`` rows are waiting and at close. Building one archetype and calling
  ``log`` per call cost ~0.4 ms (most of the replay's overhead); the recording's content
  is the same: same entity paths, components, values and ``sim_time`` stamps.
* Error time series are buffered the same way and sent with
  ``RecordingStream.send_columns(path, [rr.TimeColumn(TIMELINE, duration=t)],
  rr.Scalars.columns(scalars=...))``.

Geometry
--------
* Vehicle box: centre = front bumper - L/2 · heading, at height H/2 above the road
  (z = 0, as for the buildings of :mod:`v2v.world.buildings`); half sizes (L/2, W/2, H/2);
  rotation about +z by the yaw ``psi = pi/2 - (alpha - gamma)`` counter-clockwise from +x,
  where ``alpha`` is the true azimuth and ``gamma`` the grid convergence
  (:meth:`v2v.frames.GeoReference.grid_convergence_rad`: grid azimuth = alpha - gamma).
* Uncertainty ellipse of probability ``p`` for a 2-D Gaussian: the points ``d`` with
  ``d^T C^-1 d = k^2``, ``k^2 = -2 ln(1 - p)`` (the chi-square quantile with 2 degrees
  of freedom in closed form; p = 0.95 gives k = 2.4477), drawn as
  ``d = k · V diag(sqrt(lambda)) [cos t, sin t]^T`` with ``C = V diag(lambda) V^T``.
  ``C`` is given east/north and rotated into net XY: ``C_xy = R(gamma) C_en R(gamma)^T``,
  ``R`` the counter-clockwise rotation (a true-azimuth direction turns by +gamma
  counter-clockwise in the grid).
* Sky plot: ``x = (90 - el_deg) sin(az)``, ``y = -(90 - el_deg) cos(az)`` (rerun's 2-D
  views have +y pointing down, so the minus puts north at the top and east on the right,
  the usual sky plot); rings at elevations 0, 30, 60 deg.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import rerun as rr
import shapely
from numpy.typing import ArrayLike, NDArray

from v2v.frames import GeoReference
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
SIGMA_RGB = (160, 160, 160)


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
        Rows (error-series rows; scene rows, one per logging call) buffered before they
        are sent with ``send_columns``.
    ellipse_probability : float
        Probability mass inside the drawn uncertainty ellipse (0.95: the 95 % ellipse,
        k = 2.4477 sigma; 1 - exp(-1/2) = 0.3935 gives the 1-sigma ellipse).
    ellipse_points : int
        Vertices per ellipse (closed strip: the first is repeated).
    estimate_z_m : float
        Height at which 2-D estimates and their ellipses are drawn (just above the road).
    show_map : bool
        Log geodetic positions and add the MapView to the blueprint.
    """

    application_id: str = "v2v"
    recording_id: str | None = None
    flush_rows: int = 4096
    ellipse_probability: float = 0.95
    ellipse_points: int = 37
    estimate_z_m: float = 0.2
    show_map: bool = True

    def __post_init__(self) -> None:
        if not 0.0 < self.ellipse_probability < 1.0:
            raise ValueError(f"ellipse_probability must be in (0, 1), got {self.ellipse_probability}")
        if self.flush_rows < 1 or self.ellipse_points < 4:
            raise ValueError("flush_rows must be >= 1 and ellipse_points >= 4")


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
    coords = np.stack([np.asarray(t.exterior.coords)[:3] for t in tris])
    e1 = coords[:, 1] - coords[:, 0]
    e2 = coords[:, 2] - coords[:, 0]
    cw = (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]) < 0.0
    coords[cw] = coords[cw][:, ::-1]
    return coords


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


def ellipse_points(center_xy_m: ArrayLike, cov_m2: ArrayLike, k: float, n_points: int) -> FloatArray:
    """Closed outlines ``(n, n_points, 2)`` of ``d^T C^-1 d = k^2`` around each centre.

    ``C = V diag(lambda) V^T`` (``numpy.linalg.eigh``, negative round-off clipped to 0):
    ``d(t) = k V diag(sqrt(lambda)) [cos t, sin t]^T``, ``t`` in [0, 2 pi], last = first.
    """
    c = np.asarray(center_xy_m, dtype=float).reshape(-1, 2)
    cov = np.asarray(cov_m2, dtype=float).reshape(-1, 2, 2)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    lam, vec = np.linalg.eigh(cov)
    a = vec * np.sqrt(np.clip(lam, 0.0, None))[:, None, :]  # (n, 2, 2) = V diag(sqrt(lambda))
    t = np.linspace(0.0, 2.0 * np.pi, n_points)
    unit = np.stack([np.cos(t), np.sin(t)])  # (2, P)
    d = k * np.einsum("nij,jp->npi", a, unit)
    d[:, -1] = d[:, 0]
    return c[:, None, :] + d


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
    out = []
    for side in (0.5 * width_m, -0.5 * width_m):
        off = line.offset_curve(side)
        out.extend(np.asarray(g.coords) for g in shapely.get_parts(off) if not g.is_empty)
    return out


# ---------------------------------------------------------------------------- scene buffer


class _SceneRows:
    """Rows of one archetype on one entity path, waiting for ``send_columns``.

    ``per_instance`` components hold one array per row (leading axis = the row's
    instance count, equal across those components); ``per_row`` components hold one
    value per row (logged as a unit-length batch, like a scalar passed to ``log``).
    ``key`` is the archetype plus both component-name sets: a row with another key
    cannot share the columns and makes the caller flush this buffer first.
    """

    __slots__ = ("archetype", "key", "times", "lengths", "per_instance", "per_row")

    def __init__(self, archetype: type, per_instance: Mapping[str, object], per_row: Mapping[str, object]):
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

    def send(self, rec: rr.RecordingStream, path: str) -> int:
        n_rows = len(self.times)
        if n_rows == 0:
            return 0
        # nanoseconds rounded as ``set_time(duration=t)`` does (``rerun.time.to_nanos``); a
        # float array given to ``TimeColumn`` would be truncated instead (4.1 s -> 4099999999 ns)
        ns = np.round(np.asarray(self.times, dtype=np.float64) * 1e9).astype(np.int64)
        index = [rr.TimeColumn(bp.TIMELINE, duration=ns.astype("timedelta64[ns]"))]
        cols: list[rr.ComponentColumn] = []
        if self.per_instance:
            merged: dict[str, object] = {}
            for name, rows in self.per_instance.items():
                if rows and isinstance(rows[0], np.ndarray):
                    merged[name] = np.concatenate(rows)
                else:  # lists (labels, line strips)
                    merged[name] = [x for row in rows for x in row]
            cols.extend(self.archetype.columns(**merged).partition(np.asarray(self.lengths)))
        if self.per_row:
            cols.extend(self.archetype.columns(**{name: np.asarray(v) for name, v in self.per_row.items()}))
        rec.send_columns(path, indexes=index, columns=cols)
        self.times.clear()
        self.lengths.clear()
        for rows in (*self.per_instance.values(), *self.per_row.values()):
            rows.clear()
        return n_rows


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
        # error series buffers: path -> (times, values), values flat (width per row fixed)
        self._buf: dict[str, tuple[list[float], list[float], int]] = {}
        self._buffered_rows = 0
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
        buf = self._scene.get(path)
        key = (archetype, tuple(per_instance), tuple(per_row))
        if buf is not None and buf.key != key:
            self.scene_rows_sent += buf.send(self._rec, path)
            buf = None
        if buf is None:
            buf = self._scene[path] = _SceneRows(archetype, per_instance, per_row)
        buf.add(float(t_s), int(n), per_instance, per_row)
        self._scene_rows += 1
        if self._scene_rows >= self.params.flush_rows:
            self._flush_scene()

    def _flush_scene(self) -> None:
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
        rec = self._rec
        lane_xy = {
            lid: np.asarray(xy, dtype=float).reshape(-1, np.shape(xy)[-1])[:, :2] for lid, xy in lanes.items()
        }
        lane_xy = {lid: xy for lid, xy in lane_xy.items() if len(xy) >= 2}
        if lane_xy:
            allpts = np.concatenate(list(lane_xy.values()))
            cx, cy = (allpts.min(axis=0) + allpts.max(axis=0)) / 2.0
            self._gamma_rad = geo.grid_convergence_rad(float(cx), float(cy))
            self._rot_en_to_xy = rotation_2d(self._gamma_rad)
            strips = [np.column_stack([xy, np.full(len(xy), 0.02)]) for xy in lane_xy.values()]
            rec.log(bp.LANES, rr.LineStrips3D(strips, radii=0.05, colors=LANE_LINE_RGB), static=True)
            surf_tris = []
            for lid, xy in lane_xy.items():
                w = float(lane_widths.get(lid, 3.2))
                poly = shapely.LineString(xy).buffer(
                    0.5 * w, cap_style="flat", join_style="mitre", mitre_limit=3.0
                )
                for part in shapely.get_parts(poly):
                    if part.area > 0.0:
                        surf_tris.append(triangulate_polygon(np.asarray(part.exterior.coords)[:-1]))
            if surf_tris:
                tri = np.concatenate(surf_tris).reshape(-1, 2)
                verts = np.column_stack([tri, np.zeros(len(tri))])
                rec.log(
                    bp.LANE_SURFACE,
                    rr.Mesh3D(
                        vertex_positions=verts,
                        triangle_indices=np.arange(len(verts), dtype=np.uint32).reshape(-1, 3),
                        albedo_factor=LANE_SURFACE_RGBA,
                    ),
                    static=True,
                )
            if self.params.show_map:
                sizes = [len(xy) for xy in lane_xy.values()]
                lat, lon = geo.xy_to_geodetic(allpts[:, 0], allpts[:, 1])
                latlon = np.degrees(np.column_stack([lat, lon]))
                geo_strips = np.split(latlon, np.cumsum(sizes)[:-1])
                rec.log(
                    bp.MAP_LANES,
                    rr.GeoLineStrings(
                        lat_lon=geo_strips, radii=rr.Radius.ui_points(1.5), colors=BACKGROUND_RGB
                    ),
                    static=True,
                )
        for path, items, rgba in (
            (bp.BUILDINGS, buildings, BUILDING_RGBA),
            (bp.FOLIAGE, foliage, FOLIAGE_RGBA),
        ):
            if not items:
                continue
            v, t, n = extrude_footprints(
                [b.footprint_xy_m for b in items], [float(b.height_m) for b in items]
            )
            rec.log(
                path,
                rr.Mesh3D(vertex_positions=v, triangle_indices=t, vertex_normals=n, albedo_factor=rgba),
                static=True,
            )

    # -- truth ----------------------------------------------------------------------

    def log_truth(self, t_s: float, step: TrafficStep) -> None:
        self._at(t_s)
        states = list(step.vehicles.values())
        if states:
            az = np.array([s.azimuth_rad for s in states])
            grid_az = az - self._gamma_rad
            fwd = np.column_stack([np.sin(grid_az), np.cos(grid_az)])
            size = np.array([[s.length_m, s.width_m, s.height_m] for s in states])
            front = np.array([s.front_bumper_xy_m for s in states], dtype=float)
            centre_xy = front - 0.5 * size[:, :1] * fwd
            centres = np.column_stack([centre_xy, 0.5 * size[:, 2]])
            yaw = 0.5 * np.pi - grid_az
            quat = np.column_stack([np.zeros((len(states), 2)), np.sin(yaw / 2), np.cos(yaw / 2)])
            colors = np.array([LEAD_RGB if s.is_lead else FOLLOWER_RGB for s in states], dtype=np.uint8)
            labels = [s.vehicle_id for s in states]
            n = len(states)
            self._add_row(
                bp.TRUTH,
                rr.Boxes3D,
                t_s,
                n,
                {
                    "half_sizes": 0.5 * size,
                    "centers": centres,
                    "quaternions": quat,
                    "colors": colors,
                    "labels": labels,
                },
                {},
            )
            antennas = np.array([s.xyz_m for s in states], dtype=float)
            self._add_row(
                bp.TRUTH_ANTENNAS,
                rr.Points3D,
                t_s,
                n,
                {"positions": antennas, "colors": colors},
                {"radii": 0.1},
            )
            if self.params.show_map:
                latlon = np.degrees([[s.lat_rad, s.lon_rad] for s in states])
                self._add_row(
                    bp.MAP_VEHICLES,
                    rr.GeoPoints,
                    t_s,
                    n,
                    {"positions": latlon, "colors": colors},
                    {"radii": float(rr.Radius.ui_points(5.0))},
                )
        else:
            self._add_row(bp.TRUTH, rr.Boxes3D, t_s, 0, {"half_sizes": np.zeros((0, 3))}, {})
        bg = np.asarray(step.background, dtype=float).reshape(-1, 6)
        yaw_bg = 0.5 * np.pi - (bg[:, 2] - self._gamma_rad)
        self._add_row(
            bp.BACKGROUND,
            rr.Boxes3D,
            t_s,
            len(bg),
            {
                "half_sizes": 0.5 * bg[:, 3:6],
                "centers": np.column_stack([bg[:, :2], 0.5 * bg[:, 5]]),
                "quaternions": np.column_stack(
                    [np.zeros((len(bg), 2)), np.sin(yaw_bg / 2), np.cos(yaw_bg / 2)]
                ),
            },
            {"colors": np.array(BACKGROUND_RGB, dtype=np.uint8)},
        )

    # -- estimates --------------------------------------------------------------------

    def log_estimates(
        self,
        t_s: float,
        solution: str,
        vehicle_ids: Sequence[str],
        est_xy_m: ArrayLike,
        cov_en_m2: ArrayLike,
    ) -> None:
        self._at(t_s)
        xy = np.asarray(est_xy_m, dtype=float).reshape(-1, 2)
        cov = np.asarray(cov_en_m2, dtype=float).reshape(-1, 2, 2)
        if not (len(xy) == len(cov) == len(vehicle_ids)):
            raise ValueError(
                f"log_estimates: {len(vehicle_ids)} ids, {len(xy)} positions, {len(cov)} covariances"
            )
        self._solutions.setdefault(solution)
        rgb = self._color_of(solution)
        r = self._rot_en_to_xy
        cov_xy = r @ cov @ r.T
        z = self.params.estimate_z_m
        pts = np.column_stack([xy, np.full(len(xy), z)])
        rgb_u8 = np.array(rgb, dtype=np.uint8)
        self._add_row(
            bp.estimates_path(solution),
            rr.Points3D,
            t_s,
            len(pts),
            {"positions": pts, "labels": [str(v) for v in vehicle_ids]},
            {"radii": 0.12, "colors": rgb_u8},
        )
        ok = np.all(np.isfinite(cov_xy), axis=(1, 2)) & np.all(np.isfinite(xy), axis=1)
        outline = ellipse_points(xy[ok], cov_xy[ok], self._k, self.params.ellipse_points)
        strips = np.concatenate([outline, np.full(outline.shape[:2] + (1,), z)], axis=2)
        self._add_row(
            bp.ellipses_path(solution),
            rr.LineStrips3D,
            t_s,
            len(strips),
            {"strips": strips},
            {"radii": 0.03, "colors": rgb_u8},
        )

    # -- links ------------------------------------------------------------------------

    def log_links(
        self, t_s: float, kind: str, a_xyz_m: ArrayLike, b_xyz_m: ArrayLike, status: Sequence[str]
    ) -> None:
        self._at(t_s)
        a = np.asarray(a_xyz_m, dtype=float).reshape(-1, 3)
        b = np.asarray(b_xyz_m, dtype=float).reshape(-1, 3)
        status = list(status)
        if not (len(a) == len(b) == len(status)):
            raise ValueError(f"log_links: {len(a)} starts, {len(b)} ends, {len(status)} statuses")
        bad = sorted(set(status) - set(LINK_STATUSES))
        if bad:
            raise ValueError(f"log_links: unknown status {bad}; expected one of {LINK_STATUSES}")
        colors = np.array([STATUS_RGB[s] for s in status], dtype=np.uint8).reshape(-1, 3)
        self._add_row(
            bp.links_path(kind),
            rr.LineStrips3D,
            t_s,
            len(a),
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
        self._at(t_s)
        if vehicle_id not in self._sky_vehicles:
            self._sky_vehicles[vehicle_id] = None
            self._log_sky_grid(vehicle_id)
        xy = sky_xy(az_rad, el_rad)
        los_b = np.asarray(los, dtype=bool).reshape(-1)
        labels = [str(p) for p in np.asarray(prn).reshape(-1)]
        if not (len(xy) == len(los_b) == len(labels)):
            raise ValueError(
                f"log_satellites: {len(labels)} PRNs, {len(xy)} directions, {len(los_b)} LOS flags"
            )
        colors = np.where(los_b[:, None], np.array(LOS_RGB), np.array(NLOS_RGB)).astype(np.uint8)
        self._add_row(
            bp.sky_path(vehicle_id),
            rr.Points2D,
            t_s,
            len(xy),
            {"positions": xy, "colors": colors, "labels": labels},
            {"radii": 2.5, "draw_order": 10.0},
        )

    def _log_sky_grid(self, vehicle_id: str) -> None:
        t = np.linspace(0.0, 2.0 * np.pi, 73)
        rings = [np.column_stack([r * np.sin(t), -r * np.cos(t)]) for r in (90.0, 60.0, 30.0)]
        axes = [np.array([[0.0, -90.0], [0.0, 90.0]]), np.array([[-90.0, 0.0], [90.0, 0.0]])]
        self._rec.log(
            bp.sky_grid_path(vehicle_id),
            rr.LineStrips2D(
                rings + axes,
                radii=0.3,
                colors=(120, 120, 120),
                labels=["0°", "30°", "60°", "N-S", "E-W"],
                draw_order=1.0,
            ),
            static=True,
        )

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
        self._check_open()
        self._solutions.setdefault(solution)
        self._error_vehicles.setdefault(vehicle_id)
        t = float(t_s)
        sa, sx = float(sigma_along_m), float(sigma_across_m)
        rows = (
            ("along", (float(along_m),)),
            ("along_sigma", (sa, -sa)),
            ("across", (float(across_m),)),
            ("across_sigma", (sx, -sx)),
            ("nees", (float(nees),)),
            ("nis", (float(nis),)),
            ("n_sats", (float(n_sats),)),
            ("rejections", (float(rejections),)),
        )
        for series, values in rows:
            path = bp.error_path(solution, vehicle_id, series)
            buf = self._buf.get(path)
            if buf is None:
                buf = self._buf[path] = ([], [], len(values))
                self._log_series_style(path, solution, series)
            buf[0].append(t)
            buf[1].extend(values)
        self._buffered_rows += 1
        if self._buffered_rows >= self.params.flush_rows:
            self._flush_series()

    def _log_series_style(self, path: str, solution: str, series: str) -> None:
        rgb = self._color_of(solution)
        if series.endswith("_sigma"):
            style = rr.SeriesLines(colors=[SIGMA_RGB, SIGMA_RGB], names=["+1σ", "-1σ"], widths=[1.0, 1.0])
        else:
            style = rr.SeriesLines(colors=rgb, names=series, widths=1.5)
        self._rec.log(path, style, static=True)

    def _flush_series(self) -> None:
        for path, (times, values, width) in self._buf.items():
            if not times:
                continue
            n = len(times)
            cols = rr.Scalars.columns(scalars=np.asarray(values, dtype=np.float64))
            if width > 1:
                cols = cols.partition(np.full(n, width))
            # rounded nanoseconds, like the scene columns (a float array would be truncated)
            ns = np.round(np.asarray(times, dtype=np.float64) * 1e9).astype(np.int64).astype("timedelta64[ns]")
            self._rec.send_columns(path, indexes=[rr.TimeColumn(bp.TIMELINE, duration=ns)], columns=cols)
            self.rows_sent += n
            times.clear()
            values.clear()
        self._buffered_rows = 0

    # -- closing --------------------------------------------------------------------------

    def close(self) -> None:
        """Send buffered series and the blueprint, close the file, rename it into place."""
        if self._closed:
            return
        try:
            self._flush_series()
            self._flush_scene()
            blueprint = bp.default_blueprint(
                list(self._solutions),
                list(self._error_vehicles),
                list(self._sky_vehicles),
                show_map=self.params.show_map,
            )
            self._rec.send_blueprint(blueprint, make_active=True, make_default=True)
            self._rec.flush()
            self._rec.disconnect()
            os.chmod(self._tmp_path, 0o644)  # mkstemp creates 0600; a replay is meant to be shared
            os.replace(self._tmp_path, self.path)
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
