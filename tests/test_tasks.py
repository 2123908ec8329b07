"""Tasks as plug-ins (softcrawl.tasks): each task's reward against closed forms on recorded or
rigidly moved states, the env's rewards and termination, the incline's gravity against a
block on an incline, settings validation, and the backends' handling of tasks.

Uses the coarse full-order robot of tests/test_envs.py (16 mm legs, 25 mm disk) and 2 steps
per action."""

import math
from dataclasses import dataclass
from functools import partial

import numpy as np
import pytest

from softcrawl.codesign.config import override, preset
from softcrawl.design.space import BASELINE_DESIGN, PAPER_BEST_DESIGN
from softcrawl.envs import BuildRobot, CrawlerEnv
from softcrawl.envs.backends import make_backend
from softcrawl.envs.backends.jaxcheck import check_jax_task
from softcrawl.fem.solver import ImplicitEulerSolver, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.robot import RobotConfig, build_robot
from softcrawl.tasks import (
    TASKS,
    Forward,
    Heading,
    Incline,
    OnFloor,
    Target,
    Turning,
    disk_yaw_deg,
    make_task,
    parse_task,
    wrap_deg,
)
from softcrawl.tasks.base import Snapshot, replay_return
from softcrawl.tasks.baselines import TurnResult, best_turn, sweep_turning
from softcrawl.verify.checks import block_model

COARSE = RobotConfig(leg_mesh_size=16, disk_mesh_size=25, refactor_every=5)
ACTIONS = np.array([[1, -1, 0.5], [-0.5, 1, -1], [1, 1, -1], [-1, 0.3, 1]], np.float32)


def make_env(**kw):
    kw.setdefault("robot_factory", BuildRobot(COARSE))
    kw.setdefault("steps_per_action", 2)
    kw.setdefault("n_actions", 4)
    kw.setdefault("designs", [PAPER_BEST_DESIGN, BASELINE_DESIGN])
    kw.setdefault("share_robots", True)  # the envs of the tasks on one floor settle a design once
    return CrawlerEnv(**kw)


def run(env, design=PAPER_BEST_DESIGN, actions=ACTIONS):
    """Rewards, infos (reset's first) and the node positions after reset and each action."""
    _, info = env.reset(seed=0, options={"design": design})
    rewards, infos, xs = [], [info], [env.episode.state.x.copy()]
    for a in actions:
        _, r, term, trunc, info = env.step(a)
        rewards.append(r)
        infos.append(info)
        xs.append(env.episode.state.x.copy())
    return rewards, infos, xs


@pytest.fixture(scope="module")
def forward_run():
    env = make_env()
    return env, *run(env)


@pytest.fixture(scope="module")
def robot():
    return build_robot(PAPER_BEST_DESIGN, COARSE)


def rotate_z(x, deg, centre=(0.0, 0.0, 0.0)):
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return (x - centre) @ R.T + centre


# -- forward: the paper's reward, unchanged ----------------------------------------------------

def test_forward_is_the_default_and_its_rewards_are_the_reward_points_x_displacement(forward_run):
    env, rewards, infos, _ = forward_run
    assert isinstance(env.task, Forward) and env.task.unit == "cm"
    assert env.robot_factory == BuildRobot(COARSE)  # not wrapped: the robot cache keys are today's
    x = [info["disk_position_mm"][0] for info in infos]
    # the same floating point operations as the pre-task env: displacement after minus before
    expected = [float(x[k + 1] - x[0]) / 10.0 - float(x[k] - x[0]) / 10.0 for k in range(len(rewards))]
    assert rewards == expected  # bit for bit
    assert any(abs(r) > 1e-3 for r in rewards)  # the robot moved: the comparison can fail
    assert [info["progress"] for info in infos] == [info["displacement_cm"] for info in infos]


