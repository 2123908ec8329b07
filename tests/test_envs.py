"""Crawler gymnasium environment and the design-sampling VecEnv (softcrawl.envs).

Uses a coarse full-order robot (16 mm legs, 25 mm disk, factorization reuse 5) and 2 steps per
action so that an episode costs about a second."""

import sys

import numpy as np
import pytest

from softcrawl.design.space import BASELINE_DESIGN, PAPER_BEST_DESIGN, one_hot
from softcrawl.envs import BuildRobot, CrawlerEnv, action_to_kpa, kpa_to_action
from softcrawl.fem.solver import SimulationDiverged
from softcrawl.robot import RobotConfig

COARSE = RobotConfig(leg_mesh_size=16, disk_mesh_size=25, refactor_every=5)
DESIGNS = [PAPER_BEST_DESIGN, BASELINE_DESIGN]


def make_env(**kw):
    kw.setdefault("robot_factory", BuildRobot(COARSE))
    kw.setdefault("steps_per_action", 2)
    kw.setdefault("n_actions", 4)
    kw.setdefault("designs", DESIGNS)
    return CrawlerEnv(**kw)


@pytest.fixture(scope="module")
def env():
    return make_env()


def test_action_mapping():
    np.testing.assert_allclose(action_to_kpa([-1, 0, 1]), [0, 45, 90])
    np.testing.assert_allclose(action_to_kpa([-3, 3, 0.5]), [0, 90, 67.5])  # clipped
    np.testing.assert_allclose(kpa_to_action(action_to_kpa([-0.2, 0.3, 0.9])), [-0.2, 0.3, 0.9])


def test_spaces_obs_history_and_reward(env):
    assert env.observation_space.shape == (44,) and env.action_space.shape == (3,)
    obs, info = env.reset(seed=1, options={"design": "1,0,0,2,2,0,0,0"})
    assert obs.dtype == np.float32 and info["design"] == PAPER_BEST_DESIGN
    np.testing.assert_array_equal(obs[:32], one_hot(PAPER_BEST_DESIGN))
    assert np.all(obs[32:] == 0)
    acts = [np.array([1.0, -1.0, 0.5], np.float32), np.array([-0.5, 1.0, -1.0], np.float32)]
    total, x0 = 0.0, info["disk_position_mm"][0]
    for k, a in enumerate(acts):
        obs, r, term, trunc, info = env.step(a)
        total += r
        assert not term and not trunc
        np.testing.assert_allclose(obs[32:35], a)  # most recent first
        np.testing.assert_allclose(info["commanded_kpa"], action_to_kpa(a))
        assert info["applied_kpa"].shape == (3,) and np.all(info["applied_kpa"] <= 90)
        assert info["t"] == pytest.approx((k + 1) * 2 * COARSE.dt)
    np.testing.assert_allclose(obs[35:38], acts[0])
    assert np.all(obs[38:] == 0)
    # the return is the +x displacement of the disk top centre, cm
    assert total == pytest.approx(info["displacement_cm"], abs=1e-9)
    assert total == pytest.approx((info["disk_position_mm"][0] - x0) / 10.0, abs=1e-6)
    for _ in range(2):
        obs, r, term, trunc, info = env.step(acts[0])
    assert trunc and not term  # time limit after n_actions
    obs, info = env.reset(options={"design": BASELINE_DESIGN})
    assert np.all(obs[32:] == 0), "history must be cleared on reset"
    assert len(env._robots) == 2  # robots cached per design


def test_episodes_are_reproducible():
    env = make_env(n_actions=3)
    acts = np.array([[1, -1, 0.5], [0.2, 1, -1], [-1, 0, 1]], np.float32)
    returns = []
    for design in (PAPER_BEST_DESIGN, BASELINE_DESIGN, PAPER_BEST_DESIGN):
        env.reset(options={"design": design})
        returns.append(sum(env.step(a)[1] for a in acts))
    assert returns[0] == returns[2]  # same design and actions, other episodes in between


