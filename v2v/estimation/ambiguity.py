"""Integer carrier-phase ambiguity resolution: LAMBDA, validation, partial fixing.

Implements MacGougan (2009) sections 3.6-3.7 on top of a single-difference (SD) float
filter solution:

1. **SD -> DD** (thesis eq. 3.30-3.31). The SD float state carries one SD clock and one
   SD ambiguity per satellite; the clock and the ambiguities cannot be separated, only
   the double differences ``a_j - a_ref`` are integers. A linear map ``D`` drops the
   clock state(s) and differences the ambiguities against a reference satellite::

       x_dd = D x_sd,     P_dd = D P_sd D^T              (3.30), (3.31)

   The reference is the highest-elevation satellite (:func:`reference_satellite`): it is
   the least likely to carry multipath or an echo-only blunder (thesis section 3.5.1)
   and it is the first one the filter updates with.

2. **Integer least squares (ILS)** (eq. 3.32-3.34), solved by the LAMBDA method
   (Teunissen 1995; de Jonge and Tiberius 1996)::

       a_check = argmin_{a in Z^n} (a_hat - a)^T Q^-1 (a_hat - a)

   * :func:`ldl_decompose`: ``Q = L^T diag(d) L``, ``L`` unit lower triangular. With
     ``a = a_hat + L^T e``, ``e ~ N(0, diag(d))``, ``d[i]`` is the variance of ``a_i``
     *conditioned on* ``a_{i+1..n}`` (sequential conditioning runs from the last index
     to the first, as in de Jonge and Tiberius 1996).
   * :func:`decorrelate`: integer Gauss transformations and permutations of adjacent
     ambiguities build an integer unimodular ``Z`` (``|det Z| = 1``, so ``Z^-1`` is
     integer too and integer vectors map one-to-one)::

         z_hat = Z^T a_hat,    Q_z = Z^T Q Z             (3.33)

     with the conditional variances sorted (mostly) from large (first) to small (last).
   * :func:`search`: depth-first enumeration of the shrinking ILS ellipsoid in z-space,
     from the last (most precise) ambiguity to the first, each level visiting integers
     around its conditional estimate nearest first (Schnorr-Euchner order); keeps the
     ``k`` best candidates and shrinks the radius to the ``k``-th best norm.

3. **Validation** (section 3.7.1): the ratio ``F = ||second||^2 / ||best||^2`` (eq. 3.35
   with ``Omega = 0``, the usual fixed-threshold form) and the bootstrapped probability
   of a correct fix (eq. 3.36, Teunissen 1998), a lower bound of the ILS success rate::

       P_B = prod_i ( 2 Phi( 1 / (2 sigma_{i|I}) ) - 1 )

4. **Fixed solution** (eq. 3.37): the rest of the state conditioned on the fixed
   integers, ``b_check = b - Q_ba Q_a^-1 (a_hat - a_check)``,
   ``Q_b|a = Q_b - Q_ba Q_a^-1 Q_ab`` (the term of the fixed-ambiguity uncertainty is
   neglected, as in the thesis).

5. **Partial fixing** (eq. 3.39-3.40): in z-space, the largest trailing subset
   ``z_j..z_n`` whose bootstrapped success rate reaches a threshold is searched; if its
   ratio test fails, the subset shrinks by one and the search is repeated. The
   remaining parameters (``b`` and the unfixed ``z``) are conditioned on the fixed
   subset (eq. 3.40); :func:`fixed_solution` with ``transform=Z_s`` does the same for a
   full filter state.

Units: ambiguities in cycles throughout (the functions are unit-agnostic as long as an
ambiguity is an integer in the unit used).

References
----------
- MacGougan, G. (2009). *Real-time kinematic surveying using tightly-coupled GPS and
  ultra-wideband ranging*. PhD thesis, University of Calgary, sections 3.6-3.7.
- Teunissen, P.J.G. (1995). The least-squares ambiguity decorrelation adjustment: a
  method for fast GPS integer ambiguity estimation. *J. Geodesy* 70, 65-82.
- de Jonge, P., Tiberius, C. (1996). The LAMBDA method for integer ambiguity estimation:
  implementation aspects. *LGR series* 12, Delft University of Technology.
- Teunissen, P.J.G. (1998). Success probability of integer GPS ambiguity rounding and
  bootstrapping. *J. Geodesy* 72, 606-612.
- Teunissen, P.J.G. (1999). An optimality property of the integer least-squares
  estimator. *J. Geodesy* 73, 587-593 (P(ILS correct) >= P(bootstrapping correct)).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import erf

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


# --------------------------------------------------------------------------- SD -> DD
def reference_satellite(elevation_rad: ArrayLike) -> int:
    """Index of the reference satellite for double differencing: the highest elevation.

    Parameters
    ----------
    elevation_rad : (m,) elevations of the satellites whose SD ambiguities are differenced,
        in the order of ``amb_idx`` of :func:`sd_to_dd`.
    """
    el = np.asarray(elevation_rad, dtype=float)
    if el.ndim != 1 or el.size == 0:
        raise ValueError("elevation_rad must be a non-empty 1-D array")
    return int(np.argmax(el))


@dataclass(frozen=True)
class DoubleDifference:
    """Result of :func:`sd_to_dd`.

    Attributes
    ----------
    x, P : (k,), (k, k) double-difference state and covariance, ``D x_sd``, ``D P D^T``.
    D : (k, n) the differencing matrix (thesis eq. 3.30).
    b_idx : (k - m + 1,) indices in ``x`` of the kept non-ambiguity states (in their
        original order, first).
    amb_idx : (m - 1,) indices in ``x`` of the DD ambiguities (last).
    sd_pairs : (m - 1, 2) for each DD ambiguity, ``(j, ref)`` as positions in the input
        ``amb_idx``: the DD ambiguity is ``a_sd[j] - a_sd[ref]``.
    """

    x: F64
    P: F64
    D: F64
    b_idx: NDArray[np.intp]
    amb_idx: NDArray[np.intp]
    sd_pairs: NDArray[np.intp]


def sd_to_dd(
    x: ArrayLike, P: ArrayLike, amb_idx: Sequence[int], ref: int, *, drop_idx: Sequence[int] = ()
) -> DoubleDifference:
    """Difference the SD ambiguity states of a float solution (thesis eq. 3.30-3.31).

    ``D`` keeps every state that is neither an ambiguity nor in ``drop_idx`` (identity
    rows, original order), then appends one row per non-reference ambiguity ``j``
    (``+1`` at ``a_j``, ``-1`` at ``a_ref``: the thesis's block ``B``). The dropped
    states are the SD receiver clock(s), which the DD removes.

    Parameters
    ----------
    x : (n,) SD float state.
    P : (n, n) its covariance.
    amb_idx : (m,) state indices of the SD ambiguities of one receiver pair (cycles),
        m >= 2.
    ref : position *in amb_idx* of the reference satellite; use
        :func:`reference_satellite` (highest elevation).
    drop_idx : state indices to drop (SD clock bias, and drift if the caller wishes).

    Returns
    -------
    DoubleDifference
    """
    x = np.asarray(x, dtype=float)
    P = np.asarray(P, dtype=float)
    amb = np.asarray(amb_idx, dtype=np.intp)
    n, m = x.size, amb.size
    if P.shape != (n, n):
        raise ValueError(f"P must be ({n}, {n}), got {P.shape}")
    if m < 2:
        raise ValueError("need at least two SD ambiguities to form a double difference")
    if not 0 <= ref < m:
        raise ValueError(f"ref must index amb_idx (0..{m - 1}), got {ref}")
    drop = np.asarray(drop_idx, dtype=np.intp)
    if len(set(amb.tolist()) | set(drop.tolist())) != m + drop.size:
        raise ValueError("amb_idx and drop_idx must be distinct state indices")
    removed = np.zeros(n, dtype=bool)
    removed[amb] = True
    removed[drop] = True
    keep = np.flatnonzero(~removed)
    others = np.array([j for j in range(m) if j != ref], dtype=np.intp)
    D = np.zeros((keep.size + m - 1, n))
    D[np.arange(keep.size), keep] = 1.0
    rows = keep.size + np.arange(m - 1)
    D[rows, amb[others]] = 1.0
    D[rows, amb[ref]] = -1.0
    P_dd = D @ P @ D.T
    return DoubleDifference(
        x=D @ x,
        P=0.5 * (P_dd + P_dd.T),
        D=D,
        b_idx=np.arange(keep.size, dtype=np.intp),
        amb_idx=rows.astype(np.intp),
        sd_pairs=np.column_stack([others, np.full(m - 1, ref, dtype=np.intp)]),
    )


# --------------------------------------------------------------------------- LAMBDA
def ldl_decompose(Q: ArrayLike) -> tuple[F64, F64]:
    """``Q = L^T diag(d) L`` with ``L`` unit lower triangular (de Jonge and Tiberius 1996).

    ``d[i]`` is the conditional variance ``sigma^2_{i|i+1..n}``; ``d[-1] = Q[-1, -1]``.
    Computed from the last row/column backwards.

    Raises
    ------
    ValueError if ``Q`` is not symmetric positive definite.
    """
    A = np.array(Q, dtype=float)
    if A.ndim != 2 or A.size == 0:
        raise ValueError("Q must be a non-empty square matrix")
    n = A.shape[0]
    if A.shape != (n, n) or not np.allclose(A, A.T, rtol=1e-10, atol=1e-12 * np.abs(A).max()):
        raise ValueError("Q must be a symmetric square matrix")
    L = np.zeros((n, n))
    d = np.zeros(n)
    for i in range(n - 1, -1, -1):
        d[i] = A[i, i]
        if not d[i] > 0.0:
            raise ValueError("Q is not positive definite")
        L[i, : i + 1] = A[i, : i + 1] / np.sqrt(d[i])
        # Schur complement on the leading block (condition on variable i).
        A[:i, :i] -= np.outer(L[i, :i], L[i, :i])
        L[i, : i + 1] /= L[i, i]
    return L, d


def _conditional_variances(Q: F64) -> F64:
    return ldl_decompose(Q)[1]


def decorrelate(Q: ArrayLike, a: ArrayLike) -> tuple[I64, F64, F64]:
    """LAMBDA decorrelation: integer Gauss transformations and adjacent permutations.

    Returns ``Z`` (integer, unimodular), ``Q_z = Z^T Q Z`` and ``z_float = Z^T a``
    (thesis eq. 3.33). After it, ``|L_z[j, i]| <= 1/2`` below the diagonal and the
    conditional variances satisfy ``d[i+1] <= d[i] + L[i+1, i]^2 d[i+1]`` (no
    adjacent swap reduces ``d[i+1]``): the last ambiguities are the most precise.

    Parameters
    ----------
    Q : (n, n) covariance of the float ambiguities (symmetric positive definite).
    a : (n,) float ambiguities.
    """
    Z, _, L, d = _decorrelate_ldl(np.asarray(Q, dtype=float))
    Qz = L.T @ (d[:, None] * L)
    return Z, 0.5 * (Qz + Qz.T), Z.T @ np.asarray(a, dtype=float)


def _decorrelate_ldl(Q: F64) -> tuple[I64, I64, F64, F64]:
    """Core of :func:`decorrelate`; also returns ``Z^-1`` and the LDL factors of Q_z."""
    L, d = ldl_decompose(Q)
    n = d.size
    Z = np.eye(n, dtype=np.int64)
    Zinv = np.eye(n, dtype=np.int64)  # kept exactly: a = Zinv^T z
    i = n - 2
    last_swap = n - 2  # columns after the last swap position are already reduced
    while i >= 0:
        # Integer Gauss transformations on column i (z_i -= mu z_j), j ascending, so the
        # entries already reduced are not touched again.
        for j in range(i + 1, n) if i <= last_swap else ():
            mu = int(np.rint(L[j, i]))
            if mu != 0:
                L[j:, i] -= mu * L[j:, j]
                Z[:, i] -= mu * Z[:, j]
                Zinv[j, :] += mu * Zinv[i, :]
        # Swap i and i+1 if it makes the conditional variance at i+1 smaller.
        l_i = L[i + 1, i]
        delta = d[i] + l_i * l_i * d[i + 1]
        if delta < d[i + 1] * (1.0 - 1e-12):
            eta = d[i] / delta
            lam = d[i + 1] * l_i / delta
            d[i], d[i + 1] = eta * d[i + 1], delta
            L[i : i + 2, :i] = np.array([[-l_i, 1.0], [eta, lam]]) @ L[i : i + 2, :i]
            L[i + 1, i] = lam
            L[i + 2 :, [i, i + 1]] = L[i + 2 :, [i + 1, i]]
            Z[:, [i, i + 1]] = Z[:, [i + 1, i]]
            Zinv[[i, i + 1], :] = Zinv[[i + 1, i], :]
            last_swap = i
            i = n - 2  # restart from the end, as de Jonge and Tiberius (1996)
        else:
            i -= 1
    return Z, Zinv, L, d


def _search_ldl(L: F64, d: F64, z: F64, n_cands: int) -> tuple[I64, F64]:
    """ILS enumeration on ``Q_z = L^T diag(d) L``; see :func:`search`."""
    n = d.size
    best: list[tuple[float, I64]] = []
    bound = np.inf
    cand = np.zeros(n, dtype=np.int64)
    centre = np.zeros(n)
    resid = np.zeros(n)  # z_j - centre_j of the current partial candidate

    def level(i: int, partial: float) -> None:
        nonlocal bound
        # Conditional estimate of z_i given the integers chosen for i+1..n-1.
        c = z[i] + L[i + 1 :, i] @ resid[i + 1 :]
        centre[i] = c
        zi = float(np.rint(c))
        step = 1.0 if c >= zi else -1.0
        k = 0
        while True:
            cost = partial + (zi - c) ** 2 / d[i]
            if cost >= bound:
                return  # Schnorr-Euchner order: later integers are farther away
            cand[i] = int(zi)
            resid[i] = zi - c
            if i == 0:
                best.append((cost, cand.copy()))
                if len(best) > n_cands:
                    best.sort(key=lambda t: t[0])
                    best.pop()
                if len(best) == n_cands:
                    bound = max(t[0] for t in best)
            else:
                level(i - 1, cost)
            # Next integer in zig-zag order around c.
            k += 1
            zi += step * k
            step = -step

    level(n - 1, 0.0)
    best.sort(key=lambda t: t[0])
    return np.column_stack([b[1] for b in best]), np.array([b[0] for b in best])


def search(Qz: ArrayLike, z: ArrayLike, n_cands: int = 2) -> tuple[I64, F64]:
    """Integer least-squares search (thesis eq. 3.34) with a shrinking ellipsoid.

    Parameters
    ----------
    Qz : (n, n) covariance of the (decorrelated) float ambiguities.
    z : (n,) float ambiguities.
    n_cands : number of best integer vectors to return.

    Returns
    -------
    candidates : (n, n_cands) int64, column k is the k-th best integer vector.
    squared_norms : (n_cands,) ascending ``(z - c)^T Qz^-1 (z - c)``.
    """
    if n_cands < 1:
        raise ValueError("n_cands must be >= 1")
    z = np.asarray(z, dtype=float)
    shift = np.rint(z)  # search near 0 for accuracy; integers shift back exactly
    L, d = ldl_decompose(Qz)
    cands, norms = _search_ldl(L, d, z - shift, n_cands)
    return cands + shift.astype(np.int64)[:, None], norms


def bootstrapped_success_rate(Qz: ArrayLike) -> float:
    """Probability that bootstrapping yields the correct integers (thesis eq. 3.36).

    ``P_B = prod_i (2 Phi(1 / (2 sigma_{i|I})) - 1) = prod_i erf(1 / (2 sqrt(2 d_i)))``
    with ``d_i`` the conditional variances of :func:`ldl_decompose` (Teunissen 1998).
    It depends on the parametrization: evaluate it on the decorrelated ``Q_z``, where it
    is larger and the sharpest easily computed lower bound of the ILS success rate
    (Teunissen 1999); on the original ``Q`` it is usually far more pessimistic.
    """
    d = _conditional_variances(np.asarray(Qz, dtype=float))
    return float(np.prod(erf(1.0 / (2.0 * np.sqrt(2.0 * d)))))


def bootstrap(z: ArrayLike, L: ArrayLike, d: ArrayLike) -> I64:
    """Bootstrapped integers: round ``z_n``, then each ``z_i`` conditioned on the rounded
    ``z_{i+1..n}`` (sequential rounding, Teunissen 1998), with ``Q_z = L^T diag(d) L``.
    """
    z = np.asarray(z, dtype=float)
    L = np.asarray(L, dtype=float)
    n = z.size
    out = np.zeros(n, dtype=np.int64)
    resid = np.zeros(n)
    for i in range(n - 1, -1, -1):
        c = z[i] + L[i + 1 :, i] @ resid[i + 1 :]
        out[i] = int(np.rint(c))
        resid[i] = out[i] - c
    return out


@dataclass(frozen=True)
class LambdaResult:
    """Result of :func:`lambda_resolve`.

    Attributes
    ----------
    fixed : (n,) int64, the ILS solution in the original (a-) space.
    candidates : (n, k) int64, the k best integer vectors in a-space (column 0 = fixed).
    sq_norms : (k,) their squared norms ``(a_hat - a)^T Q^-1 (a_hat - a)`` (ascending).
    ratio : ``sq_norms[1] / sq_norms[0]`` (inf if the best norm is 0; nan if k = 1).
    Z : (n, n) int64 unimodular decorrelating transformation, ``z = Z^T a``.
    Qz : (n, n) ``Z^T Q Z``.
    z_float : (n,) ``Z^T a_hat``.
    success_rate_bootstrap : bootstrapped success rate of Q_z (eq. 3.36).
    """

    fixed: I64
    candidates: I64
    sq_norms: F64
    ratio: float
    Z: I64
    Qz: F64
    z_float: F64
    success_rate_bootstrap: float


def _ratio(sq_norms: F64) -> float:
    if sq_norms.size < 2:
        return float("nan")
    if sq_norms[0] <= 0.0:
        return float("inf")
    return float(sq_norms[1] / sq_norms[0])


def lambda_resolve(a_float: ArrayLike, Q: ArrayLike, n_cands: int = 2) -> LambdaResult:
    """LAMBDA: decorrelate, search in z-space, transform back (thesis eq. 3.32-3.36).

    Parameters
    ----------
    a_float : (n,) float (DD) ambiguities, cycles.
    Q : (n, n) their covariance, cycles^2.
    n_cands : number of candidates to keep (>= 2 for the ratio).
    """
    a = np.asarray(a_float, dtype=float)
    shift = np.rint(a)
    Z, Zinv, L, d = _decorrelate_ldl(np.asarray(Q, dtype=float))
    z = Z.T @ (a - shift)
    cz, norms = _search_ldl(L, d, z, n_cands)
    cands = Zinv.T @ cz + shift.astype(np.int64)[:, None]
    Qz = L.T @ (d[:, None] * L)
    return LambdaResult(
        fixed=cands[:, 0].copy(),
        candidates=cands,
        sq_norms=norms,
        ratio=_ratio(norms),
        Z=Z,
        Qz=0.5 * (Qz + Qz.T),
        z_float=Z.T @ a,
        success_rate_bootstrap=float(np.prod(erf(1.0 / (2.0 * np.sqrt(2.0 * d))))),
    )


# --------------------------------------------------------------------------- fixed solution
@dataclass(frozen=True)
class FixedSolution:
    """State conditioned on fixed integers (thesis eq. 3.37 / 3.40)."""

    x: F64
    P: F64


def fixed_solution(
    x_float: ArrayLike,
    P: ArrayLike,
    amb_idx: Sequence[int] | NDArray[np.integer],
    a_fixed: ArrayLike,
    *,
    transform: ArrayLike | None = None,
) -> FixedSolution:
    """Condition a float solution on fixed ambiguities (thesis eq. 3.37, 3.40).

    With ``C`` the rows selecting the fixed quantities (``C x = a`` for the ambiguities,
    or ``C x = Z_s^T a`` with ``transform = Z_s`` for a subset of z-space ambiguities)::

        x_check = x - P C^T (C P C^T)^-1 (C x - a_fixed)
        P_check = P - P C^T (C P C^T)^-1 C P

    For ``C`` = selection this is exactly eq. 3.37 for the non-ambiguity part ``b``
    (``b - Q_ba Q_a^-1 (a_hat - a_check)``, ``Q_b - Q_ba Q_a^-1 Q_ab``) and sets the
    ambiguities to ``a_fixed`` with zero variance; with ``transform`` it is eq. 3.40
    (b and the unfixed z conditioned on the fixed ``z_s``). The thesis's
    ``Q_ba Q_a^-1 Q_a_check Q_a^-1 Q_ab`` term is neglected (fixed integers are treated
    as known).

    Parameters
    ----------
    x_float : (n,) float state (e.g. the DD state of :func:`sd_to_dd`).
    P : (n, n) its covariance.
    amb_idx : (m,) state indices of the ambiguities.
    a_fixed : (m,) fixed ambiguities, or (s,) fixed z values if ``transform`` is given.
    transform : optional (m, s) integer matrix ``Z_s`` (columns of ``Z`` of the fixed
        z-space ambiguities, e.g. ``Z[:, result.fixed_mask]`` of :func:`partial_fix`).
    """
    x = np.asarray(x_float, dtype=float)
    P = np.asarray(P, dtype=float)
    amb = np.asarray(amb_idx, dtype=np.intp)
    n = x.size
    if transform is None:
        Zs = np.eye(amb.size)
    else:
        Zs = np.asarray(transform, dtype=float)
        if Zs.ndim != 2 or Zs.shape[0] != amb.size:
            raise ValueError(f"transform must be ({amb.size}, s), got {Zs.shape}")
    fixed = np.asarray(a_fixed, dtype=float)
    if fixed.shape != (Zs.shape[1],):
        raise ValueError(f"a_fixed must have {Zs.shape[1]} elements, got {fixed.shape}")
    if fixed.size == 0:
        return FixedSolution(x=x.copy(), P=P.copy())
    C = np.zeros((Zs.shape[1], n))
    C[:, amb] = Zs.T
    PCt = P @ C.T
    S = C @ PCt
    S = 0.5 * (S + S.T)
    K = np.linalg.solve(S, PCt.T).T
    x_c = x - K @ (C @ x - fixed)
    P_c = P - K @ PCt.T
    P_c = 0.5 * (P_c + P_c.T)
    if transform is None:  # exact values where the algebra gives them up to round-off
        x_c[amb] = fixed
        P_c[amb, :] = 0.0
        P_c[:, amb] = 0.0
    return FixedSolution(x=x_c, P=P_c)


# --------------------------------------------------------------------------- partial fixing
@dataclass(frozen=True)
class PartialFixResult:
    """Result of :func:`partial_fix`.

    Attributes
    ----------
    Z : (n, n) int64 decorrelating transformation, ``z = Z^T a``.
    z_float : (n,) ``Z^T a_hat``.
    Qz : (n, n) ``Z^T Q Z``.
    fixed_mask : (n,) bool, which z-space ambiguities are fixed (a trailing block).
    z_fixed : (s,) int64 fixed values of ``z[fixed_mask]`` (ILS on the subset).
    success_rate : bootstrapped success rate of the fixed subset (eq. 3.39); 1.0 if none.
    ratio : ratio test value of the accepted subset (nan if none fixed).
    z_cond, Qz_cond : (n,), (n, n) z conditioned on the fixed subset (eq. 3.40): the
        fixed entries equal ``z_fixed`` with zero variance.
    a_cond, Qa_cond : (n,), (n, n) the same in a-space, ``a = Z^-T z``; integer (and
        zero variance) when every ambiguity is fixed.
    """

    Z: I64
    z_float: F64
    Qz: F64
    fixed_mask: NDArray[np.bool_]
    z_fixed: I64
    success_rate: float
    ratio: float
    z_cond: F64
    Qz_cond: F64
    a_cond: F64
    Qa_cond: F64

    @property
    def n_fixed(self) -> int:
        return int(self.fixed_mask.sum())


def partial_fix(
    a_float: ArrayLike,
    Q: ArrayLike,
    min_success: float = 0.999,
    ratio_threshold: float = 3.0,
) -> PartialFixResult:
    """Partial ambiguity fixing in the decorrelated space (thesis section 3.7.3).

    1. Decorrelate (:func:`decorrelate`); ``Q_z = L^T diag(d) L``.
    2. Bootstrapped success rate of the trailing subset ``z_j..z_n`` (eq. 3.39):
       ``prod_{i=j}^{n} erf(1 / (2 sqrt(2 d_i)))`` (the conditional variances of a
       trailing block are the trailing ``d``); take the smallest ``j`` (largest subset)
       with success ``>= min_success``.
    3. ILS on the subset; if ``ratio < ratio_threshold`` drop the first ambiguity of the
       subset (the least precise) and repeat.
    4. Condition the unfixed z on the fixed subset (eq. 3.40) and map to a-space.

    With one fixed ambiguity the second-best candidate is the next integer, so the ratio
    test still applies.

    Parameters
    ----------
    a_float : (n,) float (DD) ambiguities, cycles.
    Q : (n, n) their covariance.
    min_success : bootstrapped success rate required of the fixed subset.
    ratio_threshold : minimum ratio ``second / best`` to accept a subset.
    """
    a = np.asarray(a_float, dtype=float)
    shift = np.rint(a)
    Z, Zinv, L, d = _decorrelate_ldl(np.asarray(Q, dtype=float))
    n = a.size
    z0 = Z.T @ (a - shift)  # around 0 for accuracy
    zshift = Z.T @ shift
    Qz = L.T @ (d[:, None] * L)
    Qz = 0.5 * (Qz + Qz.T)
    factors = erf(1.0 / (2.0 * np.sqrt(2.0 * d)))
    tail = np.cumprod(factors[::-1])[::-1]  # tail[j] = P_B of z_j..z_n
    ok = np.flatnonzero(tail >= min_success)
    j = int(ok[0]) if ok.size else n
    z_fixed = np.zeros(0, dtype=np.int64)
    ratio = float("nan")
    while j < n:
        cz, norms = _search_ldl(L[j:, j:], d[j:], z0[j:], 2)
        ratio = _ratio(norms)
        if ratio >= ratio_threshold:
            z_fixed = cz[:, 0] + zshift[j:].astype(np.int64)
            break
        j += 1
    if j == n:
        ratio = float("nan")
    mask = np.zeros(n, dtype=bool)
    mask[j:] = True
    z_float = z0 + zshift
    cond = fixed_solution(z_float, Qz, np.arange(n), z_fixed, transform=np.eye(n)[:, mask])
    z_cond = cond.x.copy()
    Qz_cond = cond.P.copy()
    z_cond[mask] = z_fixed
    Qz_cond[mask, :] = 0.0
    Qz_cond[:, mask] = 0.0
    Zinv_t = Zinv.T.astype(float)
    a_cond = Zinv_t @ z_cond
    Qa_cond = Zinv_t @ Qz_cond @ Zinv_t.T
    return PartialFixResult(
        Z=Z,
        z_float=z_float,
        Qz=Qz,
        fixed_mask=mask,
        z_fixed=z_fixed,
        success_rate=float(tail[j]) if j < n else 1.0,
        ratio=ratio,
        z_cond=z_cond,
        Qz_cond=Qz_cond,
        a_cond=a_cond,
        Qa_cond=0.5 * (Qa_cond + Qa_cond.T),
    )
