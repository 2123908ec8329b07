"""The attachments' elimination products of one robot, by XLA or in one GPU kernel (Pallas,
Triton form).

:func:`softcrawl.jaxsim.delassus.condense` eliminates the attachment rows by a Schur complement:
with ``W_bb^-1`` formed, ``P = W_cb W_bb^-1`` ``(3K, 3A)``, ``S = P W_bc`` ``(3K, 3K)``, the
contacts' free velocities ``q_c = u_c - P u_b`` and the attachments' ``x_u = W_bb^-1 u_b``. Who
touches what makes ``W_bc`` block-sparse: its columns of the disk's contacts are dense (``W_bd``
``(3A, 3K_d)``), those of leg ``l``'s contacts are non-zero in its own ``3F`` attachment rows only
(``W_bl[l]`` ``(3F, 3K_l)``, the leg's Gram block). So

    P[disk rows] = W_bd^T W_bb^-1,   P[leg l' rows] = W_bl[l']^T W_bb^-1[l' rows],
    S[:, leg l] = P[:, l cols] W_bl[l],   S[:, disk] = sum_l P[:, l cols] W_bd[l rows],
    P u_b = W_cb x_u,

each a product of small blocks (:func:`products`; Golub & Van Loan, "Matrix Computations", 4th
ed., sec. 3.2 for block elimination). XLA's form (:func:`by_xla`) runs them as half a dozen
batched products plus the concatenation and the transpose that put ``P``'s blocks where the next
product reads them, each through memory: compiled for an H100 with the other kernel forms taken,
the elimination is half the 16,384-robot step's memory traffic (``benchmarks/RESULTS.md``).
:func:`by_kernel` does all of it for one robot in one program (:func:`_kernel`): ``P`` written
once and read back by attachment-column blocks (from the cache), ``S``'s disk columns from its
disk rows (``S`` is symmetric), ``q_c`` from ``x_u``; its inputs read once, the leg Grams'
attachment blocks and the disk's block masked as they are read (no masked copies). Compiled for
an H100 the program issues 84k warp instructions a robot (``benchmarks/kernel_sass.py --kernel
elimination``), and the step moves 0.57 MB a robot-step less at 16,384 robots.

The kernel's products run on the tensor cores in three TF32 passes (:data:`DOT_ALGORITHM`, about
float32's accuracy); float64 elimination and platforms other than CUDA take XLA's form, where
``FORM`` asks for the kernel (:data:`FORM`), as robots without disk or leg contacts do. Where JAX
has no GPU (``"interpret"``, the tests on a CPU) the same kernel runs in Pallas' interpreter.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jax.experimental import pallas as pl

from softcrawl.jaxsim.factor import padded_size
from softcrawl.jaxsim.gpu import cuda_kernel, kernel_precision

#: How :func:`products` forms the elimination's products: ``"xla"`` (the default; every
#: platform), ``"kernel"`` (:func:`by_kernel` on CUDA for float32, XLA's form elsewhere) or
#: ``"interpret"`` (the kernel in Pallas' interpreter, any platform and precision: the tests').
#: Read when a step is traced.
FORM = "xla"
#: The values :data:`FORM` may take.
FORMS = ("xla", "kernel", "interpret")
#: Warps a robot's program, and contact rows of ``S`` it forms at once (a loop over the blocks):
#: compiled for an H100, 4 warps and 128 rows issue 84k warp instructions a robot, 8 warps 124k,
#: neither spilling; 256 rows at 4 warps spill (``benchmarks/RESULTS.md``). Read when a step is
#: traced.
NUM_WARPS = 4
ROW_BLOCK = 128
#: The kernel's products in float32 on a GPU: a ``jax.lax.DotAlgorithmPreset`` name (three TF32
#: passes: relative error 2e-7, ``benchmarks/dot_algorithms.py``; ``S`` is subtracted from
#: ``W_cc`` and up to 5.5 times the condensed operator's norm on landed robots, so one TF32 pass,
#: 1e-3, is too coarse), or None for full float32 arithmetic. The interpreter multiplies at full
#: precision. Read when a step is traced.
DOT_ALGORITHM = "TF32_TF32_F32_X3"


def by_xla(W_inv, disk_ad, gram, bilateral, u_b, u_c):
    """:func:`products` by XLA's batched products (arguments and results as there)."""
    L, n_leg, _ = gram.shape
    A3 = W_inv.shape[0]
    F3 = A3 // L
    W_bd, W_bl = attachment_blocks(disk_ad, gram, bilateral)
    Kd3, Kl3 = W_bd.shape[1], n_leg - F3
    # u_b^T W_bb^-1 as one more disk row of P
    P_d = jnp.concatenate([W_bd, u_b[:, None]], axis=1).T @ W_inv
    P = jnp.concatenate([P_d[:Kd3], jnp.einsum("lbc,lba->lca", W_bl, W_inv.reshape(L, F3, A3))
                         .reshape(L * Kl3, A3)])
    s_legs = jnp.einsum("rlb,lbk->lrk", P.reshape(-1, L, F3), W_bl)
    return P, P @ W_bd, s_legs, u_c - P @ u_b, P_d[-1]


