"""Open-loop gaits for the pressure regulators of a design space (3 in the paper's), in real kPa.

Below the simulator: imports nothing of :mod:`softcrawl.robot`, :mod:`softcrawl.envs` or
:mod:`softcrawl.fem` (the regulators' command range is :mod:`softcrawl.gaits.pressure`, which
:mod:`softcrawl.robot.actuation` re-exports; ``tests/test_import_graph.py`` checks this).
"""

from softcrawl.gaits.gaits import (
    CSV_HEADER,
    ActionSequence,
    Gait,
    SineGait,
    VentedAfter,
    csv_header,
    paper_best_gait,
    read_actions_csv,
    write_actions_csv,
)
from softcrawl.gaits.periodic import PeriodicGait
from softcrawl.gaits.pressure import P_MAX_KPA, P_MIN_KPA, PressureRangeError, check_pressures

__all__ = [
    "CSV_HEADER",
    "ActionSequence",
    "Gait",
    "P_MAX_KPA",
    "P_MIN_KPA",
    "PeriodicGait",
    "PressureRangeError",
    "SineGait",
    "VentedAfter",
    "check_pressures",
    "csv_header",
    "paper_best_gait",
    "read_actions_csv",
    "write_actions_csv",
]
