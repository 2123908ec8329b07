"""The expert baseline's phase sweep (``codesign.md``, "Expert baseline"): one full-order
episode of the sine gait per phase lag φ of the rear regulator, in parallel over processes.

Layout of an output directory ``out`` (written atomically by
:func:`softcrawl.robot.output.staged_directory`):

- ``sweep.json``: settings, one entry per phase (``phase_deg``, ``reward_cm`` (null if the
  episode diverged), ``displacement_cm``, ``diverged``, ``reason``, ``steps``,
  ``wall_seconds``, ``reused``), the best phase, total wall time, workers, software version.
- ``sweep.csv``: columns :data:`CSV_COLUMNS`, one row per phase.
- ``reward_vs_phase.png``: reward vs φ, best phase marked, the paper's best φ = 110° dashed.

Resuming: while it runs, each finished phase is written to ``<out>.partial/partial/`` (settings
in ``<out>.partial/settings.json``). Running the same sweep again reuses those phases (the list
of phases may differ; every other setting must match, see :func:`sweep_settings`); a work
directory from a sweep with other settings is refused (:class:`SweepSettingsMismatch`). The
work directory is removed once ``out`` is complete. A full disk or read-only file system does
not stop the sweep: phases that cannot be saved stay in memory, and if ``out`` cannot be
written either, ``sweep.json`` / ``sweep.csv`` go to a rescue folder named in the error, which
also names the work directory.
"""

from __future__ import annotations

import csv
import dataclasses
import functools
import json
import math
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from tqdm.auto import tqdm

from softcrawl import __version__
from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.spacefile import DesignSpace
from softcrawl.fem.solver import SimulationDiverged
from softcrawl.gaits import PeriodicGait, SineGait
from softcrawl.geometry.io import replace_atomically
from softcrawl.parallel import run_pool
from softcrawl.robot.actuation import PressureCalibration
from softcrawl.robot.assembly import RobotConfig, build_robot
from softcrawl.robot.episode import SettledState, Settling, run_episode, settle
from softcrawl.robot.output import (
    NO_SPACE_ERRNOS,
    OutputWriteError,
    check_output_path,
    describe_gait,
    jsonable,
    staged_directory,
)

#: The paper's best phase lag of the baseline, degrees.
PAPER_BEST_PHASE_DEG = 110.0
#: Columns of ``sweep.csv``.
CSV_COLUMNS = ("phase_deg", "reward_cm", "displacement_cm", "diverged", "steps", "wall_seconds")


class SweepSettingsMismatch(ValueError):
    """The work directory of an interrupted sweep was made with other settings."""


@dataclass(frozen=True)
class PhaseResult:
    """Outcome of one episode of the sweep.

    Attributes:
        phase_deg: lag of regulator 2 behind regulator 1, degrees.
        reward_cm: +x displacement of the disk top centre, cm; NaN if the episode diverged.
        displacement_cm: displacement up to the last valid state, cm (NaN if settling diverged).
        diverged: whether the solver failed; reason: its message ("" otherwise).
        steps: completed episode steps.
        wall_seconds: wall-clock time of the episode (settling included), s.
        reused: taken from an interrupted run's work directory instead of simulated.
    """

    phase_deg: float
    reward_cm: float
    displacement_cm: float
    diverged: bool
    reason: str
    steps: int
    wall_seconds: float
    reused: bool = False

    def to_json(self) -> dict:
        """JSON-ready dict (non-finite numbers become null)."""
        return jsonable(dataclasses.asdict(self))

    @classmethod
    def from_json(cls, d: dict) -> PhaseResult:
        """Inverse of :meth:`to_json` (null -> NaN). Raises KeyError/TypeError on a malformed dict."""
        nan = float("nan")
        return cls(float(d["phase_deg"]), nan if d["reward_cm"] is None else float(d["reward_cm"]),
                   nan if d["displacement_cm"] is None else float(d["displacement_cm"]), bool(d["diverged"]),
                   str(d["reason"]), int(d["steps"]), float(d["wall_seconds"]), bool(d.get("reused", False)))


