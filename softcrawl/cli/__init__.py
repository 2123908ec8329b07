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
               "softcrawl.cli.groundtruth", "softcrawl.cli.regret",
               "softcrawl.cli.rig", "softcrawl.cli.deploy", "softcrawl.cli.calibrate", "softcrawl.cli.compare")


class _Parser(argparse.ArgumentParser):
    """Usage errors as one line (``softcrawl CMD: error: ...``), exit code 2."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="softcrawl", description="Soft crawling robots: FEM simulation, reduction and co-design."
    )
    parser.add_argument("--version", action="version", version=f"softcrawl {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    for name in SUBCOMMANDS:
        importlib.import_module(name).register(sub)
    return parser


def run_command(args: argparse.Namespace) -> int:
    """Run a parsed subcommand: user errors (ValueError, OSError such as a missing file, a full
    disk or a read-only folder) are one line on stderr and exit code 2, Ctrl-C is a one-line
    note naming ``--out`` (where partial results are) and exit code 130; never a traceback."""
    try:
        return int(args.func(args) or 0)
    except (ValueError, OSError) as exc:  # user errors: one clear line, no traceback
        msg = " ".join(str(exc).split()) or type(exc).__name__
        print(f"softcrawl {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        out = getattr(args, "out", None)
        where = f"; partial results, if any, are in {out}" if out else ""
        hint = f" (continue with: softcrawl train --resume --out {out})" if args.command == "train" and out else ""
        print(f"softcrawl {args.command}: interrupted{where}{hint}", file=sys.stderr)
        return 130


def main(argv: list[str] | None = None) -> int:
    return run_command(build_parser().parse_args(argv))


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
