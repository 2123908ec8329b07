"""Episodes start from the robot at rest: settling runs until every node is slower
than the rest speed, the start is cached per design, and a robot that does not come to rest
in time is reported.

Uses the reduced model (shipped 6 mm leg reduction) with the demo's coarse 25 mm disk, where
a one-sided design tips over in about 0.1 s and rests after about 0.5 s."""

import numpy as np
import pytest

from softcrawl.envs import CrawlerEnv
from softcrawl.robot import RobotConfig, Settling, build_robot, run_episode, settle

ONE_SIDED = (0, 0, 1, 0, 2, 2, 0, 0)  # three legs at 112.5, 202.5, 247.5 deg: tips over
CONFIG = RobotConfig(model="reduced", disk_mesh_size=25)


@pytest.fixture(scope="module")
def one_sided():
    return build_robot(ONE_SIDED, CONFIG)


class Ramp:
    """Commanded real kPa on all regulators rising ``rate`` kPa/s (default 150: 1.5 kPa per
    0.01 s step, the regulators' slew limit)."""

    def __init__(self, rate: float = 150.0):
        self.rate = rate

    def pressure_at(self, t):
        return np.full(3, min(self.rate * t, 90.0))


def test_episode_starts_at_rest_and_does_not_score_the_fall(one_sided):
    """At t = 0 the disk's vertical speed is below the rest speed; with no pressure the disk top
    centre then drifts < 0.1 mm in x over 0.2 s (measured 0.007 mm), and on a 1.5 kPa/step ramp
    it moves < 0.1 mm while the pressure is still low (first 0.05 s: <= 7.5 kPa real, 10 kPa
    sim; measured 0.016 mm). After that the ramp's pressure itself bends the legs (1.3 mm by
    0.2 s, 28.5 kPa real): actuation, not the fall that 3 settling steps used to score (+5.5 mm
    in 0.06 s, below 10 kPa)."""
    rule = Settling()
    settled = settle(one_sided, rule)
    assert settled.at_rest and settled.rest_speed < rule.rest_speed
    disk = one_sided.model.body_slice(one_sided.disk_body)
    assert np.abs(settled.state.v[disk, 2]).max() < rule.rest_speed
    assert settled.state.t == 0.0 and settled.steps * one_sided.config.dt == pytest.approx(settled.seconds)
    still = run_episode(one_sided, Ramp(rate=0.0), duration=0.2, record_every=None, progress=False, settled=settled)
    assert not still.diverged and still.steps == 20
    assert abs(still.position[-1, 0] - still.position[0, 0]) < 0.1  # mm
    ramp = run_episode(one_sided, Ramp(), duration=0.2, record_every=None, progress=False, settled=settled)
    assert abs(ramp.position[5, 0] - ramp.position[0, 0]) < 0.1  # mm
    assert ramp.settled["at_rest"] and ramp.settled["settle_steps"] == settled.steps


def test_few_settling_steps_leave_the_robot_falling(one_sided):
    """The old rule (a fixed 3 steps) started the episode mid-fall: the check above can fail."""
    early = settle(one_sided, Settling(max_seconds=0.03))
    assert not early.at_rest and early.rest_speed > 100.0  # mm/s, still falling
    res = run_episode(one_sided, Ramp(), duration=0.2, record_every=None, progress=False, settled=early)
    assert abs(res.position[5, 0] - res.position[0, 0]) > 1.0  # mm in the first 0.05 s


def test_cached_start_gives_the_same_episode(one_sided):
    """An episode from a cached settled state equals one that settles itself (fresh solvers)."""
    a = run_episode(one_sided, Ramp(), duration=0.1, record_every=None, progress=False)
    b = run_episode(one_sided, Ramp(), duration=0.1, record_every=None, progress=False, settled=settle(one_sided))
    np.testing.assert_array_equal(a.position, b.position)


def test_settling_rule_validation():
    with pytest.raises(ValueError, match="rest_speed"):
        Settling(rest_speed=0.0)
    with pytest.raises(ValueError, match="max_seconds"):
        Settling(max_seconds=float("nan"))
    assert Settling(hold_seconds=0.05, max_seconds=3.0).steps(0.01) == (5, 300)
    assert Settling(hold_seconds=0.05, max_seconds=3.0).steps(0.02) == (3, 150)


def test_env_caches_the_start_and_reports_it(one_sided):
    """The env settles a design once (the second episode reuses the settled state) and puts the
    settling statistics in ``info``; an episode that could not rest is flagged."""
    calls = []

    def factory(design):
        calls.append(design)
        return one_sided

    env = CrawlerEnv(robot_factory=factory, steps_per_action=2, n_actions=2, designs=[ONE_SIDED])
    _, info = env.reset(seed=0)
    first = env.episode.settled
    assert info["at_rest"] and info["settle_steps"] == first.steps and info["rest_speed_mm_s"] < 0.5
    _, _, _, _, info = env.step(np.zeros(3))
    assert info["at_rest"] and "settle_seconds" in info
    env.reset(seed=1)
    assert env.episode.settled is first and calls == [ONE_SIDED]
    capped = CrawlerEnv(robot_factory=factory, steps_per_action=2, n_actions=2, designs=[ONE_SIDED],
                        settling=Settling(max_seconds=0.02))
    _, info = capped.reset(seed=0)
    assert not info["at_rest"] and info["settle_steps"] == 2
