"""``softcrawl groundtruth --out GT``: every design of a set with its best open-loop gait
(:mod:`softcrawl.codesign.groundtruth`), in parallel and resumable: re-running the same command
(or ``--resume``) continues a killed run and never recomputes a finished design. Writes
``results.jsonl`` (per design, as they finish), ``groundtruth.csv``, ``ranked.png``,
``references.json``, ``summary.json`` and ``summary.md``. ``config.json`` records the settings and the design set:
``--resume`` (and the same command without ``--designs``) continues exactly that set, and refuses
setting options and another ``--designs``. ``--engine jax`` searches ``--in-flight`` designs at
once in lockstep, each round of all of them in one batched call (``--designs all``: the
space's every canonical design, 6,972 in the paper's). Every setting is checked, and the reduction file
loaded, before anything is written; ``--out`` must be new, empty or a ground truth, and is locked
while the run writes it (a second run on it is refused, naming the holder)."""

from __future__ import annotations

import argparse
import math

from softcrawl.cli import MAX_WORKERS, SEED_BOUNDS, bounded
from softcrawl.cli.train import check_ray_address
from softcrawl.codesign.config import MAX_EPISODE_S, MAX_HOLD_S, SIM_BOUNDS
from softcrawl.codesign.groundtruth.config import MAX_EVALS, MAX_FINALISTS, MAX_IN_FLIGHT, MAX_JAX_BATCH, SEED_KINDS
from softcrawl.fem.solver import RID_DTYPES
from softcrawl.tasks.registry import task_spec


def _floats(text: str, what: str) -> tuple[float, ...]:
    try:
        values = tuple(float(v) for v in text.replace(" ", "").split(",") if v)
    except ValueError:
        values = None
    if values is None or not all(map(math.isfinite, values)):
        raise ValueError(f"{what} must be comma-separated numbers, got {text!r}")
    return values


def _phases(text: str) -> tuple[float, ...]:
    """``--baseline-phases``: none, or :func:`softcrawl.robot.sweep.parse_phases`'s forms."""
    if text.strip().lower() in ("none", ""):
        return ()
    from softcrawl.robot.sweep import parse_phases

    try:
        return parse_phases(text)
    except ValueError as exc:
        raise ValueError(f"--baseline-phases: {exc}") from None


#: The options that set a :class:`~softcrawl.codesign.groundtruth.GroundTruthConfig` setting
#: (their ``args`` names): the saved ones of a folder, so ``--resume`` takes none of them.
SETTINGS = ("space", "task", "duration", "screen_duration", "hold", "cycles", "evals_per_cycle", "finalists", "seed",
            "seeds", "leg_mesh_size", "disk_mesh_size", "dt", "reduction", "rid_dtype", "baseline_phases", "engine",
            "jax_batch")


def _config(args: argparse.Namespace):
    """The :class:`GroundTruthConfig` of the options (a default for each one not given), validated."""
    from softcrawl.codesign.groundtruth import GroundTruthConfig, gt_robot

    default = GroundTruthConfig()

    def given(name, value):
        return getattr(default, name) if value is None else value

    screen = default.screen_duration
    if args.screen_duration is not None:
        screen = None
        if args.screen_duration.strip().lower() != "none":
            screen = _floats(args.screen_duration, "--screen-duration")
            if len(screen) != 1:
                raise ValueError(f"--screen-duration must be a number of seconds or none, got {args.screen_duration!r}")
            screen = screen[0]
    cycles = default.cycles
    if args.cycles is not None:
        cycles = _floats(args.cycles, "--cycles")
        if any(c != int(c) for c in cycles):
            raise ValueError(f"--cycles must be integers, got {args.cycles!r}")
        cycles = tuple(int(c) for c in cycles)
    return GroundTruthConfig(
        duration=given("duration", args.duration), screen_duration=screen, hold=given("hold", args.hold),
        cycles=cycles, evals_per_cycle=given("evals_per_cycle", args.evals_per_cycle),
        finalists=given("finalists", args.finalists), seed=given("seed", args.seed), seeds=given("seeds", args.seeds),
        robot=gt_robot(leg_mesh_size=args.leg_mesh_size, disk_mesh_size=args.disk_mesh_size, reduction=args.reduction,
                       rid_dtype=args.rid_dtype, dt=args.dt),
        baseline_phases=default.baseline_phases if args.baseline_phases is None else _phases(args.baseline_phases),
        engine=given("engine", args.engine), jax_batch=given("jax_batch", args.jax_batch),
        space=args.space or default.space,
        task=task_spec(args.task, "--task") if args.task is not None else default.task).validate()


