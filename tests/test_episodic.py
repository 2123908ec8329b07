"""Episode-at-once training (``rollout = "episode"``, :mod:`softcrawl.codesign.episodic`): whole
episodes give the per-action loop's transitions to the bit on every CPU backend, an episode that
ends early waits for the round's end, the JAX backend's one-call episodes equal its per-action
steps, the setting is refused where the policy observes the state, recorded and migrated, and a
run killed mid-way and resumed is the uninterrupted run."""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import gymnasium as gym
import numpy as np
import pytest

from softcrawl.cli import main
from helpers import one_line_error


def _smoke(*sets):
    from softcrawl.codesign.config import override, preset

    return override(preset("smoke"), list(sets))


def same(x, y, where="") -> None:
    """``x`` and ``y`` equal to the bit, recursively (dicts, lists, arrays with their dtypes)."""
    if isinstance(x, dict):
        assert isinstance(y, dict) and set(x) == set(y), where
        for k in x:
            same(x[k], y[k], f"{where}.{k}")
    elif isinstance(x, (np.ndarray, np.generic)) or isinstance(y, (np.ndarray, np.generic)):
        x, y = np.asarray(x), np.asarray(y)
        assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes(), where
    elif isinstance(x, (list, tuple)):
        assert type(x) is type(y) and len(x) == len(y), where
        for i, (a, b) in enumerate(zip(x, y)):
            same(a, b, f"{where}[{i}]")
    else:
        assert type(x) is type(y) and (x == y or (x != x and y != y)), f"{where}: {x!r} != {y!r}"


def _rounds(cfg, episode: bool, rounds: int = 2, seed: int = 0):
    """Two rounds of the same random actions through ``cfg``'s vector env (its sampler, seeded
    as training seeds it), stepped one action at a time or ``run_episodes``; the per-step
    ``(obs, rewards, dones, infos)`` and the designs after each round."""
    from softcrawl.codesign.factory import make_sampler, make_vec_env

    venv = make_vec_env(cfg, make_sampler(cfg))
    try:
        out, designs = [venv.reset()], []
        rng = np.random.default_rng(seed)
        for _ in range(rounds):
            actions = rng.uniform(-1, 1, (cfg.n_envs, cfg.env.n_actions, 3)).astype(np.float32)
            if episode:
                out += [(s.obs, s.rewards, s.dones, s.infos) for s in venv.run_episodes(actions)]
            else:
                out += [venv.step(actions[:, k]) for k in range(cfg.env.n_actions)]
            designs.append(list(venv.designs))
        return out, designs, venv.num_transitions
    finally:
        venv.close()


@pytest.mark.parametrize("backend", ["serial", "subprocess"])
def test_whole_episodes_give_the_per_action_transitions_to_the_bit(backend):
    """Three envs of the smoke simulation, two rounds of fixed actions: every vectorised step's
    observations, rewards, dones and infos (terminal observations, time-limit flags, episode
    returns, positions, pressures) are those of stepping one action at a time, bit for bit, and
    the sampler drew the same designs after each round (it saw the same returns at the same
    steps). The subprocess backend's workers step their robots as one batch, one message per
    episode."""
    cfg = _smoke(f'backend="{backend}"', "n_envs=3", "n_workers=2")
    per_action, episodes = _rounds(cfg, episode=False), _rounds(cfg, episode=True)
    assert len(per_action[0]) == 1 + 2 * cfg.env.n_actions
    same(per_action, episodes)


