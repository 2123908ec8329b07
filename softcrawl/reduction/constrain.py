"""The constraint stage of many reduced robots in one compiled pass (no Python work per robot per
step).

A reduced robot of the default kind (:class:`~softcrawl.reduction.solver.ReducedSolver` with a
:class:`~softcrawl.reduction.floating.FloatingFrameBody` disk and every other body in one
:class:`~softcrawl.reduction.group.ModalGroup`) is constrained by its attachments (legs to disk)
and its floor contacts. After the free motion, :func:`constrain_robots` does for every robot of a
batch what :meth:`ReducedSolver.constrain <softcrawl.reduction.solver.ReducedSolver.constrain>`
(the full solver's constraint stage with the reduced rows) does for one, in the same order and
by the same rules:

1. floor contact candidates: the disk's collision nodes and the legs' (bounded by their modal
   speed, as :func:`~softcrawl.reduction.kernels.floor_candidates`), sorted by node;
2. the contact set: last step's loaded contacts, or at first touch the deepest penetrating
   candidates (at most ``min_growth``); grown by the deepest candidates the solve leaves below the
   floor until there is none;
3. the Delassus operator: the disk's share from its compliance columns ``A_0^-1 E`` in its
   floating frame (:class:`DiskColumns`, shared by every robot with the same disk, with the
   coefficients times the frame rotation, :func:`~softcrawl.fem.constraints.add_block_delassus`),
   the legs' from their step matrices' Cholesky factors
   (:func:`~softcrawl.reduction.kernels.add_delassus`);
4. bilateral rows eliminated by a Schur complement, the contact problem solved exactly by the
   active-set polish from last step's impulses, else by projected Gauss-Seidel then the polish
   (:mod:`softcrawl.fem.contact`, with its extra sweep chunks);
5. the corrections: the disk's nodal velocities, the legs' modal velocities.

Only the disk compliance columns differ from the Python path: all collision nodes' columns are
solved once per process and disk (not grown per solver as contacts appear), which gives the same
numbers up to the order of round-off.
"""

from __future__ import annotations

import weakref
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp
from numba import njit

from softcrawl.fem.constraints import add_block_delassus, block_impulses
from softcrawl.fem.contact import EXTRA_SWEEP_CHUNKS, pgs_coulomb, polish_kernel
from softcrawl.fem.linalg import Factorization, ldl_solve_many
from softcrawl.fem.solver import FLOOR_FRAME, MIN_CONTACT_GROWTH
from softcrawl.reduction.kernels import (add_delassus, back_substitute_transposed, body_floor_candidates, corrections,
                                        forward_substitute, point_velocity)

#: Active-set rounds and relative tolerance of the polish (as :func:`softcrawl.fem.contact.polish_active_set`).
POLISH_ROUNDS, POLISH_RTOL = 30, 1e-9


