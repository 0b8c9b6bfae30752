"""Measurement models of the cluster filter with analytic, sparse Jacobian rows.

Every model returns a :class:`Row` ``(h, idx, val)``: the predicted measurement ``h(x)``
and the nonzero entries of its Jacobian row (state indices ``idx`` and values ``val``).
A row touches at most two vehicle blocks plus optional azimuth / UWB states, so the
filter's scalar update costs O(n) for ``P h^T`` (see :mod:`v2v.estimation.filter`).

Geometry (Petovello et al. section 3.1, "lead vehicle"): the lead's position is a *base*
known from its standalone solution (``GnssGeometry.base_ecef_m``); a non-lead vehicle's
absolute position is ``base + R^T p_v`` with ``p_v`` its relative ENU position and ``R``
the ECEF->ENU rotation at the base. The base error maps into the baseline only as
``|d base| * |baseline| / rho`` (the standard base-error rule of Tang (1996), which the paper
cites; its eq. 7 as printed has a different factor): a few metres of SPP base error on a
300 m baseline to satellites ~2e7 m away give < 0.1 mm, so it is not estimated.
The ENU frame is re-centred on the base each GNSS update; its rotation as the lead
moves (1e-4 rad per km travelled) is not modelled.

All geometry goes through the shared functions of :mod:`v2v.measmodels`, which the
sensors use to generate measurements (one model, two users).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from v2v.estimation import kernels
from v2v.estimation.layout import UWB, StateLayout, uwb_pair_key
from v2v.frames import ecef_to_enu_rotation, ecef_to_geodetic_point, wrap_angle
from v2v.measmodels import (
    bearing_rad,
    range_jacobian,
    range_m,
    range_rate_jacobians,
    range_rate_mps,
)

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


class Row(NamedTuple):
    """Predicted scalar measurement and its sparse Jacobian row."""

    h: float
    idx: I64
    val: F64


@dataclass(frozen=True, kw_only=True)
class GnssGeometry:
    """The lead base for one GNSS epoch.

    ``base_ecef_m`` is the lead's standalone (SPP) position, ``base_vel_ecef_mps`` its
    velocity (only enters SD Doppler through the tiny line-of-sight difference between
    receivers, ~|baseline|/rho = 1e-6, so zero is acceptable).
    """

    base_ecef_m: F64
    base_vel_ecef_mps: F64 = field(default_factory=lambda: np.zeros(3))
    rot_ecef_to_enu: F64 = field(init=False)

    def __post_init__(self) -> None:
        b = np.asarray(self.base_ecef_m, dtype=float).reshape(3)
        object.__setattr__(self, "base_ecef_m", b)
        object.__setattr__(self, "base_vel_ecef_mps", np.asarray(self.base_vel_ecef_mps, dtype=float).reshape(3))
        lat, lon, _ = ecef_to_geodetic_point(*b.tolist())  # one point: scalar math, not array ufuncs
        object.__setattr__(self, "rot_ecef_to_enu", ecef_to_enu_rotation(lat, lon))

    def abs_position(self, rel_enu_m: F64) -> F64:
        """ECEF position of a vehicle at relative ENU position ``rel_enu_m``."""
        return self.base_ecef_m + rel_enu_m @ self.rot_ecef_to_enu

    def abs_velocity(self, rel_vel_enu_mps: F64) -> F64:
        return self.base_vel_ecef_mps + rel_vel_enu_mps @ self.rot_ecef_to_enu


def rel_position(x: F64, layout: StateLayout, v: str) -> F64:
    """Relative ENU position of ``v`` (zeros for the lead)."""
    if v == layout.lead:
        return np.zeros(3)
    return x[layout.position(v)]


def _pos_idx(layout: StateLayout, v: str) -> I64:
    s = layout.position(v)
    return np.arange(s.start, s.stop)


def _vel_idx(layout: StateLayout, v: str) -> I64:
    s = layout.velocity(v)
    return np.arange(s.start, s.stop)


# ----------------------------------------------------------------------- GNSS
def sd_pseudorange(x: F64, layout: StateLayout, geo: GnssGeometry, v: str, sv_v_ecef_m: F64,
                   sv_lead_ecef_m: F64) -> Row:
    """SD pseudorange ``P_v - P_lead`` for one satellite seen by both.

    ``h = rho(base + R^T p_v, sv_v) - rho(base, sv_lead) + clk_v`` (MacGougan (2009) eq. 3.2,
    3.3 with the lead as reference receiver). Jacobian: d/d p_v = -R u_v (unit line of
    sight v->satellite rotated to ENU), d/d clk_v = 1.
    """
    r_v = geo.abs_position(x[layout.position(v)])
    h = float(range_m(r_v, sv_v_ecef_m) - range_m(geo.base_ecef_m, sv_lead_ecef_m)) + x[layout.clock(v)]
    u_enu = geo.rot_ecef_to_enu @ range_jacobian(r_v, sv_v_ecef_m)
    idx = np.append(_pos_idx(layout, v), layout.clock(v))
    return Row(h, idx, np.append(-u_enu, 1.0))


def sd_pseudorange_pair(x: F64, layout: StateLayout, geo: GnssGeometry, a: str, b: str, sv_a_ecef_m: F64,
                        sv_b_ecef_m: F64) -> Row:
    """SD pseudorange ``P_a - P_b`` between two non-lead vehicles (satellite not seen by the lead).

    Petovello et al. section 3.2: relates two relative states.
    ``h = rho_a - rho_b + clk_a - clk_b`` with both positions ``base + R^T p``.
    """
    r_a = geo.abs_position(x[layout.position(a)])
    r_b = geo.abs_position(x[layout.position(b)])
    h = float(range_m(r_a, sv_a_ecef_m) - range_m(r_b, sv_b_ecef_m)) + x[layout.clock(a)] - x[layout.clock(b)]
    u_a = geo.rot_ecef_to_enu @ range_jacobian(r_a, sv_a_ecef_m)
    u_b = geo.rot_ecef_to_enu @ range_jacobian(r_b, sv_b_ecef_m)
    idx = np.concatenate([_pos_idx(layout, a), [layout.clock(a)], _pos_idx(layout, b), [layout.clock(b)]])
    return Row(h, idx, np.concatenate([-u_a, [1.0], u_b, [-1.0]]))


def sd_doppler(x: F64, layout: StateLayout, geo: GnssGeometry, v: str, sv_v_ecef_m: F64, sv_vel_v_ecef_mps: F64,
               sv_lead_ecef_m: F64, sv_vel_lead_ecef_mps: F64) -> Row:
    """SD pseudorange rate ``Pdot_v - Pdot_lead``, m/s.

    ``h = u_v . (vsv - v_v) - u_lead . (vsv - v_base) + drift_v`` with
    ``v_v = v_base + R^T dv_v`` (:func:`v2v.measmodels.range_rate_mps`). Jacobian: d/d dv_v
    = -R u_v, d/d p_v = R (d rate/d r) (line-of-sight rotation, ~2e-4 /s), d/d drift_v = 1.
    """
    r_v = geo.abs_position(x[layout.position(v)])
    v_v = geo.abs_velocity(x[layout.velocity(v)])
    h = float(range_rate_mps(r_v, v_v, sv_v_ecef_m, sv_vel_v_ecef_mps)
              - range_rate_mps(geo.base_ecef_m, geo.base_vel_ecef_mps, sv_lead_ecef_m, sv_vel_lead_ecef_mps))
    h += x[layout.drift(v)]
    d_r, d_v = range_rate_jacobians(r_v, v_v, sv_v_ecef_m, sv_vel_v_ecef_mps)
    rot = geo.rot_ecef_to_enu
    idx = np.concatenate([_pos_idx(layout, v), _vel_idx(layout, v), [layout.drift(v)]])
    return Row(h, idx, np.concatenate([rot @ d_r, rot @ d_v, [1.0]]))


# ----------------------------------------------------------------------- UWB
def uwb_range(x: F64, layout: StateLayout, a: str, b: str, *, use_bias_scale: bool = True) -> Row:
    """UWB two-way range between the antennas of vehicles a and b (either may be the lead).

    ``R = (1 + s) rho_ab + b`` when the pair has bias/scale states and ``use_bias_scale``
    (MacGougan (2009) eq. 3.4-3.5 with kappa = 1 + s, beta = b), else ``R = rho_ab``
    (Petovello et al. eq. 1). Jacobian: d/d p_b = (1 + s) u_ab = -d/d p_a, d/d b = 1,
    d/d s = rho_ab.
    """
    d = rel_position(x, layout, b) - rel_position(x, layout, a)
    dx, dy, dz = d.tolist()
    rho = math.sqrt(dx * dx + dy * dy + dz * dz)  # = range_m(p_a, p_b), same arithmetic
    u = d / rho  # = range_jacobian(p_a, p_b)
    pair = uwb_pair_key(a, b)
    has = use_bias_scale and layout.has(UWB, pair)
    k = 1.0 + x[layout.uwb_scale(pair)] if has else 1.0
    h = k * rho + (x[layout.uwb_bias(pair)] if has else 0.0)
    idx_l: list[I64] = []
    val_l: list[F64] = []
    if a != layout.lead:
        idx_l.append(_pos_idx(layout, a))
        val_l.append(-k * u)
    if b != layout.lead:
        idx_l.append(_pos_idx(layout, b))
        val_l.append(k * u)
    if has:
        idx_l.append(np.array([layout.uwb_bias(pair), layout.uwb_scale(pair)]))
        val_l.append(np.array([1.0, rho]))
    return Row(h, np.concatenate(idx_l), np.concatenate(val_l))


# ----------------------------------------------------------------------- bearing
def bearing(x: F64, layout: StateLayout, a: str, b: str, azimuth_a_rad: float | None = None) -> Row:
    """Bearing from vehicle a to b relative to a's heading (Petovello et al. eq. 5-6).

    ``beta = atan2(dE_ab, dN_ab) - alpha_a`` with ``d_ab = p_b - p_a`` (lead at the origin).
    ``azimuth_a_rad`` given: azimuth known (``Bearings.azimuth_reported_rad``); ``None``:
    a's azimuth state is used and d beta / d alpha_a = -1. The innovation must be wrapped
    with :func:`bearing_residual`.
    """
    d = rel_position(x, layout, b) - rel_position(x, layout, a)
    if azimuth_a_rad is None:
        alpha = x[layout.azimuth(a)]
    else:
        alpha = float(azimuth_a_rad)
    h = float(bearing_rad(d, alpha))
    e, n, _ = d.tolist()
    r2 = e * e + n * n
    j = np.array([n / r2, -e / r2, 0.0])  # = bearing_jacobian(d), without the array overhead
    idx_l: list[I64] = []
    val_l: list[F64] = []
    if a != layout.lead:
        idx_l.append(_pos_idx(layout, a))
        val_l.append(-j)
    if b != layout.lead:
        idx_l.append(_pos_idx(layout, b))
        val_l.append(j)
    if azimuth_a_rad is None:
        idx_l.append(np.array([layout.azimuth(a)]))
        val_l.append(np.array([-1.0]))
    return Row(h, np.concatenate(idx_l), np.concatenate(val_l))


def bearing_residual(measured_rad: float, predicted_rad: float) -> float:
    """Bearing innovation wrapped to (-pi, pi] (the measurement owns its residual)."""
    return float(wrap_angle(measured_rad - predicted_rad))


def dense_row(row: Row, n: int) -> F64:
    """The Jacobian row as a dense (1, n) array (reference engine and tests)."""
    h = np.zeros((1, n))
    np.add.at(h[0], row.idx, row.val)
    return h


# ----------------------------------------------------------------------- GNSS, one vehicle at once
class SdPseudorangeRows:
    """All SD pseudorange rows of one vehicle for one epoch (vectorized :func:`sd_pseudorange`).

    The lead's ranges do not depend on the state: computed once. :meth:`all` builds every
    row at one state in one numpy step (screening, clock-jump test); :meth:`row` rebuilds
    satellite ``o``'s row at the current state for the sequential update, with the same
    arithmetic as :func:`sd_pseudorange` (the range, ~2e7 m, is differenced against the
    lead's, so ``h`` is computed in exactly the same order to keep it bit-identical).
    Every row has the same ``idx`` (position, clock).
    """

    def __init__(self, layout: StateLayout, geo: GnssGeometry, v: str, sv_v_ecef_m: F64, sv_lead_ecef_m: F64):
        ps = layout.position(v)
        self._ps = ps
        self._clk = layout.clock(v)
        self.idx = np.array([ps.start, ps.start + 1, ps.start + 2, self._clk], dtype=np.int64)
        self._geo = geo
        self._rot = geo.rot_ecef_to_enu
        self._sv = np.ascontiguousarray(sv_v_ecef_m, dtype=np.float64).reshape(-1, 3)
        self._rho_lead = kernels.ranges_from(geo.base_ecef_m, np.ascontiguousarray(sv_lead_ecef_m, dtype=np.float64)
                                             .reshape(-1, 3))  # = range_m(base, sv_lead)
        self._sv_rows: list[F64] | None = None  # per-row views for row(), built on first use
        self._rho_lead_f: list[float] = []

    def __len__(self) -> int:
        return len(self._sv)

    def kernel_args(self) -> tuple:
        """Arguments of :func:`v2v.estimation.kernels.sd_pseudorange_batch` after ``(x, P)``:
        base position (ECEF), R, position slice start, clock index, satellite positions
        (m, 3) and the lead's ranges (m,)."""
        return (self._geo.base_ecef_m, self._rot, self._ps.start, self._clk, self._sv, self._rho_lead)

    def all(self, x: F64) -> tuple[F64, F64]:
        """(h (m,), val (m, 4)) of every row at state ``x`` (compiled:
        :func:`v2v.estimation.kernels.sd_pseudorange_rows`, the arithmetic of the batch update)."""
        x = np.ascontiguousarray(x, dtype=np.float64)
        return kernels.sd_pseudorange_rows(x, self._geo.base_ecef_m, self._rot, self._ps.start, self._clk, self._sv,
                                           self._rho_lead, float(x[self._clk]))

    def row(self, x: F64, o: int) -> Row:
        """Row of satellite ``o`` at state ``x`` (same as :func:`sd_pseudorange`)."""
        if self._sv_rows is None:
            self._sv_rows = [s for s in self._sv]
            self._rho_lead_f = self._rho_lead.tolist()
        r_v = self._geo.abs_position(x[self._ps])
        d = self._sv_rows[o] - r_v
        dx, dy, dz = d.tolist()
        rho = math.sqrt(dx * dx + dy * dy + dz * dz)
        h = float(rho - self._rho_lead_f[o]) + x[self._clk]
        val = np.empty(4)
        val[:3] = self._rot @ (d / rho)
        np.negative(val[:3], out=val[:3])
        val[3] = 1.0
        return Row(h, self.idx, val)


class SdDopplerRows:
    """All SD Doppler rows of one vehicle for one epoch (vectorized :func:`sd_doppler`).

    Rows have ``idx`` (position, velocity, drift); the lead's range rates are computed once.
    """

    def __init__(self, layout: StateLayout, geo: GnssGeometry, v: str, sv_v_ecef_m: F64, sv_vel_v_ecef_mps: F64,
                 sv_lead_ecef_m: F64, sv_vel_lead_ecef_mps: F64):
        ps, vs = layout.position(v), layout.velocity(v)
        self._ps, self._vs = ps, vs
        self._drift = layout.drift(v)
        self.idx = np.array([*range(ps.start, ps.stop), *range(vs.start, vs.stop), self._drift], dtype=np.int64)
        self._geo = geo
        self._rot = geo.rot_ecef_to_enu
        self._sv = np.ascontiguousarray(sv_v_ecef_m, dtype=np.float64).reshape(-1, 3)
        self._svv = np.ascontiguousarray(sv_vel_v_ecef_mps, dtype=np.float64).reshape(-1, 3)
        self._rate_lead = kernels.range_rates_from(  # = range_rate_mps(base, base_vel, sv_lead, svv_lead)
            geo.base_ecef_m, geo.base_vel_ecef_mps, np.ascontiguousarray(sv_lead_ecef_m, dtype=np.float64).reshape(-1, 3),
            np.ascontiguousarray(sv_vel_lead_ecef_mps, dtype=np.float64).reshape(-1, 3))
        self._sv_rows: list[F64] | None = None  # per-row views for row(), built on first use
        self._svv_rows: list[F64] = []
        self._rate_lead_f: list[float] = []

    def __len__(self) -> int:
        return len(self._sv)

    def all(self, x: F64) -> tuple[F64, F64]:
        """(h (m,), val (m, 7)) of every row at state ``x`` (compiled:
        :func:`v2v.estimation.kernels.sd_doppler_rows`, the arithmetic of the batch update)."""
        return kernels.sd_doppler_rows(np.ascontiguousarray(x, dtype=np.float64), *self.kernel_args())

    def kernel_args(self) -> tuple:
        """Arguments of :func:`v2v.estimation.kernels.sd_doppler_batch` after ``(x, P)``:
        base position/velocity (ECEF), R (ECEF->ENU), position/velocity slice starts, drift
        index, satellite positions/velocities (m, 3) and the lead's range rates (m,)."""
        return (self._geo.base_ecef_m, self._geo.base_vel_ecef_mps, self._rot, self._ps.start, self._vs.start,
                self._drift, self._sv, self._svv, self._rate_lead)

    def row(self, x: F64, o: int) -> Row:
        """Row of satellite ``o`` at state ``x``: :func:`sd_doppler`'s arithmetic
        (:func:`v2v.measmodels.range_rate_mps`, :func:`~v2v.measmodels.range_rate_jacobians`)
        on one satellite without the per-call array overhead."""
        if self._sv_rows is None:
            self._sv_rows = [s for s in self._sv]
            self._svv_rows = [s for s in self._svv]
            self._rate_lead_f = self._rate_lead.tolist()
        r_v = self._geo.abs_position(x[self._ps])
        v_v = self._geo.abs_velocity(x[self._vs])
        d = self._sv_rows[o] - r_v
        dx, dy, dz = d.tolist()
        rho = math.sqrt(dx * dx + dy * dy + dz * dz)
        u = d / rho
        dv = self._svv_rows[o] - v_v
        ux, uy, uz = u.tolist()
        wx, wy, wz = dv.tolist()
        rate = ux * wx + uy * wy + uz * wz
        h = float(rate - self._rate_lead_f[o]) + x[self._drift]
        val = np.empty(7)
        val[0:3] = self._rot @ (-(dv - u * rate) / rho)
        val[3:6] = self._rot @ -u
        val[6] = 1.0
        return Row(h, self.idx, val)
