"""Ground truth, regret and settings lose nothing and fail fast: one regression test per
defect (numbered as in the probe report: 4 results rewritten, 5 output folder unguarded, 6 rows
not validated, 7 tracebacks on malformed files, 8 settings validated late, 13 deep nesting,
14/15 settings without bounds, 16 a silent Ray address, 18 two runs on one folder)."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path

import pytest

from groundtruth_helpers import DESIGNS, SETTINGS, fake_task, killed_folder, make_folder, reward, row
from softcrawl.cli import main as cli_main
from softcrawl.codesign import groundtruth_regret as rg
from softcrawl.codesign.config import override, preset
from softcrawl.codesign.groundtruth import (
    LOCK,
    FolderLockedError,
    GroundTruthConfig,
    folder_lock,
    load_groundtruth,
    read_results,
    run_groundtruth,
    write_outputs,
)
from softcrawl.safeio import UnsafeFileError, loads_json

BEST = max(DESIGNS, key=reward)
GT_CLI = ["--designs", "1,0,0,2,2,0,0,0", "--no-progress", "--executor", "serial"]


@pytest.fixture(autouse=True)
def no_simulation(monkeypatch):
    """``softcrawl groundtruth`` in this process computes fake designs and no references: a test
    whose refusal fails ends at once instead of simulating."""
    import softcrawl.codesign.groundtruth.runner as gtmod

    monkeypatch.setattr(gtmod, "optimize_design", lambda d, cfg: gtmod.DesignResult.from_dict(fake_task(d, None)))
    monkeypatch.setattr(gtmod, "references", lambda cfg: {})


def _one_line_error(capsys, *words) -> str:
    err = capsys.readouterr().err
    assert err.count("error:") == 1 and "Traceback" not in err, err
    for w in words:
        assert w in err, err
    return err


def _regret_cli(monkeypatch, gt: Path, design, *extra) -> int:
    """``softcrawl regret RUN --groundtruth gt`` with the run's choice ``design`` (no training run)."""
    monkeypatch.setattr(rg, "run_choice", lambda run: {"design": tuple(design), "prob": 0.9, "latest_cm": 1.0,
                                                        "episodes": 7})
    monkeypatch.setattr(rg, "run_settings", lambda run: rg.gt_settings(GroundTruthConfig()))
    monkeypatch.setattr(rg, "policy_reward", lambda run, d: {"reward_cm": float("nan"), "diverged": True,
                                                              "actions_kpa": [], "episode_seconds": 20.0,
                                                              "hold_s": 1.0})
    return cli_main(["regret", "RUN", "--groundtruth", str(gt), *extra])


# -- 4: results are never rewritten by a reader ----------------------------------------------------
def test_4_readers_leave_every_line_in_place(tmp_path, monkeypatch, capsys):
    gt = make_folder(tmp_path / "gt")
    res = gt / "results.jsonl"
    with open(res, "a") as f:  # an extra key on a row, a line that is not JSON, a row of another version
        f.write(row(DESIGNS[0], note="hand-edited") + "\n" + "not json\n" + '{"design": [1,0,0,2,2,0,0,0]}\n')
    before = res.read_bytes()
    assert _regret_cli(monkeypatch, gt, BEST, "--json", str(tmp_path / "r.json")) == 0
    err = capsys.readouterr().err
    assert f"{res}, line 7" in err and f"{res}, line 8" in err and "line 6" not in err  # an extra key is tolerated
    write_outputs(gt)
    assert res.read_bytes() == before
    # the same run with the design of the bad row computes it, appends, and keeps every byte that was there
    calls = []
    run_groundtruth(DESIGNS + [(1, 0, 0, 2, 2, 0, 0, 0)], gt, SETTINGS, executor="serial", progress=False,
                    refs=False, task=lambda d, c: calls.append(d) or fake_task(d, c))
    assert calls == [(1, 0, 0, 2, 2, 0, 0, 0)]
    assert res.read_bytes().startswith(before) and len(res.read_text().splitlines()) == 9
    assert len(read_results(gt)[0]) == 6


