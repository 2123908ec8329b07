"""The final shortlist of a co-design run (softcrawl.codesign.shortlist): its candidates, its
choice (the best gait, not the most probable design; ties; diverged gaits never), the report's
"Shortlist" section, and `regret`, `evaluate` and `deploy --run` on the chosen design; a run
without a shortlist keeps the most probable design. The policy is a stub (fixed returns per
design) except where `evaluate` re-simulates the smoke run's design."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from softcrawl.codesign.shortlist import (
    choose,
    design_rows,
    make_shortlist,
    most_probable,
    rank_candidates,
    read_shortlist,
    run_design,
)


def _row(name, index, prob, latest, best=math.nan, recent=math.nan):
    return {"design": name, "index": index, "prob": prob, "latest_cm": latest, "best_ok_cm": best,
            "recent_cm": recent, "episodes": 1, "mean_cm": latest, "best_cm": best}


def test_candidates_are_taken_in_turn_from_the_three_rankings():
    rows = [_row("A", 0, 0.90, 3.0, best=3.0, recent=2.0),   # the most probable
            _row("B", 1, 0.01, 1.0, best=9.0, recent=1.0),   # the best episode
            _row("C", 2, 0.02, 2.0, best=4.0, recent=5.0),   # the best recent mean; second most probable
            _row("D", 3, 0.05, 2.5, best=2.5, recent=2.5),
            _row("E", 4, 0.02, 2.5)]                         # every episode diverged: by probability only
    assert [c["design"] for c in rank_candidates(rows, 1)] == ["A"]  # k = 1: the choice before the shortlist
    four = rank_candidates(rows, 4)
    assert [c["design"] for c in four] == ["A", "B", "C", "D"]
    assert [(c["rank_probability"], c["rank_best"], c["rank_recent"]) for c in four] == [
        (1, 3, 3), (5, 1, 4), (4, 2, 1), (2, 4, 2)]
    # E ties C on p and beats it on R: E is third by probability, and has no best or recent rank
    assert [c["design"] for c in rank_candidates(rows, 10)] == ["A", "B", "C", "D", "E"]
    assert rank_candidates(rows, 10)[-1]["rank_best"] is None
    for bad in (0, 101, 2.5, True):
        with pytest.raises(ValueError, match="1 to 100 candidates"):
            rank_candidates(rows, bad)


def test_the_choice_is_the_best_gait_ties_to_the_earlier_and_never_a_diverged_one():
    def c(gait, diverged=False):
        return {"gait_cm": gait, "gait_diverged": diverged}

    assert choose([c(1.0), c(3.0), c(2.0)], "cm") == 1  # not the first (most probable) one
    assert choose([c(2.0), c(2.0)], "cm") == 0  # a tie keeps the earlier candidate
    assert choose([c(1.0), c(50.0, diverged=True), c(None), c(math.nan)], "cm") == 0
    assert choose([c(5.0, diverged=True)], "cm") is None


def _stub(run, gaits: dict, calls: list | None = None):
    """An ``evaluate_policy`` stand-in: ``gaits[design] = (deterministic, its divergence, sampled
    returns, their divergences)``; each sampled gait's actions are 10 * (its number) kPa."""
    from softcrawl.codesign.evaluation import PolicyEvaluation
    from softcrawl.codesign.run import Run

    cfg = Run(run).read_config()

    def evaluate(run_, design, checkpoint=None, samples=0, episodes=1):
        det, det_bad, sampled, bad = gaits[tuple(design)]
        if calls is not None:
            calls.append(tuple(design))
        return PolicyEvaluation(tuple(design), [det], [det_bad], np.zeros((20, 3)), None, cfg, str(checkpoint), [],
                                list(sampled), list(bad), [np.full((20, 3), 10.0 * (i + 1)) for i in range(len(sampled))])
    return evaluate


def _shortlisted(run, monkeypatch, gaits_of, k=3, calls=None):
    """The run's shortlist of ``k`` made with a stub policy whose gaits ``gaits_of(candidates)``
    gives (a dict as :func:`_stub`'s); returns (shortlist, candidates)."""
    import softcrawl.codesign.evaluation as evaluation

    cands = [c["design"] for c in rank_candidates(design_rows(run), k)]
    monkeypatch.setattr(evaluation, "evaluate_policy", _stub(run, gaits_of(cands), calls))
    return make_shortlist(run, k=k, progress=False), cands


