"""ECSW hyper-reduction: sparse non-negative element weights (reduction.md, "Hyper-reduction").

Find ``xi >= 0`` with few non-zeros and ``|G xi - b| <= tol_gie |b|``, ``b = G 1``, where
``G[(s, k), e] = Phi_e[:, k]^T f_e(x_s)`` (Farhat, Avery, Chapman & Cortial 2014, "Dimensional
reduction of nonlinear finite element dynamic models with finite rotations and
energy-conserving mesh sampling and weighting", sec. 3; solver: Lawson & Hanson 1974,
*Solving Least Squares Problems*, ch. 23, stopped at the tolerance).

Everything works on the Gram matrix ``G^T G`` (``E x E``), accumulated state by state, so
``G`` itself (rows = states x modes, up to ~1e10 entries in the reference pipeline) is never
stored: ``G^T r = G^T b - (G^T G) xi``, ``|r|^2 = b^T b - 2 xi^T G^T b + xi^T G^T G xi``,
and the least-squares problems on the active set are Cholesky solves of ``(G^T G)_AA``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla


class GramAccumulator:
    """Streams ``G^T G`` for one element family.

    Args:
        n_elements: columns of ``G``.
    """

    def __init__(self, n_elements: int):
        self.gram = np.zeros((n_elements, n_elements))
        self.rows = 0

    def add(self, block: np.ndarray) -> None:
        """Add rows of ``G``: ``block`` ``(n_elements, m)`` = the reduced force of every
        element at one training state (column ``k`` = mode ``k``)."""
        if block.shape[0] != self.gram.shape[0] or not np.all(np.isfinite(block)):
            raise ValueError(f"need a finite ({self.gram.shape[0]}, m) block, got {block.shape}")
        self.gram += block @ block.T
        self.rows += block.shape[1]


@dataclass(frozen=True)
class ECSWResult:
    """Result of :func:`ecsw_weights`.

    Attributes:
        elements: ``(k,)`` the RID, sorted.
        weights: ``(k,)`` ``xi_e > 0``.
        relative_residual: ``|G xi - b| / |b|``.
        iterations: elements added (including those later dropped).
    """

    elements: np.ndarray
    weights: np.ndarray
    relative_residual: float
    iterations: int


def ecsw_weights(gram: np.ndarray, tol_gie: float, max_elements: int | None = None) -> ECSWResult:
    """Greedy Lawson-Hanson NNLS on the Gram matrix, stopped at ``tol_gie``.

    Each pass adds the element most correlated with the residual, solves the unconstrained
    least squares on the active set, and steps back along the segment to the previous
    iterate until all active weights are positive (dropping those that reach zero).

    Args:
        gram: ``(E, E)`` ``G^T G`` (symmetric PSD).
        tol_gie: relative residual target in (0, 1) (reduction.md; reference 0.001).
        max_elements: stop when the RID has this many elements (default ``E``).

    Raises:
        ValueError: a non-square or non-finite Gram matrix, or a tolerance out of range.
    """
    Gm = np.asarray(gram, float)
    E = Gm.shape[0]
    if Gm.shape != (E, E) or not np.all(np.isfinite(Gm)):
        raise ValueError(f"gram must be a finite square matrix, got {Gm.shape}")
    if not 0 < tol_gie < 1:
        raise ValueError(f"tol_gie must be in (0, 1), got {tol_gie}")
    cap = E if max_elements is None else min(E, int(max_elements))
    Gtb = Gm.sum(axis=1)
    btb = float(Gtb.sum())
    if btb <= 0:
        return ECSWResult(np.zeros(0, np.int64), np.zeros(0), 0.0, 0)
    xi = np.zeros(E)
    active: list[int] = []
    iterations = 0

    def residual(x: np.ndarray) -> float:
        return float(np.sqrt(max(btb - 2 * x @ Gtb + x @ (Gm @ x), 0.0) / btb))

    def lsq(idx: list[int]) -> np.ndarray:
        A = Gm[np.ix_(idx, idx)]
        try:
            return sla.cho_solve(sla.cho_factor(A), Gtb[idx])
        except np.linalg.LinAlgError:  # (near) dependent columns: minimum-norm solution
            return np.linalg.lstsq(A, Gtb[idx], rcond=None)[0]

    res = 1.0
    while res > tol_gie and len(active) < cap:
        corr = Gtb - Gm[:, active] @ xi[active] if active else Gtb.copy()
        corr[active] = -np.inf
        j = int(np.argmax(corr))
        if not corr[j] > 0:
            break
        active.append(j)
        iterations += 1
        while True:
            z = lsq(active)
            if np.all(z > 0):
                xi[active] = z
                break
            old = xi[active]
            neg = z <= 0
            alpha = np.min(old[neg] / (old[neg] - z[neg]))
            new = old + alpha * (z - old)
            keep = new > 1e-14 * max(1.0, new.max())
            xi[active] = np.where(keep, new, 0.0)
            active = [a for a, k in zip(active, keep) if k]
            if not active:
                break
        res = residual(xi)
    idx = np.array(sorted(active), np.int64)
    return ECSWResult(idx, xi[idx], res, iterations)