def test_4_a_symlinked_results_file_is_refused_and_its_target_kept(tmp_path, monkeypatch, capsys):
    gt = make_folder(tmp_path / "gt")
    target = tmp_path / "elsewhere.jsonl"
    (gt / "results.jsonl").rename(target)
    (gt / "results.jsonl").symlink_to(target)
    kept = target.read_bytes()
    assert _regret_cli(monkeypatch, gt, BEST) == 2
    _one_line_error(capsys, "symbolic link")
    with pytest.raises(UnsafeFileError, match="symbolic link"):
        run_groundtruth(DESIGNS + [(1, 0, 0, 2, 2, 0, 0, 0)], gt, SETTINGS, executor="serial", progress=False,
                        refs=False, task=fake_task)
    assert target.read_bytes() == kept


def test_4_a_row_torn_by_a_kill_stays_a_line_of_its_own(tmp_path):
    gt = make_folder(tmp_path / "gt", DESIGNS[:2])
    with open(gt / "results.jsonl", "a") as f:
        f.write('{"design": [1, 1, 1')
    make_folder(gt, DESIGNS[:3])
    lines = (gt / "results.jsonl").read_text().splitlines()
    assert lines[2] == '{"design": [1, 1, 1' and json.loads(lines[3])["design"] == list(DESIGNS[2])


# -- 5: the output folder is guarded -----------------------------------------------------------------
@pytest.mark.parametrize("files", [
    {".softcrawl-output": "", "summary.json": '{"reward_cm": 3.1}'},  # softcrawl simulate
    {"log.csv": "t,p1\n", "summary.json": '{"vented": true}'},  # softcrawl deploy
    {"config.json": json.dumps({"config": preset("smoke").to_dict()})},  # softcrawl train
    {"notes.txt": "mine"},
])
def test_5_groundtruth_refuses_a_folder_another_command_wrote(files, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    for name, text in files.items():
        (out / name).write_text(text)
    assert cli_main(["groundtruth", "--out", str(out), *GT_CLI]) == 2
    _one_line_error(capsys, str(out), "another --out")
    assert {p.name: p.read_text() for p in out.iterdir()} == files


def test_5_groundtruth_takes_a_new_an_empty_or_its_own_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    for out in (tmp_path / "new" / "gt", tmp_path / "empty"):
        make_folder(out, DESIGNS[:1])
        make_folder(out, DESIGNS[:2])  # its own folder: continued
        assert len(read_results(out)[0]) == 2
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match="not a directory"):
        make_folder(tmp_path / "file")


# -- 6: rows are validated ---------------------------------------------------------------------------
@pytest.mark.parametrize("bad", [
    '{"design": [0,0,0,0,0,1,1,1], "reward_cm": NaN}',
    row(DESIGNS[1], reward_cm=1e999),  # json reads it as inf
    row(DESIGNS[1], reward_cm=-1e999),
    row(DESIGNS[1], reward_cm=10**401),  # no float holds it
    row(DESIGNS[1], design=[9, 9, 9, 9, 9, 9, 9, 9], reward_cm=1000.0),
    row(DESIGNS[1], design=[1, 2], reward_cm=1000.0),
    row(DESIGNS[1], design=[2, 0, 0, 1, 1, 0, 0, 0], reward_cm=1000.0),  # not canonical
])
def test_6_regret_ranks_only_valid_rows_and_writes_no_nan(bad, tmp_path, monkeypatch, capsys):
    gt = make_folder(tmp_path / "gt")
    with open(gt / "results.jsonl", "a") as f:
        f.write(bad + "\n")
    chosen = sorted(DESIGNS, key=reward)[2]
    assert _regret_cli(monkeypatch, gt, chosen, "--json", str(tmp_path / "r.json")) == 0
    out, err = capsys.readouterr()
    assert "line 6" in err and "3 of 5" in out and "no reward (diverged)" in out
    r = loads_json((tmp_path / "r.json").read_text())  # refuses NaN and Infinity
    assert r["placement"]["best_design"] == list(BEST) and r["policy"]["reward_cm"] is None
    summary = write_outputs(gt)
    assert summary["designs"] == 5 and summary["reward_cm"]["max"] == reward(BEST)
    loads_json((gt / "summary.json").read_text())


