"""A deformable body: static model data of one FEM part (mesh, materials, masses, loads).

Nothing here changes during a simulation; positions and velocities live in
:class:`softcrawl.fem.state.State`, pressures in :class:`softcrawl.fem.state.Control`.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from softcrawl.fem.elements import ElementSet, SparsePattern, membrane_triangles, sparse_pattern, tetrahedra
from softcrawl.fem.kernels import corotational_assemble
from softcrawl.fem.materials import LinearElastic
from softcrawl.fem.pressure import pressure_forces
from softcrawl.geometry.mesh import TetMesh, collision_nodes

MASS_LUMPING = ("uniform", "volume")


@dataclass(frozen=True, eq=False)
class Membrane:
    """Corotational membrane triangles glued on a body's surface (e.g. the paper layer).

    Attributes:
        triangles: ``(k, 3)`` node indices of the body's mesh.
        material: plane-stress law (E kPa, nu).
        thickness: mm.
    """

    triangles: np.ndarray
    material: LinearElastic
    thickness: float = 1.0


@dataclass(frozen=True, eq=False)
class Cavity:
    """A pressurised cavity: oriented triangles (normals into the solid) fed by one channel.

    Attributes:
        triangles: ``(k, 3)`` node indices.
        channel: index into :attr:`softcrawl.fem.state.Control.pressures`.
    """

    triangles: np.ndarray
    channel: int = 0


@dataclass(frozen=True, eq=False)
class Body:
    """One deformable part made of corotational linear tetrahedra.

    Attributes:
        mesh: the rest mesh (mm), in world coordinates.
        material: linear elastic law of the tetrahedra.
        mass: total mass, kg (> 0).
        mass_lumping: ``"uniform"`` (equal mass per node, SOFA's UniformMass, the reference)
            or ``"volume"`` (each tet's mass split equally over its 4 nodes).
        membrane: optional membrane layer (its mass is part of ``mass``).
        cavities: pressurised cavities.
        fixed: ``(n, 3)`` bool mask of Dirichlet-fixed degrees of freedom (held at rest), or None.
        collision_nodes: node indices that can touch the floor (default: the mesh's
            ``"collision"`` node set, else all boundary nodes).
        rotation_method: ``"large"`` (SOFA) or ``"polar"``.
        name: label for reports.

    Raises:
        ValueError: non-positive or non-finite mass, unknown lumping, a wrongly shaped mask.
    """

    mesh: TetMesh
    material: LinearElastic
    mass: float
    mass_lumping: str = "uniform"
    membrane: Membrane | None = None
    cavities: tuple[Cavity, ...] = ()
    fixed: np.ndarray | None = None
    collision_nodes: np.ndarray | None = None
    rotation_method: str = "large"
    name: str = "body"

    def __post_init__(self) -> None:
        if not (np.isfinite(self.mass) and self.mass > 0):
            raise ValueError(f"body {self.name!r}: mass must be positive, got {self.mass!r} kg")
        if self.mass_lumping not in MASS_LUMPING:
            raise ValueError(f"body {self.name!r}: mass_lumping must be one of {MASS_LUMPING}")
        n = self.mesh.n_nodes
        fixed = np.zeros((n, 3), bool) if self.fixed is None else np.asarray(self.fixed, bool)
        if fixed.shape != (n, 3):
            raise ValueError(f"body {self.name!r}: fixed mask must have shape {(n, 3)}, got {fixed.shape}")
        object.__setattr__(self, "fixed", fixed)
        if self.collision_nodes is None:
            object.__setattr__(self, "collision_nodes", collision_nodes(self.mesh))

    @property
    def n_nodes(self) -> int:
        return self.mesh.n_nodes

    @cached_property
    def tetrahedra(self) -> ElementSet:
        return tetrahedra(self.mesh.points, self.mesh.tets, self.material, self.rotation_method)

    @cached_property
    def membranes(self) -> ElementSet | None:
        if self.membrane is None:
            return None
        m = self.membrane
        return membrane_triangles(self.mesh.points, np.asarray(m.triangles, np.int64), m.material, m.thickness)

    @cached_property
    def element_sets(self) -> tuple[ElementSet, ...]:
        return tuple(es for es in (self.tetrahedra, self.membranes) if es is not None)

    @cached_property
    def pattern(self) -> SparsePattern:
        return sparse_pattern(self.n_nodes, list(self.element_sets))

    @cached_property
    def nodal_mass(self) -> np.ndarray:
        """``(n,)`` lumped nodal masses, kg."""
        n = self.n_nodes
        if self.mass_lumping == "uniform":
            return np.full(n, self.mass / n)
        vol = self.tetrahedra.measure
        w = np.bincount(self.mesh.tets.ravel(), weights=np.repeat(vol / 4, 4), minlength=n)
        return self.mass * w / w.sum()

    @cached_property
    def free_dofs(self) -> np.ndarray:
        """``(3n,)`` bool: degrees of freedom not fixed by Dirichlet conditions."""
        return ~self.fixed.ravel()

    @cached_property
    def fixed_entries(self) -> np.ndarray:
        """``(nnz,)`` bool: entries of :attr:`pattern` in a fixed row or column."""
        pat, fixed = self.pattern, ~self.free_dofs
        rows = np.repeat(np.arange(pat.n_dof), np.diff(pat.indptr))
        return fixed[rows] | fixed[pat.indices]

    def internal_forces(self, x: np.ndarray, tangent_coef: float | None = None) -> tuple[np.ndarray, np.ndarray, int]:
        """Corotational elastic forces and optionally the scaled tangent stiffness.

        Args:
            x: ``(n, 3)`` current positions, mm.
            tangent_coef: if given, the tangent ``K_t = sum_e R K_e R^T`` (positive
                semi-definite, mN/mm) times this factor is returned as CSR data of
                :attr:`pattern`.

        Returns:
            ``(f, data, n_bad)``: forces ``(n, 3)`` mN; tangent data ``(nnz,)`` (empty if not
            requested); number of inverted or degenerate elements at ``x``.
        """
        f = np.zeros((self.n_nodes, 3))
        data = np.zeros(self.pattern.nnz if tangent_coef is not None else 0)
        coef = 1.0 if tangent_coef is None else float(tangent_coef)
        n_bad = 0
        for es, dmap in zip(self.element_sets, self.pattern.maps):
            n_bad += corotational_assemble(
                x, es.conn, es.rest, es.stiffness, es.frames, es.method, coef, f, data, dmap
            )
        return f, data, n_bad

    def external_forces(self, x: np.ndarray, pressures: np.ndarray, gravity: np.ndarray) -> np.ndarray:
        """Gravity plus cavity pressure follower loads.

        Args:
            x: ``(n, 3)`` positions, mm.
            pressures: ``(n_channels,)`` gauge pressures, kPa.
            gravity: ``(3,)`` acceleration, mm/s^2.

        Returns:
            ``(n, 3)`` forces, mN.
        """
        f = self.nodal_mass[:, None] * np.asarray(gravity)[None, :]
        for cav in self.cavities:
            p = float(pressures[cav.channel])
            if p != 0.0:
                f += pressure_forces(x, cav.triangles, p)
        return f
