"""The run folder of a co-design training run: its layout, and every read and write of it.

Training writes through :class:`Run`; evaluation, the report, regret and deploy read through
it; nothing else builds a run's paths by hand. Layout::

    RUN/
    ├── config.json                {"version": softcrawl version, "config": TrainConfig.to_dict()}
    │                              (written once the run has started: config valid, envs built)
    ├── episodes.csv               t (transitions), design, return_cm, diverged; one row per episode
    ├── distribution.csv           t, beta, entropy, target, effective_target, floor, clamped, top designs
    ├── sessions.csv               first step, last step, wall seconds, version; one row per train/resume call,
    │                              updated at each of its checkpoints (a killed call keeps its time)
    ├── domain.csv                 domain-randomized runs only: t, design, return, diverged, the draw's values
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
``weights_only=True``, JSON and ``allow_pickle=False`` npz; the old pickle format
(``state.pkl``, ``replay_buffer.pkl``) is refused. A checkpoint is read by the learner that
wrote it (its format), whatever the run's ``sac.learner`` says. Nothing is read or written
through links out of the run: a run whose entries above are symbolic links is refused
(:meth:`Run.check_links`), and ``latest`` is only a name.

Checkpoints are written into ``step-*.tmp`` and renamed into place, ``latest`` is replaced
atomically; a missing, dangling or damaged ``latest`` falls back to the newest complete
checkpoint (said on stderr), as does a ``latest`` older than a complete checkpoint on disk, and
at least two complete checkpoints are kept. When the disk is full (or read-only) a checkpoint
that cannot be written into the run is written into a ``softcrawl-rescue-*`` folder of the
system's temporary directory instead and named in the error (move it into ``checkpoints/`` to
resume from it). Errors about a run's CSV files name the file and the 1-based line.
"""

from __future__ import annotations

import csv
import dataclasses
import errno
import hashlib
import io
import json
import os
import random
import re
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

from softcrawl import __version__
from softcrawl.codesign.config import TrainConfig
from softcrawl.design.space import validate_design
from softcrawl.safeio import atomic_write_text

#: Checkpoint format of each learner and the file of its state (module docstring).
CHECKPOINT_FORMATS = {"sbx": 2, "torch": 1}
LEARNER_FILES = {"sbx": "learner.msgpack", "torch": "model.pt"}
_STEP = re.compile(r"step-(\d{10})")
_BUFFER_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


class NoSpaceError(ValueError):
    """A write failed for lack of space or a read-only file system (the message says where
    what was computed is kept)."""


def is_no_space(exc: BaseException) -> bool:
    """True for ENOSPC / EDQUOT / EROFS (disk full, quota, read-only file system)."""
    return isinstance(exc, OSError) and exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS)


