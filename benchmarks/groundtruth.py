"""Ground-truth measurements: screening rank agreement, the cost of one design, and the
rate of a whole-space run on the JAX engine.

``python benchmarks/groundtruth.py screening --designs 8 --gaits 5 --out screening.json``:
random step gaits on a random sample of three-legged designs (plus the paper's L1), each run
with short episodes and the full 20 s; prints the Spearman rank correlations (all pairs, best per
design, within designs) and the wall seconds per duration (1 process).

``python benchmarks/groundtruth.py cost --design 1,0,0,2,2,0,0,0``: one design's ground truth
with the default :class:`GroundTruthConfig` (or ``--evals-per-cycle``), prints its episodes,
simulated seconds and wall seconds, and the projection for N designs on W cores.

``python benchmarks/groundtruth.py rate --designs 8 [--max-seconds S]``: the command
``softcrawl groundtruth --engine jax --designs all`` with its default settings, on a sample of
the space's designs (each leg count its share of ``all``, at least one each; seeded), to its end
or, with ``--max-seconds``, to the first call after S seconds. Reports the wall time split into
JAX compilation, engine and host (CMA-ES, bookkeeping) seconds, the engine's simulated seconds
per second without compilation, and the projection for the whole space:
``N x (T / r + E h) + compile``, where one design's search is ``E`` episodes of ``T`` simulated
seconds in all (148 and 944 s by default: 4 x 36 screening episodes of 6 s, 2 x 2 finals of
20 s), ``r`` the measured simulated seconds per engine second and ``h`` the host seconds per
episode. ``r`` counts the padding of the sample's batches (each leg count's group padded to a power of
two; ``hours_unpadded`` leaves it out, as a full run's large groups nearly do), and grows with
the batch on a GPU: sample at least ``--in-flight`` designs (and pass the full run's
``--jax-batch`` / ``--in-flight``) so that the calls are as large as the full run's.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections import Counter

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

from softcrawl.codesign.groundtruth import (  # noqa: E402
    GroundTruthConfig,
    gt_robot,
    optimize_design,
    parse_designs,
    run_groundtruth,
    screening_agreement,
)
from softcrawl.design.space import DEFAULT_SPACE, PAPER_BEST_DESIGN  # noqa: E402


def sample_designs(n: int, seed: int = 0, space=DEFAULT_SPACE) -> list[tuple[int, ...]]:
    """``n`` of the canonical designs of ``space``, each leg count its share of them (largest
    remainder, at least one each), drawn without replacement by a seeded generator, in leg-count
    order.

    Raises:
        ValueError: ``n`` below the number of leg counts or above the number of designs.
    """
    groups: dict[int, list] = {}
    for d in parse_designs("all", space):
        groups.setdefault(sum(v > 0 for v in d), []).append(d)
    total = sum(map(len, groups.values()))
    if not len(groups) <= n <= total:
        raise ValueError(f"--designs must be in {len(groups)}..{total}, got {n}")
    quota = {k: n * len(g) / total for k, g in groups.items()}
    take = {k: max(1, int(q)) for k, q in quota.items()}
    while sum(take.values()) != n:  # hand out (or take back) one at a time by the remainders
        more = sum(take.values()) < n
        k = (max if more else min)((k for k in take if more or take[k] > 1), key=lambda k: quota[k] - take[k])
        take[k] += 1 if more else -1
    rng = np.random.default_rng(seed)
    return [groups[k][i] for k in sorted(groups) for i in sorted(rng.choice(len(groups[k]), take[k], replace=False))]


class _TimeUp(Exception):
    """``rate --max-seconds`` ran out: the run stops before its next call."""


def rate(a) -> dict:
    """The ``rate`` measurement (module docstring) as a dict."""
    import tempfile
    import time

    import jax

    from softcrawl.codesign.groundtruth import load_results
    from softcrawl.codesign.groundtruth.runner import jax_evaluator

    designs = sample_designs(a.designs, a.seed)
    cfg = GroundTruthConfig(engine="jax", baseline_phases=(), **({"jax_batch": a.jax_batch} if a.jax_batch else {}))
    times = {"compile": 0.0, "engine": 0.0, "calls": 0}

    def compiled(event, duration, **_):
        if event.startswith("/jax/core/compile/"):
            times["compile"] += duration

    jax.monitoring.register_event_duration_secs_listener(compiled)
    engine = jax_evaluator(cfg)
    t0, cpu0 = time.perf_counter(), time.process_time()

    def evaluate_many(requests):
        if a.max_seconds and time.perf_counter() - t0 > a.max_seconds:
            raise _TimeUp
        t = time.perf_counter()
        replies = engine.evaluate(requests)
        times["engine"] += time.perf_counter() - t
        times["calls"] += 1
        return replies

    out = a.out or tempfile.mkdtemp(prefix="gt-rate-")
    try:
        run_groundtruth(designs, out, cfg, refs=False, evaluate_many=evaluate_many, in_flight=a.in_flight)
        complete = True
    except _TimeUp:
        complete = False
    wall, cpu = time.perf_counter() - t0, time.process_time() - cpu0
    finished = len(load_results(out))
    # one design's work under these settings: its episodes and simulated seconds (at most 2 finals each)
    screen = cfg.screen_duration if cfg.screen_duration is not None and cfg.screen_duration < cfg.duration else None
    search = len(cfg.cycles) * cfg.evals_per_cycle
    finals = cfg.finalists * (2 if screen else 1)
    design_episodes, design_sim = search + finals, search * (screen or cfg.duration) + finals * cfg.duration
    warm = times["engine"] - times["compile"]
    sim_rate = engine.sim_seconds / warm if warm > 0 else float("nan")  # simulated s per engine s
    step_rate = engine.robot_steps / warm if warm > 0 else float("nan")  # padding included
    host_per_episode = (wall - times["engine"]) / max(engine.episodes, 1)
    design_s = design_sim / sim_rate + design_episodes * host_per_episode
    total = len(DEFAULT_SPACE.canonical_designs)
    return {"device": f"{jax.default_backend()}: {jax.devices()[0].device_kind}", "cpu_cores": os.cpu_count(),
            "folder": str(out), "designs": len(designs), "finished": finished, "complete": complete,
            "legs": {str(k): n for k, n in sorted(Counter(sum(v > 0 for v in d) for d in designs).items())},
            "jax_batch": cfg.jax_batch, "in_flight": a.in_flight, "calls": times["calls"],
            "wall_s": wall, "process_cpu_s": cpu, "compile_s": times["compile"], "engine_s": times["engine"],
            "host_s": wall - times["engine"], "episodes": engine.episodes, "sim_seconds": engine.sim_seconds,
            "robot_steps": engine.robot_steps, "padding": engine.robot_steps * cfg.robot.dt / max(engine.sim_seconds,
                                                                                                   1e-9),
            "sim_seconds_per_engine_second": sim_rate, "robot_steps_per_engine_second": step_rate,
            "host_s_per_episode": host_per_episode,
            "design": {"episodes": design_episodes, "sim_seconds": design_sim, "seconds": design_s},
            "designs_per_hour": 3600 * finished / wall if complete else None,
            "projected_designs_per_hour": 3600 / design_s,
            "projection": {"designs": total, "hours": (total * design_s + times["compile"]) / 3600,
                           # the same without this sample's padding (a full run's groups are large)
                           "hours_unpadded": (total * (design_sim / (step_rate * cfg.robot.dt)
                                                       + design_episodes * host_per_episode)
                                              + times["compile"]) / 3600}}


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
    r = sub.add_parser("rate")
    r.add_argument("--designs", type=int, default=8, help="sampled designs of the paper space's 'all'")
    r.add_argument("--jax-batch", type=int, default=None, help="as softcrawl groundtruth's (default its default)")
    r.add_argument("--in-flight", type=int, default=None, help="as softcrawl groundtruth's (default its default)")
    r.add_argument("--max-seconds", type=float, default=None,
                   help="stop before the first call after this long and project from the calls made")
    r.add_argument("--seed", type=int, default=0, help="the sample's seed")
    r.add_argument("--out", default=None, help="the sample's ground-truth folder (default a temporary one)")
    r.add_argument("--json", default=None, help="also write the numbers here")
    a = p.parse_args(argv)
    if a.cmd == "rate":
        res = rate(a)
        if a.json:
            with open(a.json, "w") as f:
                json.dump(res, f, indent=2)
        print(json.dumps(res, indent=2))
    elif a.cmd == "screening":
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
