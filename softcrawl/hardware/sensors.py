"""Pressure sensors: Honeywell SSC on I2C, and a replay of a recorded log.

A sensor bank has ``read_kpa() -> (3,)`` gauge kPa, regulator order 1, 2, 3, and ``zero()``
(take the atmospheric reference with all lines vented).

**Honeywell TruStability SSCMANV030PA2A3** (the later rig's sensors; Honeywell "TruStability
Board Mount Pressure Sensors, SSC Series" datasheet and the technical note "I2C Communications
with Honeywell Digital Output Pressure Sensors"): I2C address 0x28 (the ``2`` in ``...PA2A3``),
0-30 psi *absolute* (``030PA``), transfer function A: 10-90 % of 2^14 counts, i.e. output
1638 counts at 0 psi and 14745 at 30 psi. A 2-byte read returns ``S1 S0 B13..B0``: status
bits 00 = normal, 01 = command mode, 10 = stale data (already read), 11 = diagnostic fault.
An absolute sensor reads about 101 kPa at rest, so gauge pressure needs an atmospheric zero.
All three sensors have the same fixed address: put them on separate buses or behind an I2C
multiplexer (TCA9548A, address 0x70, channel select byte ``1 << channel``).
"""

from __future__ import annotations

import math

import numpy as np

from softcrawl.hardware.errors import SensorError, one_line

PSI_KPA = 6.894757
SSC_ADDRESS = 0x28
SSC_COUNTS_MIN = 1638
SSC_COUNTS_MAX = 14745
SSC_P_MAX_PSI = 30.0
#: Plausible atmospheric zero of an absolute sensor, kPa (sea level to ~3,000 m).
ATMOSPHERE_KPA = (65.0, 110.0)


class SMBusDevice:
    """One I2C device through ``smbus2`` (``pip install softcrawl[rig]``), optionally behind a
    TCA9548A multiplexer channel.

    Args:
        bus: I2C bus number (``/dev/i2c-<bus>``). address: 7-bit address.
        mux_address, mux_channel: multiplexer address and channel 0..7, or None.

    Raises:
        SensorError: smbus2 missing or the bus cannot be opened.
    """

    def __init__(self, bus: int, address: int = SSC_ADDRESS, mux_address: int | None = None,
                 mux_channel: int | None = None) -> None:
        try:
            from smbus2 import SMBus
        except ImportError:
            raise SensorError("reading I2C sensors needs smbus2: pip install 'softcrawl[rig]'") from None
        try:
            self._bus = SMBus(int(bus))
        except OSError as exc:
            raise SensorError(f"cannot open I2C bus {bus}: {one_line(exc)}") from None
        self.address, self.mux_address, self.mux_channel = int(address), mux_address, mux_channel

    def read(self, n: int) -> bytes:
        """Select the mux channel (if any), then one plain ``n``-byte read transaction."""
        from smbus2 import i2c_msg

        try:
            if self.mux_address is not None:
                self._bus.write_byte(int(self.mux_address), 1 << int(self.mux_channel))
            msg = i2c_msg.read(self.address, n)
            self._bus.i2c_rdwr(msg)
            return bytes(list(msg))
        except OSError as exc:
            raise SensorError(f"I2C device 0x{self.address:02x}: {one_line(exc)}") from None

    def close(self) -> None:
        self._bus.close()


class HoneywellSSC:
    """One SSC sensor; ``device`` has ``read(n) -> bytes`` (:class:`SMBusDevice` or a fake).

    Args:
        p_max_psi: full scale, psi absolute (30 for ...030PA).
        counts: ``(min, max)`` output counts of the transfer function (1638, 14745).
    """

    def __init__(self, device, p_max_psi: float = SSC_P_MAX_PSI, counts=(SSC_COUNTS_MIN, SSC_COUNTS_MAX),
                 stale_retries: int = 3) -> None:
        self.device = device
        self.p_max_kpa = float(p_max_psi) * PSI_KPA
        self.c0, self.c1 = int(counts[0]), int(counts[1])
        self.stale_retries = int(stale_retries)

    def read_counts(self) -> tuple[int, int]:
        """``(status, counts)`` from one 2-byte read."""
        try:
            b = self.device.read(2)
        except OSError as exc:  # I2C bus errors (NACK, EREMOTEIO): the sensor is gone
            raise SensorError(f"SSC sensor: I2C read failed: {one_line(exc)}") from None
        if len(b) != 2:
            raise SensorError(f"SSC sensor: expected 2 bytes, got {len(b)}")
        return b[0] >> 6, ((b[0] & 0x3F) << 8) | b[1]

    def read_kpa_abs(self) -> float:
        """Absolute pressure, kPa.

        Raises:
            SensorError: diagnostic fault, command mode, data stale after the retries, or counts
                outside the transfer function's range (a broken bridge or wiring).
        """
        for _ in range(self.stale_retries + 1):
            status, counts = self.read_counts()
            if status != 2:
                break
        if status == 3:
            raise SensorError("SSC sensor: diagnostic fault (status 11)")
        if status == 1:
            raise SensorError("SSC sensor: in command mode (status 01)")
        if status == 2:
            raise SensorError("SSC sensor: data stale (status 10) after retries")
        if not (self.c0 - 200 <= counts <= self.c1 + 200):
            raise SensorError(f"SSC sensor: {counts} counts is outside its {self.c0}-{self.c1} range")
        return (counts - self.c0) * self.p_max_kpa / (self.c1 - self.c0)


