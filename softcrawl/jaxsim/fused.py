"""The accelerated gradient's iterations for one robot's contacts in one GPU kernel (Pallas).

:func:`softcrawl.jaxsim.contact.apgd_coulomb`'s unrolled iterations compile, on a GPU, to a
matrix-vector product and a fused elementwise loop per iteration: 48 iterations are about a
hundred kernels in sequence, each reading the Delassus operator from memory again. At a few
dozen robots a step's latency is the count of its kernels; at thousands, the bytes moved
(``benchmarks/RESULTS.md``). :func:`fused_iterations` runs all the iterations of one robot in one
program of one kernel (a batch of robots under ``jax.vmap``: one program per robot): the operator
comes from device memory once, and each iteration reads it again from the cache (128 KB a robot
in float16).

The iteration is :func:`~softcrawl.jaxsim.contact.apgd_coulomb`'s with ``restart=False`` and a
reduced-precision ``storage`` (Mazhar et al. 2015 with De Saxce's change; iterative refinement as
there), row by row on the contacts' interleaved rows ``(normal, tangent 1, tangent 2)``: with
``y`` the extrapolated iterate,

    u = Ws~ y + g0;   u_n += mu |u_t|;   z = y - step u;   x' = P(z);   y = x' + beta (x' - x)

A row's contact's three components of ``u`` and ``y`` (for De Saxce's term and the cone
projection ``P``, which need all three) are read back from scratch vectors the program stores and
reads again after a barrier, one an iteration: a gather within the program, where XLA's program
needs a reshape of the whole vector.

The kernel is Pallas' Triton form (``jax.experimental.pallas.triton``; JAX marks it deprecated
in favour of Mosaic GPU, and keeps it): one program per robot, :data:`NUM_WARPS` warps, the
operator ``(N, N)`` in its storage dtype (``N`` the rows padded to a power of two, 256 for the
paper preset's 80 contacts) multiplied :data:`ROW_BLOCK` rows at a time. Where JAX has no GPU
(``interpret=True``, the tests on a CPU) the same kernel runs in Pallas' interpreter.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import pallas as pl

#: Warps per program, and rows of the operator a program multiplies at once: a block's numbers
#: are spread over the program's registers, and too large a block (the whole operator at any
#: warp count) spills them to local memory (ptxas' counts for an H100: benchmarks/RESULTS.md,
#: ``step_cost.py --gpu-target ... --registers``). Read when a solve is traced:
#: ``benchmarks/fused_kernel.py`` times the variants (each after ``jax.clear_caches()``).
NUM_WARPS = 8
ROW_BLOCK = 32


def _padded(n: int) -> int:
    """The smallest power of two ``>= max(n, 16)``: Triton's blocks have power-of-two shapes."""
    return max(16, 1 << (int(n) - 1).bit_length())


