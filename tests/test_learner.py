"""The learner: updates overlapped with the simulation (same number as SB3's
schedule, run while the envs step, none left behind at the end), and the actor's step without
the critics' weight gradients (the same updates to the bit)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.sac import make_sac
from softcrawl.envs.backends import SerialBackend
from softcrawl.envs.vec import DesignVecEnv


class _Tiny(gym.Env):
    """Episodes of 5 steps with the crawler's spaces (44 observations, 3 actions)."""

    observation_space = gym.spaces.Box(-1, 1, (44,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (3,), np.float32)

    def reset(self, *, seed=None, options=None):
        self.k = 0
        return np.zeros(44, np.float32), {}

    def step(self, a):
        self.k += 1
        return np.full(44, 0.1 * self.k, np.float32), float(a[0]), False, self.k >= 5, {}


class _Spy(SerialBackend):
    """Counts the gradient updates made while a step is in flight (between send and receive)."""

    def __init__(self, fns):
        super().__init__(fns)
        self.in_flight, self.model, self.during = False, None, 0

    def step_send(self, actions):
        super().step_send(actions)
        self.in_flight, self.before = True, self.model._n_updates

    def step_recv(self):
        self.during += self.model._n_updates - self.before
        self.in_flight = False
        return super().step_recv()


@pytest.mark.parametrize("overlap", [False, True])
def test_overlapped_updates_follow_the_schedule(overlap):
    backend = _Spy([_Tiny] * 2)
    venv = DesignVecEnv(backend)
    cfg = SACConfig(buffer_size=200, batch_size=8, learning_starts=10, net_arch=(8,), overlap=overlap)
    model = make_sac(venv, cfg, seed=0)
    backend.model = model
    model.learn(total_timesteps=40)
    model.flush()
    # one update per transition after learning_starts: 2 per vectorised step of 2 envs; the
    # first come after step 6 (12 transitions > 10), the last after step 20: 15 x 2
    assert model._n_updates == 30
    if overlap:
        # all but the last step's updates ran while the next step was simulated
        assert backend.during == 30 - 2 and model._deferred == 0
    else:
        assert backend.during == 0
    assert model.learner_seconds > 0


def test_the_actor_step_skips_the_critics_weight_gradients_and_changes_nothing():
    """SplitLRSAC freezes the critics' weights during the actor's step (their weight gradients
    were computed and discarded); the networks after 30 updates equal those of SB3's own SAC to
    the bit, and the critics train again afterwards."""
    from stable_baselines3 import SAC

    from softcrawl.codesign.sac import SplitLRSAC

    def trained(frozen: bool):
        cfg = SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 8), overlap=False)
        model = make_sac(DesignVecEnv(SerialBackend([_Tiny])), cfg, seed=0)
        rng = np.random.default_rng(0)
        for _ in range(64):
            o = rng.uniform(-1, 1, (1, 44)).astype(np.float32)
            model.replay_buffer.add(o, o, rng.uniform(-1, 1, (1, 3)), rng.uniform(-1, 1, 1), np.zeros(1), [{}])
        model._setup_learn(1)
        if not frozen:  # SB3's update, without the hooks' effect
            model._critic_weight_grads = lambda on: None
            SAC.train(model, gradient_steps=30, batch_size=16)
        else:
            model.train(gradient_steps=30, batch_size=16)
        return model

    plain, frozen = trained(False), trained(True)
    assert isinstance(frozen, SplitLRSAC)
    for a, b in zip(plain.policy.state_dict().values(), frozen.policy.state_dict().values()):
        assert np.array_equal(a.numpy(), b.numpy())
    assert plain.log_ent_coef.item() == frozen.log_ent_coef.item()
    assert all(p.requires_grad for p in frozen.critic.parameters())
    # the critics' gradients after the last step are theirs alone (none from the actor's loss)
    g_plain = [p.grad for p in plain.critic.parameters()]
    g_frozen = [p.grad for p in frozen.critic.parameters()]
    assert all(g is not None for g in g_frozen)
    assert any(not np.array_equal(a.numpy(), b.numpy()) for a, b in zip(g_plain, g_frozen))
