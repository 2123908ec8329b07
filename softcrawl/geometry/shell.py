"""One octant of a thick hollow sphere, for checking the FEM against Lamé's solution
for an internally pressurised sphere. Units are mm."""

from __future__ import annotations

import math

import gmsh
import numpy as np

from softcrawl.geometry.mesh import TetMesh, boundary_triangles
from softcrawl.geometry.primitives import geom_tol, nodes_on_plane, occ_tet_mesh


def _build_occ(inner_radius: float, outer_radius: float) -> None:
    occ = gmsh.model.occ
    octant = {"angle1": 0.0, "angle2": math.pi / 2, "angle3": math.pi / 2}  # z >= 0, azimuth 0..90 deg
    outer, inner = (occ.addSphere(0, 0, 0, r, **octant) for r in (outer_radius, inner_radius))
    occ.cut([(3, outer)], [(3, inner)])
    occ.synchronize()


def spherical_shell_octant(inner_radius: float, outer_radius: float, mesh_size: float) -> TetMesh:
    """Tetrahedral mesh of the ``x, y, z >= 0`` octant of a hollow sphere centred at the origin.

    Args:
        inner_radius: cavity radius ``a``, mm.
        outer_radius: outer radius ``b > a``, mm.
        mesh_size: maximum tetrahedron size, mm.

    Returns:
        A :class:`TetMesh` (points mm) with surface ``"cavity"`` (the inner spherical face,
        normals pointing radially outward, into the solid) and node sets ``"sym_x"``,
        ``"sym_y"``, ``"sym_z"`` (nodes on the planes ``x = 0``, ``y = 0``, ``z = 0``).

    Raises:
        ValueError: unless ``0 < inner_radius < outer_radius`` and ``mesh_size > 0``.
    """
    if not 0 < inner_radius < outer_radius:
        raise ValueError(f"need 0 < inner_radius < outer_radius, got {inner_radius}, {outer_radius}")
    points, tets = occ_tet_mesh("shell", lambda: _build_occ(inner_radius, outer_radius), mesh_size)
    tol = geom_tol(points)
    tris = boundary_triangles(tets)
    on_inner = np.all(np.abs(np.linalg.norm(points[tris], axis=2) - inner_radius) <= tol, axis=1)
    on_plane = np.any(np.all(np.abs(points[tris]) <= tol, axis=1), axis=1)  # all 3 nodes on one sym plane
    return TetMesh(
        points,
        tets,
        surfaces={"cavity": tris[on_inner & ~on_plane][:, [0, 2, 1]]},  # flip: into the solid
        node_sets={f"sym_{c}": nodes_on_plane(points, i, 0.0) for i, c in enumerate("xyz")},
        params={"inner_radius": inner_radius, "outer_radius": outer_radius, "mesh_size": mesh_size},
    )
