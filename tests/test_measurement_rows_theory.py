"""Measurement functions and Jacobian rows checked against the physics they model.

Unlike ``tests/test_jacobians.py`` (finite differences of the package's own ``h``) and
``tests/test_kernels.py`` (whole updates of the batch kernels), every reference here is
written out independently:

* the second-order terms' Hessians (:func:`kernels.range_hessian`, :func:`kernels.bearing_hessian`
  and their Python twins in the filter) against a central finite-difference Hessian of
  ``|d|`` and of the bearing ``atan2(E, N)`` (clockwise from north, Petovello et al. eq. 5);
* the SD rows (:func:`kernels.sd_pseudorange_rows`, :func:`kernels.sd_doppler_rows`,
  :class:`models.SdPseudorangeRows`, :class:`models.SdDopplerRows`) against the single
  difference of MacGougan (2009) eq. 3.2-3.3 (lead = reference receiver):
  ``P_v - P_lead = |sv_v - r_v| - |sv_lead - base| + c (dt_v - dt_lead)`` with the vehicle
  placed at its lead-relative ENU offset by pymap3d (``enu2ecef`` at the lead's geodetic
  position), and the SD pseudorange *rate* as the time derivative of those ranges (relative
  motion linear over +-tau) plus the relative clock drift;
* :func:`v2v.measmodels.bearing_jacobian` and :func:`v2v.measmodels.range_rate_jacobians`
  (the latter reaches test_jacobians only rotated into ENU, and the former not at all).

The GNSS references are evaluated in 60-digit ``decimal`` arithmetic from the exact binary
values of the float inputs: a difference of two 2.2e7 m ranges keeps only ~4e-9 m in double
(one ulp of 2.2e7), which would swamp a 1e-9 m comparison and any finite difference with a
step below a metre. Geometry: the lead at Calgary (51.08 N, 114.13 W, 1100 m), six GPS-like
satellites on the 26 560 km orbit radius (20 200 km altitude) in all directions from 10 to
80 deg elevation, baselines of tens of metres.
"""

from __future__ import annotations

import math
from decimal import Decimal, localcontext

import numpy as np
import pymap3d
import pytest

from v2v.estimation import kernels, models
from v2v.estimation.filter import _bearing_hessian, _range_hessian
from v2v.estimation.layout import StateLayout
from v2v.measmodels import bearing_jacobian, range_rate_jacobians

EPS = np.finfo(float).eps  # 2.2e-16

# ------------------------------------------------------------------ geometry (all through pymap3d)
LAT0, LON0, H0 = 51.08, -114.13, 1100.0  # deg, deg, m: the lead (base)
BASE = np.array(pymap3d.geodetic2ecef(LAT0, LON0, H0))
# ECEF -> ENU rotation: rows are the east, north and up unit vectors expressed in ECEF
ROT = np.array([pymap3d.enu2uvw(*axis, LAT0, LON0) for axis in np.eye(3)], dtype=float)
BASE_VEL = np.array(pymap3d.enu2uvw(20.0 * math.sin(math.radians(30.0)), 20.0 * math.cos(math.radians(30.0)),
                                    0.1, LAT0, LON0), dtype=float)  # lead driving 20 m/s at 30 deg azimuth

R_ORBIT = 26_560e3  # GPS orbit radius, m (20 200 km altitude)
V_ORBIT = math.sqrt(3.986004418e14 / R_ORBIT)  # circular speed, 3874 m/s
SKY = [(10.0, 80.0), (60.0, 25.0), (135.0, 45.0), (200.0, 15.0), (255.0, 55.0), (320.0, 30.0)]  # (az, el), deg
DT_LEAD_S = 1e-3  # the lead's receiver epoch differs by 1 ms: its satellite positions differ by ~4 m


