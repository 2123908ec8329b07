"""`regret` says when the learned gait beats the ground truth's best gait for the chosen design
(its search missed a gait there, so the rank is a lower bound), and only then."""

from __future__ import annotations

from types import SimpleNamespace

from softcrawl.codesign.groundtruth_regret import BEATS_MARGIN, policy_beats, regret_markdown


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
