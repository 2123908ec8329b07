"""Domain randomization: ranges and draws, each randomized quantity reaching
the simulation, identity when off, the batched backend, the training log and
``softcrawl evaluate --randomize N``.

The simulation is the ``smoke`` preset's (reduced 6 mm legs, 25 mm floating-frame disk, 0.01 s,
2 steps per action), with 4-action episodes where a whole episode is not needed."""

from __future__ import annotations

import csv
import dataclasses
import json
import math

import numpy as np
import pytest

from softcrawl.codesign.config import TrainConfig, override, preset
from softcrawl.codesign.factory import env_fn, robot_factory
from softcrawl.envs import CrawlerEnv
from softcrawl.envs.backends import SerialBackend
from softcrawl.envs.backends.batched import BatchedBackend
from softcrawl.envs.vec import DesignVecEnv
from softcrawl.robot.actuation import PressureCalibration, RegulatorBank
from softcrawl.robot.domain import DomainRanges, DomainSample, LaggedRegulatorBank, RegulatorWarp
from softcrawl.robot.episode import Episode

DESIGN = (1, 0, 0, 2, 2, 0, 0, 0)
ACTIONS = np.array([[1, -1, 0.5], [-0.5, 1, -1], [1, 1, 1], [-1, 0.2, 1]], np.float32)
ALL = dict(friction=(0.6, 1.6), youngs_scale=(0.8, 1.2), mass_scale=(0.9, 1.1), pressure_gain=(0.9, 1.2),
           pressure_offset=(-6.0, -2.0), tau_inflate=(0.0, 0.6), tau_vent=(0.2, 0.7), control_period=(1.0, 1.6))


def smoke(*sets, n_actions=4) -> TrainConfig:
    return override(preset("smoke"), [f"env.n_actions={n_actions}", *sets])


_PLAIN = object()


def make_env(ranges=_PLAIN, **kw) -> CrawlerEnv:
    """A smoke-preset env with ``ranges`` (none given: the argument is not passed at all)."""
    base = {k: v for k, v in env_fn(smoke()).keywords.items() if k != "randomize"}
    return CrawlerEnv(**{**base, **kw, **({} if ranges is _PLAIN else {"randomize": ranges})})


def rollout(env, actions=ACTIONS, seed=0, design=DESIGN):
    obs, info = env.reset(seed=seed, options={"design": design})
    out = [(obs, info)]
    for a in actions:
        out.append(env.step(a))
    return out


def assert_same(a, b, path="transition"):
    """Bit-identical nested transitions (arrays, floats, dicts, tuples)."""
    if isinstance(a, dict):
        assert a.keys() == b.keys(), f"{path}: keys {sorted(a)} != {sorted(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif isinstance(a, (list, tuple)) and not isinstance(a, str) and len(a) and not np.isscalar(a[0]) \
            or isinstance(a, (list, tuple)) and len(a) == 0:
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    else:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b), err_msg=path)


# -- ranges ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("setting, match", [
    ("env.randomize.friction=[1.6, 0.8]", r"env\.randomize\.friction: low 1\.6 > high 0\.8"),
    ("env.randomize.youngs_scale=[-1, 1]", r"env\.randomize\.youngs_scale: low -1\.0 must be > 0"),
    ("env.randomize.mass_scale=[0, 1]", r"env\.randomize\.mass_scale: low 0\.0 must be > 0"),
    ("env.randomize.tau_vent=[NaN, 1]", r"env\.randomize\.tau_vent: low nan is not finite"),
    ("env.randomize.pressure_offset=[-1, Infinity]", r"env\.randomize\.pressure_offset: high inf is not finite"),
    ("env.randomize.pressure_gain=[-0.1, 1]", r"env\.randomize\.pressure_gain: low -0\.1 must be >= 0"),
    ("env.randomize.control_period=[1]", r"env\.randomize\.control_period must be a list of 2 float or null, got \[1\]"),
    ("env.randomize.friction=[1, \"a\"]", r"env\.randomize\.friction must be a list of 2 float or null"),
    ("env.randomize.control_period=[0.3, 1]", r"env\.randomize\.control_period: low 0\.3 gives actions of less"),
    ("env.randomize.gravity=[1, 2]", r"unknown setting 'env\.randomize\.gravity'"),
    ("env.randomize=wind", r"unknown env\.randomize preset 'wind'"),
    ("env.settling=rig", r"unknown setting 'env\.settling'"),
])
def test_bad_ranges_are_refused_naming_the_key(setting, match):
    with pytest.raises(ValueError, match=match):
        smoke(setting)  # smoke: 2 steps per action, so a period factor of 0.3 gives 0.6 steps


