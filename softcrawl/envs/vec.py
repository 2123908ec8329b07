"""Vectorised crawler rollouts: a stable-baselines3 ``VecEnv`` of N crawlers whose designs are
drawn at every (auto-)reset by a design sampler living in the learner's process
(codesign.md, "Each iteration"). The crawlers run in a backend (:mod:`softcrawl.envs.backends`:
in-process, subprocess workers, Ray actors or one JAX batch), one action at a time
(:meth:`DesignVecEnv.step`) or, for open-loop policies, a whole episode of every env at once
(:meth:`DesignVecEnv.run_episodes`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from stable_baselines3.common.vec_env import VecEnv

from softcrawl.design.space import Design
from softcrawl.envs.backends import EnvBackend


@dataclass
class VecStep:
    """One vectorised step of :meth:`DesignVecEnv.run_episodes`: ``obs`` ``(N, obs_dim)``,
    ``rewards`` ``(N,)``, ``dones`` ``(N,)`` and ``infos`` as :meth:`DesignVecEnv.step` returns
    them; ``live`` ``(N,)``: the envs that took an action at this step; ``ended`` ``(N,)``: the
    envs whose episode has ended (at this step or before)."""

    obs: np.ndarray
    rewards: np.ndarray
    dones: np.ndarray
    infos: list[dict]
    live: np.ndarray
    ended: np.ndarray


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
    the backend's envs step (they were started by :meth:`step_async`), and in
    :meth:`run_episodes` while they run their episodes: the learner's gradient updates overlap
    the simulation (:class:`softcrawl.codesign.sac_common.OverlappedUpdates`).
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
        obs, rewards, dones, infos, finished = self._record(results)
        if finished:
            for i, (o, _) in zip(finished, self._reset_envs(finished)):
                obs[i] = o
        return obs, rewards, dones, infos

    def _record(self, results: list) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[dict], list[int]]:
        """One vectorised step's ``(obs, rewards, dones, infos, finished)`` from the envs'
        transitions ``results`` (None for an env that did not step: zeros, ``{}``): returns and
        lengths accumulated, the SB3 keys of the finished episodes added to their infos and
        the episodes reported to the sampler (not reset)."""
        live = [r for r in results if r is not None]
        self.num_transitions += len(live)
        obs = np.zeros((self.num_envs, *live[0][0].shape), live[0][0].dtype)
        rewards = np.zeros(self.num_envs, np.float32)
        dones = np.zeros(self.num_envs, bool)
        infos: list[dict] = [{} for _ in range(self.num_envs)]
        finished = []
        for i, result in enumerate(results):
            if result is None:
                continue
            o, rew, term, trunc, info = result
            obs[i], rewards[i], info = o, rew, dict(info)
            self._returns[i] += rew
            self._lengths[i] += 1
            if term or trunc:
                dones[i] = True
                info["terminal_observation"] = o
                info["TimeLimit.truncated"] = bool(trunc and not term)
                info["episode"] = {"r": float(self._returns[i]), "l": int(self._lengths[i]),
                                   "t": float(info.get("t", 0.0))}
                finished.append(i)
            infos[i] = info
        if finished and self.sampler is not None:
            self.sampler.observe([self.designs[i] for i in finished], [self._returns[i] for i in finished],
                                 [bool(infos[i].get("diverged", False)) for i in finished], self.num_transitions)
        return obs, rewards, dones, infos, finished

    def run_episodes(self, actions: np.ndarray) -> list[VecStep]:
        """Every env's whole episode at once (open-loop policies), from the episode boundary
        after a reset: env ``i`` takes ``actions[i, k]`` (``actions`` ``(N, K, R)``, ``K`` the
        envs' ``n_actions``) until its episode ends, in one call of the backend
        (:meth:`~softcrawl.envs.backends.base.EnvBackend.run_episodes`: one compiled call on the
        JAX backend, one message per worker on the subprocess and Ray backends), with
        :attr:`while_stepping` run while the backend works.

        Returns the episodes' vectorised steps as :meth:`step` returns them for the same
        actions, exactly: each finished episode reported to the sampler at its step, with the
        SB3 keys in its info. An env whose episode ended before the last step waits
        (``live`` False from the next step on: zeros, ``{}``). Once all have ended, every env
        gets a new design from one ``sampler.sample(N)`` and is reset; the observation row of
        an env at the step its episode ended, and at every step it waited, is the first
        observation of its next episode (SB3's auto-reset convention), so the last step's
        observations are the next episodes' first ones.

        Raises:
            RuntimeError: an env inside an episode, or an episode not ended by ``K`` actions.
            ValueError: ``actions`` not ``(N, K, R)``.
        """
        if self.starting_designs() is None:
            raise RuntimeError("run_episodes starts every env's episode: call it right after a reset")
        actions = np.asarray(actions, dtype=np.float32)
        if actions.ndim != 3 or actions.shape[0] != self.num_envs or actions.shape[2:] != self.action_space.shape:
            raise ValueError(f"actions must be (n_envs {self.num_envs}, n_actions, {self.action_space.shape[0]}), "
                             f"got shape {actions.shape}")
        self.backend.episodes_send(actions)
        if self.while_stepping is not None:
            self.while_stepping()
        results = self.backend.episodes_recv()
        if any(not r or not (r[-1][2] or r[-1][3]) for r in results):
            raise RuntimeError(f"an episode did not end within the {actions.shape[1]} actions given")
        steps, ended = [], np.zeros(self.num_envs, bool)
        for k in range(max(len(r) for r in results)):
            res = [r[k] if k < len(r) else None for r in results]
            obs, rewards, dones, infos, _ = self._record(res)
            ended |= dones
            steps.append(VecStep(obs, rewards, dones, infos, np.array([r is not None for r in res]), ended.copy()))
        first = np.stack([o for o, _ in self._reset_envs(list(range(self.num_envs)))])
        for step in steps:
            step.obs[step.ended] = first[step.ended]
        return steps

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
