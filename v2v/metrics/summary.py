"""Per-solution, per-vehicle statistics for ``summary.json`` and the paper-style table."""

from __future__ import annotations

import re
from collections.abc import Collection
from typing import Any

import numpy as np
import pandas as pd

from v2v.estimation.filter import KIND_CONSTRAINT
from v2v.metrics.errors import chi2_band, consistency_summary, error_statistics

NIS_DOF = 1  # every update is scalar
_ERROR_COLUMNS = ("along_err_m", "across_err_m", "up_err_m", "sigma_along_m", "sigma_across_m", "sigma_up_m", "nees_pos")


def _skipna_mean(a: np.ndarray) -> float:
    """The mean of the non-NaN values (NaN if none): pandas' ``Series.mean()`` without
    bottleneck, NaN replaced by 0, summed (numpy's pairwise sum) and divided by their count."""
    nan = np.isnan(a)
    n = a.size - int(nan.sum())
    return float(np.where(nan, 0.0, a).sum() / n) if n else float("nan")


def solution_statistics(epochs: pd.DataFrame, updates: dict[str, pd.DataFrame],
                        measurements: dict[str, dict[str, Any]] | None = None,
                        azimuth_solutions: Collection[str] | None = None) -> dict[str, Any]:
    """Statistics per solution and vehicle over the epochs where the vehicle is initialized.

    ``availability`` is the fraction of output epochs with an initialized estimate.
    ``measurements``: per solution, the per-update statistics already reduced (e.g. by
    :func:`update_kind_statistics` kind by kind from a streamed run's compact log); used
    instead of ``updates`` for the solutions it names. ``azimuth_solutions``: the solutions
    that estimate azimuths (``azimuth = "estimated"``); only they get the azimuth error
    statistics (``azimuth_err_deg`` per vehicle, ``lead_azimuth_err_deg``), whose columns are
    NaN for the others. None: every solution with the columns gets them.
    """
    out: dict[str, Any] = {}
    for sol, g_sol in epochs.groupby("solution", sort=False):
        # each vehicle's rows (vehicles in sorted order, as groupby("vehicle", sort=True) gives
        # them), read from the solution's columns as arrays: the same values, in the same order,
        # as the per-vehicle frames, without building one
        codes, names = pd.factorize(g_sol["vehicle"], sort=True)
        col = {c: g_sol[c].to_numpy(dtype=float) for c in _ERROR_COLUMNS}
        initialized = g_sol["initialized"].to_numpy(dtype=bool)
        az_est = azimuth_solutions is None or str(sol) in azimuth_solutions
        azimuth = g_sol["azimuth_err_rad"].to_numpy(dtype=float) if az_est and "azimuth_err_rad" in g_sol else None
        phase = "phase_state" in g_sol
        per_vehicle: dict[str, Any] = {}
        for k, veh in enumerate(names):
            rows = np.flatnonzero(codes == k)
            ok = rows[initialized[rows]]
            entry: dict[str, Any] = {"epochs": int(len(rows)), "availability": float(len(ok) / max(len(rows), 1))}
            for comp in ("along", "across", "up"):
                err, sigma = col[f"{comp}_err_m"][ok], col[f"sigma_{comp}_m"][ok]
                entry[comp] = error_statistics(err)
                entry[f"{comp}_sigma_mean_m"] = _skipna_mean(sigma)
                # integrity: how often |error| exceeds the filter's own 3-sigma bound
                if len(ok):
                    entry[f"{comp}_exceeds_3sigma"] = float(np.mean(np.abs(err) > 3.0 * sigma))
            entry["nees_pos"] = consistency_summary(col["nees_pos"][ok], dof=3)
            if azimuth is not None:
                az = azimuth[ok]
                entry["azimuth_err_deg"] = error_statistics(np.degrees(az[~np.isnan(az)]))
            if phase and g_sol["phase_state"].iloc[rows].notna().any():  # a carrier-phase solution
                entry["ambiguity"] = ambiguity_statistics(g_sol.iloc[ok])
            per_vehicle[str(veh)] = entry
        sol_entry: dict[str, Any] = {"vehicles": per_vehicle}
        if az_est and "lead_azimuth_err_rad" in g_sol:
            # one value per cluster epoch (each of the epoch's vehicle rows repeats its lead's)
            keys = [c for c in ("cluster", "t_s") if c in g_sol]
            lead = g_sol.drop_duplicates(keys) if keys else g_sol
            az = lead["lead_azimuth_err_rad"].dropna().to_numpy()
            sol_entry["lead_azimuth_err_deg"] = error_statistics(np.degrees(az))
        if measurements is not None and str(sol) in measurements:
            if measurements[str(sol)]:
                sol_entry["measurements"] = measurements[str(sol)]
        else:
            u = updates.get(str(sol))
            if u is not None and len(u):
                sol_entry["measurements"] = _update_stats(u)
        out[str(sol)] = sol_entry
    return out


