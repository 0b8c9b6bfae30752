"""``measurements.parquet``: every synthesized measurement, one row each, long format.

Columns: ``t_s``, ``type`` (``pseudorange`` | ``uwb`` | ``bearing``), ``vehicle`` (receiver /
initiator / measuring vehicle), ``other`` (UWB responder or bearing target, else empty),
``prn`` (-1 if none), ``value`` (pseudorange m, range m, bearing rad), ``true_value``,
``los``; GNSS extras ``doppler_mps``, ``carrier_cycles``, ``elevation_rad``,
``azimuth_rad``, ``cn0_dbhz``, ``ambiguity_cycles``; bearing extras ``azimuth_reported_rad``
(the measuring vehicle's azimuth as it reports it) and ``true_azimuth_rad``; and one
``err_<component>_m`` column per error component of either sensor (NaN where it does not
apply). A UWB range's ``t_s`` is the time tag its initiator logged (true time plus the radio's
time-tag error), and its ``true_value`` the true range at that time tag.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from v2v.sensors.measurements import Bearings, GnssEpoch, UwbRanges


def measurements_table(gnss_epochs: Sequence[tuple[float, dict[str, GnssEpoch]]], uwb: UwbRanges | None,
                       bearings: Bearings | None) -> pd.DataFrame:
    parts = []
    for _, eps in gnss_epochs:
        for v, ep in eps.items():
            if ep.n == 0:
                continue
            d = {
                "t_s": np.full(ep.n, ep.t_s), "type": "pseudorange", "vehicle": v, "other": "", "prn": ep.prn,
                "value": ep.pseudorange_m, "true_value": ep.true_range_m, "los": ep.los,
                "doppler_mps": ep.doppler_mps, "carrier_cycles": ep.carrier_cycles,
                "elevation_rad": ep.elevation_rad, "azimuth_rad": ep.azimuth_rad, "cn0_dbhz": ep.cn0_dbhz,
                "ambiguity_cycles": ep.ambiguity_cycles.astype(float),
            }
            d.update({f"err_{k}_m": val for k, val in ep.errors_m.items()})
            parts.append(pd.DataFrame(d))
    if uwb is not None and uwb.n:
        d = {"t_s": uwb.t_s, "type": "uwb", "vehicle": list(uwb.a), "other": list(uwb.b), "prn": -1,
             "value": uwb.range_m, "true_value": uwb.true_range_m, "los": uwb.los}
        d.update({f"err_{k}_m": val for k, val in uwb.errors_m.items()})
        parts.append(pd.DataFrame(d))
    if bearings is not None and bearings.n:
        parts.append(pd.DataFrame({
            "t_s": bearings.t_s, "type": "bearing", "vehicle": list(bearings.a), "other": list(bearings.b), "prn": -1,
            "value": bearings.bearing_rad, "true_value": bearings.true_bearing_rad, "los": bearings.los,
            "azimuth_reported_rad": bearings.azimuth_reported_rad, "true_azimuth_rad": bearings.true_azimuth_rad,
        }))
    if not parts:
        return pd.DataFrame({"t_s": [], "type": [], "vehicle": [], "other": [], "prn": [], "value": [], "true_value": [], "los": []})
    df = pd.concat(parts, ignore_index=True)
    # the injected components exist only on the epochs a fault touched: 0 on the other rows of the
    # types they apply to (so that the components add up to value - true_value on every row)
    for col, types in _INJECTED.items():
        if col in df.columns:
            df.loc[df["type"].isin(types) & df[col].isna(), col] = 0.0
    return df.sort_values(["t_s", "type", "vehicle"], kind="stable", ignore_index=True)


_INJECTED = {"err_fault_m": ("pseudorange", "uwb"), "err_clock_jump_m": ("pseudorange",)}
