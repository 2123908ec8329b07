"""What the animation (``crawl.gif``, :func:`softcrawl.robot.animation.write_animation`) adds to
a report: the ``demo`` preset's robot (reduced 6 mm legs, 25 mm disk, dt 0.02 s) of ``--design``
crawls one 20 s episode with the sine gait (110° phase lag), recorded every 10 steps as the
report's re-run is; the GIF of that episode is then rendered ``--repeats`` times. Prints JSON: the
simulation's wall seconds, and per render the wall and CPU seconds, the frames drawn and the file
size.

Usage: OMP_NUM_THREADS=1 python benchmarks/animation_cost.py [--design 0,0,1,0,2,1,0,0] [--repeats 3]
       [--out /tmp/crawl.gif]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

from softcrawl.codesign.config import preset
from softcrawl.codesign.evaluation import episode_seconds
from softcrawl.codesign.factory import robot_factory
from softcrawl.design.space import validate_design
from softcrawl.gaits import SineGait
from softcrawl.robot.animation import write_animation
from softcrawl.robot.episode import run_episode


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--design", default="0,0,1,0,2,1,0,0")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--out", default="crawl.gif")
    args = p.parse_args()
    cfg = preset("demo")
    robot = robot_factory(cfg)(validate_design(args.design))
    result = run_episode(robot, SineGait(phase_deg=110.0), episode_seconds(cfg), record_every=10, progress=False)
    renders = []
    for _ in range(args.repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        n = write_animation(args.out, robot, result)
        renders.append({"wall_s": round(time.perf_counter() - wall, 3), "cpu_s": round(time.process_time() - cpu, 3),
                        "frames": n, "bytes": os.path.getsize(args.out)})
    print(json.dumps({"design": args.design, "episode_s": result.sim_seconds, "recorded_frames": len(result.frames),
                      "simulation_wall_s": round(result.wall_seconds, 2), "renders": renders,
                      "load_average": os.getloadavg(), "cpu": platform.processor() or platform.machine()}, indent=1))


if __name__ == "__main__":
    main()
