"""The JAX vector-env backend (``backend="jax"``, :mod:`softcrawl.envs.backends.jaxvec`): its
episodes against the CPU backends', mixed designs and resets in one batch, divergence, the
per-design settling cache, the per-env rig against the CPU regulators, training end to end and
the config's refusals."""

import dataclasses
import functools

import numpy as np
import pytest

jax = pytest.importorskip("jax")

BEST = (1, 0, 0, 2, 2, 0, 0, 0)  # the paper's best design: 3 legs on two regulators
FOUR = (1, 0, 2, 0, 1, 0, 3, 0)  # 4 legs on three regulators
#: Two 0.5-s actions: regulators 1 and 2 at 90 and 68 kPa, then vented.
ACTIONS = np.array([[1.0, 0.5, -1.0], [-1.0, -1.0, -1.0]], np.float32)


@pytest.fixture(scope="module", autouse=True)
def _x64(x64):
    """float64 for the module (the backend sets it; the caller's setting is restored after)."""


def config(*sets):
    """The ``smoke`` simulation (reduced 6 mm legs, 25 mm floating disk, dt 0.01 s) with 0.5-s
    actions, 2 per episode, the 3- and 4-legged designs, ``backend="jax"``."""
    from softcrawl.codesign.config import override, preset

    return override(preset("smoke"), ['backend="jax"', "env.steps_per_action=50", "env.n_actions=2",
                                      "env.legs=[3, 4]", *sets])


@pytest.fixture(scope="module")
def backend():
    """A JAX backend of 2 envs (4 leg slots), compiled once for the module."""
    from softcrawl.codesign.factory import env_fn
    from softcrawl.envs.backends import make_backend

    b = make_backend("jax", [env_fn(config())] * 2)
    yield b
    b.close()


def test_the_backend_runs_the_configured_contact_solve():
    """Issue 50: every JAX path honours the run's contact solve: ``jax_solver`` and
    ``jax_iterations``, and for Gauss-Seidel without a count the robots'
    ``contact_max_iterations`` (the backend used 100 sweeps whatever the config said)."""
    from softcrawl.codesign.factory import env_fn, jax_options
    from softcrawl.envs.backends import make_backend
    from softcrawl.jaxsim.contact import DEFAULT_ITERATIONS

    for sets, want in ((['jax_solver="pgs"', "env.robot.contact_max_iterations=7"], ("pgs", 7)),
                       (['jax_solver="pgs"', "jax_iterations=30"], ("pgs", 30)),
                       (["jax_iterations=20"], ("apgd", 20)), ([], ("apgd", DEFAULT_ITERATIONS["apgd"]))):
        cfg = config(*sets)
        b = make_backend("jax", [env_fn(cfg)], jax=jax_options(cfg))
        try:
            assert (b.settings.solver, b.settings.iterations) == want, sets
        finally:
            b.close()


def episode(b, designs, seeds=(0, 1), actions=ACTIONS, reset_at=None):
    """Transitions ``[(obs, reward, terminated, truncated, info)] * N`` per action of backend
    ``b`` from a reset of all envs; ``reset_at=(k, i, design)`` resets env ``i`` alone before
    action ``k``."""
    b.reset(range(b.num_envs), designs, seeds)
    out = []
    for k, a in enumerate(actions):
        if reset_at is not None and reset_at[0] == k:
            b.reset([reset_at[1]], [reset_at[2]], [7])
        out.append(b.step(np.tile(a, (b.num_envs, 1))))
    return out


def test_episode_matches_the_cpu_backend(backend):
    """A fixed design and fixed actions: the per-action rewards agree with the ``serial``
    backend's (the CPU reduced engine, the preset's float32 RID products and 100 sweeps) within
    0.03 cm, and the observations, flags and info keys are the same. The engine's own
    validation (tests/test_jaxsim_robot.py) bounds the reward point's distance to the CPU
    engine's by 0.3 mm after landing and 1 s of actuation (mean node distance 0.09 mm); a
    reward is the difference of two such positions, at most 0.06 cm apart. Measured here:
    0.008 cm on rewards of 0.13-0.14 cm (the engines' contact solves differ, and so do their
    settling rules and so the starts)."""
    from softcrawl.codesign.factory import env_fn
    from softcrawl.envs.backends import make_backend

    got = episode(backend, [BEST] * 2)
    cpu = make_backend("serial", [env_fn(config())])
    try:
        cpu.reset([0], [BEST], [0])
        ref = [cpu.step(a[None])[0] for a in ACTIONS]
    finally:
        cpu.close()
    r_jax, r_cpu = np.array([t[0][1] for t in got]), np.array([t[1] for t in ref])
    assert np.abs(r_cpu).max() > 0.1  # it crawled
    np.testing.assert_allclose(r_jax, r_cpu, rtol=0, atol=0.03)
    for (o, _, term, trunc, info), (o_ref, _, term_ref, trunc_ref, info_ref) in zip([t[0] for t in got], ref):
        np.testing.assert_array_equal(o, o_ref)
        assert (term, trunc) == (term_ref, trunc_ref)
        assert set(info) == set(info_ref) and info["design"] == BEST and not info["diverged"]
        np.testing.assert_allclose(info["applied_kpa"], info_ref["applied_kpa"], rtol=0, atol=1e-9)
        assert info["t"] == pytest.approx(info_ref["t"])
    assert got[-1][0][3] and not got[-2][0][3]  # truncated after n_actions
    np.testing.assert_array_equal(r_jax, [t[1][1] for t in got])  # same design, same transitions


