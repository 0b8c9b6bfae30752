"""Occlusion geometry and polygon loading against hand-computed geometry.

Tolerances: the geometry is exact arithmetic on metre-scale numbers, so results agree
with the closed-form values to float64 rounding. ``ATOL_M = 1e-9`` m is ~1e5 times the
rounding of a 100 m-scale computation (~1e-14 m) and far below any physical length here.
Angle thresholds are probed at +-1e-9 rad, which moves the ray height at the wall by
~1e-8 m, still ~1e6 times above rounding.
"""

from __future__ import annotations

import math
import subprocess
from pathlib import Path

import numpy as np
import pytest

from v2v.errors import UserError
from v2v.world.buildings import Building, FoliageArea, World, classify, load_polygons
from v2v.world.occlusion import OcclusionGeometry, _box_hits, _box_hits_vectorized

ATOL_M = 1e-9
DATA = Path(__file__).parent / "data"


def square(x0: float, x1: float, y0: float, y1: float) -> np.ndarray:
    return np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)


def building(bid: str, fp: np.ndarray, h: float) -> Building:
    return Building(id=bid, footprint_xy_m=fp, height_m=h, height_source="height")


def geometry(*buildings: Building, foliage: tuple[FoliageArea, ...] = ()) -> OcclusionGeometry:
    return OcclusionGeometry(World(buildings=tuple(buildings), foliage=foliage))


# ------------------------------------------------------------------ sky rays
@pytest.mark.parametrize("az_rad", [0.0, 0.3, -0.6])
def test_sky_threshold_elevation_at_near_face(az_rad):
    """20 m building, near face y = 10 m; antenna at 1.5 m height at the origin.

    Along grid azimuth az the ray reaches the near face at horizontal distance
    d = 10 / cos(az) (inside the face's x-extent for these az), so the ray clears the
    roof edge iff el > atan((20 - 1.5) / d).
    """
    g = geometry(building("B", square(-10, 10, 10, 30), 20.0))
    d = 10.0 / math.cos(az_rad)
    thr = math.atan((20.0 - 1.5) / d)
    r = g.sky(np.array([0.0, 0.0, 1.5]), np.full(2, az_rad), np.array([thr + 1e-9, thr - 1e-9]))
    assert r.blocked.tolist() == [False, True]
    assert r.blocker_id.tolist() == ["", "B"]
    assert np.isnan(r.echo_excess_m[0])


def test_sky_ray_away_from_building_and_beyond_max_dist():
    g = geometry(building("B", square(-10, 10, 10, 30), 20.0))
    r = g.sky(np.array([0.0, 0.0, 1.5]), np.array([math.pi, 0.0]), np.array([0.01, 0.01]), max_dist_m=5.0)
    # Away from the building; and toward it but the near face (10 m) is beyond 5 m.
    assert not r.blocked.any()


def test_sky_antenna_inside_footprint_below_roof_is_blocked():
    """A ray leaving through the roof never crosses a wall below the roof top."""
    g = geometry(building("B", square(-10, 10, -10, 10), 20.0))
    r = g.sky(np.array([0.0, 0.0, 1.5]), np.array([0.0]), np.array([1.5]))
    assert r.blocked.tolist() == [True]


def urban_canyon() -> OcclusionGeometry:
    """South block 20 m tall with its north face at y = -10; north block 40 m, south face y = 15."""
    return geometry(
        building("S", square(-50, 50, -30, -10), 20.0),
        building("N", square(-50, 50, 15, 35), 40.0),
    )


@pytest.mark.parametrize("daz_rad", [0.0, 0.4, -0.25])
def test_sky_echo_excess_image_method(daz_rad):
    """Satellite behind the south block, echo off the north block's south face.

    Wall normal azimuth az_n = pi (facing south), d_w = 15 m, el = 45 deg:
    excess = 2 d_w cos(el) cos(az - az_n) (image method). Hand check of validity for
    daz = 0.4: s.n = cos45 cos0.4 = 0.6513, tau = 15/0.6513 = 23.03 m, reflection point
    at x = -6.3 m on the wall, z = 1.5 + 23.03 sin45 = 17.8 m < 40 m; the incident leg
    from there climbs to 44.9 m above the south block's face (> 20 m): clear.
    """
    g = urban_canyon()
    el = math.radians(45.0)
    az = math.pi + daz_rad
    r = g.sky(np.array([0.0, 0.0, 1.5]), np.array([az]), np.array([el]))
    assert r.blocked.tolist() == [True]
    assert r.blocker_id.tolist() == ["S"]
    expected = 2.0 * 15.0 * math.cos(el) * math.cos(az - math.pi)
    assert r.echo_excess_m[0] == pytest.approx(expected, abs=ATOL_M)
    # its gradient in the antenna's XY: d_w = 15 - y, so d(excess)/dy = -2 cos(el) cos(az - az_n)
    # and nothing along the wall (x); a central difference of 1 cm agrees (the excess is linear)
    np.testing.assert_allclose(r.echo_gradient_xy[0], [0.0, -2.0 * math.cos(el) * math.cos(daz_rad)], atol=1e-12)
    fd = [(g.sky(np.array([0.0, 0.0, 1.5]) + d, np.array([az]), np.array([el])).echo_excess_m[0]
           - g.sky(np.array([0.0, 0.0, 1.5]) - d, np.array([az]), np.array([el])).echo_excess_m[0]) / 0.02
          for d in (np.array([0.01, 0, 0]), np.array([0, 0.01, 0]))]
    np.testing.assert_allclose(fd, r.echo_gradient_xy[0], atol=1e-9)


