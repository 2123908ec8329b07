"""Open-loop gaits for the 3 pressure regulators, in real kPa."""

from softcrawl.gaits.gaits import (
    CSV_HEADER,
    ActionSequence,
    Gait,
    SineGait,
    paper_best_gait,
    read_actions_csv,
    write_actions_csv,
)
from softcrawl.robot.actuation import PressureRangeError

__all__ = [
    "CSV_HEADER",
    "ActionSequence",
    "Gait",
    "PressureRangeError",
    "SineGait",
    "paper_best_gait",
    "read_actions_csv",
    "write_actions_csv",
]
