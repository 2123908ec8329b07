"""softcrawl.hardware: drivers, rig config, simulated rig and the fail-safe deploy loop.

Every fail-safe path is a fault-injection test on the simulated rig: the run must end with
every line vented to 0 kPa (the last APP:VOLT sent is 0,0,0 and the simulated regulators
decay toward 0), the outputs off (OUTP 0 sent, outputs off in the fake supply) and the reason
in the log and the summary."""

import csv
import json

import numpy as np
import pytest

from softcrawl.hardware.config import example_rig_path, load_rig_config
from softcrawl.hardware.deploy import deploy, validate_actions
from softcrawl.hardware.errors import RigConfigError, SensorError, SupplyError, VoltageLimitError
from softcrawl.hardware.logs import read_deploy_log
from softcrawl.hardware.sensors import HoneywellSSC, SSCBank, counts_for_kpa_abs
from softcrawl.hardware.simrig import IDN, FakeBK9129B, SCPIProtocolError, SimRig
from softcrawl.hardware.supply import BK9129B
from softcrawl.robot.actuation import PressureRangeError

GAIT = np.array([[0, 90, 0], [90, 0, 0], [0, 0, 0]] * 2, dtype=float)  # paper-best cycle, 6 s
#: What a confirmed fail-safe reports (the fake supply measures exactly 0 V with its outputs off).
FAIL_SAFE_OK = ["vented to 0 kPa (set 0.000,0.000,0.000 V read back)",
                "outputs off (read back off; measured 0.000,0.000,0.000 V)", "front panel local"]


# -- supply driver: the exact SCPI exchange ---------------------------------------------------------

def test_bk9129b_exact_exchange():
    sim = SimRig(seed=1)
    rig = sim.rig
    rig.start()
    rig.source.set_kpa([90.0, 45.0, 0.0])
    v = rig.source.measure_volts()
    fs = rig.fail_safe()
    assert sim.supply.sent() == [
        "*IDN?", "SYST:REM", "APP:VOLT 0.000,0.000,0.000", "APP:VOLT?", "OUTP 1", "OUTP?",
        "APP:VOLT 4.500,2.250,0.000", "APP:VOLT?", "MEAS:VOLT:ALL?",
        "APP:VOLT 0.000,0.000,0.000", "APP:VOLT?", "OUTP 0", "OUTP?", "MEAS:VOLT:ALL?", "SYST:LOC"]
    assert fs.confirmed and fs.steps == FAIL_SAFE_OK
    assert sim.supply.transcript[1] == ("<", IDN)
    assert np.allclose(v, [4.5, 2.25, 0.0], atol=0.003)
    assert not sim.supply.on and not sim.supply.remote


def test_fake_supply_rejects_anything_outside_the_exchange():
    from softcrawl.hardware.clock import SimClock

    f = FakeBK9129B(SimClock())
    for bad in ("VOLT 1.23", "APP:VOLT 1.2,3.4,5.6", "APP:VOLT 1.000, 2.000, 3.000", "OUTP ON", "*RST"):
        with pytest.raises(SCPIProtocolError):
            f.write(bad)
    with pytest.raises(SCPIProtocolError):
        f.query("MEAS:VOLT?")
    with pytest.raises(SCPIProtocolError):  # settings only in remote mode
        f.write("APP:VOLT 1.000,1.000,1.000")
    f.write("SYST:REM")
    with pytest.raises(SCPIProtocolError):  # beyond the 5 V of channel 3
        f.write("APP:VOLT 1.000,1.000,6.000")


def test_supply_verify_and_retry():
    sim = SimRig()
    drv = sim.rig.source.supply
    drv.remote()
    sim.supply.ignore_sets = 2  # two garbled settings, the third takes
    assert np.allclose(drv.set_volts([1.0, 2.0, 3.0]), [1, 2, 3])
    assert sim.supply.sent().count("APP:VOLT 1.000,2.000,3.000") == 3
    sim.supply.ignore_sets = 5
    with pytest.raises(SupplyError, match="after 3 attempts"):
        drv.set_volts([2.0, 2.0, 2.0])


