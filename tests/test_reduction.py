"""Reduced model (POD + ECSW): exactness limits, basis and RID construction, artifacts."""

import numpy as np
import pytest

from softcrawl.fem.body import Body, Cavity, Membrane
from softcrawl.fem.materials import LinearElastic
from softcrawl.fem.model import Attachment, Floor, Model, PointRef
from softcrawl.fem.solver import ImplicitEulerSolver, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.geometry import box_mesh
from softcrawl.reduction.model import PartReduction, reduce_body
from softcrawl.reduction.solver import ReducedSolver


def _two_box_model():
    """A soft box with a membrane and a pressurised face, tied to a stiffer box, on a
    frictional floor under gravity: every term of the reduced step is exercised."""
    soft = box_mesh((30.0, 12.0, 8.0), (4, 2, 2)).transformed(np.eye(3), np.array([0.0, 0.0, 0.5]))
    bottom = soft.surfaces["boundary"][np.all(np.isclose(soft.points[soft.surfaces["boundary"], 2], 0.5), axis=1)]
    top = soft.surfaces["boundary"][np.all(np.isclose(soft.points[soft.surfaces["boundary"], 2], 8.5), axis=1)]
    hard = box_mesh((10.0, 12.0, 6.0), (2, 2, 1), origin=(10.0, 0.0, 9.0))
    b0 = Body(soft, LinearElastic(500.0, 0.3), 0.02, membrane=Membrane(bottom, LinearElastic(2000.0, 0.45), 1.0),
              cavities=(Cavity(top[:, ::-1], 0),), name="soft")
    b1 = Body(hard, LinearElastic(5000.0, 0.3), 0.01, name="hard")
    ties = []
    for p in hard.points[np.isclose(hard.points[:, 2], 9.0)][:4]:
        j = int(np.argmin(np.linalg.norm(soft.points - (p + [0, 0, -0.5]), axis=1)))
        i = int(np.argmin(np.linalg.norm(hard.points - p, axis=1)))
        ties.append(Attachment(PointRef(0, np.array([j]), np.ones(1)), PointRef(1, np.array([i]), np.ones(1))))
    return Model((b0, b1), tuple(ties), floor=Floor(0.0, 0.8, 0.5))


def _run(solver, model, steps, pressure=40.0):
    state = model.rest_state()
    forces = np.zeros_like(state.x)
    forces[: model.bodies[0].n_nodes, 0] = 5.0
    for k in range(steps):
        state = solver.step(state, Control(np.array([pressure * min(1.0, k / 5)]), forces))
    return state


def test_all_modes_all_elements_reproduce_the_full_model_to_round_off():
    """Phi = I (all modes), every element at unit weight: the reduced step is the full step
    in another algebra (dense Cholesky of the same matrix), so states agree to round-off
    (verification.md, "Reduced-order model"); 1e-9 mm over 30 steps of contact and stick-slip."""
    model = _two_box_model()
    body = model.bodies[0]
    part = PartReduction.full(body.mesh, np.eye(3 * body.n_nodes), len(body.membrane.triangles))
    rom = ReducedSolver(model, {0: reduce_body(body, part, np.eye(3))})
    fom = ImplicitEulerSolver(model, SolverSettings())
    a, b = _run(rom, model, 30), _run(fom, model, 30)
    assert fom.stats.n_contacts > 0
    assert np.abs(a.x - b.x).max() < 1e-9
    assert np.abs(a.v - b.v).max() < 1e-6
