"""However ``softcrawl deploy`` ends, the rig is vented and the run is reported.

End to end: a ``softcrawl deploy`` subprocess drives a fake BK 9129B on a pseudo-terminal through
the real driver, pyvisa, pyvisa-py and pyserial (:mod:`softcrawl.hardware.ptysupply`), and is
stopped with each stop signal once its log has rows; the fake's final state (outputs off, 0 V
set, front panel local), the log's last row and the summary are checked. In process: the
signal handlers are restored, the log is on disk while the run goes on, a write error and an
unconfirmed fail-safe are reported as such.

No wall-clock assertions: the tests wait for the log's first rows before signalling, with
generous time limits (a loaded machine only makes them slower).
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from softcrawl.hardware.config import example_rig_path
from softcrawl.hardware.deploy import STOP_SIGNALS, deploy
from softcrawl.hardware.simrig import SimRig

pytest.importorskip("termios")  # pseudo-terminals: POSIX
pytest.importorskip("pyvisa")
pytest.importorskip("pyvisa_py")
pytest.importorskip("serial")  # pyvisa-py's serial backend

from softcrawl.hardware.ptysupply import PtySupply  # noqa: E402

GAIT = np.array([[0, 90, 0], [90, 0, 0], [0, 0, 0]] * 2, dtype=float)
WAIT_S = 120.0  # upper bound on any wait: a run that hangs fails the test instead of the suite


def _rig_toml(tmp_path: Path, address: str) -> Path:
    """The example rig on ``address``, without sensors, with a 10-s control period and watchdog:
    the watchdog runs on the real clock, and must not trip before the test's signal, however
    slowly a loaded machine answers (one pty exchange takes milliseconds; 10 s is the margin)."""
    text = example_rig_path().read_text().split("[sensors]")[0] + '[sensors]\nkind = "none"\n'
    for a, b in (("ASRL/dev/ttyUSB0::INSTR", address), ("control_period_s = 1.0", "control_period_s = 10.0"),
                 ("watchdog_s = 0.5", "watchdog_s = 10.0"), ("sample_hz = 20.0", "sample_hz = 10.0")):
        assert a in text
        text = text.replace(a, b)
    p = tmp_path / "rig.toml"
    p.write_text(text)
    return p


def _start(args: list[str], **kw) -> subprocess.Popen:
    """``softcrawl ARGS`` in a subprocess with default dispositions of the stop signals (a test
    runner started under ``nohup`` must not make SIGHUP ignored in the child)."""
    code = ("import signal, sys\n"
            "for s in ('SIGINT', 'SIGTERM', 'SIGHUP', 'SIGQUIT'):\n"
            "    signal.signal(getattr(signal, s), signal.default_int_handler if s == 'SIGINT' else signal.SIG_DFL)\n"
            "from softcrawl.cli import main\n"
            "sys.exit(main(sys.argv[1:]))\n")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    return subprocess.Popen([sys.executable, "-c", code, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True, env=env, **kw)


def _wait_for_rows(proc: subprocess.Popen, log: Path, rows: int = 2) -> None:
    """Wait until ``log`` holds the header and ``rows`` rows (the run is under way)."""
    deadline = time.monotonic() + WAIT_S
    while not (log.exists() and log.read_text().count("\n") >= rows + 1):
        if proc.poll() is not None:
            out, err = proc.communicate()
            pytest.fail(f"deploy ended before the signal (exit {proc.returncode}): {out} {err}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail("deploy wrote no rows")
        time.sleep(0.05)


def _last_row(log: Path) -> dict:
    with log.open(newline="") as f:
        return list(csv.DictReader(f))[-1]


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP", "SIGINT", "SIGQUIT"])
def test_deploy_subprocess_vents_on_each_signal(tmp_path, sig):
    with PtySupply() as fake:
        out = tmp_path / "out"
        proc = _start(["deploy", "--rig", str(_rig_toml(tmp_path, fake.address)), "--gait", "sine",
                       "--n-actions", "60", "--out", str(out), "--no-progress"])
        _wait_for_rows(proc, out / "log.csv")
        assert fake.supply.on and fake.supply.remote  # the run was under way, outputs on
        proc.send_signal(getattr(signal, sig))
        stdout, stderr = proc.communicate(timeout=WAIT_S)
        sent = fake.supply.sent()
        assert fake.errors == []
    # the fake supply: vented, outputs off (and read back), front panel local
    assert not fake.supply.on and not fake.supply.set_v.any() and not fake.supply.remote
    assert sent[-6:] == ["APP:VOLT 0.000,0.000,0.000", "APP:VOLT?", "OUTP 0", "OUTP?", "MEAS:VOLT:ALL?", "SYST:LOC"]
    reason = "interrupted (Ctrl-C, SIGINT)" if sig == "SIGINT" else f"stopped by signal {sig}"
    last = _last_row(out / "log.csv")
    assert last["step"] == "-1" and last["event"].startswith(f"fail-safe: {reason}; vented to 0 kPa")
    assert "outputs off (read back off" in last["event"]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "aborted" and summary["reason"] == reason and summary["signal"] == sig
    assert summary["fail_safe_confirmed"] is True and summary["log_error"] is None
    assert proc.returncode == 1, stderr  # stopped, rig safe
    assert f"stopped by the fail-safe: {reason}" in stderr and "Traceback" not in stderr
    assert stdout.startswith("aborted: 60 actions")


def test_deploy_subprocess_reports_an_unconfirmed_fail_safe(tmp_path):
    """The supply acknowledges OUTP 0 but its outputs stay on: the summary and the exit code
    say that the fail-safe is not confirmed, never "outputs off"."""
    with PtySupply() as fake:
        fake.supply.stuck_on = True
        out = tmp_path / "out"
        proc = _start(["deploy", "--rig", str(_rig_toml(tmp_path, fake.address)), "--gait", "sine",
                       "--n-actions", "60", "--out", str(out), "--no-progress"])
        _wait_for_rows(proc, out / "log.csv")
        proc.send_signal(signal.SIGTERM)
        _, stderr = proc.communicate(timeout=WAIT_S)
    assert fake.supply.on and not fake.supply.set_v.any()  # vented, but the outputs are still on
    summary = json.loads((out / "summary.json").read_text())
    assert summary["fail_safe_confirmed"] is False
    assert any(s.startswith("FAILED (off): supply: sent OUTP 0 but OUTP? still reads on") for s in summary["fail_safe"])
    assert "NOT CONFIRMED" in _last_row(out / "log.csv")["event"]
    assert proc.returncode == 3 and "DANGER" in stderr and "switch the supply off by hand" in stderr


def test_deploy_log_survives_kill_9(tmp_path):
    """SIGKILL cannot be handled; the log written so far is on disk, header included."""
    with PtySupply() as fake:
        out = tmp_path / "out"
        proc = _start(["deploy", "--rig", str(_rig_toml(tmp_path, fake.address)), "--gait", "sine",
                       "--n-actions", "60", "--out", str(out), "--no-progress"])
        _wait_for_rows(proc, out / "log.csv", rows=3)
        proc.kill()
        proc.communicate(timeout=WAIT_S)
    lines = (out / "log.csv").read_text().splitlines()
    assert lines[0].startswith("t_s,step,") and len(lines) >= 4 and not (out / "summary.json").exists()


def test_sim_deploy_stopped_by_timeout_leaves_a_final_row_and_summary(tmp_path):
    """`timeout` sends SIGTERM: the simulated rig's run ends like a real one."""
    out = tmp_path / "out"
    proc = _start(["deploy", "--rig", "sim", "--gait", "sine", "--n-actions", "20000", "--out", str(out),
                   "--no-progress"])
    _wait_for_rows(proc, out / "log.csv")
    proc.send_signal(signal.SIGTERM)
    _, stderr = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1, stderr
    assert _last_row(out / "log.csv")["event"].startswith("fail-safe: stopped by signal SIGTERM; vented to 0 kPa")
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "aborted" and summary["fail_safe_confirmed"] is True


