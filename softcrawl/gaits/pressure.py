"""The command range of the pressure regulators (real kPa) and its check.

Every source of commands checks against it: gaits (:mod:`softcrawl.gaits.gaits`), the robot's
regulators (:mod:`softcrawl.robot.actuation`, which re-exports these names), the rig
(:mod:`softcrawl.hardware`). It lives here, at the bottom, so that :mod:`softcrawl.gaits`
imports nothing of the simulator (importing ``softcrawl.robot.actuation`` would run
``softcrawl/robot/__init__.py``: assembly, FEM, reduction).
"""

from __future__ import annotations

import numpy as np

#: Command range of the real pressure regulators, kPa.
P_MIN_KPA = 0.0
P_MAX_KPA = 90.0


class PressureRangeError(ValueError):
    """A commanded pressure is not finite or lies outside [P_MIN_KPA, P_MAX_KPA]."""


def pressure_problem(v: float) -> str | None:
    """Why real pressure ``v`` (kPa) cannot be commanded, or None if it can."""
    if not np.isfinite(v):
        return "is not finite"
    if v < P_MIN_KPA or v > P_MAX_KPA:
        return f"is outside [{P_MIN_KPA:g}, {P_MAX_KPA:g}] kPa"
    return None


def check_pressures(p: np.ndarray, what: str = "pressure") -> None:
    """Raise PressureRangeError naming the first non-finite or out-of-range entry of ``p``.

    ``p`` is 1-D ``(m,)`` (entry named by column) or 2-D ``(k, m)`` (named by row and column).
    """
    p = np.asarray(p, dtype=float)
    bad = ~np.isfinite(p) | (p < P_MIN_KPA) | (p > P_MAX_KPA)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        names = {0: (), 1: ("column",), 2: ("row", "column")}.get(len(idx), ("index",) * len(idx))
        where = (" " + ", ".join(f"{name} {i}" for name, i in zip(names, idx)) + " (0-based)") if idx else ""
        v = float(p[idx])
        raise PressureRangeError(f"{what}{where}: {v:g} kPa {pressure_problem(v)}")
