"""One step of a reduced robot in JAX (:func:`step`) and the batched, jitted rollout of an action
(:func:`make_rollout`).

A step (physics.md, "Time stepping"; :class:`softcrawl.reduction.solver.ReducedSolver`):

1. the regulators slew toward their commands (150 kPa/s) and the pressures are warped to sim kPa;
2. free motion: every leg's linearly implicit step (:mod:`softcrawl.jaxsim.legs`), the disk's
   in its floating frame (:mod:`softcrawl.jaxsim.disk`);
3. constraints: the ``F`` attachments of each leg (equality, blocks first) and the ``K`` collision
   points of lowest predicted gap (floor contacts, normal/t1/t2). The Delassus operator
   ``W = sum_legs J_l A_l^-1 J_l^T + J_d A_d^-1 J_d^T`` (Duriez et al. 2006, sec. 4; reduction.md)
   is formed from each leg's Cholesky factor and the disk's constant ``A_0^-1`` rotated by its
   frame, the free constraint velocities get the attachments' drift ``(x_a - x_b) / h`` and the
   contacts' gap ``g / h`` (Signorini, ``g + h u_n >= 0``); it is assembled by blocks and the
   attachments are eliminated exactly (:mod:`softcrawl.jaxsim.delassus`), and
   :mod:`softcrawl.jaxsim.contact` solves the Coulomb contacts (accelerated projected gradient
   by default, or projected Gauss-Seidel: ``settings.solver``);
4. velocity corrections ``A^-1 J^T lam``, then ``q += h qdot``, ``x += h v``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from softcrawl.jaxsim import disk as disk_motion
from softcrawl.jaxsim import legs as leg_motion
from softcrawl.jaxsim.contact import solve_on_platform
from softcrawl.jaxsim.delassus import condense, constraint_rows, corrections
from softcrawl.jaxsim.model import register_pytree
from softcrawl.jaxsim.ridkernel import with_kernel_rows

#: The engine's numerical version: changes whenever a step's result changes (caches of settled
#: states built by an engine of another version are stale).
ENGINE_VERSION = 14

#: The parts of :func:`physics_step`, in order, as named scopes of its operations (a profile's
#: kernels are summed by them: :func:`softcrawl.jaxsim.cost.kernel_profile`).
STEP_SCOPES = ("legs_free_motion", "disk_free_motion", "constraint_rows", "condense", "solve_contacts", "corrections")


@dataclass(frozen=True)
class State:
    """One robot's state (a leading batch axis on every field when batched).

    Attributes:
        q, qdot: ``(L, m)`` legs' modal displacements (mm) and velocities (mm/s), part frame.
        x, v: ``(n, 3)`` disk node positions (mm) and velocities (mm/s).
        contact_points: ``(K,)`` last step's contact points (index into the disk's collision
            nodes, then each leg slot's); impulses: ``(K, 3)`` their impulses, mN s.
        pressure: ``(R,)`` regulator outputs, real kPa (``R = settings.channels``); t: time, s.
        bad: inverted or degenerate RID elements and steps of non-finite disk velocities met so
            far (0 for a valid rollout).
    """

    q: jax.Array
    qdot: jax.Array
    x: jax.Array
    v: jax.Array
    contact_points: jax.Array
    impulses: jax.Array
    pressure: jax.Array
    t: jax.Array
    bad: jax.Array


@dataclass(frozen=True)
class Control:
    """Regulator commands, real kPa: ``command`` ``(R,)`` (a leading batch axis when batched)."""

    command: jax.Array


for _cls in (State, Control):
    register_pytree(_cls)


def n_contacts(settings, n_slots: int) -> int:
    """K, the contact rows of a robot with ``n_slots`` leg slots (0 without a floor)."""
    return settings.disk_contacts + n_slots * settings.leg_contacts if settings.floor else 0


def rest_state(model) -> State:
    """The assembled robot at rest (mid-air) for a model with stacked robots (batch axis first)."""
    B, L = model.robot.leg_mask.shape
    m = model.leg.mass.shape[0]
    K = n_contacts(model.settings, L)
    dt = model.disk.rest.dtype
    x = jnp.broadcast_to(model.disk.rest, (B,) + model.disk.rest.shape)
    R = model.settings.channels
    return State(jnp.zeros((B, L, m), dt), jnp.zeros((B, L, m), dt), x, jnp.zeros_like(x),
                 jnp.full((B, K), -1, jnp.int32), jnp.zeros((B, K, 3), dt), jnp.zeros((B, R), dt),
                 jnp.zeros((B,), dt), jnp.zeros((B,), jnp.int32))


def sim_pressures(model, pressure):
    """``(R,)`` sim kPa of regulator outputs ``pressure`` (real kPa): ``max(a p + b, 0)`` (physics.md)."""
    a, b = model.settings.calibration
    return jnp.maximum(a * pressure + b, 0.0)


def physics_step(model, state: State, sim_kpa) -> State:
    """One ``dt`` of one robot at cavity pressures ``sim_kpa`` ``(R,)`` (sim kPa per regulator);
    the regulators are not stepped (module doc, steps 2-4).

    Matrix products run at the arrays' full precision (``jax.default_matmul_precision("float32")``
    while tracing): a GPU's default for float32 products, TF32 (10-bit mantissa), is too coarse for
    the step and inverts elements (``benchmarks/RESULTS.md``, the JAX engine). On a CPU the setting
    changes nothing."""
    with jax.default_matmul_precision("float32"):
        return _physics_step(model, state, sim_kpa)


def _constrained(model, state: State, sim_kpa):
    """Steps 2 and 3 up to the contact solve: the free motion, the constraint rows, the condensed
    contact problem and its warm start (last step's impulses of the points kept)."""
    st, leg, dk, rd = model.settings, model.leg, model.disk, model.robot
    with jax.named_scope("legs_free_motion"):
        qd_free, inv_chol, n_bad = jax.vmap(leg_motion.free_motion, in_axes=(None, None, 0, 0, 0, 0, 0))(
            leg, st, state.q, state.qdot, rd.rotation, sim_kpa[rd.channel] * rd.leg_mask, rd.leg_mask)
    with jax.named_scope("disk_free_motion"):
        v_free, R = disk_motion.free_motion(dk, st, state.x, state.v)
    with jax.named_scope("constraint_rows"):
        rows = constraint_rows(model, state, v_free, qd_free, R)
    with jax.named_scope("condense"):
        cond = condense(rows, inv_chol, qd_free, st.cholesky)
    return qd_free, inv_chol, n_bad, v_free, R, rows, cond, rows.warm.reshape(-1)


def contact_problem(model, state: State, sim_kpa):
    """The contact problem one robot's next step solves at cavity pressures ``sim_kpa`` ``(R,)``
    (sim kPa), for diagnostics: ``(W (3K, 3K), q (3K,), mu (K,), warm (3K,), active (K,))`` as
    :func:`softcrawl.jaxsim.contact.solve_contacts` takes them (the attachments eliminated)."""
    with jax.default_matmul_precision("float32"):
        *_, rows, cond, warm = _constrained(model, state, sim_kpa)
    return cond.W, cond.q, jnp.full(rows.active.shape, model.settings.friction, cond.q.dtype), warm, rows.active


def _physics_step(model, state: State, sim_kpa) -> State:
    st, rd = model.settings, model.robot
    h = st.dt
    # 2.-3. free motion, constraint rows, the attachments eliminated; the contacts solved
    qd_free, inv_chol, n_bad, v_free, R, rows, cond, warm = _constrained(model, state, sim_kpa)
    K = rows.points.shape[0]
    with jax.named_scope("solve_contacts"):  # the kernel is CUDA's (Settings.delassus)
        lam_c = solve_on_platform(cond.schur, cond.q, jnp.full((K,), st.friction, cond.q.dtype), warm, rows.active,
                                  st.solver, st.iterations, op=cond.blocks if st.delassus == "blocks" else None,
                                  storage=st.delassus_storage, kernel=st.delassus == "fused16")
    # 4. corrections
    with jax.named_scope("corrections"):
        dq, dv, _ = corrections(model, rows, cond, inv_chol, lam_c, R)
    v = v_free + dv
    qdot = qd_free + dq
    return dataclasses.replace(
        state, q=state.q + h * qdot, qdot=qdot, x=state.x + h * v, v=v, t=state.t + h,
        contact_points=rows.points.astype(jnp.int32), impulses=lam_c.reshape(K, 3),
        bad=(state.bad + jnp.sum(n_bad * rd.leg_mask) + (~jnp.all(jnp.isfinite(v)))).astype(state.bad.dtype))


def step(model, state: State, control: Control) -> State:
    """One ``dt`` of one robot: regulators (slew ``rate dt`` toward the commands), warp, physics."""
    st = model.settings
    dp = st.rate * st.dt
    pressure = state.pressure + jnp.clip(control.command - state.pressure, -dp, dp)
    new = physics_step(model, state, sim_pressures(model, pressure))
    return dataclasses.replace(new, pressure=pressure)


def max_speed(model, state: State):
    """Fastest node speed of one robot over all its nodes, mm/s, as the CPU rule
    (:func:`softcrawl.robot.episode.settle`) watches them: the disk's nodes and every leg node,
    ``|R Phi_n qdot| = |Phi_n qdot|`` (reduction.md, "Reduced kinematics"; absent legs masked)."""
    qdot = state.qdot * model.robot.leg_mask[:, None]
    vl = jnp.einsum("nam,lm->lna", model.leg.basis, qdot)
    return jnp.sqrt(jnp.maximum(jnp.max(jnp.sum(state.v ** 2, axis=1)), jnp.max(jnp.sum(vl ** 2, axis=2))))


def shared_parts(model):
    """The model without its per-robot data (``robot=None``: the parts every robot of a batch
    shares, ``jax.vmap`` ped with ``in_axes=None``), ready for a loop of steps: the legs' frame
    stiffness and the RID kernel's rows formed once, outside the loop
    (:func:`softcrawl.jaxsim.legs.with_frame_stiffness`,
    :func:`softcrawl.jaxsim.ridkernel.with_kernel_rows`)."""
    return dataclasses.replace(model, robot=None,
                               leg=with_kernel_rows(leg_motion.with_frame_stiffness(model.leg)))


def make_settle(rest_speed: float = 0.5, hold_steps: int = 5, max_steps: int = 300):
    """A jitted ``settle(model, state) -> (state, steps)``: every robot of the batch stepped at zero
    pressure until its :func:`max_speed` stayed below ``rest_speed`` (mm/s) for ``hold_steps``
    steps or ``max_steps`` passed (the rule of :class:`softcrawl.robot.Settling`; its defaults:
    0.5 mm/s held 0.05 s, at most 3 s, at dt 0.01 s); ``t`` is set to 0. Robots at rest wait
    for the others (``jax.lax.while_loop`` under ``jax.vmap``)."""

    def one(model, rd, state):
        mdl = dataclasses.replace(model, robot=rd)
        zero = jnp.zeros(model.settings.channels, state.x.dtype)

        def cond(c):
            return (c[2] < max_steps) & (c[1] < hold_steps)

        def body(c):
            s, calm, n = c
            s = physics_step(mdl, s, zero)
            return s, jnp.where(max_speed(mdl, s) < rest_speed, calm + 1, 0), n + 1

        s, _, n = jax.lax.while_loop(cond, body, (state, jnp.int32(0), jnp.int32(0)))
        return dataclasses.replace(s, t=jnp.zeros_like(s.t)), n

    @jax.jit
    def settle(model, state):
        return jax.vmap(one, in_axes=(None, 0, 0))(shared_parts(model), model.robot, state)

    return settle


def make_rollout(n_steps: int, physics_only: bool = False):
    """A jitted ``rollout(model, state, control) -> state`` that holds each robot's control for
    ``n_steps`` steps (``jax.lax.scan``), ``jax.vmap`` ped over the batch (the model's per-robot
    data, the states and the controls carry a leading batch axis; the parts are shared).
    ``physics_only``: ``control`` is ``(B, R)`` sim kPa for :func:`physics_step` (no regulators)."""

    def one(model, rd, state, control):
        mdl = dataclasses.replace(model, robot=rd)

        def body(s, _):
            return (physics_step(mdl, s, control) if physics_only else step(mdl, s, control)), None

        return jax.lax.scan(body, state, None, length=n_steps)[0]

    @jax.jit
    def rollout(model, state, control):
        return jax.vmap(one, in_axes=(None, 0, 0, 0))(shared_parts(model), model.robot, state, control)

    return rollout


def make_schedule_rollout(physics_only: bool = False, trace: bool = False):
    """A jitted ``rollout(model, state, schedule) -> (state, peak_speed, frames)`` that steps each
    robot of the batch through its own per-step commands (one ``jax.lax.scan`` over the steps,
    ``jax.vmap`` ped over the batch; the shape of ``schedule`` fixes the compiled program).

    Args:
        physics_only: ``schedule`` holds sim kPa per channel for :func:`physics_step` (no
            regulators; any number of channels ``c``) instead of real kPa regulator commands
            (``c = R``, the model's ``settings.channels``) for :func:`step`.
        trace: also return every step's legs' modal displacements and disk positions.

    The returned function takes ``schedule`` ``(B, n, c)`` (command of step ``k`` in row ``k``)
    and returns the state after ``n`` steps, ``peak_speed`` ``(B,)`` the fastest node speed met
    (:func:`max_speed`, mm/s; the CPU engine calls a run faster than its ``max_speed`` diverged)
    and, with ``trace``, ``frames = (q, x)``: ``(B, n, L, m)`` and ``(B, n, nd, 3)`` after each
    step (None without)."""

    def one(model, rd, state, schedule):
        mdl = dataclasses.replace(model, robot=rd)

        def body(carry, command):
            s, peak = carry
            s = physics_step(mdl, s, command) if physics_only else step(mdl, s, Control(command))
            return (s, jnp.maximum(peak, max_speed(mdl, s))), ((s.q, s.x) if trace else None)

        (s, peak), frames = jax.lax.scan(body, (state, jnp.zeros((), state.x.dtype)), schedule)
        return s, peak, frames

    @jax.jit
    def rollout(model, state, schedule):
        return jax.vmap(one, in_axes=(None, 0, 0, 0))(shared_parts(model), model.robot, state, schedule)

    return rollout
