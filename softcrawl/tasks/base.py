"""The task interface: what an episode is scored on, and the floor it runs on.

A task is a frozen dataclass of numbers (its settings, checked at construction: one clear
``ValueError`` line naming the task and the setting). It is data, not code: a run's
``config.json`` holds its name and settings (:func:`softcrawl.tasks.registry.parse_task`
rebuilds it). What every task defines (docs/tasks.md):

* :attr:`Task.unit`: the unit of its reward, ``"cm"`` or ``"deg"``;
* :meth:`Task.origin` / :meth:`Task.progress`: a scalar measure of the episode's progress since
  its start (after settling), in :attr:`Task.unit`; the reward of an action is
  :meth:`Task.reward` of the measures before and after it (``after - before`` unless the task
  says otherwise), so an episode's return is its progress;
* :meth:`Task.reached`: its termination (a goal reached), if any; a diverged simulation ends
  every task's episode (:mod:`softcrawl.envs.crawler`);
* the floor: :attr:`Task.friction` (Coulomb mu; None: the robot config's, 1.2 by default) and
  :meth:`Task.gravity` (mm/s^2; None: the model's ``(0, 0, -9800)``), applied to every robot
  the env builds (:meth:`Task.robots`); a floor the robot cannot stand still on (tilted more
  than its friction holds) is refused (:meth:`Task.check_floor`);
* :attr:`Task.observes_state`: whether its policy needs the robot-state summary in its
  observation (none of the shipped tasks does: open-loop observations, codesign.md);
* :attr:`Task.baseline`: the expert baseline it has (``"sine"``: the paper's sine gait on the
  baseline design, ``"turning"``: :mod:`softcrawl.tasks.baselines`; None: none);
* :attr:`Task.reads_disk`: whether :meth:`progress` reads the disk's nodes (not only the
  reward point, the disk's top centre): the JAX backend returns the reward point only;
* :attr:`Task.vent_seconds`: seconds the episode goes on after its last action with every
  regulator vented (0 kPa), so that its last reward and its return count what the robot keeps at
  rest, not a twist or stretch the pressure only holds (0: none, the paper's ``forward``).
  Every path that scores a task's episode applies it: the env, the ground truth's episodes, the
  turning baseline and the replays (:func:`scored_gait`).

Episodes are read duck-typed: an object with ``robot`` (``reward_position(x)``; with
:attr:`reads_disk` a :class:`softcrawl.robot.Robot`), ``state.x`` ``(N, 3)`` mm, ``start``
``(3,)`` mm (the reward point after settling) and ``displacement_cm``
(:class:`softcrawl.robot.episode.Episode`, or the JAX backend's point episode).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from softcrawl.robot.assembly import Robot
from softcrawl.robot.domain import randomized_robot
from softcrawl.robot.episode import MM_PER_CM, Settling, run_episode

#: Seconds a gait's episode is continued with every regulator vented (0 kPa) to see what of its
#: return the robot keeps at rest (:func:`vented_return`): the regulators slew to 0 kPa within
#: 0.6 s (150 kPa/s, :class:`softcrawl.robot.actuation.RegulatorBank`), and the robot is at
#: rest well before the 5 s end (docs/tasks.md, "Twist or turn").
VENT_SECONDS = 5.0

#: Bounds of a task's floor friction (Coulomb mu, dimensionless), both included.
FRICTION_BOUNDS = (0.0, 10.0)


def check_number(task: str, name: str, value, low: float, high: float, unit: str = "") -> float:
    """``value`` as a float if it is a number in ``[low, high]``; else ValueError (one line
    naming the task and the setting)."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and math.isfinite(value) and low <= value <= high):  # NaN fails too
        raise ValueError(f"task {task!r}: {name} must be a number in [{low:g}, {high:g}]"
                         f"{' ' + unit if unit else ''}, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Task:
    """Base of the tasks (module docstring). Settings are dataclass fields (numbers).

    Attributes:
        friction: the floor's Coulomb coefficient mu (``[0, 10]``); None: the robot config's
            (:attr:`softcrawl.robot.RobotConfig.friction`, 1.2: the paper's floor).

    Raises:
        ValueError: a setting that is not a finite number in its range (one line).
    """

    name: ClassVar[str] = ""
    unit: ClassVar[str] = "cm"
    baseline: ClassVar[str | None] = None
    observes_state: ClassVar[bool] = False
    reads_disk: ClassVar[bool] = False
    #: One line on the reward, for reports and ``docs/tasks.md``.
    describe: ClassVar[str] = ""

    friction: float | None = None

    def __post_init__(self) -> None:
        if self.friction is not None:
            object.__setattr__(self, "friction", check_number(self.name, "friction", self.friction, *FRICTION_BOUNDS))

    @property
    def vent_seconds(self) -> float:
        """Seconds vented after the last action before the episode is scored (module docstring;
        0 here: scored while the last action's pressure holds)."""
        return 0.0

    # -- floor ---------------------------------------------------------------------------
    def gravity(self) -> tuple[float, float, float] | None:
        """Gravity of the task's world, ``(3,)`` mm/s^2 (None: the model's own)."""
        return None

    def check_floor(self, friction: float | None = None) -> None:
        """Refuse a floor no robot can stand still on: gravity (:meth:`gravity`) tilted from the
        floor's normal (-z) by an angle ``a`` with ``tan a > mu``, ``mu`` this task's
        :attr:`friction`, else ``friction`` (the robot's; None: unknown, not checked). By
        Coulomb's law a body on such a slope slides for good (docs/tasks.md, "incline"): the
        robot would never come to rest before an episode, and every return would score the
        slide.

        Raises:
            ValueError: such a floor (one line naming the task, its tilt and the friction).
        """
        g, mu = self.gravity(), self.friction if self.friction is not None else friction
        if g is None or mu is None:
            return
        along, normal = math.hypot(g[0], g[1]), -g[2]
        if along > mu * normal * (1 + 1e-12):
            tilt = math.degrees(math.atan2(along, normal))
            raise ValueError(f"task {self.name!r}: its floor is tilted {tilt:.4g} deg (tan {along / normal:.3g}), "
                             f"steeper than the friction mu = {mu:g} holds (atan mu = {math.degrees(math.atan(mu)):.4g} "
                             "deg): a robot on it slides down for good and never comes to rest; lower the tilt or "
                             "raise the friction")

    def robots(self, factory: Callable) -> Callable:
        """``factory`` (``design -> Robot``) whose robots stand on this task's floor: the same
        object when the task keeps the robot's floor (so robot caches keyed on the factory
        stay shared), else a picklable :class:`OnFloor` wrapper."""
        gravity = self.gravity()
        if self.friction is None and gravity is None:
            return factory
        return OnFloor(factory, self.friction, gravity)

    # -- scoring -------------------------------------------------------------------------
    def origin(self, episode) -> object:
        """What :meth:`progress` measures from, taken at the episode's start: by default the
        reward point's settled position ``episode.start`` ``(3,)`` mm."""
        return np.asarray(episode.start, dtype=float).copy()

    def progress(self, episode, origin) -> float:
        """The episode's progress since its start, in :attr:`unit` (subclasses)."""
        raise NotImplementedError

    def reward(self, before: float, after: float) -> float:
        """The reward of an action from the progress before and after it: ``after - before``."""
        return after - before

    def reached(self, episode, origin) -> bool:
        """Whether the episode ends now with its goal reached (default: never)."""
        return False

    def settings(self) -> dict:
        """``{"name": ..., setting: value, ...}``: the table :func:`parse_task` reads back."""
        return {"name": self.name, **dataclasses.asdict(self)}

    def label(self) -> str:
        """A short human label: the name and its non-default settings, e.g. ``heading (heading_deg=90)``."""
        default = type(self)()
        changed = [f"{f.name}={getattr(self, f.name):g}" for f in dataclasses.fields(self)
                   if getattr(self, f.name) != getattr(default, f.name)]
        return f"{self.name} ({', '.join(changed)})" if changed else self.name


@dataclass(frozen=True)
class OnFloor:
    """A robot factory whose robots stand on another floor (picklable, hashable).

    Attributes:
        factory: ``design -> Robot``.
        friction: the floor's Coulomb mu (None: the robot's).
        gravity: ``(3,)`` mm/s^2 (None: the model's).
    """

    factory: Callable
    friction: float | None = None
    gravity: tuple[float, float, float] | None = None

    def __call__(self, design) -> Robot:
        return on_floor(self.factory(design), self.friction, self.gravity)


def on_floor(robot: Robot, friction: float | None = None, gravity=None) -> Robot:
    """``robot`` with the floor's friction ``friction`` (:func:`softcrawl.robot.domain.randomized_robot`:
    ``robot.config`` records it) and gravity ``gravity`` ``(3,)`` mm/s^2 (None: unchanged). The
    solvers read both from the model when they are made (the reduced legs' gravity loads too)."""
    if friction is not None:
        robot = randomized_robot(robot, friction=friction)
    if gravity is not None:
        robot = dataclasses.replace(robot, model=dataclasses.replace(robot.model, gravity=tuple(map(float, gravity))))
    return robot


@dataclass(frozen=True, eq=False)
class Snapshot:
    """A recorded state read as an episode by the tasks (module docstring): ``robot``, ``state.x``
    ``(N, 3)`` mm, ``start`` ``(3,)`` mm (the reward point at the episode's start)."""

    robot: Robot
    x: np.ndarray
    start: np.ndarray

    @property
    def state(self) -> Snapshot:
        return self

    @property
    def displacement_cm(self) -> float:
        """+x displacement of the reward point since ``start``, cm (:attr:`Episode.displacement_cm`)."""
        return float(self.robot.reward_position(self.x)[0] - self.start[0]) / MM_PER_CM


def return_series(task: Task, robot: Robot, frames) -> np.ndarray:
    """``(k,)`` ``task``'s return accumulated from frame 0 to each recorded frame (0 at frame 0), in
    the task's unit: the running sum of :meth:`Task.reward` between consecutive frames
    (``frames`` ``(k, N, 3)`` mm, frame 0 the episode's start, e.g.
    :attr:`softcrawl.robot.EpisodeResult.frames`); empty without frames."""
    frames = np.asarray(frames, dtype=float)
    if len(frames) == 0:
        return np.zeros(0)
    start = np.asarray(robot.reward_position(frames[0]), dtype=float)
    snaps = [Snapshot(robot, x, start) for x in frames]
    origin = task.origin(snaps[0])
    progress = [task.progress(s, origin) for s in snaps]
    return np.concatenate([[0.0], np.cumsum([task.reward(a, b) for a, b in zip(progress[:-1], progress[1:])])])


def replay_return(task: Task, robot: Robot, frames) -> float:
    """``task``'s return over recorded frames (:func:`return_series`'s last value); NaN without
    frames."""
    series = return_series(task, robot, frames)
    return float(series[-1]) if len(series) else float("nan")


def scored_gait(gait, duration: float, vent_seconds: float):
    """``(gait, duration)`` of an episode as a task with :attr:`Task.vent_seconds` =
    ``vent_seconds`` scores it: ``gait`` for ``duration`` s, then ``vent_seconds`` more with every
    regulator vented (:class:`softcrawl.gaits.VentedAfter`); unchanged for 0."""
    from softcrawl.gaits import VentedAfter

    return (VentedAfter(gait, duration), duration + vent_seconds) if vent_seconds > 0 else (gait, duration)


def vented_return(task: Task, robot: Robot, gait, duration: float, settling: Settling = Settling(),
                  calibration=None, vent_seconds: float = VENT_SECONDS) -> tuple[float, float, bool]:
    """``task``'s return of ``gait`` over ``duration`` s, and what of it is kept once every
    regulator has vented for ``vent_seconds`` more (:class:`softcrawl.gaits.VentedAfter`): an
    elastic twist or stretch that the pressure only holds springs back, a move on the floor
    stays. One :func:`softcrawl.robot.run_episode` after ``settling``, frames every 1 s (or
    fewer steps, so that one falls at ``duration``) read by :func:`return_series`.

    Args:
        task, robot: the task and its robot (the task's floor). gait: any gait, real kPa.
        duration, vent_seconds: s, > 0. calibration: the rig's pressure calibration (None:
            the identity).

    Returns:
        ``(return at duration, return after venting, diverged)`` in the task's unit (NaN where
        the episode diverged before that frame).

    Raises:
        ValueError: a non-positive or non-finite ``duration`` or ``vent_seconds``.
    """
    from softcrawl.robot.actuation import PressureCalibration

    if not all(math.isfinite(v) and v > 0 for v in (duration, vent_seconds)):
        raise ValueError(f"duration and vent_seconds must be > 0 s, got {duration}, {vent_seconds}")
    dt = robot.config.dt
    n, m = int(round(duration / dt)), int(round((duration + vent_seconds) / dt))
    every = math.gcd(max(1, int(round(1.0 / dt))), n, m)
    res = run_episode(robot, *scored_gait(gait, duration, vent_seconds),
                      calibration if calibration is not None else PressureCalibration(), settling=settling,
                      record_every=every, progress=False)
    series = return_series(task, robot, res.frames)
    held, kept = (float(series[i]) if i < len(series) else float("nan") for i in (n // every, m // every))
    return held, kept, bool(res.diverged)
