"""Time integration: linearly implicit Euler with frictional contact (the full-order solver).

One step (physics.md, "Time stepping"), per body, with ``K`` the corotational tangent
stiffness (positive) at the current positions, ``M`` the lumped mass, Rayleigh damping
``C = r_M M + r_K K``:

    [(1 + h r_M) M + h (h + r_K) K] dv = h (f(x) - (h + r_K) K v - r_M M v)

(SOFA ``EulerImplicitSolver``; Baraff & Witkin 1998, "Large steps in cloth simulation").
Optional extra Newton iterations solve the nonlinear backward-Euler equations
``M (v - v_n) = h (f(x_n + h v) - C v)``. Then floor contacts and attachments correct the
velocities (:mod:`softcrawl.fem.contact`) and ``x += h v``.

Bodies are coupled only through constraints, so each body's matrix is factorized alone.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.sparse as sp

from softcrawl.fem.body import Body
from softcrawl.fem.contact import solve_constraints
from softcrawl.fem.linalg import LaggedSolver
from softcrawl.fem.model import Model, PointRef
from softcrawl.fem.state import Control, State


class SimulationDiverged(RuntimeError):
    """The state became invalid (NaN/inf, runaway speed, inverted elements).

    Attributes:
        reason: what was detected.
        time: simulation time of the step that failed, s.
    """

    def __init__(self, reason: str, time: float):
        super().__init__(f"simulation diverged at t = {time:.4f} s: {reason}")
        self.reason, self.time = reason, time


@dataclass(frozen=True)
class SolverSettings:
    """Settings of :class:`ImplicitEulerSolver`.

    Attributes:
        dt: time step, s (> 0; physics.md: 0.01).
        newton_iterations: 1 = linearly implicit Euler (the reference); more = Newton
            iterations on backward Euler.
        refactor_every: reuse a body's factorization for up to this many linear solves,
            solving exactly with factorization-preconditioned CG in between (1 = always
            refactorize). The Delassus operator uses the current factorization.
        cg_rtol: CG relative residual tolerance.
        contact_tolerance: Gauss-Seidel relative impulse change to stop at (physics.md: 1e-8).
        contact_max_iterations: Gauss-Seidel sweep limit (physics.md: 250).
        max_speed: any node faster than this (mm/s) means divergence.

    Raises:
        ValueError: non-positive dt or iteration counts.
    """

    dt: float = 0.01
    newton_iterations: int = 1
    refactor_every: int = 1
    cg_rtol: float = 1e-10
    contact_tolerance: float = 1e-8
    contact_max_iterations: int = 250
    max_speed: float = 1e5

    def __post_init__(self) -> None:
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"time step dt must be positive, got {self.dt!r} s")
        if self.newton_iterations < 1 or self.refactor_every < 1 or self.contact_max_iterations < 1:
            raise ValueError("newton_iterations, refactor_every and contact_max_iterations must be >= 1")


@dataclass
class StepStats:
    """What the last step did (for reports and solver diagnostics)."""

    n_contacts: int = 0
    n_sticking: int = 0
    contact_sweeps: int = 0
    contact_change: float = 0.0
    normal_force: float = 0.0  # total floor normal force, mN
    factorizations: int = 0
    cg_iterations: int = 0
    extra: dict = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class _Row:
    """A 3-row constraint block acting on one body: rows = frame @ sum_a w_a v[node_a]."""

    body: int
    nodes: np.ndarray
    weights: np.ndarray


_FLOOR_FRAME = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])  # normal, t1, t2


class ImplicitEulerSolver:
    """Full-order solver: ``step(state, control) -> state``.

    Args:
        model: the static model.
        settings: integration and contact settings.

    The solver keeps per-body factorizations between steps (a cache; results do not
    depend on it beyond solver tolerances) and the statistics of the last step in
    :attr:`stats`.
    """

    def __init__(self, model: Model, settings: SolverSettings = SolverSettings()):
        self.model, self.settings = model, settings
        self._linear = [
            LaggedSolver(settings.refactor_every, settings.cg_rtol) for _ in model.bodies
        ]
        self._mass3 = [np.repeat(b.nodal_mass, 3) for b in model.bodies]
        self._collision = np.concatenate(
            [self.model.node_offsets[i] + b.collision_nodes[b.fixed[b.collision_nodes].sum(1) == 0]
             for i, b in enumerate(model.bodies)]
        )
        self._attach_rows = [
            (_Row(a.a.body, a.a.nodes, a.a.weights), _Row(a.b.body, a.b.nodes, -a.b.weights))
            for a in model.attachments
        ]
        self.stats = StepStats()

    # -- free motion ---------------------------------------------------------------------
    def _system(self, i: int, body: Body, x: np.ndarray, v: np.ndarray, v_n: np.ndarray,
                control: Control, t: float, linearised: bool) -> tuple[sp.csr_matrix, np.ndarray]:
        """Matrix and right-hand side of one (Newton) iteration for body ``i``."""
        h, m = self.settings.dt, self.model
        rM, rK = m.rayleigh_mass, m.rayleigh_stiffness
        f, kdata, n_bad = body.internal_forces(x, tangent_coef=1.0)
        if n_bad:
            raise SimulationDiverged(f"{n_bad} inverted elements in body {body.name!r}", t)
        f += body.external_forces(x, control.pressures, np.asarray(m.gravity))
        if control.forces is not None:
            f += control.forces[m.body_slice(i)]
        K = body.pattern.matrix(kdata)
        m3 = self._mass3[i]
        vf = v.ravel()
        # Linearised at x_n (first iteration): f(x_n + h v) ~ f(x_n) - h K v.
        rhs = h * (f.ravel() - ((h if linearised else 0.0) + rK) * (K @ vf) - rM * m3 * vf)
        if not linearised:
            rhs -= m3 * (vf - v_n.ravel())
        adata = h * (h + rK) * kdata
        adata[body.pattern.diag] += (1 + h * rM) * m3
        fixed = ~body.free_dofs
        if fixed.any():
            adata[body.fixed_entries] = 0.0
            adata[body.pattern.diag[fixed]] = 1.0
            rhs[fixed] = 0.0
        return body.pattern.matrix(adata), rhs

    def _free_velocity(self, i: int, body: Body, x: np.ndarray, v: np.ndarray,
                       control: Control, t: float) -> np.ndarray:
        h = self.settings.dt
        vk = v.copy()
        for it in range(self.settings.newton_iterations):
            xk = x if it == 0 else x + h * vk
            A, rhs = self._system(i, body, xk, vk, v, control, t, linearised=(it == 0))
            vk = vk + self._linear[i].solve(A, rhs).reshape(-1, 3)
        return vk

    # -- constraints ---------------------------------------------------------------------
    def _contact_rows(self, x: np.ndarray, v_free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Global nodes that are floor contact candidates and their current gaps (mm)."""
        floor = self.model.floor
        if floor is None:
            return np.zeros(0, np.int64), np.zeros(0)
        c = self._collision
        gap = x[c, 2] - floor.height
        gap_free = gap + self.settings.dt * v_free[c, 2]
        near = np.minimum(gap, gap_free) < floor.contact_distance
        return c[near], gap[near]

    def _constrain(self, state: State, v_free: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Velocity corrections from attachments and floor contacts."""
        m, h = self.model, self.settings.dt
        nodes, gaps = self._contact_rows(state.x, v_free)
        blocks: list[tuple[_Row, ...]] = list(self._attach_rows)
        frames = [np.eye(3)] * len(blocks) + [_FLOOR_FRAME] * len(nodes)
        offsets = m.node_offsets
        for g in nodes:
            b = int(np.searchsorted(offsets, g, side="right") - 1)
            blocks.append((_Row(b, np.array([g - offsets[b]]), np.ones(1)),))
        n_rows = 3 * len(blocks)
        if n_rows == 0:
            return np.zeros_like(v_free), nodes, np.zeros((0, 3))
        # Per-body H (rows x 3n_b) and Y = A^-1 H^T.
        per_body: dict[int, list[tuple[int, _Row, np.ndarray]]] = {}
        for j, (blk, fr) in enumerate(zip(blocks, frames)):
            for row in blk:
                per_body.setdefault(row.body, []).append((j, row, fr))
        W = np.zeros((n_rows, n_rows))
        q = np.zeros(n_rows)
        H_list = {}
        for b, items in per_body.items():
            body = m.bodies[b]
            rows, cols, vals = [], [], []
            for j, row, fr in items:
                for r in range(3):
                    for node, w in zip(row.nodes, row.weights):
                        rows.extend([3 * j + r] * 3)
                        cols.extend(3 * node + np.arange(3))
                        vals.extend(w * fr[r])
            H = sp.csr_matrix((vals, (rows, cols)), shape=(n_rows, 3 * body.n_nodes))
            H = H @ sp.diags(body.free_dofs.astype(float))
            used = np.unique(H.nonzero()[0])
            Hu = H[used]
            Y = self._linear[b].factor.solve(Hu.T.toarray())
            W[np.ix_(used, used)] += Hu @ Y
            q += H @ v_free[m.body_slice(b)].ravel()
            H_list[b] = (used, Y)
        nb = 3 * len(self._attach_rows)
        for j, (ra, rb) in enumerate(self._attach_rows):  # drift correction: u = -(x_a - x_b)/h
            pa = m.point_position(state.x, PointRef(ra.body, ra.nodes, ra.weights))
            pb = m.point_position(state.x, PointRef(rb.body, rb.nodes, -rb.weights))
            q[3 * j : 3 * j + 3] += (pa - pb) / h
        q[nb::3] += gaps / h  # Signorini: gap + h u_n >= 0
        mu = np.full(len(nodes), m.floor.friction if m.floor else 0.0)
        warm = np.zeros((len(nodes), 3))
        if len(state.contact_nodes) and len(nodes):
            idx = np.searchsorted(state.contact_nodes, nodes)
            idx = np.minimum(idx, len(state.contact_nodes) - 1)
            hit = state.contact_nodes[idx] == nodes
            warm[hit] = state.contact_impulses[idx[hit]]
        sol = solve_constraints(W, q, nb, mu, warm, self.settings.contact_tolerance,
                                self.settings.contact_max_iterations)
        lam = np.concatenate([sol.bilateral, sol.contact.ravel()])
        dv = np.zeros_like(v_free)
        for b, (used, Y) in H_list.items():
            dv[m.body_slice(b)] += (Y @ lam[used]).reshape(-1, 3)
        u = W @ lam + q
        tang = np.hypot(u[nb + 1 :: 3], u[nb + 2 :: 3])
        st = self.stats
        st.n_contacts = int(np.sum(sol.contact[:, 0] > 0))
        st.n_sticking = int(np.sum((sol.contact[:, 0] > 0) & (tang <= 1e-6 * (1 + np.abs(u).max()))))
        st.contact_sweeps, st.contact_change = sol.sweeps, sol.relative_change
        st.normal_force = float(sol.contact[:, 0].sum() / h)
        return dv, nodes, sol.contact

    # -- public --------------------------------------------------------------------------
    def step(self, state: State, control: Control) -> State:
        """Advance one time step.

        Args:
            state: positions/velocities at time t (``(N, 3)`` each, mm and mm/s).
            control: cavity pressures (sim kPa), one per channel of the model.

        Returns:
            The state at ``t + dt``.

        Raises:
            ValueError: if the control has the wrong number of channels.
            SimulationDiverged: NaN/inf or runaway velocities, or inverted elements.
        """
        m, h = self.model, self.settings.dt
        p = control.pressures
        if len(p) != m.n_channels:
            raise ValueError(f"control has {len(p)} pressures, the model has {m.n_channels} channels")
        if control.forces is not None and control.forces.shape != state.x.shape:
            raise ValueError(f"control forces have shape {control.forces.shape}, expected {state.x.shape}")
        if not state.is_finite():
            raise SimulationDiverged("non-finite positions or velocities in the input state", state.t)
        self.stats = StepStats()
        before = [(s.factorizations, s.cg_iterations) for s in self._linear]
        v_free = np.empty_like(state.v)
        for i, body in enumerate(m.bodies):
            sl = m.body_slice(i)
            v_free[sl] = self._free_velocity(i, body, state.x[sl], state.v[sl], control, state.t)
        dv, nodes, impulses = self._constrain(state, v_free)
        v = v_free + dv
        x = state.x + h * v
        for s, (f0, c0) in zip(self._linear, before):
            self.stats.factorizations += s.factorizations - f0
            self.stats.cg_iterations += s.cg_iterations - c0
        t = state.t + h
        if not (np.all(np.isfinite(x)) and np.all(np.isfinite(v))):
            raise SimulationDiverged("non-finite positions or velocities", t)
        vmax = float(np.sqrt((v * v).sum(1)).max())
        if vmax > self.settings.max_speed:
            raise SimulationDiverged(f"node speed {vmax:.3g} mm/s exceeds {self.settings.max_speed:.3g}", t)
        order = np.argsort(nodes)
        return State(x=x, v=v, t=t, contact_nodes=nodes[order], contact_impulses=impulses[order])

