"""``rig.toml``: what a rig is made of, read with :mod:`tomllib` (a data file, never code).

Layout (see ``softcrawl/hardware/data/example_rig.toml``)::

    [rig]        name (printable, <= 80 characters), max_kpa (<= 90), control_period_s,
                 sample_hz (>= 10), watchdog_s, disagreement_kpa, disagreement_s, overrun_tolerance_s
    [supply]     model = "BK9129B", address (VISA name, printable), timeout_ms, retries,
                 max_volts = [3 V]
    [[regulator]] x 3, in regulator order: channel (1..3), volts_per_kpa (>= 0.001), offset_v
    [sensors]    kind = "honeywell-ssc" | "none"; for SSC: buses = [3 ints] or bus + mux_address
                 + mux_channels = [3 ints], address (0x28), p_max_psi (30); bus numbers
                 0..255, I2C addresses 7-bit (0x08..0x77)

Every key is checked: unknown keys (typos), wrong types, out-of-range values and unsafe
combinations (a 90 kPa command that needs more than a channel's voltage limit) raise
:class:`RigConfigError` with one line naming the file and the key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from softcrawl.hardware.errors import RigConfigError, one_line
from softcrawl.hardware.source import RegulatorMap
from softcrawl.hardware.supply import BK9129B_MAX_V
from softcrawl.robot.actuation import P_MAX_KPA
from softcrawl.safeio import UnsafeFileError, load_toml

SENSOR_KINDS = ("honeywell-ssc", "none")
#: Largest rig file read, bytes (the example is 2 kB).
MAX_RIG_BYTES = 1 << 20
#: Usable 7-bit I2C addresses (0x00-0x07 and 0x78-0x7F are reserved by the I2C specification).
I2C_ADDRESSES = (0x08, 0x77)


@dataclass(frozen=True)
class RigSettings:
    """Deploy-loop settings ([rig] table). Units: kPa, s, Hz."""

    name: str = "rig"
    max_kpa: float = P_MAX_KPA
    control_period_s: float = 1.0
    sample_hz: float = 20.0
    watchdog_s: float = 0.5
    disagreement_kpa: float = 30.0
    disagreement_s: float = 1.5
    overrun_tolerance_s: float = 0.05


@dataclass(frozen=True)
class SupplySettings:
    model: str = "BK9129B"
    address: str = "ASRL/dev/ttyUSB0::INSTR"
    timeout_ms: int = 1000
    retries: int = 3
    max_volts: tuple = BK9129B_MAX_V


@dataclass(frozen=True)
class SensorSettings:
    kind: str = "none"
    buses: tuple = ()
    bus: int | None = None
    mux_address: int | None = None
    mux_channels: tuple = ()
    address: int = 0x28
    p_max_psi: float = 30.0


@dataclass(frozen=True)
class RigConfig:
    """A validated rig description."""

    path: str
    rig: RigSettings
    supply: SupplySettings
    regulators: tuple
    sensors: SensorSettings = field(default_factory=SensorSettings)


_SPEC = {
    "rig": {"name": str, "max_kpa": float, "control_period_s": float, "sample_hz": float, "watchdog_s": float,
            "disagreement_kpa": float, "disagreement_s": float, "overrun_tolerance_s": float},
    "supply": {"model": str, "address": str, "timeout_ms": int, "retries": int, "max_volts": list},
    "regulator": {"channel": int, "volts_per_kpa": float, "offset_v": float},
    "sensors": {"kind": str, "buses": list, "bus": int, "mux_address": int, "mux_channels": list, "address": int,
                "p_max_psi": float},
}


def _table(path, data, name, required=True) -> dict:
    t = data.get(name)
    if t is None:
        if required:
            raise RigConfigError(f"{path}: missing [{name}] table")
        return {}
    if not isinstance(t, dict):
        raise RigConfigError(f"{path}: [{name}] must be a table")
    return _typed(path, name, t)


def _typed(path, name, t: dict) -> dict:
    spec = _SPEC[name]
    out = {}
    for k, v in t.items():
        if k not in spec:
            raise RigConfigError(f"{path}: unknown key {name}.{k} (known: {', '.join(spec)})")
        want = spec[k]
        if want is float and isinstance(v, int) and not isinstance(v, bool):
            v = float(v)
        if not isinstance(v, want) or isinstance(v, bool):
            raise RigConfigError(f"{path}: {name}.{k} must be {want.__name__}, got {type(v).__name__} {v!r}")
        if isinstance(v, float) and not math.isfinite(v):
            raise RigConfigError(f"{path}: {name}.{k} must be finite, got {v}")
        out[k] = v
    return out


def _check(path, ok: bool, msg: str) -> None:
    if not ok:
        raise RigConfigError(f"{path}: {msg}")


def _ints(path, key, v, n=3, lo=0, hi=127) -> tuple:
    _check(path, isinstance(v, list) and len(v) == n and all(isinstance(x, int) and not isinstance(x, bool)
                                                              and lo <= x <= hi for x in v),
           f"{key} must be a list of {n} integers in [{lo}, {hi}], got {v!r}")
    return tuple(v)


def load_rig_config(path: str | Path) -> RigConfig:
    """Read and validate a ``rig.toml``.

    Raises:
        FileNotFoundError: no such file.
        RigConfigError: not a regular file of at most 1 MB, not TOML, nested too deeply, unknown
            keys, bad types/values, unsafe limits (one line).
    """
    path = Path(path)
    try:
        data = load_toml(path, max_bytes=MAX_RIG_BYTES)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: rig config not found") from None
    except (OSError, UnsafeFileError) as exc:
        raise RigConfigError(f"not a readable TOML rig file: {one_line(exc)}") from None
    unknown = set(data) - set(_SPEC)
    _check(path, not unknown, f"unknown table(s) {sorted(unknown)} (known: rig, supply, regulator, sensors)")

    r = RigSettings(**_table(path, data, "rig"))
    _check(path, 0 < len(r.name) <= 80 and r.name.isprintable(),
           f"rig.name must be 1 to 80 printable characters, got {r.name!r}")
    _check(path, 0 < r.max_kpa <= P_MAX_KPA, f"rig.max_kpa must be in (0, {P_MAX_KPA:g}] kPa, got {r.max_kpa}")
    _check(path, 0.1 <= r.control_period_s <= 10, f"rig.control_period_s must be in [0.1, 10] s, got "
                                                  f"{r.control_period_s}")
    _check(path, 10 <= r.sample_hz <= 1000, f"rig.sample_hz must be in [10, 1000] Hz, got {r.sample_hz}")
    _check(path, 0 < r.watchdog_s <= r.control_period_s, "rig.watchdog_s must be in (0, control_period_s] s, "
                                                         f"got {r.watchdog_s}")
    _check(path, r.watchdog_s >= 2.0 / r.sample_hz, f"rig.watchdog_s ({r.watchdog_s:g} s) must be at least two "
                                                    f"sample periods (2 / sample_hz = {2 / r.sample_hz:g} s)")
    _check(path, 0 < r.disagreement_kpa <= 90, f"rig.disagreement_kpa must be in (0, 90] kPa, got "
                                               f"{r.disagreement_kpa}")
    _check(path, 0 < r.disagreement_s <= 10, f"rig.disagreement_s must be in (0, 10] s, got {r.disagreement_s}")
    _check(path, 0 <= r.overrun_tolerance_s < r.control_period_s, "rig.overrun_tolerance_s must be in "
                                                                  "[0, control_period_s) s")

    s = _table(path, data, "supply")
    if "max_volts" in s:
        v = s["max_volts"]
        _check(path, len(v) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in v),
               f"supply.max_volts must be 3 numbers, got {v!r}")
        bad = [i for i in range(3) if not (0 < v[i] <= BK9129B_MAX_V[i])]
        _check(path, not bad, f"supply.max_volts {v} must be within the 9129B's (0, {list(BK9129B_MAX_V)}] V")
        s["max_volts"] = tuple(float(x) for x in v)
    supply = SupplySettings(**s)
    _check(path, supply.model == "BK9129B", f"supply.model must be \"BK9129B\" (the only driver), got "
                                            f"{supply.model!r}")
    _check(path, 0 < len(supply.address) <= 256 and supply.address.isprintable(),
           f"supply.address must be 1 to 256 printable characters, got {supply.address!r}")
    _check(path, 100 <= supply.timeout_ms <= 10000, "supply.timeout_ms must be in [100, 10000]")
    _check(path, 1 <= supply.retries <= 10, "supply.retries must be in [1, 10]")

    regs = data.get("regulator")
    _check(path, isinstance(regs, list) and len(regs) == 3,
           "need exactly 3 [[regulator]] tables (regulator 1, 2, 3 in order)")
    maps = []
    for i, t in enumerate(regs):
        _check(path, isinstance(t, dict), f"regulator {i + 1} must be a table")
        t = _typed(path, "regulator", t)
        _check(path, {"channel", "volts_per_kpa"} <= set(t), f"regulator {i + 1} needs channel and volts_per_kpa")
        try:
            m = RegulatorMap(**t)
        except ValueError as exc:
            raise RigConfigError(f"{path}: regulator {i + 1}: {exc}") from None
        top = m.volts(r.max_kpa)
        _check(path, top <= supply.max_volts[m.channel - 1],
               f"regulator {i + 1}: {r.max_kpa:g} kPa needs {top:g} V, above channel {m.channel}'s limit "
               f"{supply.max_volts[m.channel - 1]:g} V")
        maps.append(m)
    _check(path, sorted(m.channel for m in maps) == [1, 2, 3], "the 3 regulators must use channels 1, 2, 3 once each")

    sn = _table(path, data, "sensors", required=False)
    for k in ("buses", "mux_channels"):
        if k in sn:
            sn[k] = _ints(path, f"sensors.{k}", sn[k], hi=7 if k == "mux_channels" else 255)
    sensors = SensorSettings(**sn)
    _check(path, sensors.kind in SENSOR_KINDS, f"sensors.kind must be one of {SENSOR_KINDS}, got {sensors.kind!r}")
    if sensors.kind == "honeywell-ssc":
        _check(path, bool(sensors.buses) != (sensors.bus is not None),
               "honeywell-ssc sensors need either buses = [3 buses] or bus + mux_address + mux_channels")
        if sensors.bus is not None:
            _check(path, sensors.mux_address is not None and len(sensors.mux_channels) == 3,
                   "three sensors share address 0x28: with one bus, give mux_address and mux_channels = [3]")
            _check(path, 0 <= sensors.bus <= 255, f"sensors.bus must be in [0, 255], got {sensors.bus}")
            _check(path, I2C_ADDRESSES[0] <= sensors.mux_address <= I2C_ADDRESSES[1],
                   f"sensors.mux_address {sensors.mux_address} is not a 7-bit I2C address (0x08..0x77)")
        _check(path, I2C_ADDRESSES[0] <= sensors.address <= I2C_ADDRESSES[1],
               f"sensors.address {sensors.address} is not a 7-bit I2C address (0x08..0x77)")
        _check(path, 0 < sensors.p_max_psi <= 150, "sensors.p_max_psi must be in (0, 150] psi")
    return RigConfig(str(path), r, supply, tuple(maps), sensors)


def example_rig_path() -> Path:
    """The example ``rig.toml`` shipped with softcrawl."""
    return Path(__file__).with_name("data") / "example_rig.toml"
