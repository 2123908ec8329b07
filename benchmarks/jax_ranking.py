"""The design ranking on the JAX engine against the CPU reduced engine: the three-legged ground
truth's designs, each with its ground-truth gait for the ground truth's full episode (20 s),
re-simulated by :class:`softcrawl.jaxsim.episodes.JaxEvaluator`, and ranked against the ground
truth's own rewards (the CPU engine's 20-s rewards of exactly those gaits: the ground truth
re-runs its finalists at full length and keeps the best; ``--cpu-check K`` re-simulates K
designs on the CPU engine to confirm the file matches the current code).

Prints and writes to OUT a JSON object: the Spearman rank correlation of the two engines'
rewards, each engine's top design, the max / mean absolute reward difference (cm), diverged
episodes, wall seconds (building and settling the designs; the episodes, compilation included)
and robot-steps per second of the episodes (padding included), and the same per CPU second of
this process (the measure on a shared machine).

``--designs N`` takes a stratified subset: N designs at evenly spaced ranks of the ground truth
(its top design included; ``--offset 0.5``: the ranks between those), for a shared machine that
cannot afford all 280.

Usage: OMP_NUM_THREADS=1 python benchmarks/jax_ranking.py OUT.json [--designs N] [--precision float32]
       [--max-batch 64] [--cpu-check K] [--groundtruth benchmarks/groundtruth/three-legged]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np
from scipy.stats import spearmanr

from softcrawl.codesign.groundtruth import DIVERGED_CM, DesignEvaluator, PeriodicGait, load_groundtruth
from softcrawl.safeio import atomic_write_text

GROUNDTRUTH = Path(__file__).parent / "groundtruth" / "three-legged"


def stratified(designs: list, n: int, offset: float = 0.0) -> list:
    """``n`` of ``designs`` (sorted best first) at evenly spaced ranks, the first included, or
    shifted by ``offset`` (a fraction of the spacing: 0.5 takes the ranks between those of 0)."""
    if n >= len(designs):
        return designs
    ranks = np.linspace(0, len(designs) - 1, n)
    ranks = np.minimum(ranks + offset * (ranks[1] - ranks[0] if n > 1 else 0), len(designs) - 1)
    return [designs[i] for i in np.unique(ranks.round().astype(int))]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("out", help="JSON file to write")
    p.add_argument("--groundtruth", default=str(GROUNDTRUTH), help="ground-truth folder")
    p.add_argument("--designs", type=int, default=None, help="stratified subset of N designs (default: all)")
    p.add_argument("--offset", type=float, default=0.0,
                   help="shift of the subset's ranks, a fraction of their spacing (0.5: the ranks between)")
    p.add_argument("--precision", choices=("float32", "float64"), default="float32")
    p.add_argument("--max-batch", type=int, default=64)
    p.add_argument("--cpu-check", type=int, default=0, help="designs re-simulated on the CPU engine")
    p.add_argument("--duration", type=float, default=None, help="episode s (default: the ground truth's)")
    args = p.parse_args()
    jax.config.update("jax_enable_x64", args.precision == "float64")
    from softcrawl.jaxsim.episodes import JaxEvaluator

    cfg, results, _ = load_groundtruth(args.groundtruth)
    duration = args.duration or cfg.duration
    ranked = sorted(results.values(), key=lambda r: -r.reward_cm)
    rows = stratified(ranked, args.designs or len(ranked), args.offset)
    requests = [(r.design, PeriodicGait.from_dict(r.gait), duration) for r in rows]
    ev = JaxEvaluator(cfg.robot, args.precision, max_batch=args.max_batch, diverged_cm=DIVERGED_CM)
    wall, cpu_time = time.perf_counter(), time.process_time()
    ev.prepare([r.design for r in rows])
    settling = (time.perf_counter() - wall, time.process_time() - cpu_time)
    wall, cpu_time = time.perf_counter(), time.process_time()
    got = []
    for i in range(0, len(requests), args.max_batch):  # one batch per call: progress on stderr
        got += ev.evaluate(requests[i:i + args.max_batch])
        print(f"{len(got)}/{len(requests)} episodes, {time.perf_counter() - wall:.0f} s", file=sys.stderr, flush=True)
    episodes = (time.perf_counter() - wall, time.process_time() - cpu_time)
    cpu = np.array([r.reward_cm for r in rows]) if duration == cfg.duration else None
    jx = np.array([g for g, _ in got])
    report = {
        "groundtruth": str(args.groundtruth), "designs": len(rows), "of": len(ranked), "duration_s": duration,
        "dt_s": cfg.robot.dt, "precision": args.precision, "max_batch": args.max_batch,
        "diverged": int(sum(d for _, d in got)),
        "settle_steps": {"mean": float(np.mean([ev.settled(r.design).steps for r in rows])),
                         "not_at_rest": int(sum(not ev.settled(r.design).at_rest for r in rows))},
        "wall_seconds_settling": settling[0], "cpu_seconds_settling": settling[1],
        "wall_seconds_episodes": episodes[0], "cpu_seconds_episodes": episodes[1],
        "robot_steps": ev.robot_steps, "robot_steps_per_s": ev.robot_steps / episodes[0],
        "robot_steps_per_cpu_s": ev.robot_steps / episodes[1],
        "jax_top": list(rows[int(np.argmax(jx))].design),
        "host": platform.processor() or platform.machine(), "jax": jax.__version__,
    }
    if cpu is not None:
        diff = np.abs(jx - cpu)
        report.update(spearman=float(spearmanr(cpu, jx).statistic), cpu_top=list(rows[int(np.argmax(cpu))].design),
                      same_top=bool(np.argmax(cpu) == np.argmax(jx)), max_abs_diff_cm=float(diff.max()),
                      mean_abs_diff_cm=float(diff.mean()))
    if args.cpu_check:
        check = []
        for r in stratified(rows, args.cpu_check):
            t = time.perf_counter()
            reward, div = DesignEvaluator(r.design, cfg)(PeriodicGait.from_dict(r.gait), duration)
            check.append({"design": list(r.design), "file_cm": r.reward_cm, "cpu_now_cm": reward,
                          "diverged": div, "wall_s": time.perf_counter() - t})
        report["cpu_check"] = check
    report["rows"] = [{"design": list(r.design), "cpu_cm": r.reward_cm, "jax_cm": g, "jax_diverged": d}
                      for r, (g, d) in zip(rows, got)]
    text = json.dumps(report, indent=1)
    atomic_write_text(Path(args.out), text + "\n")
    print(json.dumps({k: v for k, v in report.items() if k not in ("rows",)}, indent=1))


if __name__ == "__main__":
    main()
