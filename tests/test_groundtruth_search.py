"""The per-design search as a coroutine of rounds: driven one episode at a time
(``optimize_design``, ``design_search``) or many designs in lockstep, each call holding the
round of every design in flight (``search_many``), the same results; a small real-model budget keeps
the budget of the rows the code wrote before the search became a coroutine, and their best gait
crawls as far on any CPU, within half the reduced model's error budget."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from groundtruth_helpers import DESIGNS
from softcrawl.codesign.groundtruth import (
    DIVERGED_CM,
    DesignEvaluator,
    GroundTruthConfig,
    PeriodicGait,
    SerialEvaluateMany,
    cma_generations,
    design_rounds,
    design_search,
    drive,
    load_results,
    optimize_design,
    parse_designs,
    run_groundtruth,
    duty_knots,
    search_many,
    seed_knots,
)
from softcrawl.codesign.migrate import read_settings
from softcrawl.design.space import PAPER_BEST_DESIGN

pytest.importorskip("cma")

DATA = Path(__file__).parent / "data"
#: The search's mechanics are tested on the structured search (its episode counts); the duty
#: search adds episodes to it (test_the_duty_search_asks_the_structured_episodes_and_more).
CFG = GroundTruthConfig(cycles=(2, 3), evals_per_cycle=7, finalists=2, duration=20.0, screen_duration=5.0,
                        baseline_phases=(), seeds="structured")


class FakeEvaluator:
    """A design's episodes without simulating: a smooth, design-dependent reward of the gait
    (cm, proportional to the duration); one knot pattern diverges. Counts calls."""

    def __init__(self, design):
        self.w = np.asarray(design, float) + 1.0
        self.calls = 0

    def __call__(self, gait, duration):
        self.calls += 1
        p = np.array([gait.pressure_at(t) for t in np.arange(0.0, 6.0, 0.5)]) / 90.0
        if p[0, 0] > 0.99 and p[1, 0] > 0.99:
            return float("nan"), True
        return float(np.sin(p @ self.w[:3]).mean() * duration / 4 + p.std()), False


def _same(a, b) -> None:
    """Two results equal in every field but the wall time."""
    da, db = a.to_dict(), b.to_dict()
    da.pop("wall_seconds"), db.pop("wall_seconds")
    assert json.dumps(da) == json.dumps(db)


def test_design_search_asks_for_the_episodes_optimize_design_runs():
    ev, asked = FakeEvaluator(DESIGNS[0]), []
    search = design_search(DESIGNS[0], CFG)
    request = next(search)
    try:
        while True:
            asked.append(request)
            request = search.send(ev(*request))
    except StopIteration as stop:
        result = stop.value
    assert all(isinstance(g, PeriodicGait) for g, _ in asked)
    assert [t for _, t in asked] == [5.0] * 14 + [20.0] * 4  # 2 x 7 screening, 2 finalists x 2 waveforms
    assert result.evaluations == 18 and result.full_evaluations == 4 and result.wall_seconds == 0.0
    _same(result, optimize_design(DESIGNS[0], CFG, evaluator=FakeEvaluator(DESIGNS[0])))


def test_duty_knots_are_the_in_phase_duty_cycles_the_structured_seeds_lack():
    """The one-regulator design ``0,0,0,1,1,1,0,0`` crawls +24.90 cm inflating 2 knots of 3, and
    the structured seeds of a 3-knot run hold 1 of 3 (docs/results.md, "Ground truth")."""
    assert [d[:, 0].tolist() for d in duty_knots(1, 3)] == [[1.0, 1.0, 0.0]]
    assert duty_knots(1, 2) == []  # 1 of 2 knots is the structured "all together for half"
    for m, L in ((1, 4), (2, 3), (3, 4), (3, 5)):
        have = {s.tobytes() for s in seed_knots(m, L)}
        got = duty_knots(m, L)
        assert got and all(s.shape == (L, m) and s.tobytes() not in have for s in got)
        for k in range(1, L):  # every regulator inflated together for k knots: a seed or a duty cycle
            together = np.zeros((L, m))
            together[:k] = 1.0
            assert together.tobytes() in have | {s.tobytes() for s in got}
    with pytest.raises(ValueError, match="seeds must be one of"):
        GroundTruthConfig(seeds="random").validate()


@pytest.mark.parametrize("design", [(0, 0, 0, 1, 1, 1, 0, 0), (1, 0, 0, 2, 2, 0, 0, 0), (0, 0, 0, 1, 2, 3, 0, 0)])
def test_the_duty_search_asks_the_structured_episodes_and_more(design):
    """The same CMA-ES episodes, in the same rounds, with the duty cycles added to the first
    round and their best as one more finalist: its reward is never below the structured one's."""
    duty_cfg = dataclasses.replace(CFG, seeds="duty")
    asked = {}

    def rounds(cfg):
        ev, out = FakeEvaluator(design), []

        def answer(requests):
            out.append([(g.to_dict(), t) for g, t in requests])
            return [ev(g, t) for g, t in requests]
        return drive(design_rounds(design, cfg), answer), out

    (old, asked["structured"]), (new, asked["duty"]) = rounds(CFG), rounds(duty_cfg)
    m = max(design)
    duty = [(L, d) for L in CFG.cycles for d in duty_knots(m, L)]
    a, b = asked["structured"], asked["duty"]
    assert len(a) == len(b) and b[0][:len(a[0])] == a[0] and len(b[0]) == len(a[0]) + len(duty)
    assert b[1:-1] == a[1:-1] and b[-1][:len(a[-1])] == a[-1] and len(b[-1]) - len(a[-1]) in (0, 2)
    assert new.reward_cm >= old.reward_cm and new.evaluations == old.evaluations + len(b[0]) - len(a[0]) + \
        len(b[-1]) - len(a[-1])


