"""The regulator model against the recorded real rig logs (shared/data/auro2023; skipped when
that folder is absent) and the log importer's refusal of malformed files."""

from pathlib import Path

import numpy as np
import pytest

from softcrawl.hardware import regulator_model as rm
from softcrawl.hardware.logs import read_auro_log, read_auro_logs

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "auro2023"
needs_data = pytest.mark.skipif(not (DATA / "pressure_logs").is_dir(), reason="recorded logs (../shared) absent")


@pytest.fixture(scope="module")
def trials():
    good, bad = read_auro_logs(DATA / "pressure_logs")
    return good, bad


@needs_data
def test_importer_reads_complete_files_and_rejects_malformed(trials):
    good, bad = trials
    assert len(good) == 273 and len(bad) == 10  # README: "a few files are short (10 steps) or malformed"
    assert all(t.commanded_kpa.shape == (20, 3) and t.sensed_kpa.shape == (20, 3) for t in good)
    reasons = " ".join(r for _, r in bad)
    assert "expected 20 steps" in reasons and "5 lines" in reasons
    # the real control period (issue #19: 1.067 s per nominal 1-s step)
    assert np.mean(np.concatenate([t.hold_s for t in good])) == pytest.approx(1.067, abs=0.002)


@needs_data
def test_channel_order_matches_the_commands(trials):
    """Regulator k's command correlates best with regulator reading index 2 - (k-1) and with
    Honeywell index k-1 (the importer's reordering)."""
    good, _ = trials
    c = np.concatenate([t.commanded_kpa[:-1] for t in good])
    for name in ("regulator_kpa", "sensed_kpa"):
        s = np.concatenate([getattr(t, name)[1:] for t in good])
        corr = np.corrcoef(c.T, s.T)[:3, 3:]
        assert np.all(np.argmax(corr, axis=1) == [0, 1, 2]), (name, corr.round(2))


@needs_data
def test_regulator_fit_on_held_out_logs(trials):
    good, _ = trials
    fit, held = rm.split_trials(good)
    assert len(fit) == 205 and len(held) == 68
    params = rm.fit_regulators(fit)
    hold = 1.067  # s, the rig's mean control period
    for p, q in zip(params, rm.FITTED):  # the shipped constants are this fit
        assert p.gain == pytest.approx(q.gain, abs=2e-3) and p.offset == pytest.approx(q.offset, abs=0.02)
        # The logs see a time constant only through the part of a step left at the end of a
        # hold, exp(-hold / tau): regulator 2 inflates within a hold (tau ~0.03 s leaves e^-40),
        # so its tau_inflate is not identifiable and the fit lands anywhere below ~0.1 s with
        # the machine's rounding (0.027 or 0.041 s seen). Compare what the data determine.
        for a, b in ((p.tau_inflate, q.tau_inflate), (p.tau_vent, q.tau_vent)):
            assert np.exp(-hold / a) == pytest.approx(np.exp(-hold / b), abs=5e-3)
    err = rm.prediction_errors(rm.FITTED, held)
    naive = rm.prediction_errors([rm.RegulatorParams(1.0, 0.0, 1e-3, 1e-3)] * 3, held)
    # held-out one-step error of the sensed pressure at the end of a 1.067-s hold (kPa)
    assert err["n_holds"] > 3000
    assert err["rmse"] < 13.0 and err["median_abs"] < 6.5
    assert err["rmse"] < naive["rmse"] - 1.0 and err["median_abs"] < naive["median_abs"] - 1.0
    held_fit = rm.prediction_errors(params, held)
    assert held_fit["rmse"] < 13.0


def test_fitted_end_of_hold_pressure_lies_in_the_recorded_band_within_2_kpa():
    """The recorded trials read 0.79-0.99 x command + 3-7 kPa at the end of a 1.067-s hold; the
    fitted regulators' end-of-hold pressures for 45 and 90 kPa commands lie in that band widened
    by 2 kPa each side. Measured: 37.7-43.9 kPa at 45 kPa (band 38.55-51.55) and 80.3-89.9 kPa at
    90 kPa (band 74.1-96.1); regulator 2 at 45 kPa is the closest, 0.85 kPa below the band's edge
    (the margin: well under the fit's 5.9 kPa median held-out error, docs/results.md)."""
    margin = 2.0
    for p in rm.FITTED:
        for cmd in (45.0, 90.0):
            end = p.advance(0.0, cmd, 1.067)
            assert 0.79 * cmd + 3 - margin < end < 0.99 * cmd + 7 + margin, (p, cmd, end)


def test_first_order_model_lags():
    p = rm.RegulatorParams(gain=1.0, offset=0.0, tau_inflate=0.2, tau_vent=0.5)
    up = p.advance(0.0, 90.0, 0.2)
    assert up == pytest.approx(90 * (1 - np.exp(-1)))
    down = p.advance(90.0, 0.0, 0.5)
    assert down == pytest.approx(90 * np.exp(-1))
    with pytest.raises(ValueError):
        rm.RegulatorParams(tau_vent=0.0)


