"""Update records and the per-update log.

The production engine builds its ``UpdateInfo`` records from the compiled kernels' output
arrays in bulk (one C-level map per kernel call); the reference engine builds each one in
Python from the scalar update it just made. Every field must agree: kind, vehicles, PRN and
accepted exactly, innovation and variance to the engines' 1e-9 relative agreement (see
tests/test_engines_agree.py), and ``nis`` must be ``innovation**2 / variance`` of the same
record, bit for bit (the definition in ``UpdateInfo``'s docstring).

The log (:class:`v2v.pipeline.UpdateLog`) keeps its chunks compact; its per-kind statistics
must equal :func:`v2v.metrics.summary.update_kind_statistics` applied to the updates of each
kind in update order, computed here straight from the records that went in.
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from v2v.estimation.filter import ClusterEkf, FilterConfig, UpdateBatch, UpdateInfo, Updates
from v2v.estimation.layout import StateLayout
from v2v.estimation.reference import ReferenceClusterEkf
from v2v.estimation.simulate import SimScenario, run_filter, simulate, vehicle_ids
from v2v.frames import ecef_to_enu_rotation, ecef_to_geodetic
from v2v.metrics.summary import update_kind_statistics
from v2v.pipeline import Event, SolutionRunner, UpdateLog, _faulty, _faulty_flags, _update_counts


def test_production_records_match_reference_field_by_field():
    """Six vehicles (all-vehicle GNSS kernels with several vehicles per call), UWB between
    every pair, bearings from two vehicles, one PR blunder so that a batch also takes the
    per-record path (a rejection is counted there)."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=6, duration_s=3.0, turn_rate_rps=0.05, bearing_vehicles=("lead", "v1"))
    ids = vehicle_ids(6)
    lay = StateLayout.build(lead="lead", vehicles=ids[1:], azimuth_vehicles=("lead", "v1"))
    eps = simulate(scn, cfg, np.random.default_rng(3))
    v2 = eps[20].gnss["v2"]
    v2.pseudorange_m[0] += 60.0  # blunder: > 10 sigma of an SD pseudorange
    prod, ref = ClusterEkf(lay, cfg), ReferenceClusterEkf(lay, cfg)
    kinds: set[str] = set()
    n_rec = n_batch = 0
    for (_, ip), (_, ir) in zip(run_filter(prod, eps, scn.dt_s), run_filter(ref, eps, scn.dt_s), strict=True):
        assert len(ip) == len(ir)
        for a, b in zip(ip, ir, strict=True):
            assert type(a) is UpdateInfo
            assert (a.kind, a.vehicles, a.prn, a.accepted) == (b.kind, b.vehicles, b.prn, b.accepted)
            assert abs(a.variance - b.variance) <= 1e-9 * abs(b.variance)
            assert abs(a.innovation - b.innovation) <= 1e-9 * np.sqrt(b.variance)
            assert a.nis == a.innovation * a.innovation / a.variance
            kinds.add(a.kind)
        n_rec += len(ip)
        n_batch += sum(len(p) for p in ip.parts if isinstance(p, UpdateBatch))
    assert kinds >= {"sd_pseudorange", "sd_doppler", "uwb", "bearing"}
    assert n_batch > 0.9 * n_rec  # most records come as column batches (all accepted), built only here
    assert prod.counters == ref.counters
    assert prod.counters.get("rejected_sd_pseudorange", 0) >= 1  # the blunder went through the per-record path
    assert n_rec > 1000