def test_supply_refuses_voltages_beyond_limits_before_sending():
    sim = SimRig()
    drv = sim.rig.source.supply
    n = len(sim.supply.transcript)
    for bad in ([5.1, 0, 0], [0, 0, -0.1], [np.nan, 0, 0], [1, 1]):
        with pytest.raises(VoltageLimitError):
            drv.set_volts(bad)
    assert len(sim.supply.transcript) == n
    with pytest.raises(VoltageLimitError):
        BK9129B(sim.supply, max_v=(30, 30, 6))  # channel 3 is a 5 V channel


def test_supply_identify_and_lost_connection():
    sim = SimRig()
    drv = sim.rig.source.supply
    assert "9129B" in drv.identify()

    class Other:
        def query(self, cmd):
            return "KEITHLEY 2230"

    with pytest.raises(SupplyError, match="9129B"):
        BK9129B(Other()).identify()
    sim.supply.fail_from = sim.supply.n
    with pytest.raises(SupplyError, match="lost connection"):
        drv.measure_volts()


def test_pressure_source_refuses_out_of_range_commands():
    sim = SimRig()
    src = sim.rig.source
    src.start()
    n = len(sim.supply.transcript)
    for bad in ([91, 0, 0], [-1, 0, 0], [np.nan, 0, 0], [np.inf, 0, 0]):
        with pytest.raises(PressureRangeError):
            src.set_kpa(bad)
    assert len(sim.supply.transcript) == n


# -- sensors ---------------------------------------------------------------------------------------

class _Dev:
    def __init__(self, frames):
        self.frames = list(frames)

    def read(self, n):
        return self.frames.pop(0)


def _frame(status, counts):
    return bytes([(status << 6) | (counts >> 8), counts & 0xFF])


def test_honeywell_ssc_transfer_function_and_status():
    psi = 6.894757
    s = HoneywellSSC(_Dev([_frame(0, 1638), _frame(0, 14745), _frame(0, 8192)]))
    assert s.read_kpa_abs() == pytest.approx(0.0)
    assert s.read_kpa_abs() == pytest.approx(30 * psi)
    assert s.read_kpa_abs() == pytest.approx((8192 - 1638) / (14745 - 1638) * 30 * psi)
    assert counts_for_kpa_abs(30 * psi) == 14745
    with pytest.raises(SensorError, match="diagnostic"):
        HoneywellSSC(_Dev([_frame(3, 8000)])).read_kpa_abs()
    with pytest.raises(SensorError, match="stale"):
        HoneywellSSC(_Dev([_frame(2, 8000)] * 4)).read_kpa_abs()
    assert HoneywellSSC(_Dev([_frame(2, 8000), _frame(0, 8000)])).read_kpa_abs() > 0  # stale, then fresh
    with pytest.raises(SensorError, match="outside"):
        HoneywellSSC(_Dev([_frame(0, 16000)])).read_kpa_abs()


def test_ssc_bank_needs_a_plausible_atmospheric_zero():
    atm = counts_for_kpa_abs(101.3)
    bank = SSCBank([HoneywellSSC(_Dev([_frame(0, atm)] * 20)) for _ in range(3)])
    with pytest.raises(SensorError, match="not zeroed"):
        bank.read_kpa()
    assert np.allclose(bank.zero(n=5), 101.3, atol=0.05)
    assert np.allclose(bank.read_kpa(), 0.0, atol=0.05)
    pressurised = SSCBank([HoneywellSSC(_Dev([_frame(0, counts_for_kpa_abs(160.0))] * 20)) for _ in range(3)])
    with pytest.raises(SensorError, match="not vented"):
        pressurised.zero(n=2)


# -- rig.toml -------------------------------------------------------------------------------------

def test_example_rig_config_loads():
    cfg = load_rig_config(example_rig_path())
    assert cfg.rig.max_kpa == 90 and cfg.rig.sample_hz >= 10 and len(cfg.regulators) == 3
    assert cfg.sensors.kind == "honeywell-ssc" and cfg.sensors.mux_channels == (0, 1, 2)


