"""Ground truth of the design space: gait family, CMA-ES, per-design optimizer,
resumable runs, regret."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from groundtruth_helpers import DESIGNS, fake_task, make_folder
from softcrawl.cli import main as cli_main
from softcrawl.codesign import groundtruth_regret as rg
from softcrawl.codesign.groundtruth import (
    GroundTruthConfig,
    PeriodicGait,
    cma_maximize,
    competition_ranks,
    load_results,
    optimize_design,
    parse_designs,
    read_config,
    run_groundtruth,
    spearman,
)
from softcrawl.design.space import PAPER_BEST_DESIGN
from softcrawl.gaits import SineGait, paper_best_gait

pytest.importorskip("cma")

L1 = PAPER_BEST_DESIGN


# -- gait family ---------------------------------------------------------------------------------
@pytest.mark.parametrize("phase", [0.0, 37.0, 90.0, 110.0, 180.0, 275.0, 359.0])
def test_family_holds_expert_sine_at_any_phase(phase):
    g, ref = PeriodicGait.expert_sine(phase), SineGait(phase_deg=phase)
    for t in np.linspace(-2.0, 21.0, 937):
        np.testing.assert_allclose(g.pressure_at(t), ref.pressure_at(t), atol=1e-9)
    assert g.period == 4.0


def test_family_holds_paper_three_second_cycle():
    g, ref = PeriodicGait.paper_cycle(), paper_best_gait()
    dt = 0.01
    for k in range(2000):  # every step of a 20 s episode, as run_episode queries it
        np.testing.assert_array_equal(g.pressure_at(k * dt), ref.pressure_at(k * dt))
    assert g.period == 3.0


def test_step_and_smooth_waveforms_and_per_regulator_lengths():
    g = PeriodicGait(((0, 90), (10, 20, 30), (5,)))
    assert g.period == 6.0
    np.testing.assert_allclose(g.pressure_at(0.5), [0, 10, 5])
    np.testing.assert_allclose(g.pressure_at(1.0), [90, 20, 5])
    np.testing.assert_allclose(g.pressure_at(4.99), [0, 20, 5])
    s = g.with_waveform("smooth")
    for i in range(6):  # smooth passes through the knots
        np.testing.assert_allclose(s.pressure_at(float(i)), g.pressure_at(float(i)), atol=1e-9)
    assert 0 < s.pressure_at(0.5)[0] < 90  # and between them moves continuously
    assert PeriodicGait.from_dict(json.loads(json.dumps(g.to_dict()))).to_dict() == g.to_dict()


@pytest.mark.parametrize("bad", [((0, 91), (0,), (0,)), (), (tuple(range(9)), (0,), (0,)),
                                 ((0, float("nan")), (0,), (0,))])
def test_bad_gaits_raise(bad):
    with pytest.raises(ValueError):
        PeriodicGait(bad)
    with pytest.raises(ValueError):
        PeriodicGait(((0,), (0,), (0,)), waveform="square")


# -- CMA-ES ----------------------------------------------------------------------------------------
def test_cma_finds_best_phase_of_a_1d_problem():
    calls = []

    def f(x):
        calls.append(1)
        return math.cos(2 * math.pi * (x[0] - 0.37))

    x, v, hist = cma_maximize(f, 1, 40, seed=1)
    assert abs(x[0] - 0.37) < 0.01 and v > 0.998
    assert len(calls) == len(hist) == 40  # exactly the budget


def test_cma_reaches_bounds_and_uses_seeds():
    f = lambda x: -float(np.sum((x - np.array([0.0, 1.0, 0.2])) ** 2))  # noqa: E731
    x, v, _ = cma_maximize(f, 3, 150, seed=0)
    np.testing.assert_allclose(x, [0.0, 1.0, 0.2], atol=0.02)
    # an exact seed is evaluated exactly, first
    _, v, hist = cma_maximize(f, 3, 10, seeds=[np.array([0.0, 1.0, 0.2])])
    assert v == 0.0 and hist[0][1] == 0.0


# -- per-design optimizer ------------------------------------------------------------------------
class FakeEvaluator:
    """Reward peaked at the paper's 3-s cycle (step, cm scales with duration); counts calls."""

    def __init__(self):
        self.calls = []

    def __call__(self, gait, duration):
        self.calls.append(duration)
        t = np.arange(0, 6, 0.5)
        ref = PeriodicGait.paper_cycle()
        err = np.mean([np.abs(gait.pressure_at(x) - ref.pressure_at(x)).sum() for x in t]) / 90
        return (10.0 - 5 * err) * duration / 20, False


