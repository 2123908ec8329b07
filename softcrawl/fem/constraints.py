"""Constraint rows and the Delassus operator built from per-body compliances.

A constraint block is 3 rows ``u_k = sum_e C_e v[node_e]`` over its entries ``e`` (3 x 3
coefficients ``C_e``: ``w I`` for an attachment point, the contact frame for a floor
contact; entries may lie on several bodies, e.g. an attachment ``v_a - v_b``). Each body
expresses its entries as a Jacobian ``J_b`` in its own coordinates (the DOFs of the nodes
that constraints touch for a full-order body, the modes for a reduced one) and, with its
implicit matrix ``A_b`` factorized,

    W = sum_b J_b A_b^-1 J_b^T,      dv_b = A_b^-1 J_b^T lam_b

(Duriez et al. 2006, "Realistic haptic rendering of interacting deformable objects in
virtual environments", sec. 4). A full-order body's compliance columns ``A_b^-1 E_b`` are
kept while its factorization is: one column per row of its permanent constraints (the
attachments, :class:`FixedRows`: 3 per attachment, however many nodes its patch spans) and
one per DOF of every other node a constraint touches (floor contacts), added as contacts
appear.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from softcrawl.fem.linalg import Factorization


def block_sum_matrix(blocks: np.ndarray, n_blocks: int) -> np.ndarray:
    """``(n_blocks, E)`` 0/1 matrix ``S`` with ``(S @ a)[b] = sum of a[e] over blocks[e] == b``
    (a dense product is faster than ``np.add.at`` at these sizes: tens of entries)."""
    S = np.zeros((n_blocks, len(blocks)))
    S[blocks, np.arange(len(blocks))] = 1.0
    return S


@dataclass(frozen=True, eq=False)
class Entries:
    """Constraint entries on one body: block ``blocks[e]`` gets ``coefs[e] @ v[nodes[e]]``.

    Attributes:
        blocks: ``(E,)`` global block indices.
        nodes: ``(E,)`` the body's local node indices.
        coefs: ``(E, 3, 3)`` coefficients.
    """

    blocks: np.ndarray
    nodes: np.ndarray
    coefs: np.ndarray

    def __add__(self, other: Entries) -> Entries:
        return Entries(*(np.concatenate([a, b]) for a, b in
                         ((self.blocks, other.blocks), (self.nodes, other.nodes), (self.coefs, other.coefs))))

    def apply(self, x: np.ndarray, n_blocks: int) -> np.ndarray:
        """``(n_blocks, 3)`` block sums ``sum_e C_e x[node_e]`` of a nodal field ``x`` ``(n, 3)``."""
        return block_sum_matrix(self.blocks, n_blocks) @ np.einsum("eij,ej->ei", self.coefs, x[self.nodes])


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
    def from_entries(cls, entries: Entries, n_nodes: int) -> FixedRows:
        """The rows of all ``entries`` (of one body with ``n_nodes`` nodes); repeated
        (block, node) entries are summed."""
        blocks = np.unique(entries.blocks)
        local = np.searchsorted(blocks, entries.blocks)
        i = np.arange(3)
        rows = np.broadcast_to(3 * local[:, None, None] + i[None, :, None], entries.coefs.shape)
        cols = np.broadcast_to(3 * entries.nodes[:, None, None] + i[None, None, :], entries.coefs.shape)
        H = sp.csr_matrix((entries.coefs.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * len(blocks), 3 * n_nodes))
        return cls(blocks, H)

    def locate(self, blocks: np.ndarray) -> np.ndarray:
        """``(E,)`` position of each of ``blocks`` in :attr:`blocks`, -1 where it is not one."""
        pos = np.minimum(np.searchsorted(self.blocks, blocks), len(self.blocks) - 1)
        return np.where(self.blocks[pos] == blocks, pos, -1)


class NodalCompliance:
    """Compliance columns ``G = A^-1 E`` of one body's factorized matrix ``A``: first one per
    row of its fixed blocks (``E = H_f^T``), then one per DOF of a growing set of nodes
    (``E`` selects DOFs). A Jacobian from :meth:`jacobian` is in these columns' coordinates:
    the rows ``H`` of a constraint are ``J E^T``.

    Args:
        factor: the body's factorized implicit matrix (fixed DOFs as identity rows).
        free_dofs: ``(3n,)`` bool; fixed DOFs get zero compliance.
        fixed: the body's permanent constraint rows (None: none). Every entry of
            :meth:`jacobian` in one of its blocks must be one of the entries it was built from.
    """

    def __init__(self, factor: Factorization, free_dofs: np.ndarray, fixed: FixedRows | None = None):
        self.factor, self.free, self.fixed = factor, free_dofs, fixed
        self._n_fixed = 0 if fixed is None else fixed.H.shape[0]
        if self._n_fixed:
            self.G = self._solve(fixed.H.T.toarray())
        else:
            self.G = np.zeros((len(free_dofs), 0))
        self._nodes: list[int] = []  # nodes seen, in column order (after the fixed rows' columns)
        self._column = np.full(len(free_dofs) // 3, -1)  # node -> its position in _nodes, -1 if unseen
        self._EtG: np.ndarray | None = None  # E^T A^-1 E for the current columns

    def _solve(self, E: np.ndarray) -> np.ndarray:
        free = self.free[:, None]
        return self.factor.solve(E * free) * free

    def ensure(self, nodes: np.ndarray) -> None:
        """Compute the columns of nodes not seen yet (one solve per DOF)."""
        nodes = np.asarray(nodes)
        new = list(dict.fromkeys(nodes[self._column[nodes] < 0].tolist()))
        if not new:
            return
        dofs = (3 * np.asarray(new)[:, None] + np.arange(3)).ravel()
        E = np.zeros((len(self.free), len(dofs)))
        E[dofs, np.arange(len(dofs))] = 1.0
        self.G = np.hstack([self.G, self._solve(E)])
        self._column[new] = np.arange(len(self._nodes), len(self._nodes) + len(new))
        self._nodes += new
        self._EtG = None

    def nodes(self) -> np.ndarray:
        """``(K,)`` the nodes seen, in column order."""
        return np.asarray(self._nodes, np.int64)

    def dofs(self) -> np.ndarray:
        """``(3K,)`` the DOFs of the nodes seen, in column order."""
        return (3 * self.nodes()[:, None] + np.arange(3)).ravel()

    def jacobian(self, entries: Entries, blocks: np.ndarray, n_blocks: int) -> np.ndarray:
        """``(3B, n_fixed_rows + 3K)`` rows of ``entries`` in column coordinates (adds node
        columns first); ``blocks`` ``(E,)`` are the entries' local block numbers in ``0..B-1``."""
        fixed_pos = self.fixed.locate(entries.blocks) if self._n_fixed else np.full(len(blocks), -1)
        on_fixed = fixed_pos >= 0
        nodal = ~on_fixed
        nodes, local, coefs = entries.nodes[nodal], blocks[nodal], entries.coefs[nodal]
        self.ensure(nodes)
        K, nf = len(self._nodes), self._n_fixed
        J = np.zeros((3 * n_blocks, nf + 3 * K))
        if on_fixed.any():  # a fixed block's rows are its own columns: identity
            lb, first = np.unique(blocks[on_fixed], return_index=True)
            k = fixed_pos[on_fixed][first]
            r = np.arange(3)
            J[(3 * lb[:, None] + r).ravel(), (3 * k[:, None] + r).ravel()] = 1.0
        if len(nodes):
            Jn = np.zeros((n_blocks, K, 3, 3))
            columns = self._column[nodes]
            if len(np.unique(local * K + columns)) == len(local):  # each (block, node) once: assign
                Jn[local, columns] = coefs
            else:
                np.add.at(Jn, (local, columns), coefs)
            J[:, nf:] = Jn.transpose(0, 2, 1, 3).reshape(3 * n_blocks, 3 * K)
        return J

    def _Et(self, a: np.ndarray) -> np.ndarray:
        """``E^T a`` for ``a`` ``(3n,)`` or ``(3n, k)``."""
        parts = [a[self.dofs()]]
        if self._n_fixed:
            parts.insert(0, self.fixed.H @ a)
        return np.concatenate(parts)

    def delassus(self, J: np.ndarray) -> np.ndarray:
        """``J E^T A^-1 E J^T``."""
        if self._EtG is None:
            self._EtG = self._Et(self.G)
        return J @ self._EtG @ J.T

    def constraint_velocity(self, J: np.ndarray, v: np.ndarray) -> np.ndarray:
        """``J E^T v`` for the body's velocities ``v`` ``(n, 3)``."""
        return J @ self._Et(v.ravel())

    def correction(self, J: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``(n, 3)`` velocity change ``A^-1 E J^T lam`` (the body's correction coordinates:
        its nodal velocities)."""
        return (self.G @ (J.T @ lam)).reshape(-1, 3)

    def velocities(self, correction: np.ndarray, nodes: np.ndarray | None = None) -> np.ndarray:
        """``(k, 3)`` nodal velocity change of a :meth:`correction` at local ``nodes``
        (None: ``(n, 3)``, all nodes)."""
        return correction if nodes is None else correction[nodes]


def assemble(entries: dict[int, Entries], compliances: dict, velocities: dict[int, np.ndarray],
             n_blocks: int) -> tuple[np.ndarray, np.ndarray, dict[int, tuple[np.ndarray, np.ndarray]]]:
    """Delassus operator and free constraint velocities.

    Args:
        entries: body -> its constraint entries.
        compliances: body -> its compliance (:class:`NodalCompliance`, or any object with
            the same ``jacobian``/``delassus``/``constraint_velocity``/``correction``/
            ``velocities``).
        velocities: body -> ``(n_b, 3)`` free velocities, mm/s.
        n_blocks: number of 3-row blocks.

    Returns:
        ``(W, u_free, jacobians)``: ``W`` ``(3B, 3B)`` (mm/s per mN s), ``u_free = H v_free``
        ``(3B,)``, and body -> ``(rows, J_b)`` for :func:`velocity_correction`.
    """
    W = np.zeros((3 * n_blocks, 3 * n_blocks))
    u_free = np.zeros(3 * n_blocks)
    jacobians = {}
    for b, ent in entries.items():
        touched = np.unique(ent.blocks)
        local = np.searchsorted(touched, ent.blocks)
        c = compliances[b]
        J = c.jacobian(ent, local, len(touched))
        rows = (3 * touched[:, None] + np.arange(3)).ravel()
        W[np.ix_(rows, rows)] += c.delassus(J)
        u_free[rows] += c.constraint_velocity(J, velocities[b])
        jacobians[b] = (rows, J)
    return W, u_free, jacobians


def velocity_correction(lam: np.ndarray, jacobians: dict[int, tuple[np.ndarray, np.ndarray]],
                        compliances: dict) -> dict[int, np.ndarray]:
    """body -> velocity correction ``A_b^-1 J_b^T lam_b`` in the body's correction
    coordinates (nodal velocities, mm/s, for a full-order body; the compliance's
    ``velocities`` method gives nodal values)."""
    return {b: compliances[b].correction(J, lam[rows]) for b, (rows, J) in jacobians.items()}
