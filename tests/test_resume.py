"""``train --resume`` never loses history: it continues from the newest complete checkpoint and
reproduces the uninterrupted run; malformed or missing checkpoints are refused, nothing changed."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from softcrawl.cli import main
from helpers import file_tree, one_line_error, rehash


def _steps(run: Path) -> list[str]:
    return sorted(p.name for p in (run / "checkpoints").iterdir() if p.name.startswith("step-"))


def test_dangling_latest_resumes_from_newest_complete_checkpoint(run):
    from softcrawl.codesign.run import Run
    from softcrawl.codesign.training import train

    for name in ("step-0000000120", "step-0000000160"):
        shutil.rmtree(run / "checkpoints" / name)
    (run / "checkpoints" / "latest").write_text("step-0000000160")  # dangling
    head = (run / "episodes.csv").read_text().splitlines()[:4]  # t = 40, 40, 80, 80
    res = train(run, resume=True, progress=False)
    assert res.steps == 160
    rows = (run / "episodes.csv").read_text().splitlines()
    assert rows[:4] == head and [int(r.split(",")[0]) for r in rows] == [40, 40, 80, 80, 120, 120, 160, 160]
    assert (run / "sessions.csv").read_text().splitlines()[-1].startswith("80,160,")
    assert _steps(run) == ["step-0000000040", "step-0000000080", "step-0000000120", "step-0000000160"]
    assert Run(run).latest_checkpoint().name == "step-0000000160"


def test_a_run_resumed_at_an_episode_boundary_is_the_uninterrupted_run(trained, run):
    """Regression: the checkpoint at 80 steps (every env between episodes) keeps the
    designs the run had just drawn for the next episodes; resumed from it, the run logs the same
    episodes and design distribution as the uninterrupted one (it drew new designs instead and
    went its own way from the first episode after the checkpoint)."""
    from softcrawl.codesign.run import Run
    from softcrawl.codesign.training import train

    state = Run(run).read_checkpoint_state(run / "checkpoints" / "step-0000000080")
    assert state["next_designs"] is not None and len(state["next_designs"]) == 2
    for name in ("step-0000000120", "step-0000000160"):
        shutil.rmtree(run / "checkpoints" / name)
    (run / "checkpoints" / "latest").write_text("step-0000000080")
    assert train(run, resume=True, progress=False).steps == 160
    for name in ("episodes.csv", "distribution.csv"):
        assert (run / name).read_text() == (trained / name).read_text(), name


def test_malformed_next_designs_are_refused(run, capsys):
    """A checkpoint whose ``next_designs`` are not designs is not restorable: one clear line."""
    ck = run / "checkpoints" / "step-0000000160"
    st = json.loads((ck / "state.json").read_text())
    st["next_designs"] = [[9, 9, 9, 9, 9, 9, 9, 9], [1, 0, 0, 2, 2, 0, 0, 0]]
    (ck / "state.json").write_text(json.dumps(st))
    rehash(ck)
    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["total_steps"] = 200
    (run / "config.json").write_text(json.dumps(cfg))
    one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "malformed")


def test_no_complete_checkpoint_refuses_and_keeps_everything(run):
    from softcrawl.codesign.run import latest_checkpoint
    from softcrawl.codesign.training import train

    (run / "checkpoints" / "latest").unlink()
    assert latest_checkpoint(run).name == "step-0000000160"  # missing pointer: newest complete one
    for ck in (run / "checkpoints").glob("step-*"):
        (ck / "manifest.json").unlink()
    before = file_tree(run)
    with pytest.raises(ValueError, match="no complete checkpoint"):
        train(run, resume=True, progress=False)
    assert file_tree(run) == before


def test_a_resumed_run_may_move_but_not_change(trained, run, capsys):
    """Where a run runs may change on resume (the learner's device, the worker processes: a run
    started on a GPU machine is finished on a laptop) and the run is the uninterrupted one; what
    it learns may not: one line, nothing changed."""
    for name in ("step-0000000120", "step-0000000160"):
        shutil.rmtree(run / "checkpoints" / name)
    (run / "checkpoints" / "latest").write_text("step-0000000080")
    before, config = file_tree(run), (run / "config.json").read_bytes()
    one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress",
                                 "--set", "sac.batch_size=8"]), "only where it runs may change")
    assert file_tree(run) == before
    assert main(["train", "--resume", "--out", str(run), "--no-progress", "--workers", "3",
                 "--set", 'sac.device="cpu"']) == 0
    assert (run / "config.json").read_bytes() == config
    for name in ("episodes.csv", "distribution.csv"):
        assert (run / name).read_text() == (trained / name).read_text(), name
