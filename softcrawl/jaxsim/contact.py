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
batch of robots, in float32 or float64 (the dtype of ``W``).

Solvers:

- :func:`pgs_coulomb`: projected block Gauss-Seidel, the CPU engine's block update in its order
  (Jean 1999, "The non-smooth contact dynamics method", CMAME 177; Duriez et al. 2006).
  Sequential over contacts: ``K`` dependent steps per sweep (``lax.fori_loop`` s).
- :func:`apgd_coulomb`: Nesterov-accelerated projected gradient on the cone complementarity
  problem (Mazhar, Heyn, Negrut, Tasora 2015, "Using Nesterov's method to accelerate multibody
  dynamics with friction and contact", ACM TOG 34(3), with a fixed step ``1 / L`` instead of
  their line search), with De Saxce's change of variable ``u_n -> u_n + mu |u_t|`` (De Saxce
  and Feng 1998, "The bipotential method", Math. Comput. Modelling 28) so that its fixed point
  is the Coulomb problem above rather than the convex relaxation (which would let a slipping
  contact lift off at ``u_n = mu |u_t|``), on the Delassus operator scaled per contact to unit
  normal diagonal. All contacts at once: one matrix-vector product per iteration. Run to
  convergence with an adaptive restart, or as the engine runs it: a fixed number of unrolled
  iterations without restart (:func:`solve_contacts`).

