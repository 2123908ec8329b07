"""A ground-truth folder on disk: ``results.jsonl`` (read, validated, appended), the settings
and the design set in ``config.json``, ``references.json``, the check of a folder before a run writes it
(:func:`check_folder`) and its lock (:func:`folder_lock`).

``results.jsonl`` is only ever appended to, never rewritten, and never through a symbolic link.
Its readers (:func:`read_results`: the run itself, ``regret``, ``report --groundtruth``)
validate every row and use only the valid ones; a bad row (a line cut short by a killed run, a
non-finite reward, a design outside the space, a knot outside [0, 90] kPa) is named by file and
line and left in place, and a resumed run computes its design again.
"""

from __future__ import annotations

import json
import os
import stat
from pathlib import Path

from softcrawl.codesign.groundtruth.config import GroundTruthConfig, parse_designs
from softcrawl.codesign.groundtruth.result import DesignResult, _finite
from softcrawl.codesign.migrate import SPACE_VERSION, config_version, read_settings
from softcrawl.codesign.run import note
from softcrawl.design.resolve import check_space_copy
from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.safeio import UnsafeFileError, load_json, loads_json, read_text
from softcrawl.safeio import folder_lock as safe_folder_lock
from softcrawl.tasks import DEFAULT_TASK, Task, parse_task

RESULTS = "results.jsonl"


def read_results(out_dir: str | Path) -> tuple[dict[Design, DesignResult], list[str]]:
    """The rows of a ground truth's ``results.jsonl``, read and never written:
    ``(results by design, problems)``. Each row is validated (:meth:`DesignResult.from_dict`);
    a bad row (not JSON, as a line cut short by a killed run, or not a valid result) is left
    out of the results and in the file, and described in ``problems`` by file and line. Of
    two rows of one design the later counts (a design recomputed after a bad row).

    Raises:
        UnsafeFileError: ``results.jsonl`` is a symbolic link, not a regular file, or too large.
    """
    path = Path(out_dir) / RESULTS
    if path.is_symlink():
        raise UnsafeFileError(f"{path} is a symbolic link; a ground truth's results must be a file in its folder")
    if not path.exists():
        return {}, []
    space, unit = folder_space(out_dir), folder_task(out_dir).unit
    good, bad = {}, []
    for n, line in enumerate(read_text(path).split("\n"), start=1):
        if not line.strip():
            continue
        where = f"{path}, line {n}"
        try:
            r = DesignResult.from_dict(loads_json(line, where), where, space, unit)
        except ValueError as exc:
            bad.append(str(exc))
            continue
        good[r.design] = r
    return good, bad


def folder_space(out_dir: str | Path) -> DesignSpace:
    """The design space of a ground-truth folder (its ``space.toml``, :func:`read_config`);
    the paper's for a folder without ``config.json``. ValueError as :func:`read_config`."""
    return read_config(out_dir).design_space() if (Path(out_dir) / "config.json").exists() else DEFAULT_SPACE


def folder_task(out_dir: str | Path) -> Task:
    """The task of a ground-truth folder (:attr:`GroundTruthConfig.task` of its ``config.json``;
    ``forward`` for a folder saved before tasks existed, or without ``config.json``).
    ValueError as :func:`read_config`."""
    return read_config(out_dir).task_spec() if (Path(out_dir) / "config.json").exists() else parse_task(DEFAULT_TASK)


def load_results(out_dir: str | Path) -> dict[Design, DesignResult]:
    """The valid rows of :func:`read_results`; each bad row is a note on stderr naming its file
    and line (the row stays in the file)."""
    good, bad = read_results(out_dir)
    for problem in bad:
        note(f"{problem}; row left in place and not used")
    return good


def _append(path: Path, result: DesignResult, unit: str = "cm") -> None:
    """Append one row to ``results.jsonl`` (its rewards keyed in ``unit``, the task's) and fsync
    it. A last line left unfinished by a killed run is first ended, so that it stays a (bad)
    line of its own.

    Raises:
        UnsafeFileError: the file is a symbolic link or not a regular file.
    """
    line = (json.dumps(result.to_dict(unit), allow_nan=False) + "\n").encode()
    try:
        fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError:
        if path.is_symlink():
            raise UnsafeFileError(f"{path} is a symbolic link; a ground truth's results must be a file "
                                  "in its folder") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise UnsafeFileError(f"{path}: not a regular file")
        if st.st_size and os.pread(fd, 1, st.st_size - 1) != b"\n":
            line = b"\n" + line
        os.write(fd, line)
        os.fsync(fd)
    finally:
        os.close(fd)


#: Lock file of a ground-truth folder: held by the run writing it (:func:`folder_lock`).
LOCK = ".groundtruth.lock"


