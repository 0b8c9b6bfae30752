"""Fault injection: the scenario's ``[[faults]]`` list, applied to the synthesized
measurements before the V2V exchange (so every solution sees the same faults).

Each fault has a ``kind``, a time window ``[start_s, start_s + duration_s)`` (duration 0 =
to the end of the run for step faults such as a clock jump), and targets. Injected errors
are recorded in the measurement's ``errors_m["fault"]`` component (NaN/Inf faults and
dropped measurements are counted in the fault log), so metrics can tell true from false
rejections.

Kinds
-----
``gnss_outage``       all GNSS of ``vehicles`` (or all) missing in the window.
``satellites_lost``   ``prns`` missing for ``vehicles`` in the window.
``clock_jump``        receiver clock of each of ``vehicles`` jumps by ``size_m`` (default +1 ms =
                      299 792.458 m) at ``start_s``: every later pseudorange and carrier phase.
``cycle_slip``        carrier phase of ``prns`` (default all) jumps by ``size_cycles`` at ``start_s``
                      (lock time reset).
``pr_blunder``        each pseudorange in the window gets ``+size_m`` with ``probability``.
``uwb_blunder``       each UWB range in the window gets ``+size_m`` with ``probability``.
``uwb_replace``       the radio of ``vehicles[0]`` is replaced at ``start_s`` by a unit with another
                      bias (``size_m``) and scale (``scale_ppm``): every later range involving it.
``uwb_scale_drift``   ranges involving ``vehicles`` get an extra scale growing at ``scale_ppm`` per
                      second from ``start_s`` (beyond the model).
``bearing_outage``    bearings measured by ``vehicles`` missing in the window.
``nonfinite``         measurements of ``sensor`` (gnss|uwb|bearing) of ``vehicles`` in the window become
                      NaN (``size_m = inf`` for +Inf) with ``probability``.
``message_loss``      every V2V message from ``vehicles`` lost in the window (a burst).
``vehicle_leaves``    ``vehicles`` leave the cluster for the window (no GNSS from them, no UWB range or
                      bearing involving them, no messages) and rejoin after it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Annotated, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, StrictFloat, StrictInt, model_validator

from v2v.config.sections import GPS_MAX_PRN
from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M, SPEED_OF_LIGHT_MPS, Bearings, GnssEpoch, UwbRanges

FaultKind = Literal[
    "gnss_outage", "satellites_lost", "clock_jump", "cycle_slip", "pr_blunder", "uwb_blunder", "uwb_replace",
    "uwb_scale_drift", "bearing_outage", "nonfinite", "message_loss", "vehicle_leaves",
]


# what each kind acts on besides start_s, duration_s and vehicles (which every kind uses), and
# the defaults of those optional fields: a field a kind does not use, given anything but its
# default, is an error (pr_blunder with prns = [5] would blunder every satellite, not PRN 5)
_KIND_FIELDS: dict[str, tuple[str, ...]] = {
    "gnss_outage": (), "satellites_lost": ("prns",), "clock_jump": ("size_m",), "cycle_slip": ("prns", "size_cycles"),
    "pr_blunder": ("size_m", "probability"), "uwb_blunder": ("size_m", "probability"),
    "uwb_replace": ("size_m", "scale_ppm"), "uwb_scale_drift": ("scale_ppm",), "bearing_outage": (),
    "nonfinite": ("sensor", "size_m", "probability"), "message_loss": (), "vehicle_leaves": (),
}
_OPTIONAL_DEFAULTS: dict[str, object] = {"prns": [], "size_m": 0.0, "size_cycles": 0, "scale_ppm": 0.0,
                                         "probability": 1.0, "sensor": "gnss"}
MAX_PRN = GPS_MAX_PRN  # GPS PRNs (the nominal constellation's slots are 1-27; a RINEX file's GPS PRNs 1-32)
MAX_SIZE_CYCLES = 10**9  # (carrier_cycles is float64, ambiguity_cycles int64: beyond, a slip overflows or loses cycles)
MAX_SIZE_M = 3.0e8  # |size_m|: a 1 s clock jump (c x 1 s); beyond, squares of the errors lose meaning, then overflow
MAX_SCALE_PPM = 1.0e6  # |scale_ppm|: a scale factor error of 100 %


class FaultSection(BaseModel):
    """One ``[[faults]]`` entry."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    kind: FaultKind
    start_s: StrictFloat = Field(ge=0.0)
    duration_s: StrictFloat = Field(default=0.0, ge=0.0)
    vehicles: Literal["all"] | list[str] = "all"
    prns: list[Annotated[StrictInt, Field(ge=1, le=MAX_PRN)]] = Field(default_factory=list)
    size_m: StrictFloat = 0.0
    size_cycles: StrictInt = Field(default=0, ge=-MAX_SIZE_CYCLES, le=MAX_SIZE_CYCLES)
    scale_ppm: StrictFloat = 0.0
    probability: StrictFloat = Field(default=1.0, ge=0.0, le=1.0)
    sensor: Literal["gnss", "uwb", "bearing"] = "gnss"

    @model_validator(mode="after")
    def _needs(self) -> FaultSection:
        k = self.kind
        for name, default in _OPTIONAL_DEFAULTS.items():
            value = getattr(self, name)
            if name not in _KIND_FIELDS[k] and value != default:  # (nan != 0.0)
                users = ", ".join(kk for kk, used in _KIND_FIELDS.items() if name in used)
                raise ValueError(f"@{name}: {k} does not use {name} (got {value!r}) -- fix: remove {name} from this "
                                 f"fault ({name} is for {users})")
        if k == "nonfinite":
            if not (self.size_m == 0.0 or math.isnan(self.size_m) or self.size_m == math.inf):
                raise ValueError(f"@size_m: a nonfinite fault writes NaN, or +Inf with size_m = inf (got {self.size_m!r})"
                                 " -- fix: give size_m = inf for +Inf, or leave size_m out for NaN")
        elif not math.isfinite(self.size_m):
            raise ValueError(f"@size_m: {k}'s size_m must be a finite number of metres (got {self.size_m!r}) -- fix: give"
                             " a finite size_m (non-finite measurements: kind = \"nonfinite\")")
        elif abs(self.size_m) > MAX_SIZE_M:
            raise ValueError(f"@size_m: {k}'s size_m is beyond +-{MAX_SIZE_M:g} m (got {self.size_m!r}; {MAX_SIZE_M:g} m is "
                             f"a 1 s clock jump) -- fix: give |size_m| <= {MAX_SIZE_M:g}")
        if not math.isfinite(self.scale_ppm):
            raise ValueError(f"@scale_ppm: must be a finite number (got {self.scale_ppm!r}) -- fix: give a finite scale_ppm")
        if abs(self.scale_ppm) > MAX_SCALE_PPM:
            raise ValueError(f"@scale_ppm: beyond +-{MAX_SCALE_PPM:g} ppm, a 100 % scale error (got {self.scale_ppm!r}) -- "
                             f"fix: give |scale_ppm| <= {MAX_SCALE_PPM:g}")
        if k == "satellites_lost" and not self.prns:
            raise ValueError("@prns: satellites_lost needs the PRNs it removes -- fix: give prns = [...], e.g. [5, 12]")
        if k in ("pr_blunder", "uwb_blunder") and self.size_m == 0.0:
            raise ValueError(f"@size_m: {k} needs size_m (the blunder, metres) -- fix: give size_m, e.g. 30.0")
        if k == "cycle_slip" and self.size_cycles == 0:
            raise ValueError("@size_cycles: cycle_slip needs size_cycles (a non-zero integer) -- fix: give size_cycles, "
                             "e.g. 1 or -2")
        if k == "uwb_replace" and (self.vehicles == "all" or len(self.vehicles) != 1):
            raise ValueError('@vehicles: uwb_replace needs vehicles = [one vehicle id] -- fix: give e.g. vehicles = ["c1.1"]')
        if k in ("gnss_outage", "satellites_lost", "pr_blunder", "uwb_blunder", "bearing_outage", "nonfinite",
                 "message_loss", "vehicle_leaves") and self.duration_s <= 0.0:
            raise ValueError(f"@duration_s: {k} needs duration_s > 0 (its window) -- fix: give duration_s, e.g. 10.0")
        return self

    def size_or_default_m(self) -> float:
        if self.kind == "clock_jump" and self.size_m == 0.0:
            return 1e-3 * SPEED_OF_LIGHT_MPS  # 1 ms
        return self.size_m

    def active(self, t_s: float) -> bool:
        if self.duration_s <= 0.0:
            return t_s >= self.start_s - 1e-9
        return self.start_s - 1e-9 <= t_s < self.start_s + self.duration_s - 1e-9

    def targets(self, vehicle: str) -> bool:
        return self.vehicles == "all" or vehicle in self.vehicles


