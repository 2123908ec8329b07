"""Evaluating a trained co-design run: roll out its design-conditioned policy on a design, and
re-simulate the result (or the expert baseline) with the run's simulation settings.

Used by ``softcrawl evaluate`` and by the report (:mod:`softcrawl.codesign.report`): the best
design's gait (commanded vs applied pressures, x(t)) and the expert baseline's phase sweep at
the run's episode length (codesign.md, "Expert baseline").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softcrawl.codesign.config import TrainConfig
from softcrawl.codesign.run import Run
from softcrawl.gaits import ActionSequence
from softcrawl.robot.domain import DomainRanges
from softcrawl.robot.episode import EpisodeResult, run_episode
from softcrawl.tasks import Task, parse_task


def load_run_config(run: str | Path) -> TrainConfig:
    """The :class:`TrainConfig` saved in ``run/config.json`` (:meth:`Run.read_config`).

    Raises:
        ValueError: ``run`` is not a training run, or its config is malformed.
    """
    return Run(run).read_config()


def episode_seconds(cfg: TrainConfig) -> float:
    """Length of one episode of the run's environment, s."""
    return cfg.env.n_actions * cfg.env.steps_per_action * cfg.env.robot.dt


def action_hold(dt: float, steps: int, n_actions: int) -> float:
    """Hold time (s) for an :class:`ActionSequence` so that step k gets action k // steps exactly
    (floor(k dt / hold) can round the wrong way at some boundaries; nudge hold down then)."""
    for hold in (dt * steps, dt * steps * (1 - 1e-9)):
        if all(math.floor(k * dt / hold) == k // steps for k in range(steps * n_actions)):
            return hold
    raise ValueError("cannot represent the action timing as an ActionSequence")  # pragma: no cover


@dataclass(frozen=True, eq=False)
class PolicyEvaluation:
    """Outcome of :func:`evaluate_policy`.

    Attributes:
        design: the canonical design (regulator k of the outputs is the canonical k).
        returns_cm: return of each episode in the run's task's unit (:attr:`unit`: cm for
            ``forward``, the paper's task). diverged: per episode.
        actions_kpa: ``(n_actions, R)`` real kPa commanded in the first episode (``R``: the
            space's regulators, 3 in the paper's).
        env: the :class:`softcrawl.envs.CrawlerEnv` (its robot cached). config: the run's config
            (its ``env.randomize`` the ranges the episodes were drawn from).
        checkpoint: the checkpoint folder the policy came from.
        domains: per episode, its domain draw (:meth:`softcrawl.robot.domain.DomainSample.as_dict`;
            empty without randomization).
    """

    design: tuple[int, ...]
    returns_cm: list
    diverged: list
    actions_kpa: np.ndarray
    env: object
    config: TrainConfig
    checkpoint: str
    domains: list = field(default_factory=list)

    @property
    def task(self) -> Task:
        """The run's task (:mod:`softcrawl.tasks`)."""
        return parse_task(self.config.env.task)

    @property
    def unit(self) -> str:
        """The unit of :attr:`returns_cm`: the task's, ``"cm"`` or ``"deg"``."""
        return self.task.unit

    def gait(self) -> ActionSequence:
        """The first episode's actions as a gait with the run's hold time."""
        e = self.config.env
        return ActionSequence(self.actions_kpa, hold=action_hold(e.robot.dt, e.steps_per_action, len(self.actions_kpa)))

    def resimulate(self, record_every: int | None = 10, progress: bool = False) -> EpisodeResult:
        """Re-run the first episode's actions through :func:`softcrawl.robot.run_episode` (same
        robot, calibration and settling as the env): per-step commanded/applied pressures and
        positions, and ParaView frames every ``record_every`` steps.

        Raises:
            ValueError: a randomized evaluation (its episodes had other robots and rigs).
        """
        if self.domains:
            raise ValueError("resimulate re-runs a nominal episode; this evaluation was randomized")
        e = self.config.env
        return run_episode(self.env.episode.robot, self.gait(), episode_seconds(self.config), self.env.calibration,
                           settling=e.settling(), record_every=record_every, progress=progress)


def evaluate_policy(run: str | Path, design, episodes: int = 1,
                    checkpoint: str | Path | None = None, randomize: DomainRanges | None = None,
                    seed: int | None = None) -> PolicyEvaluation:
    """Roll out the trained policy (deterministic actions) on ``design`` for ``episodes``
    episodes in a :class:`softcrawl.envs.CrawlerEnv` with the run's settings.

    The episodes are nominal (no domain randomization, even if the run trained with it) unless
    ``randomize`` gives ranges: then each episode draws its own domain from the env's RNG,
    seeded with ``seed`` at the first reset (:mod:`softcrawl.envs.crawler`).

    ``design`` is canonicalised first (regulators relabelled by first appearance; the policy
    only saw canonical designs).

    ``checkpoint`` (default: the run's newest complete one) must be a complete checkpoint of
    the run (its folder or its name); its networks are read by the learner that wrote it
    (:meth:`Run.load_learner`: arrays, or tensors with ``weights_only=True``) and the actions
    computed on the CPU, whatever device the run trained on.

    Raises:
        ValueError: not a training run, no complete checkpoint, a damaged or crafted one,
            ``episodes < 1``, ranges the run's action timing cannot take.
        InvalidDesignError: an invalid design.
    """
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.factory import env_fn
    from softcrawl.codesign.sac import make_sac
    from softcrawl.envs import action_to_kpa

    r = Run(run)
    cfg = r.read_config()
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    design = cfg.env.design_space().canonicalize(design)
    if checkpoint is None:
        ck = r.require_checkpoint()
    else:  # a folder, or a checkpoint's name (step-XXXXXXXXXX) in the run
        ck = Path(checkpoint) if Path(checkpoint).exists() else r.checkpoints_dir / str(checkpoint)
    learner = r.read_learner(ck)  # before the env is built
    cfg.env.randomize = randomize if randomize is not None else DomainRanges()
    env = env_fn(cfg)()
    cfg.sac.buffer_size = 1
    cfg.sac.device = "cpu"  # whatever the run trained on: 20 actions need no GPU
    cfg.sac.learner = r.checkpoint_learner(ck)
    model = make_sac(DummyVecEnv([lambda: env]), cfg.sac, seed=cfg.seed)
    r.load_learner(ck, model, learner)
    returns, diverged, first, domains = [], [], None, []
    for k in range(episodes):
        obs, info = env.reset(seed=seed if k == 0 else None, options={"design": design})
        if "domain" in info:
            domains.append(info["domain"])
        total, acts, done, info = 0.0, [], False, {}
        while not done:
            a, _ = model.predict(obs, deterministic=True)
            obs, r, term, trunc, info = env.step(a)
            total += r
            acts.append(action_to_kpa(a))
            done = term or trunc
        returns.append(total)
        diverged.append(bool(info.get("diverged")))
        first = first if first is not None else np.array(acts)
    return PolicyEvaluation(design, returns, diverged, first, env, cfg, str(ck), domains)


def baseline_sweep(run: str | Path, out: str | Path, phases, workers: int | None = None, progress: bool = False):
    """The expert baseline (:data:`softcrawl.design.BASELINE_DESIGN`, sine gait) swept over
    ``phases`` (degrees) with the run's robot settings and episode length, written to ``out``
    (a ``softcrawl sweep-phase`` output, resumable). Returns the
    :class:`softcrawl.robot.sweep.SweepResult`."""
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.design.space import BASELINE_DESIGN
    from softcrawl.robot.sweep import run_sweep

    cfg = load_run_config(run)
    return run_sweep(out, phases, BASELINE_DESIGN, robot_factory(cfg).config, duration=episode_seconds(cfg),
                     workers=workers, overwrite=True, progress=progress)
