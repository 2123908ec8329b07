"""One design's ground truth (:class:`DesignResult`, a row of ``results.jsonl``), validated
when read back."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.gaits.periodic import MAX_KNOTS, WAVEFORMS, PeriodicGait

#: Objective value given to an episode whose simulation diverged, in the task's unit (cm; degrees
#: for ``turning``).
DIVERGED_CM = -100.0


@dataclass
class DesignResult:
    """Ground truth of one design.

    The rewards are in the unit of the ground truth's task (:attr:`softcrawl.tasks.Task.unit`:
    cm for the paper's ``forward``, whose names the fields carry; degrees for ``turning``); a
    row of ``results.jsonl`` names them in that unit (:meth:`to_dict`).

    Attributes:
        design: canonical design. reward_cm: best full-episode reward (the task's return) per
            ``duration`` s.
        gait: the best :class:`PeriodicGait` as a dict. cycle: its pattern length; waveform.
        evaluations: episodes simulated (search + finals). full_evaluations: of those, full-length.
        sim_seconds: simulated seconds of all episodes. wall_seconds: wall time (1 process).
        screen_cm: the best gait's screening reward (NaN without screening).
        per_cycle: best screening (or full) reward per cycle length, cm.
        diverged: episodes that diverged.
    """

    design: Design
    reward_cm: float
    gait: dict
    cycle: int
    waveform: str
    evaluations: int
    full_evaluations: int
    sim_seconds: float
    wall_seconds: float
    screen_cm: float = float("nan")
    per_cycle: dict = field(default_factory=dict)
    diverged: int = 0

    def to_dict(self, unit: str = "cm") -> dict:
        """JSON-able (NaN written as None); the rewards keyed in ``unit`` (the task's:
        ``reward_<unit>``, ``screen_<unit>``)."""
        d = dataclasses.asdict(self)
        d["design"] = list(self.design)
        d["screen_cm"] = None if not math.isfinite(self.screen_cm) else self.screen_cm
        return {_unit_key(k, unit): v for k, v in d.items()}

    @classmethod
    def from_dict(cls, d: dict, where: str = "result", space: DesignSpace = DEFAULT_SPACE,
                  unit: str = "cm") -> DesignResult:
        """Inverse of :meth:`to_dict` (rewards keyed in ``unit``), validated: a canonical design
        of ``space`` (default the paper's), finite
        rewards and times, counts >= 0, a gait of the family (knots in [0, 90] kPa). Keys
        that are not fields are ignored (a newer version's additions).

        Raises:
            ValueError: the first fault, prefixed by ``where`` (file and line) and the design.
        """
        if not isinstance(d, dict):
            raise ValueError(f"{where}: a result must be a JSON object, got {type(d).__name__}")
        if unit != "cm":  # the fields' names are cm's
            d = {k: v for k, v in d.items() if k not in ("reward_cm", "screen_cm")}
            d = {({_unit_key(f, unit): f for f in ("reward_cm", "screen_cm")}).get(k, k): v for k, v in d.items()}
        fields = {f.name: f for f in dataclasses.fields(cls)}
        missing = [k for k, f in fields.items() if k not in d and f.default is dataclasses.MISSING
                   and f.default_factory is dataclasses.MISSING]
        if missing:
            raise ValueError(f"{where}: missing {', '.join(_unit_key(k, unit) for k in missing)}")
        design = d["design"]
        if not isinstance(design, list) or any(isinstance(v, bool) or not isinstance(v, int) for v in design):
            raise ValueError(f"{where}: design must be a list of {space.n_slots} integers, got {design!r}")
        design = tuple(design)
        try:
            canonical = space.canonicalize(design)
        except ValueError as exc:  # InvalidDesignError names the fault
            raise ValueError(f"{where}: {exc}") from None
        if canonical != design:
            raise ValueError(f"{where}: design {design} is not canonical ({canonical})")
        at = f"{where} (design {','.join(map(str, design))})"

        def number(key, low=-math.inf, integer=False, optional=False):
            v = d.get(key, fields[key].default)
            if v is None and optional:
                return float("nan")
            if not (_finite(v) and v >= low and (isinstance(v, int) or not integer)):
                kind = "an integer" if integer else "a finite number"
                raise ValueError(f"{at}: {_unit_key(key, unit)} must be {kind}"
                                 f"{f' >= {low:g}' if low > -math.inf else ''}, got {v!r}")
            return v if integer else float(v)

        try:
            gait = PeriodicGait.from_dict(d["gait"])
        except (ValueError, TypeError, KeyError, AttributeError, OverflowError) as exc:
            raise ValueError(f"{at}: gait: {exc}") from None
        if d["waveform"] not in WAVEFORMS:
            raise ValueError(f"{at}: waveform must be one of {WAVEFORMS}, got {d['waveform']!r}")
        per_cycle = d.get("per_cycle", {})
        if not isinstance(per_cycle, dict) or not all(
                str(k).isdigit() and 1 <= int(k) <= MAX_KNOTS and _finite(v) for k, v in per_cycle.items()):
            raise ValueError(f"{at}: per_cycle must map cycle lengths 1..{MAX_KNOTS} to finite rewards, "
                             f"got {per_cycle!r}")
        cycle = number("cycle", 1, integer=True)
        if cycle > MAX_KNOTS:
            raise ValueError(f"{at}: cycle must be in 1..{MAX_KNOTS}, got {cycle}")
        return cls(design, number("reward_cm"), gait.to_dict(), cycle, d["waveform"],
                   number("evaluations", 0, True), number("full_evaluations", 0, True), number("sim_seconds", 0),
                   number("wall_seconds", 0), number("screen_cm", optional=True),
                   {int(k): float(v) for k, v in per_cycle.items()}, number("diverged", 0, True))


def _unit_key(key: str, unit: str) -> str:
    """``key`` of a reward field named in ``unit``: ``reward_cm`` -> ``reward_deg``."""
    return key[:-2] + unit if key in ("reward_cm", "screen_cm") else key


def _finite(v) -> bool:
    """Whether ``v`` is a number (not a bool) that a float holds finitely."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer beyond any float
        return False
