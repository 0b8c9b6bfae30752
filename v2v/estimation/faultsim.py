"""Fault trials in the filter's own world (:mod:`v2v.estimation.simulate`), shared by the fault
tests and ``experiments/fault_campaign.py``.

There the measurement noise is exactly the filter's, so the textbook figures hold: a blunder
of ``b`` innovation sigmas (``b sqrt(S)``) is detected by the test ``|nu| > k sqrt(S)`` with
probability ``P(|N(b, 1)| > k)`` (0.761 / 0.956 / 0.9966 for b = 4 / 5 / 6 at k = 3.29), and a
clean measurement is rejected with probability alpha. Each trial runs on a copy of the filter
(``copy.deepcopy``) so that the main filter stays on clean data; the blunder goes to the last
measurement of its kind in the update order, whose S is then the same as in the clean update.

``check(ekf)``, when given, is called after every update of the main filter (the tests assert
that P stays symmetric positive definite there).
"""

from __future__ import annotations

import copy
from collections.abc import Callable, Iterator, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from v2v.estimation.filter import KIND_SD_PR, KIND_UWB, ClusterEkf, FilterConfig, UpdateInfo
from v2v.estimation.layout import StateLayout
from v2v.estimation.simulate import SimEpoch, SimScenario, simulate, vehicle_ids
from v2v.sensors.measurements import GnssEpoch

CLOCK_JUMP_M = 299_792.458  # 1 ms of receiver clock
BLUNDER_SIZES = (4.0, 5.0, 6.0)  # innovation sigmas
CONVERGE_EPOCHS = 30  # 3 s at 10 Hz before the first trial

Check = Callable[[ClusterEkf], Any] | None
#: called before an epoch's update with (epoch, filter, its GNSS epochs by vehicle); returns
#: the GNSS epochs to update with (a test's tampering: satellites left out, a state moved)
Before = Callable[[SimEpoch, ClusterEkf, dict[str, GnssEpoch] | None], dict[str, GnssEpoch] | None] | None


def sim_layout(n: int) -> StateLayout:
    """Lead ``"lead"`` and followers ``v1..v{n-1}`` (the simulate.py names)."""
    return StateLayout.build(lead="lead", vehicles=vehicle_ids(n)[1:])


def with_pr_offset(gnss: dict[str, GnssEpoch], v: str, add_m: Any) -> dict[str, GnssEpoch]:
    """The epochs with ``add_m`` (scalar or per satellite) added to vehicle ``v``'s pseudoranges."""
    out = dict(gnss)
    out[v] = replace(gnss[v], pseudorange_m=gnss[v].pseudorange_m + add_m)
    return out


def blunder_trials(n_per_size: int, seed: int, *, sizes: tuple[float, ...] = BLUNDER_SIZES,
                   check: Check = None) -> tuple[dict[float, list[bool]], int, int]:
    """Pseudorange blunders of ``b sqrt(S)`` on the lowest-elevation satellite of v1 (last in the
    update order), sizes in turn, one per epoch after convergence; truth from the filter's own
    process model (with the rigid "kinematic" formation the filter's 10 m/s velocity model is
    conservative and the rates are off by ~1 %).

    Returns ({b: detected per trial}, clean tests, clean rejections).
    """
    cfg = FilterConfig()
    n_ep = CONVERGE_EPOCHS + n_per_size * len(sizes)
    scn = SimScenario(n_vehicles=3, duration_s=(n_ep - 1) * 0.1, uwb=False, bearing_vehicles=(), truth="process")
    eps = simulate(scn, cfg, np.random.default_rng(seed))
    ekf = ClusterEkf(sim_layout(3), cfg)
    det: dict[float, list[bool]] = {b: [] for b in sizes}
    n_clean = n_rej = 0
    for k, ep in enumerate(eps):
        if k:
            ekf.predict(scn.dt_s)
        trial = copy.deepcopy(ekf) if k >= CONVERGE_EPOCHS else None
        assert ep.gnss is not None  # GNSS at every epoch here (gnss_every = 1, no outage)
        infos = ekf.update_gnss(ep.gnss, ep.lead_base_ecef_m)
        if check is not None:
            check(ekf)
        if trial is None:
            continue
        prs = [i for i in infos if i.kind == KIND_SD_PR]
        n_clean += len(prs)
        n_rej += sum(not i.accepted for i in prs)
        g = ep.gnss["v1"]
        prn = int(g.prn[np.argmin(g.elevation_rad)])
        s = next(i.variance for i in prs if i.vehicles == ("v1",) and i.prn == prn)
        b = sizes[(k - CONVERGE_EPOCHS) % len(sizes)]
        out = trial.update_gnss(with_pr_offset(ep.gnss, "v1", np.where(g.prn == prn, b * np.sqrt(s), 0.0)),
                                ep.lead_base_ecef_m)
        det[b].append(not next(i.accepted for i in out if i.vehicles == ("v1",) and i.prn == prn))
    return det, n_clean, n_rej