def test_the_shortlist_chooses_the_best_gait_not_the_most_probable_design(run, monkeypatch):
    calls = []
    sl, (a, b, c) = _shortlisted(run, monkeypatch, lambda d: {
        d[0]: (1.0, False, [2.0, 1.5], [False, False]),     # the most probable: its best gait 2.0
        d[1]: (0.5, False, [9.0, 3.0], [True, False]),      # a better sample that diverged: 3.0 counts
        d[2]: (40.0, True, [0.1, -1.0], [False, False]),    # a diverged deterministic episode: 0.1
    }, calls=calls)
    assert most_probable(design_rows(run))["design"] == a
    assert [tuple(x["design"]) for x in sl["candidates"]] == [a, b, c] and calls == [a, b, c]
    assert sl["chosen"] == 1 and not sl["all_diverged"] and sl["k"] == 3 and sl["samples"] == 11
    chosen = sl["candidates"][1]
    assert chosen["gait_cm"] == 3.0 and chosen["gait_source"] == "sample 2" and not chosen["gait_diverged"]
    assert chosen["actions_kpa"] == np.full((20, 3), 20.0).tolist()
    assert sl["candidates"][2]["gait_cm"] == 0.1 and sl["candidates"][2]["deterministic_diverged"]
    assert read_shortlist(run) == json.loads((run / "shortlist.json").read_text()) == sl
    d = run_design(run)
    assert d["design"] == b and d["source"] == "shortlist"
    # made once: the same command again keeps it (the training's end, then `report`)
    assert make_shortlist(run, k=3, progress=False) == sl and calls == [a, b, c]


def test_every_candidate_diverged_keeps_the_most_probable(run, monkeypatch):
    sl, cands = _shortlisted(run, monkeypatch, lambda d: {x: (5.0, True, [6.0], [True]) for x in d}, k=2)
    assert sl["chosen"] == 0 and sl["all_diverged"]
    assert run_design(run)["design"] == cands[0] == most_probable(design_rows(run))["design"]


