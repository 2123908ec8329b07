"""Resolve a ``--space`` value (a shipped space's name or a space file's path) to a
:class:`softcrawl.design.spacefile.DesignSpace`: the one helper every command uses
(``softcrawl train --space``, ``groundtruth --space``, a run's own ``space.toml``).

A value without a path separator and without the ``.toml`` suffix names a shipped space
(``spaces/<name>.toml``: ``paper``, ``hex6``); anything else is a file path. A file whose
space equals the paper's (every compared field of :class:`DesignSpace`) resolves to
:data:`softcrawl.design.space.DEFAULT_SPACE` itself, so the default space's enumerations are
shared and its robots are the paper's, bit for bit.

A co-design run or a ground-truth folder keeps the file it was started with as ``space.toml``
(:func:`write_space_copy`, with a reduction the file names by a relative path, and the file's
name as the space's ``name`` if it gives none) and its SHA-256 in its ``config.json``; its
readers use that copy, checked first (:func:`check_space_copy`). The copy is the same space as
the file (:class:`DesignSpace` equality: the same name, and a reduction compared by its bytes).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import tempfile
import tomllib
from pathlib import Path

from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import SHIPPED_PREFIX, SPACES_DIR, DesignSpace, SpaceFileError, load_space
from softcrawl.safeio import atomic_write_text, read_bytes

#: Name of the paper's shipped space (``EnvConfig.space``'s default).
PAPER_SPACE = "paper"

#: ``(resolved path, sha256) -> DesignSpace``: a file read once per content.
_CACHE: dict[tuple[str, str], DesignSpace] = {}


def shipped_space_names() -> tuple[str, ...]:
    """Names of the shipped space files, sorted (``("hex6", "paper")``)."""
    return tuple(sorted(p.stem for p in SPACES_DIR.glob("*.toml")))


def is_space_name(value: str) -> bool:
    """Whether ``value`` is read as a shipped space's name (no path separator, no ``.toml``)."""
    return os.sep not in value and "/" not in value and not value.endswith(".toml")


def space_path(value: str | os.PathLike) -> Path:
    """The file a ``--space`` value names: ``spaces/<value>.toml`` for a shipped name, else
    the path itself.

    Raises:
        SpaceFileError: (a ValueError, one line) an unknown shipped name, no such file, or not
            a regular file (a folder, a device, a FIFO).
    """
    text = os.fspath(value)
    if not text:
        raise SpaceFileError("design space: empty name (a shipped space: "
                             f"{', '.join(shipped_space_names())}; or a space file's path)")
    if is_space_name(text):
        path = SPACES_DIR / f"{text}.toml"
        if not path.is_file():
            raise SpaceFileError(f"no shipped design space {text!r} (shipped: {', '.join(shipped_space_names())}; "
                                 "or give a space file's path)")
        return path
    path = Path(text)
    if not path.is_file():
        raise SpaceFileError(f"{path}: " + ("not a regular file (a design-space file is a TOML file)" if path.exists()
                                            else "no such design-space file"))
    return path


def resolve_space(value: str | os.PathLike | DesignSpace) -> DesignSpace:
    """The design space a ``--space`` value names (module docstring), read with
    :func:`softcrawl.design.spacefile.load_space` (every key checked, PneuNet dimensions too).

    Args:
        value: a shipped name (``"paper"``, ``"hex6"``), a space file's path, or a
            :class:`DesignSpace` (returned as it is).

    Returns:
        The space (:data:`DEFAULT_SPACE` for the paper's).

    Raises:
        SpaceFileError: (a ValueError) one line: an unknown name, no such file, or a malformed
            or inconsistent file (:func:`load_space`).
    """
    if isinstance(value, DesignSpace):
        return value
    if os.fspath(value) == PAPER_SPACE:
        return DEFAULT_SPACE
    return space_file(value)[1]


