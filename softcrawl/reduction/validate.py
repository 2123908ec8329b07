"""Validating a reduction against the full-order model on held-out scenes (the paper's
appendix protocol, reduction.md "Validating a reduction").

Per scene: the mean node position error (L2 distance of each node between the reduced and
the full-order run, averaged over all nodes of the robot and all recorded frames, mm), the
mean disk top-centre trajectory error (mm), the reward (+x of the disk top centre, cm) of
both and its error, and the wall time per step of both models (settling included).
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from softcrawl.reduction.model import PartReduction
from softcrawl.reduction.runs import run_fom_scenes
from softcrawl.reduction.scenes import Scene, run_scene, scene_robot, validation_scenes
from softcrawl.robot.assembly import RobotConfig, reduce_legs
from softcrawl.robot.episode import MM_PER_CM, SETTLE_STEPS


def fom_references(workdir: str | os.PathLike, config: RobotConfig, scenes: tuple[Scene, ...],
                   record_every: int = 2, workers: int | None = None, progress: bool = True,
                   refactor_every: int = 5) -> list[Path]:
    """Full-order runs of the validation scenes (reused when their settings match)."""
    fom = dataclasses.replace(config, model="full", reduction=None, refactor_every=refactor_every)
    return run_fom_scenes(Path(workdir) / "reference", scenes, fom, "reference", record_every, workers, progress)


def compare_scene(part: PartReduction, config: RobotConfig, scene: Scene, reference: Path,
                  record_every: int = 2) -> dict:
    """Run ``scene`` with the reduction and compare it with its full-order ``reference`` run.

    Raises:
        ValueError: the reference was recorded on another mesh or at other times.
    """
    ref = np.load(reference)
    robot = reduce_legs(scene_robot(scene, dataclasses.replace(config, model="full", reduction=None),
                                    leg_mesh=part.mesh), part)
    rec = run_scene(robot, scene.animation, record_every=record_every)
    fom_x = ref["positions"]
    k = len(rec.positions)
    if rec.positions.shape[1:] != fom_x.shape[1:] or k > len(fom_x):
        raise ValueError(f"reference {reference} does not match the reduction's robot (mesh or duration differ)")
    err = np.linalg.norm(rec.positions.astype(float) - fom_x[:k], axis=2)
    node = robot.reward_node
    traj = err[:, node]
    reward_rom = (rec.positions[-1, node, 0] - rec.positions[0, node, 0]) / MM_PER_CM
    reward_fom = (fom_x[k - 1, node, 0] - fom_x[0, node, 0]) / MM_PER_CM
    steps_fom = int(ref["steps"]) + SETTLE_STEPS
    return {
        "scene": scene.name, "diverged": rec.diverged, "frames": k,
        "mean_node_error_mm": float(err.mean()), "max_node_error_mm": float(err.max()),
        "mean_trajectory_error_mm": float(traj.mean()),
        "reward_full_cm": float(reward_fom), "reward_reduced_cm": float(reward_rom),
        "reward_error_cm": float(abs(reward_rom - reward_fom)),
        "seconds_per_step_full": float(ref["wall_seconds"]) / steps_fom,
        "seconds_per_step_reduced": rec.wall_seconds / (rec.steps + SETTLE_STEPS),
    }


def validate_reduction(part: PartReduction, config: RobotConfig, workdir: str | os.PathLike,
                       scenes: tuple[Scene, ...] | None = None, record_every: int = 2,
                       workers: int | None = None, progress: bool = True) -> dict:
    """Compare ``part`` with the full-order model on the held-out scenes.

    Returns:
        ``{"scenes": [per-scene dicts of compare_scene], "mean_node_error_mm",
        "max_scene_node_error_mm", "mean_seconds_per_step_full/reduced", "speedup"}``.
    """
    scenes = scenes or validation_scenes()
    refs = fom_references(workdir, config, scenes, record_every, workers, progress)
    rows = [compare_scene(part, config, s, r, record_every)
            for s, r in tqdm(list(zip(scenes, refs)), desc="reduced runs", unit="scene", disable=not progress)]
    full = float(np.mean([r["seconds_per_step_full"] for r in rows]))
    red = float(np.mean([r["seconds_per_step_reduced"] for r in rows]))
    return {"scenes": rows, "mean_node_error_mm": float(np.mean([r["mean_node_error_mm"] for r in rows])),
            "max_scene_node_error_mm": float(max(r["mean_node_error_mm"] for r in rows)),
            "mean_seconds_per_step_full": full, "mean_seconds_per_step_reduced": red, "speedup": full / red,
            "n_modes": part.n_modes, "rid_tetrahedra": len(part.tet_rid), "rid_triangles": len(part.tri_rid)}