def test_records_and_counters_match_with_unusable_measurements():
    """The bulk paths' fall-backs: a non-finite SD Doppler (that vehicle's satellite left out
    and counted, the all-vehicle gathers rebuilt), a non-finite UWB range and one naming an
    unknown radio (the per-range usability checks count them), UWB ranges deferred as too
    nonlinear while P is still large (counted, no record). Records field by field and every
    counter must equal the reference engine's, which takes the Python path for each."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=4, duration_s=2.0, turn_rate_rps=0.05, bearing_vehicles=("lead",))
    ids = vehicle_ids(4)
    lay = StateLayout.build(lead="lead", vehicles=ids[1:], azimuth_vehicles=("lead",))
    eps = simulate(scn, cfg, np.random.default_rng(8))
    eps[6].gnss["v2"].doppler_mps[1] = np.nan
    eps[9].gnss["lead"].doppler_mps[0] = np.inf
    u = next(ep.uwb for ep in eps[5:] if ep.uwb is not None and ep.uwb.n >= 2)
    u.range_m[0] = np.nan
    u2 = next(ep.uwb for ep in eps[12:] if ep.uwb is not None and ep.uwb.n >= 2)
    object.__setattr__(u2, "b", ("nobody", *u2.b[1:]))
    prod, ref = ClusterEkf(lay, cfg), ReferenceClusterEkf(lay, cfg)
    for (_, ip), (_, ir) in zip(run_filter(prod, eps, scn.dt_s), run_filter(ref, eps, scn.dt_s), strict=True):
        assert [(a.kind, a.vehicles, a.prn, a.accepted) for a in ip] == [(b.kind, b.vehicles, b.prn, b.accepted)
                                                                         for b in ir]
        for a, b in zip(ip, ir, strict=True):
            assert abs(a.innovation - b.innovation) <= 1e-9 * np.sqrt(b.variance)
    assert prod.counters == ref.counters
    assert prod.counters["nonfinite_sd_doppler"] >= 2  # v2's own, and every vehicle's SD with the lead's
    assert prod.counters["nonfinite_uwb"] == 1 and prod.counters["uwb_unknown_vehicle"] == 1
    assert prod.counters.get("uwb_deferred_nonlinear", 0) >= 1


def test_a_bearing_batch_with_rejections_keeps_its_accepted_runs_as_columns():
    """Bearings from every vehicle, with blunders (0.5 rad, ~150 sigma) in two epochs: in each
    a batch that is accepted but for a few. Records field by field and every counter must
    equal the reference engine's (its Python path makes one record per bearing); the
    production engine keeps the accepted runs around each rejection as column batches, so
    each such epoch's bearing records come as batch, rejected record(s), batch."""
    cfg = FilterConfig()
    ids = vehicle_ids(4)
    scn = SimScenario(n_vehicles=4, duration_s=3.0, turn_rate_rps=0.05, bearing_vehicles=tuple(ids))
    lay = StateLayout.build(lead="lead", vehicles=ids[1:], azimuth_vehicles=())
    eps = simulate(scn, cfg, np.random.default_rng(5))
    hit = [k for k, ep in enumerate(eps) if ep.bearings is not None and ep.bearings.n >= 8][10:12]
    assert len(hit) == 2
    for k, j in zip(hit, (3, 5), strict=True):
        eps[k].bearings.bearing_rad[j] += 0.5
    prod, ref = ClusterEkf(lay, cfg), ReferenceClusterEkf(lay, cfg)
    shapes = {}
    for k, ((_, ip), (_, ir)) in enumerate(zip(run_filter(prod, eps, scn.dt_s), run_filter(ref, eps, scn.dt_s),
                                               strict=True)):
        assert [(a.kind, a.vehicles, a.prn, a.accepted) for a in ip] == [(b.kind, b.vehicles, b.prn, b.accepted)
                                                                         for b in ir]
        for a, b in zip(ip, ir, strict=True):
            assert abs(a.innovation - b.innovation) <= 1e-9 * np.sqrt(b.variance)
            assert a.nis == a.innovation * a.innovation / a.variance
        if k in hit:
            shapes[k] = [("batch" if isinstance(p, UpdateBatch) else [r.accepted for r in p])
                         for p in ip.parts if next(iter(p)).kind == "bearing"]
    assert prod.counters == ref.counters
    assert prod.counters["rejected_bearing"] >= 2
    for k in hit:  # the blunder rejected, the bearings before and after it one batch each
        assert shapes[k][0] == "batch" and shapes[k][-1] == "batch"
        assert [False] in shapes[k] and shapes[k].count("batch") >= 2