def test_the_report_shows_the_shortlist(run, monkeypatch):
    from softcrawl.codesign.report import write_report

    sl, (a, b, c) = _shortlisted(run, monkeypatch, lambda d: {
        d[0]: (1.0, False, [1.0, 3.0], [False, False]), d[1]: (4.0, False, [2.0, 2.0], [False, False]),
        d[2]: (0.0, False, [], [])})
    out = write_report(run, simulate=False)
    md, numbers = (out / "summary.md").read_text(), json.loads((out / "summary.json").read_text())
    section = md.split("## Shortlist\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("| ") and "`" in line]
    assert len(rows) == 3 and "**chosen**" in rows[1] and "**chosen**" not in rows[0] + rows[2]
    assert f"`{','.join(map(str, b))}`" in rows[1] and "+4.000 (deterministic)" in rows[1]
    assert "+2.000 ± 1.000 (2)" in rows[0] and "+3.000 (sample 2)" in rows[0]  # the samples' mean ± sd
    assert f"- the run's design: `{','.join(map(str, b))}` (the best gait of its shortlist)" in md
    assert (out / "shortlist.png").exists()
    assert numbers["design"] == {"design": ",".join(map(str, b)), "source": "shortlist"}
    assert numbers["shortlist"] == sl


def test_regret_evaluate_and_deploy_use_the_chosen_design(run, tmp_path, monkeypatch, capsys):
    from helpers import groundtruth_of_tried

    import softcrawl.codesign.evaluation as evaluation
    from softcrawl.cli import main
    from softcrawl.cli.deploy import policy_actions
    from softcrawl.codesign.groundtruth_regret import compute_regret, regret_markdown

    sl, (a, b, c) = _shortlisted(run, monkeypatch, lambda d: {
        d[0]: (1.0, False, [], []), d[1]: (0.5, False, [], []), d[2]: (2.5, False, [], [])})
    assert sl["candidates"][sl["chosen"]]["design"] == list(c)
    groundtruth_of_tried(run, tmp_path / "gt")
    r = compute_regret(run, tmp_path / "gt", policy=True)  # the policy's gait read from the shortlist
    assert r["choice"]["design"] == list(c) and r["choice"]["source"] == "shortlist"
    assert r["choice"]["candidates"] == [",".join(map(str, d)) for d in (a, b, c)]
    assert r["policy"]["reward_cm"] == 2.5 and r["policy"]["gait_source"] == "deterministic"
    assert "chosen design (the best gait of 3 shortlisted" in "\n".join(regret_markdown(r))
    seen = []
    monkeypatch.setattr(evaluation, "evaluate_policy",
                        lambda run_, design, **kw: seen.append(tuple(design)) or _stub(run, {
                            tuple(design): (1.0, False, [], [])})(run_, design, **kw))
    assert policy_actions(str(run), None)[1]["design"] == list(c) and seen == [c]
    with pytest.raises(ValueError, match="--checkpoint needs --design"):
        policy_actions(str(run), None, checkpoint="step-0000000160")
    monkeypatch.undo()  # `evaluate` re-simulates the chosen design with the real policy
    assert main(["evaluate", str(run), "--out", str(tmp_path / "ev"), "--samples", "0", "--no-animation",
                 "--no-progress"]) == 0
    assert json.loads((tmp_path / "ev" / "evaluation.json").read_text())["design"] == list(c)
    assert f"design {','.join(map(str, c))}: the run's design (the best gait of its shortlist)" in \
        capsys.readouterr().err


def test_a_run_without_a_shortlist_keeps_the_most_probable_design(run, tmp_path, monkeypatch, capsys):
    from helpers import groundtruth_of_tried

    import softcrawl.codesign.evaluation as evaluation
    from softcrawl.codesign.groundtruth_regret import compute_regret
    from softcrawl.codesign.report import _report_shortlist, write_report
    from softcrawl.codesign.run import Run

    best = most_probable(design_rows(run))["design"]
    d = run_design(run)
    assert d["design"] == best and d["source"] == "most probable" and "shortlist" not in d
    assert "has no shortlist of its last checkpoint" in capsys.readouterr().err
    groundtruth_of_tried(run, tmp_path / "gt")
    assert compute_regret(run, tmp_path / "gt", policy=False)["choice"]["design"] == list(best)
    md = (write_report(run, simulate=False) / "summary.md").read_text()
    assert "## Shortlist\n\nNone: this run has no shortlist" in md and "(the most probable)" in md
    assert not (run / "shortlist.json").exists()
    # a run of config format 6 (before the setting): a shortlist of 1, computed on demand by the report
    meta = json.loads((run / "config.json").read_text())
    del meta["config"]["shortlist"]
    (run / "config.json").write_text(json.dumps({**meta, "config_version": 6}))
    assert Run(run).read_config().shortlist == 1
    monkeypatch.setattr(evaluation, "evaluate_policy", _stub(run, {best: (0.5, False, [], [])}))
    sl, evs = _report_shortlist(Run(run), True, None, 0, None)
    assert [tuple(c["design"]) for c in sl["candidates"]] == [best] and len(evs) == 1
    assert read_shortlist(run) == sl


def test_a_stale_or_malformed_shortlist(run, monkeypatch):
    from softcrawl.codesign.run import Run

    sl, _ = _shortlisted(run, monkeypatch, lambda d: {x: (1.0, False, [], []) for x in d}, k=2)
    path = run / "shortlist.json"
    path.write_text(json.dumps({**sl, "checkpoint": "step-0000000120"}))  # of an earlier checkpoint: stale
    assert read_shortlist(run) is None and run_design(run)["source"] == "most probable"
    for bad in ("{", "[1]", json.dumps({**sl, "chosen": 2}), json.dumps({**sl, "format": 2}),
                json.dumps({**sl, "candidates": [{"design": [9] * 8, "gait_cm": 1.0, "gait_diverged": False}]})):
        path.write_text(bad)
        with pytest.raises(ValueError, match="shortlist.json: not a shortlist of this run") as err:
            read_shortlist(run)
        assert "\n" not in str(err.value)
    path.unlink()
    path.symlink_to(run / "config.json")
    with pytest.raises(ValueError, match="symbolic link"):
        Run(run).read_config()


def test_training_ends_with_the_shortlist(run, monkeypatch):
    import softcrawl.codesign.evaluation as evaluation
    import softcrawl.codesign.training as training
    from softcrawl.cli.train import train_and_report

    monkeypatch.setattr(training, "train", lambda out, *a, **k: training.TrainResult(run, 160, 1.0, 120))
    monkeypatch.setattr(evaluation, "evaluate_policy",
                        _stub(run, {d["design"]: (d["latest_cm"], False, [], []) for d in design_rows(run)}))
    train_and_report(run, resume=True, progress=False, report=False)
    sl = read_shortlist(run)
    assert sl is not None and sl["k"] == 2 and not (run / "report").exists()  # the smoke preset's


def test_the_shortlist_is_the_same_on_worker_processes(run):
    """Candidates evaluated in two worker processes give this process's shortlist to the bit (the
    same machine), and their detached evaluations re-simulate the chosen gait once given an env."""
    from softcrawl.codesign.shortlist import compute_shortlist

    def numbers(data):
        return {**data, "wall_seconds": None,
                "candidates": [{**c, "wall_seconds": None} for c in data["candidates"]]}

    here, evs_here = compute_shortlist(run, 2, 1, workers=1)
    there, evs_there = compute_shortlist(run, 2, 1, workers=2)
    assert numbers(there) == numbers(here) and len(here["candidates"]) == 2
    assert all(ev.env is not None for ev in evs_here) and all(ev.env is None for ev in evs_there)
    i = here["chosen"]
    a, b = evs_here[i], evs_there[i].with_env()
    assert b.env is not None and b.with_env() is b
    assert np.array_equal(b.gait_actions_kpa, a.gait_actions_kpa)
    assert b.resimulate(record_every=None).reward_cm == a.resimulate(record_every=None).reward_cm
