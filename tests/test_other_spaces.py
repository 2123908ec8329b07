"""Robots, gaits, envs, domain randomization, both engines and the ground-truth gait search on
design spaces other than the paper's: the shipped ``hex6`` space (full order, coarse mesh) and a
space written here, the paper's PneuNet and reduction on 6 slots at 30 + 60 i deg with 2
regulators (reduced: the CPU and the JAX engine)."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from softcrawl.design.spacefile import load_space, shipped_space_path
from softcrawl.gaits import ActionSequence, PeriodicGait, SineGait, read_actions_csv, write_actions_csv
from softcrawl.robot import NO_SETTLING, RobotConfig, build_robot, run_episode

#: A design of the 6-slot space: slot 0 (30 deg) on regulator 1, slots 2 and 3 (150, 210 deg) on 2.
DESIGN = (1, 0, 2, 2, 0, 0)
#: The regulators' slew, kPa/s (physics.md, "Regulator dynamics").
RATE_KPA_S = 150.0


@pytest.fixture(scope="module")
def six(tmp_path_factory):
    """The paper's space file with 6 equally spaced slots, 2 regulators and 2-4 legs (the paper's
    PneuNet and its shipped reduction, ``reduction = "softcrawl:pneunet_6mm.npz"``)."""
    text = shipped_space_path("paper").read_text()
    for old, new in (('name = "paper"', 'name = "six2"'), ("count = 8", "count = 6"),
                     ("first_angle_deg = 22.5", "first_angle_deg = 30.0"), ("regulators = 3", "regulators = 2"),
                     ("min_legs = 3", "min_legs = 2"), ("max_legs = 6", "max_legs = 4")):
        assert text.count(old) == 1, old
        text = text.replace(old, new)
    assert 'reduction = "softcrawl:pneunet_6mm.npz"' in text
    path = tmp_path_factory.mktemp("space") / "six2.toml"
    path.write_text(text)
    space = load_space(path)
    assert (space.n_slots, space.n_regulators, space.slot_angles_deg[:2]) == (6, 2, (30.0, 90.0))
    return space


@pytest.fixture(scope="module")
def six_config(six):
    """The reduced robot of the 6-slot space: the reduction's 6 mm legs, a 25 mm floating disk."""
    return RobotConfig.for_space(six, model="reduced", disk_mesh_size=25.0)


@pytest.fixture(scope="module")
def six_robot(six, six_config):
    return build_robot(DESIGN, six_config, space=six)


def slewed(command: np.ndarray, steps: int, dt: float) -> np.ndarray:
    """``(steps + 1, R)`` regulator outputs from 0 kPa slewing at :data:`RATE_KPA_S` toward a
    held ``command``: ``min(rate k dt, command)`` after step ``k``."""
    k = np.arange(steps + 1)[:, None]
    return np.minimum(RATE_KPA_S * k * dt, np.asarray(command, float)[None])


# -- gaits -----------------------------------------------------------------------------------------
def test_action_csv_of_two_regulators(tmp_path):
    """A 2-regulator action sequence round-trips through its CSV (header ``p1,p2``); the width
    comes from the header or the first row, or is required by ``n_regulators``, and a row of
    another width is refused naming its line."""
    seq = ActionSequence(np.random.default_rng(2).uniform(0, 90, (5, 2)), hold=0.5)
    assert seq.n_regulators == 2 and seq.pressure_at(0.6).shape == (2,)
    path = tmp_path / "a.csv"
    write_actions_csv(seq, path)
    assert path.read_text().splitlines()[0] == "p1,p2"
    for n in (None, 2):
        back = read_actions_csv(path, hold=0.5, n_regulators=n)
        np.testing.assert_array_equal(back.actions, seq.actions)
    with pytest.raises(ValueError, match=r"a\.csv, line 1: expected 3 columns, got 2"):
        read_actions_csv(path, n_regulators=3)  # the header of 2 regulators is no header of 3
    path.write_text("0,90\n90,0,0\n")
    with pytest.raises(ValueError, match=r"a\.csv, line 2: expected 2 columns, got 3"):
        read_actions_csv(path)


