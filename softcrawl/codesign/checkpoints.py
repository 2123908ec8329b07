"""Checkpoints of a co-design run: written, checked, read back and rescued.

A checkpoint is the folder ``checkpoints/step-XXXXXXXXXX/`` of a run (layout:
:mod:`softcrawl.codesign.run`): the learner's state, ``learner.msgpack`` (the sbx learner,
format 2: flax msgpack of arrays) or ``model.pt`` (the torch learner, format 1: tensors only,
``torch.load(weights_only=True)``), ``replay_buffer.npz`` (``np.load(allow_pickle=False)``),
``state.json`` and ``manifest.json`` (``{"format": 2 or 1, "files": {name: sha256}}``); it is
complete iff the manifest's SHA-256 sums match. A checkpoint is read by the learner that wrote
it (its format), whatever the run's ``sac.learner`` says. The old pickle format
(``state.pkl``, ``replay_buffer.pkl``) is refused.

Checkpoints are written into ``step-*.tmp`` and renamed into place, ``latest`` is replaced
atomically; a missing, dangling or damaged ``latest`` falls back to the newest complete
checkpoint (said on stderr), as does a ``latest`` older than a complete checkpoint on disk, and
at least two complete checkpoints are kept. When the disk is full (or read-only) a checkpoint
that cannot be written into the run is written into a ``softcrawl-rescue-*`` folder of the
system's temporary directory instead and named in the error (move it into ``checkpoints/`` to
resume from it).

``manifest.json``, ``state.json`` and ``latest`` are read with :mod:`softcrawl.safeio` (regular
files, bounded size and nesting). ``state.json`` holds ``NaN``: the design distribution's
latest return of every design not tried yet (:class:`softcrawl.codesign.distribution.GibbsDesignDistribution`),
so it is parsed with NaN allowed; its integrity is the manifest's checksum.
"""

from __future__ import annotations

import dataclasses
import errno
import hashlib
import json
import os
import random
import re
import shutil
import tempfile
from pathlib import Path

import numpy as np

from softcrawl import __version__
from softcrawl.codesign.notes import note
from softcrawl.safeio import atomic_write_text, load_json, read_text

#: Checkpoint format of each learner and the file of its state (module docstring).
CHECKPOINT_FORMATS = {"sbx": 2, "torch": 1}
LEARNER_FILES = {"sbx": "learner.msgpack", "torch": "model.pt"}
_FORMAT_LEARNERS = {v: k for k, v in CHECKPOINT_FORMATS.items()}
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


class RunCheckpoints:
    """The checkpoint methods of :class:`softcrawl.codesign.run.Run` (that class's
    ``checkpoints_dir``, ``path``, ``_inside`` and ``design_space``)."""

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
            manifest = load_json(path / "manifest.json")
            files = manifest["files"]
            learner = _FORMAT_LEARNERS.get(manifest.get("format"))
            if learner is None or set(files) != set(checkpoint_files(learner)):
                return "unknown checkpoint format"
            for name in checkpoint_files(learner):
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
                name = read_text(ptr).strip()
            except (OSError, ValueError):
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

    def save_checkpoint(self, model, sampler, keep: int = 2) -> Path:
        """Write a complete checkpoint of ``model`` (a :class:`SplitLRSAC`) and ``sampler`` (a
        :class:`GibbsDesignSampler`) atomically, point ``latest`` at it and prune complete
        checkpoints beyond the newest ``max(keep, 2)``. Returns its folder.

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

    def checkpoint_learner(self, path: Path) -> str:
        """The ``sac.learner`` that wrote complete checkpoint ``path`` (``"sbx"`` or ``"torch"``,
        from its format).

        Raises:
            ValueError: not a complete checkpoint of this run.
        """
        why = self.check_checkpoint(path)
        if why is not None:
            raise ValueError(f"{path}: {why}")
        return _FORMAT_LEARNERS[load_json(Path(path) / "manifest.json")["format"]]

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
        space = self.design_space()
        try:
            state = load_json(Path(path) / "state.json", allow_nan=True)
            state["sampler"] = sampler_state_from_json(state["sampler"])
            for key in ("num_timesteps", "n_updates", "episode_num"):
                state[key] = int(state[key])
            nxt = state.get("next_designs")  # absent in checkpoints written before it existed
            state["next_designs"] = None if nxt is None else [space.validate_design(d) for d in nxt]
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
                "files": {f: _sha256(folder / f) for f in checkpoint_files(model.learner)}}
    (folder / "manifest.json").write_text(json.dumps(manifest, indent=1), encoding="utf-8")


def checkpoint_files(learner: str) -> tuple[str, ...]:
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
