"""Checkpoints: a damaged latest one falls back to the previous, a full disk keeps the previous
``latest`` (and the new checkpoint elsewhere), and each holds its step's gradient updates."""

from __future__ import annotations

import errno
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from softcrawl.cli import main
from helpers import one_line_error, restored_learner


def test_corrupt_latest_falls_back_to_the_previous_one(run, capsys):
    from softcrawl.codesign.run import Run

    model = run / "checkpoints" / "step-0000000160" / "learner.msgpack"
    data = bytearray(model.read_bytes())
    data[len(data) // 2] ^= 0xFF
    model.write_bytes(bytes(data))
    assert Run(run).latest_checkpoint().name == "step-0000000120"
    assert "damaged" in capsys.readouterr().err


def test_disk_full_while_checkpointing_keeps_the_previous_latest(run, monkeypatch):
    import softcrawl.codesign.run as run_mod

    model, sampler, r = restored_learner(run)
    model.num_timesteps = 200

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(run_mod.np, "savez", full)
    with pytest.raises(run_mod.NoSpaceError, match="no space left"):
        r.save_checkpoint(model, sampler, keep=4)
    assert not list((run / "checkpoints").glob("*.tmp"))
    assert (run / "checkpoints" / "latest").read_text() == "step-0000000160"


def test_full_disk_at_a_checkpoint_keeps_it_elsewhere_and_resume_uses_it(run, tmp_path, monkeypatch, capsys):
    """``train`` on a full disk: a one-line error naming where the checkpoint that did not fit
    was kept (the system's temp dir) and how to continue; moved into the run, resume finds it
    although ``latest`` names an older one."""
    import softcrawl.codesign.run as run_mod

    meta = json.loads((run / "config.json").read_text())
    meta["config"]["total_steps"] = 200
    (run / "config.json").write_text(json.dumps(meta))
    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    savez = np.savez

    def full_in_run(file, *a, **k):
        if Path(file).resolve().is_relative_to(run.resolve()):
            raise OSError(errno.ENOSPC, "No space left on device")
        return savez(file, *a, **k)

    monkeypatch.setattr(run_mod.np, "savez", full_in_run)
    err = one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]),
                          "no space left", "step-0000000200", "train --resume --out")
    assert (run / "checkpoints" / "latest").read_text() == "step-0000000160"
    assert not list((run / "checkpoints").glob("*.tmp"))
    kept = next(systmp.glob("softcrawl-rescue-*/step-0000000200"))
    assert str(kept) in err
    monkeypatch.setattr(run_mod.np, "savez", savez)
    shutil.move(kept, run / "checkpoints" / kept.name)
    r = run_mod.Run(run)
    assert r.latest_checkpoint().name == "step-0000000200"  # newer than latest: complete, so it wins
    assert "older than the complete step-0000000200" in capsys.readouterr().err
    assert r.read_checkpoint_state(r.latest_checkpoint())["num_timesteps"] == 200

def test_checkpoints_are_written_after_the_gradient_updates(trained):
    from softcrawl.codesign.run import Run

    r = Run(trained)
    learning_starts = r.read_config().sac.learning_starts
    for ck in r.checkpoints():
        steps = r.checkpoint_steps(ck)
        assert r.read_checkpoint_state(ck)["n_updates"] == max(0, steps - learning_starts), ck.name