@dataclass(frozen=True)
class SweepResult:
    """A finished sweep.

    Attributes:
        settings: JSON-ready dict of everything that determines an episode (:func:`sweep_settings`).
        phases: one :class:`PhaseResult` per phase, in the requested order.
        wall_seconds: wall-clock time of this run (reused phases cost nothing), s.
        workers: worker processes used (1 = in this process).
    """

    settings: dict
    phases: tuple[PhaseResult, ...]
    wall_seconds: float
    workers: int

    @property
    def best(self) -> PhaseResult | None:
        """The phase with the highest reward among episodes that did not diverge (the first on
        ties), or None if all diverged."""
        ok = [r for r in self.phases if not r.diverged]
        return max(ok, key=lambda r: r.reward_cm) if ok else None


#: Most phases a sweep may have (every 0.5 deg of a full turn; each is a whole episode).
MAX_PHASES = 721


def parse_phases(spec: str) -> tuple[float, ...]:
    """Phases from ``"start:stop:step"`` (degrees, stop included if on the grid) or a comma list.

    ``"0:180:10"`` gives 0, 10, ..., 180 (19 phases).

    Raises:
        ValueError: malformed spec, non-finite values, step <= 0, stop < start, repeats, or
            more than :data:`MAX_PHASES` phases.
    """
    malformed = ValueError(f"phases must be 'start:stop:step' (step > 0, stop >= start) or a comma list of degrees, "
                           f"got {spec!r}")
    try:
        grid = tuple(float(v) for v in spec.split(":")) if ":" in spec else None
        phases = tuple(float(v) for v in spec.split(",")) if grid is None else ()
    except ValueError:
        raise malformed from None
    if grid is not None:
        if len(grid) != 3 or not all(map(math.isfinite, grid)) or grid[2] <= 0 or grid[1] < grid[0]:
            raise malformed
        start, stop, step = grid
        steps = (stop - start) / step  # inf for a step tiny enough
        if steps + 1e-9 >= MAX_PHASES:
            raise ValueError(f"phases {spec!r} are more than the {MAX_PHASES} allowed")
        phases = tuple(float(v) for v in np.round(start + step * np.arange(math.floor(steps + 1e-9) + 1), 9))
    if len(phases) > MAX_PHASES:
        raise ValueError(f"phases {spec!r} are more than the {MAX_PHASES} allowed")
    if not phases or not all(map(math.isfinite, phases)) or len(set(phases)) != len(phases):
        raise ValueError(f"phases must be finite and distinct, got {spec!r}")
    return phases


def baseline_gait(phase_deg: float, n_regulators: int = DEFAULT_SPACE.n_regulators) -> SineGait | PeriodicGait:
    """The expert's sine gait with the rear regulator lagging by ``phase_deg`` for a space of
    ``n_regulators`` regulators: :class:`SineGait` for the paper's 3, else the same wave as
    :meth:`PeriodicGait.expert_sine` (regulators 3..R at 0 kPa).

    Raises:
        ValueError: ``n_regulators < 2``.
    """
    if n_regulators == DEFAULT_SPACE.n_regulators:
        return SineGait(phase_deg=phase_deg)
    return PeriodicGait.expert_sine(phase_deg, n_regulators=n_regulators)


def sweep_settings(design, config: RobotConfig, duration: float,
                   calibration: PressureCalibration = PressureCalibration(),
                   space: DesignSpace = DEFAULT_SPACE) -> dict:
    """JSON-ready dict of everything that determines an episode of the sweep except the phase:
    design, the sine gait's other parameters, duration (s), robot config, calibration, the
    settling rule and the software version, and for a space other than the paper's its name
    and file checksum. Two sweeps may share finished phases only if these match."""
    gait = describe_gait(baseline_gait(0.0, space.n_regulators))
    gait.pop("phase_deg", None)
    other = {} if space == DEFAULT_SPACE else {"space": {"name": space.name, "sha256": space.sha256}}
    return jsonable({
        "design": list(space.validate_design(design)), "gait": gait, "duration_s": float(duration),
        "config": dataclasses.asdict(config), "calibration": {"a": calibration.a, "b": calibration.b},
        "settling": dataclasses.asdict(Settling()), "softcrawl_version": __version__, **other,
    })


