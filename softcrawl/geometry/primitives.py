"""Mesh building blocks: a structured box in pure numpy, and the gmsh/OpenCASCADE
meshing and tagging helpers shared by the PneuNet, disk and shell builders.

Units are mm.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import fields
from itertools import permutations

import gmsh
import numpy as np

from softcrawl.geometry.mesh import MeshError, TetMesh, boundary_triangles, tet_signed_volumes

#: Relative tolerance (times the mesh's bounding-box size) for "node lies on a plane/point".
GEOM_RTOL = 1e-6


#: Bounds of a part's lengths (every dimension of a disk or a PneuNet but its mesh size), mm,
#: both included: a tenth of a millimetre (a printer's resolution) to a metre.
LENGTH_BOUNDS_MM = (0.1, 1000.0)
#: Bounds of a part's mesh size (the largest tetrahedron edge), mm, both included. At 1 mm the
#: paper's disk already has 701,709 tetrahedra. Far below, gmsh's node count of an edge,
#: ``(int)(a + 1.99)`` with ``a`` about length / size (``meshGEdge.cpp``, ``meshGEdgeProcessing``),
#: overflows a C int and the edge falls back to gmsh's minimum of segments: a coarse mesh without
#: an error (1e-9 mm gave the disk 37 nodes, 25 mm gives it 127).
MESH_SIZE_BOUNDS_MM = (1.0, 100.0)
#: Most mesh cells of a part: its bounding box's volume over the mesh size cubed. gmsh makes about
#: 3.3 tetrahedra of a cell (the paper's disk at 1 mm: 213,858 cells, 701,709 tetrahedra).
MAX_MESH_CELLS = 500_000


def check_part_fields(params: object, int_bounds: dict[str, tuple[int, int]] | None = None) -> None:
    """Canonicalise a frozen dataclass of part sizes in place and check every field's bounds:
    ``mesh_size`` within :data:`MESH_SIZE_BOUNDS_MM`, an integer field within its
    ``int_bounds``, every other field (a length, mm) within :data:`LENGTH_BOUNDS_MM`.

    Integer fields become ``int``, all others ``float``, so equal parameter sets serialise (and
    hash, for the mesh cache) identically.

    Args:
        params: the dataclass (``DiskParams``, ``PneuNetParams``).
        int_bounds: ``field name -> (low, high)`` of its integer fields, both included.

    Raises:
        TypeError: if an integer field's value is not an integer.
        ValueError: one line naming the field, its bounds and the value, for a value out of
            them (NaN and infinities too).
    """
    int_bounds = int_bounds or {}
    for f in fields(params):
        value = getattr(params, f.name)
        if f.name in int_bounds:
            canonical, (lo, hi), unit = operator.index(value), int_bounds[f.name], ""
        else:
            canonical = float(value)
            (lo, hi), unit = MESH_SIZE_BOUNDS_MM if f.name == "mesh_size" else LENGTH_BOUNDS_MM, " mm"
        if not lo <= canonical <= hi:
            raise ValueError(f"{f.name} must lie in [{lo:g}, {hi:g}]{unit}, got {canonical:g}")
        object.__setattr__(params, f.name, canonical)


def check_mesh_cells(extent: Sequence[float], mesh_size: float) -> None:
    """Refuse a mesh size too fine for a part: more than :data:`MAX_MESH_CELLS` cells.

    Args:
        extent: ``(3,)`` the part's bounding box, mm.
        mesh_size: the mesh size, mm.

    Raises:
        ValueError: one line with the cell count and the smallest mesh size the part takes.
    """
    volume = float(np.prod(extent))
    cells = volume / mesh_size**3
    if cells > MAX_MESH_CELLS:
        finest = (volume / MAX_MESH_CELLS) ** (1 / 3)
        raise ValueError(f"mesh_size {mesh_size:g} mm is too fine for a part of {' x '.join(f'{v:g}' for v in extent)} "
                         f"mm: {cells:.3g} cells (bounding box / mesh_size^3), more than {MAX_MESH_CELLS}; give a "
                         f"mesh_size of at least {math.ceil(finest * 100) / 100:g} mm")


def orient_tets(points: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Tetrahedra with two nodes swapped wherever the signed volume is negative.

    Args:
        points: ``(n, 3)`` node positions, mm.
        tets: ``(m, 4)`` node indices.

    Returns:
        ``(m, 4)`` int64 node indices, all with non-negative signed volume.
    """
    tets = np.array(tets, dtype=np.int64)
    neg = tet_signed_volumes(points, tets) < 0
    tets[neg] = tets[neg][:, [0, 1, 3, 2]]
    return tets


