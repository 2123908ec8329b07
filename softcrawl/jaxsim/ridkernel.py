"""The legs' RID terms in one GPU kernel: ``K_r = Z^T Z`` and ``f_r = -Z^T (s + c Z qdot')`` of one
leg with ``Z`` formed block by block on chip, never in memory (Pallas, Triton form).

:func:`softcrawl.jaxsim.legs.rid_terms`' other forms are XLA programs: ``"rows"`` forms ``Z``
(256 KB a leg: it does not fit at 16,384 robots on a GPU) and ``"pairs"`` contracts each
element's frame monomials with a model matrix in one large product over all legs (about 1.3
TFLOP a step at 16,384 robots, 3.8 times the rows form's multiply-adds, and the monomials
written to memory and read again). This kernel runs the rows form per leg, one program a leg
(``jax.vmap`` over legs and robots; or :data:`SPLIT` programs sharing its elements),
:data:`ELEMENTS` elements at a time: their frames and stresses from the RID nodes' positions,
``Z``'s rows of the block in registers and ``Z^T Z`` accumulated by matrix products
(:data:`DOT_ALGORITHM`: bfloat16 parts of ``Z`` on the tensor cores). An edge's basis rows are
read once for all of an element's stress rows (``Z_i = sum_q (C~ F)_iq H_q``, ``q`` the edge's
components), from rows padded to the column tiles' widths (aligned, so that Triton reads them by
vectors), and each product and sum is one fused multiply-add
(:func:`softcrawl.jaxsim.factor.fused_multiply_add`). The strain modes are handled in column
tiles of :data:`TILE` columns and a few loose columns (:func:`column_tiles`; ``m' = 33`` as two
tiles of 16 and one column), each pair of tiles one product (two 16-column tiles joined into one
of 32 for the products: :func:`product_tiles`), the loose columns' terms by elementwise sums. The
formulas are those of :mod:`softcrawl.jaxsim.legs` (its module doc; Farhat, Chapman & Avery
2015, eq. 20); the per-element quantities are component arrays (:mod:`softcrawl.jaxsim.frames`).

Where JAX has no GPU (``interpret=True``, the tests on a CPU) the same kernel runs in Pallas'
interpreter.
"""

from __future__ import annotations

import dataclasses
from functools import partial, reduce

import jax
import jax.numpy as jnp
from jax import lax

from softcrawl.jaxsim.factor import fused_multiply_add, padded_size
from softcrawl.jaxsim.frames import frame_terms
from softcrawl.jaxsim.gpu import kernel_precision

