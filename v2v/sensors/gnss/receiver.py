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

Speed: an epoch of the whole cluster is one numpy pass over the (vehicle, candidate
satellite) pairs: one ephemeris evaluation per pair at its previous light time, a linear
light-time correction (:meth:`GnssSynthesizer._geometry`), one batched sky query, and the
tracking/error processes of all receivers at once; only the random draws loop over the
receivers (each from its own streams, in the order it would draw alone).
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from v2v.errors import UserError
from v2v.frames import GeoReference
from v2v.sensors.gnss.atmosphere import IonosphereField, SatelliteErrors, TroposphereField, rac_to_ecef
from v2v.sensors.gnss.clock import ReceiverClock
from v2v.sensors.gnss.ephemeris import OMEGA_E_RADPS, Ephemeris, SvStates, rotate_earth
from v2v.sensors.gnss.errors import (
    GnssErrorConfig,
    cn0_dbhz,
    dll_jitter_m,
    doppler_sigma_mps,
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
# Candidate screen and pass counting are refreshed at this interval: elevations change by
# < 0.01 deg per second, far inside the 2 deg candidate margin.
_COARSE_UPDATE_S = 1.0


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


class GnssReceiver:
    """One vehicle's receiver: its random streams and its two-state clock.

    Created by :class:`GnssSynthesizer`, which keeps the per-satellite tracking states
    (multipath and DLL noise processes, lock, ambiguity) of every receiver in one array
    per quantity (row ``self.row``), so that an epoch of the whole cluster is one numpy pass.
    Each receiver draws only from its own streams, in a fixed order per epoch (phase:
    slips, new ambiguities, phase noise; multipath: code then carrier; noise; Doppler), so
    its numbers do not depend on the other vehicles.
    """

    def __init__(
        self, vehicle_id: str, config: GnssReceiverConfig, seed: np.random.SeedSequence, t0_s: float, row: int = 0
    ):
        self.vehicle_id = vehicle_id
        self.config = config
        self.row = int(row)
        vs = _child_seed(seed, _TAG_VEHICLE, vehicle_key(vehicle_id))
        self.rng_multipath = np.random.default_rng(_child_seed(vs, _COMP_MULTIPATH))
        self.rng_noise = np.random.default_rng(_child_seed(vs, _COMP_NOISE))
        self.rng_phase = np.random.default_rng(_child_seed(vs, _COMP_PHASE))
        self.rng_doppler = np.random.default_rng(_child_seed(vs, _COMP_DOPPLER))
        self.clock = ReceiverClock.start(config.errors.clock, np.random.default_rng(_child_seed(vs, _COMP_CLOCK)), t0_s)


class _TrackingStates:
    """Per (receiver row, PRN slot) tracking states of all receivers, grown on demand."""

    def __init__(self, rows: int = 8):
        self.cap = 0
        self._grow(rows)

    def _grow(self, rows: int) -> None:
        n = _MAX_PRN_SLOTS
        new = {
            "last_t": np.full((rows, n), -np.inf),  # last epoch each PRN was tracked
            "z_mp": np.zeros((rows, n)),  # unit-variance code multipath state
            "z_mp_phase": np.zeros((rows, n)),
            "z_noise": np.zeros((rows, n)),  # unit-variance DLL noise state
            "ambiguity": np.zeros((rows, n), dtype=np.int64),
            "lock_start": np.zeros((rows, n)),
            "los": np.ones((rows, n), dtype=bool),
            "tau_guess": np.full((rows, n), 0.075),  # light time of the last evaluation
            "tau_t": np.full((rows, n), -np.inf),  # epoch of that evaluation
        }
        for key, arr in new.items():
            if self.cap:
                arr[: self.cap] = getattr(self, key)
            setattr(self, key, arr)
        self.cap = rows

    def ensure(self, rows: int) -> None:
        if rows > self.cap:
            self._grow(max(rows, 2 * self.cap))


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
        self._trk = _TrackingStates()
        self._coarse_el: F64 | None = None
        self._coarse_t = -np.inf

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
        """Synthesize every vehicle's epoch at scenario time ``t_s`` (one numpy pass for all)."""
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
        lat = np.array([s.lat_rad for s in states])
        lon = np.array([s.lon_rad for s in states])
        dt = float(t_s) - np.array([s.t_s for s in states])
        vel_enu = np.array([s.vel_enu_mps for s in states], dtype=float).reshape(m, 3)
        sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
        rots = np.empty((m, 3, 3))  # ECEF -> ENU (v2v.frames.ecef_to_enu_rotation, per vehicle)
        rots[:, 0] = np.column_stack([-so, co, np.zeros(m)])
        rots[:, 1] = np.column_stack([-sl * co, -sl * so, cl])
        rots[:, 2] = np.column_stack([cl * co, cl * so, sl])
        vel = np.einsum("mi,mij->mj", vel_enu, rots)
        rx = np.array([s.ecef_m for s in states], dtype=float).reshape(m, 3) + vel * dt[:, None]
        h = np.array([s.h_m for s in states]) + vel_enu[:, 2] * dt
        xyz = np.array([s.xyz_m for s in states], dtype=float).reshape(m, 3) + vel_enu * dt[:, None]

        ref = rx.mean(axis=0)
        if self._coarse_el is None or float(t_s) - self._coarse_t >= _COARSE_UPDATE_S - 1e-9:
            self._coarse_el = self._update_passes(ref, rots[0], t_gps)
            self._coarse_t = float(t_s)
        el_coarse = self._coarse_el
        cand = self._prns[el_coarse >= self.config.elevation_mask_rad - _CANDIDATE_MARGIN_RAD]
        k = cand.size

        rcvs = []
        for vid in ids:
            rcv = self.receivers.get(vid)
            if rcv is None:
                rcv = self.receivers[vid] = GnssReceiver(vid, self.config, self.seed, float(t_s), len(self.receivers))
            rcvs.append(rcv)
        self._trk.ensure(len(self.receivers))
        rows = np.array([r.row for r in rcvs], dtype=np.int64)
        if k == 0:
            for rcv in rcvs:
                rcv.clock.advance_to(float(t_s))
            return {vid: _empty_epoch(float(t_s), vid) for vid in ids}
        geom = self._geometry(float(t_s), cand, rows, rx, rots, lat, lon, h)

        sky = None
        if self.occlusion is not None:
            az_grid = geom["az_rad"] - self._convergence_rad
            if hasattr(self.occlusion, "sky_many"):
                # One batched query for every (vehicle, candidate) ray of the epoch.
                res = self.occlusion.sky_many(
                    xyz, np.repeat(np.arange(m), k), az_grid.reshape(-1), geom["el_rad"].reshape(-1)
                )
                sky = (res.blocked, res.echo_excess_m, res.foliage_loss_db)
            else:  # any object with the per-antenna ``sky`` method
                per = [self.occlusion.sky(xyz[i], az_grid[i], geom["el_rad"][i]) for i in range(m)]
                sky = tuple(np.concatenate([np.asarray(getattr(r, a)) for r in per])
                            for a in ("blocked", "echo_excess_m", "foliage_loss_db"))
        return self._measure(float(t_s), ids, rcvs, rows, cand, geom, vel, sky)

    def _measure(
        self,
        t_s: float,
        ids: list[str],
        rcvs: list[GnssReceiver],
        rows: I64,
        cand: I64,
        geom: dict[str, np.ndarray],
        vel: F64,
        sky: tuple[np.ndarray, np.ndarray, np.ndarray] | None,
    ) -> dict[str, GnssEpoch]:
        """Tracking, error processes and observables of all receivers (see the module docstring).

        Arrays are (m, k) over (vehicle, candidate satellite) until the tracked pairs are
        selected; those are flattened vehicle by vehicle (PRNs ascending within a vehicle),
        so each vehicle's epoch is a contiguous slice.
        """
        cfg = self.config
        err = cfg.errors
        trk = err.tracking
        m, k = len(ids), cand.size
        el_mk = geom["el_rad"]
        if sky is None:
            blocked = np.zeros((m, k), dtype=bool)
            echo = np.full((m, k), np.nan)
            foliage_db = np.zeros((m, k))
        else:
            blocked, echo, foliage_db = (np.asarray(a).reshape(m, k) for a in sky)
            blocked = blocked.astype(bool)
        has_echo = blocked & np.isfinite(echo)
        nlos_mk = has_echo if trk.nlos_enabled else np.zeros((m, k), dtype=bool)
        cn0_mk = cn0_dbhz(el_mk, trk, foliage_db, nlos_mk)
        tracked = (el_mk >= cfg.elevation_mask_rad) & (~blocked | nlos_mk) & (cn0_mk >= trk.track_threshold_dbhz)
        vi, sj = np.nonzero(tracked)  # row-major: grouped by vehicle, PRNs ascending
        counts = tracked.sum(axis=1)
        off = np.concatenate([[0], np.cumsum(counts)])
        r = rows[vi]
        prn = cand[sj]
        el = el_mk[vi, sj]
        cn0 = cn0_mk[vi, sj]
        nlos = nlos_mk[vi, sj]
        n = prn.size
        st = self._trk

        # Lock continuity: a gap (missed epoch), a LOS <-> echo switch or a random slip
        # starts a new arc with a new integer ambiguity.
        gap = t_s - st.last_t[r, prn]
        dt_epoch = 1.0 / cfg.rate_hz
        new_arc = (gap > 1.5 * dt_epoch) | (st.los[r, prn] != ~nlos)
        slips = trk.random_slip_rate_hz > 0.0
        p_slip = 1.0 - np.exp(-trk.random_slip_rate_hz * np.minimum(gap, dt_epoch)) if slips else None
        mp_on, noise_on = err.multipath.enabled, trk.noise_enabled
        amb_new = np.zeros(n, dtype=np.int64)
        w_mp = np.empty(n) if mp_on else None
        w_mpp = np.empty(n) if mp_on else None
        w_n = np.empty(n) if noise_on else None
        w_ph = np.empty(n) if noise_on else None
        w_d = np.empty(n) if noise_on else None
        clock_bias = np.empty(m)
        clock_drift = np.empty(m)
        # Random draws, receiver by receiver from its own streams (same order as one receiver alone).
        for i, rcv in enumerate(rcvs):
            rcv.clock.advance_to(t_s)
            clock_bias[i] = rcv.clock.bias_m
            clock_drift[i] = rcv.clock.drift_mps
            lo, hi = int(off[i]), int(off[i + 1])
            ni = hi - lo
            if ni == 0:
                continue
            if slips:
                new_arc[lo:hi] |= rcv.rng_phase.random(ni) < p_slip[lo:hi]
            na = new_arc[lo:hi]
            c = int(np.count_nonzero(na))
            if c:
                amb_new[lo + np.flatnonzero(na)] = rcv.rng_phase.integers(
                    -trk.ambiguity_max_cycles, trk.ambiguity_max_cycles, size=c, endpoint=True
                )
            if mp_on:
                w_mp[lo:hi] = rcv.rng_multipath.standard_normal(ni)
                w_mpp[lo:hi] = rcv.rng_multipath.standard_normal(ni)
            if noise_on:
                w_n[lo:hi] = rcv.rng_noise.standard_normal(ni)
                w_ph[lo:hi] = rcv.rng_phase.standard_normal(ni)
                w_d[lo:hi] = rcv.rng_doppler.standard_normal(ni)
        if new_arc.any():
            st.ambiguity[r[new_arc], prn[new_arc]] = amb_new[new_arc]
            st.lock_start[r[new_arc], prn[new_arc]] = t_s
        st.los[r, prn] = ~nlos

        # Multipath (code and carrier) and DLL noise: unit Gauss-Markov states, exact steps
        # (errors.gauss_markov_step: z <- phi z + sqrt(1 - phi^2) w, phi = exp(-dt / tau)).
        dt = np.where(np.isfinite(gap), gap, np.inf)
        zeros = np.zeros(n)
        if mp_on and n:
            phi = np.exp(-dt / err.multipath.tau_s)
            q = np.sqrt(1.0 - phi**2)
            z_mp = phi * st.z_mp[r, prn] + q * w_mp
            z_mpp = phi * st.z_mp_phase[r, prn] + q * w_mpp
            st.z_mp[r, prn] = z_mp
            st.z_mp_phase[r, prn] = z_mpp
            sig_mp = multipath_sigma_m(el, err.multipath)
            mp = sig_mp * z_mp
            mp_phase = err.multipath.phase_multipath_ratio * sig_mp * z_mpp
        else:
            mp = mp_phase = zeros
        if noise_on and n:
            phi = np.exp(-dt / trk.dll_correlation_time_s)
            z_n = phi * st.z_noise[r, prn] + np.sqrt(1.0 - phi**2) * w_n
            st.z_noise[r, prn] = z_n
            noise = dll_jitter_m(cn0, trk) * z_n
            noise_phase = pll_jitter_m(cn0, trk) * w_ph
            noise_dopp = doppler_sigma_mps(cn0, trk) * w_d
        else:
            noise = noise_phase = noise_dopp = zeros
        st.last_t[r, prn] = t_s

        def g(key: str) -> np.ndarray:
            return geom[key][vi, sj]

        echo_t = echo[vi, sj]
        nlos_m = np.where(nlos, echo_t, 0.0)  # nlos implies a finite echo (has_echo)
        rho = g("range_m")
        sv_clock_m = g("sv_clock_m")
        errors = {
            "clock": clock_bias[vi],
            "sv_clock": -sv_clock_m,
            "sv_clock_error": -g("sv_clock_error_m"),
            "orbit": g("orbit_m"),
            "iono": g("iono_m"),
            "tropo": g("tropo_m"),
            "multipath": mp,
            "nlos": nlos_m,
            "noise": noise,
        }
        pseudorange = rho + sum(errors[key] for key in ERROR_KEYS)
        phase_m = pseudorange - errors["iono"] * 2.0 - errors["multipath"] - errors["noise"] + mp_phase + noise_phase
        amb = st.ambiguity[r, prn]
        carrier = phase_m / GPS_L1_WAVELENGTH_M + amb
        e = g("los_unit")
        # Light-time rate: the satellite position in the reception frame is R3(w tau) x_sv(t - tau);
        # with tau_dot = rho_dot / c its rate is R3 v_sv (1 - tau_dot) + w tau_dot (y, -x, 0).
        p_sv = g("sv_pos_ecef_m")
        v_sv = g("sv_vel_ecef_mps")
        e_vsv = np.einsum("ij,ij->i", e, v_sv)
        e_rot = OMEGA_E_RADPS * (e[:, 0] * p_sv[:, 1] - e[:, 1] * p_sv[:, 0])
        e_vrx = np.einsum("ij,ij->i", e, vel[vi])
        range_rate = (e_vsv - e_vrx) / (1.0 + (e_vsv - e_rot) / SPEED_OF_LIGHT_MPS)
        doppler = range_rate + clock_drift[vi] - g("sv_clock_drift_mps") + noise_dopp
        lock_time = t_s - st.lock_start[r, prn]
        az = g("az_rad")
        los = ~nlos

        out: dict[str, GnssEpoch] = {}
        for i, vid in enumerate(ids):
            sl = slice(int(off[i]), int(off[i + 1]))
            out[vid] = GnssEpoch(
                t_s=t_s,
                vehicle_id=vid,
                prn=prn[sl],
                pseudorange_m=pseudorange[sl],
                doppler_mps=doppler[sl],
                carrier_cycles=carrier[sl],
                lock_time_s=lock_time[sl],
                cn0_dbhz=cn0[sl],
                sv_pos_ecef_m=p_sv[sl],
                sv_vel_ecef_mps=v_sv[sl],
                sv_clock_m=sv_clock_m[sl],
                elevation_rad=el[sl],
                azimuth_rad=az[sl],
                los=los[sl],
                true_range_m=rho[sl],
                ambiguity_cycles=amb[sl],
                errors_m={key: val[sl] for key, val in errors.items()},
            )
        return out

    def _geometry(
        self, t_s: float, cand: I64, rows: I64, rx: F64, rots: F64, lat: F64, lon: F64, h: F64
    ) -> dict[str, np.ndarray]:
        """Light-time solution and common errors for all (vehicle, candidate) pairs: arrays (m, k, ...).

        One ephemeris evaluation per pair and epoch, at ``t - guess`` where ``guess`` is the
        pair's light time of the previous epoch (it changes by < 3e-7 s in 0.1 s); a pair
        without one (new receiver, rising satellite, gap) is evaluated at ``t - 0.075 s`` and
        again at its light time from that. Absolute GPS seconds (~1.3e9) resolve time only to
        2.4e-7 s (~1 mm of satellite motion), so the evaluation time is split exactly
        (Knuth's TwoSum) as ``t_eval + t_err = gps_start + (t_s - guess)`` and the state is
        moved by ``t_err`` with its rates. The light time ``tau`` then solves
        ``tau = |R3(w tau) x(t - tau) - x_rx| / c`` with ``x(t - tau) = x0 - v0 dtau``,
        ``dtau = tau - guess`` (and the clock ``b0 - b0_dot dtau``): with ``|dtau| < 1e-6 s``
        the neglected ``|a| dtau^2 / 2`` (``|a| < 1 m/s^2`` in ECEF) is below 1e-12 m and the
        velocity error ``|a| dtau`` below 1e-6 m/s. Each pair depends only on its own
        history: adding a vehicle changes no other vehicle's numbers.
        """
        m, k = rx.shape[0], cand.size
        trk = self._trk
        prn = np.broadcast_to(cand, (m, k))
        rr = np.broadcast_to(rows[:, None], (m, k))
        warm = trk.tau_t[rr, prn] >= t_s - 1.5 / self.config.rate_hz
        guess = np.where(warm, trk.tau_guess[rr, prn], 0.075)
        rxb = rx[:, None, :]
        p0 = np.empty((m, k, 3))
        v0 = np.empty((m, k, 3))
        b0 = np.empty((m, k))
        d0 = np.empty((m, k))
        healthy = np.empty((m, k), dtype=bool)
        tau = np.empty((m, k))
        todo = np.ones((m, k), dtype=bool)
        for _ in range(3):
            vi, sj = np.nonzero(todo)
            g = guess[vi, sj]
            t_eval, t_err = _two_sum(self.gps_start_s, t_s - g)
            st = self.eph.sv_states(cand[sj], t_eval)
            p0[vi, sj] = st.pos_ecef_m + st.vel_ecef_mps * t_err[:, None]
            v0[vi, sj] = st.vel_ecef_mps
            b0[vi, sj] = st.clock_bias_s + st.clock_drift_sps * t_err
            d0[vi, sj] = st.clock_drift_sps
            healthy[vi, sj] = st.healthy
            tau_i = _light_time(p0[vi, sj], v0[vi, sj], g, g, rx[vi])
            tau[vi, sj] = tau_i
            # Guess within 1 us of the light time (see above); else evaluate once more there.
            far = np.isfinite(tau_i) & (np.abs(tau_i - g) > 1e-6)
            if not far.any():
                break
            todo[:] = False
            todo[vi[far], sj[far]] = True
            guess[vi[far], sj[far]] = tau_i[far]
        fin = np.isfinite(tau)
        trk.tau_guess[rr[fin], prn[fin]] = tau[fin]
        trk.tau_t[rr[fin], prn[fin]] = t_s
        st = SvStates(prn=prn, pos_ecef_m=p0, vel_ecef_mps=v0, clock_bias_s=b0, clock_drift_sps=d0, healthy=healthy)
        tau0 = guess
        dtau = tau - tau0
        ang = OMEGA_E_RADPS * tau
        pos = rotate_earth(p0 - v0 * dtau[..., None], ang)
        vel_sv = rotate_earth(v0, ang)
        clk = st.clock_bias_s - st.clock_drift_sps * dtau
        clk_d = st.clock_drift_sps
        d = pos - rxb
        rng_m = np.linalg.norm(d, axis=-1)
        u = d / rng_m[..., None]
        enu = np.einsum("mij,mkj->mki", rots, d)
        az = np.arctan2(enu[..., 0], enu[..., 1]) % (2.0 * np.pi)
        el = np.arctan2(enu[..., 2], np.hypot(enu[..., 0], enu[..., 1]))
        ok = np.isfinite(rng_m) & st.healthy
        el = np.where(ok, el, -np.pi / 2)  # unusable satellites fall below any mask
        pos = np.where(ok[..., None], pos, 0.0)
        vel_sv = np.where(ok[..., None], vel_sv, 0.0)
        rng_m = np.where(ok, rng_m, 1.0)
        u = np.where(ok[..., None], u, 0.0)
        clk = np.where(ok, clk, 0.0)
        clk_d = np.where(ok, clk_d, 0.0)

        # Satellite orbit and clock errors: per satellite (and pass), common to all receivers.
        pas = self._pass_index[cand]
        rac = self.satellite_errors.orbit_error_rac_m(cand, pas)  # (k, 3)
        okv = ok[..., None]
        dr = rac_to_ecef(rac, np.where(okv, pos, 1.0), np.where(okv, vel_sv, 1.0))  # ECEF at reception
        orbit = np.linalg.norm(pos - dr - rxb, axis=-1) - rng_m
        orbit = np.where(ok, orbit, 0.0)
        sv_clk_err = np.broadcast_to(self.satellite_errors.clock_error_m(cand, pas), (m, k))
        latr, lonr, hr = np.repeat(lat, k), np.repeat(lon, k), np.repeat(h, k)
        el_c = np.clip(el, 1e-3, None).reshape(-1)
        iono = self._iono.slant_delay_m(latr, lonr, el_c, az.reshape(-1), self.gps_start_s + t_s).reshape(m, k)
        tropo = self._tropo.slant_delay_m(latr, lonr, hr, el_c).reshape(m, k)

        return {
            "sv_pos_ecef_m": pos,
            "sv_vel_ecef_mps": vel_sv,
            "sv_clock_m": SPEED_OF_LIGHT_MPS * clk,
            "sv_clock_drift_mps": SPEED_OF_LIGHT_MPS * clk_d,
            "range_m": rng_m,
            "los_unit": u,
            "el_rad": el,
            "az_rad": az,
            "orbit_m": orbit,
            "sv_clock_error_m": np.where(ok, sv_clk_err, 0.0),
            "iono_m": np.where(ok, iono, 0.0),
            "tropo_m": np.where(ok, tropo, 0.0),
        }


def _empty_epoch(t_s: float, vehicle_id: str) -> GnssEpoch:
    """An epoch without satellites (no candidate above the mask)."""
    z = np.zeros(0)
    z3 = np.zeros((0, 3))
    return GnssEpoch(
        t_s=t_s, vehicle_id=vehicle_id, prn=np.zeros(0, dtype=np.int64), pseudorange_m=z, doppler_mps=z,
        carrier_cycles=z, lock_time_s=z, cn0_dbhz=z, sv_pos_ecef_m=z3, sv_vel_ecef_mps=z3, sv_clock_m=z,
        elevation_rad=z, azimuth_rad=z, los=np.zeros(0, dtype=bool), true_range_m=z,
        ambiguity_cycles=np.zeros(0, dtype=np.int64), errors_m={key: z for key in ERROR_KEYS},
    )


def _two_sum(a: float, b: F64) -> tuple[F64, F64]:
    """``s + e == a + b`` exactly, ``s = fl(a + b)`` (Knuth's TwoSum, branch-free)."""
    s = a + b
    bp = s - a
    e = (a - (s - bp)) + (b - bp)
    return s, e


def _light_time(p0: F64, v0: F64, t0_back_s: F64, tau_start_s: F64, rx_ecef_m: F64) -> F64:
    """Light time ``tau`` from satellites with state ``(p0, v0)`` at ``t - t0_back`` to receivers.

    Fixed point of ``tau = |R3(w tau) (p0 - v0 (tau - t0_back)) - x_rx| / c`` (contraction
    ``|v| / c ~ 1e-5``), iterated until ``|d tau| < 1e-12 s``. Broadcasts over leading axes
    (``p0``, ``v0``: (k, 3); ``tau_start_s``: (k,) or (m, k); ``rx_ecef_m``: (3,) or (m, 1, 3)).
    Satellites without a valid (finite) state give NaN.
    """
    tau = np.array(tau_start_s, dtype=float)
    tau_new = tau
    for _ in range(10):
        p = rotate_earth(p0 - v0 * (tau - t0_back_s)[..., None], OMEGA_E_RADPS * tau)
        tau_new = np.linalg.norm(p - rx_ecef_m, axis=-1) / SPEED_OF_LIGHT_MPS
        fin = np.isfinite(tau_new)
        done = not np.any(np.abs(tau_new[fin] - tau[fin]) >= _TRANSIT_TOL_S)
        tau = np.where(fin, tau_new, tau)
        if done:
            break
    return np.where(np.isfinite(tau_new), tau, np.nan)
