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
  ``disagreement_s``), **any exception** (a failed write of the log included: a full disk, a
  file-size limit), and the **stop signals** SIGINT (Ctrl-C), SIGTERM (``kill``, ``timeout``),
  SIGHUP (a closed terminal or SSH session; a SIGHUP the caller ignores, as under ``nohup``,
  stays ignored) and SIGQUIT. Their handlers are installed for the duration of the deploy only
  (main thread) and the caller's are restored afterwards; a further signal during the shutdown
  is recorded (``signals_during_shutdown``), not obeyed. The reason goes into the log's last
  row, the summary (``status: "aborted"``, ``reason``, ``signal``, ``fail_safe``) and the
  return value. A completed run vents and turns the outputs off too;
- the fail-safe reads back what it did (:meth:`Rig.fail_safe`): the 0 V settings
  (``APP:VOLT?``) and the outputs off (``OUTP?``, then ``MEAS:VOLT:ALL?`` at most
  :data:`softcrawl.hardware.supply.OFF_TOL_V` per channel). When that cannot be read back,
  ``fail_safe_confirmed`` is false in the summary and the result, and the log's last row says
  so: the supply may still be on;
- ``log.csv`` gets its header at once and every row is flushed as it is written, so a kill that
  no handler can catch (SIGKILL, a power cut) loses at most the row being written; a log or
  summary that cannot be written is reported (``log_error``, ``write_errors``), the rig is
  vented all the same.
"""

from __future__ import annotations

import csv
import json
import math
import os
import signal
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softcrawl.hardware.errors import SafetyTrip, SensorError, SupplyError, one_line
from softcrawl.hardware.logs import DEPLOY_COLUMNS
from softcrawl.robot.actuation import PressureRangeError, check_pressures
from softcrawl.safeio import atomic_write_text

#: Signals that stop a deploy through the fail-safe (those this platform has).
STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP", "SIGQUIT") if hasattr(signal, n))


@dataclass
class DeployResult:
    """Outcome of :func:`deploy`: ``status`` ``"completed"`` or ``"aborted"``, ``reason`` (None
    when completed), ``fail_safe`` (what the shutdown did, one line per step),
    ``fail_safe_confirmed`` (the supply read back 0 V set and outputs off), ``summary`` (the
    JSON written), ``write_errors`` (``log.csv`` or ``summary.json`` writes that failed; empty
    when both were written)."""

    status: str
    reason: str | None
    fail_safe: list
    summary: dict = field(default_factory=dict)
    out: str = ""
    fail_safe_confirmed: bool = False
    write_errors: list = field(default_factory=list)


class StopSignal(KeyboardInterrupt):
    """A stop signal (:data:`STOP_SIGNALS`) arrived during a deploy. A ``KeyboardInterrupt``
    (a ``BaseException``), so that no driver's ``except Exception`` can swallow it."""

    def __init__(self, signum: int) -> None:
        self.signum = int(signum)
        super().__init__(signal.Signals(signum).name)


class _SignalGuard:
    """Handlers of :data:`STOP_SIGNALS` while a deploy runs (main thread only; elsewhere a no-op).

    Until :meth:`shield`, a signal raises :class:`StopSignal` in the main thread; after it,
    signals are only recorded in ``late`` (the shutdown must finish). :meth:`restore` puts the
    caller's handlers back. SIGINT is always handled (the watchdog thread interrupts a hung
    call with it, even where the caller ignores SIGINT); another signal the caller ignores
    stays ignored."""

    def __init__(self) -> None:
        self.active = threading.current_thread() is threading.main_thread()
        self.saved: dict = {}
        self.shielded = False
        self.late: list[str] = []

    def install(self) -> None:
        if not self.active:
            return
        for s in STOP_SIGNALS:
            old = signal.getsignal(s)
            if old is signal.SIG_IGN and s != signal.SIGINT:
                continue
            self.saved[s] = old
            signal.signal(s, self._handle)

    def _handle(self, signum, frame) -> None:
        if self.shielded:
            self.late.append(signal.Signals(signum).name)
            return
        self.shielded = True  # a second signal must not interrupt the handling of the first
        raise StopSignal(signum)

    def shield(self) -> None:
        self.shielded = True

    def restore(self) -> None:
        for s, old in self.saved.items():
            # None: a handler not set from Python; the default then
            default = signal.default_int_handler if s == signal.SIGINT else signal.SIG_DFL
            signal.signal(s, default if old is None else old)
        self.saved = {}


