"""Constraint rows and the Delassus operator built from per-body compliances.

A constraint block is 3 rows of velocity. Every block touches a full-order body through one
3-vector of that body: an attachment through its *fixed rows* ``H_f`` (the weighted
combination of a patch of nodes, :class:`FixedRows`: one block per attachment), a floor
contact through one node. With the body's implicit matrix ``A_b`` factorized, its compliance
columns ``G = A_b^-1 E`` (``E = [H_f^T, node selectors]``) give ``T = E^T A_b^-1 E``, and a
block ``i`` with 3 x 3 coefficient ``P_i`` on column triple ``c_i`` contributes

    W_ij += P_i T[c_i, c_j] P_j^T,     u_i += P_i (E^T v)[c_i],     dv_b = G sum_i E_ci P_i^T lam_i

(the Delassus operator ``W = sum_b H_b A_b^-1 H_b^T``: Duriez et al. 2006, "Realistic haptic
rendering of interacting deformable objects in virtual environments", sec. 4). A body whose
matrix is a rotated constant (a floating frame: ``A = R A_0 R^T`` blockwise) keeps the
columns of ``A_0`` and has every coefficient multiplied by ``R`` on the right.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp
from numba import njit

from softcrawl.fem.linalg import Factorization


def attachment_matrix(model) -> sp.csr_matrix:
    """``(3A, 3N)`` sparse rows giving every attachment's violation ``x_a - x_b`` (mm) from the
    stacked positions ``x.ravel()`` of a :class:`~softcrawl.fem.model.Model` (attachment
    ``j`` is rows ``3j .. 3j + 2``)."""
    rows, cols, vals = [], [], []
    i = np.arange(3)
    for j, att in enumerate(model.attachments):
        for ref, sign in ((att.a, 1.0), (att.b, -1.0)):
            nodes = model.node_offsets[ref.body] + np.asarray(ref.nodes)
            rows.append(np.broadcast_to(3 * j + i, (len(nodes), 3)).ravel())
            cols.append((3 * nodes[:, None] + i).ravel())
            vals.append(np.repeat(sign * np.asarray(ref.weights, float), 3))
    shape = (3 * len(model.attachments), 3 * model.n_nodes)
    if not rows:
        return sp.csr_matrix(shape)
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=shape)


@dataclass(frozen=True, eq=False)
class FixedRows:
    """A body's permanent constraint blocks (its attachments) as one sparse row matrix.

    Attributes:
        blocks: ``(F,)`` sorted global block indices.
        H: ``(3F, 3n)`` CSR rows: block ``blocks[k]``, row ``i`` is row ``3k + i``.
    """

    blocks: np.ndarray
    H: sp.csr_matrix

    @classmethod
    def of_body(cls, rows: sp.csr_matrix, first: int, n_nodes: int) -> FixedRows | None:
        """The blocks of global constraint ``rows`` (``(3B, 3N)``, e.g.
        :func:`attachment_matrix`) that touch the body of nodes ``first .. first + n_nodes - 1``,
        restricted to its columns; None if none does."""
        H = sp.csr_matrix(rows[:, 3 * first:3 * (first + n_nodes)])
        blocks = np.unique(np.flatnonzero(np.diff(H.indptr)) // 3)
        if not len(blocks):
            return None
        return cls(blocks, sp.csr_matrix(H[(3 * blocks[:, None] + np.arange(3)).ravel()]))


class NodalCompliance:
    """Compliance columns ``G = A^-1 E`` of one full-order body's factorized matrix ``A``:
    first one per row of its fixed blocks (``E = H_f^T``), then one per DOF of a growing set
    of nodes (``E`` selects DOFs), and ``T = E^T A^-1 E``.

    Args:
        factor: the body's factorized implicit matrix (fixed DOFs as identity rows).
        free_dofs: ``(3n,)`` bool; fixed DOFs get zero compliance.
        fixed: the body's permanent constraint rows (None: none).

    Attributes:
        rotation: ``(3, 3)`` ``R`` of a floating-frame body whose matrix is ``R A R^T``
            blockwise (identity otherwise): every coefficient is multiplied by it.
    """

    def __init__(self, factor: Factorization, free_dofs: np.ndarray, fixed: FixedRows | None = None):
        self.factor, self.free, self.fixed = factor, free_dofs, fixed
        self.rotation = np.eye(3)
        self.n_fixed = 0 if fixed is None else fixed.H.shape[0]
        self.G = self._solve(fixed.H.T.toarray()) if self.n_fixed else np.zeros((len(free_dofs), 0))
        self._nodes: list[int] = []  # nodes seen, in column order (after the fixed rows' columns)
        self._column = np.full(len(free_dofs) // 3, -1)  # node -> its position in _nodes, -1 if unseen
        self._gram: np.ndarray | None = None

    def _solve(self, E: np.ndarray) -> np.ndarray:
        free = self.free[:, None]
        return self.factor.solve(E * free) * free

    def columns(self, nodes: np.ndarray) -> np.ndarray:
        """``(F + k,)`` first column of the triple of each fixed block, then of each of the
        (local) ``nodes``; columns of nodes not seen yet are computed (one solve per DOF)."""
        nodes = np.asarray(nodes, np.int64)
        new = list(dict.fromkeys(nodes[self._column[nodes] < 0].tolist()))
        if new:
            dofs = (3 * np.asarray(new)[:, None] + np.arange(3)).ravel()
            E = np.zeros((len(self.free), len(dofs)))
            E[dofs, np.arange(len(dofs))] = 1.0
            self.G = np.hstack([self.G, self._solve(E)])
            self._column[new] = np.arange(len(self._nodes), len(self._nodes) + len(new))
            self._nodes += new
            self._gram = None
        return np.concatenate([np.arange(0, self.n_fixed, 3), self.n_fixed + 3 * self._column[nodes]])

    def et(self, a: np.ndarray) -> np.ndarray:
        """``E^T a`` for ``a`` ``(3n,)`` or ``(3n, k)``."""
        dofs = (3 * np.asarray(self._nodes, np.int64)[:, None] + np.arange(3)).ravel()
        return np.concatenate([self.fixed.H @ a, a[dofs]]) if self.n_fixed else a[dofs]

    @property
    def gram(self) -> np.ndarray:
        """``T = E^T A^-1 E`` for the current columns."""
        if self._gram is None:
            self._gram = self.et(self.G)
        return self._gram


@njit(cache=True)
def add_block_delassus(W, u, T, Etv, columns, P, blocks):
    """``W[i, j] += P_i T[c_i, c_j] P_j^T`` and ``u_i += P_i (E^T v)[c_i]`` over a body's
    blocks (module doc).

    Args:
        W: ``(3B, 3B)`` Delassus operator, added to; u: ``(3B,)`` free constraint velocities.
        T: ``(K, K)`` the body's ``E^T A^-1 E``; Etv: ``(K,)`` its ``E^T v``.
        columns: ``(b,)`` first column of each block's triple; P: ``(b, 3, 3)`` coefficients;
        blocks: ``(b,)`` global block numbers.
    """
    nb = columns.shape[0]
    PT = np.empty((3, 3))
    for p in range(nb):
        cp, rp = columns[p], 3 * blocks[p]
        for i in range(3):
            acc = 0.0
            for k in range(3):
                acc += P[p, i, k] * Etv[cp + k]
            u[rp + i] += acc
        for q in range(nb):
            cq, rq = columns[q], 3 * blocks[q]
            for i in range(3):
                for k in range(3):
                    acc = 0.0
                    for a in range(3):
                        acc += P[p, i, a] * T[cp + a, cq + k]
                    PT[i, k] = acc
            for i in range(3):
                for j in range(3):
                    acc = 0.0
                    for k in range(3):
                        acc += PT[i, k] * P[q, j, k]
                    W[rp + i, rq + j] += acc


@njit(cache=True)
def block_impulses(lam, columns, P, blocks, n_columns):
    """``(K,)`` ``sum_i E_ci P_i^T lam_i``: a body's impulses in its column coordinates."""
    g = np.zeros(n_columns)
    for p in range(columns.shape[0]):
        c, r = columns[p], 3 * blocks[p]
        for k in range(3):
            g[c + k] += P[p, 0, k] * lam[r] + P[p, 1, k] * lam[r + 1] + P[p, 2, k] * lam[r + 2]
    return g