#: Elements a program treats at once (the products' inner size; at least 16).
ELEMENTS = 16
#: Warps per program. The per-element numbers (frames, stresses, ``C~ F``) are computed by every
#: thread that holds a column of their rows: fewer warps repeat them less. Machine code for an
#: H100 (``benchmarks/kernel_sass.py --kernel rid``) counts 101k warp instructions a leg at 2
#: warps against 172k at 4 (254 and 174 registers, no spill). At 1 warp a program is twice as
#: long (where legs are few, the kernel's time) and holds twice the numbers a thread: 88k with
#: 1.2 KB spilled, in three row groups (:data:`ROW_GROUPS`) 90k without spill.
NUM_WARPS = 2
#: Programs per leg: program ``s`` of a leg treats its element blocks ``s, s + SPLIT, ...`` and
#: writes its shares of ``K_r``, ``f_r`` and the count, which are added after the kernel. More
#: programs at few legs (96 robots: 576 legs for 132 multiprocessors), one at many.
SPLIT = 1
#: The widest column tile: 16 or 32 columns. Each stress row's ``Z`` block is ``(ELEMENTS, TILE)``
#: numbers a tile, which Triton spreads over the threads by rows of four numbers each (vector
#: loads): at 32 columns a thread holds two elements' rows, at 16 one, so that the per-element
#: numbers (frame, stresses, ``C~ F``), computed by each thread for the rows it holds, are
#: computed half as often. For the products, pairs of 16-column tiles are joined again
#: (:func:`product_tiles`): their bfloat16 parts stacked on a last axis, the columns interleaved,
#: two numbers of a register; products of 16 x 16 outputs would be formed whole by both warps.
#: Machine code for an H100 (``kernel_sass.py --kernel rid``): 101k warp instructions a leg at 16
#: columns against 116k at 32 (254 and 255 registers, no spill); 106k with the tiles' products
#: apart, 111k with the tiles joined as float32 numbers (283 register moves a block).
TILE = 16
#: Strain modes after the last full column tile, up to this many, are treated one by one as
#: vectors over the elements (not a padded tile of 16 columns).
LOOSE = 4
#: Groups of an element's stress rows whose ``Z`` rows a program forms at once, each group by its
#: own pass over the element's edges (the basis rows read again for each; :func:`row_groups`):
#: fewer rows at once, fewer registers held. Machine code for an H100 at 2 warps: 3 groups take
#: 168 registers a thread instead of 254 (six programs a multiprocessor instead of four) for 116k
#: warp instructions a leg instead of 101k; 2 groups, 238 registers and 108k.
ROW_GROUPS = 1
#: The kernel's products in float32, on the tensor cores: ``"SPLIT_BF16"``, each block's ``Z``
#: split in three bfloat16 parts (truncations, read off its bits by masks and shifts, not
#: rounding conversions) and ``Z^T Z`` accumulated by four products of them
#: (:func:`split_products`: about float32's accuracy); ``"SPLIT_TF32"``, ``Z = H + L`` with ``H``
#: its TF32 part (:func:`tf32_high`) and two TF32 products, ``H^T H`` and ``H^T L``; in both,
#: ``K_r = K + M + M^T`` formed once at the end. Machine code for an H100 (``kernel_sass.py
#: --kernel rid``): 101k warp instructions a leg by bfloat16 parts, 115k by TF32 parts (Triton
#: rounds each TF32 operand by three to five instructions; bfloat16 operands are read by
#: ``ldmatrix``).
#: Else a ``jax.lax.DotAlgorithmPreset`` name (``"TF32_TF32_F32_X3"``: three TF32 passes,
#: relative error 2e-7, ``benchmarks/dot_algorithms.py``), or None for full float32 arithmetic.
#: Other precisions, and the interpreter, use their own arithmetic (the interpreter applies the
#: splits in float32, with exact products). This module's constants are read when a call is
#: traced: ``benchmarks/rid_kernel.py`` times other values.
DOT_ALGORITHM = "SPLIT_BF16"


def column_tiles(ms: int) -> tuple[list[tuple[int, int]], list[int]]:
    """The strain modes' columns as the kernel treats them: ``(start, width)`` of the column
    tiles, :data:`TILE` wide but a last one, padded to 16 or 32, and the columns after the last
    tile, at most :data:`LOOSE` of them, each treated alone (33 modes: ``([(0, 16), (16, 16)],
    [32])``, ``([(0, 32)], [32])`` at ``TILE = 32``; 40 at 32: ``([(0, 32), (32, 16)], [])``)."""
    tiles, start = [], 0
    while ms - start > LOOSE:
        width = TILE if ms - start >= TILE else padded_size(ms - start)
        tiles.append((start, width))
        start += width
    return tiles, list(range(start, ms))


