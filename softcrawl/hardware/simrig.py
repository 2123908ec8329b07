"""A simulated rig for tests and dry runs (``softcrawl deploy --rig sim``).

- :class:`FakeBK9129B`: the supply as a fake message-based resource (the interface pyvisa
  gives the driver: ``write``, ``query``, ``close``). It accepts only the exact SCPI exchange of
  :mod:`softcrawl.hardware.supply` (write for settings, query for ``?`` commands, 3-decimal
  voltages within the hardware limits) and raises :class:`SCPIProtocolError` on anything else;
  it keeps the full transcript; serial I/O costs simulated time (10 bits per byte at 9600 baud).
- :class:`SimRegulators`: three regulators with the first-order inflate / vent lags and the
  gain / offset fitted to the recorded real logs (:data:`softcrawl.hardware.regulator_model.FITTED`),
  driven by the supply's output voltages through the rig's kPa-to-volt maps.
- :class:`FakeSSCDevice`: a Honeywell SSC answering 2-byte reads with status and counts of
  ``atmosphere + pressure + noise``, read through the real :class:`HoneywellSSC` driver.
- :class:`SimClock` time with a sleep jitter.

Each fake has fault-injection knobs (a lost connection from exchange N on, a slow exchange,
ignored settings, a stuck or faulty sensor) used by the fail-safe tests.
"""

from __future__ import annotations

import re

import numpy as np

from softcrawl.hardware.clock import SimClock
from softcrawl.hardware.config import RigConfig, RigSettings, load_rig_config, example_rig_path
from softcrawl.hardware.regulator_model import FITTED
from softcrawl.hardware.sensors import HoneywellSSC, SSCBank, counts_for_kpa_abs
from softcrawl.hardware.source import PressureSource
from softcrawl.hardware.supply import BK9129B, BK9129B_MAX_V

IDN = "B&K Precision, 9129B, SIM0001, 1.00-1.00"
_V = r"(\d{1,2}\.\d{3})"
_WRITES = {
    "SYST:REM": re.compile(r"SYST:REM"),
    "SYST:LOC": re.compile(r"SYST:LOC"),
    "APP:VOLT": re.compile(rf"APP:VOLT {_V},{_V},{_V}"),
    "OUTP": re.compile(r"OUTP ([01])"),
}
_QUERIES = ("*IDN?", "APP:VOLT?", "MEAS:VOLT:ALL?", "OUTP?")


class SCPIProtocolError(AssertionError):
    """The driver sent something the exact exchange does not allow."""


class FakeBK9129B:
    """Fake serial resource of a BK 9129B (see module docstring).

    Attributes:
        transcript: ``[(">", sent), ("<", answer), ...]``.
        set_v: ``(3,)`` set voltages; ``on``: outputs on; ``remote``: in remote mode.
        fail_from: exchange index from which every call raises ``ConnectionError`` (a pulled cable).
        slow: ``{exchange index: extra seconds}`` (a stalled port).
        ignore_sets: how many ``APP:VOLT`` settings to silently drop (a garbled line).
        stuck_on: ``OUTP 0`` is acknowledged but the outputs stay on (a failed output relay).

    Args:
        clock: the :class:`SimClock` charged with the serial I/O time, or None (no time charged:
            a fake served on a real port, :mod:`softcrawl.hardware.ptysupply`).
    """

    def __init__(self, clock: SimClock | None, baud: int = 9600) -> None:
        self.clock = clock
        self.baud = baud
        self.transcript: list[tuple[str, str]] = []
        self.set_v = np.zeros(3)
        self.on = False
        self.remote = False
        self.closed = False
        self.fail_from: int | None = None
        self.fail_when = None
        self.slow: dict[int, float] = {}
        self.ignore_sets = 0
        self.stuck_on = False
        self.n = 0
        self._rng = np.random.default_rng(1)

    def _io(self, text: str, answer: str = "") -> None:
        i = self.n
        self.n += 1
        if self.closed:
            raise SCPIProtocolError(f"{text!r} sent after close()")
        if (self.fail_from is not None and i >= self.fail_from) or (self.fail_when and self.fail_when(text)):
            raise ConnectionError("simulated: device disconnected (USB-serial port vanished)")
        n_bytes = len(text) + 1 + (len(answer) + 1 if answer else 0)
        if self.clock is not None:
            self.clock.advance(n_bytes * 10 / self.baud + self.slow.get(i, 0.0))

    def write(self, cmd: str) -> None:
        for name, rx in _WRITES.items():
            m = rx.fullmatch(cmd)
            if m:
                break
        else:
            raise SCPIProtocolError(f"not in the allowed SCPI exchange: write {cmd!r}")
        self._io(cmd)
        self.transcript.append((">", cmd))
        if name == "SYST:REM":
            self.remote = True
        elif name == "SYST:LOC":
            self.remote = False
        elif name == "OUTP":
            self.on = m.group(1) == "1" or (self.on and self.stuck_on)
        elif name == "APP:VOLT":
            if not self.remote:
                raise SCPIProtocolError("APP:VOLT before SYST:REM")
            v = np.array([float(g) for g in m.groups()])
            if (v > np.array(BK9129B_MAX_V)).any():
                raise SCPIProtocolError(f"{cmd!r}: beyond the hardware limits {BK9129B_MAX_V} V")
            if self.ignore_sets > 0:
                self.ignore_sets -= 1
            else:
                self.set_v = v

    def output_v(self) -> np.ndarray:
        """What the outputs actually drive, V."""
        return self.set_v.copy() if self.on else np.zeros(3)

    def query(self, cmd: str) -> str:
        if cmd not in _QUERIES:
            raise SCPIProtocolError(f"not in the allowed SCPI exchange: query {cmd!r}")
        if cmd == "*IDN?":
            ans = IDN
        elif cmd == "APP:VOLT?":
            ans = ", ".join(f"{x:.3f}" for x in self.set_v)
        elif cmd == "OUTP?":
            ans = "1" if self.on else "0"
        else:
            ans = ", ".join(f"{x:.3f}" for x in self.output_v() + self._rng.normal(0, 0.0005, 3) * self.on)
        self._io(cmd, ans)
        self.transcript.append((">", cmd))
        self.transcript.append(("<", ans))
        return ans

    def close(self) -> None:
        self.closed = True

    def sent(self) -> list[str]:
        """Everything the driver sent, in order."""
        return [t for d, t in self.transcript if d == ">"]


