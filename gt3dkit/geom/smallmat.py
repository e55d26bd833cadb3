"""Small dense matrices inside compiled kernels (numba): Cholesky factor and solves, the inverse of
a triangular factor, a symmetric solve that falls back to the eigen-decomposition, Jacobi
eigenvalues, products. numba's own ``np.linalg`` and ``@`` cost seconds of compilation each;
these are a few loops. Called only from other compiled functions (the box filter, the per-frame
box fits); :mod:`gt3dkit.geom.kernel_cache` keeps the callers' caches in step with this file."""

from __future__ import annotations

import math

import numba
import numpy as np

from gt3dkit.geom.kernel_cache import drop_stale
from gt3dkit.types import F64

drop_stale()  # before any compiled function below is called (and its cache read)


@numba.njit(cache=True, nogil=True)
def chol(A: F64, L: F64) -> bool:
    """Lower Cholesky factor of the symmetric ``A (n, n)`` into ``L``; False if not PD."""
    n = A.shape[0]
    for j in range(n):
        s = A[j, j]
        for k in range(j):
            s -= L[j, k] * L[j, k]
        if not s > 0.0:
            return False
        d = math.sqrt(s)
        L[j, j] = d
        for i in range(j + 1, n):
            s = A[i, j]
            for k in range(j):
                s -= L[i, k] * L[j, k]
            L[i, j] = s / d
        for i in range(j):
            L[i, j] = 0.0
    return True


@numba.njit(cache=True, nogil=True)
def eigh_jacobi(S: F64) -> tuple[F64, F64]:
    """Eigenvalues ``w (n,)`` and eigenvectors (columns of ``V``) of a small symmetric matrix by
    cyclic Jacobi rotations (to machine precision; numba's ``np.linalg.eigh`` costs seconds of
    compilation)."""
    n = S.shape[0]
    A = S.copy()
    V = np.eye(n)
    for _ in range(100):
        off = 0.0
        for i in range(n):
            for j in range(i + 1, n):
                off += A[i, j] * A[i, j]
        if off <= 1e-30 * max(np.sum(A * A), 1e-300):
            break
        for p in range(n):
            for q in range(p + 1, n):
                if A[p, q] == 0.0:
                    continue
                theta = (A[q, q] - A[p, p]) / (2.0 * A[p, q])
                tt = (1.0 if theta >= 0 else -1.0) / (abs(theta) + math.sqrt(theta * theta + 1.0))
                c = 1.0 / math.sqrt(tt * tt + 1.0)
                sn = tt * c
                for k in range(n):  # A <- J^T A J
                    akp, akq = A[k, p], A[k, q]
                    A[k, p], A[k, q] = c * akp - sn * akq, sn * akp + c * akq
                for k in range(n):
                    apk, aqk = A[p, k], A[q, k]
                    A[p, k], A[q, k] = c * apk - sn * aqk, sn * apk + c * aqk
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p], V[k, q] = c * vkp - sn * vkq, sn * vkp + c * vkq
    w = np.empty(n)
    for i in range(n):
        w[i] = A[i, i]
    return w, V


@numba.njit(cache=True, nogil=True)
def chol_solve(L: F64, B: F64, X: F64) -> None:
    """``X = (L L^T)^-1 B`` for a lower Cholesky factor ``L (n, n)`` and ``B (n, k)``."""
    n, k = B.shape
    # rows of X at a time (memory order); each entry's sum runs in the same order as one
    # column at a time would
    s = np.empty(k)
    for i in range(n):
        s[:] = B[i]
        for j in range(i):
            lij = L[i, j]
            for c in range(k):
                s[c] -= lij * X[j, c]
        d = L[i, i]
        for c in range(k):
            X[i, c] = s[c] / d
    for i in range(n - 1, -1, -1):
        s[:] = X[i]
        for j in range(i + 1, n):
            lji = L[j, i]
            for c in range(k):
                s[c] -= lji * X[j, c]
        d = L[i, i]
        for c in range(k):
            X[i, c] = s[c] / d


