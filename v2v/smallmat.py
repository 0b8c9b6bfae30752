"""Compiled (numba) linear algebra for small dense matrices, callable from other kernels.

The normal matrices of a least-squares fix or a data-snooping screen are 4 x 4: a LAPACK call
from compiled code costs several microseconds of set-up for a few hundred flops, so the two
operations those kernels need are written out here once (the standalone GPS solution,
:mod:`v2v.sensors.gnss.spp`, and the filter's screen, :mod:`v2v.estimation.kernels`, both use
them). ``tests/test_compiled_spp_frames.py`` checks both against numpy/LAPACK.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

_JIT: dict[str, Any] = {"cache": True, "nogil": True, "error_model": "numpy"}


@njit(**_JIT)
def solve_small(a, b):  # pragma: no cover - compiled
    """``a^-1 b`` for a small square ``a`` and ``b`` (m, k): Gaussian elimination with partial
    pivoting (the algorithm of LAPACK ``dgesv``, unblocked). A zero pivot gives inf/NaN."""
    m = a.shape[0]
    lu = a.copy()
    x = b.copy()
    for j in range(m):
        p = j + np.argmax(np.abs(lu[j:, j]))
        if p != j:
            for c in range(m):
                lu[j, c], lu[p, c] = lu[p, c], lu[j, c]
            for c in range(x.shape[1]):
                x[j, c], x[p, c] = x[p, c], x[j, c]
        for i in range(j + 1, m):
            f = lu[i, j] / lu[j, j]
            for c in range(j + 1, m):
                lu[i, c] -= f * lu[j, c]
            for c in range(x.shape[1]):
                x[i, c] -= f * x[j, c]
    for j in range(m - 1, -1, -1):
        for c in range(x.shape[1]):
            acc = x[j, c]
            for i in range(j + 1, m):
                acc -= lu[j, i] * x[i, c]
            x[j, c] = acc / lu[j, j]
    return x


@njit(**_JIT)
def cond2_symmetric(a):  # pragma: no cover - compiled
    """2-norm condition number ``max|lambda| / min|lambda|`` of a symmetric matrix (its
    singular values are its eigenvalues' magnitudes), by cyclic Jacobi rotations (Golub & Van
    Loan 2013, alg. 8.5.3), which find even the small eigenvalues of a positive definite
    matrix to high relative accuracy. ``a`` is symmetrized first (H'WH is symmetric only up
    to rounding)."""
    m = a.shape[0]
    s = np.empty((m, m))
    for p in range(m):
        for q in range(m):
            s[p, q] = 0.5 * (a[p, q] + a[q, p])
    for _ in range(30):
        off = 0.0
        diag = 0.0
        for p in range(m):
            diag += s[p, p] ** 2
            for q in range(p + 1, m):
                off += s[p, q] ** 2
        if not off > 1e-36 * diag:  # converged (also stops on NaN)
            break
        for p in range(m - 1):
            for q in range(p + 1, m):
                if s[p, q] == 0.0:
                    continue
                theta = (s[q, q] - s[p, p]) / (2.0 * s[p, q])
                t = 1.0 / (abs(theta) + np.sqrt(theta * theta + 1.0)) if abs(theta) < 1e150 else 0.5 / abs(theta)
                if theta < 0.0:
                    t = -t
                c = 1.0 / np.sqrt(t * t + 1.0)
                sn = t * c
                for k in range(m):  # columns p, q
                    skp, skq = s[k, p], s[k, q]
                    s[k, p], s[k, q] = c * skp - sn * skq, sn * skp + c * skq
                for k in range(m):  # rows p, q
                    spk, sqk = s[p, k], s[q, k]
                    s[p, k], s[q, k] = c * spk - sn * sqk, sn * spk + c * sqk
    lo, hi = np.inf, 0.0
    for p in range(m):
        lo, hi = min(lo, abs(s[p, p])), max(hi, abs(s[p, p]))
    return hi / lo
