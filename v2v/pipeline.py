"""Builders from scenario sections to sensor / filter objects, and the per-solution
processing of one synthesized measurement stream.

Randomness: one ``numpy.random.SeedSequence(seed)`` per run, spawned into child streams
by fixed index (0 traffic/background, 1 GNSS, 2 UWB, 3 bearing, 4 V2V exchange, 5 faults), and the
same seed handed to SUMO's ``--seed``. The same seed therefore gives bit-identical outputs,
and changing one component's settings leaves the other components' draws unchanged.

Every solution processes the *same* measurements (and the same exchange losses).
"""

from __future__ import annotations

import itertools
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from operator import itemgetter
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from v2v.config.scenario import Scenario
from v2v.config.sections import SolutionSection
from v2v.estimation.filter import (
    KIND_BEARING,
    KIND_SD_DOPPLER,
    KIND_SD_PR,
    KIND_SD_PR_PAIR,
    KIND_UWB,
    ClusterEkf,
    FilterConfig,
    MeasurementNoiseConfig,
    UpdateBatch,
    UpdateInfo,
    Updates,
)
from v2v.estimation.layout import StateLayout
from v2v.estimation.phase import PhaseConfig, wrong_fix
from v2v.estimation.process import ProcessNoiseConfig
from v2v.exchange import Message, V2VExchange
from v2v.frames import ecef_to_enu_rotation
from v2v.metrics.errors import EPOCH_COLUMNS, epoch_errors, epoch_nis_sums
from v2v.sensors.measurements import Bearings, GnssEpoch, UwbRanges
from v2v.traffic.snapshot import TrafficStep

if TYPE_CHECKING:
    import pandas as pd

LEAVE_AFTER_S = 5.0  # a vehicle the lead has not heard from for this long has left the cluster

STREAM_TRAFFIC, STREAM_GNSS, STREAM_UWB, STREAM_BEARING, STREAM_EXCHANGE, STREAM_FAULTS = range(6)
N_STREAMS = 6


def child_seeds(seed: int) -> list[np.random.SeedSequence]:
    return np.random.SeedSequence(seed).spawn(N_STREAMS)


# --------------------------------------------------------------------------- sensors


def build_ephemeris(scenario: Scenario, gps_start_s: float):
    """The scenario's sky (:func:`v2v.sensors.gnss.source.ephemeris_source`: the nominal
    constellation, or its RINEX file; a relative path is relative to the working directory;
    :func:`v2v.run.run_scenario` makes it absolute first)."""
    from v2v.sensors.gnss.source import ephemeris_source

    return ephemeris_source(scenario.sensors.gnss.ephemeris, gps_start_s, scenario.duration_s)


def build_gnss(scenario: Scenario, gps_start_s: float, seed: np.random.SeedSequence, occlusion, georef):
    from v2v.sensors.gnss.atmosphere import IonosphereConfig, SatelliteErrorConfig, TroposphereConfig
    from v2v.sensors.gnss.clock import OCXO, TCXO, ClockConfig
    from v2v.sensors.gnss.errors import GnssErrorConfig, MultipathConfig, TrackingConfig
    from v2v.sensors.gnss.receiver import GnssReceiverConfig, GnssSynthesizer

    sec = scenario.sensors.gnss
    e = sec.errors
    errors = GnssErrorConfig(
        clock=ClockConfig(enabled=e.receiver_clock, oscillator=TCXO if sec.oscillator == "TCXO" else OCXO),
        iono=IonosphereConfig(enabled=e.ionosphere),
        tropo=TroposphereConfig(enabled=e.troposphere),
        satellite=SatelliteErrorConfig(orbit_enabled=e.satellite_orbit, clock_enabled=e.satellite_clock),
        multipath=MultipathConfig(enabled=e.multipath),
        tracking=TrackingConfig(noise_enabled=e.noise, foliage_enabled=e.foliage, nlos_enabled=e.nlos),
    )
    cfg = GnssReceiverConfig(rate_hz=sec.rate_hz, elevation_mask_rad=float(np.radians(sec.elevation_mask_deg)), errors=errors)
    eph = build_ephemeris(scenario, gps_start_s)
    return GnssSynthesizer(eph, cfg, seed, gps_start_s, occlusion=occlusion, georef=georef if occlusion is not None else None)


def build_uwb(scenario: Scenario, vehicle_ids: Sequence[str], seed: np.random.SeedSequence):
    from v2v.sensors.uwb import UwbNetwork

    sec = scenario.sensors.uwb
    pairs: Any = "all" if sec.pairs == "all" else [tuple(p) for p in sec.pairs]
    return UwbNetwork(vehicle_ids=vehicle_ids, rng=np.random.default_rng(seed.spawn(1)[0]), profile=sec.profile,
                      vehicle_profiles=dict(sec.vehicle_profiles) or None, pairs=pairs)


def build_bearing(scenario: Scenario):
    from v2v.sensors.bearing import BearingSensor

    sec = scenario.sensors.bearing
    return BearingSensor(
        sigma_rad=float(np.radians(sec.sigma_deg)),
        field_of_view_rad=float(np.radians(sec.field_of_view_deg)),
        max_range_m=sec.max_range_m,
        rate_hz=sec.rate_hz,
        azimuth_sigma_rad=float(np.radians(sec.azimuth_sigma_deg)),
        measuring="all" if sec.measuring == "all" else tuple(sec.measuring),
    )


# --------------------------------------------------------------------------- filters


def build_filter(sol: SolutionSection, lead: str, vehicles: Sequence[str], bearing_vehicles: Sequence[str],
                 uwb_pairs: Sequence[tuple[str, str]], antenna_heights_m: dict[str, float] | None = None) -> ClusterEkf:
    """The production EKF for one solution (``antenna_heights_m``: the vehicles' antenna
    heights above the road, for the height aiding; ``FilterConfig.antenna_heights_m``)."""
    az = tuple(bearing_vehicles) if sol.azimuth == "estimated" else ()
    pairs = tuple(uwb_pairs) if sol.uwb_error_states else ()
    layout = StateLayout.build(lead=lead, vehicles=tuple(vehicles), azimuth_vehicles=az, uwb_pairs=pairs,
                               azimuth_rates=sol.yaw_rate_sigma_deg_s > 0.0)
    cfg = FilterConfig(
        process=ProcessNoiseConfig(
            vel_tau_s=sol.velocity_tau_s,
            vel_sigma_horizontal_mps=sol.velocity_sigma_horizontal_mps,
            vel_sigma_vertical_mps=sol.velocity_sigma_vertical_mps,
            drift_tau_s=sol.clock_drift_tau_s,
            drift_sigma_mps=sol.clock_drift_sigma_mps,
            azimuth_rw_rad_per_sqrt_s=float(np.radians(sol.azimuth_rw_deg_per_sqrt_s)),
            yaw_rate_sigma_rps=float(np.radians(sol.yaw_rate_sigma_deg_s)),
            yaw_rate_tau_s=sol.yaw_rate_tau_s,
        ),
        noise=MeasurementNoiseConfig(
            pseudorange_sigma_m=sol.pseudorange_sigma_m,
            doppler_sigma_mps=sol.doppler_sigma_mps,
            uwb_sigma_m=sol.uwb_sigma_m,
            bearing_sigma_rad=float(np.radians(sol.bearing_sigma_deg)),
        ),
        significance=sol.significance,
        use_uwb_bias_scale=sol.uwb_error_states,
        uwb_bias_bounds_m=sol.uwb_bias_bounds_m if sol.uwb_constraints else None,
        uwb_scale_bounds=sol.uwb_scale_bounds if sol.uwb_constraints else None,
        height_aiding_sigma_m=sol.height_aiding_sigma,
        antenna_heights_m=antenna_heights_m,
        gnss_min_satellites=sol.gnss_min_satellites,
        gnss_cn0_mask_dbhz=sol.gnss_cn0_mask_dbhz,
        phase=PhaseConfig(
            phase_sigma_m=sol.phase_sigma_m,
            elevation_mask_rad=float(np.radians(sol.phase_elevation_mask_deg)),
            resolve=sol.ambiguity_resolution,
            ar_min_success=sol.ar_min_success,
            ar_ratio=sol.ar_ratio,
            ar_min_dd=3 if "uwb" in sol.sensors else 4,  # UWB ranges give the redundancy (PhaseConfig)
        ) if sol.carrier_phase else None,
    )
    return ClusterEkf(layout, cfg)


# --------------------------------------------------------------------------- the stream


