"""Vectorised crawler rollouts: a stable-baselines3 ``VecEnv`` of N crawlers whose designs are
drawn at every (auto-)reset by a design sampler living in the learner's process
(codesign.md, "Each iteration"). The crawlers run in a backend (:mod:`softcrawl.envs.backends`:
in-process, subprocess workers or Ray actors).
"""

from __future__ import annotations

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from softcrawl.design.space import Design
from softcrawl.envs.backends import EnvBackend


class DesignVecEnv(VecEnv):
    """SB3 ``VecEnv`` of crawler envs whose designs come from ``sampler`` at every reset.

    Args:
        backend: where the envs run (:mod:`softcrawl.envs.backends`).
        sampler: object with ``sample(n) -> list[design]`` and
            ``observe(designs, returns_cm, diverged, timestep)`` (e.g.
            :class:`softcrawl.codesign.GibbsDesignSampler`); None lets each env pick a random
            design.

    On every step the finished episodes (terminated or truncated) are first reported to
    ``sampler.observe`` (``timestep`` = transitions collected so far, :attr:`num_transitions`),
    then all of them get new designs from one ``sampler.sample(k)`` call and are reset
    (auto-reset, SB3 convention: ``infos[i]["terminal_observation"]``, ``"TimeLimit.truncated"``
    and Monitor-style ``"episode": {"r": return cm, "l": actions, "t": s}``, plus
    ``"design"`` and ``"diverged"``).

    :attr:`while_stepping` (None, or a zero-argument callable) runs in :meth:`step_wait` while
    the backend's envs step (they were started by :meth:`step_async`): the learner's gradient
    updates overlap the simulation (:class:`softcrawl.codesign.sac_common.OverlappedUpdates`).
    """

    def __init__(self, backend: EnvBackend, sampler=None):
        self.backend, self.sampler = backend, sampler  # before super(): it queries render_mode
        super().__init__(backend.num_envs, backend.observation_space, backend.action_space)
        self.num_transitions = 0
        self.designs: list[Design | None] = [None] * self.num_envs
        self._returns = np.zeros(self.num_envs)
        self._lengths = np.zeros(self.num_envs, np.int64)
        self._actions: np.ndarray | None = None
        self._resume: list[Design] | None = None
        self.while_stepping = None

    def _new_designs(self, k: int) -> list[Design | None]:
        return list(self.sampler.sample(k)) if self.sampler is not None else [None] * k

    def starting_designs(self) -> list[Design] | None:
        """The designs of the episodes every env has just started (none has taken an action),
        for a checkpoint; None if some env is inside an episode or has no design yet."""
        if self._lengths.any() or any(d is None for d in self.designs):
            return None
        return list(self.designs)

    def resume_with(self, designs) -> None:
        """Start the next :meth:`reset` with ``designs`` (one per env; from
        :meth:`starting_designs` of a checkpoint) instead of new draws from the sampler, so a
        run resumed at an episode boundary continues as the uninterrupted one did.

        Raises:
            ValueError: not one design per env.
        """
        if len(designs) != self.num_envs:
            raise ValueError(f"{len(designs)} designs to resume {self.num_envs} envs with")
        self._resume = list(designs)

    def _reset_envs(self, indices: list[int], designs: list | None = None) -> list[tuple[np.ndarray, dict]]:
        designs = self._new_designs(len(indices)) if designs is None else designs
        seeds = [self._seeds[i] for i in indices]
        out = self.backend.reset(indices, designs, seeds)
        for i, (_, info) in zip(indices, out):
            self.designs[i] = info.get("design")
            self.reset_infos[i] = info
            self._returns[i], self._lengths[i] = 0.0, 0
            self._seeds[i] = None
        return out

    def reset(self) -> np.ndarray:
        designs, self._resume = self._resume, None
        out = self._reset_envs(list(range(self.num_envs)), designs)
        return np.stack([o for o, _ in out])

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions, dtype=np.float32).reshape(self.num_envs, -1)
        self.backend.step_send(self._actions)

    def step_wait(self):
        if self._actions is None:
            raise RuntimeError("step_async must be called before step_wait")
        if self.while_stepping is not None:
            self.while_stepping()
        results = self.backend.step_recv()
        self._actions = None
        self.num_transitions += self.num_envs
        obs = np.stack([r[0] for r in results])
        rewards = np.array([r[1] for r in results], dtype=np.float32)
        dones = np.zeros(self.num_envs, bool)
        infos: list[dict] = []
        finished = []
        for i, (o, rew, term, trunc, info) in enumerate(results):
            info = dict(info)
            self._returns[i] += rew
            self._lengths[i] += 1
            if term or trunc:
                dones[i] = True
                info["terminal_observation"] = o
                info["TimeLimit.truncated"] = bool(trunc and not term)
                info["episode"] = {"r": float(self._returns[i]), "l": int(self._lengths[i]),
                                   "t": float(info.get("t", 0.0))}
                finished.append(i)
            infos.append(info)
        if finished:
            if self.sampler is not None:
                self.sampler.observe([self.designs[i] for i in finished], [self._returns[i] for i in finished],
                                     [bool(infos[i].get("diverged", False)) for i in finished], self.num_transitions)
            for i, (o, _) in zip(finished, self._reset_envs(finished)):
                obs[i] = o
        return obs, rewards, dones, infos

    def close(self) -> None:
        self.backend.close()

    def _indices(self, indices) -> list[int]:
        if indices is None:
            return list(range(self.num_envs))
        if isinstance(indices, int):
            return [indices]
        return list(indices)

    def get_attr(self, attr_name, indices=None):
        return self.backend.get_attr(attr_name, self._indices(indices))

    def set_attr(self, attr_name, value, indices=None):
        self.backend.set_attr(attr_name, value, self._indices(indices))

    def env_method(self, method_name, *method_args, indices=None, **method_kwargs):
        return self.backend.call(method_name, method_args, method_kwargs, self._indices(indices))

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._indices(indices))
