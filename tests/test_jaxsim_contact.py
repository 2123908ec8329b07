"""The JAX contact solve (:mod:`softcrawl.jaxsim.contact`) against the CPU engine's
(:mod:`softcrawl.fem.contact`, :mod:`softcrawl.reduction.constrain`) and closed-form friction.

Float64 throughout (``jax_enable_x64`` is switched on for this module only and restored after),
except the float32 tests."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

from softcrawl.fem.contact import pgs_coulomb as cpu_pgs  # noqa: E402
from softcrawl.reduction.constrain import condense as cpu_condense, solve_condensed  # noqa: E402
from softcrawl.verify.jax_contact import box_on_incline  # noqa: E402

DATA = Path(__file__).parent / "data"
#: Impulse agreement with the CPU Gauss-Seidel (and between padded, batched and single calls),
#: relative to the largest impulse: the two sum their dot products in different orders
#: (measured at most 8e-15 over the cases below).
ROUND_OFF = 1e-13


@pytest.fixture(autouse=True, scope="module")
def _float64(x64):
    """Every test of this module in float64 (``x64``: tests/conftest.py)."""


@pytest.fixture(scope="module")
def C():
    from softcrawl.jaxsim import contact

    return contact


#: The fixed shapes every random problem is padded to (inactive blocks at the end), so each
#: function compiles once: contact slots and bilateral rows.
K, NB = 10, 6


def _random_problem(rng, k: int, nb: int = 0, mu: float = 0.5):
    """``(W, q, mu)``: an SPD Delassus operator of ``nb`` bilateral rows and ``k`` contacts
    (the shape of tests/test_fem.py's random problems), random free velocities."""
    n = nb + 3 * k
    B = rng.standard_normal((n, n))
    return B @ B.T / n + 0.05 * np.eye(n), rng.standard_normal(n), np.full(k, mu)


def _padded(W, q, mu, lam, nb: int = 0, slots: int = K):
    """The problem with inactive blocks appended up to ``slots`` contacts (zero rows):
    ``(W, q, mu, lam, active)``."""
    k = len(mu)
    n = nb + 3 * slots
    Wp, qp, lp = np.zeros((n, n)), np.zeros(n), np.zeros(3 * slots)
    Wp[:len(q), :len(q)], qp[:len(q)], lp[:3 * k] = W, q, lam
    return Wp, qp, np.concatenate([mu, np.full(slots - k, 0.5)]), lp, np.arange(slots) < k


def _cpu(W, q, mu, lam0, sweeps):
    lam = np.array(lam0, float)
    cpu_pgs(W, q, mu, lam, 0.0, sweeps)  # tol 0: every sweep runs
    return lam


def _recorded():
    """The saved real contact problems ``(name, W, q, mu, warm)``: condensed where they have
    bilateral rows (by the CPU :func:`condense`)."""
    z = np.load(DATA / "cycling_contact.npz")
    yield "cycling", z["W"], z["q"], z["mu"], z["warm_start"].ravel()
    z = np.load(DATA / "ill_conditioned_contact.npz")
    _, Wc, qc = cpu_condense(z["W"], z["q"], int(z["n_bilateral_rows"]))
    yield "ill_conditioned", Wc, qc, z["mu"], z["warm_start"].ravel()
    z = np.load(DATA / "repeating_polish.npz")  # (its schur_* problem condenses to failing_*)
    for case in ("failing", "found"):
        yield case, z[f"{case}_W"], z[f"{case}_q"], z[f"{case}_mu"], z[f"{case}_warm_start"]


def _rel(a, b):
    return np.abs(np.asarray(a) - np.asarray(b)).max() / max(np.abs(np.asarray(b)).max(), 1e-300)


@pytest.mark.parametrize("seed", range(3))
def test_pgs_matches_the_cpu_gauss_seidel_on_random_problems(C, seed):
    """Same block update in the same order: after 1, 7 and 60 sweeps from a random warm start
    the impulses equal the CPU function's to round-off (1-10 contacts, SPD, mu 0.5; padded
    to 10 slots)."""
    rng = np.random.default_rng(seed)
    for k in (1, 4, 10):
        W, q, mu = _random_problem(rng, k)
        warm = np.abs(rng.standard_normal(3 * k))
        for sweeps in (1, 7, 60):
            out = C.pgs_coulomb(*_padded(W, q, mu, warm), sweeps)
            assert _rel(out[:3 * k], _cpu(W, q, mu, warm, sweeps)) <= ROUND_OFF


@pytest.mark.parametrize("case", ["cycling", "ill_conditioned", "failing", "found"])
def test_pgs_matches_the_cpu_gauss_seidel_on_recorded_problems(C, case):
    """The saved real problems of reduced robots (condition numbers to 1e5, 7-12 contacts,
    padded to 12 slots), warm-started as recorded: 300 sweeps equal the CPU function's
    impulses to round-off."""
    name, W, q, mu, warm = next(p for p in _recorded() if p[0] == case)
    out = C.pgs_coulomb(*_padded(W, q, mu, warm, slots=12), 300)
    assert _rel(out[:len(q)], _cpu(W, q, mu, warm, 300)) <= ROUND_OFF


def _pad(rng, W, q, lam, nb: int, where_b, where_c):
    """Insert padding rows (random entries) into a problem: bilateral padding rows at positions
    ``where_b`` among the ``nb`` bilateral rows, padding blocks at ``where_c`` among the contacts.
    Returns ``(W, q, lam, bilateral mask, active mask, index of the original rows)``."""
    k = (len(q) - nb) // 3
    b_real = np.ones(nb + len(where_b), bool)
    b_real[where_b] = False
    c_real = np.ones(k + len(where_c), bool)
    c_real[where_c] = False
    rows = np.concatenate([b_real, np.repeat(c_real, 3)])
    take = np.flatnonzero(rows)
    n = len(rows)
    G = rng.standard_normal((n, n))
    Wp, qp, lp = G @ G.T + np.eye(n), rng.standard_normal(n), rng.standard_normal(n)
    Wp[np.ix_(take, take)] = W
    qp[take] = q
    lp[take] = lam
    return Wp, qp, lp[len(b_real):], b_real, c_real, take


def test_padding_blocks_change_nothing(C):
    """Inactive contact blocks and masked bilateral rows with random entries in W, q and the
    warm start, interleaved with the real ones (4 bilateral rows, 7 contacts, padded to 6 and
    10) or all at the end: the real impulses and the residuals agree to round-off, and the
    padding's impulses are exactly 0 (Gauss-Seidel, accelerated projected gradient, the whole
    constraint solve). The accelerated gradient runs to convergence (200 iterations: natural-map
    residual 5e-16) and agrees to 1e-11 (measured 6e-18): at 60 it is not converged on this
    problem (residual 1.4e-9), and its adaptive restart, a decision taken on a sign, can fire at
    another iteration in the other layout on one CPU and not on another (2.5e-9 apart on one,
    6e-13 on others), so that comparison held only where the round-off happened to fall the same
    way. With the padding at the end Gauss-Seidel equals the CPU
    function on the unpadded problem (the random-problem tests)."""
    rng = np.random.default_rng(7)
    nb, k = 4, 7
    W, q, mu = _random_problem(rng, k, nb)
    lam = np.concatenate([np.zeros(nb), np.abs(rng.standard_normal(3 * k))])
    layouts = [_pad(rng, W, q, lam, nb, where_b, where_c) for where_b, where_c in (([4, 5], [7, 8, 9]),
                                                                                  ([0, 3], [0, 4, 9]))]
    mup = np.full(K, 0.5)
    results = []
    for Wp, qp, wp, bmask, cmask, take in layouts:
        Wc, qc, ctake = Wp[NB:, NB:], qp[NB:], take[nb:] - NB
        out = {}
        for solver, n_iter in ((C.pgs_coulomb, 60), (C.apgd_coulomb, 200)):
            lam_c = np.asarray(solver(Wc, qc, mup, wp, cmask, n_iter))
            assert np.all(lam_c[np.repeat(~cmask, 3)] == 0)
            res = C.residuals(Wc, qc, mup, lam_c, cmask)
            out[solver.__name__] = lam_c[ctake], {key: float(v) for key, v in res.items()}
        full = np.asarray(C.solve_constraints(Wp, qp, bmask, mup, wp, cmask, 60))
        assert np.all(full[np.setdiff1d(np.arange(len(full)), take)] == 0)
        out["full"] = full[take], {}
        results.append(out)
    for key, (ref, ref_res) in results[0].items():
        lam_c, res = results[1][key]
        tol = 1e-11 if key == "apgd_coulomb" else ROUND_OFF
        assert _rel(lam_c, ref) <= tol, key
        assert all(abs(res[n] - ref_res[n]) <= tol * max(1.0, ref_res[n]) for n in ref_res), key


def test_vmap_over_robots_equals_one_call_per_robot(C):
    """A batch of 4 robots of different contact patterns (padding masks, mu, warm starts):
    ``jax.vmap`` of each function gives each robot's own call to round-off."""
    rng = np.random.default_rng(3)
    R = 4
    probs = [_random_problem(rng, K, NB, mu=0.3 + 0.3 * r) for r in range(R)]
    W = np.stack([p[0] for p in probs])
    q = np.stack([p[1] for p in probs])
    mu = np.stack([p[2] for p in probs])
    warm = np.abs(rng.standard_normal((R, 3 * K)))
    act = rng.random((R, K)) < 0.7
    bil = rng.random((R, NB)) < 0.8
    for solver in (C.pgs_coulomb, C.apgd_coulomb):
        batch = jax.vmap(lambda *a: solver(*a, 60))(W[:, NB:, NB:], q[:, NB:], mu, warm, act)
        for r in range(R):
            assert _rel(batch[r], solver(W[r, NB:, NB:], q[r, NB:], mu[r], warm[r], act[r], 60)) <= ROUND_OFF
    batch, res = jax.vmap(lambda *a: C.solve_constraints(*a, 60, return_residuals=True))(W, q, bil, mu, warm, act)
    for r in range(R):
        one, one_res = C.solve_constraints(W[r], q[r], bil[r], mu[r], warm[r], act[r], 60, return_residuals=True)
        assert _rel(batch[r], one) <= ROUND_OFF
        assert all(abs(float(res[key][r]) - float(one_res[key])) <= ROUND_OFF * max(1.0, float(one_res[key]))
                   for key in one_res)
    pts = rng.uniform(-1, 1, (R, 20))
    vel = rng.uniform(-20, 20, (R, 20))
    batch = jax.vmap(lambda p, v: C.floor_contacts(p, v, 0.0, 0.5, 8, dt=0.02))(pts, vel)
    for r in range(R):
        for a, b in zip(batch, C.floor_contacts(pts[r], vel[r], 0.0, 0.5, 8, dt=0.02)):
            np.testing.assert_array_equal(a[r], b)


def test_attachments_alone_without_contact_slots_are_solved_exactly(C):
    """A robot with no contact slots (K = 0, in the air): the bilateral rows alone, ``u_b = 0``
    to round-off (regression: the Gauss-Seidel loop failed to trace on an empty block)."""
    rng = np.random.default_rng(5)
    W, q, *_ = _random_problem(rng, 0, NB)
    bil = np.ones(NB, bool)
    lam = C.solve_constraints(W, q, bil, 0.5, np.zeros(0), np.zeros(0, bool), 10, least_squares=False)
    assert lam.shape == (NB,)
    assert np.max(np.abs(W @ np.asarray(lam) + q)) <= ROUND_OFF * np.max(np.abs(q))


@pytest.mark.parametrize("case", ["ill_conditioned", "schur"])
def test_condense_matches_the_cpu_schur_complement(C, case):
    """The recorded attachment blocks (42 and 60 bilateral rows, condition numbers to 5.6e4):
    ``X``, ``Wc`` and ``qc`` equal :func:`softcrawl.reduction.constrain.condense`'s to
    1e-11 relative (LAPACK's and XLA's Cholesky round differently; measured 1.4e-12), with or
    without the least-squares fallback (unused on these regular blocks)."""
    if case == "schur":
        z = np.load(DATA / "repeating_polish.npz")
        W, q, nb = z["schur_W"], z["schur_q"], int(z["schur_nb"])
    else:
        z = np.load(DATA / "ill_conditioned_contact.npz")
        W, q, nb = z["W"], z["q"], int(z["n_bilateral_rows"])
    for least_squares in (True, False):
        for a, b in zip(C.condense(W, q, np.ones(nb, bool), least_squares=least_squares), cpu_condense(W, q, nb)):
            assert _rel(a, b) <= 1e-11


def test_condense_of_redundant_attachments_is_least_squares(C):
    """A bilateral block that is singular (an attachment row repeated): Cholesky fails, and
    like the CPU engine the Schur complement falls back to the pseudo-inverse; the result is
    finite and equals the CPU's to 1e-9 relative."""
    rng = np.random.default_rng(5)
    W, q, _ = _random_problem(rng, K, NB)
    J = np.eye(len(q))
    J[1] = J[0]  # rows 0 and 1 constrain the same thing
    W, q = J @ W @ J.T, J @ q
    out = C.condense(W, q, np.ones(NB, bool))
    for a, b in zip(out, cpu_condense(W, q, NB)):
        assert np.all(np.isfinite(np.asarray(a))) and _rel(a, b) <= 1e-9


def _assert_solution(res, lam, tol_v, tol_f):
    """Every residual of the dict ``res`` (:func:`residuals`) within ``tol_v`` (velocity-like,
    mm/s; the products scaled by the largest impulse of ``lam``) or ``tol_f`` (impulse-like, mN s)."""
    res = {key: float(v) for key, v in res.items()}
    scale_f = max(np.abs(np.asarray(lam)).max(), 1e-300)
    limits = {"penetration": tol_v, "pull": tol_f, "cone": tol_f, "natural_map": tol_f,
              "complementarity": tol_v * scale_f, "dissipation": tol_v * scale_f}
    bad = {key: (res[key], limits[key]) for key in limits if not res[key] <= limits[key]}
    assert not bad, bad


@pytest.mark.parametrize("seed", range(3))
def test_solve_constraints_matches_the_cpu_solve_where_gauss_seidel_converges(C, seed):
    """Random problems with 6 bilateral rows and 2-7 contacts (padded to 10 slots): where the
    CPU's :func:`solve_condensed` finds the solution (its Gauss-Seidel converges to 1e-10
    relative change, or else its exact polish succeeds), 400 sweeps of the JAX solve
    (Gauss-Seidel, or the accelerated projected gradient) give the same impulses to 1e-9
    relative (measured 9e-11) and satisfy every condition to 1e-11 of the velocity and
    impulse scales (measured 1.2e-13), the bilateral rows included."""
    rng = np.random.default_rng(20 + seed)
    checked = 0
    for _ in range(8):
        k = int(rng.integers(2, 8))
        W, q, mu = _random_problem(rng, k, NB)
        ref, _, rel, polished = solve_condensed(W, q, NB, mu, np.zeros(3 * k), 1e-10, 2000, 0)
        if not (polished or rel <= 1e-10):
            continue
        checked += 1
        Wp, qp, mup, warm, act = _padded(W, q, mu, np.zeros(3 * k), NB)
        for method in ("pgs", "apgd"):
            lam, res = C.solve_constraints(Wp, qp, np.ones(NB, bool), mup, warm, act, 400, method=method,
                                           return_residuals=True)
            lam = np.asarray(lam)[:len(q)]
            assert _rel(lam, ref) <= 1e-9, method
            assert float(res.pop("bilateral")) <= 1e-11 * np.abs(q).max()
            _assert_solution(res, lam[NB:], 1e-11 * np.abs(q).max(), 1e-11 * np.abs(ref).max())
    assert checked >= 6


def test_the_ill_conditioned_recorded_problem_is_solved_by_the_accelerated_gradient(C):
    """The recorded ill-conditioned problem (4 attachments, 7 contacts of a reduced leg; the
    CPU engine needs its exact polish after 500 sweeps): 1,000 accelerated projected gradient
    iterations reach the polished solution's velocities to 1e-8 of the velocity scale
    (measured 3.2e-9) and satisfy every condition to 1e-8 (natural-map residual: measured
    8e-11 of the impulse scale), where 1,000 Gauss-Seidel sweeps are still 1e-6 away (measured 3e-6; Gauss-Seidel
    converges slowly on the ill-conditioned W of several contacts on one reduced leg)."""
    from softcrawl.fem.contact import solve_constraints as cpu_solve

    z = np.load(DATA / "ill_conditioned_contact.npz")
    W, q, nb, mu = z["W"], z["q"], int(z["n_bilateral_rows"]), z["mu"]
    sol = cpu_solve(W, q, nb, mu, z["warm_start"], 1e-8, 250)
    assert sol.polished
    ref = np.concatenate([sol.bilateral, sol.contact.ravel()])
    k = len(mu)
    vscale, fscale = np.abs(q).max(), np.abs(ref).max()
    args = (W, q, np.ones(nb, bool), mu, np.zeros(3 * k), np.ones(k, bool), 1000)
    lam, res = C.solve_constraints(*args, method="apgd", return_residuals=True)
    assert np.abs(W @ (np.asarray(lam) - ref)).max() <= 1e-8 * vscale
    assert float(res.pop("bilateral")) <= 1e-8 * vscale
    _assert_solution(res, lam[nb:], 1e-8 * vscale, 1e-8 * fscale)
    _, res = C.solve_constraints(*args, method="pgs", return_residuals=True)
    assert float(res["natural_map"]) > 1e-6 * fscale


@pytest.mark.parametrize("method", ["pgs", "apgd"])
def test_a_box_below_the_friction_angle_sticks(C, method):
    """verification.md: a block on an incline sticks iff tan(theta) <= mu (mu 1.2, threshold
    50.19 deg). At 45 deg the box's four corners stay at rest to 1e-12 of the free velocity
    dt g (no creep; measured 3e-16 with both solvers) and the normal impulses carry the normal
    weight, sum lam_n = m g cos(theta) dt, to 1e-12 relative (measured 3e-16)."""
    W, q, mu, mgdt, dt = box_on_incline(45.0, 30.0, 1.2)
    lam = np.asarray(C.solve_constraints(W, q, np.zeros(0, bool), mu, np.zeros(12), np.ones(4, bool), 600,
                                         method=method))
    u = (W @ lam + q).reshape(4, 3)
    assert np.abs(u).max() <= 1e-12 * dt * 9810.0
    assert abs(lam[::3].sum() - mgdt * np.cos(np.radians(45.0))) <= 1e-12 * mgdt


@pytest.mark.parametrize("method", ["pgs", "apgd"])
def test_a_box_above_the_friction_angle_slides_with_the_coulomb_acceleration(C, method):
    """verification.md: above the friction angle the block slides with acceleration
    g (sin(theta) - mu cos(theta)). At 60 deg (mu 1.2), gravity tilted towards 30 deg in the
    floor plane: every corner's velocity after one step is dt g (sin - mu cos) along that
    direction with no normal velocity, and the friction impulse is mu times the normal one,
    opposite to the slip (maximal dissipation), all to 1e-12 relative (measured 3e-15)."""
    theta, phi = 60.0, 30.0
    W, q, mu, mgdt, dt = box_on_incline(theta, phi, 1.2)
    lam = np.asarray(C.solve_constraints(W, q, np.zeros(0, bool), mu, np.zeros(12), np.ones(4, bool), 600,
                                         method=method))
    u, L = (W @ lam + q).reshape(4, 3), lam.reshape(4, 3)
    th, ph = np.radians(theta), np.radians(phi)
    speed = dt * 9810.0 * (np.sin(th) - 1.2 * np.cos(th))
    want = np.tile([0.0, speed * np.cos(ph), speed * np.sin(ph)], (4, 1))
    assert np.abs(u - want).max() <= 1e-12 * speed
    total = L.sum(axis=0)
    assert abs(total[0] - mgdt * np.cos(th)) <= 1e-12 * mgdt
    np.testing.assert_allclose(total[1:], -1.2 * total[0] * np.array([np.cos(ph), np.sin(ph)]), rtol=1e-12)


def _incline_velocities(theta: float, dt: float):
    """The closed-form results of the box of :func:`softcrawl.verify.jax_contact.box_on_incline`
    at ``theta`` deg (gravity towards 30 deg in the floor plane, mu 1.2) after one step from
    rest: the slip speed ``dt g max(sin - mu cos, 0)`` (mm/s) and every corner's velocity ``(4,
    3)`` (normal, tangents)."""
    th, ph = np.radians(theta), np.radians(30.0)
    speed = max(dt * 9810.0 * (np.sin(th) - 1.2 * np.cos(th)), 0.0)
    return speed, np.tile([0.0, speed * np.cos(ph), speed * np.sin(ph)], (4, 1))


@pytest.mark.parametrize("storage", [None, "float16"])
@pytest.mark.parametrize("theta", [45.0, 60.0])
def test_the_engines_warm_started_solve_reaches_the_closed_form_results(C, theta, storage):
    """The engine's solve (:func:`solve_contacts`: 48 accelerated gradient iterations without
    restart, the default) warm-started from the last step's impulses, as the engine does, on the
    box's step repeated (the box on the incline at rest, or sliding at its steady slip): the
    closed-form results of the two tests above to the same 1e-12 within 8 steps (measured: the
    45-deg box sticks to 5e-16 after 4 steps, the 60-deg one slides with the Coulomb acceleration
    to 9e-15 after 6; one cold solve is 2.5e-4 and 1.2e-2 away). The engine's contact solve is
    iterative across steps: a contact state that persists converges to round-off.

    So does the solve reading the operator in float16 (``storage``, the float32 engine's
    default), by its iterative refinement (measured 6e-16 after 4 and 7 steps; an operator
    merely rounded to float16 would stop at float16's rounding, about 1e-4)."""
    W, q, mu, mgdt, dt = box_on_incline(theta, 30.0, 1.2)
    lam = np.zeros(12)
    for _ in range(8):
        lam = np.asarray(C.solve_contacts(W, q, mu, lam, np.ones(4, bool), "apgd", C.DEFAULT_ITERATIONS["apgd"],
                                          storage=storage))
    u, L = (W @ lam + q).reshape(4, 3), lam.reshape(4, 3)
    th, ph = np.radians(theta), np.radians(30.0)
    speed, want = _incline_velocities(theta, dt)
    assert np.abs(u - want).max() <= 1e-12 * dt * 9810.0
    assert abs(L[:, 0].sum() - mgdt * np.cos(th)) <= 1e-12 * mgdt
    if speed:
        np.testing.assert_allclose(L[:, 1:].sum(axis=0), -1.2 * L[:, 0].sum() * np.array([np.cos(ph), np.sin(ph)]),
                                   rtol=1e-12)


#: Float32 bound on the fused kernel's results against closed form and XLA's iterations, in units
#: of the scales named by each test: 16 times float32's rounding unit (1.2e-7). The kernel sums
#: its matrix-vector products in another order than XLA's; both reach about 4e-7.
FUSED_TOL = 2e-6


@pytest.mark.parametrize("theta", [45.0, 60.0])
def test_the_fused_kernels_warm_started_solve_reaches_the_closed_form_results(C, theta):
    """The engine's GPU solve with its iterations in one kernel (``fused``,
    :mod:`softcrawl.jaxsim.fused`; here in Pallas' interpreter, the kernel's program run on a
    CPU) in float32, operator read in float16, warm-started across the box's repeated step as
    the test above: after 6 steps the corners' velocities are the closed-form ones to
    :data:`FUSED_TOL` of ``dt g`` (measured 1.4e-7 at 45 deg, 3.7e-7 at 60; XLA's float32
    iterations 1.3e-7 and 2.7e-7; one cold solve is 3.7e-4 and 3.1e-3 away), and the normal
    impulses carry the weight to :data:`FUSED_TOL` (measured 8.0e-8 and 1.5e-7)."""
    W, q, mu, mgdt, dt = (np.asarray(a, np.float32) for a in box_on_incline(theta, 30.0, 1.2))
    lam = np.zeros(12, np.float32)
    for _ in range(6):
        lam = np.asarray(C.solve_contacts(W, q, mu, lam, np.ones(4, bool), "apgd", C.DEFAULT_ITERATIONS["apgd"],
                                          storage="float16", fused="interpret"))
    assert lam.dtype == np.float32
    u, L = (W.astype(float) @ lam + q).reshape(4, 3), lam.reshape(4, 3)
    _, want = _incline_velocities(theta, dt)
    assert np.abs(u - want).max() <= FUSED_TOL * dt * 9810.0
    assert abs(L[:, 0].sum() - mgdt * np.cos(np.radians(theta))) <= FUSED_TOL * mgdt


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_fused_kernel_iterates_as_xlas_unrolled_iterations(C, dtype):
    """The kernel's solve (interpreted: its scaling, rounding, refinement and 48 iterations)
    against XLA's unrolled one, both with the operator in float16 and the iterations in
    ``dtype``, on random problems of 2-10 contacts padded to 10 slots and warm-started from a
    solve: impulses within :data:`FUSED_TOL` (float32; measured 7.1e-7) or 1e-12 (float64;
    measured 2.1e-15) of the largest, the products summed in another order; padding contacts
    exactly 0."""
    rng = np.random.default_rng(5)
    for _ in range(4):
        k = int(rng.integers(2, 11))
        W, q, mu, warm, act = _padded(*_random_problem(rng, k), np.zeros(3 * k))
        arrays = [a.astype(dtype) for a in (W, q, mu)]
        warm = np.asarray(C.apgd_coulomb(*arrays, warm.astype(dtype), act, 20, restart=False, storage="float16"))
        ref = np.asarray(C.apgd_coulomb(*arrays, warm, act, 48, restart=False, storage="float16"))
        out = np.asarray(C.apgd_coulomb(*arrays, warm, act, 48, restart=False, storage="float16", fused="interpret"))
        assert out.dtype == dtype
        assert _rel(out, ref) <= (FUSED_TOL if dtype == np.float32 else 1e-12)
        assert not out[3 * k:].any()


def test_the_fused_kernels_variants_give_the_same_impulses(C, monkeypatch):
    """The kernel's tuning constants (:data:`softcrawl.jaxsim.fused.ROW_BLOCK`, ``NUM_WARPS``,
    ``LOOP_PRODUCT``, which ``benchmarks/fused_kernel.py`` times on a GPU) change how a program
    is laid out, not its arithmetic: in the interpreter (float32; warps do not reach it) blocks
    of 16, 32 and 64 rows, the product unrolled or looped, give the same impulses to the bit,
    each row's product summed over all columns in one reduction."""
    from softcrawl.jaxsim import fused

    W, q, mu, warm, act = _padded(*_random_problem(np.random.default_rng(9), 8), np.zeros(24))
    args = [a.astype(np.float32) for a in (W, q, mu, warm)]

    def solve():
        jax.clear_caches()  # the constants are read when a solve is traced
        return np.asarray(C.apgd_coulomb(*args[:3], args[3], act, 48, restart=False, storage="float16",
                                         fused="interpret"))

    monkeypatch.setattr(fused, "ROW_BLOCK", 64)
    monkeypatch.setattr(fused, "LOOP_PRODUCT", False)
    want = solve()
    assert np.abs(want).max() > 0
    for rows, loop in ((32, False), (16, False), (64, True), (16, True)):
        monkeypatch.setattr(fused, "ROW_BLOCK", rows)
        monkeypatch.setattr(fused, "LOOP_PRODUCT", loop)
        np.testing.assert_array_equal(solve(), want)
    jax.clear_caches()


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_fused_kernel_holding_its_operator_on_chip_iterates_as_reading_it(C, monkeypatch, dtype):
    """:data:`softcrawl.jaxsim.fused.RESIDENT_ROWS`: in float32 the program keeps the scaled
    float16 operator through the iterations and forms each product as a matrix product with ``y``
    split into two float16 columns, instead of reading the operator from its scratch output every
    iteration. On random problems of 2-10 contacts padded to 10 slots, blocks of 16 to 128 rows:
    float32 impulses within :data:`FUSED_TOL` of the largest of the kernel reading its scratch
    (measured 2.1e-7); float64, which the held form does not serve (two float16 columns carry 22
    bits of ``y``), the scratch's to the bit; padding contacts exactly 0. An operator too large to
    hold (86 contacts: ``N = 512``, a float16 copy of 512 KB beyond
    :data:`~softcrawl.jaxsim.fused.HELD_BYTES`) keeps the scratch's form: its impulses to the bit."""
    from softcrawl.jaxsim import fused

    def solve(held, arrays, warm, act):
        monkeypatch.setattr(fused, "RESIDENT_ROWS", held)
        jax.clear_caches()  # read when a solve is traced
        return np.asarray(C.apgd_coulomb(*arrays, warm, act, 48, restart=False, storage="float16", fused="interpret"))

    rng = np.random.default_rng(5)
    for held in (128, 64, 32, 16):
        k = int(rng.integers(2, 11))
        W, q, mu, warm, act = _padded(*_random_problem(rng, k), np.zeros(3 * k))
        arrays = [a.astype(dtype) for a in (W, q, mu)]
        warm = np.asarray(C.apgd_coulomb(*arrays, warm.astype(dtype), act, 20, restart=False, storage="float16"))
        want, got = solve(None, arrays, warm, act), solve(held, arrays, warm, act)
        assert got.dtype == dtype and np.abs(want).max() > 0
        if dtype == np.float32:
            assert _rel(got, want) <= FUSED_TOL
        else:
            np.testing.assert_array_equal(got, want)
        assert not got[3 * k:].any()
    if dtype == np.float32:
        W, q, mu = (a.astype(dtype) for a in _random_problem(rng, 86))
        zero, act = np.zeros(258, dtype), np.ones(86, bool)
        np.testing.assert_array_equal(solve(128, (W, q, mu), zero, act), solve(None, (W, q, mu), zero, act))
    jax.clear_caches()


def test_the_solve_holds_its_operator_only_on_cards_with_room_for_it(monkeypatch):
    """:func:`softcrawl.jaxsim.fused.held_bytes`: a program may hold the 128 KiB operator on a card
    with 227 KiB of shared memory a program (compute capability 9.0, 10.0, 10.3), in the
    interpreter and without a GPU (a kernel compiled for an H100 without one); on the A100 (8.0,
    163 KiB) and the 99-KiB cards (8.6, 8.9, 12.0: A10, L4, L40, RTX 4090 and 5090) Triton could
    not place it beside its own exchanges, and the solve keeps the scratch's form."""
    from softcrawl.jaxsim import fused

    class Card:
        def __init__(self, capability):
            self.compute_capability = capability

    for capability, want in (("9.0", fused.HELD_BYTES), ("10.0", fused.HELD_BYTES), ("8.0", 0), ("8.9", 0),
                             ("12.0", 0)):
        monkeypatch.setattr(jax, "local_devices", lambda backend=None, c=capability: [Card(c)])
        assert fused.held_bytes() == want, capability
        assert fused.held_bytes(interpret=True) == fused.HELD_BYTES
    monkeypatch.undo()
    if all(d.platform == "cpu" for d in jax.devices()):  # no GPU here
        assert fused.held_bytes() == fused.HELD_BYTES


@pytest.mark.parametrize("shape", [(2, 3, 2), (3, 1, 4), (0, 2, 3), (2, 2, 0)])
def test_the_fused_kernel_reads_an_operator_in_its_parts_as_formed(C, shape):
    """:func:`softcrawl.jaxsim.fused.fused_solve` given a random SPD operator in its
    :class:`~softcrawl.jaxsim.schur.SchurOperator` parts (``K_d`` disk contacts, ``L`` legs of
    ``K_l``, the legs' blocks with 2 leading rows and columns the kernel skips) forms the
    entries as :meth:`~softcrawl.jaxsim.schur.SchurOperator.dense` does and gives the impulses
    of the same solve on the formed operator to round-off, in the interpreter: the two programs
    compile to different fusions, whose rounding may differ (float32 within :data:`FUSED_TOL`
    of the largest impulse, measured up to 1.2e-8; float64 within 1e-12, measured 8e-17), and
    ``S`` off by 1e-4 fails both bounds. A disk or legs without contacts (``K_d`` or ``K_l`` 0)
    are read formed."""
    from softcrawl.jaxsim.fused import fused_solve
    from softcrawl.jaxsim.schur import SchurOperator

    Kd, L, Kl = shape
    nd, nl = 3 * Kd, 3 * Kl
    n = nd + L * nl
    rng = np.random.default_rng(n)
    U = rng.standard_normal((n + 3, n)) / n
    S = U.T @ U
    spd = [(lambda a: a @ a.T / k + np.eye(k))(rng.standard_normal((k, k))) for k in [nd] + [nl + 2] * L]
    for dtype in (np.float32, np.float64):
        parts = SchurOperator(*(jnp.asarray(a, dtype) for a in (
            spd[0], np.stack(spd[1:]), S[:, :nd], S[:, nd:].reshape(n, L, nl).transpose(1, 0, 2))))
        W = parts.dense()
        K = n // 3
        q = jnp.asarray(np.where(np.arange(n) % 3 == 0, -1.0, 0.3) * rng.standard_normal(n) ** 2, dtype)
        mu, lam0 = jnp.full(K, 0.6, dtype), jnp.asarray(np.abs(rng.standard_normal(n)) * 0.1, dtype)
        act, betas = jnp.asarray(rng.random(K) < 0.8), jnp.asarray(C.momentum_schedule(48), dtype)
        want = np.asarray(fused_solve(W, q, mu, lam0, act, betas, interpret=True))
        assert np.abs(want).max() > 0
        got = np.asarray(fused_solve(parts, q, mu, lam0, act, betas, interpret=True))
        tol = FUSED_TOL if dtype == np.float32 else 1e-12
        assert _rel(got, want) <= tol
        off = dataclasses.replace(parts, s_legs=parts.s_legs * (1 + 1e-4), s_disk=parts.s_disk * (1 + 1e-4))
        assert _rel(fused_solve(off, q, mu, lam0, act, betas, interpret=True), want) > tol  # S 1e-4 off: caught


def test_split_columns_carry_a_vector_to_float32s_accuracy_in_two_float16_columns():
    """:func:`softcrawl.jaxsim.fused.split_columns`: ``m (Y[:, 0] + Y[:, 1])`` gives ``y`` back to
    2^-23 of its largest entry ``m = max |y|`` (measured 2^-24: the second column's rounding,
    float16's smallest subnormal being 2^-24) whatever the scale of ``y`` (1e-6 to 1e4, beyond
    float16's range of 6e-5 to 65504), the other columns 0; ``y = 0`` splits into zeros with
    ``m`` positive."""
    from softcrawl.jaxsim.fused import SPLIT_COLUMNS, split_columns

    rng = np.random.default_rng(4)
    for scale in (1e-6, 1.0, 1e4):
        y = (scale * rng.standard_normal(256) * rng.uniform(0, 1, 256) ** 6).astype(np.float32)
        m, Y = split_columns(jnp.asarray(y), jnp.float16)
        Y = np.asarray(Y)
        assert Y.dtype == np.float16 and Y.shape == (256, SPLIT_COLUMNS) and not Y[:, 2:].any()
        assert float(m) == np.abs(y).max()
        back = float(m) * (Y[:, 0].astype(np.float64) + Y[:, 1].astype(np.float64))
        assert np.abs(back - y).max() <= 2.0 ** -23 * float(m)
    m, Y = split_columns(jnp.zeros(16, jnp.float32), jnp.float16)
    assert float(m) > 0 and not np.asarray(Y).any()


def test_kernel_sass_counts_the_instructions_of_the_outermost_loops():
    """``benchmarks/kernel_sass.py`` reads the loops' instructions from ``nvdisasm -c`` text: each
    outermost loop in the order of the code (a label to the furthest backward branch to it; the
    last here 4 instructions with its inner loop's 2, the solve kernel's iterations, after the
    larger loop that prepares the operator), opcodes without predicates or modifiers; every loop
    with its parent and its own instructions (``loop_tree``), and the RID kernel's instructions a
    leg (``leg_instructions``: outside the loops once, each family's block loop times its blocks,
    its edge loop times the edges too), None where the loops are not the families', and the solve
    kernel's a robot (``solve_instructions``), None without the iterations' loop."""
    from helpers import benchmark_module

    sass = benchmark_module("kernel_sass")
    text = """
        /*0000*/                   MOV R1, c[0x0][0x28] ;
.L_x_2:
        /*0010*/                   LDG.E R5, desc[UR4][R4.64] ;
        /*0020*/                   STG.E desc[UR4][R4.64], R5 ;
        /*0030*/                   FMUL R5, R5, R5 ;
        /*0040*/                   FMUL R5, R5, R5 ;
        /*0050*/               @P2 BRA `(.L_x_2) ;
.L_x_0:
        /*0060*/                   LDG.E R2, desc[UR4][R4.64] ;
.L_x_1:
        /*0070*/                   FADD R3, R2, R2 ;
        /*0080*/               @P0 BRA `(.L_x_1) ;
        /*0090*/              @!P1 BRA `(.L_x_0) ;
        /*00a0*/                   EXIT ;
"""
    assert sass.outer_loops(text) == [{"LDG": 1, "STG": 1, "FMUL": 2, "BRA": 1}, {"LDG": 1, "FADD": 1, "BRA": 2}]
    assert sass.outer_loops("        /*0000*/                   EXIT ;") == []
    tree = sass.loop_tree(text)
    assert [(lp["parent"], lp["total"], dict(lp["opcodes"])) for lp in tree] == [
        (None, 5, {"LDG": 1, "STG": 1, "FMUL": 2, "BRA": 1}), (None, 4, {"LDG": 1, "BRA": 1}),
        (1, 2, {"FADD": 1, "BRA": 1})]
    # read as the RID kernel: the second loop a family of 40 elements with 3 edges; the first is not
    assert sass.leg_instructions(text, [(40, 4)], elements=16, split=1, warps=2) is None
    one = text.replace("@P2 BRA `(.L_x_2)", "NOP")  # now one family's loop, its edge loop inside
    assert sass.leg_instructions(one, [(40, 4)], elements=16, split=1, warps=2) == 2 * (7 + 3 * (2 + 3 * 2))
    # read as the solve kernel: outside the loops once, the preparation's loop 3 times (its full row
    # blocks), the iterations 48 times and the looped product's blocks inside them 3 times each
    assert sass.solve_instructions(text, full=3, iterations=48, warps=8) == 8 * (2 + 3 * 5 + 48 * (2 + 3 * 2))
    assert sass.solve_instructions(one, full=3, iterations=48, warps=8) == 8 * (7 + 48 * (2 + 3 * 2))
    assert sass.solve_instructions("        /*0000*/                   EXIT ;", 3, 48, 8) is None


def test_the_fused_kernels_row_blocks_cover_the_rows_and_no_more_of_the_padding():
    """:func:`softcrawl.jaxsim.fused.row_blocks`: for every row count up to 300 and block size
    16, 32 and 64, full blocks then tail blocks of powers of two (at least 16) cover rows ``0 ..
    n`` in order, each inside the padded size ``N`` and aligned to its size; past ``n`` they
    reach less than 16 rows (the paper preset's 240 rows: 240, not 256; the crawl preset's 132:
    144)."""
    from softcrawl.jaxsim.factor import padded_size
    from softcrawl.jaxsim.fused import row_blocks

    assert row_blocks(240, 64) == (3, [(192, 32), (224, 16)])
    assert row_blocks(132, 64) == (2, [(128, 16)])
    for rb in (16, 32, 64):
        for n in range(1, 301):
            full, tail = row_blocks(n, rb)
            blocks = [(b * rb, rb) for b in range(full)] + tail
            assert [s for s, _ in blocks] == list(np.cumsum([0] + [z for _, z in blocks[:-1]]))
            end = blocks[-1][0] + blocks[-1][1]
            assert n <= end < n + 16 and end <= padded_size(n)
            assert all(z in (16, 32, 64) and z <= rb and s % z == 0 for s, z in blocks)


def test_the_fused_kernel_is_refused_where_it_does_not_apply(C):
    """``fused`` needs the float16 storage's refinement, the unrolled iterations, the dense
    operator: anything else is a ValueError, not a silent fallback."""
    W, q, mu, warm, act = (np.asarray(a) for a in _padded(*_random_problem(np.random.default_rng(0), 2), np.zeros(6)))
    f32 = [a.astype(np.float32) for a in (W, q, mu, warm)]
    for kwargs in ({}, {"storage": "float16", "restart": True}, {"storage": "float16", "op": W.astype(np.float32)},
                   {"storage": "float16", "fused": "triton"}):
        with pytest.raises(ValueError, match="fused"):
            C.apgd_coulomb(*f32, act, 5, **{"restart": False, "fused": "interpret", **kwargs})


def test_float32_solves_agree_with_float64_within_the_stated_tolerance(C):
    """Float32 (inputs cast, the same functions) against float64 on random problems of 2-10
    contacts solved to convergence (400 sweeps or iterations): impulses within 1e-5 of the
    largest impulse (measured 2e-7 Gauss-Seidel, 7e-7 accelerated gradient: float32 round-off
    6e-8 amplified by the operators' conditioning) and residuals within 1e-5 of the scales
    (natural map measured 4e-7)."""
    rng = np.random.default_rng(11)
    for _ in range(5):
        k = int(rng.integers(2, 11))
        W, q, mu, warm, act = _padded(*_random_problem(rng, k), np.zeros(3 * k))
        for solver in (C.pgs_coulomb, C.apgd_coulomb):
            ref = solver(W, q, mu, warm, act, 400)
            out = solver(*(a.astype(np.float32) for a in (W, q, mu, warm)), act, 400)
            assert out.dtype == jnp.float32
            assert _rel(out, ref) <= 1e-5
            out = np.asarray(out, float)
            _assert_solution(C.residuals(W, q, mu, out, act), out, 1e-5 * np.abs(q).max(), 1e-5 * np.abs(ref).max())


def test_float32_solve_of_the_ill_conditioned_recorded_problem_gets_the_velocities_right(C):
    """The recorded ill-conditioned problem (condensed condition number 1.3e5) solved whole in
    float32, 1,600 Gauss-Seidel sweeps or 3,200 accelerated gradient iterations (its safe
    Gershgorin step is shorter than a sweep's per-contact steps): the constraint velocities
    ``W lam + q`` (what moves the robot) are those of the CPU engine's exact solution to 1e-5 of
    the velocity scale (measured 2.9e-6 Gauss-Seidel, 3.5e-6 accelerated gradient; 1.1e-5 after
    1,600 iterations), and so are the attachments' (measured 4.2e-6); the impulses themselves
    only to 1e-3 of the largest (measured 1.4e-4: float32 round-off times the condition number)."""
    from softcrawl.fem.contact import solve_constraints as cpu_solve

    z = np.load(DATA / "ill_conditioned_contact.npz")
    W, q, nb, mu = z["W"], z["q"], int(z["n_bilateral_rows"]), z["mu"]
    sol = cpu_solve(W, q, nb, mu, z["warm_start"], 1e-8, 250)
    ref = np.concatenate([sol.bilateral, sol.contact.ravel()])
    k, f32, vscale = len(mu), np.float32, np.abs(q).max()
    for method, n in (("pgs", 1600), ("apgd", 3200)):
        lam, res = C.solve_constraints(W.astype(f32), q.astype(f32), np.ones(nb, bool), mu.astype(f32),
                                       np.zeros(3 * k, f32), np.ones(k, bool), n, method=method,
                                       return_residuals=True)
        lam = np.asarray(lam, float)
        assert np.abs(W @ (lam - ref)).max() <= 1e-5 * vscale, method
        assert float(res["bilateral"]) <= 1e-5 * vscale
        assert _rel(lam, ref) <= 1e-3


def test_residuals_measure_each_violated_condition(C):
    """Hand-made impulses on W = I (u = lam + q), one contact per violation, mu 0.5: each
    residual reports exactly the violation it is named for."""
    W, mu = np.eye(6), np.full(2, 0.5)
    act = np.ones(2, bool)

    def res(lam, q):
        out = C.residuals(W, np.asarray(q, float), mu, np.asarray(lam, float), act)
        return {key: float(v) for key, v in out.items()}

    exact = res([1.0, 0.5, 0.0, 0.0, 0.0, 0.0], [-1.0, -1.5, 0.0, 2.0, 0.0, 0.0])  # slipping; separating
    assert max(exact.values()) <= 1e-15
    r = res([-0.25, 0.0, 0.0, 0.0, 0.0, 0.0], [-0.75, 0.0, 0.0, 0.0, 0.0, 0.0])  # pulling, penetrating
    assert r["pull"] == 0.25 and r["penetration"] == 1.0 and r["complementarity"] == 0.25
    r = res([1.0, 0.8, 0.0, 0.0, 0.0, 0.0], [-1.0, -0.8, 0.0, 0.0, 0.0, 0.0])  # outside the cone
    assert r["cone"] == pytest.approx(0.3)
    r = res([1.0, 0.5, 0.0, 0.0, 0.0, 0.0], [-1.0, -0.5, 1.0, 0.0, 0.0, 0.0])  # slip at 90 deg to friction
    assert r["dissipation"] == pytest.approx(0.5) and r["natural_map"] > 0.1
    r = res([1.0, 0.2, 0.0, 0.0, 0.0, 0.0], [-1.0, -0.2, 0.3, 0.0, 0.0, 0.0])  # creeping inside the cone
    assert r["dissipation"] == pytest.approx(0.15) and r["natural_map"] > 0.1


def test_extra_candidates_above_the_floor_change_no_impulse(C):
    """floor_contacts' rule (its docstring): every candidate within the contact distance enters
    the solve, a superset of the CPU engine's grown set. Candidates that the smaller set's
    solution leaves separating (here u_n = 1 mm/s) get no impulse in the larger solve and the
    others' impulses stay the same, to 1e-9 relative after 400 sweeps (measured: equal; random
    problems of 6 contacts plus 4 candidates, coupled through W)."""
    rng = np.random.default_rng(4)
    for _ in range(3):
        W, q, mu = _random_problem(rng, K)
        n = 18
        small = np.asarray(C.pgs_coulomb(*_padded(W[:n, :n], q[:n], mu[:6], np.zeros(n)), 400))[:n]
        q = q.copy()
        q[n::3] = 1.0 - W[n::3, :n] @ small  # the extra candidates separate at the small set's solution
        act = np.ones(K, bool)
        big = np.asarray(C.pgs_coulomb(W, q, mu, np.zeros(3 * K), act, 400))
        assert np.all(big[n:] == 0)
        assert _rel(big[:n], small) <= 1e-9


def test_floor_contacts_keeps_the_k_lowest_predicted_gaps_in_point_order(C):
    """Six points, K = 3: the three of smallest predicted gap min(g, g + dt v_z) are chosen, in
    point order, active where that gap is below the contact distance, with their current gaps;
    more slots than points is refused."""
    pts = np.array([5.0, 0.2, 3.0, -0.1, 2.0, 0.4])
    vel = np.zeros(6)
    vel[2] = -200.0  # falls 4 mm in 20 ms: predicted gap -1
    idx, active, gap = C.floor_contacts(pts, vel, 0.0, 0.3, 3, dt=0.02)
    np.testing.assert_array_equal(idx, [1, 2, 3])
    np.testing.assert_array_equal(active, [True, True, True])
    np.testing.assert_allclose(gap, [0.2, 3.0, -0.1])
    idx, active, gap = C.floor_contacts(pts, vel, 0.0, 0.3, 5, dt=0.02)
    np.testing.assert_array_equal(idx, [1, 2, 3, 4, 5])
    np.testing.assert_array_equal(active, [True, True, True, False, False])
    with pytest.raises(ValueError, match="exceed"):
        C.floor_contacts(pts, vel, 0.0, 0.3, 7, dt=0.02)


@pytest.mark.parametrize("P", [1024, 1179, 3000])
def test_the_two_stage_selection_picks_what_one_top_k_picks(C, P):
    """``smallest_k`` (two stages from ``SMALLEST_K_SPLIT`` values on: a leg's 1,179 collision
    points) returns exactly the indices of ``lax.top_k(-values, K)``, sorted, also where many
    values are equal (integers: the lower indices of equal values win in both) and where the
    smallest values crowd into one group. Leaving the chosen groups in the order of their minima
    instead of their indices before the second stage breaks ties at the K-th value differently
    and fails the draws of integers below P / 4."""
    from jax import lax

    assert P >= C.SMALLEST_K_SPLIT
    rng = np.random.default_rng(P)
    draws = [rng.normal(size=P), rng.integers(0, 6, P).astype(float), np.where(np.arange(P) < 40, -1.0, 1.0)
             + 1e-3 * rng.normal(size=P)] + [rng.integers(0, P // 4, P).astype(float) for _ in range(20)]
    for K in (1, 8, 12, 16):
        for v in draws:
            np.testing.assert_array_equal(np.asarray(C.smallest_k(jnp.asarray(v), K)),
                                          np.sort(np.asarray(lax.top_k(-jnp.asarray(v), K)[1])))


def test_an_unknown_method_is_refused(C):
    W, q, mu = _random_problem(np.random.default_rng(0), 2)
    with pytest.raises(ValueError, match="method"):
        C.solve_constraints(W, q, np.zeros(0, bool), mu, np.zeros(6), np.ones(2, bool), 5, method="newton")
