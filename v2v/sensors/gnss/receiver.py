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
by component: clock, multipath, DLL noise, carrier-phase noise, Doppler noise, new
ambiguities, random slips), so adding a vehicle does not change any other vehicle's noise.
Each stream draws one kind of number only (standard normals; uniforms for slips and
ambiguities), pre-drawn in blocks per receiver (numpy's Generator gives the same sequence
drawn in pieces or at once, so block size and refill times do not change any number).

Speed (issue 3: synthesis well below the filter's time): an epoch of the whole cluster is
three compiled (numba, cached) passes over the (vehicle, candidate satellite) pairs:
truth/rotations, geometry (satellite states interpolated between ephemeris evaluations on a
5 s grid, light time, az/el, orbit, ionosphere, troposphere: :meth:`GnssSynthesizer._geometry`),
and tracking/errors/observables of all receivers (:func:`_measure_kernel`), plus one batched
sky query; Python only builds the :class:`GnssEpoch` records.
"""

from __future__ import annotations

import zlib
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from itertools import chain
from typing import Any

import numpy as np
from numba import njit
from numpy.typing import NDArray

from v2v.errors import UserError
from v2v.frames import GeoReference
from v2v.sensors.gnss.atmosphere import (
    IonosphereField,
    SatelliteErrors,
    TroposphereField,
    iono_slant_delay_core_m,
    tropo_zenith_scalar_m,
)
from v2v.sensors.gnss.clock import ClockJump, ReceiverClock, _process_noise_cholesky
from v2v.sensors.gnss.ephemeris import OMEGA_E_RADPS, Ephemeris
from v2v.sensors.gnss.errors import GPS_CA_CHIP_S, GnssErrorConfig
from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M, SPEED_OF_LIGHT_MPS, GnssEpoch
from v2v.traffic.snapshot import TrafficStep, VehicleState

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]

ERROR_KEYS = ("clock", "sv_clock", "sv_clock_error", "orbit", "iono", "tropo", "multipath", "nlos", "noise")

# SeedSequence spawn-key tags (stable: changing them changes every run's numbers).
_TAG_IONO, _TAG_TROPO, _TAG_SAT, _TAG_VEHICLE = 1, 2, 3, 100
_COMP_CLOCK, _COMP_MULTIPATH, _COMP_NOISE, _COMP_PHASE, _COMP_DOPPLER, _COMP_AMBIGUITY, _COMP_SLIP = 1, 2, 3, 4, 5, 6, 7
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
    (multipath and DLL noise processes, lock, ambiguity), the clock state and the pre-drawn
    random numbers of every receiver in one array per quantity (row ``self.row``), so that an
    epoch of the whole cluster is one compiled pass. ``clock.state`` is a view of that row
    (``clock.t_s`` is not kept current; ``clock.jumps`` is). Each receiver draws only from its
    own streams, in a fixed order per epoch (per tracked satellite: slip uniform, then a new
    ambiguity's uniform; multipath: all code then all carrier; DLL noise; phase noise;
    Doppler), so its numbers do not depend on the other vehicles.
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
        self.rng_ambiguity = np.random.default_rng(_child_seed(vs, _COMP_AMBIGUITY))
        self.rng_slip = np.random.default_rng(_child_seed(vs, _COMP_SLIP))
        self.clock = ReceiverClock.start(config.errors.clock, np.random.default_rng(_child_seed(vs, _COMP_CLOCK)), t0_s)


class _TrackingStates:
    """Per (receiver row, PRN slot) tracking states and per-row clocks of all receivers, grown on demand."""

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
            "clock": np.zeros((rows, 2)),  # receiver clock (bias m, drift m/s)
            "clock_t": np.zeros(rows),  # time of that clock state
            # Pre-drawn random numbers per (stream, receiver row) and the next unused index.
            "draws": np.zeros((_N_STREAMS, rows, _DRAW_BLOCK)),
            "draw_pos": np.full((_N_STREAMS, rows), _DRAW_BLOCK, dtype=np.int64),
        }
        for key, arr in new.items():
            if self.cap:
                if key in ("draws", "draw_pos"):
                    arr[:, : self.cap] = getattr(self, key)
                else:
                    arr[: self.cap] = getattr(self, key)
            setattr(self, key, arr)
        self.cap = rows

    def ensure(self, rows: int) -> None:
        if rows > self.cap:
            self._grow(max(rows, 2 * self.cap))


# Pre-drawn random numbers: one block per (stream, receiver), refilled from the receiver's own
# Generator when fewer than an epoch's worst case remain. Each stream draws one kind of number
# only, and numpy's Generator gives the same sequence for standard_normal(a) then
# standard_normal(b) as for standard_normal(a + b) (likewise random()): a receiver's numbers
# do not depend on the block size or on when a block is refilled (which depends on the
# cluster's candidate satellites), only on how many it consumed.
_S_CLOCK, _S_MULTIPATH, _S_NOISE, _S_DOPPLER, _S_PHASE = 0, 1, 2, 3, 4  # N(0, 1)
_S_SLIP, _S_AMBIGUITY = 5, 6  # U[0, 1)
_N_STREAMS = 7
_DRAW_BLOCK = 2048
# Satellite states are interpolated (cubic Hermite in position/velocity and clock/drift)
# between ephemeris evaluations on a fixed GPS-time grid of this step (see _geometry).
_NODE_STEP_S = 5.0
_TAU_MIN_S, _TAU_MAX_S = 0.060, 0.100  # light-time bounds of ground receivers (67-86 ms)
# Columns of the geometry array (m, k, _G_N).
_G_POS, _G_VEL, _G_CLK, _G_CLKD, _G_RANGE, _G_U = 0, 3, 6, 7, 8, 9
_G_EL, _G_AZ, _G_ORBIT, _G_SVCLKERR, _G_IONO, _G_TROPO, _G_N = 12, 13, 14, 15, 16, 17, 18
# Rows of the per-epoch float output of _observe_kernel (n tracked pairs each).
_O_PR, _O_DOPP, _O_CARR, _O_LOCK, _O_CN0, _O_EL, _O_AZ, _O_RHO, _O_SVCLK = range(9)
_O_ERR = 9  # then one row per ERROR_KEYS entry
_O_N = _O_ERR + len(ERROR_KEYS)
assert ERROR_KEYS == ("clock", "sv_clock", "sv_clock_error", "orbit", "iono", "tropo", "multipath", "nlos", "noise")
# Epochs are built by filling a new GnssEpoch's __dict__ (what its generated __init__ does, field
# by field through object.__setattr__ because it is frozen): valid while GnssEpoch is a plain
# dataclass with exactly these fields, no __post_init__ and no slots; otherwise the constructor.
_FAST_EPOCH = (
    {f.name for f in fields(GnssEpoch)} == {
        "t_s", "vehicle_id", "prn", "pseudorange_m", "doppler_mps", "carrier_cycles", "lock_time_s", "cn0_dbhz",
        "sv_pos_ecef_m", "sv_vel_ecef_mps", "sv_clock_m", "elevation_rad", "azimuth_rad", "los", "true_range_m",
        "ambiguity_cycles", "errors_m"}
    and not hasattr(GnssEpoch, "__post_init__")
    and not hasattr(GnssEpoch, "__slots__")
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
        self._trk = _TrackingStates()
        self._coarse_el: F64 | None = None
        self._coarse_t = -np.inf
        self._nodes: dict[int, tuple[float, F64, F64, F64, F64, np.ndarray]] = {}
        self._sat_rac = np.zeros((self._prns.size, 3))  # orbit error of each PRN's current pass
        self._sat_clk = np.zeros(self._prns.size)  # clock error of each PRN's current pass
        self._dt_epoch = 1.0 / config.rate_hz
        self._stacked: tuple[int, tuple] | None = None
        self._last_ids: list[str] | None = None
        self._last_rcvs: tuple[list[GnssReceiver], I64] = ([], np.zeros(0, dtype=np.int64))
        self._last_t_s = -np.inf

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

    def _node(self, i: int) -> tuple[float, F64, F64, F64, F64, np.ndarray]:
        """Ephemeris states of every PRN at grid node ``i`` (GPS time ``i * _NODE_STEP_S``, clipped
        into the source's validity), as ``(t - gps_start, pos, vel, clock, drift, ok)``."""
        node = self._nodes.get(i)
        if node is None:
            t0, t1 = self.eph.validity()
            t = min(max(i * _NODE_STEP_S, t0), t1)
            st = self.eph.sv_states(self._prns, t)
            ok = st.healthy & np.all(np.isfinite(st.pos_ecef_m), axis=1) & np.isfinite(st.clock_bias_s)
            z = ~ok
            pos, vel = np.where(z[:, None], 0.0, st.pos_ecef_m), np.where(z[:, None], 0.0, st.vel_ecef_mps)
            clk, drift = np.where(z, 0.0, st.clock_bias_s), np.where(z, 0.0, st.clock_drift_sps)
            node = (t - self.gps_start_s, pos, vel, clk, drift, ok)
            self._nodes[i] = node
            for old in [j for j in self._nodes if j < i - 4]:
                del self._nodes[old]
        return node

    def _node_arrays(self, t_s: float) -> tuple[F64, F64, F64, F64, F64, np.ndarray]:
        """The three grid nodes around every transmit time of the epoch ``t_s`` (light times in
        ``[_TAU_MIN_S, _TAU_MAX_S]``), stacked: node_t (3,), pos/vel (3, P, 3), clock/drift/ok (3, P)."""
        i0 = int(np.floor((self.gps_start_s + (t_s - _TAU_MAX_S)) / _NODE_STEP_S))
        if self._stacked is None or self._stacked[0] != i0:
            nodes = [self._node(i) for i in (i0, i0 + 1, i0 + 2)]
            self._stacked = (i0, tuple(np.stack([nd[c] for nd in nodes]) if c else np.array([nd[0] for nd in nodes])
                                       for c in range(6)))
        return self._stacked[1]

    def _update_passes(self, ref_ecef_m: F64, rot: F64, t_s: float, nodes: tuple) -> F64:
        """Coarse elevations of all PRNs at the cluster reference; count rising passes."""
        node_t, npos, nvel, nclk, ndrift, nok = nodes
        pos = _hermite_all(t_s - 0.075, node_t, npos, nvel)
        enu = (pos - ref_ecef_m) @ rot.T
        el = np.arctan2(enu[:, 2], np.hypot(enu[:, 0], enu[:, 1]))
        ok = nok.all(axis=0)
        el = np.where(ok & np.isfinite(el), el, -np.pi / 2)
        above = el > 0.0
        rising = above & ~self._above[self._prns]
        self._pass_index[self._prns[rising]] += 1
        self._above[self._prns] = above
        if rising.any() or not self._sat_clk.any():
            pas = self._pass_index[self._prns]
            self._sat_rac = self.satellite_errors.orbit_error_rac_m(self._prns, pas)
            self._sat_clk = self.satellite_errors.clock_error_m(self._prns, pas)
        return el

    def epoch(self, t_s: float, vehicles: Mapping[str, VehicleState]) -> dict[str, GnssEpoch]:
        """Synthesize every vehicle's epoch at scenario time ``t_s`` (one compiled pass for all)."""
        t_s = float(t_s)
        ids = list(vehicles)
        states = list(vehicles.values())
        m = len(states)
        if m == 0:
            return {}
        first = states[0]
        if self._iono is None:
            self._init_fields(first.lat_rad, first.lon_rad, first.xyz_m)
        # Truth at the epoch (velocity extrapolation if the state is not exactly at t_s).
        scal = np.fromiter(chain.from_iterable((s.lat_rad, s.lon_rad, s.h_m, s.t_s) for s in states), float,
                           4 * m).reshape(m, 4)
        vec = np.concatenate([x for s in states for x in (s.vel_enu_mps, s.ecef_m, s.xyz_m)]).reshape(m, 9)
        lat, lon, h, rx, rots, vel, xyz = _truth_kernel(t_s, scal, vec)

        if ids == self._last_ids:  # same vehicles as the previous epoch (the usual case)
            rcvs, rows = self._last_rcvs
        else:
            rcvs = []
            for vid in ids:
                rcv = self.receivers.get(vid)
                if rcv is None:
                    rcv = self._new_receiver(vid, t_s)
                rcvs.append(rcv)
            rows = np.array([r.row for r in rcvs], dtype=np.int64)
            self._last_ids, self._last_rcvs = ids, (rcvs, rows)
        if t_s < self._last_t_s - 1e-9:
            raise ValueError(f"GNSS epochs must not go back in time ({self._last_t_s} -> {t_s} s)")
        self._last_t_s = t_s

        nodes = self._node_arrays(t_s)
        if self._coarse_el is None or t_s - self._coarse_t >= _COARSE_UPDATE_S - 1e-9:
            self._coarse_el = self._update_passes(rx.mean(axis=0), rots[0], t_s, nodes)
            self._coarse_t = t_s
        slot = np.flatnonzero(self._coarse_el >= self.config.elevation_mask_rad - _CANDIDATE_MARGIN_RAD)
        cand = self._prns[slot]
        k = cand.size
        if k == 0:
            self._step_clocks(t_s, rows, rcvs)
            return {vid: _empty_epoch(t_s, vid) for vid in ids}
        geom = self._geometry(t_s, slot, nodes, rx, rots, lat, lon, h)

        sky = None
        el_mk = geom[..., _G_EL]
        if self.occlusion is not None:
            az_grid = geom[..., _G_AZ] - self._convergence_rad
            if hasattr(self.occlusion, "sky_many"):
                # One batched query for every (vehicle, candidate) ray of the epoch.
                res = self.occlusion.sky_many(xyz, np.repeat(np.arange(m), k), az_grid.reshape(-1), el_mk.reshape(-1))
                sky = (res.blocked, res.echo_excess_m, res.foliage_loss_db)
            else:  # any object with the per-antenna ``sky`` method
                per = [self.occlusion.sky(xyz[i], az_grid[i], el_mk[i]) for i in range(m)]
                sky = tuple(np.concatenate([np.asarray(getattr(r, a)) for r in per])
                            for a in ("blocked", "echo_excess_m", "foliage_loss_db"))
        return self._measure(t_s, ids, rcvs, rows, cand, geom, vel, sky)

    def _new_receiver(self, vid: str, t_s: float) -> GnssReceiver:
        row = len(self.receivers)
        rcv = self.receivers[vid] = GnssReceiver(vid, self.config, self.seed, t_s, row)
        trk = self._trk
        if row >= trk.cap:
            trk.ensure(row + 1)
            for r in self.receivers.values():  # the clocks' states are views into the grown arrays
                trk.clock[r.row] = r.clock.state
                r.clock.state = trk.clock[r.row]
        trk.clock[row] = rcv.clock.state
        rcv.clock.state = trk.clock[row]
        trk.clock_t[row] = t_s
        trk.draw_pos[:, row] = _DRAW_BLOCK
        return rcv

    def _refill(self, rows: I64, rcvs: list[GnssReceiver], need: I64) -> None:
        """Make sure every receiver has ``need[s]`` unused pre-drawn numbers in stream ``s``."""
        trk = self._trk
        low = trk.draw_pos[:, rows] + need[:, None] > _DRAW_BLOCK
        if not low.any():
            return
        for s, i in zip(*np.nonzero(low), strict=True):
            rcv, r = rcvs[i], rows[i]
            p = int(trk.draw_pos[s, r])
            left = _DRAW_BLOCK - p
            buf = trk.draws[s, r]
            buf[:left] = buf[p:].copy()
            if s >= _S_SLIP:
                buf[left:] = (rcv.rng_slip if s == _S_SLIP else rcv.rng_ambiguity).random(_DRAW_BLOCK - left)
            else:
                rng = (rcv.clock.rng, rcv.rng_multipath, rcv.rng_noise, rcv.rng_doppler, rcv.rng_phase)[s]
                buf[left:] = rng.standard_normal(_DRAW_BLOCK - left)
            trk.draw_pos[s, r] = 0

    def _clock_factors(self, t_s: float, rows: I64) -> tuple[F64, F64]:
        """Per receiver: step ``dt`` and the Cholesky factors ``(l11, l21, l22)`` of its clock noise."""
        trk = self._trk
        dt = t_s - trk.clock_t[rows]
        fac = np.zeros((rows.size, 3))
        ccfg = self.config.errors.clock
        if ccfg.enabled:
            d0 = float(dt[0])
            for d in [d0] if (dt == d0).all() else np.unique(dt).tolist():
                if d > 0.0:
                    fac[dt == d] = _process_noise_cholesky(ccfg.oscillator, d)
        return dt, fac

    def _step_clocks(self, t_s: float, rows: I64, rcvs: list[GnssReceiver]) -> None:
        """Advance the clocks of ``rcvs`` (rows ``rows``) to ``t_s`` (epochs without candidate satellites)."""
        need = np.array([2, 0, 0, 0, 0, 0, 0])
        self._refill(rows, rcvs, need)
        dt, fac = self._clock_factors(t_s, rows)
        jumps = np.zeros(rows.size)
        ccfg = self.config.errors.clock
        thr = -1.0 if ccfg.ms_jump_threshold_s is None else ccfg.ms_jump_threshold_s * SPEED_OF_LIGHT_MPS
        trk = self._trk
        _clock_kernel(rows, dt, fac, ccfg.enabled, thr, trk.clock, trk.clock_t, t_s, trk.draws, trk.draw_pos, jumps)
        self._log_jumps(t_s, rcvs, jumps)

    @staticmethod
    def _log_jumps(t_s: float, rcvs: list[GnssReceiver], jumps: F64) -> None:
        for i in np.flatnonzero(jumps):
            rcvs[i].clock.jumps.append(ClockJump(t_s=t_s, jump_m=float(jumps[i])))
        for rcv in rcvs:
            rcv.clock.t_s = t_s

    def _measure(
        self,
        t_s: float,
        ids: list[str],
        rcvs: list[GnssReceiver],
        rows: I64,
        cand: I64,
        geom: F64,
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
        st = self._trk
        m, k = len(ids), cand.size
        if sky is None:
            blocked = np.zeros((m, k), dtype=bool)
            echo = np.full((m, k), np.nan)
            foliage_db = np.zeros((m, k))
        else:
            blocked, echo, foliage_db = (np.asarray(a, dtype=d).reshape(m, k) for a, d in zip(sky, (bool, float, float),
                                                                                                strict=True))
        slips = trk.random_slip_rate_hz > 0.0
        mp_on, noise_on = err.multipath.enabled, trk.noise_enabled
        need = np.array([2, 2 * k if mp_on else 0, k if noise_on else 0, k if noise_on else 0, k if noise_on else 0,
                         k if slips else 0, k])
        self._refill(rows, rcvs, need)
        dt_clk, fac = self._clock_factors(t_s, rows)
        ccfg = err.clock
        thr = -1.0 if ccfg.ms_jump_threshold_s is None else ccfg.ms_jump_threshold_s * SPEED_OF_LIGHT_MPS
        jumps = np.zeros(m)
        _clock_kernel(rows, dt_clk, fac, ccfg.enabled, thr, st.clock, st.clock_t, t_s, st.draws, st.draw_pos, jumps)
        if ccfg.ms_jump_threshold_s is not None:
            self._log_jumps(t_s, rcvs, jumps)

        cap = m * k
        sj = np.empty(cap, dtype=np.int64)
        out_f = np.empty((_O_N, cap))
        sv_pos = np.empty((cap, 3))
        sv_vel = np.empty((cap, 3))
        amb = np.empty(cap, dtype=np.int64)
        los = np.empty(cap, dtype=np.bool_)
        off = np.zeros(m + 1, dtype=np.int64)
        mpc = err.multipath
        n = _measure_kernel(
            t_s, geom, blocked, echo, foliage_db, rows, cand, vel, cfg.elevation_mask_rad, trk.cn0_zenith_dbhz,
            trk.cn0_horizon_dbhz, trk.foliage_enabled, trk.foliage_max_db, trk.nlos_enabled, trk.echo_loss_db,
            trk.track_threshold_dbhz, self._dt_epoch, trk.random_slip_rate_hz, mp_on, mpc.tau_s, mpc.sigma_a_m,
            mpc.sigma_b_m, mpc.el0_rad, mpc.phase_multipath_ratio, noise_on, trk.dll_correlation_time_s,
            trk.dll_spacing_chips, trk.dll_bandwidth_hz, trk.predetection_s, trk.pll_bandwidth_hz,
            trk.doppler_sigma_mps_at_45dbhz, st.clock, st.z_mp, st.z_mp_phase, st.z_noise, st.ambiguity,
            trk.ambiguity_max_cycles, st.lock_start, st.los, st.last_t, st.draws, st.draw_pos, sj, out_f, sv_pos,
            sv_vel, amb, los, off,
        )
        prn = cand[sj[:n]]

        out: dict[str, GnssEpoch] = {}
        o = off.tolist()
        new = object.__new__
        for i, vid in enumerate(ids):
            lo, hi = o[i], o[i + 1]
            f = list(out_f[:, lo:hi])
            # GnssEpoch(**fields) without the frozen dataclass's per-field object.__setattr__
            # (~4 us of the ~15 us budget per receiver-epoch); see _FAST_EPOCH.
            kw = {
                "t_s": t_s, "vehicle_id": vid, "prn": prn[lo:hi], "pseudorange_m": f[_O_PR],
                "doppler_mps": f[_O_DOPP], "carrier_cycles": f[_O_CARR], "lock_time_s": f[_O_LOCK],
                "cn0_dbhz": f[_O_CN0], "sv_pos_ecef_m": sv_pos[lo:hi], "sv_vel_ecef_mps": sv_vel[lo:hi],
                "sv_clock_m": f[_O_SVCLK], "elevation_rad": f[_O_EL], "azimuth_rad": f[_O_AZ], "los": los[lo:hi],
                "true_range_m": f[_O_RHO], "ambiguity_cycles": amb[lo:hi],
                "errors_m": {"clock": f[9], "sv_clock": f[10], "sv_clock_error": f[11], "orbit": f[12],
                             "iono": f[13], "tropo": f[14], "multipath": f[15], "nlos": f[16], "noise": f[17]},
            }
            if _FAST_EPOCH:
                ep = new(GnssEpoch)
                ep.__dict__.update(kw)
            else:
                ep = GnssEpoch(**kw)
            out[vid] = ep
        return out

    def _geometry(
        self, t_s: float, slot: I64, nodes: tuple, rx: F64, rots: F64, lat: F64, lon: F64, h: F64
    ) -> F64:
        """Light-time solution and common errors for all (vehicle, candidate) pairs: array (m, k, _G_N).

        Satellite states come from ephemeris evaluations on a fixed grid of GPS times
        (every ``_NODE_STEP_S``, shared by all receivers and epochs), interpolated to each
        pair's transmit time by cubic Hermite interpolation of position with velocity (and of
        clock bias with drift). Its error is ``h^4 |x''''| / 384`` (``h`` the node step,
        ``|x''''| ~ r n^4 ~ 1.3e-8 m/s^4`` for a GPS orbit, ``n = 1.46e-4 rad/s``): ~2e-8 m
        at ``h = 5 s``, and ~1e-8 m/s in velocity (tests/test_gnss_kernels.py checks it
        against the direct IS-GPS-200 evaluation). Times are local (``t - gps_start``,
        ~1e3 s) so they resolve 1e-13 s, not the 2.4e-7 s of absolute GPS seconds. The
        light time ``tau`` solves ``tau = |R3(w tau) x(t - tau) - x_rx| / c`` (fixed point,
        ``|d tau| < 1e-12 s``). A broadcast-record change inside a node interval is blended
        smoothly over that interval (the same for every receiver; the filter is given the
        same interpolated orbit, so the measurements stay consistent). Each pair depends only
        on the grid and its own receiver: adding a vehicle changes no other vehicle's numbers.
        """
        m, k = rx.shape[0], slot.size
        node_t, npos, nvel, nclk, ndrift, nok = nodes
        io, tr = self.config.errors.iono, self.config.errors.tropo
        fi, ft = self._iono, self._tropo
        out = np.empty((m, k, _G_N))
        _geometry_kernel(
            t_s, self.gps_start_s + t_s, self.config.elevation_mask_rad, node_t, npos, nvel, nclk, ndrift, nok, slot,
            rx, rots, lat, lon, h,
            self._sat_rac[slot], self._sat_clk[slot],
            io.enabled, io.klobuchar_scale, np.asarray(io.klobuchar_alpha, dtype=float),
            np.asarray(io.klobuchar_beta, dtype=float), io.shell_height_m, fi.ref_lat_rad, fi.ref_lon_rad, fi.k_en,
            fi.omega_radps, fi.phase_rad, fi.amp_m,
            tr.enabled, tr.temperature_sea_level_c, tr.relative_humidity, ft.zenith_residual_m, ft.gradient_en[0],
            ft.gradient_en[1], ft.ref_lat_rad, ft.ref_lon_rad, out,
        )
        return out


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


def _hermite_all(x: float, node_t: F64, npos: F64, nvel: F64) -> F64:
    """Positions (P, 3) of every PRN at local time ``x`` from the node states (cubic Hermite)."""
    j = 0 if x < node_t[1] else 1
    hh = node_t[j + 1] - node_t[j]
    s = (x - node_t[j]) / hh if hh > 0 else 0.0
    h00, h10, h01, h11 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s, -2 * s**3 + 3 * s**2, s**3 - s**2
    return h00 * npos[j] + h10 * hh * nvel[j] + h01 * npos[j + 1] + h11 * hh * nvel[j + 1]


# ---------------------------------------------------------------------------- compiled kernels
_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def _truth_kernel(t_s, scal, vec):  # pragma: no cover - compiled
    """Per vehicle: ECEF->ENU rotation (v2v.frames.ecef_to_enu_rotation), ECEF velocity, and the
    antenna moved from its state time to ``t_s`` with its velocity. ``scal``: (lat, lon, h, t);
    ``vec``: (vel ENU, ECEF, net XYZ)."""
    m = scal.shape[0]
    lat, lon, h = scal[:, 0].copy(), scal[:, 1].copy(), np.empty(m)
    rx, vel, xyz = np.empty((m, 3)), np.empty((m, 3)), np.empty((m, 3))
    rots = np.empty((m, 3, 3))
    for i in range(m):
        sl, cl, so, co = np.sin(lat[i]), np.cos(lat[i]), np.sin(lon[i]), np.cos(lon[i])
        r = rots[i]
        r[0, 0], r[0, 1], r[0, 2] = -so, co, 0.0
        r[1, 0], r[1, 1], r[1, 2] = -sl * co, -sl * so, cl
        r[2, 0], r[2, 1], r[2, 2] = cl * co, cl * so, sl
        dt = t_s - scal[i, 3]
        for c in range(3):
            vel[i, c] = vec[i, 0] * r[0, c] + vec[i, 1] * r[1, c] + vec[i, 2] * r[2, c]
        for c in range(3):
            rx[i, c] = vec[i, 3 + c] + vel[i, c] * dt
            xyz[i, c] = vec[i, 6 + c] + vec[i, c] * dt
        h[i] = scal[i, 2] + vec[i, 2] * dt
    return lat, lon, h, rx, rots, vel, xyz


@njit(**_JIT, inline="always")
def _earth_rotation_cs(tau_s):  # pragma: no cover - compiled
    """``(cos a, sin a)`` of the Earth-rotation angle ``a = OMEGA_E tau`` (< 1e-5 rad for light
    times): Taylor series to ``a^5``; the first neglected terms (``a^6 / 720``, ``a^7 / 5040``)
    are < 1e-33, far below float64 resolution, so this equals cos/sin to rounding."""
    a = OMEGA_E_RADPS * tau_s
    a2 = a * a
    return 1.0 - a2 / 2.0 + a2 * a2 / 24.0, a * (1.0 - a2 / 6.0 + a2 * a2 / 120.0)


@njit(**_JIT)
def _hermite(x, j, node_t, npos, nvel, nclk, ndrift, q, p_out, v_out):  # pragma: no cover - compiled
    """State of slot ``q`` at local time ``x`` in node interval ``j``: fills p_out, v_out; returns (clock, drift)."""
    hh = node_t[j + 1] - node_t[j]
    if hh <= 0.0:
        for c in range(3):
            p_out[c] = npos[j, q, c]
            v_out[c] = nvel[j, q, c]
        return nclk[j, q], ndrift[j, q]
    s = (x - node_t[j]) / hh
    s2 = s * s
    s3 = s2 * s
    h00, h10, h01, h11 = 2 * s3 - 3 * s2 + 1, s3 - 2 * s2 + s, -2 * s3 + 3 * s2, s3 - s2
    d00, d10, d01, d11 = (6 * s2 - 6 * s) / hh, 3 * s2 - 4 * s + 1, (-6 * s2 + 6 * s) / hh, 3 * s2 - 2 * s
    for c in range(3):
        p0, p1, v0, v1 = npos[j, q, c], npos[j + 1, q, c], nvel[j, q, c], nvel[j + 1, q, c]
        p_out[c] = h00 * p0 + h10 * hh * v0 + h01 * p1 + h11 * hh * v1
        v_out[c] = d00 * p0 + d10 * v0 + d01 * p1 + d11 * v1
    b0, b1, r0, r1 = nclk[j, q], nclk[j + 1, q], ndrift[j, q], ndrift[j + 1, q]
    return h00 * b0 + h10 * hh * r0 + h01 * b1 + h11 * hh * r1, d00 * b0 + d10 * r0 + d01 * b1 + d11 * r1


@njit(**_JIT)
def _geometry_kernel(
    t_s, t_gps_s, mask_rad, node_t, npos, nvel, nclk, ndrift, nok, slot, rx, rots, lat, lon, h, rac, sv_clk_err,
    iono_on, iono_scale, alpha, beta, shell_h, i_ref_lat, i_ref_lon, k_en, omega, phase, amp,
    tropo_on, t0_c, rh, z_res, g_e, g_n, t_ref_lat, t_ref_lon, out,
):  # pragma: no cover - compiled
    """Fills ``out`` (m, k, _G_N) for every (vehicle, candidate) pair (see GnssSynthesizer._geometry).

    Orbit error, ionosphere and troposphere are left 0 for pairs below the elevation mask
    (never tracked)."""
    m, k = rx.shape[0], slot.shape[0]
    p = np.empty(3)
    v = np.empty(3)
    cos_i_ref = np.cos(i_ref_lat)
    for i in range(m):
        sin_lat, cos_lat = np.sin(lat[i]), np.cos(lat[i])
        zenith = 0.0
        if tropo_on:
            zenith = tropo_zenith_scalar_m(lat[i], lon[i], h[i], t0_c, rh, z_res, g_e, g_n, t_ref_lat, t_ref_lon)
        for jj in range(k):
            q = slot[jj]
            o = out[i, jj]
            ok = nok[0, q] and nok[1, q] and nok[2, q]
            if not ok:
                o[:] = 0.0
                o[_G_RANGE] = 1.0
                o[_G_EL] = -np.pi / 2
                continue
            # Light time: fixed point of tau = |R3(w tau) x(t - tau) - x_rx| / c.
            tau = 0.075
            for _ in range(10):
                x = t_s - tau
                j = 0 if x < node_t[1] else 1
                _hermite(x, j, node_t, npos, nvel, nclk, ndrift, q, p, v)
                ca, sa = _earth_rotation_cs(tau)
                dx = ca * p[0] + sa * p[1] - rx[i, 0]
                dy = -sa * p[0] + ca * p[1] - rx[i, 1]
                dz = p[2] - rx[i, 2]
                tau_new = np.sqrt(dx * dx + dy * dy + dz * dz) / SPEED_OF_LIGHT_MPS
                done = abs(tau_new - tau) < _TRANSIT_TOL_S
                tau = tau_new
                if done:
                    break
            x = t_s - tau
            j = 0 if x < node_t[1] else 1
            clk, clkd = _hermite(x, j, node_t, npos, nvel, nclk, ndrift, q, p, v)
            ca, sa = _earth_rotation_cs(tau)
            px, py, pz = ca * p[0] + sa * p[1], -sa * p[0] + ca * p[1], p[2]
            vx, vy, vz = ca * v[0] + sa * v[1], -sa * v[0] + ca * v[1], v[2]
            dx, dy, dz = px - rx[i, 0], py - rx[i, 1], pz - rx[i, 2]
            rng_m = np.sqrt(dx * dx + dy * dy + dz * dz)
            ux, uy, uz = dx / rng_m, dy / rng_m, dz / rng_m
            r = rots[i]
            e_ = r[0, 0] * dx + r[0, 1] * dy + r[0, 2] * dz
            n_ = r[1, 0] * dx + r[1, 1] * dy + r[1, 2] * dz
            u_ = r[2, 0] * dx + r[2, 1] * dy + r[2, 2] * dz
            az = np.arctan2(e_, n_) % (2.0 * np.pi)
            el = np.arctan2(u_, np.hypot(e_, n_))
            o[0], o[1], o[2], o[3], o[4], o[5] = px, py, pz, vx, vy, vz
            o[_G_CLK] = SPEED_OF_LIGHT_MPS * clk
            o[_G_CLKD] = SPEED_OF_LIGHT_MPS * clkd
            o[_G_RANGE] = rng_m
            o[_G_U], o[_G_U + 1], o[_G_U + 2] = ux, uy, uz
            o[_G_EL] = el
            o[_G_AZ] = az
            o[_G_SVCLKERR] = sv_clk_err[jj]
            if el < mask_rad:
                o[_G_ORBIT] = o[_G_IONO] = o[_G_TROPO] = 0.0
                continue
            # Broadcast-minus-true orbit error (radial, along, cross) at the reception-frame state.
            rn = np.sqrt(px * px + py * py + pz * pz)
            urx, ury, urz = px / rn, py / rn, pz / rn
            hx, hy, hz = py * vz - pz * vy, pz * vx - px * vz, px * vy - py * vx
            hn = np.sqrt(hx * hx + hy * hy + hz * hz)
            ucx, ucy, ucz = hx / hn, hy / hn, hz / hn
            uax, uay, uaz = ucy * urz - ucz * ury, ucz * urx - ucx * urz, ucx * ury - ucy * urx
            r0, r1, r2 = rac[jj, 0], rac[jj, 1], rac[jj, 2]
            drx = r0 * urx + r1 * uax + r2 * ucx
            dry = r0 * ury + r1 * uay + r2 * ucy
            drz = r0 * urz + r1 * uaz + r2 * ucz
            tx, ty, tz = px - drx - rx[i, 0], py - dry - rx[i, 1], pz - drz - rx[i, 2]
            orbit = np.sqrt(tx * tx + ty * ty + tz * tz) - rng_m
            el_c = max(el, 1e-3)
            iono = 0.0
            if iono_on:
                iono = iono_slant_delay_core_m(lat[i], lon[i], sin_lat, cos_lat, el_c, np.cos(az), np.sin(az), t_gps_s,
                                               iono_scale, alpha, beta, shell_h, i_ref_lat, cos_i_ref, i_ref_lon, k_en,
                                               omega, phase, amp)
            o[_G_ORBIT] = orbit
            o[_G_IONO] = iono
            o[_G_TROPO] = 0.0
            if tropo_on:
                s_el = np.sin(el_c)  # troposphere mapping (atmosphere.tropo_mapping)
                o[_G_TROPO] = 1.001 / np.sqrt(0.002001 + s_el**2) * zenith


@njit(**_JIT)
def _clock_kernel(rows, dt, fac, enabled, jump_thr_m, clock, clock_t, t_s, draws, draw_pos, jumps):
    """Two-state clock steps (clock.ReceiverClock.advance_to: same draws and arithmetic) of ``rows``."""
    ms_m = 1e-3 * SPEED_OF_LIGHT_MPS
    for i in range(rows.shape[0]):
        r = rows[i]
        d = dt[i]
        if enabled and d > 0.0:
            p = draw_pos[_S_CLOCK, r]
            z0, z1 = draws[_S_CLOCK, r, p], draws[_S_CLOCK, r, p + 1]
            draw_pos[_S_CLOCK, r] = p + 2
            b, dr = clock[r, 0], clock[r, 1]
            clock[r, 0] = b + d * dr + fac[i, 0] * z0
            clock[r, 1] = dr + (fac[i, 1] * z0 + fac[i, 2] * z1)
            if jump_thr_m > 0.0 and abs(clock[r, 0]) > jump_thr_m:
                jump = -np.round(clock[r, 0] / ms_m) * 1e-3 * SPEED_OF_LIGHT_MPS
                clock[r, 0] += jump
                jumps[i] = jump
        clock_t[r] = max(t_s, clock_t[r])


@njit(**_JIT)
def _measure_kernel(
    t_s, geom, blocked, echo, foliage_db, rows, cand, vel, mask_rad, cn0_zen, cn0_hor, foliage_on, foliage_max,
    nlos_on, echo_loss, threshold, dt_epoch, slip_rate, mp_on, mp_tau, mp_a, mp_b, mp_el0, mp_phase_ratio, noise_on,
    dll_tau, dll_d, dll_bl, t_pre, pll_bn, dopp45, clock, z_mp, z_mpp, z_noise, ambiguity, amb_max, lock_start,
    los_state, last_t, draws, draw_pos, sj_out, out, sv_pos, sv_vel, amb, los, off,
):  # pragma: no cover - compiled
    """Tracking, error processes and observables of every receiver (module docstring; errors.py models).

    Per vehicle: the tracked candidates (PRNs ascending) are those above the mask, not blocked
    or received as an echo, with C/N0 (:func:`~v2v.sensors.gnss.errors.cn0_dbhz`) above the
    tracking threshold. A gap (missed epoch), a LOS <-> echo switch or a random slip starts a
    new arc with a new integer ambiguity. Multipath (code, carrier) and DLL noise are unit
    Gauss-Markov states stepped exactly (errors.gauss_markov_step: ``z <- phi z + sqrt(1 -
    phi^2) w``, ``phi = exp(-dt / tau)``); noise sigmas are errors.dll_jitter_m, pll_jitter_m
    and doppler_sigma_mps. Each receiver consumes its own pre-drawn streams in a fixed order
    (slip uniforms, then ambiguities, per tracked satellite; multipath: all code then all
    carrier; noise; phase; Doppler). Outputs are written vehicle-major; returns their number.
    """
    m, k = blocked.shape
    chip_m = SPEED_OF_LIGHT_MPS * GPS_CA_CHIP_S
    n = 0
    for i in range(m):
        r = rows[i]
        lo = n
        for j in range(k):
            el = geom[i, j, _G_EL]
            nlos = blocked[i, j] and np.isfinite(echo[i, j]) and nlos_on
            cn0 = cn0_zen - (cn0_zen - cn0_hor) * (1.0 - np.sin(max(el, 0.0)))
            if foliage_on:
                cn0 = cn0 - min(foliage_db[i, j], foliage_max)
            cn0 = cn0 - (echo_loss if nlos else 0.0)
            if el >= mask_rad and ((not blocked[i, j]) or nlos) and cn0 >= threshold:
                sj_out[n] = j
                out[_O_CN0, n] = cn0
                los[n] = not nlos
                n += 1
        off[i + 1] = n
        ni = n - lo
        p_mp, p_n, p_d = draw_pos[_S_MULTIPATH, r], draw_pos[_S_NOISE, r], draw_pos[_S_DOPPLER, r]
        p_ph, p_sl, p_am = draw_pos[_S_PHASE, r], draw_pos[_S_SLIP, r], draw_pos[_S_AMBIGUITY, r]
        for t in range(lo, n):
            o = t - lo
            j = sj_out[t]
            prn = cand[j]
            g = geom[i, j]
            nlos = not los[t]
            gap = t_s - last_t[r, prn]
            new_arc = (gap > 1.5 * dt_epoch) or (los_state[r, prn] != los[t])
            if slip_rate > 0.0:
                p_slip = 1.0 - np.exp(-slip_rate * min(gap, dt_epoch))
                new_arc = (draws[_S_SLIP, r, p_sl] < p_slip) or new_arc
                p_sl += 1
            if new_arc:
                # Uniform integer in [-amb_max, amb_max] from u in [0, 1) (53-bit u: the
                # 2 amb_max + 1 values are equally likely to 1e-9 relative).
                u_bin = np.floor(draws[_S_AMBIGUITY, r, p_am] * (2 * amb_max + 1))
                ambiguity[r, prn] = np.int64(min(u_bin, 2 * amb_max)) - amb_max  # u -> 1 may round up
                p_am += 1
                lock_start[r, prn] = t_s
            los_state[r, prn] = los[t]
            dt = gap if np.isfinite(gap) else np.inf
            el = g[_G_EL]
            cn0 = out[_O_CN0, t]
            mp = 0.0
            mp_phase = 0.0
            if mp_on:
                phi = np.exp(-dt / mp_tau)
                q = np.sqrt(1.0 - phi**2)
                zm = phi * z_mp[r, prn] + q * draws[_S_MULTIPATH, r, p_mp + o]
                zp = phi * z_mpp[r, prn] + q * draws[_S_MULTIPATH, r, p_mp + ni + o]
                z_mp[r, prn] = zm
                z_mpp[r, prn] = zp
                sig = mp_a + mp_b * np.exp(-el / mp_el0)
                mp = sig * zm
                mp_phase = mp_phase_ratio * sig * zp
            noise = 0.0
            noise_phase = 0.0
            noise_dopp = 0.0
            if noise_on:
                phi = np.exp(-dt / dll_tau)
                zn = phi * z_noise[r, prn] + np.sqrt(1.0 - phi**2) * draws[_S_NOISE, r, p_n + o]
                z_noise[r, prn] = zn
                cn0_lin = 10.0 ** (cn0 / 10.0)
                chips = np.sqrt(dll_bl * dll_d / (2.0 * cn0_lin) * (1.0 + 2.0 / ((2.0 - dll_d) * t_pre * cn0_lin)))
                noise = chip_m * chips * zn
                rad = np.sqrt(pll_bn / cn0_lin * (1.0 + 1.0 / (2.0 * t_pre * cn0_lin)))
                noise_phase = GPS_L1_WAVELENGTH_M / (2.0 * np.pi) * rad * draws[_S_PHASE, r, p_ph + o]
                noise_dopp = dopp45 * np.sqrt(10.0 ** ((45.0 - cn0) / 10.0)) * draws[_S_DOPPLER, r, p_d + o]
            last_t[r, prn] = t_s
            rho = g[_G_RANGE]
            sv_clock_m = g[_G_CLK]
            iono = g[_G_IONO]
            nlos_m = echo[i, j] if nlos else 0.0
            errs = (clock[r, 0], -sv_clock_m, -g[_G_SVCLKERR], g[_G_ORBIT], iono, g[_G_TROPO], mp, nlos_m, noise)
            total = 0.0
            for e_i in range(9):
                out[_O_ERR + e_i, t] = errs[e_i]
                total += errs[e_i]
            pr = rho + total
            phase_m = pr - iono * 2.0 - mp - noise + mp_phase + noise_phase
            a = ambiguity[r, prn]
            amb[t] = a
            ex, ey, ez = g[_G_U], g[_G_U + 1], g[_G_U + 2]
            e_vsv = ex * g[_G_VEL] + ey * g[_G_VEL + 1] + ez * g[_G_VEL + 2]
            e_rot = OMEGA_E_RADPS * (ex * g[_G_POS + 1] - ey * g[_G_POS])
            e_vrx = ex * vel[i, 0] + ey * vel[i, 1] + ez * vel[i, 2]
            range_rate = (e_vsv - e_vrx) / (1.0 + (e_vsv - e_rot) / SPEED_OF_LIGHT_MPS)
            out[_O_PR, t] = pr
            out[_O_DOPP, t] = range_rate + clock[r, 1] - g[_G_CLKD] + noise_dopp
            out[_O_CARR, t] = phase_m / GPS_L1_WAVELENGTH_M + a
            out[_O_LOCK, t] = t_s - lock_start[r, prn]
            out[_O_EL, t] = el
            out[_O_AZ, t] = g[_G_AZ]
            out[_O_RHO, t] = rho
            out[_O_SVCLK, t] = sv_clock_m
            for c in range(3):
                sv_pos[t, c] = g[_G_POS + c]
                sv_vel[t, c] = g[_G_VEL + c]
        if mp_on:
            draw_pos[_S_MULTIPATH, r] = p_mp + 2 * ni
        if noise_on:
            draw_pos[_S_NOISE, r] = p_n + ni
            draw_pos[_S_DOPPLER, r] = p_d + ni
            draw_pos[_S_PHASE, r] = p_ph + ni
        draw_pos[_S_SLIP, r] = p_sl
        draw_pos[_S_AMBIGUITY, r] = p_am
    return n


def warm_up() -> None:
    """Load (or, on the first use after an install, compile and cache) the compiled kernels by
    synthesizing two epochs of one receiver under the nominal constellation."""
    from v2v.sensors.gnss.constellation import NominalConstellation

    eph = NominalConstellation(1.3e9)
    syn = GnssSynthesizer(eph, GnssReceiverConfig(), np.random.SeedSequence(0), 1.3e9)
    rx = np.array([-1641945.0, -3664804.0, 4940009.0])  # 51 N, 114 W
    vel0 = np.zeros(3)
    lat, lon = np.deg2rad(51.08), np.deg2rad(-114.13)
    rows = np.zeros(1, dtype=np.int64)
    rcv = syn._new_receiver("w", 0.0)
    nodes = syn._node_arrays(0.1)
    syn._iono = IonosphereField(syn.config.errors.iono, np.random.default_rng(0), lat, lon)
    syn._tropo = TroposphereField(syn.config.errors.tropo, np.random.default_rng(0), lat, lon)
    slot = np.arange(syn._prns.size)
    rots = np.eye(3)[None]
    geom = syn._geometry(0.1, slot, nodes, rx[None], rots, np.array([lat]), np.array([lon]), np.zeros(1))
    syn._measure(0.1, ["w"], [rcv], rows, syn._prns, geom, vel0[None], None)
    _truth_kernel(0.0, np.zeros((1, 4)), np.zeros((1, 9)))
