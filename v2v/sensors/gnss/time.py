"""GPS time: GPS seconds, weeks, and conversions to and from UTC.

**GPS seconds** (``t_gps_s``) count SI seconds of GPS time since the GPS epoch
1980-01-06 00:00:00 UTC (= 00:00:00 GPS), continuously: no week rollover, no leap
seconds. GPS time runs ahead of UTC by the number of leap seconds inserted since 1980
(18 s since 2017-01-01).

Two kinds of calendar date are handled and must not be confused:

* a **UTC** date (what a user writes in a scenario): :func:`utc_to_gps_s` adds the leap
  seconds;
* a **GPS-time** calendar date (RINEX navigation epochs TOC, SP3 epochs with time system
  ``GPS``): :func:`gps_calendar_to_gps_s`, no leap seconds. Treating a RINEX epoch as UTC
  shifts every orbit by 18 s (~ 70 km): gnss_lib_py issue #180.

References
----------
IS-GPS-200 section 20.3.3.5.2.4 (UTC and GPS time); IERS Bulletin C (leap seconds).
"""

from __future__ import annotations

import bisect
from datetime import UTC, datetime, timedelta

import numpy as np
from numpy.typing import ArrayLike, NDArray

from v2v.errors import UserError

GPS_EPOCH = datetime(1980, 1, 6, tzinfo=UTC)
GPS_WEEK_S = 604_800
SECONDS_PER_DAY = 86_400

# UTC instants at which GPS - UTC increased by one second (IERS Bulletin C). The value is
# GPS - UTC from that instant on (TAI - UTC - 19 s).
_LEAP_TABLE: tuple[tuple[datetime, int], ...] = tuple(
    (datetime(y, m, 1, tzinfo=UTC), n)
    for (y, m, n) in (
        (1981, 7, 1),
        (1982, 7, 2),
        (1983, 7, 3),
        (1985, 7, 4),
        (1988, 1, 5),
        (1990, 1, 6),
        (1991, 1, 7),
        (1992, 7, 8),
        (1993, 7, 9),
        (1994, 7, 10),
        (1996, 1, 11),
        (1997, 7, 12),
        (1999, 1, 13),
        (2006, 1, 14),
        (2009, 1, 15),
        (2012, 7, 16),
        (2015, 7, 17),
        (2017, 1, 18),
    )
)
_LEAP_UTC = [d for d, _ in _LEAP_TABLE]
LATEST_LEAP_SECONDS = _LEAP_TABLE[-1][1]


def _as_utc(dt: datetime, what: str) -> datetime:
    """Naive datetimes are taken as UTC; aware ones are converted to UTC."""
    dt = dt.replace(tzinfo=UTC) if dt.tzinfo is None else dt.astimezone(UTC)
    if dt < GPS_EPOCH:
        raise UserError(
            f"{dt.isoformat()} is before the GPS epoch 1980-01-06",
            field=what,
            fix="give a date after 1980-01-06",
        )
    return dt


def leap_seconds(utc: datetime) -> int:
    """GPS - UTC in seconds at a UTC instant (0 before 1981-07-01, 18 since 2017-01-01)."""
    u = _as_utc(utc, "time")
    i = bisect.bisect_right(_LEAP_UTC, u)
    return 0 if i == 0 else _LEAP_TABLE[i - 1][1]


def _seconds_since_epoch(dt: datetime) -> float:
    d = dt - GPS_EPOCH
    return d.days * SECONDS_PER_DAY + d.seconds + d.microseconds * 1e-6


def utc_to_gps_s(utc: datetime) -> float:
    """UTC datetime -> GPS seconds: calendar seconds since 1980-01-06 + leap seconds.

    A naive ``datetime`` is taken as UTC. E.g. 2021-04-28 17:59:42 UTC -> 2021-04-28
    18:00:00 GPS (18 leap seconds).
    """
    u = _as_utc(utc, "utc")
    return _seconds_since_epoch(u) + leap_seconds(u)


def gps_s_to_utc(t_gps_s: float) -> datetime:
    """GPS seconds -> timezone-aware UTC datetime (inverse of :func:`utc_to_gps_s`).

    Instants inside an inserted leap second map onto the following second (datetime has
    no 23:59:60).
    """
    cal = GPS_EPOCH + timedelta(seconds=float(t_gps_s))  # GPS calendar time
    # GPS - UTC at this instant: try each table value, keep the consistent one.
    for i in range(len(_LEAP_TABLE), -1, -1):
        n = 0 if i == 0 else _LEAP_TABLE[i - 1][1]
        utc = cal - timedelta(seconds=n)
        if i == 0 or utc >= _LEAP_UTC[i - 1]:
            return utc
    raise AssertionError("unreachable")  # pragma: no cover


def gps_calendar_to_gps_s(
    year: int, month: int, day: int, hour: int = 0, minute: int = 0, second: float = 0.0
) -> float:
    """A calendar date **in the GPS time scale** (RINEX TOC, SP3 epochs) -> GPS seconds.

    No leap seconds are applied: GPS-time calendar dates count SI seconds from the epoch.
    """
    try:
        d = datetime(year, month, day, hour, minute, tzinfo=UTC)
    except ValueError as exc:
        raise UserError(
            f"invalid date {year}-{month}-{day} {hour}:{minute}", field="epoch", fix="check the date fields"
        ) from exc
    return _seconds_since_epoch(d) + float(second)


def gps_s_to_gps_calendar(t_gps_s: float) -> datetime:
    """GPS seconds -> the calendar date in the GPS time scale (tz-naive, it is not UTC)."""
    return (GPS_EPOCH + timedelta(seconds=float(t_gps_s))).replace(tzinfo=None)


def gps_week_sow(t_gps_s: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
    """GPS seconds -> (full GPS week number, seconds of week in [0, 604800))."""
    t = np.asarray(t_gps_s, dtype=float)
    week = np.floor(t / GPS_WEEK_S).astype(np.int64)
    return week, t - week * float(GPS_WEEK_S)


def gps_s_from_week_sow(week: ArrayLike, sow_s: ArrayLike) -> NDArray[np.float64]:
    """(full GPS week, seconds of week) -> GPS seconds."""
    return np.asarray(week, dtype=float) * GPS_WEEK_S + np.asarray(sow_s, dtype=float)
