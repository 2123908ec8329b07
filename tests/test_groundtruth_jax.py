"""``softcrawl groundtruth --engine jax``: the searched episodes on the JAX engine, every design's
episode of a round in one batch (:func:`softcrawl.codesign.groundtruth.runner.jax_evaluate_many`)."""

from __future__ import annotations

import json
import math

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
