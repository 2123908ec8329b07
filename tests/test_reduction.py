"""Reduced model (POD + ECSW): exactness limits, basis and RID construction, artifacts."""

import dataclasses
import math

import numpy as np
import pytest

from softcrawl.fem.body import Body, Cavity, Membrane
from softcrawl.fem.materials import LinearElastic
from softcrawl.fem.model import Attachment, Floor, Model, PointRef
from softcrawl.fem.solver import ImplicitEulerSolver, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.geometry import box_mesh
from softcrawl.reduction.floating import FloatingFrameBody
from softcrawl.reduction.model import PartReduction, ReducedBody, reduce_body
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


def test_reduced_states_carry_their_modal_velocities():
    """A reduced solver's states carry their reduced bodies' modal velocities, and a step starts
    from those (any solver: the state holds them) instead of projecting ``v``; a state without
    them, or with ones of other shapes, is projected (Phi orthonormal: ``Phi^T Phi qdot = qdot``),
    which gives the same step to round-off (1e-9 mm, 1e-6 mm/s)."""
    model = _two_box_model()
    body = model.bodies[0]
    basis = np.linalg.qr(np.random.default_rng(0).standard_normal((3 * body.n_nodes, 30)))[0]
    reduced = {0: reduce_body(body, PartReduction.full(body.mesh, basis, len(body.membrane.triangles)), np.eye(3))}
    rom = ReducedSolver(model, reduced)
    state = _run(rom, model, 10)
    (qd,) = state.modal_velocities
    assert qd.shape == (1, 30) and np.abs(qd).max() > 0.5  # mm/s: it moves
    control = Control(np.array([40.0]))
    kept = rom.step(state, control)
    fresh = ReducedSolver(model, reduced).step(state, control)
    np.testing.assert_array_equal(kept.x, fresh.x)
    # the carried modal velocities are the ones used: scaled 1000x, they move the step's result by
    # ~1e-3 mm (the stiff implicit step keeps little of them), far above the 1e-9 mm of round-off
    scaled = ReducedSolver(model, reduced).step(dataclasses.replace(state, modal_velocities=(1e3 * qd,)), control)
    assert np.abs(scaled.x - kept.x).max() > 1e-5
    projected = ReducedSolver(model, reduced).step(dataclasses.replace(state, modal_velocities=None), control)
    assert np.abs(kept.x - projected.x).max() < 1e-9 and np.abs(kept.v - projected.v).max() < 1e-6
    other = dataclasses.replace(state, modal_velocities=(np.zeros((1, 5)),))
    np.testing.assert_array_equal(ReducedSolver(model, reduced).step(other, control).x, projected.x)


