"""Full-order scene runs of a reduction build, in parallel and resumable.

Each finished scene is one ``.npz`` (written atomically) next to a ``.json`` of the settings
that produced it; a later build reuses a scene only when those settings match exactly, so
an interrupted build resumes where it stopped and a changed setting is never mixed in.
"""

from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from softcrawl import __version__
from softcrawl.geometry.io import replace_atomically
from softcrawl.parallel import run_pool
from softcrawl.reduction.scenes import Scene, disk_displacements, leg_displacements, run_scene, scene_robot
from softcrawl.robot.assembly import RobotConfig
from softcrawl.robot.episode import Settling

#: RobotConfig fields a full-order run does not depend on (left out of its settings).
REDUCED_ONLY_FIELDS = ("reduced_disk",)
#: Fields of :class:`RobotConfig` added after runs were saved, and the value those runs used:
#: left out of a run's settings at that value, so the saved runs still match.
LATER_FIELDS = {"contact_max_iterations": 250, "leg_collision_spacing": 0.0}
#: Part -> its array in a snapshot run file.
SNAPSHOT_KEYS = {"leg": "u", "disk": "u_disk"}


def _settings(scene: Scene, config: RobotConfig, kind: str, record_every: int,
              perturbation: tuple[float, int] = (0.0, 0)) -> dict:
    """The settings of a run as they read back from its ``.json`` (tuples become lists), so
    that a finished run compares equal to its saved settings. Fields of ``config`` that only
    a reduced model reads are left out: they do not change a full-order run."""
    config = {k: v for k, v in dataclasses.asdict(config).items()
              if k not in REDUCED_ONLY_FIELDS and not (k in LATER_FIELDS and v == LATER_FIELDS[k])}
    settings = {"kind": kind, "scene": scene.describe(), "config": config, "settling": dataclasses.asdict(Settling()),
                "record_every": record_every, "version": __version__}
    if perturbation[0]:
        settings["perturbation"] = {"amplitude_mm": perturbation[0], "seed": perturbation[1]}
    if kind == "snapshots":
        settings["arrays"] = sorted(SNAPSHOT_KEYS.values())
    return json.loads(json.dumps(settings))


def _save(path: Path, arrays: dict, settings: dict) -> None:
    replace_atomically(path, lambda tmp: np.savez(tmp, **arrays))
    replace_atomically(path.with_suffix(".json"),
                       lambda tmp: tmp.write_text(json.dumps(settings, indent=1) + "\n", encoding="utf-8"))


def run_fom_scene(scene: Scene, config: RobotConfig, kind: str, record_every: int, path: str,
                  perturbation: tuple[float, int] = (0.0, 0)) -> str:
    """Run one scene on the full-order model and save it (worker entry point);
    ``perturbation``: ``(amplitude mm, seed)`` of the initial noise (:func:`run_scene`).

    ``kind == "snapshots"`` saves the leg-local displacements ``u`` ``(k * n_legs, n, 3)``
    and the disk's ``u_disk`` ``(k, n_disk, 3)``, float32 (mm); ``kind == "reference"`` saves
    all node positions ``positions`` ``(k, N, 3)`` float32 (mm), ``times`` (s) and
    ``reward_x`` (mm) for validation.

    Raises:
        RuntimeError: the full-order run diverged (no file is written).
    """
    robot = scene_robot(scene, config)
    rec = run_scene(robot, scene.animation, record_every=record_every, perturbation=perturbation[0],
                    seed=perturbation[1])
    if rec.diverged:
        raise RuntimeError(f"full-order scene {scene.name!r} diverged: {rec.diverged}")
    if kind == "snapshots":
        arrays = {"u": leg_displacements(robot, rec.positions), "u_disk": disk_displacements(robot, rec.positions)}
    else:
        arrays = {"positions": rec.positions, "times": rec.times, "reward_x": rec.reward_x}
    arrays["wall_seconds"] = np.array(rec.wall_seconds)
    arrays["steps"] = np.array(rec.steps + rec.settle_steps)  # all steps the wall time covers
    _save(Path(path), arrays, _settings(scene, config, kind, record_every, perturbation))
    return path


def _is_done(path: Path, settings: dict) -> bool:
    try:
        return path.exists() and json.loads(path.with_suffix(".json").read_text(encoding="utf-8")) == settings
    except (OSError, ValueError):
        return False


def run_fom_scenes(directory: str | os.PathLike, scenes: Sequence[Scene], config: RobotConfig, kind: str,
                   record_every: int = 2, workers: int | None = None, progress: bool = True,
                   perturbation: tuple[float, int] = (0.0, 0)) -> list[Path]:
    """Run (or reuse) the full-order runs of ``scenes`` into ``directory/<scene>.npz``.

    Args:
        directory: where the runs live (created).
        scenes: what to run.
        config: the full-order robot settings.
        kind: ``"snapshots"`` or ``"reference"`` (see :func:`run_fom_scene`).
        record_every: steps between recorded frames (reduction.md: every 0.02 s).
        workers: processes (default: the CPU count).
        progress: show a progress bar over scenes.
        perturbation: ``(amplitude mm, seed)`` of the initial noise of every run.

    Returns:
        The ``.npz`` paths, in scene order.
    """
    if kind not in ("snapshots", "reference"):
        raise ValueError(f"kind must be 'snapshots' or 'reference', got {kind!r}")
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    paths = [out / f"{s.name}.npz" for s in scenes]
    todo = [(s, config, kind, record_every, str(p), perturbation) for s, p in zip(scenes, paths)
            if not _is_done(p, _settings(s, config, kind, record_every, perturbation))]
    bar = tqdm(total=len(scenes), initial=len(scenes) - len(todo), unit="scene", desc=f"full-order {kind}",
               disable=not progress, dynamic_ncols=True)
    try:
        run_pool(run_fom_scene, workers, todo, lambda _: bar.update())
    finally:
        bar.close()
    return paths