def check_fault_prns(faults: list[FaultSection], sky_prns) -> None:
    """UserError naming ``faults.<i>.prns`` when none of a fault's PRNs is in the run's sky
    (``sky_prns``: the ephemeris' PRNs): such a fault could never match a signal. Some PRNs
    missing is allowed (a set such as "the odd PRNs 1-31" over a 27-slot sky)."""
    from v2v.errors import UserError

    have = {int(p) for p in sky_prns}
    for i, f in enumerate(faults):
        listed = sorted({int(p) for p in f.prns})
        if listed and not have.intersection(listed):
            sky = f"its PRNs: {min(have)}-{max(have)}" if have else "it has none"
            raise UserError(f"none of PRN(s) {listed} is in the run's sky ({sky})", field=f"faults.{i}.prns",
                            fix="list PRNs of the constellation (`v2v sky` shows them)")


def unreachable_faults(faults: list[FaultSection], duration_s: float) -> list[str]:
    """The faults that start at or after the run's end, so never act: ``faults.<i> (<kind> at <start> s)``."""
    return [f"faults.{i} ({f.kind} at {f.start_s:g} s)" for i, f in enumerate(faults) if f.start_s >= duration_s - 1e-9]


@dataclass
class FaultLog:
    """What was injected: counts per fault (index in the scenario list) and kind."""

    counts: dict[str, int] = field(default_factory=dict)

    def add(self, i: int, kind: str, n: int = 1) -> None:
        if n:
            key = f"{i}:{kind}"
            self.counts[key] = self.counts.get(key, 0) + int(n)


