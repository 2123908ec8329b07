"""Pictures of a design: a text sketch and a matplotlib top view (schematic, not to scale).

Both views look down -z with +x (forward) to the right and +y up, so slot 0 (22.5 deg)
is right of centre, slightly up, and slot 7 (337.5 deg) right, slightly down.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from softcrawl.design.space import DEFAULT_SPACE, SLOT_ANGLES_DEG
from softcrawl.design.spacefile import DesignSpace

# Slot {i} placed by its angle: 1, 2 on top; 3, 4 left; 5, 6 bottom; 7, 0 right.
_ASCII_TEMPLATE = """\
         {2}   {1}
       .---------.
     {3} |         | {0}
       |    o    |   --> +x (forward)
     {4} |         | {7}
       '---------'
         {5}   {6}"""

#: Matplotlib colours of regulators 1, 2, 3.
REGULATOR_COLOURS = {1: "tab:blue", 2: "tab:orange", 3: "tab:green"}


def design_ascii(d: Sequence[int] | str, space: DesignSpace = DEFAULT_SPACE) -> str:
    """A small text top view of the disk: each slot shows '.' (empty) or its regulator number
    (for a space whose slots are not the paper's 8: one line ``angle: value`` per slot).

    Raises:
        InvalidDesignError: if ``d`` is not a valid design of ``space``.
    """
    d = space.validate_design(d)
    marks = ["." if v == 0 else str(v) for v in d]
    if space.slot_angles_deg == SLOT_ANGLES_DEG:
        return _ASCII_TEMPLATE.format(*marks)
    return "\n".join(f"slot {i} at {a:g} deg: {m}" for i, (a, m) in enumerate(zip(space.slot_angles_deg, marks)))


def regulator_colour(k: int) -> str:
    """Matplotlib colour of regulator ``k`` (:data:`REGULATOR_COLOURS`, then the colour cycle)."""
    return REGULATOR_COLOURS.get(k, f"C{(k - 1) % 10}")


def _leg_polygon(angle_deg: float, r0: float, length: float, width: float) -> np.ndarray:
    """Corners ``(4, 2)`` of a rectangle from radius ``r0`` outward along ``angle_deg``."""
    a = np.deg2rad(angle_deg)
    u = np.array([np.cos(a), np.sin(a)])  # radial
    n = np.array([-u[1], u[0]])  # tangential
    half = 0.5 * width * n
    p0, p1 = r0 * u, (r0 + length) * u
    return np.array([p0 - half, p1 - half, p1 + half, p0 + half])


def plot_design(d: Sequence[int] | str, ax=None, path: str | Path | None = None, space: DesignSpace = DEFAULT_SPACE):
    """Top-view drawing of a design: disk, legs as rectangles radiating at their slot angles
    coloured by regulator (legend), empty slots as dashed outlines, and a +x (forward) arrow.

    Uses the object-oriented matplotlib API (no pyplot state; renders with Agg).

    Args:
        d: a design (sequence or string, see :func:`~softcrawl.design.space.validate_design`).
        ax: an existing Axes to draw into; a new Figure is created if None.
        path: if given, the figure is saved there as PNG.
        space: the design space (slot angles, regulators).

    Returns:
        The matplotlib Figure.

    Raises:
        InvalidDesignError: if ``d`` is not a valid design of ``space``.
    """
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Patch, Polygon

    d = space.validate_design(d)
    if ax is None:
        fig = Figure(figsize=(4.5, 4.5))
        ax = fig.add_subplot()
    else:
        fig = ax.figure

    r_disk, leg_len, leg_w = 1.0, 1.1, 0.45
    ax.add_patch(Circle((0, 0), r_disk, facecolor="0.85", edgecolor="0.3", lw=1.5, zorder=2))
    for slot, (v, ang) in enumerate(zip(d, space.slot_angles_deg)):
        corners = _leg_polygon(ang, 0.8 * r_disk, leg_len, leg_w)
        if v:
            patch = Polygon(corners, facecolor=regulator_colour(v), edgecolor="k", lw=1.0, zorder=1)
        else:
            patch = Polygon(corners, fill=False, edgecolor="0.6", ls="--", lw=0.8, zorder=1)
        ax.add_patch(patch)
        a = np.deg2rad(ang)
        r_lab = 0.8 * r_disk + leg_len + 0.25
        ax.text(r_lab * np.cos(a), r_lab * np.sin(a), str(slot), ha="center", va="center", fontsize=8, color="0.4")

    ax.annotate(
        "", xy=(0.7, 0), xytext=(-0.3, 0), arrowprops=dict(arrowstyle="-|>", lw=2, color="k"), zorder=3
    )
    ax.text(0.72, 0.08, "+x", fontsize=9, zorder=3)

    handles = [Patch(facecolor=regulator_colour(k), edgecolor="k", label=f"regulator {k}")
               for k in space.regulator_groups(d)]
    ax.legend(handles=handles, loc="upper left", bbox_to_anchor=(1.0, 1.0), fontsize=8, frameon=False)
    lim = 0.8 * r_disk + leg_len + 0.45
    ax.set_xlim(-lim, lim)
    ax.set_ylim(-lim, lim)
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.set_title(",".join(map(str, d)), fontsize=10)
    if path is not None:
        fig.savefig(path, format="png", dpi=120, bbox_inches="tight")
    return fig


__all__ = ["REGULATOR_COLOURS", "design_ascii", "plot_design", "regulator_colour"]
