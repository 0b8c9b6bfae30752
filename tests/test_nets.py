"""Shipped road networks and the net builder (v2v.nets) against their promises.

Every test here runs the real netconvert / polyconvert (marker ``sumo``). The shipped
nets are built once per module into a temporary folder, never into the repo, so
parallel test runs do not race on ``sumo_nets/*/build``.
"""

from __future__ import annotations

import gzip
import math
import os
import shutil
import tomllib
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
import sumolib
from shapely.geometry import LineString, Point, Polygon

from v2v import nets
from v2v.errors import UserError
from v2v.frames import GeoReference, geodetic_to_ecef

pytestmark = pytest.mark.sumo

TINY_OSM = Path(__file__).parent / "data" / "tiny.osm"
# SUMO's default passenger speedFactor is N(1, 0.1): 1.2 is its 2-sigma upper value.
# A route "lasts >= 120 s" if it does even for a vehicle driving 1.2x every limit.
FAST_SPEED_FACTOR = 1.2


@pytest.fixture(scope="module")
def built(tmp_path_factory) -> dict[str, nets.BuiltNet]:
    root = tmp_path_factory.mktemp("nets")
    return {b.name: b for b in nets.build_all(root)}


@pytest.fixture(scope="module")
def sumo_nets(built):
    return {n: sumolib.net.readNet(str(b.net_path), withInternal=True) for n, b in built.items()}


def read_polys(path: Path) -> list[tuple[str, str, Polygon, float]]:
    out = []
    for p in ET.parse(path).getroot().iter("poly"):
        pts = [tuple(map(float, q.split(","))) for q in p.get("shape").split()]
        params = {q.get("key"): q.get("value") for q in p.iter("param")}
        out.append((p.get("id"), p.get("type"), Polygon(pts), float(params["height"])))
    return out


def lane_lines(net, internal=False) -> list[tuple[LineString, float]]:
    return [
        (LineString(lane.getShape()), lane.getWidth())
        for e in net.getEdges(withInternal=internal)
        for lane in e.getLanes()
    ]


def site(name: str) -> tuple[float, float]:
    with (nets.NETS_DIR / name / "net.toml").open("rb") as f:
        meta = tomllib.load(f)
    return meta["site_lat_deg"], meta["site_lon_deg"]


# --------------------------------------------------------------------------- geo-reference


@pytest.mark.parametrize("name", nets.SHIPPED_NETS)
def test_net_is_georeferenced_at_its_calgary_site(name, built, sumo_nets):
    """The built net keeps the sources' tmerc <location>, no offset, and sits at its site.

    Every junction, mapped XY -> lat/lon -> ECEF, must lie within 2 km (straight line)
    of the site centre; the nets are at most ~3.6 km long and centred on the site.
    netOffset must be exactly 0,0 (we disable netconvert's normalization) and junction
    XY must equal the source node XY, so the polygon files (same XY) need no shift.
    """
    loc = nets.read_location(built[name].net_path)
    assert loc.proj is not None and "+proj=tmerc" in loc.proj
    assert loc.net_offset_m == (0.0, 0.0)
    geo = loc.georeference()
    lat0, lon0 = site(name)
    assert f"+lat_0={lat0}" in loc.proj and f"+lon_0={lon0}" in loc.proj
    net = sumo_nets[name]
    xy = np.array([n.getCoord()[:2] for n in net.getNodes()])
    lat, lon = geo.xy_to_geodetic(xy[:, 0], xy[:, 1])
    d_m = np.linalg.norm(
        geodetic_to_ecef(lat, lon, 0.0) - geodetic_to_ecef(math.radians(lat0), math.radians(lon0), 0.0),
        axis=1,
    )
    assert d_m.max() < 2000.0
    src = ET.parse(nets.NETS_DIR / name / f"{name}.nod.xml").getroot()
    for node in src.iter("node"):
        x, y = net.getNode(node.get("id")).getCoord()[:2]
        # Sources are written with 2 decimals; netconvert keeps node positions exactly.
        assert (x, y) == pytest.approx((float(node.get("x")), float(node.get("y"))), abs=0.005)


def test_read_location_gz_equals_plain(built, tmp_path):
    plain = built["hospital_loop"].net_path
    gz = tmp_path / "h.net.xml.gz"
    with plain.open("rb") as fi, gzip.open(gz, "wb") as fo:
        shutil.copyfileobj(fi, fo)
    assert nets.read_location(gz) == nets.read_location(plain)


# --------------------------------------------------------------------------- routes and lanes


