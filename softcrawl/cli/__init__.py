"""The ``softcrawl`` command line. Each subcommand lives in its own module with a
``register(subparsers)`` function that adds its parser and sets ``func``."""

from __future__ import annotations

import argparse
import importlib
import os
import sys

# One BLAS/OpenMP thread per process unless the user says otherwise: on small machines
# oversubscribed thread pools made dense and sparse solves 3-30x slower (measured); runs
# are parallelised with processes instead. Must happen before numpy is imported.
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from softcrawl import __version__

#: Subcommand modules, in the order they appear in ``softcrawl --help``.
SUBCOMMANDS = ("softcrawl.cli.verify", "softcrawl.cli.designs", "softcrawl.cli.simulate", "softcrawl.cli.sweep",
               "softcrawl.cli.reduce", "softcrawl.cli.train", "softcrawl.cli.evaluate", "softcrawl.cli.report",
               "softcrawl.cli.rig", "softcrawl.cli.deploy", "softcrawl.cli.calibrate", "softcrawl.cli.compare")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="softcrawl", description="Soft crawling robots: FEM simulation, reduction and co-design."
    )
    parser.add_argument("--version", action="version", version=f"softcrawl {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in SUBCOMMANDS:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError) as exc:  # user errors: one clear line, no traceback
        print(f"softcrawl {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
