"""Co-design training: config, SAC learner, checkpoint / kill / resume, report (softcrawl.codesign)."""

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

from softcrawl.codesign.config import PRESETS, SACConfig, TrainConfig, override, preset
from helpers import groundtruth_of_tried, restored_learner


def test_presets_and_overrides():
    for name in PRESETS:
        cfg = preset(name)
        assert TrainConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    paper = preset("paper")
    assert (paper.n_envs, paper.total_steps, paper.sac.batch_size, paper.sac.buffer_size) == (96, 1_000_000, 512, 100_000)
    assert (paper.sac.policy_lr, paper.sac.q_lr, paper.sac.gamma, paper.sac.tau) == (6e-4, 2e-3, 0.95, 0.01)
    assert paper.sac.net_arch == (400, 200, 100) and paper.sac.learning_starts == 10_000
    assert paper.design.t0_fraction * paper.total_steps == 200_000
    assert paper.design.t1_fraction * paper.total_steps == 950_000
    assert len(paper.env.designs()) == 6972 and len(preset("demo").env.designs()) == 280
    cfg = override(paper, ["sac.batch_size=64", "env.legs=[3, 4]", 'backend="serial"', "design.untried=zero"])
    assert cfg.sac.batch_size == 64 and cfg.env.legs == (3, 4) and cfg.backend == "serial"
    assert cfg.design.untried == "zero"
    for bad in (["sac.nope=1"], ["n_envs=0"], ["env.legs=[2]"], ["backend=\"mpi\""], ["sac.timeout=\"x\""], ["n_envs"],
                ['sac.device="tpu"'], ['sac.device="gpu:x"'], ['sac.device="cuda:x"']):
        with pytest.raises(ValueError):
            override(paper, bad)
    for device in ("cpu", "gpu", "gpu:1", "cuda", "cuda:0"):  # "cuda": configs written before the JAX learner
        assert override(paper, [f'sac.device="{device}"']).sac.device == device
    with pytest.raises(ValueError):
        preset("huge")


def test_run_config_saved_before_a_setting_reads_back_with_its_reference_value():
    """A run's config.json written before ``env.rid_dtype``, ``env.contact_max_iterations`` and
    ``env.leg_collision_spacing`` existed resumes with the values it was trained with (the
    reference), not the presets' newer defaults; the factory hands them to the robots."""
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.codesign.migrate import read_settings

    saved = (Path(__file__).parent / "data" / "run_config_v1.json").read_text()  # format 1, the smoke preset
    d = json.loads(saved)
    for key in ("rid_dtype", "contact_max_iterations"):
        del d["config"]["env"][key]
    old = TrainConfig.from_dict(read_settings("train", d))
    assert (old.env.robot.rid_dtype, old.env.robot.contact_max_iterations) == ("float64", 250)
    new = preset("demo")
    assert new.env.robot.contact_max_iterations == 100 and robot_factory(new).config.contact_max_iterations == 100
    assert robot_factory(old).config.contact_max_iterations == 250
    d = json.loads(saved)
    del d["config"]["env"]["leg_collision_spacing"]
    old = TrainConfig.from_dict(read_settings("train", d))
    assert old.env.robot.leg_collision_spacing == 0.0 and robot_factory(old).config.leg_collision_spacing == 0.0
    assert robot_factory(new).config.leg_collision_spacing == new.env.robot.leg_collision_spacing
    for bad in (["env.leg_collision_spacing=-1"], ['env.leg_collision_spacing="8"']):
        with pytest.raises(ValueError, match="env.leg_collision_spacing"):
            override(new, bad)
    for bad in (["env.contact_max_iterations=0"], ["env.contact_max_iterations=2.5"]):
        with pytest.raises(ValueError, match="env.contact_max_iterations"):
            override(new, bad)
    d = preset("demo").to_dict()
    del d["sac"]["learner"]  # runs saved before sac.learner (formats 1 and 2) were the torch learner's
    assert TrainConfig.from_dict(read_settings("train", {"config_version": 2, "config": d})).sac.learner == "torch"
    assert TrainConfig().sac.learner == "sbx" and new.sac.learner == "torch"  # demo: docs/codesign.md
    with pytest.raises(ValueError, match="sac.learner must be one of"):
        override(new, ['sac.learner="tf"'])


