"""The real rig's code paths without hardware: :func:`open_rig` with the BK 9129B driver over
pyvisa + pyvisa-py on a pseudo-terminal (:class:`~softcrawl.hardware.ptysupply.PtySupply`) and
the Honeywell SSC sensors through :class:`~softcrawl.hardware.sensors.SMBusDevice` on a fake
``smbus2`` module (an SSC's 2-byte reads behind a TCA9548A multiplexer or on separate buses);
and :class:`~softcrawl.hardware.rig.NoSensors`."""

from __future__ import annotations

import errno
import sys
import types

import numpy as np
import pytest

pytest.importorskip("pyvisa")
pytest.importorskip("serial")

from softcrawl.hardware.config import example_rig_path, load_rig_config  # noqa: E402
from softcrawl.hardware.errors import SensorError  # noqa: E402
from softcrawl.hardware.ptysupply import PtySupply  # noqa: E402
from softcrawl.hardware.rig import NoSensors, open_rig  # noqa: E402
from softcrawl.hardware.sensors import PSI_KPA, SSC_COUNTS_MAX, SSC_COUNTS_MIN, SMBusDevice  # noqa: E402

ATM_KPA = 101.3
#: One SSC count in kPa (30 psi over 13,107 counts): the resolution the readings are checked to.
COUNT_KPA = 30 * PSI_KPA / (SSC_COUNTS_MAX - SSC_COUNTS_MIN)


class FakeI2C:
    """The I2C buses a fake ``smbus2`` sees: ``kpa_abs[(bus, mux channel or None)]`` is the
    absolute pressure of the SSC (0x28) there; ``log`` records every transaction."""

    def __init__(self, kpa_abs: dict, missing_buses=()):
        self.kpa_abs, self.missing, self.log, self.closed = dict(kpa_abs), set(missing_buses), [], []

    def module(self) -> types.ModuleType:
        i2c = self

        class Msg:
            def __init__(self, addr, n):
                self.addr, self.len, self.buf = addr, n, [0] * n

            def __iter__(self):
                return iter(self.buf)

        class SMBus:
            def __init__(self, bus):
                if bus in i2c.missing:
                    raise FileNotFoundError(errno.ENOENT, f"No such file or directory: '/dev/i2c-{bus}'")
                self.bus, self.channel = bus, None

            def write_byte(self, addr, value):
                assert addr == 0x70 and bin(value).count("1") == 1, (addr, value)  # TCA9548A select
                self.channel = value.bit_length() - 1
                i2c.log.append(("select", self.bus, self.channel))

            def i2c_rdwr(self, *msgs):
                for m in msgs:
                    key = (self.bus, self.channel)
                    if m.addr != 0x28 or key not in i2c.kpa_abs:
                        raise OSError(errno.EREMOTEIO, "Remote I/O error")  # no device answers: NACK
                    c = round(SSC_COUNTS_MIN + i2c.kpa_abs[key] / (30 * PSI_KPA) * (SSC_COUNTS_MAX - SSC_COUNTS_MIN))
                    m.buf = [(c >> 8) & 0x3F, c & 0xFF][: m.len]  # status bits 00: normal
                    i2c.log.append(("read", self.bus, self.channel, m.addr, m.len))

            def close(self):
                i2c.closed.append(self.bus)

        mod = types.ModuleType("smbus2")
        mod.SMBus = SMBus
        mod.i2c_msg = types.SimpleNamespace(read=Msg)
        return mod


def _rig_toml(tmp_path, address: str, sensors: str):
    text = example_rig_path().read_text().split("[sensors]")[0] + "[sensors]\n" + sensors
    p = tmp_path / "rig.toml"
    p.write_text(text.replace("ASRL/dev/ttyUSB0::INSTR", address))
    return load_rig_config(p)


MUX = 'kind = "honeywell-ssc"\nbus = 1\nmux_address = 0x70\nmux_channels = [2, 0, 1]\n'


