"""The co-design pipeline on a design space given as a file: ``train --space``, the
run's own ``space.toml`` and its checksum, resume, evaluate, report, a tampered or malformed
space file, older runs read as the paper's space, deploy's regulator count.

The space of these tests is the paper's PneuNet (so the shipped reduction fits) on another slot
layout: 6 slots at 30 + 60 i degrees, 3 regulators, exactly 3 legs, mirror symmetry about x. Its
file ``hex3.toml`` gives no ``name`` (the space is ``hex3``) and names its reduction by a path
relative to its folder (``red/leg.npz``, a copy of the shipped one), as the docs allow: the run
and the ground truth keep the same space, name and reduction.
"""

import hashlib
import json
import math
import shutil
from pathlib import Path

import pytest

from softcrawl.codesign.config import override, preset
from softcrawl.codesign.run import Run
from softcrawl.design import DEFAULT_SPACE, shipped_space_path
from softcrawl.design.resolve import resolve_space

PAPER_TOML = shipped_space_path("paper").read_text(encoding="utf-8")


def hex3_text() -> str:
    """The paper's space file with 6 slots at 30 + 60 i deg, 3 legs, mirror_x."""
    text = PAPER_TOML.replace('name = "paper"', 'name = "hex3"').replace("count = 8", "count = 6")
    text = text.replace("first_angle_deg = 22.5", "first_angle_deg = 30.0")
    text = text.replace("max_legs = 6", "max_legs = 3").replace("mirror_x = false", "mirror_x = true")
    assert text.count("count = 6") == 1 and "max_legs = 3" in text and "mirror_x = true" in text
    return text


def unnamed_text() -> str:
    """:func:`hex3_text` without its name, naming its reduction ``red/leg.npz``."""
    return hex3_text().replace('name = "hex3"\n', "").replace('"softcrawl:pneunet_6mm.npz"', '"red/leg.npz"')


@pytest.fixture(scope="module")
def space_file(tmp_path_factory) -> Path:
    from softcrawl.reduction.data import default_reduction_path

    path = tmp_path_factory.mktemp("space") / "hex3.toml"
    path.write_text(unnamed_text(), encoding="utf-8")
    (path.parent / "red").mkdir()
    shutil.copy(default_reduction_path(), path.parent / "red" / "leg.npz")
    return path


@pytest.fixture(scope="module")
def hex3_run(space_file, tmp_path_factory) -> Path:
    """A smoke run of 80 transitions on the hex3 space, checkpoints at 40 and 80 kept."""
    from softcrawl.codesign.training import train

    run = tmp_path_factory.mktemp("hex3") / "run"
    cfg = override(preset("smoke"), [f"env.space={json.dumps(str(space_file))}", "total_steps=80",
                                     "checkpoint_every=40", "keep_checkpoints=4"])
    train(run, cfg, progress=False)
    return run


def test_the_space_sets_the_designs_the_encoding_and_the_leg_bounds(space_file):
    cfg = override(preset("smoke"), [f"env.space={json.dumps(str(space_file))}"])
    space = cfg.env.design_space()
    assert (space.n_slots, space.n_regulators, space.one_hot_size) == (6, 3, 24)
    # 3 legs in 6 slots: C(6,3) slot sets; regulator labellings by first appearance: 1 + 3 + 1 = 5
    # (one, two or three regulators: S(3,1) + S(3,2) + S(3,3)); mirror pairs identified on top.
    raw_canonical = math.comb(6, 3) * 5
    designs = cfg.env.designs()
    assert raw_canonical / 2 <= len(designs) < raw_canonical
    assert all(len(d) == 6 and sum(v > 0 for v in d) == 3 and space.canonicalize(d) == d for d in designs)
    for bad in ("env.legs=[2]", "env.legs=[4]"):
        with pytest.raises(ValueError, match=r"env.legs must be a non-empty subset of 3..3"):
            override(cfg, [bad])
    # the default is the paper's space, its designs and its robot settings, untouched
    default = preset("smoke")
    assert default.env.space == "paper" and default.env.design_space() is DEFAULT_SPACE
    assert default.env.robot_config() is default.env.robot and len(preset("demo").env.designs()) == 280
    assert resolve_space("hex6") == resolve_space(shipped_space_path("hex6")) and resolve_space("paper") is DEFAULT_SPACE
    assert resolve_space(shipped_space_path("paper")) is DEFAULT_SPACE  # the paper's file, by path: the same space


