"""Reduction scenes on the JAX engine: :func:`run_scene` of :mod:`softcrawl.reduction.scenes`
with the reduced robot stepped by :mod:`softcrawl.jaxsim` (``softcrawl reduce validate --engine jax``).

The same protocol as the CPU runner: settle at zero pressure by the episodes' rule
(:class:`~softcrawl.robot.episode.Settling`), then drive each leg's channel with the animation's
sim kPa (no regulators), recording all node positions every ``record_every`` steps and at
``t = 0``. The node positions are rebuilt from the engine's state in the robot's node order:
the disk's nodes as stepped, each leg's ``(X + Phi q) R^T + t`` (reduction.md, "Reduced
kinematics").
"""

from __future__ import annotations

import time

import jax.numpy as jnp
import numpy as np

from softcrawl.fem.solver import SolverSettings
from softcrawl.jaxsim.engine import make_schedule_rollout, make_settle, rest_state
from softcrawl.jaxsim.model import build_model, engine_dtype
from softcrawl.reduction.scenes import SceneRecord
from softcrawl.robot.episode import Settling


def node_positions(robot, model, q, x, b: int = 0) -> np.ndarray:
    """All nodes ``(T, N, 3)`` (mm, the robot's node order) of robot ``b`` of a batched model
    from its legs' modal displacements ``q`` ``(T, L, m)`` and disk positions ``x`` ``(T, nd, 3)``."""
    q, x = np.asarray(q, float), np.asarray(x, float)
    out = np.empty((x.shape[0], robot.model.n_nodes, 3))
    out[:, robot.model.body_slice(robot.disk_body)] = x
    rb = robot.reduced[robot.legs[0].body]
    X, Phi = rb.part.mesh.points, rb.part.basis
    for j, leg in enumerate(robot.legs):
        R, t = np.asarray(model.robot.rotation[b, j], float), np.asarray(model.robot.translation[b, j], float)
        out[:, robot.model.body_slice(leg.body)] = (X + (q[:, j] @ Phi.T).reshape(len(q), -1, 3)) @ R.T + t
    return out


def run_scene(robot, animation, record_every: int = 2, duration: float | None = None, precision: str = "float64",
              settling: Settling = Settling(), **engine) -> SceneRecord:
    """Settle, then play ``animation`` on the JAX engine (module doc).

    Args:
        robot: a reduced robot with a floating disk (:func:`softcrawl.jaxsim.model.build_model`).
        animation: ``sim_pressure_at(t) -> (n_channels,)`` sim kPa, and ``duration`` (s).
        record_every: steps between recorded frames.
        duration: s (default: the animation's).
        precision: the engine's, ``"float32"`` or ``"float64"`` (which needs ``jax_enable_x64``).
        settling: the rest rule before the animation.
        engine: ``leg_contacts``, ``disk_contacts``, ``solver``, ``iterations`` of :func:`build_model`.

    Returns:
        A :class:`~softcrawl.reduction.scenes.SceneRecord` (float32 positions); ``diverged``
        names the failure (an inverted element, a non-finite value, a node faster than the CPU
        engine's ``max_speed``). Its wall time includes compiling the engine for this robot.

    Raises:
        ValueError: a robot the JAX engine cannot step; float64 without ``jax_enable_x64``.
    """
    wall = time.perf_counter()
    dt = robot.config.dt
    n = int(round((duration if duration is not None else animation.duration) / dt))
    nch = robot.model.n_channels
    model = build_model([robot], dtype=engine_dtype(precision), **engine)
    hold, cap = settling.steps(dt)
    state, settle_steps = make_settle(settling.rest_speed, hold, cap)(model, rest_state(model))
    schedule = np.zeros((1, n, nch))
    for k in range(n):
        a = np.asarray(animation.sim_pressure_at(k * dt), float)[:nch]
        schedule[0, k, :len(a)] = a
    final, peak, (q, x) = make_schedule_rollout(physics_only=True, trace=True)(
        model, state, jnp.asarray(schedule, state.x.dtype))
    keep = np.arange(record_every, n + 1, record_every) - 1  # frame after step k + 1
    q = np.concatenate([np.asarray(state.q[0])[None], np.asarray(q[0])[keep]])
    x = np.concatenate([np.asarray(state.x[0])[None], np.asarray(x[0])[keep]])
    positions = node_positions(robot, model, q, x)
    reason = ""
    if int(final.bad[0]) > 0 or not np.isfinite(positions).all():
        reason = "inverted elements or non-finite values"
    elif float(peak[0]) > SolverSettings.max_speed:
        reason = f"node speed {float(peak[0]):.3g} mm/s exceeds {SolverSettings.max_speed:.3g}"
    return SceneRecord(np.arange(len(positions)) * record_every * dt, positions.astype(np.float32),
                       positions[:, robot.reward_node, 0], n, time.perf_counter() - wall, reason,
                       int(settle_steps[0]))