def test_ranges_direct_and_presets():
    with pytest.raises(ValueError, match=r"env\.randomize\.friction: low -0\.5 must be >= 0"):
        DomainRanges(friction=(-0.5, 1.0))
    with pytest.raises(ValueError, match=r"env\.randomize\.tau_inflate must be two numbers"):
        DomainRanges(tau_inflate=(True, 1.0))
    with pytest.raises(ValueError, match=r"env\.randomize\.mass_scale: value 0\.0 must be > 0"):
        DomainSample(mass_scale=0.0)
    with pytest.raises(ValueError, match=r"env\.randomize\.pressure_gain: need 3 values"):
        DomainSample(pressure_gain=(1.0, 1.0)).check_regulators(3)  # 2 regulators' values on a 3-regulator space
    with pytest.raises(ValueError, match=r"env\.randomize\.pressure_gain/tau_vent: need one value per regulator"):
        DomainSample(pressure_gain=(1.0, 1.0), tau_vent=(0.1, 0.1, 0.1))
    assert not DomainRanges().enabled and DomainRanges().draw(np.random.default_rng(0)) is None
    rig = smoke("env.randomize=rig").env.randomize
    assert rig == DomainRanges.rig() and rig.enabled and not rig.physical
    assert rig.control_period == (1.062, 1.070) and rig.tau_vent == (0.264, 0.691)
    from softcrawl.hardware.regulator_model import FITTED  # the copy in softcrawl.robot.domain is the fit's span

    for key, name in (("pressure_gain", "gain"), ("pressure_offset", "offset"), ("tau_inflate", "tau_inflate"),
                      ("tau_vent", "tau_vent")):
        vals = [getattr(p, name) for p in FITTED]
        assert getattr(rig, key) == (min(vals), max(vals)), key
    # presets combine with single ranges, in order; "off" clears them
    cfg = smoke("env.randomize=rig", "env.randomize.youngs_scale=[0.7,1.3]")
    assert cfg.env.randomize == dataclasses.replace(DomainRanges.rig(), youngs_scale=(0.7, 1.3))
    assert smoke("env.randomize.friction=[1,2]", "env.randomize=off").env.randomize == DomainRanges()
    # the config round-trips through JSON (config.json of a run)
    assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg


def test_draws_are_reproducible_and_in_range():
    ranges = DomainRanges(**ALL)
    draws = [ranges.draw(np.random.default_rng(s)) for s in (0, 0, 1)]
    assert draws[0] == draws[1] and draws[0] != draws[2]
    many = [ranges.draw(np.random.default_rng(s)) for s in range(200)]
    for key, (lo, hi) in ALL.items():
        vals = np.array([getattr(d, key) for d in many], float)
        assert vals.shape in ((200,), (200, 3))
        assert np.all((vals >= lo) & (vals <= hi)), key
        assert vals.max() - vals.min() > 0.8 * (hi - lo), key  # the range is used, not a corner of it
    assert DomainRanges(friction=(0.7, 0.7)).draw(np.random.default_rng(5)).friction == 0.7
    # in the env: the draw follows the reset seed, and designs drawn by the env are the same
    # with and without randomization (the domain is drawn after the design)
    env, plain = make_env(ranges), make_env()
    infos = [env.reset(seed=s)[1] for s in (3, 4, 3)]
    assert infos[0]["domain"] == infos[2]["domain"] != infos[1]["domain"]
    assert [i["design"] for i in infos] == [plain.reset(seed=s)[1]["design"] for s in (3, 4, 3)]
    assert set(infos[0]["domain"]) == set(ALL) and len(infos[0]["domain"]["tau_vent"]) == 3


# -- identity when off ------------------------------------------------------------------------------
def test_off_is_bit_identical():
    """An env without the randomize argument, one with all-null ranges and the config's factory
    give the same transitions to the bit, with no ``domain`` key; and the env's positions are
    those of a bare :class:`Episode` stepped by hand (independent of the env's code)."""
    runs = [rollout(make_env()), rollout(make_env(DomainRanges())), rollout(env_fn(smoke())())]
    for other in runs[1:]:
        assert_same(runs[0], other)
    assert all("domain" not in info for *_, info in runs[0][1:])
    env = make_env()
    env.reset(seed=0, options={"design": DESIGN})
    robot, settled = env._robots[DESIGN]
    ep = Episode(robot, PressureCalibration(), env.settling, settled=settled)
    ep.reset()
    x0 = robot.reward_position(ep.state.x)
    for (obs, r, term, trunc, info), a in zip(runs[0][1:], ACTIONS):
        for _ in range(2):
            ep.step((np.clip(a, -1, 1) + 1.0) * 45.0)
        np.testing.assert_array_equal(info["disk_position_mm"], robot.reward_position(ep.state.x))
    assert runs[0][-1][4]["displacement_cm"] == (robot.reward_position(ep.state.x)[0] - x0[0]) / 10.0