class Event:
    """A batch of measurements with one time tag, as the lead's filter receives it.

    ``bad_prns``: per vehicle, the PRNs whose pseudorange the simulator corrupted beyond the
    filter's model (NLOS or an injected fault), computed once per event for every solution;
    ``nlos_prns`` the NLOS (echo-only) ones among them, whose Doppler carries the echo's path
    rate (injected faults are on the pseudorange only).

    A UWB event delivered by the exchange holds one range: range ``uwb_index`` of the chunk's
    :class:`UwbRanges` ``uwb_source``; :attr:`uwb` is that range as its own ``UwbRanges``
    (views), built when first read (a run of UWB events is filtered from the source's columns,
    :meth:`SolutionRunner._uwb_run`). Read-only by convention, like the frozen record it was.
    """

    __slots__ = ("t_s", "kind", "gnss", "_uwb", "bearings", "lead_base_ecef_m", "bad_prns", "nlos_prns", "uwb_source",
                 "uwb_index")

    def __init__(self, t_s: float, kind: str, gnss: dict[str, GnssEpoch] | None = None, uwb: UwbRanges | None = None,
                 bearings: Bearings | None = None, lead_base_ecef_m: np.ndarray | None = None,
                 bad_prns: dict[str, frozenset[int]] | None = None,
                 nlos_prns: dict[str, frozenset[int]] | None = None) -> None:
        self.t_s, self.kind, self.gnss, self._uwb, self.bearings = t_s, kind, gnss, uwb, bearings  # "gnss" | "uwb" | "bearing"
        self.lead_base_ecef_m, self.bad_prns, self.nlos_prns = lead_base_ecef_m, bad_prns, nlos_prns
        self.uwb_source: UwbRanges | None = None
        self.uwb_index = -1

    @classmethod
    def one_range(cls, t_s: float, src: UwbRanges, k: int) -> Event:
        """The UWB event of range ``k`` of ``src``."""
        ev = cls(t_s, "uwb")
        ev.uwb_source, ev.uwb_index = src, k
        return ev

    @property
    def uwb(self) -> UwbRanges | None:
        if self._uwb is None and self.uwb_source is not None:
            self._uwb = _one_range(self.uwb_source, self.uwb_index)
        return self._uwb

    def __repr__(self) -> str:
        return f"Event({self.t_s!r}, {self.kind!r})"


_KIND_RANK = {"gnss": 0, "uwb": 1, "bearing": 2}
_SEND_KEY = itemgetter(0, 1, 2)  # of ExchangeStream's unsent (t_s, kind rank, seq, message)


def _bad_prns(eps: dict[str, GnssEpoch]) -> tuple[dict[str, frozenset[int]], dict[str, frozenset[int]]]:
    """Per vehicle: the PRNs (first occurrence in the epoch) that are NLOS or carry an injected
    fault, and the NLOS ones among them (:class:`Event` ``bad_prns``, ``nlos_prns``)."""
    none: frozenset[int] = frozenset()
    if eps and all("fault" not in ep.errors_m for ep in eps.values()) \
            and np.concatenate([np.asarray(ep.los, dtype=bool) for ep in eps.values()]).all():
        return dict.fromkeys(eps, none), dict.fromkeys(eps, none)  # the common case, in one pass
    bad_out: dict[str, frozenset[int]] = {}
    nlos_out: dict[str, frozenset[int]] = {}
    for v, ep in eps.items():
        bad_out[v] = nlos_out[v] = frozenset()
        if ep.n == 0:
            continue
        nlos = ~np.asarray(ep.los, dtype=bool)
        fault = ep.errors_m.get("fault")
        bad = nlos | (fault != 0.0) if fault is not None else nlos
        if not bad.any():  # the common case: nothing NLOS or faulted
            continue
        _, first = np.unique(ep.prn, return_index=True)
        prn = ep.prn[first]
        bad_out[v] = frozenset(int(p) for p in prn[bad[first]])
        nlos_out[v] = frozenset(int(p) for p in prn[nlos[first]])
    return bad_out, nlos_out


class ExchangeStream:
    """The V2V exchange of one cluster, fed chunk by chunk (see :func:`exchange_stream`).

    Add each chunk's measurements (:meth:`add_gnss`, :meth:`add_uwb`, :meth:`add_bearings`, in
    time order per kind) and output epochs (:meth:`add_output_time`), then :meth:`advance` with
    the time up to which every measurement is known: it sends (in time-tag order, GNSS before
    UWB before bearings at equal tags) and delivers at each output epoch it can, and returns
    the events that no later delivery can precede. Messages still in flight (latency) carry
    over to the next chunk. The sequence of sends, deliveries, loss draws and events is the
    one of a single whole-run call, so the result does not depend on the chunk length.

    ``lead_bases``: the lead's base positions (paper eq. 7) of its delivered epochs, given in
    delivery order, one call per delivery (:meth:`v2v.sensors.gnss.spp.SppChain.many`); None
    where there is none.
    """

    def __init__(self, exchange: V2VExchange, lead_bases: Callable[[list[GnssEpoch]], list[np.ndarray | None]],
                 dropped: Callable[[str, float], bool] | None = None):
        self.exchange = exchange
        self.lead_bases = lead_bases
        self.dropped = dropped
        self._msgs: list[tuple[float, int, int, Message]] = []  # (t_s, rank, seq, message), unsent
        self._sorted = True
        self._seq = itertools.count()
        self._times: list[float] = []  # output epochs not yet delivered at
        self._delivered: list[Message] = []  # delivered, not yet turned into events
        self._n_sent_times = 0

    def _add(self, t: float, sender: str, kind: str, payload: Any) -> None:
        if self.dropped is not None and self.dropped(sender, t):
            return
        self._msgs.append((t, _KIND_RANK[kind], next(self._seq), Message(t, sender, kind, payload)))
        self._sorted = False

    def add_gnss(self, t_s: float, eps: dict[str, GnssEpoch]) -> None:
        for v, ep in eps.items():
            self._add(t_s, v, "gnss", ep)

    def add_uwb(self, uwb: UwbRanges | None) -> None:
        """One message per range, sent by its initiator ``a``."""
        if uwb is None or not uwb.n:
            return
        kind_rank, seq, dropped = _KIND_RANK["uwb"], self._seq, self.dropped
        self._msgs += [(t, kind_rank, next(seq), Message(t, a, "uwb", (uwb, k)))
                       for k, (t, a) in enumerate(zip(uwb.t_s.tolist(), uwb.a, strict=True))
                       if dropped is None or not dropped(a, t)]
        self._sorted = False

    def add_bearings(self, bearings: Bearings | None) -> None:
        """One message per measuring vehicle and time tag, carrying all its bearings of that
        instant (the packet the exchange model describes; lost or delayed as a whole)."""
        if bearings is None or bearings.n == 0:
            return
        t = np.asarray(bearings.t_s, dtype=float)
        if not (len(t) == len(bearings.a) == bearings.n):
            raise ValueError(f"bearings: {len(t)} time tags, {len(bearings.a)} measuring vehicles, {bearings.n} bearings")
        # packets = (time tag, measuring vehicle) groups in order of first occurrence, each
        # with its bearings' indices in measurement order (what a dict of lists gives)
        names = list(dict.fromkeys(bearings.a))
        code = {v: i for i, v in enumerate(names)}
        ai = np.fromiter(map(code.__getitem__, bearings.a), dtype=np.int64, count=bearings.n)
        _, ti = np.unique(t, return_inverse=True, equal_nan=False)  # (each NaN time tag its own packet)
        _, first, inv = np.unique(ti.reshape(-1) * len(names) + ai, return_index=True, return_inverse=True)
        by_first = np.argsort(first, kind="stable")
        rank = np.empty_like(by_first)
        rank[by_first] = np.arange(len(by_first))
        g = rank[inv.reshape(-1)]
        members = np.argsort(g, kind="stable")
        ends = np.cumsum(np.bincount(g, minlength=len(by_first))).tolist()
        starts = [0, *ends[:-1]]
        heads = first[by_first]
        kind_rank, seq, dropped, a = _KIND_RANK["bearing"], self._seq, self.dropped, bearings.a
        self._msgs += [(tk, kind_rank, next(seq), Message(tk, a[h], "bearing", (bearings, members[k0:k1])))
                       for k0, k1, h, tk in zip(starts, ends, heads.tolist(), t[heads].tolist(), strict=True)
                       if dropped is None or not dropped(a[h], tk)]
        self._sorted = False

    def add_output_time(self, t_s: float) -> None:
        self._times.append(t_s)

    def advance(self, known_until_s: float, final: bool = False) -> list[Event]:
        """Send and deliver at every output epoch ``now`` with ``now + 1e-9 < known_until_s``
        (all of them when ``final``, then everything still in flight); return the complete events."""
        if not self._sorted:  # by (time tag, kind rank, sequence number): seq is unique, so the
            self._msgs.sort(key=_SEND_KEY)  # message itself is never compared
            self._sorted = True
        exch = self.exchange
        i = 0
        n_done = 0
        msgs = self._msgs
        n = len(msgs)
        for now in self._times:
            if not final and not now + 1e-9 < known_until_s:
                break
            j = i
            while j < n and msgs[j][0] <= now + 1e-9:
                j += 1
            if j > i:
                exch.send_many([m[3] for m in msgs[i:j]])
                i = j
            self._delivered += exch.deliver(now)
            n_done += 1
        del self._times[:n_done]
        if final:
            exch.send_many([m[3] for m in msgs[i:]])
            i = n
            self._delivered += exch.deliver(1e18)
        del msgs[:i]
        self._delivered.sort(key=lambda m: (m.t_s, _KIND_RANK[m.kind]))
        if final:
            cut = len(self._delivered)
        else:  # a later delivery has t_s >= processed_until_s - 2e-9 (V2VExchange.deliver)
            s = exch.processed_until_s - 2e-9
            cut = 0
            while cut < len(self._delivered) and self._delivered[cut].t_s < s:
                cut += 1
        ready, self._delivered = self._delivered[:cut], self._delivered[cut:]
        return self._events(ready)

    def _events(self, delivered: list[Message]) -> list[Event]:
        lead_id = self.exchange.lead_id
        events: list[Event] = []
        based: list[Event] = []  # the GNSS events with the lead's epoch, in order
        j = 0
        while j < len(delivered):
            m = delivered[j]
            k = j
            while k < len(delivered) and delivered[k].t_s == m.t_s and delivered[k].kind == m.kind:
                k += 1
            group = delivered[j:k]
            if m.kind == "gnss":
                eps = {g.sender: g.payload for g in group}
                bad, nlos = _bad_prns(eps)
                events.append(Event(m.t_s, "gnss", gnss=eps, bad_prns=bad, nlos_prns=nlos))
                if lead_id in eps:
                    based.append(events[-1])
            elif m.kind == "uwb":
                for g in group:
                    src, idx = g.payload
                    events.append(Event.one_range(m.t_s, src, idx))
            elif m.kind == "bearing":  # every delivered packet of this time tag, in measurement order
                srcs = {id(g.payload[0]): g.payload[0] for g in group}
                if len(srcs) == 1:
                    src = group[0].payload[0]
                    idx = np.sort(np.concatenate([np.asarray(g.payload[1], dtype=np.intp) for g in group]))
                    events.append(Event(m.t_s, "bearing", bearings=src.take(idx)))
                else:  # one time tag split over two chunks' outputs (not expected: bearings are per step)
                    parts = [g.payload[0].take(g.payload[1]) for g in group]
                    events.append(Event(m.t_s, "bearing", bearings=_concat_bearings(parts)))
            j = k
        if based:  # the lead's bases (paper eq. 7) of the delivery, in one call
            bases = self.lead_bases([ev.gnss[lead_id] for ev in based])  # type: ignore[index]
            for ev, base in zip(based, bases, strict=True):
                ev.lead_base_ecef_m = base
        return events