def test_random_design_from_rng():
    env = make_env()
    seen = {env.reset(seed=s)[1]["design"] for s in range(6)}
    assert seen <= set(DESIGNS) and len(seen) == 2
    assert env.reset(seed=4)[1]["design"] == env.reset(seed=4)[1]["design"]


def test_gymnasium_and_sb3_checkers():
    from gymnasium.utils.env_checker import check_env as gym_check
    from stable_baselines3.common.env_checker import check_env as sb3_check

    env = make_env()
    gym_check(env, skip_render_check=True)
    sb3_check(env, warn=False)
    env_s = make_env(observe_state=True)
    assert env_s.observation_space.shape == (53,)
    gym_check(env_s, skip_render_check=True)
    sb3_check(env_s, warn=False)


def test_observe_state(env):
    e = make_env(observe_state=True)
    obs, _ = e.reset(options={"design": PAPER_BEST_DESIGN})
    np.testing.assert_allclose(obs[44:47], 0.0, atol=1e-6)  # no displacement right after settling
    obs, _, _, _, info = e.step(np.ones(3, np.float32))
    assert obs[44] == pytest.approx(info["displacement_cm"], abs=1e-5)
    assert np.all(obs[50:53] > -1)  # regulators rising


def test_divergence_ends_episode_without_raising(env):
    env.reset(options={"design": PAPER_BEST_DESIGN})
    env.step(np.zeros(3, np.float32))

    def boom(command):
        raise SimulationDiverged("NaN in test", 0.0)

    env.episode.step = boom
    try:
        obs, r, term, trunc, info = env.step(np.zeros(3, np.float32))
    finally:
        del env.episode.step
    assert term and not trunc and info["diverged"] and "NaN in test" in info["reason"]
    assert r == 0.0 and np.all(np.isfinite(obs))


def test_bad_input(env):
    with pytest.raises(ValueError):
        make_env(steps_per_action=0)
    with pytest.raises(ValueError):
        make_env(designs=[])
    with pytest.raises(ValueError):
        env.reset(options={"design": (1, 1, 0, 0, 0, 0, 0, 0)})  # 2 legs
    env.reset(options={"design": PAPER_BEST_DESIGN})
    with pytest.raises(ValueError):
        env.step(np.array([np.nan, 0, 0]))


class FixedSampler:
    def __init__(self, designs):
        self.designs, self.seen = list(designs), []

    def sample(self, n):
        return [self.designs[i % len(self.designs)] for i in range(n)]

    def observe(self, designs, returns, diverged, timestep):
        self.seen.append((list(designs), list(returns), timestep))


@pytest.mark.parametrize("backend", ["serial", "subprocess"])
def test_vec_env(backend):
    from softcrawl.envs.backends import SerialBackend, SubprocessBackend
    from softcrawl.envs.vec import DesignVecEnv

    fns = [make_env] * 3
    be = SerialBackend(fns) if backend == "serial" else SubprocessBackend(fns, n_workers=2)
    sampler = FixedSampler([BASELINE_DESIGN, PAPER_BEST_DESIGN])
    venv = DesignVecEnv(be, sampler)
    try:
        obs = venv.reset()
        assert obs.shape == (3, 44)
        assert venv.designs == [BASELINE_DESIGN, PAPER_BEST_DESIGN, BASELINE_DESIGN]
        np.testing.assert_array_equal(obs[1, :32], one_hot(PAPER_BEST_DESIGN))
        rng = np.random.default_rng(0)
        total = np.zeros(3)
        for k in range(4):
            obs, rew, dones, infos = venv.step(rng.uniform(-1, 1, (3, 3)).astype(np.float32))
            total += rew
        assert dones.all() and venv.num_transitions == 12
        for i, info in enumerate(infos):
            assert info["TimeLimit.truncated"] and info["episode"]["l"] == 4
            assert info["episode"]["r"] == pytest.approx(total[i], abs=1e-5)
            assert info["terminal_observation"].shape == (44,)
        assert np.all(obs[:, 32:] == 0)  # auto-reset cleared the history
        (designs, _returns, t), = sampler.seen
        assert t == 12 and designs == [BASELINE_DESIGN, PAPER_BEST_DESIGN, BASELINE_DESIGN]
        assert venv.get_attr("steps_per_action") == [2, 2, 2]
        with pytest.raises(ValueError, match="legs"):  # errors in workers reach the caller
            be.reset([2], [(1, 1, 0, 0, 0, 0, 0, 0)], [None])
    finally:
        venv.close()


