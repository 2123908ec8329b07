"""Batched vs one-by-one reduced stepping of many robots (issue 18), per leg count, in one process.

For each leg count (3, 4, 5, 6) ``--robots`` random canonical designs of that count, and a mixed
batch of all of them, are built with the shipped reduction (floating disk), dropped on the floor
and pressurised (every channel on its own phase, 0..60 sim kPa); then ``--steps`` steps of the
robots with their own :class:`ReducedSolver` one after another and of one
:class:`BatchedReducedSolver` are timed in ``--rounds`` alternating blocks (same states, one BLAS
thread). Both paths are checked to give the same positions. Prints JSON: per set, ms per robot
step and sim steps per second per core of each path and their ratio; optionally (``--profile``)
the batch step's time by function (cProfile, top 15); and the peak RSS.

Usage: OMP_NUM_THREADS=1 python benchmarks/batch_step.py [--robots 12] [--steps 20] [--rounds 4]
       [--settle 60] [--legs 3 4 5 6] [--no-mixed] [--profile] [--dt 0.02] [--rid-dtype float32]
       [--disk-mesh-size 10] [--contact-max-iterations 100] [--leg-collision-spacing 4]
Training's settings are ``--dt 0.02 --rid-dtype float32 --contact-max-iterations 100`` (``paper``:
10 mm disk; ``crawl``, ``demo``: 25 mm).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from softcrawl.design.space import canonical_designs  # noqa: E402
from softcrawl.reduction.batch import BatchedReducedSolver  # noqa: E402
from softcrawl.fem.solver import RID_DTYPES  # noqa: E402
from softcrawl.robot import RobotConfig, build_robot  # noqa: E402


def pressures(robot: int, k: int) -> np.ndarray:
    """Sim kPa of robot ``robot`` at step ``k`` (0..60, every channel on its own phase)."""
    return 30.0 * (1.0 - np.cos(0.05 * k + np.array([0.0, 2.0, 4.0]) + robot))


def designs_with(legs: int, n: int, rng) -> list:
    pool = [d for d in canonical_designs() if sum(v > 0 for v in d) == legs]
    return [pool[i] for i in rng.choice(len(pool), n, replace=False)]


def measure(robots, steps: int, rounds: int, settle: int, profile: bool) -> dict:
    """Interleaved timing of one-by-one and batched stepping of ``robots`` (see module doc)."""
    singles = [r.make_solver() for r in robots]
    batch = BatchedReducedSolver([r.make_solver() for r in robots])
    s_states = [r.model.rest_state() for r in robots]
    b_states = list(s_states)
    k = 0

    def one_by_one(k0):
        nonlocal s_states
        for k in range(k0, k0 + steps):
            s_states = [s.step(st, r.control(pressures(i, k)))
                        for i, (s, st, r) in enumerate(zip(singles, s_states, robots))]

    def batched(k0):
        nonlocal b_states
        for k in range(k0, k0 + steps):
            b_states = batch.step(b_states, [r.control(pressures(i, k)) for i, r in enumerate(robots)])
            bad = [s for s in b_states if not isinstance(s, type(robots[0].model.rest_state()))]
            if bad:
                raise bad[0]

    for k0 in range(0, settle, steps):  # onto the floor (not timed)
        one_by_one(k0)
        batched(k0)
        k = k0 + steps
    t_single = t_batch = 0.0
    for _ in range(rounds):
        t = time.perf_counter()
        one_by_one(k)
        t_single += time.perf_counter() - t
        t = time.perf_counter()
        batched(k)
        t_batch += time.perf_counter() - t
        k += steps
    n = rounds * steps * len(robots)
    diff = max(float(np.abs(a.x - b.x).max()) for a, b in zip(s_states, b_states))
    out = {"robots": len(robots), "legs": [len(r.legs) for r in robots], "robot_steps": n,
           "single_ms_per_robot_step": 1e3 * t_single / n, "batch_ms_per_robot_step": 1e3 * t_batch / n,
           "single_steps_per_s_core": n / t_single, "batch_steps_per_s_core": n / t_batch,
           "speedup": t_single / t_batch, "max_position_difference_mm": diff,
           "contacts_mean": float(np.mean([len(s.contact_nodes) for s in b_states]))}
    if profile:
        import cProfile
        import pstats

        pr = cProfile.Profile()
        pr.enable()
        batched(k)
        pr.disable()
        st = pstats.Stats(pr)
        total = sum(v[2] for v in st.stats.values())
        top = sorted(st.stats.items(), key=lambda kv: -kv[1][2])[:15]
        out["profile_tottime_fraction"] = {f"{f[0].split('/')[-1]}:{f[2]}": round(v[2] / total, 3) for f, v in top}
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--robots", type=int, default=12, help="robots per leg count")
    p.add_argument("--steps", type=int, default=20, help="steps per timed block")
    p.add_argument("--rounds", type=int, default=4, help="alternating blocks")
    p.add_argument("--settle", type=int, default=60, help="untimed steps first (landing)")
    p.add_argument("--legs", type=int, nargs="+", default=[3, 4, 5, 6])
    p.add_argument("--no-mixed", action="store_true", help="skip the batch of all leg counts together")
    p.add_argument("--profile", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--dt", type=float, default=None, help="time step, s (default: the robot's)")
    p.add_argument("--rid-dtype", choices=RID_DTYPES, default="float64", help="precision of the RID products")
    p.add_argument("--disk-mesh-size", type=float, default=None, help="mm (default: the robot's)")
    p.add_argument("--contact-max-iterations", type=int, default=None, help="Gauss-Seidel sweeps per chunk")
    p.add_argument("--leg-collision-spacing", type=float, default=None, help="mm (RobotConfig.leg_collision_spacing)")
    args = p.parse_args()
    rng = np.random.default_rng(args.seed)
    extra = {k: v for k, v in (("dt", args.dt), ("disk_mesh_size", args.disk_mesh_size),
                               ("contact_max_iterations", args.contact_max_iterations),
                               ("leg_collision_spacing", args.leg_collision_spacing)) if v is not None}
    config = RobotConfig(model="reduced", rid_dtype=args.rid_dtype, **extra)
    sets = {legs: [build_robot(d, config) for d in designs_with(legs, args.robots, rng)] for legs in args.legs}
    results = {}
    for legs, robots in sets.items():
        results[f"{legs}_legs"] = measure(robots, args.steps, args.rounds, args.settle, args.profile)
    if not args.no_mixed and len(sets) > 1:
        mixed = [r for robots in sets.values() for r in robots]
        results["mixed"] = measure(mixed, args.steps, args.rounds, args.settle, args.profile)
    print(json.dumps({"machine": platform.platform(), "cpus": os.cpu_count(), "args": vars(args),
                      "results": results, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024},
                     indent=2))


if __name__ == "__main__":
    main()
