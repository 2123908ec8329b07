"""Reduced vs full-order step of the expert baseline (design 1,0,0,2,2,0,0,1, sine gait, φ = 110°),
both in one process, one BLAS thread, timed in alternating blocks. Prints JSON: seconds per
step of each model (episode steps only, after settling), the speedup, reduced steps per
second per core, the robot's reduced sizes (modes, RID elements of a leg and of the disk),
optionally the reduced solver's time per section, and the peak RSS. The full model uses the
reduction's meshes.

Usage: OMP_NUM_THREADS=1 python benchmarks/reduced_step.py [--full-steps 30] [--reduced-steps 500] [--rounds 10]
       [--reduction FILE.npz] [--disk-mesh 10] [--reduced-disk floating|corotational] [--sections]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import resource
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


#: Solver methods timed by ``--sections`` (nested: a section's time includes its callees').
SECTIONS = ("step", "_free_motion", "_free_velocity", "_constrain", "_contact_rows", "_delassus",
            "_corrections", "_velocity")


class SectionTimer:
    """Wall time per call of the solver methods in :data:`SECTIONS` (instance attributes
    wrap them, so only this solver is timed) and of the contact solve."""

    def __init__(self, solver):
        import softcrawl.fem.solver as fem_solver

        self.total: dict[str, float] = {}
        for name in SECTIONS:
            setattr(solver, name, self._wrap(getattr(solver, name), name))
        self._module, self._solve = fem_solver, fem_solver.solve_constraints
        self._timed_solve = self._wrap(self._solve, "contact_solve")

    def _wrap(self, fn, name):
        def timed(*a, **k):
            t0 = time.perf_counter()
            try:
                return fn(*a, **k)
            finally:
                self.total[name] = self.total.get(name, 0.0) + time.perf_counter() - t0
        return timed

    def __enter__(self):  # the contact solve is a module function: timed inside the block only
        self._module.solve_constraints = self._timed_solve
        return self

    def __exit__(self, *exc):
        self._module.solve_constraints = self._solve


def time_interleaved(robots, steps: list[int], rounds: int, sections: bool = False) -> tuple[list[float], dict]:
    """Seconds per step of each robot's episode (gait steps after settling), run in
    ``rounds`` alternating blocks of ``steps[i] / rounds`` steps so that every model sees the
    same machine load (this VM's speed drifts by tens of percent within minutes); with
    ``sections``, also the first robot's solver sections in ms per step."""
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
    timer = SectionTimer(episodes[0].solver) if sections else None
    for r in range(rounds):
        for i, ep in enumerate(episodes):
            block = steps[i] * (r + 1) // rounds - steps[i] * r // rounds
            with timer if timer and i == 0 else contextlib.nullcontext():
                t0 = time.perf_counter()
                for _ in range(block):
                    ep.step(gait.pressure_at(done[i] * ep.dt))
                    done[i] += 1
                spent[i] += time.perf_counter() - t0
    ms = {k: round(v / steps[0] * 1e3, 3) for k, v in timer.total.items()} if timer else {}
    return [t / n for t, n in zip(spent, steps)], ms


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
    p.add_argument("--sections", action="store_true",
                   help="also time the reduced solver's sections (adds a few us per call)")
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
    (t_red, t_full), sections = time_interleaved([reduced, full], [args.reduced_steps, args.full_steps],
                                                 args.rounds, args.sections)
    print(json.dumps({
        "design": list(BASELINE_DESIGN), "nodes": full.model.n_nodes, "disk_mesh_size": full.config.disk_mesh_size,
        "modes_per_leg": leg.n_modes, "rid_tetrahedra_per_leg": len(leg.part.tet_rid),
        "rid_triangles_per_leg": len(leg.part.tri_rid),
        "disk": ({"modes": pod_disk.n_modes, "rid_tetrahedra": len(pod_disk.part.tet_rid)} if pod_disk
                 else "floating frame" if disk else "full-order corotational"),
        "full_seconds_per_step": round(t_full, 4), "full_steps": args.full_steps, "rounds": args.rounds,
        "reduced_seconds_per_step": round(t_red, 6), "reduced_steps": args.reduced_steps,
        "speedup": round(t_full / t_red, 1), "reduced_steps_per_second_per_core": round(1.0 / t_red, 1),
        **({"reduced_sections_ms_per_step": sections} if sections else {}),
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024),
        "machine": f"{platform.machine()}, {os.cpu_count()} CPUs, Python {platform.python_version()}",
    }, indent=1))


if __name__ == "__main__":
    main()