def read_config(out_dir: str | Path) -> GroundTruthConfig:
    """The settings saved in a ground-truth folder's ``config.json`` (an older format read
    through :func:`softcrawl.codesign.migrate.read_settings`: the paper's space). From format 4
    on, ``space`` is the folder's own ``space.toml``, checked against the ``space_sha256`` of
    ``config.json`` (:func:`softcrawl.design.resolve.check_space_copy`).

    Raises:
        FileNotFoundError: no ``config.json``.
        ValueError: not a ground truth's ``config.json``, or a missing or changed
            ``space.toml`` (the message names the file).
    """
    path = Path(out_dir) / "config.json"
    doc = load_json(path)
    try:
        settings = read_settings("groundtruth", doc)
        if config_version(doc) >= SPACE_VERSION:
            settings = {**settings, "space": str(check_space_copy(out_dir, doc.get("space_sha256")))}
        return GroundTruthConfig.from_dict(settings)
    except ValueError as exc:
        raise ValueError(f"{path}: not a ground truth's settings ({exc})") from None


def recorded_designs(out_dir: str | Path) -> list[Design] | None:
    """The design set a ground-truth folder's ``config.json`` records (its ``"designs"``,
    :func:`~softcrawl.codesign.groundtruth.config.design_set_spec`, in the folder's space); None
    for a folder written before ground truths recorded theirs.

    Raises:
        FileNotFoundError: no ``config.json``.
        ValueError: a record that is not a design set of the folder's space (names the file),
            or as :func:`read_config`.
    """
    path = Path(out_dir) / "config.json"
    doc = load_json(path)
    spec = doc.get("designs") if isinstance(doc, dict) else None
    if spec is None:
        return None
    space = folder_space(out_dir)
    try:
        if not isinstance(spec, str):
            raise ValueError(f"designs must be text, got {spec!r}")
        return parse_designs(spec, space)
    except ValueError as exc:
        raise ValueError(f"{path}: not a ground truth's design set ({exc})") from None


def check_folder(out_dir: str | Path) -> Path:
    """``--out`` of ``softcrawl groundtruth``, checked before any work: a folder that can be
    created, an empty one, or a ground-truth folder (its ``config.json`` readable); never a
    folder another command wrote (a simulation, a deployment, a training run).

    Raises:
        OutputExistsError: not a directory, or not writable.
        ValueError: a folder of other files, or a ``config.json`` that is not a ground truth's.
    """
    from softcrawl.robot.output import OutputExistsError, check_output_path

    out = Path(out_dir)
    if not out.exists() and not out.is_symlink():
        return check_output_path(out)
    if out.is_symlink() or not out.is_dir():
        raise OutputExistsError(f"{out} exists and is not a directory")
    if (out / "config.json").exists() or (out / "config.json").is_symlink():
        try:
            read_config(out)
        except ValueError as exc:
            raise ValueError(f"{out} is not a ground-truth folder: {exc}; use another --out") from None
    else:
        others = sorted(p.name for p in out.iterdir() if p.name != LOCK)
        if others:
            raise ValueError(f"{out} holds other files ({', '.join(others[:3])}{', ...' if len(others) > 3 else ''}) "
                             "and no ground truth; use another --out")
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputExistsError(f"{out} is not writable")
    return out


def folder_lock(out: Path):
    """The lock of the ground-truth folder ``out`` (:data:`LOCK`,
    :func:`softcrawl.safeio.folder_lock`: it names its holder, and dies with it).

    Raises:
        FolderLockedError: another process holds it.
    """
    return safe_folder_lock(Path(out) / LOCK, out)


def read_references(out_dir: str | Path) -> dict | None:
    """``references.json`` of a ground-truth folder, or None if it is missing or not valid
    (a note says so): an object of references, each with a finite ``reward_<unit>`` (the
    folder's task's unit, :func:`folder_task`)."""
    path = Path(out_dir) / "references.json"
    if not path.exists() and not path.is_symlink():
        return None
    try:
        key = f"reward_{folder_task(out_dir).unit}"
        refs = load_json(path)
        if not isinstance(refs, dict) or not all(isinstance(v, dict) and _finite(v.get(key))
                                                 for v in refs.values()):
            raise ValueError("not an object of references with finite rewards")
        if not _finite(refs.get("expert_baseline", {"best_phase_deg": 0.0}).get("best_phase_deg")):
            raise ValueError("the expert baseline has no finite best_phase_deg")
    except (ValueError, OSError) as exc:
        note(f"{exc if str(path) in str(exc) else f'{path}: {exc}'}; references left out")
        return None
    return refs


def load_groundtruth(gt_dir: str | Path) -> tuple[GroundTruthConfig, dict[Design, DesignResult], dict]:
    """``(config, results by design, references)`` of a ground-truth folder.

    Raises:
        ValueError: not a ground-truth folder, or no finished design.
    """
    gt = Path(gt_dir)
    if not (gt / "config.json").exists():
        raise ValueError(f"{gt} is not a ground-truth folder (no config.json)")
    cfg = read_config(gt)
    res = load_results(gt)
    if not res:
        raise ValueError(f"{gt} has no finished design yet")
    return cfg, res, read_references(gt) or {}