def test_sky_echo_absent_when_reflection_point_above_wall_top():
    """Same canyon, north block only 10 m: the reflection point would be at 16.5 m."""
    g = geometry(building("S", square(-50, 50, -30, -10), 20.0), building("N", square(-50, 50, 15, 35), 10.0))
    r = g.sky(np.array([0.0, 0.0, 1.5]), np.array([math.pi]), np.array([math.radians(45.0)]))
    assert r.blocked.tolist() == [True]
    assert np.isnan(r.echo_excess_m[0])


def test_sky_echo_absent_when_incident_leg_blocked():
    """South block 60 m tall: the wave cannot reach the reflection point (16.5 m high).

    From R = (0, 15, 16.5) toward the satellite at 45 deg, the south block's face at
    y = -10 is 25 m away horizontally: height 41.5 m < 60 m.
    """
    g = geometry(building("S", square(-50, 50, -30, -10), 60.0), building("N", square(-50, 50, 15, 35), 40.0))
    r = g.sky(np.array([0.0, 0.0, 1.5]), np.array([math.pi]), np.array([math.radians(45.0)]))
    assert r.blocked.tolist() == [True]
    assert np.isnan(r.echo_excess_m[0])


# ------------------------------------------------------------------ foliage
def canopy_geometry() -> OcclusionGeometry:
    f = FoliageArea(id="F", footprint_xy_m=square(-5, 5, 20, 30), height_m=12.0, attenuation_db_per_m=0.5)
    return geometry(foliage=(f,))


def test_foliage_chord_through_square_canopy():
    """Canopy x in [-5, 5], y in [20, 30], top 12 m; antenna (0, 0, 1.5).

    * az 0, el 5 deg: enters at y = 20 (z = 3.25 m), leaves at y = 30 (z = 4.12 m), under
      the top: horizontal chord 10 m, slant 10 / cos(el).
    * az 0.1 rad: crosses y = 20 at x = 2.01 and y = 30 at x = 3.01 (both within +-5):
      horizontal chord 10 / cos(0.1).
    * az 0, el 25 deg: rises above 12 m at d = 10.5 / tan(25 deg) = 22.52 m: horizontal
      path 22.52 - 20 m.
    * az pi: away from the canopy: 0.
    """
    g = canopy_geometry()
    e5, e25 = math.radians(5.0), math.radians(25.0)
    r = g.sky(np.array([0.0, 0.0, 1.5]), np.array([0.0, 0.1, 0.0, math.pi]), np.array([e5, e5, e25, e5]))
    expected = np.array(
        [
            10.0 / math.cos(e5),
            10.0 / math.cos(0.1) / math.cos(e5),
            (10.5 / math.tan(e25) - 20.0) / math.cos(e25),
            0.0,
        ]
    )
    np.testing.assert_allclose(r.foliage_path_m, expected, rtol=0, atol=ATOL_M)
    np.testing.assert_allclose(r.foliage_loss_db, 0.5 * expected, rtol=0, atol=ATOL_M)
    assert not r.blocked.any()


def test_foliage_antenna_inside_canopy_and_ray_through_corner():
    """Inside at (0, 25): 5 m horizontally to the back face. A ray from (-10, 15) at
    az 45 deg passes exactly through the corners (-5, 20) and (5, 30): chord 10 sqrt(2)
    (a vertex on the ray must count once, not twice)."""
    g = canopy_geometry()
    e5 = math.radians(5.0)
    r = g.sky(np.array([0.0, 25.0, 1.5]), np.array([0.0]), np.array([e5]))
    assert r.foliage_path_m[0] == pytest.approx(5.0 / math.cos(e5), abs=ATOL_M)
    r = g.sky(np.array([-10.0, 15.0, 1.5]), np.array([math.pi / 4]), np.array([e5]))
    assert r.foliage_path_m[0] == pytest.approx(10.0 * math.sqrt(2.0) / math.cos(e5), abs=ATOL_M)


# ------------------------------------------------------------------ links
def test_link_over_low_building_passes_and_through_tall_building_blocked():
    low = geometry(building("low", square(-10, 10, 10, 30), 5.0))
    tall = geometry(building("tall", square(-10, 10, 10, 30), 20.0))
    p0 = np.array([[-30.0, 20.0, 6.0], [-30.0, 20.0, 1.5]])
    p1 = np.array([[30.0, 20.0, 6.0], [30.0, 20.0, 2.5]])
    r = low.links(p0, p1)
    # Second link is at 1.5-2.5 m: below the 5 m roof, so it is blocked too.
    assert r.blocked.tolist() == [False, True]
    assert r.blocker_kind.tolist() == ["", "building"]
    r = tall.links(p0, p1)
    assert r.blocked.tolist() == [True, True]
    assert r.blocker_id.tolist() == ["tall", "tall"]
    # Entry through the face x = -10, i.e. a third of the way: t = 20 / 60.
    expected = np.array([20.0, math.hypot(60.0, 1.0) / 3.0])
    np.testing.assert_allclose(r.hit_distance_m, expected, rtol=0, atol=ATOL_M)


def test_link_entering_through_roof():
    """From above the roof (0, 29, 25) down to (0, -20, 1.5): crosses z = 20 at
    t = 5 / 23.5, at y = 29 - 49 t = 18.6 (inside the footprint), so the first entry is
    through the roof, 3-D distance t |p1 - p0| (not at the wall y = 10, t = 19 / 49)."""
    g = geometry(building("B", square(-10, 10, 10, 30), 20.0))
    r = g.links(np.array([[0.0, 29.0, 25.0]]), np.array([[0.0, -20.0, 1.5]]))
    assert r.blocked.tolist() == [True]
    assert r.hit_distance_m[0] == pytest.approx(5.0 / 23.5 * math.hypot(49.0, 23.5), abs=ATOL_M)


