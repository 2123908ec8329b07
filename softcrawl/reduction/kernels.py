"""Compiled kernels of hyper-reduced bodies (numba), batched over the bodies that share a part.

For a reduced integration domain (RID) element ``e`` with weight ``xi_e``, rest stiffness
``K_e`` (``3k x 3k``, :mod:`softcrawl.fem.elements`), current corotational rotation ``R_e``
(SOFA "large" frame, as in :mod:`softcrawl.fem.kernels`) and basis rows ``Phi_e``
(``3k x m``), the reduced internal force and tangent are

    f_r = -sum_e xi_e Phi_e^T R K_e (R^T x_e - X_e),   K_r = sum_e xi_e Phi_e^T R K_e R^T Phi_e

(``R = blockdiag(R_e)``). ``K_e`` does not see rigid translations, so it acts on the element's
*edge vectors* ``d_a = x_a - x_0`` (a = 1 .. k-1) only: ``K_e = D^T C_e^T C_e D`` with ``D`` the
``3(k-1) x 3k`` edge-difference operator and ``C_e`` (``r x 3(k-1)``, r = 6 for tetrahedra,
3 for membrane triangles) a factor of rank r. ``D`` commutes with rotating every node, so with
the edge basis rows ``H_e = D Phi_e``

    Z_e = sqrt(xi_e) C_e blockdiag(R_e)^T H_e   (r x m),   s_e = sqrt(xi_e) C_e (R_e^T d - d^0)

give ``K_r = Z^T Z`` and ``f_r = -Z^T s`` (Farhat, Chapman & Avery 2015, "Structure-preserving,
stability, and accuracy properties of the energy-conserving sampling and weighting method",
eq. 20; the ``C^T C`` split makes ``K_r`` one symmetric BLAS update). Modes that move no RID
element's edges (the translations) have zero columns in every ``H_e`` and are left out: ``H_e``
holds the *strain modes* only (9 x 34 rows x columns for a tetrahedron of the shipped leg,
against 12 x 37 for ``Phi_e``).

The basis rows are those of the *part*: a body placed by rotation ``R_b`` has the basis
``blockdiag(R_b) Phi_p`` (reduction.md), so ``R_e`` above is the element's rotation in the part
frame, ``R_e = R_b^T F^T F_0`` with ``F`` the element's current frame in the world and ``F_0`` its
rest frame in the part (rows e1, e2, n). With the precomputed ``C~_e = sqrt(xi_e) C_e
blockdiag(F_0)^T`` and ``s0_e = sqrt(xi_e) C_e d^0``,

    Z_e = C~_e blockdiag(F R_b) H_e,     s_e = C~_e blockdiag(F) d - s0_e,

so a step needs only world positions and one 3 x 3 product per element and body. All legs of a
robot share one copy of the RID data, and the kernels loop over elements outside and bodies
inside, so each element's basis rows are read once per step for all legs.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from softcrawl.fem.kernels import triangle_frame
from softcrawl.reduction.blas import syrk_upper, syrk_upper32


@njit(cache=True, inline="always")
def _row_times(w, H, out):
    """``out = w H`` (``w`` ``(nd,)``, ``H`` ``(nd, m)``, nd = 9 or 6), each entry summed in the
    order of ``w``: vectorised over the columns, the same rounding for every row."""
    if w.shape[0] == 9:
        for j in range(H.shape[1]):
            out[j] = (w[0] * H[0, j] + w[1] * H[1, j] + w[2] * H[2, j] + w[3] * H[3, j] + w[4] * H[4, j]
                      + w[5] * H[5, j] + w[6] * H[6, j] + w[7] * H[7, j] + w[8] * H[8, j])
    elif w.shape[0] == 6:
        for j in range(H.shape[1]):
            out[j] = (w[0] * H[0, j] + w[1] * H[1, j] + w[2] * H[2, j] + w[3] * H[3, j] + w[4] * H[4, j]
                      + w[5] * H[5, j])
    else:
        for j in range(H.shape[1]):
            acc = w[0] * H[0, j]
            for q in range(1, w.shape[0]):
                acc += w[q] * H[q, j]
            out[j] = acc


@njit(cache=True)
def element_terms(x, offsets, rotations, conn, C, s0, rows, Z, s, e0, e1, n_bad):
    """Fill ``Z`` and ``s`` for elements ``e0 .. e1 - 1`` of one RID element family of every
    body of a group.

    Args:
        x: ``(N, 3)`` current node positions of the whole model (world frame), mm.
        offsets: ``(L,)`` first node of each body in ``x``.
        rotations: ``(L, 3, 3)`` each body's placement rotation (part frame -> world).
        conn: ``(E, k)`` element node indices of the part (k = 4 or 3).
        C: ``(E, r, 3(k - 1))`` factors ``C~_e`` on the edge vectors in the element's rest
            frame, weighted (sqrt(mN/mm)).
        s0: ``(E, r)`` ``C~_e`` times the rest edge vectors in the rest frame.
        rows: ``(E, 3(k - 1), m)`` edge basis rows ``H_e = D Phi_e`` of the strain modes.
        Z: ``(L, R, m)`` output: element ``e``'s rows are ``(e - e0) * r ..`` (r rows each).
        s: ``(L, R)`` output, the same rows.
        e0, e1: the range of elements.
        n_bad: ``(L,)`` incremented by each body's inverted tetrahedra and degenerate elements.

    The ``Z_e`` of all bodies are ``CR_b H_e`` with ``CR_b = C~_e blockdiag(F R_b)``, in the
    precision of ``Z`` and ``rows`` (float64, or float32 for :func:`accumulate_terms32`); ``s``
    is float64. Each row is summed in a fixed order (:func:`_row_times`), so a body's ``Z`` does
    not depend on which other bodies share its block: one BLAS product ``[CR_1; ...; CR_L] H_e``
    per element is no faster, and ``sgemm`` rounds a row differently depending on where it falls
    in its tiles (a batched robot left its single-robot trajectory by up to 0.6 mm in 140 steps).
    """
    L = offsets.shape[0]
    k = conn.shape[1]
    r = C.shape[1]
    nd = 3 * (k - 1)
    F = np.empty((3, 3))
    Q = np.empty((3, 3))
    d = np.empty((k - 1, 3))
    g = np.empty(nd)
    CR = np.empty((L * r, nd), Z.dtype)  # body b's rows b*r..: C~_e blockdiag(F R_b)
    for e in range(e0, e1):
        row = (e - e0) * r
        for b in range(L):
            n0 = offsets[b] + conn[e, 0]
            for a in range(k - 1):
                na = offsets[b] + conn[e, a + 1]
                for i in range(3):
                    d[a, i] = x[na, i] - x[n0, i]
            if k == 4 and not (d[0, 0] * (d[1, 1] * d[2, 2] - d[1, 2] * d[2, 1])
                               - d[0, 1] * (d[1, 0] * d[2, 2] - d[1, 2] * d[2, 0])
                               + d[0, 2] * (d[1, 0] * d[2, 1] - d[1, 1] * d[2, 0])) > 0.0:
                n_bad[b] += 1  # inverted tetrahedron
            if not triangle_frame(x[n0], x[offsets[b] + conn[e, 1]], x[offsets[b] + conn[e, 2]], F):
                n_bad[b] += 1
                for i in range(r):
                    s[b, row + i] = 0.0
                    for q in range(nd):
                        CR[b * r + i, q] = 0.0
                continue
            Rb = rotations[b]
            for p in range(3):
                for c in range(3):
                    Q[p, c] = F[p, 0] * Rb[0, c] + F[p, 1] * Rb[1, c] + F[p, 2] * Rb[2, c]
                for a in range(k - 1):
                    g[3 * a + p] = F[p, 0] * d[a, 0] + F[p, 1] * d[a, 1] + F[p, 2] * d[a, 2]
            for i in range(r):
                acc = -s0[e, i]
                for q in range(nd):
                    acc += C[e, i, q] * g[q]
                s[b, row + i] = acc
                for a in range(k - 1):
                    for c in range(3):
                        CR[b * r + i, 3 * a + c] = (C[e, i, 3 * a] * Q[0, c] + C[e, i, 3 * a + 1] * Q[1, c]
                                                    + C[e, i, 3 * a + 2] * Q[2, c])
        He = rows[e]
        for b in range(L):
            for i in range(r):
                _row_times(CR[b * r + i], He, Z[b, row + i])


def stiffness_factors(K: np.ndarray, rank: int) -> np.ndarray:
    """``(E, rank, 3(k - 1))`` factors ``C`` with ``D^T C^T C D = K`` for element stiffness
    matrices ``K`` ``(E, 3k, 3k)`` (symmetric PSD, blind to rigid translations, of the given
    rank: 6 for linear tetrahedra, 3 for membrane triangles); ``D`` is the edge-difference
    operator (:func:`edge_difference`). From the eigendecomposition of ``K``.

    Raises:
        ValueError: ``K`` is not reproduced (relative 1e-9): it has a higher rank or resists
            rigid translations.
    """
    k = K.shape[1] // 3
    lam, V = np.linalg.eigh(K)
    lam, V = lam[:, -rank:], V[:, :, -rank:]
    full = np.sqrt(np.maximum(lam, 0.0))[:, :, None] * V.transpose(0, 2, 1)
    D = edge_difference(k)
    C = full @ np.linalg.pinv(D)
    CD = C @ D
    if np.abs(CD.transpose(0, 2, 1) @ CD - K).max(initial=0.0) > 1e-9 * np.abs(K).max(initial=0.0):
        raise ValueError(f"element stiffness matrices must be of rank {rank} and not resist rigid translations")
    return np.ascontiguousarray(C)


def edge_difference(k: int) -> np.ndarray:
    """``(3(k - 1), 3k)`` the operator taking an element's nodal vectors ``(v_0 .. v_{k-1})``
    to its edge vectors ``(v_1 - v_0, ..., v_{k-1} - v_0)``."""
    D = np.zeros((3 * (k - 1), 3 * k))
    for a in range(k - 1):
        D[3 * a:3 * a + 3, :3] = -np.eye(3)
        D[3 * a:3 * a + 3, 3 * a + 3:3 * a + 6] = np.eye(3)
    return D


@njit(cache=True)
def cavity_forces(x, offsets, rotations, triangles, local, n_local, scale):
    """``(L, c, 3)`` each body's cavity follower forces at its ``c`` cavity nodes, in the part
    frame, mN: every triangle gives ``(p / 3) n_t`` to each of its vertices, with
    ``n_t = (x1 - x0) x (x2 - x0) / 2`` its area normal
    (:func:`softcrawl.fem.pressure.area_normals`). Their reduced load is
    ``F_b^T Phi_cavity``.

    Args:
        x, offsets, rotations: as in :func:`element_terms`.
        triangles: ``(T, 3)`` the part's cavity triangles (node indices).
        local: ``(T, 3)`` their vertices' indices among the cavity nodes; n_local: ``c``.
        scale: ``(L, T)`` ``p / 3`` of each body's triangle (its cavity's pressure), kPa.
    """
    L = offsets.shape[0]
    F = np.zeros((L, n_local, 3))
    for t in range(triangles.shape[0]):
        for b in range(L):
            sc = scale[b, t]
            if sc == 0.0:
                continue
            o = offsets[b]
            ia, ib, ic = o + triangles[t, 0], o + triangles[t, 1], o + triangles[t, 2]
            u0, u1, u2 = x[ib, 0] - x[ia, 0], x[ib, 1] - x[ia, 1], x[ib, 2] - x[ia, 2]
            v0, v1, v2 = x[ic, 0] - x[ia, 0], x[ic, 1] - x[ia, 1], x[ic, 2] - x[ia, 2]
            w0, w1, w2 = 0.5 * (u1 * v2 - u2 * v1), 0.5 * (u2 * v0 - u0 * v2), 0.5 * (u0 * v1 - u1 * v0)
            Rb = rotations[b]
            n0 = sc * (Rb[0, 0] * w0 + Rb[1, 0] * w1 + Rb[2, 0] * w2)
            n1 = sc * (Rb[0, 1] * w0 + Rb[1, 1] * w1 + Rb[2, 1] * w2)
            n2 = sc * (Rb[0, 2] * w0 + Rb[1, 2] * w1 + Rb[2, 2] * w2)
            for a in range(3):
                i = local[t, a]
                F[b, i, 0] += n0
                F[b, i, 1] += n1
                F[b, i, 2] += n2
    return F


@njit(cache=True, fastmath=True)
def add_projected(F, rows, out):
    """``out[b] += rows^T F[b]``: nodal vectors ``F`` ``(L, 3c)`` of each body projected on basis
    rows ``(3c, m)`` into ``out`` ``(L, m)``; one pass over the rows for all bodies (BLAS takes
    twice as long for so few right-hand sides)."""
    L, m = out.shape
    for i in range(rows.shape[0]):
        for b in range(L):
            f = F[b, i]
            if f != 0.0:
                for j in range(m):
                    out[b, j] += f * rows[i, j]


@njit(cache=True)
def forward_substitute(L, Y):
    """``Y <- L^-1 Y`` in place for a lower triangular ``L`` ``(n, n)`` and ``Y`` ``(n, k)``.

    Row by row, each row's update over all ``k`` columns at once (a loop the compiler
    vectorises): every entry is reduced in the order of column-by-column substitution, so the
    result is that substitution's to the bit (``CHANGELOG.md``)."""
    n, k = Y.shape
    for i in range(n):
        for j in range(i):
            lij = L[i, j]
            for c in range(k):
                Y[i, c] -= lij * Y[j, c]
        for c in range(k):
            Y[i, c] /= L[i, i]