def _satellites() -> tuple[np.ndarray, np.ndarray]:
    """ECEF positions on the orbit sphere at the (azimuth, elevation) seen from the lead, and
    velocities of orbital speed perpendicular to the radius (orbit planes inclined 55 deg)."""
    sv, svv = [], []
    for k, (az, el) in enumerate(SKY):
        a, e = math.radians(az), math.radians(el)
        w = np.array(pymap3d.enu2uvw(math.cos(e) * math.sin(a), math.cos(e) * math.cos(a), math.sin(e), LAT0, LON0))
        bw = float(BASE @ w)
        s = -bw + math.sqrt(bw * bw - float(BASE @ BASE) + R_ORBIT**2)  # |BASE + s w| = R_ORBIT
        pos = BASE + s * w
        raan, inc = math.radians(60.0 * k), math.radians(55.0)
        normal = np.array([math.sin(inc) * math.sin(raan), -math.sin(inc) * math.cos(raan), math.cos(inc)])
        vel = np.cross(normal, pos)
        sv.append(pos)
        svv.append(V_ORBIT * vel / np.linalg.norm(vel))
    return np.array(sv), np.array(svv)


SV, SVV = _satellites()
SV_LEAD = SV - SVV * DT_LEAD_S  # the same satellites computed for the lead's transmit times

# (relative ENU position m, relative ENU velocity m/s, relative clock m, relative drift m/s)
VEHICLES = {
    "behind_left": (np.array([-14.0, -24.0, 0.4]), np.array([0.5, -0.3, 0.05]), 1234.5, -56.7),
    "ahead_right": (np.array([35.5, 61.25, -1.1]), np.array([-1.2, 2.0, 0.0]), -321.0, 12.0),
}


# ------------------------------------------------------------------ independent references
def _dist(a, b) -> Decimal:
    """|a - b| in 60-digit decimal from the exact binary values of float 3-vectors."""
    with localcontext() as ctx:
        ctx.prec = 60
        return sum(((Decimal(float(x)) - Decimal(float(y))) ** 2 for x, y in zip(a, b, strict=True)),
                   Decimal(0)).sqrt()


TAU_S = Decimal("1e-4")


def _range_rate(r, v, s, s_vel) -> Decimal:
    """d/dt |s + s_vel t - (r + v t)| at t = 0, as a central difference over +-tau (decimal).

    Truncation tau^2 |rho'''| / 6 with |rho'''| <= 3 |dv|^3 / rho^2 ~ 5e-4 m/s^3 (|dv| < 4e3
    m/s, rho > 2e7 m): < 1e-12 m/s; 60-digit round-off is ~1e-52 m / tau, nil."""
    with localcontext() as ctx:
        ctx.prec = 60
        d = [Decimal(float(a)) - Decimal(float(b)) for a, b in zip(s, r, strict=True)]
        w = [Decimal(float(a)) - Decimal(float(b)) for a, b in zip(s_vel, v, strict=True)]
        plus = sum(((di + wi * TAU_S) ** 2 for di, wi in zip(d, w, strict=True)), Decimal(0)).sqrt()
        minus = sum(((di - wi * TAU_S) ** 2 for di, wi in zip(d, w, strict=True)), Decimal(0)).sqrt()
        return (plus - minus) / (2 * TAU_S)


def _vehicle_ecef(p_enu) -> np.ndarray:
    """The point at ENU offset ``p_enu`` from the lead (pymap3d; rounding < 1e-9 m: one
    rounding of the ~6.4e6 m coordinates, ulp 9.3e-10 m)."""
    return np.array(pymap3d.enu2ecef(*(float(c) for c in p_enu), LAT0, LON0, H0), dtype=float)


def _vehicle_vel(dv_enu) -> np.ndarray:
    return BASE_VEL + np.array(pymap3d.enu2uvw(*(float(c) for c in dv_enu), LAT0, LON0), dtype=float)


def _sd_pr_ref(p_enu, clk, o) -> Decimal:
    """MacGougan (2009) eq. 3.2: SD pseudorange of satellite ``o`` (vehicle minus lead)."""
    return _dist(SV[o], _vehicle_ecef(p_enu)) - _dist(SV_LEAD[o], BASE) + Decimal(float(clk))