def _run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from softcrawl.codesign.groundtruth import EXECUTORS, check_folder, parse_designs, run_groundtruth
    from softcrawl.codesign.groundtruth.store import folder_space

    if args.executor not in EXECUTORS:
        raise ValueError(f"--executor must be one of {EXECUTORS}")
    if args.resume:
        given = [f"--{name.replace('_', '-')}" for name in SETTINGS if getattr(args, name) is not None]
        if given:
            raise ValueError(f"--resume continues with the folder's saved settings (its config.json, space.toml) and "
                             f"design set; drop {', '.join(given)}")
        check_folder(args.out)
        if not (Path(args.out) / "config.json").exists():
            raise ValueError(f"--resume: {args.out} is not a ground-truth folder (no config.json)")
        cfg = None
        space = folder_space(args.out)
    else:
        cfg = _config(args)
        space = cfg.design_space()
        check_folder(args.out)
    existing = (Path(args.out) / "config.json").exists()
    # no --designs: the folder's recorded set (resumed, or the same command again), "3" for a new one
    spec = args.designs if args.designs is not None else None if existing else "3"
    designs = None if spec is None else parse_designs(spec, space)
    check_ray_address(args.executor, args.ray_address)
    s = run_groundtruth(designs, args.out, cfg, workers=args.workers, executor=args.executor,
                        progress=not args.no_progress, ray_address=args.ray_address, in_flight=args.in_flight)
    best = s["best"][0] if s["best"] else None
    u = s.get("task", {}).get("unit", "cm")  # the summary's rewards are in its task's unit
    print(f"{s['designs']} of {s['requested']} designs done; best {','.join(map(str, best['design']))} "
          f"{best[f'reward_{u}']:+.2f} {u} ({best['gait']})" if best else "no design finished")
    for key, name in (("paper_l1", "paper L1"), ("expert_design", "expert design")):
        if s.get(key):
            print(f"{name}: rank {s[key]['rank']} of {s['designs']} ({s[key][f'reward_{u}']:+.2f} {u})")
    if "expert_baseline" in s["references"]:
        b = s["references"]["expert_baseline"]
        print(f"expert baseline (sine, {b['best_phase_deg']:.0f} deg): {b['reward_cm']:+.2f} cm; "
              f"{s.get('designs_beating_expert_baseline', 0)} designs beat it")
    if "turning_baseline" in s["references"]:
        b = s["references"]["turning_baseline"]
        print(f"turning baseline ({b['best_phase_deg']:.0f} deg lag): {b['reward_deg']:+.2f} deg; "
              f"{s.get('designs_beating_turning_baseline', 0)} designs beat it")
    if len(s["by_legs"]) > 1:
        print("best per leg count: " + "; ".join(
            f"{legs} legs {','.join(map(str, g['best']['design']))} {g['best'][f'reward_{u}']:+.2f} {u} "
            f"(rank {g['best']['rank']})" for legs, g in s["by_legs"].items()))
    if s["bad_rows"]:
        print(f"{len(s['bad_rows'])} bad rows of {args.out}/results.jsonl left in place and not used "
              f"(summary.json lists them); first: {s['bad_rows'][0]}")
    print(f"wrote {args.out}/groundtruth.csv, ranked.png, summary.json, summary.md")
    return 0