def test_pair_sds_are_the_satellites_the_lead_misses_seen_by_two_or_more():
    """SDs between two non-lead vehicles (``use_pair_sd``) written out from the epochs: for
    every satellite with no finite pseudorange at the lead but a finite one at >= 2 ready
    vehicles, one SD per further vehicle against the first (layout order) that sees it, the
    satellites by the first one's elevation, highest first."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=4, duration_s=2.0, turn_rate_rps=0.05, lead_blocked_prns=(3, 7))
    ids = vehicle_ids(4)
    lay = StateLayout.build(lead="lead", vehicles=ids[1:])
    eps = simulate(scn, cfg, np.random.default_rng(5))
    eps[8].gnss["v1"].pseudorange_m[np.flatnonzero(eps[8].gnss["v1"].prn == 3)] = np.nan  # v2 is the reference then
    ekf = ClusterEkf(lay, cfg)
    n_pairs = 0
    for k, (ep, infos) in enumerate(run_filter(ekf, eps, scn.dt_s)):
        if k < 2 or ep.gnss is None:
            continue
        assert all(ekf.is_initialized(v) for v in ids[1:])
        lead = ep.gnss["lead"]
        lead_ok = set(lead.prn[np.isfinite(lead.pseudorange_m)].tolist())
        expected = []
        for prn in sorted({p for v in ids[1:] for p in ep.gnss[v].prn.tolist()} - lead_ok):
            have = [v for v in ids[1:] if np.isfinite(ep.gnss[v].pseudorange_m[ep.gnss[v].prn == prn]).any()]
            if len(have) >= 2:
                ref = ep.gnss[have[0]]
                lat, lon, _ = ecef_to_geodetic(ep.lead_base_ecef_m)  # elevation at the lead base
                up = ecef_to_enu_rotation(float(lat), float(lon))[2]
                d = ref.sv_pos_ecef_m[ref.prn == prn][0] - ep.lead_base_ecef_m
                expected.append((-float(np.arcsin(up @ d / np.linalg.norm(d))), [(a, have[0], prn) for a in have[1:]]))
        want = [t for _, ts in sorted(expected, key=lambda e: e[0]) for t in ts]
        got = [(*i.vehicles, i.prn) for i in infos if i.kind == "sd_pseudorange_pair"]
        assert got == want
        n_pairs += len(got)
    assert n_pairs >= 20


def _info(kind: str, veh: tuple[str, ...], nis: float, ok: bool, prn: int = -1) -> UpdateInfo:
    return UpdateInfo(kind, veh, np.sqrt(nis), 1.0, nis, ok, prn)


def test_update_log_statistics_and_columns_match_the_records():
    """Three flushes with different sets of kinds (one kind only in the last chunk)."""
    rng = np.random.default_rng(7)
    chunks = []
    for kinds in (("sd_pseudorange", "uwb"), ("bearing", "sd_pseudorange"), ("uwb", "sd_doppler", "bearing")):
        events = []
        for t in range(5):
            infos = [_info(kinds[k % len(kinds)], ("v1",) if k % 2 else ("v1", "v2"), float(rng.chisquare(1)),
                           bool(rng.random() > 0.2), prn=k) for k in range(7)]
            faulty = [bool(rng.random() > 0.7) for _ in infos]
            events.append((0.1 * t, infos, faulty))
        chunks.append(events)
    log = UpdateLog()
    for events in chunks:
        for t, infos, faulty in events:
            log.add(t, infos, faulty)
        log.flush()
    all_infos = [(i, f) for events in chunks for _, infos, faulty in events for i, f in zip(infos, faulty, strict=True)]
    stats = log.kind_statistics()
    assert list(stats) == sorted({i.kind for i, _ in all_infos})
    for kind, got in stats.items():
        sel = [(i, f) for i, f in all_infos if i.kind == kind]
        want = update_kind_statistics(np.array([i.accepted for i, _ in sel]), np.array([f for _, f in sel]),
                                      np.array([i.nis for i, _ in sel]))
        assert got == want
    cols = log.columns()
    assert cols["kind"] == [i.kind for i, _ in all_infos]
    assert cols["vehicles"] == [",".join(i.vehicles) for i, _ in all_infos]
    assert cols["prn"] == [i.prn for i, _ in all_infos]
    assert cols["nis"] == [i.nis for i, _ in all_infos]
    assert cols["faulty"] == [f for _, f in all_infos]
    assert log.n == len(all_infos)
    # closing deletes the spill file (its descriptor closed, not left to the garbage collector)
    spill = log._file
    log.close()
    assert spill.closed and log.n == 0 and log.columns()["kind"] == []


def _mixed_updates() -> tuple[Updates, list[UpdateInfo]]:
    """An :class:`Updates` of two column batches around plain records (one rejected), and the
    records it stands for, built one by one as ``UpdateInfo``'s definition says."""
    rng = np.random.default_rng(11)
    nu1, s1 = rng.normal(size=5), rng.uniform(1.0, 4.0, 5)
    nu2, s2 = rng.normal(size=3), rng.uniform(1.0, 4.0, 3)
    veh1 = [("v1",), ("v1",), ("v2",), ("v2",), ("v2",)]
    prn1 = [3, 7, 3, 9, 12]
    plain = [UpdateInfo("sd_pseudorange", ("v2",), 8.0, 1.0, 64.0, False, 21), UpdateInfo("uwb", ("v1", "v2"), 0.5, 2.0, 0.125, True)]
    up = Updates()
    up += UpdateBatch("sd_pseudorange", veh1, nu1, s1, prn1)
    up += plain
    up += UpdateBatch("uwb", [("lead", "v1"), ("v1", "v2"), ("lead", "v2")], nu2, s2)
    want = [UpdateInfo("sd_pseudorange", v, a, b, a * a / b, True, p) for v, a, b, p in
            zip(veh1, nu1.tolist(), s1.tolist(), prn1, strict=True)]
    want += plain
    want += [UpdateInfo("uwb", v, a, b, a * a / b, True, -1) for v, a, b in
             zip([("lead", "v1"), ("v1", "v2"), ("lead", "v2")], nu2.tolist(), s2.tolist(), strict=True)]
    return up, want


