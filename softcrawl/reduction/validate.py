"""Validating a reduction against the full-order model on held-out scenes (the paper's
appendix protocol, reduction.md "Validating a reduction").

Per scene: the mean node position error (L2 distance of each node between the reduced and
the full-order run, averaged over all nodes of the robot and all recorded frames, mm), the
mean deformation error (the same after the best rigid fit of each body, frame by frame), the
mean disk top-centre trajectory error (mm), the reward (+x of the disk top centre, cm) of
both and its error, and the wall time per step of both models (settling included).

The reference is the exact full-order model (``refactor_every=1``). A crawler's stick-slip
motion is chaotic: full-order runs whose initial node positions differ by round-off-sized
noise (``perturbation``, 1e-6 mm) end millimetres apart. So each scene is also run by an
*ensemble* of such perturbed full-order runs, and reports their distance to the reference
(the chaos floor: no model, the full one included, can be closer to the reference than
that on average) and the spread of their rewards: a reduced reward inside the ensemble's
range is as close as the full model's own reward is to itself. The reduced model gets the
same ensemble (its noise projected on each leg's basis): its spread says how much of a
single reduced run's error is its own sensitivity to round-off (measured larger than the
full model's). The deformation error separates the reduction's approximation from rigid
drift.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import DesignSpace
from softcrawl.reduction.floating import rigid_fit_rotation
from softcrawl.reduction.model import RobotReduction
from softcrawl.reduction.runs import run_fom_scenes
from softcrawl.reduction.scenes import Scene, reduced_scene_robot, run_scene, validation_scenes
from softcrawl.robot.assembly import RobotConfig
from softcrawl.robot.episode import MM_PER_CM

#: Engines of the reduced runs: the CPU reduced solver, the JAX engine (:mod:`softcrawl.jaxsim`).
ENGINES = ("cpu", "jax")


def fom_references(workdir: str | os.PathLike, config: RobotConfig, scenes: tuple[Scene, ...],
                   record_every: int = 2, workers: int | None = None, progress: bool = True,
                   perturbation: float = 0.0, seed: int = 0) -> list[Path]:
    """Exact full-order runs of the validation scenes into ``workdir/reference`` (or, with an
    initial ``perturbation`` (mm) drawn by ``seed``, ``workdir/perturbed<seed>``), reused
    when their settings match."""
    fom = dataclasses.replace(config, model="full", reduction=None, refactor_every=1)
    name = f"perturbed{seed}" if perturbation else "reference"
    return run_fom_scenes(Path(workdir) / name, scenes, fom, "reference", record_every, workers, progress,
                          (perturbation, seed))


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


def _node_distances(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``(T, N)`` distances between the nodes of two runs ``(T', N, 3)`` over their common
    frames (``T = min(T', T'')``), mm."""
    k = min(len(a), len(b))
    return np.linalg.norm(a[:k] - b[:k], axis=2)


def _errors(a: np.ndarray, b: np.ndarray, bodies: list[slice], node: int) -> dict:
    err = _node_distances(a, b)
    return {"mean_node_error_mm": float(err.mean()), "max_node_error_mm": float(err.max()),
            "mean_deformation_error_mm": float(deformation_error(a, b, bodies).mean()),
            "mean_trajectory_error_mm": float(err[:, node].mean())}


def _reward(positions: np.ndarray, node: int) -> float:
    """+x displacement of ``node`` over ``positions`` ``(k, N, 3)``, cm."""
    return float((positions[-1, node, 0] - positions[0, node, 0]) / MM_PER_CM)