def test_heading_0_equals_forward_and_heading_90_the_y_displacement(forward_run):
    env, rewards, infos, _ = forward_run
    h0, _, _ = run(make_env(task="heading"))
    assert h0 == rewards  # heading 0 is forward to the bit
    h90, infos90, _ = run(make_env(task={"name": "heading", "heading_deg": 90}))
    y = [info["disk_position_mm"][1] for info in infos90]
    np.testing.assert_allclose(h90, np.diff(y) / 10.0, rtol=0, atol=1e-12)
    assert max(abs(r) for r in h90) > 1e-4
    h180, _, _ = run(make_env(task={"name": "heading", "heading_deg": -180}))
    np.testing.assert_allclose(h180, -np.array(rewards), rtol=0, atol=1e-12)


# -- turning -----------------------------------------------------------------------------------

@pytest.mark.parametrize("deg", [-170.0, -30.0, 7.5, 90.0, 179.0])
def test_disk_yaw_of_a_rigidly_rotated_robot_is_the_rotation(robot, deg):
    x = robot.model.rest_state().x
    base = disk_yaw_deg(robot, x)
    assert base == pytest.approx(0.0, abs=1e-9)
    for centre in ((0.0, 0.0, 0.0), (35.0, -12.0, 4.0)):  # about any vertical axis
        x_rot = rotate_z(x, deg, centre) + np.array([3.0, -7.0, 1.0])
        assert wrap_deg(disk_yaw_deg(robot, x_rot) - base) == pytest.approx(deg, abs=1e-9)


def test_a_non_finite_disk_has_no_yaw(robot):
    x = robot.model.rest_state().x.copy()
    x[robot.model.body_slice(robot.disk_body)][3, 1] = np.nan
    assert math.isnan(disk_yaw_deg(robot, x))


def test_turning_return_is_the_unwrapped_turn(robot):
    """Snapshots of the robot rigidly turned by 0, 120, 240, 360, 480 degrees: the wrapped
    per-action rewards add up to 480 (more than a turn)."""
    x = robot.model.rest_state().x
    frames = [rotate_z(x, 120.0 * k) for k in range(5)]
    assert replay_return(Turning(), robot, frames) == pytest.approx(480.0, abs=1e-8)
    assert replay_return(Turning(), robot, frames[::-1]) == pytest.approx(-480.0, abs=1e-8)


def test_turning_env_rewards_are_the_disks_yaw_increments():
    env = make_env(task="turning")
    assert env.task.unit == "deg" and env.task.reads_disk
    rewards, _, xs = run(env)
    robot = env.episode.robot
    yaw = [disk_yaw_deg(robot, x) for x in xs]
    np.testing.assert_allclose(rewards, [wrap_deg(b - a) for a, b in zip(yaw[:-1], yaw[1:])], rtol=0, atol=1e-9)
    assert max(abs(r) for r in rewards) > 1e-6  # it yawed a little: the comparison can fail


def test_a_turning_episode_is_scored_at_rest_after_venting():
    """The env's return of a turning episode is what :func:`vented_return` (one
    :func:`run_episode` of the same actions, a second code path) keeps after venting, and with
    ``vent_s = 0`` what it holds at the last action. Tolerance 1e-5°: the replay reads float32
    frames (see the test of :func:`vented_return` against :func:`turned_degrees`)."""
    from softcrawl.envs import action_to_kpa
    from softcrawl.gaits import ActionSequence
    from softcrawl.tasks.base import vented_return

    returns = {}
    for vent in (0.0, 0.5):
        env = make_env(task=Turning(vent_s=vent))
        rewards, _, _ = run(env)
        returns[vent] = sum(rewards)
    robot = env.episode.robot
    gait = ActionSequence(np.array([action_to_kpa(a) for a in ACTIONS]), hold=2 * robot.config.dt)
    held, kept, diverged = vented_return(Turning(), robot, gait, 8 * robot.config.dt, env.settling, vent_seconds=0.5)
    assert not diverged and returns[0.5] == pytest.approx(kept, abs=1e-5) and returns[0.0] == pytest.approx(held, abs=1e-5)
    assert abs(kept - held) > 1e-3  # the vented robot moved on: the two scores differ, the test can fail
    assert env.episode.state.t == pytest.approx(8 * robot.config.dt + 0.5, abs=1e-9)  # 50 steps vented


