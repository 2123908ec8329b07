"""Sparse symmetric positive-definite solves.

Backend: CHOLMOD's supernodal Cholesky as bundled by the ``cholespy`` wheel (no system
SuiteSparse needed). Measured on one 4 mm PneuNet matrix (8,229 DOF, this 2-core machine):
factorization 0.13 s and 115 right-hand sides (a typical contact Delassus build) in
0.10 s, against 0.08 s + 0.37 s for QDLDL and 0.40 s + 0.80 s for SuperLU (``splu``);
see ``benchmarks/RESULTS.md``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from cholespy import CholeskySolverD, MatrixType


class Factorization:
    """Cholesky factorization of a sparse SPD matrix.

    Args:
        A: ``(n, n)`` sparse symmetric positive-definite matrix (full storage).

    Raises:
        np.linalg.LinAlgError: if the matrix is not positive definite.
    """

    def __init__(self, A: sp.spmatrix):
        A = sp.csc_matrix(A)
        self.n = A.shape[0]
        try:
            self._solver = CholeskySolverD(
                self.n, A.indptr.astype(np.int32), A.indices.astype(np.int32), A.data, MatrixType.CSC
            )
        except (ValueError, RuntimeError) as exc:
            raise np.linalg.LinAlgError(f"sparse Cholesky factorization failed: {exc}") from exc

    def solve(self, b: np.ndarray) -> np.ndarray:
        """Solve ``A x = b`` for ``b`` of shape ``(n,)`` or ``(n, k)``."""
        b = np.asarray(b, dtype=np.float64)
        b2 = np.ascontiguousarray(b.reshape(self.n, -1))
        x = np.empty_like(b2)
        if b2.shape[1]:
            self._solver.solve(b2, x)
        return x.reshape(b.shape)