@pytest.mark.parametrize("name", nets.SHIPPED_NETS)
def test_suggested_routes_connected_and_long_enough(name, built, sumo_nets):
    """Consecutive route edges are connected; each route lasts >= 120 s even at 1.2x the limits."""
    net = sumo_nets[name]
    routes = built[name].routes
    assert "default" in routes and 1 <= len(routes) <= 3
    for rname, route in routes.items():
        for a, b in zip(route, route[1:], strict=False):
            assert net.getEdge(b) in net.getEdge(a).getOutgoing(), f"{name}/{rname}: {a} -> {b} not connected"
        t_s = sum(net.getEdge(e).getLength() / (FAST_SPEED_FACTOR * net.getEdge(e).getSpeed()) for e in route)
        assert t_s >= 120.0, f"{name}/{rname}: {t_s:.0f} s"


@pytest.mark.parametrize("name", nets.SHIPPED_NETS)
def test_every_lane_continues_and_multilane_edges_allow_changes(name, built, sumo_nets):
    """Closed circuits: every lane of every normal edge has a successor lane; no lane forbids changing."""
    net = sumo_nets[name]
    dead = [ln.getID() for e in net.getEdges() for ln in e.getLanes() if not ln.getOutgoing()]
    assert dead == []
    multi = [e for e in net.getEdges() if e.getLaneNumber() > 1]
    assert multi, "each shipped net has multi-lane edges"
    root = ET.parse(built[name].net_path).getroot()
    restricted = [ln.get("id") for ln in root.iter("lane") if ln.get("changeLeft") or ln.get("changeRight")]
    assert restricted == []


# --------------------------------------------------------------------------- buildings and foliage


def test_urban_canyon_buildings(built, sumo_nets):
    """Heights 20-120 m with a >= 100 m tower; every building >= 3 m behind the kerb.

    Distance to a lane centreline >= half a lane (1.6 m) + 3 m minimum setback; internal
    (junction) lanes included, so block corners are checked too.
    """
    polys = [p for p in read_polys(built["urban_canyon"].poly_path) if p[1] == "building"]
    h = np.array([p[3] for p in polys])
    assert len(polys) >= 200
    assert h.min() >= 20.0 and h.max() >= 100.0 and h.max() <= 120.0
    lanes = lane_lines(sumo_nets["urban_canyon"], internal=True)
    gap = min(poly.distance(line) - w / 2 for _, _, poly, _ in polys for line, w in lanes)
    assert gap >= 3.0


