"""Batched stepping of many reduced robots: every robot's trajectory in a batch equals
its trajectory with its own single-robot :class:`ReducedSolver`, whatever the batch's other robots
do (designs with 3 to 6 legs, different regulators, floor contact, varying pressures, robots
joining and leaving); a fixed scene stays within half the reduced model's error budget of its
stored result on any CPU."""

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from softcrawl.fem.solver import SimulationDiverged
from softcrawl.fem.state import Control
from softcrawl.reduction.batch import BatchedReducedSolver
from softcrawl.robot import RobotConfig, build_robot

#: 3, 4, 5 and 6 legs on different regulators.
DESIGNS = [(1, 0, 0, 2, 0, 0, 3, 0), (1, 0, 2, 0, 2, 0, 1, 0), (0, 1, 3, 2, 0, 1, 2, 0), (1, 2, 3, 1, 2, 3, 0, 0)]


def pressures(robot: int, k: int) -> np.ndarray:
    """Sim kPa of robot ``robot`` at step ``k``: every channel on its own phase, 0..60 kPa."""
    return 30.0 * (1.0 - np.cos(0.05 * k + np.array([0.0, 2.0, 4.0]) + robot))


@pytest.fixture(scope="module", params=[{"rid_dtype": "float64"}, {"rid_dtype": "float32"},
                                        {"rid_dtype": "float32", "leg_collision_spacing": 4.0}],
                ids=["float64", "float32", "coarse-contact"])
def robots(request):
    """The designs' reduced robots, with the RID products in double or single precision, and with
    the legs' contact points 4 mm apart (``RobotConfig.leg_collision_spacing``)."""
    return [build_robot(d, RobotConfig(model="reduced", **request.param)) for d in DESIGNS]


def solo(robot, index: int, steps: int, start: int = 0):
    """States after each step of ``robot`` stepped alone from rest (pressures from step ``start``)."""
    solver, state, out = robot.make_solver(), robot.model.rest_state(), []
    for k in range(steps):
        state = solver.step(state, robot.control(pressures(index, start + k)))
        out.append(state)
    return out


def test_batched_trajectories_equal_single_robot_ones(robots):
    steps = 150  # lands within ~15 steps, then 1.35 s of pressurised contact
    batch = BatchedReducedSolver([r.make_solver() for r in robots])
    assert batch._compiled is not None  # all robots' constraints in one compiled pass
    states = [r.model.rest_state() for r in robots]
    runs = [[] for _ in robots]
    for k in range(steps):
        states = batch.step(states, [r.control(pressures(i, k)) for i, r in enumerate(robots)])
        for run, st in zip(runs, states):
            run.append(st)
    for i, robot in enumerate(robots):
        ref = solo(robot, i, steps)
        assert max(len(s.contact_nodes) for s in ref) > 0  # on the floor
        for a, b in zip(runs[i], ref):
            assert np.abs(a.x - b.x).max() <= 1e-9 and np.abs(a.v - b.v).max() <= 1e-9 * 1e3
            np.testing.assert_array_equal(a.contact_nodes, b.contact_nodes)
            assert a.t == b.t


def test_robots_joining_and_leaving_do_not_disturb_the_others(robots):
    """Robot 0 runs 150 steps; robot 1 joins at step 30 and leaves at 100; robot 2 joins at 60
    (after robot 3 left at 40, which had run from the start): each equals its solo run."""
    plan = {0: (0, 150), 1: (30, 100), 2: (60, 150), 3: (0, 40)}
    solvers, states, runs, batch, members = {}, {}, {i: [] for i in plan}, None, ()
    for k in range(150):
        live = tuple(i for i, (a, b) in plan.items() if a <= k < b)
        for i in live:
            if i not in solvers:
                solvers[i], states[i] = robots[i].make_solver(), robots[i].model.rest_state()
        if live != members:  # a new batch of the same solvers (their kept velocities go on)
            batch, members = BatchedReducedSolver([solvers[i] for i in live]), live
        out = batch.step([states[i] for i in live], [robots[i].control(pressures(i, k - plan[i][0])) for i in live])
        for i, st in zip(live, out):
            states[i] = st
            runs[i].append(st)
    for i, (a, b) in plan.items():
        ref = solo(robots[i], i, b - a)
        assert len(runs[i]) == len(ref)
        assert max(np.abs(s.x - r.x).max() for s, r in zip(runs[i], ref)) <= 1e-9


def test_a_diverging_robot_is_reported_and_the_others_go_on(robots):
    batch = BatchedReducedSolver([r.make_solver() for r in robots[:2]])
    states = [r.model.rest_state() for r in robots[:2]]
    bad = states[1].x.copy()
    bad[5] = np.nan
    states[1] = type(states[1])(bad, states[1].v)
    out = batch.step(states, [r.control(np.zeros(3)) for r in robots[:2]])
    assert isinstance(out[1], SimulationDiverged)
    ref = robots[0].make_solver().step(robots[0].model.rest_state(), robots[0].control(np.zeros(3)))
    assert np.abs(out[0].x - ref.x).max() == 0.0
    with pytest.raises(ValueError):
        batch.step(states[:1], [Control(np.zeros(3))])


