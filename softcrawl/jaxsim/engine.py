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
   contacts' gap ``g / h`` (Signorini, ``g + h u_n >= 0``), and :mod:`softcrawl.jaxsim.contact`
   solves it (bilateral rows exactly, the Coulomb contacts by projected Gauss-Seidel);
4. velocity corrections ``A^-1 J^T lam``, then ``q += h qdot``, ``x += h v``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from functools import partial

import jax
import jax.numpy as jnp

from softcrawl.jaxsim import disk as disk_motion
from softcrawl.jaxsim import legs as leg_motion
from softcrawl.jaxsim.contact import floor_contacts, solve_constraints
from softcrawl.jaxsim.model import register_pytree

#: The engine's numerical version: changes whenever a step's result changes (caches of settled
#: states built by an engine of another version are stale).
ENGINE_VERSION = 1
#: Floor contact frame, rows normal, tangent 1, tangent 2 (:mod:`softcrawl.fem.solver`).
FLOOR_FRAME = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
#: z given to the collision points of absent legs (mm): never a contact.
FAR = 1e6


@dataclass(frozen=True)
class State:
    """One robot's state (a leading batch axis on every field when batched).

    Attributes:
        q, qdot: ``(L, m)`` legs' modal displacements (mm) and velocities (mm/s), part frame.
        x, v: ``(n, 3)`` disk node positions (mm) and velocities (mm/s).
        contact_points: ``(K,)`` last step's contact points (index into the disk's collision
            nodes, then each leg slot's); impulses: ``(K, 3)`` their impulses, mN s.
        pressure: ``(R,)`` regulator outputs, real kPa (``R = settings.channels``); t: time, s.
        bad: inverted or degenerate RID elements met so far (0 for a valid rollout).
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


def _leg_points(leg, rd, q, qdot):
    """World positions and velocities ``(L nc, 3)`` of the legs' collision nodes (absent legs far up)."""
    x = jnp.einsum("lnc,lac->lna", leg.coll_rest[None] + jnp.einsum("nam,lm->lna", leg.coll_basis, q), rd.rotation)
    x = x + rd.translation[:, None]
    v = jnp.einsum("lnc,lac->lna", jnp.einsum("nam,lm->lna", leg.coll_basis, qdot), rd.rotation)
    x = jnp.where(rd.leg_mask[:, None, None], x, jnp.asarray([0.0, 0.0, FAR], x.dtype))
    return x.reshape(-1, 3), v.reshape(-1, 3)


def _disk_gather(inverse, rows_nodes, cols_nodes):
    """Blocks ``A_0^-1[n_p, n_q]`` ``(..., 3, ..., 3)`` of node index arrays."""
    r = 3 * rows_nodes[..., None] + jnp.arange(3)
    c = 3 * cols_nodes[..., None] + jnp.arange(3)
    return inverse[r.reshape(r.shape + (1,) * c.ndim), c.reshape((1,) * r.ndim + c.shape)]


def _attachments(leg, rd, state, v_free, R, h):
    """Rows of the attachment blocks (leg point minus disk point, block ``l F + a``).

    Returns:
        ``(J, W, u, nodes, weights)``: ``(L, 3A, m)`` each leg's share of the rows (modal), the
        disk's share ``(3A, 3A)`` of the Delassus operator, ``(3A,)`` the disk's free velocities
        plus the drift ``(x_a - x_b) / h`` (mm/s), and the disk points' nodes and weights ``(A, 4)``.
    """
    L, m = state.q.shape
    F = leg.att_rest.shape[0]
    A = L * F
    Ja = jnp.einsum("lac,fcm->lfam", rd.rotation, leg.att_basis) * rd.leg_mask[:, None, None, None]
    J = (jnp.eye(L, dtype=Ja.dtype)[:, :, None, None, None] * Ja[None]).reshape(L, 3 * A, m)
    x_leg = jnp.einsum("lfc,lac->lfa", leg.att_rest[None] + jnp.einsum("fam,lm->lfa", leg.att_basis, state.q),
                       rd.rotation) + rd.translation[:, None]
    nodes, w = rd.disk_nodes.reshape(A, -1), rd.disk_weights.reshape(A, -1)
    drift = (x_leg.reshape(A, 3) - jnp.einsum("ai,aic->ac", w, state.x[nodes])) * jnp.repeat(rd.leg_mask, F)[:, None]
    u = (drift / h - jnp.einsum("ai,aic->ac", w, v_free[nodes])).reshape(-1)
    W = jnp.einsum("ab,pqbc,dc->paqd", R, rd.att_gram, R).reshape(3 * A, 3 * A)
    return J, W, u, nodes, w