def test_design_search_checks_before_the_first_request():
    with pytest.raises(ValueError, match="cycles"):
        design_search(DESIGNS[0], GroundTruthConfig(cycles=(12,)))
    with pytest.raises(ValueError):
        design_search((1, 0, 0, 9, 2, 0, 0, 0), CFG)


def test_a_diverged_or_non_finite_episode_scores_the_divergence_value():
    search = design_search(DESIGNS[0], GroundTruthConfig(cycles=(2,), evals_per_cycle=2, finalists=1,
                                                         screen_duration=None))
    next(search)
    search.send((float("nan"), False))  # non-finite: counted as diverged
    with pytest.raises(StopIteration) as stop:
        search.send((1.0, True))  # diverged, whatever its reward
        search.send((DIVERGED_CM, True))  # the smooth finalist
    r = stop.value.value
    assert r.diverged == 3 and r.reward_cm == DIVERGED_CM and r.per_cycle == {2: DIVERGED_CM}


def rounds_of(design, cfg) -> list[int]:
    """The sizes of the rounds of ``design``'s search under ``cfg`` with the fake episodes."""
    ev, sizes = FakeEvaluator(design), []

    def run(requests):
        sizes.append(len(requests))
        return [ev(*r) for r in requests]

    drive(design_rounds(design, cfg), run)
    return sizes


def test_design_rounds_ask_for_a_generation_of_every_cycle_at_once():
    """The rounds: the seeds of both cycle lengths, then a CMA-ES generation of each run still
    going, then the 4 finals; the episodes, flattened, are design_search's, one at a time."""
    ev, asked, sizes = FakeEvaluator(DESIGNS[1]), [], []

    def run(requests):
        sizes.append(len(requests))
        asked.extend(requests)
        return [ev(*r) for r in requests]

    result = drive(design_rounds(DESIGNS[1], CFG), run)
    # m = 2: 3 seeds per cycle; then 4 of 7 left for L = 2 (dim 4, popsize 8: one truncated
    # generation) and for L = 3 (dim 6, popsize 9: one truncated generation); then the finals
    assert sizes == [6, 8, 4] and result.evaluations == 18
    one = design_search(DESIGNS[1], CFG)
    request, flat = next(one), []
    with pytest.raises(StopIteration):
        while True:
            flat.append(request)
            request = one.send(FakeEvaluator(DESIGNS[1])(*request))
    assert [(g.to_dict(), t) for g, t in flat] == [(g.to_dict(), t) for g, t in asked]
    with pytest.raises(ValueError, match="1 replies to a round of 6"):
        search = design_rounds(DESIGNS[1], CFG)
        next(search)
        search.send([(1.0, False)])


def test_cma_runs_advanced_together_draw_their_own_samples():
    """Two CMA-ES runs advanced generation by generation in turn give each the points it gives
    alone (cma's seed option reseeds numpy's global generator, which the runs would share)."""
    def f(x):
        return -float(np.sum((x - 0.3) ** 2))

    def alone(seed):
        return drive(cma_generations(4, 40, seed=seed), lambda xs: [f(x) for x in xs])

    a, b = cma_generations(4, 40, seed=1), cma_generations(4, 40, seed=2)
    xs = {a: next(a), b: next(b)}
    got = {}
    while xs:
        for run in list(xs):
            try:
                xs[run] = run.send([f(x) for x in xs[run]])
            except StopIteration as stop:
                got[run] = stop.value
                del xs[run]
    for run, seed in ((a, 1), (b, 2)):
        assert [(x.tolist(), v) for x, v in got[run]] == [(x.tolist(), v) for x, v in alone(seed)]