class _LogWriteError(Exception):
    """Writing ``log.csv`` failed (full disk, file-size limit, a vanished folder)."""


class _Log:
    """``log.csv``: created exclusively (an existing file or a symlink at its place is refused),
    header written at once, every row flushed as written. A failed write raises
    :class:`_LogWriteError`; the first failure is kept in ``error``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.error: str | None = None
        self.f = path.open("x", newline="", encoding="utf-8")
        self._w = csv.writer(self.f)
        self.write(DEPLOY_COLUMNS)

    def write(self, row) -> None:
        try:
            self._w.writerow(row)
            self.f.flush()
        except OSError as exc:
            self.error = self.error or f"writing {self.path} failed: {one_line(exc)}"
            raise _LogWriteError(self.error) from None

    def close(self) -> None:
        try:
            self.f.close()
        except OSError as exc:  # the unflushed rows could not be written: the file is closed anyway
            self.error = self.error or f"writing {self.path} failed: {one_line(exc)}"


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


def check_regulators(space_regulators: int, rig_regulators: int, where: str) -> None:
    """Refuse a gait of a design space with another number of regulators than the rig has
    (a policy's actions are one pressure per regulator of its run's space).

    Args:
        space_regulators: regulators of the design space the gait was made for.
        rig_regulators: regulators of the rig config (``len(RigConfig.regulators)``).
        where: what the gait came from, named in the message (a run, a space).

    Raises:
        ValueError: one line, when the counts differ.
    """
    if space_regulators != rig_regulators:
        raise ValueError(f"{where} drives {space_regulators} regulators but the rig config has {rig_regulators}; "
                         "refusing to deploy")


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


def _reason(exc: BaseException, wd) -> str:
    """The summary's ``reason`` for the exception that ended the loop."""
    if isinstance(exc, KeyboardInterrupt) and wd is not None and wd.fired:
        return "watchdog: the loop hung inside a call"
    if isinstance(exc, StopSignal) and exc.signum != signal.SIGINT:
        return f"stopped by signal {signal.Signals(exc.signum).name}"
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted (Ctrl-C, SIGINT)"
    if isinstance(exc, (SafetyTrip, _LogWriteError)):
        return one_line(exc)
    if isinstance(exc, (SupplyError, SensorError)):  # the message says which: lost connection, sensor fault, ...
        return f"rig fault: {one_line(exc)}"
    return f"exception: {type(exc).__name__}: {one_line(exc)}"


