"""Full-order episode cost of the expert baseline (design 1,0,0,2,2,0,0,1, sine gait, phase 110°)
vs leg mesh size and factorization reuse. Prints JSON: per case the wall time of a short episode,
seconds per step, real-time factor, projected wall time of a 20 s episode, nodes/tets, mean
contacts and the case's peak RSS.

Each case runs in its own fresh process (one BLAS thread), so its peak RSS is its own; a one-step
warm-up episode (numba cache load) precedes the timed one and is reported separately. Wall times
include the settling steps.

Usage: OMP_NUM_THREADS=1 python benchmarks/episode.py [--sizes 8 6 4] [--refactor-every 1 5] [--duration 2]
"""

from __future__ import annotations

import argparse
import concurrent.futures as cf
import json
import multiprocessing
import os
import platform
import resource
import time

#: Episode length the projection is for, s (the paper's episodes).
PROJECT_TO_S = 20.0


def bench(mesh_size: float, refactor_every: int, duration: float) -> dict:
    """One case, run in a worker process: build the baseline robot and run ``duration`` s."""
    from softcrawl.design.space import BASELINE_DESIGN
    from softcrawl.gaits import SineGait
    from softcrawl.robot import NO_SETTLING, RobotConfig, build_robot, run_episode, settle

    t0 = time.perf_counter()
    robot = build_robot(BASELINE_DESIGN, RobotConfig(leg_mesh_size=mesh_size, refactor_every=refactor_every))
    build = time.perf_counter() - t0
    t0 = time.perf_counter()  # warm-up: load the numba kernels' disk cache, first factorizations
    run_episode(robot, SineGait(phase_deg=110.0), robot.config.dt, settling=NO_SETTLING, record_every=None,
                progress=False)
    warmup = time.perf_counter() - t0
    settled = settle(robot)  # once per design; not part of the episode's time
    res = run_episode(robot, SineGait(phase_deg=110.0), duration, record_every=None, progress=False, settled=settled)
    per_step = res.wall_seconds / res.steps
    return {
        "mesh_size_mm": mesh_size, "refactor_every": refactor_every,
        "nodes": robot.model.n_nodes, "tets": sum(b.mesh.n_tets for b in robot.model.bodies),
        "build_seconds": round(build, 2), "warmup_seconds": round(warmup, 2),
        "steps": res.steps, "settle_steps": settled.steps,
        "wall_seconds": round(res.wall_seconds, 2), "seconds_per_step": round(per_step, 4),
        "real_time_factor": round(res.real_time_factor, 4),
        "projected_20s_episode_minutes": round(per_step * PROJECT_TO_S / robot.config.dt / 60, 1),
        "mean_contacts": round(float(res.contacts[1:].mean()), 1) if res.steps else None,
        "factorizations": res.factorizations, "reward_cm": round(res.reward_cm, 4),
        "diverged": res.diverged, "divergence_reason": res.reason,
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=float, nargs="+", default=[8.0, 6.0, 4.0], help="leg mesh sizes, mm")
    ap.add_argument("--refactor-every", type=int, nargs="+", default=[1, 5],
                    help="factorization reuse settings (1 = exact, the reference)")
    ap.add_argument("--duration", type=float, default=2.0, help="episode length, s (default 2)")
    args = ap.parse_args()
    os.environ["OMP_NUM_THREADS"] = "1"  # inherited by the spawned workers
    rows = []
    ctx = multiprocessing.get_context("spawn")
    for h in args.sizes:
        for r in args.refactor_every:
            with cf.ProcessPoolExecutor(max_workers=1, mp_context=ctx) as pool:  # fresh process per case
                rows.append(pool.submit(bench, h, r, args.duration).result())
    import numpy, scipy  # noqa: E401 (versions only)
    print(json.dumps({
        "benchmark": "episode_baseline_sine110", "date": time.strftime("%Y-%m-%d"),
        "machine": f"{platform.node()} {platform.machine()}, {os.cpu_count()} CPUs",
        "python": platform.python_version(), "numpy": numpy.__version__, "scipy": scipy.__version__,
        "duration_s": args.duration, "results": rows,
    }, indent=1))


if __name__ == "__main__":
    main()
