"""Built-in nominal GPS constellation: the SPS PS 24-slot constellation, expanded (27) or baseline.

Slot tables
-----------
Six orbital planes A-F, given as right ascension of the ascending node (RAAN) and argument
of latitude at the defined epoch 1993-07-01 00:00:00 UTC, when the Greenwich hour angle (of
the FK5/J2000 equinox) was 18h36m14.4s = 279.06 deg. Reference orbit: circular (e = 0;
tolerance 0-0.02), semi-major axis 26 559.7 km, inclination 55 deg.

* **Baseline 24 slots** (``slots="baseline24"``): four slots per plane. GPS SPS Performance
  Standard, "Reference Orbit Slot Assignments as of the Defined Epoch" (Table 3-1 of the
  2001 edition, Table 3.1-1 of the 2008 and 2020 editions). Kaplan & Hegarty (2006) Table
  3.1 prints slot D3's argument of latitude as 35.136 deg instead of 35.156 deg (used here);
  the difference (0.02 deg, ~10 km along track) is immaterial to a sky plot.
* **Expandable 24-slot constellation, fully expanded: 27 slots** (``slots="expandable27"``,
  the default). SPS PS 2008 and 2020, section 3.1 and Table 3.1-2 ("Expandable Slots"):
  slots B1, D2 and F2 may each be split into a fore (``F``) and an aft (``A``) slot, which
  the Air Force completed in June 2011 (GPS.gov, "Space Segment": the "Expandable 24"
  configuration), i.e. 27 satellites in defined slots. Table 3.1-2 values used
  here (RAAN deg, argument of latitude deg): B1F (332.847, 94.916), B1A (332.847, 66.356),
  D2F (92.847, 282.676), D2A (92.847, 257.976), F2F (212.847, 0.456), F2A (212.847, 334.016).
  They were reproduced from public copies of the table, not from the PDF itself: check them
  against it before relying on them for anything but a realistic sky (an error of a few
  degrees along an orbit moves one satellite by a few degrees in the sky).

**Why 27 by default.** The user-facing default should give the sky a car sees on a typical
day. The operational GPS constellation has had about 30 healthy satellites since the late
2000s (the paper's February 2010 test was in such a sky; the extra ones are spares next to
occupied slots): the broadcast file of 2021-04-28 puts 11 above 10 deg at Calgary at the
default start time, the 24 baseline slots 6 (5-8 over the day, mean 6.8). The fully expanded
27-slot table is the largest *documented* slot table (Table 3.1-2): 8 at the start time,
mean 7.8 over the day (a uniformly filled shell would give N x 0.30: 7.2 and 8.1). It is
still a conservative sky; for a real date's sky, give a RINEX navigation file
(``sensors.gnss.ephemeris``).

PRN numbers 1..N are assigned to the slots in the order of :data:`SLOTS_BASELINE` /
:data:`SLOTS_EXPANDABLE`. **They are not the PRNs that occupied those slots on any real
date**: use a RINEX navigation file for a real sky.

Propagation model
-----------------
Two-body Keplerian circular orbits, with two documented departures:

* the ascending node regresses at the secular J2 rate
  ``Omega_dot = -3/2 n J2 (R_e / a)^2 cos i = -7.84e-9 rad/s (-0.0388 deg/day)``
  (J2 = 1.08263e-3, R_e = 6378.137 km); it matches the -4.4874e-7 deg/s of the SPS PS
  2001 nominal almanac (Table A-2-1);
* the argument of latitude advances at ``u_dot = 2 (OMEGA_E - Omega_dot)``: the ground
  track repeats every ``2 pi / (OMEGA_E - Omega_dot)`` (two orbits per ~sidereal day). The
  Air Force holds this by station-keeping (the SPS PS keeps ground-track equatorial
  crossings within +-2 deg). The two-body mean motion at a = 26 559.7 km is 9 ppm
  faster (1.35e-9 rad/s): propagated from 1993 that alone would slide the slots ~70 deg
  along their orbits by 2021. The difference is carried as ``delta_n`` of the elements.

Short-period J2 terms, lunisolar and solar-pressure perturbations and the precession of
the equinox since 1993 (~0.4 deg of hour angle by 2021; the Earth is rotated at the
IS-GPS-200 rate OMEGA_E) are neglected: metre-to-kilometre positions, adequate for
realistic satellite geometry (azimuth/elevation to ~0.5 deg), not for orbit accuracy.
Clocks are perfect (zero bias and drift); every satellite is healthy.
"""