# -- target ------------------------------------------------------------------------------------

def test_target_reward_is_the_decrease_of_the_distance_and_it_terminates_within_the_radius(robot):
    task = Target(x_mm=30.0, y_mm=40.0, radius_mm=5.0)  # 50 mm away
    x0 = robot.model.rest_state().x
    start = robot.reward_position(x0)
    moves = [(0.0, 0.0), (3.0, 4.0), (-6.0, 8.0), (27.0, 37.0)]
    snaps = [Snapshot(robot, x0 + np.array([dx, dy, 0.0]), start) for dx, dy in moves]
    origin = task.origin(snaps[0])
    progress = [task.progress(s, origin) for s in snaps]
    dist = [math.hypot(30.0 - dx, 40.0 - dy) for dx, dy in moves]
    np.testing.assert_allclose(progress, [(50.0 - d) / 10.0 for d in dist], rtol=0, atol=1e-12)
    assert [task.reached(s, origin) for s in snaps] == [False, False, False, True]  # 3*sqrt(2) < 5 mm


def test_a_reached_goal_terminates_the_episode():
    class Reached(Forward):
        def reached(self, episode, origin):
            return True

    env = make_env(task=Reached())
    env.reset(options={"design": PAPER_BEST_DESIGN})
    _, _, term, trunc, info = env.step(ACTIONS[0])
    assert term and not trunc and not info["diverged"]


# -- incline: gravity tilts, the floor stays -----------------------------------------------------

def test_incline_gravity_is_g_tilted_downhill_along_minus_x():
    g = np.array(Incline(angle_deg=30.0).gravity())
    np.testing.assert_allclose(g, 9800.0 * np.array([-0.5, 0.0, -math.sqrt(3) / 2]), rtol=1e-15, atol=1e-12)
    assert Incline(angle_deg=0.0).gravity()[0] == 0.0


@pytest.mark.parametrize("angle, mu", [(20.0, 0.2), (20.0, 0.5)])
def test_a_block_on_the_incline_slides_or_sticks_as_coulomb_says(angle, mu):
    """A stiff block (verify.checks.block_model) under the task's gravity: it slides downhill
    (-x) at g (sin a - mu cos a) when tan a > mu (5%), else stays (1e-3 mm in 1 s)."""
    model = block_model(np.array(Incline(angle_deg=angle).gravity()), friction=mu)
    solver, state = ImplicitEulerSolver(model, SolverSettings(dt=0.01)), model.rest_state()
    ts, xs = [], []
    for _ in range(100):
        state = solver.step(state, Control(np.zeros(model.n_channels)))
        ts.append(state.t)
        xs.append(state.x[:, 0].mean())
    a = math.radians(angle)
    if math.tan(a) > mu:
        accel = 2 * float(np.polyfit(ts[10:], xs[10:], 2)[0])
        assert accel == pytest.approx(-9800.0 * (math.sin(a) - mu * math.cos(a)), rel=0.05)
    else:
        assert abs(xs[-1] - xs[9]) < 1e-3


def test_the_tasks_floor_reaches_the_robots_and_their_solver():
    env = make_env(task={"name": "incline", "angle_deg": 15.0, "friction": 0.8})
    assert isinstance(env.robot_factory, OnFloor)
    env.reset(options={"design": PAPER_BEST_DESIGN})
    model = env.episode.robot.model
    np.testing.assert_allclose(model.gravity, Incline(angle_deg=15.0).gravity())
    assert model.floor.friction == 0.8 and env.episode.robot.config.friction == 0.8
    assert env.episode.solver.model is model


