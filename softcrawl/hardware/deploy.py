"""Run an open-loop gait on a rig, fail-safe.

:func:`deploy` holds each action (3 real kPa) for ``control_period_s`` on the rig's monotonic
clock (action k is applied at ``t0 + k * period``: deadlines do not drift, unlike a
``sleep(1)`` loop, which ran at 1.067 s per step on the paper's rig), samples commanded kPa,
set volts, measured volts and sensed kPa at ``sample_hz`` (>= 10 Hz) into ``log.csv``, and
writes ``summary.json``. An action applied later than ``overrun_tolerance_s`` is flagged in
the log (column ``overrun``) and counted.

Safety:

- every action is range-checked (``[0, max_kpa]``, max 90 kPa) *before the rig is touched*:
  a bad gait raises :class:`PressureRangeError` and nothing is sent;
- the loop then stops and runs :meth:`Rig.fail_safe` (vent every line to 0 kPa, outputs off)
  on: the **watchdog** (an I/O call, or the gap between two loop iterations, longer than
  ``watchdog_s``; on a real rig a watchdog thread also interrupts a loop hung inside a call),
  a **lost connection** or another instrument fault (:class:`SupplyError` / :class:`SensorError`:
  no answer, a setting not taken after the retries, a sensor status fault), a **sensor/command
  disagreement** (``|sensed - commanded| > disagreement_kpa`` continuously for
  ``disagreement_s``), **any exception**, and **Ctrl-C**. The reason goes into the log's last
  row, the summary (``status: "aborted"``, ``reason``, ``fail_safe``) and the return value.
  A completed run vents and turns the outputs off too.
"""

from __future__ import annotations

import csv
import json
import math
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softcrawl.hardware.errors import SafetyTrip, SensorError, SupplyError, one_line
from softcrawl.hardware.logs import DEPLOY_COLUMNS
from softcrawl.robot.actuation import PressureRangeError, check_pressures


@dataclass
class DeployResult:
    """Outcome of :func:`deploy`: ``status`` ``"completed"`` or ``"aborted"``, ``reason`` (None
    when completed), ``fail_safe`` (what the shutdown did), ``summary`` (the JSON written)."""

    status: str
    reason: str | None
    fail_safe: list
    summary: dict = field(default_factory=dict)
    out: str = ""


class _Watchdog:
    """Kicked by the loop; ``check()`` raises :class:`SafetyTrip` when the last kick is older
    than ``timeout_s`` on the rig's clock. With ``thread=True`` (real rigs) a daemon thread on
    :func:`time.monotonic` also interrupts the main thread if no kick arrives for 2x the timeout
    (a call hung inside a driver never returns to ``check``)."""

    def __init__(self, clock, timeout_s: float, thread: bool) -> None:
        self.clock, self.timeout = clock, timeout_s
        self.last = clock.now()
        self._real_last = time.monotonic()
        self.fired = False
        self._stop = threading.Event()
        self._thread = None
        if thread:
            self._thread = threading.Thread(target=self._run, daemon=True, name="softcrawl-watchdog")
            self._thread.start()

    def kick(self) -> None:
        self.last = self.clock.now()
        self._real_last = time.monotonic()

    def check(self, what: str) -> None:
        late = self.clock.now() - self.last
        if late > self.timeout:
            raise SafetyTrip(f"watchdog: {what} took {late:.3f} s (limit {self.timeout:g} s)")
        self.kick()

    def _run(self) -> None:
        while not self._stop.wait(self.timeout / 4):
            if time.monotonic() - self._real_last > 2 * self.timeout and not self._stop.is_set():
                self.fired = True
                # a real SIGINT to the main thread: unlike _thread.interrupt_main it also breaks a
                # blocking system call (PEP 475: the default handler raises KeyboardInterrupt)
                signal.pthread_kill(threading.main_thread().ident, signal.SIGINT)
                return

    def stop(self) -> None:
        self._stop.set()


