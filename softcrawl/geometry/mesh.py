"""Tagged linear-tetrahedron meshes: the hand-off from geometry to FEM.

Units are mm. Tetrahedra are positively oriented: for a tet (a, b, c, d),
``det[b - a, c - a, d - a] > 0``.

Tags
----
``surfaces``: named triangle sets, ``(k, 3)`` int64 node indices. Conventions:

- ``"cavity"``: the inner surface of the pneumatic cavity, oriented so that the
  normal ``(x1 - x0) x (x2 - x0)`` points *out of the air and into the solid*.
  With that orientation the divergence theorem gives the enclosed air volume
  ``V = sum((x0 . (x1 x x2)) / 6) > 0`` and the pressure load on the wall is
  ``+p * area * n`` (see :mod:`softcrawl.fem.pressure`).
- ``"paper"``: the bottom (strain-limiting) face of a PneuNet, outward normal (-z).
- ``"boundary"``: the outer boundary surface, outward normals.

``node_sets``: named node index arrays, ``(k,)`` int64. Conventions:

- ``"collision"``: nodes that may touch the floor.
- ``"attachment"``: for a PneuNet, the 4 inner-end corners in the order
  ``(-52,-10,4), (-52,10,4), (-52,-10,20), (-52,10,20)`` (reference dimensions).
- ``"top_centre"``: for the disk, the single node at the centre of its top face.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


class MeshError(ValueError):
    """A mesh is malformed (bad shapes, out-of-range indices, inverted or degenerate tetrahedra)."""


def tet_signed_volumes(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed volumes (mm^3) of tetrahedra.

    Args:
        points: ``(n, 3)`` node positions, mm.
        tets: ``(m, 4)`` node indices.

    Returns:
        ``(m,)`` signed volumes ``det[b-a, c-a, d-a] / 6``; positive for positive orientation.
    """
    p = points[tets]
    e = p[:, 1:, :] - p[:, :1, :]
    return np.linalg.det(e.transpose(0, 2, 1)) / 6.0


@dataclass(frozen=True, eq=False)
class TetMesh:
    """A linear tetrahedral mesh with named surface and node tags.

    Attributes:
        points: ``(n, 3)`` float64 node positions, mm.
        tets: ``(m, 4)`` int64 node indices, positively oriented.
        surfaces: name -> ``(k, 3)`` int64 triangle node indices (see module docstring).
        node_sets: name -> ``(k,)`` int64 node indices (see module docstring).
        params: the parameters the mesh was built from (for caching and provenance).

    Raises:
        MeshError: on construction, if shapes are wrong, indices are out of range,
            or any tetrahedron is inverted or degenerate.
    """

    points: np.ndarray
    tets: np.ndarray
    surfaces: dict[str, np.ndarray] = field(default_factory=dict)
    node_sets: dict[str, np.ndarray] = field(default_factory=dict)
    params: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        pts = np.ascontiguousarray(self.points, dtype=np.float64)
        tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise MeshError(f"points must have shape (n, 3), got {pts.shape}")
        if tets.ndim != 2 or tets.shape[1] != 4 or len(tets) == 0:
            raise MeshError(f"tets must have shape (m, 4) with m > 0, got {tets.shape}")
        if not np.all(np.isfinite(pts)):
            raise MeshError("points contain NaN or inf")
        n = len(pts)
        if tets.min() < 0 or tets.max() >= n:
            raise MeshError(f"tet node indices out of range [0, {n})")
        vol = tet_signed_volumes(pts, tets)
        scale = np.ptp(pts, axis=0).max() ** 3
        bad = np.flatnonzero(vol <= 1e-12 * scale)
        if len(bad):
            raise MeshError(
                f"{len(bad)} inverted or degenerate tetrahedra (first: element {bad[0]}, "
                f"signed volume {vol[bad[0]]:.3g} mm^3)"
            )
        surfaces = {k: np.ascontiguousarray(v, dtype=np.int64).reshape(-1, 3) for k, v in self.surfaces.items()}
        node_sets = {k: np.ascontiguousarray(v, dtype=np.int64).reshape(-1) for k, v in self.node_sets.items()}
        for name, arr in [*surfaces.items(), *node_sets.items()]:
            if arr.size and (arr.min() < 0 or arr.max() >= n):
                raise MeshError(f"tag {name!r} has node indices out of range [0, {n})")
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "tets", tets)
        object.__setattr__(self, "surfaces", surfaces)
        object.__setattr__(self, "node_sets", node_sets)

    @property
    def n_nodes(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    def volumes(self) -> np.ndarray:
        """``(m,)`` tetrahedron volumes, mm^3."""
        return tet_signed_volumes(self.points, self.tets)

    def volume(self) -> float:
        """Total solid volume, mm^3."""
        return float(self.volumes().sum())

    def transformed(self, rotation: np.ndarray, translation: np.ndarray) -> "TetMesh":
        """A copy with points mapped to ``rotation @ p + translation`` (tags kept).

        Args:
            rotation: ``(3, 3)`` proper rotation matrix.
            translation: ``(3,)`` mm.
        """
        pts = self.points @ np.asarray(rotation, float).T + np.asarray(translation, float)
        return TetMesh(pts, self.tets, self.surfaces, self.node_sets, dict(self.params))


def boundary_triangles(tets: np.ndarray) -> np.ndarray:
    """Outward-oriented boundary faces of a tetrahedral mesh.

    Args:
        tets: ``(m, 4)`` positively oriented tetrahedra.

    Returns:
        ``(k, 3)`` triangles that belong to exactly one tetrahedron, with normals pointing out.
    """
    # Faces opposite each vertex, ordered so their normal points away from that vertex
    # for a positively oriented tet.
    faces = np.concatenate(
        [tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]], axis=0
    )
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