@functools.lru_cache(maxsize=1)
def _robot(design: tuple[int, ...], config: RobotConfig, space: DesignSpace = DEFAULT_SPACE):
    return build_robot(design, config, space=space)  # one per worker process; episodes do not modify it


@functools.lru_cache(maxsize=1)
def _settled(design: tuple[int, ...], config: RobotConfig, space: DesignSpace = DEFAULT_SPACE) -> SettledState | None:
    """The robot at rest, once per worker process (None if settling diverged: each episode
    then settles again and reports the divergence)."""
    try:
        return settle(_robot(design, config, space))
    except SimulationDiverged:
        return None


def run_phase(design: Sequence[int], config: RobotConfig, phase_deg: float, duration: float,
              calibration: PressureCalibration = PressureCalibration(),
              space: DesignSpace = DEFAULT_SPACE) -> PhaseResult:
    """Run one episode of the expert gait at ``phase_deg`` (:func:`baseline_gait` of the
    space's regulators; no frames, no progress bar) on ``design`` of ``space``.

    A diverged episode is returned with ``diverged=True`` and ``reward_cm`` NaN.

    Raises:
        InvalidDesignError, ValueError, MeshError: for invalid inputs (see :func:`build_robot`).
    """
    design = space.validate_design(design)
    res = run_episode(_robot(design, config, space), baseline_gait(phase_deg, space.n_regulators), duration,
                      calibration, record_every=None, progress=False, settled=_settled(design, config, space))
    return PhaseResult(float(phase_deg), float("nan") if res.diverged else res.reward_cm, res.reward_cm,
                       res.diverged, res.reason, res.steps, res.wall_seconds)


def _flatten(d: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in d.items():
        out.update(_flatten(v, f"{prefix}{k}.") if isinstance(v, dict) else {f"{prefix}{k}": v})
    return out


def _open_work_dir(work: Path, settings: dict) -> dict[float, PhaseResult]:
    """Create the work directory or check its settings; return its finished phases by phase.

    Raises:
        SweepSettingsMismatch: the directory holds a sweep with other settings.
        ValueError: an unreadable settings or phase file.
    """
    path = work / "settings.json"
    if not path.exists():
        shutil.rmtree(work / "partial", ignore_errors=True)  # phase files without settings cannot be trusted
        (work / "partial").mkdir(parents=True)
        replace_atomically(path, lambda tmp: tmp.write_text(json.dumps(settings, indent=1) + "\n", encoding="utf-8"))
        return {}
    try:
        old = json.loads(path.read_text(encoding="utf-8"))
        done = {}
        for f in sorted((work / "partial").glob("phase_*.json")):
            r = PhaseResult.from_json(json.loads(f.read_text(encoding="utf-8")))
            done[r.phase_deg] = dataclasses.replace(r, reused=True)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"cannot read the interrupted sweep in {work} ({exc}); delete it to start over") from exc
    if old != settings:
        a, b = _flatten(old), _flatten(settings)
        diff = "; ".join(f"{k}: {a.get(k)!r} there, {b.get(k)!r} now" for k in sorted(a.keys() | b.keys())
                         if a.get(k) != b.get(k))
        raise SweepSettingsMismatch(f"{work} holds an interrupted sweep with other settings ({diff}); re-run it "
                                    f"with the same settings to resume, or delete {work} to start over")
    return done


def _save_phase(work: Path, r: PhaseResult) -> None:
    path = work / "partial" / f"phase_{r.phase_deg!r}.json"  # repr: distinct phases, distinct names
    replace_atomically(path, lambda tmp: tmp.write_text(json.dumps(r.to_json()) + "\n", encoding="utf-8"))