def test_optimizer_finds_paper_cycle_and_counts_episodes():
    cfg = GroundTruthConfig(cycles=(2, 3), evals_per_cycle=12, finalists=2, duration=20.0, screen_duration=5.0,
                            seeds="structured")  # the duty search's extra episodes: test_groundtruth_search.py
    ev = FakeEvaluator()
    r = optimize_design(L1, cfg, evaluator=ev)
    assert r.reward_cm == pytest.approx(10.0) and r.cycle == 3 and r.waveform == "step"
    np.testing.assert_allclose(PeriodicGait.from_dict(r.gait).patterns, PeriodicGait.paper_cycle().patterns)
    # 2 cycles x 12 screening episodes + 2 finalists x (step, smooth) at full length
    assert ev.calls.count(5.0) == 24 and ev.calls.count(20.0) == 4
    assert r.evaluations == 28 and r.full_evaluations == 4 and r.sim_seconds == 24 * 5 + 4 * 20
    assert r.screen_cm == pytest.approx(2.5)


def test_optimizer_without_screening_reuses_step_rewards():
    cfg = GroundTruthConfig(cycles=(3,), evals_per_cycle=6, finalists=1, screen_duration=None, seeds="structured")
    ev = FakeEvaluator()
    r = optimize_design(L1, cfg, evaluator=ev)
    assert ev.calls == [20.0] * 7 and r.full_evaluations == 7  # 6 search + smooth finalist
    assert r.reward_cm == pytest.approx(10.0)


def test_parse_designs():
    assert len(parse_designs("3")) == 280 and len(parse_designs("3,4")) == 1260
    assert parse_designs("2,0,0,1,1,0,0,0; 1,0,0,2,2,0,0,0") == [L1]
    with pytest.raises(ValueError):
        parse_designs("1,0,0")
    with pytest.raises(ValueError):
        parse_designs("7")


def test_spearman():
    assert spearman([1, 2, 3, 4], [10, 20, 30, 40]) == pytest.approx(1.0)
    assert spearman([1, 2, 3, 4], [4, 3, 2, 1]) == pytest.approx(-1.0)


# -- resumable runs --------------------------------------------------------------------------------
def test_resume_never_recomputes_a_finished_design(tmp_path):
    calls = []

    def task(d, c):
        calls.append(d)
        if len(calls) == 3 and kill["on"]:
            raise KeyboardInterrupt  # the run is killed while the 3rd design runs
        return fake_task(d, c)

    kill = {"on": True}
    cfg = GroundTruthConfig(baseline_phases=())
    with pytest.raises(KeyboardInterrupt):
        run_groundtruth(DESIGNS, tmp_path, cfg, executor="serial", task=task, progress=False, refs=False)
    assert len(load_results(tmp_path)) == 2
    with open(tmp_path / "results.jsonl", "a") as f:  # a line torn by the kill
        f.write('{"design": [1, 1, 1')
    kill["on"], calls[:] = False, []
    s = run_groundtruth(DESIGNS, tmp_path, cfg, executor="serial", task=task, progress=False, refs=False)
    assert calls == DESIGNS[2:]  # only the unfinished designs
    lines = (tmp_path / "results.jsonl").read_text().splitlines()
    assert s["designs"] == 5 and len(lines) == 6  # the torn line is left in place, on a line of its own
    assert lines[2] == '{"design": [1, 1, 1' and len(s["bad_rows"]) == 1 and "line 3" in s["bad_rows"][0]
    calls[:] = []
    run_groundtruth(DESIGNS, tmp_path, None, executor="serial", task=task, progress=False, refs=False)
    assert calls == []
    rows = (tmp_path / "groundtruth.csv").read_text().splitlines()
    assert rows[0].startswith("rank,design,reward_cm") and len(rows) == 6
    import csv
    rewards = [float(r["reward_cm"]) for r in csv.DictReader(rows)]
    assert rewards == sorted(rewards, reverse=True)
    assert (tmp_path / "ranked.png").stat().st_size > 1000
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["best"][0]["reward_cm"] == max(fake_task(d, None)["reward_cm"] for d in DESIGNS)


def test_other_settings_in_same_folder_is_an_error(tmp_path):
    run_groundtruth(DESIGNS[:1], tmp_path, GroundTruthConfig(baseline_phases=()), executor="serial",
                    task=fake_task, progress=False, refs=False)
    with pytest.raises(ValueError, match="other settings"):
        run_groundtruth(DESIGNS[:1], tmp_path, GroundTruthConfig(evals_per_cycle=3, baseline_phases=()),
                        executor="serial", task=fake_task, progress=False, refs=False)


def test_cli_errors(tmp_path, capsys):
    assert cli_main(["groundtruth", "--out", str(tmp_path / "a"), "--designs", "1,0,0,9,2,0,0,0"]) == 2
    assert cli_main(["groundtruth", "--out", str(tmp_path / "a"), "--designs", "3", "--cycles", "2,12"]) == 2
    assert cli_main(["groundtruth", "--out", str(tmp_path / "b"), "--resume"]) == 2
    assert "error" in capsys.readouterr().err


TINY = ["--cycles", "2", "--evals-per-cycle", "3", "--finalists", "1", "--duration", "1.0",
        "--screen-duration", "0.5", "--disk-mesh-size", "25", "--baseline-phases", "90"]