def _kernel(n_iter: int, barrier, row_block: int, w_ref, v_ref, b_ref, x_ref, su_ref, sy_ref):
    """One robot's iterations (module doc): ``w_ref`` ``(N, N)`` the reduced operator (read
    ``row_block`` rows at a time, every iteration: after the first from the cache),
    ``v_ref`` ``(8, N)`` rows ``g0, x0, mu, live, step``, ``b_ref`` the extrapolation weights;
    ``x_ref`` receives the last iterate. An iteration stores ``u`` and ``y`` into the scratch
    ``su_ref`` and ``sy_ref`` ``(2, N)``, slot ``k % 2``, and reads back its contact's three
    components of each after ``barrier()`` (the program's threads' stores made visible to all
    of them): one barrier an iteration, the two slots keeping an iteration's stores from
    overwriting what a slower thread still reads of the last."""
    N = w_ref.shape[-1]
    dt = v_ref.dtype
    x0, mu, step = v_ref[1, :], v_ref[2, :], v_ref[4, :]
    live = v_ref[3, :] > 0
    i = lax.iota(jnp.int32, N)
    base = 3 * (i // 3)
    normal, tangent1 = i == base, i == base + 1
    i1, i2 = jnp.minimum(base + 1, N - 1), jnp.minimum(base + 2, N - 1)
    tiny = jnp.finfo(dt).tiny

    def body(k, c):
        x, y = c
        slot = lax.rem(k, 2)
        sy_ref[slot, :] = y
        for r0 in range(0, N, row_block):  # u = Ws~ y + g0, by blocks of rows
            rows = pl.ds(r0, row_block)
            su_ref[slot, rows] = jnp.sum(w_ref[rows, :].astype(dt) * y[None, :], axis=1) + v_ref[0, rows]
        barrier()
        u1, u2 = su_ref[slot, i1], su_ref[slot, i2]
        # z = y - step u after De Saxce's change, this row's contact's three components
        n = sy_ref[slot, base] - step * (su_ref[slot, base] + mu * jnp.sqrt(u1 * u1 + u2 * u2))
        t1, t2 = sy_ref[slot, i1] - step * u1, sy_ref[slot, i2] - step * u2
        # project_cone's arithmetic on this row's contact
        s = t1 * t1 + t2 * t2
        r = lax.rsqrt(jnp.maximum(s, tiny))
        nt = s * r
        inside = nt <= mu * n
        ln = jnp.where(inside, n, jnp.maximum((n + mu * nt) / (1 + mu * mu), 0))
        own = jnp.where(tangent1, t1, t2)
        xn = jnp.where(live, jnp.where(normal, ln, own * jnp.where(inside, 1, mu * ln * r)), 0)
        beta = b_ref[k]
        return xn, xn + beta * (xn - x)

    x_ref[...] = lax.fori_loop(0, n_iter, body, (x0, x0))[0]


@partial(jax.jit, static_argnames=("interpret",))
def fused_iterations(Wi, g0, x0, mu, live, step, betas, *, interpret: bool = False):
    """The accelerated gradient's iterations of one robot in one kernel (module doc).

    Args:
        Wi: ``(n, n)`` the scaled Delassus operator in its storage dtype (float16), rows and
            columns interleaved by contact (normal, tangent 1, tangent 2), ``n = 3K``.
        g0: ``(n,)`` the refinement's constant ``(Ws - Ws~) x0 + S q``, mm/s scaled, float32 or
            float64: the iterations' precision.
        x0: ``(n,)`` the projected warm start.
        mu: ``(n,)`` each row's contact's friction coefficient.
        live: ``(n,)`` bool, False on the rows of padding contacts (their iterate stays 0).
        step: the step ``1 / L`` (a scalar).
        betas: ``(n_iter,)`` the extrapolation weights
            (:func:`softcrawl.jaxsim.contact.momentum_schedule`).
        interpret: run the kernel in Pallas' interpreter (any platform) instead of compiling it
            for a GPU.

    Returns:
        ``(n,)`` the last iterate ``x``, in ``g0``'s dtype.

    Raises:
        ValueError: ``n`` not a multiple of 3, or arrays of other lengths.
    """
    from jax.experimental.pallas import triton as pltriton

    n = Wi.shape[0]
    if n % 3 or Wi.shape != (n, n) or any(a.shape != (n,) for a in (g0, x0, mu, live)):
        raise ValueError(f"fused_iterations needs a (3K, 3K) operator and (3K,) vectors, got {Wi.shape}, "
                         f"{[a.shape for a in (g0, x0, mu, live)]}")
    N, dt = _padded(n), g0.dtype
    n_iter = betas.shape[0]
    Wp = jnp.zeros((N, N), Wi.dtype).at[:n, :n].set(Wi)
    v = jnp.zeros((8, N), dt).at[:5, :n].set(jnp.stack([g0, x0, mu, live, jnp.broadcast_to(step, (n,))]).astype(dt))
    b = jnp.zeros(_padded(n_iter), dt).at[:n_iter].set(betas.astype(dt))
    scratch = jax.ShapeDtypeStruct((2, N), dt)
    x, _, _ = pl.pallas_call(
        partial(_kernel, n_iter, (lambda: None) if interpret else pltriton.debug_barrier, min(ROW_BLOCK, N)),
        out_shape=(jax.ShapeDtypeStruct((N,), dt), scratch, scratch),
        interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        name="apgd_iterations",
    )(Wp, v, b)
    return x[:n]