def _one_range(src: UwbRanges, k: int) -> UwbRanges:
    """Range ``k`` of ``src`` as its own UwbRanges (views: slices of src, not copies;
    the same values as ``v2v.sensors.uwb.select_ranges(src, [k])``)."""
    sl = slice(k, k + 1)
    return UwbRanges(t_s=src.t_s[sl], true_t_s=src.true_t_s[sl], a=src.a[sl], b=src.b[sl], range_m=src.range_m[sl],
                     true_range_m=src.true_range_m[sl], los=src.los[sl],
                     errors_m={name: v[sl] for name, v in src.errors_m.items()})


def _concat_bearings(parts: Sequence[Bearings]) -> Bearings:
    return Bearings(
        t_s=np.concatenate([p.t_s for p in parts]), a=tuple(x for p in parts for x in p.a),
        b=tuple(x for p in parts for x in p.b), bearing_rad=np.concatenate([p.bearing_rad for p in parts]),
        true_bearing_rad=np.concatenate([p.true_bearing_rad for p in parts]),
        azimuth_reported_rad=np.concatenate([p.azimuth_reported_rad for p in parts]),
        true_azimuth_rad=np.concatenate([p.true_azimuth_rad for p in parts]), los=np.concatenate([p.los for p in parts]),
    )


def exchange_stream(gnss_epochs: Sequence[tuple[float, dict[str, GnssEpoch]]], uwb: UwbRanges | None,
                    bearings: Bearings | None, exchange: V2VExchange, lead_bases: Callable[[list[GnssEpoch]], list[np.ndarray | None]],
                    output_times: Sequence[float],
                    dropped: Callable[[str, float], bool] | None = None) -> tuple[list[Event], list[float]]:
    """Send every measurement through the V2V exchange and return the delivered events
    (time-tag order, GNSS before UWB before bearings at equal tags) and the output epochs.

    A UWB range travels with its initiator ``a``; a bearing with its measuring vehicle.
    One whole-run :class:`ExchangeStream`.
    """
    xs = ExchangeStream(exchange, lead_bases, dropped)
    for t, eps in gnss_epochs:
        xs.add_gnss(t, eps)
    xs.add_uwb(uwb)
    xs.add_bearings(bearings)
    for t in output_times:
        xs.add_output_time(t)
    return xs.advance(np.inf, final=True), list(output_times)


# --------------------------------------------------------------------------- processing


UPDATE_COLUMNS = ("t_s", "kind", "vehicles", "prn", "nis", "accepted", "faulty")


