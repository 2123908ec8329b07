"""softcrawl calibrate: bend matching by root finding on the clamped PneuNet, the affine fit,
the calibration file and its loader."""

import json

import numpy as np
import pytest

from softcrawl.hardware.calibration import (BendCurve, BendModel, calibrate, load_calibration, plot_calibration,
                                            read_bends_csv, write_calibration)
from softcrawl.robot.actuation import REAL_KPA_TABLE, SIM_KPA_TABLE, PressureCalibration

A_REF, B_REF = 4.0785, -20.36


def _analytic(p):
    """A monotone, nonlinear stand-in for the FEM bend: (angle deg, deflection mm)."""
    return 0.3 * p ** 0.95, 80 * (1 - np.exp(-p / 300))


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SOFTCRAWL_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache"


def test_round_trip_analytic_and_cache(cache):
    fwd = BendCurve(BendModel(mesh_size=99.0), evaluate=_analytic, cache=False)
    for measure in ("tip_angle_deg", "tip_deflection_mm"):
        bends = [fwd.bend(p, measure) for p in SIM_KPA_TABLE]
        curve = BendCurve(BendModel(mesh_size=99.0), evaluate=_analytic)
        res = calibrate(REAL_KPA_TABLE, bends, measure, curve)
        assert np.allclose(res.sim_kpa, SIM_KPA_TABLE, atol=0.02)
        assert res.a == pytest.approx(A_REF, rel=1e-3) and res.b == pytest.approx(B_REF, rel=1e-2)
        assert np.allclose(res.residual_kpa, res.a * np.array(REAL_KPA_TABLE) + res.b - res.sim_kpa)
        again = BendCurve(BendModel(mesh_size=99.0), evaluate=_analytic)  # read back from the disk cache
        res2 = calibrate(REAL_KPA_TABLE, bends, measure, again)
        assert again.evaluations == 0 and np.allclose(res2.sim_kpa, res.sim_kpa)
    assert len(list((cache / "bend_curves").glob("*.json"))) == 1


def test_unreachable_or_bad_bends_are_refused():
    curve = BendCurve(BendModel(mesh_size=99.0), evaluate=_analytic, cache=False)
    with pytest.raises(ValueError, match="beyond"):
        curve.find_pressure(10_000.0)
    with pytest.raises(ValueError, match="> 0"):
        curve.find_pressure(-1.0)
    with pytest.raises(ValueError):
        calibrate([10.0], [3.0], curve=curve)
    with pytest.raises(ValueError, match="measure"):
        calibrate([10.0, 20.0], [3.0, 6.0], "tip_twist", curve=curve)


def test_calibration_file_round_trip_and_loader_errors(tmp_path):
    curve = BendCurve(BendModel(mesh_size=99.0), evaluate=_analytic, cache=False)
    res = calibrate([20.0, 50.0, 80.0], [_analytic(p)[0] for p in (60.0, 180.0, 300.0)], curve=curve)
    path = write_calibration(res, tmp_path / "cal.json", source="bends.csv")
    cal = load_calibration(path)
    assert isinstance(cal, PressureCalibration) and cal.a == pytest.approx(4.0, abs=1e-3)
    assert cal.b == pytest.approx(-20.0, abs=0.1)
    d = json.loads(path.read_text())
    assert d["format"] == "softcrawl-calibration" and len(d["points"]) == 3 and d["rms_residual_kpa"] < 0.05
    assert plot_calibration(res, tmp_path / "cal.png").stat().st_size > 10_000
    bad = {"not json": "{", "wrong format": json.dumps({"format": "x", "a": 1, "b": 0}),
           "no a": json.dumps({"format": "softcrawl-calibration", "version": 1, "b": 0}),
           "nan": '{"format": "softcrawl-calibration", "version": 1, "a": NaN, "b": 0}',
           "string": json.dumps({"format": "softcrawl-calibration", "version": 1, "a": "4", "b": 0}),
           "negative": json.dumps({"format": "softcrawl-calibration", "version": 1, "a": -4, "b": 0}),
           "version": json.dumps({"format": "softcrawl-calibration", "version": 9, "a": 4, "b": 0})}
    for name, text in bad.items():
        p = tmp_path / f"{name}.json"
        p.write_text(text)
        with pytest.raises(ValueError, match=p.name):
            load_calibration(p)
    with pytest.raises(FileNotFoundError):
        load_calibration(tmp_path / "missing.json")


