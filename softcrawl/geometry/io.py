"""Reading and writing tagged meshes, and the on-disk mesh cache.

File format: a mesh ``name.vtu`` (VTK XML, binary, readable by ParaView) plus a sidecar
``name.json``. The ``.vtu`` holds the points (float64, exact), the tetrahedra, one
triangle block per surface with cell data ``"surface"`` (1-based surface id; 0 on
tetrahedra) and, per node set, point data ``"node_set:<name>"`` holding each member's
1-based position in the set (0 elsewhere), so the set order round-trips. The ``.json``
holds the format version, surface and node-set names, the mesh ``params`` and the
SHA-256 of the ``.vtu`` bytes, so a ``.vtu`` that does not belong to its sidecar is
rejected.
"""

from __future__ import annotations

import hashlib
import json
import os
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path

import meshio
import numpy as np

from softcrawl.geometry.mesh import MeshError, TetMesh

#: Bump when the file layout or any mesh builder changes, so cached meshes are rebuilt.
GEOMETRY_FORMAT_VERSION = 1


def _sidecar(path: Path) -> Path:
    return path.with_suffix(".json")


def replace_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write`` on a temporary file next to ``path``, then move it onto ``path``."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}-", suffix=path.suffix)
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_mesh(mesh: TetMesh, path: str | os.PathLike) -> None:
    """Write a mesh to ``path`` (``.vtu``) and its sidecar (same name, ``.json``).

    Each file is written to a temporary file and moved into place (atomic per file).

    Args:
        mesh: the mesh; its ``params`` must be JSON-serialisable.
        path: destination, must end in ``.vtu``; its directory must exist.

    Raises:
        ValueError: if ``path`` does not end in ``.vtu``.
        MeshError: if a node set contains a node twice (its order could not be stored).
        TypeError: if ``mesh.params`` is not JSON-serialisable.
        OSError: on file-system errors.
    """
    path = Path(path)
    if path.suffix != ".vtu":
        raise ValueError(f"mesh path must end in .vtu, got {path}")
    surfaces = sorted(mesh.surfaces)
    node_sets = sorted(mesh.node_sets)
    point_data = {}
    for name in node_sets:
        members = mesh.node_sets[name]
        if len(np.unique(members)) != len(members):
            raise MeshError(f"node set {name!r} has repeated nodes")
        rank = np.zeros(mesh.n_nodes, dtype=np.int64)
        rank[members] = np.arange(1, len(members) + 1)
        point_data[f"node_set:{name}"] = rank
    blocks = [(i + 1, mesh.surfaces[name]) for i, name in enumerate(surfaces) if len(mesh.surfaces[name])]
    vtu = meshio.Mesh(
        mesh.points,
        [("tetra", mesh.tets)] + [("triangle", tris) for _, tris in blocks],
        point_data=point_data,
        cell_data={"surface": [np.zeros(mesh.n_tets, np.int64)] + [np.full(len(t), i, np.int64) for i, t in blocks]},
    )
    meta = {
        "format": GEOMETRY_FORMAT_VERSION,
        "surfaces": surfaces,
        "node_sets": node_sets,
        "params": mesh.params,
    }
    json.dumps(meta)  # fail (TypeError) before writing anything
    replace_atomically(path, lambda tmp: meshio.write(tmp, vtu, file_format="vtu"))
    meta["vtu_sha256"] = hashlib.sha256(path.read_bytes()).hexdigest()
    replace_atomically(_sidecar(path), lambda tmp: tmp.write_text(json.dumps(meta, indent=1)))


def read_mesh(path: str | os.PathLike) -> TetMesh:
    """Read a mesh written by :func:`write_mesh`; the round trip is exact.

    Args:
        path: the ``.vtu`` file; its ``.json`` sidecar must sit next to it.

    Returns:
        The :class:`TetMesh`, with points, tetrahedra, triangle orientation, node-set
        order and ``params`` as written.

    Raises:
        FileNotFoundError: if either file is missing.
        MeshError: if the files do not match each other or their content is malformed.
        ValueError: if the sidecar is not valid JSON.
    """
    path = Path(path)
    meta = json.loads(_sidecar(path).read_text())
    data = path.read_bytes()
    if meta.get("format") != GEOMETRY_FORMAT_VERSION:
        raise MeshError(f"{path}: format {meta.get('format')!r}, expected {GEOMETRY_FORMAT_VERSION}")
    if hashlib.sha256(data).hexdigest() != meta.get("vtu_sha256"):
        raise MeshError(f"{path} does not match the checksum in its sidecar {_sidecar(path).name}")
    vtu = meshio.read(path, file_format="vtu")
    tets = np.concatenate([b.data for b in vtu.cells if b.type == "tetra"])
    tris = [b.data for b in vtu.cells if b.type == "triangle"]
    tris = np.concatenate(tris) if tris else np.zeros((0, 3), np.int64)
    ids = np.concatenate([d for b, d in zip(vtu.cells, vtu.cell_data["surface"]) if b.type == "triangle"] or [[]])
    surfaces = {name: tris[ids == i + 1] for i, name in enumerate(meta["surfaces"])}
    node_sets = {}
    for name in meta["node_sets"]:
        rank = np.asarray(vtu.point_data[f"node_set:{name}"])
        members = np.flatnonzero(rank)
        node_sets[name] = members[np.argsort(rank[members])]
    return TetMesh(vtu.points, tets, surfaces, node_sets, meta["params"])


def cache_dir() -> Path:
    """The mesh cache directory: ``$SOFTCRAWL_CACHE_DIR`` or ``~/.cache/softcrawl/meshes``."""
    return Path(os.environ.get("SOFTCRAWL_CACHE_DIR") or Path.home() / ".cache" / "softcrawl" / "meshes")


def cache_key(kind: str, params: dict) -> str:
    """SHA-256 hex digest of ``kind``, the sorted-JSON ``params`` and the format version."""
    blob = json.dumps({"kind": kind, "params": params, "format": GEOMETRY_FORMAT_VERSION}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()


def cached_mesh(kind: str, params: dict, build: Callable[[], TetMesh]) -> TetMesh:
    """Load a mesh from the disk cache, or build and store it.

    A cache entry that cannot be read, fails its checksum, or was built from different
    parameters is rebuilt (with a warning), never trusted. If the cache cannot be written
    the built mesh is still returned (with a warning).

    Args:
        kind: mesh family, e.g. ``"pneunet"``.
        params: JSON-serialisable parameters that fully determine the mesh.
        build: builds the mesh on a cache miss.

    Returns:
        The cached or freshly built :class:`TetMesh`.
    """
    path = cache_dir() / f"{kind}-{cache_key(kind, params)}.vtu"
    if path.exists():
        try:
            mesh = read_mesh(path)
            if json.dumps(mesh.params, sort_keys=True) == json.dumps(params, sort_keys=True):
                return mesh
            warnings.warn(f"mesh cache entry {path} has other parameters; rebuilding", stacklevel=2)
        except Exception as exc:  # any unreadable entry is rebuilt
            warnings.warn(f"corrupt mesh cache entry {path} ({exc!r}); rebuilding", stacklevel=2)
    mesh = build()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        write_mesh(mesh, path)
    except OSError as exc:
        warnings.warn(f"could not write mesh cache entry {path}: {exc}", stacklevel=2)
    return mesh