def _sd_rate_ref(p_enu, dv_enu, drift, o) -> Decimal:
    """SD pseudorange rate of satellite ``o``: the vehicle's range rate minus the lead's plus the drift."""
    return (_range_rate(_vehicle_ecef(p_enu), _vehicle_vel(dv_enu), SV[o], SVV[o])
            - _range_rate(BASE, BASE_VEL, SV_LEAD[o], SVV[o]) + Decimal(float(drift)))


def _fd(f, x, i, step) -> float:
    """Central difference of a decimal-valued ``f`` along coordinate ``i``, divided by the step
    actually taken (``x_i +- step`` are rounded floats; their difference is exact)."""
    xp, xm = np.array(x, dtype=float), np.array(x, dtype=float)
    xp[i] += step
    xm[i] -= step
    return float((f(xp) - f(xm)) / Decimal(float(xp[i] - xm[i])))


# Step of the ENU position differences, 4 m. Truncation h^2 M3 / 6: M3 <= 3 / rho^2 = 7e-15 /m^2
# for a range, <= 15 |dv| / rho^3 = 6e-18 /(m^2 s) for a range rate: 2e-14 and 2e-17. Round-off:
# the decimal references are exact on their inputs, but pymap3d rounds the vehicle's ECEF
# position (< 1.6e-9 m over 3 coordinates) differently at x +- h: 2 * 1.6e-9 / (2 h) = 4e-10 for
# a range (O(1) entries), times |dv| / rho = 1.8e-4 /s for a range rate: 7e-14 /s.
STEP_P = 4.0
TOL_PR_POS = 2e-9  # ~4x the 4e-10 + 2e-14 above (the kernel's own -R u is exact to a few eps)
TOL_RATE_POS = 3e-13  # /s, ~4x the 7e-14 above (entries are ~1e-4 /s: 3e-9 relative)
# h is linear in velocity, clock and drift: the central difference is exact on the decimal
# reference up to the rounding of BASE_VEL + R^T dv (half an ulp of ~20 m/s, 1.8e-15 m/s, at each
# end) over the 2 m/s span: ~2e-15; the kernel's -R u carries a few eps. Entries are O(1).
STEP_LIN = 1.0
TOL_LIN = 1e-14
# h itself: a range of ~2.2e7 m carries ~3 unit roundoffs (3 * 1.1e-16 * 2.6e7 = 9e-9 m) in the
# kernel's double sqrt(d . d) plus half an ulp of each ECEF coordinate it adds (base + R^T p,
# < 1e-9 m) and of the lead's range passed in (1.9e-9 m); the reference adds pymap3d's < 1.6e-9 m.
# Measured differences are ~2-4e-9 m, i.e. the double-precision floor of a 2.2e7 m range.
TOL_PR_H = 1.5e-8
# An SD range rate in double: u . dv with |dv| ~ 4e3 m/s rounds to a few eps * 4e3 = 3e-12 m/s;
# the reference's time-difference truncation adds < 1e-12 m/s per receiver (see _range_rate).
TOL_RATE_H = 1e-11


# ------------------------------------------------------------------ Hessians of the second-order terms
HESS_D = [
    np.array([12.0, 26.0, 0.7]),
    np.array([-35.0, 8.0, -1.5]),
    np.array([0.4, -41.0, 2.0]),  # almost due south: the bearing is near +-pi (branch cut of atan2)
    np.array([-60.0, -60.0, 0.0]),  # E^2 = N^2: the off-diagonal of the bearing Hessian vanishes
    np.array([75.0, 0.0, 3.0]),  # due east: its diagonal vanishes
    np.array([1.0, -0.83, 0.45]),  # horizontal 1.30 m, 3-D 1.37 m: close, just above the 1 m degeneracy limit
]
HESS_IDS = ["ne_26m", "wnw_36m", "south_41m", "sw_85m", "east_75m", "near_1p3m"]


