"""The JAX engine's block-sparse Delassus assembly and attachment elimination
(:mod:`softcrawl.jaxsim.delassus`) against the dense formulas, and the sequential cost of its step
(:mod:`softcrawl.jaxsim.cost`). Float64 (``jax_enable_x64`` switched on for this module)."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from functools import partial
from pathlib import Path

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _float64(x64):
    """Every test of this module in float64 (``x64``: tests/conftest.py)."""


@pytest.fixture(scope="module")
def landed():
    """A 4-legged robot of the paper's space in a 6-slot model (two slots masked), landed and
    pressed on the floor (30 steps at dt 0.02 s): ``(model, state, sim kPa)`` of one robot."""
    from softcrawl.jaxsim.engine import Control, make_rollout, rest_state
    from softcrawl.jaxsim.model import build_model
    from softcrawl.robot import RobotConfig, build_robot

    robot = build_robot("1,0,2,0,1,0,3,0", RobotConfig(model="reduced", dt=0.02, disk_mesh_size=25))
    model = build_model([robot], n_slots=6)
    state = make_rollout(30)(model, rest_state(model), Control(jnp.asarray([[60.0, 30.0, 90.0]])))
    one = dataclasses.replace(model, robot=jax.tree_util.tree_map(lambda a: a[0], model.robot))
    return one, jax.tree_util.tree_map(lambda a: a[0], state), jnp.asarray([150.0, 60.0, 90.0])


def _step_rows(landed, R=None):
    """The next step's free motion and constraint rows of the ``landed`` robot at its pressures:
    ``(model, rows, inv_chol, qd_free, R)`` (:mod:`softcrawl.jaxsim.delassus`); ``R`` given: the
    rows with that disk frame instead of the disk's own."""
    from softcrawl.jaxsim import disk as disk_motion
    from softcrawl.jaxsim import legs as leg_motion
    from softcrawl.jaxsim.delassus import constraint_rows

    model, state, kpa = landed
    rd = model.robot
    qd_free, inv_chol, _ = jax.vmap(leg_motion.free_motion, in_axes=(None, None, 0, 0, 0, 0, 0))(
        model.leg, model.settings, state.q, state.qdot, rd.rotation, kpa[rd.channel] * rd.leg_mask, rd.leg_mask)
    v_free, R_disk = disk_motion.free_motion(model.disk, model.settings, state.x, state.v)
    R = R_disk if R is None else jnp.asarray(R)
    return model, constraint_rows(model, state, v_free, qd_free, R), inv_chol, qd_free, R


def _step_matrix(inv_chol):
    """A leg's step matrix ``A = C C^T`` from the inverse ``C^-1`` of its Cholesky factor
    (:func:`softcrawl.jaxsim.legs.free_motion`'s; that it inverts the CPU kernels' factor is
    tests/test_jaxsim_robot.py's)."""
    C = np.linalg.inv(np.asarray(inv_chol))
    return C @ C.T


def _dense(rows, inv_chol, qd_free):
    """The full Delassus operator and free velocities of ``rows``, summed densely: each leg's
    ``J_l A_l^-1 J_l^T`` placed at its attachment and contact rows (solved with ``A_l``),
    plus the disk's blocks."""
    L, n_leg, m = rows.leg.shape
    F3 = rows.u_att.shape[0] // L
    Kd3 = rows.disk_dd.shape[0]
    nb, nc = L * F3, Kd3 + L * (n_leg - F3)
    W = np.zeros((nb + nc, nb + nc))
    u = np.zeros(nb + nc)
    W[:nb, :nb] = rows.disk_aa
    W[:nb, nb:nb + Kd3] = rows.disk_ad
    W[nb:nb + Kd3, :nb] = np.asarray(rows.disk_ad).T
    W[nb:nb + Kd3, nb:nb + Kd3] = rows.disk_dd
    u[:nb], u[nb:nb + Kd3] = rows.u_att, rows.u_disk
    for leg in range(L):
        A = _step_matrix(inv_chol[leg])
        J = np.asarray(rows.leg[leg])
        idx = np.concatenate([leg * F3 + np.arange(F3), nb + Kd3 + leg * (n_leg - F3) + np.arange(n_leg - F3)])
        W[np.ix_(idx, idx)] += J @ np.linalg.solve(A, J.T)
        u[idx] += J @ np.asarray(qd_free[leg])
    gap = np.zeros((L, n_leg - F3))
    gap[:, ::3] = rows.gap_leg
    u[nb + Kd3:] += gap.reshape(-1)
    return W, u


@pytest.mark.parametrize("form", ["xla", "interpret"])
def test_block_assembly_and_elimination_equal_the_dense_schur_complement(landed, form, monkeypatch):
    """On a landed, pressurised 4-legged robot in 6 slots (80 contact slots, 24 of the 72
    attachment rows masked): the block-assembled condensed operator ``W_c``, velocities ``q_c``
    and back-substitution (``x_u`` and ``P^T``, the columns of the dense ``X``) equal
    :func:`softcrawl.jaxsim.contact.condense` of the densely summed Delassus operator to 1e-10 of
    their scale (float64; measured 1e-13: only the order of the sums differs), with contacts
    active: the elimination's products by XLA and by the kernel (``elimination.FORM``, in
    Pallas' interpreter)."""
    from softcrawl.jaxsim import elimination
    from softcrawl.jaxsim.contact import condense as dense_condense
    from softcrawl.jaxsim.delassus import condense

    monkeypatch.setattr(elimination, "FORM", form)
    _, rows, inv_chol, qd_free, _ = _step_rows(landed)
    got = condense(rows, inv_chol, qd_free)
    W, u = _dense(rows, inv_chol, qd_free)
    X, Wc, qc = dense_condense(W, u, rows.bilateral, least_squares=False)
    assert int(rows.active.sum()) > 4
    for a, b in ((got.W, Wc), (got.q, qc), (got.x_u, X[:, 0]), (np.asarray(got.P).T, X[:, 1:])):
        a, b = np.asarray(a), np.asarray(b)
        assert np.abs(a - b).max() <= 1e-10 * np.abs(b).max()


def test_the_delassus_blocks_apply_the_condensed_operator(landed):
    """``DelassusBlocks @ y`` equals the formed ``W_c @ y`` to 1e-10 of its size for random ``y`` on
    the landed robot, whose two masked leg slots give zero blocks: the same sums in another
    order, in float64, where the attachments' term ``W_cb W_bb^-1 W_bc`` subtracts products of
    the stiff attachment block's inverse far larger than ``W_c``'s entries (measured 1e-12).
    The accelerated gradient through the blocks gives the dense solve's impulses to 1e-9 of
    their size after its 48 iterations. Leaving out the attachments' term (``W_cc`` alone) is
    off by about the operator's size."""
    from softcrawl.jaxsim.contact import solve_contacts
    from softcrawl.jaxsim.delassus import condense

    model, rows, inv_chol, qd_free, _ = _step_rows(landed)
    cond = condense(rows, inv_chol, qd_free)
    W = np.asarray(cond.W)
    rng = np.random.default_rng(3)
    for y in rng.normal(size=(4, W.shape[0])):
        ref = W @ y
        assert np.abs(np.asarray(cond.blocks @ jnp.asarray(y)) - ref).max() <= 1e-10 * np.abs(ref).max()
    b = cond.blocks
    cc = np.zeros_like(W)
    nd = b.disk.shape[0]
    cc[:nd, :nd] = b.disk
    for leg, blk in enumerate(np.asarray(b.legs)):
        i = nd + leg * blk.shape[0] + np.arange(blk.shape[0])
        cc[np.ix_(i, i)] = blk
    assert np.abs(cc - W).max() > 0.1 * np.abs(W).max()
    K = rows.active.shape[0]
    mu = jnp.full((K,), model.settings.friction)
    args = (cond.W, cond.q, mu, jnp.zeros(3 * K), rows.active, "apgd", 48)
    dense, blocks = solve_contacts(*args), solve_contacts(*args, op=cond.blocks)
    assert float(jnp.abs(dense).max()) > 0
    assert np.abs(np.asarray(blocks - dense)).max() <= 1e-9 * np.abs(np.asarray(dense)).max()


def test_the_solve_kernel_reads_the_operator_in_its_parts_as_formed(landed, monkeypatch):
    """The GPU's solve kernel (in Pallas' interpreter) given the landed robot's condensed operator
    in its parts (:class:`softcrawl.jaxsim.schur.SchurOperator`: ``W_cc``'s blocks, the legs' as
    their whole Grams, and ``S``'s column blocks) forms each entry as
    :meth:`~softcrawl.jaxsim.schur.SchurOperator.dense` does and iterates on it as on the formed
    operator: the impulses to round-off (the two programs' fusions may round differently; float64
    within 1e-12 of the largest, float32 within 2e-6, 16 rounding units, reading its scaled copy
    from the scratch and holding it, :data:`softcrawl.jaxsim.fused.RESIDENT_ROWS`; measured
    equal)."""
    from softcrawl.jaxsim import fused
    from softcrawl.jaxsim.contact import apgd_coulomb
    from softcrawl.jaxsim.delassus import condense
    from softcrawl.jaxsim.schur import SchurOperator

    model, rows, inv_chol, qd_free, _ = _step_rows(landed)
    cond = condense(rows, inv_chol, qd_free)
    assert cond.schur.legs.shape[1] > cond.schur.s_legs.shape[2]  # the Grams' attachment rows are skipped
    K = rows.active.shape[0]
    for dtype, held in ((jnp.float64, None), (jnp.float32, None), (jnp.float32, 128)):
        monkeypatch.setattr(fused, "RESIDENT_ROWS", held)
        jax.clear_caches()  # read when a solve is traced
        parts = jax.tree.map(lambda a: a.astype(dtype), cond.schur)
        assert isinstance(parts, SchurOperator)
        args = (cond.q.astype(dtype), jnp.full((K,), model.settings.friction, dtype), jnp.zeros(3 * K, dtype),
                rows.active, 48)
        kw = dict(restart=False, storage="float16", fused="interpret")
        got, want = apgd_coulomb(parts, *args, **kw), apgd_coulomb(parts.dense(), *args, **kw)
        assert got.dtype == dtype and float(jnp.abs(want).max()) > 0
        tol = 1e-12 if dtype == jnp.float64 else 2e-6
        assert float(jnp.abs(got - want).max()) <= tol * float(jnp.abs(want).max())
    jax.clear_caches()


def test_an_unknown_delassus_form_is_refused(landed):
    """``Settings.delassus`` other than ``"dense"``, ``"dense16"``, ``"fused16"`` or ``"blocks"``
    is refused where the settings are made, with a ValueError naming the setting, instead of the
    step falling back to the dense product silently; ``"fused16"`` reads the operator in
    float16. :func:`build_model` makes float64 models ``"dense"`` with the library's
    factorisations (the verifying engine keeps its operator whole) and float32 ones the GPU's
    kernels, ``"fused16"`` and ``Settings.cholesky = "kernel"`` (a CPU steps them as ``"dense"``
    and ``"library"`` to the bit: the tests below); an unknown ``cholesky`` is refused too."""
    from softcrawl.jaxsim.model import build_model
    from softcrawl.robot import RobotConfig, build_robot

    model = landed[0]
    with pytest.raises(ValueError, match="settings.delassus"):
        dataclasses.replace(model.settings, delassus="block")
    assert dataclasses.replace(model.settings, delassus="blocks").delassus == "blocks"
    assert dataclasses.replace(model.settings, delassus="fused16").delassus_storage == "float16"
    assert model.settings.delassus == "dense" and model.settings.delassus_storage is None
    assert model.settings.cholesky == "library"
    robot = build_robot("1,0,2,0,1,0,3,0", RobotConfig(model="reduced", dt=0.02, disk_mesh_size=25))
    half = build_model([robot], dtype=jnp.float32).settings
    assert half.delassus == "fused16" and half.delassus_storage == "float16" and half.cholesky == "kernel"
    chosen = build_model([robot], dtype=jnp.float32, delassus="dense16", cholesky="library").settings
    assert chosen.delassus == "dense16" and chosen.cholesky == "library"
    with pytest.raises(ValueError, match="settings.delassus"):
        build_model([robot], delassus="float16")
    with pytest.raises(ValueError, match="settings.cholesky"):
        build_model([robot], cholesky="cusolver")


def test_the_float16_operator_gives_the_full_operators_velocities(landed):
    """The accelerated gradient reading the scaled Delassus operator in float16
    (:func:`softcrawl.jaxsim.contact.apgd_coulomb`'s ``storage``, ``Settings.delassus =
    "dense16"``, the float32 engine's default) on the landed robot's contact problem, in float64
    so that only the operator's storage differs; constraint velocities ``W lam`` against the
    full operator's solve (their scale here about 300 mm/s):

    * one solve from the step's warm start: within 0.1 mm/s (measured 0.033), below the 48
      iterations' own truncation (one more full solve moves them 1.5 mm/s), and not to
      round-off (above 1e-4 mm/s: the operator is read in float16);
    * ten solves, each warm-started from the last (a persisting contact state): within 0.01
      mm/s (measured 0.0014): the iterative refinement's error shrinks with the step from the
      warm start (an operator merely rounded to float16 stays about 0.09 mm/s away).
    """
    from softcrawl.jaxsim.contact import solve_contacts
    from softcrawl.jaxsim.engine import contact_problem

    model, state, kpa = landed
    W, q, mu, warm, active = contact_problem(model, state, kpa)
    Wn = np.asarray(W)
    full, half = warm, warm
    for k in range(10):
        full = solve_contacts(W, q, mu, full, active, "apgd", 48)
        half = solve_contacts(W, q, mu, half, active, "apgd", 48, storage="float16")
        gap = np.abs(Wn @ np.asarray(full - half)).max()
        if k == 0:
            assert 1e-4 < gap <= 0.1
    assert gap <= 0.01


@pytest.mark.parametrize("form", ["dense16", "fused16"])
def test_a_cpu_steps_the_float16_operators_setting_with_the_whole_operator(landed, form):
    """``Settings.delassus = "dense16"`` (and ``"fused16"``, the same iterations in one GPU
    kernel) reads the operator in float16 where the step runs on an accelerator only: a CPU's
    step (``jax.lax.platform_dependent``'s CPU branch) is the ``"dense"`` step to the bit, and the
    traced step holds the float16 branch for the others (``"fused16"``'s with the kernel)."""
    from softcrawl.jaxsim.engine import physics_step

    model, state, kpa = landed
    half = dataclasses.replace(model, settings=dataclasses.replace(model.settings, delassus=form))
    a, b = physics_step(model, state, kpa), physics_step(half, state, kpa)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    traced = str(jax.make_jaxpr(physics_step)(half, state, kpa))
    assert "f16[" in traced and ("pallas_call" in traced) == (form == "fused16")
    assert "f16[" not in str(jax.make_jaxpr(physics_step)(model, state, kpa))


def test_the_fused_kernel_solves_the_landed_robots_problem_as_xlas_iterations(landed):
    """The landed robot's contact problem in float32 (the GPU engine's precision), solved ten
    times each from the last as a persisting contact state is, by the solve in one kernel
    (:mod:`softcrawl.jaxsim.fused`, interpreted) and by XLA's iterations, both reading the operator
    in float16: constraint velocities ``W lam`` within 1e-3 mm/s of each other after every solve
    (their scale about 300 mm/s; measured at most 1.2e-4 mm/s: float32's rounding of products
    summed in another order), far below the 0.033 mm/s by which the float16 operator moves
    them (test above)."""
    from softcrawl.jaxsim.contact import solve_contacts
    from softcrawl.jaxsim.engine import contact_problem

    model, state, kpa = landed
    W, q, mu, warm, active = (jnp.asarray(a, jnp.float32) if a.dtype != bool else a
                              for a in contact_problem(model, state, kpa))
    Wn = np.asarray(W, float)
    xla, fused = warm, warm
    for _ in range(10):
        xla = solve_contacts(W, q, mu, xla, active, "apgd", 48, storage="float16")
        fused = solve_contacts(W, q, mu, fused, active, "apgd", 48, storage="float16", fused="interpret")
        assert np.abs(Wn @ np.asarray(xla - fused, float)).max() <= 1e-3


def test_the_step_takes_the_rid_form_its_settings_name(landed):
    """``Settings.rid_form`` reaches the legs' RID terms: on a CPU (``"rows"`` by platform) the
    step with ``"pairs"`` differs from the default in its last bits but not beyond float64
    round-off (the two forms' sums in another order: modal velocities within 1e-9 of their
    size, measured 2e-12), and an unknown form is refused where the settings are made."""
    from softcrawl.jaxsim.engine import physics_step

    model, state, kpa = landed
    pairs = dataclasses.replace(model, settings=dataclasses.replace(model.settings, rid_form="pairs"))
    a, b = np.asarray(physics_step(model, state, kpa).qdot), np.asarray(physics_step(pairs, state, kpa).qdot)
    assert not np.array_equal(a, b)
    assert np.abs(a - b).max() <= 1e-9 * np.abs(a).max()
    with pytest.raises(ValueError, match="settings.rid_form"):
        dataclasses.replace(model.settings, rid_form="z")


def test_corrections_give_the_constrained_velocities_the_impulses_ask_for(landed):
    """After the step's contact solve, the attachment rows' velocities are those the elimination
    demands: every present leg's attachment points move with the disk (``u_b = 0``, with the
    drift term) to 1e-8 of the velocity scale (float64; measured 1e-12)."""
    from softcrawl.jaxsim.contact import solve_contacts
    from softcrawl.jaxsim.delassus import condense, corrections

    model, rows, inv_chol, qd_free, R = _step_rows(landed)
    rd = model.robot
    cond = condense(rows, inv_chol, qd_free)
    K = rows.points.shape[0]
    lam_c = solve_contacts(cond.W, cond.q, jnp.full(K, 1.2), jnp.zeros(3 * K), rows.active, "apgd", 48)
    dq, dv, lam_b = corrections(model, rows, cond, inv_chol, lam_c, R)
    W, u = _dense(rows, inv_chol, qd_free)
    lam = np.concatenate([lam_b, lam_c])
    nb = lam_b.shape[0]
    u_b = (W @ lam + u)[:nb][np.asarray(rows.bilateral)]
    assert np.abs(u_b).max() <= 1e-8 * np.abs(u).max()
    # the legs' velocity change is A_l^-1 J_l^T lam_l
    F3 = nb // rows.leg.shape[0]
    Kd3, Kl3 = rows.disk_dd.shape[0], rows.leg.shape[1] - F3
    for leg in np.flatnonzero(np.asarray(rd.leg_mask)):
        A = _step_matrix(inv_chol[leg])
        lam_l = np.concatenate([lam_b[leg * F3:(leg + 1) * F3], lam_c[Kd3 + leg * Kl3:Kd3 + (leg + 1) * Kl3]])
        want = np.linalg.solve(A, np.asarray(rows.leg[leg]).T @ lam_l)
        assert np.abs(np.asarray(dq[leg]) - want).max() <= 1e-9 * np.abs(want).max()
    assert np.isfinite(np.asarray(dv)).all()


def test_sequential_cost_counts_loop_trips_and_ops():
    """:func:`softcrawl.jaxsim.cost.sequential_cost` of small programs: a loop of 7 trips around
    a loop of 5 counts 7 x (1 + 5) = 42 trips; the same work unrolled has no trips; a loop body's
    operations count once per trip."""
    from jax import lax

    from softcrawl.jaxsim.cost import sequential_cost

    def nested(x):
        return lax.fori_loop(0, 7, lambda i, y: lax.fori_loop(0, 5, lambda j, z: jnp.sin(z) @ x, y), x)

    def unrolled(x):
        for _ in range(3):
            x = jnp.sin(x) @ x
        return x

    x = jnp.ones((4, 4))
    c = sequential_cost(jax.jit(nested).lower(x).compile().as_text())
    assert (c.trips, c.loops, c.unknown_trip_loops) == (42, 2, 0)
    assert c.ops >= 35  # at least the dot of each of the 35 inner trips
    u = sequential_cost(jax.jit(unrolled).lower(x).compile().as_text())
    assert (u.trips, u.loops) == (0, 0) and 3 <= u.ops <= 12


def test_sequential_cost_splits_its_count_by_scope():
    """With ``scopes``, :func:`softcrawl.jaxsim.cost.sequential_cost` splits its ``ops`` and
    ``bytes`` by the named scope of each instruction: a scope inside a loop of 7 trips counts 7
    times its body's, the parts add up to the whole, instructions of no scope asked for are
    ``"other"``; without scopes there is no split."""
    from jax import lax

    from softcrawl.jaxsim.cost import sequential_cost

    def f(x):
        with jax.named_scope("outside"):
            x = jnp.cos(x) @ x
        def body(i, y):
            with jax.named_scope("inside"):
                return jnp.sin(y) @ x
        return lax.fori_loop(0, 7, body, x)

    text = jax.jit(f).lower(jnp.ones((4, 4))).compile().as_text()
    c = sequential_cost(text, ("inside", "outside"))
    assert sum(ops for ops, _ in c.by_scope.values()) == c.ops
    assert sum(b for _, b in c.by_scope.values()) == c.bytes
    inside, outside = c.by_scope["inside"], c.by_scope["outside"]
    assert inside[0] >= 7 and inside[0] % 7 == 0 and inside[1] % 7 == 0
    assert 1 <= outside[0] < 7
    assert sequential_cost(text).by_scope == {}


def test_sequential_cost_counts_the_bytes_each_operation_touches():
    """An elementwise operation on 1,000 float32 numbers reads 4,000 bytes and writes 4,000: its
    program touches 8,000 (the constants folded into the fusion are no operands); a loop of 5
    trips around it, 5 times that plus a copy of the input into the loop's state and the loop's
    counter (a few hundred bytes)."""
    from jax import lax

    from softcrawl.jaxsim.cost import sequential_cost

    x = jnp.ones(1000, jnp.float32)
    assert sequential_cost(jax.jit(lambda x: x * 2.0 + 1.0).lower(x).compile().as_text()).bytes == 8000
    looped = sequential_cost(jax.jit(lambda x: lax.fori_loop(0, 5, lambda i, y: jnp.sin(y) * 2.0, x))
                             .lower(x).compile().as_text())
    assert 6 * 8000 <= looped.bytes <= 6 * 8000 + 300


def test_deviceless_gpu_compilation_says_what_it_needs():
    """Without JAX's CUDA plugin (CI's install) asking for a GPU target says which package to
    install, instead of JAX's bare "topology not implemented"."""
    import importlib.util

    from softcrawl.jaxsim.cost import deviceless_gpu

    if importlib.util.find_spec("jax_plugins") is not None:
        pytest.skip("JAX has plugins here")
    with pytest.raises(RuntimeError, match="jax-cuda12-plugin"):
        deviceless_gpu((Path(__file__).parents[1] / "benchmarks/gpu_targets/h100.pbtxt").read_text())


def test_kernel_profile_reads_a_trace_by_scope(tmp_path):
    """:func:`softcrawl.jaxsim.cost.kernel_profile` of a traced program of two named parts (three
    calls of it, as three steps): every kernel is placed in its part, the counts are per step,
    the busy time is within the window and the per-kernel sum; a folder with no trace is refused."""
    from softcrawl.jaxsim.cost import kernel_profile

    def f(x):
        with jax.named_scope("first"):
            y = jnp.sin(x) @ x
        with jax.named_scope("second"):
            return jnp.cos(y) @ y

    g = jax.jit(f)
    x = jnp.ones((64, 64))
    jax.block_until_ready(g(x))
    with jax.profiler.trace(str(tmp_path), create_perfetto_trace=True):
        for _ in range(3):
            x = jax.block_until_ready(g(x))
    p = kernel_profile(tmp_path, g.lower(x).compile().as_text(), steps=3, top=None, scopes=("first", "second"))
    assert p["kernels_per_step"] >= 2 and set(p["by_scope"]) <= {"first", "second"} and len(p["by_scope"]) == 2
    assert sum(v["kernels"] for v in p["by_scope"].values()) == pytest.approx(p["kernels_per_step"])
    assert 0 < p["busy_us_per_step"] <= min(p["window_us_per_step"], p["kernel_us_per_step"]) + 1e-9
    assert all(r["count"] % 3 == 0 for r in p["top"])
    with pytest.raises(FileNotFoundError):
        kernel_profile(tmp_path / "none", "", steps=1)


def test_every_part_of_the_step_is_a_named_scope_of_its_program(landed):
    """Each name of ``STEP_SCOPES`` (the parts a profile is summed by) names operations of the
    compiled physics step, so a renamed scope cannot leave a profile's part silently empty."""
    from softcrawl.jaxsim.engine import STEP_SCOPES, physics_step

    model, state, kpa = landed
    text = jax.jit(physics_step).lower(model, state, kpa).compile().as_text()
    assert all(f"/{scope}/" in text for scope in STEP_SCOPES)


def test_the_step_solves_two_triangular_systems(landed):
    """The compiled physics step has two triangular solves, each against the identity: the legs'
    inverse Cholesky factors (one batched solve) and the attachment block's; every other use of
    them is a product. On a GPU each triangular solve of small batched matrices is a chain of
    kernel launches, a product one (benchmarks/RESULTS.md has the kernel table)."""
    import re

    from softcrawl.jaxsim.engine import physics_step

    model, state, kpa = landed
    text = jax.jit(physics_step).lower(model, state, kpa).compile().as_text()
    solves = re.findall(r'custom_call_target="[a-z_]*trsm[a-z_]*"|= \S+ triangular-solve\(', text)
    assert len(solves) == 2


def test_the_engines_step_has_a_short_dependency_chain():
    """The vector env's step of the paper preset's robots (6 leg slots, 80 contact slots, the
    default contact solve) compiled for a CPU: no loop but the steps' own (one trip per step) and
    at most 600 operations in sequence per step (measured 545 on this VM with JAX
    0.10.2; the previous engine's 100 Gauss-Seidel sweeps ran 8,101 trips and 184,545
    operations per step: benchmarks/step_cost.py, benchmarks/RESULTS.md)."""
    out = subprocess.run([sys.executable, "benchmarks/step_cost.py", "--steps", "10"], capture_output=True, text=True,
                         check=True, cwd=Path(__file__).parents[1]).stdout
    cost = json.loads(out.strip().splitlines()[-1])
    assert cost["loop_trips_per_step"] == 1.0 and cost["inner_loops"] == 0
    assert cost["dependent_ops_per_step"] <= 600
    assert cost["mflop_per_robot_step"] <= 50


def test_step_cost_compares_a_batchs_end_with_a_reference_file(tmp_path):
    """``against_reference`` stores a batch's end where the file has none (keeping its other
    batches), then gives the largest node distance over robots valid in both runs (here 3 mm
    and 4 mm moves of two nodes; the robot invalid in one run left out and counted), and
    refuses a reference of other designs or calls."""
    from helpers import benchmark_module

    against = benchmark_module("step_cost").against_reference
    path = tmp_path / "ref.npz"
    rng = np.random.default_rng(0)
    end = {"designs": rng.integers(0, 3, (4, 8)), "x": rng.normal(0.0, 50.0, (4, 5, 3)).astype(np.float32),
           "dead": np.zeros(4, bool), "calls": np.asarray(3)}
    assert against(path, "b4", end) == {"reference": "stored"}
    assert against(path, "b2", {**end, "designs": end["designs"][:2], "x": end["x"][:2], "dead": end["dead"][:2]}) \
        == {"reference": "stored"}
    x = end["x"].copy()
    x[0, 1, 2] += 3.0
    x[2, 4] += (0.0, 4.0, 0.0)
    x[3] += 100.0  # robot 3 invalid here: not compared
    got = against(path, "b4", {**end, "x": x, "dead": np.asarray([False, False, False, True])})
    assert got["reference_max_node_distance_mm"] == pytest.approx(4.0, abs=1e-5)
    assert got["reference_median_robot_distance_mm"] == pytest.approx(3.0, abs=1e-5)
    assert (got["bad_robots_here_only"], got["bad_robots_reference_only"]) == (1, 0)
    assert against(path, "b2", {**end, "designs": end["designs"][:2], "x": end["x"][:2], "dead": end["dead"][:2]}) \
        ["reference_max_node_distance_mm"] == 0.0
    with pytest.raises(ValueError, match="other designs"):
        against(path, "b4", {**end, "designs": end["designs"][::-1]})
    with pytest.raises(ValueError, match="other calls"):
        against(path, "b4", {**end, "calls": np.asarray(2)})


def test_step_cost_compares_two_forms_of_the_step_on_the_same_robots(tmp_path):
    """Two runs of ``benchmarks/step_cost.py --reference`` (the way a GPU session compares a
    candidate form of the step with the defaults on the same robots): the RID terms' ``pairs``
    form sums the ``rows`` form's terms in another order, so that after six steps (landing, then
    pressing) the disk nodes differ by float32 round-off carried through the contacts, measured
    0.016 mm on this VM; a wrong term in either would move them by millimetres. Bounded by 0.1
    mm, a fifth of the issue's 0.5 mm between the engines over 2 s; not bit-equal, so that the
    runs did step different programs."""
    ref = tmp_path / "ref.npz"

    def run(*flags):
        out = subprocess.run([sys.executable, "benchmarks/step_cost.py", "--time", "--no-cost", "--batches", "2",
                              "--calls", "1", "--steps", "3", "--reference", str(ref), *flags], capture_output=True,
                             text=True, check=True, cwd=Path(__file__).parents[1]).stdout
        return json.loads(out.strip().splitlines()[-1])

    assert run("--rid-form", "rows")["reference"] == "stored"
    got = run("--rid-form", "pairs")
    assert 0.0 < got["reference_max_node_distance_mm"] <= 0.1
    assert got["bad_robots"] == got["bad_robots_here_only"] == got["bad_robots_reference_only"] == 0


def test_the_legs_heights_are_the_z_of_their_rotated_collision_nodes(landed):
    """``leg_height_terms`` forms only the world z of the legs' collision nodes (third row of each
    leg's rotation), ``place_heights`` adds the translation: equal, to 1e-12 mm (float64
    round-off of ~40-term sums of numbers below 100), to the full placement ``R (X + Phi q) + t``
    in numpy, velocities likewise; absent legs are FAR up. Rows and columns of ``R`` swapped
    would move the bent, pressed legs' nodes by millimetres."""
    from softcrawl.jaxsim.delassus import FAR, leg_height_terms, place_heights

    model, state, _ = landed
    leg, rd = model.leg, model.robot
    qdot = state.qdot + jnp.asarray(np.random.default_rng(1).normal(0.0, 5.0, state.qdot.shape))
    z, vz = leg_height_terms(leg, rd, state.q, qdot)
    z = place_heights(z, rd.translation[:, 2], rd.leg_mask)
    Phi, X, R = np.asarray(leg.coll_affine[..., :-1]), np.asarray(leg.coll_affine[..., -1]), np.asarray(rd.rotation)
    x = np.einsum("lac,lnc->lna", R, X + np.einsum("nam,lm->lna", Phi, np.asarray(state.q)))
    v = np.einsum("lac,lnc->lna", R, np.einsum("nam,lm->lna", Phi, np.asarray(qdot)))
    present = np.asarray(rd.leg_mask)
    assert present.sum() == 4 and np.abs(R[present] - np.eye(3)).max() > 0.5
    np.testing.assert_allclose(np.asarray(z)[present], (x[..., 2] + np.asarray(rd.translation)[:, 2:])[present],
                               rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(vz), v[..., 2], rtol=0, atol=1e-12)
    assert np.all(np.asarray(z)[~present] == FAR)


def test_the_disks_rotation_by_newtons_iteration_is_the_svds(landed):
    """On CUDA the disk's Kabsch rotation is the polar factor by Newton's iteration
    (:func:`softcrawl.jaxsim.disk.polar_rotation`), elsewhere by the SVD. On 300 moment matrices
    of the paper's disk, rotated at random, stretched and sheared by up to 30% and moved, the
    two agree to 1e-13 in float64 (measured 1e-14; five iterations instead of eight: 1.9e-12)
    and 1e-6 in float32 (measured 1.6e-7, round-off of entries near 1); a disk turned inside out
    (``det H < 0``) gives NaN, where the SVD would fit a rotation to a reflected disk; on a CPU
    the rotation is the SVD's of the moment matrix (to 1e-13, measured 2e-16: its sums in
    another order); and the step exported for CUDA calls no library routine for it (cuSOLVER's
    SVD is a chain of kernels there), its iterations ending in an optimization barrier (without
    it, XLA's GPU fusion at 96 robots evaluated them once per entry of the stacked rotation:
    216,000 instructions of machine code, 6.5 KB spilled a thread, 2.5 minutes of compilation)."""
    from scipy.spatial.transform import Rotation

    from softcrawl.jaxsim.disk import _svd_rotation, kabsch, polar_rotation

    model = landed[0]
    rest, wr = np.asarray(model.disk.rest), np.asarray(model.disk.weighted_rest)
    rng = np.random.default_rng(3)
    newton, svd = jax.jit(polar_rotation), jax.jit(_svd_rotation)
    short = jax.jit(lambda H: polar_rotation(H, iterations=5))
    err = {np.float64: 0.0, np.float32: 0.0, "short": 0.0}
    for k in range(300):
        stretch = np.eye(3) + rng.uniform(-0.3, 0.3, (3, 3))
        x = rest @ stretch.T @ Rotation.random(random_state=k).as_matrix().T + rng.normal(0.0, 5.0, 3)
        H = wr.T @ x
        ref = np.asarray(svd(jnp.asarray(H)))
        for dt in (np.float64, np.float32):
            err[dt] = max(err[dt], np.abs(np.asarray(newton(jnp.asarray(H, dt))) - ref).max())
        err["short"] = max(err["short"], np.abs(np.asarray(short(jnp.asarray(H))) - ref).max())
    assert err[np.float64] <= 1e-13 and err[np.float32] <= 1e-6
    assert err["short"] > 1e-13  # five iterations are not enough (measured 1.9e-12): the bound can fail
    assert np.isnan(np.asarray(polar_rotation(jnp.asarray(wr.T @ (rest * [1.0, 1.0, -1.0]))))).all()
    args = (jnp.asarray(rest), jnp.asarray(wr))
    cuda = jax.export.export(jax.jit(kabsch), platforms=["cuda"])(*args).mlir_module()
    assert "custom_call" not in cuda and "optimization_barrier" in cuda
    fit = jax.jit(lambda x, w: _svd_rotation(w.T @ x))  # the moment matrix summed in another order
    np.testing.assert_allclose(np.asarray(jax.jit(kabsch)(*args)), np.asarray(fit(*args)), rtol=0, atol=1e-13)


def test_the_constraint_rows_blocks_are_their_frames_products(landed):
    """The constraint rows' blocks, each formed as elementwise sums of products (one fused
    operation on a GPU), equal the frames' products by numpy's einsum to 1e-14 of their largest
    entry (measured 5e-16: only the order of the sums differs), for a disk frame far from the
    identity (the landed disk's own is near it): the disk's share of the attachment block ``R
    G_pq R^T`` for every pair of attachment points (``R^T G R`` instead is off by about the
    entries' size), of the disk contacts' ``(D R) A_0^-1[n_p, n_q] (D R)^T`` and the coupling
    ``-R (sum_i w_ai A_0^-1[n_ai, n_k]) (D R)^T``, and each leg's rows, its attachment patches'
    basis rows turned by its rotation (zero for an absent leg) over its contact points' turned
    by the floor frame ``D R_l``."""
    from scipy.spatial.transform import Rotation

    from softcrawl.jaxsim.delassus import FLOOR_FRAME

    R = Rotation.from_rotvec([0.4, -1.1, 0.7]).as_matrix()
    model, rows, _, _, _ = _step_rows(landed, R)
    leg, dk, rd, st = model.leg, model.disk, model.robot, model.settings
    G = np.asarray(rd.att_gram)
    D, inverse = np.asarray(FLOOR_FRAME), np.asarray(dk.inverse)
    DR = D @ R

    def blocks(rows_nodes, cols_nodes):  # A_0^-1[n_p, n_q], (..., 3, ..., 3)
        r, c = np.asarray(rows_nodes), np.asarray(cols_nodes)
        r, c = 3 * r[..., None] + np.arange(3), 3 * c[..., None] + np.arange(3)
        return inverse[r.reshape(r.shape + (1,) * c.ndim), c.reshape((1,) * r.ndim + c.shape)]

    L, m = rd.rotation.shape[0], leg.basis.shape[2]
    Kd, Kl, nd, nc = st.disk_contacts, st.leg_contacts, dk.collision.shape[0], leg.coll_affine.shape[0]
    lnode = (np.asarray(rows.points[Kd:]) - nd).reshape(L, Kl) % nc
    rot, mask = np.asarray(rd.rotation), np.asarray(rd.leg_mask)
    J_att = np.einsum("lac,fcm->lfam", rot, np.asarray(leg.att_affine)[..., :m]) * mask[:, None, None, None]
    J_con = np.einsum("ab,lbc,lkcm->lkam", D, rot, np.asarray(leg.coll_affine)[lnode, :, :m])
    expected = {
        "disk_aa": np.einsum("ab,pqbc,dc->paqd", R, G, R),
        "disk_dd": np.einsum("ab,pbqc,dc->paqd", DR, blocks(rows.disk_node, rows.disk_node), DR),
        "disk_ad": -np.einsum("ai,xb,aibkc,dc->axkd", rows.att_weights, R, blocks(rows.att_nodes, rows.disk_node), DR),
        "leg": np.concatenate([J_att.reshape(L, -1, m), J_con.reshape(L, -1, m)], axis=1)}
    assert not mask.all() and np.abs(J_att).max() > 0
    for name, ref in expected.items():
        got = np.asarray(getattr(rows, name))
        assert got.shape == ref.reshape(got.shape).shape
        assert np.abs(got - ref.reshape(got.shape)).max() <= 1e-14 * np.abs(ref).max(), name
    wrong = np.einsum("ba,pqbc,cd->paqd", R, G, R).reshape(rows.disk_aa.shape)
    assert np.abs(wrong - np.asarray(rows.disk_aa)).max() > 0.1 * np.abs(expected["disk_aa"]).max()


def test_the_strain_modes_terms_are_placed_by_their_slots(landed):
    """``LegPart.mode_slots`` gives each strain mode its position among them and every other mode
    (the rigid translations, which have no internal force) the padding slot ``m'``: the legs'
    step gathers ``K_r`` and ``f_r`` into all modes by it."""
    leg = landed[0].leg
    sm, slots = np.asarray(leg.strain_modes), np.asarray(leg.mode_slots)
    m = np.asarray(leg.mass).shape[0]
    assert slots.shape == (m,) and 0 < len(sm) < m
    np.testing.assert_array_equal(slots[sm], np.arange(len(sm)))
    assert np.all(np.delete(slots, sm) == len(sm))


def test_the_cavity_load_is_the_polynomial_it_is(landed):
    """``cavity_load`` as its quadratic polynomial in ``q`` (the default) and as the CPU engine
    computes it (positions, cross products, scattered into the cavity nodes) on the landed
    robot's bent legs and on legs bent far (random modal displacements of 20 and 80 mm) at 30
    kPa: equal to 1e-12 of the largest entry in float64 (measured 1.1e-15; the polynomial is
    exact, its coefficients summed in float64), and in float32 within 2e-6 of it, about 30
    roundings (measured 6.0e-7, the nodes' form 2.4e-7; on the landed legs 4.9e-7 and 3.6e-7).
    Leaving out the quadratic terms' transposed pairs moves the load by a third of its largest
    entry. An unknown form is refused."""
    from softcrawl.jaxsim import legs as leg_motion

    model, state, _ = landed
    rng = np.random.default_rng(0)
    qs = jnp.concatenate([state.q, jnp.asarray(rng.normal(0.0, 20.0, (4, state.q.shape[1]))),
                          jnp.asarray(rng.normal(0.0, 80.0, (4, state.q.shape[1])))])
    assert float(jnp.abs(state.q).max()) > 1.0
    loads = {form: np.asarray(jax.vmap(lambda q, form=form: leg_motion.cavity_load(model.leg, q, 30.0, form))(qs))
             for form in ("nodes", "polynomial")}
    scale = np.abs(loads["nodes"]).max()
    assert scale > 0
    assert np.abs(loads["polynomial"] - loads["nodes"]).max() <= 1e-12 * scale
    leg32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, model.leg)
    load32 = jax.vmap(lambda q: leg_motion.cavity_load(leg32, q, jnp.float32(30.0)))(qs.astype(jnp.float32))
    assert load32.dtype == jnp.float32
    assert np.abs(np.asarray(load32, float) - loads["nodes"]).max() <= 2e-6 * scale
    with pytest.raises(ValueError, match="form"):
        leg_motion.cavity_load(model.leg, state.q[0], 30.0, "edges")


@pytest.mark.parametrize("n_rows, kept", [(3, 35), (2, 19)])
def test_the_kept_frame_monomials_give_every_quadratic_monomial_of_a_rotation(n_rows, kept):
    """:func:`softcrawl.jaxsim.legs.frame_monomials` on 500 random rotations (float64): every
    quadratic monomial of the first ``n_rows`` rows is the expansion of the kept ones to 1e-14
    (measured 1.2e-15; the relations are exact, the rows orthonormal to round-off), and the kept
    ones are independent there (their rank over the samples is their number: 35 = 1 + 9 + 25 for
    a rotation, 19 for two orthonormal rows), so no smaller set would do. Without the column relations
    (40 kept) both counts fail."""
    from scipy.spatial.transform import Rotation

    from softcrawl.jaxsim.legs import frame_monomials

    i, j, E = frame_monomials(n_rows)
    assert len(i) == kept and E.shape == (3 * n_rows * (3 * n_rows + 1) // 2, kept)
    assert set(np.unique(E)) <= {-1.0, 0.0, 1.0}
    f = Rotation.random(500, random_state=0).as_matrix()[:, :n_rows].reshape(500, -1)
    a, b = np.triu_indices(3 * n_rows)
    every, mine = f[:, a] * f[:, b], f[:, i] * f[:, j]
    assert np.abs(every - mine @ E.T).max() <= 1e-14
    assert np.linalg.matrix_rank(mine, tol=1e-8) == kept
    with pytest.raises(ValueError, match="n_rows"):
        frame_monomials(1)


def test_the_legs_rid_terms_agree_in_both_orders_of_the_sums(landed):
    """``rid_terms`` with ``Z`` formed (``"rows"``, the CPU's) and without (``"pairs"``, the
    GPU's: the frames' kept quadratic monomials contracted with each element's stiffness per
    monomial) on the landed robot's bent, pressed legs: the same sums in another order, so
    ``K_r`` and ``f_r`` agree to 1e-12 of their largest entries in float64 (each entry sums
    ~2,000-14,000 products, each rounded to 1.1e-16; the relations among the monomials hold to
    the frames' round-off). A wrong pair factor (the off-diagonal transpose left out) moves
    ``K_r`` by about half. The frame stiffness formed once before a loop
    (``with_frame_stiffness``) gives the same bits. On legs bent far enough to invert elements
    (random modal displacements of 80 mm: 8-56 per leg), both forms count the same inverted or
    degenerate elements."""
    from softcrawl.jaxsim import legs as leg_motion

    model, state, _ = landed
    qdot = state.qdot + jnp.asarray(np.random.default_rng(0).normal(0.0, 5.0, state.qdot.shape))
    formed = leg_motion.with_frame_stiffness(model.leg)
    terms = {(form, part is formed): jax.vmap(lambda q, v, form=form, part=part: leg_motion.rid_terms(
        part, q, v, 0.03, form))(state.q, qdot) for form in ("rows", "pairs") for part in (model.leg, formed)}
    for form in ("rows", "pairs"):
        for a, b in zip(terms[(form, False)], terms[(form, True)]):
            np.testing.assert_array_equal(a, b)
    assert all(f.stiffness is None for f in model.leg.families)
    (Kr, fr, nr), (Kp, fp, np_) = terms[("rows", False)], terms[("pairs", False)]
    assert float(jnp.abs(state.q).max()) > 1.0  # bent: the frames are not the rest frames
    assert np.abs(np.asarray(Kp - Kr)).max() <= 1e-12 * np.abs(np.asarray(Kr)).max()
    assert np.abs(np.asarray(Kp - Kp.transpose(0, 2, 1))).max() == 0.0
    assert np.abs(np.asarray(fp - fr)).max() <= 1e-12 * np.abs(np.asarray(fr)).max()
    np.testing.assert_array_equal(nr, np_)
    wild = jnp.asarray(np.random.default_rng(1).normal(0.0, 80.0, (4, state.q.shape[-1])))
    bad = [jax.vmap(lambda q, form=form: leg_motion.rid_terms(model.leg, q, 0 * q, 0.03, form)[2])(wild)
           for form in ("rows", "pairs")]
    assert np.asarray(bad[0]).min() > 0
    np.testing.assert_array_equal(bad[0], bad[1])
    with pytest.raises(ValueError, match="form"):
        leg_motion.rid_terms(model.leg, state.q[0], qdot[0], 0.03, "dense")


def test_the_rid_kernel_forms_the_rows_forms_terms(landed, monkeypatch):
    """``rid_terms`` in one kernel (``"interpret"``: :mod:`softcrawl.jaxsim.ridkernel` in Pallas'
    interpreter, ``Z`` formed 16 elements at a time, its 33 strain modes as two tiles of 16, joined
    for the products, and one loose column) on the landed robot's bent, pressed legs: the rows
    form's ``K_r`` and ``f_r`` to 1e-12 of their largest entries in float64 (the same products,
    summed by blocks: measured 4e-15 on a random state), ``K_r`` exactly symmetric, the same
    inverted or degenerate elements counted on legs bent to invert them; the same with each leg's
    element blocks shared among three programs (``ridkernel.SPLIT``), their shares added; the same
    to the bit from the kernel's rows formed before a loop of steps
    (``ridkernel.with_kernel_rows``); zeros for an empty slot (``present`` false: its program treats
    no element). On one leg: the same with the modes as padded tiles only (16 + 16 + 16), with 3 of
    the modes as loose columns only (``ridkernel.LOOSE``), as a tile of 32 and a loose column
    (``ridkernel.TILE``), and with ``Z``'s rows formed by groups of stress rows
    (``ridkernel.ROW_GROUPS``); in float32, ``K_r`` by the products of its split operands, TF32
    parts (``DOT_ALGORITHM = "SPLIT_TF32"``) or bfloat16 parts (``"SPLIT_BF16"``), within 2e-6 of
    float64's (float32's round-off summed over 1,944 rows: measured 3.1e-7 and 5.6e-7 for ``K_r``,
    6.3e-7 to 7.6e-7 for ``f_r``), which a state 1e-4 off fails (6.6e-6 and 9.2e-5). ``"kernel"`` on
    a CPU is the rows form to the bit, its traced program holding the kernel for CUDA, in float32
    with fused multiply-adds; exported for a TPU, the step with it holds no kernel."""
    from softcrawl.jaxsim import legs as leg_motion
    from softcrawl.jaxsim import ridkernel
    from softcrawl.jaxsim.engine import physics_step

    model, state, kpa = landed
    qdot = state.qdot + jnp.asarray(np.random.default_rng(0).normal(0.0, 5.0, state.qdot.shape))

    def terms(form, q, v):
        return jax.vmap(lambda q, v: leg_motion.rid_terms(model.leg, q, v, 0.03, form))(q, v)

    Kr, fr, nr = terms("rows", state.q, qdot)
    wild = jnp.asarray(np.random.default_rng(1).normal(0.0, 80.0, (2, state.q.shape[-1])))
    bad = terms("rows", wild, 0 * wild)[2]
    assert np.asarray(bad).min() > 0
    for split in (3, 1):
        monkeypatch.setattr(ridkernel, "SPLIT", split)
        Kk, fk, nk = terms("interpret", state.q, qdot)
        assert np.abs(np.asarray(Kk - Kr)).max() <= 1e-12 * np.abs(np.asarray(Kr)).max()
        assert np.abs(np.asarray(Kk - Kk.transpose(0, 2, 1))).max() == 0.0
        assert np.abs(np.asarray(fk - fr)).max() <= 1e-12 * np.abs(np.asarray(fr)).max()
        np.testing.assert_array_equal(nr, nk)
        np.testing.assert_array_equal(bad, terms("interpret", wild, 0 * wild)[2])
    shared = ridkernel.with_kernel_rows(model.leg)  # the rows formed before a loop of steps: the same terms
    for a, b in zip(jax.vmap(lambda q, v: leg_motion.rid_terms(shared, q, v, 0.03, "interpret"))(state.q, qdot),
                    (Kk, fk, nk)):
        np.testing.assert_array_equal(a, b)
    on = np.asarray(model.robot.leg_mask)
    pick = np.asarray([np.argmax(on), np.argmax(~on)])  # a present leg and an empty slot
    got = jax.vmap(lambda q, v, present: leg_motion.rid_terms(model.leg, q, v, 0.03, "interpret", present))(
        state.q[pick], qdot[pick], jnp.asarray([True, False]))
    for a, b in zip(got, (Kk, fk, nk)):
        np.testing.assert_array_equal(a[0], b[pick[0]])
        assert not np.any(np.asarray(a[1]))
    q1, v1 = state.q[:1], qdot[:1]  # one leg from here on: the interpreter is slow
    few = dataclasses.replace(model.leg, strain_modes=model.leg.strain_modes[:3], families=tuple(
        dataclasses.replace(f, rows=f.rows[..., :3]) for f in model.leg.families))
    for part, loose, tile in ((model.leg, 0, 16), (few, 4, 16), (model.leg, 4, 32)):
        # 33 modes as three tiles of 16, the last padded (two joined for the products, one alone); 3 modes
        # loose, no tile; a tile of 32 and a loose one
        monkeypatch.setattr(ridkernel, "LOOSE", loose)
        monkeypatch.setattr(ridkernel, "TILE", tile)
        (Kp, fp, _), (Kq, fq, _) = (jax.vmap(lambda q, v: leg_motion.rid_terms(part, q, v, 0.03, form))(
            q1, v1) for form in ("rows", "interpret"))
        assert np.abs(np.asarray(Kq - Kp)).max() <= 1e-12 * np.abs(np.asarray(Kp)).max()
        assert np.abs(np.asarray(Kq - Kq.transpose(0, 2, 1))).max() == 0.0
        assert np.abs(np.asarray(fq - fp)).max() <= 1e-12 * np.abs(np.asarray(fp)).max()
    monkeypatch.setattr(ridkernel, "TILE", 16)
    K1, f1 = Kr[:1], fr[:1]
    monkeypatch.setattr(ridkernel, "ROW_GROUPS", 4)  # tetrahedra's 6 rows as 3 groups of 2, triangles' 3 as 3 of 1
    Kg, fg, _ = terms("interpret", q1, v1)
    assert np.abs(np.asarray(Kg - K1)).max() <= 1e-12 * np.abs(np.asarray(K1)).max()
    assert np.abs(np.asarray(Kg - Kg.transpose(0, 2, 1))).max() == 0.0
    assert np.abs(np.asarray(fg - f1)).max() <= 1e-12 * np.abs(np.asarray(f1)).max()
    monkeypatch.setattr(ridkernel, "ROW_GROUPS", 1)
    f32 = jax.tree.map(lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a, model.leg)
    Kp, fp, _ = terms("rows", q1 * (1 + 1e-4), v1)  # a state 1e-4 off: the bound tells it apart
    for algorithm in ("SPLIT_TF32", "SPLIT_BF16"):  # float32: K_r = K + M + M^T from split operands
        monkeypatch.setattr(ridkernel, "DOT_ALGORITHM", algorithm)
        K32, f32_, _ = jax.vmap(lambda q, v: leg_motion.rid_terms(f32, q, v, 0.03, "interpret"))(
            q1.astype(jnp.float32), v1.astype(jnp.float32))
        for K, f, close in ((K1, f1, True), (Kp, fp, False)):
            assert (np.abs(np.asarray(K32, float) - np.asarray(K)).max() <= 2e-6 * np.abs(np.asarray(K)).max()) == close
            err = np.abs(np.asarray(f32_, float) - np.asarray(f)).max()
            assert (err <= 2e-6 * np.abs(np.asarray(f)).max()) == close
    for a, b in zip(terms("kernel", state.q, qdot), (Kr, fr, nr)):
        np.testing.assert_array_equal(a, b)
    traced = str(jax.make_jaxpr(lambda q, v: terms("kernel", q, v))(state.q, qdot))
    assert "rid_terms" in traced and "fma.rn.f32" not in traced  # float64: no float32 fused multiply-add
    traced = str(jax.make_jaxpr(jax.vmap(lambda q, v: leg_motion.rid_terms(f32, q, v, 0.03, "kernel")))(
        state.q.astype(jnp.float32), qdot.astype(jnp.float32)))
    assert "fma.rn.f32" in traced  # the CUDA kernel's products and sums, one rounding each
    kernel = dataclasses.replace(model, settings=dataclasses.replace(model.settings, rid_form="kernel"))
    export = jax.export.export(jax.jit(physics_step), platforms=["tpu"])
    text = export(kernel, state, kpa).mlir_module()
    assert "triton" not in text


def test_the_rid_kernels_operand_splits_are_exact():
    """``split_products``' parts of float32 numbers of every sign and of 60 binades (zeros and
    float32's smallest normal among them): the bfloat16 parts sum to ``z`` exactly (in float64),
    the first two truncations (``bfloat16_high``: its float32 and bfloat16 the same number, ``|z
    - h| < 2^-7 |z|``, ``h`` of ``z``'s sign and no larger) and the third below ``2^-14 |z|``;
    the TF32 parts sum to ``z``, ``H`` with 13 low bits clear and ``|z - H| < 2^-10 |z|``."""
    from softcrawl.jaxsim import ridkernel

    rng = np.random.default_rng(3)
    z = (rng.choice([-1.0, 1.0], 4096) * rng.uniform(1.0, 2.0, 4096) * 2.0 ** rng.integers(-30, 30, 4096))
    z = jnp.asarray(np.concatenate([z, [0.0, -0.0, np.finfo(np.float32).tiny]]), jnp.float32).reshape(-1, 1)
    zd = np.asarray(z, np.float64)
    h, b = ridkernel.bfloat16_high(z)
    assert b.dtype == jnp.bfloat16
    np.testing.assert_array_equal(np.asarray(b, np.float64), np.asarray(h, np.float64))
    assert np.all(np.abs(zd - np.asarray(h, np.float64)) <= 2.0 ** -7 * np.abs(zd))
    assert np.all(np.asarray(h, np.float64) * np.sign(zd) <= np.abs(zd)) and np.all(np.asarray(h) * zd >= 0)
    K, M = ridkernel.split_products([z], "bf16")
    (B1, _), (B2, _) = K(0, 0)
    (_, B2_), (_, B3) = M(0, 0)
    B1, B2, B3 = (np.asarray(B, np.float64) for B in (B1, B2, B3))
    np.testing.assert_array_equal(B2, np.asarray(B2_, np.float64))
    np.testing.assert_array_equal(B1 + B2 + B3, zd)
    assert np.all(np.abs(B2) <= 2.0 ** -7 * np.abs(zd)) and np.all(np.abs(B3) <= 2.0 ** -14 * np.abs(zd))
    ((H, _),), ((_, L),) = (f(0, 0) for f in ridkernel.split_products([z], "tf32"))
    np.testing.assert_array_equal(np.asarray(H, np.float64) + np.asarray(L, np.float64), zd)
    assert not np.any(np.asarray(jax.lax.bitcast_convert_type(H, jnp.int32)) & ((1 << 13) - 1))
    assert np.all(np.abs(np.asarray(L, np.float64)) <= 2.0 ** -10 * np.abs(zd))


def test_the_rid_kernels_columns_are_tiles_then_loose_columns(monkeypatch):
    """``column_tiles``: tiles of ``TILE`` columns (32 or 16), a last tile padded to 16 or 32
    where more than ``LOOSE`` columns are left, else those columns loose; ``product_tiles``:
    pairs of consecutive 16-column tiles joined for the products, their columns interleaved
    (``product_columns``, ``join_tiles``), the others alone."""
    from softcrawl.jaxsim import ridkernel

    monkeypatch.setattr(ridkernel, "LOOSE", 4)
    monkeypatch.setattr(ridkernel, "TILE", 32)
    assert ridkernel.column_tiles(33) == ([(0, 32)], [32])
    assert ridkernel.column_tiles(36) == ([(0, 32)], [32, 33, 34, 35])
    assert ridkernel.column_tiles(37) == ([(0, 32), (32, 16)], [])
    assert ridkernel.column_tiles(64) == ([(0, 32), (32, 32)], [])
    assert ridkernel.column_tiles(20) == ([(0, 32)], [])
    assert ridkernel.column_tiles(3) == ([], [0, 1, 2])
    assert ridkernel.product_tiles(ridkernel.column_tiles(37)[0]) == [(0,), (1,)]
    monkeypatch.setattr(ridkernel, "TILE", 16)
    assert ridkernel.column_tiles(33) == ([(0, 16), (16, 16)], [32])
    assert ridkernel.column_tiles(20) == ([(0, 16)], [16, 17, 18, 19])
    assert ridkernel.column_tiles(3) == ([], [0, 1, 2])
    tiles = ridkernel.column_tiles(37)[0]
    assert tiles == [(0, 16), (16, 16), (32, 16)]
    assert ridkernel.product_tiles(tiles) == [(0, 1), (2,)]
    pair = np.stack([np.arange(16), np.arange(16, 32)], axis=-1).reshape(-1)  # 0, 16, 1, 17, ...
    np.testing.assert_array_equal(ridkernel.product_columns(tiles, (0, 1)), pair)
    np.testing.assert_array_equal(ridkernel.product_columns(tiles, (2,)), np.arange(32, 48))
    parts = [jnp.asarray(np.arange(32.0).reshape(2, 16) + 100 * t) for t in range(3)]  # 2 elements' rows
    joined = ridkernel.join_tiles(parts, [(0, 1), (2,)])
    np.testing.assert_array_equal(joined[0], np.asarray(parts[0])[:, pair % 16] + 100 * (pair >= 16))
    np.testing.assert_array_equal(joined[1], parts[2])


def test_the_gpu_kernels_are_cudas_only(landed):
    """The float32 defaults' two Pallas kernels (``Settings.delassus = "fused16"``,
    ``Settings.cholesky = "kernel"``) are written for Triton on NVIDIA GPUs: the step exported for
    CUDA holds them (JAX refuses to serialise their custom call, which names them), and the step
    exported for other accelerators, TPU and ROCm, lowers without them (XLA's float16 solve and
    the library's factors) instead of failing on a kernel it cannot lower."""
    from softcrawl.jaxsim.engine import physics_step

    model, state, kpa = landed
    kernels = dataclasses.replace(model, settings=dataclasses.replace(model.settings, delassus="fused16",
                                                                      cholesky="kernel"))

    def exported(platform):
        return jax.export.export(jax.jit(physics_step), platforms=[platform])(kernels, state, kpa).mlir_module()

    with pytest.raises(ValueError, match="gpu.triton"):
        exported("cuda")
    for platform in ("tpu", "rocm"):
        text = exported(platform)
        assert "triton" not in text and "f16" in text


def test_a_gpu_older_than_ampere_runs_the_step_without_kernels(landed, monkeypatch):
    """Every kernel form on (the solve, the factors, the RID terms, the contact candidates): for a
    GPU of compute capability 7.5 (a T4; XLA compiles Triton kernels from 8.0 on and fails on
    them) the step exported for CUDA holds no Triton kernel (XLA's forms instead, the float16
    solve among them), for 9.0 it holds them (JAX refuses to serialise their custom call). A
    regression test: a T4 failed to compile the float32 defaults."""
    from softcrawl.jaxsim import candidates, gpu
    from softcrawl.jaxsim.engine import physics_step

    model, state, kpa = landed
    kernels = dataclasses.replace(model, settings=dataclasses.replace(
        model.settings, delassus="fused16", cholesky="kernel", rid_form="kernel"))
    monkeypatch.setattr(candidates, "SELECTION", "kernel")

    def exported(capability):
        monkeypatch.setattr(gpu, "compute_capability", lambda: capability)
        monkeypatch.setattr(gpu, "_warned", False)
        jax.clear_caches()
        return jax.export.export(jax.jit(physics_step), platforms=["cuda"])(kernels, state, kpa).mlir_module()

    with pytest.warns(UserWarning, match="compiles no Pallas kernels"):
        text = exported((7, 5))
    assert "triton" not in text and "f16" in text
    with pytest.raises(ValueError, match="gpu.triton"):
        exported((9, 0))
    jax.clear_caches()


def test_the_candidates_kernel_chooses_the_steps_contacts_as_xla(landed, monkeypatch):
    """:data:`softcrawl.jaxsim.candidates.SELECTION`: each body's contact candidates chosen in one
    kernel per body (interpreted here) are XLA's all-bodies choice on the landed robot (loaded
    points kept, two empty slots), to the bit, and three whole steps from it end in the same
    state to the bit; exported for CUDA the step holds the kernel, for ROCm it does not; an
    unknown selection is refused."""
    from softcrawl.jaxsim import candidates
    from softcrawl.jaxsim import disk as disk_motion
    from softcrawl.jaxsim import legs as leg_motion
    from softcrawl.jaxsim.delassus import select_contacts
    from softcrawl.jaxsim.engine import Control, make_rollout

    model, state, kpa = landed
    rd = model.robot
    qd_free, _, _ = jax.vmap(leg_motion.free_motion, in_axes=(None, None, 0, 0, 0, 0, 0))(
        model.leg, model.settings, state.q, state.qdot, rd.rotation, kpa[rd.channel] * rd.leg_mask, rd.leg_mask)
    v_free, _ = disk_motion.free_motion(model.disk, model.settings, state.x, state.v)
    assert np.sum(np.asarray(state.impulses[:, 0]) > 0) >= 3

    def chosen(selection):
        monkeypatch.setattr(candidates, "SELECTION", selection)
        jax.clear_caches()
        return [np.asarray(a) for a in select_contacts(model, state, v_free, qd_free)]

    def stepped(selection):
        monkeypatch.setattr(candidates, "SELECTION", selection)
        jax.clear_caches()
        batch = dataclasses.replace(model, robot=jax.tree_util.tree_map(lambda a: a[None], model.robot))
        end = make_rollout(3)(batch, jax.tree_util.tree_map(lambda a: a[None], state), Control(kpa[None]))
        return [np.asarray(a) for a in jax.tree_util.tree_leaves(end)]

    want = chosen("xla")
    assert want[1].sum() >= 3
    for got, w in zip(chosen("interpret"), want):
        np.testing.assert_array_equal(got, w)
    for got, w in zip(stepped("interpret"), stepped("xla")):
        np.testing.assert_array_equal(got, w)
    monkeypatch.setattr(candidates, "SELECTION", "kernel")
    jax.clear_caches()

    def exported(platform):
        return jax.export.export(jax.jit(lambda s: select_contacts(model, s, v_free, qd_free)),
                                 platforms=[platform])(state).mlir_module()

    with pytest.raises(ValueError, match="gpu.triton"):
        exported("cuda")
    assert "triton" not in exported("rocm")
    monkeypatch.setattr(candidates, "SELECTION", "sorted")
    with pytest.raises(ValueError, match="SELECTION"):
        select_contacts(model, state, v_free, qd_free)
    jax.clear_caches()


def test_the_elimination_kernel_forms_xlas_products(landed, monkeypatch):
    """:data:`softcrawl.jaxsim.elimination.FORM`: the elimination's products in one kernel
    (interpreted here) against XLA's on the landed robot (two slots masked). In float32, from the
    same float32 rows, the kernel's products are off the float64 products by at most three times
    XLA's form's own error (or 1e-3 of their scale) and 1e-2 of their scale: both errors are the
    stiff attachment block's inverse in float32, not the order of the sums (measured 6.9e-4 and
    4.1e-4 for ``W_c``, 1.4e-3 for ``P`` and 1.9e-3 for ``x_u`` in both; with four slots
    present 6.9e-3 and 6.2e-3 for ``W_c``); an index or a mask wrong is off by the scale. Three
    whole float64 steps from it end within 1e-9 mm of XLA's. Exported for CUDA the
    float32 step holds the kernel, but not for a GPU older than Ampere (XLA's form, with a
    warning), not for ROCm, and a float64 step takes XLA's form; an unknown form is refused."""
    from softcrawl.jaxsim import elimination, gpu
    from softcrawl.jaxsim.delassus import condense
    from softcrawl.jaxsim.engine import Control, make_rollout, physics_step

    model, state, kpa = landed
    _, rows, inv_chol, qd_free, _ = _step_rows(landed)
    want = condense(rows, inv_chol, qd_free)
    f32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if a.dtype == jnp.float64 else a, rows)
    errors = {}
    for form in ("xla", "interpret"):
        monkeypatch.setattr(elimination, "FORM", form)
        got = condense(f32, inv_chol.astype(jnp.float32), qd_free.astype(jnp.float32))
        errors[form] = [np.abs(np.asarray(a, np.float64) - np.asarray(b)).max() / np.abs(np.asarray(b)).max()
                        for a, b in ((got.W, want.W), (got.q, want.q), (got.P, want.P), (got.x_u, want.x_u))]
    for kernel, xla in zip(errors["interpret"], errors["xla"]):
        assert kernel <= min(max(3 * xla, 1e-3), 1e-2)

    def stepped(form):
        monkeypatch.setattr(elimination, "FORM", form)
        jax.clear_caches()
        batch = dataclasses.replace(model, robot=jax.tree_util.tree_map(lambda a: a[None], model.robot))
        return make_rollout(3)(batch, jax.tree_util.tree_map(lambda a: a[None], state), Control(kpa[None]))

    a, b = stepped("interpret"), stepped("xla")
    assert np.abs(np.asarray(a.x) - np.asarray(b.x)).max() <= 1e-9
    assert np.abs(np.asarray(a.q) - np.asarray(b.q)).max() <= 1e-9 * np.abs(np.asarray(b.q)).max()
    monkeypatch.setattr(elimination, "FORM", "kernel")

    def exported(platform, dtype, capability=None):
        monkeypatch.setattr(gpu, "compute_capability", lambda: capability)
        monkeypatch.setattr(gpu, "_warned", False)
        jax.clear_caches()
        cast = jax.tree_util.tree_map(lambda a: a.astype(dtype) if a.dtype == jnp.float64 else a, (model, state, kpa))
        settings = dataclasses.replace(cast[0].settings, delassus="dense", cholesky="library")
        return jax.export.export(jax.jit(physics_step), platforms=[platform])(
            dataclasses.replace(cast[0], settings=settings), *cast[1:]).mlir_module()

    with pytest.raises(ValueError, match="gpu.triton"):
        exported("cuda", jnp.float32)
    with pytest.warns(UserWarning, match="compiles no Pallas kernels"):
        assert "triton" not in exported("cuda", jnp.float32, (7, 5))
    assert "triton" not in exported("rocm", jnp.float32)
    assert "triton" not in exported("cuda", jnp.float64)
    monkeypatch.setattr(elimination, "FORM", "dense")
    with pytest.raises(ValueError, match="FORM"):
        condense(rows, inv_chol, qd_free)
    jax.clear_caches()