def truck_scene(h_ant_m: float):
    """Cars (4.5 x 1.8 x 1.5 m) at y = -50 and y = -20 on the line x = 0, a 12 x 2.5 x 3.5 m
    truck centred at y = -35 heading north (azimuth 0); antennas on the car centres."""
    boxes = np.array(
        [
            [0.0, -35.0, 0.0, 12.0, 2.5, 3.5],
            [0.0, -50.0, 0.0, 4.5, 1.8, 1.5],
            [0.0, -20.0, 0.0, 4.5, 1.8, 1.5],
        ]
    )
    p0 = np.array([[0.0, -50.0, h_ant_m]])
    p1 = np.array([[0.0, -20.0, h_ant_m]])
    return p0, p1, boxes, np.array([[1, 2]])


def test_truck_blocks_low_antennas_not_high_ones():
    g = geometry()
    p0, p1, boxes, ex = truck_scene(1.5)
    r = g.links(p0, p1, boxes, ex)
    assert r.blocked.tolist() == [True]
    assert r.blocker_kind.tolist() == ["vehicle"]
    assert r.blocker_id.tolist() == ["0"]
    # Truck rear face at y = -35 - 6 = -41: 9 m from p0.
    assert r.hit_distance_m[0] == pytest.approx(9.0, abs=ATOL_M)
    p0, p1, boxes, ex = truck_scene(4.0)
    assert g.links(p0, p1, boxes, ex).blocked.tolist() == [False]


def test_truck_rotated_and_own_vehicle_exclusion():
    g = geometry()
    p0, p1, boxes, ex = truck_scene(1.5)
    # Truck turned 90 deg (across the road): the link crosses it over its 2.5 m width,
    # entering at y = -35 - 1.25: 13.75 m from p0.
    boxes_rot = boxes.copy()
    boxes_rot[0, 2] = math.pi / 2
    assert g.links(p0, p1, boxes_rot, ex).hit_distance_m[0] == pytest.approx(13.75, abs=ATOL_M)
    # Truck moved 2 m sideways (width 2.5 m: its side at x = 0.75 > 0): clear.
    boxes_side = boxes.copy()
    boxes_side[0, 0] = 2.0
    assert not g.links(p0, p1, boxes_side, ex).blocked[0]
    # Antennas at 1.0 m are inside their own 1.5 m tall car boxes: without the
    # exclusion the link is blocked by car 1 at distance 0; with it, clear.
    p0[:, 2] = p1[:, 2] = 1.0
    r = g.links(p0, p1, boxes_side, None)
    assert r.blocker_id.tolist() == ["1"] and r.hit_distance_m[0] == 0.0
    assert not g.links(p0, p1, boxes_side, ex).blocked[0]


def test_reflection_excess_parallel_wall():
    """Link of length L = 30 m along x = 0 blocked by the truck; wall parallel at x = w.

    Image method: excess = 2 sqrt((L/2)^2 + w^2) - L. With w = 8: 2 * 17 - 30 = 4 m; a
    wall at x = -20 alone gives 2 * 25 - 30 = 20 m. Heights 1.5 / 2.5 m: the image path is
    sqrt((2 sqrt((L/2)^2 + w^2))^2 + dz^2) and the direct sqrt(L^2 + dz^2).
    """
    near = building("near", square(8, 18, -100, 0), 15.0)
    far = building("far", square(-30, -20, -100, 0), 15.0)
    p0, p1, boxes, ex = truck_scene(1.5)
    r = geometry(near, far).links(p0, p1, boxes, ex)
    assert r.blocked[0]
    assert r.reflection_excess_m[0] == pytest.approx(2 * math.sqrt(15.0**2 + 8.0**2) - 30.0, abs=ATOL_M)
    r = geometry(far).links(p0, p1, boxes, ex)
    assert r.reflection_excess_m[0] == pytest.approx(2 * math.sqrt(15.0**2 + 20.0**2) - 30.0, abs=ATOL_M)
    # A footprint given clockwise reflects the same (walls face outward either way).
    near_cw = building("near", square(8, 18, -100, 0)[::-1], 15.0)
    r = geometry(near_cw).links(p0, p1, boxes, ex)
    assert r.reflection_excess_m[0] == pytest.approx(4.0, abs=ATOL_M)
    p1 = p1.copy()
    p1[:, 2] = 2.5
    r = geometry(near).links(p0, p1, boxes, ex)
    img = 2 * math.sqrt(15.0**2 + 8.0**2)
    assert r.reflection_excess_m[0] == pytest.approx(math.hypot(img, 1.0) - math.hypot(30.0, 1.0), abs=ATOL_M)


def test_reflection_with_blocked_leg_falls_back_to_next_wall():
    """A 2 x 2 m pillar at x in [3, 5], y in [-44, -42] cuts the first leg of the near-wall
    reflection ((0, -50) -> (8, -35) passes x = 3.73 at y = -43) but not the direct path
    (x = 0) nor the far-wall path: the answer becomes the far wall's 20 m."""
    near = building("near", square(8, 18, -100, 0), 15.0)
    far = building("far", square(-30, -20, -100, 0), 15.0)
    pillar = building("pillar", square(3, 5, -44, -42), 15.0)
    p0, p1, boxes, ex = truck_scene(1.5)
    r = geometry(near, far, pillar).links(p0, p1, boxes, ex)
    assert r.blocker_kind.tolist() == ["vehicle"]
    assert r.reflection_excess_m[0] == pytest.approx(20.0, abs=ATOL_M)


