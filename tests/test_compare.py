"""softcrawl compare: sim vs real pressures and distances, importers, Markdown summary."""

import json
from pathlib import Path

import numpy as np
import pytest

from softcrawl.gaits import paper_best_gait
from softcrawl.hardware.compare import compare, read_real, read_tracked
from softcrawl.hardware.deploy import deploy
from softcrawl.hardware.simrig import SimRig
from helpers import fake_sim_run

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "auro2023"


def test_compare_deploy_logs_with_tracks(tmp_path):
    actions = paper_best_gait(n_actions=6).actions
    sim = fake_sim_run(tmp_path / "sim", actions)
    logs, tracks = [], []
    for seed in range(3):
        r = deploy(SimRig(seed=seed).rig, actions, tmp_path / f"real{seed}", progress=False)
        assert r.status == "completed"
        logs.append(tmp_path / f"real{seed}")
        t = np.linspace(0, 6, 61)
        tr = tmp_path / f"track{seed}.csv"
        np.savetxt(tr, np.c_[t, 100 + (1.0 + 0.2 * seed) * t], delimiter=",", header="t_s,x_mm", comments="")
        tracks.append(tr)
    res = compare(sim, logs, tmp_path / "cmp", tracks)
    assert res["sim_final_distance_cm"] == pytest.approx(1.2, abs=1e-6)
    assert res["real_final_distances_cm"] == pytest.approx([0.6, 0.72, 0.84])
    sp = res["spread"]
    assert sp["n"] == 3 and sp["mean_cm"] == pytest.approx(0.72) and sp["std_cm"] == pytest.approx(0.12)
    assert sp["real_over_sim"] == pytest.approx(0.6)
    for row in res["logs"]:
        assert row["max_command_mismatch_kpa"] < 1e-6  # same gait
        rms = row["rms_sensed_minus_sim_kpa"]
        assert all(0 < v < 30 for v in rms)
    md = (tmp_path / "cmp" / "compare.md").read_text()
    assert "| real0 | deploy | completed |" in md and "mean +0.72 cm" in md and "std 0.12 cm" in md
    for f in ("pressures.png", "distance.png", "compare.json"):
        assert (tmp_path / "cmp" / f).stat().st_size > 1000
    assert json.loads((tmp_path / "cmp" / "compare.json").read_text())["spread"]["n"] == 3


def test_compare_flags_a_different_gait_and_bad_inputs(tmp_path):
    sim = fake_sim_run(tmp_path / "sim", paper_best_gait(n_actions=4).actions)
    deploy(SimRig().rig, np.full((4, 3), 30.0), tmp_path / "real", progress=False)
    res = compare(sim, [tmp_path / "real"], tmp_path / "cmp")
    assert res["logs"][0]["max_command_mismatch_kpa"] > 50 and res["spread"] is None
    assert "did not run the simulated gait" in (tmp_path / "cmp" / "compare.md").read_text()
    with pytest.raises(ValueError, match="one per log"):
        compare(sim, [tmp_path / "real"], tmp_path / "c2", [tmp_path / "a.csv", tmp_path / "b.csv"])
    with pytest.raises(FileNotFoundError):
        compare(tmp_path / "nosim", [tmp_path / "real"], tmp_path / "c3")
    with pytest.raises(FileNotFoundError):
        read_real(tmp_path / "missing.csv")
    bad = tmp_path / "t.csv"
    bad.write_text("t_s,x_mm\n0,1\n0,2\n")
    with pytest.raises(ValueError, match="increasing"):
        read_tracked(bad)
    bad.write_text("time,x\n0,1\n1,2\n")
    with pytest.raises(ValueError, match="header"):
        read_tracked(bad)


def test_compare_time_scale_for_a_policy_with_short_holds(tmp_path):
    """A policy trained with 0.25-s holds, deployed at 1 s per action: simulated time is stretched."""
    actions = paper_best_gait(n_actions=4).actions
    sim = fake_sim_run(tmp_path / "sim", actions, hold=0.25)
    deploy(SimRig().rig, actions, tmp_path / "real", meta={"sim_hold_s": 0.25}, progress=False)
    res = compare(sim, [tmp_path / "real"], tmp_path / "cmp")
    assert res["sim_time_scale"] == pytest.approx(4.0) and res["logs"][0]["max_command_mismatch_kpa"] < 1e-6


