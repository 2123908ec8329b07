"""The report's reading of a learned gait ("crawls with a periodic gait", "crawls
forward over the whole episode (not one push)")."""

import numpy as np

from softcrawl.codesign.report import gait_analysis, gait_period

A, B, C = [90.0, 0.0, 0.0], [0.0, 90.0, 0.0], [0.0, 0.0, 0.0]


def test_cycle_after_a_transient_is_found():
    acts = np.array([[45.0, 45.0, 45.0], [10.0, 80.0, 5.0]] + [A, B, C] * 6)  # 20 actions
    acts[5] += 2.0  # below the 3 kPa tolerance
    assert gait_period(acts) == (3, 2)


def test_constant_tail_and_no_cycle():
    rng = np.random.default_rng(0)
    stall = np.vstack([rng.uniform(0, 90, (6, 3)), np.tile([[30.0, 60.0, 0.0]], (14, 1))])
    assert gait_period(stall) == (1, 6)
    assert gait_period(rng.uniform(0, 90, (20, 3))) is None
    short = np.vstack([rng.uniform(0, 90, (14, 3)), np.tile([[30.0, 60.0, 0.0]], (6, 1))])
    assert gait_period(short) is None  # a constant tail over less than half of the episode


def test_progress_over_the_episode():
    t = np.linspace(0.0, 20.0, 1001)
    steady = gait_analysis(np.array([A, B, C] * 6 + [A, B]), t, 5.0 * t)  # 5 mm/s
    assert steady["period_actions"] == 3 and steady["crawls_throughout"]
    assert np.allclose(steady["distance_per_part_cm"], 2.5)
    push = gait_analysis(np.tile(A, (20, 1)), t, np.minimum(t, 5.0) * 8.0)  # 40 mm in 5 s, then nothing
    assert push["period_actions"] == 1 and not push["crawls_throughout"]
    assert push["distance_per_part_cm"][0] == 4.0 and push["distance_per_part_cm"][1] == 0.0


def test_a_task_other_than_forward_is_read_on_its_own_return():
    """A turning gait that turns steadily while drifting backwards: the report reads its turn per
    part (deg) and says it gains throughout; a turn made in the first quarter only does not."""
    from softcrawl.codesign.report import _describe_gait
    from softcrawl.tasks import make_task

    t, ft = np.linspace(0.0, 20.0, 1001), np.linspace(0.0, 20.0, 101)
    acts = np.array([A, B] * 10)
    steady = gait_analysis(acts, t, -t, task_return=(ft, 0.6 * ft, "deg"))
    assert np.allclose(steady["return_per_part_deg"], 3.0) and steady["task_throughout"]
    assert not steady["crawls_throughout"]
    line = _describe_gait(steady, make_task("turning"))
    assert "the `turning` return per 5-s part: +3.00 / +3.00 / +3.00 / +3.00 deg (it gains throughout" in line
    once = gait_analysis(acts, t, -t, task_return=(ft, np.minimum(ft, 5.0) * 2.0, "deg"))
    assert once["return_per_part_deg"] == [10.0, 0.0, 0.0, 0.0] and not once["task_throughout"]
    assert "it does NOT gain throughout" in _describe_gait(once, make_task("turning"))
