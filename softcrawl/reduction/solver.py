"""The reduced solver: the full-order integrator with some bodies reduced (Galerkin + ECSW).

For a reduced body (``x = X + Phi q``, ``v = Phi qdot``) the linearly implicit Euler step of
:class:`softcrawl.fem.solver.ImplicitEulerSolver` is projected on the basis
(reduction.md, "Reduced kinematics"):

    [(1 + h r_M) M_r + h (h + r_K) K_r] dqdot = h (f_r - (h + r_K) K_r qdot - r_M M_r qdot)

with ``M_r = Phi^T M Phi`` (constant), ``K_r`` and the internal part of ``f_r`` from the RID
elements only (:mod:`softcrawl.reduction.kernels`), gravity projected once, and the cavity
pressure follower load projected exactly. Reduced bodies placed from one part (the legs) are
stepped together as a :class:`~softcrawl.reduction.group.ModalGroup`, in the part frame,
with compiled kernels. Contacts and attachments keep their full-order rows ``H``; a reduced
body's rows are ``H Phi`` and its share of the Delassus operator ``(H Phi) A_r^-1 (H Phi)^T``.
A floating-frame body (the disk by default, :mod:`softcrawl.reduction.floating`) is stepped
in its frame with its constant factorization; full-order bodies are stepped as before. States
keep all node positions and velocities, so everything downstream (rewards, outputs, ParaView
frames) is unchanged; a reduced body's nodes stay on ``X + range(Phi)``. The states it returns
also carry the modal velocities ``qdot`` (:attr:`State.modal_velocities`), which the next step
starts from instead of projecting ``v``.

The phases of a step are public for :class:`~softcrawl.reduction.batch.BatchedReducedSolver`,
which does the modal bodies' free motion of many robots at once: :meth:`~ReducedSolver.carried_modal_velocities`,
:meth:`~ReducedSolver.nodal_free_motion` (with :meth:`~ReducedSolver.external_forces` and
:attr:`~ReducedSolver.compliance` for the floating-frame bodies) and :meth:`~ReducedSolver.constrain`.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from softcrawl.fem.body import Body
from softcrawl.fem.constraints import NodalCompliance
from softcrawl.fem.model import Model
from softcrawl.fem.solver import FLOOR_FRAME, ImplicitEulerSolver, SimulationDiverged, SolverSettings
from softcrawl.fem.state import Control, State
from softcrawl.reduction.constrain import ConstraintBatch
from softcrawl.reduction.floating import FloatingFrameBody
from softcrawl.reduction.group import ModalGroup
from softcrawl.reduction.model import ReducedBody


@dataclass
class Corrections:
    """Velocity corrections of one constraint solve: the nodal bodies' (body -> ``(n, 3)``
    mm/s, as for the full solver) and each modal group's ``(L, m)`` modal velocity changes, mm/s."""

    nodal: dict[int, np.ndarray]
    modal: list[np.ndarray]


