"""The inverse Cholesky factor of small SPD matrices (:mod:`softcrawl.jaxsim.factor`): the GPU
kernel, run in Pallas' interpreter, against LAPACK's factor in float64 (numpy), and the settings
that choose it. The kernel inside a whole step: tests/test_jaxsim_delassus.py."""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _float64(x64):
    """Float64 available (``x64``: tests/conftest.py); each test names its arrays' dtype."""


def _spd(rng, batch, n, cond):
    """``(batch, n, n)`` symmetric positive definite matrices of condition number ``cond``
    (eigenvalues spread geometrically from 1 to ``cond``, random orthogonal eigenvectors)."""
    Q, _ = np.linalg.qr(rng.standard_normal((batch, n, n)))
    return np.einsum("bij,j,bkj->bik", Q, np.geomspace(1.0, cond, n), Q)


def test_a_program_holds_its_matrix_in_blocks_of_powers_of_two_that_cover_it():
    """:func:`softcrawl.jaxsim.factor.row_parts`: the legs' 36 rows as blocks of 32 and 4, the
    attachment block's 72 as 64 and 8 (a pivot's update then touches 1,296 and 5,184 numbers,
    not the padded matrices' 4,096 and 16,384); one padded block for powers of two, up to 16
    rows, and where the rest would be padded past three quarters of the padded size (60 rows:
    32 and 32, as the padded 64); every block a power of two, contiguous, covering ``n``."""
    from softcrawl.jaxsim.factor import padded_size, row_parts

    assert row_parts(36) == ((0, 32), (32, 4)) and row_parts(72) == ((0, 64), (64, 8))
    assert row_parts(64) == ((0, 64),) and row_parts(5) == ((0, 16),) and row_parts(60) == ((0, 64),)
    assert row_parts(17) == ((0, 16), (16, 4)) and row_parts(48) == ((0, 32), (32, 16))
    for n in range(1, 300):
        parts = row_parts(n)
        assert parts[0][0] == 0 and all(a + s == b for (a, s), (b, _) in zip(parts, parts[1:]))
        assert all(s & (s - 1) == 0 for _, s in parts) and n <= sum(s for _, s in parts) <= padded_size(n)


@pytest.mark.parametrize("n", [5, 17, 36, 48, 60, 72])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_kernel_inverts_the_cholesky_factor(n, dtype):
    """The kernel's ``C^-1`` (interpreted, batched by ``jax.vmap``) against LAPACK's float64
    factor inverted, for sizes held in one padded block (5, 60) and in two (17: 16 and 4 rows,
    three of them padding; the legs' 36: 32 and 4; 48; the attachment block's 72: 64 and 8), on
    matrices of condition number 1e4 (the landed robot's leg step matrices: about 1e5): relative
    error (of the largest entry) within ``cond u`` with ``u`` the rounding unit (Higham 2002,
    sec. 10.1: the factor's error is of that order; measured at most 1e-13 in float64 and 4.4e-5
    in float32, where LAPACK's own float32 factor errs by 4e-5), exactly lower triangular, and
    ``C^-1 A C^-T = I`` within the same bound (measured 3.4e-13 and 8.1e-5)."""
    from softcrawl.jaxsim.factor import cholesky_inverse

    cond = 1e4
    A = _spd(np.random.default_rng(n), 3, n, cond)
    Ci = np.asarray(jax.vmap(lambda a: cholesky_inverse(a, "interpret"))(jnp.asarray(A, dtype)), float)
    ref = np.linalg.inv(np.linalg.cholesky(A))
    tol = cond * np.finfo(dtype).eps
    assert np.abs(Ci - ref).max() <= tol * np.abs(ref).max()
    assert np.all(np.triu(Ci, 1) == 0)
    eye = np.einsum("bij,bjk,blk->bil", Ci, A, Ci)
    assert np.abs(eye - np.eye(n)).max() <= tol


