"""The reduced legs' free motion in JAX: RID internal forces and tangent, cavity follower
pressure, gravity, Rayleigh damping and the linearly implicit Euler step, for one leg in its
part frame (``jax.vmap`` over legs and robots).

The formulas are those of :mod:`softcrawl.reduction.kernels` (its module doc): with ``x = X +
Phi q`` the RID nodes' part-frame positions, ``F`` each element's frame (rows e1, e2, n) and
``d`` its edge vectors,

    Z_e = C~_e blockdiag(F) H_e,   s_e = C~_e blockdiag(F) d - s0_e,   K_r = Z^T Z,   f_r = -Z^T s

(Farhat, Chapman & Avery 2015, eq. 20). The CPU kernels evaluate ``F`` and ``d`` from world
positions and ``Z`` with ``F R_b``; both are the part-frame quantities (``F_world R_b =
F_part``), so the leg's placement enters only its gravity load. The step is

    [(1 + h r_M) M_r + h (h + r_K) K_r] dqdot = h (f_r - (h + r_K) K_r qdot - r_M M_r qdot)

(reduction.md, "Reduced kinematics"; physics.md, "Time stepping").
"""

from __future__ import annotations

import dataclasses
from functools import lru_cache, partial

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg
from jax import lax

from softcrawl.jaxsim.factor import step_solve
from softcrawl.jaxsim.frames import by_rows, frame_terms, homogeneous
from softcrawl.jaxsim.gpu import cuda_kernel
from softcrawl.jaxsim.ridkernel import rid_kernel_terms


#: The forms of :func:`rid_terms` (``Settings.rid_form``).
RID_FORMS = ("rows", "pairs", "kernel")

#: The dot algorithm (a name of ``jax.lax.DotAlgorithmPreset``) of the pairs form's matrix
#: product in float32, None for full float32 arithmetic: e.g. ``"TF32_TF32_F32_X3"``, three
#: TF32 passes on a GPU's tensor cores at about float32's accuracy (relative error 2e-7 against
#: 3e-4 for one pass, ``benchmarks/dot_algorithms.py``). At 16,384 robots the product is about
#: 1.3 TFLOP a step, bound by float32 arithmetic on an H200 (benchmarks/RESULTS.md); three TF32
#: passes were not faster, at 96 robots on an H200 nor at 16,384 on an H100 (the step 3% slower).
#: Other precisions ignore it. Read when a step is traced (``benchmarks/step_cost.py
#: --pairs-dot`` times it).
PAIRS_DOT_ALGORITHM = None


def _unit(v):
    return v / jnp.linalg.norm(v, axis=-1, keepdims=True)


def element_frames(d):
    """``(E, 3, 3)`` element frames (rows e1 = unit(d_1), e2 = n x e1, n = unit(d_1 x d_2)) of
    edge vectors ``d`` ``(E, k - 1, 3)`` (:func:`softcrawl.fem.kernels._triangle_frame`)."""
    e1 = _unit(d[:, 0])
    n = _unit(jnp.cross(d[:, 0], d[:, 1]))
    return jnp.stack((e1, jnp.cross(n, e1), n), axis=-2)


