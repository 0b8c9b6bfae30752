"""Buildings and foliage from SUMO polygon files.

SUMO polygon files (``polyconvert`` output, ``*.poly.xml`` / ``*.add.xml``) hold
``<poly id= type= shape="x1,y1 x2,y2 ...">`` elements, coordinates in net XY metres,
under an ``<additional>`` (or ``<polygons>`` / ``<shapes>``) root. With
``polyconvert --all-attributes`` the OSM tags come along as
``<param key="height" value="12 m"/>`` and ``<param key="building:levels" value="4"/>``.

Classification (by the polygon's ``type``):

* building: ``type`` starts with ``"building"`` (``building``, ``building.yes``,
  ``building.commercial``...);
* foliage: ``type`` in :data:`FOLIAGE_TYPES` or starting with ``"foliage"``;
* everything else is ignored.

Heights: the ``height`` param (metres; a trailing ``m`` is stripped) or, without it,
the poly's own ``height`` attribute (polyconvert writes the parsed OSM height there even
without ``--all-attributes``), else
``building:levels`` x :attr:`PolygonLoadParams.level_height_m`, else a default. Each
object records which of the three gave its height (``"height"``, ``"levels"``,
``"default"``). A tag that cannot be read as a positive number (OSM data holds values
like ``"40'"`` or ``"2;3"``) falls through to the next source rather than failing the
whole file.

Open foliage lines (``natural.tree_row``, ``fill="0"``) are buffered by
:attr:`PolygonLoadParams.tree_crown_radius_m` into a band, and single trees
(``<poi type="natural.tree">``) become discs of that radius, so every foliage object
is an area.

All footprints are returned counter-clockwise (positive shoelace area) without the
repeated closing vertex.
"""

from __future__ import annotations

import logging
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from v2v.errors import UserError
from v2v.frames import GeoReference

log = logging.getLogger(__name__)

FOLIAGE_TYPES = frozenset(
    {
        "tree",
        "trees",
        "foliage",
        "forest",
        "natural.wood",
        "natural.tree",
        "natural.tree_row",
        "landuse.forest",
        "leisure.park",
    }
)
ROOT_TAGS = frozenset({"additional", "polygons", "shapes"})
HEIGHT_SOURCES = ("height", "levels", "default")


@dataclass(frozen=True, kw_only=True)
class PolygonLoadParams:
    """How polygon files become buildings and foliage.

    Parameters
    ----------
    level_height_m : float
        Storey height used with ``building:levels``: height = levels x 3.0 m (a common
        storey-height convention for OSM building heights, e.g. the OSM-3D / OSMBuildings
        renderers).
    default_building_height_m : float
        Height of a building without ``height`` or ``building:levels`` tags (10 m:
        three storeys).
    default_foliage_height_m : float
        Canopy top of foliage without a height tag (12 m: a mature street tree).
    foliage_attenuation_db_per_m : float
        Specific attenuation of the L-band signal per metre of path inside the canopy.
        Assumption: 0.5 dB/m, from Weissberger's modified exponential-decay model for
        paths under 14 m, ``L = 0.45 f_GHz^0.284 d`` dB, i.e. 0.45 x 1.575^0.284
        = 0.51 dB/m at GPS L1 (Weissberger 1982; ITU-R P.833 reviews measured in-leaf
        values of roughly 0.3-1 dB/m at 1-2 GHz).
    tree_crown_radius_m : float
        Crown radius used to turn single trees (points) and tree rows (lines) into
        areas.
    """

    level_height_m: float = 3.0
    default_building_height_m: float = 10.0
    default_foliage_height_m: float = 12.0
    foliage_attenuation_db_per_m: float = 0.5
    tree_crown_radius_m: float = 3.0


@dataclass(frozen=True, kw_only=True)
class Building:
    """An extruded building footprint standing on the ground (z = 0).

    ``footprint_xy_m`` is (K, 2) net XY metres, counter-clockwise, not closed.
    ``height_source`` is one of ``"height"``, ``"levels"``, ``"default"``.
    """

    id: str
    footprint_xy_m: NDArray[np.float64]
    height_m: float
    height_source: str


@dataclass(frozen=True, kw_only=True)
class FoliageArea:
    """A canopy volume: footprint (K, 2) net XY metres, from the ground to ``height_m``."""

    id: str
    footprint_xy_m: NDArray[np.float64]
    height_m: float
    attenuation_db_per_m: float
    height_source: str = "default"


