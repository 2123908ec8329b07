"""Each body's floor contact candidates in one GPU kernel (Pallas, Triton form).

:func:`softcrawl.jaxsim.delassus.select_contacts` gives each body (the disk, each leg slot) the
``K`` points of smallest predicted gap among its collision points, last step's loaded points
first (lowered by :data:`~softcrawl.jaxsim.delassus.FAR`), in point order
(:func:`softcrawl.jaxsim.contact.floor_contacts`). XLA's program does it for all bodies at once:
the loaded points scattered into a mask over every point, the ranked heights sliced per body,
the legs' selection in two stages of sorts (:func:`~softcrawl.jaxsim.contact.smallest_k`), the
chosen indices sorted, the gaps gathered: most of the constraint rows' kernels on a GPU.
:func:`body_candidates` does one body's selection in one program: its points' heights
and vertical velocities read once, its own slots of last step's contacts as the loaded points
(a body's slots hold its own points only), then ``K`` rounds of the smallest predicted gap (of
equal ones the lowest index, as ``lax.top_k`` orders them) and the chosen points stored in point
order. The same choice as XLA's, arithmetic included (tested in Pallas' interpreter); a batch of
bodies under ``jax.vmap`` is one program a body. Compiled for an H100, the step has 7 operations
fewer at 96 and 16,384 robots and moves 0.37 MB less a robot-step (``benchmarks/RESULTS.md``).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax

from softcrawl.jaxsim.factor import padded_size

#: How :func:`softcrawl.jaxsim.delassus.select_contacts` chooses the candidates: ``"xla"`` (the
#: default; every platform), ``"kernel"`` (:func:`body_candidates` on CUDA, ``"xla"`` elsewhere)
#: or ``"interpret"`` (the kernel in Pallas' interpreter, any platform: the tests'). Read when a
#: step is traced.
SELECTION = "xla"
#: Warps a body's program: a leg's 1,179 points padded to 2,048 are 16 a thread.
NUM_WARPS = 4
#: Lanes of a program's choices: ``K`` at most this.
_LANES = 16


def _kernel(P: int, K: int, far: float, floor_z: float, distance: float, dt: float,
            z_ref, vz_ref, prev_ref, held_ref, idx_ref, act_ref, gap_ref):
    """One body: ``z_ref``, ``vz_ref`` ``(P,)`` its points' heights (mm) and vertical free
    velocities (mm/s); ``prev_ref`` ``(K,)`` its slots' points of last step (-1: none) and
    ``held_ref`` ``(K,)`` whether each bore a normal impulse (int32); ``idx_ref``, ``act_ref``,
    ``gap_ref`` ``(K,)`` receive the chosen points in point order, whether each is within the
    contact distance (int32) and its gap (mm). The program works on ``N`` lanes (``P`` padded to
    a power of two) and ``16`` lanes for the ``K <= 16`` choices."""
    from jax.experimental.pallas import triton as pltriton

    N = padded_size(P)
    i = lax.iota(jnp.int32, N)
    inside = i < P
    z = pltriton.load(z_ref.at[i], mask=inside, other=0.0)
    vz = pltriton.load(vz_ref.at[i], mask=inside, other=0.0)
    loaded = jnp.zeros((N,), jnp.bool_)
    for k in range(K):
        loaded = loaded | ((i == prev_ref[k]) & (held_ref[k] != 0))
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
    a, b = chosen[:, None], chosen[None, :]  # [choice, other choice]
    earlier = (b < a) | ((b == a) & (lane[None, :] < lane[:, None]))
    rank = jnp.sum((earlier & valid[None, :]).astype(jnp.int32), axis=1, dtype=jnp.int32)
    at = (rank[None, :] == lane[:, None]) & valid[None, :]  # [place, choice]
    chosen = jnp.sum(jnp.where(at, chosen[None, :], 0), axis=1, dtype=jnp.int32)
    value = jnp.sum(jnp.where(at, value[None, :], 0), axis=1)
    pltriton.store(idx_ref.at[lane], chosen, mask=valid)
    pltriton.store(act_ref.at[lane], (value < distance).astype(jnp.int32), mask=valid)
    heights = pltriton.load(z_ref.at[chosen], mask=valid, other=0.0)
    pltriton.store(gap_ref.at[lane], heights - floor_z, mask=valid)


def body_candidates(z, vz, prev, held, *, K: int, far: float, floor_z: float, distance: float, dt: float,
                    interpret: bool = False):
    """One body's ``K`` floor contact candidates (module doc) in one kernel.

    Args:
        z, vz: ``(P,)`` its collision points' heights (mm) and free vertical velocities (mm/s).
        prev: ``(K,)`` int, the points its contact slots held last step (-1: none); held: ``(K,)``
            bool, whether each bore a normal impulse (those points are lowered by ``far``, mm,
            so that they stay).
        K: slots (static, ``K <= min(P, 16)``); floor_z, distance: mm; dt: s.
        interpret: run the kernel in Pallas' interpreter instead of compiling it for a GPU.

    Returns:
        ``(idx (K,) int32, active (K,) bool, gap (K,))``: the chosen points in point order,
        whether each one's predicted gap ``min(g, g + dt v_z)`` (of the lowered heights) is below
        ``distance``, and its gap ``z - floor_z``, mm (of its own height).

    Raises:
        ValueError: ``K`` above ``P`` or 16, or arrays of other lengths.
    """
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    P = z.shape[0]
    if not 0 < K <= min(P, _LANES) or vz.shape != (P,) or prev.shape != (K,) or held.shape != (K,):
        raise ValueError(f"body_candidates needs 0 < K <= min(P, {_LANES}) and (P,) z and vz, (K,) prev and held; got "
                         f"K = {K}, {z.shape}, {vz.shape}, {prev.shape}, {held.shape}")
    out = jax.ShapeDtypeStruct((K,), jnp.int32)
    idx, act, gap = pl.pallas_call(
        partial(_kernel, P, K, float(far), float(floor_z), float(distance), float(dt)),
        out_shape=(out, out, jax.ShapeDtypeStruct((K,), z.dtype)), interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        name="contact_candidates",
    )(z, vz.astype(z.dtype), prev.astype(jnp.int32), held.astype(jnp.int32))
    return idx, act != 0, gap
