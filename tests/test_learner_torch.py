"""The torch learner (``sac.learner = "torch"``): updates overlapped with the simulation (same
number as SB3's schedule, run while the envs step, none left behind at the end), the actor's
step without the critics' weight gradients (the same updates to the bit), the split learning
rates, and its state read back with ``weights_only=True`` to the bit."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.sac_torch import decode_learner_state, learner_state_bytes, make_sac, restore_learner_state
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

    from softcrawl.codesign.sac_torch import SplitLRSAC

    def trained(frozen: bool):
        model = _filled(SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 8), overlap=False))
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


def _filled(cfg: SACConfig):
    model = make_sac(DesignVecEnv(SerialBackend([_Tiny])), cfg, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(64):
        o = rng.uniform(-1, 1, (1, 44)).astype(np.float32)
        model.replay_buffer.add(o, o, rng.uniform(-1, 1, (1, 3)), rng.uniform(-1, 1, 1), np.zeros(1), [{}])
    model._setup_learn(1)
    return model


_SMALL = SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 8), overlap=False,
                   policy_lr=1e-3, q_lr=5e-3, learner="torch")


def test_split_learning_rates_and_network_layout():
    model = _filled(_SMALL)
    model.train(gradient_steps=3, batch_size=16)
    assert model.actor.optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    assert model.critic.optimizer.param_groups[0]["lr"] == pytest.approx(5e-3)
    assert model.ent_coef_optimizer.param_groups[0]["lr"] == pytest.approx(1e-3)
    assert [m.out_features for m in model.actor.latent_pi if hasattr(m, "out_features")] == [16, 8]
    assert model.replay_buffer.handle_timeout_termination and model.learner == "torch"


def test_a_restored_torch_learner_continues_to_the_bit():
    """State written after 5 updates, read (``weights_only=True``) into a fresh learner: the
    next 5 updates (numpy's RNG restored as a checkpoint does; torch's by the state) give the
    same networks and temperature as the learner that went on. A pickle is refused unread."""
    import pickle

    a = _filled(_SMALL)
    np.random.seed(1)
    a.train(gradient_steps=5, batch_size=16)
    data, rng = learner_state_bytes(a), np.random.get_state()
    a.train(gradient_steps=5, batch_size=16)
    b = _filled(_SMALL)
    restore_learner_state(b, decode_learner_state(data))
    np.random.set_state(rng)
    b.train(gradient_steps=5, batch_size=16)
    for x, y in zip(a.policy.state_dict().values(), b.policy.state_dict().values()):
        assert np.array_equal(x.numpy(), y.numpy())
    assert a.log_ent_coef.item() == b.log_ent_coef.item()
    with pytest.raises(ValueError, match="not a tensors-only checkpoint"):
        decode_learner_state(pickle.dumps({"policy": print}))
    other = _filled(SACConfig(buffer_size=200, batch_size=16, net_arch=(16, 4), overlap=False, learner="torch"))
    with pytest.raises(ValueError, match="of this config"):
        restore_learner_state(b, decode_learner_state(learner_state_bytes(other)))