def geom_tol(points: np.ndarray) -> float:
    """Absolute geometric tolerance (mm) for a point cloud: ``GEOM_RTOL`` times its largest extent."""
    return GEOM_RTOL * float(np.ptp(points, axis=0).max())


def nodes_on_plane(points: np.ndarray, axis: int, value: float) -> np.ndarray:
    """``(k,)`` int64 indices of nodes with ``points[:, axis] == value`` (within :func:`geom_tol`)."""
    return np.flatnonzero(np.abs(points[:, axis] - value) <= geom_tol(points)).astype(np.int64)


def nodes_at(points: np.ndarray, targets: Sequence[Sequence[float]]) -> np.ndarray:
    """Indices of the nodes that coincide with given positions, in the order given.

    Args:
        points: ``(n, 3)`` node positions, mm.
        targets: ``(k, 3)`` positions, mm.

    Returns:
        ``(k,)`` int64 node indices.

    Raises:
        MeshError: if some target has no node within :func:`geom_tol`.
    """
    targets = np.asarray(targets, dtype=float).reshape(-1, 3)
    dist = np.linalg.norm(points[None, :, :] - targets[:, None, :], axis=2)
    idx = dist.argmin(axis=1)
    missing = dist[np.arange(len(targets)), idx] > geom_tol(points)
    if missing.any():
        raise MeshError(f"no mesh node at {targets[missing].tolist()}")
    return idx.astype(np.int64)


def boundary_nodes(triangles: np.ndarray) -> np.ndarray:
    """``(k,)`` sorted unique int64 node indices of ``(t, 3)`` triangles."""
    return np.unique(triangles).astype(np.int64)


@contextmanager
def gmsh_model(name: str, options: dict[str, float]) -> Iterator[None]:
    """A fresh, quiet gmsh model with the given numeric options, cleaned up afterwards.

    If gmsh was not initialised, it is initialised here and finalised on exit. If some
    other code already initialised it, a separate model is added and removed on exit and
    the options changed here are restored, so the caller's gmsh state is left as found.
    """
    owner = not gmsh.isInitialized()
    if owner:
        gmsh.initialize(readConfigFiles=False, interruptible=False)
    previous = {} if owner else {key: gmsh.option.getNumber(key) for key in ["General.Terminal", *options]}
    previous_model = None if owner else gmsh.model.getCurrent()
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        for key, value in options.items():
            gmsh.option.setNumber(key, value)
        gmsh.model.add(name)
        yield
    finally:
        if owner:
            gmsh.finalize()
        else:
            gmsh.model.remove()
            gmsh.model.setCurrent(previous_model)
            for key, value in previous.items():
                gmsh.option.setNumber(key, value)