def test_read_bends_csv(tmp_path):
    p = tmp_path / "b.csv"
    p.write_text("real_kpa,tip_angle_deg\n10,5.5\n20,12.1\n")
    real, bend, measure = read_bends_csv(p)
    assert real.tolist() == [10, 20] and bend.tolist() == [5.5, 12.1] and measure == "tip_angle_deg"
    for text, match in (("real,angle\n1,2\n3,4\n", "header"), ("real_kpa,tip_angle_deg\n10,x\n20,3\n", "line 2"),
                        ("real_kpa,tip_angle_deg\n10,-1\n20,3\n", "> 0"),
                        ("real_kpa,tip_angle_deg\n10,1\n", "at least 2")):
        p.write_text(text)
        with pytest.raises(ValueError, match=match):
            read_bends_csv(p)


def test_fem_bend_inverts_to_its_pressure(cache):
    """Root finding on the clamped full-order leg (coarse 12 mm mesh) returns the pressure the
    bend was simulated at."""
    model = BendModel(mesh_size=12.0)
    fwd = BendCurve(model, cache=False)
    targets = (65.67, 224.37)
    bends = [fwd.bend(p) for p in targets]
    assert 0 < bends[0] < bends[1]
    curve = BendCurve(model)
    for p, b in zip(targets, bends):
        assert curve.find_pressure(b) == pytest.approx(p, abs=0.05)


@pytest.mark.slow
def test_paper_table_round_trip(cache):
    """Issue #19: the paper's 10-point table reproduces sim = 4.0785 real - 20.36 within 1% when
    its bends (simulated at the table's sim pressures) are fed back in (~40 s, 12 mm mesh)."""
    model = BendModel(mesh_size=12.0)
    fwd = BendCurve(model, cache=False)
    bends = [fwd.bend(p) for p in SIM_KPA_TABLE]
    assert np.all(np.diff(bends) > 0)
    curve = BendCurve(model)  # empty cache: the root finder simulates
    res = calibrate(REAL_KPA_TABLE, bends, curve=curve)
    assert curve.evaluations >= 20
    assert res.a == pytest.approx(A_REF, rel=0.01) and res.b == pytest.approx(B_REF, rel=0.01)
    ref = A_REF * np.array(REAL_KPA_TABLE) + B_REF
    assert np.all(np.abs(res.calibration.to_sim(REAL_KPA_TABLE) - ref) <= 0.01 * np.abs(ref))


def test_cli_calibrate(tmp_path, cache, capsys):
    from softcrawl.cli import main

    fwd = BendCurve(BendModel(mesh_size=12.0))  # fills the cache the CLI then reads
    bends = tmp_path / "bends.csv"
    bends.write_text("real_kpa,tip_angle_deg\n" + "".join(f"{r},{fwd.bend(4.0785 * r - 20.36):.6f}\n"
                                                          for r in (20.0, 60.0)))
    out = tmp_path / "cal"
    assert main(["calibrate", str(bends), "--out", str(out), "--mesh-size", "12", "--no-progress"]) == 0
    cal = load_calibration(out / "calibration.json")
    assert cal.a == pytest.approx(A_REF, rel=1e-3) and cal.b == pytest.approx(B_REF, rel=1e-2)
    assert (out / "calibration.png").exists() and "sim = 4.07" in capsys.readouterr().out
    assert main(["calibrate", str(bends), "--out", str(out), "--mesh-size", "12"]) == 2  # exists
    bends.write_text("real_kpa,angle\n")
    assert main(["calibrate", str(bends), "--out", str(tmp_path / "c2")]) == 2
    assert "header" in capsys.readouterr().err


def test_unreachable_bend_raises_value_error():
    """A model that does not settle at the pressures a bend needs (the FEM at hundreds of kPa):
    ValueError as documented, not the solver's RuntimeError."""
    def stiff(p):
        if p > 100:
            raise RuntimeError(f"clamped PneuNet at {p:g} kPa did not settle in 60 s")
        return _analytic(p)

    curve = BendCurve(BendModel(mesh_size=99.0), evaluate=stiff, cache=False)
    with pytest.raises(ValueError, match="cannot be reached by the model: clamped PneuNet at 150 kPa did not settle"):
        curve.find_pressure(150.0)
    with pytest.raises(ValueError, match="cannot be reached"):
        calibrate([10.0, 90.0], [5.0, 150.0], curve=curve)


