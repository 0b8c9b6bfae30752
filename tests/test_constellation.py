"""Built-in nominal constellation: SPS PS slot tables (baseline 24, expandable 27).

Checks orbit geometry against the SPS PS reference orbit (six planes 60 deg apart, 55 deg
inclination, circular at 26 559.7 km) and the visible-satellite count against the
spherical-cap fraction of the orbit shell. Deterministic (no random numbers).
"""

from __future__ import annotations

from datetime import datetime

import numpy as np
import pytest

from v2v.errors import UserError
from v2v.sensors.gnss.constellation import (
    SLOTS_BASELINE,
    SLOTS_EXPANDABLE,
    NominalConstellation,
    j2_node_rate_radps,
)
from v2v.sensors.gnss.ephemeris import OMEGA_E_RADPS
from v2v.sensors.gnss.sky import sky_view
from v2v.sensors.gnss.time import utc_to_gps_s

T0 = utc_to_gps_s(datetime(2021, 4, 28, 12))
R_ORBIT_M = 26_559_700.0
R_EARTH_M = 6_378_137.0


def _planes(nc: NominalConstellation, t: float) -> np.ndarray:
    """Node longitude (deg) of each satellite's orbit plane, from r x v in the frame turning
    with the planes (rate OMEGA_E - Omega_dot), and the plane inclinations (deg)."""
    st = nc.sv_states(nc.prns(), t)
    w_plane = np.array([0.0, 0.0, OMEGA_E_RADPS - j2_node_rate_radps()])
    h = np.cross(st.pos_ecef_m, st.vel_ecef_mps + np.cross(w_plane, st.pos_ecef_m))
    node = np.degrees(np.arctan2(h[:, 0], -h[:, 1])) % 360.0
    inc = np.degrees(np.arccos(h[:, 2] / np.linalg.norm(h, axis=1)))
    return node, inc


@pytest.mark.parametrize(("slots", "n", "per_plane"), [
    ("baseline24", 24, [4, 4, 4, 4, 4, 4]),     # SPS PS Table 3.1-1
    ("expandable27", 27, [4, 5, 4, 5, 4, 5]),   # Table 3.1-2: B1, D2, F2 each split fore/aft
])
def test_slot_tables_geometry(slots, n, per_plane):
    nc = NominalConstellation(T0, slots=slots)
    assert nc.prns().tolist() == list(range(1, n + 1)) and len(nc.slot_names) == n
    st = nc.sv_states(nc.prns(), T0 + 3600.0)
    # circular reference orbit: radius = a to float rounding
    np.testing.assert_allclose(np.linalg.norm(st.pos_ecef_m, axis=1), R_ORBIT_M, rtol=0, atol=1e-4)
    node, inc = _planes(nc, T0 + 3600.0)
    np.testing.assert_allclose(inc, 55.0, atol=1e-9)  # arccos rounding near 55 deg
    # six planes 60 deg apart (A = plane 0 at the smallest RAAN of the table: A is 272.847 deg,
    # so order the planes from A's node)
    a_node = node[nc.slot_names.index("A1")]
    k = (node - a_node) % 360.0 / 60.0
    np.testing.assert_allclose(k, np.round(k), atol=1e-6)
    counts = np.bincount(np.round(k).astype(int) % 6, minlength=6)
    assert counts.tolist() == per_plane


def test_expanded_slots_straddle_their_baseline_slot():
    """Each expandable slot (B1, D2, F2) becomes a fore and an aft slot in the same plane, ahead
    of and behind the baseline position along the orbit, and the other 21 slots are unchanged."""
    base = {s: (raan, u) for s, raan, u in SLOTS_BASELINE}
    exp = {s: (raan, u) for s, raan, u in SLOTS_EXPANDABLE}
    assert len(exp) == 27 and {"B1", "D2", "F2"}.isdisjoint(exp)
    for s in base.keys() - {"B1", "D2", "F2"}:
        assert exp[s] == base[s]
    for s in ("B1", "D2", "F2"):
        fore, aft = exp[s + "F"], exp[s + "A"]
        assert fore[0] == aft[0] == base[s][0]
        ahead = (fore[1] - base[s][1] + 180.0) % 360.0 - 180.0
        behind = (base[s][1] - aft[1] + 180.0) % 360.0 - 180.0
        # fore ahead, aft behind, each within the 90 deg spacing of a 4-slot plane
        assert 0.0 < ahead < 45.0 and 0.0 < behind < 45.0, (s, ahead, behind)


def _mean_count(nc: NominalConstellation, sites, step_s: float = 900.0) -> float:
    c = [len(sky_view(np.radians(la), np.radians(lo), 0.0, T0 + k * step_s, nc, np.radians(10.0)))
         for la, lo in sites for k in range(int(86_400 // step_s))]
    return float(np.mean(c)), int(np.min(c))


def test_visible_count_follows_the_visible_cap():
    """Above a 10 deg mask a ground point sees the orbit shell inside an Earth-central half-angle
    lambda = 90 - E - asin(R_e cos E / a) = 66.3 deg, a cap of (1 - cos lambda)/2 = 29.9 % of the
    shell: N x 0.299 = 7.2 (24) and 8.1 (27) in view on average if the shell were uniformly
    populated. Six discrete 55 deg planes do not populate it uniformly (the count depends on
    the site's latitude and on where the planes cross), so the day averages at three
    mid-latitude sites (measured 6.75 and 7.63) are allowed +-0.6 around the uniform value.
    The expanded table must add about 3 x 0.299 = 0.9 satellites (measured 0.88)."""
    lam = np.pi / 2 - np.radians(10.0) - np.arcsin(R_EARTH_M * np.cos(np.radians(10.0)) / R_ORBIT_M)
    frac = (1.0 - np.cos(lam)) / 2.0
    assert frac == pytest.approx(0.299, abs=1e-3)
    sites = [(51.08, -114.13), (45.0, -75.0), (35.0, 139.0)]  # Calgary (the paper), Ottawa, Tokyo
    m24, min24 = _mean_count(NominalConstellation(T0 + 43_200.0, slots="baseline24"), sites)
    m27, min27 = _mean_count(NominalConstellation(T0 + 43_200.0), sites)
    print(f"mean in view: 24 slots {m24:.2f} (min {min24}), 27 slots {m27:.2f} (min {min27})")
    assert abs(m24 - 24 * frac) < 0.6 and abs(m27 - 27 * frac) < 0.6
    assert 0.5 < m27 - m24 < 1.3
    assert min27 >= 5


def test_unknown_slot_table_is_a_user_error():
    with pytest.raises(UserError, match="slot table"):
        NominalConstellation(T0, slots="31")


def test_default_world_uses_the_27_slot_sky():
    """The default scenario (ephemeris = "nominal") gets the expanded constellation."""
    from v2v.config.scenario import load_scenario
    from v2v.pipeline import build_ephemeris

    eph = build_ephemeris(load_scenario(None, ["solutions=[]"]), T0)
    assert eph.prns().size == 27