The engine's default is the accelerated gradient, 48 iterations per step, warm-started from the
last step's impulses (:data:`DEFAULT_ITERATIONS`). A physics step's latency on a GPU is set by
its chain of dependent kernels, and a Gauss-Seidel sweep is ``K`` of them: 100 sweeps over 80
contacts made the previous engine's step 184,545 operations and 8,101 loop trips in sequence;
the unrolled gradient makes it under 550 and one (``benchmarks/step_cost.py``). Per step it solves
less accurately than 100 sweeps (on landed, pressurised robots of the paper's space, median
penetration velocity 1.2 against 0.10 mm/s, ``benchmarks/contact_accuracy.py``: 0.02 mm per
step at dt 0.02 s, which the next step's gap term takes back), but the solve continues across
steps from its warm start: a contact state that persists converges to round-off within a few
steps (tests/test_jaxsim_contact.py), and trajectories follow the CPU engine's as closely as
with 100 sweeps (tests/test_jaxsim_robot.py, ``benchmarks/jax_ranking.py``). Gauss-Seidel
stays selectable (``solver="pgs"``): the CPU engine's iteration, the same numbers in float64.

On single problems solved to convergence: Gauss-Seidel needs fewer sweeps on well-conditioned
operators (random ones of 40 contacts: a relative natural-map residual of 1e-7 in 50 sweeps,
where the accelerated gradient needs 200-400 iterations); on the recorded problems of reduced
robots (condition numbers to 1e5, 7-12 contacts) the accelerated gradient reaches 1e-6 within
400 to 1,600 iterations, Gauss-Seidel within 1,600 to 3,200 sweeps (one of the four problems
not in 3,200).

Precision: in float32 the velocities ``W lam + q`` of the recorded ill-conditioned problem
(condition number 1.3e5) come out within 1e-5 of their scale, its impulses within 1e-3 of the
largest (tests/test_jaxsim_contact.py); in float64 both solvers reach round-off.

Neither runs the CPU engine's exact active-set polish (a data-dependent sequence of dense
solves); :func:`residuals` measures how far a solution is from satisfying every condition.
"""

from __future__ import annotations

import math
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.linalg import cho_factor, cho_solve

from softcrawl.jaxsim.cone import cone_projection, de_saxce_term
from softcrawl.jaxsim.gpu import cuda_kernel
from softcrawl.jaxsim.schur import SchurOperator

#: The normal column of ``(K, 3)`` impulses or velocities (a broadcastable mask).
_NORMAL = np.arange(3) == 0


def _dtype(W):
    """The dtype of an operator, formed or in its parts (:class:`~softcrawl.jaxsim.schur.SchurOperator`)."""
    return W.dtype if isinstance(W, SchurOperator) else jnp.result_type(W)


def _blocks(W, mu, lam0, active):
    """Common set-up: ``(dtype, mu (K,), lam0 masked (3K,), row mask (3K,))``."""
    dtype = _dtype(W)
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


def _columns(v):
    """The normal and the two tangential components of ``(K, 3)`` vectors, each broadcast to
    ``(K, 3)``: a cone's arithmetic then runs on whole ``(K, 3)`` arrays (three times the
    elementwise work) and its result is a select, not a stack, which XLA compiles as a
    concatenation of its own: on a GPU an accelerated-gradient iteration is then one product
    with ``W`` and one fused loop (``benchmarks/RESULTS.md``)."""
    return tuple(jnp.broadcast_to(v[:, i:i + 1], v.shape) for i in range(3))


def project_cone(lam, mu):
    """Euclidean projection of impulses ``(K, 3)`` (normal first) onto the Coulomb cones
    ``|lam_t| <= mu lam_n`` (:func:`softcrawl.jaxsim.cone.cone_projection`), written with selects
    and broadcasts (:func:`_columns`) so that a compiled iteration fuses it with its neighbours."""
    n, t1, t2 = _columns(lam)
    ln, f = cone_projection(n, t1, t2, jnp.reshape(mu, (-1, 1)))
    return jnp.where(_NORMAL, ln, lam * f)


def _de_saxce(u, mu):
    """Velocities ``(K, 3)`` with De Saxce's normal ``u_n + mu |u_t|``
    (:func:`softcrawl.jaxsim.cone.de_saxce_term`)."""
    _, t1, t2 = _columns(u)
    return u + jnp.where(_NORMAL, de_saxce_term(t1, t2, jnp.reshape(mu, (-1, 1))), 0)


def gershgorin_bound(W):
    """An upper bound ``max_i sum_j |W_ij|`` of the largest eigenvalue of the symmetric ``W``
    (Gershgorin's circle theorem; padding rows and columns are zero): one reduction, where power
    iteration needs a chain of products and approaches the eigenvalue from below. On the scaled
    Delassus operators of landed robots it is 1.23 to 1.48 times the largest eigenvalue
    (problems recorded from 3- to 6-legged robots)."""
    return jnp.maximum(jnp.max(jnp.sum(jnp.abs(W), axis=1)), jnp.finfo(W.dtype).tiny)


def momentum_schedule(n_iter: int) -> tuple[float, ...]:
    """Nesterov's extrapolation weights ``beta_k`` of ``n_iter`` iterations without restart
    (``theta_0 = 1``, ``theta_{k+1}^2 = (1 - theta_{k+1}) theta_k^2``, ``beta_k = theta_k (1 -
    theta_k) / (theta_k^2 + theta_{k+1})``; Mazhar et al. 2015, Alg. 2): constants of the compiled
    program."""
    out, theta = [], 1.0
    for _ in range(n_iter):
        tn = 0.5 * (-theta * theta + theta * (theta * theta + 4) ** 0.5)
        out.append(theta * (1 - theta) / (theta * theta + tn))
        theta = tn
    return tuple(out)


@partial(jax.jit, static_argnames=("n_iter", "restart", "storage", "fused"))
def apgd_coulomb(W, q, mu, lam0, active, n_iter: int, restart: bool = True, op=None, storage=None,
                 fused: str | None = None):
    """Accelerated projected gradient descent for frictional contact, ``n_iter`` iterations.

    With ``S`` the per-contact scaling ``1 / sqrt(W_nn)`` (one scalar per block, which keeps the
    cones), iterates ``x = lam / S`` on ``Ws = S W S``: ``x' = P(y - g / L)`` with ``g = Ws y +
    S q`` after De Saxce's change (module doc), ``P`` the projection onto the cones,
    ``L`` :func:`gershgorin_bound` of ``Ws`` (a safe step ``1 / L``), and Nesterov's
    extrapolation ``y = x' + beta (x' - x)`` (Mazhar et al. 2015).

    ``restart`` (static) chooses between two uses:

    * True: the momentum restarts when ``g . (x' - x) > 0`` (O'Donoghue and Candes 2015,
      "Adaptive restart for accelerated gradient schemes"), in a ``lax.fori_loop``, and the
      iterate of smallest gradient mapping ``|y - x'|`` is returned (Mazhar et al. keep the one of
      smallest residual): it converges to round-off on ill-conditioned problems, for solves run
      to convergence.
    * False: no restart, the weights :func:`momentum_schedule` are constants and the iterations
      are unrolled: an iteration is one matrix-vector product and elementwise work, with no
      reduction and no loop in the compiled program (on a GPU each loop trip costs a round trip
      to the host). The engine's warm-started solve, a few dozen iterations per step
      (:func:`solve_contacts`): over 2.5-s scenes of landing and actuation its trajectories are
      as close to the CPU engine's as with the adaptive restart (0.11 and 0.10 mm mean node
      distance against 0.12 and 0.13 mm at 48 iterations, ``tests/test_jaxsim_robot.py``'s
      scene); over hundreds of iterations from a cold start it oscillates.

    Args and returns as :func:`pgs_coulomb` (``n_iter`` for ``n_sweeps``; one iteration is
    one product with ``W``, the arithmetic of one Gauss-Seidel sweep, but all contacts at once);
    ``op``, where given, applies ``W`` in the iterations (``op @ y``: the same operator kept in
    factors, :class:`softcrawl.jaxsim.delassus.DelassusBlocks`), ``W`` then giving only the
    scaling and the step.

    ``storage`` (static), where given, is the dtype in which the iterations read the scaled
    operator (``"float16"``: half the bytes of float32), by mixed-precision iterative refinement
    (Higham 2002, "Accuracy and Stability of Numerical Algorithms", ch. 12): the gradient at the
    warm start ``x0`` is formed once at full precision and the iterations add the reduced
    operator ``Ws~``'s product with their step from it, ``g(y) = Ws~ (y - x0) + (Ws x0 + S q)``,
    computed as ``Ws~ y + ((Ws - Ws~) x0 + S q)`` with the products summed in ``W``'s dtype.
    The fixed point then errs by ``(Ws - Ws~)(x* - x0)``: float16's rounding
    (``2^-11`` relative; scaled to a unit normal diagonal, ``Ws``'s entries are of order one, at
    most 1.18 on landed robots of the paper's space, far inside float16's range) times the step
    from the warm start, which vanishes as a persisting contact state's warm start converges
    across steps.

    ``fused`` (static), with ``storage`` and without ``restart``, runs the solve, scaling and
    refinement included, in one kernel (:func:`softcrawl.jaxsim.fused.fused_solve`): ``"gpu"``
    compiled for a GPU, ``"interpret"`` in Pallas' interpreter (any platform; the tests'); None:
    XLA's iterations. ``W`` may be given in its parts
    (:class:`~softcrawl.jaxsim.schur.SchurOperator`): the kernel reads them, XLA's iterations
    form ``W`` first.

    Raises:
        ValueError: ``fused`` without ``storage``, with ``restart`` or with ``op``, or not one of
            None, ``"gpu"``, ``"interpret"``.
    """
    if fused not in (None, "gpu", "interpret"):
        raise ValueError(f"fused must be None, 'gpu' or 'interpret', got {fused!r}")
    if fused and (storage is None or restart or op is not None):
        raise ValueError("the fused iterations need a storage dtype, no restart and no op")
    if isinstance(W, SchurOperator) and not fused:
        W = W.dense()
    dtype, mu, lam, rows = _blocks(W, mu, lam0, active)
    if fused:
        from softcrawl.jaxsim.fused import fused_solve

        return fused_solve(W if isinstance(W, SchurOperator) else jnp.asarray(W, dtype), jnp.asarray(q, dtype), mu,
                           jnp.asarray(lam0, dtype), active, jnp.asarray(momentum_schedule(n_iter), dtype),
                           storage=storage, interpret=fused == "interpret")
    K = active.shape[0]
    W, q = jnp.asarray(W, dtype), jnp.asarray(q, dtype)
    s = jnp.repeat(jnp.where(active, lax.rsqrt(jnp.where(active, jnp.diagonal(W)[::3], 1)), 0), 3)
    Ws = s[:, None] * W * s[None, :]
    qs = s * q
    step = 1 / gershgorin_bound(Ws)
    live = rows.reshape(K, 3)

    def proj(z):
        return jnp.where(live, project_cone(z, mu), 0)

    x0 = proj(jnp.where(rows, lam / jnp.where(rows, s, 1), 0).reshape(K, 3))
    if op is not None:
        def grad(y):
            return _de_saxce((s * (op @ (s * y.reshape(-1))) + qs).reshape(K, 3), mu)
    else:
        if storage is None:
            Wi, g0 = Ws, qs
        else:  # materialised once (the barrier keeps XLA from fusing the rounding into every product)
            Wi = lax.optimization_barrier(Ws.astype(storage))
            g0 = (Ws - Wi.astype(dtype)) @ x0.reshape(-1) + qs  # Ws x0 + S q - Ws~ x0 (docstring)

        def grad(y):
            Wy = lax.dot_general(Wi, y.reshape(-1), (((1,), (0,)), ((), ())), preferred_element_type=dtype)
            return _de_saxce((Wy + g0).reshape(K, 3), mu)

    if restart:
        def it(_, c):
            x, y, theta, best, best_r = c
            g = grad(y)
            xn = proj(y - step * g)
            r = jnp.sqrt(jnp.sum((y - xn) ** 2))  # the gradient mapping's size, times the step
            best, best_r = jnp.where(r < best_r, xn, best), jnp.minimum(r, best_r)
            tn = 0.5 * (-theta * theta + theta * jnp.sqrt(theta * theta + 4))
            beta = theta * (1 - theta) / (theta * theta + tn)
            again = jnp.sum(g * (xn - x)) > 0
            return (xn, jnp.where(again, xn, xn + beta * (xn - x)), jnp.where(again, 1, tn).astype(dtype), best,
                    best_r)

        x = lax.fori_loop(0, n_iter, it, (x0, x0, jnp.ones((), dtype), x0, jnp.asarray(jnp.inf, dtype)))[3]
    else:
        x = y = x0
        for beta in momentum_schedule(n_iter):
            xn = proj(y - step * grad(y))
            x, y = xn, xn + beta * (xn - x)
    return s * x.reshape(-1)


#: Iterations per step of each solver by default (:func:`solve_contacts`).
DEFAULT_ITERATIONS = {"apgd": 48, "pgs": 100}


def check_solver(solver: str, iterations: int | None) -> int:
    """The iterations of ``solver`` (``iterations``, or its :data:`DEFAULT_ITERATIONS` for None).

    Raises:
        ValueError: an unknown solver, or fewer than one iteration.
    """
    if solver not in DEFAULT_ITERATIONS:
        raise ValueError(f"contact solver must be one of {sorted(DEFAULT_ITERATIONS)}, got {solver!r}")
    n = DEFAULT_ITERATIONS[solver] if iterations is None else iterations
    if int(n) != n or n < 1:
        raise ValueError(f"contact solver iterations must be a positive integer, got {iterations!r}")
    return int(n)


def solve_contacts(W, q, mu, lam0, active, solver: str, iterations: int, op=None, storage=None, fused=None):
    """The engine's contact solve: ``iterations`` of :func:`apgd_coulomb` without restart (unrolled:
    no loop in the compiled step) for ``solver="apgd"``, or sweeps of :func:`pgs_coulomb` for ``"pgs"``; the
    arguments and result as theirs (``op``, ``storage`` and ``fused``: the accelerated gradient's,
    ignored by Gauss-Seidel, which reads ``W`` by rows; ``W`` formed or in its parts,
    :class:`~softcrawl.jaxsim.schur.SchurOperator`). No contact slots (no floor) gives an empty result."""
    if not active.shape[0]:
        return jnp.zeros(0, _dtype(W))
    if solver == "apgd":
        return apgd_coulomb(W, q, mu, lam0, active, iterations, restart=False, op=op, storage=storage, fused=fused)
    return pgs_coulomb(W.dense() if isinstance(W, SchurOperator) else W, q, mu, lam0, active, iterations)


def solve_on_platform(W, q, mu, lam0, active, solver: str, iterations: int, op=None, storage=None,
                      kernel: bool = False):
    """:func:`solve_contacts` in the form each platform runs it (the engine's step): a CPU reads
    its operator whole in its own precision (there it stays in cache and float16 would only add
    conversions); other platforms read it in ``storage`` (None: their own precision too); with
    ``kernel``, a CUDA GPU that runs Pallas' kernels solves in one kernel (``fused="gpu"``;
    :func:`softcrawl.jaxsim.gpu.cuda_kernel`). Arguments and result as :func:`solve_contacts`'."""
    solve = partial(solve_contacts, solver=solver, iterations=iterations, op=op)
    if storage is None:
        return solve(W, q, mu, lam0, active)
    stored = partial(solve, storage=storage)
    kernels = cuda_kernel(partial(stored, fused="gpu")) if kernel else {}
    return lax.platform_dependent(W, q, mu, lam0, active, cpu=solve, default=stored, **kernels)


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