def uwb_blunder_trials(n_trials: int, b: float, seed: int, *, check: Check = None) -> tuple[list[bool], int, int]:
    """As :func:`blunder_trials` for UWB ranges (filter sigma 0.5 m = world): the last range of
    each epoch of a copy of the filter gets ``b sqrt(S)``. Returns (detected per trial, clean
    UWB tests, clean rejections)."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=3, duration_s=(CONVERGE_EPOCHS + n_trials - 1) * 0.1, bearing_vehicles=(),
                      truth="process")
    eps = simulate(scn, cfg, np.random.default_rng(seed))
    ekf = ClusterEkf(sim_layout(3), cfg)
    hits: list[bool] = []
    n_clean = n_rej = 0
    for k, ep in enumerate(eps):
        if k:
            ekf.predict(scn.dt_s)
        trial = copy.deepcopy(ekf) if k >= CONVERGE_EPOCHS else None
        infos = ekf.update_epoch(gnss=ep.gnss, lead_base_ecef_m=ep.lead_base_ecef_m, uwb=ep.uwb)
        if check is not None:
            check(ekf)
        if trial is None or ep.uwb is None:
            continue
        u = [i for i in infos if i.kind == KIND_UWB]
        n_clean += len(u)
        n_rej += sum(not i.accepted for i in u)
        j = ep.uwb.n - 1
        if not u or u[-1].vehicles != (ep.uwb.a[j], ep.uwb.b[j]):
            raise RuntimeError("the last UWB record is not the epoch's last range: its S would differ")
        r = ep.uwb.range_m.copy()
        r[j] += b * np.sqrt(u[-1].variance)
        out = trial.update_epoch(gnss=ep.gnss, lead_base_ecef_m=ep.lead_base_ecef_m, uwb=replace(ep.uwb, range_m=r))
        hits.append(not [i for i in out if i.kind == KIND_UWB][-1].accepted)
    return hits, n_clean, n_rej


def fault_run(scn: SimScenario, seed: int, *, cfg: FilterConfig | None = None, jump_at_s: float | None = None,
              corrupt_at_s: float | None = None, check: Check = None,
              before: Before = None) -> Iterator[tuple[SimEpoch, ClusterEkf, Sequence[UpdateInfo]]]:
    """Filter ``scn`` with a 1 ms clock jump of v1's receiver from ``jump_at_s`` on (every
    pseudorange + 299 792.458 m) and/or a +50 m east corruption of v1's state at
    ``corrupt_at_s``, and whatever ``before`` does to each epoch; yields (epoch, filter, update
    records) after every epoch."""
    cfg = cfg or FilterConfig()
    eps = simulate(scn, cfg, np.random.default_rng(seed))
    ekf = ClusterEkf(sim_layout(scn.n_vehicles), cfg)
    for k, ep in enumerate(eps):
        if k:
            ekf.predict(scn.dt_s)
        if corrupt_at_s is not None and abs(ep.t_s - corrupt_at_s) < 1e-6:
            ekf._get_x()[ekf.layout.position("v1").start] += 50.0  # the engine's live state
        gnss = ep.gnss
        if gnss is not None and jump_at_s is not None and ep.t_s >= jump_at_s - 1e-9:
            gnss = with_pr_offset(gnss, "v1", CLOCK_JUMP_M)
        if before is not None:
            gnss = before(ep, ekf, gnss)
        infos = ekf.update_epoch(gnss=gnss, lead_base_ecef_m=ep.lead_base_ecef_m, uwb=ep.uwb, bearings=ep.bearings)
        if check is not None:
            check(ekf)
        yield ep, ekf, infos


def uwb_bias_step_run(seed: int, *, bias_m: float = 1.0, t_step_s: float = 15.0
                      ) -> list[tuple[float, list[UpdateInfo], float]]:
    """A replaced UWB radio: every range involving v1 + ``bias_m`` from ``t_step_s`` (filter
    without UWB error states, 2 t_step_s long). Per epoch: (t, v1's UWB records, v1's position NEES)."""
    cfg = FilterConfig()
    scn = SimScenario(n_vehicles=3, duration_s=2.0 * t_step_s, bearing_vehicles=(), truth="process")
    eps = simulate(scn, cfg, np.random.default_rng(seed))
    ekf = ClusterEkf(sim_layout(3), cfg)
    rec = []
    for k, ep in enumerate(eps):
        if k:
            ekf.predict(scn.dt_s)
        u = ep.uwb
        if u is not None and ep.t_s >= t_step_s - 1e-9:
            u = replace(u, range_m=u.range_m + bias_m * np.array(["v1" in (a, b) for a, b in zip(u.a, u.b, strict=True)]))
        infos = ekf.update_epoch(gnss=ep.gnss, lead_base_ecef_m=ep.lead_base_ecef_m, uwb=u)
        sl = ekf.layout.position("v1")
        e = ekf.x[sl] - ep.rel_state["v1"][:3]
        rec.append((ep.t_s, [i for i in infos if i.kind == KIND_UWB and "v1" in i.vehicles],
                    float(e @ np.linalg.solve(ekf.P[sl, sl], e))))
    return rec
