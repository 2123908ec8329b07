"""Seeded fuzz tests (hypothesis, derandomized) of what the rig commands read: rig files, action
CSVs, bend tables and calibration files, deploy folders and recorded logs. Every input is either
accepted, and then valid by the rules the readers document, or refused with a ValueError (or
FileNotFoundError) of one line; through the CLI, exit code 2 with one line on stderr, never a
traceback, and never a file written outside ``--out``."""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from softcrawl.cli import main
from softcrawl.hardware.calibration import (A_RANGE, MAX_REAL_KPA, BendCurve, BendModel, calibrate, load_calibration,
                                            read_bends_csv)
from softcrawl.hardware.compare import read_real
from softcrawl.hardware.config import example_rig_path, load_rig_config
from softcrawl.hardware.deploy import deploy
from softcrawl.hardware.logs import read_auro_log
from softcrawl.hardware.simrig import SimRig

FUZZ = settings(max_examples=40, deadline=None, database=None, derandomize=True,
                suppress_health_check=list(HealthCheck))


def _one_line(exc: BaseException) -> str:
    msg = str(exc)
    assert msg and "\n" not in msg, msg
    return msg


def _cli(capsys, argv) -> int:
    """``main(argv)``: 0, or 2 with one line on stderr; never a traceback."""
    try:
        rc = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse
        rc = exc.code
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    if rc != 0:
        assert rc == 2 and err and "\n" not in err, (rc, err)
    return rc


# -- rig files ------------------------------------------------------------------------------------------

_RIG_LINES = example_rig_path().read_text().splitlines()
_RIG_VALUES = st.one_of(
    st.sampled_from(["0", "-1", "1e-300", "1e308", "nan", "inf", "-5", "0x78", "255", "256", "100000000000000000000",
                     '"x"', '"a\\nb"', '"\\u001b[2J"', '""', "[]", "[1, 2]", "[0, 1, 2]", "[5.0, 5.0, 30.0]", "true",
                     "{}", "[" * 100 + "]" * 100, "0.001", "0.3", "90.0", "5.0", "1", "2", "3"]),
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(-2 ** 70, 2 ** 70).map(str))


@st.composite
def _rig_text(draw) -> str:
    """The example rig.toml with a few lines' values replaced, lines dropped or duplicated."""
    lines = list(_RIG_LINES)
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(lines) - 1))
        how = draw(st.sampled_from(["value", "value", "drop", "dup", "garbage"]))
        key = lines[i].split("=")[0].strip() if "=" in lines[i] else None
        if how == "value" and key:
            lines[i] = f"{key} = {draw(_RIG_VALUES)}"
        elif how == "drop":
            del lines[i]
        elif how == "dup":
            lines.insert(i, lines[i])
        elif how == "garbage":
            lines[i] = draw(st.text(alphabet="[]=\"'.#ab01\\ \t\x00\x1b", max_size=20))
    return "\n".join(lines) + "\n"


@FUZZ
@given(text=_rig_text())
def test_fuzz_rig_files(text, capsys):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "rig.toml"
        p.write_text(text)
        try:
            cfg = load_rig_config(p)
        except ValueError as exc:
            assert str(p) in _one_line(exc)
            assert _cli(capsys, ["rig", "check", p, "--sim"]) == 2
            return
        r = cfg.rig  # accepted: within every documented bound
        assert 0 < r.max_kpa <= 90 and r.name.isprintable() and 10 <= r.sample_hz <= 1000
        for m in cfg.regulators:
            assert 1e-3 <= m.volts_per_kpa and m.volts(r.max_kpa) <= cfg.supply.max_volts[m.channel - 1]
        sn = cfg.sensors
        assert sn.bus is None or (0 <= sn.bus <= 255 and 0x08 <= sn.mux_address <= 0x77)
        assert _cli(capsys, ["rig", "check", p, "--sim"]) == 0


# -- action CSVs through `deploy --rig sim` -----------------------------------------------------------------

_CSV_CELLS = st.sampled_from(["0", "45", "90", "90.0", "95", "-1", "nan", "1e400", "1" * 401, "x", "", " 30 "])


