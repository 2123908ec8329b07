"""The JAX engine's leg free motion against the CPU engine's compiled kernels (float64)."""

import numpy as np
import pytest

jax = pytest.importorskip("jax")


@pytest.fixture(scope="module")
def x64():
    """float64 for this module's tests (switched by the test, not at import)."""
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", old)


@pytest.fixture(scope="module")
def robot():
    from softcrawl.robot import RobotConfig, build_robot

    return build_robot("1,0,0,2,2,0,0,0", RobotConfig(model="reduced"))


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
    the free modal velocities and the step matrices' Cholesky factors agree with
    :meth:`ModalGroup.free_motion` to round-off (1e-9 relative; the sums run in another order)."""
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
    qd, chol, bad = step(model.leg, model.settings, jnp.asarray(q), jnp.asarray(qdot), rd.rotation[0], p,
                         rd.leg_mask[0])
    assert not np.asarray(bad).any()
    dq = np.asarray(qd) - qdot
    np.testing.assert_allclose(dq, ref_qd - qdot, rtol=0, atol=1e-9 * np.abs(ref_qd - qdot).max())
    np.testing.assert_allclose(np.asarray(chol), ref_chol, rtol=0, atol=1e-9 * np.abs(ref_chol).max())