def test_importer_refuses_malformed_files(tmp_path):
    ok_dicts = ",".join('"{\'regulator\': [1, 2, 3], \'honeywell\': [4, 5, 6], \'commanded\': [0, 0, 0]}"'
                        for _ in range(20))
    times = ",".join(str(1000 + 1067 * i) for i in range(20))
    row = ",".join(["10"] * 20)
    good = tmp_path / "logs-good.csv"
    good.write_text("\n".join([times, row, row, row, ok_dicts]) + "\n")
    t = read_auro_log(good)
    assert np.allclose(t.regulator_kpa[0], [3, 2, 1]) and np.allclose(t.sensed_kpa[0], [4, 5, 6])
    assert t.t_s[0] == 0 and t.t_s[1] == pytest.approx(1.067)
    cases = {
        "short": "\n".join([",".join(times.split(",")[:10]), *[",".join(["1"] * 10)] * 3,
                            ",".join(ok_dicts.split('","')[:1])]),
        "four lines": "\n".join([times, row, row, row]),
        "code": "\n".join([times, row, row, row, ",".join(['"__import__(\'os\').system(\'true\')"'] * 20)]),
        "text": "\n".join([times, row.replace("10", "x", 1), row, row, ok_dicts]),
    }
    for name, text in cases.items():
        p = tmp_path / f"logs-{name.replace(' ', '_')}.csv"
        p.write_text(text + "\n")
        with pytest.raises(ValueError, match=str(p.name)):
            read_auro_log(p)
    with pytest.raises(FileNotFoundError):
        read_auro_log(tmp_path / "missing.csv")


@needs_data
def test_cli_rig_fit(tmp_path, capsys):
    import json

    from softcrawl.cli import main

    assert main(["rig", "fit", str(DATA / "pressure_logs"), "--out", str(tmp_path / "fit.json")]) == 0
    out = capsys.readouterr().out
    assert "273 logs (10 refused" in out and "held out 68" in out
    d = json.loads((tmp_path / "fit.json").read_text())
    assert d["held_out"]["rmse"] < 13.0 and len(d["regulators"]) == 3
    assert main(["rig", "fit", str(tmp_path)]) == 2  # no logs there


def _synthetic_log(path, rng):
    """A recorded-format log (20 one-second holds) whose readings follow the fitted regulator model."""
    cmd = rng.choice([0.0, 45.0, 90.0], size=(20, 3))
    p, cells = np.zeros(3), []
    for k in range(20):
        r = [round(float(x), 3) for x in p]
        cells.append('"' + str({"regulator": r[::-1], "honeywell": r, "commanded": cmd[k].tolist()}) + '"')
        p = np.array([prm.advance(x, c, 1.0) for prm, x, c in zip(rm.FITTED, p, cmd[k])])
    lines = [",".join(str(1000 * k) for k in range(20)), *(",".join(f"{x:g}" for x in cmd[:, j]) for j in range(3)),
             ",".join(cells)]
    path.write_text("\n".join(lines) + "\n")
    return lines


def test_value_that_does_not_fit_refuses_one_file_with_its_line(tmp_path):
    """A 401-digit integer in a reading (OverflowError in float()) or in a time stamp (inf) refuses
    that file, naming it and the line."""
    lines = _synthetic_log(tmp_path / "logs-good.csv", np.random.default_rng(0))
    huge = "1" * 401
    cases = {"reading": (4, lines[4].replace("'honeywell': [", f"'honeywell': [{huge}, ", 1)),
             "time": (0, lines[0].replace("1000", huge, 1))}
    for name, (i, text) in cases.items():
        p = tmp_path / f"logs-{name}.csv"
        p.write_text("\n".join(lines[:i] + [text] + lines[i + 1:]) + "\n")
        with pytest.raises(ValueError, match=rf"logs-{name}.csv, line {i + 1}: .*(finite|number)"):
            read_auro_log(p)


def test_cli_rig_fit_skips_and_reports_bad_files(tmp_path, capsys):
    """`rig fit` refuses a file with a value that does not fit, a link to a device and a dangling
    link, reports each with its name, and fits the others."""
    from softcrawl.cli import main

    rng = np.random.default_rng(1)
    for i in range(5):
        lines = _synthetic_log(tmp_path / f"logs-{i}.csv", rng)
    (tmp_path / "logs-huge.csv").write_text("\n".join(lines[:4] + [lines[4].replace("[", "[" + "9" * 401 + ", ", 1)]))
    (tmp_path / "logs-z.csv").symlink_to("/dev/zero")
    (tmp_path / "logs-gone.csv").symlink_to(tmp_path / "nowhere.csv")
    assert main(["rig", "fit", str(tmp_path), "--out", str(tmp_path / "fit.json")]) == 0
    out = capsys.readouterr().out
    assert "5 logs (3 refused" in out
    for name, why in (("logs-huge.csv", "line 5"), ("logs-z.csv", "not a regular file"),
                      ("logs-gone.csv", "No such file")):
        assert any(name in line and why in line for line in out.splitlines() if "refused:" in line), name
    import json

    assert len(json.loads((tmp_path / "fit.json").read_text())["refused"]) == 3