def run_sweep(out: str | os.PathLike, phases: Sequence[float], design, config: RobotConfig = RobotConfig(),
              duration: float = 20.0, workers: int | None = None, overwrite: bool = False,
              progress: bool = True, space: DesignSpace = DEFAULT_SPACE) -> SweepResult:
    """Run (or resume) the phase sweep and write its outputs (module docstring) into ``out``.

    Args:
        out: output directory; its work directory is ``<out>.partial``.
        phases: phase lags φ, degrees (distinct, finite).
        design: one value per slot of ``space`` (sequence or string such as ``"1,0,0,2,2,0,0,1"``).
        config: robot settings (leg mesh size, factorization reuse, ...; another space's:
            :meth:`RobotConfig.for_space`).
        duration: episode length, s.
        workers: worker processes (default ``os.cpu_count()``; capped at the number of phases
            left). Each is started with one BLAS thread (spawn context). 1 runs the episodes in
            this process.
        overwrite: replace an existing ``out``.
        progress: tqdm bar over finished episodes (rate, ETA) on stderr.
        space: the design's space (slots, regulators, parts; at least 2 regulators).

    Returns:
        The :class:`SweepResult` (phases in the given order).

    Raises:
        OutputExistsError: ``out`` exists and ``overwrite`` is False (checked before any work).
        SweepSettingsMismatch: ``<out>.partial`` is from a sweep with other settings.
        ValueError / InvalidDesignError: invalid phases, duration, workers or design.
        Any error of an episode other than divergence (finished phases stay in the work
        directory; ``out`` is not written).
    """
    phases = tuple(float(p) for p in phases)
    if not phases or not all(map(math.isfinite, phases)) or len(set(phases)) != len(phases):
        raise ValueError(f"phases must be non-empty, finite and distinct, got {phases}")
    if not (math.isfinite(duration) and duration >= config.dt):
        raise ValueError(f"duration must be at least one time step ({config.dt} s), got {duration}")
    workers = (os.cpu_count() or 1) if workers is None else int(workers)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    design = space.validate_design(design)
    out = check_output_path(out, overwrite)
    work = out.with_name(out.name + ".partial")
    settings = sweep_settings(design, config, duration, space=space)
    done = _open_work_dir(work, settings)
    todo = [p for p in phases if p not in done]
    workers = max(1, min(workers, len(todo)))
    wall = time.perf_counter()
    if todo:
        _robot(design, config, space)  # fail early on a bad config; fills the mesh cache for the workers
    bar = tqdm(total=len(todo), unit="episode", desc=f"sweep ({len(done)} reused)" if done else "sweep",
               disable=not progress, dynamic_ncols=True)

    unsaved = []

    def finished(r: PhaseResult) -> None:
        done[r.phase_deg] = r
        try:
            _save_phase(work, r)
        except OSError as exc:  # a full disk: keep sweeping, the results are written (or rescued) at the end
            if exc.errno not in NO_SPACE_ERRNOS:
                raise
            if not unsaved:
                bar.write(f"softcrawl: cannot save finished phases in {work} ({exc.strerror}); carrying on, "
                          "the sweep is written (or rescued) at the end", file=sys.stderr)
            unsaved.append(r.phase_deg)
        bar.set_postfix(phase=f"{r.phase_deg:g}", reward="diverged" if r.diverged else f"{r.reward_cm:+.2f}cm",
                        refresh=False)
        bar.update()

    try:
        calibration = PressureCalibration()
        run_pool(run_phase, workers, [(design, config, p, duration, calibration, space) for p in todo], finished)
    finally:
        bar.close()
    result = SweepResult(settings, tuple(done[p] for p in phases), time.perf_counter() - wall, workers)
    try:
        write_sweep(out, result, overwrite)
    except OutputWriteError as exc:
        saved = len(done) - len(unsaved)
        raise OutputWriteError(f"{exc}; {saved} finished phase(s) are also kept in {work} (the same command "
                               "resumes from them)") from None
    shutil.rmtree(work, ignore_errors=True)
    return result


def sweep_json(result: SweepResult) -> dict:
    """The content of ``sweep.json`` (JSON-ready; non-finite numbers become null)."""
    best = result.best
    return jsonable({
        "settings": result.settings,
        "phases": [r.to_json() for r in result.phases],
        "best": None if best is None else {"phase_deg": best.phase_deg, "reward_cm": best.reward_cm},
        "paper_best_phase_deg": PAPER_BEST_PHASE_DEG,
        "wall_seconds": result.wall_seconds,
        "episode_wall_seconds": sum(r.wall_seconds for r in result.phases),
        "reused_phases": [r.phase_deg for r in result.phases if r.reused],
        "workers": result.workers,
        "softcrawl_version": __version__,
    })