@pytest.mark.parametrize("edit, match", [
    (("max_kpa = 90.0", "max_kpa = 120.0"), "max_kpa"),
    (("sample_hz = 20.0", "sample_hz = 5.0"), "sample_hz"),
    (("watchdog_s = 0.5", "watchdog_s = 0"), "watchdog_s"),
    (("watchdog_s = 0.5", "watchdog_s = 0.08"), "two sample periods"),
    (("max_volts = [5.0, 5.0, 5.0]", "max_volts = [5.0, 5.0, 12.0]"), "max_volts"),
    (("volts_per_kpa = 0.05\noffset_v = 0.0\n\n[[regulator]]   # regulator 3", "volts_per_kpa = 0.1\noffset_v = 0.0\n\n"
      "[[regulator]]   # regulator 3"), "needs 9 V"),
    (("channel = 3", "channel = 2"), "channels 1, 2, 3"),
    (("retries = 3", "retries = 3\nretry = 3"), "unknown key supply.retry"),
    (("timeout_ms = 1000", 'timeout_ms = "1000"'), "must be int"),
    (('model = "BK9129B"', 'model = "E3631A"'), "BK9129B"),
    (('kind = "honeywell-ssc"', 'kind = "bmp280"'), "sensors.kind"),
    (("mux_address = 0x70", "# no mux"), "mux_address"),
    (("[rig]", "[rigg]"), "unknown table"),
    (("[rig]", "[rig"), "not a readable TOML"),
    (('name = "PneuNet crawler rig"', 'name = "rig\\n\\u001b[2Jcleared"'), "printable"),
    (('name = "PneuNet crawler rig"', 'name = ""'), "printable"),
    (('address = "ASRL/dev/ttyUSB0::INSTR"', 'address = "ASRL\\u001b[31m::INSTR"'), "printable"),
    (("volts_per_kpa = 0.05", "volts_per_kpa = 1e-300"), "volts_per_kpa must be finite and >= 0.001"),
    (("bus = 1 ", "bus = -1 "), r"sensors.bus must be in \[0, 255\]"),
    (("bus = 1 ", "bus = 100000000000000000 "), r"sensors.bus must be in \[0, 255\]"),
    (("mux_address = 0x70", "mux_address = -5"), "mux_address -5 is not a 7-bit"),
    (("mux_address = 0x70", "mux_address = 0x78"), "mux_address 120 is not a 7-bit"),
    (("address = 0x28", "address = 0x7f"), "sensors.address 127 is not a 7-bit"),
    (("[rig]", "x = " + "[" * 5000 + "]" * 5000 + "\n[rig]"), "nested"),
])
def test_bad_rig_configs_are_refused(tmp_path, edit, match):
    text = example_rig_path().read_text()
    assert edit[0] in text
    p = tmp_path / "rig.toml"
    p.write_text(text.replace(edit[0], edit[1], 1))
    with pytest.raises(RigConfigError, match=match) as e:
        load_rig_config(p)
    assert str(p) in str(e.value) and "\n" not in str(e.value)