def test_update_batches_are_the_records_they_stand_for():
    """Column batches read as the ``UpdateInfo`` records built one by one (nis bit for bit
    ``innovation**2 / variance`` of Python floats); slices, counts and ``+`` as on the list."""
    up, want = _mixed_updates()
    assert len(up) == len(want) and list(up) == want and up == want and want == up
    assert all(type(r) is UpdateInfo for r in up)
    assert up[2] == want[2] and up[-1] == want[-1]
    b = up.parts[0]
    assert list(b[1:4]) == want[1:4] and isinstance(b[1:4], UpdateBatch)
    assert up + [want[0]] == [*want, want[0]]
    from collections import Counter
    assert up.counts() == Counter((r.vehicles, r.kind, r.accepted) for r in want)
    assert _update_counts(up) == _update_counts(list(want))


def test_update_log_of_batches_equals_the_log_of_their_records():
    """The log written from column batches has the columns and statistics of the same records given one by one."""
    up, want = _mixed_updates()
    faulty = [k % 3 == 0 for k in range(len(want))]
    a, b = UpdateLog(), UpdateLog()
    a.add(0.1, up, faulty)
    a.add(0.2, Updates(), [])
    b.add(0.1, list(want), faulty)
    assert a.columns() == b.columns()
    assert a.kind_statistics() == b.kind_statistics()


def test_faulty_flags_of_batches_follow_the_per_record_definition():
    """``_faulty_flags`` reads batches from their columns; each flag must still be
    :func:`v2v.pipeline._faulty` of its own record (NLOS / faulted satellites of a GNSS
    event; an NLOS UWB range; an NLOS bearing)."""
    up, want = _mixed_updates()
    events = [
        Event(0.1, "gnss", gnss={}, bad_prns={"v1": frozenset({7}), "v2": frozenset({9, 21})}),
        Event(0.1, "gnss", gnss={}, bad_prns={"v1": frozenset(), "v2": frozenset()}),
        Event(0.1, "uwb", uwb=SimpleNamespace(los=np.array([False]), errors_m={})),  # type: ignore[arg-type]
        Event(0.1, "uwb", uwb=SimpleNamespace(los=np.array([True]), errors_m={"fault": np.array([0.3])})),  # type: ignore[arg-type]
        Event(0.1, "uwb", uwb=SimpleNamespace(los=np.array([True]), errors_m={})),  # type: ignore[arg-type]
        Event(0.1, "bearing", bearings=SimpleNamespace(los=np.array([True, False]))),  # type: ignore[arg-type]
    ]
    n_true = 0
    for ev in events:
        for lead in (None, "v2"):
            got = _faulty_flags(up, ev, lead)
            assert got == [_faulty(r, ev, lead) for r in want]
            n_true += sum(got)
    assert n_true > 0


