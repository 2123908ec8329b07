"""Reduction files: one self-describing, versioned, checksummed ``.npz``.

A file holds the parts of a :class:`~softcrawl.reduction.model.RobotReduction` (the leg and,
optionally, the disk). Arrays, prefixed ``<part>__``: the part mesh (points, tets, surfaces,
node sets), the basis, singular values, the RIDs and weights. Key ``metadata`` holds UTF-8
JSON: format version, software version, per part its mesh hash and sizes, the model
parameters the reduction is valid for, tolerances and build statistics, a SHA-256 over
every array (``checksum``) and one over the metadata itself and that array checksum
(``metadata_checksum``), so ``valid_for``, tolerances and ``n_rigid`` cannot be altered
unnoticed either. :func:`load_reduction` rejects a file that is unreadable, of another format or
version, altered (either checksum), inconsistent (``n_rigid`` against the basis), or whose mesh
or parameters do not match. Files written before ``metadata_checksum`` existed are accepted only
if their metadata is one of :data:`_TRUSTED_LEGACY_METADATA` (the shipped reduction).
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np

from softcrawl import __version__
from softcrawl.geometry.io import replace_atomically
from softcrawl.geometry.mesh import TetMesh
from softcrawl.reduction.model import PartReduction, RobotReduction

FORMAT = "softcrawl-reduction"
#: 2: named parts (leg, disk); 1 (leg only) files are refused with a request to rebuild.
FORMAT_VERSION = 2
#: RobotConfig fields every reduction depends on (its leg part); loading under other values is refused.
MATCHED_FIELDS = ("leg_mesh_size", "leg_mass", "mass_lumping", "tilt_deg", "rayleigh_mass", "rayleigh_stiffness")
#: Further fields a reduction with a disk part depends on.
DISK_MATCHED_FIELDS = ("disk_mesh_size", "disk_mass")


class ReductionFileError(ValueError):
    """A reduction file is missing, unreadable, corrupt or of another format."""


class ReductionMismatchError(ValueError):
    """A reduction does not match the mesh or the model parameters in use."""


def mesh_hash(mesh: TetMesh) -> str:
    """SHA-256 of a mesh's points (rounded to 1e-9 mm) and connectivity."""
    h = hashlib.sha256()
    h.update(np.round(mesh.points, 9).astype("<f8").tobytes())
    h.update(mesh.tets.astype("<i8").tobytes())
    return h.hexdigest()


def _arrays(part: PartReduction, prefix: str) -> dict[str, np.ndarray]:
    m = part.mesh
    out = {"mesh_points": m.points, "mesh_tets": m.tets, "basis": part.basis,
           "singular_values": part.singular_values, "tet_rid": part.tet_rid, "tet_weights": part.tet_weights,
           "tri_rid": part.tri_rid, "tri_weights": part.tri_weights, "n_rigid": np.array(part.n_rigid)}
    out.update({f"surface__{k}": v for k, v in m.surfaces.items()})
    out.update({f"nodeset__{k}": v for k, v in m.node_sets.items()})
    return {f"{prefix}__{k}": v for k, v in out.items()}


def _part(data: dict[str, np.ndarray], prefix: str, meta: dict) -> PartReduction:
    d = {k[len(prefix) + 2:]: v for k, v in data.items() if k.startswith(prefix + "__")}
    mesh = TetMesh(d["mesh_points"], d["mesh_tets"], {k[9:]: v for k, v in d.items() if k.startswith("surface__")},
                   {k[9:]: v for k, v in d.items() if k.startswith("nodeset__")}, meta.get("mesh_params", {}))
    return PartReduction(mesh, d["basis"], int(d["n_rigid"]), d["singular_values"], d["tet_rid"],
                         d["tet_weights"], d["tri_rid"], d["tri_weights"], meta.get("build", {}))