def _sha256(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def note(msg: str) -> None:
    """A one-line note on stderr (``softcrawl: ...``): what was skipped or substituted."""
    print(f"softcrawl: {msg}", file=sys.stderr)


class Run:
    """A co-design run folder (module docstring).

    Args:
        path: the run folder (need not exist yet).
    """

    def __init__(self, path: str | os.PathLike):
        self.path = Path(path)

    # -- paths -----------------------------------------------------------------------------
    config_path = property(lambda self: self.path / "config.json")
    episodes_csv = property(lambda self: self.path / "episodes.csv")
    distribution_csv = property(lambda self: self.path / "distribution.csv")
    sessions_csv = property(lambda self: self.path / "sessions.csv")
    domain_csv = property(lambda self: self.path / "domain.csv")
    snapshots_dir = property(lambda self: self.path / "snapshots")
    logs_dir = property(lambda self: self.path / "logs")
    checkpoints_dir = property(lambda self: self.path / "checkpoints")
    report_dir = property(lambda self: self.path / "report")

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

    def check_links(self) -> None:
        """Refuse a run whose own files or folders (config, logs, snapshots, checkpoints,
        report) are symbolic links: through them, reading a run someone sent, or resuming it,
        would read or write files outside the run.

        Raises:
            ValueError: naming the first such link.
        """
        for p in (self.config_path, self.episodes_csv, self.distribution_csv, self.sessions_csv, self.domain_csv,
                  self.snapshots_dir, self.logs_dir, self.checkpoints_dir, self.report_dir):
            if p.is_symlink():
                raise ValueError(f"{p} is a symbolic link: a run's files must be inside its folder (refusing to "
                                 "read or write through it)")

    def read_meta(self) -> dict:
        """``config.json`` as a dict with ``version`` and ``config`` (:meth:`check_links` first).

        Raises:
            ValueError: not a training run, a run with linked files, or an unreadable /
                malformed ``config.json``.
        """
        if not self.exists():
            raise ValueError(f"{self.path} is not a training run (no config.json)")
        self.check_links()
        try:
            meta = json.loads(self.config_path.read_text(encoding="utf-8"))
            if not isinstance(meta, dict) or not isinstance(meta.get("config"), dict):
                raise ValueError("no 'config' object")
        except (OSError, ValueError) as exc:
            raise ValueError(f"{self.config_path}: not a softcrawl run config ({exc})") from None
        return meta

    def read_config(self) -> TrainConfig:
        """The run's :class:`TrainConfig` (ValueError as :meth:`read_meta`, or a bad setting)."""
        try:
            return TrainConfig.from_dict(self.read_meta()["config"])
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{self.config_path}: {exc}") from None

    def write_config(self, cfg: TrainConfig) -> None:
        """Write ``config.json`` atomically (creates the folder)."""
        self.path.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.config_path, json.dumps({"version": __version__, "config": cfg.to_dict()}, indent=2))

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

    # -- checkpoints -----------------------------------------------------------------------
    def _step_dirs(self) -> list[Path]:
        root = self.checkpoints_dir
        if not root.is_dir() or not self._inside(root):
            return []
        return sorted(p for p in root.iterdir() if _STEP.fullmatch(p.name) and p.is_dir() and self._inside(p))

    def check_checkpoint(self, path: Path) -> str | None:
        """None if ``path`` is a complete checkpoint of this run, else why not."""
        path = Path(path)
        if not _STEP.fullmatch(path.name) or not path.is_dir() or not self._inside(path):
            return "not a checkpoint folder of this run"
        if (path / "state.pkl").exists() or (path / "replay_buffer.pkl").exists():
            return "old pickle format (can run code when loaded; not read)"
        try:
            manifest = json.loads((path / "manifest.json").read_text(encoding="utf-8"))
            files = manifest["files"]
            learner = _FORMAT_LEARNERS.get(manifest.get("format"))
            if learner is None or set(files) != set(_checkpoint_files(learner)):
                return "unknown checkpoint format"
            for name in _checkpoint_files(learner):
                f = path / name
                if f.is_symlink() or not f.is_file() or _sha256(f) != files[name]:
                    return f"{name} is missing or damaged (checksum)"
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            return "manifest.json is missing or damaged"
        return None

    def checkpoints(self) -> list[Path]:
        """Complete checkpoints, oldest first."""
        return [p for p in self._step_dirs() if self.check_checkpoint(p) is None]

    def latest_checkpoint(self, quiet: bool = False) -> Path | None:
        """The checkpoint ``latest`` names if it is complete and no complete one on disk is
        newer, else the newest complete one (said on stderr unless ``quiet``), or None if there
        is none."""
        ptr = self.checkpoints_dir / "latest"
        why = "checkpoints/latest is missing"
        if ptr.is_file() and not ptr.is_symlink():
            try:
                name = ptr.read_text(encoding="utf-8").strip()
            except (OSError, UnicodeDecodeError):
                name = ""
            if not _STEP.fullmatch(name):
                why = f"checkpoints/latest names {name[:80]!r}, not a checkpoint of this run"
            else:
                why = self.check_checkpoint(self.checkpoints_dir / name)
                if why is None:
                    newer = [p for p in self._step_dirs() if p.name > name and self.check_checkpoint(p) is None]
                    if not newer:
                        return self.checkpoints_dir / name
                    why = f"checkpoints/latest names {name}, older than the complete {newer[-1].name}"
                else:
                    why = f"checkpoint {name}: {why}"
        elif ptr.exists() or ptr.is_symlink():
            why = "checkpoints/latest is not a plain file"
        complete = self.checkpoints()
        if complete and not quiet and (ptr.exists() or ptr.is_symlink() or self._step_dirs()):
            note(f"{why}; using {complete[-1].name}, the newest complete checkpoint")
        return complete[-1] if complete else None

    def require_checkpoint(self) -> Path:
        """:meth:`latest_checkpoint`, or ValueError if the run has none."""
        ck = self.latest_checkpoint()
        if ck is None:
            raise ValueError(f"{self.path} has no complete checkpoint (not a training run, or it has not "
                             "checkpointed yet)")
        return ck

    def checkpoint_learner(self, path: Path) -> str:
        """The ``sac.learner`` that wrote complete checkpoint ``path`` (``"sbx"`` or ``"torch"``,
        from its format).

        Raises:
            ValueError: not a complete checkpoint of this run.
        """
        why = self.check_checkpoint(path)
        if why is not None:
            raise ValueError(f"{path}: {why}")
        manifest = json.loads((Path(path) / "manifest.json").read_text(encoding="utf-8"))
        return _FORMAT_LEARNERS[manifest["format"]]

    def save_checkpoint(self, model, sampler, keep: int = 2) -> Path:
        """Write a complete checkpoint of ``model`` (a learner of :mod:`softcrawl.codesign.sac`)
        and ``sampler`` (a :class:`GibbsDesignSampler`) atomically, point ``latest`` at it and
        prune complete checkpoints beyond the newest ``max(keep, 2)``. Returns its folder.

        Raises:
            NoSpaceError: disk full / read-only: the partial ``.tmp`` is removed, ``latest`` is
                unchanged, and the checkpoint is written into a ``softcrawl-rescue-*`` folder of
                the system's temporary directory instead if it fits there (named in the message).
        """
        root = self.checkpoints_dir
        name = f"step-{model.num_timesteps:010d}"
        tmp = root / f"{name}.tmp"
        try:
            root.mkdir(parents=True, exist_ok=True)
            shutil.rmtree(tmp, ignore_errors=True)
            tmp.mkdir()
            _write_checkpoint(tmp, model, sampler)
            final = root / name
            shutil.rmtree(final, ignore_errors=True)
            os.replace(tmp, final)
            atomic_write_text(root / "latest", name)
        except OSError as exc:
            shutil.rmtree(tmp, ignore_errors=True)
            if is_no_space(exc):
                kept = _rescue_checkpoint(name, model, sampler)
                where = (f"it is kept in {kept} (move that folder into {root}/ to resume from it)" if kept else
                         "it could not be kept elsewhere either")
                raise NoSpaceError(f"no space left to write checkpoint {name} in {root} ({exc.strerror}); the "
                                   f"previous checkpoint stays latest; {where}") from None
            raise
        complete = self.checkpoints()
        for p in complete[:-max(keep, 2)]:
            shutil.rmtree(p, ignore_errors=True)
        return final

    def read_learner(self, path: Path) -> dict:
        """The decoded learner state of checkpoint ``path`` (its learner's
        ``decode_learner_state``, :mod:`softcrawl.codesign.sac`: arrays, or tensors read with
        ``weights_only=True``; nothing else unpickled).

        Raises:
            ValueError: incomplete, damaged, or not a learner state.
        """
        from softcrawl.codesign.sac import learner_module
        from softcrawl.safeio import read_bytes

        learner = self.checkpoint_learner(path)
        f = Path(path) / LEARNER_FILES[learner]
        try:
            return learner_module(learner).decode_learner_state(read_bytes(f))
        except (OSError, ValueError) as exc:
            raise ValueError(f"{f}: refused: {exc}") from None

    def load_learner(self, path: Path, model, raw: dict | None = None) -> None:
        """Restore the networks, optimizer states, temperature and random state of checkpoint
        ``path`` (or its :meth:`read_learner` output ``raw``) into ``model``, a learner of the
        run's config and of the checkpoint's learner (:meth:`checkpoint_learner`).

        Raises:
            ValueError: as :meth:`read_learner`, a checkpoint of the other learner, or a learner
                state of another config.
        """
        from softcrawl.codesign.sac import learner_module

        learner = self.checkpoint_learner(path)
        if model.learner != learner:
            raise ValueError(f"{path}: a checkpoint of the {learner!r} learner, read into the {model.learner!r} one")
        raw = self.read_learner(path) if raw is None else raw
        try:
            learner_module(learner).restore_learner_state(model, raw)
        except ValueError as exc:
            raise ValueError(f"{Path(path) / LEARNER_FILES[learner]}: refused: {exc}") from None

    def read_checkpoint_state(self, path: Path) -> dict:
        """``state.json`` of checkpoint ``path`` with ``sampler`` decoded
        (:func:`sampler_state_from_json`). ValueError if incomplete or malformed."""
        why = self.check_checkpoint(path)
        if why is not None:
            raise ValueError(f"{path}: {why}")
        try:
            state = json.loads((Path(path) / "state.json").read_text(encoding="utf-8"))
            state["sampler"] = sampler_state_from_json(state["sampler"])
            for key in ("num_timesteps", "n_updates", "episode_num"):
                state[key] = int(state[key])
            nxt = state.get("next_designs")  # absent in checkpoints written before it existed
            state["next_designs"] = None if nxt is None else [validate_design(d) for d in nxt]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ValueError(f"{path / 'state.json'}: malformed ({exc!r})") from None
        return state

    def load_checkpoint(self, path: Path, model, sampler) -> None:
        """Restore checkpoint ``path`` into a freshly built model / sampler (same config), and
        the numpy / python / action-space RNGs. ``model._last_obs`` is cleared so ``learn()`` starts
        fresh episodes: with the checkpoint's ``next_designs`` (an episode boundary) if it has
        them (:meth:`softcrawl.envs.DesignVecEnv.resume_with`), else with new draws.

        Raises:
            ValueError: incomplete, damaged, not a learner state, or built for another config.
        """
        self.load_learner(path, model)
        state = self.read_checkpoint_state(path)
        try:
            with np.load(Path(path) / "replay_buffer.npz", allow_pickle=False) as z:
                buffer = {k: z[k] for k in z.files}
            rb = model.replay_buffer
            for k in _BUFFER_ARRAYS:
                have = getattr(rb, k, None)
                if have is None:
                    continue
                if k not in buffer or buffer[k].shape != have.shape or buffer[k].dtype != have.dtype:
                    raise ValueError(f"replay buffer array {k!r} does not match this run's config")
            sampler.load_state_dict(state["sampler"])
            for k in _BUFFER_ARRAYS:
                if getattr(rb, k, None) is not None:
                    getattr(rb, k)[...] = buffer[k]
            rb.pos, rb.full = int(buffer["pos"]), bool(buffer["full"])
            if "action_space_rng" in state:  # absent in checkpoints written before it existed
                model.action_space.np_random.bit_generator.state = state["action_space_rng"]
            r = state["numpy_rng"]
            np.random.set_state((r["name"], np.array(r["key"], dtype=np.uint32), r["pos"], r["has_gauss"],
                                 r["cached_gaussian"]))
            v, key, gauss = state["python_rng"]
            random.setstate((v, tuple(key), gauss))
            env = _vec_env(model)
            if env is not None and state["next_designs"] is not None:
                env.resume_with(state["next_designs"])  # the designs the uninterrupted run had drawn
        except Exception as exc:  # zip/npy errors, shapes, RNG states: all mean "not restorable"
            msg = str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
            raise ValueError(f"{path}: cannot restore checkpoint ({msg})") from None
        model.num_timesteps, model._n_updates = state["num_timesteps"], state["n_updates"]
        model._episode_num = state["episode_num"]
        model._last_obs = None  # forces env.reset() in learn(): fresh episodes

    def checkpoint_steps(self, path: Path) -> int:
        """Environment steps of checkpoint ``path`` (from its name)."""
        return int(_STEP.fullmatch(Path(path).name).group(1))

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