def rid_terms(part, q, qdot, c, form: str | None = None, present=True):
    """The RID terms of one leg.

    Args:
        part: :class:`~softcrawl.jaxsim.model.LegPart`.
        q, qdot: ``(m,)`` modal displacement (mm) and velocity (mm/s).
        c: ``h + r_K``, s (a number for ``"kernel"`` and ``"interpret"``: compiled in).
        form: ``"rows"`` (``Z`` formed, ``K_r = Z^T Z``), ``"pairs"`` (``Z`` never formed: the
            quadratic monomials of each element's frame contracted with its stiffness per
            monomial, :func:`frame_stiffness`, made of the products of pairs of its basis rows),
            ``"kernel"`` (the rows form in one GPU kernel per leg, ``Z`` formed block by block on
            chip, :mod:`softcrawl.jaxsim.ridkernel`; CUDA only: other platforms, a CPU among
            them, run ``"rows"``), ``"interpret"`` (that kernel in Pallas' interpreter, any
            platform: the tests') or ``None``: ``"rows"`` on a CPU, ``"pairs"`` elsewhere
            (``jax.lax.platform_dependent``). The same sums in another order; ``"pairs"`` costs
            about 2.5x the multiply-adds but is one large matrix product over all legs of a
            batch and keeps no ``Z`` (256 KB per leg): faster on a GPU, slower on a CPU (figures
            in benchmarks/RESULTS.md).
        present: whether the leg exists (a bool, traced or not): the kernel's forms skip an
            absent leg's elements and return zeros, the XLA forms compute its terms all the same
            (an absent leg has no load and stays at rest: :func:`free_motion`).

    Returns:
        ``(K, f, n_bad)``: ``(m', m')`` ``K_r`` of the strain modes (mN/mm), ``(m',)``
        ``-Z^T (s + c Z qdot')`` (mN) and the number of inverted or degenerate RID elements.

    Raises:
        ValueError: an unknown ``form``.
    """
    if form not in (*RID_FORMS, "interpret", None):
        raise ValueError(f"form must be one of {RID_FORMS} or 'interpret', not {form!r}")
    x = part.rid_affine @ homogeneous(q)
    qs = qdot[part.strain_modes]
    if form is None:
        return jax.lax.platform_dependent(part, x, qs, cpu=partial(_xla_terms, c=c, form="rows"),
                                          default=partial(_xla_terms, c=c, form="pairs"))
    if form == "kernel":
        return jax.lax.platform_dependent(part, x, qs, **cuda_kernel(partial(rid_kernel_terms, c=c, present=present)),
                                          default=partial(_xla_terms, c=c, form="rows"))
    if form == "interpret":
        return rid_kernel_terms(part, x, qs, c, interpret=True, present=present)
    return _xla_terms(part, x, qs, c, form)


def _xla_terms(part, x, qs, c, form: str):
    """:func:`rid_terms` in its XLA forms, ``"rows"`` or ``"pairs"``, from the RID nodes'
    positions ``x`` ``(nr, 3)`` (mm) and the strain modes' velocities ``qs`` ``(m',)`` (mm/s)."""
    ms = part.strain_modes.shape[0]
    n_bad = jnp.zeros((), jnp.int32)
    Zs, ss, K, f = [], [], 0.0, 0.0
    for fam in part.families:
        xe = x[fam.conn]
        d = xe[:, 1:] - xe[:, :1]
        if form == "pairs":
            dK, df, bad = _pair_terms(fam, d, qs, c)
            K, f, n_bad = K + dK, f + df, n_bad + bad
            continue
        E, k1 = d.shape[:2]
        F = element_frames(d)
        if k1 == 3:
            n_bad = n_bad + jnp.sum(~(jnp.linalg.det(d) > 0)).astype(jnp.int32)
        n_bad = n_bad + jnp.sum(~jnp.all(jnp.isfinite(F), axis=(1, 2))).astype(jnp.int32)
        g = jnp.einsum("epc,eac->eap", F, d).reshape(E, -1)
        r = fam.factors.shape[1]
        s = jnp.einsum("eiq,eq->ei", fam.factors, g) - fam.rest_terms
        CR = jnp.einsum("eiap,epc->eiac", fam.factors.reshape(E, r, k1, 3), F).reshape(E, r, -1)
        Zs.append(jnp.einsum("eiq,eqj->eij", CR, fam.rows).reshape(E * r, ms))
        ss.append(s.reshape(-1))
    if form == "rows":  # Z used by its column blocks only: no copy of the whole
        Z, s = jnp.concatenate(Zs), jnp.concatenate(ss)
        edges = gram_columns(ms)
        cols = [Z[:, a:b] for a, b in edges]
        w = s + c * sum(Zc @ qs[a:b] for Zc, (a, b) in zip(cols, edges))
        return symmetric_gram(cols), -jnp.concatenate([Zc.T @ w for Zc in cols]), n_bad
    return K[_symmetric_index(ms)], f, n_bad


