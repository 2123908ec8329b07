"""Every ``softcrawl`` command and subcommand runs in a test: a check that the test suite invokes
each one the parser lists, and cheap real invocations of those no other test runs (``verify``,
``reduce build`` and ``reduce validate`` on the tiny reduction settings, ``rig example``,
``regret`` with its real policy rollout)."""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import re
from pathlib import Path

import numpy as np
import pytest

from softcrawl.cli import build_parser, main
from helpers import groundtruth_of_tried

TESTS = Path(__file__).resolve().parent


def _commands() -> list[tuple[str, ...]]:
    """``(command,)`` or ``(command, subcommand)`` for everything ``softcrawl --help`` lists."""
    def subparsers(parser):
        return next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))

    out = []
    for name, p in subparsers(build_parser()).choices.items():
        subs = [a for a in p._actions if isinstance(a, argparse._SubParsersAction)]
        out += [(name, s) for s in subs[0].choices] if subs else [(name,)]
    return out


def test_every_cli_command_is_invoked_by_a_test():
    """An argument list starting with the command (and its subcommand) in some test file:
    ``main(["reduce", "build", ...])``, ``_start(["deploy", ...])``. A new command without a
    test fails here."""
    commands = _commands()
    assert ("reduce", "build") in commands and ("train",) in commands and len(commands) >= 19
    text = "\n".join(p.read_text() for p in TESTS.glob("test_*.py"))
    missing = [c for c in commands
               if not re.search(r"\[\s*" + r",\s*".join(f'"{re.escape(w)}"' for w in c) + r"\s*[,\]]", text)]
    assert missing == []


def test_verify_runs_the_named_checks_and_fails_on_a_failed_one(monkeypatch, capsys):
    """``verify --only corotational --json``: its 2 results (rigid motions give no elastic force,
    a rotated beam responds rotated) pass; a failing check makes the exit status 1, an unknown
    check name is a one-line error (exit 2)."""
    import softcrawl.verify.checks as checks

    assert main(["verify", "--only", "corotational", "--json"]) == 0
    res = json.loads(capsys.readouterr().out)
    assert res["resolution"] == "coarse" and len(res["checks"]) == 2 and all(c["pass"] for c in res["checks"])
    failing = checks.CheckResult(name="fails", expected=1.0, got=2.0, tolerance=0.1, mode="rel", unit="mm")
    assert not failing.passed
    monkeypatch.setitem(checks.CHECKS, "fails", lambda resolution: [failing])
    assert main(["verify", "--only", "fails"]) == 1
    assert "FAIL  fails" in capsys.readouterr().out
    assert main(["verify", "--only", "nope"]) == 2
    assert "unknown checks ['nope']" in capsys.readouterr().err


def test_reduce_build_then_validate_on_tiny_settings(tmp_path, monkeypatch, capsys):
    """``reduce build`` and ``reduce validate`` through the CLI on a 12-mm leg mesh with the
    scene lengths of test_reduction's tiny build (0.05-s states) and one 0.1-s validation scene
    (the CLI exposes only the designs and tolerances: the rest is narrowed here). The file
    written loads for that mesh; the validation compares the reduced with the full model."""
    import softcrawl.cli.reduce as reduce_cli
    from softcrawl.reduction.artifact import load_reduction
    from softcrawl.reduction.build import BuildSettings
    from softcrawl.reduction.scenes import validation_scenes
    from softcrawl.reduction.validate import validate_reduction

    @dataclasses.dataclass(frozen=True)
    class TinyBuild(BuildSettings):
        sizes: tuple = (3,)
        state_seconds: float = 0.05
        gait_seconds: float = 0.05
        ecsw_scenes: int = 1
        ecsw_every: int = 3

    monkeypatch.setattr(reduce_cli, "BuildSettings", TinyBuild)
    monkeypatch.setattr(reduce_cli, "validate_reduction",
                        functools.partial(validate_reduction, scenes=validation_scenes(0.1)[1:2]))
    common = ["--workdir", str(tmp_path / "work"), "--mesh-size", "12", "--designs", "2", "--gait-designs", "1",
              "--workers", "1", "--no-progress"]
    assert main(["reduce", "build", *common, "--out", str(tmp_path / "tiny.npz")]) == 0
    assert "wrote" in capsys.readouterr().out
    reduction, meta = load_reduction(tmp_path / "tiny.npz")
    assert meta["valid_for"]["leg_mesh_size"] == 12.0 and reduction.leg.n_modes >= 3
    out = tmp_path / "validation"
    assert main(["reduce", "validate", *common, "--reduction", str(tmp_path / "tiny.npz"), "--ensemble", "0",
                 "--out", str(out)]) == 0
    rep = json.loads((out / "validation.json").read_text())
    assert [s["scene"] for s in rep["scenes"]] == ["baseline"] and np.isfinite(rep["mean_node_error_mm"])
    assert rep["mean_node_error_mm"] > 0 and "| baseline |" in (out / "validation.md").read_text()


def test_rig_example_prints_a_rig_file_that_loads(tmp_path, capsys):
    from softcrawl.hardware.config import load_rig_config

    assert main(["rig", "example"]) == 0
    (tmp_path / "rig.toml").write_text(capsys.readouterr().out)
    cfg = load_rig_config(tmp_path / "rig.toml")
    assert cfg.supply.model == "BK9129B" and cfg.rig.max_kpa <= 90.0 and len(cfg.regulators) == 3


def test_regret_rolls_out_the_learned_policy(trained, tmp_path, capsys):
    """``regret RUN --groundtruth GT`` with the real policy episode (no monkeypatch): a ground
    truth of the run's tried designs with made-up rewards (reward = the design's index among
    them); the policy's reward is that of the same gait ``softcrawl evaluate`` chooses (the best
    of the deterministic episode and the default samples), its actions one per action step of
    the run and within the regulators' 0-90 kPa."""
    from softcrawl.codesign.evaluation import GAIT_SAMPLES, evaluate_policy
    from softcrawl.codesign.run import Run

    tried = groundtruth_of_tried(trained, tmp_path / "gt")
    assert main(["regret", str(trained), "--groundtruth", str(tmp_path / "gt"), "--json", str(tmp_path / "r.json")]) == 0
    r = json.loads((tmp_path / "r.json").read_text())
    chosen = tuple(r["choice"]["design"])
    assert r["placement"]["rank"] == len(tried) - tried.index(chosen)
    pol = r["policy"]
    ev = evaluate_policy(trained, chosen, samples=GAIT_SAMPLES)
    assert pol["reward_cm"] == pytest.approx(ev.gait_return, abs=1e-12) and pol["gait_source"] == ev.gait_source
    assert np.allclose(pol["actions_kpa"], ev.gait_actions_kpa, atol=0.005)
    actions = np.array(pol["actions_kpa"])
    assert actions.shape == (Run(trained).read_config().env.n_actions, 3)
    assert actions.min() >= 0.0 and actions.max() <= 90.0
    assert f"{pol['reward_cm']:+.2f} cm" in capsys.readouterr().out