def _write_checkpoint(folder: Path, model, sampler) -> None:
    """The checkpoint files of ``model`` and ``sampler`` (module docstring) into ``folder``."""
    from softcrawl.codesign.sac import learner_module

    (folder / LEARNER_FILES[model.learner]).write_bytes(learner_module(model.learner).learner_state_bytes(model))
    rb = model.replay_buffer
    arrays = {k: getattr(rb, k) for k in _BUFFER_ARRAYS if getattr(rb, k, None) is not None}
    np.savez(folder / "replay_buffer.npz", pos=np.int64(rb.pos), full=np.bool_(rb.full), **arrays)
    np_rng = np.random.get_state()
    py_rng = random.getstate()
    state = {
        "format": CHECKPOINT_FORMATS[model.learner], "version": __version__,
        "num_timesteps": int(model.num_timesteps), "n_updates": int(model._n_updates),
        "episode_num": int(model._episode_num),
        "sampler": sampler_state_to_json(sampler.state_dict()),
        "numpy_rng": {"name": np_rng[0], "key": np_rng[1].tolist(), "pos": int(np_rng[2]),
                      "has_gauss": int(np_rng[3]), "cached_gaussian": float(np_rng[4])},
        "python_rng": [py_rng[0], list(py_rng[1]), py_rng[2]],
        "action_space_rng": model.action_space.np_random.bit_generator.state,
        "next_designs": _starting_designs(model),
    }
    (folder / "state.json").write_text(json.dumps(state), encoding="utf-8")
    manifest = {"format": CHECKPOINT_FORMATS[model.learner],
                "files": {f: _sha256(folder / f) for f in _checkpoint_files(model.learner)}}
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=1), encoding="utf-8")