class UpdateLog:
    """Per-update diagnostics of one solution, kept compact: columns of each chunk are spilled
    to a temporary file (numpy arrays, pickled), so memory does not grow with the run. Read
    them back with :meth:`columns` (or :attr:`SolutionRecord.updates`).

    With ``keep_recent`` set (a run with the replay on), each spilled chunk's columns are also
    kept in memory until :meth:`take_recent` takes them: the replay's per-epoch NIS
    (:func:`epoch_nis_of_rows`) reads them without reading the file back."""

    def __init__(self) -> None:
        self._pending: list[tuple[float | np.ndarray, Sequence[UpdateInfo], Sequence[bool]]] = []  # per event or run
        self._file: Any = None
        self.n = 0
        self.keep_recent = False
        self._recent: list[dict[str, Any]] = []

    def add(self, t_s: float, infos: Sequence[UpdateInfo], faulty: Sequence[bool]) -> None:
        self._pending.append((t_s, infos, faulty))

    def add_records(self, t_s: np.ndarray, infos: Sequence[UpdateInfo], faulty: Sequence[bool]) -> None:
        """Records of several events at once: ``t_s[i]`` is the time tag of record ``i``."""
        self._pending.append((t_s, infos, faulty))

    def flush(self) -> None:
        """Spill the pending updates to the log file as one chunk of compact columns: time
        tags, kinds and vehicle sets as codes into the chunk's name lists, PRN, NIS and the
        flags as arrays. A column batch contributes its columns whole (one kind, all accepted);
        plain records field by field."""
        if not self._pending:
            return
        import pickle
        import tempfile
        import weakref

        pending = self._pending
        code: dict[str, int] = {}  # the chunk's kinds, numbered in order of first appearance
        # Columns as they are gathered: runs (value, count) for the kinds, time tags and
        # flags, which a batch repeats (kinds and accepted flags share their runs: a batch is
        # one run of each, a plain record its own); flat lists for what plain records and a
        # batch's PRN list give value by value; whole arrays for a batch's NIS (and PRN array).
        # One np.repeat / np.array per column at the end, instead of small arrays per segment.
        kind_val: list[int] = []
        acc_val: list[bool] = []
        rep: list[int] = []  # the runs' lengths of kind_val and acc_val
        t_val: list[float] = []
        t_rep: list[int] = []
        vehicles: list[tuple[str, ...]] = []
        nis_parts: list[Any] = []
        nis_flat: list[float] = []  # plain records' NIS since the last batch
        prn_parts: list[Any] = []
        prn_flat: list[int] = []  # PRNs since the last PRN array
        setcode = code.setdefault
        for t, infos, _ in pending:
            n_ev = 0
            for seg in _segments(infos):
                m = len(seg)
                if not m:
                    continue
                n_ev += m
                if isinstance(seg, UpdateBatch):
                    kind_val.append(setcode(seg.kind, len(code)))
                    acc_val.append(True)
                    rep.append(m)
                    vehicles += seg.vehicles
                    if nis_flat:
                        nis_parts.append(np.array(nis_flat, dtype=float))
                        nis_flat = []
                    nis_parts.append(seg.nis)
                    if seg.prn is None:
                        prn_flat += [-1] * m
                    elif isinstance(seg.prn, np.ndarray):
                        if prn_flat:
                            prn_parts.append(np.array(prn_flat, dtype=np.int64))
                            prn_flat = []
                        prn_parts.append(seg.prn)
                    else:
                        prn_flat += seg.prn
                else:
                    k, v, _nu, _s, ni, ac, pr = zip(*seg, strict=True)
                    for x in dict.fromkeys(k):  # (new kinds numbered in order of first appearance)
                        setcode(x, len(code))
                    kind_val += map(code.__getitem__, k)
                    acc_val += ac
                    rep += [1] * m
                    vehicles += v
                    nis_flat += ni
                    prn_flat += pr
            if n_ev:
                if isinstance(t, np.ndarray):
                    t_val += t.tolist()
                    t_rep += [1] * len(t)
                else:
                    t_val.append(t)
                    t_rep.append(n_ev)
        n = len(vehicles)
        if not n:
            self._pending = []
            return
        if nis_flat:
            nis_parts.append(np.array(nis_flat, dtype=float))
        if prn_flat:
            prn_parts.append(np.array(prn_flat, dtype=np.int64))
        # faulty flags: an event's all-False list (most events) as one run
        f_val: list[bool] = []
        f_rep: list[int] = []
        for _, _, fs in pending:
            if any(fs):
                f_val += fs
                f_rep += [1] * len(fs)
            elif len(fs):
                f_val.append(False)
                f_rep.append(len(fs))
        faulty = np.repeat(np.array(f_val, dtype=bool), f_rep)
        if faulty.shape[0] != n:
            raise ValueError(f"the update log got {faulty.shape[0]} faulty flags for {n} updates")
        names = sorted(code)  # each update stores its kind as an index into the chunk's sorted kinds
        to_sorted = np.empty(len(names), dtype=np.int16)
        to_sorted[[code[k] for k in names]] = np.arange(len(names), dtype=np.int16)
        kind_code = to_sorted[np.repeat(np.array(kind_val, dtype=np.int16), rep)]
        veh_index = {v: i for i, v in enumerate(dict.fromkeys(vehicles))}  # the chunk's vehicle sets, first-seen order
        cols = {
            "t_s": np.repeat(np.array(t_val, dtype=float), t_rep),
            "kind_names": names,
            "kind_code": kind_code,
            "vehicle_names": [",".join(v) for v in veh_index],
            "vehicle_code": np.fromiter(map(veh_index.__getitem__, vehicles), np.int32, n),
            "prn": np.concatenate([np.asarray(p, dtype=np.int64) for p in prn_parts]),
            "nis": np.concatenate(nis_parts),
            "accepted": np.repeat(np.array(acc_val, dtype=bool), rep),
            "faulty": faulty,
        }
        if self._file is None:
            self._file = tempfile.TemporaryFile(prefix="v2v_updates_")
            # closed (and so deleted) with the log: its records are read after the run (the
            # experiments keep the SolutionRecord), so not at the run's end; left to the garbage
            # collector's own close, each file was a ResourceWarning under python -X dev
            weakref.finalize(self, self._file.close)
        pickle.dump(cols, self._file, protocol=pickle.HIGHEST_PROTOCOL)
        if self.keep_recent:  # (plus the vehicle sets as tuples, not joined with commas)
            self._recent.append({**cols, "vehicle_sets": list(veh_index)})
        self.n += n
        self._pending = []

    def close(self) -> None:
        """Close (and so delete) the spill file now, not when the log is collected: the log is
        empty afterwards."""
        if self._file is not None:
            self._file.close()
            self._file = None
        self._pending, self._recent, self.n = [], [], 0

    def take_recent(self) -> list[dict[str, Any]]:
        """The columns of the chunks spilled since the last call (``keep_recent`` set; else
        none), each as :meth:`flush` stores it plus ``vehicle_sets`` (the tuples that
        ``vehicle_code`` indexes), and forget them."""
        recent, self._recent = self._recent, []
        return recent

    def kind_statistics(self) -> dict[str, Any]:
        """Per measurement kind (sorted), :func:`v2v.metrics.summary.update_kind_statistics` of
        the whole run, read back one kind at a time as compact arrays (the same numbers as the
        per-update table's, bit for bit: same values in the same order)."""
        return kind_statistics_of([self])

    def _chunks(self, pickle: Any):
        self._file.seek(0)
        while True:
            try:
                yield pickle.load(self._file)
            except EOFError:
                break
        self._file.seek(0, 2)

    def columns(self, names: Sequence[str] = UPDATE_COLUMNS) -> dict[str, list[Any]]:
        """The whole run's updates, column by column (lists, in update order)."""
        import pickle

        self.flush()
        out: dict[str, list[Any]] = {k: [] for k in names}
        if self._file is None:
            return out
        self._file.seek(0)
        while True:
            try:
                cols = pickle.load(self._file)
            except EOFError:
                break
            for k in names:
                if k == "kind":  # stored as indices into the chunk's kind names
                    out[k].extend(map(cols["kind_names"].__getitem__, cols["kind_code"].tolist()))
                elif k == "vehicles":  # likewise
                    out[k].extend(map(cols["vehicle_names"].__getitem__, cols["vehicle_code"].tolist()))
                else:
                    out[k].extend(cols[k].tolist() if isinstance(cols[k], np.ndarray) else cols[k])
        self._file.seek(0, 2)
        return out


def kind_statistics_of(logs: Sequence[UpdateLog]) -> dict[str, Any]:
    """Per measurement kind (sorted), :func:`v2v.metrics.summary.update_kind_statistics` of the
    updates of all of ``logs`` together, log after log, each in update order: one solution's
    statistics pooled over the clusters of a run (each cluster has its own filter and log).
    Of one log: :meth:`UpdateLog.kind_statistics`."""
    import pickle

    from v2v.metrics.summary import update_kind_statistics

    kinds: set[str] = set()
    for log in logs:
        log.flush()
        if log._file is not None:
            for cols in log._chunks(pickle):
                kinds.update(cols["kind_names"])
    out: dict[str, Any] = {}
    for kind in sorted(kinds):
        acc, faulty, nis = [], [], []
        for log in logs:
            if log._file is None:
                continue
            for cols in log._chunks(pickle):
                if kind not in cols["kind_names"]:
                    continue
                m = cols["kind_code"] == cols["kind_names"].index(kind)
                acc.append(cols["accepted"][m])
                faulty.append(cols["faulty"][m])
                nis.append(cols["nis"][m])
        out[kind] = update_kind_statistics(np.concatenate(acc), np.concatenate(faulty), np.concatenate(nis), kind)
    return out


def epoch_nis_of_rows(chunks: Sequence[dict[str, Any]], output_times: ArrayLike, row_t_s: ArrayLike,
                      row_vehicles: Sequence[str]) -> np.ndarray:
    """Per epoch row (time ``row_t_s[j]``, vehicle ``row_vehicles[j]``) the mean NIS of its
    vehicle's accepted measurement updates of that output interval
    (:func:`v2v.metrics.errors.epoch_nis_sums`: the definition), NaN where there is none.

    ``chunks``: update-log columns (:meth:`UpdateLog.take_recent`) holding every update of
    ``output_times``, the filter's output epochs of the span (each row's time one of them).
    """
    times = np.asarray(output_times, dtype=float).reshape(-1)
    t_rows = np.asarray(row_t_s, dtype=float).reshape(-1)
    ids = list(dict.fromkeys(row_vehicles))
    sums = np.zeros((len(times), len(ids)))
    counts = np.zeros((len(times), len(ids)), dtype=np.int64)
    for c in chunks:
        s, n = epoch_nis_sums(times, ids, c["t_s"], c["nis"], c["accepted"], c["kind_code"], c["kind_names"],
                              c["vehicle_code"], c["vehicle_sets"])
        sums += s
        counts += n
    ep = np.searchsorted(times, t_rows - 1e-9, side="left")  # the row's own epoch
    if len(t_rows) and (ep.max() >= len(times) or np.abs(times[ep] - t_rows).max() > 1e-9):
        raise ValueError("epoch_nis_of_rows: a row's time is not one of the output epochs")
    code = {v: i for i, v in enumerate(ids)}
    veh = np.fromiter(map(code.__getitem__, row_vehicles), dtype=np.intp, count=len(t_rows))
    n_row = counts[ep, veh]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n_row > 0, sums[ep, veh] / n_row, np.nan)


