"""The JAX learner (SBX's SAC): its updates equal the torch learner's given the same weights,
batches and noise, its networks start as torch's, it learns a contextual bandit; updates
overlapped with the simulation (same number as SB3's schedule, run while the envs step, none
left behind at the end), all updates of a vectorised step in one compiled call, the split
learning rates, the JAX device check, and its state written as arrays that restore to the bit
and cannot run code when read."""

from __future__ import annotations

import pickle

import gymnasium as gym
import jax
import msgpack
import numpy as np
import pytest

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.sac_jax import (check_device, decode_learner_state, learner_state_bytes, make_sac,
                                        restore_learner_state)
from softcrawl.envs.backends import SerialBackend
from softcrawl.envs.vec import DesignVecEnv

from helpers import continued_and_restored, filled_learner, tiny_env_class, update_spy


_Tiny = tiny_env_class()


@pytest.mark.parametrize("learner", ["sbx", "torch"])
@pytest.mark.parametrize("overlap", [False, True])
def test_overlapped_updates_follow_the_schedule(overlap, learner):
    """Both learners; the JAX one makes a vectorised step's updates in one compiled call."""
    from softcrawl.codesign.sac import learner_module

    backend = update_spy([_Tiny] * 2)
    venv = DesignVecEnv(backend)
    cfg = SACConfig(buffer_size=200, batch_size=8, learning_starts=10, net_arch=(8,), overlap=overlap)
    model = learner_module(learner).make_sac(venv, cfg, seed=0)
    backend.model = model
    calls = []
    if learner == "sbx":
        compiled = model._train  # SBX's jitted fori_loop over the gradient steps

        def spy(*args, **kwargs):
            calls.append(args[2])  # gradient_steps
            return compiled(*args, **kwargs)

        model._train = spy
    model.learn(total_timesteps=40)
    model.flush()
    # one update per transition after learning_starts: 2 per vectorised step of 2 envs; the
    # first come after step 6 (12 transitions > 10), the last after step 20: 15 x 2 (the JAX
    # learner: in one compiled call per vectorised step)
    assert model._n_updates == 30 and calls == ([2] * 15 if learner == "sbx" else [])
    if overlap:
        # all but the last step's updates ran while the next step was simulated
        assert backend.during == 30 - 2 and model._deferred == 0
    else:
        assert backend.during == 0
    assert model.learner_seconds > 0


_SMALL = SACConfig(buffer_size=200, batch_size=16, learning_starts=0, net_arch=(16, 8), overlap=False,
                   policy_lr=1e-3, q_lr=5e-3)


def _leaves(model) -> list[np.ndarray]:
    p = model.policy
    return [np.asarray(x) for x in jax.tree_util.tree_leaves((p.actor_state, p.qf_state, model.ent_coef_state,
                                                               model.key, p.key, p.noise_key))]


def test_split_learning_rates_and_network_layout():
    model = filled_learner(make_sac, _SMALL)
    model.train(gradient_steps=3, batch_size=16)
    p = model.policy
    assert float(p.actor_state.opt_state.hyperparams["learning_rate"]) == pytest.approx(1e-3)
    assert float(p.qf_state.opt_state.hyperparams["learning_rate"]) == pytest.approx(5e-3)
    assert model.lr_schedule(1) == pytest.approx(1e-3)  # the temperature's Adam (SBX: the policy's rate)
    assert model.target_entropy == -3.0 and model._n_updates == 3
    actor = p.actor_state.params["params"]
    widths = [actor[k]["kernel"].shape[1] for k in sorted(actor) if k.startswith("Linear")]
    assert widths[:2] == [16, 8]  # hidden layers; then the mean and log-std heads (3 each)
    assert model.replay_buffer.handle_timeout_termination
    terminal = filled_learner(make_sac, SACConfig(timeout="terminal", buffer_size=100, net_arch=(8,)))
    assert not terminal.replay_buffer.handle_timeout_termination


def test_a_restored_learner_continues_to_the_bit():
    """Learner state written after 5 updates and read into a fresh learner: the next 5 updates
    (same replay sample: numpy's RNG restored as a checkpoint does) give the same networks,
    optimizer states, temperature and keys, and the same actions, as the learner that went on."""
    from softcrawl.codesign import sac_jax

    a, b = continued_and_restored(sac_jax, _SMALL)
    assert all(np.array_equal(x, y) for x, y in zip(_leaves(a), _leaves(b)))
    obs = np.linspace(-1, 1, 44, dtype=np.float32)
    assert np.array_equal(a.predict(obs, deterministic=True)[0], b.predict(obs, deterministic=True)[0])
    assert np.array_equal(a.predict(obs)[0], b.predict(obs)[0])  # the exploration noise's key too


