"""Body design spaces: leg slots, each empty or driven by one of the regulators. A space is
read from a TOML file (:mod:`softcrawl.design.spacefile`); the module functions and constants
here are the paper's space (8 slots, 3 regulators, 3-6 legs: ``spaces/paper.toml``);
:func:`resolve_space` turns a ``--space`` value (a shipped name or a path) into a space."""

from softcrawl.design.space import (
    BASELINE_DESIGN,
    DEFAULT_SPACE,
    MAX_LEGS,
    MIN_LEGS,
    N_REGULATORS,
    N_SLOTS,
    PAPER_BEST_DESIGN,
    SLOT_ANGLES_DEG,
    Design,
    InvalidDesignError,
    canonical_array,
    canonical_designs,
    canonicalize,
    design_from_index,
    design_index,
    is_canonical,
    n_legs,
    one_hot,
    one_hot_batch,
    raw_designs,
    regulator_groups,
    validate_design,
)
from softcrawl.design.spacefile import DesignSpace, SpaceFileError, load_space, shipped_space_path
from softcrawl.design.resolve import resolve_space

__all__ = [
    "BASELINE_DESIGN",
    "DEFAULT_SPACE",
    "MAX_LEGS",
    "MIN_LEGS",
    "N_REGULATORS",
    "N_SLOTS",
    "PAPER_BEST_DESIGN",
    "SLOT_ANGLES_DEG",
    "Design",
    "DesignSpace",
    "InvalidDesignError",
    "canonical_array",
    "canonical_designs",
    "canonicalize",
    "design_from_index",
    "design_index",
    "is_canonical",
    "n_legs",
    "one_hot",
    "one_hot_batch",
    "raw_designs",
    "regulator_groups",
    "resolve_space",
    "SpaceFileError",
    "load_space",
    "shipped_space_path",
    "validate_design",
]