@pytest.mark.parametrize("real, bend, match", [
    ([10.0, 20.0, 30.0], [5.0, 3.0, 8.0], "bends must increase with pressure: 5 at 10 kPa but 3 at 20 kPa"),
    ([10.0, 20.0], [5.0, 5.0], "bends must increase with pressure"),
    ([10.0, 5000.0], [5.0, 8.0], r"measurement 2: real pressure 5000 kPa must be in \(0, 100\]"),
    ([10.0, 1e308], [5.0, 8.0], "real pressure 1e\\+308 kPa"),
    ([0.0, 20.0], [1.0, 8.0], "measurement 1: real pressure 0 kPa"),
    ([20.0, 20.0], [5.0, 6.0], "need at least 2 pressures"),
    ([10.0, 20.0], [5.0, np.inf], "bend inf must be finite"),
])
def test_implausible_measurements_are_refused_before_any_simulation(real, bend, match):
    calls = []
    curve = BendCurve(BendModel(mesh_size=99.0), evaluate=lambda p: calls.append(p) or _analytic(p), cache=False)
    with pytest.raises(ValueError, match=match):
        calibrate(real, bend, curve=curve)
    assert calls == []


def test_fitted_slope_outside_the_physical_range_is_refused(tmp_path):
    """Bends that the model reaches at a hundredth of the real pressure (pressures logged in the
    wrong unit) give a = 0.01: refused, and so is a calibration file with such a slope."""
    curve = BendCurve(BendModel(mesh_size=99.0), evaluate=_analytic, cache=False)
    real = [20.0, 60.0]
    with pytest.raises(ValueError, match=r"slope a = 0\.01\d* sim kPa per real kPa is outside the plausible \[0\.2,"):
        calibrate(real, [_analytic(0.01 * r)[0] for r in real], curve=curve)
    for a in (9.3e-19, 25.0):
        p = tmp_path / f"cal{a}.json"
        p.write_text(json.dumps({"format": "softcrawl-calibration", "version": 1, "a": a, "b": 0.0}))
        with pytest.raises(ValueError, match=f"{p.name}: slope a = .* outside the plausible"):
            load_calibration(p)


def test_bends_csv_refuses_implausible_pressures_with_file_and_line(tmp_path):
    p = tmp_path / "b.csv"
    for text, match in (("real_kpa,tip_angle_deg\n10,5\n5000,9\n", "b.csv, line 3: real pressure 5000 kPa"),
                        ("real_kpa,tip_angle_deg\n0,1\n20,3\n", "b.csv, line 2: real pressure 0 kPa"),
                        ("real_kpa,tip_angle_deg\n10,1\n99999999999999999999,3\n", "line 3: real pressure 1e\\+20")):
        p.write_text(text)
        with pytest.raises(ValueError, match=match):
            read_bends_csv(p)
    p.write_bytes(b"\xef\xbb\xbfreal_kpa,tip_angle_deg\n10,5\n20,9\n")  # spreadsheet export with a BOM
    assert read_bends_csv(p)[0].tolist() == [10, 20]
    link = tmp_path / "z.csv"
    link.symlink_to("/dev/zero")
    with pytest.raises(ValueError, match="not a regular file"):
        read_bends_csv(link)


def test_load_calibration_refuses_devices_and_deep_nesting(tmp_path):
    (tmp_path / "zero.json").symlink_to("/dev/zero")
    (tmp_path / "deep.json").write_text('{"format": "softcrawl-calibration", "x": ' + "[" * 5000 + "]" * 5000 + "}")
    for name, match in (("zero.json", "zero.json: not a regular file"), ("deep.json", "deep.json: nested")):
        with pytest.raises(ValueError, match=match):
            load_calibration(tmp_path / name)


def test_cli_calibrate_refuses_implausible_bends_before_creating_out(tmp_path, capsys):
    from softcrawl.cli import main

    bends = tmp_path / "bends.csv"
    bends.write_text("real_kpa,tip_angle_deg\n10,30\n20,12\n30,40\n")  # not increasing with pressure
    assert main(["calibrate", str(bends), "--out", str(tmp_path / "cal"), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "bends must increase with pressure: 30 at 10 kPa but 12 at 20 kPa" in err
    assert not (tmp_path / "cal").exists()
