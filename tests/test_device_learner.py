"""The device-resident learner of episode-at-once training (:mod:`softcrawl.codesign.episodic`,
:mod:`softcrawl.codesign.replay`): its replay buffer and scanned updates give the sbx learner's
parameters from the same weights and batches, the buffer is a ring that a checkpoint reads and
restores, the actor's scan feeds back its actions as the env builds its observations, and the
loop makes SB3's number of updates per round, overlapped with the next round's episodes."""

from __future__ import annotations

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.episodic import EpisodicSAC, episode_actions, make_episodic_sac, scanned_updates
from softcrawl.codesign.replay import FIELDS, DeviceReplay
from softcrawl.codesign.sac_jax import make_sac
from softcrawl.envs.backends import SerialBackend
from softcrawl.envs.vec import DesignVecEnv

from helpers import tiny_env_class, update_spy


def _transitions(n: int, rng) -> dict[str, np.ndarray]:
    """``n`` random transitions of the crawler's sizes, about 30% of them episode ends and half
    of those time limits."""
    t = {"observations": rng.uniform(-1, 1, (n, 44)), "next_observations": rng.uniform(-1, 1, (n, 44)),
         "actions": rng.uniform(-1, 1, (n, 3)), "rewards": rng.normal(size=n), "dones": rng.random(n) < 0.3}
    t["timeouts"] = t["dones"] & (rng.random(n) < 0.5)
    return {k: np.asarray(v, np.float32) for k, v in t.items()}


def test_device_replay_and_scanned_updates_equal_the_sbx_learner():
    """The same 64 transitions in SB3's replay buffer of the sbx learner and in the device
    buffer (stored alike, array by array); the same 7 batches of 16 rows, the same starting
    weights, optimizer states, temperature and key: the sbx learner's 7 compiled updates (its
    ``train``, SBX's ``fori_loop``) and :func:`scanned_updates` (``jax.lax.scan`` on the device
    buffer) end with the same critics, target critics, actor, temperature and Adam moments to
    float32 round-off: every array within 1e-6 of its largest magnitude (about 8 ulps; 1.3e-7
    measured: XLA fuses the two loops' bodies differently) and the same next key."""
    cfg = SACConfig(buffer_size=256, batch_size=16, learning_starts=0, net_arch=(32, 16), overlap=False)
    model = make_sac(DesignVecEnv(SerialBackend([tiny_env_class()])), cfg, seed=0)
    rng = np.random.default_rng(0)
    n, steps = 64, 7
    t = _transitions(n, rng)
    rb = model.replay_buffer
    for j in range(n):
        rb.add(*(t[k][j:j + 1] for k in ("observations", "next_observations", "actions", "rewards", "dones")),
               [{"TimeLimit.truncated": bool(t["timeouts"][j])}])
    model._setup_learn(1)
    replay = DeviceReplay(cfg.buffer_size, model.observation_space, model.action_space)
    replay.add({k: np.concatenate([v, np.zeros((8, *v.shape[1:]), v.dtype)]) for k, v in t.items()}, n)
    for k in FIELDS:
        np.testing.assert_array_equal(replay.host_arrays()[k][:n], getattr(rb, k)[:n, 0], err_msg=k)

    index = rng.integers(0, n, (steps, cfg.batch_size))
    rb.sample = lambda size, env=None: rb._get_samples(index.reshape(-1))
    p = model.policy
    qf, actor, ent, key = p.qf_state, p.actor_state, model.ent_coef_state, model.key
    model.train(gradient_steps=steps, batch_size=cfg.batch_size)
    with model.on_device():
        qf, actor, ent, key, _ = scanned_updates(replay.device_arrays(), jnp.asarray(index), key, qf, actor, ent,
                                                 model.tau, model.target_entropy, model.gamma)
    want = (p.qf_state.params, p.qf_state.target_params, p.qf_state.opt_state, p.actor_state.params,
            p.actor_state.opt_state, model.ent_coef_state.params, model.ent_coef_state.opt_state)
    got = (qf.params, qf.target_params, qf.opt_state, actor.params, actor.opt_state, ent.params, ent.opt_state)
    leaves = list(zip(jax.tree_util.tree_leaves(want), jax.tree_util.tree_leaves(got)))
    assert len(leaves) == len(jax.tree_util.tree_leaves(got)) > 30
    moved = 0
    for a, b in leaves:
        a, b = np.asarray(a), np.asarray(b)
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-6 * float(np.abs(a).max(initial=0)))
        moved += a.dtype.kind == "f" and a.size > 1
    assert moved > 20
    np.testing.assert_array_equal(np.asarray(key), np.asarray(model.key))


def test_the_device_replay_is_a_ring_a_checkpoint_reads_and_restores():
    """Rounds of 4 transitions (padded to 6 rows) into 10 rows: the oldest are overwritten
    first, ``pos`` and ``full`` follow; a round larger than the buffer keeps its last rows; the
    arrays a checkpoint reads are numpy arrays of the buffer, and what it writes into them is
    what the device holds next; time limits are kept only with ``handle_timeout_termination``."""
    space = tiny_env_class()
    replay = DeviceReplay(10, space.observation_space, space.action_space)
    rng = np.random.default_rng(1)
    rounds = [_transitions(6, rng) for _ in range(3)]
    for r in rounds:
        replay.add(r, 4)
    assert (replay.pos, replay.full, replay.size()) == (2, True, 10)
    rewards = replay.rewards
    assert isinstance(rewards, np.ndarray) and rewards.flags.writeable
    r0, r1, r2 = (r["rewards"] for r in rounds)  # rows 8, 9, 0, 1 hold the third round
    np.testing.assert_array_equal(rewards, np.concatenate([r2[2:4], r0[2:4], r1[:4], r2[:2]]))
    big = _transitions(15, rng)
    replay.add(big, 13)
    assert (replay.pos, replay.full) == (5, True)
    np.testing.assert_array_equal(np.roll(replay.observations, -5, axis=0), big["observations"][3:13])
    replay.rewards[:] = 7.0  # a checkpoint's restore writes into the host arrays
    replay.pos = 3
    np.testing.assert_array_equal(np.asarray(replay.device_arrays()["rewards"]), np.full(10, 7.0, np.float32))
    plain = DeviceReplay(4, space.observation_space, space.action_space, handle_timeout_termination=False)
    plain.add(_transitions(4, np.random.default_rng(2)) | {"timeouts": np.ones(4, np.float32)}, 4)
    np.testing.assert_array_equal(plain.timeouts, 0.0)
    with pytest.raises(ValueError, match="fields"):
        plain.add({"rewards": np.zeros(2)}, 1)
    with pytest.raises(ValueError, match="count"):
        plain.add(_transitions(2, rng), 3)


