"""FEM engine against closed-form physics (verification.md) and on bad input.

Tolerances are stated per test. The closed-form checks of ``softcrawl.verify.checks``, their
convergence and their mutations are in ``tests/test_closed_form.py``.
"""

import numpy as np
import pytest

from softcrawl.fem.body import Body, Cavity, Membrane
from softcrawl.fem.materials import LinearElastic
from softcrawl.fem.model import Floor, Model
from softcrawl.fem.pressure import enclosed_volume, pressure_forces
from softcrawl.fem.solver import ImplicitEulerSolver, SimulationDiverged, SolverSettings
from softcrawl.fem.state import Control, State
from softcrawl.geometry import PneuNetParams, box_mesh, pneunet_mesh
from softcrawl.geometry.mesh import MeshError, TetMesh
from softcrawl.verify import checks


def test_membrane_uniform_stretch_matches_plane_stress():
    """A 1 mm paper layer stretched by strain e along x: the edge force equals
    E t H e / (1 - nu^2) (plane stress with eps_yy = 0 imposed)."""
    mat, t, e = LinearElastic(2320.0, 0.49), 1.0, 1e-3
    mesh = box_mesh((20.0, 10.0, 2.0), (4, 2, 1))
    bottom = mesh.surfaces["boundary"][np.all(np.isclose(mesh.points[mesh.surfaces["boundary"], 2], 0.0), axis=1)]
    body = Body(mesh, LinearElastic(1e-6, 0.0), 1e-3, membrane=Membrane(bottom, mat, t))
    x = mesh.points.copy()
    x[:, 0] *= 1 + e
    f, _, _ = body.internal_forces(x)
    edge = np.isclose(mesh.points[:, 0], 20.0) & np.isclose(mesh.points[:, 2], 0.0)
    expected = -mat.youngs_modulus * t * 10.0 * e / (1 - mat.poisson_ratio**2)
    assert f[edge, 0].sum() == pytest.approx(expected, rel=1e-3)  # tets contribute E = 1e-6 only


def test_membrane_rigid_rotation_gives_zero_force():
    mesh = box_mesh((20.0, 10.0, 2.0), (4, 2, 1))
    body = Body(mesh, LinearElastic(1.0, 0.3), 1e-3,
                membrane=Membrane(mesh.surfaces["boundary"], LinearElastic(2320.0, 0.49), 1.0))
    R = checks._rotation([0.3, -1.0, 2.0], 123.0)
    f, _, _ = body.internal_forces(mesh.points @ R.T + 4.0)
    assert np.abs(f).max() < 1e-10 * 2320.0


def test_cavity_pressure_is_p_dV_dx():
    """Follower load = p dV/dx (finite differences of the enclosed volume) and sums to zero."""
    mesh = pneunet_mesh(PneuNetParams(mesh_size=10.0))
    cav = mesh.surfaces["cavity"]
    assert enclosed_volume(mesh.points, cav) == pytest.approx(3528.0, rel=1e-9)
    rng = np.random.default_rng(0)
    x = mesh.points + rng.normal(scale=0.2, size=mesh.points.shape)
    f = pressure_forces(x, cav, 50.0)
    assert np.abs(f.sum(0)).max() < 1e-9 * np.abs(f).max()
    dx = rng.normal(size=x.shape) * 1e-4
    dV = enclosed_volume(x + dx, cav) - enclosed_volume(x - dx, cav)
    assert np.sum(f * 2 * dx) == pytest.approx(50.0 * dV, rel=1e-6)


def test_bad_material_and_settings_raise():
    with pytest.raises(ValueError, match="Young"):
        LinearElastic(0.0, 0.3)
    with pytest.raises(ValueError, match="Young"):
        LinearElastic(-5.0, 0.3)
    for nu in (0.5, -1.0, 0.7, float("nan")):
        with pytest.raises(ValueError, match="Poisson"):
            LinearElastic(100.0, nu)
    with pytest.raises(ValueError, match="dt"):
        SolverSettings(dt=-0.01)
    with pytest.raises(ValueError, match="finite"):
        Control(np.array([10.0, np.nan]))
    with pytest.raises(ValueError, match="mass"):
        Body(box_mesh(), LinearElastic(1.0, 0.3), mass=0.0)
    with pytest.raises(ValueError, match="friction"):
        Floor(friction=-1.0)


