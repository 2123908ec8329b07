"""Readers for recorded rig logs.

:func:`read_auro_log` imports one trial of the recorded real rig runs published with
Schaff, Sedal, Ni, Walter, "Sim-to-real transfer of co-optimized soft robot crawlers",
Autonomous Robots 2023 (repository ``macrobotics-lab/AuRo_evolving_sobot_data``, commit
06a1e93; a copy of the CSV files lives in ``shared/data/auro2023``). File layout (5 lines):

1. time stamps of the 20 control steps, ms;
2.-4. commanded pressure of regulators 1-3, kPa;
5. 20 quoted Python dict literals ``{'regulator': [3], 'honeywell': [3], 'commanded': [3]}``.
   The readings of step k+1 are those at the end of the hold of command k.

Channel order (checked against the commands over all 273 complete files, correlation of
command k with the next reading): the regulators' own readings come in reverse order
(reading index 2 is regulator 1, as the authors' decoder has it; r = 0.92, 0.93, 0.91), the
Honeywell readings in order (r = 0.95, 0.87, 0.95). :class:`RecordedTrial` stores both in
regulator order. Dict literals are parsed with :func:`ast.literal_eval`, never ``eval``.

:func:`read_deploy_log` reads the CSV written by :mod:`softcrawl.hardware.deploy`.
"""

from __future__ import annotations

import ast
import csv
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softcrawl.hardware.errors import one_line
from softcrawl.safeio import load_json, read_text

N_REG = 3
#: Index in the logged ``regulator`` list of regulators 1, 2, 3.
AURO_REGULATOR_ORDER = (2, 1, 0)
#: Index in the logged ``honeywell`` list of regulators 1, 2, 3.
AURO_HONEYWELL_ORDER = (0, 1, 2)


@dataclass(frozen=True, eq=False)
class RecordedTrial:
    """One recorded real trial (all arrays in regulator order 1, 2, 3).

    Attributes:
        path: source file.
        t_s: ``(n,)`` step time stamps, s, from 0.
        commanded_kpa: ``(n, 3)`` commanded pressure of step k, kPa.
        regulator_kpa: ``(n, 3)`` regulators' own readings at the start of step k (= end of hold k-1), kPa.
        sensed_kpa: ``(n, 3)`` Honeywell readings at the start of step k, kPa gauge.
    """

    path: str
    t_s: np.ndarray
    commanded_kpa: np.ndarray
    regulator_kpa: np.ndarray
    sensed_kpa: np.ndarray

    @property
    def n_steps(self) -> int:
        return len(self.t_s)

    @property
    def hold_s(self) -> np.ndarray:
        """``(n - 1,)`` duration of each hold, s."""
        return np.diff(self.t_s)


def read_auro_log(path: str | Path, n_steps: int = 20) -> RecordedTrial:
    """Import one recorded trial (format in the module docstring).

    Args:
        path: a ``logs-*.csv`` file.
        n_steps: required number of control steps (20 for the recorded episodes).

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a regular text file of at most 16 MB, malformed or short, or a value that
            is not a finite float (one line naming the file and the line).
    """
    path = Path(path)
    text = read_text(path, max_bytes=16 * 1024 * 1024)
    rows = [(i, r) for i, r in enumerate(csv.reader(text.splitlines()), start=1) if any(c.strip() for c in r)]
    if len(rows) != 5:
        raise ValueError(f"{path}: expected 5 lines (times, 3 command rows, readings), got {len(rows)}")
    nums = []
    for line, r in rows[:4]:
        try:
            v = np.array(r, float)
        except ValueError:
            raise ValueError(f"{path}, line {line}: not a list of numbers") from None
        if not np.isfinite(v).all():
            raise ValueError(f"{path}, line {line}: a value is not a finite number")
        nums.append(v)
    t, cmd = nums[0], np.array(nums[1:4]) if len({v.size for v in nums[1:4]}) == 1 else None
    if t.size != n_steps or cmd is None or cmd.shape != (N_REG, n_steps):
        raise ValueError(f"{path}: expected {n_steps} steps, got {t.size} time stamps and command rows of "
                         f"{[v.size for v in nums[1:4]]}")
    line5, cells = rows[4]
    if len(cells) != n_steps:
        raise ValueError(f"{path}, line {line5}: expected {n_steps} readings, got {len(cells)}")
    reg, hw = [], []
    for i, cell in enumerate(cells):
        try:
            d = ast.literal_eval(cell)
            r = [float(d["regulator"][j]) for j in AURO_REGULATOR_ORDER]
            h = [float(d["honeywell"][j]) for j in AURO_HONEYWELL_ORDER]
        except (ValueError, SyntaxError, KeyError, IndexError, TypeError, OverflowError, RecursionError,
                MemoryError):
            raise ValueError(f"{path}, line {line5}: reading {i} is not a dict with 3 'regulator' and 3 "
                             "'honeywell' numbers") from None
        if not np.isfinite(r + h).all():
            raise ValueError(f"{path}, line {line5}: reading {i} holds a value that is not a finite number")
        reg.append(r)
        hw.append(h)
    if np.any(np.diff(t) <= 0):
        raise ValueError(f"{path}, line {rows[0][0]}: time stamps are not increasing")
    return RecordedTrial(str(path), (t - t[0]) / 1000.0, cmd.T.copy(), np.array(reg), np.array(hw))


