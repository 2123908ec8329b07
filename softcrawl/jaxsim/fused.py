"""The accelerated gradient's solve of one robot's contacts in one GPU kernel (Pallas).

:func:`softcrawl.jaxsim.contact.apgd_coulomb`'s unrolled iterations compile, on a GPU, to a
matrix-vector product and a fused elementwise loop per iteration: 48 iterations are about a
hundred kernels in sequence, each reading the Delassus operator from memory again, after half a
dozen more that scale the operator, round it to float16 and form the refinement's constant. At a
few dozen robots a step's latency is the count of its kernels; at thousands, the bytes moved
(``benchmarks/RESULTS.md``). :func:`fused_solve` runs all of it for one robot in one program of
one kernel (a batch of robots under ``jax.vmap``: one program per robot): the operator comes
from device memory once, in its own precision, whole or in the parts the step forms it from
(:class:`~softcrawl.jaxsim.schur.SchurOperator`, :data:`OPERATOR_PARTS`: each entry formed as it
is read, so that the formed operator never passes through memory); the program writes its
scaled float16 copy (128 KB a robot) and each iteration reads that again from the cache, or,
with :data:`RESIDENT_ROWS`, reads it once more and keeps it on chip, multiplying it on the
tensor cores.

The solve is :func:`~softcrawl.jaxsim.contact.apgd_coulomb`'s with ``restart=False`` and a
reduced-precision ``storage`` (Mazhar et al. 2015 with De Saxce's change; iterative refinement as
there), row by row on the contacts' interleaved rows ``(normal, tangent 1, tangent 2)``: with
``S`` the per-contact scaling, ``Ws~`` the scaled operator ``S W S`` in the storage dtype, ``x0``
the scaled warm start projected, ``g0 = (Ws - Ws~) x0 + S q``, ``L`` the Gershgorin bound of
``Ws`` and ``y`` the extrapolated iterate,

    u = Ws~ y + g0;   u_n += mu |u_t|;   z = y - u / L;   x' = P(z);   y = x' + beta (x' - x)

and the impulses ``S x``. A row's contact's three components of ``u`` and ``y`` (for De Saxce's
term and the cone projection ``P``, which need all three) are read back from scratch vectors the
program stores and reads again after a barrier, one an iteration: a gather within the program,
where XLA's program needs a reshape of the whole vector.

The kernel is Pallas' Triton form (``jax.experimental.pallas.triton``; JAX marks it deprecated
in favour of Mosaic GPU, and keeps it): one program per robot, :data:`NUM_WARPS` warps, the
operator handled in blocks of :data:`ROW_BLOCK` rows and powers of two after them
(:func:`row_blocks`) by ``N`` columns (``N`` the rows padded to a power of two, 256 for the
paper preset's 80 contacts), read through masked pointers: an iteration reads 240 of the 256
rows and columns for the paper preset, 144 rows of 132 columns for the crawl preset's 44
contacts. Where JAX has no GPU (``interpret=True``, the tests on a CPU) the same kernel runs in
Pallas' interpreter.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import pallas as pl

from softcrawl.jaxsim import gpu
from softcrawl.jaxsim.cone import cone_projection, de_saxce_term
from softcrawl.jaxsim.factor import padded_size
from softcrawl.jaxsim.schur import SchurOperator

#: Warps per program, and rows of the operator a program multiplies at once: a block's numbers
#: are spread over the program's registers, and too large a block (the whole operator at any
#: warp count) spills them to local memory (ptxas' counts for an H100: benchmarks/RESULTS.md,
#: ``step_cost.py --gpu-target ... --registers``). Read when a solve is traced:
#: ``benchmarks/fused_kernel.py`` times the variants (each after ``jax.clear_caches()``). 64 rows
#: at 8 warps (160 registers, no spill) was the fastest of seven on an H200 at 96 robots
#: (benchmarks/RESULTS.md).
NUM_WARPS = 8
ROW_BLOCK = 64
#: Whether an iteration's product runs its blocks of rows as a loop in the program instead of
#: unrolled: fewer registers a thread, so more programs per multiprocessor at large batches, and
#: less overlap of the blocks' loads within a program. Read when a solve is traced, as above.
LOOP_PRODUCT = False
#: Rows a block of the scaled operator that the program holds on chip through the iterations of a
#: float32 solve, or None: the program writes the operator to a scratch output and reads it back
#: from the cache every iteration, by blocks of :data:`ROW_BLOCK` rows (the default, every
#: float64 solve, operators whose float16 copy exceeds :data:`HELD_BYTES`, and cards with less
#: shared memory: :func:`held_bytes`). Held, the
#: blocks are unrolled (:data:`LOOP_PRODUCT` ignored) and each iteration's product is a matrix
#: product on the tensor cores: the float16 block times ``y`` split into two float16 columns, ``y
#: = m (y1 + y2)``, accumulated in float32 (:func:`split_columns`); the blocks cover the padding
#: to ``N`` rows (its rows zeros, not read: the paper preset's 240 rows as two blocks of 128, not
#: 128, 64, 32 and 16), each a whole warpgroup product on an H100; Triton keeps them in shared
#: memory (128 KB) instead of reading them from the cache, 90 GB a step at 16,384 robots.
#: Compiled for an H100 (``benchmarks/kernel_sass.py``, the paper preset's operator in its
#: parts): an iteration is 435 instructions a warp at 128 rows and 8 warps, 646 at 64, against
#: 1,261 for the scratch's (255 registers a thread, no spill in the iterations). Read when a
#: solve is traced, as above.
RESIDENT_ROWS = None
#: Whether the program reads a condensed operator given in its parts
#: (:class:`~softcrawl.jaxsim.schur.SchurOperator`, the engine's) as parts, each entry formed as
#: it is read, or XLA forms the operator first and the program reads it whole: compiled for an
#: H100, the parts take 0.7 MB a robot-step from the step's memory traffic (the formed operator
#: written and read again, 230 KB each) for one more operation at 96 robots and twice the
#: instructions in the preparation before the iterations (``benchmarks/RESULTS.md``). Read when
#: a solve is traced, as above.
OPERATOR_PARTS = True
#: Columns of the operator a program reads at once when it scales and rounds it, before the
#: iterations. Read when a solve is traced, as above.
COLUMN_BLOCK = 64
#: The largest float16 copy of the scaled operator (``N x N``) held on chip: an H100's program
#: has 227 KB of shared memory, of which Triton takes some for its own exchanges; 128 KiB holds
#: ``N = 256`` (up to 85 contacts).
HELD_BYTES = 128 * 1024
#: CUDA compute capabilities whose programs may use 227 KiB of shared memory (the CUDA C++
#: Programming Guide's table of compute capabilities: 9.0, 10.0, 10.3; H100, H200, B200, B300),
#: where the held operator's 128 KiB leave Triton room for its own exchanges. A card of another
#: capability (A100's 163 KiB a program; 99 KiB on 8.6, 8.9 and 12.x: A10, L4, L40, RTX 4090 and
#: 5090) solves with the scratch's form, whatever :data:`RESIDENT_ROWS` asks.
HOLDING_CAPABILITIES = frozenset({(9, 0), (10, 0), (10, 3)})


def held_bytes(interpret: bool = False) -> int:
    """The largest float16 copy of the scaled operator a program holds on chip here, bytes:
    :data:`HELD_BYTES` on a GPU of :data:`HOLDING_CAPABILITIES` (JAX's, or the one a deviceless
    compilation targets: :func:`softcrawl.jaxsim.gpu.compute_capability`), in Pallas'
    interpreter, and where there is none; 0 on any other GPU."""
    capability = gpu.compute_capability()
    if interpret or capability is None:
        return HELD_BYTES
    return HELD_BYTES if capability in HOLDING_CAPABILITIES else 0


def program_rows(n: int, dtype, storage: str = "float16", interpret: bool = False) -> tuple[bool, int]:
    """``(resident, rows)``: whether :func:`fused_solve`'s program holds the scaled ``n x n``
    operator on chip (:data:`RESIDENT_ROWS` set, a float32 solve, its ``storage`` copy padded to
    ``N x N`` within :func:`held_bytes`) and the rows of its blocks (:data:`RESIDENT_ROWS` held,
    :data:`ROW_BLOCK` otherwise, at most ``N``)."""
    N = padded_size(n)
    resident = (RESIDENT_ROWS is not None and jnp.dtype(dtype) == jnp.float32
                and N * N * jnp.dtype(storage).itemsize <= held_bytes(interpret))
    return resident, min(RESIDENT_ROWS if resident else ROW_BLOCK, N)


def row_blocks(n: int, row_block: int) -> tuple[int, list[tuple[int, int]]]:
    """How a program covers ``n`` rows: ``full`` blocks of ``row_block`` rows, then ``tail``, the
    ``(start, size)`` of blocks of the largest powers of two (at least 16) that cover the rest,
    the last masked past ``n``: 240 rows at 64 are 3 blocks and ``[(192, 32), (224, 16)]``, so
    that no row of the padding to ``N = 256`` is read."""
    full = n // row_block
    tail, start = [], full * row_block
    while start < n:
        size = max(16, 1 << ((n - start).bit_length() - 1))
        tail.append((start, size))
        start += size
    return full, tail


def _entries(w_refs):
    """``entries(r, c, mask)``: ``W``'s entries at rows ``r`` and columns ``c`` (broadcast
    together; int32 arrays) where ``mask`` (0 elsewhere), read through masked pointers: from
    ``w_refs`` ``(W,)`` the operator ``(n, n)``, or from its
    :class:`~softcrawl.jaxsim.schur.SchurOperator` parts ``(disk, legs, s_disk, s_legs)``, each
    entry ``W_cc_ij - S_ij`` (``W_cc``'s block or 0, ``S``'s column block) as
    :meth:`~softcrawl.jaxsim.schur.SchurOperator.dense` forms it."""
    from jax.experimental.pallas import triton as pltriton

    if len(w_refs) == 1:
        return lambda r, c, mask: pltriton.load(w_refs[0].at[r, c], mask=mask, other=0.0)
    disk, legs, s_disk, s_legs = w_refs
    nd, (L, n, nl) = disk.shape[0], s_legs.shape
    off = legs.shape[1] - nl  # the legs' contacts are their blocks' trailing rows

    def entries(r, c, mask):
        r = jnp.minimum(r, n - 1)
        rd, cd = r < nd, c < nd
        rl, cl = jnp.maximum(r - nd, 0), jnp.clip(c - nd, 0, L * nl - 1)
        lr, lc, d = rl // nl, cl // nl, jnp.minimum(c, nd - 1)
        w_cc = (pltriton.load(disk.at[jnp.minimum(r, nd - 1), d], mask=mask & rd & cd, other=0.0)
                + pltriton.load(legs.at[lr, off + rl % nl, off + cl % nl], mask=mask & ~rd & ~cd & (lr == lc),
                                other=0.0))
        return w_cc - (pltriton.load(s_disk.at[r, d], mask=mask & cd, other=0.0)
                       + pltriton.load(s_legs.at[lc, r, cl % nl], mask=mask & ~cd, other=0.0))

    return entries


def _kernel(n: int, n_iter: int, barrier, row_block: int, loop_product: bool, resident: bool, n_parts: int, *refs):
    """One robot's solve (module doc). Inputs ``refs[:n_parts]`` the operator ``W`` ``(n, n)`` or
    its parts (:func:`_entries`), then ``q_ref`` ``(n,)``, ``mu_ref`` and ``act_ref`` ``(K,)``
    (``act_ref`` int32, nonzero for an active contact), ``lam_ref`` ``(n,)`` the warm start,
    ``b_ref`` the extrapolation weights; ``x_ref`` ``(n,)`` receives the impulses. The program
    works on ``N`` rows (``n`` padded to a power of two) and reads its inputs through masked
    pointers (lanes past ``n`` load nothing).

    First, once: each row's scaling ``s`` (its contact's ``1 / sqrt(W_nn)``, 0 on inactive
    contacts' rows), the warm start ``x0`` projected, and, by the blocks of :func:`row_blocks`
    and of :data:`COLUMN_BLOCK` columns, ``Ws = s W s`` rounded to the storage dtype into the
    scratch ``wi_ref`` ``(N, N)`` (with ``resident``, read back once, by the row blocks, and kept
    as values through the iterations), the refinement's constant ``g0 = (Ws - Ws~) x0 + s q``
    into ``g_ref`` and the Gershgorin bound ``L``. Then the
    iterations (each product by the same blocks, the full ones unrolled or, with
    ``loop_product``, looped; no column past ``n`` read): each stores ``u`` and ``y`` into the
    scratch ``su_ref`` and ``sy_ref`` ``(2, N)``, slot ``k % 2``, and reads back its contact's
    three components of each after ``barrier()`` (the program's threads' stores made visible to
    all of them): one barrier an iteration, the two slots keeping an iteration's stores from
    overwriting what a slower thread still reads of the last."""
    from jax.experimental.pallas import triton as pltriton

    entries = _entries(refs[:n_parts])
    q_ref, mu_ref, lam_ref, act_ref, b_ref, x_ref, wi_ref, g_ref, su_ref, sy_ref = refs[n_parts:]
    N = wi_ref.shape[-1]
    dt = x_ref.dtype
    i = lax.iota(jnp.int32, N)
    base = 3 * (i // 3)
    normal, tangent1 = i == base, i == base + 1
    i1, i2 = jnp.minimum(base + 1, N - 1), jnp.minimum(base + 2, N - 1)
    tiny = jnp.finfo(dt).tiny

    def scale(rows):  # s and the live mask of these rows
        on = (rows < n) & (pltriton.load(act_ref.at[rows // 3], mask=rows < n, other=0) != 0)
        b = 3 * (rows // 3)
        return jnp.where(on, lax.rsqrt(jnp.where(on, entries(b, b, on), 1)), 0), on

    s, live = scale(i)
    mu = pltriton.load(mu_ref.at[i // 3], mask=i < n, other=0.0)

    def project(n_, t1, t2):  # the cone projection of this row's contact: this row's component
        ln, f = cone_projection(n_, t1, t2, mu)
        return jnp.where(live, jnp.where(normal, ln, jnp.where(tangent1, t1, t2) * f), 0)

    safe = jnp.where(live, s, 1)
    x0 = project(*(pltriton.load(lam_ref.at[j], mask=live, other=0.0) / safe for j in (base, base + 1, base + 2)))

    full, tail = row_blocks(n, row_block)

    # s and x0 by columns, for the column blocks of prepare (a program cannot slice the vectors in its registers)
    su_ref[0, :] = s
    sy_ref[0, :] = x0
    barrier()

    def prepare(r0, size, bound):  # Ws~ into the scratch, g0 and the bound on rows r0 .. r0 + size, by
        # column blocks (fewer numbers a thread, all the more where the operator comes in parts; the
        # full row blocks in a loop of the program: unrolled, the compiler held several at once)
        rows = r0 + lax.iota(jnp.int32, size)
        s_r, _ = scale(rows)
        g, total = jnp.zeros((size,), dt), jnp.zeros((size,), dt)
        for c0 in range(0, n, min(COLUMN_BLOCK, N)):
            cols = c0 + lax.iota(jnp.int32, min(COLUMN_BLOCK, N))
            Ws = (s_r[:, None] * entries(rows[:, None], cols[None, :], (rows[:, None] < n) & (cols[None, :] < n))
                  * su_ref[0, pl.ds(c0, cols.shape[0])][None, :])
            Wi = Ws.astype(wi_ref.dtype)
            wi_ref[pl.ds(r0, size), pl.ds(c0, cols.shape[0])] = Wi
            g += jnp.sum((Ws - Wi.astype(dt)) * sy_ref[0, pl.ds(c0, cols.shape[0])][None, :], axis=1)
            total += jnp.sum(jnp.abs(Ws), axis=1)
        g_ref[pl.ds(r0, size)] = g + s_r * pltriton.load(q_ref.at[rows], mask=rows < n, other=0.0)
        return jnp.maximum(bound, jnp.max(total))

    def block(r0, size):  # the scratch's rows r0 .. r0 + size, the rows and columns past n not read (0)
        rows = r0 + lax.iota(jnp.int32, size)
        return pltriton.load(wi_ref.at[rows[:, None], i[None, :]], mask=(rows < n)[:, None] & (i < n)[None, :],
                             other=0.0)

    bound = lax.fori_loop(0, full, lambda blk, b: prepare(blk * row_block, row_block, b), jnp.zeros((), dt))
    for r0, size in tail:
        bound = prepare(r0, size, bound)
    step = 1 / jnp.maximum(bound, tiny)
    barrier()
    if resident:  # whole blocks over the padding too (its rows 0): no smaller products after them
        full, tail = row_blocks(N, row_block)
    held = {r0: block(r0, size) for r0, size in [(b * row_block, row_block) for b in range(full)] + tail} \
        if resident else {}

    def body(k, c):
        x, y = c
        slot = lax.rem(k, 2)
        sy_ref[slot, :] = y

        def product(r0, size):  # u = Ws~ y + g0 on rows r0 .. r0 + size, the columns past n not read
            if resident:  # the block times Y (its two columns and zeros), on the tensor cores
                Wy = m * jnp.sum(jnp.dot(held[r0], Y, preferred_element_type=dt), axis=1)
            else:
                Wy = jnp.sum(block(r0, size).astype(dt) * y[None, :], axis=1)
            su_ref[slot, pl.ds(r0, size)] = Wy + g_ref[pl.ds(r0, size)]

        if resident:
            m, Y = split_columns(y, wi_ref.dtype)

        if loop_product and not resident:
            def looped(blk, c):
                product(blk * row_block, row_block)
                return c

            lax.fori_loop(0, full, looped, 0)
        else:
            for blk in range(full):
                product(blk * row_block, row_block)
        for r0, size in tail:
            product(r0, size)
        barrier()
        u1, u2 = su_ref[slot, i1], su_ref[slot, i2]
        # z = y - step u after De Saxce's change, this row's contact's three components, projected
        xn = project(sy_ref[slot, base] - step * (su_ref[slot, base] + de_saxce_term(u1, u2, mu)),
                     sy_ref[slot, i1] - step * u1, sy_ref[slot, i2] - step * u2)
        return xn, xn + b_ref[k] * (xn - x)

    x = lax.fori_loop(0, n_iter, body, (x0, x0))[0]
    pltriton.store(x_ref.at[i], scale(i)[0] * x, mask=i < n)  # s again: fewer registers held through the loop


#: Columns of :func:`split_columns`' matrix: a GPU's matrix product takes 16 at least.
SPLIT_COLUMNS = 16


def split_columns(y, dtype):
    """``(m, Y)``: ``y`` ``(N,)`` as ``m (Y[:, 0] + Y[:, 1])`` with ``m = max |y|`` (the smallest
    normal number if ``y`` is 0) and ``Y`` ``(N, SPLIT_COLUMNS)`` of the 16-bit ``dtype``, its
    first column ``y / m`` rounded, its second the rest rounded, the others 0: with float16, ``y``
    to 2^-24 of ``m`` (the second column's rounding: float16's smallest subnormal is 2^-24,
    whatever ``y``'s scale). A product ``A @ Y`` of float16 ``A`` accumulated in float32 then
    gives ``A y`` to about float32's accuracy for ``y``'s largest entries: the splitting of Ozaki
    et al. 2012 ("Error-free transformations of matrix multiplication by using fast routines of
    matrix multiplication and its applications", Numer. Algorithms 59) in two terms."""
    m = jnp.maximum(jnp.max(jnp.abs(y)), jnp.finfo(y.dtype).tiny)
    ys = y / m
    y1 = ys.astype(dtype)
    y2 = (ys - y1.astype(y.dtype)).astype(dtype)
    col = lax.iota(jnp.int32, SPLIT_COLUMNS)[None, :]
    return m, jnp.where(col == 0, y1[:, None], jnp.where(col == 1, y2[:, None], jnp.zeros((), dtype)))


@partial(jax.jit, static_argnames=("storage", "interpret"))
def fused_solve(W, q, mu, lam0, active, betas, *, storage: str = "float16", interpret: bool = False):
    """The accelerated gradient's solve of one robot's contacts in one kernel (module doc).

    Args:
        W: ``(n, n)`` the Delassus operator (mm/s per mN s), rows and columns interleaved by
            contact (normal, tangent 1, tangent 2), ``n = 3K``, float32 or float64: the
            iterations' precision; or the same operator in its parts
            (:class:`~softcrawl.jaxsim.schur.SchurOperator`), which the program reads instead.
        q: ``(n,)`` the free velocities, mm/s.
        mu: ``(K,)`` each contact's friction coefficient.
        lam0: ``(n,)`` the warm start, mN s.
        active: ``(K,)`` bool, False for padding contacts (their impulses are 0).
        betas: ``(n_iter,)`` the extrapolation weights
            (:func:`softcrawl.jaxsim.contact.momentum_schedule`).
        storage: the dtype in which the iterations read the scaled operator (static).
        interpret: run the kernel in Pallas' interpreter (any platform) instead of compiling it
            for a GPU.

    Returns:
        ``(n,)`` the impulses after ``n_iter`` iterations, mN s, in ``W``'s dtype.

    Raises:
        ValueError: ``n`` not ``3K``, or arrays of other lengths.
    """
    from jax.experimental.pallas import triton as pltriton

    n, K = W.shape[0], active.shape[0]
    if W.shape != (n, n) or n != 3 * K or q.shape != (n,) or lam0.shape != (n,) or mu.shape != (K,):
        raise ValueError(f"fused_solve needs a (3K, 3K) operator, (3K,) q and lam0, (K,) mu and active; got "
                         f"{W.shape}, {q.shape}, {lam0.shape}, {mu.shape}, {active.shape}")
    if isinstance(W, SchurOperator):  # parts without a disk's or legs' contacts: formed (no empty inputs)
        whole = not (OPERATOR_PARTS and W.disk.size and W.s_legs.size)
        parts = (W.dense(),) if whole else (W.disk, W.legs, W.s_disk, W.s_legs)
    else:
        parts = (W,)
    N, dt = padded_size(n), W.dtype
    n_iter = betas.shape[0]
    b = jnp.zeros(padded_size(n_iter), dt).at[:n_iter].set(betas.astype(dt))
    vector = jax.ShapeDtypeStruct((N,), dt)
    pair = jax.ShapeDtypeStruct((2, N), dt)
    resident, rows = program_rows(n, dt, storage, interpret)
    x, *_ = pl.pallas_call(
        partial(_kernel, n, n_iter, (lambda: None) if interpret else pltriton.debug_barrier,
                rows, LOOP_PRODUCT, resident, len(parts)),
        out_shape=(jax.ShapeDtypeStruct((n,), dt), jax.ShapeDtypeStruct((N, N), storage), vector,
                   pair, pair),
        interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        name="apgd_solve",
    )(*parts, q.astype(dt), mu.astype(dt), lam0.astype(dt), active.astype(jnp.int32), b)
    return x
