"""Generate the plain-XML sources of the four shipped networks.

Run ``python sumo_nets/generate.py`` to rewrite ``sumo_nets/<name>/`` (nodes, edges,
polygons, routes.toml, net.toml). The output is deterministic (fixed seeds), so the
committed XML is exactly what this script writes; edit the script, not the XML.

Geometry is built in net XY metres (x east, y north) of a local transverse Mercator
projection centred on each site (``+proj=tmerc +lat_0=<site> +lon_0=<site> +k=1``),
so net XY (0, 0) is the site centre and the built net keeps ``netOffset = 0,0``
(``netconvert --offset.disable-normalization true``; see v2v/nets.py).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np
import pyproj
from shapely.geometry import LineString, Point, Polygon

HERE = Path(__file__).resolve().parent
LANE_WIDTH_M = 3.2  # SUMO default lane width (netconvert --default.lanewidth)

SITES = {
    # name: (lat_deg, lon_deg, where)
    "open_highway": (51.0950, -114.1580, "Shaganappi Trail NW, west of the University of Calgary"),
    "residential": (51.0700, -114.1380, "University Heights, Calgary NW"),
    "urban_canyon": (51.0465, -114.0690, "downtown Calgary core"),
    "hospital_loop": (51.0746, -114.1472, "Alberta Children's Hospital, Calgary NW"),
}


def proj_string(lat_deg: float, lon_deg: float) -> str:
    return (
        f"+proj=tmerc +lat_0={lat_deg} +lon_0={lon_deg} +k=1 +x_0=0 +y_0=0 "
        "+ellps=WGS84 +datum=WGS84 +units=m +no_defs"
    )


# --------------------------------------------------------------------------- paths


def turtle(start_xy, heading_rad, segments, step_m=4.0) -> np.ndarray:
    """Polyline from a start point and heading through ``segments``.

    Each segment is ``("S", length_m)``, ``("L", radius_m, angle_rad)`` (left turn) or
    ``("R", radius_m, angle_rad)``. Points every ~``step_m`` along arcs and straights.
    """
    x, y = float(start_xy[0]), float(start_xy[1])
    th = float(heading_rad)
    pts = [(x, y)]
    for seg in segments:
        if seg[0] == "S":
            length = seg[1]
            n = max(1, math.ceil(length / step_m))
            for k in range(1, n + 1):
                s = length * k / n
                pts.append((x + s * math.cos(th), y + s * math.sin(th)))
            x, y = pts[-1]
        else:
            kind, radius, angle = seg
            sign = 1.0 if kind == "L" else -1.0
            # Centre of curvature to the left (L) or right (R) of the heading.
            cx = x - sign * radius * math.sin(th)
            cy = y + sign * radius * math.cos(th)
            n = max(2, math.ceil(radius * angle / step_m))
            for k in range(1, n + 1):
                t = th + sign * angle * k / n
                pts.append((cx + sign * radius * math.sin(t), cy - sign * radius * math.cos(t)))
            th += sign * angle
            x, y = pts[-1]
    return np.asarray(pts)


def offset_polyline(pts: np.ndarray, d_left_m: float) -> np.ndarray:
    """Offset a densely sampled polyline by ``d_left_m`` to its left (negative: right)."""
    tang = np.gradient(pts, axis=0)
    tang /= np.linalg.norm(tang, axis=1, keepdims=True)
    normal_left = np.stack([-tang[:, 1], tang[:, 0]], axis=1)
    return pts + d_left_m * normal_left


def split_polyline(pts: np.ndarray, n_parts: int) -> list[np.ndarray]:
    """Split a polyline into ``n_parts`` pieces of equal arc length (sharing end points)."""
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    cuts = [int(np.argmin(np.abs(s - s[-1] * k / n_parts))) for k in range(n_parts + 1)]
    return [pts[cuts[k] : cuts[k + 1] + 1] for k in range(n_parts)]


def bowed(p0, p1, bow_m: float, step_m: float = 5.0) -> np.ndarray:
    """Straight segment p0->p1 bowed sideways by ``bow_m`` (left positive) as a half sine."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d = p1 - p0
    length = float(np.linalg.norm(d))
    n = max(2, math.ceil(length / step_m))
    t = np.linspace(0.0, 1.0, n + 1)
    left = np.array([-d[1], d[0]]) / length
    return p0 + t[:, None] * d + (bow_m * np.sin(np.pi * t))[:, None] * left