@dataclass(frozen=True, kw_only=True)
class World:
    """Everything that occludes or attenuates signals. ``skipped`` lists degenerate polygons."""

    buildings: tuple[Building, ...] = ()
    foliage: tuple[FoliageArea, ...] = ()
    skipped: tuple[str, ...] = field(default=())


def classify(poly_type: str) -> str | None:
    """``"building"``, ``"foliage"`` or ``None`` (ignored) for a SUMO polygon type."""
    t = poly_type.strip().lower()
    if t.startswith("building"):
        return "building"
    if t in FOLIAGE_TYPES or t.startswith("foliage"):
        return "foliage"
    return None


def _parse_positive(text: str | None) -> float | None:
    """A positive finite number from an OSM-style tag (``"12"``, ``"12 m"``, ``"12,5m"``) or None."""
    if text is None:
        return None
    s = text.strip().lower()
    if s.endswith("m"):
        s = s[:-1].strip()
    s = s.replace(",", ".")
    try:
        v = float(s)
    except ValueError:
        return None
    return v if math.isfinite(v) and v > 0.0 else None


def _height(params: dict[str, str], default_m: float, level_m: float) -> tuple[float, str]:
    h = _parse_positive(params.get("height"))
    if h is not None:
        return h, "height"
    levels = _parse_positive(params.get("building:levels"))
    if levels is not None:
        return levels * level_m, "levels"
    return default_m, "default"


def _ccw(xy: NDArray[np.float64]) -> NDArray[np.float64]:
    """Drop a repeated closing vertex and orient counter-clockwise (shoelace area > 0)."""
    if len(xy) > 1 and np.array_equal(xy[0], xy[-1]):
        xy = xy[:-1]
    x, y = xy[:, 0], xy[:, 1]
    area2 = float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))
    return xy[::-1].copy() if area2 < 0.0 else xy


def _parse_shape(shape: str, path: Path, pid: str) -> NDArray[np.float64]:
    pts = []
    for tok in shape.split():
        parts = tok.split(",")
        if len(parts) not in (2, 3):
            raise UserError(
                f"{path}: poly '{pid}': shape point '{tok}' is not 'x,y'",
                field="network.polygon_files",
                fix="write shape as space-separated 'x,y' pairs (SUMO polygon format)",
            )
        try:
            pts.append((float(parts[0]), float(parts[1])))
        except ValueError:
            raise UserError(
                f"{path}: poly '{pid}': shape point '{tok}' is not numeric",
                field="network.polygon_files",
                fix="write shape as space-separated 'x,y' pairs of numbers in metres",
            ) from None
    arr = np.asarray(pts, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(arr)):
        raise UserError(
            f"{path}: poly '{pid}': shape has non-finite coordinates",
            field="network.polygon_files",
            fix="remove nan/inf coordinates from the polygon file",
        )
    return arr


def _buffer_xy(xy: NDArray[np.float64], radius_m: float) -> NDArray[np.float64]:
    import shapely

    geom = shapely.Point(xy[0]) if len(xy) == 1 else shapely.LineString(xy)
    poly = shapely.buffer(geom, radius_m, quad_segs=4)
    return np.asarray(poly.exterior.coords, dtype=float)


def _element_params(el: ET.Element) -> dict[str, str]:
    out = {}
    for p in el.findall("param"):
        k, v = p.get("key"), p.get("value")
        if k is not None and v is not None:
            out[k.strip().lower()] = v
    return out


