"""Pressure animations for training and validating reductions (sim kPa per channel).

An animation is anything with ``sim_pressure_at(t) -> (n_channels,)`` sim kPa and a
``duration`` in s. They drive robots whose legs each have their own pressure channel
(:func:`softcrawl.robot.assembly.assemble_robot`), bypassing the regulators, as the
paper's reduction scenes did (reduction.md, "Design-reconfigurable reduction").
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from softcrawl.robot.actuation import P_MAX_KPA, PressureCalibration


def full_sim_pressure() -> float:
    """Sim kPa of the regulators' full 90 real kPa under the reference calibration (346.7)."""
    return float(PressureCalibration().to_sim(np.array([P_MAX_KPA]))[0])


def gray_code(n: int) -> np.ndarray:
    """``(2^n, n)`` 0/1 states of the reflected binary Gray code: a Hamiltonian path over the
    vertices of the n-cube (consecutive rows differ in one bit), starting at all-zero."""
    if n < 1:
        raise ValueError(f"need at least one channel, got {n}")
    k = np.arange(2**n)
    g = k ^ (k >> 1)
    return ((g[:, None] >> np.arange(n)) & 1).astype(float)


def _ramped(states: np.ndarray, t: float, state_seconds: float, ramp_seconds: float) -> np.ndarray:
    """Piecewise-linear walk through ``states`` (rows): ramp from the previous row, then hold."""
    i = min(int(t // state_seconds), len(states) - 1)
    prev = states[i - 1] if i > 0 else np.zeros(states.shape[1])
    s = min(max((t - i * state_seconds) / ramp_seconds, 0.0), 1.0)
    return prev + s * (states[i] - prev)


@dataclass(frozen=True)
class HamiltonianAnimation:
    """The paper's "Hamiltonian" animation: a Gray-code walk through all ``2^n`` on/off
    pressure states of ``n`` channels (reduction.md), each state ``state_seconds`` long,
    reached by a linear ramp of ``ramp_seconds``, then back to zero.

    Attributes:
        n_channels: legs (one channel each).
        high_kpa: "on" pressure, sim kPa (default: 90 real kPa calibrated, 346.7).
        state_seconds, ramp_seconds: s (``0 < ramp <= state``).
    """

    n_channels: int
    high_kpa: float = full_sim_pressure()
    state_seconds: float = 0.3
    ramp_seconds: float = 0.15

    def __post_init__(self) -> None:
        if not 0 < self.ramp_seconds <= self.state_seconds:
            raise ValueError("need 0 < ramp_seconds <= state_seconds")

    @property
    def duration(self) -> float:
        return (2**self.n_channels + 1) * self.state_seconds

    def sim_pressure_at(self, t: float) -> np.ndarray:
        states = np.vstack([gray_code(self.n_channels), np.zeros(self.n_channels)])
        return self.high_kpa * _ramped(states, t, self.state_seconds, self.ramp_seconds)


@dataclass(frozen=True)
class AlternatingAnimation:
    """Groups of channels inflating in turn: group ``g`` is on during the ``g``-th part of each
    period (square wave with linear ramps).

    Attributes:
        groups: channel indices of each group.
        period: s; duration: s.
        high_kpa: sim kPa; ramp_seconds: s.
    """

    groups: tuple[tuple[int, ...], ...]
    period: float = 2.0
    duration: float = 6.0
    high_kpa: float = full_sim_pressure()
    ramp_seconds: float = 0.3

    @property
    def n_channels(self) -> int:
        return 1 + max(c for g in self.groups for c in g)

    def sim_pressure_at(self, t: float) -> np.ndarray:
        seg = self.period / len(self.groups)
        states = np.zeros((len(self.groups), self.n_channels))
        for g, chans in enumerate(self.groups):
            states[g, list(chans)] = 1.0
        cycle = np.vstack([states] * (int(t // self.period) + 2))
        return self.high_kpa * _ramped(cycle, t, seg, min(self.ramp_seconds, seg))


@dataclass(frozen=True)
class GaitAnimation:
    """A regulator gait (real kPa, e.g. :class:`softcrawl.gaits.SineGait`) seen through the
    calibration; no rate limit (the sine gait never exceeds the regulators' 150 kPa/s)."""

    gait: object
    duration: float = 6.0
    calibration: PressureCalibration = PressureCalibration()

    def sim_pressure_at(self, t: float) -> np.ndarray:
        return self.calibration.to_sim(np.asarray(self.gait.pressure_at(t), float))