def rect(cx, cy, along_m, depth_m, angle_rad) -> Polygon:
    """Rectangle centred at (cx, cy), ``along_m`` along ``angle_rad`` (from +x), ``depth_m`` across."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    hx, hy = along_m / 2.0, depth_m / 2.0
    corners = [(-hx, -hy), (hx, -hy), (hx, hy), (-hx, hy)]
    return Polygon([(cx + c * u - s * v, cy + s * u + c * v) for u, v in corners])


def circle(cx, cy, r, n=12) -> Polygon:
    a = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return Polygon(np.stack([cx + r * np.cos(a), cy + r * np.sin(a)], axis=1))


# --------------------------------------------------------------------------- net model


@dataclass
class Net:
    name: str
    description: str
    nodes: dict[str, tuple[float, float, dict]] = field(default_factory=dict)
    edges: list[dict] = field(default_factory=list)
    polys: list[tuple[str, str, Polygon, float]] = field(default_factory=list)  # id, type, poly, height
    routes: dict[str, list[str]] = field(default_factory=dict)
    route_notes: dict[str, str] = field(default_factory=dict)
    # (from_edge, to_edge, from_lane, to_lane): explicit lane connections for lane drops, so
    # that no lane ends without a successor (netconvert leaves one lane of a 3->2 or 2->1
    # drop unconnected). Given for every lane of each listed edge pair.
    connections: list[tuple[str, str, int, int]] = field(default_factory=list)

    def node(self, nid, x, y, **attrs):
        self.nodes[nid] = (float(x), float(y), attrs)

    def edge(self, eid, frm, to, *, lanes, speed, priority=1, shape=None, name="", spread=None):
        self.edges.append(
            dict(
                id=eid,
                frm=frm,
                to=to,
                lanes=lanes,
                speed=speed,
                priority=priority,
                shape=shape,
                name=name,
                spread=spread,
            )
        )

    def two_way(self, a, b, *, lanes, speed, priority=1, shape=None, name=""):
        """Edge pair ``a-b`` and ``b-a`` sharing one centreline (lanes spread to the right)."""
        self.edge(f"{a}-{b}", a, b, lanes=lanes, speed=speed, priority=priority, shape=shape, name=name)
        rshape = None if shape is None else shape[::-1]
        self.edge(f"{b}-{a}", b, a, lanes=lanes, speed=speed, priority=priority, shape=rshape, name=name)

    def road_lines(self) -> list[tuple[LineString, float]]:
        """Each edge's centreline with the half-width of the paved area it belongs to."""
        out = []
        for e in self.edges:
            if e["shape"] is not None:
                pts = e["shape"]
            else:
                a, b = self.nodes[e["frm"]], self.nodes[e["to"]]
                pts = [(a[0], a[1]), (b[0], b[1])]
            # Two-way edges share the centreline: lanes of both directions lie within.
            half = e["lanes"] * LANE_WIDTH_M if e["spread"] is None else e["lanes"] * LANE_WIDTH_M / 2
            out.append((LineString(pts), half))
        return out

    def add_poly(self, kind, poly: Polygon, height_m: float):
        self.polys.append((f"{kind[:4]}{len(self.polys):04d}", kind, poly, float(height_m)))

    def clear_of_roads(self, poly: Polygon, margin_m: float) -> bool:
        return all(poly.distance(line) >= half + margin_m for line, half in self.road_lines())

    # ---------------------------------------------------------------- writing
    def write(self, site):
        lat, lon, where = site
        d = HERE / self.name
        d.mkdir(parents=True, exist_ok=True)
        proj = proj_string(lat, lon)
        xs = [v[0] for v in self.nodes.values()]
        ys = [v[1] for v in self.nodes.values()]
        for _, _, p, _ in self.polys:
            minx, miny, maxx, maxy = p.bounds
            xs += [minx, maxx]
            ys += [miny, maxy]
        tr = pyproj.Transformer.from_crs(pyproj.CRS.from_proj4(proj), "EPSG:4326", always_xy=True)
        lons, lats = tr.transform([min(xs), max(xs)], [min(ys), max(ys)])
        conv = f"{min(xs):.2f},{min(ys):.2f},{max(xs):.2f},{max(ys):.2f}"
        orig = f"{min(lons):.6f},{min(lats):.6f},{max(lons):.6f},{max(lats):.6f}"
        header = (
            f'<?xml version="1.0" encoding="UTF-8"?>\n'
            f"<!-- {self.name}: generated by sumo_nets/generate.py; edit the script, not this file. -->\n"
        )
        loc = (
            f'    <location netOffset="0.00,0.00" convBoundary="{conv}" origBoundary="{orig}" '
            f'projParameter="{proj}"/>\n'
        )
        lines = [header, "<nodes>\n", loc]
        for nid, (x, y, attrs) in self.nodes.items():
            extra = "".join(f" {k}={quoteattr(str(v))}" for k, v in attrs.items())
            lines.append(f'    <node id="{nid}" x="{x:.2f}" y="{y:.2f}"{extra}/>\n')
        lines.append("</nodes>\n")
        (d / f"{self.name}.nod.xml").write_text("".join(lines))

        lines = [header, "<edges>\n"]
        for e in self.edges:
            attrs = (
                f'id="{e["id"]}" from="{e["frm"]}" to="{e["to"]}" numLanes="{e["lanes"]}" '
                f'speed="{e["speed"]:.2f}" priority="{e["priority"]}"'
            )
            if e["name"]:
                attrs += f" name={quoteattr(e['name'])}"
            if e["spread"]:
                attrs += f' spreadType="{e["spread"]}"'
            if e["shape"] is not None:
                attrs += ' shape="' + " ".join(f"{x:.2f},{y:.2f}" for x, y in e["shape"]) + '"'
            lines.append(f"    <edge {attrs}/>\n")
        lines.append("</edges>\n")
        (d / f"{self.name}.edg.xml").write_text("".join(lines))

        lines = [header, "<additional>\n", loc]
        for pid, kind, poly, h in self.polys:
            color = "200,200,200" if kind == "building" else "60,140,60"
            shape = " ".join(f"{x:.2f},{y:.2f}" for x, y in poly.exterior.coords)
            layer = "1" if kind == "foliage" else "0"
            lines.append(
                f'    <poly id="{pid}" type="{kind}" color="{color}" fill="1" layer="{layer}" shape="{shape}">\n'
                f'        <param key="height" value="{h:.1f}"/>\n    </poly>\n'
            )
        lines.append("</additional>\n")
        (d / f"{self.name}.poly.xml").write_text("".join(lines))

        lines = [
            f"# Suggested routes for {self.name}: lists of edge ids, in driving order.\n",
            "# 'default' is the scenario default. Written by sumo_nets/generate.py.\n",
        ]
        for rname, edges in self.routes.items():
            if rname in self.route_notes:
                lines.append(f"# {rname}: {self.route_notes[rname]}\n")
            lines.append(f"{rname} = [\n")
            for k in range(0, len(edges), 6):
                lines.append("    " + ", ".join(f'"{e}"' for e in edges[k : k + 6]) + ",\n")
            lines.append("]\n")
        (d / "routes.toml").write_text("".join(lines))

        con = d / f"{self.name}.con.xml"
        if self.connections:
            lines = [header, "<connections>\n"]
            for frm, to, fl, tl in self.connections:
                lines.append(f'    <connection from="{frm}" to="{to}" fromLane="{fl}" toLane="{tl}"/>\n')
            lines.append("</connections>\n")
            con.write_text("".join(lines))
        elif con.exists():
            con.unlink()

        (d / "net.toml").write_text(
            f"# Metadata for {self.name}. Written by sumo_nets/generate.py.\n"
            f"description = {quote_toml(self.description)}\n"
            f"site = {quote_toml(where)}\n"
            f"site_lat_deg = {lat}\nsite_lon_deg = {lon}\n"
        )


