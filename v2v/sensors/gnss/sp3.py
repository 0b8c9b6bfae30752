"""SP3 (versions a-d) precise orbit files: position records only.

Epoch lines ``*  YYYY MM DD hh mm ss.ssssssss`` and position records
``P<sv> x_km y_km z_km clock_us``. Positions are converted from km to metres; a
coordinate of exactly 0.000000 (or a clock of 999999.999999) marks a missing value and
becomes NaN. Epochs are taken in the file's time system, which must be GPS (the ``%c``
line; SP3-a/b files have none and are GPS by definition).

Reference: Hilla, S. (2016), *The Extended Standard Product 3 Orbit Format (SP3-d)*, IGS.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from v2v.errors import UserError
from v2v.sensors.gnss.time import gps_calendar_to_gps_s

_FIELD = "sp3_file"
_FIX = "give an SP3-c or SP3-d orbit file in GPS time"


@dataclass(frozen=True, kw_only=True)
class Sp3Orbits:
    """Precise positions of ``n`` satellites at ``k`` epochs.

    Attributes
    ----------
    t_gps_s : (k,) epochs, GPS seconds.
    sv : (n,) satellite ids as in the file (``'G01'``, ``'R05'``...).
    pos_ecef_m : (k, n, 3) centre-of-mass positions, ITRF/IGS frame ECEF, metres (NaN = missing).
    clock_bias_s : (k, n) satellite clock offsets, seconds (NaN = missing).
    """

    t_gps_s: NDArray[np.float64]
    sv: tuple[str, ...]
    pos_ecef_m: NDArray[np.float64]
    clock_bias_s: NDArray[np.float64]

    def gps_prns(self) -> NDArray[np.int64]:
        """PRNs of the GPS satellites in the file."""
        return np.array([int(s[1:]) for s in self.sv if s[0] == "G"], dtype=np.int64)

    def gps_positions(self, prn: int) -> NDArray[np.float64]:
        """(k, 3) positions of GPS satellite ``prn``."""
        return self.pos_ecef_m[:, self.sv.index(f"G{prn:02d}"), :]


def read_sp3(path: str | Path) -> Sp3Orbits:
    """Read an SP3 file's position records. Raises :class:`UserError` naming file and line."""
    p = Path(path)
    try:
        lines = p.read_text(encoding="ascii", errors="replace").splitlines()
    except OSError as exc:
        raise UserError(f"cannot read {p}: {exc.strerror}", field=_FIELD, fix=_FIX) from None

    def err(lineno: int, msg: str) -> UserError:
        return UserError(f"{p}, line {lineno}: {msg}", field=_FIELD, fix=_FIX)

    if not lines or not lines[0].startswith("#") or lines[0][1:2] not in "abcd" or len(lines[0]) < 2:
        raise err(1, "not an SP3 file (the first line must start with '#a'..'#d')")
    epochs: list[float] = []
    recs: dict[str, dict[int, tuple[float, float, float, float]]] = {}
    first_pct_c = True
    for i, line in enumerate(lines, start=1):
        if line.startswith("%c") and first_pct_c:
            first_pct_c = False
            tsys = line[9:12].strip()
            if tsys not in ("GPS", "ccc", ""):
                raise err(i, f"time system {tsys!r} is not supported (GPS only)")
        elif line.startswith("* "):
            try:
                year, mo, dd, hh, mi = (int(x) for x in line[2:].split()[:5])
                sec = float(line[2:].split()[5])
            except (ValueError, IndexError):
                raise err(i, "cannot read the epoch line") from None
            epochs.append(gps_calendar_to_gps_s(year, mo, dd, hh, mi, sec))
        elif line.startswith("P") and epochs:
            sv = line[1:4].replace(" ", "0")
            try:
                x, y, z = (float(line[4 + 14 * k : 18 + 14 * k]) for k in range(3))
                clk_txt = line[46:60].strip()
                clk_us = float(clk_txt) if clk_txt else 999999.999999
            except ValueError:
                raise err(i, f"cannot read the position record of {sv}") from None
            recs.setdefault(sv, {})[len(epochs) - 1] = (x, y, z, clk_us)
        elif line.startswith("EOF"):
            break
    if not epochs or not recs:
        raise err(len(lines), "no epochs with position records")
    sv_ids = tuple(sorted(recs))
    k, n = len(epochs), len(sv_ids)
    pos = np.full((k, n, 3), np.nan)
    clk = np.full((k, n), np.nan)
    for j, s in enumerate(sv_ids):
        for e, (x, y, z, c) in recs[s].items():
            if not (x == 0.0 and y == 0.0 and z == 0.0):
                pos[e, j] = (x * 1e3, y * 1e3, z * 1e3)
            if abs(c) < 999999.0:
                clk[e, j] = c * 1e-6
    return Sp3Orbits(t_gps_s=np.array(epochs), sv=sv_ids, pos_ecef_m=pos, clock_bias_s=clk)
