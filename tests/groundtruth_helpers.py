"""Ground-truth folders for the tests of its readers: rows written as ``softcrawl groundtruth``
writes them, by a fake task (no simulation)."""

from __future__ import annotations

import json
from pathlib import Path

from softcrawl.codesign.groundtruth import DesignResult, GroundTruthConfig, PeriodicGait, parse_designs, run_groundtruth

#: Five canonical three-legged designs.
DESIGNS = parse_designs("3")[:5]


def reward(design) -> float:
    """The fake ground truth's reward of ``design``, cm (distinct for distinct designs here)."""
    return float(sum(i * v for i, v in enumerate(design)))


def fake_task(design, cfg_dict) -> dict:
    """A worker's result for ``design`` without simulating (``run_groundtruth(task=...)``)."""
    return DesignResult(tuple(design), reward(design), PeriodicGait.paper_cycle().to_dict(), 3, "step", 10, 2,
                        80.0, 0.1).to_dict()


def row(of, **changes) -> str:
    """One line of ``results.jsonl`` for the design ``of`` with ``changes`` to its fields (no newline)."""
    return json.dumps({**fake_task(of, None), **changes})


#: The settings of the folders of :func:`make_folder`.
SETTINGS = GroundTruthConfig(baseline_phases=())


def make_folder(path: Path, designs=DESIGNS, task=fake_task) -> Path:
    """A finished ground truth of ``designs`` in ``path`` (no references)."""
    run_groundtruth(designs, path, SETTINGS, executor="serial", task=task, progress=False, refs=False)
    return path


def killed_folder(path: Path, designs, done: int) -> Path:
    """A ground truth of ``designs`` in ``path`` whose run was killed after its first ``done``
    designs (their rows only)."""
    make_folder(path, designs)
    rows = (path / "results.jsonl").read_text().splitlines(keepends=True)
    (path / "results.jsonl").write_text("".join(rows[:done]))
    return path