# -- 7: malformed files are one line naming the file, the line and the design ------------------------
@pytest.mark.parametrize("change, words", [
    ({"reward_cm": "12"}, ["reward_cm", "'12'"]),
    ({"gait": {"patterns": [[1000.0], [0.0], [0.0]]}}, ["gait", "kPa", "1000"]),
    ({"evaluations": -3}, ["evaluations"]),
    ({"gait": {"patterns": [[10**400], [0.0], [0.0]], "hold": 10**400}}, ["gait"]),
    ({"per_cycle": {"x": 1.0}}, ["per_cycle"]),
])
def test_7_a_malformed_row_names_file_line_and_design_and_resume_goes_on(change, words, tmp_path, capsys):
    gt = killed_folder(tmp_path / "gt", DESIGNS[:3], done=2)
    with open(gt / "results.jsonl", "a") as f:
        f.write(row(DESIGNS[2], **change) + "\n")
    good, bad = read_results(gt)
    assert set(good) == set(DESIGNS[:2]) and len(bad) == 1
    for w in [f"{gt / 'results.jsonl'}, line 3", ",".join(map(str, DESIGNS[2])), *words]:
        assert w in bad[0]
    calls = []
    run_groundtruth(DESIGNS[:3], gt, None, executor="serial", progress=False, refs=False,
                    task=lambda d, c: calls.append(d) or fake_task(d, c))
    assert calls == [DESIGNS[2]] and set(read_results(gt)[0]) == set(DESIGNS[:3])


def test_7_the_cli_resume_names_bad_rows_and_recomputes_their_designs(tmp_path, capsys):
    gt = killed_folder(tmp_path / "gt", DESIGNS[:3], done=2)
    with open(gt / "results.jsonl", "a") as f:
        f.write(row(DESIGNS[2], reward_cm="12") + "\n")
    designs = ";".join(",".join(map(str, d)) for d in DESIGNS[:3])
    assert cli_main(["groundtruth", "--out", str(gt), "--resume", "--designs", designs, "--no-progress",
                     "--executor", "serial"]) == 0
    out, err = capsys.readouterr()
    assert f"{gt / 'results.jsonl'}, line 3" in err and "1 bad rows" in out and "3 of 3 designs done" in out
    assert len((gt / "results.jsonl").read_text().splitlines()) == 4


@pytest.mark.parametrize("config", ["{}", "[]", '{"config": []}', '{"config": {"duration": "20"}}',
                                    '{"config": {"baseline_phases": [1e400]}}',
                                    '{"config": {"duration": 1' + "0" * 400 + "}}", "[" * 5000 + "]" * 5000])
def test_7_13_malformed_config_is_one_line_in_regret_and_resume(config, tmp_path, monkeypatch, capsys):
    gt = make_folder(tmp_path / "gt")
    (gt / "config.json").write_text(config)
    assert _regret_cli(monkeypatch, gt, BEST) == 2
    _one_line_error(capsys, "config.json")
    assert cli_main(["groundtruth", "--out", str(gt), "--resume", *GT_CLI]) == 2
    _one_line_error(capsys, "config.json")


def test_13_a_deeply_nested_row_is_a_bad_row(tmp_path, monkeypatch, capsys):
    gt = make_folder(tmp_path / "gt")
    with open(gt / "results.jsonl", "a") as f:
        f.write("[" * 5000 + "]" * 5000 + "\n")
    assert _regret_cli(monkeypatch, gt, BEST) == 0
    err = capsys.readouterr().err
    assert "line 6" in err and "nested" in err and len(err.splitlines()) == 1


def test_7_a_bad_references_file_is_a_note_and_recomputed(tmp_path, monkeypatch, capsys):
    gt = make_folder(tmp_path / "gt")
    for bad in ('{"paper_l1_gait": {"reward_cm": "x"}}', '{"paper_l1_gait": {"reward_cm": 1' + "0" * 400 + "}}",
                '{"expert_baseline": {"reward_cm": 1.0}}', "[]"):
        (gt / "references.json").write_text(bad)
        s = write_outputs(gt)
        assert s["references"] == {} and "references.json" in capsys.readouterr().err


