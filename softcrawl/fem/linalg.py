"""Sparse symmetric positive-definite solves with factorization reuse.

Backend: CHOLMOD (scikit-sparse, optional extra ``softcrawl[cholmod]``) when importable,
else SuperLU (``scipy.sparse.linalg.splu`` with the ``MMD_AT_PLUS_A`` ordering, measured
2.2x faster than COLAMD on these matrices). A factorization may be *lagged*: kept for
several steps and used as the preconditioner of conjugate gradients on the current
matrix, refactorizing when CG needs too many iterations.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

try:  # pragma: no cover - optional
    from sksparse.cholmod import cholesky as _cholmod_cholesky
except Exception:  # noqa: BLE001
    _cholmod_cholesky = None

BACKEND = "cholmod" if _cholmod_cholesky is not None else "superlu"


class Factorization:
    """A sparse direct factorization of an SPD matrix.

    Args:
        A: ``(n, n)`` sparse symmetric positive-definite matrix.

    Raises:
        np.linalg.LinAlgError: if the matrix is singular or not positive definite (CHOLMOD).
    """

    def __init__(self, A: sp.spmatrix):
        if _cholmod_cholesky is not None:  # pragma: no cover - optional
            self._solve = _cholmod_cholesky(sp.csc_matrix(A))
        else:
            try:
                lu = spla.splu(sp.csc_matrix(A), permc_spec="MMD_AT_PLUS_A")
            except RuntimeError as exc:  # "Factor is exactly singular"
                raise np.linalg.LinAlgError(str(exc)) from exc
            self._solve = lu.solve

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` for ``b`` of shape ``(n,)`` or ``(n, k)``."""
        return self._solve(np.asarray(b, dtype=np.float64))


class LaggedSolver:
    """Solves a sequence of slowly changing SPD systems, reusing factorizations.

    Args:
        max_age: reuse a factorization for at most this many calls to :meth:`solve`
            (1 = refactorize every time: exact direct solves).
        rtol: relative residual tolerance of preconditioned CG.
        max_cg_iterations: refactorize when CG has not converged after this many iterations.

    Attributes:
        factor: the current factorization (use it for the Delassus operator).
        factorizations, cg_iterations: counters for statistics.
    """

    def __init__(self, max_age: int = 1, rtol: float = 1e-10, max_cg_iterations: int = 25):
        if max_age < 1:
            raise ValueError(f"max_age must be >= 1, got {max_age}")
        self.max_age, self.rtol, self.max_cg_iterations = max_age, rtol, max_cg_iterations
        self.factor: Factorization | None = None
        self.age = 0
        self.factorizations = 0
        self.cg_iterations = 0

    def _refactor(self, A: sp.spmatrix) -> None:
        self.factor = Factorization(A)
        self.age = 0
        self.factorizations += 1

    def solve(self, A: sp.spmatrix, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` (``b`` of shape ``(n,)``)."""
        if self.factor is None or self.age >= self.max_age:
            self._refactor(A)
        self.age += 1
        if self.age == 1:
            return self.factor.solve(b)
        M = spla.LinearOperator(A.shape, matvec=self.factor.solve, dtype=np.float64)
        its = 0

        def count(_):
            nonlocal its
            its += 1

        x, info = spla.cg(A, b, x0=self.factor.solve(b), rtol=self.rtol, atol=0.0,
                          maxiter=self.max_cg_iterations, M=M, callback=count)
        self.cg_iterations += its
        if info != 0:
            self._refactor(A)
            self.age = 1
            return self.factor.solve(b)
        return x
