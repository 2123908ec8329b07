"""Many reduced robots stepped as one batch (a training worker steps all of its robots at once).

A :class:`BatchedReducedSolver` advances the states of many models (robots that differ in
design, leg count and pose), each with its own :class:`~softcrawl.reduction.solver.ReducedSolver`,
by the same linearly implicit step, with the work arranged by kind instead of by robot:

- the reduced bodies placed from one part (the legs of every robot) form one stacked
  :class:`~softcrawl.reduction.group.ModalGroup` (:meth:`ModalGroup.stack`) with one copy of the
  part's RID data: their free motion is one compiled pass over the RID (in blocks of
  :data:`~softcrawl.reduction.group.BODY_BLOCK` legs), their velocities one pass over the basis;
- the nodal bodies take their robot's own free step (:meth:`ReducedSolver.nodal_free_motion`;
  the floating-frame disks' constant factorizations solve all robots' right-hand sides at once);
- constraints (attachments, floor contacts) couple the bodies of one robot only, so each robot's
  contact problem is solved alone, by its solver's own constraint code
  (:meth:`ReducedSolver.constrain`), from the batch's free velocities, or for robots of the
  default kind all in one compiled pass (:class:`~softcrawl.reduction.constrain.ConstraintBatch`);
- the end-of-step position update and the divergence checks are one compiled pass over all
  robots' nodes (:func:`softcrawl.fem.kernels.advance_positions_ranges`).

Every robot's arithmetic is the single solver's, operation for operation, so a robot's
trajectory in a batch equals its trajectory alone to the last bit (tests/test_batch.py), and a
robot that diverges is reported without touching the others.

The positions and velocities of all robots live in two stacked arrays (the batched state);
the :class:`~softcrawl.fem.state.State` of robot ``i`` returned by :meth:`step` holds views of
its rows and the modal velocities of its reduced bodies. Passing those states back (as an
episode does) lets the next step use the stacked arrays and those modal velocities without
copying or projecting.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from softcrawl.fem.kernels import advance_positions_ranges
from softcrawl.fem.solver import SimulationDiverged, StepStats
from softcrawl.fem.state import Control, State
from softcrawl.reduction.constrain import ConstraintBatch
from softcrawl.reduction.floating import FloatingFrameBody
from softcrawl.reduction.group import ModalGroup
from softcrawl.reduction.solver import ReducedSolver


def _same_part(a: ModalGroup, b: ModalGroup) -> bool:
    """Whether two modal groups were placed from equal parts (same basis, RID, cavities, collision
    nodes), so one copy of the part data serves both."""
    if a.basis is b.basis and a.families is b.families:
        return True
    arrays = lambda g: [g.basis, g.strain_modes, g.cavity_triangles, g.cavity_local, g.cavity_basis, g.collision,
                        g.collision_bound] + [x for f in g.families for x in (f.conn, f.factors, f.rest_terms, f.rows)]
    pa, pb = arrays(a), arrays(b)
    return len(pa) == len(pb) and all(x.shape == y.shape and np.array_equal(x, y) for x, y in zip(pa, pb))


class BatchedReducedSolver:
    """``step(states, controls) -> states`` for many reduced models at once (module doc).

    Args:
        solvers: one :class:`ReducedSolver` per robot (its static data, factorizations and
            constraint code); all with the same time step, contact settings and Rayleigh
            coefficients. After a batched step every solver is left as if it had made that
            step itself (its ``stats``), and the states carry their modal velocities, so a
            robot can leave a batch and go on alone or in another batch.

    Attributes:
        solvers: the robots' solvers (each one's ``stats`` describe its last batched step).
        starts: ``(M + 1,)`` first row of each robot in the stacked positions.
        groups: the stacked modal groups (one per part).

    Raises:
        ValueError: no solvers, a solver that is not a :class:`ReducedSolver`, or differing
            settings.
    """

    def __init__(self, solvers: Sequence[ReducedSolver]):
        self.solvers = list(solvers)
        if not self.solvers:
            raise ValueError("a batch needs at least one solver")
        first = self.solvers[0]
        for s in self.solvers:
            if not isinstance(s, ReducedSolver):
                raise ValueError(f"a batch steps ReducedSolvers, got {type(s).__name__}")
            if (s.settings != first.settings or s.model.rayleigh_mass != first.model.rayleigh_mass
                    or s.model.rayleigh_stiffness != first.model.rayleigh_stiffness):
                raise ValueError("the solvers of a batch must share settings and Rayleigh damping")
        self.settings = first.settings
        sizes = [s.model.n_nodes for s in self.solvers]
        self.starts = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
        channels = np.concatenate([[0], np.cumsum([s.model.n_channels for s in self.solvers])]).astype(np.int64)
        # Stack each part's groups: members[k] = [(robot, group index in the robot)], and per
        # robot and group its (stack, body slice in the stack).
        reps: list[ModalGroup] = []
        members: list[list[tuple[int, int]]] = []
        for r, s in enumerate(self.solvers):
            for g, group in enumerate(s.groups):
                k = next((k for k, rep in enumerate(reps) if _same_part(rep, group)), None)
                if k is None:
                    reps.append(group)
                    members.append([])
                    k = len(reps) - 1
                members[k].append((r, g))
        self.groups: list[ModalGroup] = []
        self._where: list[list[tuple[int, slice]]] = [[None] * len(s.groups) for s in self.solvers]
        for k, mem in enumerate(members):
            parts = [self.solvers[r].groups[g] for r, g in mem]
            self.groups.append(ModalGroup.stack(parts, self.starts[[r for r, _ in mem]],
                                                channels[[r for r, _ in mem]]))
            at = 0
            for (r, g), part in zip(mem, parts):
                self._where[r][g] = (k, slice(at, at + part.n_bodies))
                at += part.n_bodies
        self._body_robot = [np.repeat([r for r, _ in mem], [self.solvers[r].groups[g].n_bodies for r, g in mem])
                            for mem in members]
        self._members = members
        # the compiled constraint stage of all robots when they are all of its kind (legs of one part)
        self._compiled = None
        if len(self.groups) == 1:
            leg_start = [self._where[r][0][1].start for r in range(len(self.solvers))] + [self.groups[0].n_bodies]
            self._compiled = ConstraintBatch.of(self.solvers, self.groups[0], leg_start, self.starts)
        self._x = self._v = None  # the stacked arrays of the last step's states
        self._views: list[tuple[np.ndarray, np.ndarray] | None] = [None] * len(self.solvers)

    @property
    def n_robots(self) -> int:
        return len(self.solvers)

    def _stacked(self, states: Sequence[State]) -> tuple[np.ndarray, np.ndarray]:
        """Stacked ``(x, v)`` ``(N, 3)`` of ``states`` (no copy when they are this batch's last
        output)."""
        if all(w is not None and st.x is w[0] and st.v is w[1] for st, w in zip(states, self._views)):
            return self._x, self._v
        return np.concatenate([st.x for st in states]), np.concatenate([st.v for st in states])

    def _modal_velocities(self, k: int, v: np.ndarray, carried: list) -> np.ndarray:
        """``(L, m)`` start-of-step modal velocities of stacked group ``k``: those the robots'
        states carry (``carried[r]``, :meth:`ReducedSolver.carried_modal_velocities`), the
        others projected from ``v``."""
        group = self.groups[k]
        qd = np.empty((group.n_bodies, group.n_modes))
        for r, g in self._members[k]:
            sl = self._where[r][g][1]
            if carried[r] is not None:
                qd[sl] = carried[r][g]
            else:
                qd[sl] = group.project(v, np.arange(sl.start, sl.stop))
        return qd

    def step(self, states: Sequence[State], controls: Sequence[Control]) -> list[State | SimulationDiverged]:
        """Advance every robot one time step.

        Args:
            states: one :class:`State` per robot (``(N_i, 3)`` positions mm, velocities mm/s).
            controls: one :class:`Control` per robot (its model's pressure channels, kPa;
                optional prescribed forces, mN).

        Returns:
            Per robot its state at ``t + dt``, or the :class:`SimulationDiverged` that stopped
            it (NaN/inf, runaway speed, inverted elements, a reduced matrix that is not
            positive definite); the other robots are not affected.

        Raises:
            ValueError: wrong numbers of states or controls, or a control with the wrong
                number of channels or forces of the wrong shape.
        """
        M, h = self.n_robots, self.settings.dt
        if len(states) != M or len(controls) != M:
            raise ValueError(f"a batch of {M} robots needs {M} states and controls, got {len(states)}, {len(controls)}")
        for s, st, c in zip(self.solvers, states, controls):
            if len(c.pressures) != s.model.n_channels:
                raise ValueError(f"control has {len(c.pressures)} pressures, the model has {s.model.n_channels} channels")
            if c.forces is not None and c.forces.shape != st.x.shape:
                raise ValueError(f"control forces have shape {c.forces.shape}, expected {st.x.shape}")
        x, v = self._stacked(states)
        carried = [s.carried_modal_velocities(st) for s, st in zip(self.solvers, states)]
        failed: list[SimulationDiverged | None] = [None] * M
        for r, (st, w) in enumerate(zip(states, self._views)):
            if not (w is not None and st.x is w[0] and st.v is w[1]) and not st.is_finite():
                failed[r] = SimulationDiverged("non-finite positions or velocities in the input state", st.t)
        pressures = np.concatenate([c.pressures for c in controls])
        forces = None
        if any(c.forces is not None for c in controls):
            forces = np.concatenate([c.forces if c.forces is not None else np.zeros_like(st.x)
                                     for st, c in zip(states, controls)])
        m = self.solvers[0].model
        # Free motion of all modal bodies: one pass per part.
        free = []
        for k, group in enumerate(self.groups):
            robots = self._body_robot[k]
            qd = self._modal_velocities(k, v, carried)
            qd_free, chol, n_bad, positive = group.free_motion(x, qd, pressures, h, m.rayleigh_mass,
                                                               m.rayleigh_stiffness, forces, self.settings.rid_dtype)
            for j in np.flatnonzero((n_bad > 0) | ~positive):
                r = robots[j]
                if failed[r] is None:
                    failed[r] = self._group_failure(r, k, j, n_bad[j], states[r].t)
            free.append((qd_free, chol))
        # Nodal bodies and constraints: each robot's own solver code.
        v_free = np.zeros_like(v)
        v_new = np.empty_like(v)
        corrections: list = [None] * M
        contacts: list = [None] * M
        for r, (s, st, c) in enumerate(zip(self.solvers, states, controls)):
            if failed[r] is not None:
                continue
            rows = slice(self.starts[r], self.starts[r + 1])
            s.stats = StepStats()
            try:  # the floating bodies are solved below, with the other robots'
                s.nodal_free_motion(x[rows], v[rows], c, st.t, v_free[rows], floating=False)
            except SimulationDiverged as exc:
                failed[r] = exc
        self._floating_free_motion(x, v, v_free, controls, failed)
        if self._compiled is not None:  # every robot's constraints in one compiled pass
            dv, dq, contacts = self._compiled.run(x, v_free, free[0][0], free[0][1], states,
                                                  np.array([f is not None for f in failed]))
            for r, s in enumerate(self.solvers):
                if failed[r] is None:
                    rows = slice(self.starts[r], self.starts[r + 1])
                    v_new[rows] = v_free[rows]
                    sl = s.model.body_slice(self._compiled.disks[r])
                    v_new[rows][sl] += dv[rows][sl]
            qdot = [free[0][0] + dq]
        else:  # each robot's own solver code
            for r, (s, st) in enumerate(zip(self.solvers, states)):
                if failed[r] is not None:
                    continue
                rows = slice(self.starts[r], self.starts[r + 1])
                vf = v_free[rows]
                try:
                    corr, nodes, impulses = s.constrain(st, vf, [(free[k][0][sl], free[k][1][sl])
                                                                 for k, sl in self._where[r]])
                except SimulationDiverged as exc:
                    failed[r] = exc
                    continue
                corrections[r], contacts[r] = corr, (nodes, impulses)
                v_new[rows] = vf
                for i, d in (corr.nodal if corr else {}).items():
                    v_new[rows][s.model.body_slice(i)] += d
            # velocities of the modal bodies (kept as modal velocities)
            qdot = [qd_free.copy() for qd_free, _ in free]
            for r, corr in enumerate(corrections):
                if corr is not None:
                    for (k, sl), dq in zip(self._where[r], corr.modal):
                        qdot[k][sl] += dq
        for group, qd in zip(self.groups, qdot):
            group.velocities(qd, v_new)
        x_new, speed2, finite = advance_positions_ranges(x, v_new, h, self.starts)
        out: list[State | SimulationDiverged] = []
        max2 = self.settings.max_speed ** 2
        for r, st in enumerate(states):
            t = st.t + h
            if failed[r] is None and not finite[r]:
                failed[r] = SimulationDiverged("non-finite positions or velocities", t)
            elif failed[r] is None and speed2[r] > max2:
                failed[r] = SimulationDiverged(f"node speed {np.sqrt(speed2[r]):.3g} mm/s exceeds "
                                               f"{self.settings.max_speed:.3g}", t)
            if failed[r] is not None:
                self._views[r] = None
                out.append(failed[r])
                continue
            rows = slice(self.starts[r], self.starts[r + 1])
            nodes, impulses = contacts[r]
            order = np.argsort(nodes)
            new = State(x=x_new[rows], v=v_new[rows], t=t, contact_nodes=nodes[order], contact_impulses=impulses[order],
                        modal_velocities=tuple(qdot[k][sl] for k, sl in self._where[r]))
            self._views[r] = (new.x, new.v)
            out.append(new)
        self._x, self._v = x_new, v_new
        return out

    def _floating_free_motion(self, x: np.ndarray, v: np.ndarray, v_free: np.ndarray, controls: Sequence[Control],
                              failed: list) -> None:
        """Free velocities of every robot's floating-frame bodies into ``v_free`` (stacked, mm/s),
        each as its solver computes it (:meth:`FloatingFrameBody.free_velocity`), with the solves
        of bodies that share a factorization done at once (one multi-right-hand-side LDL^T
        solve: the same numbers, 4x less time per body); sets each body's compliance rotation."""
        h, m = self.settings.dt, self.solvers[0].model
        systems: dict[int, list] = {}
        for r, (s, c) in enumerate(zip(self.solvers, controls)):
            if failed[r] is not None:
                continue
            for i, fb in s.floating.items():
                sl = s.model.body_slice(i)
                rows = slice(self.starts[r] + sl.start, self.starts[r] + sl.stop)
                vb, rhs, R = fb.free_rhs(x[rows], v[rows], s.external_forces(i, x[rows], c), h, m.rayleigh_mass,
                                         m.rayleigh_stiffness)
                s.compliance[i].rotation = R
                factor = s.compliance[i].factor
                systems.setdefault(id(factor), [factor, []])[1].append((rows, vb, rhs, R))
        for factor, items in systems.values():
            dv = factor.solve(np.column_stack([rhs for _, _, rhs, _ in items]))
            for j, (rows, vb, _, R) in enumerate(items):
                v_free[rows] = FloatingFrameBody.world_velocity(vb, dv[:, j], R)

    def _group_failure(self, r: int, k: int, j: int, n_bad: int, t: float) -> SimulationDiverged:
        """The single solver's message for body ``j`` of stacked group ``k`` (robot ``r``)."""
        s = self.solvers[r]
        for g, (kk, sl) in enumerate(self._where[r]):
            if kk == k and sl.start <= j < sl.stop:
                name = s.model.bodies[s.groups[g].members[j - sl.start]].name
                break
        if n_bad:
            return SimulationDiverged(f"{n_bad} inverted elements in reduced body {name!r}", t)
        return SimulationDiverged(f"reduced matrix of body {name!r} is not positive definite", t)