def _kernel_range_hessian(d):
    out = np.empty((3, 3))
    kernels.range_hessian(d, out)
    return out


def _kernel_bearing_hessian(d):
    out = np.full((3, 3), np.nan)  # the kernel must write every entry (the U row / column as 0)
    kernels.bearing_hessian(d, out)
    return out


def _fd_hessian(f, d, h):
    """Central 4-point Hessian: [f(++) - f(+-) - f(-+) + f(--)] / (4 h^2) (2h steps on the diagonal)."""
    out = np.zeros((3, 3))
    for i in range(3):
        for k in range(3):
            ei, ek = np.eye(3)[i] * h, np.eye(3)[k] * h
            out[i, k] = (f(d + ei + ek) - f(d + ei - ek) - f(d - ei + ek) + f(d - ei - ek)) / (4.0 * h * h)
    return out


@pytest.mark.parametrize("hessian", [_kernel_range_hessian, _range_hessian], ids=["kernel", "filter"])
@pytest.mark.parametrize("d", HESS_D, ids=HESS_IDS)
def test_range_hessian_is_the_second_derivative_of_distance(d, hessian):
    """Hessian of |d| (Gelb 1974 second-order range terms) = central FD Hessian of np.linalg.norm."""
    r = float(np.linalg.norm(d))
    h = 2e-4 * r
    fd = _fd_hessian(lambda v: float(np.linalg.norm(v)), d, h)
    # Truncation: diagonal (2h steps) h^2 f_iiii / 3, mixed h^2 (f_iiik + f_ikkk) / 6; directional
    # 4th derivatives of |d| are <= 3 / r^3 (Taylor coefficients of sqrt(1 + 2cs + s^2) are the
    # Gegenbauer C_4^(-1/2)(c), |.| <= 1/8, times 4!), mixed ones by polarization, so <= h^2 / r^3.
    # Round-off: 4 evaluations of ~r, each off by ~3 eps r, over 4 h^2: 3 eps r / h^2.
    # With h = 2e-4 r: 4e-8 / r + 1.7e-8 / r; the entries are ~1 / r. Tolerance 4x.
    tol = 4.0 * (h * h / r**3 + 3.0 * EPS * r / (h * h))
    np.testing.assert_allclose(hessian(d), fd, rtol=0, atol=tol)


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


@pytest.mark.parametrize("hessian", [_kernel_bearing_hessian, _bearing_hessian], ids=["kernel", "filter"])
@pytest.mark.parametrize("d", HESS_D, ids=HESS_IDS)
def test_bearing_hessian_is_the_second_derivative_of_atan2_east_north(d, hessian):
    """Hessian of the bearing atan2(E, N) (clockwise from north; U ignored) = central FD Hessian."""
    theta0 = math.atan2(d[0], d[1])

    def bearing(v):  # atan2(E, N) continued across the +-pi cut around d (a constant shift: same Hessian)
        return _wrap(math.atan2(v[0], v[1]) - theta0)

    rh = math.hypot(d[0], d[1])
    h = 2e-4 * rh
    fd = _fd_hessian(bearing, d, h)
    # theta = arg(N + iE) is harmonic: the k-th directional derivative is Im((k-1)! w^k / z^k) up
    # to sign, <= (k-1)! / r^k = 6 / r^4 for k = 4 (r horizontal); with the polarization above the
    # truncation is <= 2 h^2 / r^4. Round-off: each angle is off by ~4 eps rad (atan2, the input
    # rounding, the wrap), over 4 h^2: 4 eps / h^2. With h = 2e-4 r: 8e-8 / r^2 + 2.2e-8 / r^2,
    # entries ~1 / r^2. Tolerance 4x. The U row and column are exactly 0 in both (f ignores U).
    tol = 4.0 * (2.0 * h * h / rh**4 + 4.0 * EPS / (h * h))
    np.testing.assert_allclose(hessian(d), fd, rtol=0, atol=tol)