from __future__ import annotations

from datetime import datetime

import numpy as np
from numpy.typing import ArrayLike

from v2v.errors import UserError
from v2v.sensors.gnss.ephemeris import OMEGA_E_RADPS, KeplerElements, SvStates, kepler_states
from v2v.sensors.gnss.time import gps_week_sow, utc_to_gps_s

NOMINAL_A_M = 26_559_700.0
NOMINAL_INCLINATION_RAD = np.deg2rad(55.0)
J2 = 1.08263e-3
EARTH_EQ_RADIUS_M = 6_378_137.0
SLOT_EPOCH_GPS_S = utc_to_gps_s(datetime(1993, 7, 1))
SLOT_EPOCH_GHA_RAD = np.deg2rad((18.0 + 36.0 / 60.0 + 14.4 / 3600.0) * 15.0)
VALIDITY_HALF_SPAN_S = 7.0 * 86_400.0

# (slot, RAAN deg, argument of latitude deg) at SLOT_EPOCH: SPS PS Table 3.1-1 (baseline 24 slots).
SLOTS_BASELINE: tuple[tuple[str, float, float], ...] = (
    ("A1", 272.847, 268.126),
    ("A2", 272.847, 161.786),
    ("A3", 272.847, 11.676),
    ("A4", 272.847, 41.806),
    ("B1", 332.847, 80.956),
    ("B2", 332.847, 173.336),
    ("B3", 332.847, 309.976),
    ("B4", 332.847, 204.376),
    ("C1", 32.847, 111.876),
    ("C2", 32.847, 11.796),
    ("C3", 32.847, 339.666),
    ("C4", 32.847, 241.556),
    ("D1", 92.847, 135.226),
    ("D2", 92.847, 265.446),
    ("D3", 92.847, 35.156),
    ("D4", 92.847, 167.356),
    ("E1", 152.847, 197.046),
    ("E2", 152.847, 302.596),
    ("E3", 152.847, 66.066),
    ("E4", 152.847, 333.686),
    ("F1", 212.847, 238.886),
    ("F2", 212.847, 345.226),
    ("F3", 212.847, 105.206),
    ("F4", 212.847, 135.346),
)

# SPS PS (2008, 2020) Table 3.1-2: the expandable slots B1, D2, F2, each split fore/aft.
EXPANDED_SLOTS: dict[str, tuple[tuple[str, float, float], tuple[str, float, float]]] = {
    "B1": (("B1F", 332.847, 94.916), ("B1A", 332.847, 66.356)),
    "D2": (("D2F", 92.847, 282.676), ("D2A", 92.847, 257.976)),
    "F2": (("F2F", 212.847, 0.456), ("F2A", 212.847, 334.016)),
}
SLOTS_EXPANDABLE: tuple[tuple[str, float, float], ...] = tuple(
    s for slot in SLOTS_BASELINE for s in EXPANDED_SLOTS.get(slot[0], (slot,))
)
SLOT_TABLES: dict[str, tuple[tuple[str, float, float], ...]] = {
    "baseline24": SLOTS_BASELINE,
    "expandable27": SLOTS_EXPANDABLE,
}


def j2_node_rate_radps(a_m: float = NOMINAL_A_M, inc_rad: float = NOMINAL_INCLINATION_RAD) -> float:
    """Secular J2 regression of the node of a circular orbit: ``-3/2 n J2 (R_e/a)^2 cos i`` (rad/s)."""
    from v2v.sensors.gnss.ephemeris import GM_MPS2

    n = np.sqrt(GM_MPS2 / a_m**3)
    return float(-1.5 * n * J2 * (EARTH_EQ_RADIUS_M / a_m) ** 2 * np.cos(inc_rad))


