"""The per-design gait search: CMA-ES (the ``cma`` package) over the knots of a periodic gait.

For each cycle length ``L`` in :attr:`GroundTruthConfig.cycles` a CMA-ES run over the knots of
the regulators the design uses (``m L`` numbers in [0, 90] kPa, step waveform),
``evals_per_cycle`` episodes each, started from the best of a few structured gaits evaluated
first (:func:`seed_knots`); the ``finalists`` best distinct candidates, and the smooth variant
of each, are then re-run with full ``duration`` episodes (module docstring of
:mod:`softcrawl.codesign.groundtruth`).

The search of one design is a coroutine (:func:`design_search`) that asks for episodes and is
told their rewards, so that any engine can run them: one design on the CPU
(:func:`softcrawl.codesign.groundtruth.optimize.optimize_design`), or many designs in lockstep,
each round's episodes in one batched call (:func:`search_many`).
"""

from __future__ import annotations

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


def cma_search(dim: int, budget: int, seeds: Sequence[np.ndarray] = (), x0: float | np.ndarray = 0.5,
               sigma0: float = 0.3, popsize: int | None = None, seed: int = 0):
    """CMA-ES (``cma``) maximizing over ``[0, 1]^dim`` as a generator: it yields points
    ``(dim,)`` and is sent their values; exactly ``budget`` points (the last generation
    truncated). ``seeds`` (points in [0, 1]^dim) come first (at most ``budget // 2`` of them) and
    CMA-ES starts at the best one (else at ``x0``). CMA-ES searches ``[-0.15, 1.15]^dim``
    clipped to ``[0, 1]`` so that the bounds (vent, full pressure) are reached; it restarts
    around the best point with half the step if it converges early. ``dim == 1`` searches a
    dummy second coordinate (cma needs 2).

    Returns (``StopIteration.value``): the history ``[(x, value), ...]`` in evaluation order.

    Raises:
        ValueError: ``dim < 1`` or ``budget < 1``.
    """
    import cma

    if dim < 1 or budget < 1:
        raise ValueError(f"need dim >= 1 and budget >= 1, got {dim}, {budget}")
    n = max(dim, 2)

    def pad(x):
        x = np.ravel(np.asarray(x, float))
        return np.r_[x, np.full(n - len(x), 0.5)] if len(x) < n else x

    history: list[tuple[np.ndarray, float]] = []
    for s in [np.clip(pad(s), 0, 1) for s in seeds][: max(0, budget // 2)]:
        v = yield s[:dim].copy()
        history.append((s, float(v)))
    x0v = max(history, key=lambda h: h[1])[0] if history else (
        np.full(n, x0, float) if np.ndim(x0) == 0 else pad(x0))
    lo, hi = -0.15, 1.15
    opts = {"bounds": [lo, hi], "seed": int(seed) % (2**31 - 1) + 1, "verbose": -9, "tolfun": 1e-9, "tolx": 1e-6}
    if popsize is not None:
        opts["popsize"] = int(popsize)
    es = cma.CMAEvolutionStrategy(np.clip(x0v, lo + 1e-3, hi - 1e-3), sigma0, opts)
    while len(history) < budget:
        xs = es.ask()[: budget - len(history)]
        vals = []
        for x in xs:
            v = yield np.clip(x[:dim], 0.0, 1.0)
            vals.append(float(v))
            history.append((np.clip(x, 0.0, 1.0), float(v)))
        if len(xs) < es.popsize:
            break
        es.tell(xs, [-v for v in vals])
        if es.stop() and len(history) < budget:  # converged early: restart around the best
            opts["seed"] += 1
            es = cma.CMAEvolutionStrategy(np.clip(max(history, key=lambda h: h[1])[0], lo + 1e-3, hi - 1e-3),
                                          sigma0 / 2, opts)
    return [(x[:dim], v) for x, v in history]


def drive(gen, f: Callable[[np.ndarray], float]):
    """Run a coroutine that yields requests and is sent their answers ``f(request)`` (a
    :func:`cma_search` with objective ``f``, a :func:`design_search` with an evaluator) to its
    end; returns its return value."""
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


def design_search(design, cfg: GroundTruthConfig,
                  space: DesignSpace = DEFAULT_SPACE) -> typing.Generator[Request, Reply, DesignResult]:
    """The best gait of ``design`` in the family as a coroutine (the search of the module
    docstring): it yields the episodes it needs, ``(gait, duration)``, one at a time, and is
    sent each one's ``(reward cm, diverged)``; a diverged episode (or a non-finite reward)
    scores :data:`DIVERGED_CM`. Exactly ``len(cfg.cycles) * cfg.evals_per_cycle`` search
    episodes of ``cfg.screen_duration`` s (``cfg.duration`` without screening), then at most
    ``2 * cfg.finalists`` finals of ``cfg.duration`` s.

    The design and the settings are checked when this is called, before the first request.
    The gaits command the ``R`` regulators of ``space`` (the design's design space).

    Returns (``StopIteration.value``):
        :class:`DesignResult` with ``wall_seconds`` 0 (the driver knows the time it took).

    Raises:
        InvalidDesignError: invalid design. ValueError: invalid ``cfg``.
    """
    cfg.validate()
    return _search(space.canonicalize(design), cfg, space.n_regulators)


def _search(design: Design, cfg: GroundTruthConfig, n_reg: int) -> typing.Generator[Request, Reply, DesignResult]:
    """The body of :func:`design_search` (a generator, run only once asked for its first request)."""
    m = max(design)  # canonical labels are 1..m (used_regulators)
    screen = cfg.screen_duration if cfg.screen_duration is not None and cfg.screen_duration < cfg.duration else None
    search_t = screen or cfg.duration
    n_eval, n_full, sim, n_div = 0, 0, 0.0, 0

    def score(reply: Reply, duration: float) -> float:
        nonlocal n_eval, n_full, sim, n_div
        r, div = float(reply[0]), bool(reply[1]) or not math.isfinite(reply[0])
        n_eval, n_full, sim, n_div = n_eval + 1, n_full + int(duration == cfg.duration), sim + duration, n_div + int(div)
        return DIVERGED_CM if div else r

    candidates: list[tuple[float, int, np.ndarray]] = []  # (search reward, L, x)
    per_cycle = {}
    for ci, L in enumerate(cfg.cycles):
        cma = cma_search(m * L, cfg.evals_per_cycle, [s.ravel() for s in seed_knots(m, L)], sigma0=cfg.sigma0,
                         popsize=cfg.popsize, seed=design_seed(design, cfg.seed) + ci)
        try:
            x = next(cma)
            while True:
                gait = knots_to_gait(x, m, L, cfg.hold, n_regulators=n_reg)
                x = cma.send(score((yield gait, search_t), search_t))
        except StopIteration as stop:
            hist = stop.value
        per_cycle[int(L)] = max(hist, key=lambda h: h[1])[1]
        candidates += [(v, L, x) for x, v in hist]
    # finals: the best distinct candidates, step and smooth, with full episodes
    candidates.sort(key=lambda c: -c[0])
    finals, seen = [], set()
    for v, L, x in candidates:
        key = (L, np.round(x, 4).tobytes())
        if key not in seen:
            seen.add(key)
            finals.append((v, L, x))
        if len(finals) >= cfg.finalists:
            break
    best = None  # (full reward, screen reward, gait, L)
    for v, L, x in finals:
        for wf in WAVEFORMS:
            gait = knots_to_gait(x, m, L, cfg.hold, wf, n_reg)
            if wf == "step" and screen is None:
                r = v
            else:
                r = score((yield gait, cfg.duration), cfg.duration)
            if best is None or r > best[0]:
                best = (r, v if (wf == "step" and screen) else float("nan"), gait, L)
    r, sv, gait, L = best
    return DesignResult(design, float(r), gait.to_dict(), int(L), gait.waveform, n_eval, n_full, sim, 0.0,
                        float(sv), per_cycle, n_div)


#: ``evaluate_many(requests) -> replies``: ``requests`` a list of ``(design, gait, duration s)``,
#: the replies ``(reward cm, diverged)`` in the same order.
EvaluateMany = Callable[[list[tuple[Design, PeriodicGait, float]]], Sequence[Reply]]


def search_many(designs: Iterable, cfg: GroundTruthConfig, evaluate_many: EvaluateMany,
                space: DesignSpace = DEFAULT_SPACE) -> Iterator[DesignResult]:
    """The searches of ``designs`` (:func:`design_search`) advanced in lockstep: each round
    collects the pending episode of every unfinished design and makes one call
    ``evaluate_many([(design, gait, duration), ...])`` (any engine: a batched simulator, or
    :class:`softcrawl.codesign.groundtruth.optimize.SerialEvaluateMany` on the CPU). Each
    design's result equals :func:`~softcrawl.codesign.groundtruth.optimize.optimize_design`'s
    with the same episodes' answers.

    Args:
        designs: designs of ``space`` (canonicalised; duplicates dropped).
        cfg: settings.
        evaluate_many: see :data:`EvaluateMany`.
        space: the designs' design space (its canonical forms, its regulators).

    Yields:
        :class:`DesignResult` of each design as it finishes (designs with fewer episodes first);
        ``wall_seconds``: its share of the time spent in ``evaluate_many`` (each call's time
        split evenly among its episodes).

    Raises:
        InvalidDesignError: an invalid design. ValueError: invalid ``cfg``; ``evaluate_many``
            answered a round with another number of replies than it was asked.
    """
    pending = {}  # design -> [search, its request, wall seconds]
    for d in dict.fromkeys(space.canonicalize(d) for d in designs):
        search = design_search(d, cfg, space)
        pending[d] = [search, next(search), 0.0]
    while pending:
        round_ = list(pending.items())
        t0 = time.perf_counter()
        replies = list(evaluate_many([(d, *p[1]) for d, p in round_]))
        if len(replies) != len(round_):
            raise ValueError(f"evaluate_many answered {len(replies)} of {len(round_)} episodes")
        share = (time.perf_counter() - t0) / len(round_)
        for (d, p), reply in zip(round_, replies):
            p[2] += share
            try:
                p[1] = p[0].send(reply)
            except StopIteration as stop:
                del pending[d]
                yield dataclasses.replace(stop.value, wall_seconds=p[2])