def floor_contacts(heights, vz, floor_z, distance, K: int, *, dt):
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
        heights: ``(P,)`` the candidates' heights ``z``, mm. vz: ``(P,)`` their free vertical
            velocities, mm/s. floor_z, distance: floor height and contact distance, mm.
        K: number of contact slots (static, ``K <= P``). dt: time step, s.

    Returns:
        ``(idx (K,) int, active (K,) bool, gap (K,) current gaps g, mm)``.

    Raises:
        ValueError: ``K > P``.
    """
    P = heights.shape[0]
    if K > P:
        raise ValueError(f"K = {K} contact slots exceed the {P} candidate points")
    gap = heights - floor_z
    pred = jnp.minimum(gap, gap + dt * vz)
    idx = smallest_k(pred, K)
    return idx, pred[idx] < distance, gap[idx]


#: Candidates from which :func:`smallest_k` selects in two stages (XLA's GPU compiler gives a
#: top-k of a thousand or more values its top-k kernel, of fewer a sort).
SMALLEST_K_SPLIT = 1024


def smallest_k(values, K: int):
    """``(K,)`` the indices of the ``K`` smallest of ``values`` ``(P,)``, in increasing order; of
    equal values the lower indices (the set ``lax.top_k(-values, K)`` gives).

    Where ``P`` is large (:data:`SMALLEST_K_SPLIT` or more) and large against ``K``, it makes
    two small selections instead of one large: the values in ``G`` groups of ``S ~ sqrt(P /
    K)``, the ``K`` groups of smallest minimum, then the ``K`` smallest of those groups' ``K S``
    values. Exact: each of the ``K`` smallest values lies in one of those groups (a group left
    out has ``K`` groups of no larger minimum before it, which hold ``K`` values no larger than
    any of its own, of lower index where equal). A GPU's top-k does work in proportion to ``P
    K`` per row (a leg's 1,179 points: 81 µs of the 96-robot step on an H100,
    ``benchmarks/RESULTS.md``); the two stages do ``(G + K S) K``, a fifth of it there. Fewer
    values than :data:`SMALLEST_K_SPLIT` take one selection (XLA sorts them, in one kernel on a
    GPU).
    """
    P = values.shape[0]
    S = max(2, round(math.sqrt(P / K)))
    G = -(-P // S)
    if P < SMALLEST_K_SPLIT or 2 * (G + K * S) > P:
        return jnp.sort(lax.top_k(-values, K)[1])
    groups = jnp.pad(values, (0, G * S - P), constant_values=jnp.inf).reshape(G, S)
    g = jnp.sort(lax.top_k(-jnp.min(groups, axis=1), K)[1])
    _, j = lax.top_k(-groups[g].reshape(-1), K)
    return jnp.minimum(jnp.sort((g[:, None] * S + jnp.arange(S)).reshape(-1)[j]), P - 1)
