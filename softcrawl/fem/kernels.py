"""Compiled corotational element kernels (numba).

One kernel serves linear tetrahedra (4 nodes) and membrane triangles (3 nodes): each
element stores its rest stiffness ``K`` in rest world coordinates and a rest frame; at
the current state a rotation ``R`` (rest world -> current world) is extracted and

    f_e = -R K (R^T x_e - X_e),        K_t,e = R K R^T

(SOFA ``TetrahedronFEMForceField`` / ``TriangularFEMForceField`` with ``method="large"``;
Felippa & Haugen 2005, "A unified formulation of small-strain corotational finite
elements"; the tangent omits dR/dx as SOFA does).

Rotation extraction (``method``):

- 0, ``"large"``: SOFA's frame from the first three nodes: ``e1 = (x1-x0)/|x1-x0|``,
  ``n = (x1-x0) x (x2-x0)`` normalised, ``e2 = n x e1``; ``R = F_cur^T F_rest`` with frames
  stored as rows.
- 1, ``"polar"``: the rotation of the polar decomposition of the deformation gradient
  ``F = D_s D_m^-1`` (tetrahedra only), via SVD with a reflection fix.
"""

from __future__ import annotations

import numpy as np
from numba import njit

ROTATION_METHODS = {"large": 0, "polar": 1}


@njit(cache=True, inline="always")
def triangle_frame(x0, x1, x2, out):
    """Orthonormal frame of the triangle ``(x0, x1, x2)`` (``(3,)`` positions each) into
    ``out`` ``(3, 3)``: rows ``e1`` (unit ``x1 - x0``), ``e2 = n x e1`` and ``n`` (unit
    ``(x1 - x0) x (x2 - x0)``). Returns False (``out`` untouched) for a degenerate triangle."""
    a0 = x1[0] - x0[0]
    a1 = x1[1] - x0[1]
    a2 = x1[2] - x0[2]
    b0 = x2[0] - x0[0]
    b1 = x2[1] - x0[1]
    b2 = x2[2] - x0[2]
    la = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
    n0 = a1 * b2 - a2 * b1
    n1 = a2 * b0 - a0 * b2
    n2 = a0 * b1 - a1 * b0
    ln = np.sqrt(n0 * n0 + n1 * n1 + n2 * n2)
    if la == 0.0 or ln == 0.0:
        return False
    a0 /= la
    a1 /= la
    a2 /= la
    n0 /= ln
    n1 /= ln
    n2 /= ln
    out[0, 0] = a0
    out[0, 1] = a1
    out[0, 2] = a2
    out[1, 0] = n1 * a2 - n2 * a1
    out[1, 1] = n2 * a0 - n0 * a2
    out[1, 2] = n0 * a1 - n1 * a0
    out[2, 0] = n0
    out[2, 1] = n1
    out[2, 2] = n2
    return True


@njit(cache=True)
def rest_frames(points, conn):
    """``(m, 3, 3)`` rest frames (rows e1, e2, n) of elements' first three nodes."""
    m = conn.shape[0]
    out = np.zeros((m, 3, 3))
    for e in range(m):
        triangle_frame(points[conn[e, 0]], points[conn[e, 1]], points[conn[e, 2]], out[e])
    return out