def test_cli_real_run_in_two_processes_and_resume(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SOFTCRAWL_CACHE_DIR", str(tmp_path / "cache"))
    out = tmp_path / "gt"
    designs = "1,0,0,2,2,0,0,0;1,1,1,0,0,0,0,0"
    assert cli_main(["groundtruth", "--out", str(out), "--designs", designs, "--workers", "2",
                     "--no-progress", "--seeds", "structured", *TINY]) == 0
    assert read_config(out).seeds == "structured"  # saved, and kept by --resume below
    res = load_results(out)
    assert set(res) == {L1, (1, 1, 1, 0, 0, 0, 0, 0)}
    for r in res.values():  # 2 x 3 screening + (step, smooth) finals
        assert r.evaluations == 5 and r.full_evaluations == 2 and math.isfinite(r.reward_cm)
    refs = json.loads((out / "references.json").read_text())
    assert set(refs) == {"expert_baseline", "paper_l1_gait"}
    summary = json.loads((out / "summary.json").read_text())
    other = res[(1, 1, 1, 0, 0, 0, 0, 0)].reward_cm  # the rank from the two rewards, computed here
    assert summary["paper_l1"]["rank"] == (1 if res[L1].reward_cm >= other else 2)
    assert summary["paper_l1"]["reward_cm"] == res[L1].reward_cm
    before = (out / "results.jsonl").read_text()
    assert cli_main(["groundtruth", "--out", str(out), "--designs", designs, "--resume", "--no-progress"]) == 0
    assert (out / "results.jsonl").read_text() == before  # nothing recomputed
    assert "paper L1: rank" in capsys.readouterr().out


# -- regret ----------------------------------------------------------------------------------------
def test_regret_of_a_run(tmp_path, monkeypatch):
    gt = make_folder(tmp_path / "gt")
    rewards = {d: fake_task(d, None)["reward_cm"] for d in DESIGNS}
    order = sorted(DESIGNS, key=lambda d: -rewards[d])
    chosen = order[2]
    monkeypatch.setattr(rg, "run_choice", lambda run: {"design": chosen, "prob": 0.9, "latest_cm": 1.0, "episodes": 7})
    monkeypatch.setattr(rg, "policy_reward", lambda run, d: {"reward_cm": 3.25, "diverged": False, "actions_kpa": [],
                                                              "episode_seconds": 20.0, "hold_s": 1.0})
    monkeypatch.setattr(rg, "run_settings", lambda run: rg.gt_settings(GroundTruthConfig()) | {"disk_mesh_size": 25.0})
    lines, r = rg.regret_section("RUN", gt)
    p = r["placement"]
    assert p["rank"] == 3 and p["of"] == 5 and p["percentile"] == pytest.approx(60.0)
    assert p["regret_cm"] == pytest.approx(rewards[order[0]] - rewards[chosen])
    assert r["settings_differ"] == {"disk_mesh_size": [25.0, 10.0]}
    text = "\n".join(lines)
    assert "3 of 5" in text and "+3.25 cm" in text and "different episodes" in text
    # the CLI
    monkeypatch.setattr("softcrawl.codesign.groundtruth_regret.run_choice",
                        lambda run: {"design": (1, 0, 0, 0, 0, 0, 0, 0), "prob": 1, "latest_cm": 0, "episodes": 1})
    assert cli_main(["regret", "RUN", "--groundtruth", str(gt), "--no-policy"]) == 2  # 1 leg: invalid design
    assert cli_main(["regret", "RUN", "--groundtruth", str(tmp_path / "nope")]) == 2


def test_place_design_unknown(tmp_path):
    gt = make_folder(tmp_path)
    with pytest.raises(ValueError, match="not in the ground truth"):
        rg.place_design((1, 0, 0, 2, 2, 0, 0, 1), gt)


def test_tied_designs_share_a_rank_in_every_table(tmp_path):
    """Regression: ``groundtruth.csv`` numbered tied designs 1, 2, 3... while ``regret`` (and the
    docs) gave them one rank. Three designs of one reward (as one-regulator gaits on designs that
    differ only in regulator labels give, to the bit) now share it in the table, the summary's
    ``best`` and ``place_design``, and the next design's rank skips them."""
    import csv

    tied = {DESIGNS[1], DESIGNS[2], DESIGNS[3]}
    gt = make_folder(tmp_path, task=lambda d, c: {**fake_task(d, c), "reward_cm": 5.0 if tuple(d) in tied
                                                   else 9.0 if tuple(d) == DESIGNS[0] else 1.0})
    with open(gt / "groundtruth.csv", newline="") as f:
        table = {r["design"]: int(r["rank"]) for r in csv.DictReader(f)}
    text = ",".join
    assert table == {text(map(str, DESIGNS[0])): 1, **{text(map(str, d)): 2 for d in tied},
                     text(map(str, DESIGNS[4])): 5}
    summary = json.loads((gt / "summary.json").read_text())
    assert [b["rank"] for b in summary["best"]] == [1, 2, 2, 2, 5]
    assert {d: rg.place_design(d, gt)["rank"] for d in DESIGNS} == {tuple(map(int, k.split(","))): v
                                                                    for k, v in table.items()}
    with pytest.raises(ValueError, match="sorted best first"):
        competition_ranks([1.0, 2.0])