def test_robot_settings_of_another_space_take_its_part_values(tmp_path):
    """Part settings still at the paper's defaults take the space's (hex6: 0.08 kg legs); a
    preset's own value (the 25 mm disk) and every other setting stay the config's."""
    cfg = override(preset("smoke"), ["env.space=hex6"])
    robot = cfg.env.robot_config()
    assert robot.leg_mass == pytest.approx(0.08, abs=0) and robot.disk_mesh_size == 25
    assert (robot.dt, robot.model) == (cfg.env.robot.dt, cfg.env.robot.model)


def test_a_run_keeps_its_space_file_and_reads_it_back(hex3_run, space_file, tmp_path):
    run = Run(hex3_run)
    data = b'name = "hex3"\n' + space_file.read_bytes()  # the copy records the space's name
    assert run.space_path.read_bytes() == data
    assert (hex3_run / "red" / "leg.npz").read_bytes() == (space_file.parent / "red" / "leg.npz").read_bytes()
    meta = json.loads(run.config_path.read_text())
    assert meta["space_sha256"] == hashlib.sha256(data).hexdigest()
    assert meta["config"]["env"]["space"] == str(space_file)
    assert run.read_config().env.space == str(run.space_path)
    space = run.design_space()
    assert space == resolve_space(space_file) and space.n_slots == 6 and space.name == "hex3"
    assert space.reduction == str(hex3_run / "red" / "leg.npz")
    rows = run.read_episodes()
    assert len(rows["design"]) == 4 and all(space.canonicalize(d) == d and len(d) == 6 for d in rows["design"])
    # the run does not change when the file it was started from does
    moved = tmp_path / "hex3.toml"
    shutil.copy(space_file, moved)
    moved.write_text(hex3_text().replace("max_legs = 3", "max_legs = 4"), encoding="utf-8")
    assert Run(hex3_run).design_space() == space


def test_resume_on_the_runs_space_gives_the_same_episodes(hex3_run, tmp_path):
    from softcrawl.codesign.training import train

    copy = tmp_path / "run"
    shutil.copytree(hex3_run, copy)
    shutil.rmtree(copy / "checkpoints" / "step-0000000080")
    (copy / "checkpoints" / "latest").write_text("step-0000000040")
    train(copy, resume=True, progress=False)
    assert (copy / "episodes.csv").read_text() == (hex3_run / "episodes.csv").read_text()


def test_evaluate_and_report_use_the_runs_space(hex3_run, tmp_path, monkeypatch):
    import softcrawl.codesign.report as report
    from softcrawl.codesign.evaluation import evaluate_policy

    copy = tmp_path / "run"
    shutil.copytree(hex3_run, copy)
    space = Run(copy).design_space()
    mirrored = (3, 0, 0, 0, 1, 2)  # relabelled and mirrored (slot i <-> 5 - i): (1, 0, 0, 0, 2, 3)
    ev = evaluate_policy(copy, mirrored)
    assert ev.design == (1, 0, 0, 0, 2, 3) and ev.actions_kpa.shape == (20, 3)
    assert ev.env.observation_space.shape[0] == space.one_hot_size + 4 * 3
    drawn = []
    original = report.plot_design
    monkeypatch.setattr(report, "plot_design", lambda d, **kw: drawn.append((d, kw["space"])) or original(d, **kw))
    out = report.write_report(copy, k=2)
    summary = json.loads((out / "summary.json").read_text())
    assert summary["space"]["slots"] == 6 and summary["space"]["regulators"] == 3
    # the expert baseline runs on the space's own four legs in an X, with the run's settings
    from softcrawl.design.baseline import sine_baseline_design

    sweep = json.loads((out / "baseline_sweep" / "sweep.json").read_text())
    assert tuple(sweep["settings"]["design"]) == sine_baseline_design(space) and len(sweep["phases"]) == 12
    assert summary["baseline"]["best_phase_deg"] == sweep["best"]["phase_deg"]
    assert (out / "baseline_best" / "trajectory.png").exists()
    assert drawn and all(s == space and len(d) == 6 for d, s in drawn)
    assert (out / "top-1.png").stat().st_size > 0 and (out / "best_design" / "trajectory.png").exists()
    assert "design space `hex3`" in (out / "summary.md").read_text()


