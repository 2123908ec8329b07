"""One-line notes on stderr: what a command skipped or substituted."""

from __future__ import annotations

import sys


def note(msg: str) -> None:
    """A one-line note on stderr (``softcrawl: ...``): what was skipped or substituted."""
    print(f"softcrawl: {msg}", file=sys.stderr)
