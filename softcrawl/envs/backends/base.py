"""The interface of a vector env's backend (where its N crawler envs live and run).

A backend resets envs given their indices, designs and seeds, steps all envs, and forwards
``get_attr`` / ``set_attr`` / ``call`` to the envs it holds; :class:`EnvBackend` is that contract.
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

    def get_attr(self, name: str, indices: Sequence[int]) -> list:  # pragma: no cover
        raise NotImplementedError

    def set_attr(self, name: str, value, indices: Sequence[int]) -> None:  # pragma: no cover
        raise NotImplementedError

    def call(self, method: str, args: tuple, kwargs: dict, indices: Sequence[int]) -> list:  # pragma: no cover
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover
        pass
