"""Pneumatic actuation: the sim-to-real pressure calibration and rate-limited regulators.

Pressures are kPa. *Real* pressures are what the hardware regulators are commanded
(range [0, 90] kPa); *sim* pressures are what the FEM cavity load needs to reproduce the
real leg's bending (the "pressure warp", paper Sec. "Sim-to-real"; ``codesign.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# The regulators' command range lives below the simulator, so that softcrawl.gaits needs nothing
# of this package; re-exported here (P_MIN_KPA, P_MAX_KPA, PressureRangeError, check_pressures).
from softcrawl.gaits.pressure import P_MAX_KPA, P_MIN_KPA, PressureRangeError, check_pressures  # noqa: F401

#: Reference calibration table (paper Sec. "Sim-to-real"): real kPa 10, 20, ..., 100 ...
REAL_KPA_TABLE: tuple[float, ...] = tuple(float(p) for p in range(10, 101, 10))
#: ... and the sim kPa that reproduce the measured bending at each real pressure.
SIM_KPA_TABLE: tuple[float, ...] = (29.54, 65.67, 93.51, 128.17, 178.47, 224.37, 277.59, 316.16, 343.51, 382.57)

def _fit_line(real_kpa, sim_kpa) -> tuple[float, float]:
    """Validated least-squares ``(a, b)`` for ``sim = a * real + b`` (see PressureCalibration.from_table)."""
    x = np.asarray(real_kpa, dtype=float)
    y = np.asarray(sim_kpa, dtype=float)
    if x.ndim != 1 or y.ndim != 1 or x.shape != y.shape:
        raise ValueError(f"calibration table: real and sim must be 1-D of equal length, got {x.shape} and {y.shape}")
    if x.size < 2:
        raise ValueError(f"calibration table needs at least 2 points, got {x.size}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ValueError("calibration table contains non-finite values")
    if np.ptp(x) == 0:
        raise ValueError("calibration table: real pressures are all equal, the line is undetermined")
    a, b = np.polyfit(x, y, 1)
    return float(a), float(b)


_A_REF, _B_REF = _fit_line(REAL_KPA_TABLE, SIM_KPA_TABLE)


@dataclass(frozen=True)
class PressureCalibration:
    """Affine sim-to-real pressure map ``sim = max(a * real + b, 0)``, kPa.

    The default is the least-squares line through the reference table
    (:data:`REAL_KPA_TABLE`, :data:`SIM_KPA_TABLE`): ``a ~= 4.0785``, ``b ~= -20.36``.

    Attributes:
        a: slope, sim kPa per real kPa.
        b: intercept, sim kPa.

    Raises:
        ValueError: if ``a`` or ``b`` is not finite.
    """

    a: float = _A_REF
    b: float = _B_REF

    def __post_init__(self) -> None:
        if not (np.isfinite(self.a) and np.isfinite(self.b)):
            raise ValueError(f"calibration coefficients must be finite, got a={self.a}, b={self.b}")

    @classmethod
    def from_table(cls, real_kpa, sim_kpa) -> PressureCalibration:
        """Least-squares line ``sim = a * real + b`` through paired measurements.

        Args:
            real_kpa, sim_kpa: 1-D sequences of equal length >= 2, finite, kPa; ``real_kpa``
                must not be all equal.

        Raises:
            ValueError: on mismatched lengths, fewer than 2 points, non-finite or degenerate data.
        """
        a, b = _fit_line(real_kpa, sim_kpa)
        return cls(a=a, b=b)

    @classmethod
    def identity(cls) -> PressureCalibration:
        """The map ``sim = real`` (a=1, b=0)."""
        return cls(a=1.0, b=0.0)

    def to_sim(self, real_kpa):
        """Sim pressure (kPa) for real pressure(s) ``real_kpa``; any shape, clamped at >= 0.

        Returns a float for scalar input, else an array of the input's shape.
        """
        sim = np.maximum(self.a * np.asarray(real_kpa, dtype=float) + self.b, 0.0)
        return float(sim) if sim.ndim == 0 else sim


class RegulatorBank:
    """A bank of pressure regulators whose output pressures slew toward their commands.

    Each ``step`` moves every output by at most ``rate_kpa_s * dt`` toward its command.
    Commands must be finite and within [P_MIN_KPA, P_MAX_KPA] real kPa.

    Args:
        n: number of regulators (default 3).
        rate_kpa_s: slew-rate limit, kPa/s (default 150), > 0.
    """

    def __init__(self, n: int = 3, rate_kpa_s: float = 150.0) -> None:
        if int(n) < 1:
            raise ValueError(f"need at least one regulator, got n={n}")
        if not (np.isfinite(rate_kpa_s) and rate_kpa_s > 0):
            raise ValueError(f"rate limit must be finite and > 0 kPa/s, got {rate_kpa_s}")
        self.n = int(n)
        self.rate_kpa_s = float(rate_kpa_s)
        self.state = np.zeros(self.n)

    def reset(self, pressures=None) -> None:
        """Set all outputs to 0 kPa, or to ``pressures`` ``(n,)`` (range-checked)."""
        if pressures is None:
            self.state = np.zeros(self.n)
        else:
            self.state = self._check(pressures, "reset pressure")

    def _check(self, p, what: str) -> np.ndarray:
        p = np.asarray(p, dtype=float)
        if p.shape != (self.n,):
            raise ValueError(f"{what} must have shape ({self.n},), got {p.shape}")
        check_pressures(p, what)
        return p.copy()

    def step(self, command, dt: float) -> np.ndarray:
        """Advance ``dt`` seconds toward ``command`` ``(n,)`` real kPa; return the applied ``(n,)``.

        Raises:
            PressureRangeError: if a command is non-finite or outside [0, 90] kPa.
            ValueError: on a wrong shape or a negative / non-finite ``dt``.
        """
        cmd = self._check(command, "command")
        if not (np.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be finite and >= 0 s, got {dt}")
        max_dp = self.rate_kpa_s * dt
        self.state = self.state + np.clip(cmd - self.state, -max_dp, max_dp)
        return self.state.copy()