@FUZZ
@given(rows=st.lists(st.lists(_CSV_CELLS, min_size=2, max_size=4), min_size=0, max_size=4),
       header=st.booleans(), bom=st.booleans(), crlf=st.booleans())
def test_fuzz_deploy_action_csv(rows, header, bom, crlf, capsys):
    nl = "\r\n" if crlf else "\n"
    text = (("p1,p2,p3" + nl) if header else "") + nl.join(",".join(r) for r in rows) + nl
    with tempfile.TemporaryDirectory() as d:
        root = Path(d)
        (root / "gait.csv").write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
        rc = _cli(capsys, ["deploy", "--rig", "sim", "--actions", root / "gait.csv", "--out", root / "out",
                           "--no-progress"])
        if rc == 0:
            s = json.loads((root / "out" / "summary.json").read_text())
            a = np.array(s["actions_kpa"])
            assert s["status"] == "completed" and s["fail_safe_confirmed"] and np.all((a >= 0) & (a <= 90))
        else:
            assert not (root / "out").exists()  # refused before anything moved or was written


# -- bend tables and calibration files ------------------------------------------------------------------------

def _analytic(p):
    return 0.3 * p ** 0.95, 80 * (1 - np.exp(-p / 300))


_NUM = st.one_of(st.sampled_from(["0", "-5", "100", "100.5", "1e308", "5000", "nan", "inf", "99999999999999999999",
                                  "x", ""]),
                 st.floats(0.5, 120, allow_nan=False).map(lambda v: f"{v:.3g}"))


@FUZZ
@given(rows=st.lists(st.tuples(_NUM, _NUM), min_size=0, max_size=5),
       head=st.sampled_from(["real_kpa,tip_angle_deg", "real_kpa,tip_deflection_mm", "real_kpa,angle", ""]))
def test_fuzz_bend_tables(rows, head):
    curve = BendCurve(BendModel(mesh_size=99.0), evaluate=_analytic, cache=False)
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "bends.csv"
        p.write_text(head + "\n" + "\n".join(f"{a},{b}" for a, b in rows) + "\n")
        try:
            real, bend, measure = read_bends_csv(p)
            res = calibrate(real, bend, measure, curve)
        except ValueError as exc:
            _one_line(exc)
            return
    assert np.all((res.real_kpa > 0) & (res.real_kpa <= MAX_REAL_KPA)) and A_RANGE[0] <= res.a <= A_RANGE[1]
    order = np.argsort(res.real_kpa)
    assert np.all(np.diff(res.bend[order])[np.diff(res.real_kpa[order]) > 0] > 0)


_JSON_VALUE = st.recursive(st.one_of(st.none(), st.booleans(), st.integers(-10 ** 30, 10 ** 30),
                                     st.floats(allow_nan=False, allow_infinity=False), st.text(max_size=5)),
                           lambda c: st.one_of(st.lists(c, max_size=3), st.dictionaries(st.text(max_size=3), c,
                                                                                        max_size=3)), max_leaves=8)


@FUZZ
@given(a=st.one_of(_JSON_VALUE, st.floats(-100, 100)), b=_JSON_VALUE,
       fmt=st.sampled_from(["softcrawl-calibration", "x", None]), version=st.sampled_from([1, 2, "1", None]),
       raw=st.one_of(st.none(), st.sampled_from(["", "{", "[" * 3000 + "]" * 3000, '{"a": NaN}', "1e999",
                                                 '{"format": "softcrawl-calibration", "version": 1, "a": 1e999, '
                                                 '"b": 0}'])))
def test_fuzz_calibration_files(a, b, fmt, version, raw):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "calibration.json"
        p.write_text(raw if raw is not None else json.dumps({"format": fmt, "version": version, "a": a, "b": b}))
        try:
            cal = load_calibration(p)
        except ValueError as exc:
            assert str(p) in _one_line(exc)
            return
    assert A_RANGE[0] <= cal.a <= A_RANGE[1] and np.isfinite(cal.b)


# -- deploy folders and recorded logs -------------------------------------------------------------------------

