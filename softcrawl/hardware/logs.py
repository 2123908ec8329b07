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
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

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
        ValueError: malformed or short file (one line naming the file and the problem).
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise ValueError(f"{path}: cannot read: {exc}") from None
    rows = [r for r in csv.reader(text.splitlines()) if any(c.strip() for c in r)]
    if len(rows) != 5:
        raise ValueError(f"{path}: expected 5 lines (times, 3 command rows, readings), got {len(rows)}")
    try:
        t = np.array(rows[0], float)
        cmd = np.array(rows[1:4], float)
    except ValueError:
        raise ValueError(f"{path}: lines 1-4 must be numbers") from None
    if t.size != n_steps or cmd.shape != (N_REG, n_steps):
        raise ValueError(f"{path}: expected {n_steps} steps, got {t.size} time stamps and commands {cmd.shape}")
    if len(rows[4]) != n_steps:
        raise ValueError(f"{path}: expected {n_steps} readings on line 5, got {len(rows[4])}")
    reg, hw = [], []
    for i, cell in enumerate(rows[4]):
        try:
            d = ast.literal_eval(cell)
            r = [float(d["regulator"][j]) for j in AURO_REGULATOR_ORDER]
            h = [float(d["honeywell"][j]) for j in AURO_HONEYWELL_ORDER]
        except (ValueError, SyntaxError, KeyError, IndexError, TypeError):
            raise ValueError(f"{path}: reading {i} on line 5 is not a dict with 3 'regulator' and 3 'honeywell' "
                             f"values") from None
        reg.append(r)
        hw.append(h)
    arrays = (t, cmd, np.array(reg), np.array(hw))
    if not all(np.isfinite(a).all() for a in arrays):
        raise ValueError(f"{path}: non-finite values")
    if np.any(np.diff(t) <= 0):
        raise ValueError(f"{path}: time stamps are not increasing")
    return RecordedTrial(str(path), (t - t[0]) / 1000.0, cmd.T.copy(), arrays[2], arrays[3])


def find_auro_logs(root: str | Path) -> list[Path]:
    """All ``logs-*.csv`` files under ``root``, sorted."""
    return sorted(Path(root).rglob("logs-*.csv"))


def read_auro_logs(root: str | Path) -> tuple[list[RecordedTrial], list[tuple[str, str]]]:
    """Every readable trial under ``root`` and ``(path, reason)`` for each rejected file."""
    good, bad = [], []
    for p in find_auro_logs(root):
        try:
            good.append(read_auro_log(p))
        except ValueError as exc:
            bad.append((str(p), str(exc)))
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


def read_deploy_log(folder: str | Path) -> DeployLog:
    """Read a deploy output folder (``log.csv`` and ``summary.json``).

    Raises:
        FileNotFoundError: missing folder or files. ValueError: malformed content.
    """
    folder = Path(folder)
    log, summ = folder / "log.csv", folder / "summary.json"
    for p in (log, summ):
        if not p.exists():
            raise FileNotFoundError(f"{p}: not found (not a deploy log folder?)")
    try:
        summary = json.loads(summ.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{summ}: not valid JSON: {exc}") from None
    with log.open(newline="", encoding="utf-8") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames is None or tuple(reader.fieldnames) != DEPLOY_COLUMNS:
            raise ValueError(f"{log}: unexpected header {reader.fieldnames}")
        rows = list(reader)
    if not rows:
        raise ValueError(f"{log}: no samples")

    def col(*names):
        try:
            return np.array([[float(r[n]) for n in names] for r in rows])
        except ValueError:
            raise ValueError(f"{log}: non-numeric value in {names}") from None

    c3 = lambda p: col(*(f"{p}_{i}" for i in (1, 2, 3)))  # noqa: E731
    return DeployLog(str(folder), col("t_s")[:, 0], col("step")[:, 0].astype(int), c3("cmd_kpa"), c3("set_v"),
                     c3("meas_v"), c3("sensed_kpa"), summary, [r["event"] for r in rows])