def test_an_sd_pseudorange_is_faulty_when_the_leads_signal_is():
    """``P_v - P_lead``: an NLOS or faulted signal at the lead corrupts the follower's SD of
    that satellite as much as its own does; a pair SD between two followers is corrupted by
    either of them, not by the lead."""
    ev = Event(0.1, "gnss", gnss={}, bad_prns={"lead": frozenset({7}), "v1": frozenset({9})})
    recs = [UpdateInfo("sd_pseudorange", ("v1",), 0.1, 1.0, 0.01, True, 7),
            UpdateInfo("sd_pseudorange", ("v1",), 0.1, 1.0, 0.01, True, 9),
            UpdateInfo("sd_pseudorange", ("v1",), 0.1, 1.0, 0.01, True, 12),
            UpdateInfo("sd_pseudorange_pair", ("v1", "v2"), 0.1, 1.0, 0.01, True, 7)]
    assert [_faulty(r, ev, "lead") for r in recs] == [True, True, False, False]
    batch = UpdateBatch("sd_pseudorange", [("v1",)] * 3, np.full(3, 0.1), np.ones(3), [7, 9, 12])
    assert _faulty_flags(Updates([batch]), ev, "lead") == [True, True, False]


def test_a_uwb_event_with_several_ranges_is_filtered_as_its_ranges():
    """The exchange delivers one range per UWB event (``Event.one_range``); an event built with
    its own several-range ``UwbRanges`` (one time tag) must be filtered as all of them in
    order, with no prediction between them, as ``update_uwb`` of the whole object does: the
    same state, covariance, update log and "heard" times as the one-range events."""
    from v2v.config.sections import SolutionSection

    cfg = FilterConfig()
    lay = StateLayout.build(lead="lead", vehicles=vehicle_ids(4)[1:])
    scn = SimScenario(n_vehicles=4, duration_s=2.0)
    eps = simulate(scn, cfg, np.random.default_rng(3))
    sol = SolutionSection(name="x", sensors=["gnss", "uwb"])
    runners = [SolutionRunner(sol, ClusterEkf(lay, cfg), "lead", lay.vehicles) for _ in range(2)]
    n_ranges, since_gnss = 0, 0.0
    for k, ep in enumerate(eps):
        for r in runners:
            if k > 0:
                r.ekf.predict(scn.dt_s - since_gnss)
            r.ekf.update_epoch(gnss=ep.gnss, lead_base_ecef_m=ep.lead_base_ecef_m)
        since_gnss = 0.0
        if k < 5 or ep.uwb is None or ep.uwb.n < 2:
            continue
        since_gnss = 0.05  # the ranges 50 ms after the GNSS epoch: one prediction before them
        t = ep.t_s + since_gnss
        whole = [Event(t, "uwb", uwb=ep.uwb)]
        one_each = [Event.one_range(t, ep.uwb, i) for i in range(ep.uwb.n)]
        for r, evs in zip(runners, (whole, one_each), strict=True):
            ei, t_f, _ = r._uwb_run(evs, 0, t, ep.t_s)
            assert ei == len(evs) and t_f == t
        n_ranges += ep.uwb.n
    (a, b) = runners
    assert n_ranges > 20
    assert np.array_equal(a.ekf.x, b.ekf.x) and np.array_equal(a.ekf.P, b.ekf.P)
    assert a.last_heard == b.last_heard and set(a.last_heard) == {"lead", *lay.vehicles}
    assert a.rec.log.columns() == b.rec.log.columns() and a.rec.log.n == b.rec.log.n > 20