@dataclass(slots=True, eq=False)
class EpochBlock:
    """One output epoch of one solution as columns: the rows :func:`_epoch_record` would
    give as dicts (:meth:`rows`), for an epoch whose rows all have the same keys (every
    present vehicle in the filter; azimuth states for all of them or none).

    ``nums`` ``(n, len(EPOCH_COLUMNS))``, ``counts`` ``(n, len(count_keys))``; per row
    ``vehicles``, ``initialized``, ``true_lane``, ``lane_width``, ``integrity`` and
    ``azimuth_err`` (``None``: no azimuth states); ``lead_azimuth_err`` is every row's
    (``None``: the lead has no azimuth state).
    """

    t_s: float
    solution: str
    vehicles: list[str]
    initialized: list[bool]
    nums: np.ndarray
    true_lane: list[int]
    lead_lane: int
    lane_width: list[float]
    count_keys: tuple[str, ...]
    counts: np.ndarray
    integrity: list[bool]
    azimuth_err: list[float] | None
    lead_azimuth_err: float | None

    @property
    def columns(self) -> tuple[tuple[str, ...], bool, bool]:
        """What decides the rows' keys (the frame's columns): the count keys and whether the
        azimuth errors are there."""
        return self.count_keys, self.azimuth_err is not None, self.lead_azimuth_err is not None

    def rows(self) -> list[dict[str, Any]]:
        """The epoch's rows as dicts (:func:`_vehicle_row`)."""
        nums, counts = self.nums.tolist(), self.counts.tolist()
        az = self.azimuth_err
        return [_vehicle_row(self.t_s, self.solution, v, self.initialized[k], nums[k], self.true_lane[k], self.lead_lane,
                             self.lane_width[k], self.count_keys, counts[k], self.integrity[k],
                             None if az is None else az[k], self.lead_azimuth_err)
                for k, v in enumerate(self.vehicles)]


def _vehicle_row(t_s: float, solution: str, vehicle: str, initialized: bool, nums: Sequence[float], true_lane: int,
                 lead_lane: int, lane_width: float, count_keys: Sequence[str], counts: Sequence[int], integrity: bool,
                 azimuth_err: float | None, lead_azimuth_err: float | None) -> dict[str, Any]:
    """One epoch row of a vehicle in the filter, keys in column order (``EPOCH_COLUMNS`` the
    numbers of :func:`v2v.metrics.errors.epoch_errors`; an azimuth error only where given)."""
    row = {"t_s": t_s, "solution": solution, "vehicle": vehicle, "initialized": initialized,
           **dict(zip(EPOCH_COLUMNS, nums, strict=True)),
           "true_lane_index": true_lane, "lead_lane_index": lead_lane, "lane_width_m": lane_width,
           **dict(zip(count_keys, counts, strict=True)), "integrity_available": integrity}
    if azimuth_err is not None:
        row["azimuth_err_rad"] = azimuth_err
    if lead_azimuth_err is not None:
        row["lead_azimuth_err_rad"] = lead_azimuth_err
    return row


def _flat_rows(epochs: Sequence[EpochBlock | list[dict[str, Any]]]) -> list[dict[str, Any]]:
    return [r for e in epochs for r in (e.rows() if isinstance(e, EpochBlock) else e)]


def _blocks_frame(blocks: Sequence[EpochBlock]) -> pd.DataFrame:
    """``pandas.DataFrame`` of the blocks' rows (blocks with the same keys), column by column:
    the dtypes pandas' records constructor infers from the dict rows (float64, int64, bool,
    and its string dtype for the names)."""
    import pandas as pd

    b0 = blocks[0]
    n = [len(b.vehicles) for b in blocks]
    nums = np.concatenate([b.nums for b in blocks])
    counts = np.concatenate([b.counts for b in blocks])
    cols: dict[str, Any] = {
        "t_s": np.repeat(np.array([b.t_s for b in blocks], dtype=np.float64), n),
        "solution": [b.solution for b in blocks for _ in b.vehicles],
        "vehicle": [v for b in blocks for v in b.vehicles],
        "initialized": np.array([x for b in blocks for x in b.initialized], dtype=bool),
    }
    for j, c in enumerate(EPOCH_COLUMNS):
        cols[c] = nums[:, j]
    cols["true_lane_index"] = np.array([x for b in blocks for x in b.true_lane], dtype=np.int64)
    cols["lead_lane_index"] = np.repeat(np.array([b.lead_lane for b in blocks], dtype=np.int64), n)
    cols["lane_width_m"] = np.array([x for b in blocks for x in b.lane_width], dtype=np.float64)
    for j, c in enumerate(b0.count_keys):
        cols[c] = counts[:, j]
    cols["integrity_available"] = np.array([x for b in blocks for x in b.integrity], dtype=bool)
    if b0.azimuth_err is not None:
        cols["azimuth_err_rad"] = np.array([x for b in blocks for x in b.azimuth_err or ()], dtype=np.float64)
    if b0.lead_azimuth_err is not None:
        cols["lead_azimuth_err_rad"] = np.repeat(np.array([b.lead_azimuth_err for b in blocks], dtype=np.float64), n)
    return pd.DataFrame(cols)


def empty_epochs_frame() -> pd.DataFrame:
    """``epochs.parquet``'s table of a run that estimated nothing (no solution, or no cluster
    with a follower): :func:`_blocks_frame` of an epoch without vehicles (so the columns every
    epochs table has; the per-type update counts and azimuth errors depend on the solutions,
    so they are not there), with the run's ``cluster`` column and its names typed as strings."""
    b = EpochBlock(t_s=0.0, solution="", vehicles=[], initialized=[], nums=np.zeros((0, len(EPOCH_COLUMNS))),
                   true_lane=[], lead_lane=0, lane_width=[], count_keys=(), counts=np.zeros((0, 0), dtype=np.int64),
                   integrity=[], azimuth_err=None, lead_azimuth_err=None)
    frame = _blocks_frame([b]).astype({"solution": "str", "vehicle": "str"})
    frame.insert(1, "cluster", frame["solution"])  # (as the run inserts it: after t_s)
    return frame


@dataclass
class SolutionRecord:
    """Per-epoch estimates and per-update diagnostics of one solution.

    ``rows`` holds the epochs not yet taken by :meth:`take_rows` (a streamed run takes them
    every chunk); ``updates`` reads the compact per-update log back (columns
    :data:`UPDATE_COLUMNS`).
    """

    name: str
    membership: list[tuple[float, str, str]] = field(default_factory=list)  # (t_s, vehicle, left|joined)
    counters: dict[str, int] = field(default_factory=dict)  # the filter's event counters at the end
    log: UpdateLog = field(default_factory=UpdateLog)
    # epochs not yet taken: an EpochBlock (the usual epoch) or the epoch's dict rows
    _epochs: list[EpochBlock | list[dict[str, Any]]] = field(default_factory=list, repr=False)

    @property
    def updates(self) -> dict[str, list[Any]]:
        return self.log.columns()

    @property
    def rows(self) -> dict[str, list[Any]]:
        """The epochs not yet taken, as columns (a column that first appears in a later row,
        e.g. after a vehicle rejoined, is NaN before it; so is a key a row lacks)."""
        rows = _flat_rows(self._epochs)
        keys: dict[str, None] = {}
        for r in rows:
            if len(r) != len(keys) or r.keys() != keys.keys():
                keys.update(dict.fromkeys(r))
        nan = float("nan")
        return {k: [r.get(k, nan) for r in rows] for k in keys}

    def add_row(self, row: dict[str, Any]) -> None:
        self._epochs.append([row])

    def add_epoch(self, epoch: EpochBlock | list[dict[str, Any]]) -> None:
        """One output epoch's rows: an :class:`EpochBlock` or a list of row dicts (none: nothing)."""
        if isinstance(epoch, EpochBlock) or epoch:
            self._epochs.append(epoch)

    def take_rows(self) -> list[dict[str, Any]]:
        """The epochs recorded since the last call (one dict per row), and forget them.

        ``pandas.DataFrame`` of them is the frame of :attr:`rows`: columns in order of first
        appearance, NaN where a row lacks a key (:meth:`take_frame` builds it faster)."""
        epochs, self._epochs = self._epochs, []
        return _flat_rows(epochs)

    def take_frame(self) -> pd.DataFrame | None:
        """The frame of the epochs recorded since the last call (``None``: none), and forget
        them: ``pandas.DataFrame(take_rows())``, built from the blocks' columns when every
        epoch is an :class:`EpochBlock` with the same columns (the usual chunk: ~3x faster
        than pandas' records constructor on the dict rows), else from the rows."""
        import pandas as pd

        epochs, self._epochs = self._epochs, []
        if not epochs:
            return None
        first = epochs[0]
        if isinstance(first, EpochBlock) and all(isinstance(e, EpochBlock) and e.columns == first.columns
                                                 for e in epochs):
            return _blocks_frame(epochs)  # type: ignore[arg-type]
        rows = _flat_rows(epochs)
        return pd.DataFrame(rows) if rows else None


