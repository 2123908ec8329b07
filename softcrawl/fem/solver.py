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

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from softcrawl.fem.body import Body
from softcrawl.fem.constraints import FixedRows, NodalCompliance, add_body, attachment_matrix, body_correction
from softcrawl.fem.contact import solve_constraints
from softcrawl.fem.kernels import advance_positions
from softcrawl.fem.linalg import ReusedFactorization
from softcrawl.fem.model import Model
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


#: Precisions of the reduced bodies' RID element products (:attr:`SolverSettings.rid_dtype`).
RID_DTYPES = ("float64", "float32")
#: The reference Gauss-Seidel sweep limit of the contact solve, per chunk (physics.md: 250).
CONTACT_MAX_ITERATIONS = 250


@dataclass(frozen=True)
class SolverSettings:
    """Settings of :class:`ImplicitEulerSolver`.

    Attributes:
        dt: time step, s (> 0; physics.md: 0.01).
        newton_iterations: 1 = linearly implicit Euler (the reference); more = Newton
            iterations on backward Euler.
        refactor_every: refactorize each body's matrix every this many linear solves
            (1 = every step: exact). In between, the free motion is still solved to
            ``cg_rtol`` by CG preconditioned with the kept factorization, but the contact
            compliance ``A^-1 H^T`` (Delassus operator and velocity correction) uses the
            kept factorization: constraints hold exactly, the impulse response lags.
        cg_rtol: relative residual tolerance of those CG solves.
        contact_tolerance: Gauss-Seidel relative impulse change to stop at (physics.md: 1e-8).
        contact_max_iterations: Gauss-Seidel sweep limit (physics.md: 250).
        max_speed: any node faster than this (mm/s) means divergence.
        rid_dtype: reduced bodies only (:class:`softcrawl.reduction.solver.ReducedSolver`): the
            precision of their RID element products, ``"float64"`` (the reference) or
            ``"float32"`` (:func:`softcrawl.reduction.kernels.accumulate_terms32`).

    Raises:
        ValueError: non-positive dt or iteration counts.
    """

    dt: float = 0.01
    newton_iterations: int = 1
    refactor_every: int = 1
    cg_rtol: float = 1e-9
    contact_tolerance: float = 1e-8
    contact_max_iterations: int = CONTACT_MAX_ITERATIONS
    max_speed: float = 1e5
    rid_dtype: str = "float64"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise ValueError(f"time step dt must be positive, got {self.dt!r} s")
        if min(self.newton_iterations, self.refactor_every, self.contact_max_iterations) < 1:
            raise ValueError("newton_iterations, refactor_every and contact_max_iterations must be >= 1")
        if self.rid_dtype not in RID_DTYPES:
            raise ValueError(f"rid_dtype must be one of {RID_DTYPES}, got {self.rid_dtype!r}")


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


#: The contact set grows by at most ``max(MIN_CONTACT_GROWTH, its size)`` candidates per round:
#: when a reduced leg's paper face lands, ~300 nodes penetrate at once but ~10 carry load.
MIN_CONTACT_GROWTH = 16

#: ``(3, 3)`` rows: the floor contact frame's normal and two tangents (world z, x, y).
FLOOR_FRAME = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
_FLOOR_FRAMES = np.tile(FLOOR_FRAME, (64, 1, 1))


def _floor_frames(k: int) -> np.ndarray:
    """``(k, 3, 3)`` copies of the floor contact frame (a view of a kept array for k <= 64:
    ``np.broadcast_to`` costs more than the Delassus terms it feeds)."""
    return _FLOOR_FRAMES[:k] if k <= len(_FLOOR_FRAMES) else np.tile(FLOOR_FRAME, (k, 1, 1))


