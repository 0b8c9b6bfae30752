"""Line-of-sight geometry shared by every radio link and satellite ray.

One :class:`OcclusionGeometry` is built per world (buildings + foliage from
:mod:`v2v.world.buildings`) and answers two questions, vectorized:

* :meth:`OcclusionGeometry.sky`: for an antenna and a set of satellite directions,
  which rays a building blocks, how much canopy each ray crosses, and the excess path
  of the shortest wall echo for the blocked ones (the echo-only NLOS signal of
  MacGougan (2009) section 3.5.1, fig. 3.3); :meth:`OcclusionGeometry.sky_many` answers it
  for the rays of many antennas in one vectorized call (a GNSS epoch of a whole cluster);
* :meth:`OcclusionGeometry.links`: for vehicle-to-vehicle segments, whether a building
  or a vehicle body blocks them, where, and the excess path of the shortest single-bounce
  wall reflection (the "first detectable reflection" a UWB radio measures under NLOS,
  MacGougan (2009) sections 2.8 and 2.11.3).

Geometry model
--------------
Net XY metres plus height ``z`` above the ground (z = 0). A building is its footprint
extruded from the ground to its height (flat roof); a foliage area is its footprint
extruded from the ground to the canopy top; a vehicle is a box on the ground. Walls are
the footprint edges, footprints counter-clockwise, so each wall's outward normal is its
direction vector turned 90 deg clockwise: ``n = (e_y, -e_x) / |e|``.

Blocking. A straight 3-D segment from ``p0`` to ``p1`` with height
``z(t) = z0 + t (z1 - z0)`` is blocked by a building when it is inside the building
volume somewhere. Between crossings of the footprint boundary ``z`` is linear, so it
suffices to test (a) every wall crossing: blocked if ``z(t_c) < h``, and (b) an end
point inside the footprint below the roof. The first entry into the volume is the
smallest of: a blocking wall crossing, ``t = 0`` when ``p0`` is inside, and the roof
crossing ``t_r = (h - z0) / (z1 - z0)`` when the segment descends through the roof
inside the footprint. Grazing a wall (segment parallel to it) does not block.

Sky ray at grid azimuth ``az`` (clockwise from +y) and elevation ``el``: horizontal
direction ``u = (sin az, cos az)``, height ``z(d) = z_a + d tan(el)`` at horizontal
distance ``d``; it is the segment above cut at ``d = max_dist_m``.

Specular reflection (image method). Mirroring a point across the vertical plane of a
wall keeps its height. Link: the image of ``p1`` is ``p1' = p1 - 2 delta1 n`` with
``delta_i = (p_i - a) . n`` (``a`` a wall vertex); the reflected path has length
``|p1' - p0|`` and meets the wall at fraction ``f = delta0 / (delta0 + delta1)`` of the
way from ``p0``. Sky echo: a plane wave from unit direction
``s = (cos el sin az, cos el cos az, sin el)`` reflected by a wall at perpendicular
distance ``d_w`` in front of the antenna arrives with excess path
``2 d_w (s . n) = 2 d_w cos(el) cos(az - az_n)`` (``az_n`` the azimuth of ``n``), from
the reflection point ``R = x_a + tau (s - 2 (s . n) n)``, ``tau = d_w / (s . n)``. A
reflection counts when both the antenna(s) are in front of the wall (``delta > 0``),
the wave comes from the front (``s . n > 0``), ``R`` lies on the wall segment between
the ground and the wall top, and both legs of the reflected path are free of buildings
(for the echo: ``R`` to the antenna, and ``R`` toward the satellite). Vehicles are not
tested on reflected legs.

Foliage. The horizontal length of a ray inside a canopy polygon up to horizontal
distance ``D`` is computed without sorting crossings, from the winding number:
``integral_0^D w(d) dd = w(0) D + sum_entries (D - d_i) - sum_exits (D - d_j)`` with
crossings beyond ``D`` contributing nothing. ``D = min(max_dist, (h - z_a) / tan(el))``
is where the ray rises above the canopy. The slant length is the horizontal one over
``cos(el)``. Overlapping foliage polygons add up (a tree inside a forest polygon counts
twice).

Implementation. The building test of every segment (sky rays, reflected legs, radio links)
and the sky-echo candidate search run in compiled (numba, cached) brute-force kernels with a
per-building bounding-box screen: for worlds of hundreds of buildings that is several times
faster than the spatial-index queries. They evaluate the same floating-point expressions as
the numpy/spatial-index formulations (``_building_hits_vectorized``, ``_sky_echo_vectorized``),
which large worlds (``compiled_pairs_max``) and the rare segments that descend through a roof
still use; the tests check that both give identical results. The vehicle-box test of links is
compiled the same way (``_box_hits_kernel``, reference ``_box_hits_vectorized``), and
:meth:`OcclusionGeometry.links_many` answers the links of many time steps, each against its own
step's vehicle boxes, in one call (a whole UWB or bearing chunk).
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import numpy as np
import shapely
from numba import njit
from numpy.typing import ArrayLike, NDArray

from v2v.world.buildings import World

FloatArray = NDArray[np.float64]

#: Crossings this close (metres, horizontal) to a reflection point are the reflecting
#: wall itself (or its neighbour at a corner) and are not counted as blocking the
#: reflected legs. Far above float rounding of the reflection point (~1e-12 m at 1 km)
#: and far below any wall length that matters.
_REFLECTION_POINT_TOL_M = 1e-6
#: Leg checks of candidate reflections are done for the best few per link/ray first.
_RANK_WINDOWS = (0, 4, 16, 64, np.iinfo(np.int64).max)


@dataclass(frozen=True, kw_only=True)
class SkyResult:
    """Per-ray results of :meth:`OcclusionGeometry.sky`, arrays of shape (n,).

    ``foliage_path_m`` is the slant length inside canopy volumes, ``foliage_loss_db`` that
    length weighted by each area's specific attenuation, ``echo_excess_m`` the excess path
    of the shortest valid wall echo of a blocked ray (NaN when unblocked or none), and
    ``echo_gradient_xy`` (n, 2) its gradient with respect to the antenna's net-XY position:
    ``d(excess)/d(x_a) = 2 (s . n) n`` (module docstring; the excess does not depend on the
    antenna height), so the echo's path rate is ``echo_gradient_xy . v_xy`` for an antenna
    moving at ``v_xy`` (the satellite's motion adds ``2 d_w (ds/dt . n)``, ~1e-4 rad/s times
    the wall distance: mm/s, left out). NaN where ``echo_excess_m`` is; ``None`` from
    objects that do not compute it (then taken as zero). ``echo_wall`` identifies the
    reflecting wall's vertical plane (-1 where there is no echo; walls of one facade, split
    between buildings or at in-line footprint vertices, share it): an echo that moves to
    another plane jumps in path length, which a receiver's phase lock does not follow (a new
    carrier arc); along one plane the path is continuous.
    """

    blocked: NDArray[np.bool_]
    blocker_id: NDArray[np.str_]
    foliage_path_m: FloatArray
    foliage_loss_db: FloatArray
    echo_excess_m: FloatArray
    echo_gradient_xy: FloatArray | None = None
    echo_wall: NDArray[np.int64] | None = None


@dataclass(frozen=True, kw_only=True)
class LinkResult:
    """Per-link results of :meth:`OcclusionGeometry.links`, arrays of shape (m,).

    ``blocker_kind`` is ``""``, ``"building"`` or ``"vehicle"``; ``blocker_id`` the building
    id or the vehicle box row index as a string; ``hit_distance_m`` the 3-D distance from
    ``p0`` to the first entry into a blocker (NaN if unblocked); ``reflection_excess_m`` the
    shortest single-bounce wall reflection path minus the direct distance (NaN if unblocked
    or none within the search limit).
    """

    blocked: NDArray[np.bool_]
    blocker_kind: NDArray[np.str_]
    blocker_id: NDArray[np.str_]
    hit_distance_m: FloatArray
    reflection_excess_m: FloatArray


_M = TypeVar("_M", bound=Callable[..., Any])


def _timed(method: _M) -> _M:
    """Adds each call's wall time to the instance's ``time_s`` (the run's ``occlusion`` stage)."""

    @functools.wraps(method)
    def timed(self: OcclusionGeometry, *args: Any, **kwargs: Any) -> Any:
        t0 = time.perf_counter()
        try:
            return method(self, *args, **kwargs)
        finally:
            self.time_s += time.perf_counter() - t0

    return timed  # type: ignore[return-value]


def _ccw(footprint_xy_m: ArrayLike) -> FloatArray:
    """Footprint vertices counter-clockwise (positive shoelace area), so normals point out."""
    xy = np.asarray(footprint_xy_m, dtype=float)
    area2 = np.sum(xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1])
    return xy[::-1] if area2 < 0.0 else xy


