"""Open-loop gaits for ``R`` pressure regulators, in REAL kPa (paper Sec. "Gaits"; ``codesign.md``).

A gait is anything with ``pressure_at(t) -> (R,)`` (the :class:`Gait` protocol): the
commanded real pressures of regulators ``1..R`` at time ``t`` seconds (``R = 3`` in the
paper's design space; another space's ``R`` is its ``[design] regulators``,
:class:`softcrawl.design.spacefile.DesignSpace`). Column ``k - 1`` of every pressure array is
regulator ``k``. A gait takes ``R`` from its data (the columns of an action array, the number
of patterns) or, where nothing else tells, from an ``n_regulators`` argument (default 3).
Convert to sim pressures with :class:`softcrawl.robot.actuation.PressureCalibration`.
"""

from __future__ import annotations

import csv
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from softcrawl.gaits.pressure import P_MAX_KPA, P_MIN_KPA, PressureRangeError, check_pressures, pressure_problem
from softcrawl.safeio import UnsafeFileError, read_text

#: Regulators of the paper's design space: the default where no data gives ``R``.
N_REGULATORS = 3


def csv_header(n_regulators: int = N_REGULATORS) -> tuple[str, ...]:
    """Header of an action CSV for ``n_regulators`` regulators: ``("p1", ..., "pR")``."""
    return tuple(f"p{k}" for k in range(1, int(n_regulators) + 1))


#: Header of an action CSV of the paper's 3 regulators.
CSV_HEADER = csv_header()


@runtime_checkable
class Gait(Protocol):
    """An open-loop gait: commanded real pressures ``(R,)`` kPa at time ``t`` s (one per regulator)."""

    def pressure_at(self, t: float) -> np.ndarray: ...


@dataclass(frozen=True, eq=False)
class ActionSequence:
    """Piecewise-constant gait: action ``i`` is held during ``[i * hold, (i + 1) * hold)``.

    Attributes:
        actions: ``(k, R)`` float64 real kPa, ``k >= 1`` actions of ``R >= 1`` regulators
            (column ``j`` = regulator ``j + 1``), finite, within [0, 90] kPa (stored as a
            read-only copy).
        hold: seconds per action, > 0 (default 1.0).

    Raises:
        ValueError: on a bad shape or non-positive ``hold``.
        PressureRangeError: naming the row/column of a non-finite or out-of-range pressure.
    """

    actions: np.ndarray
    hold: float = 1.0

    def __post_init__(self) -> None:
        a = np.array(self.actions, dtype=float)  # copy
        if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
            raise ValueError(f"actions must have shape (k, R) with k >= 1 actions of R >= 1 regulators, got {a.shape}")
        check_pressures(a, "action")
        if not (math.isfinite(self.hold) and self.hold > 0):
            raise ValueError(f"hold must be finite and > 0 s, got {self.hold}")
        a.setflags(write=False)
        object.__setattr__(self, "actions", a)
        object.__setattr__(self, "hold", float(self.hold))

    def __len__(self) -> int:
        return len(self.actions)

    @property
    def n_regulators(self) -> int:
        """``R``, the regulators of each action (the array's columns)."""
        return self.actions.shape[1]

    @property
    def duration(self) -> float:
        """Total duration ``k * hold`` in seconds."""
        return len(self.actions) * self.hold

    def pressure_at(self, t: float) -> np.ndarray:
        """Commanded ``(R,)`` real kPa at ``t`` s: the current action; before 0 the first,
        after the end the last."""
        i = min(max(int(math.floor(t / self.hold)), 0), len(self.actions) - 1)
        return self.actions[i].copy()


def read_actions_csv(path: str | Path, hold: float = 1.0, n_regulators: int | None = None) -> ActionSequence:
    """Read an action sequence: one row ``p1,...,pR`` (real kPa) per action, optional header
    line ``p1,...,pR``; blank lines are skipped; a UTF-8 byte-order mark (spreadsheet export) is
    accepted.

    Args:
        path: the CSV file.
        hold: seconds per action.
        n_regulators: ``R``, the columns every row must have (a design space's regulators);
            None: the header's count, else the first row's.

    Raises:
        FileNotFoundError: if ``path`` does not exist.
        ValueError: if the file cannot be read / decoded (or is a directory), a row does not
            have ``R`` numbers, or it has no actions.
        PressureRangeError: for a non-finite or out-of-range pressure.

    Every error about a row names the file and its 1-based line (``a.csv, line 4, p3: ...``).
    """
    path = Path(path)
    if n_regulators is not None and (int(n_regulators) != n_regulators or n_regulators < 1):
        raise ValueError(f"n_regulators must be a positive integer, got {n_regulators!r}")
    try:
        text = read_text(path)  # a regular file of bounded size; a UTF-8 byte-order mark is dropped
    except FileNotFoundError:
        raise
    except (OSError, UnsafeFileError) as exc:  # not UTF-8, not a regular file, too large, unreadable
        raise ValueError(f"cannot read action CSV: {exc}") from exc
    rows: list[list[float]] = []
    width = n_regulators
    for lineno, row in enumerate(csv.reader(text.splitlines()), start=1):
        cells = [c.strip() for c in row]
        if not any(cells):
            continue
        lowered = tuple(c.lower() for c in cells)
        if not rows and lowered == csv_header(len(cells)) and width in (None, len(cells)):
            width = len(cells)
            continue
        width = len(cells) if width is None else width
        if len(cells) != width:
            raise ValueError(f"{path}, line {lineno}: expected {width} columns, got {len(cells)}: {row!r}")
        try:
            values = [float(c) for c in cells]
        except ValueError:
            raise ValueError(f"{path}, line {lineno}: non-numeric pressure in {row!r}") from None
        for name, v in zip(csv_header(width), values):
            if (problem := pressure_problem(v)) is not None:
                raise PressureRangeError(f"{path}, line {lineno}, {name}: {v:g} kPa {problem}")
        rows.append(values)
    if not rows:
        raise ValueError(f"{path}: no actions found")
    return ActionSequence(np.array(rows), hold=hold)