_FORMAT_LEARNERS = {v: k for k, v in CHECKPOINT_FORMATS.items()}


def _checkpoint_files(learner: str) -> tuple[str, ...]:
    """The files (besides the manifest) of a checkpoint of ``learner``."""
    return LEARNER_FILES[learner], "replay_buffer.npz", "state.json"


def _vec_env(model):
    """The :class:`~softcrawl.envs.DesignVecEnv` under ``model``'s env wrappers (None if none)."""
    env = model.get_env()
    while env is not None and not hasattr(env, "starting_designs"):
        env = getattr(env, "venv", None)
    return env


def _starting_designs(model) -> list | None:
    """The designs of the episodes every env has just started (a checkpoint at an episode
    boundary), as lists; None if some env is inside an episode."""
    env = _vec_env(model)
    designs = None if env is None else env.starting_designs()
    return None if designs is None else [list(d) for d in designs]


def _rescue_checkpoint(name: str, model, sampler) -> Path | None:
    """Write checkpoint ``name`` into a fresh ``softcrawl-rescue-*`` folder of the system's
    temporary directory (another file system, often); its path, or None if that fails too."""
    try:
        rescue = Path(tempfile.mkdtemp(prefix="softcrawl-rescue-"))
    except OSError:
        return None
    try:
        (rescue / name).mkdir()
        _write_checkpoint(rescue / name, model, sampler)
        return rescue / name
    except OSError:
        shutil.rmtree(rescue, ignore_errors=True)
        return None


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


