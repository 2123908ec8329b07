"""The JAX engine's contact solve against closed-form results, on the machine's own JAX device.

A rigid box on an incline (verification.md, "Incline: stick vs slide"; the Delassus operator of
its four bottom corners, ``J M^-1 J^T``) is stepped from rest with the float32 engine's default
solve in the form this device runs (:func:`softcrawl.jaxsim.contact.solve_on_platform`: 48
accelerated projected-gradient iterations, warm-started from the last step; on a CUDA GPU of
compute capability 8.0 or newer in one Pallas kernel reading the operator in float16, on other
GPUs by XLA in float16, on a CPU by XLA in float32). Below the friction angle the corners stay at
rest; above it they slide at ``dt g (sin theta - mu cos theta)`` with the friction impulse ``mu``
times the normal one, opposite to the slip; the normal impulses carry ``m g cos theta dt``.
The solve is iterative across steps, as in the engine: a persisting contact state converges to
round-off within a few steps (:data:`STEPS`).
"""

from __future__ import annotations

from functools import partial

import numpy as np

from softcrawl.verify.result import NOMINAL, CheckResult, ModelScales

#: The box's friction coefficient and the two inclines, degrees: below and above the friction
#: angle ``atan(1.2) = 50.19``.
MU, STICK_DEG, SLIDE_DEG = 1.2, 45.0, 60.0
#: Steps of the repeated step from rest; the direction of gravity in the floor plane, degrees.
STEPS, PHI_DEG = 8, 30.0
#: The acceptance bound, relative to the step's free velocity ``dt g`` or to the impulse it
#: checks: 16 times float32's rounding unit (the solve is float32; measured 1e-7 to 4e-7 on a CPU
#: and in the kernel's interpreter, ``tests/test_jaxsim_contact.py``).
TOLERANCE = 2e-6


def box_on_incline(theta_deg: float, phi_deg: float, mu: float, gravity: float = 9810.0):
    """A rigid box (50 g, 40 x 30 x 10 mm, centre of mass 5 mm above its four bottom corners)
    resting on the floor, gravity (``gravity`` mm/s^2) tilted by ``theta`` from the normal
    towards the floor direction ``phi``, one 20 ms step from rest.

    Returns:
        ``(W, q, mu, m g dt, dt)``: the ``(12, 12)`` Delassus operator of its four corner
        contacts (rank 6; rows normal z, tangents x, y; mm/s per mN s), their free velocities
        ``(12,)`` mm/s, ``(4,)`` friction coefficients, the weight's impulse over a step (mN s)
        and the step (s)."""
    m, a, b, h, dt = 0.05, 20.0, 15.0, 5.0, 0.02
    inertia = m / 12 * np.array([(2 * b) ** 2 + (2 * h) ** 2, (2 * a) ** 2 + (2 * h) ** 2, (2 * a) ** 2 + (2 * b) ** 2])
    Minv = np.diag(np.concatenate([np.full(3, 1 / m), 1 / inertia]))
    rows = []
    for sx, sy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        r = np.array([sx * a, sy * b, -h])
        cross = np.array([[0, -r[2], r[1]], [r[2], 0, -r[0]], [-r[1], r[0], 0]])  # [r]x
        Jp = np.hstack([np.eye(3), -cross])  # point velocity v + w x r
        rows += [Jp[2], Jp[0], Jp[1]]
    J = np.array(rows)
    th, ph = np.radians(theta_deg), np.radians(phi_deg)
    g = gravity * np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), -np.cos(th)])
    q = J @ np.concatenate([dt * g, np.zeros(3)])
    return J @ Minv @ J.T, q, np.full(4, mu), m * gravity * dt, dt


def check_jax_incline(resolution: str = "coarse", scales: ModelScales = NOMINAL) -> list[CheckResult]:
    """The box below and above the friction angle (module doc) on JAX's default device, after
    :data:`STEPS` steps: the corners' velocity, the normal impulse and, sliding, the friction
    impulse against the closed form, to :data:`TOLERANCE`. ``resolution`` is unused (no mesh);
    ``scales`` perturb the simulated box's friction and gravity."""
    del resolution
    import jax
    import jax.numpy as jnp

    from softcrawl.jaxsim.contact import DEFAULT_ITERATIONS, solve_on_platform

    device = jax.devices()[0]
    where = f"JAX contact solve on {device.platform} ({device.device_kind})"
    solve = jax.jit(partial(solve_on_platform, solver="apgd", iterations=DEFAULT_ITERATIONS["apgd"],
                            storage="float16", kernel=True))
    g = 9810.0
    out = []
    for theta in (STICK_DEG, SLIDE_DEG):
        W, q, mu, _, dt = (np.asarray(a, np.float32) if np.ndim(a) else a for a in
                           box_on_incline(theta, PHI_DEG, MU * scales.friction, g * scales.gravity))
        weight = box_on_incline(theta, PHI_DEG, MU, g)[3]  # the nominal box's weight over a step, mN s
        lam = jnp.zeros(12, jnp.float32)
        for _ in range(STEPS):
            lam = solve(jnp.asarray(W), jnp.asarray(q), jnp.asarray(mu), lam, jnp.ones(4, bool))
        lam = np.asarray(lam, float)
        u, L = (W.astype(float) @ lam + q).reshape(4, 3), lam.reshape(4, 3)
        th, ph = np.radians(theta), np.radians(PHI_DEG)
        speed = max(dt * g * (np.sin(th) - MU * np.cos(th)), 0.0)
        along = u[:, 1:] @ np.array([np.cos(ph), np.sin(ph)])  # each corner's velocity down the slope
        across = np.abs(np.concatenate([u[:, 0], u[:, 1:] @ np.array([-np.sin(ph), np.cos(ph)])])).max()
        worst = along[np.argmax(np.abs(along - speed))]
        what = "sticks" if speed == 0 else "slides at dt g (sin - mu cos)"
        out.append(CheckResult(f"{where}: box at {theta:g} deg {what}, corners' velocity down the slope (farthest)",
                               speed, float(worst), TOLERANCE * dt * g, "mm/s", mode="abs"))
        out.append(CheckResult(f"{where}: box at {theta:g} deg, corners' normal and cross-slope velocity (largest)",
                               0.0, float(across), TOLERANCE * dt * g, "mm/s", mode="abs"))
        out.append(CheckResult(f"{where}: box at {theta:g} deg, normal impulse = m g cos(theta) dt",
                               weight * np.cos(th), float(L[:, 0].sum()), TOLERANCE, "mN s"))
        if speed:
            out.append(CheckResult(f"{where}: box at {theta:g} deg, friction impulse / normal impulse (Coulomb, "
                                   "opposite to the slip)", MU,
                                   float(-L[:, 1:].sum(axis=0) @ np.array([np.cos(ph), np.sin(ph)]) / L[:, 0].sum()),
                                   TOLERANCE))
    return out
