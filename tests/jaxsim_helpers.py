"""The JAX engine against the CPU reduced engine: both engines over the same scene, and the JAX
state's node positions stacked as the CPU engine's (``tests/test_jaxsim_robot.py``,
``tests/test_other_spaces.py``)."""

from __future__ import annotations

import numpy as np


def node_positions(robot, model, state, b=0):
    """``(N, 3)`` all nodes of robot ``b`` of a batched JAX state, stacked as the CPU engine's."""
    from softcrawl.jaxsim.scenes import node_positions as positions

    return positions(robot, model, state.q[b][None], state.x[b][None], b)[0]


def scene(robot, model, commands, per):
    """Both engines over segments of ``per`` steps holding regulator ``commands`` (real kPa, one
    per regulator of the robot's space): ``(cpu, jax)`` node positions ``(frames, N, 3)`` every
    10 steps and the JAX engine's last state."""
    import jax.numpy as jnp

    from softcrawl.jaxsim.engine import Control, make_rollout, rest_state
    from softcrawl.robot import PressureCalibration, RegulatorBank

    solver, bank, cal = robot.make_solver(), RegulatorBank(robot.model.n_channels), PressureCalibration()
    s, ref = robot.model.rest_state(), []
    roll, st, got = make_rollout(10), rest_state(model), []
    for c in commands:
        for i in range(per):
            s = solver.step(s, robot.control(cal.to_sim(bank.step(np.asarray(c, float), robot.config.dt))))
            if (i + 1) % 10 == 0:
                ref.append(s.x.copy())
        for _ in range(per // 10):
            st = roll(model, st, Control(jnp.asarray(c, st.x.dtype)[None]))
            got.append(node_positions(robot, model, st))
    return np.stack(ref), np.stack(got), st


def assert_follows(robot, ref, got, st, bound_mm=0.3):
    """The JAX run ``got`` follows the CPU run ``ref`` (``(frames, nodes, 3)`` mm) of a robot
    that moved (its reward node > 5 mm): no bad step, mean node distance and the reward node's
    final distance below ``bound_mm`` (the tests' bound: the JAX and CPU reduced engines agree
    to about 0.1 mm over such a scene)."""
    assert int(st.bad[0]) == 0
    node = robot.reward_node
    assert np.linalg.norm(ref[-1, node] - ref[0, node]) > 5.0  # it moved
    dist = np.linalg.norm(ref - got, axis=2).mean()
    assert dist < bound_mm, dist
    assert np.linalg.norm(ref[-1, node] - got[-1, node]) < bound_mm