# -- 8, 14, 15: every setting is bounded and checked before any work --------------------------------
@pytest.mark.parametrize("flags, words", [
    (["--baseline-phases", "nan,10"], ["--baseline-phases", "finite"]),
    (["--baseline-phases", "0:1e7:0.001"], ["--baseline-phases", "more than"]),
    (["--baseline-phases=-300:300:1e-320"], ["--baseline-phases", "more than"]),
    (["--baseline-phases", "0,400"], ["baseline_phases"]),
    (["--dt", "1e308"], ["dt"]),
    (["--duration", "1e9"], ["duration"]),
    (["--hold", "inf"], ["hold"]),
    (["--evals-per-cycle", "100000000"], ["--evals-per-cycle", "100000"]),
    (["--disk-mesh-size", "0.01"], ["--disk-mesh-size"]),
    (["--cycles", "nan"], ["--cycles"]),
    (["--screen-duration", "nan"], ["--screen-duration"]),
])
def test_8_14_groundtruth_settings_are_refused_before_any_work(flags, words, tmp_path, capsys):
    out = tmp_path / "gt"
    assert cli_main(["groundtruth", "--out", str(out), *GT_CLI, *flags]) == 2
    _one_line_error(capsys, *words)
    assert not out.exists()


@pytest.mark.parametrize("setting, words", [
    ("env.dt=1e308", ["env.dt"]),
    ("env.randomize.mass_scale=[1e-300,1e-300]", ["env.randomize.mass_scale"]),
    ("env.randomize.control_period=[1e6,1e6]", ["env.randomize.control_period"]),
    ("sac.net_arch=[100000000]", ["sac.net_arch"]),
    ("sac.buffer_size=1e12", ["sac.buffer_size"]),
    ("n_envs=100000000", ["n_envs"]),
    ("env.steps_per_action=10000", ["episode"]),
    ("env.leg_mesh_size=0.01", ["env.leg_mesh_size"]),
    ("n_envs=" + "9" * 401, ["n_envs"]),
    ("env.disk_mesh_size=" + "9" * 401, ["env.disk_mesh_size"]),
    ("env.leg_collision_spacing=" + "9" * 401, ["env.leg_collision_spacing"]),
    ("env.settle_speed=" + "9" * 401, ["env.settle_speed"]),
    ("env.refactor_every=" + "9" * 401, ["env.refactor_every"]),
    ("env=null", ["env is a section"]),
    ("seed=-1", ["seed"]),
    ("design.t1_fraction=1e300", ["design.t1_fraction"]),
])
def test_8_14_15_train_settings_are_refused_before_training(setting, words, tmp_path, capsys):
    out = tmp_path / "run"
    assert cli_main(["train", "--preset", "smoke", "--out", str(out), "--set", setting]) == 2
    _one_line_error(capsys, *words)
    assert not out.exists()


def test_14_randomize_null_is_off_and_evaluation_ranges_are_bounded():
    from softcrawl.codesign.randomization import evaluate_randomized
    from softcrawl.robot.domain import DomainRanges

    rig = override(preset("smoke"), ["env.randomize=rig"])
    assert override(rig, ["env.randomize=null"]).env.randomize == DomainRanges()
    with pytest.raises(ValueError, match="env.randomize.mass_scale"):
        evaluate_randomized("no-run", (1, 0, 0, 2, 2, 0, 0, 0), 2, DomainRanges(mass_scale=(1e-300, 1e-300)))


@pytest.mark.parametrize("flags, words", [(["--episodes", "100000"], ["--episodes"]),
                                          (["--randomize", "100000"], ["--randomize"]),
                                          (["--randomize", "2", "--seed", "-1"], ["--seed"])])
def test_15_evaluate_episodes_and_seed_are_bounded(flags, words, tmp_path, capsys):
    out = tmp_path / "out"
    assert cli_main(["evaluate", str(tmp_path / "run"), "--design", "1,0,0,2,2,0,0,0", "--out", str(out),
                     *flags]) == 2
    _one_line_error(capsys, *words)
    assert not out.exists()