def test_missing_rig_config(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_rig_config(tmp_path / "nope.toml")


def test_rig_config_device_or_folder_is_refused(tmp_path):
    link = tmp_path / "rig.toml"
    link.symlink_to("/dev/zero")
    for p in (link, tmp_path):
        with pytest.raises(RigConfigError, match="not a regular file"):
            load_rig_config(p)


def test_cli_rig_check_and_deploy_refuse_deep_nesting_in_one_line(tmp_path, capsys):
    """5,000 nested arrays in rig.toml (rig check, deploy --sim-config) or calibration.json
    (deploy --calibration): one line, exit 2, no RecursionError traceback."""
    from softcrawl.cli import main

    deep = tmp_path / "deep.toml"
    deep.write_text(example_rig_path().read_text().replace("[rig]", "x = " + "[" * 5000 + "]" * 5000 + "\n[rig]"))
    cal = tmp_path / "calibration.json"
    cal.write_text("[" * 5000 + "]" * 5000)
    for argv in (["rig", "check", str(deep), "--sim"],
                 ["deploy", "--rig", "sim", "--sim-config", str(deep), "--out", str(tmp_path / "a")],
                 ["deploy", "--rig", "sim", "--calibration", str(cal), "--out", str(tmp_path / "b")]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "nested" in err and "Traceback" not in err


# -- deploy: normal run ----------------------------------------------------------------------------

def _rows(out):
    with (out / "log.csv").open() as f:
        return list(csv.DictReader(f))


def _assert_failsafe(sim, res, out, reason):
    assert res.status == "aborted" and reason in res.reason
    assert res.fail_safe == FAIL_SAFE_OK and res.fail_safe_confirmed
    sent = sim.supply.sent()
    sets = [c for c in sent if c.startswith("APP:VOLT ")]
    assert sets[-1] == "APP:VOLT 0.000,0.000,0.000" and "OUTP 0" in sent[sent.index(sets[-1]):]
    assert not sim.supply.on and np.all(sim.supply.set_v == 0)
    sim.clock.sleep(5.0)  # the lines empty once vented
    assert np.all(sim.plant.p < 1.0)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "aborted" and reason in summary["reason"] and summary["fail_safe_confirmed"]
    last = _rows(out)[-1]["event"]
    assert last.startswith("fail-safe: ") and reason in last and last.endswith("; ".join(FAIL_SAFE_OK))


def test_deploy_sim_completes_and_logs(tmp_path):
    sim = SimRig(seed=3, jitter_s=0.002)
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    assert res.status == "completed" and res.reason is None
    s = res.summary
    assert s["samples"] >= 10 * len(GAIT) and s["sample_hz_achieved"] >= 10 and s["overruns"] == 0
    assert abs(s["elapsed_s"] - len(GAIT)) < 0.2  # deadlines on the monotonic clock do not drift
    log = read_deploy_log(tmp_path / "d")
    t = log.t_s[log.step >= 0]
    assert np.all(np.diff(t) >= 0) and np.max(np.diff(t)) <= 0.1  # >= 10 Hz throughout
    # the sensed pressures follow the commands (fitted regulator model): regulator 2 near 90 kPa
    # gain/offset at the end of the first hold, the others near 0
    end0 = log.sensed_kpa[(log.step == 0)][-1]
    assert 75 < end0[1] < 95 and abs(end0[0]) < 3 and abs(end0[2]) < 3
    assert np.allclose(log.set_v[log.step == 0][0], [0, 4.5, 0])
    assert _rows(tmp_path / "d")[-1]["event"] == "completed; " + "; ".join(FAIL_SAFE_OK)
    assert res.fail_safe_confirmed and s["fail_safe_confirmed"] and s["log_error"] is None
    assert not sim.supply.on


def test_deploy_flags_overruns(tmp_path):
    sim = SimRig(seed=0, jitter_s=0.0)
    sim.supply.slow = {20: 0.3}  # one slow exchange in the middle (within the watchdog)
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    assert res.status == "completed"
    assert res.summary["overruns"] == 1 and res.summary["max_lateness_s"] > 0.05
    assert sum(int(r["overrun"]) for r in _rows(tmp_path / "d")) == 1


def test_deploy_refuses_bad_commands_before_anything_moves(tmp_path):
    for bad in ([[0, 95, 0]], [[0, -5, 0]], [[np.nan, 0, 0]]):
        sim = SimRig()
        a = np.vstack([GAIT, bad])
        with pytest.raises(PressureRangeError, match="row 6"):
            deploy(sim.rig, a, tmp_path / "x", progress=False)
        assert sim.supply.transcript == [] and not (tmp_path / "x" / "log.csv").exists()
    with pytest.raises(ValueError, match="shape"):
        validate_actions(np.zeros((3, 2)), 90)
    with pytest.raises(PressureRangeError, match="rig's limit"):
        validate_actions([[0, 80, 0]], 70)


# -- deploy: fault injection ------------------------------------------------------------------------

def test_failsafe_watchdog(tmp_path):
    sim = SimRig()
    sim.supply.slow = {30: 0.8}  # a stalled exchange, longer than the 0.5 s watchdog
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "watchdog")


def test_failsafe_lost_connection_mid_run(tmp_path):
    sim = SimRig()
    fails = {"n": 0}

    def pulled(cmd):  # the cable is pulled during action 2 and plugged back for the shutdown
        if cmd == "MEAS:VOLT:ALL?" and sim.clock.now() > 2.3 and fails["n"] < 1:
            fails["n"] += 1
            return True
        return False

    sim.supply.fail_when = pulled
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "lost connection")