def test_inverted_mesh_is_rejected():
    mesh = box_mesh((1.0, 1.0, 1.0), (1, 1, 1))
    tets = mesh.tets.copy()
    tets[0, [1, 2]] = tets[0, [2, 1]]
    with pytest.raises(MeshError, match="inverted"):
        TetMesh(mesh.points, tets)


def _falling_block():
    body = Body(box_mesh((10.0, 10.0, 5.0), (2, 2, 1)), LinearElastic(1e4, 0.3), 0.01)
    return Model((body,), floor=Floor())


def test_diverged_state_is_reported_not_propagated():
    model = _falling_block()
    solver = ImplicitEulerSolver(model)
    rest = model.rest_state()
    bad = State(rest.x.copy(), rest.v.copy())
    bad.v[0, 0] = np.nan
    with pytest.raises(SimulationDiverged, match="non-finite"):
        solver.step(bad, Control(np.zeros(1)))
    inverted = rest.x.copy()
    inverted[:, 2] *= -1.0  # mirror: every element inverted
    with pytest.raises(SimulationDiverged, match="inverted"):
        solver.step(State(inverted + [0, 0, 10.0], rest.v), Control(np.zeros(1)))
    with pytest.raises(ValueError, match="channels"):
        solver.step(rest, Control(np.zeros(2)))


def test_pressurised_cavity_inflates_dynamically():
    """A free PneuNet under pressure: cavity volume grows, the step stays finite."""
    mesh = pneunet_mesh(PneuNetParams(mesh_size=10.0))
    body = Body(mesh, LinearElastic(1160.0, 0.2), 0.105, cavities=(Cavity(mesh.surfaces["cavity"], 0),))
    model = Model((body,), gravity=(0.0, 0.0, 0.0))
    solver = ImplicitEulerSolver(model)
    state = model.rest_state()
    for _ in range(10):
        state = solver.step(state, Control(np.array([50.0])))
    assert enclosed_volume(state.x, mesh.surfaces["cavity"]) > 3528.0 * 1.01


def test_factorization_multi_rhs_and_reuse():
    """Multi-RHS LDL^T solves and factorization-preconditioned CG match a direct solve."""
    import scipy.sparse as sp

    from softcrawl.fem.linalg import Factorization, ReusedFactorization

    rng = np.random.default_rng(1)
    n = 300
    R = sp.random(n, n, density=0.02, random_state=2)
    A = (R @ R.T + sp.eye(n) * 5).tocsr()
    B = rng.normal(size=(n, 7))
    X = Factorization(A).solve(B)
    assert np.abs(A @ X - B).max() < 1e-10
    A2 = (A + sp.diags(rng.uniform(0, 0.5, n))).tocsr()  # a slightly different matrix
    reuse = ReusedFactorization(max_age=3, rtol=1e-12)
    reuse.solve(A, B[:, 0])
    x = reuse.solve(A2, B[:, 1])  # kept factorization of A preconditions CG on A2
    assert reuse.factorizations == 1 and reuse.cg_iterations > 0
    assert np.linalg.norm(A2 @ x - B[:, 1]) < 1e-10 * np.linalg.norm(B[:, 1])