def occ_tet_mesh(name: str, build: Callable[[], None], mesh_size: float) -> tuple[np.ndarray, np.ndarray]:
    """Mesh an OpenCASCADE solid into linear tetrahedra.

    Args:
        name: gmsh model name (diagnostics only).
        build: adds the solid to ``gmsh.model.occ``, synchronises, and may add mesh
            constraints (e.g. embedded points); called inside a fresh gmsh model.
        mesh_size: maximum element size, mm.

    Returns:
        ``points`` ``(n, 3)`` float64 mm and ``tets`` ``(m, 4)`` int64, positively oriented,
        with nodes not used by any tetrahedron dropped.

    Raises:
        MeshError: if gmsh produces no tetrahedra.
        ValueError: if ``mesh_size`` is not positive.
    """
    if not mesh_size > 0:
        raise ValueError(f"mesh_size must be positive, got {mesh_size}")
    options = {"Mesh.MeshSizeMax": mesh_size, "Mesh.MeshSizeMin": 0.0, "General.NumThreads": 1}
    with gmsh_model(name, options):
        build()
        gmsh.model.mesh.generate(3)
        tags, coords, _ = gmsh.model.mesh.getNodes()
        _, conn = gmsh.model.mesh.getElementsByType(4)
    if len(conn) == 0:
        raise MeshError(f"gmsh produced no tetrahedra for {name!r}")
    lookup = np.zeros(int(tags.max()) + 1, dtype=np.int64)
    lookup[tags.astype(np.int64)] = np.arange(len(tags))
    tets = lookup[np.asarray(conn, dtype=np.int64).reshape(-1, 4)]
    used, tets = np.unique(tets, return_inverse=True)
    points = np.asarray(coords, dtype=float).reshape(-1, 3)[used]
    return points, orient_tets(points, tets.reshape(-1, 4))


def box_mesh(
    size: Sequence[float] = (1.0, 1.0, 1.0),
    divisions: Sequence[int] = (1, 1, 1),
    origin: Sequence[float] = (0.0, 0.0, 0.0),
) -> TetMesh:
    """A structured tetrahedral mesh of an axis-aligned box.

    Each of the ``nx * ny * nz`` hexahedra is split into 6 tetrahedra around its main
    diagonal (Kuhn subdivision), so face diagonals of neighbouring cells conform.

    Args:
        size: ``(lx, ly, lz)`` edge lengths, mm.
        divisions: ``(nx, ny, nz)`` cells per axis.
        origin: ``(3,)`` the minimum corner, mm.

    Returns:
        A :class:`TetMesh` with ``(nx+1)(ny+1)(nz+1)`` nodes and ``6 nx ny nz`` tetrahedra;
        surface ``"boundary"`` (outward); node sets ``"x0"``, ``"x1"`` (min/max x),
        ``"z0"`` (min z) and ``"collision"`` (all boundary nodes).

    Raises:
        ValueError: if a size is not positive or a division count is below 1.
    """
    size = np.asarray(size, dtype=float)
    origin = np.asarray(origin, dtype=float)
    div = np.asarray(divisions, dtype=np.int64)
    if size.shape != (3,) or origin.shape != (3,) or div.shape != (3,):
        raise ValueError("size, divisions and origin must each have 3 entries")
    if not (np.all(size > 0) and np.all(div >= 1)):
        raise ValueError(f"need size > 0 and divisions >= 1, got {size.tolist()}, {div.tolist()}")
    axes = [np.linspace(origin[i], origin[i] + size[i], div[i] + 1) for i in range(3)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    node = np.arange(len(points)).reshape(div + 1)
    cell = np.stack(np.meshgrid(*[np.arange(n) for n in div], indexing="ij"), axis=-1).reshape(-1, 3)
    # Kuhn tetrahedra: walk from corner (0,0,0) to (1,1,1) adding one unit step per axis.
    tets = []
    for order in permutations(range(3)):
        corners = [np.zeros(3, dtype=np.int64)]
        for axis in order:
            corners.append(corners[-1] + np.eye(3, dtype=np.int64)[axis])
        tets.append(np.stack([node[tuple((cell + c).T)] for c in corners], axis=1))
    tets = orient_tets(points, np.concatenate(tets))
    boundary = boundary_triangles(tets)
    return TetMesh(
        points,
        tets,
        surfaces={"boundary": boundary},
        node_sets={
            "x0": nodes_on_plane(points, 0, origin[0]),
            "x1": nodes_on_plane(points, 0, origin[0] + size[0]),
            "z0": nodes_on_plane(points, 2, origin[2]),
            "collision": boundary_nodes(boundary),
        },
        params={"size": size.tolist(), "divisions": div.tolist(), "origin": origin.tolist()},
    )
