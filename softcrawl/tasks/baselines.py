"""Expert baselines of the tasks that have one (:attr:`softcrawl.tasks.Task.baseline`).

* ``"sine"`` (``forward``): the paper's sine gait on :data:`softcrawl.design.BASELINE_DESIGN`,
  swept over its phase lag by :func:`softcrawl.robot.sweep.run_sweep` (codesign.md).
* ``"turning"`` (``turning``): a hand-made turning gait, :func:`turning_gait` on
  :data:`TURNING_BASELINE_DESIGN`, a design of the paper's space symmetric under a half turn
  (legs at 22.5 and 202.5 deg on regulator 1, at 67.5 and 247.5 deg on regulator 2): the two
  diagonally opposite leg pairs inflate alternately, pair 2 lagging pair 1 by a phase lag, with
  the raised-cosine waves of the sine baseline (:class:`softcrawl.gaits.SineGait`: 0-90 kPa, 4 s
  period). Every mirror line of the design swaps its two regulators, so a lag other than 0 or
  180 deg makes the actuation chiral (in a mirror-symmetric model a lag of -phi is the mirror
  image of phi and turns the other way; the model's inflating legs also twist the disk
  counter-clockwise, docs/tasks.md); a design with a mirror line that keeps each regulator's legs, such as 22.5 and
  67.5 deg on regulator 1 and 202.5 and 247.5 deg on regulator 2, cannot turn under any gait
  of its two regulators. :func:`sweep_turning` tunes the lag as ``softcrawl sweep-phase`` tunes the forward
  baseline's; its score is the yaw the disk turns in the episode, degrees
  (:func:`turned_degrees`). In another design space the same construction
  (:func:`turning_baseline_design`: regulator 1 on slots 0 and n/2, regulator 2 on slots 1 and
  1 + n/2) is its baseline where the space has it (opposite slots 180 deg apart, 4 legs
  allowed), else the space has no turning baseline.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import DesignSpace
from softcrawl.gaits import PeriodicGait, SineGait
from softcrawl.parallel import run_pool
from softcrawl.robot.assembly import Robot
from softcrawl.robot.episode import Settling, run_episode
from softcrawl.robot.sweep import baseline_gait
from softcrawl.tasks.base import scored_gait
from softcrawl.tasks.builtin import disk_yaw_deg, wrap_deg

#: The turning baseline's design: regulator 1 at 22.5 and 202.5 deg, regulator 2 at 67.5 and
#: 247.5 deg (slots 0, 4 and 1, 5 of the paper's space): symmetric under a half turn about +z.
TURNING_BASELINE_DESIGN: tuple[int, ...] = (1, 2, 0, 0, 1, 2, 0, 0)
#: Phase lags of regulator 2 behind regulator 1 swept by default, degrees.
TURNING_PHASES: tuple[float, ...] = tuple(float(p) for p in range(0, 360, 45))


def turning_gait(phase_deg: float, n_regulators: int = DEFAULT_SPACE.n_regulators) -> SineGait | PeriodicGait:
    """The turning baseline's gait: the sine baseline's waves (0-90 kPa raised cosine, period
    4 s) on regulators 1 and 2, regulator 2 lagging by ``phase_deg`` degrees
    (:func:`softcrawl.robot.sweep.baseline_gait` for ``n_regulators`` regulators; the
    baseline's design puts no leg on regulators 3..R)."""
    return baseline_gait(phase_deg, n_regulators)


def turning_baseline_design(space: DesignSpace) -> tuple[int, ...] | None:
    """The turning baseline's design in ``space``: regulator 1 on slots 0 and n/2, regulator 2
    on slots 1 and 1 + n/2 (``n`` slots; :data:`TURNING_BASELINE_DESIGN` in the paper's space),
    symmetric under a half turn about +z. None when the space has no such design: an odd slot
    count, fewer than 4 slots or 2 regulators, slots 0 and n/2 (or 1 and 1 + n/2) not 180 deg
    apart (within 1e-6 deg), or 4 legs outside its leg counts."""
    n = space.n_slots
    if n % 2 or n < 4 or space.n_regulators < 2 or not space.min_legs <= 4 <= space.max_legs:
        return None
    angles = space.slot_angles_deg
    if any(abs(wrap_deg(angles[i + n // 2] - angles[i] - 180.0)) > 1e-6 for i in (0, 1)):
        return None
    design = [0] * n
    design[0] = design[n // 2] = 1
    design[1] = design[1 + n // 2] = 2
    return tuple(design)


@dataclass(frozen=True)
class TurnResult:
    """One episode of a turning gait.

    Attributes:
        phase_deg: the gait's phase lag, degrees.
        turned_deg: counter-clockwise yaw of the disk over the episode, degrees (up to the last
            valid state if it diverged; NaN if settling diverged).
        diverged: whether the simulation failed. wall_seconds: its wall-clock time.
    """

    phase_deg: float
    turned_deg: float
    diverged: bool
    wall_seconds: float


def turned_degrees(robot: Robot, gait, duration: float, settling: Settling = Settling(),
                   sample_every: float = 1.0, vent_seconds: float = 0.0) -> tuple[float, bool]:
    """Yaw the disk turns under ``gait`` over ``duration`` s (after settling), degrees
    counter-clockwise: :func:`softcrawl.tasks.disk_yaw_deg` sampled every ``sample_every`` s
    (rounded to whole steps; fewer if needed, so that the samples include the episode's last
    step) and its wrapped increments summed (the turning task's return with 1-s actions).
    With ``vent_seconds`` the episode goes on that long with every regulator vented and is
    scored at its end, at rest (the ``turning`` task's ``vent_s``,
    :func:`softcrawl.tasks.base.scored_gait`).
    Returns ``(degrees, diverged)``; NaN degrees if settling diverged."""
    gait, duration = scored_gait(gait, duration, vent_seconds)
    dt = robot.config.dt
    n = int(round(duration / dt)) if math.isfinite(duration) else 0
    every = math.gcd(max(1, int(round(sample_every / dt))), max(n, 1))
    yaws: list[float] = []
    res = run_episode(robot, gait, duration, settling=settling, record_every=every, progress=False,
                      on_frame=lambda t, x: yaws.append(disk_yaw_deg(robot, x)))
    if not yaws:
        return float("nan"), True
    total = sum(wrap_deg(b - a) for a, b in zip(yaws[:-1], yaws[1:]))
    return float(total), bool(res.diverged)


def run_turning_phase(factory: Callable, phase_deg: float, duration: float,
                      settling: Settling = Settling(), design: tuple[int, ...] = TURNING_BASELINE_DESIGN,
                      n_regulators: int = DEFAULT_SPACE.n_regulators, vent_seconds: float = 0.0) -> TurnResult:
    """One episode of :func:`turning_gait` at ``phase_deg`` (``n_regulators`` regulators) on
    ``factory(design)``, scored after ``vent_seconds`` vented (:func:`turned_degrees`)."""
    wall = time.perf_counter()
    turned, diverged = turned_degrees(factory(design), turning_gait(phase_deg, n_regulators), duration, settling,
                                      vent_seconds=vent_seconds)
    return TurnResult(float(phase_deg), turned, diverged, time.perf_counter() - wall)


def sweep_turning(factory: Callable, phases: Sequence[float] = TURNING_PHASES, duration: float = 20.0,
                  settling: Settling = Settling(), workers: int | None = 1,
                  space: DesignSpace = DEFAULT_SPACE, vent_seconds: float = 0.0) -> list[TurnResult]:
    """The turning baseline at each phase lag of ``phases`` (degrees), in that order.

    Args:
        factory: picklable ``design -> Robot`` (a run's robot factory on the task's floor).
        duration: episode length, s. settling: the rest rule before each episode.
        workers: processes (:func:`softcrawl.parallel.run_pool`; 1: in this process).
        space: the factory's design space (:func:`turning_baseline_design` and its regulators).
        vent_seconds: seconds vented after each episode before it is scored (the turning
            task's ``vent_s``; :func:`turned_degrees`).

    Raises:
        ValueError: no phases, a non-finite or repeated phase, a non-positive duration, a
            space without a turning baseline design.
    """
    phases = tuple(float(p) for p in phases)
    if not phases or not all(map(math.isfinite, phases)) or len(set(phases)) != len(phases):
        raise ValueError(f"phases must be non-empty, finite and distinct, got {phases}")
    if not (math.isfinite(duration) and duration > 0):
        raise ValueError(f"duration must be a positive number of seconds, got {duration}")
    design = turning_baseline_design(space)
    if design is None:
        raise ValueError(f"the design space {space.name!r} has no turning baseline design (turning_baseline_design)")
    done: dict[float, TurnResult] = {}
    run_pool(run_turning_phase, workers, [(factory, p, duration, settling, design, space.n_regulators,
                                           vent_seconds) for p in phases],
             lambda r: done.__setitem__(r.phase_deg, r))
    return [done[p] for p in phases]


def best_turn(results: Sequence[TurnResult]) -> TurnResult | None:
    """The result that turned furthest in either direction (largest ``|turned_deg|``; the
    mirror image of a gait turns the other way), None if every episode diverged."""
    ok = [r for r in results if not r.diverged and np.isfinite(r.turned_deg)]
    return max(ok, key=lambda r: abs(r.turned_deg)) if ok else None
