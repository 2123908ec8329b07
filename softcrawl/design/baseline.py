"""The expert baseline's design in any design space (codesign.md, "Expert baseline"): the
paper's four legs in an X, front pair on regulator 1 and rear pair on regulator 2, found again
among another space's slots."""

from __future__ import annotations

import math

from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import Design, DesignSpace

#: Legs of a space's symmetric design (:func:`symmetric_design`), clipped to its leg counts.
SYMMETRIC_LEGS = 4


def _axis_distance(angle_deg: float) -> float:
    """Angle (degrees, rounded to 1e-6) between a slot direction and the x axis, either way."""
    folded = angle_deg % 180.0
    return round(min(folded, 180.0 - folded), 6)


def symmetric_design(space: DesignSpace = DEFAULT_SPACE) -> Design:
    """A design of ``space`` shaped like the paper's expert baseline (codesign.md): the
    ``SYMMETRIC_LEGS`` slots nearest the x axis (clipped to ``min_legs..max_legs``; ties by slot
    index), those in front (``cos(theta) > 0``) on regulator 1, the others on regulator 2 (1 if
    the space has one regulator). The paper's space gives ``BASELINE_DESIGN`` (1,0,0,2,2,0,0,1);
    a mirror-symmetric slot set gives a design mirror-symmetric about the x axis.
    """
    n = min(max(SYMMETRIC_LEGS, space.min_legs), space.max_legs)
    angles = space.slot_angles_deg
    slots = sorted(range(space.n_slots), key=lambda i: (_axis_distance(angles[i]), i))[:n]
    rear = min(2, space.n_regulators)
    design = [0] * space.n_slots
    for i in slots:
        design[i] = 1 if math.cos(math.radians(angles[i])) > 0 else rear
    return space.validate_design(design)


def sine_baseline_design(space: DesignSpace = DEFAULT_SPACE) -> Design | None:
    """The design the ``forward`` task's expert sine gait runs on in ``space``: its
    :func:`symmetric_design` (the paper's ``1,0,0,2,2,0,0,1`` in the paper's space; ``1,0,2,2,0,1``
    in ``hex6``), or None for a space of one regulator (the gait's phase lag needs two)."""
    return symmetric_design(space) if space.n_regulators >= 2 else None
