"""Co-design algorithms behind one small interface, compared against the ground truth.

An algorithm *proposes* (design, gait) pairs of a design space and *receives* their episode
returns (the ground truth's task's unit, cm for the paper's):

* :class:`RandomSearch`: designs in a random order without replacement, each with the
  per-design CMA-ES gait search of :mod:`softcrawl.codesign.groundtruth` (``evals_per_design``
  episodes, one cycle length drawn from ``cycles`` per design).
* :class:`OptunaSearch`: one optuna study over (design, cycle length, knots): TPE
  (``sampler="tpe"``) or the NSGA-II genetic algorithm (``sampler="ga"``, single objective).
* :class:`GibbsSACReplay`: the paper's Gibbs-SAC evaluated *post hoc* from a training run's
  ``episodes.csv`` (transition count, design, return per episode): its proposals are the
  episodes it ran, with their known returns (no simulation).

Every algorithm has an *incumbent*: the design it would choose now (random search and optuna:
the best return seen; Gibbs-SAC: the highest latest return, which is the most probable design
of its Gibbs distribution for any β > 0). :func:`run_algorithm` runs one until a budget of
simulated seconds and records the ground-truth reward of the incumbent after each proposal:
"best-found ground-truth reward vs simulated seconds".
"""

from __future__ import annotations

import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softcrawl.codesign.groundtruth import (
    GroundTruthConfig,
    PeriodicGait,
    cma_search,
    design_seed,
    knots_to_gait,
    seed_knots,
    used_regulators,
)
from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace

ALGORITHMS = ("random", "tpe", "ga")


@dataclass
class Proposal:
    """One episode an algorithm asks for.

    Attributes:
        design: canonical design. gait: the gait (None for replayed episodes).
        duration: episode length, s. known_return: cm, for replayed episodes (else None).
    """

    design: Design
    gait: PeriodicGait | None
    duration: float
    known_return: float | None = None


class CodesignAlgorithm:
    """Interface: ``propose() -> list[Proposal]`` (empty: finished), ``tell(proposals, returns)``
    with the returns in cm; ``incumbent`` is the design it would choose now (None before any)."""

    name = "algorithm"

    def __init__(self):
        self.best: dict[Design, float] = {}
        self.latest: dict[Design, float] = {}

    def propose(self) -> list[Proposal]:  # pragma: no cover
        raise NotImplementedError

    def tell(self, proposals: Sequence[Proposal], returns: Sequence[float]) -> None:
        for p, r in zip(proposals, returns):
            self.best[p.design] = max(self.best.get(p.design, -math.inf), float(r))
            self.latest[p.design] = float(r)

    @property
    def incumbent(self) -> Design | None:
        if not self.best:
            return None
        return max(self.best, key=lambda d: (self.best[d], d))


class RandomSearch(CodesignAlgorithm):
    """Random designs (without replacement, then again) each with a CMA-ES gait search.

    Args:
        designs: the designs searched (of ``space``). duration: episode s. hold: s per knot.
        evals_per_design: episodes per design. cycles: pattern lengths (one drawn per design).
        seed: RNG seed. space: the designs' design space (canonical forms, regulators; default
            the paper's).
    """

    name = "random"

    def __init__(self, designs: Sequence, duration: float, hold: float = 1.0, evals_per_design: int = 24,
                 cycles: Sequence[int] = (3, 4), seed: int = 0, space: DesignSpace = DEFAULT_SPACE):
        super().__init__()
        self.space = space
        self.designs = [space.canonicalize(d) for d in designs]
        self.duration, self.hold, self.evals, self.cycles = duration, hold, int(evals_per_design), tuple(cycles)
        self.rng = np.random.default_rng(seed)
        self.seed = seed
        self._order: list[Design] = []
        self._gen = None
        self._x = None

    def _next_design(self) -> None:
        if not self._order:
            self._order = [self.designs[i] for i in self.rng.permutation(len(self.designs))]
        self._design = self._order.pop()
        self._m, self._L = used_regulators(self._design, self.space), int(self.rng.choice(self.cycles))
        self._gen = cma_search(self._m * self._L, self.evals, [s.ravel() for s in seed_knots(self._m, self._L)],
                               seed=design_seed(self._design, self.seed))
        self._x = next(self._gen)

    def propose(self) -> list[Proposal]:
        if self._gen is None:
            self._next_design()
        gait = knots_to_gait(self._x, self._m, self._L, self.hold, n_regulators=self.space.n_regulators)
        return [Proposal(self._design, gait, self.duration)]

    def tell(self, proposals, returns) -> None:
        super().tell(proposals, returns)
        try:
            self._x = self._gen.send(float(returns[0]))
        except StopIteration:
            self._gen = None


