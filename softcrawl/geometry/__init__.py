"""Geometry: parametric solids (OpenCASCADE via gmsh) meshed into tagged linear
tetrahedra (:class:`TetMesh`), plus mesh file I/O and an on-disk mesh cache. Units: mm."""

from softcrawl.geometry.disk import DiskParams, disk_mesh
from softcrawl.geometry.io import read_mesh, write_mesh
from softcrawl.geometry.mesh import MeshError, TetMesh
from softcrawl.geometry.pneunet import PneuNetParams, pneunet_mesh
from softcrawl.geometry.primitives import box_mesh
from softcrawl.geometry.shell import spherical_shell_octant

__all__ = [
    "DiskParams",
    "MeshError",
    "PneuNetParams",
    "TetMesh",
    "box_mesh",
    "disk_mesh",
    "pneunet_mesh",
    "read_mesh",
    "spherical_shell_octant",
    "write_mesh",
]
