"""Replay logger: write a small synthetic run, read it back with rerun's own reader.

Reading uses ``rerun.chunk.RrdReader`` (rerun-sdk 0.41; ``rerun.dataframe`` is gone).
Geometry stored by rerun is float32 (Vec3D, Vec2D, HalfSize3D, Quaternion): float32 has a
24-bit mantissa, relative spacing 2**-23 = 1.2e-7, so coordinates below 128 m round by at
most 128 m * 2**-24 = 7.6e-6 m. Geometric tolerances below are derived from that. Scalars
(error time series) are float64 and must round-trip exactly.
"""

from __future__ import annotations

import math
import os
from collections import defaultdict
from types import SimpleNamespace

import numpy as np
import pytest
import rerun as rr
import shapely
from rerun.chunk import RrdReader
from scipy.stats import chi2

from v2v.frames import GeoReference
from v2v.traffic.snapshot import TrafficStep, VehicleState
from v2v.viz import blueprint as bp
from v2v.viz.logger import NullLogger, ReplayLogger
from v2v.viz.rerun_logger import (
    SOLUTION_RGB,
    RerunReplayLogger,
    RerunReplayParams,
    blueprint_chunks,
    ellipse_axes,
    ellipse_scale,
    extrude_footprints,
    rotation_2d,
    send_blueprint_chunks,
    series_style_chunks,
    strips3d_arrow,
)

F32_ABS_M = 1e-5  # > 7.6e-6 m, float32 rounding of coordinates below 128 m (module docstring)
GEO = GeoReference(proj=None, origin_lat_deg=51.08, origin_lon_deg=-114.13)  # Calgary, tangent TM
N_STEPS = 100
DT_S = 0.1
SOLUTIONS = ("gps", "gps+uwb")  # '+' must be escaped in entity paths
VEHICLES = ("lead", "veh.1", "veh_2")
L_SHAPE = np.array(
    [[0.0, 10.0], [20.0, 10.0], [20.0, 20.0], [10.0, 20.0], [10.0, 30.0], [0.0, 30.0]]
)  # CCW, 300 m²
L_HEIGHT_M = 12.0


def _state(
    vid: str, t_s: float, front_xy, az_rad: float, *, lead: bool, length=4.5, width=1.8, height=1.5
) -> VehicleState:
    x, y = front_xy
    return VehicleState(
        vehicle_id=vid,
        cluster="c0",
        is_lead=lead,
        t_s=t_s,
        xyz_m=np.array([x, y, height]),
        lat_rad=math.radians(51.08),
        lon_rad=math.radians(-114.13),
        h_m=height,
        ecef_m=np.zeros(3),
        vel_enu_mps=np.zeros(3),
        speed_mps=10.0,
        accel_mps2=0.0,
        azimuth_rad=az_rad,
        grid_azimuth_rad=az_rad,  # (a tangent projection near its origin: no grid convergence)
        yaw_rate_rps=0.0,
        front_bumper_xy_m=np.array([x, y]),
        edge_id="e",
        lane_id="e_0",
        lane_index=0,
        lane_width_m=3.2,
        lateral_offset_m=0.0,
        length_m=length,
        width_m=width,
        height_m=height,
    )


def _error_row(k: int, s: int, v: int) -> tuple[float, ...]:
    """Deterministic, distinct float64 values per (step, solution, vehicle)."""
    base = 0.001 * k + 0.1 * s + 0.01 * v
    return (base + 1 / 3, -base - 1 / 7, 0.2 + base, 0.3 + base, 2.0 + base, 1.0 + base, 8 + v, k % 3)


def _read(path) -> dict[str, list]:
    chunks: dict[str, list] = defaultdict(list)
    for c in RrdReader(path).stream():
        chunks[c.entity_path].append(c)
    return chunks


