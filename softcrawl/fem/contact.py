"""Frictional contact with the floor and bilateral constraints, solved in impulse space.

After the free (unconstrained) implicit step gives velocities ``v_f``, constraint impulses
``lam`` correct them: ``v = v_f + A^-1 H^T lam``. With the Delassus operator
``W = H A^-1 H^T`` (impulse -> velocity; ``dt * W`` maps forces to positions as in
physics.md) the constraint velocities are ``u = W lam + H v_f``.

- Bilateral attachments (3 rows each) require ``u + (x_a - x_b)/dt = 0`` (zero velocity
  error plus full drift correction). They are eliminated exactly with a Schur complement.
- Floor contacts (rows: normal, tangent 1, tangent 2) obey Signorini at the end of the
  step, ``g + dt u_n >= 0  _|_  lam_n >= 0`` (so the new gap is non-negative), and
  Coulomb's law ``|lam_t| <= mu lam_n`` with ``u_t = 0`` inside the cone (stick) and
  ``u_t`` opposite to ``lam_t`` on its boundary (slip, maximal dissipation).

The contact problem is solved by projected block Gauss-Seidel on the condensed ``W``
(Jean 1999, "The non-smooth contact dynamics method"; Duriez et al. 2006, as used by
SOFA's GenericConstraintSolver), then *polished*: the stick/slip/separation pattern that
Gauss-Seidel found is taken as the active set and the resulting equalities are solved
directly, and the friction directions of slipping contacts are then turned opposite to
their slip by Newton's method (maximal dissipation); the polished impulses are kept when
they satisfy every condition of the problem (which makes sticking contacts stick to
round-off, where Gauss-Seidel alone converges slowly on the ill-conditioned ``W`` of stiff
bodies). When last step's impulses are available the exact active-set solve is tried first
from them, and Gauss-Seidel runs only if it fails.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg.lapack import dpotrf, dpotrs
from numba import njit


@njit(cache=True)
def pgs_coulomb(W, q, mu, lam, tol, max_iter):
    """Projected Gauss-Seidel for frictional contact blocks.

    Solves ``u = W lam + q`` with, per block ``i`` (rows 3i: normal, 3i+1, 3i+2: tangents),
    ``u_n >= 0 _|_ lam_n >= 0`` and the Coulomb cone ``|lam_t| <= mu_i lam_n`` (stick
    ``u_t = 0`` inside; on the boundary ``u_t`` antiparallel to ``lam_t``).

    Args:
        W: ``(3k, 3k)`` Delassus operator (symmetric positive semi-definite).
        q: ``(3k,)`` constraint velocities at zero impulse, incl. gap terms.
        mu: ``(k,)`` friction coefficients.
        lam: ``(3k,)`` initial impulses (warm start); updated in place.
        tol: stop when the largest impulse change in a sweep is <= tol * max |lam|.
        max_iter: sweep limit.

    Returns:
        ``(sweeps, relative_change)`` of the last sweep.
    """
    k = mu.shape[0]
    rel = 0.0
    for it in range(max_iter):
        dmax = 0.0
        lmax = 1e-300
        for i in range(k):
            r = 3 * i
            un = q[r]
            for j in range(3 * k):
                un += W[r, j] * lam[j]
            ln_old = lam[r]
            ln = ln_old - un / W[r, r]
            if ln < 0.0:
                ln = 0.0
            lam[r] = ln
            dn = ln - ln_old
            u1 = q[r + 1]  # tangential velocities with the updated normal impulse
            u2 = q[r + 2]
            for j in range(3 * k):
                u1 += W[r + 1, j] * lam[j]
                u2 += W[r + 2, j] * lam[j]
            wt = 0.5 * (W[r + 1, r + 1] + W[r + 2, r + 2])
            t1_old = lam[r + 1]
            t2_old = lam[r + 2]
            t1 = t1_old - u1 / wt
            t2 = t2_old - u2 / wt
            nt = np.sqrt(t1 * t1 + t2 * t2)
            lim = mu[i] * ln
            if nt > lim:
                s = lim / nt
                t1 *= s
                t2 *= s
            lam[r + 1] = t1
            lam[r + 2] = t2
            d = max(abs(dn), abs(t1 - t1_old), abs(t2 - t2_old))
            if d > dmax:
                dmax = d
            m = max(ln, np.sqrt(t1 * t1 + t2 * t2))
            if m > lmax:
                lmax = m
        rel = dmax / lmax
        if rel <= tol:
            return it + 1, rel
    return max_iter, rel


_SEP, _STICK, _SLIP = 0, 1, 2
#: Extra chunks of ``max_iter`` Gauss-Seidel sweeps allowed when the first chunk neither
#: converges nor yields a consistent active set. One: the recorded ill-conditioned problem
#: (tests/data/ill_conditioned_contact.npz) needs it; more almost never help (over 516 problems
#: recorded in co-design training, 8 chunks polished 490 and 1 chunk 467, for 3.2x the contact
#: time, the rest being rank-deficient Delassus operators of reduced legs whose Gauss-Seidel
#: impulses stay unconverged however long it runs: CHANGELOG.md).
EXTRA_SWEEP_CHUNKS = 1
#: Above this many contacts every violated contact switches in every round of the polish
#: (each round is a dense solve: one switch per round would cost too much).
SINGLE_SWITCH_MAX_CONTACTS = 40
#: Polish rounds above that size.
MULTI_SWITCH_ROUNDS = 12
#: A slipping contact's friction direction must be opposite to its slip velocity to within
#: this angle (rad) for the polish to stop aligning it (Coulomb's maximal dissipation).
DIRECTION_TOLERANCE = 1e-6
#: Newton iterations of one alignment, and alignments per polish.
ALIGN_ITERATIONS = 25
MAX_ALIGNMENTS = 4


@njit(cache=True)
def _align_slip(W, q, mu, mode, d, lam, vtol, max_iterations):
    """Newton iteration turning the friction directions ``d`` of the slipping contacts that
    slip (``|u_t| > vtol``) until each is opposite to its slip velocity, on the fixed
    stick/slip/separation pattern ``mode``.

    Unknowns: the 3 impulses of each sticking contact, the normal impulse ``a`` and the
    direction angle of each slipping one (``lam_t = mu a (cos t, sin t)``). Equations:
    ``u = 0`` (stick), ``u_n = 0`` (slip) and ``d x u_t = 0`` (slip, maximal dissipation).
    ``d`` and ``lam`` are updated in place when the directions converge to
    :data:`DIRECTION_TOLERANCE`. Returns whether they did.
    """
    k = mu.shape[0]
    u0 = W @ lam + q
    stick = np.flatnonzero(mode == _STICK)
    slip = np.flatnonzero(mode == _SLIP)
    ns, npl = 3 * len(stick), len(slip)
    turn = np.zeros(npl, np.bool_)  # slipping contacts whose direction is an unknown
    for c in range(npl):
        j = 3 * slip[c]
        turn[c] = np.hypot(u0[j + 1], u0[j + 2]) > vtol and lam[j] > 0.0
    tcol = np.full(npl, -1, np.int64)
    col = ns + npl
    for c in range(npl):
        if turn[c]:
            tcol[c] = col
            col += 1
    n = col
    x = np.empty(n)
    for a in range(len(stick)):
        for c in range(3):
            x[3 * a + c] = lam[3 * stick[a] + c]
    for c in range(npl):
        j = 3 * slip[c]
        x[ns + c] = lam[j]
        if turn[c]:
            x[tcol[c]] = np.arctan2(d[slip[c], 1], d[slip[c], 0])
    cof = np.full(n, -1, np.int64)  # direction column -> its slipping contact
    for c in range(npl):
        if turn[c]:
            cof[tcol[c]] = c
    cth, sth = np.empty(npl), np.empty(npl)  # the slip directions of this iteration
    L = np.zeros(3 * k)
    F = np.empty(n)
    J = np.empty((n, n))
    dlam, du = np.empty(3), np.empty(3)
    cols = np.empty(3, np.int64)
    for it in range(max_iterations + 1):
        L[:] = 0.0
        for a in range(len(stick)):
            for c in range(3):
                L[3 * stick[a] + c] = x[3 * a + c]
        for c in range(npl):
            i, j = slip[c], 3 * slip[c]
            th = x[tcol[c]] if turn[c] else np.arctan2(d[i, 1], d[i, 0])
            cth[c], sth[c] = np.cos(th), np.sin(th)
            L[j] = x[ns + c]
            L[j + 1] = mu[i] * x[ns + c] * cth[c]
            L[j + 2] = mu[i] * x[ns + c] * sth[c]
        u = W @ L + q
        done = True
        for a in range(ns):
            F[a] = u[3 * stick[a // 3] + a % 3]
            done = done and abs(F[a]) <= vtol
        for c in range(npl):
            j = 3 * slip[c]
            F[ns + c] = u[j]
            done = done and abs(u[j]) <= vtol
            if turn[c]:
                g = cth[c] * u[j + 2] - sth[c] * u[j + 1]  # d x u_t
                F[tcol[c]] = g
                done = done and abs(g) <= DIRECTION_TOLERANCE * np.hypot(u[j + 1], u[j + 2])
        if done:
            for c in range(npl):
                d[slip[c], 0], d[slip[c], 1] = cth[c], sth[c]
            lam[:] = L
            return True
        if it == max_iterations:
            break
        # Jacobian: dF/dx = (rows of W dL/dx), plus the direct d(d x u_t)/dt = -d . u_t;
        # column by column, dL/dx has at most 3 entries.
        for col in range(n):
            if col < ns:
                dlam[0], dlam[1], dlam[2] = 1.0, 0.0, 0.0
                base = 3 * stick[col // 3] + col % 3
                cols[0], cols[1], cols[2] = base, base, base
            else:
                c = col - ns if col < ns + npl else cof[col]
                i, j = slip[c], 3 * slip[c]
                cs, sn = cth[c], sth[c]
                cols[0], cols[1], cols[2] = j, j + 1, j + 2
                if col < ns + npl:  # normal impulse
                    dlam[0], dlam[1], dlam[2] = 1.0, mu[i] * cs, mu[i] * sn
                else:  # direction angle
                    dlam[0], dlam[1], dlam[2] = 0.0, -mu[i] * x[ns + c] * sn, mu[i] * x[ns + c] * cs
            for a in range(ns):
                r = 3 * stick[a // 3] + a % 3
                J[a, col] = W[r, cols[0]] * dlam[0] + W[r, cols[1]] * dlam[1] + W[r, cols[2]] * dlam[2]
            for c2 in range(npl):
                j2 = 3 * slip[c2]
                for e in range(3):
                    du[e] = (W[j2 + e, cols[0]] * dlam[0] + W[j2 + e, cols[1]] * dlam[1]
                             + W[j2 + e, cols[2]] * dlam[2])
                J[ns + c2, col] = du[0]
                if turn[c2]:
                    J[tcol[c2], col] = cth[c2] * du[2] - sth[c2] * du[1]
        for c in range(npl):
            if turn[c]:
                j = 3 * slip[c]
                J[tcol[c], tcol[c]] -= cth[c] * u[j + 1] + sth[c] * u[j + 2]
        try:
            x += np.linalg.solve(J, -F)
        except Exception:  # singular: directions not determined
            return False
    return False


@njit(cache=True)
def _seen_before(mode, d, alignments, seen_mode, seen_d, seen_align, rnd):
    """Whether the polish state ``(mode, d, alignments)`` is that of one of rounds ``1 .. rnd - 1``."""
    for p in range(1, rnd):
        if seen_align[p] != alignments:
            continue
        same = True
        for i in range(mode.shape[0]):
            if seen_mode[p, i] != mode[i] or seen_d[p, i, 0] != d[i, 0] or seen_d[p, i, 1] != d[i, 1]:
                same = False
                break
        if same:
            return True
    return False


@njit(cache=True)
def polish_kernel(W, q, mu, lam, max_rounds, rtol):
    """Compiled body of :func:`polish_active_set`: ``(consistent, impulses)``."""
    k = mu.shape[0]
    mode = np.empty(k, np.int64)
    d = np.zeros((k, 2))
    for i in range(k):
        ln, lt = lam[3 * i], np.hypot(lam[3 * i + 1], lam[3 * i + 2])
        mode[i] = (_SLIP if lt >= mu[i] * ln * (1 - 1e-6) else _STICK) if ln > 0 else _SEP
        den = max(lt, 1e-300)
        d[i, 0], d[i, 1] = lam[3 * i + 1] / den, lam[3 * i + 2] / den
    vscale = max(np.abs(q).max(), 1e-300) if k else 1e-300
    vtol = rtol * vscale
    new = np.zeros(3 * k)
    u = np.empty(3 * k)
    change = np.empty(k, np.int64)
    single = k <= SINGLE_SWITCH_MAX_CONTACTS
    alignments, have_found = 0, False
    found = np.zeros(3 * k)  # the last consistent solution before an alignment
    rounds = max_rounds if single else min(max_rounds, MULTI_SWITCH_ROUNDS)
    # From round 1 on, a round is a function of (mode, d, alignments) alone; a state met before
    # repeats its rounds until the limit without returning, so the iteration stops at once
    # (the same result as running out of rounds, in fewer dense solves).
    seen_mode = np.empty((rounds, k), np.int64)
    seen_d = np.empty((rounds, k, 2))
    seen_align = np.empty(rounds, np.int64)
    for rnd in range(rounds):
        if rnd > 0:
            if _seen_before(mode, d, alignments, seen_mode, seen_d, seen_align, rnd):
                break
            seen_mode[rnd], seen_d[rnd], seen_align[rnd] = mode, d, alignments
        # Unknowns: 3 impulses per sticking contact, the normal impulse per slipping one
        # (its tangential impulse is mu lam_n d). Equations: u = 0 / u_n = 0 on those rows.
        stick = np.flatnonzero(mode == _STICK)
        slip = np.flatnonzero(mode == _SLIP)
        ns = 3 * len(stick)
        n = ns + len(slip)
        rows = np.empty(n, np.int64)
        for a in range(len(stick)):
            for c in range(3):
                rows[3 * a + c] = 3 * stick[a] + c
        for a in range(len(slip)):
            rows[ns + a] = 3 * slip[a]
        A = np.empty((n, n))
        rhs = np.empty(n)
        for a in range(n):
            r = rows[a]
            rhs[a] = -q[r]
            for c in range(ns):
                A[a, c] = W[r, rows[c]]
            for c in range(len(slip)):
                j = 3 * slip[c]
                A[a, ns + c] = (W[r, j] + mu[slip[c]] * d[slip[c], 0] * W[r, j + 1]
                                + mu[slip[c]] * d[slip[c], 1] * W[r, j + 2])
        z = np.zeros(n)
        if n:
            try:
                z = np.linalg.solve(A, rhs)
            except Exception:  # singular active-set system
                return False, new
        new[:] = 0.0
        for a in range(ns):
            new[rows[a]] = z[a]
        for c in range(len(slip)):
            j, ln = 3 * slip[c], z[ns + c]
            new[j] = ln
            new[j + 1] = ln * mu[slip[c]] * d[slip[c], 0]
            new[j + 2] = ln * mu[slip[c]] * d[slip[c], 1]
        u[:] = W @ new + q
        fscale = max(np.abs(new).max(), 1e-300) if k else 1e-300
        ftol = rtol * fscale
        # Violations, each with its severity (relative to the impulse or velocity scale).
        worst, worst_sev, n_viol, misaligned = -1, -1.0, 0, False
        for i in range(k):
            r, m = 3 * i, mode[i]
            ltn = np.hypot(new[r + 1], new[r + 2])
            along = u[r + 1] * d[i, 0] + u[r + 2] * d[i, 1]  # slip velocity along the friction force
            nxt, sev = m, 0.0
            if m == _SEP and u[r] < -vtol:
                nxt, sev = _STICK, -u[r] / vscale  # penetrating
            if m != _SEP and new[r] < -ftol:
                nxt, sev = _SEP, -new[r] / fscale  # pulling
            if m == _STICK and ltn > mu[i] * new[r] + ftol:
                nxt, sev = _SLIP, (ltn - mu[i] * new[r]) / fscale  # outside the cone
            if m == _SLIP and along > vtol:
                nxt, sev = _STICK, along / vscale  # slipping along the friction force
            if m == _SLIP and abs(d[i, 0] * u[r + 2] - d[i, 1] * u[r + 1]) > DIRECTION_TOLERANCE * max(
                    np.hypot(u[r + 1], u[r + 2]), vtol / DIRECTION_TOLERANCE):
                misaligned = True  # friction not opposite to the slip
            change[i] = nxt
            if nxt != m:
                n_viol += 1
                if sev > worst_sev:
                    worst, worst_sev = i, sev
        if n_viol == 0:
            # A consistent pattern. Its slip directions come from the start (last step's
            # impulses or Gauss-Seidel): turn them opposite to the slip (maximal
            # dissipation) and check the pattern again with them; if they do not converge,
            # or no consistent pattern follows, keep the directions found.
            if misaligned and alignments < MAX_ALIGNMENTS:
                alignments += 1
                found[:] = new
                have_found = True
                if _align_slip(W, q, mu, mode, d, new.copy(), vtol, ALIGN_ITERATIONS):
                    continue
            return True, new
        # All violated contacts switch in the first round; later only the worst one, which
        # stops the cycling of ill-conditioned problems (a few contacts on one reduced leg).
        for i in range(k):
            if change[i] != mode[i] and (rnd == 0 or i == worst or not single):
                if change[i] == _SLIP:
                    ltn = np.hypot(new[3 * i + 1], new[3 * i + 2])
                    d[i, 0], d[i, 1] = new[3 * i + 1] / ltn, new[3 * i + 2] / ltn
                mode[i] = change[i]
    if have_found:  # aligned directions changed the pattern and no consistent one followed
        return True, found
    return False, new


def polish_active_set(W, q, mu, lam, max_rounds=30, rtol=1e-9):
    """Solve the contact problem exactly by a primal-dual active-set iteration from ``lam``.

    Each contact is separated (``lam = 0``), sticking (``u = 0`` on its three rows) or
    slipping (``u_n = 0``, ``lam_t = mu lam_n d``, with the friction direction ``d`` taken
    from ``lam``; the check demands ``u_t . d <= 0``). Once the pattern is consistent, the
    directions are turned opposite to the slip velocities (:func:`_align_slip`, to
    :data:`DIRECTION_TOLERANCE`) and the pattern is checked again; if that fails, the
    consistent solution with the directions from ``lam`` is returned. Starting from the pattern of ``lam``,
    the equalities are solved directly and the pattern is updated from the violated
    conditions (penetration -> stick, pulling -> separate, outside the cone -> slip, slip
    along the force -> stick) until it is consistent (compiled: :func:`polish_kernel`): all of
    them in the first round, then the most violated one per round (up to
    :data:`SINGLE_SWITCH_MAX_CONTACTS` contacts), which avoids cycling. An iteration that returns
    to an earlier state (pattern, directions, alignments) stops there with what running out of
    rounds would give, since it would only repeat itself.

    Args:
        W, q, mu: as in :func:`pgs_coulomb`.
        lam: ``(3k,)`` approximate solution (e.g. from Gauss-Seidel).
        max_rounds: active-set updates to try.
        rtol: relative tolerance of the validity checks.

    Returns:
        ``(3k,)`` exact impulses, or None if no consistent active set was found.
    """
    ok, new = polish_kernel(np.ascontiguousarray(W, dtype=np.float64), np.ascontiguousarray(q, dtype=np.float64),
                            np.ascontiguousarray(mu, dtype=np.float64), np.ascontiguousarray(lam, dtype=np.float64),
                            int(max_rounds), float(rtol))
    return new if ok else None


@dataclass(frozen=True)
class ConstraintSolution:
    """Impulses of one constraint solve.

    Attributes:
        bilateral: ``(3b,)`` attachment impulses, mN s.
        contact: ``(k, 3)`` contact impulses (normal, tangent 1, tangent 2), mN s.
        sweeps: Gauss-Seidel sweeps used.
        relative_change: last sweep's relative impulse change.
        polished: whether the exact active-set solution was accepted.
    """

    bilateral: np.ndarray
    contact: np.ndarray
    sweeps: int
    relative_change: float
    polished: bool = False


def solve_constraints(
    W: np.ndarray,
    q: np.ndarray,
    n_bilateral_rows: int,
    mu: np.ndarray,
    warm_start: np.ndarray,
    tol: float,
    max_iter: int,
) -> ConstraintSolution:
    """Solve bilateral rows exactly and contact blocks by projected Gauss-Seidel.

    Args:
        W: ``(r, r)`` Delassus operator; the first ``n_bilateral_rows`` rows are bilateral.
        q: ``(r,)`` constraint velocities at zero impulse including stabilisation terms
            (bilateral rows must reach ``u = 0``; contact rows as in :func:`pgs_coulomb`).
        n_bilateral_rows: number of bilateral rows (multiple of 3).
        mu: ``(k,)`` friction coefficients of the contacts.
        warm_start: ``(k, 3)`` initial contact impulses.
        tol, max_iter: Gauss-Seidel stopping rule; if ``max_iter`` sweeps neither converge
            nor give the polish a consistent active set, up to :data:`EXTRA_SWEEP_CHUNKS`
            more chunks of ``max_iter`` sweeps are run, polishing after each.
    """
    nb = n_bilateral_rows
    B, C = slice(0, nb), slice(nb, None)
    k = len(mu)
    if nb:
        rhs = np.column_stack([q[B], W[B, C]])
        fac, info = dpotrf(W[B, B], lower=1)
        if info == 0:
            X = dpotrs(fac, rhs, lower=1)[0]
        else:  # redundant attachments: least-squares impulses
            X = np.linalg.pinv(W[B, B]) @ rhs
        Wc = W[C, C] - W[C, B] @ X[:, 1:]
        qc = q[C] - W[C, B] @ X[:, 0]
    else:
        Wc, qc = W[C, C], q[C]
    lam_c = np.ascontiguousarray(warm_start, dtype=np.float64).reshape(-1).copy()
    sweeps, rel, polished = 0, 0.0, False
    if k:
        Wc, qc = np.ascontiguousarray(Wc), np.ascontiguousarray(qc)
        # The stick/slip/separation pattern rarely changes between steps: try the exact
        # active-set solve from the warm start first, Gauss-Seidel only if that fails.
        exact = polish_active_set(Wc, qc, mu, lam_c) if np.any(lam_c) else None
        if exact is None:
            sweeps, rel = pgs_coulomb(Wc, qc, mu, lam_c, tol, max_iter)
            # Unconverged and not polishable (an ill-conditioned W, e.g. several contacts on
            # one reduced leg): more sweeps, in chunks of max_iter, until the pattern is
            # right for the polish or Gauss-Seidel converges.
            for chunk in range(EXTRA_SWEEP_CHUNKS + 1):
                if rel <= tol:
                    break
                exact = polish_active_set(Wc, qc, mu, lam_c)
                if exact is not None or chunk == EXTRA_SWEEP_CHUNKS:
                    break
                more, rel = pgs_coulomb(Wc, qc, mu, lam_c, tol, max_iter)
                sweeps += more
        if exact is not None:
            lam_c, polished = exact, True
    lam_b = -(X[:, 0] + X[:, 1:] @ lam_c) if nb else np.zeros(0)
    return ConstraintSolution(lam_b, lam_c.reshape(k, 3), int(sweeps), float(rel), polished)
