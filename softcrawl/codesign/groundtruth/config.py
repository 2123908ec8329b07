"""Settings of a ground-truth run (:class:`GroundTruthConfig`, saved as its ``config.json``) and its
design set (:func:`parse_designs`, recorded beside them as :func:`design_set_spec`)."""

from __future__ import annotations

import dataclasses
import importlib.util
from dataclasses import dataclass, field

from softcrawl.codesign.config import MAX_EPISODE_S, MAX_HOLD_S, SIM_BOUNDS, build_config, check_bounds, space_robot
from softcrawl.design.resolve import PAPER_SPACE, resolve_space
from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.gaits.periodic import MAX_KNOTS
from softcrawl.robot.assembly import RobotConfig
from softcrawl.tasks import DEFAULT_TASK, Task, parse_task

#: Upper bounds of the search settings (far beyond the defaults 36, 2 and cma's 4 + 3 ln n).
MAX_EVALS, MAX_FINALISTS, MAX_POPSIZE = 100_000, 1000, 10_000
#: Engines of the searched episodes (:attr:`GroundTruthConfig.engine`) and the JAX batch's bound.
ENGINES, MAX_JAX_BATCH = ("cpu", "jax"), 65_536
#: Most designs a batched engine searches at once (``softcrawl groundtruth --in-flight``).
MAX_IN_FLIGHT = 100_000
#: The search's starting gaits (:attr:`GroundTruthConfig.seeds`).
SEED_KINDS = ("structured", "duty")


def gt_robot(**changes) -> RobotConfig:
    """The ground truth's robot (:attr:`GroundTruthConfig.robot`'s default: the reduced model,
    RID products in float32) with ``changes`` (a None change keeps the default)."""
    return RobotConfig(**({"model": "reduced", "rid_dtype": "float32"} | {k: v for k, v in changes.items()
                                                                         if v is not None}))