def test_search_many_in_lockstep_equals_one_design_at_a_time():
    """Each call holds the round of every design in flight: as many calls as the longest search
    has rounds, and each design's result is the one-at-a-time search's."""
    calls = []
    serial = SerialEvaluateMany(CFG, make=FakeEvaluator)

    def evaluate_many(requests):
        calls.append([d for d, _, _ in requests])
        return serial(requests)

    designs = [*DESIGNS[:4], DESIGNS[0]]  # a duplicate is searched once
    got = list(search_many(designs, CFG, evaluate_many))
    assert sorted(r.design for r in got) == sorted(DESIGNS[:4])
    sizes = {d: rounds_of(d, CFG) for d in DESIGNS[:4]}
    assert len(calls) == max(map(len, sizes.values())) == 3
    for k, call in enumerate(calls):  # the designs' k-th rounds, in the designs' order
        assert call == [d for d in DESIGNS[:4] if k < len(sizes[d]) for _ in range(sizes[d][k])]
    for r in got:
        _same(r, optimize_design(r.design, CFG, evaluator=FakeEvaluator(r.design)))
        assert r.wall_seconds >= 0.0
    assert {d: e.calls for d, e in serial.evaluators.items()} == {d: 18 for d in DESIGNS[:4]}


def test_lockstep_of_the_default_budget_makes_few_large_calls():
    """8 designs with the default settings (4 cycle lengths x 36 screening episodes and 4 to 6
    duty cycles, 2 finalists and the best duty cycle): 8 calls of up to 269 episodes (the rounds
    of 6 to 8 per design), not 155 calls of 8."""
    cfg, calls = GroundTruthConfig(baseline_phases=()), []
    serial = SerialEvaluateMany(cfg, make=FakeEvaluator)
    designs = parse_designs("3")[::35]

    def evaluate_many(requests):
        calls.append(len(requests))
        return serial(requests)

    got = list(search_many(designs, cfg, evaluate_many))
    assert len(got) == 8 and sum(calls) == sum(r.evaluations for r in got) == 1240
    assert len(calls) == 8 and max(calls) == 269


def test_search_many_keeps_at_most_in_flight_designs():
    """``in_flight`` 4 of 8 designs: never more than 4 in a call; the next ones join together
    once 2 or fewer are left, and every design's result is still the one-at-a-time search's."""
    serial, calls = SerialEvaluateMany(CFG, make=FakeEvaluator), []
    designs = parse_designs("3")[::35]

    def evaluate_many(requests):
        calls.append(list(dict.fromkeys(d for d, _, _ in requests)))
        return serial(requests)

    got = list(search_many(designs, CFG, evaluate_many, in_flight=4))
    assert sorted(r.design for r in got) == sorted(designs)
    assert calls[0] == designs[:4] and all(len(c) <= 4 for c in calls)
    for before, now in zip(calls, calls[1:]):
        new = [d for d in now if d not in before]
        if new:  # newcomers, in the order given, only when half or fewer were left
            assert len(now) - len(new) <= 2 and new == [d for d in designs if d in new]
    for r in got:
        _same(r, optimize_design(r.design, CFG, evaluator=FakeEvaluator(r.design)))
    with pytest.raises(ValueError, match="in_flight must be a positive integer"):
        list(search_many(designs, CFG, evaluate_many, in_flight=0))


#: Settings under which the fake episodes give designs different numbers of rounds: ONE (one
#: regulator: 1 seed, then generations of 6) has 6 rounds, L1 (two: 3 seeds, generations of 8) 5.
UNEVEN = GroundTruthConfig(cycles=(2,), evals_per_cycle=20, finalists=2, screen_duration=None, baseline_phases=(),
                           seeds="structured")
ONE, L1 = (1, 1, 1, 0, 0, 0, 0, 0), PAPER_BEST_DESIGN


