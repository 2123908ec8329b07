"""``softcrawl regret RUN --groundtruth GT``: where a co-design run's chosen design ranks in a
ground truth (``softcrawl groundtruth``): true rank and percentile, regret in cm, and the learned
policy's reward next to the ground-truth gait's (:mod:`softcrawl.codesign.groundtruth_regret`)."""

from __future__ import annotations

import argparse
import json


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.groundtruth_regret import compute_regret, regret_markdown
    from softcrawl.safeio import atomic_write_text

    r = compute_regret(args.run, args.groundtruth, policy=not args.no_policy)
    print("\n".join(regret_markdown(r)))
    if args.json:
        atomic_write_text(args.json, json.dumps(r, indent=2, allow_nan=False) + "\n")
    return 0


def register(subparsers) -> None:
    """Add the ``regret`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("regret", help="rank and regret of a run's chosen design in a ground truth",
                              description="Place a training run's chosen design (the best gait of its final "
                              "shortlist; a run without one: the most probable in its final design distribution) in "
                              "a ground truth: rank, percentile, regret (cm), and the learned policy's reward next to "
                              "the ground-truth gait's.")
    p.add_argument("run", help="training run directory")
    p.add_argument("--groundtruth", required=True, metavar="GT", help="ground-truth folder (softcrawl groundtruth)")
    p.add_argument("--no-policy", action="store_true", help="skip the learned policy's episode")
    p.add_argument("--json", metavar="PATH", help="also write the numbers as JSON")
    p.set_defaults(func=_run)