def test_unblocked_links_have_no_reflection_and_no_hit():
    g = geometry(building("B", square(8, 18, -100, 0), 15.0))
    p0, p1, boxes, ex = truck_scene(4.0)
    r = g.links(p0, p1, boxes, ex)
    assert not r.blocked[0]
    assert np.isnan(r.hit_distance_m[0]) and np.isnan(r.reflection_excess_m[0])


# ------------------------------------------------------------------ polygon files
def test_load_fixture_heights_and_classes():
    w = load_polygons(DATA / "occlusion_city.poly.xml")
    b = {x.id: x for x in w.buildings}
    assert set(b) == {"b_height", "b_levels", "b_default", "b_attr", "b_feet"}
    assert (b["b_height"].height_m, b["b_height"].height_source) == (25.0, "height")
    assert (b["b_levels"].height_m, b["b_levels"].height_source) == (12.0, "levels")
    assert (b["b_default"].height_m, b["b_default"].height_source) == (10.0, "default")
    assert (b["b_attr"].height_m, b["b_attr"].height_source) == (7.5, "height")
    assert (b["b_feet"].height_m, b["b_feet"].height_source) == (6.0, "levels")
    # Clockwise closed ring -> 4 vertices, counter-clockwise (shoelace area +200 m^2).
    fp = b["b_height"].footprint_xy_m
    assert fp.shape == (4, 2)
    assert 0.5 * np.sum(fp[:, 0] * np.roll(fp[:, 1], -1) - np.roll(fp[:, 0], -1) * fp[:, 1]) == 200.0
    f = {x.id: x for x in w.foliage}
    assert set(f) == {"wood", "row", "tree1"}
    assert (f["wood"].height_m, f["wood"].height_source) == (15.0, "height")
    assert (f["row"].height_m, f["row"].attenuation_db_per_m) == (12.0, 0.5)
    # Tree row buffered by the 3 m crown radius: its band spans x in [-53, -47].
    assert f["row"].footprint_xy_m[:, 0].min() == pytest.approx(-53.0)
    assert f["row"].footprint_xy_m[:, 0].max() == pytest.approx(-47.0)
    assert w.skipped == ("b_degenerate",)


def test_classify():
    assert classify("building") == classify("building.yes") == classify("building.commercial") == "building"
    assert classify("natural.wood") == classify("foliage.hedge") == classify("leisure.park") == "foliage"
    assert classify("amenity.parking") is None and classify("landuse.grass") is None


@pytest.mark.parametrize(
    ("body", "what"),
    [
        ("<additional><poly id='a' type='building' shape='0,0 1,x 1,1'/></additional>", "not numeric"),
        ("<additional><poly id='a' type='building'/></additional>", "no shape"),
        ("<additional><poly type='building' shape='0,0 1,0 1,1'/></additional>", "no id"),
        ("<net><poly id='a' type='building' shape='0,0 1,0 1,1'/></net>", "root element"),
        ("<additional><poly id='a'", "not well-formed"),
        (
            "<additional><poly id='a' type='building' shape='0,0 1,0 1,1'/>"
            "<poly id='a' type='building' shape='0,0 1,0 1,1'/></additional>",
            "appears twice",
        ),
    ],
)
def test_malformed_file_raises_user_error_naming_file(tmp_path, body, what):
    p = tmp_path / "bad.poly.xml"
    p.write_text(body)
    with pytest.raises(UserError) as exc:
        load_polygons([p])
    assert str(p) in str(exc.value) and what in str(exc.value)
    assert exc.value.field == "network.polygon_files"  # the scenario field; the message names the file


def test_missing_file_raises_user_error(tmp_path):
    with pytest.raises(UserError, match="not found"):
        load_polygons(tmp_path / "nope.poly.xml")


def test_real_polyconvert_output(tmp_path):
    """A tiny OSM file through SUMO's own polyconvert (--all-attributes): the height tag
    and building:levels arrive as polyconvert writes them. (polyconvert ships with the pinned
    eclipse-sumo: found as the simulator finds it, and its absence is a failure, not a skip.)"""
    from v2v.nets import _tool

    exe = _tool("polyconvert")
    osm = tmp_path / "t.osm"
    osm.write_text(
        """<?xml version="1.0" encoding="UTF-8"?><osm version="0.6">
 <node id="1" lat="52.5000" lon="13.4000"/><node id="2" lat="52.5000" lon="13.4003"/>
 <node id="3" lat="52.5002" lon="13.4003"/><node id="4" lat="52.5002" lon="13.4000"/>
 <way id="10"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="4"/><nd ref="1"/>
  <tag k="building" v="yes"/><tag k="height" v="25 m"/></way>
 <way id="11"><nd ref="1"/><nd ref="2"/><nd ref="3"/><nd ref="1"/>
  <tag k="building" v="yes"/><tag k="building:levels" v="5"/></way>
</osm>"""
    )
    out = tmp_path / "t.poly.xml"
    subprocess.run(
        [
            exe,
            "--osm-files",
            str(osm),
            "--proj.utm",
            "--all-attributes",
            "--osm.keep-full-type",
            "-o",
            str(out),
        ],
        check=True,
        capture_output=True,
        timeout=60,
    )
    b = {x.id: x for x in load_polygons(out).buildings}
    assert (b["10"].height_m, b["10"].height_source) == (25.0, "height")
    assert (b["11"].height_m, b["11"].height_source) == (15.0, "levels")