@pytest.mark.parametrize("floating", [False, True])
def test_compliance_blocks_give_the_dense_delassus_operator(floating):
    """Attachment rows kept as one compliance column per row (FixedRows), contact nodes as one
    column per DOF, and 3 x 3 block coefficients reproduce the dense ``W = H A^-1 H^T``,
    ``H v`` and ``A^-1 H^T lam`` to round-off (1e-9 relative): with a fixed DOF for a
    full-order body, and for a floating-frame body (``A = R A_0 R^T`` blockwise, the
    compliance of ``A_0`` with ``rotation = R``)."""
    import scipy.sparse as sp

    from softcrawl.fem.constraints import FixedRows, NodalCompliance, add_body, body_correction
    from softcrawl.fem.linalg import Factorization

    rng = np.random.default_rng(3)
    n = 40  # nodes
    S = sp.random(3 * n, 3 * n, density=0.05, random_state=4)
    A0 = (S @ S.T + sp.eye(3 * n) * 3).tolil()
    free = np.ones(3 * n, bool)
    Q = np.eye(3)
    if floating:
        Q = np.linalg.qr(rng.normal(size=(3, 3)))[0] * np.array([1.0, 1.0, -1.0])
        Q *= np.sign(np.linalg.det(Q))
        A = (sp.block_diag([Q] * n) @ A0 @ sp.block_diag([Q] * n).T).toarray()
    else:
        free[5] = False  # fixed DOF: identity row and column, zero compliance
        A0[5, :], A0[:, 5] = 0.0, 0.0
        A0[5, 5] = 1.0
        A = A0.toarray()
    # Global rows: 2 attachment blocks of another body first, then 3 of this body over 4-6
    # nodes each (isotropic weights), then 2 contacts with general coefficients.
    Hatt = np.zeros((15, 3 * (n + 10)))
    for j, k in zip((2, 3, 4), (4, 6, 5)):
        for node, w in zip(rng.choice(n, k, replace=False), rng.normal(size=k)):
            Hatt[3 * j:3 * j + 3, 3 * (10 + node):3 * (10 + node) + 3] += w * np.eye(3)
    Hatt[:6, :30] = rng.normal(size=(6, 30))
    fixed = FixedRows.of_body(sp.csr_matrix(Hatt), 10, n)
    assert fixed.blocks.tolist() == [2, 3, 4]
    nodes, coefs = np.array([1, 11]), rng.normal(size=(2, 3, 3))  # node 1 holds DOF 5
    H = np.zeros((21, 3 * n))
    H[:15] = Hatt[:, 30:]
    for k, (node, c) in enumerate(zip(nodes, coefs)):
        H[15 + 3 * k:18 + 3 * k, 3 * node:3 * node + 3] = c
    H[:, ~free] = 0.0
    Ainv = np.linalg.inv(A)
    Ainv[~free] = Ainv[:, ~free] = 0.0
    v = rng.normal(size=(n, 3))
    v[1, 2] = 0.0 if not floating else v[1, 2]  # a fixed DOF does not move
    lam = rng.normal(size=21)
    lam[:6] = 0.0  # blocks of the other body
    c = NodalCompliance(Factorization(A0.tocsr()), free, fixed)
    c.rotation = Q
    W, u = np.zeros((21, 21)), np.zeros(21)
    bb = add_body(W, u, c, v, nodes, coefs, np.array([5, 6]))
    dv = body_correction(c, lam, bb)
    ref = H @ Ainv @ H.T
    assert np.abs(W - ref).max() < 1e-9 * np.abs(ref).max()
    assert np.abs(u - H @ v.ravel()).max() < 1e-9 * np.abs(H @ v.ravel()).max()
    assert np.abs(dv.ravel() - Ainv @ H.T @ lam).max() < 1e-9 * np.abs(Ainv @ H.T @ lam).max()


@pytest.mark.skipif("not os.path.exists('/proc/self/statm')", reason="needs Linux /proc")
def test_refactorizing_does_not_leak_memory():
    """Regression: the cholespy backend leaked the last solve's workspace of every freed
    solver (~n k 8 bytes; 14 GB over one 20 s robot episode). Measured on the resident set now
    (Linux ``/proc/self/statm``), not the process's high-water mark: in a test session an earlier
    test's peak would hide any growth."""
    import os

    import scipy.sparse as sp

    from softcrawl.fem.linalg import ReusedFactorization

    n = 8000
    A = sp.diags([np.full(n, 4.0), np.full(n - 1, -1.0), np.full(n - 1, -1.0)], [0, -1, 1]).tocsr()
    lin = ReusedFactorization(max_age=1)

    def cycle():
        lin.solve(A, np.ones(n))
        lin.factor.solve(np.ones((n, 30)))

    for _ in range(20):
        cycle()
    def rss_mb() -> float:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20

    before = rss_mb()
    for _ in range(200):
        cycle()
    grown_mb = rss_mb() - before
    assert grown_mb < 20.0  # the leak grew ~380 MB here


def test_model_channel_count():
    mesh = pneunet_mesh(PneuNetParams(mesh_size=10.0))
    body = Body(mesh, LinearElastic(1160.0, 0.2), 0.105, cavities=(Cavity(mesh.surfaces["cavity"], 1),))
    assert Model((body,)).n_channels == 2
    assert Model((body,), channels=3).n_channels == 3
    with pytest.raises(ValueError, match="channels"):
        Model((body,), channels=1)


