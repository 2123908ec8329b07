"""The reduced solver: the full-order integrator with some bodies reduced (Galerkin + ECSW).

For a reduced body (``x = X + Phi q``, ``v = Phi qdot``) the linearly implicit Euler step of
:class:`softcrawl.fem.solver.ImplicitEulerSolver` is projected on the basis
(reduction.md, "Reduced kinematics"):

    [(1 + h r_M) M_r + h (h + r_K) K_r] dqdot = h (f_r - (h + r_K) K_r qdot - r_M M_r qdot)

with ``M_r = Phi^T M Phi`` (constant), ``K_r`` and the internal part of ``f_r`` from the RID
elements only (:mod:`softcrawl.reduction.kernels`), gravity projected once, and the cavity
pressure follower load projected exactly. Contacts and attachments keep their full-order
rows ``H``; a reduced body's compliance is ``Phi A_r^-1 Phi^T`` (so the Delassus operator is
``(H Phi) A_r^-1 (H Phi)^T``). Full-order bodies (the disk) are stepped as before. States
keep all node positions and velocities, so everything downstream (rewards, outputs,
ParaView frames) is unchanged; a reduced body's nodes stay on ``X + range(Phi)``.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg.blas import dsyrk, dtrsm
from scipy.linalg.lapack import dpotrf, dpotrs

from softcrawl.fem.body import Body
from softcrawl.fem.constraints import Entries, block_sum_matrix
from softcrawl.fem.model import Model
from softcrawl.fem.solver import ImplicitEulerSolver, SimulationDiverged, SolverSettings
from softcrawl.fem.state import Control, State
from softcrawl.reduction.kernels import reduced_area_normal_load, reduced_element_terms
from softcrawl.reduction.model import ReducedBody


class ReducedCompliance:
    """Constraint compliance of a reduced body (the role of
    :class:`softcrawl.fem.constraints.NodalCompliance` for full bodies): rows in modal
    coordinates ``J = H Phi`` and ``W_b = J A_r^-1 J^T = Y^T Y`` with ``Y = L^-1 J^T``.

    Args:
        cholesky: lower Cholesky factor ``L`` of ``A_r`` ``(m, m)``.
        basis: ``(3n, m)`` the body's basis.
        velocity: ``(m,)`` the body's free modal velocity (``v_free = Phi qdot``).
    """

    def __init__(self, cholesky: np.ndarray, basis: np.ndarray, velocity: np.ndarray):
        self.L, self.basis, self.velocity = cholesky, basis, velocity
        self.last_correction = np.zeros_like(velocity)  # modal velocity change of the last correction

    def jacobian(self, entries: Entries, blocks: np.ndarray, n_blocks: int) -> np.ndarray:
        """``(3B, m)`` ``H Phi`` of the entries (local block numbers ``blocks``)."""
        m = self.basis.shape[1]
        rows = entries.coefs @ self.basis.reshape(-1, 3, m)[entries.nodes]
        return (block_sum_matrix(blocks, n_blocks) @ rows.reshape(len(blocks), 3 * m)).reshape(3 * n_blocks, m)

    def delassus(self, J: np.ndarray) -> np.ndarray:
        Y = dtrsm(1.0, self.L, J.T, lower=1)
        return Y.T @ Y

    def constraint_velocity(self, J: np.ndarray, v: np.ndarray) -> np.ndarray:
        return J @ self.velocity

    def correction(self, J: np.ndarray, lam: np.ndarray) -> np.ndarray:
        """``(n, 3)`` ``Phi A_r^-1 J^T lam``."""
        self.last_correction = dpotrs(self.L, J.T @ lam, lower=1)[0]
        return (self.basis @ self.last_correction).reshape(-1, 3)


class ReducedSolver(ImplicitEulerSolver):
    """``step(state, control) -> state`` for a model whose bodies may be reduced.

    Args:
        model: the full-order model (meshes, masses, constraints, floor).
        reduced: body index -> its :class:`ReducedBody` (the others stay full-order).
        settings: as for the full solver; reduced bodies take one linear solve per step
            (``newton_iterations`` must be 1) and are always solved exactly.

    A state this solver produced carries its reduced bodies' modal velocities (kept here,
    not projected again); do not modify such a state's ``v`` in place.

    Raises:
        ValueError: a reduced body that is not the model's body at that index, or
            ``newton_iterations != 1`` with reduced bodies.
    """

    def __init__(self, model: Model, reduced: dict[int, ReducedBody], settings: SolverSettings = SolverSettings()):
        super().__init__(model, settings)
        for i, rb in reduced.items():
            if not 0 <= i < len(model.bodies) or model.bodies[i] is not rb.body:
                raise ValueError(f"reduced body {i} is not body {i} of the model")
        if reduced and settings.newton_iterations != 1:
            raise ValueError("reduced bodies support the linearly implicit step only (newton_iterations=1)")
        self.reduced = dict(reduced)
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

    def step(self, state: State, control: Control) -> State:
        # A state this solver produced carries the reduced bodies' exact modal velocities
        # (kept below); any other state is projected (``qdot = Phi^T v``, Phi orthonormal).
        self._modal_valid = state.v is self._last_v
        new = super().step(state, control)
        for i in self.reduced:
            c = self._compliance[i]
            self._modal_velocity[i] = c.velocity + c.last_correction
        self._last_v = new.v
        return new

    def _free_velocity(self, i: int, body: Body, x: np.ndarray, v: np.ndarray,
                       control: Control, t: float) -> np.ndarray:
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
        self._compliance[i] = ReducedCompliance(L, Phi, qd)
        return (Phi @ qd).reshape(-1, 3)