def test_links_agree_with_brute_force_sampling():
    """Seeded random scene (seed 7) against an independent point-sampling check.

    40 axis-aligned buildings (heights 3-30 m) and 30 rotated vehicle boxes in a
    200 m square; 200 random links with ends at 0.5-20 m height. Brute force: sample
    20001 points along each link (step <= 1.5e-5 of its length, < 5 mm) and test each
    against every footprint/box below its top. The two must agree on blocked/unblocked
    except where the blocked stretch is shorter than ~2 samples, and the first-entry
    distance must agree within one sample step. The chance that a random link's inside
    stretch is that short is about step / (typical stretch ~5 m), ~1e-3 per crossing: with
    a fixed seed the outcome is deterministic; over seeds a false failure has roughly
    that probability per link, which is why ambiguous links are excluded, not counted.
    """
    rng = np.random.default_rng(7)
    lo = rng.uniform(-100, 90, (40, 2))
    hi = lo + rng.uniform(3, 20, (40, 2))
    h = rng.uniform(3, 30, 40)
    blds = [building(f"b{i}", square(lo[i, 0], hi[i, 0], lo[i, 1], hi[i, 1]), h[i]) for i in range(40)]
    boxes = np.column_stack(
        [rng.uniform(-100, 100, (30, 2)), rng.uniform(0, 2 * np.pi, 30), rng.uniform(4, 12, 30)]
        + [rng.uniform(1.7, 2.5, 30), rng.uniform(1.4, 4.0, 30)]
    )
    m = 200
    p0 = np.column_stack([rng.uniform(-100, 100, (m, 2)), rng.uniform(0.5, 20, m)])
    p1 = np.column_stack([rng.uniform(-100, 100, (m, 2)), rng.uniform(0.5, 20, m)])
    r = geometry(*blds).links(p0, p1, boxes, None)
    # The compiled building test (default) and the numpy/spatial-index one give identical results.
    g_np = geometry(*blds)
    g_np.compiled_pairs_max = 0
    r_np = g_np.links(p0, p1, boxes, None)
    for f in ("blocked", "blocker_kind", "blocker_id", "hit_distance_m", "reflection_excess_m"):
        np.testing.assert_array_equal(getattr(r, f), getattr(r_np, f))

    t = np.linspace(0.0, 1.0, 20001)
    n_inside = np.zeros(m, dtype=int)
    first = np.full(m, np.inf)
    for k in range(m):
        q = p0[k] + t[:, None] * (p1[k] - p0[k])
        inb = (
            (q[:, None, 0] > lo[None, :, 0])
            & (q[:, None, 0] < hi[None, :, 0])
            & (q[:, None, 1] > lo[None, :, 1])
            & (q[:, None, 1] < hi[None, :, 1])
            & (q[:, None, 2] < h[None, :])
        ).any(axis=1)
        rel = q[:, None, :2] - boxes[None, :, :2]
        a = boxes[:, 2]
        along = rel[..., 0] * np.sin(a) + rel[..., 1] * np.cos(a)
        across = -rel[..., 0] * np.cos(a) + rel[..., 1] * np.sin(a)
        inv = (
            (np.abs(along) < boxes[:, 3] / 2)
            & (np.abs(across) < boxes[:, 4] / 2)
            & (q[:, None, 2] < boxes[:, 5])
        ).any(axis=1)
        inside = inb | inv
        n_inside[k] = inside.sum()
        if inside.any():
            first[k] = t[np.argmax(inside)] * np.linalg.norm(p1[k] - p0[k])
    clear_cut = (n_inside == 0) | (n_inside > 2)
    assert clear_cut.sum() >= m - 2
    np.testing.assert_array_equal(r.blocked[clear_cut], n_inside[clear_cut] > 0)
    both = clear_cut & r.blocked
    step = np.linalg.norm(p1 - p0, axis=1) / 20000
    assert np.all(np.abs(r.hit_distance_m[both] - first[both]) <= step[both] + ATOL_M)
    assert 30 < both.sum() < m - 30  # the scene exercises both outcomes


def _rotated_rect(c: np.ndarray, half: np.ndarray, ang: float) -> np.ndarray:
    """Counter-clockwise corners of a rectangle of half-sizes ``half`` rotated by ``ang``."""
    u = np.array([math.cos(ang), math.sin(ang)])
    v = np.array([-math.sin(ang), math.cos(ang)])
    signs = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], dtype=float)
    return c + (signs[:, :1] * half[0]) * u + (signs[:, 1:] * half[1]) * v