class _Open(gym.Env):
    """An open-loop env built as :class:`CrawlerEnv` builds its observation: the design's
    one-hot code (2) and the last ``history`` = 2 actions (1 regulator), most recent first;
    ``n_actions`` = 3; reward: the action."""

    n_actions, history = 3, 2
    observation_space = gym.spaces.Box(-1, 1, (4,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.design = (options or {}).get("design") or (1 + int(self.np_random.integers(2)),)
        self.code, self.past, self.k = np.eye(2, dtype=np.float32)[self.design[0] - 1], np.zeros(2, np.float32), 0
        return np.concatenate([self.code, self.past]), {"design": self.design}

    def step(self, action):
        a = np.clip(np.asarray(action, np.float32).reshape(-1), -1, 1)
        self.past, self.k = np.concatenate([a, self.past[:-1]]), self.k + 1
        return np.concatenate([self.code, self.past]), float(a[0]), False, self.k >= self.n_actions, {
            "design": self.design}


def _open_learner(n_envs: int = 2, backend=None, **sac) -> EpisodicSAC:
    venv = DesignVecEnv(backend or SerialBackend([_Open] * n_envs))
    venv.seed(0)
    return make_episodic_sac(venv, SACConfig(**{"buffer_size": 100, "batch_size": 8, "net_arch": (8,)} | sac), seed=0)


def test_the_actors_scan_feeds_back_its_actions_as_the_env_builds_its_observations():
    """The observations :func:`episode_actions` drew each action at are, to the bit, those the
    envs return (the code, then the actions taken, most recent first, zeros before the first);
    the steps that start before ``learning_starts`` take the action space's uniform draws in
    SB3's warm-up order (step by step, env by env), the rest the policy's."""
    model = _open_learner(learning_starts=4)  # 2 envs: steps 0 and 1 start before 4 transitions
    first = model.env.reset()
    rng = model.action_space.np_random.bit_generator.state
    actions = model.draw_actions(first)
    model.action_space.np_random.bit_generator.state = rng
    warm = np.array([[model.action_space.sample() for _ in range(2)] for _ in range(2)])
    np.testing.assert_array_equal(actions[:, :2].swapaxes(0, 1), warm)
    assert np.all(np.abs(actions) <= 1) and not np.array_equal(actions[:, 2], actions[:, 1])
    random = np.zeros((3, 2, 1), np.float32)
    random[:2] = warm
    with model.on_device():
        again, obs = episode_actions(model.policy.actor_state, jnp.asarray(first), model.policy.noise_key,
                                     random, np.array([True, True, False]), history=2)
    np.testing.assert_array_equal(np.asarray(again), actions)
    steps = model.env.run_episodes(actions)
    seen = [first] + [s.obs for s in steps[:-1]]
    for k in range(3):
        np.testing.assert_array_equal(np.asarray(obs)[:, k], seen[k])


@pytest.mark.parametrize("overlap", [False, True])
def test_the_loop_makes_sb3s_updates_per_round_overlapped_with_the_next_episodes(overlap):
    """2 envs, 3-action episodes, one update per transition after 10 transitions: 40 asked
    for, 7 rounds (42: whole episodes); updates after the vectorised steps at 12, 14, ..., 42:
    2 x 16 = 32, in one compiled call per round; overlapped, all but the last round's run
    while the next round's episodes do (the last ones at ``flush``)."""
    backend = update_spy([_Open] * 2)
    model = _open_learner(backend=backend, learning_starts=10, overlap=overlap)
    backend.model = model
    calls = []
    model.run_updates = lambda g, b, run=model.run_updates: calls.append(g) or run(g, b)
    model.learn(total_timesteps=40)
    assert model.num_timesteps == 42 and model.replay_buffer.size() == 42 and model._episode_num == 14
    model.flush()
    assert model._n_updates == 32 and calls == [2, 6, 6, 6, 6, 6]
    assert backend.during == (32 - 6 if overlap else 0) and model._deferred == 0


def test_the_loop_compiles_its_update_once_per_number_of_updates():
    """The rounds of the test above (updates 2, 6, 6, 6, 6, 6 per round) compile the device
    update twice (one per number of updates: a static argument) and the actor's episode scan
    once. Without the learner's states committed as strong-typed device arrays, SBX's weakly
    typed, uncommitted initial states make the update compile again on the first rounds
    (three times for 6 updates), several seconds each on a GPU."""
    from softcrawl.codesign.episodic import device_updates

    model = _open_learner(learning_starts=10)
    updates, actions = device_updates._cache_size(), episode_actions._cache_size()
    model.learn(total_timesteps=40)
    assert device_updates._cache_size() - updates == 2
    assert episode_actions._cache_size() - actions == 1
