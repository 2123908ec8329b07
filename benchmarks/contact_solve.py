"""The contact solve of a training batch (issue 18): where the constraint stage's time goes.

Builds ``--robots`` random canonical designs of each leg count in ``--legs`` (shipped reduction,
10 mm disk, dt 0.02 s, float32 RID products: the ``paper`` preset's robots), drops them on the
floor and drives them as training does: every regulator channel holds a random pressure
(0..90 sim kPa) for one second (50 steps), then another. After ``--settle`` steps it records
every contact problem the robots' constraint stages solve over ``--steps`` steps (through the
Python constraint path, which forms the same Delassus operators as the compiled one) and times,
on those problems:

- ``solve_condensed``: the compiled solve as the stage calls it (Schur complement of the
  attachment rows, warm-started active-set polish, else Gauss-Seidel chunks and polishes);
- its parts: the Schur complement, the warm polish, the Gauss-Seidel sweeps and the polishes
  after them (each timed on its own from Python, so the parts add up to a little more);

and prints JSON (ms per problem, problems per robot step, how often each path runs). With
``--save FILE`` the problems are kept (npz, arrays only), and ``--problems FILE`` times a saved
set instead of recording one, so two versions of the code can be timed on the same problems
(``PYTHONPATH=<other checkout> python benchmarks/contact_solve.py --problems FILE``).

Usage: OMP_NUM_THREADS=1 python benchmarks/contact_solve.py [--robots 12] [--legs 5 6]
       [--settle 60] [--steps 100] [--rounds 3] [--seed 0] [--save FILE | --problems FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

import softcrawl.fem.solver as fem_solver  # noqa: E402
from softcrawl.fem.contact import EXTRA_SWEEP_CHUNKS, pgs_coulomb, polish_kernel  # noqa: E402
from softcrawl.reduction.batch import BatchedReducedSolver  # noqa: E402
from softcrawl.reduction.constrain import POLISH_ROUNDS, POLISH_RTOL, condense, solve_condensed  # noqa: E402
from softcrawl.robot import RobotConfig, build_robot  # noqa: E402
from batch_step import designs_with  # noqa: E402  (this folder's script)


def record(robots_per_count: int, legs: list[int], settle: int, steps: int, seed: int) -> tuple[list, int]:
    """The contact problems ``(W, q, nb, mu, warm, tol, max_iter)`` of ``steps`` batched steps
    of training-like robots (module doc), and the number of robot steps they came from."""
    rng = np.random.default_rng(seed)
    designs = [d for n in legs for d in designs_with(n, robots_per_count, rng)]
    cfg = RobotConfig(model="reduced", dt=0.02, rid_dtype="float32")
    robots = [build_robot(d, cfg) for d in designs]
    batch = BatchedReducedSolver([r.make_solver() for r in robots])
    held = rng.uniform(0.0, 90.0, ((settle + steps) // 50 + 1, len(robots), 3))
    states = [r.model.rest_state() for r in robots]
    problems: list = []
    real = fem_solver.solve_constraints

    def keep(W, q, nb, mu, warm, tol, max_iter):
        problems.append((W.copy(), q.copy(), nb, mu.copy(), np.asarray(warm, float).ravel().copy(), tol, max_iter))
        return real(W, q, nb, mu, warm, tol, max_iter)

    for k in range(settle + steps):
        if k == settle:  # from here on through the Python constraint path, recording
            batch._compiled = None
            for s in batch.solvers:
                s._compiled = False
            fem_solver.solve_constraints = keep
        states = batch.step(states, [r.control(held[k // 50, i]) for i, r in enumerate(robots)])
    fem_solver.solve_constraints = real
    return problems, steps * len(robots)


def time_parts(problems: list) -> dict:
    """ms per problem of the Schur complement, the warm polish, Gauss-Seidel and the polishes
    after it, run as :func:`solve_condensed` runs them, and how often each path is taken."""
    t = time.perf_counter()
    cond = [condense(W, q, nb)[1:] + (mu, warm, tol, mx) for W, q, nb, mu, warm, tol, mx in problems]
    schur = time.perf_counter() - t
    warm_s = pgs_s = after_s = 0.0
    n_warm_failed = n_after = n_after_ok = sweeps = 0
    for Wc, qc, mu, warm, tol, mx in cond:
        lam, ok = warm.copy(), False
        if np.any(lam != 0.0):
            t = time.perf_counter()
            ok, _ = polish_kernel(Wc, qc, mu, lam, POLISH_ROUNDS, POLISH_RTOL)
            warm_s += time.perf_counter() - t
        if ok:
            continue
        n_warm_failed += 1
        t = time.perf_counter()
        s, rel = pgs_coulomb(Wc, qc, mu, lam, tol, mx)
        pgs_s += time.perf_counter() - t
        for chunk in range(EXTRA_SWEEP_CHUNKS + 1):
            if rel <= tol:
                break
            t = time.perf_counter()
            ok, _ = polish_kernel(Wc, qc, mu, lam, POLISH_ROUNDS, POLISH_RTOL)
            after_s += time.perf_counter() - t
            n_after += 1
            n_after_ok += ok
            if ok or chunk == EXTRA_SWEEP_CHUNKS:
                break
            t = time.perf_counter()
            more, rel = pgs_coulomb(Wc, qc, mu, lam, tol, mx)
            pgs_s += time.perf_counter() - t
            s += more
        sweeps += s
    n = len(problems)
    return {"schur_ms": 1e3 * schur / n, "warm_polish_ms": 1e3 * warm_s / n, "gauss_seidel_ms": 1e3 * pgs_s / n,
            "polish_after_gauss_seidel_ms": 1e3 * after_s / n, "warm_polish_failed": n_warm_failed,
            "gauss_seidel_sweeps_when_run": sweeps / max(n_warm_failed, 1), "polishes_after_gauss_seidel": n_after,
            "of_which_consistent": n_after_ok}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=12, help="robots per leg count")
    p.add_argument("--legs", type=int, nargs="+", default=[5, 6])
    p.add_argument("--settle", type=int, default=60, help="steps before recording (landing)")
    p.add_argument("--steps", type=int, default=100, help="recorded steps")
    p.add_argument("--rounds", type=int, default=3, help="timings of solve_condensed (best kept)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--save", help="keep the recorded problems here (.npz)")
    p.add_argument("--problems", help="time these saved problems instead of recording")
    args = p.parse_args()
    if args.problems:
        z = np.load(args.problems)
        problems = [(z[f"W{i}"], z[f"q{i}"], int(z["nb"][i]), z[f"mu{i}"], z[f"warm{i}"], float(z["tol"]),
                     int(z["max_iter"])) for i in range(len(z["nb"]))]
        robot_steps = int(z["robot_steps"])
    else:
        problems, robot_steps = record(args.robots, args.legs, args.settle, args.steps, args.seed)
        if args.save:
            arrays = {f"{key}{i}": a for i, (W, q, _, mu, warm, *_) in enumerate(problems)
                      for key, a in (("W", W), ("q", q), ("mu", mu), ("warm", warm))}
            np.savez_compressed(args.save, nb=np.array([pr[2] for pr in problems]), tol=problems[0][5],
                                max_iter=problems[0][6], robot_steps=robot_steps, **arrays)
    solve_condensed(*problems[0][:7], EXTRA_SWEEP_CHUNKS)  # compile outside the timing
    best = np.inf
    for _ in range(args.rounds):
        t = time.perf_counter()
        for W, q, nb, mu, warm, tol, mx in problems:
            solve_condensed(W, q, nb, mu, warm, tol, mx, EXTRA_SWEEP_CHUNKS)
        best = min(best, time.perf_counter() - t)
    print(json.dumps({
        "machine": platform.platform(), "cpus": os.cpu_count(), "args": vars(args),
        "problems": len(problems), "problems_per_robot_step": len(problems) / robot_steps,
        "contacts_mean": float(np.mean([len(pr[3]) for pr in problems])),
        "attachment_rows_mean": float(np.mean([pr[2] for pr in problems])),
        "solve_condensed_ms": 1e3 * best / len(problems),
        "solve_condensed_ms_per_robot_step": 1e3 * best / robot_steps,
        "parts": time_parts(problems)}, indent=2))


if __name__ == "__main__":
    main()
