"""The interface of a vector env's backend (where its N crawler envs live and run).

A backend resets envs given their indices, designs and seeds, steps all envs (one action each,
:meth:`EnvBackend.step`) or runs every env's whole episode from given actions
(:meth:`EnvBackend.run_episodes`, for open-loop policies), and forwards ``get_attr`` /
``set_attr`` / ``call`` to the envs it holds; :class:`EnvBackend` is that contract.
"""

from __future__ import annotations

from collections.abc import Sequence

import gymnasium as gym
import numpy as np

from softcrawl.design.space import Design

#: One env's transition, as :meth:`gymnasium.Env.step` returns it: ``(observation, reward,
#: terminated, truncated, info)``.
StepResult = tuple[np.ndarray, float, bool, bool, dict]


class EnvBackend:
    """Where the N environments live. Subclasses implement the methods below."""

    num_envs: int
    observation_space: gym.Space
    action_space: gym.Space

    def reset(self, indices: Sequence[int], designs: Sequence[Design | None],
              seeds: Sequence[int | None]) -> list[tuple[np.ndarray, dict]]:  # pragma: no cover
        """Reset envs ``indices`` with the given designs (None: the env chooses) and seeds."""
        raise NotImplementedError

    def step(self, actions: np.ndarray) -> list[StepResult]:  # pragma: no cover
        """Step all envs with ``actions`` ``(N, R)`` (``R`` regulators of the envs' space); no auto-reset."""
        raise NotImplementedError

    def step_send(self, actions: np.ndarray) -> None:
        """Start :meth:`step` (backends whose envs run elsewhere start them now and return);
        finish with :meth:`step_recv`."""
        self._sent = actions

    def step_recv(self) -> list[StepResult]:
        """The results of the step started by :meth:`step_send`."""
        actions, self._sent = self._sent, None
        return self.step(actions)

    def step_envs(self, indices: Sequence[int], actions: np.ndarray) -> list[StepResult]:  # pragma: no cover
        """Step envs ``indices`` only, env ``indices[j]`` with ``actions[j]`` ``(R,)``; no auto-reset
        (backends holding their envs in this process; :meth:`run_episodes` uses it)."""
        raise NotImplementedError

    def run_episodes(self, actions: np.ndarray) -> list[list[StepResult]]:
        """Every env's episode from its start (all envs just reset): env ``i`` takes
        ``actions[i, k]`` (``actions`` ``(N, K, R)``, ``K`` the envs' ``n_actions``) for
        ``k = 0, 1, ...`` until its episode ends (terminated or truncated). Returns each env's
        transitions in order, exactly those :meth:`step` would give for the same actions (no
        auto-reset; an env whose episode ended waits). Here: one :meth:`step_envs` of the
        envs still in their episode per action; backends whose envs run elsewhere send each
        worker its envs' actions at once (one message per episode, not per action)."""
        actions = np.asarray(actions)
        results: list[list[StepResult]] = [[] for _ in range(len(actions))]
        live = list(range(len(actions)))
        for k in range(actions.shape[1]):
            if not live:
                break
            for i, r in zip(live, self.step_envs(live, actions[live, k])):
                results[i].append(r)
            live = [i for i in live if not (results[i][-1][2] or results[i][-1][3])]
        return results

    def episodes_send(self, actions: np.ndarray) -> None:
        """Start :meth:`run_episodes` (backends whose envs run elsewhere start them now and
        return); finish with :meth:`episodes_recv`."""
        self._sent_episodes = actions

    def episodes_recv(self) -> list[list[StepResult]]:
        """The results of the episodes started by :meth:`episodes_send`."""
        actions, self._sent_episodes = self._sent_episodes, None
        return self.run_episodes(actions)

    def get_attr(self, name: str, indices: Sequence[int]) -> list:  # pragma: no cover
        raise NotImplementedError

    def set_attr(self, name: str, value, indices: Sequence[int]) -> None:  # pragma: no cover
        raise NotImplementedError

    def call(self, method: str, args: tuple, kwargs: dict, indices: Sequence[int]) -> list:  # pragma: no cover
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover
        pass
