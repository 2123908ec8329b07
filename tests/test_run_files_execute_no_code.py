"""Run folders are data: crafted, pickled or linked-out files in a training run are refused by
``evaluate``, ``report`` and ``train --resume`` before they can run code or write outside the run."""

from __future__ import annotations

import json
import pickle
import shutil

import numpy as np
import pytest

from softcrawl.cli import main
from helpers import Evil, file_tree, one_line_error, rehash


def test_crafted_learner_file_is_refused_by_evaluate_and_resume(run, tmp_path, capsys):
    """A pickle in ``learner.msgpack`` (its checksum updated) is refused, never unpickled."""
    marker = tmp_path / "pwned"
    latest = run / "checkpoints" / (run / "checkpoints" / "latest").read_text().strip()
    (latest / "learner.msgpack").write_bytes(pickle.dumps({"policy": Evil(marker)}))
    rehash(latest)
    rc = main(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"])
    one_line_error(capsys, rc, "learner.msgpack", "refused")
    before = file_tree(run)
    rc = main(["train", "--resume", "--out", str(run), "--no-progress"])
    one_line_error(capsys, rc, "refused")
    rc = main(["report", str(run), "--phases", ""])  # the best design's re-simulation loads the policy
    one_line_error(capsys, rc, "learner.msgpack", "refused")
    assert not marker.exists() and not (tmp_path / "ev").exists()
    assert file_tree(run) == before  # nothing truncated or written, no report


def test_crafted_model_pt_of_the_torch_learner_is_refused(run, tmp_path, capsys):
    """A checkpoint of the torch learner (format 1) whose ``model.pt`` is a pickle that would
    run code (checksums updated) is read by the torch learner with ``weights_only=True`` and
    refused by evaluate, resume and report; nothing is unpickled, nothing written."""
    from softcrawl.codesign.checkpoints import _sha256, checkpoint_files

    marker = tmp_path / "pwned"
    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["rollout"] = "action"  # the torch learner's loop
    (run / "config.json").write_text(json.dumps(cfg))
    for ck in (run / "checkpoints").glob("step-*"):
        (ck / "learner.msgpack").unlink()
        with open(ck / "model.pt", "wb") as f:
            pickle.dump({"policy": Evil(marker)}, f)
        st = json.loads((ck / "state.json").read_text())
        st.update(format=1)
        (ck / "state.json").write_text(json.dumps(st))
        files = {f: _sha256(ck / f) for f in checkpoint_files("torch")}
        (ck / "manifest.json").write_text(json.dumps({"format": 1, "files": files}))
    before = file_tree(run)
    for argv in (["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"],
                 ["train", "--resume", "--out", str(run), "--no-progress"], ["report", str(run), "--phases", ""]):
        one_line_error(capsys, main(argv), "model.pt", "refused")
    assert not marker.exists() and not (tmp_path / "ev").exists()
    assert file_tree(run) == before


def test_pickled_replay_buffer_never_loads(run, tmp_path, capsys):
    """An object array in ``replay_buffer.npz`` (a pickle inside the npz) is refused on resume."""
    marker = tmp_path / "pwned"
    latest = run / "checkpoints" / "step-0000000160"
    with np.load(latest / "replay_buffer.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["rewards"] = np.array([Evil(marker)], dtype=object)
    np.savez(latest / "replay_buffer.npz", **arrays)
    rehash(latest)
    before = file_tree(run)
    one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "cannot restore")
    assert not marker.exists() and file_tree(run) == before


def test_pickled_sampler_state_never_loads(run, tmp_path, capsys):
    """Old-format (pickle) files in a checkpoint are not read, even by ``report --no-simulate``."""
    marker = tmp_path / "pwned"
    for ck in (run / "checkpoints").glob("step-*"):
        with open(ck / "state.pkl", "wb") as f:
            pickle.dump({"sampler": Evil(marker)}, f)
    rc = main(["report", str(run), "--no-simulate"])
    one_line_error(capsys, rc, "no complete checkpoint")
    before = file_tree(run)
    one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "no complete checkpoint")
    rc = main(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"])
    one_line_error(capsys, rc, "no complete checkpoint")
    assert not marker.exists() and file_tree(run) == before


def test_latest_pointer_and_report_stay_inside_the_run(run, tmp_path, capsys):
    from softcrawl.codesign.report import write_report
    from softcrawl.codesign.run import Run

    elsewhere = tmp_path / "elsewhere"
    shutil.copytree(run / "checkpoints" / "step-0000000040", elsewhere)
    (run / "checkpoints" / "latest").write_text("../../elsewhere")
    ck = Run(run).latest_checkpoint()
    assert ck.name == "step-0000000160" and ck.parent == run / "checkpoints"
    assert "not a checkpoint of this run" in capsys.readouterr().err
    outside = tmp_path / "outside"
    outside.mkdir()
    (run / "report").symlink_to(outside)
    with pytest.raises(ValueError, match="link"):
        write_report(run, simulate=False)
    assert list(outside.iterdir()) == []


@pytest.mark.parametrize("entry", ["sessions.csv", "logs", "snapshots"])
def test_run_files_linked_out_of_the_run_are_refused(entry, run, tmp_path, capsys):
    """A crafted run whose logs link elsewhere would make ``train --resume`` append to, rename
    or write files outside the run: refused before anything is read or written."""
    outside = tmp_path / "outside"
    src = run / entry
    shutil.move(src, outside)
    src.symlink_to(outside)
    before = file_tree(outside)
    with open(run / "config.json") as f:  # room to train: the resume would write
        meta = json.load(f)
    meta["config"]["total_steps"] = 200
    (run / "config.json").write_text(json.dumps(meta))
    one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "symbolic link")
    one_line_error(capsys, main(["report", str(run), "--no-simulate"]), "symbolic link")
    assert file_tree(outside) == before and not (run / "report").exists()
