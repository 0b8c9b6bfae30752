"""Receiver-specific GNSS errors: multipath, tracking noise, C/N0, NLOS echoes, cycle slips.

Also holds :class:`GnssErrorConfig`, the one frozen configuration of every GNSS error
model (each switchable on its own).

Models
------
* **C/N0** (dB-Hz): ``C/N0(E) = zen - (zen - hor)(1 - sin E)`` (antenna gain roll-off),
  minus the canopy loss (specific attenuation in dB/m of each foliage area times the
  slant path through it, from :meth:`v2v.world.occlusion.OcclusionGeometry.sky`, capped
  at ``foliage_max_db``), minus ``echo_loss_db`` for
  echo-only (NLOS) signals. Below ``track_threshold_dbhz`` the satellite is not tracked
  (loss of lock).
* **Code multipath**: a unit-variance first-order Gauss-Markov process ``z`` per
  (receiver, satellite), ``z_{k+1} = exp(-dt/tau) z_k + sqrt(1 - exp(-2 dt/tau)) w_k``,
  scaled by ``sigma(E) = a + b exp(-E/E0)`` (the elevation model of Euler & Goad 1991,
  as used e.g. by RTKLIB/Jin et al.). Correlation time 5 s for a moving antenna (the
  DLL averages the fast fading; what is left changes as the car passes its reflectors:
  :class:`MultipathConfig`); a static antenna's multipath oscillates over tens of s to
  minutes (MacGougan 2009 fig. 5.24).
  Carrier multipath: an independent process of the same kind, ``phase_multipath_ratio``
  times smaller (mm level, bounded by lambda/4 in theory).
* **Code thermal noise** (DLL, non-coherent early-minus-late power discriminator,
  Van Dierendonck et al. 1992; Kaplan & Hegarty 2006 eq. 5.80)::

      sigma_DLL = c T_chip sqrt( B_L d / (2 C/N0) (1 + 2 / ((2 - d) T C/N0)) )

  ``d`` early-late spacing (chips), ``B_L`` loop bandwidth (Hz), ``T`` predetection time.
  The DLL output is low-pass filtered noise: modelled as a Gauss-Markov process with the
  loop's correlation time ``1/(4 B_L)`` (first-order loop), so 10-20 Hz samples are
  correlated like a real receiver's.
* **Carrier thermal noise** (PLL, Kaplan & Hegarty 2006 eq. 5.6 / Misra & Enge eq. 10.x)::

      sigma_PLL = (lambda / 2 pi) sqrt( B_n / (C/N0) (1 + 1 / (2 T C/N0)) )   metres

  white at the output rate. Doppler (pseudorange rate) noise scales the same way with C/N0.
* **Echo-only NLOS** (MacGougan 2009 §3.5.1 fig. 3.3, §5.2.3): direct path blocked, a
  reflection tracked -> code and carrier error = the echo's excess path (> 0), C/N0 reduced
  by the reflection loss; blocked with no reflection -> not tracked.
* **Ambiguities and slips**: a new random integer ambiguity at every (re)lock; a slip on
  loss of lock (including a LOS <-> echo switch) or at a configurable random rate.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray

from v2v.errors import UserError
from v2v.sensors.gnss.atmosphere import IonosphereConfig, SatelliteErrorConfig, TroposphereConfig
from v2v.sensors.gnss.clock import ClockConfig
from v2v.sensors.measurements import GPS_L1_WAVELENGTH_M, SPEED_OF_LIGHT_MPS

F64 = NDArray[np.float64]

GPS_CA_CHIP_S = 1.0 / 1.023e6  # C/A code chip duration


@dataclass(frozen=True, kw_only=True)
class MultipathConfig:
    """Code and carrier multipath (Gauss-Markov, elevation dependent).

    Parameters
    ----------
    enabled : bool
    sigma_a_m, sigma_b_m, el0_rad : float
        ``sigma(E) = a + b exp(-E / E0)`` (the elevation model of Euler & Goad 1991):
        0.15 m at zenith, 0.34 m at 10 deg, 0.68 m at 0 deg with the defaults.
    tau_s : float
        Correlation time of the slowly varying (DLL-averaged) part, for a car moving at
        urban speeds (5 s: ~50 m of travel at 36 km/h).
    phase_multipath_ratio : float
        Carrier multipath sigma / code multipath sigma (0.01: 1.5-7 mm).

    Notes
    -----
    How the defaults were chosen (a geodetic-grade narrow-correlator receiver with a
    pinwheel-type antenna on a car roof, as in Petovello et al. section 4: NovAtel OEM4 /
    OEMV3 with GPS-702GG antennas):

    * **Level**: the sky-averaged code multipath of a modern receiver in a benign
      environment is 0.2 m (1 sigma) in the GPS L1 C/A UERE budget of Kaplan & Hegarty
      (2006) Table 7.4. The default ``(a, b) = (0.15, 0.53)`` keeps the elevation shape of
      the previous default (``b / a = 3.5``, ``E0 = 10 deg``) and scales it so that its RMS
      over the satellites above a 10 deg mask at Calgary (the built-in 27-slot sky, sampled
      every 10 min for a day, median elevation 33 deg) is 0.20 m (0.26 m before).
    * **Correlation time**: for a moving antenna the multipath phase rotates fast (fading
      at up to ``v / lambda``, ~50-70 Hz at 36-50 km/h), the DLL averages it, and what is
      left is a mean error set by the reflectors around the antenna (van Nee 1992, "Multipath
      effects on GPS code phase measurements", Navigation 39(2): averaging is far more
      effective for mobile than for stationary users). That residual changes as the car
      passes its reflectors, over tens of metres: 5 s. The former 20 s came from static
      antennas (MacGougan 2009 fig. 5.24 is a static point beside a building), where code
      multipath oscillates over minutes. A car stopped at a light keeps the same multipath
      for as long as it stands: this one-tau model does not represent that.
    * **What it gives** (``experiments/paper_sensor_combinations.py``, 3 in-line cars, 27-slot
      sky, seeds 1-5; experiments/RESULTS.md section 1): GPS-only relative error std along /
      across 0.13-0.18 / 0.18-0.20 m at the hospital (paper Tables 3-4: 0.12 / 0.17-0.19 m)
      and 0.28-0.43 / 0.37-0.55 m under foliage (Tables 5-6: 0.32-0.43 / 0.29-0.45 m); with
      the previous default 0.17-0.23 / 0.29-0.32 m and 0.32-0.56 / 0.43-0.55 m (24 slots).
      Neither number was fitted: ``(a, b, tau)`` follow from the two sources above.
    """

    enabled: bool = True
    sigma_a_m: float = 0.15
    sigma_b_m: float = 0.53
    el0_rad: float = np.deg2rad(10.0)
    tau_s: float = 5.0
    phase_multipath_ratio: float = 0.01

    def __post_init__(self) -> None:
        if self.tau_s <= 0 or self.el0_rad <= 0:
            raise UserError("multipath tau_s and el0_rad must be > 0", field="gnss.multipath",
                            fix="use tau_s = 5 and el0 = 10 deg")
        if min(self.sigma_a_m, self.sigma_b_m, self.phase_multipath_ratio) < 0:
            raise UserError("multipath sigmas must be >= 0", field="gnss.multipath", fix="use a=0.15, b=0.53")


@dataclass(frozen=True, kw_only=True)
class TrackingConfig:
    """Signal strength, tracking-loop noise, NLOS echoes and carrier-phase continuity.

    Parameters
    ----------
    noise_enabled : bool
        Code (DLL), carrier (PLL) and Doppler thermal noise.
    cn0_zenith_dbhz, cn0_horizon_dbhz : float
        C/N0 of an unobstructed signal at 90 deg and 0 deg elevation.
    foliage_enabled : bool
        Apply the canopy loss (the world's per-area dB/m, default 0.5 dB/m: Weissberger's
        0.51 dB/m at L1 for paths up to 14 m; ~1 dB/m in dense leaf, Goldhirsh & Vogel 1998,
        ITU-R P.833; times the slant path), capped at ``foliage_max_db``.
    nlos_enabled : bool
        False: echo-only signals are not tracked (only clean LOS signals).
    echo_loss_db : float
        Extra C/N0 loss of a tracked reflection (reflection + LHCP rejection, 6-10 dB).
    track_threshold_dbhz : float
        Below this C/N0 the receiver loses lock (not tracked, next lock = new ambiguity).
    dll_spacing_chips, dll_bandwidth_hz, predetection_s : float
        ``d``, ``B_L``, ``T`` of the DLL jitter formula (narrow correlator 0.1 chip,
        carrier-aided 0.5 Hz loop: 0.26 m at 45 dB-Hz).
    pll_bandwidth_hz : float
        ``B_n`` of the PLL (15 Hz: 0.7 mm at 45 dB-Hz).
    doppler_sigma_mps_at_45dbhz : float
        Pseudorange-rate noise at 45 dB-Hz, scaled as ``sqrt(10^((45 - C/N0)/10))``.
    ambiguity_max_cycles : int
        New ambiguities are uniform integers in ``[-max, max]``.
    random_slip_rate_hz : float
        Poisson rate of random cycle slips per tracked satellite (0 = only on loss of lock).
    """

    noise_enabled: bool = True
    cn0_zenith_dbhz: float = 49.0
    cn0_horizon_dbhz: float = 36.0
    foliage_enabled: bool = True
    foliage_max_db: float = 30.0
    nlos_enabled: bool = True
    echo_loss_db: float = 8.0
    track_threshold_dbhz: float = 28.0
    dll_spacing_chips: float = 0.1
    dll_bandwidth_hz: float = 0.5
    predetection_s: float = 0.02
    pll_bandwidth_hz: float = 15.0
    doppler_sigma_mps_at_45dbhz: float = 0.03
    ambiguity_max_cycles: int = 1_000_000
    random_slip_rate_hz: float = 0.0

    def __post_init__(self) -> None:
        if not 0 < self.dll_spacing_chips <= 1:
            raise UserError("dll_spacing_chips must be in (0, 1]", field="gnss.tracking.dll_spacing_chips",
                            fix="use 0.1 (narrow correlator) or 1.0 (standard)")
        if min(self.dll_bandwidth_hz, self.predetection_s, self.pll_bandwidth_hz) <= 0:
            raise UserError("loop bandwidths and predetection time must be > 0", field="gnss.tracking",
                            fix="use dll_bandwidth_hz=0.5, pll_bandwidth_hz=15, predetection_s=0.02")
        if self.random_slip_rate_hz < 0 or self.foliage_max_db < 0 or self.echo_loss_db < 0:
            raise UserError("slip rate, foliage and echo losses must be >= 0", field="gnss.tracking",
                            fix="use non-negative values")

    @property
    def dll_correlation_time_s(self) -> float:
        """Correlation time of the DLL noise, ``1 / (4 B_L)`` (first-order loop)."""
        return 1.0 / (4.0 * self.dll_bandwidth_hz)


@dataclass(frozen=True, kw_only=True)
class GnssErrorConfig:
    """Every GNSS error model, each switchable on its own (``enabled`` flags in each part).

    How the defaults were chosen
    ----------------------------
    The paper's GPS-only relative errors in open areas are 0.12 m along / 0.17-0.19 m
    across (std, tables 3-4) with NovAtel OEM4 receivers. Everything common to receivers
    tens of metres apart (clock of the satellite, orbit, ionosphere, troposphere) cancels
    in single differences to < 1 mm here; what is left is receiver clock (estimated),
    multipath and noise. With the defaults, at 30 / 60 deg elevation (C/N0 42.5 / 47.3 dB-Hz),
    one receiver's code error is ``sqrt(0.18^2 + 0.35^2) ~ 0.39 m`` / ``sqrt(0.15^2 + 0.20^2) ~
    0.25 m`` (multipath, :func:`multipath_sigma_m`, + DLL noise, :func:`dll_jitter_m`), a single
    difference ~0.55 / 0.36 m (SDs of two static receivers over 1200 s: std 0.58 / 0.41 / 0.34 m at
    20-40 / 40-60 / 60-90 deg).
    Multipath decorrelates in 5 s
    and noise in 0.5 s, so a Doppler-aided filter with a memory of tens of seconds averages
    them down to the paper's 0.1-0.2 m (tables 3-4); what the defaults give is in
    :class:`MultipathConfig` ("What it gives"). (An earlier measurement of snapshot SD
    errors, 0.36-0.67 m, was made with the former 0.22 m / 20 s multipath.)
    """

    clock: ClockConfig = field(default_factory=ClockConfig)
    iono: IonosphereConfig = field(default_factory=IonosphereConfig)
    tropo: TroposphereConfig = field(default_factory=TroposphereConfig)
    satellite: SatelliteErrorConfig = field(default_factory=SatelliteErrorConfig)
    multipath: MultipathConfig = field(default_factory=MultipathConfig)
    tracking: TrackingConfig = field(default_factory=TrackingConfig)

    @classmethod
    def ideal(cls) -> GnssErrorConfig:
        """Everything off: pseudorange = range - sv clock (broadcast), phase = range/lambda + N."""
        return cls(
            clock=ClockConfig(enabled=False),
            iono=IonosphereConfig(enabled=False),
            tropo=TroposphereConfig(enabled=False),
            satellite=SatelliteErrorConfig(orbit_enabled=False, clock_enabled=False),
            multipath=MultipathConfig(enabled=False),
            tracking=TrackingConfig(noise_enabled=False, foliage_enabled=False, nlos_enabled=False),
        )


# --------------------------------------------------------------------------- functions


def multipath_sigma_m(el_rad: ArrayLike, cfg: MultipathConfig) -> F64:
    """Code multipath 1-sigma ``a + b exp(-E/E0)``, metres (Euler & Goad 1991 form)."""
    return cfg.sigma_a_m + cfg.sigma_b_m * np.exp(-np.asarray(el_rad, dtype=float) / cfg.el0_rad)


def cn0_dbhz(
    el_rad: ArrayLike, cfg: TrackingConfig, foliage_loss_db: ArrayLike = 0.0, echo: ArrayLike = False
) -> F64:
    """C/N0 (dB-Hz): ``zen - (zen - hor)(1 - sin E) - min(foliage_loss, max) - echo_loss``."""
    el = np.asarray(el_rad, dtype=float)
    c = cfg.cn0_zenith_dbhz - (cfg.cn0_zenith_dbhz - cfg.cn0_horizon_dbhz) * (1.0 - np.sin(np.clip(el, 0.0, None)))
    if cfg.foliage_enabled:
        c = c - np.minimum(np.asarray(foliage_loss_db, dtype=float), cfg.foliage_max_db)
    return c - np.where(np.asarray(echo, dtype=bool), cfg.echo_loss_db, 0.0)


def dll_jitter_m(cn0_dbhz_: ArrayLike, cfg: TrackingConfig) -> F64:
    """Code tracking thermal-noise 1-sigma, metres (Van Dierendonck et al. 1992).

    ``c T_chip sqrt(B_L d / (2 C/N0) (1 + 2 / ((2 - d) T C/N0)))``, C/N0 in Hz (linear).
    """
    cn0 = 10.0 ** (np.asarray(cn0_dbhz_, dtype=float) / 10.0)
    d, bl, t = cfg.dll_spacing_chips, cfg.dll_bandwidth_hz, cfg.predetection_s
    chips = np.sqrt(bl * d / (2.0 * cn0) * (1.0 + 2.0 / ((2.0 - d) * t * cn0)))
    return SPEED_OF_LIGHT_MPS * GPS_CA_CHIP_S * chips


def pll_jitter_m(cn0_dbhz_: ArrayLike, cfg: TrackingConfig) -> F64:
    """Carrier tracking thermal-noise 1-sigma, metres: ``(lambda/2pi) sqrt(B_n/CN0 (1 + 1/(2 T CN0)))``."""
    cn0 = 10.0 ** (np.asarray(cn0_dbhz_, dtype=float) / 10.0)
    rad = np.sqrt(cfg.pll_bandwidth_hz / cn0 * (1.0 + 1.0 / (2.0 * cfg.predetection_s * cn0)))
    return GPS_L1_WAVELENGTH_M / (2.0 * np.pi) * rad


def doppler_sigma_mps(cn0_dbhz_: ArrayLike, cfg: TrackingConfig) -> F64:
    """Pseudorange-rate noise 1-sigma, m/s: ``sigma_45 sqrt(10^((45 - C/N0)/10))``."""
    return cfg.doppler_sigma_mps_at_45dbhz * np.sqrt(10.0 ** ((45.0 - np.asarray(cn0_dbhz_, dtype=float)) / 10.0))


def gauss_markov_step(z: ArrayLike, dt_s: ArrayLike, tau_s: float, rng: np.random.Generator) -> F64:
    """Exact step of a unit-variance first-order Gauss-Markov process.

    ``z_{k+1} = exp(-dt/tau) z_k + sqrt(1 - exp(-2 dt/tau)) w_k``, ``w_k ~ N(0, 1)``: stationary
    variance 1 and autocorrelation ``exp(-|lag|/tau)`` (Brown & Hwang 2012 §2.9).
    """
    zz = np.asarray(z, dtype=float)
    phi = np.exp(-np.asarray(dt_s, dtype=float) / tau_s)
    return phi * zz + np.sqrt(1.0 - phi**2) * rng.standard_normal(zz.shape)
