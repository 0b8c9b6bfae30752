"""The sky of a run: the built-in nominal constellation or a RINEX navigation file.

Scenario field ``sensors.gnss.ephemeris``: ``"nominal"`` (:class:`~v2v.sensors.gnss.constellation.
NominalConstellation` at the run's start) or the path of a RINEX 2/3 GPS navigation file
(:func:`~v2v.sensors.gnss.rinex.read_rinex_nav`), which must span the whole run. Light on
imports (no filter, no compiled kernels), so ``v2v scenario check`` and a sweep's study check can
resolve it without loading the rest of the simulator.
"""

from __future__ import annotations

from pathlib import Path

from v2v.errors import UserError, not_a_file
from v2v.sensors.gnss.ephemeris import Ephemeris


def ephemeris_source(ephemeris: str, gps_start_s: float, duration_s: float) -> Ephemeris:
    """The ephemeris a run of ``duration_s`` from GPS time ``gps_start_s`` uses: ``ephemeris`` is
    ``"nominal"`` or a RINEX nav file path (a relative path is relative to the working directory;
    :func:`v2v.run.run_scenario` makes it absolute first). UserError if the file is missing or
    unreadable, or if the run leaves the file's validity span."""
    if ephemeris == "nominal":
        from v2v.sensors.gnss.constellation import NominalConstellation

        return NominalConstellation(gps_start_s)
    from v2v.sensors.gnss.rinex import read_rinex_nav

    path = Path(ephemeris)
    why = not_a_file(path) if ephemeris.strip() else "is empty"
    if why:
        raise UserError(f"RINEX navigation file {ephemeris!r} {why}", field="sensors.gnss.ephemeris",
                        fix='give an existing RINEX 2/3 nav file, or "nominal"')
    eph = read_rinex_nav(path)
    lo, hi = eph.validity()
    end = gps_start_s + duration_s
    if gps_start_s < lo or end > hi:
        from v2v.sensors.gnss.time import gps_s_to_utc

        span = f"the ephemeris ({gps_s_to_utc(lo):%Y-%m-%d %H:%M} to {gps_s_to_utc(hi):%Y-%m-%d %H:%M} UTC)"
        run = f"the run ({gps_s_to_utc(gps_start_s):%Y-%m-%d %H:%M:%S} UTC + {duration_s:.0f} s)"
        if lo <= gps_start_s <= hi:  # it starts inside and runs past the end: its length is what is wrong
            raise UserError(f"{run} ends at {gps_s_to_utc(end):%Y-%m-%d %H:%M:%S} UTC, after the end of {span}",
                            field="duration_s", fix=f"give duration_s <= {hi - gps_start_s:.0f} s, or an earlier "
                            "start_utc")
        raise UserError(f"{run} starts outside {span}", field="start_utc",
                        fix="pick a start time inside the navigation file's span")
    return eph
