"""Constraint rows and the Delassus operator built from per-body nodal compliances.

A constraint block is 3 rows ``u = F sum_t w_t v[node_t]`` (frame ``F``; terms may lie on
several bodies, e.g. an attachment ``v_a - v_b``). With each body's implicit matrix ``A_b``
factorized, the compliance of the nodes that constraints touch,
``G_b = A_b^-1 E_b`` (``E_b`` selects those nodes' DOFs), gives

    W = sum_b T_b (E_b^T G_b) T_b^T,      dv_b = G_b T_b^T lam,

where ``T_b`` maps the touched nodes' velocities to constraint rows. ``G_b`` is computed
once per node per step and grows as contacts are added (Duriez et al. 2006, "Realistic
haptic rendering of interacting deformable objects in virtual environments", sec. 4).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from softcrawl.fem.linalg import Factorization


@dataclass(frozen=True, eq=False)
class Term:
    """``sum_a w_a v[node_a]`` on one body (local node indices)."""

    body: int
    nodes: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True, eq=False)
class Block:
    """Three constraint rows ``frame @ sum(term velocities)``."""

    frame: np.ndarray
    terms: tuple[Term, ...]


class NodalCompliance:
    """Columns ``A^-1 E`` of one body's factorized matrix for a growing set of nodes.

    Args:
        factor: the body's factorized implicit matrix (fixed DOFs as identity rows).
        free_dofs: ``(3n,)`` bool; fixed DOFs get zero compliance.
    """

    def __init__(self, factor: Factorization, free_dofs: np.ndarray):
        self.factor, self.free = factor, free_dofs
        self.index: dict[int, int] = {}
        self.G = np.zeros((len(free_dofs), 0))

    def ensure(self, nodes: np.ndarray) -> None:
        """Compute the columns of nodes not seen yet (one solve per DOF)."""
        new = [int(a) for a in dict.fromkeys(np.asarray(nodes).tolist()) if a not in self.index]
        if not new:
            return
        n_dof = len(self.free)
        E = np.zeros((n_dof, 3 * len(new)))
        dofs = (3 * np.asarray(new)[:, None] + np.arange(3)).ravel()
        E[dofs, np.arange(len(dofs))] = self.free[dofs]
        cols = self.factor.solve(E) * self.free[:, None]
        for a in new:
            self.index[a] = len(self.index)
        self.G = np.hstack([self.G, cols])

    def nodes(self) -> np.ndarray:
        """``(K,)`` the nodes seen, in column order."""
        return np.fromiter(self.index, np.int64, len(self.index))

    @property
    def n_columns(self) -> int:
        """``3K``: columns computed so far."""
        return self.G.shape[1]

    def correction(self, y: np.ndarray) -> np.ndarray:
        """``(n, 3)`` velocity change ``A^-1 E y`` for generalised impulses ``y`` ``(3K,)``."""
        return (self.G @ y).reshape(-1, 3)

    def nodal(self) -> np.ndarray:
        """``(3K, 3K)`` compliance ``E^T A^-1 E`` of the K nodes seen, ordered as columns."""
        return self.G[(3 * self.nodes()[:, None] + np.arange(3)).ravel()]


def assemble(blocks: list[Block], compliances: dict[int, NodalCompliance],
             velocities: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray, dict[int, sp.csr_matrix]]:
    """Delassus operator and free constraint velocities of a list of blocks.

    Args:
        blocks: the constraint blocks (3 rows each).
        compliances: body -> its :class:`NodalCompliance` (nodes are added as needed).
        velocities: body -> ``(n_b, 3)`` free velocities, mm/s.

    Returns:
        ``(W, u_free, T)``: ``W`` ``(3B, 3B)`` (mm/s per mN s), ``u_free = H v_free`` ``(3B,)``,
        and body -> sparse ``T_b`` ``(3B, 3K_b)`` for :func:`velocity_correction`.
    """
    entries: dict[int, tuple[list, list, list]] = {}
    for j, blk in enumerate(blocks):
        for t in blk.terms:
            rows, nodes, coef = entries.setdefault(t.body, ([], [], []))
            rows.append(np.full(len(t.nodes), j))
            nodes.append(t.nodes)
            coef.append(t.weights[:, None, None] * blk.frame[None])
    n_rows = 3 * len(blocks)
    W = np.zeros((n_rows, n_rows))
    u_free = np.zeros(n_rows)
    T = {}
    r3 = np.arange(3)
    for b, (rows, nodes, coef) in entries.items():
        c = compliances[b]
        nodes = np.concatenate(nodes)
        c.ensure(nodes)
        cols = np.fromiter((c.index[a] for a in nodes.tolist()), np.int64, len(nodes))
        blk_rows, vals = np.concatenate(rows), np.concatenate(coef)  # (m,), (m, 3, 3)
        ii = np.broadcast_to((3 * blk_rows[:, None] + r3)[:, :, None], vals.shape)
        jj = np.broadcast_to((3 * cols[:, None] + r3)[:, None, :], vals.shape)
        Tb = sp.csr_matrix((vals.ravel(), (ii.ravel(), jj.ravel())), shape=(n_rows, c.n_columns))
        TN = Tb @ c.nodal()
        W += np.asarray(Tb @ TN.T)  # T N T^T (N symmetric)
        u_free += Tb @ velocities[b][c.nodes()].ravel()
        T[b] = Tb
    return W, u_free, T


def velocity_correction(lam: np.ndarray, T: dict[int, sp.csr_matrix],
                        compliances: dict[int, NodalCompliance]) -> dict[int, np.ndarray]:
    """body -> ``(n_b, 3)`` velocity corrections ``A_b^-1 H_b^T lam``, mm/s."""
    return {b: compliances[b].correction(Tb.T @ lam) for b, Tb in T.items()}