def _corrupting_prns(ev: Event, kind: str) -> dict[str, frozenset[int]] | None:
    """Per vehicle, the PRNs whose ``kind`` GNSS measurement the simulator corrupted: NLOS or an
    injected fault for (pair) SD pseudoranges, NLOS for SD Dopplers (an echo's Doppler carries
    its path rate; the faults are on the pseudorange); None for other kinds."""
    if kind not in (KIND_SD_PR, KIND_SD_PR_PAIR, KIND_SD_DOPPLER) or ev.gnss is None:
        return None
    if ev.bad_prns is None:
        bad, nlos = _bad_prns(ev.gnss)
    else:
        bad, nlos = ev.bad_prns, ev.nlos_prns if ev.nlos_prns is not None else _bad_prns(ev.gnss)[1]
    return nlos if kind == KIND_SD_DOPPLER else bad


def _faulty(info: UpdateInfo, ev: Event, lead: str | None = None) -> bool:
    """Did the simulator corrupt this measurement beyond the filter's model (NLOS or an injected
    fault)? A single difference with the lead (SD pseudorange ``P_v - P_lead``, SD Doppler) is
    corrupted when either receiver's signal is (the lead's only when ``lead`` is given); a pair
    SD by either of its two vehicles."""
    sets = _corrupting_prns(ev, info.kind)
    if sets is not None:
        vehs = info.vehicles + (lead,) if info.kind != KIND_SD_PR_PAIR and lead is not None else info.vehicles
        return any(info.prn in sets.get(v, ()) for v in vehs)
    if info.kind == KIND_UWB and ev.uwb is not None:
        return not bool(ev.uwb.los[0]) or float(ev.uwb.errors_m.get("fault", np.zeros(1))[0]) != 0.0
    if info.kind == KIND_BEARING and ev.bearings is not None:
        return not bool(np.all(ev.bearings.los))
    return False


def _faulty_flags(infos: Sequence[UpdateInfo], ev: Event, lead: str | None = None) -> list[bool]:
    """:func:`_faulty` of every update of one event, with the event-level work done once
    (most GNSS events have no NLOS / faulted satellite at all); the batches of an
    :class:`Updates` from their columns (one kind each)."""
    if ev.kind == "gnss":
        bad = ev.bad_prns if ev.bad_prns is not None else (_bad_prns(ev.gnss)[0] if ev.gnss is not None else {})
        if not any(bad.values()):
            return [False] * len(infos)
        out: list[bool] = []
        for seg in _segments(infos):
            if isinstance(seg, UpdateBatch):
                sets = _corrupting_prns(ev, seg.kind)
                if sets is not None and seg.prn is not None:
                    also = sets.get(lead, frozenset()) if lead is not None and seg.kind != KIND_SD_PR_PAIR else frozenset()
                    out += [p in also or any(p in sets.get(v, ()) for v in vehs)
                            for vehs, p in zip(seg.vehicles, seg.prn, strict=True)]
                else:
                    out += [False] * len(seg)
            else:
                out += [_faulty(info, ev, lead) for info in seg]
        return out
    if ev.kind in ("uwb", "bearing"):
        own = KIND_UWB if ev.kind == "uwb" else KIND_BEARING
        if ev.kind == "uwb" and ev.uwb is not None:
            f = not bool(ev.uwb.los[0]) or float(ev.uwb.errors_m.get("fault", np.zeros(1))[0]) != 0.0
        elif ev.kind == "bearing" and ev.bearings is not None:
            f = not bool(np.all(ev.bearings.los))
        else:
            return [_faulty(info, ev) for info in infos]
        if not f:
            return [False] * len(infos)
        out = []
        for seg in _segments(infos):
            out += [seg.kind == own] * len(seg) if isinstance(seg, UpdateBatch) else [info.kind == own for info in seg]
        return out
    return [_faulty(info, ev) for info in infos]


def _kinds(infos: Sequence[UpdateInfo]) -> list[str]:
    """The kind of each record of ``infos`` (batches from their one kind)."""
    out: list[str] = []
    for seg in _segments(infos):
        out += [seg.kind] * len(seg) if isinstance(seg, UpdateBatch) else [info.kind for info in seg]
    return out


def _segments(infos: Sequence[UpdateInfo]) -> Sequence[Sequence[UpdateInfo]]:
    """The record lists and column batches of ``infos`` (an :class:`Updates`), or ``infos`` as one piece."""
    return infos.parts if isinstance(infos, Updates) else (infos,)


