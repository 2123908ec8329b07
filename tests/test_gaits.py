"""Open-loop gaits: sine baseline, action sequences, CSV I/O, range checks."""

from __future__ import annotations

import numpy as np
import pytest

from softcrawl.gaits import (
    ActionSequence,
    Gait,
    PressureRangeError,
    SineGait,
    paper_best_gait,
    read_actions_csv,
    write_actions_csv,
)


def test_sine_values():
    g = SineGait()
    np.testing.assert_allclose(g.pressure_at(0.0), [0, 0, 0], atol=1e-12)
    np.testing.assert_allclose(g.pressure_at(2.0), [90, 90, 0])
    np.testing.assert_allclose(g.pressure_at(1.0), [45, 45, 0])
    np.testing.assert_allclose(g.pressure_at(4.0), [0, 0, 0], atol=1e-12)


@pytest.mark.parametrize("phase", [0.0, 45.0, 90.0, 180.0, 270.0])
def test_sine_phase_lag(phase):
    g = SineGait(phase_deg=phase)
    lag = phase / 360.0 * g.period
    for t in np.linspace(0, 8, 17):
        assert g.pressure_at(t + lag)[1] == pytest.approx(g.pressure_at(t)[0], abs=1e-9)
        assert g.pressure_at(t)[2] == 0.0
    # rear (regulator 2) peaks `lag` seconds after the front (regulator 1)
    assert g.pressure_at(2.0 + lag)[1] == pytest.approx(90.0)


def test_sine_parameters():
    g = SineGait(amplitude=30.0, offset=40.0)
    assert g.pressure_at(2.0)[0] == pytest.approx(70.0)
    with pytest.raises(PressureRangeError):
        SineGait(amplitude=50.0, offset=45.0)
    with pytest.raises(ValueError):
        SineGait(period=0.0)


def test_action_sequence_piecewise_constant():
    seq = ActionSequence([[10, 20, 30], [40, 50, 60]], hold=0.5)
    assert len(seq) == 2 and seq.duration == 1.0
    np.testing.assert_array_equal(seq.pressure_at(0.0), [10, 20, 30])
    np.testing.assert_array_equal(seq.pressure_at(0.49), [10, 20, 30])
    np.testing.assert_array_equal(seq.pressure_at(0.5), [40, 50, 60])
    np.testing.assert_array_equal(seq.pressure_at(10.0), [40, 50, 60])  # after the end: last action
    with pytest.raises(ValueError):
        seq.actions[0, 0] = 1.0  # read-only


def test_protocol():
    assert isinstance(SineGait(), Gait) and isinstance(paper_best_gait(), Gait)


def test_paper_best_gait():
    seq = paper_best_gait()
    assert seq.actions.shape == (20, 3) and seq.hold == 1.0
    np.testing.assert_array_equal(seq.actions[:3], [[0, 90, 0], [90, 0, 0], [0, 0, 0]])
    np.testing.assert_array_equal(seq.actions[3:6], seq.actions[:3])
    np.testing.assert_array_equal(seq.pressure_at(1.5), [90, 0, 0])
    assert paper_best_gait(n_cycles=2).actions.shape == (6, 3)


@pytest.mark.parametrize(
    "actions, fragment",
    [
        ([[0, 0, 0], [0, 95, 0]], "row 1, column 1"),
        ([[-1, 0, 0]], "row 0, column 0"),
        ([[0, 0, np.nan]], "not finite"),
        ([[0, 0, np.inf]], "not finite"),
    ],
)
def test_out_of_range(actions, fragment):
    with pytest.raises(PressureRangeError, match=fragment):
        ActionSequence(actions)


@pytest.mark.parametrize("actions", [np.zeros((0, 3)), np.zeros((2, 0)), np.zeros(3)])
def test_bad_shapes(actions):
    with pytest.raises(ValueError, match="shape"):
        ActionSequence(actions)


def test_csv_round_trip(tmp_path):
    seq = ActionSequence(np.random.default_rng(1).uniform(0, 90, (7, 3)))
    path = tmp_path / "a.csv"
    write_actions_csv(seq, path)
    assert path.read_text().splitlines()[0] == "p1,p2,p3"
    back = read_actions_csv(path)
    np.testing.assert_array_equal(back.actions, seq.actions)


def test_csv_without_header(tmp_path):
    path = tmp_path / "a.csv"
    path.write_text("0, 90, 0\n\n90,0,0\n")
    np.testing.assert_array_equal(read_actions_csv(path).actions, [[0, 90, 0], [90, 0, 0]])


@pytest.mark.parametrize(
    "text, fragment",
    [
        ("p1,p2,p3\n1,2,3\n4,5\n", "line 3: expected 3 columns, got 2"),
        ("1,2,3\n1,x,3\n", "line 2: non-numeric"),
        ("p1,p2,p3\n", "no actions"),
        ("", "no actions"),
    ],
)
def test_malformed_csv(tmp_path, text, fragment):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(ValueError, match=fragment):
        read_actions_csv(path)


def test_csv_unreadable(tmp_path):
    path = tmp_path / "bin.csv"
    path.write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(ValueError, match="cannot read"):
        read_actions_csv(path)
    with pytest.raises(FileNotFoundError):
        read_actions_csv(tmp_path / "missing.csv")


def test_csv_out_of_range(tmp_path):
    path = tmp_path / "hi.csv"
    path.write_text("0,0,0\n0,0,120\n")
    with pytest.raises(PressureRangeError, match=r"hi\.csv, line 2, p3: 120 kPa is outside"):
        read_actions_csv(path)