@njit(cache=True)
def back_substitute_transposed(L, Y):
    """``Y <- L^-T Y`` in place (``L``, ``Y`` as in :func:`forward_substitute`, the same
    row-by-row order)."""
    n, k = Y.shape
    for i in range(n - 1, -1, -1):
        for j in range(i + 1, n):
            lji = L[j, i]
            for c in range(k):
                Y[i, c] -= lji * Y[j, c]
        for c in range(k):
            Y[i, c] /= L[i, i]


@njit(cache=True)
def _cholesky_solve(L, b):
    """``A^-1 b`` from the lower Cholesky factor ``L`` of ``A`` (``b``: ``(m,)``). The
    arithmetic of :func:`forward_substitute` then :func:`back_substitute_transposed` with one
    column, written out: calling them on a ``(m, 1)`` view gives the same bits but took 2.6x as
    long per call (8 against 3 us for m = 36, measured in a compiled loop), on the hot path."""
    m = b.shape[0]
    y = b.copy()
    for i in range(m):
        acc = y[i]
        for j in range(i):
            acc -= L[i, j] * y[j]
        y[i] = acc / L[i, i]
    for i in range(m - 1, -1, -1):
        acc = y[i]
        for j in range(i + 1, m):
            acc -= L[j, i] * y[j]
        y[i] = acc / L[i, i]
    return y


