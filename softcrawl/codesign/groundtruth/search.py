"""The per-design gait search: CMA-ES (the ``cma`` package) over the knots of a periodic gait.

For each cycle length ``L`` in :attr:`GroundTruthConfig.cycles` a CMA-ES run over the knots of
the regulators the design uses (``m L`` numbers in [0, 90] kPa, step waveform),
``evals_per_cycle`` episodes each, started from the best of a few structured gaits evaluated
first (:func:`seed_knots`); the ``finalists`` best distinct candidates, and the smooth variant
of each, are then re-run with full ``duration`` episodes (module docstring of
:mod:`softcrawl.codesign.groundtruth`).

The search of one design is a coroutine that asks for episodes and is told their rewards, so
that any engine can run them. It asks in rounds (:func:`design_rounds`): every episode it can
ask for before it needs an answer, i.e. the structured seeds of all cycle lengths, then one
CMA-ES generation of each cycle length's run (the runs are independent), then all the finals;
6 to 8 rounds of up to about 50 episodes with the default settings. One design on the CPU runs them one
after another (:func:`softcrawl.codesign.groundtruth.optimize.optimize_design`); many designs
advance in lockstep (:func:`search_many`), the round of every design in flight in one batched
call. :func:`design_search` is the same search asking for one episode at a time.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import math
import time
import typing
from collections.abc import Callable, Iterable, Iterator, Sequence

import numpy as np

from softcrawl.codesign.groundtruth.config import GroundTruthConfig
from softcrawl.codesign.groundtruth.result import DIVERGED_CM, DesignResult
from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.gaits.periodic import WAVEFORMS, PeriodicGait
from softcrawl.gaits.pressure import P_MAX_KPA


def used_regulators(design, space: DesignSpace = DEFAULT_SPACE) -> int:
    """Regulators a canonical design of ``space`` uses (canonical labels are 1..m), m.

    Raises:
        InvalidDesignError: ``design`` is not a design of ``space``.
    """
    return max(space.canonicalize(design))


def seed_knots(m: int, L: int) -> list[np.ndarray]:
    """Structured starting gaits ``(L, m)`` in units of 90 kPa for CMA-ES: each order of the
    ``m`` regulators inflating one after another then venting (the paper's cycle is one), all
    together for half the cycle, and for ``L = 4`` the expert's sine samples at lags 90/180/270 deg."""
    seeds = []
    for perm in itertools.permutations(range(m)):
        s = np.zeros((L, m))
        for i, r in enumerate(perm[: max(1, L - 1)]):
            s[i, r] = 1.0
        seeds.append(s)
    s = np.zeros((L, m))
    s[: max(1, L // 2)] = 1.0
    seeds.append(s)
    if L == 4 and m >= 2:
        for lag in (1, 2, 3):
            base = 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(L) / L)
            s = np.zeros((L, m))
            s[:, 0], s[:, 1] = base, np.roll(base, lag)
            seeds.append(s)
    return _distinct(seeds)


def duty_knots(m: int, L: int) -> list[np.ndarray]:
    """The bang-bang duty cycles ``(L, m)`` (units of 90 kPa) that :func:`seed_knots` lacks:
    every regulator inflated together for the first ``k`` of the ``L`` knots, then vented
    (``k = 1 .. L - 1``). A CMA-ES run of a few dozen episodes started from the structured
    seeds does not reach every corner of the box, where the best gaits of one-regulator designs
    lie (docs/results.md, "Ground truth", measures it); the ``"duty"`` search
    (:attr:`GroundTruthConfig.seeds`) screens these besides its CMA-ES runs."""
    seeds = seed_knots(m, L)
    duty = [np.zeros((L, m)) for _ in range(1, L)]
    for k, s in enumerate(duty, 1):
        s[:k] = 1.0
    return _distinct(seeds + duty)[len(seeds):]


def _distinct(seeds: list[np.ndarray]) -> list[np.ndarray]:
    """``seeds`` without repeats (to 1e-6), in order."""
    uniq, seen = [], set()
    for s in seeds:
        key = s.round(6).tobytes()
        if key not in seen:
            seen.add(key)
            uniq.append(s)
    return uniq


def knots_to_gait(x: np.ndarray, m: int, L: int, hold: float, waveform: str = "step",
                  n_regulators: int = DEFAULT_SPACE.n_regulators) -> PeriodicGait:
    """CMA-ES vector ``(m L,)`` in [0, 1] -> gait of ``n_regulators`` regulators (the design
    space's ``R >= m``; regulators beyond m stay at 0 kPa)."""
    k = np.zeros((L, n_regulators))
    k[:, :m] = np.clip(np.asarray(x, float).reshape(L, m), 0.0, 1.0) * P_MAX_KPA
    return PeriodicGait.from_knots(k, hold, waveform)


def cma_generations(dim: int, budget: int, seeds: Sequence[np.ndarray] = (), x0: float | np.ndarray = 0.5,
                    sigma0: float = 0.3, popsize: int | None = None,
                    seed: int = 0) -> typing.Generator[list[np.ndarray], list[float], list]:
    """CMA-ES (``cma``) maximizing over ``[0, 1]^dim`` as a generator of rounds: it yields lists
    of points ``(dim,)`` (first the seeds, then each generation) and is sent the list of their
    values; exactly ``budget`` points (the last generation truncated). ``seeds`` (points in
    [0, 1]^dim) come first (at most ``budget // 2`` of them) and CMA-ES starts at the best one
    (else at ``x0``). CMA-ES searches ``[-0.15, 1.15]^dim`` clipped to ``[0, 1]`` so that the
    bounds (vent, full pressure) are reached; it restarts around the best point with half the
    step if it converges early. ``dim == 1`` searches a dummy second coordinate (cma needs 2).
    Its samples come from a generator of its own (numpy's ``RandomState`` of ``seed``, the
    stream cma's ``seed`` option would give numpy's global one): runs advanced together do not
    change each other's points.

    Returns (``StopIteration.value``): the history ``[(x, value), ...]`` in evaluation order.

    Raises:
        ValueError: ``dim < 1`` or ``budget < 1``; a round answered with another number of values.
    """
    import cma

    if dim < 1 or budget < 1:
        raise ValueError(f"need dim >= 1 and budget >= 1, got {dim}, {budget}")
    n = max(dim, 2)

    def pad(x):
        x = np.ravel(np.asarray(x, float))
        return np.r_[x, np.full(n - len(x), 0.5)] if len(x) < n else x

    def ask(points: list[np.ndarray]):
        """Yield ``points`` (clipped to [0, 1], the first ``dim`` coordinates) and return their values."""
        values = yield [np.clip(x[:dim], 0.0, 1.0) for x in points]
        if len(values) != len(points):
            raise ValueError(f"{len(values)} values sent for {len(points)} points")
        history.extend((np.clip(x, 0.0, 1.0), float(v)) for x, v in zip(points, values))
        return [float(v) for v in values]

    history: list[tuple[np.ndarray, float]] = []
    first = [np.clip(pad(s), 0, 1) for s in seeds][: max(0, budget // 2)]
    if first:
        yield from ask(first)
    x0v = max(history, key=lambda h: h[1])[0] if history else (
        np.full(n, x0, float) if np.ndim(x0) == 0 else pad(x0))
    lo, hi = -0.15, 1.15
    rng_seed = int(seed) % (2**31 - 1) + 1

    def options() -> dict:
        # cma's own seeding reseeds numpy's global generator, which searches advanced together
        # would share: each run draws from a generator of its own (the same stream)
        return {"bounds": [lo, hi], "randn": np.random.RandomState(rng_seed).randn, "verbose": -9,
                "tolfun": 1e-9, "tolx": 1e-6, **({} if popsize is None else {"popsize": int(popsize)})}

    es = cma.CMAEvolutionStrategy(np.clip(x0v, lo + 1e-3, hi - 1e-3), sigma0, options())
    while len(history) < budget:
        xs = es.ask()[: budget - len(history)]
        vals = yield from ask(xs)
        if len(xs) < es.popsize:
            break
        es.tell(xs, [-v for v in vals])
        if es.stop() and len(history) < budget:  # converged early: restart around the best
            rng_seed += 1
            es = cma.CMAEvolutionStrategy(np.clip(max(history, key=lambda h: h[1])[0], lo + 1e-3, hi - 1e-3),
                                          sigma0 / 2, options())
    return [(x[:dim], v) for x, v in history]


def one_at_a_time(rounds: typing.Generator[list, list, typing.Any]) -> typing.Generator:
    """The coroutine ``rounds`` (it yields lists of requests and is sent lists of their
    answers, in order) asking for one request at a time: it yields each request and is sent
    its answer; returns what ``rounds`` returns."""
    try:
        requests = next(rounds)
        while True:
            answers = []
            for request in requests:
                answers.append((yield request))
            requests = rounds.send(answers)
    except StopIteration as stop:
        return stop.value


def cma_search(dim: int, budget: int, seeds: Sequence[np.ndarray] = (), x0: float | np.ndarray = 0.5,
               sigma0: float = 0.3, popsize: int | None = None, seed: int = 0):
    """:func:`cma_generations` asking for one point at a time: it yields points ``(dim,)`` and
    is sent their values (the same points, in the same order).

    Returns (``StopIteration.value``): the history ``[(x, value), ...]`` in evaluation order.

    Raises:
        ValueError: ``dim < 1`` or ``budget < 1``.
    """
    return one_at_a_time(cma_generations(dim, budget, seeds, x0, sigma0, popsize, seed))


def drive(gen, f: Callable):
    """Run a coroutine that yields requests and is sent their answers ``f(request)`` (a
    :func:`cma_search` with objective ``f``, a :func:`design_search` with an evaluator, a
    :func:`design_rounds` with a function answering a round's list) to its end; returns its
    return value."""
    try:
        x = next(gen)
        while True:
            x = gen.send(f(x))
    except StopIteration as stop:
        return stop.value


def cma_maximize(f: Callable[[np.ndarray], float], dim: int, budget: int, seeds: Sequence[np.ndarray] = (),
                 x0: float | np.ndarray = 0.5, sigma0: float = 0.3, popsize: int | None = None,
                 seed: int = 0) -> tuple[np.ndarray, float, list[tuple[np.ndarray, float]]]:
    """Maximize ``f`` over ``[0, 1]^dim`` with :func:`cma_search` (exactly ``budget`` calls).

    Returns:
        ``(best x, best f, history)``: history lists every ``(x, f(x))`` in evaluation order.

    Raises:
        ValueError: ``dim < 1`` or ``budget < 1``.
    """
    history = drive(cma_search(dim, budget, seeds, x0, sigma0, popsize, seed), f)
    best_x, best_v = max(history, key=lambda h: h[1])
    return best_x, best_v, history


def design_seed(design: Design, seed: int) -> int:
    """Deterministic per-design seed (independent of set order and Python's hash salt): the
    design's digits read in base ``max(4, largest value + 1)`` (base 4 for the paper's space)."""
    base = max(4, max(design) + 1)
    return (seed * 1_000_003 + sum(v * base**i for i, v in enumerate(reversed(design)))) % (2**31 - 2)


#: An episode a search asks for: ``(gait, duration s)``; its answer: ``(reward cm, diverged)``.
Request = tuple[PeriodicGait, float]
Reply = tuple[float, bool]


def design_rounds(design, cfg: GroundTruthConfig,
                  space: DesignSpace = DEFAULT_SPACE) -> typing.Generator[list[Request], list[Reply], DesignResult]:
    """The best gait of ``design`` in the family as a coroutine of rounds (the search of the
    module docstring): it yields lists of the episodes it needs, ``[(gait, duration), ...]``,
    and is sent each list's ``[(reward cm, diverged), ...]`` in the same order; a diverged
    episode (or a non-finite reward) scores :data:`DIVERGED_CM`. Its rounds: the seeds of every
    cycle length (:func:`seed_knots`), then a generation of each cycle length's CMA-ES run
    still going (:func:`cma_generations`; the runs are independent, each with its own seed),
    then the finals. Exactly ``len(cfg.cycles) * cfg.evals_per_cycle`` search episodes of
    ``cfg.screen_duration`` s (``cfg.duration`` without screening), then at most
    ``2 * cfg.finalists`` finals of ``cfg.duration`` s. The ``"duty"`` search
    (:attr:`GroundTruthConfig.seeds`) asks for those same episodes and, in the first round, the
    duty cycles (:func:`duty_knots`) of every cycle length, and its best duty cycle is a
    finalist too (2 finals more): its reward is never below the ``"structured"`` search's.

    The design and the settings are checked when this is called, before the first round.
    The gaits command the ``R`` regulators of ``space`` (the design's design space).

    Returns (``StopIteration.value``):
        :class:`DesignResult` with ``wall_seconds`` 0 (the driver knows the time it took).

    Raises:
        InvalidDesignError: invalid design. ValueError: invalid ``cfg``; a round answered with
            another number of replies than it asked for.
    """
    cfg.validate()
    return _rounds(space.canonicalize(design), cfg, space.n_regulators)


def design_search(design, cfg: GroundTruthConfig,
                  space: DesignSpace = DEFAULT_SPACE) -> typing.Generator[Request, Reply, DesignResult]:
    """:func:`design_rounds` asking for one episode at a time (:func:`one_at_a_time`): it
    yields ``(gait, duration)`` and is sent that episode's ``(reward cm, diverged)``; the same
    episodes in the same order, the same result. Checked as :func:`design_rounds`, when called.

    Raises:
        InvalidDesignError: invalid design. ValueError: invalid ``cfg``.
    """
    return one_at_a_time(design_rounds(design, cfg, space))


def _answered(replies: Sequence[Reply], requests: Sequence) -> Sequence[Reply]:
    """``replies``, checked to answer every one of ``requests`` (ValueError otherwise)."""
    if len(replies) != len(requests):
        raise ValueError(f"{len(replies)} replies to a round of {len(requests)} episodes")
    return replies


def _rounds(design: Design, cfg: GroundTruthConfig, n_reg: int) -> typing.Generator[list[Request], list[Reply],
                                                                                    DesignResult]:
    """The body of :func:`design_rounds` (a generator, run only once asked for its first round)."""
    m = max(design)  # canonical labels are 1..m (used_regulators)
    screen = cfg.screen_duration if cfg.screen_duration is not None and cfg.screen_duration < cfg.duration else None
    search_t = screen or cfg.duration
    n_eval, n_full, sim, n_div = 0, 0, 0.0, 0

    def score(reply: Reply, duration: float) -> float:
        nonlocal n_eval, n_full, sim, n_div
        r, div = float(reply[0]), bool(reply[1]) or not math.isfinite(reply[0])
        n_eval, n_full, sim, n_div = n_eval + 1, n_full + int(duration == cfg.duration), sim + duration, n_div + int(div)
        return DIVERGED_CM if div else r

    # the search: one CMA-ES run per cycle length, all advanced together
    runs = [cma_generations(m * L, cfg.evals_per_cycle, [s.ravel() for s in seed_knots(m, L)], sigma0=cfg.sigma0,
                            popsize=cfg.popsize, seed=design_seed(design, cfg.seed) + ci)
            for ci, L in enumerate(cfg.cycles)]
    # the "duty" search: the duty cycles screened in the first round, beside (not inside) the runs
    duty = [(int(L), s.ravel()) for L in cfg.cycles for s in duty_knots(m, L)] if cfg.seeds == "duty" else []
    duty_scored: list[tuple[float, int, np.ndarray]] = []
    asked = {ci: next(run) for ci, run in enumerate(runs)}  # each unfinished run's points of this round
    histories: dict[int, list] = {}
    while asked:
        current = list(asked.items())
        requests = [(knots_to_gait(x, m, cfg.cycles[ci], cfg.hold, n_regulators=n_reg), search_t)
                    for ci, xs in current for x in xs]
        extra = [(knots_to_gait(x, m, L, cfg.hold, n_regulators=n_reg), search_t) for L, x in duty]
        replies = _answered((yield requests + extra), requests + extra)
        duty_scored += [(score(reply, search_t), L, x) for reply, (L, x) in zip(replies[len(requests):], duty)]
        duty = []
        at = 0
        for ci, xs in current:
            values = [score(reply, search_t) for reply in replies[at:at + len(xs)]]
            at += len(xs)
            try:
                asked[ci] = runs[ci].send(values)
            except StopIteration as stop:
                del asked[ci]
                histories[ci] = stop.value
    candidates: list[tuple[float, int, np.ndarray]] = []  # (search reward, L, x)
    per_cycle = {}
    for ci, L in enumerate(cfg.cycles):
        per_cycle[int(L)] = max([h[1] for h in histories[ci]] + [v for v, Ld, _ in duty_scored if Ld == L])
        candidates += [(v, L, x) for x, v in histories[ci]]
    # finals: the best distinct candidates, step and smooth, with full episodes, in one round; then
    # the best duty cycle (the "duty" search), so that it only adds to what the runs found
    candidates.sort(key=lambda c: -c[0])
    finals, seen = [], set()
    for v, L, x in candidates:
        key = (L, np.round(x, 4).tobytes())
        if key not in seen:
            seen.add(key)
            finals.append((v, L, x))
        if len(finals) >= cfg.finalists:
            break
    if duty_scored:
        v, L, x = max(duty_scored, key=lambda c: c[0])  # ties: the first
        if (L, np.round(x, 4).tobytes()) not in seen:
            finals.append((v, L, x))
    trials = [(v, L, wf, knots_to_gait(x, m, L, cfg.hold, wf, n_reg)) for v, L, x in finals for wf in WAVEFORMS]
    known = [wf == "step" and screen is None for _, _, wf, _ in trials]  # the search ran it at full length
    requests = [(gait, cfg.duration) for (*_, gait), k in zip(trials, known) if not k]
    replies = iter(_answered((yield requests), requests))
    best = None  # (full reward, screen reward, gait, L)
    for (v, L, wf, gait), k in zip(trials, known):
        r = v if k else score(next(replies), cfg.duration)
        if best is None or r > best[0]:
            best = (r, v if (wf == "step" and screen) else float("nan"), gait, L)
    r, sv, gait, L = best
    return DesignResult(design, float(r), gait.to_dict(), int(L), gait.waveform, n_eval, n_full, sim, 0.0,
                        float(sv), per_cycle, n_div)


#: ``evaluate_many(requests) -> replies``: ``requests`` a list of ``(design, gait, duration s)``,
#: the replies ``(reward cm, diverged)`` in the same order.
EvaluateMany = Callable[[list[tuple[Design, PeriodicGait, float]]], Sequence[Reply]]


def search_many(designs: Iterable, cfg: GroundTruthConfig, evaluate_many: EvaluateMany,
                space: DesignSpace = DEFAULT_SPACE, in_flight: int | None = None) -> Iterator[DesignResult]:
    """The searches of ``designs`` (:func:`design_rounds`) advanced in lockstep: each step
    collects the round of every design in flight, and makes one call
    ``evaluate_many([(design, gait, duration), ...])`` of all their episodes (any engine: a
    batched simulator, or :class:`softcrawl.codesign.groundtruth.optimize.SerialEvaluateMany`
    on the CPU). Each design's result equals
    :func:`~softcrawl.codesign.groundtruth.optimize.optimize_design`'s with the same episodes'
    answers.

    At most ``in_flight`` designs are searched at once (bounded memory, and a batch of about
    ``in_flight`` times a round's 10 to 50 episodes); the next designs, in the order given, join
    when half of them or fewer are left, together (so that a batched engine prepares the
    newcomers in one batch), until none is left.

    Args:
        designs: designs of ``space`` (canonicalised; duplicates dropped).
        cfg: settings.
        evaluate_many: see :data:`EvaluateMany`.
        space: the designs' design space (its canonical forms, its regulators).
        in_flight: most designs searched at once (None: all of them).

    Yields:
        :class:`DesignResult` of each design as it finishes (designs with fewer rounds first);
        ``wall_seconds``: its share of the time spent in ``evaluate_many`` (each call's time
        split evenly among its episodes).

    Raises:
        InvalidDesignError: an invalid design. ValueError: invalid ``cfg`` or ``in_flight``;
            ``evaluate_many`` answered a call with another number of replies than it was asked.
        All but the last are raised before the first call.
    """
    cfg.validate()
    if in_flight is not None and (isinstance(in_flight, bool) or int(in_flight) != in_flight or in_flight < 1):
        raise ValueError(f"in_flight must be a positive integer or None, got {in_flight!r}")
    queue = collections.deque(dict.fromkeys(space.canonicalize(d) for d in designs))
    limit = len(queue) if in_flight is None else int(in_flight)
    active: dict = {}  # design -> [its rounds, its requests of this step, wall seconds]

    def admit() -> None:
        while queue and len(active) < limit:
            d = queue.popleft()
            rounds = design_rounds(d, cfg, space)
            active[d] = [rounds, next(rounds), 0.0]

    admit()
    while active:
        step = list(active.items())
        requests = [(d, *request) for d, p in step for request in p[1]]
        t0 = time.perf_counter()
        replies = list(evaluate_many(requests))
        if len(replies) != len(requests):
            raise ValueError(f"evaluate_many answered {len(replies)} of {len(requests)} episodes")
        share = (time.perf_counter() - t0) / len(requests)
        at = 0
        for d, p in step:
            n = len(p[1])
            p[2] += share * n
            try:
                p[1] = p[0].send(replies[at:at + n])
            except StopIteration as stop:
                del active[d]
                yield dataclasses.replace(stop.value, wall_seconds=p[2])
            at += n
        if len(active) <= limit // 2:
            admit()
