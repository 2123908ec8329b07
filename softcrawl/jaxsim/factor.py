"""The inverse of a symmetric positive definite matrix's Cholesky factor, and the matrix's inverse:
by the library, or in one GPU kernel.

The step solves with two kinds of small SPD matrices each time: every leg's step matrix (36 x 36
for the shipped leg) and the attachment block (72 x 72 for six legs). It forms the inverse ``C^-1``
of each leg's lower Cholesky factor ``A = C C^T`` and the attachment block's inverse once, so that
every later solve is a product (:func:`softcrawl.jaxsim.legs.free_motion`,
:func:`softcrawl.jaxsim.delassus.condense`).

``form="library"`` factorises and then solves against the identity (``jax.lax.linalg.cholesky``
and a triangular solve: LAPACK on a CPU; on a GPU cuSOLVER's batched factorisation and cuBLAS'
triangular solve, each a chain of kernel launches, ``benchmarks/RESULTS.md``). ``form="kernel"``
does both in one Pallas kernel on an NVIDIA GPU (Triton form, as :mod:`softcrawl.jaxsim.fused`), one
program per matrix, the matrix in registers in blocks of power-of-two sizes (:func:`row_parts`:
36 rows as 32 and 4, not padded to 64): Gaussian elimination of ``[A | I]`` without pivoting,
stable for SPD matrices as Cholesky's (Higham 2002, "Accuracy and Stability of Numerical
Algorithms", sec. 10.1-10.2). Step ``k`` subtracts ``l r_k^T`` from the rows below ``k``, with
``r_k`` row ``k`` of the current matrix and ``l_i = a_ik / d_k`` (``d_k = a_kk``, the pivot); the
same row operations turn ``I`` into ``L^-1`` of ``A = L D L^T`` (``L`` unit lower triangular), so
that ``C = L D^1/2`` and ``C^-1 = D^-1/2 L^-1``. :func:`step_solve` runs it on a leg's step
matrix formed in the program from its parts and solves the leg's free motion with the factor
in the same program (:func:`softcrawl.jaxsim.legs.free_motion`). A matrix that is not positive
definite gives a non-positive pivot and NaN or infinite entries, as the library's factorisation
gives NaN. On other platforms than CUDA (a CPU among them) and on GPUs older than Ampere
(:mod:`softcrawl.jaxsim.gpu`) ``"kernel"`` runs the library's form (``jax.lax.platform_dependent``);
``"interpret"`` runs the kernel in Pallas' interpreter on any platform (the tests').

Where the inverse itself is wanted (the attachment block, :func:`inverse_spd`), the kernel form
is the symmetric sweep operator instead (Goodnight 1979, "A tutorial on the SWEEP operator",
The American Statistician 33(3); Gauss-Jordan elimination with the diagonal pivots, Higham 2002,
sec. 14.4): sweeping pivot ``k`` (``d = a_kk``, ``c`` column ``k``) sets ``a_ij -= c_i c_j / d``
off row and column ``k``, ``a_ik = a_ki = c_i / d`` and ``a_kk = -1 / d``; after all ``n``
pivots the matrix is ``-A^-1``. One matrix, one column read and one rank-one update a pivot,
against three reads and two updates of two matrices for ``C^-1`` (then ``C^-T C^-1``, a product
more). Its pivots are the factorisation's; a non-positive one makes the result NaN.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import solve_triangular

from softcrawl.jaxsim.gpu import cuda_kernel

#: The forms of :func:`cholesky_inverse` a model may choose (``Settings.cholesky``).
CHOLESKY_FORMS = ("library", "kernel")


def fused_multiply_add(a, b, c, compiled: bool):
    """``a * b + c`` (broadcast together), one rounding: the GPU's ``fma.rn.f32`` where
    ``compiled`` and float32, the two operations otherwise (Pallas' interpreter, float64).
    Triton rounds each product and each sum of a Pallas kernel on its own (``mul.rn``,
    ``add.rn``), which ptxas may not fuse: two instructions where one does."""
    if not compiled or jnp.result_type(a, b, c) != jnp.float32:
        return a * b + c
    from jax.experimental.pallas import triton as pltriton

    a, b, c = jnp.broadcast_arrays(a, b, c)
    return pltriton.elementwise_inline_asm("fma.rn.f32 $0, $1, $2, $3;", args=[a, b, c], constraints="=f,f,f,f",
                                           pack=1, result_shape_dtypes=[jax.ShapeDtypeStruct(a.shape, a.dtype)])[0]


def padded_size(n: int) -> int:
    """The smallest power of two ``>= max(n, 16)``: the size a Triton program handles ``n`` rows
    at (its blocks have power-of-two shapes; :mod:`softcrawl.jaxsim.fused` too)."""
    return max(16, 1 << (int(n) - 1).bit_length())


#: Numbers of each of the program's ``(N, N)`` matrices (``N`` :func:`padded_size`) a thread would
#: hold, which sets its warps (:func:`_warps`; 1 to 16): 64 gives 2 warps for the legs (``N =
#: 64``) and 8 for the attachment block (``N = 128``), the fastest of 8, 16, 32 and 64 for both
#: sizes on an H200, and for the sweeps within 4% of the fastest of 16 to 128 on an H100, each
#: matrix then held padded (benchmarks/RESULTS.md); held in blocks (:func:`row_parts`), 96 and 78
#: registers a thread, no spill, on an H100 (ptxas' counts). Read when a call is traced:
#: ``benchmarks/cholesky_kernel.py`` times other values.
PER_THREAD = 64
#: Matrices in a batch (``jax.vmap``'s axis) from which :func:`inverse_spd`'s ``"kernel"`` form
#: hands the batch to the library, or None: never. Held padded to 128 rows, the sweeps of 16,384
#: attachment blocks took 7.37 ms on an H100 against cuSOLVER's batched factorisation and
#: inverse's 5.45 (at 96 blocks 0.104 against 0.263 ms), so the library served from 2,048 blocks;
#: held in blocks of 64 and 8 rows the kernel issues 2.7 times fewer instructions a matrix
#: (compiled for an H100: 125,192 warp instructions against 341,728), about 2.7 ms at the issue
#: rate the padded kernel ran at. Read when a call is traced: ``benchmarks/cholesky_kernel.py``
#: times the kernel against the library at the sizes between (``gpu_checks.sh crossover``).
LIBRARY_FROM = None

#: The largest matrix size whose pivots the kernels unroll, or 0 for none. Unrolled (one pivot's
#: step after another in straight-line code), the masks of pivot ``k``'s row and column are
#: constants: compiled for an H100 (``benchmarks/kernel_sass.py --kernel factor``), a leg's step
#: (:func:`step_solve`, 36 x 36 in blocks of 32 and 4 rows) issues 16,208 warp instructions
#: against the loop's 23,562 (8,104 instructions of code; 112 registers, no spill; at 128 numbers
#: a thread, one warp, 8,624), the attachment block's 72 x 72 inverse 88,640 against 125,192 (8
#: bytes spilled). The looped kernel, padded, ran 98,304 legs' matrices at about 80% of an H100's
#: issue rate (4.35 ms): there, fewer instructions should be faster, unless the longer code stalls
#: on its fetch. Measured on a GPU before it becomes a default (``benchmarks/cholesky_kernel.py``'
#: ``_unrolled`` variants). Read when a call is traced.
UNROLL_PIVOTS = 0
#: Whether :func:`step_solve`'s kernel forms (``"kernel"``, ``"interpret"``) form the matrix and
#: solve in the kernel's program, or XLA forms the matrix and multiplies by the factor around
#: :func:`cholesky_inverse`'s kernel (the step's form before; compiled for an H100, five to seven
#: more operations and 0.13 MB a robot-step at 16,384 robots, about 11% fewer warp instructions a
#: matrix in the kernel). Read when a call is traced: ``benchmarks/cholesky_kernel.py`` times both.
STEP_IN_KERNEL = True


def _warps(n: int) -> int:
    """Warps per program for ``n x n`` matrices (padded size ``N``, :data:`PER_THREAD`)."""
    N = padded_size(n)
    return max(1, min(16, N * N // (PER_THREAD * 32)))


def row_parts(n: int) -> tuple[tuple[int, int], ...]:
    """``((start, size), ...)``: the blocks of rows (and of columns) in which a program holds an
    ``n x n`` matrix, each of a power-of-two size (Triton's blocks have power-of-two shapes):
    one of :func:`padded_size` where ``n`` is a power of two, 16 or less, or its rest past the
    largest power of two below it would be padded to more than a quarter of :func:`padded_size`;
    else that power of two and the rest padded to a power of two (at least 4). 36 rows are
    ``((0, 32), (32, 4))`` and 72 ``((0, 64), (64, 8))``: a pivot's update touches 1,296 and
    5,184 numbers instead of the padded 64 x 64 and 128 x 128 matrices' 4,096 and 16,384."""
    N = padded_size(n)
    if n <= 16 or n == N:
        return ((0, N),)
    small = max(4, 1 << (n - N // 2 - 1).bit_length())
    return ((0, N),) if small > N // 4 else ((0, N // 2), (N // 2, small))


def _blocks(n: int, dt, load, symmetrize: bool = False):
    """A program's ``n x n`` matrix in the blocks of :func:`row_parts`: ``load(rows, cols,
    inside)`` its entries (``rows`` ``(a, 1)``, ``cols`` ``(1, b)`` global indices, masked by
    ``inside``: lanes past ``n`` load nothing), the identity on the padding; with
    ``symmetrize``, ``(A + A^T) / 2``, the transposes formed in the program (no transposing pass
    before the kernel).
    Returns ``(idx, inside, A)``: ``idx[i]`` the global indices of block ``i``'s rows,
    ``inside[i][j]`` the mask of block ``(i, j)``'s entries of the ``n x n`` matrix and
    ``A[i][j]`` the block."""
    idx = [start + lax.iota(jnp.int32, size) for start, size in row_parts(n)]
    P = range(len(idx))
    inside = [[(idx[i][:, None] < n) & (idx[j][None, :] < n) for j in P] for i in P]
    A = [[load(idx[i][:, None], idx[j][None, :], inside[i][j]) for j in P] for i in P]
    if symmetrize:
        A = [[(A[i][j] + A[j][i].T) / 2 for j in P] for i in P]
    return idx, inside, [[jnp.where(inside[i][j], A[i][j], _eye(idx[i], idx[j], dt)) for j in P] for i in P]


def _eye(rows, cols, dt):
    """The identity's block of global ``rows`` ``(a,)`` and ``cols`` ``(b,)``."""
    return (rows[:, None] == cols[None, :]).astype(dt)


def _read(a_ref):
    """:func:`_blocks`' ``load`` of a matrix ``a_ref`` read whole through masked pointers."""
    from jax.experimental.pallas import triton as pltriton

    return lambda rows, cols, inside: pltriton.load(a_ref.at[rows, cols], mask=inside, other=0.0)


def _store(o_ref, idx, inside, blocks):
    """Store ``blocks[i][j]`` (None: zeros) at block ``(i, j)`` of ``o_ref`` through masked
    pointers: lanes past ``n`` store nothing."""
    from jax.experimental.pallas import triton as pltriton

    for i, rows in enumerate(idx):
        for j, cols in enumerate(idx):
            value = blocks[i][j] if blocks[i][j] is not None else jnp.zeros((rows.shape[0], cols.shape[0]), o_ref.dtype)
            pltriton.store(o_ref.at[rows[:, None], cols[None, :]], value, mask=inside[i][j])


def _block_pivots(n: int, idx, body, init):
    """``body(p, k, carry)`` for the pivots of block ``p = 0, 1, ...`` in turn, ``k`` the pivot's
    index in its block: each block's a loop, or unrolled where ``n <=`` :data:`UNROLL_PIVOTS`;
    the padding's rows are no pivots."""
    start = 0
    for p, rows in enumerate(idx):
        pivots = min(n - start, rows.shape[0])
        if n > UNROLL_PIVOTS:
            init = lax.fori_loop(0, pivots, partial(body, p), init)
        else:
            for k in range(pivots):
                init = body(p, k, init)
        start += rows.shape[0]
    return init


def _at(idx, p, k):
    """Per block ``i``, the mask of block ``p``'s row ``k`` among block ``i``'s rows (none
    where ``i != p``), and the index of block ``p``'s row ``k`` in the matrix."""
    local = [lax.iota(jnp.int32, rows.shape[0]) for rows in idx]
    at = [(local[i] == k) if i == p else jnp.zeros(rows.shape, bool) for i, rows in enumerate(idx)]
    return at, sum(rows.shape[0] for rows in idx[:p]) + k


def _eliminated(n: int, fma, idx, A):
    """``C^-1`` of a program's matrix in blocks (:func:`_blocks`' ``idx`` and ``A``) by the module
    doc's elimination of its ``n`` pivots, ``fma`` the rank-one updates' multiply-add
    (:func:`fused_multiply_add`): its blocks ``(i, j)``, ``j <= i`` (None above: zero). A pivot of
    block ``p`` changes the matrix's blocks ``(i, j)``, ``i, j >= p`` (the rows above the pivot
    keep theirs; the columns of earlier blocks are eliminated and not read again) and the
    inverse's ``(i, j)``, ``i >= p >= j``."""
    P = range(len(idx))
    dt = A[0][0].dtype
    T = [[_eye(idx[i], idx[j], dt) for j in range(i + 1)] for i in P]
    d = [jnp.ones(rows.shape, dt) for rows in idx]

    def body(p, k, c):
        A, T, d = c
        at, kk = _at(idx, p, k)
        col = {i: jnp.sum(jnp.where(at[p][None, :], A[i][p], 0), axis=1) for i in P if i >= p}  # column k
        row = {j: jnp.sum(jnp.where(at[p][:, None], A[p][j], 0), axis=0) for j in P if j >= p}  # row k
        trow = {j: jnp.sum(jnp.where(at[p][:, None], T[p][j], 0), axis=0) for j in range(p + 1)}
        dk = jnp.sum(jnp.where(at[p], col[p], 0))
        l = {i: jnp.where(idx[i] > kk, col[i] / dk, 0) for i in col}
        A = [[fma(-l[i][:, None], row[j][None, :], A[i][j]) if min(i, j) >= p else A[i][j] for j in P] for i in P]
        T = [[fma(-l[i][:, None], trow[j][None, :], T[i][j]) if i >= p >= j else T[i][j] for j in range(i + 1)]
             for i in P]
        return A, T, [jnp.where(at[p], dk, d[p]) if i == p else d[i] for i in P]

    _, T, d = _block_pivots(n, idx, body, (A, T, d))
    return [[T[i][j] * lax.rsqrt(d[i])[:, None] if j <= i else None for j in P] for i in P]


def _kernel(n: int, fma, symmetrize: bool, a_ref, o_ref):
    """One matrix (module doc): ``a_ref`` ``(n, n)`` the symmetric matrix, read whole (with
    ``symmetrize``, ``(A + A^T) / 2``); ``o_ref`` receives ``C^-1``; ``fma`` the rank-one updates'
    multiply-add (:func:`fused_multiply_add`). The program holds the matrix in the blocks of
    :func:`row_parts` (:func:`_blocks`) and writes through masked pointers."""
    idx, inside, A = _blocks(n, o_ref.dtype, _read(a_ref), symmetrize)
    _store(o_ref, idx, inside, _eliminated(n, fma, idx, A))


def _step_kernel(n: int, k: int, numbers: tuple, fma, barrier, m_ref, k_ref, fs_ref, s_ref, f_ref, w_ref, x_ref,
                 o_ref, y_ref):
    """:func:`step_solve`'s one matrix: ``A = alpha M + beta K_s`` formed in the program from
    ``m_ref`` ``(n, n)`` and ``k_ref`` ``(k, k)`` placed by ``s_ref`` ``(n,)`` (index ``k``: a zero
    row and column), symmetrized; ``o_ref`` receives ``C^-1`` (:func:`_eliminated`) and ``y_ref``
    ``x + C^-T C^-1 h (w f + f_s - rate M x)`` of ``fs_ref`` ``(k,)`` (placed as ``K``), ``f_ref``
    and ``x_ref`` ``(n,)`` and ``w_ref`` ``(1,)``; ``numbers`` ``(alpha, beta, h, rate)``;
    ``barrier()`` the program's (none in the interpreter). In blocks as :func:`_kernel`; the
    products after the factor on the matrices padded to :func:`padded_size`, masked."""
    from jax.experimental.pallas import triton as pltriton

    alpha, beta, h, rate = numbers

    def formed(rows, cols, inside):
        si, sj = (pltriton.load(s_ref.at[i], mask=i < n, other=k) for i in (rows, cols))
        K = pltriton.load(k_ref.at[si, sj], mask=(si < k) & (sj < k), other=0.0)
        return alpha * _read(m_ref)(rows, cols, inside) + beta * K

    idx, inside, A = _blocks(n, o_ref.dtype, formed, symmetrize=True)
    _store(o_ref, idx, inside, _eliminated(n, fma, idx, A))
    # read back after a barrier (the factor, and M and the slots again): products with the factor
    # in registers change the layout Triton gives the elimination (684 instructions a pivot and
    # 229 registers instead of 508 and 128, padded)
    barrier()
    r = lax.iota(jnp.int32, padded_size(n))
    rows, cols, on = r[:, None], r[None, :], r < n
    whole = (rows < n) & (cols < n)
    Ci, M = _read(o_ref)(rows, cols, whole), _read(m_ref)(rows, cols, whole)
    s = pltriton.load(s_ref.at[r], mask=on, other=k)
    x = pltriton.load(x_ref.at[r], mask=on, other=0.0)
    f = pltriton.load(f_ref.at[r], mask=on, other=0.0) * w_ref[0] + pltriton.load(fs_ref.at[s], mask=s < k, other=0.0)
    b = h * (f - rate * jnp.sum(M * x[None, :], axis=1))
    y = jnp.sum(Ci * b[None, :], axis=1)  # C^-1 b
    pltriton.store(y_ref.at[r], x + jnp.sum(Ci * y[:, None], axis=0), mask=on)


def _sweep_kernel(n: int, fma, symmetrize: bool, a_ref, o_ref):
    """One matrix's inverse by the symmetric sweep operator (module doc): ``a_ref`` ``(n, n)``
    the symmetric matrix, read whole (with ``symmetrize``, ``(A + A^T) / 2``); ``o_ref``
    receives ``A^-1``. In blocks and masked as :func:`_kernel`; the padding's identity rows are
    never swept."""
    idx, inside, A = _blocks(n, o_ref.dtype, _read(a_ref), symmetrize)
    P = range(len(idx))

    def body(p, k, c):
        A, low = c
        at, _ = _at(idx, p, k)
        col = [jnp.sum(jnp.where(at[p][None, :], A[i][p], 0), axis=1) for i in P]
        dk = jnp.sum(jnp.where(at[p], col[p], 0))
        u = [jnp.where(at[i], -1.0, col[i]) / dk for i in P]
        return ([[fma(-(dk * u[i])[:, None], u[j][None, :], jnp.where(at[i][:, None] | at[j][None, :], 0, A[i][j]))
                  for j in P] for i in P], jnp.minimum(low, dk))

    A, low = _block_pivots(n, idx, body, (A, jnp.ones((), o_ref.dtype)))
    _store(o_ref, idx, inside, [[jnp.where(low > 0, -A[i][j], jnp.nan) for j in P] for i in P])


def _library(A, symmetrize: bool = False):
    C = lax.linalg.cholesky(A, symmetrize_input=symmetrize)
    return solve_triangular(C, jnp.eye(A.shape[-1], dtype=A.dtype), lower=True)


def _pallas(A, interpret: bool, kernel=_kernel, name: str = "cholesky_inverse", symmetrize: bool = False):
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    n = A.shape[-1]
    return pl.pallas_call(
        partial(kernel, n, partial(fused_multiply_add, compiled=not interpret), symmetrize),
        out_shape=jax.ShapeDtypeStruct((n, n), A.dtype), interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=_warps(n), num_stages=1),
        name=name)(A)


def _check(A, form: str) -> None:
    if form not in (*CHOLESKY_FORMS, "interpret"):
        raise ValueError(f"form must be one of {CHOLESKY_FORMS} or 'interpret', not {form!r}")
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"cholesky_inverse and inverse_spd need one square matrix, got shape {A.shape}")


def cholesky_inverse(A, form: str = "library", symmetrize: bool = False):
    """``C^-1`` ``(n, n)`` (lower triangular), the inverse of the lower Cholesky factor of a
    symmetric positive definite ``A = C C^T`` ``(n, n)`` (any units: ``C^-1`` has the inverse
    square root of ``A``'s), by the module doc's ``form``: ``"library"``, ``"kernel"`` (one GPU
    kernel on CUDA, the library's form elsewhere) or ``"interpret"`` (the kernel in Pallas' interpreter).
    The library reads ``A``'s lower triangle only, the kernel the whole of it; ``symmetrize``
    factors ``(A + A^T) / 2`` instead, in every form (as ``jnp.linalg.cholesky``: for a matrix
    symmetric up to round-off, the step matrices' sums; the kernel forms it itself).
    Its error is of the order of ``cond(A)`` times the rounding unit (Higham 2002, sec. 10.1).
    Batch it with ``jax.vmap`` (the kernel: one program per matrix).

    Raises:
        ValueError: an unknown ``form``, or ``A`` not square.
    """
    _check(A, form)
    if form == "library":
        return _library(A, symmetrize)

    def kernel(a, interpret):
        return _pallas(a, interpret, symmetrize=symmetrize)

    if form == "interpret":
        return kernel(A, True)
    return lax.platform_dependent(A, **cuda_kernel(partial(kernel, interpret=False)),
                                  default=partial(_library, symmetrize=symmetrize))


def step_solve(M, K, f_s, slots, f, w, x, alpha: float, beta: float, h: float, rate: float, form: str = "library"):
    """A linearly implicit step's solve: ``A = alpha M + beta K_s`` (symmetrized) and ``x + A^-1 h
    (w f + f_s - rate M x)``, where ``K_s`` ``(n, n)`` and ``f_s`` ``(n,)`` are ``K`` ``(k, k)`` and
    ``f_s`` ``(k,)`` placed by ``slots`` ``(n,)`` int (``K_s[i, j] = K[slots[i], slots[j]]``, zero
    where a slot is ``k``) and ``w`` a number (an array or bool). A leg's step
    (:func:`softcrawl.jaxsim.legs.free_motion`): ``M`` its mass, ``K`` and ``f_s`` its RID
    stiffness and internal forces, ``f`` its external load, ``w`` whether the leg exists, ``x``
    its modal velocity, ``alpha = 1 + h r_M``, ``beta = h (h + r_K)``, ``rate = r_M`` (Rayleigh
    damping). Returns ``(C^-1 (n, n), x + A^-1 h (w f + f_s - rate M x) (n,))``, ``C^-1`` as
    :func:`cholesky_inverse` gives it. ``form`` as :func:`cholesky_inverse`'s: ``"library"``
    forms ``A`` and solves by XLA's products; ``"kernel"`` (CUDA; the library's form elsewhere)
    and ``"interpret"`` do all of it in one kernel program a matrix (:func:`cholesky_inverse`'s
    elimination, ``A`` formed as it is read, the right-hand side and ``A^-1`` times it from
    ``C^-1`` read back by the same program: no matrix ``A`` in memory, no product before or after
    the kernel), unless :data:`STEP_IN_KERNEL` is off. The numbers ``alpha``, ``beta``, ``h``
    and ``rate`` are compiled into the kernel. Batch it with ``jax.vmap`` (``M`` and ``slots``
    may be shared).

    Raises:
        ValueError: an unknown ``form``, or arrays of other shapes.
    """
    _check(M, form)
    n, k = M.shape[0], K.shape[0]
    if (K.shape != (k, k) or f_s.shape != (k,) or slots.shape != (n,) or f.shape != (n,) or jnp.ndim(w)
            or x.shape != (n,)):
        raise ValueError(f"step_solve needs (n, n) M, (k, k) K, (k,) f_s, (n,) slots and f, one w and (n,) x; got "
                         f"{M.shape}, {K.shape}, {f_s.shape}, {slots.shape}, {f.shape}, {jnp.shape(w)}, {x.shape}")
    arrays, numbers = (M, K, f_s, slots, f, jnp.asarray(w), x), (alpha, beta, h, rate)
    if form == "library":
        return _step_library(*arrays, *numbers)
    if not STEP_IN_KERNEL:
        return _step_library(*arrays, *numbers, factor=partial(cholesky_inverse, form=form, symmetrize=True))
    if form == "interpret":
        return _step_pallas(*arrays, *numbers, interpret=True)
    named = dict(zip(("alpha", "beta", "h", "rate"), numbers))
    return lax.platform_dependent(*arrays, **cuda_kernel(partial(_step_pallas, **named, interpret=False)),
                                  default=partial(_step_library, **named))


def _step_library(M, K, f_s, slots, f, w, x, alpha, beta, h, rate, factor=None):
    """:func:`step_solve` by XLA's products (``factor``: the factor's form, the library's if
    None), its arguments in :func:`step_solve`'s order."""
    A = alpha * M + beta * jnp.pad(K, ((0, 1), (0, 1)))[slots[:, None], slots[None, :]]
    Ci = _library(A, symmetrize=True) if factor is None else factor(A)
    b = h * (f * w + jnp.pad(f_s, (0, 1))[slots] - rate * (M @ x))
    return Ci, x + Ci.T @ (Ci @ b)


def _step_pallas(M, K, f_s, slots, f, w, x, alpha, beta, h, rate, interpret: bool):
    """:func:`step_solve` in one kernel (:func:`_step_kernel`), its arguments in its order."""
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    n, dt = M.shape[0], M.dtype
    barrier = (lambda: None) if interpret else pltriton.debug_barrier
    return pl.pallas_call(
        partial(_step_kernel, n, K.shape[0], tuple(float(v) for v in (alpha, beta, h, rate)),
                partial(fused_multiply_add, compiled=not interpret), barrier),
        out_shape=(jax.ShapeDtypeStruct((n, n), dt), jax.ShapeDtypeStruct((n,), dt)), interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=_warps(n), num_stages=1),
        name="step_solve")(M, K.astype(dt), f_s.astype(dt), slots.astype(jnp.int32), f.astype(dt),
                           w.astype(dt).reshape(1), x.astype(dt))


def inverse_spd(A, form: str = "library"):
    """The inverse ``(n, n)`` of a symmetric positive definite ``A`` ``(n, n)`` (read whole), by
    ``form`` as :func:`cholesky_inverse`'s: ``"library"`` is ``C^-T C^-1`` from that function's
    library form; ``"kernel"`` (CUDA; the library's form elsewhere) and ``"interpret"`` are the
    module doc's sweeps in one kernel, which form ``A^-1`` without a factor; ``"kernel"``
    batched by ``jax.vmap`` over :data:`LIBRARY_FROM` matrices or more (where it is not None)
    is the library's form. Its error is of the order of ``cond(A)`` times the rounding unit, as a
    solve's (Higham 2002, sec. 14.4); a matrix that is not positive definite gives NaN or
    infinite entries in every form.

    Raises:
        ValueError: an unknown ``form``, or ``A`` not square.
    """
    _check(A, form)
    if form == "library":  # the product at full precision wherever it is traced (a GPU's float32 default is TF32)
        Ci = _library(A)
        return jnp.matmul(Ci.T, Ci, precision=lax.Precision.HIGHEST)
    if form == "interpret":
        return _sweeps(A, True)
    return _inverse_by_batch(A)


_sweeps = partial(_pallas, kernel=_sweep_kernel, name="inverse_spd")


def _sweeps_on_cuda(A):
    return lax.platform_dependent(A, **cuda_kernel(partial(_sweeps, interpret=False)), default=inverse_spd)


@jax.custom_batching.custom_vmap
def _inverse_by_batch(A):
    """:func:`inverse_spd`'s ``"kernel"`` form: the sweeps on CUDA; batched by ``jax.vmap``, the
    library's form from :data:`LIBRARY_FROM` matrices (the innermost ``vmap``'s size)."""
    return _sweeps_on_cuda(A)


@_inverse_by_batch.def_vmap
def _inverse_batched(axis_size, in_batched, A):
    if not in_batched[0]:
        return _inverse_by_batch(A), False
    library = LIBRARY_FROM is not None and axis_size >= LIBRARY_FROM
    return jax.vmap(inverse_spd if library else _sweeps_on_cuda)(A), True