def space_file(value: str | os.PathLike) -> tuple[bytes, DesignSpace]:
    """The bytes of the file a ``--space`` value names and its space (:func:`resolve_space`),
    read once: the bytes are those the space was read from (what a run keeps as ``space.toml``).

    Raises:
        SpaceFileError: as :func:`resolve_space`, the file changed while it was read, or it names
            its reduction by a relative path out of its folder (``..``: a folder's copy,
            :func:`write_space_copy`, could not take it along).
    """
    path = space_path(value)
    try:
        data = read_bytes(path)
    except (OSError, ValueError) as exc:
        raise SpaceFileError(" ".join(f"{path}: {exc}".split())) from None
    sha = hashlib.sha256(data).hexdigest()
    key = (str(path.resolve()), sha)
    if key not in _CACHE:
        try:
            space = load_space(path)
        except FileNotFoundError as exc:
            raise SpaceFileError(" ".join(str(exc).split())) from None
        if space.sha256 != sha:
            raise SpaceFileError(f"{path}: changed while it was read; run the command again")
        _relative_reduction(data, space)
        _CACHE[key] = DEFAULT_SPACE if space == DEFAULT_SPACE else space
    return data, _CACHE[key]


def _relative_reduction(data: bytes, space: DesignSpace) -> str | None:
    """The ``[actuator] reduction`` of a space file's bytes if it is a relative path (else None).

    Raises:
        SpaceFileError: the path leaves the space file's folder (``..``).
    """
    ref = tomllib.loads(data.decode("utf-8-sig")).get("actuator", {}).get("reduction")
    if not isinstance(ref, str) or ref.startswith(SHIPPED_PREFIX) or Path(ref).is_absolute():
        return None
    if ".." in Path(ref).parts:
        raise SpaceFileError(f"{space.source}: actuator.reduction: {ref!r} leaves the space file's folder; give an "
                             "absolute path or one below that folder")
    return ref


#: File name of the copy of its design space that a run or ground-truth folder keeps.
SPACE_COPY = "space.toml"


def write_space_copy(folder: str | os.PathLike, value: str | os.PathLike) -> str:
    """Copy the file a ``--space`` value names into ``folder`` as :data:`SPACE_COPY`
    (atomically; the bytes :func:`resolve_space` read, after a line ``name = "<the file's
    name>"`` if the file gives no ``name``) and return the copy's SHA-256 (hex), which the
    folder's ``config.json`` records for :func:`check_space_copy`. A reduction the file names
    by a relative path is copied too, to the same path below ``folder``, so that the copy
    reads as the original did (``softcrawl:`` names and absolute paths need no copy). The copy
    is the same space as the file (:class:`DesignSpace` equality).

    Args:
        folder: the run or ground-truth folder (it must exist).
        value: the ``--space`` value.

    Raises:
        SpaceFileError: as :func:`space_file`, or the reduction file changed while it was read
            (nothing written then). OSError: the folder cannot be written.
    """
    data, space = space_file(value)
    text = data.decode("utf-8-sig")  # a space file is UTF-8 TOML (load_toml), a byte-order mark dropped with it
    if "name" not in tomllib.loads(text):
        text = f"name = {json.dumps(space.name)}\n" + text  # a name is a TOML basic string (NAME_PATTERN)
    ref = _relative_reduction(data, space)
    if ref is not None:
        reduction = read_bytes(space.reduction)
        if f"sha256:{hashlib.sha256(reduction).hexdigest()}" != space.reduction_key:
            raise SpaceFileError(f"{space.reduction}: the reduction file changed while it was read; run the command "
                                 "again")
        _write_bytes(Path(folder) / ref, reduction)
    atomic_write_text(Path(folder) / SPACE_COPY, text)
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _write_bytes(path: Path, data: bytes) -> None:
    """Replace ``path`` by a file holding ``data``, atomically (a temporary file renamed over
    it; its folder created). OSError: it cannot be written."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def check_space_copy(folder: str | os.PathLike, sha256: object) -> Path:
    """The folder's :data:`SPACE_COPY`, checked against the SHA-256 its ``config.json``
    recorded (:func:`write_space_copy`). Returns its path (a ``--space`` value).

    Raises:
        ValueError: one line: no recorded checksum, the copy is missing or unreadable, or it
            was changed (its SHA-256 differs).
    """
    path = Path(folder) / SPACE_COPY
    if not isinstance(sha256, str):
        raise ValueError(f"{path.parent / 'config.json'}: no space_sha256 (the checksum of its {SPACE_COPY})")
    try:
        data = read_bytes(path)
    except (OSError, ValueError) as exc:
        raise ValueError(" ".join(f"{path}: the folder's design space cannot be read ({exc})".split())) from None
    have = hashlib.sha256(data).hexdigest()
    if have != sha256:
        raise ValueError(f"{path}: sha256 {have[:12]}... is not the recorded {sha256[:12]}... (the design space "
                         "was changed after the folder was written); refusing to use it")
    return path
