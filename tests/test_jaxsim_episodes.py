"""Batched episodes on the JAX engine (:mod:`softcrawl.jaxsim.episodes`) against the CPU reduced
engine's :func:`softcrawl.robot.run_episode`, and their batching and caching."""

import numpy as np
import pytest

jax = pytest.importorskip("jax")

THREE, FOUR = "1,0,0,2,2,0,0,0", "1,0,2,0,1,0,3,0"


def short_gait():
    """A 1-s step gait on all three regulators (two knots of 0.5 s)."""
    from softcrawl.codesign.groundtruth import PeriodicGait

    return PeriodicGait.from_knots([[90, 40, 0], [0, 90, 60]], hold=0.5)


def test_commands_are_what_run_episode_commands():
    """Row ``k`` of the host-side schedule is the CPU episode's command of step ``k`` (its row
    ``k + 1``, exactly), and a gait outside [0, 90] kPa or a duration under one step is refused
    before anything runs."""
    from softcrawl.gaits.pressure import PressureRangeError
    from softcrawl.jaxsim.episodes import episode_steps, gait_commands
    from softcrawl.robot import NO_SETTLING, RobotConfig, build_robot, run_episode

    robot = build_robot(THREE, RobotConfig(model="reduced"))
    gait, dt = short_gait(), robot.config.dt
    n = episode_steps(0.6, dt)
    ref = run_episode(robot, gait, 0.6, settling=NO_SETTLING, record_every=None, progress=False)
    assert n == ref.steps == 60
    np.testing.assert_array_equal(gait_commands(gait, n, dt), ref.commanded[1:])

    class Over:
        def pressure_at(self, t):
            return np.array([0.0, 95.0 if t > 0.1 else 0.0, 0.0])

    with pytest.raises(PressureRangeError, match="row 11, column 1"):
        gait_commands(Over(), n, dt)
    with pytest.raises(ValueError, match="at least one time step"):
        episode_steps(0.004, dt)


def test_batches_are_padded_to_a_few_sizes():
    """The ground truth's batches: powers of two from 1; the vector env's: powers of four from 4."""
    from softcrawl.jaxsim.batch import padded_size

    assert [padded_size(n, 64, 2, 1) for n in (1, 2, 3, 5, 33, 64)] == [1, 2, 4, 8, 64, 64]
    assert padded_size(3, 2, 2, 1) == 2
    assert [padded_size(n, 96) for n in (1, 4, 5, 17, 70, 96)] == [4, 4, 16, 64, 96, 96]


def out_of_memory():
    """The error XLA raises where a device cannot allocate a buffer."""
    return jax.errors.JaxRuntimeError("RESOURCE_EXHAUSTED: Out of memory while trying to allocate 1073741824 bytes.")


def test_a_batch_is_halved_only_where_the_device_ran_out_of_memory():
    """:func:`halved_on_memory`: half the batch after a lack of memory (a warning naming it);
    the same error for one robot, and any other error, raised again as it is."""
    from softcrawl.jaxsim.batch import halved_on_memory

    with pytest.warns(UserWarning, match="out of memory on episodes of 8 robots a batch; going on at 4"):
        assert halved_on_memory(out_of_memory(), 8, "episodes") == 4
    for error, size in ((out_of_memory(), 1), (jax.errors.JaxRuntimeError("INTERNAL: a failed launch"), 8),
                        (ValueError("a bad design"), 8)):
        with pytest.raises(type(error)) as raised:
            halved_on_memory(error, size, "episodes")
        assert raised.value is error