def _reduced_recording(config: RobotConfig, record_every: int, reduced_dt: float | None,
                       rid_dtype: str = "float64", contact_max_iterations: int | None = None,
                       leg_collision_spacing: float = 0.0) -> tuple[RobotConfig, int, int]:
    """The reduced runs' config, their frame spacing (steps) and the stride over the reference's
    frames for a reduced time step ``reduced_dt`` (s; None: the reference's), so that the frames
    compared fall on the same times, with the RID products in ``rid_dtype`` and the Gauss-Seidel
    sweep limit ``contact_max_iterations`` (None: ``config``'s) and the legs' contact points
    ``leg_collision_spacing`` (mm; 0: every surface node, the reference). A step that divides
    the reference's frame spacing is recorded every few steps against every reference frame; a
    step that is a multiple of it is recorded every step against every few reference frames.

    Raises:
        ValueError: ``reduced_dt`` neither divides nor is a multiple of the reference's frame
            spacing.
    """
    config = dataclasses.replace(config, rid_dtype=rid_dtype,
                                 contact_max_iterations=contact_max_iterations or config.contact_max_iterations,
                                 leg_collision_spacing=float(leg_collision_spacing))
    if reduced_dt is None or reduced_dt == config.dt:
        return config, record_every, 1
    frame = config.dt * record_every
    spacing, stride = frame / reduced_dt, reduced_dt / frame
    whole = lambda r: abs(r - round(r)) < 1e-9 and round(r) >= 1
    if not (reduced_dt > 0 and (whole(spacing) or whole(stride))):
        raise ValueError(f"the reduced time step must divide or be a multiple of the reference frame spacing "
                         f"{frame:g} s, got {reduced_dt!r} s")
    reduced = dataclasses.replace(config, dt=float(reduced_dt))
    return (reduced, int(round(spacing)), 1) if whole(spacing) else (reduced, 1, int(round(stride)))


