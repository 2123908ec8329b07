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
program per matrix, the matrix in registers: Gaussian elimination of ``[A | I]`` without pivoting,
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


#: Numbers of each of the program's ``(N, N)`` matrices a thread holds, which sets its warps
#: (:func:`_warps`; 1 to 16): 64 gives 2 warps for the legs (``N = 64``) and 8 for the attachment
#: block (``N = 128``), 128 registers a thread, no spill on an H100 (ptxas' counts), the fastest
#: of 8, 16, 32 and 64 for both sizes on an H200, and for the sweeps within 4% of the fastest of
#: 16 to 128 on an H100 (benchmarks/RESULTS.md). Read when a call is traced:
#: ``benchmarks/cholesky_kernel.py`` times other values.
PER_THREAD = 64
#: Matrices in a batch (``jax.vmap``'s axis) from which :func:`inverse_spd`'s ``"kernel"`` form
#: hands the batch to the library: one program a matrix pads the attachment block's 72 rows to
#: 128, and at 16,384 blocks cuSOLVER's batched factorisation and inverse take 5.45 ms against
#: the sweeps' 7.37; at 96, 0.263 against 0.104 (H100, benchmarks/RESULTS.md). A line through
#: both crosses at about 1,900 blocks; ``benchmarks/cholesky_kernel.py`` times the sizes between.
#: Read when a call is traced.
LIBRARY_FROM = 2048

#: The largest matrix size whose pivots the kernels unroll, or 0 for none. Unrolled (one pivot's
#: step after another in straight-line code), the masks of pivot ``k``'s row and column are
#: constants: compiled for an H100 (``benchmarks/kernel_sass.py --kernel factor``), a leg's 36 x
#: 36 factor (symmetrized, as the step asks) takes 208 instructions a pivot and warp against the
#: loop's 495, 14,976 warp instructions a matrix against 35,640 (7,488 instructions of code, 120
#: KB; 164 registers, no spill; at 128 numbers a thread, one warp, 10,800), the attachment
#: block's 72 x 72 inverse 390
#: against 588 (28,112 instructions, 24 bytes spilled). The looped kernel ran 98,304 legs'
#: matrices at about 80% of an H100's issue rate (4.35 ms): there, fewer instructions should be
#: faster, unless the longer code stalls on its fetch. Measured on a GPU before it becomes a
#: default (``benchmarks/cholesky_kernel.py``' ``_unrolled`` variants). Read when a call is traced.
UNROLL_PIVOTS = 0
#: Whether :func:`step_solve`'s kernel forms (``"kernel"``, ``"interpret"``) form the matrix and
#: solve in the kernel's program, or XLA forms the matrix and multiplies by the factor around
#: :func:`cholesky_inverse`'s kernel (the step's form before; compiled for an H100, five to seven
#: more operations and 0.13 MB a robot-step at 16,384 robots, about 11% fewer warp instructions a
#: matrix in the kernel). Read when a call is traced: ``benchmarks/cholesky_kernel.py`` times both.
STEP_IN_KERNEL = True


def _pivots(n: int, body, init):
    """``body(k, carry)`` for pivots ``k = 0 .. n - 1``: a loop, or unrolled where ``n <=``
    :data:`UNROLL_PIVOTS`."""
    if n > UNROLL_PIVOTS:
        return lax.fori_loop(0, n, body, init)
    for k in range(n):
        init = body(k, init)
    return init


