"""Validating a reduction against the full-order model on held-out scenes (the paper's
appendix protocol, reduction.md "Validating a reduction").

Per scene: the mean node position error (L2 distance of each node between the reduced and
the full-order run, averaged over all nodes of the robot and all recorded frames, mm), the
mean deformation error (the same after the best rigid fit of each body, frame by frame), the
mean disk top-centre trajectory error (mm), the reward (+x of the disk top centre, cm) of
both and its error, and the wall time per step of both models (settling included).

The reference is the exact full-order model (``refactor_every=1``). A crawler's stick-slip
motion is sensitive: two *full-order* runs that differ only in solver settings drift apart
by millimetres. So each scene also reports that floor, the distance between the exact
reference and a full-order run reusing factorizations (``floor_refactor_every``): reduced
errors near the floor are as good as the full model's own solver sensitivity, and the
deformation error separates the reduction's approximation from rigid drift.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from softcrawl.reduction.floating import rigid_fit_rotation
from softcrawl.reduction.model import RobotReduction
from softcrawl.reduction.runs import run_fom_scenes
from softcrawl.reduction.scenes import Scene, reduced_scene_robot, run_scene, validation_scenes
from softcrawl.robot.assembly import RobotConfig
from softcrawl.robot.episode import MM_PER_CM, SETTLE_STEPS


def fom_references(workdir: str | os.PathLike, config: RobotConfig, scenes: tuple[Scene, ...],
                   record_every: int = 2, workers: int | None = None, progress: bool = True,
                   refactor_every: int = 1) -> list[Path]:
    """Full-order runs of the validation scenes into ``workdir/reference`` (exact solver) or
    ``workdir/reference_refactor<k>``, reused when their settings match."""
    fom = dataclasses.replace(config, model="full", reduction=None, refactor_every=refactor_every)
    name = "reference" if refactor_every == 1 else f"reference_refactor{refactor_every}"
    return run_fom_scenes(Path(workdir) / name, scenes, fom, "reference", record_every, workers, progress)


def deformation_error(a: np.ndarray, b: np.ndarray, bodies: list[slice]) -> np.ndarray:
    """Node distances after the best rigid fit of each body of ``a`` onto ``b``, per frame.

    Args:
        a, b: ``(T, N, 3)`` node positions of two runs of one robot, mm.
        bodies: the node slice of each body.

    Returns:
        ``(T, N)`` distances, mm. The fit is Kabsch's (least-squares rotation about the
        centroids, reflections excluded: :func:`rigid_fit_rotation`).
    """
    out = np.empty(a.shape[:2])
    for sl in bodies:
        A = a[:, sl] - a[:, sl].mean(1, keepdims=True)
        B = b[:, sl] - b[:, sl].mean(1, keepdims=True)
        R = rigid_fit_rotation(B, A, np.full(A.shape[1], 1.0 / A.shape[1]))  # R A_n ~ B_n
        out[:, sl] = np.linalg.norm(A @ R.swapaxes(-1, -2) - B, axis=2)
    return out


def _errors(a: np.ndarray, b: np.ndarray, bodies: list[slice], node: int) -> dict:
    err = np.linalg.norm(a - b, axis=2)
    return {"mean_node_error_mm": float(err.mean()), "max_node_error_mm": float(err.max()),
            "mean_deformation_error_mm": float(deformation_error(a, b, bodies).mean()),
            "mean_trajectory_error_mm": float(err[:, node].mean())}


def compare_scene(reduction: RobotReduction, config: RobotConfig, scene: Scene, reference: Path,
                  record_every: int = 2, floor_reference: Path | None = None) -> dict:
    """Run ``scene`` with the reduction and compare it with its full-order ``reference`` run
    (and, given ``floor_reference``, that run with the reference: keys ``floor_*``).

    Raises:
        ValueError: a reference was recorded on another mesh or at other times.
    """
    ref = np.load(reference)
    robot = reduced_scene_robot(scene, config, reduction)
    rec = run_scene(robot, scene.animation, record_every=record_every)
    fom_x = ref["positions"].astype(float)
    k = len(rec.positions)
    if rec.positions.shape[1:] != fom_x.shape[1:] or k > len(fom_x):
        raise ValueError(f"reference {reference} does not match the reduction's robot (mesh or duration differ)")
    bodies = [robot.model.body_slice(i) for i in range(len(robot.model.bodies))]
    node = robot.reward_node
    reward_rom = (rec.positions[-1, node, 0] - rec.positions[0, node, 0]) / MM_PER_CM
    reward_fom = (fom_x[k - 1, node, 0] - fom_x[0, node, 0]) / MM_PER_CM
    steps_fom = int(ref["steps"]) + SETTLE_STEPS
    row = {"scene": scene.name, "diverged": rec.diverged, "frames": k,
           **_errors(rec.positions.astype(float), fom_x[:k], bodies, node),
           "reward_full_cm": float(reward_fom), "reward_reduced_cm": float(reward_rom),
           "reward_error_cm": float(abs(reward_rom - reward_fom)),
           "seconds_per_step_full": float(ref["wall_seconds"]) / steps_fom,
           "seconds_per_step_reduced": rec.wall_seconds / (rec.steps + SETTLE_STEPS)}
    if floor_reference is not None:
        other = np.load(floor_reference)["positions"].astype(float)
        if other.shape != fom_x.shape:
            raise ValueError(f"{floor_reference} does not match {reference} (mesh or duration differ)")
        row.update({f"floor_{key}": v for key, v in _errors(other[:k], fom_x[:k], bodies, node).items()})
        row["floor_reward_cm"] = float((other[k - 1, node, 0] - other[0, node, 0]) / MM_PER_CM)
    return row


def validate_reduction(reduction: RobotReduction, config: RobotConfig, workdir: str | os.PathLike,
                       scenes: tuple[Scene, ...] | None = None, record_every: int = 2,
                       workers: int | None = None, progress: bool = True,
                       floor_refactor_every: int | None = 5) -> dict:
    """Compare ``reduction`` with the exact full-order model on the held-out scenes.

    Args:
        floor_refactor_every: also run the full model with this factorization reuse and
            report its distance to the exact one (the sensitivity floor); None: skip.

    Raises:
        ValueError: ``floor_refactor_every`` below 2 (the floor run would be the reference).

    Returns:
        ``{"scenes": [per-scene dicts of compare_scene], "mean_node_error_mm",
        "mean_deformation_error_mm", "max_scene_node_error_mm", "floor_mean_node_error_mm"
        (with a floor), "mean_seconds_per_step_full/reduced", "speedup", sizes}``.
    """
    if floor_refactor_every is not None and floor_refactor_every < 2:
        raise ValueError(f"floor_refactor_every must be >= 2 (1 is the exact reference), got {floor_refactor_every}")
    scenes = scenes or validation_scenes()
    refs = fom_references(workdir, config, scenes, record_every, workers, progress)
    floors = (fom_references(workdir, config, scenes, record_every, workers, progress, floor_refactor_every)
              if floor_refactor_every else [None] * len(scenes))
    rows = [compare_scene(reduction, config, s, r, record_every, f)
            for s, r, f in tqdm(list(zip(scenes, refs, floors)), desc="reduced runs", unit="scene",
                                disable=not progress)]
    full = float(np.mean([r["seconds_per_step_full"] for r in rows]))
    red = float(np.mean([r["seconds_per_step_reduced"] for r in rows]))
    means = {key: float(np.mean([r[key] for r in rows])) for key in
             ("mean_node_error_mm", "mean_deformation_error_mm", "floor_mean_node_error_mm",
              "floor_mean_deformation_error_mm") if key in rows[0]}
    return {"scenes": rows, **means,
            "max_scene_node_error_mm": float(max(r["mean_node_error_mm"] for r in rows)),
            "mean_seconds_per_step_full": full, "mean_seconds_per_step_reduced": red, "speedup": full / red,
            **reduction_sizes(reduction)}


def reduction_sizes(reduction: RobotReduction) -> dict:
    """``{"n_modes", "rid_tetrahedra", "rid_triangles"}`` of the leg, and ``disk_n_modes``,
    ``disk_rid_tetrahedra`` with a disk part."""
    leg, disk = reduction.leg, reduction.disk
    out = {"n_modes": leg.n_modes, "rid_tetrahedra": len(leg.tet_rid), "rid_triangles": len(leg.tri_rid)}
    if disk is not None:
        out.update(disk_n_modes=disk.n_modes, disk_rid_tetrahedra=len(disk.tet_rid))
    return out