def _select_contacts(model, state, v_free, qd_free):
    """The ``K`` contact points of this step: the disk's and each leg's own lowest predicted
    gaps, last step's loaded points first (:func:`softcrawl.jaxsim.contact.floor_contacts` on
    the points with those lowered by :data:`FAR`).

    Each body gets its own rows, so that one body's landing cannot take the others'; loaded
    points stay, as in the CPU engine's contact set: a leg lying on its paper face has more
    points at the floor than rows, and a set redrawn every step chatters.

    Returns:
        ``(idx, active, gap)``: ``(K,)`` point indices (disk collision nodes, then each leg
        slot's), whether each is a candidate, its current gap (mm).
    """
    st, leg, dk, rd = model.settings, model.leg, model.disk, model.robot
    L = state.q.shape[0]
    nd, nc = dk.collision.shape[0], leg.coll_rest.shape[0]
    xl, vl = _leg_points(leg, rd, state.q, qd_free)
    points = jnp.concatenate([state.x[dk.collision], xl])
    vel = jnp.concatenate([v_free[dk.collision], vl])
    pts = jnp.where(state.contact_points >= 0, state.contact_points, points.shape[0])
    loaded = jnp.zeros(points.shape[0], bool).at[pts].max(state.impulses[:, 0] > 0, mode="drop")
    ranked = points.at[:, 2].add(jnp.where(loaded, -FAR, 0.0))
    select = partial(floor_contacts, floor_z=st.floor_z, distance=st.contact_distance, dt=st.dt)
    i_d, a_d, _ = select(ranked[:nd], vel[:nd], K=st.disk_contacts)
    i_l, a_l, _ = jax.vmap(partial(select, K=st.leg_contacts))(ranked[nd:].reshape(L, nc, 3),
                                                             vel[nd:].reshape(L, nc, 3))
    idx = jnp.concatenate([i_d, (i_l + nd + nc * jnp.arange(L)[:, None]).reshape(-1)])
    return idx, jnp.concatenate([a_d, a_l.reshape(-1)]), points[idx, 2] - st.floor_z


