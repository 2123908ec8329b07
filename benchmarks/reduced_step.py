"""Reduced vs full-order step of the expert baseline (design 1,0,0,2,2,0,0,1, sine gait, φ = 110°),
both in one process, one BLAS thread, timed in alternating blocks. Prints JSON: seconds per step of each model (episode
steps only, after settling), the speedup, reduced steps per second per core, the robot's
reduced sizes (modes, RID elements of a leg and of the disk) and the peak RSS. The full model
uses the reduction's meshes.

Usage: OMP_NUM_THREADS=1 python benchmarks/reduced_step.py [--full-steps 30] [--reduced-steps 500] [--rounds 10]
       [--reduction FILE.npz] [--disk-mesh 10] [--reduced-disk floating|corotational]
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


def time_interleaved(robots, steps: list[int], rounds: int) -> list[float]:
    """Seconds per step of each robot's episode (gait steps after settling), run in
    ``rounds`` alternating blocks of ``steps[i] / rounds`` steps so that every model sees the
    same machine load (this VM's speed drifts by tens of percent within minutes)."""
    from softcrawl.gaits import SineGait
    from softcrawl.robot import Episode

    gait = SineGait(phase_deg=110.0)
    episodes, done, spent = [], [], []
    for robot in robots:
        ep = Episode(robot)
        ep.reset()
        ep.step(gait.pressure_at(0.0))  # warm-up (numba cache load, first factorization)
        episodes.append(ep)
        done.append(1)
        spent.append(0.0)
    for r in range(rounds):
        for i, ep in enumerate(episodes):
            block = steps[i] * (r + 1) // rounds - steps[i] * r // rounds
            t0 = time.perf_counter()
            for _ in range(block):
                ep.step(gait.pressure_at(done[i] * ep.dt))
                done[i] += 1
            spent[i] += time.perf_counter() - t0
    return [t / n for t, n in zip(spent, steps)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--full-steps", type=int, default=30)
    p.add_argument("--reduced-steps", type=int, default=500)
    p.add_argument("--rounds", type=int, default=10, help="alternating blocks of reduced and full steps")
    p.add_argument("--reduction", default=None, help="reduction file (default: the shipped one)")
    p.add_argument("--disk-mesh", type=float, default=None,
                   help="disk mesh size, mm (default: the robot's, 10; not with a POD-reduced disk)")
    p.add_argument("--reduced-disk", default="floating", choices=("floating", "corotational"),
                   help="the reduced robot's disk when the reduction has none (RobotConfig.reduced_disk)")
    args = p.parse_args()
    from softcrawl.design.space import BASELINE_DESIGN
    from softcrawl.reduction.model import ReducedBody
    from softcrawl.robot import RobotConfig, build_robot

    size = {} if args.disk_mesh is None else {"disk_mesh_size": args.disk_mesh}
    reduced = build_robot(BASELINE_DESIGN, RobotConfig(model="reduced", reduction=args.reduction,
                                                       reduced_disk=args.reduced_disk, **size))
    leg = reduced.reduced[reduced.legs[0].body]
    disk = reduced.reduced.get(reduced.disk_body)
    pod_disk = disk if isinstance(disk, ReducedBody) else None
    full = build_robot(BASELINE_DESIGN, RobotConfig(**size), leg_mesh=leg.part.mesh,
                       disk_mesh_local=pod_disk.part.mesh if pod_disk else None)
    t_red, t_full = time_interleaved([reduced, full], [args.reduced_steps, args.full_steps], args.rounds)
    print(json.dumps({
        "design": list(BASELINE_DESIGN), "nodes": full.model.n_nodes, "disk_mesh_size": full.config.disk_mesh_size,
        "modes_per_leg": leg.n_modes, "rid_tetrahedra_per_leg": len(leg.part.tet_rid),
        "rid_triangles_per_leg": len(leg.part.tri_rid),
        "disk": ({"modes": pod_disk.n_modes, "rid_tetrahedra": len(pod_disk.part.tet_rid)} if pod_disk
                 else "floating frame" if disk else "full-order corotational"),
        "full_seconds_per_step": round(t_full, 4), "full_steps": args.full_steps, "rounds": args.rounds,
        "reduced_seconds_per_step": round(t_red, 6), "reduced_steps": args.reduced_steps,
        "speedup": round(t_full / t_red, 1), "reduced_steps_per_second_per_core": round(1.0 / t_red, 1),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
    }, indent=1))


if __name__ == "__main__":
    main()
