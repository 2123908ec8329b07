"""The legs' RID terms in one GPU kernel: ``K_r = Z^T Z`` and ``f_r = -Z^T (s + c Z qdot')`` of one
leg with ``Z`` formed block by block on chip, never in memory (Pallas, Triton form).

:func:`softcrawl.jaxsim.legs.rid_terms`' other forms are XLA programs: ``"rows"`` forms ``Z``
(256 KB a leg: it does not fit at 16,384 robots on a GPU) and ``"pairs"`` contracts each
element's frame monomials with a model matrix in one large product over all legs (about 1.3
TFLOP a step at 16,384 robots, 3.8 times the rows form's multiply-adds, and the monomials
written to memory and read again). This kernel runs the rows form per leg, one program a leg
(``jax.vmap`` over legs and robots; or :data:`SPLIT` programs sharing its elements),
:data:`ELEMENTS` elements at a time: their frames and stresses from the RID nodes' positions,
``Z``'s rows of the block in registers (``C~_e F_e`` times the elements' basis rows), and ``Z^T
Z`` accumulated by matrix products (:data:`DOT_ALGORITHM`); the strain modes are handled in
column tiles of at most 32 (``m' = 33`` as 32 + 16 padded), each pair of tiles one product. The
formulas are those of :mod:`softcrawl.jaxsim.legs` (its module doc; Farhat, Chapman & Avery
2015, eq. 20); the per-element quantities are component arrays (:mod:`softcrawl.jaxsim.frames`).

Where JAX has no GPU (``interpret=True``, the tests on a CPU) the same kernel runs in Pallas'
interpreter.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax

from softcrawl.jaxsim.factor import padded_size
from softcrawl.jaxsim.frames import frame_terms

#: Elements a program treats at once (the products' inner size; at least 16).
ELEMENTS = 16
#: Warps per program.
NUM_WARPS = 4
#: Programs per leg: program ``s`` of a leg treats its element blocks ``s, s + SPLIT, ...`` and
#: writes its shares of ``K_r``, ``f_r`` and the count, which are added after the kernel. More
#: programs at few legs (96 robots: 576 legs for 132 multiprocessors), one at many.
SPLIT = 1
#: The dot algorithm (a ``jax.lax.DotAlgorithmPreset`` name) of the kernel's products in float32:
#: three TF32 passes on the tensor cores, about float32's accuracy (relative error 2e-7,
#: ``benchmarks/dot_algorithms.py``); None for full float32 arithmetic. Other precisions, and
#: the interpreter, use their own arithmetic. These three are read when a call is traced:
#: ``benchmarks/rid_kernel.py`` times other values.
DOT_ALGORITHM = "TF32_TF32_F32_X3"


def column_tiles(ms: int) -> list[tuple[int, int]]:
    """``(start, width)`` of the column tiles of ``ms`` strain modes: widths powers of two from
    16 to 32, the last padded (33 modes: ``[(0, 32), (32, 16)]``)."""
    tiles, start = [], 0
    while start < ms:
        width = 32 if ms - start >= 32 else padded_size(ms - start)
        tiles.append((start, width))
        start += width
    return tiles


def _kernel(shapes, ms: int, c: float, precision, x_ref, qs_ref, *refs):
    """One leg (module doc). ``shapes``: each family's ``(E, k, r)``; inputs ``x_ref``
    ``(3 nr,)`` the RID nodes' part-frame positions, ``qs_ref`` ``(m',)``, then per family its
    ``conn``, ``factors``, ``rest_terms`` and ``rows``, flattened; outputs ``K`` ``(S m' m',)``,
    ``f`` ``(S m',)`` and the bad elements' count in lane 0 of ``(S 16,)`` (the others 0): program
    ``s`` of :data:`SPLIT` ``S`` writes share ``s`` of each."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    k_ref, f_ref, bad_ref = refs[-3:]
    share = pl.program_id(0)
    dt = k_ref.dtype
    tiles = column_tiles(ms)
    pairs = [(t, u) for t in range(len(tiles)) for u in range(t, len(tiles))]
    cols = [s + lax.iota(jnp.int32, w) for s, w in tiles]
    qs = [pltriton.load(qs_ref.at[j], mask=j < ms, other=0.0) for j in cols]
    eb = lax.iota(jnp.int32, ELEMENTS)
    K = [jnp.zeros((tiles[t][1], tiles[u][1]), dt) for t, u in pairs]
    f = [jnp.zeros((w,), dt) for _, w in tiles]
    bad = jnp.zeros((), jnp.int32)
    for fam, (E, k, r) in enumerate(shapes):
        conn_ref, fac_ref, rest_ref, rows_ref = refs[4 * fam:4 * fam + 4]
        n = 3 * (k - 1)

        def block(b, carry, E=E, k=k, r=r, n=n, conn_ref=conn_ref, fac_ref=fac_ref, rest_ref=rest_ref,
                  rows_ref=rows_ref):
            K, f, bad = carry
            e = (share + SPLIT * b) * ELEMENTS + eb  # blocks past the family's: no element
            on = e < E

            def load(ref, index):
                return pltriton.load(ref.at[index], mask=on, other=0)

            node = [load(conn_ref, e * k + a) for a in range(k)]
            x = [[pltriton.load(x_ref.at[3 * node[a] + i], mask=on, other=float(a == i + 1)) for i in range(3)]
                 for a in range(k)]  # padding elements: a unit tetrahedron (or triangle), finite frames
            F, g, wrong = frame_terms([[x[a + 1][i] - x[0][i] for i in range(3)] for a in range(k - 1)])
            bad = bad + jnp.sum(wrong & on).astype(jnp.int32)

            def stress(i, carry):  # stress row i of the block's elements: Z's rows i, their terms
                K, f = carry
                s = sum(load(fac_ref, (e * r + i) * n + q) * g[q] for q in range(n)) - load(rest_ref, e * r + i)

                def column(q, Z):  # Z_i += (C~ F)_iq rows_q, q = 3a + c: edge a, component c
                    a, c_ = lax.div(q, 3), lax.rem(q, 3)
                    Fc = [jnp.where(c_ == 0, F[p][0], jnp.where(c_ == 1, F[p][1], F[p][2])) for p in range(3)]
                    CR = sum(load(fac_ref, (e * r + i) * n + 3 * a + p) * Fc[p] for p in range(3))
                    return [z + CR[:, None] * pltriton.load(rows_ref.at[(e * n + q)[:, None] * ms + j[None, :]],
                                                            mask=on[:, None] & (j < ms)[None, :], other=0.0)
                            for z, j in zip(Z, cols)]

                Z = lax.fori_loop(0, n, column, [jnp.zeros((ELEMENTS, w), dt) for _, w in tiles])
                K = tuple(Km + lax.dot_general(Z[t], Z[u], (((0,), (0,)), ((), ())), precision=precision,
                                               preferred_element_type=dt) for Km, (t, u) in zip(K, pairs))
                w = s + c * sum(jnp.sum(z * v[None, :], axis=1) for z, v in zip(Z, qs))
                return K, [fj + jnp.sum(z * w[:, None], axis=0) for fj, z in zip(f, Z)]

            K, f = lax.fori_loop(0, r, stress, (K, f))
            return K, f, bad

        K, f, bad = lax.fori_loop(0, -(-E // (ELEMENTS * SPLIT)), block, (tuple(K), f, bad))
    at = share * ms * ms
    for m, (t, u) in enumerate(pairs):
        i, j = cols[t], cols[u]
        inside = (i[:, None] < ms) & (j[None, :] < ms)
        pltriton.store(k_ref.at[at + i[:, None] * ms + j[None, :]], K[m], mask=inside)
        if t != u:
            pltriton.store(k_ref.at[at + j[None, :] * ms + i[:, None]], K[m], mask=inside)
    for j, fj in zip(cols, f):
        pltriton.store(f_ref.at[share * ms + j], -fj, mask=j < ms)
    lane = lax.iota(jnp.int32, 16)
    pltriton.store(bad_ref.at[share * 16 + lane], jnp.where(lane == 0, bad, 0))


def rid_kernel_terms(part, x, qs, c: float, interpret: bool = False):
    """One leg's ``(K (m', m'), f (m',), n_bad)`` as :func:`softcrawl.jaxsim.legs.rid_terms`
    returns them, in one kernel (module doc).

    Args:
        part: :class:`~softcrawl.jaxsim.model.LegPart`; x: ``(nr, 3)`` the RID nodes' part-frame
            positions, mm; qs: ``(m',)`` the strain modes' velocities, mm/s; c: ``h + r_K``, s
            (a number: the kernel is compiled for it).
        interpret: run the kernel in Pallas' interpreter (any platform) instead of compiling it
            for a GPU.

    Returns:
        ``(K, f, n_bad)``: ``(m', m')`` ``K_r`` (mN/mm), ``(m',)`` ``f_r`` (mN) and the number of
        inverted or degenerate RID elements.
    """
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    dt = x.dtype
    ms = qs.shape[0]
    shapes, arrays = [], []
    for fam in part.families:
        E, k = fam.conn.shape
        shapes.append((E, k, fam.factors.shape[1]))
        arrays += [fam.conn.reshape(-1).astype(jnp.int32), fam.factors.reshape(-1).astype(dt),
                   fam.rest_terms.reshape(-1).astype(dt), fam.rows.reshape(-1).astype(dt)]
    if dt == jnp.float32 and DOT_ALGORITHM is not None and not interpret:  # a CPU has no TF32
        precision = lax.DotAlgorithmPreset[DOT_ALGORITHM]
    else:
        precision = (lax.Precision.HIGHEST, lax.Precision.HIGHEST)
    K, f, bad = pl.pallas_call(
        partial(_kernel, tuple(shapes), ms, float(c), precision),
        out_shape=(jax.ShapeDtypeStruct((SPLIT * ms * ms,), dt), jax.ShapeDtypeStruct((SPLIT * ms,), dt),
                   jax.ShapeDtypeStruct((SPLIT * 16,), jnp.int32)),
        grid=(SPLIT,), interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        name="rid_terms",
    )(x.reshape(-1), qs, *arrays)
    if SPLIT == 1:
        return K.reshape(ms, ms), f, bad[0]
    return K.reshape(SPLIT, ms, ms).sum(0), f.reshape(SPLIT, ms).sum(0), bad[::16].sum(dtype=jnp.int32)
