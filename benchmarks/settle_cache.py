"""How many settlings a training run's robot cache saves (issue 18): replays the designs of a
recorded run (``episodes.csv``, in order: each block of ``n_envs`` rows is one reset of every env,
env ``i`` on the worker whose chunk holds it, :func:`softcrawl.envs.backends.env_chunks`) through each worker's
:class:`softcrawl.envs.robot_cache.RobotCache` (``max_cached_robots`` spare robots), once keeping
no settled state beyond its robot (``--settled-mb 0``, the cache before this benchmark) and once
with the default memory bound, and counts the episodes that had to settle. Each kept state has
the size of the run's robots' positions and velocities (one robot built per leg count).

With ``--measure K`` it also settles K of the run's designs in lockstep, as a training worker
does (:meth:`softcrawl.envs.backends.batched.BatchedBackend.settle_together`), and prints their mean CPU
seconds, so the saved settlings can be put in seconds.

Usage: OMP_NUM_THREADS=1 python benchmarks/settle_cache.py RUN [--settled-mb MB] [--measure K]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from softcrawl.codesign.factory import robot_factory
from softcrawl.codesign.run import Run
from softcrawl.envs.backends import env_chunks
from softcrawl.envs.robot_cache import SETTLED_MB, RobotCache
from softcrawl.fem.state import State
from softcrawl.reduction.batch import run_in_lockstep
from softcrawl.robot.episode import SettledState, settle


def replay(designs: list, n_envs: int, n_workers: int, spare: int, settled_mb: float, nodes: dict) -> int:
    """Settlings of the run's resets (module doc) with caches keeping ``settled_mb`` MB of states
    (``nodes``: a robot's node count per leg count)."""
    chunks = env_chunks(n_envs, n_workers)
    worker = {i: w for w, chunk in enumerate(chunks) for i in chunk}
    caches = [RobotCache(spare, settled_mb) for _ in chunks]
    for cache, chunk in zip(caches, chunks):
        for _ in chunk:
            cache.attach()
    settles = 0
    for i, design in enumerate(designs):
        cache = caches[worker[i % n_envs]]
        robot, settled = cache.fetch(design, lambda d: object())
        if settled is None:
            settles += 1
            n = nodes[sum(v > 0 for v in design)]
            cache.keep_settled(design, robot, SettledState(State(np.empty((n, 3)), np.empty((n, 3))), 0, 0.0, 0.0, True))
    return settles


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("run", help="a training run folder (episodes.csv, config.json)")
    p.add_argument("--settled-mb", type=float, default=SETTLED_MB)
    p.add_argument("--measure", type=int, default=0, help="designs to settle for the CPU cost of a settling")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    run = Run(args.run)
    cfg = run.read_config()
    designs = [tuple(int(c) for c in d) for d in run.read_episodes()["design"]]
    build = robot_factory(cfg)
    nodes = {}
    for d in designs:
        legs = sum(v > 0 for v in d)
        if legs not in nodes:
            nodes[legs] = build(d).model.n_nodes
    kw = {"n_envs": cfg.n_envs, "n_workers": cfg.n_workers, "spare": cfg.env.max_cached_robots, "nodes": nodes}
    before = replay(designs, settled_mb=0.0, **kw)
    after = replay(designs, settled_mb=args.settled_mb, **kw)
    out = {"machine": platform.platform(), "run": str(run.path), "preset": cfg.preset, "episodes": len(designs),
           "distinct_designs": len(set(designs)), "max_cached_robots": cfg.env.max_cached_robots,
           "settled_mb": args.settled_mb, "state_mb_by_legs": {k: 48 * n / 1e6 for k, n in sorted(nodes.items())},  # x and v: 2 x 3 x 8 bytes a node
           "settlings_robots_only": before, "settlings_with_kept_states": after}
    if args.measure:
        rng = np.random.default_rng(args.seed)
        pool = sorted(set(designs))
        sample = [pool[i] for i in rng.choice(len(pool), min(args.measure, len(pool)), replace=False)]
        robots = [build(d) for d in sample]
        t = time.process_time()
        run_in_lockstep([r.make_solver() for r in robots],
                        [lambda s, r=r: settle(r, cfg.env.settling(), solver=s) for r in robots])
        cpu = (time.process_time() - t) / len(robots)
        out.update({"settle_cpu_s_mean": cpu, "cpu_s_saved": cpu * (before - after)})
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
