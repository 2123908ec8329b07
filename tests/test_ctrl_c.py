"""Ctrl-C is a clean stop: exit code 130, one line naming what is kept, no worker tracebacks."""

from __future__ import annotations

import os

from softcrawl.cli import main


def test_ctrl_c_is_a_clean_stop(tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: object())

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(sim, "run_episode", interrupted)
    rc = main(["simulate", "--duration", "0.01", "--out", str(tmp_path / "o"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 130 and "\n" not in err and "interrupted" in err and str(tmp_path / "o") in err


def test_ctrl_c_in_train_and_sweep_names_what_is_kept(tmp_path, monkeypatch, capsys):
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


def test_ctrl_c_stops_worker_processes_cleanly(tmp_path):
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
        deadline = time.monotonic() + 600  # a guard against a hang only: a loaded machine starts workers slowly
        while len(list(tmp_path.glob("started-*"))) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(list(tmp_path.glob("started-*"))) == 2, "workers did not start"
        os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert proc.returncode == 130 and err.strip() == "interrupted", err


def test_workers_end_when_their_caller_is_killed(tmp_path):
    """A caller killed without its cleanup (SIGKILL; SIGTERM's default does the same) leaves no
    worker computing: each ends itself within a few seconds of its parent."""
    import signal
    import subprocess
    import sys
    import time

    import psutil

    (tmp_path / "pool.py").write_text(_POOL_SCRIPT)
    proc = subprocess.Popen([sys.executable, str(tmp_path / "pool.py"), str(tmp_path / "started-")],
                            cwd=tmp_path, start_new_session=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    try:
        deadline = time.monotonic() + 600  # a guard against a hang only
        while len(list(tmp_path.glob("started-*"))) < 2 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(list(tmp_path.glob("started-*"))) == 2, "workers did not start"
        workers = [p for p in psutil.Process(proc.pid).children(recursive=True) if "spawn_main" in " ".join(p.cmdline())]
        assert len(workers) == 2
        proc.kill()
        proc.wait(timeout=60)
        gone, alive = psutil.wait_procs(workers, timeout=30)  # the watchdog looks every 2 s
        assert not alive, [p.pid for p in alive]
    finally:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:  # every process of the group is gone
            pass