# -- each quantity reaches the simulation -------------------------------------------------------
def _episode_return(ranges=_PLAIN, actions=ACTIONS, seed=0):
    out = rollout(make_env(ranges), actions, seed)
    return sum(r for _, r, *_ in out[1:]), out


def test_friction_reaches_the_floor():
    env = make_env(DomainRanges(friction=(0.0, 0.0)))
    env.reset(seed=0, options={"design": DESIGN})
    assert env.episode.robot.model.floor.friction == 0.0 and env.episode.robot.config.friction == 0.0
    nominal = env._robots[DESIGN][0]
    assert nominal.model.floor.friction == 1.2 and env.episode.robot is not nominal  # cache untouched
    # same robot as the cached one when the draw is the nominal 1.2, settled anew: same episode
    assert _episode_return(DomainRanges(friction=(1.2, 1.2)))[0] == _episode_return(_PLAIN)[0]
    # 0.4 s of alternating legs: on a frictionless floor the robot slides (0.17 mm); on the
    # nominal and a sticky floor its nodes move at most 0.03 mm in the plane
    acts = np.tile(np.array([[1, -1, 0], [-1, 1, 0]], np.float32), (10, 1))
    slide = {}
    for mu in (0.0, 1.2, 5.0):
        env = make_env(DomainRanges(friction=(mu, mu)), n_actions=20)
        env.reset(seed=0, options={"design": DESIGN})
        x0 = env.episode.state.x[:, :2].copy()
        for a in acts:
            env.step(a)
        slide[mu] = np.abs(env.episode.state.x[:, :2] - x0).max()
    assert slide[0.0] > 5 * max(slide[1.2], slide[5.0])


def test_pressure_gain_zero_means_no_actuation():
    """``g = 0, o = 0``: the legs see 0 real kPa, the warp's sim pressure is max(b, 0) = 0 (b < 0):
    the same trajectory as commanding 0 kPa throughout, to the bit."""
    _, off = _episode_return(DomainRanges(pressure_gain=(0.0, 0.0), pressure_offset=(0.0, 0.0)))
    _, zero = _episode_return(_PLAIN, actions=-np.ones_like(ACTIONS))
    for a, b in zip(off[1:], zero[1:]):
        np.testing.assert_array_equal(a[4]["disk_position_mm"], b[4]["disk_position_mm"])
    warp = RegulatorWarp(PressureCalibration(), (1.1, 0.9, 1.0), (-3.0, 2.0, 0.0))
    cal = PressureCalibration()
    np.testing.assert_allclose(warp.to_sim(np.array([50.0, 10.0, 0.0])),
                               [cal.to_sim(1.1 * 50 - 3), cal.to_sim(0.9 * 10 + 2), 0.0], rtol=1e-15)
    # a gain changes the applied sim pressure, hence the crawl
    assert _episode_return(DomainRanges(pressure_gain=(1.25, 1.25)))[0] != _episode_return(_PLAIN)[0]