def test_sac_learns_one_update_per_transition():
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.sac import make_sac

    venv = DummyVecEnv([lambda: gym.make("Pendulum-v1")] * 2)
    cfg = SACConfig(policy_lr=1e-3, q_lr=5e-3, learning_starts=20, batch_size=16, buffer_size=500, net_arch=(32, 16),
                    learner="sbx")
    model = make_sac(venv, cfg, seed=0)
    assert model.gradient_steps == 2  # one update per transition with 2 envs
    model.learn(60)
    assert model._n_updates == 60 - 20  # one per transition after learning_starts (2 per vectorised step)
    assert float(model.policy.qf_state.opt_state.hyperparams["learning_rate"]) == pytest.approx(5e-3)


def test_the_torch_learner_trains_checkpoints_and_evaluates(tmp_path):
    """``sac.learner="torch"``: a smoke run writes checkpoints of format 1 (``model.pt``), which
    a fresh torch learner restores (counters, replay buffer) and evaluation reads, whatever the
    config's learner says; a JAX learner refuses to read them."""
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.evaluation import evaluate_policy
    from softcrawl.codesign.run import Run
    from softcrawl.codesign.sac import make_sac
    from softcrawl.codesign.training import train

    cfg = override(preset("smoke"), ['sac.learner="torch"', 'rollout="action"', "checkpoint_every=80"])
    res = train(tmp_path / "run", cfg, progress=False)
    r = Run(tmp_path / "run")
    ck = r.latest_checkpoint()
    assert r.checkpoint_learner(ck) == "torch" and (ck / "model.pt").exists() and res.updates == 160 - 40
    model = restored_learner(tmp_path / "run")[0]
    assert model.learner == "torch" and model._n_updates == 160 - 40 and model.replay_buffer.pos == 80
    on_torch = evaluate_policy(tmp_path / "run", "1,0,0,2,2,0,0,0").returns_cm
    saved = json.loads((tmp_path / "run" / "config.json").read_text())
    saved["config"]["sac"]["learner"] = "sbx"
    (tmp_path / "run" / "config.json").write_text(json.dumps(saved))
    assert evaluate_policy(tmp_path / "run", "1,0,0,2,2,0,0,0").returns_cm == on_torch
    jax_learner = make_sac(DummyVecEnv([lambda: gym.make("Pendulum-v1")]), SACConfig(buffer_size=10, learner="sbx"))
    with pytest.raises(ValueError, match="a checkpoint of the 'torch' learner, read into the 'sbx' one"):
        r.load_learner(ck, jax_learner)


def _rows(path):
    with open(path, newline="") as f:
        return [r for r in csv.reader(f) if r]