class SSCBank:
    """Three :class:`HoneywellSSC` (regulator order) read as gauge kPa against an atmospheric zero."""

    def __init__(self, sensors) -> None:
        self.sensors = tuple(sensors)
        if len(self.sensors) != 3:
            raise ValueError(f"need 3 sensors, got {len(self.sensors)}")
        self.zero_kpa = None

    def read_abs(self) -> np.ndarray:
        return np.array([s.read_kpa_abs() for s in self.sensors])

    def zero(self, n: int = 10) -> np.ndarray:
        """Average ``n`` readings (lines vented) as the atmospheric zero ``(3,)`` kPa absolute.

        Raises:
            SensorError: a zero outside :data:`ATMOSPHERE_KPA` (the line is not vented, or the
                sensor is not an absolute sensor / is broken).
        """
        z = np.mean([self.read_abs() for _ in range(max(1, n))], axis=0)
        lo, hi = ATMOSPHERE_KPA
        if ((z < lo) | (z > hi)).any():
            raise SensorError(f"atmospheric zero {np.round(z, 1).tolist()} kPa outside {lo:g}-{hi:g} kPa: "
                              "lines not vented or a sensor is faulty")
        self.zero_kpa = z
        return z

    def read_kpa(self) -> np.ndarray:
        """Gauge pressures ``(3,)`` kPa (needs :meth:`zero` first)."""
        if self.zero_kpa is None:
            raise SensorError("sensors not zeroed: call zero() with the lines vented")
        return self.read_abs() - self.zero_kpa

    def close(self) -> None:
        for s in self.sensors:
            close = getattr(s.device, "close", None)
            if close:
                close()


class ReplaySensor:
    """Sensed pressures replayed from a log: ``times_s (m,)`` and ``kpa (m, 3)``; ``read_kpa``
    returns the last sample at or before ``clock.now() - t_start`` (the first before it)."""

    def __init__(self, times_s, kpa, clock) -> None:
        self.t = np.asarray(times_s, dtype=float)
        self.kpa = np.asarray(kpa, dtype=float)
        if self.t.ndim != 1 or self.kpa.shape != (self.t.size, 3) or self.t.size == 0:
            raise ValueError(f"replay needs times (m,) and pressures (m, 3), got {self.t.shape}, {self.kpa.shape}")
        self.clock = clock
        self.t_start = None

    @classmethod
    def from_trial(cls, trial, clock) -> ReplaySensor:
        """Replay the sensed pressures of a :class:`softcrawl.hardware.logs.RecordedTrial`."""
        return cls(trial.t_s, trial.sensed_kpa, clock)

    def zero(self, n: int = 10) -> np.ndarray:
        self.t_start = self.clock.now()
        return np.zeros(3)

    def read_kpa(self) -> np.ndarray:
        if self.t_start is None:
            self.t_start = self.clock.now()
        i = int(np.searchsorted(self.t, self.clock.now() - self.t_start, side="right")) - 1
        return self.kpa[max(i, 0)].copy()

    def close(self) -> None:
        pass


def counts_for_kpa_abs(kpa_abs: float, p_max_psi: float = SSC_P_MAX_PSI) -> int:
    """Inverse of the SSC transfer function (used by the simulated sensor): counts for kPa absolute."""
    c = SSC_COUNTS_MIN + kpa_abs / (p_max_psi * PSI_KPA) * (SSC_COUNTS_MAX - SSC_COUNTS_MIN)
    return int(min(max(round(c), 0), 0x3FFF)) if math.isfinite(c) else 0