class SolutionRunner:
    """One solution's filter over a cluster's event stream, resumable chunk by chunk.

    :meth:`run` processes output epochs given the events (in time-tag order) that contain
    every event up to the last of those epochs; the loop state (filter time, pending update
    infos, last GNSS epoch for the carrier-phase truth, previous output time, membership)
    is kept across calls, so chunked processing equals one whole-run :func:`run_solution`.
    """

    def __init__(self, sol: SolutionSection, ekf: ClusterEkf, lead: str, vehicles: Sequence[str],
                 on_epoch: Callable[[float, str, ClusterEkf, TrafficStep, list[dict[str, Any]]], None] | None = None):
        self.sol, self.ekf, self.lead, self.vehicles = sol, ekf, lead, list(vehicles)
        self.on_epoch = on_epoch
        self.rec = SolutionRecord(sol.name)
        self.use = set(sol.sensors)
        self.t_filter: float | None = None
        self.pending = Updates()
        self.last_gnss: tuple[float, dict[str, GnssEpoch]] | None = None  # for the phase truth (wrong fixes)
        self.t_prev_out: float | None = None
        self.members = set(vehicles)
        self.last_heard: dict[str, float] = {}
        self.consumed = 0  # events consumed by the last call of run_solution(runner=self)

    def run(self, events: Sequence[Event], output_times: Iterable[float],
            truth_at: Callable[[float], TrafficStep | None]) -> int:
        """Process ``output_times``; returns how many leading ``events`` were consumed."""
        sol, ekf, lead, vehicles, rec = self.sol, self.ekf, self.lead, self.vehicles, self.rec
        use, members, last_heard = self.use, self.members, self.last_heard
        aid_sigma = sol.height_aiding_sigma
        t_filter, pending, last_gnss, t_prev_out = self.t_filter, self.pending, self.last_gnss, self.t_prev_out
        ei = 0
        n_events = len(events)
        for t_out in output_times:
            # Cluster membership as the lead sees it: a vehicle silent for LEAVE_AFTER_S has left
            # (its block is marginalized out); its next GNSS message adds it back (re-initialized).
            for v in list(ekf.layout.vehicles):
                if t_out - last_heard.setdefault(v, t_out) > LEAVE_AFTER_S:
                    ekf.remove_vehicle(v)
                    rec.membership.append((t_out, v, "left"))
            # a usable GNSS epoch in this output interval? (look ahead only within it)
            has_gnss = False
            k = ei
            while k < n_events and events[k].t_s <= t_out + 1e-9:
                if events[k].kind == "gnss" and events[k].lead_base_ecef_m is not None:
                    has_gnss = True
                    break
                k += 1
            if not has_gnss:
                ekf.gnss_unavailable()
            aided = False
            while ei < n_events and events[ei].t_s <= t_out + 1e-9:
                ev = events[ei]
                if (ev.kind == "uwb" and "uwb" in use and t_filter is not None
                        and (has_gnss or aided or aid_sigma is None)):
                    # a run of UWB events (one time tag each at 3 Hz x all pairs): predict + update
                    # of every one in a single compiled call (ClusterEkf.update_uwb_events)
                    ei, t_filter, infos = self._uwb_run(events, ei, t_out, t_filter)
                    pending += infos
                    continue
                ei += 1
                # any message counts as "heard", whatever sensors this solution uses
                heard = (ev.gnss or {}).keys() if ev.kind == "gnss" else (
                    set(ev.uwb.a) | set(ev.uwb.b) if ev.kind == "uwb" and ev.uwb is not None else
                    set(ev.bearings.a) if ev.bearings is not None else set())
                for v in heard:
                    last_heard[v] = ev.t_s
                if ev.kind not in use:
                    continue
                if ev.kind == "gnss":
                    for v in heard:
                        if v in members and v != lead and v not in ekf.layout.vehicles:
                            ekf.add_vehicle(v)
                            rec.membership.append((ev.t_s, v, "joined"))
                if t_filter is None:
                    t_filter = ev.t_s
                ekf.predict(max(0.0, ev.t_s - t_filter))
                t_filter = max(t_filter, ev.t_s)
                infos = Updates()
                if not has_gnss and not aided and aid_sigma is not None:
                    infos += ekf.update_height_aiding(aid_sigma)
                    aided = True
                if ev.kind == "gnss":
                    if ev.lead_base_ecef_m is None:
                        continue
                    infos = ekf.update_gnss(ev.gnss or {}, ev.lead_base_ecef_m)
                    last_gnss = (ev.t_s, ev.gnss or {})
                elif ev.kind == "uwb":
                    infos += ekf.update_uwb(ev.uwb)  # type: ignore[arg-type]
                else:
                    infos += ekf.update_bearings(ev.bearings)  # type: ignore[arg-type]
                if infos:
                    rec.log.add(ev.t_s, infos, _faulty_flags(infos, ev, lead))
                pending += infos
            if t_filter is None:
                continue
            ekf.predict(max(0.0, t_out - t_filter))
            t_filter = max(t_filter, t_out)
            step = truth_at(t_out)
            if step is None or lead not in step.vehicles:
                pending = Updates()
                continue
            epoch = _epoch_record(sol.name, t_out, ekf, step, lead, vehicles, pending)
            if ekf.config.phase is not None:
                rows = epoch.rows() if isinstance(epoch, EpochBlock) else epoch
                # the status belongs to a GNSS epoch delivered in this output interval (t_prev_out, t_out]
                fresh = last_gnss is not None and (t_prev_out is None or last_gnss[0] > t_prev_out + 1e-9)
                _phase_columns(rows, ekf, last_gnss[1] if fresh and last_gnss is not None else None, lead)
                epoch = rows
            t_prev_out = t_out
            rec.add_epoch(epoch)
            if self.on_epoch is not None:
                self.on_epoch(t_out, sol.name, ekf, step, epoch.rows() if isinstance(epoch, EpochBlock) else epoch)
            pending = Updates()
        self.t_filter, self.pending, self.last_gnss, self.t_prev_out = t_filter, pending, last_gnss, t_prev_out
        rec.log.flush()
        return ei

    def _uwb_run(self, events: Sequence[Event], ei: int, t_out: float,
                 t_filter: float) -> tuple[int, float, Updates]:
        """The UWB events from ``events[ei]`` up to the next other event or ``t_out``, as
        the loop of :meth:`run` would process them; returns (next event index, filter time,
        their update records). The ranges are read from the columns of their sources
        (:attr:`Event.uwb_source`) and filtered in one :meth:`ClusterEkf.update_uwb_run`
        call; the update log gets each record with its event's time tag and faulty flag."""
        n = len(events)
        last_heard = self.last_heard
        e0 = ei
        while ei < n and events[ei].kind == "uwb" and events[ei].t_s <= t_out + 1e-9:
            ei += 1
        src0 = events[e0].uwb_source if ei > e0 else None
        if src0 is not None and all(ev.uwb_source is src0 for ev in events[e0 + 1:ei]):
            # the usual run: one range per event, all from one chunk's columns, gathered at once
            t_filter, infos = self._uwb_run_columns(events[e0:ei], src0, t_filter)
            return ei, t_filter, infos
        dts: list[float] = []
        t_ev: list[float] = []
        a: list[str] = []
        b: list[str] = []
        z: list[float] = []
        bad: list[bool] = []  # NLOS or an injected fault (what _faulty_flags says of a UWB event)
        for ev in events[e0:ei]:
            src: UwbRanges | None = ev.uwb_source
            ks: tuple[int, ...]
            if src is not None:  # one range of a chunk's columns (what the exchange delivers)
                ks = (ev.uwb_index,)
            else:  # an event built with its own range object: all its ranges at its time tag
                src = ev.uwb
                assert src is not None
                ks = tuple(range(src.n))
            fault = src.errors_m.get("fault")
            for i, k in enumerate(ks):
                ak, bk = src.a[k], src.b[k]
                last_heard[ak] = ev.t_s
                last_heard[bk] = ev.t_s
                a.append(ak)
                b.append(bk)
                z.append(src.range_m[k])
                bad.append(not bool(src.los[k]) or (fault is not None and float(fault[k]) != 0.0))
                t_ev.append(ev.t_s)
                dts.append(max(0.0, ev.t_s - t_filter) if i == 0 else 0.0)  # (no prediction within an event)
            t_filter = max(t_filter, ev.t_s)
        return ei, t_filter, self._uwb_updates(dts, a, b, np.array(z, dtype=float), bad, t_ev)

    def _uwb_run_columns(self, run: Sequence[Event], src: UwbRanges, t_filter: float) -> tuple[float, Updates]:
        """:meth:`_uwb_run` of events that each hold one range of the same ``src`` (what the
        exchange delivers within a chunk): the same ranges, time tags, predictions and flags,
        gathered from the columns with one index array. Returns (filter time, records)."""
        idx = [ev.uwb_index for ev in run]
        t_ev = [ev.t_s for ev in run]
        a = [src.a[k] for k in idx]
        b = [src.b[k] for k in idx]
        last_heard = self.last_heard
        dts: list[float] = []
        for ak, bk, t in zip(a, b, t_ev, strict=True):
            last_heard[ak] = t
            last_heard[bk] = t
            dts.append(max(0.0, t - t_filter))
            t_filter = max(t_filter, t)
        ix = np.array(idx, dtype=np.intp)
        fault = src.errors_m.get("fault")
        bad = ~np.asarray(src.los, dtype=bool)[ix]
        if fault is not None:
            bad |= np.asarray(fault, dtype=float)[ix] != 0.0
        return t_filter, self._uwb_updates(dts, a, b, np.array(src.range_m[ix], dtype=float), bad.tolist(), t_ev)

    def _uwb_updates(self, dts: list[float], a: list[str], b: list[str], z: np.ndarray, bad: list[bool],
                     t_ev: list[float]) -> Updates:
        """One :meth:`ClusterEkf.update_uwb_run` of a run's ranges; the update log gets each
        record with its event's time tag and faulty flag (``bad``: NLOS or an injected fault)."""
        event_of, infos = self.ekf.update_uwb_run(dts, a, b, z)
        if not len(infos):
            return Updates()
        if any(bad):
            faulty = [bad[e] and info_kind == KIND_UWB for e, info_kind in zip(event_of, _kinds(infos), strict=True)]
        else:
            faulty = [False] * len(infos)
        self.rec.log.add_records(np.array(t_ev)[event_of], infos, faulty)
        return Updates([infos])

    def finish(self) -> SolutionRecord:
        self.rec.counters = dict(self.ekf.counters)
        self.rec.log.flush()
        return self.rec


def run_solution(sol: SolutionSection, ekf: ClusterEkf, events: Sequence[Event], output_times: Sequence[float],
                 truth_at: Callable[[float], TrafficStep | None], lead: str, vehicles: Sequence[str],
                 on_epoch: Callable[[float, str, ClusterEkf, TrafficStep, list[dict[str, Any]]], None] | None = None,
                 runner: SolutionRunner | None = None) -> SolutionRecord:
    """Filter the delivered events with one solution and record an estimate at every output epoch.

    Output epochs are the GNSS epoch grid (they continue through GNSS outages). In an
    output interval with no usable GNSS, a solution with ``height_aiding`` on adds the
    "relative up = h_v - h_lead" pseudo-measurement once, before its UWB and bearing updates (UWB and
    bearings carry no vertical information; see ``FilterConfig.height_aiding_sigma_m``), and
    every solution's filter is told (:meth:`ClusterFilterBase.gnss_unavailable`: no vehicle has
    integrity in such an epoch).
    One whole-run :class:`SolutionRunner`; or, given ``runner`` (a streamed run, chunk by
    chunk), that runner continued over ``output_times`` (``sol``, ``ekf``, ``lead``,
    ``vehicles``, ``on_epoch`` are then the runner's own): the returned record is the same
    object every chunk, its ``rows`` holding the epochs since the caller last took them.
    """
    if runner is None:
        runner = SolutionRunner(sol, ekf, lead, vehicles, on_epoch=on_epoch)
    runner.consumed = runner.run(events, output_times, truth_at)
    return runner.finish()


_KIND_COLUMNS = {"sd_pseudorange": "pr", "sd_pseudorange_pair": "pr", "sd_doppler": "doppler", "sd_phase": "phase"}


_COUNT_KEYS: dict[tuple[str, bool], str] = {}  # (kind, accepted) -> "used_<kind>" | "rejected_<kind>"