@njit(cache=True)
def accumulate_terms(x, offsets, rotations, conn, C, s0, rows, qdot, c, Zc, sc, t, K, f, n_bad):
    """Add one RID element family's ``K_r = Z^T Z`` (upper triangle) and
    ``-Z^T (s + c Z qdot)`` to ``K`` ``(L, m', m')`` and ``f`` ``(L, m')`` of the strain modes
    (arguments of :func:`element_terms`; ``qdot``: ``(L, m')`` their modal velocities,
    ``c = h + r_K``). ``Z`` is formed in chunks of elements in the scratch arrays ``Zc``
    ``(L, R, m')``, ``sc`` ``(L, R)`` and ``t`` ``(R,)`` (R a multiple of r), so it stays in
    cache for its products; ``K_r`` is a BLAS ``dsyrk`` update."""
    E = conn.shape[0]
    r = C.shape[1]
    chunk = Zc.shape[1] // r
    ft = np.empty(rows.shape[2])
    for e0 in range(0, E, chunk):
        e1 = min(E, e0 + chunk)
        element_terms(x, offsets, rotations, conn, C, s0, rows, Zc, sc, e0, e1, n_bad)
        n = (e1 - e0) * r
        tb = t[:n]
        for b in range(offsets.shape[0]):
            Zb = Zc[b, :n]
            np.dot(Zb, qdot[b], tb)
            for i in range(n):
                tb[i] = sc[b, i] + c * tb[i]
            np.dot(Zb.T, tb, ft)
            f[b] -= ft
            syrk_upper(Zb, K[b])