# ------------------------------------------------------------------ measmodels Jacobians
def test_bearing_jacobian_is_the_gradient_of_atan2_east_north():
    """d atan2(E, N) / d(E, N, U) of measmodels.bearing_jacobian = central FD gradient (also stacked input)."""
    got = bearing_jacobian(np.array(HESS_D))  # (k, 3): the vectorized form, one row per vector
    assert got.shape == (len(HESS_D), 3)
    for d, row in zip(HESS_D, got, strict=True):
        theta0 = math.atan2(d[0], d[1])
        rh = math.hypot(d[0], d[1])
        h = 2e-5 * rh
        fd = np.empty(3)
        for i in range(3):
            e = np.eye(3)[i] * h
            fd[i] = _wrap(math.atan2(*(d + e)[:2]) - theta0) - _wrap(math.atan2(*(d - e)[:2]) - theta0)
            fd[i] /= 2.0 * h
        # truncation h^2 M3 / 6 with M3 <= 2! / r^3 (harmonic angle, as above): h^2 / (3 r^3);
        # round-off 2 * 4 eps / (2 h). With h = 2e-5 r: 1.3e-10 / r + 4.4e-11 / r. Tolerance 4x.
        tol = 4.0 * (h * h / (3.0 * rh**3) + 4.0 * EPS / h)
        np.testing.assert_allclose(row, fd, rtol=0, atol=tol)
        np.testing.assert_allclose(bearing_jacobian(d), row, rtol=0, atol=0)  # one vector = its stacked row


@pytest.mark.parametrize("vehicle", list(VEHICLES), ids=list(VEHICLES))
def test_range_rate_jacobians_are_gradients_of_the_time_derivative_of_range(vehicle):
    """measmodels.range_rate_jacobians (ECEF) = central FD of d|sv(t) - r(t)|/dt in receiver position and velocity."""
    p, dv, _, _ = VEHICLES[vehicle]
    r, v = _vehicle_ecef(p), _vehicle_vel(dv)
    for o in range(len(SV)):
        d_r, d_v = range_rate_jacobians(r, v, SV[o], SVV[o])
        for i in range(3):
            # ECEF coordinates are exact floats here (no pymap3d in the loop) and the reference is
            # exact on them: the position FD error is the truncation 2e-17 /s derived at STEP_P;
            # the function's own (dv - u rate) / rho rounds to ~eps * 4e3 / 2e7 = 4e-20 /s.
            fd_r = _fd(lambda rr, o=o: _range_rate(rr, v, SV[o], SVV[o]), r, i, STEP_P)
            assert abs(d_r[i] - fd_r) <= 1e-16, (o, i, d_r[i], fd_r)  # entries ~1e-4 /s: 1e-12 relative
            fd_v = _fd(lambda vv, o=o: _range_rate(r, vv, SV[o], SVV[o]), v, i, STEP_LIN)
            assert abs(d_v[i] - fd_v) <= TOL_LIN, (o, i, d_v[i], fd_v)  # linear in v: exact FD


# ------------------------------------------------------------------ SD rows (compiled kernels)
PS, VS, ICLK, IDRIFT = 2, 5, 8, 9  # the vehicle's slots in a 12-state vector (others hold junk)


def _kernel_state(p, dv, clk, drift):
    x = np.array([7.0, -3.0, *p, *dv, clk, drift, 99.0, -99.0])
    assert x[PS:PS + 3].tolist() == p.tolist() and x[ICLK] == clk and x[IDRIFT] == drift
    return x


def _rho_lead() -> np.ndarray:
    return np.array([float(_dist(SV_LEAD[o], BASE)) for o in range(len(SV))])


def _rate_lead() -> np.ndarray:
    return np.array([float(_range_rate(BASE, BASE_VEL, SV_LEAD[o], SVV[o])) for o in range(len(SV))])