def format_table(result: SweepResult) -> str:
    """Human-readable reward table: one line per phase (reward in cm or ``DIVERGED``, wall
    time), the best phase marked ``<- best``."""
    best = result.best
    lines = [f"{'phase (deg)':>11}  {'reward (cm)':>11}  {'wall (s)':>8}"]
    for r in result.phases:
        reward = f"{'DIVERGED':>11}" if r.diverged else f"{r.reward_cm:>+11.3f}"
        note = "  <- best" if r is best else ("  (reused)" if r.reused else "")
        if r.diverged:
            note += f"  after {r.steps} steps: {r.reason}"
        lines.append(f"{r.phase_deg:>11g}  {reward}  {r.wall_seconds:>8.1f}{note}")
    lines.append(f"best: {best.phase_deg:g} deg, {best.reward_cm:+.3f} cm" if best else "best: none (all diverged)")
    return "\n".join(lines)


def plot_reward_vs_phase(path: Path, result: SweepResult) -> None:
    """Save a PNG of reward (cm) vs phase (deg): episodes as dots, diverged ones as red crosses at
    their last displacement, the best as a star, the paper's best phase as a dashed line."""
    fig = Figure(figsize=(7, 4.5), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    ph = np.array([r.phase_deg for r in result.phases])
    rw = np.array([r.reward_cm for r in result.phases])
    ok = ~np.array([r.diverged for r in result.phases])
    ax.plot(ph[ok], rw[ok], "o-", color="k", label="episode")
    if not ok.all():
        ax.plot(ph[~ok], [r.displacement_cm for r in result.phases if r.diverged], "x", color="C3", ms=9,
                label="diverged (last displacement)")
    best = result.best
    if best is not None:
        ax.plot([best.phase_deg], [best.reward_cm], "*", color="C1", ms=16,
                label=f"best: {best.phase_deg:g}° ({best.reward_cm:+.2f} cm)")
    ax.axvline(PAPER_BEST_PHASE_DEG, ls="--", color="C0", label=f"paper's best φ = {PAPER_BEST_PHASE_DEG:g}°")
    s = result.settings
    ax.set_title(f"design {','.join(map(str, s['design']))}, sine gait, {s['duration_s']:g} s episodes, "
                 f"{s['config']['leg_mesh_size']:g} mm legs", fontsize="medium")
    ax.set_xlabel("phase lag φ of the rear regulator (deg)")
    ax.set_ylabel("reward: x displacement (cm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize="small")
    fig.savefig(path, dpi=120)


def write_sweep(out: str | os.PathLike, result: SweepResult, overwrite: bool = False) -> Path:
    """Write ``sweep.json``, ``sweep.csv`` and ``reward_vs_phase.png`` into ``out`` atomically
    (on a full or read-only disk, ``sweep.json`` and ``sweep.csv`` are saved into a rescue
    folder instead: :func:`softcrawl.robot.output.staged_directory`).

    Raises:
        OutputExistsError: ``out`` exists and ``overwrite`` is False.
        OutputWriteError: disk full / read-only (names where the results are kept).
    """
    def tables(folder: Path) -> None:
        (folder / "sweep.json").write_text(json.dumps(sweep_json(result), indent=2) + "\n", encoding="utf-8")
        with (folder / "sweep.csv").open("w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(CSV_COLUMNS)
            for r in result.phases:
                w.writerow([f"{r.phase_deg:g}", "" if r.diverged else f"{r.reward_cm:.6g}",
                            f"{r.displacement_cm:.6g}", int(r.diverged), r.steps, f"{r.wall_seconds:.2f}"])

    with staged_directory(out, overwrite, rescue=tables) as tmp:
        tables(tmp)
        plot_reward_vs_phase(tmp / "reward_vs_phase.png", result)
    return Path(out)