class DiskColumns:
    """Compliance columns ``G = A_0^-1 E`` of one floating-frame body's constant step matrix
    (:meth:`FloatingFrameBody.step_factorization`), shared by every robot of the process with
    that body: three per attachment block met so far (``E`` = its rows ``H``; a block is known by
    its rows, so legs in the same slot of different designs share theirs), solved when a robot
    with it joins a constraint stage, and three per collision node (``E`` selects its DOFs),
    solved inside the compiled stage the first time the node is in contact (the same solve as
    :class:`~softcrawl.fem.constraints.NodalCompliance`'s).

    The Delassus blocks are formed from the columns as ``T_pq = (E_p^T G_q + (E_q^T G_p)^T) / 2``
    (:func:`_disk_gram`), the same numbers whichever designs the process met first.

    Args:
        factor: the factorized ``A_0`` (all DOFs free).
        collision: ``(c,)`` the body's collision nodes.

    Attributes:
        node_index: ``(n,)`` each node's position among the collision nodes (-1: none).
        node_Gt: ``(3c, 3n)`` collision-node columns (transposed; rows of nodes not yet in
            contact unset), node_done: ``(c,)`` which are solved.
        fixed_Gt: ``(3B, 3n)`` attachment-block columns (transposed); H: ``(3B, 3n)`` CSR rows.
    """

    def __init__(self, factor: Factorization, collision: np.ndarray):
        self.factor = factor
        self.ldl = factor.ldl_factors()
        n = factor.n // 3
        self.collision = np.asarray(collision, np.int64)
        self.node_index = np.full(n, -1, np.int64)
        self.node_index[self.collision] = np.arange(len(self.collision))
        self.node_Gt = np.empty((3 * len(self.collision), 3 * n))  # pages touched only when solved
        self.node_done = np.zeros(len(self.collision), np.bool_)
        self.fixed_Gt = np.zeros((0, 3 * n))
        self.H = sp.csr_matrix((0, 3 * n))
        self._blocks: dict[bytes, int] = {}

    def block_columns(self, H: sp.csr_matrix) -> np.ndarray:
        """``(F,)`` index of each 3-row block of the attachment rows ``H`` ``(3F, 3n)`` among
        this body's blocks (the columns of blocks not met before are solved and appended)."""
        Hd = H.toarray()
        out = np.empty(len(Hd) // 3, np.int64)
        new = []
        for b in range(len(out)):
            rows = np.ascontiguousarray(Hd[3 * b:3 * b + 3])
            key = rows.tobytes()
            if key not in self._blocks:
                self._blocks[key] = len(self._blocks)
                new.append(rows)
            out[b] = self._blocks[key]
        if new:  # one 3-column solve per block (the same numbers however blocks arrive)
            G = [self.factor.solve(np.ascontiguousarray(rows.T)).T for rows in new]
            self.fixed_Gt = np.vstack([self.fixed_Gt] + G)
            self.H = sp.csr_matrix(sp.vstack([self.H] + [sp.csr_matrix(rows) for rows in new]))
        return out


    def attachment_gram(self, blocks: np.ndarray) -> np.ndarray:
        """``(3F, 3F)`` ``T = (E^T G + (E^T G)^T) / 2`` of attachment ``blocks`` (as returned by
        :meth:`block_columns`; each entry from its own pair of blocks, so the same for the same
        blocks whatever else is known)."""
        rows = (3 * np.asarray(blocks)[:, None] + np.arange(3)).ravel()
        HG = np.asarray(self.H[rows] @ self.fixed_Gt[rows].T)
        return 0.5 * (HG + HG.T)


_COLUMNS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def disk_columns(factor: Factorization, collision: np.ndarray) -> DiskColumns:
    """The process's :class:`DiskColumns` of ``factor`` (made on first use; dropped with the
    factorization).

    Raises:
        ValueError: ``factor`` was met before with other collision nodes.
    """
    cols = _COLUMNS.get(factor)
    if cols is None:
        cols = _COLUMNS[factor] = DiskColumns(factor, collision)
    elif not np.array_equal(cols.collision, collision):
        raise ValueError("a floating body's factorization shared by bodies with different collision nodes")
    return cols


@njit(cache=True)
def _node_columns(j, node, ldl, node_Gt, node_done):
    """Solve collision node ``j``'s (DOFs of ``node``) three columns into ``node_Gt`` once (``ldl``:
    :meth:`Factorization.ldl_factors <softcrawl.fem.linalg.Factorization.ldl_factors>`)."""
    if node_done[j]:
        return
    Lp, Li, Lx, d, perm = ldl
    B = np.zeros((node_Gt.shape[1], 3))
    for a in range(3):
        B[3 * node + a, a] = 1.0
    X = ldl_solve_many(Lp, Li, Lx, d, perm, B)
    for a in range(3):
        for i in range(node_Gt.shape[1]):
            node_Gt[3 * j + a, i] = X[i, a]
    node_done[j] = True


@njit(cache=True)
def _column(kind, idx, node_Gt, fixed_Gt, a):
    """Column ``a`` of disk block ``(kind, idx)`` (kind 0: attachment block, 1: collision node)."""
    return fixed_Gt[3 * idx + a] if kind == 0 else node_Gt[3 * idx + a]


@njit(cache=True)
def _disk_gram(kinds, idxs, nodes, n_fixed, Tff, node_Gt, fixed_Gt):
    """``(3b, 3b)`` ``T = E^T A_0^-1 E`` of the disk's blocks ``(kinds, idxs, nodes)``: its first
    ``n_fixed`` (attachments) from ``Tff``, every entry with a collision node read off the other
    block's column at the node's DOFs (``T_pq = E_q^T G_p``, ``A_0`` symmetric)."""
    nb = kinds.shape[0]
    T = np.empty((3 * nb, 3 * nb))
    for p in range(nb):
        for q in range(nb):
            if p < n_fixed and q < n_fixed:
                for a in range(3):
                    for b in range(3):
                        T[3 * p + a, 3 * q + b] = Tff[3 * p + a, 3 * q + b]
            elif kinds[q] == 1:  # column of p at q's node
                for a in range(3):
                    col = _column(kinds[p], idxs[p], node_Gt, fixed_Gt, a)
                    for b in range(3):
                        T[3 * p + a, 3 * q + b] = col[3 * nodes[q] + b]
            else:  # p a node, q an attachment: column of q at p's node
                for b in range(3):
                    col = _column(kinds[q], idxs[q], node_Gt, fixed_Gt, b)
                    for a in range(3):
                        T[3 * p + a, 3 * q + b] = col[3 * nodes[p] + a]
    return T


def _disk_of(solver) -> int | None:
    """The floating-frame disk of a reduced solver whose constraint stage can be compiled (one
    modal group, that disk its only other body, a floor, attachments); None otherwise."""
    if solver.model.floor is None or len(solver.groups) != 1 or len(solver.nodal_bodies) != 1:
        return None
    (i,) = solver.nodal_bodies
    c = solver.compliance[i]
    if i not in solver.floating or c is None or c.fixed is None or not c.free.all():
        return None
    return i


class ContactSettings(NamedTuple):
    """The scalars of a constraint stage (:class:`~softcrawl.fem.solver.SolverSettings` and
    :class:`~softcrawl.fem.model.Floor`).

    Attributes:
        dt: time step, s. floor_height: the floor's z, mm. distance: contact distance, mm
            (a node is a candidate if its gap, now or after a free step, is below it).
        friction: Coulomb coefficient. tol, max_iter: Gauss-Seidel stopping rule (relative
            change, sweeps per chunk); extra_chunks: more chunks if the polish fails
            (:data:`softcrawl.fem.contact.EXTRA_SWEEP_CHUNKS`).
        min_growth: least growth of the contact set per round
            (:data:`softcrawl.fem.solver.MIN_CONTACT_GROWTH`).
    """

    dt: float
    floor_height: float
    distance: float
    friction: float
    tol: float
    max_iter: int
    extra_chunks: int
    min_growth: int


class Disks(NamedTuple):
    """The robots' floating-frame disks: one shared :class:`DiskColumns` (``c`` collision
    nodes of ``n``, ``B`` attachment blocks known) and each robot's placement and attachments.

    Attributes:
        start: ``(M,)`` first stacked row of each robot's disk.
        collision: ``(c,)`` the collision nodes (disk-local, sorted); node_index: ``(n,)``
            each node's position among them (-1: none).
        node_Gt: ``(3c, 3n)`` collision-node compliance columns, 1/kg (mm/s per mN s;
            transposed; solved here when first needed), node_done: ``(c,)`` which are solved.
        fixed_Gt: ``(3B, 3n)`` attachment-block columns (transposed); H_indptr, H_indices,
            H_data: their rows ``H`` ``(3B, 3n)`` in CSR.
        ldl: ``(Lp, Li, Lx, d, perm)`` the disk step matrix's factors
            (:meth:`Factorization.ldl_factors <softcrawl.fem.linalg.Factorization.ldl_factors>`).
        fixed_index, fixed_blocks: ``(M, F)`` each robot's attachment blocks as block numbers
            of the columns and of the robot; n_fixed: ``(M,)`` how many; Tff: ``(M, 3F, 3F)``
            their ``E^T A_0^-1 E`` (:meth:`DiskColumns.attachment_gram`).
    """

    start: np.ndarray
    collision: np.ndarray
    node_index: np.ndarray
    node_Gt: np.ndarray
    node_done: np.ndarray
    fixed_Gt: np.ndarray
    H_indptr: np.ndarray
    H_indices: np.ndarray
    H_data: np.ndarray
    ldl: tuple
    fixed_index: np.ndarray
    fixed_blocks: np.ndarray
    n_fixed: np.ndarray
    Tff: np.ndarray


class Attachments(NamedTuple):
    """The robots' attachment rows (violation ``x_a - x_b``, mm, over the stacked DOFs) in CSR.

    Attributes:
        start: ``(M + 1,)`` first row of each robot; count: ``(M,)`` its attachments (3 rows
            each); indptr, indices, data: the CSR rows.
    """

    start: np.ndarray
    count: np.ndarray
    indptr: np.ndarray
    indices: np.ndarray
    data: np.ndarray


class Legs(NamedTuple):
    """The robots' legs: bodies of one stacked :class:`~softcrawl.reduction.group.ModalGroup`
    (``L`` bodies, ``m`` modes, part of ``n`` nodes, ``c`` collision nodes, ``F`` attachment
    blocks each).

    Attributes:
        start: ``(M + 1,)`` first body of each robot.
        offsets: ``(L,)`` each body's first stacked row.
        collision: ``(c,)`` the part's collision nodes; bound: ``(c,)`` their basis rows'
            Frobenius norms.
        z_axes: ``(L, 3)`` world z in each body's part frame; basis: ``(3n, m)``.
        fixed_rows: ``(L, 3F, m)``, fixed_blocks: ``(L, F)``, frame_rot: ``(L, 3, 3)``: as
            the group's.
    """

    start: np.ndarray
    offsets: np.ndarray
    collision: np.ndarray
    bound: np.ndarray
    z_axes: np.ndarray
    basis: np.ndarray
    fixed_rows: np.ndarray
    fixed_blocks: np.ndarray
    frame_rot: np.ndarray


class FreeMotion(NamedTuple):
    """A step's free (unconstrained) motion of the robots.

    Attributes:
        v: ``(N, 3)`` stacked free velocities, mm/s (the disks' rows are read; the legs' are
            ``qd``'s).
        rotations: ``(M, 3, 3)`` each disk's floating-frame rotation
            (:meth:`FloatingFrameBody.free_rhs <softcrawl.reduction.floating.FloatingFrameBody.free_rhs>`).
        qd: ``(L, m)`` the legs' free modal velocities; chol: ``(L, m, m)`` their step
            matrices' Cholesky factors (:meth:`ModalGroup.free_motion
            <softcrawl.reduction.group.ModalGroup.free_motion>`).
    """

    v: np.ndarray
    rotations: np.ndarray
    qd: np.ndarray
    chol: np.ndarray


class Contacts(NamedTuple):
    """Contacts of each robot (robot-local sorted nodes), robot ``r``'s at ``start[r]:start[r + 1]``.

    Attributes:
        start: ``(M + 1,)``; nodes: ``(K,)``; impulses: ``(K, 3)`` in the floor frame
            (normal, x, y), mN s.
    """

    start: np.ndarray
    nodes: np.ndarray
    impulses: np.ndarray


class Outputs(NamedTuple):
    """What :func:`constrain_robots` writes.

    Attributes:
        dv: ``(N, 3)`` each disk's velocity correction (its rows only), mm/s.
        dq: ``(L, m)`` the legs' modal velocity corrections.
        nodes, impulses: ``(N,)``, ``(N, 3)``: robot ``r``'s contacts (robot-local, sorted;
            mN s in the floor frame) at ``starts[r]:starts[r] + count[r]``; count: ``(M,)``.
        stats: ``(M, 5)`` loaded contacts, sticking ones, Gauss-Seidel sweeps, relative
            change, total normal force (mN).
    """

    dv: np.ndarray
    dq: np.ndarray
    nodes: np.ndarray
    impulses: np.ndarray
    count: np.ndarray
    stats: np.ndarray


class ConstraintBatch:
    """The static arrays of :func:`constrain_robots` for some reduced solvers whose legs are
    bodies ``leg_start[r]:leg_start[r + 1]`` of one modal ``group`` and whose states are rows
    ``starts[r]:starts[r + 1]`` of stacked arrays; :meth:`of` makes one if they all qualify.

    Attributes:
        solvers: the robots' :class:`~softcrawl.reduction.solver.ReducedSolver`.
        disks: each robot's disk body index.
        starts: ``(M + 1,)`` each robot's first stacked row.
        contact_settings, disk_arrays, attachments, legs: the static records of
            :func:`constrain_robots`.
    """

    def __init__(self, solvers, disks, columns: DiskColumns, group, leg_start: np.ndarray, starts: np.ndarray):
        self.solvers, self.disks, self.group, self.columns = list(solvers), list(disks), group, columns
        self.starts = np.asarray(starts, np.int64)
        M = len(self.solvers)
        fixed = [columns.block_columns(s.compliance[d].fixed.H) for s, d in zip(self.solvers, self.disks)]
        F = max(len(f) for f in fixed)
        fixed_index = np.zeros((M, F), np.int64)
        fixed_blocks = np.zeros((M, F), np.int64)
        for r, (f, s, d) in enumerate(zip(fixed, self.solvers, self.disks)):
            fixed_index[r, :len(f)] = f
            fixed_blocks[r, :len(f)] = s.compliance[d].fixed.blocks
        Tff = np.zeros((M, 3 * F, 3 * F))
        for r, f in enumerate(fixed):
            Tff[r, :3 * len(f), :3 * len(f)] = columns.attachment_gram(f)
        disk_start = np.array([st + s.model.node_offsets[d] for st, s, d in zip(self.starts, self.solvers, self.disks)],
                              np.int64)
        # the attachment columns as they are now (they hold every block of these robots)
        H = columns.H
        self.disk_arrays = Disks(disk_start, columns.collision, columns.node_index, columns.node_Gt, columns.node_done,
                                 columns.fixed_Gt, H.indptr.astype(np.int64), H.indices.astype(np.int64), H.data,
                                 columns.ldl, fixed_index, fixed_blocks, np.array([len(f) for f in fixed], np.int64),
                                 Tff)
        rows = [sp.csr_matrix(s.attachment_drift) for s in self.solvers]
        self.attachments = Attachments(
            np.concatenate([[0], np.cumsum([r.shape[0] for r in rows])]).astype(np.int64),
            np.array([r.shape[0] // 3 for r in rows], np.int64),
            np.concatenate([[0]] + [r.indptr[1:] + off for r, off in zip(
                rows, np.cumsum([0] + [r.nnz for r in rows[:-1]]))]).astype(np.int64),
            np.concatenate([r.indices + 3 * st for r, st in zip(rows, self.starts)]).astype(np.int64),
            np.concatenate([r.data for r in rows]).astype(np.float64))
        self.legs = Legs(np.asarray(leg_start, np.int64), group.offsets, group.collision, group.collision_bound,
                         np.ascontiguousarray(group.rotations[:, 2, :]), group.basis, group.fixed_rows,
                         group.fixed_blocks, group.frame_rot)
        st, fl = self.solvers[0].settings, self.solvers[0].model.floor
        self.contact_settings = ContactSettings(float(st.dt), float(fl.height), float(fl.contact_distance),
                                                float(fl.friction), float(st.contact_tolerance),
                                                int(st.contact_max_iterations), EXTRA_SWEEP_CHUNKS, MIN_CONTACT_GROWTH)

    @classmethod
    def of(cls, solvers, group, leg_start, starts) -> ConstraintBatch | None:
        """A :class:`ConstraintBatch` of ``solvers`` if each has the compiled kind (a floating-frame
        disk with attachments and one modal group, a floor) and they share one disk factorization,
        collision nodes, floor and settings; else None (their own Python constraint code applies)."""
        disks = [_disk_of(s) for s in solvers]
        if any(d is None for d in disks):
            return None
        first, d0 = solvers[0], disks[0]
        factor = first.compliance[d0].factor
        coll = first.model.bodies[d0].collision_nodes
        for s, d in zip(solvers, disks):
            if (s.compliance[d].factor is not factor or s.model.floor != first.model.floor
                    or s.settings != first.settings or not np.array_equal(s.model.bodies[d].collision_nodes, coll)):
                return None
        return cls(solvers, disks, disk_columns(factor, np.asarray(coll, np.int64)), group, leg_start, starts)

    def run(self, x: np.ndarray, v_free: np.ndarray, qd_free: np.ndarray, chol: np.ndarray, states,
            skip: np.ndarray) -> tuple[np.ndarray, np.ndarray, list]:
        """Constrain the robots (:func:`constrain_robots`; the disks' rotations are their
        compliances' of this step, ``qd_free``, ``chol`` the group's free step) and set each
        solver's contact ``stats``.

        Returns:
            ``(dv, dq, contacts)``: ``(N, 3)`` the disks' velocity corrections (their rows),
            ``(L, m)`` the legs' modal ones, and per robot ``(nodes (k,), impulses (k, 3))``
            (None for a skipped robot).
        """
        M = len(self.solvers)
        R = np.stack([s.compliance[d].rotation for s, d in zip(self.solvers, self.disks)])
        previous = Contacts(
            np.concatenate([[0], np.cumsum([len(s.contact_nodes) for s in states])]).astype(np.int64),
            np.concatenate([s.contact_nodes for s in states]).astype(np.int64),
            np.ascontiguousarray(np.concatenate([s.contact_impulses for s in states]), dtype=np.float64))
        out = Outputs(np.zeros_like(v_free), np.zeros_like(qd_free), np.zeros(len(x), np.int64), np.zeros((len(x), 3)),
                      np.zeros(M, np.int64), np.zeros((M, 5)))
        constrain_robots(x, self.starts, skip, self.contact_settings, self.disk_arrays, self.attachments, self.legs,
                         FreeMotion(v_free, R, qd_free, chol), previous, out)
        contacts: list = []
        for r, s in enumerate(self.solvers):
            if skip[r]:
                contacts.append(None)
                continue
            a, b = self.starts[r], self.starts[r] + out.count[r]
            contacts.append((out.nodes[a:b].copy(), out.impulses[a:b].copy()))
            n, stick, sweeps, rel, force = out.stats[r]
            s.stats.n_contacts, s.stats.n_sticking, s.stats.contact_sweeps = int(n), int(stick), int(sweeps)
            s.stats.contact_change, s.stats.normal_force = float(rel), float(force)
        return out.dv, out.dq, contacts


@njit(cache=True)
def _cholesky_solve_many(L, B):
    """``A^-1 B`` from the lower Cholesky factor ``L`` of ``A`` (``B``: ``(n, k)``), by
    :func:`~softcrawl.reduction.kernels.forward_substitute` and
    :func:`~softcrawl.reduction.kernels.back_substitute_transposed` (column-by-column
    substitution's bits; 3.5x faster than it for the Schur complements of :func:`condense`,
    ``n`` ~ 66 attachment rows, ``k`` ~ 47 contact rows and one more column)."""
    Y = B.copy()
    forward_substitute(L, Y)
    back_substitute_transposed(L, Y)
    return Y


@njit(cache=True)
def _disk_dv(kinds, which, node_Gt, fixed_Gt, g, node, R):
    """``(3,)`` world velocity change of one disk node, ``R (G g)[node]`` (``g``: the impulses in
    the columns of the disk blocks ``(kinds, which)``), summed in the order of the whole disk's
    correction (so both agree to the bit)."""
    acc = np.zeros(3)
    for c in range(kinds.shape[0]):
        for e in range(3):
            gc = g[3 * c + e]
            if gc != 0.0:
                col = _column(kinds[c], which[c], node_Gt, fixed_Gt, e)
                for b in range(3):
                    acc[b] += col[3 * node + b] * gc
    out = np.empty(3)
    for a in range(3):
        out[a] = R[a, 0] * acc[0] + R[a, 1] * acc[1] + R[a, 2] * acc[2]
    return out


@njit(cache=True)
def condense(W, q, nb):
    """The contact problem left when the bilateral rows ``0 .. nb - 1`` of ``u = W lam + q``
    are eliminated (their ``u = 0``; Schur complement by the Cholesky factor of their block,
    least squares if it is singular): ``(X, Wc, qc)`` with ``X = W_bb^-1 [q_b, W_bc]``
    ``(nb, nc + 1)``, the condensed ``Wc`` ``(nc, nc)`` and ``qc`` ``(nc,)``; the bilateral
    impulses are then ``-(X[:, 0] + X[:, 1:] lam_c)``."""
    nc = W.shape[0] - nb
    if not nb:
        return np.zeros((0, nc + 1)), W[nb:, nb:].copy(), q[nb:].copy()
    rhs = np.empty((nb, nc + 1))
    rhs[:, 0] = q[:nb]
    rhs[:, 1:] = W[:nb, nb:]
    try:
        X = _cholesky_solve_many(np.linalg.cholesky(W[:nb, :nb]), rhs)
    except Exception:  # redundant attachments: least-squares impulses
        X = np.linalg.pinv(np.ascontiguousarray(W[:nb, :nb])) @ rhs
    Wcb = np.ascontiguousarray(W[nb:, :nb])
    return X, W[nb:, nb:] - Wcb @ np.ascontiguousarray(X[:, 1:]), q[nb:] - Wcb @ np.ascontiguousarray(X[:, 0])


@njit(cache=True)
def solve_condensed(W, q, nb, mu, warm, tol, max_iter, extra_chunks):
    """Compiled :func:`softcrawl.fem.contact.solve_constraints`: bilateral rows ``0 .. nb - 1``
    eliminated (Cholesky of their block; least squares if it is singular), the contacts solved
    by the active-set polish from ``warm`` ``(3k,)`` or else Gauss-Seidel and the polish (up to
    ``extra_chunks`` more chunks of ``max_iter`` sweeps). Returns ``(lam (3B,), sweeps,
    relative_change, polished)``."""
    n = W.shape[0]
    nc = n - nb
    X, Wc, qc = condense(W, q, nb)
    lam_c = warm.copy()
    sweeps, rel, polished = 0, 0.0, False
    if nc:
        ok = False
        if np.any(lam_c != 0.0):
            ok, new = polish_kernel(Wc, qc, mu, lam_c, POLISH_ROUNDS, POLISH_RTOL)
        if not ok:
            sweeps, rel = pgs_coulomb(Wc, qc, mu, lam_c, tol, max_iter)
            for chunk in range(extra_chunks + 1):
                if rel <= tol:
                    break
                ok, new = polish_kernel(Wc, qc, mu, lam_c, POLISH_ROUNDS, POLISH_RTOL)
                if ok or chunk == extra_chunks:
                    break
                more, rel = pgs_coulomb(Wc, qc, mu, lam_c, tol, max_iter)
                sweeps += more
        if ok:
            lam_c, polished = new, True
    lam = np.empty(n)
    lam[nb:] = lam_c
    if nb:
        lam[:nb] = -(X[:, 0] + np.ascontiguousarray(X[:, 1:]) @ lam_c)
    return lam, sweeps, rel, polished


@njit(cache=True)
def constrain_robots(x, starts, skip, settings, disks, attachments, legs, free, previous, out):
    """Constrain every robot of a batch (module doc); robot ``r`` with ``skip[r]`` is left out.

    Args:
        x: ``(N, 3)`` stacked positions, mm.
        starts: ``(M + 1,)`` first stacked row of each robot; skip: ``(M,)`` bool.
        settings: :class:`ContactSettings` (``dt`` s, ``floor_height`` and ``distance`` mm,
            ``friction``, the Gauss-Seidel ``tol``, ``max_iter``, ``extra_chunks`` and
            ``min_growth``).
        disks: :class:`Disks`: ``start`` ``(M,)`` each disk's first stacked row,
            ``collision`` ``(c,)`` its collision nodes (disk-local, sorted), ``node_index``
            ``(n,)``, the shared :class:`DiskColumns` (``node_Gt`` ``(3c, 3n)`` 1/kg and
            ``node_done`` ``(c,)``, updated here when a node's columns are first needed,
            ``fixed_Gt`` ``(3B, 3n)``, ``H_indptr``, ``H_indices``, ``H_data`` in CSR, ``ldl``
            the factors of ``A_0``) and each robot's attachment blocks (``fixed_index``, ``fixed_blocks`` ``(M, F)``,
            ``n_fixed`` ``(M,)``, ``Tff`` ``(M, 3F, 3F)``).
        attachments: :class:`Attachments`: ``start`` ``(M + 1,)`` each robot's first row,
            ``count`` ``(M,)``, CSR rows ``indptr``, ``indices``, ``data`` of the violations
            ``x_a - x_b`` (mm) over the stacked DOFs.
        legs: :class:`Legs`: ``start`` ``(M + 1,)`` each robot's first body of the stacked
            modal group (``L`` bodies, ``m`` modes), ``offsets`` ``(L,)``, ``collision``,
            ``bound`` ``(c_l,)``, ``z_axes`` ``(L, 3)``, ``basis`` ``(3n_l, m)``,
            ``fixed_rows`` ``(L, 3F, m)``, ``fixed_blocks`` ``(L, F)``, ``frame_rot``
            ``(L, 3, 3)``.
        free: :class:`FreeMotion` of this step: ``v`` ``(N, 3)`` mm/s (the disks' rows are
            read), the disks' ``rotations`` ``(M, 3, 3)``, the legs' ``qd`` ``(L, m)`` and
            ``chol`` ``(L, m, m)``.
        previous: :class:`Contacts` of last step (warm start): ``start`` ``(M + 1,)``, robot-local
            sorted ``nodes`` ``(K,)``, ``impulses`` ``(K, 3)`` mN s.
        out: :class:`Outputs`, written: ``dv`` ``(N, 3)`` the disks' velocity corrections (their
            rows only, mm/s), ``dq`` ``(L, m)`` the legs' modal ones, robot ``r``'s contacts at
            ``nodes[starts[r]:starts[r] + count[r]]`` ``(N,)`` and ``impulses`` ``(N, 3)``
            (robot-local, sorted; mN s), ``stats`` ``(M, 5)`` loaded contacts, sticking ones,
            Gauss-Seidel sweeps, relative change, total normal force (mN).
    """
    h, v_free, basis, node_Gt, fixed_Gt = settings.dt, free.v, legs.basis, disks.node_Gt, disks.fixed_Gt
    M = starts.shape[0] - 1
    nd = disks.collision.shape[0]
    n_disk = node_Gt.shape[1] // 3
    nc_leg = legs.collision.shape[0]
    m = basis.shape[1]
    for r in range(M):
        if skip[r]:
            continue
        s0, d0, R = starts[r], disks.start[r], free.rotations[r]
        b0, b1 = legs.start[r], legs.start[r + 1]
        L = b1 - b0
        chol, fixed_rows, fixed_blocks, frame_rot = (free.chol[b0:b1], legs.fixed_rows[b0:b1],
                                                     legs.fixed_blocks[b0:b1], legs.frame_rot[b0:b1])
        # 1. candidates (robot-local node, gap, free z velocity, leg in robot or -1, part node)
        cap = nd + L * nc_leg
        c_node = np.empty(cap, np.int64)
        c_gap = np.empty(cap)
        c_vz = np.empty(cap)
        c_leg = np.empty(cap, np.int64)
        c_local = np.empty(cap, np.int64)
        k = 0
        for j in range(nd):
            g_node = d0 + disks.collision[j]
            gap = x[g_node, 2] - settings.floor_height
            if min(gap, gap + h * v_free[g_node, 2]) < settings.distance:
                c_node[k], c_gap[k], c_vz[k] = g_node - s0, gap, v_free[g_node, 2]
                c_leg[k], c_local[k] = -1, disks.collision[j]
                k += 1
        for b in range(L):
            bb = b0 + b
            k1 = body_floor_candidates(x, legs.offsets[bb], legs.collision, legs.bound, free.qd[bb],
                                       legs.z_axes[bb], basis, h, settings.floor_height, settings.distance, c_node,
                                       c_gap, c_vz, c_local, k)
            for q in range(k, k1):  # robot-local node, leg in robot, part node
                c_node[q] -= s0
                c_leg[q] = b
                c_local[q] = legs.collision[c_local[q]]
            k = k1
        order = np.argsort(c_node[:k], kind="mergesort")
        near, gaps, vzf = c_node[:k][order], c_gap[:k][order], c_vz[:k][order]
        near_leg, near_local = c_leg[:k][order], c_local[:k][order]
        # 2. start of the contact set: last step's loaded contacts, else the deepest penetrating
        p0, p1 = previous.start[r], previous.start[r + 1]
        active = np.zeros(k, np.bool_)
        any_active = False
        for i in range(k):
            for p in range(p0, p1):  # (few contacts: a scan)
                if previous.nodes[p] == near[i]:
                    if previous.impulses[p, 0] > 0.0:
                        active[i] = True
                        any_active = True
                    break
        if not any_active:
            pred = gaps + h * vzf
            cand = np.flatnonzero(pred < 0.0)
            deepest = cand[np.argsort(pred[cand], kind="mergesort")[:settings.min_growth]]
            active[deepest] = True
        # attachment violations x_a - x_b
        A = attachments.count[r]
        nb = 3 * A
        drift = np.zeros(nb)
        a0 = attachments.start[r]
        for i in range(nb):
            acc = 0.0
            for p in range(attachments.indptr[a0 + i], attachments.indptr[a0 + i + 1]):
                col = attachments.indices[p]
                acc += attachments.data[p] * x[col // 3, col % 3]
            drift[i] = acc
        F = disks.n_fixed[r]
        vb = np.empty(3 * n_disk)  # the disk's free velocities in its frame, v R (flat)
        for i in range(n_disk):
            for a in range(3):
                vb[3 * i + a] = v_free[d0 + i, 0] * R[0, a] + v_free[d0 + i, 1] * R[1, a] + v_free[d0 + i, 2] * R[2, a]
        frame_R = FLOOR_FRAME @ R
        gmax = 0.0
        for i in range(k):
            gmax = max(gmax, abs(gaps[i]))
        while True:
            idx = np.flatnonzero(active)
            kk = idx.shape[0]
            B = A + kk
            W = np.zeros((3 * B, 3 * B))
            u = np.zeros(3 * B)
            # 3a. the disk's blocks: its attachments, then its contacts (its DiskColumns,
            # coefficients times its rotation, E^T v in its frame)
            on_disk = 0
            for i in range(kk):
                if near_leg[idx[i]] < 0:
                    on_disk += 1
            ncol = F + on_disk
            kinds = np.zeros(ncol, np.int64)
            which = np.empty(ncol, np.int64)
            dnode = np.full(ncol, -1, np.int64)
            P = np.empty((ncol, 3, 3))
            blocks = np.empty(ncol, np.int64)
            for a in range(F):
                which[a], blocks[a] = disks.fixed_index[r, a], disks.fixed_blocks[r, a]
                P[a] = R
            c = F
            for i in range(kk):
                if near_leg[idx[i]] < 0:
                    node = near_local[idx[i]]
                    kinds[c], which[c], dnode[c], blocks[c] = 1, disks.node_index[node], node, A + i
                    _node_columns(which[c], node, disks.ldl, node_Gt, disks.node_done)
                    P[c] = frame_R
                    c += 1
            columns = 3 * np.arange(ncol)
            Tg = _disk_gram(kinds, which, dnode, F, disks.Tff[r], node_Gt, fixed_Gt)
            Etv = np.empty(3 * ncol)
            for c in range(ncol):
                for e in range(3):
                    if kinds[c] == 1:
                        Etv[3 * c + e] = vb[3 * dnode[c] + e]
                    else:
                        acc = 0.0
                        row = 3 * which[c] + e
                        for p in range(disks.H_indptr[row], disks.H_indptr[row + 1]):
                            acc += disks.H_data[p] * vb[disks.H_indices[p]]
                        Etv[3 * c + e] = acc
            add_block_delassus(W, u, Tg, Etv, columns, P, blocks)
            # 3b. the legs' blocks
            cb = np.empty(kk, np.int64)
            cn = np.empty(kk, np.int64)
            ck = np.empty(kk, np.int64)
            for i in range(kk):
                cb[i], cn[i], ck[i] = near_leg[idx[i]], near_local[idx[i]], A + i
            if L:
                add_delassus(W, u, chol, free.qd[b0:b1], fixed_rows, fixed_blocks, frame_rot, basis, cb, cn, ck)
            for i in range(nb):
                u[i] += drift[i] / h
            for i in range(kk):
                u[nb + 3 * i] += gaps[idx[i]] / h
            warm = np.zeros(3 * kk)
            for i in range(kk):
                for p in range(p0, p1):
                    if previous.nodes[p] == near[idx[i]]:
                        for a in range(3):
                            warm[3 * i + a] = previous.impulses[p, a]
                        break
            mus = np.full(kk, settings.friction)
            lam, sweeps, rel, _ = solve_condensed(W, u, nb, mus, warm, settings.tol, settings.max_iter,
                                                  settings.extra_chunks)
            # 5. corrections: the disk's (body frame, then world) and the legs' modal ones
            g = block_impulses(lam, columns, P, blocks, 3 * ncol)
            dql = (corrections(lam, chol, fixed_rows, fixed_blocks, frame_rot, basis, cb, cn, ck) if L
                   else np.zeros((0, m)))
            # candidates the solve leaves below the floor join the set
            missed = np.zeros(k, np.bool_)
            n_missed = 0
            leg_idx = np.flatnonzero(near_leg >= 0)
            dvz = np.zeros(k)
            for i in range(k):
                if near_leg[i] < 0:  # the disk node's z velocity change only (its columns' rows)
                    dvz[i] = _disk_dv(kinds, which, node_Gt, fixed_Gt, g, near_local[i], R)[2]
            if leg_idx.shape[0] and L:
                dvz[leg_idx] = point_velocity(dql, legs.z_axes[b0:b1], basis, near_leg[leg_idx], near_local[leg_idx])
            lim = -1e-9 * max(1.0, gmax)
            for i in range(k):
                if not active[i] and gaps[i] + h * (vzf[i] + dvz[i]) < lim:
                    missed[i] = True
                    n_missed += 1
            if n_missed == 0:
                break
            grow = max(settings.min_growth, kk)
            miss = np.flatnonzero(missed)
            if n_missed > grow:
                new_gap = gaps[miss] + h * (vzf[miss] + dvz[miss])
                miss = miss[np.argsort(new_gap, kind="mergesort")[:grow]]
            active[miss] = True
        # outputs: the disk's velocity corrections (world), the legs' modal ones, the contacts
        dvb = np.zeros(3 * n_disk)
        for c in range(kinds.shape[0]):
            for e in range(3):
                gc = g[3 * c + e]
                if gc != 0.0:
                    col = _column(kinds[c], which[c], node_Gt, fixed_Gt, e)
                    for j in range(3 * n_disk):
                        dvb[j] += col[j] * gc
        for i in range(n_disk):
            for a in range(3):
                out.dv[d0 + i, a] = R[a, 0] * dvb[3 * i] + R[a, 1] * dvb[3 * i + 1] + R[a, 2] * dvb[3 * i + 2]
        for b in range(L):
            out.dq[b0 + b] = dql[b]
        ul = W @ lam + u
        umax = np.abs(ul).max() if ul.shape[0] else 0.0
        n_loaded, n_stick, force = 0, 0, 0.0
        for i in range(kk):
            out.nodes[s0 + i] = near[idx[i]]
            for a in range(3):
                out.impulses[s0 + i, a] = lam[nb + 3 * i + a]
            ln = lam[nb + 3 * i]
            force += ln
            if ln > 0.0:
                n_loaded += 1
                if np.hypot(ul[nb + 3 * i + 1], ul[nb + 3 * i + 2]) <= 1e-9 * (1.0 + umax):
                    n_stick += 1
        out.count[r] = kk
        stats = out.stats[r]
        stats[0], stats[1], stats[2], stats[3], stats[4] = n_loaded, n_stick, sweeps, rel, force / h