def test_the_learner_stays_float32_where_the_process_runs_float64_robots(x64):
    """The JAX engine turns ``jax_enable_x64`` on for float64 robots (``backend="jax"``) in the
    learner's process: the learner is built, updated and restored in float32 all the same (SBX's
    update loop failed with float64 branches)."""
    from softcrawl.codesign import sac_jax

    assert jax.config.jax_enable_x64
    a, b = continued_and_restored(sac_jax, _SMALL)
    assert {np.asarray(x).dtype for x in _leaves(a) if np.asarray(x).dtype.kind == "f"} == {np.dtype(np.float32)}
    assert all(np.array_equal(x, y) for x, y in zip(_leaves(a), _leaves(b)))
    assert a.predict(np.zeros(44, np.float32), deterministic=True)[0].dtype == np.float32


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
    model = filled_learner(make_sac, _SMALL)
    other = filled_learner(make_sac, SACConfig(buffer_size=200, batch_size=16, net_arch=(16, 4), overlap=False))
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


# -- the same updates as the torch learner ---------------------------------------------------------
def _torch_weights_in_jax(torch_model, jax_model) -> None:
    """Copy the torch learner's actor, critics and target critics into the JAX learner (kernels
    transposed; fresh Adam states on both sides)."""
    import torch

    def linears(seq):
        return [m for m in seq if isinstance(m, torch.nn.Linear)]

    def dense(layer):
        return {"kernel": layer.weight.detach().numpy().T, "bias": layer.bias.detach().numpy()}

    def critics(critic):
        nets = [linears(q) for q in critic.q_networks]
        return {"params": {"VmapCritic_0": {f"Linear_{i}": {k: np.stack([dense(n[i])[k] for n in nets])
                                                            for k in ("kernel", "bias")}
                                            for i in range(len(nets[0]))}}}

    a = torch_model.actor
    actor = {"params": {f"Linear_{i}": dense(m) for i, m in enumerate(linears(a.latent_pi) + [a.mu, a.log_std])}}
    p = jax_model.policy
    for mine, theirs in ((p.actor_state.params, actor), (p.qf_state.params, critics(torch_model.critic))):
        shapes = jax.tree_util.tree_map(np.shape, mine), jax.tree_util.tree_map(np.shape, theirs)
        assert shapes[0] == shapes[1]
    actor, qf = jax.tree_util.tree_map(jax.numpy.asarray, (actor, critics(torch_model.critic)))
    p.actor_state = p.actor_state.replace(params=actor, opt_state=p.actor_state.tx.init(actor))
    p.qf_state = p.qf_state.replace(params=qf, opt_state=p.qf_state.tx.init(qf),
                                    target_params=jax.tree_util.tree_map(jax.numpy.asarray,
                                                                         critics(torch_model.critic_target)))
    return actor


@pytest.fixture
def no_exploration_noise(monkeypatch):
    """Both learners' Gaussian noise replaced by zeros (JAX's traces recompiled before and after)."""
    import torch

    from softcrawl.codesign import sac_nets

    monkeypatch.setattr(sac_nets, "standard_normal", lambda key, shape, dtype: jax.numpy.zeros(shape, dtype))
    monkeypatch.setattr(torch.distributions.Normal, "rsample",
                        lambda self, sample_shape=(): self.loc + 0 * self.scale)
    jax.clear_caches()
    yield
    jax.clear_caches()