def test_failsafe_dead_connection_still_logs(tmp_path):
    sim = SimRig()
    sim.supply.fail_from = 20  # the port is gone for good: the shutdown cannot reach the supply
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    assert res.status == "aborted" and "lost connection" in res.reason
    assert all(s.startswith("FAILED") for s in res.fail_safe)  # said, not hidden
    assert not res.fail_safe_confirmed and not res.summary["fail_safe_confirmed"]
    last = _rows(tmp_path / "d")[-1]["event"]
    assert "lost connection" in last and "FAILED" in last and "NOT CONFIRMED" in last


def test_failsafe_sensor_lost(tmp_path):
    sim = SimRig()
    sim.clock.on_advance(lambda t0, t1: setattr(sim.devices[1], "fail", t1 > 1.5))
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "I2C read failed")


@pytest.mark.parametrize("fault", ["unplugged sensor", "burst leg"])
def test_failsafe_sensor_command_disagreement(tmp_path, fault):
    sim = SimRig()
    if fault == "unplugged sensor":
        sim.devices[1].stuck_kpa = 0.0
    else:
        sim.plant.leak[1] = 0.3
    hold = np.array([[0, 90, 0]] * 3 + [[0, 0, 0]], dtype=float)  # regulator 2 at 90 kPa for 3 s
    res = deploy(sim.rig, hold, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "disagreement: regulator 2")
    # tripped after the set time (1.5 s) of disagreement, not at the first sample
    log = read_deploy_log(tmp_path / "d")
    assert log.t_s[log.step >= 0][-1] > 1.5


def test_no_trip_for_short_disagreement(tmp_path):
    """A single 1-s spike above the margin is shorter than the 1.5-s limit: no trip."""
    sim = SimRig()
    sim.clock.on_advance(lambda t0, t1: setattr(sim.devices[0], "stuck_kpa", 50.0 if 3.0 < t1 < 4.0 else None))
    assert deploy(sim.rig, GAIT, tmp_path / "d", progress=False).status == "completed"


def test_failsafe_exception(tmp_path):
    sim = SimRig()
    calls = {"n": 0}
    orig = sim.rig.sensors.read_kpa

    def broken():
        calls["n"] += 1
        if calls["n"] > 25:
            raise ZeroDivisionError("bug in a sensor filter")
        return orig()

    sim.rig.sensors.read_kpa = broken
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "exception: ZeroDivisionError")


def test_failsafe_ctrl_c(tmp_path):
    sim = SimRig()

    def interrupt(t0, t1):
        if t1 > 2.5 and not fired:
            fired.append(1)
            raise KeyboardInterrupt

    fired = []

    sim.clock.on_advance(interrupt)
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "Ctrl-C")


def test_second_ctrl_c_does_not_stop_the_shutdown():
    sim = SimRig()
    sim.rig.start()
    sim.rig.source.set_kpa([90, 90, 90])
    hits = []

    def interrupt_once(t0, t1):
        if not hits:
            hits.append(1)
            raise KeyboardInterrupt

    sim.clock.on_advance(interrupt_once)
    done = sim.rig.fail_safe()
    assert done.steps[0] == "FAILED (vent): interrupted" and done.steps[1:] == FAIL_SAFE_OK[1:]
    assert not done.confirmed and not sim.supply.on


