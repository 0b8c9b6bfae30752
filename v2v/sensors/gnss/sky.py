"""Which satellites a receiver sees: azimuth, elevation and range (library part of ``v2v sky``)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from v2v.frames import azimuth_elevation, ecef_to_enu, geodetic_to_ecef
from v2v.sensors.gnss.ephemeris import Ephemeris, sv_states_at_reception


def sky_view(
    lat_rad: float,
    lon_rad: float,
    h_m: float,
    t_gps_s: float,
    eph: Ephemeris,
    mask_el_rad: float = np.deg2rad(10.0),
    *,
    include_unhealthy: bool = False,
) -> pd.DataFrame:
    """Satellites above an elevation mask at a receiver, at a reception time.

    Satellite positions are taken at their transmit times and expressed in the ECEF frame
    at reception (:func:`~v2v.sensors.gnss.ephemeris.sv_states_at_reception`: light time
    and Earth rotation), then seen from the receiver in its local ENU frame
    (:func:`v2v.frames.azimuth_elevation`).

    Parameters
    ----------
    lat_rad, lon_rad, h_m : receiver geodetic position (WGS-84).
    t_gps_s : reception time, GPS seconds.
    eph : orbit source.
    mask_el_rad : keep satellites with ``el >= mask_el_rad``.
    include_unhealthy : also list satellites flagged unhealthy (never ones without a state).

    Returns
    -------
    DataFrame with columns ``prn`` (int), ``az_deg`` (clockwise from north, [0, 360)),
    ``el_deg``, ``range_m`` (geometric, in the reception ECEF frame) and ``healthy``,
    sorted by decreasing elevation.
    """
    rx = geodetic_to_ecef(lat_rad, lon_rad, h_m)
    prn = eph.prns()
    st, _ = sv_states_at_reception(eph, prn, rx, t_gps_s)
    have = np.all(np.isfinite(st.pos_ecef_m), axis=1)
    if not include_unhealthy:
        have &= st.healthy
    st = st.take(have)
    enu = ecef_to_enu(st.pos_ecef_m, lat_rad, lon_rad, rx)
    az, el = azimuth_elevation(enu)
    keep = el >= mask_el_rad
    df = pd.DataFrame(
        {
            "prn": st.prn[keep].astype(np.int64),
            "az_deg": np.rad2deg(az[keep]),
            "el_deg": np.rad2deg(el[keep]),
            "range_m": np.linalg.norm(enu[keep], axis=1),
            "healthy": st.healthy[keep],
        }
    )
    return df.sort_values("el_deg", ascending=False, ignore_index=True)
