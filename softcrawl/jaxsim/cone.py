"""The Coulomb cone's arithmetic on a contact's components, shared by the contact solve's two
forms: XLA's (:func:`softcrawl.jaxsim.contact.project_cone`, whole ``(K, 3)`` arrays) and the
GPU kernel's (:mod:`softcrawl.jaxsim.fused`, one row's contact per lane). Every argument is an
array of one shape (or broadcastable): the normal component ``n``, the tangential ``t1, t2``
and the friction coefficient ``mu``.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax


def cone_projection(n, t1, t2, mu):
    """The Euclidean projection of ``(n, t1, t2)`` onto the Coulomb cone ``|t| <= mu n`` as
    ``(n', f)``: the projected normal component and the factor of the tangential ones
    (``t' = f t``). Unchanged inside, 0 in the polar cone ``mu |t| <= -n``, else ``n' = (n + mu
    |t|) / (1 + mu^2)``, ``t' = mu n' t / |t|`` (the closed-form projection onto a second-order
    cone, as in Mazhar et al. 2015). One reciprocal square root: ``|t| = s r``, ``s = |t|^2``,
    ``r = 1 / sqrt(s)`` (``s`` floored at the dtype's smallest normal number for ``t = 0``)."""
    s = t1 * t1 + t2 * t2
    r = lax.rsqrt(jnp.maximum(s, jnp.finfo(jnp.result_type(n)).tiny))
    nt = s * r
    inside = nt <= mu * n
    ln = jnp.where(inside, n, jnp.maximum((n + mu * nt) / (1 + mu * mu), 0))
    return ln, jnp.where(inside, 1, mu * ln * r)


def de_saxce_term(t1, t2, mu):
    """De Saxce's addition ``mu |u_t|`` to a velocity's normal component (tangential ``t1,
    t2``, mm/s): the velocities with it are complementary to the impulses in the Coulomb cone
    exactly when they solve the Coulomb problem (De Saxce and Feng 1991, the bipotential)."""
    return mu * jnp.sqrt(t1 * t1 + t2 * t2)