def test_failsafe_hung_call_real_clock_watchdog_thread(tmp_path):
    """On a real (monotonic) clock, a call that never returns is interrupted by the watchdog thread."""
    import time

    from softcrawl.hardware.clock import MonotonicClock

    sim = SimRig()
    sim.rig.clock = MonotonicClock()
    sim.rig.simulated = False  # run the watchdog thread
    # a watchdog of 0.5 s: a shorter one can trip on an ordinary loop iteration of a loaded machine,
    # and the hang then falls into the fail-safe shutdown (SIGINT ignored there by design)
    sim.rig.settings = type(sim.rig.settings)(watchdog_s=0.5, sample_hz=20.0, control_period_s=0.2)
    orig = sim.rig.sensors.read_kpa
    calls = {"n": 0, "slept": False}

    def hang():
        calls["n"] += 1
        if calls["n"] == 4:
            time.sleep(10.0)  # hung I2C read; the watchdog thread's SIGINT lands here after 2 x 0.5 s
            calls["slept"] = True  # not reached when the watchdog interrupts the hung call
        return orig()

    sim.rig.sensors.read_kpa = hang
    # the caller ignores SIGINT, as a background job of a non-interactive shell does (regression: the
    # watchdog's SIGINT was then ignored too and the hung call ran on)
    import signal

    caller = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        res = deploy(sim.rig, GAIT[:3], tmp_path / "d", progress=False)
        assert calls["n"] >= 4 and not calls["slept"]  # the 10-s hang was cut short, on any machine load
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN  # the caller's handler is back
    finally:
        signal.signal(signal.SIGINT, caller)
    _assert_failsafe(sim, res, tmp_path / "d", "watchdog: the loop hung inside a call")


# -- CLI --------------------------------------------------------------------------------------------

def test_cli_deploy_sim_and_bad_input(tmp_path, capsys):
    from softcrawl.cli import main

    assert main(["deploy", "--rig", "sim", "--gait", "paper-best", "--n-actions", "4", "--out", str(tmp_path / "a"),
                 "--no-progress"]) == 0
    assert json.loads((tmp_path / "a" / "summary.json").read_text())["status"] == "completed"
    bad = tmp_path / "bad.csv"
    bad.write_text("p1,p2,p3\n0,95,0\n")
    assert main(["deploy", "--rig", "sim", "--actions", str(bad), "--out", str(tmp_path / "b")]) == 2
    err = capsys.readouterr().err
    assert "95" in err and err.count("\n") == 1 and not (tmp_path / "b").exists()
    rig = tmp_path / "rig.toml"
    rig.write_text(example_rig_path().read_text().replace("max_kpa = 90.0", "max_kpa = 200.0"))
    assert main(["deploy", "--rig", str(rig), "--out", str(tmp_path / "c")]) == 2
    assert main(["rig", "check", str(rig)]) == 2
    assert main(["rig", "check", str(example_rig_path()), "--sim"]) == 0
    assert "rig check passed" in capsys.readouterr().out
    noport = tmp_path / "noport.toml"  # never touch a real port from the tests
    noport.write_text(example_rig_path().read_text().replace("/dev/ttyUSB0", "/dev/softcrawl-test-no-such-port"))
    assert main(["rig", "check", str(noport)]) == 1  # one-line error, exit 1
    assert capsys.readouterr().err.count("\n") == 1


def test_cli_deploy_accepts_an_action_csv_with_a_bom(tmp_path):
    """A spreadsheet export starts with a UTF-8 byte-order mark: the header is still recognised."""
    from softcrawl.cli import main

    gait = tmp_path / "gait.csv"
    gait.write_bytes(b"\xef\xbb\xbfp1,p2,p3\r\n0,90,0\r\n90,0,0\r\n")
    assert main(["deploy", "--rig", "sim", "--actions", str(gait), "--out", str(tmp_path / "d"), "--no-progress"]) == 0
    assert json.loads((tmp_path / "d" / "summary.json").read_text())["actions_kpa"] == [[0, 90, 0], [90, 0, 0]]


def test_replay_sensor_follows_the_clock():
    from softcrawl.hardware.clock import SimClock
    from softcrawl.hardware.sensors import ReplaySensor

    clock = SimClock()
    s = ReplaySensor([0.0, 1.0, 2.0], [[0, 0, 0], [10, 20, 30], [5, 5, 5]], clock)
    s.zero()
    assert s.read_kpa().tolist() == [0, 0, 0]
    clock.advance(1.5)
    assert s.read_kpa().tolist() == [10, 20, 30]
    clock.advance(10)
    assert s.read_kpa().tolist() == [5, 5, 5]
    with pytest.raises(ValueError):
        ReplaySensor([0.0], [[1, 2]], clock)