@njit(cache=True)
def accumulate_terms32(x, offsets, rotations, conn, C, s0, rows32, qdot, c, Zc, sc, K32, f, n_bad):
    """:func:`accumulate_terms` with ``Z`` in single precision: ``Z`` formed from float32 basis
    rows ``rows32``, ``K_r = Z^T Z`` by ``ssyrk`` into ``K32`` ``(L, m', m')`` (float32, upper
    triangle) and ``-Z^T (s + c Z qdot)`` by float32 products added to ``f`` (float64); the
    element rotations and ``s`` stay in double precision. 1.5x faster than double precision on
    the shipped leg; ``K_r`` and ``f_r`` agree with it to about 3e-7 of their largest entries
    (``RobotConfig.rid_dtype``, validated in ``docs/results.md``). ``Zc`` is float32."""
    E = conn.shape[0]
    r = C.shape[1]
    chunk = Zc.shape[1] // r
    m = rows32.shape[2]
    tb = np.empty(Zc.shape[1], np.float32)
    q = np.empty(m, np.float32)
    for e0 in range(0, E, chunk):
        e1 = min(E, e0 + chunk)
        element_terms(x, offsets, rotations, conn, C, s0, rows32, Zc, sc, e0, e1, n_bad)
        n = (e1 - e0) * r
        for b in range(offsets.shape[0]):
            Zb = Zc[b, :n]
            for j in range(m):
                q[j] = qdot[b, j]
            t = tb[:n]
            np.dot(Zb, q, t)
            for i in range(n):
                t[i] = sc[b, i] + c * t[i]
            ft = np.dot(Zb.T, t)
            for j in range(m):
                f[b, j] -= ft[j]
            syrk_upper32(Zb, K32[b])