def test_youngs_modulus_and_mass_scale_the_model():
    base = robot_factory(smoke())(DESIGN)
    s, m = 1.3, 0.8
    robot = DomainSample(youngs_scale=s, mass_scale=m).apply(base)
    for b0, b1 in zip(base.model.bodies, robot.model.bodies):
        assert b1.material.youngs_modulus == pytest.approx(s * b0.material.youngs_modulus, rel=1e-15)
        assert b1.mass == pytest.approx(m * b0.mass, rel=1e-15)
        assert b1.mesh is b0.mesh
        if b0.membrane is not None:
            assert b1.membrane.material.youngs_modulus == pytest.approx(s * b0.membrane.material.youngs_modulus)
    leg = base.legs[0].body
    # element stiffness is linear in E: the RID factors (square roots of the stiffness) scale by sqrt(s)
    # (the factors C_e are unique up to an orthogonal transform: compare C_e^T C_e, the element
    # stiffness in the element's rest frame restricted to the edge vectors)
    for f0, f1 in zip(base.reduced[leg].element_factors, robot.reduced[leg].element_factors):
        k0, k1 = (np.einsum("eiq,eir->eqr", f.factors, f.factors) for f in (f0, f1))
        np.testing.assert_allclose(k1, s * k0, rtol=1e-10, atol=1e-10 * np.abs(k0).max())
    # the reduced mass Phi^T M Phi is linear in M; the basis is the reduction's
    M0 = base.reduced[leg].reduced_mass
    np.testing.assert_allclose(robot.reduced[leg].reduced_mass, m * M0, rtol=0, atol=1e-12 * np.abs(M0).max())
    assert robot.reduced[leg].part is base.reduced[leg].part
    disk = robot.reduced[robot.disk_body]
    np.testing.assert_allclose(disk.rest_stiffness.toarray(),
                               s * base.reduced[base.disk_body].rest_stiffness.toarray(), rtol=1e-12, atol=1e-9)
    assert robot.config.leg_mass == pytest.approx(m * base.config.leg_mass)
    # and it reaches the episode: a stiffer robot crawls differently
    r_nominal = _episode_return(_PLAIN)[0]
    assert _episode_return(DomainRanges(youngs_scale=(1.3, 1.3)))[0] != r_nominal
    assert _episode_return(DomainRanges(mass_scale=(0.8, 0.8)))[0] != r_nominal


def test_regulator_lags_closed_form():
    dt, tau_i, tau_v = 0.01, (2.0, 0.5, 0.0), (1.0, 3.0, 0.0)
    bank = LaggedRegulatorBank(3, 150.0, tau_i, tau_v)
    t = np.arange(1, 101) * dt
    got = np.array([bank.step([60.0, 60.0, 60.0], dt) for _ in t])
    # regulator 1: p = c (1 - exp(-t / tau)) while below the slew limit (c / tau = 30 < 150 kPa/s)
    np.testing.assert_allclose(got[:, 0], 60.0 * -np.expm1(-t / 2.0), rtol=1e-12)
    # regulator 2: c / tau = 120 kPa/s < 150: pure lag too; regulator 3 (no lag): the slew limit
    np.testing.assert_allclose(got[:, 1], 60.0 * -np.expm1(-t / 0.5), rtol=1e-12)
    np.testing.assert_allclose(got[:, 2], np.minimum(150.0 * t, 60.0), rtol=1e-12)
    p0 = bank.state.copy()
    vent = np.array([bank.step([0.0, 0.0, 0.0], dt) for _ in t])
    np.testing.assert_allclose(vent[:, 0], p0[0] * np.exp(-t / 1.0), rtol=1e-12)
    np.testing.assert_allclose(vent[:, 1], p0[1] * np.exp(-t / 3.0), rtol=1e-12)
    # zero lags: the plain slew-limited bank, to the bit
    rng = np.random.default_rng(0)
    a, b = RegulatorBank(3, 150.0), LaggedRegulatorBank(3, 150.0)
    for c in rng.uniform(0, 90, (50, 3)):
        np.testing.assert_array_equal(a.step(c, dt), b.step(c, dt))
    with pytest.raises(ValueError, match="tau_vent"):
        LaggedRegulatorBank(3, 150.0, (0, 0, 0), (0, -1, 0))
    # in the env: the applied pressures lag
    # (a lag of 5 s keeps the first action's 90 kPa step below the slew limit: 18 < 150 kPa/s)
    _, lagged = _episode_return(DomainRanges(tau_inflate=(5.0, 5.0), tau_vent=(5.0, 5.0)))
    _, nominal = _episode_return(_PLAIN)
    assert np.all(lagged[1][4]["applied_kpa"] < nominal[1][4]["applied_kpa"] + 1e-12)
    assert lagged[1][4]["applied_kpa"][0] < nominal[1][4]["applied_kpa"][0]


def test_control_period_dilation_changes_the_steps():
    sample = DomainSample(control_period=1.067)
    for n in (2, 50, 100):
        steps = [sample.action_steps(n, k) for k in range(20)]
        assert all(s >= 1 for s in steps)
        assert sum(steps) == math.floor(1.067 * n * 20 + 0.5)  # exact over the episode to one step
    assert [DomainSample().action_steps(50, k) for k in range(3)] == [50, 50, 50]
    env = make_env(DomainRanges(control_period=(1.5, 1.5)))
    out = rollout(env)
    counts = []
    for obs, r, term, trunc, info in out[1:]:
        counts.append(info["t"])
    assert counts == pytest.approx([0.03, 0.06, 0.09, 0.12])  # 3 steps of 0.01 s per action, not 2
    assert env.nominal_steps_per_action == 2
    assert rollout(make_env())[-1][4]["t"] == pytest.approx(0.08)