def test_the_evaluator_halves_its_batch_where_the_device_runs_out_of_memory(monkeypatch):
    """Five episodes at a largest batch of 8, on a device (faked) that holds 2 robots: the
    batches of 8 and 4 run out of memory, the evaluator warns twice, goes on at 2 and returns
    every request's result in order (3 batches), counting each episode once; later calls start
    at 2."""
    from softcrawl.jaxsim.episodes import JaxEvaluator, SettledDesign
    from softcrawl.robot import RobotConfig

    ev = JaxEvaluator(RobotConfig(model="reduced"), max_batch=8)
    designs = ["1,1,1,0,0,0,0,0", "1,0,1,0,1,0,0,0", "2,1,1,0,0,0,0,0", "1,2,1,0,0,0,0,0", "1,1,2,0,0,0,0,0"]
    runs = []

    def prepare(ds):
        for d in ds:
            ev._designs[ev.space.canonicalize(d)] = SettledDesign(3, None, 0.0, 0, True, False)

    def run(ds, commands):
        runs.append(len(ds))
        if len(ds) > 2:
            raise out_of_memory()
        return [(float(sum(d)), False) for d in ds]

    monkeypatch.setattr(ev, "prepare", prepare)
    monkeypatch.setattr(ev, "_run", run)
    with pytest.warns(UserWarning, match="out of memory") as caught:
        got = ev.evaluate([(d, short_gait(), 1.0) for d in designs])
    assert len(caught) == 2 and ev.max_batch == 2 and runs == [5, 4, 2, 2, 1]
    assert got == [(float(sum(ev.space.canonicalize(d))), False) for d in designs]
    assert ev.episodes == 5
    ev.evaluate([(designs[0], short_gait(), 1.0)] * 3)
    assert runs[5:] == [2, 1] and ev.episodes == 8


def test_evaluator_refuses_what_it_cannot_run():
    from softcrawl.codesign.groundtruth import DIVERGED_CM
    from softcrawl.jaxsim.episodes import JaxEvaluator
    from softcrawl.robot import RobotConfig

    with pytest.raises(ValueError, match="reduced"):
        JaxEvaluator(RobotConfig(model="full"))
    with pytest.raises(ValueError, match="precision"):
        JaxEvaluator(RobotConfig(model="reduced"), precision="float16")
    with pytest.raises(ValueError, match="power of two"):
        JaxEvaluator(RobotConfig(model="reduced"), max_batch=12)
    if not jax.config.jax_enable_x64:
        with pytest.raises(ValueError, match="jax_enable_x64"):
            JaxEvaluator(RobotConfig(model="reduced"), precision="float64")
    assert JaxEvaluator(RobotConfig(model="reduced")).diverged_cm == DIVERGED_CM


@pytest.mark.slow
def test_episodes_of_two_leg_counts_match_run_episode(x64):
    """One call with a 3- and a 4-legged design (two leg-count groups, each settled once and run
    in its own batch) and the same 2-s gait: each reward is the CPU engine's
    (:func:`run_episode` from its own settled state) within 0.2 mm (measured 0.07 and 0.02 mm on
    rewards of 2.6 and 1.5 mm, float64; the engines' contact solves differ, and their rested
    states by about 0.1 mm). A second call, in the other order, settles nothing (2 settlings in all) and
    gives the same rewards. Slow: four programs compile (about a minute of one core)."""
    from softcrawl.jaxsim.episodes import JaxEvaluator
    from softcrawl.robot import RobotConfig, build_robot, run_episode

    config, gait = RobotConfig(model="reduced"), short_gait()
    ev = JaxEvaluator(config, "float64")
    got = ev.evaluate([(THREE, gait, 2.0), (FOUR, gait, 2.0)])
    assert ev.settles == 2 and ev.episodes == 2 and ev.robot_steps == 2 * 200
    for design, (reward, diverged) in zip((THREE, FOUR), got):
        ref = run_episode(build_robot(design, config), gait, 2.0, record_every=None, progress=False)
        assert not diverged and not ref.diverged and abs(ref.reward_cm) > 0.1
        assert abs(reward - ref.reward_cm) < 0.02, (design, reward, ref.reward_cm)
    again = ev.evaluate([(FOUR, gait, 2.0), (THREE, gait, 2.0)])
    assert ev.settles == 2 and ev.episodes == 4 and ev.robot_steps == 4 * 200
    assert again == got[::-1]