def test_hospital_tower_faces_the_loop(built, sumo_nets):
    """A >= 40 m building within 100 m of the turnaround loop, whose arc radius is 25-40 m."""
    net = sumo_nets["hospital_loop"]
    loop = [LineString(net.getEdge(e).getLanes()[0].getShape()) for e in ("loop_in", "loop_out")]
    polys = read_polys(built["hospital_loop"].poly_path)
    near_tall = [
        p for p in polys if p[1] == "building" and p[3] >= 40.0 and min(p[2].distance(g) for g in loop) < 100
    ]
    assert near_tall
    # Radius from three points on the loop's far half (circumscribed circle).
    pts = np.array(net.getEdge("loop_out").getLanes()[0].getShape())[:, :2]
    a, b, c = pts[2], pts[len(pts) // 4], pts[len(pts) // 2]
    ab, bc, ca = np.linalg.norm(a - b), np.linalg.norm(b - c), np.linalg.norm(c - a)
    area2 = abs((b[0] - a[0]) * (c[1] - a[1]) - (c[0] - a[0]) * (b[1] - a[1]))
    radius_m = ab * bc * ca / (2.0 * area2)
    assert 25.0 <= radius_m <= 40.0
    # The approach road is ~500 m with 2 lanes inbound.
    ap = net.getEdge("ap_in")
    assert ap.getLaneNumber() == 2 and 450.0 <= ap.getLength() <= 550.0


def test_residential_trees_and_houses(built, sumo_nets):
    """Many trees (canopy 8-15 m) within 15 m of a lane; houses 6-9 m, none on the road."""
    polys = read_polys(built["residential"].poly_path)
    trees = [p for p in polys if p[1] == "foliage"]
    houses = [p for p in polys if p[1] == "building"]
    assert len(trees) >= 200 and len(houses) >= 100
    assert all(8.0 <= p[3] <= 15.0 for p in trees)
    assert all(6.0 <= p[3] <= 9.0 for p in houses)
    lanes = lane_lines(sumo_nets["residential"])
    assert max(min(p[2].distance(line) for line, _ in lanes) for p in trees) < 15.0
    assert min(p[2].distance(line) - w / 2 for p in houses for line, w in lanes) > 3.0
    # Curved streets: every street bows >= 10 m off the chord between its lane's ends (the
    # sources bow 8-18 m as a half sine; a straight street would give 0 m).
    net = sumo_nets["residential"]
    bows = []
    for e in net.getEdges(withInternal=False):
        pts = np.array(e.getLanes()[0].getShape())[:, :2]
        chord = LineString([pts[0], pts[-1]])
        bows.append(max(chord.distance(Point(p)) for p in pts))
    assert sum(b >= 10.0 for b in bows) >= len(bows) // 2 and min(bows) >= 5.0


def test_open_highway_is_open(built, sumo_nets):
    """3 lanes each way at 22-28 m/s, ~3 km; buildings low (<= 8 m) and >= 100 m from any lane."""
    net = sumo_nets["open_highway"]
    main = [net.getEdge(f"nb{k}") for k in range(1, 6)]
    assert all(e.getLaneNumber() == 3 and 22.0 <= e.getSpeed() <= 28.0 for e in main)
    assert 2800.0 <= sum(e.getLength() for e in main) <= 3800.0
    polys = read_polys(built["open_highway"].poly_path)
    lanes = lane_lines(net, internal=True)
    assert all(p[3] <= 8.0 for p in polys)
    assert min(p[2].distance(line) for p in polys for line, _ in lanes) >= 100.0


# --------------------------------------------------------------------------- OSM import


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> nets.BuiltNet:
    return nets.import_osm(TINY_OSM, "tiny", tmp_path_factory.mktemp("osm"))


def test_import_osm_heights(tiny):
    """height=25 -> 25 m (tag); building:levels=4 -> 4 x 3 m = 12 m; no tag -> 9 m; wood -> foliage."""
    root = ET.parse(tiny.poly_path).getroot()
    got = {
        p.get("id"): (p.get("type"), {q.get("key"): q.get("value") for q in p.iter("param")})
        for p in root.iter("poly")
    }
    assert got["2000"][0] == "building" and float(got["2000"][1]["height"]) == 25.0
    assert got["2000"][1]["height_source"] == "tag"
    assert float(got["2001"][1]["height"]) == 4 * nets.LEVEL_HEIGHT_M == 12.0
    assert got["2001"][1]["height_source"] == "levels"
    assert float(got["2002"][1]["height"]) == nets.DEFAULT_BUILDING_HEIGHT_M
    assert got["2003"][0] == "foliage" and got["2003"][1]["osm_type"] == "forest"


def test_import_osm_net_geo_and_route(tiny):
    """The imported net is geo-referenced: a building corner maps back to its OSM node.

    Node 101 of tiny.osm is (51.0766, -114.1300). Tolerance 0.05 m: polyconvert writes
    shapes to 1e-6 m, netconvert writes netOffset to 0.01 m (<= 0.005 m per axis), the
    projections are exact to well below that.
    """
    net = sumolib.net.readNet(str(tiny.net_path))
    edges = [e for e in net.getEdges() if e.allows("passenger")]
    assert len(edges) >= 4  # main street both ways (>= 2 pieces) and the side street
    loc = nets.read_location(tiny.net_path)
    geo = GeoReference(proj=loc.proj, net_offset_m=loc.net_offset_m)
    poly = {p[0]: p for p in read_polys(tiny.poly_path)}["2000"][2]
    x, y = poly.exterior.coords[0]
    lat, lon = geo.xy_to_geodetic(x, y)
    err_m = np.linalg.norm(
        geodetic_to_ecef(lat, lon, 0.0)
        - geodetic_to_ecef(math.radians(51.0766), math.radians(-114.1300), 0.0)
    )
    assert err_m < 0.05
    route = tiny.default_route
    for a, b in zip(route, route[1:], strict=False):
        assert net.getEdge(b) in net.getEdge(a).getOutgoing()
    # The longest shortest path is at least the ~300 m main street end to end.
    assert sum(net.getEdge(e).getLength() for e in route) >= 290.0
    assert nets.resolve_net(tiny.net_path).routes["default"] == route  # routes.toml beside the net


# --------------------------------------------------------------------------- errors and caching


def test_missing_and_unknown_inputs_raise_user_error(tmp_path):
    with pytest.raises(UserError) as e:
        nets.resolve_net({"net_file": tmp_path / "nope.net.xml"})
    assert e.value.field == "network.net_file" and "hospital_loop" in str(e.value)
    with pytest.raises(UserError) as e:
        nets.resolve_net("no_such_net")
    assert e.value.field == "network.name" and "urban_canyon" in str(e.value)
    with pytest.raises(UserError) as e:
        nets.resolve_net({"name": "residential", "poly_file": tmp_path / "nope.poly.xml"})
    assert e.value.field == "network.poly_file"
    with pytest.raises(UserError) as e:
        nets.import_osm(tmp_path / "nope.osm", "x", tmp_path)
    assert e.value.field == "OSM"
    with pytest.raises(UserError) as e:
        nets.read_location(tmp_path / "nope.net.xml")
    assert e.value.field == "network.net_file"


def test_files_that_are_not_sumo_nets_or_osm(tmp_path):
    """A net_file whose root is not <net>, or a <net> SUMO cannot read, is a UserError naming
    network.net_file (not a sumolib KeyError); a failed OSM import leaves no empty net folder."""
    fake = tmp_path / "routes.net.xml"
    fake.write_text('<?xml version="1.0"?>\n<!-- a comment -->\n<routes></routes>\n')
    with pytest.raises(UserError, match="root element is not <net>") as e:
        nets.resolve_net({"net_file": fake})
    assert e.value.field == "network.net_file"
    fake.write_text("<net>garbage</net>")
    with pytest.raises(UserError, match="SUMO cannot read") as e:
        nets.resolve_net({"net_file": fake})
    assert e.value.field == "network.net_file"
    osm = tmp_path / "garbage.osm"
    osm.write_text("this is not OSM")
    with pytest.raises(UserError) as e:
        nets.import_osm(osm, "zz", tmp_path / "out")
    assert e.value.field == "OSM" and not (tmp_path / "out").exists()  # (--out made by the import: gone)
    (tmp_path / "mine").mkdir()
    with pytest.raises(UserError):
        nets.import_osm(osm, "zz", tmp_path / "mine")
    assert (tmp_path / "mine").is_dir() and not any((tmp_path / "mine").iterdir())  # a folder that was there stays


def test_import_never_replaces_a_nets_files_and_its_outputs_are_readable(tiny, tmp_path):
    """An import into a folder that holds files (a shipped net's sources, an earlier import:
    `--name open_highway` without --out wrote over sumo_nets/open_highway/) is refused; --out
    under a file is one line; an extract without a drivable road is refused at the import, not
    at the first run; the outputs have the mode a plain open gives (0666 less the umask: they
    were 0600, unreadable to the other users of a shared checkout)."""
    with pytest.raises(UserError) as e:
        nets.import_osm(TINY_OSM, "tiny", tiny.net_path.parent.parent)  # the fixture's import again
    assert e.value.field == "--name"
    with pytest.raises(UserError) as e:
        nets.import_osm(TINY_OSM, "open_highway")  # the default place: the shipped net's folder
    assert e.value.field == "--name"
    with pytest.raises(UserError) as e:
        nets.import_osm(TINY_OSM, "x", TINY_OSM)  # --out is a file
    assert e.value.field == "--out"
    footway = tmp_path / "footway.osm"
    footway.write_text(TINY_OSM.read_text().replace('v="residential"', 'v="footway"').replace('v="secondary"', 'v="footway"'))
    assert 'v="footway"' in footway.read_text()
    with pytest.raises(UserError, match="no road a car can drive") as e:
        nets.import_osm(footway, "fw", tmp_path / "out")
    assert e.value.field == "OSM" and not (tmp_path / "out").exists()
    umask = os.umask(0o022)
    os.umask(umask)
    for p in (tiny.net_path, tiny.poly_path, tiny.net_path.parent / "routes.toml"):
        assert p.stat().st_mode & 0o777 == 0o666 & ~umask, p


def test_netconvert_failure_is_one_user_error_line(tmp_path, monkeypatch):
    d = tmp_path / "broken"
    d.mkdir()
    (d / "broken.nod.xml").write_text('<nodes><node id="a" x="0" y="0"/></nodes>')
    (d / "broken.edg.xml").write_text('<edges><edge id="e" from="a" to="ghost"/></edges>')
    monkeypatch.setattr(nets, "NETS_DIR", tmp_path)
    monkeypatch.setattr(nets, "SHIPPED_NETS", ("broken",))
    with pytest.raises(UserError) as e:
        nets.build_net("broken", tmp_path / "out")
    assert e.value.field == "network.name" and "Error" in str(e.value) and "\n" not in str(e.value)
    assert not (tmp_path / "out" / "broken.net.xml").exists()
    assert list((tmp_path / "out").glob("*.tmp*")) == []  # no half-written file left behind


def test_build_is_reused_when_sources_unchanged(tmp_path):
    first = nets.build_net("hospital_loop", tmp_path)
    mtime = first.net_path.stat().st_mtime_ns
    again = nets.build_net("hospital_loop", tmp_path)
    assert again.net_path.stat().st_mtime_ns == mtime
    info = {i.name: i for i in nets.list_nets()}
    assert set(info) == set(nets.SHIPPED_NETS) and all(i.description for i in info.values())
