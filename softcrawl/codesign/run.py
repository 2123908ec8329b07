"""The run folder of a co-design training run: its layout, and every read and write of it.

Training writes through :class:`Run`; evaluation, the report, regret and deploy read through
it; nothing else builds a run's paths by hand. Layout::

    RUN/
    ├── .run.lock                  held by the command writing the run (train, train --resume, report;
    │                              Run.lock: a second one is refused, naming the holder); removed when
    │                              it ends, left unlocked by a killed one
    ├── config.json                {"version": softcrawl version, "config_version": format,
    │                              "space_sha256": space.toml's SHA-256, "config": TrainConfig.to_dict()}
    │                              (written once the run has started: config valid, envs built; an
    │                              older format is read through softcrawl.codesign.migrate)
    ├── space.toml                 the design space's file as it was when training started (a copy of
    │                              env.space's file; written just before config.json); the run's
    │                              readers use it, never the file env.space names (format 4 on)
    ├── episodes.csv               t (transitions), design, return_cm, diverged; one row per episode
    ├── distribution.csv           t, beta, entropy, target, effective_target, floor, clamped, top designs
    ├── sessions.csv               first step, last step, wall seconds, version; one row per train/resume call,
    │                              updated at each of its checkpoints (a killed call keeps its time)
    ├── domain.csv                 domain-randomized runs only: t, design, return, diverged, the draw's values
    ├── shortlist.json             the run's design: its final shortlist, each candidate's gaits and returns, the
    │                              chosen one, of one checkpoint (softcrawl.codesign.shortlist; written when
    │                              training ends, or by the report of a run without one)
    ├── snapshots/t-XXXXXXXXXX.npz p, scores (float32), tried (bool), t of the design distribution
    ├── logs/                      SB3 logger: progress.csv (progress-<k>.csv: earlier calls), TensorBoard events
    ├── checkpoints/
    │   ├── latest                 text: name of the newest complete checkpoint (a hint, checked, never followed
    │   │                          out of checkpoints/)
    │   └── step-XXXXXXXXXX/       complete iff manifest.json's SHA-256 sums match:
    │       ├── learner.msgpack    sbx learner (format 2): flax msgpack of arrays (softcrawl.codesign.sac_jax):
    │       │                      actor, critics, target critics, Adam states, log temperature, JAX random keys
    │       ├── model.pt           or torch learner (format 1): tensors only (torch.load(weights_only=True)):
    │       │                      policy, critics, targets, optimizers, log temperature, torch RNG
    │       ├── replay_buffer.npz  the SB3 replay buffer's arrays and pos/full (np.load(allow_pickle=False))
    │       ├── state.json         counters, design sampler (distribution + its RNG), numpy, python and
    │       │                      action-space RNGs, the designs of the episodes just begun (at an episode
    │       │                      boundary, else null)
    │       └── manifest.json      {"format": 2 or 1, "files": {name: sha256}}
    └── report/                    softcrawl report (built in .report.partial-*, swapped in when complete)

Nothing read from a run folder is executed: msgpack of arrays, tensors only with
``weights_only=True``, JSON (read with :mod:`softcrawl.safeio`) and ``allow_pickle=False`` npz. Nothing is read or
written through links out of the run: a run whose entries above are symbolic links is refused
(:meth:`Run.check_links`), and ``latest`` is only a name. Errors about a run's CSV files name
the file and the 1-based line.

This module holds the layout, the settings, the logs, the snapshots and the report's
installation; writing, checking, reading and rescuing checkpoints is
:mod:`softcrawl.codesign.checkpoints` (:class:`~softcrawl.codesign.checkpoints.RunCheckpoints`,
whose methods :class:`Run` has).
"""

from __future__ import annotations

import csv
import io
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np

from softcrawl import __version__
from softcrawl.codesign.checkpoints import NoSpaceError, RunCheckpoints, _sha256, is_no_space
from softcrawl.codesign.config import TrainConfig
from softcrawl.codesign.migrate import CONFIG_VERSION, SPACE_VERSION, config_version, read_settings
from softcrawl.codesign.notes import note
from softcrawl.design.resolve import SPACE_COPY, check_space_copy, resolve_space, write_space_copy
from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import DesignSpace
from softcrawl.safeio import atomic_write_text, folder_lock, load_json

#: Names other modules import from here (the checkpoint helpers live in
#: :mod:`softcrawl.codesign.checkpoints`, the notes in :mod:`softcrawl.codesign.notes`).
__all__ = ["NoSpaceError", "Run", "_sha256", "is_no_space", "latest_checkpoint", "note"]

#: The lock file of a run folder (:meth:`Run.lock`).
RUN_LOCK = ".run.lock"


