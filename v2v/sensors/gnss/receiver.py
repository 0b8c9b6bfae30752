"""Per-vehicle GNSS receiver measurement synthesis (pseudorange, Doppler, carrier phase).

Measurement models (MacGougan 2009 eq. 3.1, 3.6 and 5.1; Misra & Enge 2011 ch. 5)::

    P   = rho + c dT - c dt_sv + orbit + I + T + MP + NLOS + eps_P                    (m)
    Phi = (rho + c dT - c dt_sv + orbit - I + T + mp_phi + NLOS + eps_phi) / lambda + N   (cycles)
    dP/dt = e . (v_sv - v_rx) / (1 + (e . v_sv - w e . (y_sv, -x_sv, 0)) / c)
            + c dT/dt - c d(dt_sv)/dt + eps_D                                           (m/s)

* ``rho`` (``true_range_m``): geometric range from the true antenna at the true reception
  time ``t = gps_start + t_s`` to the *broadcast* satellite position at the transmit time
  (light-time iteration), in the ECEF frame at reception (Earth rotation / Sagnac,
  IS-GPS-200 20.3.3.4.3.4). It is what the filter's model ``|x_sv - x|`` gives at the
  true position; the difference to the true satellite position is the ``orbit`` term.
* Doppler: ``e`` unit vector receiver -> satellite; the denominator is the light-time
  rate (transmit time advances by ``1 - rho_dot / c`` per received second, and the
  Earth-rotation angle ``w tau`` changes with it): ~4 mm/s.
  Ionosphere/troposphere/multipath rates (mm/s to cm/s) are not included.
* ``c dT``: receiver clock bias, two-state model (:mod:`.clock`). The epoch is tagged
  with the true time; the bias appears in the measurements only (thesis eq. 3.1).
* ``c dt_sv`` = broadcast clock (``sv_clock_m``, incl. relativistic term and T_GD as the
  ephemeris gives it) + the broadcast clock error (``sv_clock_error``).

``errors_m`` holds one (n,) array per term, so that
``pseudorange_m - true_range_m - sum(errors_m.values()) == 0`` (to float rounding):

===============  ================================================================
``clock``        ``+c dT`` receiver clock bias (incl. millisecond jumps)
``sv_clock``     ``-sv_clock_m``: broadcast satellite clock (known: add ``sv_clock_m``)
``sv_clock_error`` ``-(c dt_sv,true - sv_clock_m)``: common to all receivers
``orbit``        ``|x_sv,true - x| - |x_sv,bc - x|``: common to nearby receivers
``iono``         L1 group delay (> 0); the carrier gets ``-iono``
``tropo``        tropospheric delay
``multipath``    code multipath (Gauss-Markov, elevation dependent)
``nlos``         echo-only excess path (> 0; 0 for line-of-sight signals)
``noise``        DLL thermal noise (C/N0 dependent, loop-correlated)
===============  ================================================================

Randomness: everything shared by receivers (ionosphere field, troposphere residual,
satellite orbit/clock errors) comes from streams keyed by a tag under the run's
``SeedSequence``; each vehicle's streams are keyed by a stable hash of its id (and then
by component), so adding a vehicle does not change any other vehicle's noise.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from v2v.errors import UserError
from v2v.frames import GeoReference, ecef_to_enu_rotation
from v2v.sensors.gnss.atmosphere import IonosphereField, SatelliteErrors, TroposphereField
from v2v.sensors.gnss.clock import ReceiverClock
from v2v.sensors.gnss.ephemeris import OMEGA_E_RADPS, Ephemeris, rotate_earth
from v2v.sensors.gnss.errors import (
    GnssErrorConfig,
    cn0_dbhz,
    dll_jitter_m,
    doppler_sigma_mps,
    gauss_markov_step,
    multipath_sigma_m,
    pll_jitter_m,
)
from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M, SPEED_OF_LIGHT_MPS, GnssEpoch
from v2v.traffic.snapshot import TrafficStep, VehicleState

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

ERROR_KEYS = ("clock", "sv_clock", "sv_clock_error", "orbit", "iono", "tropo", "multipath", "nlos", "noise")

# SeedSequence spawn-key tags (stable: changing them changes every run's numbers).
_TAG_IONO, _TAG_TROPO, _TAG_SAT, _TAG_VEHICLE = 1, 2, 3, 100
_COMP_CLOCK, _COMP_MULTIPATH, _COMP_NOISE, _COMP_PHASE, _COMP_DOPPLER = 1, 2, 3, 4, 5
_TRANSIT_TOL_S = 1e-12  # light-time iteration tolerance (0.3 mm of range)
_CANDIDATE_MARGIN_RAD = np.deg2rad(2.0)  # coarse visibility screen margin (receivers within ~100 km)
_MAX_PRN_SLOTS = 256


def _child_seed(seed: np.random.SeedSequence, *key: int) -> np.random.SeedSequence:
    """Deterministic child ``SeedSequence`` addressed by ``key`` (what ``spawn`` does, but by name)."""
    return np.random.SeedSequence(seed.entropy, spawn_key=(*seed.spawn_key, *key))


def vehicle_key(vehicle_id: str) -> int:
    """Stable 32-bit key of a vehicle id (CRC-32 of its UTF-8 bytes)."""
    return zlib.crc32(vehicle_id.encode("utf-8"))


@dataclass(frozen=True, kw_only=True)
class GnssReceiverConfig:
    """Receiver settings.

    Parameters
    ----------
    rate_hz : float
        Measurement rate (the paper's OEM4 logged 20 Hz; default 10 Hz).
    elevation_mask_rad : float
        Satellites below are not tracked (default 10 deg).
    errors : GnssErrorConfig
        All error models (each switchable).
    """

    rate_hz: float = 10.0
    elevation_mask_rad: float = np.deg2rad(10.0)
    errors: GnssErrorConfig = field(default_factory=GnssErrorConfig)

    def __post_init__(self) -> None:
        if not 0.0 < self.rate_hz <= 100.0:
            raise UserError(f"GNSS rate must be in (0, 100] Hz, got {self.rate_hz}", field="gnss.rate_hz",
                            fix="use 10 or 20")
        if not 0.0 <= self.elevation_mask_rad < np.pi / 2:
            raise UserError("elevation mask must be in [0, 90) deg", field="gnss.elevation_mask_deg",
                            fix="use 10 deg")


@dataclass(frozen=True, kw_only=True)
class _SatGeometry:
    """Geometry and common errors of one receiver's candidate satellites at one epoch (k,)."""

    prn: I64
    sv_pos_ecef_m: F64
    sv_vel_ecef_mps: F64
    sv_clock_m: F64
    sv_clock_drift_mps: F64
    range_m: F64
    los_unit: F64
    el_rad: F64
    az_rad: F64
    orbit_m: F64
    sv_clock_error_m: F64
    iono_m: F64
    tropo_m: F64


class GnssReceiver:
    """One vehicle's receiver: clock, tracking states, per-satellite error processes.

    Created by :class:`GnssSynthesizer`; :meth:`measure` turns one epoch's satellite
    geometry (with the common errors already evaluated) and the antenna's sky view into a
    :class:`GnssEpoch`.
    """

    def __init__(self, vehicle_id: str, config: GnssReceiverConfig, seed: np.random.SeedSequence, t0_s: float):
        self.vehicle_id = vehicle_id
        self.config = config
        vs = _child_seed(seed, _TAG_VEHICLE, vehicle_key(vehicle_id))
        self.rng_multipath = np.random.default_rng(_child_seed(vs, _COMP_MULTIPATH))
        self.rng_noise = np.random.default_rng(_child_seed(vs, _COMP_NOISE))
        self.rng_phase = np.random.default_rng(_child_seed(vs, _COMP_PHASE))
        self.rng_doppler = np.random.default_rng(_child_seed(vs, _COMP_DOPPLER))
        self.clock = ReceiverClock.start(config.errors.clock, np.random.default_rng(_child_seed(vs, _COMP_CLOCK)), t0_s)
        n = _MAX_PRN_SLOTS
        self._last_t = np.full(n, -np.inf)  # last epoch each PRN was tracked
        self._z_mp = np.zeros(n)  # unit-variance code multipath state
        self._z_mp_phase = np.zeros(n)
        self._z_noise = np.zeros(n)  # unit-variance DLL noise state
        self._ambiguity = np.zeros(n, dtype=np.int64)
        self._lock_start = np.zeros(n)
        self._los = np.ones(n, dtype=bool)
        self._dt_epoch = 1.0 / config.rate_hz

    def measure(
        self,
        t_s: float,
        geom: _SatGeometry,
        vel_ecef_mps: F64,
        sky: Any | None,
    ) -> GnssEpoch:
        """Synthesize the epoch at ``t_s`` (see the module docstring for the models)."""
        cfg = self.config
        err = cfg.errors
        trk = err.tracking
        self.clock.advance_to(t_s)

        k = geom.prn.shape[0]
        blocked = np.zeros(k, dtype=bool)
        echo = np.full(k, np.nan)
        foliage_db = np.zeros(k)
        if sky is not None and k:
            blocked = np.asarray(sky.blocked, dtype=bool)
            echo = np.asarray(sky.echo_excess_m, dtype=float)
            foliage_db = np.asarray(sky.foliage_loss_db, dtype=float)
        has_echo = blocked & np.isfinite(echo)
        nlos = has_echo if trk.nlos_enabled else np.zeros(k, dtype=bool)
        cn0 = cn0_dbhz(geom.el_rad, trk, foliage_db, nlos)
        tracked = (geom.el_rad >= cfg.elevation_mask_rad) & (~blocked | nlos) & (cn0 >= trk.track_threshold_dbhz)
        idx = np.flatnonzero(tracked)
        prn = geom.prn[idx]
        el = geom.el_rad[idx]
        cn0 = cn0[idx]
        nlos = nlos[idx]
        n = idx.size

        # Lock continuity: a gap (missed epoch), a LOS <-> echo switch or a random slip
        # starts a new arc with a new integer ambiguity.
        gap = t_s - self._last_t[prn]
        new_arc = (gap > 1.5 * self._dt_epoch) | (self._los[prn] != ~nlos)
        if trk.random_slip_rate_hz > 0.0 and n:
            p_slip = 1.0 - np.exp(-trk.random_slip_rate_hz * np.minimum(gap, self._dt_epoch))
            new_arc |= self.rng_phase.random(n) < p_slip
        if new_arc.any():
            m = int(new_arc.sum())
            self._ambiguity[prn[new_arc]] = self.rng_phase.integers(
                -trk.ambiguity_max_cycles, trk.ambiguity_max_cycles, size=m, endpoint=True
            )
            self._lock_start[prn[new_arc]] = t_s
        self._los[prn] = ~nlos

        # Multipath (code and carrier) and DLL noise: unit Gauss-Markov states, exact steps.
        dt = np.where(np.isfinite(gap), gap, np.inf)
        zeros = np.zeros(n)
        if err.multipath.enabled and n:
            self._z_mp[prn] = gauss_markov_step(self._z_mp[prn], dt, err.multipath.tau_s, self.rng_multipath)
            self._z_mp_phase[prn] = gauss_markov_step(
                self._z_mp_phase[prn], dt, err.multipath.tau_s, self.rng_multipath
            )
            sig_mp = multipath_sigma_m(el, err.multipath)
            mp = sig_mp * self._z_mp[prn]
            mp_phase = err.multipath.phase_multipath_ratio * sig_mp * self._z_mp_phase[prn]
        else:
            mp = mp_phase = zeros
        if trk.noise_enabled and n:
            self._z_noise[prn] = gauss_markov_step(self._z_noise[prn], dt, trk.dll_correlation_time_s, self.rng_noise)
            noise = dll_jitter_m(cn0, trk) * self._z_noise[prn]
            noise_phase = pll_jitter_m(cn0, trk) * self.rng_phase.standard_normal(n)
            noise_dopp = doppler_sigma_mps(cn0, trk) * self.rng_doppler.standard_normal(n)
        else:
            noise = noise_phase = noise_dopp = zeros
        self._last_t[prn] = t_s

        nlos_m = np.where(nlos, echo[idx], 0.0)  # nlos implies a finite echo (has_echo)
        rho = geom.range_m[idx]
        errors = {
            "clock": np.full(n, self.clock.bias_m),
            "sv_clock": -geom.sv_clock_m[idx],
            "sv_clock_error": -geom.sv_clock_error_m[idx],
            "orbit": geom.orbit_m[idx],
            "iono": geom.iono_m[idx],
            "tropo": geom.tropo_m[idx],
            "multipath": mp,
            "nlos": nlos_m,
            "noise": noise,
        }
        pseudorange = rho + sum(errors[key] for key in ERROR_KEYS)
        phase_m = (
            pseudorange
            - errors["iono"] * 2.0
            - errors["multipath"]
            - errors["noise"]
            + mp_phase
            + noise_phase
        )
        amb = self._ambiguity[prn].copy()
        carrier = phase_m / GPS_L1_WAVELENGTH_M + amb
        e = geom.los_unit[idx]
        # Light-time rate: the satellite position in the reception frame is R3(w tau) x_sv(t - tau);
        # with tau_dot = rho_dot / c its rate is R3 v_sv (1 - tau_dot) + w tau_dot (y, -x, 0).
        p_sv = geom.sv_pos_ecef_m[idx]
        e_vsv = np.einsum("ij,ij->i", e, geom.sv_vel_ecef_mps[idx])
        e_rot = OMEGA_E_RADPS * (e[:, 0] * p_sv[:, 1] - e[:, 1] * p_sv[:, 0])
        range_rate = (e_vsv - e @ vel_ecef_mps) / (1.0 + (e_vsv - e_rot) / SPEED_OF_LIGHT_MPS)
        doppler = range_rate + self.clock.drift_mps - geom.sv_clock_drift_mps[idx] + noise_dopp

        return GnssEpoch(
            t_s=float(t_s),
            vehicle_id=self.vehicle_id,
            prn=prn.astype(np.int64),
            pseudorange_m=pseudorange,
            doppler_mps=doppler,
            carrier_cycles=carrier,
            lock_time_s=t_s - self._lock_start[prn],
            cn0_dbhz=cn0,
            sv_pos_ecef_m=geom.sv_pos_ecef_m[idx],
            sv_vel_ecef_mps=geom.sv_vel_ecef_mps[idx],
            sv_clock_m=geom.sv_clock_m[idx],
            elevation_rad=el,
            azimuth_rad=geom.az_rad[idx],
            los=~nlos,
            true_range_m=rho,
            ambiguity_cycles=amb,
            errors_m=errors,
        )


class GnssSynthesizer:
    """GNSS measurements of every vehicle, with errors shared where physics shares them.

    Parameters
    ----------
    ephemeris : Ephemeris
        Broadcast ephemeris or nominal constellation (positions are "broadcast").
    config : GnssReceiverConfig
    seed : np.random.SeedSequence
        The run's GNSS seed; everything random derives from it.
    gps_start_s : float
        GPS seconds of scenario time ``t_s = 0``.
    occlusion : OcclusionGeometry | None
        Buildings/foliage: :class:`v2v.world.occlusion.OcclusionGeometry` (its batched
        ``sky_many``), or any object with its per-antenna ``sky`` method; None = open sky.
    georef : GeoReference | None
        Needed with ``occlusion``: converts true azimuths to grid azimuths
        (``az_grid = az - grid_convergence``; the convergence is evaluated once at the first
        vehicle position: it changes by ~0.006 deg per km east at mid-latitudes).

    Use :meth:`feed` with each :class:`TrafficStep` (emits the epochs due), or :meth:`run`.
    """

    def __init__(
        self,
        ephemeris: Ephemeris,
        config: GnssReceiverConfig,
        seed: np.random.SeedSequence,
        gps_start_s: float,
        *,
        occlusion: Any | None = None,
        georef: GeoReference | None = None,
    ):
        if occlusion is not None and georef is None:
            raise UserError("an occlusion geometry needs the net's geo-reference", field="georef",
                            fix="pass the GeoReference of the SUMO net")
        self.eph = ephemeris
        self.config = config
        self.seed = seed
        self.gps_start_s = float(gps_start_s)
        self.occlusion = occlusion
        self.georef = georef
        self.receivers: dict[str, GnssReceiver] = {}
        self.satellite_errors = SatelliteErrors(config.errors.satellite, _child_seed(seed, _TAG_SAT))
        self._prns = np.asarray(ephemeris.prns(), dtype=np.int64)
        if self._prns.size and self._prns.max() >= _MAX_PRN_SLOTS:
            raise UserError(f"PRN {self._prns.max()} out of range", field="ephemeris",
                            fix=f"use PRNs below {_MAX_PRN_SLOTS}")
        self._pass_index = np.zeros(_MAX_PRN_SLOTS, dtype=np.int64)
        self._above = np.zeros(_MAX_PRN_SLOTS, dtype=bool)
        self._iono: IonosphereField | None = None
        self._tropo: TroposphereField | None = None
        self._convergence_rad: float | None = None
        self._next_k: int | None = None

    # ------------------------------------------------------------------ scheduling
    def feed(self, step: TrafficStep) -> list[dict[str, GnssEpoch]]:
        """Epochs due up to ``step.t_s`` (on the ``k / rate_hz`` grid), one dict per epoch.

        Vehicle truth is moved from ``step.t_s`` to each epoch time with its velocity
        (only when the traffic step is coarser than or offset from the GNSS grid).
        """
        rate = self.config.rate_hz
        if self._next_k is None:
            self._next_k = int(np.ceil(step.t_s * rate - 1e-6))
        out = []
        while self._next_k / rate <= step.t_s + 1e-6:
            t_e = self._next_k / rate
            if step.vehicles:
                out.append(self.epoch(t_e, step.vehicles))
            self._next_k += 1
        return out

    def run(self, steps: Iterable[TrafficStep]) -> list[GnssEpoch]:
        """All epochs of all vehicles, ordered by time then vehicle id."""
        out: list[GnssEpoch] = []
        for step in steps:
            for ep in self.feed(step):
                out.extend(ep[v] for v in sorted(ep))
        return out

    # ------------------------------------------------------------------ one epoch
    def _init_fields(self, lat_rad: float, lon_rad: float, xy_m: F64) -> None:
        e = self.config.errors
        self._iono = IonosphereField(e.iono, np.random.default_rng(_child_seed(self.seed, _TAG_IONO)), lat_rad, lon_rad)
        self._tropo = TroposphereField(e.tropo, np.random.default_rng(_child_seed(self.seed, _TAG_TROPO)),
                                       lat_rad, lon_rad)
        if self.georef is not None:
            self._convergence_rad = self.georef.grid_convergence_rad(float(xy_m[0]), float(xy_m[1]))

    def _update_passes(self, ref_ecef_m: F64, rot: F64, t_gps_s: float) -> F64:
        """Coarse elevations of all PRNs at the cluster reference; count rising passes."""
        st = self.eph.sv_states(self._prns, t_gps_s - 0.075)
        d = st.pos_ecef_m - ref_ecef_m
        enu = d @ rot.T
        el = np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))
        el = np.where(np.isfinite(el), el, -np.pi / 2)
        above = el > 0.0
        rising = above & ~self._above[self._prns]
        self._pass_index[self._prns[rising]] += 1
        self._above[self._prns] = above
        return np.where(st.healthy, el, -np.pi / 2)

    def epoch(self, t_s: float, vehicles: Mapping[str, VehicleState]) -> dict[str, GnssEpoch]:
        """Synthesize every vehicle's epoch at scenario time ``t_s``."""
        t_gps = self.gps_start_s + float(t_s)
        ids = list(vehicles)
        states = [vehicles[v] for v in ids]
        m = len(states)
        if m == 0:
            return {}
        first = states[0]
        if self._iono is None:
            self._init_fields(first.lat_rad, first.lon_rad, first.xyz_m)
        # Truth at the epoch (velocity extrapolation if the state is not exactly at t_s).
        rx = np.empty((m, 3))
        vel = np.empty((m, 3))
        lat = np.array([s.lat_rad for s in states])
        lon = np.array([s.lon_rad for s in states])
        h = np.empty(m)
        xyz = np.empty((m, 3))
        rots = np.empty((m, 3, 3))
        for i, s in enumerate(states):
            rots[i] = ecef_to_enu_rotation(s.lat_rad, s.lon_rad)
            vel[i] = np.asarray(s.vel_enu_mps, dtype=float) @ rots[i]
            dt = float(t_s) - s.t_s
            rx[i] = np.asarray(s.ecef_m, dtype=float) + vel[i] * dt
            h[i] = s.h_m + s.vel_enu_mps[2] * dt
            xyz[i] = np.asarray(s.xyz_m, dtype=float) + np.asarray(s.vel_enu_mps, dtype=float) * dt

        ref = rx.mean(axis=0)
        el_coarse = self._update_passes(ref, rots[0], t_gps)
        cand = self._prns[el_coarse >= self.config.elevation_mask_rad - _CANDIDATE_MARGIN_RAD]
        k = cand.size
        geoms = self._geometry(t_gps, cand, rx, rots, lat, lon, h) if k else None

        skies: list[Any] = [None] * m
        if self.occlusion is not None and geoms is not None:
            az_grid = geoms["az_rad"] - self._convergence_rad
            if hasattr(self.occlusion, "sky_many"):
                # One batched query for every (vehicle, candidate) ray of the epoch.
                res = self.occlusion.sky_many(xyz, np.repeat(np.arange(m), k), az_grid.reshape(-1),
                                              geoms["el_rad"].reshape(-1))
                skies = [_SkySlice(res, i * k, (i + 1) * k) for i in range(m)]
            else:  # any object with the per-antenna ``sky`` method
                skies = [self.occlusion.sky(xyz[i], az_grid[i], geoms["el_rad"][i]) for i in range(m)]

        out: dict[str, GnssEpoch] = {}
        for i, vid in enumerate(ids):
            rcv = self.receivers.get(vid)
            if rcv is None:
                rcv = self.receivers[vid] = GnssReceiver(vid, self.config, self.seed, float(t_s))
            if geoms is None:
                g = _empty_geometry()
            else:
                g = _SatGeometry(**{key: val[i] for key, val in geoms.items()})
            out[vid] = rcv.measure(float(t_s), g, vel[i], skies[i])
        return out

    def _geometry(
        self, t_gps: float, cand: I64, rx: F64, rots: F64, lat: F64, lon: F64, h: F64
    ) -> dict[str, np.ndarray]:
        """Light-time solution and common errors for all (vehicle, candidate) pairs: arrays (m, k, ...)."""
        m, k = rx.shape[0], cand.size
        prn = np.broadcast_to(cand, (m, k)).reshape(-1)
        rxr = np.repeat(rx, k, axis=0)
        tau = np.full(m * k, 0.075)
        for _ in range(10):
            st = self.eph.sv_states(prn, t_gps - tau)
            pos = rotate_earth(st.pos_ecef_m, OMEGA_E_RADPS * tau)
            tau_new = np.linalg.norm(pos - rxr, axis=-1) / SPEED_OF_LIGHT_MPS
            done = not np.any(np.abs(tau_new - tau) >= _TRANSIT_TOL_S)
            tau = np.where(np.isfinite(tau_new), tau_new, tau)
            if done:
                break
        st = self.eph.sv_states(prn, t_gps - tau)
        ang = OMEGA_E_RADPS * tau
        pos = rotate_earth(st.pos_ecef_m, ang)
        vel_sv = rotate_earth(st.vel_ecef_mps, ang)
        d = pos - rxr
        rng_m = np.linalg.norm(d, axis=-1)
        u = d / rng_m[:, None]
        enu = np.einsum("mij,mkj->mki", rots, d.reshape(m, k, 3)).reshape(-1, 3)
        az = np.arctan2(enu[:, 0], enu[:, 1]) % (2.0 * np.pi)
        el = np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))
        ok = np.isfinite(rng_m) & st.healthy
        el = np.where(ok, el, -np.pi / 2)  # unusable satellites fall below any mask
        pos = np.where(ok[:, None], pos, 0.0)
        vel_sv = np.where(ok[:, None], vel_sv, 0.0)
        rng_m = np.where(ok, rng_m, 1.0)
        u = np.where(ok[:, None], u, 0.0)
        clk = np.where(ok, st.clock_bias_s, 0.0)
        clk_d = np.where(ok, st.clock_drift_sps, 0.0)

        pas = self._pass_index[prn]
        dr = self.satellite_errors.orbit_error_ecef_m(prn, pas, np.where(ok[:, None], pos, 1.0),
                                                      np.where(ok[:, None], vel_sv, 1.0))
        orbit = np.linalg.norm(pos - dr - rxr, axis=-1) - rng_m
        orbit = np.where(ok, orbit, 0.0)
        sv_clk_err = self.satellite_errors.clock_error_m(prn, pas)
        latr, lonr, hr = np.repeat(lat, k), np.repeat(lon, k), np.repeat(h, k)
        el_c = np.clip(el, 1e-3, None)
        iono = self._iono.slant_delay_m(latr, lonr, el_c, az, t_gps)
        tropo = self._tropo.slant_delay_m(latr, lonr, hr, el_c)

        def mk(a: np.ndarray) -> np.ndarray:
            return a.reshape(m, k, *a.shape[1:])

        return {
            "prn": mk(prn.astype(np.int64)),
            "sv_pos_ecef_m": mk(pos),
            "sv_vel_ecef_mps": mk(vel_sv),
            "sv_clock_m": mk(SPEED_OF_LIGHT_MPS * clk),
            "sv_clock_drift_mps": mk(SPEED_OF_LIGHT_MPS * clk_d),
            "range_m": mk(rng_m),
            "los_unit": mk(u),
            "el_rad": mk(el),
            "az_rad": mk(az),
            "orbit_m": mk(orbit),
            "sv_clock_error_m": mk(np.where(ok, sv_clk_err, 0.0)),
            "iono_m": mk(np.where(ok, iono, 0.0)),
            "tropo_m": mk(np.where(ok, tropo, 0.0)),
        }


class _SkySlice:
    """One receiver's rays of a batched sky result (the attributes ``measure`` reads)."""

    def __init__(self, res: Any, lo: int, hi: int):
        self.blocked = res.blocked[lo:hi]
        self.echo_excess_m = res.echo_excess_m[lo:hi]
        self.foliage_loss_db = res.foliage_loss_db[lo:hi]


def _empty_geometry() -> _SatGeometry:
    z = np.zeros(0)
    z3 = np.zeros((0, 3))
    return _SatGeometry(
        prn=np.zeros(0, dtype=np.int64), sv_pos_ecef_m=z3, sv_vel_ecef_mps=z3, sv_clock_m=z, sv_clock_drift_mps=z,
        range_m=z, los_unit=z3, el_rad=z, az_rad=z, orbit_m=z, sv_clock_error_m=z, iono_m=z, tropo_m=z,
    )