def _checksum(arrays: dict[str, np.ndarray]) -> str:
    h = hashlib.sha256()
    for k in sorted(arrays):
        a = np.ascontiguousarray(arrays[k])
        h.update(k.encode())
        h.update(str(a.dtype.str).encode() + str(a.shape).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _metadata_checksum(meta: dict) -> str:
    """SHA-256 of the metadata (all of it but ``metadata_checksum``, canonical JSON; it holds
    the array checksum, so this covers the arrays too)."""
    body = {k: v for k, v in meta.items() if k != "metadata_checksum"}
    return hashlib.sha256(json.dumps(body, sort_keys=True, default=str).encode()).hexdigest()


#: ``_metadata_checksum`` of reduction files written before ``metadata_checksum`` existed that
#: are trusted as they are: the shipped ``softcrawl/reduction/data/pneunet_6mm.npz``.
_TRUSTED_LEGACY_METADATA = frozenset({
    "dcbc9d43f1802c38709b645923eb48ef051b7eca66c62432a40d23020f6b45b5",  # pneunet_6mm.npz, the shipped reduction
})


def save_reduction(path: str | os.PathLike, reduction: RobotReduction, valid_for: dict) -> Path:
    """Write ``reduction`` atomically to ``path`` (``.npz``).

    Args:
        path: destination.
        reduction: the reduced parts.
        valid_for: model parameters it is valid for (at least :data:`MATCHED_FIELDS`, and
            :data:`DISK_MATCHED_FIELDS` with a disk part).
    """
    path = Path(path)
    arrays, parts = {}, {}
    for name, part in reduction.parts.items():
        arrays.update(_arrays(part, name))
        parts[name] = {"mesh_hash": mesh_hash(part.mesh), "mesh_params": part.mesh.params, "n_modes": part.n_modes,
                       "n_rigid": part.n_rigid, "rid_tetrahedra": len(part.tet_rid),
                       "rid_triangles": len(part.tri_rid), "build": part.metadata}
    meta = {"format": FORMAT, "format_version": FORMAT_VERSION, "software_version": __version__,
            "parts": parts, "valid_for": valid_for, "build": reduction.metadata, "checksum": _checksum(arrays)}
    meta = json.loads(json.dumps(meta, default=str))  # what load_reduction will read back
    meta["metadata_checksum"] = _metadata_checksum(meta)
    blob = np.frombuffer(json.dumps(meta, indent=1, default=str).encode(), np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    replace_atomically(path, lambda tmp: np.savez_compressed(tmp, metadata=blob, **arrays))
    return path


def load_reduction(path: str | os.PathLike, expect: dict | None = None,
                   check: bool = True) -> tuple[RobotReduction, dict]:
    """Read a reduction file and check it.

    Args:
        path: the ``.npz``.
        expect: model parameters in use (e.g. ``dataclasses.asdict(RobotConfig(...))``); each
            of :data:`MATCHED_FIELDS` (and :data:`DISK_MATCHED_FIELDS` if the file has a disk
            part) present here must equal the file's ``valid_for`` value.
        check: verify format, version, checksum and mesh hashes.

    Returns:
        ``(reduction, metadata)``.

    Raises:
        ReductionFileError: missing, unreadable, other format/version, checksum mismatch.
        ReductionMismatchError: a parameter in ``expect`` differs from the file's.
    """
    path = Path(path)
    if path.is_dir():
        raise ReductionFileError(f"reduction file {path} is a directory; give the .npz file")
    if not path.is_file():
        raise ReductionFileError(f"reduction file {path} does not exist (build one with `softcrawl reduce build`)")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
        meta = json.loads(data.pop("metadata").tobytes().decode())
    except Exception as exc:  # zip, npy and JSON errors all mean "not a readable reduction"
        raise ReductionFileError(f"cannot read reduction file {path}: {exc}") from exc
    if not isinstance(meta, dict) or not isinstance(meta.get("parts", {}), dict) \
            or not isinstance(meta.get("valid_for", {}), dict):
        raise ReductionFileError(f"reduction file {path}: its metadata is not a JSON object with 'parts' and "
                                 "'valid_for' objects")
    if check:
        if meta.get("format") != FORMAT or meta.get("format_version") != FORMAT_VERSION:
            raise ReductionFileError(f"{path} is not a {FORMAT} file of version {FORMAT_VERSION} "
                                     f"(found {meta.get('format')!r} version {meta.get('format_version')!r}); "
                                     "rebuild it with `softcrawl reduce build`")
        if _checksum(data) != meta.get("checksum"):
            raise ReductionFileError(f"reduction file {path} is corrupt: its arrays do not match their checksum")
        if "metadata_checksum" in meta:
            if meta["metadata_checksum"] != _metadata_checksum(meta):
                raise ReductionFileError(f"reduction file {path} is corrupt: its metadata (valid_for, tolerances, "
                                         "n_rigid) does not match its checksum")
        elif _metadata_checksum(meta) not in _TRUSTED_LEGACY_METADATA:
            raise ReductionFileError(f"reduction file {path} has no metadata checksum (an older softcrawl wrote "
                                     "it); rebuild it with `softcrawl reduce build`")
    parts_meta = meta.get("parts", {})
    try:
        parts = {name: _part(data, name, parts_meta[name]) for name in parts_meta}
        for name, part in parts.items():
            recorded = parts_meta[name].get("n_rigid", part.n_rigid)
            if not 0 <= part.n_rigid <= part.basis.shape[1] or recorded != part.n_rigid:
                raise ValueError(f"{name}: n_rigid {part.n_rigid} (metadata {recorded!r}) does not fit a basis of "
                                 f"{part.basis.shape[1]} modes")
        reduction = RobotReduction(parts["leg"], parts.get("disk"), meta.get("build", {}))
    except (KeyError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise ReductionFileError(f"reduction file {path} is incomplete or inconsistent: {exc}") from exc
    if check:
        for name, part in parts.items():
            if mesh_hash(part.mesh) != parts_meta[name].get("mesh_hash"):
                raise ReductionFileError(f"reduction file {path}: the {name} mesh does not match its recorded hash")
    if expect:
        valid = meta.get("valid_for", {})
        fields = MATCHED_FIELDS + (DISK_MATCHED_FIELDS if reduction.disk is not None else ())
        diff = [f"{k}: {valid.get(k)!r} in the reduction, {expect[k]!r} in use"
                for k in fields if k in expect and valid.get(k) != expect[k]]
        if diff:
            raise ReductionMismatchError(f"reduction {path} does not match the model ({'; '.join(diff)}); "
                                         "rebuild it with `softcrawl reduce build` or use --model full")
    return reduction, meta
