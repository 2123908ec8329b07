"""Sparse symmetric positive-definite solves.

Backend: QDLDL (the ``qdldl`` wheel of the OSQP project: LDL^T with AMD ordering), with
numeric refactorization *in place* for a matrix of the same pattern (the symbolic
analysis is reused), and a compiled multi-right-hand-side triangular solve on its
factors. Measured on one 4 mm PneuNet implicit matrix (8,229 DOF, one core of this
2-core machine): refactorization 0.07 s + 115 right-hand sides 0.06 s, against
0.13 s + 0.10 s for CHOLMOD through ``cholespy`` (which also leaked the last solve's
workspace of every freed solver: ~6 MB per robot step) and 0.40 s + 0.8 s for SuperLU.
"""

from __future__ import annotations

import numpy as np
import qdldl
import scipy.sparse as sp
from numba import njit


@njit(cache=True)
def ldl_solve_many(Lp, Li, Lx, d, perm, B):
    """Solve ``A X = B`` with ``A = P (I + L) D (I + L)^T P^T`` (QDLDL's factors).

    Args:
        Lp, Li, Lx: strictly lower-triangular ``L`` in CSC form.
        d: ``(n,)`` the diagonal ``D``.
        perm: ``(n,)`` the permutation ``p`` (``P[p, arange(n)] = 1``).
        B: ``(n, k)`` right-hand sides (C order).

    Returns:
        ``(n, k)`` solutions.
    """
    n, k = B.shape
    X = np.empty_like(B)
    for i in range(n):
        for r in range(k):
            X[i, r] = B[perm[i], r]
    for j in range(n):
        for q in range(Lp[j], Lp[j + 1]):
            i, lv = Li[q], Lx[q]
            for r in range(k):
                X[i, r] -= lv * X[j, r]
    for j in range(n):
        dj = 1.0 / d[j]
        for r in range(k):
            X[j, r] *= dj
    for j in range(n - 1, -1, -1):
        for q in range(Lp[j], Lp[j + 1]):
            i, lv = Li[q], Lx[q]
            for r in range(k):
                X[j, r] -= lv * X[i, r]
    out = np.empty_like(B)
    for i in range(n):
        for r in range(k):
            out[perm[i], r] = X[i, r]
    return out


class Factorization:
    """LDL^T factorization of a sparse SPD matrix, refactorizable in place.

    Args:
        A: ``(n, n)`` sparse symmetric positive-definite matrix (full storage).

    Raises:
        np.linalg.LinAlgError: if the factorization fails (zero or non-finite pivot).
    """

    def __init__(self, A: sp.spmatrix):
        A = sp.csc_matrix(A)
        self.n = A.shape[0]
        try:
            self._solver = qdldl.Solver(A)
        except (ValueError, RuntimeError) as exc:
            raise np.linalg.LinAlgError(f"sparse LDL^T factorization failed: {exc}") from exc
        self._factors = None

    def refactor(self, A: sp.spmatrix) -> None:
        """Numeric refactorization of a matrix with the same sparsity pattern.

        Raises:
            np.linalg.LinAlgError: if the factorization fails.
        """
        try:
            self._solver.update(sp.csc_matrix(A))
        except (ValueError, RuntimeError) as exc:
            raise np.linalg.LinAlgError(f"sparse LDL^T refactorization failed: {exc}") from exc
        self._factors = None

    def ldl_factors(self) -> tuple[np.ndarray, ...]:
        """``(Lp, Li, Lx, d, perm)``: the factors as :func:`ldl_solve_many` takes them."""
        if self._factors is None:
            L, d, p = self._solver.factors()
            L = sp.csc_matrix(L)
            self._factors = (L.indptr.astype(np.int64), L.indices.astype(np.int64), L.data,
                             np.asarray(d, np.float64), np.asarray(p, np.int64))
        return self._factors

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` for ``b`` of shape ``(n,)`` or ``(n, k)``."""
        b = np.asarray(b, dtype=np.float64)
        if b.ndim == 1:
            return self._solver.solve(b)
        return ldl_solve_many(*self.ldl_factors(), np.ascontiguousarray(b))


class ReusedFactorization:
    """Solves a sequence of slowly changing SPD systems, reusing a factorization.

    The first solve after a (re)factorization is direct; later ones run conjugate gradients
    on the *current* matrix preconditioned by the kept factorization, so their accuracy is
    that of ``rtol`` and does not depend on the lag. The matrix is refactorized every
    ``max_age`` solves, or when CG needs more than ``max_cg_iterations``.

    Args:
        max_age: solves per factorization (1 = refactorize every time).
        rtol: CG relative residual tolerance ``|A x - b| <= rtol |b|``.
        max_cg_iterations: CG iteration limit before refactorizing.

    Attributes:
        factor: the kept factorization (of the matrix at the last refactorization).
        factorizations, cg_iterations: running counters.
    """

    def __init__(self, max_age: int = 1, rtol: float = 1e-9, max_cg_iterations: int = 30):
        if max_age < 1:
            raise ValueError(f"max_age must be >= 1, got {max_age}")
        self.max_age, self.rtol, self.max_cg_iterations = max_age, rtol, max_cg_iterations
        self.factor: Factorization | None = None
        self.age = 0
        self.factorizations = 0
        self.cg_iterations = 0

    def _refactor(self, A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
        if self.factor is None:
            self.factor = Factorization(A)
        else:
            self.factor.refactor(A)
        self.age = 1
        self.factorizations += 1
        return self.factor.solve(b)

    def solve(self, A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` (``b`` of shape ``(n,)``)."""
        if self.factor is None or self.age >= self.max_age:
            return self._refactor(A, b)
        self.age += 1
        x = self.factor.solve(b)
        r = b - A @ x
        z = self.factor.solve(r)
        p = z.copy()
        rz = r @ z
        target = self.rtol * np.linalg.norm(b)
        for _ in range(self.max_cg_iterations):
            if np.linalg.norm(r) <= target:
                return x
            self.cg_iterations += 1
            Ap = A @ p
            alpha = rz / (p @ Ap)
            x += alpha * p
            r -= alpha * Ap
            z = self.factor.solve(r)
            rz, rz_old = r @ z, rz
            p = z + (rz / rz_old) * p
        if np.linalg.norm(r) <= target:
            return x
        return self._refactor(A, b)