def _load_one(
    path: Path,
    params: PolygonLoadParams,
    geo_reference: GeoReference | None,
) -> tuple[list[Building], list[FoliageArea], list[str]]:
    if not path.is_file():
        raise UserError(
            f"polygon file {path} not found", field="network.polygon_files", fix="give the path of a SUMO .poly.xml file"
        )
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise UserError(
            f"{path} is not well-formed XML ({exc})", field="network.polygon_files", fix="regenerate the file with polyconvert"
        ) from None
    if root.tag not in ROOT_TAGS:
        raise UserError(
            f"{path}: root element is <{root.tag}>, expected <additional> or <polygons>",
            field="network.polygon_files",
            fix="give a SUMO polygon file (polyconvert output)",
        )
    buildings: list[Building] = []
    foliage: list[FoliageArea] = []
    skipped: list[str] = []
    for el in root:
        if el.tag not in ("poly", "poi"):
            continue
        pid = el.get("id")
        kind = classify(el.get("type", ""))
        if kind is None:
            continue
        if pid is None:
            raise UserError(
                f"{path}: a <{el.tag}> of type '{el.get('type')}' has no id",
                field="network.polygon_files",
                fix="give every polygon an id",
            )
        if el.tag == "poly":
            shape = el.get("shape")
            if shape is None:
                raise UserError(
                    f"{path}: poly '{pid}' has no shape attribute", field="network.polygon_files", fix='add shape="x1,y1 x2,y2 ..."'
                )
            xy = _parse_shape(shape, path, pid)
        else:
            try:
                xy = np.array([[float(el.get("x", "")), float(el.get("y", ""))]])
            except ValueError:
                raise UserError(
                    f"{path}: poi '{pid}' needs numeric x and y",
                    field="network.polygon_files",
                    fix='write x="..." y="..." in metres',
                ) from None
        if el.get("geo", "0").lower() in ("1", "true"):
            if geo_reference is None:
                raise UserError(
                    f"{path}: {el.tag} '{pid}' has geo coordinates (lon,lat) but no geo-reference was given",
                    field="network.polygon_files",
                    fix="run polyconvert without --proj.plain-geo, or pass the net's GeoReference",
                )
            x, y = geo_reference.geodetic_to_xy(np.radians(xy[:, 1]), np.radians(xy[:, 0]))
            xy = np.column_stack([x, y])
        is_line = el.tag == "poi" or el.get("fill", "1").lower() in ("0", "false")
        if kind == "foliage" and is_line:
            xy = _buffer_xy(xy, params.tree_crown_radius_m)
        xy = _ccw(xy)
        x, y = xy[:, 0], xy[:, 1]
        area_m2 = 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)) if len(xy) >= 3 else 0.0
        if len(np.unique(xy, axis=0)) < 3 or area_m2 <= 1e-9:
            log.warning("%s: skipping degenerate %s '%s' (fewer than 3 points or zero area)", path, kind, pid)
            skipped.append(pid)
            continue
        xy.setflags(write=False)
        tags = _element_params(el)
        if "height" not in tags and el.get("height") is not None:
            # polyconvert copies a parsed OSM height tag into the poly's own height attribute.
            tags["height"] = el.get("height", "")
        if kind == "building":
            h, src = _height(tags, params.default_building_height_m, params.level_height_m)
            buildings.append(Building(id=pid, footprint_xy_m=xy, height_m=h, height_source=src))
        else:
            h, src = _height(tags, params.default_foliage_height_m, params.level_height_m)
            foliage.append(
                FoliageArea(
                    id=pid,
                    footprint_xy_m=xy,
                    height_m=h,
                    attenuation_db_per_m=params.foliage_attenuation_db_per_m,
                    height_source=src,
                )
            )
    return buildings, foliage, skipped


def load_polygons(
    paths: str | Path | Iterable[str | Path],
    *,
    params: PolygonLoadParams | None = None,
    geo_reference: GeoReference | None = None,
) -> World:
    """Read SUMO polygon file(s) into a :class:`World`.

    Parameters
    ----------
    paths : path or iterable of paths
        SUMO ``.poly.xml`` / ``.add.xml`` files.
    params : PolygonLoadParams, optional
        Height defaults and foliage attenuation (defaults: :class:`PolygonLoadParams`).
    geo_reference : GeoReference, optional
        Needed only for polygons written with ``geo="1"`` (lon,lat coordinates).

    Raises
    ------
    UserError
        A file is missing, not XML, has the wrong root, a polygon without id/shape, a
        non-numeric coordinate, or two buildings/foliage areas share an id.
    """
    params = params or PolygonLoadParams()
    if isinstance(paths, (str, Path)):
        paths = [paths]
    buildings: list[Building] = []
    foliage: list[FoliageArea] = []
    skipped: list[str] = []
    seen: dict[str, Path] = {}
    for p in paths:
        path = Path(p)
        b, f, s = _load_one(path, params, geo_reference)
        areas: tuple[Building | FoliageArea, ...] = (*b, *f)
        for obj in areas:
            if obj.id in seen:
                raise UserError(
                    f"{path}: polygon id '{obj.id}' appears twice (also in {seen[obj.id]})",
                    field="network.polygon_files",
                    fix="give each polygon file once; polygon ids must be unique across files",
                )
            seen[obj.id] = path
        buildings += b
        foliage += f
        skipped += s
    return World(buildings=tuple(buildings), foliage=tuple(foliage), skipped=tuple(skipped))
