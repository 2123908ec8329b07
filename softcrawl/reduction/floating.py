"""A stiff body reduced to linear elasticity in one floating frame (the disk of a reduced robot).

The full model rotates every element by its own corotational frame (SOFA ``"large"``). A
body whose strains stay small, like the printed disk (E = 5,000 kPa, 4.3x the legs'), moves
almost rigidly, so one frame for the whole body is enough: with ``R`` the rotation of the
best rigid fit of the current positions to the rest ones (mass-weighted Kabsch / polar
decomposition), ``K_0`` the rest stiffness and ``M`` the lumped (isotropic) mass,

    f = -R K_0 (R^T x - X),     K_t = R K_0 R^T,
    A = (1 + h r_M) M + h (h + r_K) K_t = R A_0 R^T,   A_0 = (1 + h r_M) M + h (h + r_K) K_0

(floating frame of reference formulation: Shabana, *Dynamics of Multibody Systems*, 3rd ed.,
ch. 5; the corotational force of Felippa & Haugen 2005, "A unified formulation of small-strain
corotational finite elements", with one frame for all elements). ``A_0`` is constant, so the
body's implicit step is one solve with a factorization made once, and its constraint
compliance columns ``A_0^-1 E`` never change: ``W_b = (H R) A_0^-1 (H R)^T`` (a
:class:`~softcrawl.fem.constraints.NodalCompliance` of ``A_0`` whose ``rotation`` is ``R``). ``R`` is
taken at the start of the step, as the corotational solver takes its element rotations; like
there, the tangent ignores the derivative of ``R``. The body keeps all its nodes (no basis):
this reduces the nonlinearity, not the dimension. It has no per-element inversion check (strains
stay small); a diverging state is still caught by the solver's speed and finiteness checks.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.sparse as sp
from numba import njit

from softcrawl.fem.body import Body


@njit(cache=True)
def _kabsch(x, weighted_rest):
    """``R`` maximising ``tr(R H)``, ``H = sum_n w_n X_n x_n^T``, with ``det R = +1``."""
    H = weighted_rest.T @ x
    U, _, Vt = np.linalg.svd(H)
    d = 1.0 if np.linalg.det(U @ Vt) >= 0.0 else -1.0
    V = Vt.T.copy()
    V[:, 2] *= d
    return V @ U.T


def rigid_fit_rotation(x: np.ndarray, rest_centred: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Rotation ``R`` minimising ``sum_n w_n |R X_n - (x_n - xbar)|^2`` (``xbar`` the weighted
    centroid of ``x``; the Kabsch algorithm, reflections excluded: Kabsch 1976, Acta Cryst.
    A32, 922).

    Args:
        x: ``(..., n, 3)`` current positions, mm (leading axes: a batch, e.g. frames).
        rest_centred: ``(..., n, 3)`` rest positions minus their weighted centroid (with
            ``weights``), mm.
        weights: ``(n,)`` non-negative weights summing to 1 (e.g. nodal masses over the total).

    Returns:
        ``(..., 3, 3)`` rotations.
    """
    # sum_n w_n X_n (x_n - xbar)^T = sum_n w_n X_n x_n^T: the weighted X_n sum to zero.
    x, rest = np.broadcast_arrays(np.asarray(x, float), rest_centred)
    weighted = rest * weights[:, None]
    out = np.empty(x.shape[:-2] + (3, 3))
    for i in np.ndindex(x.shape[:-2]):
        out[i] = _kabsch(np.ascontiguousarray(x[i]), np.ascontiguousarray(weighted[i]))
    return out


@njit(cache=True)
def floating_rhs(x, v, f, R, X, mass, indptr, indices, data, h, r_mass, r_stiff):
    """Body-frame velocities ``v' = R^T v`` ``(n, 3)`` and the right-hand side of the body-frame
    step ``h (R^T f - K_0 (R^T x - X + (h + r_K) v') - r_M M v')`` ``(3n,)`` (module doc);
    ``K_0`` in CSR (``indptr, indices, data``), ``mass`` ``(n,)`` nodal masses."""
    n = x.shape[0]
    vb = v @ R
    stretch = (x @ R - X + (h + r_stiff) * vb).ravel()
    fb = (f @ R).ravel()
    vf = vb.ravel()
    rhs = np.empty(3 * n)
    for i in range(3 * n):
        acc = 0.0
        for p in range(indptr[i], indptr[i + 1]):
            acc += data[p] * stretch[indices[p]]
        rhs[i] = h * (fb[i] - acc - r_mass * mass[i // 3] * vf[i])
    return vb, rhs


@dataclass(frozen=True, eq=False)
class FloatingFrameBody:
    """A full-order body simulated as linear elastic in its floating frame (see module doc).

    Attributes:
        body: the body (all its nodes stay degrees of freedom).

    Raises:
        ValueError: the body has fixed DOFs (its frame would not float).
    """

    body: Body

    def __post_init__(self) -> None:
        if not self.body.free_dofs.all():
            raise ValueError(f"floating-frame body {self.body.name!r} cannot have fixed DOFs")

    @cached_property
    def weights(self) -> np.ndarray:
        """``(n,)`` nodal masses over the body's mass."""
        return self.body.nodal_mass / self.body.nodal_mass.sum()

    @cached_property
    def rest_centred(self) -> np.ndarray:
        """``(n, 3)`` rest positions minus the rest centre of mass, mm."""
        X = self.body.mesh.points
        return X - self.weights @ X

    @cached_property
    def rest_stiffness(self) -> sp.csr_matrix:
        """``(3n, 3n)`` ``K_0``, the tangent stiffness at rest (mN/mm)."""
        _, data, _ = self.body.internal_forces(self.body.mesh.points, tangent_coef=1.0)
        return self.body.pattern.matrix(data)

    @cached_property
    def weighted_rest(self) -> np.ndarray:
        """``(n, 3)`` :attr:`rest_centred` times :attr:`weights`."""
        return np.ascontiguousarray(self.rest_centred * self.weights[:, None])

    def rotation(self, x: np.ndarray) -> np.ndarray:
        """``(3, 3)`` the floating frame's rotation at positions ``x`` ``(n, 3)`` mm."""
        return _kabsch(np.ascontiguousarray(x), self.weighted_rest)
