"""UWB two-way time-of-flight ranging radios (MacGougan 2009, ch. 2; Petovello et al. §2.1, §5.4).

Measurement model
-----------------
One two-way range from requester ``a`` to responder ``b`` (Petovello et al. eq. 1 with the
error terms of MacGougan ch. 2)::

    range_m = rho(t_log) + sync + nlos + bias + scale + walk + multipath + noise + quantization

with, per component (all metres, keys of ``UwbRanges.errors_m``):

``sync``
    ``rho(t_true) - rho(t_log)``: the logged time tag ``t_log = t_true + N(0, sigma_tag)`` is wrong
    (the paper's radios were time-tagged by a logging PC, §4), so a filter that evaluates its
    prediction at ``t_log`` sees an error of about ``-(d rho / dt) * (t_log - t_true)``.
``nlos``
    When the direct path is blocked the radio measures the first detectable reflection
    (MacGougan §2.8, fig. 2.14; §2.11.3): the reflection's excess path length, else no range.
``bias``
    Turn-around-time bias ``1/2 (e_A - e_B) t_ta c`` (MacGougan eq. 2.25; the tiny
    ``-1/2 e_A e_B t_ta`` term of eq. 2.24 is kept), a fixed hardware bias and a random walk per
    unit from oscillator drift with temperature (§2.6 last paragraph; §4.2.1: 6 cm in ~15 min).
``scale``
    Oscillator scale factor ``e_A * path`` (eq. 2.25, requester only).
``walk``
    Geometric-walk scale factor ``kappa * path`` of the threshold (leading-edge) detectors
    (§2.7, measured 2300-4700 ppm in §2.11.1); ``kappa = (kappa_A + kappa_B) / 2`` because
    each end's detection delay enters half of the two-way time of flight.
``multipath``
    Residual time-correlated error after the first-order trend (§2.12, fig. 2.30): a
    first-order Gauss-Markov process per pair, ``x_k = phi x_{k-1} + sqrt(1 - phi^2) sigma w``
    with ``phi = exp(-dt/tau - |d rho|/L)`` (it "decorrelates during motion", §2.12), clipped at
    half the pulse width (the largest delay error undistinguishable multipath can cause, §2.8).
``noise``
    White timing jitter, ``sigma(d) = sigma_ref (d / d_ref)^n``; ``n = 1`` is the free-space
    CRLB scaling (eq. 2.2: sigma_tau ~ 1/sqrt(SNR), SNR ~ 1/d^2), ``n = 0`` constant.
``quantization``
    The output is rounded to a step (MSSI: 0.5 ns of range, about 0.15 m, §2.9).

``path = rho(t_true) + nlos`` is the propagated distance. ``true_range_m`` of the record is
``rho(t_log)``, i.e. the truth at the logged time tag the filter will use; the truth at the true
measurement instant ``true_t_s`` is ``true_range_m + errors_m["sync"]``.

Geometry and timing
-------------------
Ranges are computed in WGS-84 ECEF between antenna positions; occlusion is tested in net XY
(plus height), where the occlusion module works. Truth between SUMO steps is interpolated
linearly in position (ECEF and net XY) and azimuth; a vehicle has no truth across a gap of more
than twice the median step interval. Ranging attempts of each pair form a renewal process with
gamma-distributed intervals (mean ``1 / rate_hz``, shape ``k``: ``k = 1`` Poisson, ``k = inf``
regular), as the MSSI radios delivered "3 Hz (average)" irregularly (Petovello et al. table 2).

References
----------
MacGougan, G. D. (2009). *Real-Time Kinematic Surveying using Tightly-Coupled GPS and
Ultra-Wideband Ranging*, PhD thesis, UCGE Report 20293, University of Calgary, ch. 2 and 4.
Petovello, M. G., O'Keefe, K., Chan, B., Spiller, S., Pedrosa, C., Xie, P., Basnayake, C.
*Demonstration of inter-vehicle UWB ranging to augment DGPS for improved relative positioning*.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import ArrayLike, NDArray

from v2v.errors import UserError
from v2v.sensors.measurements import SPEED_OF_LIGHT_MPS, UwbRanges
from v2v.traffic.snapshot import TrafficStep

F64 = NDArray[np.float64]

ERROR_KEYS = ("bias", "scale", "walk", "multipath", "nlos", "noise", "sync", "quantization")
"""Keys of ``UwbRanges.errors_m`` written by this module (their sum is ``range_m - true_range_m``)."""


# ---------------------------------------------------------------------------------------------
# Two-way time-of-flight physics
# ---------------------------------------------------------------------------------------------


def two_way_tof_error(
    range_m: ArrayLike, turnaround_s: ArrayLike, ppm_a: ArrayLike, ppm_b: ArrayLike
) -> tuple[F64, F64, F64]:
    """Range error of two-way time-of-flight ranging from oscillator errors (MacGougan eq. 2.21-2.25).

    The requester A times the round trip with its clock (eq. 2.22),
    ``t_rt = (1 + e_A)(2 t_f + t_ta_true)``; the responder B waits its *perceived* design
    turn-around time, so ``t_ta_true = t_ta / (1 + e_B)`` (eq. 2.23, used here exactly); A
    estimates ``t_f_hat = (t_rt - t_ta) / 2`` (eq. 2.21). The error (eq. 2.24-2.25) is::

        c (t_f_hat - t_f) ~= e_A * rho  +  1/2 (e_A - e_B) t_ta c
                             (scale)        (turn-around-time bias)

    Parameters
    ----------
    range_m : true distance ``rho = c t_f``, metres.
    turnaround_s : design turn-around time ``t_ta`` of the responder, seconds.
    ppm_a, ppm_b : frequency errors ``e_A``, ``e_B`` of requester and responder, ppm
        (positive = the oscillator runs fast, so it measures time intervals too long).

    Returns
    -------
    bias_m : ``1/2 (e_A - e_B) t_ta c`` (eq. 2.25 second term).
    scale_m : ``e_A rho`` (eq. 2.25 first term).
    total_m : the exact error ``c (t_f_hat - t_f)`` from eq. 2.21-2.23 (differs from
        ``bias + scale`` by the second-order ``-1/2 e_A e_B t_ta c`` of eq. 2.24 and the
        ``1/(1 + e_B)`` expansion: micrometres for tens of ppm).

    Examples
    --------
    MacGougan §2.6: 0.333 us (99.83 m), t_ta = 205 us, +20 / -20 ppm gives about 1.231 m, of
    which 1.229 m is the turn-around bias and 2 mm the scale term.
    """
    rho = np.asarray(range_m, dtype=float)
    t_ta = np.asarray(turnaround_s, dtype=float)
    e_a = np.asarray(ppm_a, dtype=float) * 1e-6
    e_b = np.asarray(ppm_b, dtype=float) * 1e-6
    c = SPEED_OF_LIGHT_MPS
    t_f = rho / c
    t_ta_true = t_ta / (1.0 + e_b)  # eq. 2.23 before the first-order expansion
    t_rt = (1.0 + e_a) * (2.0 * t_f + t_ta_true)  # eq. 2.22
    t_f_hat = 0.5 * (t_rt - t_ta)  # eq. 2.21
    total_m = c * (t_f_hat - t_f)
    bias_m = 0.5 * (e_a - e_b) * t_ta * c
    scale_m = e_a * rho
    return bias_m, scale_m, total_m


# ---------------------------------------------------------------------------------------------
# Radio profiles
# ---------------------------------------------------------------------------------------------


def _uwb_field(name: str) -> str:
    return f"uwb.{name}"


@dataclass(frozen=True, kw_only=True)
class UwbRadioProfile:
    """Hardware parameters of one UWB ranging radio type (all SI units).

    Per-unit values (oscillator error, walk scale factor) are *drawn* from the spreads given
    here when a :class:`UwbNetwork` is built; the rest apply to every unit of the type.

    Attributes
    ----------
    name : profile name.
    oscillator_ppm_max : each unit's frequency error ``e`` is uniform in ``[-max, +max]`` ppm.
    turnaround_s : design turn-around time ``t_ta`` (eq. 2.21).
    walk_ppm_min, walk_ppm_max : each unit's geometric-walk scale factor is uniform in this range, ppm.
    fixed_bias_m : constant range bias common to all pairs of this type (cable/antenna delays).
    bias_drift_m_per_sqrt_s : random-walk strength of a *pair's* bias from oscillator drift;
        each unit carries ``1/sqrt(2)`` of it (A adds, B subtracts, as in eq. 2.25).
    noise_sigma_m, noise_ref_range_m, noise_range_exponent : white noise
        ``sigma(d) = noise_sigma_m * (max(d, 1 m) / noise_ref_range_m) ** noise_range_exponent``.
    multipath_sigma_m, multipath_tau_s, multipath_decorrelation_m, multipath_max_m : first-order
        Gauss-Markov residual error (§2.12): steady-state sigma, time constant, range change that
        decorrelates it, and clip at half the pulse width (§2.8).
    quantization_m : output step (0 = none).
    max_range_m : no range beyond this propagated path length.
    rate_hz : mean ranging attempt rate per pair.
    timing_shape : gamma shape ``k`` of the attempt intervals (1 = exponential, ``inf`` = regular).
    time_tag_sigma_s : std of the logged time-tag error.
    packet_loss_probability : probability that an attempt yields nothing.
    nlos_detection_probability : probability that a blocked link with a reflection yields a
        (reflected, long) range; a blocked link without a reflection never does.
    """

    name: str
    oscillator_ppm_max: float
    turnaround_s: float
    walk_ppm_min: float
    walk_ppm_max: float
    fixed_bias_m: float = 0.0
    bias_drift_m_per_sqrt_s: float = 0.0
    noise_sigma_m: float = 0.0
    noise_ref_range_m: float = 50.0
    noise_range_exponent: float = 0.0
    multipath_sigma_m: float = 0.0
    multipath_tau_s: float = 5.0
    multipath_decorrelation_m: float = math.inf
    multipath_max_m: float = math.inf
    quantization_m: float = 0.0
    max_range_m: float = math.inf
    rate_hz: float = 3.0
    timing_shape: float = math.inf
    time_tag_sigma_s: float = 0.0
    packet_loss_probability: float = 0.0
    nlos_detection_probability: float = 0.0

    def __post_init__(self) -> None:
        nonneg = (
            "oscillator_ppm_max",
            "turnaround_s",
            "walk_ppm_min",
            "bias_drift_m_per_sqrt_s",
            "noise_sigma_m",
            "noise_range_exponent",
            "multipath_sigma_m",
            "quantization_m",
            "time_tag_sigma_s",
        )
        positive = (
            "noise_ref_range_m",
            "multipath_tau_s",
            "multipath_decorrelation_m",
            "multipath_max_m",
            "max_range_m",
            "rate_hz",
            "timing_shape",
        )
        for f in fields(self):
            if f.name == "name":
                continue
            v = getattr(self, f.name)
            if not isinstance(v, int | float) or math.isnan(v):
                raise UserError(f"must be a number, got {v!r}", field=_uwb_field(f.name), fix="give a number")
        for n in nonneg:
            if getattr(self, n) < 0.0:
                raise UserError(
                    f"must be >= 0, got {getattr(self, n)!r}", field=_uwb_field(n), fix="use a non-negative value"
                )
        for n in positive:
            if not getattr(self, n) > 0.0:
                raise UserError(
                    f"must be > 0, got {getattr(self, n)!r}", field=_uwb_field(n), fix="use a positive value"
                )
        if self.walk_ppm_max < self.walk_ppm_min:
            raise UserError(
                f"walk_ppm_max ({self.walk_ppm_max}) < walk_ppm_min ({self.walk_ppm_min})",
                field=_uwb_field("walk_ppm_max"),
                fix="give walk_ppm_min <= walk_ppm_max",
            )
        for n in ("packet_loss_probability", "nlos_detection_probability"):
            p = getattr(self, n)
            if not 0.0 <= p <= 1.0:
                raise UserError(f"must be in [0, 1], got {p!r}", field=_uwb_field(n), fix="give a probability")
        for n in ("oscillator_ppm_max", "turnaround_s", "walk_ppm_max", "fixed_bias_m", "rate_hz"):
            if math.isinf(getattr(self, n)):
                raise UserError("must be finite", field=_uwb_field(n), fix="give a finite value")

    def noise_sigma_at(self, path_m: ArrayLike) -> F64:
        """White-noise std at a propagated path length, metres (see class docstring)."""
        d = np.maximum(np.asarray(path_m, dtype=float), 1.0)
        return self.noise_sigma_m * (d / self.noise_ref_range_m) ** self.noise_range_exponent


_C_HALF_NS_M = 0.5e-9 * SPEED_OF_LIGHT_MPS  # 0.1499 m

MSSI = UwbRadioProfile(
    name="mssi",
    # |bias| < 0.5 m measured (§2.11.1, §7) with t_ta = 205 us: |e_A - e_B| <= 16 ppm -> +-8 ppm.
    oscillator_ppm_max=8.0,
    turnaround_s=205e-6,  # §2.6: "the 205 us turn-around-time is used by the Multi-spectral Solutions" radio
    walk_ppm_min=3900.0,  # §2.11.1 static LOS line fits 3900-4700 ppm (dynamic cold test: >2x, §2.11.2)
    walk_ppm_max=4700.0,
    fixed_bias_m=0.0,
    bias_drift_m_per_sqrt_s=0.002,  # §4.2.1: bias changed ~6 cm in ~15 min (MSSI): 0.06 / sqrt(900)
    # §2.11.2: detrended dynamic errors std 9 cm = sqrt(noise^2 + multipath^2 + step^2 / 12)
    # = sqrt(0.06^2 + 0.05^2 + 0.043^2) = 0.089 m; §2.9 "precision better than 15 cm".
    noise_sigma_m=0.06,
    multipath_sigma_m=0.05,
    multipath_tau_s=5.0,  # fig. 2.30 shows correlation over a static period; no number given: assumed
    multipath_decorrelation_m=1.0,  # §2.12 "decorrelates due to [range change]": assumed 1 m
    multipath_max_m=0.5 * 3e-9 * SPEED_OF_LIGHT_MPS,  # §2.8: half of the ~3 ns pulse (§2.9)
    quantization_m=_C_HALF_NS_M,  # §2.9: output quantized to 0.5 ns (~15 cm)
    max_range_m=100.0,  # §2.11.1: "most of the MSSI pairs were able to obtain ranges up to 100 m"
    rate_hz=3.0,  # Petovello et al. table 2: "3 Hz (average)"
    timing_shape=4.0,  # irregular timing: interval CV = 1/sqrt(4) = 0.5, assumed
    time_tag_sigma_s=0.020,  # PC time tags synced once via NMEA (Petovello et al. §4): ~20 ms, assumed
    packet_loss_probability=0.02,  # assumed (§2.11.1: outliers < 1 %)
    nlos_detection_probability=1.0,  # §2.11.3: obstructed MSSI pair measured reflections
)

TDC = UwbRadioProfile(
    name="tdc",
    # |bias| < 0.1 m measured (§2.11.1, §7). t_ta is not given for the TDC PulsON 210; with the
    # assumed 100 us, +-3 ppm units give |bias| <= 0.09 m.
    oscillator_ppm_max=3.0,
    turnaround_s=100e-6,
    walk_ppm_min=2300.0,  # §2.11.1 static LOS line fits 2300-3900 ppm
    walk_ppm_max=3900.0,
    fixed_bias_m=0.0,
    bias_drift_m_per_sqrt_s=0.002,  # no TDC figure; MSSI value of §4.2.1 reused
    # §2.9 precision 1-3 cm; §2.11.2 detrended std 3 cm: sqrt(0.025^2 + 0.015^2) = 0.029 m.
    noise_sigma_m=0.025,
    multipath_sigma_m=0.015,
    multipath_tau_s=5.0,
    multipath_decorrelation_m=1.0,
    multipath_max_m=0.5 * 0.23e-9 * SPEED_OF_LIGHT_MPS,  # §2.8 / §2.9: half of the 0.23 ns pulse
    quantization_m=0.0,  # no output quantization reported
    max_range_m=70.0,  # §2.11.1: "consistently obtain ranges up to 70 m"
    rate_hz=1.0,  # §5.2.1: ranges not simultaneous at 5 Hz, counted per 1 Hz; assumed 1 Hz per pair
    timing_shape=4.0,
    time_tag_sigma_s=0.020,
    packet_loss_probability=0.02,
    # §2.11.3: the pair obstructed by a metal sign got 3 ranges in 75 s (at 1 Hz: 3/75).
    nlos_detection_probability=0.04,
)

IDEAL = UwbRadioProfile(
    name="ideal",
    oscillator_ppm_max=0.0,
    turnaround_s=205e-6,
    walk_ppm_min=0.0,
    walk_ppm_max=0.0,
    rate_hz=3.0,
    timing_shape=math.inf,
    nlos_detection_probability=0.0,
)

PROFILES: dict[str, UwbRadioProfile] = {p.name: p for p in (MSSI, TDC, IDEAL)}


def profile_by_name(name: str, field: str = "sensors.uwb.profile") -> UwbRadioProfile:
    """The built-in profile ``"mssi"``, ``"tdc"`` or ``"ideal"``; UserError (naming ``field``) otherwise."""
    try:
        return PROFILES[str(name).lower()]
    except KeyError:
        raise UserError(
            f"unknown UWB radio profile {name!r}",
            field=field,
            fix=f"use one of {', '.join(sorted(PROFILES))}",
        ) from None


# ---------------------------------------------------------------------------------------------
# Truth tracks (interpolation between SUMO steps)
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class _Track:
    t_s: F64  # (n,)
    ecef_m: F64  # (n, 3) radio antenna
    xyz_m: F64  # (n, 3) radio antenna, net XY + height

    def bracket(self, t_s: F64) -> tuple[NDArray[np.intp], F64]:
        """Segment index (clipped, so ends extrapolate) and fraction for linear interpolation."""
        n = self.t_s.shape[0]
        if n == 1:
            return np.zeros(t_s.shape, dtype=np.intp), np.zeros(t_s.shape)
        i = np.minimum(np.maximum(np.searchsorted(self.t_s, t_s, side="right") - 1, 0), n - 2)
        w = (t_s - self.t_s[i]) / (self.t_s[i + 1] - self.t_s[i])
        return i, w

    def valid(self, t_s: F64, max_gap_s: float, br: tuple[NDArray[np.intp], F64] | None = None) -> NDArray[np.bool_]:
        """True where t lies inside the track and its bracketing steps are at most max_gap_s apart
        (``br``: ``bracket(t_s)`` if already known)."""
        n = self.t_s.shape[0]
        inside = (t_s >= self.t_s[0]) & (t_s <= self.t_s[-1])
        if n == 1:
            return inside & (t_s == self.t_s[0])
        i, _ = self.bracket(t_s) if br is None else br
        return inside & ((self.t_s[i + 1] - self.t_s[i]) <= max_gap_s)

    def at(self, t_s: F64, *, with_xyz: bool = True, br: tuple[NDArray[np.intp], F64] | None = None
           ) -> tuple[F64, F64 | None]:
        """Interpolated ECEF and net-XYZ antenna positions (``with_xyz=False``: ECEF only, xyz None;
        ``br``: ``bracket(t_s)`` if already known)."""
        i, w = self.bracket(t_s) if br is None else br
        w = w[:, None]
        j = np.minimum(i + 1, len(self.t_s) - 1)
        ecef = self.ecef_m[i] * (1.0 - w) + self.ecef_m[j] * w
        xyz = self.xyz_m[i] * (1.0 - w) + self.xyz_m[j] * w if with_xyz else None
        return ecef, xyz


def _offset_vectors(
    offset_body_m: F64, azimuth_rad: F64, grid_azimuth_rad: F64, lat_rad: F64, lon_rad: F64
) -> tuple[F64, F64]:
    """Body-frame lever arm (x fwd, y left, z up) to net-XY (+ height) and ECEF vectors, (n, 3) each.

    ENU = x (sin a, cos a, 0) + y (-cos a, sin a, 0) + z (0, 0, 1) (heading_unit_vectors in
    v2v.frames) with ``a`` the true azimuth; net XY the same with the grid azimuth (SUMO's
    angle: the two differ by the projection's grid convergence, ~2.3 deg at a UTM zone's edge;
    the projection's scale, < 1e-3, is neglected).
    """
    x, y, z = offset_body_m

    def horizontal(a: F64) -> tuple[F64, F64]:
        s, c = np.sin(a), np.cos(a)
        return x * s - y * c, x * c + y * s

    gx, gy = horizontal(grid_azimuth_rad)
    xy = np.stack([gx, gy, np.full_like(gx, z)], axis=-1)
    e, n = horizontal(azimuth_rad)
    u = np.full_like(e, z)
    sl, cl, so, co = np.sin(lat_rad), np.cos(lat_rad), np.sin(lon_rad), np.cos(lon_rad)
    ecef = np.stack(
        [-so * e - sl * co * n + cl * co * u, co * e - sl * so * n + cl * so * u, cl * n + sl * u], axis=-1
    )
    return xy, ecef


def _tracks_from_states(rows: Mapping[str, list], offsets: Mapping[str, F64]) -> dict[str, _Track]:
    out: dict[str, _Track] = {}
    for vid, states in rows.items():
        if not states:
            continue
        t = np.array([s.t_s for s in states], dtype=float)
        ecef = np.array([s.ecef_m for s in states], dtype=float)
        xyz = np.array([s.xyz_m for s in states], dtype=float)
        off = offsets.get(vid)
        if off is not None and np.any(off != 0.0):
            az = np.array([s.azimuth_rad for s in states])
            grid_az = np.array([s.grid_azimuth_rad for s in states])
            lat = np.array([s.lat_rad for s in states])
            lon = np.array([s.lon_rad for s in states])
            d_xy, d_ecef = _offset_vectors(off, az, grid_az, lat, lon)
            ecef = ecef + d_ecef
            xyz = xyz + d_xy
        out[vid] = _Track(t_s=t, ecef_m=ecef, xyz_m=xyz)
    return out


def vehicle_boxes(step: TrafficStep) -> tuple[F64, dict[str, int]]:
    """Occluding boxes at one step: cluster vehicles (sorted by id) then ``step.background``.

    Rows ``(cx, cy, grid azimuth, length_m, width_m, height_m)`` in net XY (the grid azimuth
    clockwise from the net's +y axis, as SUMO's ``getAngle`` and ``step.background``); a
    cluster vehicle's centre is its front bumper (SUMO ``getPosition``) moved back by half its
    length along its heading.
    Returns the boxes and the row index of each cluster vehicle.
    """
    ids = sorted(step.vehicles)
    rows = []
    for vid in ids:
        vs = step.vehicles[vid]
        fb = np.asarray(vs.front_bumper_xy_m, dtype=float)
        a = vs.grid_azimuth_rad
        c = fb - 0.5 * vs.length_m * np.array([np.sin(a), np.cos(a)])
        rows.append((c[0], c[1], a, vs.length_m, vs.width_m, vs.height_m))
    cluster = np.array(rows, dtype=float).reshape(-1, 6)
    bg = np.asarray(step.background, dtype=float).reshape(-1, 6)
    return np.vstack([cluster, bg]), {vid: i for i, vid in enumerate(ids)}


def vehicle_boxes_many(steps: Sequence[TrafficStep]) -> tuple[F64, NDArray[np.int64], list[list[str]]]:
    """:func:`vehicle_boxes` of several steps at once (one vectorized pass).

    Returns every step's boxes stacked, ``first`` (steps + 1,) with step ``s``'s rows at
    ``first[s]:first[s + 1]``, and each step's sorted cluster ids (vehicle ``ids[s][i]`` is
    row ``i`` of its step's set). The rows equal :func:`vehicle_boxes`' bit for bit.
    """
    ids = [sorted(st.vehicles) for st in steps]
    states = [st.vehicles[v] for st, vs in zip(steps, ids, strict=True) for v in vs]
    n_v = np.array([len(v) for v in ids], dtype=np.int64)
    bgs = [np.asarray(st.background, dtype=float).reshape(-1, 6) for st in steps]
    n_bg = np.array([len(b) for b in bgs], dtype=np.int64)
    first = np.zeros(len(steps) + 1, dtype=np.int64)
    np.cumsum(n_v + n_bg, out=first[1:])
    out = np.empty((int(first[-1]), 6))
    if states:
        fb = np.array([vs.front_bumper_xy_m for vs in states], dtype=float).reshape(-1, 2)
        a = np.array([vs.grid_azimuth_rad for vs in states], dtype=float)
        size = np.array([(vs.length_m, vs.width_m, vs.height_m) for vs in states], dtype=float)
        c = fb - (0.5 * size[:, :1]) * np.column_stack([np.sin(a), np.cos(a)])
        rows = np.repeat(first[:-1], n_v) + np.arange(a.size) - np.repeat(np.cumsum(n_v) - n_v, n_v)
        out[rows, :2], out[rows, 2], out[rows, 3:] = c, a, size
    if n_bg.any():
        rows = np.repeat(first[:-1] + n_v, n_bg) + np.arange(int(n_bg.sum())) - np.repeat(np.cumsum(n_bg) - n_bg, n_bg)
        out[rows] = np.concatenate(bgs)
    return out, first, ids


# ---------------------------------------------------------------------------------------------
# Network
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True, kw_only=True)
class UwbUnit:
    """One physical radio as drawn for a run: its type and its own oscillator / walk errors."""

    vehicle_id: str
    profile: UwbRadioProfile
    oscillator_ppm: float
    walk_ppm: float


@dataclass(frozen=True, kw_only=True)
class PairErrorModel:
    """Deterministic error model of one requester->responder pair at the start of a run.

    ``range error ~= bias_m + scale * rho`` with ``scale = (oscillator_ppm + walk_ppm) * 1e-6``
    (the line a fit of error vs. range recovers, MacGougan §2.11, Petovello et al. fig. 16).
    ``bias_m`` excludes the bias random walk, which starts at zero.
    """

    a: str
    b: str
    bias_m: float
    oscillator_ppm: float  # requester's e_A
    walk_ppm: float  # (kappa_A + kappa_B) / 2

    @property
    def scale_ppm(self) -> float:
        return self.oscillator_ppm + self.walk_ppm


class UwbNetwork:
    """The UWB radios of one run: which vehicle carries which radio, and which pairs range.

    Parameters
    ----------
    vehicle_ids : vehicles carrying a radio.
    rng : draws each unit's oscillator error and walk scale factor (in ``vehicle_ids`` order).
    profile : radio type of every vehicle (a :class:`UwbRadioProfile` or a built-in name).
    vehicle_profiles : optional per-vehicle override of ``profile``.
    pairs : ``"all"`` (every pair, the earlier vehicle in ``vehicle_ids`` initiates) or a list
        of ``(requester, responder)`` ids. Both radios of a pair must be of one type.
    antenna_offsets_body_m : optional per-vehicle offset of the UWB antenna from the truth
        antenna ``VehicleState.xyz_m`` in the body frame (x forward, y left, z up), metres.
    """

    def __init__(
        self,
        *,
        vehicle_ids: Sequence[str],
        rng: np.random.Generator,
        profile: UwbRadioProfile | str = "mssi",
        vehicle_profiles: Mapping[str, UwbRadioProfile | str] | None = None,
        pairs: str | Sequence[tuple[str, str]] = "all",
        antenna_offsets_body_m: Mapping[str, ArrayLike] | None = None,
    ) -> None:
        ids = [str(v) for v in vehicle_ids]
        if len(set(ids)) != len(ids):
            raise UserError("vehicle ids repeat", field="uwb.vehicles", fix="list each vehicle once")
        known = set(ids)
        default = profile_by_name(profile) if isinstance(profile, str) else profile
        vp = dict(vehicle_profiles or {})
        for vid in vp:
            if vid not in known:
                raise UserError(
                    f"vehicle {vid!r} is not in the run", field="sensors.uwb.vehicle_profiles", fix=f"use one of {ids}"
                )
        offsets: dict[str, F64] = {}
        for vid, off in dict(antenna_offsets_body_m or {}).items():
            if vid not in known:
                raise UserError(
                    f"vehicle {vid!r} is not in the run", field="uwb.antenna_offsets_body_m", fix=f"use one of {ids}"
                )
            o = np.asarray(off, dtype=float)
            if o.shape != (3,) or not np.all(np.isfinite(o)):
                raise UserError(
                    f"offset of {vid!r} must be 3 finite numbers (x fwd, y left, z up), got {off!r}",
                    field="uwb.antenna_offsets_body_m",
                    fix="give [x_m, y_m, z_m]",
                )
            offsets[vid] = o
        self.antenna_offsets_body_m = offsets

        self.units: dict[str, UwbUnit] = {}
        for vid in ids:
            p = vp.get(vid, default)
            p = profile_by_name(p, f'sensors.uwb.vehicle_profiles."{vid}"' if vid in vp else "sensors.uwb.profile") \
                if isinstance(p, str) else p
            osc = float(rng.uniform(-p.oscillator_ppm_max, p.oscillator_ppm_max))
            walk = float(rng.uniform(p.walk_ppm_min, p.walk_ppm_max))
            self.units[vid] = UwbUnit(vehicle_id=vid, profile=p, oscillator_ppm=osc, walk_ppm=walk)

        if isinstance(pairs, str):
            if pairs != "all":
                raise UserError(f"unknown pairs setting {pairs!r}", field="sensors.uwb.pairs", fix='use "all" or a list of pairs')
            pair_list = list(itertools.combinations(ids, 2))
        else:
            pair_list = []
            for pr in pairs:
                if len(pr) != 2:
                    raise UserError(f"pair {pr!r} must name two vehicles", field="sensors.uwb.pairs", fix="give [a, b]")
                a, b = str(pr[0]), str(pr[1])
                for v in (a, b):
                    if v not in known:
                        raise UserError(
                            f"pair ({a!r}, {b!r}) names vehicle {v!r} which has no radio in this run",
                            field="sensors.uwb.pairs",
                            fix=f"use vehicles among {ids}",
                        )
                if a == b:
                    raise UserError(f"pair ({a!r}, {b!r}) ranges a radio to itself", field="sensors.uwb.pairs", fix="use two vehicles")
                if (a, b) not in pair_list and (b, a) not in pair_list:
                    pair_list.append((a, b))
        for a, b in pair_list:
            pa, pb = self.units[a].profile, self.units[b].profile
            if pa.name != pb.name:
                raise UserError(
                    f"vehicles {a!r} ({pa.name}) and {b!r} ({pb.name}) carry radios of different types",
                    field="sensors.uwb.pairs",
                    fix="range only between radios of one type (list the pairs explicitly)",
                )
        self.pairs: tuple[tuple[str, str], ...] = tuple(pair_list)

    def pair_model(self, a: str, b: str) -> PairErrorModel:
        """Bias and scale factor of requester ``a`` to responder ``b`` as drawn for this run."""
        ua, ub = self.units[a], self.units[b]
        # Bias: exact two-way-ranging total minus its scale term at rho = 0 (eq. 2.24).
        _, _, tat = two_way_tof_error(0.0, ub.profile.turnaround_s, ua.oscillator_ppm, ub.oscillator_ppm)
        return PairErrorModel(
            a=a,
            b=b,
            bias_m=float(tat) + ua.profile.fixed_bias_m,
            oscillator_ppm=ua.oscillator_ppm,
            walk_ppm=0.5 * (ua.walk_ppm + ub.walk_ppm),
        )

    # -----------------------------------------------------------------------------------------

    def simulate(
        self, steps: Sequence[TrafficStep], rng: np.random.Generator, occlusion: Any = None
    ) -> UwbRanges:
        """Synthesize every range of the run, sorted by logged time tag.

        Parameters
        ----------
        steps : truth at each SUMO step (``t_s`` increasing).
        rng : random stream of this run's UWB; one child stream is spawned per pair and per
            unit (``Generator.spawn``), so adding a pair leaves the others unchanged.
        occlusion : object with ``links(p0_xyz_m, p1_xyz_m, vehicle_boxes, exclude)`` returning
            ``blocked`` and ``reflection_excess_m`` arrays (v2v.world.occlusion.OcclusionGeometry),
            or None for open space.

        Returns
        -------
        UwbRanges with ``errors_m`` keys :data:`ERROR_KEYS`; ``range_m = true_range_m + sum``.
        The same as one :class:`UwbStream` over the whole run (``t_end_s`` = the last step).
        """
        steps = list(steps)
        if not steps:
            rng.spawn(len(self.pairs) + len(self.units))
            return _empty_ranges()
        stream = self.stream(rng, occlusion=occlusion, t_start_s=steps[0].t_s, t_end_s=steps[-1].t_s)
        parts = [stream.push(steps), stream.finish()]
        return concat_ranges([p for p in parts if p.n])

    def stream(
        self, rng: np.random.Generator, *, occlusion: Any = None, t_start_s: float, t_end_s: float,
        max_gap_s: float | None = None,
    ) -> UwbStream:
        """A chunked synthesizer of this network's ranges over ``[t_start_s, t_end_s]`` (see :class:`UwbStream`)."""
        return UwbStream(self, rng, occlusion=occlusion, t_start_s=t_start_s, t_end_s=t_end_s, max_gap_s=max_gap_s)

    @staticmethod
    def _occlusion_filter(
        cat: dict[str, NDArray[Any]],
        a_ids: NDArray[Any],
        b_ids: NDArray[Any],
        steps: Sequence[TrafficStep],
        t_steps: F64,
        occlusion: Any,
    ) -> NDArray[np.bool_]:
        """Sets cat['nlos'] (reflection excess path) and cat['blocked']; returns the keep mask."""
        n = cat["t_true"].shape[0]
        nlos = np.zeros(n)
        blocked_all = np.zeros(n, dtype=bool)
        keep = cat["present"].copy()
        if occlusion is not None and np.any(keep):
            # Boxes from the step nearest to each attempt's true time.
            k = np.clip(np.searchsorted(t_steps, cat["t_true"]), 0, len(t_steps) - 1)
            k_prev = np.clip(k - 1, 0, len(t_steps) - 1)
            nearer_prev = np.abs(t_steps[k_prev] - cat["t_true"]) < np.abs(t_steps[k] - cat["t_true"])
            k = np.where(nearer_prev, k_prev, k)
            idx = np.flatnonzero(keep)
            if hasattr(occlusion, "links_many"):
                # One query: each attempt against the boxes of its own step.
                used, box_set = np.unique(k[idx], return_inverse=True)
                boxes, first, step_ids = vehicle_boxes_many([steps[int(i)] for i in used])
                # Box row of each end's vehicle in its step (-1 if absent): a table per distinct
                # vehicle set (usually one) over the names of the chunk.
                names, name_inv = np.unique(np.concatenate([a_ids[idx], b_ids[idx]]), return_inverse=True)
                sets: dict[tuple[str, ...], int] = {}
                set_of_step = np.array([sets.setdefault(tuple(v), len(sets)) for v in step_ids], dtype=np.int64)
                table = np.array([[row.get(x, -1) for x in names.tolist()]
                                  for row in ({v: i for i, v in enumerate(ids)} for ids in sets)],
                                 dtype=np.int64).reshape(len(sets), names.size)
                exclude = table[set_of_step[box_set][:, None], name_inv.reshape(2, -1).T]
                res = occlusion.links_many(cat["xyz_a"][idx], cat["xyz_b"][idx], boxes, first, box_set, exclude)
                blocked = np.asarray(res.blocked, dtype=bool)
                blocked_all[idx] = blocked
                nlos[idx] = np.where(blocked, np.asarray(res.reflection_excess_m, dtype=float), 0.0)
            else:
                # group the attempts by step: one stable sort, not a scan of every attempt per step
                # (that scan was O(steps x attempts): ~500 s of a 10-vehicle hour in one call)
                idx = idx[np.argsort(k[idx], kind="stable")]
                bounds = np.flatnonzero(np.diff(k[idx])) + 1
                for sel in np.split(idx, bounds) if idx.size else ():
                    boxes, row = vehicle_boxes(steps[int(k[sel[0]])])
                    exclude = np.array(
                        [[row.get(a, -1), row.get(b, -1)] for a, b in zip(a_ids[sel], b_ids[sel], strict=True)],
                        dtype=np.int64,
                    ).reshape(-1, 2)
                    res = occlusion.links(cat["xyz_a"][sel], cat["xyz_b"][sel], boxes if len(boxes) else None, exclude)
                    blocked = np.asarray(res.blocked, dtype=bool)
                    blocked_all[sel] = blocked
                    nlos[sel] = np.where(blocked, np.asarray(res.reflection_excess_m, dtype=float), 0.0)
            # Blocked: measured only via a reflection, and then only with the detection probability.
            detect = cat["nlos_draw"] < cat["nlos_p"]
            keep &= ~(blocked_all & (np.isnan(nlos) | ~detect))
        nlos = np.where(np.isnan(nlos), 0.0, nlos)
        cat["nlos"] = nlos
        cat["blocked"] = blocked_all
        path = cat["rho_true"] + nlos
        keep &= path <= cat["max_range"]
        return keep


class _Clone:
    """A copy of a generator's state: ``Generator(PCG64)`` positioned like ``g`` (optionally advanced).

    The copy's bit generator is made from a fixed seed sequence and then given ``g``'s whole
    state (the state, increment and buffered 32-bit half): a bit generator made without a seed
    would first read the operating system's entropy (~3.6 us per copy, several copies per UWB
    pair), only to have it overwritten."""

    _SEED = np.random.SeedSequence(0)

    @staticmethod
    def of(g: np.random.Generator, advance: int = 0) -> np.random.Generator:
        bg = type(g.bit_generator)(_Clone._SEED)
        bg.state = g.bit_generator.state
        if advance:
            if not isinstance(bg, np.random.PCG64):  # (the run's streams are default_rng's PCG64)
                raise TypeError(f"UWB random streams must be Generator(PCG64), got {type(bg).__name__}")
            bg.advance(advance)
        return np.random.Generator(bg)


_BLOCK = 4096


class _PairDraws:
    """Every random number of one pair's run, drawn lazily in time order.

    The whole-run synthesis draws, from the pair's generator: the first attempt's phase
    (1 uniform), the renewal intervals (``n_draw`` gammas, doubled until they cover the run),
    then ``n`` uniforms (loss), ``n`` uniforms (NLOS detection), ``n`` normals (time tag),
    ``n`` normals (noise), ``n`` normals (multipath), ``n`` = attempts in the run. A pre-pass
    finds where each block starts in the bit stream (uniform doubles use one 64-bit output
    each, so those blocks are jumps with ``PCG64.advance``; the gamma and normal blocks are
    drawn once and discarded), then one cloned generator per block hands out the numbers of
    each chunk: the draws, and so the ranges, are bit-identical to one whole-run call.
    """

    def __init__(self, g: np.random.Generator, rate_hz: float, shape: float, t0: float, t1: float):
        span = t1 - t0
        self.mean_dt = 1.0 / rate_hz
        self.shape = shape
        self.t1 = t1
        n_exp = span * rate_hz
        n_draw = int(n_exp + 6.0 * math.sqrt(n_exp + 1.0) + 10)
        self.first = t0 + g.random() * self.mean_dt
        while True:  # pre-pass over the renewal batches (as _attempt_times: t = first + cumsum)
            start = _Clone.of(g)
            carry, n, t_last = 0.0, 1 if self.first <= t1 else 0, self.first
            left = n_draw
            while left:
                k = min(left, 65536)
                iv = np.full(k, self.mean_dt) if math.isinf(shape) else g.gamma(shape, self.mean_dt / shape, size=k)
                c = np.cumsum(np.concatenate([[carry], iv]))[1:]
                carry = float(c[-1])
                t = self.first + c
                n += int(np.count_nonzero(t <= t1))
                t_last = float(t[-1])
                left -= k
            if t_last > t1:
                break
            n_draw *= 2
        self.n = n
        self._times_g = start
        self._carry = 0.0  # cumulative sum of the intervals drawn so far
        self._buf = np.array([self.first])  # attempt times drawn but not handed out
        self._made = 1  # attempt times drawn (first included)
        self._lost = _Clone.of(g)
        self._nlos = _Clone.of(g, n)
        tag_g = _Clone.of(g, 2 * n)
        self._tag = _Clone.of(tag_g)
        self.max_tag_z = 0.0
        for k in range(0, n, 65536):
            self.max_tag_z = max(self.max_tag_z, float(np.max(np.abs(tag_g.standard_normal(min(65536, n - k))))))
        self._noise = _Clone.of(tag_g)
        for k in range(0, n, 65536):
            tag_g.standard_normal(min(65536, n - k))
        self._mp = tag_g
        self.done = 0  # attempts handed out

    def take(self, t_limit: float) -> tuple[F64, F64, F64, F64, F64, F64]:
        """The next attempts with true time <= t_limit: times, loss and NLOS uniforms, tag/noise/multipath normals."""
        while self._made < self.n and (self._buf.size == 0 or self._buf[-1] <= t_limit):
            iv = np.full(_BLOCK, self.mean_dt) if math.isinf(self.shape) else self._times_g.gamma(
                self.shape, self.mean_dt / self.shape, size=_BLOCK)
            c = np.cumsum(np.concatenate([[self._carry], iv]))[1:]
            self._carry = float(c[-1])
            self._buf = np.concatenate([self._buf, self.first + c])
            self._made += _BLOCK
        k = min(int(np.searchsorted(self._buf, t_limit, side="right")), self.n - self.done)
        t = self._buf[:k]
        self._buf = self._buf[k:]
        self.done += k
        return (t, self._lost.random(k), self._nlos.random(k), self._tag.standard_normal(k),
                self._noise.standard_normal(k), self._mp.standard_normal(k))


_PAIR_COLUMNS = ("nlos_p", "osc", "walk_k", "max_range", "quant", "noise_sigma", "noise_ref", "noise_exp")
"""Per-pair settings copied to every attempt of the pair (columns of the synthesis, see :func:`_finish_unsorted`)."""


def _pair_constants(net: UwbNetwork) -> dict[str, Any]:
    """Per-pair arrays (index = position in ``net.pairs``) of the settings the synthesis gathers by pair:
    the columns :data:`_PAIR_COLUMNS`, loss probability, time-tag sigma, multipath clip, bias (from
    :meth:`UwbNetwork.pair_model`), and the requester / responder as indices into ``vehicles``."""
    vehicles = list(net.units)
    col = {v: i for i, v in enumerate(vehicles)}
    rows = []
    for a, b in net.pairs:
        p, model = net.units[a].profile, net.pair_model(a, b)
        rows.append((p.nlos_detection_probability, model.oscillator_ppm * 1e-6, model.walk_ppm * 1e-6, p.max_range_m,
                     p.quantization_m, p.noise_sigma_m, p.noise_ref_range_m, p.noise_range_exponent,
                     p.packet_loss_probability, p.time_tag_sigma_s, p.multipath_max_m, model.bias_m))
    vals = np.array(rows, dtype=float).reshape(-1, 12)
    out: dict[str, Any] = dict(zip((*_PAIR_COLUMNS, "loss_p", "tag_sigma", "mp_max", "bias"), vals.T, strict=True))
    out["veh_a"] = np.array([col[a] for a, _ in net.pairs], dtype=np.int64)
    out["veh_b"] = np.array([col[b] for _, b in net.pairs], dtype=np.int64)
    out["vehicles"] = vehicles
    out["names"] = np.array(vehicles, dtype=object)
    return out


class UwbStream:
    """Chunked synthesis of a :class:`UwbNetwork`'s ranges: push the SUMO steps chunk by chunk.

    Each :meth:`push` returns the ranges whose logged time tag can no longer be preceded by a
    later one (``t_s <= complete_until_s``), sorted by logged time tag as one whole-run
    :meth:`UwbNetwork.simulate` sorts them; :meth:`finish` returns the rest. Random draws
    (:class:`_PairDraws`, per-unit bias walk on the step grid) and the multipath Gauss-Markov
    state continue across chunks, so the concatenated output is bit-identical to one call over
    the same ``[t_start_s, t_end_s]`` whatever the chunk length. The truth window kept is the
    last few seconds of steps (plus each vehicle's last two states), so memory does not grow
    with the run.

    Exception: a vehicle that disappears from the traffic and later reappears (a SUMO teleport)
    is extrapolated from its last states during its absence, where the whole-run synthesis
    interpolated across the gap; its ranges there are absent either way, only the multipath
    sequence after its return may differ.
    """

    def __init__(self, net: UwbNetwork, rng: np.random.Generator, *, occlusion: Any, t_start_s: float,
                 t_end_s: float, max_gap_s: float | None = None):
        self.net = net
        self.occlusion = occlusion
        n_pairs = len(net.pairs)
        children = rng.spawn(n_pairs + len(net.units))
        self._unit_rngs = dict(zip(net.units, children[n_pairs:], strict=True))
        self.t0, self.t1 = float(t_start_s), float(t_end_s)
        self._draws: list[_PairDraws] = []
        for (a, _), g in zip(net.pairs, children[:n_pairs], strict=True):
            p = net.units[a].profile
            self._draws.append(_PairDraws(g, p.rate_hz, p.timing_shape, self.t0, self.t1))
        self.max_tag_s = max((d.max_tag_z * net.units[a].profile.time_tag_sigma_s
                              for d, (a, _) in zip(self._draws, net.pairs, strict=True)), default=0.0)
        self.margin_s = 1.0 + 2.0 * self.max_tag_s  # truth kept before the first pending attempt
        self._max_gap_s = max_gap_s
        self._gm: list[tuple[float, float, float] | None] = [None] * n_pairs  # multipath (t, rho, x) carried
        self._consts = _pair_constants(net)
        self._steps: list[TrafficStep] = []  # the truth window
        self._drift: dict[str, list[float]] = {v: [] for v in net.units}
        self._drift_started = False
        self._last_states: dict[str, list] = {v: [] for v in net.units}  # (t, state) before the window
        self._pending: list[dict[str, Any]] = []  # ranges synthesized, not yet complete in t_log order
        self._synth_until = -np.inf  # attempts with t_true <= this are synthesized
        self._seq = 0
        self.complete_until_s = -np.inf

    # -----------------------------------------------------------------------------------------
    def push(self, steps: Sequence[TrafficStep]) -> UwbRanges:
        """Add the next SUMO steps; return the ranges now complete (sorted by ``t_s``)."""
        for st in steps:
            if self._steps and st.t_s - self._steps[-1].t_s <= 0:
                raise UserError("traffic steps are not in increasing time", field="steps", fix="pass steps in time order")
            self._steps.append(st)
        # Per-unit bias random walk on the step grid (whole-run: cumsum of q sqrt(dt) N(0,1)).
        n_new = len(steps)
        if n_new:
            t_all = np.array([s.t_s for s in self._steps[-n_new - 1:]], dtype=float)
            fresh = not self._drift_started
            dt = np.diff(t_all) if not fresh else np.diff(t_all[-n_new:])
            for vid, unit in self.net.units.items():
                q = unit.profile.bias_drift_m_per_sqrt_s / math.sqrt(2.0)
                inc = q * np.sqrt(dt) * self._unit_rngs[vid].standard_normal(dt.shape[0])
                d = self._drift[vid]
                start = [0.0] if fresh else [d[-1]]
                d.extend(np.cumsum(np.concatenate([start, inc]))[0 if fresh else 1:].tolist())
            self._drift_started = True
        if not self._steps:
            return _empty_ranges()
        if self._max_gap_s is None and len(self._steps) > 1:
            self._max_gap_s = 2.0 * float(np.median(np.diff([s.t_s for s in self._steps])))
        t_last = self._steps[-1].t_s
        limit = t_last - self.margin_s
        out = self._advance(limit) if limit > self._synth_until else _empty_ranges()
        return out

    def finish(self) -> UwbRanges:
        """Synthesize the remaining attempts (to ``t_end_s``) and return every pending range."""
        out = self._advance(np.inf, final=True)
        self._steps.clear()
        return out

    # -----------------------------------------------------------------------------------------
    def _advance(self, limit: float, final: bool = False) -> UwbRanges:
        steps = self._steps
        t_steps = np.array([s.t_s for s in steps], dtype=float)
        max_gap_s = self._max_gap_s if self._max_gap_s is not None else 0.0
        tracks = self._tracks(steps)
        drift = {v: np.asarray(d, dtype=float) for v, d in self._drift.items()}
        drawn = [dr.take(limit) for dr in self._draws]
        cat = self._chunk(drawn, tracks, t_steps, max_gap_s, drift)
        self._synth_until = limit
        if cat is not None:
            a_ids, b_ids = cat.pop("a"), cat.pop("b")
            keep = UwbNetwork._occlusion_filter(cat, a_ids, b_ids, steps, t_steps, self.occlusion)
            self._pending.append(_finish_unsorted(cat, a_ids, b_ids, keep, self.net))
        # Ranges whose t_log cannot be preceded by a later attempt's (t_true > limit).
        horizon = np.inf if final else limit - self.max_tag_s - 1e-9
        self.complete_until_s = horizon
        out = self._emit(horizon)
        # Drop the truth not needed by the next chunk (keep the vehicles' last two states).
        if not final:
            cut = limit - self.margin_s
            i = int(np.searchsorted(t_steps, cut, side="left"))
            for st in steps[:i]:
                for vid, vs in st.vehicles.items():
                    if vid in self._last_states:
                        ls = self._last_states[vid]
                        ls.append(vs)
                        if len(ls) > 2:
                            ls.pop(0)
            del self._steps[:i]
            for v in self._drift:
                del self._drift[v][:i]
        return out

    def _tracks(self, steps: Sequence[TrafficStep]) -> dict[str, _Track]:
        rows: dict[str, list] = {v: list(self._last_states[v]) for v in self.net.units}
        for st in steps:
            for vid, vs in st.vehicles.items():
                if vid in rows:
                    rows[vid].append(vs)
        return _tracks_from_states(rows, self.net.antenna_offsets_body_m)

    def _chunk(self, drawn: list[tuple], tracks: dict[str, _Track], t_steps: F64, max_gap_s: float,
               drift: dict[str, F64]) -> dict[str, Any] | None:
        """Geometry and error inputs of the chunk's attempts of every pair, pair-major (one column per key).

        Pairs whose radios have no truth in the window are left out (their draws are used up all
        the same). The truth of each vehicle is interpolated once for all its attempts and the
        per-pair settings are gathered by pair index: elementwise the numbers of a pair-by-pair
        synthesis; only the multipath Gauss-Markov recursion runs pair by pair.
        """
        c = self._consts
        use = [j for j, (a, b) in enumerate(self.net.pairs) if drawn[j][0].shape[0] and a in tracks and b in tracks]
        if not use:
            return None
        n_j = np.array([drawn[j][0].shape[0] for j in use], dtype=np.int64)
        pair = np.repeat(np.array(use, dtype=np.int64), n_j)
        t_true, u_lost, nlos_draw, z_tag, z_noise, z_mp = (np.concatenate([drawn[j][q] for j in use]) for q in range(6))
        attempt = np.concatenate([np.arange(self._draws[j].done - n, self._draws[j].done, dtype=np.int64)
                                  for j, n in zip(use, n_j.tolist(), strict=True)])
        lost = u_lost < c["loss_p"][pair]
        t_log = t_true + c["tag_sigma"][pair] * z_tag
        m = t_true.shape[0]
        present = np.ones(m, dtype=bool)
        ends = []  # (ECEF at t_true, net XYZ at t_true, ECEF at t_log, drift at t_true) of a, then of b
        for side in (c["veh_a"][pair], c["veh_b"][pair]):
            e, x, e_log, dr = np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3)), np.empty(m)
            for vi in np.unique(side).tolist():
                vid = c["vehicles"][vi]
                tr, sel = tracks[vid], np.flatnonzero(side == vi)
                br = tr.bracket(t_true[sel])
                present[sel] &= tr.valid(t_true[sel], max_gap_s, br)
                e[sel], x[sel] = tr.at(t_true[sel], br=br)
                e_log[sel], _ = tr.at(t_log[sel], with_xyz=False)
                dr[sel] = np.interp(t_true[sel], t_steps, drift[vid])
            ends.append((e, x, e_log, dr))
        (ea, xa, ea_l, dr_a), (eb, xb, eb_l, dr_b) = ends
        rho_true = np.linalg.norm(eb - ea, axis=1)
        rho_log = np.linalg.norm(eb_l - ea_l, axis=1)
        mp = np.empty(m)
        lo = 0
        for j, n in zip(use, n_j.tolist(), strict=True):
            sl = slice(lo, lo + n)
            p = self.net.units[self.net.pairs[j][0]].profile
            mp[sl], self._gm[j] = _gauss_markov_cont(t_true[sl], rho_true[sl], z_mp[sl], p.multipath_sigma_m,
                                                    p.multipath_tau_s, p.multipath_decorrelation_m, self._gm[j])
            lo += n
        mp = np.clip(mp, -c["mp_max"][pair], c["mp_max"][pair])
        bias = c["bias"][pair] + dr_a - dr_b
        out = {
            "a": c["names"][c["veh_a"][pair]], "b": c["names"][c["veh_b"][pair]], "pair": pair, "attempt": attempt,
            "t_true": t_true, "t_log": t_log, "rho_true": rho_true, "rho_log": rho_log, "xyz_a": xa, "xyz_b": xb,
            "present": present & ~lost, "nlos_draw": nlos_draw, "z_noise": z_noise, "multipath": mp, "bias": bias,
        }
        out.update({k: c[k][pair] for k in _PAIR_COLUMNS})
        return out

    def _emit(self, horizon: float) -> UwbRanges:
        if not self._pending:
            return _empty_ranges()
        c = {k: np.concatenate([p[k] for p in self._pending]) for k in self._pending[0]}
        # The whole-run order: stable sort by t_log of the pair-major concatenation.
        order = np.lexsort((c["attempt"], c["pair"], c["t_log"]))
        c = {k: v[order] for k, v in c.items()}
        k = int(np.searchsorted(c["t_log"], horizon, side="right"))
        rest = {key: v[k:] for key, v in c.items()}
        self._pending = [rest] if rest["t_log"].size else []
        o = {key: v[:k] for key, v in c.items()}
        return UwbRanges(
            t_s=o["t_log"], true_t_s=o["t_true"], a=tuple(str(x) for x in o["a"]), b=tuple(str(x) for x in o["b"]),
            range_m=o["range"], true_range_m=o["rho_log"], los=~o["blocked"],
            errors_m={key: o["err_" + key] for key in ERROR_KEYS},
        )