class NominalConstellation:
    """The nominal GPS constellation around a chosen date; implements ``Ephemeris``.

    Parameters
    ----------
    epoch_gps_s : GPS seconds of the scenario (e.g. ``utc_to_gps_s(start)``). Elements are
        referenced to this instant (like an almanac's time of applicability) and states
        are given for ``epoch +- 7 days``.
    slots : ``"expandable27"`` (default: SPS PS 2008/2020 Table 3.1-2, the 24-slot
        constellation with its three expandable slots split, 27 satellites) or
        ``"baseline24"`` (Table 3.1-1, 24 satellites).
    """

    def __init__(self, epoch_gps_s: float, *, slots: str = "expandable27"):
        if slots not in SLOT_TABLES:
            raise UserError(f"unknown nominal slot table {slots!r}", field="sensors.gnss.ephemeris",
                            fix=f"use one of {sorted(SLOT_TABLES)}")
        table = SLOT_TABLES[slots]
        self.slots = slots
        self.epoch_gps_s = float(epoch_gps_s)
        node_rate = j2_node_rate_radps()
        u_rate = 2.0 * (OMEGA_E_RADPS - node_rate)
        dt = self.epoch_gps_s - SLOT_EPOCH_GPS_S
        raan = np.deg2rad([s[1] for s in table])
        u0 = np.deg2rad([s[2] for s in table])
        # Earth-fixed longitude of the node at the epoch, and argument of latitude.
        lon_node = raan - SLOT_EPOCH_GHA_RAD + (node_rate - OMEGA_E_RADPS) * dt
        u_epoch = np.mod(u0 + u_rate * dt, 2.0 * np.pi)
        n = len(table)
        _, sow = gps_week_sow(self.epoch_gps_s)
        sqrt_a = np.sqrt(NOMINAL_A_M)
        from v2v.sensors.gnss.ephemeris import GM_MPS2

        zeros = np.zeros(n)
        self.slot_names = tuple(s[0] for s in table)
        self.elements = KeplerElements(
            prn=np.arange(1, n + 1, dtype=np.int64),
            sqrt_a_sqrtm=np.full(n, sqrt_a),
            e=zeros.copy(),
            i0_rad=np.full(n, NOMINAL_INCLINATION_RAD),
            # Table 20-IV: Omega(tk) = Omega0 + (Omega_dot - OMEGA_E) tk - OMEGA_E toe_sow.
            omega0_rad=np.mod(lon_node + OMEGA_E_RADPS * float(sow), 2.0 * np.pi),
            omega_rad=zeros.copy(),
            m0_rad=u_epoch,
            delta_n_radps=np.full(n, u_rate - np.sqrt(GM_MPS2 / NOMINAL_A_M**3)),
            idot_radps=zeros.copy(),
            omega_dot_radps=np.full(n, node_rate),
            cuc_rad=zeros.copy(),
            cus_rad=zeros.copy(),
            crc_m=zeros.copy(),
            crs_m=zeros.copy(),
            cic_rad=zeros.copy(),
            cis_rad=zeros.copy(),
            toe_gps_s=np.full(n, self.epoch_gps_s),
            toe_sow_s=np.full(n, float(sow)),
            toc_gps_s=np.full(n, self.epoch_gps_s),
            af0_s=zeros.copy(),
            af1_sps=zeros.copy(),
            af2_sps2=zeros.copy(),
            tgd_s=zeros.copy(),
            health=np.zeros(n, dtype=np.int64),
        )

    def prns(self) -> np.ndarray:
        return self.elements.prn.copy()

    def validity(self) -> tuple[float, float]:
        return self.epoch_gps_s - VALIDITY_HALF_SPAN_S, self.epoch_gps_s + VALIDITY_HALF_SPAN_S

    def sv_states(self, prn: ArrayLike, t_gps_s: float | ArrayLike) -> SvStates:
        """States in the ECEF frame at ``t``; an unknown PRN (not 1..N) gives NaN and ``healthy=False``.

        Raises
        ------
        UserError
            if any ``t`` is outside :meth:`validity`.
        """
        prn_arr = np.atleast_1d(np.asarray(prn, dtype=np.int64))
        t = np.broadcast_to(np.asarray(t_gps_s, dtype=float), prn_arr.shape)
        t0, t1 = self.validity()
        if np.any(~((t >= t0) & (t <= t1))):
            raise UserError(
                f"GPS time outside the nominal constellation's +-7 day span around {self.epoch_gps_s:.0f} GPS s",
                field="start_utc",
                fix="build the NominalConstellation with an epoch at the scenario's start",
            )
        known = (prn_arr >= 1) & (prn_arr <= self.elements.m)
        n = prn_arr.shape[0]
        pos = np.full((n, 3), np.nan)
        vel = np.full((n, 3), np.nan)
        clk = np.full(n, np.nan)
        drift = np.full(n, np.nan)
        if np.any(known):
            p, v, c, d, _ = kepler_states(self.elements.take(prn_arr[known] - 1), t[known])
            pos[known], vel[known], clk[known], drift[known] = p, v, c, d
        return SvStates(
            prn=prn_arr.copy(),
            pos_ecef_m=pos,
            vel_ecef_mps=vel,
            clock_bias_s=clk,
            clock_drift_sps=drift,
            healthy=known,
        )