def attachment_blocks(disk_ad, gram, bilateral):
    """``(W_bd, W_bl)``: ``W_bc``'s blocks (module doc), ``disk_ad`` ``(3A, 3K_d)`` and each leg
    Gram's ``(L, 3F, 3K_l)`` attachment-by-contact block, the rows of absent legs' attachments
    (``bilateral`` false) 0."""
    L, n_leg, _ = gram.shape
    F3 = bilateral.shape[0] // L
    W_bd = jnp.where(bilateral[:, None], disk_ad, 0)
    W_bl = gram[:, :F3, F3:] * bilateral.reshape(L, F3)[:, :, None]
    return W_bd, W_bl


def products(W_inv, disk_ad, gram, bilateral, u_b, u_c):
    """The elimination's products of one robot (module doc), in the form :data:`FORM` names.

    Args:
        W_inv: ``(3A, 3A)`` ``W_bb^-1`` (mN s per mm/s), ``3A = 3 L F`` attachment rows, each leg
            slot's ``3F`` in turn.
        disk_ad: ``(3A, 3K_d)`` the disk's share between the attachments and its contacts.
        gram: ``(L, 3F + 3K_l, 3F + 3K_l)`` each leg's share ``Y_l^T Y_l``, its attachments'
            rows first.
        bilateral: ``(3A,)`` bool, the attachment rows of present legs.
        u_b: ``(3A,)`` the attachments' free velocities (0 on absent legs' rows), mm/s.
        u_c: ``(3K,)`` the contacts' free velocities, mm/s; ``3K = 3K_d + L 3K_l``.

    Returns:
        ``(P, s_disk, s_legs, q_c, x_u)``: ``(3K, 3A)``, ``(3K, 3K_d)`` ``S``'s disk columns,
        ``(L, 3K, 3K_l)`` its columns of each leg's contacts, ``(3K,)`` mm/s and ``(3A,)`` mN s.

    Raises:
        ValueError: an unknown :data:`FORM`.
    """
    if FORM not in FORMS:
        raise ValueError(f"elimination.FORM must be one of {FORMS}, not {FORM!r}")
    args = (W_inv, disk_ad, gram, bilateral, u_b, u_c)
    F3 = W_inv.shape[0] // gram.shape[0]  # a leg's attachment rows; its Gram's others are its contacts'
    if FORM == "xla" or not (disk_ad.size and gram.shape[1] > F3):  # the kernel needs both bodies' contacts
        return by_xla(*args)
    if FORM == "interpret":
        return by_kernel(*args, interpret=True)
    if W_inv.dtype != jnp.float32:
        return by_xla(*args)
    return jax.lax.platform_dependent(*args, **cuda_kernel(partial(by_kernel, interpret=False)), default=by_xla)


