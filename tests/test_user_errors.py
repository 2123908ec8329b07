"""User mistakes (bad durations, action CSVs, run files) are one-line errors naming the file
and line; damaged optional files are left out with a note."""

from __future__ import annotations

import pytest

from softcrawl.cli import main
from helpers import one_line_error, rehash


def test_user_mistakes_are_one_line_errors(run, tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: pytest.fail("model built"))
    rc = main(["simulate", "--duration", "1e12", "--out", str(tmp_path / "o"), "--no-progress"])
    one_line_error(capsys, rc, "--duration", "3600")
    with open(run / "episodes.csv", "a") as f:
        f.write("120,not-a-design,1.0,0\n")
    rc = main(["report", str(run), "--no-simulate"])
    one_line_error(capsys, rc, "episodes.csv, line 9")
    for ck in (run / "checkpoints").glob("step-*"):
        (ck / "state.pkl").write_bytes(b"")
    one_line_error(capsys, main(["report", str(run), "--no-simulate"]), "no complete checkpoint")
    one_line_error(capsys, main(["simulate", "--reduction", str(tmp_path), "--out", str(tmp_path / "o"),
                                  "--no-progress", "--duration", "0.01"]), "directory")
    rc = main(["sweep-phase", "--duration", "1e12", "--out", str(tmp_path / "o"), "--no-progress"])
    one_line_error(capsys, rc, "--duration", "3600")
    (tmp_path / "file").write_text("x")
    one_line_error(capsys, main(["train", "--out", str(tmp_path / "file")]), "not a directory")
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text, where", [("p1,p2,p3\n10,20,30\n\n10,20,300\n", "a.csv, line 4, p3: 300 kPa"),
                                         ("10,20,30\n1,2\n", "a.csv, line 2: expected 3 columns"),
                                         ("0,0,0\n0,nan,0\n", "a.csv, line 2, p2: nan kPa is not finite"),
                                         ("0,0,0\n0,0,x\n", "a.csv, line 2: non-numeric")])
def test_action_csv_errors_name_the_file_and_line(text, where, tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: pytest.fail("model built"))
    (tmp_path / "a.csv").write_text(text)
    rc = main(["simulate", "--actions", str(tmp_path / "a.csv"), "--out", str(tmp_path / "o"), "--no-progress"])
    one_line_error(capsys, rc, where)


def test_run_file_errors_name_the_file_and_line(run, tmp_path, capsys):
    from softcrawl.codesign.run import Run

    latest = run / "checkpoints" / "step-0000000160"
    (latest / "state.json").write_bytes(b"")  # an empty state file, checksummed: malformed, not a traceback
    rehash(latest)
    one_line_error(capsys, main(["report", str(run), "--no-simulate"]), "state.json: malformed")
    with open(run / "sessions.csv", "a") as f:
        f.write("160,oops\n")
    with pytest.raises(ValueError, match=r"sessions\.csv, line 2: not a session row"):
        Run(run).wall_seconds()
    with open(run / "episodes.csv", "a") as f:
        f.write("1x0,01200000,1.0,0\n")
    with pytest.raises(ValueError, match=r"episodes\.csv, line 9: not a row of this run"):
        Run(run).forget_after(120)  # resume bookkeeping: refuses, changes nothing
    assert len((run / "episodes.csv").read_text().splitlines()) == 9


def test_an_unfinished_last_row_is_not_an_error(run, capsys):
    """A writer killed mid-row (or a full disk) leaves a last line without newline: the report
    leaves it out with a note, and resume drops it with the rest after the checkpoint."""
    from softcrawl.codesign.run import Run

    with open(run / "episodes.csv", "a") as f:
        f.write("16")  # of "160,0120...": its t would read as 16
    assert main(["report", str(run), "--no-simulate"]) == 0
    assert "episodes.csv, line 9: unfinished last row" in capsys.readouterr().err
    Run(run).forget_after(160)
    assert (run / "episodes.csv").read_text().splitlines()[-1].startswith("160,")


def test_directory_as_the_training_reduction(tmp_path, capsys):
    rc = main(["train", "--preset", "smoke", "--out", str(tmp_path / "r"), "--no-progress",
               "--set", f'env.reduction="{tmp_path}"'])
    one_line_error(capsys, rc, "is a directory")
    assert not (tmp_path / "r" / "config.json").exists()


def test_damaged_snapshot_is_left_out_of_the_report(run, capsys):
    """Found by the fuzz test: an empty snapshot file raised EOFError out of ``report``."""
    (run / "snapshots" / "t-0000000040.npz").write_bytes(b"")
    assert main(["report", str(run), "--no-simulate"]) == 0
    assert "t-0000000040.npz: not a design-distribution snapshot" in capsys.readouterr().err
    assert (run / "report" / "reward_histogram.png").exists()
