"""The design's gait from a trained policy: its deterministic episode and episodes sampled from
the stochastic policy (:func:`softcrawl.codesign.evaluation.evaluate_policy`, ``samples``), the
best of them chosen, and where that choice shows (report, evaluate, regret, deploy).

The smoke run's episodes are 20 actions of 2 steps; every return is re-checked by replaying the
chosen actions through :func:`softcrawl.robot.run_episode`, a second code path from the env's."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from softcrawl.cli import main
from softcrawl.codesign.evaluation import GAIT_SAMPLES, PolicyEvaluation, evaluate_policy

DESIGN = "1,0,0,2,2,0,0,0"


def test_sampled_gaits_differ_from_the_mean_and_the_chosen_one_replays_to_its_return(trained):
    ev = evaluate_policy(trained, DESIGN, samples=4)
    assert len(ev.sampled_returns) == len(ev.sampled_actions) == len(ev.sampled_diverged) == 4
    for acts in ev.sampled_actions:  # the squashed Gaussian's samples, not its mean
        assert acts.shape == ev.actions_kpa.shape and np.all((acts >= 0) & (acts <= 90))
        assert np.abs(acts - ev.actions_kpa).max() > 1.0
    candidates = [ev.returns_cm[0], *ev.sampled_returns]
    assert ev.gait_return == max(candidates)
    k = int(np.argmax(candidates))
    assert ev.gait_source == ("deterministic" if k == 0 else f"sample {k}")
    assert np.array_equal(ev.gait_actions_kpa, ev.actions_kpa if k == 0 else ev.sampled_actions[k - 1])
    assert ev.resimulate(record_every=None).reward_cm == pytest.approx(ev.gait_return, abs=1e-9)


def test_the_same_call_samples_the_same_gaits_and_no_samples_is_the_deterministic_gait(trained):
    a, b = evaluate_policy(trained, DESIGN, samples=3), evaluate_policy(trained, DESIGN, samples=3)
    assert a.sampled_returns == b.sampled_returns  # the policy's noise is seeded by the run's seed
    plain = evaluate_policy(trained, DESIGN)
    assert plain.sampled_returns == [] and plain.gait_source == "deterministic"
    assert np.array_equal(plain.gait_actions_kpa, a.actions_kpa) and plain.gait_return == a.returns_cm[0]


def _evaluation(det: float, sampled, diverged=None) -> PolicyEvaluation:
    n = len(sampled)
    return PolicyEvaluation((1, 0, 0, 2, 2, 0, 0, 0), [det], [False], np.zeros((2, 3)), None, None, "ck",
                            sampled_returns=list(sampled), sampled_diverged=list(diverged or [False] * n),
                            sampled_actions=[np.full((2, 3), float(k + 1)) for k in range(n)])


def test_the_choice_keeps_the_deterministic_gait_on_ties_and_never_takes_a_diverged_one():
    assert _evaluation(2.0, [1.0, 2.0]).chosen is None  # a tie keeps the deterministic gait
    assert _evaluation(2.0, [1.0, 3.0, 2.5]).chosen == 1
    assert _evaluation(2.0, [9.0, 3.0], diverged=[True, False]).gait_return == 3.0
    assert _evaluation(2.0, [math.nan, math.inf]).chosen is None  # never a non-finite return
    assert _evaluation(2.0, [math.nan, 2.5]).gait_source == "sample 2"


def test_bad_sample_counts_are_refused(trained, tmp_path, capsys):
    from softcrawl.robot.domain import DomainRanges

    with pytest.raises(ValueError, match="samples"):
        evaluate_policy(trained, DESIGN, samples=-1)
    with pytest.raises(ValueError, match="samples"):
        evaluate_policy(trained, DESIGN, samples=2, randomize=DomainRanges(friction=(0.8, 1.6)))
    capsys.readouterr()
    assert main(["evaluate", str(trained), "--design", DESIGN, "--samples", "-2", "--out", str(tmp_path / "e")]) == 2
    assert main(["deploy", "--rig", "sim", "--gait", "sine", "--samples", "3", "--out", str(tmp_path / "d")]) == 2
    err = capsys.readouterr().err
    assert "--samples must be 0 to" in err and "--samples go with --run" in err
    assert not (tmp_path / "e").exists() and not (tmp_path / "d").exists()


def test_evaluate_writes_the_chosen_gait(trained, tmp_path):
    out = tmp_path / "ev"
    assert main(["evaluate", str(trained), "--design", DESIGN, "--samples", "3", "--out", str(out),
                 "--no-animation", "--no-progress"]) == 0
    ev = json.loads((out / "evaluation.json").read_text())
    assert len(ev["sampled_cm"]) == 3 and ev["gait_cm"] == max(ev["returns_cm"][0], *ev["sampled_cm"])
    assert ev["rerun_reward_cm"] == pytest.approx(ev["gait_cm"], abs=1e-9)
    from softcrawl.gaits import read_actions_csv

    assert np.allclose(read_actions_csv(out / "actions.csv").actions, ev["actions_kpa"], atol=1e-9)


def test_a_turning_report_compares_the_chosen_gait_and_the_sampled_mean_with_the_baseline(run):
    """The smoke run relabelled as turning: the baseline section's ratios are those of the best
    design's numbers (its chosen gait, the mean of its samples) over the baseline's best turn."""
    from softcrawl.codesign.report import write_report

    cfg = json.loads((run / "config.json").read_text())
    cfg["config"]["env"]["task"] = "turning"
    (run / "config.json").write_text(json.dumps(cfg))
    out = write_report(run, baseline_phases=(0.0, 90.0), samples=2, workers=1)
    numbers = json.loads((out / "summary.json").read_text())
    best, base = numbers["best_design"], numbers["baseline"]
    assert len(best["sampled_deg"]) == 2 and best["gait_deg"] == max(best["policy_deg"], *best["sampled_deg"])
    assert best["resimulated_deg"] == pytest.approx(best["gait_deg"], abs=1e-6)
    assert base["ratio"] == pytest.approx(abs(best["gait_deg"]) / abs(base["best_deg"]), rel=1e-12)
    mean = float(np.mean(best["sampled_deg"]))
    assert base["ratio_sampled_mean"] == pytest.approx(abs(mean) / abs(base["best_deg"]), rel=1e-12)
    e = cfg["config"]["env"]  # the gait's parts cover its own episode, not the venting after it
    assert best["gait"]["part_seconds"] == pytest.approx(e["n_actions"] * e["steps_per_action"] * e["robot"]["dt"] / 4)
    # turning is scored at rest: the return is what the vented replay keeps, the sweep's too
    assert best["kept_after_venting_deg"] == pytest.approx(best["gait_deg"], abs=1e-5)
    assert base["kept_after_venting_deg"] == pytest.approx(base["best_deg"], abs=1e-5) and "ratio_kept" not in base
    summary = (out / "summary.md").read_text()
    assert f"its gait ({best['gait_source']}): {best['gait_deg']:+.2f}°, {base['ratio']:.2f}x" in summary
    assert f"kept at rest after 5 s more with every regulator vented: {best['kept_after_venting_deg']:+.3f} deg" in summary
    assert f"Sampled from the stochastic policy, 2 episodes: mean {mean:+.3f}" in summary


def test_the_reports_default_samples_is_the_help_texts():
    import argparse

    from softcrawl.cli import report

    parser = argparse.ArgumentParser()
    report.register(parser.add_subparsers())
    text = parser._subparsers._group_actions[0].choices["report"].format_help()
    assert f"default {GAIT_SAMPLES}:" in " ".join(text.split()) and GAIT_SAMPLES + 1 == 12