def _contact_rows(model, idx, gap, v_free, R, att_nodes, att_weights):
    """Rows of the contact blocks (frame :data:`FLOOR_FRAME`) at points ``idx``.

    Returns:
        ``(J, W_ac, W_cc, u, disk_node, on_disk)``: ``(L, 3K, m)`` each leg's share (modal),
        the disk's share of the Delassus operator against the attachments ``(3A, 3K)`` and
        among the contacts ``(3K, 3K)``, ``(3K,)`` the disk's free velocities plus the gap term
        ``g / h`` (normal rows), and each contact's disk node and whether it is on the disk.
    """
    st, leg, dk, rd = model.settings, model.leg, model.disk, model.robot
    L, m = rd.rotation.shape[0], leg.coll_basis.shape[2]
    K, A = idx.shape[0], att_nodes.shape[0]
    nd, nc = dk.collision.shape[0], leg.coll_rest.shape[0]
    dt = v_free.dtype
    on_disk = idx < nd
    wc = on_disk.astype(dt)
    node = dk.collision[jnp.where(on_disk, idx, 0)]
    lidx = jnp.where(on_disk, 0, (idx - nd) // nc)
    lnode = jnp.where(on_disk, 0, (idx - nd) % nc)
    D = jnp.asarray(FLOOR_FRAME, dt)
    DR = D @ R
    Jc = jnp.einsum("ab,kbc,kcm->kam", D, rd.rotation[lidx], leg.coll_basis[lnode]) * (1 - wc)[:, None, None]
    J = ((lidx[None, :] == jnp.arange(L)[:, None]).astype(dt)[:, :, None, None] * Jc[None]).reshape(L, 3 * K, m)
    W_cc = jnp.einsum("ab,pbqc,dc->paqd", DR, _disk_gather(dk.inverse, node, node), DR)
    W_cc = (W_cc * (wc[:, None, None, None] * wc[None, None, :, None])).reshape(3 * K, 3 * K)
    W_ac = -jnp.einsum("ai,xb,aibkc,dc->axkd", att_weights, R, _disk_gather(dk.inverse, att_nodes, node), DR)
    W_ac = (W_ac * wc[None, None, :, None]).reshape(3 * A, 3 * K)
    u = (jnp.einsum("ab,kb->ka", D, v_free[node]) * wc[:, None]).at[:, 0].add(gap / st.dt)
    return J, W_ac, W_cc, u.reshape(-1), node, wc


def physics_step(model, state: State, sim_kpa) -> State:
    """One ``dt`` of one robot at cavity pressures ``sim_kpa`` ``(R,)`` (sim kPa per regulator);
    the regulators are not stepped (module doc, steps 2-4).

    Matrix products run at the arrays' full precision (``jax.default_matmul_precision("float32")``
    while tracing): a GPU's default for float32 products, TF32 (10-bit mantissa), is too coarse for
    the step and inverts elements (``benchmarks/RESULTS.md``, the JAX engine). On a CPU the setting
    changes nothing."""
    with jax.default_matmul_precision("float32"):
        return _physics_step(model, state, sim_kpa)


def _physics_step(model, state: State, sim_kpa) -> State:
    st, leg, dk, rd = model.settings, model.leg, model.disk, model.robot
    h = st.dt
    dt = state.x.dtype
    L = state.q.shape[0]
    K = n_contacts(st, L)
    # 2. free motion
    qd_free, chol, n_bad = jax.vmap(leg_motion.free_motion, in_axes=(None, None, 0, 0, 0, 0, 0))(
        leg, st, state.q, state.qdot, rd.rotation, sim_kpa[rd.channel] * rd.leg_mask, rd.leg_mask)
    v_free, R = disk_motion.free_motion(dk, st, state.x, state.v)
    # 3. constraints: attachments, then contacts; the legs' share of W through their factors
    J, W, u, att_nodes, att_w = _attachments(leg, rd, state, v_free, R, h)
    nb = u.shape[0]
    warm, active = jnp.zeros(0, dt), jnp.zeros(0, bool)
    if K:
        idx, active, gap = _select_contacts(model, state, v_free, qd_free)
        Jc, W_ac, W_cc, u_c, c_node, on_disk = _contact_rows(model, idx, gap, v_free, R, att_nodes, att_w)
        J = jnp.concatenate([J, Jc], axis=1)
        W = jnp.block([[W, W_ac], [W_ac.T, W_cc]])
        u = jnp.concatenate([u, u_c])
        warm = ((idx[:, None] == state.contact_points[None, :]).astype(dt) @ state.impulses).reshape(-1)
    Y = jax.vmap(lambda c, j: jax.scipy.linalg.solve_triangular(c, j.T, lower=True))(chol, J)
    W = W + jnp.einsum("lmi,lmj->ij", Y, Y)
    u = u + jnp.einsum("lim,lm->i", J, qd_free)
    # attachments of distinct nodes: W_bb is positive definite, no least-squares fallback needed
    lam = solve_constraints(W, u, jnp.repeat(rd.leg_mask, nb // L), jnp.full((K,), st.friction, dt), warm,
                            active, st.sweeps, least_squares=False)
    # 4. corrections: legs A_l^-1 J_l^T lam, the disk A_0^-1 of its body-frame impulses
    dq = jax.vmap(lambda c, j: jax.scipy.linalg.cho_solve((c, True), j.T @ lam))(chol, J)
    lam_a = lam[:nb].reshape(-1, 3)
    f_body = jnp.zeros_like(state.x).at[att_nodes.reshape(-1)].add(
        (-att_w[:, :, None] * (lam_a @ R)[:, None, :]).reshape(-1, 3))
    if K:
        lam_c = lam[nb:].reshape(K, 3)
        f_body = f_body.at[c_node].add(on_disk[:, None] * (lam_c @ (jnp.asarray(FLOOR_FRAME, dt) @ R)))
    v = v_free + (dk.inverse @ f_body.reshape(-1)).reshape(-1, 3) @ R.T
    qdot = qd_free + dq
    new = dataclasses.replace(
        state, q=state.q + h * qdot, qdot=qdot, x=state.x + h * v, v=v, t=state.t + h,
        bad=(state.bad + jnp.sum(n_bad * rd.leg_mask) + (~jnp.all(jnp.isfinite(v)))).astype(state.bad.dtype))
    if K:
        new = dataclasses.replace(new, contact_points=idx.astype(jnp.int32), impulses=lam_c)
    return new


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
        return jax.vmap(one, in_axes=(None, 0, 0))(dataclasses.replace(model, robot=None), model.robot, state)

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
        return jax.vmap(one, in_axes=(None, 0, 0, 0))(dataclasses.replace(model, robot=None), model.robot, state,
                                                      control)

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
        return jax.vmap(one, in_axes=(None, 0, 0, 0))(dataclasses.replace(model, robot=None), model.robot, state,
                                                      schedule)

    return rollout