@pytest.mark.skipif(not (DATA / "policies").is_dir(), reason="recorded logs (../shared) absent")
def test_compare_recorded_auro_logs_cli(tmp_path, capsys):
    from softcrawl.cli import main

    logs = sorted((DATA / "pressure_logs" / "trials-L1-noncoopt").glob("logs-*table*.csv"))
    assert logs
    run = read_real(logs[0])
    assert run.kind == "auro2023" and run.sensed_kpa.shape == (20, 3)
    # the simulated run: the L1 policy as recorded (rows: regulators), 1-s holds
    pol = np.loadtxt(DATA / "policies" / "L1_pressure.csv", delimiter=",").T
    sim = fake_sim_run(tmp_path / "sim", np.clip(pol, 0, 90))
    assert main(["compare", str(sim), *map(str, logs), "--out", str(tmp_path / "cmp")]) == 0
    res = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert len(res["logs"]) == len(logs)
    assert main(["compare", str(sim), str(DATA / "README.md"), "--out", str(tmp_path / "c2")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def _deploy_folder(tmp_path: Path) -> Path:
    out = tmp_path / "real"
    deploy(SimRig().rig, paper_best_gait(n_actions=2).actions, out, progress=False)
    return out


@pytest.mark.parametrize("edit, match", [
    ({"control_period_s": "1.0"}, "field 'control_period_s' must be a positive number, got str"),
    ({"sim_hold_s": [0.25]}, "field 'sim_hold_s' must be a positive number, got list"),
    ({"status": {"a": 1}}, "field 'status' must be str, got dict"),
    ({"samples": True}, "field 'samples' must be int, got bool"),
    ({"control_period_s": 1e999}, "field 'control_period_s' must be a positive number"),
])
def test_deploy_summary_with_a_wrong_type_is_a_clear_error(tmp_path, edit, match):
    sim = fake_sim_run(tmp_path / "sim", paper_best_gait(n_actions=2).actions)
    out = _deploy_folder(tmp_path)
    s = json.loads((out / "summary.json").read_text())
    s.update(edit)
    (out / "summary.json").write_text(json.dumps(s).replace("Infinity", "1e999"))
    with pytest.raises(ValueError, match=match):
        compare(sim, [out], tmp_path / "cmp")
    (out / "summary.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="must be a JSON object, got list"):
        read_real(out)


def test_compare_out_is_guarded(tmp_path, capsys):
    """``compare --out`` writes only into a new folder, or with ``--overwrite`` into one softcrawl
    wrote (regression: it wrote into any folder, a deploy's or a stranger's), and checks that
    before reading a log."""
    from softcrawl.cli import main

    sim = fake_sim_run(tmp_path / "sim", paper_best_gait(n_actions=2).actions)
    real = _deploy_folder(tmp_path)
    stranger = tmp_path / "thesis"
    stranger.mkdir()
    (stranger / "draft.tex").write_text("precious")
    args = ["compare", str(sim), str(real), "--out"]
    assert main([*args, str(stranger)]) == 2 and "already exists" in capsys.readouterr().err
    assert main([*args, str(stranger), "--overwrite"]) == 2 and "not a softcrawl output" in capsys.readouterr().err
    assert sorted(p.name for p in stranger.iterdir()) == ["draft.tex"]
    assert main([*args, str(tmp_path / "cmp")]) == 0
    assert main([*args, str(tmp_path / "cmp")]) == 2  # exists: refused without --overwrite
    assert main([*args, str(tmp_path / "cmp"), "--overwrite"]) == 0
    assert (tmp_path / "cmp" / "compare.md").is_file()


def test_log_values_that_do_not_fit_and_device_links_are_refused(tmp_path, capsys):
    """A 401-digit number in log.csv (inf), a recorded log with a 401-digit integer reading
    (OverflowError), log.csv -> /dev/zero: one-line errors naming the file, never a traceback or
    an endless read."""
    from softcrawl.cli import main

    sim = fake_sim_run(tmp_path / "sim", paper_best_gait(n_actions=2).actions)
    out = _deploy_folder(tmp_path)
    rows = (out / "log.csv").read_text().splitlines()
    cells = rows[3].split(",")
    cells[11] = "1" * 401
    (out / "log.csv").write_text("\n".join(rows[:3] + [",".join(cells)] + rows[4:]) + "\n")
    with pytest.raises(ValueError, match=r"log.csv, line 4: .*infinite"):
        read_real(out)
    ok = "{'regulator': [1, 2, 3], 'honeywell': [4, 5, 6]}"
    rec = tmp_path / "logs-x.csv"
    rec.write_text("\n".join([",".join(str(1000 * i) for i in range(20)), *[",".join(["10"] * 20)] * 3,
                              ",".join(f'"{ok}"' for _ in range(19)) + f',"{ok.replace("4,", "1" * 401 + ",")}"'])
                   + "\n")
    assert main(["compare", str(sim), str(rec), "--out", str(tmp_path / "c1")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "logs-x.csv, line 5: reading 19" in err
    (out / "log.csv").unlink()
    (out / "log.csv").symlink_to("/dev/zero")
    assert main(["compare", str(sim), str(out), "--out", str(tmp_path / "c2")]) == 2
    assert "not a regular file" in capsys.readouterr().err