def _column(chunks, name: str, timeline: str = bp.TIMELINE):
    """(times_ns, values) of a component over all temporal chunks, sorted by time."""
    t, vals = [], []
    for c in chunks:
        if c.is_static:
            continue
        rb = c.to_record_batch()
        if name not in rb.schema.names:
            continue
        t.extend(rb.column(timeline).cast("int64").to_pylist())
        vals.extend(rb.column(name).to_pylist())
    order = np.argsort(t, kind="stable")
    return np.asarray(t)[order], [vals[i] for i in order]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A synthetic 100-step run: 3 vehicles heading east along y = 0, 2 solutions."""
    path = tmp_path_factory.mktemp("replay") / "replay.rrd"
    building = SimpleNamespace(id="b1", footprint_xy_m=L_SHAPE, height_m=L_HEIGHT_M, height_source="height")
    tree = SimpleNamespace(
        id="f1",
        footprint_xy_m=np.array([[30.0, 10.0], [40.0, 10.0], [40.0, 20.0]]),
        height_m=8.0,
        attenuation_db_per_m=0.5,
    )
    # lanes symmetric about net x = 0 (the tangent origin), so the grid convergence at their centre is 0
    lanes = {"e_0": np.array([[-100.0, 0.0], [100.0, 0.0]]), "e_1": np.array([[-100.0, 3.2], [100.0, 3.2]])}
    logger = RerunReplayLogger(
        path, params=RerunReplayParams(flush_rows=64, recording_id="test")
    )  # 64: several flushes
    logger.log_world(lanes, {"e_0": 3.2, "e_1": 3.2}, [building], [tree], GEO)
    for k in range(N_STEPS):
        t = k * DT_S
        vs = {
            vid: _state(vid, t, (50.0 - 30.0 * i + t, 0.0), math.pi / 2, lead=i == 0)
            for i, vid in enumerate(VEHICLES)
        }
        logger.log_truth(t, TrafficStep(t_s=t, vehicles=vs))
        for s, sol in enumerate(SOLUTIONS):
            logger.log_estimates(
                t,
                sol,
                VEHICLES[1:],
                [[20.0 + t, 0.1], [-10.0 + t, -0.1]],
                [[[0.04, 0.01], [0.01, 0.09]], [[0.25, 0.0], [0.0, 0.01]]],
            )
            for v, vid in enumerate(VEHICLES[1:]):
                logger.log_errors(t, sol, vid, *_error_row(k, s, v))
        logger.log_links(
            t,
            "uwb",
            [[50.0, 0.0, 1.5], [50.0, 0.0, 1.5]],
            [[20.0, 0.0, 1.5], [-10.0, 0.0, 1.5]],
            ["los", "nlos"],
        )
        logger.log_links(t, "bearing", [[50.0, 0.0, 1.5]], [[20.0, 0.0, 1.5]], ["rejected"])
        logger.log_satellites(
            t,
            "veh.1",
            ["G01", "G07", "G30"],
            [math.pi / 2, 0.0, math.pi],
            np.radians([0.0, 30.0, 90.0]),
            [True, False, True],
        )
    logger.close()
    return path, _read(path)


def test_entity_paths_exist_and_solution_names_are_escaped(run):
    _, chunks = run
    expected = {
        "/world/lanes",
        "/world/lanes/surface",
        "/world/buildings",
        "/world/foliage",
        "/world/vehicles/truth",
        "/world/vehicles/truth/antennas",
        "/world/vehicles/background",
        "/world/estimates/gps",
        "/world/estimates/gps/ellipses",
        "/world/estimates/gps\\+uwb/ellipses",
        "/world/links/uwb",
        "/world/links/bearing",
        "/map/lanes",
        "/map/vehicles",
        "/sky/veh.1",
        "/sky/veh.1/grid",
    }
    expected |= {
        f"/errors/{s}/{v}/{k}" for s in ("gps", "gps\\+uwb") for v in VEHICLES[1:] for k in bp.ERROR_SERIES
    }
    assert expected <= set(chunks), sorted(expected - set(chunks))
    assert not any(p.startswith("/errors/") and "/lead/" in p for p in chunks)  # never logged for the lead


@pytest.mark.parametrize("s,v", [(0, 0), (1, 1)])
def test_error_series_round_trip(run, s, v):
    """Every logged row is there once, at its time, with its exact float64 value."""
    _, chunks = run
    sol, vid = SOLUTIONS[s], VEHICLES[1 + v]
    t_ns, along = _column(chunks[bp.error_path(sol, vid, "along")], "Scalars:scalars")
    assert len(t_ns) == N_STEPS
    # durations are stored as integer nanoseconds: k * 0.1 s rounds to the nearest ns
    np.testing.assert_allclose(t_ns, np.arange(N_STEPS) * DT_S * 1e9, atol=1.0)
    assert along[0] == [_error_row(0, s, v)[0]]
    assert along[-1] == [_error_row(N_STEPS - 1, s, v)[0]]
    assert [a[0] for a in along] == [_error_row(k, s, v)[0] for k in range(N_STEPS)]
    _, sig = _column(chunks[bp.error_path(sol, vid, "along_sigma")], "Scalars:scalars")
    assert sig[-1] == [
        _error_row(N_STEPS - 1, s, v)[2],
        -_error_row(N_STEPS - 1, s, v)[2],
    ]  # [+1 sigma, -1 sigma]
    _, rej = _column(chunks[bp.error_path(sol, vid, "rejections")], "Scalars:scalars")
    assert [r[0] for r in rej] == [float(k % 3) for k in range(N_STEPS)]
    # every series, by name, against log_errors' arguments (along, across, sigma_along,
    # sigma_across, nees, nis, n_sats, rejections)
    rows = [_error_row(k, s, v) for k in range(N_STEPS)]
    want = {"along": [[r[0]] for r in rows], "across": [[r[1]] for r in rows],
            "along_sigma": [[r[2], -r[2]] for r in rows], "across_sigma": [[r[3], -r[3]] for r in rows],
            "nees": [[r[4]] for r in rows], "nis": [[r[5]] for r in rows], "n_sats": [[float(r[6])] for r in rows],
            "rejections": [[float(r[7])] for r in rows]}
    assert set(want) == set(bp.ERROR_SERIES)
    for series, values in want.items():
        assert _column(chunks[bp.error_path(sol, vid, series)], "Scalars:scalars")[1] == values, series


def test_static_world_is_static_and_building_mesh_is_the_prism(run):
    """Roof area = footprint area (300 m² L-shape), wall area = perimeter (80 m) x height."""
    _, chunks = run
    for p in (
        "/world/buildings",
        "/world/foliage",
        "/world/lanes",
        "/world/lanes/surface",
        "/map/lanes",
        "/sky/veh.1/grid",
    ):
        assert all(c.is_static and c.timeline_names == [] for c in chunks[p]), p
    rb = chunks["/world/buildings"][0].to_record_batch()
    verts = np.asarray(rb.column("Mesh3D:vertex_positions").to_pylist()[0])
    tris = np.asarray(rb.column("Mesh3D:triangle_indices").to_pylist()[0])
    normals = np.asarray(rb.column("Mesh3D:vertex_normals").to_pylist()[0])
    p = verts[tris]
    cross = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    roof = np.all(np.abs(p[:, :, 2] - L_HEIGHT_M) < F32_ABS_M, axis=1)
    # float32 vertices (< 128 m): area error <= ~2 * 30 m * 1e-5 m per triangle, far below 1e-3 m²
    assert area[roof].sum() == pytest.approx(300.0, abs=1e-3)
    assert area[~roof].sum() == pytest.approx(80.0 * L_HEIGHT_M, abs=1e-3)
    assert np.all(cross[roof, 2] > 0)  # roof faces counter-clockwise seen from above (front faces)
    # every wall faces outward: a point just outside along the face normal lies outside the footprint
    poly = shapely.Polygon(L_SHAPE)
    n_face = cross[~roof] / np.linalg.norm(cross[~roof], axis=1, keepdims=True)
    probe = p[~roof].mean(axis=1)[:, :2] + 0.01 * n_face[:, :2]
    assert not any(poly.contains(shapely.Point(q)) for q in probe)
    np.testing.assert_allclose(
        normals[tris[~roof, 0]], n_face, atol=1e-6
    )  # stored normals agree with winding


@pytest.mark.parametrize("shape", [(5, 2, 3), (7, 37, 3), (0, 2, 3), (1, 1, 3)])
def test_strips_arrow_is_what_rerun_builds_from_the_array(shape):
    """The links' strips converted in one pass are the arrow array rerun's own
    LineStrip3D conversion builds from the same (n, k, 3) float64 array: same type (so rerun
    takes it as it is), same float32 points, same offsets; also for no strips."""
    a = np.random.default_rng(7).normal(size=shape) * 1e3
    ours = strips3d_arrow(a)
    assert ours.type == rr.components.LineStrip3DBatch._ARROW_DATATYPE
    assert rr.components.LineStrip3DBatch(ours).as_arrow_array().equals(rr.components.LineStrip3DBatch(a).as_arrow_array())
    with pytest.raises(ValueError, match="n_points, 3"):
        strips3d_arrow(a.reshape(-1, 3))


def test_extrude_accepts_clockwise_and_closed_footprints():
    """Orientation and a repeated closing vertex must not change the prism."""
    cw_closed = np.vstack([L_SHAPE[::-1], L_SHAPE[-1:]])
    v1, t1, _ = extrude_footprints([L_SHAPE], [5.0])
    v2, t2, _ = extrude_footprints([cw_closed], [5.0])
    assert len(t1) == len(t2) == 4 + 2 * 6  # roof: K - 2 = 4 triangles; 2 per wall
    a1 = (
        0.5 * np.linalg.norm(np.cross(v1[t1][:, 1] - v1[t1][:, 0], v1[t1][:, 2] - v1[t1][:, 0]), axis=1).sum()
    )
    a2 = (
        0.5 * np.linalg.norm(np.cross(v2[t2][:, 1] - v2[t2][:, 0], v2[t2][:, 2] - v2[t2][:, 0]), axis=1).sum()
    )
    assert a1 == pytest.approx(300.0 + 80.0 * 5.0, rel=1e-12) and a2 == pytest.approx(a1, rel=1e-12)


def test_truth_box_size_centre_and_heading(run):
    """Half sizes L/2, W/2, H/2; centre = front bumper - L/2 along the heading (east here)."""
    _, chunks = run
    t_ns, half = _column(chunks["/world/vehicles/truth"], "Boxes3D:half_sizes")
    _, centres = _column(chunks["/world/vehicles/truth"], "Boxes3D:centers")
    _, quats = _column(chunks["/world/vehicles/truth"], "Boxes3D:quaternions")
    _, labels = _column(chunks["/world/vehicles/truth"], "Boxes3D:labels")
    assert len(t_ns) == N_STEPS
    k = N_STEPS - 1
    i = labels[k].index("veh.1")
    np.testing.assert_allclose(half[k][i], [2.25, 0.9, 0.75], atol=1e-6)  # 4.5 x 1.8 x 1.5 m car
    front_x = 50.0 - 30.0 * 1 + k * DT_S
    np.testing.assert_allclose(centres[k][i], [front_x - 2.25, 0.0, 0.75], atol=F32_ABS_M)
    # the box's body +x axis, rotated by its quaternion, must point along azimuth 90 deg = +x (east)
    x, y, z, w = quats[k][i]
    body_x = np.array([1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)])
    np.testing.assert_allclose(body_x, [math.sin(math.pi / 2), math.cos(math.pi / 2), 0.0], atol=1e-6)


def test_truth_box_heading_north_without_world(tmp_path):
    """Azimuth 0 (north): body +x -> +y, centre 2.25 m south of the front bumper (no world: gamma = 0)."""
    path = tmp_path / "r.rrd"
    with RerunReplayLogger(path) as lg:
        lg.log_truth(0.0, TrafficStep(t_s=0.0, vehicles={"a": _state("a", 0.0, (5.0, 7.0), 0.0, lead=True)}))
    c = _read(path)["/world/vehicles/truth"]
    _, centres = _column(c, "Boxes3D:centers")
    _, quats = _column(c, "Boxes3D:quaternions")
    np.testing.assert_allclose(centres[0][0], [5.0, 7.0 - 2.25, 0.75], atol=F32_ABS_M)
    x, y, z, w = quats[0][0]
    np.testing.assert_allclose([1 - 2 * (y * y + z * z), 2 * (x * y + w * z)], [0.0, 1.0], atol=1e-6)


def _quat_matrix(q):
    """Rotation matrix of the unit quaternion (x, y, z, w) (rerun's order; textbook formula)."""
    x, y, z, w = q
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _drawn_ellipse(centre, half, quat, n=73):
    """Points of the horizontal cross-section the viewer draws for a flat ellipsoid:
    centre + R(q) diag(half) [cos t, sin t, 0]."""
    t = np.linspace(0.0, 2.0 * np.pi, n)
    unit = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)])
    return np.asarray(centre) + (_quat_matrix(quat) @ (np.asarray(half)[:, None] * unit)).T


def test_ellipse_is_the_95_percent_contour(run):
    """Every point d of the drawn ellipse satisfies d^T C^-1 d = k^2, k^2 = chi2.ppf(0.95, 2) =
    5.9915; it lies flat at the estimate's height, centred on the estimate, drawn as wireframe."""
    assert ellipse_scale(0.95) ** 2 == pytest.approx(chi2.ppf(0.95, 2), rel=1e-12)
    _, chunks = run
    c = chunks[bp.ellipses_path("gps+uwb")]
    _, half = _column(c, "Ellipsoids3D:half_sizes")
    _, centres = _column(c, "Ellipsoids3D:centers")
    _, quats = _column(c, "Ellipsoids3D:quaternions")
    _, fill = _column(c, "Ellipsoids3D:fill_mode")
    _, pts = _column(chunks[bp.estimates_path("gps+uwb")], "Points3D:positions")
    covs = [np.array([[0.04, 0.01], [0.01, 0.09]]), np.array([[0.25, 0.0], [0.0, 0.01]])]
    k = N_STEPS - 1
    assert len(half[k]) == 2 and fill[k] == [rr.components.FillMode.MajorWireframe.value]
    for j, cov in enumerate(covs):
        np.testing.assert_allclose(centres[k][j], pts[k][j], atol=0)  # centred on the estimate
        assert 0.0 < half[k][j][2] < 0.01 * min(half[k][j][:2])  # flat: under 1 % of the minor semi-axis
        outline = _drawn_ellipse(centres[k][j], half[k][j], quats[k][j])
        np.testing.assert_allclose(outline[:, 2], pts[k][j][2], atol=1e-6)  # horizontal
        d = outline[:, :2] - np.asarray(centres[k][j][:2])
        m2 = np.einsum("pi,ij,pj->p", d, np.linalg.inv(cov), d)
        # float32 half sizes and quaternions: relative error ~1e-7 per number, ~1e-6 in m2
        np.testing.assert_allclose(m2, chi2.ppf(0.95, 2), rtol=1e-5)


