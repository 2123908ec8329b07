"""The crawler: actuation (calibration, regulators), assembly of the FEM model, episodes.

Imports of :mod:`softcrawl.gaits` only the regulators' command range
(:mod:`softcrawl.gaits.pressure`, re-exported by :mod:`softcrawl.robot.actuation`; gaits sit
below the robot and import nothing of it), and not the output writers
(:mod:`softcrawl.robot.output`, heavy plotting/IO imports).
"""

from softcrawl.robot.actuation import (
    P_MAX_KPA,
    P_MIN_KPA,
    PressureCalibration,
    PressureRangeError,
    RegulatorBank,
    check_pressures,
)
from softcrawl.robot.assembly import (
    LegSlot,
    Robot,
    RobotConfig,
    build_robot,
    leg_transform,
)
from softcrawl.robot.domain import DomainRanges, DomainSample
from softcrawl.robot.episode import NO_SETTLING, Episode, EpisodeResult, SettledState, Settling, run_episode, settle

__all__ = [
    "P_MAX_KPA",
    "P_MIN_KPA",
    "NO_SETTLING",
    "DomainRanges",
    "DomainSample",
    "Episode",
    "EpisodeResult",
    "LegSlot",
    "PressureCalibration",
    "PressureRangeError",
    "RegulatorBank",
    "Robot",
    "RobotConfig",
    "SettledState",
    "Settling",
    "build_robot",
    "check_pressures",
    "leg_transform",
    "run_episode",
    "settle",
]
