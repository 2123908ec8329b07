"""The BK 9129B driver through real pyvisa against a pyvisa-sim instrument (pyvisa and
pyvisa-sim are in the test extra; skipped only where they are not installed)."""

import numpy as np
import pytest

pytest.importorskip("pyvisa")
pytest.importorskip("pyvisa_sim")

from softcrawl.hardware.errors import SupplyError  # noqa: E402
from softcrawl.hardware.supply import BK9129B  # noqa: E402

YAML = r'''
spec: "1.1"
devices:
  bk9129b:
    eom:
      ASRL INSTR:
        q: "\n"
        r: "\n"
    error: ERROR
    dialogues:
      - q: "*IDN?"
        r: "B&K Precision, 9129B, 602199010067110001, 1.78-1.38"
      - q: "SYST:REM"
      - q: "SYST:LOC"
      - q: "MEAS:VOLT:ALL?"
        r: "0.000, 0.000, 0.000"
    properties:
      volts:
        default: "0.000,0.000,0.000"
        getter:
          q: "APP:VOLT?"
          r: "{:s}"
        setter:
          q: "APP:VOLT {:s}"
      output:
        default: 0
        getter:
          q: "OUTP?"
          r: "{:d}"
        setter:
          q: "OUTP {:d}"
        specs:
          valid: [0, 1]
          type: int
resources:
  ASRL1::INSTR:
    device: bk9129b
'''


def test_driver_over_pyvisa_sim(tmp_path):
    y = tmp_path / "bk9129b.yaml"
    y.write_text(YAML)
    drv = BK9129B.open("ASRL1::INSTR", backend=f"{y}@sim", max_v=(5.0, 5.0, 5.0))
    assert "9129B" in drv.identify()
    drv.remote()
    assert np.allclose(drv.set_volts([1.0, 2.25, 4.5]), [1.0, 2.25, 4.5])
    assert drv.resource.query("APP:VOLT?") == "1.000,2.250,4.500"
    drv.output(True)  # verified with OUTP?
    assert drv.output_on() and drv.resource.query("OUTP?") == "1"
    drv.output(False)
    assert not drv.output_on()
    assert np.allclose(drv.confirm_zero(), 0.0)
    drv.close()


def test_open_missing_port_is_a_supply_error():
    with pytest.raises(SupplyError, match="cannot open"):
        BK9129B.open("ASRL/dev/does-not-exist::INSTR", timeout_ms=200)
