"""Run folders and outputs that cannot hurt or mislead: one regression test per item,
each failing on the code before the fix, and a fuzz test (hypothesis) of the CLI's user inputs:
designs, action CSVs, ``--set`` strings and run folders with missing, corrupt or crafted files."""

from __future__ import annotations

import errno
import json
import os
import pickle
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

from softcrawl.cli import main
from softcrawl.codesign.config import override, preset
from helpers import restored_learner


class Evil:
    """Unpickling this creates ``self.marker``: proof that a file ran code when loaded."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


@pytest.fixture(scope="module")
def trained(tmp_path_factory) -> Path:
    """A finished smoke run (160 steps) with checkpoints at 40, 80, 120, 160 kept, no report."""
    from softcrawl.codesign.training import train

    run = tmp_path_factory.mktemp("trained") / "run"
    cfg = override(preset("smoke"), ["checkpoint_every=40", "keep_checkpoints=4", 'sac.learner="sbx"'])
    train(run, cfg, progress=False)
    return run


@pytest.fixture
def run(trained, tmp_path) -> Path:
    """A private copy of the trained run."""
    dst = tmp_path / "run"
    shutil.copytree(trained, dst, symlinks=True)
    return dst


def _steps(run: Path) -> list[str]:
    return sorted(p.name for p in (run / "checkpoints").iterdir() if p.name.startswith("step-"))


def _rehash(ck: Path) -> None:
    """Recompute a checkpoint's manifest (a crafted folder can do that too)."""
    from softcrawl.codesign.run import _sha256

    m = json.loads((ck / "manifest.json").read_text())
    m["files"] = {f: _sha256(ck / f) for f in m["files"]}
    (ck / "manifest.json").write_text(json.dumps(m))


def _tree(root: Path) -> dict:
    return {str(p.relative_to(root)): (p.stat().st_size if p.is_file() else -1) for p in root.rglob("*")}


def _one_line_error(capsys, rc: int, *needles: str) -> str:
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "\n" not in err and "Traceback" not in err, err
    for n in needles:
        assert n in err, err
    return err


# -- 1: no code execution from run files ---------------------------------------------------------------
def test_1_crafted_learner_file_is_refused_by_evaluate_and_resume(run, tmp_path, capsys):
    """A pickle in ``learner.msgpack`` (its checksum updated) is refused, never unpickled."""
    marker = tmp_path / "pwned"
    latest = run / "checkpoints" / (run / "checkpoints" / "latest").read_text().strip()
    (latest / "learner.msgpack").write_bytes(pickle.dumps({"policy": Evil(marker)}))
    _rehash(latest)
    rc = main(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"])
    _one_line_error(capsys, rc, "learner.msgpack", "refused")
    before = _tree(run)
    rc = main(["train", "--resume", "--out", str(run), "--no-progress"])
    _one_line_error(capsys, rc, "refused")
    rc = main(["report", str(run), "--phases", ""])  # the best design's re-simulation loads the policy
    _one_line_error(capsys, rc, "learner.msgpack", "refused")
    assert not marker.exists() and not (tmp_path / "ev").exists()
    assert _tree(run) == before  # nothing truncated or written, no report


def test_1_crafted_model_pt_of_the_torch_learner_is_refused(run, tmp_path, capsys):
    """A checkpoint of the torch learner (format 1) whose ``model.pt`` is a pickle that would
    run code (checksums updated) is read by the torch learner with ``weights_only=True`` and
    refused by evaluate, resume and report; nothing is unpickled, nothing written."""
    from softcrawl.codesign.run import _sha256

    marker = tmp_path / "pwned"
    for ck in (run / "checkpoints").glob("step-*"):
        (ck / "learner.msgpack").unlink()
        with open(ck / "model.pt", "wb") as f:
            pickle.dump({"policy": Evil(marker)}, f)
        st = json.loads((ck / "state.json").read_text())
        st.update(format=1)
        (ck / "state.json").write_text(json.dumps(st))
        files = {f: _sha256(ck / f) for f in ("model.pt", "replay_buffer.npz", "state.json")}
        (ck / "manifest.json").write_text(json.dumps({"format": 1, "files": files}))
    before = _tree(run)
    for argv in (["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"],
                 ["train", "--resume", "--out", str(run), "--no-progress"], ["report", str(run), "--phases", ""]):
        _one_line_error(capsys, main(argv), "model.pt", "refused")
    assert not marker.exists() and not (tmp_path / "ev").exists()
    assert _tree(run) == before


def test_1_pickled_replay_buffer_never_loads(run, tmp_path, capsys):
    """An object array in ``replay_buffer.npz`` (a pickle inside the npz) is refused on resume."""
    marker = tmp_path / "pwned"
    latest = run / "checkpoints" / "step-0000000160"
    with np.load(latest / "replay_buffer.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["rewards"] = np.array([Evil(marker)], dtype=object)
    np.savez(latest / "replay_buffer.npz", **arrays)
    _rehash(latest)
    before = _tree(run)
    _one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "cannot restore")
    assert not marker.exists() and _tree(run) == before


def test_1_pickled_sampler_state_never_loads(run, tmp_path, capsys):
    """Old-format (pickle) files in a checkpoint are not read, even by ``report --no-simulate``."""
    marker = tmp_path / "pwned"
    for ck in (run / "checkpoints").glob("step-*"):
        with open(ck / "state.pkl", "wb") as f:
            pickle.dump({"sampler": Evil(marker)}, f)
    rc = main(["report", str(run), "--no-simulate"])
    _one_line_error(capsys, rc, "no complete checkpoint")
    before = _tree(run)
    _one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "no complete checkpoint")
    rc = main(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"])
    _one_line_error(capsys, rc, "no complete checkpoint")
    assert not marker.exists() and _tree(run) == before


def test_1_latest_pointer_and_report_stay_inside_the_run(run, tmp_path, capsys):
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
def test_1_run_files_linked_out_of_the_run_are_refused(entry, run, tmp_path, capsys):
    """A crafted run whose logs link elsewhere would make ``train --resume`` append to, rename
    or write files outside the run: refused before anything is read or written."""
    outside = tmp_path / "outside"
    src = run / entry
    shutil.move(src, outside)
    src.symlink_to(outside)
    before = _tree(outside)
    with open(run / "config.json") as f:  # room to train: the resume would write
        meta = json.load(f)
    meta["config"]["total_steps"] = 200
    (run / "config.json").write_text(json.dumps(meta))
    _one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "symbolic link")
    _one_line_error(capsys, main(["report", str(run), "--no-simulate"]), "symbolic link")
    assert _tree(outside) == before and not (run / "report").exists()


