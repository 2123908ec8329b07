"""The JAX engine (:mod:`softcrawl.jaxsim`) against the CPU reduced engine: the legs' free motion,
a robot hanging free (no floor), landing and actuation on the floor, batches of mixed designs."""

import dataclasses
import functools

import numpy as np
import pytest
from jaxsim_helpers import assert_follows, node_positions, scene

jax = pytest.importorskip("jax")

DESIGN = "1,0,0,2,2,0,0,0"  # the paper's best design: 3 legs on two regulators
SIM_KPA = np.array([150.0, 60.0, 0.0])


@pytest.fixture(scope="module")
def robot():
    from softcrawl.robot import RobotConfig, build_robot

    return build_robot(DESIGN, RobotConfig(model="reduced"))


def deformed_legs(robot, seed=0, scale=1.0):
    """Random modal states of the robot's legs and the stacked world positions they give."""
    rng = np.random.default_rng(seed)
    L = len(robot.legs)
    rb = robot.reduced[robot.legs[0].body]
    m = rb.n_modes
    q = scale * rng.normal(size=(L, m))
    qdot = 20.0 * scale * rng.normal(size=(L, m))
    x = robot.model.rest_state().x.copy()
    for j, leg in enumerate(robot.legs):
        sl = robot.model.body_slice(leg.body)
        R = robot.reduced[leg.body].rotation
        x[sl] += (rb.part.basis @ q[j]).reshape(-1, 3) @ R.T
    return q, qdot, x


def test_leg_free_motion_matches_the_cpu_kernels(x64, robot):
    """One step of the free motion of 4 deformed, moving, pressurised legs (two regulators):
    the free modal velocities agree with :meth:`ModalGroup.free_motion` to round-off (1e-9
    relative; the sums run in another order), and the inverse factors the step returns invert
    the CPU kernels' Cholesky factors of the step matrices (``C^-1 C = I`` to 1e-9)."""
    import jax.numpy as jnp

    from softcrawl.jaxsim.legs import free_motion
    from softcrawl.jaxsim.model import build_model

    q, qdot, x = deformed_legs(robot, scale=5.0)
    sim_kpa = np.array([150.0, 60.0, 0.0])
    solver = robot.make_solver()
    group = solver.groups[0]
    m = robot.model
    ref_qd, ref_chol, n_bad, ok = group.free_motion(x, qdot, sim_kpa, robot.config.dt, m.rayleigh_mass,
                                                    m.rayleigh_stiffness)
    assert ok.all() and not n_bad.any()
    model = build_model([robot])
    rd = model.robot
    p = jnp.asarray(sim_kpa)[rd.channel[0]]
    step = jax.jit(jax.vmap(free_motion, in_axes=(None, None, 0, 0, 0, 0, 0)), static_argnums=1)
    qd, inv_chol, bad = step(model.leg, model.settings, jnp.asarray(q), jnp.asarray(qdot), rd.rotation[0], p,
                             rd.leg_mask[0])
    assert not np.asarray(bad).any()
    dq = np.asarray(qd) - qdot
    np.testing.assert_allclose(dq, ref_qd - qdot, rtol=0, atol=1e-9 * np.abs(ref_qd - qdot).max())
    eye = np.broadcast_to(np.eye(ref_chol.shape[-1]), ref_chol.shape)
    np.testing.assert_allclose(np.asarray(inv_chol) @ ref_chol, eye, rtol=0, atol=1e-9)
    assert np.all(np.triu(np.asarray(inv_chol), 1) == 0)