def test_a_tampered_space_file_is_refused(hex3_run, tmp_path):
    from softcrawl.codesign.evaluation import evaluate_policy
    from softcrawl.codesign.report import write_report

    copy = tmp_path / "run"
    shutil.copytree(hex3_run, copy)
    (copy / "space.toml").write_text(unnamed_text().replace("max_legs = 3", "max_legs = 4"), encoding="utf-8")
    for call in (lambda: Run(copy).read_config(), lambda: evaluate_policy(copy, (1, 1, 1, 0, 0, 0)),
                 lambda: write_report(copy, simulate=False)):
        with pytest.raises(ValueError, match=r"space.toml: sha256 .* \(the design space was changed after") as exc:
            call()
        assert "\n" not in str(exc.value)
    assert not (copy / "report").exists()
    (copy / "space.toml").unlink()
    with pytest.raises(ValueError, match="space.toml: the folder's design space cannot be read"):
        Run(copy).read_config()


def test_a_malformed_space_file_gives_one_line_and_writes_nothing(tmp_path, capsys):
    from softcrawl.cli import main

    bad = tmp_path / "bad.toml"
    bad.write_text(hex3_text().replace("max_legs = 3", "max_legs = 7"), encoding="utf-8")
    for space, why in ((str(bad), "design.max_legs: 7 is more than the 6 slots"),
                       ("nope", "no shipped design space 'nope'"),
                       (str(tmp_path / "none.toml"), "no such design-space file")):
        out = tmp_path / "out"
        for command in (["train", "--preset", "smoke", "--out", str(out), "--no-progress"],
                        ["groundtruth", "--designs", "3", "--out", str(out), "--no-progress"], ["designs", "count"]):
            assert main([*command, "--space", space]) != 0
            err = capsys.readouterr().err.strip()
            assert why in err and len(err.splitlines()) == 1, (command, err)
            assert not out.exists()


def test_older_runs_are_the_paper_space(tmp_path):
    from softcrawl.codesign.config import TrainConfig
    from softcrawl.codesign.migrate import CONFIG_VERSION, read_settings

    doc = json.loads((Path(__file__).parent / "data" / "run_config_v1.json").read_text())
    assert read_settings("train", doc)["env"]["space"] == "paper"
    cfg = TrainConfig.from_dict(read_settings("train", doc))
    v3 = {"config_version": 3, "config": {**cfg.to_dict(), "env": {k: v for k, v in cfg.to_dict()["env"].items()
                                                                     if k != "space"}}}
    assert CONFIG_VERSION >= 4 and read_settings("train", v3)["env"]["space"] == "paper"
    run = tmp_path / "old"
    run.mkdir()
    (run / "config.json").write_text(json.dumps({"version": "0.2.0", **v3}))
    assert Run(run).read_config() == cfg and Run(run).design_space() is DEFAULT_SPACE  # no space.toml needed
    assert read_settings("groundtruth", {"config_version": 3, "config": {"seed": 1}})["space"] == "paper"


def test_deploy_refuses_a_run_of_another_regulator_count(tmp_path, capsys):
    """A run on hex6 (2 regulators) against the 3-regulator example rig: refused before the
    policy is rolled out (the run needs no checkpoint to be refused), nothing written."""
    from softcrawl.cli import main
    from softcrawl.hardware.deploy import check_regulators

    run = Run(tmp_path / "run")
    run.write_config(override(preset("smoke"), ["env.space=hex6", 'env.robot.model="full"']))
    out = tmp_path / "deploy"
    assert main(["deploy", "--rig", "sim", "--run", str(run.path), "--design", "1,0,0,2,0,0", "--out", str(out),
                 "--no-progress"]) != 0
    err = capsys.readouterr().err.strip()
    assert "drives 2 regulators but the rig config has 3" in err and len(err.splitlines()) == 1
    assert not out.exists()
    check_regulators(3, 3, "paper")
    with pytest.raises(ValueError, match="drives 2 regulators"):
        check_regulators(2, 3, "hex6")