def collision_nodes(mesh: TetMesh) -> np.ndarray:
    """``(c,)`` the nodes of ``mesh`` that can touch the floor: its ``"collision"`` node set if it
    has one, else every boundary node (the default of a body's collision nodes)."""
    coll = mesh.node_sets.get("collision")
    if coll is None:
        coll = np.unique(boundary_triangles(mesh.tets))
    return np.asarray(coll, np.int64)


def spaced_nodes(points: np.ndarray, nodes: np.ndarray, spacing: float) -> np.ndarray:
    """A subset of ``nodes`` no two of which are closer than ``spacing`` and with every node of
    ``nodes`` within ``spacing`` of one of them: greedy farthest-point sampling from the node
    farthest from their centroid (so corners and edges come first), deterministic.

    A coarse set of contact points on a surface, in the spirit of the paper's simplified
    collision surface (physics.md, "Geometry": base and a 104 x 20 x 16 block).

    Args:
        points: ``(n, 3)`` node positions, mm.
        nodes: ``(c,)`` candidate node indices (e.g. the surface nodes).
        spacing: minimum distance between chosen nodes, mm (``<= 0``: all of ``nodes``).

    Returns:
        ``(k,)`` the chosen node indices, sorted.

    Raises:
        ValueError: ``spacing`` is not finite.
    """
    nodes = np.asarray(nodes, np.int64)
    if not np.isfinite(spacing):
        raise ValueError(f"spacing must be finite, got {spacing!r}")
    if spacing <= 0 or len(nodes) == 0:
        return np.sort(nodes)
    p = np.asarray(points, float)[nodes]
    dist = np.linalg.norm(p - p.mean(axis=0), axis=1)
    chosen = [int(np.argmax(dist))]
    dist = np.linalg.norm(p - p[chosen[0]], axis=1)
    while True:
        far = int(np.argmax(dist))
        if dist[far] < spacing:
            break
        chosen.append(far)
        dist = np.minimum(dist, np.linalg.norm(p - p[far], axis=1))
    return np.sort(nodes[chosen])
