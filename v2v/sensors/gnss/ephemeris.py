"""GPS satellite states from Keplerian ephemerides: the common interface of every orbit source.

Two sources implement :class:`Ephemeris`: a RINEX broadcast navigation file
(:class:`v2v.sensors.gnss.rinex.BroadcastEphemeris`) and the built-in nominal 24-slot
constellation (:class:`v2v.sensors.gnss.constellation.NominalConstellation`). Both evaluate
the user algorithm of IS-GPS-200 Table 20-IV, implemented once here in
:func:`kepler_states`.

Times are **GPS seconds**: seconds of GPS time since the GPS epoch 1980-01-06 00:00:00,
continuous (no week rollover, no leap seconds). See :mod:`v2v.sensors.gnss.time`.

References
----------
IS-GPS-200 (Rev. N), section 20.3.3.4.3 and Table 20-IV (user algorithm for ephemeris
determination), section 20.3.3.3.3.1 (user algorithm for SV clock correction, relativistic
term, L1 C/A group delay).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import ArrayLike, NDArray

# IS-GPS-200 constants (section 20.3.3.4.3, Table 20-IV).
GM_MPS2 = 3.986005e14  # WGS-84 value of the Earth's gravitational constant for GPS, m^3/s^2
OMEGA_E_RADPS = 7.2921151467e-5  # WGS-84 value of the Earth's rotation rate, rad/s
F_RELATIVISTIC_S_PER_SQRTM = -4.442807633e-10  # F = -2 sqrt(GM) / c^2, s/m^0.5 (20.3.3.3.3.1)
SPEED_OF_LIGHT_MPS = 299_792_458.0
GPS_WEEK_S = 604_800.0
KEPLER_TOL_RAD = 1e-13  # |dE| at which Kepler's equation is considered solved
KEPLER_MAX_ITER = 30  # Newton converges in <= 5 iterations for e < 0.1; guard only

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True, kw_only=True)
class SvStates:
    """States of ``n`` satellites at their (transmit) times.

    Attributes
    ----------
    prn : (n,) int64, satellite PRN numbers.
    pos_ecef_m : (n, 3) antenna position, WGS-84 ECEF, metres (frame: see the producer).
    vel_ecef_mps : (n, 3) velocity relative to the rotating ECEF frame, m/s.
    clock_bias_s : (n,) satellite clock offset ``dt_sv`` to *subtract* from the SV time
        to get GPS time, seconds: ``af0 + af1 dt + af2 dt^2 + dt_r - T_GD``
        (IS-GPS-200 20.3.3.3.3.1 and 20.3.3.3.3.2, L1 C/A single-frequency user).
    clock_drift_sps : (n,) its time derivative, s/s.
    healthy : (n,) bool. False when the broadcast SV health is non-zero or when no
        ephemeris covers the requested time (positions are then NaN).
    """

    prn: I64
    pos_ecef_m: F64
    vel_ecef_mps: F64
    clock_bias_s: F64
    clock_drift_sps: F64
    healthy: NDArray[np.bool_]

    @property
    def n(self) -> int:
        return int(self.prn.shape[0])

    def take(self, idx: ArrayLike) -> SvStates:
        """Subset (index array or boolean mask) along the satellite axis."""
        return SvStates(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})


@runtime_checkable
class Ephemeris(Protocol):
    """A source of GPS satellite states (broadcast file or nominal constellation)."""

    def prns(self) -> I64:
        """PRNs this source can give states for, sorted ascending."""
        ...

    def sv_states(self, prn: ArrayLike, t_gps_s: float | ArrayLike) -> SvStates:
        """States at GPS time(s) ``t_gps_s`` (transmit time; scalar or one per ``prn``).

        Positions are in the ECEF frame *at* ``t_gps_s`` (no Sagnac/Earth-rotation
        correction: see :func:`sv_states_at_reception`).
        """
        ...

    def validity(self) -> tuple[float, float]:
        """First and last GPS second (inclusive) for which the source gives states."""
        ...


@dataclass(frozen=True, kw_only=True)
class KeplerElements:
    """Broadcast (or almanac-like) Keplerian elements of ``m`` orbit records, one per entry.

    Angles in radians and rates in rad/s (RINEX stores them so; IS-GPS-200 transmits
    semicircles). ``toe_gps_s``/``toc_gps_s`` are continuous GPS seconds; ``toe_sow_s`` is
    the TOE as seconds of its GPS week (the reference of ``omega0_rad``, Table 20-IV).
    """

    prn: I64
    sqrt_a_sqrtm: F64
    e: F64
    i0_rad: F64
    omega0_rad: F64  # longitude of ascending node of the orbit plane at the week epoch
    omega_rad: F64  # argument of perigee
    m0_rad: F64
    delta_n_radps: F64
    idot_radps: F64
    omega_dot_radps: F64
    cuc_rad: F64
    cus_rad: F64
    crc_m: F64
    crs_m: F64
    cic_rad: F64
    cis_rad: F64
    toe_gps_s: F64
    toe_sow_s: F64
    toc_gps_s: F64
    af0_s: F64
    af1_sps: F64
    af2_sps2: F64
    tgd_s: F64
    health: I64

    @property
    def m(self) -> int:
        return int(self.prn.shape[0])

    def take(self, idx: ArrayLike) -> KeplerElements:
        """Subset of records (index array or boolean mask)."""
        return KeplerElements(**{f.name: getattr(self, f.name)[idx] for f in fields(self)})


def solve_kepler(mean_anomaly_rad: ArrayLike, e: ArrayLike) -> F64:
    """Eccentric anomaly ``E`` from Kepler's equation ``M = E - e sin E`` (IS-GPS-200 Table 20-IV).

    Newton's iteration ``E <- E - (E - e sin E - M) / (1 - e cos E)`` from ``E0 = M``, run
    until every ``|dE| < 1e-13`` rad. A single fixed-point step (as some libraries do)
    leaves ``e^2``-order errors: ~660 m along-track for GPS eccentricities of 0.01.
    """
    m_rad = np.asarray(mean_anomaly_rad, dtype=float)
    ecc = np.asarray(e, dtype=float)
    ecc_anom = m_rad.copy()
    for _ in range(KEPLER_MAX_ITER):
        d_e = (ecc_anom - ecc * np.sin(ecc_anom) - m_rad) / (1.0 - ecc * np.cos(ecc_anom))
        ecc_anom = ecc_anom - d_e
        if not np.any(np.abs(d_e) >= KEPLER_TOL_RAD):
            return ecc_anom
    raise RuntimeError(f"Kepler's equation did not converge (max |dE| = {np.max(np.abs(d_e)):.3e} rad)")


def kepler_states(el: KeplerElements, t_gps_s: ArrayLike) -> tuple[F64, F64, F64, F64, F64]:
    """Satellite ECEF position/velocity and clock at GPS time(s) ``t`` (IS-GPS-200 Table 20-IV).

    With ``A = sqrt_a^2``, ``n0 = sqrt(GM / A^3)``, ``tk = t - toe``:

    * ``n = n0 + delta_n``; ``M = M0 + n tk``; ``M = E - e sin E`` (solved to 1e-13 rad);
    * ``nu = atan2(sqrt(1 - e^2) sin E, cos E - e)``; ``phi = nu + omega``;
    * ``du = cus sin 2phi + cuc cos 2phi``, ``dr = crs sin 2phi + crc cos 2phi``,
      ``di = cis sin 2phi + cic cos 2phi``;
    * ``u = phi + du``; ``r = A (1 - e cos E) + dr``; ``i = i0 + di + IDOT tk``;
    * ``Omega = Omega0 + (Omega_dot - OMEGA_E) tk - OMEGA_E toe_sow`` (Earth rotation);
    * ``x = x' cos Omega - y' cos i sin Omega``, ``y = x' sin Omega + y' cos i cos Omega``,
      ``z = y' sin i`` with ``x' = r cos u``, ``y' = r sin u``.

    Velocity is the analytic time derivative of these expressions (IS-GPS-200 Table
    20-IV, "SV velocity" rows): ``Edot = n / (1 - e cos E)``,
    ``nudot = Edot sqrt(1 - e^2) / (1 - e cos E)``, ``udot = nudot (1 + 2 (cus cos 2phi -
    cuc sin 2phi))``, ``rdot = A e sin E Edot + 2 nudot (crs cos 2phi - crc sin 2phi)``,
    ``idot = IDOT + 2 nudot (cis cos 2phi - cic sin 2phi)``, ``Omegadot = Omega_dot - OMEGA_E``.

    Clock (IS-GPS-200 20.3.3.3.3.1): ``dt_sv = af0 + af1 (t - toc) + af2 (t - toc)^2 + dt_r
    - T_GD`` with ``dt_r = F e sqrt(A) sin E``, ``F = -4.442807633e-10 s/m^0.5``; its rate
    adds ``F e sqrt(A) cos E Edot``.

    Parameters
    ----------
    el : the ``m`` records to evaluate, one time each.
    t_gps_s : (m,) or scalar GPS seconds.

    Returns
    -------
    pos_ecef_m (m, 3), vel_ecef_mps (m, 3), clock_bias_s (m,), clock_drift_sps (m,),
    ecc_anomaly_rad (m,).
    """
    t = np.broadcast_to(np.asarray(t_gps_s, dtype=float), el.prn.shape)
    a_m = el.sqrt_a_sqrtm**2
    n0 = np.sqrt(GM_MPS2 / a_m**3)
    n = n0 + el.delta_n_radps
    tk = t - el.toe_gps_s
    ecc_anom = solve_kepler(el.m0_rad + n * tk, el.e)
    sin_e, cos_e = np.sin(ecc_anom), np.cos(ecc_anom)
    one_m_ecos = 1.0 - el.e * cos_e
    sqrt_1me2 = np.sqrt(1.0 - el.e**2)
    nu = np.arctan2(sqrt_1me2 * sin_e, cos_e - el.e)
    phi = nu + el.omega_rad
    s2, c2 = np.sin(2.0 * phi), np.cos(2.0 * phi)
    u = phi + el.cus_rad * s2 + el.cuc_rad * c2
    r = a_m * one_m_ecos + el.crs_m * s2 + el.crc_m * c2
    inc = el.i0_rad + el.cis_rad * s2 + el.cic_rad * c2 + el.idot_radps * tk
    big_omega = el.omega0_rad + (el.omega_dot_radps - OMEGA_E_RADPS) * tk - OMEGA_E_RADPS * el.toe_sow_s

    cu, su = np.cos(u), np.sin(u)
    co, so = np.cos(big_omega), np.sin(big_omega)
    ci, si = np.cos(inc), np.sin(inc)
    xp, yp = r * cu, r * su
    x = xp * co - yp * ci * so
    y = xp * so + yp * ci * co
    z = yp * si

    e_dot = n / one_m_ecos
    nu_dot = e_dot * sqrt_1me2 / one_m_ecos
    u_dot = nu_dot * (1.0 + 2.0 * (el.cus_rad * c2 - el.cuc_rad * s2))
    r_dot = a_m * el.e * sin_e * e_dot + 2.0 * nu_dot * (el.crs_m * c2 - el.crc_m * s2)
    i_dot = el.idot_radps + 2.0 * nu_dot * (el.cis_rad * c2 - el.cic_rad * s2)
    om_dot = el.omega_dot_radps - OMEGA_E_RADPS
    xp_dot = r_dot * cu - r * u_dot * su
    yp_dot = r_dot * su + r * u_dot * cu
    vx = xp_dot * co - yp_dot * ci * so + yp * si * so * i_dot - y * om_dot
    vy = xp_dot * so + yp_dot * ci * co - yp * si * co * i_dot + x * om_dot
    vz = yp_dot * si + yp * ci * i_dot

    dtc = t - el.toc_gps_s
    f_e_sqrta = F_RELATIVISTIC_S_PER_SQRTM * el.e * el.sqrt_a_sqrtm
    clock_bias = el.af0_s + el.af1_sps * dtc + el.af2_sps2 * dtc**2 + f_e_sqrta * sin_e - el.tgd_s
    clock_drift = el.af1_sps + 2.0 * el.af2_sps2 * dtc + f_e_sqrta * cos_e * e_dot
    pos = np.stack([x, y, z], axis=-1)
    vel = np.stack([vx, vy, vz], axis=-1)
    return pos, vel, clock_bias, clock_drift, ecc_anom


def rotate_earth(vec_ecef: ArrayLike, angle_rad: ArrayLike) -> F64:
    """Rotate ECEF vector(s) about z by ``-angle``: the frame rotates by ``angle`` meanwhile.

    A vector fixed in the ECEF frame of an earlier instant, expressed in the ECEF frame
    ``tau`` seconds later (``angle = OMEGA_E tau``): ``x' = cos a x + sin a y``,
    ``y' = -sin a x + cos a y``, ``z' = z`` (the Earth-rotation or Sagnac correction,
    IS-GPS-200 20.3.3.4.3.4 and e.g. Misra & Enge (2011) eq. 5.16).
    """
    v = np.asarray(vec_ecef, dtype=float)
    a = np.asarray(angle_rad, dtype=float)
    c, s = np.cos(a), np.sin(a)
    return np.stack([c * v[..., 0] + s * v[..., 1], -s * v[..., 0] + c * v[..., 1], v[..., 2]], axis=-1)


def sv_states_at_reception(
    eph: Ephemeris,
    prn: ArrayLike,
    rx_ecef_m: ArrayLike,
    t_rx_gps_s: float,
    rx_clock_bias_s: float = 0.0,
    *,
    tol_s: float = 1e-12,
    max_iter: int = 10,
) -> tuple[SvStates, F64]:
    """Satellite states for signals received at ``rx_ecef_m``, in the ECEF frame at reception.

    The true reception time is ``t_r = t_rx_gps_s - rx_clock_bias_s`` (the receiver
    clock reads ``t_rx_gps_s``; its bias is the amount it is ahead of GPS time). The
    geometric transit time ``tau`` solves the light-time equation

    ``tau = |R3(OMEGA_E tau) x_sv(t_r - tau) - x_rx| / c``

    by fixed-point iteration from ``tau = 0.075 s`` until ``|d tau| < tol_s`` (contraction
    factor ``|v_sv| / c ~ 1e-5``: three iterations reach 1e-12 s). ``R3`` rotates the
    satellite position and velocity from the ECEF frame at transmission into the ECEF frame
    at reception (:func:`rotate_earth`): ``OMEGA_E tau ~ 5e-6 rad`` moves the satellite by
    ~ 130 m in x/y, changing the range by up to ~ 40 m.

    Parameters
    ----------
    eph : the orbit source.
    prn : (n,) PRNs.
    rx_ecef_m : (3,) receiver antenna position, ECEF at reception, metres.
    t_rx_gps_s : receiver time tag of reception, GPS seconds.
    rx_clock_bias_s : receiver clock bias, seconds.

    Returns
    -------
    states : satellite states at transmit time ``t_r - tau``, rotated into the ECEF frame
        at reception (clock terms are evaluated at the transmit time).
    transit_time_s : (n,) geometric signal travel time ``tau``, seconds (NaN where the
        ephemeris has no valid state).
    """
    prn_arr = np.atleast_1d(np.asarray(prn, dtype=np.int64))
    rx = np.asarray(rx_ecef_m, dtype=float).reshape(3)
    t_r = float(t_rx_gps_s) - float(rx_clock_bias_s)
    tau = np.full(prn_arr.shape, 0.075)
    for _ in range(max_iter):
        st = eph.sv_states(prn_arr, t_r - tau)
        pos = rotate_earth(st.pos_ecef_m, OMEGA_E_RADPS * tau)
        tau_new = np.linalg.norm(pos - rx, axis=-1) / SPEED_OF_LIGHT_MPS
        done = not np.any(np.abs(tau_new - tau) >= tol_s)  # NaN (no ephemeris) counts as done
        tau = np.where(np.isfinite(tau_new), tau_new, tau)
        if done:
            break
    st = eph.sv_states(prn_arr, t_r - tau)
    angle = OMEGA_E_RADPS * tau
    tau_out = np.where(np.all(np.isfinite(st.pos_ecef_m), axis=-1), tau, np.nan)
    out = SvStates(
        prn=st.prn,
        pos_ecef_m=rotate_earth(st.pos_ecef_m, angle),
        vel_ecef_mps=rotate_earth(st.vel_ecef_mps, angle),
        clock_bias_s=st.clock_bias_s,
        clock_drift_sps=st.clock_drift_sps,
        healthy=st.healthy,
    )
    return out, tau_out