def test_smbus_device_selects_the_mux_channel_before_each_read(monkeypatch):
    i2c = FakeI2C({(1, 5): ATM_KPA})
    monkeypatch.setitem(sys.modules, "smbus2", i2c.module())
    dev = SMBusDevice(1, 0x28, mux_address=0x70, mux_channel=5)
    raw = dev.read(2)
    assert len(raw) == 2 and raw[0] >> 6 == 0
    assert i2c.log == [("select", 1, 5), ("read", 1, 5, 0x28, 2)]
    with pytest.raises(SensorError, match="I2C device 0x29"):  # nothing at 0x29: the NACK is a SensorError
        SMBusDevice(1, 0x29, mux_address=0x70, mux_channel=5).read(2)
    dev.close()
    assert i2c.closed == [1]


def test_open_rig_reads_gauge_pressures_through_the_mux_and_vents_on_fail_safe(tmp_path, monkeypatch):
    """Sensors in regulator order on mux channels 2, 0, 1: after the atmospheric zero each reads
    its line's gauge pressure to one count (0.016 kPa); the fail-safe is confirmed by the supply."""
    gauge = np.array([12.0, 34.5, 80.25])  # regulator 1, 2, 3
    i2c = FakeI2C({(1, 2): ATM_KPA, (1, 0): ATM_KPA, (1, 1): ATM_KPA})
    monkeypatch.setitem(sys.modules, "smbus2", i2c.module())
    with PtySupply() as fake:
        rig = open_rig(_rig_toml(tmp_path, fake.address, MUX))
        try:
            assert "9129B" in rig.start()
            assert fake.supply.on and fake.supply.remote
            assert np.allclose(rig.sensors.zero_kpa, ATM_KPA, atol=COUNT_KPA)
            for ch, g in zip((2, 0, 1), gauge):
                i2c.kpa_abs[(1, ch)] = ATM_KPA + g
            assert np.allclose(rig.sensors.read_kpa(), gauge, atol=2 * COUNT_KPA)
            safe = rig.fail_safe()
        finally:
            rig.close()
        assert fake.errors == []
    # vent and off are read back (so the fake has seen them); SYST:LOC is a write nothing answers
    assert safe.confirmed and not fake.supply.on and not fake.supply.set_v.any()
    assert {e[2] for e in i2c.log if e[0] == "select"} == {0, 1, 2} and i2c.closed == [1, 1, 1]


def test_open_rig_with_one_bus_per_sensor_and_without_sensors(tmp_path, monkeypatch):
    i2c = FakeI2C({(3, None): ATM_KPA + 1.0, (4, None): ATM_KPA + 2.0, (5, None): ATM_KPA + 3.0})
    monkeypatch.setitem(sys.modules, "smbus2", i2c.module())
    with PtySupply() as fake:
        rig = open_rig(_rig_toml(tmp_path, fake.address, 'kind = "honeywell-ssc"\nbuses = [3, 4, 5]\n'))
        try:
            rig.start()
            for bus in (3, 4, 5):
                i2c.kpa_abs[(bus, None)] += 10.0 * bus
            assert np.allclose(rig.sensors.read_kpa(), [30.0, 40.0, 50.0], atol=2 * COUNT_KPA)
            assert not any(e[0] == "select" for e in i2c.log)
        finally:
            rig.close()
        rig = open_rig(_rig_toml(tmp_path, fake.address, 'kind = "none"\n'))
        try:
            assert isinstance(rig.sensors, NoSensors)
            rig.start()
            assert np.isnan(rig.sensors.read_kpa()).all() and rig.sensors.zero().tolist() == [0.0, 0.0, 0.0]
            assert rig.fail_safe().confirmed
        finally:
            rig.close()
        assert fake.errors == []


def test_open_rig_with_a_missing_i2c_bus_closes_the_supply(tmp_path, monkeypatch):
    """A sensor bus that cannot be opened is a SensorError naming it, and the supply already
    opened is closed again (its serial port is free for the retry)."""
    import softcrawl.hardware.supply as supply_mod

    i2c = FakeI2C({}, missing_buses={1})
    monkeypatch.setitem(sys.modules, "smbus2", i2c.module())
    closed = []
    close = supply_mod.BK9129B.close
    monkeypatch.setattr(supply_mod.BK9129B, "close", lambda self: closed.append(True) or close(self))
    with PtySupply() as fake:
        with pytest.raises(SensorError, match="cannot open I2C bus 1"):
            open_rig(_rig_toml(tmp_path, fake.address, MUX))
    assert closed == [True]
