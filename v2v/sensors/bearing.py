"""Bearing sensor: horizontal direction of another vehicle relative to one's own heading.

Model (Petovello et al. eq. 3-5)::

    beta_ab = wrap( atan2(dE_ab, dN_ab) - alpha_a + eps ),   eps ~ N(0, sigma_rad^2)

with ``dE, dN`` the a->b antenna vector in the local-level ENU frame *at vehicle a* (computed
from ECEF with :func:`v2v.frames.ecef_to_enu`) and ``alpha_a`` a's true azimuth. The true part
is :func:`v2v.measmodels.bearing_rad`, the same function the filter uses to predict it. The paper
assumed sigma = 0.5 deg (§4.4) and generated its bearings from a reference trajectory (§4.3).

Vehicle a also reports its own azimuth for the azimuth-known case (paper §2.2):
``alpha_reported = alpha_a + b_a(t) + N(0, azimuth_sigma_rad^2)``, where ``b_a`` is an optional
slowly varying first-order Gauss-Markov bias (steady-state std ``azimuth_bias_sigma_rad``, time
constant ``azimuth_bias_tau_s``), one process per measuring vehicle.

A bearing exists when b is within ``max_range_m`` (3-D antenna distance), inside the field of
view ``|beta_true| <= field_of_view_rad / 2``, and the antenna-to-antenna line is not blocked
(v2v.world.occlusion; other vehicles and buildings): the sensor sees nothing through obstacles.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from v2v.errors import UserError
from v2v.frames import wrap_angle
from v2v.measmodels import bearing_rad, range_m
from v2v.sensors.measurements import Bearings
from v2v.sensors.uwb import vehicle_boxes, vehicle_boxes_many
from v2v.traffic.snapshot import TrafficStep


@dataclass(frozen=True, kw_only=True)
class BearingSensor:
    """Bearing sensor settings, the same on every measuring vehicle (SI units, radians).

    Attributes
    ----------
    sigma_rad : bearing noise std (paper §4.4: 0.5 deg).
    field_of_view_rad : total horizontal field of view centred on the forward axis (2 pi = all round).
    max_range_m : farthest vehicle measured.
    rate_hz : measurement rate; the first step at or after each ``1/rate_hz`` tick is used.
        ``None`` measures at every step.
    azimuth_sigma_rad : white noise of the measuring vehicle's reported azimuth (0.1 deg).
    azimuth_bias_sigma_rad, azimuth_bias_tau_s : slowly varying Gauss-Markov azimuth bias.
    measuring : ``"all"`` or the ids of the vehicles that carry the sensor.
    """

    sigma_rad: float = math.radians(0.5)
    field_of_view_rad: float = 2.0 * math.pi
    max_range_m: float = 150.0
    rate_hz: float | None = 10.0
    azimuth_sigma_rad: float = math.radians(0.1)
    azimuth_bias_sigma_rad: float = 0.0
    azimuth_bias_tau_s: float = 300.0
    measuring: str | tuple[str, ...] = "all"

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if f.name == "measuring" or (f.name == "rate_hz" and v is None):
                continue
            if not isinstance(v, int | float) or not math.isfinite(v):
                raise UserError(f"must be a finite number, got {v!r}", field=f"bearing.{f.name}", fix="give a number")
        for n in ("sigma_rad", "azimuth_sigma_rad", "azimuth_bias_sigma_rad"):
            if getattr(self, n) < 0.0:
                raise UserError(f"must be >= 0, got {getattr(self, n)!r}", field=f"bearing.{n}", fix="use a value >= 0")
        for n in ("max_range_m", "azimuth_bias_tau_s"):
            if not getattr(self, n) > 0.0:
                raise UserError(f"must be > 0, got {getattr(self, n)!r}", field=f"bearing.{n}", fix="use a value > 0")
        if self.rate_hz is not None and not self.rate_hz > 0.0:
            raise UserError(
                f"must be > 0, got {self.rate_hz!r}", field="bearing.rate_hz", fix="use a positive rate, or omit it for every step"
            )
        if not 0.0 < self.field_of_view_rad <= 2.0 * math.pi:
            raise UserError(
                f"must be in (0, 2 pi], got {self.field_of_view_rad!r}",
                field="bearing.field_of_view_rad",
                fix="give the total field of view in radians (2 pi = all round)",
            )
        if isinstance(self.measuring, str):
            if self.measuring != "all":
                raise UserError(
                    f"unknown setting {self.measuring!r}", field="sensors.bearing.measuring", fix='use "all" or a list of vehicle ids'
                )
        else:
            object.__setattr__(self, "measuring", tuple(str(v) for v in self.measuring))

    def simulate(self, steps: Sequence[TrafficStep], rng: np.random.Generator, occlusion: Any = None) -> Bearings:
        """Bearings of every measuring vehicle to every other vehicle, over the run.

        Parameters
        ----------
        steps : truth per SUMO step, increasing ``t_s``.
        rng : random stream of this sensor.
        occlusion : object with ``links(p0_xyz_m, p1_xyz_m, vehicle_boxes, exclude)`` returning a
            ``blocked`` array (v2v.world.occlusion.OcclusionGeometry), or None for open space.

        The same as one :class:`BearingStream` fed every step.
        """
        stream = self.stream(rng, occlusion)
        out = stream.push(steps)
        stream.finish()
        return out

    def stream(self, rng: np.random.Generator, occlusion: Any = None) -> BearingStream:
        """A chunked synthesizer (see :class:`BearingStream`)."""
        return BearingStream(self, rng, occlusion)


class BearingStream:
    """Bearings synthesized chunk by chunk: :meth:`push` the next SUMO steps, get their bearings.

    The sensor is per step (rate ticks, azimuth-bias Gauss-Markov state and the random stream
    continue across chunks), so the concatenated output is bit-identical to one
    :meth:`BearingSensor.simulate` over the whole run. :meth:`finish` checks that every listed
    measuring vehicle appeared.
    """

    def __init__(self, sensor: BearingSensor, rng: np.random.Generator, occlusion: Any = None):
        self.sensor = sensor
        self.rng = rng
        self.occlusion = occlusion
        self._last_tick: int | None = None
        self._t0: float | None = None
        self._bias: dict[str, tuple[float, float]] = {}  # vehicle -> (t_s, bias_rad)
        self._seen: set[str] = set()
        self.n = 0

    def finish(self) -> None:
        if not isinstance(self.sensor.measuring, str):
            missing = [v for v in self.sensor.measuring if v not in self._seen]
            if missing:
                raise UserError(
                    f"measuring vehicle(s) {missing} never appear in the traffic",
                    field="sensors.bearing.measuring",
                    fix=f"use ids among {sorted(self._seen)}",
                )

    def push(self, steps: Sequence[TrafficStep]) -> Bearings:
        """Bearings of the given steps (the next ones of the run, in time order).

        The whole chunk is synthesized at once: the measuring steps are grouped into runs of
        the same vehicles, each run's geometry is one stacked computation, the occlusion is one
        query (``links_many`` when the occlusion object has it), and the random numbers are
        one draw split as the step-by-step synthesis drew them (per step: each measuring
        vehicle's azimuth bias and white noise, then the bearing noise of every link).
        """
        s = self.sensor
        steps = list(steps)
        for st in steps:
            self._seen.update(st.vehicles)
        if self._t0 is None and steps:
            self._t0 = steps[0].t_s
        sel: list[tuple[TrafficStep, list[str], list[str]]] = []
        for st in steps:
            if s.rate_hz is not None:
                assert self._t0 is not None  # set above from the first step
                tick = math.floor((st.t_s - self._t0) * s.rate_hz + 1e-9)
                if tick == self._last_tick:
                    continue
                self._last_tick = tick
            ids = sorted(st.vehicles)
            if len(ids) < 2:
                continue
            meas = ids if s.measuring == "all" else [v for v in s.measuring if v in st.vehicles]
            if meas:
                sel.append((st, ids, meas))
        if not sel:
            return self._output([])
        # Runs of consecutive steps with the same vehicles and measuring vehicles.
        runs: list[_Run] = []
        for st, ids, meas in sel:
            if runs and runs[-1].ids == ids and runs[-1].meas == meas:
                runs[-1].steps.append(st)
            else:
                runs.append(_Run(ids, meas, [st]))
        n_draw = sum(len(r.steps) * r.draws_per_step(s.azimuth_bias_sigma_rad > 0.0) for r in runs)
        z = self.rng.standard_normal(n_draw)
        off = 0
        for r in runs:
            n = len(r.steps) * r.draws_per_step(s.azimuth_bias_sigma_rad > 0.0)
            r.synthesize(s, z[off:off + n], self._bias)
            off += n
        if self.occlusion is not None:
            _occlude(runs, self.occlusion)
        return self._output(runs)

    def _output(self, runs: list[_Run]) -> Bearings:
        """The kept links of the runs, in step order (links in (measuring, other) id order)."""
        keep = [(r, np.flatnonzero(r.ok)) for r in runs]
        a = tuple(x for r, k in keep for x in r.name_a[k % r.pa.size].tolist())
        b = tuple(x for r, k in keep for x in r.name_b[k % r.pa.size].tolist())

        def cat(parts: list[np.ndarray]) -> np.ndarray:
            return np.concatenate(parts) if parts else np.zeros(0)

        out = Bearings(
            t_s=cat([r.t_s[k // r.pa.size] for r, k in keep]),
            a=a,
            b=b,
            bearing_rad=cat([wrap_angle(r.beta_true[k] + r.noise[k]) for r, k in keep]),
            true_bearing_rad=cat([r.beta_true[k] for r, k in keep]),
            azimuth_reported_rad=cat([r.az_rep.reshape(-1)[r.link_meas[k]] for r, k in keep]),
            true_azimuth_rad=cat([r.az_true[k] for r, k in keep]),
            los=np.ones(len(a), dtype=bool),
        )
        self.n += out.n
        return out


class _Run:
    """Consecutive measuring steps with the same vehicles ``ids`` and measuring vehicles ``meas``.

    Links are (step, measuring vehicle a, other vehicle b), flattened step-major with a's in
    ``meas`` order and b's in ``ids`` order (the step-by-step order): link ``i`` is step
    ``i // P`` and pair ``i % P`` of ``pa``/``pb`` (indices into ``ids``).
    """

    def __init__(self, ids: list[str], meas: list[str], steps: list[TrafficStep]):
        self.ids, self.meas, self.steps = ids, meas, steps
        col = {v: i for i, v in enumerate(ids)}
        self.am = np.array([col[a] for a in meas], dtype=np.int64)  # (M,)
        self.others = np.array([[j for j in range(len(ids)) if j != i] for i in self.am], dtype=np.int64)  # (M, N-1)
        self.pa = np.repeat(self.am, len(ids) - 1)
        self.pb = self.others.reshape(-1)
        names = np.array(ids, dtype=object)
        self.name_a, self.name_b = names[self.pa], names[self.pb]

    def draws_per_step(self, bias_on: bool) -> int:
        return len(self.meas) * (2 if bias_on else 1) + self.pa.size

    def synthesize(self, s: BearingSensor, z: np.ndarray, bias: dict[str, tuple[float, float]]) -> None:
        """True bearings, visibility (range, field of view), noise and reported azimuths of every link.

        ``ecef_to_enu`` per measuring vehicle and step is one stacked ``matmul`` here (the same
        BLAS product per step), the rest elementwise: the numbers equal the per-step ones.
        """
        n_s, n_m, n_p = len(self.steps), len(self.meas), self.pa.size
        vs = [[st.vehicles[v] for v in self.ids] for st in self.steps]
        ecef = np.array([[v.ecef_m for v in row] for row in vs], dtype=float)  # (S, N, 3)
        geo = np.array([[(v.lat_rad, v.lon_rad, v.azimuth_rad) for v in row] for row in vs], dtype=float)
        self.xyz = np.array([[v.xyz_m for v in row] for row in vs], dtype=float)
        self.t_s = np.array([st.t_s for st in self.steps], dtype=float)
        lat, lon, az = geo[:, self.am, 0], geo[:, self.am, 1], geo[:, self.am, 2]  # (S, M)
        sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
        rot = np.empty((n_s, n_m, 3, 3))  # v2v.frames.ecef_to_enu_rotation
        rot[..., 0, 0], rot[..., 0, 1], rot[..., 0, 2] = -so, co, 0.0
        rot[..., 1, 0], rot[..., 1, 1], rot[..., 1, 2] = -sl * co, -sl * so, cl
        rot[..., 2, 0], rot[..., 2, 1], rot[..., 2, 2] = cl * co, cl * so, sl
        d = ecef[:, self.others, :] - ecef[:, self.am, None, :]  # (S, M, N-1, 3)
        d_enu = np.matmul(d, rot.swapaxes(-1, -2)).reshape(-1, 3)
        self.az_true = np.repeat(az, len(self.ids) - 1, axis=1).reshape(-1)
        self.beta_true = bearing_rad(d_enu, self.az_true)
        self.ok = (range_m(np.zeros(3), d_enu) <= s.max_range_m) & (
            np.abs(self.beta_true) <= 0.5 * s.field_of_view_rad + 1e-12
        )
        # Reported azimuth: one value per measuring vehicle and epoch (from a's own navigation).
        bias_on = s.azimuth_bias_sigma_rad > 0.0
        zz = z.reshape(n_s, -1)
        z_az = zz[:, : n_m * (2 if bias_on else 1)].reshape(n_s, n_m, -1)
        bval = np.zeros((n_s, n_m))
        if bias_on:
            for i, st in enumerate(self.steps):
                for j, a in enumerate(self.meas):
                    b_prev = bias.get(a)
                    zb = z_az[i, j, 0]
                    if b_prev is None:
                        v = s.azimuth_bias_sigma_rad * zb
                    else:
                        phi = math.exp(-(st.t_s - b_prev[0]) / s.azimuth_bias_tau_s)
                        v = phi * b_prev[1] + math.sqrt(1.0 - phi * phi) * s.azimuth_bias_sigma_rad * zb
                    bias[a] = (st.t_s, v)
                    bval[i, j] = v
        w = s.azimuth_sigma_rad * z_az[..., -1]
        self.az_rep = (az + bval + w) % (2.0 * math.pi)  # (S, M)
        link = np.arange(n_s * n_p)
        self.link_meas = (link // n_p) * n_m + (link % n_p) // (len(self.ids) - 1)  # row of az_rep.reshape(-1)
        self.noise = s.sigma_rad * zz[:, n_m * (2 if bias_on else 1):].reshape(-1)


def _occlude(runs: list[_Run], occlusion: Any) -> None:
    """Clear ``ok`` of the links that a vehicle or a building blocks (antenna to antenna).

    One ``occlusion.links_many`` query for every visible link of the chunk, each against its
    own step's vehicle boxes; an occlusion object with only ``links`` is asked step by step.
    """
    steps = [st for r in runs for st in r.steps]
    link_step, p0, p1, ex, where = [], [], [], [], []
    base = 0
    for ri, r in enumerate(runs):
        n_p = r.pa.size
        k = np.flatnonzero(r.ok)
        si, pi = k // n_p, k % n_p
        link_step.append(base + si)
        p0.append(r.xyz[si, r.pa[pi]])
        p1.append(r.xyz[si, r.pb[pi]])
        ex.append(np.column_stack([r.pa[pi], r.pb[pi]]))
        where.append(np.column_stack([np.full(k.size, ri), k]))
        base += len(r.steps)
    link_step_a = np.concatenate(link_step)
    if link_step_a.size == 0:
        return
    p0_a, p1_a, ex_a, where_a = (np.concatenate(x) for x in (p0, p1, ex, where))
    if hasattr(occlusion, "links_many"):
        boxes, first, _ = vehicle_boxes_many(steps)
        blocked = np.asarray(occlusion.links_many(p0_a, p1_a, boxes, first, link_step_a, ex_a).blocked, dtype=bool)
    else:
        blocked = np.zeros(link_step_a.size, dtype=bool)
        bounds = np.flatnonzero(np.diff(link_step_a)) + 1
        for sel in np.split(np.arange(link_step_a.size), bounds):
            boxes, _ = vehicle_boxes(steps[int(link_step_a[sel[0]])])
            res = occlusion.links(p0_a[sel], p1_a[sel], boxes if len(boxes) else None, ex_a[sel])
            blocked[sel] = np.asarray(res.blocked, dtype=bool)
    for ri, r in enumerate(runs):
        mine = where_a[:, 0] == ri
        r.ok[where_a[mine, 1][blocked[mine]]] = False
