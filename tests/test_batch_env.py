"""Batched env stepping: a worker that steps its envs' robots together gives the same
transitions as one that steps its envs one after another (same seeds, mixed designs and episode
lengths, so robots join and leave the batch at different times; designs drawn by the envs or
given by a sampler, when the batched backend settles new designs together), divergences
included."""

import numpy as np
import pytest

from softcrawl.envs import BuildRobot, CrawlerEnv
from softcrawl.envs.backends import SerialBackend
from softcrawl.envs.backends.batched import BatchedBackend
from softcrawl.envs.vec import DesignVecEnv
from softcrawl.fem.state import State
from softcrawl.robot import RobotConfig
from softcrawl.robot.episode import Settling

REDUCED = BuildRobot(RobotConfig(model="reduced"))
COARSE_FULL = BuildRobot(RobotConfig(leg_mesh_size=16, disk_mesh_size=25, refactor_every=5))
DESIGNS = [(1, 0, 0, 2, 0, 0, 3, 0), (1, 0, 2, 0, 2, 0, 1, 0), (0, 1, 3, 2, 0, 1, 2, 0), (1, 2, 3, 1, 2, 3, 0, 0)]
SHORT = Settling(max_seconds=0.05)


def env_fns():
    """Reduced envs of 3 to 6-leg designs with 2, 3 and 4 actions per episode (resets at different
    times) and one full-order env (stepped on its own by the batched backend)."""
    fns = [lambda n=n: CrawlerEnv(REDUCED, steps_per_action=4, n_actions=n, designs=DESIGNS, settling=SHORT)
           for n in (2, 3, 4, 3)]
    fns.append(lambda: CrawlerEnv(COARSE_FULL, steps_per_action=2, n_actions=2, designs=DESIGNS[:1], settling=SHORT))
    return fns


class CyclingSampler:
    """Designs in turn (a design given at reset: the batched backend settles them together)."""

    def __init__(self):
        self.k = 0

    def sample(self, n):
        self.k += n
        return [DESIGNS[(self.k - n + j) % len(DESIGNS)] for j in range(n)]

    def observe(self, designs, returns, diverged, timestep):
        pass


def rollout(backend, n_steps: int = 7, poison: tuple[int, int] | None = None, sampler=None):
    """Transitions of a seeded DesignVecEnv on ``backend``; ``poison = (step, env)`` makes that
    env's state non-finite before that step (a divergence)."""
    venv = DesignVecEnv(backend, sampler)
    venv.seed(3)
    out = [venv.reset()]
    rng = np.random.default_rng(0)
    for k in range(n_steps):
        if poison is not None and poison[0] == k:
            ep = backend.envs[poison[1]].episode
            x = ep.state.x.copy()
            x[0, 0] = np.nan
            ep.state = State(x, ep.state.v, ep.state.t)
        obs, rew, dones, infos = venv.step(rng.uniform(-1, 1, (venv.num_envs, 3)).astype(np.float32))
        out.append((obs, rew, dones, [{k: v for k, v in i.items() if k != "terminal_observation"} for i in infos]))
    return out


def assert_same(a, b):
    np.testing.assert_array_equal(a[0], b[0])
    for (oa, ra, da, ia), (ob, rb, db, ib) in zip(a[1:], b[1:]):
        np.testing.assert_array_equal(oa, ob)
        np.testing.assert_array_equal(ra, rb)
        np.testing.assert_array_equal(da, db)
        for x, y in zip(ia, ib):
            assert x.keys() == y.keys()
            for key in x:
                if isinstance(x[key], np.ndarray):
                    np.testing.assert_array_equal(x[key], y[key])
                else:
                    assert x[key] == y[key], key


@pytest.mark.parametrize("poison, sampled", [(None, False), ((2, 1), True)])
def test_batched_backend_gives_the_serial_transitions(poison, sampled, monkeypatch):
    import softcrawl.envs.backends.batched as batch

    settled = []
    run = batch.run_in_lockstep
    monkeypatch.setattr(batch, "run_in_lockstep", lambda solvers, loops: settled.append(len(loops)) or run(solvers, loops))
    serial = rollout(SerialBackend(env_fns()), poison=poison, sampler=CyclingSampler() if sampled else None)
    batched = rollout(BatchedBackend(env_fns()), poison=poison, sampler=CyclingSampler() if sampled else None)
    assert_same(serial, batched)
    assert bool(settled) == sampled and (not sampled or settled[0] == 4)  # 4 new designs settled together
    if poison is not None:
        assert batched[poison[0] + 1][3][poison[1]]["diverged"]
