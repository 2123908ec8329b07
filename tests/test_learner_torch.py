"""The torch learner (``sac.learner = "torch"``): the actor's step without the critics' weight
gradients (the same updates to the bit), the split learning rates, and its state read back with
``weights_only=True`` to the bit (its overlapped updates: ``tests/test_learner.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.sac_torch import decode_learner_state, learner_state_bytes, make_sac, restore_learner_state

from helpers import continued_and_restored, filled_learner


def test_the_actor_step_skips_the_critics_weight_gradients_and_changes_nothing():
    """SplitLRSAC freezes the critics' weights during the actor's step (their weight gradients
    were computed and discarded); the networks after 30 updates equal those of SB3's own SAC to
    the bit, and the critics train again afterwards."""
    from stable_baselines3 import SAC

    from softcrawl.codesign.sac_torch import SplitLRSAC

    def trained(frozen: bool):
        model = filled_learner(make_sac, SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 8),
                                                   overlap=False))
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


_SMALL = SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 8), overlap=False,
                   policy_lr=1e-3, q_lr=5e-3, learner="torch")


def test_split_learning_rates_and_network_layout():
    model = filled_learner(make_sac, _SMALL)
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

    from softcrawl.codesign import sac_torch

    a, b = continued_and_restored(sac_torch, _SMALL)
    for x, y in zip(a.policy.state_dict().values(), b.policy.state_dict().values()):
        assert np.array_equal(x.numpy(), y.numpy())
    assert a.log_ent_coef.item() == b.log_ent_coef.item()
    with pytest.raises(ValueError, match="not a tensors-only checkpoint"):
        decode_learner_state(pickle.dumps({"policy": print}))
    other = filled_learner(make_sac, SACConfig(buffer_size=200, batch_size=16, net_arch=(16, 4), overlap=False))
    with pytest.raises(ValueError, match="of this config"):
        restore_learner_state(b, decode_learner_state(learner_state_bytes(other)))
