"""Builders of a co-design run's simulation and design sampler from its :class:`TrainConfig`.

Shared by training (:mod:`softcrawl.codesign.training`) and by everything that re-uses a
trained run's settings (:mod:`softcrawl.codesign.evaluation`, the report, regret, deploy), so
none of those has to import the training driver. Everything returned is picklable (the
subprocess backend ships the env constructors to its workers).
"""

from __future__ import annotations

from functools import partial

from softcrawl.codesign.config import TrainConfig
from softcrawl.codesign.distribution import EntropySchedule, GibbsDesignDistribution
from softcrawl.codesign.sampler import GibbsDesignSampler
from softcrawl.envs.crawler import BuildRobot, CrawlerEnv
from softcrawl.envs.backends import make_backend
from softcrawl.envs.vec import DesignVecEnv


def robot_factory(cfg: TrainConfig) -> BuildRobot:
    """Picklable ``design -> Robot`` of ``cfg.env``'s design space with
    :meth:`EnvConfig.robot_config` (``cfg.env.robot`` for the paper's space; full-order or
    reduced model)."""
    return BuildRobot(cfg.env.robot_config(), cfg.env.design_space())


def env_fn(cfg: TrainConfig):
    """Zero-argument constructor of one :class:`CrawlerEnv` (picklable)."""
    e = cfg.env
    return partial(CrawlerEnv, robot_factory=robot_factory(cfg), steps_per_action=e.steps_per_action,
                   n_actions=e.n_actions, observe_state=e.observe_state, designs=e.designs(),
                   settling=e.settling(), max_cached=e.max_cached_robots, randomize=e.randomize, share_robots=True,
                   space=e.design_space(), task=e.task)


def jax_options(cfg: TrainConfig) -> dict:
    """The JAX backend's options of ``cfg`` (:class:`softcrawl.envs.backends.jaxvec.JaxBackend`)."""
    return {"precision": cfg.jax_precision, "solver": cfg.jax_solver, "iterations": cfg.jax_iterations or None}


def make_vec_env(cfg: TrainConfig, sampler, ray_address: str | None = None) -> DesignVecEnv:
    """The vectorised env of ``cfg`` (``cfg.backend``: serial, subprocess, ray on the cluster
    at ``ray_address`` or a local one, or jax with :func:`jax_options`,
    :func:`softcrawl.envs.backends.make_backend`) with ``sampler``, seeded with ``cfg.seed``."""
    venv = DesignVecEnv(make_backend(cfg.backend, [env_fn(cfg)] * cfg.n_envs, n_workers=cfg.n_workers or None,
                                     ray_address=ray_address, jax=jax_options(cfg)), sampler)
    venv.seed(cfg.seed)
    return venv


def check_reduction(cfg: TrainConfig) -> None:
    """Load and check the reduction file of a reduced-model config now (robots are built
    lazily, at the first reset), so a bad file fails before a run is started: the config's
    ``env.robot.reduction``, else the design space's (the paper's: the shipped one). The file
    must match the robot config, have been built for the space's actuator and disk
    (:meth:`softcrawl.design.spacefile.DesignSpace.part_record` at the config's mesh sizes) and,
    being the space's own file, have its ``reduction_sha256`` (the checks
    :func:`softcrawl.robot.build_robot` makes at the first reset).

    Raises:
        ValueError: neither names a reduction (the message says how to go on); and
            ReductionFileError, ReductionMismatchError (ValueErrors, one line): see
            :func:`softcrawl.reduction.artifact.load_reduction`.
    """
    if cfg.env.robot.model != "reduced":
        return
    import dataclasses

    from softcrawl.reduction.artifact import load_reduction

    config, space = cfg.env.robot_config(), cfg.env.design_space()
    path = config.reduction or space.reduction
    if path is None:
        raise ValueError(f'env.robot.model is "reduced" but the design space {space.name!r} names no reduction '
                         "([actuator] reduction) nor does env.robot.reduction: build one (softcrawl reduce build) "
                         'or train the full-order model (--set env.robot.model="full")')
    load_reduction(path, expect=dataclasses.asdict(config),
                   part=space.part_record(config.leg_mesh_size, config.disk_mesh_size),
                   sha256=space.reduction_sha256 if str(path) == space.reduction else None)


def make_sampler(cfg: TrainConfig) -> GibbsDesignSampler:
    """Design distribution over ``cfg.env.designs()`` with the entropy schedule of ``cfg``
    (its own RNG seeded with ``cfg.seed + 1``)."""
    dist = GibbsDesignDistribution(cfg.env.designs(), untried=cfg.design.untried, beta_max=cfg.design.beta_max,
                                   space=cfg.env.design_space())
    sched = EntropySchedule(t0=int(cfg.design.t0_fraction * cfg.total_steps),
                            t1=int(cfg.design.t1_fraction * cfg.total_steps), h_max=dist.h_max,
                            h_end=min(cfg.design.h_end, dist.h_max))
    return GibbsDesignSampler(dist, sched, seed=cfg.seed + 1)