def test_failsafe_setting_not_taken(tmp_path):
    """The supply drops an action's setting 3 times (verify-and-retry gives up): fail safe; the
    vent that follows is taken."""
    sim = SimRig()
    sim.clock.on_advance(lambda t0, t1: setattr(sim.supply, "ignore_sets", 3) if 2.0 < t1 < 2.2 else None)
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "after 3 attempts")


def test_failsafe_sensor_diagnostic_fault(tmp_path):
    sim = SimRig()
    sim.clock.on_advance(lambda t0, t1: setattr(sim.devices[2], "status", 3 if t1 > 1.0 else 0))
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    _assert_failsafe(sim, res, tmp_path / "d", "diagnostic fault")


def test_failsafe_lines_not_vented_at_start(tmp_path):
    """A pressurised line at start gives an implausible atmospheric zero: stop before the first action."""
    sim = SimRig()
    sim.plant.p[:] = 60.0
    sim.plant.params = tuple(type(p)(p.gain, p.offset, p.tau_inflate, 1e6) for p in sim.plant.params)  # no vent
    res = deploy(sim.rig, GAIT, tmp_path / "d", progress=False)
    assert res.status == "aborted" and "atmospheric zero" in res.reason
    assert not sim.supply.on and sim.supply.sent()[-4:] == ["OUTP 0", "OUTP?", "MEAS:VOLT:ALL?", "SYST:LOC"]
    assert "APP:VOLT 0.000,4.500,0.000" not in sim.supply.sent()  # no action was sent


def test_smbus_device_on_a_missing_bus_is_a_sensor_error():
    """The real I2C path through smbus2 (in the test extra): a bus that does not exist is a
    SensorError naming it, not an OSError traceback."""
    pytest.importorskip("smbus2")
    from softcrawl.hardware.sensors import SMBusDevice

    with pytest.raises(SensorError, match="cannot open I2C bus 250"):
        SMBusDevice(250, mux_address=0x70, mux_channel=0)


def test_cli_rig_check_reports_a_supply_it_cannot_confirm_off(tmp_path, capsys, monkeypatch):
    """A supply that stops answering during `rig check`: exit 3 and a warning, not "outputs off"."""
    import softcrawl.hardware.simrig as simrig
    from softcrawl.cli import main

    orig = simrig.SimRig.__init__

    def dying(self, *a, **k):
        orig(self, *a, **k)
        self.supply.fail_from = 2  # *IDN? and SYST:REM answer, nothing after

    monkeypatch.setattr(simrig.SimRig, "__init__", dying)
    assert main(["rig", "check", str(example_rig_path()), "--sim"]) == 3
    err = capsys.readouterr().err
    assert "lost connection" in err and "DANGER" in err


class _LateAnswers:
    """A resource whose answers queue up on the line, as on a serial port: a query cut short by a
    signal leaves its answer behind, to be read by the next query unless the buffer is discarded."""

    def __init__(self, fake):
        self.fake, self.line, self.cut, self.flushes = fake, [], False, 0

    def write(self, cmd):
        self.fake.write(cmd)

    def query(self, cmd):
        self.line.append(self.fake.query(cmd))
        if self.cut:
            self.cut = False
            raise KeyboardInterrupt  # the signal lands while the answer is in transit
        return self.line.pop(0)

    def flush(self, mask):
        self.flushes += 1
        self.line.clear()

    def close(self):
        pass


def test_answer_of_a_query_cut_short_is_not_read_as_the_next_answer(monkeypatch):
    import softcrawl.hardware.supply as supply

    monkeypatch.setattr(supply, "LATE_ANSWER_S", 0.0)
    sim = SimRig()
    res = _LateAnswers(sim.supply)
    drv = BK9129B(res, max_v=(5.0, 5.0, 5.0))
    drv.remote()
    drv.set_volts([1.0, 2.0, 3.0])
    drv.output(True)
    res.cut = True
    with pytest.raises(KeyboardInterrupt):
        drv.measure_volts()
    assert np.allclose(drv.set_volts([0.0, 0.0, 0.0]), 0.0)  # read back its own answer, not the stale one
    drv.output(False)
    assert np.allclose(drv.confirm_zero(), 0.0) and res.flushes == 1
    assert sim.supply.sent().count("APP:VOLT 0.000,0.000,0.000") == 1  # no retry needed