class _LockstepSolver:
    """Stands in for one robot's solver in a loop run by :func:`run_in_lockstep`: its ``step``
    waits for the batch step of all loops; other attributes are the solver's."""

    def __init__(self, request, index: int, solver: ReducedSolver):
        self._request, self._index, self._solver = request, index, solver

    def step(self, state: State, control: Control) -> State:
        return self._request(self._index, state, control)

    def __getattr__(self, name):
        return getattr(self._solver, name)


def run_in_lockstep(solvers: Sequence[ReducedSolver], loops: Sequence) -> list:
    """Run single-robot code for many robots at once: ``loops[i](solver_i)`` in its own thread,
    where ``solver_i`` stands in for ``solvers[i]`` and its ``step`` calls from all loops are
    gathered into :class:`BatchedReducedSolver` steps (this thread steps the batch whenever
    every unfinished loop waits for a step; loops may stop at different times). Each loop gets
    what its solver alone would give (the batch's arithmetic is each solver's own), e.g.
    ``loops[i] = lambda s: settle(robot_i, settling, solver=s)``.

    Args:
        solvers: one :class:`ReducedSolver` per loop.
        loops: callables taking the stand-in solver.

    Returns:
        Per loop its return value, or the exception it raised (a divergence, say).
    """
    import threading

    n = len(loops)
    cond = threading.Condition()
    pending: dict[int, tuple[State, Control]] = {}
    results: dict[int, object] = {}
    done, outcome = [False] * n, [None] * n

    def request(i: int, state: State, control: Control) -> State:
        with cond:
            pending[i] = (state, control)
            cond.notify_all()
            cond.wait_for(lambda: i in results)
            out = results.pop(i)
        if isinstance(out, BaseException):
            raise out
        return out

    def run(i: int) -> None:
        try:
            outcome[i] = loops[i](_LockstepSolver(request, i, solvers[i]))
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            outcome[i] = exc
        finally:
            with cond:
                done[i] = True
                cond.notify_all()

    threads = [threading.Thread(target=run, args=(i,), daemon=True) for i in range(n)]
    for t in threads:
        t.start()
    batch, members = None, ()
    with cond:
        while True:
            cond.wait_for(lambda: all(done[i] or i in pending for i in range(n)))
            if all(done):
                break
            live = tuple(sorted(pending))
            if live != members:
                batch, members = BatchedReducedSolver([solvers[i] for i in live]), live
            requests = [pending.pop(i) for i in live]
            try:
                out = batch.step([s for s, _ in requests], [c for _, c in requests])
            except Exception as exc:  # noqa: BLE001 - an invalid request: every waiting loop gets it
                out = [exc] * len(live)
            results.update(zip(live, out))
            cond.notify_all()
    for t in threads:
        t.join()
    return outcome
