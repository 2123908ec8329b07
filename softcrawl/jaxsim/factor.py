"""The inverse of a symmetric positive definite matrix's Cholesky factor: by the library, or in one GPU kernel.

The step solves with two kinds of small SPD matrices each time: every leg's step matrix (36 x 36
for the shipped leg) and the attachment block (72 x 72 for six legs). It forms the inverse ``C^-1``
of each one's lower Cholesky factor ``A = C C^T`` once, so that every later solve is a product
(:func:`softcrawl.jaxsim.legs.free_motion`, :func:`softcrawl.jaxsim.delassus.condense`).

``form="library"`` factorises and then solves against the identity (``jax.lax.linalg.cholesky``
and a triangular solve: LAPACK on a CPU; on a GPU cuSOLVER's batched factorisation and cuBLAS'
triangular solve, each a chain of kernel launches, ``benchmarks/RESULTS.md``). ``form="kernel"``
does both in one Pallas kernel on an NVIDIA GPU (Triton form, as :mod:`softcrawl.jaxsim.fused`), one
program per matrix, the matrix in registers: Gaussian elimination of ``[A | I]`` without pivoting,
stable for SPD matrices as Cholesky's (Higham 2002, "Accuracy and Stability of Numerical
Algorithms", sec. 10.1-10.2). Step ``k`` subtracts ``l r_k^T`` from the rows below ``k``, with
``r_k`` row ``k`` of the current matrix and ``l_i = a_ik / d_k`` (``d_k = a_kk``, the pivot); the
same row operations turn ``I`` into ``L^-1`` of ``A = L D L^T`` (``L`` unit lower triangular), so
that ``C = L D^1/2`` and ``C^-1 = D^-1/2 L^-1``. A matrix that is not positive definite gives a
non-positive pivot and NaN or infinite entries, as the library's factorisation gives NaN. On
other platforms than CUDA (a CPU among them) ``"kernel"`` runs the library's form
(``jax.lax.platform_dependent``); ``"interpret"`` runs the kernel in Pallas' interpreter on any
platform (the tests').
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import solve_triangular

#: The forms of :func:`cholesky_inverse` a model may choose (``Settings.cholesky``).
CHOLESKY_FORMS = ("library", "kernel")


def padded_size(n: int) -> int:
    """The smallest power of two ``>= max(n, 16)``: the size a Triton program handles ``n`` rows
    at (its blocks have power-of-two shapes; :mod:`softcrawl.jaxsim.fused` too)."""
    return max(16, 1 << (int(n) - 1).bit_length())


#: Numbers of each of the program's two ``(N, N)`` matrices a thread holds, which sets its warps
#: (:func:`_warps`; 1 to 16): 64 gives 2 warps for the legs (``N = 64``) and 8 for the attachment
#: block (``N = 128``), 128 registers a thread, no spill on an H100 (ptxas' counts), the fastest
#: of 8, 16, 32 and 64 for both sizes on an H200 (benchmarks/RESULTS.md). Read when a call is
#: traced: ``benchmarks/cholesky_kernel.py`` times other values.
PER_THREAD = 64


def _warps(N: int) -> int:
    """Warps per program for a padded size ``N`` (:data:`PER_THREAD`)."""
    return max(1, min(16, N * N // (PER_THREAD * 32)))


def _kernel(n: int, a_ref, o_ref):
    """One matrix (module doc): ``a_ref`` ``(n, n)`` the symmetric matrix, read whole; ``o_ref``
    receives ``C^-1``. The program works on the padded size ``N`` (the identity on the padding)
    and reads and writes through masked pointers: lanes past ``n`` neither load nor store."""
    N = padded_size(n)
    dt = o_ref.dtype
    from jax.experimental.pallas import triton as pltriton

    r = lax.iota(jnp.int32, N)
    rows, cols = r[:, None], r[None, :]
    inside = (rows < n) & (cols < n)
    eye = (rows == cols).astype(dt)
    A = jnp.where(inside, pltriton.load(a_ref.at[rows, cols], mask=inside, other=0.0), eye)

    def body(k, c):
        A, T, d = c
        col = jnp.sum(jnp.where(cols == k, A, 0), axis=1)  # column k, by rows
        row = jnp.sum(jnp.where(rows == k, A, 0), axis=0)  # row k, by columns
        trow = jnp.sum(jnp.where(rows == k, T, 0), axis=0)
        dk = jnp.sum(jnp.where(r == k, col, 0))
        l = jnp.where(r > k, col / dk, 0)
        return A - l[:, None] * row[None, :], T - l[:, None] * trow[None, :], jnp.where(r == k, dk, d)

    _, T, d = lax.fori_loop(0, n, body, (A, eye, jnp.ones((N,), dt)))
    pltriton.store(o_ref.at[rows, cols], T * lax.rsqrt(d)[:, None], mask=inside)


def _library(A, symmetrize: bool = False):
    C = lax.linalg.cholesky(A, symmetrize_input=symmetrize)
    return solve_triangular(C, jnp.eye(A.shape[-1], dtype=A.dtype), lower=True)


def _pallas(A, interpret: bool):
    from jax.experimental import pallas as pl
    from jax.experimental.pallas import triton as pltriton

    n = A.shape[-1]
    return pl.pallas_call(
        partial(_kernel, n), out_shape=jax.ShapeDtypeStruct((n, n), A.dtype), interpret=interpret,
        compiler_params=pltriton.CompilerParams(num_warps=_warps(padded_size(n)), num_stages=1),
        name="cholesky_inverse")(A)


def cholesky_inverse(A, form: str = "library", symmetrize: bool = False):
    """``C^-1`` ``(n, n)`` (lower triangular), the inverse of the lower Cholesky factor of a
    symmetric positive definite ``A = C C^T`` ``(n, n)`` (any units: ``C^-1`` has the inverse
    square root of ``A``'s), by the module doc's ``form``: ``"library"``, ``"kernel"`` (one GPU
    kernel on CUDA, the library's form elsewhere) or ``"interpret"`` (the kernel in Pallas' interpreter).
    The library reads ``A``'s lower triangle only, the kernel the whole of it; ``symmetrize``
    factors ``(A + A^T) / 2`` instead, in every form (as ``jnp.linalg.cholesky``: for a matrix
    symmetric up to round-off, the step matrices' sums). Its error is of the order of
    ``cond(A)`` times the rounding unit (Higham 2002, sec. 10.1). Batch it with ``jax.vmap``
    (the kernel: one program per matrix).

    Raises:
        ValueError: an unknown ``form``, or ``A`` not square.
    """
    if form not in (*CHOLESKY_FORMS, "interpret"):
        raise ValueError(f"form must be one of {CHOLESKY_FORMS} or 'interpret', not {form!r}")
    if A.ndim != 2 or A.shape[0] != A.shape[1]:
        raise ValueError(f"cholesky_inverse needs one square matrix, got shape {A.shape}")
    if form == "library":
        return _library(A, symmetrize)

    def kernel(a, interpret):
        return _pallas((a + a.T) / 2 if symmetrize else a, interpret)

    if form == "interpret":
        return kernel(A, True)
    return lax.platform_dependent(A, cuda=partial(kernel, interpret=False),
                                  default=partial(_library, symmetrize=symmetrize))


def inverse_spd(A, form: str = "library"):
    """The inverse ``(n, n)`` of a symmetric positive definite ``A`` ``(n, n)``, ``C^-T C^-1`` from
    :func:`cholesky_inverse` (``form`` as there): then products only. Its error is of the order
    of ``cond(A)`` times the rounding unit, as a solve's."""
    Ci = cholesky_inverse(A, form)
    return Ci.T @ Ci
