"""Full-order step time of one PneuNet (clamped at its inner end, pressurised, on the floor)
vs mesh size. Prints JSON: nodes, tets, seconds per step (mean of the steady part), peak RSS.

Usage: OMP_NUM_THREADS=1 python benchmarks/fom_step.py [--sizes 8 6 4] [--steps 40]
"""

from __future__ import annotations

import argparse
import json
import platform
import resource
import time

import numpy as np

from softcrawl.fem.body import Body, Cavity, Membrane
from softcrawl.fem.materials import DRAGONSKIN_30, PAPER
from softcrawl.fem.model import Floor, Model
from softcrawl.fem.solver import ImplicitEulerSolver, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.geometry import PneuNetParams, pneunet_mesh


def bench(mesh_size: float, steps: int, refactor_every: int = 1) -> tuple[dict, np.ndarray]:
    t0 = time.perf_counter()
    mesh = pneunet_mesh(PneuNetParams(mesh_size=mesh_size))
    t_mesh = time.perf_counter() - t0
    fixed = np.zeros((mesh.n_nodes, 3), bool)
    fixed[np.abs(mesh.points[:, 0] + 57.5) < 1e-6] = True
    placed = mesh.transformed(np.eye(3), [0.0, 0.0, 2.0])  # 2 mm above the floor: it lands, then bends
    body = Body(placed, DRAGONSKIN_30, 0.105, membrane=Membrane(mesh.surfaces["paper"], PAPER, 1.0),
                cavities=(Cavity(mesh.surfaces["cavity"], 0),), fixed=fixed)
    model = Model((body,), floor=Floor())
    solver = ImplicitEulerSolver(model, SolverSettings(refactor_every=refactor_every))
    state = model.rest_state()
    times, contacts, factorizations, cg = [], [], 0, 0
    for k in range(steps):
        t = time.perf_counter()
        state = solver.step(state, Control(np.array([min(150.0, 5.0 * k)])))
        times.append(time.perf_counter() - t)
        contacts.append(solver.stats.n_contacts)
        factorizations += solver.stats.factorizations
        cg += solver.stats.cg_iterations
    steady = np.array(times[steps // 4 :])
    return {
        "mesh_size_mm": mesh_size, "refactor_every": refactor_every,
        "factorizations": factorizations, "cg_iterations": cg, "nodes": mesh.n_nodes, "tets": mesh.n_tets, "dof": 3 * mesh.n_nodes,
        "mesh_seconds": round(t_mesh, 3), "first_step_seconds": round(times[0], 3),
        "seconds_per_step": round(float(steady.mean()), 4), "max_step_seconds": round(float(steady.max()), 4),
        "mean_loaded_contacts": round(float(np.mean(contacts[steps // 4 :])), 1),
    }, state.x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--sizes", type=float, nargs="+", default=[8.0, 6.0, 4.0])
    ap.add_argument("--steps", type=int, default=40)
    ap.add_argument("--refactor-every", type=int, nargs="+", default=[1, 5, 10],
                    help="factorization reuse settings to compare (1 = exact, the reference)")
    args = ap.parse_args()
    rows = []
    for h in args.sizes:
        ref = None
        for r in args.refactor_every:
            row, x = bench(h, args.steps, r)
            ref = x if ref is None else ref
            # Lagging the contact compliance changes the trajectory slightly: report by how much.
            row["max_node_difference_vs_first_mm"] = float(np.abs(x - ref).max())
            rows.append(row)
    print(json.dumps({
        "benchmark": "fom_step_single_pneunet", "machine": f"{platform.node()} {platform.processor() or platform.machine()}",
        "python": platform.python_version(), "results": rows,
        "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1),
    }, indent=1))


if __name__ == "__main__":
    main()
