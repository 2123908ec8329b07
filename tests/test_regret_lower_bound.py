"""`regret` says when the learned gait beats the ground truth's best gait for the chosen design
(its search missed a gait there, so the rank is a lower bound), and only then; and when the
ground truth is unfinished."""

from __future__ import annotations

from types import SimpleNamespace

from groundtruth_helpers import DESIGNS, killed_folder, make_folder

from softcrawl.codesign.groundtruth_regret import BEATS_MARGIN, place_design, policy_beats, regret_markdown
from softcrawl.codesign.report_training import _groundtruth_placer


def _setup(policy_cm, diverged=False):
    results = {(0, 0, 0, 1, 1, 1, 0, 0): SimpleNamespace(reward_cm=18.13),
               (0, 0, 0, 1, 2, 1, 0, 0): SimpleNamespace(reward_cm=32.87),
               (0, 0, 0, 1, 2, 2, 0, 0): SimpleNamespace(reward_cm=24.47),
               (0, 0, 1, 1, 2, 0, 0, 0): SimpleNamespace(reward_cm=21.22)}
    placement = {"design": [0, 0, 0, 1, 1, 1, 0, 0], "reward_cm": 18.13, "rank": 4, "of": 4, "percentile": 25.0,
                 "best_design": [0, 0, 0, 1, 2, 1, 0, 0], "best_cm": 32.87, "regret_cm": 14.74,
                 "gait": {"patterns": [[90.0, 7.49], [0.0, 0.0], [0.0, 0.0]], "hold": 1.0, "waveform": "step"}}
    pol = {"reward_cm": policy_cm, "diverged": diverged, "gait_source": "sample 2", "episode_seconds": 20.0}
    return placement, pol, results


def test_a_learned_gait_beyond_the_margin_is_said_with_the_rank_it_would_take():
    placement, pol, results = _setup(23.82)
    beats = policy_beats(placement, pol, results, "cm")
    assert beats["rank"] == 3 and abs(beats["margin_cm"] - 5.69) < 1e-9  # behind 32.87 and 24.47
    md = "\n".join(regret_markdown({"groundtruth": "gt", "choice": {"source": "shortlist", "prob": 1.0},
                                    "placement": {**placement, "policy_beats_groundtruth": beats}, "policy": pol,
                                    "settings_differ": {}}))
    assert "returns 5.69 cm more on the chosen design" in md and "would place 3 of 4" in md


def test_within_the_margin_diverged_or_not_finite_says_nothing():
    for cm, diverged in ((18.13 * (1 + BEATS_MARGIN), False), (17.0, False), (40.0, True), (float("nan"), False),
                         (None, False)):
        placement, pol, results = _setup(cm, diverged)
        assert policy_beats(placement, pol, results, "cm") is None
    placement, pol, _ = _setup(23.82)
    md = "\n".join(regret_markdown({"groundtruth": "gt", "choice": {"source": "shortlist", "prob": 1.0},
                                    "placement": placement, "policy": pol, "settings_differ": {}}))
    assert "missed a gait" not in md


def test_an_unfinished_ground_truth_is_said_with_how_many_designs_are_done(tmp_path):
    """Regression: ``regret`` against a ground truth still being computed gave "rank 5 of 49"
    with nothing saying that 231 of its 280 designs were still to come."""
    part = killed_folder(tmp_path / "part", DESIGNS, 3)
    p = place_design(DESIGNS[0], part)
    assert (p["of"], p["requested"]) == (3, 5)
    md = "\n".join(regret_markdown({"groundtruth": "gt", "choice": {"source": "shortlist", "prob": 1.0},
                                    "placement": p, "policy": None, "settings_differ": {}}))
    assert "unfinished: 3 of its 5 designs are done" in md
    assert _groundtruth_placer(part)[1] == "3 of its 5 designs: unfinished"
    whole = make_folder(tmp_path / "whole")
    p = place_design(DESIGNS[0], whole)
    assert (p["of"], p["requested"]) == (5, 5)
    md = "\n".join(regret_markdown({"groundtruth": "gt", "choice": {"source": "shortlist", "prob": 1.0},
                                    "placement": p, "policy": None, "settings_differ": {}}))
    assert "unfinished" not in md and _groundtruth_placer(whole)[1] == "5 designs"
