"""``softcrawl designs``: inspect a body design space (count, list, show); ``--space NAME|FILE``
names a shipped space or reads one from a file (:func:`softcrawl.design.resolve.resolve_space`;
default the paper's)."""

from __future__ import annotations

import argparse
from collections import Counter

from softcrawl.cli import bounded
from softcrawl.design.picture import design_ascii, plot_design
from softcrawl.design.resolve import resolve_space
from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import MAX_RAW_DESIGNS, DesignSpace


def _fmt(d) -> str:
    return ",".join(map(str, d))


def _space(args: argparse.Namespace) -> DesignSpace:
    return resolve_space(args.space) if args.space else DEFAULT_SPACE


def _count(args: argparse.Namespace) -> int:
    space = _space(args)
    s = space.n_slots
    raw = Counter(s - d.count(0) for d in space.raw_designs)  # enumerated designs: already valid
    canon = Counter(s - d.count(0) for d in space.canonical_designs)
    if args.space:
        mirror = ", mirror about x" if space.mirror_x else ""
        print(f"space {space.name}: {s} slots, {space.n_regulators} regulators, {space.min_legs}..{space.max_legs} "
              f"legs{mirror} ({args.space}, sha256 {space.sha256[:12]})")
    print(f"raw designs:       {sum(raw.values())}")
    print(f"canonical designs: {sum(canon.values())}")
    print(f"{'legs':>4}  {'raw':>6}  {'canonical':>9}")
    for k in range(space.min_legs, space.max_legs + 1):
        print(f"{k:>4}  {raw[k]:>6}  {canon[k]:>9}")
    return 0


def _list(args: argparse.Namespace) -> int:
    space = _space(args)
    if args.legs is not None and not space.min_legs <= args.legs <= space.max_legs:
        raise ValueError(f"--legs must be in {space.min_legs}..{space.max_legs}, got {args.legs}")
    shown = 0
    for i, d in enumerate(space.canonical_designs):
        if args.limit is not None and shown >= args.limit:
            break
        if args.legs is None or space.n_slots - d.count(0) == args.legs:
            print(f"{i:5d}  {_fmt(d)}")
            shown += 1
    return 0


def _show(args: argparse.Namespace) -> int:
    space = _space(args)
    d = space.validate_design(args.design)
    c = space.canonicalize(d)
    print(f"design:     {_fmt(d)}")
    print(f"canonical:  {_fmt(c)}")
    print(f"index:      {space.design_index(c)}")
    print(f"legs:       {space.n_legs(d)}")
    for k, slots in space.regulator_groups(d).items():
        print(f"regulator {k}: slots {', '.join(map(str, slots))}")
    print(design_ascii(d, space))
    if args.png:
        plot_design(d, path=args.png, space=space)
        print(f"wrote {args.png}")
    return 0


def register(subparsers) -> None:
    """Add the ``designs`` subcommand (actions ``count``, ``list``, ``show``) to ``subparsers``."""
    p = subparsers.add_parser(
        "designs", help="inspect the body design space", description="Inspect the body design space: count, list, show."
    )
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--space", metavar="NAME|FILE", default=None,
                        help="design space: a shipped one (paper, hex6) or a file (TOML; default: the paper's space, "
                             "8 slots, 3 regulators, 3-6 legs)")
    actions = p.add_subparsers(dest="action", required=True)

    a = actions.add_parser("count", parents=[common], help="raw and canonical design counts per number of legs")
    a.set_defaults(func=_count)

    a = actions.add_parser("list", parents=[common], help="canonical designs with their indices")
    a.add_argument("--legs", type=int, default=None, **bounded(1, MAX_RAW_DESIGNS),
                   help="only designs with this many legs (within the space's)")
    a.add_argument("--limit", type=int, default=None, **bounded(0, MAX_RAW_DESIGNS), help="print at most N designs")
    a.set_defaults(func=_list)

    a = actions.add_parser("show", parents=[common],
                           help="canonical form, index, regulators and a picture of one design")
    a.add_argument("design", help='comma-separated slot values (0 or a regulator), e.g. "1,0,0,2,2,0,0,1"')
    a.add_argument("--png", metavar="FILE", default=None, help="also save a PNG drawing of the design")
    a.set_defaults(func=_show)