class OptunaSearch(CodesignAlgorithm):
    """One optuna study over (design, cycle length, knots of the used regulators, kPa).

    Args:
        designs: the designs searched (of ``space``). duration, hold: s. cycles: pattern lengths.
        sampler: ``"tpe"`` (:class:`optuna.samplers.TPESampler`) or ``"ga"``
            (:class:`optuna.samplers.NSGAIISampler`, population ``population``).
        seed: sampler seed. space: the designs' design space (default the paper's).

    Raises:
        ValueError: unknown sampler.
    """

    def __init__(self, designs: Sequence, duration: float, hold: float = 1.0, cycles: Sequence[int] = (3, 4),
                 sampler: str = "tpe", seed: int = 0, population: int = 16, space: DesignSpace = DEFAULT_SPACE):
        import optuna

        super().__init__()
        optuna.logging.set_verbosity(optuna.logging.WARNING)
        if sampler == "tpe":
            s = optuna.samplers.TPESampler(seed=seed, n_startup_trials=10)
        elif sampler == "ga":
            s = optuna.samplers.NSGAIISampler(seed=seed, population_size=population)
        else:
            raise ValueError(f"sampler must be 'tpe' or 'ga', got {sampler!r}")
        self.name = sampler
        self.space = space
        canonical = [space.canonicalize(d) for d in designs]
        self.designs = {",".join(map(str, d)) if max(d) > 9 else "".join(map(str, d)): d for d in canonical}
        self.duration, self.hold, self.cycles = duration, hold, tuple(int(c) for c in cycles)
        self.study = optuna.create_study(direction="maximize", sampler=s)
        self._trial = None

    def propose(self) -> list[Proposal]:
        t = self.study.ask()
        d = self.designs[t.suggest_categorical("design", list(self.designs))]
        L = t.suggest_categorical("cycle", list(self.cycles))
        knots = np.zeros((L, self.space.n_regulators))
        for k in range(used_regulators(d, self.space)):
            for i in range(L):
                knots[i, k] = t.suggest_float(f"p{k + 1}_{i}", 0.0, 90.0)
        self._trial = t
        return [Proposal(d, PeriodicGait.from_knots(knots, self.hold), self.duration)]

    def tell(self, proposals, returns) -> None:
        super().tell(proposals, returns)
        self.study.tell(self._trial, float(returns[0]))


class GibbsSACReplay(CodesignAlgorithm):
    """The episodes of a Gibbs-SAC training run, in order, as proposals with known returns.

    Args:
        run: training run folder (``episodes.csv``: transitions, design digits, return cm,
            diverged; ``config.json``: the episode length ``n_actions x steps_per_action x dt``).
        designs: keep only episodes of these designs (None: all).
        batch: episodes per proposal batch (default: the run's ``n_envs``).

    Raises:
        ValueError: not a training run (no ``episodes.csv`` or ``config.json``).
    """

    name = "gibbs-sac"

    def __init__(self, run: str | Path, designs: Sequence | None = None, batch: int | None = None):
        super().__init__()
        from softcrawl.codesign.migrate import read_settings
        from softcrawl.codesign.run import Run

        r = Run(run)
        if not r.episodes_csv.exists() or not r.exists():
            raise ValueError(f"{run} is not a training run with episodes (episodes.csv, config.json)")
        meta = r.read_meta()
        try:  # the raw settings, migrated (not validated): runs of older versions replay too
            cfg = read_settings("train", meta)
            e = cfg["env"]
            self.episode_seconds = float(e["n_actions"]) * float(e["steps_per_action"]) * float(e["robot"]["dt"])
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"{r.config_path}: no env settings n_actions, steps_per_action, robot.dt ({exc!r})") \
                from None
        space = r.design_space()  # the run's own (its space.toml; the paper's for an older run)
        keep = None if designs is None else {space.canonicalize(d) for d in designs}
        self.keep = keep
        ep = r.read_episodes()  # ValueError naming the file and line of a bad row
        self.rows = [(int(t), d, float(ret), keep is None or d in keep)
                     for t, d, ret in zip(ep["t"], ep["design"], ep["r"])]
        self.batch = int(batch or cfg.get("n_envs", 1))
        self._i = 0

    def propose(self) -> list[Proposal]:
        out = []
        while self._i < len(self.rows) and len(out) < self.batch:
            _, d, r, _ = self.rows[self._i]
            self._i += 1
            out.append(Proposal(d, None, self.episode_seconds, r))
        return out

    def tell(self, proposals, returns) -> None:
        """Record the returns; designs outside ``designs`` cost time but cannot be chosen."""
        kept = [(p, r) for p, r in zip(proposals, returns) if self.keep is None or p.design in self.keep]
        super().tell([p for p, _ in kept], [r for _, r in kept])

    @property
    def incumbent(self) -> Design | None:
        if not self.latest:
            return None
        return max(self.latest, key=lambda d: (self.latest[d], d))


