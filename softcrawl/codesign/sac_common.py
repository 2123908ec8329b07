"""What both SAC learners (:mod:`softcrawl.codesign.sac`) share: their stable-baselines3
settings from a :class:`SACConfig`, and gradient updates overlapped with the simulation."""

from __future__ import annotations

import time

from softcrawl.codesign.config import SACConfig


def sb3_arguments(env, cfg: SACConfig) -> dict:
    """The keyword arguments of SB3's (and SBX's) ``SAC`` that both learners take from ``cfg``
    for vectorised env ``env``: ``gradient_steps`` per vectorised step =
    ``round(cfg.utd_ratio * env.num_envs)`` (at least 1), i.e. ``utd_ratio`` updates per
    transition (paper: 1); automatic temperature (initial 1) with target entropy
    ``cfg.target_entropy`` (-3 = -dim A); the time limit bootstrapped unless ``cfg.timeout``
    is ``"terminal"``."""
    return dict(
        buffer_size=cfg.buffer_size, learning_starts=cfg.learning_starts, batch_size=cfg.batch_size,
        tau=cfg.tau, gamma=cfg.gamma, train_freq=(1, "step"),
        gradient_steps=max(1, round(cfg.utd_ratio * env.num_envs)), ent_coef="auto", target_entropy=cfg.target_entropy,
        replay_buffer_kwargs={"handle_timeout_termination": cfg.timeout == "bootstrap"}, verbose=0)


class OverlappedUpdates:
    """Mixin before an SB3 off-policy algorithm: its ``train`` deferred while the envs step.

    With ``overlap`` (and an env with a ``while_stepping`` hook, :class:`DesignVecEnv`), the
    gradient updates due after a vectorised step are deferred and run while the envs simulate
    the next one (the workers are separate processes), so the learner costs wall time only
    where it takes longer than the simulation. The policy that picks the actions of step
    ``t + 1`` is then the one before the updates of step ``t`` (a lag of one vectorised step,
    as in asynchronous actor-learner schemes); the number of updates and the data they sample
    are those of SB3's schedule. :meth:`flush` runs deferred updates now (before a checkpoint,
    at the end of ``learn``). A subclass runs the updates in :meth:`run_updates`.

    Attributes:
        overlap: whether updates are deferred to the next env step.
        learner_seconds: wall seconds spent in gradient updates (all of them).
    """

    overlap = False
    _deferred = 0
    learner_seconds = 0.0

    def hook_overlap(self, overlap: bool) -> None:
        """Defer updates to the env's steps if ``overlap`` and the env has the hook."""
        self.overlap = overlap
        if overlap and hasattr(self.env, "while_stepping"):
            self.env.while_stepping = self.flush

    def train(self, gradient_steps: int, batch_size: int = 64) -> None:
        """The updates (:meth:`run_updates`) now, or (``overlap``) at the next env step."""
        if self.overlap and getattr(self.env, "while_stepping", None) == self.flush:
            self._deferred += gradient_steps
            return
        self._timed(gradient_steps, batch_size)

    def flush(self) -> None:
        """Run the deferred gradient updates now."""
        n, self._deferred = self._deferred, 0
        if n:
            self._timed(n, self.batch_size)

    def run_updates(self, gradient_steps: int, batch_size: int) -> None:
        raise NotImplementedError

    def _timed(self, gradient_steps: int, batch_size: int) -> None:
        t = time.perf_counter()
        self.run_updates(gradient_steps, batch_size)
        self.learner_seconds += time.perf_counter() - t
