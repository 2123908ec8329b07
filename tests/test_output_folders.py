"""Outputs are checked before the work starts, kept (and rescued) on a full or read-only disk,
and only softcrawl's own output folders are ever overwritten."""

from __future__ import annotations

import errno
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest

from softcrawl.cli import main
from helpers import file_tree, one_line_error


def test_output_paths_are_checked_before_simulating(tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    def never(*a, **k):
        raise AssertionError("the model was built before the output was checked")

    monkeypatch.setattr(sim, "build_robot", never)
    monkeypatch.chdir(tmp_path)
    one_line_error(capsys, main(["simulate", "--duration", "0.01", "--out", ".", "--no-progress"]), "not the current")
    (tmp_path / "file").write_text("x")
    rc = main(["simulate", "--duration", "0.01", "--out", str(tmp_path / "file" / "out"), "--no-progress"])
    one_line_error(capsys, rc, "not a directory")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("years of work")
    rc = main(["simulate", "--duration", "0.01", "--out", str(foreign), "--overwrite", "--no-progress"])
    one_line_error(capsys, rc, "not a softcrawl output")
    assert (foreign / "thesis.tex").read_text() == "years of work"
    rc = main(["train", "--preset", "smoke", "--out", str(tmp_path / "file")])
    one_line_error(capsys, rc, "not a directory")
    before = file_tree(tmp_path)
    rc = main(["simulate", "--duration", "0.01", "--out", ".", "--overwrite", "--no-progress"])
    one_line_error(capsys, rc, "not the current")  # --overwrite never replaces the working directory
    assert file_tree(tmp_path) == before


def test_sweep_and_evaluate_check_their_output_first(tmp_path, monkeypatch, capsys):
    import softcrawl.codesign.evaluation as evaluation
    import softcrawl.robot.sweep as sweep

    def never(*a, **k):
        raise AssertionError("the work started before the output was checked")

    monkeypatch.setattr(sweep, "_robot", never)
    monkeypatch.setattr(evaluation, "evaluate_policy", never)
    (tmp_path / "file").write_text("x")
    bad = str(tmp_path / "file" / "out")
    one_line_error(capsys, main(["sweep-phase", "--phases", "0", "--out", bad, "--no-progress"]), "not a directory")
    rc = main(["evaluate", str(tmp_path), "--design", "1,0,0,2,2,0,0,0", "--out", bad, "--no-progress"])
    one_line_error(capsys, rc, "not a directory")
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    rc = main(["sweep-phase", "--phases", "0", "--out", str(foreign), "--overwrite", "--no-progress"])
    one_line_error(capsys, rc, "not a softcrawl output")
    if os.geteuid() != 0:  # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o555)
        rc = main(["sweep-phase", "--phases", "0", "--out", str(locked / "out"), "--no-progress"])
        one_line_error(capsys, rc, "not writable")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["file", "mine"] + (["locked"] if os.geteuid() else []))


def _no_space(*a, **k):
    raise OSError(errno.ENOSPC, "No space left on device")


def _kept_and_rescued(err: str) -> tuple[Path, Path]:
    """The folders a full-disk error names: ``kept in X`` (next to --out) and ``saved in Y``."""
    import re

    kept = re.search(r"kept in (\S+?);", err)
    saved = re.search(r"saved in (\S+?)(;|$)", err)
    return (Path(kept.group(1)) if kept else None), (Path(saved.group(1)) if saved else None)


def test_full_disk_after_simulating_keeps_the_result(tmp_path, monkeypatch, capsys):
    """``simulate``: ENOSPC while writing the ParaView frames (after the run) keeps what was
    written next to --out and saves summary + trajectory in the system's temp dir."""
    import softcrawl.robot.output as output

    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    monkeypatch.setattr(output, "write_paraview", _no_space)
    out = tmp_path / "sim"
    rc = main(["simulate", "--duration", "0.05", "--out", str(out), "--no-progress"])
    err = one_line_error(capsys, rc, "No space left on device")
    kept, saved = _kept_and_rescued(err)
    assert kept.parent == tmp_path and saved.parent == systmp and not out.exists()
    for folder in (kept, saved):
        assert json.loads((folder / "summary.json").read_text())["steps"] == 5
        assert np.load(folder / "trajectory.npz")["t"].shape == (6,)


def test_read_only_file_system_still_saves_the_result(tmp_path, monkeypatch, capsys):
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
    err = one_line_error(capsys, rc, "Read-only file system")
    kept, saved = _kept_and_rescued(err)
    assert kept is None and saved.parent == systmp and (saved / "trajectory.csv").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["systmp"]


def test_full_disk_after_a_sweep_keeps_every_phase(tmp_path, monkeypatch, capsys):
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


def test_full_disk_after_evaluating_keeps_the_evaluation(run, tmp_path, monkeypatch, capsys):
    """``evaluate``: evaluation.json and actions.csv are written with the rest, so a full disk
    keeps (and rescues) them too."""
    import softcrawl.robot.output as output

    systmp = tmp_path / "systmp"
    systmp.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(systmp))
    monkeypatch.setattr(output, "write_paraview", _no_space)
    rc = main(["evaluate", str(run), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "ev"), "--no-progress"])
    kept, saved = _kept_and_rescued(one_line_error(capsys, rc, "No space left on device"))
    for folder in (kept, saved):
        assert json.loads((folder / "evaluation.json").read_text())["design"] == [1, 0, 0, 2, 2, 0, 0, 0]
        assert (folder / "actions.csv").read_text().startswith("p1,p2,p3")
    assert not (tmp_path / "ev").exists()


def test_full_disk_keeps_what_was_written(tmp_path):
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


def test_report_is_staged_and_swapped_in(run, monkeypatch):
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