def test_an_sd_doppler_is_faulty_when_either_signal_is_an_echo():
    """An echo-only signal's Doppler carries the reflected path's rate (up to 2 |v|), so an SD
    Doppler is flagged when the follower's or the lead's signal of that satellite is NLOS;
    an injected pseudorange fault (``bad_prns`` but line of sight) leaves the Doppler clean."""
    ev = Event(0.1, "gnss", gnss={}, bad_prns={"lead": frozenset({7}), "v1": frozenset({9, 11})},
               nlos_prns={"lead": frozenset({7}), "v1": frozenset({9})})
    recs = [UpdateInfo("sd_doppler", ("v1",), 0.1, 1.0, 0.01, True, p) for p in (7, 9, 11, 12)]
    assert [_faulty(r, ev, "lead") for r in recs] == [True, True, False, False]
    batch = UpdateBatch("sd_doppler", [("v1",)] * 4, np.full(4, 0.1), np.ones(4), [7, 9, 11, 12])
    assert _faulty_flags(Updates([batch]), ev, "lead") == [True, True, False, False]
    assert _faulty_flags(Updates([batch]), ev) == [False, True, False, False]  # without the lead: its echo unseen


def test_epoch_rows_taken_as_records_make_the_epochs_frame():
    """``SolutionRecord.take_rows`` hands the rows over as records: the chunk's frame
    (``pandas.DataFrame`` of them) has the columns in order of first appearance and NaN where
    a row lacks a key (a vehicle that left the cluster has no estimate columns), written out
    here by hand; the next call has nothing new."""
    import pandas as pd

    from v2v.pipeline import SolutionRecord

    rec = SolutionRecord(name="GPS")
    rows = [{"t_s": 0.1, "vehicle": "c1.1", "initialized": True, "along_err_m": 0.25, "used_pr": 7},
            {"t_s": 0.1, "vehicle": "c1.2", "initialized": False},  # left the cluster
            {"t_s": 0.2, "vehicle": "c1.1", "initialized": True, "along_err_m": -0.5, "used_pr": 6, "n_fixed": 3}]
    for r in rows:
        rec.add_row(r)
    got = pd.DataFrame(rec.take_rows())
    nan = float("nan")
    want = pd.DataFrame({"t_s": [0.1, 0.1, 0.2], "vehicle": ["c1.1", "c1.2", "c1.1"], "initialized": [True, False, True],
                         "along_err_m": [0.25, nan, -0.5], "used_pr": [7.0, nan, 6.0], "n_fixed": [nan, nan, 3.0]})
    pd.testing.assert_frame_equal(got, want, check_exact=True)
    assert rec.take_rows() == []