def deploy(rig, actions, out: str | Path, meta: dict | None = None, progress: bool = True) -> DeployResult:
    """Run ``actions`` ``(n, 3)`` real kPa on ``rig`` (module docstring); write ``out/log.csv`` and
    ``out/summary.json`` (``out`` is created; must not hold a previous log).

    Returns:
        :class:`DeployResult`; an aborted run is a normal return (the reason is in it), and so
        is a run whose log or summary could not be written (``write_errors``).

    Raises:
        PressureRangeError / ValueError: bad actions or output folder (nothing was sent).
        OSError: ``log.csv`` cannot be created (nothing was sent).
    """
    s = rig.settings
    actions = validate_actions(actions, s.max_kpa)  # before anything moves
    out = Path(out)
    if any(os.path.lexists(out / f) for f in ("log.csv", "summary.json")):
        raise ValueError(f"{out} already holds a deploy log; choose a new --out")
    out.mkdir(parents=True, exist_ok=True)
    clock = rig.clock
    period, dt_sample = s.control_period_s, 1.0 / s.sample_hz
    n = len(actions)
    status, reason, fail_safe = "aborted", "stopped during the shutdown", None
    counts = {"samples": 0, "overruns": 0}
    max_late = 0.0
    idn = None
    t0 = None
    bar = None
    log = _Log(out / "log.csv")
    wd = None
    guard = _SignalGuard()
    stop_signal = None
    last = {"cmd": np.zeros(3), "set_v": np.zeros(3), "step": -1}

    def row(meas_v, sensed, overrun=0, event="", t_abs=None):
        now = clock.now() if t_abs is None else t_abs
        t = now - (t0 if t0 is not None else now)
        log.write([f"{t:.4f}", last["step"], *(f"{x:.3f}" for x in last["cmd"]),
                   *(f"{x:.3f}" for x in last["set_v"]), *(f"{x:.4f}" for x in meas_v),
                   *(f"{x:.3f}" for x in sensed), int(overrun), event])

    guard.install()
    try:
        if progress:
            from tqdm import tqdm

            bar = tqdm(total=n, desc=f"deploy on {rig.name}", unit="action")
        idn = rig.start()
        wd = _Watchdog(clock, s.watchdog_s, thread=not getattr(rig, "simulated", False) and guard.active)
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
        status, reason = "completed", None
    except BaseException as exc:  # every way out of the loop goes through the fail-safe below
        guard.shield()
        status, reason = "aborted", _reason(exc, wd)
        stop_signal = signal.Signals(exc.signum).name if isinstance(exc, StopSignal) else None
    finally:
        try:
            guard.shield()  # a further signal must not interrupt the shutdown
            if wd is not None:
                wd.stop()
            try:
                if bar is not None:
                    bar.close()
            except Exception:  # a closed terminal: the shutdown goes on
                pass
            fail_safe = rig.fail_safe()
            last["cmd"], last["set_v"], last["step"] = np.zeros(3), np.full(3, np.nan), -1  # step -1: not an action
            event = ("fail-safe: " + reason if reason else "completed") + "; " + "; ".join(fail_safe.steps)
            if not fail_safe.confirmed:
                event += "; FAIL-SAFE NOT CONFIRMED: the supply may still be on"
            try:
                row(np.full(3, np.nan), np.full(3, np.nan), 0, event)
            except _LogWriteError:
                pass  # kept in log.error, reported in the summary
            log.close()
            rig.close()
            elapsed = (clock.now() - t0) if t0 is not None else 0.0
            summary = {
                "status": status, "reason": reason, "fail_safe": fail_safe.steps,
                "fail_safe_confirmed": fail_safe.confirmed, "signal": stop_signal,
                "signals_during_shutdown": guard.late, "log_error": log.error, "rig": rig.name,
                "simulated": rig.simulated, "supply_idn": idn, "n_actions": n, "actions_kpa": actions.tolist(),
                "control_period_s": period, "sample_hz_target": s.sample_hz, "samples": counts["samples"],
                "sample_hz_achieved": counts["samples"] / elapsed if elapsed > 0 else None,
                "elapsed_s": elapsed, "overruns": counts["overruns"], "max_lateness_s": max_late,
                "overrun_tolerance_s": s.overrun_tolerance_s, "settings": dict(s.__dict__), **(meta or {}),
            }
            errors = [log.error] if log.error else []
            try:
                atomic_write_text(out / "summary.json", json.dumps(summary, indent=2, default=_json_default) + "\n")
            except OSError as exc:
                errors.append(f"writing {out / 'summary.json'} failed: {one_line(exc)}")
        finally:
            guard.restore()  # the caller's handlers, even if the shutdown failed
    return DeployResult(status, reason, fail_safe.steps, summary, str(out), fail_safe.confirmed, errors)


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    return str(o)