def test_sim_deploy_write_error_goes_through_the_fail_safe(tmp_path):
    """A file-size limit (``ulimit -f``, EFBIG) mid-run: vented, the write error in the summary and
    on stderr, exit code 1 (stopped, rig safe), not the bad-input code 2."""
    import resource

    out = tmp_path / "out"
    limit = 20_000  # bytes: log.csv passes it within a few actions; summary.json stays below it

    def limit_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    proc = _start(["deploy", "--rig", "sim", "--gait", "sine", "--n-actions", "40", "--out", str(out),
                   "--no-progress"], preexec_fn=limit_files)
    _, stderr = proc.communicate(timeout=WAIT_S)
    assert proc.returncode == 1, stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "aborted" and "File too large" in summary["reason"]
    assert "log.csv" in summary["log_error"] and summary["fail_safe_confirmed"] is True
    assert summary["fail_safe"][1].startswith("outputs off (read back off")
    assert "File too large" in stderr and "Traceback" not in stderr
    assert (out / "log.csv").stat().st_size <= limit


# -- in process ---------------------------------------------------------------------------------------

def _handlers():
    return {s: signal.getsignal(s) for s in STOP_SIGNALS}


@pytest.fixture
def default_disposition(sig):
    """Signal ``sig`` at its default disposition for the test, restored afterwards: a runner may
    ignore it (SIGHUP under ``nohup``, SIGQUIT in a shell's background job), and deploy rightly
    keeps an ignored signal ignored."""
    old = signal.signal(getattr(signal, sig), signal.SIG_DFL)
    yield
    signal.signal(getattr(signal, sig), old)