def _attempt_times(t0: float, t1: float, rate_hz: float, shape: float, g: np.random.Generator) -> F64:
    """Renewal process on [t0, t1] with gamma(shape, 1/(shape*rate)) intervals and a random phase.

    The first attempt comes a uniform fraction of a mean interval after t0 (the radios were
    not started in step with the simulation). ``shape = inf`` gives a regular 1/rate grid.
    """
    span = t1 - t0
    mean_dt = 1.0 / rate_hz
    n_exp = span * rate_hz
    n_draw = int(n_exp + 6.0 * math.sqrt(n_exp + 1.0) + 10)
    first = t0 + g.random() * mean_dt
    while True:
        if math.isinf(shape):
            intervals = np.full(n_draw, mean_dt)
        else:
            intervals = g.gamma(shape, mean_dt / shape, size=n_draw)
        t = first + np.concatenate([[0.0], np.cumsum(intervals)])
        if t[-1] > t1:
            return t[t <= t1]
        n_draw *= 2


def _gauss_markov(t: F64, rho: F64, z: F64, sigma: float, tau_s: float, decorr_m: float) -> F64:
    """First-order Gauss-Markov samples at irregular times, stationary start (sigma * z[0])."""
    if sigma == 0.0:
        return np.zeros_like(t)
    phi = np.exp(-np.diff(t) / tau_s - np.abs(np.diff(rho)) / decorr_m)
    w = np.sqrt(1.0 - phi * phi) * sigma
    x = np.empty_like(t)
    x[0] = sigma * z[0]
    _gauss_markov_kernel(x[0], phi, w, z[1:], x[1:])
    return x