def _cross(a: FloatArray, b: FloatArray) -> FloatArray:
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def _plane_ids(normals: FloatArray, points: FloatArray, tol_rad: float = 1e-6, tol_m: float = 1e-3) -> NDArray[np.int64]:
    """One id per vertical wall plane: walls whose unit normals agree to ``tol_rad`` and whose
    offsets ``n . a`` agree to ``tol_m`` share an id (a facade split between buildings, or at
    in-line vertices of one footprint). Ids are consecutive from 0 in the order of the sorted
    (normal azimuth, offset) pairs; the tolerances are far below what a real facade could
    distinguish and far above float rounding of the footprint coordinates."""
    n = normals.shape[0]
    ids = np.zeros(n, dtype=np.int64)
    if n == 0:
        return ids
    ang = np.arctan2(normals[:, 0], normals[:, 1]) % (2 * np.pi)
    off = normals[:, 0] * points[:, 0] + normals[:, 1] * points[:, 1]
    order = np.lexsort((off, np.round(ang / tol_rad)))
    pid = 0
    ids[order[0]] = 0
    for prev, cur in zip(order[:-1], order[1:], strict=True):
        d_ang = abs((ang[cur] - ang[prev] + np.pi) % (2 * np.pi) - np.pi)
        if not (d_ang <= tol_rad and abs(off[cur] - off[prev]) <= tol_m):
            pid += 1
        ids[cur] = pid
    return ids


def _group_min(group: NDArray[np.int64], value: FloatArray, n: int) -> tuple[FloatArray, NDArray[np.int64]]:
    """Per group: minimum value (inf if empty) and the index of the element holding it (-1)."""
    best = np.full(n, np.inf)
    arg = np.full(n, -1, dtype=np.int64)
    if group.size:
        order = np.lexsort((value, group))
        g = group[order]
        first = np.ones(g.size, dtype=bool)
        first[1:] = g[1:] != g[:-1]
        best[g[first]] = value[order[first]]
        arg[g[first]] = order[first]
    return best, arg


