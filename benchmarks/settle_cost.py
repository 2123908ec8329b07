"""What a training worker's robots cost before and during an episode (issue 18): ``--robots``
random canonical designs of each leg count in ``--legs`` (the ``paper`` preset's robots: shipped
reduction, 10 mm disk, dt 0.02 s, float32 RID products) are settled to rest together from their
assembled state (the landing before every episode, ``softcrawl.robot.settle`` in lockstep as
:meth:`softcrawl.envs.backends.batched.BatchedBackend.settle_together` runs it), then stepped ``--steps``
steps as one batch under training-like pressures (every regulator holds a random 0..90 sim kPa
for 1 s). Prints JSON: CPU seconds and ms per robot step of each part, settling steps.

``--contact-max-iterations`` sets the Gauss-Seidel sweep limit and ``--leg-collision-spacing`` the
legs' contact points (``RobotConfig``; default: the ``paper`` preset's). To compare two
checkouts, run each with ``PYTHONPATH=<checkout>``, alternately (this machine's speed drifts by
±15%).

Usage: OMP_NUM_THREADS=1 python benchmarks/settle_cost.py [--robots 12] [--legs 5 6] [--steps 150]
       [--seed 0] [--contact-max-iterations N] [--leg-collision-spacing MM]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import time

import numpy as np

from softcrawl.codesign.config import EnvConfig
from softcrawl.reduction.batch import BatchedReducedSolver, run_in_lockstep
from softcrawl.robot import Settling, build_robot, settle
from batch_step import designs_with  # this folder's script


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--robots", type=int, default=12, help="robots per leg count")
    p.add_argument("--legs", type=int, nargs="+", default=[5, 6])
    p.add_argument("--steps", type=int, default=150, help="batched steps after settling")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--leg-collision-spacing", type=float, default=None, help="mm (default: the paper preset's)")
    p.add_argument("--contact-max-iterations", type=int, default=None,
                   help="Gauss-Seidel sweeps per chunk (default: the paper preset's)")
    args = p.parse_args()
    env = EnvConfig()
    iterations = args.contact_max_iterations or env.robot.contact_max_iterations
    spacing = env.robot.leg_collision_spacing if args.leg_collision_spacing is None else args.leg_collision_spacing
    rng = np.random.default_rng(args.seed)
    designs = [d for n in args.legs for d in designs_with(n, args.robots, rng)]
    cfg = dataclasses.replace(env.robot, contact_max_iterations=iterations, leg_collision_spacing=spacing)
    robots = [build_robot(d, cfg) for d in designs]
    solvers = [r.make_solver() for r in robots]
    c0 = time.process_time()
    settled = run_in_lockstep(solvers, [lambda s, r=r: settle(r, Settling(), solver=s) for r in robots])
    c1 = time.process_time()
    batch = BatchedReducedSolver(solvers)
    states = [s.state for s in settled]
    held = rng.uniform(0.0, 90.0, (args.steps // 50 + 1, len(robots), 3))
    for k in range(args.steps):
        states = batch.step(states, [r.control(held[k // 50, i]) for i, r in enumerate(robots)])
    c2 = time.process_time()
    settle_steps = sum(s.steps for s in settled)
    print(json.dumps({"machine": platform.platform(), "robots": len(robots), "legs": args.legs,
                      "contact_max_iterations": iterations, "leg_collision_spacing": spacing,
                      "settle_cpu_s": c1 - c0, "settle_robot_steps": settle_steps,
                      "settle_ms_per_robot_step": 1e3 * (c1 - c0) / settle_steps, "episode_cpu_s": c2 - c1,
                      "episode_ms_per_robot_step": 1e3 * (c2 - c1) / (args.steps * len(robots))}, indent=1))


if __name__ == "__main__":
    main()
