"""What building the JAX engine's per-design data costs (issue 50): the design table of the
``paper`` preset's robots (:func:`softcrawl.jaxsim.tables.build_table`, once per run), the rows
of ``--designs`` random canonical designs of the paper's space gathered from it
(:meth:`DesignTable.rows`, numpy, and :meth:`DesignTable.model`, on JAX's device), against the
per-robot path for ``--old`` designs, per design: ``build_robot``, then the robot's rows as
:func:`~softcrawl.jaxsim.model.build_model` makes them. With ``--cache`` it also settles the
designs for one step (no floor: the cost measured is the cache's, not the settling's) into a
temporary settled-state cache (:class:`~softcrawl.jaxsim.tables.SettledStates`) and reads them
all back.

Runs on one CPU core: the process is pinned to its first allowed core (as ``taskset -c 0``) and
BLAS gets one thread (XLA's threads share the core). Prints JSON: seconds, float32 (the
preset's precision).

Usage: python benchmarks/design_tables.py [--designs 1024] [--old 16] [--seed 0] [--cache]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_v] = "1"
os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})

import argparse  # noqa: E402
import json  # noqa: E402
import platform  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402
import numpy as np  # noqa: E402

from softcrawl.codesign.config import preset  # noqa: E402
from softcrawl.codesign.factory import robot_factory  # noqa: E402
from softcrawl.jaxsim.model import _robot_data, disk_inverse  # noqa: E402
from softcrawl.jaxsim.tables import SettledStates, build_table  # noqa: E402
from softcrawl.robot import Settling  # noqa: E402


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--designs", type=int, default=1024, help="random canonical designs whose rows are built")
    p.add_argument("--old", type=int, default=16, help="designs built by the per-robot path")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--cache", action="store_true", help="also time the settled-state cache's write and read")
    args = p.parse_args()
    cfg = preset("paper")
    factory, space = robot_factory(cfg), cfg.env.design_space()
    rng = np.random.default_rng(args.seed)
    designs = [space.canonical_designs[i] for i in rng.choice(len(space.canonical_designs), args.designs)]
    factory(designs[0])  # meshes and reduction file read once, as in a run
    t0 = time.perf_counter()
    table = build_table(space, factory=factory, n_slots=space.max_legs)
    t1 = time.perf_counter()
    rows = table.rows(designs)
    t2 = time.perf_counter()
    jax.block_until_ready(table.model(designs))
    t3 = time.perf_counter()
    inverse = disk_inverse(factory(designs[0]))
    t4 = time.perf_counter()
    for d in designs[:args.old]:
        _robot_data(factory(d), space.max_legs, inverse)
    t5 = time.perf_counter()
    out = {"machine": platform.platform(), "cpu": platform.processor() or platform.machine(),
           "cores": sorted(os.sched_getaffinity(0)), "dtype": str(table.dtype), "designs": args.designs,
           "table_build_s": t1 - t0, "rows_s": t2 - t1,
           "rows_mb": sum(a.nbytes for a in jax.tree_util.tree_leaves(rows)) / 1e6,
           "model_s": t3 - t2, "old_per_design_s": (t5 - t4) / args.old,
           "old_for_all_designs_s": (t5 - t4) / args.old * args.designs}
    if args.cache:
        with tempfile.TemporaryDirectory() as folder:
            one_step = build_table(space, factory=factory, n_slots=space.max_legs, floor=False)
            cache = SettledStates(one_step, Settling(max_seconds=cfg.env.robot.dt), folder)
            t6 = time.perf_counter()
            cache.get(designs, space.max_legs, batch=len(designs))
            t7 = time.perf_counter()
            again = SettledStates(one_step, Settling(max_seconds=cfg.env.robot.dt), folder)
            again.get(designs, space.max_legs)
            t8 = time.perf_counter()
            files = list(cache.folder.rglob("*.npz"))
            out.update({"cache_settle_and_write_s": t7 - t6, "cache_read_s": t8 - t7, "cache_files": len(files),
                        "cache_file_kb": float(np.mean([f.stat().st_size for f in files])) / 1e3})
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