def register(subparsers) -> None:
    """Add the ``groundtruth`` subcommand to ``subparsers``."""
    p = subparsers.add_parser(
        "groundtruth", help="best open-loop gait of every design (ground truth of the design space)",
        description="Optimize a periodic open-loop gait per design with CMA-ES on the reduced model and rank "
        "the designs. Resumable: run the same command again (or with --resume) to continue.")
    p.add_argument("--out", required=True, help="ground-truth folder (created, or continued)")
    p.add_argument("--designs", default=None, help='"3" (the 280 three-legged designs, the default of a new folder; an '
                   'existing one: the set it records), leg counts like "3,4", "all" (6,972), or designs separated by '
                   '";" e.g. "1,0,0,2,2,0,0,0;1,0,0,2,2,0,0,1"; with --resume only the folder\'s own set')
    p.add_argument("--resume", action="store_true",
                   help="continue with the folder's saved settings and design set (no setting options)")
    p.add_argument("--space", default=None, metavar="NAME|PATH",
                   help="design space: a shipped one (paper, the default; hex6) or a space file (TOML); the folder "
                        "keeps a copy as space.toml (the expert-baseline references are the paper space's only)")
    p.add_argument("--task", default=None, metavar="NAME|TABLE",
                   help="what the gait search maximises (docs/tasks.md): forward (the default, the paper's), heading, "
                        "turning, target or incline, or a JSON table of its settings, e.g. "
                        "'{\"name\": \"heading\", \"heading_deg\": 90}'; rewards are in the task's unit "
                        "(cm, or deg for turning); references: the forward task's, or turning's hand-made baseline "
                        "(--baseline-phases its lags)")
    p.add_argument("--workers", type=int, default=None, **bounded(1, MAX_WORKERS),
                   help="processes (or Ray CPUs); default: all cores")
    p.add_argument("--executor", default="process", help="process (default), serial or ray")
    p.add_argument("--ray-address", default=None, help="existing Ray cluster (default: start a local Ray)")
    p.add_argument("--duration", type=float, default=None, **bounded(0.0, MAX_EPISODE_S, "s", open_low=True),
                   help="full episode, s (default 20)")
    p.add_argument("--screen-duration", default=None, help="search episode, s, or none (default 6)")
    p.add_argument("--hold", type=float, default=None, **bounded(0.0, MAX_HOLD_S, "s", open_low=True),
                   help="seconds per action / knot (default 1)")
    p.add_argument("--cycles", default=None, help="distinct pattern lengths searched (default 2,3,4,5)")
    p.add_argument("--evals-per-cycle", type=int, default=None, **bounded(1, MAX_EVALS),
                   help="CMA-ES episodes per cycle length (default 36)")
    p.add_argument("--finalists", type=int, default=None, **bounded(1, MAX_FINALISTS),
                   help="candidates re-run at full length (default 2)")
    p.add_argument("--seed", type=int, default=None, **bounded(*SEED_BOUNDS), help="CMA-ES seed (default 0)")
    p.add_argument("--seeds", default=None, choices=SEED_KINDS,
                   help="the search's starting gaits: duty (default: the CMA-ES runs from the structured seeds, "
                   "and the bang-bang duty cycles screened beside them) or structured (the runs alone, as config "
                   "formats before 9)")
    p.add_argument("--leg-mesh-size", type=float, default=None, **bounded(*SIM_BOUNDS["leg_mesh_size"]),
                   help="mm (the reduction's; default 6)")
    p.add_argument("--disk-mesh-size", type=float, default=None, **bounded(*SIM_BOUNDS["disk_mesh_size"]),
                   help="mm (10: paper preset, the default; 25: demo)")
    p.add_argument("--dt", type=float, default=None, **bounded(*SIM_BOUNDS["dt"]),
                   help="time step, s (default: the robot's default)")
    p.add_argument("--reduction", default=None, help="reduction file (default: shipped)")
    p.add_argument("--rid-dtype", choices=RID_DTYPES, default=None,
                   help="precision of the reduced legs' RID products (default float32, validated)")
    p.add_argument("--baseline-phases", default=None,
                   help="expert-baseline lags swept, START:STOP:STEP or a list, degrees, or none (default 0:180:10)")
    p.add_argument("--engine", choices=("cpu", "jax"), default=None,
                   help="cpu (default: one design per worker) or jax (every design's episode of a search round "
                        "in one batch on JAX's default device, CPU or GPU; --rid-dtype is its precision)")
    p.add_argument("--jax-batch", type=int, default=None, **bounded(1, MAX_JAX_BATCH),
                   help="largest JAX batch, a power of two (default 1024; halved, with a warning, where the "
                        "device runs out of memory)")
    p.add_argument("--in-flight", type=int, default=None, **bounded(1, MAX_IN_FLIGHT),
                   help="--engine jax: designs searched at once, each round of all of them in one call (default "
                        "jax-batch / 16; memory grows with it); not saved, a resumed run may change it")
    p.add_argument("--no-progress", action="store_true")
    p.set_defaults(func=_run)