def ambiguity_statistics(ok: pd.DataFrame) -> dict[str, Any]:
    """Carrier-phase metrics of one vehicle over its initialized epochs with a GNSS epoch.

    ``fix_rate``: fraction of those epochs with every DD ambiguity fixed (validated by the
    bootstrapped success rate and the ratio test); ``partial_rate``: some but not all;
    ``time_to_first_fix_s``: from the first initialized epoch to the first fixed one (NaN:
    never); ``wrong_fix_rate``: among epochs with any fixed combination, the fraction where
    one differs from the true integers; ``fixed_along`` / ``fixed_across``: error statistics
    over the fixed epochs.
    """
    g = ok[ok["phase_state"] != ""]
    n = len(g)
    fixed = g["phase_state"] == "fixed"
    wf = g["wrong_fix"].dropna()
    t_first = float(ok["t_s"].min()) if len(ok) else float("nan")
    t_fix = float(g.loc[fixed, "t_s"].min()) if fixed.any() else float("nan")
    return {
        "epochs": int(n),
        "fix_rate": float(fixed.mean()) if n else float("nan"),
        "partial_rate": float((g["phase_state"] == "partial").mean()) if n else float("nan"),
        "time_to_first_fix_s": t_fix - t_first,
        "epochs_with_fix": int(len(wf)),
        "wrong_fix_epochs": int((wf > 0.5).sum()),
        "wrong_fix_rate": float((wf > 0.5).mean()) if len(wf) else float("nan"),
        "fixed_along": error_statistics(g.loc[fixed, "along_err_m"].to_numpy()),
        "fixed_across": error_statistics(g.loc[fixed, "across_err_m"].to_numpy()),
    }


def _update_stats(u: pd.DataFrame) -> dict[str, Any]:
    res: dict[str, Any] = {}
    for kind, g in u.groupby("kind", sort=True):
        res[str(kind)] = update_kind_statistics(g["accepted"].to_numpy(bool), g["faulty"].to_numpy(bool),
                                                g["nis"].to_numpy(float), str(kind))
    return res


def update_kind_statistics(acc: np.ndarray, faulty: np.ndarray, nis: np.ndarray, kind: str = "") -> dict[str, Any]:
    """Rejections and NIS of one measurement kind's updates (in update order): used / rejected,
    true / false rejections and missed faults (the simulator knows which were faulty), NIS
    mean and fraction inside the chi-square band over the clean updates. ``uwb_constraint``
    updates (pulls onto a bound, thesis eq. 3.19-3.22) are not measurements: no NIS."""
    lo, hi = chi2_band(NIS_DOF)
    clean = ~faulty & (kind != KIND_CONSTRAINT)
    return {
        "used": int(acc.sum()),
        "rejected": int((~acc).sum()),
        "true_rejections": int((~acc & faulty).sum()),
        "false_rejections": int((~acc & ~faulty).sum()),
        "missed_faults": int((acc & faulty).sum()),
        "faulty": int(faulty.sum()),
        "nis_mean_clean": float(nis[clean].mean()) if clean.any() else float("nan"),
        "nis_frac_in_band_clean": float(np.mean((nis[clean] >= lo) & (nis[clean] <= hi))) if clean.any() else float("nan"),
    }


def vehicle_order(vehicle: str) -> tuple[str | int, ...]:
    """Sort key of a vehicle id in departure order: its digit runs compared as numbers
    (``c1.2`` before ``c1.10``, where text order puts ``c1.10`` first)."""
    return tuple(int(part) if part.isdigit() else part for part in re.split(r"(\d+)", vehicle))


def paper_table(stats: dict[str, Any]) -> str:
    """Along/across mean and std per solution and vehicle (Petovello et al. tables 3-8), metres;
    with carrier-phase solutions also the fix rate and the wrong-fix rate (``ambiguity``);
    vehicles in departure order (:func:`vehicle_order`)."""
    phase = any("ambiguity" in e for s in stats.values() for e in s["vehicles"].values())
    head = f"{'solution':24s} {'vehicle':8s} {'along mean':>10s} {'along std':>9s} {'across mean':>11s} {'across std':>10s} {'avail':>6s}"
    lines = [head + (f" {'fix':>5s} {'wrong':>6s}" if phase else "")]
    for sol, s in stats.items():
        for veh, e in sorted(s["vehicles"].items(), key=lambda item: vehicle_order(item[0])):
            a, c = e["along"], e["across"]
            line = f"{sol:24s} {veh:8s} {a['mean']:10.3f} {a['std']:9.3f} {c['mean']:11.3f} {c['std']:10.3f} {e['availability']:6.2f}"
            amb = e.get("ambiguity")
            if amb is not None:
                line += f" {amb['fix_rate']:5.2f} {amb['wrong_fix_rate']:6.3f}"
            lines.append(line)
    return "\n".join(lines)


def json_safe(obj: Any) -> Any:
    """NaN/inf -> None, numpy scalars -> Python (JSON has no NaN)."""
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [json_safe(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj
