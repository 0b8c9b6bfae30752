"""Entity layout of ``replay.rrd`` and the default viewer blueprint.

Entity paths (``<sol>`` = solution name, ``<veh>`` = vehicle id, both escaped with
``rerun.escape_entity_path_part``, so ``gps+uwb`` appears as ``gps\\+uwb``). One timeline,
``sim_time`` (a duration: simulation seconds). *static* = logged once, without time.

==================================  ===============  ======================================
path                                archetype        content
==================================  ===============  ======================================
``world``                           ViewCoordinates  right-handed, z up (static)
``world/lanes``                     LineStrips3D     lane centre lines, z = 0.02 m, just
                                                     above the surface (static)
``world/lanes/surface``             Mesh3D           lane surfaces: centre line buffered by
                                                     half the lane width (static)
``world/buildings``                 Mesh3D           extruded footprints, roofs + walls
                                                     (static)
``world/foliage``                   Mesh3D           extruded canopy volumes, translucent
                                                     (static)
``world/vehicles/truth``            Boxes3D          true vehicle bodies, one batch per step
``world/vehicles/truth/antennas``   Points3D         true antenna positions (``xyz_m``)
``world/vehicles/background``       Boxes3D          non-cluster traffic (radio blockers)
``world/estimates/<sol>``           Points3D         estimated antenna positions, horizontal
                                                     only: drawn at z = 0.2 m
                                                     (``estimate_z_m``; the up error is in
                                                     ``epochs.parquet``, not drawn)
``world/estimates/<sol>/ellipses``  Ellipsoids3D     horizontal 95 % uncertainty ellipses:
                                                     flat ellipsoids, drawn with their axes
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
``errors/<sol>/<veh>/nis``          Scalars          mean NIS of the epoch's accepted
                                                     measurement updates naming the
                                                     vehicle (NaN: none); ~1 if consistent
``errors/<sol>/<veh>/n_sats``       Scalars          satellites used
``errors/<sol>/<veh>/rejections``   Scalars          innovation-test rejections
==================================  ===============  ======================================

A run with several clusters logs each cluster's estimates and ellipses on its own entity,
``world/estimates/<sol>/<cluster>`` and ``world/estimates/<sol>/<cluster>/ellipses`` (one
entity per solution would hold a row per cluster at each time, and the viewer shows the last
row logged at a time: one cluster's estimates only).

What ``v2v run`` logs (``v2v.run``): estimates and errors only for initialized vehicles (an
epoch without any, after some were drawn, is an empty estimates row, which clears them);
each estimate is drawn at its vehicle's true antenna plus its error (``est - true`` ENU,
turned into net XY by the grid convergence), so its horizontal offset from the drawn truth
is the ``epochs.parquet`` east/north error (estimates are drawn at ``estimate_z_m``, truth
antennas at their height); a vehicle's error series have a hole (a ``Clear``) from the first
epoch it has no estimate after one (it left the cluster, or was reset and not yet
re-initialized) to its next row; ``n_sats`` is ``used_pr`` and ``rejections`` the sum of the
``rejected_*`` counts of pr, doppler, uwb, bearing and, in a carrier-phase solution, phase;
``nis`` the mean NIS of the accepted updates those ``used_*`` counts count (the output
interval's SD pseudoranges, Dopplers, phases, UWB ranges and bearings naming the vehicle, a
pair's for both of its vehicles; rejected ones are in ``rejections``), from the run's update log
(:func:`v2v.metrics.errors.epoch_nis_sums`): chi-square(1) NIS average ~1 in a consistent
filter, NaN where the vehicle had no accepted update. Links: at every step the UWB ranges
and bearings measured since the previous step between vehicles present at it (an empty row
when there are none, so that no earlier step's links stay drawn), LOS or NLOS ("rejected" is
never logged by ``v2v run``).

Colours: line of sight green, NLOS orange, rejected red; lead vehicle orange, other
cluster vehicles blue, background traffic grey. Each error series carries its own style
(a static ``SeriesLines`` on its entity, :func:`series_style`: the solution's colour), so the
blueprint needs no per-view overrides.

The default blueprint: the 3-D world large on the left; on the right, top to bottom,
along-track error with ±σ, across-track error with ±σ, NEES (a second tab: NIS),
satellites/rejections, then a row with the sky plots (one tab per vehicle) and a map of the
geodetic truth.
"""

from __future__ import annotations

import functools
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


def estimates_path(solution: str, cluster: str = "") -> str:
    """``world/estimates/<sol>``, or ``world/estimates/<sol>/<cluster>`` for one of several clusters."""
    return rr.new_entity_path(["world", "estimates", solution, *([cluster] if cluster else [])])


def ellipses_path(solution: str, cluster: str = "") -> str:
    """``world/estimates/<sol>/ellipses``, or ``world/estimates/<sol>/<cluster>/ellipses``."""
    return rr.new_entity_path(["world", "estimates", solution, *([cluster] if cluster else []), "ellipses"])


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


def _whole_run() -> dict:
    """Time-series views show the whole run, not rerun's default window around the cursor."""
    inf = rrb.TimeRangeBoundary.infinite()
    return dict(
        time_ranges=rrb.VisibleTimeRange(TIMELINE, start=inf, end=inf),
        axis_x=rrb.TimeAxis(view_range=rr.TimeRange(start=inf, end=inf)),
    )