@pytest.mark.parametrize("cov", [[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 4.0]], [[2.0, 1.9], [1.9, 2.0]],
                                 [[1e-6, 0.0], [0.0, 9.0]], [[1.0, 0.0], [0.0, 1.0]], [[2.0, -1.0], [-1.0, 0.0]]])
def test_ellipse_axes_are_the_covariance_eigenpairs(cov):
    """Semi-axes k sqrt(lambda) (major first) along the eigenvectors: the contour points
    d = R(angle) diag(semi-axes) [cos t, sin t] satisfy d^T C^-1 d = k^2 (hand-picked
    covariances: axis-aligned either way, nearly singular, thin, a circle); a matrix with a
    negative eigenvalue (round-off) gets a zero semi-axis, not NaN."""
    c = np.array(cov)
    half, angle = ellipse_axes(c, 2.0)
    lam = np.linalg.eigvalsh(c)
    np.testing.assert_allclose(half[0], 2.0 * np.sqrt(np.clip(lam[::-1], 0.0, None)), rtol=1e-12)
    if lam[0] <= 0:
        assert half[0, 1] == 0.0
        return
    t = np.linspace(0.0, 2.0 * np.pi, 13)
    d = (rotation_2d(angle[0]) @ (half[0][:, None] * np.stack([np.cos(t), np.sin(t)]))).T
    np.testing.assert_allclose(np.einsum("pi,ij,pj->p", d, np.linalg.inv(c), d), 4.0, rtol=1e-9)


def test_covariance_is_rotated_by_grid_convergence(tmp_path):
    """A covariance along true north only must be drawn along grid azimuth -gamma in net XY."""
    lanes = {"far": np.array([[39_000.0, 0.0], [41_000.0, 0.0]])}  # 40 km east of the central meridian
    gamma = GEO.grid_convergence_rad(40_000.0, 0.0)
    assert abs(gamma) > 1e-3  # ~ dlon sin(lat) = 5.7e-3 * 0.78: big enough to see
    path = tmp_path / "r.rrd"
    with RerunReplayLogger(path) as lg:
        lg.log_world(lanes, {}, [], [], GEO)
        lg.log_estimates(0.0, "s", ["a"], [[0.0, 0.0]], [[[0.0, 0.0], [0.0, 4.0]]])
    c = _read(path)[bp.ellipses_path("s")]
    (half,), (centre,), (quat,) = (_column(c, f"Ellipsoids3D:{name}")[1][0] for name in ("half_sizes", "centers", "quaternions"))
    outline = _drawn_ellipse(centre, half, quat)[:, :2]
    far = outline[np.argmax(np.linalg.norm(outline, axis=1))]
    assert np.linalg.norm(far) == pytest.approx(2.0 * ellipse_scale(0.95), rel=1e-6)  # k sigma, sigma = 2 m
    grid_az = math.atan2(far[0], far[1])
    grid_az = (grid_az + math.pi / 2) % math.pi - math.pi / 2  # the axis has no sign
    assert grid_az == pytest.approx(-gamma, abs=1e-6)


def test_ellipse_rows_are_what_logging_the_archetype_stores(tmp_path):
    """The buffered ellipse rows sent with send_columns are the rows that logging
    rr.Ellipsoids3D (the documented archetype: half sizes, centres, quaternions; one line
    radius, colour and fill mode per row) at the same time stores, component for component."""
    cov = np.array([[[0.04, 0.01], [0.01, 0.09]], [[0.25, -0.02], [-0.02, 0.01]]])
    xy = np.array([[3.0, 4.0], [-1.0, 2.0]])
    ours = tmp_path / "ours.rrd"
    with RerunReplayLogger(ours, params=RerunReplayParams(recording_id="e")) as lg:
        lg.log_estimates(0.5, "s", ["a", "b"], xy, cov)
    half, yaw = ellipse_axes(cov, ellipse_scale(0.95))
    z = RerunReplayParams().estimate_z_m
    ref = tmp_path / "ref.rrd"
    rec = rr.RecordingStream(application_id="v2v", recording_id="e", send_properties=False)
    rec.set_log_time_enabled(False)
    rec.set_log_tick_enabled(False)
    rec.save(ref)
    rec.set_time(bp.TIMELINE, duration=0.5)
    rec.log(bp.ellipses_path("s"), rr.Ellipsoids3D(
        half_sizes=np.column_stack([half, [1e-3, 1e-3]]), centers=np.column_stack([xy, [z, z]]),
        quaternions=[[0.0, 0.0, math.sin(a / 2), math.cos(a / 2)] for a in yaw],
        line_radii=0.03, colors=SOLUTION_RGB[0], fill_mode="majorwireframe"))
    rec.flush()
    rec.disconnect()
    path = "/" + bp.ellipses_path("s").lstrip("/")
    a, b = _rows_by_entity(_read(ours))[path], _rows_by_entity(_read(ref))[path]
    assert sorted(a) == sorted(f"Ellipsoids3D:{c}" for c in (
        "half_sizes", "centers", "quaternions", "line_radii", "colors", "fill_mode"))
    assert a == b


def test_links_and_sky(run):
    _, chunks = run
    _, colors = _column(chunks["/world/links/uwb"], "LineStrips3D:colors")
    rgb = [((c >> 24) & 255, (c >> 16) & 255, (c >> 8) & 255) for c in colors[-1]]  # rerun stores 0xRRGGBBAA
    assert rgb == [(40, 200, 80), (255, 150, 30)]  # los green, nlos orange
    _, sky = _column(chunks["/sky/veh.1"], "Points2D:positions")
    # az 90 deg, el 0 -> (90, 0); az 0, el 30 -> north, 60 deg from the centre, drawn up (y < 0);
    # az 180, el 90 -> the centre
    np.testing.assert_allclose(sky[-1], [[90.0, 0.0], [0.0, -60.0], [0.0, 0.0]], atol=1e-4)


def test_blueprint_is_stored_with_the_views(run):
    """The blueprint travels in the file, and each vehicle's along-track view (one tab per
    vehicle), run through rerun's own entity-path-filter engine on the recording, selects
    exactly that vehicle's along-track error and sigma series of every solution (escaped
    names included)."""
    path, _ = run
    reader = RrdReader(path)
    assert len(reader.recordings()) == 1 and len(reader.blueprints()) == 1
    kinds, queries = set(), []
    for c in reader.stream(store=reader.blueprints()[0]):
        rb = c.to_record_batch()
        if "ViewBlueprint:class_identifier" in rb.schema.names:
            kinds.update(rb.column("ViewBlueprint:class_identifier").to_pylist()[0])
        if "ViewContents:query" in rb.schema.names:
            queries.append(rb.column("ViewContents:query").to_pylist()[0])
    assert {"3D", "TimeSeries", "2D", "Map"} <= {k.replace("Spatial", "") for k in kinds}, kinds
    along_queries = [q for q in queries if any(line.endswith("/along_sigma") for line in q)]
    assert len(along_queries) == len(VEHICLES[1:])
    selections = [frozenset(c.entity_path for c in RrdReader(path).stream().filter(content=q)) for q in along_queries]
    expected = {frozenset(bp.error_path(s, v, k) for s in SOLUTIONS for k in ("along", "along_sigma")) for v in VEHICLES[1:]}
    assert set(selections) == expected


def _store_content(path, blueprint: bool = False) -> list[tuple]:
    """The recording store of ``path`` (its blueprint store if ``blueprint``): (entity, static,
    columns) of every chunk, sorted; the wall-clock ``log_time`` stamps and row ids left out."""
    reader = RrdReader(path)
    stream = reader.stream(store=reader.blueprints()[0]) if blueprint else reader.stream()
    out = []
    for c in stream:
        rb = c.to_record_batch()
        cols = {n: rb.column(n).to_pylist() for n in rb.schema.names if n != "log_time" and "RowId" not in n}
        out.append((c.entity_path, c.is_static, repr(sorted(cols.items()))))
    return sorted(out)


def _write_recording(path, send) -> None:
    """A recording saved to ``path`` with what ``send(rec)`` sends, flushed and closed."""
    rec = rr.RecordingStream(application_id="v2v", recording_id="test", send_properties=False)
    rec.save(path)
    send(rec)
    rec.flush()
    rec.disconnect()