def test_update_log_columns_of_every_kind_of_piece_in_order():
    """Each way an update reaches the log, interleaved over two flushes: column batches with a
    PRN list, a PRN array and no PRN (-1), plain records (one rejected) between them, a UWB
    run's records with one time tag each (``add_records``), an empty event, and faulty flags
    all False for some events and mixed for others. Every column must list the updates in the
    order they went in, with their own time tag, as the records say one by one."""
    up, recs = _mixed_updates()  # batch (PRN list), two plain records, batch (no PRN)
    nu, s = np.array([0.5, -1.5, 2.0]), np.array([1.0, 2.0, 4.0])
    prn_arr = np.array([5, 6, 5], dtype=np.int64)
    arr_batch = UpdateBatch("sd_doppler", [("v1",), ("v1",), ("v2",)], nu, s, prn_arr)
    arr_recs = [UpdateInfo("sd_doppler", v, a, b, a * a / b, True, p)
                for v, a, b, p in zip([("v1",), ("v1",), ("v2",)], nu.tolist(), s.tolist(), prn_arr.tolist(), strict=True)]
    uwb = UpdateBatch("uwb", [("v1", "v2"), ("lead", "v1")], np.array([0.1, 0.2]), np.array([0.5, 0.5]))
    uwb_recs = [UpdateInfo("uwb", ("v1", "v2"), 0.1, 0.5, 0.1 * 0.1 / 0.5, True, -1),
                UpdateInfo("uwb", ("lead", "v1"), 0.2, 0.5, 0.2 * 0.2 / 0.5, True, -1)]
    rejected = [UpdateInfo("bearing", ("v2", "v1"), 3.0, 0.25, 36.0, False, -1)]
    mixed = Updates()
    mixed += arr_batch
    mixed += rejected
    log = UpdateLog()
    expect: list[tuple[float, UpdateInfo, bool]] = []
    # chunk 1
    f1 = [False] * len(recs)
    log.add(0.1, up, f1)
    expect += [(0.1, r, f) for r, f in zip(recs, f1, strict=True)]
    log.add_records(np.array([0.15, 0.45]), uwb, [True, False])
    expect += [(0.15, uwb_recs[0], True), (0.45, uwb_recs[1], False)]
    log.add(0.2, Updates(), [])
    log.flush()
    # chunk 2
    f2 = [False, True, False, False]
    log.add(0.3, mixed, f2)
    expect += [(0.3, r, f) for r, f in zip(arr_recs + rejected, f2, strict=True)]
    log.add(0.4, list(recs[5:]), [False] * 5)
    expect += [(0.4, r, False) for r in recs[5:]]
    log.flush()
    cols = log.columns()
    assert cols["t_s"] == [t for t, _, _ in expect]
    assert cols["kind"] == [r.kind for _, r, _ in expect]
    assert cols["vehicles"] == [",".join(r.vehicles) for _, r, _ in expect]
    assert cols["prn"] == [r.prn for _, r, _ in expect]
    assert cols["nis"] == [r.nis for _, r, _ in expect]
    assert cols["accepted"] == [r.accepted for _, r, _ in expect]
    assert cols["faulty"] == [f for _, _, f in expect]
    assert log.n == len(expect)
    bad = UpdateLog()
    bad.add(0.1, recs[:2], [False])  # one flag for two updates
    with pytest.raises(ValueError, match="faulty flags"):
        bad.flush()


def test_epoch_blocks_make_the_frame_the_dict_rows_make():
    """``SolutionRecord.take_frame`` builds a chunk of ``EpochBlock`` epochs column by column:
    the frame (values, column order, dtypes) equals pandas' records constructor on the same
    rows written out by hand (azimuth errors with a NaN, the lead's azimuth error on every
    row, counts as integers); a chunk that also holds a dict-rows epoch (a vehicle that left
    the cluster) is built from the rows, NaN where they lack a key."""
    import pandas as pd

    from v2v.metrics.errors import EPOCH_COLUMNS
    from v2v.pipeline import _ROW_COUNT_KEYS, EpochBlock, SolutionRecord

    m, nan = len(EPOCH_COLUMNS), float("nan")

    def block(t, az):
        return EpochBlock(t_s=t, solution="GPS+Bearing", vehicles=["c1.1", "c1.2"], initialized=[True, False],
                          nums=np.arange(2.0 * m).reshape(2, m) + t, true_lane=[0, 1], lead_lane=1, lane_width=[3.2, 3.5],
                          count_keys=_ROW_COUNT_KEYS, counts=np.arange(16, dtype=np.int64).reshape(2, 8),
                          integrity=[True, False], azimuth_err=az, lead_azimuth_err=-0.25)

    def row(t, k, az):
        r = {"t_s": t, "solution": "GPS+Bearing", "vehicle": f"c1.{k + 1}", "initialized": k == 0}
        r.update({c: float(j + m * k) + t for j, c in enumerate(EPOCH_COLUMNS)})
        r.update({"true_lane_index": k, "lead_lane_index": 1, "lane_width_m": [3.2, 3.5][k]})
        r.update({c: 8 * k + j for j, c in enumerate(_ROW_COUNT_KEYS)})
        r.update({"integrity_available": k == 0, "azimuth_err_rad": az[k], "lead_azimuth_err_rad": -0.25})
        return r

    rec = SolutionRecord(name="GPS+Bearing")
    rec.add_epoch(block(0.1, [0.01, nan]))
    rec.add_epoch([])  # an epoch without rows adds nothing
    rec.add_epoch(block(0.2, [0.02, -0.03]))
    want = [row(0.1, 0, [0.01, nan]), row(0.1, 1, [0.01, nan]), row(0.2, 0, [0.02, -0.03]), row(0.2, 1, [0.02, -0.03])]
    got = rec.take_frame()
    pd.testing.assert_frame_equal(got, pd.DataFrame(want), check_exact=True)
    assert got["used_pr"].dtype == np.int64 and got["initialized"].dtype == bool
    assert rec.take_frame() is None
    rec.add_epoch(block(0.3, [0.04, 0.05]))
    left = {"t_s": 0.4, "solution": "GPS+Bearing", "vehicle": "c1.2", "initialized": False}
    rec.add_epoch([left])
    mixed = rec.take_frame()
    pd.testing.assert_frame_equal(mixed, pd.DataFrame([row(0.3, 0, [0.04, 0.05]), row(0.3, 1, [0.04, 0.05]), left]),
                                  check_exact=True)
    assert np.isnan(mixed["used_pr"].iloc[2]) and mixed["used_pr"].dtype == np.float64