@pytest.mark.parametrize("n", [5, 17, 36, 48, 60, 72])
@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_sweeps_invert_the_matrix(n, dtype):
    """``inverse_spd``'s kernel (the symmetric sweep operator, interpreted, batched by
    ``jax.vmap``) against numpy's float64 inverse, sizes and matrices as the factor's test:
    relative error (of the largest entry) within ``cond u`` (Higham 2002, sec. 14.4; measured at
    most 1.5e-13 in float64 and 7.4e-5 in float32, bounds 2.2e-12 and 1.2e-3), symmetric within the
    same bound (measured 2e-16 and 8e-8), and ``A A^-1 = I`` within it (measured 7e-13 and
    1.5e-4)."""
    from softcrawl.jaxsim.factor import inverse_spd

    cond = 1e4
    A = _spd(np.random.default_rng(10 + n), 3, n, cond)
    P = np.asarray(jax.vmap(lambda a: inverse_spd(a, "interpret"))(jnp.asarray(A, dtype)), float)
    ref = np.linalg.inv(A)
    tol = cond * np.finfo(dtype).eps
    assert np.abs(P - ref).max() <= tol * np.abs(ref).max()
    assert np.abs(P - P.transpose(0, 2, 1)).max() <= tol * np.abs(ref).max()
    assert np.abs(A @ P - np.eye(n)).max() <= tol


def test_the_library_and_kernel_forms_agree_and_a_cpu_takes_the_library():
    """``"library"`` (factorisation and triangular solve) and the kernel give the same factor
    (float64, condition 100: within 1e-12 relative, measured 1.2e-15); ``"kernel"`` on a CPU is the
    library's result to the bit (``jax.lax.platform_dependent``), its traced program holding the
    kernel for other platforms."""
    from softcrawl.jaxsim.factor import cholesky_inverse, inverse_spd

    A = jnp.asarray(_spd(np.random.default_rng(1), 1, 36, 100.0)[0])
    lib = np.asarray(cholesky_inverse(A))
    assert np.abs(np.asarray(cholesky_inverse(A, "interpret")) - lib).max() <= 1e-12 * np.abs(lib).max()
    np.testing.assert_array_equal(np.asarray(cholesky_inverse(A, "kernel")), lib)
    assert "pallas_call" in str(jax.make_jaxpr(lambda a: cholesky_inverse(a, "kernel"))(A))
    assert "pallas_call" not in str(jax.make_jaxpr(cholesky_inverse)(A))
    np.testing.assert_allclose(np.asarray(inverse_spd(A, "interpret")) @ np.asarray(A), np.eye(36), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(inverse_spd(A, "kernel")), np.asarray(jax.jit(inverse_spd)(A)))
    assert "inverse_spd" in str(jax.make_jaxpr(lambda a: inverse_spd(a, "kernel"))(A))


def test_a_large_batch_of_the_inverses_kernel_form_is_the_librarys(monkeypatch):
    """``inverse_spd``'s ``"kernel"`` form batched by ``jax.vmap``: below
    :data:`softcrawl.jaxsim.factor.LIBRARY_FROM` matrices the traced program holds the sweeps'
    kernel (for CUDA), from it only the library's form (where cuSOLVER's batched factorisation
    may be the faster on a GPU); on a CPU both are the library's result to the bit, and the choice is
    made again for each batch size (it is read when a call is traced). None (the default): the
    kernel at every size."""
    from softcrawl.jaxsim import factor

    A = jnp.asarray(_spd(np.random.default_rng(6), 5, 12, 100.0))
    cases = [(None, 5, True)] + [(4, batch, kernel) for batch, kernel in ((3, True), (4, False), (5, False))]
    for library_from, batch, kernel in cases:
        monkeypatch.setattr(factor, "LIBRARY_FROM", library_from)

        def f(a):
            return jax.vmap(lambda m: factor.inverse_spd(m, "kernel"))(a)

        assert ("inverse_spd" in str(jax.make_jaxpr(f)(A[:batch]))) == kernel
        np.testing.assert_array_equal(np.asarray(jax.jit(f)(A[:batch])),
                                      np.asarray(jax.jit(jax.vmap(factor.inverse_spd))(A[:batch])))