class SimRegulators:
    """Three simulated regulators (pressure state ``p`` ``(3,)`` kPa) fed by ``supply``'s output
    voltages through ``maps``; integrates exactly on every advance of ``clock``.

    Attributes:
        params: 3 :class:`RegulatorParams` (default: fitted to the recorded logs).
        leak: ``(3,)`` multiplier of each regulator's target (1 = healthy; 0.2 = a burst leg).
    """

    def __init__(self, supply: FakeBK9129B, maps, clock: SimClock, params=FITTED) -> None:
        self.supply, self.maps, self.params = supply, tuple(maps), tuple(params)
        self.p = np.zeros(3)
        self.leak = np.ones(3)
        clock.on_advance(self._advance)

    def commanded_kpa(self) -> np.ndarray:
        v = self.supply.output_v()
        return np.array([max(m.kpa(v[m.channel - 1]), 0.0) for m in self.maps])

    def _advance(self, t0: float, t1: float) -> None:
        c = self.commanded_kpa()
        self.p = np.array([prm.advance(p, cmd * lk, t1 - t0) for prm, p, cmd, lk in zip(self.params, self.p, c,
                                                                                         self.leak)])


class FakeSSCDevice:
    """A Honeywell SSC on the fake bus: ``read(2)`` -> status + counts of the regulator's pressure.

    Attributes:
        stuck_kpa: report this gauge pressure forever (an unplugged tube), or None.
        status: status bits to report (0 normal, 3 diagnostic fault).
        fail: raise OSError (I2C bus error) on every read.
    """

    def __init__(self, plant: SimRegulators, index: int, noise_kpa: float = 0.5, atmosphere_kpa: float = 101.3,
                 seed: int = 0) -> None:
        self.plant, self.index, self.noise, self.atm = plant, index, noise_kpa, atmosphere_kpa
        self._rng = np.random.default_rng(seed + 100 * index)
        self.stuck_kpa = None
        self.status = 0
        self.fail = False

    def read(self, n: int) -> bytes:
        if self.fail:
            raise OSError(121, "Remote I/O error")
        p = self.plant.p[self.index] if self.stuck_kpa is None else self.stuck_kpa
        c = counts_for_kpa_abs(self.atm + p + self._rng.normal(0.0, self.noise))
        return bytes([(self.status << 6) | (c >> 8), c & 0xFF])[:n]


class SimRig:
    """All parts of a simulated rig, for fault injection; ``rig`` is the :class:`softcrawl.hardware.rig.Rig`."""

    def __init__(self, config: RigConfig | None = None, seed: int = 0, jitter_s: float = 0.002,
                 noise_kpa: float = 0.5, params=FITTED) -> None:
        from softcrawl.hardware.rig import Rig

        self.config = config or load_rig_config(example_rig_path())
        self.clock = SimClock(jitter_s=jitter_s, seed=seed)
        self.supply = FakeBK9129B(self.clock)
        self.plant = SimRegulators(self.supply, self.config.regulators, self.clock, params)
        self.devices = [FakeSSCDevice(self.plant, i, noise_kpa, seed=seed) for i in range(3)]
        driver = BK9129B(self.supply, max_v=self.config.supply.max_volts, retries=self.config.supply.retries)
        source = PressureSource(driver, self.config.regulators, self.config.rig.max_kpa)
        sensors = SSCBank([HoneywellSSC(d) for d in self.devices])
        settings: RigSettings = self.config.rig
        self.rig = Rig(source, sensors, self.clock, settings, name=f"simulated: {settings.name}", simulated=True)