def _rank_in_group(
    group: NDArray[np.int64], value: FloatArray
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Order by (group, value) and each element's rank within its group (in that order)."""
    order = np.lexsort((value, group))
    g = group[order]
    starts = np.ones(g.size, dtype=bool)
    starts[1:] = g[1:] != g[:-1]
    start_pos = np.maximum.accumulate(np.where(starts, np.arange(g.size), 0))
    return order, np.arange(g.size) - start_pos


def _query_pairs(tree: shapely.STRtree, geoms, **kw) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    res = np.asarray(tree.query(geoms, **kw)).reshape(2, -1)
    return res[0].astype(np.int64), res[1].astype(np.int64)


_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def _wall_crossings_kernel(
    p0, p1, skip_start_m, skip_end_m, h_max, wa, wb, w_h, w_len, b_first, b_bbox, b_order, b_x0_sorted, b_width_max,
    any_hit,
):  # pragma: no cover - compiled
    """First blocking wall crossing of each segment (the wall part of ``_building_hits``).

    Exactly the decisions of the vectorized path, evaluated with the same floating-point
    expressions: the sub-segment below the tallest roof, the closed-segment orientation test
    (preceded by the envelope test the spatial index does), ``t = clip(cross(a - p0, e) /
    cross(d, e))``, grazing rejection, ``z(t) < h_wall`` and the skip distances. Buildings
    whose bounding box misses the sub-segment's envelope are skipped (their walls' envelopes
    miss it too); only buildings whose box starts (``x0``, sorted: ``b_order``, ``b_x0_sorted``)
    within ``[sx0 - widest box - 1 m, sx1]`` can overlap the envelope's x range, so only those are
    visited. Returns per segment the smallest ``t`` (inf if none), the lowest-index building
    holding it (-1; the building-order loop's first), and whether any blocking crossing belongs
    to a building whose roof the segment descends through (``z0 > h > z1``): those need the roof
    test. Buildings are visited in the segment's x direction, stopping once no further box can
    hold an earlier crossing (segments that do not descend). With ``any_hit``, such a segment
    stops at its first blocking crossing found: ``t`` is then *a* crossing (for "is it
    clear?"), not necessarily the first.
    """
    n = p0.shape[0]
    t_best = np.full(n, np.inf)
    b_best = np.full(n, -1, dtype=np.int64)
    roof = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        x0, y0, z0 = p0[i, 0], p0[i, 1], p0[i, 2]
        dx, dy = p1[i, 0] - x0, p1[i, 1] - y0
        dz = p1[i, 2] - z0
        hlen = np.hypot(dx, dy)
        if dz < 0.0:
            ta = min(max((h_max - z0) / dz, 0.0), 1.0)
            tb = 1.0
            below = ta < tb
        elif dz > 0.0:
            ta = 0.0
            tb = min(max((h_max - z0) / dz, 0.0), 1.0)
            below = ta < tb
        else:
            ta, tb = 0.0, 1.0
            below = z0 < h_max
        if not below:
            continue
        ax, ay = x0 + ta * dx, y0 + ta * dy
        bx, by = x0 + tb * dx, y0 + tb * dy
        sx0, sx1 = min(ax, bx), max(ax, bx)
        sy0, sy1 = min(ay, by), max(ay, by)
        lo = np.searchsorted(b_x0_sorted, sx0 - b_width_max - 1.0)
        hi = np.searchsorted(b_x0_sorted, sx1, side="right")
        # Buildings are visited along the segment's x direction; once a crossing at t_best is
        # known, a building whose box starts (1 m margin) beyond x(t_best) cannot hold a crossing
        # at t <= t_best: stop (not for descending segments, whose roof flags need every wall).
        forward = dx >= 0.0
        can_stop = dz >= 0.0
        for kb in range(hi - lo):
            ib = lo + kb if forward else hi - 1 - kb
            if can_stop and t_best[i] <= 1.0:
                if any_hit:
                    break
                x_hit = x0 + t_best[i] * dx
                if (b_x0_sorted[ib] > x_hit + 1.0) if forward else (b_x0_sorted[ib] + b_width_max + 1.0 < x_hit):
                    break
            b = b_order[ib]
            if b_bbox[b, 0] > sx1 or b_bbox[b, 2] < sx0 or b_bbox[b, 1] > sy1 or b_bbox[b, 3] < sy0:
                continue
            for w in range(b_first[b], b_first[b + 1]):
                cx, cy, ex, ey = wa[w, 0], wa[w, 1], wb[w, 0], wb[w, 1]
                if min(cx, ex) > sx1 or max(cx, ex) < sx0 or min(cy, ey) > sy1 or max(cy, ey) < sy0:
                    continue
                o1 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
                o2 = (bx - ax) * (ey - ay) - (by - ay) * (ex - ax)
                if not (min(o1, o2) <= 0.0 and max(o1, o2) >= 0.0):
                    continue
                o3 = (ex - cx) * (ay - cy) - (ey - cy) * (ax - cx)
                o4 = (ex - cx) * (by - cy) - (ey - cy) * (bx - cx)
                if not (min(o3, o4) <= 0.0 and max(o3, o4) >= 0.0):
                    continue
                e0, e1 = ex - cx, ey - cy
                den = dx * e1 - dy * e0
                if not abs(den) > 1e-12 * hlen * w_len[w]:
                    continue
                t = ((cx - x0) * e1 - (cy - y0) * e0) / den
                t = min(max(t, 0.0), 1.0)
                z = z0 + t * dz
                if not z < w_h[w]:
                    continue
                if skip_start_m > 0.0 and not t * hlen >= skip_start_m:
                    continue
                if skip_end_m > 0.0 and not (1.0 - t) * hlen >= skip_end_m:
                    continue
                if z0 > w_h[w] and p1[i, 2] < w_h[w]:
                    roof[i] = True
                if t < t_best[i] or (t == t_best[i] and b < b_best[i]):
                    t_best[i] = t
                    b_best[i] = b
    return t_best, b_best, roof


@njit(**_JIT)
def _sky_echo_candidates_kernel(
    ants, ray_ant, s_hx, s_hy, ce, se, tan_el, max_dist_m, wa, w_nx, w_ny, w_dir, w_len, w_h
):  # pragma: no cover - compiled
    """Every geometrically valid wall echo of each blocked sky ray (see ``_sky_echo``).

    For ray ``i`` from antenna ``ants[ray_ant[i]]`` with horizontal direction ``(s_hx, s_hy)``
    (times ``cos el``) and wall ``w``: antenna in front (``d_w > 0``), wall above the antenna
    (both screened once per antenna), wave from the front (``c = s . n > 0``),
    ``d_w tan(el) < h_w - z_a``, reflection point ``R`` on the wall segment below its top and
    within ``max_dist_m``. Returns (ray, excess ``2 d_w c``, R xyz, far point of the incident
    leg xyz, wall) with the same floating-point expressions as the vectorized formulation
    (trigonometric inputs are computed by numpy outside).
    """
    nw = wa.shape[0]
    na = ants.shape[0]
    order = np.argsort(ray_ant, kind="mergesort")
    ray_first = np.searchsorted(ray_ant[order], np.arange(na + 1))
    walls = np.empty(nw, dtype=np.int64)
    deltas = np.empty(nw)
    hzs = np.empty(nw)
    f_nx = np.empty(nw)
    f_ny = np.empty(nw)
    cap = max(64, 4 * ray_ant.shape[0])
    ri = np.empty(cap, dtype=np.int64)
    wid = np.empty(cap, dtype=np.int64)
    exc = np.empty(cap)
    r3 = np.empty((cap, 3))
    far = np.empty((cap, 3))
    count = 0
    for a in range(na):
        if ray_first[a] == ray_first[a + 1]:
            continue
        xx, xy, xz = ants[a, 0], ants[a, 1], ants[a, 2]
        # The antenna's flattest ray: a wall failing ``d_w tan(el) < h_w - z_a`` for it fails for
        # every ray of the antenna (fl(d t) is non-decreasing in t), so it is dropped here.
        q0, q1 = ray_first[a], ray_first[a + 1]
        tan_lo = np.inf
        for q in range(q0, q1):
            tan_lo = min(tan_lo, tan_el[order[q]])
        nfront = 0
        for w in range(nw):
            delta = (xx - wa[w, 0]) * w_nx[w] + (xy - wa[w, 1]) * w_ny[w]
            hz = w_h[w] - xz
            if delta > 0.0 and hz > 0.0 and delta * tan_lo < hz:
                walls[nfront] = w
                deltas[nfront] = delta
                hzs[nfront] = hz
                f_nx[nfront] = w_nx[w]
                f_ny[nfront] = w_ny[w]
                nfront += 1
        for q in range(q0, q1):
            i = order[q]
            sx, sy, te = s_hx[i], s_hy[i], tan_el[i]
            for j in range(nfront):
                nx, ny = f_nx[j], f_ny[j]
                c = sx * nx + sy * ny
                if not (c > 0.0 and deltas[j] * te < hzs[j]):
                    continue
                w = walls[j]
                delta = deltas[j]
                tau = delta / c
                rx = xx + tau * (sx - 2.0 * c * nx)
                ry = xy + tau * (sy - 2.0 * c * ny)
                s_wall = ((rx - wa[w, 0]) * w_dir[w, 0] + (ry - wa[w, 1]) * w_dir[w, 1]) / w_len[w]
                if not (s_wall >= 0.0 and s_wall <= 1.0):
                    continue
                z_r = xz + tau * se[i]
                if not (z_r < w_h[w] and tau * ce[i] <= max_dist_m):
                    continue
                if count == cap:  # grow the outputs
                    cap *= 2
                    ri2, exc2, r32, far2 = np.empty(cap, dtype=np.int64), np.empty(cap), np.empty((cap, 3)), np.empty(
                        (cap, 3))
                    wid2 = np.empty(cap, dtype=np.int64)
                    ri2[:count], exc2[:count], r32[:count], far2[:count], wid2[:count] = ri, exc, r3, far, wid
                    ri, exc, r3, far, wid = ri2, exc2, r32, far2, wid2
                ri[count] = i
                wid[count] = w
                exc[count] = 2.0 * delta * c
                r3[count, 0], r3[count, 1], r3[count, 2] = rx, ry, z_r
                far[count, 0] = rx + max_dist_m * s_hx[i] / ce[i]
                far[count, 1] = ry + max_dist_m * s_hy[i] / ce[i]
                far[count, 2] = z_r + max_dist_m * tan_el[i]
                count += 1
    return ri[:count].copy(), exc[:count].copy(), r3[:count].copy(), far[:count].copy(), wid[:count].copy()


@njit(**_JIT)
def _in_any_box_kernel(p, bbox, b_order, b_x0_sorted, b_width_max):  # pragma: no cover - compiled
    """Whether each point's (x, y) lies in at least one closed box ``(x0, y0, x1, y1)`` (only boxes
    starting within ``[x - widest box - 1 m, x]`` are visited: ``b_order`` sorts them by ``x0``)."""
    out = np.zeros(p.shape[0], dtype=np.bool_)
    for i in range(p.shape[0]):
        x, y = p[i, 0], p[i, 1]
        lo = np.searchsorted(b_x0_sorted, x - b_width_max - 1.0)
        hi = np.searchsorted(b_x0_sorted, x, side="right")
        for ib in range(lo, hi):
            b = b_order[ib]
            if bbox[b, 0] <= x <= bbox[b, 2] and bbox[b, 1] <= y <= bbox[b, 3]:
                out[i] = True
                break
    return out


def warm_up() -> None:
    """Load (or, on the first use after an install, compile and cache) the compiled kernels.

    The first call of a numba kernel in a process costs its import and cache load (~0.1-0.5 s;
    a few seconds when it has to compile); benchmarks call this outside their timed region.
    """
    p = np.zeros((1, 3))
    w = np.zeros((1, 2))
    one = np.ones(1)
    i0 = np.zeros(1, dtype=np.int64)
    _wall_crossings_kernel(p, p, 0.0, 0.0, 1.0, w, w + 1.0, one, one, np.array([0, 1]), np.zeros((1, 4)), i0,
                           np.zeros(1), 0.0, False)
    _sky_echo_candidates_kernel(p, i0, one, one, one, one, one, 1.0, w, one, one, w, one, one)
    _in_any_box_kernel(p, np.zeros((1, 4)), i0, np.zeros(1), 0.0)
    _box_hits_kernel(p, p, np.zeros((1, 6)), one, one, np.array([0, 1]), i0, np.zeros((1, 2), dtype=np.int64))


class OcclusionGeometry:
    """Cached wall/footprint arrays and spatial indexes of one :class:`World`.

    Parameters
    ----------
    world : World
        Buildings and foliage (net XY metres).
    max_reflection_excess_m : float
        Reflections whose excess path exceeds this are not searched for (links). The
        search radius around a link of horizontal length ``L`` follows from the ellipse
        of constant path ``L + E``: walls farther than ``sqrt(E (E + 2L)) / 2`` from the
        segment cannot give an excess below ``E``.

    Attributes
    ----------
    time_s : float
        Wall time (s) spent in :meth:`sky_many` and :meth:`links_many` (and so in
        :meth:`sky` and :meth:`links`) since construction: a run reports it as its
        ``occlusion`` stage.
    """

    #: Up to this many (antenna, wall) pairs per sky query, echo candidates are screened
    #: over all walls at once instead of through the spatial index (same result, faster
    #: for small worlds).
    dense_pairs_max = 200_000
    #: Up to this many (segment, building) pairs per building test, or (blocked ray, wall)
    #: pairs per echo search, the compiled brute-force kernels are used; beyond (large
    #: worlds) the spatial-index formulations (identical results).
    compiled_pairs_max = 4_000_000

    def __init__(self, world: World, *, max_reflection_excess_m: float = 100.0):
        self.world = world
        self.max_reflection_excess_m = float(max_reflection_excess_m)
        self.time_s = 0.0
        bl = world.buildings
        self._b_ids = np.array([b.id for b in bl], dtype=str) if bl else np.array([], dtype=str)
        self._b_h = np.array([b.height_m for b in bl], dtype=float)
        wa, wb, wbld = [], [], []
        for i, b in enumerate(bl):
            xy = _ccw(b.footprint_xy_m)
            wa.append(xy)
            wb.append(np.roll(xy, -1, axis=0))
            wbld.append(np.full(len(xy), i, dtype=np.int64))
        self._wa = np.concatenate(wa) if wa else np.zeros((0, 2))
        self._wb = np.concatenate(wb) if wb else np.zeros((0, 2))
        self._w_bld = np.concatenate(wbld) if wbld else np.zeros(0, dtype=np.int64)
        self._we = self._wb - self._wa
        self._w_len = np.hypot(self._we[:, 0], self._we[:, 1])
        keep = self._w_len > 0.0
        self._wa, self._wb, self._w_bld, self._we, self._w_len = (
            self._wa[keep],
            self._wb[keep],
            self._w_bld[keep],
            self._we[keep],
            self._w_len[keep],
        )
        self._w_h = self._b_h[self._w_bld] if self._w_bld.size else np.zeros(0)
        self._h_max = float(self._b_h.max()) if self._b_h.size else 0.0
        self._w_dir = self._we / self._w_len[:, None] if self._w_len.size else np.zeros((0, 2))
        # Walls are grouped by building (ascending): per-building wall ranges and bounding boxes
        # for the compiled crossing test.
        nb = len(bl)
        self._b_first = np.searchsorted(self._w_bld, np.arange(nb + 1)).astype(np.int64)
        bbox = np.empty((nb, 4))
        bbox[:, :2], bbox[:, 2:] = np.inf, -np.inf
        if self._w_bld.size:
            for end in (self._wa, self._wb):
                np.minimum.at(bbox[:, 0], self._w_bld, end[:, 0])
                np.minimum.at(bbox[:, 1], self._w_bld, end[:, 1])
                np.maximum.at(bbox[:, 2], self._w_bld, end[:, 0])
                np.maximum.at(bbox[:, 3], self._w_bld, end[:, 1])
        self._b_bbox = bbox
        self._index_boxes()
        self._w_n = (
            np.column_stack([self._w_dir[:, 1], -self._w_dir[:, 0]]) if self._w_len.size else np.zeros((0, 2))
        )
        self._w_nx, self._w_ny = self._w_n[:, 0].copy(), self._w_n[:, 1].copy()
        self._w_plane = _plane_ids(self._w_n, self._wa)
        self._wall_tree = shapely.STRtree(shapely.linestrings(np.stack([self._wa, self._wb], axis=1)))
        self._b_polys = np.array(
            [shapely.make_valid(shapely.Polygon(b.footprint_xy_m)) for b in bl], dtype=object
        )
        shapely.prepare(self._b_polys)
        self._b_tree = shapely.STRtree(self._b_polys)

        fl = world.foliage
        self._f_h = np.array([f.height_m for f in fl], dtype=float)
        self._f_att = np.array([f.attenuation_db_per_m for f in fl], dtype=float)
        fa, fb, fp = [], [], []
        for i, f in enumerate(fl):
            xy = _ccw(f.footprint_xy_m)
            fa.append(xy)
            fb.append(np.roll(xy, -1, axis=0))
            fp.append(np.full(len(xy), i, dtype=np.int64))
        self._fa = np.concatenate(fa) if fa else np.zeros((0, 2))
        self._fe = (np.concatenate(fb) if fb else np.zeros((0, 2))) - self._fa
        self._f_poly = np.concatenate(fp) if fp else np.zeros(0, dtype=np.int64)
        self._fol_edge_tree = shapely.STRtree(
            shapely.linestrings(np.stack([self._fa, self._fa + self._fe], axis=1))
        )
        self._f_polys = np.array(
            [shapely.make_valid(shapely.Polygon(f.footprint_xy_m)) for f in fl], dtype=object
        )
        self._f_tree = shapely.STRtree(self._f_polys)

    def _index_boxes(self) -> None:
        """Building boxes sorted by their west edge, and the widest box (compiled kernels visit
        only the boxes that can overlap a query's x range)."""
        bbox = self._b_bbox
        self._b_order = np.argsort(bbox[:, 0], kind="stable").astype(np.int64)
        self._b_x0_sorted = bbox[self._b_order, 0].copy()
        width = bbox[:, 2] - bbox[:, 0]
        width = width[np.isfinite(width)]
        self._b_width_max = float(width.max()) if width.size else 0.0

    # ------------------------------------------------------------------ buildings
    def _building_hits(
        self,
        p0: FloatArray,
        p1: FloatArray,
        *,
        skip_start_m: float = 0.0,
        skip_end_m: float = 0.0,
        check_start_inside: bool = True,
        check_end_inside: bool = True,
        any_hit: bool = False,
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """First entry (segment parameter t in [0, 1], inf if none) of segments into buildings.

        Crossings within ``skip_start_m`` / ``skip_end_m`` (horizontal) of ``p0`` / ``p1``
        are ignored (used for legs starting or ending on a reflecting wall). ``any_hit``: only
        whether ``t`` is finite is wanted (blocked or clear); the compiled path may then return
        any blocking crossing instead of the first.
        """
        k = len(p0)
        if k == 0 or self._w_len.size == 0:
            return np.full(k, np.inf), np.full(k, -1, dtype=np.int64)
        if k * (self._b_first.size - 1) > self.compiled_pairs_max:
            return self._building_hits_vectorized(
                p0, p1, skip_start_m=skip_start_m, skip_end_m=skip_end_m,
                check_start_inside=check_start_inside, check_end_inside=check_end_inside,
            )
        p0 = np.ascontiguousarray(p0, dtype=float)
        p1 = np.ascontiguousarray(p1, dtype=float)
        t_w, b_w, roof = _wall_crossings_kernel(
            p0, p1, float(skip_start_m), float(skip_end_m), self._h_max, self._wa, self._wb, self._w_h,
            self._w_len, self._b_first, self._b_bbox, self._b_order, self._b_x0_sorted, self._b_width_max, any_hit,
        )
        # Roofs matter only for segments that descend through one: a blocking wall crossing of
        # a building below p0 and above p1 (flagged), or p1 inside a footprint (needs dz < 0).
        slow = roof | ((p1[:, 2] < p0[:, 2]) & check_end_inside)
        if slow.any():
            idx = np.flatnonzero(slow)
            t_w[idx], b_w[idx] = self._building_hits_vectorized(
                p0[idx], p1[idx], skip_start_m=skip_start_m, skip_end_m=skip_end_m,
                check_start_inside=False, check_end_inside=check_end_inside,
            )
        if check_start_inside:
            # Only points inside some footprint's bounding box can be within a footprint.
            cand = np.flatnonzero(_in_any_box_kernel(p0, self._b_bbox, self._b_order, self._b_x0_sorted,
                                                     self._b_width_max))
            if cand.size:
                pi, bi = _query_pairs(self._b_tree, shapely.points(p0[cand, :2]), predicate="within")
                pi = cand[pi]
                # Ties at t = 0 go, as in the vectorized path, to a wall crossing at t = 0, then
                # to the first footprint in index-query order (reversed: the last write wins).
                ok = (p0[pi, 2] < self._b_h[bi]) & (t_w[pi] != 0.0)
                t_w[pi[ok]] = 0.0
                b_w[pi[ok][::-1]] = bi[ok][::-1]
        return t_w, b_w

    def _building_hits_vectorized(
        self,
        p0: FloatArray,
        p1: FloatArray,
        *,
        skip_start_m: float = 0.0,
        skip_end_m: float = 0.0,
        check_start_inside: bool = True,
        check_end_inside: bool = True,
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """:meth:`_building_hits` with the spatial index and numpy (reference implementation)."""
        k = len(p0)
        t_cand: list[FloatArray] = []
        g_cand: list[NDArray[np.int64]] = []
        b_cand: list[NDArray[np.int64]] = []
        if k == 0 or self._w_len.size == 0:
            return np.full(k, np.inf), np.full(k, -1, dtype=np.int64)
        d = p1[:, :2] - p0[:, :2]
        dz = p1[:, 2] - p0[:, 2]
        hlen = np.hypot(d[:, 0], d[:, 1])
        # Only the part of each segment below the tallest roof can hit a wall: query the
        # index with that sub-segment [ta, tb] (crossings elsewhere have z >= every h).
        with np.errstate(divide="ignore", invalid="ignore"):
            t_top = (self._h_max - p0[:, 2]) / dz
        ta = np.where(dz < 0.0, np.clip(t_top, 0.0, 1.0), 0.0)
        tb = np.where(dz > 0.0, np.clip(t_top, 0.0, 1.0), 1.0)
        below = np.where(dz == 0.0, p0[:, 2] < self._h_max, ta < tb)
        q = np.flatnonzero(below)
        qa = p0[q, :2] + ta[q, None] * d[q]
        qb = p0[q, :2] + tb[q, None] * d[q]
        # Index candidates by bounding box, then the closed-segment intersection test by
        # orientations (what GEOS ``intersects`` decides, up to float rounding of an
        # orientation; a pair decided differently has an end point within rounding of the
        # other segment: at a leg's end on its reflecting wall it is skipped either way).
        si, wi = _query_pairs(self._wall_tree, shapely.linestrings(np.stack([qa, qb], axis=1)))
        ax, ay, bx, by = qa[si, 0], qa[si, 1], qb[si, 0], qb[si, 1]
        cx, cy, ex, ey = self._wa[wi, 0], self._wa[wi, 1], self._wb[wi, 0], self._wb[wi, 1]
        o1 = (bx - ax) * (cy - ay) - (by - ay) * (cx - ax)
        o2 = (bx - ax) * (ey - ay) - (by - ay) * (ex - ax)
        o3 = (ex - cx) * (ay - cy) - (ey - cy) * (ax - cx)
        o4 = (ex - cx) * (by - cy) - (ey - cy) * (bx - cx)
        meet = (np.minimum(o1, o2) <= 0.0) & (np.maximum(o1, o2) >= 0.0)
        meet &= (np.minimum(o3, o4) <= 0.0) & (np.maximum(o3, o4) >= 0.0)
        si, wi = q[si[meet]], wi[meet]
        roof_g: list[NDArray[np.int64]] = []
        roof_b: list[NDArray[np.int64]] = []
        if si.size:
            ds = d[si]
            e = self._we[wi]
            ap = self._wa[wi] - p0[si, :2]
            den = _cross(ds, e)
            ok = np.abs(den) > 1e-12 * hlen[si] * self._w_len[wi]
            with np.errstate(divide="ignore", invalid="ignore"):
                t = np.clip(_cross(ap, e) / den, 0.0, 1.0)
            z = p0[si, 2] + t * dz[si]
            hw = self._w_h[wi]
            ok &= z < hw
            if skip_start_m > 0.0:
                ok &= t * hlen[si] >= skip_start_m
            if skip_end_m > 0.0:
                ok &= (1.0 - t) * hlen[si] >= skip_end_m
            t_cand.append(t[ok])
            g_cand.append(si[ok])
            b_cand.append(self._w_bld[wi[ok]])
            roof_g.append(si[ok])
            roof_b.append(self._w_bld[wi[ok]])
        if check_start_inside:
            pi, bi = _query_pairs(self._b_tree, shapely.points(p0[:, :2]), predicate="within")
            ok = p0[pi, 2] < self._b_h[bi]
            t_cand.append(np.zeros(int(ok.sum())))
            g_cand.append(pi[ok])
            b_cand.append(bi[ok])
        if check_end_inside:
            pi, bi = _query_pairs(self._b_tree, shapely.points(p1[:, :2]), predicate="within")
            ok = p1[pi, 2] < self._b_h[bi]
            roof_g.append(pi[ok])
            roof_b.append(bi[ok])
        if roof_g:
            rg = np.concatenate(roof_g)
            rb = np.concatenate(roof_b)
            hb = self._b_h[rb]
            desc = (p0[rg, 2] > hb) & (p1[rg, 2] < hb)
            rg, rb, hb = rg[desc], rb[desc], hb[desc]
            if rg.size:
                tr = (hb - p0[rg, 2]) / dz[rg]
                xr = p0[rg, :2] + tr[:, None] * d[rg]
                inside = shapely.contains_xy(self._b_polys[rb], xr[:, 0], xr[:, 1])
                if skip_start_m > 0.0:
                    inside &= tr * hlen[rg] >= skip_start_m
                if skip_end_m > 0.0:
                    inside &= (1.0 - tr) * hlen[rg] >= skip_end_m
                t_cand.append(tr[inside])
                g_cand.append(rg[inside])
                b_cand.append(rb[inside])
        if not t_cand:
            return np.full(k, np.inf), np.full(k, -1, dtype=np.int64)
        t_all = np.concatenate(t_cand)
        best, arg = _group_min(np.concatenate(g_cand), t_all, k)
        b_all = np.concatenate(b_cand)
        return best, np.where(arg >= 0, b_all[np.maximum(arg, 0)] if b_all.size else -1, -1)

    def _legs_clear(self, a: FloatArray, r: FloatArray, b: FloatArray) -> NDArray[np.bool_]:
        """Both legs a->r and r->b free of buildings; r lies on the reflecting wall."""
        t1, _ = self._building_hits(a, r, skip_end_m=_REFLECTION_POINT_TOL_M, check_end_inside=False, any_hit=True)
        clear = ~np.isfinite(t1)
        # The long leg only where the short one is clear (each segment is tested on its own).
        idx = np.flatnonzero(clear)
        t2, _ = self._building_hits(r[idx], b[idx], skip_start_m=_REFLECTION_POINT_TOL_M, check_start_inside=False,
                                    any_hit=True)
        clear[idx] = ~np.isfinite(t2)
        return clear

    def _best_reflection(
        self,
        group: NDArray[np.int64],
        excess: FloatArray,
        a: FloatArray,
        r: FloatArray,
        b: FloatArray,
        n: int,
    ) -> tuple[FloatArray, NDArray[np.int64]]:
        """Smallest excess per group among candidates whose legs are clear (NaN if none), and
        the candidate giving it (-1 if none).

        Candidates are leg-checked best-first in rank windows, so a group's first window
        that holds a clear candidate gives its global minimum.
        """
        out = np.full(n, np.nan)
        which = np.full(n, -1, dtype=np.int64)
        if group.size == 0:
            return out, which
        order, rank = _rank_in_group(group, excess)
        done = np.zeros(n, dtype=bool)
        for lo, hi in zip(_RANK_WINDOWS[:-1], _RANK_WINDOWS[1:], strict=True):
            sel = order[(rank >= lo) & (rank < hi)]
            sel = sel[~done[group[sel]]]
            if sel.size == 0:
                continue
            clear = self._legs_clear(a[sel], r[sel], b[sel])
            cand = sel[clear]
            best, arg = _group_min(group[cand], excess[cand], n)
            found = np.isfinite(best)
            out[found] = best[found]
            which[found] = cand[arg[found]]
            done |= found
        return out, which

    # ------------------------------------------------------------------ sky
    def sky(
        self,
        antenna_xyz_m: ArrayLike,
        azimuth_grid_rad: ArrayLike,
        elevation_rad: ArrayLike,
        max_dist_m: float = 500.0,
    ) -> SkyResult:
        """Building blocking, canopy path and wall echo for satellite rays from one antenna.

        Parameters
        ----------
        antenna_xyz_m : (3,)
            Antenna in net XY metres and height above ground.
        azimuth_grid_rad, elevation_rad : (n,)
            Ray directions: grid azimuth (clockwise from +y) and elevation, radians.
        max_dist_m : float
            Horizontal distance beyond which nothing is tested.

        Returns
        -------
        SkyResult
            ``blocked`` when the ray enters a footprint at horizontal distance ``d`` where
            the building is taller than ``z_a + d tan(el)``; ``echo_excess_m`` the smallest
            ``2 d_w cos(el) cos(az - az_n)`` over valid wall echoes (see module docstring).
        """
        xa = np.asarray(antenna_xyz_m, dtype=float).reshape(1, 3)
        az = np.atleast_1d(np.asarray(azimuth_grid_rad, dtype=float))
        el = np.atleast_1d(np.asarray(elevation_rad, dtype=float))
        az, el = np.broadcast_arrays(az, el)
        return self.sky_many(xa, np.zeros(az.size, dtype=np.int64), az, el, max_dist_m)

    @_timed
    def sky_many(
        self,
        antennas_xyz_m: ArrayLike,
        antenna_index: ArrayLike,
        azimuth_grid_rad: ArrayLike,
        elevation_rad: ArrayLike,
        max_dist_m: float = 500.0,
    ) -> SkyResult:
        """:meth:`sky` for the rays of several antennas at once (one call per GNSS epoch).

        Parameters
        ----------
        antennas_xyz_m : (m, 3)
            Antennas in net XY metres and height above ground.
        antenna_index : (n,) int
            Row of ``antennas_xyz_m`` each ray starts from.
        azimuth_grid_rad, elevation_rad : (n,)
            Ray directions (grid azimuth clockwise from +y, elevation), radians.
        max_dist_m : float
            Horizontal distance beyond which nothing is tested.

        Returns
        -------
        SkyResult
            Per ray, exactly what :meth:`sky` gives for that ray from its antenna.
        """
        ants = np.asarray(antennas_xyz_m, dtype=float).reshape(-1, 3)
        ai = np.atleast_1d(np.asarray(antenna_index, dtype=np.int64))
        az = np.atleast_1d(np.asarray(azimuth_grid_rad, dtype=float))
        el = np.atleast_1d(np.asarray(elevation_rad, dtype=float))
        if not (ai.shape == az.shape == el.shape) or ai.ndim != 1:
            raise ValueError(f"antenna_index, azimuth and elevation must be (n,), got {ai.shape}, {az.shape}, {el.shape}")
        n = az.size
        xa = ants[ai] if n else np.zeros((0, 3))
        el_c = np.minimum(np.maximum(el, -np.pi / 2 + 1e-9), np.pi / 2 - 1e-9)  # np.clip without its overhead
        u = np.empty((n, 2))
        u[:, 0], u[:, 1] = np.sin(az), np.cos(az)
        tan_el = np.tan(el_c)
        cos_el = np.cos(el_c)
        p1 = np.empty((n, 3))
        p1[:, :2] = xa[:, :2] + max_dist_m * u
        p1[:, 2] = xa[:, 2] + max_dist_m * tan_el

        t_hit, b_hit = self._building_hits(xa, p1)
        blocked = np.isfinite(t_hit)
        if blocked.any():
            blocker_id = np.where(blocked, self._b_ids[np.maximum(b_hit, 0)] if self._b_ids.size else "", "")
        else:
            blocker_id = np.full(n, "")

        if self._f_h.size:
            path_h = np.zeros(n)
            loss_h = np.zeros(n)
            for a in np.unique(ai):
                sel = np.flatnonzero(ai == a)
                path_h[sel], loss_h[sel] = self._foliage_horizontal(ants[a], u[sel], tan_el[sel], max_dist_m)
            foliage_path_m = path_h / cos_el
            foliage_loss_db = loss_h / cos_el
        else:  # no canopy: 0 / cos(el) = 0
            foliage_path_m = np.zeros(n)
            foliage_loss_db = np.zeros(n)

        echo = np.full(n, np.nan)
        grad = np.full((n, 2), np.nan)
        wall = np.full(n, -1, dtype=np.int64)
        if blocked.any() and self._w_len.size:
            echo, grad, wall = self._sky_echo(ants, ai, az, el_c, blocked, max_dist_m)
        return SkyResult(
            blocked=blocked,
            blocker_id=blocker_id.astype(str),
            foliage_path_m=foliage_path_m,
            foliage_loss_db=foliage_loss_db,
            echo_excess_m=echo,
            echo_gradient_xy=grad,
            echo_wall=wall,
        )

    def _foliage_horizontal(
        self, xa: FloatArray, u: FloatArray, tan_el: FloatArray, max_dist_m: float
    ) -> tuple[FloatArray, FloatArray]:
        """Horizontal length (and length x dB/m) of each ray inside canopy volumes."""
        n = len(u)
        path = np.zeros(n)
        loss = np.zeros(n)
        if self._f_h.size == 0:
            return path, loss

        def reach(ray: NDArray[np.int64], poly: NDArray[np.int64]) -> FloatArray:
            h = self._f_h[poly]
            te = tan_el[ray]
            with np.errstate(divide="ignore", invalid="ignore"):
                d_top = np.where(te > 0.0, (h - xa[2]) / te, np.inf)
            return np.where(xa[2] >= h, 0.0, np.minimum(max_dist_m, d_top))

        # Crossings beyond the tallest canopy's reach contribute nothing: query only up to it.
        d_q = reach(np.arange(n), np.full(n, int(np.argmax(self._f_h))))
        lines = shapely.linestrings(
            np.stack([np.broadcast_to(xa[:2], (n, 2)), xa[:2] + d_q[:, None] * u], axis=1)
        )
        ri, ei = _query_pairs(self._fol_edge_tree, lines, predicate="intersects")
        if ri.size:
            a_rel = self._fa[ei] - xa[:2]
            e = self._fe[ei]
            ur = u[ri]
            side_a = _cross(ur, a_rel)
            side_b = _cross(ur, a_rel + e)
            crosses = (side_a >= 0.0) != (side_b >= 0.0)
            den = _cross(ur, e)
            with np.errstate(divide="ignore", invalid="ignore"):
                t = _cross(a_rel, e) / den
            crosses &= t >= 0.0
            ri, ei, t, den = ri[crosses], ei[crosses], t[crosses], den[crosses]
            poly = self._f_poly[ei]
            dmax = reach(ri, poly)
            # Entering a CCW polygon: the ray crosses the edge from its right to its left,
            # cross(e, u) > 0, i.e. cross(u, e) < 0.
            sign = np.where(den < 0.0, 1.0, -1.0)
            contrib = sign * (dmax - np.minimum(t, dmax))
            path += np.bincount(ri, weights=contrib, minlength=n)
            loss += np.bincount(ri, weights=contrib * self._f_att[poly], minlength=n)
        inside = np.asarray(self._f_tree.query(shapely.Point(xa[:2]), predicate="within"), dtype=np.int64)
        for p in inside:
            dm = reach(np.arange(n), np.full(n, p))
            path += dm
            loss += dm * self._f_att[p]
        return np.maximum(path, 0.0), np.maximum(loss, 0.0)

    def _sky_echo(
        self,
        ants: FloatArray,
        ai: NDArray[np.int64],
        az: FloatArray,
        el: FloatArray,
        blocked: NDArray[np.bool_],
        max_dist_m: float,
    ) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
        """Shortest valid wall-echo excess of each blocked ray (ray ``i`` starts at
        ``ants[ai[i]]``), its gradient with respect to the antenna's XY and its wall
        (:class:`SkyResult`).

        Every (blocked ray, wall) pair is tested exactly (compiled kernel; the module
        docstring's conditions), then the candidates' legs are checked best-first
        (:meth:`_best_reflection`). Worlds with more than ``compiled_pairs_max`` pairs use
        the spatial-index formulation :meth:`_sky_echo_vectorized` (same result).
        """
        n = az.size
        rays = np.flatnonzero(blocked)
        if rays.size * self._w_len.size > self.compiled_pairs_max:
            return self._sky_echo_vectorized(ants, ai, az, el, blocked, max_dist_m)
        ce, se = np.cos(el[rays]), np.sin(el[rays])
        tan_el = se / ce
        xr = ants[ai[rays]]
        s_hx, s_hy = ce * np.sin(az[rays]), ce * np.cos(az[rays])
        ri, excess, r3, far, wi = _sky_echo_candidates_kernel(
            np.ascontiguousarray(ants, dtype=float), ai[rays], s_hx, s_hy, ce, se, tan_el, float(max_dist_m),
            self._wa, self._w_nx, self._w_ny, self._w_dir, self._w_len, self._w_h,
        )
        out = np.full(n, np.nan)
        grad = np.full((n, 2), np.nan)
        wall = np.full(n, -1, dtype=np.int64)
        if ri.size == 0:
            return out, grad, wall
        # _legs_clear(a, r, b) checks a->r and r->b: antenna -> R, then R -> far.
        out[rays], which = self._best_reflection(ri, excess, xr[ri], r3, far, rays.size)
        got = which >= 0
        k, w = ri[which[got]], wi[which[got]]
        nx, ny = self._w_nx[w], self._w_ny[w]
        c2 = 2.0 * (s_hx[k] * nx + s_hy[k] * ny)  # 2 (s . n), c as the kernel computes it
        grad[rays[got], 0], grad[rays[got], 1] = c2 * nx, c2 * ny
        wall[rays[got]] = self._w_plane[w]
        return out, grad, wall

    def _sky_echo_vectorized(
        self,
        ants: FloatArray,
        ai: NDArray[np.int64],
        az: FloatArray,
        el: FloatArray,
        blocked: NDArray[np.bool_],
        max_dist_m: float,
    ) -> tuple[FloatArray, FloatArray, NDArray[np.int64]]:
        """:meth:`_sky_echo` with numpy and the spatial index (reference implementation).

        Candidate walls are screened per antenna first (antenna in front of the wall, wall
        above the antenna, ``d_w tan(el) < h_w - z_a`` for the antenna's lowest ray: exact
        necessary conditions), then each ray is paired only with its antenna's walls sorted
        by ``d_w / (h_w - z_a)`` up to its own bound, and the exact per-ray tests of the
        module docstring select the valid reflections. A wall holding a valid reflection
        point R lies within ``(h_max - z_a) / tan(el)`` of the antenna (``z_R < h_w``), so the
        spatial-index window used for large worlds is a superset as well.
        """
        n = az.size
        rays = np.flatnonzero(blocked)
        ce, se = np.cos(el[rays]), np.sin(el[rays])
        tan_el = se / ce
        ray_ant = ai[rays]
        xr = ants[ray_ant]
        # The reflection point R is at horizontal distance tau cos(el) >= d_w from the antenna
        # and height z_a + tau sin(el) < h_w: only walls within (h_max - z_a) / tan(el).
        radius = np.minimum(max_dist_m, (self._h_max - xr[:, 2]) / np.maximum(tan_el, 1e-12))
        ua, ray_u = np.unique(ray_ant, return_inverse=True)
        order = np.argsort(ray_u, kind="stable")
        first = np.flatnonzero(np.r_[True, ray_u[order][1:] != ray_u[order][:-1]])
        rad_u = np.maximum.reduceat(np.abs(radius[order]), first)
        tan_lo = np.minimum.reduceat(tan_el[order], first)
        xu = ants[ua]
        # Antenna in front of the wall (d_w > 0), wall above the antenna, and the test on d_w
        # below for the antenna's lowest ray (float products are monotonic: only walls that
        # every ray of the antenna rejects are removed).
        wa, wn = self._wa, self._w_n
        if ua.size * self._w_len.size <= self.dense_pairs_max:
            # Small worlds: every (antenna, wall) pair at once; the exact tests select.
            delta_d = (xu[:, 0, None] - wa[None, :, 0]) * wn[None, :, 0] + (xu[:, 1, None] - wa[None, :, 1]) * wn[
                None, :, 1
            ]
            hz_d = self._w_h[None, :] - xu[:, 2, None]
            keep = (delta_d > 0.0) & (hz_d > 0.0) & (delta_d * tan_lo[:, None] < hz_d)
            uj, wj = np.nonzero(keep)
            delta_u, hz_u = delta_d[keep], hz_d[keep]
        else:
            # Square windows (supersets of the discs) per antenna; the tests below are exact.
            uj, wj = _query_pairs(
                self._wall_tree,
                shapely.box(xu[:, 0] - rad_u, xu[:, 1] - rad_u, xu[:, 0] + rad_u, xu[:, 1] + rad_u),
            )
            delta_u = (xu[uj, 0] - wa[wj, 0]) * wn[wj, 0] + (xu[uj, 1] - wa[wj, 1]) * wn[wj, 1]
            hz_u = self._w_h[wj] - xu[uj, 2]
            keep = (delta_u > 0.0) & (hz_u > 0.0) & (delta_u * tan_lo[uj] < hz_u)
            uj, wj, delta_u, hz_u = uj[keep], wj[keep], delta_u[keep], hz_u[keep]
        # Per antenna, walls by d_w / (h_w - z_a); a ray of elevation el needs that ratio
        # below 1 / tan(el) (test below): pair each ray with the prefix of its antenna's walls
        # up to a slightly larger bound (a superset; the exact test follows).
        # One ascending key per (antenna, ratio) block (fl(+) is monotonic, so a key above a
        # ray's threshold has a ratio above its bound).
        key = uj * 4.0 + np.minimum(delta_u / hz_u, 2.0)
        srt = np.argsort(key, kind="stable")
        uj, wj, delta_u, hz_u, key = uj[srt], wj[srt], delta_u[srt], hz_u[srt], key[srt]
        block = np.searchsorted(uj, np.arange(ua.size + 1))
        thr = ray_u * 4.0 + np.minimum((1.0 + 1e-9) / tan_el, 2.0)
        rep = np.searchsorted(key, thr, side="right") - block[ray_u]
        ray_pair = np.repeat(np.arange(rays.size), rep)
        offs = np.arange(ray_pair.size) - np.repeat(np.cumsum(rep) - rep, rep)
        pair = block[ray_u[ray_pair]] + offs
        ri = ray_pair
        wi = wj[pair]
        if wi.size == 0:
            return np.full(n, np.nan), np.full((n, 2), np.nan), np.full(n, -1, dtype=np.int64)
        s_hx, s_hy = ce * np.sin(az[rays]), ce * np.cos(az[rays])
        nx, ny = self._w_nx[wi], self._w_ny[wi]
        c = s_hx[ri] * nx + s_hy[ri] * ny  # s . n
        # Necessary for z_R < h_w: d_w tan(el) <= tau cos(el) tan(el) = z_R - z_a < h_w - z_a.
        ok = (c > 0.0) & (delta_u[pair] * tan_el[ri] < hz_u[pair])
        ri, wi, c, dw, nx, ny = ri[ok], wi[ok], c[ok], delta_u[pair[ok]], nx[ok], ny[ok]
        tau = dw / c
        # R = x_a + tau (s - 2 (s . n) n), on the wall segment (one coordinate per array).
        rx = xr[ri, 0] + tau * (s_hx[ri] - 2.0 * c * nx)
        ry = xr[ri, 1] + tau * (s_hy[ri] - 2.0 * c * ny)
        s_wall = ((rx - self._wa[wi, 0]) * self._w_dir[wi, 0] + (ry - self._wa[wi, 1]) * self._w_dir[wi, 1]) / (
            self._w_len[wi]
        )
        ok = (s_wall >= 0.0) & (s_wall <= 1.0)
        ri, wi, c, dw, tau, rx, ry = ri[ok], wi[ok], c[ok], dw[ok], tau[ok], rx[ok], ry[ok]
        nx, ny = nx[ok], ny[ok]
        z_r = xr[ri, 2] + tau * se[ri]
        ok = (z_r < self._w_h[wi]) & (tau * ce[ri] <= max_dist_m)
        ri, wi, c, dw, z_r, nx, ny = ri[ok], wi[ok], c[ok], dw[ok], z_r[ok], nx[ok], ny[ok]
        r_h = np.column_stack([rx[ok], ry[ok]])
        s_h = np.column_stack([s_hx, s_hy])  # (r, 2)
        excess = 2.0 * dw * c
        r3 = np.column_stack([r_h, z_r])
        a3 = xr[ri]
        # Incident leg: from R toward the satellite, out to max_dist_m horizontally.
        te = tan_el[ri]
        far = np.column_stack([r_h + max_dist_m * s_h[ri] / ce[ri][:, None], z_r + max_dist_m * te])
        # _legs_clear(a, r, b) checks a->r and r->b: antenna -> R, then R -> far.
        best, which = self._best_reflection(ri, excess, a3, r3, far, rays.size)
        out = np.full(n, np.nan)
        out[rays] = best
        grad = np.full((n, 2), np.nan)
        wall = np.full(n, -1, dtype=np.int64)
        got = which >= 0
        c2 = 2.0 * c[which[got]]
        grad[rays[got], 0], grad[rays[got], 1] = c2 * nx[which[got]], c2 * ny[which[got]]
        wall[rays[got]] = self._w_plane[wi[which[got]]]
        return out, grad, wall

    # ------------------------------------------------------------------ links
    def links(
        self,
        p0_xyz_m: ArrayLike,
        p1_xyz_m: ArrayLike,
        vehicle_boxes: ArrayLike | None = None,
        exclude: ArrayLike | None = None,
    ) -> LinkResult:
        """Blocking and reflection for straight links ``p0 -> p1``.

        Parameters
        ----------
        p0_xyz_m, p1_xyz_m : (m, 3)
            Link end points, net XY metres and height above ground.
        vehicle_boxes : (v, 6), optional
            Rows ``(cx, cy, azimuth_rad, length_m, width_m, height_m)``: box centre, heading
            clockwise from the net's +y axis (the grid azimuth: SUMO's angle, not the true
            azimuth), and size; each box stands on the ground (z in [0, height]).
        exclude : (m, 2) int, optional
            Box rows ignored per link (the end points' own vehicles); -1 = none.

        Returns
        -------
        LinkResult
            See :class:`LinkResult`. A vehicle blocks when the segment passes through its box
            (3-D slab clipping, Liang-Barsky); ties between kinds go to the nearer entry.
        """
        return self.links_many(p0_xyz_m, p1_xyz_m, vehicle_boxes, None, None, exclude)

    @_timed
    def links_many(
        self,
        p0_xyz_m: ArrayLike,
        p1_xyz_m: ArrayLike,
        vehicle_boxes: ArrayLike | None,
        box_first: ArrayLike | None,
        box_set: ArrayLike | None,
        exclude: ArrayLike | None = None,
    ) -> LinkResult:
        """:meth:`links` for links that see different vehicle boxes (the links of many time steps).

        ``vehicle_boxes`` rows ``box_first[g]:box_first[g + 1]`` form box set ``g``; link ``i``
        is tested against set ``box_set[i]`` only, and its ``exclude`` rows (and the returned
        ``blocker_id`` of a vehicle) count from the start of that set. ``box_first`` and
        ``box_set`` None: one set, every row (:meth:`links`). Per link, exactly what
        :meth:`links` gives with that set's boxes.
        """
        p0 = np.atleast_2d(np.asarray(p0_xyz_m, dtype=float))
        p1 = np.atleast_2d(np.asarray(p1_xyz_m, dtype=float))
        if p0.shape != p1.shape or p0.shape[-1] != 3:
            raise ValueError(f"p0 and p1 must both be (m, 3), got {p0.shape} and {p1.shape}")
        m = len(p0)
        t_b, b_idx = self._building_hits(p0, p1)
        t_v, v_idx = _box_hits(p0, p1, vehicle_boxes, exclude, box_first, box_set)
        use_v = t_v < t_b
        t_hit = np.where(use_v, t_v, t_b)
        blocked = np.isfinite(t_hit)
        refl = np.full(m, np.nan)
        if not blocked.any():
            return LinkResult(blocked=blocked, blocker_kind=np.full(m, ""), blocker_id=np.full(m, ""),
                              hit_distance_m=refl.copy(), reflection_excess_m=refl)
        kind = np.where(blocked, np.where(use_v, "vehicle", "building"), "")
        bid = self._b_ids[np.maximum(b_idx, 0)] if self._b_ids.size else np.full(m, "")
        blocker_id = np.where(blocked, np.where(use_v, v_idx.astype(str), bid), "")
        length = np.linalg.norm(p1 - p0, axis=1)
        hit = np.where(blocked, np.where(blocked, t_hit, 0.0) * length, np.nan)
        if self._w_len.size:
            idx = np.flatnonzero(blocked)
            refl[idx] = self._link_reflection(p0[idx], p1[idx])
        return LinkResult(
            blocked=blocked,
            blocker_kind=kind.astype(str),
            blocker_id=blocker_id.astype(str),
            hit_distance_m=hit,
            reflection_excess_m=refl,
        )

    def _link_reflection(self, p0: FloatArray, p1: FloatArray) -> FloatArray:
        """Shortest single-bounce wall reflection excess for each link (NaN if none)."""
        k = len(p0)
        e_max = self.max_reflection_excess_m
        d_h = np.hypot(*(p1[:, :2] - p0[:, :2]).T)
        radius = 0.5 * np.sqrt(e_max * (e_max + 2.0 * d_h))
        # Bounding boxes grown by the radius: a cheap superset; the excess test below is exact.
        lo = np.minimum(p0[:, :2], p1[:, :2]) - radius[:, None]
        hi = np.maximum(p0[:, :2], p1[:, :2]) + radius[:, None]
        li, wi = _query_pairs(self._wall_tree, shapely.box(lo[:, 0], lo[:, 1], hi[:, 0], hi[:, 1]))
        if li.size == 0:
            return np.full(k, np.nan)
        nrm = self._w_n[wi]
        a = self._wa[wi]
        d0 = np.einsum("ij,ij->i", p0[li, :2] - a, nrm)
        d1 = np.einsum("ij,ij->i", p1[li, :2] - a, nrm)
        ok = (d0 > 0.0) & (d1 > 0.0)
        li, wi, nrm, a, d0, d1 = li[ok], wi[ok], nrm[ok], a[ok], d0[ok], d1[ok]
        img = p1[li, :2] - 2.0 * d1[:, None] * nrm
        f = d0 / (d0 + d1)
        r_h = p0[li, :2] + f[:, None] * (img - p0[li, :2])
        z_r = p0[li, 2] + f * (p1[li, 2] - p0[li, 2])
        s_wall = np.einsum("ij,ij->i", r_h - a, self._w_dir[wi]) / self._w_len[wi]
        dz = p1[li, 2] - p0[li, 2]
        dimg = img - p0[li, :2]
        path = np.sqrt(dimg[:, 0] ** 2 + dimg[:, 1] ** 2 + dz**2)
        excess = path - np.linalg.norm(p1[li] - p0[li], axis=1)
        ok = (s_wall >= 0.0) & (s_wall <= 1.0) & (z_r >= 0.0) & (z_r < self._w_h[wi]) & (excess <= e_max)
        li, r_h, z_r, excess = li[ok], r_h[ok], z_r[ok], excess[ok]
        r3 = np.column_stack([r_h, z_r])
        return self._best_reflection(li, excess, p0[li], r3, p1[li], k)[0]


def _box_hits(
    p0: FloatArray,
    p1: FloatArray,
    boxes: ArrayLike | None,
    exclude: ArrayLike | None,
    box_first: ArrayLike | None = None,
    box_set: ArrayLike | None = None,
) -> tuple[FloatArray, NDArray[np.int64]]:
    """First entry parameter t (inf if none) of segments into vehicle boxes, and the box row.

    Slab clipping in each box's frame (forward = (sin a, cos a), left = (-cos a, sin a)):
    the segment is inside on ``t`` in the intersection of ``[0, 1]`` with every axis'
    slab interval; it passes through the box when that interval is non-empty (touching
    a face only does not count). With ``box_first``/``box_set`` (see
    :meth:`OcclusionGeometry.links_many`) segment ``i`` sees only the rows of its set, and
    ``exclude`` and the returned row count from the start of that set. Compiled
    (:func:`_box_hits_kernel`); :func:`_box_hits_vectorized` is the numpy reference.
    """
    m = len(p0)
    if boxes is None or m == 0:  # no boxes, or no links (exclude cannot be reshaped to (0, -1))
        return np.full(m, np.inf), np.full(m, -1, dtype=np.int64)
    bx = np.atleast_2d(np.asarray(boxes, dtype=float))
    if bx.size == 0:
        return np.full(m, np.inf), np.full(m, -1, dtype=np.int64)
    if bx.ndim != 2 or bx.shape[1] != 6:
        raise ValueError(f"vehicle_boxes must be (v, 6), got {bx.shape}")
    if box_first is None:
        first = np.array([0, len(bx)], dtype=np.int64)
        group = np.zeros(m, dtype=np.int64)
    else:
        first = np.asarray(box_first, dtype=np.int64)
        group = np.asarray(box_set, dtype=np.int64).reshape(m)
    ex = (np.full((m, 0), -1, dtype=np.int64) if exclude is None
          else np.ascontiguousarray(np.asarray(exclude, dtype=np.int64).reshape(m, -1)))
    # The trigonometry stays in numpy (its sin/cos, not the compiled libm's).
    return _box_hits_kernel(np.ascontiguousarray(p0, dtype=float), np.ascontiguousarray(p1, dtype=float),
                            np.ascontiguousarray(bx), np.sin(bx[:, 2]), np.cos(bx[:, 2]), first, group, ex)


@njit(**_JIT)
def _box_hits_kernel(p0, p1, bx, sin_a, cos_a, first, group, exclude):  # pragma: no cover - compiled
    """:func:`_box_hits_vectorized` per segment over its own box set, with the same floating-point
    expressions (slab offsets ``rel . u``, ``t = (bound - q0) / dq``, the parallel-slab rule, the
    lowest-row tie break of ``argmin``)."""
    m = p0.shape[0]
    t_first = np.full(m, np.inf)
    row = np.full(m, -1, dtype=np.int64)
    for i in range(m):
        dx, dy, dz = p1[i, 0] - p0[i, 0], p1[i, 1] - p0[i, 1], p1[i, 2] - p0[i, 2]
        lo_row = first[group[i]]
        for j in range(first[group[i] + 1] - lo_row):
            r = lo_row + j
            skip = False
            for c in range(exclude.shape[1]):
                if exclude[i, c] == j:
                    skip = True
            if skip:
                continue
            rx, ry = p0[i, 0] - bx[r, 0], p0[i, 1] - bx[r, 1]
            s, co = sin_a[r], cos_a[r]
            t_lo, t_hi = 0.0, 1.0
            for axis in range(3):
                if axis == 0:  # forward (sin a, cos a)
                    q0, dq, lo, hi = rx * s + ry * co, dx * s + dy * co, -(0.5 * bx[r, 3]), 0.5 * bx[r, 3]
                elif axis == 1:  # left (-cos a, sin a)
                    q0, dq, lo, hi = rx * -co + ry * s, dx * -co + dy * s, -(0.5 * bx[r, 4]), 0.5 * bx[r, 4]
                else:  # height above the ground
                    q0, dq, lo, hi = p0[i, 2], dz, 0.0, bx[r, 5]
                if dq == 0.0:
                    inside = q0 > lo and q0 < hi
                    tmin = -np.inf if inside else np.inf
                    tmax = np.inf if inside else -np.inf
                else:
                    t1 = (lo - q0) / dq
                    t2 = (hi - q0) / dq
                    tmin, tmax = min(t1, t2), max(t1, t2)
                t_lo = max(t_lo, tmin)
                t_hi = min(t_hi, tmax)
            if t_lo < t_hi and t_lo < t_first[i]:
                t_first[i] = t_lo
                row[i] = j
    return t_first, row


def _box_hits_vectorized(
    p0: FloatArray, p1: FloatArray, boxes: ArrayLike | None, exclude: ArrayLike | None
) -> tuple[FloatArray, NDArray[np.int64]]:
    """:func:`_box_hits` over one box set with numpy (reference implementation)."""
    m = len(p0)
    if boxes is None:
        return np.full(m, np.inf), np.full(m, -1, dtype=np.int64)
    bx = np.atleast_2d(np.asarray(boxes, dtype=float))
    if bx.size == 0:
        return np.full(m, np.inf), np.full(m, -1, dtype=np.int64)
    if bx.ndim != 2 or bx.shape[1] != 6:
        raise ValueError(f"vehicle_boxes must be (v, 6), got {bx.shape}")
    v = len(bx)
    fwd = np.column_stack([np.sin(bx[:, 2]), np.cos(bx[:, 2])])
    left = np.column_stack([-np.cos(bx[:, 2]), np.sin(bx[:, 2])])
    rel = p0[:, None, :2] - bx[None, :, :2]  # (m, v, 2)
    d = (p1 - p0)[:, None, :2]
    d = np.broadcast_to(d, rel.shape)
    axes = [
        (np.einsum("mvk,vk->mv", rel, unit), np.einsum("mvk,vk->mv", d, unit), 0.5 * size)
        for unit, size in ((fwd, bx[:, 3]), (left, bx[:, 4]))
    ]
    t_lo = np.zeros((m, v))
    t_hi = np.ones((m, v))
    slabs = [(q0, dq, -half[None, :], half[None, :]) for q0, dq, half in axes]
    z0 = np.broadcast_to(p0[:, 2:3], (m, v))
    dz = np.broadcast_to((p1 - p0)[:, 2:3], (m, v))
    slabs.append((z0, dz, np.zeros((1, v)), bx[None, :, 5]))
    for q0, dq, lo, hi in slabs:
        par = dq == 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (lo - q0) / dq
            t2 = (hi - q0) / dq
        inside = (q0 > lo) & (q0 < hi)
        tmin = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(t1, t2))
        tmax = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(t1, t2))
        t_lo = np.maximum(t_lo, tmin)
        t_hi = np.minimum(t_hi, tmax)
    hit = t_lo < t_hi
    if exclude is not None:
        ex = np.asarray(exclude, dtype=np.int64).reshape(m, -1)
        rows, cols = np.nonzero(ex >= 0)
        hit[rows, ex[rows, cols]] = False
    t_enter = np.where(hit, t_lo, np.inf)
    j = np.argmin(t_enter, axis=1)
    t_first = t_enter[np.arange(m), j]
    return t_first, np.where(np.isfinite(t_first), j, -1)
