"""The report's training section (softcrawl.codesign.report_training), the paper's reward-histogram
figure: the histogram weighted by the design distribution over training and at points of it,
the best return so far, the mode switches, and the paper's designs L1-L5 placed in the run and in
a ground truth; from a crafted run folder (snapshots, distribution.csv, episodes.csv)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from softcrawl.codesign.config import override, preset
from softcrawl.codesign.distribution import GibbsDesignDistribution
from softcrawl.codesign.report_training import (
    PAPER_DESIGNS,
    histogram_points,
    mode_switches,
    paper_designs_section,
    training_section,
)
from softcrawl.codesign.run import Run
from softcrawl.design.space import DEFAULT_SPACE, PAPER_BEST_DESIGN

DESIGNS = preset("demo").env.designs()  # the 280 three-legged designs, the snapshots' order
A, B, C = DESIGNS[0], DESIGNS[1], DESIGNS[2]


def _s(d) -> str:
    return "".join(map(str, d))


def _crafted_run(folder):
    """A run folder with six snapshots (t = 100..600; A's return grows from 1 to 6 cm, B's stays
    2 cm, C's 0.5 cm, the rest untried), a distribution.csv with a uniform phase, a tie and
    switches A -> B -> A -> C, and episodes.csv with a diverged episode of +99 cm."""
    r = Run(folder)
    folder.mkdir()
    dist = GibbsDesignDistribution(DESIGNS)
    for t in range(100, 700, 100):
        dist.record([A, B, C], [t / 100.0, 2.0, 0.5])
        dist.beta = 0.0 if t == 100 else 1.0
        r.write_snapshot(dist, t)
    rows = [[100, 0, 5.6, 5.6, 5.6, 0, 0, f"{_s(A)}:0.00357 {_s(B)}:0.00357"],   # uniform: no mode
            [200, 1, 3.0, 3.0, 3.0, 0, 0, f"{_s(A)}:0.4 {_s(B)}:0.2"],          # A
            [300, 1, 2.0, 2.0, 2.0, 0, 0, f"{_s(B)}:0.4 {_s(A)}:0.4"],          # a tie: still A
            [400, 1, 1.0, 1.0, 1.0, 0, 0, f"{_s(B)}:0.6 {_s(A)}:0.3"],          # B
            [450, 1, 1.0, 1.0, 1.0, 0, 0, f"{_s(A)}:0.6 {_s(B)}:0.3"],          # A again
            [500, 1, 0.5, 0.5, 0.5, 0, 0, f"{_s(A)}:0.9 {_s(B)}:0.05"],
            [600, 1, 0.1, 0.1, 0.1, 0, 0, f"{_s(C)}:0.97 {_s(A)}:0.01"]]        # C, to the end
    with open(r.distribution_csv, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    eps = [(100, A, 1.0, 0), (200, B, 2.0, 0), (300, C, 99.0, 1), (400, A, 4.0, 0), (600, A, 6.0, 0)]
    with open(r.episodes_csv, "w", newline="") as f:
        csv.writer(f).writerows([t, _s(d), ret, bad] for t, d, ret, bad in eps)
    return r


def test_mode_switches_from_a_crafted_log(tmp_path):
    switches = mode_switches(_crafted_run(tmp_path / "run").read_distribution())
    assert [(s["t"], s["design"], s["p"], s["held_steps"]) for s in switches] == [
        (200, A, 0.4, 200), (400, B, 0.6, 50), (450, A, 0.6, 150), (600, C, 0.97, 0)]
    # labelled by when each first became the mode; a design's switches share its label
    assert [s["label"] for s in switches] == ["M1", "M2", "M1", "M3"]


def test_the_histogram_over_training_and_at_points_of_it(tmp_path):
    r = _crafted_run(tmp_path / "run")
    ep = r.read_episodes()
    data = [r.read_snapshot(p) for p in r.snapshots()]
    points = histogram_points(data, ep)
    assert [p["t"] for p in points] == [100, 200, 300, 500, 600]  # 5 of the 6 snapshots, first and last
    for p in points:
        assert p["mass"].sum() == pytest.approx(1.0) and len(p["edges"]) == 41
    assert points[0]["mode"] is None  # beta = 0: uniform
    assert DESIGNS[points[-1]["mode"]] == A and points[-1]["tried"] == 3
    w = np.exp([6.0, 2.0, 0.5])
    assert points[-1]["mean"] == pytest.approx(np.dot(w / w.sum(), [6.0, 2.0, 0.5]), rel=1e-5)
    # the best so far leaves the diverged +99 cm episode out
    assert [p["best_so_far"] for p in points] == [1.0, 2.0, 2.0, 4.0, 6.0]
    out = tmp_path / "out"
    out.mkdir()
    lines, numbers = training_section(r, ep, out, "cm", DEFAULT_SPACE, DESIGNS)
    for name in ("reward_histogram.png", "reward_histogram_points.png", "mode_switches.png", "returns.png"):
        assert (out / name).stat().st_size > 0, name
    md = "\n".join(lines)
    assert "| 100 | 3 | " in md and "| uniform (" in md
    assert f"| 600 | 3 | {points[-1]['mean']:+.3f} | `{','.join(map(str, A))}` (" in md and "| +6.000 |" in md
    assert "(4 times; M: the 3 designs that were the mode longest" in md
    assert f"| M2 | 400 | `{','.join(map(str, B))}` | 0.6 | 50 |" in md
    assert [s["design"] for s in numbers["mode_switches"]] == [",".join(map(str, d)) for d in (A, B, A, C)]
    assert numbers["points"][0]["mode"] is None and numbers["points"][-1]["mode"] == ",".join(map(str, A))


def test_a_damaged_distribution_log_leaves_the_mode_switches_out(tmp_path, capsys):
    r = _crafted_run(tmp_path / "run")
    r.distribution_csv.write_text("200,1,3,3,3,0,0,AB:x\n")
    out = tmp_path / "out"
    out.mkdir()
    lines, numbers = training_section(r, r.read_episodes(), out, "cm", DEFAULT_SPACE, DESIGNS)
    assert "distribution.csv, line 1: not a distribution row" in capsys.readouterr().err
    assert numbers["mode_switches"] == [] and "None: no design was more probable" in "\n".join(lines)
    assert (out / "reward_histogram.png").exists()


def _groundtruth(folder, rewards: dict) -> None:
    """A finished ground truth in ``folder`` with made-up rewards (cm) per design."""
    from softcrawl.codesign.groundtruth import DesignResult, GroundTruthConfig, PeriodicGait, run_groundtruth

    fake = lambda d, _cfg: DesignResult(tuple(d), rewards[tuple(d)], PeriodicGait.paper_cycle().to_dict(), 3,
                                        "step", 10, 2, 80.0, 0.1).to_dict()
    run_groundtruth(list(rewards), folder, GroundTruthConfig(baseline_phases=()), executor="serial", task=fake,
                    progress=False, refs=False)


def _rows(*designs_latest):
    return [{"design": d, "index": i, "latest_cm": r, "best_cm": r + 1, "prob": 0.1 * (i + 1), "episodes": 2}
            for i, (d, r) in enumerate(designs_latest)]


def test_the_papers_designs_placed_in_the_run_and_in_a_ground_truth(tmp_path):
    l1 = PAPER_BEST_DESIGN
    assert [name for name, *_ in PAPER_DESIGNS] == ["L1", "L2", "L3", "L4", "L5"] and PAPER_DESIGNS[0][1] == l1
    rows = _rows((A, 7.0), (l1, 5.0), (B, 3.0))
    _groundtruth(tmp_path / "gt", {A: 2.0, l1: 9.0, B: 4.0, C: 1.0})
    lines, numbers = paper_designs_section(rows, preset("demo"), tmp_path / "gt")
    md = "\n".join(lines)
    assert "## The paper's designs (L1-L5)" in md and "ground truth: rank, reward" in md
    assert "| L1 | `1,0,0,2,2,0,0,0` | " in md and "| 2 of 3 | +5.000 | +6.000 | 0.2 | 1 of 4, +9.00 cm |" in md
    assert md.count("| not named |") == 4
    assert numbers[0] == {"name": "L1", "design": "1,0,0,2,2,0,0,0", "rank": 2, "of": 3, "latest": 5.0, "best": 6.0,
                          "prob": 0.2, "groundtruth": {"rank": 1, "of": 4, "reward": 9.0, "unit": "cm"}}
    assert all(n["design"] is None and n["groundtruth"] is None for n in numbers[1:])
    # without a ground truth: the run's ranking only; L1 untried, or out of play (4-legged designs only)
    lines, numbers = paper_designs_section(_rows((A, 1.0)), preset("demo"))
    assert "| never tried |" in "\n".join(lines) and "ground truth" not in lines[-1]
    assert numbers[0]["run"] == "never tried"
    _, numbers = paper_designs_section(_rows((A, 1.0)), override(preset("demo"), ["env.legs=[4]"]))
    assert numbers[0]["run"] == "not in play"
    hex6 = override(preset("demo"), ['env.space="hex6"'])
    lines, numbers = paper_designs_section([], hex6)
    assert numbers == [] and "this run's is `hex6`" in lines[-1]
