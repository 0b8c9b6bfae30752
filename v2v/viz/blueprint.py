"""Entity layout of ``replay.rrd`` and the default viewer blueprint.

Entity paths (``<sol>`` = solution name, ``<veh>`` = vehicle id, both escaped with
``rerun.escape_entity_path_part``, so ``gps+uwb`` appears as ``gps\\+uwb``). One timeline,
``sim_time`` (a duration: simulation seconds). *static* = logged once, without time.

==================================  ===============  ======================================
path                                archetype        content
==================================  ===============  ======================================
``world/lanes``                     LineStrips3D     lane centre lines, z = 0 (static)
``world/lanes/surface``             Mesh3D           lane surfaces: centre line buffered by
                                                     half the lane width (static)
``world/buildings``                 Mesh3D           extruded footprints, roofs + walls
                                                     (static)
``world/foliage``                   Mesh3D           extruded canopy volumes, translucent
                                                     (static)
``world/vehicles/truth``            Boxes3D          true vehicle bodies, one batch per step
``world/vehicles/truth/antennas``   Points3D         true antenna positions (``xyz_m``)
``world/vehicles/background``       Boxes3D          non-cluster traffic (radio blockers)
``world/estimates/<sol>``           Points3D         estimated antenna positions
``world/estimates/<sol>/ellipses``  LineStrips3D     horizontal uncertainty ellipses
``world/links/uwb``                 LineStrips3D     UWB ranges a -> b, coloured by status
``world/links/bearing``             LineStrips3D     bearings a -> b, coloured by status
``map/lanes``                       GeoLineStrings   lane centre lines, WGS-84 (static)
``map/vehicles``                    GeoPoints        true vehicle positions, WGS-84
``sky/<veh>``                       Points2D         satellites in a polar sky plot
``sky/<veh>/grid``                  LineStrips2D     elevation rings 0/30/60 deg, N-S and
                                                     E-W axes (static)
``errors/<sol>/<veh>/along``        Scalars          along-track error, m
``errors/<sol>/<veh>/along_sigma``  Scalars (2)      +1 sigma, -1 sigma of the filter, m
``errors/<sol>/<veh>/across``       Scalars          across-track error, m
``errors/<sol>/<veh>/across_sigma`` Scalars (2)      +1 sigma, -1 sigma, m
``errors/<sol>/<veh>/nees``         Scalars          normalized estimation error squared
``errors/<sol>/<veh>/nis``          Scalars          normalized innovation squared
``errors/<sol>/<veh>/n_sats``       Scalars          satellites used
``errors/<sol>/<veh>/rejections``   Scalars          innovation-test rejections
==================================  ===============  ======================================

Colours: line of sight green, NLOS orange, rejected red; lead vehicle orange, other
cluster vehicles blue, background traffic grey.

The default blueprint: the 3-D world large on the left; on the right, top to bottom,
along-track error with ±σ, across-track error with ±σ, NEES/NIS, satellites/rejections,
then a row with the sky plots (one tab per vehicle) and a map of the geodetic truth.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import rerun as rr
import rerun.blueprint as rrb

TIMELINE = "sim_time"

WORLD = "world"
LANES = "world/lanes"
LANE_SURFACE = "world/lanes/surface"
BUILDINGS = "world/buildings"
FOLIAGE = "world/foliage"
TRUTH = "world/vehicles/truth"
TRUTH_ANTENNAS = "world/vehicles/truth/antennas"
BACKGROUND = "world/vehicles/background"
MAP = "map"
MAP_LANES = "map/lanes"
MAP_VEHICLES = "map/vehicles"

ERROR_SERIES = ("along", "along_sigma", "across", "across_sigma", "nees", "nis", "n_sats", "rejections")


def estimates_path(solution: str) -> str:
    return rr.new_entity_path(["world", "estimates", solution])


def ellipses_path(solution: str) -> str:
    return rr.new_entity_path(["world", "estimates", solution, "ellipses"])


def links_path(kind: str) -> str:
    return rr.new_entity_path(["world", "links", kind])


def sky_path(vehicle_id: str) -> str:
    return rr.new_entity_path(["sky", vehicle_id])


def sky_grid_path(vehicle_id: str) -> str:
    return rr.new_entity_path(["sky", vehicle_id, "grid"])


def error_path(solution: str, vehicle_id: str, series: str) -> str:
    """``errors/<sol>/<veh>/<series>`` with ``series`` in :data:`ERROR_SERIES`."""
    if series not in ERROR_SERIES:
        raise ValueError(f"unknown error series {series!r}; expected one of {ERROR_SERIES}")
    return rr.new_entity_path(["errors", solution, vehicle_id, series])


def _series_view(name: str, pairs: Iterable[tuple[str, str]], series: Sequence[str]) -> rrb.TimeSeriesView:
    contents = [f"+ {error_path(s, v, k)}" for s, v in pairs for k in series]
    return rrb.TimeSeriesView(origin="/errors", contents=contents or ["- /**"], name=name)


def default_blueprint(
    solutions: Sequence[str],
    vehicle_ids: Sequence[str],
    sky_vehicle_ids: Sequence[str] = (),
    *,
    show_map: bool = True,
) -> rrb.Blueprint:
    """The default layout of a replay (see the module docstring).

    Parameters
    ----------
    solutions, vehicle_ids : sequences of str
        Names as logged; every (solution, vehicle) pair gets its error series listed.
        The entity-path filters of rerun 0.41 only support a trailing ``/**`` wildcard,
        so the time-series views name their entities explicitly.
    sky_vehicle_ids : sequence of str
        Vehicles with a sky plot (one tab each).
    show_map : bool
        Add the MapView of ``map/**`` (needs map tiles from the network when *viewed*;
        nothing is fetched when the file is written).
    """
    pairs = [(s, v) for s in solutions for v in vehicle_ids]
    right: list[rrb.Container | rrb.View] = [
        _series_view("Along-track error ±1σ [m]", pairs, ("along", "along_sigma")),
        _series_view("Across-track error ±1σ [m]", pairs, ("across", "across_sigma")),
        _series_view("NEES / NIS", pairs, ("nees", "nis")),
        _series_view("Satellites used / rejections", pairs, ("n_sats", "rejections")),
    ]
    bottom: list[rrb.Container | rrb.View] = []
    if sky_vehicle_ids:
        skies = [rrb.Spatial2DView(origin=sky_path(v), name=f"Sky {v}") for v in sky_vehicle_ids]
        bottom.append(rrb.Tabs(*skies, name="Sky"))
    if show_map:
        bottom.append(rrb.MapView(origin=MAP, name="Map (truth)"))
    if bottom:
        right.append(rrb.Horizontal(*bottom))
    world = rrb.Spatial3DView(origin=WORLD, name="World (net XY)")
    return rrb.Blueprint(
        rrb.Horizontal(world, rrb.Vertical(*right), column_shares=[3.0, 2.0]),
        collapse_panels=False,
    )
