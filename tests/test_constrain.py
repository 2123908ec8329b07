"""The compiled constraint stage of reduced robots (softcrawl.reduction.constrain) and the
single-precision RID terms: each against the double-precision / Python reference it replaces."""

import dataclasses

import numpy as np
import pytest

from softcrawl.reduction.constrain import DiskColumns
from softcrawl.reduction.kernels import accumulate_terms, accumulate_terms32
from softcrawl.robot import RobotConfig, build_robot
from softcrawl.robot.episode import settle

DESIGN = (1, 0, 2, 0, 3, 0, 1, 0)  # 4 legs on 3 regulators


@pytest.fixture(scope="module")
def crawling():
    """A reduced robot after settling and 0.4 s of pressure (legs bent, several floor contacts)."""
    robot = build_robot(DESIGN, RobotConfig(model="reduced", dt=0.02))
    state = settle(robot).state
    solver = robot.make_solver()
    for k in range(20):
        state = solver.step(state, robot.control(60.0 * np.array([1.0, 0.5, 0.0]) * min(1.0, k / 10)))
    assert len(state.contact_nodes) >= 4
    return robot, state


def test_compiled_constraint_stage_matches_the_python_one(crawling):
    """One step from the same state through the compiled stage and through the solver's Python
    constraint code (the full solver's, with the reduced rows): the same contact set and the
    same velocities to 1e-9 of the largest speed. Both solve the same problems by the same
    rules; only the order of round-off differs (the disk's compliance block is symmetrised, the
    bilateral Schur complement uses another Cholesky routine), and the polish solves each
    contact problem exactly, so the difference stays at round-off."""
    from softcrawl.fem.solver import ImplicitEulerSolver

    robot, state = crawling
    control = robot.control(np.array([60.0, 30.0, 0.0]))
    compiled = robot.make_solver()
    python = robot.make_solver()
    python._constrain = lambda st, vf: ImplicitEulerSolver._constrain(python, st, vf)
    a, b = compiled.step(state, control), python.step(state, control)
    assert compiled._compiled and compiled.stats.n_contacts == python.stats.n_contacts
    np.testing.assert_array_equal(a.contact_nodes, b.contact_nodes)
    scale = np.abs(b.v).max()
    assert np.abs(a.v - b.v).max() <= 1e-9 * scale
    assert np.abs(a.contact_impulses - b.contact_impulses).max() <= 1e-9 * np.abs(b.contact_impulses).max()


def test_the_sweep_limit_reaches_the_solver_and_is_checked(crawling):
    """``RobotConfig.contact_max_iterations`` is the solver's Gauss-Seidel limit: a step with a
    limit of 1 stops its sweeps there (the sweep count of a step is at most limit x (1 + extra
    chunks)), and a bad limit is refused."""
    from softcrawl.fem.contact import EXTRA_SWEEP_CHUNKS

    robot, state = crawling
    one = build_robot(DESIGN, dataclasses.replace(robot.config, contact_max_iterations=1))
    solver = one.make_solver()
    assert solver.settings.contact_max_iterations == 1
    control = robot.control(np.array([60.0, 30.0, 0.0]))
    st = state
    for _ in range(5):
        st = solver.step(st, control)
        assert solver.stats.contact_sweeps <= 1 + EXTRA_SWEEP_CHUNKS
    for bad in (0, 1.5, True):
        with pytest.raises(ValueError, match="contact_max_iterations"):
            RobotConfig(model="reduced", contact_max_iterations=bad)


