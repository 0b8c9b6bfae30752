"""Forward collision warning (FCW) on V2V relative positioning, and braking-event injection.

The application
---------------
For a *following* vehicle ``f`` and the vehicle *ahead* of it in the same lane ``a``, with
relative (antenna) positions ``r`` and velocities ``v`` of both with respect to the cluster
lead (the lead's own are zero), the follower's view of the vehicle ahead is

* range ``d = |r_a - r_f|`` (horizontal), bumper-to-bumper gap ``g = d - L_a - (x_a - x_f)``
  (``L_a`` the length of the vehicle ahead; ``x_a``, ``x_f`` the antennas' forward lever arms
  from their front bumpers, negative behind them: ``d - (x_a - x_f)`` is the front-to-front
  distance of two vehicles in line; a car's antenna 2.0 m behind its bumper following a
  truck's 1.0 m behind: ``g = d - L_a - 1.0``; equal lever arms: ``g = d - L_a``);
* closing speed ``c = -dd/dt = -(v_a - v_f) . (r_a - r_f) / d``;
* time to collision ``TTC = g / c`` when ``c > 0`` (infinite otherwise, 0 once ``g <= 0``).

A warning is issued while ``TTC < T_warn`` and ``c > c_min`` (``c_min`` = 0.5 m/s ignores the
creeping closure of a queue at a standstill, whose TTC is dominated by noise). The default
``T_warn = 2.5 s`` sits just above the strictest alert-timing criterion of the NHTSA NCAP
*Forward Collision Warning System Confirmation Test* (2013): the alert must come at
TTC >= 2.1 s for a stopped lead vehicle, >= 2.0 s for a slower-moving one and >= 2.4 s for a
lead decelerating at 0.3 g. ISO 15623:2013 (*Forward vehicle collision warning systems —
performance requirements and test procedures*) states the same requirement kinematically, as
a warning distance from the driver's reaction time and the two vehicles' decelerations; TTC is
its constant-speed special case.

The relative quantities come from a solution's estimates (``est_*``) or from truth
(``true_*``) in ``epochs.parquet``; the relative state between two non-lead vehicles is the
difference of their lead-relative states. Relative velocity: the filter's own velocity states
(``est_ve_mps``, ``est_vn_mps`` written by the pipeline) when present; otherwise (or with
``velocity="difference"``) the *causal* least-squares slope of the range over the last
``fd_window_s`` seconds (a real-time system cannot look ahead; the slope of a window of
length ``W`` lags the true range rate by ``W/2`` and has noise std ``sigma_d sqrt(12 / (n^3 - n))
/ dt`` for ``n`` samples of range noise ``sigma_d``).

Scoring (estimates against truth, both through the same application):

* *intervals*: a truth warning interval is **detected** when the estimate warns anywhere in
  ``[t_on - tol, t_off + tol]``, else **missed**; an estimated warning interval that does not
  meet any truth interval widened by ``tol`` is a **false warning**; the **warning-time error**
  of a detected interval is ``first estimated warning in the window - t_on`` (negative =
  early; bounded below by ``-tol``);
* *braking events* (from truth, ``accel_mps2 < -2 m/s^2`` for at least 0.3 s): for the vehicle
  following the braking one, whether truth and estimate warn in ``[t_start, t_end +
  horizon]``, and the difference of their first warning times.

Braking injection
-----------------
:class:`BrakingInjector` turns a list of :class:`BrakingEvent` (start time, vehicle,
deceleration, duration) into per-step speed commands for libsumo (``vehicle.setSpeed``), see
its docstring for the traffic-layer hook.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
import pandas as pd
from numpy.typing import ArrayLike, NDArray

F64 = NDArray[np.float64]
B = NDArray[np.bool_]

NCAP_TTC_S = {"stopped_lead": 2.1, "slower_lead": 2.0, "decelerating_lead": 2.4}


@dataclass(frozen=True, kw_only=True)
class FcwConfig:
    """FCW settings (see the module docstring for the basis of the defaults)."""

    ttc_threshold_s: float = 2.5
    min_closing_speed_mps: float = 0.5
    velocity: Literal["auto", "filter", "difference"] = "auto"
    fd_window_s: float = 0.5
    match_tolerance_s: float = 1.0
    braking_threshold_mps2: float = -2.0
    braking_min_duration_s: float = 0.3
    braking_horizon_s: float = 3.0


# ----------------------------------------------------------------------------------- kinematics


def time_to_collision_s(gap_m: ArrayLike, closing_mps: ArrayLike) -> F64:
    """``gap / closing`` where closing > 0; +inf where not closing; 0 where the gap is <= 0."""
    g = np.asarray(gap_m, dtype=float)
    c = np.asarray(closing_mps, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        ttc = np.where(c > 0.0, g / np.where(c > 0.0, c, 1.0), np.inf)
    ttc = np.where(g <= 0.0, 0.0, ttc)
    return np.where(np.isfinite(g) & ~np.isnan(c), ttc, np.nan)


def fcw_warnings(gap_m: ArrayLike, closing_mps: ArrayLike, config: FcwConfig = FcwConfig()) -> B:
    """Warning flag per epoch: ``TTC < T_warn`` and closing faster than ``c_min`` (NaN -> no warning)."""
    ttc = time_to_collision_s(gap_m, closing_mps)
    c = np.asarray(closing_mps, dtype=float)
    with np.errstate(invalid="ignore"):
        return np.asarray((ttc < config.ttc_threshold_s) & (c > config.min_closing_speed_mps), dtype=bool)


def causal_slope(t_s: ArrayLike, y: ArrayLike, window_s: float) -> F64:
    """Least-squares slope of ``y`` over the samples in ``(t - window_s, t]`` (NaN with < 2 samples).

    Causal (no look-ahead): for a ramp it is exact; for a general signal it estimates the
    derivative at ``t - window_s / 2``.
    """
    t = np.asarray(t_s, dtype=float)
    v = np.asarray(y, dtype=float)
    out = np.full(t.size, np.nan)
    lo = 0
    for i in range(t.size):
        while t[lo] <= t[i] - window_s + 1e-9:
            lo += 1
        tt, yy = t[lo:i + 1], v[lo:i + 1]
        ok = np.isfinite(yy)
        if ok.sum() < 2:
            continue
        tt, yy = tt[ok], yy[ok]
        tc = tt - tt.mean()
        den = float(tc @ tc)
        if den > 0:
            out[i] = float(tc @ (yy - yy.mean())) / den
    return out


def _time_key(t_s: ArrayLike) -> NDArray[np.int64]:
    return np.round(np.asarray(t_s, dtype=float) * 1000.0).astype(np.int64)


def _vehicle_states(epochs: pd.DataFrame, solution: str, vehicle: str, lead: str, source: str) -> pd.DataFrame:
    """Lead-relative horizontal position / velocity of one vehicle per time key (zeros for the lead)."""
    sol = epochs[epochs["solution"] == solution]
    keys = np.unique(_time_key(sol["t_s"]))
    if vehicle == lead:
        z = np.zeros(keys.size)
        return pd.DataFrame({"e": z, "n": z, "ve": z, "vn": z, "ok": np.ones(keys.size, bool)}, index=keys)
    g = sol[sol["vehicle"] == vehicle]
    p = "est" if source == "est" else "true"
    has_v = f"{p}_ve_mps" in g and f"{p}_vn_mps" in g
    df = pd.DataFrame({
        "e": g[f"{p}_e_m"].to_numpy(float), "n": g[f"{p}_n_m"].to_numpy(float),
        "ve": g[f"{p}_ve_mps"].to_numpy(float) if has_v else np.nan,
        "vn": g[f"{p}_vn_mps"].to_numpy(float) if has_v else np.nan,
        "ok": g["initialized"].to_numpy(bool) if source == "est" else np.ones(len(g), bool),
    }, index=_time_key(g["t_s"]))
    return df[~df.index.duplicated()]


def pair_kinematics(epochs: pd.DataFrame, solution: str, follower: str, ahead: str, lead: str, *,
                    source: Literal["est", "true"], length_ahead_m: float, arm_x_ahead_m: float = 0.0,
                    arm_x_follower_m: float = 0.0, config: FcwConfig = FcwConfig()) -> pd.DataFrame:
    """Range, gap, closing speed, TTC and warning of ``follower`` w.r.t. ``ahead`` over time.

    ``source="est"`` uses the solution's estimates, ``"true"`` the truth columns of the same
    rows. ``arm_x_*_m``: the two antennas' forward lever arms from their front bumpers
    (negative behind; :func:`antenna_arms_x_m` reads them from truth); only their difference
    enters the gap (module docstring). Returns columns ``t_s``, ``available``, ``range_m``,
    ``gap_m``, ``closing_mps``, ``ttc_s``, ``warn`` (``available`` = both vehicles' estimates
    initialized).
    """
    fa = _vehicle_states(epochs, solution, follower, lead, source)
    aa = _vehicle_states(epochs, solution, ahead, lead, source)
    keys = fa.index.intersection(aa.index).sort_values()
    fa, aa = fa.loc[keys], aa.loc[keys]
    t = keys.to_numpy() / 1000.0
    de = aa["e"].to_numpy() - fa["e"].to_numpy()
    dn = aa["n"].to_numpy() - fa["n"].to_numpy()
    rng = np.hypot(de, dn)
    ok = fa["ok"].to_numpy(bool) & aa["ok"].to_numpy(bool)
    use_filter = config.velocity == "filter" or (
        config.velocity == "auto" and bool(np.isfinite(fa["ve"]).any() or follower == lead)
        and bool(np.isfinite(aa["ve"]).any() or ahead == lead))
    if use_filter:
        dve = aa["ve"].to_numpy() - fa["ve"].to_numpy()
        dvn = aa["vn"].to_numpy() - fa["vn"].to_numpy()
        with np.errstate(invalid="ignore", divide="ignore"):
            closing = -(dve * de + dvn * dn) / rng
    else:
        r = np.where(ok, rng, np.nan)
        closing = -causal_slope(t, r, config.fd_window_s)
    gap = rng - length_ahead_m - (arm_x_ahead_m - arm_x_follower_m)
    gap = np.where(ok, gap, np.nan)
    closing = np.where(ok, closing, np.nan)
    return pd.DataFrame({
        "t_s": t, "available": ok, "range_m": np.where(ok, rng, np.nan), "gap_m": gap, "closing_mps": closing,
        "ttc_s": time_to_collision_s(gap, closing), "warn": fcw_warnings(gap, closing, config),
    })


# ----------------------------------------------------------------------------------- scoring


def warning_intervals(t_s: ArrayLike, warn: ArrayLike) -> list[tuple[float, float]]:
    """Maximal runs of consecutive warning samples as (first, last) sample times."""
    t = np.asarray(t_s, dtype=float)
    w = np.asarray(warn, dtype=bool)
    if not w.any():
        return []
    d = np.diff(np.r_[0, w.astype(int), 0])
    on = np.flatnonzero(d == 1)
    off = np.flatnonzero(d == -1) - 1
    return [(float(t[a]), float(t[b])) for a, b in zip(on, off, strict=True)]


@dataclass(frozen=True, kw_only=True)
class WarningComparison:
    truth_warnings: int
    estimated_warnings: int
    detected: int
    missed: int
    false: int
    time_errors_s: tuple[float, ...] = field(default_factory=tuple)


def compare_warnings(t_s: ArrayLike, warn_true: ArrayLike, warn_est: ArrayLike, tolerance_s: float) -> WarningComparison:
    """Detected / missed truth warnings, false estimated warnings, warning-time errors (module docstring)."""
    t = np.asarray(t_s, dtype=float)
    we = np.asarray(warn_est, dtype=bool)
    ti = warning_intervals(t, warn_true)
    ei = warning_intervals(t, we)
    errors: list[float] = []
    detected = 0
    for on, off in ti:
        win = (t >= on - tolerance_s - 1e-9) & (t <= off + tolerance_s + 1e-9) & we
        if win.any():
            detected += 1
            errors.append(float(t[np.argmax(win)] - on))
    false = sum(1 for a, b in ei if not any(a <= off + tolerance_s + 1e-9 and b >= on - tolerance_s - 1e-9 for on, off in ti))
    return WarningComparison(truth_warnings=len(ti), estimated_warnings=len(ei), detected=detected,
                             missed=len(ti) - detected, false=false, time_errors_s=tuple(errors))


def detect_braking_events(truth: pd.DataFrame, config: FcwConfig = FcwConfig()) -> pd.DataFrame:
    """Braking events per vehicle from truth: ``accel_mps2 < threshold`` for >= the minimum duration.

    Returns columns ``vehicle``, ``t_start_s``, ``t_end_s``, ``min_accel_mps2``, ``speed_start_mps``.
    """
    rows = []
    for veh, g in truth.sort_values("t_s").groupby("vehicle", sort=True):
        t = g["t_s"].to_numpy(float)
        a = g["accel_mps2"].to_numpy(float)
        spd = g["speed_mps"].to_numpy(float)
        for on, off in warning_intervals(t, a < config.braking_threshold_mps2):
            # (n samples at a step dt cover n dt of braking, one dt more than their first-to-last span)
            k_on = int(np.searchsorted(t, on))
            dt = float(t[k_on + 1] - t[k_on]) if k_on + 1 < len(t) else (float(t[k_on] - t[k_on - 1]) if k_on else 0.0)
            if off - on + dt + 1e-9 < config.braking_min_duration_s:
                continue
            k = (t >= on) & (t <= off)
            rows.append({"vehicle": veh, "t_start_s": on, "t_end_s": off, "min_accel_mps2": float(a[k].min()),
                         "speed_start_mps": float(spd[k][0])})
    return pd.DataFrame(rows, columns=["vehicle", "t_start_s", "t_end_s", "min_accel_mps2", "speed_start_mps"])


def antenna_arms_x_m(truth: pd.DataFrame) -> dict[str, float]:
    """Each vehicle's antenna lever arm along its heading from its front bumper (m, negative
    behind), from ``truth.parquet``: the median over its rows of ``(x - front_x) sin(az) +
    (y - front_y) cos(az)``. Exact for an antenna on the centre line; a lateral arm ``y``
    adds ``y`` times the grid convergence (< 1e-3 m on the shipped nets)."""
    along = (truth["x_m"] - truth["front_x_m"]) * np.sin(truth["azimuth_rad"]) + (
        truth["y_m"] - truth["front_y_m"]) * np.cos(truth["azimuth_rad"])
    return {str(k): float(v) for k, v in along.groupby(truth["vehicle"]).median().items()}


def following_pairs(truth: pd.DataFrame, cluster: str | None = None) -> list[tuple[str, str]]:
    """(follower, ahead) pairs: for each vehicle, the cluster vehicle most often directly ahead of
    it in the same lane (same edge and lane index, ahead along the follower's heading).

    Vehicles never behind another one in their lane are not followers.
    """
    tr = truth if cluster is None else truth[truth["cluster"] == cluster]
    votes: dict[tuple[str, str], int] = {}
    for _, g in tr.groupby(_time_key(tr["t_s"])):
        veh = g["vehicle"].to_numpy()
        x, y = g["x_m"].to_numpy(float), g["y_m"].to_numpy(float)
        az = g["azimuth_rad"].to_numpy(float)
        lane = g["lane"].astype(str).to_numpy()
        for i in range(len(g)):
            best, best_d = None, np.inf
            for j in range(len(g)):
                if i == j or lane[i] != lane[j]:
                    continue
                d = (x[j] - x[i]) * np.sin(az[i]) + (y[j] - y[i]) * np.cos(az[i])
                if 0.0 < d < best_d:
                    best, best_d = veh[j], d
            if best is not None:
                votes[(veh[i], best)] = votes.get((veh[i], best), 0) + 1
    pairs: dict[str, tuple[str, int]] = {}
    for (f, a), n in votes.items():
        if f not in pairs or n > pairs[f][1]:
            pairs[f] = (a, n)
    return sorted(((f, a) for f, (a, _) in pairs.items()), key=lambda p: p[0])


def _first_time(t: F64, mask: B) -> float:
    return float(t[np.argmax(mask)]) if mask.any() else float("nan")


def fcw_study(epochs: pd.DataFrame, truth: pd.DataFrame, *, config: FcwConfig = FcwConfig(),
              pairs: Sequence[tuple[str, str]] | None = None) -> dict[str, pd.DataFrame]:
    """Run the FCW on truth and on every solution's estimates; score the estimates.

    Returns ``{"pairs": per (solution, follower) table, "solutions": per solution totals,
    "events": per (solution, braking event) rows, "braking": the braking events}``.
    ``pairs`` defaults to :func:`following_pairs` per cluster. Lengths of the vehicles ahead
    come from ``truth.length_m``, the antennas' lever arms from :func:`antenna_arms_x_m`.
    """
    lengths = truth.groupby("vehicle")["length_m"].first().to_dict()
    arms = antenna_arms_x_m(truth)
    leads = truth[truth["is_lead"].astype(bool)].groupby("cluster")["vehicle"].first().to_dict()
    cluster_of = truth.groupby("vehicle")["cluster"].first().to_dict()
    if pairs is None:
        pairs = [p for c in leads for p in following_pairs(truth, c)]
    braking = detect_braking_events(truth, config)
    pair_rows, event_rows = [], []
    for sol in epochs["solution"].drop_duplicates():
        for f, a in pairs:
            lead = leads[cluster_of[f]]
            geometry = {"length_ahead_m": lengths[a], "arm_x_ahead_m": arms[a], "arm_x_follower_m": arms[f]}
            kt = pair_kinematics(epochs, sol, f, a, lead, source="true", **geometry, config=config)
            ke = pair_kinematics(epochs, sol, f, a, lead, source="est", **geometry, config=config)
            t = kt["t_s"].to_numpy()
            wt, we = kt["warn"].to_numpy(bool), ke["warn"].to_numpy(bool)
            cmp = compare_warnings(t, wt, we, config.match_tolerance_s)
            err = np.asarray(cmp.time_errors_s)
            av = ke["available"].to_numpy(bool)
            gap_err = (ke["gap_m"] - kt["gap_m"]).to_numpy()
            cl_err = (ke["closing_mps"] - kt["closing_mps"]).to_numpy()
            pair_rows.append({
                "solution": sol, "follower": f, "ahead": a, "epochs": int(t.size), "available": float(av.mean()) if t.size else float("nan"),
                "gap_err_rms_m": _rms(gap_err), "closing_err_rms_mps": _rms(cl_err),
                "gap_err_n": int(np.isfinite(gap_err).sum()), "closing_err_n": int(np.isfinite(cl_err).sum()),
                "truth_warn_epochs": int(wt.sum()), "est_warn_epochs": int(we.sum()),
                "epoch_agreement": float(np.mean(wt == we)) if t.size else float("nan"),
                "truth_warnings": cmp.truth_warnings, "est_warnings": cmp.estimated_warnings,
                "detected": cmp.detected, "missed": cmp.missed, "false": cmp.false,
                "warn_time_err_mean_s": float(err.mean()) if err.size else float("nan"),
                "warn_time_err_abs_max_s": float(np.abs(err).max()) if err.size else float("nan"),
            })
            for ev in braking[braking["vehicle"] == a].itertuples():
                win = (t >= ev.t_start_s - 1e-9) & (t <= ev.t_end_s + config.braking_horizon_s + 1e-9)
                t_true, t_est = _first_time(t, win & wt), _first_time(t, win & we)
                kind = ("hit" if np.isfinite(t_est) else "missed") if np.isfinite(t_true) else (
                    "false" if np.isfinite(t_est) else "none")
                event_rows.append({
                    "solution": sol, "follower": f, "ahead": a, "t_start_s": ev.t_start_s, "t_end_s": ev.t_end_s,
                    "min_accel_mps2": ev.min_accel_mps2, "speed_start_mps": ev.speed_start_mps,
                    "first_warn_true_s": t_true, "first_warn_est_s": t_est, "outcome": kind,
                    "warn_time_err_s": t_est - t_true if kind == "hit" else float("nan"),
                    "min_ttc_true_s": float(np.nanmin(kt["ttc_s"].to_numpy()[win])) if win.any() else float("nan"),
                })
    pair_df = pd.DataFrame(pair_rows, columns=PAIR_COLUMNS)
    ev_df = pd.DataFrame(event_rows, columns=[
        "solution", "follower", "ahead", "t_start_s", "t_end_s", "min_accel_mps2", "speed_start_mps",
        "first_warn_true_s", "first_warn_est_s", "outcome", "warn_time_err_s", "min_ttc_true_s"])
    return {"pairs": pair_df, "solutions": _solution_totals(pair_df, ev_df), "events": ev_df, "braking": braking}


#: the columns of :func:`fcw_study`'s ``pairs`` table (also when it has no rows)
PAIR_COLUMNS = ("solution", "follower", "ahead", "epochs", "available", "gap_err_rms_m", "closing_err_rms_mps",
                "gap_err_n", "closing_err_n", "truth_warn_epochs", "est_warn_epochs", "epoch_agreement",
                "truth_warnings", "est_warnings", "detected", "missed", "false", "warn_time_err_mean_s",
                "warn_time_err_abs_max_s")
#: the columns of its ``solutions`` table
SOLUTION_COLUMNS = ("solution", "available", "gap_err_rms_m", "closing_err_rms_mps", "truth_warnings", "detected",
                    "missed", "false", "missed_rate", "epoch_agreement", "braking_events", "events_warned_true",
                    "events_hit", "events_missed", "events_false", "event_warn_time_err_mean_s",
                    "event_warn_time_err_abs_p95_s")


def _rms(x: F64) -> float:
    x = x[np.isfinite(x)]
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def _pooled_rms(rms: pd.Series, n: pd.Series) -> float:
    """The RMS over the pairs' samples together: each pair's mean square weighted by its count
    of finite samples (a pair without any adds nothing)."""
    r, k = rms.to_numpy(float), n.to_numpy(float)
    use = k > 0
    return float(np.sqrt(np.sum(r[use] ** 2 * k[use]) / np.sum(k[use]))) if use.any() else float("nan")


def _solution_totals(pair_df: pd.DataFrame, ev_df: pd.DataFrame) -> pd.DataFrame:
    """Per solution: availability and the agreement weighted by the pairs' epochs, the RMS
    errors pooled over the pairs' finite samples (:func:`_pooled_rms`; before 2026-12-06 each
    pair's RMS was weighted by all its epochs, and a pair with none available made the total
    NaN), warning and braking-event counts."""
    rows = []
    for sol, g in pair_df.groupby("solution", sort=False):
        e = ev_df[ev_df["solution"] == sol]
        errs = e["warn_time_err_s"].dropna().to_numpy()
        n_true = int(g["truth_warnings"].sum())
        rows.append({
            "solution": sol, "available": float(np.average(g["available"], weights=g["epochs"])) if g["epochs"].sum() else float("nan"),
            "gap_err_rms_m": _pooled_rms(g["gap_err_rms_m"], g["gap_err_n"]),
            "closing_err_rms_mps": _pooled_rms(g["closing_err_rms_mps"], g["closing_err_n"]),
            "truth_warnings": n_true, "detected": int(g["detected"].sum()), "missed": int(g["missed"].sum()),
            "false": int(g["false"].sum()),
            "missed_rate": float(g["missed"].sum() / n_true) if n_true else float("nan"),
            "epoch_agreement": float(np.average(g["epoch_agreement"], weights=g["epochs"])) if g["epochs"].sum() else float("nan"),
            "braking_events": int(len(e)), "events_warned_true": int(e["outcome"].isin(["hit", "missed"]).sum()),
            "events_hit": int((e["outcome"] == "hit").sum()), "events_missed": int((e["outcome"] == "missed").sum()),
            "events_false": int((e["outcome"] == "false").sum()),
            "event_warn_time_err_mean_s": float(errs.mean()) if errs.size else float("nan"),
            "event_warn_time_err_abs_p95_s": float(np.percentile(np.abs(errs), 95.0)) if errs.size else float("nan"),
        })
    return pd.DataFrame(rows, columns=SOLUTION_COLUMNS)


# ----------------------------------------------------------------------------------- braking injection


@dataclass(frozen=True, kw_only=True)
class BrakingEvent:
    """Hard braking of ``vehicle`` from ``t_s`` for ``duration_s`` at ``decel_mps2`` (> 0)."""

    t_s: float
    vehicle: str
    decel_mps2: float
    duration_s: float

    def __post_init__(self) -> None:
        if not (self.decel_mps2 > 0.0 and self.duration_s > 0.0):
            raise ValueError(f"braking event needs decel_mps2 > 0 and duration_s > 0, got {self!r}")


class VehicleApi(Protocol):
    """The part of ``libsumo.vehicle`` (or ``traci.vehicle``) the injector uses."""

    def setSpeed(self, vehID: str, speed: float) -> None: ...  # noqa: N802, N803

    def setSpeedMode(self, vehID: str, speedMode: int) -> None: ...  # noqa: N802, N803


SPEED_MODE_DEFAULT = 31  # bits 0-4: safe speed, max accel, max decel, right of way, red-light braking
SPEED_MODE_BRAKING = 27  # bit 2 (regard maximum deceleration) cleared: may brake harder than vType decel


class BrakingInjector:
    """Per-step speed commands realizing a list of braking events in SUMO.

    At the first step ``t >= t_s`` of an event the vehicle's speed ``v0`` is recorded; while
    ``t_s <= t < t_s + duration_s`` the commanded speed is ``max(0, v0 - decel (t - t_s))``;
    at the first step after the event the command is ``-1`` (SUMO: give control back to the
    car-following model). Pure logic in :meth:`commands`, SUMO calls in :meth:`apply`.

    Traffic-layer hook (``v2v/traffic/sumo.py``, inside ``SumoSimulation.step`` before
    ``simulationStep``, ``t`` the time of the step about to be simulated and ``speeds`` the
    current ``vehicle.getSpeed`` of the cluster)::

        injector.apply(libsumo.vehicle, t, speeds)

    :meth:`apply` sets speed mode 27 at an event's start (maximum-deceleration bit cleared,
    so ``decel_mps2`` may exceed the vType's ``decel``; safe speed to the leader is still
    respected) and restores 31 at its end. The followers' car-following model reacts (up to
    their ``emergencyDecel``). A scenario section ``[[braking]] t_s, vehicle, decel_mps2,
    duration_s`` mapping onto :class:`BrakingEvent` would expose it to users.
    """

    def __init__(self, events: Iterable[BrakingEvent]) -> None:
        self.events = sorted(events, key=lambda e: (e.t_s, e.vehicle))
        self._v0: dict[int, float] = {}
        self._done: set[int] = set()

    def commands(self, t_s: float, speeds_mps: Mapping[str, float]) -> dict[str, float]:
        """Speed command per vehicle for the step at ``t_s`` (``-1`` = release); others absent."""
        out: dict[str, float] = {}
        for i, ev in enumerate(self.events):
            if i in self._done or t_s < ev.t_s - 1e-9 or ev.vehicle not in speeds_mps:
                continue
            if t_s < ev.t_s + ev.duration_s - 1e-9:
                v0 = self._v0.setdefault(i, float(speeds_mps[ev.vehicle]))
                out[ev.vehicle] = max(0.0, v0 - ev.decel_mps2 * (t_s - ev.t_s))
            else:
                self._done.add(i)
                if i in self._v0:
                    out.setdefault(ev.vehicle, -1.0)
        return out

    def apply(self, vehicle_api: VehicleApi, t_s: float, speeds_mps: Mapping[str, float]) -> dict[str, float]:
        """Send :meth:`commands` to SUMO; returns them."""
        cmds = self.commands(t_s, speeds_mps)
        for vid, v in cmds.items():
            vehicle_api.setSpeedMode(vid, SPEED_MODE_DEFAULT if v < 0 else SPEED_MODE_BRAKING)
            vehicle_api.setSpeed(vid, v)
        return cmds


def to_markdown(df: pd.DataFrame, digits: int = 3) -> str:
    """A DataFrame as a Markdown table (floats to ``digits`` significant digits)."""
    cols = list(df.columns)
    lines = ["| " + " | ".join(map(str, cols)) + " |", "|" + "---|" * len(cols)]
    for _, row in df.iterrows():
        cells: list[Any] = [f"{v:.{digits}g}" if isinstance(v, float) else str(v) for v in row]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)