@njit(cache=True)
def corotational_assemble(x, conn, X, K, frames, method, coef, f_out, data_out, data_map):
    """Accumulate corotational element forces and (scaled) tangents.

    Args:
        x: ``(n, 3)`` current node positions, mm.
        conn: ``(m, k)`` element node indices, k = 3 (membrane) or 4 (tetrahedron).
        X: ``(m, k, 3)`` rest node positions (rest world frame), mm.
        K: ``(m, 3k, 3k)`` rest element stiffness (rest world frame), mN/mm.
        frames: ``(m, 3, 3)`` rest frames (method 0) or ``D_m^-1`` (method 1).
        method: 0 (SOFA "large") or 1 (polar decomposition).
        coef: scale applied to tangent entries written into ``data_out``.
        f_out: ``(n, 3)`` forces, mN; element forces are *added*.
        data_out: ``(nnz,)`` CSR data of the global tangent; ``coef * R K R^T`` entries are
            added at ``data_map``. Pass an empty array to skip the tangent.
        data_map: ``(m, (3k)^2)`` positions in ``data_out`` of each element entry (row-major).

    Returns:
        Number of inverted or degenerate elements (tetrahedra with current signed volume
        <= 0, or elements whose frame is undefined).
    """
    m, k = conn.shape
    nd = 3 * k
    want_tangent = data_out.shape[0] > 0
    Fc = np.empty((3, 3))
    R = np.empty((3, 3))
    u = np.empty(nd)
    fl = np.empty(nd)
    RK = np.empty((nd, nd))
    Ds = np.empty((3, 3))
    n_bad = 0
    for e in range(m):
        if k == 4:
            for c in range(3):
                for r in range(3):
                    Ds[r, c] = x[conn[e, c + 1], r] - x[conn[e, 0], r]
            det = (
                Ds[0, 0] * (Ds[1, 1] * Ds[2, 2] - Ds[1, 2] * Ds[2, 1])
                - Ds[0, 1] * (Ds[1, 0] * Ds[2, 2] - Ds[1, 2] * Ds[2, 0])
                + Ds[0, 2] * (Ds[1, 0] * Ds[2, 1] - Ds[1, 1] * Ds[2, 0])
            )
            if not det > 0.0:
                n_bad += 1
        if method == 0 or k == 3:
            if not triangle_frame(x[conn[e, 0]], x[conn[e, 1]], x[conn[e, 2]], Fc):
                n_bad += 1
                continue
            # R = Fc^T F0
            for i in range(3):
                for j in range(3):
                    s = 0.0
                    for q in range(3):
                        s += Fc[q, i] * frames[e, q, j]
                    R[i, j] = s
        else:
            F = Ds @ frames[e]
            U, S, Vt = np.linalg.svd(F)
            if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
                for r in range(3):
                    U[r, 2] = -U[r, 2]
            R[:, :] = U @ Vt
        # u = R^T x - X
        for a in range(k):
            xa = x[conn[e, a]]
            for i in range(3):
                u[3 * a + i] = R[0, i] * xa[0] + R[1, i] * xa[1] + R[2, i] * xa[2] - X[e, a, i]
        Ke = K[e]
        for i in range(nd):
            s = 0.0
            for j in range(nd):
                s += Ke[i, j] * u[j]
            fl[i] = s
        for a in range(k):
            na = conn[e, a]
            for i in range(3):
                f_out[na, i] -= R[i, 0] * fl[3 * a] + R[i, 1] * fl[3 * a + 1] + R[i, 2] * fl[3 * a + 2]
        if want_tangent:
            # RK = blockdiag(R) @ K
            for a in range(k):
                for i in range(3):
                    for j in range(nd):
                        RK[3 * a + i, j] = (
                            R[i, 0] * Ke[3 * a, j] + R[i, 1] * Ke[3 * a + 1, j] + R[i, 2] * Ke[3 * a + 2, j]
                        )
            # data += coef * RK @ blockdiag(R)^T
            dm = data_map[e]
            for i in range(nd):
                for b in range(k):
                    for j in range(3):
                        s = RK[i, 3 * b] * R[j, 0] + RK[i, 3 * b + 1] * R[j, 1] + RK[i, 3 * b + 2] * R[j, 2]
                        data_out[dm[i * nd + 3 * b + j]] += coef * s
    return n_bad


@njit(cache=True)
def _advance(x, v, h, out, n0, n1):
    """Rows ``n0 .. n1 - 1`` of :func:`advance_positions` into ``out``: ``(max |v_n|^2, finite)``."""
    speed2 = 0.0
    finite = True
    for n in range(n0, n1):
        s = 0.0
        for i in range(3):
            out[n, i] = x[n, i] + h * v[n, i]
            s += v[n, i] * v[n, i]
            finite &= np.isfinite(out[n, i])
        finite &= np.isfinite(s)
        speed2 = max(speed2, s)
    return speed2, finite


@njit(cache=True)
def advance_positions(x, v, h):
    """``(x + h v, max_n |v_n|^2, finite)`` for positions and velocities ``(N, 3)`` (mm, mm/s)
    in one pass; ``finite`` is False if any velocity or new position is NaN or infinite."""
    out = np.empty_like(x)
    speed2, finite = _advance(x, v, h, out, 0, x.shape[0])
    return out, speed2, finite


@njit(cache=True)
def advance_positions_ranges(x, v, h, starts):
    """:func:`advance_positions` of stacked models: ``(x + h v, speed2, finite)`` with the
    largest squared speed ``(M,)`` (mm^2/s^2) and the finiteness ``(M,)`` of each model's rows
    ``starts[i] .. starts[i + 1] - 1`` (``starts``: ``(M + 1,)``)."""
    out = np.empty_like(x)
    M = starts.shape[0] - 1
    speed2 = np.empty(M)
    finite = np.empty(M, np.bool_)
    for i in range(M):
        speed2[i], finite[i] = _advance(x, v, h, out, starts[i], starts[i + 1])
    return out, speed2, finite
