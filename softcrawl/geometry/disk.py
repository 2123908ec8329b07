"""The robot's central disk: a cone frustum on the z axis, built with OpenCASCADE and
meshed by gmsh. Units are mm."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import partial

import gmsh

from softcrawl.geometry.io import cached_mesh
from softcrawl.geometry.mesh import MeshError, TetMesh, boundary_triangles
from softcrawl.geometry.primitives import boundary_nodes, check_mesh_cells, check_part_fields, nodes_at, occ_tet_mesh


@dataclass(frozen=True)
class DiskParams:
    """Disk dimensions, mm: a frustum from ``z = 0`` (radius ``bottom_radius``) to
    ``z = height`` (radius ``top_radius``), centred on the z axis.

    Raises:
        ValueError: on construction, one line: a length outside
            :data:`~softcrawl.geometry.primitives.LENGTH_BOUNDS_MM`, a mesh size outside
            :data:`~softcrawl.geometry.primitives.MESH_SIZE_BOUNDS_MM`, or one too fine for the
            disk (:func:`~softcrawl.geometry.primitives.check_mesh_cells`).
    """

    bottom_radius: float = 50.0
    top_radius: float = 54.5
    height: float = 18.0
    mesh_size: float = 10.0

    def __post_init__(self) -> None:
        check_part_fields(self)
        diameter = 2 * max(self.bottom_radius, self.top_radius)
        check_mesh_cells((diameter, diameter, self.height), self.mesh_size)


def _build_occ(p: DiskParams) -> None:
    """Add the frustum to the current gmsh model with a mesh node forced at the top centre."""
    occ = gmsh.model.occ
    occ.addCone(0, 0, 0, 0, 0, p.height, p.bottom_radius, p.top_radius)
    centre = occ.addPoint(0, 0, p.height)
    occ.synchronize()
    r, eps = max(p.bottom_radius, p.top_radius) * 1.01, 1e-3 * p.height
    top = gmsh.model.getEntitiesInBoundingBox(-r, -r, p.height - eps, r, r, p.height + eps, dim=2)
    if len(top) != 1:
        raise MeshError(f"expected one top face of the disk, found {len(top)}")
    gmsh.model.mesh.embed(0, [centre], 2, top[0][1])


def _build_mesh(p: DiskParams) -> TetMesh:
    points, tets = occ_tet_mesh("disk", partial(_build_occ, p), p.mesh_size)
    boundary = boundary_triangles(tets)
    return TetMesh(
        points,
        tets,
        surfaces={"boundary": boundary},
        node_sets={"top_centre": nodes_at(points, [(0.0, 0.0, p.height)]), "collision": boundary_nodes(boundary)},
        params=asdict(p),
    )


def disk_mesh(params: DiskParams = DiskParams(), cache: bool = True) -> TetMesh:
    """Tetrahedral mesh of the central disk.

    Args:
        params: dimensions and mesh size, mm.
        cache: reuse / store the mesh in the on-disk cache (:func:`softcrawl.geometry.io.cached_mesh`).

    Returns:
        A :class:`TetMesh` (points mm) with surface ``"boundary"`` (outward) and node sets
        ``"top_centre"`` (the single node at ``(0, 0, height)``) and ``"collision"`` (all
        boundary nodes); ``params`` = ``asdict(params)``.

    Raises:
        MeshError: if the geometry or the mesh is malformed.
    """
    build = partial(_build_mesh, params)
    return cached_mesh("disk", asdict(params), build) if cache else build()
