"""Per-robot rig of the JAX engine: each robot's own regulators and pressure warp, and the
rollout of an action that stops each robot where its simulation diverged.

:func:`softcrawl.jaxsim.engine.step` takes the regulators' slew rate and the real-to-sim warp
from the model's static :class:`~softcrawl.jaxsim.model.Settings` (one value for the whole
batch). A vector env with domain randomization draws them per episode
(:class:`softcrawl.robot.domain.DomainSample`), so here they are per-robot arrays
(:class:`Rig`), inputs of the compiled rollout: a new draw costs no recompilation.

* Pressure reaching the legs (:class:`softcrawl.robot.domain.RegulatorWarp`, physics.md
  "Sim-to-real"): sim kPa ``= max(a max(g_k p_k + o_k, 0) + b, 0)`` for regulator output
  ``p_k`` (real kPa), per-robot gains ``g_k`` and offsets ``o_k`` (kPa), the model's warp
  ``(a, b)``. With ``g = 1, o = 0`` this is :func:`softcrawl.jaxsim.engine.sim_pressures`.
* Regulators (:class:`softcrawl.robot.domain.LaggedRegulatorBank`): per step of ``dt`` towards
  command ``c``, ``p += clip((c - p) (1 - exp(-dt / tau)), -rate dt, rate dt)`` with
  ``tau = tau_inflate`` when ``c > p`` else ``tau_vent``; ``tau = 0`` is no lag, the plain
  slew step of :func:`softcrawl.jaxsim.engine.step` (physics.md, "Regulator dynamics").
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import jax
import jax.numpy as jnp

from softcrawl.jaxsim.engine import physics_step, shared_parts
from softcrawl.jaxsim.model import register_pytree


@dataclass(frozen=True)
class Rig:
    """Each robot's regulators and warp (a leading batch axis on every field when batched).

    Attributes:
        gain: ``(R,)`` gain on each regulator's output (nominal 1).
        offset: ``(R,)`` offset added to it, real kPa (nominal 0).
        tau_inflate, tau_vent: ``(R,)`` first-order lags, s (0: none).
    """

    gain: jax.Array
    offset: jax.Array
    tau_inflate: jax.Array
    tau_vent: jax.Array


register_pytree(Rig)


def regulator_step(settings, rig: Rig, pressure, command):
    """Regulator outputs ``(R,)`` real kPa after one ``settings.dt`` towards ``command`` ``(R,)``
    from ``pressure`` (module doc; the model's slew rate ``settings.rate`` kPa/s)."""
    tau = jnp.where(command > pressure, rig.tau_inflate, rig.tau_vent)
    lagged = tau > 0
    frac = jnp.where(lagged, -jnp.expm1(-settings.dt / jnp.where(lagged, tau, 1.0)), 1.0)
    dp = settings.rate * settings.dt
    return pressure + jnp.clip((command - pressure) * frac, -dp, dp)


def rig_pressures(settings, rig: Rig, pressure):
    """Sim kPa ``(R,)`` of regulator outputs ``pressure`` ``(R,)`` real kPa (module doc)."""
    a, b = settings.calibration
    return jnp.maximum(a * jnp.maximum(rig.gain * pressure + rig.offset, 0.0) + b, 0.0)


def healthy(state) -> jax.Array:
    """Whether one robot's state is valid: no inverted or degenerate RID element met
    (``state.bad == 0``) and finite positions and velocities (legs and disk)."""
    finite = [jnp.all(jnp.isfinite(a)) for a in (state.q, state.qdot, state.x, state.v)]
    return (state.bad == 0) & jnp.all(jnp.stack(finite))


def make_action_rollout(n_steps: int):
    """A jitted ``rollout(model, rig, state, command, steps) -> (state, diverged)`` for a batch:
    robot ``b`` holds ``command[b]`` ``(R,)`` (real kPa) for ``steps[b]`` (<= ``n_steps``) steps
    of its own regulators (:func:`regulator_step`, :func:`rig_pressures`) and
    :func:`~softcrawl.jaxsim.engine.physics_step`, then waits; a robot whose step gives an
    invalid state (:func:`healthy`) keeps its last valid state and waits too, flagged in
    ``diverged`` ``(B,)`` (as :class:`softcrawl.fem.solver.SimulationDiverged` leaves a CPU
    episode's state). ``jax.lax.scan`` over ``n_steps``, ``jax.vmap`` over the batch (the
    model's per-robot data, ``rig``, ``state``, ``command``, ``steps`` carry a leading batch
    axis); each robot's arithmetic is its own, so a diverged one cannot disturb the others."""

    def one(model, rd, rig, state, command, steps):
        mdl = dataclasses.replace(model, robot=rd)

        def body(carry, k):
            s, dead = carry
            pressure = regulator_step(mdl.settings, rig, s.pressure, command)
            new = dataclasses.replace(physics_step(mdl, s, rig_pressures(mdl.settings, rig, pressure)),
                                      pressure=pressure)
            run = (k < steps) & ~dead
            fail = run & ~healthy(new)
            keep = run & ~fail
            s = jax.tree_util.tree_map(lambda a, b: jnp.where(keep, a, b), new, s)
            return (s, dead | fail), None

        return jax.lax.scan(body, (state, jnp.zeros((), bool)), jnp.arange(n_steps))[0]

    @jax.jit
    def rollout(model, rig, state, command, steps):
        return jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0))(shared_parts(model), model.robot, rig,
                                                           state, command, steps)

    return rollout