def compare_scene(reduction: RobotReduction, config: RobotConfig, scene: Scene, reference: Path,
                  record_every: int = 2, ensemble: list[Path] = (), perturbation: float = 0.0,
                  reduced_dt: float | None = None, rid_dtype: str = "float64",
                  contact_max_iterations: int | None = None, leg_collision_spacing: float = 0.0,
                  engine: str = "cpu") -> dict:
    """Run ``scene`` with the reduction and compare it with its full-order ``reference`` run
    (recorded every ``record_every`` steps of ``config.dt``); ``reduced_dt``: the reduced
    model's time step (s; None: ``config.dt``), frames compared at the same times;
    ``rid_dtype``: the precision of its RID products and ``contact_max_iterations`` its
    Gauss-Seidel sweep limit (:class:`RobotConfig`; None: ``config``'s), ``leg_collision_spacing``
    its legs' contact points (mm, :attr:`RobotConfig.leg_collision_spacing`). ``engine``:
    ``"cpu"`` the reduced solver, ``"jax"`` the JAX engine (:func:`softcrawl.jaxsim.scenes.run_scene`,
    all of it in ``rid_dtype``; ``jax_enable_x64`` must be on for float64; its wall time includes
    compiling; no ensemble).

    Given perturbed full-order runs (``ensemble``), also their mean distance to the reference
    (keys ``floor_*``) and their rewards (``ensemble_rewards_cm``, the reference's first); and
    as many reduced runs perturbed by ``perturbation`` (mm, seeds 1, 2, ...): their rewards
    (``reduced_ensemble_rewards_cm``, the unperturbed run's first), their mean node distance
    to the unperturbed reduced run (``reduced_spread_mm``) and their mean node errors against
    the reference (``reduced_ensemble_node_errors_mm``).

    A reduced run that diverges fails its scene: its errors are infinite and its reward NaN (the
    frames before the divergence are not compared; without this a run that diverged early was
    scored on its first frames only, and one that diverged while settling crashed the report).

    Raises:
        ValueError: a reference was recorded on another mesh or at other times.
    """
    ref = np.load(reference)
    reduced_config, record_every, stride = _reduced_recording(config, record_every, reduced_dt, rid_dtype,
                                                              contact_max_iterations, leg_collision_spacing)
    robot = reduced_scene_robot(scene, reduced_config, reduction)
    if engine == "jax":
        from softcrawl.jaxsim.scenes import run_scene as run_jax_scene

        rec = run_jax_scene(robot, scene.animation, record_every=record_every, precision=rid_dtype)
    else:
        rec = run_scene(robot, scene.animation, record_every=record_every)
    fom_x = ref["positions"][::stride].astype(float)
    k = len(rec.positions)
    if rec.positions.shape[1:] != fom_x.shape[1:] or k > len(fom_x):
        raise ValueError(f"reference {reference} does not match the reduction's robot (mesh or duration differ)")
    bodies = [robot.model.body_slice(i) for i in range(len(robot.model.bodies))]
    node = robot.reward_node
    rom_x = rec.positions.astype(float)
    if rec.diverged:  # a diverged run fails the scene: its frames before the divergence do not count
        errors = dict.fromkeys(("mean_node_error_mm", "max_node_error_mm", "mean_deformation_error_mm",
                                "mean_trajectory_error_mm"), float("inf"))
        reward_rom, reward_fom = float("nan"), _reward(fom_x, node)
    else:
        errors = _errors(rom_x, fom_x[:k], bodies, node)
        reward_rom, reward_fom = _reward(rom_x, node), _reward(fom_x[:k], node)
    steps_fom = int(ref["steps"])
    row = {"scene": scene.name, "engine": engine, "diverged": rec.diverged, "frames": k, **errors,
           "reward_full_cm": reward_fom, "reward_reduced_cm": reward_rom,
           "reward_error_cm": abs(reward_rom - reward_fom),
           "seconds_per_step_full": float(ref["wall_seconds"]) / steps_fom,
           "seconds_per_step_reduced": rec.wall_seconds / (rec.steps + rec.settle_steps),
           "seconds_per_sim_second_reduced": rec.wall_seconds / ((rec.steps + rec.settle_steps) * reduced_config.dt)}
    if ensemble and not rec.diverged:
        members = [np.load(p)["positions"][::stride].astype(float) for p in ensemble]
        if any(x.shape != fom_x.shape for x in members):
            raise ValueError(f"the perturbed runs do not match {reference} (mesh or duration differ)")
        floors = [_errors(x[:k], fom_x[:k], bodies, node) for x in members]
        row.update({f"floor_{key}": float(np.mean([f[key] for f in floors])) for key in floors[0]})
        rewards = [reward_fom] + [_reward(x[:k], node) for x in members]
        row.update(ensemble_rewards_cm=rewards, reward_in_ensemble=bool(min(rewards) <= reward_rom <= max(rewards)))
        reduced = [run_scene(robot, scene.animation, record_every=record_every, perturbation=perturbation,
                             seed=seed).positions[:k].astype(float) for seed in range(1, len(ensemble) + 1)]
        row.update(reduced_ensemble_rewards_cm=[reward_rom] + [_reward(x, node) for x in reduced],
                   reduced_spread_mm=float(np.mean([_node_distances(x, rom_x).mean() for x in reduced])),
                   reduced_ensemble_node_errors_mm=[row["mean_node_error_mm"]] + [
                       float(_node_distances(x, fom_x).mean()) for x in reduced])
    return row


