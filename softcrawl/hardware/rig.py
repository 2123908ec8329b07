"""A rig = a :class:`PressureSource`, a sensor bank, a clock and the loop settings; built from
a ``rig.toml`` (:func:`open_rig`) or simulated (:class:`softcrawl.hardware.simrig.SimRig`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softcrawl.hardware.clock import MonotonicClock
from softcrawl.hardware.config import RigConfig, RigSettings
from softcrawl.hardware.errors import RigError, one_line
from softcrawl.hardware.sensors import HoneywellSSC, SMBusDevice, SSCBank
from softcrawl.hardware.source import PressureSource
from softcrawl.hardware.supply import BK9129B, format_volts


class NoSensors:
    """A rig without sensors: reads NaN (the disagreement check is then off)."""

    def zero(self, n: int = 10) -> np.ndarray:
        return np.zeros(3)

    def read_kpa(self) -> np.ndarray:
        return np.full(3, np.nan)

    def close(self) -> None:
        pass


@dataclass(frozen=True)
class FailSafe:
    """What :meth:`Rig.fail_safe` did: ``steps``, one line per step (``"vented to 0 kPa (...)"``,
    ``"outputs off (...)"``, ``"front panel local"`` or ``"FAILED (<step>): <error>"``), and
    ``confirmed``: the 0 V settings and the outputs off were both read back from the supply."""

    steps: list
    confirmed: bool


class Rig:
    """The parts the deploy loop drives. ``simulated`` marks a simulated rig."""

    def __init__(self, source: PressureSource, sensors, clock, settings: RigSettings, name: str = "rig",
                 simulated: bool = False) -> None:
        self.source, self.sensors, self.clock, self.settings = source, sensors, clock, settings
        self.name, self.simulated = name, simulated

    def start(self) -> str:
        """Connect: identify the supply, remote mode, 0 kPa, outputs on; zero the sensors. Returns ``*IDN?``."""
        idn = self.source.start()
        self.sensors.zero()
        return idn

    def fail_safe(self) -> FailSafe:
        """Vent every line to 0 kPa, then outputs off, then the front panel back to local; each
        step is tried even if another failed, and the first two are confirmed by reading them back
        (:meth:`PressureSource.vent`, :meth:`PressureSource.off`)."""
        steps, ok = [], []
        for name, fn, done in (("vent", self.source.vent, "vented to 0 kPa (set {} V read back)"),
                               ("off", self.source.off, "outputs off (read back off; measured {} V)"),
                               ("local", self.source.local, "front panel local")):
            try:
                v = fn()
                steps.append(done.format(format_volts(v)) if v is not None else done)
                ok.append(name)
            except KeyboardInterrupt:  # a further signal must not stop the shutdown
                steps.append(f"FAILED ({name}): interrupted")
            except Exception as exc:  # keep going: the next step may still work
                steps.append(f"FAILED ({name}): {one_line(exc)}")
        return FailSafe(steps, confirmed={"vent", "off"} <= set(ok))

    def close(self) -> None:
        for c in (self.source.close, self.sensors.close):
            try:
                c()
            except Exception:
                pass


def open_rig(config: RigConfig) -> Rig:
    """Open the real instruments of ``config`` (needs ``softcrawl[rig]``).

    Raises:
        SupplyError / SensorError: an instrument cannot be opened.
    """
    s = config.supply
    supply = BK9129B.open(s.address, timeout_ms=s.timeout_ms, max_v=s.max_volts, retries=s.retries)
    source = PressureSource(supply, config.regulators, config.rig.max_kpa)
    sn = config.sensors
    try:
        if sn.kind == "none":
            sensors = NoSensors()
        elif sn.buses:
            sensors = SSCBank([HoneywellSSC(SMBusDevice(b, sn.address), sn.p_max_psi) for b in sn.buses])
        else:
            sensors = SSCBank([HoneywellSSC(SMBusDevice(sn.bus, sn.address, sn.mux_address, ch), sn.p_max_psi)
                               for ch in sn.mux_channels])
    except RigError:
        supply.close()
        raise
    return Rig(source, sensors, MonotonicClock(), config.rig, name=config.rig.name)