@njit(cache=True, nogil=True)
def _gauss_markov_kernel(x_prev, phi, w, z, out):  # pragma: no cover - compiled
    """The recursion ``x_k = phi_k x_{k-1} + w_k z_k`` from ``x_prev`` into ``out`` (the Python loop
    it replaces evaluated the same two products and one sum per sample)."""
    for k in range(z.shape[0]):
        x_prev = phi[k] * x_prev + w[k] * z[k]
        out[k] = x_prev


def _gauss_markov_cont(t: F64, rho: F64, z: F64, sigma: float, tau_s: float, decorr_m: float,
                       prev: tuple[float, float, float] | None) -> tuple[F64, tuple[float, float, float] | None]:
    """:func:`_gauss_markov` continued from ``prev = (t, rho, x)`` of the previous chunk's last sample.

    Returns the samples and the state to carry; the samples equal the whole-run recursion's.
    """
    if sigma == 0.0 or t.shape[0] == 0:
        return np.zeros_like(t), prev
    if prev is None:
        x = _gauss_markov(t, rho, z, sigma, tau_s, decorr_m)
    else:
        tt = np.concatenate([[prev[0]], t])
        rr = np.concatenate([[prev[1]], rho])
        phi = np.exp(-np.diff(tt) / tau_s - np.abs(np.diff(rr)) / decorr_m)
        w = np.sqrt(1.0 - phi * phi) * sigma
        x = np.empty_like(t)
        _gauss_markov_kernel(prev[2], phi, w, z, x)
    return x, (float(t[-1]), float(rho[-1]), float(x[-1]))


