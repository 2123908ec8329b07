"""An RID element's corotational frame and edge terms from its edge vectors given by components:
lists of arrays (one entry per element), combined by sums of products only, so that XLA fuses
them into element-wise kernels and a Pallas kernel holds them in registers, without the stacks
that vector operations (``jnp.cross``, ``jnp.stack``) bring (:mod:`softcrawl.jaxsim.legs`'
pairs form, :mod:`softcrawl.jaxsim.ridkernel`); and products of 3-vectors with a matrix the same
way (:func:`by_rows`), and the modal coordinates the leg part's affine arrays multiply
(:func:`homogeneous`).
"""

from __future__ import annotations

from functools import reduce

import jax.numpy as jnp
from jax import lax


def cross(a, b):
    """The cross product of two vectors given by their components (lists of three arrays)."""
    return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]


def unit(a):
    """The unit vector along ``a`` given by its components (a list of three arrays)."""
    inv = lax.rsqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    return [ai * inv for ai in a]


def frame_terms(d):
    """``(F, g, bad)`` of elements with edge vectors ``d`` (``d[a][i]``: edge ``a`` of ``k - 1``,
    component ``i``, arrays of one shape): the frame ``F[p][i]`` (rows e1 = unit(d_0), e2 = n x
    e1, n = unit(d_0 x d_1), as :func:`softcrawl.jaxsim.legs.element_frames`), the edges in it
    ``g[3 a + p] = F_p . d_a`` and whether each element is inverted or degenerate (a frame not
    finite; for a tetrahedron, ``k - 1 = 3``, also ``det(d) = d_2 . (d_0 x d_1)`` not positive)."""
    normal = cross(d[0], d[1])
    e1, n = unit(d[0]), unit(normal)
    F = [e1, cross(n, e1), n]
    bad = ~reduce(jnp.logical_and, [jnp.isfinite(v) for row in F for v in row])
    if len(d) == 3:
        bad = bad | ~(sum(a * b for a, b in zip(d[2], normal)) > 0)
    g = [F[p][0] * da[0] + F[p][1] * da[1] + F[p][2] * da[2] for da in d for p in range(3)]
    return F, g, bad


def by_rows(x, M):
    """``x @ M`` for ``x`` ``(..., 3)`` and ``M`` ``(..., 3, k)`` (broadcast together): three
    elementwise products summed, which XLA fuses with the operations around them, where a matrix
    product with an inner size of 3 is a kernel of its own on a GPU (a library call, often with
    a transpose)."""
    return x[..., 0, None] * M[..., 0, :] + x[..., 1, None] * M[..., 1, :] + x[..., 2, None] * M[..., 2, :]


def homogeneous(q, w: float = 1.0):
    """``(..., m + 1)``: ``q`` ``(..., m)`` with ``w`` appended, ``(q, w)``. With ``w = 1`` the leg
    part's ``[Phi_n, X_n]`` arrays multiply it to give positions ``X_n + Phi_n q``
    (:class:`softcrawl.jaxsim.model.LegPart`), and the cavity load's polynomial takes it; with
    ``w = 0`` (modal velocities) they give velocities ``Phi_n qdot``."""
    return jnp.concatenate([q, jnp.full((*q.shape[:-1], 1), w, q.dtype)], axis=-1)
