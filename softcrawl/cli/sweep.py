"""``softcrawl sweep-phase``: the expert baseline's tuning, one sine-gait episode per phase lag.

Example::

    softcrawl sweep-phase --out runs/sweep --phases 0:180:10 --duration 20 --workers 2
    softcrawl sweep-phase --space hex6 --design 1,0,2,1,0,2 --out runs/hex6-sweep

``--space`` (a shipped name or a space file) gives the design's slots and regulators and the
robot's parts; the gait is :func:`softcrawl.robot.sweep.baseline_gait` of its regulators.

Writes ``sweep.json``, ``sweep.csv`` and ``reward_vs_phase.png`` into ``--out`` (atomically, see
:mod:`softcrawl.robot.sweep`) and prints the reward table. An interrupted sweep is resumed by
running the same command again. Exits with 1 if every episode diverged.
"""

from __future__ import annotations

import argparse
import sys

from softcrawl.cli import MAX_WORKERS, bounded
from softcrawl.cli.simulate import add_model_arguments, add_robot_arguments, add_space_argument, model_fields, space_design
from softcrawl.design.resolve import resolve_space
from softcrawl.robot.assembly import RobotConfig
from softcrawl.robot.sweep import format_table, parse_phases, run_sweep


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.config import space_robot

    space = resolve_space(args.space)
    design = space_design(space, args.design)
    fields = model_fields(args)
    config = space_robot(RobotConfig(leg_mesh_size=args.mesh_size, refactor_every=args.refactor_every, **fields),
                         space)
    try:
        result = run_sweep(args.out, parse_phases(args.phases), design, config, args.duration, workers=args.workers,
                           overwrite=args.overwrite, progress=not args.no_progress, space=space)
    except KeyboardInterrupt:
        print(f"softcrawl sweep-phase: interrupted; finished phases are kept in {args.out}.partial "
              "(run the same command again to resume)", file=sys.stderr)
        return 130
    print(format_table(result))
    reused = sum(r.reused for r in result.phases)
    print(f"{len(result.phases)} episodes ({reused} reused) in {result.wall_seconds:.1f} s wall "
          f"on {result.workers} worker(s); wrote {args.out}")
    return 0 if result.best is not None else 1


def register(subparsers) -> None:
    """Add the ``sweep-phase`` subcommand to ``subparsers``."""
    p = subparsers.add_parser(
        "sweep-phase", help="sweep the phase lag of the baseline sine gait (one episode per phase)",
        description="Run one episode (reduced or full-order model, --model) of the sine gait per phase lag of the rear regulator, in "
        "parallel worker processes, and write sweep.json, sweep.csv and reward_vs_phase.png into --out. "
        "Finished phases are kept in <out>.partial/ until the sweep completes; re-running the same command "
        "resumes an interrupted sweep.",
    )
    p.add_argument("--out", required=True, help="output directory (must not exist unless --overwrite)")
    p.add_argument("--phases", default="0:180:10",
                   help="phase lags, degrees: start:stop:step (stop included) or a comma list (default 0:180:10)")
    add_space_argument(p)
    p.add_argument("--design", default=None,
                   help="comma-separated slot values, one per slot of the space, 0 or a regulator (default, paper's "
                   'space only: the baseline "1,0,0,2,2,0,0,1")')
    add_model_arguments(p)
    add_robot_arguments(p)
    p.add_argument("--workers", type=int, default=None, **bounded(1, MAX_WORKERS),
                   help="worker processes, one BLAS thread each (default: number of CPUs; 1 = in this process)")
    p.add_argument("--overwrite", action="store_true", help="replace --out if it exists")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)
