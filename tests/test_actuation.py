"""Pneumatic actuation: sim-to-real pressure calibration and rate-limited regulators."""

from __future__ import annotations

import numpy as np
import pytest

from softcrawl.robot.actuation import (
    REAL_KPA_TABLE,
    SIM_KPA_TABLE,
    PressureCalibration,
    PressureRangeError,
    RegulatorBank,
)


def test_default_least_squares():
    cal = PressureCalibration()
    assert cal.a == pytest.approx(4.0785, abs=1e-3)
    assert cal.b == pytest.approx(-20.36, abs=1e-2)
    assert PressureCalibration.from_table(REAL_KPA_TABLE, SIM_KPA_TABLE) == cal
    a, b = np.polyfit(REAL_KPA_TABLE, SIM_KPA_TABLE, 1)
    assert (cal.a, cal.b) == pytest.approx((a, b))


def test_to_sim_vectorised_and_clamped():
    cal = PressureCalibration()
    assert cal.to_sim(0.0) == 0.0  # a*0 + b < 0 -> clamped
    assert cal.to_sim(2.0) == 0.0
    assert isinstance(cal.to_sim(50.0), float)
    real = np.array([[0.0, 10.0], [50.0, 90.0]])
    sim = cal.to_sim(real)
    assert sim.shape == (2, 2)
    np.testing.assert_allclose(sim, np.maximum(cal.a * real + cal.b, 0))
    assert PressureCalibration.identity().to_sim(37.0) == 37.0


def test_from_table_exact_line():
    cal = PressureCalibration.from_table([0, 10], [5, 25])
    assert (cal.a, cal.b) == pytest.approx((2.0, 5.0))


@pytest.mark.parametrize(
    "real, sim",
    [([1, 2, 3], [1, 2]), ([1], [1]), ([1, np.nan], [1, 2]), ([1, 2], [np.inf, 2]), ([3, 3], [1, 2])],
)
def test_from_table_invalid(real, sim):
    with pytest.raises(ValueError):
        PressureCalibration.from_table(real, sim)


def test_rate_limit_reaches_90_after_0p6s():
    bank = RegulatorBank()
    dt = 0.01
    for step in range(1, 61):
        p = bank.step([90.0, 0.0, 45.0], dt)
        assert p[0] == pytest.approx(min(150.0 * step * dt, 90.0))
        if step < 60:
            assert p[0] < 90.0 - 1e-6
    assert p == pytest.approx([90.0, 0.0, 45.0])
    np.testing.assert_array_equal(bank.step([90.0, 0.0, 45.0], dt), p)  # holds


def test_rate_limit_down_and_reset():
    bank = RegulatorBank(rate_kpa_s=100.0)
    bank.reset([90.0, 50.0, 0.0])
    np.testing.assert_allclose(bank.step([0.0, 50.0, 10.0], 0.2), [70.0, 50.0, 10.0])
    bank.reset()
    np.testing.assert_array_equal(bank.state, np.zeros(3))
    assert RegulatorBank(n=5).step(np.full(5, 1.0), 1.0).shape == (5,)


@pytest.mark.parametrize("command, fragment", [([0, 91, 0], "column 1"), ([-5, 0, 0], "column 0"), ([0, 0, np.nan], "not finite")])
def test_command_range_errors(command, fragment):
    bank = RegulatorBank()
    with pytest.raises(PressureRangeError, match=fragment):
        bank.step(command, 0.1)
    np.testing.assert_array_equal(bank.state, np.zeros(3))  # unchanged


def test_other_errors():
    bank = RegulatorBank()
    with pytest.raises(ValueError, match="shape"):
        bank.step([0, 0], 0.1)
    with pytest.raises(ValueError, match="dt"):
        bank.step([0, 0, 0], -0.1)
    with pytest.raises(ValueError):
        RegulatorBank(rate_kpa_s=0.0)
    with pytest.raises(PressureRangeError):
        bank.reset([0, 0, 100])
    assert issubclass(PressureRangeError, ValueError)
