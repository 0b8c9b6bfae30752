"""RINEX 2.x / 3.x GPS navigation files -> :class:`BroadcastEphemeris`.

Reads the GPS records ('N' files of RINEX 2.x; 'N' files of RINEX 3.x/3.05 with system
'G' or 'M', other systems' records are skipped). Numbers may use the Fortran ``D``
exponent. Every record is kept (merged ``brdc`` files hold several per PRN); at a query
time each PRN uses the record whose TOE is nearest, if within the fit interval
``|t - toe| <= 2 h`` (IS-GPS-200 20.3.4.4: the 4-hour curve fit of nominal uploads).

Validity policy
---------------
* a time outside :meth:`BroadcastEphemeris.validity` (before the first record's TOE - 2 h
  or after the last record's TOE + 2 h) raises :class:`~v2v.errors.UserError`: the
  scenario's date does not match the navigation file, and nothing sensible can be
  simulated;
* inside that span, a PRN without a record within +-2 h (a satellite missing from the
  file, or a gap) gets ``healthy=False`` and NaN position/velocity/clock;
* a record with a non-zero SV health word gives its computed state with ``healthy=False``.

Record layout (RINEX 2.11 table A4 / RINEX 3.05 table A8): epoch line with TOC and
``af0 af1 af2``; then seven "broadcast orbit" lines of four values:
``IODE Crs dn M0 / Cuc e Cus sqrtA / Toe Cic OMEGA0 Cis / i0 Crc omega OMEGADOT /
IDOT L2codes week L2Pflag / accuracy health TGD IODC / t_tx fit``.
The week in the record is the continuous GPS week of TOE; TOC is in GPS time.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from v2v.errors import UserError
from v2v.sensors.gnss.ephemeris import GPS_WEEK_S, KeplerElements, SvStates, kepler_states
from v2v.sensors.gnss.time import gps_calendar_to_gps_s, gps_s_to_utc

FIT_HALF_INTERVAL_S = 7200.0  # +-2 h around TOE
_FIX = "give a RINEX 2.x or 3.x GPS navigation file (e.g. brdcDDD0.YYn or *_GN.rnx)"
_FIELD = "sensors.gnss.ephemeris (or --rinex)"
# Lines per record for each RINEX 3 system (epoch line + broadcast-orbit lines).
_LINES_PER_RECORD = {"G": 8, "E": 8, "C": 8, "J": 8, "I": 8, "R": 4, "S": 4}


def _utc(t_gps_s: float) -> str:
    return gps_s_to_utc(t_gps_s).strftime("%Y-%m-%d %H:%M:%S UTC")


def _err(path: Path, lineno: int, msg: str) -> UserError:
    return UserError(f"{path}, line {lineno}: {msg}", field=_FIELD, fix=_FIX)


def _num(text: str, path: Path, lineno: int) -> float:
    s = text.strip().replace("D", "E").replace("d", "e")
    if not s:
        return 0.0  # RINEX allows blank trailing fields (e.g. fit interval)
    try:
        return float(s)
    except ValueError:
        raise _err(path, lineno, f"cannot read the number {text.strip()!r}") from None


def _fields(line: str, start: int, count: int, path: Path, lineno: int) -> list[float]:
    """``count`` D19.12 fields starting at column ``start`` (0-based)."""
    return [_num(line[start + 19 * k : start + 19 * (k + 1)], path, lineno) for k in range(count)]


@dataclass(frozen=True, kw_only=True)
class NavHeader:
    """What the header says: version, file type/system, leap seconds (GPS - UTC) if given."""

    version: float
    leap_seconds: int | None


def _read_header(lines: list[str], path: Path) -> tuple[NavHeader, int]:
    if not lines:
        raise _err(path, 1, "the file is empty")
    first = lines[0]
    if "RINEX VERSION / TYPE" not in first:
        raise _err(path, 1, "no 'RINEX VERSION / TYPE' header line: not a RINEX file")
    try:
        version = float(first[:9])
    except ValueError:
        raise _err(path, 1, f"cannot read the RINEX version {first[:9].strip()!r}") from None
    ftype = first[20:21].upper()
    system = first[40:41].upper()
    if version >= 4.0 or version < 2.0:
        raise _err(path, 1, f"RINEX version {version} is not supported (2.x and 3.x are)")
    if version < 3.0:
        if ftype != "N":
            raise _err(path, 1, f"file type {ftype!r} is not a GPS navigation file ('N')")
    elif ftype != "N" or system not in ("G", "M", " ", ""):
        raise _err(path, 1, f"file type {ftype!r} / system {system!r} is not GPS navigation data")
    leap: int | None = None
    for i, line in enumerate(lines):
        label = line[60:].strip()
        if label == "LEAP SECONDS":
            try:
                leap = int(line[:6])
            except ValueError:
                raise _err(path, i + 1, "cannot read LEAP SECONDS") from None
        if label == "END OF HEADER":
            return NavHeader(version=version, leap_seconds=leap), i + 1
    raise _err(path, len(lines), "no 'END OF HEADER' line")


def _epoch_v2(line: str, path: Path, lineno: int) -> tuple[int, float]:
    try:
        prn = int(line[0:2])
        yy, mo, dd, hh, mi = (int(line[k : k + 3]) for k in (2, 5, 8, 11, 14))
        sec = float(line[17:22])
    except ValueError:
        raise _err(path, lineno, "cannot read the PRN / epoch of a navigation record") from None
    year = yy + (2000 if yy < 80 else 1900)
    return prn, gps_calendar_to_gps_s(year, mo, dd, hh, mi, sec)


def _epoch_v3(line: str, path: Path, lineno: int) -> tuple[int, float]:
    try:
        prn = int(line[1:3])
        year = int(line[4:8])
        mo, dd, hh, mi, ss = (int(line[k : k + 3]) for k in (8, 11, 14, 17, 20))
    except ValueError:
        raise _err(path, lineno, "cannot read the satellite / epoch of a navigation record") from None
    return prn, gps_calendar_to_gps_s(year, mo, dd, hh, mi, float(ss))


def read_rinex_nav(path: str | Path) -> BroadcastEphemeris:
    """Read a RINEX 2.x/3.x GPS navigation file.

    Raises
    ------
    UserError
        The file is missing, not RINEX navigation data, or a record is truncated or has an
        unreadable number; the message names the file and line.
    """
    p = Path(path)
    try:
        text = p.read_text(encoding="ascii", errors="replace")
    except OSError as exc:
        raise UserError(f"cannot read {p}: {exc.strerror}", field=_FIELD, fix=_FIX) from None
    lines = text.splitlines()
    header, i = _read_header(lines, p)
    v3 = header.version >= 3.0
    col0 = 4 if v3 else 3  # first column of broadcast-orbit fields
    rows: list[list[float]] = []
    n = len(lines)
    while i < n:
        line = lines[i]
        if not line.strip():
            i += 1
            continue
        nlines = 8
        if v3:
            system = line[0:1]
            if system not in _LINES_PER_RECORD:
                raise _err(p, i + 1, f"unknown satellite system {system!r} at the start of a record")
            nlines = _LINES_PER_RECORD[system]
            if system != "G":
                i += nlines
                continue
            prn, toc = _epoch_v3(line, p, i + 1)
            vals = _fields(line, 23, 3, p, i + 1)
        else:
            prn, toc = _epoch_v2(line, p, i + 1)
            vals = _fields(line, 22, 3, p, i + 1)
        if i + nlines > n:
            raise _err(p, n, f"truncated navigation record for PRN {prn} starting at line {i + 1}")
        for k in range(1, 8):
            orbit_line = lines[i + k]
            count = 2 if k == 7 else 4
            if len(orbit_line.rstrip()) <= col0 or orbit_line[:col0].strip():
                raise _err(p, i + k + 1, f"broadcast-orbit line {k} of PRN {prn} is missing or misplaced")
            vals.extend(_fields(orbit_line, col0, count, p, i + k + 1))
        rows.append([float(prn), toc, *vals, float(i + 1)])
        i += nlines
    if not rows:
        raise _err(p, n, "no GPS navigation records")
    return BroadcastEphemeris(_elements_from_rows(np.array(rows)), source=str(p))


def _elements_from_rows(r: np.ndarray) -> KeplerElements:
    # columns: prn, toc, af0, af1, af2, then 7 x 4 orbit values (last line: 2), lineno
    c = {
        name: r[:, k]
        for k, name in enumerate(
            "prn toc af0 af1 af2 iode crs dn m0 cuc e cus sqrta toe cic om0 cis i0 crc omega omdot "
            "idot l2 week l2p acc health tgd iodc ttx fit".split()
        )
    }
    toe_abs = c["week"] * GPS_WEEK_S + c["toe"]
    # Some writers give the week of TOC when TOE is in the next/previous week: take the
    # TOE instant nearest the TOC.
    toe_abs = toe_abs - GPS_WEEK_S * np.round((toe_abs - c["toc"]) / GPS_WEEK_S)
    return KeplerElements(
        prn=c["prn"].astype(np.int64),
        sqrt_a_sqrtm=c["sqrta"],
        e=c["e"],
        i0_rad=c["i0"],
        omega0_rad=c["om0"],
        omega_rad=c["omega"],
        m0_rad=c["m0"],
        delta_n_radps=c["dn"],
        idot_radps=c["idot"],
        omega_dot_radps=c["omdot"],
        cuc_rad=c["cuc"],
        cus_rad=c["cus"],
        crc_m=c["crc"],
        crs_m=c["crs"],
        cic_rad=c["cic"],
        cis_rad=c["cis"],
        toe_gps_s=toe_abs,
        toe_sow_s=c["toe"],
        toc_gps_s=c["toc"],
        af0_s=c["af0"],
        af1_sps=c["af1"],
        af2_sps2=c["af2"],
        tgd_s=c["tgd"],
        health=c["health"].astype(np.int64),
    )


class BroadcastEphemeris:
    """GPS broadcast ephemeris records; implements :class:`~v2v.sensors.gnss.ephemeris.Ephemeris`.

    Parameters
    ----------
    elements : all records (any order, several per PRN).
    source : the file name, for error messages.
    fit_half_interval_s : a record is used for ``|t - toe| <= fit_half_interval_s``.
    """

    def __init__(
        self, elements: KeplerElements, *, source: str = "", fit_half_interval_s: float = FIT_HALF_INTERVAL_S
    ):
        order = np.lexsort((elements.toe_gps_s, elements.prn))
        self.elements = elements.take(order)
        self.source = source
        self.fit_half_interval_s = float(fit_half_interval_s)
        self._prns, starts = np.unique(self.elements.prn, return_index=True)
        ends = np.append(starts[1:], self.elements.m)
        self._ranges = {int(p): (int(s), int(e)) for p, s, e in zip(self._prns, starts, ends, strict=True)}

    def prns(self) -> np.ndarray:
        return self._prns.copy()

    def validity(self) -> tuple[float, float]:
        toe = self.elements.toe_gps_s
        return float(toe.min() - self.fit_half_interval_s), float(toe.max() + self.fit_half_interval_s)

    def select(self, prn: ArrayLike, t_gps_s: ArrayLike) -> np.ndarray:
        """Index (into ``self.elements``) of the record with the TOE nearest ``t`` per query; -1 if none within the fit interval."""
        prn_arr = np.atleast_1d(np.asarray(prn, dtype=np.int64))
        t = np.broadcast_to(np.asarray(t_gps_s, dtype=float), prn_arr.shape)
        idx = np.full(prn_arr.shape, -1, dtype=np.int64)
        toe_all = self.elements.toe_gps_s
        for p in np.unique(prn_arr):
            rng = self._ranges.get(int(p))
            if rng is None:
                continue
            s, e = rng
            sel = prn_arr == p
            toe = toe_all[s:e]
            k = np.clip(np.searchsorted(toe, t[sel]), 1, max(e - s - 1, 1))
            lo = np.maximum(k - 1, 0)
            hi = np.minimum(k, e - s - 1)
            best = np.where(np.abs(t[sel] - toe[lo]) <= np.abs(toe[hi] - t[sel]), lo, hi)
            ok = np.abs(t[sel] - toe[best]) <= self.fit_half_interval_s
            idx[sel] = np.where(ok, best + s, -1)
        return idx

    def sv_states(self, prn: ArrayLike, t_gps_s: float | ArrayLike) -> SvStates:
        """States at GPS time(s) ``t`` in the ECEF frame at ``t`` (see the module's validity policy).

        Raises
        ------
        UserError
            if any ``t`` is outside :meth:`validity`.
        """
        prn_arr = np.atleast_1d(np.asarray(prn, dtype=np.int64))
        t = np.broadcast_to(np.asarray(t_gps_s, dtype=float), prn_arr.shape)
        t0, t1 = self.validity()
        bad = ~((t >= t0) & (t <= t1))
        if np.any(bad):
            tb = float(t[bad][0])
            raise UserError(
                f"{_utc(tb)} (GPS {tb:.1f} s) is outside the navigation file {self.source or '(in memory)'}, "
                f"which covers {_utc(t0)} to {_utc(t1)}",
                field="start_utc",
                fix="choose a start time and duration inside the file's span or give the matching day's file",
            )
        idx = self.select(prn_arr, t)
        have = idx >= 0
        n = prn_arr.shape[0]
        pos = np.full((n, 3), np.nan)
        vel = np.full((n, 3), np.nan)
        clk = np.full(n, np.nan)
        drift = np.full(n, np.nan)
        healthy = np.zeros(n, dtype=bool)
        if np.any(have):
            el = self.elements.take(idx[have])
            p, v, c, d, _ = kepler_states(el, t[have])
            pos[have], vel[have], clk[have], drift[have] = p, v, c, d
            healthy[have] = el.health == 0
        return SvStates(
            prn=prn_arr.copy(),
            pos_ecef_m=pos,
            vel_ecef_mps=vel,
            clock_bias_s=clk,
            clock_drift_sps=drift,
            healthy=healthy,
        )
