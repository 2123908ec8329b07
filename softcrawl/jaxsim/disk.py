"""The floating-frame disk's free motion in JAX (:mod:`softcrawl.reduction.floating`, its module doc):
with ``R`` the best rigid fit of the current positions to the rest ones (mass-weighted Kabsch),

    dv' = A_0^-1 h (R^T f - K_0 (R^T x - X + (h + r_K) R^T v) - r_M M R^T v),   v_free = R (R^T v + dv')

(Shabana, *Dynamics of Multibody Systems*, ch. 5; Felippa & Haugen 2005), ``A_0^-1`` dense and
constant. As ``A_0 = h (h + r_K) K_0 + (1 + h r_M) M``, ``A_0 (R^T v + dv') = M R^T v + h (R^T f -
K_0 (R^T x - X))``: the damping terms cancel. So, with ``f = m ⊗ g`` (gravity, the disk's only
load),

    R^T v_free = A_0^-1 M R^T v - h A_0^-1 K_0 (R^T x - X) + h A_0^-1 (m ⊗ I_3) R^T g,

one product of the constant ``(3n, 6n + 3)`` operator ``[A_0^-1 M | -h A_0^-1 K_0 | h A_0^-1 (m ⊗
I_3)]`` (:attr:`~softcrawl.jaxsim.model.DiskPart.step_operator`) with ``(R^T v, R^T x - X, R^T g)``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from softcrawl.jaxsim.frames import by_rows, cross

#: Newton iterations of :func:`polar_rotation`: 8 give the SVD's rotation to 1e-14 in float64 and
#: 1.6e-7 in float32 on moment matrices of the paper's disk rotated at random, stretched and
#: sheared by up to 30% (``tests/test_jaxsim_delassus.py``).
POLAR_ITERATIONS = 8


def polar_rotation(H, iterations: int = POLAR_ITERATIONS):
    """``(3, 3)`` the rotation maximising ``tr(R H)``: the orthogonal polar factor of ``H^T``, by
    Newton's iteration with determinant scaling ``X' = (z X + X^-T / z) / 2``, ``z = |det X|^-1/3``,
    from ``X = H^T`` (Higham 2008, "Functions of Matrices", ch. 8, determinantal scaling): ``X^-T``
    is the cofactor matrix over the determinant, so that the iterations are elementwise
    arithmetic on the nine entries, each its own array (on a GPU they fuse into few kernels;
    the SVD is a chain of library kernels). ``H`` with ``det H <= 0`` (the disk turned inside
    out: no rotation fits without a reflection) gives NaN.

    The nine entries pass an optimization barrier before they are stacked: fused with the
    stack, XLA's GPU emitter evaluates the iterations once for each of the nine entries of the
    output, and at small batches it fused all eight iterations into one such kernel, whose
    machine code is 170 times the barrier's (benchmarks/RESULTS.md)."""
    X = [[H[j, i] for j in range(3)] for i in range(3)]  # rows of H^T, each entry its own array
    det_h = None
    for _ in range(iterations):
        cof = [cross(X[1], X[2]), cross(X[2], X[0]), cross(X[0], X[1])]
        det = X[0][0] * cof[0][0] + X[0][1] * cof[0][1] + X[0][2] * cof[0][2]
        det_h = det if det_h is None else det_h  # det X_0 = det H
        z = jnp.abs(det) ** (-1.0 / 3.0)
        w = 1.0 / (z * det)
        X = [[0.5 * (z * X[i][j] + w * cof[i][j]) for j in range(3)] for i in range(3)]
    X, det_h = jax.lax.optimization_barrier((X, det_h))
    return jnp.where(det_h > 0, jnp.stack([jnp.stack(r) for r in X]), jnp.nan)


def kabsch(x, weighted_rest):
    """``(3, 3)`` rotation maximising ``tr(R H)``, ``H = sum_n w_n X_n x_n^T`` (reflections
    excluded; Kabsch 1976, Acta Cryst. A32, 922); ``x``, ``weighted_rest``: ``(n, 3)`` mm. By the
    SVD ``H = U S V^T``, ``R = V diag(1, 1, d) U^T``; on CUDA by :func:`polar_rotation`, the same
    rotation to round-off wherever ``det H > 0``. ``H`` is summed elementwise, one reduction per
    robot: as a matrix product a batch's positions were transposed first, an operation of its own
    on a GPU."""
    H = jnp.sum(weighted_rest[:, :, None] * x[:, None, :], axis=0)
    return jax.lax.platform_dependent(H, cuda=polar_rotation, default=_svd_rotation)


def _svd_rotation(H):
    U, _, Vt = jnp.linalg.svd(H)
    d = jnp.sign(jnp.linalg.det(U @ Vt))
    V = Vt.T.at[:, 2].multiply(d)
    return V @ U.T


def free_motion(disk, settings, x, v):
    """The disk's step without constraints under gravity (module doc; the step length and
    Rayleigh damping are those :attr:`~softcrawl.jaxsim.model.DiskPart.step_operator` was formed
    with, ``settings``' own).

    Args:
        disk: :class:`~softcrawl.jaxsim.model.DiskPart`; settings: :class:`~softcrawl.jaxsim.model.Settings`.
        x, v: ``(n, 3)`` positions (mm) and velocities (mm/s).

    Returns:
        ``(v_free (n, 3) mm/s, R (3, 3))``.
    """
    R = kabsch(x, disk.weighted_rest)
    g = by_rows(jnp.asarray(settings.gravity, x.dtype), R)[None, :]
    frame = jnp.concatenate([by_rows(v, R), by_rows(x, R) - disk.rest, g])
    return by_rows((disk.step_operator @ frame.reshape(-1)).reshape(-1, 3), R.T), R