# -- settings ----------------------------------------------------------------------------------

@pytest.mark.parametrize("spec, match", [
    ("walk", "unknown task 'walk'"),
    ({"name": "heading", "heading_deg": float("nan")}, "heading_deg must be a number in"),
    ({"name": "heading", "heading_deg": 200}, r"\[-180, 180\] deg"),
    ({"name": "incline", "angle_deg": -5}, r"angle_deg must be a number in \[0, 45\]"),
    ({"name": "incline", "angle_deg": True}, "angle_deg"),
    ({"name": "turning", "friction": -1}, "friction"),
    ({"name": "turning", "speed": 2}, "has no setting 'speed'"),
    ({"name": "turning", "vent_s": -1}, r"vent_s must be a number in \[0, 60\] s"),
    ({"name": "target", "x_mm": 10, "y_mm": 0, "radius_mm": 20}, "outside the goal radius"),
    ({"heading_deg": 3}, "needs a name"),
    (3, "a task is a name"),
])
def test_bad_task_settings_get_one_line(spec, match):
    with pytest.raises(ValueError, match=match) as exc:
        parse_task(spec)
    assert "\n" not in str(exc.value)


def test_task_settings_round_trip_and_the_registry():
    assert set(TASKS) == {"forward", "heading", "turning", "target", "incline"}
    for name in TASKS:
        task = make_task(name)
        assert parse_task(task.settings()) == task and task.unit in ("cm", "deg")
        assert not task.observes_state
    t = parse_task({"name": "heading", "heading_deg": 45, "friction": 1})
    assert t == Heading(heading_deg=45.0, friction=1.0) and t.label() == "heading (friction=1, heading_deg=45)"
    assert {n: make_task(n).baseline for n in TASKS} == {"forward": "sine", "heading": None, "turning": "turning",
                                                        "target": None, "incline": None}


def test_env_task_in_the_config():
    cfg = override(preset("smoke"), ['env.task={"name": "heading", "heading_deg": 90}'])
    assert parse_task(cfg.env.task) == Heading(heading_deg=90.0)
    assert override(cfg, ["env.task=turning"]).env.task == "turning"  # a table replaced by a name
    assert preset("demo").env.task == "forward"
    with pytest.raises(ValueError, match=r"^env.task: unknown task 'spin'"):
        override(cfg, ["env.task=spin"])
    with pytest.raises(ValueError, match=r"env.task: task 'heading': heading_deg"):
        override(cfg, ['env.task={"name": "heading", "heading_deg": "north"}'])


# -- backends ----------------------------------------------------------------------------------

def test_the_jax_backend_refuses_a_task_that_reads_the_disk_before_any_work():
    check_jax_task(Heading(heading_deg=30.0))  # a projection of the reward point: supported
    check_jax_task(Incline())
    with pytest.raises(ValueError, match='backend "jax" does not run task \'turning\''):
        check_jax_task(Turning())
    with pytest.raises(ValueError, match='backend "jax" does not run task \'turning\''):
        override(preset("smoke"), ['backend="jax"', 'env.robot.model="reduced"', "env.task=turning"])

    @dataclass(frozen=True)
    class VentedForward(Forward):  # the reward point only, but scored after venting
        @property
        def vent_seconds(self) -> float:
            return 1.0

    with pytest.raises(ValueError, match="scored after venting"):
        check_jax_task(VentedForward())


def test_the_jax_backend_itself_refuses_turning():
    pytest.importorskip("jax")
    from softcrawl.envs.backends.jaxvec import JaxBackend

    with pytest.raises(ValueError, match="does not run task 'turning'"):
        JaxBackend([partial(make_env, task="turning")])


