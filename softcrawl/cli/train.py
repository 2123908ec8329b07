"""``softcrawl train``: co-design of body and gait with SAC and the Gibbs design distribution.

Examples::

    softcrawl train --preset smoke --out runs/smoke
    softcrawl train --preset demo --out runs/demo
    softcrawl train --preset paper --out runs/paper --set sac.batch_size=256 --set env.legs=[3,4]
    softcrawl train --resume --out runs/paper          # continue a killed run

Writes the run folder described in :mod:`softcrawl.codesign.training` and, at the end, its
report (:mod:`softcrawl.codesign.report`).
"""

from __future__ import annotations

import argparse
import os
import sys

from softcrawl.codesign.config import BACKENDS, PRESETS, override, preset


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.training import train  # heavy: torch, stable-baselines3

    if args.resume:
        if args.set or args.total_steps or args.n_envs or args.backend or args.workers is not None or args.seed is not None:
            raise ValueError("--resume uses the run's saved config.json; drop the other settings")
        res = train(args.out, resume=True, progress=not args.no_progress)
    else:
        sets = list(args.set or [])
        for flag, key in ((args.total_steps, "total_steps"), (args.n_envs, "n_envs"), (args.backend, "backend"),
                          (args.workers, "n_workers"), (args.seed, "seed")):
            if flag is not None:
                sets.append(f"{key}={flag}" if key != "backend" else f'backend="{flag}"')
        cfg = override(preset(args.preset), sets)
        res = train(args.out, cfg, progress=not args.no_progress)
    print(f"trained {res.steps} steps ({res.updates} SAC updates) in {res.wall_seconds:.1f} s; run in {res.run_dir}")
    report = res.run_dir / "report" / "summary.md"
    if report.exists():
        print(report.read_text(encoding="utf-8"))
        print(f"report: {report}")
    return 0


def register(subparsers) -> None:
    """Add the ``train`` subcommand to ``subparsers``."""
    p = subparsers.add_parser(
        "train", help="co-design: train SAC and the design distribution",
        description="Train the design-conditioned open-loop policy (SAC) and the Gibbs design distribution "
        "(codesign.md). Presets: paper (96 envs, 1M steps), demo (~15 min on 2 cores), smoke (CI, < 1 min).",
    )
    p.add_argument("--preset", choices=PRESETS, default="demo", help="settings to start from (default demo)")
    p.add_argument("--out", required=True, help="run directory (new, or the run to --resume)")
    p.add_argument("--resume", action="store_true", help="continue the run in --out from its last checkpoint")
    p.add_argument("--total-steps", type=int, default=None, help="environment transitions in total")
    p.add_argument("--n-envs", type=int, default=None, help="parallel environments")
    p.add_argument("--backend", choices=BACKENDS, default=None, help="where envs run")
    p.add_argument("--workers", type=int, default=None, help="worker processes of the subprocess backend (0: cores)")
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override any setting, e.g. sac.batch_size=256, env.legs=[3], design.untried=\"zero\"")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


def main(argv: list[str] | None = None) -> int:
    """Standalone entry (``python -m softcrawl.cli.train``), for use before the subcommand is registered."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    parser = argparse.ArgumentParser(prog="softcrawl")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["train", *(sys.argv[1:] if argv is None else argv)])
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:
        print(f"softcrawl train: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
