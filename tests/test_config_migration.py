"""Composed configs and the versioned migration of saved settings: a run folder and a ground
truth written by the code before the robot's settings became one ``RobotConfig`` (format 1,
``tests/data/*_v1.json``, copied from such folders) read back as the same simulation; the
``--set env.FIELD`` keys users type keep working."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import pytest

from softcrawl.cli import main as cli_main
from softcrawl.codesign.config import EnvConfig, TrainConfig, env_robot, override, preset
from softcrawl.codesign.factory import robot_factory
from softcrawl.codesign.groundtruth import GroundTruthConfig, gt_robot, read_config
from softcrawl.codesign.migrate import CONFIG_VERSION, config_version, migrate, read_settings
from softcrawl.codesign.run import Run
from softcrawl.robot.assembly import RobotConfig

DATA = Path(__file__).parent / "data"


def test_a_format_1_run_reads_back_as_the_preset_it_was_trained_with(tmp_path):
    """``run_config_v1.json``: the config.json of ``softcrawl train --preset smoke --seed 0``
    written by the format-1 code; its robot is the one that code's factory built, its learner
    the torch one (the only learner of formats 1 and 2)."""
    shutil.copy(DATA / "run_config_v1.json", tmp_path / "config.json")
    cfg = Run(tmp_path).read_config()
    assert cfg.sac.learner == "torch" and preset("smoke").sac.learner == "sbx"
    assert cfg == override(preset("smoke"), ['sac.learner="torch"', 'rollout="action"', "shortlist=1", 'jax_solver="pgs"',
                                               "jax_iterations=100"])
    assert robot_factory(cfg).config == RobotConfig(
        leg_mesh_size=6.0, disk_mesh_size=25, refactor_every=None, rid_dtype="float32", dt=0.01, model="reduced",
        reduction=None, contact_max_iterations=100, leg_collision_spacing=0.0)


def test_a_run_is_written_in_the_current_format_and_read_back(tmp_path):
    cfg = override(preset("smoke"), ["env.robot.friction=0.9"])
    Run(tmp_path).write_config(cfg)
    doc = json.loads((tmp_path / "config.json").read_text())
    assert doc["config_version"] == CONFIG_VERSION and doc["config"]["env"]["robot"]["friction"] == 0.9
    assert "dt" not in doc["config"]["env"]  # held once, in env.robot
    own_space = dataclasses.replace(cfg.env, space=str(tmp_path / "space.toml"))  # the run reads its own copy
    assert Run(tmp_path).read_config() == dataclasses.replace(cfg, env=own_space)


def test_a_format_2_run_reads_back_with_the_torch_learner(tmp_path):
    doc = {"config_version": 2, "config": preset("smoke").to_dict()}
    del doc["config"]["sac"]["learner"]
    (tmp_path / "config.json").write_text(json.dumps(doc))
    assert Run(tmp_path).read_config().sac.learner == "torch"


def test_a_format_1_ground_truth_reads_back_with_its_robot(tmp_path):
    """``groundtruth_config_v1.json``: the config.json of the three-legged ground truth shipped
    before the duty search (structured seeds)."""
    shutil.copy(DATA / "groundtruth_config_v1.json", tmp_path / "config.json")
    cfg = read_config(tmp_path)
    assert cfg.robot == RobotConfig(model="reduced", leg_mesh_size=6.0, disk_mesh_size=25.0, dt=0.02,
                                    reduction=None, rid_dtype="float32")
    assert (cfg.cycles, cfg.evals_per_cycle, cfg.screen_duration) == ((2, 3, 4), 30, 6.0)
    assert cfg.seeds == "structured" and GroundTruthConfig().seeds == "duty"  # format 9's seeds: older searched those
    old = json.loads((DATA / "groundtruth_config_v1.json").read_text())["config"]
    del old["rid_dtype"]  # written before the setting: computed in float64
    old["dt"] = None  # the robot's default step
    robot = GroundTruthConfig.from_dict(migrate("groundtruth", old, 1)).robot
    assert (robot.rid_dtype, robot.dt) == ("float64", RobotConfig().dt)


def test_an_unknown_format_is_one_clear_error(tmp_path):
    for v in (CONFIG_VERSION + 1, 0, "2", True):
        with pytest.raises(ValueError, match="config_version"):
            config_version({"config_version": v})
        (tmp_path / "config.json").write_text(json.dumps({"config_version": v, "config": preset("smoke").to_dict()}))
        with pytest.raises(ValueError) as err:
            Run(tmp_path).read_config()
        assert str(tmp_path / "config.json") in str(err.value) and "\n" not in str(err.value)
        with pytest.raises(ValueError, match="config_version"):
            read_config(tmp_path)
    with pytest.raises(ValueError, match='no "config" object'):
        read_settings("train", {"config": 1})


def test_env_and_ground_truth_hold_a_robot_config():
    assert {f.name for f in dataclasses.fields(EnvConfig)}.isdisjoint(f.name for f in dataclasses.fields(RobotConfig))
    assert EnvConfig().robot == env_robot() == RobotConfig(model="reduced", rid_dtype="float32", dt=0.02,
                                                           contact_max_iterations=100)
    assert GroundTruthConfig().robot == gt_robot() == RobotConfig(model="reduced", rid_dtype="float32")
    assert gt_robot(dt=None, disk_mesh_size=25).dt == RobotConfig().dt
    d = preset("demo").to_dict()
    d["env"]["robot"] = {"dt": 0.01}  # missing keys: the env's default robot, not RobotConfig's
    assert TrainConfig.from_dict(d).env.robot == env_robot(dt=0.01)


def test_set_keys_of_robot_fields_keep_working():
    smoke = preset("smoke")
    for typed in ("env.dt=0.02", "env.robot.dt=0.02"):
        assert override(smoke, [typed]).env.robot.dt == 0.02
    cfg = override(smoke, ["env.leg_mesh_size=8", 'env.rid_dtype="float64"', "env.contact_max_iterations=250"])
    assert (cfg.env.robot.leg_mesh_size, cfg.env.robot.rid_dtype, cfg.env.robot.contact_max_iterations) == \
        (8, "float64", 250)
    for bad, names in ((["env.dt=0"], ("env.dt", "env.robot.dt")),
                       (["env.contact_max_iterations=0"], ("env.contact_max_iterations",)),
                       (["env.robot.model=\"tiny\""], ("env.robot.model",)),
                       (["env.nope=1"], ("env.nope",))):
        with pytest.raises(ValueError) as err:
            override(smoke, bad)
        assert all(n in str(err.value) for n in names), str(err.value)


def test_train_cli_takes_the_old_key(tmp_path, capsys):
    assert cli_main(["train", "--preset", "smoke", "--out", str(tmp_path / "r"), "--set", "env.dt=1e308"]) == 2
    err = capsys.readouterr().err
    assert "env.dt (env.robot.dt)" in err and err.count("error:") == 1


def test_a_turning_task_saved_before_venting_reads_as_unvented():
    """Version 5: runs and ground truths of older formats scored a turn while the pressure held
    (``vent_s = 0``); a newer folder's setting, and every other task, stay as saved."""
    from softcrawl.tasks import parse_task

    cfg = preset("smoke").to_dict()
    for saved, expected in (("turning", 0.0), ({"name": "turning", "friction": 0.8}, 0.0)):
        doc = {"config_version": 4, "config": {**cfg, "env": {**cfg["env"], "task": saved}}}
        task = parse_task(read_settings("train", doc)["env"]["task"])
        assert task.vent_s == expected and task.friction == (None if saved == "turning" else 0.8)
        assert parse_task(read_settings("groundtruth", {"config_version": 4, "config": {"task": saved}})["task"]).vent_s == 0
    new = {"config_version": CONFIG_VERSION, "config": {**cfg, "env": {**cfg["env"], "task": "turning"}}}
    assert parse_task(read_settings("train", new)["env"]["task"]).vent_s == 5.0
    old_forward = {"config_version": 4, "config": {**cfg, "env": {**cfg["env"], "task": "forward"}}}
    assert read_settings("train", old_forward)["env"]["task"] == "forward"


