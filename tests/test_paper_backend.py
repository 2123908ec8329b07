"""`softcrawl train --preset paper` runs its envs on the JAX backend and its learner on the GPU
when JAX sees a GPU (one line says so; a ``sac.device`` given keeps the learner there), keeps the subprocess backend otherwise, and a backend given always wins (JAX's devices
faked; the training itself stubbed)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from softcrawl.cli import main


@pytest.fixture
def started(monkeypatch, tmp_path):
    """``(configs, asked)``: the config each ``softcrawl train`` would have trained, and how often
    JAX's devices were asked for; ``started.gpu`` sets whether JAX sees one."""
    import jax

    import softcrawl.cli.train as train_cli
    from softcrawl.codesign.training import TrainResult

    configs, asked, gpu = [], [], [True]

    def devices(backend=None):
        asked.append(backend)
        cpu = SimpleNamespace(platform="cpu", device_kind="cpu")
        return [cpu] if backend == "cpu" or not gpu[0] else [SimpleNamespace(platform="gpu", device_kind="Fake H100")]

    def trained(out, cfg=None, **kw):
        configs.append(cfg)
        return TrainResult(tmp_path / "none", 0, 0.0, 0)

    monkeypatch.setattr(jax, "devices", devices)
    monkeypatch.setattr(train_cli, "train_and_report", trained)
    return SimpleNamespace(configs=configs, asked=asked, gpu=gpu, out=str(tmp_path / "run"))


def test_the_paper_preset_takes_the_jax_backend_when_jax_sees_a_gpu(started, capsys):
    assert main(["train", "--preset", "paper", "--out", started.out, "--no-progress"]) == 0
    assert started.configs[-1].backend == "jax" and started.configs[-1].sac.device == "gpu"
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "JAX sees 1 GPU(s) (Fake H100): the paper preset runs its 96 envs on the JAX " \
        "backend" in err
    started.gpu[0] = False
    assert main(["train", "--preset", "paper", "--out", started.out, "--no-progress"]) == 0
    assert started.configs[-1].backend == "subprocess" and started.configs[-1].sac.device == "cpu"
    assert "JAX" not in capsys.readouterr().err


def test_a_learner_device_given_keeps_the_learner_where_it_is_told(started, capsys):
    assert main(["train", "--preset", "paper", "--out", started.out, "--no-progress", "--set", 'sac.device="cpu"']) == 0
    assert started.configs[-1].backend == "jax" and started.configs[-1].sac.device == "cpu"
    assert "learns there" not in capsys.readouterr().err


@pytest.mark.parametrize("given", [["--backend", "serial"], ["--set", 'backend="subprocess"']])
def test_a_backend_given_always_wins(started, capsys, given):
    assert main(["train", "--preset", "paper", "--out", started.out, "--no-progress", *given]) == 0
    assert started.configs[-1].backend == ("serial" if "serial" in given else "subprocess")
    assert started.asked == [] and "JAX" not in capsys.readouterr().err


def test_other_presets_and_settings_jax_cannot_run_keep_their_backend(started, capsys):
    assert main(["train", "--preset", "demo", "--out", started.out, "--no-progress"]) == 0
    assert started.configs[-1].backend == "subprocess" and started.asked == []
    assert main(["train", "--preset", "paper", "--task", "turning", "--out", started.out, "--no-progress"]) == 0
    assert started.configs[-1].backend == "subprocess"
    err = capsys.readouterr().err
    assert "JAX sees a GPU, but these settings do not run on the JAX backend" in err and "keeping backend " \
        "'subprocess'" in err