@njit(cache=True)
def add_strain_terms(Ks, fs, modes, K, f):
    """Add the strain modes' tangents (upper triangles) ``Ks`` ``(L, m', m')`` and forces
    ``fs`` ``(L, m')`` to the full ``K`` ``(L, m, m)`` and ``f`` ``(L, m)`` at ``modes``."""
    for b in range(Ks.shape[0]):
        for i in range(modes.shape[0]):
            f[b, modes[i]] += fs[b, i]
            for j in range(i, modes.shape[0]):
                K[b, modes[i], modes[j]] += Ks[b, i, j]
                if j != i:
                    K[b, modes[j], modes[i]] += Ks[b, i, j]


@njit(cache=True)
def implicit_steps(K, f, mass, qdot, h, r_mass, r_stiff, chol, qdot_free):
    """The linearly implicit Euler step of each body in reduced coordinates:

        [(1 + h r_M) M_r + h (h + r_K) K_r] dqdot = h (f_r - (h + r_K) K_r qdot - r_M M_r qdot)

    (SOFA ``EulerImplicitSolver`` projected on the basis; reduction.md, "Reduced kinematics").

    Args:
        K: ``(L, m, m)`` reduced tangents ``K_r``, mN/mm.
        f: ``(L, m)`` ``f_r - (h + r_K) K_r qdot``: reduced load, internal force and
            stiffness damping (:func:`accumulate_terms`), mN.
        mass: ``(L, m, m)`` reduced masses ``Phi^T M Phi``, kg.
        qdot: ``(L, m)`` modal velocities at the start of the step.
        h, r_mass, r_stiff: time step (s) and Rayleigh coefficients.
        chol: ``(L, m, m)`` output: lower Cholesky factors of the step matrices.
        qdot_free: ``(L, m)`` output: modal velocities after the free step.

    Returns:
        ``(L,)`` bool: whether each body's step matrix was positive definite.
    """
    L = K.shape[0]
    ok = np.ones(L, np.bool_)
    for b in range(L):
        A = (1.0 + h * r_mass) * mass[b] + (h * (h + r_stiff)) * K[b]
        try:
            chol[b] = np.linalg.cholesky(A)
        except Exception:  # not positive definite
            ok[b] = False
            qdot_free[b] = qdot[b]
            continue
        qdot_free[b] = qdot[b] + _cholesky_solve(chol[b], h * (f[b] - r_mass * (mass[b] @ qdot[b])))
    return ok


@njit(cache=True)
def _jacobian(b, fixed_rows, frame_rot, basis, c_body, c_node, J):
    """Rows of body ``b``'s constraint blocks in its modal coordinates, into ``J``: first its
    fixed (attachment) blocks, then its contacts in the order of ``c_body``. Returns the
    number of blocks."""
    nf = fixed_rows.shape[1]
    m = basis.shape[1]
    for r in range(nf):
        J[r] = fixed_rows[b, r]
    row = nf
    F = frame_rot[b]
    for c in range(c_body.shape[0]):
        if c_body[c] != b:
            continue
        n = 3 * c_node[c]
        for i in range(3):
            for j in range(m):
                J[row + i, j] = F[i, 0] * basis[n, j] + F[i, 1] * basis[n + 1, j] + F[i, 2] * basis[n + 2, j]
        row += 3
    return row // 3