def _update_counts(infos: Sequence[UpdateInfo]) -> dict[str, dict[str, int]]:
    """``{vehicle: {"used_<kind>" | "rejected_<kind>": count}}`` of an output interval's updates
    (an update counts once for each vehicle it names). A batch's vehicles are counted from its
    column in one pass (tens of thousands of records per epoch in a large cluster: bearings
    and ranges name a distinct pair each)."""
    per: dict[str, Counter[str]] = {}  # batches: count key -> vehicle -> count
    pairs: Counter[tuple[str, str]] = Counter()  # plain records: (vehicle, count key) -> count
    for p in (infos.parts if isinstance(infos, Updates) else [infos]):
        if isinstance(p, UpdateBatch):  # all accepted
            key = _count_key(p.kind, True)
            c = per.get(key)
            if c is None:
                c = per[key] = Counter()
            c.update(itertools.chain.from_iterable(p.vehicles))
        else:
            pairs.update((v, _count_key(info.kind, info.accepted)) for info in p for v in info.vehicles)
    counts: dict[str, dict[str, int]] = {}
    for key, c in per.items():
        for v, n in c.items():
            counts.setdefault(v, {})[key] = n
    for (v, key), n in pairs.items():
        cv = counts.setdefault(v, {})
        cv[key] = cv.get(key, 0) + n
    return counts


def _count_key(kind: str, accepted: bool) -> str:
    """"used_<kind>" | "rejected_<kind>" (short kind names: :data:`_KIND_COLUMNS`)."""
    key = _COUNT_KEYS.get((kind, accepted))
    if key is None:
        key = _COUNT_KEYS[(kind, accepted)] = ("used_" if accepted else "rejected_") + _short(kind)
    return key


# the update-count columns of an epoch row, in column order (used_<kind>, rejected_<kind> per kind)
_ROW_COUNT_KEYS = tuple(f"{pre}_{kind}" for kind in ("pr", "doppler", "uwb", "bearing") for pre in ("used", "rejected"))
_ROW_COUNT_KEYS_PHASE = _ROW_COUNT_KEYS + ("used_phase", "rejected_phase")


def _epoch_record(name: str, t_s: float, ekf: ClusterEkf, step: TrafficStep, lead: str, vehicles: Sequence[str],
                  infos: Sequence[UpdateInfo]) -> EpochBlock | list[dict[str, Any]]:
    """One row per cluster vehicle at output epoch ``t_s``: truth and estimate relative to the
    lead (ENU), errors and 1-sigma in the lead's frame (along, across-left, up), NEES of the
    position, update counts; the numbers of all vehicles from one compiled call
    (:func:`v2v.metrics.errors.epoch_errors`). As an :class:`EpochBlock` when every present
    vehicle is in the filter and all or none of them have an azimuth state (the usual epoch),
    else as dict rows (a vehicle that left the cluster, as the lead sees it, has a row without
    an estimate)."""
    lead_st = step.vehicles[lead]
    x, P = ekf.state_arrays()  # (epoch_errors only reads them)
    lay = ekf.layout
    counts = _update_counts(infos)
    est_v = [v for v in vehicles if v in step.vehicles and v in lay.vehicles]
    if est_v:
        sts = [step.vehicles[v] for v in est_v]
        a = float(lead_st.azimuth_rad)
        nums = epoch_errors(
            x, P, np.array([lay.position_starts[v] for v in est_v]), np.array([lay.velocity_starts[v] for v in est_v]),
            np.array([st.ecef_m for st in sts], dtype=float), np.asarray(lead_st.ecef_m, dtype=float),
            ecef_to_enu_rotation(lead_st.lat_rad, lead_st.lon_rad), np.array([st.vel_enu_mps for st in sts], dtype=float),
            np.array([(st.lat_rad, st.lon_rad) for st in sts], dtype=float), np.asarray(lead_st.vel_enu_mps, dtype=float),
            float(np.sin(a)), float(np.cos(a)), np.array([ekf.is_initialized(v) for v in est_v]))
    count_keys = _ROW_COUNT_KEYS_PHASE if ekf.config.phase is not None else _ROW_COUNT_KEYS
    integrity = getattr(ekf, "integrity_available", {})
    lead_az = (float(_wrap(ekf.azimuth_rad(lead) - lead_st.azimuth_rad)) if ekf.is_azimuth_initialized(lead)
               else float("nan")) if lay.has("azimuth", lead) else None
    has_az = [lay.has("azimuth", v) for v in est_v]
    present = [v for v in vehicles if v in step.vehicles]
    if est_v and present == est_v and (all(has_az) or not any(has_az)):
        return EpochBlock(
            t_s=t_s, solution=name, vehicles=est_v, initialized=[ekf.is_initialized(v) for v in est_v], nums=nums,
            true_lane=[st.lane_index for st in sts], lead_lane=lead_st.lane_index,
            lane_width=[st.lane_width_m for st in sts], count_keys=count_keys,
            counts=np.array([[counts.get(v, {}).get(key, 0) for key in count_keys] for v in est_v], dtype=np.int64),
            integrity=[bool(integrity.get(v, False)) for v in est_v],
            azimuth_err=[_azimuth_err(ekf, v, st) for v, st in zip(est_v, sts, strict=True)] if has_az[0] else None,
            lead_azimuth_err=lead_az)
    num = dict(zip(est_v, nums.tolist(), strict=True)) if est_v else {}
    gone = [v for v in present if v not in lay.vehicles]
    if gone:  # left the cluster (as the lead sees it): the truth only, as an uninitialized vehicle's row
        sts = [step.vehicles[v] for v in gone]
        a = float(lead_st.azimuth_rad)
        k = len(gone)
        truth_only = epoch_errors(  # (no state of theirs: a placeholder the kernel does not use when not ready)
            np.zeros(6), np.eye(6), np.zeros(k, dtype=np.int64), np.full(k, 3, dtype=np.int64),
            np.array([st.ecef_m for st in sts], dtype=float), np.asarray(lead_st.ecef_m, dtype=float),
            ecef_to_enu_rotation(lead_st.lat_rad, lead_st.lon_rad), np.array([st.vel_enu_mps for st in sts], dtype=float),
            np.array([(st.lat_rad, st.lon_rad) for st in sts], dtype=float), np.asarray(lead_st.vel_enu_mps, dtype=float),
            float(np.sin(a)), float(np.cos(a)), np.zeros(k, dtype=bool))
        num.update(zip(gone, truth_only.tolist(), strict=True))
    rows = []
    for v in vehicles:
        st = step.vehicles.get(v)
        if st is None:
            continue
        c = counts.get(v, {})
        if v not in lay.vehicles:  # no estimate, no update, no integrity screen, no azimuth state
            rows.append(_vehicle_row(t_s, name, v, False, num[v], st.lane_index, lead_st.lane_index, st.lane_width_m,
                                     count_keys, [c.get(key, 0) for key in count_keys], False, None, lead_az))
            continue
        rows.append(_vehicle_row(t_s, name, v, ekf.is_initialized(v), num[v], st.lane_index, lead_st.lane_index,
                                 st.lane_width_m, count_keys, [c.get(key, 0) for key in count_keys],
                                 bool(integrity.get(v, False)),
                                 _azimuth_err(ekf, v, st) if lay.has("azimuth", v) else None, lead_az))
    return rows


def _azimuth_err(ekf: ClusterEkf, v: str, st: Any) -> float:
    """The azimuth state's error (wrapped, rad); NaN before it is initialized."""
    return float(_wrap(ekf.azimuth_rad(v) - st.azimuth_rad)) if ekf.is_azimuth_initialized(v) else float("nan")


def _phase_columns(rows: list[dict[str, Any]], ekf: ClusterEkf, gnss: dict[str, GnssEpoch] | None,
                   lead: str) -> None:
    """Ambiguity-resolution columns of a carrier-phase solution: ``phase_state`` (fixed /
    partial / float; "" without a GNSS epoch in this output interval), ``n_dd``, ``n_fixed``,
    ``ar_ratio``, ``ar_success_rate`` and ``wrong_fix`` (a fixed combination differs from the
    true integers: the simulator knows them; NaN when nothing is fixed)."""
    for r in rows:
        if "est_e_m" not in r:
            continue
        st = ekf.phase_status.get(r["vehicle"]) if gnss is not None else None
        if st is None:
            r.update(phase_state="", n_dd=0, n_eligible=0, n_fixed=0, ar_ratio=float("nan"), ar_success_rate=float("nan"),
                     wrong_fix=float("nan"))
            continue
        wf = wrong_fix(st, gnss.get(r["vehicle"]), gnss.get(lead)) if gnss is not None else None
        r.update(phase_state=st.state, n_dd=st.n_dd, n_eligible=st.n_eligible, n_fixed=st.n_fixed, ar_ratio=st.ratio,
                 ar_success_rate=st.success_rate, wrong_fix=float("nan") if wf is None else float(wf))


def _wrap(a: float) -> float:
    from v2v.frames import wrap_angle

    return float(wrap_angle(a))


def _short(kind: str) -> str:
    return _KIND_COLUMNS.get(kind, kind)


def enu_rotation(lat_rad: float, lon_rad: float) -> np.ndarray:
    return ecef_to_enu_rotation(lat_rad, lon_rad)
