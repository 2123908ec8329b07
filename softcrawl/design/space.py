"""The paper's body design space (paper Sec. "Design space"; ``codesign.md``), as module
constants and functions: the shipped space file ``spaces/paper.toml`` read into
:data:`DEFAULT_SPACE` (:class:`softcrawl.design.spacefile.DesignSpace`, which holds the algebra).

A robot is a disk with ``N_SLOTS = 8`` leg slots at angles ``22.5 deg + 45 deg * i``
(``i = 0..7``), measured about +z from +x (+x is forward). A *design* is a tuple of 8
integers: ``0`` = empty slot, ``k in {1, 2, 3}`` = a PneuNet leg driven by pressure
regulator ``k``. Designs have between ``MIN_LEGS = 3`` and ``MAX_LEGS = 6`` legs.

Regulator labels are interchangeable (the gait can permute regulators), so designs are
compared in *canonical* form: regulators relabelled by order of first appearance when
scanning slots 0 -> 7. This leaves 6,972 canonical designs out of 41,202 raw ones.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import numpy as np

from softcrawl.design.spacefile import Design, DesignSpace, InvalidDesignError, load_space, shipped_space_path

#: The paper's space (``spaces/paper.toml``; its PneuNet dimensions are checked by the tests).
DEFAULT_SPACE: DesignSpace = load_space(shipped_space_path("paper"), check_geometry=False)

N_SLOTS = DEFAULT_SPACE.n_slots
N_REGULATORS = DEFAULT_SPACE.n_regulators
MIN_LEGS = DEFAULT_SPACE.min_legs
MAX_LEGS = DEFAULT_SPACE.max_legs

#: Slot angles, degrees about +z from +x (forward): 22.5, 67.5, ..., 337.5.
SLOT_ANGLES_DEG: tuple[float, ...] = DEFAULT_SPACE.slot_angles_deg

#: Expert baseline: front pair (22.5, 337.5 deg) on regulator 1, rear pair (157.5, 202.5 deg) on 2.
BASELINE_DESIGN: tuple[int, ...] = (1, 0, 0, 2, 2, 0, 0, 1)
#: Best design reported in the paper: the baseline without the 337.5 deg front leg.
PAPER_BEST_DESIGN: tuple[int, ...] = (1, 0, 0, 2, 2, 0, 0, 0)

__all__ = ["BASELINE_DESIGN", "DEFAULT_SPACE", "MAX_LEGS", "MIN_LEGS", "N_REGULATORS", "N_SLOTS", "PAPER_BEST_DESIGN",
           "SLOT_ANGLES_DEG", "Design", "InvalidDesignError", "canonical_array", "canonical_designs", "canonicalize",
           "design_from_index", "design_index", "is_canonical", "n_legs", "one_hot", "one_hot_batch", "raw_designs",
           "regulator_groups", "validate_design"]


def validate_design(d: Sequence[int] | str) -> Design:
    """:meth:`DesignSpace.validate_design` of the paper's space: a tuple of 8 ints in {0..3}
    with 3 to 6 legs. Raises InvalidDesignError naming the fault."""
    return DEFAULT_SPACE.validate_design(d)


def canonicalize(d: Sequence[int] | str) -> Design:
    """Regulators relabelled by first appearance scanning slots 0 -> 7, e.g.
    ``(2,0,0,1,1,0,0,2) -> (1,0,0,2,2,0,0,1)`` (:meth:`DesignSpace.canonicalize`).
    Raises InvalidDesignError if ``d`` is not a valid design."""
    return DEFAULT_SPACE.canonicalize(d)


def is_canonical(d: Sequence[int] | str) -> bool:
    """Whether ``d`` equals its canonical form. Raises InvalidDesignError if invalid."""
    return DEFAULT_SPACE.is_canonical(d)


def n_legs(d: Sequence[int] | str) -> int:
    """Number of occupied slots. Raises InvalidDesignError if invalid."""
    return DEFAULT_SPACE.n_legs(d)


def regulator_groups(d: Sequence[int] | str) -> dict[int, list[int]]:
    """Regulator -> its slots, e.g. ``BASELINE_DESIGN -> {1: [0, 7], 2: [3, 4]}``
    (:meth:`DesignSpace.regulator_groups`). Raises InvalidDesignError if invalid."""
    return DEFAULT_SPACE.regulator_groups(d)


def raw_designs() -> tuple[Design, ...]:
    """All 41,202 valid designs (Sum_{k=3..6} C(8,k) 3^k), lexicographically sorted."""
    return DEFAULT_SPACE.raw_designs


def canonical_designs() -> tuple[Design, ...]:
    """All 6,972 canonical designs (3/4/5/6 legs: 280/980/2,296/3,416), lexicographically sorted."""
    return DEFAULT_SPACE.canonical_designs


def canonical_array() -> np.ndarray:
    """The canonical designs as a read-only ``(6972, 8)`` int8 array (row i = index i)."""
    return DEFAULT_SPACE.canonical_array


def design_index(d: Sequence[int] | str) -> int:
    """Index of ``canonicalize(d)`` in :func:`canonical_designs`. Raises InvalidDesignError if invalid."""
    return DEFAULT_SPACE.design_index(d)


def design_from_index(i: int) -> Design:
    """The canonical design with index ``i`` (``0 <= i < 6972``). Raises IndexError if out of range."""
    return DEFAULT_SPACE.design_from_index(i)


def one_hot(d: Sequence[int] | str) -> np.ndarray:
    """One-hot encoding, ``(32,)`` float32: 8 slot-major blocks of length 4 (value 0..3).
    The design is encoded as given (not canonicalised). Raises InvalidDesignError if invalid."""
    return DEFAULT_SPACE.one_hot_batch([d])[0]


def one_hot_batch(designs: Iterable[Sequence[int] | str] | np.ndarray) -> np.ndarray:
    """One-hot encodings of several designs, ``(n, 32)`` float32 (see :func:`one_hot`).
    Raises InvalidDesignError if any design is invalid."""
    return DEFAULT_SPACE.one_hot_batch(designs)