def test_blueprint_chunks_are_what_send_blueprint_stores(tmp_path):
    """The cached blueprint chunks, sent to two recordings in turn (the second reuses the
    cache), store what ``RecordingStream.send_blueprint`` of the same blueprint stores (the
    log_time stamps aside), made active and default (rerun's own ``rrd print`` of the file)."""
    import shutil
    import subprocess
    import sys

    args = ("v2v", ("gps", "gps+uwb"), ("veh.1", "veh_2"), ("lead", "veh.1"), True)
    blueprint_chunks.cache_clear()
    _write_recording(tmp_path / "ref.rrd", lambda rec: rec.send_blueprint(
        bp.default_blueprint(*args[1:4], show_map=True), make_active=True, make_default=True))
    for name in ("a.rrd", "b.rrd"):
        _write_recording(tmp_path / name, lambda rec: send_blueprint_chunks(rec, "v2v", blueprint_chunks(*args)))
    assert blueprint_chunks.cache_info().hits == 1
    ref = _store_content(tmp_path / "ref.rrd", blueprint=True)
    assert len(ref) > 20
    assert _store_content(tmp_path / "a.rrd", blueprint=True) == ref
    assert _store_content(tmp_path / "b.rrd", blueprint=True) == ref
    exe = shutil.which("rerun", path=os.path.dirname(sys.executable))
    assert exe is not None, "rerun-sdk's `rerun` command is missing beside the interpreter (it ships with the pinned wheel)"
    for name in ("ref.rrd", "b.rrd"):
        out = subprocess.run([exe, "rrd", "print", str(tmp_path / name)], capture_output=True, text=True,
                             timeout=60).stdout
        lines = [ln for ln in out.splitlines() if ln.startswith("BlueprintActivationCommand")]
        assert len(lines) == 1 and "make_active: true, make_default: true" in lines[0], (name, lines)


def test_series_style_chunks_are_what_logging_the_styles_stores(tmp_path):
    """The cached style chunks of a (solution, vehicle), sent to two recordings (the second
    from the cache), store what logging each series' style static on its entity stores."""
    args = ("gps+uwb", "veh.1", (31, 119, 180))
    series_style_chunks.cache_clear()

    def log(rec):
        for series in bp.ERROR_SERIES:
            rec.log(bp.error_path(args[0], args[1], series), bp.series_style(series, *args), static=True)

    _write_recording(tmp_path / "ref.rrd", log)
    ref = _store_content(tmp_path / "ref.rrd")
    assert len(ref) == len(bp.ERROR_SERIES) and all(static for _, static, _ in ref)
    for name in ("a.rrd", "b.rrd"):
        _write_recording(tmp_path / name, lambda rec: rr.send_chunks(series_style_chunks(*args), recording=rec))
        assert _store_content(tmp_path / name) == ref
    assert series_style_chunks.cache_info().hits == 1


def test_each_error_series_is_styled_on_its_entity_and_shown_in_one_view(run):
    """The blueprint has no per-view overrides: an error series' look is the style logged
    static on its entity. That equals a per-view style only if no series is in two views,
    so each series path is selected by at most one view of the blueprint (rerun's own
    filter engine); and its static style is the solution's colour (0xRRGGBBAA), named after
    the solution (along/across), its +-1 sigma bounds at alpha 80, or per (solution, vehicle)."""
    path, chunks = run
    reader = RrdReader(path)
    queries, origins = {}, {}  # view path -> its content query, its space origin
    for c in reader.stream(store=reader.blueprints()[0]):
        assert "/overrides/" not in c.entity_path, c.entity_path
        rb = c.to_record_batch()
        if "ViewContents:query" in rb.schema.names:
            queries[c.entity_path.removesuffix("/ViewContents")] = rb.column("ViewContents:query").to_pylist()[0]
        if "ViewBlueprint:space_origin" in rb.schema.names:
            origins[c.entity_path] = rb.column("ViewBlueprint:space_origin").to_pylist()[0][0]
    assert set(queries) == set(origins) and len(queries) >= 6
    shown: dict[str, int] = defaultdict(int)
    for view, q in queries.items():  # ($origin: the filter engine here does not expand it)
        q = [line.replace("$origin", origins[view].rstrip("/")) for line in q]
        for p in {c.entity_path for c in RrdReader(path).stream().filter(content=q)}:
            shown[p] += 1
    assert shown["/" + bp.TRUTH] == 1  # the world view ($origin/**) is counted too
    for s, sol in enumerate(SOLUTIONS):
        r, g, b = SOLUTION_RGB[s]
        solid, faint = (r << 24) | (g << 16) | (b << 8) | 255, (r << 24) | (g << 16) | (b << 8) | 80
        w08 = float(np.float32(0.8))  # widths are float32 components
        for vid in VEHICLES[1:]:
            for series in bp.ERROR_SERIES:
                p = bp.error_path(sol, vid, series)
                assert shown[p] == 1, (p, shown[p])
                (static,) = [c.to_record_batch() for c in chunks[p] if c.is_static]
                style = {n.split(":")[1]: static.column(n).to_pylist()[0] for n in static.schema.names if n.startswith("SeriesLines:")}
                if series in ("along", "across"):
                    assert style == {"names": [sol], "colors": [solid], "widths": [1.5]}
                elif series.endswith("_sigma"):
                    assert style == {"names": [f"{sol} +1σ", f"{sol} -1σ"], "colors": [faint, faint], "widths": [w08, w08]}
                else:
                    assert style == {"names": [f"{sol} {vid}"], "colors": [solid], "widths": [1.5]}


def test_null_logger_accepts_every_call():
    """``--no-replay`` runs through NullLogger: it must override every public method of the
    ReplayLogger interface with the same parameters (a method it inherited would do the base
    class's work), and each returns None."""
    import inspect

    from v2v.viz.logger import ReplayLogger

    # (abort is the base class's no-op hook: nothing to discard)
    public = [n for n, f in inspect.getmembers(ReplayLogger, inspect.isfunction) if not n.startswith("_") and n != "abort"]
    assert {"log_world", "log_truth_many", "log_errors", "close"} <= set(public)
    for name in public:
        assert name in NullLogger.__dict__, f"NullLogger inherits {name}"
        assert list(inspect.signature(getattr(NullLogger, name)).parameters) == \
            list(inspect.signature(getattr(ReplayLogger, name)).parameters), name
    with NullLogger() as lg:
        lg.log_world({"a": np.zeros((2, 2))}, {"a": 3.2}, [], [], GEO)
        lg.log_truth(0.0, TrafficStep(t_s=0.0, vehicles={}))
        lg.log_estimates(0.0, "s", ["a"], np.zeros((1, 2)), np.eye(2)[None])
        lg.log_links(0.0, "uwb", np.zeros((1, 3)), np.ones((1, 3)), ["los"])
        lg.log_satellites(0.0, "a", [1], [0.0], [1.0], [True])
        assert lg.log_errors(0.0, "s", "a", 0.1, 0.2, 0.3, 0.4, 1.0, 1.0, 8, 0) is None
        assert lg.log_errors_many(0.0, "s", ["a"], [(0.1, 0.2, 0.3, 0.4, 1.0, 1.0, 8, 0)]) is None
    assert lg.close() is None and lg.abort() is None


def test_close_failure_leaves_no_file_and_keeps_the_old_one(tmp_path, monkeypatch):
    """If close() raises, nothing appears under the final name and no temp file is left."""
    path = tmp_path / "replay.rrd"
    path.write_bytes(b"previous run")
    lg = RerunReplayLogger(path)
    lg.log_errors(0.0, "s", "a", 0.1, 0.2, 0.3, 0.4, 1.0, 1.0, 8, 0)

    def broken_flush(*args, **kwargs):
        raise OSError("disk full")

    monkeypatch.setattr(lg._rec, "flush", broken_flush)
    with pytest.raises(OSError, match="disk full"):
        lg.close()
    assert path.read_bytes() == b"previous run"
    assert sorted(os.listdir(tmp_path)) == ["replay.rrd"]
    with pytest.raises(RuntimeError, match="closed"):
        lg.log_errors(0.1, "s", "a", 0.1, 0.2, 0.3, 0.4, 1.0, 1.0, 8, 0)


def test_context_manager_aborts_on_error(tmp_path):
    path = tmp_path / "replay.rrd"
    with pytest.raises(ValueError, match="unknown status"):
        with RerunReplayLogger(path) as lg:
            lg.log_links(0.0, "uwb", np.zeros((1, 3)), np.ones((1, 3)), ["blocked"])
    assert os.listdir(tmp_path) == []


def test_temp_file_is_hidden_until_close(tmp_path):
    path = tmp_path / "replay.rrd"
    lg = RerunReplayLogger(path)
    lg.log_errors(0.0, "s", "a", 0.1, 0.2, 0.3, 0.4, 1.0, 1.0, 8, 0)
    assert not path.exists()
    lg.close()
    lg.close()  # idempotent
    assert path.exists() and os.listdir(tmp_path) == ["replay.rrd"]


# ------------------------------------------------------------------ batched logging


