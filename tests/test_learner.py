"""The learner (SBX's SAC on JAX): updates overlapped with the simulation (same number as SB3's
schedule, run while the envs step, none left behind at the end), all updates of a vectorised
step in one compiled call, the split learning rates, the JAX device check, and its state
written as arrays that restore to the bit and cannot run code when read."""

from __future__ import annotations

import pickle

import gymnasium as gym
import jax
import msgpack
import numpy as np
import pytest

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.sac import (check_device, decode_learner_state, learner_state_bytes, make_sac,
                                    restore_learner_state)
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
def test_overlapped_updates_follow_the_schedule_in_one_compiled_call_per_step(overlap):
    backend = _Spy([_Tiny] * 2)
    venv = DesignVecEnv(backend)
    cfg = SACConfig(buffer_size=200, batch_size=8, learning_starts=10, net_arch=(8,), overlap=overlap)
    model = make_sac(venv, cfg, seed=0)
    backend.model = model
    calls = []
    compiled = model._train  # SBX's jitted fori_loop over the gradient steps

    def spy(*args, **kwargs):
        calls.append(args[2])  # gradient_steps
        return compiled(*args, **kwargs)

    model._train = spy
    model.learn(total_timesteps=40)
    model.flush()
    # one update per transition after learning_starts: 2 per vectorised step of 2 envs; the
    # first come after step 6 (12 transitions > 10), the last after step 20: 15 x 2, in one
    # compiled call per vectorised step
    assert model._n_updates == 30 and calls == [2] * 15
    if overlap:
        # all but the last step's updates ran while the next step was simulated
        assert backend.during == 30 - 2 and model._deferred == 0
    else:
        assert backend.during == 0
    assert model.learner_seconds > 0


def _filled(cfg: SACConfig, n: int = 64):
    model = make_sac(DesignVecEnv(SerialBackend([_Tiny])), cfg, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(n):
        o = rng.uniform(-1, 1, (1, 44)).astype(np.float32)
        model.replay_buffer.add(o, o, rng.uniform(-1, 1, (1, 3)), rng.uniform(-1, 1, 1), np.zeros(1), [{}])
    model._setup_learn(1)
    return model


_SMALL = SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 8), overlap=False,
                   policy_lr=1e-3, q_lr=5e-3)


def _leaves(model) -> list[np.ndarray]:
    p = model.policy
    return [np.asarray(x) for x in jax.tree_util.tree_leaves((p.actor_state, p.qf_state, model.ent_coef_state,
                                                               model.key, p.key, p.noise_key))]


def test_split_learning_rates_and_network_layout():
    model = _filled(_SMALL)
    model.train(gradient_steps=3, batch_size=16)
    p = model.policy
    assert float(p.actor_state.opt_state.hyperparams["learning_rate"]) == pytest.approx(1e-3)
    assert float(p.qf_state.opt_state.hyperparams["learning_rate"]) == pytest.approx(5e-3)
    assert model.lr_schedule(1) == pytest.approx(1e-3)  # the temperature's Adam (SBX: the policy's rate)
    assert model.target_entropy == -3.0 and model._n_updates == 3
    actor = p.actor_state.params["params"]
    widths = [actor[k]["kernel"].shape[1] for k in sorted(actor) if k.startswith("Dense")]
    assert widths[:2] == [16, 8]  # hidden layers; then the mean and log-std heads (3 each)
    assert model.replay_buffer.handle_timeout_termination
    assert not _filled(SACConfig(timeout="terminal", buffer_size=100, net_arch=(8,))).replay_buffer \
        .handle_timeout_termination


def test_a_restored_learner_continues_to_the_bit():
    """Learner state written after 5 updates and read into a fresh learner: the next 5 updates
    (same replay sample: numpy's RNG restored as a checkpoint does) give the same networks,
    optimizer states, temperature and keys, and the same actions, as the learner that went on."""
    a = _filled(_SMALL)
    np.random.seed(1)
    a.train(gradient_steps=5, batch_size=16)
    data, rng = learner_state_bytes(a), np.random.get_state()
    a.train(gradient_steps=5, batch_size=16)
    b = _filled(_SMALL)
    restore_learner_state(b, decode_learner_state(data))
    np.random.set_state(rng)
    b.train(gradient_steps=5, batch_size=16)
    assert all(np.array_equal(x, y) for x, y in zip(_leaves(a), _leaves(b)))
    obs = np.linspace(-1, 1, 44, dtype=np.float32)
    assert np.array_equal(a.predict(obs, deterministic=True)[0], b.predict(obs, deterministic=True)[0])
    assert np.array_equal(a.predict(obs)[0], b.predict(obs)[0])  # the exploration noise's key too


class _Evil:
    """Unpickling this creates ``marker``: proof that a file ran code when it was read."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_a_crafted_learner_file_cannot_run_code(tmp_path):
    """A pickle, a msgpack whose array ext holds a pickled object array, and a well-formed
    state of another network layout are all refused; none runs code."""
    marker = tmp_path / "pwned"
    evil = pickle.dumps(_Evil(marker))
    with pytest.raises(ValueError, match="not a learner state"):
        decode_learner_state(evil)
    # flax's ndarray ext (code 1): (shape, dtype name, buffer); "O" would be an object array
    ext = msgpack.ExtType(1, msgpack.packb(((1,), b"O", evil)))
    crafted = msgpack.packb({"actor": ext, "qf": {}, "ent_coef": {}, "key": ext, "policy_key": ext, "noise_key": ext})
    with pytest.raises(ValueError, match="not a learner state"):
        decode_learner_state(crafted)
    assert not marker.exists()
    model = _filled(_SMALL)
    other = _filled(SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 4), overlap=False))
    with pytest.raises(ValueError, match="of this config"):
        restore_learner_state(model, decode_learner_state(learner_state_bytes(other)))


def test_device_names_are_checked_against_what_jax_sees(monkeypatch):
    assert check_device("cpu").platform == "cpu"
    with pytest.raises(ValueError, match="sac.device must be"):
        check_device("tpu")

    def no_gpu(backend=None):
        raise RuntimeError("Unknown backend gpu")

    monkeypatch.setattr(jax, "devices", no_gpu)
    with pytest.raises(ValueError, match=r"sac.device='gpu:1'.*sees no GPU.*softcrawl\[gpu\]"):
        check_device("gpu:1")
    monkeypatch.setattr(jax, "devices", lambda backend=None: ["gpu0"])
    assert check_device("cuda") == "gpu0"  # "cuda" is read as "gpu" (configs written before)
    with pytest.raises(ValueError, match="sees 1 GPU"):
        check_device("cuda:1")