def test_mixed_designs_and_a_reset_mid_run_leave_the_other_envs_alone(backend):
    """3 and 4 legs in one batch; env 1 reset alone (to the 3-legged design) before the second
    action: env 0 steps exactly as in the run without that reset, and env 1 starts its new
    episode (its new design's one-hot, no action in its history before the reset) and its
    first action gives the reward env 0's first action gave (same design, same action)."""
    from softcrawl.design.space import one_hot

    plain = episode(backend, [BEST, FOUR])
    assert plain[0][0][4]["design"] == BEST and plain[0][1][4]["design"] == FOUR
    assert plain[0][0][1] != plain[0][1][1]
    mixed = episode(backend, [BEST, FOUR], actions=np.concatenate([ACTIONS[:1], ACTIONS[:1]]), reset_at=(1, 1, BEST))
    np.testing.assert_array_equal(mixed[0][0][0], plain[0][0][0])
    assert mixed[0][0][1:4] == plain[0][0][1:4]
    obs, reward, term, trunc, info = mixed[1][1]
    assert info["design"] == BEST and info["t"] == pytest.approx(0.5) and not (term or trunc)
    np.testing.assert_array_equal(obs[:32], one_hot(BEST))
    np.testing.assert_array_equal(obs[35:], 0.0)  # only the action taken since the reset
    assert reward == plain[0][0][1]


def test_a_diverged_env_terminates_alone(backend):
    """Env 1 with an inverted element (``state.bad`` forced), then after a reset with non-finite
    velocities, terminates on its next action with ``info["diverged"]`` and a reason, reward 0
    (its last valid state), and a reset revives it; env 0 steps as without it."""
    plain = episode(backend, [BEST, FOUR])
    backend.reset(range(2), [BEST, FOUR], (0, 1))
    for k, spoil in enumerate((lambda s: dataclasses.replace(s, bad=s.bad.at[1].set(1)),
                               lambda s: dataclasses.replace(s, v=s.v.at[1, 0, 0].set(np.nan)))):
        backend._state = spoil(backend._state)
        out = backend.step(np.tile(ACTIONS[k], (2, 1)))
        assert out[0][1] == plain[k][0][1] and not out[0][2]
        _, reward, term, trunc, info = out[1]
        assert term and not trunc and info["diverged"] and "JAX engine" in info["reason"] and reward == 0.0
        assert np.all(np.isfinite(info["disk_position_mm"]))
        (_, info), = backend.reset([1], [FOUR], [1])
        assert not info["diverged"]
    out = backend.step(np.tile(ACTIONS[0], (2, 1)))
    assert out[1][1] == plain[0][1][1] and not out[1][2]


def test_settled_states_are_computed_once_per_design(backend, monkeypatch):
    """A design is settled once (the designs new at a reset together, in one call); later
    resets to it start from the cached state."""
    calls = []
    settle = backend._settle_designs
    monkeypatch.setattr(backend, "_settle_designs", lambda designs: calls.append(list(designs)) or settle(designs))
    designs = config().env.designs()
    a, b = designs[7], designs[-7]  # 3 and 4 legs, not used by the other tests
    backend.reset(range(2), [a, b], (0, 1))
    backend.reset(range(2), [b, a], (0, 1))
    backend.reset([0], [a], [0])
    assert calls == [[a, b]]