def test_the_symmetrized_library_form_is_jax_numpys_factor_inverted():
    """``symmetrize=True`` (the legs' step matrices, sums symmetric up to round-off) is
    ``jnp.linalg.cholesky``'s factor of ``(A + A^T) / 2`` inverted by a triangular solve, to the
    bit: the CPU engine's step is the one it was before the factor had forms."""
    from jax.scipy.linalg import solve_triangular

    from softcrawl.jaxsim.factor import cholesky_inverse

    A = _spd(np.random.default_rng(3), 1, 36, 1e3)[0]
    A = jnp.asarray(A * (1 + 1e-5 * np.triu(np.random.default_rng(4).standard_normal((36, 36)), 1)), jnp.float32)
    want = solve_triangular(jnp.linalg.cholesky(A), jnp.eye(36, dtype=A.dtype), lower=True)
    np.testing.assert_array_equal(np.asarray(cholesky_inverse(A, symmetrize=True)), np.asarray(want))
    assert not np.array_equal(np.asarray(cholesky_inverse(A)), np.asarray(want))


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_symmetrized_kernel_factors_the_symmetric_part_it_reads(dtype):
    """The kernel's ``symmetrize=True`` forms ``(A + A^T) / 2`` itself, the transpose in the program
    (no transposing pass before it on a GPU): on a matrix symmetric up to a 1e-5
    perturbation of its upper triangle (the legs' step matrices are sums, symmetric up to
    round-off), the interpreted kernel's ``C^-1`` is the kernel's of the symmetrized matrix to
    the bit, and differs from the kernel's of ``A`` as read (its column and row of each pivot
    disagree)."""
    from softcrawl.jaxsim.factor import cholesky_inverse

    A = _spd(np.random.default_rng(3), 2, 36, 1e3)
    A = jnp.asarray(A * (1 + 1e-5 * np.triu(np.random.default_rng(4).standard_normal((2, 36, 36)), 1)), dtype)

    def kernel(a, symmetrize):
        return np.asarray(jax.vmap(lambda m: cholesky_inverse(m, "interpret", symmetrize))(a))

    want = kernel((A + A.transpose(0, 2, 1)) / 2, False)
    np.testing.assert_array_equal(kernel(A, True), want)
    assert not np.array_equal(kernel(A, False), want)


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_the_step_solve_forms_its_matrix_and_solves_in_the_kernel(dtype, monkeypatch):
    """``step_solve``: ``A = alpha M + beta K_s`` (a 36 x 36 mass-like ``M``, shared by the batch
    as the legs' is, and a 33 x 33 ``K`` placed by slots that leave three modes without
    stiffness, as the legs' rigid modes) and ``x + A^-1 h (w f + f_s - rate M x)`` (``f_s`` placed
    as ``K``; ``w`` a leg's presence, true for two matrices and false for one). Its interpreted
    kernel (batched by ``jax.vmap``, ``M`` and the slots unbatched) against numpy's float64 ``A``
    and solve: ``C^-1`` within ``cond u`` of the largest entry as :func:`cholesky_inverse`'s
    kernel (``C^-1 A C^-T = I`` too), the step within ``cond u`` of its change (condition 7.1e3
    here, bounds 1.6e-12 and 8.5e-4; measured 1.7e-15 and 9.4e-7 for ``C^-1``, 4.6e-15 and 1.0e-6
    for the step); the library form likewise; ``"kernel"`` on a CPU is the library's result to
    the bit, its traced program holding the kernel for CUDA; with ``STEP_IN_KERNEL`` off, the
    kernel forms factor in ``cholesky_inverse``'s kernel with XLA's products around it, within
    the same bounds; shapes that do not fit are refused."""
    from softcrawl.jaxsim import factor
    from softcrawl.jaxsim.factor import step_solve

    rng = np.random.default_rng(11)
    M, K = _spd(rng, 1, 36, 30.0)[0], _spd(rng, 3, 33, 1e3)
    slots = np.concatenate([np.arange(33), [33, 33, 33]])[rng.permutation(36)]
    f_s, f, x = rng.standard_normal((3, 33)), rng.standard_normal((3, 36)), rng.standard_normal((3, 36))
    numbers = alpha, beta, h, rate = 1.02, 50.0, 0.02, 1.5
    Ks = np.pad(K, ((0, 0), (0, 1), (0, 1)))[:, slots[:, None], slots[None, :]]
    A = alpha * M + beta * Ks
    w = np.array([True, False, True])
    b = h * (f * w[:, None] + np.pad(f_s, ((0, 0), (0, 1)))[:, slots] - rate * x @ M.T)
    cond = np.linalg.cond(A).max()
    tol = cond * np.finfo(dtype).eps
    ref, solved = np.linalg.inv(np.linalg.cholesky(A)), x + np.linalg.solve(A, b[..., None])[..., 0]
    M_, slots_ = jnp.asarray(M, dtype), jnp.asarray(slots)
    batched = [jnp.asarray(a, dtype) for a in (K, f_s, f)] + [jnp.asarray(w), jnp.asarray(x, dtype)]

    def step(form):
        return lambda k, fs, f_, w_, x_: step_solve(M_, k, fs, slots_, f_, w_, x_, *numbers, form)

    def batch(form):
        return [np.asarray(a, float) for a in jax.vmap(step(form))(*batched)]

    def traced():
        return str(jax.make_jaxpr(step("kernel"))(*(a[0] for a in batched)))

    for in_kernel in (True, False):
        monkeypatch.setattr(factor, "STEP_IN_KERNEL", in_kernel)
        for form in ("interpret", "library"):
            Ci, y = batch(form)
            assert np.abs(Ci - ref).max() <= tol * np.abs(ref).max()
            assert np.abs(np.einsum("bij,bjk,blk->bil", Ci, A, Ci) - np.eye(36)).max() <= tol
            assert np.abs(y - solved).max() <= tol * np.abs(solved - x).max()
        for got, want in zip(batch("kernel"), batch("library")):
            np.testing.assert_array_equal(got, want)
        assert ("step_solve" in traced()) == in_kernel and ("cholesky_inverse" in traced()) != in_kernel
    with pytest.raises(ValueError, match="step_solve needs"):
        step_solve(M_, batched[0][0], batched[1][0], slots_[:35], batched[2][0], True, batched[4][0], *numbers)


