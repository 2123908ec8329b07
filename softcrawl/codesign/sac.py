"""Soft actor-critic for co-design: stable-baselines3's SAC with separate policy and Q learning
rates, one gradient update per environment transition (codesign.md, "Soft actor-critic").

Time limit. An episode ends after 20 actions by *truncation*: the observation (design + the
last 4 actions) does not contain the time, but the MDP continues physically, so the Q target
bootstraps through the cut (``r + gamma Q(s', a')``): SB3's replay buffer reads
``info["TimeLimit.truncated"]`` (set by :class:`softcrawl.envs.vec.DesignVecEnv`) with
``handle_timeout_termination=True``. The reference implementation treated the limit as a true
terminal (``SACConfig.timeout = "terminal"`` reproduces that). Divergence of the simulation is a
true terminal (no bootstrap).
"""

from __future__ import annotations

import time

import torch

from stable_baselines3 import SAC
from stable_baselines3.common.logger import Logger

from softcrawl.codesign.config import SACConfig


class SplitLRSAC(SAC):
    """SAC whose critic optimizer uses ``q_learning_rate`` (a float); the actor and the entropy
    temperature use ``learning_rate`` (SB3's).

    With ``overlap`` (and an env with a ``while_stepping`` hook, :class:`DesignVecEnv`), the
    gradient updates due after a vectorised step are deferred and run while the envs simulate
    the next one (the workers are separate processes), so the learner costs wall time only
    where it takes longer than the simulation. The policy that picks the actions of step
    ``t + 1`` is then the one before the updates of step ``t`` (a lag of one vectorised step,
    as in asynchronous actor-learner schemes); the number of updates and the data they sample
    are those of SB3's schedule. :meth:`flush` runs deferred updates now (before a checkpoint,
    at the end of ``learn``).

    The actor's step differentiates the critics' Q values with respect to the action only: the
    critics' weights are frozen from their optimizer's step to the actor optimizer's step
    (optimizer hooks), so the actor's backward pass skips their weight gradients, which SB3
    computes and then discards (about 11% of an update's matrix products; updates 1.15-1.19x
    faster, ``CHANGELOG.md``, and the same to the bit, ``tests/test_learner.py``).
    Everything else is SB3's SAC.

    Attributes:
        learner_seconds: wall seconds spent in gradient updates (all of them).
    """

    def __init__(self, *args, q_learning_rate: float | None = None, overlap: bool = False, **kwargs):
        self.q_learning_rate = q_learning_rate
        self.overlap = overlap
        self._deferred = 0
        self.learner_seconds = 0.0
        super().__init__(*args, **kwargs)
        if overlap and hasattr(self.env, "while_stepping"):
            self.env.while_stepping = self.flush
        self.critic.optimizer.register_step_post_hook(lambda *_: self._critic_weight_grads(False))
        self.actor.optimizer.register_step_post_hook(lambda *_: self._critic_weight_grads(True))

    def _critic_weight_grads(self, on: bool) -> None:
        for p in self.critic.parameters():
            p.requires_grad_(on)

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """SB3's updates, or (``overlap``) deferred to the next env step (:meth:`flush`)."""
        if self.overlap and getattr(self.env, "while_stepping", None) == self.flush:
            self._deferred += gradient_steps
            return
        self._train(gradient_steps, batch_size)

    def flush(self) -> None:
        """Run the deferred gradient updates now."""
        n, self._deferred = self._deferred, 0
        if n:
            self._train(n, self.batch_size)

    def _train(self, gradient_steps: int, batch_size: int) -> None:
        t = time.perf_counter()
        self._critic_weight_grads(True)  # in case an interrupted update left them frozen
        super().train(gradient_steps, batch_size)
        self.learner_seconds += time.perf_counter() - t

    def _update_learning_rate(self, optimizers) -> None:
        critic_opt = self.critic.optimizer
        super()._update_learning_rate([o for o in optimizers if o is not critic_opt])
        if self.q_learning_rate is not None:
            for group in critic_opt.param_groups:
                group["lr"] = float(self.q_learning_rate)
            self.logger.record("train/q_learning_rate", float(self.q_learning_rate))


def check_device(device: str) -> None:
    """Raise ValueError unless torch can place tensors on ``device`` ("cpu", "cuda", "cuda:N")."""
    if device == "cpu":
        return
    if not torch.cuda.is_available():
        raise ValueError(f"sac.device={device!r}, but torch {torch.__version__} sees no CUDA GPU "
                         "(use sac.device=cpu, or install a CUDA build of torch)")
    index = int(device.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise ValueError(f"sac.device={device!r}, but torch sees {torch.cuda.device_count()} CUDA GPU(s)")


def make_sac(env, cfg: SACConfig, seed: int | None = None) -> SplitLRSAC:
    """The SAC learner for a vectorised crawler env.

    ``gradient_steps`` per vectorised step = ``round(cfg.utd_ratio * env.num_envs)`` (at least 1),
    i.e. ``utd_ratio`` updates per transition (paper: 1). Networks: MLP ``cfg.net_arch`` with ReLU
    for the actor and both critics; Adam(β1 0.9, β2 0.999); automatic temperature with target
    entropy ``cfg.target_entropy`` (−3 = −dim A); updates overlapped with the simulation if
    ``cfg.overlap`` (:class:`SplitLRSAC`), on torch device ``cfg.device``. Its logger writes
    nowhere until ``set_logger`` is called (SB3's default would create ``/tmp/SB3-<date>/``).

    Raises:
        ValueError: ``cfg.device`` is a GPU this torch cannot use.
    """
    check_device(cfg.device)
    grad_steps = max(1, round(cfg.utd_ratio * env.num_envs))
    model = SplitLRSAC(
        "MlpPolicy", env,
        learning_rate=cfg.policy_lr, q_learning_rate=cfg.q_lr,
        buffer_size=cfg.buffer_size, learning_starts=cfg.learning_starts, batch_size=cfg.batch_size,
        tau=cfg.tau, gamma=cfg.gamma, train_freq=(1, "step"), gradient_steps=grad_steps,
        ent_coef="auto", target_entropy=cfg.target_entropy,
        replay_buffer_kwargs={"handle_timeout_termination": cfg.timeout == "bootstrap"},
        policy_kwargs={"net_arch": list(cfg.net_arch), "optimizer_kwargs": {"betas": (0.9, 0.999)}},
        seed=seed, device=cfg.device, verbose=0, overlap=cfg.overlap,
    )
    # a logger writing nowhere until the caller sets one: SB3's default makes /tmp/SB3-<date>/
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model