def test_subprocess_workers_carry_the_task():
    fn = partial(make_env, task={"name": "heading", "heading_deg": 90})
    serial = make_backend("serial", [fn])
    sub = make_backend("subprocess", [fn, fn], n_workers=2)
    try:
        assert sub.get_attr("task", [0, 1]) == [Heading(heading_deg=90.0)] * 2
        sub.reset([0, 1], [PAPER_BEST_DESIGN] * 2, [0, 0])
        serial.reset([0], [PAPER_BEST_DESIGN], [0])
        got, want = sub.step(ACTIONS[:2]), serial.step(ACTIONS[:1])
        assert got[0][1] == want[0][1]  # the same heading reward as in-process
    finally:
        sub.close()
        serial.close()


# -- the turning baseline -----------------------------------------------------------------------

def test_best_turn_and_sweep_checks():
    results = [TurnResult(0.0, 3.0, False, 1.0), TurnResult(90.0, -7.0, False, 1.0),
               TurnResult(180.0, float("nan"), True, 1.0)]
    assert best_turn(results).phase_deg == 90.0  # furthest either way
    assert best_turn(results[2:]) is None
    with pytest.raises(ValueError, match="distinct"):
        sweep_turning(BuildRobot(COARSE), [0.0, 0.0])
    with pytest.raises(ValueError, match="duration"):
        sweep_turning(BuildRobot(COARSE), [0.0], duration=0.0)


# -- the report ----------------------------------------------------------------------------------

def test_the_reports_baseline_section_of_a_task_without_one(tmp_path):
    from softcrawl.codesign.report import _task_baseline_section

    cfg = override(preset("smoke"), ["env.task=target"])
    lines, numbers = _task_baseline_section(cfg, parse_task(cfg.env.task), tmp_path, None, (0.0,), True, 1)
    assert lines[1] == "## Expert baseline" and "The task `target` has no expert baseline." in lines
    assert numbers == {} and not any(tmp_path.iterdir())


def test_replaying_frames_gives_the_forward_return(robot):
    x0 = robot.model.rest_state().x
    frames = [x0 + np.array([d, 0.5 * d, 0.0]) for d in (0.0, 4.0, -2.0, 11.0)]
    assert replay_return(Forward(), robot, frames) == pytest.approx(1.1, abs=1e-12)  # 11 mm
    assert math.isnan(replay_return(Forward(), robot, []))


@pytest.mark.slow  # compiles the JAX engine twice: about 100 s on 2 busy cores
def test_the_jax_backend_scores_heading_and_tilts_gravity_for_incline(x64):
    """The JAX backend reads the reward point only: heading 90's rewards are its y increments
    (cm), and an incline's gravity is in its compiled model."""
    pytest.importorskip("jax")
    from softcrawl.codesign.factory import env_fn

    cfg = override(preset("smoke"), ['backend="jax"', "env.steps_per_action=25", "env.n_actions=2",
                                     'env.task={"name": "heading", "heading_deg": 90}'])
    b = make_backend("jax", [env_fn(cfg)])
    try:
        (_, info), = b.reset([0], [PAPER_BEST_DESIGN], [0])
        y = [info["disk_position_mm"][1]]
        rewards = []
        for a in ACTIONS[:2]:
            (_, r, _, _, info), = b.step(a[None])
            rewards.append(r)
            y.append(info["disk_position_mm"][1])
        np.testing.assert_allclose(rewards, np.diff(y) / 10.0, rtol=0, atol=1e-12)
        assert max(abs(r) for r in rewards) > 1e-4
    finally:
        b.close()
    b = make_backend("jax", [env_fn(override(cfg, ['env.task={"name": "incline", "angle_deg": 20}']))])
    try:
        np.testing.assert_allclose(b._model.settings.gravity, Incline(angle_deg=20.0).gravity())
    finally:
        b.close()


