"""The ground truth of a whole design space (``softcrawl groundtruth --designs all``): the set is
the space's canonical designs, a batched engine searches a bounded number of them in lockstep in
order of leg count, a killed run resumes without losing a finished design, and ``regret`` places
a design among all 6,972. The searches are stubbed (one or two rounds of one episode, a reward
that depends on the design only) so that the paper's whole space runs in seconds."""

from __future__ import annotations

import json
import os

import pytest

import softcrawl.codesign.groundtruth_regret as rg
import softcrawl.codesign.groundtruth.runner as runner
import softcrawl.codesign.groundtruth.search as search
from groundtruth_helpers import reward
from softcrawl.cli import main as cli_main
from softcrawl.codesign.groundtruth import (
    DesignResult,
    GroundTruthConfig,
    PeriodicGait,
    design_set_spec,
    load_results,
    parse_designs,
    recorded_designs,
    run_groundtruth,
)
from softcrawl.design.resolve import resolve_space
from softcrawl.design.space import DEFAULT_SPACE, PAPER_BEST_DESIGN
from softcrawl.tasks import Forward

ALL = list(DEFAULT_SPACE.canonical_designs)
GAIT = PeriodicGait.paper_cycle()
SETTINGS = GroundTruthConfig(baseline_phases=())


def legs(design) -> int:
    return sum(v > 0 for v in design)


def quick_rounds(design, cfg, space=DEFAULT_SPACE):
    """A stub of :func:`~softcrawl.codesign.groundtruth.search.design_rounds`: one round of one
    episode (two rounds for an odd digit sum), the design's result the last episode's reward."""
    design = space.canonicalize(design)

    def rounds():
        replies = []
        for _ in range(1 + sum(design) % 2):
            replies += (yield [(GAIT, cfg.duration)])
        n = len(replies)
        return DesignResult(design, replies[-1][0], GAIT.to_dict(), 3, "step", n, n, n * cfg.duration, 0.0)

    return rounds()


class Engine:
    """A batched engine's stub: each episode's reward is :func:`reward` of its design; counts the
    calls and their designs; killed (KeyboardInterrupt) at call ``kill_at``."""

    def __init__(self, kill_at: int | None = None):
        self.calls: list[list] = []
        self.forgotten: list = []
        self.kill_at = kill_at

    def evaluate(self, requests):
        self.calls.append([d for d, _, _ in requests])
        if len(self.calls) == self.kill_at:
            raise KeyboardInterrupt
        return [(reward(d), False) for d, _, _ in requests]

    def forget(self, designs):
        self.forgotten += list(designs)


def test_all_is_every_canonical_design_of_the_space():
    assert parse_designs("all") == ALL and len(ALL) == 6972
    assert [sum(legs(d) == n for d in ALL) for n in (3, 4, 5, 6)] == [280, 980, 2296, 3416]
    assert design_set_spec(ALL[::-1]) == "all" and design_set_spec(ALL[1:]) != "all"
    hex6 = resolve_space("hex6")
    assert parse_designs("all", hex6) == list(hex6.canonical_designs) and len(hex6.canonical_designs) == 124


@pytest.fixture(scope="module")
def whole_space(tmp_path_factory):
    """A ground truth of all 6,972 designs, killed at its 4th call and resumed (``fsync`` skipped:
    the rows are appended as a real run appends them, 6,972 syncs would only cost time).
    Returns ``(folder, the rows before the kill, the killed run's engine, the resumed run's)``."""
    out = tmp_path_factory.mktemp("gt-all")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(search, "design_rounds", quick_rounds)
        mp.setattr(os, "fsync", lambda fd: None)
        killed = Engine(kill_at=4)
        with pytest.raises(KeyboardInterrupt):
            run_groundtruth(parse_designs("all"), out, SETTINGS, progress=False, refs=False,
                            evaluate_many=killed.evaluate, in_flight=1000)
        before = (out / "results.jsonl").read_text()
        resumed = Engine()
        run_groundtruth(None, out, None, progress=False, refs=False, evaluate_many=resumed.evaluate, in_flight=1000)
    return out, before, killed, resumed