def test_disk_free_motion_matches_the_cpu_floating_frame(x64, robot):
    """One free step of the disk turned 35 degrees, stretched and moving (its nodes at random
    velocities of 100 mm/s, its shape 0.5 mm from rigid): the JAX step's one product with
    ``DiskPart.step_operator`` gives :meth:`FloatingFrameBody.free_velocity`'s velocities under
    gravity (a sparse solve with ``A_0`` and the damping terms written out) to 1e-9 of the
    velocity change's largest entry (measured 2e-11: the dense ``A_0^-1`` against a sparse
    factor, round-off amplified by ``A_0``'s conditioning; 1% off the mass block is 3e-4), and
    the same rotation to 1e-12."""
    import jax.numpy as jnp
    from scipy.spatial.transform import Rotation

    from softcrawl.jaxsim import disk as disk_motion
    from softcrawl.jaxsim.model import build_model

    rng = np.random.default_rng(3)
    fb = robot.reduced[robot.disk_body]
    X = fb.body.mesh.points
    turn = Rotation.from_rotvec(np.radians(35.0) * np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]))
    x = (X + 0.5 * rng.normal(size=X.shape)) @ turn.as_matrix().T + np.array([4.0, -2.0, 7.0])
    v = 100.0 * rng.normal(size=X.shape)
    m, h = robot.model, robot.config.dt
    f = fb.body.nodal_mass[:, None] * np.asarray(m.gravity)[None, :]
    ref_v, ref_R = fb.free_velocity(fb.step_factorization(h, m.rayleigh_mass, m.rayleigh_stiffness), x, v, f, h,
                                    m.rayleigh_mass, m.rayleigh_stiffness)
    model = build_model([robot])
    got_v, got_R = jax.jit(disk_motion.free_motion, static_argnums=1)(model.disk, model.settings, jnp.asarray(x),
                                                                       jnp.asarray(v))
    dv = ref_v - v
    assert np.abs(dv).max() > 10.0  # gravity and the elastic forces moved it
    np.testing.assert_allclose(np.asarray(got_v) - v, dv, rtol=0, atol=1e-9 * np.abs(dv).max())
    np.testing.assert_allclose(np.asarray(got_R), ref_R, rtol=0, atol=1e-12)


def cpu_run(robot, n, sim_kpa):
    """The CPU reduced engine's positions ``(n, N, 3)`` over ``n`` steps at ``sim_kpa``."""
    from softcrawl.fem.state import Control

    solver = robot.make_solver()
    s = robot.model.rest_state()
    out = []
    for _ in range(n):
        s = solver.step(s, Control(np.asarray(sim_kpa, float)))
        out.append(s.x.copy())
    return np.stack(out), s


def jax_run(robot, model, n, sim_kpa):
    """The JAX engine's positions ``(n, N, 3)`` over ``n`` steps at ``sim_kpa`` and its last state."""
    import jax.numpy as jnp

    from softcrawl.jaxsim.engine import make_rollout, rest_state

    roll = make_rollout(1, physics_only=True)
    st = rest_state(model)
    out = []
    for _ in range(n):
        st = roll(model, st, jnp.asarray(sim_kpa)[None])
        out.append(node_positions(robot, model, st))
    return np.stack(out), st


def test_hanging_robot_matches_the_cpu_engine(x64, robot):
    """No floor, three legs pressurised on two regulators, 30 steps (0.3 s, the robot falls 0.48 m and
    the legs bend): every node within 1e-6 mm of the CPU reduced engine (measured 8e-9 mm: the
    same equations, the attachments solved exactly by both, round-off only)."""
    from softcrawl.jaxsim.model import build_model

    hanging = dataclasses.replace(robot, model=dataclasses.replace(robot.model, floor=None))
    ref, _ = cpu_run(hanging, 30, SIM_KPA)
    got, st = jax_run(robot, build_model([robot], floor=False), 30, SIM_KPA)
    assert int(st.bad[0]) == 0
    assert np.abs(ref[-1] - ref[0]).max() > 100.0  # it moved
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-6)


@pytest.fixture(params=["float32", "float64"])
def precision(request):
    """Both precisions, switched for the test and restored after it."""
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", request.param == "float64")
    yield request.param
    jax.config.update("jax_enable_x64", old)


def test_landing_and_actuation_match_the_cpu_engine(precision, robot):
    """Landing from the assembled pose (0.5 s at zero pressure), then 1 s with regulators 1 and 2
    commanded to 90 and 40 kPa: the mean node distance to the CPU reduced engine over the scene
    stays below 0.3 mm and the reward point ends within 0.3 mm of it, in float64 and in float32
    (measured 0.091 and 0.089 mm in float64; a 3-s scene of four commands gave 0.105 mm in
    both). The engines differ in the contact solve only (100 Gauss-Seidel sweeps on 8 disk and 12
    leg points against the CPU engine's exact active-set polish on its growing set; frictional
    contact problems of the reduced legs can have several solutions), and the budget is the reduced
    model's own error against the full-order one, about 1 mm on held-out scenes."""
    from softcrawl.jaxsim.model import build_model

    ref, got, st = scene(robot, build_model([robot]), [(0, 0, 0), (90, 40, 0), (90, 40, 0)], 50)
    assert_follows(robot, ref, got, st)