def test_disk_columns_do_not_depend_on_the_order_designs_arrive(crawling):
    """Two processes that meet the attachment blocks in different orders give every robot the
    same attachment block ``T`` to the bit (each entry comes from its own pair of blocks), so a
    design's trajectory does not depend on which designs a worker met before."""
    robot, _ = crawling
    c = robot.make_solver().compliance[robot.disk_body]
    H = c.fixed.H
    blocks = [H[3 * b:3 * b + 3] for b in range(H.shape[0] // 3)]
    one = DiskColumns(c.factor, robot.model.bodies[robot.disk_body].collision_nodes)
    two = DiskColumns(c.factor, robot.model.bodies[robot.disk_body].collision_nodes)
    import scipy.sparse as sp

    ia = one.block_columns(H)
    two.block_columns(sp.vstack(blocks[::-1]).tocsr())  # the same blocks, reversed
    ib = two.block_columns(H)
    np.testing.assert_array_equal(one.attachment_gram(ia), two.attachment_gram(ib))
    # and T is that of the dense compliance: E^T A^-1 E
    E = H.toarray().T
    ref = E.T @ c.factor.solve(E)
    assert np.abs(one.attachment_gram(ia) - ref).max() <= 1e-12 * np.abs(ref).max()


def test_single_precision_rid_terms_agree_with_double_precision(crawling):
    """``accumulate_terms32`` (float32 ``Z``, ``ssyrk``) against ``accumulate_terms`` on a bent
    robot's legs: ``K_r`` and ``f_r`` agree to 2e-6 of their largest entries. Single precision
    rounds each product to 6e-8 relative; a ``K_r`` entry sums ~2,000 of them (the RID rows),
    so sqrt(2000) x 6e-8 = 3e-6 bounds the random round-off (measured: ~3e-7)."""
    robot, state = crawling
    g = robot.make_solver().groups[0]
    L, ms = g.n_bodies, len(g.strain_modes)
    rows = 64 * 6
    qs = np.random.default_rng(0).normal(0.0, 1.0, (L, ms))
    K64, f64, K32, f32 = np.zeros((L, ms, ms)), np.zeros((L, ms)), np.zeros((L, ms, ms), np.float32), np.zeros((L, ms))
    for f in g.families:
        accumulate_terms(state.x, g.offsets, g.rotations, f.conn, f.factors, f.rest_terms, f.rows, qs, 0.12,
                         np.empty((L, rows, ms)), np.empty((L, rows)), np.empty(rows), K64, f64, np.zeros(L, np.int64))
        accumulate_terms32(state.x, g.offsets, g.rotations, f.conn, f.factors, f.rest_terms,
                           f.rows.astype(np.float32), qs, 0.12, np.empty((L, rows, ms), np.float32),
                           np.empty((L, rows)), K32, f32, np.zeros(L, np.int64))
    iu = np.triu_indices(ms)
    assert np.abs(K64[:, iu[0], iu[1]] - K32[:, iu[0], iu[1]]).max() <= 2e-6 * np.abs(K64).max()
    assert np.abs(f64 - f32).max() <= 2e-6 * np.abs(f64).max()


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_a_legs_rid_terms_do_not_depend_on_the_other_legs_of_its_block(crawling, dtype):
    """A batch puts each robot's legs at other places of the RID kernels' body blocks than the
    robot's own solver does; the terms of a leg must come out bit for bit the same wherever it
    sits, or batched and single-robot trajectories part (regression: with one ``sgemm`` per
    element for all bodies of a block, a leg's float32 ``K_r`` changed in its last bits with its
    place, and a batched robot left its own trajectory by 0.6 mm in 140 steps)."""
    robot, state = crawling
    g = robot.make_solver().groups[0]
    ms, rows = len(g.strain_modes), 64 * 6

    def terms(bodies):
        L = len(bodies)
        qs = np.random.default_rng(0).normal(0.0, 1.0, (g.n_bodies, ms))[bodies]
        K, f = np.zeros((L, ms, ms), dtype), np.zeros((L, ms))
        for fam in g.families:
            args = (state.x, g.offsets[bodies], g.rotations[bodies], fam.conn, fam.factors, fam.rest_terms)
            if dtype == np.float32:
                accumulate_terms32(*args, fam.rows.astype(np.float32), qs, 0.12, np.empty((L, rows, ms), dtype),
                                   np.empty((L, rows)), K, f, np.zeros(L, np.int64))
            else:
                accumulate_terms(*args, fam.rows, qs, 0.12, np.empty((L, rows, ms)), np.empty((L, rows)),
                                 np.empty(rows), K, f, np.zeros(L, np.int64))
        return K, f

    alone = terms([1])
    for block in ([0, 1], [2, 0, 3, 1], [1, 1, 1]):
        K, f = terms(block)
        j = block.index(1)
        np.testing.assert_array_equal(K[j], alone[0][0])
        np.testing.assert_array_equal(f[j], alone[1][0])


def test_robot_config_rejects_an_unknown_precision():
    with pytest.raises(ValueError, match="rid_dtype"):
        RobotConfig(model="reduced", rid_dtype="float16")
    with pytest.raises(ValueError, match="rid_dtype"):
        dataclasses.replace(RobotConfig(), rid_dtype="half")


def test_schur_solves_equal_column_by_column_substitution_to_the_bit():
    """The Schur complement's triangular solves (:func:`_cholesky_solve_many`) run row by row
    over all right-hand sides (vectorised); each entry must still be reduced in the
    order of column-by-column forward and back substitution, so the constraint stage's
    impulses stay the same to the bit. Checked against that substitution in plain Python
    (IEEE double, no fused multiply-add) on a recorded attachment block (60 rows, of a 5-legged robot
    in a training batch) and its 37 right-hand sides, and against LAPACK to 1e-9 relative
    (its condition number is 5.6e4)."""
    from pathlib import Path

    from softcrawl.reduction.constrain import _cholesky_solve_many

    z = np.load(Path(__file__).parent / "data" / "repeating_polish.npz")
    W, q, nb = z["schur_W"], z["schur_q"], int(z["schur_nb"])
    L = np.linalg.cholesky(W[:nb, :nb])
    B = np.column_stack([q[:nb], W[:nb, nb:]])
    n, k = B.shape
    ref = [[float(v) for v in row] for row in B]
    for c in range(k):
        for i in range(n):
            acc = ref[i][c]
            for j in range(i):
                acc -= float(L[i, j]) * ref[j][c]
            ref[i][c] = acc / float(L[i, i])
        for i in range(n - 1, -1, -1):
            acc = ref[i][c]
            for j in range(i + 1, n):
                acc -= float(L[j, i]) * ref[j][c]
            ref[i][c] = acc / float(L[i, i])
    out = _cholesky_solve_many(L, B)
    np.testing.assert_array_equal(out, np.array(ref))
    np.testing.assert_allclose(out, np.linalg.solve(W[:nb, :nb], B), rtol=0, atol=1e-9 * np.abs(out).max())


def test_leg_delassus_blocks_are_the_projected_compliance():
    """:func:`add_delassus` (the legs' share of the Delassus operator, its forward substitution
    vectorised over the constraint columns) adds ``J_b A_b^-1 J_b^T`` of every body
    and ``J_b qdot_b`` at the bodies' global blocks, ``J_b`` its attachment rows and its
    contacts' rows ``F R_b Phi[n]``: checked against the dense formula (two bodies of 7 modes,
    one attachment block each, three contacts) to 1e-12 relative."""
    from softcrawl.reduction.kernels import add_delassus

    rng = np.random.default_rng(3)
    L, m, n_nodes = 2, 7, 5
    basis = rng.standard_normal((3 * n_nodes, m))
    fixed_rows = rng.standard_normal((L, 3, m))
    fixed_blocks = np.array([[0], [1]])
    frame_rot = np.stack([np.linalg.qr(rng.standard_normal((3, 3)))[0] for _ in range(L)])
    A = [(lambda B: B @ B.T + m * np.eye(m))(rng.standard_normal((m, m))) for _ in range(L)]
    chol = np.stack([np.linalg.cholesky(a) for a in A])
    qdot = rng.standard_normal((L, m))
    c_body, c_node, c_block = np.array([0, 1, 0]), np.array([1, 2, 4]), np.array([2, 3, 4])
    W, u = np.zeros((15, 15)), np.zeros(15)
    add_delassus(W, u, chol, qdot, fixed_rows, fixed_blocks, frame_rot, basis, c_body, c_node, c_block)
    W_ref, u_ref = np.zeros((15, 15)), np.zeros(15)
    for b in range(L):
        rows = [fixed_rows[b]] + [frame_rot[b] @ basis[3 * n:3 * n + 3] for c, n in zip(c_body, c_node) if c == b]
        blocks = [fixed_blocks[b, 0]] + [k for c, k in zip(c_body, c_block) if c == b]
        J = np.vstack(rows)
        idx = np.concatenate([3 * k + np.arange(3) for k in blocks])
        W_ref[np.ix_(idx, idx)] += J @ np.linalg.solve(A[b], J.T)
        u_ref[idx] += J @ qdot[b]
    np.testing.assert_allclose(W, W_ref, rtol=0, atol=1e-12 * np.abs(W_ref).max())
    np.testing.assert_allclose(u, u_ref, rtol=0, atol=1e-12 * np.abs(u_ref).max())


def test_coarse_leg_contact_points_are_the_same_in_every_leg_and_hold_the_robot_up():
    """``RobotConfig.leg_collision_spacing``: every leg gets the same spaced subset of its surface
    nodes (the legs share one reduced part), a bad spacing is refused, and the robot still
    stands on its contact points. At 4 mm (the spacing that passes ``reduce validate``), after
    settling and 1 s of rising pressure no leg node is more than 0.1 mm below the floor
    (measured 0.05 mm; 0.02 mm with every surface node), and the disk's travel stays within
    0.2 mm of the reference's (measured 0.05 mm)."""
    reference = build_robot(DESIGN, RobotConfig(model="reduced", dt=0.02, contact_max_iterations=100))
    coarse = build_robot(DESIGN, dataclasses.replace(reference.config, leg_collision_spacing=4.0))
    legs = [coarse.model.bodies[b] for b in coarse.leg_bodies]
    full = reference.model.bodies[reference.leg_bodies[0]].collision_nodes
    assert 100 < len(legs[0].collision_nodes) < len(full) / 2 and np.isin(legs[0].collision_nodes, full).all()
    for leg in legs[1:]:
        np.testing.assert_array_equal(leg.collision_nodes, legs[0].collision_nodes)
    x_end = []
    for robot in (reference, coarse):
        state = settle(robot).state
        solver = robot.make_solver()
        lowest = np.inf
        for k in range(50):
            state = solver.step(state, robot.control(60.0 * np.array([1.0, 0.5, 0.0]) * min(1.0, k / 10)))
            lowest = min(lowest, min(state.x[robot.model.body_slice(b), 2].min() for b in robot.leg_bodies))
        assert lowest > -0.1
        x_end.append(state.x[robot.reward_node, 0])
    assert abs(x_end[1] - x_end[0]) < 0.2
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="leg_collision_spacing"):
            RobotConfig(model="reduced", leg_collision_spacing=bad)