@dataclass
class GroundTruthConfig:
    """Settings of a ground-truth run (saved as ``config.json``; a resumed run must match).

    Attributes:
        duration: full episode, s (20: the paper's 20 actions of 1 s).
        screen_duration: episode length of the CMA-ES search, s (None: ``duration``); allowed
            where :func:`~softcrawl.codesign.groundtruth.optimize.screening_agreement` shows short
            episodes rank like full ones.
        hold: seconds per knot (= per action).
        cycles: distinct pattern lengths ``L`` searched (one CMA-ES run each, 1..8).
        evals_per_cycle: episodes per CMA-ES run.
        popsize: CMA-ES population (None: cma's default ``4 + 3 ln n``).
        sigma0: initial CMA-ES step, as a fraction of 90 kPa.
        finalists: best distinct candidates re-run with ``duration`` (step and smooth each).
        seed: CMA-ES seed, 0..2**32 - 1 (design-specific seeds are derived from it).
        seeds: the search's starting gaits (:data:`SEED_KINDS`): ``"structured"``, the CMA-ES
            runs from :func:`~softcrawl.codesign.groundtruth.search.seed_knots` (what folders of
            config formats before 9 searched); ``"duty"`` (default), those same runs, and beside
            them the bang-bang duty cycles
            (:func:`~softcrawl.codesign.groundtruth.search.duty_knots`) screened and the best of
            them a finalist too: the same episodes and more, so never a lower reward.
        robot: the simulated robot (:class:`softcrawl.robot.RobotConfig`; default
            :func:`gt_robot`: the reduced model with the shipped reduction, RID products in
            float32, validated like the training presets' model, ``docs/results.md``; every
            other field the robot's default: dt 0.01 s, 6 mm legs, 10 mm disk).
        baseline_phases: expert-baseline phase lags swept for ``references.json`` (degrees;
            empty: no sweep).
        engine: what simulates the searched episodes (:data:`ENGINES`): ``"cpu"``, the CPU
            reduced engine, one design per worker; ``"jax"``, the JAX engine
            (:class:`softcrawl.jaxsim.episodes.JaxEvaluator`) with every unfinished design's
            episode of a round in one batch, in ``robot.rid_dtype`` throughout. The
            references (``references.json``) are computed on the CPU either way.
        jax_batch: the JAX engine's largest batch (a power of two).
        space: the design space (a shipped space's name, ``"paper"`` by default, or a space
            file's path; a ground-truth folder reads its own copy, ``space.toml``,
            :mod:`softcrawl.codesign.groundtruth.store`).
        task: what the gait search maximises (:mod:`softcrawl.tasks`, docs/tasks.md): a task's
            name or a table of its settings (``{"name": "heading", "heading_deg": 90}``), as
            :attr:`softcrawl.codesign.config.EnvConfig.task`; default ``"forward"``, the paper's.
            A design's reward is the task's return over the episode (its progress, in
            :attr:`softcrawl.tasks.Task.unit`; ``"cm"`` or ``"deg"``), on the task's floor. A
            folder saved before tasks existed reads as ``"forward"``.
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
    seeds: str = "duty"
    robot: RobotConfig = field(default_factory=gt_robot)
    baseline_phases: tuple[float, ...] = tuple(range(0, 181, 10))
    engine: str = "cpu"
    jax_batch: int = 1024
    space: str = PAPER_SPACE
    task: str | dict = DEFAULT_TASK

    def design_space(self) -> DesignSpace:
        """The :class:`DesignSpace` ``space`` names (SpaceFileError, a ValueError, if none)."""
        return resolve_space(self.space)

    def task_spec(self) -> Task:
        """The :class:`softcrawl.tasks.Task` ``task`` names (ValueError, one line, if none)."""
        return parse_task(self.task)

    def robot_config(self) -> RobotConfig:
        """The simulated robot's settings: ``robot`` for the space's robots
        (:func:`softcrawl.codesign.config.space_robot`; ``robot`` itself in the paper's space)."""
        return space_robot(self.robot, self.design_space())

    def validate(self) -> GroundTruthConfig:
        """Raise ValueError naming the first bad setting; returns self."""
        if not isinstance(self.robot, RobotConfig):
            raise ValueError(f"robot must be RobotConfig, got {type(self.robot).__name__}")
        try:
            self.design_space()
        except ValueError as exc:
            raise ValueError(f"space: {exc}") from None
        try:
            task = self.task_spec()
            task.check_floor(self.robot.friction)
        except ValueError as exc:
            raise ValueError(f"task: {exc}") from None
        for name, (low, high, unit) in SIM_BOUNDS.items():
            check_bounds(f"robot.{name}", getattr(self.robot, name), low, high, unit)
        for name, high, unit in (("duration", MAX_EPISODE_S, "s"), ("hold", MAX_HOLD_S, "s"),
                                 ("sigma0", 1, "(of 90 kPa)")):
            check_bounds(name, getattr(self, name), 0, high, unit, open_low=True)
        if self.screen_duration is not None and not (0 < self.screen_duration <= self.duration):
            raise ValueError(f"screen_duration must be in (0, duration], got {self.screen_duration!r}")
        if not self.cycles or any(int(c) != c or not 1 <= c <= MAX_KNOTS for c in self.cycles) \
                or len(set(self.cycles)) != len(self.cycles):
            raise ValueError(f"cycles must be distinct pattern lengths in 1..{MAX_KNOTS}, got {self.cycles!r}")
        check_bounds("seed", self.seed, 0, 2**32 - 1)
        if self.seeds not in SEED_KINDS:
            raise ValueError(f"seeds must be one of {SEED_KINDS}, got {self.seeds!r}")
        for name, low, high in (("evals_per_cycle", 1, MAX_EVALS), ("finalists", 1, MAX_FINALISTS),
                                ("popsize", 2, MAX_POPSIZE)):
            v = getattr(self, name)
            if v is not None:
                check_bounds(name, v, low, high)
                if int(v) != v:
                    raise ValueError(f"{name} must be an integer, got {v!r}")
        if self.engine not in ENGINES:
            raise ValueError(f"engine must be one of {ENGINES}, got {self.engine!r}")
        if self.engine == "jax" and self.robot.model != "reduced":
            raise ValueError(f'engine "jax" steps the reduced robot only, got robot.model={self.robot.model!r}')
        if self.engine == "jax" and task.name != DEFAULT_TASK:
            raise ValueError(f'engine "jax" does not run task {task.name!r}: its episodes return the +x crawl of the '
                             'disk\'s top centre only (the forward task); use engine "cpu"')
        check_bounds("jax_batch", self.jax_batch, 1, MAX_JAX_BATCH)
        if int(self.jax_batch) != self.jax_batch or self.jax_batch & (self.jax_batch - 1):
            raise ValueError(f"jax_batch must be a power of two, got {self.jax_batch!r}")
        from softcrawl.robot.sweep import MAX_PHASES

        if len(self.baseline_phases) > MAX_PHASES:
            raise ValueError(f"baseline_phases: {len(self.baseline_phases)} lags, more than the {MAX_PHASES} allowed")
        for ph in self.baseline_phases:
            check_bounds("baseline_phases", ph, -360, 360, "deg")
        return self

    def check_engine(self) -> None:
        """Check now what the searches would find out later, in a worker: the reduced model's
        reduction file (``robot.reduction``, else the space's; it must match the robot, the
        space's parts and, being the space's own, its ``reduction_sha256``:
        :func:`softcrawl.reduction.artifact.load_reduction`, the checks
        :func:`softcrawl.robot.build_robot` makes) and, for ``engine="jax"``, that JAX imports.

        Raises:
            ValueError: no reduction for the reduced model, or JAX missing (one line each);
                ReductionFileError, ReductionMismatchError (ValueErrors): a bad reduction file.
        """
        if self.engine == "jax" and importlib.util.find_spec("jax") is None:
            raise ValueError('engine "jax" needs JAX: pip install "softcrawl[jax]" (or "softcrawl[gpu]")')
        config, space = self.robot_config(), self.design_space()
        if config.model != "reduced":
            return
        from softcrawl.reduction.artifact import load_reduction

        path = config.reduction or space.reduction
        if path is None:
            raise ValueError(f"the design space {space.name!r} names no reduction ([actuator] reduction) and "
                             "--reduction none: the reduced model needs one (softcrawl reduce build)")
        load_reduction(path, expect=dataclasses.asdict(config),
                       part=space.part_record(config.leg_mesh_size, config.disk_mesh_size),
                       sha256=space.reduction_sha256 if str(path) == space.reduction else None)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["cycles"], d["baseline_phases"] = list(self.cycles), list(self.baseline_phases)
        return d

    @classmethod
    def from_dict(cls, d: dict) -> GroundTruthConfig:
        """Inverse of :meth:`to_dict` (:func:`softcrawl.codesign.config.build_config`: each value
        checked against its field's type, a robot object's missing keys from :func:`gt_robot`),
        validated. Only the current format: a folder's ``config.json`` is read through
        :func:`softcrawl.codesign.groundtruth.store.read_config`.

        Raises:
            ValueError: not an object, an unknown key, a value of the wrong type (named), or a
                setting out of bounds.
        """
        return build_config(cls, d).validate()


def parse_designs(spec: str, space: DesignSpace = DEFAULT_SPACE) -> list[Design]:
    """Design set of ``space`` (default the paper's) from text: ``"3"`` (all canonical designs
    with 3 legs; ``"3,4"`` ...), ``"all"`` (6,972 in the paper's space), or designs separated by
    ``;`` (``"1,0,0,2,2,0,0,0; 1,0,0,2,2,0,0,1"``), canonicalised.

    Raises:
        ValueError / InvalidDesignError: an unreadable set, leg counts outside the space's.
    """
    spec = spec.strip()
    if spec == "all":
        return list(space.canonical_designs)
    if ";" not in spec and all(p.strip().isdigit() and len(p.strip()) == 1 for p in spec.split(",")) \
            and len(spec.split(",")) < space.n_slots:
        legs = {int(p) for p in spec.split(",")}
        if not legs <= set(range(space.min_legs, space.max_legs + 1)):
            raise ValueError(f"leg counts must be in {space.min_legs}..{space.max_legs}, got {sorted(legs)}")
        return [d for d in space.canonical_designs if sum(v > 0 for v in d) in legs]
    out, seen = [], set()
    for part in spec.split(";"):
        if part.strip():
            d = space.canonicalize(part)
            if d not in seen:
                seen.add(d)
                out.append(d)
    if not out:
        raise ValueError("empty design set")
    return out


def design_set_spec(designs, space: DesignSpace = DEFAULT_SPACE) -> str:
    """The text :func:`parse_designs` reads back as the set of the canonical ``designs`` of
    ``space``: ``"all"``, leg counts (``"3"``, ``"3,4"``) when they are every design of those
    counts, else the designs separated by ``;`` in their order (a ground truth's
    ``config.json`` records its design set so: :mod:`softcrawl.codesign.groundtruth.store`).

    Raises:
        ValueError: an empty set.
    """
    designs = list(dict.fromkeys(designs))
    if not designs:
        raise ValueError("empty design set")
    if set(designs) == set(space.canonical_designs):
        return "all"
    legs = ",".join(map(str, sorted({sum(v > 0 for v in d) for d in designs})))
    try:
        if set(parse_designs(legs, space)) == set(designs):
            return legs
    except ValueError:  # not a leg-count set of this space (too many counts, two-digit ones)
        pass
    return ";".join(",".join(map(str, d)) for d in designs)
