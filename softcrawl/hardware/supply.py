"""Driver of the BK Precision 9129B programmable triple-output DC supply (SCPI over its
USB-serial port, 9600 baud 8N1, ``\\n`` terminated), which commands the three pressure
regulators with analog voltages in the paper's rig.

SCPI used (BK Precision 9129B/9130B-series programming manual, "SCPI essential commands",
APPLy / MEASure / OUTPut / SYSTem subsystems; the same set as the issue #19 rig notes)::

    *IDN?                    -> "B&K Precision, 9129B, <serial>, <firmware>"
    SYST:REM                 remote mode (front panel locked)
    APP:VOLT a,b,c           set the three channel voltages at once, V
    APP:VOLT?                -> "a, b, c" the set voltages, V
    MEAS:VOLT:ALL?           -> "a, b, c" the measured output voltages, V
    OUTP 1 / OUTP 0          all outputs on / off
    OUTP?                    -> "1" / "0" (also "ON" / "OFF") whether the outputs are on
    SYST:LOC                 back to local (front panel) control

The driver is written against any object with ``write(str)``, ``query(str) -> str`` and
``close()`` (a pyvisa ``MessageBasedResource`` or the simulated instrument of
:mod:`softcrawl.hardware.simrig`), so the exact exchange is testable without hardware. Every
setting is verified by reading it back and re-sent up to ``retries`` times (as B&K's own
example driver does); a voltage beyond a channel's limit is refused before anything is sent.
"""

from __future__ import annotations

import time

import numpy as np

from softcrawl.hardware.errors import SupplyError, VoltageLimitError, one_line

#: Hardware maximum output of each 9129B channel, V (channel 3 is the 5 V channel).
BK9129B_MAX_V = (30.0, 30.0, 5.0)
#: A channel measuring at most this much with its output off counts as off, V (the 9129B's
#: voltage read-back resolution is 1 mV; 0.05 V is 1 kPa on the example rig's 0.05 V/kPa maps).
OFF_TOL_V = 0.05
#: How long a late answer to a query cut short may take to arrive, s: the longest answer
#: (``*IDN?``, about 55 bytes) takes 57 ms at 9600 baud, plus the instrument's reply latency.
LATE_ANSWER_S = 0.2
#: Serial settings of the 9129B's USB-serial (VCP) interface.
SERIAL = {"baud_rate": 9600, "data_bits": 8, "parity": "none", "stop_bits": "one", "termination": "\n"}


def format_volts(v) -> str:
    """SCPI argument list for ``APP:VOLT``: three voltages with 3 decimals (1 mV resolution)."""
    return ",".join(f"{float(x):.3f}" for x in v)


def parse_triple(text: str, what: str) -> np.ndarray:
    """Parse ``"a, b, c"`` into ``(3,)`` float V.

    Raises:
        SupplyError: not three finite numbers.
    """
    try:
        vals = np.array([float(s) for s in str(text).strip().split(",")])
    except ValueError:
        raise SupplyError(f"supply: unreadable answer to {what}: {text!r}") from None
    if vals.shape != (3,) or not np.isfinite(vals).all():
        raise SupplyError(f"supply: expected 3 values from {what}, got {text!r}")
    return vals