class ReducedSolver(ImplicitEulerSolver):
    """``step(state, control) -> state`` for a model whose bodies may be reduced.

    Args:
        model: the full-order model (meshes, masses, constraints, floor).
        reduced: body index -> its :class:`ReducedBody` (POD + ECSW) or
            :class:`FloatingFrameBody`; the others stay full-order.
        settings: as for the full solver; reduced bodies take one linear solve per step
            (``newton_iterations`` must be 1) and are always solved exactly.

    A state this solver produced carries its reduced bodies' modal velocities
    (:attr:`State.modal_velocities`); do not modify such a state's ``v`` in place.

    Raises:
        ValueError: a reduced body that is not the model's body at that index, reduced bodies
            of one part that differ in materials or attachments, or ``newton_iterations != 1``
            with reduced bodies.
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
            self.compliance[i] = NodalCompliance(fb.step_factorization(h, rM, rK), fb.body.free_dofs,
                                                 self._attach_rows.get(i))
        self.reduced = {i: rb for i, rb in reduced.items() if i not in self.floating}
        by_part: dict[int, dict[int, ReducedBody]] = {}
        for i, rb in sorted(self.reduced.items()):
            by_part.setdefault(id(rb.part), {})[i] = rb
        self.groups = [ModalGroup.build(model, bodies, self._attach_rows, FLOOR_FRAME) for bodies in by_part.values()]
        self.nodal_bodies = {i for i in range(len(model.bodies)) if i not in self.reduced}
        # Global node -> (group, body in group), -1 for nodes of nodal bodies.
        self._node_group = np.full(model.n_nodes, -1, np.int64)
        self._node_member = np.full(model.n_nodes, -1, np.int64)
        for g, group in enumerate(self.groups):
            for j, b in enumerate(group.members):
                self._node_group[model.body_slice(b)] = g
                self._node_member[model.body_slice(b)] = j
        self._collision = self._collision[self._node_group[self._collision] < 0]  # groups: _contact_rows
        self._qdot: list[np.ndarray] = []  # per group: the modal velocities of this step's result
        self._free: list[tuple[np.ndarray, np.ndarray]] = []  # per group: (qdot_free, chol) of this step
        self._compiled: ConstraintBatch | None | bool = None  # made at the first constraint stage

    # -- free motion ---------------------------------------------------------------------
    def carried_modal_velocities(self, state: State) -> tuple[np.ndarray, ...] | None:
        """``state``'s modal velocities (:attr:`State.modal_velocities`) if it carries them for
        this solver's modal groups (one ``(L, m)`` array each, mm/s), else None: they are then
        projected from ``v`` (``qdot = Phi^T v``, Phi orthonormal)."""
        q = state.modal_velocities
        if q is None or len(q) != len(self.groups):
            return None
        if any(a.shape != (g.n_bodies, g.n_modes) for a, g in zip(q, self.groups)):
            return None
        return q

    def nodal_free_motion(self, x: np.ndarray, v: np.ndarray, control: Control, t: float, v_free: np.ndarray,
                          floating: bool = True) -> None:
        """Write the free (unconstrained) velocities of the nodal bodies (full-order and, if
        ``floating``, floating-frame) into their rows of ``v_free`` ``(N, 3)``, mm/s.

        Args:
            x, v: ``(N, 3)`` positions (mm) and velocities (mm/s) of the model's nodes at time ``t`` (s).
            control: the step's pressures (sim kPa) and prescribed forces (mN).

        Raises:
            SimulationDiverged: inverted elements in a full-order body.
        """
        m = self.model
        for i in sorted(self.nodal_bodies):
            if floating or i not in self.floating:
                sl = m.body_slice(i)
                v_free[sl] = self._free_velocity(i, m.bodies[i], x[sl], v[sl], control, t)

    def _free_motion(self, state: State, control: Control) -> np.ndarray:
        """Free velocities of the nodal bodies; a modal group's bodies get theirs (z only, at
        the nodes near the floor) from :meth:`_contact_rows`, and their step velocities
        from :meth:`_velocity`. The modal velocities start from those ``state`` carries
        (:meth:`carried_modal_velocities`), else from ``v`` projected."""
        m, h = self.model, self.settings.dt
        v_free = np.zeros_like(state.v)
        self.nodal_free_motion(state.x, state.v, control, state.t, v_free)
        carried = self.carried_modal_velocities(state)
        self._free = []
        for g, group in enumerate(self.groups):
            qd = carried[g] if carried is not None else group.project(state.v)
            qd_free, chol, n_bad, positive = group.free_motion(state.x, qd, control.pressures, h, m.rayleigh_mass,
                                                               m.rayleigh_stiffness, control.forces,
                                                               self.settings.rid_dtype)
            for j in np.flatnonzero(n_bad):
                raise SimulationDiverged(f"{n_bad[j]} inverted elements in reduced body "
                                         f"{m.bodies[group.members[j]].name!r}", state.t)
            for j in np.flatnonzero(~positive):
                raise SimulationDiverged(f"reduced matrix of body {m.bodies[group.members[j]].name!r} "
                                         "is not positive definite", state.t)
            self._free.append((qd_free, chol))
        return v_free

    def _free_velocity(self, i: int, body: Body, x: np.ndarray, v: np.ndarray,
                       control: Control, t: float) -> np.ndarray:
        """The implicit step of a :class:`FloatingFrameBody`, solved in its frame:
        ``dv' = A_0^-1 h (R^T f_ext - K_0 (R^T x - X + (h + r_K) R^T v) - r_M M R^T v)``;
        full-order bodies as in the full solver."""
        if i not in self.floating:
            return super()._free_velocity(i, body, x, v, control, t)
        m, c = self.model, self.compliance[i]
        v_free, c.rotation = self.floating[i].free_velocity(c.factor, x, v, self.external_forces(i, x, control),
                                                            self.settings.dt, m.rayleigh_mass, m.rayleigh_stiffness)
        return v_free

    def external_forces(self, i: int, x: np.ndarray, control: Control) -> np.ndarray:
        """``(n, 3)`` gravity, pressure and prescribed forces on body ``i`` at its positions ``x``, mN."""
        m = self.model
        f = m.bodies[i].external_forces(x, control.pressures, np.asarray(m.gravity))
        if control.forces is not None:
            f = f + control.forces[m.body_slice(i)]
        return f

    # -- constraints ---------------------------------------------------------------------
    def constrain(self, state: State, v_free: np.ndarray,
                  modal_free: list[tuple[np.ndarray, np.ndarray]]) -> tuple[Corrections | None, np.ndarray, np.ndarray]:
        """The constraint stage of a step (attachments and floor contacts) given its free motion.

        Args:
            state: the state at the start of the step.
            v_free: ``(N, 3)`` free velocities of the nodal bodies, mm/s (:meth:`nodal_free_motion`;
                the modal groups' floor candidates' z velocities are written into it).
            modal_free: per modal group ``(qdot_free (L, m) mm/s, chol (L, m, m))``: the free
                modal velocities and the Cholesky factors of the step matrices
                (:meth:`~softcrawl.reduction.group.ModalGroup.free_motion`).

        Returns:
            ``(corrections, nodes, impulses)``: the :class:`Corrections` (None: no constraint),
            the contact nodes ``(k,)`` (global) and their impulses ``(k, 3)`` (normal, t1, t2), mN s.

        Raises:
            SimulationDiverged: as the step.
        """
        self._free = list(modal_free)
        try:
            return self._constrain(state, v_free)
        finally:
            self._free = []

    def _constrain(self, state: State, v_free: np.ndarray):
        """The constraint stage: compiled (:mod:`softcrawl.reduction.constrain`, the same as in a
        :class:`~softcrawl.reduction.batch.BatchedReducedSolver`) for a robot of the default kind
        (a floating-frame disk and one modal group), else the full solver's with this class's
        reduced rows."""
        if self._compiled is None:
            m = self.model
            leg_start = [0, self.groups[0].n_bodies] if self.groups else [0, 0]
            self._compiled = ConstraintBatch.of([self], self.groups[0] if self.groups else None, leg_start,
                                                [0, m.n_nodes]) or False
        if not self._compiled:
            return super()._constrain(state, v_free)
        qd_free, chol = self._free[0]
        dv, dq, ((nodes, impulses),) = self._compiled.run(state.x, v_free, qd_free, chol, [state], np.zeros(1, bool))
        disk = self._compiled.disks[0]
        sl = self.model.body_slice(disk)
        return Corrections({disk: dv[sl]}, [dq]), nodes, impulses

    def _contact_rows(self, x: np.ndarray, v_free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As the full solver, and for a modal group's collision nodes: a node can only be a
        candidate if ``gap - h |v| < d`` with the bound ``|v_n| <= |Phi_p[n]|_F |qdot|``
        (Phi orthonormal); only those nodes' free z velocities are computed (written to
        ``v_free``)."""
        near, gaps = super()._contact_rows(x, v_free)
        floor, h = self.model.floor, self.settings.dt
        if floor is None:
            return near, gaps
        parts, part_gaps = [near], [gaps]
        for group, (qd, _) in zip(self.groups, self._free):
            n, g, vz = group.floor_candidates(x, qd, h, floor)
            v_free[n, 2] = vz
            parts.append(n)
            part_gaps.append(g)
        near, gaps = np.concatenate(parts), np.concatenate(part_gaps)
        order = np.argsort(near)
        return near[order], gaps[order]

    def _group_contacts(self, g: int, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Contacts at global ``nodes`` as ``(body in group g or -1, part node, global block)``."""
        group = self.groups[g]
        member = np.where(self._node_group[nodes] == g, self._node_member[nodes], -1)
        local = nodes - group.offsets[np.maximum(member, 0)]
        return member, local, len(self.model.attachments) + np.arange(len(nodes))

    def _delassus(self, v_free, nodes, bodies):
        W, q, blocks = super()._delassus(v_free, nodes, bodies)
        contacts = [self._group_contacts(g, nodes) for g in range(len(self.groups))]
        for group, (qd, chol), c in zip(self.groups, self._free, contacts):
            group.add_delassus(W, q, chol, qd, c)
        return W, q, (blocks, contacts)

    def _corrections(self, lam, jacobians) -> Corrections:
        blocks, contacts = jacobians
        return Corrections(super()._corrections(lam, blocks),
                           [group.corrections(lam, chol, c) for group, (_, chol), c in
                            zip(self.groups, self._free, contacts)])

    def _normal_velocity_change(self, corrections: Corrections, near, near_body):
        dv = super()._normal_velocity_change(corrections.nodal, near, near_body)
        for g, (group, dq) in enumerate(zip(self.groups, corrections.modal)):
            on = np.flatnonzero(self._node_group[near] == g)
            if len(on):
                member = self._node_member[near[on]]
                dv[on] = group.velocity_z(dq, member, near[on] - group.offsets[member])
        return dv

    def _velocity(self, v_free: np.ndarray, corrections: Corrections | None) -> np.ndarray:
        """As the full solver, and a modal group's velocities ``Phi (qdot_free + dqdot)``
        (one reconstruction per group and step; the modal velocities go to the new state)."""
        v = super()._velocity(v_free, corrections.nodal if corrections else None)
        self._qdot = []
        for g, (group, (qd_free, _)) in enumerate(zip(self.groups, self._free)):
            qd = qd_free + corrections.modal[g] if corrections else qd_free
            self._qdot.append(qd)
            group.velocities(qd, v)
        return v

    def step(self, state: State, control: Control) -> State:
        """The full solver's step (:meth:`ImplicitEulerSolver.step`: same arguments, errors);
        the new state carries the modal velocities of the reduced bodies."""
        new = super().step(state, control)
        return dataclasses.replace(new, modal_velocities=tuple(self._qdot))
