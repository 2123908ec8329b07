"""Static equilibrium of unconstrained-by-contact bodies: ``f_int(x) + f_ext(x) = 0``.

Newton iterations with the corotational tangent ``K = sum_e R K_e R^T`` (SOFA's, without
dR/dx, so convergence is linear rather than quadratic under large rotations), a
backtracking line search on the residual norm, and optional load stepping. Used by the verification checks (cantilever, Lamé sphere, PneuNet bending).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softcrawl.fem.linalg import Factorization
from softcrawl.fem.model import Model
from softcrawl.fem.state import Control, State


class StaticSolveError(RuntimeError):
    """Newton iterations did not reach equilibrium."""


@dataclass(frozen=True)
class StaticResult:
    """Equilibrium state and convergence record.

    Attributes:
        state: equilibrium positions (velocities zero).
        iterations: Newton iterations used in total.
        residual: final relative residual ``|r_free| / |f_ext_free|``.
    """

    state: State
    iterations: int
    residual: float


def solve_static(
    model: Model,
    control: Control | None = None,
    state: State | None = None,
    load_steps: int = 1,
    tol: float = 1e-7,
    max_iterations: int = 200,
) -> StaticResult:
    """Solve for static equilibrium under gravity and cavity pressures.

    The floor and attachments are ignored (use the dynamic solver for contact); bodies are
    held by their Dirichlet-fixed degrees of freedom.

    Args:
        model: the model (each body needs enough fixed DOFs to remove rigid motion).
        control: pressures (sim kPa); zeros if None.
        state: initial guess (rest state if None).
        load_steps: apply the loads in this many equal increments.
        tol: relative residual tolerance.
        max_iterations: Newton iteration limit per load step.

    Returns:
        The equilibrium :class:`StaticResult`.

    Raises:
        ValueError: if the model has attachments.
        StaticSolveError: if a load step does not converge, or elements invert.
    """
    if model.attachments:
        raise ValueError("solve_static does not handle attachments; use ImplicitEulerSolver")
    control = control or Control(np.zeros(model.n_channels))
    state = state or model.rest_state()
    x = state.x.copy()
    g = np.asarray(model.gravity, float)
    total_its, res = 0, 0.0
    for i, body in enumerate(model.bodies):
        sl = model.body_slice(i)
        xb = x[sl]
        free = body.free_dofs
        diag_fixed = body.pattern.diag[~free]
        def residual(x: np.ndarray, scale: float, tangent: bool):
            f, kdata, n_bad = body.internal_forces(x, tangent_coef=1.0 if tangent else None)
            f_ext = body.external_forces(x, scale * control.pressures, scale * g)
            if control.forces is not None:
                f_ext += scale * control.forces[sl]
            r = (f + f_ext).ravel()
            r[~free] = 0.0
            return r, kdata, n_bad, max(np.linalg.norm(f_ext.ravel()[free]), 1e-300)

        for s in range(1, load_steps + 1):
            scale = s / load_steps
            r, kdata, n_bad, ref = residual(xb, scale, True)
            for it in range(max_iterations + 1):
                if n_bad:
                    raise StaticSolveError(f"{n_bad} inverted elements in body {body.name!r}")
                res = float(np.linalg.norm(r) / ref)
                if res <= tol:
                    break
                if it == max_iterations:
                    raise StaticSolveError(
                        f"no equilibrium for body {body.name!r} at load {scale:.2f} after "
                        f"{max_iterations} iterations (relative residual {res:.3g})"
                    )
                kdata[body.fixed_entries] = 0.0
                kdata[diag_fixed] = 1.0
                dx = Factorization(body.pattern.matrix(kdata)).solve(r).reshape(-1, 3)
                # Backtracking line search on the residual norm (the corotational tangent
                # omits dR/dx, so full steps can overshoot under large rotations).
                step = 1.0
                for _ in range(12):
                    x_try = xb + step * dx
                    r_try, _, bad_try, _ = residual(x_try, scale, False)
                    if not bad_try and np.linalg.norm(r_try) < np.linalg.norm(r):
                        break
                    step *= 0.5
                xb[:] = x_try
                r, kdata, n_bad, ref = residual(xb, scale, True)
                total_its += 1
    return StaticResult(State(x=x, v=np.zeros_like(x), t=state.t), total_its, res)