def test_recent_chunks_of_the_update_log_give_each_rows_mean_nis():
    """The replay's per-epoch NIS from the log's recent chunks (two flushes, so two code
    tables), by hand. Output epochs 0.1, 0.2, 0.3 s:

    * 0.1: a pseudorange batch v1 NIS 1, v2 NIS 2; a UWB range v1-v2 NIS 0.5; a rejected
      pseudorange of v1 NIS 64 (left out) -> v1 (1 + 0.5) / 2 = 0.75, v2 (2 + 0.5) / 2 = 1.25
    * 0.2: a bearing lead -> v1 NIS 3 -> v1 3, v2 NaN (no update)
    * 0.3 (second chunk): a UWB bound pull v1-v2 (a constraint, left out) and a Doppler of v2
      NIS 0.25 -> v1 NaN, v2 0.25
    """
    from v2v.pipeline import epoch_nis_of_rows

    log = UpdateLog()
    log.keep_recent = True
    log.add(0.1, Updates([UpdateBatch("sd_pseudorange", [("v1",), ("v2",)], np.array([1.0, 2.0]), np.array([1.0, 2.0]),
                                      [3, 5]),
                          [UpdateInfo("uwb", ("v1", "v2"), 1.0, 2.0, 0.5, True),
                           UpdateInfo("sd_pseudorange", ("v1",), 8.0, 1.0, 64.0, False, 7)]]), [False] * 4)
    log.add(0.2, [UpdateInfo("bearing", ("lead", "v1"), 3.0, 3.0, 3.0, True)], [False])
    log.flush()
    log.add(0.3, [UpdateInfo("uwb_constraint", ("v1", "v2"), 7.0, 7.0, 7.0, True),
                  UpdateInfo("sd_doppler", ("v2",), 0.5, 1.0, 0.25, True, 5)], [False, False])
    log.flush()
    recent = log.take_recent()
    assert len(recent) == 2 and log.take_recent() == []
    times = [0.1, 0.2, 0.3]
    t_rows, v_rows = np.repeat(times, 2), ["v1", "v2"] * 3
    got = epoch_nis_of_rows(recent, times, t_rows, v_rows)
    np.testing.assert_allclose(got, [0.75, 1.25, 3.0, np.nan, np.nan, 0.25], rtol=1e-15, atol=0)
    # rows of some epochs only, in any order: each its own epoch's value
    np.testing.assert_allclose(epoch_nis_of_rows(recent, times, [0.3, 0.1], ["v2", "v1"]), [0.25, 0.75], rtol=1e-15)
    with pytest.raises(ValueError, match="not one of the output epochs"):
        epoch_nis_of_rows(recent, times, [0.15], ["v1"])
    # the spilled log is the same with or without the recent chunks kept
    plain = UpdateLog()
    plain.add(0.2, [UpdateInfo("bearing", ("lead", "v1"), 3.0, 3.0, 3.0, True)], [False])
    plain.flush()
    assert plain.take_recent() == [] and plain.columns()["nis"] == [3.0]