def _check_pr_rows(h, val, p, clk):
    """h and rows [d/dp (ENU), d/dclk] of every satellite against the eq. 3.2 reference."""
    assert h.shape == (len(SV),) and val.shape == (len(SV), 4)
    for o in range(len(SV)):
        assert abs(h[o] - float(_sd_pr_ref(p, clk, o))) <= TOL_PR_H, (o, h[o], float(_sd_pr_ref(p, clk, o)))
        for i in range(3):
            fd = _fd(lambda q, o=o: _sd_pr_ref(q, clk, o), p, i, STEP_P)
            assert abs(val[o, i] - fd) <= TOL_PR_POS, (o, i, val[o, i], fd)
        fd_clk = _fd(lambda c, o=o: _sd_pr_ref(p, c[0], o), [clk], 0, STEP_LIN)
        assert abs(val[o, 3] - fd_clk) <= TOL_LIN


def _check_doppler_rows(h, val, p, dv, drift):
    """h and rows [d/dp, d/d dv (ENU), d/d drift] of every satellite against the SD range-rate reference."""
    assert h.shape == (len(SV),) and val.shape == (len(SV), 7)
    for o in range(len(SV)):
        ref = float(_sd_rate_ref(p, dv, drift, o))
        assert abs(h[o] - ref) <= TOL_RATE_H, (o, h[o], ref)
        for i in range(3):
            fd = _fd(lambda q, o=o: _sd_rate_ref(q, dv, drift, o), p, i, STEP_P)
            assert abs(val[o, i] - fd) <= TOL_RATE_POS, (o, i, val[o, i], fd)
            fd = _fd(lambda w, o=o: _sd_rate_ref(p, w, drift, o), dv, i, STEP_LIN)
            assert abs(val[o, 3 + i] - fd) <= TOL_LIN, (o, i, val[o, 3 + i], fd)
        fd_drift = _fd(lambda c, o=o: _sd_rate_ref(p, dv, c[0], o), [drift], 0, STEP_LIN)
        assert abs(val[o, 6] - fd_drift) <= TOL_LIN


@pytest.mark.parametrize("vehicle", list(VEHICLES), ids=list(VEHICLES))
def test_sd_pseudorange_rows_kernel_is_the_single_difference_model(vehicle):
    """kernels.sd_pseudorange_rows: h = eq. 3.2 (vehicle range - lead range + clk argument), rows = its FD gradient."""
    p, dv, clk, drift = VEHICLES[vehicle]
    x = _kernel_state(p, dv, clk, drift)
    clk_arg = clk + 29.979  # the rows use the clock passed in (a re-initialized clock), not x[iclk]
    h, val = kernels.sd_pseudorange_rows(x, BASE, ROT, PS, ICLK, SV, _rho_lead(), clk_arg)
    _check_pr_rows(h, val, p, clk_arg)


@pytest.mark.parametrize("vehicle", list(VEHICLES), ids=list(VEHICLES))
def test_sd_doppler_rows_kernel_is_the_single_difference_range_rate(vehicle):
    """kernels.sd_doppler_rows: h = d/dt(vehicle range - lead range) + drift, rows = its FD gradient."""
    p, dv, clk, drift = VEHICLES[vehicle]
    x = _kernel_state(p, dv, clk, drift)
    h, val = kernels.sd_doppler_rows(x, BASE, BASE_VEL, ROT, PS, VS, IDRIFT, SV, SVV, _rate_lead())
    _check_doppler_rows(h, val, p, dv, drift)


# ------------------------------------------------------------------ SD rows (models classes)
LAYOUT = StateLayout.build(lead="L", vehicles=["A", "B"])
GEO = models.GnssGeometry(base_ecef_m=BASE, base_vel_ecef_mps=BASE_VEL)


