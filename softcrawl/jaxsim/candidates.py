"""Each body's floor contact candidates in one GPU kernel (Pallas, Triton form).

:func:`softcrawl.jaxsim.delassus.select_contacts` gives each body (the disk, each leg slot) the
``K`` points of smallest predicted gap among its collision points, last step's loaded points
first (lowered by :data:`~softcrawl.jaxsim.delassus.FAR`), in point order
(:func:`softcrawl.jaxsim.contact.floor_contacts`). XLA's program does it for all bodies at once:
the loaded points scattered into a mask over every point, the ranked heights sliced per body,
the legs' selection in two stages of sorts (:func:`~softcrawl.jaxsim.contact.smallest_k`), the
chosen indices sorted, the gaps gathered: most of the constraint rows' kernels on a GPU.
:func:`robot_candidates` does one robot's selection in one kernel, one program a body: its
points' heights and vertical velocities read once (the disk's gathered from its nodes, the legs'
as their height product writes them, shifted and masked in the program), its own slots of last
step's contacts as the loaded points (a body's slots hold its own points only), then ``K``
rounds of the smallest predicted gap (of equal ones the lowest index, as ``lax.top_k`` orders
them) and the chosen points written in point order into the robot's slots, each with its
impulse of last step where it was a contact then (the contact solve's warm start, which XLA
forms by a product with a ``K x K`` matrix of matches). The same choice as XLA's, arithmetic
included (tested in Pallas' interpreter). Compiled for an H100, the step has 16 operations
fewer at 96 and 16,384 robots and moves 0.55 MB less a robot-step (``benchmarks/RESULTS.md``).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax

from softcrawl.jaxsim.factor import padded_size

#: How :func:`softcrawl.jaxsim.delassus.select_contacts` chooses the candidates: ``"xla"`` (the
#: default; every platform), ``"kernel"`` (:func:`robot_candidates` on CUDA, ``"xla"`` elsewhere)
#: or ``"interpret"`` (the kernel in Pallas' interpreter, any platform: the tests'). Read when a
#: step is traced.
SELECTION = "xla"
#: The values :data:`SELECTION` may take.
SELECTIONS = ("xla", "kernel", "interpret")
#: Warps a body's program: a leg's 1,179 points padded to 2,048 are 16 a thread.
NUM_WARPS = 4
#: Lanes of a program's choices: ``K`` at most this.
_LANES = 16


def _choose(P: int, K: int, far: float, floor_z: float, distance: float, dt: float, heights, velocities,
            first: int, offset, pts_ref, imp_ref, idx_ref, act_ref, gap_ref, warm_ref):
    """One body's choice (module doc) in a program: ``heights(points, mask)`` and
    ``velocities(points, mask)`` its ``P`` points' heights (mm) and free vertical velocities
    (mm/s); its ``K`` slots are ``first ..`` of the robot's, whose last step's points
    ``pts_ref`` (-1: none) are its own ``offset`` on and ``imp_ref`` their impulses; writes its
    slots of ``idx_ref`` (the robot's point indices), ``act_ref`` (int32), ``gap_ref`` (mm) and
    ``warm_ref`` (each chosen point's impulse of last step, 0 where it had no slot).
    ``N`` lanes (``P`` padded to a power of two) and ``16`` for the choices."""
    from jax.experimental.pallas import triton as pltriton

    N = padded_size(P)
    i = lax.iota(jnp.int32, N)
    inside = i < P
    z, vz = heights(i, inside), velocities(i, inside)
    loaded = jnp.zeros((N,), jnp.bool_)
    for k in range(K):
        p = pts_ref[first + k]
        loaded = loaded | ((i == p - offset) & (p >= 0) & (imp_ref[first + k, 0] > 0))
    gap = (z - jnp.where(loaded, far, 0.0)) - floor_z  # floor_contacts' gap of the ranked heights
    pred = jnp.where(inside, jnp.minimum(gap, gap + dt * vz), jnp.inf)
    lane = lax.iota(jnp.int32, _LANES)
    chosen, value = jnp.zeros((_LANES,), jnp.int32), jnp.zeros((_LANES,), z.dtype)
    for k in range(K):  # the smallest, of equal ones the lowest index (in range whatever NaN the values hold)
        m = jnp.min(pred)
        j = jnp.minimum(jnp.min(jnp.where(pred == m, i, N)), P - 1)
        chosen, value = jnp.where(lane == k, j, chosen), jnp.where(lane == k, m, value)
        pred = jnp.where(i == j, jnp.inf, pred)
    valid = lane < K
    # each choice's place in point order (ties by round: a permutation of 0 .. K - 1 in any case),
    # then the choices in that order, lane by lane (one store of consecutive lanes, no scatter)
    a, c = chosen[:, None], chosen[None, :]  # [choice, other choice]
    earlier = (c < a) | ((c == a) & (lane[None, :] < lane[:, None]))
    rank = jnp.sum((earlier & valid[None, :]).astype(jnp.int32), axis=1, dtype=jnp.int32)
    at = (rank[None, :] == lane[:, None]) & valid[None, :]  # [place, choice]
    chosen = jnp.sum(jnp.where(at, chosen[None, :], 0), axis=1, dtype=jnp.int32)
    value = jnp.sum(jnp.where(at, value[None, :], 0), axis=1)
    pltriton.store(idx_ref.at[first + lane], chosen + offset, mask=valid)
    pltriton.store(act_ref.at[first + lane], (value < distance).astype(jnp.int32), mask=valid)
    pltriton.store(gap_ref.at[first + lane], heights(chosen, valid) - floor_z, mask=valid)
    # the warm start: a chosen point's impulse from its slot of last step (the body's own slots)
    warm = [jnp.zeros((_LANES,), z.dtype) for _ in range(3)]
    for k in range(K):
        kept = chosen + offset == pts_ref[first + k]
        warm = [jnp.where(kept, imp_ref[first + k, c], w) for c, w in enumerate(warm)]
    for c, w in enumerate(warm):
        pltriton.store(warm_ref.at[first + lane, c], w, mask=valid)


def _kernel(nd: int, Kd: int, nc: int, Kl: int, rule: tuple, coll_ref, x_ref, v_ref, legs_ref, t_ref, on_ref,
            pts_ref, imp_ref, idx_ref, act_ref, gap_ref, warm_ref):
    """One robot's body ``b`` (the program's index): the disk (``b = 0``, its ``nd`` collision
    nodes ``coll_ref`` among the nodes' positions ``x_ref`` and free velocities ``v_ref`` ``(n,
    3)``) or leg ``b - 1`` (its ``nc`` points' heights before its translation and their
    velocities in ``legs_ref`` ``(2, L, nc)``, its translation ``t_ref`` ``(L, 3)``, whether it
    exists ``on_ref`` ``(L,)`` int32: an absent leg's points lie at ``far``); ``rule`` ``(far,
    floor_z, distance, dt)``; the rest as :func:`_choose`."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    b = pl.program_id(0)
    out = (pts_ref, imp_ref, idx_ref, act_ref, gap_ref, warm_ref)

    def disk(field_ref):
        def read(points, mask):
            node = pltriton.load(coll_ref.at[points], mask=mask, other=0)
            return pltriton.load(field_ref.at[node, 2], mask=mask, other=0.0)
        return read

    if Kd:
        pl.when(b == 0)(lambda: _choose(nd, Kd, *rule, disk(x_ref), disk(v_ref), 0, 0, *out))
    if Kl:
        def leg():
            l = b - 1
            on, shift = on_ref[l] != 0, t_ref[l, 2]

            def heights(points, mask):
                return jnp.where(on, pltriton.load(legs_ref.at[0, l, points], mask=mask, other=0.0) + shift, rule[0])

            def velocities(points, mask):
                return pltriton.load(legs_ref.at[1, l, points], mask=mask, other=0.0)

            _choose(nc, Kl, *rule, heights, velocities, Kd + Kl * l, nd + nc * l, *out)

        pl.when(b > 0)(leg)


