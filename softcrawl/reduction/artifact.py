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

The build records the part each reduced body was built for (``metadata["build"]["part"]``: the
PneuNet's or disk's dimensions and mesh size, its material, and the leg's paper layer;
:meth:`softcrawl.design.spacefile.DesignSpace.part_record`). Given the part in use,
:func:`load_reduction` refuses a reduction of another part; files written before the record
existed were built for the paper's materials (:data:`PAPER_MATERIALS`; their dimensions are
their mesh's). Given a space's ``reduction_sha256``, it refuses a file with another SHA-256.
"""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from softcrawl.safeio import read_bytes

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
    """A reduction does not match the mesh, the part or the model parameters in use, or not
    the checksum its design space expects."""


#: Per part, what a reduction file without a part record was built for besides its mesh's
#: dimensions: the paper's materials and paper layer (the only ones softcrawl could build for
#: then; ``paper.toml``, checked against it by the tests).
PAPER_MATERIALS = {
    "leg": {"material": {"name": "dragonskin30", "youngs_modulus_kpa": None, "poisson_ratio": None,
                         "density_kg_per_m3": None},
            "paper_material": {"name": "paper", "youngs_modulus_kpa": None, "poisson_ratio": None,
                               "density_kg_per_m3": None},
            "paper_thickness": 1.0},
    "disk": {"material": {"name": "printed_polymer", "youngs_modulus_kpa": None, "poisson_ratio": None,
                          "density_kg_per_m3": None}},
}
#: How the parts are named in messages.
_PART_NAMES = {"leg": "PneuNet", "disk": "disk"}


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


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 (64 lower-case hex digits) of a file's bytes (a space's ``reduction_sha256``).

    Raises:
        ValueError: not a regular file or too large (:func:`softcrawl.safeio.read_bytes`).
    """
    return hashlib.sha256(read_bytes(Path(path))).hexdigest()


def part_record(meta: dict, name: str) -> dict:
    """The part a reduction file's ``name`` part (``"leg"``, ``"disk"``) was built for: its
    recorded ``metadata["build"]["part"][name]``, or for a file without one its mesh's
    dimensions (``params``) and :data:`PAPER_MATERIALS`."""
    recorded = (meta.get("build") or {}).get("part") or {}
    if name in recorded:
        return recorded[name]
    return {"params": dict(meta["parts"][name].get("mesh_params", {})), **PAPER_MATERIALS.get(name, {})}


def check_part(path: str | os.PathLike, meta: dict, part: dict) -> None:
    """Refuse a reduction whose parts were built for another part than ``part``.

    Args:
        path: the file (for the message).
        meta: its metadata (:func:`load_reduction`).
        part: the parts in use, ``{"leg": {...}, "disk": {...}}`` as
            :meth:`softcrawl.design.spacefile.DesignSpace.part_record` gives; each part the
            file has is compared, key by key (``params`` dimension by dimension).

    Raises:
        ReductionMismatchError: one line naming every differing value, the file's and the one in use.
    """
    for name in meta.get("parts", {}):
        if name not in part:
            continue
        have, want = part_record(meta, name), part[name]
        pairs = [(k, have.get("params", {}).get(k), v) for k, v in want.get("params", {}).items()]
        pairs += [(k, have.get(k), v) for k, v in want.items() if k != "params"]
        diff = [f"{k}: {_show(a)} != {_show(b)}" for k, a, b in sorted(pairs) if a != b]
        if diff:
            raise ReductionMismatchError(f"reduction {path} was built for another {_PART_NAMES.get(name, name)} "
                                         f"than the one in use (the reduction's != in use: {', '.join(diff)}); "
                                         "build one for this part with `softcrawl reduce build --space` or use "
                                         "--model full")


def _show(value) -> str:
    """A record value in a message: a material by its name when it has one."""
    if isinstance(value, dict) and value.get("name"):
        return str(value["name"])
    return json.dumps(value) if isinstance(value, dict) else str(value)


def load_reduction(path: str | os.PathLike, expect: dict | None = None, check: bool = True,
                   part: dict | None = None, sha256: str | None = None) -> tuple[RobotReduction, dict]:
    """Read a reduction file and check it.

    Args:
        path: the ``.npz``.
        expect: model parameters in use (e.g. ``dataclasses.asdict(RobotConfig(...))``); each
            of :data:`MATCHED_FIELDS` (and :data:`DISK_MATCHED_FIELDS` if the file has a disk
            part) present here must equal the file's ``valid_for`` value.
        check: verify format, version, checksum and mesh hashes.
        part: the parts in use (:meth:`softcrawl.design.spacefile.DesignSpace.part_record`;
            None: not checked): the file's parts must have been built for them (:func:`check_part`).
        sha256: the SHA-256 the file must have (a space's ``reduction_sha256``; None: not checked).

    Returns:
        ``(reduction, metadata)``.

    Raises:
        ReductionFileError: missing, unreadable, other format/version, checksum mismatch.
        ReductionMismatchError: another SHA-256 than ``sha256``, a parameter in ``expect``
            that differs from the file's, or parts built for another part than ``part``.
    """
    path = Path(path)
    if path.is_dir():
        raise ReductionFileError(f"reduction file {path} is a directory; give the .npz file")
    if not path.is_file():
        raise ReductionFileError(f"reduction file {path} does not exist (build one with `softcrawl reduce build`)")
    if sha256 is not None:
        try:
            actual = file_sha256(path)
        except ValueError as exc:
            raise ReductionFileError(f"cannot read reduction file {path}: {exc}") from None
        if actual != sha256.lower():
            raise ReductionMismatchError(f"reduction {path} has SHA-256 {actual}, but its design space expects "
                                         f"{sha256.lower()} ([actuator] reduction_sha256)")
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
        for name, reduced in parts.items():
            recorded = parts_meta[name].get("n_rigid", reduced.n_rigid)
            if not 0 <= reduced.n_rigid <= reduced.basis.shape[1] or recorded != reduced.n_rigid:
                raise ValueError(f"{name}: n_rigid {reduced.n_rigid} (metadata {recorded!r}) does not fit a basis of "
                                 f"{reduced.basis.shape[1]} modes")
        reduction = RobotReduction(parts["leg"], parts.get("disk"), meta.get("build", {}))
    except (KeyError, ValueError, TypeError, AttributeError, IndexError) as exc:
        raise ReductionFileError(f"reduction file {path} is incomplete or inconsistent: {exc}") from exc
    if check:
        for name, reduced in parts.items():
            if mesh_hash(reduced.mesh) != parts_meta[name].get("mesh_hash"):
                raise ReductionFileError(f"reduction file {path}: the {name} mesh does not match its recorded hash")
    if expect:
        valid = meta.get("valid_for", {})
        fields = MATCHED_FIELDS + (DISK_MATCHED_FIELDS if reduction.disk is not None else ())
        diff = [f"{k}: {valid.get(k)!r} in the reduction, {expect[k]!r} in use"
                for k in fields if k in expect and valid.get(k) != expect[k]]
        if diff:
            raise ReductionMismatchError(f"reduction {path} does not match the model ({'; '.join(diff)}); "
                                         "rebuild it with `softcrawl reduce build` or use --model full")
    if part is not None:
        check_part(path, meta, part)
    return reduction, meta
