"""Every measurement model's analytic sparse Jacobian row against central finite differences.

Error bound of a central difference with step h (stated per model below):
    |FD - f'| <= h^2 M3 / 6            (truncation; M3 bounds |f'''| along the coordinate)
               + 2 eps F / (2 h)        (rounding; F is the largest intermediate magnitude,
                                          e.g. the 2.2e7 m satellite range or the 6.4e6 m
                                          ECEF coordinates the relative position is added to)
The test tolerance is 4x that bound (the factor covers the few floating-point operations
between the intermediate and f). Bounds: |d^3 |d| / dt^3| <= 3 / rho^2 along any unit
direction; |d^3 atan2(E, N) / dt^3| <= 6 / r^3 (r = horizontal distance); models linear in
a state (clock, drift, bias, azimuth) have no truncation error.
"""

from __future__ import annotations

import numpy as np
import pytest

from v2v.estimation import models
from v2v.estimation.layout import StateLayout
from v2v.frames import geodetic_to_ecef, wrap_angle

EPS = np.finfo(float).eps

LAYOUT = StateLayout.build(
    lead="L", vehicles=["A", "B"], azimuth_vehicles=["L", "A"], uwb_pairs=[("L", "A"), ("A", "B")],
    azimuth_rates=True,  # the yaw-rate states enter no measurement: their columns must be 0
)
BASE = geodetic_to_ecef(np.radians(51.08), np.radians(-114.13), 1100.0)
GEO = models.GnssGeometry(base_ecef_m=BASE, base_vel_ecef_mps=np.array([3.0, -12.0, 5.0]))
SV_DIR = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
SV = BASE + 2.2e7 * SV_DIR
SV_VEL = np.array([2500.0, 1200.0, 800.0])
SV2 = SV + np.array([120.0, -40.0, 15.0])  # the same satellite computed at another transmit time


def _state() -> np.ndarray:
    x = np.zeros(LAYOUT.n)
    x[LAYOUT.position("A")] = [-14.0, -24.0, 0.4]
    x[LAYOUT.velocity("A")] = [0.5, -0.3, 0.05]
    x[LAYOUT.clock("A")] = 1234.5
    x[LAYOUT.drift("A")] = -56.7
    x[LAYOUT.position("B")] = [-26.0, -50.0, -0.3]
    x[LAYOUT.velocity("B")] = [-0.2, 0.6, -0.02]
    x[LAYOUT.clock("B")] = -321.0
    x[LAYOUT.drift("B")] = 12.0
    x[LAYOUT.azimuth("L")] = np.radians(210.0)
    x[LAYOUT.azimuth("A")] = np.radians(205.0)
    x[LAYOUT.azimuth_rate("L")] = np.radians(12.0)
    x[LAYOUT.azimuth_rate("A")] = np.radians(-7.0)
    x[LAYOUT.uwb_bias(("L", "A"))] = 0.3
    x[LAYOUT.uwb_scale(("L", "A"))] = 3.5e-3
    x[LAYOUT.uwb_bias(("A", "B"))] = -0.2
    x[LAYOUT.uwb_scale(("A", "B"))] = 4.7e-3
    return x


# name, f(x) -> Row, is_angle, F (largest intermediate magnitude), M3 (third-derivative bound)
RHO_AB = float(np.linalg.norm([12.0, 26.0, 0.7]))
CASES = [
    ("sd_pseudorange", lambda x: models.sd_pseudorange(x, LAYOUT, GEO, "A", SV, SV2), False, 2.2e7, 3 / 2.2e7**2),
    ("sd_pseudorange_pair", lambda x: models.sd_pseudorange_pair(x, LAYOUT, GEO, "A", "B", SV, SV2), False,
     2.2e7, 3 / 2.2e7**2),
    ("sd_doppler", lambda x: models.sd_doppler(x, LAYOUT, GEO, "B", SV, SV_VEL, SV2, SV_VEL), False,
     6.4e6 * 3e3 / 2.2e7, 3 * 3e3 / 2.2e7**3),
    ("uwb_lead_to_vehicle", lambda x: models.uwb_range(x, LAYOUT, "L", "A", use_bias_scale=False), False, 30.0,
     3 / 27.0**2),
    ("uwb_with_bias_scale", lambda x: models.uwb_range(x, LAYOUT, "A", "L"), False, 30.0, 3.1 / 27.0**2),
    ("uwb_two_followers_bias_scale", lambda x: models.uwb_range(x, LAYOUT, "A", "B"), False, 60.0,
     3.1 / RHO_AB**2),
    ("uwb_two_followers_no_states", lambda x: models.uwb_range(x, LAYOUT, "B", "A", use_bias_scale=False), False,
     60.0, 3 / RHO_AB**2),
    ("bearing_lead_known", lambda x: models.bearing(x, LAYOUT, "L", "B", np.radians(200.0)), True, 60.0,
     6 / 56.0**3),
    ("bearing_lead_estimated", lambda x: models.bearing(x, LAYOUT, "L", "A", None), True, 30.0, 6 / 27.0**3),
    ("bearing_follower_estimated", lambda x: models.bearing(x, LAYOUT, "A", "B", None), True, 60.0,
     6 / 28.0**3),
    ("bearing_follower_to_lead_known", lambda x: models.bearing(x, LAYOUT, "B", "L", 0.3), True, 60.0,
     6 / 56.0**3),
]

STEP = 1e-3  # m, m/s, m, m/s, rad for azimuths, m for bias; scale factor uses 1e-6 (below)


@pytest.mark.parametrize("name,fun,is_angle,big,m3", CASES, ids=[c[0] for c in CASES])
def test_jacobian_matches_central_difference(name, fun, is_angle, big, m3):
    x = _state()
    row = fun(x)
    analytic = models.dense_row(row, LAYOUT.n)[0]
    assert len(set(row.idx.tolist())) == len(row.idx), "sparse row has duplicate indices"
    for j in range(LAYOUT.n):
        h = 1e-6 if j in (LAYOUT.uwb_scale(("L", "A")), LAYOUT.uwb_scale(("A", "B"))) else STEP
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        diff = fun(xp).h - fun(xm).h
        if is_angle:
            diff = float(wrap_angle(diff))
        fd = diff / (2 * h)
        # the scale factor multiplies rho: its "third derivative" along s is 0, rounding uses F
        tol = 4.0 * (h * h * m3 / 6.0 + EPS * big / h) + 1e-12
        assert abs(fd - analytic[j]) <= tol, f"{name}: state {j}: FD {fd!r} vs analytic {analytic[j]!r} (tol {tol:.2e})"


def test_rows_touch_only_their_blocks():
    """Sparsity: a row names only the blocks its model involves (<= 2 vehicles + extras)."""
    x = _state()
    row = models.uwb_range(x, LAYOUT, "L", "A")
    allowed = set(range(LAYOUT.position("A").start, LAYOUT.position("A").stop)) | {
        LAYOUT.uwb_bias(("L", "A")), LAYOUT.uwb_scale(("L", "A"))}
    assert set(row.idx.tolist()) == allowed


def test_bearing_residual_wraps_at_pi():
    """The bearing owns its residual: +-pi crossings give the short way round."""
    assert models.bearing_residual(np.pi - 0.01, -np.pi + 0.01) == pytest.approx(-0.02, abs=1e-12)
    assert models.bearing_residual(-np.pi + 0.01, np.pi - 0.01) == pytest.approx(0.02, abs=1e-12)
    assert models.bearing_residual(np.pi, -np.pi) == pytest.approx(0.0, abs=1e-12)
