"""Evaluating a trained co-design run: roll out its design-conditioned policy on a design, and
re-simulate the result (or the expert baseline) with the run's simulation settings.

Used by ``softcrawl evaluate`` and by the report (:mod:`softcrawl.codesign.report`): the best
design's gait (commanded vs applied pressures, x(t)) and the expert baseline's phase sweep at
the run's episode length (codesign.md, "Expert baseline").
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from softcrawl.codesign.config import TrainConfig
from softcrawl.codesign.run import Run
from softcrawl.gaits import ActionSequence
from softcrawl.robot.domain import DomainRanges
from softcrawl.robot.episode import EpisodeResult, run_episode
from softcrawl.tasks import Task, parse_task

#: Episodes sampled from the stochastic policy by default (:func:`evaluate_policy`'s ``samples``)
#: where a design's gait is chosen: with the deterministic episode, 12 candidate open-loop gaits,
#: as many as the phase lags the expert baselines are swept over (``softcrawl report``).
GAIT_SAMPLES = 11
#: Most episodes one evaluation runs: deterministic ones (``episodes``, ``softcrawl evaluate
#: --episodes`` and ``--randomize``) and sampled ones (``samples``, ``--samples`` of
#: ``evaluate``, ``report`` and ``deploy --run``) each; 10,000 episodes of the paper's 20 s are
#: hours of simulation.
MAX_EPISODES = MAX_SAMPLES = 10_000


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
        env: the :class:`softcrawl.envs.CrawlerEnv` (its robot cached; None in a
            :meth:`detached` one). config: the run's config
            (its ``env.randomize`` the ranges the episodes were drawn from).
        checkpoint: the checkpoint folder the policy came from.
        domains: per episode, its domain draw (:meth:`softcrawl.robot.domain.DomainSample.as_dict`;
            empty without randomization).
        sampled_returns: return of each episode with actions sampled from the stochastic policy
            (:attr:`unit`), after the deterministic ones. sampled_diverged: per sampled episode.
        sampled_actions: per sampled episode, its ``(n_actions, R)`` commanded real kPa.
    """

    design: tuple[int, ...]
    returns_cm: list
    diverged: list
    actions_kpa: np.ndarray
    env: object
    config: TrainConfig
    checkpoint: str
    domains: list = field(default_factory=list)
    sampled_returns: list = field(default_factory=list)
    sampled_diverged: list = field(default_factory=list)
    sampled_actions: list = field(default_factory=list)

    @property
    def task(self) -> Task:
        """The run's task (:mod:`softcrawl.tasks`)."""
        return parse_task(self.config.env.task)

    @property
    def unit(self) -> str:
        """The unit of :attr:`returns_cm`: the task's, ``"cm"`` or ``"deg"``."""
        return self.task.unit

    @property
    def chosen(self) -> int | None:
        """Which episode's actions are the design's gait: None for the first deterministic one,
        or the index of the sampled episode that returned strictly more than it (the highest;
        diverged ones never). An open-loop gait is a fixed action sequence, so any of them
        replays to its return: this picks the best of ``1 + samples`` candidate gaits, as the
        expert baselines pick the best of their phase lags."""
        best, pick = self.returns_cm[0] if not self.diverged[0] else -math.inf, None
        for k, (ret, bad) in enumerate(zip(self.sampled_returns, self.sampled_diverged)):
            if not bad and math.isfinite(ret) and ret > best:
                best, pick = ret, k
        return pick

    @property
    def gait_source(self) -> str:
        """``"deterministic"`` or ``"sample k"`` (k from 1): where :meth:`gait` comes from."""
        return "deterministic" if self.chosen is None else f"sample {self.chosen + 1}"

    @property
    def gait_return(self) -> float:
        """The return of :meth:`gait`'s episode, in :attr:`unit`."""
        return float(self.returns_cm[0] if self.chosen is None else self.sampled_returns[self.chosen])

    @property
    def gait_actions_kpa(self) -> np.ndarray:
        """``(n_actions, R)`` commanded real kPa of :meth:`gait`."""
        return np.asarray(self.actions_kpa if self.chosen is None else self.sampled_actions[self.chosen])

    def gait(self) -> ActionSequence:
        """The design's gait (:attr:`chosen`: the first deterministic episode's actions unless a
        sampled episode did better) with the run's hold time."""
        e, a = self.config.env, self.gait_actions_kpa
        return ActionSequence(a, hold=action_hold(e.robot.dt, e.steps_per_action, len(a)))

    def detached(self) -> PolicyEvaluation:
        """This evaluation without its env (picklable: what a worker process sends back)."""
        return replace(self, env=None)

    def with_env(self) -> PolicyEvaluation:
        """This evaluation with an env (a :meth:`detached` one gets a new
        :class:`softcrawl.envs.CrawlerEnv` of its config, reset to its design), as
        :meth:`resimulate` needs."""
        if self.env is not None:
            return self
        from softcrawl.codesign.factory import env_fn

        env = env_fn(self.config)()
        env.reset(options={"design": self.design})
        return replace(self, env=env)

    def resimulate(self, record_every: int | None = 10, progress: bool = False) -> EpisodeResult:
        """Re-run :meth:`gait` through :func:`softcrawl.robot.run_episode` (same
        robot, calibration and settling as the env): per-step commanded/applied pressures and
        positions, and ParaView frames every ``record_every`` steps.

        Raises:
            ValueError: a randomized evaluation (its episodes had other robots and rigs).
        """
        if self.domains:
            raise ValueError("resimulate re-runs a nominal episode; this evaluation was randomized")
        from softcrawl.tasks.base import scored_gait

        e = self.config.env
        gait, seconds = scored_gait(self.gait(), episode_seconds(self.config), self.task.vent_seconds)
        return run_episode(self.env.episode.robot, gait, seconds, self.env.calibration,
                           settling=e.settling(), record_every=record_every, progress=progress)


