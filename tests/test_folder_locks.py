"""One writer per folder (issue 49, defect 1): a training run, its report and an ``evaluate
--out`` folder are locked while a command writes them (:func:`softcrawl.safeio.folder_lock`); a
second command is refused at once with one line naming the holder (process, host, command) and
touches nothing; a killed holder leaves no lock that blocks the next command. The ground truth's
lock (the same mechanism) is tested in tests/test_groundtruth_safety.py (18)."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import pytest

from softcrawl.cli import main
from softcrawl.codesign.run import RUN_LOCK, Run
from softcrawl.safeio import FolderLockedError, folder_lock
from helpers import file_tree, one_line_error

DESIGN = "1,0,0,2,2,0,0,0"


def _holder(lock: str) -> subprocess.Popen:
    """A process holding ``lock`` (Python: the ``with`` expression of a softcrawl lock on
    ``sys.argv[1]``) until it is killed, started and holding."""
    code = (f"import sys, time\nfrom pathlib import Path\nfrom softcrawl.codesign.run import Run\n"
            f"from softcrawl.cli import output_lock\nwith {lock}:\n    print('locked', flush=True)\n"
            "    time.sleep(300)\n")
    return subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)


def _started(holder: subprocess.Popen) -> subprocess.Popen:
    assert holder.stdout.readline().strip() == "locked"
    return holder


def _killed(holder: subprocess.Popen) -> None:
    holder.send_signal(signal.SIGKILL)  # no finally runs: the lock file stays behind
    holder.wait()


def test_a_second_train_on_a_run_being_written_is_refused_with_its_holder(run):
    holder = _started(_holder(f"Run({str(run)!r}).lock()"))
    before = file_tree(run)
    try:
        second = subprocess.run([sys.executable, "-m", "softcrawl.cli", "train", "--resume", "--out", str(run),
                                 "--no-progress"], capture_output=True, text=True, timeout=120)
    finally:
        _killed(holder)
    err = second.stderr.strip()
    assert second.returncode == 2 and "\n" not in err and "Traceback" not in err, err
    assert f"process {holder.pid} on {socket.gethostname()}" in err and "being written by another" in err
    assert "python" in err and "-c import sys" in err  # the holder's command line
    assert file_tree(run) == before  # nothing touched, the lock file (left by the killed holder) included
    assert (run / RUN_LOCK).exists()
    from softcrawl.codesign.training import train

    res = train(run, resume=True, progress=False)  # the killed holder's lock file does not block the next run
    assert res.steps == 160 and not (run / RUN_LOCK).exists()


def test_report_and_resume_are_refused_while_a_run_trains(run, capsys):
    with Run(run).lock():
        before = file_tree(run)
        one_line_error(capsys, main(["report", str(run), "--no-simulate"]), f"process {os.getpid()}",
                       "being written by another softcrawl command")
        one_line_error(capsys, main(["train", "--resume", "--out", str(run), "--no-progress"]),
                       f"process {os.getpid()}")
        assert file_tree(run) == before
    assert main(["report", str(run), "--no-simulate"]) == 0 and (run / "report" / "summary.md").exists()
    assert not (run / RUN_LOCK).exists()


def test_a_second_evaluate_into_the_same_out_is_refused(trained, tmp_path, capsys):
    out = tmp_path / "ev"
    holder = _started(_holder(f"output_lock({str(out)!r})"))
    try:
        rc = main(["evaluate", str(trained), "--design", DESIGN, "--samples", "0", "--out", str(out),
                   "--no-progress", "--no-animation"])
        one_line_error(capsys, rc, f"process {holder.pid}", str(out))
        assert not out.exists()
    finally:
        _killed(holder)
    assert main(["evaluate", str(trained), "--design", DESIGN, "--samples", "0", "--out", str(out),
                 "--no-progress", "--no-animation"]) == 0
    assert (out / "evaluation.json").exists() and not (tmp_path / ".ev.lock").exists()


def test_a_new_run_refused_by_a_lock_or_a_failed_start_leaves_no_folder(tmp_path, monkeypatch, capsys):
    import softcrawl.codesign.training as training

    out = tmp_path / "new"
    out.mkdir()
    (out / RUN_LOCK).write_text('{"pid": 1}')  # a killed new run's lock file: the folder is still new
    monkeypatch.setattr(training, "make_vec_env", lambda *a, **k: (_ for _ in ()).throw(ValueError("no envs")))
    one_line_error(capsys, main(["train", "--preset", "smoke", "--out", str(out), "--no-progress"]), "no envs")
    assert list(out.iterdir()) == []  # the lock file goes with the command that held it
    one_line_error(capsys, main(["train", "--preset", "smoke", "--out", str(tmp_path / "other"), "--no-progress"]),
                   "no envs")
    assert not (tmp_path / "other").exists()  # created for the run, removed with its failed start


def test_the_lock_names_its_holder_and_goes_with_it(tmp_path):
    lock = tmp_path / ".x.lock"
    with folder_lock(lock, tmp_path):
        holder = json.loads(lock.read_text())
        assert holder["pid"] == os.getpid() and holder["host"] == socket.gethostname() and holder["command"]
        with pytest.raises(FolderLockedError, match=f"process {os.getpid()} on {socket.gethostname()}"), \
                folder_lock(lock, tmp_path):  # not re-entrant: a second writer in one process is refused too
            pass
    assert not lock.exists()
    lock.symlink_to(tmp_path / "elsewhere")
    with pytest.raises(OSError), folder_lock(lock, tmp_path):  # never through a link
        pass
    assert not (tmp_path / "elsewhere").exists()