def sampler_state_to_json(state: dict) -> dict:
    """A :meth:`GibbsDesignSampler.state_dict` as JSON-ready data (exact: floats round-trip)."""
    dist = dict(state["distribution"])
    last = dist.get("last")
    dist["designs"] = [list(d) for d in dist["designs"]]
    dist["returns"] = [float(v) for v in np.asarray(dist["returns"], dtype=float)]
    dist["last"] = None if last is None else {k: (v.item() if isinstance(v, np.generic) else v)
                                              for k, v in dataclasses.asdict(last).items()}
    return {"distribution": dist, "rng": state["rng"], "timestep": int(state["timestep"])}


def sampler_state_from_json(data: dict) -> dict:
    """Inverse of :func:`sampler_state_to_json` (TypeError/KeyError/ValueError if malformed)."""
    from softcrawl.codesign.distribution import BetaUpdate

    dist = dict(data["distribution"])
    dist["designs"] = tuple(tuple(int(c) for c in d) for d in dist["designs"])
    dist["returns"] = np.array(dist["returns"], dtype=float)
    dist["last"] = None if dist.get("last") is None else BetaUpdate(**dist["last"])
    if not isinstance(data["rng"], dict):
        raise TypeError("sampler rng state is not an object")
    return {"distribution": dist, "rng": data["rng"], "timestep": int(data["timestep"])}