def find_auro_logs(root: str | Path) -> list[Path]:
    """All ``logs-*.csv`` files under ``root``, sorted."""
    return sorted(Path(root).rglob("logs-*.csv"))


def read_auro_logs(root: str | Path) -> tuple[list[RecordedTrial], list[tuple[str, str]]]:
    """Every readable trial under ``root`` and ``(path, reason)`` for each refused file (malformed,
    not a regular file, a dangling link, unreadable): one bad file never stops the others."""
    good, bad = [], []
    for p in find_auro_logs(root):
        try:
            good.append(read_auro_log(p))
        except (ValueError, OSError) as exc:
            bad.append((str(p), one_line(exc)))
    return good, bad


# -- deploy logs --------------------------------------------------------------------------------

DEPLOY_COLUMNS = ("t_s", "step", "cmd_kpa_1", "cmd_kpa_2", "cmd_kpa_3", "set_v_1", "set_v_2", "set_v_3",
                  "meas_v_1", "meas_v_2", "meas_v_3", "sensed_kpa_1", "sensed_kpa_2", "sensed_kpa_3",
                  "overrun", "event")


@dataclass(frozen=True, eq=False)
class DeployLog:
    """A log written by ``softcrawl deploy`` (``log.csv`` + ``summary.json`` in one folder).

    Attributes:
        path: the folder. t_s: ``(m,)`` s since start. step: ``(m,)`` action index (-1 before the
            first action and on the final row, which records the shutdown in ``events``).
        commanded_kpa, set_v, measured_v, sensed_kpa: ``(m, 3)``. summary: the summary dict.
    """

    path: str
    t_s: np.ndarray
    step: np.ndarray
    commanded_kpa: np.ndarray
    set_v: np.ndarray
    measured_v: np.ndarray
    sensed_kpa: np.ndarray
    summary: dict
    events: list


#: Types of the ``summary.json`` fields that readers use (absent or null is allowed).
SUMMARY_TYPES = {"status": str, "reason": str, "rig": str, "simulated": bool, "samples": int, "overruns": int,
                 "n_actions": int, "sample_hz_achieved": float, "control_period_s": float, "sim_hold_s": float,
                 "elapsed_s": float, "fail_safe_confirmed": bool}


def check_summary(summary, where: str) -> dict:
    """A deploy ``summary.json`` value checked against :data:`SUMMARY_TYPES` (a dict; numbers
    finite, ints not bools; ``control_period_s`` and ``sim_hold_s`` > 0).

    Raises:
        ValueError: naming ``where`` and the first bad field.
    """
    if not isinstance(summary, dict):
        raise ValueError(f"{where}: a deploy summary must be a JSON object, got {type(summary).__name__}")
    for k, want in SUMMARY_TYPES.items():
        v = summary.get(k)
        if v is None:
            continue
        if want is float:
            positive = k in ("control_period_s", "sim_hold_s")
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            ok = ok and (v > 0 or not positive)
            what = "a positive number" if positive else "a finite number"
        else:
            ok = isinstance(v, want) and (want is bool or not isinstance(v, bool))
            what = want.__name__
        if not ok:
            raise ValueError(f"{where}: field {k!r} must be {what}, got {type(v).__name__} {str(v)[:40]!r}")
    return summary


def read_deploy_log(folder: str | Path) -> DeployLog:
    """Read a deploy output folder (``log.csv`` and ``summary.json``).

    Raises:
        FileNotFoundError: missing folder or files.
        ValueError: a file that is not regular or too large, a summary that is not a JSON object of
            the right field types (:func:`check_summary`), a log with a wrong header, no rows, or a
            value that is not a number (NaN allowed, infinities not; time and step finite),
            naming the file and line.
    """
    folder = Path(folder)
    log, summ = folder / "log.csv", folder / "summary.json"
    for p in (log, summ):
        if not p.exists():
            raise FileNotFoundError(f"{p}: not found (not a deploy log folder?)")
    summary = check_summary(load_json(summ, max_bytes=64 * 1024 * 1024), str(summ))
    reader = csv.DictReader(read_text(log).splitlines())
    if reader.fieldnames is None or tuple(reader.fieldnames) != DEPLOY_COLUMNS:
        raise ValueError(f"{log}: unexpected header {str(reader.fieldnames)[:200]}")
    num = DEPLOY_COLUMNS[:-1]  # every column but the event
    values, events = [], []
    for r in reader:
        try:
            v = [float(r[n]) for n in num]
        except (TypeError, ValueError):  # TypeError: a short row (missing cells are None)
            raise ValueError(f"{log}, line {reader.line_num}: a value is not a number") from None
        if any(math.isinf(x) for x in v) or not math.isfinite(v[0]) or not (-1 <= v[1] <= 1e9 and v[1] == int(v[1])):
            raise ValueError(f"{log}, line {reader.line_num}: a value is infinite or out of range")
        values.append(v)
        events.append(r["event"])
    if not values:
        raise ValueError(f"{log}: no samples")
    a = np.array(values)
    return DeployLog(str(folder), a[:, 0], a[:, 1].astype(int), a[:, 2:5], a[:, 5:8], a[:, 8:11], a[:, 11:14],
                     summary, events)