def test_14_report_phases_are_bounded(tmp_path, capsys):
    assert cli_main(["report", str(tmp_path / "run"), "--phases", "0:1e7:0.001", "--no-simulate"]) == 2
    _one_line_error(capsys, "more than")


# -- 16: a Ray address that does not answer ------------------------------------------------------------
def test_16_a_silent_ray_address_fails_with_one_line(tmp_path, monkeypatch, capsys):
    from softcrawl.parallel import check_address, connect_timeout

    monkeypatch.setenv("SOFTCRAWL_RAY_TIMEOUT", "1")
    assert connect_timeout() == 1.0
    with socket.socket() as s:  # a port nobody listens on: bound, not listening
        s.bind(("127.0.0.1", 0))
        silent = f"127.0.0.1:{s.getsockname()[1]}"
        with pytest.raises(ConnectionError, match="within 1 s"):
            check_address(silent, 1.0)
        out = tmp_path / "run"
        assert cli_main(["train", "--preset", "smoke", "--out", str(out), "--set", 'backend="ray"',
                         "--ray-address", silent]) == 2
        _one_line_error(capsys, "no Ray cluster answers", silent)
        assert not out.exists()
        assert cli_main(["groundtruth", "--out", str(out), *GT_CLI[:-2], "--executor", "ray",
                         "--ray-address", f"ray://{silent}"]) == 2
        _one_line_error(capsys, "no Ray cluster answers")
        assert not out.exists()
        ray = pytest.importorskip("ray")
        if not ray.is_initialized():  # where the backends connect
            from softcrawl.parallel import ensure_ray

            with pytest.raises(ConnectionError, match="no Ray cluster answers"):
                ensure_ray(silent)
            assert not ray.is_initialized()
    with socket.socket() as s:  # a head that answers passes
        s.bind(("127.0.0.1", 0))
        s.listen()
        check_address(f"127.0.0.1:{s.getsockname()[1]}", 1.0)
    with pytest.raises(ValueError, match="port"):
        check_address("127.0.0.1:99999", 1.0)
    monkeypatch.setenv("SOFTCRAWL_RAY_TIMEOUT", "-5")
    with pytest.raises(ValueError, match="SOFTCRAWL_RAY_TIMEOUT"):
        connect_timeout()


# -- 18: one run per folder ---------------------------------------------------------------------------
def test_18_a_second_run_on_a_folder_being_written_stops_at_once(tmp_path, capsys):
    gt = tmp_path / "gt"
    seen = []

    def task(d, c):  # while the first run computes its first design, a second one starts
        if not seen:
            seen.append(cli_main(["groundtruth", "--out", str(gt), "--resume", *GT_CLI]))
            seen.append(capsys.readouterr().err)
        return fake_task(d, c)

    make_folder(gt, DESIGNS[:2], task)
    assert seen[0] == 2 and f"process {os.getpid()} on {socket.gethostname()}" in seen[1]
    assert "another softcrawl command" in seen[1] and "\n" not in seen[1].strip()
    assert len((gt / "results.jsonl").read_text().splitlines()) == 2  # nothing done twice
    with folder_lock(gt), pytest.raises(FolderLockedError):
        make_folder(gt, DESIGNS[:3])
    make_folder(gt, DESIGNS[:3])  # released: the next run goes on
    assert not (gt / LOCK).exists() and len(load_groundtruth(gt)[1]) == 3  # the lock file goes with its run


