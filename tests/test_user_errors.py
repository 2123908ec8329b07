"""User mistakes (bad durations, action CSVs, run files) are one-line errors naming the file
and line; damaged optional files are left out with a note."""

from __future__ import annotations

import argparse

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


# -- issue 49, defect 5: every count has an upper bound -------------------------------------------------
def _options():
    """``(command words, option string, action)`` of every option of every command."""
    from softcrawl.cli import build_parser

    todo, out = [((), build_parser())], []
    while todo:
        words, parser = todo.pop()
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                todo += [((*words, name), sub) for name, sub in action.choices.items()]
            elif action.option_strings:
                out.append((words, action.option_strings[-1], action))
    return out


def test_every_numeric_option_of_every_command_is_bounded(capsys):
    """Each ``int`` or ``float`` option has bounds (:func:`softcrawl.cli.bounded`), and a value far
    beyond them is one usage line naming the option, before the command does anything (the
    required arguments are not even looked at)."""
    from softcrawl.cli import _Bounded

    numeric = [(w, o, a) for w, o, a in _options() if a.type in (int, float)]
    assert len(numeric) > 60 and {w[0] for w, _, _ in numeric} >= {"evaluate", "report", "deploy", "groundtruth",
                                                                    "train", "simulate", "sweep-phase", "reduce"}
    assert [f"{' '.join(w)} {o}" for w, o, a in numeric if not isinstance(a, _Bounded)] == []
    for words, option, action in numeric:
        huge = "1e300" if action.type is float else str(10**30)
        assert main([*words, option, huge]) == 2
        err = capsys.readouterr().err.strip()
        assert f"{option} must be" in err and "\n" not in err, err


@pytest.mark.parametrize("argv", [
    ["evaluate", "RUN", "--design", "1,0,0,2,2,0,0,0", "--samples", "1000000000"],
    ["report", "RUN", "--samples", "1000000000"],
    ["deploy", "--rig", "sim", "--run", "RUN", "--design", "1,0,0,2,2,0,0,0", "--samples", "1000000000"],
    ["deploy", "--rig", "sim", "--gait", "sine", "--n-actions", "1000000000"],
    ["groundtruth", "--evals-per-cycle", "1000000000"],
    ["groundtruth", "--workers", "1000000000"],
    ["train", "--n-envs", "1000000000"],
    ["sweep-phase", "--workers", "1000000000"],
])
def test_the_probes_huge_counts_are_refused_at_once(argv, tmp_path, capsys):
    """The tester's commands: ``--samples 1000000000`` ran silently; ``deploy --n-actions
    1000000000`` grew memory by 45 MB/s before the rig was touched."""
    rc = main([a.replace("RUN", str(tmp_path / "run")) for a in argv] + ["--out", str(tmp_path / "o")])
    one_line_error(capsys, rc, argv[-2], "1000000000")
    assert list(tmp_path.iterdir()) == []
