"""The floating-frame disk's free motion in JAX (:mod:`softcrawl.reduction.floating`, its module doc):
with ``R`` the best rigid fit of the current positions to the rest ones (mass-weighted Kabsch),

    dv' = A_0^-1 h (R^T f - K_0 (R^T x - X + (h + r_K) R^T v) - r_M M R^T v),   v_free = R (R^T v + dv')

(Shabana, *Dynamics of Multibody Systems*, ch. 5; Felippa & Haugen 2005), ``A_0^-1`` dense and
constant.
"""

from __future__ import annotations

import jax.numpy as jnp


def kabsch(x, weighted_rest):
    """``(3, 3)`` rotation maximising ``tr(R H)``, ``H = sum_n w_n X_n x_n^T`` (reflections
    excluded; Kabsch 1976, Acta Cryst. A32, 922); ``x``, ``weighted_rest``: ``(n, 3)`` mm."""
    U, _, Vt = jnp.linalg.svd(weighted_rest.T @ x)
    d = jnp.sign(jnp.linalg.det(U @ Vt))
    V = Vt.T.at[:, 2].multiply(d)
    return V @ U.T


def free_motion(disk, settings, x, v):
    """The disk's step without constraints under gravity.

    Args:
        disk: :class:`~softcrawl.jaxsim.model.DiskPart`; settings: :class:`~softcrawl.jaxsim.model.Settings`.
        x, v: ``(n, 3)`` positions (mm) and velocities (mm/s).

    Returns:
        ``(v_free (n, 3) mm/s, R (3, 3))``.
    """
    h, rM, rK = settings.dt, settings.rayleigh_mass, settings.rayleigh_stiffness
    R = kabsch(x, disk.weighted_rest)
    vb = v @ R
    stretch = (x @ R - disk.rest + (h + rK) * vb).reshape(-1)
    f = disk.mass[:, None] * (jnp.asarray(settings.gravity, x.dtype) @ R)[None, :]
    rhs = h * (f.reshape(-1) - disk.stiffness @ stretch - rM * (disk.mass[:, None] * vb).reshape(-1))
    dv = (disk.inverse @ rhs).reshape(-1, 3)
    return (vb + dv) @ R.T, R