def series_style(series: str, solution: str, vehicle_id: str, rgb: tuple[int, int, int]) -> rr.SeriesLines:
    """How the default blueprint draws the error series ``series`` of (``solution``,
    ``vehicle_id``), ``rgb`` being the solution's colour: the logger logs it static on the
    series' entity. Each series is in one view of the blueprint (along and across: the
    vehicle's error tab; NEES; NIS; satellites used / rejections), so the entity's
    own style is what that view shows, and the blueprint carries no per-view overrides
    (they were 189 of its 342 chunks at N = 10; sending, flushing and closing the blueprint
    took 55.9 ms with them, 21.4 ms without).

    along, across: a solid line named after the solution; their ``_sigma``: the +-1 sigma
    bounds faint in the same colour; the rest: one line per (solution, vehicle)."""
    if series in ("along", "across"):
        return rr.SeriesLines(names=solution, colors=rgb, widths=1.5)
    if series in ("along_sigma", "across_sigma"):
        faint = (*rgb, 80)
        return rr.SeriesLines(names=[f"{solution} +1σ", f"{solution} -1σ"], colors=[faint, faint], widths=[0.8, 0.8])
    if series not in ERROR_SERIES:
        raise ValueError(f"unknown error series {series!r}; expected one of {ERROR_SERIES}")
    return rr.SeriesLines(names=f"{solution} {vehicle_id}", colors=rgb, widths=1.5)


def _error_view(title: str, solutions: Sequence[str], vehicle: str, key: str) -> rrb.TimeSeriesView:
    """One vehicle's error component for every solution (styles: :func:`series_style`)."""
    contents = [f"+ {error_path(s, vehicle, k)}" for s in solutions for k in (key, key + "_sigma")]
    # +-2 m: lane-level scale; the metres-wide sigma of the first epochs would squash the plot
    return rrb.TimeSeriesView(origin="/errors", contents=contents, name=f"{title} — {vehicle}",
                              plot_legend=rrb.PlotLegend(visible=key == "along"),
                              axis_y=rrb.ScalarAxis(range=(-2.0, 2.0)), **_whole_run())


def _series_view(name: str, pairs: Iterable[tuple[str, str]], series: Sequence[str]) -> rrb.TimeSeriesView:
    contents = [f"+ {error_path(s, v, k)}" for s, v in pairs for k in series]
    return rrb.TimeSeriesView(origin="/errors", contents=contents or ["- /**"], name=name,
                              plot_legend=rrb.PlotLegend(visible=False), **_whole_run())


def default_blueprint(
    solutions: Sequence[str],
    vehicle_ids: Sequence[str],
    sky_vehicle_ids: Sequence[str] = (),
    *,
    show_map: bool = True,
) -> rrb.Blueprint:
    """The default layout of a replay (see the module docstring).

    Left: the 3-D world, the camera following the cluster. Right, top to bottom: along-track
    and across-track error with +-1 sigma (one tab per vehicle, one colour per solution, the
    whole run on the time axis), position NEES with the per-epoch NIS in a second tab,
    satellites used / rejections, and the sky plots (one tab per vehicle) beside the map.
    Side panels start collapsed.

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

    The blueprint is cached by its arguments (the runs of a sweep share it; it is only
    read when sent), so treat the returned object as read-only.
    """
    return _default_blueprint(tuple(solutions), tuple(vehicle_ids), tuple(sky_vehicle_ids), show_map)


@functools.lru_cache(maxsize=8)
def _default_blueprint(
    solutions: tuple[str, ...], vehicle_ids: tuple[str, ...], sky_vehicle_ids: tuple[str, ...], show_map: bool
) -> rrb.Blueprint:
    sols = list(solutions)
    pairs = [(s, v) for s in sols for v in vehicle_ids]
    right: list[rrb.Container | rrb.View] = []
    if vehicle_ids:
        right.append(rrb.Tabs(*[_error_view("Along-track error ±1σ [m]", sols, v, "along") for v in vehicle_ids]))
        right.append(rrb.Tabs(*[_error_view("Across-track error ±1σ [m]", sols, v, "across") for v in vehicle_ids]))
    else:
        right.append(_series_view("Along-track error ±1σ [m]", pairs, ("along", "along_sigma")))
    right.append(rrb.Tabs(_series_view("NEES (position, 3 dof)", pairs, ("nees",)),
                          _series_view("NIS (epoch mean of scalar updates, 1 dof)", pairs, ("nis",))))
    right.append(_series_view("Satellites used / rejections", pairs, ("n_sats", "rejections")))
    bottom: list[rrb.Container | rrb.View] = []
    if sky_vehicle_ids:
        skies = [rrb.Spatial2DView(origin=sky_path(v), name=f"Sky {v}") for v in sky_vehicle_ids]
        bottom.append(rrb.Tabs(*skies, name="Sky"))
    if show_map:
        bottom.append(rrb.MapView(origin=MAP, name="Map (truth)"))
    if bottom:
        right.append(rrb.Horizontal(*bottom))
    world = rrb.Spatial3DView(origin=WORLD, name="World (net XY)", eye_controls=rrb.EyeControls3D(tracking_entity=TRUTH))
    return rrb.Blueprint(
        rrb.Horizontal(world, rrb.Vertical(*right), column_shares=[3.0, 2.0]),
        rrb.SelectionPanel(state="collapsed"),
        rrb.BlueprintPanel(state="collapsed"),
        rrb.TimePanel(state="collapsed", timeline=TIMELINE),
    )