def test_the_jax_updates_are_the_torch_learners(no_exploration_noise):
    """The torch learner's initial weights in the JAX learner, the same 20 batches (10% true
    terminals), no exploration noise: critic loss, actor loss and temperature agree at every
    update and the networks after 20 updates agree to float32 rounding (measured: losses within
    4e-7 relative, parameters within 5e-7 of their largest magnitude; bounds 1e-5)."""
    import torch
    from stable_baselines3.common.type_aliases import ReplayBufferSamples

    from softcrawl.codesign import sac_torch

    cfg = SACConfig(buffer_size=200, batch_size=32, learning_starts=0, net_arch=(32, 16), overlap=False)
    mt = sac_torch.make_sac(DesignVecEnv(SerialBackend([_Tiny])), cfg, seed=0)
    mj = make_sac(DesignVecEnv(SerialBackend([_Tiny])), cfg, seed=0)
    _torch_weights_in_jax(mt, mj)
    rng = np.random.default_rng(1)
    batches = [ReplayBufferSamples(*(torch.as_tensor(x.astype(np.float32)) for x in (
        rng.normal(size=(32, 44)), rng.uniform(-1, 1, (32, 3)), rng.normal(size=(32, 44)),
        rng.uniform(size=(32, 1)) < 0.1, rng.normal(size=(32, 1))))) for _ in range(20)]
    for m in (mt, mj):
        m.replay_buffer.sample = lambda n, env=None, it=iter(batches): next(it)
    for _ in range(20):
        mt.train(1, 32)
        mj.train(1, 32)
        for name in ("critic_loss", "actor_loss", "ent_coef"):
            t, j = mt.logger.name_to_value[f"train/{name}"], mj.logger.name_to_value[f"train/{name}"]
            assert j == pytest.approx(t, rel=1e-5), name
    after = _torch_weights_in_jax(mt, make_sac(DesignVecEnv(SerialBackend([_Tiny])), cfg, seed=1))
    for x, y in zip(jax.tree_util.tree_leaves(after), jax.tree_util.tree_leaves(mj.policy.actor_state.params)):
        assert np.abs(np.asarray(x) - np.asarray(y)).max() <= 1e-5 * np.abs(np.asarray(x)).max()
    assert float(mj.ent_coef_state.params["log_ent_coef"]) == pytest.approx(mt.log_ent_coef.item(), abs=1e-6)


def test_fresh_networks_are_drawn_as_torchs():
    """Kernels and biases uniform on +-1/sqrt(fan_in) (torch's nn.Linear; flax's default would
    be LeCun-normal kernels, sqrt(3) larger in std, and zero biases): every array of the paper's
    networks within the bound and without zeros, those of 400+ entries with the uniform's std
    ``bound / sqrt(3)`` within 10% (4.5 standard errors at 400 entries); a fresh actor's mean
    actions and log-stds are small (|mean| < 0.3, |log std| < 0.3 on random observations; with
    flax's defaults they reached 0.46-0.87 and 0.41-0.72, seeds 0-2)."""
    model = make_sac(DesignVecEnv(SerialBackend([_Tiny])), SACConfig(buffer_size=10), seed=0)
    for tree in (model.policy.actor_state.params, model.policy.qf_state.params):
        for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
            leaf = np.asarray(leaf)
            bound = 1 / np.sqrt(leaf.shape[-2] if path[-1].key == "kernel" else tree_fan_in(tree, path))
            assert np.abs(leaf).max() <= bound and np.all(leaf != 0)
            if leaf.size >= 400:
                assert leaf.std() == pytest.approx(bound / np.sqrt(3), rel=0.1)
    obs = np.random.default_rng(0).uniform(-1, 1, (256, 44)).astype(np.float32)
    dist = model.policy.actor_state.apply_fn(model.policy.actor_state.params, obs)
    assert np.abs(np.asarray(dist.mean)).max() < 0.3 and np.abs(np.asarray(dist.log_std)).max() < 0.3


def tree_fan_in(tree, bias_path) -> int:
    """The fan-in of the layer that owns bias ``bias_path``: its kernel's input size."""
    node = tree
    for k in bias_path[:-1]:
        node = node[k.key]
    return node["kernel"].shape[-2]


class _Bandit(gym.Env):
    """One-step episodes: observation a one-hot context of 4 (of 44 inputs), reward
    ``-|a - a*(context)|^2`` with the best actions inside the box, away from its edges."""

    observation_space = gym.spaces.Box(-1, 1, (44,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (3,), np.float32)
    best = np.array([[0.6, -0.5, 0.2], [-0.6, 0.4, -0.3], [0.3, 0.6, -0.6], [-0.2, -0.6, 0.5]], np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.k = int(self.np_random.integers(4))
        return np.eye(44, dtype=np.float32)[self.k], {}

    def step(self, a):
        return np.eye(44, dtype=np.float32)[self.k], -float(np.sum((a - self.best[self.k]) ** 2)), True, False, {}


@pytest.mark.parametrize("seed", [0, 1])
def test_the_jax_learner_learns_a_contextual_bandit(seed):
    """The paper's learning rates, temperature and target entropy on small networks: after
    2,400 updates the deterministic action of every context is within 0.15 of the best one
    (measured: 0.060 and 0.062 for seeds 0 and 1); the untrained actor's is 0.62-0.68 away."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    cfg = SACConfig(buffer_size=5_000, batch_size=64, learning_starts=200, net_arch=(64, 64), overlap=False)
    model = make_sac(DummyVecEnv([_Bandit] * 4), cfg, seed=seed)
    model.learn(2_600)
    actions = model.predict(np.eye(44, dtype=np.float32)[:4], deterministic=True)[0]
    assert model._n_updates == 2_400
    assert np.abs(actions - _Bandit.best).max() < 0.15, actions