@numba.njit(cache=True, nogil=True)
def solve_sym(S: F64, B: F64, X: F64) -> None:
    """``X = S^-1 B`` for a symmetric ``S``: by Cholesky, or (not positive definite) by its
    eigen-decomposition; NaN if singular or not finite."""
    n = S.shape[0]
    L = np.empty((n, n))
    if not np.all(np.isfinite(S)):
        X[:, :] = np.nan
        return
    Ssym = 0.5 * (S + S.T)
    if chol(Ssym, L):
        chol_solve(L, B, X)
        return
    w, V = eigh_jacobi(Ssym)
    k = B.shape[1]
    for c in range(k):
        for i in range(n):
            s = 0.0
            for a in range(n):
                if w[a] == 0.0:
                    s = np.nan
                    break
                pa = 0.0
                for j in range(n):
                    pa += V[j, a] * B[j, c]
                s += V[i, a] * pa / w[a]
            X[i, c] = s


@numba.njit(cache=True, nogil=True)
def matmul(A: F64, B: F64, out: F64) -> None:
    """``out = A B`` (small matrices; numba's ``@`` adds seconds of compilation). Rows of ``B``
    at a time (memory order); each entry's sum runs over ``k`` in order, as ``A[i] . B[:, j]``."""
    m = B.shape[1]
    for i in range(A.shape[0]):
        for j in range(m):
            out[i, j] = 0.0
        for k in range(A.shape[1]):
            a = A[i, k]
            for j in range(m):
                out[i, j] += a * B[k, j]


@numba.njit(cache=True, nogil=True)
def matmul_sparse_left(A: F64, B: F64, out: F64) -> None:
    """``out = A B`` for a sparse ``A`` (a transition matrix: at most two entries per row), in
    ``O(nnz(A) m)``: :func:`matmul` without the rows of ``B`` that ``A``'s zeros would multiply
    (they add nothing: the same sums in the same order, the same bits for finite ``B``)."""
    m = B.shape[1]
    for i in range(A.shape[0]):
        for j in range(m):
            out[i, j] = 0.0
        for k in range(A.shape[1]):
            a = A[i, k]
            if a != 0.0:
                for j in range(m):
                    out[i, j] += a * B[k, j]


@numba.njit(cache=True, nogil=True)
def symmetrised(A: F64) -> F64:
    """``(A + A^T) / 2`` as a new array."""
    n = A.shape[0]
    S = np.empty((n, n))
    for i in range(n):
        for j in range(n):
            S[i, j] = 0.5 * (A[i, j] + A[j, i])
    return S


@numba.njit(cache=True, nogil=True)
def safe_chol(A: F64, L: F64) -> int:
    """:func:`gt3dkit.fusion.ukf.sigma.safe_cholesky` of one matrix: ``L`` of ``(A + A^T) / 2``,
    eigenvalue-clipped if that is not PD. Returns 1 if a repair was needed, else 0."""
    n = A.shape[0]
    S = symmetrised(A)
    if chol(S, L):
        return 0
    if not np.all(np.isfinite(S)):
        L[:, :] = np.nan
        return 1
    w, V = eigh_jacobi(S)
    wmax = max(w.max(), 1e-300)
    bad = 1 if w.min() <= 1e-15 * wmax else 0
    w = np.maximum(w, 1e-12 * wmax)
    for i in range(n):
        for j in range(n):
            s = 0.0
            for a in range(n):
                s += V[i, a] * w[a] * V[j, a]
            S[i, j] = s
    for i in range(n):
        for j in range(i):
            S[i, j] = S[j, i] = 0.5 * (S[i, j] + S[j, i])
    if not chol(S, L):
        for i in range(n):
            for j in range(n):
                L[i, j] = np.nan
    return bad


@numba.njit(cache=True, nogil=True)
def lower_inverse(L: F64, Li: F64) -> None:
    """``Li = L^-1`` of a lower triangular ``L`` (forward substitution)."""
    n = L.shape[0]
    s = np.empty(n)
    for i in range(n):  # row i from the rows above it (memory order; each entry's sum in order)
        for j in range(n):
            s[j] = 1.0 if i == j else 0.0
        for k in range(i):
            lik = L[i, k]
            for j in range(k + 1):
                s[j] -= lik * Li[k, j]
        d = L[i, i]
        for j in range(n):
            Li[i, j] = s[j] / d if j <= i else 0.0