class _Recorder(ReplayLogger):
    """Records the per-step calls the default ``*_many`` methods make."""

    def __init__(self):
        self.calls = []

    def log_world(self, lanes, lane_widths, buildings, foliage, geo):
        pass

    def log_truth(self, t_s, step):
        self.calls.append(("truth", t_s, step))

    def log_estimates(self, t_s, solution, vehicle_ids, est_xy_m, cov_en_m2):
        self.calls.append(("estimates", t_s, solution, list(vehicle_ids), np.asarray(est_xy_m).tolist(),
                           np.asarray(cov_en_m2).tolist()))

    def log_links(self, t_s, kind, a_xyz_m, b_xyz_m, status):
        self.calls.append(("links", t_s, kind, np.asarray(a_xyz_m).tolist(), np.asarray(b_xyz_m).tolist(), list(status)))

    def log_satellites(self, t_s, vehicle_id, prn, az_rad, el_rad, los):
        self.calls.append(("sky", t_s, vehicle_id, np.asarray(prn).tolist(), np.asarray(az_rad).tolist(),
                           np.asarray(el_rad).tolist(), np.asarray(los).tolist()))

    def log_errors(self, *args):
        self.calls.append(("errors", *args))

    def close(self):
        pass


def _steps(n: int = 12) -> list[TrafficStep]:
    """Steps of 3 vehicles; one step without cluster vehicles, 'veh_2' missing at step 3,
    a background box at every other step."""
    steps = []
    for k in range(n):
        t = k * DT_S
        vs = {} if k == 5 else {
            vid: _state(vid, t, (50.0 - 30.0 * i + t, 0.5 * i), math.pi / 2 + 0.1 * i, lead=i == 0)
            for i, vid in enumerate(VEHICLES) if not (k == 3 and vid == "veh_2")
        }
        bg = np.array([[5.0 + t, 3.0, 1.0, 4.0, 1.8, 1.5]]) if k % 2 else np.zeros((0, 6))
        steps.append(TrafficStep(t_s=t, vehicles=vs, background=bg))
    return steps


def _sky_rows(steps):
    """(t, vehicle, prn, az, el, los) at the even steps, two vehicles, 2-3 satellites."""
    rows = []
    for k, st in enumerate(steps[::2]):
        for v, m in (("veh.1", 3), ("lead", 2)):
            rows.append((st.t_s, v, np.arange(1, m + 1) + k, np.linspace(0.1, 3.0, m) + k,
                         np.linspace(0.2, 1.2, m), np.arange(m) % 2 == 0))
    return rows


def _link_rows(steps):
    """(t, a (m, 3), b (m, 3), status) for every step but 4 (no link there)."""
    rows = []
    for k, st in enumerate(steps):
        m = 0 if k == 4 else 1 + k % 3
        a = np.arange(3 * m, dtype=float).reshape(m, 3) + k
        rows.append((st.t_s, a, a + 1.0, [LINK_STATUSES_CYCLE[(k + i) % 3] for i in range(m)]))
    return [r for r in rows if len(r[1])]


LINK_STATUSES_CYCLE = ("los", "nlos", "rejected")


def _write(path, steps, batched: bool) -> dict[str, list]:
    # per step: every call sent at once (flush_rows=1), each ellipse computed on its own
    params = RerunReplayParams(recording_id="batch", flush_rows=8192 if batched else 1)
    links, sky = _link_rows(steps), _sky_rows(steps)
    with RerunReplayLogger(path, params=params) as lg:
        lg.log_world({"e_0": np.array([[-100.0, 0.0], [100.0, 0.0]])}, {"e_0": 3.2}, [], [], GEO)
        if batched:
            lg.log_truth_many(steps)
            lg.log_links_many([r[0] for r in links], "uwb", [len(r[1]) for r in links],
                              np.concatenate([r[1] for r in links]), np.concatenate([r[2] for r in links]),
                              [s for r in links for s in r[3]])
            lg.log_satellites_many([r[0] for r in sky], [r[1] for r in sky], [len(r[2]) for r in sky],
                                   *(np.concatenate([r[i] for r in sky]) for i in range(2, 6)))
        else:
            for st in steps:
                lg.log_truth(st.t_s, st)
            for t, a, b, status in links:
                lg.log_links(t, "uwb", a, b, status)
            for t, v, prn, az, el, los in sky:
                lg.log_satellites(t, v, prn, az, el, los)
        cov = np.array([[[0.04, 0.01], [0.01, 0.09]], [[np.nan, 0.0], [0.0, 1.0]], [[0.25, -0.02], [-0.02, 0.01]]])
        epochs = {s: [] for s in SOLUTIONS}  # solution -> (t, ids, xy, cov, error rows) of its epochs
        for k, st in enumerate(steps):
            n_est = k % 4  # 0 to 3 estimates; the second has no finite covariance (no ellipse)
            ids = [f"v{i}" for i in range(n_est)][::-1 if k == 7 else 1]  # one epoch in another order
            xy = [[10.0 + k + i, -1.0 * i] for i in range(n_est)]
            epochs[SOLUTIONS[k % 2]].append((st.t_s, ids, xy, cov[:n_est], [_error_row(k, k % 2, i) for i in range(n_est)]))
            if batched:
                lg.log_errors_many(st.t_s, "gps only", VEHICLES[1:], [_error_row(k, 2, v) for v in range(2)])
            else:
                for v in range(2):
                    lg.log_errors(st.t_s, "gps only", VEHICLES[1 + v], *_error_row(k, 2, v))
        for s, eps in epochs.items():
            if batched:
                lg.log_epochs([e[0] for e in eps], s, [len(e[1]) for e in eps], [v for e in eps for v in e[1]],
                              np.concatenate([np.reshape(e[2], (-1, 2)) for e in eps]), np.concatenate([e[3] for e in eps]),
                              np.concatenate([np.reshape(e[4], (-1, 8)) for e in eps]))
            else:
                for t, ids, xy, c, rows in eps:
                    lg.log_estimates(t, s, ids, xy, c)
                    for v, row in zip(ids, rows, strict=True):
                        lg.log_errors(t, s, v, *row)
    return _read(path)


def _rows_by_entity(chunks):
    """entity -> component -> [(time, value)] in time order (static rows: time None)."""
    out = {}
    for path, cs in chunks.items():
        comps = defaultdict(list)
        for c in cs:
            rb = c.to_record_batch()
            t = rb.column(bp.TIMELINE).cast("int64").to_pylist() if bp.TIMELINE in rb.schema.names else [None] * rb.num_rows
            for name in rb.schema.names:
                if name != bp.TIMELINE and ":" in name:
                    comps[name] += [(ti, v) for ti, v in zip(t, rb.column(name).to_pylist(), strict=True) if v is not None]
        out[path] = {k: sorted(v, key=lambda tv: -1 if tv[0] is None else tv[0]) for k, v in comps.items()}
    return out


def test_batched_calls_store_the_same_rows_as_per_step_calls(tmp_path):
    """log_truth_many / log_links_many / log_satellites_many / log_errors_many / log_epochs and the
    deferred ellipses give the same entities, components, time stamps and values (exactly) as
    one call per step sent at once: empty steps, steps without links, epochs without estimates
    or with vehicles in another order, estimates without a finite covariance."""
    steps = _steps()
    per_step = _rows_by_entity(_write(tmp_path / "a.rrd", steps, batched=False))
    batched = _rows_by_entity(_write(tmp_path / "b.rrd", steps, batched=True))
    assert set(per_step) == set(batched)
    paths = (bp.TRUTH, bp.BACKGROUND, bp.links_path("uwb"), bp.sky_path("lead"), bp.ellipses_path("gps"))
    assert {"/" + p.lstrip("/") for p in paths} <= set(batched)
    for path in per_step:
        assert per_step[path] == batched[path], path
    chunks = _read(tmp_path / "b.rrd")
    _, half = _column(chunks["/" + bp.TRUTH], "Boxes3D:half_sizes")
    assert len(half) == len(steps) and half[5] == []  # the empty step is a row without boxes
    _, half = _column(chunks[bp.ellipses_path("gps+uwb")], "Ellipsoids3D:half_sizes")
    assert [len(h) for h in half] == [1, 2] * 3  # steps 1, 3, 5, ...: 1 and 3 estimates, one NaN


def test_error_rows_of_the_wrong_shape_are_refused(tmp_path):
    lg = RerunReplayLogger(tmp_path / "r.rrd")
    with pytest.raises(ValueError, match="8 numbers each"):
        lg.log_errors_many(0.0, "gps", ["a", "b"], [tuple(range(8)), tuple(range(7))])
    with pytest.raises(ValueError, match="2 vehicle ids and 1 rows"):
        lg.log_errors_many(0.0, "gps", ["a", "b"], [tuple(range(8))])
    with pytest.raises(ValueError, match="8 numbers each"):
        lg.log_errors_many(0.0, "gps", ["a"], [("x",) * 8])
    row = [0.0] * 8
    lg.log_errors_many(0.0, "gps", ["a"], [row])
    row[0] = 5.0  # the row was copied when logged
    assert np.concatenate(lg._errors[("gps", "a")].rows).tolist() == [[0.0] * 8]
    with pytest.raises(ValueError, match="2 times and 2 counts .adding up to 3. for 2 vehicle ids"):
        lg.log_epochs([0.1, 0.2], "gps", [1, 2], ["a", "b"], np.zeros((2, 2)), np.zeros((2, 2, 2)), np.zeros((2, 8)))
    lg.abort()
    assert not list(tmp_path.iterdir())


