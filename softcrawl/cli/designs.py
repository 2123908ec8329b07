"""``softcrawl designs``: inspect the body design space (count, list, show)."""

from __future__ import annotations

import argparse
from collections import Counter

from softcrawl.design import (
    MAX_LEGS,
    MIN_LEGS,
    N_SLOTS,
    canonical_designs,
    canonicalize,
    design_index,
    n_legs,
    raw_designs,
    regulator_groups,
    validate_design,
)
from softcrawl.design.picture import design_ascii, plot_design


def _fmt(d) -> str:
    return ",".join(map(str, d))


def _count(args: argparse.Namespace) -> int:
    raw = Counter(N_SLOTS - d.count(0) for d in raw_designs())  # enumerated designs: already valid
    canon = Counter(N_SLOTS - d.count(0) for d in canonical_designs())
    print(f"raw designs:       {sum(raw.values())}")
    print(f"canonical designs: {sum(canon.values())}")
    print(f"{'legs':>4}  {'raw':>6}  {'canonical':>9}")
    for k in range(MIN_LEGS, MAX_LEGS + 1):
        print(f"{k:>4}  {raw[k]:>6}  {canon[k]:>9}")
    return 0


def _list(args: argparse.Namespace) -> int:
    if args.legs is not None and not MIN_LEGS <= args.legs <= MAX_LEGS:
        raise ValueError(f"--legs must be in {MIN_LEGS}..{MAX_LEGS}, got {args.legs}")
    if args.limit is not None and args.limit < 0:
        raise ValueError(f"--limit must be >= 0, got {args.limit}")
    shown = 0
    for i, d in enumerate(canonical_designs()):
        if args.limit is not None and shown >= args.limit:
            break
        if args.legs is None or n_legs(d) == args.legs:
            print(f"{i:5d}  {_fmt(d)}")
            shown += 1
    return 0


def _show(args: argparse.Namespace) -> int:
    d = validate_design(args.design)
    c = canonicalize(d)
    print(f"design:     {_fmt(d)}")
    print(f"canonical:  {_fmt(c)}")
    print(f"index:      {design_index(c)}")
    print(f"legs:       {n_legs(d)}")
    for k, slots in regulator_groups(d).items():
        print(f"regulator {k}: slots {', '.join(map(str, slots))}")
    print(design_ascii(d))
    if args.png:
        plot_design(d, path=args.png)
        print(f"wrote {args.png}")
    return 0


def register(subparsers) -> None:
    """Add the ``designs`` subcommand (actions ``count``, ``list``, ``show``) to ``subparsers``."""
    p = subparsers.add_parser(
        "designs", help="inspect the body design space", description="Inspect the body design space: count, list, show."
    )
    actions = p.add_subparsers(dest="action", required=True)

    a = actions.add_parser("count", help="raw and canonical design counts per number of legs")
    a.set_defaults(func=_count)

    a = actions.add_parser("list", help="canonical designs with their indices")
    a.add_argument("--legs", type=int, default=None, help=f"only designs with this many legs ({MIN_LEGS}..{MAX_LEGS})")
    a.add_argument("--limit", type=int, default=None, help="print at most N designs")
    a.set_defaults(func=_list)

    a = actions.add_parser("show", help="canonical form, index, regulators and a picture of one design")
    a.add_argument("design", help='8 comma-separated slot values in {0..3}, e.g. "1,0,0,2,2,0,0,1"')
    a.add_argument("--png", metavar="FILE", default=None, help="also save a PNG drawing of the design")
    a.set_defaults(func=_show)
