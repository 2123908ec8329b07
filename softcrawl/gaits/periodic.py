"""Periodic open-loop gaits: per regulator a pressure pattern of knots, repeated.

Per regulator a pattern of ``L`` knots (real kPa, ``L`` = 1..8, one knot per action of
``hold`` s), repeated periodically. Two waveforms: ``"step"`` holds knot ``i`` during
``[i hold, (i + 1) hold)`` (what a policy with 1-s actions can command); ``"smooth"`` is the
periodic trigonometric interpolation through the knots (period ``L hold``). The smooth 4-knot
pattern through the samples ``p(0..3 s)`` of the expert's raised cosine
``45 - 45 cos(2 pi t / 4 s)`` *is* that cosine at any phase (:meth:`PeriodicGait.expert_sine`),
and the step 3-knot pattern rear / front / vent is the paper's 3-s cycle
(:meth:`PeriodicGait.paper_cycle`); both are proven in ``tests/test_groundtruth.py``. The gait
family of the ground truth (:mod:`softcrawl.codesign.groundtruth`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from softcrawl.gaits.gaits import N_REGULATORS, SineGait
from softcrawl.gaits.pressure import P_MAX_KPA, P_MIN_KPA

#: Longest pattern a regulator may have (knots).
MAX_KNOTS = 8
WAVEFORMS = ("step", "smooth")


@dataclass(frozen=True, eq=False)
class PeriodicGait:
    """Periodic open-loop gait: per regulator a pattern of knots, repeated.

    Attributes:
        patterns: ``R >= 1`` tuples of knots, one per regulator (real kPa, each in [0, 90];
            ``R = 3`` in the paper's design space); regulator ``k`` uses
            ``patterns[k - 1]`` of length ``L_k`` (1..:data:`MAX_KNOTS`); period of regulator
            ``k``: ``L_k * hold`` s; the gait's period is their least common multiple.
        hold: seconds per knot (> 0; 1 s = one action of the paper).
        waveform: ``"step"`` (knot ``i`` held over ``[i hold, (i + 1) hold)`` of the cycle) or
            ``"smooth"`` (periodic trigonometric interpolation through knot ``i`` at ``t = i hold``,
            clipped to [0, 90] kPa).

    Raises:
        ValueError: bad shapes, lengths, hold or waveform; knots outside [0, 90] kPa or non-finite.
    """

    patterns: tuple
    hold: float = 1.0
    waveform: str = "step"

    def __post_init__(self) -> None:
        if isinstance(self.patterns, (str, bytes)) or len(self.patterns) < 1:
            raise ValueError(f"need one pattern per regulator (at least one), got {self.patterns!r}")
        pats = []
        for k, p in enumerate(self.patterns, start=1):
            a = np.array(p, dtype=float).reshape(-1)
            if not 1 <= len(a) <= MAX_KNOTS:
                raise ValueError(f"regulator {k}: pattern needs 1..{MAX_KNOTS} knots, got {len(a)}")
            if not np.all(np.isfinite(a)) or a.min() < P_MIN_KPA or a.max() > P_MAX_KPA:
                raise ValueError(f"regulator {k}: knots must be finite and in [{P_MIN_KPA:g}, {P_MAX_KPA:g}] kPa, "
                                 f"got {a.tolist()}")
            pats.append(tuple(float(v) for v in a))
        if not (math.isfinite(self.hold) and self.hold > 0):
            raise ValueError(f"hold must be a positive number of seconds, got {self.hold!r}")
        if self.waveform not in WAVEFORMS:
            raise ValueError(f"waveform must be one of {WAVEFORMS}, got {self.waveform!r}")
        object.__setattr__(self, "patterns", tuple(pats))
        object.__setattr__(self, "hold", float(self.hold))

    # constructors
    @classmethod
    def from_knots(cls, knots, hold: float = 1.0, waveform: str = "step") -> PeriodicGait:
        """Gait from a ``(L, R)`` knot table (real kPa; column ``k - 1`` = regulator ``k``, ``R >= 1``).

        Raises:
            ValueError: a table that is not 2-D with at least one column (and the class's errors).
        """
        k = np.asarray(knots, dtype=float)
        if k.ndim != 2 or k.shape[1] < 1:
            raise ValueError(f"knots must have shape (L, R) with R >= 1 regulators, got {k.shape}")
        return cls(tuple(k[:, j] for j in range(k.shape[1])), hold, waveform)

    @classmethod
    def expert_sine(cls, phase_deg: float, period_knots: int = 4, hold: float = 1.0,
                    n_regulators: int = N_REGULATORS) -> PeriodicGait:
        """The expert gait :class:`softcrawl.gaits.SineGait` (period ``period_knots * hold`` s,
        0..90 kPa, regulator 2 lagging 1 by ``phase_deg``) as a smooth pattern of its samples;
        equal to it at every ``t`` for ``period_knots >= 3`` (a raised cosine has harmonics 0
        and 1 only). With ``n_regulators`` ``R``: regulators 1 and 2 as in the paper's gait,
        regulators 3..R at 0 kPa.

        Raises:
            ValueError: ``n_regulators < 2`` (the gait needs a front and a rear regulator).
        """
        if isinstance(n_regulators, bool) or int(n_regulators) != n_regulators or n_regulators < 2:
            raise ValueError(f"the expert gait drives a front and a rear regulator: n_regulators must be an "
                             f"integer >= 2, got {n_regulators!r}")
        g = SineGait(period=period_knots * hold, phase_deg=phase_deg)
        knots = np.zeros((period_knots, int(n_regulators)))
        knots[:, :2] = [g.pressure_at(i * hold)[:2] for i in range(period_knots)]
        return cls.from_knots(knots, hold, "smooth")

    @classmethod
    def paper_cycle(cls, high_kpa: float = P_MAX_KPA, hold: float = 1.0) -> PeriodicGait:
        """The paper's learned 3-s cycle for (1,0,0,2,2,0,0,0): rear regulator 2 inflates, then
        front regulator 1, then both vent (codesign.md); equals
        :func:`softcrawl.gaits.paper_best_gait` step for step."""
        return cls.from_knots([[0.0, high_kpa, 0.0], [high_kpa, 0.0, 0.0], [0.0, 0.0, 0.0]], hold, "step")

    @property
    def n_regulators(self) -> int:
        """``R``, the regulators driven (one pattern each)."""
        return len(self.patterns)

    @property
    def period(self) -> float:
        """Period of the whole gait, s (lcm of the pattern lengths times ``hold``)."""
        return math.lcm(*(len(p) for p in self.patterns)) * self.hold

    def with_waveform(self, waveform: str) -> PeriodicGait:
        return PeriodicGait(self.patterns, self.hold, waveform)

    def pressure_at(self, t: float) -> np.ndarray:
        """Commanded ``(R,)`` real kPa at ``t`` s (periodic, defined for all ``t``)."""
        u = t / self.hold
        out = np.empty(len(self.patterns))
        for k, p in enumerate(self.patterns):
            n = len(p)
            if n == 1 or self.waveform == "step":
                out[k] = p[int(math.floor(u + 1e-9)) % n]
            else:
                out[k] = _trig_interp(p, u)
        return np.clip(out, P_MIN_KPA, P_MAX_KPA)

    def to_dict(self) -> dict:
        """JSON-able form (inverse :meth:`from_dict`)."""
        return {"patterns": [list(p) for p in self.patterns], "hold": self.hold, "waveform": self.waveform}

    @classmethod
    def from_dict(cls, d: dict) -> PeriodicGait:
        return cls(tuple(d["patterns"]), d.get("hold", 1.0), d.get("waveform", "step"))

    def describe(self) -> str:
        """Short text: waveform and knots per regulator (kPa, rounded; regulators separated by ``;``)."""
        return f"{self.waveform} " + "; ".join("/".join(f"{v:.0f}" for v in p) for p in self.patterns)


def _trig_interp(knots: Sequence[float], u: float) -> float:
    """Periodic trigonometric interpolant of ``knots`` (at u = 0, 1, ..., n - 1; period n) at ``u``."""
    y = np.asarray(knots, float)
    n = len(y)
    c = np.fft.rfft(y) / n
    w = 2.0 * math.pi * u / n
    val = c[0].real
    for k in range(1, len(c)):
        if n % 2 == 0 and k == n // 2:  # Nyquist term: real coefficient, cosine only
            val += c[k].real * math.cos(w * k)
        else:
            val += 2.0 * (c[k].real * math.cos(w * k) - c[k].imag * math.sin(w * k))
    return float(val)