def test_envs_of_a_process_share_one_bounded_robot_cache():
    """Training's envs (``share_robots``) share their process's robots and settled states; the
    cache holds one robot per env plus ``max_cached`` spare (regression: 16 robots per env, up to
    768 per worker of the paper preset)."""
    from softcrawl.envs.robot_cache import RobotCache, process_cache

    factory = BuildRobot(COARSE)
    a, b = make_env(robot_factory=factory, share_robots=True, max_cached=1), make_env(
        robot_factory=BuildRobot(COARSE), share_robots=True, max_cached=1)
    assert a._robots is b._robots is process_cache(factory, a.settling, 1) and a._robots.capacity >= 3
    a.reset(seed=0, options={"design": PAPER_BEST_DESIGN})
    _, info = b.reset(seed=0, options={"design": PAPER_BEST_DESIGN})
    assert b.episode.robot is a.episode.robot and b.episode.settled is a.episode.settled  # settled once
    assert info["settle_steps"] == a.episode.settled.steps
    assert make_env(robot_factory=factory)._robots is not a._robots  # private by default

    built = []
    cache = RobotCache(spare=1).attach().attach()  # 2 envs + 1 spare

    def build(design):
        built.append(design)
        return object()

    for d in ("a", "b", "c", "a", "d"):
        cache.fetch(d, build)
    assert list(cache) == ["c", "a", "d"] and built == ["a", "b", "c", "d"]  # LRU, at most 3
    robot = cache["a"][0]
    cache.keep_settled("a", robot, "rested")
    cache.keep_settled("c", object(), "stale")  # not the cached robot: ignored
    assert cache["a"] == (robot, "rested") and cache["c"][1] is None
    cache.detach()  # an env closed: 1 env + 1 spare
    assert list(cache) == ["a", "d"]
    with pytest.raises(ValueError, match="spare"):
        RobotCache(0)
    n = a._robots.envs
    a.close()
    assert b._robots.envs == n - 1


def test_settled_states_outlive_their_robots_within_a_memory_bound():
    """A dropped robot's settled state stays (LRU, ``settled_mb``) and comes back with the
    rebuilt robot; states beyond the bound go, least recently used first."""
    from softcrawl.envs.robot_cache import RobotCache
    from softcrawl.fem.state import State
    from softcrawl.robot.episode import SettledState

    def rested(n):  # n nodes: 2 * 3 * 8 n bytes of positions and velocities
        return SettledState(State(np.zeros((n, 3)), np.zeros((n, 3))), 1, 0.02, 0.0, True)

    cache = RobotCache(spare=1, settled_mb=2 * 48 * 10_000 / 1e6).attach()  # room for 2 states of 10k nodes
    states = {d: rested(10_000) for d in "abcd"}
    for d in "abcd":
        robot, settled = cache.fetch(d, lambda d: object())
        assert settled is None
        cache.keep_settled(d, robot, states[d])
    assert list(cache) == ["c", "d"] and list(cache.settled) == ["a", "b"]
    robot, settled = cache.fetch("a", lambda d: "rebuilt")  # c's robot goes, a's state comes back
    assert robot == "rebuilt" and settled is states["a"]
    assert list(cache) == ["d", "a"] and list(cache.settled) == ["b", "c"]
    cache.fetch("e", lambda d: object())  # d's state pushes b's out (2 states fit)
    assert list(cache.settled) == ["c", "d"]
    big = RobotCache(spare=1, settled_mb=0.1).attach()  # a state larger than the bound is not kept
    big.keep_settled("a", big.fetch("a", lambda d: object())[0], rested(10_000))
    for d in "bc":
        big.fetch(d, lambda d: object())
    assert not big.settled
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="settled_mb"):
            RobotCache(1, settled_mb=bad)