def validate_actions(actions, max_kpa: float) -> np.ndarray:
    """``(n, 3)`` float kPa, every entry finite and in ``[0, max_kpa]``.

    Raises:
        ValueError: wrong shape. PressureRangeError: naming the first bad action and regulator.
    """
    a = np.array(actions, dtype=float)
    if a.ndim != 2 or a.shape[1] != 3 or a.shape[0] < 1:
        raise ValueError(f"actions must have shape (n, 3) with n >= 1, got {a.shape}")
    check_pressures(a, "action")
    if (a > max_kpa).any():
        r, c = (int(i) for i in np.argwhere(a > max_kpa)[0])
        raise PressureRangeError(f"action row {r}, column {c} (0-based): {a[r, c]:g} kPa is above the rig's "
                                 f"limit {max_kpa:g} kPa")
    return a


def deploy(rig, actions, out: str | Path, meta: dict | None = None, progress: bool = True) -> DeployResult:
    """Run ``actions`` ``(n, 3)`` real kPa on ``rig`` (module docstring); write ``out/log.csv`` and
    ``out/summary.json`` (``out`` is created; must not hold a previous log).

    Returns:
        :class:`DeployResult`; an aborted run is a normal return (the reason is in it).

    Raises:
        PressureRangeError / ValueError: bad actions or output folder (nothing was sent).
    """
    s = rig.settings
    actions = validate_actions(actions, s.max_kpa)  # before anything moves
    out = Path(out)
    if (out / "log.csv").exists() or (out / "summary.json").exists():
        raise ValueError(f"{out} already holds a deploy log; choose a new --out")
    out.mkdir(parents=True, exist_ok=True)
    clock = rig.clock
    period, dt_sample = s.control_period_s, 1.0 / s.sample_hz
    n = len(actions)
    status, reason, fail_safe_done = "completed", None, []
    counts = {"samples": 0, "overruns": 0}
    max_late = 0.0
    idn = None
    t0 = None
    bar = None
    f = (out / "log.csv").open("w", newline="", encoding="utf-8")
    w = csv.writer(f)
    w.writerow(DEPLOY_COLUMNS)
    wd = None
    main_thread = threading.current_thread() is threading.main_thread()  # signal handlers: main thread only
    caller_sigint = signal.getsignal(signal.SIGINT) if main_thread else None
    last = {"cmd": np.zeros(3), "set_v": np.zeros(3), "step": -1}

    def row(meas_v, sensed, overrun=0, event="", t_abs=None):
        now = clock.now() if t_abs is None else t_abs
        t = now - (t0 if t0 is not None else now)
        w.writerow([f"{t:.4f}", last["step"], *(f"{x:.3f}" for x in last["cmd"]),
                    *(f"{x:.3f}" for x in last["set_v"]), *(f"{x:.4f}" for x in meas_v),
                    *(f"{x:.3f}" for x in sensed), int(overrun), event])

    try:
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n, desc=f"deploy on {rig.name}", unit="action")
        idn = rig.start()
        watch_thread = not getattr(rig, "simulated", False) and main_thread
        if watch_thread:
            # the watchdog thread breaks a hung call with SIGINT: it must raise KeyboardInterrupt even
            # where the caller ignores SIGINT (a background job of a non-interactive shell does)
            signal.signal(signal.SIGINT, signal.default_int_handler)
        wd = _Watchdog(clock, s.watchdog_s, thread=watch_thread)
        t0 = clock.now()
        disagree_since = None
        for k in range(n):
            deadline = t0 + k * period
            t_cmd = clock.now()  # the post-set row is stamped when the command is sent
            late = t_cmd - deadline
            overrun = late > s.overrun_tolerance_s
            counts["overruns"] += int(overrun)
            max_late = max(max_late, late)
            last["set_v"] = rig.source.set_kpa(actions[k])
            last["cmd"], last["step"] = actions[k], k
            wd.check(f"setting action {k}")
            row(np.full(3, np.nan), rig.sensors.read_kpa(), overrun, "late" if overrun else "", t_abs=t_cmd)
            wd.check("reading the sensors")
            counts["samples"] += 1
            next_sample = clock.now()
            while True:
                t_sample = clock.now()  # rows are stamped when their sample starts (inside the hold)
                meas_v = rig.source.measure_volts()
                wd.check("reading the supply")
                sensed = rig.sensors.read_kpa()
                wd.check("reading the sensors")
                row(meas_v, sensed, t_abs=t_sample)
                counts["samples"] += 1
                bad = np.abs(sensed - last["cmd"]) > s.disagreement_kpa  # NaN (no sensors) compares False
                now = clock.now()
                if bad.any():
                    disagree_since = now if disagree_since is None else disagree_since
                    if now - disagree_since >= s.disagreement_s:
                        i = int(np.flatnonzero(bad)[0])
                        raise SafetyTrip(f"sensor/command disagreement: regulator {i + 1} sensed {sensed[i]:.1f} kPa "
                                         f"vs commanded {last['cmd'][i]:.1f} kPa for {now - disagree_since:.2f} s "
                                         f"(limit {s.disagreement_kpa:g} kPa for {s.disagreement_s:g} s)")
                else:
                    disagree_since = None
                next_sample += dt_sample
                end = t0 + (k + 1) * period
                if next_sample >= end:
                    clock.sleep(end - clock.now())
                    wd.check("the sample loop")
                    break
                clock.sleep(next_sample - clock.now())
                wd.check("the sample loop")
            if bar is not None:
                bar.update(1)
    except KeyboardInterrupt:
        status = "aborted"
        reason = "watchdog: the loop hung inside a call" if wd is not None and wd.fired else "interrupted (Ctrl-C)"
    except SafetyTrip as exc:
        status, reason = "aborted", one_line(exc)
    except (SupplyError, SensorError) as exc:  # the message says which: lost connection, sensor fault, ...
        status, reason = "aborted", f"rig fault: {one_line(exc)}"
    except Exception as exc:  # any fault: fail safe, record it
        status, reason = "aborted", f"exception: {type(exc).__name__}: {one_line(exc)}"
    finally:
        # a further Ctrl-C must not interrupt the shutdown: ignore SIGINT until the lines are vented
        if main_thread:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        if wd is not None:
            wd.stop()
        if bar is not None:
            bar.close()
        try:
            fail_safe_done = rig.fail_safe()
        finally:
            if main_thread:  # the caller's handler (None: one not set from Python; the default then)
                signal.signal(signal.SIGINT, signal.default_int_handler if caller_sigint is None else caller_sigint)
        last["cmd"], last["set_v"], last["step"] = np.zeros(3), np.full(3, np.nan), -1  # step -1: not an action
        event = ("fail-safe: " + reason if reason else "completed") + "; " + "; ".join(fail_safe_done)
        row(np.full(3, np.nan), np.full(3, np.nan), 0, event)
        f.close()
        rig.close()
    elapsed = (clock.now() - t0) if t0 is not None else 0.0
    summary = {
        "status": status, "reason": reason, "fail_safe": fail_safe_done, "rig": rig.name, "simulated": rig.simulated,
        "supply_idn": idn, "n_actions": n, "actions_kpa": actions.tolist(), "control_period_s": period,
        "sample_hz_target": s.sample_hz, "samples": counts["samples"],
        "sample_hz_achieved": counts["samples"] / elapsed if elapsed > 0 else None,
        "elapsed_s": elapsed, "overruns": counts["overruns"], "max_lateness_s": max_late,
        "overrun_tolerance_s": s.overrun_tolerance_s, "settings": dict(s.__dict__), **(meta or {}),
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_json_default) + "\n")
    return DeployResult(status, reason, fail_safe_done, summary, str(out))


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)