class _Ends(gym.Env):
    """Episodes of up to 4 actions on designs ``(m,)``: terminated after ``m`` actions if
    ``m < 4`` (a goal reached, a divergence), else truncated at 4; observation: the step."""

    observation_space = gym.spaces.Box(-1, 10, (2,), np.float32)
    action_space = gym.spaces.Box(-1, 1, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        self.design, self.k = options["design"], 0
        return np.array([0, self.design[0]], np.float32), {"design": self.design}

    def step(self, action):
        self.k += 1
        term = self.k == self.design[0] < 4
        return (np.array([self.k, self.design[0]], np.float32), float(action[0]), term, not term and self.k >= 4,
                {"design": self.design})


class _Sampler:
    """Hands out ``designs`` in turn; records ``observe`` calls."""

    def __init__(self, designs):
        self.designs, self.seen = list(designs), []

    def sample(self, n):
        out, self.designs = self.designs[:n], self.designs[n:]
        return out

    def observe(self, designs, returns, diverged, timestep):
        self.seen.append((list(designs), [float(r) for r in returns], timestep))


def test_an_episode_that_ends_early_waits_and_restarts_at_the_round_end():
    """Env 0's episode ends after 2 of 4 actions: its transitions up to then are the per-action
    loop's; it is reported to the sampler at that step (2 x 2 transitions made), then waits
    (``live`` False, no transition counted) while env 1 finishes at 4; both get their next
    designs from one ``sample(2)`` at the end, and env 0's rows from its last step on hold the
    first observation of its next episode."""
    from softcrawl.envs.backends import SerialBackend
    from softcrawl.envs.vec import DesignVecEnv

    actions = np.array([[[0.1], [0.2], [0.3], [0.4]], [[0.5], [0.6], [0.7], [0.8]]], np.float32)
    sampler = _Sampler([(2,), (4,), (3,), (4,), (4,), (4,)])
    venv = DesignVecEnv(SerialBackend([_Ends, _Ends]), sampler)
    venv.reset()
    steps = venv.run_episodes(actions)
    assert [s.live.tolist() for s in steps] == [[True, True], [True, True], [False, True], [False, True]]
    assert [s.dones.tolist() for s in steps] == [[False, False], [True, False], [False, False], [False, True]]
    assert [s.ended.tolist() for s in steps] == [[False, False], [True, False], [True, False], [True, True]]
    assert venv.num_transitions == 6 and venv.designs == [(3,), (4,)]
    assert sampler.seen == [([(2,)], [pytest.approx(0.3)], 4), ([(4,)], [pytest.approx(2.6)], 6)]
    first = np.array([0, 3], np.float32)  # env 0's next episode
    for s in steps[1:]:
        np.testing.assert_array_equal(s.obs[0], first)
    info = steps[1].infos[0]
    np.testing.assert_array_equal(info["terminal_observation"], [2, 2])
    assert info["TimeLimit.truncated"] is False and info["episode"]["l"] == 2
    assert steps[2].infos[0] == {} and steps[2].rewards[0] == 0 and steps[3].infos[1]["TimeLimit.truncated"]

    reference = DesignVecEnv(SerialBackend([_Ends, _Ends]), _Sampler([(2,), (4,), (3,)]))
    reference.reset()
    for k in range(2):  # up to env 0's end the per-action loop agrees
        obs, rewards, dones, infos = reference.step(actions[:, k])
        same((rewards, dones), (steps[k].rewards, steps[k].dones))
        np.testing.assert_array_equal(obs[1], steps[k].obs[1])
        same(infos[0].get("terminal_observation"), steps[k].infos[0].get("terminal_observation"))

    with pytest.raises(ValueError, match="n_envs"):
        venv.run_episodes(actions[:1])
    with pytest.raises(RuntimeError, match="did not end"):
        venv.run_episodes(actions[:, :2])
    venv.reset()
    venv.step(actions[:, 0])
    with pytest.raises(RuntimeError, match="right after a reset"):
        venv.run_episodes(actions)


def test_the_rollout_setting_is_refused_for_a_state_observing_policy_recorded_and_migrated(tmp_path, capsys):
    """``rollout="episode"`` draws the actions at the episode's start: refused (one line, no
    folder) with ``env.observe_state`` or the torch learner; an older run's settings read as
    ``"action"``, what it ran; a new run's config.json records the setting."""
    from softcrawl.codesign.config import TrainConfig
    from softcrawl.codesign.migrate import read_settings

    for sets, why in ((["env.observe_state=true"], "env.observe_state is set"),
                      (['sac.learner="torch"'], "sac.learner is 'torch'")):
        argv = ["train", "--preset", "smoke", "--out", str(tmp_path / "r"), "--set", 'rollout="episode"']
        one_line_error(capsys, main(argv + [x for s in sets for x in ("--set", s)]), why, 'rollout="action"')
        assert not (tmp_path / "r").exists()
    assert _smoke('rollout="action"', "env.observe_state=true").rollout == "action"
    old = _smoke().to_dict()
    del old["rollout"]
    assert TrainConfig.from_dict(read_settings("train", {"config_version": 5, "config": old})).rollout == "action"
    from softcrawl.codesign.run import Run

    Run(tmp_path / "run").write_config(_smoke())
    assert json.loads((tmp_path / "run" / "config.json").read_text())["config"]["rollout"] == "episode"


_TRAIN = """
import sys
from softcrawl.codesign.config import override, preset
from softcrawl.codesign.training import train
cfg = override(preset("smoke"), ['rollout="episode"', "total_steps=160", "checkpoint_every=40", "keep_checkpoints=10"])
train(sys.argv[1], cfg, resume=len(sys.argv) > 2, progress=False)
"""


def test_a_killed_episodic_run_resumed_is_the_uninterrupted_run(tmp_path):
    """A smoke run of 4 rounds (checkpoints at every round boundary, 40 transitions) killed with
    SIGKILL once its second checkpoint is complete, then resumed, logs the same episodes and
    design distribution as the same run uninterrupted, and ends with the same learner (every
    network, optimizer and key, to the bit) and the same device replay buffer."""
    from softcrawl.codesign.run import Run

    script = tmp_path / "train.py"
    script.write_text(_TRAIN)
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    subprocess.run([sys.executable, str(script), str(whole)], check=True, timeout=600)
    proc = subprocess.Popen([sys.executable, str(script), str(killed)])
    try:
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and proc.poll() is None:
            ck = Run(killed).latest_checkpoint(quiet=True)
            if ck is not None and Run(killed).checkpoint_steps(ck) >= 80:
                proc.send_signal(signal.SIGKILL)
                break
            time.sleep(0.02)
    finally:
        proc.wait(timeout=60)
    assert proc.returncode == -signal.SIGKILL, "the run ended before it could be killed"
    assert Run(killed).checkpoint_steps(Run(killed).latest_checkpoint(quiet=True)) < 160
    subprocess.run([sys.executable, str(script), str(killed), "--resume"], check=True, timeout=600)
    for name in ("episodes.csv", "distribution.csv"):
        assert (killed / name).read_text() == (whole / name).read_text(), name
    a, b = (Run(r).latest_checkpoint() for r in (whole, killed))
    assert a.name == b.name == "step-0000000160"
    assert (a / "learner.msgpack").read_bytes() == (b / "learner.msgpack").read_bytes()
    with np.load(a / "replay_buffer.npz") as x, np.load(b / "replay_buffer.npz") as y:
        assert set(x.files) == set(y.files) and all(np.array_equal(x[k], y[k]) for k in x.files)
        assert x["observations"].shape == (1000, 44) and int(x["pos"]) == 160
    state = json.loads((a / "state.json").read_text())
    assert json.loads((b / "state.json").read_text())["n_updates"] == state["n_updates"] == 120