@njit(cache=True)
def _blocks(b, fixed_blocks, c_body, c_block):
    """Global block numbers of body ``b``'s constraint blocks, in :func:`_jacobian` order."""
    out = np.empty(fixed_blocks.shape[1] + c_body.shape[0], np.int64)
    n = 0
    for a in range(fixed_blocks.shape[1]):
        out[n] = fixed_blocks[b, a]
        n += 1
    for c in range(c_body.shape[0]):
        if c_body[c] == b:
            out[n] = c_block[c]
            n += 1
    return out[:n]


@njit(cache=True)
def add_delassus(W, u, chol, qdot, fixed_rows, fixed_blocks, frame_rot, basis, c_body, c_node, c_block):
    """Add the bodies' terms ``J_b A_b^-1 J_b^T`` to the Delassus operator and ``J_b qdot_b``
    to the free constraint velocities (Duriez et al. 2006, sec. 4; reduction.md: rows
    ``H Phi``).

    Args:
        W: ``(3B, 3B)`` Delassus operator (mm/s per mN s), added to.
        u: ``(3B,)`` free constraint velocities, mm/s, added to.
        chol: ``(L, m, m)`` lower Cholesky factors of the bodies' step matrices.
        qdot: ``(L, m)`` free modal velocities.
        fixed_rows: ``(L, 3F, m)`` rows ``H_f Phi_b`` of each body's attachment blocks (world).
        fixed_blocks: ``(L, F)`` their global block numbers.
        frame_rot: ``(L, 3, 3)`` ``F R_b``: the contact frame (rows normal, t1, t2) times the
            body's rotation, so that a contact at node ``n`` has rows ``F R_b Phi_p[n]``.
        basis: ``(3n, m)`` the part basis.
        c_body, c_node, c_block: ``(k,)`` each contact's body (index in the group, -1: not
            in it), part node and global block number.
    """
    L, m = qdot.shape
    J = np.empty((3 * (fixed_blocks.shape[1] + c_body.shape[0]), m))
    for b in range(L):
        nb = _jacobian(b, fixed_rows, frame_rot, basis, c_body, c_node, J)
        blocks = _blocks(b, fixed_blocks, c_body, c_block)
        Jb = J[:3 * nb]
        Y = np.ascontiguousarray(Jb.T)
        forward_substitute(chol[b], Y)  # L^-1 J^T
        Wb = Y.T @ Y
        ub = Jb @ qdot[b]
        for p in range(nb):
            rp = 3 * blocks[p]
            for i in range(3):
                u[rp + i] += ub[3 * p + i]
                for q in range(nb):
                    rq = 3 * blocks[q]
                    for j in range(3):
                        W[rp + i, rq + j] += Wb[3 * p + i, 3 * q + j]


@njit(cache=True)
def corrections(lam, chol, fixed_rows, fixed_blocks, frame_rot, basis, c_body, c_node, c_block):
    """``(L, m)`` modal velocity corrections ``A_b^-1 J_b^T lam_b`` (arguments as in
    :func:`add_delassus`; ``lam``: ``(3B,)`` impulses, mN s)."""
    L = chol.shape[0]
    m = basis.shape[1]
    out = np.zeros((L, m))
    J = np.empty((3 * (fixed_blocks.shape[1] + c_body.shape[0]), m))
    for b in range(L):
        nb = _jacobian(b, fixed_rows, frame_rot, basis, c_body, c_node, J)
        blocks = _blocks(b, fixed_blocks, c_body, c_block)
        g = np.zeros(m)
        for p in range(nb):
            for i in range(3):
                li = lam[3 * blocks[p] + i]
                if li != 0.0:
                    for j in range(m):
                        g[j] += J[3 * p + i, j] * li
        out[b] = _cholesky_solve(chol[b], g)
    return out


@njit(cache=True)
def point_velocity(qdot, direction, basis, body, node):
    """``(k,)`` velocity component ``d_b . (Phi_p[node] qdot_b)`` of points ``(body, node)``,
    with ``direction``: ``(L, 3)`` a part-frame direction per body (e.g. ``R_b^T e_z``)."""
    m = basis.shape[1]
    out = np.empty(body.shape[0])
    for c in range(body.shape[0]):
        b, n = body[c], 3 * node[c]
        acc = 0.0
        for j in range(m):
            acc += (direction[b, 0] * basis[n, j] + direction[b, 1] * basis[n + 1, j]
                    + direction[b, 2] * basis[n + 2, j]) * qdot[b, j]
        out[c] = acc
    return out


