"""``softcrawl report RUN``: write RUN/report/ (top designs with pictures, reward histogram
weighted by the design distribution, the best design's gait re-simulated with the policy, the
expert baseline at its best phase, with ``--groundtruth GT`` the regret against a ground truth,
Markdown summary; :mod:`softcrawl.codesign.report`)."""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.evaluation import GAIT_SAMPLES
    from softcrawl.codesign.report import BASELINE_PHASES, write_report

    if args.top < 1:
        raise ValueError(f"--top must be >= 1, got {args.top}")
    from softcrawl.robot.sweep import parse_phases

    phases = BASELINE_PHASES if args.phases is None else parse_phases(args.phases) if args.phases else ()
    extra = {}
    if args.groundtruth is not None:
        from functools import partial

        from softcrawl.codesign.groundtruth_regret import regret_section

        extra["regret"] = partial(regret_section, args.run, args.groundtruth, policy=not args.no_simulate)
    args.samples = GAIT_SAMPLES if args.samples is None else args.samples
    if args.samples < 0:
        raise ValueError(f"--samples must be >= 0, got {args.samples}")
    out = write_report(args.run, k=args.top, baseline=args.baseline, baseline_phases=phases,
                       simulate=not args.no_simulate, workers=args.workers, extra=extra, samples=args.samples)
    print((out / "summary.md").read_text(encoding="utf-8"))
    print(f"wrote {out}")
    return 0


def register(subparsers) -> None:
    """Add the ``report`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("report", help="report of a co-design training run",
                              description="Write RUN/report/: top designs (scores, pictures), the reward histogram "
                              "weighted by the design distribution with the best so far, the best design's gait "
                              "(trained policy, re-simulated), the expert baseline swept over phases with the run's "
                              "settings and re-simulated at its best phase, and summary.md.")
    p.add_argument("run", help="training run directory (softcrawl train --out)")
    p.add_argument("--top", type=int, default=5, help="number of top designs (default 5)")
    p.add_argument("--baseline", default=None, metavar="SWEEP",
                   help="a softcrawl sweep-phase output (directory or sweep.json) to compare with, instead of "
                   "sweeping the baseline here")
    p.add_argument("--phases", default=None,
                   help="phase lags of the baseline sweep, degrees: start:stop:step or a comma list (default "
                   "0:330:30); empty: no baseline")
    p.add_argument("--workers", type=int, default=None, help="processes of the baseline sweep (default: cores)")
    p.add_argument("--groundtruth", default=None, metavar="GT",
                   help="a softcrawl groundtruth folder: add where the run's chosen design ranks in it and its "
                   "regret (as softcrawl regret)")
    p.add_argument("--samples", type=int, default=None, metavar="K",
                   help="episodes sampled from the stochastic policy on the best design; its gait is the best of "
                   "them and the deterministic one (default 11: with it, as many candidate gaits as the baseline's "
                   "12 phase lags; 0: the deterministic one)")
    p.add_argument("--no-simulate", action="store_true",
                   help="only what the logs hold: no re-simulation of the best design, no baseline sweep")
    p.set_defaults(func=_run)