def test_default_batch_methods_make_the_per_step_calls():
    """The base-class ``*_many`` make one per-step call per row, in order, with its slice."""
    steps = _steps(4)
    lg = _Recorder()
    lg.log_truth_many(steps)
    lg.log_links_many([0.1, 0.2], "bearing", [2, 1], np.arange(9.0).reshape(3, 3), np.ones((3, 3)), ["los", "nlos", "rejected"])
    lg.log_satellites_many([0.0, 0.0], ["a", "b"], [1, 2], [3, 4, 5], [0.1, 0.2, 0.3], [0.5, 0.6, 0.7], [True, False, True])
    lg.log_errors_many(0.3, "gps", ["a", "b"], [(1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0), range(8)])
    with pytest.raises(ValueError, match="2 vehicle ids and 1 rows of 8 numbers each"):
        lg.log_errors_many(0.3, "gps", ["a", "b"], [range(8)])
    assert [c[:2] for c in lg.calls[:4]] == [("truth", st.t_s) for st in steps]
    assert lg.calls[4:] == [
        ("links", 0.1, "bearing", [[0.0, 1.0, 2.0], [3.0, 4.0, 5.0]], [[1.0] * 3] * 2, ["los", "nlos"]),
        ("links", 0.2, "bearing", [[6.0, 7.0, 8.0]], [[1.0] * 3], ["rejected"]),
        ("sky", 0.0, "a", [3], [0.1], [0.5], [True]),
        ("sky", 0.0, "b", [4, 5], [0.2, 0.3], [0.6, 0.7], [False, True]),
        ("errors", 0.3, "gps", "a", 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7, 8),
        ("errors", 0.3, "gps", "b", 0, 1, 2, 3, 4, 5, 6, 7),
    ]
    lg.calls.clear()
    cov = np.arange(12.0).reshape(3, 2, 2)
    lg.log_epochs([0.4, 0.5, 0.6], "gps", [2, 0, 1], ["a", "b", "a"], [[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]], cov,
                  np.arange(24.0).reshape(3, 8))
    assert lg.calls == [
        ("errors", 0.4, "gps", "a", *range(8)), ("errors", 0.4, "gps", "b", *range(8, 16)),
        ("estimates", 0.4, "gps", ["a", "b"], [[1.0, 2.0], [3.0, 4.0]], cov[:2].tolist()),
        ("estimates", 0.5, "gps", [], [], []),
        ("errors", 0.6, "gps", "a", *range(16, 24)),
        ("estimates", 0.6, "gps", ["a"], [[5.0, 6.0]], cov[2:].tolist()),
    ]


def test_truth_and_links_windows_match_a_per_step_scan():
    """v2v.run._log_truth_and_links (vectorized over a chunk) logs at each step the links
    measured in (previous step, step + 1e-9] between vehicles present at that step, as a
    scan step by step does (a step without links too: an empty row); a record 0.5 ns after a
    step belongs to that step and the next."""
    from v2v.run import _log_truth_and_links

    steps = _steps(8)
    t_rec = np.array([-0.05, 0.0, 0.1, 0.1 + 5e-10, 0.15, 0.3, 0.3, 0.35, 0.5, 0.52, 0.7, 0.71, 0.9])
    rng = np.random.default_rng(1)
    perm = rng.permutation(len(t_rec))  # records need not arrive in time order
    ends = [("lead", "veh.1"), ("veh.1", "veh_2"), ("lead", "veh_2")]
    pairs = [("lead", "gone") if i == 9 else ends[i % len(ends)] for i in range(len(t_rec))]
    meas = SimpleNamespace(t_s=t_rec[perm], a=tuple(pairs[i][0] for i in perm), b=tuple(pairs[i][1] for i in perm),
                           los=(np.arange(len(t_rec)) % 2 == 0)[perm], n=len(t_rec))
    prev = -0.02
    lg = _Recorder()
    assert _log_truth_and_links(lg, steps, meas, None, {}, prev) == steps[-1].t_s
    expected, p, logged = [], prev, []
    for st in steps:  # the per-step scan
        idx = [k for k in np.argsort(meas.t_s, kind="stable")
               if p < meas.t_s[k] <= st.t_s + 1e-9 and meas.a[k] in st.vehicles and meas.b[k] in st.vehicles]
        logged += [int(perm[k]) for k in idx]
        # every step, one without links too: its empty row clears the links drawn before
        expected.append(("links", st.t_s, "uwb", [st.vehicles[meas.a[k]].xyz_m.tolist() for k in idx],
                         [st.vehicles[meas.b[k]].xyz_m.tolist() for k in idx],
                         ["los" if meas.los[k] else "nlos" for k in idx]))
        p = st.t_s
    got = [c for c in lg.calls if c[0] == "links"]
    assert got == expected
    # record 3 (0.1 s + 0.5 ns) is logged at steps 0.1 and 0.2, record 2 (0.1 s) at 0.1 only; not logged:
    # 0 (before prev), 5 (step 0.3, veh_2 absent), 8 (step 0.5, nobody), 9 (a vehicle not in the
    # cluster), 11 and 12 (after the last step)
    assert logged.count(3) == 2 and logged.count(2) == 1
    assert set(range(len(t_rec))) - set(logged) == {0, 5, 8, 9, 11, 12}
    assert [c[1] for c in lg.calls if c[0] == "truth"] == [st.t_s for st in steps]


# ---------------------------------------------------------------------------- a real run against its tables

TWO_CLUSTERS_TOML = """
name = "two_clusters"
seed = 5
duration_s = 6.0

[network]
name = "open_highway"

[[clusters]]
name = "a"
vehicles = 3
lanes = [0]

[[clusters]]
name = "b"
vehicles = 3
lanes = [1]
depart_s = 4.0

[[solutions]]
name = "GPS"
sensors = ["gnss"]

[[solutions]]
name = "GPS+UWB"
sensors = ["gnss", "uwb"]

[sensors.bearing]
rate_hz = 2.0
"""


@pytest.fixture(scope="module")
def real_run(tmp_path_factory):
    """A short two-cluster run of the shipped open_highway net (origin_h_m 1100 m: ENU metres
    are 1.7e-4 longer than net XY metres there), read back with its tables."""
    import pandas as pd

    from v2v.config.scenario import load_scenario
    from v2v.run import run_scenario

    folder = tmp_path_factory.mktemp("real")
    (folder / "two.toml").write_text(TWO_CLUSTERS_TOML)
    res = run_scenario(load_scenario(folder / "two.toml"), folder / "run", quiet=True, replay=True,
                       save_measurements=True)
    out = folder / "run"
    return (_read(out / "replay.rrd"), pd.read_parquet(out / "truth.parquet"), pd.read_parquet(out / "epochs.parquet"),
            res.summary, pd.read_parquet(out / "measurements.parquet"))


def _rows_at(chunks):
    """{time_ns: {component: value}} of temporal rows (the last row logged at a time, as the viewer shows)."""
    out: dict[int, dict] = {}
    for c in chunks:
        if c.is_static:
            continue
        rb = c.to_record_batch()
        names = [n for n in rb.schema.names if ":" in n]
        cols = {n: rb.column(n).to_pylist() for n in names}
        for i, t in enumerate(rb.column(bp.TIMELINE).cast("int64").to_pylist()):
            out.setdefault(t, {}).update({n: cols[n][i] for n in names if cols[n][i] is not None})
    return out


def _grid_convergence_from_tables(truth, epochs) -> float:
    """Angle from the true ENU baselines (east, north) of epochs.parquet to the same vehicles'
    net-XY baselines in truth.parquet: the grid convergence, estimated from the tables alone."""
    xy = truth.set_index(["t_s", "vehicle"])[["x_m", "y_m"]]
    lead = truth[truth.is_lead].set_index(["t_s", "cluster"])[["x_m", "y_m"]]
    f = xy.loc[list(zip(epochs.t_s, epochs.vehicle, strict=True))].to_numpy()
    ld = lead.loc[list(zip(epochs.t_s, epochs.cluster, strict=True))].to_numpy()
    d = (f - ld)[:, 0] + 1j * (f - ld)[:, 1]
    enu = epochs.true_e_m.to_numpy() + 1j * epochs.true_n_m.to_numpy()
    return float(np.angle(np.mean(d / enu * np.abs(enu) / np.abs(d))))


