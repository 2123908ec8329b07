"""``softcrawl report RUN``: write RUN/report/ (top designs with pictures, the run's shortlist,
the reward histogram weighted by the design distribution over training with its mode switches,
the paper's designs placed in the run, the run's design's gait re-simulated with the policy,
the expert baseline at its best phase, with ``--groundtruth GT`` the regret against a ground
truth and the paper's designs placed in it, Markdown summary; :mod:`softcrawl.codesign.report`).
The run is locked while the report is written: refused while the run trains or another report
writes it."""

from __future__ import annotations

import argparse

from softcrawl.cli import MAX_WORKERS, bounded

#: Most designs of the report's top table (``--top``; each gets a picture).
MAX_TOP = 1000


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.evaluation import GAIT_SAMPLES
    from softcrawl.codesign.report import BASELINE_PHASES, write_report
    from softcrawl.robot.sweep import parse_phases

    phases = BASELINE_PHASES if args.phases is None else parse_phases(args.phases) if args.phases else ()
    extra = {}
    if args.groundtruth is not None:
        from functools import partial

        from softcrawl.codesign.groundtruth_regret import regret_section

        extra["regret"] = partial(regret_section, args.run, args.groundtruth, policy=not args.no_simulate)
    args.samples = GAIT_SAMPLES if args.samples is None else args.samples
    out = write_report(args.run, k=args.top, baseline=args.baseline, baseline_phases=phases,
                       simulate=not args.no_simulate, workers=args.workers, extra=extra, samples=args.samples,
                       shortlist=args.shortlist, groundtruth=args.groundtruth)
    print((out / "summary.md").read_text(encoding="utf-8"))
    print(f"wrote {out}")
    return 0


def register(subparsers) -> None:
    """Add the ``report`` subcommand to ``subparsers``."""
    from softcrawl.codesign.evaluation import MAX_SAMPLES
    from softcrawl.codesign.shortlist import MAX_SHORTLIST

    p = subparsers.add_parser("report", help="report of a co-design training run",
                              description="Write RUN/report/: top designs (scores, pictures), the run's shortlist "
                              "(its most promising designs tried with the policy's gaits; the best is the run's "
                              "design), the reward histogram weighted by the design distribution over training with "
                              "the best so far and the mode switches, the paper's designs L1-L5 placed in the run, the "
                              "run's design's gait (trained policy, re-simulated), the expert baseline swept over "
                              "phases with the run's settings and re-simulated at its best phase, and summary.md.")
    p.add_argument("run", help="training run directory (softcrawl train --out)")
    p.add_argument("--top", type=int, default=5, **bounded(1, MAX_TOP), help="number of top designs (default 5)")
    p.add_argument("--baseline", default=None, metavar="SWEEP",
                   help="a softcrawl sweep-phase output (directory or sweep.json) to compare with, instead of "
                   "sweeping the baseline here")
    p.add_argument("--phases", default=None,
                   help="phase lags of the baseline sweep, degrees: start:stop:step or a comma list (default "
                   "0:330:30); empty: no baseline")
    p.add_argument("--workers", type=int, default=None, **bounded(1, MAX_WORKERS),
                   help="processes of the baseline sweep (default: cores) and of a shortlist made here "
                   "(default: the run's n_workers)")
    p.add_argument("--groundtruth", default=None, metavar="GT",
                   help="a softcrawl groundtruth folder: add where the run's chosen design ranks in it and its "
                   "regret (as softcrawl regret), and place the paper's designs in it")
    p.add_argument("--shortlist", type=int, default=None, metavar="K", **bounded(1, MAX_SHORTLIST),
                   help="compute the run's shortlist anew with K candidates and write it to the run (its design "
                   "may change; default: the run's own shortlist, computed with its `shortlist` setting if it has "
                   "none)")
    p.add_argument("--samples", type=int, default=None, metavar="K", **bounded(0, MAX_SAMPLES),
                   help="episodes sampled from the stochastic policy on the best design; its gait is the best of "
                   "them and the deterministic one (default 11: with it, as many candidate gaits as the baseline's "
                   f"12 phase lags; 0: the deterministic one; at most {MAX_SAMPLES})")
    p.add_argument("--no-simulate", action="store_true",
                   help="only what the logs hold: no re-simulation of the best design, no baseline sweep")
    p.set_defaults(func=_run)