@dataclass(frozen=True, eq=False)
class BodyBlocks:
    """One body's constraint blocks in one solve: what :func:`body_correction` needs.

    Attributes:
        columns: ``(b,)`` first compliance column of each block; P: ``(b, 3, 3)``
        coefficients (times the body's rotation); blocks: ``(b,)`` global block numbers.
    """

    columns: np.ndarray
    P: np.ndarray
    blocks: np.ndarray


def add_body(W: np.ndarray, u: np.ndarray, c: NodalCompliance, v: np.ndarray, nodes: np.ndarray,
             contact_coefs: np.ndarray, contact_blocks: np.ndarray) -> BodyBlocks:
    """Add a body's terms to ``W`` ``(3B, 3B)`` and ``u = H v_free`` ``(3B,)``: all its fixed
    blocks (coefficient I) and contacts at its local ``nodes`` (``contact_coefs`` ``(k, 3, 3)``,
    global blocks ``contact_blocks``); ``v``: ``(n, 3)`` its free velocities, mm/s."""
    columns = c.columns(nodes)
    nf = len(columns) - len(nodes)
    R = c.rotation
    P = np.concatenate([np.broadcast_to(R, (nf, 3, 3)), contact_coefs @ R])
    blocks = np.concatenate([c.fixed.blocks if nf else np.zeros(0, np.int64), contact_blocks]).astype(np.int64)
    add_block_delassus(W, u, c.gram, c.et((v @ R).ravel()), columns, P, blocks)
    return BodyBlocks(columns, P, blocks)


def body_correction(c: NodalCompliance, lam: np.ndarray, bb: BodyBlocks) -> np.ndarray:
    """``(n, 3)`` a body's velocity change ``A^-1 H^T lam`` (world frame), mm/s."""
    g = block_impulses(lam, bb.columns, bb.P, bb.blocks, c.G.shape[1])
    return (c.G @ g).reshape(-1, 3) @ c.rotation.T
