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
  (reported) or estimated azimuth, initialized at its first bearing; a batch that initializes
  none runs in the subspace of the states its bearings touch (:func:`_bearing_batch_subspace`:
  O(m^2) per bearing for m of them, then one rank-m update of P).
* :func:`sd_doppler_batch`, :func:`sd_pseudorange_batch`: one vehicle's SD Dopplers /
  pseudoranges in the given order, with the screen's exclusions (thesis eq. 3.2-3.3); all
  vehicles of an epoch in one call: :func:`sd_pseudorange_vehicles`, :func:`sd_doppler_vehicles`.

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
from typing import Any

import numpy as np
from numba import njit, types
from numba.np.linalg import _BLAS

from v2v.estimation.process import _B11, _B12, _SERIES_MAX_A
from v2v.smallmat import cond2_symmetric, solve_small

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

_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


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
    s, st = _lazy_apply(x, P[:0], 0, p, idx, val, nnz, nu, r_var, gate_k, test)  # no buffered terms
    if st != ACCEPTED:
        return s, st
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
    """(tr(H2 P_d) / 2, tr((H2 P_d)^2) / 2): second-order mean and variance (Gelb 1974).

    For a UWB range ``hess`` is the Hessian of |d| alone, also with bias / scale states
    (h = (1 + s)|d| + b): the factor 1 + s and the cross term u . P[d, s] are left out
    (~1 % of the range sigma; see :meth:`v2v.estimation.filter.ClusterFilterBase._uwb_sequence`)."""
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
#: UWB bias / scale bound constraints (MacGougan (2009) eq. 3.19-3.22): a state outside its
#: bounds by at most this fraction of their width counts as on them. A pull leaves the state
#: on its bound up to round-off, and the compiled and the Python engines round differently:
#: without it, one of them could pull again (a record of NIS ~1e-50) where the other did not.
BOUND_TOL = 1e-9
_TILE = 32  # square tiles (8 KB of float64) for the passes that read or write P column-wise


_FLUSH_PANEL = 48  # column panels of the blocked flush (measured best of 48-100 at n = 156-316)
_FLUSH_BLOCKED_MIN_N = 128  # below this one dgemm of the whole Q^T Q is faster (fewer calls)


@njit(**_JIT)
def _sub_sym_block(P, g, o):
    """``P[o+i, o+j] -= g[min(i, j), max(i, j)]`` over the square block ``g``: the upper
    triangle of ``g`` subtracted from both halves of P's diagonal block (stays exactly symmetric)."""
    m = g.shape[0]
    for i in range(m):
        pi = P[o + i]
        gi = g[i]
        for j in range(i):
            pi[o + j] -= g[j, i]
        for j in range(i, m):
            pi[o + j] -= gi[j]


# dgemm with alpha and beta (C <- alpha A B + beta C), the BLAS entry point behind numba's own
# np.dot (numba.np.linalg: scipy's BLAS, resolved by name, so kernels using it stay cacheable);
# numba's np.dot has no alpha / beta and would need a product buffer and a subtraction pass.
_XXGEMM = _BLAS().numba_xxgemm(types.float64)
_CH_D, _CH_N, _CH_T = ord("d"), ord("N"), ord("T")


