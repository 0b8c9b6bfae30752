"""Compiled (numba) kernels of the production cluster EKF: whole batches of sequential scalar updates.

The sequential EKF of :mod:`v2v.estimation.filter` (MacGougan (2009) table 3.1) applies one
scalar update per measurement, each re-linearized at the state left by the previous one.
In Python the per-measurement overhead (row building, the second-order check, the
``UpdateInfo`` record) cost several times the O(n^2) algebra. These kernels run a whole
batch of one measurement type in one call, with exactly the filter's rules:

* :func:`scalar_update`: ``p = P h^T`` over the row's nonzero columns, ``S = h p + r``
  (thesis eq. 3.23), the innovation test ``|nu| <= k sqrt(S)`` (eq. 3.26-3.27), then
  ``x += p nu / S`` and the symmetric rank-1 form ``P -= q q^T``, ``q = p / sqrt(S)`` of
  eq. 3.16-3.18 (``q_i q_j == q_j q_i`` exactly, so P stays exactly symmetric).
* second-order terms of a range or bearing ``f(d)``, ``d = p_b - p_a`` with covariance
  ``P_d`` (Gelb 1974 sec. 6.1): mean ``tr(H2 P_d) / 2`` added to ``h(x)``, variance
  ``tr((H2 P_d)^2) / 2`` added to R; the measurement is deferred while that variance
  exceeds ``nonlinear_fraction`` times R (see the filter's module docstring).
* :func:`uwb_batch`: ranges ``(1 + s) rho + b`` (thesis eq. 3.4-3.5) with optional
  bias/scale states and their inequality constraints as pseudo-measurements (eq. 3.19-3.22).
* :func:`bearing_batch`: ``atan2(dE, dN) - alpha`` (Petovello et al. eq. 5-6) with a known
  (reported) or estimated azimuth, initialized at its first bearing.
* :func:`sd_doppler_batch`, :func:`sd_pseudorange_batch`: one vehicle's SD Dopplers /
  pseudoranges in the given order, with the screen's exclusions (thesis eq. 3.2-3.3).

Inside a batch the covariance updates are deferred (:func:`lazy_scalar_update`): the
rank-1 terms are buffered and applied ``LAZY_RANK`` at a time as one BLAS-3 product, which
for large states is several times faster than one memory pass over P per measurement and
equal to the sequential result up to round-off.

Each batch kernel returns per-record arrays (innovation, S, status) from which the filter
builds the same ``UpdateInfo`` records and counters as the plain-Python path of
:class:`v2v.estimation.filter.ClusterFilterBase` (which the reference engine runs:
``tests/test_engines_agree.py`` checks both to 1e-9). Compiled once per machine
(``cache=True``); ``error_model="numpy"`` so that 0/0 gives NaN (a non-finite result is
counted, as in Python) instead of raising.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# status of one record (kernel output)
ACCEPTED = 0
REJECTED = 1  # failed the innovation test (or non-finite P h^T): an UpdateInfo with accepted=False
NONFINITE = 2  # non-finite innovation or S: counted nonfinite_<kind>, no record
DEFERRED = 3  # second-order variance too large: counted <kind>_deferred_nonlinear
DEGENERATE = 4  # bearing with horizontal distance < 1 m: counted bearing_degenerate_geometry
NONFINITE_INPUT = 5  # non-finite reported azimuth: counted nonfinite_<kind>, no record
EXCLUDED = 6  # left out by the epoch's screen: an UpdateInfo with accepted=False (x, P untouched)

# record kinds of uwb_batch
REC_UWB = 0
REC_CONSTRAINT = 1

_JIT = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def wrap_angle(a: float) -> float:
    """Wrap to (-pi, pi] (same convention as :func:`v2v.frames.wrap_angle`)."""
    w = (a + math.pi) % (2.0 * math.pi) - math.pi
    return math.pi if w == -math.pi else w


@njit(**_JIT)
def scalar_update(x, P, idx, val, nnz, nu, r_var, gate_k, test):
    """In-place sequential scalar update with a sparse row (``idx[:nnz]``, ``val[:nnz]``).

    Returns ``(S, status)``: ACCEPTED, REJECTED (test failed or ``P h^T`` non-finite, x, P
    untouched) or NONFINITE (innovation or S non-finite or S <= 0). P must be symmetric:
    ``P[:, idx] h`` is read row-wise as ``P[idx, :]^T h`` (contiguous).
    """
    n = x.shape[0]
    p = np.zeros(n)
    for k in range(nnz):
        row = P[idx[k]]
        v = val[k]
        for i in range(n):
            p[i] += row[i] * v
    s = 0.0
    for k in range(nnz):
        s += val[k] * p[idx[k]]
    s += r_var
    if not (math.isfinite(nu) and math.isfinite(s) and s > 0.0):
        return s, NONFINITE
    for i in range(n):
        if not math.isfinite(p[i]):
            return s, REJECTED
    if test and abs(nu) > gate_k * math.sqrt(s):
        return s, REJECTED
    g = nu / s
    for i in range(n):
        x[i] += p[i] * g
    c = math.sqrt(1.0 / s)
    for i in range(n):
        p[i] *= c
    for i in range(n):
        qi = p[i]
        row = P[i]
        for j in range(n):
            row[j] -= qi * p[j]
    return s, ACCEPTED


@njit(**_JIT)
def _second_order(hess, pd):
    """(tr(H2 P_d) / 2, tr((H2 P_d)^2) / 2): second-order mean and variance (Gelb 1974)."""
    m = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            m[i, j] = hess[i, 0] * pd[0, j] + hess[i, 1] * pd[1, j] + hess[i, 2] * pd[2, j]
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    tr2 = 0.0
    for i in range(3):
        for j in range(3):
            tr2 += m[i, j] * m[j, i]
    return 0.5 * tr, 0.5 * tr2


@njit(**_JIT)
def range_hessian(d, out):
    """Hessian of |d|: (I - u u^T) / |d| (NaN for d = 0)."""
    r = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    for i in range(3):
        ui = d[i] / r
        for j in range(3):
            out[i, j] = ((1.0 if i == j else 0.0) - ui * (d[j] / r)) / r


@njit(**_JIT)
def bearing_hessian(d, out):
    """Hessian of atan2(E, N) in (E, N, U): [[-2EN, E^2-N^2], [E^2-N^2, 2EN]] / r^4."""
    e, n = d[0], d[1]
    r4 = (e * e + n * n) ** 2
    out[:, :] = 0.0
    out[0, 0] = -2.0 * e * n / r4
    out[1, 1] = 2.0 * e * n / r4
    out[0, 1] = (e * e - n * n) / r4
    out[1, 0] = out[0, 1]


@njit(**_JIT)
def _delta(x, sa, sb, d):
    for i in range(3):
        d[i] = (x[sb + i] if sb >= 0 else 0.0) - (x[sa + i] if sa >= 0 else 0.0)


@njit(**_JIT)
def _set_block1(x, P, i, mean, var):
    """Re-initialize scalar state i: mean, variance, zero correlations."""
    x[i] = mean
    P[i, :] = 0.0
    P[:, i] = 0.0
    P[i, i] = var


# ------------------------------------------------------------------ deferred (lazy) covariance
# A batch of m sequential scalar updates costs m rank-1 passes over P (O(m n^2), bound by
# memory bandwidth once P leaves the cache). With P_k = P_0 - sum_j q_j q_j^T the updates
# only need P_k h^T = P_0 h^T - sum_j (q_j . h) q_j and a few entries of P_k (sparse h:
# O(nnz n + k n) each), so the q_j are buffered (LAZY_RANK at a time) and applied as one
# rank-k product P -= Q^T Q (BLAS-3). The result equals the sequential one up to round-off
# (a different summation order); the upper triangle is applied to both halves, so P stays
# exactly symmetric.

LAZY_RANK = 32


@njit(**_JIT)
def lazy_flush(P, Q, kq):
    """Apply the buffered ``P -= Q[:kq]^T Q[:kq]`` (symmetric: upper triangle to both halves); returns 0."""
    if kq == 0:
        return 0
    qk = Q[:kq]
    g = np.dot(qk.T, qk)
    n = P.shape[0]
    for i in range(n):
        for j in range(i, n):
            v = g[i, j]
            P[i, j] -= v
            if j != i:
                P[j, i] -= v
    return 0


@njit(**_JIT)
def _lazy_entry(P, Q, kq, i, j):
    v = P[i, j]
    for k in range(kq):
        v -= Q[k, i] * Q[k, j]
    return v


@njit(**_JIT)
def _rel_cov_lazy(P, Q, kq, sa, sb, out):
    """Covariance of d = p_b - p_a (position slices start at sa, sb; -1 = lead at the origin)
    from the lazily updated covariance."""
    for i in range(3):
        for j in range(3):
            v = 0.0
            if sa >= 0:
                v += _lazy_entry(P, Q, kq, sa + i, sa + j)
            if sb >= 0:
                v += _lazy_entry(P, Q, kq, sb + i, sb + j)
            if sa >= 0 and sb >= 0:
                v -= _lazy_entry(P, Q, kq, sa + i, sb + j) + _lazy_entry(P, Q, kq, sb + i, sa + j)
            out[i, j] = v


@njit(**_JIT)
def lazy_scalar_update(x, P, Q, kq, idx, val, nnz, nu, r_var, gate_k, test):
    """:func:`scalar_update` on the lazily updated covariance ``P - Q[:kq]^T Q[:kq]``.

    Returns ``(S, status, kq)``; an accepted update appends ``q = P h^T / sqrt(S)`` to Q
    (flushing first when Q is full).
    """
    n = x.shape[0]
    p = np.zeros(n)
    for a in range(nnz):
        row = P[idx[a]]
        v = val[a]
        for i in range(n):
            p[i] += row[i] * v
    for k in range(kq):
        qk = Q[k]
        c = 0.0
        for a in range(nnz):
            c += val[a] * qk[idx[a]]
        if c != 0.0:
            for i in range(n):
                p[i] -= c * qk[i]
    s = 0.0
    for a in range(nnz):
        s += val[a] * p[idx[a]]
    s += r_var
    if not (math.isfinite(nu) and math.isfinite(s) and s > 0.0):
        return s, NONFINITE, kq
    for i in range(n):
        if not math.isfinite(p[i]):
            return s, REJECTED, kq
    if test and abs(nu) > gate_k * math.sqrt(s):
        return s, REJECTED, kq
    g = nu / s
    for i in range(n):
        x[i] += p[i] * g
    if kq == Q.shape[0]:
        kq = lazy_flush(P, Q, kq)
    c = math.sqrt(1.0 / s)
    qk = Q[kq]
    for i in range(n):
        qk[i] = p[i] * c
    return s, ACCEPTED, kq + 1


@njit(**_JIT)
def uwb_batch(x, P, sa, sb, ib, isc, z, r_var, gate_k, nl_frac,
              bias_on, bias_lo, bias_hi, scale_on, scale_lo, scale_hi):
    """Sequential UWB range updates (MacGougan (2009) eq. 3.4-3.5, 3.19-3.22).

    Per range k: ``sa[k]``, ``sb[k]`` position-slice starts of a, b (-1 = lead), ``ib[k]``,
    ``isc[k]`` bias and scale state indices (-1 = no bias/scale states), measured ``z[k]``.
    Each range is re-linearized at the current state; deferred while its second-order
    variance exceeds ``nl_frac[k] * r_var`` (``nl_frac`` per range: the filter's
    ``nonlinear_fraction``, or inf when GNSS cannot shrink P); after an accepted range with
    bias/scale states, the enabled bound constraints (bias first, then scale, at most 4
    passes) are applied as untested pseudo-measurements.

    Returns ``(n_rec, rec_kind, rec_meas, rec_nu, rec_s, rec_status)``: the first ``n_rec``
    records in order; ``rec_kind`` REC_UWB or REC_CONSTRAINT, ``rec_meas`` the range index.
    """
    m = z.shape[0]
    cap = m * 9
    rec_kind = np.zeros(cap, dtype=np.int64)
    rec_meas = np.zeros(cap, dtype=np.int64)
    rec_nu = np.zeros(cap)
    rec_s = np.zeros(cap)
    rec_status = np.zeros(cap, dtype=np.int64)
    n_rec = 0
    d = np.empty(3)
    hess = np.empty((3, 3))
    pd = np.empty((3, 3))
    idx = np.empty(8, dtype=np.int64)
    val = np.empty(8)
    Q = np.empty((LAZY_RANK, x.shape[0]))  # deferred rank-1 terms (see lazy_scalar_update)
    kq = 0
    for k in range(m):
        lim = r_var * nl_frac[k]
        _delta(x, sa[k], sb[k], d)
        range_hessian(d, hess)
        _rel_cov_lazy(P, Q, kq, sa[k], sb[k], pd)
        h2_mean, h2_var = _second_order(hess, pd)
        if not h2_var <= lim:
            rec_kind[n_rec] = REC_UWB
            rec_meas[n_rec] = k
            rec_status[n_rec] = DEFERRED
            n_rec += 1
            continue
        rho = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
        has = ib[k] >= 0
        kap = 1.0 + x[isc[k]] if has else 1.0
        h = kap * rho + (x[ib[k]] if has else 0.0)
        h = h + h2_mean
        nnz = 0
        if sa[k] >= 0:
            for i in range(3):
                idx[nnz] = sa[k] + i
                val[nnz] = -kap * (d[i] / rho)
                nnz += 1
        if sb[k] >= 0:
            for i in range(3):
                idx[nnz] = sb[k] + i
                val[nnz] = kap * (d[i] / rho)
                nnz += 1
        if has:
            idx[nnz] = ib[k]
            val[nnz] = 1.0
            idx[nnz + 1] = isc[k]
            val[nnz + 1] = rho
            nnz += 2
        nu = z[k] - h
        s, st, kq = lazy_scalar_update(x, P, Q, kq, idx, val, nnz, nu, r_var + h2_var, gate_k, True)
        rec_kind[n_rec] = REC_UWB
        rec_meas[n_rec] = k
        rec_nu[n_rec] = nu
        rec_s[n_rec] = s
        rec_status[n_rec] = st
        n_rec += 1
        if st != ACCEPTED or not has:
            continue
        for _ in range(4):
            changed = False
            for c in range(2):
                if c == 0:
                    if not bias_on:
                        continue
                    i, lo, hi = ib[k], bias_lo, bias_hi
                else:
                    if not scale_on:
                        continue
                    i, lo, hi = isc[k], scale_lo, scale_hi
                xi = x[i]
                pii = _lazy_entry(P, Q, kq, i, i)
                if xi > hi:
                    zc, rc = lo, pii * (hi - lo) / (xi - hi)
                elif xi < lo:
                    zc, rc = hi, pii * (hi - lo) / (lo - xi)
                else:
                    continue
                idx[0] = i
                val[0] = 1.0
                nuc = zc - xi
                sc, stc, kq = lazy_scalar_update(x, P, Q, kq, idx, val, 1, nuc, rc, gate_k, False)
                rec_kind[n_rec] = REC_CONSTRAINT
                rec_meas[n_rec] = k
                rec_nu[n_rec] = nuc
                rec_s[n_rec] = sc
                rec_status[n_rec] = stc
                n_rec += 1
                if stc != NONFINITE:
                    changed = True
            if not changed:
                break
    kq = lazy_flush(P, Q, kq)
    return n_rec, rec_kind, rec_meas, rec_nu, rec_s, rec_status




@njit(**_JIT)
def bearing_batch(x, P, sa, sb, iaz, az_ready, z, az_reported, r_var, gate_k, nl_frac, az_var0):
    """Sequential bearing updates (Petovello et al. eq. 5-6), one record per bearing.

    ``sa[k]``, ``sb[k]`` position-slice starts (-1 = lead); ``iaz[k]`` the azimuth state
    of a (-1: azimuth known, ``az_reported[k]`` used). ``az_ready`` (length n, indexed by
    the azimuth state) marks initialized azimuths and is updated in place: an azimuth is
    initialized at its first usable bearing to ``wrap(atan2(dE, dN) - beta)`` with variance
    ``az_var0`` and no correlations, then that bearing is applied (zero innovation).
    Status per bearing: DEGENERATE (horizontal distance < 1 m), DEFERRED, NONFINITE_INPUT
    (reported azimuth), NONFINITE, REJECTED, ACCEPTED. Returns ``(nu, s, status)``.
    The covariance updates are deferred and applied as rank-``LAZY_RANK`` products
    (:func:`lazy_scalar_update`); P is complete on return.
    """
    m = z.shape[0]
    out_nu = np.zeros(m)
    out_s = np.zeros(m)
    out_st = np.zeros(m, dtype=np.int64)
    d = np.empty(3)
    hess = np.empty((3, 3))
    pd = np.empty((3, 3))
    idx = np.empty(7, dtype=np.int64)
    val = np.empty(7)
    Q = np.empty((LAZY_RANK, x.shape[0]))  # deferred rank-1 terms (see lazy_scalar_update)
    kq = 0
    for k in range(m):
        lim = r_var * nl_frac[k]
        _delta(x, sa[k], sb[k], d)
        if math.hypot(d[0], d[1]) < 1.0:
            out_st[k] = DEGENERATE
            continue
        bearing_hessian(d, hess)
        _rel_cov_lazy(P, Q, kq, sa[k], sb[k], pd)
        h2_mean, h2_var = _second_order(hess, pd)
        if not h2_var <= lim:
            out_st[k] = DEFERRED
            continue
        ia = iaz[k]
        if ia >= 0:
            if not az_ready[ia]:
                kq = lazy_flush(P, Q, kq)
                _set_block1(x, P, ia, wrap_angle(math.atan2(d[0], d[1]) - z[k]), az_var0)
                az_ready[ia] = True
            alpha = x[ia]
        else:
            alpha = az_reported[k]
            if not math.isfinite(alpha):
                out_st[k] = NONFINITE_INPUT
                continue
        e, n_ = d[0], d[1]
        h = wrap_angle(math.atan2(e, n_) - alpha) + h2_mean
        r2 = e * e + n_ * n_
        j0, j1 = n_ / r2, -e / r2
        nnz = 0
        if sa[k] >= 0:
            idx[0], idx[1], idx[2] = sa[k], sa[k] + 1, sa[k] + 2
            val[0], val[1], val[2] = -j0, -j1, -0.0
            nnz = 3
        if sb[k] >= 0:
            idx[nnz], idx[nnz + 1], idx[nnz + 2] = sb[k], sb[k] + 1, sb[k] + 2
            val[nnz], val[nnz + 1], val[nnz + 2] = j0, j1, 0.0
            nnz += 3
        if ia >= 0:
            idx[nnz] = ia
            val[nnz] = -1.0
            nnz += 1
        nu = wrap_angle(z[k] - h)
        s, st, kq = lazy_scalar_update(x, P, Q, kq, idx, val, nnz, nu, r_var + h2_var, gate_k, True)
        out_nu[k] = nu
        out_s[k] = s
        out_st[k] = st
    kq = lazy_flush(P, Q, kq)
    return out_nu, out_s, out_st


@njit(**_JIT)
def _abs3(base, rot, x, s, out):
    """base + R^T x[s:s+3] (ECEF of a relative ENU vector; models.GnssGeometry.abs_position)."""
    for c in range(3):
        out[c] = base[c] + (x[s] * rot[0, c] + x[s + 1] * rot[1, c] + x[s + 2] * rot[2, c])


@njit(**_JIT)
def _excluded_s(P, Q, kq, idx, val, nnz, r_var):
    """S = h P h^T + r of a row on the lazily updated covariance (no update)."""
    s = 0.0
    for a in range(nnz):
        t = 0.0
        for b in range(nnz):
            t += _lazy_entry(P, Q, kq, idx[a], idx[b]) * val[b]
        s += val[a] * t
    return s + r_var


@njit(**_JIT)
def sd_doppler_batch(x, P, base, base_vel, rot, ps, vs, idrift, sv, svv, rate_lead, z, order, excluded,
                     r_var, gate_k):
    """One vehicle's SD pseudorange-rate updates in ``order`` (models.SdDopplerRows.row).

    ``h = u . (vsv - v) - rate_lead + drift`` with ``v = base_vel + R^T dv``; Jacobian
    d/d p = R (-(dv - u rate) / rho), d/d dv = -R u, d/d drift = 1 (``ps``, ``vs``: position
    and velocity slice starts, ``idrift``: drift index). ``excluded[o]``: reported with
    (nu, S) at the current state and not applied (status EXCLUDED, or NONFINITE).
    Returns ``(nu, s, status)`` indexed like ``order``.
    """
    m = order.shape[0]
    out_nu = np.zeros(m)
    out_s = np.zeros(m)
    out_st = np.zeros(m, dtype=np.int64)
    r_v = np.empty(3)
    v_v = np.empty(3)
    u = np.empty(3)
    dv = np.empty(3)
    g = np.empty(3)
    idx = np.empty(7, dtype=np.int64)
    for i in range(3):
        idx[i] = ps + i
        idx[3 + i] = vs + i
    idx[6] = idrift
    val = np.empty(7)
    Q = np.empty((LAZY_RANK, x.shape[0]))  # deferred rank-1 terms (see lazy_scalar_update)
    kq = 0
    for k in range(m):
        o = order[k]
        _abs3(base, rot, x, ps, r_v)
        _abs3(base_vel, rot, x, vs, v_v)
        d0, d1, d2 = sv[o, 0] - r_v[0], sv[o, 1] - r_v[1], sv[o, 2] - r_v[2]
        rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        u[0], u[1], u[2] = d0 / rho, d1 / rho, d2 / rho
        for i in range(3):
            dv[i] = svv[o, i] - v_v[i]
        rate = u[0] * dv[0] + u[1] * dv[1] + u[2] * dv[2]
        h = (rate - rate_lead[o]) + x[idrift]
        for i in range(3):
            g[i] = -(dv[i] - u[i] * rate) / rho
        for i in range(3):
            val[i] = rot[i, 0] * g[0] + rot[i, 1] * g[1] + rot[i, 2] * g[2]
            val[3 + i] = -(rot[i, 0] * u[0] + rot[i, 1] * u[1] + rot[i, 2] * u[2])
        val[6] = 1.0
        nu = z[o] - h
        if excluded[o]:
            s = _excluded_s(P, Q, kq, idx, val, 7, r_var)
            out_nu[k], out_s[k] = nu, s
            out_st[k] = EXCLUDED if (math.isfinite(nu) and math.isfinite(s) and s > 0.0) else NONFINITE
            continue
        s, st, kq = lazy_scalar_update(x, P, Q, kq, idx, val, 7, nu, r_var, gate_k, True)
        out_nu[k], out_s[k], out_st[k] = nu, s, st
    kq = lazy_flush(P, Q, kq)
    return out_nu, out_s, out_st


@njit(**_JIT)
def sd_pseudorange_batch(x, P, base, rot, ps, iclk, sv, rho_lead, z, order, excluded, r_var, gate_k):
    """One vehicle's SD pseudorange updates in ``order`` (models.SdPseudorangeRows.row).

    ``h = |sv - (base + R^T p)| - rho_lead + clk`` (MacGougan (2009) eq. 3.2-3.3), Jacobian
    ``(-R u, 1)`` on (position, clock). ``excluded`` as in :func:`sd_doppler_batch`.
    Returns ``(nu, s, status)`` indexed like ``order``.
    """
    m = order.shape[0]
    out_nu = np.zeros(m)
    out_s = np.zeros(m)
    out_st = np.zeros(m, dtype=np.int64)
    r_v = np.empty(3)
    idx = np.empty(4, dtype=np.int64)
    for i in range(3):
        idx[i] = ps + i
    idx[3] = iclk
    val = np.empty(4)
    Q = np.empty((LAZY_RANK, x.shape[0]))  # deferred rank-1 terms (see lazy_scalar_update)
    kq = 0
    for k in range(m):
        o = order[k]
        _abs3(base, rot, x, ps, r_v)
        d0, d1, d2 = sv[o, 0] - r_v[0], sv[o, 1] - r_v[1], sv[o, 2] - r_v[2]
        rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        h = (rho - rho_lead[o]) + x[iclk]
        u0, u1, u2 = d0 / rho, d1 / rho, d2 / rho
        for i in range(3):
            val[i] = -(rot[i, 0] * u0 + rot[i, 1] * u1 + rot[i, 2] * u2)
        val[3] = 1.0
        nu = z[o] - h
        if excluded[o]:
            s = _excluded_s(P, Q, kq, idx, val, 4, r_var)
            out_nu[k], out_s[k] = nu, s
            out_st[k] = EXCLUDED if (math.isfinite(nu) and math.isfinite(s) and s > 0.0) else NONFINITE
            continue
        s, st, kq = lazy_scalar_update(x, P, Q, kq, idx, val, 4, nu, r_var, gate_k, True)
        out_nu[k], out_s[k], out_st[k] = nu, s, st
    kq = lazy_flush(P, Q, kq)
    return out_nu, out_s, out_st


@njit(**_JIT)
def predict_vehicle_blocks(x, P, s0, m, fb, qb):
    """x <- F x, P <- F P F^T + Q for ``m`` contiguous 8-state vehicle blocks from ``s0``
    (F = blockdiag(fb), identity elsewhere; Q = blockdiag(qb)), in place (not symmetrized).

    Only the nonzeros of ``fb`` are used (12 of 64 for [p, v, clk, drift]: position
    integrates velocity, the clock integrates the drift).
    """
    n = x.shape[0]
    nz_i = np.empty(64, dtype=np.int64)
    nz_j = np.empty(64, dtype=np.int64)
    nz_f = np.empty(64)
    nnz = 0
    for i in range(8):
        for j in range(8):
            if fb[i, j] != 0.0:
                nz_i[nnz], nz_j[nnz], nz_f[nnz] = i, j, fb[i, j]
                nnz += 1
    tmp = np.empty(8)
    rows = np.empty((8, n))
    for a in range(m):
        s = s0 + 8 * a
        tmp[:] = 0.0
        for k in range(nnz):
            tmp[nz_i[k]] += nz_f[k] * x[s + nz_j[k]]
        for i in range(8):
            x[s + i] = tmp[i]
        # rows: P[s:s+8, :] <- fb @ P[s:s+8, :]
        rows[:, :] = 0.0
        for k in range(nnz):
            f = nz_f[k]
            dst = rows[nz_i[k]]
            src = P[s + nz_j[k]]
            for c in range(n):
                dst[c] += f * src[c]
        for i in range(8):
            P[s + i, :] = rows[i]
    # columns: P[:, s:s+8] <- P[:, s:s+8] @ fb^T
    for r in range(n):
        row = P[r]
        for a in range(m):
            s = s0 + 8 * a
            tmp[:] = 0.0
            for k in range(nnz):
                tmp[nz_i[k]] += row[s + nz_j[k]] * nz_f[k]
            for i in range(8):
                row[s + i] = tmp[i]
    for a in range(m):
        s = s0 + 8 * a
        for i in range(8):
            for j in range(8):
                P[s + i, s + j] += qb[i, j]


@njit(**_JIT)
def symmetrize(P):
    """P <- (P + P^T) / 2 in place."""
    n = P.shape[0]
    for i in range(n):
        for j in range(i + 1, n):
            v = 0.5 * (P[i, j] + P[j, i])
            P[i, j] = v
            P[j, i] = v
