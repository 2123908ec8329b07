"""``softcrawl groundtruth --engine jax``: the searched episodes on the JAX engine, the round of
every design in flight in one batch (:func:`softcrawl.codesign.groundtruth.runner.jax_evaluator`)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from softcrawl.cli import main as cli_main
from softcrawl.codesign.groundtruth import GroundTruthConfig, PeriodicGait, gt_robot, load_results

pytest.importorskip("jax")

#: Two designs of different leg counts (two JAX groups), a 2-knot search of 3 episodes of 0.5 s
#: and one finalist of 1 s on the coarse 25 mm disk.
DESIGNS = "1,0,0,2,2,0,0,0;1,1,0,2,0,0,0,0"
TINY = ["--cycles", "2", "--evals-per-cycle", "3", "--finalists", "1", "--duration", "1.0",
        "--screen-duration", "0.5", "--disk-mesh-size", "25", "--baseline-phases", "none"]
#: |JAX - CPU| of a 1-s episode's reward, cm: the JAX engine's episodes agree with
#: ``run_episode`` to 0.007 cm over 2 s (tests/test_jaxsim_episodes.py); 0.02 cm is that bound.
TOL_CM = 0.02


@pytest.mark.slow
def test_jax_ground_truth_rows_are_what_the_cpu_engine_gives_their_gaits(tmp_path, monkeypatch):
    """Each row's reward is the CPU reduced engine's reward of the row's own best gait (re-run
    here with :class:`DesignEvaluator`) within :data:`TOL_CM`; the folder records the engine and
    a resume with the CPU engine is refused."""
    from softcrawl.codesign.groundtruth import DesignEvaluator

    monkeypatch.setenv("SOFTCRAWL_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "gt"
    assert cli_main(["groundtruth", "--out", str(out), "--designs", DESIGNS, "--engine", "jax",
                     "--jax-batch", "4", "--no-progress", *TINY]) == 0
    res = load_results(out)
    assert len(res) == 2
    saved = json.loads((out / "config.json").read_text())["config"]
    assert saved["engine"] == "jax"
    cfg = GroundTruthConfig.from_dict(saved)
    for design, row in res.items():
        assert row.evaluations == 5 and math.isfinite(row.reward_cm)
        cpu, diverged = DesignEvaluator(design, cfg)(PeriodicGait.from_dict(row.gait), cfg.duration)
        assert not diverged
        assert abs(cpu - row.reward_cm) <= TOL_CM, (design, cpu, row.reward_cm)
    assert cli_main(["groundtruth", "--out", str(out), "--designs", DESIGNS, "--no-progress", *TINY]) == 2


def test_engine_settings_are_checked():
    assert GroundTruthConfig().engine == "cpu"  # an older folder's config (no engine) reads as the CPU's
    with pytest.raises(ValueError, match="engine must be one of"):
        GroundTruthConfig(engine="gpu").validate()
    with pytest.raises(ValueError, match="reduced robot only"):
        GroundTruthConfig(engine="jax", robot=gt_robot(model="full")).validate()
    with pytest.raises(ValueError, match="power of two"):
        GroundTruthConfig(engine="jax", jax_batch=48).validate()


def test_step_gait_commands_are_pressure_at_of_every_step():
    """The search's step gaits' schedules, computed for all steps at once, are exactly
    ``pressure_at(k dt)`` of each step (cycle lengths 1 to 8, holds and steps that do not
    divide each other, knots at the bounds)."""
    from softcrawl.codesign.groundtruth import knots_to_gait
    from softcrawl.jaxsim.episodes import gait_commands

    rng = np.random.default_rng(0)
    for trial in range(60):
        m, L = int(rng.integers(1, 4)), int(rng.integers(1, 9))
        x = np.where(rng.random(m * L) < 0.2, rng.integers(0, 2, m * L), rng.random(m * L))
        gait = knots_to_gait(x, m, L, (1.0, 0.5, 1 / 3, 0.7, 0.02)[trial % 5])
        for dt in (0.01, 0.02, 0.003):
            expect = np.array([gait.pressure_at(k * dt) for k in range(700)])
            np.testing.assert_array_equal(gait_commands(gait, 700, dt), expect)


def test_a_finished_designs_state_is_let_go():
    """``JaxEvaluator.forget`` drops the designs' rested states held in memory (the runner calls it
    as each design finishes), and ignores a design it does not hold."""
    from softcrawl.jaxsim.episodes import JaxEvaluator

    ev = JaxEvaluator(gt_robot())
    held = ev.space.canonicalize((2, 0, 0, 1, 1, 0, 0, 0))
    ev._designs[held] = object()  # as prepare() leaves a settled design
    ev.forget([(1, 0, 0, 2, 2, 0, 0, 0), (1, 1, 1, 0, 0, 0, 0, 0)])
    assert held not in ev._designs
