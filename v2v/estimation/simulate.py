"""Tiny truth + measurement generator for filter tests (not the simulator's sensors).

It draws an in-line cluster (lead ``"lead"``, followers ``"v1"``, ``"v2"``, ...) and
measurements from the *shared* model functions of :mod:`v2v.measmodels` with Gaussian
noise that matches the filter's assumptions exactly, so that NEES/NIS tests can check
the filter's consistency. The real sensors live in :mod:`v2v.sensors`.

Truth modes
-----------
``"kinematic"``: the lead drives at constant speed on a straight line or an arc
(constant turn rate); follower i sits ``i * gap`` behind the lead and at its lane offset
to the left, both fixed in the lead frame, so the relative ENU vector turns with the
lead. Clock states follow the process model.
``"process"``: every relative state (position, velocity, clock, drift, azimuth, UWB
bias/scale) is drawn from the filter's own discrete process model (exact Van Loan
F, Q), starting from the in-line formation with velocity, drift and UWB states drawn
from the filter's priors. This is the world in which the filter is exactly right.

Noise that matches the filter
-----------------------------
The filter treats every SD pseudorange as independent with variance 2 sigma^2. Here
the lead's pseudoranges and Dopplers are noise-free and each non-lead receiver carries
the whole SD noise (sigma * sqrt 2) on satellites the lead sees, so the SDs are
independent as assumed. On satellites hidden from the lead (``lead_blocked_prns``) the
non-lead receivers carry sigma each, so a non-lead/non-lead SD has variance 2 sigma^2
(exact for two followers; with more, the SDs share the reference vehicle's noise).
The lead base is the lead's true position (its error only enters by paper eq. 7).
Satellite clocks, atmosphere and multipath are zero: they cancel in single differences.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from v2v.estimation.filter import FilterConfig
from v2v.estimation.layout import StateLayout, uwb_pair_key
from v2v.estimation.process import azimuth_block, random_walk_variances, vehicle_block
from v2v.frames import (
    azimuth_elevation,
    ecef_to_enu_rotation,
    ecef_to_geodetic,
    geodetic_to_ecef,
    wrap_angle,
)
from v2v.measmodels import bearing_rad, range_m, range_rate_mps
from v2v.sensors.measurements import Bearings, GnssEpoch, UwbRanges

F64 = NDArray[np.float64]

GPS_ORBIT_RANGE_M = 2.2e7  # typical receiver-satellite range
GPS_SAT_SPEED_MPS = 3.0e3  # line-of-sight-perpendicular satellite speed seen from Earth


@dataclass(frozen=True, kw_only=True)
class SimScenario:
    """In-line cluster scenario. Angles in radians; followers are ``v1..v{n-1}``."""

    n_vehicles: int = 3
    dt_s: float = 0.1
    duration_s: float = 10.0
    truth: str = "kinematic"  # or "process"
    speed_mps: float = 14.0
    heading_rad: float = float(np.radians(30.0))
    turn_rate_rps: float = 0.0
    gap_m: float = 28.0
    lane_offsets_m: tuple[float, ...] = (0.0, 3.5)  # cycled over followers, + = left
    origin_lat_rad: float = float(np.radians(51.08))
    origin_lon_rad: float = float(np.radians(-114.13))
    origin_h_m: float = 1100.0
    sat_az_el_rad: tuple[tuple[float, float], ...] = tuple(
        (float(np.radians(a)), float(np.radians(e)))
        for a, e in [(10, 75), (80, 40), (150, 25), (200, 55), (260, 30), (320, 15), (40, 20), (120, 60)]
    )
    lead_blocked_prns: tuple[int, ...] = ()  # PRNs (1-based index into sat_az_el_rad) the lead cannot see
    gnss_every: int = 1  # GNSS every k-th epoch
    gnss_outage_s: tuple[float, float] | None = None  # [t0, t1): no GNSS
    uwb: bool = True
    bearing_vehicles: tuple[str, ...] = ("lead",)  # vehicles that measure bearings to all others
    uwb_state_pairs: tuple[tuple[str, str], ...] = ()  # pairs with bias/scale truth (process mode)
    uwb_bias_m: float = 0.0  # kinematic mode: bias of every pair in uwb_state_pairs
    uwb_scale: float = 0.0
    azimuth_rates: bool = False  # process mode: azimuths integrate a GM yaw rate (process.azimuth_block)
    # Carrier phase (generated when the filter config has ``phase``): every receiver gets a random
    # integer ambiguity per satellite; (t_s, vehicle, prn or 0 = all, cycles) slips add cycles from
    # t_s on and restart the lock time. Noise like the pseudoranges: the lead noise-free, followers
    # sigma_phi * sqrt 2 (independent SDs with variance 2 sigma_phi^2, as the filter assumes).
    phase_slips: tuple[tuple[float, str, int, int], ...] = ()
    silent_slips: bool = False  # slips keep the lock time running (no loss-of-lock indicator)
    # kinematic mode: the SD clock drifts at a constant rate (a real oscillator) instead of the
    # filter's deliberately loose Gauss-Markov drift (sigma 1000 m/s), whose 0.1 s increments of
    # ~140 m/s no carrier-minus-Doppler slip test could tell from a slip.
    steady_clock: bool = False


@dataclass(frozen=True, kw_only=True)
class SimEpoch:
    """Measurements and truth at one epoch."""

    t_s: float
    gnss: dict[str, GnssEpoch] | None
    lead_base_ecef_m: F64
    uwb: UwbRanges | None
    bearings: Bearings | None
    rel_state: dict[str, F64]  # vehicle -> [p(3), v(3), clk, drift]
    azimuth_rad: dict[str, float]
    azimuth_rate_rps: dict[str, float] = field(default_factory=dict)
    uwb_bias_scale: dict[tuple[str, str], tuple[float, float]] = field(default_factory=dict)
    lead_azimuth_rad: float = 0.0

    def truth_vector(self, layout: StateLayout) -> F64:
        """The true state in ``layout`` order (azimuths wrapped like the truth)."""
        x = np.zeros(layout.n)
        for v in layout.vehicles:
            x[layout.block("vehicle", v)] = self.rel_state[v]
        for v in layout.azimuth_vehicles:
            x[layout.azimuth(v)] = self.azimuth_rad[v]
        for v in layout.azimuth_rate_vehicles:
            x[layout.azimuth_rate(v)] = self.azimuth_rate_rps.get(v, 0.0)
        for pair in layout.uwb_pairs:
            b, s = self.uwb_bias_scale.get(pair, (0.0, 0.0))
            x[layout.uwb_bias(pair)] = b
            x[layout.uwb_scale(pair)] = s
        return x


def vehicle_ids(n: int) -> tuple[str, ...]:
    return ("lead",) + tuple(f"v{i}" for i in range(1, n))


def _draw(rng: np.random.Generator, cov: F64) -> F64:
    w, v = np.linalg.eigh(0.5 * (cov + cov.T))
    return v @ (np.sqrt(np.clip(w, 0.0, None)) * rng.standard_normal(len(w)))


def simulate(scn: SimScenario, cfg: FilterConfig, rng: np.random.Generator) -> list[SimEpoch]:
    """Truth and measurements for every epoch of ``scn`` (noise sigmas from ``cfg.noise``)."""
    ids = vehicle_ids(scn.n_vehicles)
    followers = ids[1:]
    pcfg, ncfg = cfg.process, cfg.noise
    origin = geodetic_to_ecef(scn.origin_lat_rad, scn.origin_lon_rad, scn.origin_h_m)
    r0 = ecef_to_enu_rotation(scn.origin_lat_rad, scn.origin_lon_rad)
    pos0_l: list[F64] = []
    vel_l: list[F64] = []
    for sat_az, sat_el in scn.sat_az_el_rad:
        u_enu = np.array([np.sin(sat_az) * np.cos(sat_el), np.cos(sat_az) * np.cos(sat_el), np.sin(sat_el)])
        perp = np.cross(u_enu, [0.0, 0.0, 1.0]) if abs(sat_el) < 1.5 else np.array([1.0, 0.0, 0.0])
        perp /= np.linalg.norm(perp)
        pos0_l.append(origin + (GPS_ORBIT_RANGE_M * u_enu) @ r0)
        vel_l.append((GPS_SAT_SPEED_MPS * perp) @ r0)
    sat_pos0, sat_vel = np.array(pos0_l), np.array(vel_l)
    prns = np.arange(1, len(sat_pos0) + 1)
    blocked = np.isin(prns, scn.lead_blocked_prns)

    n_ep = int(round(scn.duration_s / scn.dt_s)) + 1
    fb, qb = vehicle_block(pcfg, scn.dt_s)
    sig_d = pcfg.drift_sigma_mps
    sig_vh, sig_vv = pcfg.vel_sigma_horizontal_mps, pcfg.vel_sigma_vertical_mps

    def formation(i: int, heading: float) -> F64:
        along = -scn.gap_m * i
        across = scn.lane_offsets_m[(i - 1) % len(scn.lane_offsets_m)]
        fwd = np.array([np.sin(heading), np.cos(heading)])
        left = np.array([-np.cos(heading), np.sin(heading)])
        return np.r_[along * fwd + across * left, 0.0]

    # initial relative states
    rel = {}
    for i, v in enumerate(followers, start=1):
        s = np.zeros(8)
        s[0:3] = formation(i, scn.heading_rad)
        s[6] = rng.normal(0.0, 1e4)  # SD clock bias: anything, the filter initializes it
        s[7] = rng.normal(0.0, sig_d)
        if scn.truth == "process":
            s[3:6] = rng.normal(0.0, [sig_vh, sig_vh, sig_vv])
        rel[v] = s
    az = {v: scn.heading_rad for v in ids}
    az_rate = {v: (rng.normal(0.0, pcfg.yaw_rate_sigma_rps) if scn.truth == "process" and scn.azimuth_rates
                   else scn.turn_rate_rps) for v in ids}
    if scn.azimuth_rates:
        fa, qa = azimuth_block(pcfg, scn.dt_s)
    uwb_bs = {}
    for a, b in scn.uwb_state_pairs:
        key = uwb_pair_key(a, b)
        if scn.truth == "process":
            uwb_bs[key] = (rng.normal(0.0, cfg.uwb_bias_sigma0_m), rng.normal(0.0, cfg.uwb_scale_sigma0))
        else:
            uwb_bs[key] = (scn.uwb_bias_m, scn.uwb_scale)

    lead_enu = np.zeros(3)
    heading = scn.heading_rad
    epochs: list[SimEpoch] = []
    phase_cfg = cfg.phase
    if phase_cfg is not None:
        from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M

        amb = {v: rng.integers(-10_000, 10_000, size=len(prns), endpoint=True) for v in ids}
        lock_start = {v: np.zeros(len(prns)) for v in ids}
        slips_done: set[tuple[int, str]] = set()
    for k in range(n_ep):
        t = k * scn.dt_s
        if k > 0:
            # lead: constant speed, constant turn rate (exact arc integration)
            h0 = heading
            heading = h0 + scn.turn_rate_rps * scn.dt_s
            if abs(scn.turn_rate_rps) > 1e-12:
                rad = scn.speed_mps / scn.turn_rate_rps
                lead_enu = lead_enu + rad * np.array([np.cos(h0) - np.cos(heading), np.sin(heading) - np.sin(h0), 0.0])
            else:
                lead_enu = lead_enu + scn.speed_mps * scn.dt_s * np.array([np.sin(h0), np.cos(h0), 0.0])
            for i, v in enumerate(followers, start=1):
                s_prev = rel[v]
                s_new = fb @ s_prev + _draw(rng, qb)
                if scn.steady_clock:
                    s_new[7] = s_prev[7]
                    s_new[6] = s_prev[6] + s_prev[7] * scn.dt_s
                if scn.truth == "kinematic":
                    s_new[0:3] = formation(i, heading)
                    s_new[3:6] = (formation(i, heading + 1e-6) - formation(i, heading - 1e-6)) / 2e-6 \
                        * scn.turn_rate_rps
                rel[v] = s_new
            for v in ids:
                if scn.truth == "process" and scn.azimuth_rates:
                    a_new = fa @ np.array([az[v], az_rate[v]]) + _draw(rng, qa)
                    az[v], az_rate[v] = float(wrap_angle(a_new[0])), float(a_new[1])
                elif scn.truth == "process":
                    az[v] = float(wrap_angle(az[v] + np.sqrt(random_walk_variances(pcfg, "azimuth", scn.dt_s)[0])
                                             * rng.standard_normal()))
                else:
                    az[v] = float(wrap_angle(heading))
            if scn.truth == "process":
                q = np.sqrt(random_walk_variances(pcfg, "uwb", scn.dt_s))
                uwb_bs = {p: (b + q[0] * rng.standard_normal(), s + q[1] * rng.standard_normal())
                          for p, (b, s) in uwb_bs.items()}

        lead_ecef = origin + lead_enu @ r0
        lat, lon, _ = ecef_to_geodetic(lead_ecef)
        rot = ecef_to_enu_rotation(float(lat), float(lon))
        lead_vel_ecef = (scn.speed_mps * np.array([np.sin(heading), np.cos(heading), 0.0])) @ r0
        pos = {"lead": lead_ecef}
        vel = {"lead": lead_vel_ecef}
        clk = {"lead": 0.0}
        drift = {"lead": 0.0}
        for v in followers:
            pos[v] = lead_ecef + rel[v][0:3] @ rot
            vel[v] = lead_vel_ecef + rel[v][3:6] @ rot
            clk[v], drift[v] = rel[v][6], rel[v][7]

        gnss = None
        in_outage = scn.gnss_outage_s is not None and scn.gnss_outage_s[0] <= t < scn.gnss_outage_s[1]
        if k % scn.gnss_every == 0 and not in_outage:
            sv = sat_pos0 + sat_vel * t
            gnss = {}
            for v in ids:
                rho = range_m(pos[v], sv)
                rate = range_rate_mps(pos[v], vel[v], sv, sat_vel)
                if v == "lead":
                    s_pr, s_dp = np.zeros(len(sv)), np.zeros(len(sv))
                else:
                    s_pr = np.where(blocked, ncfg.pseudorange_sigma_m, ncfg.pseudorange_sigma_m * np.sqrt(2.0))
                    s_dp = np.where(blocked, ncfg.doppler_sigma_mps, ncfg.doppler_sigma_mps * np.sqrt(2.0))
                pr = rho + clk[v] + s_pr * rng.standard_normal(len(sv))
                dop = rate + drift[v] + s_dp * rng.standard_normal(len(sv))
                keep = ~blocked if v == "lead" else np.ones(len(sv), dtype=bool)
                enu = (sv - pos[v]) @ rot.T
                s_az, s_el = azimuth_elevation(enu)
                n = int(keep.sum())
                carrier = np.full(len(sv), np.nan)
                lock = np.zeros(len(sv))
                n_true = np.zeros(len(sv), dtype=np.int64)
                if phase_cfg is not None:
                    for si, (t_slip, v_slip, prn_slip, cycles) in enumerate(scn.phase_slips):
                        if v_slip == v and t >= t_slip - 1e-9 and (si, v) not in slips_done:
                            hit = np.ones(len(sv), dtype=bool) if prn_slip == 0 else prns == prn_slip
                            amb[v] = amb[v] + cycles * hit
                            if not scn.silent_slips:
                                lock_start[v][hit] = t
                            slips_done.add((si, v))
                    s_ph = 0.0 if v == "lead" else phase_cfg.phase_sigma_m * np.sqrt(2.0)
                    ph_m = rho + clk[v] + s_ph * rng.standard_normal(len(sv))
                    carrier = ph_m / GPS_L1_WAVELENGTH_M + amb[v]
                    lock = t - lock_start[v]
                    n_true = amb[v].astype(np.int64)
                gnss[v] = GnssEpoch(
                    t_s=t, vehicle_id=v, prn=prns[keep], pseudorange_m=pr[keep], doppler_mps=dop[keep],
                    carrier_cycles=carrier[keep], lock_time_s=lock[keep], cn0_dbhz=np.full(n, 45.0),
                    sv_pos_ecef_m=sv[keep], sv_vel_ecef_mps=sat_vel[keep], sv_clock_m=np.zeros(n),
                    elevation_rad=s_el[keep], azimuth_rad=s_az[keep], los=np.ones(n, dtype=bool),
                    true_range_m=rho[keep], ambiguity_cycles=n_true[keep],
                    errors_m={"noise": (pr - rho - clk[v])[keep]},
                )

        rel_enu = {"lead": np.zeros(3), **{v: rel[v][0:3] for v in followers}}
        uwb = None
        if scn.uwb:
            a_l, b_l, z_l, t_l = [], [], [], []
            for i, a in enumerate(ids):
                for b in ids[i + 1:]:
                    r_ab = float(range_m(rel_enu[a], rel_enu[b]))
                    bias, scale = uwb_bs.get(uwb_pair_key(a, b), (0.0, 0.0))
                    a_l.append(a)
                    b_l.append(b)
                    t_l.append(r_ab)
                    z_l.append((1.0 + scale) * r_ab + bias + ncfg.uwb_sigma_m * rng.standard_normal())
            m = len(z_l)
            uwb = UwbRanges(t_s=np.full(m, t), true_t_s=np.full(m, t), a=tuple(a_l), b=tuple(b_l),
                            range_m=np.array(z_l), true_range_m=np.array(t_l), los=np.ones(m, dtype=bool))
        bearings = None
        if scn.bearing_vehicles:
            a_l, b_l, z_l, t_l, az_l = [], [], [], [], []
            for a in scn.bearing_vehicles:
                for b in ids:
                    if b == a:
                        continue
                    tb = float(bearing_rad(rel_enu[b] - rel_enu[a], az[a]))
                    a_l.append(a)
                    b_l.append(b)
                    t_l.append(tb)
                    az_l.append(az[a])
                    z_l.append(float(wrap_angle(tb + ncfg.bearing_sigma_rad * rng.standard_normal())))
            m = len(z_l)
            bearings = Bearings(t_s=np.full(m, t), a=tuple(a_l), b=tuple(b_l), bearing_rad=np.array(z_l),
                                true_bearing_rad=np.array(t_l), azimuth_reported_rad=np.array(az_l),
                                true_azimuth_rad=np.array(az_l), los=np.ones(m, dtype=bool))
        epochs.append(SimEpoch(
            t_s=t, gnss=gnss, lead_base_ecef_m=lead_ecef, uwb=uwb, bearings=bearings,
            rel_state={v: rel[v].copy() for v in followers}, azimuth_rad=dict(az), azimuth_rate_rps=dict(az_rate),
            uwb_bias_scale=dict(uwb_bs), lead_azimuth_rad=heading,
        ))
    return epochs


def run_filter(ekf, epochs: list[SimEpoch], dt_s: float):
    """Feed simulated epochs to a filter (predict, GNSS, UWB, bearings); yields (epoch, infos)."""
    for k, ep in enumerate(epochs):
        if k > 0:
            ekf.predict(dt_s)
        infos = ekf.update_epoch(gnss=ep.gnss, lead_base_ecef_m=ep.lead_base_ecef_m, uwb=ep.uwb,
                                 bearings=ep.bearings)
        yield ep, infos