@njit(cache=True)
def floor_candidates(x, offsets, collision, bound, qdot, direction, basis, h, height, distance):
    """Collision nodes of a group's bodies that are floor contact candidates: gap below
    ``distance`` before or after the free motion (``gap + h v_z``).

    A node is skipped without computing its velocity when ``gap - h bound_n |qdot_b| >=
    distance`` (``|v_n| <= bound_n |qdot_b|`` with ``bound_n`` the Frobenius norm of its
    basis rows: the basis is orthonormal).

    Args:
        x: ``(N, 3)`` stacked positions, mm; offsets: ``(L,)`` the bodies' first nodes.
        collision: ``(c,)`` part nodes; bound: ``(c,)`` their basis-row norms.
        qdot: ``(L, m)`` free modal velocities; direction: ``(L, 3)`` each body's world z axis
            in the part frame; basis: ``(3n, m)`` the part basis.
        h: time step, s; height: floor z, mm; distance: contact distance, mm.

    Returns:
        ``(nodes, gaps, vz)``: global node indices ``(k,)``, their gaps (mm) and free z
        velocities (mm/s), in body then collision order.
    """
    L = qdot.shape[0]
    c = collision.shape[0]
    nodes = np.empty(L * c, np.int64)
    gaps = np.empty(L * c)
    vz = np.empty(L * c)
    which = np.empty(L * c, np.int64)
    k = 0
    for b in range(L):
        k = body_floor_candidates(x, offsets[b], collision, bound, qdot[b], direction[b], basis, h, height, distance,
                                  nodes, gaps, vz, which, k)
    return nodes[:k], gaps[:k], vz[:k]


@njit(cache=True, inline="always")
def body_floor_candidates(x, offset, collision, bound, qd, direction, basis, h, height, distance,
                          nodes, gaps, vz, which, k):
    """One body's part of :func:`floor_candidates`: its candidates appended at ``k`` to
    ``nodes``, ``gaps``, ``vz`` and ``which`` (the index into ``collision``); returns the new
    count. ``offset``: its first node; ``qd`` ``(m,)``, ``direction`` ``(3,)``: its free modal
    velocities and world z axis in the part frame."""
    m = qd.shape[0]
    speed = 0.0
    for j in range(m):
        speed += qd[j] * qd[j]
    reach = h * np.sqrt(speed)
    for i in range(collision.shape[0]):
        node = offset + collision[i]
        gap = x[node, 2] - height
        if gap - reach * bound[i] >= distance:
            continue
        r = 3 * collision[i]
        v = 0.0
        for j in range(m):
            v += (direction[0] * basis[r, j] + direction[1] * basis[r + 1, j] + direction[2] * basis[r + 2, j]) * qd[j]
        if min(gap, gap + h * v) < distance:
            nodes[k], gaps[k], vz[k], which[k] = node, gap, v, i
            k += 1
    return k


@njit(cache=True, fastmath=True)
def expand_velocities(qdot, basis, rotations, offsets, out):
    """``out[o_b + i] = R_b Phi_p[i] qdot_b``: each body's world nodal velocities (mm/s) from
    its modal velocities ``qdot`` ``(L, m)`` and the part basis ``(3n, m)``, written to its rows
    of the stacked ``out`` ``(N, 3)``. One pass over the basis for all bodies (a BLAS product
    and a separate rotation pass took 2.3x as long with the basis out of cache)."""
    L, m = qdot.shape
    for i in range(basis.shape[0] // 3):
        for b in range(L):
            w0 = w1 = w2 = 0.0
            for j in range(m):
                q = qdot[b, j]
                w0 += basis[3 * i, j] * q
                w1 += basis[3 * i + 1, j] * q
                w2 += basis[3 * i + 2, j] * q
            R = rotations[b]
            o = offsets[b] + i
            out[o, 0] = R[0, 0] * w0 + R[0, 1] * w1 + R[0, 2] * w2
            out[o, 1] = R[1, 0] * w0 + R[1, 1] * w1 + R[1, 2] * w2
            out[o, 2] = R[2, 0] * w0 + R[2, 1] * w1 + R[2, 2] * w2