def test_real_run_truth_and_times_are_the_tables(real_run):
    """Antennas and map points are truth.parquet's (net XY m, WGS-84 deg); the boxes carry its
    vehicles at every step; nothing is logged outside [0, simulated_s]; no position is NaN."""
    chunks, truth, _, summary, _ = real_run
    ants, boxes, geo = (_rows_at(chunks["/" + p]) for p in (bp.TRUTH_ANTENNAS, bp.TRUTH, bp.MAP_VEHICLES))
    times = np.sort(truth.t_s.unique())
    np.testing.assert_allclose(np.array(sorted(ants)) / 1e9, times, atol=1e-9, rtol=0)
    by_t = {round(t * 1e9): g.set_index("vehicle") for t, g in truth.groupby("t_s")}
    for t_ns, row in boxes.items():
        g = by_t[t_ns]
        labels = row["Boxes3D:labels"]
        assert sorted(labels) == sorted(g.index)
        # float32 positions: |x|, |y| < 2048 m, spacing 2**-13 m, rounding <= 6.2e-5 m
        np.testing.assert_allclose(ants[t_ns]["Points3D:positions"], g.loc[labels, ["x_m", "y_m", "z_m"]], atol=6.2e-5,
                                   rtol=0)
        np.testing.assert_allclose(geo[t_ns]["GeoPoints:positions"], g.loc[labels, ["lat_deg", "lon_deg"]], atol=1e-12,
                                   rtol=0)
    for path, cs in chunks.items():
        for c in cs:
            rb = c.to_record_batch()
            if not c.is_static:
                t = rb.column(bp.TIMELINE).cast("int64").to_numpy() / 1e9
                assert t.min() >= 0.0 and t.max() <= summary["simulated_s"] + 1e-9, path
            for name in rb.schema.names:
                if name.split(":")[-1] in ("positions", "centers", "half_sizes", "strips", "vertex_positions"):
                    vals = np.array(pa_flatten(rb.column(name)), dtype=float)
                    assert np.isfinite(vals).all(), (path, name)


def pa_flatten(col):
    """All numbers of a (nested) arrow list column."""
    import pyarrow as pa

    arr = col.combine_chunks() if hasattr(col, "combine_chunks") else col
    while pa.types.is_list(arr.type) or pa.types.is_fixed_size_list(arr.type) or pa.types.is_large_list(arr.type):
        arr = arr.flatten()
    return arr.to_numpy(zero_copy_only=False)


def test_real_run_estimates_ellipses_and_errors_are_the_epochs(real_run):
    """Per solution and cluster (two clusters: each its own entity, so that neither hides the
    other): at every epoch the drawn estimates are the initialized vehicles of epochs.parquet;
    estimate - the vehicle's true antenna (truth.parquet) = (est - true) ENU turned by the grid
    convergence, as the lead frame's errors are; the ellipse semi-axes are
    sqrt(chi2.ppf(0.95, 2)) sqrt(eigenvalues) of (cov_ee, cov_en; cov_en, cov_nn) along its
    eigenvectors; the error series are the epochs' along / across errors, +-sigma and NEES."""
    chunks, truth, epochs, _, _ = real_run
    ini = epochs[epochs.initialized]
    assert set(ini.cluster) == {"a", "b"} and len(ini)
    gamma = _grid_convergence_from_tables(truth, ini)
    rot = rotation_2d(gamma)
    k95 = math.sqrt(chi2.ppf(0.95, 2))
    xy = truth.set_index(["t_s", "vehicle"])[["x_m", "y_m"]]
    for (sol, cl), e in ini.groupby(["solution", "cluster"]):
        pts = _rows_at(chunks[bp.estimates_path(sol, cl)])
        ell = _rows_at(chunks[bp.ellipses_path(sol, cl)])
        by_t = {round(t * 1e9): g.set_index("vehicle") for t, g in e.groupby("t_s")}
        assert sorted(pts) == sorted(by_t) == sorted(ell), (sol, cl)
        for t_ns, g in by_t.items():
            labels = pts[t_ns]["Points3D:labels"]
            assert sorted(labels) == sorted(g.index)
            r = g.loc[labels]
            drawn = np.asarray(pts[t_ns]["Points3D:positions"])[:, :2]
            true_xy = xy.loc[[(r.t_s.iat[0], v) for v in labels]].to_numpy()
            err_en = np.column_stack([r.est_e_m - r.true_e_m, r.est_n_m - r.true_n_m])
            np.testing.assert_allclose(drawn - true_xy, err_en @ rot.T, atol=2e-4, rtol=0)
            np.testing.assert_allclose(np.asarray(ell[t_ns]["Ellipsoids3D:centers"]), pts[t_ns]["Points3D:positions"],
                                       atol=0)
            for j, (_, row) in enumerate(r.iterrows()):
                lam, vec = np.linalg.eigh([[row.cov_ee_m2, row.cov_en_m2], [row.cov_en_m2, row.cov_nn_m2]])
                half = ell[t_ns]["Ellipsoids3D:half_sizes"][j]
                np.testing.assert_allclose(half[:2], k95 * np.sqrt(lam[::-1]), rtol=1e-6)
                major = _quat_matrix(ell[t_ns]["Ellipsoids3D:quaternions"][j])[:2, 0]
                want = rot @ vec[:, 1]
                if lam[1] > 1.001 * lam[0]:
                    assert abs(major @ want) == pytest.approx(1.0, abs=1e-6)
        for v, ev in e.groupby("vehicle"):
            ev = ev.sort_values("t_s")
            series = {s: _column(chunks[bp.error_path(sol, v, s)], "Scalars:scalars") for s in
                      ("along", "across", "along_sigma", "across_sigma", "nees")}
            np.testing.assert_allclose(np.asarray(series["along"][0]) / 1e9, ev.t_s, atol=1e-9, rtol=0)  # ns
            assert [x[0] for x in series["along"][1]] == ev.along_err_m.tolist()
            assert [x[0] for x in series["across"][1]] == ev.across_err_m.tolist()
            assert series["along_sigma"][1] == [[s, -s] for s in ev.sigma_along_m]
            assert series["across_sigma"][1] == [[s, -s] for s in ev.sigma_across_m]
            assert [x[0] for x in series["nees"][1]] == ev.nees_pos.tolist()


def _nis_series(chunks, epochs):
    """{(solution, vehicle): (times_ns, values)} of the replay's nis series, for the
    initialized (solution, vehicle) pairs of ``epochs``."""
    out = {}
    for (sol, v), _ in epochs[epochs.initialized].groupby(["solution", "vehicle"]):
        t, vals = _column(chunks[bp.error_path(sol, v, "nis")], "Scalars:scalars")
        out[sol, v] = (t, np.array([x[0] for x in vals], dtype=float))
    return out


def test_real_run_nis_is_a_mean_of_accepted_nis_where_the_epoch_used_measurements(real_run, tmp_path):
    """The nis series (a mean of accepted NIS: v2v.metrics.errors.epoch_nis_sums) has a point
    at every initialized epoch: NaN exactly where the row's used_pr + used_doppler + used_uwb
    + used_bearing is 0 (those counts count the same updates, a pair's for both vehicles),
    else inside (0, k^2] (each accepted NIS passed the gate |nu| <= k sqrt(S), k^2 = 10.83).
    The same run in 1 s chunks (updates and epochs handed to the replay chunk by chunk)
    logs the same values."""
    from v2v.config.scenario import load_scenario
    from v2v.estimation.filter import FilterConfig
    from v2v.run import run_scenario

    chunks, _, epochs, _, _ = real_run
    gate = FilterConfig().gate_k ** 2
    series = _nis_series(chunks, epochs)
    assert len(series) >= 6
    n_points = 0
    for (sol, v), (t_ns, nis) in series.items():
        e = epochs[epochs.initialized & (epochs.solution == sol) & (epochs.vehicle == v)].sort_values("t_s")
        np.testing.assert_allclose(t_ns / 1e9, e.t_s, atol=1e-9, rtol=0)
        used = sum(e[k].to_numpy() for k in ("used_pr", "used_doppler", "used_uwb", "used_bearing"))
        np.testing.assert_array_equal(np.isnan(nis), used == 0, err_msg=f"{sol} {v}")
        finite = nis[used > 0]
        assert ((finite > 0.0) & (finite <= gate)).all(), (sol, v, finite.min(), finite.max())
        n_points += len(finite)
    assert n_points > 100
    (tmp_path / "two.toml").write_text(TWO_CLUSTERS_TOML)
    run_scenario(load_scenario(tmp_path / "two.toml"), tmp_path / "run", quiet=True, replay=True, chunk_s=1.0)
    chunked = _nis_series(_read(tmp_path / "run" / "replay.rrd"), epochs)
    assert chunked.keys() == series.keys()
    for key, (t_ns, nis) in series.items():
        np.testing.assert_array_equal(chunked[key][0], t_ns)
        np.testing.assert_array_equal(chunked[key][1], nis)


def test_real_run_links_are_the_steps_measurements(real_run):
    """At every step the links drawn (the row at that step: none is left from an earlier step)
    join antennas of truth.parquet at that step; bearings (2 Hz, time-tagged at steps) are the
    measurements.parquet rows of that step between cluster vehicles, NLOS ones orange."""
    chunks, truth, _, _, meas = real_run
    steps = sorted(round(t * 1e9) for t in truth.t_s.unique())
    ants = _rows_at(chunks["/" + bp.TRUTH_ANTENNAS])
    for kind in ("uwb", "bearing"):
        links = _rows_at(chunks[bp.links_path(kind)])
        first = min(links)
        assert [t for t in steps if t >= first] == sorted(links), kind  # a row at every step from the first
        for t in sorted(links):
            strips = links[t].get("LineStrips3D:strips", [])
            ends = np.asarray(strips, dtype=float).reshape(-1, 3)
            a = np.asarray(ants[t]["Points3D:positions"])
            assert all(np.min(np.linalg.norm(a - p, axis=1)) == 0.0 for p in ends), (kind, t)
    bearings = _rows_at(chunks[bp.links_path("bearing")])
    b = meas[(meas.type == "bearing") & meas.vehicle.isin(truth.vehicle) & meas.other.isin(truth.vehicle)]
    for t in steps:
        rows = b[np.round(b.t_s * 1e9) == t]
        colors = bearings.get(t, {}).get("LineStrips3D:colors", [])
        assert len(colors) == len(rows) if t in bearings else len(rows) == 0
        nlos_rgba = (255 << 24) | (150 << 16) | (30 << 8) | 255
        assert sum(c == nlos_rgba for c in colors) == int((~rows.los).sum())