def quote_toml(s: str) -> str:
    return '"' + s.replace("\\", "\\\\").replace('"', '\\"') + '"'


def balloon(start_xy, heading_rad, half_gap_m, r_entry_m, r_loop_m) -> np.ndarray:
    """Balloon turnaround from a right-hand carriageway to the opposite one.

    Starts at ``start_xy`` heading ``heading_rad`` and ends ``2*half_gap_m`` to the left
    heading the opposite way: a right arc (r_entry, alpha), a left arc (r_loop,
    180 deg + 2 alpha), a right arc (r_entry, alpha). Symmetry puts the apex on the axis
    when cos(alpha) = (half_gap + r_entry) / (r_entry + r_loop).
    """
    alpha = math.acos((half_gap_m + r_entry_m) / (r_entry_m + r_loop_m))
    return turtle(
        start_xy,
        heading_rad,
        [("R", r_entry_m, alpha), ("L", r_loop_m, math.pi + 2 * alpha), ("R", r_entry_m, alpha)],
    )


# --------------------------------------------------------------------------- open_highway


def open_highway() -> Net:
    net = Net(
        "open_highway",
        "Divided 3+3-lane arterial, ~3 km north-south with gentle curves (R 1.5 km), "
        "balloon turnarounds at both ends (2 lanes, R 60 m), 25 m/s; open sky, a few low buildings "
        "more than 100 m from the road.",
    )
    rng = np.random.default_rng(1)
    centre = turtle(
        (0.0, -1500.0),
        math.pi / 2,
        [
            ("S", 600.0),
            ("L", 1500.0, math.radians(15)),
            ("S", 500.0),
            ("R", 1500.0, math.radians(30)),
            ("S", 300.0),
            ("L", 1500.0, math.radians(15)),
            ("S", 400.0),
        ],
        step_m=10.0,
    )
    centre[:, 1] -= 0.5 * (centre[0, 1] + centre[-1, 1])  # centre the road on the site
    median_m = 12.0
    half_gap = median_m / 2 + 1.5 * LANE_WIDTH_M  # road axis to carriageway centreline
    nb = offset_polyline(centre, -half_gap)  # northbound on the east (right) side
    sb = offset_polyline(centre, +half_gap)[::-1]
    n_parts = 5
    for tag, line in (("nb", nb), ("sb", sb)):
        parts = split_polyline(line, n_parts)
        for k, part in enumerate(parts):
            net.node(f"{tag}{k}", *part[0])
            if k == n_parts - 1:
                net.node(f"{tag}{k + 1}", *part[-1])
            net.edge(
                f"{tag}{k + 1}",
                f"{tag}{k}",
                f"{tag}{k + 1}",
                lanes=3,
                speed=25.0,
                priority=3,
                shape=part,
                name="Shaganappi Trail NW",
                spread="center",
            )
    for tag, line, dest in (("loop_n", nb, "sb0"), ("loop_s", sb, "nb0")):
        end = line[-1]
        head = math.atan2(line[-1, 1] - line[-3, 1], line[-1, 0] - line[-3, 0])
        loop = balloon(end, head, half_gap, 60.0, 60.0)
        src = "nb5" if tag == "loop_n" else "sb5"
        loop[-1] = (net.nodes[dest][0], net.nodes[dest][1])
        net.edge(
            tag, src, dest, lanes=2, speed=13.89, priority=2, shape=loop, spread="center", name="turnaround"
        )
    for frm, to in (("nb5", "loop_n"), ("sb5", "loop_s")):  # 3 -> 2 lanes: right two merge
        net.connections += [(frm, to, 0, 0), (frm, to, 1, 0), (frm, to, 2, 1)]
    # A few low buildings (farm sheds, a depot), all >= 100 m from the carriageways.
    placed = 0
    while placed < 6:
        x, y = rng.uniform(-700, 700), rng.uniform(-1500, 1500)
        b = rect(x, y, rng.uniform(15, 40), rng.uniform(10, 25), rng.uniform(0, math.pi))
        if net.clear_of_roads(b, 100.0) and all(not b.buffer(20).intersects(p[2]) for p in net.polys):
            net.add_poly("building", b, rng.uniform(4.0, 8.0))
            placed += 1
    circuit = [f"nb{k}" for k in range(1, 6)] + ["loop_n"] + [f"sb{k}" for k in range(1, 6)] + ["loop_s"]
    net.routes["default"] = circuit * 2
    net.route_notes["default"] = "the whole circuit twice (~14 km, ~10 min at 25 m/s)"
    net.routes["northbound"] = [f"nb{k}" for k in range(1, 6)] + ["loop_n"] + [f"sb{k}" for k in range(1, 6)]
    net.route_notes["northbound"] = "one pass north, the turnaround, and back south (~6.4 km)"
    return net