def _slip_angles(L, U):
    """Angle (rad) between each row's friction ``L[:, 1:]`` and the opposite of its slip
    ``-U[:, 1:]``; atan2 of cross and dot products keeps round-off-sized angles exact (an
    arccos of the cosine loses them below ~1e-8 rad)."""
    a, b = L[:, 1:], -U[:, 1:]
    return np.arctan2(np.abs(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]), np.einsum("ij,ij->i", a, b))


def _assert_contact_conditions(L, U, mu, tol, slip_angle=1e-6):
    """Signorini and Coulomb for impulses ``L`` and velocities ``U`` ``(k, 3)`` (normal first);
    a slipping contact's friction must be antiparallel to its slip within ``slip_angle`` rad
    (default: the polish's stopping tolerance, ``contact.DIRECTION_TOLERANCE``, 1e-6 rad)."""
    lt, ut = np.hypot(L[:, 1], L[:, 2]), np.hypot(U[:, 1], U[:, 2])
    assert np.all(L[:, 0] >= -tol) and np.all(U[:, 0] >= -tol)
    assert np.all(np.abs(L[:, 0] * U[:, 0]) <= tol * max(1.0, np.abs(U).max()))
    assert np.all(lt <= mu * L[:, 0] + tol)
    inside = lt < mu * L[:, 0] - tol
    assert np.all(ut[inside] <= tol)
    slip = (L[:, 0] > tol) & ~inside & (ut > tol)
    angles = _slip_angles(L[slip], U[slip])
    assert np.all(angles <= slip_angle), angles.max()  # maximal dissipation: friction opposes slip


def _random_contact_problem(rng, k_min: int, k_max: int):
    """``(W, q, mu)``: an SPD Delassus operator of k_min..k_max-1 contacts, random free
    velocities, mu = 0.5."""
    k = int(rng.integers(k_min, k_max))
    B = rng.standard_normal((3 * k, 3 * k))
    return B @ B.T / (3 * k) + 0.05 * np.eye(3 * k), rng.standard_normal(3 * k), np.full(k, 0.5)


def _polished(W, q, mu, tol, sweeps):
    """Impulses polished from Gauss-Seidel run from zero (``tol``, ``sweeps``), or None."""
    from softcrawl.fem.contact import pgs_coulomb, polish_active_set

    lam = np.zeros(len(q))
    pgs_coulomb(W, q, mu, lam, tol, sweeps)
    return polish_active_set(W, q, mu, lam)


@pytest.mark.parametrize("seed", range(4))
def test_contact_solution_satisfies_signorini_and_coulomb(seed):
    """Random Delassus operators (SPD, 1-10 contacts, mu = 0.5): the polished impulses
    satisfy every condition of the frictional contact problem (contact.py docstring) to
    1e-8 relative: lam_n >= 0, u_n >= 0, lam_n u_n = 0, |lam_t| <= mu lam_n, u_t = 0 inside
    the cone and u_t antiparallel to lam_t on it within 1e-6 rad (the polish's direction
    tolerance; measured at most 7.5e-7 rad over 228 slipping contacts). (Gauss-Seidel alone
    stops at 1e-8 in the impulses; the active-set polish makes these hold to round-off.)"""
    rng = np.random.default_rng(seed)
    solved = 0
    for _ in range(25):
        W, q, mu = _random_contact_problem(rng, 1, 11)
        k = len(mu)
        out = _polished(W, q, mu, 1e-6, 100)
        if out is None:
            continue
        solved += 1
        _assert_contact_conditions(out.reshape(k, 3), (W @ out + q).reshape(k, 3), mu,
                                   1e-8 * max(1.0, np.abs(q).max(), np.abs(out).max()))
    assert solved >= 20  # the polish must succeed from a converged Gauss-Seidel start