def _warps(N: int) -> int:
    """Warps per program for a padded size ``N`` (:data:`PER_THREAD`)."""
    return max(1, min(16, N * N // (PER_THREAD * 32)))


def _padded(n: int, dt, load, symmetrize: bool = False):
    """A program's ``n x n`` matrix at the padded size ``N``: ``load(rows, cols, inside)`` its
    entries (``rows`` ``(N, 1)``, ``cols`` ``(1, N)``, masked by ``inside``: lanes past ``n`` load
    nothing), the identity on the padding; with ``symmetrize``, ``(A + A^T) / 2``, the transpose
    formed in the program (no transposing pass before the kernel).
    Returns the lane indices ``r`` ``(N,)``, ``rows``, ``cols``, the mask ``inside`` of the ``n x
    n`` entries, the identity and the matrix ``(N, N)``."""
    r = lax.iota(jnp.int32, padded_size(n))
    rows, cols = r[:, None], r[None, :]
    inside = (rows < n) & (cols < n)
    eye = (rows == cols).astype(dt)
    A = load(rows, cols, inside)
    if symmetrize:
        A = (A + A.T) / 2
    return r, rows, cols, inside, eye, jnp.where(inside, A, eye)


def _read(a_ref):
    """:func:`_padded`'s ``load`` of a matrix ``a_ref`` read whole through masked pointers."""
    from jax.experimental.pallas import triton as pltriton

    return lambda rows, cols, inside: pltriton.load(a_ref.at[rows, cols], mask=inside, other=0.0)


def _eliminated(n: int, fma, r, rows, cols, eye, A):
    """``C^-1`` ``(N, N)`` of a program's padded matrix ``A`` (:func:`_padded`'s ``r``, ``rows``,
    ``cols``, ``eye`` and matrix) by the module doc's elimination of its ``n`` pivots; ``fma`` the
    rank-one updates' multiply-add (:func:`fused_multiply_add`)."""
    def body(k, c):
        A, T, d = c
        col = jnp.sum(jnp.where(cols == k, A, 0), axis=1)  # column k, by rows
        row = jnp.sum(jnp.where(rows == k, A, 0), axis=0)  # row k, by columns
        trow = jnp.sum(jnp.where(rows == k, T, 0), axis=0)
        dk = jnp.sum(jnp.where(r == k, col, 0))
        l = jnp.where(r > k, col / dk, 0)
        return fma(-l[:, None], row[None, :], A), fma(-l[:, None], trow[None, :], T), jnp.where(r == k, dk, d)

    _, T, d = _pivots(n, body, (A, eye, jnp.ones(r.shape, A.dtype)))
    return T * lax.rsqrt(d)[:, None]


def _kernel(n: int, fma, symmetrize: bool, a_ref, o_ref):
    """One matrix (module doc): ``a_ref`` ``(n, n)`` the symmetric matrix, read whole (with
    ``symmetrize``, ``(A + A^T) / 2``); ``o_ref`` receives ``C^-1``; ``fma`` the rank-one updates'
    multiply-add (:func:`fused_multiply_add`). The program works on the padded size ``N``
    (:func:`_padded`) and writes through masked pointers: lanes past ``n`` store nothing."""
    from jax.experimental.pallas import triton as pltriton

    r, rows, cols, inside, eye, A = _padded(n, o_ref.dtype, _read(a_ref), symmetrize)
    pltriton.store(o_ref.at[rows, cols], _eliminated(n, fma, r, rows, cols, eye, A), mask=inside)


def _step_kernel(n: int, k: int, numbers: tuple, fma, barrier, m_ref, k_ref, fs_ref, s_ref, f_ref, w_ref, x_ref,
                 o_ref, y_ref):
    """:func:`step_solve`'s one matrix: ``A = alpha M + beta K_s`` formed in the program from
    ``m_ref`` ``(n, n)`` and ``k_ref`` ``(k, k)`` placed by ``s_ref`` ``(n,)`` (index ``k``: a zero
    row and column), symmetrized; ``o_ref`` receives ``C^-1`` (:func:`_eliminated`) and ``y_ref``
    ``x + C^-T C^-1 h (w f + f_s - rate M x)`` of ``fs_ref`` ``(k,)`` (placed as ``K``), ``f_ref``
    and ``x_ref`` ``(n,)`` and ``w_ref`` ``(1,)``; ``numbers`` ``(alpha, beta, h, rate)``;
    ``barrier()`` the program's (none in the interpreter). Padded and masked as :func:`_kernel`."""
    from jax.experimental.pallas import triton as pltriton

    alpha, beta, h, rate = numbers

    def formed(rows, cols, inside):
        si, sj = (pltriton.load(s_ref.at[i], mask=i < n, other=k) for i in (rows, cols))
        K = pltriton.load(k_ref.at[si, sj], mask=(si < k) & (sj < k), other=0.0)
        return alpha * _read(m_ref)(rows, cols, inside) + beta * K

    r, rows, cols, inside, eye, A = _padded(n, o_ref.dtype, formed, symmetrize=True)
    pltriton.store(o_ref.at[rows, cols], _eliminated(n, fma, r, rows, cols, eye, A), mask=inside)
    # read back after a barrier (the factor, and M and the slots again): products with the factor
    # in registers change the layout Triton gives the elimination (684 instructions a pivot and
    # 229 registers instead of 508 and 128)
    barrier()
    on = r < n
    Ci, M = _read(o_ref)(rows, cols, inside), _read(m_ref)(rows, cols, inside)
    s = pltriton.load(s_ref.at[r], mask=on, other=k)
    x = pltriton.load(x_ref.at[r], mask=on, other=0.0)
    f = pltriton.load(f_ref.at[r], mask=on, other=0.0) * w_ref[0] + pltriton.load(fs_ref.at[s], mask=s < k, other=0.0)
    b = h * (f - rate * jnp.sum(M * x[None, :], axis=1))
    y = jnp.sum(Ci * b[None, :], axis=1)  # C^-1 b
    pltriton.store(y_ref.at[r], x + jnp.sum(Ci * y[:, None], axis=0), mask=on)


def _sweep_kernel(n: int, fma, symmetrize: bool, a_ref, o_ref):
    """One matrix's inverse by the symmetric sweep operator (module doc): ``a_ref`` ``(n, n)``
    the symmetric matrix, read whole (with ``symmetrize``, ``(A + A^T) / 2``); ``o_ref``
    receives ``A^-1``. Padded and masked as :func:`_kernel`; the padding's identity rows are
    never swept."""
    from jax.experimental.pallas import triton as pltriton

    r, rows, cols, inside, _, A = _padded(n, o_ref.dtype, _read(a_ref), symmetrize)

    def body(k, c):
        A, low = c
        col = jnp.sum(jnp.where(cols == k, A, 0), axis=1)
        dk = jnp.sum(jnp.where(r == k, col, 0))
        u = jnp.where(r == k, -1.0, col) / dk
        return fma(-(dk * u)[:, None], u[None, :], jnp.where((rows == k) | (cols == k), 0, A)), jnp.minimum(low, dk)

    A, low = _pivots(n, body, (A, jnp.ones((), A.dtype)))
    pltriton.store(o_ref.at[rows, cols], jnp.where(low > 0, -A, jnp.nan), mask=inside)


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
        compiler_params=pltriton.CompilerParams(num_warps=_warps(padded_size(n)), num_stages=1),
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
        compiler_params=pltriton.CompilerParams(num_warps=_warps(padded_size(n)), num_stages=1),
        name="step_solve")(M, K.astype(dt), f_s.astype(dt), slots.astype(jnp.int32), f.astype(dt),
                           w.astype(dt).reshape(1), x.astype(dt))


def inverse_spd(A, form: str = "library"):
    """The inverse ``(n, n)`` of a symmetric positive definite ``A`` ``(n, n)`` (read whole), by
    ``form`` as :func:`cholesky_inverse`'s: ``"library"`` is ``C^-T C^-1`` from that function's
    library form; ``"kernel"`` (CUDA; the library's form elsewhere) and ``"interpret"`` are the
    module doc's sweeps in one kernel, which form ``A^-1`` without a factor; ``"kernel"``
    batched by ``jax.vmap`` over :data:`LIBRARY_FROM` matrices or more is the library's form,
    faster there. Its error is of the order of ``cond(A)`` times the rounding unit, as a
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
    return jax.vmap(inverse_spd if axis_size >= LIBRARY_FROM else _sweeps_on_cuda)(A), True