def robot_candidates(collision, x, v, legs, translation, present, points, impulses, *, Kd: int, Kl: int, far: float,
                     floor_z: float, distance: float, dt: float, interpret: bool = False):
    """One robot's floor contact candidates (module doc), one program a body: the disk's ``K_d``
    and each leg slot's ``K_l``, as :func:`softcrawl.jaxsim.delassus.select_contacts` chooses
    them.

    Args:
        collision: ``(nd,)`` the disk's collision nodes; x, v: ``(n, 3)`` its nodes' positions
            (mm) and free velocities (mm/s).
        legs: ``(2, L, nc)`` the legs' collision points' heights before their translation (mm),
            then their free vertical velocities (mm/s)
            (:func:`softcrawl.jaxsim.delassus.leg_height_terms`, read as it writes them);
            translation: ``(L, 3)`` each leg's placement's translation (mm; its heights are
            ``legs[0] + translation[:, 2]``); present: ``(L,)`` bool, whether each leg exists
            (an absent leg's points lie at ``far``).
        points: ``(K,)`` int, last step's contact points (the disk's slots, then each leg's; -1:
            none), the robot's indices (the disk's collision points, then each leg's); impulses:
            ``(K, 3)`` theirs (those with a normal impulse are lowered by ``far``, mm, so that
            they stay).
        Kd, Kl: the disk's and each leg's slots (static, at most 16 and at most its points);
        floor_z, distance: mm; dt: s.
        interpret: run the kernel in Pallas' interpreter instead of compiling it for a GPU.

    Returns:
        ``(idx (K,) int32, active (K,) bool, gap (K,), warm (K, 3))``: each body's chosen points
        in point order (the robot's indices), whether each one's predicted gap ``min(g, g + dt
        v_z)`` (of the lowered heights) is below ``distance``, its gap ``z - floor_z``, mm (of its
        own height), and its impulse of last step where it was a contact then (0 else), mN s: the
        contact solve's warm start.

    Raises:
        ValueError: a body with more slots than 16 or than its points, or arrays of other shapes.
    """
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    nd, (_, L, nc) = collision.shape[0], legs.shape
    K = Kd + L * Kl
    if (Kd > min(nd, _LANES) or Kl > min(nc, _LANES) or legs.shape[0] != 2 or translation.shape != (L, 3)
            or present.shape != (L,) or points.shape != (K,) or impulses.shape != (K, 3)):
        raise ValueError(f"robot_candidates needs at most min(points, {_LANES}) slots a body, (2, L, nc) legs, "
                         f"(L, 3) translation, (L,) present, (K,) points and (K, 3) impulses; got Kd = {Kd} of {nd}, "
                         f"Kl = {Kl} of {nc}, {legs.shape}, {translation.shape}, {present.shape}, {points.shape}, "
                         f"{impulses.shape}")
    dt_ = legs.dtype
    idx, act, gap, warm = pl.pallas_call(
        partial(_kernel, nd, Kd, nc, Kl, (float(far), float(floor_z), float(distance), float(dt))),
        out_shape=(jax.ShapeDtypeStruct((K,), jnp.int32), jax.ShapeDtypeStruct((K,), jnp.int32),
                   jax.ShapeDtypeStruct((K,), dt_), jax.ShapeDtypeStruct((K, 3), dt_)),
        grid=(1 + L,), interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        name="contact_candidates",
    )(collision.astype(jnp.int32), x.astype(dt_), v.astype(dt_), legs, translation.astype(dt_),
      present.astype(jnp.int32), points.astype(jnp.int32), impulses.astype(dt_))
    return idx, act != 0, gap, warm