def test_sky_agrees_with_brute_force_reference_and_both_screening_paths():
    """Seeded random city (seed 11) against an independent per-ray reference.

    30 rotated rectangular buildings (4-30 m footprints, 5-60 m tall) in a 240 m square; 12
    antennas at 1.5 m with 8 random satellite rays each (elevation 8-75 deg), max_dist 200 m.
    Reference, one ray and one wall at a time in plain Python:

    * blocked: 10001 samples along the ray (step <= 2 cm horizontally) tested against every
      footprint below its roof; rays whose inside stretch is <= 2 samples are ambiguous and
      left out (probability ~ step / typical stretch ~ 1e-3 per crossing);
    * echo: every wall, image method (module docstring), both legs sampled the same way
      (without the 1 cm next to the reflection point), smallest valid excess.

    The optimized paths (compiled brute-force kernels, the default for worlds of this size;
    the numpy formulations forced with ``compiled_pairs_max = 0``, with dense screening over all
    walls or, forced with ``dense_pairs_max = 0``, the spatial index) must give bit-identical
    results, and all must match the reference: blocked exactly, echo found/not found exactly
    and its excess to ATOL_M, except where a leg's blocked stretch is ambiguous under sampling.
    """
    rng = np.random.default_rng(11)
    nb = 40
    cen = rng.uniform(-100, 100, (nb, 2))
    half = rng.uniform(2, 15, (nb, 2))
    ang = rng.uniform(0, np.pi, nb)
    h = rng.uniform(5, 60, nb)
    fps = [_rotated_rect(cen[i], half[i], ang[i]) for i in range(nb)]
    g = geometry(*[building(f"b{i}", fps[i], h[i]) for i in range(nb)])
    g_index = geometry(*[building(f"b{i}", fps[i], h[i]) for i in range(nb)])
    g_index.dense_pairs_max = 0
    g_index.compiled_pairs_max = 0
    g_dense = geometry(*[building(f"b{i}", fps[i], h[i]) for i in range(nb)])
    g_dense.compiled_pairs_max = 0
    na, k, max_d = 20, 10, 200.0
    ants = np.column_stack([rng.uniform(-100, 100, (na, 2)), np.full(na, 1.5)])
    ai = np.repeat(np.arange(na), k)
    az = rng.uniform(0, 2 * np.pi, na * k)
    el = np.radians(rng.uniform(8, 75, na * k))
    r = g.sky_many(ants, ai, az, el, max_d)
    r_idx = g_index.sky_many(ants, ai, az, el, max_d)
    r_dense = g_dense.sky_many(ants, ai, az, el, max_d)
    assert r.blocked.any() and np.isfinite(r.echo_excess_m).any()
    for f in ("blocked", "blocker_id", "echo_excess_m", "echo_gradient_xy", "echo_wall"):
        np.testing.assert_array_equal(getattr(r, f), getattr(r_idx, f))
        np.testing.assert_array_equal(getattr(r, f), getattr(r_dense, f))
    # The gradient is that of the excess: a central difference over +-1 mm of antenna motion
    # (the same wall stays the shortest echo for all but rays near a tie; those are skipped)
    echo = np.flatnonzero(np.isfinite(r.echo_excess_m))
    for d in (np.array([1e-3, 0.0, 0.0]), np.array([0.0, 1e-3, 0.0])):
        up, dn = (g.sky_many(ants + sgn * d, ai, az, el, max_d).echo_excess_m for sgn in (1.0, -1.0))
        fd = (up - dn)[echo] / 2e-3
        same = np.isfinite(fd) & (np.abs(up - dn)[echo] < 0.01)  # no switch to another wall
        assert same.mean() > 0.9
        # float rounding of ~100 m excess values over 2 mm: 1e-12 m / 2e-3 m ~ 1e-9
        np.testing.assert_allclose(fd[same], (r.echo_gradient_xy[echo] @ d[:2] / 1e-3)[same], atol=1e-6)

    # Per building, the local frame of its rectangle (inside test for samples).
    u = np.column_stack([np.cos(ang), np.sin(ang)])
    v = np.column_stack([-np.sin(ang), np.cos(ang)])

    def inside_count(pts: np.ndarray) -> np.ndarray:
        rel = pts[:, None, :2] - cen[None]
        a = np.abs(np.einsum("nbk,bk->nb", rel, u)) < half[None, :, 0]
        b = np.abs(np.einsum("nbk,bk->nb", rel, v)) < half[None, :, 1]
        return (a & b & (pts[:, None, 2] < h[None])).any(axis=1)

    def sampled(p0: np.ndarray, p1: np.ndarray, n: int = 10001) -> int:
        t = np.linspace(0.0, 1.0, n)[:, None]
        return int(inside_count(p0 + t * (p1 - p0)).sum())

    walls = [(fp[j], fp[(j + 1) % 4], h[i]) for i, fp in enumerate(fps) for j in range(4)]
    n_checked = n_echo = 0
    for i in range(na * k):
        xa = ants[ai[i]]
        s_h = math.cos(el[i]) * np.array([math.sin(az[i]), math.cos(az[i])])
        far = np.r_[xa[:2] + max_d * s_h / math.cos(el[i]), xa[2] + max_d * math.tan(el[i])]
        n_in = sampled(xa, far)
        if 0 < n_in <= 2:
            continue  # ambiguous under sampling
        assert r.blocked[i] == (n_in > 0)
        if not r.blocked[i]:
            assert np.isnan(r.echo_excess_m[i])
            continue
        best, ambiguous = np.inf, False
        for a, b, hw in walls:
            e = b - a
            n_w = np.array([e[1], -e[0]]) / np.hypot(*e)
            dw = float((xa[:2] - a) @ n_w)
            c = float(s_h @ n_w)
            if dw <= 0.0 or c <= 0.0:
                continue
            tau = dw / c
            rp = xa[:2] + tau * (s_h - 2.0 * c * n_w)
            zr = xa[2] + tau * math.sin(el[i])
            sw = float((rp - a) @ e) / float(e @ e)
            if not (0.0 <= sw <= 1.0 and zr < hw and tau * math.cos(el[i]) <= max_d):
                continue
            r3 = np.r_[rp, zr]
            leg1_dir = (r3 - xa) / np.linalg.norm(r3 - xa)
            leg2_end = np.r_[rp + max_d * s_h / math.cos(el[i]), zr + max_d * math.tan(el[i])]
            leg2_dir = (leg2_end - r3) / np.linalg.norm(leg2_end - r3)
            n1 = sampled(xa, r3 - 0.01 * leg1_dir)
            n2 = sampled(r3 + 0.01 * leg2_dir, leg2_end)
            if 0 < n1 <= 2 or 0 < n2 <= 2:
                ambiguous = True
            if n1 == 0 and n2 == 0:
                best = min(best, 2.0 * dw * c)
        if ambiguous:
            continue
        n_checked += 1
        if np.isfinite(best):
            n_echo += 1
            assert r.echo_excess_m[i] == pytest.approx(best, abs=ATOL_M)
        else:
            assert np.isnan(r.echo_excess_m[i])
    assert n_checked >= 50 and n_echo >= 5  # the scene exercises blocked rays with and without echoes