def test_search_many_yields_each_design_as_it_finishes():
    serial, calls = SerialEvaluateMany(UNEVEN, make=FakeEvaluator), []

    def evaluate_many(requests):
        calls.append(len(requests))
        return serial(requests)

    one, l1 = rounds_of(ONE, UNEVEN), rounds_of(L1, UNEVEN)
    assert len(one) == 6 and len(l1) == 5
    order = []
    for r in search_many([ONE, L1], UNEVEN, evaluate_many):
        assert len(calls) == len(rounds_of(r.design, UNEVEN))  # yielded after the call of its last round
        order.append(r.design)
        _same(r, optimize_design(r.design, UNEVEN, evaluator=FakeEvaluator(r.design)))
    assert order == [L1, ONE] and calls == [a + b for a, b in zip(one, l1)] + one[5:]
    with pytest.raises(ValueError, match="answered 1 of"):
        list(search_many([L1, ONE], UNEVEN, lambda requests: serial(requests)[:1]))


def test_run_groundtruth_with_a_batched_engine_appends_and_resumes(tmp_path):
    serial, calls = SerialEvaluateMany(UNEVEN, make=FakeEvaluator), []

    def evaluate_many(requests):
        calls.append(len(requests))
        if len(calls) == 6 and kill["on"]:
            raise KeyboardInterrupt  # killed after L1 finished (5 rounds), before ONE did
        return serial(requests)

    kill = {"on": True}
    with pytest.raises(KeyboardInterrupt):
        run_groundtruth([L1, ONE], tmp_path, UNEVEN, progress=False, refs=False, evaluate_many=evaluate_many)
    assert set(load_results(tmp_path)) == {L1}  # appended as it finished
    kill["on"], calls[:] = False, []
    s = run_groundtruth([L1, ONE], tmp_path, None, progress=False, refs=False, evaluate_many=evaluate_many)
    assert calls == rounds_of(ONE, UNEVEN) and s["designs"] == 2  # only the unfinished design, searched again
    for d, r in load_results(tmp_path).items():
        _same(r, optimize_design(d, UNEVEN, evaluator=FakeEvaluator(d)))


#: cm: the most the stored best gait's reward may move on any CPU (its measurement:
#: :func:`test_small_real_budget_reproduces_the_rows_of_the_direct_search`).
REWARD_TOL_CM = 0.05


def test_small_real_budget_reproduces_the_rows_of_the_direct_search():
    """The reduced model, a small budget, with and without screening
    (``tests/data/groundtruth_small_budget.json``: each case's settings, in the format of the
    code before the search became a coroutine, and the row that code wrote). Driven one design
    at a time and in lockstep on this machine, the search gives the same row to the bit (the
    same episodes in the same order are the same floating-point operations). Against the stored
    row, what holds on any CPU: the budget (evaluations, full-length ones, simulated seconds,
    cycles tried: set by the settings, the finalists of continuous CMA-ES samples being
    distinct), no divergence, a finite reward, and the stored gait's reward recomputed here
    within :data:`REWARD_TOL_CM` of the stored one. Which gait CMA-ES ends on follows its
    rewards' round-off, so the row's own gait and reward are not compared.
    The tolerance: 0.5 mm of crawl, half the reduced model's validated error budget (mean node
    error <= 1 mm, docs/reduction.md); measured, the stored gait's reward on three CPUs within
    0.0019 cm of each other, and within 0.0031 cm of the stored one after settling from 20
    starts translated by 1e-12 mm in random directions."""
    cases = json.loads((DATA / "groundtruth_small_budget.json").read_text())
    for case in cases:
        cfg = GroundTruthConfig.from_dict(read_settings("groundtruth", {"config": case["config"]}))
        direct = optimize_design(PAPER_BEST_DESIGN, cfg).to_dict()
        (lockstep,) = search_many([PAPER_BEST_DESIGN], cfg, SerialEvaluateMany(cfg))
        lockstep = lockstep.to_dict()
        for got in (direct, lockstep):
            got.pop("wall_seconds")
        assert json.dumps(direct) == json.dumps(lockstep)
        expect = case["result"]
        assert sorted(direct) == sorted(expect) and direct["design"] == expect["design"]
        for key in ("evaluations", "full_evaluations", "sim_seconds", "diverged"):
            assert direct[key] == expect[key], key
        assert sorted(map(str, direct["per_cycle"])) == sorted(expect["per_cycle"]) and np.isfinite(direct["reward_cm"])
        reward, diverged = DesignEvaluator(PAPER_BEST_DESIGN, cfg)(PeriodicGait.from_dict(expect["gait"]), cfg.duration)
        assert not diverged and abs(reward - expect["reward_cm"]) <= REWARD_TOL_CM, (reward, expect["reward_cm"])