def test_batched_backend_matches_serial_with_randomization():
    """The batched worker steps randomized robots (own moduli, masses, friction, dilated actions)
    to the same transitions as stepping them one by one."""
    ranges = DomainRanges(**ALL)
    fns = [lambda n=n: make_env(ranges, n_actions=n) for n in (2, 3)]

    def run(backend):
        venv = DesignVecEnv(backend)
        venv.seed(7)
        out = [venv.reset()]
        rng = np.random.default_rng(0)
        for _ in range(5):
            obs, rew, dones, infos = venv.step(rng.uniform(-1, 1, (2, 3)).astype(np.float32))
            out.append((obs, rew, dones, [{k: v for k, v in i.items() if k != "terminal_observation"}
                                          for i in infos]))
        return out

    assert_same(run(SerialBackend(fns)), run(BatchedBackend(fns)))


# -- the run log and softcrawl evaluate --randomize ------------------------------------------
def test_training_log_and_evaluate_randomize(tmp_path, capsys):
    from softcrawl.cli.evaluate import register
    from softcrawl.codesign.randomization import DomainLog, read_domain_log
    from softcrawl.codesign.run import Run
    from softcrawl.codesign.training import train

    cfg = override(preset("smoke"), ["total_steps=40", "checkpoint_every=40", "snapshot_every=40",
                                     "env.randomize.pressure_gain=[0.5,1.5]", "env.randomize.friction=[0.8,1.6]"])
    run = tmp_path / "run"
    train(run, cfg, progress=False)
    with open(run / "episodes.csv", newline="") as f:
        episodes = [r for r in csv.reader(f) if r]
    assert [len(r) for r in episodes] == [4, 4]  # episodes.csv keeps its format
    log = read_domain_log(Run(run).domain_csv)
    assert list(log) == ["t", "design", "return_cm", "diverged", "friction",
                         *(f"pressure_gain_{k}" for k in (1, 2, 3))]
    assert list(log["t"]) == [40, 40] and [float(r[2]) for r in episodes] == pytest.approx(list(log["return_cm"]))
    assert np.all((log["friction"] >= 0.8) & (log["friction"] <= 1.6))
    # a resumed run drops the rows after its checkpoint
    DomainLog(Run(run).domain_csv, cfg.env.randomize, after=39).close()
    assert len(read_domain_log(Run(run).domain_csv)["t"]) == 0
    DomainLog(Run(tmp_path / "plain").domain_csv, DomainRanges(), 0).close()
    assert not (tmp_path / "plain").exists()  # no randomization: nothing written

    import argparse

    p = argparse.ArgumentParser(prog="softcrawl")
    register(p.add_subparsers(dest="command"))
    out = tmp_path / "robust"
    args = p.parse_args(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--randomize", "4", "--out", str(out),
                         "--set", "env.randomize.youngs_scale=[0.8,1.2]", "--no-progress"])
    assert args.func(args) == 0
    assert "4 randomized episodes" in capsys.readouterr().out
    res = json.loads((out / "randomization.json").read_text())
    r = np.array(res["returns_cm"])
    assert res["n"] == 4 and res["mean_cm"] == pytest.approx(r.mean()) and res["std_cm"] == pytest.approx(r.std())
    assert res["min_cm"] == r.min() and res["max_cm"] == r.max() and len(set(r)) == 4
    assert res["ranges"]["youngs_scale"] == [0.8, 1.2] and res["ranges"]["friction"] == [0.8, 1.6]
    assert len(res["domains"]) == 4 and "nominal_return_cm" in res
    with open(out / "randomization.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert [float(row["return_cm"]) for row in rows] == pytest.approx(list(r), rel=1e-5)
    assert (out / "randomization.png").stat().st_size > 1000
    # the same seed gives the same distribution
    args = p.parse_args(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--randomize", "4", "--out", str(out),
                         "--set", "env.randomize.youngs_scale=[0.8,1.2]", "--overwrite"])
    args.func(args)
    assert json.loads((out / "randomization.json").read_text())["returns_cm"] == res["returns_cm"]
    for bad, match in ((["--set", "sac.batch_size=8"], "only takes env.randomize"),
                       (["--episodes", "2"], "not both"),
                       (["--set", "env.randomize=off"], "no randomization ranges")):
        args = p.parse_args(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--randomize", "2",
                             "--out", str(tmp_path / "bad"), *bad])
        with pytest.raises(ValueError, match=match):
            args.func(args)
    assert not (tmp_path / "bad").exists()