# --------------------------------------------------------------------------- residential


def residential() -> Net:
    net = Net(
        "residential",
        "Curved residential 3x3-node street grid (~2.8 km of street), 1 lane each way at 11.1 m/s, "
        "a 2+2-lane collector across the middle; trees (canopy 8-15 m) line every street, "
        "houses 6-9 m.",
    )
    rng = np.random.default_rng(2)
    xs = [-260.0, 0.0, 260.0]
    ys = [-200.0, 0.0, 200.0]
    for i, x in enumerate(xs):
        for j, y in enumerate(ys):
            net.node(f"n{i}{j}", x, y, type="priority", radius="8")
    names_ew = ["Uxbridge Drive NW", "Collingwood Drive NW", "Unwin Road NW"]
    names_ns = ["Urbana Road NW", "Ulster Road NW", "Usher Road NW"]
    bow_sign = 1.0
    for j in range(3):
        for i in range(2):
            a, b = f"n{i}{j}", f"n{i + 1}{j}"
            collector = j == 1
            perimeter = j in (0, 2)
            bow_sign = -bow_sign
            shape = bowed(net.nodes[a][:2], net.nodes[b][:2], bow_sign * (8.0 if collector else 18.0))
            net.two_way(
                a,
                b,
                lanes=2 if collector else 1,
                speed=13.89 if collector else 11.11,
                priority=3 if perimeter else 2,
                shape=shape,
                name=names_ew[j],
            )
    for i in range(3):
        for j in range(2):
            a, b = f"n{i}{j}", f"n{i}{j + 1}"
            perimeter = i in (0, 2)
            bow_sign = -bow_sign
            shape = bowed(net.nodes[a][:2], net.nodes[b][:2], bow_sign * 15.0)
            net.two_way(
                a, b, lanes=1, speed=11.11, priority=3 if perimeter else 1, shape=shape, name=names_ns[i]
            )
    node_pts = [Point(v[0], v[1]) for v in net.nodes.values()]
    trees: list[Point] = []
    houses: list[Polygon] = []
    for e in net.edges[::2]:  # one per two-way pair: the shared centreline
        line = LineString(e["shape"])
        half_w = e["lanes"] * LANE_WIDTH_M
        for side in (-1.0, 1.0):
            s = rng.uniform(5.0, 15.0)
            while s < line.length:
                p = line.interpolate(s)
                q = line.interpolate(min(s + 1.0, line.length))
                t = np.array([q.x - p.x, q.y - p.y])
                t /= np.linalg.norm(t) + 1e-12
                nrm = side * np.array([-t[1], t[0]])
                off = half_w + 2.5 + rng.uniform(0.0, 1.5)
                c = Point(p.x + off * nrm[0], p.y + off * nrm[1])
                if min(c.distance(n) for n in node_pts) > 14.0 and all(c.distance(o) > 6.0 for o in trees):
                    r = rng.uniform(3.0, 5.0)
                    canopy = circle(c.x, c.y, r)
                    if net.clear_of_roads(Point(c.x, c.y), 1.5):
                        trees.append(c)
                        net.add_poly("foliage", canopy, rng.uniform(8.0, 15.0))
                s += rng.uniform(12.0, 20.0)
            s = rng.uniform(18.0, 30.0)
            while s < line.length - 15.0:
                p = line.interpolate(s)
                q = line.interpolate(s + 1.0)
                ang = math.atan2(q.y - p.y, q.x - p.x)
                nrm = side * np.array([-math.sin(ang), math.cos(ang)])
                depth = rng.uniform(9.0, 12.0)
                off = half_w + 12.0 + depth / 2
                h = rect(p.x + off * nrm[0], p.y + off * nrm[1], rng.uniform(11.0, 15.0), depth, ang)
                if net.clear_of_roads(h, 9.0) and all(h.distance(o) > 3.0 for o in houses):
                    houses.append(h)
                    net.add_poly("building", h, rng.uniform(6.0, 9.0))
                s += rng.uniform(20.0, 26.0)
    # Clockwise around the perimeter (right turns only): n02 -> n22 -> n20 -> n00 -> n02.
    lap = ["n02-n12", "n12-n22", "n22-n21", "n21-n20", "n20-n10", "n10-n00", "n00-n01", "n01-n02"]
    net.routes["default"] = lap * 3
    net.route_notes["default"] = "perimeter clockwise three times (~5.5 km, ~9 min)"
    net.routes["figure_eight"] = [
        "n01-n11",
        "n11-n21",
        "n21-n22",
        "n22-n12",
        "n12-n11",
        "n11-n10",
        "n10-n00",
        "n00-n01",
    ] * 2
    net.route_notes["figure_eight"] = "collector east, north-east block, back through the centre, twice"
    return net