def _with_fault(errors: dict[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    out = dict(errors)
    if "fault" not in out:
        out["fault"] = np.zeros(n)
    else:
        out["fault"] = out["fault"].copy()
    return out


def apply_gnss_faults(epochs: list[tuple[float, dict[str, GnssEpoch]]], faults: list[FaultSection],
                      rng: np.random.Generator, log: FaultLog) -> list[tuple[float, dict[str, GnssEpoch]]]:
    gnss_faults = [(i, f) for i, f in enumerate(faults) if f.kind in (
        "gnss_outage", "vehicle_leaves", "satellites_lost", "clock_jump", "cycle_slip", "pr_blunder") or (f.kind == "nonfinite" and f.sensor == "gnss")]
    if not gnss_faults:
        return epochs
    out = []
    slipped: set[tuple[int, str]] = set()
    for t, eps in epochs:
        new: dict[str, GnssEpoch] = {}
        for v, ep in eps.items():
            keep = True
            for i, f in gnss_faults:
                if not (f.targets(v) and f.active(t)):
                    continue
                if f.kind in ("gnss_outage", "vehicle_leaves"):
                    keep = False
                    log.add(i, f.kind)
                    break
                if f.kind == "satellites_lost":
                    m = ~np.isin(ep.prn, f.prns)
                    log.add(i, f.kind, int((~m).sum()))
                    ep = ep.select(m)
                elif f.kind == "clock_jump":
                    # Common to every satellite of the receiver: a clock error (the filter's clock
                    # state may absorb it), recorded apart from measurement faults.
                    d = f.size_or_default_m()
                    err = dict(ep.errors_m)
                    err["clock_jump"] = err.get("clock_jump", np.zeros(ep.n)) + d
                    ep = replace(ep, pseudorange_m=ep.pseudorange_m + d,
                                 carrier_cycles=ep.carrier_cycles + d / GPS_L1_WAVELENGTH_M, errors_m=err)
                    log.add(i, f.kind, ep.n)
                elif f.kind == "cycle_slip":
                    # A slip is a step: from start_s on, the phase carries the extra cycles; the
                    # receiver's lock time restarts at the first epoch after the slip.
                    hit = np.ones(ep.n, bool) if not f.prns else np.isin(ep.prn, f.prns)
                    first = (i, v) not in slipped
                    slipped.add((i, v))
                    ep = replace(ep, carrier_cycles=ep.carrier_cycles + f.size_cycles * hit,
                                 ambiguity_cycles=ep.ambiguity_cycles + f.size_cycles * hit,
                                 lock_time_s=np.where(hit & first, 0.0, ep.lock_time_s))
                    log.add(i, f.kind, int(hit.sum()) if first else 0)
                elif f.kind == "pr_blunder":
                    hit = rng.random(ep.n) < f.probability
                    err = _with_fault(ep.errors_m, ep.n)
                    err["fault"] += f.size_m * hit
                    ep = replace(ep, pseudorange_m=ep.pseudorange_m + f.size_m * hit, errors_m=err)
                    log.add(i, f.kind, int(hit.sum()))
                elif f.kind == "nonfinite":
                    hit = rng.random(ep.n) < f.probability
                    bad = np.inf if np.isinf(f.size_m) else np.nan
                    ep = replace(ep, pseudorange_m=np.where(hit, bad, ep.pseudorange_m),
                                 doppler_mps=np.where(hit, bad, ep.doppler_mps))
                    log.add(i, f.kind, int(hit.sum()))
            if keep:
                new[v] = ep
        out.append((t, new))
    return out


def apply_uwb_faults(uwb: UwbRanges | None, faults: list[FaultSection], rng: np.random.Generator,
                     log: FaultLog) -> UwbRanges | None:
    fs = [(i, f) for i, f in enumerate(faults) if f.kind in ("uwb_blunder", "uwb_replace", "uwb_scale_drift", "vehicle_leaves")
          or (f.kind == "nonfinite" and f.sensor == "uwb")]
    if uwb is None or not fs or uwb.n == 0:
        return uwb
    r = uwb.range_m.copy()
    keep = np.ones(uwb.n, bool)
    err = _with_fault(uwb.errors_m, uwb.n)
    t = uwb.t_s
    involves = lambda f: np.array([f.targets(a) or f.targets(b) for a, b in zip(uwb.a, uwb.b, strict=True)])  # noqa: E731
    for i, f in fs:
        act = np.array([f.active(x) for x in t]) & involves(f)
        if f.kind == "uwb_blunder":
            hit = act & (rng.random(uwb.n) < f.probability)
            r += f.size_m * hit
            err["fault"] += f.size_m * hit
            log.add(i, f.kind, int(hit.sum()))
        elif f.kind == "uwb_replace":
            d = (f.size_m + f.scale_ppm * 1e-6 * uwb.true_range_m) * act
            r += d
            err["fault"] += d
            log.add(i, f.kind, int(act.sum()))
        elif f.kind == "uwb_scale_drift":
            d = f.scale_ppm * 1e-6 * np.clip(t - f.start_s, 0.0, None) * uwb.true_range_m * act
            r += d
            err["fault"] += d
            log.add(i, f.kind, int(act.sum()))
        elif f.kind == "nonfinite":
            hit = act & (rng.random(uwb.n) < f.probability)
            r = np.where(hit, np.inf if np.isinf(f.size_m) else np.nan, r)
            log.add(i, f.kind, int(hit.sum()))
        elif f.kind == "vehicle_leaves":  # out of the cluster: out of radio range too
            keep &= ~act
            log.add(i, f.kind, int(act.sum()))
    out = replace(uwb, range_m=r, errors_m=err)
    if keep.all():
        return out
    from v2v.sensors.uwb import select_ranges

    return select_ranges(out, keep)


def apply_bearing_faults(b: Bearings | None, faults: list[FaultSection], rng: np.random.Generator,
                         log: FaultLog) -> Bearings | None:
    fs = [(i, f) for i, f in enumerate(faults) if f.kind in ("bearing_outage", "vehicle_leaves")
          or (f.kind == "nonfinite" and f.sensor == "bearing")]
    if b is None or not fs or b.n == 0:
        return b
    keep = np.ones(b.n, bool)
    val = b.bearing_rad.copy()
    for i, f in fs:
        if f.kind == "vehicle_leaves":
            act = np.array([f.active(x) and (f.targets(a) or f.targets(c)) for x, a, c in zip(b.t_s, b.a, b.b, strict=True)])
        else:
            act = np.array([f.active(x) and f.targets(a) for x, a in zip(b.t_s, b.a, strict=True)])
        if f.kind in ("bearing_outage", "vehicle_leaves"):
            keep &= ~act
            log.add(i, f.kind, int(act.sum()))
        else:
            hit = act & (rng.random(b.n) < f.probability)
            val = np.where(hit, np.inf if np.isinf(f.size_m) else np.nan, val)
            log.add(i, f.kind, int(hit.sum()))
    idx = np.flatnonzero(keep)
    return replace(b, bearing_rad=val).take(idx)


def dropping_fault(faults: list[FaultSection], sender: str, t_s: float, lead: str | None = None) -> int | None:
    """The index of the first fault that silences ``sender``'s message at ``t_s``, or None: a
    vehicle-leaves fault, or a message-loss burst (a V2V link's: not the ``lead``'s own
    measurements, which reach its filter on board)."""
    for i, f in enumerate(faults):
        if (f.kind == "vehicle_leaves" or (f.kind == "message_loss" and sender != lead)) and f.targets(sender) \
                and f.active(t_s):
            return i
    return None