class SimEvaluator:
    """``(design, gait, duration) -> return`` (the task's unit) on the reduced model of a ground
    truth's settings (its space and task), keeping the ``max_robots`` most recent designs' robots
    (and rested states). Counts episodes."""

    def __init__(self, cfg: GroundTruthConfig, max_robots: int = 16):
        from softcrawl.codesign.groundtruth import DesignEvaluator

        self.cfg, self.max_robots, self.cls = cfg, max_robots, DesignEvaluator
        self.space = cfg.design_space()
        self._cache: OrderedDict = OrderedDict()
        self.episodes = 0

    def __call__(self, design, gait, duration) -> float:
        d = self.space.canonicalize(design)
        if d not in self._cache:
            self._cache[d] = self.cls(d, self.cfg)
            while len(self._cache) > self.max_robots:
                self._cache.popitem(last=False)
        self._cache.move_to_end(d)
        self.episodes += 1
        return self._cache[d](gait, duration)[0]


def run_algorithm(algo: CodesignAlgorithm, evaluate: Callable[[Design, PeriodicGait, float], float],
                  gt_reward: dict[Design, float], budget_seconds: float) -> dict:
    """Run ``algo`` until ``budget_seconds`` simulated seconds (or until it stops proposing).

    Args:
        evaluate: ``(design, gait, duration) -> return cm`` (not called for known returns).
        gt_reward: ground-truth reward per design, cm; incumbents outside it count as unknown.

    Returns:
        ``{"name", "sim_seconds": [...], "incumbent": [...], "gt_cm": [...], "episodes"}``, one
        entry per proposal batch (``gt_cm`` NaN while the incumbent is unknown).
    """
    sim, trace = 0.0, {"name": algo.name, "sim_seconds": [], "incumbent": [], "gt_cm": [], "episodes": 0}
    while sim < budget_seconds:
        props = algo.propose()
        if not props:
            break
        rets = [p.known_return if p.known_return is not None else evaluate(p.design, p.gait, p.duration) for p in props]
        algo.tell(props, rets)
        sim += sum(p.duration for p in props)
        trace["episodes"] += len(props)
        inc = algo.incumbent
        trace["sim_seconds"].append(sim)
        trace["incumbent"].append(list(inc) if inc else None)
        trace["gt_cm"].append(float(gt_reward.get(inc, float("nan"))) if inc else float("nan"))
    return trace


def best_so_far_on_grid(trace: dict, grid: np.ndarray) -> np.ndarray:
    """Ground-truth reward of the incumbent at each simulated-seconds value of ``grid`` (NaN
    before the first known incumbent)."""
    t, g = np.asarray(trace["sim_seconds"]), np.asarray(trace["gt_cm"], float)
    out = np.full(len(grid), np.nan)
    for i, x in enumerate(grid):
        k = np.searchsorted(t, x, side="right") - 1
        if k >= 0:
            out[i] = g[k]
    return out


def make_algorithm(name: str, designs: Sequence, cfg: GroundTruthConfig, seed: int, evals_per_design: int = 24,
                   cycles: Sequence[int] = (3, 4), duration: float | None = None) -> CodesignAlgorithm:
    """``"random"``, ``"tpe"`` or ``"ga"`` over ``designs`` with ``cfg``'s hold and episode
    length (``duration`` overrides it), in ``cfg``'s design space.

    Raises:
        ValueError: unknown name.
    """
    T = cfg.duration if duration is None else duration
    space = cfg.design_space()
    if name == "random":
        return RandomSearch(designs, T, cfg.hold, evals_per_design, cycles, seed, space)
    if name in ("tpe", "ga"):
        return OptunaSearch(designs, T, cfg.hold, cycles, name, seed, space=space)
    raise ValueError(f"algorithm must be one of {ALGORITHMS}, got {name!r}")