def write_actions_csv(seq: ActionSequence, path: str | Path) -> None:
    """Write ``seq.actions`` as CSV with header ``p1,...,pR`` (full float precision; ``hold``
    is not stored)."""
    with Path(path).open("w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(csv_header(seq.n_regulators))
        w.writerows([repr(float(p)) for p in row] for row in seq.actions)


@dataclass(frozen=True)
class SineGait:
    """The expert baseline gait (paper Sec. "Baseline"): raised-cosine pressure waves.

    Front regulator 1: ``p(t) = offset - amplitude * cos(2 pi t / period)``; rear regulator 2
    lags it by ``phase_deg``: ``p2(t) = p(t - phase_deg / 360 * period)``; regulator 3 stays 0.
    The paper's 3 regulators; the same wave for ``R`` regulators is
    :meth:`softcrawl.gaits.PeriodicGait.expert_sine` with ``n_regulators=R``.
    Defaults give ``p(t) = 45 - 45 cos(2 pi t / 4)``: 0 kPa at t = 0, 90 kPa peak at t = T/2.

    Attributes:
        period: T, seconds (> 0).
        amplitude, offset: kPa; ``offset +/- amplitude`` must lie in [0, 90] kPa.
        phase_deg: lag of regulator 2 behind regulator 1, degrees.

    Raises:
        ValueError: for a non-positive period or non-finite parameters.
        PressureRangeError: if the wave leaves [0, 90] kPa.
    """

    period: float = 4.0
    amplitude: float = 45.0
    offset: float = 45.0
    phase_deg: float = 0.0

    def __post_init__(self) -> None:
        if not all(math.isfinite(v) for v in (self.period, self.amplitude, self.offset, self.phase_deg)):
            raise ValueError(f"SineGait parameters must be finite: {self}")
        if self.period <= 0:
            raise ValueError(f"period must be > 0 s, got {self.period}")
        lo, hi = self.offset - abs(self.amplitude), self.offset + abs(self.amplitude)
        if lo < P_MIN_KPA or hi > P_MAX_KPA:
            raise PressureRangeError(
                f"sine gait spans [{lo:g}, {hi:g}] kPa, outside [{P_MIN_KPA:g}, {P_MAX_KPA:g}] kPa"
            )

    def _wave(self, t: float) -> float:
        return self.offset - self.amplitude * math.cos(2.0 * math.pi * t / self.period)

    def pressure_at(self, t: float) -> np.ndarray:
        """Commanded ``(3,)`` real kPa ``[p(t), p(t - lag), 0]`` at ``t`` seconds."""
        lag = self.phase_deg / 360.0 * self.period
        # clip guards the +/- 1 ulp overshoot of the cosine at the range ends
        return np.clip([self._wave(t), self._wave(t - lag), 0.0], P_MIN_KPA, P_MAX_KPA)


@dataclass(frozen=True)
class VentedAfter:
    """``gait`` until ``after_s`` seconds, then every regulator commanded to 0 kPa (vented).

    Appended to an episode's gait it lets the robot relax, so that what the gait moved the robot
    can be told from what the pressure only holds in place (a twist of the body that springs back
    when the legs vent; :func:`softcrawl.tasks.base.vented_return`).

    Attributes:
        gait: any :class:`Gait`. after_s: seconds, finite and >= 0.

    Raises:
        ValueError: ``after_s`` negative or not finite.
    """

    gait: Gait
    after_s: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.after_s) and self.after_s >= 0):
            raise ValueError(f"after_s must be a finite number of seconds >= 0, got {self.after_s}")

    def pressure_at(self, t: float) -> np.ndarray:
        """``gait.pressure_at(t)`` before ``after_s``, zeros of its shape from then on, real kPa."""
        p = np.asarray(self.gait.pressure_at(t), dtype=float)
        return p if t < self.after_s else np.zeros_like(p)


def paper_best_gait(n_cycles: int | None = None, n_actions: int = 20, high_kpa: float = P_MAX_KPA) -> ActionSequence:
    """The paper's learned gait for ``PAPER_BEST_DESIGN`` (1,0,0,2,2,0,0,0), hold 1 s.

    A 3-action (3 s) cycle: rear regulator 2 at ``high_kpa`` (90 kPa), then front regulator 1
    at ``high_kpa``, then both at 0; repeated and truncated to ``n_actions`` actions (default 20,
    paper Sec. "Results"), or exactly ``3 * n_cycles`` actions if ``n_cycles`` is given.

    Returns:
        ActionSequence with ``(n, 3)`` real-kPa actions (the paper's 3 regulators).
    """
    cycle = np.array([[0.0, high_kpa, 0.0], [high_kpa, 0.0, 0.0], [0.0, 0.0, 0.0]])
    n = 3 * int(n_cycles) if n_cycles is not None else int(n_actions)
    if n < 1:
        raise ValueError(f"need at least one action, got {n}")
    return ActionSequence(np.resize(cycle, (n, cycle.shape[1])), hold=1.0)

