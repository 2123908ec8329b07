"""``softcrawl report RUN``: write RUN/report/ (top designs with pictures, reward histogram
weighted by the design distribution, Markdown summary; :mod:`softcrawl.codesign.report`)."""

from __future__ import annotations

import argparse


def _run(args: argparse.Namespace) -> int:
    from softcrawl.codesign.report import write_report

    if args.top < 1:
        raise ValueError(f"--top must be >= 1, got {args.top}")
    out = write_report(args.run, k=args.top, baseline=args.baseline)
    print((out / "summary.md").read_text(encoding="utf-8"))
    print(f"wrote {out}")
    return 0


def register(subparsers) -> None:
    """Add the ``report`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("report", help="report of a co-design training run",
                              description="Write RUN/report/: top designs (scores, pictures), the reward histogram "
                              "weighted by the design distribution with the best so far, and summary.md.")
    p.add_argument("run", help="training run directory (softcrawl train --out)")
    p.add_argument("--top", type=int, default=5, help="number of top designs (default 5)")
    p.add_argument("--baseline", default=None, metavar="SWEEP",
                   help="a softcrawl sweep-phase output (directory or sweep.json) to compare with")
    p.set_defaults(func=_run)