@pytest.fixture(scope="module")
def deployed(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("deployed") / "d"
    assert deploy(SimRig().rig, [[0, 90, 0], [90, 0, 0]], out, progress=False).status == "completed"
    return out


_DAMAGE = ["delete", "empty", "garbage", "json-list", "json-deep", "field-type", "huge-number", "cell",
           "truncate", "dev-zero", "dangling"]
_FIELDS = ["status", "reason", "samples", "overruns", "simulated", "sim_hold_s", "control_period_s",
           "sample_hz_achieved"]


@FUZZ
@given(damage=st.lists(st.tuples(st.sampled_from(["log.csv", "summary.json"]), st.sampled_from(_DAMAGE)),
                       min_size=1, max_size=2),
       field=st.sampled_from(_FIELDS), value=_JSON_VALUE, noise=st.binary(min_size=1, max_size=64),
       where=st.integers(0, 10 ** 6))
def test_fuzz_deploy_folders(deployed, damage, field, value, noise, where):
    with tempfile.TemporaryDirectory() as d:
        run = Path(d) / "d"
        shutil.copytree(deployed, run)
        for name, how in damage:
            p = run / name
            if p.is_symlink() or not p.exists():
                p.unlink(missing_ok=True)
                continue
            text = p.read_bytes().decode("utf-8", "replace")  # an earlier damage may have left bytes
            if how == "delete":
                p.unlink()
            elif how == "empty":
                p.write_text("")
            elif how == "garbage":
                p.write_bytes(noise)
            elif how == "json-list":
                p.write_text("[1, 2]")
            elif how == "json-deep":
                p.write_text("[" * 5000 + "]" * 5000)
            elif how == "field-type" and name == "summary.json":
                try:
                    s = json.loads(text)
                    s[field] = value
                except (ValueError, TypeError):  # an earlier damage: no longer a summary object
                    continue
                p.write_text(json.dumps(s))
            elif how == "huge-number":
                i = where % max(len(text) - 1, 1)
                p.write_text(text[:i] + "1" * 401 + text[i:])
            elif how == "cell" and name == "log.csv":
                lines = text.splitlines()
                k = 1 + where % (len(lines) - 1)
                cells = lines[k].split(",")
                cells[where % len(cells)] = ["", "x", "inf", "-inf", "nan", "1e999", "1" * 401, "1,2"][where % 8]
                lines[k] = ",".join(cells)
                p.write_text("\n".join(lines) + "\n")
            elif how == "truncate":
                p.write_text(text[:where % len(text)])
            elif how == "dev-zero":
                p.unlink()
                p.symlink_to("/dev/zero")
            elif how == "dangling":
                p.unlink()
                p.symlink_to(Path(d) / "nowhere")
        try:
            real = read_real(run)
        except (ValueError, FileNotFoundError) as exc:
            _one_line(exc)
            return
    assert real.kind == "deploy" and np.isfinite(real.t_s).all() and not np.isinf(real.sensed_kpa).any()
    h, period = real.info.get("sim_hold_s"), real.info.get("control_period_s")
    for v in (h, period):
        assert v is None or (isinstance(v, (int, float)) and v > 0)


_CELL = st.sampled_from(["10", "1" * 401, "-1e999", "nan", "x", "", "'a'", "{'regulator': [1, 2, 3], "
                         "'honeywell': [4, 5, " + "9" * 401 + "]}", "{'regulator': [[[[[]]]]]}", "()" * 50,
                         "{'regulator': [1, 2, 3], 'honeywell': [4, 5, 6]}"])


@FUZZ
@given(lines=st.lists(st.lists(_CELL, min_size=1, max_size=22), min_size=0, max_size=6))
def test_fuzz_recorded_logs(lines):
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / "logs-x.csv"
        p.write_text("\n".join(",".join(f'"{c}"' for c in row) for row in lines) + "\n")
        try:
            tr = read_auro_log(p)
        except ValueError as exc:
            assert p.name in _one_line(exc)
            return
    assert tr.n_steps == 20 and np.isfinite(tr.sensed_kpa).all() and np.all(np.diff(tr.t_s) > 0)