def test_ill_conditioned_contact_problem_is_solved_exactly():
    """Regression: 4 attachments and 7 floor contacts of a reduced leg, recorded from a tiny
    reduced run (condensed Delassus condition number 1.3e5). 250 Gauss-Seidel sweeps
    neither converged (relative change 6e-4) nor gave the polish a consistent active set,
    and a contact ended 6.5e-5 mm below the floor. The extra sweep chunks let the polish
    find the solution: attachments, Signorini and the cone hold to 1e-9 relative; the slip
    directions, kept from the Gauss-Seidel iterate, oppose the slip to within 0.5 degrees
    (8.7e-3 rad)."""
    from pathlib import Path

    from softcrawl.fem.contact import solve_constraints

    z = np.load(Path(__file__).parent / "data" / "ill_conditioned_contact.npz")
    W, q, nb, mu = z["W"], z["q"], int(z["n_bilateral_rows"]), z["mu"]
    sol = solve_constraints(W, q, nb, mu, z["warm_start"], 1e-8, 250)
    assert sol.polished and 250 < sol.sweeps <= 250 * 9
    lam = np.concatenate([sol.bilateral, sol.contact.ravel()])
    u = W @ lam + q
    tol = 1e-9 * max(np.abs(q).max(), np.abs(lam).max())
    assert np.abs(u[:nb]).max() <= tol
    _assert_contact_conditions(sol.contact, u[nb:].reshape(-1, 3), mu, tol, slip_angle=np.radians(0.5))


@pytest.mark.parametrize("seed", range(3))
def test_polish_from_last_step_turns_friction_against_the_slip(seed):
    """Regression: polishing from last step's impulses kept their friction directions, so a
    slipping contact's friction could be up to 90 degrees off its slip (measured on a
    reduced crawl: median 57 degrees). Solved exactly once, then the free velocities change
    as between two steps; polished from the old impulses, the friction of every slipping
    contact must again oppose its slip within 1e-6 rad (measured at most 6.0e-7 rad over 197
    slipping contacts) with all other conditions to 1e-8."""
    from softcrawl.fem.contact import polish_active_set

    rng = np.random.default_rng(10 + seed)
    checked = 0
    for _ in range(30):
        W, q, mu = _random_contact_problem(rng, 2, 9)
        k = len(mu)
        before = _polished(W, q, mu, 1e-12, 5000)
        if before is None:
            continue
        q2 = q + 0.2 * rng.standard_normal(3 * k) * np.tile([0.0, 1.0, 1.0], k)  # tangential change
        out = polish_active_set(W, q2, mu, before)
        if out is None:
            continue
        U, L = (W @ out + q2).reshape(k, 3), out.reshape(k, 3)
        slipping = (L[:, 0] > 0) & (np.hypot(U[:, 1], U[:, 2]) > 1e-6)
        checked += int(slipping.sum())
        _assert_contact_conditions(L, U, mu, 1e-8 * max(1.0, np.abs(q2).max(), np.abs(out).max()))
    assert checked >= 10


def test_slip_direction_check_sees_a_friction_turned_by_2e_6_rad():
    """The 1e-6 rad bound of ``_assert_contact_conditions`` is not vacuous: on a solved
    problem, the friction of each slipping contact turned by 2e-6 rad (its magnitude kept)
    fails it, and the angle helper reads the turn back to 1e-9 rad."""
    rng = np.random.default_rng(10)
    for _ in range(30):
        W, q, mu = _random_contact_problem(rng, 2, 9)
        out = _polished(W, q, mu, 1e-12, 5000)
        if out is None:
            continue
        L, U = out.reshape(-1, 3), (W @ out + q).reshape(-1, 3)
        slipping = (L[:, 0] > 1e-8) & (np.hypot(L[:, 1], L[:, 2]) >= mu * L[:, 0] - 1e-8) & (np.hypot(U[:, 1], U[:, 2]) > 1e-8)
        if slipping.any():
            break
    c, s = np.cos(2e-6), np.sin(2e-6)
    turned = L.copy()
    turned[slipping, 1:] = L[slipping, 1:] @ np.array([[c, s], [-s, c]])
    tol = 1e-8 * max(1.0, np.abs(q).max(), np.abs(out).max())
    _assert_contact_conditions(L, U, mu, tol)
    assert np.abs(_slip_angles(turned[slipping], U[slipping]) - _slip_angles(L[slipping], U[slipping])).max() \
        == pytest.approx(2e-6, abs=1e-9)
    with pytest.raises(AssertionError):
        _assert_contact_conditions(turned, U, mu, tol)