def test_the_pairs_forms_dot_algorithm_reaches_its_product_in_float32_only(landed, monkeypatch):
    """:data:`softcrawl.jaxsim.legs.PAIRS_DOT_ALGORITHM` names the dot algorithm of the pairs
    form's matrix product (for a GPU's tensor cores, which a CPU does not have: XLA's CPU runs
    every preset in float32, so only where the setting goes is testable here): the float32
    leg's traced RID terms carry it on their two products (tetrahedra, triangles), the float64
    leg's do not (the verifying engine keeps full products), and a name that is no
    ``jax.lax.DotAlgorithmPreset`` is a ValueError naming the setting."""
    from softcrawl.jaxsim import legs as leg_motion

    model, state, _ = landed
    f32 = jax.tree_util.tree_map(lambda a: a.astype(jnp.float32) if jnp.issubdtype(a.dtype, jnp.floating) else a,
                                 model.leg)
    q = state.q[0]

    def traced(part, dtype):
        return str(jax.make_jaxpr(lambda a: leg_motion.rid_terms(part, a, 0 * a, 0.03, "pairs"))(q.astype(dtype)))

    assert "TF32_TF32_F32_X3" not in traced(f32, jnp.float32)
    monkeypatch.setattr(leg_motion, "PAIRS_DOT_ALGORITHM", "TF32_TF32_F32_X3")
    assert traced(f32, jnp.float32).count("TF32_TF32_F32_X3") == 2
    assert "TF32_TF32_F32_X3" not in traced(model.leg, jnp.float64)
    monkeypatch.setattr(leg_motion, "PAIRS_DOT_ALGORITHM", "TF32x3")
    with pytest.raises(ValueError, match="PAIRS_DOT_ALGORITHM"):
        traced(f32, jnp.float32)