@pytest.mark.parametrize("sig", ["SIGTERM", "SIGHUP", "SIGQUIT"])
def test_signal_in_process_vents_and_restores_handlers(tmp_path, sig, default_disposition):
    sim = SimRig()
    before = _handlers()
    sent = []

    def kill(t0, t1):
        if t1 > 2.5 and not sent:
            sent.append(1)
            os.kill(os.getpid(), getattr(signal, sig))

    def again(cmd):  # a second signal during the shutdown is recorded, not obeyed
        if cmd == "OUTP 0":
            os.kill(os.getpid(), signal.SIGINT)
        return False

    sim.clock.on_advance(kill)
    sim.supply.fail_when = again
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    assert res.status == "aborted" and res.reason == f"stopped by signal {sig}" and res.fail_safe_confirmed
    assert not sim.supply.on and not sim.supply.set_v.any()
    assert _handlers() == before
    assert res.summary["signal"] == sig and res.summary["signals_during_shutdown"] == ["SIGINT"]


def test_ignored_sighup_stays_ignored(tmp_path):
    """Under ``nohup`` (SIGHUP ignored) a closed terminal does not stop the run."""
    sim = SimRig()
    old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
    try:
        sim.clock.on_advance(lambda t0, t1: os.kill(os.getpid(), signal.SIGHUP) if 2.0 < t1 < 2.2 else None)
        res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
        assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGHUP, old)
    assert res.status == "completed"


def test_log_is_on_disk_while_the_run_goes_on(tmp_path):
    sim = SimRig()
    seen = []
    log = tmp_path / "d" / "log.csv"

    def look(t0, t1):
        if t1 > 3.0 and not seen:
            seen.append(log.read_text().splitlines())

    sim.clock.on_advance(look)
    assert deploy(sim.rig, GAIT, tmp_path / "d", progress=False).status == "completed"
    rows = seen[0]
    assert rows[0].startswith("t_s,step,") and len(rows) > 2 * 20  # more than two 1-s actions at 20 Hz, all flushed


def test_failsafe_not_confirmed_when_the_outputs_stay_on(tmp_path):
    """A supply that acknowledges OUTP 0 but stays on is never reported as off."""
    sim = SimRig()
    sim.supply.stuck_on = True
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    assert res.status == "completed" and not res.fail_safe_confirmed and sim.supply.on
    assert res.fail_safe[0].startswith("vented to 0 kPa") and res.fail_safe[1].startswith("FAILED (off)")
    assert res.summary["fail_safe_confirmed"] is False


def test_outputs_off_but_measuring_volts_is_not_confirmed(tmp_path):
    """OUTP? reads off but the outputs still measure volts (a stuck relay): not confirmed."""
    sim = SimRig()
    sim.supply.output_v = lambda: np.array([4.5, 0.0, 0.0])
    res = deploy(sim.rig, GAIT[:1], tmp_path / "d", progress=False)
    assert not res.fail_safe_confirmed
    assert "FAILED (off): supply: outputs read back off but measure 4.500,0.000,0.000 V" in res.fail_safe[1]


def test_existing_log_or_symlink_in_out_is_refused(tmp_path):
    out = tmp_path / "d"
    out.mkdir()
    (out / "log.csv").symlink_to(tmp_path / "elsewhere.csv")  # dangling: would be written through
    with pytest.raises(ValueError, match="already holds a deploy log"):
        deploy(SimRig().rig, GAIT, out, progress=False)
    assert not (tmp_path / "elsewhere.csv").exists()