def test_kill_and_resume(tmp_path):
    """A smoke run killed (SIGKILL) after its first checkpoint resumes, keeps counting, completes."""
    from softcrawl.cli.train import train_and_report
    from softcrawl.codesign.report import top_designs
    from softcrawl.codesign.run import latest_checkpoint

    run = tmp_path / "run"
    env = dict(os.environ, OMP_NUM_THREADS="1")
    proc = subprocess.Popen([sys.executable, "-m", "softcrawl.cli.train", "--preset", "smoke", "--out", str(run),
                             "--no-progress", "--set", "checkpoint_every=40"], env=env,
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 1800  # only a guard against a hung run: a loaded machine may take minutes
    try:
        while time.monotonic() < deadline and proc.poll() is None and latest_checkpoint(run) is None:
            time.sleep(0.2)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)
        _, err = proc.communicate()
    ck = latest_checkpoint(run)
    assert ck is not None, err.decode()[-2000:]
    killed_at = int(ck.name.split("-")[1])
    assert 40 <= killed_at < 160, "the run must be killed before it completes"
    assert not (run / "report").exists()
    res = train_and_report(run, resume=True, progress=False)
    assert res.steps == 160 and latest_checkpoint(run).name == "step-0000000160"
    ts = [int(r[0]) for r in _rows(run / "episodes.csv")]
    # 2 envs x 20-action episodes: episodes end together every 40 transitions, none lost or doubled
    assert ts == [40, 40, 80, 80, 120, 120, 160, 160]
    # SAC kept its counters: 1 update per transition after learning_starts (40) over the whole run
    assert res.updates == 160 - 40
    # ... and so does the final checkpoint (the one `report` loads): checkpoints are written after
    # the step's gradient updates (`res.updates` alone passed when the kill came
    # at step 40, before any update)
    from softcrawl.codesign.run import Run

    assert Run(run).read_checkpoint_state(latest_checkpoint(run))["n_updates"] == 160 - 40
    # truncation at the time limit is bootstrapped: stored as done with timeout, sampled as not done
    rb = restored_learner(run)[0].replay_buffer
    assert rb.dones.sum() > 0 and np.all(rb.timeouts[rb.dones > 0] == 1)
    from softcrawl.codesign.replay import gather

    assert float(gather(rb.host_arrays(), np.arange(rb.size()))["dones"].max()) == 0.0  # the device buffer's
    assert (run / "logs" / "progress-0.csv").exists()  # the killed part's SB3 log is kept
    snaps = sorted(int(p.stem.split("-")[1]) for p in (run / "snapshots").glob("t-*.npz"))
    assert snaps == [40, 80, 120, 160]
    # evaluate: the written re-run (ActionSequence through run_episode) reproduces the env's return
    from softcrawl.codesign.evaluation import evaluate_policy

    ev = evaluate_policy(run, "1,0,0,2,2,0,0,0", episodes=2)
    assert ev.actions_kpa.shape == (20, 3) and np.all((ev.actions_kpa >= 0) & (ev.actions_kpa <= 90))
    assert ev.returns_cm[0] == ev.returns_cm[1]  # deterministic policy, fresh solver per episode
    rerun = ev.resimulate(record_every=None)
    assert rerun.reward_cm == pytest.approx(ev.returns_cm[0], abs=1e-9)
    top = top_designs(run, 3)
    assert top and top[0]["latest_cm"] >= top[-1]["latest_cm"]
    report = run / "report"
    assert (report / "summary.md").exists() and (report / "reward_histogram.png").exists()
    # the end-of-training report re-simulates the best design with the policy and sweeps the baseline
    summary = (report / "summary.md").read_text()
    assert "## Best design's gait" in summary and (report / "best_design" / "trajectory.png").exists()
    best = json.loads((report / "best_design" / "summary.json").read_text())
    assert best["design"] == list(top[0]["design"])
    sweep = json.loads((report / "baseline_sweep" / "sweep.json").read_text())
    assert len(sweep["phases"]) == 12 and sweep["settings"]["duration_s"] == pytest.approx(0.4)
    assert (report / "baseline_best" / "trajectory.png").exists()
    assert f"best phase lag: {sweep['best']['phase_deg']:g}°" in summary
    # the killed call keeps its wall time up to its last checkpoint (its row is written before each
    # checkpoint); the resume's row starts at that checkpoint
    sessions = _rows(run / "sessions.csv")
    assert len(sessions) == 2 and sessions[0][0] == "0" and int(sessions[0][1]) >= killed_at
    assert sessions[1][:2] == [str(killed_at), "160"] and float(sessions[0][2]) > 0
    # the report compares with the expert baseline's phase sweep when given one
    from softcrawl.codesign.report import write_report

    sweep = tmp_path / "sweep"
    sweep.mkdir()
    (sweep / "sweep.json").write_text(json.dumps({
        "settings": {"design": [1, 0, 0, 2, 2, 0, 0, 1], "duration_s": 20.0, "config": {"model": "reduced",
                                                                                      "leg_mesh_size": 6.0}},
        "best": {"phase_deg": 250.0, "reward_cm": 3.21}, "paper_best_phase_deg": 110.0}))
    summary = (write_report(run, baseline=sweep, simulate=False) / "summary.md").read_text()
    assert "## Expert baseline" in summary and "250° (paper: 110.0°), +3.210 cm" in summary
    assert "this run: 0.4 s episodes" in summary  # smoke: 20 actions x 2 steps x 0.01 s
    (sweep / "sweep.json").write_text("{}")
    with pytest.raises(ValueError, match="not a softcrawl sweep-phase output"):
        write_report(run, baseline=sweep, simulate=False)
    assert (run / "logs" / "progress.csv").exists()
    assert any(p.name.startswith("events.out.tfevents") for p in (run / "logs").iterdir())
    # `softcrawl report --groundtruth GT` places the chosen design in a ground truth (here one of
    # the run's tried designs with made-up rewards: reward = the design's index among them)
    from softcrawl.cli import main as cli_main

    tried = groundtruth_of_tried(run, tmp_path / "gt")
    score = {d: float(i) for i, d in enumerate(tried)}
    assert cli_main(["report", str(run), "--groundtruth", str(tmp_path / "gt"), "--no-simulate"]) == 0
    summary = (report / "summary.md").read_text()
    numbers = json.loads((report / "summary.json").read_text())["regret"]
    chosen = tuple(numbers["choice"]["design"])
    assert "## Regret against the ground truth" in summary
    assert numbers["placement"]["rank"] == len(tried) - tried.index(chosen)
    assert numbers["placement"]["regret_cm"] == pytest.approx(len(tried) - 1 - score[chosen])