def test_any_hit_mode_agrees_with_first_hit_on_blocked_or_clear():
    """``_building_hits(any_hit=True)`` (used for echo legs, which only ask "clear?") stops at the
    first blocking crossing it finds: the blocked/clear decision must equal the full search's,
    segment by segment, for ascending, level and descending segments (descending ones keep the
    full search: a roof may matter). Also checks that the x-sorted building range visits every
    building that can overlap (same first crossing and blocker as the numpy/index path)."""
    rng = np.random.default_rng(23)
    nb = 60
    blds = _random_buildings(rng, nb, 150.0, (2.0, 25.0), (5.0, 60.0))
    g = geometry(*blds)
    g_np = geometry(*blds)
    g_np.compiled_pairs_max = 0
    m = 3000
    p0 = np.column_stack([rng.uniform(-160, 160, (m, 2)), rng.uniform(0.5, 70, m)])
    p1 = np.column_stack([rng.uniform(-160, 160, (m, 2)), rng.uniform(0.5, 70, m)])
    t_full, b_full = g._building_hits(p0, p1)
    t_np, b_np = g_np._building_hits(p0, p1)
    np.testing.assert_array_equal(t_full, t_np)
    np.testing.assert_array_equal(b_full, b_np)
    for kw in ({}, {"skip_start_m": 0.01, "check_start_inside": False}, {"skip_end_m": 0.01, "check_end_inside": False}):
        t_any, _ = g._building_hits(p0, p1, any_hit=True, **kw)
        t_ref, _ = g._building_hits(p0, p1, **kw)
        np.testing.assert_array_equal(np.isfinite(t_any), np.isfinite(t_ref))
    print(f"{np.isfinite(t_full).mean():.2f} of {m} segments blocked")