def _kernel(L: int, F3: int, precision, barrier, inv_ref, ad_ref, gram_ref, mb_ref, ub_ref, uc_ref, p_ref,
            sd_ref, sl_ref, q_ref, xu_ref):
    """One robot's products (module doc): inputs as :func:`products`' (``mb_ref`` int32), outputs
    ``P``, ``S``'s disk and leg columns, ``q_c`` and ``x_u``. The blocks have power-of-two shapes
    (:func:`padded_size`: 128 attachment rows, 16 of a leg, 32 disk and 64 leg contact rows, 256
    contact rows for the paper preset's robot), read and written through masked pointers (the
    loads' indices clipped, the stores' not: a clipped index would store a masked lane's old value
    over another lane's in Pallas' interpreter).

    First, leg by leg: ``P``'s disk rows in the leg's attachment columns and the leg's contact rows
    of ``P``, stored; the leg's share of ``x_u`` and, from it, its contacts' ``q_c = u_c - W_cb
    x_u`` (``P u_b = W_cb W_bb^-1 u_b``); the disk rows' ``S`` and ``q_c`` accumulated. Then, by
    :data:`ROW_BLOCK` rows of ``P`` read back: ``S``'s columns of each leg's contacts, and, ``S``
    being symmetric, its disk columns' leg rows as the transpose of their disk rows."""
    from jax.experimental.pallas import triton as pltriton

    A3, Kd3 = ad_ref.shape
    Kl3, n = gram_ref.shape[1] - F3, p_ref.shape[0]
    dt = p_ref.dtype
    a, f = lax.iota(jnp.int32, padded_size(A3)), lax.iota(jnp.int32, padded_size(F3))
    d, k = lax.iota(jnp.int32, padded_size(Kd3)), lax.iota(jnp.int32, padded_size(Kl3))
    on_a, on_f, on_d, on_k = a < A3, f < F3, d < Kd3, k < Kl3
    ac, dc, fc, kc = jnp.minimum(a, A3 - 1), jnp.minimum(d, Kd3 - 1), jnp.minimum(f, F3 - 1), jnp.minimum(k, Kl3 - 1)

    def load(ref, mask):
        return pltriton.load(ref, mask=mask, other=0.0)

    def dot(x, y):
        return lax.dot_general(x, y, (((1,), (0,)), ((), ())), precision=precision, preferred_element_type=dt)

    def leg(l):  # leg l's attachment rows (clipped), and which of them exist and are bilateral
        rows = jnp.minimum(l * F3 + f, A3 - 1)
        return rows, on_f & (pltriton.load(mb_ref.at[rows], mask=on_f, other=0) != 0)

    bilateral = pltriton.load(mb_ref.at[ac], mask=on_a, other=0) != 0
    disk_t = load(ad_ref.at[ac[None, :], dc[:, None]], on_d[:, None] & (on_a & bilateral)[None, :])  # W_bd^T
    u_b = load(ub_ref.at[ac], on_a)

    def per_leg(l, carry):  # leg l: P's disk rows in its attachment columns, its contact rows of P, its
        # x_u and its contacts' q_c; the disk rows' S and W_cb x_u accumulated
        s_dd, w_x = carry
        rows, live = leg(l)
        inv_cols = load(inv_ref.at[ac[:, None], rows[None, :]], on_a[:, None] & on_f[None, :])
        P_d = dot(disk_t, inv_cols)
        pltriton.store(p_ref.at[d[:, None], l * F3 + f[None, :]], P_d, mask=on_d[:, None] & on_f[None, :])
        gram_t = load(gram_ref.at[l, fc[None, :], F3 + kc[:, None]], on_k[:, None] & live[None, :])  # W_bl[l]^T
        inv_rows = load(inv_ref.at[rows[:, None], ac[None, :]], on_f[:, None] & on_a[None, :])
        pltriton.store(p_ref.at[Kd3 + l * Kl3 + k[:, None], a[None, :]], dot(gram_t, inv_rows),
                       mask=on_k[:, None] & on_a[None, :])
        x_u = jnp.sum(inv_cols * u_b[:, None], axis=0)  # (u_b^T W_bb^-1)'s leg l entries
        pltriton.store(xu_ref.at[l * F3 + f], x_u, mask=on_f)
        contacts = Kd3 + l * Kl3 + k
        pltriton.store(q_ref.at[contacts], load(uc_ref.at[jnp.minimum(contacts, n - 1)], on_k)
                       - jnp.sum(gram_t * x_u[None, :], axis=1), mask=on_k)
        W_bd = load(ad_ref.at[rows[:, None], dc[None, :]], live[:, None] & on_d[None, :])  # leg l's rows of W_bd
        return s_dd + dot(P_d, W_bd), w_x + jnp.sum(W_bd * x_u[:, None], axis=0)

    # a loop, not unrolled: unrolled, the compiler interleaves the legs and spills
    s_dd, w_x = lax.fori_loop(0, L, per_leg, (jnp.zeros((d.shape[0], d.shape[0]), dt), jnp.zeros(d.shape, dt)))
    pltriton.store(sd_ref.at[d[:, None], d[None, :]], s_dd, mask=on_d[:, None] & on_d[None, :])
    pltriton.store(q_ref.at[d], load(uc_ref.at[dc], on_d) - w_x, mask=on_d)
    barrier()  # P's stores visible to every thread of the program

    def per_block(i, carry):  # S's columns of leg l = i % L's contacts on the rows of block i // L
        blk = i // L
        l, r = i - blk * L, blk * row_rows + lax.iota(jnp.int32, row_rows)
        on_r = r < n
        rows, live = leg(l)
        P_l = load(p_ref.at[jnp.minimum(r, n - 1)[:, None], rows[None, :]], on_r[:, None] & on_f[None, :])
        S_l = dot(P_l, load(gram_ref.at[l, fc[:, None], F3 + kc[None, :]], live[:, None] & on_k[None, :]))
        pltriton.store(sl_ref.at[l, r[:, None], k[None, :]], S_l, mask=on_r[:, None] & on_k[None, :])
        pltriton.store(sd_ref.at[Kd3 + l * Kl3 + k[None, :], r[:, None]], S_l,  # its disk rows, transposed
                       mask=(r < Kd3)[:, None] & on_k[None, :])
        return carry

    row_rows = min(ROW_BLOCK, padded_size(n))
    lax.fori_loop(0, L * (padded_size(n) // row_rows), per_block, 0)


@partial(jax.jit, static_argnames=("interpret",))
def by_kernel(W_inv, disk_ad, gram, bilateral, u_b, u_c, *, interpret: bool = False):
    """:func:`products` in one kernel program (module doc; arguments and results as there; a
    batch of robots under ``jax.vmap``: one program a robot). ``interpret``: run it in Pallas'
    interpreter (any platform) instead of compiling it for a GPU."""
    from jax.experimental.pallas import triton as pltriton

    L, n_leg, _ = gram.shape
    A3, Kd3 = disk_ad.shape
    F3, n = A3 // L, u_c.shape[0]
    Kl3, dt = n_leg - F3, W_inv.dtype
    return pl.pallas_call(
        partial(_kernel, L, F3, kernel_precision(dt, DOT_ALGORITHM, interpret),
                (lambda: None) if interpret else pltriton.debug_barrier),
        out_shape=(jax.ShapeDtypeStruct((n, A3), dt), jax.ShapeDtypeStruct((n, Kd3), dt),
                   jax.ShapeDtypeStruct((L, n, Kl3), dt), jax.ShapeDtypeStruct((n,), dt),
                   jax.ShapeDtypeStruct((A3,), dt)),
        interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=NUM_WARPS, num_stages=1),
        name="attachment_elimination",
    )(W_inv, disk_ad.astype(dt), gram.astype(dt), bilateral.astype(jnp.int32), u_b.astype(dt), u_c.astype(dt))
