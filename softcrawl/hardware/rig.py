"""A rig = a :class:`PressureSource`, a sensor bank, a clock and the loop settings; built from
a ``rig.toml`` (:func:`open_rig`) or simulated (:class:`softcrawl.hardware.simrig.SimRig`)."""

from __future__ import annotations

import numpy as np

from softcrawl.hardware.clock import MonotonicClock
from softcrawl.hardware.config import RigConfig, RigSettings
from softcrawl.hardware.errors import RigError
from softcrawl.hardware.sensors import HoneywellSSC, SMBusDevice, SSCBank
from softcrawl.hardware.source import PressureSource
from softcrawl.hardware.supply import BK9129B


class NoSensors:
    """A rig without sensors: reads NaN (the disagreement check is then off)."""

    def zero(self, n: int = 10) -> np.ndarray:
        return np.zeros(3)

    def read_kpa(self) -> np.ndarray:
        return np.full(3, np.nan)

    def close(self) -> None:
        pass


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

    def fail_safe(self) -> list[str]:
        """Vent every line to 0 kPa, then outputs off; each step is tried even if another
        failed. Returns what happened, one line per step (``"vented to 0 kPa"``, ``"outputs off"``
        or the error)."""
        done = []
        for what, fn in (("vented to 0 kPa", self.source.vent), ("outputs off", self.source.off)):
            try:
                fn()
                done.append(what)
            except KeyboardInterrupt:  # a second Ctrl-C must not stop the shutdown
                done.append(f"FAILED ({what.split()[0]}): interrupted")
            except Exception as exc:  # keep going: the next step may still work
                done.append(f"FAILED ({what.split()[0]}): {exc}")
        return done

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