def test_turned_degrees_samples_the_last_step_of_a_short_episode(robot):
    """Regression: a 0.4 s episode sampled every 1 s was scored from its first frame alone (0°).
    Here a stub solver turns the robot rigidly by 1° per step: 0.4 s at dt 0.01 s is 40°."""
    import dataclasses

    from softcrawl.robot import NO_SETTLING
    from softcrawl.tasks.baselines import turned_degrees, turning_gait

    class Spin:
        stats = type("Stats", (), {"n_contacts": 0, "contact_sweeps": 0, "factorizations": 0})()

        def step(self, state, control):
            return dataclasses.replace(state, x=rotate_z(state.x, 1.0), t=state.t + 0.01)

    class Spinning:  # the robot, stepped by Spin
        def __getattr__(self, name):
            return getattr(robot, name)

        def make_solver(self):
            return Spin()

    assert robot.config.dt == 0.01
    turned, diverged = turned_degrees(Spinning(), turning_gait(90.0), 0.4, settling=NO_SETTLING)
    assert not diverged and turned == pytest.approx(40.0, abs=1e-8)
    turned, _ = turned_degrees(Spinning(), turning_gait(90.0), 2.5, settling=NO_SETTLING)
    assert turned == pytest.approx(250.0, abs=1e-8)  # unwrapped, 1-s samples and the last step
    turned, _ = turned_degrees(Spinning(), turning_gait(90.0), 0.4, settling=NO_SETTLING, vent_seconds=0.6)
    assert turned == pytest.approx(100.0, abs=1e-8)  # scored after 60 more steps, vented


def test_a_twist_held_by_the_pressure_is_not_kept_after_venting_and_a_turn_is(robot):
    """:func:`vented_return` on two stub solvers of the robot: one twists the body to 0.1° per
    simulated kPa of the first cavity and no further (an elastic twist held by the pressure), one
    turns it 1° per step whatever the pressure (a turn on the floor). The regulators slew to
    0 kPa at 150 kPa/s (:class:`softcrawl.robot.actuation.RegulatorBank`: 0.3 s from 45 kPa), so
    after the 5 s the twist is gone and the turn has gone on 500 steps."""
    import dataclasses

    from softcrawl.gaits import SineGait, VentedAfter
    from softcrawl.robot import NO_SETTLING
    from softcrawl.tasks.base import VENT_SECONDS, vented_return

    rest = robot.model.rest_state().x

    class Stub:
        stats = type("Stats", (), {"n_contacts": 0, "contact_sweeps": 0, "factorizations": 0})()

        def __init__(self, twist):
            self.twist = twist

        def step(self, state, control):
            x = rotate_z(rest, 0.1 * control.pressures[0]) if self.twist else rotate_z(state.x, 1.0)
            return dataclasses.replace(state, x=x, t=state.t + 0.01)

    class Stubbed:
        def __init__(self, twist):
            self.twist = twist

        def __getattr__(self, name):
            return getattr(robot, name)

        def make_solver(self):
            return Stub(self.twist)

    hold = SineGait(offset=45.0, amplitude=0.0)  # 45 kPa held
    held, kept, diverged = vented_return(Turning(), Stubbed(True), hold, 2.0, settling=NO_SETTLING)
    assert not diverged and held > 1.0 and abs(kept) < 0.01 * held
    held, kept, _ = vented_return(Turning(), Stubbed(False), hold, 2.0, settling=NO_SETTLING)
    assert held == pytest.approx(200.0, abs=1e-6) and kept == pytest.approx(200.0 + 100 * VENT_SECONDS, abs=1e-6)
    assert np.array_equal(VentedAfter(hold, 2.0).pressure_at(1.99), [45.0, 45.0, 0.0])
    assert not VentedAfter(hold, 2.0).pressure_at(2.0).any()
    with pytest.raises(ValueError, match="after_s"):
        VentedAfter(hold, -1.0)
    with pytest.raises(ValueError, match="vent_seconds"):
        vented_return(Turning(), robot, hold, 2.0, vent_seconds=0.0)


