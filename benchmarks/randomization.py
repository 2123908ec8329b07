"""Domain randomization and the reduced model's accuracy (issue 19, item 6). Prints JSON.

The reduction (POD basis + ECSW weights of the leg) was built at the nominal Young's moduli and
masses; a randomized robot keeps that basis and those weights and only re-forms its element data
(:func:`softcrawl.robot.domain.randomized_robot`). For each Young's modulus scale (and mass
scale) the same design and gait run on the reduced model and on the exact full-order model
(``refactor_every=1``) with the same scale, each from its own settled rest state, and are
compared as ``softcrawl reduce validate`` does (:mod:`softcrawl.reduction.validate`): mean node
error (L2 distance per node, averaged over all nodes and recorded frames, mm), mean deformation
error (each body rigidly fitted first, mm), and the reward (+x of the disk top centre, cm) of
both and its error (over the frames both runs reached: a run that diverges stops at its last
valid state). Also the cost of randomizing the robot per episode at the ``demo`` preset
(build + settle against one 20-action episode).

    OMP_NUM_THREADS=1 python benchmarks/randomization.py [--duration 4] [--scales 0.7,1.0,1.3]
        [--mass-scales 0.8,1.2] [--workers 1]
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from softcrawl.parallel import run_pool

DESIGN = (1, 0, 0, 2, 2, 0, 0, 1)  # the expert baseline design
PHASE_DEG = 110.0  # its sine gait as in the "baseline" validation scene (softcrawl.reduction.scenes)


def run_case(model: str, youngs: float, mass: float, duration: float, dt: float, record_every: int,
             leg_mesh: float, disk_mesh: float) -> dict:
    """One episode of the sine gait (phase lag ``PHASE_DEG``) on ``DESIGN`` with Young's moduli x ``youngs`` and masses x
    ``mass``; returns its reward, timing and recorded frames (float32, every ``record_every`` steps)."""
    from softcrawl.gaits import SineGait
    from softcrawl.robot import RobotConfig, Settling, build_robot, run_episode
    from softcrawl.robot.domain import DomainSample

    cfg = RobotConfig(model=model, leg_mesh_size=leg_mesh, disk_mesh_size=disk_mesh, dt=dt,
                      refactor_every=1 if model == "full" else None)
    nominal = build_robot(DESIGN, cfg)
    t = time.perf_counter()
    robot = DomainSample(youngs_scale=youngs, mass_scale=mass).apply(nominal)
    build = time.perf_counter() - t
    res = run_episode(robot, SineGait(phase_deg=PHASE_DEG), duration, settling=Settling(), record_every=record_every, progress=False)
    return {"model": model, "youngs_scale": youngs, "mass_scale": mass, "reward_cm": res.reward_cm,
            "diverged": res.diverged, "reason": res.reason, "steps": res.steps, "settle_steps": res.settled.get("settle_steps"),
            "wall_seconds": res.wall_seconds, "randomize_seconds": build, "frames": res.frames,
            "reward_node": robot.reward_node,
            "bodies": [(robot.model.body_slice(i).start, robot.model.body_slice(i).stop)
                       for i in range(len(robot.model.bodies))]}


def compare(rom: dict, fom: dict) -> dict:
    from softcrawl.reduction.validate import deformation_error

    a, b = rom["frames"].astype(float), fom["frames"].astype(float)
    k = min(len(a), len(b))
    a, b = a[:k], b[:k]
    err = np.linalg.norm(a - b, axis=2)
    deform = deformation_error(a, b, [slice(*s) for s in rom["bodies"]])
    node = rom["reward_node"]
    # rewards over the common frames (a diverged run's frames stop at its last valid state)
    r_rom, r_fom = ((x[-1, node, 0] - x[0, node, 0]) / 10.0 for x in (a, b))
    return {"youngs_scale": rom["youngs_scale"], "mass_scale": rom["mass_scale"], "frames": k,
            "mean_node_error_mm": float(err.mean()), "max_node_error_mm": float(err.max()),
            "mean_deformation_error_mm": float(deform.mean()), "mean_trajectory_error_mm": float(err[:, node].mean()),
            "reward_full_cm": float(r_fom), "reward_reduced_cm": float(r_rom),
            "reward_error_cm": float(abs(r_rom - r_fom)),
            "reward_error_rel": float(abs(r_rom - r_fom) / max(abs(r_fom), 1e-12)),
            "episode_reward_full_cm": fom["reward_cm"], "episode_reward_reduced_cm": rom["reward_cm"],
            "settle_steps_full": fom["settle_steps"], "settle_steps_reduced": rom["settle_steps"],
            "wall_seconds_full": fom["wall_seconds"], "wall_seconds_reduced": rom["wall_seconds"],
            "steps_full": fom["steps"], "steps_reduced": rom["steps"],
            "diverged_full": fom["reason"] or False, "diverged_reduced": rom["reason"] or False}


def episode_cost(repeats: int = 3) -> dict:
    """Per-episode cost of a physical draw at the ``demo`` preset (reduced, 0.02 s, 25 mm disk, 20
    actions of 50 steps) on the paper's best design: randomized robot build and its settling
    against the episode's stepping."""
    from softcrawl.codesign.config import preset
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.robot import Episode, settle
    from softcrawl.robot.domain import DomainSample

    cfg = preset("demo")
    robot = robot_factory(cfg)((1, 0, 0, 2, 2, 0, 0, 0))
    settled = settle(robot, cfg.env.settling())
    build, settling, steps = [], [], []
    for k in range(repeats):
        t = time.perf_counter()
        r = DomainSample(youngs_scale=0.9 + 0.1 * k, mass_scale=1.05, friction=1.0).apply(robot)
        build.append(time.perf_counter() - t)
        t = time.perf_counter()
        s = settle(r, cfg.env.settling())
        settling.append((time.perf_counter() - t, s.steps))
    ep = Episode(robot, settled=settled)
    ep.reset()
    t = time.perf_counter()
    rng = np.random.default_rng(0)
    for _ in range(cfg.env.n_actions):
        cmd = rng.uniform(0, 90, 3)
        for _ in range(cfg.env.steps_per_action):
            ep.step(cmd)
    steps.append(time.perf_counter() - t)
    episode = float(np.median(steps))
    return {"preset": "demo", "build_seconds": float(np.median(build)),
            "settle_seconds": float(np.median([s for s, _ in settling])),
            "settle_steps": [n for _, n in settling], "episode_seconds": episode,
            "overhead_fraction": float((np.median(build) + np.median([s for s, _ in settling])) / episode)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=4.0, help="episode length, s (default 4)")
    ap.add_argument("--dt", type=float, default=0.01)
    ap.add_argument("--record-every", type=int, default=10, help="frames every K steps (default 10)")
    ap.add_argument("--scales", default="0.7,0.85,0.9,0.95,1.0,1.3,1.5", help="Young's modulus scales")
    ap.add_argument("--mass-scales", default="0.8,1.2", help="mass scales (at Young's scale 1)")
    ap.add_argument("--leg-mesh", type=float, default=6.0)
    ap.add_argument("--disk-mesh", type=float, default=10.0)
    ap.add_argument("--workers", type=int, default=1)
    ap.add_argument("--no-cost", action="store_true", help="skip the per-episode cost measurement")
    args = ap.parse_args()
    cases = [(float(s), 1.0) for s in args.scales.split(",") if s] + \
            [(1.0, float(m)) for m in args.mass_scales.split(",") if m]
    jobs = [(model, e, m, args.duration, args.dt, args.record_every, args.leg_mesh, args.disk_mesh)
            for e, m in cases for model in ("full", "reduced")]
    out: dict = {}
    t0 = time.perf_counter()
    run_pool(run_case, args.workers, jobs, lambda r: out.__setitem__((r["model"], r["youngs_scale"], r["mass_scale"]), r))
    rows = [compare(out[("reduced", e, m)], out[("full", e, m)]) for e, m in cases]
    result = {
        "design": ",".join(map(str, DESIGN)), "gait": f"sine (period 4 s, phase {PHASE_DEG:g} deg)", "duration_s": args.duration,
        "dt_s": args.dt, "leg_mesh_mm": args.leg_mesh, "disk_mesh_mm": args.disk_mesh,
        "reference": "full-order exact (refactor_every=1), same scales", "cases": rows,
        "wall_seconds": time.perf_counter() - t0, "machine": platform.platform(), "python": platform.python_version(),
    }
    if not args.no_cost:
        result["episode_cost"] = episode_cost()
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