def test_rig_matches_the_cpu_regulators_and_warp():
    """:func:`regulator_step` and :func:`rig_pressures` against :class:`LaggedRegulatorBank` and
    :class:`RegulatorWarp` over 200 steps of random commands, lags (0 included: the plain slew
    step), gains and offsets: equal to 1e-12 kPa (the same formulas, float64)."""
    import jax.numpy as jnp

    from softcrawl.jaxsim.model import Settings
    from softcrawl.jaxsim.rig import Rig, regulator_step, rig_pressures
    from softcrawl.robot import PressureCalibration
    from softcrawl.robot.domain import LaggedRegulatorBank, RegulatorWarp

    rng = np.random.default_rng(0)
    cal, dt = PressureCalibration(), 0.02
    settings = Settings(dt, 0.0, 0.0, (0.0, 0.0, 0.0), True, 0.0, 0.5, 1.0, 0, 0, "apgd", 1, (cal.a, cal.b), 150.0)
    rig = Rig(*(jnp.asarray(v) for v in ([0.95, 1.2, 1.0], [-5.0, 2.0, 0.0], [0.0, 0.3, 0.05], [0.5, 0.0, 0.3])))
    bank = LaggedRegulatorBank(3, 150.0, tuple(np.asarray(rig.tau_inflate)), tuple(np.asarray(rig.tau_vent)))
    warp = RegulatorWarp(cal, tuple(np.asarray(rig.gain)), tuple(np.asarray(rig.offset)))
    step = jax.jit(functools.partial(regulator_step, settings))
    p = jnp.zeros(3)
    for k in range(200):
        if k % 20 == 0:
            c = rng.uniform(0, 90, 3)
        ref = bank.step(c, dt)
        p = step(rig, p, jnp.asarray(c))
        np.testing.assert_allclose(np.asarray(p), ref, rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.asarray(rig_pressures(settings, rig, p)), warp.to_sim(ref), rtol=0, atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_smoke_training_runs_with_the_jax_backend(tmp_path, precision):
    """``softcrawl train --preset smoke --set backend="jax"`` end to end in either precision,
    with the rig's randomization (per-env gains, offsets, lags and control periods): every
    transition collected, the run folder written (config, checkpoint, the episodes' domain draws)."""
    from softcrawl.codesign.config import override, preset
    from softcrawl.codesign.run import Run
    from softcrawl.codesign.training import train

    cfg = override(preset("smoke"), ['backend="jax"', "env.randomize=rig", f'jax_precision="{precision}"'])
    x64 = jax.config.jax_enable_x64
    try:
        res = train(tmp_path / "run", cfg, progress=False)
    finally:
        jax.config.update("jax_enable_x64", x64)  # the backend set it for the process
    assert res.steps == cfg.total_steps
    run = Run(tmp_path / "run")
    assert run.read_config().backend == "jax" and run.latest_checkpoint(quiet=True) is not None
    rows = run.domain_csv.read_text().splitlines()
    assert len(rows) > 1 and "control_period" in rows[0]


def test_the_compiled_rollout_is_long_enough_for_every_dilated_action():
    """The rollout's step count bounds every action of the control-period dilation (the rig's
    range, and a wide one) over a 20-action episode."""
    from softcrawl.envs.backends.jaxvec import JaxBackend
    from softcrawl.envs.crawler import CrawlerEnv
    from softcrawl.robot.domain import DomainRanges

    rng = np.random.default_rng(0)
    for n, period in ((50, (1.062, 1.070)), (7, (0.5, 1.9)), (2, (0.5, 2.0))):
        env = CrawlerEnv(steps_per_action=n, designs=[BEST], randomize=DomainRanges(control_period=period))
        longest = JaxBackend._longest_action(env)
        for _ in range(50):
            sample = env.randomize.draw(rng)
            assert max(sample.action_steps(n, k) for k in range(20)) <= longest


def test_config_refuses_what_the_jax_backend_cannot_run():
    """The full-order robot, friction / stiffness / mass randomization and an unknown
    precision are refused at config time, one line each; the rig's ranges are accepted."""
    from softcrawl.codesign.config import override, preset

    smoke = preset("smoke")
    with pytest.raises(ValueError, match='reduced robot only.*env.model=.full'):
        override(smoke, ['backend="jax"', 'env.model="full"'])
    for key in ("friction", "youngs_scale", "mass_scale"):
        with pytest.raises(ValueError, match=f"does not randomize env.randomize.{key} "):
            override(smoke, ['backend="jax"', f"env.randomize.{key}=[1.0, 1.1]"])
    with pytest.raises(ValueError, match="jax_precision"):
        override(smoke, ['jax_precision="float16"'])
    cfg = override(smoke, ['backend="jax"', "env.randomize=rig", 'jax_precision="float32"'])
    assert cfg.jax_precision == "float32" and cfg.env.randomize.control_period is not None
    assert override(smoke, ["env.randomize.friction=[1.0, 1.1]"]).backend == "serial"  # CPU backends draw it


def test_backend_refuses_randomization_it_cannot_draw():
    """Envs given to the backend directly are checked too, before anything is compiled."""
    from softcrawl.codesign.factory import env_fn
    from softcrawl.envs.backends.jaxvec import JaxBackend

    cfg = config()
    cfg.env.randomize = dataclasses.replace(cfg.env.randomize, friction=(1.0, 1.1))
    with pytest.raises(ValueError, match="does not randomize env.randomize.friction"):
        JaxBackend([env_fn(cfg)])
    with pytest.raises(ValueError, match="jax_precision"):
        JaxBackend([env_fn(config())], precision="float16")
