"""Sim-to-real: the paper's rig, fail-safe deploys, pressure calibration, sim-vs-real reports.

Modules (optional extra ``softcrawl[rig]`` for real instruments; the simulated rig needs none):

- :mod:`~softcrawl.hardware.supply`: BK Precision 9129B driver (SCPI over pyvisa + pyvisa-py).
- :mod:`~softcrawl.hardware.source`: kPa-to-volt regulator maps and the :class:`PressureSource`.
- :mod:`~softcrawl.hardware.sensors`: Honeywell SSC over I2C (smbus2), log replay.
- :mod:`~softcrawl.hardware.config`: ``rig.toml`` loading and validation.
- :mod:`~softcrawl.hardware.rig`: a rig's parts and :func:`open_rig`; the fail-safe.
- :mod:`~softcrawl.hardware.simrig`: the simulated rig (fake SCPI instrument, fitted regulators).
- :mod:`~softcrawl.hardware.ptysupply`: the fake supply served on a pseudo-terminal (end-to-end
  runs of the real-rig path through pyvisa, without hardware).
- :mod:`~softcrawl.hardware.regulator_model`: first-order regulator model and its fit to recorded logs.
- :mod:`~softcrawl.hardware.deploy`: the deploy loop.
- :mod:`~softcrawl.hardware.calibration`: the pressure warp from measured bends.
- :mod:`~softcrawl.hardware.logs`, :mod:`~softcrawl.hardware.compare`: log importers, sim vs real.

Nothing here reads ``../shared`` at run time; the recorded logs are test data only.
"""

from softcrawl.hardware.calibration import load_calibration
from softcrawl.hardware.config import RigConfig, load_rig_config
from softcrawl.hardware.deploy import DeployResult, deploy
from softcrawl.hardware.errors import RigConfigError, RigError, SafetyTrip, SensorError, SupplyError
from softcrawl.hardware.rig import Rig, open_rig
from softcrawl.hardware.source import PressureSource, RegulatorMap

__all__ = ["DeployResult", "PressureSource", "RegulatorMap", "Rig", "RigConfig", "RigConfigError", "RigError",
           "SafetyTrip", "SensorError", "SupplyError", "deploy", "load_calibration", "load_rig_config", "open_rig"]
