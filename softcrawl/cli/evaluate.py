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

import numpy as np


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.evaluation import evaluate_policy
    from softcrawl.gaits import write_actions_csv
    from softcrawl.robot.output import check_output_path, write_results

    check_output_path(args.out, args.overwrite)
    if args.frames_every < 1:
        raise ValueError(f"--frames-every must be >= 1, got {args.frames_every}")
    ev = evaluate_policy(args.run, args.design, args.episodes)
    gait, robot = ev.gait(), ev.env.episode.robot
    result = ev.resimulate(record_every=args.frames_every, progress=not args.no_progress)
    out = write_results(args.out, robot, gait, result, ev.env.calibration, overwrite=args.overwrite)
    write_actions_csv(gait, out / "actions.csv")
    (out / "evaluation.json").write_text(json.dumps({
        "run": str(args.run), "checkpoint": ev.checkpoint, "design": list(ev.design),
        "episodes": args.episodes, "returns_cm": ev.returns_cm, "mean_return_cm": float(np.mean(ev.returns_cm)),
        "diverged": ev.diverged, "rerun_reward_cm": result.reward_cm,
        "hold_s": ev.config.env.steps_per_action * ev.config.env.dt,
        "actions_kpa": np.asarray(ev.actions_kpa).tolist(),
    }, indent=2) + "\n")
    print(f"design {','.join(map(str, ev.design))}: returns {', '.join(f'{r:+.3f}' for r in ev.returns_cm)} cm "
          f"(re-run {result.reward_cm:+.3f} cm); wrote {out}")
    return 1 if result.diverged or any(ev.diverged) else 0


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