def test_kill_and_resume_of_the_whole_space_loses_no_finished_design(whole_space):
    out, before, killed, resumed = whole_space
    finished = [tuple(json.loads(line)["design"]) for line in before.splitlines()]
    assert 1000 < len(finished) < 6972  # the kill came mid-run, after designs finished
    assert json.loads((out / "config.json").read_text())["designs"] == "all" and recorded_designs(out) == ALL
    # lockstep: at most 1,000 designs a call, three-legged ones first, then in order of leg count
    assert all(len(set(c)) <= 1000 for c in killed.calls + resumed.calls)
    asked = [legs(d) for c in killed.calls for d in c]
    assert asked[0] == 3 and max(asked) <= 5 and sorted(set(asked)) == [3, 4, 5]
    # the resumed run asked for no finished design, and every unfinished one
    again = {d for c in resumed.calls for d in c}
    assert not again & set(finished) and again == set(ALL) - set(finished)
    text = (out / "results.jsonl").read_text()
    assert text.startswith(before) and len(text.splitlines()) == 6972  # rows kept, none computed twice
    res = load_results(out)
    assert set(res) == set(ALL) and all(r.reward_cm == reward(d) for d, r in res.items())
    summary = json.loads((out / "summary.json").read_text())
    assert summary["designs"] == summary["requested"] == 6972
    assert {k: g["designs"] for k, g in summary["by_legs"].items()} == {"3": 280, "4": 980, "5": 2296, "6": 3416}
    best6 = max((d for d in ALL if legs(d) == 6), key=reward)
    assert summary["by_legs"]["6"]["best"]["reward_cm"] == reward(best6)
    md = (out / "summary.md").read_text()
    assert md.startswith("# Ground truth: 6972 of 6972 designs") and "## Best of each leg count" in md


def test_regret_against_the_whole_space(whole_space, monkeypatch, tmp_path, capsys):
    out = whole_space[0]
    rewards = {d: reward(d) for d in ALL}
    chosen = PAPER_BEST_DESIGN
    monkeypatch.setattr(rg, "run_choice", lambda run: {"design": chosen, "prob": 0.5, "latest_cm": 1.0, "episodes": 9})
    monkeypatch.setattr(rg, "run_space", lambda run: DEFAULT_SPACE)
    monkeypatch.setattr(rg, "run_task", lambda run: Forward())
    monkeypatch.setattr(rg, "run_settings", lambda run: rg.gt_settings(SETTINGS))
    args = ["regret", "RUN", "--groundtruth", str(out), "--no-policy", "--json", str(tmp_path / "r.json")]
    assert cli_main(args) == 0
    p = json.loads((tmp_path / "r.json").read_text())["placement"]
    assert p["of"] == 6972 and p["rank"] == 1 + sum(r > rewards[chosen] for r in rewards.values())
    assert p["regret_cm"] == pytest.approx(max(rewards.values()) - rewards[chosen])
    assert "of 6972" in capsys.readouterr().out


def test_cli_all_on_the_jax_engine_is_lockstep_in_flight(tmp_path, monkeypatch, capsys):
    """``--engine jax --designs all --in-flight 2000`` on the engine's stub: calls of at most
    2,000 designs, each finished design's state let go, the folder resumable with another
    ``--in-flight`` and the CPU engine refusing one."""
    engine = Engine()
    monkeypatch.setattr(search, "design_rounds", quick_rounds)
    monkeypatch.setattr(os, "fsync", lambda fd: None)
    monkeypatch.setattr(runner, "jax_evaluator", lambda cfg: engine)
    monkeypatch.setattr(runner, "references", lambda cfg: {})  # the paper gait's CPU episode: not this test's
    out = tmp_path / "gt"
    args = ["groundtruth", "--out", str(out), "--designs", "all", "--engine", "jax", "--baseline-phases", "none",
            "--no-progress"]
    assert cli_main([*args, "--in-flight", "2000"]) == 0
    assert max(len(set(c)) for c in engine.calls) == 2000 and sorted(engine.forgotten) == sorted(ALL)
    assert "6972 of 6972 designs done" in capsys.readouterr().out
    assert cli_main(["groundtruth", "--out", str(out), "--resume", "--in-flight", "8", "--no-progress"]) == 0
    assert cli_main(["groundtruth", "--out", str(tmp_path / "cpu"), "--designs", "3", "--in-flight", "8",
                     "--no-progress"]) == 2
    assert "in_flight" in capsys.readouterr().err
    assert not (tmp_path / "cpu").exists()
