"""The pressure source: three regulators commanded by analog voltages from a supply.

A :class:`RegulatorMap` turns a regulator's commanded pressure into the supply voltage that
asks for it (affine, measured per rig: set a voltage, read the regulator's own gauge; the
level-shifting stage between supply and regulator is part of the map). :class:`PressureSource`
is the interface the deploy loop uses: set three pressures (kPa), read back what the supply
outputs (as V and as the kPa that asks for), vent, turn off.

Pressure limits are enforced here, before anything is sent: a command outside
``[0, max_kpa]`` (``max_kpa`` <= 90 kPa, physics.md "Pneumatic actuation") raises
:class:`softcrawl.robot.actuation.PressureRangeError`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softcrawl.robot.actuation import P_MAX_KPA, PressureRangeError, check_pressures


#: Smallest regulator gain, V/kPa: the 9129B sets voltages in 1 mV steps, so 1 kPa must be at
#: least one step.
MIN_VOLTS_PER_KPA = 1e-3


@dataclass(frozen=True)
class RegulatorMap:
    """``volts = offset_v + volts_per_kpa * kpa`` for one regulator.

    Attributes:
        channel: supply channel 1..3.
        volts_per_kpa: V per kPa, at least :data:`MIN_VOLTS_PER_KPA`.
        offset_v: V at 0 kPa, >= 0.

    Raises:
        ValueError: a channel other than 1..3, a gain below :data:`MIN_VOLTS_PER_KPA` or not
            finite, a negative or non-finite offset.
    """

    channel: int
    volts_per_kpa: float
    offset_v: float = 0.0

    def __post_init__(self) -> None:
        if self.channel not in (1, 2, 3):
            raise ValueError(f"regulator channel must be 1, 2 or 3, got {self.channel}")
        if not (math.isfinite(self.volts_per_kpa) and self.volts_per_kpa >= MIN_VOLTS_PER_KPA):
            raise ValueError(f"volts_per_kpa must be finite and >= {MIN_VOLTS_PER_KPA:g} V/kPa (the supply sets "
                             f"1 mV steps: a smaller gain cannot tell 1 kPa apart), got {self.volts_per_kpa}")
        if not (math.isfinite(self.offset_v) and self.offset_v >= 0):
            raise ValueError(f"offset_v must be finite and >= 0 V, got {self.offset_v}")

    def volts(self, kpa: float) -> float:
        return self.offset_v + self.volts_per_kpa * float(kpa)

    def kpa(self, volts: float) -> float:
        return (float(volts) - self.offset_v) / self.volts_per_kpa


class PressureSource:
    """Three regulators on a 3-channel supply.

    Args:
        supply: a :class:`softcrawl.hardware.supply.BK9129B` (or anything with ``set_volts``,
            ``measure_volts``, ``output``, ``identify``, ``remote``, ``local``, ``close``).
        maps: 3 :class:`RegulatorMap`, regulator 1, 2, 3, on distinct channels.
        max_kpa: command limit, kPa (<= 90).

    Raises:
        ValueError: bad maps or limit; VoltageLimitError if ``max_kpa`` would need a voltage
            beyond a channel's limit.
    """

    def __init__(self, supply, maps, max_kpa: float = P_MAX_KPA) -> None:
        maps = tuple(maps)
        if len(maps) != 3 or sorted(m.channel for m in maps) != [1, 2, 3]:
            raise ValueError("need 3 regulator maps on channels 1, 2, 3 (one each)")
        if not (0 < max_kpa <= P_MAX_KPA):
            raise ValueError(f"max_kpa must be in (0, {P_MAX_KPA:g}] kPa, got {max_kpa}")
        self.supply = supply
        self.maps = maps
        self.max_kpa = float(max_kpa)
        self._order = np.array([m.channel - 1 for m in maps])  # supply channel of regulator i
        top = np.zeros(3)
        top[self._order] = [m.volts(self.max_kpa) for m in maps]
        supply.check_volts(top)  # a full-scale command must be sendable

    def check(self, kpa) -> np.ndarray:
        """``(3,)`` kPa checked against ``[0, max_kpa]`` (PressureRangeError otherwise)."""
        p = np.asarray(kpa, dtype=float)
        if p.shape != (3,):
            raise ValueError(f"need 3 pressures, got shape {p.shape}")
        check_pressures(p, "command")
        if (p > self.max_kpa).any():
            i = int(np.argmax(p > self.max_kpa))
            raise PressureRangeError(f"command column {i} (0-based): {p[i]:g} kPa is above this rig's limit "
                                     f"{self.max_kpa:g} kPa")
        return p

    def volts_for(self, kpa) -> np.ndarray:
        """Supply channel voltages ``(3,)`` (channel order) for regulator pressures ``kpa`` ``(3,)``."""
        p = self.check(kpa)
        v = np.zeros(3)
        v[self._order] = [m.volts(x) for m, x in zip(self.maps, p)]
        return v

    def kpa_for(self, volts) -> np.ndarray:
        """Regulator pressures ``(3,)`` kPa asked for by channel voltages ``(3,)``."""
        v = np.asarray(volts, dtype=float)
        return np.array([m.kpa(v[m.channel - 1]) for m in self.maps])

    def set_kpa(self, kpa) -> np.ndarray:
        """Command the regulators; returns the set channel voltages ``(3,)`` V (channel order).

        Raises:
            PressureRangeError: out-of-range command (nothing sent).
            SupplyError: lost connection / not taken.
        """
        return self.supply.set_volts(self.volts_for(kpa))

    def measure_volts(self) -> np.ndarray:
        """Measured supply outputs ``(3,)`` V, channel order."""
        return self.supply.measure_volts()

    def start(self) -> str:
        """Identify, remote mode, all regulators to 0 kPa, outputs on; returns the ``*IDN?``."""
        idn = self.supply.identify()
        self.supply.remote()
        self.set_kpa(np.zeros(3))
        self.supply.output(True)
        return idn

    def vent(self) -> np.ndarray:
        """All regulators to 0 kPa; returns the set channel voltages ``(3,)`` V as read back.

        Raises:
            SupplyError: the setting could not be sent or did not read back.
        """
        return self.set_kpa(np.zeros(3))

    def off(self) -> np.ndarray:
        """Outputs off, confirmed by reading back the output state and measuring the outputs;
        returns the measured channel voltages ``(3,)`` V.

        Raises:
            SupplyError: not sent, or not confirmed (outputs still on, or a channel measuring volts).
        """
        self.supply.output(False)
        return self.supply.confirm_zero()

    def local(self) -> None:
        """Front panel back to local control."""
        self.supply.local()

    def close(self) -> None:
        self.supply.close()