def test_the_vented_return_up_to_the_episodes_end_is_the_turning_baselines(robot):
    """The first number of :func:`vented_return` is the same simulation's yaw as
    :func:`turned_degrees` gives (coarse robot, 2 s of the baseline gait: both step the same
    gait from the same settled state until then). Tolerance 1e-5°: the frames it reads are stored
    in float32 (rounding at most 6e-6 mm at the robot's 100 mm), :func:`turned_degrees` reads
    float64; one node's rounding moves the fitted yaw by at most 6e-6 / 50 rad = 7e-6°, and the
    fit averages many nodes (measured 1.7e-7°)."""
    from softcrawl.tasks.base import vented_return
    from softcrawl.tasks.baselines import turned_degrees, turning_gait

    gait = turning_gait(90.0)
    held, kept, diverged = vented_return(Turning(), robot, gait, 2.0, vent_seconds=1.0)
    turned, _ = turned_degrees(robot, gait, 2.0)
    assert not diverged and held == pytest.approx(turned, abs=1e-5) and math.isfinite(kept)


def test_a_turning_runs_report_is_in_degrees_and_leaves_out_a_forward_sweep(run, tmp_path):
    """The smoke run's config relabelled as a turning run (its logs stay as they are): the
    report's columns and numbers say deg, a forward baseline sweep is left out."""
    import json

    from softcrawl.codesign.report import write_report

    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["env"]["task"] = "turning"
    (run / "config.json").write_text(json.dumps(cfg))
    sweep = tmp_path / "sweep.json"
    sweep.write_text(json.dumps({"settings": {"design": [1, 0, 0, 2, 2, 0, 0, 1], "duration_s": 20.0,
                                              "config": {"model": "reduced"}},
                                 "best": {"phase_deg": 250.0, "reward_cm": 3.21}}))
    out = write_report(run, baseline=sweep, simulate=False)
    summary = (out / "summary.md").read_text()
    assert ("- task: `turning`: degrees the disk yaws counter-clockwise about +z, kept at rest after venting "
            "(returns in deg)") in summary
    assert "| rank | design | R (deg) | p | episodes | mean (deg) | best (deg) | picture |" in summary
    assert "250°" not in summary and "## Expert baseline" in summary
    assert (out / "top_designs.csv").read_text().splitlines()[0] == "rank,design,latest_deg,prob,episodes,mean_deg,best_deg"
    numbers = json.loads((out / "summary.json").read_text())
    assert numbers["task"] == {"name": "turning", "friction": None, "vent_s": 5.0} and "best_episode_deg" in numbers
    assert "baseline" not in numbers


def test_train_task_flag(capsys, tmp_path):
    """``softcrawl train --task``: a bad task's value is one line before any work; the settings
    of ``--task`` go to a new run's config, not to ``--resume``."""
    from helpers import one_line_error

    from softcrawl.cli import main

    out = tmp_path / "run"
    one_line_error(capsys, main(["train", "--resume", "--task", "turning", "--out", str(out), "--no-progress"]),
                   "--resume uses the run's saved config.json")
    one_line_error(capsys, main(["train", "--preset", "smoke", "--set", 'env.task={"name": "heading", "heading_deg": 400}',
                                 "--out", str(out), "--no-progress"]), "env.task: task 'heading': heading_deg")
    assert not out.exists()  # nothing written
    one_line_error(capsys, main(["train", "--task", "spin", "--out", str(out)]), "--task: unknown task 'spin'")
    one_line_error(capsys, main(["train", "--task", '{"name": "heading", "heading_deg": 400}', "--out", str(out)]),
                   "--task: task 'heading': heading_deg")
    assert not out.exists()


# -- issue 49, defect 11: a robot that does not come to rest is said, where the user looks ---------------