def test_a_settled_states_modal_velocities_count_toward_the_memory_bound():
    """The memory bound counts every array of a settled state, its reduced bodies' modal
    velocities too: 80 kB of them do not fit a 50 kB bound, the same state without them does."""
    from softcrawl.envs.robot_cache import RobotCache
    from softcrawl.fem.state import State
    from softcrawl.robot.episode import SettledState

    for modal, kept in (((np.zeros((1, 10_000)),), False), (None, True)):
        cache = RobotCache(spare=1, settled_mb=0.05).attach()
        state = State(np.zeros((10, 3)), np.zeros((10, 3)), modal_velocities=modal)
        cache.keep_settled("a", cache.fetch("a", lambda d: object())[0], SettledState(state, 1, 0.02, 0.0, True))
        for d in "bc":
            cache.fetch(d, lambda d: object())
        assert ("a" in cache.settled) == kept


def test_an_env_does_not_settle_a_design_again_after_its_robot_was_dropped(monkeypatch):
    """Regression: with 16 spare robots per worker a `crawl` run over the 280
    three-legged designs settled 1,200 of its 3,200 episodes (502 with the kept states,
    benchmarks/settle_cache.py); a dropped robot's design now starts from its kept settled
    state, and the episode is the one a fresh env gives."""
    import softcrawl.robot.episode as episode_module

    calls = []
    real = episode_module.settle

    def counting(robot, *a, **kw):
        calls.append(robot)
        return real(robot, *a, **kw)

    monkeypatch.setattr(episode_module, "settle", counting)
    env = make_env(max_cached=1)  # one robot in use + one spare
    for d in ("1,0,2,0,3,0,0,0", "1,0,0,2,0,0,3,0", PAPER_BEST_DESIGN):
        env.reset(seed=0, options={"design": d})
    assert len(calls) == 3 and (1, 0, 2, 0, 3, 0, 0, 0) not in env._robots
    _, info = env.reset(seed=0, options={"design": "1,0,2,0,3,0,0,0"})
    assert len(calls) == 3  # rebuilt, not settled again
    action = np.array([1.0, -1.0, 0.5], np.float32)
    kept = [env.step(action)[1] for _ in range(2)]
    fresh_env = make_env()
    _, fresh_info = fresh_env.reset(seed=0, options={"design": "1,0,2,0,3,0,0,0"})
    assert info["settle_steps"] == fresh_info["settle_steps"]
    np.testing.assert_array_equal(env.episode.start, fresh_env.episode.start)
    assert kept == [fresh_env.step(action)[1] for _ in range(2)]  # the same rewards, to the bit


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/PID/maps")
def test_a_subprocess_worker_loads_neither_torch_nor_jax(tmp_path):
    """A training worker holds the backends, the batched stepper and its envs, nothing of the
    learner (which the caller imports once it runs, as ``softcrawl train`` does): JAX, torch
    and stable-baselines3 cost hundreds of MB of RSS per worker (regression: the backends lived
    beside the SB3 ``VecEnv``, so every worker imported torch). A worker re-runs the caller's module-level
    imports (``spawn``/``forkserver`` semantics), so a script keeps the learner's out of them,
    as the ``softcrawl`` command does."""
    import subprocess

    script = tmp_path / "main.py"
    script.write_text(
        "from softcrawl.envs.backends import SubprocessBackend\n"
        "if __name__ == '__main__':\n"
        "    import jax  # noqa: F401 - the learner's, in the caller only\n"
        "    import torch  # noqa: F401\n"
        "    from softcrawl.codesign.config import preset\n"
        "    from softcrawl.codesign.factory import env_fn\n"
        "    be = SubprocessBackend([env_fn(preset('paper'))] * 2, n_workers=1)\n"
        "    maps = open(f'/proc/{be.processes[0].pid}/maps').read()\n"
        "    be.close()\n"
        "    print('torch' in maps or 'jax' in maps)\n")
    out = subprocess.run([sys.executable, str(script)], capture_output=True, check=True, cwd=tmp_path)
    assert out.stdout.decode().strip() == "False", out.stderr.decode()[-2000:]
