"""The discrete body design space (paper Sec. "Design space"; ``codesign.md``).

A robot is a disk with ``N_SLOTS = 8`` leg slots at angles ``22.5 deg + 45 deg * i``
(``i = 0..7``), measured about +z from +x (+x is forward). A *design* is a tuple of 8
integers: ``0`` = empty slot, ``k in {1, 2, 3}`` = a PneuNet leg driven by pressure
regulator ``k``. Designs have between ``MIN_LEGS = 3`` and ``MAX_LEGS = 6`` legs.

Regulator labels are interchangeable (the gait can permute regulators), so designs are
compared in *canonical* form: regulators relabelled by order of first appearance when
scanning slots 0 -> 7. This leaves 6,972 canonical designs out of 41,202 raw ones.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from functools import lru_cache

import numpy as np

N_SLOTS = 8
N_REGULATORS = 3
MIN_LEGS = 3
MAX_LEGS = 6

#: Slot angles, degrees about +z from +x (forward): 22.5, 67.5, ..., 337.5.
SLOT_ANGLES_DEG: tuple[float, ...] = tuple(22.5 + 45.0 * i for i in range(N_SLOTS))

#: Expert baseline: front pair (22.5, 337.5 deg) on regulator 1, rear pair (157.5, 202.5 deg) on 2.
BASELINE_DESIGN: tuple[int, ...] = (1, 0, 0, 2, 2, 0, 0, 1)
#: Best design reported in the paper: the baseline without the 337.5 deg front leg.
PAPER_BEST_DESIGN: tuple[int, ...] = (1, 0, 0, 2, 2, 0, 0, 0)

Design = tuple[int, ...]


class InvalidDesignError(ValueError):
    """A design is malformed: wrong length, non-integer entry, value outside {0..3},
    or a leg count outside [MIN_LEGS, MAX_LEGS]."""


def _as_int(v: object) -> int | None:
    """``v`` as an int if it is an integer (int, numpy integer, integral float, digit string)."""
    if isinstance(v, (bool, np.bool_)):
        return None
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return int(v) if float(v).is_integer() else None
    if isinstance(v, str):
        try:
            return int(v)
        except ValueError:
            return None
    return None


def validate_design(d: Sequence[int] | str) -> Design:
    """Check a design and return it as a tuple of 8 ints.

    Args:
        d: a sequence of 8 integers in {0, 1, 2, 3}, or a string such as ``"1,0,0,2,2,0,0,1"``
            (comma- and/or whitespace-separated; surrounding brackets are ignored).

    Returns:
        The design as ``tuple[int, ...]`` of length 8 (not canonicalised).

    Raises:
        InvalidDesignError: naming the fault (length, non-integer entry, out-of-range value
            with its slot, or the leg count).
    """
    if isinstance(d, str):
        items: list = d.strip().strip("[]()").replace(",", " ").split()
    else:
        try:
            items = list(d)
        except TypeError:
            raise InvalidDesignError(f"design must be a sequence of {N_SLOTS} integers, got {d!r}") from None
    if len(items) != N_SLOTS:
        raise InvalidDesignError(f"design must have {N_SLOTS} slots, got {len(items)}: {d!r}")
    out = []
    for slot, v in enumerate(items):
        iv = _as_int(v)
        if iv is None:
            raise InvalidDesignError(f"slot {slot}: {v!r} is not an integer")
        if not 0 <= iv <= N_REGULATORS:
            raise InvalidDesignError(
                f"slot {slot}: value {iv} not in {{0..{N_REGULATORS}}} (0 = empty, k = regulator k)"
            )
        out.append(iv)
    legs = sum(v > 0 for v in out)
    if not MIN_LEGS <= legs <= MAX_LEGS:
        which = "too few" if legs < MIN_LEGS else "too many"
        raise InvalidDesignError(f"{which} legs: {legs} (allowed {MIN_LEGS} to {MAX_LEGS})")
    return tuple(out)


def canonicalize(d: Sequence[int] | str) -> Design:
    """Relabel regulators by first appearance scanning slots 0 -> 7.

    The first regulator met becomes 1, the second distinct one 2, the third 3.
    E.g. ``(2,0,0,1,1,0,0,2) -> (1,0,0,2,2,0,0,1)``.

    Raises:
        InvalidDesignError: if ``d`` is not a valid design (see :func:`validate_design`).
    """
    return _relabel(validate_design(d))


def _relabel(d: Design) -> Design:
    """Canonical relabelling of an already validated design."""
    relabel: dict[int, int] = {0: 0}
    for v in d:
        if v not in relabel:
            relabel[v] = len(relabel)
    return tuple(relabel[v] for v in d)


def is_canonical(d: Sequence[int] | str) -> bool:
    """Whether ``d`` equals its canonical form. Raises InvalidDesignError if invalid."""
    d = validate_design(d)
    return _relabel(d) == d


def n_legs(d: Sequence[int] | str) -> int:
    """Number of occupied slots. Raises InvalidDesignError if invalid."""
    return sum(v > 0 for v in validate_design(d))


def regulator_groups(d: Sequence[int] | str) -> dict[int, list[int]]:
    """Map each regulator used by ``d`` to its slot indices (ascending), e.g.
    ``BASELINE_DESIGN -> {1: [0, 7], 2: [3, 4]}``. Raises InvalidDesignError if invalid."""
    groups: dict[int, list[int]] = {}
    for slot, v in enumerate(validate_design(d)):
        if v:
            groups.setdefault(v, []).append(slot)
    return dict(sorted(groups.items()))


@lru_cache(maxsize=1)
def raw_designs() -> tuple[Design, ...]:
    """All 41,202 valid designs (Sum_{k=3..6} C(8,k) 3^k), lexicographically sorted."""
    return tuple(
        d
        for d in itertools.product(range(N_REGULATORS + 1), repeat=N_SLOTS)  # lexicographic
        if MIN_LEGS <= N_SLOTS - d.count(0) <= MAX_LEGS
    )


@lru_cache(maxsize=1)
def canonical_designs() -> tuple[Design, ...]:
    """All 6,972 canonical designs (3/4/5/6 legs: 280/980/2,296/3,416), lexicographically sorted."""
    return tuple(d for d in raw_designs() if _relabel(d) == d)


@lru_cache(maxsize=1)
def _index_map() -> dict[Design, int]:
    return {d: i for i, d in enumerate(canonical_designs())}


@lru_cache(maxsize=1)
def canonical_array() -> np.ndarray:
    """The canonical designs as a read-only ``(6972, 8)`` int8 array (row i = index i)."""
    arr = np.array(canonical_designs(), dtype=np.int8)
    arr.setflags(write=False)
    return arr


def design_index(d: Sequence[int] | str) -> int:
    """Index of ``canonicalize(d)`` in :func:`canonical_designs` (dict lookup).

    Raises:
        InvalidDesignError: if ``d`` is not a valid design.
    """
    return _index_map()[canonicalize(d)]


def design_from_index(i: int) -> Design:
    """The canonical design with index ``i`` (``0 <= i < 6972``).

    Raises:
        IndexError: if ``i`` is out of range (negative indices are rejected too).
    """
    designs = canonical_designs()
    if not 0 <= int(i) < len(designs):
        raise IndexError(f"design index {i} out of range [0, {len(designs)})")
    return designs[int(i)]


def one_hot(d: Sequence[int] | str) -> np.ndarray:
    """One-hot encoding, ``(32,)`` float32: 8 slot-major blocks of length 4 (value 0..3).

    The design is encoded as given (not canonicalised). Raises InvalidDesignError if invalid.
    """
    return one_hot_batch([d])[0]


def one_hot_batch(designs: Iterable[Sequence[int] | str] | np.ndarray) -> np.ndarray:
    """One-hot encodings of several designs, ``(n, 32)`` float32 (see :func:`one_hot`).

    Raises:
        InvalidDesignError: if any design is invalid.
    """
    if isinstance(designs, np.ndarray) and designs.ndim == 2:
        designs = designs.tolist()
    rows = np.array([validate_design(d) for d in designs], dtype=np.int64).reshape(-1, N_SLOTS)
    out = np.zeros((len(rows), N_SLOTS, N_REGULATORS + 1), dtype=np.float32)
    out[np.arange(len(rows))[:, None], np.arange(N_SLOTS)[None, :], rows] = 1.0
    return out.reshape(len(rows), N_SLOTS * (N_REGULATORS + 1))