#: The stored result of :func:`fixed_scene` (``np.savez(FIXED_SCENE, **fixed_scene(robots))``; to
#: be rewritten only by a change meant to alter the numbers).
FIXED_SCENE = Path(__file__).parent / "data" / "batch_fixed_scene.npz"

#: mm: the most a robot's mean node distance to the stored :data:`FIXED_SCENE` may be on any CPU
#: (its measurement: :func:`test_batched_step_of_a_fixed_scene_reproduces_the_stored_trajectory`).
FIXED_SCENE_TOL_MM = 0.5


@pytest.fixture(scope="module")
def scene_robots():
    """The robots of :func:`fixed_scene`: a 3-legged and a 4-legged one (``DESIGNS[:2]``, ``dt``
    0.02 s, double-precision RID)."""
    return [build_robot(d, RobotConfig(model="reduced", dt=0.02)) for d in DESIGNS[:2]]


def fixed_scene(robots, offset_mm=(0.0, 0.0, 0.0), steps: int = 30) -> dict[str, np.ndarray]:
    """``robots`` (:func:`scene_robots`) stepped ``steps`` times by one
    :class:`BatchedReducedSolver` from rest, every node translated by ``offset_mm`` ``(3,)`` mm,
    under :func:`pressures` (they land within ~10 steps, then press on the floor): every 16th
    node's final position of robot ``i`` as ``x{i}`` ``(n_i, 3)`` mm."""
    batch = BatchedReducedSolver([r.make_solver() for r in robots])
    states = [r.model.rest_state() for r in robots]
    states = [dataclasses.replace(s, x=s.x + np.asarray(offset_mm, float)) for s in states]
    for k in range(steps):
        states = batch.step(states, [r.control(pressures(i, k)) for i, r in enumerate(robots)])
    return {f"x{i}": st.x[::16] for i, st in enumerate(states)}


def assert_near_stored_scene(got: dict[str, np.ndarray]) -> None:
    """Assert that ``got`` (:func:`fixed_scene`) has the stored result's robots and that each
    robot's nodes lie on average within :data:`FIXED_SCENE_TOL_MM` of the stored ones.

    Raises:
        AssertionError: naming the robot and its mean node distance, mm.
    """
    with np.load(FIXED_SCENE) as ref:
        assert sorted(got) == sorted(ref.files)
        for key in ref.files:
            err = np.linalg.norm(got[key] - ref[key], axis=1).mean()
            assert err <= FIXED_SCENE_TOL_MM, f"{key}: mean node distance {err:.3g} mm from the stored result"


def test_batched_step_of_a_fixed_scene_reproduces_the_stored_trajectory(scene_robots):
    """:func:`fixed_scene` is its stored result within :data:`FIXED_SCENE_TOL_MM` on any CPU:
    each robot's mean node distance at most 0.5 mm, half the reduced model's validated error
    budget (mean node error <= 1 mm, docs/reduction.md). Another CPU's code and BLAS kernels
    round otherwise, and a contact at its threshold or a stick-slip switch follows the
    round-off, so the scene ends on another of a few nearby trajectories; its discrete outcomes
    (contact counts, stick-slip switches) are not compared. Measured: results written on three
    CPUs within 0.063 mm of the stored one (up to 5 contacts apart at a step); 200 scenes whose
    start was translated by 1e-12 mm in random directions within 0.19 mm (0.26 mm for the
    farthest node); the start translated by 1 mm, 0.99-1.0 mm away."""
    assert_near_stored_scene(fixed_scene(scene_robots))


def test_another_cpus_round_off_keeps_the_fixed_scene_near_its_stored_result(scene_robots):
    """Another CPU simulated: the scene's start translated by 1e-12 mm along each axis, both
    ways (the positions' last bits change, as another CPU's rounding changes them), still
    passes :func:`assert_near_stored_scene`."""
    for offset in np.vstack([np.eye(3), -np.eye(3)]) * 1e-12:
        assert_near_stored_scene(fixed_scene(scene_robots, offset))


def test_a_fixed_scene_one_mm_away_fails_the_stored_result_check(scene_robots):
    """The check can fail: the scene's start translated by 1 mm along +x (its robots end
    about 1 mm from the stored ones) is rejected by :func:`assert_near_stored_scene`."""
    with pytest.raises(AssertionError, match="mean node distance"):
        assert_near_stored_scene(fixed_scene(scene_robots, (1.0, 0.0, 0.0)))