def _finish_unsorted(
    cat: dict[str, F64], a_ids: NDArray[Any], b_ids: NDArray[Any], keep: NDArray[np.bool_], net: UwbNetwork
) -> dict[str, Any]:
    """The kept attempts' outputs, column by column (elementwise; sorted later by :class:`UwbStream`)."""
    c = {k: v[keep] for k, v in cat.items()}
    nlos = c["nlos"]
    path = c["rho_true"] + nlos
    scale = c["osc"] * path
    walk = c["walk_k"] * path
    sigma = c["noise_sigma"] * (np.maximum(path, 1.0) / c["noise_ref"]) ** c["noise_exp"]
    noise = sigma * c["z_noise"]
    raw = path + c["bias"] + scale + walk + c["multipath"] + noise
    q = c["quant"]
    out = np.where(q > 0.0, np.round(raw / np.where(q > 0.0, q, 1.0)) * q, raw)
    sync = c["rho_true"] - c["rho_log"]
    errors = {
        "bias": c["bias"],
        "scale": scale,
        "walk": walk,
        "multipath": c["multipath"],
        "nlos": nlos,
        "noise": noise,
        "sync": sync,
    }
    # Quantization absorbs the last floating-point rounding so that the sum is exact to ~1e-15 m.
    errors["quantization"] = out - (c["rho_log"] + sum(errors.values()))
    res: dict[str, Any] = {
        "t_log": c["t_log"], "t_true": c["t_true"], "a": a_ids[keep], "b": b_ids[keep], "range": out,
        "rho_log": c["rho_log"], "blocked": c["blocked"], "pair": c["pair"], "attempt": c["attempt"],
    }
    res.update({"err_" + k: errors[k] for k in ERROR_KEYS})
    return res


