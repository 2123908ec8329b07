"""Typed configuration of a co-design training run and its presets (codesign.md tables).

A :class:`TrainConfig` is a tree of dataclasses; it is dumped as ``config.json`` in the run
directory (with the software version) and read back by ``--resume``. ``override`` applies
``"section.field=value"`` strings (values parsed as JSON, else kept as strings).

Presets (all but ``smoke`` step the reduced model at dt = 0.02 s, 50 steps per 1-s action:
``softcrawl reduce validate --dt 0.02`` against the exact 0.01 s full-order references gave a
mean node error of 0.96 mm (0.79 mm at 0.01 s) and a baseline reward error of 1.3% (1.1%), and
the paper-best 20 s crawl +11.36 cm (0.01 s: +11.69 cm; full-order exact +10.66 cm), for half
the steps; with float32 RID products, ``env.robot.rid_dtype``, 0.95 mm and 3.0%; 0.04 s fails both
targets, 1.72 mm and 17%, at about twice the cost per step, ``docs/results.md``; and with
at most 100 Gauss-Seidel sweeps per chunk (``env.robot.contact_max_iterations``), 0.95 mm and
0.6%; ``--set env.robot.dt=0.01 env.steps_per_action=100 env.robot.rid_dtype=float64
env.robot.contact_max_iterations=250`` restores the reference step):

* ``paper``: the paper's table: 96 envs, 1M transitions, buffer 100K, batch 512, γ 0.95,
  policy lr 6e-4, Q lr 2e-3, τ 0.01, learning starts 10K, 1 update per transition,
  net [400, 200, 100]; entropy schedule t0 = 200K, t1 = 950K; the reduced model (shipped 6 mm
  leg reduction, 10 mm floating-frame disk) with 1 s actions, 20 per episode.
* ``reference``: ``paper`` with the authors' actual update schedule: one gradient update per
  vectorised step of 96 transitions (about 10K updates in all, codesign.md "Known flaws"),
  the time limit still a truncation.
* ``crawl``: the paper's episode (20 actions of 1 s) on the 280 three-legged designs with the
  coarse 25 mm disk, 16 envs in 2 worker processes, 64K transitions (3,200 episodes, about 11
  per design), one update per 2 transitions (batch 256), the entropy schedule of the paper
  scaled to the run: 41 min of training for seed 0 on the quiet 2-core VM (25.8 transitions/s;
  the overlapped learner cost 16% of the wall time when measured at 15.9 transitions/s).
* ``demo``: the README's first command (its time on 2 cores: docs/results.md): the same
  simulation as ``crawl`` (20 s episodes of 1 s actions, 280 three-legged designs), 8 envs in 2
  workers, 8K transitions (400 episodes), one update per 2 transitions (batch 128),
  stable-baselines3's torch learner (``sac.learner``; why: docs/codesign.md, "The ``demo``
  preset: what was tried").
* ``smoke``: CI, < 1 min: the reduced model at 0.01 s, 2 envs in-process, 2 steps per action,
  160 transitions, a shortlist of 2 designs.

Every preset but ``smoke`` ends with a shortlist of 8 designs (``shortlist``,
:mod:`softcrawl.codesign.shortlist`; docs/codesign.md, "The run's design": why 8, and its
cost).

The robot's settings are one :class:`softcrawl.robot.RobotConfig`, ``env.robot``; ``--set
env.FIELD=VALUE`` of a robot field (``env.dt``, ``env.leg_mesh_size``, ...) sets
``env.robot.FIELD``. A saved run's ``config.json`` of an older format is read through
:mod:`softcrawl.codesign.migrate`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import re
import types
import typing
from dataclasses import asdict, dataclass, field

from softcrawl.design.resolve import PAPER_SPACE, resolve_space
from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import DesignSpace
from softcrawl.envs.backends.factory import BACKENDS
from softcrawl.envs.backends.jaxcheck import check_jax_env, check_jax_task, check_precision
from softcrawl.fem.solver import RID_DTYPES
from softcrawl.robot.assembly import MODELS, RobotConfig
from softcrawl.robot.domain import DomainRanges
from softcrawl.robot.episode import Settling
from softcrawl.tasks import DEFAULT_TASK, parse_task

#: Bounds of the simulation settings shared with :class:`softcrawl.codesign.groundtruth.GroundTruthConfig`:
#: ``name: (low, high, unit)``, both included. The time step: the presets use 0.02 s and 0.01 s
#: (0.04 s already fails ``softcrawl reduce validate``, module docstring); mesh sizes in mm (the
#: leg's reference is 4 mm, the presets' 6 mm; the disk's 10 mm and 25 mm).
SIM_BOUNDS: dict[str, tuple[float, float, str]] = {
    "dt": (1e-4, 0.1, "s"),
    "leg_mesh_size": (2.0, 20.0, "mm"),
    "disk_mesh_size": (2.0, 50.0, "mm"),
}
#: Longest action hold and episode, simulated seconds (the paper: 1 s and 20 s).
MAX_HOLD_S, MAX_EPISODE_S = 60.0, 3600.0
#: Bounds of the other numeric settings of a :class:`TrainConfig` (dotted names as ``--set``
#: takes them; ``(low, high, unit)``, both included): far beyond every preset, short of a run
#: that cannot fit in memory or never ends (a 100,000,000-wide layer, a ten-billion-step run);
#: the seed as numpy's legacy seeding (which SB3 uses) takes it.
TRAIN_BOUNDS: dict[str, tuple[float, float, str]] = {
    "n_envs": (1, 4096, ""), "total_steps": (1, 10**10, ""), "n_workers": (0, 1024, ""), "seed": (0, 2**32 - 1, ""),
    "checkpoint_every": (1, 10**10, ""), "snapshot_every": (1, 10**10, ""), "keep_checkpoints": (2, 1000, ""),
    "shortlist": (1, 100, ""), "jax_iterations": (0, 10_000, ""),
    "env.steps_per_action": (1, 10_000, ""), "env.n_actions": (1, 10_000, ""),
    "env.robot.contact_max_iterations": (1, 100_000, ""), "env.robot.leg_collision_spacing": (0.0, 100.0, "mm"),
    "env.max_cached_robots": (1, 10_000, ""), "env.settle_max_seconds": (0.0, 60.0, "s"),
    "sac.buffer_size": (1, 10**7, ""), "sac.batch_size": (1, 65_536, ""), "sac.threads": (1, 256, ""),
    "sac.learning_starts": (0, 10**10, ""), "sac.policy_lr": (0.0, 1.0, ""), "sac.q_lr": (0.0, 1.0, ""),
    "sac.utd_ratio": (0.0, 64.0, ""), "sac.target_entropy": (-100.0, 100.0, ""),
    "design.beta_max": (0.0, 1e12, "1/cm"), "design.h_end": (-1e6, 1e6, ""),
    "design.t0_fraction": (0.0, 10.0, ""), "design.t1_fraction": (0.0, 10.0, ""),
}
#: Layers and widths of ``sac.net_arch``.
MAX_LAYERS, MAX_WIDTH = 16, 4096
#: Upper bounds of ``env.randomize`` ranges (the lower ones are
#: :data:`softcrawl.robot.domain.KEYS`'s): ``key: (low, high)``, both included. Scales of
#: stiffness and mass within a decade of the nominal robot (the reduction holds for 0.95-1.5
#: and 0.8-1.2), regulator gains and offsets within the regulator's 0-90 kPa, lags and the
#: control period within what makes the 1 s action a different gait (the rig: 1.062-1.070).
RANDOMIZE_BOUNDS: dict[str, tuple[float, float]] = {
    "friction": (0.0, 10.0), "youngs_scale": (0.1, 10.0), "mass_scale": (0.1, 10.0),
    "pressure_gain": (0.0, 5.0), "pressure_offset": (-90.0, 90.0), "tau_inflate": (0.0, 10.0),
    "tau_vent": (0.0, 10.0), "control_period": (0.5, 2.0),
}
TIMEOUTS = ("bootstrap", "terminal")
#: The :class:`RobotConfig` fields a design space gives (:meth:`EnvConfig.robot_config`).
PART_FIELDS = ("leg_mesh_size", "disk_mesh_size", "leg_mass", "disk_mass")
#: The SAC learners (:mod:`softcrawl.codesign.sac`): SBX's on JAX, stable-baselines3's on torch.
LEARNERS = ("sbx", "torch")
#: How transitions are collected (:attr:`TrainConfig.rollout`).
ROLLOUTS = ("episode", "action")
#: Contact solvers of the JAX backend (:data:`softcrawl.jaxsim.contact.DEFAULT_ITERATIONS`).
JAX_SOLVERS = ("apgd", "pgs")


def space_robot(robot: RobotConfig, space: DesignSpace) -> RobotConfig:
    """``robot`` for the robots of ``space``: ``robot`` itself for the paper's space, else
    :meth:`RobotConfig.for_space` with ``robot``'s settings except the :data:`PART_FIELDS` still
    at the paper's defaults (``RobotConfig()``), which take the space's parts' values.

    Raises:
        ValueError, MeshError: as :meth:`RobotConfig.for_space`.
    """
    if space == DEFAULT_SPACE:
        return robot
    paper = RobotConfig()
    own = {k: v for k, v in dataclasses.asdict(robot).items() if k not in PART_FIELDS or v != getattr(paper, k)}
    return RobotConfig.for_space(space, **own)


def env_robot(**changes) -> RobotConfig:
    """The training robot (:attr:`EnvConfig.robot`'s default) with ``changes``: the reduced
    model at dt = 0.02 s, float32 RID products, 100 contact sweeps per chunk."""
    kw = {"model": "reduced", "rid_dtype": "float32", "dt": 0.02, "contact_max_iterations": 100}
    return RobotConfig(**(kw | changes))


@dataclass
class EnvConfig:
    """Simulation of one episode.

    Attributes:
        robot: the simulated robot (:class:`softcrawl.robot.RobotConfig`; the default,
            :func:`env_robot`: the reduced model, shipped reduction, 6 mm legs, 10 mm disk, at
            dt = 0.02 s (validated against the exact 0.01 s model, module docstring), RID
            products in float32 (``softcrawl reduce validate --dt 0.02 --rid-dtype float32``
            gave the same node error as float64, 0.95 mm, and a baseline reward error of 3.0%,
            for a 1.14x faster robot step) and at most 100 Gauss-Seidel contact sweeps per chunk
            (``softcrawl reduce validate --dt 0.02 --rid-dtype float32
            --contact-max-iterations 100`` gave a mean node error of 0.946 mm, 0.952 with 250,
            and a baseline reward error of 0.6%, 3.0%; the settling before an episode costs
            about 1.2x less, a step after it about 3% less); every other field the robot's
            default (friction 1.2, leg contact points at every surface node: 4 mm apart passes
            ``reduce validate`` for 1.04x end to end, no preset uses it).
        steps_per_action: steps per action (hold = robot.dt * steps_per_action s).
        n_actions: actions per episode (20). observe_state: robot-state summary in the observation.
        settle_speed, settle_hold, settle_max_seconds: the rest rule of the zero-pressure
            settling before each episode (mm/s, s, s; :class:`softcrawl.robot.Settling`);
            presets may change the threshold, not skip settling.
        legs: leg counts of the designs in play (default 3..6: all 6,972 canonical designs of
            the paper's space); within the space's ``min_legs..max_legs``.
        space: the design space: a shipped space's name (``"paper"``, the default; ``"hex6"``)
            or a space file's path (:func:`softcrawl.design.resolve.resolve_space`; a saved
            run reads its own copy, ``space.toml``, :mod:`softcrawl.codesign.run`).
        max_cached_robots: robots kept per worker process beyond one per env (LRU, shared by its envs;
            the settled states of dropped robots stay longer, up to 128 MB per worker:
            :mod:`softcrawl.envs.robot_cache`).
        randomize: domain randomization ranges drawn per episode
            (:class:`softcrawl.robot.domain.DomainRanges`; default: off, every range null).
            ``--set env.randomize.friction=[0.8,1.6]`` sets one range,
            ``--set env.randomize=rig`` the rig's measured ranges, ``env.randomize=off`` (or
            ``null``) none. Every range lies within :data:`RANDOMIZE_BOUNDS`.
        task: what the episodes reward (:mod:`softcrawl.tasks`, docs/tasks.md): a task's name
            (default ``"forward"``, the paper's) or a table with its name and settings
            (``--set 'env.task={"name": "heading", "heading_deg": 90}'``; ``softcrawl train --task NAME``).
    """

    robot: RobotConfig = field(default_factory=env_robot)
    steps_per_action: int = 50
    n_actions: int = 20
    observe_state: bool = False
    settle_speed: float = 0.5
    settle_hold: float = 0.05
    settle_max_seconds: float = 3.0
    legs: tuple[int, ...] = (3, 4, 5, 6)
    space: str = PAPER_SPACE
    max_cached_robots: int = 16
    randomize: DomainRanges = field(default_factory=DomainRanges)
    task: str | dict = DEFAULT_TASK

    def settling(self) -> Settling:
        """The :class:`Settling` these fields describe (ValueError if invalid)."""
        return Settling(rest_speed=self.settle_speed, hold_seconds=self.settle_hold,
                        max_seconds=self.settle_max_seconds)

    def design_space(self) -> DesignSpace:
        """The :class:`DesignSpace` ``space`` names (SpaceFileError, a ValueError, if it names none)."""
        return resolve_space(self.space)

    def designs(self) -> tuple[tuple[int, ...], ...]:
        """The space's canonical designs with a leg count in ``legs`` (sorted)."""
        return tuple(d for d in self.design_space().canonical_designs if sum(v > 0 for v in d) in self.legs)

    def robot_config(self) -> RobotConfig:
        """The simulated robot's settings: ``robot`` for the paper's space; for another space
        :meth:`RobotConfig.for_space` with ``robot``'s settings, except the part settings
        (:data:`PART_FIELDS`) still at the paper's defaults, which take the space's values (its
        parts' mesh sizes and masses; a preset's coarse 25 mm disk stays 25 mm).

        Raises:
            SpaceFileError: as :meth:`design_space`; ValueError, MeshError: as ``for_space``.
        """
        return space_robot(self.robot, self.design_space())


@dataclass
class SACConfig:
    """SAC hyper-parameters (paper table; see :mod:`softcrawl.codesign.sac`).

    ``learner``: ``"sbx"`` (SBX's SAC on JAX, :mod:`softcrawl.codesign.sac_jax`; the default)
    or ``"torch"`` (stable-baselines3's SAC, :mod:`softcrawl.codesign.sac_torch`): the same
    updates; a run's checkpoints are read by the learner that wrote them. ``timeout``:
    ``"bootstrap"`` (time limit is a truncation, default) or ``"terminal"`` (reference
    implementation). ``overlap``: run the gradient updates of a vectorised step while the
    envs simulate the next one (the policy acting lags one vectorised step behind the
    updates). ``threads``: CPU threads of the learner (XLA's and torch's; 1: the simulation has the other cores; more where cores are
    plentiful; set when the learner's library starts in the process,
    :func:`softcrawl.codesign.sac.prepare_learner`). ``device``: where the networks and their
    updates are, ``"cpu"`` or ``"gpu"`` / ``"gpu:N"`` (``"cuda"`` / ``"cuda:N"`` are read as
    the same; a GPU takes the learner off the simulation's cores; the env workers never use
    it; checkpoints are read onto the CPU, so ``report`` and ``evaluate`` need no GPU)."""

    policy_lr: float = 6e-4
    q_lr: float = 2e-3
    buffer_size: int = 100_000
    batch_size: int = 512
    gamma: float = 0.95
    tau: float = 0.01
    learning_starts: int = 10_000
    utd_ratio: float = 1.0
    net_arch: tuple[int, ...] = (400, 200, 100)
    target_entropy: float = -3.0
    timeout: str = "bootstrap"
    overlap: bool = True
    threads: int = 1
    device: str = "cpu"
    learner: str = "sbx"


@dataclass
class DesignConfig:
    """Design distribution: entropy schedule as fractions of the run (paper 0.2 and 0.95 of 1M),
    handling of untried designs (:mod:`softcrawl.codesign.distribution`), ``beta_max`` (1/cm)."""

    t0_fraction: float = 0.2
    t1_fraction: float = 0.95
    h_end: float = 0.0
    untried: str = "mean"
    beta_max: float = 1e6


@dataclass
class TrainConfig:
    """A whole run. Steps count environment transitions (one action of one env).

    ``backend``: where the envs run (:data:`BACKENDS`; ``"jax"``: all of them one batch of the
    JAX engine on JAX's default device, the reduced robot only and the rig quantities of
    ``env.randomize`` only, :mod:`softcrawl.envs.backends.jaxvec`). ``jax_precision``: that
    backend's floats, ``"float64"``, ``"float32"`` or ``"auto"`` (float32 where JAX has a GPU, else
    float64: :func:`~softcrawl.envs.backends.jaxcheck.resolve_precision`). ``jax_solver``,
    ``jax_iterations``: that backend's contact solve, ``"apgd"`` (the default) or ``"pgs"``
    (:func:`softcrawl.jaxsim.contact.solve_contacts`), and its iterations per step (0: the
    solver's default, for ``"pgs"`` ``env.robot.contact_max_iterations`` sweeps). ``rollout``:
    ``"episode"`` (every env's whole episode at once from actions drawn at its start, replay
    buffer and updates on the learner's device, :mod:`softcrawl.codesign.episodic`; open-loop
    policies and the ``sbx`` learner only) or ``"action"`` (stable-baselines3's loop, one
    vectorised step at a time; what a policy that observes the robot's state needs). ``shortlist``:
    how many of the most promising designs are tried with the trained policy's gaits when
    training ends, the run's design the best of them (:mod:`softcrawl.codesign.shortlist`; 1: the
    most probable design, what runs of config format < 7 chose)."""

    preset: str = "paper"
    n_envs: int = 96
    total_steps: int = 1_000_000
    seed: int = 0
    backend: str = "subprocess"
    n_workers: int = 0  # 0: one per CPU core
    jax_precision: str = "auto"
    jax_solver: str = "apgd"
    jax_iterations: int = 0
    checkpoint_every: int = 50_000
    snapshot_every: int = 20_000
    keep_checkpoints: int = 2
    rollout: str = "episode"
    shortlist: int = 8
    env: EnvConfig = field(default_factory=EnvConfig)
    sac: SACConfig = field(default_factory=SACConfig)
    design: DesignConfig = field(default_factory=DesignConfig)

    def validate(self) -> TrainConfig:
        """Raise ValueError naming the first bad setting (types, consistency, and the bounds of
        :data:`SIM_BOUNDS`, :data:`TRAIN_BOUNDS`, :data:`RANDOMIZE_BOUNDS`, ``sac.net_arch``
        and the hold and episode lengths); returns self."""
        def pos_int(name, v):
            if int(v) != v or v < 1:
                raise ValueError(f"{name} must be a positive integer, got {v!r}")
        for name in ("n_envs", "total_steps", "checkpoint_every", "snapshot_every", "keep_checkpoints"):
            pos_int(name, getattr(self, name))
        if not isinstance(self.env.robot, RobotConfig):
            raise ValueError(f"env.robot must be RobotConfig, got {type(self.env.robot).__name__}")
        robot = self.env.robot
        for name in ("steps_per_action", "n_actions", "max_cached_robots"):
            pos_int(f"env.{name}", getattr(self.env, name))
        pos_int("env.robot.contact_max_iterations", robot.contact_max_iterations)
        if robot.refactor_every is not None:
            pos_int("env.robot.refactor_every", robot.refactor_every)
        spacing = robot.leg_collision_spacing
        if isinstance(spacing, bool) or not isinstance(spacing, (int, float)) or not (math.isfinite(spacing)
                                                                                      and spacing >= 0):
            raise ValueError(f"env.robot.leg_collision_spacing must be >= 0 mm, got {spacing!r}")
        for name in ("buffer_size", "batch_size", "threads"):
            pos_int(f"sac.{name}", getattr(self.sac, name))
        if self.keep_checkpoints < 2:
            raise ValueError(f"keep_checkpoints must be >= 2 (a damaged newest checkpoint falls back to the one "
                             f"before), got {self.keep_checkpoints}")
        if self.sac.batch_size > self.sac.buffer_size:
            raise ValueError(f"sac.batch_size ({self.sac.batch_size}) must not exceed sac.buffer_size "
                             f"({self.sac.buffer_size})")
        if not self.sac.net_arch or any(isinstance(n, bool) or int(n) != n or n < 1 for n in self.sac.net_arch):
            raise ValueError(f"sac.net_arch must be a non-empty list of positive layer widths, got {self.sac.net_arch}")
        if robot.reduction is not None and robot.model != "reduced":
            raise ValueError(f"env.robot.reduction is set but env.robot.model is {robot.model!r}: a reduction file "
                             "is used only by the reduced model")
        settling = self.env.settling()
        if not isinstance(self.env.randomize, DomainRanges):
            raise ValueError(f"env.randomize must be DomainRanges, got {type(self.env.randomize).__name__}")
        self.env.randomize.check_steps(self.env.steps_per_action)
        if settling.max_seconds <= 0:
            raise ValueError("env.settle_max_seconds must be positive: episodes start from the robot at rest")
        if robot.rid_dtype not in RID_DTYPES:
            raise ValueError(f"env.robot.rid_dtype must be one of {RID_DTYPES}, got {robot.rid_dtype!r}")
        if robot.model not in MODELS:
            raise ValueError(f"env.robot.model must be one of {MODELS}, got {robot.model!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {tuple(BACKENDS)}, got {self.backend!r}")
        check_precision(self.jax_precision)
        try:
            task = parse_task(self.env.task)
            task.check_floor(robot.friction)
        except ValueError as exc:
            raise ValueError(f"env.task: {exc}") from None
        if self.backend == "jax":
            check_jax_env(self.env.robot.model, self.env.randomize)
            check_jax_task(task)
        if not re.fullmatch(r"cpu|(gpu|cuda)(:\d+)?", self.sac.device):
            raise ValueError(f"sac.device must be 'cpu', 'gpu' or 'gpu:N' ('cuda' is read as 'gpu'), got "
                             f"{self.sac.device!r}")
        if self.sac.learner not in LEARNERS:
            raise ValueError(f"sac.learner must be one of {LEARNERS}, got {self.sac.learner!r}")
        if self.sac.timeout not in TIMEOUTS:
            raise ValueError(f"sac.timeout must be one of {TIMEOUTS}, got {self.sac.timeout!r}")
        if self.jax_solver not in JAX_SOLVERS:
            raise ValueError(f"jax_solver must be one of {JAX_SOLVERS}, got {self.jax_solver!r}")
        if self.rollout not in ROLLOUTS:
            raise ValueError(f"rollout must be one of {ROLLOUTS}, got {self.rollout!r}")
        if self.rollout == "episode":
            why = ("env.observe_state is set" if self.env.observe_state else
                   f"task {task.name!r} observes the robot's state" if task.observes_state else
                   f"sac.learner is {self.sac.learner!r}" if self.sac.learner != "sbx" else None)
            if why:
                raise ValueError(f'rollout "episode" draws each episode\'s actions at its start, for an open-loop '
                                 f'policy on the "sbx" learner, but {why}: use rollout="action"')
        try:
            space = self.env.design_space()
        except ValueError as exc:
            raise ValueError(f"env.space: {exc}") from None
        lo, hi = space.min_legs, space.max_legs
        if not self.env.legs or any(k not in range(lo, hi + 1) for k in self.env.legs):
            raise ValueError(f"env.legs must be a non-empty subset of {lo}..{hi}"
                             f"{'' if space == DEFAULT_SPACE else ' (the legs of space ' + repr(space.name) + ')'}, "
                             f"got {self.env.legs}")
        if not 0 <= self.design.t0_fraction <= self.design.t1_fraction:
            raise ValueError("design fractions need 0 <= t0_fraction <= t1_fraction")
        if not (0 < self.sac.gamma <= 1 and 0 < self.sac.tau <= 1 and self.sac.utd_ratio > 0):
            raise ValueError("sac.gamma and sac.tau must be in (0, 1], sac.utd_ratio > 0")
        if self.n_workers < 0 or self.sac.learning_starts < 0:
            raise ValueError("n_workers and sac.learning_starts must be >= 0")
        if not all(math.isfinite(v) and v > 0 for v in (robot.dt, self.sac.policy_lr, self.sac.q_lr)):
            raise ValueError("env.robot.dt, sac.policy_lr and sac.q_lr must be positive")
        self._check_bounds()
        return self

    def _check_bounds(self) -> None:
        """The bounds of :data:`SIM_BOUNDS`, :data:`TRAIN_BOUNDS`, :data:`RANDOMIZE_BOUNDS`, the
        network's size and the hold and episode lengths (ValueError naming the setting)."""
        def get(name):
            obj = self
            for part in name.split("."):
                obj = getattr(obj, part)
            return obj
        for name, (low, high, unit) in (TRAIN_BOUNDS | {f"env.robot.{k}": b for k, b in SIM_BOUNDS.items()}).items():
            check_bounds(name, get(name), low, high, unit)
        if self.env.robot.refactor_every is not None:
            check_bounds("env.robot.refactor_every", self.env.robot.refactor_every, 1, 10**6)
        if len(self.sac.net_arch) > MAX_LAYERS or max(self.sac.net_arch) > MAX_WIDTH:
            raise ValueError(f"sac.net_arch must have at most {MAX_LAYERS} layers of at most {MAX_WIDTH} units, "
                             f"got {list(self.sac.net_arch)}")
        check_randomize(self.env.randomize)
        e, stretch = self.env, (self.env.randomize.control_period or (1.0, 1.0))[1]
        hold = e.robot.dt * e.steps_per_action * stretch
        if hold > MAX_HOLD_S or hold * e.n_actions > MAX_EPISODE_S:
            raise ValueError(f"env.robot.dt x env.steps_per_action (x env.randomize.control_period) is a {hold:g} s action "
                             f"and a {hold * e.n_actions:g} s episode; at most {MAX_HOLD_S:g} s and "
                             f"{MAX_EPISODE_S:g} s")

    def to_dict(self) -> dict:
        """A JSON-ready nested dict (tuples stay tuples; ``json`` writes them as lists)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> TrainConfig:
        """Inverse of :meth:`to_dict` (:func:`build_config`: types checked, presets by name,
        missing keys of a sub-config from its default, so ``"env": {"robot": {"dt": 0.01}}`` is
        :func:`env_robot` at 0.01 s), validated. Only the current format: a saved
        ``config.json`` is read through :func:`softcrawl.codesign.migrate.read_settings`.

        Raises:
            ValueError: an unknown key, a value of the wrong type (the message names the key),
                or a setting :meth:`validate` refuses.
        """
        return build_config(cls, d).validate()


def build_config(kind, data, prefix: str = "", base=None):
    """The dataclass ``kind`` from a JSON object ``data``, each value checked against its
    field's type (:func:`check_field`; lists become tuples), sub-configs built alike: a string
    names a preset of a class that has them (``"randomize": "rig"``,
    :meth:`DomainRanges.preset`), an object without some keys takes them from the field's
    default (or ``base``). Not validated beyond the types and the class's own checks.

    Raises:
        ValueError: not an object, an unknown key, a value of the wrong type, a value the class
            refuses (each named as ``prefix`` + the field).
    """
    if isinstance(data, str) and callable(getattr(kind, "preset", None)):
        data = asdict(kind.preset(data))
    if not isinstance(data, dict):
        raise ValueError(f"{prefix.rstrip('.') or 'config'} must be an object, got {data!r}")
    names = {f.name: f for f in dataclasses.fields(kind)}
    unknown = set(data) - set(names)
    if unknown:
        raise ValueError(f"unknown {kind.__name__} settings: {sorted(unknown)}")
    if base is not None:
        data = asdict(base) | data
    hints = typing.get_type_hints(kind)
    kw = {}
    for k, v in data.items():
        if dataclasses.is_dataclass(hints[k]):
            default = names[k].default_factory
            kw[k] = build_config(hints[k], v, f"{prefix}{k}.", None if default is dataclasses.MISSING else default())
        else:
            kw[k] = check_field(f"{prefix}{k}", v, hints[k])
    try:
        return kind(**kw)
    except ValueError as exc:  # the class names its field: name the setting instead
        raise ValueError(str(exc).replace(f"{kind.__name__}.", prefix)) from None


def check_bounds(name: str, value, low: float, high: float, unit: str = "", open_low: bool = False) -> None:
    """Raise ValueError (naming setting ``name``) unless ``value`` is a number in ``[low, high]``
    (``(low, high]`` with ``open_low``; ``unit`` is printed after the bounds)."""
    number = isinstance(value, (int, float)) and not isinstance(value, bool)
    if not (number and (low < value if open_low else low <= value) and value <= high):  # NaN fails too
        raise ValueError(f"{name} must be a number in {'(' if open_low else '['}{low:g}, {high:g}]"
                         f"{' ' + unit if unit else ''}, got {value!r}")


def check_randomize(ranges: DomainRanges) -> None:
    """Raise ValueError unless every range of ``ranges`` lies within :data:`RANDOMIZE_BOUNDS`
    (the message names ``env.randomize.KEY``)."""
    for key, (low, high) in RANDOMIZE_BOUNDS.items():
        r = getattr(ranges, key)
        if r is not None and not (low <= r[0] and r[1] <= high):
            raise ValueError(f"env.randomize.{key} must lie within [{low:g}, {high:g}], got {list(r)}")


def _type_name(tp) -> str:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis or len(set(args)) != 1:
            return f"a list of {_type_name(args[0])}"
        return f"a list of {len(args)} {_type_name(args[0])}"
    if origin in (typing.Union, types.UnionType):
        return " or ".join("null" if a is type(None) else _type_name(a) for a in args)
    return getattr(tp, "__name__", None) or str(tp).replace("typing.", "")


def check_field(name: str, value, tp):
    """``value`` checked against the annotation ``tp`` of setting ``name`` (bool, int, float,
    str, ``X | None``, ``tuple[X, ...]``; other annotations pass through). Returns the value
    (lists as tuples; integral floats for ``int`` as int).

    Raises:
        ValueError: the value does not fit the type (names ``name``).
    """
    def fail():
        raise ValueError(f"{name} must be {_type_name(tp)}, got {value!r}")

    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        for t in (a for a in args if a is not type(None)):
            try:
                return check_field(name, value, t)
            except ValueError:
                pass
        fail()
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            fail()
        elems = args[:1] * len(value) if len(args) == 2 and args[1] is Ellipsis else args
        if len(elems) != len(value):
            fail()
        return tuple(check_field(f"{name}[{i}]", v, t) for i, (v, t) in enumerate(zip(value, elems)))
    if tp is bool:
        if not isinstance(value, bool):
            fail()
    elif tp is int:
        if isinstance(value, float) and math.isfinite(value) and value.is_integer():
            return int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            fail()
    elif tp is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            fail()
        try:
            float(value)
        except OverflowError:  # an integer beyond any float
            fail()
    elif tp is str:
        if not isinstance(value, str):
            fail()
    return value


PRESETS = ("paper", "reference", "crawl", "demo", "smoke")


def _coarse_env(dt: float = 0.02, **kw) -> EnvConfig:
    """The crawl, demo and smoke simulation: reduced 6 mm legs, 25 mm floating-frame disk (20 s
    paper-best crawl within 1% of the 10 mm disk at 0.02 s, 1.3x faster), the three-legged designs."""
    return EnvConfig(robot=env_robot(disk_mesh_size=25, dt=dt), legs=(3,), **kw)


def preset(name: str) -> TrainConfig:
    """The named preset (``paper``, ``reference``, ``crawl``, ``demo``, ``smoke``; see the
    module docstring)."""
    if name == "paper":
        return TrainConfig().validate()
    if name == "reference":
        return TrainConfig(preset="reference", sac=SACConfig(utd_ratio=1 / 96)).validate()
    if name == "crawl":
        return TrainConfig(
            preset="crawl", n_envs=16, total_steps=64_000, backend="subprocess", n_workers=2,
            checkpoint_every=3_200, snapshot_every=1_600, env=_coarse_env(), rollout="action",
            sac=SACConfig(buffer_size=100_000, batch_size=256, learning_starts=3_200, utd_ratio=0.5),
        ).validate()
    if name == "demo":
        return TrainConfig(
            preset="demo", n_envs=8, total_steps=8_000, backend="subprocess", n_workers=2,
            checkpoint_every=1_600, snapshot_every=320, env=_coarse_env(), rollout="action",
            sac=SACConfig(buffer_size=20_000, batch_size=128, learning_starts=800, utd_ratio=0.5, learner="torch"),
        ).validate()
    if name == "smoke":
        return TrainConfig(
            preset="smoke", n_envs=2, total_steps=160, backend="serial", n_workers=1,
            checkpoint_every=80, snapshot_every=40, shortlist=2,
            env=_coarse_env(dt=0.01, steps_per_action=2, n_actions=20),
            sac=SACConfig(buffer_size=1_000, batch_size=32, learning_starts=40),
        ).validate()
    raise ValueError(f"unknown preset {name!r}; choose one of {PRESETS}")


#: The settings a resumed run may change: where it runs, not what it learns (the learner's device,
#: the worker processes), e.g. a run started on a GPU machine and finished on a laptop:
#: ``softcrawl train --resume --out RUN --workers 2 --set sac.device="cpu"``.
PLACEMENT_KEYS = ("sac.device", "n_workers")


def place(cfg: TrainConfig, assignments: list[str]) -> TrainConfig:
    """``cfg`` with ``assignments`` (``"key=value"`` strings of :data:`PLACEMENT_KEYS` only) applied
    by :func:`override`; the run's ``config.json`` keeps the settings it was started with.

    Raises:
        ValueError: a key outside :data:`PLACEMENT_KEYS` (named), or as :func:`override`.
    """
    for a in assignments:
        key = a.split("=", 1)[0].strip()
        if key not in PLACEMENT_KEYS:
            raise ValueError(f"a resumed run keeps its config.json; only where it runs may change "
                             f"({', '.join(PLACEMENT_KEYS)}), not {key!r}")
    return override(cfg, assignments)


def override(cfg: TrainConfig, assignments: list[str]) -> TrainConfig:
    """Apply ``"field=value"`` / ``"section.field=value"`` strings (value parsed as JSON if
    possible, else taken as a string). Returns a validated copy.

    A sub-config with presets may be set by name (``env.randomize=rig``,
    :meth:`TrainConfig.from_dict`); ``null`` names its ``"off"`` preset. ``env.FIELD`` of a
    field of :class:`softcrawl.robot.RobotConfig` (``env.dt``, ``env.leg_mesh_size``, ...) sets
    ``env.robot.FIELD`` (an error names both).

    A setting given twice (``seed=1`` and ``seed=2``; ``env.dt`` and ``env.robot.dt``) is
    refused rather than the last one taken.

    Raises:
        ValueError: a malformed string, an unknown field, a setting given twice (both named), a
            value of the wrong type for its field (named), or a setting
            :meth:`TrainConfig.validate` refuses.
    """
    d, aliases, given = cfg.to_dict(), {}, {}
    for a in assignments:
        if "=" not in a:
            raise ValueError(f"override must look like section.field=value, got {a!r}")
        key, raw = a.split("=", 1)
        try:
            value = json.loads(raw)
        except json.JSONDecodeError:
            value = raw
        parts = key.strip().split(".")
        if len(parts) == 2 and parts[0] == "env" and parts[1] in _ROBOT_FIELDS and parts[1] not in d["env"]:
            parts = ["env", "robot", parts[1]]
            aliases[".".join(parts)] = key.strip()
        if ".".join(parts) in given:
            raise ValueError(f"{given['.'.join(parts)]!r} and {a!r} set {'.'.join(parts)} twice; give it once")
        given[".".join(parts)] = a
        target, kind = d, TrainConfig
        for p in parts[:-1]:
            if p not in target or not isinstance(target[p], dict):
                raise ValueError(f"unknown setting {key!r}")
            target, kind = target[p], typing.get_type_hints(kind)[p]
        if parts[-1] not in target:
            raise ValueError(f"unknown setting {key!r}")
        if isinstance(target[parts[-1]], dict) and parts != ["env", "task"]:  # a sub-config: by preset name
            sub = typing.get_type_hints(kind)[parts[-1]]
            if not callable(getattr(sub, "preset", None)):
                raise ValueError(f"{key.strip()} is a section; set its fields ({key.strip()}.FIELD=VALUE)")
            if value is None:
                value = "off"
            if not isinstance(value, str):
                raise ValueError(f"{key.strip()} must be a preset name or null (off), got {raw!r}")
            value = asdict(sub.preset(value))
        target[parts[-1]] = value
    try:
        return TrainConfig.from_dict(d)
    except ValueError as exc:
        msg = str(exc)
        for name, typed in aliases.items():
            msg = msg.replace(name, f"{typed} ({name})")
        raise ValueError(msg) from None


_ROBOT_FIELDS = frozenset(f.name for f in dataclasses.fields(RobotConfig))