def test_polish_does_not_cycle_on_a_reduced_leg_contact_problem():
    """Regression: 8 floor contacts of a reduced crawl (condensed Delassus operator, condition
    number 1e5), warm-started from last step's impulses. Switching every violated contact in
    every round cycled for 12 rounds (then Gauss-Seidel ran 250+ sweeps); switching only the
    worst one after the first round finds the consistent pattern from the warm start, and
    its impulses satisfy Signorini and Coulomb to 1e-9 relative."""
    from pathlib import Path

    from softcrawl.fem.contact import polish_active_set

    z = np.load(Path(__file__).parent / "data" / "cycling_contact.npz")
    W, q, mu = z["W"], z["q"], z["mu"]
    out = polish_active_set(W, q, mu, z["warm_start"].ravel().copy())
    assert out is not None
    tol = 1e-9 * max(np.abs(q).max(), np.abs(out).max())
    _assert_contact_conditions(out.reshape(-1, 3), (W @ out + q).reshape(-1, 3), mu, tol)


@pytest.mark.parametrize("case", ["failing", "found"])
def test_polish_stops_at_a_repeated_state_with_the_result_of_running_out_of_rounds(monkeypatch, case):
    """Regression (contact time): a failing active-set polish used to run all 30 of
    its rounds, one dense solve each, though from round 1 on a round depends only on the
    stick/slip pattern, the slip directions and the alignment count, so a repeated state
    repeats until the limit. Two condensed problems of a 24-robot training batch (12 contacts
    of 5- and 6-legged robots, warm-started from last step's impulses) whose polish repeats
    a state: it now stops at the repeat, in fewer rounds, with exactly the result of running
    out of rounds (``failing``: no consistent pattern; ``found``: the consistent solution met
    before a slip alignment changed the pattern), compiled and in Python alike."""
    from pathlib import Path

    import softcrawl.fem.contact as contact

    z = np.load(Path(__file__).parent / "data" / "repeating_polish.npz")
    W, q, mu, warm = (z[f"{case}_{key}"] for key in ("W", "q", "mu", "warm_start"))
    real, checks = contact._seen_before, []
    monkeypatch.setattr(contact, "_seen_before", lambda *a: checks.append(real(*a)) or checks[-1])
    stopped = contact.polish_kernel.py_func(W, q, mu, warm.copy(), 30, 1e-9)
    assert checks[-1] and len(checks) < 29  # stopped at a repeat
    monkeypatch.setattr(contact, "_seen_before", lambda *a: False)
    full = contact.polish_kernel.py_func(W, q, mu, warm.copy(), 30, 1e-9)
    compiled = contact.polish_kernel(W, q, mu, warm.copy(), 30, 1e-9)
    assert stopped[0] == full[0] == compiled[0] == (case == "found")
    if case == "found":
        np.testing.assert_array_equal(stopped[1], full[1])
        np.testing.assert_array_equal(compiled[1], full[1])


def test_first_touch_starts_from_the_deepest_contacts_and_still_keeps_every_node_out_of_the_floor():
    """Regression: with no contact loaded, the contact set started from *every* candidate whose
    free motion penetrates (a reduced leg landing flat: up to 258 contacts on a Delassus operator
    of rank 210, where Gauss-Seidel runs to its sweep limit). It now starts from the
    ``MIN_CONTACT_GROWTH`` deepest and grows by the ones the solve leaves below the floor. The
    paper-best robot lowered 0.3 mm into the floor at rest (21 nodes penetrate, ~130 are within
    the contact distance): the first step's set stays small (the old rule: 135 contacts) and no
    collision node ends the step below the floor by more than 2 um (the exact Signorini
    solution is >= 0; the remainder is the contact solver's tolerance on this ill-conditioned
    problem, also 1 um with the old rule)."""
    import dataclasses

    from softcrawl.fem.solver import MIN_CONTACT_GROWTH
    from softcrawl.robot import RobotConfig, build_robot

    robot = build_robot((1, 0, 0, 2, 2, 0, 0, 0), RobotConfig(model="reduced", dt=0.02))
    m = robot.model
    rest = m.rest_state()
    coll = np.concatenate([m.node_offsets[i] + b.collision_nodes for i, b in enumerate(m.bodies)])
    x = rest.x.copy()
    x[:, 2] -= x[coll, 2].min() - m.floor.height + 0.3
    assert np.sum(x[coll, 2] < m.floor.height) > MIN_CONTACT_GROWTH
    new = robot.make_solver().step(dataclasses.replace(rest, x=x, v=np.zeros_like(x)), robot.control(np.zeros(3)))
    assert len(new.contact_nodes) <= 2 * MIN_CONTACT_GROWTH
    assert (new.x[coll, 2] - m.floor.height).min() >= -2e-3
