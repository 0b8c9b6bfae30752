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
from v2v.frames import ecef_to_enu, wrap_angle
from v2v.measmodels import bearing_rad, range_m
from v2v.sensors.measurements import Bearings
from v2v.sensors.uwb import vehicle_boxes
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
        """Bearings of the given steps (the next ones of the run, in time order)."""
        s = self.sensor
        rng = self.rng
        occlusion = self.occlusion
        steps = list(steps)
        for st in steps:
            self._seen.update(st.vehicles)
        cols: dict[str, list] = {k: [] for k in ("t", "a", "b", "beta", "beta_true", "az_rep", "az_true")}
        if self._t0 is None and steps:
            self._t0 = steps[0].t_s
        t0 = self._t0
        bias = self._bias
        for st in steps:
            if s.rate_hz is not None:
                tick = math.floor((st.t_s - t0) * s.rate_hz + 1e-9)
                if tick == self._last_tick:
                    continue
                self._last_tick = tick
            ids = sorted(st.vehicles)
            if len(ids) < 2:
                continue
            meas = ids if s.measuring == "all" else [v for v in s.measuring if v in st.vehicles]
            if not meas:
                continue
            # All (a, b) links of this step at once: a's own ENU frame for each a.
            pa = [a for a in meas for b in ids if b != a]
            pb = [b for a in meas for b in ids if b != a]
            d_enu = np.concatenate(
                [
                    ecef_to_enu(
                        np.array([st.vehicles[b].ecef_m for b in ids if b != a], dtype=float),
                        st.vehicles[a].lat_rad,
                        st.vehicles[a].lon_rad,
                        st.vehicles[a].ecef_m,
                    )
                    for a in meas
                ]
            )
            az_true = np.array([st.vehicles[a].azimuth_rad for a in pa])
            beta_true = bearing_rad(d_enu, az_true)
            ok = (range_m(np.zeros(3), d_enu) <= s.max_range_m) & (
                np.abs(beta_true) <= 0.5 * s.field_of_view_rad + 1e-12
            )
            if occlusion is not None and np.any(ok):
                boxes, row = vehicle_boxes(st)
                idx = np.flatnonzero(ok)
                p0 = np.array([st.vehicles[pa[i]].xyz_m for i in idx], dtype=float)
                p1 = np.array([st.vehicles[pb[i]].xyz_m for i in idx], dtype=float)
                excl = np.array([[row[pa[i]], row[pb[i]]] for i in idx], dtype=np.int64)
                res = occlusion.links(p0, p1, boxes if len(boxes) else None, excl)
                ok[idx] &= ~np.asarray(res.blocked, dtype=bool)
            # Reported azimuth: one value per measuring vehicle and epoch (from a's own navigation).
            az_rep: dict[str, float] = {}
            for a in meas:
                b_prev = bias.get(a)
                if s.azimuth_bias_sigma_rad > 0.0:
                    if b_prev is None:
                        bval = s.azimuth_bias_sigma_rad * rng.standard_normal()
                    else:
                        phi = math.exp(-(st.t_s - b_prev[0]) / s.azimuth_bias_tau_s)
                        bval = phi * b_prev[1] + math.sqrt(1.0 - phi * phi) * s.azimuth_bias_sigma_rad * rng.standard_normal()
                    bias[a] = (st.t_s, bval)
                else:
                    bval = 0.0
                w = s.azimuth_sigma_rad * rng.standard_normal()
                az_rep[a] = (st.vehicles[a].azimuth_rad + bval + w) % (2.0 * math.pi)
            noise = s.sigma_rad * rng.standard_normal(len(pa))
            k = np.flatnonzero(ok)
            if k.size == 0:
                continue
            cols["t"].append(np.full(k.size, st.t_s))
            cols["a"].extend(pa[i] for i in k)
            cols["b"].extend(pb[i] for i in k)
            cols["beta"].append(wrap_angle(beta_true[k] + noise[k]))
            cols["beta_true"].append(beta_true[k])
            cols["az_rep"].append(np.array([az_rep[pa[i]] for i in k]))
            cols["az_true"].append(az_true[k])

        def cat(key: str) -> np.ndarray:
            return np.concatenate(cols[key]) if cols[key] else np.zeros(0)

        out = Bearings(
            t_s=cat("t"),
            a=tuple(cols["a"]),
            b=tuple(cols["b"]),
            bearing_rad=cat("beta"),
            true_bearing_rad=cat("beta_true"),
            azimuth_reported_rad=cat("az_rep"),
            true_azimuth_rad=cat("az_true"),
            los=np.ones(len(cols["a"]), dtype=bool),
        )
        self.n += out.n
        return out
