"""``softcrawl evaluate RUN [--design D]``: re-simulate a design (default: the run's design,
:func:`softcrawl.codesign.shortlist.run_design`) with the trained policy's gait
(the best of its deterministic actions and ``--samples`` episodes sampled from it,
:attr:`softcrawl.codesign.evaluation.PolicyEvaluation.chosen`) and write the outputs of
``softcrawl simulate`` plus ``evaluation.json`` (the run's task and its unit, returns of the
deterministic episodes in that unit: ``returns_cm`` or ``returns_deg``; the sampled ones,
``sampled_cm``; which is the gait, ``gait_source``, and its return; the hold per action
``hold_s``; ``settled``, how its robot came to rest, with a warning line when it did not,
:func:`softcrawl.robot.episode.unsettled_warning`) and
``actions.csv`` (real kPa, one row per action; ``softcrawl simulate --actions`` replays it with
1 s holds, i.e. faithfully only for runs with 1 s actions such as the ``paper`` preset).

The episodes run in :class:`softcrawl.envs.CrawlerEnv` with the run's settings; the written
trajectory is a re-run of the gait's actions as a
:class:`softcrawl.gaits.ActionSequence` through :func:`softcrawl.robot.run_episode` (same
physics; its reward is reported next to the env's).

``--out`` is locked while it is written (:func:`softcrawl.cli.output_lock`): a second command
writing the same folder is refused at once.

``--randomize N`` instead runs N domain-randomized episodes (ranges: the run's
``env.randomize``, or ``--set env.randomize...``; env RNG seeded with ``--seed``) plus one
nominal episode and writes the reward distribution: ``randomization.json`` (mean, std, min,
max, quartiles, every draw), ``randomization.csv`` and the histogram ``randomization.png``
(:mod:`softcrawl.codesign.randomization`); no trajectory is re-simulated.
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from softcrawl.cli import SEED_BOUNDS, bounded, output_lock
from softcrawl.cli.simulate import FRAMES_EVERY, MAX_FRAMES_EVERY, add_animation_argument


def _randomize_ranges(run, sets):
    """The run's ``env.randomize`` after ``--set`` overrides (only ``env.randomize...`` keys).

    Raises:
        ValueError: another key, or a setting :func:`softcrawl.codesign.config.override` refuses.
    """
    from softcrawl.codesign.config import override
    from softcrawl.codesign.evaluation import load_run_config

    for a in sets:
        key = a.split("=", 1)[0].strip()
        if key != "env.randomize" and not key.startswith("env.randomize."):
            raise ValueError(f"--set {a!r}: evaluate only takes env.randomize settings (the rest is the run's)")
    return override(load_run_config(run), list(sets)).env.randomize


def _design(args: argparse.Namespace):
    """``--design``, or the run's design (its shortlist's choice; without one the most probable,
    :func:`softcrawl.codesign.shortlist.run_design`), said in one line."""
    if args.design is not None:
        return args.design
    from softcrawl.codesign.shortlist import run_design

    d = run_design(args.run)
    print(f"softcrawl evaluate: design {','.join(map(str, d['design']))}: the run's design "
          f"({'the best gait of its shortlist' if d['source'] == 'shortlist' else 'the most probable'})",
          file=sys.stderr)
    return d["design"]


def _run_randomized(args: argparse.Namespace) -> int:
    from softcrawl.codesign.randomization import evaluate_randomized, write_randomized
    from softcrawl.robot.output import check_output_path

    check_output_path(args.out, args.overwrite)
    if args.episodes is not None:
        raise ValueError("give --episodes or --randomize N, not both")
    if args.animation is not None:
        raise ValueError("--randomize N writes no trajectory to animate; drop --animation / --no-animation")
    if args.frames_every is not None:
        raise ValueError("--randomize N writes no trajectory; drop --frames-every")
    ranges = _randomize_ranges(args.run, args.set or [])
    with output_lock(args.out):
        res = evaluate_randomized(args.run, _design(args), args.randomize, ranges, seed=args.seed or 0)
        out = write_randomized(args.out, res, overwrite=args.overwrite)
    st, u = res.stats(), res.unit
    print(f"design {','.join(map(str, res.design))}: {st['n']} randomized episodes, return {st[f'mean_{u}']:+.3f} "
          f"+/- {st[f'std_{u}']:.3f} {u} (min {st[f'min_{u}']:+.3f}, max {st[f'max_{u}']:+.3f}; nominal "
          f"{res.nominal_return_cm:+.3f} {u}; {st['n_diverged']} diverged); wrote {out}")
    return 1 if st["n_diverged"] or res.nominal_diverged else 0


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.evaluation import GAIT_SAMPLES
    from softcrawl.robot.output import check_output_path

    if args.randomize is not None:
        if args.samples is not None:
            raise ValueError("--samples goes without --randomize")
        return _run_randomized(args)
    if args.set:
        raise ValueError("--set env.randomize... needs --randomize N")
    if args.seed is not None:
        raise ValueError("--seed seeds the draws of --randomize N; it goes with it")
    args.episodes = 1 if args.episodes is None else args.episodes
    args.frames_every = FRAMES_EVERY if args.frames_every is None else args.frames_every
    check_output_path(args.out, args.overwrite)
    args.samples = GAIT_SAMPLES if args.samples is None else args.samples
    with output_lock(args.out):
        return _evaluate(args)


def _evaluate(args: argparse.Namespace) -> int:
    """``evaluate`` without ``--randomize``, its settings checked and its ``--out`` locked."""
    from softcrawl.codesign.evaluation import evaluate_policy
    from softcrawl.gaits import write_actions_csv
    from softcrawl.robot.episode import unsettled_warning
    from softcrawl.robot.output import write_results

    ev = evaluate_policy(args.run, _design(args), args.episodes, samples=args.samples)
    gait, robot = ev.gait(), ev.env.episode.robot
    result = ev.resimulate(record_every=args.frames_every, progress=not args.no_progress)
    task, u = ev.task, ev.unit
    forward = task.name == "forward"
    if not forward:  # the task's return of the re-run, from its frames
        from softcrawl.tasks.base import replay_return

        rerun = replay_return(task, robot, result.frames)

    def extra(folder):  # written into the staged output: kept (or rescued) with it on a full disk
        write_actions_csv(gait, folder / "actions.csv")
        (folder / "evaluation.json").write_text(json.dumps({
            "run": str(args.run), "checkpoint": ev.checkpoint, "design": list(ev.design),
            "task": task.settings(), "unit": u,
            "episodes": args.episodes, f"returns_{u}": ev.returns_cm, f"mean_return_{u}": float(np.mean(ev.returns_cm)),
            "diverged": ev.diverged, f"sampled_{u}": ev.sampled_returns, "sampled_diverged": ev.sampled_diverged,
            "gait_source": ev.gait_source, f"gait_{u}": ev.gait_return,
            "rerun_reward_cm": result.reward_cm, **({} if forward else {f"rerun_{u}": rerun}),
            "hold_s": ev.config.env.steps_per_action * ev.config.env.robot.dt,
            "actions_kpa": np.asarray(ev.gait_actions_kpa).tolist(), "settled": result.settled,
        }, indent=2) + "\n")

    out = write_results(args.out, robot, gait, result, ev.env.calibration, overwrite=args.overwrite, extra=extra,
                        animation=args.animation is not False)
    warning = unsettled_warning(result.settled)
    if warning:
        print(f"softcrawl evaluate: warning: design {','.join(map(str, ev.design))} {warning}", file=sys.stderr)
    what = "" if forward else f" (task {task.label()}; re-run from its frames every {args.frames_every} steps)"
    sampled = f"; {len(ev.sampled_returns)} sampled, best {max(ev.sampled_returns):+.3f} {u}" if ev.sampled_returns else ""
    print(f"design {','.join(map(str, ev.design))}: deterministic returns "
          f"{', '.join(f'{r:+.3f}' for r in ev.returns_cm)} {u}{sampled}; gait ({ev.gait_source}) "
          f"{ev.gait_return:+.3f} {u}{what} (re-run {result.reward_cm if forward else rerun:+.3f} {u}); wrote {out}")
    return 1 if result.diverged or any(ev.diverged) else 0


def register(subparsers) -> None:
    """Add the ``evaluate`` subcommand to ``subparsers``."""
    from softcrawl.codesign.evaluation import MAX_EPISODES, MAX_SAMPLES

    p = subparsers.add_parser("evaluate", help="re-simulate a design with a trained policy",
                              description="Run the trained policy on a design with the run's simulation "
                              "settings (deterministic, then --samples episodes sampled from it; the gait is the best "
                              "of them); write the gait's `softcrawl simulate` outputs plus evaluation.json and "
                              "actions.csv into --out.")
    p.add_argument("run", help="training run directory")
    p.add_argument("--design", default=None, help="comma-separated slot values, one per slot of the run's design "
                   'space (the paper\'s: 8), e.g. "1,0,0,2,2,0,0,0" (default: the run\'s design, the best gait of '
                   "its final shortlist; a run without one: its most probable design)")
    p.add_argument("--episodes", type=int, default=None, **bounded(1, MAX_EPISODES),
                   help=f"deterministic episodes to run (default 1, at most {MAX_EPISODES})")
    p.add_argument("--samples", type=int, default=None, metavar="K", **bounded(0, MAX_SAMPLES),
                   help="then K episodes sampled from the stochastic policy; the written gait is the best of them "
                   "and the first deterministic one, as the report's (default 11; 0: the deterministic one; at most "
                   f"{MAX_SAMPLES})")
    p.add_argument("--randomize", type=int, default=None, metavar="N", **bounded(1, MAX_EPISODES),
                   help="run N domain-randomized episodes (the run's env.randomize ranges or --set ones) and write "
                   "the reward distribution (randomization.json/.csv/.png) instead of a trajectory")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="with --randomize: ranges, e.g. env.randomize=rig, env.randomize.friction=[0.8,1.6]")
    p.add_argument("--seed", type=int, default=None, **bounded(*SEED_BOUNDS),
                   help="with --randomize: seed of the draws (default 0)")
    p.add_argument("--out", required=True, help="output directory (must not exist unless --overwrite)")
    p.add_argument("--frames-every", type=int, default=None, metavar="K", **bounded(1, MAX_FRAMES_EVERY),
                   help=f"ParaView frame every K steps (default {FRAMES_EVERY})")
    add_animation_argument(p)
    p.add_argument("--overwrite", action="store_true")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run)
