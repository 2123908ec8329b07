"""``softcrawl evaluate RUN --design D``: re-simulate a design with the trained policy
(deterministic actions) and write the outputs of ``softcrawl simulate`` plus
``evaluation.json`` (returns of all episodes, cm; the hold per action ``hold_s``) and
``actions.csv`` (real kPa, one row per action; ``softcrawl simulate --actions`` replays it with
1 s holds, i.e. faithfully only for runs with 1 s actions such as the ``paper`` preset).

The episodes run in :class:`softcrawl.envs.CrawlerEnv` with the run's settings; the written
trajectory is a re-run of the first episode's actions as a
:class:`softcrawl.gaits.ActionSequence` through :func:`softcrawl.robot.run_episode` (same
physics; its reward is reported next to the env's).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np


def _hold(dt: float, steps: int, n_actions: int) -> float:
    """Hold time (s) for an ActionSequence so that step k gets action k // steps exactly
    (floor(k dt / hold) can round the wrong way at some boundaries; nudge hold down then)."""
    for hold in (dt * steps, dt * steps * (1 - 1e-9)):
        if all(math.floor(k * dt / hold) == k // steps for k in range(steps * n_actions)):
            return hold
    raise ValueError("cannot represent the action timing as an ActionSequence")  # pragma: no cover


def evaluate(run: str | Path, design, episodes: int = 1, checkpoint: str | Path | None = None) -> dict:
    """Roll out the trained policy on ``design`` for ``episodes`` episodes.

    ``design`` is canonicalised first (regulators relabelled by first appearance; the policy
    only saw canonical designs), so regulator k of the outputs is the canonical k.

    Returns a dict: ``design`` (canonical), ``returns_cm`` (list), ``actions_kpa`` ``(n_actions, 3)`` of the
    first episode, ``diverged`` (list), ``env`` (the CrawlerEnv, its robot cached), ``config``.
    """
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.config import TrainConfig
    from softcrawl.codesign.sac import make_sac
    from softcrawl.codesign.training import env_fn, latest_checkpoint
    from softcrawl.design.space import canonicalize
    from softcrawl.envs import action_to_kpa

    run = Path(run)
    if not (run / "config.json").exists():
        raise ValueError(f"{run} is not a training run (no config.json)")
    if episodes < 1:
        raise ValueError(f"--episodes must be >= 1, got {episodes}")
    design = canonicalize(design)  # the policy was trained on canonical designs
    cfg = TrainConfig.from_dict(json.loads((run / "config.json").read_text())["config"])
    ck = Path(checkpoint) if checkpoint is not None else latest_checkpoint(run)
    if ck is None or not (ck / "model.pt").exists():
        raise ValueError(f"no checkpoint found in {run}")
    env = env_fn(cfg)()
    cfg.sac.buffer_size = 1
    model = make_sac(DummyVecEnv([lambda: env]), cfg.sac)
    model.policy.load_state_dict(torch.load(ck / "model.pt", weights_only=False)["policy"])
    returns, diverged, first = [], [], None
    for _ in range(episodes):
        obs, _ = env.reset(options={"design": design})
        total, acts, done, info = 0.0, [], False, {}
        while not done:
            a, _ = model.predict(obs, deterministic=True)
            obs, r, term, trunc, info = env.step(a)
            total += r
            acts.append(action_to_kpa(a))
            done = term or trunc
        returns.append(total)
        diverged.append(bool(info.get("diverged")))
        first = first if first is not None else np.array(acts)
    return {"design": design, "returns_cm": returns, "actions_kpa": first, "diverged": diverged, "env": env,
            "config": cfg, "checkpoint": str(ck)}


def _run(args: argparse.Namespace) -> int:
    from softcrawl.gaits import ActionSequence, write_actions_csv
    from softcrawl.robot.episode import run_episode
    from softcrawl.robot.output import check_output_path, write_results

    check_output_path(args.out, args.overwrite)
    ev = evaluate(args.run, args.design, args.episodes)
    env, cfg = ev["env"], ev["config"]
    hold = _hold(cfg.env.dt, cfg.env.steps_per_action, len(ev["actions_kpa"]))
    gait = ActionSequence(ev["actions_kpa"], hold=hold)
    robot = env.episode.robot
    result = run_episode(robot, gait, len(gait) * cfg.env.steps_per_action * cfg.env.dt, env.calibration,
                         settle_steps=cfg.env.settle_steps, record_every=args.frames_every,
                         progress=not args.no_progress)
    out = write_results(args.out, robot, gait, result, env.calibration, overwrite=args.overwrite)
    write_actions_csv(gait, out / "actions.csv")
    (out / "evaluation.json").write_text(json.dumps({
        "run": str(args.run), "checkpoint": ev["checkpoint"], "design": list(ev["design"]),
        "episodes": args.episodes, "returns_cm": ev["returns_cm"], "mean_return_cm": float(np.mean(ev["returns_cm"])),
        "diverged": ev["diverged"], "rerun_reward_cm": result.reward_cm,
        "hold_s": cfg.env.steps_per_action * cfg.env.dt,
        "actions_kpa": np.asarray(ev["actions_kpa"]).tolist(),
    }, indent=2) + "\n")
    print(f"design {','.join(map(str, ev['design']))}: returns {', '.join(f'{r:+.3f}' for r in ev['returns_cm'])} cm "
          f"(re-run {result.reward_cm:+.3f} cm); wrote {out}")
    return 1 if result.diverged or any(ev["diverged"]) else 0


def register(subparsers) -> None:
    """Add the ``evaluate`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("evaluate", help="re-simulate a design with a trained policy",
                              description="Run the trained policy (deterministic) on a design with the run's "
                              "simulation settings; write the outputs of `softcrawl simulate` plus evaluation.json "
                              "and actions.csv into --out.")
    p.add_argument("run", help="training run directory")
    p.add_argument("--design", required=True, help='8 comma-separated slot values, e.g. "1,0,0,2,2,0,0,0"')
    p.add_argument("--episodes", type=int, default=1, help="episodes to run (default 1)")
    p.add_argument("--out", required=True, help="output directory (must not exist unless --overwrite)")
    p.add_argument("--frames-every", type=int, default=10, metavar="K", help="ParaView frame every K steps")
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run)
