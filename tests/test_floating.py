"""Floating-frame body (the reduced robot's disk): closed-form invariances, the constraint
and agreement with the corotational full-order body."""

import numpy as np

from softcrawl.fem.body import Body
from softcrawl.fem.materials import LinearElastic
from softcrawl.fem.model import Floor, Model
from softcrawl.fem.solver import ImplicitEulerSolver, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.geometry import box_mesh
from softcrawl.reduction.floating import FloatingFrameBody, rigid_fit_rotation
from softcrawl.reduction.solver import ReducedSolver
from softcrawl.reduction.validate import deformation_error


def _rotation(axis, angle_deg: float) -> np.ndarray:
    """Rodrigues' formula."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    a = np.radians(angle_deg)
    return np.eye(3) + np.sin(a) * K + (1 - np.cos(a)) * K @ K


Q = _rotation([1.0, 2.0, 0.5], 70.0)


def _beam_model(rotation=np.eye(3), gravity=(0.0, 0.0, 0.0), floor=None) -> Model:
    """A stiff 40 x 8 x 6 mm beam (the disk's printed polymer, E = 5,000 kPa), posed by ``rotation``."""
    mesh = box_mesh((40.0, 8.0, 6.0), (8, 2, 2), origin=(-20.0, -4.0, 1.0)).transformed(rotation, np.zeros(3))
    return Model((Body(mesh, LinearElastic(5000.0, 0.3), 0.02, name="beam"),), gravity=gravity, floor=floor)


def _bending_forces(model: Model, rotation=np.eye(3)) -> np.ndarray:
    """Balanced three-point bending loads (mN): -z at both ends, +2z in the middle (beam frame)."""
    X = model.bodies[0].mesh.points @ rotation  # beam-frame coordinates
    f = np.zeros_like(X)
    for x0, fz in ((-20.0, -40.0), (20.0, -40.0), (0.0, 80.0)):
        at = np.isclose(X[:, 0], x0)
        f[at, 2] = fz / at.sum()
    return f @ rotation.T


def _run(solver, model, forces, steps=40):
    state = model.rest_state()
    for _ in range(steps):
        state = solver.step(state, Control(np.zeros(model.n_channels), forces))
    return state


def test_rigid_fit_recovers_a_rotation_exactly():
    rng = np.random.default_rng(0)
    X = rng.normal(size=(30, 3)) * [20.0, 5.0, 3.0]
    w = rng.uniform(0.5, 1.5, 30)
    w /= w.sum()
    Xc = X - w @ X
    assert np.abs(rigid_fit_rotation(X @ Q.T + [5.0, -3.0, 7.0], Xc, w) - Q).max() < 1e-12


def test_rigid_motion_gives_no_elastic_force():
    """verification.md, corotational invariance: a rigidly rotated (70 deg) body translating
    and spinning has zero elastic force and its rigid velocity lies in the null space of
    ``K_0`` (rotated), so with no gravity and no floor one step only damps it by the Rayleigh
    mass term: ``v' = v / (1 + h r_M)`` (round-off: 1e-9 relative)."""
    model = _beam_model(Q)
    body = model.bodies[0]
    solver = ReducedSolver(model, {0: FloatingFrameBody(body)})
    state = model.rest_state()
    x = state.x + [3.0, -2.0, 1.0]
    omega = np.array([0.3, -1.1, 0.7])  # rad/s
    v = np.cross(omega, x - x.mean(0)) + [10.0, 5.0, -2.0]
    new = solver.step(type(state)(x=x, v=v, t=0.0, contact_nodes=state.contact_nodes,
                                  contact_impulses=state.contact_impulses), Control(np.zeros(model.n_channels)))
    expected = v / (1 + solver.settings.dt * model.rayleigh_mass)
    assert np.abs(new.v - expected).max() < 1e-9 * np.abs(v).max()


def test_rotated_loaded_body_responds_as_the_unrotated_one_rotated():
    """verification.md: the same bending loads on the beam posed by a 70 deg rotation give
    the unrotated response rotated (1e-9 mm over 40 steps)."""
    a_model, b_model = _beam_model(), _beam_model(Q)
    a = _run(ReducedSolver(a_model, {0: FloatingFrameBody(a_model.bodies[0])}), a_model, _bending_forces(a_model))
    b = _run(ReducedSolver(b_model, {0: FloatingFrameBody(b_model.bodies[0])}), b_model, _bending_forces(b_model, Q), )
    assert np.abs(a.x @ Q.T - b.x).max() < 1e-9


def test_floating_body_deforms_as_the_corotational_body_at_small_strain():
    """The beam bending under its loads, posed by the 70 deg rotation, over 20 steps
    (deformation 0.035 mm): one floating frame instead of one per element deforms it as the
    corotational body does, to 1% of the deformation (measured 0.5%; shapes compared after
    a rigid fit). Later the two part: the dead loads on the deformed beam have a torque of
    second order (0.5 mN mm), which turns the corotational beam (0.6 deg by step 20, 12 deg
    by step 80, when the loads are no longer square to it) while the linear floating body,
    whose torque balance uses its rest shape, does not turn. On the robot's disk (attachment
    loads ~1e2 mN at 50 mm arms, deformation ~1e-2 mm) that torque is ~1e-4 of the loads' own."""
    model = _beam_model(Q)
    f = _bending_forces(model, Q)
    fl = _run(ReducedSolver(model, {0: FloatingFrameBody(model.bodies[0])}), model, f, steps=20)
    co = _run(ImplicitEulerSolver(model, SolverSettings()), model, f, steps=20)
    X = model.rest_state().x
    deformation = deformation_error(co.x[None], X[None], [slice(None)]).max()
    assert deformation > 0.03
    assert deformation_error(fl.x[None], co.x[None], [slice(None)]).max() < 0.01 * deformation


def test_floating_body_rests_on_the_floor_with_its_weight():
    """verification.md, resting contact: the rotated-in-plane beam dropped on the floor settles
    with the summed normal force equal to its weight m g (1e-6 relative) and no node below
    the contact distance."""
    Rz = _rotation([0.0, 0.0, 1.0], 30.0)
    model = _beam_model(Rz, gravity=(0.0, 0.0, -9800.0), floor=Floor(0.0, 1.2, 0.5))
    solver = ReducedSolver(model, {0: FloatingFrameBody(model.bodies[0])})
    state = _run(solver, model, None, steps=60)
    weight = model.bodies[0].mass * 9800.0
    assert abs(solver.stats.normal_force - weight) < 1e-6 * weight
    assert state.x[:, 2].min() > -0.5