def test_a_matrix_that_is_not_positive_definite_gives_no_finite_factor():
    """An indefinite matrix (one negative eigenvalue, rotated at random) and a singular one: the
    kernels' factor and inverse hold NaN or infinite entries (the sweeps, which invert an
    indefinite matrix too, by a non-positive pivot), as the library's hold NaN, so that the step
    marks the robot bad instead of stepping it with a wrong inverse. The singular matrix is a
    permuted diagonal, so that its zero pivot is exactly 0 on any CPU: rotated at random, that
    pivot is 0 up to round-off, whose sign depends on the CPU (positive on some, the inverse then
    finite, 1e8), so no factorisation can tell it from a positive definite matrix of condition
    1e16."""
    from softcrawl.jaxsim.factor import cholesky_inverse, inverse_spd

    rng = np.random.default_rng(2)
    Q, _ = np.linalg.qr(rng.standard_normal((8, 8)))
    P = np.eye(8)[[3, 0, 5, 1, 7, 2, 6, 4]]
    for A in (Q @ np.diag([-1.0] + [1.0] * 7) @ Q.T, P @ np.diag([1.0] * 3 + [0.0] + [1.0] * 4) @ P.T):
        A = jnp.asarray(A)
        for f in (cholesky_inverse, inverse_spd):
            assert not np.all(np.isfinite(np.asarray(f(A, "interpret"))))
            assert not np.all(np.isfinite(np.asarray(f(A))))