class Run(RunCheckpoints):
    """A co-design run folder (module docstring).

    Args:
        path: the run folder (need not exist yet).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    # -- paths -----------------------------------------------------------------------------
    config_path = property(lambda self: self.path / "config.json")
    space_path = property(lambda self: self.path / SPACE_COPY)
    episodes_csv = property(lambda self: self.path / "episodes.csv")
    distribution_csv = property(lambda self: self.path / "distribution.csv")
    sessions_csv = property(lambda self: self.path / "sessions.csv")
    domain_csv = property(lambda self: self.path / "domain.csv")
    shortlist_json = property(lambda self: self.path / "shortlist.json")
    snapshots_dir = property(lambda self: self.path / "snapshots")
    logs_dir = property(lambda self: self.path / "logs")
    checkpoints_dir = property(lambda self: self.path / "checkpoints")
    report_dir = property(lambda self: self.path / "report")
    lock_path = property(lambda self: self.path / RUN_LOCK)

    def _inside(self, p: Path) -> bool:
        """``p`` is a real (non-symlink) entry whose resolved path is inside the run."""
        try:
            return not p.is_symlink() and p.resolve().is_relative_to(self.path.resolve())
        except OSError:
            return False

    # -- config ----------------------------------------------------------------------------
    def exists(self) -> bool:
        """The folder holds a ``config.json`` (a started run)."""
        return self.config_path.is_file()

    def is_new(self) -> bool:
        """No folder yet, or an empty one (a lock file left by a killed command aside)."""
        return not self.path.exists() or (self.path.is_dir() and not self.path.is_symlink()
                                          and all(p.name == RUN_LOCK for p in self.path.iterdir()))

    def lock(self):
        """A context manager holding the run's lock (:data:`RUN_LOCK`,
        :func:`softcrawl.safeio.folder_lock`) while a command writes the run; the folder must
        exist.

        Raises:
            FolderLockedError: another command is writing the run (the message names it).
        """
        return folder_lock(self.lock_path, self.path)

    def check_links(self) -> None:
        """Refuse a run whose own files or folders (config, logs, snapshots, checkpoints,
        report) are symbolic links: through them, reading a run someone sent, or resuming it,
        would read or write files outside the run.

        Raises:
            ValueError: naming the first such link.
        """
        for p in (self.config_path, self.space_path, self.episodes_csv, self.distribution_csv, self.sessions_csv,
                  self.domain_csv, self.shortlist_json, self.snapshots_dir, self.logs_dir, self.checkpoints_dir,
                  self.report_dir):
            if p.is_symlink():
                raise ValueError(f"{p} is a symbolic link: a run's files must be inside its folder (refusing to "
                                 "read or write through it)")

    def read_meta(self) -> dict:
        """``config.json`` as a dict with ``version`` and ``config`` (:meth:`check_links` first;
        read with :func:`softcrawl.safeio.load_json`; the settings as saved, in their format).

        Raises:
            ValueError: not a training run, a run with linked files, or an unreadable /
                malformed ``config.json``.
        """
        if not self.exists():
            raise ValueError(f"{self.path} is not a training run (no config.json)")
        self.check_links()
        try:
            meta = load_json(self.config_path)
            if not isinstance(meta, dict) or not isinstance(meta.get("config"), dict):
                raise ValueError("no 'config' object")
        except (OSError, ValueError) as exc:
            raise ValueError(f"{self.config_path}: not a softcrawl run config ({exc})") from None
        return meta

    def read_config(self) -> TrainConfig:
        """The run's :class:`TrainConfig`, an older format migrated
        (:func:`softcrawl.codesign.migrate.read_settings`; a run of an older format is the
        paper's space). A run of format 4 on has ``env.space`` set to its own ``space.toml``
        (checked against ``config.json``'s ``space_sha256``), whatever file the saved value
        names, so that the run reads the space it trained on.

        Raises:
            ValueError: as :meth:`read_meta`, a format this softcrawl does not know, a bad
                setting, or a missing or changed ``space.toml`` (:meth:`check_space`).
        """
        meta = self.read_meta()
        try:
            settings = read_settings("train", meta)
            if config_version(meta) >= SPACE_VERSION:
                self.check_space(meta)
                if isinstance(settings.get("env"), dict):
                    settings = {**settings, "env": {**settings["env"], "space": str(self.space_path)}}
            return TrainConfig.from_dict(settings)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self.config_path}: {exc}") from None

    def check_space(self, meta: dict) -> None:
        """Refuse a ``space.toml`` that is missing or whose SHA-256 is not ``meta``'s
        ``space_sha256`` (:func:`softcrawl.design.resolve.check_space_copy`; ValueError, one line)."""
        check_space_copy(self.path, meta.get("space_sha256"))

    def design_space(self) -> DesignSpace:
        """The run's design space (its ``space.toml``; the paper's for a run of an older format
        or a folder without ``config.json``). ValueError as :meth:`read_config`."""
        return resolve_space(self.read_config().env.space) if self.exists() else DEFAULT_SPACE

    def write_config(self, cfg: TrainConfig) -> None:
        """Write ``space.toml`` (the file ``cfg.env.space`` names, the same space:
        :func:`~softcrawl.design.resolve.write_space_copy`) and then ``config.json`` with its
        SHA-256, atomically (creates the folder).

        Raises:
            SpaceFileError: (a ValueError) the space file cannot be read.
        """
        self.path.mkdir(parents=True, exist_ok=True)
        sha = write_space_copy(self.path, cfg.env.space)  # the same space as the file's
        atomic_write_text(self.config_path, json.dumps({"version": __version__, "config_version": CONFIG_VERSION,
                                                        "space_sha256": sha, "config": cfg.to_dict()}, indent=2))

    # -- logs ------------------------------------------------------------------------------
    def read_episodes(self) -> dict:
        """``episodes.csv`` as arrays: ``t`` (int64), ``design`` (list of tuples), ``r`` (cm),
        ``diverged`` (bool); an unfinished last row (a killed writer) is left out, said on
        stderr. ValueError naming the file and the 1-based line of a bad row."""
        t, designs, r, div = [], [], [], []
        if self.episodes_csv.exists():
            for line, row in _csv_rows(self.episodes_csv, say=True):
                try:
                    t.append(int(row[0]))
                    designs.append(tuple(int(c) for c in row[1]))
                    r.append(float(row[2]))
                    div.append(bool(int(row[3])))
                except (IndexError, ValueError):
                    raise ValueError(f"{self.episodes_csv}, line {line}: not an episode row: {row!r}") from None
        return {"t": np.array(t, np.int64), "design": designs, "r": np.array(r), "diverged": np.array(div, bool)}

    def read_distribution(self) -> dict:
        """``distribution.csv`` as arrays: ``t`` (int64), ``beta`` (1/unit of the returns),
        ``entropy`` (nats), and ``top``: per row its most probable designs, ``[(design, p),
        ...]`` (p as logged, 3 significant digits); an unfinished last row is left out.
        ValueError naming the file and the 1-based line of a bad row."""
        t, beta, entropy, top = [], [], [], []
        if self.distribution_csv.exists():
            for line, row in _csv_rows(self.distribution_csv):
                try:
                    t.append(int(row[0]))
                    beta.append(float(row[1]))
                    entropy.append(float(row[2]))
                    top.append([(tuple(int(c) for c in d), float(p))
                                for d, p in (item.split(":") for item in row[7].split())])
                except (IndexError, ValueError):
                    raise ValueError(f"{self.distribution_csv}, line {line}: not a distribution row: {row!r}") from None
        return {"t": np.array(t, np.int64), "beta": np.array(beta), "entropy": np.array(entropy), "top": top}

    def has_history(self) -> bool:
        """Anything logged: episode rows, snapshots or checkpoints."""
        if self.episodes_csv.exists() and self.episodes_csv.stat().st_size > 0:
            return True
        return bool(self.snapshots()) or bool(self._step_dirs()) or (self.checkpoints_dir / "latest").exists()

    def record_session(self, first_step: int, last_step: int, wall_seconds: float, replace_last: bool) -> None:
        """Write this train/resume call's row of ``sessions.csv`` (atomically): appended at the
        call's first checkpoint, then replaced (``replace_last``) at each later one and at its end,
        so a killed call keeps its wall time up to its last checkpoint."""
        rows = [row for _, row in _csv_rows(self.sessions_csv)] if self.sessions_csv.exists() else []
        if replace_last and rows:
            rows.pop()
        rows.append([str(first_step), str(last_step), f"{wall_seconds:.1f}", __version__])
        buf = io.StringIO()
        csv.writer(buf, lineterminator="\n").writerows(rows)
        atomic_write_text(self.sessions_csv, buf.getvalue())

    def wall_seconds(self) -> float:
        """Training wall time over all train/resume calls (``sessions.csv``), s (NaN if none)."""
        if not self.sessions_csv.exists():
            return float("nan")
        total = 0.0
        for line, row in _csv_rows(self.sessions_csv):
            try:
                total += float(row[2])
            except (IndexError, ValueError):
                raise ValueError(f"{self.sessions_csv}, line {line}: not a session row: {row!r}") from None
        return total

    def forget_after(self, t: int) -> None:
        """Resume bookkeeping: drop episode/distribution rows and snapshots logged after step
        ``t`` (the killed call's work past its checkpoint) and keep SB3's ``progress.csv`` of
        the earlier part as ``progress-<k>.csv`` (SB3 would overwrite it). An unfinished last
        line (a call killed, or a full disk, while writing it: written after the checkpoint's
        flush) is dropped too.

        Raises:
            ValueError: a malformed row (the message names the file and its 1-based line);
                nothing is changed then.
        """
        kept = {path: _rows_up_to(path, t) for path in (self.episodes_csv, self.distribution_csv) if path.exists()}
        for path, rows in kept.items():
            tmp = path.with_suffix(".tmp")
            with open(tmp, "w", newline="") as f:
                csv.writer(f).writerows(rows)
            os.replace(tmp, path)
        for snap in self.snapshots():
            if int(snap.stem.split("-")[1]) > t:
                snap.unlink()
        progress = self.logs_dir / "progress.csv"
        if progress.exists():
            k = len(list(self.logs_dir.glob("progress-*.csv")))
            os.replace(progress, progress.with_name(f"progress-{k}.csv"))

    # -- snapshots -------------------------------------------------------------------------
    def snapshots(self) -> list[Path]:
        """Snapshot files, oldest first."""
        d = self.snapshots_dir
        return sorted(d.glob("t-*.npz")) if d.is_dir() and self._inside(d) else []

    def write_snapshot(self, distribution, t: int) -> None:
        """Snapshot of a :class:`GibbsDesignDistribution` at step ``t``."""
        self.snapshots_dir.mkdir(exist_ok=True)
        np.savez_compressed(self.snapshots_dir / f"t-{t:010d}.npz", p=distribution.probs().astype(np.float32),
                            scores=distribution.scores().astype(np.float32), tried=distribution.tried, t=t)

    def read_snapshot(self, path: Path) -> dict:
        """One snapshot's arrays (``p``, ``scores``, ``tried``, ``t``); ValueError if unreadable."""
        try:
            with np.load(path, allow_pickle=False) as z:
                return {k: z[k] for k in ("p", "scores", "tried", "t")}
        except Exception as exc:  # zip, npy, EOF errors: all mean "not a snapshot"
            raise ValueError(f"{path}: not a design-distribution snapshot ({exc or type(exc).__name__})") from None


    # -- report ----------------------------------------------------------------------------
    def report_staging(self) -> Path:
        """A fresh ``.report.partial-*`` folder inside the run (stale ones are removed first).

        Raises:
            ValueError: ``report`` is a symlink or otherwise points out of the run.
        """
        rep = self.report_dir
        if rep.is_symlink() or (rep.exists() and (not rep.is_dir() or not self._inside(rep))):
            raise ValueError(f"{rep} is a link or not a folder of the run; refusing to write the report")
        for stale in self.path.glob(".report.partial-*"):
            if stale.is_dir() and not stale.is_symlink():
                shutil.rmtree(stale, ignore_errors=True)
        return Path(tempfile.mkdtemp(prefix=".report.partial-", dir=self.path))

    def install_report(self, staged: Path) -> Path:
        """Swap a complete staged report in as ``report/`` (the old one is removed). Returns it."""
        rep = self.report_dir
        old = None
        if rep.exists():
            old = Path(tempfile.mkdtemp(prefix=".report.old-", dir=self.path))
            os.replace(rep, old / "report")
        os.replace(staged, rep)
        rep.chmod(0o755)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
        return rep


def _csv_rows(path: Path, say: bool = False) -> list[tuple[int, list[str]]]:
    """``(1-based line, row)`` of the non-empty rows of a run CSV. An unfinished last line (no
    newline: the writer was killed, or the disk filled, mid-row) is left out (noted with ``say``).

    Raises:
        ValueError: the file cannot be read or decoded (named).
    """
    try:
        with open(path, newline="", encoding="utf-8") as f:
            text = f.read()
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read ({exc})") from None
    if text and not text.endswith("\n"):
        cut = text.rfind("\n") + 1
        if say:
            note(f"{path}, line {text.count(chr(10)) + 1}: unfinished last row (the writer was stopped); left out")
        text = text[:cut]
    return [(line, row) for line, row in enumerate(csv.reader(text.splitlines()), start=1) if row]


def _rows_up_to(path: Path, t: int) -> list[list[str]]:
    """The rows of a run CSV (first column: step) with step <= ``t``; an unfinished last line
    (no newline) is left out. ValueError naming the file and the 1-based line of a bad row."""
    rows = []
    for line, row in _csv_rows(path):
        try:
            step = int(row[0])
        except ValueError:
            raise ValueError(f"{path}, line {line}: not a row of this run (step {row[0]!r})") from None
        if step <= t:
            rows.append(row)
    return rows


def latest_checkpoint(run_dir: str | os.PathLike) -> Path | None:
    """Shortcut for ``Run(run_dir).latest_checkpoint(quiet=True)``."""
    return Run(run_dir).latest_checkpoint(quiet=True)
