"""The reduced solver: the full-order integrator with some bodies reduced (Galerkin + ECSW).

For a reduced body (``x = X + Phi q``, ``v = Phi qdot``) the linearly implicit Euler step of
:class:`softcrawl.fem.solver.ImplicitEulerSolver` is projected on the basis
(reduction.md, "Reduced kinematics"):

    [(1 + h r_M) M_r + h (h + r_K) K_r] dqdot = h (f_r - (h + r_K) K_r qdot - r_M M_r qdot)

with ``M_r = Phi^T M Phi`` (constant), ``K_r`` and the internal part of ``f_r`` from the RID
elements only (:mod:`softcrawl.reduction.kernels`), gravity projected once, and the cavity
pressure follower load projected exactly. Contacts and attachments keep their full-order
rows ``H``; a reduced body's compliance is ``Phi A_r^-1 Phi^T`` (so the Delassus operator is
``(H Phi) A_r^-1 (H Phi)^T``). A floating-frame body (the disk by default,
:mod:`softcrawl.reduction.floating`) is stepped in its frame with its constant factorization;
full-order bodies are stepped as before. States
keep all node positions and velocities, so everything downstream (rewards, outputs,
ParaView frames) is unchanged; a reduced body's nodes stay on ``X + range(Phi)``.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.linalg.blas import dsyrk, dtrsm
from scipy.linalg.lapack import dpotrf, dpotrs

from softcrawl.fem.body import Body
from softcrawl.fem.constraints import Entries, FixedRows, block_sum_matrix
from softcrawl.fem.linalg import Factorization
from softcrawl.fem.model import Model
from softcrawl.fem.solver import ImplicitEulerSolver, SimulationDiverged, SolverSettings
from softcrawl.fem.state import Control, State
from softcrawl.reduction.floating import FloatingFrameBody, FloatingFrameCompliance
from softcrawl.reduction.kernels import reduced_area_normal_load, reduced_element_terms
from softcrawl.reduction.model import ReducedBody


class ReducedCompliance:
    """Constraint compliance of a reduced body (the role of
    :class:`softcrawl.fem.constraints.NodalCompliance` for full bodies): rows in modal
    coordinates ``J = H Phi`` and ``W_b = J A_r^-1 J^T = Y^T Y`` with ``Y = L^-1 J^T``;
    corrections are modal velocity changes.

    Args:
        cholesky: lower Cholesky factor ``L`` of ``A_r`` ``(m, m)``.
        basis: ``(3n, m)`` the body's basis.
        velocity: ``(m,)`` the body's free modal velocity (``v_free = Phi qdot``).
        fixed: the body's permanent constraint rows and their constant modal rows
            ``(H_f, H_f Phi)`` (``(3F, m)``), or None. Every entry in one of its blocks must
            be one of the entries it was built from.
    """

    def __init__(self, cholesky: np.ndarray, basis: np.ndarray, velocity: np.ndarray,
                 fixed: tuple[FixedRows, np.ndarray] | None = None):
        self.L, self.basis, self.velocity, self.fixed = cholesky, basis, velocity, fixed

    def jacobian(self, entries: Entries, blocks: np.ndarray, n_blocks: int) -> np.ndarray:
        """``(3B, m)`` ``H Phi`` of the entries (local block numbers ``blocks``)."""
        m = self.basis.shape[1]
        J = np.zeros((n_blocks, 3, m))
        nodal = np.ones(len(blocks), bool)
        if self.fixed is not None:
            rows, HPhi = self.fixed
            pos = rows.locate(entries.blocks)
            nodal = pos < 0
            if not nodal.all():
                J[blocks[~nodal]] = HPhi.reshape(-1, 3, m)[pos[~nodal]]  # repeats write equal rows
        if nodal.any():
            local = blocks[nodal]
            rows = entries.coefs[nodal] @ self.basis.reshape(-1, 3, m)[entries.nodes[nodal]]
            if len(np.unique(local)) == len(local):
                J[local] += rows
            else:
                J += (block_sum_matrix(local, n_blocks) @ rows.reshape(len(local), 3 * m)).reshape(n_blocks, 3, m)
        return J.reshape(3 * n_blocks, m)

    def delassus(self, J: np.ndarray) -> np.ndarray:
        Y = dtrsm(1.0, self.L, J.T, lower=1)
        return Y.T @ Y

    def constraint_velocity(self, J: np.ndarray, v: np.ndarray) -> np.ndarray:
        return J @ self.velocity

    def correction(self, J: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``(m,)`` modal velocity change ``A_r^-1 J^T lam``."""
        return dpotrs(self.L, J.T @ lam, lower=1)[0]

    def velocities(self, correction: np.ndarray, nodes: np.ndarray | None = None) -> np.ndarray:
        """``(k, 3)`` ``Phi dqdot`` at local ``nodes`` (None: all ``n`` nodes)."""
        if nodes is None:
            return (self.basis @ correction).reshape(-1, 3)
        m = self.basis.shape[1]
        return self.basis.reshape(-1, 3, m)[nodes] @ correction


