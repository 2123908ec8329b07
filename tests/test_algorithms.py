"""Co-design algorithms behind one interface, scored on a ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cma")
pytest.importorskip("optuna")

from softcrawl.codesign.algorithms import (  # noqa: E402
    GibbsSACReplay,
    OptunaSearch,
    RandomSearch,
    best_so_far_on_grid,
    run_algorithm,
)
from softcrawl.codesign.groundtruth import (  # noqa: E402
    DesignResult,
    GroundTruthConfig,
    PeriodicGait,
    parse_designs,
    run_groundtruth,
)
from helpers import benchmark_module  # noqa: E402

DESIGNS = parse_designs("3")[:6]
GT = {d: float(i) for i, d in enumerate(DESIGNS)}  # the last design is the best
BEST = DESIGNS[-1]


def fake_eval(calls):
    def evaluate(design, gait, duration):
        calls.append((design, duration))
        # the design's ground truth reached by a gait at full pressure everywhere, less otherwise
        k = np.array([p for p in gait.patterns[0]])
        return GT[design] - 0.5 * float(np.mean(90 - k)) / 90
    return evaluate


def test_random_search_visits_each_design_with_its_gait_budget():
    calls = []
    algo = RandomSearch(DESIGNS, 2.0, evals_per_design=7, cycles=(3,), seed=0)
    tr = run_algorithm(algo, fake_eval(calls), GT, budget_seconds=len(DESIGNS) * 7 * 2.0)
    per = {}
    for d, T in calls:
        per[d] = per.get(d, 0) + 1
    assert per == {d: 7 for d in DESIGNS}  # every design once, 7 CMA-ES episodes each
    assert tr["sim_seconds"][-1] == pytest.approx(len(DESIGNS) * 14.0) and tr["episodes"] == 42
    assert tuple(tr["incumbent"][-1]) == BEST and tr["gt_cm"][-1] == GT[BEST]
    g = np.asarray(tr["gt_cm"])
    assert np.all(np.diff(g[np.isfinite(g)]) >= 0)  # incumbent by best return: never worse here


@pytest.mark.parametrize("sampler", ["tpe", "ga"])
def test_optuna_search_finds_best_design(sampler):
    calls = []
    algo = OptunaSearch(DESIGNS, 1.0, cycles=(2, 3), sampler=sampler, seed=1, population=8)
    tr = run_algorithm(algo, fake_eval(calls), GT, budget_seconds=60.0)
    assert len(calls) == 60 and all(T == 1.0 for _, T in calls)
    assert tuple(tr["incumbent"][-1]) == BEST


def test_unknown_sampler():
    with pytest.raises(ValueError):
        OptunaSearch(DESIGNS, 1.0, sampler="bo")


def _fake_run(path: Path, rows):
    path.mkdir()
    (path / "config.json").write_text(json.dumps({"config": {"n_envs": 2, "env": {"n_actions": 8,
                                                                               "steps_per_action": 50, "dt": 0.01}}}))
    (path / "episodes.csv").write_text("".join(f"{t},{''.join(map(str, d))},{r},0\n" for t, d, r in rows))
    return path


def test_gibbs_sac_replay(tmp_path):
    a, b, c = DESIGNS[0], DESIGNS[1], DESIGNS[5]
    run = _fake_run(tmp_path / "run", [(16, a, 1.0), (16, b, 2.0), (32, b, 0.5), (32, c, 0.7),
                                       (48, (1, 0, 0, 2, 2, 0, 0, 1), 9.0)])
    algo = GibbsSACReplay(run, DESIGNS)
    tr = run_algorithm(algo, None, GT, float("inf"))
    assert tr["sim_seconds"] == [8.0, 16.0, 20.0]  # 4 s episodes, batches of n_envs = 2
    # b's latest return fell to 0.5: the Gibbs distribution now prefers c (0.7), then a (1.0);
    # the 4-legged design is outside the design set: it costs time but cannot be chosen
    assert [tuple(i) for i in tr["incumbent"]] == [b, a, a]
    with pytest.raises(ValueError):
        GibbsSACReplay(tmp_path)


def test_best_so_far_on_grid():
    tr = {"sim_seconds": [10, 20, 30], "gt_cm": [1.0, 1.0, 3.0]}
    np.testing.assert_array_equal(best_so_far_on_grid(tr, np.array([0, 10, 25, 40])), [np.nan, 1, 1, 3])


def test_benchmark_compare_and_plot(tmp_path):
    def task(d, c):
        return DesignResult(tuple(d), GT[tuple(d)], PeriodicGait.paper_cycle().to_dict(), 3, "step",
                            1, 1, 1.0, 0.0).to_dict()

    run_groundtruth(DESIGNS, tmp_path / "gt", GroundTruthConfig(baseline_phases=()), executor="serial", task=task,
                    progress=False, refs=False)
    run = _fake_run(tmp_path / "run", [(16, DESIGNS[0], 1.0), (16, BEST, 2.0)])
    bench = benchmark_module("codesign_algorithms")
    res = bench.compare(tmp_path / "gt", ["random", "tpe"], 3, 40.0, runs=[run, run, run], duration=1.0,
                        evals_per_design=5, cycles=(2,), evaluate=fake_eval([]), progress=False)
    assert set(res["summary"]) == {"random", "tpe", "gibbs-sac"}
    assert all(s["seeds"] == 3 for s in res["summary"].values())
    assert res["summary"]["gibbs-sac"]["final_gt_cm_mean"] == GT[BEST]
    bench.plot(res, tmp_path / "p.png")
    assert (tmp_path / "p.png").stat().st_size > 1000
    # results computed in separate processes merge into the same summary
    import json

    for name in ("random", "tpe"):
        part = {**res, "traces": {name: res["traces"][name]}}
        (tmp_path / name).mkdir()
        (tmp_path / name / "codesign_algorithms.json").write_text(json.dumps(part))
    merged = bench.merge(tmp_path / "gt", [tmp_path / "random", tmp_path / "tpe"])
    assert merged["summary"]["random"] == res["summary"]["random"] and set(merged["summary"]) == {"random", "tpe"}


def test_benchmark_keeps_finished_runs_and_grades_them_once_the_ground_truth_is_complete(tmp_path):
    """The algorithms may run while the ground truth is being computed (``designs``): their
    finished runs are kept in ``out/traces``, not recomputed by the same command, and graded
    against the ground truth as it stands when the summary is written."""
    def task(d, c):
        return DesignResult(tuple(d), GT[tuple(d)], PeriodicGait.paper_cycle().to_dict(), 3, "step",
                            1, 1, 1.0, 0.0).to_dict()

    gt = tmp_path / "gt"
    cfg = GroundTruthConfig(baseline_phases=())
    run_groundtruth(DESIGNS[:2], gt, cfg, executor="serial", task=task, progress=False, refs=False)
    bench = benchmark_module("codesign_algorithms")
    spec = ";".join(",".join(map(str, d)) for d in DESIGNS)
    calls = []
    kw = dict(duration=1.0, evals_per_design=5, cycles=(2,), evaluate=fake_eval(calls), progress=False,
              designs=spec, out=tmp_path / "out")
    first = bench.compare(gt, ["random"], 2, 40.0, **kw)
    assert first["designs"] == len(DESIGNS) and first["groundtruth_designs"] == 2
    assert len(sorted((tmp_path / "out" / "traces").glob("random-*.json"))) == 2 and calls
    n_calls = len(calls)
    run_groundtruth(DESIGNS, gt, cfg, executor="serial", task=task, progress=False, refs=False)
    again = bench.compare(gt, ["random"], 2, 40.0, **kw)
    assert len(calls) == n_calls  # nothing simulated again
    assert again["best_gt_cm"] == GT[BEST] and again["groundtruth_designs"] == len(DESIGNS)
    for tr in again["traces"]["random"]:
        assert tr["gt_cm"] == [GT[tuple(d)] for d in tr["incumbent"]]
    with pytest.raises(ValueError, match="other settings"):
        bench.compare(gt, ["random"], 2, 80.0, **kw)
