"""Ground truth of the design space: every design with its best open-loop gait.

The paper reports the design its co-design converged to; this module measures how good that
choice is against the whole space. Each design gets the best gait CMA-ES (the ``cma`` package)
finds in a periodic open-loop gait family, on the reduced model; designs are then ranked by
that reward (cm of +x crawl per episode).

**Gait family** (:class:`PeriodicGait`): per regulator a pressure pattern of ``L`` knots
(real kPa, ``L`` = 1..8, one knot per action of ``hold`` s), repeated periodically. Two
waveforms: ``"step"`` holds knot ``i`` during ``[i hold, (i + 1) hold)`` (what a policy with
1-s actions can command); ``"smooth"`` is the periodic trigonometric interpolation through the
knots (period ``L hold``). The smooth 4-knot pattern through the samples ``p(0..3 s)`` of the
expert's raised cosine ``45 - 45 cos(2 pi t / 4 s)`` *is* that cosine at any phase
(:meth:`PeriodicGait.expert_sine`), and the step 3-knot pattern rear / front / vent is the
paper's 3-s cycle (:meth:`PeriodicGait.paper_cycle`); both are proven in
``tests/test_groundtruth.py``.

**Optimizer** (:func:`optimize_design`): for each cycle length ``L`` in
:attr:`GroundTruthConfig.cycles` a CMA-ES run over the knots of the regulators the design uses
(``m L`` numbers in [0, 90] kPa, step waveform), ``evals_per_cycle`` episodes each, started from
the best of a few structured gaits evaluated first (one regulator after another then vent, all
together, the expert's sampled sine at lags 90/180/270 deg). Episodes are of ``screen_duration``
s when set (screening: :func:`screening_agreement` measures the Spearman rank correlation of
short vs full episodes on a sample: 36 (design, gait) pairs on 6 three-legged designs gave 0.87
/ 0.95 / 0.96 for 4 / 6 / 10 s over all pairs, 1.0 for the best pair per design, 0.43 / 0.75 /
0.79 within a design, hence 6 s and full-length finals); the ``finalists`` best distinct
candidates, and the smooth variant of each, are then re-run with full ``duration`` (20 s)
episodes, and the best full-episode reward is the design's ground truth. A diverged episode
scores :data:`DIVERGED_CM`.

**Runs** (:func:`run_groundtruth`, ``softcrawl groundtruth``): a folder with ``config.json``
(the :class:`GroundTruthConfig`), ``results.jsonl`` (one line per finished design, appended
and fsynced as each finishes: a killed run continues where it stopped and never recomputes a
finished design), ``references.json`` (expert baseline phase sweep, paper gait on the paper's
design), and at the end ``groundtruth.csv`` (ranked table), ``ranked.png`` and
``summary.json``. ``results.jsonl`` is only ever appended to, never rewritten, and never
through a symbolic link; the other files are replaced atomically
(:func:`softcrawl.safeio.atomic_write_text`). Its readers (:func:`read_results`: the run
itself, ``regret``, ``report --groundtruth``) validate every row and use only the valid ones;
a bad row (a line cut short by a killed run, a non-finite reward, a design outside the space,
a knot outside [0, 90] kPa) is named by file and line and left in place, and a resumed run
computes its design again. The folder must be new, empty or a ground truth
(:func:`check_folder`), and is locked while a run writes it (:func:`folder_lock`). Designs
run in a process pool (workers pinned to one BLAS thread) or as Ray tasks
(``executor="ray"``; a task whose worker died is retried by Ray, only that design).
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import itertools
import json
import math
import os
import stat
import time
import typing
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from softcrawl.design.space import (
    BASELINE_DESIGN,
    N_REGULATORS,
    PAPER_BEST_DESIGN,
    Design,
    canonical_designs,
    canonicalize,
)
from softcrawl.codesign.config import MAX_EPISODE_S, MAX_HOLD_S, SIM_BOUNDS, check_bounds, check_field
from softcrawl.codesign.run import note
from softcrawl.fem.solver import RID_DTYPES
from softcrawl.robot.actuation import P_MAX_KPA, P_MIN_KPA
from softcrawl.safeio import UnsafeFileError, atomic_write_text, load_json, loads_json, read_text

#: Objective value (cm) given to an episode whose simulation diverged.
DIVERGED_CM = -100.0
#: Longest pattern a regulator may have (knots).
MAX_KNOTS = 8
WAVEFORMS = ("step", "smooth")
EXECUTORS = ("process", "serial", "ray")
#: Paper's reward of its best design L1 with its learned gait (codesign.md), cm per 20 s.
PAPER_L1_CM = 10.0
#: Upper bounds of the search settings (far beyond the defaults 36, 2 and cma's 4 + 3 ln n).
MAX_EVALS, MAX_FINALISTS, MAX_POPSIZE = 100_000, 1000, 10_000


# -- gait family --------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class PeriodicGait:
    """Periodic open-loop gait: per regulator a pattern of knots, repeated.

    Attributes:
        patterns: 3 tuples of knots (real kPa, each in [0, 90]); regulator ``k`` uses
            ``patterns[k - 1]`` of length ``L_k`` (1..:data:`MAX_KNOTS`); period of regulator
            ``k``: ``L_k * hold`` s; the gait's period is their least common multiple.
        hold: seconds per knot (> 0; 1 s = one action of the paper).
        waveform: ``"step"`` (knot ``i`` held over ``[i hold, (i + 1) hold)`` of the cycle) or
            ``"smooth"`` (periodic trigonometric interpolation through knot ``i`` at ``t = i hold``,
            clipped to [0, 90] kPa).

    Raises:
        ValueError: bad shapes, lengths, hold or waveform; knots outside [0, 90] kPa or non-finite.
    """

    patterns: tuple
    hold: float = 1.0
    waveform: str = "step"

    def __post_init__(self) -> None:
        if len(self.patterns) != N_REGULATORS:
            raise ValueError(f"need {N_REGULATORS} patterns (one per regulator), got {len(self.patterns)}")
        pats = []
        for k, p in enumerate(self.patterns, start=1):
            a = np.array(p, dtype=float).reshape(-1)
            if not 1 <= len(a) <= MAX_KNOTS:
                raise ValueError(f"regulator {k}: pattern needs 1..{MAX_KNOTS} knots, got {len(a)}")
            if not np.all(np.isfinite(a)) or a.min() < P_MIN_KPA or a.max() > P_MAX_KPA:
                raise ValueError(f"regulator {k}: knots must be finite and in [{P_MIN_KPA:g}, {P_MAX_KPA:g}] kPa, "
                                 f"got {a.tolist()}")
            pats.append(tuple(float(v) for v in a))
        if not (math.isfinite(self.hold) and self.hold > 0):
            raise ValueError(f"hold must be a positive number of seconds, got {self.hold!r}")
        if self.waveform not in WAVEFORMS:
            raise ValueError(f"waveform must be one of {WAVEFORMS}, got {self.waveform!r}")
        object.__setattr__(self, "patterns", tuple(pats))
        object.__setattr__(self, "hold", float(self.hold))

    # constructors
    @classmethod
    def from_knots(cls, knots, hold: float = 1.0, waveform: str = "step") -> PeriodicGait:
        """Gait from a ``(L, 3)`` knot table (real kPa; column ``k - 1`` = regulator ``k``)."""
        k = np.asarray(knots, dtype=float)
        if k.ndim != 2 or k.shape[1] != N_REGULATORS:
            raise ValueError(f"knots must have shape (L, {N_REGULATORS}), got {k.shape}")
        return cls(tuple(k[:, j] for j in range(N_REGULATORS)), hold, waveform)

    @classmethod
    def expert_sine(cls, phase_deg: float, period_knots: int = 4, hold: float = 1.0) -> PeriodicGait:
        """The expert gait :class:`softcrawl.gaits.SineGait` (period ``period_knots * hold`` s,
        0..90 kPa, regulator 2 lagging 1 by ``phase_deg``) as a smooth pattern of its samples;
        equal to it at every ``t`` for ``period_knots >= 3`` (a raised cosine has harmonics 0
        and 1 only)."""
        from softcrawl.gaits import SineGait

        g = SineGait(period=period_knots * hold, phase_deg=phase_deg)
        return cls.from_knots([g.pressure_at(i * hold) for i in range(period_knots)], hold, "smooth")

    @classmethod
    def paper_cycle(cls, high_kpa: float = P_MAX_KPA, hold: float = 1.0) -> PeriodicGait:
        """The paper's learned 3-s cycle for (1,0,0,2,2,0,0,0): rear regulator 2 inflates, then
        front regulator 1, then both vent (codesign.md); equals
        :func:`softcrawl.gaits.paper_best_gait` step for step."""
        return cls.from_knots([[0.0, high_kpa, 0.0], [high_kpa, 0.0, 0.0], [0.0, 0.0, 0.0]], hold, "step")

    @property
    def period(self) -> float:
        """Period of the whole gait, s (lcm of the pattern lengths times ``hold``)."""
        return math.lcm(*(len(p) for p in self.patterns)) * self.hold

    def with_waveform(self, waveform: str) -> PeriodicGait:
        return PeriodicGait(self.patterns, self.hold, waveform)

    def pressure_at(self, t: float) -> np.ndarray:
        """Commanded ``(3,)`` real kPa at ``t`` s (periodic, defined for all ``t``)."""
        u = t / self.hold
        out = np.empty(N_REGULATORS)
        for k, p in enumerate(self.patterns):
            n = len(p)
            if n == 1 or self.waveform == "step":
                out[k] = p[int(math.floor(u + 1e-9)) % n]
            else:
                out[k] = _trig_interp(p, u)
        return np.clip(out, P_MIN_KPA, P_MAX_KPA)

    def to_dict(self) -> dict:
        """JSON-able form (inverse :meth:`from_dict`)."""
        return {"patterns": [list(p) for p in self.patterns], "hold": self.hold, "waveform": self.waveform}

    @classmethod
    def from_dict(cls, d: dict) -> PeriodicGait:
        return cls(tuple(d["patterns"]), d.get("hold", 1.0), d.get("waveform", "step"))

    def describe(self) -> str:
        """Short text: waveform and knots per regulator (kPa, rounded; regulators separated by ``;``)."""
        return f"{self.waveform} " + "; ".join("/".join(f"{v:.0f}" for v in p) for p in self.patterns)


def _trig_interp(knots: Sequence[float], u: float) -> float:
    """Periodic trigonometric interpolant of ``knots`` (at u = 0, 1, ..., n - 1; period n) at ``u``."""
    y = np.asarray(knots, float)
    n = len(y)
    c = np.fft.rfft(y) / n
    w = 2.0 * math.pi * u / n
    val = c[0].real
    for k in range(1, len(c)):
        if n % 2 == 0 and k == n // 2:  # Nyquist term: real coefficient, cosine only
            val += c[k].real * math.cos(w * k)
        else:
            val += 2.0 * (c[k].real * math.cos(w * k) - c[k].imag * math.sin(w * k))
    return float(val)


# -- configuration ------------------------------------------------------------------------------
@dataclass
class GroundTruthConfig:
    """Settings of a ground-truth run (saved as ``config.json``; a resumed run must match).

    Attributes:
        duration: full episode, s (20: the paper's 20 actions of 1 s).
        screen_duration: episode length of the CMA-ES search, s (None: ``duration``); allowed
            where :func:`screening_agreement` shows short episodes rank like full ones.
        hold: seconds per knot (= per action).
        cycles: pattern lengths ``L`` searched (one CMA-ES run each, 1..8).
        evals_per_cycle: episodes per CMA-ES run.
        popsize: CMA-ES population (None: cma's default ``4 + 3 ln n``).
        sigma0: initial CMA-ES step, as a fraction of 90 kPa.
        finalists: best distinct candidates re-run with ``duration`` (step and smooth each).
        seed: CMA-ES seed (design-specific seeds are derived from it).
        leg_mesh_size, disk_mesh_size (mm), dt (s; None: :class:`softcrawl.robot.RobotConfig`'s
            default), reduction (None: shipped): the reduced model, as in
            :func:`softcrawl.codesign.training.robot_factory`.
        baseline_phases: expert-baseline phase lags swept for ``references.json`` (degrees;
            empty: no sweep).
        rid_dtype: precision of the reduced legs' RID products (``"float32"``: validated like
            the training presets' model, ``docs/results.md``; folders written before this
            setting existed were computed in ``"float64"`` and read back as such).
    """

    duration: float = 20.0
    screen_duration: float | None = 6.0
    hold: float = 1.0
    cycles: tuple[int, ...] = (2, 3, 4, 5)
    evals_per_cycle: int = 36
    popsize: int | None = None
    sigma0: float = 0.3
    finalists: int = 2
    seed: int = 0
    leg_mesh_size: float = 6.0
    disk_mesh_size: float = 10.0
    dt: float | None = None
    reduction: str | None = None
    baseline_phases: tuple[float, ...] = tuple(range(0, 181, 10))
    rid_dtype: str = "float32"

    def validate(self) -> GroundTruthConfig:
        """Raise ValueError naming the first bad setting; returns self."""
        for name, (low, high, unit) in SIM_BOUNDS.items():
            if getattr(self, name) is not None:
                check_bounds(name, getattr(self, name), low, high, unit)
        for name, high, unit in (("duration", MAX_EPISODE_S, "s"), ("hold", MAX_HOLD_S, "s"),
                                 ("sigma0", 1, "(of 90 kPa)")):
            check_bounds(name, getattr(self, name), 0, high, unit, open_low=True)
        if self.screen_duration is not None and not (0 < self.screen_duration <= self.duration):
            raise ValueError(f"screen_duration must be in (0, duration], got {self.screen_duration!r}")
        if not self.cycles or any(int(c) != c or not 1 <= c <= MAX_KNOTS for c in self.cycles):
            raise ValueError(f"cycles must be pattern lengths in 1..{MAX_KNOTS}, got {self.cycles!r}")
        for name, low, high in (("evals_per_cycle", 1, MAX_EVALS), ("finalists", 1, MAX_FINALISTS),
                                ("popsize", 2, MAX_POPSIZE)):
            v = getattr(self, name)
            if v is not None:
                check_bounds(name, v, low, high)
                if int(v) != v:
                    raise ValueError(f"{name} must be an integer, got {v!r}")
        if self.rid_dtype not in RID_DTYPES:
            raise ValueError(f"rid_dtype must be one of {RID_DTYPES}, got {self.rid_dtype!r}")
        from softcrawl.robot.sweep import MAX_PHASES

        if len(self.baseline_phases) > MAX_PHASES:
            raise ValueError(f"baseline_phases: {len(self.baseline_phases)} lags, more than the {MAX_PHASES} allowed")
        for ph in self.baseline_phases:
            check_bounds("baseline_phases", ph, -360, 360, "deg")
        return self

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["cycles"], d["baseline_phases"] = list(self.cycles), list(self.baseline_phases)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> GroundTruthConfig:
        """Inverse of :meth:`to_dict`; each value checked against its field's type
        (:func:`softcrawl.codesign.config.check_field`) and :meth:`validate`.

        Raises:
            ValueError: not an object, an unknown key, a value of the wrong type (named), or a
                setting out of bounds.
        """
        if not isinstance(d, dict):
            raise ValueError(f"ground-truth settings must be an object, got {type(d).__name__}")
        hints = typing.get_type_hints(cls)
        unknown = set(d) - set(hints)
        if unknown:
            raise ValueError(f"unknown ground-truth settings: {sorted(unknown)}")
        kw = {k: check_field(k, v, hints[k]) for k, v in d.items()}
        kw.setdefault("rid_dtype", "float64")  # written before the setting: computed in double precision
        return cls(**kw).validate()

    def robot_config(self):
        """The :class:`softcrawl.robot.RobotConfig` of the episodes (reduced model)."""
        from softcrawl.robot.assembly import RobotConfig

        kw = {} if self.dt is None else {"dt": self.dt}
        return RobotConfig(model="reduced", leg_mesh_size=self.leg_mesh_size, disk_mesh_size=self.disk_mesh_size,
                           reduction=self.reduction, rid_dtype=self.rid_dtype, **kw)


# -- evaluating gaits on one design -------------------------------------------------------------
class DesignEvaluator:
    """Episodes of one design on the reduced model: ``evaluator(gait, duration) -> (cm, diverged)``.

    The robot is built and settled once (:func:`softcrawl.robot.episode.settle` with the default
    :class:`~softcrawl.robot.episode.Settling`); each episode starts from that rested state with
    a fresh solver (:func:`softcrawl.robot.episode.run_episode`). Counts episodes and simulated
    seconds in ``episodes`` and ``sim_seconds``.

    Raises:
        InvalidDesignError: invalid design.
    """

    def __init__(self, design, cfg: GroundTruthConfig):
        from softcrawl.robot.assembly import build_robot

        self.design, self.cfg = canonicalize(design), cfg
        self.robot = build_robot(self.design, cfg.robot_config())
        self._settled = None
        self.episodes, self.sim_seconds = 0, 0.0

    def __call__(self, gait, duration: float) -> tuple[float, bool]:
        from softcrawl.robot.episode import run_episode, settle

        if self._settled is None:
            self._settled = settle(self.robot)
        res = run_episode(self.robot, gait, duration, record_every=None, progress=False, settled=self._settled)
        self.episodes += 1
        self.sim_seconds += duration
        reward = float(res.reward_cm)
        return (reward if math.isfinite(reward) else DIVERGED_CM), bool(res.diverged)


def used_regulators(design) -> int:
    """Regulators a canonical design uses (canonical labels are 1..m), m."""
    return max(canonicalize(design))


def _seed_knots(m: int, L: int) -> list[np.ndarray]:
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


def _knots_to_gait(x: np.ndarray, m: int, L: int, hold: float, waveform: str = "step") -> PeriodicGait:
    """CMA-ES vector ``(m L,)`` in [0, 1] -> gait (regulators beyond m stay at 0 kPa)."""
    k = np.zeros((L, N_REGULATORS))
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
    """Run a :func:`cma_search` generator with objective ``f``; returns its history."""
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


@dataclass
class DesignResult:
    """Ground truth of one design.

    Attributes:
        design: canonical design. reward_cm: best full-episode reward, cm per ``duration`` s.
        gait: the best :class:`PeriodicGait` as a dict. cycle: its pattern length; waveform.
        evaluations: episodes simulated (search + finals). full_evaluations: of those, full-length.
        sim_seconds: simulated seconds of all episodes. wall_seconds: wall time (1 process).
        screen_cm: the best gait's screening reward (NaN without screening).
        per_cycle: best screening (or full) reward per cycle length, cm.
        diverged: episodes that diverged.
    """

    design: Design
    reward_cm: float
    gait: dict
    cycle: int
    waveform: str
    evaluations: int
    full_evaluations: int
    sim_seconds: float
    wall_seconds: float
    screen_cm: float = float("nan")
    per_cycle: dict = field(default_factory=dict)
    diverged: int = 0

    def to_dict(self) -> dict:
        """JSON-able (NaN written as None)."""
        d = dataclasses.asdict(self)
        d["design"] = list(self.design)
        d["screen_cm"] = None if not math.isfinite(self.screen_cm) else self.screen_cm
        return d

    @classmethod
    def from_dict(cls, d: dict, where: str = "result") -> DesignResult:
        """Inverse of :meth:`to_dict`, validated: a canonical design of the space, finite
        rewards and times, counts >= 0, a gait of the family (knots in [0, 90] kPa). Keys
        that are not fields are ignored (a newer version's additions).

        Raises:
            ValueError: the first fault, prefixed by ``where`` (file and line) and the design.
        """
        if not isinstance(d, dict):
            raise ValueError(f"{where}: a result must be a JSON object, got {type(d).__name__}")
        fields = {f.name: f for f in dataclasses.fields(cls)}
        missing = [k for k, f in fields.items() if k not in d and f.default is dataclasses.MISSING
                   and f.default_factory is dataclasses.MISSING]
        if missing:
            raise ValueError(f"{where}: missing {', '.join(missing)}")
        design = d["design"]
        if not isinstance(design, list) or any(isinstance(v, bool) or not isinstance(v, int) for v in design):
            raise ValueError(f"{where}: design must be a list of 8 integers, got {design!r}")
        design = tuple(design)
        try:
            canonical = canonicalize(design)
        except ValueError as exc:  # InvalidDesignError names the fault
            raise ValueError(f"{where}: {exc}") from None
        if canonical != design:
            raise ValueError(f"{where}: design {design} is not canonical ({canonical})")
        at = f"{where} (design {','.join(map(str, design))})"

        def number(key, low=-math.inf, integer=False, optional=False):
            v = d.get(key, fields[key].default)
            if v is None and optional:
                return float("nan")
            if not (_finite(v) and v >= low and (isinstance(v, int) or not integer)):
                kind = "an integer" if integer else "a finite number"
                raise ValueError(f"{at}: {key} must be {kind}{f' >= {low:g}' if low > -math.inf else ''}, got {v!r}")
            return v if integer else float(v)

        try:
            gait = PeriodicGait.from_dict(d["gait"])
        except (ValueError, TypeError, KeyError, AttributeError, OverflowError) as exc:
            raise ValueError(f"{at}: gait: {exc}") from None
        if d["waveform"] not in WAVEFORMS:
            raise ValueError(f"{at}: waveform must be one of {WAVEFORMS}, got {d['waveform']!r}")
        per_cycle = d.get("per_cycle", {})
        if not isinstance(per_cycle, dict) or not all(
                str(k).isdigit() and 1 <= int(k) <= MAX_KNOTS and _finite(v) for k, v in per_cycle.items()):
            raise ValueError(f"{at}: per_cycle must map cycle lengths 1..{MAX_KNOTS} to finite rewards, "
                             f"got {per_cycle!r}")
        cycle = number("cycle", 1, integer=True)
        if cycle > MAX_KNOTS:
            raise ValueError(f"{at}: cycle must be in 1..{MAX_KNOTS}, got {cycle}")
        return cls(design, number("reward_cm"), gait.to_dict(), cycle, d["waveform"],
                   number("evaluations", 0, True), number("full_evaluations", 0, True), number("sim_seconds", 0),
                   number("wall_seconds", 0), number("screen_cm", optional=True),
                   {int(k): float(v) for k, v in per_cycle.items()}, number("diverged", 0, True))


def _finite(v) -> bool:
    """Whether ``v`` is a number (not a bool) that a float holds finitely."""
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    try:
        return math.isfinite(v)
    except OverflowError:  # an integer beyond any float
        return False


def design_seed(design: Design, seed: int) -> int:
    """Deterministic per-design seed (independent of set order and Python's hash salt)."""
    return (seed * 1_000_003 + int("".join(map(str, design)), 4)) % (2**31 - 2)


def optimize_design(design, cfg: GroundTruthConfig, evaluator: Callable | None = None) -> DesignResult:
    """The best gait of ``design`` in the family (see the module docstring).

    Args:
        design: a design (canonicalised first).
        cfg: settings.
        evaluator: ``(gait, duration) -> (reward cm, diverged)`` (default: a
            :class:`DesignEvaluator`, the reduced model).

    Returns:
        :class:`DesignResult`.

    Raises:
        InvalidDesignError: invalid design. ValueError: invalid ``cfg``.
    """
    cfg.validate()
    design = canonicalize(design)
    wall = time.perf_counter()
    ev = evaluator if evaluator is not None else DesignEvaluator(design, cfg)
    m = used_regulators(design)
    screen = cfg.screen_duration if cfg.screen_duration is not None and cfg.screen_duration < cfg.duration else None
    search_t = screen or cfg.duration
    n_eval, n_full, sim, n_div = 0, 0, 0.0, 0
    candidates: list[tuple[float, int, np.ndarray]] = []  # (search reward, L, x)
    per_cycle = {}
    for ci, L in enumerate(cfg.cycles):
        def f(x, L=L):
            nonlocal n_eval, n_full, sim, n_div
            r, div = ev(_knots_to_gait(x, m, L, cfg.hold), search_t)
            n_eval, sim, n_div = n_eval + 1, sim + search_t, n_div + int(div)
            n_full += int(screen is None)
            return DIVERGED_CM if div else r
        _, best_v, hist = cma_maximize(f, m * L, cfg.evals_per_cycle, [s.ravel() for s in _seed_knots(m, L)],
                                       sigma0=cfg.sigma0, popsize=cfg.popsize,
                                       seed=design_seed(design, cfg.seed) + ci)
        per_cycle[int(L)] = best_v
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
            gait = _knots_to_gait(x, m, L, cfg.hold, wf)
            if wf == "step" and screen is None:
                r, div = v, v == DIVERGED_CM
            else:
                r, div = ev(gait, cfg.duration)
                n_eval, n_full, sim, n_div = n_eval + 1, n_full + 1, sim + cfg.duration, n_div + int(div)
                r = DIVERGED_CM if div else r
            if best is None or r > best[0]:
                best = (r, v if (wf == "step" and screen) else float("nan"), gait, L)
    r, sv, gait, L = best
    return DesignResult(design, float(r), gait.to_dict(), int(L), gait.waveform, n_eval, n_full, sim,
                        time.perf_counter() - wall, float(sv), per_cycle, n_div)


# -- screening check ---------------------------------------------------------------------------
def spearman(a: Sequence[float], b: Sequence[float]) -> float:
    """Spearman rank correlation of two equal-length samples (ties: average ranks)."""
    from scipy.stats import spearmanr

    return float(spearmanr(a, b).statistic)


def screening_agreement(designs: Iterable, cfg: GroundTruthConfig, gaits_per_design: int = 5,
                        short: Sequence[float] = (4.0, 6.0, 10.0), seed: int = 0,
                        progress: bool = True) -> dict:
    """Do short episodes rank (design, gait) pairs like full ones? Runs each of
    ``gaits_per_design`` random step gaits (random cycle length in ``cfg.cycles``, uniform knots)
    plus the seeds' first on each design with every length in ``short`` and ``cfg.duration``.

    Returns:
        dict with ``pairs`` (design, gait, rewards per duration), ``spearman`` (per short
        duration, over all pairs), ``spearman_design_best`` (per short duration: over designs, the
        best pair's reward), ``spearman_within_design`` (mean over designs), ``wall_seconds``
        per duration (1 process).
    """
    from tqdm.auto import tqdm

    rng = np.random.default_rng(seed)
    durations = sorted(set([float(s) for s in short] + [cfg.duration]))
    pairs, wall = [], {d: 0.0 for d in durations}
    designs = [canonicalize(d) for d in designs]
    bar = tqdm(total=len(designs) * (gaits_per_design + 1), desc="screening", disable=not progress)
    for d in designs:
        ev = DesignEvaluator(d, cfg)
        m = used_regulators(d)
        gaits = [_knots_to_gait(_seed_knots(m, 3)[0].ravel(), m, 3, cfg.hold)]
        for _ in range(gaits_per_design):
            L = int(rng.choice(cfg.cycles))
            gaits.append(_knots_to_gait(rng.random(m * L), m, L, cfg.hold))
        for g in gaits:
            row = {"design": list(d), "gait": g.to_dict(), "reward_cm": {}}
            for T in durations:
                t0 = time.perf_counter()
                r, div = ev(g, T)
                wall[T] += time.perf_counter() - t0
                row["reward_cm"][str(T)] = DIVERGED_CM if div else r
            pairs.append(row)
            bar.update()
    bar.close()
    full = [p["reward_cm"][str(cfg.duration)] for p in pairs]
    out = {"durations": durations, "pairs": pairs, "wall_seconds": {str(k): v for k, v in wall.items()},
           "spearman": {}, "spearman_design_best": {}, "spearman_within_design": {}}
    for T in durations[:-1] if durations[-1] == cfg.duration else durations:
        if T == cfg.duration:
            continue
        s = [p["reward_cm"][str(T)] for p in pairs]
        out["spearman"][str(T)] = spearman(s, full)
        by = {}
        for p in pairs:
            by.setdefault(tuple(p["design"]), []).append((p["reward_cm"][str(T)], p["reward_cm"][str(cfg.duration)]))
        if len(by) >= 3:
            out["spearman_design_best"][str(T)] = spearman([max(a for a, _ in v) for v in by.values()],
                                                           [max(b for _, b in v) for v in by.values()])
        within = [spearman([a for a, _ in v], [b for _, b in v]) for v in by.values() if len(v) >= 3]
        out["spearman_within_design"][str(T)] = float(np.nanmean(within)) if within else float("nan")
    return out


# -- runs ---------------------------------------------------------------------------------------
RESULTS = "results.jsonl"


def parse_designs(spec: str) -> list[Design]:
    """Design set from text: ``"3"`` (all canonical designs with 3 legs; ``"3,4"`` ...), ``"all"``
    (6,972), or designs separated by ``;`` (``"1,0,0,2,2,0,0,0; 1,0,0,2,2,0,0,1"``), canonicalised.

    Raises:
        ValueError / InvalidDesignError: an unreadable set.
    """
    spec = spec.strip()
    if spec == "all":
        return list(canonical_designs())
    if ";" not in spec and all(p.strip().isdigit() and len(p.strip()) == 1 for p in spec.split(",")) \
            and len(spec.split(",")) < 8:
        legs = {int(p) for p in spec.split(",")}
        if not legs <= {3, 4, 5, 6}:
            raise ValueError(f"leg counts must be in 3..6, got {sorted(legs)}")
        return [d for d in canonical_designs() if sum(v > 0 for v in d) in legs]
    out, seen = [], set()
    for part in spec.split(";"):
        if part.strip():
            d = canonicalize(part)
            if d not in seen:
                seen.add(d)
                out.append(d)
    if not out:
        raise ValueError("empty design set")
    return out


def read_results(out_dir: str | Path) -> tuple[dict[Design, DesignResult], list[str]]:
    """The rows of a ground truth's ``results.jsonl``, read and never written:
    ``(results by design, problems)``. Each row is validated (:meth:`DesignResult.from_dict`);
    a bad row (not JSON, as a line cut short by a killed run, or not a valid result) is left
    out of the results and in the file, and described in ``problems`` by file and line. Of
    two rows of one design the later counts (a design recomputed after a bad row).

    Raises:
        UnsafeFileError: ``results.jsonl`` is a symbolic link, not a regular file, or too large.
    """
    path = Path(out_dir) / RESULTS
    if path.is_symlink():
        raise UnsafeFileError(f"{path} is a symbolic link; a ground truth's results must be a file in its folder")
    if not path.exists():
        return {}, []
    good, bad = {}, []
    for n, line in enumerate(read_text(path).split("\n"), start=1):
        if not line.strip():
            continue
        where = f"{path}, line {n}"
        try:
            r = DesignResult.from_dict(loads_json(line, where), where)
        except ValueError as exc:
            bad.append(str(exc))
            continue
        good[r.design] = r
    return good, bad


def load_results(out_dir: str | Path) -> dict[Design, DesignResult]:
    """The valid rows of :func:`read_results`; each bad row is a note on stderr naming its file
    and line (the row stays in the file)."""
    good, bad = read_results(out_dir)
    for problem in bad:
        note(f"{problem}; row left in place and not used")
    return good


def _append(path: Path, result: DesignResult) -> None:
    """Append one row to ``results.jsonl`` and fsync it. A last line left unfinished by a
    killed run is first ended, so that it stays a (bad) line of its own.

    Raises:
        UnsafeFileError: the file is a symbolic link or not a regular file.
    """
    line = (json.dumps(result.to_dict(), allow_nan=False) + "\n").encode()
    try:
        fd = os.open(path, os.O_RDWR | os.O_APPEND | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    except OSError:
        if path.is_symlink():
            raise UnsafeFileError(f"{path} is a symbolic link; a ground truth's results must be a file "
                                  "in its folder") from None
        raise
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise UnsafeFileError(f"{path}: not a regular file")
        if st.st_size and os.pread(fd, 1, st.st_size - 1) != b"\n":
            line = b"\n" + line
        os.write(fd, line)
        os.fsync(fd)
    finally:
        os.close(fd)


#: Lock file of a ground-truth folder: held (``fcntl.flock``) by the run writing it.
LOCK = ".groundtruth.lock"


class FolderLockedError(ValueError):
    """Another process is writing this ground-truth folder."""


def read_config(out_dir: str | Path) -> GroundTruthConfig:
    """The settings saved in a ground-truth folder's ``config.json``.

    Raises:
        FileNotFoundError: no ``config.json``.
        ValueError: not a ground truth's ``config.json`` (the message names the file).
    """
    path = Path(out_dir) / "config.json"
    doc = load_json(path)
    try:
        if not isinstance(doc, dict) or "config" not in doc:
            raise ValueError('no "config" object')
        return GroundTruthConfig.from_dict(doc["config"])
    except ValueError as exc:
        raise ValueError(f"{path}: not a ground truth's settings ({exc})") from None


def check_folder(out_dir: str | Path) -> Path:
    """``--out`` of ``softcrawl groundtruth``, checked before any work: a folder that can be
    created, an empty one, or a ground-truth folder (its ``config.json`` readable); never a
    folder another command wrote (a simulation, a deployment, a training run).

    Raises:
        OutputExistsError: not a directory, or not writable.
        ValueError: a folder of other files, or a ``config.json`` that is not a ground truth's.
    """
    from softcrawl.robot.output import OutputExistsError, check_output_path

    out = Path(out_dir)
    if not out.exists() and not out.is_symlink():
        return check_output_path(out)
    if out.is_symlink() or not out.is_dir():
        raise OutputExistsError(f"{out} exists and is not a directory")
    if (out / "config.json").exists() or (out / "config.json").is_symlink():
        try:
            read_config(out)
        except ValueError as exc:
            raise ValueError(f"{out} is not a ground-truth folder: {exc}; use another --out") from None
    else:
        others = sorted(p.name for p in out.iterdir() if p.name != LOCK)
        if others:
            raise ValueError(f"{out} holds other files ({', '.join(others[:3])}{', ...' if len(others) > 3 else ''}) "
                             "and no ground truth; use another --out")
    if not os.access(out, os.W_OK | os.X_OK):
        raise OutputExistsError(f"{out} is not writable")
    return out


@contextlib.contextmanager
def folder_lock(out: Path):
    """Hold the advisory lock :data:`LOCK` of the folder ``out`` (it holds the holder's pid).

    Raises:
        FolderLockedError: another process holds it.
    """
    import fcntl

    fd = os.open(out / LOCK, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            pid = os.pread(fd, 32, 0).decode("ascii", "replace").strip() or "?"
            raise FolderLockedError(f"{out} is being written by another softcrawl groundtruth (process {pid}); "
                                    "wait for it to finish or use another --out") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        yield
    finally:
        os.close(fd)  # releases the lock


def _task(design: Design, cfg_dict: dict) -> dict:
    """Worker entry: one design's ground truth as a dict (picklable, module level)."""
    return optimize_design(design, GroundTruthConfig.from_dict(cfg_dict)).to_dict()


def _pin_threads(parent_pid: int | None = None) -> None:
    """Worker initializer: one BLAS thread; with ``parent_pid``, a watchdog thread that ends the
    worker when that process is gone (a killed run must not leave workers computing)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    if parent_pid is not None:
        import threading

        import psutil

        def watch():
            while psutil.pid_exists(parent_pid):
                time.sleep(2.0)
            os._exit(1)

        threading.Thread(target=watch, daemon=True).start()
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover
        pass


def references(cfg: GroundTruthConfig, progress: bool = False) -> dict:
    """Reference gaits with the run's settings: the expert baseline (design
    :data:`BASELINE_DESIGN`, smooth sine at every lag of ``cfg.baseline_phases``, best kept) and
    the paper's 3-s cycle on :data:`PAPER_BEST_DESIGN`; cm per ``cfg.duration`` s."""
    out: dict = {}
    if cfg.baseline_phases:
        ev = DesignEvaluator(BASELINE_DESIGN, cfg)
        sweep = {}
        for ph in cfg.baseline_phases:
            r, div = ev(PeriodicGait.expert_sine(ph, hold=cfg.hold), cfg.duration)
            sweep[str(ph)] = DIVERGED_CM if div else r
        best = max(sweep, key=sweep.get)
        out["expert_baseline"] = {"design": list(BASELINE_DESIGN), "best_phase_deg": float(best),
                                  "reward_cm": sweep[best], "sweep_cm": sweep}
    ev = DesignEvaluator(PAPER_BEST_DESIGN, cfg)
    paper = PeriodicGait.paper_cycle(hold=cfg.hold)
    r, div = ev(paper, cfg.duration)
    out["paper_l1_gait"] = {"design": list(PAPER_BEST_DESIGN), "gait": paper.to_dict(),
                            "reward_cm": DIVERGED_CM if div else r, "paper_reported_cm": PAPER_L1_CM}
    return out


def run_groundtruth(designs: Sequence, out_dir: str | Path, cfg: GroundTruthConfig | None = None,
                    workers: int | None = None, executor: str = "process", progress: bool = True,
                    task: Callable[[Design, dict], dict] = _task, ray_address: str | None = None,
                    refs: bool = True) -> dict:
    """Ground truth of ``designs`` into ``out_dir`` (see the module docstring); resumable.

    Everything is checked before any design is computed: the folder (:func:`check_folder`),
    the settings, the designs. The folder is locked while the run writes it
    (:func:`folder_lock`): a second run on it stops at once.

    Args:
        designs: designs (canonicalised; duplicates dropped).
        out_dir: run folder (created; an existing one must hold the same config).
        cfg: settings (default :class:`GroundTruthConfig`; None on an existing folder: its own).
        workers: processes (``executor="process"``; default: CPU count) or Ray CPUs.
        executor: ``"process"`` (pool), ``"serial"`` (in-process) or ``"ray"`` (Ray tasks, local
            Ray unless ``ray_address``).
        task: ``(design, cfg dict) -> DesignResult dict`` (tests inject counting fakes).
        refs: compute ``references.json`` (expert baseline sweep, paper gait) if missing.

    Returns:
        The summary dict (also ``summary.json``).

    Raises:
        ValueError: config mismatch with an existing folder, unknown executor, empty design set,
            settings out of bounds, a folder another command wrote (:func:`check_folder`).
        FolderLockedError: another run is writing the folder.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {EXECUTORS}, got {executor!r}")
    designs = list(dict.fromkeys(canonicalize(d) for d in designs))
    if not designs:
        raise ValueError("empty design set")
    out = check_folder(out_dir)
    if cfg is not None and cfg.dt is None:  # record the concrete time step
        cfg = dataclasses.replace(cfg, dt=cfg.robot_config().dt)
    if cfg is not None:
        cfg.validate()
    out.mkdir(parents=True, exist_ok=True)
    with folder_lock(out):
        cfg_path = out / "config.json"
        if cfg_path.exists():
            saved = read_config(out)
            if cfg is not None and cfg.to_dict() != saved.to_dict():
                diff = {k: (v, cfg.to_dict()[k]) for k, v in saved.to_dict().items() if cfg.to_dict()[k] != v}
                raise ValueError(f"{out} holds a ground truth with other settings (saved vs given: {diff}); "
                                 "use another folder")
            cfg = saved
        else:
            cfg = (cfg or GroundTruthConfig()).validate()
            from softcrawl import __version__

            saved = {"config": cfg.to_dict(), "softcrawl": __version__}
            atomic_write_text(cfg_path, json.dumps(saved, indent=2) + "\n")
        return _compute(designs, out, cfg, workers, executor, progress, task, ray_address, refs)


def _compute(designs: list, out: Path, cfg: GroundTruthConfig, workers, executor, progress, task, ray_address,
             refs) -> dict:
    """The body of :func:`run_groundtruth` once the folder is locked and its settings known."""
    done = load_results(out)
    todo = [d for d in designs if d not in done]
    res_path = out / RESULTS
    cd = cfg.to_dict()
    wall = time.perf_counter()
    from tqdm.auto import tqdm

    bar = tqdm(total=len(designs), initial=len(designs) - len(todo), desc="ground truth", unit="design",
               disable=not progress, dynamic_ncols=True)

    def finish(d_result: dict) -> None:
        r = DesignResult.from_dict(d_result)
        _append(res_path, r)
        done[r.design] = r
        bar.update()
        bar.set_postfix(last=f"{r.reward_cm:+.2f}cm", refresh=False)

    if todo:
        if executor == "serial":
            for d in todo:
                finish(task(d, cd))
        elif executor == "process":
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            _pin_threads()  # inherited by the workers before they import numpy
            n = max(1, min(len(todo), workers or os.cpu_count() or 1))
            method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
            pool = ProcessPoolExecutor(n, mp_context=mp.get_context(method), initializer=_pin_threads,
                                       initargs=(os.getpid(),))
            try:
                futs = [pool.submit(task, d, cd) for d in todo]
                for fut in as_completed(futs):
                    finish(fut.result())
            except BaseException:  # Ctrl-C or a failed design: do not wait for the running ones
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
        else:
            from softcrawl.parallel import ray_map

            for res in ray_map(task, [(d, cd) for d in todo], address=ray_address, num_cpus=workers):
                finish(res)
    bar.close()
    ref_path = out / "references.json"
    if refs and read_references(out) is None:
        atomic_write_text(ref_path, json.dumps(references(cfg), indent=2, allow_nan=False) + "\n")
    return write_outputs(out, designs, time.perf_counter() - wall)


def read_references(out_dir: str | Path) -> dict | None:
    """``references.json`` of a ground-truth folder, or None if it is missing or not valid
    (a note says so): an object of references, each with a finite ``reward_cm``."""
    path = Path(out_dir) / "references.json"
    if not path.exists() and not path.is_symlink():
        return None
    try:
        refs = load_json(path)
        if not isinstance(refs, dict) or not all(isinstance(v, dict) and _finite(v.get("reward_cm"))
                                                 for v in refs.values()):
            raise ValueError("not an object of references with finite rewards")
        if not _finite(refs.get("expert_baseline", {"best_phase_deg": 0.0}).get("best_phase_deg")):
            raise ValueError("the expert baseline has no finite best_phase_deg")
    except (ValueError, OSError) as exc:
        note(f"{exc if str(path) in str(exc) else f'{path}: {exc}'}; references left out")
        return None
    return refs


def _design_str(d) -> str:
    return "".join(map(str, d))


def write_outputs(out_dir: str | Path, designs: Sequence | None = None, wall_seconds: float | None = None) -> dict:
    """Write ``groundtruth.csv``, ``ranked.png`` and ``summary.json`` (each replaced
    atomically) from the valid rows of ``results.jsonl`` (only those in ``designs`` if given;
    the bad rows, by file and line, in the summary's ``bad_rows``); returns the summary.

    Raises:
        ValueError: the folder's ``config.json`` is missing or not a ground truth's.
    """
    out = Path(out_dir)
    cfg = read_config(out)
    done, bad = read_results(out)  # the bad rows are listed in the summary
    if designs is not None:
        keep = {canonicalize(d) for d in designs}
        done = {d: r for d, r in done.items() if d in keep}
    rows = sorted(done.values(), key=lambda r: (-r.reward_cm, r.design))
    table = io.StringIO()
    w = csv.writer(table)
    w.writerow(["rank", "design", "reward_cm", "cycle", "waveform", "gait_kpa", "evaluations",
                "full_evaluations", "sim_seconds", "wall_seconds", "diverged"])
    for i, r in enumerate(rows, start=1):
        g = PeriodicGait.from_dict(r.gait)
        w.writerow([i, ",".join(map(str, r.design)), f"{r.reward_cm:.4f}", r.cycle, r.waveform,
                    json.dumps([[round(v, 2) for v in p] for p in g.patterns]), r.evaluations,
                    r.full_evaluations, f"{r.sim_seconds:.1f}", f"{r.wall_seconds:.1f}", r.diverged])
    atomic_write_text(out / "groundtruth.csv", table.getvalue())
    refs = read_references(out) or {}
    rewards = np.array([r.reward_cm for r in rows])

    def place(d):
        d = tuple(d)
        if d not in done:
            return None
        rank = 1 + int(np.sum(rewards > done[d].reward_cm))
        return {"design": list(d), "reward_cm": done[d].reward_cm, "rank": rank,
                "percentile": 100.0 * (1 - (rank - 1) / len(rows))}

    summary = {
        "designs": len(rows), "requested": len(designs) if designs is not None else len(rows),
        "config": cfg.to_dict(),
        "best": [{"design": list(r.design), "reward_cm": r.reward_cm, "gait": PeriodicGait.from_dict(r.gait).describe()}
                 for r in rows[:10]],
        "reward_cm": {"max": float(rewards.max()) if len(rows) else None,
                      "median": float(np.median(rewards)) if len(rows) else None,
                      "min": float(rewards.min()) if len(rows) else None},
        "paper_l1": place(PAPER_BEST_DESIGN), "expert_design": place(BASELINE_DESIGN),
        "references": {k: {kk: vv for kk, vv in v.items() if kk != "sweep_cm"} for k, v in refs.items()},
        "cost": {"evaluations": int(sum(r.evaluations for r in rows)),
                 "sim_seconds": float(sum(r.sim_seconds for r in rows)),
                 "cpu_seconds": float(sum(r.wall_seconds for r in rows)),
                 "cpu_seconds_per_design": float(np.mean([r.wall_seconds for r in rows])) if rows else None,
                 "this_call_wall_seconds": wall_seconds},
        "bad_rows": bad,
    }
    if "expert_baseline" in refs and len(rows):
        b = refs["expert_baseline"]["reward_cm"]
        summary["designs_beating_expert_baseline"] = int(np.sum(rewards > b))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2, allow_nan=False) + "\n")
    if rows:
        _ranked_plot(rows, refs, out / "ranked.png", cfg)
    return summary


def _ranked_plot(rows: list[DesignResult], refs: dict, path: Path, cfg: GroundTruthConfig) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.array([x.reward_cm for x in rows])
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(np.arange(1, len(r) + 1), r, ".-", color="0.4", ms=4, lw=0.8, label="designs (best gait)")
    for i, x in enumerate(rows):
        if x.design == PAPER_BEST_DESIGN:
            ax.plot(i + 1, x.reward_cm, "o", color="C3", ms=9, label=f"paper L1 1,0,0,2,2,0,0,0 (rank {i + 1})")
        if x.design == BASELINE_DESIGN:
            ax.plot(i + 1, x.reward_cm, "s", color="C0", ms=8, label=f"expert design (rank {i + 1})")
    if "expert_baseline" in refs:
        b = refs["expert_baseline"]
        ax.axhline(b["reward_cm"], color="C0", ls="--", lw=1,
                   label=f"expert baseline (sine, {b['best_phase_deg']:.0f} deg): {b['reward_cm']:+.2f} cm")
    if "paper_l1_gait" in refs:
        ax.axhline(refs["paper_l1_gait"]["reward_cm"], color="C3", ls=":", lw=1,
                   label=f"paper L1 with paper's 3-s gait: {refs['paper_l1_gait']['reward_cm']:+.2f} cm")
    ax.set_xlabel("rank")
    ax.set_ylabel(f"reward (cm per {cfg.duration:g} s)")
    ax.set_title(f"Ground truth: {len(r)} designs, best gait each (reduced model)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def load_groundtruth(gt_dir: str | Path) -> tuple[GroundTruthConfig, dict[Design, DesignResult], dict]:
    """``(config, results by design, references)`` of a ground-truth folder.

    Raises:
        ValueError: not a ground-truth folder, or no finished design.
    """
    gt = Path(gt_dir)
    if not (gt / "config.json").exists():
        raise ValueError(f"{gt} is not a ground-truth folder (no config.json)")
    cfg = read_config(gt)
    res = load_results(gt)
    if not res:
        raise ValueError(f"{gt} has no finished design yet")
    return cfg, res, read_references(gt) or {}
