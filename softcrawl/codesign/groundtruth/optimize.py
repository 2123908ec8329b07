"""The best gait of one design (:func:`optimize_design`) on the reduced model
(:class:`DesignEvaluator`), and the check that short screening episodes rank gaits like full
ones (:func:`screening_agreement`)."""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable, Iterable, Sequence

import numpy as np

from softcrawl.codesign.groundtruth.config import GroundTruthConfig
from softcrawl.codesign.groundtruth.result import DIVERGED_CM, DesignResult
from softcrawl.codesign.groundtruth.search import design_rounds, drive, knots_to_gait, seed_knots, used_regulators
from softcrawl.tasks import DEFAULT_TASK


class DesignEvaluator:
    """Episodes of one design on the reduced model: ``evaluator(gait, duration) -> (return,
    diverged)``, the return of ``cfg``'s task (:meth:`GroundTruthConfig.task_spec`) in its unit.

    The robot is built in ``cfg``'s design space, stood on the task's floor
    (:func:`softcrawl.tasks.on_floor`: its friction and gravity), and settled once
    (:func:`softcrawl.robot.episode.settle` with the default
    :class:`~softcrawl.robot.episode.Settling`); each episode starts from that rested state with
    a fresh solver (:func:`softcrawl.robot.episode.run_episode`). The return of the paper's
    task (``forward``) is the episode's ``reward_cm`` (the +x crawl, cm); any other task's is
    :func:`episode_return`. Counts episodes and simulated seconds in ``episodes`` and
    ``sim_seconds``.

    Raises:
        InvalidDesignError: invalid design.
    """

    def __init__(self, design, cfg: GroundTruthConfig):
        from softcrawl.robot.assembly import build_robot
        from softcrawl.tasks import on_floor

        space = cfg.design_space()
        self.design, self.cfg, self.task = space.canonicalize(design), cfg, cfg.task_spec()
        self.robot = on_floor(build_robot(self.design, cfg.robot_config(), space=space), self.task.friction,
                              self.task.gravity())
        self._settled = None
        self.episodes, self.sim_seconds = 0, 0.0

    def __call__(self, gait, duration: float) -> tuple[float, bool]:
        from softcrawl.robot.episode import run_episode, settle

        if self._settled is None:
            self._settled = settle(self.robot)
        if self.task.name == DEFAULT_TASK:
            res = run_episode(self.robot, gait, duration, record_every=None, progress=False, settled=self._settled)
            reward, diverged = float(res.reward_cm), bool(res.diverged)
        else:
            reward, diverged = episode_return(self.task, self.robot, gait, duration, self.cfg.hold, self._settled)
        self.episodes += 1
        self.sim_seconds += duration
        return (reward if math.isfinite(reward) else DIVERGED_CM), diverged


def episode_return(task, robot, gait, duration: float, hold: float, settled=None) -> tuple[float, bool]:
    """``task``'s return of one open-loop episode of ``gait`` on ``robot``, in the task's unit,
    scored as the env scores an episode of actions of ``hold`` s (softcrawl.envs.crawler): the
    robot's state is sampled every ``hold`` s (rounded to whole steps of ``robot.config.dt``;
    fewer if needed so that the samples include the episode's last step, as
    :func:`softcrawl.tasks.baselines.turned_degrees`), and the return is
    :func:`softcrawl.tasks.base.replay_return` of the samples up to the first one where the
    task's goal is reached (:meth:`softcrawl.tasks.Task.reached`; the episode ends there). A
    task with :attr:`~softcrawl.tasks.Task.vent_seconds` is scored after venting that long, as
    the env scores it (:func:`softcrawl.tasks.base.scored_gait`).

    Args:
        task: a :class:`softcrawl.tasks.Task`. robot: a robot on the task's floor.
        gait: ``pressure_at(t) -> (R,)`` kPa. duration, hold: s.
        settled: the robot's cached :func:`softcrawl.robot.episode.settle` (None: settle now).

    Returns:
        ``(return, diverged)``; the return is NaN if settling diverged.
    """
    from softcrawl.robot.episode import run_episode
    from softcrawl.tasks.base import Snapshot, replay_return, scored_gait

    gait, duration = scored_gait(gait, duration, task.vent_seconds)
    dt = robot.config.dt
    n = int(round(duration / dt)) if math.isfinite(duration) else 0
    every = math.gcd(max(1, int(round(hold / dt))), max(n, 1))
    frames: list[np.ndarray] = []
    res = run_episode(robot, gait, duration, record_every=every, progress=False, settled=settled,
                      on_frame=lambda t, x: frames.append(np.array(x, dtype=float)))
    if not frames:
        return float("nan"), True
    start = np.asarray(robot.reward_position(frames[0]), dtype=float)
    origin = task.origin(Snapshot(robot, frames[0], start))
    end = next((k + 1 for k in range(1, len(frames)) if task.reached(Snapshot(robot, frames[k], start), origin)),
               len(frames))
    return replay_return(task, robot, np.stack(frames[:end])), bool(res.diverged)


def optimize_design(design, cfg: GroundTruthConfig, evaluator: Callable | None = None) -> DesignResult:
    """The best gait of ``design`` in the family: its :func:`design_rounds` driven by
    ``evaluator``, one episode after another (the order of
    :func:`~softcrawl.codesign.groundtruth.search.design_search`).

    Args:
        design: a design (canonicalised first).
        cfg: settings.
        evaluator: ``(gait, duration) -> (return, diverged)`` (default: a
            :class:`DesignEvaluator`, the reduced model and ``cfg``'s task).

    Returns:
        :class:`DesignResult` (``wall_seconds``: from the start of this call, robot build included).

    Raises:
        InvalidDesignError: invalid design. ValueError: invalid ``cfg``.
    """
    search = design_rounds(design, cfg, cfg.design_space())
    wall = time.perf_counter()
    ev = evaluator if evaluator is not None else DesignEvaluator(design, cfg)
    result = drive(search, lambda requests: [ev(*request) for request in requests])
    return dataclasses.replace(result, wall_seconds=time.perf_counter() - wall)


class SerialEvaluateMany:
    """An ``evaluate_many`` of :func:`~softcrawl.codesign.groundtruth.search.search_many` on the
    CPU: one evaluator per design (built at its first episode and kept), episodes one after
    another; the reference a batched engine must reproduce.

    Args:
        cfg: settings (the robots' model).
        make: ``design -> evaluator`` (default: :class:`DesignEvaluator` of ``cfg``).
    """

    def __init__(self, cfg: GroundTruthConfig, make: Callable | None = None):
        self.make = make if make is not None else (lambda d: DesignEvaluator(d, cfg))
        self.evaluators: dict = {}

    def __call__(self, requests) -> list[tuple[float, bool]]:
        out = []
        for design, gait, duration in requests:
            if design not in self.evaluators:
                self.evaluators[design] = self.make(design)
            out.append(self.evaluators[design](gait, duration))
        return out


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
    space = cfg.design_space()
    designs = [space.canonicalize(d) for d in designs]
    bar = tqdm(total=len(designs) * (gaits_per_design + 1), desc="screening", disable=not progress)
    for d in designs:
        ev = DesignEvaluator(d, cfg)
        m, n_reg = used_regulators(d, space), space.n_regulators
        gaits = [knots_to_gait(seed_knots(m, 3)[0].ravel(), m, 3, cfg.hold, n_regulators=n_reg)]
        for _ in range(gaits_per_design):
            L = int(rng.choice(cfg.cycles))
            gaits.append(knots_to_gait(rng.random(m * L), m, L, cfg.hold, n_regulators=n_reg))
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