def validate_reduction(reduction: RobotReduction, config: RobotConfig, workdir: str | os.PathLike,
                       scenes: tuple[Scene, ...] | None = None, record_every: int = 2,
                       workers: int | None = None, progress: bool = True, ensemble: int = 3,
                       perturbation: float = 1e-6, reduced_dt: float | None = None,
                       rid_dtype: str = "float64", contact_max_iterations: int | None = None,
                       leg_collision_spacing: float = 0.0, engine: str = "cpu",
                       space: DesignSpace = DEFAULT_SPACE) -> dict:
    """Compare ``reduction`` with the exact full-order model on the held-out scenes.

    Args:
        scenes: the scenes (default: ``space``'s :func:`validation_scenes`).
        space: the design space whose held-out scenes are run (when ``scenes`` is None).
        reduced_dt: the reduced model's time step, s (None: ``config.dt``); the references stay
            exact full-order runs at ``config.dt`` (the reference 0.01 s), so this measures what a
            larger step costs in accuracy (the settings study).
        rid_dtype: the precision of the reduced model's RID products (``"float32"``: what single
            precision costs in accuracy).
        contact_max_iterations: the reduced model's Gauss-Seidel sweep limit per chunk (None:
            ``config``'s): what a cheaper contact solve costs in accuracy.
        leg_collision_spacing: the reduced model's leg contact points, mm (0: every surface
            node; :attr:`RobotConfig.leg_collision_spacing`): what coarser contact costs in
            accuracy. The references keep every surface node.
        ensemble: perturbed full-order runs per scene (the chaos floor and reward spread; 0:
            none), and as many perturbed reduced runs.
        perturbation: their initial noise amplitude, mm.
        engine: the reduced model's engine, ``"cpu"`` or ``"jax"`` (:func:`compare_scene`).

    Raises:
        ValueError: a negative ensemble, an ensemble without a positive perturbation, an
            unknown engine, or an ensemble with the JAX engine.

    Returns:
        ``{"scenes": [per-scene dicts of compare_scene], "mean_node_error_mm",
        "mean_deformation_error_mm", "max_scene_node_error_mm", "floor_mean_node_error_mm"
        and "floor_mean_deformation_error_mm" (with an ensemble),
        "mean_seconds_per_step_full/reduced", "speedup", sizes}``.
    """
    if ensemble < 0 or (ensemble and not perturbation > 0):
        raise ValueError(f"an ensemble needs a positive perturbation, got ensemble={ensemble}, "
                         f"perturbation={perturbation}")
    if engine not in ENGINES or (engine == "jax" and ensemble):
        raise ValueError(f"engine must be one of {ENGINES} (the JAX engine without an ensemble), got "
                         f"engine={engine!r}, ensemble={ensemble}")
    scenes = scenes or validation_scenes(space=space)
    refs = fom_references(workdir, config, scenes, record_every, workers, progress)
    members = [fom_references(workdir, config, scenes, record_every, workers, progress, perturbation, seed)
               for seed in range(1, ensemble + 1)]
    warm = scenes[0]  # compile the reduced kernels before anything is timed (numba's cache may be cold)
    if engine == "cpu":
        run_scene(reduced_scene_robot(warm, config, reduction), warm.animation, duration=config.dt)
    rows = [compare_scene(reduction, config, s, r, record_every, [m[i] for m in members], perturbation, reduced_dt,
                          rid_dtype, contact_max_iterations, leg_collision_spacing, engine)
            for i, (s, r) in enumerate(tqdm(list(zip(scenes, refs)), desc="reduced runs", unit="scene",
                                            disable=not progress))]
    full = float(np.mean([r["seconds_per_step_full"] for r in rows]))
    red = float(np.mean([r["seconds_per_step_reduced"] for r in rows]))
    red_sim = float(np.mean([r["seconds_per_sim_second_reduced"] for r in rows]))
    means = {key: float(np.mean([r.get(key, np.nan) for r in rows])) for key in
             ("mean_node_error_mm", "mean_deformation_error_mm", "floor_mean_node_error_mm",
              "floor_mean_deformation_error_mm") if key in rows[0]}
    return {"scenes": rows, **means, "engine": engine, "ensemble": ensemble, "perturbation_mm": perturbation,
            "max_scene_node_error_mm": float(max(r["mean_node_error_mm"] for r in rows)),
            "mean_seconds_per_step_full": full, "mean_seconds_per_step_reduced": red, "speedup": full / red,
            "reduced_dt": reduced_dt or config.dt, "rid_dtype": rid_dtype,
            "contact_max_iterations": contact_max_iterations or config.contact_max_iterations,
            "leg_collision_spacing": float(leg_collision_spacing),
            "mean_seconds_per_sim_second_reduced": red_sim,
            **reduction_sizes(reduction)}


def reduction_sizes(reduction: RobotReduction) -> dict:
    """``{"n_modes", "rid_tetrahedra", "rid_triangles"}`` of the leg, and ``disk_n_modes``,
    ``disk_rid_tetrahedra`` with a disk part."""
    leg, disk = reduction.leg, reduction.disk
    out = {"n_modes": leg.n_modes, "rid_tetrahedra": len(leg.tet_rid), "rid_triangles": len(leg.tri_rid)}
    if disk is not None:
        out.update(disk_n_modes=disk.n_modes, disk_rid_tetrahedra=len(disk.tet_rid))
    return out
