"""A training run's start: a failed start does not block its retry, ``--set`` values are
checked against the config fields, a bad reduction or unusable GPU fails before the run starts,
and options that would be ignored are errors."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from softcrawl.cli import main
from softcrawl.codesign.config import override, preset
from helpers import file_tree, one_line_error


def test_failed_start_writes_no_config(tmp_path, monkeypatch):
    import softcrawl.codesign.training as training

    def broken(*a, **k):
        raise RuntimeError("envs could not be built")

    monkeypatch.setattr(training, "make_vec_env", broken)
    with pytest.raises(RuntimeError):
        training.train(tmp_path / "run", preset("smoke"), progress=False)
    assert not (tmp_path / "run" / "config.json").exists()
    from softcrawl.cli.train import _check_out

    _check_out(str(tmp_path / "run"))  # the same --out is accepted again


def test_bad_reduction_fails_before_the_run_starts(tmp_path):
    from softcrawl.codesign.training import train

    (tmp_path / "bad.npz").write_bytes(b"not a reduction")
    with pytest.raises(ValueError, match="bad.npz"):
        train(tmp_path / "run", override(preset("smoke"), [f'env.reduction="{tmp_path / "bad.npz"}"']), progress=False)
    assert not (tmp_path / "run" / "config.json").exists()


def _no_gpu(monkeypatch, gpus=()):
    """JAX as a CPU-only jaxlib sees it (``gpus``: the GPUs it would see instead)."""
    import jax

    cpu = jax.devices("cpu")

    def devices(backend=None):
        if backend == "cpu":
            return cpu
        if not gpus:
            raise RuntimeError(f"Unknown backend: '{backend}' requested")
        return list(gpus)

    monkeypatch.setattr(jax, "devices", devices)


def test_a_gpu_jax_cannot_use_fails_before_the_run_starts(tmp_path, monkeypatch):
    from softcrawl.codesign.training import train

    _no_gpu(monkeypatch)
    with pytest.raises(ValueError, match="sac.device='gpu:1'.*sees no GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="gpu:1"', 'sac.learner="sbx"']), progress=False)
    assert not (tmp_path / "run").exists()
    _no_gpu(monkeypatch, gpus=["gpu0"])
    with pytest.raises(ValueError, match="sees 1 GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="cuda:1"', 'sac.learner="sbx"']), progress=False)
    assert not (tmp_path / "run").exists()


def test_a_gpu_torch_cannot_use_fails_before_the_run_starts(tmp_path, monkeypatch):
    import torch

    from softcrawl.codesign.training import train

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match="sac.device='cuda:1'.*no CUDA GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="gpu:1"', 'sac.learner="torch"',
                                                           'rollout="action"']), progress=False)
    assert not (tmp_path / "run").exists()
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    with pytest.raises(ValueError, match="sees 1 CUDA GPU"):
        train(tmp_path / "run", override(preset("smoke"), ['sac.device="cuda:1"', 'sac.learner="torch"',
                                                           'rollout="action"']), progress=False)
    assert not (tmp_path / "run").exists()


def test_a_run_trained_on_a_gpu_is_evaluated_on_the_cpu(run, monkeypatch):
    from softcrawl.codesign.evaluation import evaluate_policy

    on_cpu = evaluate_policy(run, "1,0,0,2,2,0,0,0").returns_cm
    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["sac"]["device"] = "gpu"
    (run / "config.json").write_text(json.dumps(cfg))
    _no_gpu(monkeypatch)
    assert evaluate_policy(run, "1,0,0,2,2,0,0,0").returns_cm == on_cpu


@pytest.mark.parametrize("setting, key", [('sac.batch_size="64"', "sac.batch_size"), ("n_envs=2.5", "n_envs"),
                                          ("env.observe_state=1", "env.observe_state"), ("env.legs=3", "env.legs"),
                                          ("sac.net_arch=[0]", "sac.net_arch"), ("sac.batch_size=5000", "batch_size"),
                                          ("sac.net_arch=[64, true]", "sac.net_arch"),
                                          ("keep_checkpoints=1", "keep_checkpoints")])
def test_set_values_are_checked_against_the_fields(setting, key, tmp_path, capsys):
    rc = main(["train", "--preset", "smoke", "--out", str(tmp_path / "r"), "--set", setting])
    one_line_error(capsys, rc, key)
    assert not (tmp_path / "r").exists()


# -- 7: options that would be ignored are errors ----------------------------------------------------
def test_ignored_options_are_errors(trained, tmp_path, monkeypatch, capsys):
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: pytest.fail("model built"))
    before = file_tree(trained)
    one_line_error(capsys, main(["train", "--resume", "--preset", "smoke", "--out", str(trained)]), "--preset")
    assert file_tree(trained) == before
    rc = main(["simulate", "--model", "full", "--reduction", "x.npz", "--out", str(tmp_path / "o"), "--no-progress"])
    one_line_error(capsys, rc, "--reduction")
    with pytest.raises(ValueError, match="env.reduction"):
        override(preset("smoke"), ['env.model="full"', 'env.reduction="x.npz"'])


# -- issue 49, defect 12: two settings of one thing are refused, naming both ---------------------------
@pytest.mark.parametrize("argv, words", [
    (["--task", "turning", "--set", 'env.task="forward"'], ["--task", "env.task", "give one"]),
    (["--workers", "2", "--set", "n_workers=1"], ["--workers", "n_workers"]),
    (["--seed", "3", "--set", "seed=1"], ["--seed", "seed=1"]),
    (["--space", "hex6", "--set", 'env.space="paper"'], ["--space", "env.space"]),
    (["--set", "seed=1", "--set", "seed=2"], ["'seed=1'", "'seed=2'", "twice"]),
    (["--set", "env.dt=0.01", "--set", "env.robot.dt=0.02"], ["env.dt=0.01", "env.robot.dt=0.02", "twice"]),
])
def test_an_option_and_a_set_of_the_same_setting_are_refused(argv, words, tmp_path, capsys):
    """The probe: ``--task turning`` silently beat ``--set env.task=...``."""
    one_line_error(capsys, main(["train", "--preset", "smoke", "--out", str(tmp_path / "r"), *argv]), *words)
    assert not (tmp_path / "r").exists()


def test_a_resumed_runs_placement_is_given_once(trained, capsys):
    before = file_tree(trained)
    one_line_error(capsys, main(["train", "--resume", "--out", str(trained), "--workers", "2", "--set", "n_workers=1"]),
                   "--workers", "n_workers")
    assert file_tree(trained) == before


def test_a_floor_friction_given_twice_and_ignored_gait_options_are_refused(tmp_path, monkeypatch, capsys):
    """The probe: ``simulate --friction 0.5`` silently lost to the task's ``"friction": 2.0``."""
    import softcrawl.cli.simulate as sim

    monkeypatch.setattr(sim, "build_robot", lambda *a, **k: pytest.fail("model built"))
    rc = main(["simulate", "--task", '{"name": "incline", "angle_deg": 10, "friction": 2.0}', "--friction", "0.5",
               "--out", str(tmp_path / "o"), "--no-progress"])
    one_line_error(capsys, rc, "--friction 0.5", "the task's friction 2", "give one")
    from softcrawl.hardware.config import example_rig_path

    (tmp_path / "a.csv").write_text("10,20,30\n")
    rig = str(example_rig_path())
    for argv, words in ((["sim", "--actions", str(tmp_path / "a.csv"), "--n-actions", "5"], ["--n-actions", "--actions"]),
                        (["sim", "--gait", "paper-best", "--phase", "90"], ["--phase", "paper-best"]),
                        (["sim", "--actions", str(tmp_path / "a.csv"), "--phase", "90"], ["--phase", "--actions"]),
                        ([rig, "--jitter", "0.01", "--seed", "3"], ["--seed, --jitter", "--rig sim"])):
        one_line_error(capsys, main(["deploy", "--rig", *argv, "--out", str(tmp_path / "d"), "--no-progress"]), *words)
    assert not (tmp_path / "o").exists() and not (tmp_path / "d").exists()


def test_a_refused_train_leaves_no_folder_for_the_corrected_command(tmp_path, capsys):
    """Issue 49, defect 10 (checked for train as for groundtruth): a space whose reduction has
    another SHA-256 is refused before anything is written."""
    from softcrawl.cli.train import _check_out
    from softcrawl.design.resolve import resolve_space

    paper = resolve_space("paper")
    text = Path(paper.source).read_text()
    (tmp_path / "mine.toml").write_text(text.replace(paper.reduction_sha256, "0" * 64))
    rc = main(["train", "--preset", "smoke", "--space", str(tmp_path / "mine.toml"), "--out", str(tmp_path / "r")])
    one_line_error(capsys, rc, "SHA-256")
    assert not (tmp_path / "r").exists()
    (tmp_path / "mine.toml").write_text(text)
    _check_out(str(tmp_path / "r"))  # the corrected command is accepted