def test_18_a_run_in_another_process_holds_the_folder(tmp_path, capsys):
    import subprocess
    import sys

    gt = make_folder(tmp_path / "gt", DESIGNS[:1])
    holder = subprocess.Popen([sys.executable, "-c", (
        "import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR | os.O_CREAT)\n"
        "fcntl.flock(fd, fcntl.LOCK_EX)\n"
        "os.write(fd, f'{os.getpid()}\\n'.encode())\n"
        "print('locked', flush=True)\n"
        "time.sleep(120)\n"), str(gt / LOCK)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        assert cli_main(["groundtruth", "--out", str(gt), "--resume", *GT_CLI]) == 2
        _one_line_error(capsys, f"process {holder.pid}", "another softcrawl command")
    finally:
        holder.kill()
        holder.wait()
    assert len((gt / "results.jsonl").read_text().splitlines()) == 1
    with folder_lock(gt):  # the holder is gone: the lock is free again
        pass


# -- issue 49, defect 6: a folder records its design set and --resume continues exactly it -----------
def test_resume_continues_exactly_the_folders_design_set(tmp_path, capsys):
    """The probe: resuming a 2-design folder computed 38 of the 280 default designs into it."""
    gt = tmp_path / "gt"
    two = ";".join(",".join(map(str, d)) for d in DESIGNS[:2])
    assert cli_main(["groundtruth", "--out", str(gt), "--designs", two, "--no-progress", "--executor", "serial"]) == 0
    assert json.loads((gt / "config.json").read_text())["designs"] == two
    rows = (gt / "results.jsonl").read_text().splitlines(keepends=True)
    (gt / "results.jsonl").write_text(rows[0])  # killed after its first design
    capsys.readouterr()
    assert cli_main(["groundtruth", "--out", str(gt), "--resume", "--no-progress", "--executor", "serial"]) == 0
    assert "2 of 2 designs done" in capsys.readouterr().out
    assert set(read_results(gt)[0]) == set(DESIGNS[:2]) and len((gt / "results.jsonl").read_text().splitlines()) == 2
    for other in ("3", ";".join(",".join(map(str, d)) for d in DESIGNS[:3])):
        assert cli_main(["groundtruth", "--out", str(gt), "--resume", "--designs", other, "--no-progress"]) == 2
        _one_line_error(capsys, "--resume continues exactly them", "drop --designs")
    assert cli_main(["groundtruth", "--out", str(gt), "--resume", "--designs", two, "--no-progress",
                     "--executor", "serial"]) == 0  # the same set, written otherwise, is the folder's
    assert cli_main(["groundtruth", "--out", str(gt), "--resume", "--duration", "10"]) == 2
    _one_line_error(capsys, "saved settings", "drop --duration")
    assert len((gt / "results.jsonl").read_text().splitlines()) == 2


def test_a_folders_set_is_recorded_compactly_and_a_legacy_folder_needs_its_designs(tmp_path):
    from softcrawl.codesign.groundtruth import design_set_spec, parse_designs, recorded_designs

    for spec in ("3", "3,4", "all", "1,0,0,2,2,0,0,0;1,0,0,2,2,0,0,1"):
        assert design_set_spec(parse_designs(spec)) == spec
    gt = make_folder(tmp_path / "gt", DESIGNS[:2])
    assert recorded_designs(gt) == list(DESIGNS[:2])
    doc = json.loads((gt / "config.json").read_text())
    del doc["designs"]  # written before ground truths recorded their set
    (gt / "config.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match="records no design set"):
        run_groundtruth(None, gt, None, executor="serial", progress=False, refs=False, task=fake_task)
    run_groundtruth(DESIGNS[:2], gt, None, executor="serial", progress=False, refs=False, task=fake_task)


# -- issue 49, defect 10: a refused command writes nothing, so the corrected one is accepted ----------
def test_a_bad_reduction_is_refused_before_the_folder_is_written(tmp_path, capsys):
    """The probe: a refused ``groundtruth`` (wrong ``reduction_sha256``) had written config.json
    and space.toml, and the corrected command was refused as "other settings"."""
    from softcrawl.design.resolve import resolve_space

    paper = Path(resolve_space("paper").source).read_text()
    sha = resolve_space("paper").reduction_sha256
    space, gt = tmp_path / "mine.toml", tmp_path / "gt"
    space.write_text(paper.replace(sha, "0" * 64))
    assert cli_main(["groundtruth", "--out", str(gt), "--space", str(space), *GT_CLI]) == 2
    _one_line_error(capsys, "SHA-256")
    assert not gt.exists()
    space.write_text(paper)  # corrected
    assert cli_main(["groundtruth", "--out", str(gt), "--space", str(space), *GT_CLI]) == 0
    assert len(read_results(gt)[0]) == 1
