"""Settling to rest over a design set (issue 23): steps until every node is slower than the
rest speed (``softcrawl.robot.Settling``), the rest speed reached, how many designs hit the cap,
and the +x shift of the disk top centre during settling (what the old fixed 3 or 15 steps left
to be scored as crawling). Prints JSON.

    OMP_NUM_THREADS=1 python benchmarks/settling.py [--legs 3] [--disk-mesh 25] [--dt 0.01] [--workers 2]
        [--rest-speed 0.5] [--hold 0.05] [--limit N] [--sample N]

Each design also reports the drift after settling: the disk top centre's +x motion over the
next 0.2 s at zero pressure (what a looser rest rule would leave to be scored as crawling).
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
from tqdm.auto import tqdm

from softcrawl.codesign.config import EnvConfig
from softcrawl.parallel import run_pool


def settle_design(design, disk_mesh: float, dt: float, rest_speed: float = 0.5, hold: float = 0.05) -> dict:
    from softcrawl.robot import RobotConfig, Settling, build_robot, settle

    robot = build_robot(design, RobotConfig(model="reduced", disk_mesh_size=disk_mesh, dt=dt))
    x0 = robot.reward_position(robot.model.rest_state().x)
    t = time.perf_counter()
    s = settle(robot, Settling(rest_speed=rest_speed, hold_seconds=hold))
    wall = time.perf_counter() - t
    solver, state, zero = robot.make_solver(), s.state, robot.control(np.zeros(3))
    for _ in range(round(0.2 / dt)):
        state = solver.step(state, zero)
    drift = float(robot.reward_position(state.x)[0] - robot.reward_position(s.state.x)[0])
    return {"design": ",".join(map(str, design)), "steps": s.steps, "seconds": s.seconds, "at_rest": s.at_rest,
            "rest_speed_mm_s": s.rest_speed, "shift_x_mm": float(robot.reward_position(s.state.x)[0] - x0[0]),
            "drift_x_mm_0.2s": drift, "wall_seconds": wall}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--legs", type=int, default=3)
    ap.add_argument("--disk-mesh", type=float, default=25.0)
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--limit", type=int, default=0, help="first N designs only (0: all)")
    ap.add_argument("--sample", type=int, default=0, help="N designs drawn at random (seed 0) instead of all")
    ap.add_argument("--rest-speed", type=float, default=0.5, help="rest rule: node speed, mm/s")
    ap.add_argument("--hold", type=float, default=0.05, help="rest rule: seconds below the rest speed")
    args = ap.parse_args()
    designs = EnvConfig(legs=(args.legs,)).designs()
    if args.limit:
        designs = designs[: args.limit]
    if args.sample:
        pick = np.random.default_rng(0).choice(len(designs), args.sample, replace=False)
        designs = [designs[i] for i in sorted(pick)]
    rows, bar = [], tqdm(total=len(designs), desc="settle", unit="design")
    t0 = time.perf_counter()

    def done(row):
        rows.append(row)
        bar.update()

    run_pool(settle_design, args.workers, [(d, args.disk_mesh, args.dt, args.rest_speed, args.hold) for d in designs],
             done)
    bar.close()
    steps = np.array([r["steps"] for r in rows])
    shift = np.abs([r["shift_x_mm"] for r in rows])
    print(json.dumps({
        "designs": len(rows), "legs": args.legs, "disk_mesh_mm": args.disk_mesh, "dt_s": args.dt,
        "steps_to_rest": {"median": float(np.median(steps)), "p90": float(np.percentile(steps, 90)),
                          "max": int(steps.max()), "min": int(steps.min())},
        "hit_cap": int(sum(not r["at_rest"] for r in rows)),
        "not_at_rest": [r["design"] for r in rows if not r["at_rest"]],
        "rest_rule": {"rest_speed_mm_s": args.rest_speed, "hold_s": args.hold},
        "max_rest_speed_mm_s": float(max(r["rest_speed_mm_s"] for r in rows)),
        "drift_x_mm_0.2s": {"median": float(np.median(np.abs([r["drift_x_mm_0.2s"] for r in rows]))),
                            "max": float(np.max(np.abs([r["drift_x_mm_0.2s"] for r in rows])))},
        "settling_x_shift_mm": {"median": float(np.median(shift)), "max": float(shift.max()),
                                "over_5mm": int((shift > 5).sum())},
        "slowest": sorted(rows, key=lambda r: -r["steps"])[:5],
        "mean_settle_wall_seconds": float(np.mean([r["wall_seconds"] for r in rows])),
        "wall_seconds": round(time.perf_counter() - t0, 1), "machine": platform.node(), "cpus": 2,
    }, indent=1))


if __name__ == "__main__":
    main()