# -- 2: resume never loses history ------------------------------------------------------------------
def test_2_dangling_latest_resumes_from_newest_complete_checkpoint(run):
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


def test_2_a_run_resumed_at_an_episode_boundary_is_the_uninterrupted_run(trained, run):
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


def test_2_malformed_next_designs_are_refused(run, capsys):
    """A checkpoint whose ``next_designs`` are not designs is not restorable: one clear line."""
    ck = run / "checkpoints" / "step-0000000160"
    st = json.loads((ck / "state.json").read_text())
    st["next_designs"] = [[9, 9, 9, 9, 9, 9, 9, 9], [1, 0, 0, 2, 2, 0, 0, 0]]
    (ck / "state.json").write_text(json.dumps(st))
    _rehash(ck)
    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["total_steps"] = 200
    (run / "config.json").write_text(json.dumps(cfg))
    _one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]), "malformed")


def test_2_no_complete_checkpoint_refuses_and_keeps_everything(run):
    from softcrawl.codesign.run import latest_checkpoint
    from softcrawl.codesign.training import train

    (run / "checkpoints" / "latest").unlink()
    assert latest_checkpoint(run).name == "step-0000000160"  # missing pointer: newest complete one
    for ck in (run / "checkpoints").glob("step-*"):
        (ck / "manifest.json").unlink()
    before = _tree(run)
    with pytest.raises(ValueError, match="no complete checkpoint"):
        train(run, resume=True, progress=False)
    assert _tree(run) == before


# -- 3: damaged latest checkpoint, disk full ---------------------------------------------------------
def test_3_corrupt_latest_falls_back_to_the_previous_one(run, capsys):
    from softcrawl.codesign.run import Run

    model = run / "checkpoints" / "step-0000000160" / "learner.msgpack"
    data = bytearray(model.read_bytes())
    data[len(data) // 2] ^= 0xFF
    model.write_bytes(bytes(data))
    assert Run(run).latest_checkpoint().name == "step-0000000120"
    assert "damaged" in capsys.readouterr().err


def test_3_disk_full_while_checkpointing_keeps_the_previous_latest(run, monkeypatch):
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


def test_3_full_disk_at_a_checkpoint_keeps_it_elsewhere_and_resume_uses_it(run, tmp_path, monkeypatch, capsys):
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
    err = _one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]),
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


# -- 4: checkpoints hold the step's gradient updates -----------------------------------------------
def test_4_checkpoints_are_written_after_the_gradient_updates(trained):
    from softcrawl.codesign.run import Run

    r = Run(trained)
    learning_starts = r.read_config().sac.learning_starts
    for ck in r.checkpoints():
        steps = r.checkpoint_steps(ck)
        assert r.read_checkpoint_state(ck)["n_updates"] == max(0, steps - learning_starts), ck.name