def concat_ranges(parts: Sequence[UwbRanges]) -> UwbRanges:
    """One :class:`UwbRanges` from consecutive chunks (in the given order)."""
    parts = [p for p in parts if p.n]
    if not parts:
        return _empty_ranges()
    if len(parts) == 1:
        return parts[0]
    return UwbRanges(
        t_s=np.concatenate([p.t_s for p in parts]), true_t_s=np.concatenate([p.true_t_s for p in parts]),
        a=tuple(x for p in parts for x in p.a), b=tuple(x for p in parts for x in p.b),
        range_m=np.concatenate([p.range_m for p in parts]), true_range_m=np.concatenate([p.true_range_m for p in parts]),
        los=np.concatenate([p.los for p in parts]),
        errors_m={k: np.concatenate([p.errors_m[k] for p in parts]) for k in ERROR_KEYS},
    )


def _empty_ranges() -> UwbRanges:
    z = np.zeros(0)
    return UwbRanges(
        t_s=z, true_t_s=z, a=(), b=(), range_m=z, true_range_m=z, los=np.zeros(0, dtype=bool),
        errors_m={k: z for k in ERROR_KEYS},
    )


def select_ranges(ranges: UwbRanges, mask: ArrayLike) -> UwbRanges:
    """The records of ``ranges`` where ``mask`` (bool or index array) selects."""
    m = np.asarray(mask)
    idx = np.flatnonzero(m) if m.dtype == bool else m.astype(np.intp)
    pos = idx.tolist()
    return UwbRanges(
        t_s=ranges.t_s[idx],
        true_t_s=ranges.true_t_s[idx],
        a=tuple([ranges.a[i] for i in pos]),
        b=tuple([ranges.b[i] for i in pos]),
        range_m=ranges.range_m[idx],
        true_range_m=ranges.true_range_m[idx],
        los=ranges.los[idx],
        errors_m={k: v[idx] for k, v in ranges.errors_m.items()},
    )


