"""Reductions shipped with softcrawl (package data)."""

from __future__ import annotations

from pathlib import Path

#: File name of the default PneuNet leg reduction (6 mm leg mesh, reference parameters).
DEFAULT_REDUCTION = "pneunet_6mm.npz"


def default_reduction_path() -> Path:
    """Path of the shipped default leg reduction (see ``softcrawl reduce build``)."""
    return Path(__file__).with_name(DEFAULT_REDUCTION)