# -- 5: outputs checked before the work, kept on a full disk, overwrite only softcrawl's ----------------
def test_5_output_paths_are_checked_before_simulating(tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    def never(*a, **k):
        raise AssertionError("the model was built before the output was checked")

    monkeypatch.setattr(sim, "build_robot", never)
    monkeypatch.chdir(tmp_path)
    _one_line_error(capsys, main(["simulate", "--duration", "0.01", "--out", ".", "--no-progress"]), "not the current")
    (tmp_path / "file").write_text("x")
    rc = main(["simulate", "--duration", "0.01", "--out", str(tmp_path / "file" / "out"), "--no-progress"])
    _one_line_error(capsys, rc, "not a directory")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("years of work")
    rc = main(["simulate", "--duration", "0.01", "--out", str(foreign), "--overwrite", "--no-progress"])
    _one_line_error(capsys, rc, "not a softcrawl output")
    assert (foreign / "thesis.tex").read_text() == "years of work"
    rc = main(["train", "--preset", "smoke", "--out", str(tmp_path / "file")])
    _one_line_error(capsys, rc, "not a directory")
    before = _tree(tmp_path)
    rc = main(["simulate", "--duration", "0.01", "--out", ".", "--overwrite", "--no-progress"])
    _one_line_error(capsys, rc, "not the current")  # --overwrite never replaces the working directory
    assert _tree(tmp_path) == before


def test_5_sweep_and_evaluate_check_their_output_first(tmp_path, monkeypatch, capsys):
    import softcrawl.codesign.evaluation as evaluation
    import softcrawl.robot.sweep as sweep

    def never(*a, **k):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(sweep, "_robot", never)
    monkeypatch.setattr(evaluation, "evaluate_policy", never)
    (tmp_path / "file").write_text("x")
    bad = str(tmp_path / "file" / "out")
    _one_line_error(capsys, main(["sweep-phase", "--phases", "0", "--out", bad, "--no-progress"]), "not a directory")
    rc = main(["evaluate", str(tmp_path), "--design", "1,0,0,2,2,0,0,0", "--out", bad, "--no-progress"])
    _one_line_error(capsys, rc, "not a directory")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    rc = main(["sweep-phase", "--phases", "0", "--out", str(foreign), "--overwrite", "--no-progress"])
    _one_line_error(capsys, rc, "not a softcrawl output")
    if os.geteuid() != 0:  # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        rc = main(["sweep-phase", "--phases", "0", "--out", str(locked / "out"), "--no-progress"])
        _one_line_error(capsys, rc, "not writable")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["file", "mine"] + (["locked"] if os.geteuid() else []))


def _no_space(*a, **k):
    raise OSError(errno.ENOSPC, "No space left on device")


def _kept_and_rescued(err: str) -> tuple[Path, Path]:
    """The folders a full-disk error names: ``kept in X`` (next to --out) and ``saved in Y``."""
    import re

    kept = re.search(r"kept in (\S+?);", err)
    saved = re.search(r"saved in (\S+?)(;|$)", err)
    return (Path(kept.group(1)) if kept else None), (Path(saved.group(1)) if saved else None)


def test_5_full_disk_after_simulating_keeps_the_result(tmp_path, monkeypatch, capsys):
    """``simulate``: ENOSPC while writing the ParaView frames (after the run) keeps what was
    written next to --out and saves summary + trajectory in the system's temp dir."""
    import softcrawl.robot.output as output

    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    monkeypatch.setattr(output, "write_paraview", _no_space)
    out = tmp_path / "sim"
    rc = main(["simulate", "--duration", "0.05", "--out", str(out), "--no-progress"])
    err = _one_line_error(capsys, rc, "No space left on device")
    kept, saved = _kept_and_rescued(err)
    assert kept.parent == tmp_path and saved.parent == systmp and not out.exists()
    for folder in (kept, saved):
        assert json.loads((folder / "summary.json").read_text())["steps"] == 5
        assert np.load(folder / "trajectory.npz")["t"].shape == (6,)


def test_5_read_only_file_system_still_saves_the_result(tmp_path, monkeypatch, capsys):
    """EROFS: not even the staging folder next to --out can be made; the results are saved in
    the system's temp dir, named in the one-line error."""
    import softcrawl.robot.output as output

    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    mkdtemp = tempfile.mkdtemp

    def read_only(*a, dir=None, **k):
        if dir is not None and Path(dir) == tmp_path:
            raise OSError(errno.EROFS, "Read-only file system")
        return mkdtemp(*a, dir=dir, **k)

    monkeypatch.setattr(output.tempfile, "mkdtemp", read_only)
    rc = main(["simulate", "--duration", "0.05", "--out", str(tmp_path / "sim"), "--no-progress"])
    err = _one_line_error(capsys, rc, "Read-only file system")
    kept, saved = _kept_and_rescued(err)
    assert kept is None and saved.parent == systmp and (saved / "trajectory.csv").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["systmp"]


