"""``softcrawl simulate``: run one full-order episode of a design and gait, write the results.

Example::

    softcrawl simulate --design 1,0,0,2,2,0,0,1 --gait sine --phase 110 --duration 20 --out runs/baseline
    softcrawl simulate --space hex6 --design 1,0,2,1,0,2 --task turning --out runs/hex6

``--space`` (a shipped name or a space file, :func:`softcrawl.design.resolve.resolve_space`)
gives the design's slots and regulators and the robot's parts (:func:`softcrawl.codesign.config.space_robot`);
``--task`` (a name of :data:`softcrawl.tasks.TASKS` or a JSON table, :func:`softcrawl.tasks.registry.task_spec`) the floor (:func:`softcrawl.tasks.base.on_floor`) and,
for a task other than ``forward``, its return in its unit, summed over the recorded frames
(:func:`softcrawl.tasks.base.replay_return`), printed and written to ``task.json``
(``{"task": settings, "unit": "cm" | "deg", "return_<unit>": float, "frames_every": K}``).
A task scored at rest (``turning``: :attr:`softcrawl.tasks.Task.vent_seconds`) has the episode
go on that long after ``--duration`` with every regulator vented, and its outputs show it.
The floor's friction is ``--friction`` or the task's ``friction`` (both given: refused); a
floor the robot cannot stand still on is refused (:meth:`softcrawl.tasks.Task.check_floor`),
and a robot still moving when its settling ends is a warning line
(:func:`softcrawl.robot.episode.unsettled_warning`).

Inputs are validated (space, design, gait, action file of the space's regulators, output path,
and with ``--video`` that pyvista can render off-screen) before the model is built;
outputs appear at ``--out`` only when complete (:mod:`softcrawl.robot.output`). A diverged
simulation is written (flagged ``"diverged": true``, ``reward_cm`` null) and exits with 1.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from softcrawl.cli import bounded
from softcrawl.codesign.config import SIM_BOUNDS
from softcrawl.design.resolve import PAPER_SPACE, resolve_space
from softcrawl.design.space import BASELINE_DESIGN, DEFAULT_SPACE
from softcrawl.design.spacefile import InvalidDesignError
from softcrawl.gaits import paper_best_gait, read_actions_csv
from softcrawl.robot.actuation import PressureCalibration
from softcrawl.robot.animation import FPS, MAX_FRAMES
from softcrawl.robot.assembly import MODELS, REDUCED_DISKS, RobotConfig, build_robot
from softcrawl.robot.episode import run_episode, unsettled_warning
from softcrawl.robot.output import check_output_path, write_results
from softcrawl.robot.sweep import baseline_gait
from softcrawl.tasks.base import FRICTION_BOUNDS
from softcrawl.tasks.registry import DEFAULT_TASK, parse_task, task_spec

GAITS = ("sine", "paper-best")
#: Longest episode ``simulate`` and ``sweep-phase`` accept, s (1 h of robot time; the paper's are 20 s).
MAX_DURATION_S = 3600.0
#: ParaView frames every this many steps by default (``--frames-every``), and its bound.
FRAMES_EVERY, MAX_FRAMES_EVERY = 10, 10**7
#: Bound of ``--refactor-every`` (steps), as the training config's ``env.robot.refactor_every``.
MAX_REFACTOR_EVERY = 10**6


def add_robot_arguments(p: argparse.ArgumentParser) -> None:
    """``--duration``, ``--mesh-size`` and ``--refactor-every`` (shared with ``sweep-phase``),
    each bounded (:func:`softcrawl.cli.bounded`)."""
    p.add_argument("--duration", type=float, default=20.0, **bounded(0.0, MAX_DURATION_S, "s", open_low=True),
                   help=f"episode length, s (default 20, at most {MAX_DURATION_S:g})")
    p.add_argument("--mesh-size", type=float, default=RobotConfig.leg_mesh_size, **bounded(*SIM_BOUNDS["leg_mesh_size"]),
                   help=f"leg mesh size, mm (default {RobotConfig.leg_mesh_size:g})")
    p.add_argument("--refactor-every", type=int, default=RobotConfig.refactor_every, **bounded(1, MAX_REFACTOR_EVERY),
                   help="reuse each full-order body's factorization for this many steps (1 = exact; 5 is about "
                        "1.7x faster and lags the contact compliance; default: 1 for the full model, "
                        "5 for the reduced model's corotational disk)")


def _gait(args: argparse.Namespace, n_regulators: int):
    """The gait named by the arguments (``--actions`` overrides ``--gait``) for a space of
    ``n_regulators`` regulators (ValueError: an actions file of another width, or
    ``--gait paper-best``, a 3-regulator gait, on another space)."""
    if args.actions is not None:
        return read_actions_csv(args.actions, n_regulators=n_regulators)
    if args.gait == "sine":
        return baseline_gait(args.phase, n_regulators)
    if n_regulators != DEFAULT_SPACE.n_regulators:
        raise ValueError(f"--gait paper-best drives the paper's {DEFAULT_SPACE.n_regulators} regulators; this space "
                         f"has {n_regulators}: use --gait sine or --actions")
    return paper_best_gait(n_actions=max(1, math.ceil(args.duration)))


def space_design(space, design: str | None):
    """``design`` validated in ``space`` (:meth:`DesignSpace.validate_design`); None: the
    paper's baseline design in the paper's space, else ValueError (the space has no default).

    Raises:
        InvalidDesignError, ValueError: one line naming the space.
    """
    if design is None:
        if space != DEFAULT_SPACE:
            raise ValueError(f"give --design: {space.n_slots} comma-separated slot values in 0..{space.n_regulators} "
                             f"for the design space {space.name!r} (the default design is the paper's)")
        design = ",".join(map(str, BASELINE_DESIGN))
    try:
        return space.validate_design(design)
    except InvalidDesignError as exc:
        raise InvalidDesignError(f"{exc} (design space {space.name!r})") from None


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.config import space_robot
    from softcrawl.tasks.base import on_floor, scored_gait

    space = resolve_space(args.space)
    task = parse_task(task_spec(args.task, "--task"))
    if args.friction is not None and task.friction is not None:
        raise ValueError(f"--friction {args.friction:g} and the task's friction {task.friction:g} both set the floor's "
                         "friction; give one")
    design = space_design(space, args.design)
    friction = RobotConfig.friction if args.friction is None else args.friction
    config = space_robot(RobotConfig(leg_mesh_size=args.mesh_size, disk_mesh_size=args.disk_mesh_size,
                                     friction=friction, dt=args.dt, refactor_every=args.refactor_every,
                                     **model_fields(args)), space)
    try:
        task.check_floor(config.friction)
    except ValueError as exc:
        raise ValueError(f"--task: {exc}") from None
    gait = _gait(args, space.n_regulators)
    check_output_path(args.out, args.overwrite)
    if args.video:
        from softcrawl.robot.video import check_video_support  # optional extra

        check_video_support()
    robot = on_floor(build_robot(design, config, space=space), task.friction, task.gravity())
    calibration = PressureCalibration()
    gait, seconds = scored_gait(gait, args.duration, task.vent_seconds)  # turning: vented, scored at rest
    result = run_episode(robot, gait, seconds, calibration, record_every=args.frames_every,
                         progress=not args.no_progress)
    extra, what = None, ""
    if task.name != DEFAULT_TASK:  # the task's return, from the recorded frames
        from softcrawl.tasks.base import replay_return

        u, ret = task.unit, replay_return(task, robot, result.frames)
        record = json.dumps({"task": task.settings(), "unit": u, f"return_{u}": ret if math.isfinite(ret) else None,
                             "frames_every": args.frames_every}, indent=2) + "\n"
        what = f"task {task.label()}: return {ret:+.3f} {u} (from frames every {args.frames_every} steps); "

        def extra(folder):
            (folder / "task.json").write_text(record, encoding="utf-8")

    out = write_results(args.out, robot, gait, result, calibration, overwrite=args.overwrite, video=args.video,
                        animation=args.animation is not False, extra=extra)
    warning = unsettled_warning(result.settled)
    if warning:
        print(f"softcrawl simulate: warning: design {','.join(map(str, design))} {warning}", file=sys.stderr)
    print(f"{what}reward {result.reward_cm:+.3f} cm after {result.sim_seconds:g} s "
          f"({result.steps} steps, {result.wall_seconds:.1f} s wall, {result.real_time_factor:.3f}x real time); "
          f"wrote {out}")
    if result.diverged:
        print(f"softcrawl simulate: error: {result.reason} (outputs flagged as diverged)", file=sys.stderr)
        return 1
    return 0


def add_model_arguments(p: argparse.ArgumentParser) -> None:
    """``--model``, ``--reduction`` and ``--reduced-disk`` (shared with ``sweep-phase``;
    :func:`model_fields` reads them)."""
    p.add_argument("--model", choices=MODELS, default="reduced",
                   help="reduced: legs reduced by POD + ECSW (the shipped 6 mm reduction, fast); "
                        "full: full-order FEM (default reduced)")
    p.add_argument("--reduction", metavar="FILE.npz", default=None,
                   help="reduction file for --model reduced (default: the one shipped with softcrawl)")
    p.add_argument("--reduced-disk", choices=REDUCED_DISKS, default=RobotConfig.reduced_disk,
                   help="disk of --model reduced when the reduction has none: floating (one floating frame, "
                        "default) or corotational (full-order)")


def model_fields(args: argparse.Namespace) -> dict:
    """The :class:`RobotConfig` fields set by :func:`add_model_arguments` (ValueError for
    ``--reduction`` with ``--model full``, which would ignore it)."""
    if args.reduction is not None and args.model != "reduced":
        raise ValueError(f"--reduction is used only by --model reduced, not --model {args.model}")
    if args.reduction is not None and not Path(args.reduction).is_file():
        what = "is a directory" if Path(args.reduction).is_dir() else "does not exist"
        raise ValueError(f"--reduction {args.reduction} {what}; give a reduction .npz file")
    return {"model": args.model, "reduction": args.reduction, "reduced_disk": args.reduced_disk}


def add_animation_argument(p: argparse.ArgumentParser) -> None:
    """``--animation`` / ``--no-animation`` (shared with ``evaluate``): write ``crawl.gif``
    (:func:`softcrawl.robot.animation.write_animation`); ``args.animation`` is None when neither
    is given (the default: write it), so a command that writes no trajectory can refuse them."""
    p.add_argument("--animation", action=argparse.BooleanOptionalAction, default=None,
                   help=f"write crawl.gif, the robot crawling: up to {MAX_FRAMES} of the recorded frames at {FPS:g} "
                        "frames per second, drawn with matplotlib (default; --no-animation skips it)")


def add_space_argument(p: argparse.ArgumentParser) -> None:
    """``--space NAME|PATH`` (shared with ``sweep-phase``), read by :func:`resolve_space`."""
    p.add_argument("--space", default=PAPER_SPACE, metavar="NAME|PATH",
                   help="design space: a shipped name (paper, hex6) or a space file (default paper)")


def register(subparsers) -> None:
    """Add the ``simulate`` subcommand to ``subparsers``."""
    p = subparsers.add_parser(
        "simulate", help="simulate one episode of a design and gait (reduced or full-order FEM)",
        description="Simulate one episode of a crawler design with an open-loop gait and write summary.json, "
        "trajectory.{npz,csv,png}, a ParaView series (crawl.pvd + frames/), the animation crawl.gif and, with "
        "--video, crawl.mp4 into --out.",
    )
    add_space_argument(p)
    p.add_argument("--task", default=DEFAULT_TASK, metavar="NAME|TABLE",
                   help="what the episode is scored on (docs/tasks.md; default forward): a task's name, or a JSON "
                   "table of its settings, e.g. '{\"name\": \"incline\", \"angle_deg\": 5}'; sets the floor "
                   "and reports the task's return (turning: after the robot vents for its vent_s, at rest)")
    p.add_argument("--design", default=None,
                   help="comma-separated slot values, one per slot of the space, 0 or a regulator (default, paper's "
                   'space only: the baseline "1,0,0,2,2,0,0,1")')
    p.add_argument("--gait", choices=GAITS, default="sine",
                   help="sine: the expert baseline (45 - 45 cos(2 pi t / 4 s), rear lags by --phase; regulators 3..R "
                   "off on a space of R != 3); paper-best: the paper's learned 3 s cycle (3 regulators)")
    p.add_argument("--phase", type=float, default=110.0, **bounded(-360.0, 360.0, "deg"),
                   help="sine gait: lag of regulator 2, degrees (default 110)")
    p.add_argument("--actions", metavar="FILE.csv", default=None,
                   help="action sequence p1,...,pR, one column per regulator of the space (real kPa, one row per "
                   "1 s); overrides --gait")
    p.add_argument("--out", required=True, help="output directory (must not exist unless --overwrite)")
    add_model_arguments(p)
    add_robot_arguments(p)
    p.add_argument("--disk-mesh-size", type=float, default=RobotConfig.disk_mesh_size,
                   **bounded(*SIM_BOUNDS["disk_mesh_size"]),
                   help=f"disk mesh size, mm (default {RobotConfig.disk_mesh_size:g}; the demo preset uses 25)")
    p.add_argument("--friction", type=float, default=None, **bounded(*FRICTION_BOUNDS),
                   help=f"floor friction coefficient (default {RobotConfig.friction:g}, or the task's friction; not "
                        "both)")
    p.add_argument("--dt", type=float, default=RobotConfig.dt, **bounded(*SIM_BOUNDS["dt"]),
                   help=f"time step, s (default {RobotConfig.dt:g})")
    p.add_argument("--frames-every", type=int, default=FRAMES_EVERY, metavar="K", **bounded(1, MAX_FRAMES_EVERY),
                   help=f"write a ParaView frame every K steps (default {FRAMES_EVERY})")
    add_animation_argument(p)
    p.add_argument("--video", action="store_true",
                   help="also render crawl.mp4 off-screen (one frame per --frames-every steps, 25 fps; "
                        "needs: pip install softcrawl[video])")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)