# ------------------------------------------------------------------ compiled/batched vs reference paths
def _random_links_and_boxes(rng: np.random.Generator, trial: int, m: int, v: int):
    """Links (ends 0-3 m high) and vehicle boxes in a 60 m square, with degenerate cases by trial:
    level links, links of constant x, zero-length links, vertical links, links starting at a box
    centre (inside it below its roof), headings exactly on the axes, and links running exactly
    along the faces of axis-aligned boxes (touching, which does not count as passing through)."""
    p0 = np.column_stack([rng.uniform(-30, 30, (m, 2)), rng.uniform(0, 3, m)])
    p1 = np.column_stack([rng.uniform(-30, 30, (m, 2)), rng.uniform(0, 3, m)])
    bx = np.column_stack([rng.uniform(-30, 30, (v, 2)), rng.uniform(0, 2 * np.pi, v), rng.uniform(3, 12, v),
                          rng.uniform(1.5, 2.5, v), rng.uniform(1, 4, v)])
    if trial % 3 == 0:
        p1[:, 2] = p0[:, 2]
    if trial % 5 == 0:
        p1[:, 0] = p0[:, 0]
    if trial % 11 == 0:
        p1[: m // 2] = p0[: m // 2]
    if trial % 13 == 0:
        p1[: m // 2, :2] = p0[: m // 2, :2]
    if trial % 4 == 0:
        k = min(m, v)
        p0[:k, :2] = bx[:k, :2]
    if trial % 7 == 0:
        bx[:, 2] = rng.choice([0.0, np.pi / 2, np.pi, 3 * np.pi / 2, 2 * np.pi], v)
    if trial % 17 == 0:
        # Integer centres, heading 0, width 2 m: the face x = cx + 1 is exact; links along it.
        bx[:, :2] = np.round(bx[:, :2])
        bx[:, 2], bx[:, 4] = 0.0, 2.0
        k = min(m, v)
        p0[:k, 0] = p1[:k, 0] = bx[:k, 0] + 1.0
    return p0, p1, bx


def test_compiled_box_hits_equal_numpy_reference():
    """Compiled vehicle-box test ``_box_hits`` against the kept numpy reference ``_box_hits_vectorized``.

    600 seeded random cases (1-30 links, 1-25 boxes each, with and without ``exclude``) including
    the degenerate geometries of :func:`_random_links_and_boxes`. Equality, not closeness: the
    kernel evaluates the same floating-point expressions in the same order (slab offsets
    ``rel . u``, ``t = (bound - q0) / dq``, the parallel-slab rule, numpy's sin/cos of the
    heading, the lowest-row tie break of ``argmin``), so every entry parameter and box row must be
    bit-identical; any difference means the two decide a case differently, not rounding.
    """
    rng = np.random.default_rng(5)
    n_hit = n_miss = 0
    for trial in range(600):
        m, v = int(rng.integers(1, 31)), int(rng.integers(1, 26))
        p0, p1, bx = _random_links_and_boxes(rng, trial, m, v)
        ex = rng.integers(-1, v, (m, int(rng.integers(1, 4)))) if trial % 2 else None
        t_ref, row_ref = _box_hits_vectorized(p0, p1, bx, ex)
        t, row = _box_hits(p0, p1, bx, ex)
        np.testing.assert_array_equal(t, t_ref, err_msg=f"trial {trial}")
        np.testing.assert_array_equal(row, row_ref, err_msg=f"trial {trial}")
        n_hit += int(np.isfinite(t).sum())
        n_miss += int(np.isinf(t).sum())
    assert n_hit > 1000 and n_miss > 1000  # both outcomes well exercised
    for none_or_empty in (None, np.zeros((0, 6))):
        t, row = _box_hits(p0, p1, none_or_empty, None)
        assert np.isinf(t).all() and (row == -1).all()


def test_compiled_box_hits_per_box_set_equal_reference_per_set():
    """``_box_hits`` with ``box_first``/``box_set`` (links of many steps, each against its own
    step's boxes; ``exclude`` and the returned row count from the start of that set) against
    ``_box_hits_vectorized`` called set by set. 40 sets of 0-12 boxes (empty sets included).
    Equality for the reason of :func:`test_compiled_box_hits_equal_numpy_reference`: per link the
    kernel does exactly the single-set computation on its set's rows."""
    rng = np.random.default_rng(8)
    n_sets = 40
    sizes = rng.integers(0, 13, n_sets)
    sizes[[3, 17]] = 0
    first = np.concatenate([[0], np.cumsum(sizes)])
    _, _, boxes = _random_links_and_boxes(rng, 7, 1, int(first[-1]))
    m = 800
    p0, p1, _ = _random_links_and_boxes(rng, 1, m, 1)
    p0[::9] = p1[::9]  # some zero-length links
    box_set = rng.integers(0, n_sets, m)
    ex = np.column_stack([rng.integers(-1, np.maximum(sizes[box_set], 1)) for _ in range(2)])
    t, row = _box_hits(p0, p1, boxes, ex, first, box_set)
    for g in range(n_sets):
        sel = np.flatnonzero(box_set == g)
        t_ref, row_ref = _box_hits_vectorized(p0[sel], p1[sel], boxes[first[g]:first[g + 1]], ex[sel])
        np.testing.assert_array_equal(t[sel], t_ref, err_msg=f"set {g}")
        np.testing.assert_array_equal(row[sel], row_ref, err_msg=f"set {g}")
    assert 100 < np.isfinite(t).sum() < m - 100
    assert np.isinf(t[np.isin(box_set, [3, 17])]).all()


def _random_buildings(rng: np.random.Generator, nb: int, extent_m: float, half_m: tuple[float, float],
                      height_m: tuple[float, float]) -> list[Building]:
    """``nb`` rotated rectangular buildings: centres uniform in +-extent_m, half sizes and
    heights uniform in the given ranges, headings uniform in [0, pi)."""
    cen = rng.uniform(-extent_m, extent_m, (nb, 2))
    half = rng.uniform(*half_m, (nb, 2))
    ang = rng.uniform(0, np.pi, nb)
    h = rng.uniform(*height_m, nb)
    return [building(f"b{i}", _rotated_rect(cen[i], half[i], ang[i]), h[i]) for i in range(nb)]


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "numpy"])
def test_links_many_equals_links_per_step(compiled):
    """``links_many`` over the links of 30 steps, each against its own step's vehicle boxes, must
    give exactly what ``links`` gives step by step with that step's boxes (blocked, kind, id, hit
    distance, reflection excess). Seeded scene: 15 rotated buildings, 0-10 boxes per step (steps
    without boxes call ``links`` with None, as the sensors do), ends 0.5-4 m high. Both building
    paths: the compiled kernels and the numpy/spatial-index formulation (``compiled_pairs_max =
    0``). Equality, not closeness: every result is per link (no quantity mixes links), so batching
    changes only which links are evaluated together, never the floating-point operations of a link.
    """
    rng = np.random.default_rng(31)
    g = geometry(*_random_buildings(rng, 15, 70.0, (3.0, 15.0), (4.0, 40.0)))
    if not compiled:
        g.compiled_pairs_max = 0
    n_steps = 30
    sizes = rng.integers(0, 11, n_steps)
    sizes[[0, 12]] = 0
    first = np.concatenate([[0], np.cumsum(sizes)])
    boxes = np.column_stack([rng.uniform(-60, 60, (first[-1], 2)), rng.uniform(0, 2 * np.pi, first[-1]),
                             rng.uniform(4, 12, first[-1]), rng.uniform(1.7, 2.5, first[-1]),
                             rng.uniform(1.4, 4.0, first[-1])])
    n_links = rng.integers(0, 25, n_steps)
    step = np.repeat(np.arange(n_steps), n_links)
    m = step.size
    p0 = np.column_stack([rng.uniform(-60, 60, (m, 2)), rng.uniform(0.5, 4, m)])
    p1 = np.column_stack([rng.uniform(-60, 60, (m, 2)), rng.uniform(0.5, 4, m)])
    ex = np.column_stack([rng.integers(-1, np.maximum(sizes[step], 1)) for _ in range(2)])
    r = g.links_many(p0, p1, boxes, first, step, ex)
    fields = ("blocked", "blocker_kind", "blocker_id", "hit_distance_m", "reflection_excess_m")
    for s in range(n_steps):
        sel = np.flatnonzero(step == s)
        if sel.size == 0:
            continue  # the sensors never ask about zero links
        bs = boxes[first[s]:first[s + 1]]
        ref = g.links(p0[sel], p1[sel], bs if len(bs) else None, ex[sel])
        for f in fields:
            np.testing.assert_array_equal(getattr(r, f)[sel], getattr(ref, f), err_msg=f"step {s}, {f}")
    kinds = set(r.blocker_kind.tolist())
    assert {"", "building", "vehicle"} <= kinds
    assert np.isfinite(r.reflection_excess_m).sum() > 20  # the reflection search is exercised