@njit(**_JIT)
def _flush_panels(n):
    """Edges of the flush's column panels of P: one panel below ``_FLUSH_BLOCKED_MIN_N``
    states, else ~``_FLUSH_PANEL`` wide, each starting on a multiple of 8 (aligned rows)."""
    nb = 1 if n < _FLUSH_BLOCKED_MIN_N else (n + _FLUSH_PANEL // 2) // _FLUSH_PANEL
    edges = np.empty(nb + 1, dtype=np.int64)
    for b in range(nb):
        edges[b] = ((b * n) // nb + 7) // 8 * 8
    edges[nb] = n
    return edges


@njit(**_JIT)
def _gemm_sub_block(P, X, Y, k, a0, a1, b0, b1, coef):
    """``P[a0:a1, b0:b1] -= X[:k, a0:a1]^T Y[:k, b0:b1]`` in place, one dgemm (all C-contiguous).

    Seen column-major (Fortran BLAS) the row-major block is ``C'[r, c] = P[a0 + c, b0 + r]``
    (ld = n) and X is ``X'[i, l] = X[l, i]`` (ld = its row length), Y alike, so the update is
    ``C' <- -1 Y'[b0:b1, :k] X'[a0:a1, :k]^T + 1 C'``."""
    return _XXGEMM(_CH_D, _CH_N, _CH_T, b1 - b0, a1 - a0, k, coef[0:].ctypes, Y[0:, b0:].ctypes, Y.shape[1],
                   X[0:, a0:].ctypes, X.shape[1], coef[1:].ctypes, P[a0:, b0:].ctypes, P.shape[1])


@njit(**_JIT)
def _sub_xty_symmetric(P, X, Y, k):
    """``P -= X[:k]^T Y[:k]`` for a product known to be symmetric (``X = Y`` in
    :func:`lazy_flush`): the upper block triangle computed in place, one dgemm per block
    (:func:`_flush_panels`), then copied into the lower one tile by tile, so P stays exactly
    symmetric; returns 0."""
    n = P.shape[0]
    coef = np.array([-1.0, 1.0])
    edges = _flush_panels(n)
    nb = edges.shape[0] - 1
    for bi in range(nb):
        for bj in range(bi, nb):
            if _gemm_sub_block(P, X, Y, k, edges[bi], edges[bi + 1], edges[bj], edges[bj + 1], coef) != 0:
                raise RuntimeError("_sub_xty_symmetric: BLAS dgemm failed")
    t = _TILE
    for ti in range(0, n, t):  # lower triangle <- upper (the lower blocks were not computed)
        for tj in range(0, ti + 1, t):
            for i in range(ti, min(ti + t, n)):
                for j in range(tj, min(tj + t, i)):
                    P[i, j] = P[j, i]
    return 0


@njit(**_JIT)
def lazy_flush(P, Q, kq):
    """Apply the buffered ``P -= Q[:kq]^T Q[:kq]``, P kept exactly symmetric; returns 0.

    The upper block triangle is updated in place, one dgemm per block (alpha = -1, beta = 1:
    no product buffer, no subtraction pass): below ``_FLUSH_BLOCKED_MIN_N`` states one block,
    from there column panels of ~48 (about half the multiply-adds), then the upper triangle
    is copied into the lower one tile by tile. Each entry gets what the former form gave it
    (``P - g`` with ``g`` one dgemm's upper triangle: the same sums, tested to the bit against
    it at 12-316 states): 34 -> 27 us at 152 states, 132 -> 106 us at 312
    (``benchmarks/bench_kernels.py``: this pass is about half of every batch kernel's time at
    N = 20). A P or Q that is not C-contiguous takes the former form (:func:`_lazy_flush_dot`)."""
    if kq == 0:
        return 0
    if not (P.flags.c_contiguous and Q.flags.c_contiguous):
        return _lazy_flush_dot(P, Q, kq)
    return _sub_xty_symmetric(P, Q, Q, kq)


@njit(**_JIT)
def _lazy_flush_dot(P, Q, kq):
    """:func:`lazy_flush` with numba's np.dot (any memory layout): small states one dgemm of the
    whole ``Q^T Q``, its upper triangle subtracted from both halves; from
    ``_FLUSH_BLOCKED_MIN_N`` states Q cut into column panels of ~48 and only the upper block
    triangle computed (panel-by-panel dgemm, diagonal blocks as above, each off-diagonal block
    subtracted from its block and, transposed, from the mirrored one)."""
    n = P.shape[0]
    if n < _FLUSH_BLOCKED_MIN_N:
        qk = Q[:kq]
        g = np.dot(qk.T, qk)
        _sub_sym_block(P, g, 0)
        return 0
    edges = _flush_panels(n)
    nb = edges.shape[0] - 1
    panels = [np.ascontiguousarray(Q[:kq, edges[b]:edges[b + 1]]) for b in range(nb)]
    for bi in range(nb):
        a0 = edges[bi]
        qa = panels[bi]
        _sub_sym_block(P, np.dot(qa.T, qa), a0)
        for bj in range(bi + 1, nb):
            b0 = edges[bj]
            gb = np.dot(qa.T, panels[bj])
            ma, mb = gb.shape
            for i in range(ma):  # upper block, row by row
                pi = P[a0 + i]
                gi = gb[i]
                for j in range(mb):
                    pi[b0 + j] -= gi[j]
            for j in range(mb):  # its mirror: the same values, transposed
                pj = P[b0 + j]
                for i in range(ma):
                    pj[a0 + i] -= gb[i, j]
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
    _rel_cov_block(P, Q, kq, sa, sb, out, 3)


@njit(**_JIT)
def _rel_cov_block(P, Q, kq, sa, sb, out, m):
    """:func:`_rel_cov_lazy`'s leading ``m x m`` block, the rest of ``out`` zero. ``m = 2`` for a
    bearing: its Hessian (:func:`bearing_hessian`) has no U row or column, so in
    :func:`_second_order` the other entries only ever meet exact zeros (the same mean and
    variance for a finite covariance, from 16 instead of 36 lazy entries)."""
    for i in range(3):
        for j in range(3):
            v = 0.0
            if i < m and j < m:
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
    s, st = _lazy_apply(x, Q, kq, p, idx, val, nnz, nu, r_var, gate_k, test)
    if st != ACCEPTED:
        return s, st, kq
    if kq == Q.shape[0]:
        kq = lazy_flush(P, Q, kq)
    return s, ACCEPTED, _lazy_push(Q, kq, p, s)


@njit(**_JIT)
def _lazy_apply(x, Q, kq, p, idx, val, nnz, nu, r_var, gate_k, test):
    """The common part of a lazy scalar update given ``p = P h^T`` of the stored covariance:
    ``p -= sum_k (q_k . h) q_k``, ``S = h p + r``, the checks and the innovation test, then
    ``x += p nu / S``. Returns ``(S, status)``; the caller buffers ``q = p / sqrt(S)``."""
    n = x.shape[0]
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
        return s, NONFINITE
    for i in range(n):
        if not math.isfinite(p[i]):
            return s, REJECTED
    if test and abs(nu) > gate_k * math.sqrt(s):
        return s, REJECTED
    g = nu / s
    for i in range(n):
        x[i] += p[i] * g
    return s, ACCEPTED


@njit(**_JIT)
def _lazy_push(Q, kq, p, s):
    """Buffer ``q = p / sqrt(S)`` as row ``kq`` of Q; returns the new length."""
    c = math.sqrt(1.0 / s)
    qk = Q[kq]
    for i in range(p.shape[0]):
        qk[i] = p[i] * c
    return kq + 1


# ------------------------------------------------------------------ deferred prediction (UWB event runs)
# Between two GNSS epochs a streamed run sees one UWB event per time tag (3 Hz x every pair), each
# preceded by a prediction. A prediction touches all of P (O(n^2)); the range update only needs
# P h^T and a few entries. So over a run of events the predictions are deferred too: with the
# accumulated transition Phi (the filter's F has at most two nonzeros per row: a *level* -
# position, clock, azimuth - integrates its *rate* - velocity, drift, azimuth rate -, every other
# state is kept; products of such F keep that form, Phi[i, i] = A[i], Phi[i, part[i]] = B[i])
# and the accumulated noise Qacc (block-diagonal: per vehicle 8x8, per azimuth pair 2x2, the
# random-walk diagonal; every vehicle block gets the same F and Q, as does every azimuth pair, so
# from the idle state all vehicle blocks of Qacc are one 8x8 matrix and all pair blocks one 2x2,
# each kept once),
#     P_now = Phi P Phi^T + Qacc - sum_k q_k q_k^T,
# where the buffered update vectors q_k are carried forward by each F (O(n) each). Entries and
# P_now h^T then cost O(nnz n + kq n); P is brought up to date (:func:`_lz_materialize`) when
# the buffer is full and at the end of the run: one O(n^2) pass per LAZY_RANK updates instead of
# three (predict, symmetrize, rank-1) per event. Equal to the event-by-event arithmetic up to
# round-off (tests/test_engines_agree.py).


@njit(**_JIT)
def _lz_state(n, veh0, nveh, az_ia, az_ir):
    """Idle deferred-prediction state for a state of size ``n``: (A, B, part, order, meta,
    Qv, Qaz, az_pair, az_slot, az_ia, az_ir, qdiag, pend); ``meta`` = (veh0, nveh, n_levels);
    ``Qv`` (8 x 8) the accumulated noise of every vehicle block, ``Qaz`` (2 x 2) of every
    azimuth pair."""
    a = np.ones(n)
    b = np.zeros(n)
    part = np.full(n, -1, dtype=np.int64)
    for k in range(nveh):
        s0 = veh0 + 8 * k
        for c in range(3):
            part[s0 + c] = s0 + c + 3
        part[s0 + 6] = s0 + 7
    npair = az_ia.shape[0]
    az_pair = np.full(n, -1, dtype=np.int64)
    az_slot = np.zeros(n, dtype=np.int64)
    for k in range(npair):
        part[az_ia[k]] = az_ir[k]
        az_pair[az_ia[k]] = k
        az_pair[az_ir[k]] = k
        az_slot[az_ir[k]] = 1
    order = np.empty(n, dtype=np.int64)
    nl = 0
    for i in range(n):
        if part[i] >= 0:
            order[nl] = i
            nl += 1
    m = nl
    for i in range(n):
        if part[i] < 0:
            order[m] = i
            m += 1
    meta = np.array([veh0, nveh, nl], dtype=np.int64)
    return (a, b, part, order, meta, np.zeros((8, 8)), np.zeros((2, 2)), az_pair, az_slot,
            az_ia, az_ir, np.zeros(n), np.zeros(1, dtype=np.int64))


@njit(**_JIT, inline="always")
def _lz_entry_of(P, Q, kq, a, b, part, veh0, nveh, qv, qaz, az_pair, az_slot, qdiag, i, j):
    """``P_now[i, j]`` from the unpacked deferred-prediction state (see above)."""
    pi, pj = part[i], part[j]
    v = a[i] * a[j] * P[i, j]
    if pj >= 0:
        v += a[i] * b[j] * P[i, pj]
    if pi >= 0:
        v += b[i] * a[j] * P[pi, j]
        if pj >= 0:
            v += b[i] * b[j] * P[pi, pj]
    if veh0 <= i < veh0 + 8 * nveh and veh0 <= j < veh0 + 8 * nveh:
        bi, bj = (i - veh0) // 8, (j - veh0) // 8
        if bi == bj:
            v += qv[i - veh0 - 8 * bi, j - veh0 - 8 * bj]
    if az_pair[i] >= 0 and az_pair[i] == az_pair[j]:
        v += qaz[az_slot[i], az_slot[j]]
    if i == j:
        v += qdiag[i]
    for k in range(kq):
        v -= Q[k, i] * Q[k, j]
    return v


@njit(**_JIT)
def _lz_entry(P, Q, kq, lz, i, j):
    """``P_now[i, j]`` (see above); :func:`_lazy_entry` when no prediction is pending."""
    if lz[12][0] == 0:  # (before unpacking the state: each array taken costs a reference count)
        return _lazy_entry(P, Q, kq, i, j)
    a, b, part, order, meta, qv, qaz, az_pair, az_slot, az_ia, az_ir, qdiag, pend = lz
    return _lz_entry_of(P, Q, kq, a, b, part, meta[0], meta[1], qv, qaz, az_pair, az_slot, qdiag, i, j)


@njit(**_JIT)
def _lz_rel_cov(P, Q, kq, lz, sa, sb, out):
    """:func:`_rel_cov_lazy` on ``P_now``; the state unpacked once for the 9-36 entries (taking
    its 13 arrays out of the tuple per entry cost a third of a UWB event run at N = 20)."""
    if lz[12][0] == 0:
        _rel_cov_lazy(P, Q, kq, sa, sb, out)
        return
    a, b, part, order, meta, qv, qaz, az_pair, az_slot, az_ia, az_ir, qdiag, pend = lz
    veh0, nveh = meta[0], meta[1]
    for i in range(3):
        for j in range(3):
            v = 0.0
            if sa >= 0:
                v += _lz_entry_of(P, Q, kq, a, b, part, veh0, nveh, qv, qaz, az_pair, az_slot, qdiag, sa + i, sa + j)
            if sb >= 0:
                v += _lz_entry_of(P, Q, kq, a, b, part, veh0, nveh, qv, qaz, az_pair, az_slot, qdiag, sb + i, sb + j)
            if sa >= 0 and sb >= 0:
                v -= (_lz_entry_of(P, Q, kq, a, b, part, veh0, nveh, qv, qaz, az_pair, az_slot, qdiag, sa + i, sb + j)
                      + _lz_entry_of(P, Q, kq, a, b, part, veh0, nveh, qv, qaz, az_pair, az_slot, qdiag, sb + i, sa + j))
            out[i, j] = v


@njit(**_JIT)
def _lz_update(x, P, Q, kq, lz, idx, val, nnz, nu, r_var, gate_k, test):
    """:func:`lazy_scalar_update` on ``P_now``: ``P_now h^T = Phi (P (Phi^T h^T)) + Qacc h^T -
    sum_k (q_k . h) q_k``; when the buffer is full, P is brought up to date first."""
    if lz[12][0] == 0:
        return lazy_scalar_update(x, P, Q, kq, idx, val, nnz, nu, r_var, gate_k, test)
    a, b, part, order, meta, qv, qaz, az_pair, az_slot, az_ia, az_ir, qdiag, pend = lz
    n = x.shape[0]
    w = np.zeros(n)
    for t in range(nnz):  # w = P Phi^T h^T
        i = idx[t]
        g = a[i] * val[t]
        row = P[i]
        for c in range(n):
            w[c] += row[c] * g
        if part[i] >= 0:
            g = b[i] * val[t]
            row = P[part[i]]
            for c in range(n):
                w[c] += row[c] * g
    p = np.empty(n)
    for c in range(n):  # p = Phi w
        p[c] = a[c] * w[c]
        if part[c] >= 0:
            p[c] += b[c] * w[part[c]]
    veh0, nveh = meta[0], meta[1]
    for t in range(nnz):  # + Qacc h^T
        i = idx[t]
        v = val[t]
        if veh0 <= i < veh0 + 8 * nveh:
            bi = (i - veh0) // 8
            s0 = veh0 + 8 * bi
            for c in range(8):
                p[s0 + c] += qv[c, i - s0] * v
        if az_pair[i] >= 0:
            k = az_pair[i]
            p[az_ia[k]] += qaz[0, az_slot[i]] * v
            p[az_ir[k]] += qaz[1, az_slot[i]] * v
        p[i] += qdiag[i] * v
    s, st = _lazy_apply(x, Q, kq, p, idx, val, nnz, nu, r_var, gate_k, test)
    if st != ACCEPTED:
        return s, st, kq
    if kq == Q.shape[0]:
        kq = _lz_materialize(P, Q, kq, lz)
    return s, ACCEPTED, _lazy_push(Q, kq, p, s)


@njit(**_JIT)
def _sym_block_update(qm, f, qd, m):
    """``qm <- f qm f^T + qd`` for an m x m block, upper triangle computed and mirrored (exactly symmetric)."""
    t = np.empty((m, m))
    for i in range(m):
        for j in range(m):
            acc = 0.0
            for k in range(m):
                acc += f[i, k] * qm[k, j]
            t[i, j] = acc
    for i in range(m):
        for j in range(i, m):
            acc = 0.0
            for k in range(m):
                acc += t[i, k] * f[j, k]
            acc += qd[i, j]
            qm[i, j] = acc
            qm[j, i] = acc


@njit(**_JIT)
def _lz_predict(x, Q, kq, lz, dt, vpar, rw_diag, rw_psd, apar, fb, qb, fa, qa):
    """Defer one prediction over ``dt``: x <- F x (the arithmetic of :func:`predict_all`), the
    buffered q_k <- F q_k (row by row), Phi <- F Phi, Qacc <- F Qacc F^T + Q (the one vehicle
    block and the one azimuth-pair block)."""
    a, b, part, order, meta, qv, qaz, az_pair, az_slot, az_ia, az_ir, qdiag, pend = lz
    veh0, nveh = meta[0], meta[1]
    if nveh:
        vehicle_fq(vpar, dt, fb, qb)
        for k in range(nveh):
            s0 = veh0 + 8 * k
            for c in range(3):
                x[s0 + c] = x[s0 + c] + fb[c, c + 3] * x[s0 + 3 + c]  # as _predict_gm_vehicle_blocks
                x[s0 + 3 + c] = fb[c + 3, c + 3] * x[s0 + 3 + c]
                b[s0 + c] = b[s0 + c] + fb[c, c + 3] * a[s0 + 3 + c]
                a[s0 + 3 + c] = fb[c + 3, c + 3] * a[s0 + 3 + c]
            x[s0 + 6] = x[s0 + 6] + fb[6, 7] * x[s0 + 7]
            x[s0 + 7] = fb[7, 7] * x[s0 + 7]
            b[s0 + 6] = b[s0 + 6] + fb[6, 7] * a[s0 + 7]
            a[s0 + 7] = fb[7, 7] * a[s0 + 7]
        f0, f1, f2, f6 = fb[0, 3], fb[1, 4], fb[2, 5], fb[6, 7]
        e0, e1, e2, e6 = fb[3, 3], fb[4, 4], fb[5, 5], fb[7, 7]
        for r in range(kq):
            q = Q[r]
            for k in range(nveh):
                s0 = veh0 + 8 * k
                q[s0] = q[s0] + f0 * q[s0 + 3]
                q[s0 + 3] = e0 * q[s0 + 3]
                q[s0 + 1] = q[s0 + 1] + f1 * q[s0 + 4]
                q[s0 + 4] = e1 * q[s0 + 4]
                q[s0 + 2] = q[s0 + 2] + f2 * q[s0 + 5]
                q[s0 + 5] = e2 * q[s0 + 5]
                q[s0 + 6] = q[s0 + 6] + f6 * q[s0 + 7]
                q[s0 + 7] = e6 * q[s0 + 7]
        _sym_block_update(qv, fb, qb, 8)
    for k in range(rw_diag.shape[0]):
        qdiag[rw_diag[k]] += rw_psd[k] * dt
    if az_ia.shape[0]:
        gm_block_into(apar[0], apar[1], dt, apar[2], fa, qa, 0, 1)
        for k in range(az_ia.shape[0]):
            i, j = az_ia[k], az_ir[k]
            xa, xr = x[i], x[j]
            x[i] = fa[0, 0] * xa + fa[0, 1] * xr  # as predict_pairs
            x[j] = fa[1, 0] * xa + fa[1, 1] * xr
            for r in range(kq):
                qa_, qr_ = Q[r, i], Q[r, j]
                Q[r, i] = fa[0, 0] * qa_ + fa[0, 1] * qr_
                Q[r, j] = fa[1, 1] * qr_
            b[i] = fa[0, 0] * b[i] + fa[0, 1] * a[j]
            a[i] = fa[0, 0] * a[i]
            a[j] = fa[1, 1] * a[j]
        _sym_block_update(qaz, fa, qa, 2)
    pend[0] = 1


@njit(**_JIT)
def _lz_materialize(P, Q, kq, lz):
    """P <- P_now (Phi P Phi^T in one in-place pass, + Qacc, - the buffered q_k q_k^T); the
    state back to idle. Returns 0 (the new buffer length)."""
    a, b, part, order, meta, qv, qaz, az_pair, az_slot, az_ia, az_ir, qdiag, pend = lz
    if pend[0]:
        n = P.shape[0]
        # Phi P Phi^T, upper triangle in ``order`` (levels first) and mirrored: every entry read
        # is still the old one ((level, level) entries read (level, rate) and (rate, rate) ones,
        # processed later; (level, rate) entries read (rate, rate) ones; those read themselves)
        for ii in range(n):
            i = order[ii]
            ai, bi, pi = a[i], b[i], part[i]
            for jj in range(ii, n):
                j = order[jj]
                pj = part[j]
                v = ai * a[j] * P[i, j]
                if pj >= 0:
                    v += ai * b[j] * P[i, pj]
                if pi >= 0:
                    v += bi * a[j] * P[pi, j]
                    if pj >= 0:
                        v += bi * b[j] * P[pi, pj]
                P[i, j] = v
                P[j, i] = v
        veh0, nveh = meta[0], meta[1]
        for k in range(nveh):
            s0 = veh0 + 8 * k
            for i in range(8):
                for j in range(8):
                    P[s0 + i, s0 + j] += qv[i, j]
        for k in range(az_ia.shape[0]):
            ij = (az_ia[k], az_ir[k])
            for i in range(2):
                for j in range(2):
                    P[ij[i], ij[j]] += qaz[i, j]
        for i in range(n):
            P[i, i] += qdiag[i]
        a[:] = 1.0
        b[:] = 0.0
        qv[:] = 0.0
        qaz[:] = 0.0
        qdiag[:] = 0.0
        pend[0] = 0
    return lazy_flush(P, Q, kq)


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
    recs = _uwb_records(m)
    Q = np.empty((LAZY_RANK, x.shape[0]))  # deferred rank-1 terms (see lazy_scalar_update)
    lz = _lz_state(0, 0, 0, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))  # idle: never read
    n_rec, kq = _uwb_ranges(x, P, Q, 0, lz, 0, m, sa, sb, ib, isc, z, r_var, gate_k, nl_frac,
                            bias_on, bias_lo, bias_hi, scale_on, scale_lo, scale_hi, recs, 0)
    lazy_flush(P, Q, kq)
    return n_rec, recs[0], recs[1], recs[2], recs[3], recs[4]


@njit(**_JIT)
def _uwb_records(m):
    """Record arrays (kind, meas, nu, S, status) for ``m`` ranges: at most 1 + 8 constraint
    records each (2 constraints x 4 passes)."""
    cap = m * 9
    return (np.zeros(cap, dtype=np.int64), np.zeros(cap, dtype=np.int64), np.zeros(cap), np.zeros(cap),
            np.zeros(cap, dtype=np.int64))


@njit(**_JIT)
def _uwb_ranges(x, P, Q, kq, lz, k0, k1, sa, sb, ib, isc, z, r_var, gate_k, nl_frac,
                bias_on, bias_lo, bias_hi, scale_on, scale_lo, scale_hi, recs, n_rec):
    """The ranges ``k0 <= k < k1`` of :func:`uwb_batch` on the lazily updated covariance
    (buffer ``Q[:kq]``, and the pending prediction ``lz`` of :func:`uwb_event_run`: see
    :func:`_lz_entry`); records appended to ``recs`` from ``n_rec``. Returns
    ``(n_rec, kq)``: the caller applies the buffer (:func:`_lz_materialize`)."""
    rec_kind, rec_meas, rec_nu, rec_s, rec_status = recs
    d = np.empty(3)
    hess = np.empty((3, 3))
    pd = np.empty((3, 3))
    idx = np.empty(8, dtype=np.int64)
    val = np.empty(8)
    for k in range(k0, k1):
        lim = r_var * nl_frac[k]
        _delta(x, sa[k], sb[k], d)
        range_hessian(d, hess)
        pending = lz[12][0] != 0  # a deferred prediction (uwb_event_run); else the plain lazy forms
        if pending:
            _lz_rel_cov(P, Q, kq, lz, sa[k], sb[k], pd)
        else:
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
        if pending:
            s, st, kq = _lz_update(x, P, Q, kq, lz, idx, val, nnz, nu, r_var + h2_var, gate_k, True)
        else:
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
                pii = _lz_entry(P, Q, kq, lz, i, i) if lz[12][0] != 0 else _lazy_entry(P, Q, kq, i, i)
                tol = BOUND_TOL * (hi - lo)  # (a state a pull left on its bound, up to round-off)
                if xi > hi + tol:
                    zc, rc = lo, pii * (hi - lo) / (xi - hi)
                elif xi < lo - tol:
                    zc, rc = hi, pii * (hi - lo) / (lo - xi)
                else:
                    continue
                idx[0] = i
                val[0] = 1.0
                nuc = zc - xi
                if lz[12][0] != 0:
                    sc, stc, kq = _lz_update(x, P, Q, kq, lz, idx, val, 1, nuc, rc, gate_k, False)
                else:
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
    return n_rec, kq


@njit(**_JIT)
def bearing_batch(x, P, sa, sb, iaz, az_ready, z, az_reported, r_var, gate_k, nl_frac, az_var0):
    """Sequential bearing updates (Petovello et al. eq. 5-6), one record per bearing.

    ``sa[k]``, ``sb[k]`` position-slice starts (-1 = lead); ``iaz[k]`` the azimuth state
    of a (-1: azimuth known, ``az_reported[k]`` used). ``az_ready`` (length n, indexed by
    the azimuth state) marks initialized azimuths and is updated in place: an azimuth is
    initialized at its first usable bearing to ``wrap(atan2(dE, dN) - beta)`` with variance
    ``az_var0`` and no correlations, then that bearing is applied (zero innovation).
    Status per bearing: DEGENERATE (horizontal distance < 1 m), DEFERRED, NONFINITE_INPUT
    (reported azimuth), NONFINITE, REJECTED, ACCEPTED. Returns ``(nu, s, status)``; P is
    complete on return.

    A batch whose azimuths are all known or already initialized runs in the subspace of the
    states it touches (:func:`_bearing_batch_subspace`: a few tens of states instead of the
    whole P per bearing); one that initializes an azimuth, or whose covariance rows of those
    states are not all finite, runs on the lazily updated covariance
    (:func:`_bearing_batch_lazy`). Both are the same sequential updates up to round-off.
    """
    for k in range(z.shape[0]):
        if iaz[k] >= 0 and not az_ready[iaz[k]]:
            return _bearing_batch_lazy(x, P, sa, sb, iaz, az_ready, z, az_reported, r_var, gate_k, nl_frac, az_var0)
    ok, nu, s, st = _bearing_batch_subspace(x, P, sa, sb, iaz, z, az_reported, r_var, gate_k, nl_frac)
    if not ok:
        return _bearing_batch_lazy(x, P, sa, sb, iaz, az_ready, z, az_reported, r_var, gate_k, nl_frac, az_var0)
    return nu, s, st


@njit(**_JIT)
def _bearing_row(e, n_, alpha, h2_mean):
    """A bearing's prediction ``wrap(atan2(E, N) - alpha)`` plus its second-order mean, and its
    Jacobian on (E, N) of ``d = p_b - p_a`` (Petovello et al. eq. 5-6): ``(h, N / r^2, -E / r^2)``."""
    h = wrap_angle(math.atan2(e, n_) - alpha) + h2_mean
    r2 = e * e + n_ * n_
    return h, n_ / r2, -e / r2


@njit(**_JIT)
def _bearing_batch_subspace(x, P, sa, sb, iaz, z, az_reported, r_var, gate_k, nl_frac):
    """:func:`bearing_batch` (every azimuth known or initialized) in the subspace of the
    states the bearings touch.

    A bearing's row h has nonzeros only on S, the horizontal positions of a and b (and a's
    azimuth state): the vertical entries of :func:`_bearing_batch_lazy`'s rows are zeros.
    With P0 the covariance at the start and C = P0[:, S], each sequential update (MacGougan
    (2009) eq. 3.16-3.18, in the form ``P -= q q^T``, ``q = P h^T / sqrt(S)``) has
    ``q_k = C c_k`` for an m-vector c_k (m = |S|): by induction ``P_k = P0 - C M_k C^T``,
    ``M_k = sum_{j<=k} c_j c_j^T``, so ``P_{k-1} h^T = C (h_S - W h_S)``, ``W = sum_{j<k}
    c_j u_j^T``, ``u_j = q_j[S]``; and ``x_k = x0 + C w_k``, ``w_k = sum_j c_j nu_j /
    sqrt(S_j)``. Everything a bearing needs (its innovation, S, the second-order terms, the
    test) lives in the m x m block ``P_k[S, S]`` and ``x_k[S]``, kept up to date per bearing
    (O(m^2) each: m = 38 states at N = 20 against the 152 of the whole state); x and P are
    brought up to date once at the end: ``x += C w``, ``P -= C M C^T`` (upper block triangle,
    dgemm, mirrored: exactly symmetric). The same arithmetic as the sequential updates up to
    round-off (the rows' zero vertical entries contribute exact zeros there).

    Returns ``(ok, nu, s, status)``; ``ok`` False (x, P untouched) when a covariance row of S
    is not finite: the caller then runs :func:`_bearing_batch_lazy`, whose per-update checks
    see the whole row.
    """
    n = x.shape[0]
    mb = z.shape[0]
    out_nu = np.zeros(mb)
    out_s = np.zeros(mb)
    out_st = np.zeros(mb, dtype=np.int64)
    need = np.zeros(n, dtype=np.bool_)
    for k in range(mb):
        if sa[k] >= 0:
            need[sa[k]] = True
            need[sa[k] + 1] = True
        if sb[k] >= 0:
            need[sb[k]] = True
            need[sb[k] + 1] = True
        if iaz[k] >= 0:
            need[iaz[k]] = True
    slot = np.full(n, -1, dtype=np.int64)  # state index -> index in S (ascending state order)
    idx_s = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        if need[i]:
            slot[i] = m
            idx_s[m] = i
            m += 1
    ct = np.empty((m, n))  # C^T: row a = P0[S[a], :] (P symmetric)
    for a in range(m):
        row = P[idx_s[a]]
        for i in range(n):
            if not math.isfinite(row[i]):
                return False, out_nu, out_s, out_st
            ct[a, i] = row[i]
    pss = np.empty((m, m))  # P_k[S, S]
    for a in range(m):
        for b in range(m):
            pss[a, b] = ct[a, idx_s[b]]
    xs = np.empty(m)  # x_k[S]
    for a in range(m):
        xs[a] = x[idx_s[a]]
    wt = np.zeros((m, m))  # W^T
    g = np.empty((mb, m))  # the accepted updates' c_k, one per row
    w = np.zeros(m)
    p = np.empty(m)
    c = np.empty(m)
    hess = np.empty((3, 3))
    pd = np.empty((3, 3))
    no_q = np.empty((0, m))
    d = np.zeros(3)
    hs = np.empty(5, dtype=np.int64)
    hv = np.empty(5)
    ng = 0
    for k in range(mb):
        lim = r_var * nl_frac[k]
        ia = slot[sa[k]] if sa[k] >= 0 else -1
        ib = slot[sb[k]] if sb[k] >= 0 else -1
        for i in range(2):  # (_delta's horizontal part: the vertical one is not used)
            d[i] = (xs[ib + i] if ib >= 0 else 0.0) - (xs[ia + i] if ia >= 0 else 0.0)
        if math.hypot(d[0], d[1]) < 1.0:
            out_st[k] = DEGENERATE
            continue
        bearing_hessian(d, hess)
        _rel_cov_block(pss, no_q, 0, ia, ib, pd, 2)  # (its horizontal block, on P_k[S, S]: no buffer)
        h2_mean, h2_var = _second_order(hess, pd)
        if not h2_var <= lim:
            out_st[k] = DEFERRED
            continue
        iz = slot[iaz[k]] if iaz[k] >= 0 else -1
        if iz >= 0:
            alpha = xs[iz]
        else:
            alpha = az_reported[k]
            if not math.isfinite(alpha):
                out_st[k] = NONFINITE_INPUT
                continue
        h, j0, j1 = _bearing_row(d[0], d[1], alpha, h2_mean)
        nnz = 0
        if ia >= 0:
            hs[0], hs[1] = ia, ia + 1
            hv[0], hv[1] = -j0, -j1
            nnz = 2
        if ib >= 0:
            hs[nnz], hs[nnz + 1] = ib, ib + 1
            hv[nnz], hv[nnz + 1] = j0, j1
            nnz += 2
        if iz >= 0:
            hs[nnz] = iz
            hv[nnz] = -1.0
            nnz += 1
        nu = wrap_angle(z[k] - h)
        p[:] = 0.0  # P_k[S, S] h_S
        for t in range(nnz):
            row = pss[hs[t]]
            vt = hv[t]
            for a in range(m):
                p[a] += row[a] * vt
        s = 0.0
        for t in range(nnz):
            s += hv[t] * p[hs[t]]
        s += r_var + h2_var
        out_nu[k] = nu
        out_s[k] = s
        if not (math.isfinite(nu) and math.isfinite(s) and s > 0.0):
            out_st[k] = NONFINITE
            continue
        finite = True
        for a in range(m):
            if not math.isfinite(p[a]):
                finite = False
                break
        if not finite or abs(nu) > gate_k * math.sqrt(s):
            out_st[k] = REJECTED
            continue
        gain = nu / s
        for a in range(m):
            xs[a] += p[a] * gain
        rs = math.sqrt(1.0 / s)
        for a in range(m):
            p[a] *= rs  # u_k = q_k[S]
        c[:] = 0.0  # c_k = (h_S - W h_S) / sqrt(S)
        for t in range(nnz):
            row = wt[hs[t]]
            vt = hv[t]
            for a in range(m):
                c[a] -= row[a] * vt
        for t in range(nnz):
            c[hs[t]] += hv[t]
        for a in range(m):
            c[a] *= rs
        for a in range(m):  # P_k[S, S] -= u u^T (exactly symmetric), W^T += u c^T
            ua = p[a]
            pa = pss[a]
            wa = wt[a]
            for b in range(m):
                pa[b] -= ua * p[b]
                wa[b] += ua * c[b]
        for a in range(m):
            g[ng, a] = c[a]
        ng += 1
        f = nu * rs
        for a in range(m):
            w[a] += c[a] * f
        out_st[k] = ACCEPTED
    if ng > 0:
        for a in range(m):  # x += C w
            wa = w[a]
            row = ct[a]
            for i in range(n):
                x[i] += wa * row[i]
        for a in range(m):  # x[S] as the sequential updates left it (C[S, :] w = P0[S, S] w cancels digits)
            x[idx_s[a]] = xs[a]
        gk = g[:ng]
        mm = np.dot(gk.T, gk)  # M = sum_k c_k c_k^T
        _sub_xty_symmetric(P, np.dot(mm, ct), ct, m)  # P -= (C M) C^T: (M C^T)^T C^T
    return True, out_nu, out_s, out_st


@njit(**_JIT)
def _bearing_batch_lazy(x, P, sa, sb, iaz, az_ready, z, az_reported, r_var, gate_k, nl_frac, az_var0):
    """:func:`bearing_batch` on the lazily updated covariance (any batch: estimated azimuths
    initialized at their first bearing included).

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
        _rel_cov_block(P, Q, kq, sa[k], sb[k], pd, 2)  # (a bearing's second order: horizontal only)
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
        h, j0, j1 = _bearing_row(d[0], d[1], alpha, h2_mean)
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
def _update_or_exclude(x, P, Q, kq, idx, val, nnz, nu, r_var, gate_k, excluded):
    """One measurement of a GNSS batch: an ``excluded`` one (left out by the screen) is only
    reported, ``(S, EXCLUDED or NONFINITE, kq)`` with x, P untouched; any other goes through
    :func:`lazy_scalar_update` with the innovation test. Returns ``(S, status, kq)``."""
    if excluded:
        s = _excluded_s(P, Q, kq, idx, val, nnz, r_var)
        return s, (EXCLUDED if (math.isfinite(nu) and math.isfinite(s) and s > 0.0) else NONFINITE), kq
    return lazy_scalar_update(x, P, Q, kq, idx, val, nnz, nu, r_var, gate_k, True)


@njit(**_JIT)
def sd_doppler_batch(x, P, Q, kq, base, base_vel, rot, ps, vs, idrift, sv, svv, rate_lead, z, order, excluded,
                     r_var, gate_k):
    """One vehicle's SD pseudorange-rate updates in ``order`` (models.SdDopplerRows.row).

    ``h = u . (vsv - v) - rate_lead + drift`` with ``v = base_vel + R^T dv``; Jacobian
    d/d p = R (-(dv - u rate) / rho), d/d dv = -R u, d/d drift = 1 (``ps``, ``vs``: position
    and velocity slice starts, ``idrift``: drift index). ``excluded[o]``: reported with
    (nu, S) at the current state and not applied (status EXCLUDED, or NONFINITE). On the
    lazily updated ``P - Q[:kq]^T Q[:kq]`` (:func:`lazy_scalar_update`), not flushed.
    Returns ``(nu, s, status, kq)``, the first three indexed like ``order``.
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
        s, st, kq = _update_or_exclude(x, P, Q, kq, idx, val, 7, nu, r_var, gate_k, excluded[o])
        out_nu[k], out_s[k], out_st[k] = nu, s, st
    return out_nu, out_s, out_st, kq


@njit(**_JIT)
def sd_pseudorange_batch(x, P, Q, kq, base, rot, ps, iclk, sv, rho_lead, z, order, excluded, r_var, gate_k):
    """One vehicle's SD pseudorange updates in ``order`` (models.SdPseudorangeRows.row).

    ``h = |sv - (base + R^T p)| - rho_lead + clk`` (MacGougan (2009) eq. 3.2-3.3), Jacobian
    ``(-R u, 1)`` on (position, clock). ``excluded`` as in :func:`sd_doppler_batch`. On the
    lazily updated ``P - Q[:kq]^T Q[:kq]``, not flushed. Returns ``(nu, s, status, kq)``.
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
        s, st, kq = _update_or_exclude(x, P, Q, kq, idx, val, 4, nu, r_var, gate_k, excluded[o])
        out_nu[k], out_s[k], out_st[k] = nu, s, st
    return out_nu, out_s, out_st, kq


@njit(**_JIT)
def _is_gm_vehicle_f(fb):
    """Is ``fb`` the process model's vehicle-block F: [p(3), v(3), clk, drift] with
    ``p' = p + f v``, ``v' = e v``, ``clk' = clk + f_d drift``, ``drift' = e_d drift``
    (unit diagonal on p and clk, nothing else)?"""
    for i in range(8):
        for j in range(8):
            allowed = i == j or (i < 3 and j == i + 3) or (i == 6 and j == 7)
            if not allowed and fb[i, j] != 0.0:
                return False
    return fb[0, 0] == 1.0 and fb[1, 1] == 1.0 and fb[2, 2] == 1.0 and fb[6, 6] == 1.0


@njit(**_JIT)
def _predict_gm_vehicle_blocks(x, P, s0, m, fb, qb):
    """:func:`predict_vehicle_blocks` for the process model's F (:func:`_is_gm_vehicle_f`):
    the same products in the same order, applied in place as row / column axpy and scale
    operations (level += f * rate before rate *= e), with no temporaries."""
    n = x.shape[0]
    for a in range(m):
        s = s0 + 8 * a
        for i in range(3):
            x[s + i] = x[s + i] + fb[i, i + 3] * x[s + 3 + i]
            x[s + 3 + i] = fb[i + 3, i + 3] * x[s + 3 + i]
        x[s + 6] = x[s + 6] + fb[6, 7] * x[s + 7]
        x[s + 7] = fb[7, 7] * x[s + 7]
        # rows: P[s:s+8, :] <- fb @ P[s:s+8, :]
        for i in range(3):
            f = fb[i, i + 3]
            e = fb[i + 3, i + 3]
            rp = P[s + i]
            rv = P[s + 3 + i]
            for c in range(n):
                rp[c] = rp[c] + f * rv[c]
            for c in range(n):
                rv[c] = e * rv[c]
        f = fb[6, 7]
        e = fb[7, 7]
        rc = P[s + 6]
        rd = P[s + 7]
        for c in range(n):
            rc[c] = rc[c] + f * rd[c]
        for c in range(n):
            rd[c] = e * rd[c]
    # columns: P[:, s:s+8] <- P[:, s:s+8] @ fb^T
    for r in range(n):
        row = P[r]
        for a in range(m):
            s = s0 + 8 * a
            for i in range(3):
                row[s + i] = row[s + i] + row[s + 3 + i] * fb[i, i + 3]
                row[s + 3 + i] = row[s + 3 + i] * fb[i + 3, i + 3]
            row[s + 6] = row[s + 6] + row[s + 7] * fb[6, 7]
            row[s + 7] = row[s + 7] * fb[7, 7]
    for a in range(m):
        s = s0 + 8 * a
        for i in range(8):
            for j in range(8):
                P[s + i, s + j] += qb[i, j]


@njit(**_JIT)
def predict_pairs(x, P, ia, ir, fa, qa):
    """x <- F x, P <- F P F^T + Q for 2-state [level, rate] pairs (``ia[k]``, ``ir[k]``) that
    share one 2x2 ``fa``, ``qa`` (estimated azimuth + azimuth rate), identity elsewhere;
    all rows first, then all columns (in place, not symmetrized)."""
    n = x.shape[0]
    for k in range(ia.shape[0]):
        i, j = ia[k], ir[k]
        xa, xr = x[i], x[j]
        x[i] = fa[0, 0] * xa + fa[0, 1] * xr
        x[j] = fa[1, 0] * xa + fa[1, 1] * xr
        ra = P[i]
        rr = P[j]
        for c in range(n):
            va, vr = ra[c], rr[c]
            ra[c] = fa[0, 0] * va + fa[0, 1] * vr
            rr[c] = fa[1, 0] * va + fa[1, 1] * vr
    for r in range(n):
        row = P[r]
        for k in range(ia.shape[0]):
            i, j = ia[k], ir[k]
            ca, cr = row[i], row[j]
            row[i] = ca * fa[0, 0] + cr * fa[0, 1]
            row[j] = ca * fa[1, 0] + cr * fa[1, 1]
    for k in range(ia.shape[0]):
        i, j = ia[k], ir[k]
        P[i, i] += qa[0, 0]
        P[i, j] += qa[0, 1]
        P[j, i] += qa[1, 0]
        P[j, j] += qa[1, 1]


@njit(**_JIT)
def predict_vehicle_blocks(x, P, s0, m, fb, qb):
    """x <- F x, P <- F P F^T + Q for ``m`` contiguous 8-state vehicle blocks from ``s0``
    (F = blockdiag(fb), identity elsewhere; Q = blockdiag(qb)), in place (not symmetrized).

    Only the nonzeros of ``fb`` are used (12 of 64 for [p, v, clk, drift]: position
    integrates velocity, the clock integrates the drift).
    """
    n = x.shape[0]
    if _is_gm_vehicle_f(fb):
        _predict_gm_vehicle_blocks(x, P, s0, m, fb, qb)
        return
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
    """P <- (P + P^T) / 2 in place (tile by tile, so that the column accesses stay in cache)."""
    n = P.shape[0]
    t = _TILE
    for bi in range(0, n, t):
        for bj in range(bi, n, t):
            for i in range(bi, min(bi + t, n)):
                for j in range(max(bj, i + 1), min(bj + t, n)):
                    v = 0.5 * (P[i, j] + P[j, i])
                    P[i, j] = v
                    P[j, i] = v


# ------------------------------------------------------------------ prediction in one call
# ClusterEkf._predict_core (process.vehicle_block / azimuth_block F and Q, the vehicle blocks,
# the random-walk diagonal, the azimuth pairs, symmetrize) as one kernel: the closed-form
# Gauss-Markov discretization of v2v.estimation.process.gm_integrated_block evaluated here
# with the same operations in the same order (bit-identical: tests/test_process_closed_form.py).

_B11_C = np.array(_B11)
_B12_C = np.array(_B12)


@njit(**_JIT)
def _horner(c, a):
    acc = 0.0
    for k in range(c.shape[0]):
        acc = acc * a + c[k]
    return acc


@njit(**_JIT)
def gm_block_into(tau, sigma, dt, extra_psd_level0, f, q, i, j):
    """:func:`v2v.estimation.process.gm_integrated_block` (Pabolleta (2021) eq. 3.6 in closed
    form) written into ``f[i|j, i|j]``, ``q[i|j, i|j]`` (level ``i``, GM rate ``j``)."""
    qc = 2.0 * math.pow(sigma, 2.0) / tau
    a = dt / tau
    u1 = -math.expm1(-a)
    u2 = -math.expm1(-2.0 * a)
    if a < _SERIES_MAX_A:
        b11 = _horner(_B11_C, a)
        b12 = _horner(_B12_C, a)
    else:
        b11 = a - 2.0 * u1 + 0.5 * u2
        b12 = u1 - 0.5 * u2
    f[i, i] = 1.0
    f[i, j] = tau * u1
    f[j, i] = 0.0
    f[j, j] = math.exp(-a)
    q[i, i] = extra_psd_level0 * dt + qc * math.pow(tau, 3.0) * b11
    q12 = qc * math.pow(tau, 2.0) * b12
    q[i, j] = q12
    q[j, i] = q12
    q[j, j] = qc * tau * 0.5 * u2


@njit(**_JIT)
def vehicle_fq(vpar, dt, fb, qb):
    """The 8x8 (F, Q) of :func:`v2v.estimation.process.vehicle_block` into ``fb``, ``qb``.
    ``vpar`` = (vel_tau_s, vel_sigma_horizontal, vel_sigma_vertical, drift_tau_s,
    drift_sigma, clock_bias_psd) (:func:`process_parameters`)."""
    fb[:, :] = 0.0
    qb[:, :] = 0.0
    for axis in range(3):
        gm_block_into(vpar[0], vpar[1] if axis < 2 else vpar[2], dt, 0.0, fb, qb, axis, 3 + axis)
    gm_block_into(vpar[3], vpar[4], dt, vpar[5], fb, qb, 6, 7)


@njit(**_JIT)
def predict_all(x, P, dt, veh0, nveh, vpar, rw_diag, rw_psd, az_ia, az_ir, apar, fb, qb, fa, qa):
    """x <- F x, P <- F P F^T + Q over ``dt`` for the whole state (ClusterEkf._predict_core):
    ``nveh`` contiguous vehicle blocks from ``veh0`` (:func:`vehicle_fq`), random walks
    (``P[i, i] += psd_i dt``), azimuth / azimuth-rate pairs (``apar`` = yaw-rate tau, sigma,
    azimuth random-walk PSD), then :func:`symmetrize`. ``fb``, ``qb`` (8x8), ``fa``, ``qa``
    (2x2) are scratch."""
    if nveh:
        vehicle_fq(vpar, dt, fb, qb)
        predict_vehicle_blocks(x, P, veh0, nveh, fb, qb)
    for k in range(rw_diag.shape[0]):
        P[rw_diag[k], rw_diag[k]] += rw_psd[k] * dt
    if az_ia.shape[0]:
        gm_block_into(apar[0], apar[1], dt, apar[2], fa, qa, 0, 1)
        predict_pairs(x, P, az_ia, az_ir, fa, qa)
    symmetrize(P)


@njit(**_JIT)
def uwb_event_run(x, P, dts, starts, sa, sb, ib, isc, z, r_var, gate_k, nl_frac,
                  bias_on, bias_lo, bias_hi, scale_on, scale_lo, scale_hi,
                  veh0, nveh, vpar, rw_diag, rw_psd, az_ia, az_ir, apar):
    """A run of UWB events (one time tag each): for event ``e``, the prediction over
    ``dts[e]`` (:func:`predict_all`'s model; skipped when 0), then its ranges
    ``starts[e] <= k < starts[e + 1]`` as in :func:`uwb_batch`: the filter's ``predict`` +
    ``update_uwb`` per event, without the per-event Python, and with the predictions and
    covariance updates deferred (see "deferred prediction" above; P is complete on return).
    Returns :func:`uwb_batch`'s records (``rec_meas`` indexes the concatenated ranges)."""
    m = z.shape[0]
    recs = _uwb_records(m)
    Q = np.empty((LAZY_RANK, x.shape[0]))
    fb = np.empty((8, 8))
    qb = np.empty((8, 8))
    fa = np.empty((2, 2))
    qa = np.empty((2, 2))
    lz = _lz_state(x.shape[0], veh0, nveh, az_ia, az_ir)
    n_rec = 0
    kq = 0
    for e in range(dts.shape[0]):
        if dts[e] > 0.0:
            _lz_predict(x, Q, kq, lz, dts[e], vpar, rw_diag, rw_psd, apar, fb, qb, fa, qa)
        if starts[e + 1] > starts[e]:
            n_rec, kq = _uwb_ranges(x, P, Q, kq, lz, starts[e], starts[e + 1], sa, sb, ib, isc, z, r_var, gate_k,
                                    nl_frac, bias_on, bias_lo, bias_hi, scale_on, scale_lo, scale_hi, recs, n_rec)
    _lz_materialize(P, Q, kq, lz)
    return n_rec, recs[0], recs[1], recs[2], recs[3], recs[4]


# ------------------------------------------------------------------ GNSS epoch sequencing
# The per-vehicle preparation of an epoch's SD pseudoranges / Dopplers (satellite pairing and
# elevation order, the Baarda w-test screen, the first-update order, the clock-jump test) in
# compiled form: the same rules as the plain-numpy code they replace in
# v2v.estimation.filter (ClusterFilterBase.update_gnss, _first_unflagged_order, _clock_jump).


@njit(**_JIT)
def screen_blunders(h, r, sigma, k):
    """Least-squares data snooping (Baarda w-test), see :func:`v2v.estimation.filter.screen_blunders_status`.

    ``h`` (m, p) design matrix, ``r`` (m,) residuals. While the redundancy is >= 2: form
    ``N = H^T H`` (stop, not isolated, if ``cond(N) > 1e12`` or not finite:
    :func:`v2v.smallmat.cond2_symmetric`), ``N^-1 H^T`` (:func:`v2v.smallmat.solve_small`),
    ``e = r - H N^-1 H^T r``, ``Q_e,ii = 1 - (H N^-1 H^T)_ii``,
    ``w_i = |e_i| / (sigma sqrt(Q_e,ii))`` (MacGougan (2009) section 3.5.1); stop
    (isolated) if ``max w <= k``, else flag the largest. Small fixed-size linear algebra
    written out (no LAPACK calls: ~4 us instead of 6.3 us per screen). Returns
    ``(flagged (m,), isolated)``.
    """
    m, npar = h.shape
    flagged = np.zeros(m, dtype=np.bool_)
    use = np.empty(m, dtype=np.int64)
    n_mat = np.empty((npar, npar))
    hu = np.empty((m, npar))
    ru = np.empty(m)
    dx = np.empty(npar)
    n_use = m
    while n_use - npar >= 2:
        c = 0
        for i in range(m):
            if not flagged[i]:
                use[c] = i
                c += 1
        for a in range(c):
            ru[a] = r[use[a]]
            for j in range(npar):
                hu[a, j] = h[use[a], j]
        finite = True
        for i in range(npar):
            for j in range(npar):
                v = 0.0
                for a in range(c):
                    v += hu[a, i] * hu[a, j]
                n_mat[i, j] = v
                if not math.isfinite(v):
                    finite = False
        if not finite:
            return flagged, False
        if not cond2_symmetric(n_mat) <= 1e12:  # (also NaN: a zero matrix)
            return flagged, False
        sol = solve_small(n_mat, np.ascontiguousarray(hu[:c].T))  # N^-1 H^T
        for j in range(npar):
            v = 0.0
            for a in range(c):
                v += sol[j, a] * ru[a]
            dx[j] = v
        best = -1.0
        jbest = 0
        for a in range(c):
            fit = 0.0
            qh = 0.0
            for j in range(npar):
                fit += hu[a, j] * dx[j]
                qh += hu[a, j] * sol[j, a]
            e = ru[a] - fit
            qe = 1.0 - qh
            w = abs(e) / (sigma * math.sqrt(max(qe, 1e-12)))
            if math.isnan(w):  # np.argmax returns the first NaN; NaN <= k is False -> flagged
                best = w
                jbest = a
                break
            if w > best:
                best = w
                jbest = a
        if best <= k:
            return flagged, True
        flagged[use[jbest]] = True
        n_use -= 1
    return flagged, False


@njit(**_JIT)
def first_unflagged_order(h_pred, val, z, sigma, k, cols):
    """Elevation order with the highest-elevation w-test-clean measurement first
    (:meth:`v2v.estimation.filter.ClusterFilterBase._first_unflagged_order`).

    Screens ``z - h_pred`` on the last ``cols`` Jacobian columns. Returns ``(order, excluded,
    isolated, n_flagged)``: ``excluded`` = the flagged ones when more than one was flagged.
    """
    m = h_pred.shape[0]
    order = np.arange(m)
    excluded = np.zeros(m, dtype=np.bool_)
    if m < cols + 2:
        return order, excluded, False, 0
    nv = val.shape[1]
    h = np.empty((m, cols))
    res = np.empty(m)
    for i in range(m):
        res[i] = z[i] - h_pred[i]
        for j in range(cols):
            h[i, j] = val[i, nv - cols + j]
    flagged, isolated = screen_blunders(h, res, sigma, k)
    n_flag = 0
    first = -1
    for i in range(m):
        if flagged[i]:
            n_flag += 1
        elif first < 0:
            first = i
    if n_flag > 0:
        if first < 0:
            first = 0
        order[0] = first
        c = 1
        for i in range(m):
            if i != first:
                order[c] = i
                c += 1
        if n_flag > 1:
            excluded[:] = flagged
    return order, excluded, isolated, n_flag


@njit(**_JIT)
def sd_pseudorange_rows(x, base, rot, ps, iclk, sv, rho_lead, clk):
    """(h (m,), val (m, 4)) of one vehicle's SD pseudoranges at ``x`` with the clock state
    replaced by ``clk`` (models.SdPseudorangeRows.all; arithmetic of sd_pseudorange_batch)."""
    m = sv.shape[0]
    h = np.empty(m)
    val = np.empty((m, 4))
    r_v = np.empty(3)
    _abs3(base, rot, x, ps, r_v)
    for o in range(m):
        d0, d1, d2 = sv[o, 0] - r_v[0], sv[o, 1] - r_v[1], sv[o, 2] - r_v[2]
        rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        h[o] = (rho - rho_lead[o]) + clk
        u0, u1, u2 = d0 / rho, d1 / rho, d2 / rho
        for i in range(3):
            val[o, i] = -(rot[i, 0] * u0 + rot[i, 1] * u1 + rot[i, 2] * u2)
        val[o, 3] = 1.0
    return h, val


@njit(**_JIT)
def clock_jump_test(P, idx, h_pred, val, z, r_var, k):
    """Common-mode test of one vehicle's SD pseudorange innovations
    (:meth:`v2v.estimation.filter.ClusterFilterBase._clock_jump`): ``nu_i = z_i - h_i``,
    ``S_i = h_i P h_i^T + r``; a jump when more than half fail ``|nu| <= k sqrt(S)``, all of
    those with one sign, and a majority pass ``|nu - median(nu)| <= k sqrt(S)``.
    Returns ``(jump, median(nu))``."""
    return _clock_jump_test_q(P, np.empty((1, 1)), 0, idx, h_pred, val, z, r_var, k)


@njit(**_JIT)
def _clock_jump_test_q(P, Q, kq, idx, h_pred, val, z, r_var, k):
    """:func:`clock_jump_test` on the lazily updated ``P - Q[:kq]^T Q[:kq]``."""
    n = h_pred.shape[0]
    if n < 3:
        return False, 0.0
    nnz = idx.shape[0]
    nu = np.empty(n)
    gate = np.empty(n)
    n_fail = 0
    n_pos = 0
    n_neg = 0
    for i in range(n):
        nu[i] = z[i] - h_pred[i]
        s = 0.0
        for a in range(nnz):
            t = 0.0
            for b in range(nnz):
                t += _lazy_entry(P, Q, kq, idx[a], idx[b]) * val[i, b]
            s += val[i, a] * t
        gate[i] = k * math.sqrt(s + r_var)
        if abs(nu[i]) > gate[i]:
            n_fail += 1
            if nu[i] > 0.0:
                n_pos += 1
            elif nu[i] < 0.0:
                n_neg += 1
    if 2 * n_fail <= n or not (n_pos == n_fail or n_neg == n_fail):
        return False, 0.0
    med = np.median(nu)
    n_ok = 0
    for i in range(n):
        if abs(nu[i] - med) <= gate[i]:
            n_ok += 1
    if 2 * n_ok <= n:
        return False, 0.0
    return True, med


@njit(**_JIT)
def sd_doppler_rows(x, base, base_vel, rot, ps, vs, idrift, sv, svv, rate_lead):
    """(h (m,), val (m, 7)) of one vehicle's SD Dopplers at ``x`` (models.SdDopplerRows.all;
    arithmetic of sd_doppler_batch)."""
    m = sv.shape[0]
    h = np.empty(m)
    val = np.empty((m, 7))
    r_v = np.empty(3)
    v_v = np.empty(3)
    u = np.empty(3)
    dv = np.empty(3)
    g = np.empty(3)
    _abs3(base, rot, x, ps, r_v)
    _abs3(base_vel, rot, x, vs, v_v)
    for o in range(m):
        d0, d1, d2 = sv[o, 0] - r_v[0], sv[o, 1] - r_v[1], sv[o, 2] - r_v[2]
        rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        u[0], u[1], u[2] = d0 / rho, d1 / rho, d2 / rho
        for i in range(3):
            dv[i] = svv[o, i] - v_v[i]
        rate = u[0] * dv[0] + u[1] * dv[1] + u[2] * dv[2]
        h[o] = (rate - rate_lead[o]) + x[idrift]
        for i in range(3):
            g[i] = -(dv[i] - u[i] * rate) / rho
        for i in range(3):
            val[o, i] = rot[i, 0] * g[0] + rot[i, 1] * g[1] + rot[i, 2] * g[2]
            val[o, 3 + i] = -(rot[i, 0] * u[0] + rot[i, 1] * u[1] + rot[i, 2] * u[2])
        val[o, 6] = 1.0
    return h, val


@njit(**_JIT)
def pair_satellites(prn_v, prn_lead, pr_v, pr_lead, sv_lead, base, rot):
    """Satellites seen by a vehicle and the lead, highest elevation first (update_gnss).

    Common PRNs in ascending PRN order (``np.intersect1d(..., return_indices=True)``: first
    occurrence in each list), without those whose pseudorange is non-finite in either
    (counted), then stably sorted by decreasing elevation seen from the base,
    ``atan2(up, hypot(east, north))`` of ``R (sv - base)``. Returns ``(iv, il, el, n_bad)``.
    """
    nl = prn_lead.shape[0]
    nv = prn_v.shape[0]
    # first occurrence of each PRN in each list, then the common ones in PRN order
    sl = np.argsort(prn_lead, kind="mergesort")
    sv_ = np.argsort(prn_v, kind="mergesort")
    iv = np.empty(min(nl, nv), dtype=np.int64)
    il = np.empty(min(nl, nv), dtype=np.int64)
    a = 0
    b = 0
    c = 0
    while a < nv and b < nl:
        pa = prn_v[sv_[a]]
        pb = prn_lead[sl[b]]
        if pa < pb:
            a += 1
        elif pb < pa:
            b += 1
        else:
            iv[c] = sv_[a]
            il[c] = sl[b]
            c += 1
            while a < nv and prn_v[sv_[a]] == pa:
                a += 1
            while b < nl and prn_lead[sl[b]] == pb:
                b += 1
    n_bad = 0
    keep = 0
    for i in range(c):
        if math.isfinite(pr_v[iv[i]]) and math.isfinite(pr_lead[il[i]]):
            iv[keep] = iv[i]
            il[keep] = il[i]
            keep += 1
        else:
            n_bad += 1
    iv = iv[:keep]
    il = il[:keep]
    neg_el = np.empty(keep)
    for i in range(keep):
        j = il[i]
        e0 = sv_lead[j, 0] - base[0]
        e1 = sv_lead[j, 1] - base[1]
        e2 = sv_lead[j, 2] - base[2]
        de = e0 * rot[0, 0] + e1 * rot[0, 1] + e2 * rot[0, 2]
        dn = e0 * rot[1, 0] + e1 * rot[1, 1] + e2 * rot[1, 2]
        du = e0 * rot[2, 0] + e1 * rot[2, 1] + e2 * rot[2, 2]
        neg_el[i] = -math.atan2(du, math.hypot(de, dn))
    order = np.argsort(neg_el, kind="mergesort")
    el = np.empty(keep)
    ivs = np.empty(keep, dtype=np.int64)
    ils = np.empty(keep, dtype=np.int64)
    for i in range(keep):
        el[i] = -neg_el[order[i]]
        ivs[i] = iv[order[i]]
        ils[i] = il[order[i]]
    return ivs, ils, el, n_bad


@njit(**_JIT)
def pair_satellites_all(prn_cat, pr_cat, row0, prn_lead, pr_lead, sv_lead, base, rot):
    """:func:`pair_satellites` of several vehicles in one call: vehicle ``j``'s satellites are
    rows ``row0[j]:row0[j+1]`` of ``prn_cat`` / ``pr_cat``. Returns ``(iv_cat, il_cat, el_cat,
    moff, n_bad)``: vehicle ``j``'s ``(iv, il, el)`` are the slices ``moff[j]:moff[j+1]``
    (``iv`` into its own rows), ``n_bad[j]`` its count."""
    nveh = row0.shape[0] - 1
    cap = 0
    for j in range(nveh):
        cap += min(row0[j + 1] - row0[j], prn_lead.shape[0])
    iv_cat = np.empty(cap, dtype=np.int64)
    il_cat = np.empty(cap, dtype=np.int64)
    el_cat = np.empty(cap)
    moff = np.zeros(nveh + 1, dtype=np.int64)
    n_bad = np.zeros(nveh, dtype=np.int64)
    for j in range(nveh):
        a, b = row0[j], row0[j + 1]
        iv, il, el, nb = pair_satellites(prn_cat[a:b], prn_lead, pr_cat[a:b], pr_lead, sv_lead, base, rot)
        m = moff[j]
        for i in range(iv.shape[0]):
            iv_cat[m + i] = iv[i]
            il_cat[m + i] = il[i]
            el_cat[m + i] = el[i]
        moff[j + 1] = m + iv.shape[0]
        n_bad[j] = nb
    k = moff[nveh]
    return iv_cat[:k], il_cat[:k], el_cat[:k], moff, n_bad


@njit(**_JIT)
def ranges_from(p, sv):
    """``|sv_i - p|`` (m,) (:func:`v2v.measmodels.range_m`, same arithmetic)."""
    m = sv.shape[0]
    out = np.empty(m)
    for i in range(m):
        d0, d1, d2 = sv[i, 0] - p[0], sv[i, 1] - p[1], sv[i, 2] - p[2]
        out[i] = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return out


@njit(**_JIT)
def range_rates_from(p, v, sv, svv):
    """``u_i . (svv_i - v)``, ``u_i = (sv_i - p) / |sv_i - p|`` (:func:`v2v.measmodels.range_rate_mps`)."""
    m = sv.shape[0]
    out = np.empty(m)
    for i in range(m):
        d0, d1, d2 = sv[i, 0] - p[0], sv[i, 1] - p[1], sv[i, 2] - p[2]
        rho = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        out[i] = (d0 / rho) * (svv[i, 0] - v[0]) + (d1 / rho) * (svv[i, 1] - v[1]) + (d2 / rho) * (svv[i, 2] - v[2])
    return out


@njit(**_JIT)
def sd_pseudorange_epoch(x, P, Q, kq, base, rot, ps, iclk, sv, rho_lead, z, r_var, gate_k, detect_jump, reset_var):
    """One vehicle's SD pseudorange epoch (production engine), the steps of
    ``ClusterFilterBase._sd_pseudoranges`` with the same kernels: rows at ``x``
    (:func:`sd_pseudorange_rows`), the clock-jump test (:func:`clock_jump_test`; on a jump
    the clock state is re-initialized at ``clk + median(nu)`` with variance ``reset_var`` and
    the rows rebuilt), the screen and first-update order (:func:`first_unflagged_order`),
    then the sequential updates (:func:`sd_pseudorange_batch`). On the lazily updated
    ``P - Q[:kq]^T Q[:kq]`` (a clock reset also clears the clock's column of Q, so the reset
    entries are exact), not flushed.

    Returns ``(jump, order, isolated, n_flagged, nu, s, status, kq)``.
    """
    h, val = sd_pseudorange_rows(x, base, rot, ps, iclk, sv, rho_lead, x[iclk])
    jump = False
    if detect_jump:
        idx = np.empty(4, dtype=np.int64)
        for i in range(3):
            idx[i] = ps + i
        idx[3] = iclk
        jump, med = _clock_jump_test_q(P, Q, kq, idx, h, val, z, r_var, gate_k)
        if jump:
            for r in range(kq):
                Q[r, iclk] = 0.0
            _set_block1(x, P, iclk, x[iclk] + med, reset_var)
            h, val = sd_pseudorange_rows(x, base, rot, ps, iclk, sv, rho_lead, x[iclk])
    order, excluded, isolated, n_flag = first_unflagged_order(h, val, z, math.sqrt(r_var), gate_k, 4)
    nu, s, st, kq = sd_pseudorange_batch(x, P, Q, kq, base, rot, ps, iclk, sv, rho_lead, z, order, excluded,
                                            r_var, gate_k)
    return jump, order, isolated, n_flag, nu, s, st, kq


@njit(**_JIT)
def sd_doppler_epoch(x, P, Q, kq, base, base_vel, rot, ps, vs, idrift, sv, svv, rate_lead, z, r_var, gate_k):
    """One vehicle's SD Doppler epoch (production engine): rows (:func:`sd_doppler_rows`),
    screen on (velocity, drift) and order (:func:`first_unflagged_order`), updates
    (:func:`sd_doppler_batch`), as ``ClusterFilterBase._sd_dopplers``; on the lazily updated
    ``P - Q[:kq]^T Q[:kq]``, not flushed. Returns ``(order, n_flagged, nu, s, status, kq)``."""
    h, val = sd_doppler_rows(x, base, base_vel, rot, ps, vs, idrift, sv, svv, rate_lead)
    order, excluded, isolated, n_flag = first_unflagged_order(h, val, z, math.sqrt(r_var), gate_k, 4)
    nu, s, st, kq = sd_doppler_batch(x, P, Q, kq, base, base_vel, rot, ps, vs, idrift, sv, svv, rate_lead, z,
                                        order, excluded, r_var, gate_k)
    return order, n_flag, nu, s, st, kq


@njit(**_JIT)
def _gather_rows(src, row0, iv, a, b):
    """Rows ``row0 + iv[a:b]`` of an (r, 3) array, as a new (b - a, 3) array."""
    out = np.empty((b - a, 3))
    for i in range(b - a):
        r = row0 + iv[a + i]
        for c in range(3):
            out[i, c] = src[r, c]
    return out


@njit(**_JIT)
def _meas_outputs(m):
    """(order, nu, S, status) arrays for ``m`` measurements."""
    return np.zeros(m, dtype=np.int64), np.zeros(m), np.zeros(m), np.zeros(m, dtype=np.int64)


@njit(**_JIT)
def _store(order, nu, s, st, a, b, o, nu_j, s_j, st_j):
    """One vehicle's per-measurement outputs into the slices ``a:b`` of the concatenated ones."""
    order[a:b] = o
    nu[a:b] = nu_j
    s[a:b] = s_j
    st[a:b] = st_j


@njit(**_JIT)
def sd_pseudorange_vehicles(x, P, base, rot, ps, iclk, sv_cat, pr_cat, row0, sv_lead, pr_lead, iv_cat, il_cat, moff,
                            r_var, gate_k, detect_jump, reset_var):
    """Every vehicle's SD pseudorange epoch (:func:`sd_pseudorange_epoch`, one after another)
    in one call, on one deferred-update buffer shared by all of them (P brought up to date
    once per LAZY_RANK updates and at the end, not once per vehicle).

    Vehicle ``j``: position-slice start ``ps[j]``, clock index ``iclk[j]``; its receiver's
    satellites are rows ``row0[j]:`` of ``sv_cat`` / ``pr_cat``; its common satellites with
    the lead are ``iv_cat[moff[j]:moff[j+1]]`` (indices into its rows) and ``il_cat[...]``
    (into the lead's ``sv_lead`` / ``pr_lead``), gathered with the arithmetic of
    ``models.SdPseudorangeRows``. Returns per vehicle ``(jump, isolated, n_flagged)`` and per measurement (``moff``
    slices) ``(order, nu, s, status)``, ``order`` local to the vehicle.
    """
    nv = ps.shape[0]
    m = iv_cat.shape[0]
    jump = np.zeros(nv, dtype=np.bool_)
    isolated = np.zeros(nv, dtype=np.bool_)
    n_flag = np.zeros(nv, dtype=np.int64)
    order, nu, s, st = _meas_outputs(m)
    Q = np.empty((LAZY_RANK, x.shape[0]))
    kq = 0
    for j in range(nv):
        a, b = moff[j], moff[j + 1]
        z = np.empty(b - a)
        for i in range(b - a):
            z[i] = pr_cat[row0[j] + iv_cat[a + i]] - pr_lead[il_cat[a + i]]
        rho_lead = ranges_from(base, _gather_rows(sv_lead, 0, il_cat, a, b))
        jp, o, iso, nf, nu_j, s_j, st_j, kq = sd_pseudorange_epoch(
            x, P, Q, kq, base, rot, ps[j], iclk[j], _gather_rows(sv_cat, row0[j], iv_cat, a, b), rho_lead, z, r_var,
            gate_k, detect_jump, reset_var)
        jump[j], isolated[j], n_flag[j] = jp, iso, nf
        _store(order, nu, s, st, a, b, o, nu_j, s_j, st_j)
    lazy_flush(P, Q, kq)
    return jump, isolated, n_flag, order, nu, s, st


@njit(**_JIT)
def sd_doppler_vehicles(x, P, base, base_vel, rot, ps, vs, idrift, sv_cat, svv_cat, row0, sv_lead, svv_lead, z_cat,
                        iv_cat, il_cat, moff, r_var, gate_k):
    """Every vehicle's SD Doppler epoch (:func:`sd_doppler_epoch`) in one call on one shared
    deferred-update buffer (as :func:`sd_pseudorange_vehicles`; ``z_cat`` the SD Dopplers,
    sliced like ``iv_cat``). Returns per vehicle ``n_flagged`` and per measurement
    ``(order, nu, s, status)``."""
    nv = ps.shape[0]
    m = iv_cat.shape[0]
    n_flag = np.zeros(nv, dtype=np.int64)
    order, nu, s, st = _meas_outputs(m)
    Q = np.empty((LAZY_RANK, x.shape[0]))
    kq = 0
    for j in range(nv):
        a, b = moff[j], moff[j + 1]
        rate_lead = range_rates_from(base, base_vel, _gather_rows(sv_lead, 0, il_cat, a, b),
                                     _gather_rows(svv_lead, 0, il_cat, a, b))
        o, nf, nu_j, s_j, st_j, kq = sd_doppler_epoch(
            x, P, Q, kq, base, base_vel, rot, ps[j], vs[j], idrift[j], _gather_rows(sv_cat, row0[j], iv_cat, a, b),
            _gather_rows(svv_cat, row0[j], iv_cat, a, b), rate_lead, z_cat[a:b].copy(), r_var, gate_k)
        n_flag[j] = nf
        _store(order, nu, s, st, a, b, o, nu_j, s_j, st_j)
    lazy_flush(P, Q, kq)
    return n_flag, order, nu, s, st


def cache_missing() -> bool:
    """Whether this machine has yet to compile these kernels (``cache=True``: numba compiles a
    kernel on its first call, ~1 min for all of them, and reuses the cached machine code
    afterwards), judged by numba's cache index of :func:`sd_pseudorange_vehicles`; False when
    it cannot be told (another numba's internals). For the run's notice before a long silence."""
    from pathlib import Path

    try:
        return not Path(sd_pseudorange_vehicles._cache._cache_file._index_path).is_file()
    except (AttributeError, TypeError):
        return False
