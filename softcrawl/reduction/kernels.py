"""Compiled kernels of hyper-reduced bodies (numba), batched over the bodies that share a part.

For a reduced integration domain (RID) element ``e`` with weight ``xi_e``, rest stiffness
factored as ``K_e = C_e^T C_e`` (``C_e``: ``r x 3k``, r = 6 for tetrahedra, 3 for membrane
triangles), current corotational rotation ``R_e`` (SOFA "large" frame, as in
:mod:`softcrawl.fem.kernels`) and basis rows ``Phi_e`` (``3k x m``):

    u_e = R_e^T x_e - X_e,    Psi_e = blockdiag(R_e)^T Phi_e,
    Z_e = sqrt(xi_e) C_e Psi_e  (r x m),    s_e = sqrt(xi_e) C_e u_e  (r,),

so that the reduced force and tangent are

    f_r = sum_e xi_e Phi_e^T f_e = -Z^T s,      K_r = sum_e xi_e Phi_e^T R K_e R^T Phi_e = Z^T Z

with ``Z`` the stacked ``Z_e`` (Farhat, Chapman & Avery 2015, "Structure-preserving,
stability, and accuracy properties of the energy-conserving sampling and weighting method",
eq. 20; the ``C^T C`` split makes ``K_r`` one symmetric BLAS product).

Every quantity is evaluated in the *part frame*: a body placed by rotation ``R_b`` has the
basis ``blockdiag(R_b) Phi_p`` (reduction.md), and corotational forces are frame-invariant,
so with part-frame positions ``y = R_b^T x`` the part's own element data and basis rows give
the same ``Z`` and ``s`` (the reduced coordinates are the same in both frames). All legs of
a robot therefore share one copy of the RID data, and the kernels loop over elements outside
and bodies inside, so each element's basis rows are read once per step for all legs.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from softcrawl.fem.kernels import _triangle_frame


@njit(cache=True)
def element_terms(x, offsets, rotations, conn, X, C, frames, sqrt_w, basis_rows, Z, s, e0, e1, n_bad):
    """Fill ``Z`` and ``s`` for elements ``e0 .. e1 - 1`` of one RID element family of every
    body of a group.

    Args:
        x: ``(N, 3)`` current node positions of the whole model (world frame), mm.
        offsets: ``(L,)`` first node of each body in ``x``.
        rotations: ``(L, 3, 3)`` each body's placement rotation (part frame -> world).
        conn: ``(E, k)`` element node indices of the part (k = 4 or 3).
        X: ``(E, k, 3)`` rest node positions (part frame), mm.
        C: ``(E, r, 3k)`` stiffness factors (part frame), ``K_e = C_e^T C_e`` (sqrt(mN/mm)).
        frames: ``(E, 3, 3)`` rest frames (rows e1, e2, n of the first three nodes).
        sqrt_w: ``(E,)`` square roots of the ECSW weights.
        basis_rows: ``(E, 3k, m)`` the part basis rows of each element's nodes.
        Z: ``(L, R, m)`` output: element ``e``'s rows are ``(e - e0) * r ..`` (r rows each).
        s: ``(L, R)`` output, the same rows.
        e0, e1: the range of elements.
        n_bad: ``(L,)`` incremented by each body's inverted tetrahedra and degenerate elements.

    The ``Z_e`` of all bodies are one BLAS product per element, ``[CR_1; ...; CR_L] Phi_e``
    (3x faster than compiled loops, which do not vectorize here).
    """
    L = offsets.shape[0]
    k = conn.shape[1]
    r = C.shape[1]
    nd = 3 * k
    y = np.empty((k, 3))
    Fc = np.empty((3, 3))
    R = np.empty((3, 3))
    u = np.empty(nd)
    CR = np.empty((L * r, nd))  # body b's rows b*r..: sqrt(xi) C_e blockdiag(R_e)^T
    for e in range(e0, e1):
        row = (e - e0) * r
        for b in range(L):
            o = offsets[b]
            Rb = rotations[b]
            for a in range(k):
                na = o + conn[e, a]
                for i in range(3):
                    y[a, i] = Rb[0, i] * x[na, 0] + Rb[1, i] * x[na, 1] + Rb[2, i] * x[na, 2]
            if k == 4:
                a0, a1, a2 = y[1] - y[0], y[2] - y[0], y[3] - y[0]
                det = (a0[0] * (a1[1] * a2[2] - a1[2] * a2[1]) - a0[1] * (a1[0] * a2[2] - a1[2] * a2[0])
                       + a0[2] * (a1[0] * a2[1] - a1[1] * a2[0]))
                if not det > 0.0:
                    n_bad[b] += 1
            if not _triangle_frame(y[0], y[1], y[2], Fc):
                n_bad[b] += 1
                for i in range(r):
                    s[b, row + i] = 0.0
                    for q in range(nd):
                        CR[b * r + i, q] = 0.0
                continue
            for i in range(3):
                for j in range(3):
                    R[i, j] = Fc[0, i] * frames[e, 0, j] + Fc[1, i] * frames[e, 1, j] + Fc[2, i] * frames[e, 2, j]
            for a in range(k):
                for i in range(3):
                    u[3 * a + i] = R[0, i] * y[a, 0] + R[1, i] * y[a, 1] + R[2, i] * y[a, 2] - X[e, a, i]
            w = sqrt_w[e]
            for i in range(r):
                acc = 0.0
                for q in range(nd):
                    acc += C[e, i, q] * u[q]
                s[b, row + i] = w * acc
                for a in range(k):
                    for c in range(3):
                        CR[b * r + i, 3 * a + c] = w * (C[e, i, 3 * a] * R[c, 0] + C[e, i, 3 * a + 1] * R[c, 1]
                                                        + C[e, i, 3 * a + 2] * R[c, 2])
        Ze = np.dot(CR, basis_rows[e])
        for b in range(L):
            for i in range(r):
                Z[b, row + i] = Ze[b * r + i]


def stiffness_factors(K: np.ndarray, rank: int) -> np.ndarray:
    """``(E, rank, d)`` factors ``C`` with ``C^T C = K`` for symmetric PSD ``K`` ``(E, d, d)``
    of the given rank (6 for linear tetrahedra, 3 for membrane triangles), from the
    eigendecomposition (the discarded eigenvalues are round-off)."""
    lam, V = np.linalg.eigh(K)
    lam, V = lam[:, -rank:], V[:, :, -rank:]
    return np.sqrt(np.maximum(lam, 0.0))[:, :, None] * V.transpose(0, 2, 1)


@njit(cache=True)
def cavity_loads(x, offsets, rotations, triangles, phi_sum, scale, out):
    """Add each body's reduced cavity pressure load ``sum_t (p_t / 3) phi_sum_t^T n_t``.

    ``n_t = (x1 - x0) x (x2 - x0) / 2`` is the area normal of cavity triangle ``t``
    (:func:`softcrawl.fem.pressure.area_normals`), taken to the part frame.

    Args:
        x, offsets, rotations: as in :func:`element_terms`.
        triangles: ``(T, 3)`` the part's cavity triangles (node indices).
        phi_sum: ``(T, 3, m)`` sum of each triangle's three vertex rows of the part basis.
        scale: ``(L, T)`` ``p / 3`` of each body's triangle (its cavity's pressure), kPa.
        out: ``(L, m)`` reduced loads (mN), added to.
    """
    L = offsets.shape[0]
    m = phi_sum.shape[2]
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
            for j in range(m):
                out[b, j] += n0 * phi_sum[t, 0, j] + n1 * phi_sum[t, 1, j] + n2 * phi_sum[t, 2, j]


@njit(cache=True)
def _cholesky_solve(L, b):
    """``A^-1 b`` from the lower Cholesky factor ``L`` of ``A`` (``b``: ``(m,)``)."""
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
def accumulate_terms(x, offsets, rotations, conn, X, C, frames, sqrt_w, basis_rows, qdot, c, Zc, sc, K, f, n_bad):
    """Add one RID element family's ``K_r = Z^T Z`` and ``-Z^T (s + c Z qdot)`` to ``K``
    ``(L, m, m)`` and ``f`` ``(L, m)`` (arguments of :func:`element_terms`; ``c = h + r_K``).
    ``Z`` is formed in chunks of elements in the scratch arrays ``Zc`` ``(L, R, m)`` and
    ``sc`` ``(L, R)`` (R a multiple of r), so it stays in cache for its products."""
    E = conn.shape[0]
    r = C.shape[1]
    chunk = Zc.shape[1] // r
    for e0 in range(0, E, chunk):
        e1 = min(E, e0 + chunk)
        element_terms(x, offsets, rotations, conn, X, C, frames, sqrt_w, basis_rows, Zc, sc, e0, e1, n_bad)
        n = (e1 - e0) * r
        for b in range(offsets.shape[0]):
            Zb = Zc[b, :n]
            f[b] -= Zb.T @ (sc[b, :n] + c * (Zb @ qdot[b]))
            K[b] += Zb.T @ Zb


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
        Y = np.empty((m, 3 * nb))  # L^-1 J^T by forward substitution
        Lb = chol[b]
        for col in range(3 * nb):
            for i in range(m):
                acc = Jb[col, i]
                for j in range(i):
                    acc -= Lb[i, j] * Y[j, col]
                Y[i, col] = acc / Lb[i, i]
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
    L, m = qdot.shape
    c = collision.shape[0]
    nodes = np.empty(L * c, np.int64)
    gaps = np.empty(L * c)
    vz = np.empty(L * c)
    k = 0
    for b in range(L):
        speed = 0.0
        for j in range(m):
            speed += qdot[b, j] * qdot[b, j]
        reach = h * np.sqrt(speed)
        for i in range(c):
            node = offsets[b] + collision[i]
            gap = x[node, 2] - height
            if gap - reach * bound[i] >= distance:
                continue
            r = 3 * collision[i]
            v = 0.0
            for j in range(m):
                v += (direction[b, 0] * basis[r, j] + direction[b, 1] * basis[r + 1, j]
                      + direction[b, 2] * basis[r + 2, j]) * qdot[b, j]
            if min(gap, gap + h * v) < distance:
                nodes[k], gaps[k], vz[k] = node, gap, v
                k += 1
    return nodes[:k], gaps[:k], vz[:k]
