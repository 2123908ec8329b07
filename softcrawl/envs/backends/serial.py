"""The in-process backend: all envs in this process, stepped one after another."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import gymnasium as gym

from softcrawl.envs.backends.base import EnvBackend


class SerialBackend(EnvBackend):
    """All envs in this process, stepped one after another.

    Args:
        env_fns: one zero-argument constructor per env.

    Raises:
        ValueError: no env.
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]]):
        if len(env_fns) < 1:
            raise ValueError("need at least one env")
        self.envs = [fn() for fn in env_fns]
        self.num_envs = len(self.envs)
        self.observation_space, self.action_space = self.envs[0].observation_space, self.envs[0].action_space

    def reset(self, indices, designs, seeds):
        return [self.envs[i].reset(seed=s, options={"design": d}) for i, d, s in zip(indices, designs, seeds)]

    def step(self, actions):
        return [env.step(a) for env, a in zip(self.envs, actions)]

    def step_envs(self, indices, actions):
        return [self.envs[i].step(a) for i, a in zip(indices, actions)]

    def get_attr(self, name, indices):
        return [getattr(self.envs[i], name) for i in indices]

    def set_attr(self, name, value, indices):
        for i in indices:
            setattr(self.envs[i], name, value)

    def call(self, method, args, kwargs, indices):
        return [getattr(self.envs[i], method)(*args, **kwargs) for i in indices]

    def close(self):
        for env in self.envs:
            env.close()
