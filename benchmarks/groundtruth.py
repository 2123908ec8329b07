"""Ground-truth measurements (issue 21): screening rank agreement and the cost of one design.

``python benchmarks/groundtruth.py screening --designs 8 --gaits 5 --out screening.json``:
random step gaits on a random sample of three-legged designs (plus the paper's L1), each run
with short episodes and the full 20 s; prints the Spearman rank correlations (all pairs, best per
design, within designs) and the wall seconds per duration (1 process).

``python benchmarks/groundtruth.py cost --design 1,0,0,2,2,0,0,0``: one design's ground truth
with the default :class:`GroundTruthConfig` (or ``--evals-per-cycle``), prints its episodes,
simulated seconds and wall seconds, and the projection for N designs on W cores.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

from softcrawl.codesign.groundtruth import (  # noqa: E402
    GroundTruthConfig,
    gt_robot,
    optimize_design,
    parse_designs,
    screening_agreement,
)
from softcrawl.design.space import PAPER_BEST_DESIGN  # noqa: E402


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    s = sub.add_parser("screening")
    s.add_argument("--designs", type=int, default=6, help="sampled three-legged designs (incl. the paper's L1)")
    s.add_argument("--gaits", type=int, default=5, help="random gaits per design (plus one structured)")
    s.add_argument("--short", default="4,6,10", help="short episode lengths, s")
    s.add_argument("--disk-mesh-size", type=float, default=10.0)
    s.add_argument("--dt", type=float, default=None, help="time step, s (default: the robot's)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--out", help="write the full JSON here")
    c = sub.add_parser("cost")
    c.add_argument("--design", default="1,0,0,2,2,0,0,0")
    c.add_argument("--evals-per-cycle", type=int, default=None)
    c.add_argument("--disk-mesh-size", type=float, default=10.0)
    c.add_argument("--dt", type=float, default=None, help="time step, s (default: the robot's)")
    c.add_argument("--cycles", default=None, help="pattern lengths, e.g. 2,3,4 (default: the config's)")
    c.add_argument("--n-designs", type=int, default=280)
    c.add_argument("--cores", type=int, default=2)
    a = p.parse_args(argv)
    if a.cmd == "screening":
        rng = np.random.default_rng(a.seed)
        three = parse_designs("3")
        pick = [PAPER_BEST_DESIGN] + [three[i] for i in rng.choice(len(three), a.designs - 1, replace=False)]
        cfg = GroundTruthConfig(robot=gt_robot(disk_mesh_size=a.disk_mesh_size, dt=a.dt))
        res = screening_agreement(pick, cfg, a.gaits, [float(x) for x in a.short.split(",")], seed=a.seed)
        if a.out:
            with open(a.out, "w") as f:
                json.dump(res, f, indent=2)
        print(json.dumps({k: v for k, v in res.items() if k != "pairs"} | {"n_pairs": len(res["pairs"])}, indent=2))
    else:
        cfg = GroundTruthConfig(robot=gt_robot(disk_mesh_size=a.disk_mesh_size, dt=a.dt))
        if a.cycles:
            cfg.cycles = tuple(int(c) for c in a.cycles.split(","))
        if a.evals_per_cycle:
            cfg.evals_per_cycle = a.evals_per_cycle
        r = optimize_design(a.design, cfg)
        per = r.wall_seconds
        print(json.dumps({"design": list(r.design), "reward_cm": r.reward_cm, "gait": r.gait,
                          "evaluations": r.evaluations, "full_evaluations": r.full_evaluations,
                          "sim_seconds": r.sim_seconds, "wall_seconds": per,
                          "projection": {"designs": a.n_designs, "cores": a.cores,
                                         "wall_hours": per * a.n_designs / a.cores / 3600}}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
