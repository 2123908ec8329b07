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
import scipy.linalg as sla

from softcrawl.fem.body import Body
from softcrawl.fem.model import Model
from softcrawl.fem.pressure import area_normals
from softcrawl.fem.solver import ImplicitEulerSolver, SimulationDiverged, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.reduction.kernels import reduced_element_terms
from softcrawl.reduction.model import ReducedBody


class ReducedCompliance:
    """Contact compliance ``Phi A_r^-1 Phi^T`` of a reduced body for a growing node set
    (the role :class:`softcrawl.fem.constraints.NodalCompliance` plays for full bodies).

    Args:
        factor: Cholesky factor of ``A_r`` (``scipy.linalg.cho_factor``).
        basis: ``(3n, m)`` the body's basis.
    """

    def __init__(self, factor, basis: np.ndarray):
        self.factor, self.basis = factor, basis
        self.index: dict[int, int] = {}
        m = basis.shape[1]
        self._B = np.zeros((m, 0))  # Phi_E^T
        self._G = np.zeros((m, 0))  # A_r^-1 Phi_E^T

    def ensure(self, nodes: np.ndarray) -> None:
        new = [int(a) for a in dict.fromkeys(np.asarray(nodes).tolist()) if a not in self.index]
        if not new:
            return
        dofs = (3 * np.asarray(new)[:, None] + np.arange(3)).ravel()
        B = self.basis[dofs].T
        for a in new:
            self.index[a] = len(self.index)
        self._B = np.hstack([self._B, B])
        self._G = np.hstack([self._G, sla.cho_solve(self.factor, B)])

    def nodes(self) -> np.ndarray:
        return np.fromiter(self.index, np.int64, len(self.index))

    @property
    def n_columns(self) -> int:
        return self._B.shape[1]

    def nodal(self) -> np.ndarray:
        """``(3K, 3K)`` ``Phi_E A_r^-1 Phi_E^T``."""
        return self._B.T @ self._G

    def correction(self, y: np.ndarray) -> np.ndarray:
        """``(n, 3)`` velocity change ``Phi A_r^-1 Phi_E^T y``."""
        return (self.basis @ (self._G @ y)).reshape(-1, 3)


class ReducedSolver(ImplicitEulerSolver):
    """``step(state, control) -> state`` for a model whose bodies may be reduced.

    Args:
        model: the full-order model (meshes, masses, constraints, floor).
        reduced: body index -> its :class:`ReducedBody` (the others stay full-order).
        settings: as for the full solver; reduced bodies take one linear solve per step
            (``newton_iterations`` must be 1) and are always solved exactly.

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
        g = np.asarray(model.gravity, float)
        self._gravity_r, self._buffers, self._cavity_basis = {}, {}, {}
        for i, rb in self.reduced.items():
            b = rb.body
            self._gravity_r[i] = rb.basis.T @ (b.nodal_mass[:, None] * g[None, :]).ravel()
            rows = sum(len(ef.conn) * ef.factors.shape[1] for ef in rb.element_factors)
            self._buffers[i] = (np.empty((rows, rb.n_modes)), np.empty(rows))
            phi = rb.basis.reshape(b.n_nodes, 3, rb.n_modes)
            self._cavity_basis[i] = [(cav, phi[cav.triangles].sum(axis=1)) for cav in b.cavities]

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
        f = self._gravity_r[i] - Z.T @ s
        for cav, phi_sum in self._cavity_basis[i]:
            p = float(control.pressures[cav.channel])
            if p != 0.0:
                f += (p / 3.0) * np.einsum("tim,ti->m", phi_sum, area_normals(x, cav.triangles))
        if control.forces is not None:
            f += Phi.T @ control.forces[m.body_slice(i)].ravel()
        qd = Phi.T @ v.ravel()
        K = Z.T @ Z
        Mr = rb.reduced_mass
        A = (1 + h * rM) * Mr + h * (h + rK) * K
        rhs = h * (f - (h + rK) * (K @ qd) - rM * (Mr @ qd))
        try:
            factor = sla.cho_factor(A)
        except np.linalg.LinAlgError as exc:
            raise SimulationDiverged(f"reduced matrix of body {body.name!r} is not positive definite", t) from exc
        self._compliance[i] = ReducedCompliance(factor, Phi)
        return (Phi @ (qd + sla.cho_solve(factor, rhs))).reshape(-1, 3)