# -- issue 49, defect 7: a config.json without config_version is format 1 only if format 1 wrote it --
def test_a_later_format_without_config_version_is_refused_not_guessed(tmp_path, capsys):
    """The probe: a turning run's config.json without ``config_version`` read as format 1 became
    ``vent_s = 0``; a hex6 run became the paper's space and refused its own designs."""
    turning = override(preset("smoke"), ['env.task="turning"', 'env.space="hex6"', "env.legs=[2]"]).to_dict()
    for doc, words in (({"version": "0.3.0", "config": turning}, ["env.space", "env.task", "jax_solver"]),
                       ({"config": {"duration": 20.0, "task": "turning", "space": "hex6"}}, ["space", "task"]),
                       ({"config": json.loads((DATA / "run_config_v1.json").read_text())["config"],
                         "space_sha256": "0" * 64}, ["space_sha256"])):
        kind = "train" if "n_envs" in doc["config"] else "groundtruth"
        with pytest.raises(ValueError, match="no config_version") as err:
            read_settings(kind, doc)
        assert all(w in str(err.value) for w in words) and "\n" not in str(err.value), str(err.value)
    (tmp_path / "config.json").write_text(json.dumps({"version": "0.3.0", "config": turning}))
    with pytest.raises(ValueError, match=f"{tmp_path / 'config.json'}: no config_version"):
        Run(tmp_path).read_config()
    assert cli_main(["train", "--resume", "--out", str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert "no config_version" in err and err.count("\n") == 1 and sorted(p.name for p in tmp_path.iterdir()) == [
        "config.json"]
    (tmp_path / "config.json").write_text(json.dumps({"config": {"duration": 20.0, "task": "turning"}}))
    with pytest.raises(ValueError, match="no config_version"):
        read_config(tmp_path)  # a ground truth's reader too
    for name, kind in (("run_config_v1.json", "train"), ("groundtruth_config_v1.json", "groundtruth")):
        read_settings(kind, json.loads((DATA / name).read_text()))  # format 1 as it was written still reads