def test_hold_matches_integer_step_schedule():
    import math

    from softcrawl.codesign.evaluation import action_hold

    for dt, spa in ((0.01, 100), (0.01, 10), (0.01, 20), (0.005, 7)):
        h = action_hold(dt, spa, 20)
        assert all(math.floor(k * dt / h) == k // spa for k in range(20 * spa))


def test_train_rejects_bad_dirs(tmp_path):
    from softcrawl.codesign.training import train

    with pytest.raises(ValueError):
        train(tmp_path / "missing", resume=True)
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("x")
    with pytest.raises(ValueError):
        train(tmp_path / "full", preset("smoke"))


def _parser():
    import argparse
    import importlib

    p = argparse.ArgumentParser(prog="softcrawl")
    sub = p.add_subparsers(dest="command", required=True)
    for m in ("train", "report", "evaluate"):
        importlib.import_module(f"softcrawl.cli.{m}").register(sub)
    return p


def test_cli_bad_input(tmp_path):
    p = _parser()
    args = p.parse_args(["train", "--preset", "smoke", "--out", str(tmp_path / "r"), "--set", "n_envs=0"])
    with pytest.raises(ValueError, match="n_envs"):
        args.func(args)
    args = p.parse_args(["train", "--resume", "--out", str(tmp_path / "r"), "--total-steps", "10"])
    with pytest.raises(ValueError, match="resume"):
        args.func(args)
    args = p.parse_args(["report", str(tmp_path)])
    with pytest.raises(ValueError, match="not a training run"):
        args.func(args)
    args = p.parse_args(["evaluate", str(tmp_path), "--design", "1,0,0,2,2,0,0,0", "--out", str(tmp_path / "e")])
    with pytest.raises(ValueError, match="not a training run"):
        args.func(args)
    assert not (tmp_path / "r").exists()


def test_reduced_model_is_selectable():
    from softcrawl.codesign.factory import robot_factory

    cfg = override(preset("smoke"), ['env.model="reduced"'])
    factory = robot_factory(cfg)
    assert factory.config.model == "reduced" and factory.config.reduction is None
    with pytest.raises(ValueError):
        override(preset("smoke"), ['env.model="tiny"'])
