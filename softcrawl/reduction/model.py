"""Reduced parts and reduced bodies: the static data of a (hyper-)reduced model.

A :class:`PartReduction` is what a reduction build produces for one part (the PneuNet leg,
the disk) in the part's own frame: the POD basis and the ECSW reduced integration domain.
A :class:`RobotReduction` is the set of parts a crawler is made of (reduction.md: "reduce
each part once; build any design by placing reduced parts"). A :class:`ReducedBody` is a
part placed in a robot by a rotation ``R_i``: its basis is the part's with every node's
3-vector in every column rotated by ``R_i`` (reduction.md; RID and weights are rotation
invariant), and its RID element data are the part's, in the part frame (the solver evaluates
each leg there: :mod:`softcrawl.reduction.kernels`). Kinematics: ``x = X + Phi q`` (``X``
placed rest positions, ``q`` reduced coordinates).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from softcrawl.fem.body import Body
from softcrawl.fem.elements import ElementSet, membrane_triangles, tetrahedra
from softcrawl.geometry.mesh import TetMesh
from softcrawl.reduction.kernels import stiffness_factors


@dataclass(frozen=True, eq=False)
class PartReduction:
    """The reduction of one part, in the part's own (leg-local) frame.

    Attributes:
        mesh: the part's mesh the reduction was built on (leg-local, mm).
        basis: ``(3n, m)`` orthonormal basis (xyz interleaved per node): rigid modes first.
        n_rigid: number of rigid modes at the front of ``basis``.
        singular_values: ``(S,)`` POD singular values of the snapshots (rigid part removed).
        tet_rid, tet_weights: ``(k,)`` RID tetrahedra (indices into ``mesh.tets``) and ECSW weights.
        tri_rid, tri_weights: the same for the membrane (paper) triangles
            (indices into the body's ``membrane.triangles``).
        metadata: JSON-ready build information (tolerances, errors, settings, version).

    Raises:
        ValueError: mismatched shapes, negative weights or indices out of range.
    """

    mesh: TetMesh
    basis: np.ndarray
    n_rigid: int
    singular_values: np.ndarray
    tet_rid: np.ndarray
    tet_weights: np.ndarray
    tri_rid: np.ndarray
    tri_weights: np.ndarray
    metadata: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        n3 = 3 * self.mesh.n_nodes
        if self.basis.ndim != 2 or self.basis.shape[0] != n3 or not np.all(np.isfinite(self.basis)):
            raise ValueError(f"basis must be a finite ({n3}, m) array, got shape {self.basis.shape}")
        for name, idx, w, n in (("tetrahedra", self.tet_rid, self.tet_weights, self.mesh.n_tets),
                                ("membrane triangles", self.tri_rid, self.tri_weights, None)):
            if idx.shape != w.shape or idx.ndim != 1:
                raise ValueError(f"RID {name}: indices {idx.shape} and weights {w.shape} must match")
            if len(idx) and (idx.min() < 0 or (n is not None and idx.max() >= n) or len(np.unique(idx)) != len(idx)):
                raise ValueError(f"RID {name}: indices must be distinct and in 0..{n - 1}")
            if not (np.all(np.isfinite(w)) and np.all(w >= 0)):
                raise ValueError(f"RID {name}: ECSW weights must be finite and >= 0")

    @property
    def n_modes(self) -> int:
        return self.basis.shape[1]

    @classmethod
    def full(cls, mesh: TetMesh, basis: np.ndarray, n_triangles: int, n_rigid: int = 0, **metadata) -> PartReduction:
        """Every element (``mesh.tets`` and ``n_triangles`` membrane triangles) at unit weight:
        the Galerkin projection, no hyper-reduction."""
        n_tri = n_triangles
        return cls(mesh, basis, n_rigid, np.zeros(0), np.arange(mesh.n_tets), np.ones(mesh.n_tets),
                   np.arange(n_tri), np.ones(n_tri), dict(metadata))


@dataclass(frozen=True, eq=False)
class RobotReduction:
    """The reduced parts of a crawler.

    Attributes:
        leg: the PneuNet leg (placed in every slot, rotated to its pose).
        disk: the central disk, or None: no disk part (the robot's disk is then full-order or
            floating-frame, ``RobotConfig.reduced_disk``; the paper kept it full-order).
        metadata: JSON-ready build information shared by the parts (settings, model
            parameters, wall time and peak memory of each phase).
    """

    leg: PartReduction
    disk: PartReduction | None = None
    metadata: dict = field(default_factory=dict)

    @property
    def parts(self) -> dict[str, PartReduction]:
        """Name (``"leg"``, ``"disk"``) -> part, for the parts present."""
        return {name: p for name, p in (("leg", self.leg), ("disk", self.disk)) if p is not None}


def rotate_basis(basis: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """``(3n, m)`` basis with every node's 3-vector in every column rotated by ``rotation``."""
    n3, m = basis.shape
    return np.einsum("ij,njm->nim", rotation, basis.reshape(n3 // 3, 3, m)).reshape(n3, m)


@dataclass(frozen=True)
class ElementFactors:
    """RID element data of one family of a part, in the part frame (see
    :mod:`softcrawl.reduction.kernels`).

    Attributes:
        conn: ``(E, k)`` node indices.
        factors: ``(E, r, 3(k - 1))`` ``C~_e``: stiffness factors on the edge vectors in each
            element's rest frame, scaled by the square roots of the ECSW weights (sqrt(mN/mm)).
        rest_terms: ``(E, r)`` ``s0_e``: the factors times the rest edge vectors.
        rows: ``(E, 3(k - 1), m')`` the edge basis rows ``D Phi_e`` of the part's strain modes
            (:attr:`ReducedBody.strain_modes`).
    """

    conn: np.ndarray
    factors: np.ndarray
    rest_terms: np.ndarray
    rows: np.ndarray

    @classmethod
    def of(cls, elements: ElementSet, rank: int, weights: np.ndarray, rows: np.ndarray) -> ElementFactors:
        """The data of corotational ``"large"`` elements with ECSW ``weights`` ``(E,)``, factor
        ``rank`` (6 tetrahedra, 3 membrane triangles) and edge basis rows ``rows``."""
        E, k = elements.conn.shape
        C = np.sqrt(weights)[:, None, None] * stiffness_factors(elements.stiffness, rank)
        edges = (elements.rest[:, 1:] - elements.rest[:, :1]).reshape(E, -1)
        rest_frame = np.einsum("eiaj,ecj->eiac", C.reshape(E, rank, k - 1, 3), elements.frames)
        return cls(elements.conn, np.ascontiguousarray(rest_frame.reshape(E, rank, -1)),
                   np.einsum("eiq,eq->ei", C, edges), np.ascontiguousarray(rows))

    @property
    def n_rows(self) -> int:
        """Rows of ``Z`` of this family (``E * r``)."""
        return self.factors.shape[0] * self.factors.shape[1]


#: Largest distance (mm) between a reduced body's rest nodes and its part's nodes placed by
#: the body's rotation (after the best translation) for the body to be that placed part.
PLACEMENT_TOLERANCE = 1e-6


@dataclass(frozen=True, eq=False)
class ReducedBody:
    """A reduced part placed in a model: ``x = X + basis @ q`` with
    ``basis = blockdiag(rotation) @ part.basis`` (reduction.md: every node's 3-vector in every
    column is rotated; RID and weights are rotation invariant).

    Attributes:
        body: the full-order body (placed mesh, materials, masses, cavities, collision nodes).
        part: the part reduction it came from.
        rotation: ``(3, 3)`` the rotation placing the part frame in the world.

    Raises:
        ValueError: the body has fixed DOFs, uses the "polar" rotation method, or is not the
            part's mesh placed by ``rotation`` and a translation.
    """

    body: Body
    part: PartReduction
    rotation: np.ndarray

    def __post_init__(self) -> None:
        R = np.asarray(self.rotation, float)
        object.__setattr__(self, "rotation", R)
        if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-9) or np.linalg.det(R) <= 0:
            raise ValueError(f"rotation of reduced body {self.body.name!r} must be a proper 3x3 rotation")
        if self.body.n_nodes != self.part.mesh.n_nodes:
            raise ValueError(f"body {self.body.name!r} has {self.body.n_nodes} nodes, "
                             f"the reduction {self.part.mesh.n_nodes}")
        local = self.body.mesh.points @ R
        gap = local - self.part.mesh.points
        if np.abs(gap - gap.mean(axis=0)).max() > PLACEMENT_TOLERANCE:
            raise ValueError(f"body {self.body.name!r} is not the reduction's mesh placed by the given rotation")
        if not self.body.free_dofs.all():
            raise ValueError(f"reduced body {self.body.name!r} cannot have fixed DOFs")
        if self.body.rotation_method != "large":
            raise ValueError("reduced bodies use the corotational 'large' rotation method")

    @property
    def n_modes(self) -> int:
        return self.part.n_modes

    @cached_property
    def basis(self) -> np.ndarray:
        """``(3n, m)`` the part basis rotated to the body's pose (world frame)."""
        return rotate_basis(self.part.basis, self.rotation)

    @cached_property
    def _families(self) -> tuple[tuple[ElementSet, int, np.ndarray], ...]:
        """``(elements, factor rank, ECSW weights)`` of the RID tetrahedra and membrane triangles."""
        b, p = self.body, self.part
        pts = p.mesh.points
        out = [(tetrahedra(pts, p.mesh.tets[p.tet_rid], b.material, "large"), 6, p.tet_weights)]
        if len(p.tri_rid):
            if b.membrane is None or p.tri_rid.max() >= len(b.membrane.triangles):
                raise ValueError(f"the reduction's RID has membrane triangles body {b.name!r} does not have")
            tris = np.asarray(b.membrane.triangles, np.int64)[p.tri_rid]
            out.append((membrane_triangles(pts, tris, b.membrane.material, b.membrane.thickness), 3, p.tri_weights))
        return tuple(out)

    def _edge_rows(self, conn: np.ndarray) -> np.ndarray:
        """``(E, 3(k - 1), m)`` edge basis rows ``D Phi_e`` of elements ``conn`` (all modes)."""
        m = self.part.n_modes
        rows = self.part.basis.reshape(-1, 3, m)[conn]  # (E, k, 3, m)
        return (rows[:, 1:] - rows[:, :1]).reshape(len(conn), -1, m)

    @cached_property
    def strain_modes(self) -> np.ndarray:
        """``(m',)`` the modes that move some RID element's edges: the others (the rigid
        translations) have no internal force or stiffness and are left out of the kernels."""
        scale = np.zeros(self.part.n_modes)
        for es, _, _ in self._families:
            if es.n_elements:
                scale = np.maximum(scale, np.abs(self._edge_rows(es.conn)).max(axis=(0, 1)))
        return np.flatnonzero(scale > 1e-12 * scale.max(initial=0.0))

    @cached_property
    def element_factors(self) -> tuple[ElementFactors, ...]:
        """RID tetrahedra and membrane triangles, from the part's rest mesh (part frame)."""
        modes = self.strain_modes
        return tuple(ElementFactors.of(es, rank, w, self._edge_rows(es.conn)[:, :, modes])
                     for es, rank, w in self._families)

    @cached_property
    def reduced_mass(self) -> np.ndarray:
        """``(m, m)`` ``Phi^T M Phi`` (constant; the same in the part frame), kg."""
        Phi = self.part.basis
        return Phi.T @ (np.repeat(self.body.nodal_mass, 3)[:, None] * Phi)


def reduce_body(body: Body, part: PartReduction, rotation: np.ndarray) -> ReducedBody:
    """Place a part reduction on a body posed by ``rotation`` (``(3, 3)``, part frame -> world)."""
    return ReducedBody(body, part, np.asarray(rotation, float))