# --------------------------------------------------------------------------- urban_canyon


def urban_canyon() -> Net:
    net = Net(
        "urban_canyon",
        "Downtown grid of 5x5 blocks (110 m street spacing); main avenues/streets 3 lanes each way at "
        "13.9 m/s with traffic lights where they cross, side streets 1 lane each way; buildings "
        "20-120 m tall lining every block 4 m behind the kerb, tallest in the centre.",
    )
    rng = np.random.default_rng(3)
    n = 6
    spacing = 110.0
    coords = [(-2.5 + k) * spacing for k in range(n)]
    main = {1, 4}
    for i, x in enumerate(coords):
        for j, y in enumerate(coords):
            tls = i in main and j in main
            net.node(f"n{i}_{j}", x, y, type="traffic_light" if tls else "priority")
    avenues = ["4 Avenue SW", "5 Avenue SW", "6 Avenue SW", "7 Avenue SW", "8 Avenue SW", "9 Avenue SW"][::-1]
    streets = ["4 Street SW", "3 Street SW", "2 Street SW", "1 Street SW", "Centre Street", "1 Street SE"]
    for j in range(n):
        for i in range(n - 1):
            m = j in main
            net.two_way(
                f"n{i}_{j}",
                f"n{i + 1}_{j}",
                lanes=3 if m else 1,
                speed=13.89 if m else 11.11,
                priority=3 if m else 1,
                name=avenues[j],
            )
    for i in range(n):
        for j in range(n - 1):
            m = i in main
            net.two_way(
                f"n{i}_{j}",
                f"n{i}_{j + 1}",
                lanes=3 if m else 1,
                speed=13.89 if m else 11.11,
                priority=3 if m else 1,
                name=streets[i],
            )
    # A 3-lane main street ending at a perimeter T junction (1-lane streets): lane 0 and
    # lane 1 turn right (merging), lane 2 turns left.
    for m in main:
        for end, prev in ((0, 1), (n - 1, n - 2)):
            for a, b, rt, lt in (
                (f"n{prev}_{m}", f"n{end}_{m}", None, None),  # along an avenue to the W/E edge
                (f"n{m}_{prev}", f"n{m}_{end}", None, None),  # along a street to the S/N edge
            ):
                ax, ay = net.nodes[a][:2]
                bx, by = net.nodes[b][:2]
                dx, dy = np.sign(bx - ax), np.sign(by - ay)
                right = (dy, -dx)  # heading (dx, dy) rotated -90 deg
                bi, bj = (int(v) for v in b[1:].split("_"))
                ri, rj = bi + int(right[0]), bj + int(right[1])
                li, lj = bi - int(right[0]), bj - int(right[1])
                rt, lt = f"{b}-n{ri}_{rj}", f"{b}-n{li}_{lj}"
                net.connections += [(f"{a}-{b}", rt, 0, 0), (f"{a}-{b}", rt, 1, 0), (f"{a}-{b}", lt, 2, 0)]
    # Open-sky approach from the west onto 5 Avenue (the j = 4 main avenue): 1.2 km with no
    # buildings, for an "initialization drive" before the canyon (MacGougan (2009) ch. 4's
    # kinematic test initializes in the open, then drives downtown).
    # One-way (inbound), so that no lane ends at its far end (the nets are closed circuits).
    net.node("w_far", coords[0] - 1200.0, coords[4], type="priority")
    net.edge("w_far-n0_4", "w_far", "n0_4", lanes=2, speed=16.67, priority=3, name="Bow Trail SW", spread="center")
    approach = LineString([net.nodes["w_far"][:2], net.nodes["n0_4"][:2]])
    half = [(3 if k in main else 1) * LANE_WIDTH_M for k in range(n)]  # two-way: half-width = lanes*w
    setback = 4.0
    depth = 28.0
    r_max = math.hypot(coords[-1] + depth + 20.0, coords[-1] + depth + 20.0)

    def height(cx, cy):
        base = 120.0 - 95.0 * math.hypot(cx, cy) / r_max
        return float(np.clip(base + rng.uniform(-15.0, 15.0), 20.0, 120.0))

    def add_lot(x0, y0, x1, y1):
        b = Polygon([(x0 + 0.5, y0 + 0.5), (x1 - 0.5, y0 + 0.5), (x1 - 0.5, y1 - 0.5), (x0 + 0.5, y1 - 0.5)])
        h = height(b.centroid.x, b.centroid.y)  # drawn first: the other lots keep their heights
        if b.distance(approach) >= 2 * LANE_WIDTH_M + 1.0:  # the approach road cuts through the west ring
            net.add_poly("building", b, h)

    for i in range(n - 1):
        for j in range(n - 1):
            x0, x1 = coords[i] + half[i] + setback, coords[i + 1] - half[i + 1] - setback
            y0, y1 = coords[j] + half[j] + setback, coords[j + 1] - half[j + 1] - setback
            xb = [x0, x0 + depth, x1 - depth, x1]
            yb = [y0, y0 + depth, y1 - depth, y1]
            for a in range(3):
                for b in range(3):
                    if a == 1 and b == 1:
                        continue  # courtyard / alley
                    if a == 1 and rng.uniform() < 0.5 and (xb[2] - xb[1]) > 30.0:
                        xm = 0.5 * (xb[1] + xb[2])  # split a long frontage in two
                        add_lot(xb[1], yb[b], xm, yb[b + 1])
                        add_lot(xm, yb[b], xb[2], yb[b + 1])
                    else:
                        add_lot(xb[a], yb[b], xb[a + 1], yb[b + 1])
    # Outer ring: one row of buildings beyond the perimeter streets.
    lo, hi = coords[0] - half[0] - setback, coords[-1] + half[-1] + setback
    frontages = np.linspace(coords[0] - depth, coords[-1] + depth, 13)
    for k in range(len(frontages) - 1):
        f0, f1 = frontages[k], frontages[k + 1]
        add_lot(f0, lo - depth, f1, lo)  # south
        add_lot(f0, hi, f1, hi + depth)  # north
    frontages = np.linspace(coords[0], coords[-1], 11)
    for k in range(len(frontages) - 1):
        f0, f1 = frontages[k], frontages[k + 1]
        add_lot(lo - depth, f0, lo, f1)  # west
        add_lot(hi, f0, hi + depth, f1)  # east
    # Main-street rectangle clockwise (right turns): (1,4) -> (4,4) -> (4,1) -> (1,1) -> (1,4).
    lap = [f"n{i}_4-n{i + 1}_4" for i in (1, 2, 3)]
    lap += [f"n4_{j}-n4_{j - 1}" for j in (4, 3, 2)]
    lap += [f"n{i}_1-n{i - 1}_1" for i in (4, 3, 2)]
    lap += [f"n1_{j}-n1_{j + 1}" for j in (1, 2, 3)]
    net.routes["default"] = lap * 3
    net.route_notes["default"] = "main-street rectangle clockwise three times (~4 km, 4 lights a lap)"
    core = [f"n{i}_3-n{i + 1}_3" for i in range(5)] + ["n5_3-n5_2"]
    core += [f"n{i}_2-n{i - 1}_2" for i in range(5, 0, -1)] + ["n0_2-n0_3"]
    net.routes["core"] = core * 2
    net.route_notes["core"] = "side streets through the tallest blocks, clockwise twice (~2.6 km)"
    net.routes["init_drive"] = ["w_far-n0_4", "n0_4-n1_4"] + lap
    net.route_notes["init_drive"] = (
        "1.2 km of open sky from the west, then into the canyon: the main-street rectangle once (~2.6 km)")
    return net