def _layout_state(p, dv, clk, drift):
    """State with vehicle B as given (A holds other values: B's rows must not read them)."""
    x = np.zeros(LAYOUT.n)
    x[LAYOUT.position("A")] = [50.0, -7.0, 0.3]
    x[LAYOUT.velocity("A")] = [3.0, 1.0, -0.2]
    x[LAYOUT.clock("A")] = 777.0
    x[LAYOUT.drift("A")] = -4.0
    x[LAYOUT.position("B")] = p
    x[LAYOUT.velocity("B")] = dv
    x[LAYOUT.clock("B")] = clk
    x[LAYOUT.drift("B")] = drift
    return x


@pytest.mark.parametrize("vehicle", list(VEHICLES), ids=list(VEHICLES))
def test_sd_pseudorange_rows_class_is_the_single_difference_model(vehicle):
    """models.SdPseudorangeRows .all and .row on (position, clock) of B: eq. 3.2 and its FD gradient."""
    p, dv, clk, drift = VEHICLES[vehicle]
    x = _layout_state(p, dv, clk, drift)
    rows = models.SdPseudorangeRows(LAYOUT, GEO, "B", SV, SV_LEAD)
    ps = LAYOUT.position("B")
    assert rows.idx.tolist() == [ps.start, ps.start + 1, ps.start + 2, LAYOUT.clock("B")]
    assert len(rows) == len(SV)
    # GnssGeometry derives R from the base via v2v.frames; its latitude agrees with LAT0 to
    # ~1e-15 rad, i.e. < 1e-13 m over these baselines: the same tolerances apply.
    h, val = rows.all(x)
    _check_pr_rows(h, val, p, clk)
    one = [rows.row(x, o) for o in range(len(SV))]
    assert all(r.idx.tolist() == rows.idx.tolist() for r in one)
    _check_pr_rows(np.array([r.h for r in one]), np.array([r.val for r in one]), p, clk)


@pytest.mark.parametrize("vehicle", list(VEHICLES), ids=list(VEHICLES))
def test_sd_doppler_rows_class_is_the_single_difference_range_rate(vehicle):
    """models.SdDopplerRows .all and .row on (position, velocity, drift) of B: SD range rate and its FD gradient."""
    p, dv, clk, drift = VEHICLES[vehicle]
    x = _layout_state(p, dv, clk, drift)
    rows = models.SdDopplerRows(LAYOUT, GEO, "B", SV, SVV, SV_LEAD, SVV)
    ps, vs = LAYOUT.position("B"), LAYOUT.velocity("B")
    assert rows.idx.tolist() == [*range(ps.start, ps.stop), *range(vs.start, vs.stop), LAYOUT.drift("B")]
    h, val = rows.all(x)
    _check_doppler_rows(h, val, p, dv, drift)
    one = [rows.row(x, o) for o in range(len(SV))]
    assert all(r.idx.tolist() == rows.idx.tolist() for r in one)
    _check_doppler_rows(np.array([r.h for r in one]), np.array([r.val for r in one]), p, dv, drift)


def test_fixture_satellites_are_gps_like_at_the_stated_azimuth_elevation():
    """The test geometry itself: pymap3d sees each satellite at its (az, el), 20 200 km up, moving at 3.87 km/s."""
    for (az, el), s, v in zip(SKY, SV, SVV, strict=True):
        a, e, _ = pymap3d.ecef2aer(*s, LAT0, LON0, H0)
        assert abs(_wrap(math.radians(float(a) - az))) < 1e-9 and abs(float(e) - el) < 1e-7
        _, _, alt = pymap3d.ecef2geodetic(*s)
        assert 19.9e6 < float(alt) < 20.5e6  # ellipsoidal height of the 26 560 km sphere at these latitudes
        assert abs(float(np.linalg.norm(s)) - R_ORBIT) < 1e-6 and abs(float(s @ v)) < 1e-3 * R_ORBIT
        assert float(np.linalg.norm(v)) == pytest.approx(V_ORBIT, rel=1e-12)