def _pair_terms(fam, d, qs, c):
    """One family's share of :func:`rid_terms`' ``(K upper triangle, f, n_bad)`` in the pairs form.

    Every per-element quantity is a list of ``(E,)`` component arrays, combined by sums of
    products: the frame ``F`` (rows e1, e2, n as :func:`element_frames`), ``g = F d``, the
    stresses ``s_e`` and ``(C~_e F_e)^T w_e`` as ``F^T (C~_e^T w_e)``. ``K_r``'s share is the
    frame's kept quadratic monomials (:func:`frame_monomials`) contracted with the elements'
    stiffness per monomial (:func:`frame_stiffness`): ``C~_e F_e`` and ``G_e`` are never formed.
    XLA then fuses the elements' terms into element-wise kernels without the stacks and
    concatenations that vector operations (``jnp.cross``, ``jnp.stack``) bring, which a GPU runs
    as kernels of their own."""
    k1 = d.shape[1]
    r, n = fam.factors.shape[1:]
    F, g, bad = frame_terms([[d[:, a, i] for i in range(3)] for a in range(k1)])  # F[p][i]
    s = [sum(fam.factors[:, i, q] * g[q] for q in range(n)) - fam.rest_terms[:, i] for i in range(r)]
    mi, mj, _ = frame_monomials(frame_rows(k1))
    mono = jnp.stack([F[a // 3][a % 3] * F[b // 3][b % 3] for a, b in zip(mi, mj)])  # (M, E): monomial-major
    S = frame_stiffness(fam) if fam.stiffness is None else fam.stiffness
    dK = jnp.matmul(mono.reshape(-1), S, precision=_pairs_dot(mono.dtype))
    u = jnp.einsum("eqj,j->eq", fam.rows, qs)
    v = [[sum(F[p][i] * u[:, 3 * a + i] for i in range(3)) for p in range(3)] for a in range(k1)]  # F u_a
    w = [s[i] + c * sum(fam.factors[:, i, 3 * a + p] * v[a][p] for a in range(k1) for p in range(3))
         for i in range(r)]
    t = [[sum(fam.factors[:, i, 3 * a + p] * w[i] for i in range(r)) for p in range(3)] for a in range(k1)]
    CRw = jnp.stack([sum(t[a][p] * F[p][i] for p in range(3)) for a in range(k1) for i in range(3)])  # (n, E)
    return dK, -jnp.einsum("qe,eqj->j", CRw, fam.rows), jnp.sum(bad).astype(jnp.int32)


def _pairs_dot(dtype):
    """The pairs form's product's ``precision`` for arrays of ``dtype`` (:data:`PAIRS_DOT_ALGORITHM`).

    Raises:
        ValueError: a name that is not a ``jax.lax.DotAlgorithmPreset``.
    """
    name = PAIRS_DOT_ALGORITHM
    if name is None or jnp.dtype(dtype) != jnp.float32:
        return None
    if name not in lax.DotAlgorithmPreset.__members__:
        raise ValueError(f"PAIRS_DOT_ALGORITHM must name a jax.lax.DotAlgorithmPreset, not {name!r}")
    return lax.DotAlgorithmPreset[name]


def frame_rows(k1: int) -> int:
    """How many rows of an element's frame (e1, e2, n) its factors ``C~_e`` act on: all three
    for a tetrahedron (``k1 = 3`` edges), e1 and e2 for a membrane triangle (``k1 = 2``: its
    stiffness is in-plane, :func:`softcrawl.reduction.kernels.stiffness_factors`)."""
    return 3 if k1 == 3 else 2


@lru_cache(maxsize=None)
def frame_monomials(n_rows: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The quadratic monomials ``f_i f_j`` of a frame's first ``n_rows`` rows (entries ``f_{3p+x}
    = F[p][x]``) that span all the others on frames with orthonormal rows, and how the others
    follow from them.

    ``G_e`` is quadratic in the frame's entries, but on rotations these 45 monomials span 35
    dimensions only (products of two entries of the rotation's 3 x 3 representation are matrix
    coefficients of its tensor square, the representations of degree 0, 1 and 2: 1 + 9 + 25
    dimensions; Peter-Weyl, e.g. Folland 2016, "A Course in Abstract Harmonic Analysis", ch. 5):
    orthonormal rows and columns give 10 linear relations among them
    (rows orthogonal, 3; columns orthogonal, 3; all six norms equal, 4). Two orthonormal rows
    (a membrane triangle's e1, e2) have 21 monomials and 2 relations (orthogonal, equal norms):
    19. The eliminated monomials are those a pivoted QR factorisation of the relations picks.

    Returns:
        ``(i, j, E)``: the kept monomials' entry indices, ``(M',)`` each (``i <= j``), and ``E``
        ``(M, M')``, entries 0 and +-1: the ``M = 3 n_rows (3 n_rows + 1) / 2`` monomials in
        ``np.triu_indices(3 n_rows)`` order are ``E`` times the kept ones. Cached: do not modify.

    Raises:
        ValueError: ``n_rows`` is not 2 or 3.
    """
    if n_rows not in (2, 3):
        raise ValueError(f"n_rows must be 2 or 3, not {n_rows}")
    N = 3 * n_rows
    i, j = np.triu_indices(N)
    M = len(i)
    index = np.empty((N, N), np.int64)
    index[i, j] = index[j, i] = np.arange(M)
    relations = []

    def relation(terms):  # terms: (sign, entry, entry); the relation says their sum is zero
        row = np.zeros(M)
        for sign, a, b in terms:
            row[index[a, b]] += sign
        relations.append(row)

    for p in range(n_rows):
        for q in range(p + 1, n_rows):
            relation([(1, 3 * p + x, 3 * q + x) for x in range(3)])  # rows p, q orthogonal
        if p:
            relation([(1, 3 * p + x, 3 * p + x) for x in range(3)] + [(-1, x, x) for x in range(3)])
    if n_rows == 3:
        for x in range(3):
            for y in range(x + 1, 3):
                relation([(1, 3 * p + x, 3 * p + y) for p in range(3)])  # columns x, y orthogonal
            if x < 2:  # column x's norm that of row 0 (the third column's then follows)
                relation([(1, 3 * p + x, 3 * p + x) for p in range(3)] + [(-1, y, y) for y in range(3)])
    R = np.array(relations)
    pivots = scipy.linalg.qr(R, pivoting=True)[2]
    gone = np.sort(pivots[:len(R)])
    kept = np.setdiff1d(np.arange(M), gone)
    E = np.zeros((M, len(kept)))
    E[kept, np.arange(len(kept))] = 1.0
    E[gone] = np.round(-np.linalg.solve(R[:, gone], R[:, kept]), 12)
    return i[kept], j[kept], E


def frame_stiffness(fam):
    """``(M' E, m'(m' + 1)/2)`` each element's share of ``K_r``'s upper triangle per kept monomial
    of its frame (:func:`frame_monomials`; ``M'`` = 35 for tetrahedra, 19 for triangles): row
    ``b E + e`` (monomial-major, the order in which the pairs form writes them) is what monomial
    ``b`` of element ``e``'s frame multiplies, so that

        K_r = sum_e rows_e^T G_e rows_e = sum_e sum_b f_ib f_jb S[b E + e].

    ``G_e[(a, x), (c, y)] = sum_{p, p'} F[p][x] H_e[(a, p), (c, p')] F[p'][y]`` with ``H_e =
    C~_e^T C~_e`` is linear in the frame's monomials; its coefficients are contracted with the
    element's :func:`pair_products` and mapped onto the kept monomials. Model data only, at full
    precision wherever it is traced (a GPU's default for float32 products is TF32)."""
    E, n, ms = fam.rows.shape
    k1, P = n // 3, n * (n + 1) // 2
    nr = frame_rows(k1)
    i, j = np.triu_indices(3 * nr)
    a, b = np.triu_indices(n)  # G's upper entries: (edge a // 3, component a % 3), likewise b
    H = element_grams(fam.factors)

    def coefficient(u, v):  # of f_u f_v in G[a, b]: F[p_u][x_u] H[(a, p_u), (b, p_v)] F[p_v][x_v]
        at = (a[:, None] % 3 == u[None] % 3) & (b[:, None] % 3 == v[None] % 3)
        return jnp.where(at, H[:, 3 * (a[:, None] // 3) + u[None] // 3, 3 * (b[:, None] // 3) + v[None] // 3], 0.0)

    A = coefficient(i, j) + jnp.where(i != j, coefficient(j, i), 0.0)  # (E, P, M)
    kept = jnp.einsum("epm,mb->epb", A, jnp.asarray(frame_monomials(nr)[2], A.dtype), precision=lax.Precision.HIGHEST)
    T = pair_products(fam.rows).reshape(P, E, -1)
    return jnp.einsum("epb,pej->bej", kept, T, precision=lax.Precision.HIGHEST).reshape(-1, T.shape[-1])


def _symmetric_index(n: int) -> np.ndarray:
    """``(n, n)`` the position of each entry of a symmetric matrix in its row-major upper
    triangle (``np.triu_indices`` order): a gather, not a scatter, makes the matrix."""
    i, j = np.triu_indices(n)
    idx = np.empty((n, n), np.int32)
    idx[i, j] = idx[j, i] = np.arange(len(i))
    return idx


def pair_products(rows):
    """``(P E, m'(m' + 1)/2)`` the products of one family's basis rows ``rows`` ``(E, n, m')``
    that take its elements' ``G_e`` (``P = n(n + 1)/2`` entries on and above the diagonal, row
    major) to the upper triangle of ``K_r = sum_e rows_e^T G_e rows_e``: for ``a <= b``,
    ``rows_ea (x) rows_eb`` plus, off the diagonal, its transpose (``G_e`` symmetric). Row
    ``p E + e`` is entry ``p`` of element ``e``."""
    E, n, ms = rows.shape
    a, b = np.triu_indices(n)
    i, j = np.triu_indices(ms)
    ra, rb = rows[:, a].transpose(1, 0, 2), rows[:, b].transpose(1, 0, 2)  # (P, E, m')
    T = ra[:, :, i] * rb[:, :, j] + jnp.where((a != b)[:, None, None], ra[:, :, j] * rb[:, :, i], 0.0)
    return T.reshape(len(a) * E, len(i))


def element_grams(factors):
    """``(E, n, n)`` each element's ``C~_e^T C~_e`` of its factors ``(E, r, n)``, at full
    precision wherever it is traced (:func:`frame_stiffness` runs outside the step's precision
    setting, and a GPU's default for float32 products is TF32)."""
    return jnp.einsum("eiq,eip->eqp", factors, factors, precision=lax.Precision.HIGHEST)


def with_frame_stiffness(part):
    """``part`` with each RID family's :func:`frame_stiffness` formed (``Family.stiffness``), for a
    loop of steps to form it once: XLA does not hoist it out of the loop by itself (its pair
    products alone are 24 MB, formed from 0.3 MB of basis rows). Where the pairs form is not
    taken (a CPU), XLA drops it unused."""
    return dataclasses.replace(part, families=tuple(dataclasses.replace(f, stiffness=frame_stiffness(f))
                                                    for f in part.families))


#: Column blocks of :func:`symmetric_gram`.
GRAM_BLOCKS = 4


def gram_columns(n: int) -> list[tuple[int, int]]:
    """``(start, stop)`` of the :data:`GRAM_BLOCKS` near-equal column blocks of ``n`` columns."""
    edges = [round(i * n / GRAM_BLOCKS) for i in range(GRAM_BLOCKS + 1)]
    return list(zip(edges[:-1], edges[1:]))


def symmetric_gram(cols):
    """``Z^T Z`` ``(n, n)`` of ``Z`` ``(r, n)`` given by its :func:`gram_columns` blocks ``cols``
    (``(r, n_i)`` each), from the block products on and above the diagonal only (10 of 16
    products, five eighths of the dense product's multiply-adds; the lower blocks are the upper
    ones transposed)."""
    nb = len(cols)
    upper = {(i, j): cols[i].T @ cols[j] for i in range(nb) for j in range(i, nb)}
    return jnp.block([[upper[(i, j)] if i <= j else upper[(j, i)].T for j in range(nb)] for i in range(nb)])


def cavity_load(part, q, pressure, form: str = "polynomial"):
    """``(m,)`` reduced follower load of the cavity at ``pressure`` (kPa): every triangle gives
    ``w_t = p/3 * (x1 - x0) x (x2 - x0) / 2`` to each vertex (physics.md, "Pneumatic actuation";
    :func:`softcrawl.reduction.kernels.cavity_forces`), projected on the basis rows, mN.

    ``form``: ``"polynomial"`` (the load is a quadratic polynomial in ``q``, its coefficients
    summed once, :func:`softcrawl.jaxsim.model.cavity_polynomial`: the products of ``(q, 1)`` in
    pairs, 703 for the shipped leg, and one product with the coefficients) or ``"nodes"`` (the
    cavity's positions, the triangles' forces scattered into its nodes and projected on their
    basis rows, as the CPU engine computes it). The same load.

    Raises:
        ValueError: an unknown ``form``.
    """
    if form == "polynomial":
        qe = homogeneous(q)
        i, j = np.triu_indices(qe.shape[0])
        return pressure * ((qe[i] * qe[j]) @ part.cavity_terms)
    if form != "nodes":
        raise ValueError(f"form must be 'polynomial' or 'nodes', not {form!r}")
    x = part.cavity_rest + part.cavity_basis @ q
    t = x[part.cavity_tris]
    w = 0.5 * jnp.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]) * (pressure / 3.0)
    F = jnp.zeros_like(x).at[part.cavity_tris.reshape(-1)].add(jnp.repeat(w, 3, axis=0))
    return jnp.einsum("nam,na->m", part.cavity_basis, F)


def free_motion(part, settings, q, qdot, rotation, pressure, mask):
    """The linearly implicit step of one leg without constraints (module doc).

    Args:
        part: :class:`~softcrawl.jaxsim.model.LegPart`; settings: :class:`~softcrawl.jaxsim.model.Settings`.
        q, qdot: ``(m,)`` modal displacement (mm) and velocity (mm/s) at the start of the step.
        rotation: ``(3, 3)`` the leg's placement (gravity); pressure: its cavity pressure, sim kPa.
        mask: whether the leg exists (an absent leg gets no load and stays at rest).

    Returns:
        ``(qdot_free (m,), inv_chol (m, m), n_bad)``: ``inv_chol = C^-1``, the inverse of the
        step matrix's lower Cholesky factor ``A = C C^T`` (lower triangular), so that every later
        solve with ``A`` is a matrix product (``A^-1 b = C^-T (C^-1 b)``), formed with the free
        motion as ``settings.cholesky`` says (:func:`softcrawl.jaxsim.factor.step_solve`: on
        CUDA in one kernel, where ``"kernel"``).
    """
    h, rM, rK = settings.dt, settings.rayleigh_mass, settings.rayleigh_stiffness
    Ks, fs, n_bad = rid_terms(part, q, qdot, h + rK, form=settings.rid_form, present=mask)
    at = part.mode_slots  # the strain modes' terms among all modes, zero for the others: gathers
    g = jnp.asarray(settings.gravity, q.dtype)
    load = by_rows(by_rows(g, rotation), part.mass_rows) + cavity_load(part, q, pressure)  # mass_rows^T R^T g
    inv_chol, qd_free = step_solve(part.mass, Ks, fs, at, load, mask, qdot, 1.0 + h * rM, h * (h + rK), h, rM,
                                   settings.cholesky)
    return qd_free, inv_chol, n_bad