# --------------------------------------------------------------------------- hospital_loop


def hospital_loop() -> Net:
    net = Net(
        "hospital_loop",
        "Approach road (500 m, 2 lanes each way, westbound in) to a 1-lane balloon turnaround "
        "(R 30 m) in front of a 55 m hospital tower, lower wings and a parkade around; the approach "
        "hangs off a 400 m x 300 m campus ring road so routes can circle.",
    )
    rng = np.random.default_rng(4)
    x_loop = 60.0  # stem node of the turnaround
    x_j = x_loop + 500.0
    net.node("L0", x_loop, 0.0, type="priority")
    net.node("J", x_j, 0.0, type="priority")
    net.node("NW", x_j, 150.0, type="priority", radius="15")
    net.node("NE", x_j + 400.0, 150.0, type="priority", radius="15")
    net.node("SE", x_j + 400.0, -150.0, type="priority", radius="15")
    net.node("SW", x_j, -150.0, type="priority", radius="15")
    net.edge("ap_in", "J", "L0", lanes=2, speed=11.11, priority=2, name="Hospital Drive NW")
    net.edge("ap_out", "L0", "J", lanes=2, speed=11.11, priority=2, name="Hospital Drive NW")
    loop = balloon((x_loop, LANE_WIDTH_M), math.pi, LANE_WIDTH_M, 25.0, 30.0)
    mid = len(loop) // 2
    apex = loop[mid]
    net.node("L1", apex[0], apex[1], type="priority")
    # The loop's lane starts/ends on the approach lanes (y = +-3.2 m): netconvert accepts edge
    # shapes that begin at the junction border rather than the node.
    first, second = loop[: mid + 1], loop[mid:]
    net.edge(
        "loop_in",
        "L0",
        "L1",
        lanes=1,
        speed=8.33,
        priority=1,
        shape=first,
        spread="center",
        name="Hospital Loop",
    )
    net.edge(
        "loop_out",
        "L1",
        "L0",
        lanes=1,
        speed=8.33,
        priority=1,
        shape=second,
        spread="center",
        name="Hospital Loop",
    )
    net.connections += [("ap_in", "loop_in", 0, 0), ("ap_in", "loop_in", 1, 0)]  # 2 -> 1 lane
    ring = [("J", "NW"), ("NW", "NE"), ("NE", "SE"), ("SE", "SW"), ("SW", "J")]
    for a, b in ring:
        net.two_way(a, b, lanes=2, speed=13.89, priority=3, name="Campus Ring Road")
    # Hospital tower west of the loop apex, lower wings, parkade; trees along the approach.
    loop_poly = Polygon(loop)
    west = loop_poly.bounds[0]
    net.add_poly("building", rect(west - 15.0 - 25.0, 0.0, 50.0, 90.0, 0.0), 55.0)  # main tower
    net.add_poly("building", rect(west - 35.0, 80.0, 70.0, 45.0, 0.0), 24.0)  # north wing
    net.add_poly("building", rect(west - 35.0, -80.0, 70.0, 45.0, 0.0), 20.0)  # south wing
    net.add_poly("building", rect(230.0, 60.0, 110.0, 50.0, 0.0), 15.0)  # parkade
    net.add_poly("building", rect(260.0, -65.0, 80.0, 40.0, 0.0), 12.0)  # clinic
    net.add_poly("building", rect(420.0, 70.0, 60.0, 40.0, 0.0), 9.0)  # research annex
    net.add_poly("building", rect(760.0, 0.0, 200.0, 160.0, 0.0), 18.0)  # campus block inside the ring
    trees: list[Point] = []
    for side in (-1.0, 1.0):
        x = x_loop + 80.0
        while x < x_j - 20.0:
            c = Point(x + rng.uniform(-2.0, 2.0), side * (2 * LANE_WIDTH_M + 4.0 + rng.uniform(0.0, 1.5)))
            canopy = circle(c.x, c.y, rng.uniform(3.0, 4.5))
            if all(not canopy.intersects(p[2]) for p in net.polys):
                trees.append(c)
                net.add_poly("foliage", canopy, rng.uniform(8.0, 14.0))
            x += rng.uniform(14.0, 20.0)
    cycle = ["ap_in", "loop_in", "loop_out", "ap_out", "J-SW", "SW-SE", "SE-NE", "NE-NW", "NW-J"]
    net.routes["default"] = cycle * 2
    net.route_notes["default"] = "in to the hospital, round the loop, out, round the ring; twice (~5.2 km)"
    net.routes["visit"] = ["NE-NW", "NW-J", "ap_in", "loop_in", "loop_out", "ap_out", "J-SW", "SW-SE"]
    net.route_notes["visit"] = "from the ring's north side, one hospital visit, leave on the south side"
    return net


BUILDERS = {
    "open_highway": open_highway,
    "residential": residential,
    "urban_canyon": urban_canyon,
    "hospital_loop": hospital_loop,
}


def main() -> None:
    for name, fn in BUILDERS.items():
        net = fn()
        net.write(SITES[name])
        kinds = [p[1] for p in net.polys]
        print(
            f"{name}: {len(net.nodes)} nodes, {len(net.edges)} edges, "
            f"{kinds.count('building')} buildings, {kinds.count('foliage')} trees"
        )


if __name__ == "__main__":
    main()
