"""Frictional contact and bilateral constraints of one robot in JAX, with fixed shapes.

The problem is the CPU engine's (:mod:`softcrawl.fem.contact`, physics.md "Contact with the
floor"): constraint velocities ``u = W lam + q`` (``W`` the Delassus operator, mm/s per mN s;
``q`` mm/s including the gap and drift terms), the first ``nb`` rows bilateral (``u = 0``,
eliminated by a Schur complement), then ``K`` floor contacts with rows (normal, tangent 1,
tangent 2) under Signorini (``u_n >= 0 _|_ lam_n >= 0``) and Coulomb's law with maximal
dissipation (``|lam_t| <= mu lam_n``; ``u_t = 0`` inside the cone, ``u_t`` opposite to
``lam_t`` on its boundary). Impulses are in mN s.

Every function works on ONE robot with static shapes: ``K`` contact blocks of which those with
``active`` False are padding (impulse 0, their rows of ``W`` and ``q`` ignored), ``nb``
bilateral rows masked the same way. They are ``jax.jit``-able and ``jax.vmap``-able over a
batch of robots, in float32 or float64 (the dtype of ``W``); the iterations are
``lax.fori_loop`` s, so nothing runs on the host per iteration and the compile time does not
grow with ``K`` or the number of sweeps.

Solvers:

- :func:`pgs_coulomb`: projected block Gauss-Seidel, the CPU engine's block update in its order
  (Jean 1999, "The non-smooth contact dynamics method", CMAME 177; Duriez et al. 2006).
  Sequential over contacts: ``K`` dependent steps per sweep.
- :func:`apgd_coulomb`: Nesterov-accelerated projected gradient on the cone complementarity
  problem (Mazhar, Heyn, Negrut, Tasora 2015, "Using Nesterov's method to accelerate multibody
  dynamics with friction and contact", ACM TOG 34(3): their APGD with its gradient restart,
  here with a fixed step ``1 / L`` instead of their line search), with De Saxce's change of
  variable ``u_n -> u_n + mu |u_t|`` (De Saxce and Feng 1998, "The bipotential method", Math.
  Comput. Modelling 28) so that its fixed point is the Coulomb problem above rather than the
  convex relaxation (which would let a slipping contact lift off at ``u_n = mu |u_t|``), on the
  Delassus operator scaled per contact to unit normal diagonal. All contacts at once: one
  matrix-vector product per iteration.

Which to use: Gauss-Seidel is the CPU engine's iteration (the same numbers in float64, for
comparisons with it) and needs fewer sweeps on well-conditioned operators (random ones of 40
contacts: a relative natural-map residual of 1e-7 in 50 sweeps, where the accelerated gradient
needs 200-400 iterations). On the recorded problems of reduced robots (condition numbers to
1e5, 7-12 contacts) the accelerated gradient reaches 1e-6 within 400 to 1,600 iterations,
Gauss-Seidel within 1,600 to 3,200 sweeps (one of the four problems not in 3,200). Its
iterations have no sequential dependence across contacts: on a CPU one took 2x to 25x less time
than a sweep (40 contacts, 1 to 64 robots, ``benchmarks/gpu_contact.py``), so it wins on the
ill-conditioned problems, while Gauss-Seidel wins on well-conditioned batches (to 1e-7 on a
CPU: level at 16 robots, 2.3x to 2.9x faster at 64; one robot alone is solved 1.5x to 2x faster
by the accelerated gradient). On an accelerator a sweep costs ``K`` dependent steps.

Precision: in float32 the velocities ``W lam + q`` of the recorded ill-conditioned problem
(condition number 1.3e5) come out within 1e-5 of their scale, its impulses within 1e-3 of the
largest (tests/test_jaxsim_contact.py); in float64 both solvers reach round-off.

Neither runs the CPU engine's exact active-set polish (a data-dependent sequence of dense
solves); :func:`residuals` measures how far a solution is from satisfying every condition.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import cho_factor, cho_solve

#: Power iterations estimating the largest eigenvalue of the scaled Delassus operator
#: (:func:`apgd_coulomb`'s step), and the safety factor on the estimate (power iteration
#: approaches it from below; a step above ``2 / L`` diverges).
POWER_ITERATIONS, LIPSCHITZ_SAFETY = 30, 1.1


def _blocks(W, mu, lam0, active):
    """Common set-up: ``(dtype, mu (K,), lam0 masked (3K,), row mask (3K,))``."""
    dtype = jnp.result_type(W)
    K = active.shape[0]
    mu = jnp.broadcast_to(jnp.asarray(mu, dtype), (K,))
    rows = jnp.repeat(jnp.asarray(active, bool), 3)
    return dtype, mu, jnp.where(rows, jnp.asarray(lam0, dtype), 0), rows


@partial(jax.jit, static_argnames="n_sweeps")
def pgs_coulomb(W, q, mu, lam0, active, n_sweeps: int):
    """Projected block Gauss-Seidel for frictional contact, ``n_sweeps`` sweeps.

    Per active block ``i`` in order (rows ``3i``: normal, ``3i+1, 3i+2``: tangents), the
    update of :func:`softcrawl.fem.contact.pgs_coulomb`: ``lam_n <- max(0, lam_n - u_n /
    W_nn)``; then, with the tangential velocities of the updated normal impulse,
    ``lam_t <- lam_t - u_t / w_t`` (``w_t`` the mean of the two tangential diagonal entries)
    scaled back onto the disk ``|lam_t| <= mu lam_n`` if outside. In float64 and with the same
    sweeps it gives the CPU function's impulses to round-off (which has no fixed sweep count:
    it stops at a relative change ``tol``; ``tol = 0`` runs all its sweeps).

    Args:
        W: ``(3K, 3K)`` Delassus operator (symmetric positive semi-definite; positive diagonal
            on active blocks), mm/s per mN s.
        q: ``(3K,)`` constraint velocities at zero impulse, mm/s.
        mu: scalar or ``(K,)`` friction coefficients.
        lam0: ``(3K,)`` warm start, mN s (its inactive blocks are ignored).
        active: ``(K,)`` bool, False for padding blocks (impulse 0).
        n_sweeps: number of sweeps (static).

    Returns:
        ``(3K,)`` impulses, mN s, zero on inactive blocks.
    """
    dtype, mu, lam, _ = _blocks(W, mu, lam0, active)
    W, q = jnp.asarray(W, dtype), jnp.asarray(q, dtype)
    K = active.shape[0]
    diag = jnp.diagonal(W).reshape(K, 3)
    wn = jnp.where(active, diag[:, 0], 1)
    wt = jnp.where(active, 0.5 * (diag[:, 1] + diag[:, 2]), 1)

    def block(i, lam):
        r = 3 * i
        rows = lax.dynamic_slice_in_dim(W, r, 3, axis=0)
        qi = lax.dynamic_slice_in_dim(q, r, 3)
        old = lax.dynamic_slice_in_dim(lam, r, 3)
        ln = jnp.maximum(old[0] - (qi[0] + rows[0] @ lam) / wn[i], 0)
        ut = qi[1:] + rows[1:] @ lam.at[r].set(ln)
        t = old[1:] - ut / wt[i]
        nt = jnp.sqrt(t[0] * t[0] + t[1] * t[1])
        lim = mu[i] * ln
        out = nt > lim
        t = jnp.where(out, t * (lim / jnp.where(out, nt, 1)), t)
        new = jnp.where(active[i], jnp.stack([ln, t[0], t[1]]), old)
        return lax.dynamic_update_slice_in_dim(lam, new, r, 0)

    return lax.fori_loop(0, n_sweeps, lambda _, lam: lax.fori_loop(0, K, block, lam), lam)


def project_cone(lam, mu):
    """Euclidean projection of impulses ``(K, 3)`` (normal first) onto the Coulomb cones
    ``|lam_t| <= mu lam_n``: unchanged inside, 0 in the polar cone ``mu |lam_t| <= -lam_n``,
    else ``lam_n' = (lam_n + mu |lam_t|) / (1 + mu^2)``, ``lam_t' = mu lam_n' lam_t / |lam_t|``
    (the closed-form projection onto a second-order cone, as in Mazhar et al. 2015)."""
    n, t = lam[:, 0], lam[:, 1:]
    nt = jnp.sqrt(jnp.sum(t * t, axis=1))
    inside = nt <= mu * n
    polar = mu * nt <= -n
    ln = (n + mu * nt) / (1 + mu * mu)
    scale = jnp.where(inside | polar, 0, mu * ln / jnp.where(nt > 0, nt, 1))
    out = jnp.concatenate([ln[:, None], t * scale[:, None]], axis=1)
    return jnp.where(inside[:, None], lam, jnp.where(polar[:, None], 0, out))


def _de_saxce(u, mu):
    """Velocities ``(K, 3)`` with De Saxce's normal ``u_n + mu |u_t|``: complementary to the
    impulses in the Coulomb cone exactly when they solve the Coulomb problem."""
    ut = jnp.sqrt(jnp.sum(u[:, 1:] * u[:, 1:], axis=1))
    return u.at[:, 0].add(mu * ut)


def _largest_eigenvalue(A, v):
    """Largest eigenvalue of the symmetric positive semi-definite ``A`` by
    :data:`POWER_ITERATIONS` power iterations from ``v`` (a lower estimate)."""
    def power(_, v):
        w = A @ v
        return w / jnp.maximum(jnp.linalg.norm(w), jnp.finfo(A.dtype).tiny)

    v = lax.fori_loop(0, POWER_ITERATIONS, power, v / jnp.maximum(jnp.linalg.norm(v), 1))
    return jnp.maximum(v @ (A @ v), jnp.finfo(A.dtype).tiny)


@partial(jax.jit, static_argnames="n_iter")
def apgd_coulomb(W, q, mu, lam0, active, n_iter: int):
    """Accelerated projected gradient descent for frictional contact, ``n_iter`` iterations.

    With ``S`` the per-contact scaling ``1 / sqrt(W_nn)`` (one scalar per block, which keeps the
    cones), iterates ``x = lam / S`` on ``Ws = S W S``: ``x' = P(y - g / L)`` with ``g = Ws y +
    S q`` after De Saxce's change (module doc), ``P`` the projection onto the cones,
    ``L`` the largest eigenvalue of ``Ws`` (power iteration, :data:`LIPSCHITZ_SAFETY`), and
    Nesterov's extrapolation ``y = x' + beta (x' - x)``, restarted when ``g . (x' - x) > 0``
    (Mazhar et al. 2015). Returns the iterate with the smallest gradient mapping
    ``L |y - x'|`` met (the paper keeps the one of smallest residual).

    Args and returns as :func:`pgs_coulomb` (``n_iter`` for ``n_sweeps``; one iteration is
    one product with ``W``, the arithmetic of one Gauss-Seidel sweep, but all contacts at once).
    """
    dtype, mu, lam, rows = _blocks(W, mu, lam0, active)
    K = active.shape[0]
    W, q = jnp.asarray(W, dtype), jnp.asarray(q, dtype)
    s = jnp.repeat(jnp.where(active, lax.rsqrt(jnp.where(active, jnp.diagonal(W)[::3], 1)), 0), 3)
    Ws = s[:, None] * W * s[None, :]
    qs = s * q
    step = 1 / (LIPSCHITZ_SAFETY * _largest_eigenvalue(Ws, rows.astype(dtype)))

    def proj(x):
        return jnp.where(rows, project_cone(x.reshape(K, 3), mu).reshape(-1), 0)

    def grad(y):
        return _de_saxce((Ws @ y + qs).reshape(K, 3), mu).reshape(-1)

    def it(_, c):
        x, y, theta, best, best_r = c
        g = grad(y)
        xn = proj(y - step * g)
        r = jnp.linalg.norm(y - xn) / step
        better = r < best_r
        best, best_r = jnp.where(better, xn, best), jnp.where(better, r, best_r)
        tn = 0.5 * (-theta * theta + theta * jnp.sqrt(theta * theta + 4))
        beta = theta * (1 - theta) / (theta * theta + tn)
        restart = g @ (xn - x) > 0
        yn = jnp.where(restart, xn, xn + beta * (xn - x))
        return xn, yn, jnp.where(restart, 1, tn).astype(dtype), best, best_r

    x0 = proj(lam / jnp.where(rows, s, 1))
    one = jnp.ones((), dtype)
    *_, best, _ = lax.fori_loop(0, n_iter, it, (x0, x0, one, x0, jnp.asarray(jnp.inf, dtype)))
    return s * best


@partial(jax.jit, static_argnames="least_squares")
def condense(W, q, bilateral, *, least_squares: bool = True):
    """Eliminate the bilateral rows ``0 .. nb - 1`` (``u = 0`` there) by a Schur complement.

    The masked block ``W_bb`` (identity on rows where ``bilateral`` is False) is factorized by
    Cholesky, or, if it is singular (redundant attachments), inverted in the least-squares
    sense, as :func:`softcrawl.reduction.constrain.condense` does.

    Args:
        W: ``(nb + 3K, nb + 3K)`` Delassus operator, q: ``(nb + 3K,)`` (as in the module doc).
        bilateral: ``(nb,)`` bool, False for padding rows (impulse 0).
        least_squares: keep the least-squares fallback (static). Under ``jax.vmap`` both
            branches run for every robot, and the pseudo-inverse costs about 6x the rest of
            this function (18 bilateral rows, 40 contacts, measured on a CPU); without it a
            singular block gives NaN or impulses dominated by round-off.

    Returns:
        ``(X, Wc, qc)``: ``X = W_bb^-1 [q_b, W_bc]`` ``(nb, 3K + 1)`` (zero on padding rows),
        the contact problem's ``Wc`` ``(3K, 3K)`` and ``qc`` ``(3K,)``; the bilateral impulses
        are ``-(X[:, 0] + X[:, 1:] lam_c)``.
    """
    W, q = jnp.asarray(W), jnp.asarray(q, jnp.result_type(W))
    nb = bilateral.shape[0]
    m = jnp.asarray(bilateral, bool)
    Wbb = jnp.where(m[:, None] & m[None, :], W[:nb, :nb], jnp.eye(nb, dtype=W.dtype))
    rhs = jnp.where(m[:, None], jnp.concatenate([q[:nb, None], W[:nb, nb:]], axis=1), 0)
    X = cho_solve(cho_factor(Wbb, lower=True), rhs)
    if least_squares:
        X = lax.cond(jnp.all(jnp.isfinite(X)), lambda: X, lambda: jnp.linalg.pinv(Wbb, hermitian=True) @ rhs)
    Wcb = W[nb:, :nb]
    return X, W[nb:, nb:] - Wcb @ X[:, 1:], q[nb:] - Wcb @ X[:, 0]


_SOLVERS = {"pgs": pgs_coulomb, "apgd": apgd_coulomb}


@partial(jax.jit, static_argnames=("n_sweeps", "method", "return_residuals", "least_squares"))
def solve_constraints(W, q, bilateral, mu, lam0, active, n_sweeps: int, method: str = "pgs",
                      return_residuals: bool = False, least_squares: bool = True):
    """Attachments and floor contacts of one robot: :func:`condense`, the contact solve,
    then the bilateral impulses by back-substitution.

    Args:
        W: ``(nb + 3K, nb + 3K)``, q: ``(nb + 3K,)`` (module doc); bilateral: ``(nb,)`` bool mask
            of the bilateral rows; mu (scalar or ``(K,)``), lam0 (the contacts' warm start
            ``(3K,)``), active ``(K,)``, n_sweeps: as :func:`pgs_coulomb`.
        method: ``"pgs"`` (:func:`pgs_coulomb`) or ``"apgd"`` (:func:`apgd_coulomb`, ``n_sweeps``
            iterations), static.
        return_residuals: also return :func:`residuals` of the contact problem plus
            ``"bilateral"``: the largest ``|u|`` on the active bilateral rows (mm/s).
        least_squares: as :func:`condense`.

    Returns:
        ``lam`` ``(nb + 3K,)`` (mN s; zero on padding), or ``(lam, residuals dict)``.

    Raises:
        ValueError: unknown ``method``.
    """
    if method not in _SOLVERS:
        raise ValueError(f"method must be one of {sorted(_SOLVERS)}, got {method!r}")
    nb = bilateral.shape[0]
    X, Wc, qc = condense(W, q, bilateral, least_squares=least_squares)
    # no contact slots (a robot in the air): only the attachments
    lam_c = _SOLVERS[method](Wc, qc, mu, lam0, active, n_sweeps) if active.shape[0] else qc
    lam = jnp.concatenate([-(X[:, 0] + X[:, 1:] @ lam_c), lam_c])
    if not return_residuals:
        return lam
    res = residuals(Wc, qc, mu, lam_c, active)
    ub = W[:nb] @ lam + q[:nb]
    res["bilateral"] = jnp.max(jnp.abs(ub), initial=0, where=jnp.asarray(bilateral, bool))
    return lam, res


@jax.jit
def residuals(W, q, mu, lam, active):
    """How far impulses are from solving the contact problem: the largest violation over the
    active contacts of each condition (all zero at a solution).

    Args:
        W, q, mu, active: as :func:`pgs_coulomb`; lam: ``(3K,)`` impulses, mN s.

    Returns:
        dict of scalars:
        ``penetration`` ``max(-u_n, 0)`` (mm/s), ``pull`` ``max(-lam_n, 0)`` (mN s),
        ``complementarity`` ``|lam_n u_n|`` (mN mm), ``cone`` ``max(|lam_t| - mu lam_n, 0)``
        (mN s), ``dissipation`` ``|mu lam_n |u_t| + lam_t . u_t|`` (mN mm: zero when the contact
        sticks or its friction opposes its slip at the cone's boundary; with ``complementarity``
        the terms of De Saxce's bipotential, De Saxce and Feng 1998), and ``natural_map``
        ``|lam - P(lam - u~ / W_nn)|`` (mN s, ``u~`` De Saxce's velocities, ``P`` the cone
        projection: zero exactly at a solution; Acary, Bremond and Huber 2018, "On solving
        contact problems with Coulomb friction: formulations and numerical comparisons").
    """
    dtype, mu, lam, _ = _blocks(W, mu, lam, active)
    K = active.shape[0]
    act = jnp.asarray(active, bool)
    u = (jnp.asarray(W, dtype) @ lam + jnp.asarray(q, dtype)).reshape(K, 3)
    L = lam.reshape(K, 3)
    ltn = jnp.sqrt(jnp.sum(L[:, 1:] ** 2, axis=1))
    utn = jnp.sqrt(jnp.sum(u[:, 1:] ** 2, axis=1))
    wn = jnp.where(act, jnp.diagonal(jnp.asarray(W, dtype))[::3], 1)
    nat = L - project_cone(L - _de_saxce(u, mu) / wn[:, None], mu)

    def worst(x):
        return jnp.max(x, initial=0, where=act)

    return {
        "penetration": worst(-u[:, 0]),
        "pull": worst(-L[:, 0]),
        "complementarity": worst(jnp.abs(L[:, 0] * u[:, 0])),
        "cone": worst(ltn - mu * L[:, 0]),
        "dissipation": worst(jnp.abs(mu * L[:, 0] * utn + jnp.sum(L[:, 1:] * u[:, 1:], axis=1))),
        "natural_map": worst(jnp.sqrt(jnp.sum(nat * nat, axis=1))),
    }


def floor_contacts(points, velocities, floor_z, distance, K: int, *, dt):
    """Choose at most ``K`` floor contact candidates among ``P`` points, with a fixed shape.

    Rule: a point's predicted gap is ``min(g, g + dt v_z)`` with ``g = z - floor_z`` (the CPU
    engine's candidate test for disk nodes, :func:`softcrawl.reduction.constrain.constrain_robots`
    point 1; it bounds a leg's points by their modal speed instead, a superset). The ``K`` points
    of smallest predicted gap are taken (``lax.top_k``), ordered by point index (so Gauss-Seidel
    visits contacts in the CPU engine's node order when ``points`` are in that order), and are
    active where the predicted gap is below ``distance``.

    Relation to the CPU engine's contact set (same docstring, point 2): it starts from last
    step's loaded contacts or the deepest penetrating candidates and grows by those the solve
    leaves below the floor. Here every candidate within ``distance`` enters the solve at once,
    with its gap term ``g / dt`` in ``q``, so it is a superset of the CPU engine's final set; a
    candidate the CPU engine leaves out stays above the floor without impulse, so where the
    contact problem has a unique solution both sets give the same impulses. Where more than
    ``K`` points are within ``distance`` the farthest are dropped: the caller sizes ``K`` (or
    checks ``sum(min(g, g + dt v_z) < distance) <= K``).

    Args:
        points: ``(P, 3)`` candidate positions, mm. velocities: ``(P, 3)`` their free
            velocities, mm/s. floor_z, distance: floor height and contact distance, mm.
        K: number of contact slots (static, ``K <= P``). dt: time step, s.

    Returns:
        ``(idx (K,) int, active (K,) bool, gap (K,) current gaps g, mm)``.

    Raises:
        ValueError: ``K > P``.
    """
    P = points.shape[0]
    if K > P:
        raise ValueError(f"K = {K} contact slots exceed the {P} candidate points")
    gap = points[:, 2] - floor_z
    pred = jnp.minimum(gap, gap + dt * velocities[:, 2])
    _, idx = lax.top_k(-pred, K)
    idx = jnp.sort(idx)
    return idx, pred[idx] < distance, gap[idx]