def test_an_incline_steeper_than_its_friction_is_refused_up_front(tmp_path, capsys):
    """Coulomb: a robot slides down a slope with tan a > mu for good (the probe's episodes slid
    at 18 m/s after the 3-s settling cap); such a floor is refused where the task meets the robot."""
    from helpers import one_line_error

    from softcrawl.cli import main
    from softcrawl.codesign.groundtruth import GroundTruthConfig, gt_robot

    with pytest.raises(ValueError, match=r"task 'incline': its floor is tilted 40 deg .*friction mu = 0.5"):
        Incline(angle_deg=40.0, friction=0.5)
    assert Incline(angle_deg=26.0, friction=0.5).friction == 0.5 and Incline(angle_deg=45.0).friction is None
    with pytest.raises(ValueError, match="env.task: task 'incline'.*mu = 0.3"):
        override(preset("smoke"), ['env.task={"name": "incline", "angle_deg": 20}', "env.robot.friction=0.3"])
    with pytest.raises(ValueError, match="task: task 'incline'"):
        GroundTruthConfig(task={"name": "incline", "angle_deg": 20}, robot=gt_robot(friction=0.3)).validate()
    rc = main(["simulate", "--task", '{"name": "incline", "angle_deg": 20}', "--friction", "0.3", "--out",
               str(tmp_path / "o"), "--no-progress"])
    one_line_error(capsys, rc, "--task: task 'incline'", "slides down")
    assert not (tmp_path / "o").exists()


def test_an_unsettled_start_is_in_the_envs_info_and_a_line_of_simulate(tmp_path, monkeypatch, capsys):
    from softcrawl.cli import main
    import softcrawl.cli.simulate as sim
    from softcrawl.robot.episode import Settling, run_episode, unsettled_warning

    env = make_env(settling=Settling(max_seconds=0.02), share_robots=False)  # capped before the fall ends
    _, info = env.reset(options={"design": PAPER_BEST_DESIGN})
    assert info["at_rest"] is False and "did not come to rest" in unsettled_warning(info)
    _, _, _, _, info = env.step(ACTIONS[0])
    assert info["at_rest"] is False
    assert unsettled_warning({**info, "at_rest": True}) is None and unsettled_warning({}) is None
    monkeypatch.setattr(sim, "run_episode", lambda *a, **k: run_episode(*a, **k, settling=Settling(max_seconds=0.02)))
    assert main(["simulate", "--disk-mesh-size", "25", "--duration", "0.02", "--out", str(tmp_path / "o"),
                 "--no-progress", "--no-animation"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert [line for line in err if "warning" in line] == [
        f"softcrawl simulate: warning: design 1,0,0,2,2,0,0,1 {unsettled_warning(sim_settled(tmp_path / 'o'))}"]


def sim_settled(out) -> dict:
    """The settling statistics in a ``softcrawl simulate`` output's summary.json."""
    import json

    return json.loads((out / "summary.json").read_text())["settling"]


def test_training_warns_once_per_unsettled_design_and_the_report_says_it(tmp_path, capsys):
    """Whatever the backend, the env's ``at_rest`` reaches the training loop: one warning line per
    design (not per episode); the report's best design says it too."""
    import json

    from softcrawl.codesign.report import write_report
    from softcrawl.codesign.training import train

    run = tmp_path / "run"
    train(run, override(preset("smoke"), ["total_steps=120", "checkpoint_every=120", "env.settle_max_seconds=0.02"]),
          progress=False)
    designs = {row[1] for row in (r.split(",") for r in (run / "episodes.csv").read_text().splitlines())}
    episodes = len((run / "episodes.csv").read_text().splitlines())
    warnings = [line for line in capsys.readouterr().err.splitlines() if "softcrawl train: warning: design" in line]
    assert episodes > len(designs) and len(warnings) == len(designs), (episodes, designs, warnings)
    assert all("did not come to rest" in w and "(said once per design)" in w for w in warnings)
    out = write_report(run, baseline_phases=(), samples=0)
    summary, numbers = (out / "summary.md").read_text(), json.loads((out / "summary.json").read_text())
    assert "**Warning**: `" in summary and "did not come to rest" in summary
    assert numbers["best_design"]["settled"]["at_rest"] is False