def test_ptxas_report_reads_each_kernels_registers_and_spills():
    """:func:`softcrawl.jaxsim.cost.ptxas_report` on ptxas' report as XLA logs it (two kernels of
    a step compiled for an H100 without one, the log's lines as they came): each kernel's
    registers and spilled bytes; :func:`~softcrawl.jaxsim.cost.captured_stderr` returns what was
    written to file descriptor 2 (where XLA's C++ logs go) and restores it."""
    import os

    from softcrawl.jaxsim.cost import captured_stderr, ptxas_report

    log = """I1127 09:19:44.872731   13321 subprocess_compilation.cc:349] ptxas warning : Registers are spilled \
to local memory in function 'input_add_reduce_fusion_1', 8 bytes spill stores, 8 bytes spill loads
ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function 'input_add_reduce_fusion_1' for 'sm_90a'
ptxas info    : Function properties for input_add_reduce_fusion_1
    8 bytes stack frame, 8 bytes spill stores, 8 bytes spill loads
ptxas info    : Used 128 registers, used 0 barriers, 8 bytes cumulative stack size
ptxas info    : Compile time = 20.417 ms
I1127 09:22:05.660347   14483 subprocess_compilation.cc:356] ptxas info    : 0 bytes gmem
ptxas info    : Compiling entry function 'apgd_iterations' for 'sm_90a'
ptxas info    : Function properties for apgd_iterations
    0 bytes stack frame, 0 bytes spill stores, 0 bytes spill loads
ptxas info    : Used 128 registers, used 1 barriers
"""
    assert ptxas_report(log) == {
        "input_add_reduce_fusion_1": {"registers": 128, "spill_stores": 8, "spill_loads": 8, "stack": 8},
        "apgd_iterations": {"registers": 128, "spill_stores": 0, "spill_loads": 0, "stack": 0}}
    with captured_stderr() as out:
        os.write(2, b"ptxas info    : Function properties for k\n    0 bytes stack frame, 4 bytes spill stores, "
                    b"4 bytes spill loads\nptxas info    : Used 255 registers\n")
    assert ptxas_report(out[0]) == {"k": {"registers": 255, "spill_stores": 4, "spill_loads": 4, "stack": 0}}


def test_the_cholesky_kernels_step_is_the_librarys(landed, monkeypatch):
    """``Settings.cholesky = "kernel"`` (the legs' and the attachment block's inverse factors in
    one GPU kernel, :mod:`softcrawl.jaxsim.factor`): on a CPU the compiled step is the library's
    to the bit, the traced step holding the kernel for other platforms; with the kernels forced
    (interpreted) for every inverse of the landed robot's step (each leg's step matrix formed,
    factored and its free motion solved in one program, ``factor.step_solve``), the step's modal
    and disk velocities are the library's within 1e-8 of their size (float64). The two factorisations'
    round-off: the legs' step matrices have condition numbers of about 1e5, and their inverse
    factors differ by up to 1.3e-13 of their size; the contact solve amplifies that to 1.8e-10
    (modal) and 4.8e-10 (disk) of the velocities, measured (8e-11 and 2.6e-10 with the legs'
    step matrices formed and solved by XLA around the kernel). A wrong inverse moves them by
    their own size."""
    from softcrawl.jaxsim import factor
    from softcrawl.jaxsim.engine import physics_step

    model, state, kpa = landed
    kernel = dataclasses.replace(model, settings=dataclasses.replace(model.settings, cholesky="kernel"))
    step = jax.jit(physics_step)
    a, b = step(model, state, kpa), step(kernel, state, kpa)
    for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert "pallas_call" in str(jax.make_jaxpr(physics_step)(kernel, state, kpa))
    assert "pallas_call" not in str(jax.make_jaxpr(physics_step)(model, state, kpa))
    monkeypatch.setattr(factor, "_library",
                        lambda A, symmetrize=False: factor.cholesky_inverse(A, "interpret", symmetrize))
    monkeypatch.setattr(factor, "_step_library", partial(factor._step_pallas, interpret=True))
    jax.clear_caches()  # the patched factor is read when the step is traced
    c = step(model, state, kpa)
    for name in ("qdot", "v"):
        x, y = np.asarray(getattr(a, name)), np.asarray(getattr(c, name))
        assert not np.array_equal(x, y)
        assert np.abs(x - y).max() <= 1e-8 * np.abs(x).max(), name
    jax.clear_caches()  # nothing traced with the patched factor outlives the test
