"""Per-vehicle GNSS receiver measurement synthesis (pseudorange, Doppler, carrier phase).

Measurement models (MacGougan 2009 eq. 3.1, 3.6 and 5.1; Misra & Enge 2011 ch. 5)::

    P   = rho + c dT - c dt_sv + orbit + I + T + MP + NLOS + eps_P                    (m)
    Phi = (rho + c dT - c dt_sv + orbit - I + T + mp_phi + NLOS + eps_phi) / lambda + N   (cycles)
    dP/dt = e . (v_sv - v_rx) / (1 + (e . v_sv - w e . (y_sv, -x_sv, 0)) / c)
            + d(NLOS)/dt + c dT/dt - c d(dt_sv)/dt + eps_D                              (m/s)

* ``rho`` (``true_range_m``): geometric range from the true antenna at the true reception
  time ``t = gps_start + t_s`` to the *broadcast* satellite position at the transmit time
  (light-time iteration), in the ECEF frame at reception (Earth rotation / Sagnac,
  IS-GPS-200 20.3.3.4.3.4). It is what the filter's model ``|x_sv - x|`` gives at the
  true position; the difference to the true satellite position is the ``orbit`` term.
* Doppler: ``e`` unit vector receiver -> satellite; the denominator is the light-time
  rate (transmit time advances by ``1 - rho_dot / c`` per received second, and the
  Earth-rotation angle ``w tau`` changes with it): ~4 mm/s. An echo-only signal's
  Doppler follows its reflected path: ``d(NLOS)/dt = 2 (s . n) (n . v_xy)`` for the wall
  echo ``NLOS = 2 d_w (s . n)`` of an antenna moving at ``v_xy`` (the gradient of
  :attr:`~v2v.world.occlusion.SkyResult.echo_gradient_xy`; up to 2 |v|, 28 m/s at 50 km/h
  toward a wall), so code, carrier and Doppler of an echo stay consistent.
  Ionosphere/troposphere/multipath rates (mm/s to cm/s) and the echo's change with the
  satellite's motion (mm/s) are not included.
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

Speed (issues 3 and 7: synthesis well below the filter's time): a batch of epochs of the
whole cluster (:meth:`GnssSynthesizer.feed_many`: a streaming chunk) is three compiled (numba,
cached) passes over all its (epoch, vehicle, candidate satellite) pairs: truth/rotations,
geometry (satellite states interpolated between ephemeris evaluations on a 5 s grid, light
time, az/el, orbit, ionosphere, troposphere: :meth:`GnssSynthesizer._geometry`), and
tracking/errors/observables of all receivers, epoch after epoch (:func:`_measure_kernel`),
plus a few batched sky queries; Python only schedules the node sets and candidate screens
(once per second) and builds the :class:`GnssEpoch` records. The numbers are those of
synthesizing one epoch at a time (same arithmetic per pair, same draws in the same order).
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from itertools import chain, pairwise
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
# Rays per batched sky query: enough to amortize the call, few enough that the occlusion
# geometry keeps its compiled per-(ray, wall) tests (OcclusionGeometry.compiled_pairs_max).
_SKY_RAYS = 512
# (epoch, vehicle) rows synthesized together by feed_many (geometry ~4 kB per row).
_BATCH_ROWS = 1024


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
    random numbers of every receiver in one array per quantity (row ``self.row``), so that a
    batch of epochs of the whole cluster is one compiled pass. ``clock.state`` is a view of that row
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

    # (the arrays are set by _grow)
    last_t: F64
    z_mp: F64
    z_mp_phase: F64
    z_noise: F64
    ambiguity: I64
    lock_start: F64
    los: NDArray[np.bool_]
    echo_wall: I64
    clock: F64
    clock_t: F64
    draws: F64
    draw_pos: I64

    def __init__(self, rows: int = 8):
        self.cap = 0
        self.block = _DRAW_BLOCK  # length of each pre-drawn block (grows for long batches)
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
            "echo_wall": np.full((rows, n), -1, dtype=np.int64),  # reflecting wall of an echo-only signal
            "clock": np.zeros((rows, 2)),  # receiver clock (bias m, drift m/s)
            "clock_t": np.zeros(rows),  # time of that clock state
            # Pre-drawn random numbers per (stream, receiver row) and the next unused index.
            "draws": np.zeros((_N_STREAMS, rows, self.block)),
            "draw_pos": np.full((_N_STREAMS, rows), self.block, dtype=np.int64),
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

    def ensure_block(self, n: int) -> None:
        """Make the pre-drawn blocks at least ``n`` long; every row's unused numbers move to the
        end of its longer block (its position moves with them), so no number is lost or reordered."""
        if n <= self.block:
            return
        new = max(n, 2 * self.block)
        draws = np.zeros((_N_STREAMS, self.cap, new))
        draws[:, :, new - self.block:] = self.draws
        self.draws = draws
        self.draw_pos += new - self.block
        self.block = new


# Pre-drawn random numbers: one block per (stream, receiver), refilled from the receiver's own
# Generator when fewer than a batch's worst case remain (blocks grow to fit a batch). Each stream draws one kind of number
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
        self._cand: tuple[I64, I64, F64, F64] | None = None  # candidate (slot, PRN, orbit error, clock error)
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
        return self.feed_many([step])

    def feed_many(self, steps: Sequence[TrafficStep]) -> list[dict[str, GnssEpoch]]:
        """:meth:`feed` of each step in turn, synthesized together (e.g. a streaming chunk).

        The same epochs with the same numbers as feeding the steps one by one; they are
        synthesized in batches of about ``_BATCH_ROWS`` (epoch, vehicle) rows, each in one
        compiled pass per stage (:meth:`_epochs`), so memory stays bounded for long inputs.
        """
        rate = self.config.rate_hz
        due: list[tuple[float, Mapping[str, VehicleState]]] = []
        for step in steps:
            if self._next_k is None:
                self._next_k = int(np.ceil(step.t_s * rate - 1e-6))
            while self._next_k / rate <= step.t_s + 1e-6:
                if step.vehicles:
                    due.append((self._next_k / rate, step.vehicles))
                self._next_k += 1
        out: list[dict[str, GnssEpoch]] = []
        lo, rows = 0, 0
        for i, (_, vehicles) in enumerate(due):
            rows += len(vehicles)
            if rows >= _BATCH_ROWS or i == len(due) - 1:
                out += self._epochs(due[lo:i + 1])
                lo, rows = i + 1, 0
        return out

    def run(self, steps: Iterable[TrafficStep]) -> list[GnssEpoch]:
        """All epochs of all vehicles, ordered by time then vehicle id."""
        out: list[GnssEpoch] = []
        for ep in self.feed_many(list(steps)):
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
        return self._epochs([(t_s, vehicles)])[0]

    def _epochs(self, due: Sequence[tuple[float, Mapping[str, VehicleState]]]) -> list[dict[str, GnssEpoch]]:
        """Every vehicle's epoch at each ``(t_s, vehicles)`` of ``due`` (times ascending).

        All (epoch, vehicle) rows go through one compiled pass each: truth, geometry
        (:meth:`_geometry`) and tracking/observables (:meth:`_measure`), with one sky query for
        all their rays. What is sequential in time (node sets, candidate screen and pass
        counting, the receivers' states and draws) is kept in epoch order, so the numbers are
        those of synthesizing the epochs one by one.
        """
        ts: list[float] = []
        ids_e: list[list[str]] = []
        rcvs_e: list[list[GnssReceiver]] = []
        rows_e: list[I64] = []
        states: list[VehicleState] = []
        for t_s, vehicles in due:
            ids = list(vehicles)
            if not ids:
                continue
            t_s = float(t_s)
            if self._iono is None:
                first = vehicles[ids[0]]
                self._init_fields(first.lat_rad, first.lon_rad, first.xyz_m)
            if ids == self._last_ids:  # same vehicles as the previous epoch (the usual case)
                rcvs, rows = self._last_rcvs
            else:
                rcvs = [self.receivers.get(vid) or self._new_receiver(vid, t_s) for vid in ids]
                rows = np.array([r.row for r in rcvs], dtype=np.int64)
                self._last_ids, self._last_rcvs = ids, (rcvs, rows)
            if t_s < self._last_t_s - 1e-9:
                raise ValueError(f"GNSS epochs must not go back in time ({self._last_t_s} -> {t_s} s)")
            self._last_t_s = t_s
            ts.append(t_s)
            ids_e.append(ids)
            rcvs_e.append(rcvs)
            rows_e.append(rows)
            states.extend(vehicles.values())
        n_ep = len(ts)
        if n_ep == 0:
            return [{} for _ in due]
        m_e = np.array([len(ids) for ids in ids_e], dtype=np.int64)
        row_off = np.zeros(n_ep + 1, dtype=np.int64)
        np.cumsum(m_e, out=row_off[1:])
        n_rows = int(row_off[-1])
        t_ep = np.array(ts)
        # Truth at the epochs (velocity extrapolation if a state is not exactly at its epoch).
        scal = np.fromiter(chain.from_iterable((s.lat_rad, s.lon_rad, s.h_m, s.t_s) for s in states), float,
                           4 * n_rows).reshape(n_rows, 4)
        vec = np.concatenate([x for s in states for x in (s.vel_enu_mps, s.ecef_m, s.xyz_m)]).reshape(n_rows, 9)
        lat, lon, h, rx, rots, vel, xyz = _truth_kernel(np.repeat(t_ep, m_e), scal, vec)

        # Per epoch, in time order: ephemeris node set and candidate satellites.
        node_sets: list[tuple] = []
        cand_sets: list[tuple[I64, I64, F64, F64]] = []
        ep_node = np.empty(n_ep, dtype=np.int64)
        ep_cand = np.empty(n_ep, dtype=np.int64)
        for e, t_s in enumerate(ts):
            nodes = self._node_arrays(t_s)
            if not node_sets or node_sets[-1] is not nodes:
                node_sets.append(nodes)
            ep_node[e] = len(node_sets) - 1
            if self._coarse_el is None or t_s - self._coarse_t >= _COARSE_UPDATE_S - 1e-9:
                lo, hi = row_off[e], row_off[e + 1]
                self._coarse_el = self._update_passes(rx[lo:hi].mean(axis=0), rots[lo], t_s, nodes)
                self._coarse_t = t_s
                self._cand = None
            if self._cand is None:
                slot = np.flatnonzero(self._coarse_el >= self.config.elevation_mask_rad - _CANDIDATE_MARGIN_RAD)
                self._cand = (slot, self._prns[slot], self._sat_rac[slot], self._sat_clk[slot])
            if not cand_sets or cand_sets[-1] is not self._cand:
                cand_sets.append(self._cand)
            ep_cand[e] = len(cand_sets) - 1
        cand_off = np.zeros(len(cand_sets) + 1, dtype=np.int64)
        np.cumsum([c[0].size for c in cand_sets], out=cand_off[1:])
        slot, cand, rac, sv_clk = (np.concatenate([c[i] for c in cand_sets]) for i in range(4))
        k_e = (cand_off[1:] - cand_off[:-1])[ep_cand]
        k_row = np.repeat(k_e, m_e)
        pair_off = np.zeros(n_ep + 1, dtype=np.int64)
        np.cumsum(m_e * k_e, out=pair_off[1:])
        layout = _ChunkLayout(t_ep=t_ep, row_off=row_off, pair_off=pair_off, ep_cand=ep_cand, cand_off=cand_off)
        geom = self._geometry(layout, ep_node, node_sets, slot, rac, sv_clk, rx, rots, lat, lon, h)

        sky = None
        if self.occlusion is not None and geom.shape[0]:
            el = np.ascontiguousarray(geom[:, _G_EL])
            # set by _init_fields above: an occlusion geometry comes with a georef (checked in __init__)
            assert self._convergence_rad is not None
            az_grid = geom[:, _G_AZ] - self._convergence_rad
            if hasattr(self.occlusion, "sky_many"):
                # Batched queries of whole epochs' rays (each ray's answer depends on that ray only),
                # about _SKY_RAYS rays each: large batches would leave the compiled wall tests.
                ai = np.repeat(np.arange(n_rows), k_row)
                cuts = [0]
                for p in layout.pair_off[1:].tolist():
                    if p - cuts[-1] >= _SKY_RAYS:
                        cuts.append(p)
                if cuts[-1] != ai.size:
                    cuts.append(ai.size)
                res = [self.occlusion.sky_many(xyz, ai[a:b], az_grid[a:b], el[a:b]) for a, b in pairwise(cuts)]
            else:  # any object with the per-antenna ``sky`` method
                po = np.concatenate([[0], np.cumsum(k_row)])
                res = [self.occlusion.sky(xyz[i], az_grid[po[i]:po[i + 1]], el[po[i]:po[i + 1]]) for i in range(n_rows)]
            sky_cols = [np.concatenate([np.asarray(getattr(r, a)) for r in res]) if len(res) > 1 else np.asarray(getattr(res[0], a))
                        for a in ("blocked", "echo_excess_m", "foliage_loss_db")]
            grads: list[Any] = [getattr(r, "echo_gradient_xy", None) for r in res]
            walls: list[Any] = [getattr(r, "echo_wall", None) for r in res]
            echo_wall = (np.concatenate(walls) if len(walls) > 1 else np.asarray(walls[0])).astype(np.int64) \
                if all(w is not None for w in walls) else np.full(geom.shape[0], -1, dtype=np.int64)
            echo_rate = np.zeros(geom.shape[0])
            if all(g is not None for g in grads):
                grad = np.concatenate(grads) if len(grads) > 1 else np.asarray(grads[0])
                # the antenna's net-XY velocity: its ENU velocity turned by the grid convergence
                # (grid azimuth = true azimuth - gamma)
                gamma = self._convergence_rad or 0.0  # (set with the occlusion's first query)
                cg, sg = math.cos(gamma), math.sin(gamma)
                v_e, v_n = np.repeat(vec[:, 0], k_row), np.repeat(vec[:, 1], k_row)
                rate = grad[:, 0] * (v_e * cg - v_n * sg) + grad[:, 1] * (v_e * sg + v_n * cg)
                echo_rate = np.where(np.isfinite(rate), rate, 0.0)
            sky = (*sky_cols, echo_rate, echo_wall)
        return self._measure(layout, ids_e, rcvs_e, rows_e, cand, geom, vel, sky, due)

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
        trk.draw_pos[:, row] = trk.block
        return rcv

    def _refill(self, rows: I64, rcvs: list[GnssReceiver], need: I64) -> None:
        """Make sure every receiver has ``need[s]`` unused pre-drawn numbers in stream ``s``."""
        trk = self._trk
        trk.ensure_block(int(need.max()))
        block = trk.block
        low = trk.draw_pos[:, rows] + need[:, None] > block
        if not low.any():
            return
        for s, i in zip(*np.nonzero(low), strict=True):
            rcv, r = rcvs[i], rows[i]
            p = int(trk.draw_pos[s, r])
            left = block - p
            buf = trk.draws[s, r]
            buf[:left] = buf[p:].copy()
            if s >= _S_SLIP:
                buf[left:] = (rcv.rng_slip if s == _S_SLIP else rcv.rng_ambiguity).random(block - left)
            else:
                rng = (rcv.clock.rng, rcv.rng_multipath, rcv.rng_noise, rcv.rng_doppler, rcv.rng_phase)[s]
                buf[left:] = rng.standard_normal(block - left)
            trk.draw_pos[s, r] = 0

    def _clock_factors(self, layout: _ChunkLayout, rows: I64) -> tuple[F64, F64]:
        """Per (epoch, receiver) row: clock step ``dt`` and the Cholesky factors ``(l11, l21, l22)``
        of its clock noise (the receivers' clock times advanced epoch by epoch as the steps will)."""
        dt = _clock_steps_kernel(layout.t_ep, layout.row_off, rows, self._trk.clock_t.copy())
        fac = np.zeros((rows.size, 3))
        ccfg = self.config.errors.clock
        if ccfg.enabled:
            d0 = float(dt[0])
            for d in [d0] if (dt == d0).all() else np.unique(dt).tolist():
                if d > 0.0:
                    fac[dt == d] = _process_noise_cholesky(ccfg.oscillator, d)
        return dt, fac

    @staticmethod
    def _log_jumps(t_s: float, rcvs: list[GnssReceiver], jumps: F64) -> None:
        for i in np.flatnonzero(jumps):
            rcvs[i].clock.jumps.append(ClockJump(t_s=t_s, jump_m=float(jumps[i])))
        for rcv in rcvs:
            rcv.clock.t_s = t_s

    def _measure(
        self,
        layout: _ChunkLayout,
        ids_e: list[list[str]],
        rcvs_e: list[list[GnssReceiver]],
        rows_e: list[I64],
        cand: I64,
        geom: F64,
        vel: F64,
        sky: tuple[np.ndarray, ...] | None,
        due: Sequence[tuple[float, Mapping[str, VehicleState]]],
    ) -> list[dict[str, GnssEpoch]]:
        """Tracking, error processes and observables of all receivers (see the module docstring).

        Pair arrays are flat over (epoch, vehicle, candidate satellite) (``layout``); the
        tracked pairs are written vehicle by vehicle (PRNs ascending within a vehicle), so
        each vehicle's epoch is a contiguous slice. Returns one dict per entry of ``due``
        (empty for entries without vehicles).
        """
        cfg = self.config
        err = cfg.errors
        trk = err.tracking
        st = self._trk
        n_pairs = geom.shape[0]
        if sky is None:
            blocked = np.zeros(n_pairs, dtype=bool)
            echo = np.full(n_pairs, np.nan)
            foliage_db = np.zeros(n_pairs)
            echo_rate = np.zeros(n_pairs)
            echo_wall = np.full(n_pairs, -1, dtype=np.int64)
        else:
            blocked, echo, foliage_db, echo_rate, echo_wall = (
                np.asarray(a, dtype=d) for a, d in zip(sky, (bool, float, float, float, np.int64), strict=True))
        rows = np.concatenate(rows_e) if len(rows_e) > 1 else rows_e[0]
        k_e = np.diff(layout.pair_off) // np.diff(layout.row_off)
        slips = trk.random_slip_rate_hz > 0.0
        mp_on, noise_on = err.multipath.enabled, trk.noise_enabled
        k_sum = int(k_e.sum())
        n_ep = k_e.size
        need = np.array([2 * n_ep, 2 * k_sum if mp_on else 0, k_sum if noise_on else 0, k_sum if noise_on else 0,
                         k_sum if noise_on else 0, k_sum if slips else 0, k_sum])
        if n_ep == 1:
            self._refill(rows, rcvs_e[0], need)
        else:
            by_row = {int(r): rcv for rows_i, rcvs in zip(rows_e, rcvs_e, strict=True)
                      for r, rcv in zip(rows_i.tolist(), rcvs, strict=True)}
            self._refill(np.array(list(by_row), dtype=np.int64), list(by_row.values()), need)
        dt_clk, fac = self._clock_factors(layout, rows)
        ccfg = err.clock
        thr = -1.0 if ccfg.ms_jump_threshold_s is None else ccfg.ms_jump_threshold_s * SPEED_OF_LIGHT_MPS
        jumps = np.zeros(rows.size)

        prn = np.empty(n_pairs, dtype=np.int64)
        out_f = np.empty((_O_N, n_pairs))
        sv_pos = np.empty((n_pairs, 3))
        sv_vel = np.empty((n_pairs, 3))
        amb = np.empty(n_pairs, dtype=np.int64)
        los = np.empty(n_pairs, dtype=np.bool_)
        off = np.zeros(rows.size + 1, dtype=np.int64)
        mpc = err.multipath
        _measure_kernel(
            layout.t_ep, layout.row_off, layout.pair_off, layout.ep_cand, layout.cand_off, geom, blocked, echo,
            echo_rate, echo_wall, foliage_db, rows, cand, vel, dt_clk, fac, ccfg.enabled, thr, st.clock_t, jumps, cfg.elevation_mask_rad,
            trk.cn0_zenith_dbhz, trk.cn0_horizon_dbhz, trk.foliage_enabled, trk.foliage_max_db, trk.nlos_enabled,
            trk.echo_loss_db, trk.track_threshold_dbhz, self._dt_epoch, trk.random_slip_rate_hz, mp_on, mpc.tau_s,
            mpc.sigma_a_m, mpc.sigma_b_m, mpc.el0_rad, mpc.phase_multipath_ratio, noise_on, trk.dll_correlation_time_s,
            trk.dll_spacing_chips, trk.dll_bandwidth_hz, trk.predetection_s, trk.pll_bandwidth_hz,
            trk.doppler_sigma_mps_at_45dbhz, st.clock, st.z_mp, st.z_mp_phase, st.z_noise, st.ambiguity,
            trk.ambiguity_max_cycles, st.lock_start, st.los, st.echo_wall, st.last_t, st.draws, st.draw_pos, prn, out_f, sv_pos,
            sv_vel, amb, los, off,
        )

        o = off.tolist()
        ro = layout.row_off.tolist()
        new = object.__new__
        result: list[dict[str, GnssEpoch]] = []
        e = 0
        for _, vehicles in due:
            if not vehicles:
                result.append({})
                continue
            t_s, ids, rcvs = float(layout.t_ep[e]), ids_e[e], rcvs_e[e]
            r0 = ro[e]
            if ccfg.ms_jump_threshold_s is not None or k_e[e] == 0:
                self._log_jumps(t_s, rcvs, jumps[r0:ro[e + 1]])
            out: dict[str, GnssEpoch] = {}
            if k_e[e] == 0:
                out = {vid: _empty_epoch(t_s, vid) for vid in ids}
            for i, vid in enumerate(ids if k_e[e] else ()):
                lo, hi = o[r0 + i], o[r0 + i + 1]
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
            result.append(out)
            e += 1
        return result

    def _geometry(
        self, layout: _ChunkLayout, ep_node: I64, node_sets: list[tuple], slot: I64, rac: F64, sv_clk: F64, rx: F64,
        rots: F64, lat: F64, lon: F64, h: F64,
    ) -> F64:
        """Light-time solution and common errors for all (epoch, vehicle, candidate) pairs: array
        (pairs, _G_N), flat in that order (``layout``); epoch ``e`` uses node set ``ep_node[e]``.

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
        node_t, npos, nvel, nclk, ndrift, nok = (
            node_sets[0][c][None] if len(node_sets) == 1 else np.stack([ns[c] for ns in node_sets]) for c in range(6))
        io, tr = self.config.errors.iono, self.config.errors.tropo
        fi, ft = self._iono, self._tropo
        assert fi is not None and ft is not None  # set by _init_fields before the first epoch
        out = np.empty((int(layout.pair_off[-1]), _G_N))
        _geometry_kernel(
            layout.t_ep, self.gps_start_s, layout.row_off, layout.pair_off, ep_node, layout.ep_cand, layout.cand_off,
            self.config.elevation_mask_rad, node_t, npos, nvel, nclk, ndrift, nok, slot, rx, rots, lat, lon, h, rac,
            sv_clk, io.enabled, io.klobuchar_scale, np.asarray(io.klobuchar_alpha, dtype=float),
            np.asarray(io.klobuchar_beta, dtype=float), io.shell_height_m, fi.ref_lat_rad, fi.ref_lon_rad, fi.k_en,
            fi.omega_radps, fi.phase_rad, fi.amp_m,
            tr.enabled, tr.temperature_sea_level_c, tr.relative_humidity, ft.zenith_residual_m, ft.gradient_en[0],
            ft.gradient_en[1], ft.ref_lat_rad, ft.ref_lon_rad, out,
        )
        return out


@dataclass(frozen=True, kw_only=True)
class _ChunkLayout:
    """Where each epoch of a batch lives in the flat arrays of :meth:`GnssSynthesizer._epochs`.

    Epoch ``e`` (time ``t_ep[e]``) has (vehicle) rows ``row_off[e]:row_off[e + 1]``, candidate
    set ``ep_cand[e]`` (entries ``cand_off[c]:cand_off[c + 1]`` of the candidate arrays) and
    (vehicle, candidate) pairs ``pair_off[e]:pair_off[e + 1]``, vehicle-major.
    """

    t_ep: F64
    row_off: I64
    pair_off: I64
    ep_cand: I64
    cand_off: I64


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
_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def _truth_kernel(t_s, scal, vec):  # pragma: no cover - compiled
    """Per vehicle: ECEF->ENU rotation (v2v.frames.ecef_to_enu_rotation), ECEF velocity, and the
    antenna moved from its state time to ``t_s`` (per vehicle row) with its velocity. ``scal``: (lat, lon, h, t);
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
        dt = t_s[i] - scal[i, 3]
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
    t_ep, gps_start_s, row_off, pair_off, ep_node, ep_cand, cand_off, mask_rad, node_ts, nposs, nvels, nclks, ndrifts,
    noks, slot_all, rx, rots, lat, lon, h, rac_all, sv_clk_all,
    iono_on, iono_scale, alpha, beta, shell_h, i_ref_lat, i_ref_lon, k_en, omega, phase, amp,
    tropo_on, t0_c, rh, z_res, g_e, g_n, t_ref_lat, t_ref_lon, out,
):  # pragma: no cover - compiled
    """Fills ``out`` (pairs, _G_N) for every (epoch, vehicle, candidate) pair, flat in that
    order (see GnssSynthesizer._geometry and _ChunkLayout); epoch ``e`` interpolates in node set
    ``ep_node[e]`` (``node_ts[s]`` (3,), ``nposs[s]`` (3, P, 3), ...).

    Orbit error, ionosphere and troposphere are left 0 for pairs below the elevation mask
    (never tracked)."""
    p = np.empty(3)
    v = np.empty(3)
    cos_i_ref = np.cos(i_ref_lat)
    for e in range(t_ep.shape[0]):
        t_s = t_ep[e]
        t_gps_s = gps_start_s + t_s
        s = ep_node[e]
        node_t, npos, nvel, nclk, ndrift, nok = node_ts[s], nposs[s], nvels[s], nclks[s], ndrifts[s], noks[s]
        c0 = cand_off[ep_cand[e]]
        k = cand_off[ep_cand[e] + 1] - c0
        slot, rac, sv_clk_err = slot_all[c0:c0 + k], rac_all[c0:c0 + k], sv_clk_all[c0:c0 + k]
        for i in range(row_off[e], row_off[e + 1]):
            base = pair_off[e] + (i - row_off[e]) * k
            sin_lat, cos_lat = np.sin(lat[i]), np.cos(lat[i])
            zenith = 0.0
            if tropo_on:
                zenith = tropo_zenith_scalar_m(lat[i], lon[i], h[i], t0_c, rh, z_res, g_e, g_n, t_ref_lat, t_ref_lon)
            for jj in range(k):
                q = slot[jj]
                o = out[base + jj]
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
def _clock_steps_kernel(t_ep, row_off, rows, clock_t):  # pragma: no cover - compiled
    """Per (epoch, receiver) row: the step ``t - clock_t[receiver]`` that :func:`_clock_kernel` will
    take at that epoch, advancing ``clock_t`` (a copy of the receivers' clock times) as it does."""
    dt = np.empty(rows.shape[0])
    for e in range(t_ep.shape[0]):
        for i in range(row_off[e], row_off[e + 1]):
            dt[i] = t_ep[e] - clock_t[rows[i]]
        for i in range(row_off[e], row_off[e + 1]):
            clock_t[rows[i]] = max(t_ep[e], clock_t[rows[i]])
    return dt


@njit(**_JIT)
def _measure_kernel(
    t_ep, row_off, pair_off, ep_cand, cand_off, geom, blocked, echo, echo_rate, echo_wall, foliage_db, rows, cand_all, vel, dt_clk, fac,
    clk_on, jump_thr_m, clock_t, jumps, mask_rad, cn0_zen, cn0_hor, foliage_on, foliage_max,
    nlos_on, echo_loss, threshold, dt_epoch, slip_rate, mp_on, mp_tau, mp_a, mp_b, mp_el0, mp_phase_ratio, noise_on,
    dll_tau, dll_d, dll_bl, t_pre, pll_bn, dopp45, clock, z_mp, z_mpp, z_noise, ambiguity, amb_max, lock_start,
    los_state, wall_state, last_t, draws, draw_pos, prn_out, out, sv_pos, sv_vel, amb, los, off,
):  # pragma: no cover - compiled
    """Tracking, error processes and observables of every receiver (module docstring; errors.py models).

    Per vehicle: the tracked candidates (PRNs ascending) are those above the mask, not blocked
    or received as an echo, with C/N0 (:func:`~v2v.sensors.gnss.errors.cn0_dbhz`) above the
    tracking threshold. A gap (missed epoch), a LOS <-> echo switch, an echo moving to another
    reflecting wall (``echo_wall``: its path jumps by metres) or a random slip starts a new arc
    with a new integer ambiguity. Multipath (code, carrier) and DLL noise are unit
    Gauss-Markov states stepped exactly (errors.gauss_markov_step: ``z <- phi z + sqrt(1 -
    phi^2) w``, ``phi = exp(-dt / tau)``); noise sigmas are errors.dll_jitter_m, pll_jitter_m
    and doppler_sigma_mps. Epochs are processed in order (``t_ep``, _ChunkLayout), each first
    stepping its receivers' clocks (:func:`_clock_kernel`, ``dt_clk``/``fac`` per row). Each receiver consumes its own pre-drawn streams in a fixed order
    (slip uniforms, then ambiguities, per tracked satellite; multipath: all code then all
    carrier; noise; phase; Doppler). Outputs are written epoch- then vehicle-major; ``off[row]`` is
    where row ``row``'s tracked pairs start.
    """
    chip_m = SPEED_OF_LIGHT_MPS * GPS_CA_CHIP_S
    n = 0
    sj_out = np.empty(geom.shape[0], dtype=np.int64)  # candidate index of each tracked pair
    for e in range(t_ep.shape[0]):
        t_s = t_ep[e]
        r_lo, r_hi = row_off[e], row_off[e + 1]
        _clock_kernel(rows[r_lo:r_hi], dt_clk[r_lo:r_hi], fac[r_lo:r_hi], clk_on, jump_thr_m, clock, clock_t, t_s, draws,
                      draw_pos, jumps[r_lo:r_hi])
        c0 = cand_off[ep_cand[e]]
        k = cand_off[ep_cand[e] + 1] - c0
        cand = cand_all[c0:c0 + k]
        for i in range(r_lo, r_hi):
            g0 = pair_off[e] + (i - r_lo) * k
            r = rows[i]
            lo = n
            for j in range(k):
                el = geom[g0 + j, _G_EL]
                nlos = blocked[g0 + j] and np.isfinite(echo[g0 + j]) and nlos_on
                cn0 = cn0_zen - (cn0_zen - cn0_hor) * (1.0 - np.sin(max(el, 0.0)))
                if foliage_on:
                    cn0 = cn0 - min(foliage_db[g0 + j], foliage_max)
                cn0 = cn0 - (echo_loss if nlos else 0.0)
                if el >= mask_rad and ((not blocked[g0 + j]) or nlos) and cn0 >= threshold:
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
                g = geom[g0 + j]
                nlos = not los[t]
                gap = t_s - last_t[r, prn]
                wall = echo_wall[g0 + j] if nlos else -1
                # a gap, a LOS <-> echo switch, or an echo moving to another wall (its path jumps)
                new_arc = (gap > 1.5 * dt_epoch) or (los_state[r, prn] != los[t]) or (wall_state[r, prn] != wall)
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
                wall_state[r, prn] = wall
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
                nlos_m = echo[g0 + j] if nlos else 0.0
                nlos_rate = echo_rate[g0 + j] if nlos else 0.0  # d(nlos_m)/dt from the antenna's motion
                errs = (clock[r, 0], -sv_clock_m, -g[_G_SVCLKERR], g[_G_ORBIT], iono, g[_G_TROPO], mp, nlos_m, noise)
                total = 0.0
                for e_i in range(9):
                    out[_O_ERR + e_i, t] = errs[e_i]
                    total += errs[e_i]
                pr = rho + total
                phase_m = pr - iono * 2.0 - mp - noise + mp_phase + noise_phase
                a = ambiguity[r, prn]
                amb[t] = a
                prn_out[t] = prn
                ex, ey, ez = g[_G_U], g[_G_U + 1], g[_G_U + 2]
                e_vsv = ex * g[_G_VEL] + ey * g[_G_VEL + 1] + ez * g[_G_VEL + 2]
                e_rot = OMEGA_E_RADPS * (ex * g[_G_POS + 1] - ey * g[_G_POS])
                e_vrx = ex * vel[i, 0] + ey * vel[i, 1] + ez * vel[i, 2]
                range_rate = (e_vsv - e_vrx) / (1.0 + (e_vsv - e_rot) / SPEED_OF_LIGHT_MPS)
                out[_O_PR, t] = pr
                out[_O_DOPP, t] = range_rate + nlos_rate + clock[r, 1] - g[_G_CLKD] + noise_dopp
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


def warm_up() -> None:
    """Load (or, on the first use after an install, compile and cache) the compiled kernels by
    synthesizing two epochs of one receiver under the nominal constellation."""
    from v2v.sensors.gnss.constellation import NominalConstellation

    eph = NominalConstellation(1.3e9)
    syn = GnssSynthesizer(eph, GnssReceiverConfig(), np.random.SeedSequence(0), 1.3e9)
    z3 = np.zeros(3)
    state = VehicleState(
        vehicle_id="w", cluster="w", is_lead=True, t_s=0.0, xyz_m=z3, lat_rad=float(np.deg2rad(51.08)),
        lon_rad=float(np.deg2rad(-114.13)), h_m=0.0, ecef_m=np.array([-1641945.0, -3664804.0, 4940009.0]),  # 51 N, 114 W
        vel_enu_mps=z3, speed_mps=0.0, accel_mps2=0.0, azimuth_rad=0.0, grid_azimuth_rad=0.0, yaw_rate_rps=0.0, front_bumper_xy_m=z3[:2],
        edge_id="", lane_id="", lane_index=0, lane_width_m=3.5, lateral_offset_m=0.0, length_m=4.5, width_m=1.8,
        height_m=1.5,
    )
    syn._epochs([(0.0, {"w": state}), (0.1, {"w": state})])
