"""Measurement records exchanged between sensors, the V2V exchange and estimation.

Columnar (numpy arrays per epoch) so that synthesis and filtering stay vectorized.
Every record carries its truth and error components so that metrics can tell true
from false rejections; the filter must only read the *measured* fields (and the
broadcast satellite data a real receiver would decode).

Units: metres, seconds, radians, cycles; time tags ``t_s`` are seconds since the
scenario start (GPS time = scenario ``gps_start`` + ``t_s``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from operator import itemgetter

import numpy as np
from numpy.typing import ArrayLike, NDArray

SPEED_OF_LIGHT_MPS = 299_792_458.0  # IS-GPS-200 value
GPS_L1_HZ = 1_575.42e6
GPS_L1_WAVELENGTH_M = SPEED_OF_LIGHT_MPS / GPS_L1_HZ

F64 = NDArray[np.float64]


@dataclass(frozen=True, kw_only=True)
class GnssEpoch:
    """Everything one receiver measured at one epoch (n satellites tracked).

    Measured fields
    ---------------
    pseudorange_m : (n,) code pseudorange, metres.
    doppler_mps : (n,) pseudorange *rate*, metres/second (= -wavelength * Doppler_Hz).
    carrier_cycles : (n,) accumulated carrier phase, L1 cycles (sign: grows with range).
    lock_time_s : (n,) time since the phase tracking loop (re)locked; 0 after a slip.
    cn0_dbhz : (n,) carrier-to-noise density.

    Broadcast data (what a receiver decodes, used by the filter as known)
    ---------------------------------------------------------------------
    sv_pos_ecef_m, sv_vel_ecef_mps : (n, 3) from the broadcast ephemeris at transmit
        time, expressed in the ECEF frame at reception time (Earth-rotation corrected).
    sv_clock_m : (n,) broadcast satellite clock correction (incl. relativistic term), metres.
    elevation_rad, azimuth_rad : (n,) from the receiver's true position.

    Truth
    -----
    los : (n,) True when the direct signal was received; False for echo-only (NLOS).
    true_range_m : (n,) geometric range at the true positions.
    errors_m : per-component pseudorange errors, metres, (n,) each (keys documented by
        the receiver model, e.g. ``clock``, ``iono``, ``tropo``, ``orbit``, ``multipath``,
        ``nlos``, ``noise``).
    ambiguity_cycles : (n,) the true integer ambiguity of ``carrier_cycles``.
    """

    t_s: float
    vehicle_id: str
    prn: NDArray[np.int64]
    pseudorange_m: F64
    doppler_mps: F64
    carrier_cycles: F64
    lock_time_s: F64
    cn0_dbhz: F64
    sv_pos_ecef_m: F64
    sv_vel_ecef_mps: F64
    sv_clock_m: F64
    elevation_rad: F64
    azimuth_rad: F64
    los: NDArray[np.bool_]
    true_range_m: F64
    ambiguity_cycles: NDArray[np.int64]
    errors_m: dict[str, F64] = field(default_factory=dict)

    @property
    def n(self) -> int:
        return int(self.prn.shape[0])

    def select(self, keep: NDArray[np.bool_]) -> GnssEpoch:
        """The signals where ``keep`` (bool, (n,)) is True, every per-satellite field (the
        errors included) selected alike; ``t_s`` and ``vehicle_id`` unchanged."""
        k = np.asarray(keep, dtype=bool)
        if k.shape != (self.n,):
            raise ValueError(f"keep must be a bool array of shape ({self.n},), got {k.shape}")
        return GnssEpoch(
            t_s=self.t_s, vehicle_id=self.vehicle_id, prn=self.prn[k], pseudorange_m=self.pseudorange_m[k],
            doppler_mps=self.doppler_mps[k], carrier_cycles=self.carrier_cycles[k], lock_time_s=self.lock_time_s[k],
            cn0_dbhz=self.cn0_dbhz[k], sv_pos_ecef_m=self.sv_pos_ecef_m[k], sv_vel_ecef_mps=self.sv_vel_ecef_mps[k],
            sv_clock_m=self.sv_clock_m[k], elevation_rad=self.elevation_rad[k], azimuth_rad=self.azimuth_rad[k],
            los=self.los[k], true_range_m=self.true_range_m[k], ambiguity_cycles=self.ambiguity_cycles[k],
            errors_m={name: v[k] for name, v in self.errors_m.items()},
        )


@dataclass(frozen=True, kw_only=True)
class UwbRanges:
    """UWB two-way ranges completed at one time tag (k ranges between radio pairs).

    ``a`` initiates, ``b`` responds. ``range_m`` is the radio's output (quantized).
    ``t_s`` is the time tag as logged (includes the time-tag sync error); truth is
    evaluated at the true measurement instant ``true_t_s``.
    """

    t_s: F64  # (k,) logged time tags
    true_t_s: F64  # (k,)
    a: tuple[str, ...]
    b: tuple[str, ...]
    range_m: F64
    true_range_m: F64
    los: NDArray[np.bool_]
    errors_m: dict[str, F64] = field(default_factory=dict)  # bias, scale, multipath, nlos, noise, sync

    @property
    def n(self) -> int:
        return int(self.range_m.shape[0])


@dataclass(frozen=True, kw_only=True)
class Bearings:
    """Bearing measurements (k) from vehicle ``a`` to vehicle ``b`` (paper eq. 3-5).

    ``bearing_rad`` = azimuth of the a->b vector minus a's azimuth, wrapped to (-pi, pi].
    ``azimuth_reported_rad`` is a's own azimuth as its navigation system reports it
    (truth + configured error), for the azimuth-known case.
    """

    t_s: F64
    a: tuple[str, ...]
    b: tuple[str, ...]
    bearing_rad: F64
    true_bearing_rad: F64
    azimuth_reported_rad: F64
    true_azimuth_rad: F64
    los: NDArray[np.bool_]

    @property
    def n(self) -> int:
        return int(self.bearing_rad.shape[0])

    def take(self, idx: ArrayLike) -> Bearings:
        """The bearings at integer positions ``idx``, in that order, every field alike
        (the vehicle names gathered in one C-level call: exchange packets take a few hundred
        of a chunk's tens of thousands per epoch)."""
        ii = np.asarray(idx, dtype=np.intp).reshape(-1)
        pos = ii.tolist()
        return Bearings(
            t_s=self.t_s[ii], a=_gather(self.a, pos), b=_gather(self.b, pos), bearing_rad=self.bearing_rad[ii],
            true_bearing_rad=self.true_bearing_rad[ii], azimuth_reported_rad=self.azimuth_reported_rad[ii],
            true_azimuth_rad=self.true_azimuth_rad[ii], los=self.los[ii],
        )


def _gather(seq: tuple[str, ...], pos: list[int]) -> tuple[str, ...]:
    """``tuple(seq[i] for i in pos)``."""
    if len(pos) > 1:
        return itemgetter(*pos)(seq)
    return (seq[pos[0]],) if pos else ()