def test_periodic_gaits_of_two_regulators():
    """A knot table of 2 columns is a 2-regulator gait; the expert sine for 2 regulators is the
    paper's :class:`SineGait` without its third (zero) regulator at every t (a raised cosine
    through 4 samples is exact), and needs a front and a rear regulator."""
    g = PeriodicGait.from_knots([[90, 0], [0, 45]], hold=0.5)
    assert g.n_regulators == 2 and g.period == 1.0
    np.testing.assert_array_equal(g.pressure_at(0.7), [0.0, 45.0])
    for phase in (0.0, 110.0, 250.0):
        two, ref = PeriodicGait.expert_sine(phase, n_regulators=2), SineGait(phase_deg=phase)
        for t in np.linspace(-1.0, 9.0, 101):
            np.testing.assert_allclose(two.pressure_at(t), ref.pressure_at(t)[:2], rtol=0, atol=1e-9)
    with pytest.raises(ValueError, match="front and a rear regulator"):
        PeriodicGait.expert_sine(90.0, n_regulators=1)


# -- a full-order robot of the shipped hex6 space ----------------------------------------------------
def test_hex6_robot_episode_and_outputs(tmp_path):
    """A full-order hex6 robot (6-chamber legs, 2 regulators, coarse 12/25 mm meshes), 5 steps
    from the assembled pose: the episode records 2 commanded and 2 applied pressures, the applied
    ones the slew-limited ``min(150 kPa/s t, command)`` exactly; its trajectory CSV has the
    2-regulator columns; a 3-regulator gait and a regulator 3 are refused, naming the count."""
    from softcrawl.robot.output import csv_columns, write_trajectory

    hex6 = load_space(shipped_space_path("hex6"))
    robot = build_robot("1,0,2,0,1,0", RobotConfig.for_space(hex6, leg_mesh_size=12.0, disk_mesh_size=25.0),
                        space=hex6)
    assert robot.model.n_channels == 2 and robot.channel_of(2) == 1
    with pytest.raises(ValueError, match=r"regulator must be in 1\.\.2"):
        robot.channel_of(3)
    command = np.array([90.0, 3.0])
    res = run_episode(robot, ActionSequence(command[None]), duration=0.05, settling=NO_SETTLING,
                      record_every=None, progress=False)
    assert not res.diverged and res.steps == 5
    assert res.commanded.shape == res.applied.shape == (6, 2)
    np.testing.assert_array_equal(res.commanded[1:], np.tile(command, (5, 1)))
    np.testing.assert_allclose(res.applied, slewed(command, 5, robot.config.dt), rtol=0, atol=1e-12)
    write_trajectory(tmp_path, res)
    with (tmp_path / "trajectory.csv").open(newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == csv_columns(2) == ("t", "x", "y", "z", "cmd_1", "cmd_2", "applied_1", "applied_2",
                                                "contacts")
    assert len(rows) == 7 and all(len(r) == 9 for r in rows)
    with pytest.raises(ValueError, match="the robot has 2 regulators"):
        run_episode(robot, SineGait(), duration=0.01, settling=NO_SETTLING, record_every=None, progress=False)


# -- the reduced 6-slot robot: CPU and JAX engines ---------------------------------------------------
def test_jax_engine_follows_the_cpu_engine_on_the_six_slot_space(x64, six, six_robot):
    """The JAX model of a 6-slot, 2-regulator robot places each leg at its slot's angle
    (``R_z(theta) R_y(15 deg)``, physics.md "Geometry") and carries 2 regulator channels. Landing
    from the assembled pose (0.5 s at zero pressure), then 1 s with the regulators at 90 and
    40 kPa: the mean node distance to the CPU reduced engine over the scene stays below 0.3 mm and
    the reward point ends within 0.3 mm of it, the bounds of the paper-space test
    (``tests/test_jaxsim_robot.py``; the engines differ in the contact solve only). Measured
    0.086 mm and 0.105 mm (float64), the reward point having moved 17.6 mm."""
    from jaxsim_helpers import assert_follows, scene

    from softcrawl.jaxsim.engine import rest_state
    from softcrawl.jaxsim.model import build_model
    from softcrawl.robot.assembly import leg_transform

    model = build_model([six_robot])
    assert model.settings.channels == 2 and rest_state(model).pressure.shape == (1, 2)
    slots = [leg.slot for leg in six_robot.legs]
    assert slots == [0, 2, 3]
    for j, slot in enumerate(slots):
        R, _ = leg_transform(six.slot_angles_deg[slot])
        np.testing.assert_allclose(np.asarray(model.robot.rotation[0, j]), R, rtol=0, atol=1e-12)
        assert int(model.robot.channel[0, j]) == DESIGN[slot] - 1
    ref, got, st = scene(six_robot, model, [(0, 0), (90, 40), (90, 40)], 50)
    assert_follows(six_robot, ref, got, st)
    np.testing.assert_allclose(np.asarray(st.pressure[0]), [90.0, 40.0], rtol=0, atol=1e-12)


def test_jax_evaluator_checks_gaits_against_the_space(six, six_config):
    """The batched episode runner canonicalises designs of its space and refuses a gait of the
    paper's 3 regulators on a 2-regulator space before anything is built or simulated."""
    pytest.importorskip("jax")
    from softcrawl.jaxsim.episodes import JaxEvaluator

    ev = JaxEvaluator(six_config, space=six)
    with pytest.raises(ValueError, match="commands 3 pressures; the space 'six2' has 2 regulators"):
        ev.evaluate([((2, 0, 1, 1, 0, 0), SineGait(), 0.1)])
    assert ev.settles == 0 and not ev._designs


# -- domain randomization of a 2-regulator env -------------------------------------------------------
RIG = dict(pressure_gain=(0.9, 1.2), pressure_offset=(-5.0, -2.0), tau_inflate=(0.05, 0.5), tau_vent=(0.2, 0.6))


def test_randomized_env_of_two_regulators(six, six_config):
    """An env of the 2-regulator space draws its per-regulator quantities once per regulator,
    from its RNG (the draw of ``DomainRanges.draw(default_rng(seed), 2)`` when the design is
    given), gets 2 lagged regulators and the warp ``sim = max(a (g p + o) + b, 0)`` per regulator,
    a randomized robot for the physical keys, and logs 2 columns per per-regulator key."""
    from softcrawl.envs import BuildRobot, CrawlerEnv
    from softcrawl.robot import DomainRanges, DomainSample, PressureCalibration
    from softcrawl.robot.domain import LaggedRegulatorBank, RegulatorWarp

    ranges = DomainRanges(youngs_scale=(0.97, 1.03), **RIG)
    env = CrawlerEnv(BuildRobot(six_config, six), steps_per_action=5, n_actions=2, designs=[DESIGN],
                     randomize=ranges, space=six)
    _, info = env.reset(seed=3, options={"design": DESIGN})
    expect = ranges.draw(np.random.default_rng(3), 2)
    assert info["domain"] == expect.as_dict() and env.domain == expect
    for key, (lo, hi) in RIG.items():
        v = np.array(info["domain"][key])
        assert v.shape == (2,) and np.all((v >= lo) & (v <= hi)), key
    ep = env.episode
    assert isinstance(ep.regulators, LaggedRegulatorBank) and ep.regulators.n == 2
    np.testing.assert_array_equal(ep.regulators.tau_inflate, expect.tau_inflate)
    assert isinstance(ep.calibration, RegulatorWarp)
    cal, p = PressureCalibration(), np.array([50.0, 20.0])
    g, o = np.array(expect.pressure_gain), np.array(expect.pressure_offset)
    np.testing.assert_allclose(ep.calibration.to_sim(p), np.maximum(cal.a * (g * p + o) + cal.b, 0.0),
                               rtol=1e-15, atol=0)
    assert ep.robot is not env.cached_robot(DESIGN)[0]  # the Young's modulus sample: a robot of its own
    obs, reward, terminated, _, info = env.step(np.array([1.0, 0.0], np.float32))
    assert np.isfinite(reward) and not terminated and info["applied_kpa"].shape == (2,)
    assert info["commanded_kpa"].tolist() == [90.0, 45.0]
    cols = ranges.columns(2)
    assert "pressure_gain_2" in cols and "pressure_gain_3" not in cols
    assert tuple(DomainSample(**info["domain"]).columns()) == cols
    with pytest.raises(ValueError, match=r"env\.randomize\.pressure_gain: need 3 values"):
        expect.regulators(n_regulators=3)
    env.close()


def test_batched_backend_of_two_regulator_envs_is_the_serial_one(six, six_config):
    """A worker's batched backend settles the given designs of a 2-regulator space together and
    steps their reduced robots in one batch, the rig randomized: every transition equals the
    serial backend's to the bit (regression: its settling validated designs in the paper's
    space)."""
    from softcrawl.envs import BuildRobot, CrawlerEnv
    from softcrawl.envs.backends.batched import BatchedBackend
    from softcrawl.envs.backends.serial import SerialBackend
    from softcrawl.robot import DomainRanges

    def make():
        return CrawlerEnv(BuildRobot(six_config, six), steps_per_action=5, n_actions=2, randomize=DomainRanges(**RIG),
                          space=six)

    def run(backend):
        try:
            out = [backend.reset([0, 1], [DESIGN, (1, 0, 2, 0, 1, 0)], [1, 2])]
            for a in ([[1.0, -0.5], [0.0, 1.0]], [[-1.0, 1.0], [1.0, 1.0]]):
                out.append(backend.step(np.array(a, np.float32)))
            return out
        finally:
            backend.close()

    serial, batched = run(SerialBackend([make] * 2)), run(BatchedBackend([make] * 2))
    for ref, got in zip(serial[1:], batched[1:]):
        for (o1, r1, *_, i1), (o2, r2, *_, i2) in zip(ref, got):
            np.testing.assert_array_equal(o1, o2)
            assert r1 == r2 and i1["applied_kpa"].shape == (2,)
            np.testing.assert_array_equal(i1["disk_position_mm"], i2["disk_position_mm"])
    assert [i["domain"] for _, i in serial[0]] == [i["domain"] for _, i in batched[0]]


@pytest.mark.slow
def test_jax_backend_runs_two_regulator_envs_as_the_cpu_env(x64, six, six_config):
    """The JAX vector env of 2-regulator envs with the rig randomized: each env draws 2 values
    per regulator quantity, and the per-action rewards agree with the CPU env's (the same
    design, actions and draws) within 0.03 cm, the bound of the paper-space test
    (``tests/test_jax_backend.py``); measured 0.007 cm on rewards of 0.12-0.54 cm. Slow: the
    backend's settling and rollout compile (about a minute of one core)."""
    from softcrawl.envs import BuildRobot, CrawlerEnv
    from softcrawl.envs.backends import make_backend
    from softcrawl.robot import DomainRanges

    def make():
        return CrawlerEnv(BuildRobot(six_config, six), steps_per_action=50, n_actions=2, designs=[DESIGN],
                          randomize=DomainRanges(**RIG), space=six)

    actions = np.array([[-1.0, 1.0], [1.0, -1.0]], np.float32)  # the rear regulator inflates, then the front
    backend = make_backend("jax", [make] * 2)
    try:
        resets = backend.reset([0, 1], [None, None], [5, 6])
        got = [backend.step(np.tile(a, (2, 1))) for a in actions]
    finally:
        backend.close()
    for i, seed in enumerate((5, 6)):
        env = make()
        _, info = env.reset(seed=seed)
        assert info["domain"] == resets[i][1]["domain"] and len(info["domain"]["tau_vent"]) == 2
        ref = [env.step(a) for a in actions]
        env.close()
        r_cpu, r_jax = np.array([t[1] for t in ref]), np.array([g[i][1] for g in got])
        assert np.abs(r_cpu).max() > 0.1  # it crawled
        np.testing.assert_allclose(r_jax, r_cpu, rtol=0, atol=0.03)
        assert got[0][i][4]["applied_kpa"].shape == (2,)


# -- the ground-truth gait search of a 2-regulator design ------------------------------------------
def test_groundtruth_search_of_a_two_regulator_design(six, six_robot):
    """The gait search of a 2-regulator design on the CPU reduced engine, a tiny budget (cycle 2,
    3 episodes of 0.3 s, one finalist): every gait it asks for drives the space's 2 regulators,
    it asks for 3 search episodes and the smooth final, its best gait re-run gives its reward
    exactly (a fresh solver from the same rested state), and the lockstep driver gives the same
    result; the paper's space refuses the 6-slot design."""
    from softcrawl.codesign.groundtruth import GroundTruthConfig, design_search, search_many
    from softcrawl.codesign.groundtruth.search import drive
    from softcrawl.design.spacefile import InvalidDesignError
    from softcrawl.robot import settle

    settled = settle(six_robot)
    asked = []

    def evaluate(gait, duration):
        assert gait.n_regulators == 2 and gait.pressure_at(0.25).shape == (2,)
        asked.append(duration)
        res = run_episode(six_robot, gait, duration, record_every=None, progress=False, settled=settled)
        return float(res.reward_cm), bool(res.diverged)

    cfg = GroundTruthConfig(cycles=(2,), evals_per_cycle=3, finalists=1, duration=0.3, screen_duration=None,
                            baseline_phases=())
    result = drive(design_search(DESIGN, cfg, six), lambda request: evaluate(*request))
    assert asked == [0.3] * 4 and result.design == DESIGN and result.evaluations == 4
    best = PeriodicGait.from_dict(result.gait)
    assert best.n_regulators == 2 and np.isfinite(result.reward_cm)
    assert evaluate(best, 0.3)[0] == result.reward_cm
    (lockstep,) = search_many([DESIGN], cfg, lambda requests: [evaluate(g, t) for _, g, t in requests], space=six)
    a, b = result.to_dict(), lockstep.to_dict()
    a.pop("wall_seconds"), b.pop("wall_seconds")
    assert json.dumps(a) == json.dumps(b)
    with pytest.raises(InvalidDesignError):
        design_search(DESIGN, cfg)


# -- the expert baseline's phase sweep on another space ---------------------------------------------
def test_phase_sweep_of_a_two_regulator_design(six, six_config, six_robot, tmp_path):
    """The phase sweep of a 2-regulator design runs the expert wave on the space's regulators
    (:meth:`PeriodicGait.expert_sine`): each phase's reward is that of :func:`run_episode` of that
    gait from the design's rested state, to the bit; its settings name the space; the paper's
    settings are those of the 3-regulator :class:`SineGait` and name no space."""
    import dataclasses

    from softcrawl.robot import settle
    from softcrawl.robot.sweep import baseline_gait, run_sweep, sweep_settings

    result = run_sweep(tmp_path / "sweep", (0.0, 90.0), DESIGN, six_config, duration=0.2, workers=1,
                       progress=False, space=six)
    assert result.settings["space"] == {"name": "six2", "sha256": six.sha256}
    assert json.loads((tmp_path / "sweep" / "sweep.json").read_text())["settings"]["space"]["name"] == "six2"
    settled = settle(six_robot)
    for r in result.phases:
        gait = baseline_gait(r.phase_deg, 2)
        assert isinstance(gait, PeriodicGait) and gait.n_regulators == 2
        ref = run_episode(six_robot, gait, 0.2, record_every=None, progress=False, settled=settled)
        assert r.reward_cm == ref.reward_cm and not r.diverged
    paper = sweep_settings((1, 0, 0, 2, 2, 0, 0, 0), RobotConfig(), 20.0)
    assert "space" not in paper and paper["gait"] == {"type": "SineGait", **{
        k: v for k, v in dataclasses.asdict(SineGait()).items() if k != "phase_deg"}}
    assert isinstance(baseline_gait(110.0), SineGait)


def test_animation_of_a_four_regulator_robot(tmp_path):
    """A space with more regulators than the paper's colour table (4, the paper's parts, full
    order, coarse): an episode records 4 pressures and its crawl GIF colours and labels regulator
    4's leg (regression: the renderer looked regulators up in a 3-entry table)."""
    from PIL import Image

    from softcrawl.robot.animation import write_animation

    text = shipped_space_path("paper").read_text()
    assert text.count("regulators = 3") == 1
    path = tmp_path / "four.toml"
    path.write_text(text.replace("regulators = 3", "regulators = 4"))
    four = load_space(path)
    robot = build_robot((1, 2, 3, 4, 0, 0, 0, 0), RobotConfig.for_space(four, leg_mesh_size=12.0, disk_mesh_size=25.0),
                        space=four)
    res = run_episode(robot, ActionSequence([[90.0, 60.0, 30.0, 90.0]]), duration=0.02, settling=NO_SETTLING,
                      record_every=1, progress=False)
    assert res.applied.shape == (3, 4) and len(res.frames) == 3
    assert write_animation(tmp_path / "crawl.gif", robot, res, max_frames=2, size=(96, 64)) == 2
    with Image.open(tmp_path / "crawl.gif") as gif:
        assert gif.size == (96, 64) and gif.n_frames == 2
