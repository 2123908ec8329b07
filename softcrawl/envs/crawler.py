"""Gymnasium environment of one crawler episode (codesign.md, "The policy").

One episode = ``n_actions`` (20) actions, each held for ``steps_per_action`` simulator steps
(default 100 steps of 0.01 s = 1 s). The design is fixed per episode and chosen at
``reset(options={"design": ...})`` (a uniformly random design of ``designs`` from the env's RNG
when none is given).

* Action: ``Box(-1, 1, (3,))``, mapped inside to commanded real pressures
  ``45 (a + 1)`` kPa in [0, 90] (regulators 1..3).
* Observation: ``Box((44,))`` float32 = design one-hot (32, slot-major, see
  :func:`softcrawl.design.space.one_hot`) + the last ``history`` (4) actions in [-1, 1], most
  recent first, zeros at the start of an episode (cleared on every reset). With
  ``observe_state=True`` 9 numbers follow: disk top-centre displacement since the end of
  settling (cm, x/y/z), its velocity (cm/s) and the applied pressures scaled to [-1, 1].
* These sizes are the paper's design space's; an env of another ``space``
  (:class:`softcrawl.design.spacefile.DesignSpace`, ``S`` slots, ``R`` regulators) has ``R``
  actions, a one-hot of ``S (R + 1)``, ``R`` actions per history entry and ``6 + R`` state numbers.
* Reward: the ``task``'s (:mod:`softcrawl.tasks`, docs/tasks.md; default ``forward``, the
  paper's: cm crawled along +x by the disk top centre during the action, so the episode return
  is the +x displacement, codesign.md / paper): :meth:`Task.reward` of the task's progress
  before and after the action, in :attr:`Task.unit` (cm or degrees). The task's floor
  (friction, gravity) applies to every robot the env builds (:meth:`Task.robots`). A task
  with :attr:`Task.vent_seconds` (``turning``) has the robot vent that long after the last
  action, before the last reward is taken: the return is what the robot keeps at rest.
* ``terminated``: on a diverged simulation (``SimulationDiverged``): ``info["diverged"]``
  is True and ``info["reason"]`` holds the message; the reward of that action counts up to the
  last valid state; or when the task's goal is reached (:meth:`Task.reached`, e.g. ``target``).
  ``truncated``: after ``n_actions`` actions (the time limit; learners should
  bootstrap through it, see :mod:`softcrawl.codesign.sac`).
* ``info``: ``design``, ``t`` (s), ``disk_position_mm`` (3,), ``displacement_cm`` (+x),
  ``progress`` (the task's progress since the start, in its unit),
  ``applied_kpa`` (3,) and ``commanded_kpa`` (3,), ``diverged``, ``reason``, and how the
  episode's start was reached (:meth:`softcrawl.robot.episode.SettledState.as_dict`):
  ``settle_steps``, ``settle_seconds``, ``rest_speed_mm_s`` and ``at_rest`` (False: the robot
  was still moving at the settling cap; its episode is scored but flagged). With domain
  randomization on, also ``domain``: the episode's draw
  (:meth:`softcrawl.robot.domain.DomainSample.as_dict`); without it there is no such key.

Robots are built with an injectable ``robot_factory(design) -> Robot`` (default
:class:`BuildRobot`, the full-order model) and cached per design with their settled state
(LRU, ``max_cached``: settling to rest costs once per design, not per episode; the envs of a
training worker share one cache, which keeps settled states longer than their robots,
:mod:`softcrawl.envs.robot_cache`); each episode gets a fresh solver, so the same design and
actions give the same return.

**Domain randomization** (``randomize``, :class:`~softcrawl.robot.domain.DomainRanges`): at
every reset, after the design, a :class:`~softcrawl.robot.domain.DomainSample` is drawn from the
env's RNG (``np_random``: reproducible per reset seed; nothing is drawn when randomization is
off, so an env without it behaves exactly as before). Pressure gains and offsets give the
episode its own calibration, lags its own regulators, the control-period dilation its own step
count per action (:attr:`CrawlerEnv.steps_per_action` is then that of the current action).
A sample that changes the robot (friction, Young's moduli, masses) gets a robot built from the
cached nominal one (:meth:`~softcrawl.robot.domain.DomainSample.apply`) and is settled for that
episode alone (its rest pose is its own; at the ``demo`` preset the new robot and its settling
cost 0.18-0.19 s, 8-10% of a 20-action episode); the cached nominal robot and its settled state are
left as they are (the batched backend, :mod:`softcrawl.envs.backends.batched`, still settles a new
design's nominal robot once, before the reset that draws the sample: wasted, once per design
and worker).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from functools import lru_cache
from typing import ClassVar

import gymnasium as gym
import numpy as np

from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.envs.robot_cache import RobotCache, process_cache
from softcrawl.fem.solver import SimulationDiverged
from softcrawl.robot.actuation import P_MAX_KPA, PressureCalibration
from softcrawl.robot.assembly import Robot, RobotConfig, build_robot
from softcrawl.robot.domain import DomainRanges, DomainSample
from softcrawl.robot.episode import MM_PER_CM, Episode, SettledState, Settling
from softcrawl.tasks import DEFAULT_TASK, Task, parse_task

N_ACTIONS = 20
HISTORY = 4
DESIGN_DIM = DEFAULT_SPACE.one_hot_size  # 32: the paper's space (other spaces: CrawlerEnv.space)
STATE_DIM = 9


@dataclass(frozen=True)
class BuildRobot:
    """Picklable default robot factory: ``build_robot(design, config, space=space)``."""

    config: RobotConfig = field(default_factory=RobotConfig)
    space: DesignSpace = DEFAULT_SPACE

    def __call__(self, design: Design) -> Robot:
        return build_robot(design, self.config, space=self.space)


def action_to_kpa(action: np.ndarray) -> np.ndarray:
    """Map actions in [-1, 1] (clipped) to commanded real kPa in [0, 90]: ``45 (a + 1)``."""
    a = np.clip(np.asarray(action, dtype=float), -1.0, 1.0)
    return (a + 1.0) * (P_MAX_KPA / 2.0)


def kpa_to_action(kpa: np.ndarray) -> np.ndarray:
    """Inverse of :func:`action_to_kpa`."""
    return np.asarray(kpa, dtype=float) / (P_MAX_KPA / 2.0) - 1.0


@lru_cache(maxsize=8)
def _validated_tuple(designs: tuple, space: DesignSpace) -> tuple[Design, ...]:
    return tuple(space.validate_design(d) for d in designs)


def _validated(designs: Sequence, space: DesignSpace) -> tuple[Design, ...]:
    """``designs`` validated (:meth:`DesignSpace.validate_design`); hashable ones once per process
    (the 48 envs of a ``paper`` worker share one tuple of 6,972 designs: 65 ms each)."""
    designs = tuple(designs)
    try:
        hash(designs)
    except TypeError:  # unhashable entries (lists)
        return tuple(space.validate_design(d) for d in designs)
    return _validated_tuple(designs, space)


class CrawlerEnv(gym.Env):
    """One crawler episode as a gymnasium 1.x environment (see the module docstring).

    Args:
        robot_factory: ``design tuple -> Robot`` (default ``BuildRobot(RobotConfig.for_space(space),
            space)``; ``RobotConfig()`` for the paper's space).
        steps_per_action: simulator steps per action (default 100 = 1 s at dt 0.01 s).
        n_actions: actions per episode (default 20).
        history: past actions in the observation (default 4).
        observe_state: append the 9-number robot-state summary to the observation.
        designs: designs drawn at reset when none is given (default: all canonical designs).
        settling: the rest rule before each episode (:class:`Settling`; not counted).
        calibration: real-to-sim pressure map (default ``PressureCalibration()``).
        max_cached: robots kept beyond the one in use (LRU, :class:`RobotCache`).
        randomize: per-episode domain randomization ranges (None or all-None ranges: off;
            module docstring).
        share_robots: keep robots in the process's cache for this robot factory and settling
            rule, shared with every other env of the process that asks for it
            (:func:`softcrawl.envs.robot_cache.process_cache`; training's envs do), instead of
            a cache of this env's own.
        space: the design space: designs, one-hot code, number of regulators (actions; domain
            randomization draws its per-regulator quantities for each of them).
        task: what the env rewards (:mod:`softcrawl.tasks`): a :class:`Task`, a name or a table
            of settings (:func:`softcrawl.tasks.parse_task`; default ``"forward"``, the paper's).

    Attributes:
        nominal_steps_per_action: simulator steps per action without control-period dilation.
        domain: the current episode's :class:`DomainSample` (None: randomization off).

    Raises:
        ValueError: non-positive ``steps_per_action``/``n_actions``/``max_cached``, negative
            ``history``, an empty or invalid ``designs`` list, a control-period range that
            gives actions of less than one step, an invalid task or one that observes the
            robot's state without ``observe_state``.
    """

    metadata: ClassVar[dict] = {"render_modes": []}
    render_mode = None

    def __init__(self, robot_factory: Callable[[Design], Robot] | None = None, steps_per_action: int = 100,
                 n_actions: int = N_ACTIONS, history: int = HISTORY, observe_state: bool = False,
                 designs: Sequence[Sequence[int]] | None = None, settling: Settling = Settling(),
                 calibration: PressureCalibration | None = None, max_cached: int = 16,
                 randomize: DomainRanges | None = None, share_robots: bool = False,
                 space: DesignSpace = DEFAULT_SPACE, task: Task | str | dict = DEFAULT_TASK):
        super().__init__()
        for name, v in (("steps_per_action", steps_per_action), ("n_actions", n_actions), ("max_cached", max_cached)):
            if int(v) != v or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        if int(history) != history or history < 0:
            raise ValueError(f"history must be a non-negative integer, got {history!r}")
        self.space = space
        self.task = parse_task(task)
        if self.task.observes_state and not observe_state:
            raise ValueError(f"task {self.task.name!r} observes the robot's state: set observe_state")
        self.robot_factory = self.task.robots(robot_factory if robot_factory is not None else BuildRobot(
            RobotConfig.for_space(space), space))
        self.nominal_steps_per_action, self.n_actions = int(steps_per_action), int(n_actions)
        self.history = int(history)
        if randomize is not None and not isinstance(randomize, DomainRanges):
            raise ValueError(f"randomize must be DomainRanges or None, got {type(randomize).__name__}")
        self.randomize = randomize if randomize is not None and randomize.enabled else None
        if self.randomize is not None:
            self.randomize.check_steps(self.nominal_steps_per_action)
        self.domain: DomainSample | None = None
        self._action_steps = self.nominal_steps_per_action
        self._t_steps = 0
        self.observe_state, self.settling = bool(observe_state), settling
        self.calibration = calibration if calibration is not None else PressureCalibration()
        self.designs = space.canonical_designs if designs is None else _validated(designs, space)
        if not self.designs:
            raise ValueError("designs must not be empty")
        self.max_cached = int(max_cached)
        self._robots = (process_cache(self.robot_factory, settling, self.max_cached) if share_robots
                        else RobotCache(self.max_cached)).attach()
        n_reg, n_code = space.n_regulators, space.one_hot_size
        self._state_dim = STATE_DIM - DEFAULT_SPACE.n_regulators + n_reg
        n_hist = n_reg * self.history
        low = np.concatenate([np.zeros(n_code), -np.ones(n_hist)]).astype(np.float32)
        high = np.ones(n_code + n_hist, np.float32)
        if self.observe_state:
            low = np.concatenate([low, np.full(self._state_dim, -np.inf, np.float32)])
            high = np.concatenate([high, np.full(self._state_dim, np.inf, np.float32)])
        self.observation_space = gym.spaces.Box(low, high, dtype=np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (n_reg,), dtype=np.float32)
        self.design: Design | None = None
        self.episode: Episode | None = None
        self._hist = np.zeros((self.history, n_reg), np.float32)
        self._k = 0
        self._dead, self._reason = False, ""
        self._one_hot = np.zeros(n_code, np.float32)
        self._settled_info: dict = {}
        self._origin = None  # the task's start reference (Task.origin)

    @property
    def steps_per_action(self) -> int:
        """Simulator steps of the current action (of the next one between actions): the
        nominal count unless the control-period dilation is randomized
        (:meth:`DomainSample.action_steps`)."""
        return self._action_steps

    # -- robots ---------------------------------------------------------------------------
    def _episode_for(self, design: Design, sample: DomainSample | None = None) -> Episode:
        """A fresh :class:`Episode` (new solver: no factorization or warm start carried over
        from earlier episodes, so an episode is a function of design and actions only) on the
        cached robot of ``design``, starting from its cached settled state; with a domain
        ``sample``, on the randomized robot (settled anew if the sample is physical) with the
        sample's calibration and regulators."""
        robot, settled = self._robots.fetch(design, self.robot_factory)
        if sample is None:
            return Episode(robot, self.calibration, self.settling, settled=settled)
        if sample.physical:
            robot, settled = sample.apply(robot), None
        n_reg = self.space.n_regulators
        episode = Episode(robot, sample.calibration(self.calibration, n_reg), self.settling, settled=settled)
        episode.regulators = sample.regulators(episode.regulators.rate_kpa_s, n_reg)
        return episode

    # -- observation / info -----------------------------------------------------------------
    def _state_summary(self) -> np.ndarray:
        ep = self.episode
        node = ep.robot.reward_node
        disp = (ep.state.x[node] - ep.start) / MM_PER_CM
        vel = ep.state.v[node] / MM_PER_CM
        return np.concatenate([disp, vel, kpa_to_action(ep.applied)]).astype(np.float32)

    def _obs(self) -> np.ndarray:
        parts = [self._one_hot, self._hist.reshape(-1)]
        if self.observe_state:
            parts.append(self._state_summary() if not self._dead else np.zeros(self._state_dim, np.float32))
        return np.concatenate(parts).astype(np.float32)

    def _info(self, commanded: np.ndarray | None = None) -> dict:
        ep = self.episode
        pos = ep.robot.reward_position(ep.state.x) if not self._dead or self._k > 0 else np.full(3, np.nan)
        return {
            "design": self.design, "t": self._t_steps * ep.dt,
            "disk_position_mm": np.array(pos, dtype=float), "displacement_cm": self._displacement(),
            "progress": self._progress(),
            "applied_kpa": ep.applied, "commanded_kpa": np.zeros(len(ep.applied)) if commanded is None else commanded,
            "diverged": self._dead, "reason": self._reason, **self._settled_info,
            **({"domain": self.domain.as_dict()} if self.domain is not None else {}),
        }

    def _displacement(self) -> float:
        return self.episode.displacement_cm if (not self._dead or self._k > 0) else 0.0

    def _progress(self) -> float:
        """The task's progress since the start (its unit; 0 if settling diverged)."""
        return self.task.progress(self.episode, self._origin) if (not self._dead or self._k > 0) else 0.0

    def _steps_of(self, k: int) -> int:
        n = self.nominal_steps_per_action
        return n if self.domain is None else self.domain.action_steps(n, k)

    def episode_steps(self) -> list[int]:
        """Simulator steps of each of the episode's ``n_actions`` actions (with the control-period
        dilation of the episode's domain sample), for a driver that simulates a whole episode at
        once (:meth:`softcrawl.envs.backends.jaxvec.JaxBackend.run_episodes`)."""
        return [self._steps_of(k) for k in range(self.n_actions)]

    def _next_action(self) -> None:
        """Count the action just held (its planned steps: a diverged episode's clock runs on)."""
        self._t_steps += self._action_steps
        self._k += 1
        self._action_steps = self._steps_of(self._k)

    # -- gymnasium API ----------------------------------------------------------------------
    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode: ``options={"design": ...}`` (one value per slot of the space, or a string) or a random
        design of ``designs``. Returns ``(obs, info)``. A diverged settling is reported with
        ``info["diverged"]`` and the first step then terminates with reward 0."""
        design = self.begin_reset(seed=seed, options=options)
        return self.end_reset(self._episode_for(design, self.domain))

    # -- resets driven from outside (softcrawl.envs.backends.jaxvec: robots in a JAX batch) ----------
    def begin_reset(self, *, seed: int | None = None, options: dict | None = None) -> Design:
        """The first part of :meth:`reset`, for a driver that simulates the episode itself
        (:class:`softcrawl.envs.backends.jaxvec.JaxBackend`): seeds the RNG, draws the design
        (unless ``options`` gives one) and the domain sample (:attr:`domain`), clears the
        history. Returns the design; finish with :meth:`end_reset`."""
        super().reset(seed=seed)
        options = options or {}
        if options.get("design") is not None:
            design = self.space.validate_design(options["design"])
        else:
            design = self.designs[int(self.np_random.integers(len(self.designs)))]
        self.design = design
        self.domain = (self.randomize.draw(self.np_random, self.space.n_regulators) if self.randomize is not None
                       else None)
        self._one_hot = self.space.one_hot_batch([design])[0]
        self._hist[:] = 0.0
        self._k = self._t_steps = 0
        self._action_steps = self._steps_of(0)
        self._dead, self._reason = False, ""
        return design

    def end_reset(self, episode) -> tuple[np.ndarray, dict]:
        """The last part of :meth:`reset`: start ``episode`` (an :class:`Episode` of the design
        :meth:`begin_reset` drew, or an object with the attributes of one this env reads) and
        return ``(obs, info)``."""
        self.episode = episode
        try:
            self.episode.reset()
        except SimulationDiverged as exc:
            self._dead, self._reason = True, f"settling diverged: {exc}"
        settled = self.episode.settled
        if settled is not None:
            self._robots.keep_settled(self.design, self.episode.robot, settled)
        self._settled_info = settled.as_dict() if settled is not None else {}
        self._origin = self.task.origin(self.episode)
        return self._obs(), self._info()

    def step(self, action):
        """Apply one action for ``steps_per_action`` steps; returns
        ``(obs, reward, terminated, truncated, info)`` (reward in the task's unit)."""
        kpa = self.begin_action(action)
        error = None
        if kpa is not None:
            try:
                for _ in range(self.steps_per_action):
                    self.episode.step(kpa)
            except SimulationDiverged as exc:
                error = exc
        return self.end_action(error)

    # -- stepping driven from outside (softcrawl.envs.backends.batched: many envs' robots in one batch) ------
    def begin_action(self, action) -> np.ndarray | None:
        """The first part of :meth:`step`, for a driver that steps many envs' robots together
        (:class:`softcrawl.envs.backends.batched.BatchedBackend`): checks ``action`` and records it in the
        history. Returns the commanded real kPa ``(R,)`` to hold for :attr:`steps_per_action`
        simulator steps (:meth:`Episode.next_control` for each, the driver setting
        ``episode.state``), or None if this episode's simulation has diverged (nothing to step).
        Finish with :meth:`end_action`.

        Raises:
            RuntimeError: before :meth:`reset`. ValueError: an invalid action.
        """
        if self.episode is None:
            raise RuntimeError("call reset() before step()")
        a = np.asarray(action, dtype=np.float32).reshape(-1)
        if a.shape != self.action_space.shape or not np.all(np.isfinite(a)):
            raise ValueError(f"action must be {self.action_space.shape[0]} finite numbers in [-1, 1], got {action!r}")
        a = np.clip(a, -1.0, 1.0)
        self._action_kpa, self._action_before = action_to_kpa(a), self._progress()
        if self.history:
            self._hist[1:] = self._hist[:-1].copy()
            self._hist[0] = a
        return None if self._dead else self._action_kpa

    def end_action(self, error: SimulationDiverged | None = None):
        """The last part of :meth:`step` once the driver has stepped the episode (``error``: the
        divergence that stopped it, if any): ``(obs, reward, terminated, truncated, info)``
        (reward in the task's unit)."""
        if error is not None:
            self._dead, self._reason = True, str(error)
        self._next_action()
        if self._k >= self.n_actions and not self._dead and self.task.vent_seconds > 0:
            self._vent()
        reward = self.task.reward(self._action_before, self._progress())
        if not math.isfinite(reward):
            reward = 0.0
        terminated = self._dead or self.task.reached(self.episode, self._origin)
        truncated = (not terminated) and self._k >= self.n_actions
        return self._obs(), float(reward), terminated, truncated, self._info(self._action_kpa)

    def _vent(self) -> None:
        """After the last action: every regulator at 0 kPa for the task's
        :attr:`~softcrawl.tasks.Task.vent_seconds` (rounded to whole steps), so the episode is
        scored at rest (:mod:`softcrawl.tasks.base`); a divergence ends it as in :meth:`step`."""
        zero = np.zeros(len(self.episode.applied))
        try:
            for _ in range(int(round(self.task.vent_seconds / self.episode.dt))):
                self.episode.step(zero)
        except SimulationDiverged as exc:
            self._dead, self._reason = True, str(exc)

    def close(self) -> None:
        """Leave the robot cache (a shared one keeps its robots for the other envs)."""
        if self._robots is not None:
            self._robots.detach()
            self._robots = None
        super().close()

    def cached_robot(self, design) -> tuple[Robot, SettledState | None]:
        """The robot of ``design`` from this env's cache (built and cached if missing) and its
        settled state (None: not settled yet), for drivers that settle many robots together
        before :meth:`reset` (:meth:`softcrawl.envs.backends.batched.BatchedBackend.settle_together`)."""
        episode = self._episode_for(self.space.validate_design(design))
        return episode.robot, episode.settled

    def store_settled(self, design, settled: SettledState) -> None:
        """Cache ``settled`` (from :func:`~softcrawl.robot.episode.settle` of ``design``'s robot with
        this env's :attr:`settling`) for ``design``'s cached robot: :meth:`reset` starts from it."""
        design = self.space.validate_design(design)
        if design in self._robots:
            self._robots.keep_settled(design, self._robots[design][0], settled)