class ReducedSolver(ImplicitEulerSolver):
    """``step(state, control) -> state`` for a model whose bodies may be reduced.

    Args:
        model: the full-order model (meshes, masses, constraints, floor).
        reduced: body index -> its :class:`ReducedBody` (POD + ECSW) or
            :class:`FloatingFrameBody`; the others stay full-order.
        settings: as for the full solver; reduced bodies take one linear solve per step
            (``newton_iterations`` must be 1) and are always solved exactly.

    A state this solver produced carries its reduced bodies' modal velocities (kept here,
    not projected again); do not modify such a state's ``v`` in place.

    Raises:
        ValueError: a reduced body that is not the model's body at that index, or
            ``newton_iterations != 1`` with reduced bodies.
    """

    def __init__(self, model: Model, reduced: dict[int, ReducedBody | FloatingFrameBody],
                 settings: SolverSettings = SolverSettings()):
        super().__init__(model, settings)
        for i, rb in reduced.items():
            if not 0 <= i < len(model.bodies) or model.bodies[i] is not rb.body:
                raise ValueError(f"reduced body {i} is not body {i} of the model")
        if reduced and settings.newton_iterations != 1:
            raise ValueError("reduced bodies support the linearly implicit step only (newton_iterations=1)")
        h, rM, rK = settings.dt, model.rayleigh_mass, model.rayleigh_stiffness
        self.floating = {i: fb for i, fb in reduced.items() if isinstance(fb, FloatingFrameBody)}
        for i, fb in self.floating.items():
            A0 = h * (h + rK) * fb.rest_stiffness + sp.diags((1 + h * rM) * self._mass3[i])
            self._compliance[i] = FloatingFrameCompliance(Factorization(A0), fb.body.free_dofs,
                                                          self._attach_rows.get(i))
        self.reduced = {i: rb for i, rb in reduced.items() if i not in self.floating}
        self._modal_velocity = {i: np.zeros(rb.n_modes) for i, rb in self.reduced.items()}
        self._modal_valid, self._last_v = False, None
        g = np.asarray(model.gravity, float)
        self._gravity_r, self._buffers, self._cavity_basis = {}, {}, {}
        for i, rb in self.reduced.items():
            b = rb.body
            self._gravity_r[i] = rb.basis.T @ (b.nodal_mass[:, None] * g[None, :]).ravel()
            rows = sum(len(ef.conn) * ef.factors.shape[1] for ef in rb.element_factors)
            self._buffers[i] = (np.empty((rows, rb.n_modes)), np.empty(rows))
            phi = rb.basis.reshape(b.n_nodes, 3, rb.n_modes)
            self._cavity_basis[i] = [(cav, phi[cav.triangles].sum(axis=1)) for cav in b.cavities]
        self._fixed_rows = {i: (self._attach_rows[i], self._attach_rows[i].H @ rb.basis)
                            for i, rb in self.reduced.items() if i in self._attach_rows}
        # z rows of the basis at the collision nodes: all of a reduced body's free velocity
        # the contact search reads (the step's velocities are Phi qdot, from _velocity).
        self._collision_z = {i: (rb.body.collision_nodes, rb.basis[3 * rb.body.collision_nodes + 2])
                             for i, rb in self.reduced.items()}

    def step(self, state: State, control: Control) -> State:
        # A state this solver produced carries the reduced bodies' exact modal velocities
        # (kept below); any other state is projected (``qdot = Phi^T v``, Phi orthonormal).
        self._modal_valid = state.v is self._last_v
        new = super().step(state, control)
        self._last_v = new.v
        return new

    def _velocity(self, v_free: np.ndarray, corrections: dict[int, np.ndarray]) -> np.ndarray:
        """As the full solver, and a reduced body's velocities ``Phi (qdot_free + dqdot)``
        (one reconstruction per body and step; the modal velocities are kept)."""
        v = super()._velocity(v_free, {b: d for b, d in corrections.items() if b not in self.reduced})
        for i, rb in self.reduced.items():
            qd = self._compliance[i].velocity + corrections.get(i, 0.0)
            self._modal_velocity[i] = qd
            v[self.model.body_slice(i)] = (rb.basis @ qd).reshape(-1, 3)
        return v

    def _free_velocity(self, i: int, body: Body, x: np.ndarray, v: np.ndarray,
                       control: Control, t: float) -> np.ndarray:
        """Free velocities; of a reduced body only the rows the contact search reads (z at
        its collision nodes, zero elsewhere): its step velocities come from :meth:`_velocity`."""
        if i in self.floating:
            return self._floating_free_velocity(i, body, x, v, control)
        rb = self.reduced.get(i)
        if rb is None:
            return super()._free_velocity(i, body, x, v, control, t)
        h, m = self.settings.dt, self.model
        rM, rK = m.rayleigh_mass, m.rayleigh_stiffness
        Phi = rb.basis
        Z, s = self._buffers[i]
        row, n_bad = 0, 0
        for ef in rb.element_factors:
            rows = len(ef.conn) * ef.factors.shape[1]
            n_bad += reduced_element_terms(x, ef.conn, ef.rest, ef.factors, ef.frames, ef.sqrt_weights, Phi,
                                           Z[row:row + rows], s[row:row + rows])
            row += rows
        if n_bad:
            raise SimulationDiverged(f"{n_bad} inverted elements in reduced body {body.name!r}", t)
        qd = self._modal_velocity[i] if self._modal_valid else Phi.T @ v.ravel()
        # Internal force -Z^T s, with the linearisation and Rayleigh stiffness damping terms
        # -(h + r_K) K_r qdot (K_r = Z^T Z) in the same product.
        f = self._gravity_r[i] - Z.T @ (s + (h + rK) * (Z @ qd))
        for cav, phi_sum in self._cavity_basis[i]:
            p = float(control.pressures[cav.channel])
            if p != 0.0:
                f += (p / 3.0) * reduced_area_normal_load(x, cav.triangles, phi_sum)
        if control.forces is not None:
            f += Phi.T @ control.forces[m.body_slice(i)].ravel()
        Mr = rb.reduced_mass
        A = (1 + h * rM) * Mr + dsyrk(h * (h + rK), Z.T, lower=1)  # lower triangle of the tangent Z^T Z
        rhs = h * (f - rM * (Mr @ qd))
        L, info = dpotrf(A, lower=1, clean=1)
        if info:
            raise SimulationDiverged(f"reduced matrix of body {body.name!r} is not positive definite", t)
        qd = qd + dpotrs(L, rhs, lower=1)[0]
        self._compliance[i] = ReducedCompliance(L, Phi, qd, self._fixed_rows.get(i))
        v_free = np.zeros((body.n_nodes, 3))
        nodes, phi_z = self._collision_z[i]
        v_free[nodes, 2] = phi_z @ qd
        return v_free

    def _floating_free_velocity(self, i: int, body: Body, x: np.ndarray, v: np.ndarray,
                                control: Control) -> np.ndarray:
        """The implicit step of a :class:`FloatingFrameBody`, solved in its frame:
        ``dv' = A_0^-1 h (R^T f_ext - K_0 (R^T x - X + (h + r_K) R^T v) - r_M M R^T v)``."""
        h, m = self.settings.dt, self.model
        fb, c = self.floating[i], self._compliance[i]
        R = fb.rotation(x)
        c.rotation = R
        f = body.external_forces(x, control.pressures, np.asarray(m.gravity))
        if control.forces is not None:
            f = f + control.forces[m.body_slice(i)]
        vb = (v @ R).ravel()
        stretch = (x @ R - body.mesh.points).ravel() + (h + m.rayleigh_stiffness) * vb
        rhs = h * ((f @ R).ravel() - fb.rest_stiffness @ stretch - m.rayleigh_mass * self._mass3[i] * vb)
        return (vb + c.factor.solve(rhs)).reshape(-1, 3) @ R.T
