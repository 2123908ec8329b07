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


#: Most worker processes a command starts (``--workers``; the training config's ``n_workers``
#: has the same bound).
MAX_WORKERS = 1024
#: Bounds of a random seed (numpy's legacy seeding, which SB3 uses, takes 0..2**32 - 1).
SEED_BOUNDS = (0, 2**32 - 1)


def _number(v) -> str:
    return str(v) if isinstance(v, int) else f"{v:g}"


class _Bounded(argparse.Action):
    """Stores an option's value (after its ``type``) if it lies within its bounds, else a usage
    error naming the option (:func:`bounded`)."""

    def __init__(self, option_strings, dest, bounds=None, **kwargs):
        self.low, self.high, self.unit, self.open_low = bounds
        super().__init__(option_strings, dest, **kwargs)

    def __call__(self, parser, namespace, values, option_string=None):
        low_ok = self.low < values if self.open_low else self.low <= values
        if not (low_ok and values <= self.high):  # NaN fails too
            unit = f" {self.unit}" if self.unit else ""
            lower = f"> {_number(self.low)} and <=" if self.open_low else f"{_number(self.low)} to"
            parser.error(f"{option_string} must be {lower} {_number(self.high)}{unit}, got {_number(values)}")
        setattr(namespace, self.dest, values)


def bounded(low: float, high: float, unit: str = "", open_low: bool = False) -> dict:
    """``add_argument`` keywords of a numeric option whose value must lie in ``[low, high]``
    (``(low, high]`` with ``open_low``; ``unit`` printed after the bounds): a value outside is a
    usage error of one line naming the option, before the command does anything. Every
    ``int`` and ``float`` option of every command has bounds (``tests/test_user_errors.py``
    checks)."""
    return {"action": _Bounded, "bounds": (low, high, unit, open_low)}


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


def output_lock(out: str | os.PathLike):
    """The lock of a command's output folder ``out`` (:func:`softcrawl.safeio.folder_lock`): the
    file ``.<name>.lock`` beside it, in its parent folder (created if missing: the output is
    written there), so a second command writing the same ``out`` is refused at once.

    Raises:
        FolderLockedError: another command is writing ``out``.
        OSError: the parent folder cannot be created.
    """
    from pathlib import Path

    from softcrawl.safeio import folder_lock

    out = Path(out)
    out.absolute().parent.mkdir(parents=True, exist_ok=True)
    return folder_lock(out.absolute().parent / f".{out.absolute().name}.lock", out)


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default: the process's arguments) and run the command; returns the exit
    code (a usage error: 2, its line on stderr; ``--help``, ``--version``: 0)."""
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:
        return exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 2
    return run_command(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