def test_a_ground_truth_of_the_space_keeps_it_and_regret_compares_like_with_like(hex3_run, space_file, tmp_path):
    """``groundtruth --space``'s folder (a fake task: no simulation): its space.toml and
    checksum, its rows validated in its own space, no paper references, resumed with its own
    settings; regret of the hex3 run against it, and refused against a paper ground truth."""
    from groundtruth_helpers import fake_task, make_folder

    from softcrawl.codesign.groundtruth import GroundTruthConfig, load_groundtruth, parse_designs, run_groundtruth
    from softcrawl.codesign.groundtruth.store import read_config
    from softcrawl.codesign.groundtruth_regret import compute_regret

    space = resolve_space(space_file)
    designs = parse_designs("3", space)
    assert designs == [d for d in space.canonical_designs]
    with pytest.raises(ValueError, match=r"leg counts must be in 3..3"):
        parse_designs("4", space)
    gt = tmp_path / "gt"
    cfg = GroundTruthConfig(baseline_phases=(), space=str(space_file))
    run_groundtruth(designs, gt, cfg, executor="serial", task=fake_task, progress=False)
    meta = json.loads((gt / "config.json").read_text())
    copy = b'name = "hex3"\n' + space_file.read_bytes()
    assert (gt / "space.toml").read_bytes() == copy and (gt / "red" / "leg.npz").is_file()
    assert meta["space_sha256"] == hashlib.sha256(copy).hexdigest()
    assert not (gt / "references.json").exists()
    saved, results, _ = load_groundtruth(gt)
    assert saved.design_space() == space and set(results) == set(designs)
    run_groundtruth(designs, gt, cfg, executor="serial", task=fake_task, progress=False)  # same settings: resumes
    r = compute_regret(hex3_run, gt, policy=False)
    assert r["placement"]["of"] == len(designs) and len(r["choice"]["design"]) == 6
    paper_gt = make_folder(tmp_path / "paper_gt")
    with pytest.raises(ValueError, match=r"\(design space 'hex3'\) and the ground truth .* \(design space 'paper'\) "
                                         "are of different design spaces"):
        compute_regret(hex3_run, paper_gt, policy=False)
    (gt / "space.toml").write_text(unnamed_text() + "# changed\n", encoding="utf-8")
    with pytest.raises(ValueError, match=r"space.toml: sha256 .* \(the design space was changed after"):
        read_config(gt)


def test_a_space_copy_takes_its_relative_reduction_along(tmp_path):
    """A space naming its reduction by a relative path: the folder's copy reads the same
    reduction (copied below the folder, byte for byte) and is the same space; a path out of the
    space's folder is refused; a reduction changed after the space was read is refused before
    anything is written."""
    from softcrawl.design.resolve import write_space_copy
    from softcrawl.design.spacefile import SpaceFileError
    from softcrawl.reduction.data import default_reduction_path

    src = tmp_path / "mine"
    (src / "red").mkdir(parents=True)
    shutil.copy(default_reduction_path(), src / "red" / "leg.npz")
    (src / "s.toml").write_text(hex3_text().replace('"softcrawl:pneunet_6mm.npz"', '"red/leg.npz"'), encoding="utf-8")
    folder = tmp_path / "run"
    folder.mkdir()
    sha = write_space_copy(folder, src / "s.toml")
    assert sha == hashlib.sha256((src / "s.toml").read_bytes()).hexdigest()  # a named file: copied as it is
    copy, original = resolve_space(folder / "space.toml"), resolve_space(src / "s.toml")
    assert copy.reduction == str(folder / "red" / "leg.npz") and copy == original
    assert (folder / "red" / "leg.npz").read_bytes() == default_reduction_path().read_bytes()
    (src / "red" / "leg.npz").write_bytes(b"PK\x03\x04 another reduction")  # after the space was read
    other = tmp_path / "other"
    other.mkdir()
    with pytest.raises(SpaceFileError, match=r"leg\.npz: the reduction file changed while it was read"):
        write_space_copy(other, src / "s.toml")
    assert list(other.iterdir()) == []
    (tmp_path / "up.npz").write_bytes(b"PK\x03\x04")
    (src / "t.toml").write_text(hex3_text().replace('"softcrawl:pneunet_6mm.npz"', '"../up.npz"'), encoding="utf-8")
    with pytest.raises(SpaceFileError, match="leaves the space file's folder"):
        write_space_copy(other, src / "t.toml")
    with pytest.raises(ValueError, match="env.space: .*t.toml: actuator.reduction: '../up.npz' leaves"):
        override(preset("smoke"), [f"env.space={json.dumps(str(src / 't.toml'))}"])  # refused before any run
    assert list(other.iterdir()) == []


def test_a_space_file_without_a_name_keeps_it_in_a_runs_copy(tmp_path):
    """The copy of a file without ``name`` records the file's name (it would be ``space``, the
    copy's), so that the run's space is the file's; a byte-order mark is dropped with it."""
    from softcrawl.design.resolve import write_space_copy

    path = tmp_path / "crab.toml"
    path.write_bytes(b"\xef\xbb\xbf" + hex3_text().replace('name = "hex3"\n', "").encode())
    run = Run(tmp_path / "run")
    cfg = override(preset("smoke"), [f"env.space={json.dumps(str(path))}"])
    run.write_config(cfg)
    assert run.space_path.read_text(encoding="utf-8").startswith('name = "crab"\n# The paper')
    assert run.design_space() == cfg.env.design_space() and run.design_space().name == "crab"
    assert write_space_copy(tmp_path, run.space_path) == json.loads(run.config_path.read_text())["space_sha256"]
