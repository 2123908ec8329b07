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
from softcrawl.fem.linalg import Factorization


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


#: Static data shared by equal floating bodies of one process (e.g. the disks of all robots of a
#: worker): key -> value, the oldest dropped beyond :data:`SHARED_MAX`.
_SHARED: dict = {}
SHARED_MAX = 16


def shared(key, make):
    """The value kept for ``key`` (exact bytes of everything it depends on), made by ``make()``
    the first time. Equal keys give the same object, so it must not be modified."""
    if key not in _SHARED:
        while len(_SHARED) >= SHARED_MAX:
            _SHARED.pop(next(iter(_SHARED)))
        _SHARED[key] = make()
    return _SHARED[key]


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
    def _key(self) -> tuple | None:
        """Exact bytes of everything :attr:`rest_stiffness` depends on (None: not shared)."""
        b = self.body
        if b.membrane is not None:
            return None
        return (b.mesh.points.tobytes(), b.mesh.tets.tobytes(), repr(b.material), b.rotation_method)

    @cached_property
    def rest_stiffness(self) -> sp.csr_matrix:
        """``(3n, 3n)`` ``K_0``, the tangent stiffness at rest (mN/mm); one matrix per process for
        equal bodies (:func:`shared`: every robot's disk is the same mesh at the same place)."""
        b = self.body

        def make():
            _, data, _ = b.internal_forces(b.mesh.points, tangent_coef=1.0)
            return b.pattern.matrix(data)

        return make() if self._key is None else shared(("K0",) + self._key, make)

    def step_factorization(self, h: float, r_mass: float, r_stiff: float) -> Factorization:
        """The factorization of ``A_0 = (1 + h r_M) M + h (h + r_K) K_0`` (s, 1/s, s; one per
        process for equal bodies and coefficients: :func:`shared`)."""
        mass3 = np.repeat(self.body.nodal_mass, 3)

        def make():
            return Factorization(h * (h + r_stiff) * self.rest_stiffness + sp.diags((1 + h * r_mass) * mass3))

        if self._key is None:
            return make()
        return shared(("A0",) + self._key + (mass3.tobytes(), float(h), float(r_mass), float(r_stiff)), make)

    @cached_property
    def weighted_rest(self) -> np.ndarray:
        """``(n, 3)`` :attr:`rest_centred` times :attr:`weights`."""
        return np.ascontiguousarray(self.rest_centred * self.weights[:, None])

    def rotation(self, x: np.ndarray) -> np.ndarray:
        """``(3, 3)`` the floating frame's rotation at positions ``x`` ``(n, 3)`` mm."""
        return _kabsch(np.ascontiguousarray(x), self.weighted_rest)

    def free_rhs(self, x: np.ndarray, v: np.ndarray, f: np.ndarray, h: float, r_mass: float,
                 r_stiff: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The body-frame system of :meth:`free_velocity` before its solve: ``(v', rhs, R)`` with
        ``v' = R^T v`` ``(n, 3)``, the right-hand side ``(3n,)`` and the rotation ``(3, 3)``."""
        R = self.rotation(x)
        K = self.rest_stiffness
        vb, rhs = floating_rhs(x, v, f, R, self.body.mesh.points, self.body.nodal_mass, K.indptr, K.indices,
                               K.data, h, r_mass, r_stiff)
        return vb, rhs, R

    @staticmethod
    def world_velocity(vb: np.ndarray, dv: np.ndarray, R: np.ndarray) -> np.ndarray:
        """``(n, 3)`` world velocities ``(v' + dv') R^T`` from body-frame ones (``dv'``: ``(3n,)``)."""
        return (vb + dv.reshape(-1, 3)) @ R.T

    def free_velocity(self, factor: Factorization, x: np.ndarray, v: np.ndarray, f: np.ndarray, h: float,
                      r_mass: float, r_stiff: float) -> tuple[np.ndarray, np.ndarray]:
        """The body's implicit step without constraints, solved in its frame (module doc):
        ``dv' = A_0^-1 h (R^T f - K_0 (R^T x - X + (h + r_K) R^T v) - r_M M R^T v)``.

        Args:
            factor: the factorization of ``A_0`` (:meth:`step_factorization`).
            x, v: ``(n, 3)`` positions (mm) and velocities (mm/s) at the start of the step.
            f: ``(n, 3)`` external forces (gravity, pressures, prescribed), mN.
            h, r_mass, r_stiff: time step (s) and Rayleigh coefficients.

        Returns:
            ``(v_free, R)``: ``(n, 3)`` free world velocities (mm/s) and the frame's rotation
            ``(3, 3)`` (the body's constraint coefficients are multiplied by it).
        """
        vb, rhs, R = self.free_rhs(x, v, f, h, r_mass, r_stiff)
        return self.world_velocity(vb, factor.solve(rhs), R), R
