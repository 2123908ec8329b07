"""Compiled kernels of the hyper-reduced corotational force and tangent (numba).

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
"""

from __future__ import annotations

import numpy as np
from numba import njit

from softcrawl.fem.kernels import _triangle_frame


@njit(cache=True)
def reduced_element_terms(x, conn, X, C, frames, sqrt_w, Phi, Z, s):
    """Fill ``Z`` and ``s`` for the RID elements of one body.

    Args:
        x: ``(n, 3)`` current node positions of the body, mm.
        conn: ``(E, k)`` element node indices (k = 4 or 3).
        X: ``(E, k, 3)`` rest node positions, mm.
        C: ``(E, r, 3k)`` stiffness factors, ``K_e = C_e^T C_e`` (sqrt(mN/mm)).
        frames: ``(E, 3, 3)`` rest frames (rows e1, e2, n of the first three nodes).
        sqrt_w: ``(E,)`` square roots of the ECSW weights.
        Phi: ``(3n, m)`` the body's basis (world frame).
        Z: ``(E * r, m)`` output.
        s: ``(E * r,)`` output.

    Returns:
        Number of inverted tetrahedra or degenerate elements.
    """
    E, k = conn.shape
    r = C.shape[1]
    m = Phi.shape[1]
    nd = 3 * k
    Fc = np.empty((3, 3))
    R = np.empty((3, 3))
    u = np.empty(nd)
    CR = np.empty((r, nd))  # C_e blockdiag(R)^T: Z_e = sqrt(xi) CR Phi_e
    n_bad = 0
    for e in range(E):
        if k == 4:
            a0 = x[conn[e, 1]] - x[conn[e, 0]]
            a1 = x[conn[e, 2]] - x[conn[e, 0]]
            a2 = x[conn[e, 3]] - x[conn[e, 0]]
            det = (a0[0] * (a1[1] * a2[2] - a1[2] * a2[1]) - a0[1] * (a1[0] * a2[2] - a1[2] * a2[0])
                   + a0[2] * (a1[0] * a2[1] - a1[1] * a2[0]))
            if not det > 0.0:
                n_bad += 1
        if not _triangle_frame(x[conn[e, 0]], x[conn[e, 1]], x[conn[e, 2]], Fc):
            n_bad += 1
            for i in range(r):
                s[e * r + i] = 0.0
                for j in range(m):
                    Z[e * r + i, j] = 0.0
            continue
        for i in range(3):
            for j in range(3):
                R[i, j] = Fc[0, i] * frames[e, 0, j] + Fc[1, i] * frames[e, 1, j] + Fc[2, i] * frames[e, 2, j]
        for a in range(k):
            na = conn[e, a]
            for i in range(3):
                u[3 * a + i] = R[0, i] * x[na, 0] + R[1, i] * x[na, 1] + R[2, i] * x[na, 2] - X[e, a, i]
        w = sqrt_w[e]
        for i in range(r):
            acc = 0.0
            for q in range(nd):
                acc += C[e, i, q] * u[q]
            s[e * r + i] = w * acc
            for a in range(k):
                for c in range(3):
                    CR[i, 3 * a + c] = w * (C[e, i, 3 * a] * R[c, 0] + C[e, i, 3 * a + 1] * R[c, 1]
                                            + C[e, i, 3 * a + 2] * R[c, 2])
            for j in range(m):
                Z[e * r + i, j] = 0.0
            for a in range(k):
                r0 = 3 * conn[e, a]
                for c in range(3):
                    coef = CR[i, 3 * a + c]
                    for j in range(m):
                        Z[e * r + i, j] += coef * Phi[r0 + c, j]
    return n_bad


def stiffness_factors(K: np.ndarray, rank: int) -> np.ndarray:
    """``(E, rank, d)`` factors ``C`` with ``C^T C = K`` for symmetric PSD ``K`` ``(E, d, d)``
    of the given rank (6 for linear tetrahedra, 3 for membrane triangles), from the
    eigendecomposition (the discarded eigenvalues are round-off)."""
    lam, V = np.linalg.eigh(K)
    lam, V = lam[:, -rank:], V[:, :, -rank:]
    return np.sqrt(np.maximum(lam, 0.0))[:, :, None] * V.transpose(0, 2, 1)


@njit(cache=True)
def reduced_area_normal_load(x, triangles, phi_sum):
    """``sum_t phi_sum_t^T n_t`` with ``n_t = (x1 - x0) x (x2 - x0) / 2`` the area normal of
    triangle ``t`` (:func:`softcrawl.fem.pressure.area_normals`).

    Args:
        x: ``(n, 3)`` node positions, mm.
        triangles: ``(T, 3)`` node indices.
        phi_sum: ``(T, 3, m)`` sum of the triangle's three vertex rows of the basis.

    Returns:
        ``(m,)`` in mm^2; times ``p / 3`` (kPa) it is the reduced cavity pressure load, mN.
    """
    m = phi_sum.shape[2]
    out = np.zeros(m)
    for t in range(triangles.shape[0]):
        a, b, c = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        u0, u1, u2 = x[b, 0] - x[a, 0], x[b, 1] - x[a, 1], x[b, 2] - x[a, 2]
        v0, v1, v2 = x[c, 0] - x[a, 0], x[c, 1] - x[a, 1], x[c, 2] - x[a, 2]
        n0, n1, n2 = 0.5 * (u1 * v2 - u2 * v1), 0.5 * (u2 * v0 - u0 * v2), 0.5 * (u0 * v1 - u1 * v0)
        for j in range(m):
            out[j] += n0 * phi_sum[t, 0, j] + n1 * phi_sum[t, 1, j] + n2 * phi_sum[t, 2, j]
    return out