def test_a_mixed_batch_steps_each_robot_as_alone(precision, robot):
    """A batch of the 3-legged robot and a 4-legged one (padded to 4 leg slots, the 3-legged
    robot's fourth masked) gives each robot the trajectory it has alone in a model of its own leg
    count. Hanging free for 40 steps (float64) the masks add exact zeros, and only the order of
    round-off differs: 5e-8 mm after a 1.5 m fall (measured 1.2e-8 mm, 1e-11 of the fall). On the floor (20 steps of landing, 20 of actuation) both robots, padded or not, end up
    to 0.03 mm from their own runs (measured in float64): round-off decides ties among the
    assembled legs' tip points, which lie at one height, for the 12 contact rows of each leg,
    and contact mode switches amplify it; so 0.1 mm. In float32 the same amplification of a
    larger round-off moved the padded runs 0.005 to 0.10 mm from their own across formulations
    of the step that differ in the order of their arithmetic only, so 0.3 mm there: the budget
    of the engine against the CPU engine (:func:`test_landing_and_actuation_match_the_cpu_engine`)."""
    import jax.numpy as jnp

    from softcrawl.jaxsim.engine import Control, make_rollout, rest_state
    from softcrawl.jaxsim.model import build_model
    from softcrawl.robot import RobotConfig, build_robot

    four = build_robot("1,0,2,0,1,0,3,0", RobotConfig(model="reduced"))
    roll = make_rollout(20)
    for floor, tol in [(False, 5e-8), (True, 0.1)] if precision == "float64" else [(True, 0.3)]:
        both = build_model([robot, four], floor=floor)
        assert both.robot.leg_mask.shape == (2, 4) and not bool(both.robot.leg_mask[0, 3])
        dt = rest_state(both).x.dtype
        runs = []
        for model, n in [(both, 2)] + [(build_model([r], floor=floor), 1) for r in (robot, four)]:
            st = rest_state(model)
            for c in ([0, 0, 0], [90, 40, 60]):
                st = roll(model, st, Control(jnp.tile(jnp.asarray(c, dt), (n, 1))))
            runs.append((model, st))
        for b, r in enumerate((robot, four)):
            nb, na = node_positions(r, both, runs[0][1], b), node_positions(r, *runs[1 + b])
            assert np.abs(nb - na).max() < tol, (floor, b, np.abs(nb - na).max())
            assert np.abs(nb - r.model.rest_state().x).max() > 5.0  # it moved


def test_settling_rests_where_the_cpu_engine_rests(precision, robot):
    """:func:`make_settle` steps to rest by the CPU engine's rule (:func:`softcrawl.robot.settle`),
    watching the same nodes (all of them): the rested robot is slower than 0.5 mm/s, its time is
    0, it took within 10 steps (0.1 s) of the CPU engine's 48 and its nodes are on average within
    0.2 mm of the CPU engine's rested state (measured 54 / 55 steps and 0.109 / 0.110 mm in
    float64 / float32; the contact solves differ, and a robot at rest by this rule still drifts
    up to about 0.5 mm/s x 0.1 s, Settling.rest_speed)."""
    import jax.numpy as jnp

    from softcrawl.jaxsim.engine import make_settle, max_speed, rest_state
    from softcrawl.jaxsim.model import build_model
    from softcrawl.robot import settle

    ref = settle(robot)
    model = build_model([robot])
    st, steps = make_settle()(model, rest_state(model))
    first = functools.partial(jax.tree_util.tree_map, lambda a: a[0])
    speed = float(max_speed(dataclasses.replace(model, robot=first(model.robot)), first(st)))
    assert ref.at_rest and abs(int(steps[0]) - ref.steps) <= 10 and speed < 0.5, (int(steps[0]), ref.steps)
    assert float(jnp.abs(st.t).max()) == 0.0
    dist = np.linalg.norm(node_positions(robot, model, st) - ref.state.x, axis=1).mean()
    assert dist < 0.2, dist


