"""Reductions shipped with softcrawl (package data)."""

from __future__ import annotations

from pathlib import Path

#: File name of the default reduction (6 mm PneuNet leg, no disk part, reference parameters).
DEFAULT_REDUCTION = "pneunet_6mm.npz"


def default_reduction_path() -> Path:
    """Path of the shipped default reduction (see ``softcrawl reduce build``)."""
    return Path(__file__).with_name(DEFAULT_REDUCTION)