class BK9129B:
    """The supply as a 3-channel :class:`VoltageSupply`.

    Args:
        resource: connected message-based resource (``write``, ``query``, ``close``).
        max_v: ``(3,)`` per-channel voltage limits, V (each within :data:`BK9129B_MAX_V`).
        retries: attempts per setting before giving up (>= 1).
        tol_v: read-back tolerance, V.

    Raises:
        VoltageLimitError: a limit is outside the hardware range.
    """

    def __init__(self, resource, max_v=BK9129B_MAX_V, retries: int = 3, tol_v: float = 0.005) -> None:
        max_v = np.asarray(max_v, dtype=float)
        if max_v.shape != (3,) or not np.isfinite(max_v).all() or (max_v <= 0).any() or \
                (max_v > np.array(BK9129B_MAX_V)).any():
            raise VoltageLimitError(f"supply voltage limits {max_v.tolist()} must be in (0, {list(BK9129B_MAX_V)}] V")
        if int(retries) < 1:
            raise ValueError(f"retries must be >= 1, got {retries}")
        self.resource = resource
        self.max_v = max_v
        self.retries = int(retries)
        self.tol_v = float(tol_v)
        self._unanswered = False

    @classmethod
    def open(cls, address: str, timeout_ms: int = 1000, backend: str = "@py", **kwargs) -> BK9129B:
        """Connect through pyvisa + pyvisa-py (``pip install softcrawl[rig]``).

        Args:
            address: VISA resource name, e.g. ``"ASRL/dev/ttyUSB0::INSTR"``.
            timeout_ms: I/O timeout, ms.
            backend: pyvisa backend (``"@py"``: pyvisa-py; tests use ``"file.yaml@sim"``, pyvisa-sim).

        Raises:
            SupplyError: pyvisa missing, or the port cannot be opened.
        """
        try:
            import pyvisa
            from pyvisa.constants import Parity, StopBits
        except ImportError:
            raise SupplyError("talking to a real supply needs pyvisa: pip install 'softcrawl[rig]'") from None
        try:
            rm = pyvisa.ResourceManager(backend)
            res = rm.open_resource(address, baud_rate=SERIAL["baud_rate"], data_bits=SERIAL["data_bits"],
                                   parity=Parity.none, stop_bits=StopBits.one, read_termination="\n",
                                   write_termination="\n", timeout=int(timeout_ms))
        except Exception as exc:  # pyvisa raises many types (VisaIOError, ValueError, OSError)
            raise SupplyError(f"supply: cannot open {address}: {one_line(exc)}") from None
        return cls(res, **kwargs)

    # -- raw exchange (every I/O error is a lost connection) --
    def _write(self, cmd: str) -> None:
        try:
            self.resource.write(cmd)
        except Exception as exc:
            raise SupplyError(f"supply: lost connection sending {cmd!r}: {one_line(exc)}") from None

    def _query(self, cmd: str) -> str:
        if self._unanswered:
            self._discard_late_answer()
        self._unanswered = True  # until the answer is read: a signal or a timeout can cut the query short
        try:
            ans = str(self.resource.query(cmd))
        except Exception as exc:
            raise SupplyError(f"supply: lost connection on {cmd!r}: {one_line(exc)}") from None
        self._unanswered = False
        return ans

    def _discard_late_answer(self) -> None:
        """Drop the answer of a query that was cut short (a signal, a timeout): it arrives late and
        would otherwise be read as the next query's answer. Waits :data:`LATE_ANSWER_S` for it,
        then discards the resource's input buffer (pyvisa ``flush``; a resource without one has
        no buffer to discard)."""
        self._unanswered = False
        flush = getattr(self.resource, "flush", None)
        if flush is None:
            return
        time.sleep(LATE_ANSWER_S)
        try:
            from pyvisa.constants import BufferOperation

            flush(BufferOperation.discard_read_buffer)
        except Exception:  # nothing to discard, or the port is gone: the query that follows says which
            pass

    # -- commands --
    def identify(self) -> str:
        """``*IDN?``; raises SupplyError unless it names a 9129B."""
        idn = self._query("*IDN?").strip()
        if "9129" not in idn:
            raise SupplyError(f"supply: expected a BK Precision 9129B, *IDN? answered {idn!r}")
        return idn

    def remote(self) -> None:
        """``SYST:REM``: remote mode."""
        self._write("SYST:REM")

    def local(self) -> None:
        """``SYST:LOC``: front panel back in control."""
        self._write("SYST:LOC")

    def check_volts(self, volts) -> np.ndarray:
        """``(3,)`` V checked against the channel limits (VoltageLimitError otherwise)."""
        v = np.asarray(volts, dtype=float)
        if v.shape != (3,):
            raise VoltageLimitError(f"need 3 channel voltages, got shape {v.shape}")
        bad = ~np.isfinite(v) | (v < 0) | (v > self.max_v)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise VoltageLimitError(f"channel {i + 1}: {v[i]:g} V is outside [0, {self.max_v[i]:g}] V; nothing sent")
        return np.round(v, 3)

    def set_volts(self, volts) -> np.ndarray:
        """Set all three channels (``APP:VOLT a,b,c``), verified with ``APP:VOLT?``.

        Returns:
            ``(3,)`` the set voltages as read back, V.

        Raises:
            VoltageLimitError: before sending, for a voltage beyond a limit.
            SupplyError: lost connection, or still wrong after ``retries`` attempts.
        """
        v = self.check_volts(volts)
        readback = None
        for _ in range(self.retries):
            self._write(f"APP:VOLT {format_volts(v)}")
            readback = parse_triple(self._query("APP:VOLT?"), "APP:VOLT?")
            if np.all(np.abs(readback - v) <= self.tol_v):
                return readback
        raise SupplyError(f"supply: set {v.tolist()} V but it reads back {readback.tolist()} V "
                          f"after {self.retries} attempts")

    def measure_volts(self) -> np.ndarray:
        """``MEAS:VOLT:ALL?``: ``(3,)`` measured output voltages, V."""
        return parse_triple(self._query("MEAS:VOLT:ALL?"), "MEAS:VOLT:ALL?")

    def output_on(self) -> bool:
        """``OUTP?``: whether the outputs are on.

        Raises:
            SupplyError: lost connection or an answer other than 1 / 0 / ON / OFF.
        """
        ans = self._query("OUTP?").strip().upper()
        if ans not in ("1", "0", "ON", "OFF"):
            raise SupplyError(f"supply: unreadable answer to OUTP?: {ans!r}")
        return ans in ("1", "ON")

    def output(self, on: bool) -> None:
        """``OUTP 1`` / ``OUTP 0``: all outputs on or off, verified with ``OUTP?`` and re-sent up
        to ``retries`` times.

        Raises:
            SupplyError: lost connection, or the outputs still read back wrong after the retries.
        """
        for _ in range(self.retries):
            self._write("OUTP 1" if on else "OUTP 0")
            if self.output_on() == bool(on):
                return
        raise SupplyError(f"supply: sent OUTP {int(bool(on))} but OUTP? still reads {'off' if on else 'on'} "
                          f"after {self.retries} attempts")

    def confirm_zero(self, tol_v: float = OFF_TOL_V) -> np.ndarray:
        """Measure every channel (``MEAS:VOLT:ALL?``) and check it is at most ``tol_v`` (after
        ``output(False)``, which read back ``OUTP?``). Returns the ``(3,)`` measured voltages, V.

        Raises:
            SupplyError: lost connection, or a channel measuring more than ``tol_v``.
        """
        v = self.measure_volts()
        if (np.abs(v) > tol_v).any():
            raise SupplyError(f"supply: outputs read back off but measure {format_volts(v)} V "
                              f"(more than {tol_v:g} V)")
        return v

    def close(self) -> None:
        try:
            self.resource.close()
        except Exception:  # closing a dead port must not mask the reason we are closing
            pass