@pytest.mark.slow
def test_paper_best_crawl_distance_is_the_cpu_engines():
    """The paper's best design and gait, 20 s after settling (dt 0.01, float32): the JAX engine
    crawls within 8% of the CPU reduced engine (measured 11.26 cm against 11.78 cm, -4.4%; 300
    sweeps: 11.32 cm; float64: 11.25 cm). The budget: stick-slip makes the crawl distance the most
    sensitive output, and the CPU engine's own modelling choices move it by as much (floating
    against corotational disk 11.31 against 11.69 cm full order, RobotConfig.reduced_disk)."""
    import jax.numpy as jnp

    from softcrawl.gaits.gaits import paper_best_gait
    from softcrawl.jaxsim.engine import Control, make_rollout, make_settle, rest_state
    from softcrawl.jaxsim.model import build_model
    from softcrawl.robot import RobotConfig, build_robot, run_episode

    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", False)
    try:
        robot = build_robot(DESIGN, RobotConfig(model="reduced"))
        gait = paper_best_gait()
        ref = run_episode(robot, gait, duration=20.0).reward_cm
        model = build_model([robot])
        st, _ = make_settle()(model, rest_state(model))
        x0 = float(st.x[0, model.disk.reward_node, 0])
        roll = make_rollout(100)
        for k in range(20):
            st = roll(model, st, Control(jnp.asarray(gait.pressure_at(k + 0.5), st.x.dtype)[None]))
        got = (float(st.x[0, model.disk.reward_node, 0]) - x0) / 10.0
    finally:
        jax.config.update("jax_enable_x64", old)
    assert ref > 10.0 and int(st.bad[0]) == 0
    assert abs(got - ref) < 0.08 * ref, (got, ref)


def test_build_model_refuses_what_the_engine_cannot_step(robot):
    """No robots, a robot that is not reduced, too few leg slots and RID triangles that are not
    membranes (the GPU's form of the RID terms takes their in-plane frame rows only; the shipped
    triangles' factors on the normal components are 1.6e-16 of the largest, the limit 1e-9) are
    refused with one clear error each."""
    import copy

    from softcrawl.jaxsim.model import build_model

    with pytest.raises(ValueError, match="at least one robot"):
        build_model([])
    with pytest.raises(ValueError, match="floating-frame disk"):
        build_model([dataclasses.replace(robot, reduced={})])
    with pytest.raises(ValueError, match="n_slots"):
        build_model([robot], n_slots=2)
    body = robot.legs[0].body
    leg = copy.copy(robot.reduced[body])
    tets, tris = leg.element_factors
    bent = tris.factors.copy()
    bent[:, :, 2::3] = 1e-3 * np.abs(bent).max()
    leg.__dict__["element_factors"] = (tets, dataclasses.replace(tris, factors=bent))
    with pytest.raises(ValueError, match="membrane triangles"):
        build_model([dataclasses.replace(robot, reduced={**robot.reduced, body: leg})])


@pytest.mark.parametrize("library_from", [None, 1])
def test_float32_products_are_not_lowered_to_tensorfloat32(robot, monkeypatch, library_from):
    """Regression: on a GPU the default precision of float32 matrix products is TF32 (10-bit
    mantissa), which inverted elements of every robot of the GPU benchmark; the step's products
    ask for full precision (``precision = HIGHEST`` in the lowered program, which a CPU ignores
    and a GPU obeys). The attachment block's inverse is traced by its batching rule, outside the
    step's precision setting: its product asks for full precision itself, below
    ``factor.LIBRARY_FROM`` (the sweeps on CUDA, the library's form elsewhere) and from it (here
    1: the library's form, batched)."""
    import re

    import jax.numpy as jnp

    from softcrawl.jaxsim import factor
    from softcrawl.jaxsim.engine import Control, make_rollout, rest_state
    from softcrawl.jaxsim.model import build_model

    if library_from:
        monkeypatch.setattr(factor, "LIBRARY_FROM", library_from)
    model = build_model([robot], dtype=jnp.float32)
    st = rest_state(model)
    text = make_rollout(1).lower(model, st, Control(jnp.zeros((1, 3), jnp.float32))).as_text()
    dots = re.findall(r"stablehlo\.dot_general.*", text)
    assert dots and all("HIGHEST" in d for d in dots), [d for d in dots if "HIGHEST" not in d][:3]