class ImplicitEulerSolver:
    """Full-order solver: ``step(state, control) -> state``.

    Args:
        model: the static model.
        settings: integration and contact settings.

    Attributes:
        stats: the :class:`StepStats` of the last step.
        compliance: per body its :class:`~softcrawl.fem.constraints.NodalCompliance` (contact
            compliance columns ``A^-1 H^T`` of its current factorization; None before the
            body's first step).
        attachment_drift: ``(3A, 3N)`` sparse rows ``x_a - x_b`` of the ``A`` attachments on the
            stacked positions (weights signed), mm per mm.
        nodal_bodies: the bodies whose velocities are node velocities (all of them here; a
            reduced solver leaves out its modal bodies).
    """

    def __init__(self, model: Model, settings: SolverSettings = SolverSettings()):
        self.model, self.settings = model, settings
        self._linear = [ReusedFactorization(settings.refactor_every, settings.cg_rtol) for _ in model.bodies]
        # Contact compliance columns, valid as long as the body's factorization is kept.
        self.compliance: list[NodalCompliance | None] = [None] * len(model.bodies)
        self._mass3 = [np.repeat(b.nodal_mass, 3) for b in model.bodies]
        self._collision = np.concatenate(
            [self.model.node_offsets[i] + b.collision_nodes[b.fixed[b.collision_nodes].sum(1) == 0]
             for i, b in enumerate(model.bodies)]
        )
        # Attachment j is block j: rows x_a - x_b (weights signed); each body's part of them.
        self.attachment_drift = attachment_matrix(model)
        self._attach_rows = {}
        for i, b in enumerate(model.bodies):
            rows = FixedRows.of_body(self.attachment_drift, int(model.node_offsets[i]), b.n_nodes)
            if rows is not None:
                self._attach_rows[i] = rows
        self.nodal_bodies = set(range(len(model.bodies)))
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

    def _free_motion(self, state: State, control: Control) -> np.ndarray:
        """``(N, 3)`` free (unconstrained) velocities of all bodies, mm/s."""
        m = self.model
        v_free = np.empty_like(state.v)
        for i, body in enumerate(m.bodies):
            sl = m.body_slice(i)
            v_free[sl] = self._free_velocity(i, body, state.x[sl], state.v[sl], control, state.t)
        return v_free

    def _free_velocity(self, i: int, body: Body, x: np.ndarray, v: np.ndarray,
                       control: Control, t: float) -> np.ndarray:
        h = self.settings.dt
        vk = v.copy()
        for it in range(self.settings.newton_iterations):
            xk = x if it == 0 else x + h * vk
            A, rhs = self._system(i, body, xk, vk, v, control, t, linearised=(it == 0))
            lin = self._linear[i]
            n_fact, n_cg = lin.factorizations, lin.cg_iterations
            vk = vk + lin.solve(A, rhs).reshape(-1, 3)
            self.stats.factorizations += lin.factorizations - n_fact
            self.stats.cg_iterations += lin.cg_iterations - n_cg
            if lin.factorizations > n_fact or self.compliance[i] is None:
                self.compliance[i] = NodalCompliance(lin.factor, body.free_dofs, self._attach_rows.get(i))
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

    def _constrain(self, state: State, v_free: np.ndarray):
        """Velocity corrections from attachments and floor contacts: ``(corrections, nodes,
        impulses)`` with the corrections for :meth:`_velocity` (None: no constraint), the
        contact nodes (global, ``(k,)``) and their impulses ``(k, 3)`` (normal, t1, t2), mN s.

        Of ``v_free`` only the z velocity of collision nodes is read, and what
        :meth:`_delassus` reads.

        The contact set starts from last step's loaded contacts (the pattern changes little
        between steps), or from the candidates whose free motion penetrates when none were
        loaded, and grows by the candidates the solve leaves below the floor (the deepest
        ones, at most as many as it holds or :data:`MIN_CONTACT_GROWTH`) until there is
        none; candidates left out have zero impulse and a non-negative gap, so the result
        solves the whole problem. Starting small matters for reduced legs: a leg lying on its
        paper face has ~100 penetrating candidates but only ~36 modes, and a Delassus
        operator of that rank deficiency makes Gauss-Seidel run to its sweep limit.
        """
        m, h = self.model, self.settings.dt
        near, gaps = self._contact_rows(state.x, v_free)
        near_body = np.searchsorted(m.node_offsets, near, side="right") - 1
        loaded = state.contact_nodes[state.contact_impulses[:, 0] > 0] if len(state.contact_nodes) else near[:0]
        at = np.minimum(np.searchsorted(loaded, near), max(len(loaded) - 1, 0))  # loaded is sorted
        active = loaded[at] == near if len(loaded) else np.zeros(len(near), bool)
        if not active.any():  # first touch: the deepest penetrating candidates, the rest grow in
            pred = gaps + h * v_free[near, 2]
            first = np.flatnonzero(pred < 0)
            active[first[np.argsort(pred[first])[:MIN_CONTACT_GROWTH]]] = True
        n_att = len(m.attachments)
        nb = 3 * n_att
        drift = self.attachment_drift @ state.x.ravel()  # attachment violation x_a - x_b
        mu = m.floor.friction if m.floor else 0.0
        while True:
            idx = np.flatnonzero(active)
            if not n_att + len(idx):
                return None, near[:0], np.zeros((0, 3))
            W, q, jacobians = self._delassus(v_free, near[idx], near_body[idx])
            q[:nb] += drift / h  # attachments: u = -(x_a - x_b)/h
            q[nb::3] += gaps[idx] / h  # Signorini: gap + h u_n >= 0
            warm = np.zeros((len(idx), 3))
            if len(state.contact_nodes) and len(idx):
                pos = np.minimum(np.searchsorted(state.contact_nodes, near[idx]), len(state.contact_nodes) - 1)
                hit = state.contact_nodes[pos] == near[idx]
                warm[hit] = state.contact_impulses[pos[hit]]
            sol = solve_constraints(W, q, nb, np.full(len(idx), mu), warm,
                                    self.settings.contact_tolerance, self.settings.contact_max_iterations)
            lam = np.concatenate([sol.bilateral, sol.contact.ravel()])
            corrections = self._corrections(lam, jacobians)
            new_gap = gaps + h * (v_free[near, 2] + self._normal_velocity_change(corrections, near, near_body))
            missed = np.flatnonzero(~active & (new_gap < -1e-9 * max(1.0, float(np.abs(gaps).max(initial=0.0)))))
            if not len(missed):
                break
            grow = max(MIN_CONTACT_GROWTH, len(idx))
            if len(missed) > grow:  # the deepest first: lifting them often clears the rest
                missed = missed[np.argsort(new_gap[missed])[:grow]]
            active[missed] = True
        u = W @ lam + q
        tang = np.hypot(u[nb + 1 :: 3], u[nb + 2 :: 3])
        st = self.stats
        loaded_now = sol.contact[:, 0] > 0
        st.n_contacts = int(loaded_now.sum())
        st.n_sticking = int(np.sum(loaded_now & (tang <= 1e-9 * (1 + np.abs(u).max()))))
        st.contact_sweeps, st.contact_change = sol.sweeps, sol.relative_change
        st.normal_force = float(sol.contact[:, 0].sum() / h)
        return corrections, near[idx], sol.contact

    def _delassus(self, v_free: np.ndarray, nodes: np.ndarray, bodies: np.ndarray) -> tuple[np.ndarray, np.ndarray, dict]:
        """Delassus operator ``W`` ``(3B, 3B)``, free constraint velocities ``H v_free``
        ``(3B,)`` and what :meth:`_corrections` needs, for the attachments (blocks
        ``0..A-1``) and floor contacts at global ``nodes`` of ``bodies`` (blocks ``A..``)."""
        m = self.model
        n_att = len(m.attachments)
        B = n_att + len(nodes)
        W, u, blocks = np.zeros((3 * B, 3 * B)), np.zeros(3 * B), {}
        for b in self.nodal_bodies:
            on = np.flatnonzero(bodies == b)
            if b not in self._attach_rows and not len(on):
                continue
            blocks[b] = add_body(W, u, self.compliance[b], v_free[m.body_slice(b)], nodes[on] - m.node_offsets[b],
                                 _floor_frames(len(on)), n_att + on)
        return W, u, blocks

    def _corrections(self, lam: np.ndarray, blocks: dict) -> dict[int, np.ndarray]:
        """body -> its velocity change ``(n, 3)`` (mm/s) for the impulses ``lam``."""
        return {b: body_correction(self.compliance[b], lam, bb) for b, bb in blocks.items()}

    def _normal_velocity_change(self, corrections: dict[int, np.ndarray], near: np.ndarray,
                                near_body: np.ndarray) -> np.ndarray:
        """``(k,)`` z velocity change of the corrections at global nodes ``near`` of ``near_body``."""
        dv = np.zeros(len(near))
        for b, d in corrections.items():
            on_b = near_body == b
            if on_b.any():
                dv[on_b] = d[near[on_b] - self.model.node_offsets[b], 2]
        return dv

    def _velocity(self, v_free: np.ndarray, corrections: dict[int, np.ndarray] | None) -> np.ndarray:
        """``(N, 3)`` end-of-step velocities: the free ones plus each body's constraint
        correction, mm/s."""
        v = v_free.copy()
        for b, d in (corrections or {}).items():
            v[self.model.body_slice(b)] += d
        return v

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
        v_free = self._free_motion(state, control)
        corrections, nodes, impulses = self._constrain(state, v_free)
        v = self._velocity(v_free, corrections)
        x, speed2, finite = advance_positions(state.x, v, h)
        t = state.t + h
        if not finite:
            raise SimulationDiverged("non-finite positions or velocities", t)
        if speed2 > self.settings.max_speed ** 2:
            raise SimulationDiverged(f"node speed {np.sqrt(speed2):.3g} mm/s exceeds {self.settings.max_speed:.3g}", t)
        order = np.argsort(nodes)
        return State(x=x, v=v, t=t, contact_nodes=nodes[order], contact_impulses=impulses[order])