# ---------------------------------------------------------------------------------------------
# Figures (Petovello et al. figs. 16-17)
# ---------------------------------------------------------------------------------------------


def plot_uwb_error_figures(ranges: UwbRanges, out_dir: str | Path) -> list[Path]:
    """Save the paper's UWB error plots (LOS ranges only) as PNG; returns the file paths.

    ``uwb_error_vs_range.png``: error ``range_m - true_range_m`` vs. true range with a
    least-squares line (bias + scale, Petovello et al. fig. 16, MacGougan fig. 2.18).
    ``uwb_error_vs_10log_d2.png``: the same error vs. ``10 log10(d^2)`` (fig. 17).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    los = np.asarray(ranges.los, dtype=bool)
    d = ranges.true_range_m[los]
    err = ranges.range_m[los] - d
    paths = []
    for name, x, xlabel in (
        ("uwb_error_vs_range.png", d, "true range (m)"),
        ("uwb_error_vs_10log_d2.png", 10.0 * np.log10(np.maximum(d, 1e-3) ** 2), "10 log10(d^2) (dB m^2)"),
    ):
        fig, ax = plt.subplots(figsize=(7, 4.5))
        ax.plot(x, err, ".", ms=2, alpha=0.5, label=f"{err.size} LOS ranges")
        if err.size >= 2:
            slope, intercept = np.polyfit(x, err, 1)
            xs = np.linspace(x.min(), x.max(), 50)
            unit = "ppm" if name == "uwb_error_vs_range.png" else "m/dB"
            s = slope * 1e6 if unit == "ppm" else slope
            ax.plot(xs, intercept + slope * xs, "r-", label=f"fit: {intercept:.3f} m + {s:.4g} {unit}")
        ax.set_xlabel(xlabel)
        ax.set_ylabel("UWB range error (m)")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="best")
        fig.tight_layout()
        p = out / name
        fig.savefig(p, dpi=120)
        plt.close(fig)
        paths.append(p)
    return paths
