"""Soft actor-critic for co-design: separate policy and Q learning rates, one gradient update per
environment transition, automatic temperature (codesign.md, "Soft actor-critic"; Haarnoja et
al. 2018, "Soft Actor-Critic Algorithms and Applications", section 5).

Two learners run the same updates, ``sac.learner``:

* ``"sbx"`` (the default; :mod:`softcrawl.codesign.sac_jax`): SBX's SAC on JAX, all gradient
  updates due after a vectorised step in one compiled call, stable-baselines3's networks and
  losses (:mod:`softcrawl.codesign.sac_nets`); checkpoints of arrays (flax msgpack).
* ``"torch"`` (:mod:`softcrawl.codesign.sac_torch`): stable-baselines3's SAC; checkpoints read
  with ``torch.load(weights_only=True)``.

Given the same weights, batches and noise their updates agree to float32 rounding
(``tests/test_learner.py``).

Time limit. An episode ends after 20 actions by *truncation*: the observation (design + the
last 4 actions) does not contain the time, but the MDP continues physically, so the Q target
bootstraps through the cut (``r + gamma Q(s', a')``): SB3's replay buffer (both learners use
it) reads ``info["TimeLimit.truncated"]`` (set by :class:`softcrawl.envs.vec.DesignVecEnv`)
with ``handle_timeout_termination=True``. The reference implementation treated the limit as
a true terminal (``SACConfig.timeout = "terminal"`` reproduces that). Divergence of the
simulation is a true terminal (no bootstrap).
"""

from __future__ import annotations

from types import ModuleType

from softcrawl.codesign.config import LEARNERS, SACConfig


def learner_module(name: str) -> ModuleType:
    """The module of learner ``name`` (``"sbx"`` or ``"torch"``), imported now (JAX or torch).

    Each has ``make_sac``, ``configure_threads``, ``check_device``, ``learner_state_bytes``,
    ``decode_learner_state`` and ``restore_learner_state``.

    Raises:
        ValueError: an unknown name.
    """
    if name == "sbx":
        from softcrawl.codesign import sac_jax as module
    elif name == "torch":
        from softcrawl.codesign import sac_torch as module
    else:
        raise ValueError(f"sac.learner must be one of {LEARNERS}, got {name!r}")
    return module


def prepare_learner(cfg: SACConfig) -> None:
    """Set the learner's CPU threads and check its device, before any learner is built and
    before the env workers start.

    Raises:
        ValueError: ``cfg.device`` is not a device the learner can use.
    """
    module = learner_module(cfg.learner)
    module.configure_threads(cfg.threads)
    module.check_device(cfg.device)


def make_sac(env, cfg: SACConfig, seed: int | None = None, rollout: str = "action"):
    """The ``cfg.learner`` SAC learner for vectorised env ``env`` (its module's ``make_sac``);
    with ``rollout="episode"`` (:attr:`TrainConfig.rollout`) the sbx learner that trains on
    whole episodes with its replay buffer on its device
    (:func:`softcrawl.codesign.episodic.make_episodic_sac`).

    Raises:
        ValueError: ``cfg.device`` is not a device the learner can use; ``rollout="episode"``
            with another learner than ``"sbx"``.
    """
    if rollout == "episode":
        from softcrawl.codesign.episodic import make_episodic_sac

        return make_episodic_sac(env, cfg, seed)
    return learner_module(cfg.learner).make_sac(env, cfg, seed)
