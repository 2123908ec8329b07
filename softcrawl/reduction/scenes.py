"""Training and validation scenes of a reduction: robots with one pressure channel per leg,
driven by animations, and the runner that records them.

The leg-local displacement of leg ``i`` (placed by rotation ``R_i``) is
``u_local = R_i^T (x - X_placed)`` per node: snapshots from every slot are pooled in one
frame (reduction.md, "Design-reconfigurable reduction"). The disk is placed unrotated in
every design: its snapshots are ``x - X_placed``.

Every scene belongs to a design space (:class:`softcrawl.design.spacefile.DesignSpace`,
default the paper's): its slots, parts and leg counts. The scenes of a space are drawn from
its slots with its leg counts, so a new part or body is reduced from robots of its own space
(reduction.md, "Reducing your own part"); the paper's space gives the paper's scenes.

Part of the reduction's build pipeline, which sits above :mod:`softcrawl.robot` (a scene is an
assembled robot, settled and stepped by the robot's episode code); :mod:`softcrawl.reduction`
says why that arrow is right and the robot never imports this module.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from softcrawl.design.baseline import symmetric_design
from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import DesignSpace
from softcrawl.fem.solver import SimulationDiverged
from softcrawl.fem.state import Control
from softcrawl.gaits import SineGait
from softcrawl.reduction.animations import (
    AlternatingAnimation,
    GaitAnimation,
    HamiltonianAnimation,
)
from softcrawl.reduction.model import ReducedBody, RobotReduction
from softcrawl.robot.assembly import Robot, RobotConfig, assemble_robot, reduce_robot
from softcrawl.robot.episode import Settling, settle


@dataclass(frozen=True)
class Scene:
    """A robot layout plus an animation.

    Attributes:
        name: label (file names, reports).
        legs: ``(slot, channel)`` per leg (slots of ``space``).
        animation: object with ``sim_pressure_at(t)`` and ``duration``.
        space: the design space whose slots and parts the robot has.
    """

    name: str
    legs: tuple[tuple[int, int], ...]
    animation: object
    space: DesignSpace = DEFAULT_SPACE

    @property
    def slots(self) -> tuple[int, ...]:
        return tuple(s for s, _ in self.legs)

    def describe(self) -> dict:
        """JSON-able settings of the scene (what a saved run is matched on); a space other than
        the paper's adds ``"space"``: its name, slot angles and parts
        (:meth:`DesignSpace.part_record`)."""
        anim = self.animation
        out = {"name": self.name, "legs": [list(leg) for leg in self.legs], "animation": type(anim).__name__,
               "animation_params": {k: (str(v) if not isinstance(v, (int, float, tuple)) else v)
                                    for k, v in dataclasses.asdict(anim).items()}}
        if self.space != DEFAULT_SPACE:
            out["space"] = {"name": self.space.name, "slot_angles_deg": list(self.space.slot_angles_deg),
                            "parts": self.space.part_record()}
        return out


def per_leg(slots: Sequence[int]) -> tuple[tuple[int, int], ...]:
    """Each leg on its own channel, in slot order."""
    return tuple((int(s), i) for i, s in enumerate(sorted(slots)))


#: Names of the held-out scene driving ``n`` legs in two alternating groups (``"six_leg"``).
_COUNT_WORDS = ("one", "two", "three", "four", "five", "six", "seven", "eight", "nine", "ten", "eleven", "twelve")


def held_out_slots(space: DesignSpace = DEFAULT_SPACE) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    """Slot sets of a space's validation scenes (never used for training; reduction.md,
    "Validating a reduction"), each ascending:

    - the legs of :func:`symmetric_design`;
    - two slots as near 90 degrees apart as the space has (the first such pair);
    - ``max_legs`` slots: every slot but ``k = S - max_legs`` spread ones (slots
      ``floor((j + 1/2) S / k)``, ``j < k``), or those dropped slots moved one up if that
      leaves the symmetric design's legs.

    The paper's space gives (0, 3, 4, 7), (0, 2) (22.5 and 112.5 degrees) and (0, 1, 3, 4, 5, 7).
    """
    s, angles = space.n_slots, space.slot_angles_deg
    symmetric = tuple(i for i, r in enumerate(symmetric_design(space)) if r)

    def gap(pair: tuple[int, int]) -> float:
        d = abs(angles[pair[0]] - angles[pair[1]]) % 360.0
        return round(abs(min(d, 360.0 - d) - 90.0), 6)

    two = min(itertools.combinations(range(s), 2), key=lambda p: (gap(p), p)) if s > 1 else (0,)
    k = s - space.max_legs
    drop = {math.floor((j + 0.5) * s / k) for j in range(k)}
    many = tuple(i for i in range(s) if i not in drop)
    if k and many == symmetric:
        many = tuple(i for i in range(s) if (i - 1) % s not in drop)
    return symmetric, two, many


def validation_scenes(duration: float = 4.0, space: DesignSpace = DEFAULT_SPACE) -> tuple[Scene, ...]:
    """The paper's four held-out animations (reduction.md, "Validating a reduction") on a
    space's :func:`held_out_slots`: Hamiltonian on the symmetric design's legs, the baseline
    sine gait (phase lag 110 degrees) on the symmetric design (:func:`symmetric_design`), two
    legs about 90 degrees apart inflating alternately, ``max_legs`` legs inflating in two
    alternating groups (every other leg). The paper's space: the baseline design, and six legs
    in groups of three (``"six_leg"``)."""
    symmetric, two, many = held_out_slots(space)
    design = symmetric_design(space)
    baseline = tuple((s, design[s] - 1) for s in symmetric)
    n = len(many)
    name = f"{_COUNT_WORDS[n - 1] if n <= len(_COUNT_WORDS) else n}_leg"
    groups = (tuple(range(0, n, 2)), tuple(range(1, n, 2)))
    return (
        Scene("hamiltonian", per_leg(symmetric), HamiltonianAnimation(len(symmetric)), space),
        Scene("baseline", baseline, GaitAnimation(SineGait(phase_deg=110.0), duration), space),
        Scene("two_leg", per_leg(two), AlternatingAnimation(((0,), (1,)), duration=duration), space),
        Scene(name, per_leg(many), AlternatingAnimation(groups, duration=duration), space),
    )


def _check_leg_counts(sizes: Sequence[int], space: DesignSpace) -> None:
    """Raises ValueError: no sizes, or a size outside ``1..S``."""
    if not sizes or not all(1 <= s <= space.n_slots for s in sizes):
        raise ValueError(f"need leg counts in 1..{space.n_slots}, got {tuple(sizes)}")


def _slot_pools(sizes: Sequence[int], space: DesignSpace, rng: np.random.Generator) -> dict[int, list[tuple]]:
    """Per leg count, the slot sets of that size that no validation scene uses, shuffled by
    ``rng`` (one permutation per size, in the iteration order of ``sizes``)."""
    held_out = set(held_out_slots(space))
    pools = {s: [c for c in itertools.combinations(range(space.n_slots), s) if c not in held_out] for s in sizes}
    return {s: [pool[i] for i in rng.permutation(len(pool))] for s, pool in pools.items()}


def _pick(pools: dict[int, list[tuple]], size: int) -> tuple[int, ...]:
    """The next unused slot set of ``size`` legs.

    Raises:
        ValueError: the space has no more distinct ones.
    """
    if not pools[size]:
        raise ValueError(f"the design space has too few distinct {size}-leg slot sets for the scenes asked for")
    return pools[size].pop(0)


def training_scenes(n_designs: int = 8, sizes: Sequence[int] = (3, 4), seed: int = 0,
                    state_seconds: float = 0.3, space: DesignSpace = DEFAULT_SPACE) -> tuple[Scene, ...]:
    """Training scenes: ``n_designs`` distinct slot subsets of ``space`` (sizes cycling through
    ``sizes``, drawn with a seeded RNG, excluding the validation slot sets
    :func:`held_out_slots`), each leg on its own channel, each driven by the Hamiltonian
    animation of its legs. Like the held-out ``two_leg`` scene, a size need not be one of the
    space's leg counts (one channel per leg: these robots are layouts, not designs).

    Raises:
        ValueError: non-positive count, a size outside ``1..S``, or more designs of a size than
            the space has.
    """
    if n_designs < 1:
        raise ValueError(f"need n_designs >= 1, got {n_designs}")
    _check_leg_counts(sizes, space)
    pools = _slot_pools(set(sizes), space, np.random.default_rng(seed))
    scenes = []
    for k in range(n_designs):
        s = sizes[k % len(sizes)]
        pick = _pick(pools, s)
        scenes.append(Scene(f"train{k:03d}_" + "".join(map(str, pick)), per_leg(pick),
                            HamiltonianAnimation(s, state_seconds=state_seconds, ramp_seconds=state_seconds / 2),
                            space))
    return tuple(scenes)


def gait_scenes(n_designs: int, seed: int = 1, seconds: float = 4.0,
                space: DesignSpace = DEFAULT_SPACE) -> tuple[Scene, ...]:
    """Crawling training scenes: ``n_designs`` distinct slot subsets of ``space`` with 3 and 4
    legs (alternately; clipped to the space's leg counts; never a validation slot set), the
    legs on regulators 1, 2, ..., R, 1, ... in slot order, each driven for ``seconds`` by the
    sine gait (:class:`softcrawl.gaits.SineGait`) at a phase lag drawn from 0, 10, ..., 350
    degrees (``seed``).

    Raises:
        ValueError: a negative count, a non-positive duration, or more designs of a size than
            the space has.
    """
    if n_designs < 0 or not seconds > 0:
        raise ValueError(f"need n_designs >= 0 and seconds > 0, got {n_designs}, {seconds}")
    sizes = tuple(dict.fromkeys(min(max(s, space.min_legs), space.max_legs) for s in (3, 4)))
    rng = np.random.default_rng(seed)
    pools = _slot_pools(sizes, space, rng)
    scenes = []
    for k in range(n_designs):
        pick = _pick(pools, sizes[k % len(sizes)])
        phase = 10.0 * int(rng.integers(36))
        scenes.append(Scene(f"gait{k:03d}_" + "".join(map(str, pick)) + f"_{phase:.0f}",
                            tuple((s, i % space.n_regulators) for i, s in enumerate(pick)),
                            GaitAnimation(SineGait(phase_deg=phase), seconds), space))
    return tuple(scenes)


def scene_robot(scene: Scene, config: RobotConfig, leg_mesh=None, disk_mesh_local=None) -> Robot:
    """The full-order robot of a scene in its space (one channel per leg unless the scene says
    otherwise)."""
    return assemble_robot(scene.legs, config, leg_mesh=leg_mesh, disk_mesh_local=disk_mesh_local, space=scene.space)


def reduced_scene_robot(scene: Scene, config: RobotConfig, reduction: RobotReduction) -> Robot:
    """The robot of a scene with its parts reduced by ``reduction`` (on the reduction's meshes;
    ``config.model`` and ``config.reduction`` are ignored)."""
    disk = reduction.disk.mesh if reduction.disk is not None else None
    full = dataclasses.replace(config, model="full", reduction=None)
    return reduce_robot(scene_robot(scene, full, leg_mesh=reduction.leg.mesh, disk_mesh_local=disk), reduction)


@dataclass(frozen=True, eq=False)
class SceneRecord:
    """What :func:`run_scene` recorded.

    Attributes:
        times: ``(k,)`` s (0 = end of settling).
        positions: ``(k, N, 3)`` float32 positions of all nodes, mm.
        reward_x: ``(k,)`` x of the disk top centre, mm.
        steps: steps run after settling; wall_seconds: wall time of the stepping (settling
        included).
        diverged: reason, or "".
        settle_steps: steps of the settling to rest.
    """

    times: np.ndarray
    positions: np.ndarray
    reward_x: np.ndarray
    steps: int
    wall_seconds: float
    diverged: str = ""
    settle_steps: int = 0


def run_scene(robot: Robot, animation, solver=None, record_every: int = 2, duration: float | None = None,
              on_step: Callable[[int], None] | None = None, perturbation: float = 0.0, seed: int = 0) -> SceneRecord:
    """Settle at zero pressure until at rest (the episodes' rule,
    :class:`softcrawl.robot.episode.Settling`), then play the animation, recording every
    ``record_every`` steps (and at t = 0).

    Args:
        robot: the robot (full-order or reduced: anything with ``make_solver``).
        animation: ``sim_pressure_at(t) -> (n_channels,)`` sim kPa, and ``duration``.
        solver: the solver to use (default ``robot.make_solver()``).
        record_every: steps between records.
        duration: s (default: the animation's).
        on_step: called with the step index after each step (progress).
        perturbation: amplitude (mm) of independent uniform noise added to every rest node
            position before settling (``seed`` draws it): a run that differs from the
            unperturbed one only at round-off scale, to measure how far the model's own
            trajectories drift apart. A POD-reduced body gets the noise's projection on its
            basis (its nodes stay in ``X + range(Phi)``).
    """
    solver = solver or robot.make_solver()
    dt = robot.config.dt
    n = int(round((duration if duration is not None else animation.duration) / dt))
    nch = robot.model.n_channels
    state = robot.model.rest_state()
    if perturbation:
        noise = np.random.default_rng(seed).uniform(-perturbation, perturbation, state.x.shape)
        for i, body in robot.reduced.items():
            if isinstance(body, ReducedBody):
                sl = robot.model.body_slice(i)
                noise[sl] = (body.basis @ (body.basis.T @ noise[sl].ravel())).reshape(-1, 3)
        state = dataclasses.replace(state, x=state.x + noise)
    times, frames, rx = [], [], []
    wall = time.perf_counter()
    reason, settle_steps = "", 0
    try:
        settled = settle(robot, Settling(), solver, state, Control(np.zeros(nch)))
        state, settle_steps = settled.state, settled.steps
        for k in range(n + 1):
            if k % record_every == 0:
                x = state.x
                times.append(k * dt)
                frames.append(x.astype(np.float32))
                rx.append(float(x[robot.reward_node, 0]))
            if k == n:
                break
            p = np.zeros(nch)
            a = np.asarray(animation.sim_pressure_at(k * dt), float)[:nch]
            p[: len(a)] = a
            state = solver.step(state, Control(p))
            if on_step is not None:
                on_step(k)
    except SimulationDiverged as exc:
        reason = str(exc)
    wall = time.perf_counter() - wall
    return SceneRecord(np.array(times), np.stack(frames) if frames else np.zeros((0, robot.model.n_nodes, 3), np.float32),
                       np.array(rx), n, wall, reason, settle_steps)


def leg_displacements(robot: Robot, positions: np.ndarray) -> np.ndarray:
    """Leg-local displacements of every leg in every frame.

    Args:
        robot: the robot the positions belong to.
        positions: ``(k, N, 3)`` stacked node positions, mm.

    Returns:
        ``(k * n_legs, n_leg_nodes, 3)`` float32 ``R_i^T (x - X_placed)``, mm.
    """
    m = robot.model
    out = []
    for leg in robot.legs:
        sl = m.body_slice(leg.body)
        u = positions[:, sl] - m.bodies[leg.body].mesh.points[None]
        out.append((u @ leg.rotation).astype(np.float32))  # rows: (R^T u)^T = u^T R
    return np.concatenate(out)


def disk_displacements(robot: Robot, positions: np.ndarray) -> np.ndarray:
    """``(k, n_disk_nodes, 3)`` float32 displacements ``x - X_placed`` of the disk in every
    frame of ``positions`` ``(k, N, 3)``, mm."""
    sl = robot.model.body_slice(robot.disk_body)
    return (positions[:, sl] - robot.model.bodies[robot.disk_body].mesh.points[None]).astype(np.float32)