def evaluate_policy(run: str | Path, design, episodes: int = 1,
                    checkpoint: str | Path | None = None, randomize: DomainRanges | None = None,
                    seed: int | None = None, samples: int = 0) -> PolicyEvaluation:
    """Roll out the trained policy (deterministic actions) on ``design`` for ``episodes``
    episodes in a :class:`softcrawl.envs.CrawlerEnv` with the run's settings, then ``samples``
    nominal episodes with actions sampled from the stochastic policy (SAC's squashed Gaussian,
    its noise seeded by the run's seed, so the same call gives the same samples); the
    design's gait is the best of them all (:attr:`PolicyEvaluation.chosen`).

    The deterministic action is the squashed mean, which need not do what the policy's samples
    do (docs/codesign.md, "The design's gait": a turning policy whose mean scored a fifth of
    what its samples scored).

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
            ``episodes`` outside 1..:data:`MAX_EPISODES`, ``samples`` outside
            0..:data:`MAX_SAMPLES`, ``samples`` with ``randomize``, ranges the run's action
            timing cannot take.
        InvalidDesignError: an invalid design.
    """
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.factory import env_fn
    from softcrawl.codesign.sac import make_sac
    from softcrawl.envs import action_to_kpa

    if not 1 <= episodes <= MAX_EPISODES:
        raise ValueError(f"episodes must be 1 to {MAX_EPISODES}, got {episodes}")
    if not 0 <= samples <= MAX_SAMPLES or (samples and randomize is not None):
        raise ValueError(f"samples must be 0 to {MAX_SAMPLES} and nominal (no randomize), got {samples}")
    r = Run(run)
    cfg = r.read_config()
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

    def episode(k: int, deterministic: bool) -> tuple[float, bool, np.ndarray, dict]:
        obs, info = env.reset(seed=seed if k == 0 else None, options={"design": design})
        total, acts, done, last = 0.0, [], False, {}
        while not done:
            a, _ = model.predict(obs, deterministic=deterministic)
            obs, r, term, trunc, last = env.step(a)
            total += r
            acts.append(action_to_kpa(a))
            done = term or trunc
        return total, bool(last.get("diverged")), np.array(acts), info

    runs = [episode(k, True) for k in range(episodes)]
    sampled = [episode(episodes + k, False) for k in range(samples)]
    domains = [info["domain"] for *_, info in runs if "domain" in info]
    return PolicyEvaluation(design, [r[0] for r in runs], [r[1] for r in runs], runs[0][2], env, cfg, str(ck),
                            domains, [r[0] for r in sampled], [r[1] for r in sampled], [r[2] for r in sampled])


def baseline_sweep(run: str | Path, out: str | Path, phases, workers: int | None = None, progress: bool = False):
    """The expert baseline (the sine gait on the run's space's
    :func:`~softcrawl.design.baseline.sine_baseline_design`: the paper's
    :data:`softcrawl.design.BASELINE_DESIGN` in its space) swept over ``phases`` (degrees) with
    the run's robot settings and episode length, written to ``out`` (a ``softcrawl sweep-phase``
    output, resumable). Returns the :class:`softcrawl.robot.sweep.SweepResult`.

    Raises:
        ValueError: the run's space has no baseline design (one regulator).
    """
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.design.baseline import sine_baseline_design
    from softcrawl.robot.sweep import run_sweep

    cfg = load_run_config(run)
    space = cfg.env.design_space()
    design = sine_baseline_design(space)
    if design is None:
        raise ValueError(f"the design space {space.name!r} has no expert baseline design (one regulator)")
    return run_sweep(out, phases, design, robot_factory(cfg).config, duration=episode_seconds(cfg),
                     workers=workers, overwrite=True, progress=progress, space=space)
