"""Batched stepping of many reduced robots: every robot's trajectory in a batch equals
its trajectory with its own single-robot :class:`ReducedSolver`, whatever the batch's other robots
do (designs with 3 to 6 legs, different regulators, floor contact, varying pressures, robots
joining and leaving)."""

from pathlib import Path

import numpy as np
import pytest

from helpers import host_fingerprint

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


#: The stored results of :func:`fixed_scene` (relative to ``tests/``): one file per host it was
#: written on (its ``host`` entry, :func:`helpers.host_fingerprint`); the first is the reference for
#: other hosts.
FIXED_SCENE_DATA = ("data/batch_fixed_scene.npz", "data/batch_fixed_scene_znver5.npz")


def fixed_scene(steps: int = 30) -> dict[str, np.ndarray]:
    """A 3-legged and a 4-legged robot (``DESIGNS[:2]``, ``dt`` 0.02 s, double-precision RID)
    stepped ``steps`` times by one :class:`BatchedReducedSolver` from rest under
    :func:`pressures` (they land within ~10 steps, then press on the floor): every robot's
    contact stats after each step ``(2, steps, 5)`` (contacts, sticking, sweeps, relative
    change, normal force mN) and its final contact nodes, impulses (mN s), modal velocities and
    every 16th node's position (mm) and velocity (mm/s)."""
    robots = [build_robot(d, RobotConfig(model="reduced", dt=0.02)) for d in DESIGNS[:2]]
    batch = BatchedReducedSolver([r.make_solver() for r in robots])
    states = [r.model.rest_state() for r in robots]
    stats = np.zeros((len(robots), steps, 5))
    for k in range(steps):
        states = batch.step(states, [r.control(pressures(i, k)) for i, r in enumerate(robots)])
        for i, s in enumerate(batch.solvers):
            st = s.stats
            stats[i, k] = st.n_contacts, st.n_sticking, st.contact_sweeps, st.contact_change, st.normal_force
    out = {"stats": stats, "host": np.array(host_fingerprint())}
    for i, st in enumerate(states):
        out.update({f"x{i}": st.x[::16], f"v{i}": st.v[::16], f"nodes{i}": st.contact_nodes,
                    f"impulses{i}": st.contact_impulses, f"modal{i}": np.concatenate(st.modal_velocities)})
    return out


def test_batched_step_of_a_fixed_scene_reproduces_the_stored_trajectory():
    """:func:`fixed_scene` equals its stored result (``FIXED_SCENE_DATA``, each written by
    ``np.savez(path, **fixed_scene())``; to be rewritten only by a change meant to alter the
    numbers) to the bit on a host with a stored :func:`helpers.host_fingerprint` (runs there, with
    fresh and cached compiled code and reductions, give the same bits). Another CPU's code and
    BLAS kernels round otherwise, and a contact at its threshold or a stick-slip switch follows the
    round-off (the two stored results differ by 0.11 mm and one contact in 30 steps): there,
    every contact count within one and every stored node within 0.5 mm, half the reduced model's
    own error budget against the full-order model (about 1 mm on held-out scenes)."""
    refs = [dict(np.load(Path(__file__).parent / f)) for f in FIXED_SCENE_DATA]
    got = fixed_scene()
    same_host = [r for r in refs if str(r["host"]) == host_fingerprint()]
    ref = same_host[0] if same_host else refs[0]
    assert sorted(got) == sorted(ref)
    assert ref["stats"][:, -1, 0].min() > 0  # both on the floor at the end
    if same_host:
        for key, want in ref.items():
            if key != "host":
                np.testing.assert_array_equal(got[key], want, err_msg=key)
        return
    assert np.abs(got["stats"][..., 0] - ref["stats"][..., 0]).max() <= 1
    for key in ("x0", "x1"):
        assert np.abs(got[key] - ref[key]).max() <= 0.5, key