def _rotated_pair(floor=None):
    """Two copies of the soft box (membrane, cavity on channel 0), the second turned 70 degrees
    about z and moved away, both reduced with one part (random orthonormal basis, every
    element): the model, the reduced bodies and the rotation."""
    a = math.radians(70.0)
    Rz = np.array([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
    soft = _two_box_model().bodies[0]
    mesh2 = soft.mesh.transformed(Rz, np.array([60.0, 20.0, 0.0]))
    b2 = Body(mesh2, soft.material, soft.mass, membrane=soft.membrane, cavities=soft.cavities, name="soft2")
    model = Model((soft, b2), floor=floor)
    basis = np.linalg.qr(np.random.default_rng(1).standard_normal((3 * soft.n_nodes, 24)))[0]
    part = PartReduction.full(soft.mesh, basis, len(soft.membrane.triangles))
    return model, {0: reduce_body(soft, part, np.eye(3)), 1: reduce_body(b2, part, Rz)}, Rz


def test_legs_of_one_part_in_different_poses_step_alike():
    """reduction.md: a part placed by R has the basis R Phi (every node's vector rotated); the
    group steps every body in the part frame. Two copies of a body, one turned 70 degrees
    about z (gravity along z), with the pressure on one channel and the nodal forces turned
    with it, follow congruent trajectories (1e-9 mm) with equal modal velocities (1e-9 mm/s)."""
    model, reduced, Rz = _rotated_pair()
    rom = ReducedSolver(model, reduced)
    assert len(rom.groups) == 1 and rom.groups[0].n_bodies == 2
    n = model.bodies[0].n_nodes
    state = model.rest_state()
    forces = np.zeros_like(state.x)
    forces[:n] = [5.0, 0.0, 0.0]
    forces[n:] = Rz @ [5.0, 0.0, 0.0]
    for k in range(20):
        state = rom.step(state, Control(np.array([40.0 * min(1.0, k / 5)]), forces))
    X = model.rest_state().x
    u1, u2 = state.x[:n] - X[:n], state.x[n:] - X[n:]
    assert np.abs(u1).max() > 0.05  # it moved (a random basis: no rigid modes)
    assert np.abs(u2 - u1 @ Rz.T).max() < 1e-9
    assert np.abs(state.modal_velocities[0][0] - state.modal_velocities[0][1]).max() < 1e-9


def test_reduced_body_must_be_the_part_in_the_given_pose():
    model, reduced, Rz = _rotated_pair()
    with pytest.raises(ValueError, match="placed by the given rotation"):
        reduce_body(model.bodies[1], reduced[0].part, np.eye(3))
    with pytest.raises(ValueError, match="rotation"):
        reduce_body(model.bodies[1], reduced[0].part, 2 * Rz)


def test_reduced_element_terms_are_the_projected_full_order_force_and_tangent():
    """Every element at unit weight, a basis with the 3 translations and 20 random modes, a
    rotated body in a deformed pose: the kernels' reduced internal force, stiffness damping and
    tangent equal ``Phi^T f``, ``Phi^T K_t Phi`` of the full-order corotational body (relative
    1e-10: the same element formulas, only summed in another order), the translations are not
    strain modes and get exactly zero internal force and stiffness."""
    from softcrawl.reduction.pod import rigid_modes

    model, _, Rz = _rotated_pair()
    body = model.bodies[1]  # placed by Rz
    soft = model.bodies[0]
    rng = np.random.default_rng(3)
    modes = np.hstack([rigid_modes(soft.mesh.points), rng.standard_normal((3 * soft.n_nodes, 20))])
    basis = np.linalg.qr(modes)[0]
    part = PartReduction.full(soft.mesh, basis, len(soft.membrane.triangles))
    rb = reduce_body(body, part, Rz)
    assert np.array_equal(rb.strain_modes, np.arange(3, 23))
    rom = ReducedSolver(model, {1: rb})
    group = rom.groups[0]
    x = model.rest_state().x.copy()
    sl = model.body_slice(1)
    q = rng.standard_normal(23) * 2.0
    x[sl] += (rb.basis @ q).reshape(-1, 3)  # a large deformation: corotational terms matter
    qdot = rng.standard_normal((1, 23))
    c = 0.11
    f_int, kdata, n_bad = body.internal_forces(x[sl], tangent_coef=1.0)
    assert n_bad == 0
    K = body.pattern.matrix(kdata).toarray()
    Phi = rb.basis
    expect_K = Phi.T @ K @ Phi
    expect_f = Phi.T @ f_int.ravel() - c * expect_K @ qdot[0]
    from softcrawl.reduction.kernels import accumulate_terms, add_strain_terms

    ms = len(group.strain_modes)
    Ks, fs, K_r, f_r = np.zeros((1, ms, ms)), np.zeros((1, ms)), np.zeros((1, 23, 23)), np.zeros((1, 23))
    qs = np.ascontiguousarray(qdot[:, group.strain_modes])
    for fam in group.families:
        rows = fam.factors.shape[1] * len(fam.conn)
        accumulate_terms(x, group.offsets, group.rotations, fam.conn, fam.factors, fam.rest_terms, fam.rows, qs, c,
                         np.empty((1, rows, ms)), np.empty((1, rows)), np.empty(rows), Ks, fs, np.zeros(1, np.int64))
    add_strain_terms(Ks, fs, group.strain_modes, K_r, f_r)
    assert np.abs(K_r[0] - expect_K).max() < 1e-10 * np.abs(expect_K).max()
    assert np.abs(f_r[0] - expect_f).max() < 1e-10 * np.abs(expect_f).max()
    assert not K_r[0, :3].any() and not K_r[0, :, :3].any() and not f_r[0, :3].any()


def test_element_factors_need_translation_blind_stiffness():
    """The edge factors C with D^T C^T C D = K exist only for stiffness matrices that do not
    resist rigid translations; a spring to the ground (K with a translation stiffness) is refused."""
    from softcrawl.reduction.kernels import edge_difference, stiffness_factors

    rng = np.random.default_rng(4)
    D = edge_difference(4)
    A = rng.standard_normal((2, 6, 9))
    K = np.einsum("eij,eik->ejk", A @ D, A @ D)  # rank 6, blind to translations
    C = stiffness_factors(K, 6)
    assert np.allclose(np.einsum("eij,eik->ejk", C @ D, C @ D), K, atol=1e-10 * np.abs(K).max())
    with pytest.raises(ValueError, match="translations"):
        stiffness_factors(K + np.eye(12), 6)  # springs to the ground
    with pytest.raises(ValueError, match="rank 3"):
        stiffness_factors(K, 3)


def test_syrk_updates_the_upper_triangle_only():
    """``syrk_upper`` (BLAS dsyrk bound for compiled code) adds Z^T Z to the upper triangle."""
    from softcrawl.reduction.blas import syrk_upper

    rng = np.random.default_rng(5)
    Z, K0 = rng.standard_normal((40, 7)), rng.standard_normal((7, 7))
    K = K0.copy()
    syrk_upper(Z, K)
    iu = np.triu_indices(7)
    assert np.allclose(K[iu], (K0 + Z.T @ Z)[iu], atol=1e-12)
    assert np.array_equal(np.tril(K, -1), np.tril(K0, -1))
    syrk_upper(Z[:0], K)  # no rows: unchanged
    assert np.allclose(K[iu], (K0 + Z.T @ Z)[iu], atol=1e-12)


def test_floor_candidates_skip_only_nodes_that_cannot_reach_the_floor():
    """The velocity bound |v_n| <= |Phi_n|_F |qdot| lets the contact search skip nodes; the
    candidates must be exactly those of a search over every collision node with its exact
    free velocity, for states moving fast towards the floor."""
    model, reduced, _ = _rotated_pair(Floor(0.0, 0.8, 0.5))
    rom = ReducedSolver(model, reduced)
    group = rom.groups[0]
    rng = np.random.default_rng(2)
    floor, h = model.floor, rom.settings.dt
    for trial in range(5):
        qd = rng.standard_normal((2, group.n_modes)) * 10.0 ** rng.uniform(1, 3)
        x = model.rest_state().x
        x[:, 2] += rng.uniform(-0.2, 3.0)
        nodes, gaps, vz = group.floor_candidates(x, qd, h, floor)
        v = np.zeros_like(x)
        group.velocities(qd, v)
        expect = []
        for o in group.offsets:
            c = group.collision
            gap = x[o + c, 2] - floor.height
            close = np.minimum(gap, gap + h * v[o + c, 2]) < floor.contact_distance
            expect.append(o + c[close])
        expect = np.concatenate(expect)
        assert np.array_equal(np.sort(nodes), np.sort(expect))
        assert np.allclose(vz, v[nodes, 2], atol=1e-9)


# -- POD ------------------------------------------------------------------------------------
from softcrawl.reduction.pod import pod_basis, rigid_modes, truncation_rank  # noqa: E402


def test_truncation_rank_follows_the_tail_energy_rule():
    s = np.array([10.0, 1.0, 0.1, 0.01])
    e = s**2
    for tol in (0.5, 0.05, 0.005, 1e-6):
        m = truncation_rank(s, tol)
        assert np.sqrt(e[m:].sum() / e.sum()) <= tol  # meets the tolerance ...
        assert m == 0 or np.sqrt(e[m - 1:].sum() / e.sum()) > tol  # ... with the fewest modes


def test_pod_basis_is_orthonormal_contains_rigid_modes_and_recovers_the_snapshot_space():
    rng = np.random.default_rng(1)
    points = rng.normal(size=(40, 3)) * 10
    modes = rng.normal(size=(2, 40, 3))
    coef = rng.normal(size=(30, 2)) * [5.0, 1.0]
    shift = rng.normal(size=(30, 1, 3))  # rigid translations in every snapshot
    snaps = np.einsum("sk,knd->snd", coef, modes) + shift
    pod = pod_basis(snaps, points, tol_modes=1e-8)
    B = pod.basis
    assert np.allclose(B.T @ B, np.eye(B.shape[1]), atol=1e-12)
    assert pod.n_rigid == 3 and pod.n_pod == 2  # exactly the 2 deformation modes
    T = rigid_modes(points)
    assert np.allclose(B @ (B.T @ T), T, atol=1e-10)
    S = snaps.reshape(30, -1).T
    assert np.allclose(B @ (B.T @ S), S, atol=1e-9)
    with pytest.raises(ValueError, match="NaN"):
        pod_basis(np.full_like(snaps, np.nan), points, 1e-3)


# -- ECSW -----------------------------------------------------------------------------------
from softcrawl.reduction.ecsw import GramAccumulator, ecsw_weights  # noqa: E402


def test_ecsw_finds_a_sparse_weighting_within_tolerance():
    """Columns that are copies of a few 'representative' elements: ECSW needs only those."""
    rng = np.random.default_rng(2)
    base = rng.normal(size=(200, 5))
    owner = rng.integers(0, 5, size=300)
    G = base[:, owner] * rng.uniform(0.5, 2.0, size=300)
    acc = GramAccumulator(300)
    for rows in np.split(G, 4):  # streamed: 4 blocks of 50 rows
        acc.add(rows.T)
    assert np.allclose(acc.gram, G.T @ G)
    b = G.sum(axis=1)
    for tol in (1e-2, 1e-6):
        res = ecsw_weights(acc.gram, tol)
        assert np.all(res.weights > 0) and len(res.elements) <= 5
        got = np.linalg.norm(G[:, res.elements] @ res.weights - b) / np.linalg.norm(b)
        assert got <= tol * 1.0001 and abs(got - res.relative_residual) < 1e-6


def test_ecsw_on_independent_columns_keeps_what_the_tolerance_needs():
    rng = np.random.default_rng(3)
    G = rng.normal(size=(400, 60)) * np.exp(-np.arange(60) / 6.0)  # decaying column norms
    b = G.sum(axis=1)
    loose, tight = ecsw_weights(G.T @ G, 0.2), ecsw_weights(G.T @ G, 1e-3)
    assert len(loose.elements) < len(tight.elements) <= 60
    for res, tol in ((loose, 0.2), (tight, 1e-3)):
        assert np.linalg.norm(G[:, res.elements] @ res.weights - b) <= tol * np.linalg.norm(b) * 1.0001
    with pytest.raises(ValueError, match="tol_gie"):
        ecsw_weights(G.T @ G, 0.0)


# -- a tiny build end to end: file, checks, accuracy against the full model -----------------
from softcrawl.reduction.artifact import (  # noqa: E402
    ReductionFileError,
    ReductionMismatchError,
    load_reduction,
    save_reduction,
)
from softcrawl.reduction.build import BuildSettings, build_reduction  # noqa: E402
from softcrawl.reduction.scenes import reduced_scene_robot, run_scene, scene_robot  # noqa: E402
from softcrawl.reduction.validate import deformation_error  # noqa: E402
from softcrawl.robot.assembly import REDUCED_DISK_REFACTOR_EVERY, RobotConfig, build_robot  # noqa: E402

TINY = RobotConfig(leg_mesh_size=12.0)
# The tiny build reduces the disk too (not the default) so that both parts' paths are exercised.
TINY_SETTINGS = BuildSettings(n_designs=2, sizes=(3,), state_seconds=0.05, gait_designs=1, gait_seconds=0.05,
                              ecsw_scenes=1, ecsw_every=3, disk=True)


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    work = tmp_path_factory.mktemp("reduce")
    reduction = build_reduction(work, TINY, TINY_SETTINGS, workers=1, progress=False)
    path = save_reduction(work / "tiny.npz", reduction, dataclasses.asdict(TINY))
    return reduction, path, work


def test_tiny_build_is_hyper_reduced_and_resumes_from_saved_runs(tiny):
    reduction, _, work = tiny
    leg, disk = reduction.leg, reduction.disk
    for part, tol_modes in ((leg, TINY_SETTINGS.tol_modes), (disk, TINY_SETTINGS.disk_tol_modes)):
        meta = part.metadata
        assert 0 < len(part.tet_rid) < part.mesh.n_tets / 4  # hyper-reduction keeps a small RID
        assert meta["ecsw_residual"]["tetrahedra"] <= TINY_SETTINGS.tol_gie
        assert meta["tail_energy"] <= tol_modes
    assert disk.n_rigid == 6 and len(disk.tri_rid) == 0 and 0 < len(leg.tri_rid)
    rss = reduction.metadata["peak_rss_mb"]  # reported build memory: at least this process's imports and meshes
    assert 100 < rss["main"] <= rss["with_workers"] < 8192, rss
    runs = {p: p.stat().st_mtime_ns for p in (work / "snapshots").glob("*.npz")}
    again = build_reduction(work, TINY, TINY_SETTINGS, workers=1, progress=False)
    assert runs and {p: p.stat().st_mtime_ns for p in runs} == runs  # snapshot runs reused, none re-run
    assert np.allclose(again.leg.basis, leg.basis) and np.allclose(again.disk.basis, disk.basis)


@pytest.mark.parametrize("disk", ["floating", "corotational", "pod"])
def test_reduced_robot_follows_the_full_model_on_a_training_scene(tiny, disk):
    """The hyper-reduced robot (legs reduced; the disk floating-frame, full-order corotational
    or POD-reduced) vs the full-order robot over the training scene it was built from (legs
    115 mm long, bending by tens of mm), averaged over nodes and frames:
    - deformation error (each body rigidly fitted) below 0.1 mm: what the reduction
      approximates (measured 0.035 / 0.033 / 0.057 mm with the floating / corotational /
      POD disk);
    - raw node error below 1 mm with a full-resolution disk (measured 0.56 mm floating,
      0.63 mm corotational): it also holds the rigid drift of stick-slip contact, which solver
      details alone change by ~0.1-0.5 mm here; below 2 mm with the POD disk (measured
      1.22 mm: its basis stiffens the point ties the legs hang on, see ``BuildSettings.disk``)."""
    full = tiny[0]
    reduction = full if disk == "pod" else dataclasses.replace(full, disk=None)
    config = dataclasses.replace(TINY, reduced_disk="corotational") if disk == "corotational" else TINY
    scene = TINY_SETTINGS.scenes()[0]
    fom_robot = scene_robot(scene, TINY, leg_mesh=full.leg.mesh, disk_mesh_local=full.disk.mesh)
    fom = run_scene(fom_robot, scene.animation)
    rom_robot = reduced_scene_robot(scene, config, reduction)
    kind = {"floating": FloatingFrameBody, "pod": ReducedBody}.get(disk)
    assert (kind is None and 0 not in rom_robot.reduced) or isinstance(rom_robot.reduced[0], kind)
    rom = run_scene(rom_robot, scene.animation)
    assert not fom.diverged and not rom.diverged
    a, b = rom.positions.astype(float), fom.positions.astype(float)
    moved = np.linalg.norm(b - b[:1], axis=2).max()
    err = np.linalg.norm(a - b, axis=2).mean()
    bodies = [fom_robot.model.body_slice(i) for i in range(len(fom_robot.model.bodies))]
    shape = deformation_error(a, b, bodies).mean()
    assert moved > 5.0 and err < (2.0 if disk == "pod" else 1.0) and shape < 0.1, (moved, err, shape)
    # The contact set grows lazily from last step's loaded contacts; no candidate may be left
    # below the floor (1e-6 mm: the solver's gap tolerance is relative, ~1e-9 of the gaps).
    model = fom_robot.model
    candidates = np.concatenate([model.node_offsets[i] + b.collision_nodes for i, b in enumerate(model.bodies)])
    assert a[:, candidates, 2].min() > -1e-6


#: Held-out bound of the tiny reduction (12 mm legs, 17 leg modes, trained on 0.05 s
#: Hamiltonian walks of 3-leg designs) on the baseline gait and six-leg scenes (0.3 s, not in
#: its snapshots): mean node error, mean deformation error (mm) and the baseline scene's reward
#: error (cm; the disk moves 0.215 cm there). Measured 2.31 mm, 0.143 mm and 0.0086 cm; the
#: margins (13%, 12%, 75% of a reward error that is 4% of the motion) absorb BLAS rounding,
#: which moves a stick-slip run by ~0.01 mm here.
HELD_OUT_BOUND = {"mean_node_error_mm": 2.6, "mean_deformation_error_mm": 0.16, "baseline_reward_error_cm": 0.015}


@pytest.fixture(scope="module")
def held_out(tiny, tmp_path_factory):
    """A function from a reduction to its ``HELD_OUT_BOUND`` quantities on the held-out scenes;
    the full-order references are run once for the module."""
    from softcrawl.reduction.scenes import validation_scenes
    from softcrawl.reduction.validate import validate_reduction

    work = tmp_path_factory.mktemp("held_out")
    scenes = tuple(s for s in validation_scenes(0.3) if s.name in ("baseline", "six_leg"))

    def errors(reduction):
        rep = validate_reduction(reduction, TINY, work, scenes=scenes, workers=1, progress=False, ensemble=0)
        baseline = next(r for r in rep["scenes"] if r["scene"] == "baseline")
        return {"mean_node_error_mm": rep["mean_node_error_mm"],
                "mean_deformation_error_mm": rep["mean_deformation_error_mm"],
                "baseline_reward_error_cm": baseline["reward_error_cm"]}

    return errors


def _within_held_out_bound(errors: dict) -> bool:
    return all(errors[k] <= bound for k, bound in HELD_OUT_BOUND.items())


def test_tiny_reduction_is_within_its_held_out_bound(tiny, held_out):
    errors = held_out(tiny[0])
    assert _within_held_out_bound(errors), errors


@pytest.mark.parametrize("mutation", ["one_mode_fewer", "ecsw_weights_x1.1"])
def test_a_degraded_reduction_fails_the_held_out_bound(tiny, held_out, mutation):
    """The bound is tight enough to see a small degradation: the last leg mode dropped
    (measured 3.00 mm node, 0.196 mm deformation error) or the leg's tetrahedron ECSW weights
    10% high (0.171 mm deformation, 0.025 cm baseline reward error)."""
    reduction = tiny[0]
    leg = reduction.leg
    if mutation == "one_mode_fewer":
        leg = dataclasses.replace(leg, basis=leg.basis[:, :-1])
    else:
        leg = dataclasses.replace(leg, tet_weights=1.1 * leg.tet_weights)
    errors = held_out(dataclasses.replace(reduction, leg=leg))
    assert not _within_held_out_bound(errors), errors


def test_deformation_error_removes_rigid_motion_per_body():
    """Closed form: a rigidly moved copy has zero deformation error whatever each body's
    rotation and translation; stretching one body by 1% along a principal axis leaves the
    whole stretch as error (for a cloud with diagonal covariance the best rotation of a
    stretch is the identity)."""
    g = np.stack(np.meshgrid(*[np.array([-1.0, 0.0, 1.0])] * 3, indexing="ij"), -1).reshape(-1, 3)
    x = np.concatenate([g * [20.0, 5.0, 3.0], g * [4.0, 9.0, 2.0] + [50.0, 0.0, 0.0]])[None].repeat(2, 0)
    bodies = [slice(0, 27), slice(27, 54)]
    moved = x.copy()
    for k, sl in enumerate(bodies):
        angle = 0.7 + k
        R = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
        moved[:, sl] = x[:, sl] @ R.T + [10.0 * k, -4.0, 2.0]
    assert np.abs(deformation_error(moved, x, bodies)).max() < 1e-9
    assert np.linalg.norm(moved - x, axis=2).mean() > 5.0
    stretched = x.copy()
    stretched[:, :27, 0] *= 1.01
    got = deformation_error(stretched, x, bodies)
    assert np.allclose(got[:, 27:], 0.0, atol=1e-9)
    assert np.allclose(got[:, :27], 0.01 * np.abs(x[:, :27, 0]), rtol=1e-9, atol=1e-9)


def test_reduction_file_round_trip_and_reduced_config(tiny):
    reduction, path, work = tiny
    loaded, meta = load_reduction(path, expect=dataclasses.asdict(TINY))
    for name, part in reduction.parts.items():
        got = loaded.parts[name]
        assert np.array_equal(got.basis, part.basis) and np.array_equal(got.tet_rid, part.tet_rid)
        assert np.array_equal(got.mesh.points, part.mesh.points)
        assert got.mesh.node_sets.keys() == part.mesh.node_sets.keys()
        assert meta["parts"][name]["n_modes"] == part.n_modes
    assert meta["software_version"] and meta["build"]["settings"]["disk"]
    robot = build_robot((1, 0, 0, 2, 2, 0, 0, 1), dataclasses.replace(TINY, model="reduced", reduction=str(path)))
    solver = robot.make_solver()
    assert sorted(robot.reduced) == [0, 1, 2, 3, 4] and solver.__class__.__name__ == "ReducedSolver"
    # With a leg-only reduction the disk is a floating-frame body, or the full-order
    # corotational one on request.
    legs_only = save_reduction(work / "legs_only.npz", dataclasses.replace(reduction, disk=None),
                               dataclasses.asdict(TINY))
    config = dataclasses.replace(TINY, model="reduced", reduction=str(legs_only))
    robot = build_robot((1, 0, 0, 2, 2, 0, 0, 1), config)
    assert sorted(robot.reduced) == [0, 1, 2, 3, 4] and isinstance(robot.reduced[0], FloatingFrameBody)
    assert robot.make_solver().settings.refactor_every == 1
    robot = build_robot((1, 0, 0, 2, 2, 0, 0, 1), dataclasses.replace(config, reduced_disk="corotational"))
    assert sorted(robot.reduced) == [1, 2, 3, 4]
    # Factorization reuse defaults by model: the reduced model's corotational disk 5, the full model exact.
    assert robot.make_solver().settings.refactor_every == REDUCED_DISK_REFACTOR_EVERY > 1
    assert build_robot((1, 0, 0, 2, 2, 0, 0, 1), TINY).make_solver().settings.refactor_every == 1
    with pytest.raises(ValueError, match="reduced_disk"):
        RobotConfig(reduced_disk="rigid")


def test_corrupt_missing_and_mismatched_reduction_files_are_rejected(tiny, tmp_path):
    _, path, _ = tiny
    with pytest.raises(ReductionFileError, match="does not exist"):
        load_reduction(tmp_path / "none.npz")
    garbage = tmp_path / "garbage.npz"
    garbage.write_bytes(b"not a zip file")
    with pytest.raises(ReductionFileError, match="cannot read"):
        load_reduction(garbage)
    # Same metadata, one basis entry changed: the checksum catches it.
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    data["disk__basis"] = data["disk__basis"].copy()
    data["disk__basis"][0, 0] += 1e-6
    tampered = tmp_path / "tampered.npz"
    np.savez(tampered, **data)
    with pytest.raises(ReductionFileError, match="corrupt"):
        load_reduction(tampered)
    # A file of the first format (one leg part, no part prefixes) is refused with a rebuild hint.
    import json

    meta = json.loads(data["metadata"].tobytes().decode())
    meta["format_version"] = 1
    data["metadata"] = np.frombuffer(json.dumps(meta).encode(), np.uint8)
    np.savez(tampered, **data)
    with pytest.raises(ReductionFileError, match="version 1.*rebuild"):
        load_reduction(tampered)
    with pytest.raises(ReductionMismatchError, match="leg_mesh_size"):
        load_reduction(path, expect=dataclasses.asdict(dataclasses.replace(TINY, leg_mesh_size=6.0)))
    with pytest.raises(ReductionMismatchError, match="leg_mass"):
        build_robot((1, 0, 0, 2, 2, 0, 0, 1),
                    dataclasses.replace(TINY, model="reduced", reduction=str(path), leg_mass=0.2))
    with pytest.raises(ReductionMismatchError, match="disk_mesh_size"):  # a disk part binds the disk mesh too
        build_robot((1, 0, 0, 2, 2, 0, 0, 1),
                    dataclasses.replace(TINY, model="reduced", reduction=str(path), disk_mesh_size=25.0))


# -- the shipped default reduction -----------------------------------------------------------
def test_shipped_reduction_loads_and_simulates_the_baseline(tmp_path, monkeypatch, capsys):
    """The default 6 mm leg reduction ships in the package, is intact, and `softcrawl simulate`
    uses it by default; a leg mesh it was not built for is refused with a clear error."""
    import json

    from softcrawl import cli
    from softcrawl.reduction.data import default_reduction_path

    reduction, meta = load_reduction(default_reduction_path(), expect=dataclasses.asdict(RobotConfig()))
    part = reduction.leg
    assert meta["valid_for"]["leg_mesh_size"] == 6.0 and part.n_modes == meta["parts"]["leg"]["n_modes"] >= 10
    assert 0 < len(part.tet_rid) < part.mesh.n_tets / 10
    assert reduction.disk is None  # the shipped default keeps every disk node (BuildSettings.disk)
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("softcrawl.cli.simulate",))
    out = tmp_path / "rom"
    rc = cli.main(["simulate", "--duration", "0.2", "--frames-every", "10", "--no-progress", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    s = json.loads((out / "summary.json").read_text())
    assert s["model"] == "reduced" and s["steps"] == 20 and math.isfinite(s["reward_cm"])
    assert s["config"]["reduced_disk"] == "floating"
    rc = cli.main(["simulate", "--duration", "0.05", "--reduced-disk", "corotational", "--no-progress",
                   "--out", str(tmp_path / "corotational")])
    assert rc == 0 and json.loads((tmp_path / "corotational" / "summary.json").read_text())["config"]["reduced_disk"] \
        == "corotational"
    rc = cli.main(["simulate", "--mesh-size", "8", "--duration", "0.1", "--no-progress", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert rc == 2 and "leg_mesh_size" in err and "--model full" in err and not (tmp_path / "x").exists()


@pytest.fixture(scope="module")
def shipped_references(tmp_path_factory):
    """A folder for the exact full-order runs of the 4 held-out scenes (4 s each), shared by
    both settings below."""
    return tmp_path_factory.mktemp("shipped_validation")


@pytest.mark.slow
@pytest.mark.parametrize("settings, node_bound", [
    ({}, 0.88),
    ({"reduced_dt": 0.02, "rid_dtype": "float32", "contact_max_iterations": 100}, 1.0),
], ids=["reference", "training"])
def test_shipped_reduction_meets_its_documented_held_out_errors(shipped_references, settings, node_bound):
    """``softcrawl reduce validate`` on the shipped reduction (the paper's 4 held-out scenes, 4 s,
    against the exact full-order model at dt 0.01 s), as docs/results.md reports it:

    - reference settings (0.01 s, float64 RID products, 250 sweeps): documented mean node error
      0.793 mm and baseline reward error 1.1% (measured 0.792 mm, 1.04%); bound 0.88 mm (10%
      margin);
    - training settings (``--dt 0.02 --rid-dtype float32 --contact-max-iterations 100``):
      documented 0.955 mm and 0.3% (measured 0.943 mm, 1.08%); bound 1.0 mm (the target; 6%
      margin).

    Reward error within 2% in both: over 15 round-off-perturbed reduced runs of the baseline
    scene the documented reward error ranges 1.3-1.7% (the reduced model's own sensitivity),
    so a single run is bounded by that range with margin. 680 s of CPU, nearly all in the
    full-order runs (about 6 min on 2 idle cores): slow; command and result in
    docs/results.md."""
    from softcrawl.reduction.data import default_reduction_path
    from softcrawl.reduction.validate import validate_reduction

    config = RobotConfig()
    reduction, _ = load_reduction(default_reduction_path(), expect=dataclasses.asdict(config))
    rep = validate_reduction(reduction, config, shipped_references, workers=2, progress=False, ensemble=0,
                             **settings)
    baseline = next(r for r in rep["scenes"] if r["scene"] == "baseline")
    reward_error = baseline["reward_error_cm"] / abs(baseline["reward_full_cm"])
    summary = (rep["mean_node_error_mm"], reward_error, [r["mean_node_error_mm"] for r in rep["scenes"]])
    print("shipped reduction", settings or "reference", summary)
    assert rep["mean_node_error_mm"] <= node_bound and reward_error <= 0.02, summary


def test_validation_report_shows_floor_and_grid_plot(tmp_path):
    """The Markdown table carries the deformation error, the chaos floor and the full
    ensemble's reward range; the grid figure is written from the grid rows."""
    from softcrawl.cli.reduce import _markdown, _plot_grid

    row = {"scene": "baseline", "mean_node_error_mm": 1.5, "max_node_error_mm": 9.0,
           "mean_deformation_error_mm": 0.1, "mean_trajectory_error_mm": 1.4, "reward_full_cm": -1.15,
           "reward_reduced_cm": -1.0, "seconds_per_step_full": 0.3, "seconds_per_step_reduced": 0.02,
           "floor_mean_node_error_mm": 1.42, "floor_mean_deformation_error_mm": 0.06,
           "ensemble_rewards_cm": [-1.15, -0.9, -1.3], "reward_in_ensemble": True,
           "reduced_ensemble_rewards_cm": [-1.0, -1.2, -0.95], "reduced_spread_mm": 0.25}
    text = _markdown({"scenes": [row], "ensemble": 2, "perturbation_mm": 1e-6})
    assert ("| baseline | 1.500 | 9.00 | 0.100 | 1.400 | 1.420 / 0.060 | -1.150 | -1.300 .. -0.900 | -1.000 (inside) "
            "| -1.200 .. -0.950 | 0.250 |") in text and "Chaos floor" in text and "1e-06 mm" in text
    plain = {k: v for k, v in row.items() if not k.startswith(("floor_", "ensemble_", "reward_in", "reduced_"))}
    assert "floor" not in _markdown({"scenes": [plain]})
    rows = [dict(plain, tol_modes=tm, tol_gie=tg, mean_seconds_per_step_reduced=0.01 * (i + 1))
            for i, (tm, tg) in enumerate([(0.01, 0.01), (0.01, 0.001), (0.001, 0.01)])]
    _plot_grid(tmp_path / "grid.png", rows)
    assert (tmp_path / "grid.png").stat().st_size > 10_000


def test_crawling_training_scenes_hold_out_the_validation_designs():
    """Crawling scenes (BuildSettings.gait_designs): distinct 3- and 4-leg slot sets, none a
    validation design's, legs on regulators 1, 2, 3, 1 in slot order, sine gaits; they come after
    the Gray-code walks and make up half of the ECSW training scenes."""
    from softcrawl.reduction.build import BuildSettings
    from softcrawl.reduction.scenes import gait_scenes, validation_scenes

    scenes = gait_scenes(6)
    slots = [sc.slots for sc in scenes]
    assert len(set(slots)) == 6 and [len(s) for s in slots] == [3, 4, 3, 4, 3, 4]
    assert not set(slots) & {sc.slots for sc in validation_scenes()}
    assert all([c for _, c in sc.legs] == [i % 3 for i in range(len(sc.legs))] for sc in scenes)
    assert [sc.name for sc in gait_scenes(6)] == [sc.name for sc in scenes]  # seeded
    settings = BuildSettings(gait_designs=4)
    names = [sc.name for sc in settings.scenes()]
    assert names[:8] == [sc.name for sc in BuildSettings(gait_designs=0).scenes()] and names[8:] == [sc.name for sc in gait_scenes(4)]
    assert [sc.name for sc in settings.ecsw_training_scenes()] == names[:2] + names[8:10]
    with pytest.raises(ValueError):
        gait_scenes(-1)


def test_validation_ensemble_reports_the_chaos_floor(tiny, tmp_path):
    """A short held-out scene with 2 perturbed full-order runs (1e-6 mm): each keeps its own
    saved settings, their distance to the reference stays far below the reduced model's error
    (1e-3 mm: the exact model is not chaotic at round-off scale), and the report carries the 3
    full-order rewards and whether the reduced one lies among them. The reduced model is more
    sensitive (a round-off-sized change can flip which of a flat-landing leg's nearly equally
    deep nodes start its contact set: under 0.01 mm on this scene on one machine, 0.016 mm on
    another with other BLAS rounding), but its spread must stay below 2% of its error against the exact
    model, or that error would measure chaos rather than the reduction."""
    import json

    from softcrawl.reduction.scenes import validation_scenes
    from softcrawl.reduction.validate import validate_reduction

    reduction, _, _ = tiny
    scenes = validation_scenes(0.1)[1:2]
    rep = validate_reduction(reduction, TINY, tmp_path, scenes=scenes, workers=1, progress=False, ensemble=2)
    row = rep["scenes"][0]
    assert len(row["ensemble_rewards_cm"]) == 3 and row["ensemble_rewards_cm"][0] == row["reward_full_cm"]
    assert rep["floor_mean_node_error_mm"] < 1e-3 < rep["mean_node_error_mm"]
    assert isinstance(row["reward_in_ensemble"], bool)
    rewards, errors = row["reduced_ensemble_rewards_cm"], row["reduced_ensemble_node_errors_mm"]
    assert len(rewards) == len(errors) == 3 and rewards[0] == row["reward_reduced_cm"]
    assert errors[0] == row["mean_node_error_mm"] and 0 < row["reduced_spread_mm"] < 0.02 * row["mean_node_error_mm"]
    saved = json.loads((tmp_path / "perturbed2" / "baseline.json").read_text())
    assert saved["perturbation"] == {"amplitude_mm": 1e-6, "seed": 2}
    assert "perturbation" not in json.loads((tmp_path / "reference" / "baseline.json").read_text())


def test_a_reduced_run_that_diverges_fails_its_scene(tiny, tmp_path, monkeypatch):
    """Regression: a reduced run that diverged while settling (no frame recorded) crashed
    ``reduce validate`` (IndexError), and one that diverged later was scored on its frames
    before the divergence. Now the scene reports the divergence with infinite errors and no
    reduced reward, the means are infinite, and an ensemble is not run for it."""
    from softcrawl.reduction import validate
    from softcrawl.reduction.scenes import validation_scenes

    reduction, _, _ = tiny
    scenes = validation_scenes(0.1)[1:2]
    real = validate.run_scene

    def diverging(robot, animation, **kw):
        rec = real(robot, animation, **kw)
        return dataclasses.replace(rec, positions=rec.positions[:0], diverged="node speed exceeds the limit")

    monkeypatch.setattr(validate, "run_scene", diverging)
    rep = validate.validate_reduction(reduction, TINY, tmp_path, scenes=scenes, workers=1, progress=False,
                                      ensemble=1)
    row = rep["scenes"][0]
    assert row["diverged"] and row["frames"] == 0 and np.isnan(row["reward_reduced_cm"])
    assert rep["mean_node_error_mm"] == row["max_node_error_mm"] == np.inf
    assert "reduced_ensemble_rewards_cm" not in row


def test_validation_ensemble_needs_a_perturbation(tiny):
    """An ensemble without a positive perturbation would repeat the reference: refused."""
    from softcrawl.reduction.validate import validate_reduction

    reduction, _, work = tiny
    with pytest.raises(ValueError, match="perturbation"):
        validate_reduction(reduction, TINY, work, ensemble=2, perturbation=0.0, progress=False)


def test_validation_on_the_jax_engine(tiny, tmp_path, capsys):
    """``reduce validate --engine jax``: the same held-out scene (0.1 s of the baseline gait after
    settling) against the same exact full-order reference, the reduced side stepped by the JAX
    engine (floating disk, float64): the report and its table name the engine, and its mean node
    error is the CPU engine's within 0.1 mm (measured 0.221 against 0.235 mm; the engines' rested
    states differ by about 0.1 mm, test_jaxsim_robot's settling test). An ensemble (no JAX
    perturbed runs) is refused, through the CLI with one line and exit code 2."""
    jax = pytest.importorskip("jax")
    from softcrawl import cli
    from softcrawl.cli.reduce import _markdown
    from softcrawl.reduction.scenes import validation_scenes
    from softcrawl.reduction.validate import validate_reduction

    reduction = dataclasses.replace(tiny[0], disk=None)  # the floating disk the JAX engine steps
    scenes = validation_scenes(0.1)[1:2]
    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    try:
        rep = {engine: validate_reduction(reduction, TINY, tmp_path, scenes=scenes, workers=1, progress=False,
                                          ensemble=0, engine=engine) for engine in ("cpu", "jax")}
    finally:
        jax.config.update("jax_enable_x64", old)
    row = rep["jax"]["scenes"][0]
    assert rep["jax"]["engine"] == row["engine"] == "jax" and rep["cpu"]["engine"] == "cpu" and not row["diverged"]
    assert row["frames"] == rep["cpu"]["scenes"][0]["frames"] > 5
    assert _markdown(rep["jax"]).startswith("Reduced runs on the jax engine.")
    err = {k: r["mean_node_error_mm"] for k, r in rep.items()}
    assert err["jax"] > 0 and abs(err["jax"] - err["cpu"]) < 0.1, err
    with pytest.raises(ValueError, match="ensemble"):
        validate_reduction(reduction, TINY, tmp_path, scenes=scenes, ensemble=1, engine="jax", progress=False)
    rc = cli.main(["reduce", "validate", "--engine", "jax", "--ensemble", "2", "--workdir", str(tmp_path / "w"),
                   "--out", str(tmp_path / "out"), "--no-progress"])
    assert rc == 2 and "ensemble" in capsys.readouterr().err


def test_perturbed_reduced_run_stays_in_its_basis_range(tiny):
    """A perturbed reduced robot gets the noise's projection on each POD-reduced body's basis,
    so its nodes stay in ``X + range(Phi)`` (5e-5 mm: the float32 precision of recorded positions
    near 100 mm), and it does move off the unperturbed run."""
    from softcrawl.reduction.model import ReducedBody
    from softcrawl.reduction.scenes import reduced_scene_robot, run_scene, training_scenes

    reduction, _, _ = tiny
    scene = training_scenes(1, (1,))[0]
    robot = reduced_scene_robot(scene, TINY, reduction)
    base = run_scene(robot, scene.animation, duration=0.02).positions[0].astype(float)
    moved = run_scene(robot, scene.animation, duration=0.02, perturbation=1e-3, seed=1).positions[0].astype(float)
    assert np.abs(moved - base).max() > 1e-6
    X = robot.model.rest_state().x
    for i, body in robot.reduced.items():
        if isinstance(body, ReducedBody):
            u = (moved - X)[robot.model.body_slice(i)].ravel()
            assert np.abs(u - body.basis @ (body.basis.T @ u)).max() < 5e-5


def test_saved_runs_with_tuple_parameters_are_reused(tmp_path, monkeypatch):
    """Regression: settings holding tuples (AlternatingAnimation.groups) never compared equal
    to their JSON copy, so the two-leg and six-leg validation references re-ran every time."""
    from softcrawl.reduction import runs
    from softcrawl.reduction.animations import AlternatingAnimation
    from softcrawl.reduction.scenes import Scene

    scene = Scene("alt", ((0, 0), (4, 1)), AlternatingAnimation(groups=((0,), (1,)), duration=0.02))
    calls = []
    monkeypatch.setattr(runs, "run_pool", lambda fn, workers, todo, done: calls.append(len(todo)))
    path = tmp_path / "alt.npz"
    path.write_bytes(b"")
    settings = runs._settings(scene, TINY, "reference", 2)
    path.with_suffix(".json").write_text(__import__("json").dumps(settings), encoding="utf-8")
    runs.run_fom_scenes(tmp_path, [scene], TINY, "reference", record_every=2, workers=1, progress=False)
    assert calls == [0]
    # A field only the reduced model reads does not invalidate full-order runs (regression:
    # adding RobotConfig.reduced_disk re-ran every saved reference); a full-order one does.
    corotational = dataclasses.replace(TINY, reduced_disk="corotational")
    runs.run_fom_scenes(tmp_path, [scene], corotational, "reference", record_every=2, workers=1, progress=False)
    runs.run_fom_scenes(tmp_path, [scene], dataclasses.replace(TINY, friction=0.9), "reference", record_every=2,
                        workers=1, progress=False)
    assert calls == [0, 0, 1]
    # A field added later matches runs saved before it at the value they used (250 sweeps), and
    # only there (regression: adding RobotConfig.contact_max_iterations re-ran every reference).
    saved = {k: v for k, v in settings["config"].items() if k not in runs.LATER_FIELDS}
    path.with_suffix(".json").write_text(__import__("json").dumps({**settings, "config": saved}), encoding="utf-8")
    runs.run_fom_scenes(tmp_path, [scene], TINY, "reference", record_every=2, workers=1, progress=False)
    runs.run_fom_scenes(tmp_path, [scene], dataclasses.replace(TINY, contact_max_iterations=100), "reference",
                        record_every=2, workers=1, progress=False)
    assert calls == [0, 0, 1, 0, 1]


def test_validation_compares_a_larger_reduced_step_at_the_reference_frames():
    """``reduce validate --dt``: a reduced step that divides the references' 0.02 s frame
    spacing is recorded every few steps against every reference frame; one that is a multiple
    of it (0.04 s, the time-step study) is recorded every step against every other
    reference frame, so the frames compared fall on the same times; any other step is
    refused."""
    from softcrawl.reduction.validate import _reduced_recording
    from softcrawl.robot import RobotConfig

    cfg = RobotConfig(model="reduced", dt=0.01)
    for dt, every, stride in ((None, 2, 1), (0.005, 4, 1), (0.02, 1, 1), (0.04, 1, 2), (0.1, 1, 5)):
        reduced, e, s = _reduced_recording(cfg, 2, dt, "float32")
        assert (reduced.dt, e, s, reduced.rid_dtype) == (dt or 0.01, every, stride, "float32")
        assert math.isclose(reduced.dt * e, 0.02 * s)
    for dt in (0.03, 0.015, -0.04):
        with pytest.raises(ValueError, match="divide or be a multiple"):
            _reduced_recording(cfg, 2, dt)