def test_5_full_disk_after_a_sweep_keeps_every_phase(tmp_path, monkeypatch, capsys):
    """``sweep-phase``: a phase that cannot be saved and a full disk at the end lose nothing:
    sweep.json with every phase in the rescue folder, the saved phases in ``<out>.partial``."""
    import softcrawl.robot.sweep as sweep

    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    save = sweep._save_phase

    def save_but_90(work, r):
        if r.phase_deg == 90:
            _no_space()
        save(work, r)

    monkeypatch.setattr(sweep, "_save_phase", save_but_90)
    monkeypatch.setattr(sweep, "plot_reward_vs_phase", _no_space)
    out = tmp_path / "sweep"
    rc = main(["sweep-phase", "--phases", "0,90", "--duration", "0.05", "--workers", "1", "--out", str(out),
               "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 2 and "cannot save finished phases" in err[0] and "Traceback" not in err[1]
    kept, saved = _kept_and_rescued(err[1])
    assert "1 finished phase(s) are also kept in" in err[1] and str(out) + ".partial" in err[1]
    assert [p["phase_deg"] for p in json.loads((saved / "sweep.json").read_text())["phases"]] == [0, 90]
    assert (kept / "sweep.csv").exists() and not out.exists()
    assert [p.name for p in (tmp_path / "sweep.partial" / "partial").iterdir()] == ["phase_0.0.json"]


def test_5_full_disk_after_evaluating_keeps_the_evaluation(run, tmp_path, monkeypatch, capsys):
    """``evaluate``: evaluation.json and actions.csv are written with the rest, so a full disk
    keeps (and rescues) them too."""
    import softcrawl.robot.output as output

    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    monkeypatch.setattr(output, "write_paraview", _no_space)
    rc = main(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"])
    kept, saved = _kept_and_rescued(_one_line_error(capsys, rc, "No space left on device"))
    for folder in (kept, saved):
        assert json.loads((folder / "evaluation.json").read_text())["design"] == [1, 0, 0, 2, 2, 0, 0, 0]
        assert (folder / "actions.csv").read_text().startswith("p1,p2,p3")
    assert not (tmp_path / "ev").exists()


def test_5_full_disk_keeps_what_was_written(tmp_path):
    from softcrawl.robot.output import OUTPUT_MARKER, OutputWriteError, staged_directory

    out = tmp_path / "out"
    with pytest.raises(OutputWriteError) as info, staged_directory(out) as tmp:
        (tmp / "trajectory.npz").write_bytes(b"computed")
        raise OSError(errno.ENOSPC, "No space left on device")
    kept = Path(str(info.value).rsplit(" ", 1)[-1])
    assert (kept / "trajectory.npz").read_bytes() == b"computed" and not out.exists()
    with staged_directory(out) as tmp:
        (tmp / "a").write_text("1")
    assert (out / OUTPUT_MARKER).exists()
    with staged_directory(out, overwrite=True) as tmp:  # softcrawl's own output may be replaced
        (tmp / "b").write_text("2")
    assert (out / "b").exists() and not (out / "a").exists()


def test_5_report_is_staged_and_swapped_in(run, monkeypatch):
    import softcrawl.codesign.report as rep

    rep.write_report(run, simulate=False)
    summary = (run / "report" / "summary.md").read_text()
    (run / ".report.partial-stale").mkdir()

    def boom(*a, **k):
        raise RuntimeError("killed half-way")

    monkeypatch.setattr(rep, "_write_report", boom)
    with pytest.raises(RuntimeError):
        rep.write_report(run, simulate=False)
    assert (run / "report" / "summary.md").read_text() == summary
    assert not list(run.glob(".report.*"))


# -- 6: a failed start does not block its retry; --set values are type-checked ----------------------
def test_6_failed_start_writes_no_config(tmp_path, monkeypatch):
    import softcrawl.codesign.training as training

    def broken(*a, **k):
        raise RuntimeError("envs could not be built")

    monkeypatch.setattr(training, "make_vec_env", broken)
    with pytest.raises(RuntimeError):
        training.train(tmp_path / "run", preset("smoke"), progress=False)
    assert not (tmp_path / "run" / "config.json").exists()
    from softcrawl.cli.train import _check_out

    _check_out(str(tmp_path / "run"))  # the same --out is accepted again


def test_6_bad_reduction_fails_before_the_run_starts(tmp_path):
    from softcrawl.codesign.training import train

    (tmp_path / "bad.npz").write_bytes(b"not a reduction")
    with pytest.raises(ValueError, match="bad.npz"):
        train(tmp_path / "run", override(preset("smoke"), [f'env.reduction="{tmp_path / "bad.npz"}"']), progress=False)
    assert not (tmp_path / "run" / "config.json").exists()


def _no_gpu(monkeypatch, gpus=()):
    """JAX as a CPU-only jaxlib sees it (``gpus``: the GPUs it would see instead)."""
    import jax

    cpu = jax.devices("cpu")

    def devices(backend=None):
        if backend == "cpu":
            return cpu
        if not gpus:
            raise RuntimeError(f"Unknown backend: '{backend}' requested")
        return list(gpus)

    monkeypatch.setattr(jax, "devices", devices)


def test_6_a_gpu_jax_cannot_use_fails_before_the_run_starts(tmp_path, monkeypatch):
    from softcrawl.codesign.training import train

    _no_gpu(monkeypatch)
    with pytest.raises(ValueError, match="sac.device='gpu:1'.*sees no GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="gpu:1"', 'sac.learner="sbx"']), progress=False)
    assert not (tmp_path / "run").exists()
    _no_gpu(monkeypatch, gpus=["gpu0"])
    with pytest.raises(ValueError, match="sees 1 GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="cuda:1"', 'sac.learner="sbx"']), progress=False)
    assert not (tmp_path / "run").exists()


def test_6_a_gpu_torch_cannot_use_fails_before_the_run_starts(tmp_path, monkeypatch):
    import torch

    from softcrawl.codesign.training import train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="sac.device='cuda:1'.*no CUDA GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="gpu:1"', 'sac.learner="torch"']),
              progress=False)
    assert not (tmp_path / "run").exists()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match="sees 1 CUDA GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="cuda:1"', 'sac.learner="torch"']),
              progress=False)
    assert not (tmp_path / "run").exists()


def test_6_a_run_trained_on_a_gpu_is_evaluated_on_the_cpu(run, monkeypatch):
    from softcrawl.codesign.evaluation import evaluate_policy

    on_cpu = evaluate_policy(run, "1,0,0,2,2,0,0,0").returns_cm
    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["sac"]["device"] = "gpu"
    (run / "config.json").write_text(json.dumps(cfg))
    _no_gpu(monkeypatch)
    assert evaluate_policy(run, "1,0,0,2,2,0,0,0").returns_cm == on_cpu


@pytest.mark.parametrize("setting, key", [('sac.batch_size="64"', "sac.batch_size"), ("n_envs=2.5", "n_envs"),
                                          ("env.observe_state=1", "env.observe_state"), ("env.legs=3", "env.legs"),
                                          ("sac.net_arch=[0]", "sac.net_arch"), ("sac.batch_size=5000", "batch_size"),
                                          ("sac.net_arch=[64, true]", "sac.net_arch"),
                                          ("keep_checkpoints=1", "keep_checkpoints")])
def test_6_set_values_are_checked_against_the_fields(setting, key, tmp_path, capsys):
    rc = main(["train", "--preset", "smoke", "--out", str(tmp_path / "r"), "--set", setting])
    _one_line_error(capsys, rc, key)
    assert not (tmp_path / "r").exists()


# -- 7: options that would be ignored are errors ----------------------------------------------------
def test_7_ignored_options_are_errors(trained, tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: pytest.fail("model built"))
    before = _tree(trained)
    _one_line_error(capsys, main(["train", "--resume", "--preset", "smoke", "--out", str(trained)]), "--preset")
    assert _tree(trained) == before
    rc = main(["simulate", "--model", "full", "--reduction", "x.npz", "--out", str(tmp_path / "o"), "--no-progress"])
    _one_line_error(capsys, rc, "--reduction")
    with pytest.raises(ValueError, match="env.reduction"):
        override(preset("smoke"), ['env.model="full"', 'env.reduction="x.npz"'])


# -- 8: reduction metadata is checksummed and checked -------------------------------------------------
def _shipped():
    import softcrawl.reduction.data as data

    return Path(data.__file__).parent / "pneunet_6mm.npz"


def _rewrite(path: Path, edit) -> None:
    with np.load(_shipped(), allow_pickle=False) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(arrays.pop("metadata").tobytes().decode())
    meta = edit(meta, arrays)
    np.savez(path, metadata=np.frombuffer(json.dumps(meta).encode(), np.uint8), **arrays)


def test_8_reduction_metadata_is_covered_and_checked(tmp_path):
    from softcrawl.reduction.artifact import ReductionFileError, _checksum, _metadata_checksum, load_reduction

    def heavier(meta, arrays):
        meta["valid_for"]["leg_mass"] = 1.0  # the reduction would then load for another model
        return meta

    _rewrite(tmp_path / "a.npz", heavier)
    with pytest.raises(ReductionFileError, match="metadata"):
        load_reduction(tmp_path / "a.npz")

    def rigid(meta, arrays):
        arrays["leg__n_rigid"] = np.array(40)
        meta["parts"]["leg"]["n_rigid"] = 40
        meta["checksum"] = _checksum(arrays)
        meta["metadata_checksum"] = _metadata_checksum(meta)
        return meta

    _rewrite(tmp_path / "b.npz", rigid)
    with pytest.raises(ReductionFileError, match="n_rigid"):
        load_reduction(tmp_path / "b.npz")
    _rewrite(tmp_path / "c.npz", lambda meta, arrays: [meta])
    with pytest.raises(ReductionFileError, match="not a JSON object"):
        load_reduction(tmp_path / "c.npz")
    with pytest.raises(ReductionFileError, match="directory"):
        load_reduction(tmp_path)
    load_reduction(_shipped())  # the shipped file stays valid


# -- 9: user mistakes are one-line errors -----------------------------------------------------------
def test_9_user_mistakes_are_one_line_errors(run, tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: pytest.fail("model built"))
    rc = main(["simulate", "--duration", "1e12", "--out", str(tmp_path / "o"), "--no-progress"])
    _one_line_error(capsys, rc, "--duration", "3600")
    with open(run / "episodes.csv", "a") as f:
        f.write("120,not-a-design,1.0,0\n")
    rc = main(["report", str(run), "--no-simulate"])
    _one_line_error(capsys, rc, "episodes.csv, line 9")
    for ck in (run / "checkpoints").glob("step-*"):
        (ck / "state.pkl").write_bytes(b"")
    _one_line_error(capsys, main(["report", str(run), "--no-simulate"]), "no complete checkpoint")
    _one_line_error(capsys, main(["simulate", "--reduction", str(tmp_path), "--out", str(tmp_path / "o"),
                                  "--no-progress", "--duration", "0.01"]), "directory")
    rc = main(["sweep-phase", "--duration", "1e12", "--out", str(tmp_path / "o"), "--no-progress"])
    _one_line_error(capsys, rc, "--duration", "3600")
    (tmp_path / "file").write_text("x")
    _one_line_error(capsys, main(["train", "--out", str(tmp_path / "file")]), "not a directory")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text, where", [("p1,p2,p3\n10,20,30\n\n10,20,300\n", "a.csv, line 4, p3: 300 kPa"),
                                         ("10,20,30\n1,2\n", "a.csv, line 2: expected 3 columns"),
                                         ("0,0,0\n0,nan,0\n", "a.csv, line 2, p2: nan kPa is not finite"),
                                         ("0,0,0\n0,0,x\n", "a.csv, line 2: non-numeric")])
def test_9_action_csv_errors_name_the_file_and_line(text, where, tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: pytest.fail("model built"))
    (tmp_path / "a.csv").write_text(text)
    rc = main(["simulate", "--actions", str(tmp_path / "a.csv"), "--out", str(tmp_path / "o"), "--no-progress"])
    _one_line_error(capsys, rc, where)


def test_9_run_file_errors_name_the_file_and_line(run, tmp_path, capsys):
    from softcrawl.codesign.run import Run

    latest = run / "checkpoints" / "step-0000000160"
    (latest / "state.json").write_bytes(b"")  # an empty state file, checksummed: malformed, not a traceback
    _rehash(latest)
    _one_line_error(capsys, main(["report", str(run), "--no-simulate"]), "state.json: malformed")
    with open(run / "sessions.csv", "a") as f:
        f.write("160,oops\n")
    with pytest.raises(ValueError, match=r"sessions\.csv, line 2: not a session row"):
        Run(run).wall_seconds()
    with open(run / "episodes.csv", "a") as f:
        f.write("1x0,01200000,1.0,0\n")
    with pytest.raises(ValueError, match=r"episodes\.csv, line 9: not a row of this run"):
        Run(run).forget_after(120)  # resume bookkeeping: refuses, changes nothing
    assert len((run / "episodes.csv").read_text().splitlines()) == 9


def test_9_an_unfinished_last_row_is_not_an_error(run, capsys):
    """A writer killed mid-row (or a full disk) leaves a last line without newline: the report
    leaves it out with a note, and resume drops it with the rest after the checkpoint."""
    from softcrawl.codesign.run import Run

    with open(run / "episodes.csv", "a") as f:
        f.write("16")  # of "160,0120...": its t would read as 16
    assert main(["report", str(run), "--no-simulate"]) == 0
    assert "episodes.csv, line 9: unfinished last row" in capsys.readouterr().err
    Run(run).forget_after(160)
    assert (run / "episodes.csv").read_text().splitlines()[-1].startswith("160,")


def test_9_directory_as_the_training_reduction(tmp_path, capsys):
    rc = main(["train", "--preset", "smoke", "--out", str(tmp_path / "r"), "--no-progress",
               "--set", f'env.reduction="{tmp_path}"'])
    _one_line_error(capsys, rc, "is a directory")
    assert not (tmp_path / "r" / "config.json").exists()


def test_9_damaged_snapshot_is_left_out_of_the_report(run, capsys):
    """Found by the fuzz test: an empty snapshot file raised EOFError out of ``report``."""
    (run / "snapshots" / "t-0000000040.npz").write_bytes(b"")
    assert main(["report", str(run), "--no-simulate"]) == 0
    assert "t-0000000040.npz: not a design-distribution snapshot" in capsys.readouterr().err
    assert (run / "report" / "reward_histogram.png").exists()


def test_9_ctrl_c_is_a_clean_stop(tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: object())

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "run_episode", interrupted)
    rc = main(["simulate", "--duration", "0.01", "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 130 and "\n" not in err and "interrupted" in err and str(tmp_path / "o") in err


def test_9_ctrl_c_in_train_and_sweep_names_what_is_kept(tmp_path, monkeypatch, capsys):
    import softcrawl.cli.sweep as sweep_cli
    import softcrawl.cli.train as train_cli

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(train_cli, "train_and_report", interrupted)
    monkeypatch.setattr(sweep_cli, "run_sweep", interrupted)
    out = tmp_path / "r"
    assert main(["train", "--preset", "smoke", "--out", str(out), "--no-progress"]) == 130
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "interrupted" in err and f"softcrawl train --resume --out {out}" in err
    assert main(["sweep-phase", "--phases", "0", "--out", str(out), "--no-progress"]) == 130
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "interrupted" in err and f"{out}.partial" in err


_POOL_SCRIPT = """
import sys, time
from pathlib import Path
from softcrawl.parallel import run_pool

def task(flag):
    from tqdm.auto import tqdm
    tqdm(total=1, disable=True)  # its default lock is a named semaphore
    Path(flag).touch()
    time.sleep(60)

if __name__ == "__main__":
    try:
        run_pool(task, 2, [(sys.argv[1] + str(i),) for i in range(2)], print)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
"""


def test_9_ctrl_c_stops_worker_processes_cleanly(tmp_path):
    """Ctrl-C reaches every process of the terminal's group: the sweep's (and the report's,
    the reduction build's) workers must not print tracebacks or leak semaphores."""
    import signal
    import subprocess
    import sys
    import time

    (tmp_path / "pool.py").write_text(_POOL_SCRIPT)
    # a terminal's Ctrl-C: SIGINT at its default even when the test suite itself runs as a background
    # job of a non-interactive shell (which ignores SIGINT, and exec keeps that)
    proc = subprocess.Popen([sys.executable, str(tmp_path / "pool.py"), str(tmp_path / "started-")],
                            cwd=tmp_path, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while len(list(tmp_path.glob("started-*"))) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(list(tmp_path.glob("started-*"))) == 2, "workers did not start"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130 and err.strip() == "interrupted", err


# -- 10: the tests keep to their temp dirs ----------------------------------------------------------
def test_10_tests_write_only_into_temp_dirs(tmp_path, monkeypatch):
    import pwd

    import gmsh

    from softcrawl.geometry.io import cache_dir, cached_mesh
    from softcrawl.geometry.mesh import TetMesh
    from softcrawl.geometry.primitives import occ_tet_mesh

    real_home = Path(pwd.getpwuid(os.getuid()).pw_dir).resolve()
    home = Path(os.environ["HOME"]).resolve()
    assert home != real_home and home.is_relative_to(Path(tempfile.gettempdir()).resolve())
    cache = Path(os.environ["SOFTCRAWL_CACHE_DIR"]).resolve()
    assert not cache.is_relative_to(real_home / ".cache")

    # gmsh writes FLTK preferences into $HOME at every initialise: into the session's HOME
    prefs = real_home / ".fltk" / "fltk.org" / "fltk.prefs"
    stamp = prefs.stat().st_mtime_ns if prefs.exists() else None

    def box():
        gmsh.model.occ.addBox(0, 0, 0, 10, 10, 10)
        gmsh.model.occ.synchronize()

    params = {"box": 10, "test": tmp_path.name}

    def build():
        points, tets = occ_tet_mesh("box", box, 5.0)
        return TetMesh(points, tets, {}, {}, params)

    cached_mesh("issue20-box", params, build)
    assert (prefs.stat().st_mtime_ns if prefs.exists() else None) == stamp
    assert (home / ".fltk").exists()
    # the mesh cache entry went into the session's cache
    assert cache_dir().resolve() == cache and list(cache.glob("issue20-box-*.vtu"))
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.config import SACConfig
    from softcrawl.codesign.sac import make_sac

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    model = make_sac(DummyVecEnv([lambda: gym.make("Pendulum-v1")]),
                     SACConfig(learning_starts=5, batch_size=4, buffer_size=50, net_arch=(8,)))
    model.learn(10)
    assert not list(tmp_path.glob("SB3-*"))


# -- fuzz: the CLI's user inputs ------------------------------------------------------------------
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


class _Reached(BaseException):
    """The input was accepted and the expensive work was about to start (stopped here)."""


def _stop(*a, **k):
    raise _Reached


def _check_cli(capsys, argv, root: Path, out: Path | None) -> int | None:
    """Run ``main(argv)``; a refusal must be exit code 2 with one line and no traceback, and
    nothing outside ``out`` may be created or deleted. Returns the exit code (None: accepted)."""
    keep = (lambda rel: out is None or not (root / rel).resolve().is_relative_to(out.resolve()))
    before = {k: v for k, v in _tree(root).items() if keep(k)}
    try:
        rc = main([str(a) for a in argv])
    except _Reached:
        rc = None
    except SystemExit as exc:  # argparse: a malformed command line
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    if rc not in (None, 0):
        assert rc == 2 and err and "\n" not in err, (rc, err)
    after = {k: v for k, v in _tree(root).items() if keep(k)}
    assert set(after) == set(before), set(after) ^ set(before)
    return rc


_DESIGN = st.one_of(st.text(alphabet="0123,- x9.", max_size=24),
                    st.lists(st.integers(-2, 5), max_size=10).map(lambda v: ",".join(map(str, v))))
_CSV = st.text(alphabet="0123456789.,-+e \n#abp", max_size=80)
_KEYS = ["n_envs", "total_steps", "seed", "backend", "sac.batch_size", "sac.net_arch", "sac.gamma", "env.legs",
         "env.model", "env.dt", "env.observe_state", "env.reduction", "design.untried", "nope", "sac", "env.nope"]
_VALUES = st.one_of(st.sampled_from(["0", "-1", "1e9", "[0]", "[]", "[3,7]", "true", "null", '"x"', "1.5", "{}",
                                     "[64, true]", "nan", '"ray"', "", "=", "[[1]]"]),
                    st.text(alphabet='0123456789[]{}",.-aetrun', max_size=12))


@settings(max_examples=60, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(design=_DESIGN, csv_text=st.one_of(st.none(), _CSV),
       duration=st.sampled_from(["0.01", "-1", "nan", "1e12", "x"]))
def test_fuzz_simulate_inputs(design, csv_text, duration, monkeypatch_module, capsys):
    import softcrawl.cli.simulate as sim
    from softcrawl.design.space import validate_design
    from softcrawl.gaits import read_actions_csv

    monkeypatch_module.setattr(sim, "build_robot", _stop)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        argv = ["simulate", f"--design={design}", f"--duration={duration}", "--out", root / "out", "--no-progress"]
        if csv_text is not None:
            (root / "a.csv").write_text(csv_text)
            argv += ["--actions", root / "a.csv"]
        rc = _check_cli(capsys, argv, root, root / "out")
        if rc is None:  # accepted: then every input was valid
            validate_design(design)
            if csv_text is not None:
                read_actions_csv(root / "a.csv")
        assert not (root / "out").exists()


@settings(max_examples=60, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(sets=st.lists(st.tuples(st.sampled_from(_KEYS), _VALUES).map(lambda kv: f"{kv[0]}={kv[1]}"), min_size=1,
                     max_size=3))
def test_fuzz_train_set_strings(sets, monkeypatch_module, capsys):
    import softcrawl.cli.train as train_cli

    monkeypatch_module.setattr(train_cli, "train_and_report", _stop)
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        argv = ["train", "--preset", "smoke", "--out", root / "run"]
        for s_ in sets:
            argv += ["--set", s_]
        rc = _check_cli(capsys, argv, root, root / "run")
        if rc is None:
            override(preset("smoke"), sets)  # accepted only if valid
        assert not (root / "run").exists()


_RUN_FILES = ["config.json", "episodes.csv", "sessions.csv", "distribution.csv", "checkpoints/latest",
              "checkpoints/LATEST/state.json", "checkpoints/LATEST/manifest.json", "checkpoints/LATEST/learner.msgpack",
              "checkpoints/LATEST/replay_buffer.npz", "checkpoints/LATEST", "checkpoints", "snapshots/t-0000000040.npz",
              "snapshots", "logs", "report"]
_DAMAGE = ["delete", "empty", "garbage", "crafted", "flip", "link-out", "json-list"]


@settings(max_examples=25, deadline=None, database=None, derandomize=True,
          suppress_health_check=list(HealthCheck))
@given(damage=st.lists(st.tuples(st.sampled_from(_RUN_FILES), st.sampled_from(_DAMAGE)), min_size=1, max_size=3),
       command=st.sampled_from(["report", "evaluate", "resume"]), noise=st.binary(min_size=1, max_size=64))
def test_fuzz_run_folders(trained, damage, command, noise, monkeypatch_module, capsys):
    import softcrawl.cli.train as train_cli
    import softcrawl.codesign.factory as factory

    monkeypatch_module.setattr(factory, "env_fn", _stop)  # evaluate: stop once the policy is loaded
    monkeypatch_module.setattr(train_cli, "train_and_report", _stop)  # resume: stop before training
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        run = root / "run"
        shutil.copytree(trained, run, symlinks=True)
        marker, outside = root / "pwned", root / "outside"
        outside.mkdir()
        (outside / "keep.txt").write_text("not yours")
        for rel, how in damage:
            p = run / rel.replace("LATEST", "step-0000000160")
            if any(q.is_symlink() for q in p.parents if q.is_relative_to(run)) or not p.parent.is_dir():
                continue  # an earlier damage removed or linked away its folder
            if how == "link-out":
                shutil.rmtree(p, ignore_errors=True) if p.is_dir() and not p.is_symlink() else p.unlink(missing_ok=True)
                p.symlink_to(outside)
            elif p.is_symlink():
                continue  # damaged through the link would be the test's own write outside the run
            elif p.is_dir():
                if how == "delete":
                    shutil.rmtree(p)
            elif how == "delete":
                p.unlink(missing_ok=True)
            elif how == "empty":
                p.write_bytes(b"")
            elif how == "garbage":
                p.write_bytes(noise)
            elif how == "json-list":
                p.write_text("[1, 2]")
            elif how == "crafted":
                p.write_bytes(pickle.dumps({"policy": Evil(marker)}))
            elif how == "flip" and p.is_file() and p.stat().st_size:
                data = bytearray(p.read_bytes())
                data[noise[0] % len(data)] ^= 0xFF
                p.write_bytes(bytes(data))
        argv = {"report": ["report", run, "--no-simulate"],
                "evaluate": ["evaluate", run, "--design", "1,0,0,2,2,0,0,0", "--out", root / "ev", "--no-progress"],
                "resume": ["train", "--resume", "--out", run, "--no-progress"]}[command]
        out = run / "report" if command == "report" else root / "ev" if command == "evaluate" else None

        def outside_report(tree: dict) -> dict:  # report writes report/ (staged in .report.partial-*) only
            return {k: v for k, v in tree.items() if command != "report" or not k.startswith(("report", ".report."))}

        before_run = outside_report(_tree(run))
        try:
            rc = main([str(a) for a in argv])
        except _Reached:
            rc = None
        err = capsys.readouterr().err.strip()
        assert "Traceback" not in err, err
        if rc not in (None, 0):  # notes ("softcrawl: ...", e.g. a checkpoint fallback) may precede the error
            errors = [line for line in err.splitlines() if not line.startswith("softcrawl: ")]
            assert rc == 2 and len(errors) == 1 and ": error: " in errors[0], (rc, err)
        assert not marker.exists(), "a run file ran code"
        assert [p.name for p in outside.iterdir()] == ["keep.txt"]
        assert outside_report(_tree(run)) == before_run
        if out is not None and command == "evaluate":
            assert not out.exists()


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()
