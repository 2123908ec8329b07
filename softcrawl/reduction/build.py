"""The reduction build: full-order snapshots -> POD basis -> Galerkin runs -> ECSW RID.

``softcrawl reduce build`` calls :func:`build_reduction`. Every phase shows a progress bar;
the full-order runs are saved per scene and reused after an interruption
(:mod:`softcrawl.reduction.runs`).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm.auto import tqdm

from softcrawl.geometry.pneunet import PneuNetParams, pneunet_mesh
from softcrawl.parallel import PeakMemory, run_pool
from softcrawl.reduction.ecsw import GramAccumulator, ecsw_weights
from softcrawl.reduction.kernels import reduced_element_terms
from softcrawl.reduction.model import PartReduction, ReducedBody
from softcrawl.reduction.pod import PODBasis, pod_basis
from softcrawl.reduction.runs import run_fom_scenes
from softcrawl.reduction.scenes import Scene, run_scene, scene_robot, training_scenes
from softcrawl.robot.assembly import RobotConfig, reduce_legs


@dataclass(frozen=True)
class BuildSettings:
    """Settings of a reduction build.

    Attributes:
        n_designs: training designs (slot subsets, each leg on its own channel).
        sizes: leg counts of the training designs, cycled.
        state_seconds: time per Gray-code pressure state of the training animation, s.
        tol_modes: POD tail-energy tolerance (reduction.md; reference 0.0032).
        tol_gie: ECSW relative residual tolerance (reference 0.001).
        rigid: rigid modes, ``"translations"`` (reference) or ``"rigid"`` (+ rotations).
        record_every: steps between snapshots (2 = every 0.02 s, as the reference).
        ecsw_scenes: training scenes re-run with the Galerkin ROM for the ECSW training set.
        ecsw_every: steps between ECSW training states in those runs.
        fom_refactor_every: factorization reuse of the full-order snapshot runs.
    """

    n_designs: int = 8
    sizes: tuple[int, ...] = (3, 4)
    state_seconds: float = 0.3
    tol_modes: float = 0.0032
    tol_gie: float = 0.001
    rigid: str = "translations"
    record_every: int = 2
    ecsw_scenes: int = 4
    ecsw_every: int = 10
    fom_refactor_every: int = 5

    def scenes(self) -> tuple[Scene, ...]:
        return training_scenes(self.n_designs, self.sizes, state_seconds=self.state_seconds)


def load_snapshots(paths: list[Path]) -> np.ndarray:
    """``(S, n, 3)`` leg-local displacement snapshots pooled from snapshot run files."""
    return np.concatenate([np.load(p)["u"] for p in paths])


def element_reduced_forces(rb: ReducedBody, x: np.ndarray) -> list[np.ndarray]:
    """Per RID element family, ``(E, m)`` reduced element forces ``Phi_e^T f_e(x)`` (mN) at
    body positions ``x`` ``(n, 3)``, unweighted: one column block of the ECSW matrix ``G``."""
    out = []
    for ef in rb.element_factors:
        E, r = len(ef.conn), ef.factors.shape[1]
        Z, s = np.empty((E * r, rb.n_modes)), np.empty(E * r)
        reduced_element_terms(x, ef.conn, ef.rest, ef.factors, ef.frames, np.ones(E), rb.basis, Z, s)
        out.append(-(Z * s[:, None]).reshape(E, r, -1).sum(axis=1))
    return out


def galerkin_states(scene: Scene, config: RobotConfig, part: PartReduction, every: int) -> tuple[str, np.ndarray]:
    """Run a scene with the Galerkin ROM (all elements) and return its name and
    ``(k, n_legs, n, 3)`` leg positions every ``every`` steps (worker entry point).

    Raises:
        RuntimeError: the Galerkin run diverged.
    """
    robot = reduce_legs(scene_robot(scene, config, leg_mesh=part.mesh), part)
    rec = run_scene(robot, scene.animation, record_every=every)
    if rec.diverged:
        raise RuntimeError(f"Galerkin ROM run of {scene.name!r} diverged: {rec.diverged}")
    return scene.name, np.stack([rec.positions[:, robot.model.body_slice(leg.body)] for leg in robot.legs], axis=1)


def ecsw_grams(states: list[tuple[ReducedBody, np.ndarray]], progress: bool = True) -> list[GramAccumulator]:
    """Gram matrices ``G^T G`` of the tetrahedra and the membrane triangles from training states.

    Args:
        states: ``(Galerkin reduced body (all elements), (k, n, 3) positions)`` pairs; all
            states of all legs are pooled.
    """
    grams = None
    total = sum(len(x) for _, x in states)
    with tqdm(total=total, desc="ECSW training matrix", unit="state", disable=not progress, dynamic_ncols=True) as bar:
        for rb, xs in states:
            for x in xs:
                blocks = element_reduced_forces(rb, np.asarray(x, float))
                if grams is None:
                    grams = [GramAccumulator(len(b)) for b in blocks]
                for g, b in zip(grams, blocks):
                    g.add(b)
                bar.update()
    return grams


def build_reduction(workdir: str | os.PathLike, config: RobotConfig = RobotConfig(),
                    settings: BuildSettings = BuildSettings(), workers: int | None = None,
                    progress: bool = True) -> PartReduction:
    """Build the leg reduction for ``config`` (its leg mesh size and materials).

    Args:
        workdir: where snapshot runs are kept (reused when the settings match).
        config: the robot settings (``model`` is ignored: snapshots are full-order).
        settings: the build settings.
        workers: parallel processes for the scene runs (default: CPU count).
        progress: progress bars.

    Returns:
        The :class:`PartReduction`; ``metadata`` holds the settings, sizes, tolerances
        reached, the wall time of each phase and the peak resident memory
        (``peak_rss_mb``: of the main process, and of it with its workers, MB).
    """
    return build_reductions(workdir, config, settings, (settings.tol_gie,), workers, progress)[0]


def build_reductions(workdir: str | os.PathLike, config: RobotConfig, settings: BuildSettings,
                     tol_gies: tuple[float, ...], workers: int | None = None,
                     progress: bool = True) -> list[PartReduction]:
    """:func:`build_reduction` for several ECSW tolerances sharing one basis and one ECSW
    training set (``settings.tol_gie`` is replaced by each of ``tol_gies``)."""
    with PeakMemory() as memory:
        parts = _build(workdir, config, settings, tol_gies, workers, progress)
    for part in parts:
        part.metadata["peak_rss_mb"] = {"main": round(memory.main_mb), "with_workers": round(memory.total_mb)}
    return parts


def _build(workdir, config: RobotConfig, settings: BuildSettings, tol_gies: tuple[float, ...],
           workers: int | None, progress: bool) -> list[PartReduction]:
    t0 = time.perf_counter()
    workdir = Path(workdir)
    fom = dataclasses.replace(config, model="full", reduction=None, refactor_every=settings.fom_refactor_every)
    scenes = settings.scenes()
    paths = run_fom_scenes(workdir / "snapshots", scenes, fom, "snapshots", settings.record_every, workers, progress)
    t1 = time.perf_counter()
    mesh = pneunet_mesh(PneuNetParams(mesh_size=config.leg_mesh_size))
    snaps = load_snapshots(paths)
    pod: PODBasis = pod_basis(snaps, mesh.points, settings.tol_modes, settings.rigid)
    n_tri = len(mesh.surfaces["paper"])
    galerkin = PartReduction.full(mesh, pod.basis, n_tri, pod.n_rigid)
    t2 = time.perf_counter()
    ecsw_scenes = scenes[: settings.ecsw_scenes]
    results: dict[str, np.ndarray] = {}
    with tqdm(total=len(ecsw_scenes), desc="Galerkin ROM runs", unit="scene", disable=not progress,
              dynamic_ncols=True) as bar:
        def finished(r: tuple[str, np.ndarray]) -> None:
            results[r[0]] = r[1]
            bar.update()

        run_pool(galerkin_states, workers, [(s, fom, galerkin, settings.ecsw_every) for s in ecsw_scenes], finished)
    states = []
    for scene in ecsw_scenes:
        xs = results[scene.name]
        robot = reduce_legs(scene_robot(scene, fom, leg_mesh=mesh), galerkin)
        for j, leg in enumerate(robot.legs):
            states.append((robot.reduced[leg.body], xs[:, j]))
    t3 = time.perf_counter()
    grams = ecsw_grams(states, progress)
    return [_part(mesh, pod, grams, dataclasses.replace(settings, tol_gie=tol), fom, scenes, states, len(snaps),
                  (t0, t1, t2, t3)) for tol in tol_gies]


def _part(mesh, pod: PODBasis, grams, settings: BuildSettings, fom: RobotConfig, scenes, states, n_snaps: int,
          times: tuple[float, ...]) -> PartReduction:
    t0, t1, t2, t3 = times
    tets, tris = (ecsw_weights(g.gram, settings.tol_gie) for g in grams)
    n_tri = len(mesh.surfaces["paper"])
    t4 = time.perf_counter()
    meta = {"settings": dataclasses.asdict(settings), "config": dataclasses.asdict(fom),
            "snapshots": n_snaps, "n_pod": pod.n_pod, "n_rigid": pod.n_rigid, "tail_energy": pod.tail_energy,
            "training_scenes": [s.name for s in scenes],
            "ecsw_states": int(sum(len(x) for _, x in states)),
            "ecsw_residual": {"tetrahedra": tets.relative_residual, "triangles": tris.relative_residual},
            "rid": {"tetrahedra": [len(tets.elements), mesh.n_tets], "triangles": [len(tris.elements), n_tri]},
            "wall_seconds": {"snapshots": t1 - t0, "pod": t2 - t1, "galerkin": t3 - t2, "ecsw": t4 - t3,
                             "total": t4 - t0}}
    return PartReduction(mesh, pod.basis, pod.n_rigid, pod.singular_values, tets.elements, tets.weights,
                         tris.elements, tris.weights, meta)