def test_an_epoch_without_initialized_vehicles_clears_the_estimates(tmp_path):
    """v2v.run's epoch logger: an epoch whose rows are all uninitialized (after an estimate was
    drawn) is an empty estimates and ellipses row, so the viewer does not keep showing the
    estimate of the epoch before; the error series have no point there and a Clear at that
    time (rerun draws a clear in a time-series plot as a hole in the line, so the plot does not
    join 0.0 s to 0.2 s as if there had been an estimate in between). The nis series
    is the mean NIS of the vehicle's accepted updates of each epoch (update log by hand:
    0.0 s a pseudorange NIS 0.5 and a UWB range lead-veh.1 NIS 1.5, mean 1; 0.1 s one
    update, no point: uninitialized; 0.2 s a rejected pseudorange only, NaN)."""
    import pandas as pd

    from v2v.estimation.filter import UpdateInfo
    from v2v.pipeline import UpdateLog
    from v2v.run import _epoch_logger

    t = [0.0, 0.1, 0.2]
    frame = pd.DataFrame({
        "t_s": t, "vehicle": "veh.1", "initialized": [True, False, True],
        "est_e_m": [1.0, np.nan, 2.0], "est_n_m": [0.0, np.nan, 0.0], "true_e_m": 0.0, "true_n_m": 0.0,
        "cov_ee_m2": [1.0, np.nan, 1.0], "cov_en_m2": [0.0, np.nan, 0.0], "cov_nn_m2": [1.0, np.nan, 1.0],
        "along_err_m": [0.1, np.nan, 0.2], "across_err_m": 0.0, "sigma_along_m": 1.0, "sigma_across_m": 1.0,
        "nees_pos": 1.0, "used_pr": 8, "rejected_pr": 0, "rejected_uwb": 0, "rejected_bearing": 0,
        "rejected_doppler": 0, "rejected_phase": [2, 0, 3],  # (a carrier-phase solution's column)
    })
    steps = {round(x * 1e6): TrafficStep(t_s=x, vehicles={
        "lead": _state("lead", x, (0.0, 0.0), 0.0, lead=True), "veh.1": _state("veh.1", x, (0.0, -20.0), 0.0, lead=False)})
        for x in t}
    log = UpdateLog()
    log.keep_recent = True
    log.add(0.0, [UpdateInfo("sd_pseudorange", ("veh.1",), 0.5, 0.5, 0.5, True, 3),
                  UpdateInfo("uwb", ("lead", "veh.1"), 1.5, 1.5, 1.5, True)], [False, False])
    log.add(0.1, [UpdateInfo("sd_pseudorange", ("veh.1",), 1.0, 1.0, 1.0, True, 3)], [False])
    log.add(0.2, [UpdateInfo("sd_pseudorange", ("veh.1",), 6.0, 1.0, 36.0, False, 3)], [False])
    log.flush()
    path = tmp_path / "r.rrd"
    with RerunReplayLogger(path) as lg:
        _epoch_logger(lg, GEO, {"replay": 0.0})("GPS", "lead", frame, lambda x: steps[round(x * 1e6)], "",
                                                log.take_recent(), t)
    chunks = _read(path)
    t_ns, pos = _column(chunks[bp.estimates_path("GPS")], "Points3D:positions")
    assert [round(x / 1e8) for x in t_ns] == [0, 1, 2] and [len(p) for p in pos] == [1, 0, 1]
    _, half = _column(chunks[bp.ellipses_path("GPS")], "Ellipsoids3D:half_sizes")
    assert [len(h) for h in half] == [1, 0, 1]
    # drawn at the true antenna plus the error (east 1 m, 2 m; no grid convergence at the origin)
    np.testing.assert_allclose([pos[0][0][:2], pos[2][0][:2]], [[1.0, -20.0], [2.0, -20.0]], atol=F32_ABS_M)
    t_err, along = _column(chunks[bp.error_path("GPS", "veh.1", "along")], "Scalars:scalars")
    assert [round(x / 1e8) for x in t_err] == [0, 2] and along == [[0.1], [0.2]]
    _, rej = _column(chunks[bp.error_path("GPS", "veh.1", "rejections")], "Scalars:scalars")
    assert rej == [[2.0], [3.0]]  # every rejected_* count, the carrier phase's too
    t_nis, nis = _column(chunks[bp.error_path("GPS", "veh.1", "nis")], "Scalars:scalars")
    assert [round(x / 1e8) for x in t_nis] == [0, 2] and nis[0] == [1.0] and np.isnan(nis[1][0])
    for series in bp.ERROR_SERIES:
        t_clear, clear = _column(chunks[bp.error_path("GPS", "veh.1", series)], "Clear:is_recursive")
        assert [round(x / 1e8) for x in t_clear] == [1] and clear == [[False]], series


def test_error_gaps_start_where_an_estimate_stops_across_chunks():
    """_error_gap_starts: a gap starts at a vehicle's first uninitialized row after an
    initialized one, also when the initialized row was the last of the chunk before; a vehicle
    never initialized (or still uninitialized) starts none."""
    import pandas as pd

    from v2v.run import _error_gap_starts

    est: dict[tuple[str, str], bool] = {}
    a = pd.DataFrame({"t_s": [0.0, 0.0, 0.1, 0.1], "vehicle": ["v1", "v2"] * 2,
                      "initialized": [False, True, False, True]})
    assert _error_gap_starts(a["t_s"], a["vehicle"], a["initialized"].to_numpy(), est, "S") == ([], [])
    b = pd.DataFrame({"t_s": [0.2, 0.2, 0.3, 0.3, 0.4, 0.4], "vehicle": ["v1", "v2"] * 3,
                      "initialized": [True, False, False, False, True, True]})
    assert _error_gap_starts(b["t_s"], b["vehicle"], b["initialized"].to_numpy(), est, "S") == ([0.2, 0.3], ["v2", "v1"])
    assert _error_gap_starts(b["t_s"], b["vehicle"], b["initialized"].to_numpy(), est, "T") == ([0.3], ["v1"])
    c = pd.DataFrame({"t_s": [0.5], "vehicle": ["v2"], "initialized": [False]})
    assert _error_gap_starts(c["t_s"], c["vehicle"], c["initialized"].to_numpy(), est, "S") == ([0.5], ["v2"])


def test_real_run_measurement_statistics_pool_the_clusters(real_run):
    """summary.json's per-solution measurement statistics cover every cluster's filter (before
    2026-12-05 a run with several clusters had none: they were keyed "cluster/solution" and
    looked up by solution). Checked against epochs.parquet, counted independently of the
    update log: each accepted SD Doppler names one vehicle and falls in one output interval, so
    the solution's used Dopplers are the sum of its rows' ``used_doppler`` over both clusters;
    likewise the rejected ones."""
    _, _, epochs, summary, _ = real_run
    assert set(epochs.cluster) == {"a", "b"}
    for sol in ("GPS", "GPS+UWB"):
        meas = summary["statistics"][sol]["measurements"]
        rows = epochs[epochs.solution == sol]
        assert meas["sd_doppler"]["used"] == int(rows.used_doppler.sum()) > 0
        assert meas["sd_doppler"]["rejected"] == int(rows.rejected_doppler.sum())
        for c in ("a", "b"):  # each cluster contributed
            assert int(rows[rows.cluster == c].used_doppler.sum()) > 0
    assert "uwb" in summary["statistics"]["GPS+UWB"]["measurements"]
    assert "uwb" not in summary["statistics"]["GPS"]["measurements"]


def test_real_run_exchange_counts_add_up_the_clusters(real_run):
    """summary.json's ``exchange`` counts every cluster's link (before 2026-12-06: the last
    cluster's only). Counted from measurements.parquet: each cluster's lead is sent its
    followers' GNSS epochs (one message per receiver epoch) and every UWB range not initiated
    by itself (the ranges go to every lead, one message each); bearings go on no link (no
    solution uses them)."""
    _, _, _, summary, meas = real_run
    gnss = meas[meas.type == "pseudorange"][["t_s", "vehicle"]].drop_duplicates()
    uwb = meas[meas.type == "uwb"]
    want = 0
    for lead in summary["leads"]:
        cluster = lead.split(".")[0]
        want += int(((gnss.vehicle != lead) & gnss.vehicle.str.startswith(cluster + ".")).sum())
        want += int((uwb.vehicle != lead).sum())
    assert len(summary["leads"]) == 2 and summary["exchange"]["sent"] == want