def test_bad_forms_and_shapes_are_refused():
    """An unknown form, a non-square or batched argument, and a model setting naming no form:
    ValueError naming what is wrong."""
    from softcrawl.jaxsim.factor import cholesky_inverse, inverse_spd
    from softcrawl.jaxsim.model import Settings

    A = jnp.eye(4)
    with pytest.raises(ValueError, match="form must be"):
        cholesky_inverse(A, "cusolver")
    with pytest.raises(ValueError, match="one square matrix"):
        cholesky_inverse(jnp.ones((4, 3)))
    with pytest.raises(ValueError, match="one square matrix"):
        cholesky_inverse(jnp.ones((2, 4, 4)))
    with pytest.raises(ValueError, match="form must be"):
        inverse_spd(A, "sweep")
    with pytest.raises(ValueError, match="one square matrix"):
        inverse_spd(jnp.ones((4, 3)))
    args = dict(dt=0.01, rayleigh_mass=0.0, rayleigh_stiffness=0.0, gravity=(0.0, 0.0, -9810.0), floor=True,
                floor_z=0.0, contact_distance=1.0, friction=0.5, disk_contacts=8, leg_contacts=12, solver="apgd",
                iterations=48, calibration=(1.0, 0.0), rate=1000.0)
    assert Settings(**args).cholesky == "library" and Settings(**args, cholesky="kernel").cholesky == "kernel"
    with pytest.raises(ValueError, match="settings.cholesky"):
        Settings(**args, cholesky="interpret")


def test_the_kernels_rank_one_updates_are_fused_multiply_adds_in_float32_on_cuda():
    """The kernels' rank-one updates (the elimination's and the sweeps') are one ``fma.rn.f32`` a
    number in the float32 program compiled for CUDA (its traced branch holds the inline
    assembly); in float64 and in Pallas' interpreter they stay a product and a sum
    (``fused_multiply_add``), so the interpreted kernels the other tests check are unchanged."""
    from softcrawl.jaxsim.factor import cholesky_inverse, fused_multiply_add, inverse_spd

    A = jnp.asarray(np.eye(8) * 2.0)
    for f in (cholesky_inverse, inverse_spd):
        assert "fma.rn.f32" in str(jax.make_jaxpr(lambda a: f(a, "kernel"))(A.astype(jnp.float32)))
        assert "fma.rn.f32" not in str(jax.make_jaxpr(lambda a: f(a, "kernel"))(A))
        assert "fma.rn.f32" not in str(jax.make_jaxpr(lambda a: f(a, "interpret"))(A.astype(jnp.float32)))
    a, b, c = (jnp.asarray([1.5, -2.0], jnp.float32) * k for k in (1, 3, 5))
    np.testing.assert_array_equal(fused_multiply_add(a, b, c, compiled=False), a * b + c)


@pytest.mark.parametrize("function", ["cholesky_inverse", "inverse_spd"])
def test_unrolled_pivots_are_the_loops_steps(monkeypatch, function):
    """With :data:`softcrawl.jaxsim.factor.UNROLL_PIVOTS` at 36 the kernels (interpreted) of the
    legs' 36 x 36 matrices run their pivots as straight-line code, no loop in the traced kernel,
    and give the loop's result to float64 round-off (the same operations in the same order:
    within 1e-13 of the largest entry, condition 1e4; measured 0, while the matrices scaled by 1 +
    1e-12 move it by 5e-13 to 9e-13, beyond the bound); a 72 x 72 matrix keeps a loop over each
    of its two blocks' pivots."""
    from softcrawl.jaxsim import factor

    f = getattr(factor, function)
    A = jnp.asarray(_spd(np.random.default_rng(7), 2, 36, 1e4))
    looped = np.asarray(jax.vmap(lambda a: f(a, "interpret"))(A))
    monkeypatch.setattr(factor, "UNROLL_PIVOTS", 36)
    unrolled = np.asarray(jax.vmap(lambda a: f(a, "interpret"))(A))
    assert np.abs(unrolled - looped).max() <= 1e-13 * np.abs(looped).max()

    def loops(a):  # the loops in the traced kernel's own program
        call = next(e for e in jax.make_jaxpr(lambda m: f(m, "interpret"))(a).eqns if e.primitive.name == "pallas_call")
        return [e.primitive.name for e in call.params["jaxpr"].eqns if e.primitive.name in ("while", "scan")]

    assert loops(A[0]) == [] and len(loops(jnp.eye(72))) == len(factor.row_parts(72)) == 2
