"""Private stand-in for :mod:`softcrawl.jaxsim.contact` (the batched contact solver), with its API,
used only while that module is absent: a plain block projected Gauss-Seidel on the condensed
problem. The engine imports the real module when it exists.

Formulas: bilateral rows eliminated by a Schur complement (Duriez et al. 2006, sec. 4); block
projected Gauss-Seidel with the friction cone projection of physics.md ("Contact with the floor").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp


def condense(W, q, bilateral_mask):
    """Eliminate the bilateral rows (``u_b = 0``) of ``u = W lam + q``.

    Args:
        W: ``(nb + 3K, nb + 3K)`` Delassus operator; q: ``(nb + 3K,)`` free velocities.
        bilateral_mask: ``(nb,)`` bool, the bilateral rows in use (the others get zero impulse).

    Returns:
        ``(X, Wc, qc)``: ``X = W_bb^-1 [q_b, W_bc]`` ``(nb, 3K + 1)``, the condensed ``Wc``
        ``(3K, 3K)`` and ``qc`` ``(3K,)``.
    """
    nb = bilateral_mask.shape[0]
    on = bilateral_mask.astype(W.dtype)
    Wbb = W[:nb, :nb] * on[:, None] * on[None, :] + jnp.diag(1.0 - on)
    rhs = jnp.concatenate([q[:nb, None], W[:nb, nb:]], axis=1) * on[:, None]
    X = jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(Wbb), True), rhs)
    Wcb = W[nb:, :nb] * on[None, :]
    return X, W[nb:, nb:] - Wcb @ X[:, 1:], q[nb:] - Wcb @ X[:, 0]


def pgs_coulomb(W, q, mu, lam0, active, n_sweeps):
    """Projected Gauss-Seidel on ``u = W lam + q``, contact blocks (normal, t1, t2): per block
    the normal impulse (``lam_n >= 0``), then the tangents with the mean tangent diagonal,
    projected on the cone ``|lam_t| <= mu lam_n`` (:func:`softcrawl.fem.contact.pgs_coulomb`);
    inactive contacts keep zero impulse.

    Args:
        W: ``(3K, 3K)``; q: ``(3K,)``; mu: ``(K,)`` or scalar; lam0: ``(3K,)`` start;
        active: ``(K,)`` bool; n_sweeps: int (static).

    Returns:
        ``(3K,)`` impulses.
    """
    K = active.shape[0]
    mu = jnp.broadcast_to(mu, (K,))
    Wr = W.reshape(K, 3, 3 * K)

    Wd = W.reshape(K, 3, K, 3)[jnp.arange(K), :, jnp.arange(K), :]  # (K, 3, 3) diagonal blocks
    qb = q.reshape(K, 3)

    def contact(i, lam):
        Wi, d, li = Wr[i], Wd[i], lam[i]
        ln = jnp.maximum(li[0] - (qb[i, 0] + Wi[0] @ lam.reshape(-1)) / d[0, 0], 0.0) * active[i]
        lam = lam.at[i, 0].set(ln)
        t = li[1:] - (qb[i, 1:] + Wi[1:] @ lam.reshape(-1)) / (0.5 * (d[1, 1] + d[2, 2]))
        nt = jnp.sqrt(t @ t)
        lim = mu[i] * ln
        t = jnp.where(nt > lim, t * (lim / jnp.maximum(nt, 1e-300)), t)
        return lam.at[i, 1:].set(t)

    lam = jax.lax.fori_loop(0, n_sweeps, lambda _, l: jax.lax.fori_loop(0, K, contact, l),
                            lam0.reshape(K, 3) * active[:, None])
    return lam.reshape(-1)


def solve_constraints(W, q, bilateral_mask, mu, lam0, active, n_sweeps):
    """Bilateral rows first (exact), then the contact blocks (:func:`pgs_coulomb`): ``(nb + 3K,)``."""
    nb = bilateral_mask.shape[0]
    X, Wc, qc = condense(W, q, bilateral_mask)
    lam_c = pgs_coulomb(Wc, qc, mu, lam0, active, n_sweeps) if active.shape[0] else qc[:0]
    lam_b = -(X[:, 0] + X[:, 1:] @ lam_c) * bilateral_mask
    return jnp.concatenate([lam_b, lam_c])


def floor_contacts(points, velocities, floor_z, distance, K):
    """The ``K`` points with the smallest predicted gap ``min(gap, gap + velocities_z)``
    (``velocities``: displacements over the step, mm): ``(idx (K,), active (K,) bool: predicted
    gap below ``distance``, gap (K,) current gap mm)``."""
    gap = points[:, 2] - floor_z
    pred = jnp.minimum(gap, gap + velocities[:, 2])
    _, idx = jax.lax.top_k(-pred, K)
    return idx, pred[idx] < distance, gap[idx]