def row_groups(r: int) -> list[range]:
    """An element's ``r`` stress rows in at most :data:`ROW_GROUPS` groups of consecutive rows,
    each of ``ceil(r / ROW_GROUPS)`` rows but the last (6 rows in 3 groups: ``[range(0, 2),
    range(2, 4), range(4, 6)]``; in 4 groups the same; 3 rows in 3: one each)."""
    size = -(-r // max(1, min(ROW_GROUPS, r)))
    return [range(start, min(start + size, r)) for start in range(0, r, size)]


def product_tiles(tiles) -> list[tuple[int, ...]]:
    """The column tiles (:func:`column_tiles`) as the products take them: each pair of consecutive
    tiles of 16 columns joined into one of 32 (``(t, t + 1)``; tiles ``[(0, 16), (16, 16), (32,
    16)]`` give ``[(0, 1), (2,)]``), the others alone (``(t,)``), so that a warp forms half of
    each product (:data:`TILE`)."""
    out, t = [], 0
    while t < len(tiles):
        pair = t + 1 < len(tiles) and tiles[t][1] == tiles[t + 1][1] == 16
        out.append((t, t + 1) if pair else (t,))
        t += 1 + pair
    return out


def product_columns(tiles, tile: tuple[int, ...]):
    """The strain modes of a product tile's columns (:func:`product_tiles`), an int32 vector: a
    tile's own ``start + j``; a joined pair's ``j``-th column mode ``start_(j % 2) + j // 2``, its
    two tiles' columns interleaved (:func:`join_tiles`)."""
    if len(tile) == 1:
        start, width = tiles[tile[0]]
        return start + lax.iota(jnp.int32, width)
    j = lax.iota(jnp.int32, 32)
    return jnp.where(j % 2 == 0, tiles[tile[0]][0], tiles[tile[1]][0]) + j // 2


def join_tiles(parts, joined) -> list:
    """Blocks of a stress row's column tiles ``parts`` (each ``(ELEMENTS, width)``) as the
    product tiles ``joined`` take them (:func:`product_tiles`): a tile alone as it is, a pair
    stacked on a last axis and flattened, ``(ELEMENTS, 32)`` with the two tiles' columns
    interleaved (:func:`product_columns`)."""
    return [parts[g[0]] if len(g) == 1 else jnp.stack([parts[i] for i in g], axis=-1).reshape(
        parts[g[0]].shape[0], -1) for g in joined]


def kernel_rows(rows, ms: int) -> tuple:
    """The basis rows ``(E, n, m')`` as the kernel reads them, flattened: the column tiles'
    columns padded to the tiles' widths (rows of a multiple of 16 numbers, so aligned), then the
    loose columns (:func:`column_tiles`); each part left out where it has no column."""
    tiles, loose = column_tiles(ms)
    W = sum(w for _, w in tiles)
    parts = (jnp.pad(rows[..., :W], ((0, 0), (0, 0), (0, max(W - ms, 0)))),) if tiles else ()
    return tuple(p.reshape(-1) for p in parts + ((rows[..., W:],) if loose else ()))


def with_kernel_rows(part):
    """``part`` with each RID family's :func:`kernel_rows` formed (``Family.kernel_rows``), for a
    loop of steps to form them once (XLA forms them in every step otherwise; where the kernel is
    not taken, it drops them unused)."""
    ms = part.strain_modes.shape[0]
    return dataclasses.replace(part, families=tuple(dataclasses.replace(f, kernel_rows=kernel_rows(f.rows, ms))
                                                    for f in part.families))


def tf32_high(z):
    """``z`` (float32) with the 13 low bits of its significand cleared: a TF32 number, ``z -
    tf32_high(z)`` exact and below ``2^-10 |z|`` (the two-term splitting of a product's operands;
    Ozaki et al. 2012, as :func:`softcrawl.jaxsim.fused.split_columns`)."""
    bits = lax.bitcast_convert_type(z, jnp.int32) & jnp.int32(-(1 << 13))
    return lax.bitcast_convert_type(bits, jnp.float32)


def bfloat16_high(z):
    """``(h, b)``: ``z`` (float32) truncated to bfloat16, its 16 low bits cleared, as a float32
    ``h`` and as the bfloat16 ``b``, both read off ``z``'s bits (no conversion to round): ``z -
    h`` exact and below ``2^-7 |z|``."""
    bits = lax.bitcast_convert_type(z, jnp.uint32)
    return (lax.bitcast_convert_type(bits & jnp.uint32(0xFFFF0000), jnp.float32),
            lax.bitcast_convert_type((bits >> 16).astype(jnp.uint16), jnp.bfloat16))


def split_products(Z, split, joined=None):
    """The operand pairs ``(a, b)`` of the products ``a^T b`` that accumulate one stress row's
    ``Z^T Z`` (``Z`` its column tiles, float32) in the kernel's two accumulators, ``K_tu`` and
    ``M_tu``, so that ``Z_t^T Z_u = K_tu + M_tu + M_ut^T`` (:data:`DOT_ALGORITHM`): ``(K, M)``,
    functions of the product tiles ``t, u`` giving tuples of pairs. ``joined``: the product tiles
    (:func:`product_tiles`), each tile alone where None; the parts are split from ``Z``'s tiles
    and then joined (:func:`join_tiles`), so that a joined pair's bfloat16 numbers of a column pair
    share a register.

    ``split`` ``"tf32"``: ``Z = H + L``, ``H`` its TF32 part (:func:`tf32_high`), ``K`` holding
    ``H^T H`` and ``M`` ``H^T L`` (``L^T L``, about ``2^-22`` of ``Z``'s scale, left out).
    ``"bf16"``: ``Z = B1 + B2 + B3`` in bfloat16, each part the truncation of what the parts
    before it leave (:func:`bfloat16_high`; exact: ``Z``'s 24 bits in three parts of 8; Henry,
    Tang & Heinecke 2019, "bf16x6", who round), ``K`` holding ``B1^T B1 + B2^T B2`` and ``M``
    ``B1^T B2 + B1^T B3``: bf16x6's six products in four, ``Z^T Z`` being symmetric (``B2^T B3``
    and ``B3^T B3``, below ``2^-21`` of ``Z``'s scale squared, left out). None: ``K`` holding
    ``Z^T Z``, no ``M``."""
    def join(parts):
        return parts if joined is None else join_tiles(parts, joined)

    if split == "bf16":
        H1 = [bfloat16_high(z) for z in Z]
        R = [z - h for z, (h, _) in zip(Z, H1)]
        H2 = [bfloat16_high(r) for r in R]
        B1, B2 = [b for _, b in H1], [b for _, b in H2]
        B3 = [(r - h).astype(jnp.bfloat16) for r, (h, _) in zip(R, H2)]
        B1, B2, B3 = (join(B) for B in (B1, B2, B3))
        return (lambda t, u: ((B1[t], B1[u]), (B2[t], B2[u])),
                lambda t, u: ((B1[t], B2[u]), (B1[t], B3[u])))
    H = [tf32_high(z) for z in Z] if split else Z
    H, L = join(H), join([z - h for z, h in zip(Z, H)]) if split else None
    return lambda t, u: ((H[t], H[u]),), lambda t, u: ((H[t], L[u]),)


def _kernel(shapes, ms: int, c: float, precision, split, compiled: bool, on_ref, x_ref, qs_ref, *refs):
    """One leg (module doc). ``shapes``: each family's ``(E, k, r)``; inputs ``on_ref`` ``(1,)``
    1 where the leg exists, 0 where its slot is empty (no element treated: every output 0),
    ``x_ref`` ``(3 nr,)`` the RID nodes' part-frame positions, ``qs_ref`` ``(m',)``, then per family its
    ``conn``, ``factors``, ``rest_terms`` and :func:`kernel_rows`, flattened; ``split``: ``Z^T
    Z`` by :func:`split_products` (:data:`DOT_ALGORITHM`); outputs ``K`` ``(S m' m',)``, ``f``
    ``(S m',)`` and the bad elements' count in lane 0 of ``(S 16,)`` (the others 0): program
    ``s`` of :data:`SPLIT` ``S`` writes share ``s`` of each."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    k_ref, f_ref, bad_ref = refs[-3:]
    share = pl.program_id(0)
    dt = k_ref.dtype
    fma = partial(fused_multiply_add, compiled=compiled)

    def dot(a, b):  # a^T b
        return lax.dot_general(a, b, (((0,), (0,)), ((), ())), precision=precision, preferred_element_type=dt)

    tiles, loose = column_tiles(ms)
    joined = product_tiles(tiles)
    pcols = [product_columns(tiles, tile) for tile in joined]  # the product tiles' modes
    pairs = [(t, u) for t in range(len(joined)) for u in range(t, len(joined))]
    lpairs = [(a, b) for a in range(len(loose)) for b in range(a, len(loose))]
    cols = [s + lax.iota(jnp.int32, w) for s, w in tiles]
    qs = [pltriton.load(qs_ref.at[j], mask=j < ms, other=0.0) for j in cols]
    ql = [qs_ref[j] for j in loose]
    eb = lax.iota(jnp.int32, ELEMENTS)
    ordered = [(t, u) for t in range(len(joined)) for u in range(len(joined))] if split else []
    width = [c.shape[0] for c in pcols]
    acc = {"K": tuple(jnp.zeros((width[t], width[u]), dt) for t, u in pairs),  # Z_t^T Z_u (split: K_tu)
           "M": tuple(jnp.zeros((width[t], width[u]), dt) for t, u in ordered),  # split: M_tu
           "f": tuple(jnp.zeros((ELEMENTS, w), dt) for _, w in tiles),  # by element: Z_t w
           "KL": tuple(jnp.zeros((ELEMENTS, w), dt) for _ in loose for _, w in tiles),  # Z_t z_l
           "LL": tuple(jnp.zeros((ELEMENTS,), dt) for _ in lpairs),  # z_l z_l'
           "fL": tuple(jnp.zeros((ELEMENTS,), dt) for _ in loose)}  # z_l w
    bad = jnp.zeros((), jnp.int32)
    W, nl = sum(w for _, w in tiles), len(loose)
    per = 3 + bool(tiles) + bool(loose)

    def families(carry):  # every family's element blocks
        acc, bad = carry
        for fam, (E, k, r) in enumerate(shapes):
            conn_ref, fac_ref, rest_ref, *more = refs[per * fam:per * fam + per]
            rows_ref = more[0] if tiles else None
            loose_ref = more[-1] if loose else None
            n = 3 * (k - 1)

            def block(b, carry, E=E, k=k, r=r, n=n, conn_ref=conn_ref, fac_ref=fac_ref, rest_ref=rest_ref,
                      rows_ref=rows_ref, loose_ref=loose_ref):
                acc, bad = carry
                e = (share + SPLIT * b) * ELEMENTS + eb  # blocks past the family's: no element
                on = e < E

                def load(ref, index):
                    return pltriton.load(ref.at[index], mask=on, other=0)

                node = [load(conn_ref, e * k + a) for a in range(k)]
                x = [[pltriton.load(x_ref.at[3 * node[a] + i], mask=on, other=float(a == i + 1)) for i in range(3)]
                     for a in range(k)]  # padding elements: a unit tetrahedron (or triangle), finite frames
                F, g, wrong = frame_terms([[x[a + 1][i] - x[0][i] for i in range(3)] for a in range(k - 1)])
                bad = bad + jnp.sum(wrong & on).astype(jnp.int32)
                # Z's rows of the block, stress row i: Z_i = sum_q (C~ F)_iq H_q, q = 3a + c (edge a,
                # component c); each basis row H_q of the block's elements read once for a group's rows
                def edge(a, carry, group):  # edge a's three components c: q = 3a + c
                    s, Z, zl = carry
                    fac = [[load(fac_ref, (e * r + i) * n + 3 * a + p) for p in range(3)] for i in group]
                    ga = [sum(jnp.where(a == b, g[3 * b + p], 0.0) for b in range(k - 1)) for p in range(3)]
                    s = [si + sum(fa[p] * ga[p] for p in range(3)) for fa, si in zip(fac, s)]
                    for c_ in range(3):
                        row = e * n + 3 * a + c_
                        H = [pltriton.load(rows_ref.at[row[:, None] * W + j[None, :]], mask=on[:, None], other=0.0)
                             for j in cols]
                        Hl = [load(loose_ref, row * nl + m) for m in range(nl)]
                        for m, fa in enumerate(fac):
                            CF = fma(fa[2], F[2][c_], fma(fa[1], F[1][c_], fa[0] * F[0][c_]))
                            Z[m] = [fma(CF[:, None], h, z) for z, h in zip(Z[m], H)]
                            zl[m] = [fma(CF, h, z) for z, h in zip(zl[m], Hl)]
                    return s, Z, zl

                for group in row_groups(r):
                    s, Z, zl = lax.fori_loop(0, k - 1, partial(edge, group=group), (
                        [-load(rest_ref, e * r + i) for i in group],
                        [[jnp.zeros((ELEMENTS, w), dt) for _, w in tiles] for _ in group],
                        [[jnp.zeros((ELEMENTS,), dt) for _ in loose] for _ in group]))
                    for si, Zi, zli in zip(s, Z, zl):
                        w = si + c * (sum(jnp.sum(z * v[None, :], axis=1) for z, v in zip(Zi, qs))
                                      + sum(z * v for z, v in zip(zli, ql)))
                        K, M = split_products(Zi, split, joined)  # each product added to its accumulator
                        acc = {"K": tuple(reduce(lambda a, ab: a + dot(*ab), K(t, u), Km)
                                          for Km, (t, u) in zip(acc["K"], pairs)),
                               "M": tuple(reduce(lambda a, ab: a + dot(*ab), M(t, u), Mm)
                                          for Mm, (t, u) in zip(acc["M"], ordered)),
                               "f": tuple(fma(z, w[:, None], fa) for fa, z in zip(acc["f"], Zi)),
                               "KL": tuple(fma(z, y[:, None], kl) for kl, (y, z) in
                                           zip(acc["KL"], ((y, z) for y in zli for z in Zi))),
                               "LL": tuple(fma(zli[a], zli[b], ll) for ll, (a, b) in zip(acc["LL"], lpairs)),
                               "fL": tuple(fma(y, w, fl) for fl, y in zip(acc["fL"], zli))}
                return acc, bad

            acc, bad = lax.fori_loop(0, -(-E // (ELEMENTS * SPLIT)), block, (acc, bad))
        return acc, bad

    def write(acc, bad):  # this program's shares of K, f and the count
        at = share * ms * ms
        lane = lax.iota(jnp.int32, 16)

        def scalar(ref, index, value):  # one number, by lane 0 of a vector
            pltriton.store(ref.at[index + lane], jnp.broadcast_to(value, (16,)), mask=lane == 0)

        M = dict(zip(ordered, acc["M"]))
        for m, (t, u) in enumerate(pairs):
            i, j = pcols[t], pcols[u]
            inside = (i[:, None] < ms) & (j[None, :] < ms)
            K = acc["K"][m] + (M[t, u] + M[u, t].T if split else 0)  # Z^T Z = K + M + M^T
            pltriton.store(k_ref.at[at + i[:, None] * ms + j[None, :]], K, mask=inside)
            if t != u:
                pltriton.store(k_ref.at[at + j[None, :] * ms + i[:, None]], K, mask=inside)
        for m, (l, t) in enumerate((l, t) for l in loose for t in range(len(tiles))):
            kl = jnp.sum(acc["KL"][m], axis=0)
            pltriton.store(k_ref.at[at + cols[t] * ms + l], kl, mask=cols[t] < ms)
            pltriton.store(k_ref.at[at + l * ms + cols[t]], kl, mask=cols[t] < ms)
        for ll, (a, b) in zip(acc["LL"], lpairs):
            total = jnp.sum(ll)
            scalar(k_ref, at + loose[a] * ms + loose[b], total)
            if a != b:
                scalar(k_ref, at + loose[b] * ms + loose[a], total)
        for j, fj in zip(cols, acc["f"]):
            pltriton.store(f_ref.at[share * ms + j], -jnp.sum(fj, axis=0), mask=j < ms)
        for l, fl in zip(loose, acc["fL"]):
            scalar(f_ref, share * ms + l, -jnp.sum(fl))
        pltriton.store(bad_ref.at[share * 16 + lane], jnp.where(lane == 0, bad, 0))

    on = on_ref[0] != 0  # an empty slot treats no element and writes zeros
    pl.when(on)(lambda: write(*families((acc, bad))))
    pl.when(~on)(lambda: write(acc, bad))


def rid_kernel_terms(part, x, qs, c: float, interpret: bool = False, present=True):
    """One leg's ``(K (m', m'), f (m',), n_bad)`` as :func:`softcrawl.jaxsim.legs.rid_terms`
    returns them, in one kernel (module doc); zeros where the leg is absent.

    Args:
        part: :class:`~softcrawl.jaxsim.model.LegPart`; x: ``(nr, 3)`` the RID nodes' part-frame
            positions, mm; qs: ``(m',)`` the strain modes' velocities, mm/s; c: ``h + r_K``, s
            (a number: the kernel is compiled for it).
        interpret: run the kernel in Pallas' interpreter (any platform) instead of compiling it
            for a GPU.
        present: whether the leg exists (a bool, traced or not): the program of an empty slot
            treats none of its elements and returns zeros (in a batch of the paper's space, 12%
            of the slots).

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
        rows = kernel_rows(fam.rows, ms) if fam.kernel_rows is None else fam.kernel_rows
        arrays += [fam.conn.reshape(-1).astype(jnp.int32), fam.factors.reshape(-1).astype(dt),
                   fam.rest_terms.reshape(-1).astype(dt), *(r.astype(dt) for r in rows)]
    split = {"SPLIT_TF32": "tf32", "SPLIT_BF16": "bf16"}.get(DOT_ALGORITHM) if dt == jnp.float32 else None
    precision = None if split == "bf16" else kernel_precision(dt, "TF32_TF32_F32" if split else DOT_ALGORITHM,
                                                               interpret)
    K, f, bad = pl.pallas_call(
        partial(_kernel, tuple(shapes), ms, float(c), precision, split, not interpret),
        out_shape=(jax.ShapeDtypeStruct((SPLIT * ms * ms,), dt), jax.ShapeDtypeStruct((SPLIT * ms,), dt),
                   jax.ShapeDtypeStruct((SPLIT * 16,), jnp.int32)),
        grid=(SPLIT,), interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        name="rid_terms",
    )(jnp.asarray(present, jnp.int32).reshape(1), x.reshape(-1), qs, *arrays)
    if SPLIT == 1:
        return K.reshape(ms, ms), f, bad[0]
    return K.reshape(SPLIT, ms, ms).sum(0), f.reshape(SPLIT, ms).sum(0), bad[::16].sum(dtype=jnp.int32)
