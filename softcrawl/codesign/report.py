"""Report of a co-design run (``softcrawl report RUN``; also written at the end of training).

Writes ``RUN/report/`` (built in ``RUN/.report.partial-*`` and swapped in when complete, so a
failed report leaves the previous one; a ``report`` that links out of the run is refused; the run
is read through :class:`softcrawl.codesign.run.Run`):

* ``summary.md``: run settings, the task (:mod:`softcrawl.tasks`: its name, settings, reward
  and unit, ``U``: cm or deg), steps, episodes, best return, the run's design, final
  entropy/beta, and the top-k table (design, latest return R (``U``; the score in the Gibbs
  weights), probability, episodes, mean and best return, picture); every return is in the
  task's unit and every column that holds one says it (``R (deg)``, ``latest_deg``);
* ``top-<i>.png``: pictures of the top-k designs in the run's design space (its slots and
  regulators; :func:`softcrawl.design.picture.plot_design`);
* "Shortlist" (:func:`shortlist_section`): the run's shortlist (:mod:`softcrawl.codesign.shortlist`;
  computed here and written to the run if it has none of its last checkpoint), each
  candidate's returns (deterministic, the samples' mean ± sd, the chosen gait) and which is the
  run's design; ``shortlist.png``, each candidate's picture and gait;
* "Training" (:mod:`softcrawl.codesign.report_training`): what the paper's reward-histogram
  figure shows: ``reward_histogram.png`` (the designs' latest returns weighted by the design
  distribution over training, the best so far, the mode switches), the same at points of
  training (``reward_histogram_points.png``, a table), the mode switches (a table,
  ``mode_switches.png``), ``returns.png``; and the paper's designs L1-L5 placed in the run (and
  in a ground truth, ``groundtruth``);
* ``top_designs.csv``: the top-k table;
* ``best_design/``: the run's design re-simulated with the trained policy (its gait,
  :mod:`softcrawl.codesign.evaluation`): the outputs of ``softcrawl simulate`` (``crawl.gif``
  shows it crawling, :mod:`softcrawl.robot.animation`; ``trajectory.png`` shows commanded vs
  applied pressures and x(t); ParaView frames; ``summary.json``), and what
  the gait does (:func:`gait_analysis`: its cycle, if any, and the +x distance of each quarter of
  the episode: a crawler moves in every quarter, a push does not); a warning when its robot did
  not come to rest before the episode (:func:`softcrawl.robot.episode.unsettled_warning`: on a
  floor tilted more than its friction holds it slides, and its return is that slide);
* ``summary.json``: the numbers of ``summary.md`` (steps, wall time, top designs, the best
  design's policy reward, actions and gait analysis, the baseline's best phase and reward);
* "Expert baseline", the task's (:attr:`softcrawl.tasks.Task.baseline`): for ``forward``, the
  sine gait on the space's :func:`softcrawl.design.baseline.sine_baseline_design` (the paper's
  ``1,0,0,2,2,0,0,1`` in its space) swept over ``baseline_phases`` with the
  run's robot settings and episode length (``baseline_sweep/``, a ``softcrawl sweep-phase``
  output), its best phase re-simulated into ``baseline_best/``; or, with ``baseline``, an existing
  sweep's best phase and reward (comparable only when its episode length and model match the
  run's; the section states both), its ``reward_vs_phase.png`` copied in; for ``turning``, the
  hand-made turning gait (:mod:`softcrawl.tasks.baselines`) swept over ``baseline_phases`` with
  the run's robot, floor and episode length (``baseline_turning.csv``) on the space's
  :func:`softcrawl.tasks.baselines.turning_baseline_design`, its best turn next to the best
  design's; other tasks, a ``forward`` run on a space of one regulator (:func:`no_sine_baseline`)
  and a space without a turning design have none (the section says why);
* with a ground truth (``softcrawl report RUN --groundtruth GT``): where the run's chosen design
  ranks in it, its regret in cm and its learned policy's reward next to the ground-truth gait's
  (:mod:`softcrawl.codesign.groundtruth_regret`; ``summary.json`` key ``regret``).

Top-k ranking: designs that were tried, by their latest return ``R`` (the quantity the
distribution concentrates on), ties broken by design order. The run's design is its
shortlist's choice, or without a shortlist the most probable design.
"""

from __future__ import annotations

import csv
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np

from softcrawl.codesign.config import TrainConfig
from softcrawl.codesign.evaluation import GAIT_SAMPLES, episode_seconds
from softcrawl.codesign.run import Run, note
from softcrawl.codesign.shortlist import by_latest, design_rows
from softcrawl.design.baseline import sine_baseline_design
from softcrawl.design.picture import plot_design, regulator_colour
from softcrawl.design.space import BASELINE_DESIGN, DEFAULT_SPACE
from softcrawl.tasks import Task, parse_task

BASELINE_PHASES: tuple[float, ...] = tuple(range(0, 360, 30))
"""Phase lags (degrees) of the report's own baseline sweep."""


def load_final_sampler_state(run: str | Path) -> dict | None:
    """The design-sampler state of the run's newest complete checkpoint, or None if it has none
    (ValueError if that checkpoint's ``state.json`` is malformed)."""
    r = Run(run)
    ck = r.latest_checkpoint()
    return None if ck is None else r.read_checkpoint_state(ck)["sampler"]


#: The keys of a :func:`top_designs` row.
TOP_KEYS = ("design", "latest_cm", "prob", "episodes", "mean_cm", "best_cm")


def top_designs(run: str | Path, k: int = 5) -> list[dict]:
    """Top-k tried designs of a run (see the module docstring) as dicts with keys
    :data:`TOP_KEYS` (:func:`softcrawl.codesign.shortlist.design_rows`)."""
    return _top(design_rows(run), k)


def _top(rows: list[dict], k: int) -> list[dict]:
    """The first ``k`` of :func:`~softcrawl.codesign.shortlist.design_rows`'s ``rows`` by latest
    return, with the keys :data:`TOP_KEYS`."""
    return [{key: row[key] for key in TOP_KEYS} for row in by_latest(rows)[:k]]


def _load_sweep(sweep: str | Path) -> tuple[Path, dict]:
    """``(sweep.json path, its content)`` of a ``softcrawl sweep-phase`` output (directory or file).

    Raises:
        ValueError: unreadable, or without ``settings`` and ``best``.
    """
    sweep = Path(sweep)
    path = sweep / "sweep.json" if sweep.is_dir() else sweep
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        for key in ("design", "duration_s", "config"):
            data["settings"][key]
        data["best"]
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{sweep} is not a softcrawl sweep-phase output (sweep.json): {exc!r}") from exc
    return path, data


def _baseline_section(path: Path, data: dict, out: Path, cfg: TrainConfig, best_cm: float | None) -> list[str]:
    """Markdown lines comparing the run (config ``cfg``) with the expert baseline's phase sweep
    (``path``: its ``sweep.json``, ``data``: its content)."""
    settings, best = data["settings"], data["best"]
    if (path.parent / "reward_vs_phase.png").exists():
        shutil.copyfile(path.parent / "reward_vs_phase.png", out / "reward_vs_phase.png")
    sweep_model = settings["config"].get("model", "full")
    lines = ["", "## Expert baseline", "",
             (f"Sine gait on `{','.join(map(str, settings['design']))}`, {settings['duration_s']:g} s episodes, "
              f"{sweep_model} model, {settings['config'].get('leg_mesh_size')} mm legs (this run: {episode_seconds(cfg):g} s "
              f"episodes, {cfg.env.robot.model} model, {cfg.env.robot.leg_mesh_size} mm legs)."), ""]
    if best is None:
        lines.append("Every phase of the sweep diverged.")
    else:
        paper = (f" (paper: {data.get('paper_best_phase_deg', 110)}°)"
                 if tuple(settings["design"]) == BASELINE_DESIGN else "")  # the paper swept its own design only
        lines.append(f"- best phase lag: {best['phase_deg']:g}°{paper}, {best['reward_cm']:+.3f} cm")
        if best_cm is not None:
            lines.append(f"- this run's best episode: {best_cm:+.3f} cm")
    if (out / "reward_vs_phase.png").exists():
        lines += ["", "![baseline reward vs phase](reward_vs_phase.png)"]
    return lines


#: Two actions are "the same" in :func:`gait_period` if no regulator differs by more (real kPa).
PERIOD_TOLERANCE_KPA = 3.0


def gait_period(actions_kpa: np.ndarray, tol_kpa: float = PERIOD_TOLERANCE_KPA) -> tuple[int, int] | None:
    """The gait's cycle: the smallest period ``P`` (actions) such that, from some action
    ``t0`` on, ``actions[t] == actions[t + P]`` (to ``tol_kpa`` on every regulator) for every
    later ``t``, over at least half of the episode and two whole cycles; ``(P, t0)`` with the
    earliest such ``t0``, or None. A constant command (``P = 1``) counts as a cycle of one
    action (it cannot crawl).

    Args:
        actions_kpa: ``(n, 3)`` commanded real kPa per action.
    """
    a = np.asarray(actions_kpa, dtype=float)
    n = len(a)
    for P in range(1, n // 2 + 1):
        same = np.all(np.abs(a[P:] - a[:-P]) <= tol_kpa, axis=1)  # same[t]: a[t] == a[t + P]
        bad = np.flatnonzero(~same)
        t0 = int(bad[-1]) + 1 if len(bad) else 0
        if n - t0 >= max(2 * P, n / 2):
            return P, t0
    return None


def _per_part(time_s: np.ndarray, cumulative: np.ndarray, parts: int) -> tuple[float, np.ndarray]:
    """Seconds per part and the change of ``cumulative`` (sampled at ``time_s``) over each of
    ``parts`` equal parts of the episode."""
    edges = np.linspace(time_s[0], time_s[-1], parts + 1)
    return float(edges[1] - edges[0]), np.diff(np.interp(edges, time_s, cumulative))


def _throughout(per_part: np.ndarray) -> bool:
    """Every part gains at least 10% of the mean part, and the mean is positive."""
    mean = float(per_part.mean())
    return bool(mean > 0 and np.all(per_part >= 0.1 * mean))


def gait_analysis(actions_kpa: np.ndarray, time_s: np.ndarray, x_mm: np.ndarray, parts: int = 4,
                  task_return: tuple[np.ndarray, np.ndarray, str] | None = None) -> dict:
    """How a gait moves the robot over an episode: its cycle (:func:`gait_period`) and the +x
    distance (cm) of each of ``parts`` equal parts of the episode; ``crawls_throughout`` when
    every part moves forward by at least 10% of the mean part (a crawler, not one push).

    Args:
        actions_kpa: ``(n, 3)`` commanded real kPa per action.
        time_s: ``(k,)`` times, s; x_mm: ``(k,)`` disk top-centre x, mm.
        task_return: for a task other than ``forward``, ``(times (j,) s, return so far (j,), unit)``
            (:func:`softcrawl.tasks.base.return_series`): adds ``return_per_part_<unit>`` and
            ``task_throughout`` (the same 10% rule on the task's return).
    """
    period = gait_period(actions_kpa)
    seconds, legs = _per_part(time_s, x_mm / 10.0, parts)
    out = {"period_actions": None if period is None else period[0],
           "periodic_from_action": None if period is None else period[1],
           "part_seconds": seconds, "distance_per_part_cm": [round(float(v), 4) for v in legs],
           "crawls_throughout": _throughout(legs)}
    if task_return is not None:
        t, series, unit = task_return
        per = _per_part(np.asarray(t, float), np.asarray(series, float), parts)[1]
        out.update({f"return_per_part_{unit}": [round(float(v), 4) for v in per], "task_throughout": _throughout(per)})
    return out


def _describe_gait(g: dict, task: Task | None = None) -> str:
    """One line on the gait (:func:`gait_analysis`): for ``forward`` (None) its +x distance per
    part and whether it crawls throughout; for another task its return per part (when
    analysed) and whether it gains throughout, then the +x distance."""
    P = g["period_actions"]
    cyc = ("no repeating cycle" if P is None else "a constant command (no cycle)" if P == 1 else
           f"a {P}-action cycle from action {g['periodic_from_action'] + 1} on")
    parts = " / ".join(f"{v:+.2f}" for v in g["distance_per_part_cm"])
    if task is not None and task.name != "forward":
        per = g.get(f"return_per_part_{task.unit}")
        gains = "" if per is None else (
            f"the `{task.name}` return per {g['part_seconds']:g}-s part: {' / '.join(f'{v:+.2f}' for v in per)} "
            f"{task.unit} ({'it gains' if g['task_throughout'] else 'it does NOT gain'} throughout: every part at "
            "least 10% of the mean); ")
        return f"Gait: {cyc}; {gains}+x per {g['part_seconds']:g}-s part: {parts} cm."
    verdict = "it crawls throughout" if g["crawls_throughout"] else "it does NOT crawl throughout"
    return (f"Gait: {cyc}; +x per {g['part_seconds']:g}-s part of the episode: {parts} cm ({verdict}: every "
            "part at least 10% of the mean).")


def _sampled_lines(ev, unit: str) -> list[str]:
    """The Markdown line on an evaluation's sampled episodes (none: no line)."""
    ret = np.asarray(ev.sampled_returns, float)
    ok = ret[~np.asarray(ev.sampled_diverged, bool)]
    if not len(ret):
        return []
    stats = (f"mean {ok.mean():+.3f} ± {ok.std():.3f} {unit} (min {ok.min():+.3f}, max {ok.max():+.3f})" if len(ok)
             else "every one diverged")
    return [f"Sampled from the stochastic policy, {len(ret)} episodes: {stats}"
            f"{f'; {len(ret) - len(ok)} diverged' if 0 < len(ok) < len(ret) else ''}. Each is an open-loop gait "
            "that replays to its return; the best of these and the deterministic one is the design's gait."]


def _best_design_section(run: Path, out: Path, design, checkpoint: Path,
                         task: Task | None = None, samples: int = 0, ev=None) -> tuple[list[str], dict]:
    """Re-simulate ``design``'s gait (the best of the run's deterministic policy and ``samples``
    episodes sampled from it, :func:`softcrawl.codesign.evaluation.evaluate_policy`; ``ev``: that
    evaluation if already made) into ``out/best_design``; Markdown lines and the numbers for
    ``summary.json`` (returns in the unit of ``task``, default ``forward``'s cm)."""
    from softcrawl.codesign.evaluation import evaluate_policy
    from softcrawl.robot.episode import unsettled_warning
    from softcrawl.robot.output import write_results
    from softcrawl.tasks.base import VENT_SECONDS, return_series, vented_return

    task = task if task is not None else parse_task("forward")
    ev = evaluate_policy(run, design, checkpoint=checkpoint, samples=samples) if ev is None else ev.with_env()
    result = ev.resimulate(record_every=10)
    robot = ev.env.episode.robot
    write_results(out / "best_design", robot, ev.gait(), result, ev.env.calibration, overwrite=True,
                  animation=True)
    name = ",".join(map(str, ev.design))
    unit = task.unit
    series = None if task.name == "forward" else return_series(task, robot, result.frames)
    seconds = episode_seconds(ev.config)
    steps, frames = result.time <= seconds + 1e-9, result.frame_times <= seconds + 1e-9  # the gait, not its venting
    g = gait_analysis(ev.gait_actions_kpa, result.time[steps], result.position[steps, 0],
                      task_return=None if series is None else (result.frame_times[frames], series[frames], unit))
    rerun = float(result.reward_cm) if series is None else (float(series[-1]) if len(series) else float("nan"))
    numbers = {"design": name, f"policy_{unit}": float(ev.returns_cm[0]), "resimulated_cm": float(result.reward_cm),
               "diverged": bool(result.diverged), "gait": g, "gait_source": ev.gait_source,
               f"gait_{unit}": ev.gait_return, f"sampled_{unit}": [float(v) for v in ev.sampled_returns],
               "actions_kpa": np.round(np.asarray(ev.gait_actions_kpa, float), 2).tolist(), "settled": result.settled}
    warning = unsettled_warning(result.settled)
    if warning:
        note(f"warning: the best design {name} {warning}")
    if task.name != "forward":
        numbers[f"resimulated_{unit}"] = rerun
    held, kept, _ = vented_return(task, robot, ev.gait(), seconds, ev.config.env.settling(), ev.env.calibration)
    numbers |= {f"held_at_end_{unit}": held, f"kept_after_venting_{unit}": kept}
    return ["", "## Best design's gait", "",
            *([f"**Warning**: `{name}` {warning}.", ""] if warning else []),
            f"`{name}` with the trained policy (deterministic): {ev.returns_cm[0]:+.3f} {unit} per episode.",
            *_sampled_lines(ev, unit), "",
            (f"The gait below ({ev.gait_source}): {ev.gait_return:+.3f} {unit} "
             f"(re-run {rerun:+.3f} {unit}{', DIVERGED' if result.diverged else ''}); commanded (dashed) "
             f"vs applied (solid) pressures and x(t); ParaView series in `best_design/crawl.pvd`."), "",
            _describe_gait(g, task), "",
            (f"At the gait's end (t = {seconds:g} s): {held:+.3f} {unit}; kept at rest after {VENT_SECONDS:g} s more "
             f"with every regulator vented: {kept:+.3f} {unit} (what the pressure only held, an elastic twist or "
             "stretch of the body, springs back)."), "",
            *(["![best design crawling](best_design/crawl.gif)", ""] if (out / "best_design" / "crawl.gif").exists()
              else []),
            "![best design's gait](best_design/trajectory.png)"], numbers


def _baseline_best(cfg: TrainConfig, out: Path, data: dict) -> list[str]:
    """Re-simulate the swept baseline at its best phase (robot settings of ``cfg``) into
    ``out/baseline_best``."""
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.robot.episode import run_episode
    from softcrawl.robot.output import write_results
    from softcrawl.robot.sweep import baseline_gait

    space = cfg.env.design_space()
    robot = robot_factory(cfg)(tuple(data["settings"]["design"]))
    gait = baseline_gait(data["best"]["phase_deg"], space.n_regulators)
    result = run_episode(robot, gait, data["settings"]["duration_s"], record_every=10, progress=False)
    write_results(out / "baseline_best", robot, gait, result, overwrite=True)
    return ["", "![baseline at its best phase](baseline_best/trajectory.png)"]


def shortlist_section(sl: dict | None, out: Path, space) -> list[str]:
    """The report's "Shortlist" section of a :func:`softcrawl.codesign.shortlist.read_shortlist`
    dict (None: a line saying the run's design is the most probable one), with
    ``shortlist.png`` (each candidate's picture and gait)."""
    lines = ["", "## Shortlist", ""]
    if sl is None:
        return lines + ["None: this run has no shortlist of its last checkpoint and the report did not simulate "
                        "(--no-simulate); the run's design is the most probable one."]
    u, cands = sl["unit"], sl["candidates"]
    per = sl["wall_seconds"] / len(cands)
    lines += [(f"The run's design is the best of its {len(cands)} most promising designs (taken in turn by final "
               "probability p, best episode return and mean of the last episodes: their ranks p / best / recent), "
               f"each tried with the trained policy's gaits: the deterministic episode and {sl['samples']} sampled "
               f"ones, the best of them its gait (checkpoint `{sl['checkpoint']}`; {sl['wall_seconds']:.0f} s, "
               f"{per:.0f} s per candidate)."), "",
              f"| # | design | ranks p / best / recent | p | R ({u}) | best ({u}) | deterministic ({u}) | "
              f"samples ({u}) | gait ({u}) | |", "|---|---|---|---|---|---|---|---|---|---|"]

    def num(v, fmt="+.3f"):
        return "-" if v is None else format(v, fmt)

    for i, c in enumerate(cands):
        ranks = " / ".join("-" if c.get(key) is None else str(c[key]) for key in
                           ("rank_probability", "rank_best", "rank_recent"))
        ok = [v for v, bad in zip(c.get(f"sampled_{u}", []), c.get("sampled_diverged", [])) if not bad and v is not None]
        samples = f"{np.mean(ok):+.3f} ± {np.std(ok):.3f} ({len(ok)})" if ok else "-"
        det = num(c.get(f"deterministic_{u}")) + (" diverged" if c.get("deterministic_diverged") else "")
        gait = f"{num(c[f'gait_{u}'])} ({c.get('gait_source', '?')}{', diverged' if c['gait_diverged'] else ''})"
        lines.append(f"| {i + 1} | `{','.join(map(str, c['design']))}` | {ranks} | {num(c.get('prob'), '.3g')} | "
                     f"{num(c.get(f'latest_{u}'))} | {num(c.get(f'best_{u}'))} | {det} | {samples} | {gait} | "
                     f"{'**chosen**' if i == sl['chosen'] else ''} |")
    if sl["all_diverged"]:
        lines += ["", "Every candidate's gait diverged: the run's design is the most probable one."]
    _shortlist_figure(sl, out / "shortlist.png", space)
    return lines + ["", "![the shortlist's designs and their gaits](shortlist.png)"]


def _shortlist_figure(sl: dict, path: Path, space) -> None:
    """One row per candidate: its picture, and its gait's commanded kPa per regulator over the
    episode's actions."""
    from matplotlib.figure import Figure

    cands, u = sl["candidates"], sl["unit"]
    fig = Figure(figsize=(8, 2.6 * len(cands)))
    axes = fig.subplots(len(cands), 2, squeeze=False, gridspec_kw={"width_ratios": [1, 2.2], "hspace": 0.45})
    for i, (c, (pic, gait)) in enumerate(zip(cands, axes)):
        plot_design(c["design"], ax=pic, space=space)
        if pic.get_legend() is not None:  # the gait's legend names the regulators, in the same colours
            pic.get_legend().remove()
        pic.set_title(f"#{i + 1} {','.join(map(str, c['design']))}{' (chosen)' if i == sl['chosen'] else ''}",
                      fontsize=9)
        a = np.asarray(c.get("actions_kpa") or np.zeros((0, 0)), float)
        for j in range(a.shape[1] if a.ndim == 2 else 0):
            gait.stairs(a[:, j], np.arange(len(a) + 1), color=regulator_colour(j + 1), label=f"regulator {j + 1}")
        ret = c[f"gait_{u}"]
        gait.set_title(f"gait ({c.get('gait_source', '?')}): {'-' if ret is None else format(ret, '+.3f')} {u}",
                       fontsize=9)
        gait.set_ylim(-5, 95)
        gait.set_ylabel("commanded kPa")
        gait.legend(fontsize=7, loc="upper right")
    axes[-1][1].set_xlabel("action (each held for the run's hold time)")
    fig.savefig(path, dpi=90, bbox_inches="tight")


def write_report(run: str | Path, k: int = 5, baseline: str | Path | None = None,
                 baseline_phases=BASELINE_PHASES, simulate: bool = True, workers: int | None = None,
                 extra: dict[str, Callable[[], tuple[list[str], dict]]] | None = None,
                 samples: int = GAIT_SAMPLES, shortlist: int | None = None,
                 groundtruth: str | Path | None = None) -> Path:
    """Write ``run/report/`` (module docstring) and return its path.

    Args:
        run: the training run directory.
        k: number of top designs.
        baseline: a ``softcrawl sweep-phase`` output directory or its ``sweep.json``; None
            sweeps the baseline over ``baseline_phases`` with the run's settings (if ``simulate``).
        baseline_phases: degrees; empty: no baseline section unless ``baseline`` is given.
        simulate: re-simulate the run's design (and run the baseline sweep, and a missing
            shortlist); False writes only what the run's files hold.
        workers: processes of the baseline sweep (None: the CPU count) and of a shortlist
            computed here (None: the run's ``n_workers``).
        extra: more sections, ``summary.json`` key -> a callable giving ``(Markdown lines,
            numbers)``, appended in order (``softcrawl report --groundtruth``: the regret against
            a ground truth, :func:`softcrawl.codesign.groundtruth_regret.regret_section`, which
            reads the run itself and so is passed in rather than imported here).
        samples: episodes sampled from the stochastic policy on the run's design (and on each
            candidate of a shortlist computed here); its gait is the best of them and the
            deterministic one (0: the deterministic one).
        shortlist: compute the run's shortlist anew with this many candidates (and write it,
            :mod:`softcrawl.codesign.shortlist`); None: the run's own, computed with its
            ``shortlist`` setting if it has none of its last checkpoint (and ``simulate``).
        groundtruth: a ``softcrawl groundtruth`` folder to place the paper's designs in
            (:func:`~softcrawl.codesign.report_training.paper_designs_section`).

    The run is locked while the report is written (:meth:`Run.lock`): not while it trains.

    Raises:
        ValueError: ``run`` is not a training run with at least one complete checkpoint, a
            run file is malformed, ``report`` is a link, ``baseline`` is not a sweep output,
            ``shortlist`` without ``simulate`` or out of range, ``groundtruth`` is not a ground
            truth; and what an ``extra`` section raises.
        FolderLockedError: another command is writing the run (a training, another report).
    """
    from softcrawl.codesign.shortlist import MAX_SHORTLIST

    if shortlist is not None and not 1 <= shortlist <= MAX_SHORTLIST:
        raise ValueError(f"a shortlist has 1 to {MAX_SHORTLIST} designs, got {shortlist}")
    if shortlist is not None and not simulate:
        raise ValueError("a shortlist's designs are evaluated by simulation: --shortlist goes without --no-simulate")
    r = Run(run)
    r.read_meta()  # a training run, before its lock is taken
    with r.lock():
        meta = r.read_meta()
        sweep = _load_sweep(baseline) if baseline is not None else None
        ckpt = r.require_checkpoint()
        rows = design_rows(r.path, ckpt)
        state = r.read_checkpoint_state(ckpt)["sampler"]
        sl, evs = _report_shortlist(r, simulate, shortlist, samples, workers)
        staged = r.report_staging()
        try:
            _write_report(r, staged, meta, rows, _top(rows, k), state, ckpt, sweep, baseline_phases, simulate,
                          workers, extra or {}, samples, sl, evs, groundtruth)
            return r.install_report(staged)
        except BaseException:
            shutil.rmtree(staged, ignore_errors=True)
            raise


def _report_shortlist(r: Run, simulate: bool, k: int | None, samples: int,
                      workers: int | None) -> tuple[dict | None, list | None]:
    """The shortlist the report shows: the run's (``k`` None or its size), else one computed
    now on ``workers`` processes and written (``simulate`` only), with its evaluations;
    ``(None, None)`` without one."""
    from softcrawl.codesign.shortlist import compute_shortlist, read_shortlist, write_shortlist

    have = read_shortlist(r.path)
    if have is not None and k in (None, have["k"]):
        return have, None
    if not simulate:
        return None, None
    data, evs = compute_shortlist(r.path, r.read_config().shortlist if k is None else k, samples, progress=True,
                                  workers=workers)
    write_shortlist(r.path, data)
    return data, evs


def _write_report(r: Run, out: Path, meta: dict, rows: list, top: list, state: dict, ckpt: Path, sweep,
                  baseline_phases, simulate: bool, workers: int | None, extra: dict, samples: int, sl: dict | None,
                  evs: list | None, groundtruth) -> None:
    """Everything of :func:`write_report` into ``out`` (the staging folder); ``rows``: the tried
    designs (:func:`~softcrawl.codesign.shortlist.design_rows`), ``top`` the first of them,
    ``sl`` and ``evs`` the shortlist and its evaluations if made here (:func:`_report_shortlist`)."""
    from softcrawl.codesign.report_training import paper_designs_section, training_section
    from softcrawl.codesign.shortlist import most_probable

    run = r.path
    ep = r.read_episodes()
    run_cfg = r.read_config()
    space = run_cfg.env.design_space()
    for i, row in enumerate(top, 1):
        plot_design(row["design"], path=out / f"top-{i}.png", space=space)
    task = parse_task(run_cfg.env.task)
    u = task.unit
    with open(out / "top_designs.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["rank", "design", f"latest_{u}", "prob", "episodes", f"mean_{u}", f"best_{u}"])
        for i, row in enumerate(top, 1):
            w.writerow([i, ",".join(map(str, row["design"])), f"{row['latest_cm']:.4f}", f"{row['prob']:.4g}",
                        row["episodes"], f"{row['mean_cm']:.4f}", f"{row['best_cm']:.4f}"])
    last = state["distribution"]["last"]
    cfg = meta["config"]
    if sl is not None:
        chosen, source = tuple(sl["candidates"][sl["chosen"]]["design"]), "shortlist"
    else:
        chosen, source = (tuple(most_probable(rows)["design"]) if rows else None), "most probable"
    lines = [
        f"# Co-design run `{run.name}`", "",
        (f"softcrawl {meta['version']}, preset `{cfg['preset']}`: {cfg['n_envs']} envs, "
         f"{cfg['total_steps']} steps planned; {len(ep['r'])} episodes logged, "
         f"{int(ep['diverged'].sum())} diverged."), "",
        (f"- steps done (last checkpoint): {r.checkpoint_steps(ckpt)}; "
         f"training wall time {r.wall_seconds() / 60:.1f} min"),
        f"- design distribution last updated at step {state['timestep']} (the last episode end)",
        f"- task: `{task.label()}`: {task.describe} (returns in {u})",
        f"- best episode return: {ep['r'].max():+.3f} {u}" if len(ep["r"]) else "- no episode finished",
        *([] if chosen is None else [f"- the run's design: `{','.join(map(str, chosen))}` ("
                                     f"{'the best gait of its shortlist' if sl else 'the most probable'})"]),
        *([] if space == DEFAULT_SPACE else [
            f"- design space `{space.name}` (the run's `space.toml`): {space.n_slots} slots, "
            f"{space.n_regulators} regulators, legs {', '.join(map(str, run_cfg.env.legs))} "
            f"({len(run_cfg.env.designs())} canonical designs in play)"]),
        f"- design distribution: beta = {last.beta:.4g} /{u}, entropy {last.entropy:.3f} nats "
        f"(target {last.target:.3f}{', clamped to the tie floor' if last.clamped else ''})" if last else "",
        "", f"## Top {len(top)} designs (by latest return R)", "",
        f"| rank | design | R ({u}) | p | episodes | mean ({u}) | best ({u}) | picture |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for i, row in enumerate(top, 1):
        lines.append(f"| {i} | `{','.join(map(str, row['design']))}` | {row['latest_cm']:+.3f} | {row['prob']:.3g} | "
                     f"{row['episodes']} | {row['mean_cm']:+.3f} | {row['best_cm']:+.3f} | ![](top-{i}.png) |")
    lines += shortlist_section(sl, out, space)
    more, training = training_section(r, ep, out, u, space, run_cfg.env.designs())
    lines += more
    more, paper = paper_designs_section(rows, run_cfg, groundtruth, u)
    lines += more
    best_cm = float(ep["r"].max()) if len(ep["r"]) else None
    numbers = {"run": run.name, "preset": cfg["preset"], "task": task.settings(), "unit": u,
               "steps": r.checkpoint_steps(ckpt),
               "training_wall_seconds": r.wall_seconds(), "episodes": int(len(ep["r"])),
               f"best_episode_{u}": best_cm, "top_designs": [
                   {**row, "design": ",".join(map(str, row["design"]))} for row in top],
               "design": None if chosen is None else {"design": ",".join(map(str, chosen)), "source": source},
               "shortlist": sl, "training": training, "paper_designs": paper}
    if space != DEFAULT_SPACE:
        numbers["space"] = {"name": space.name, "slots": space.n_slots, "regulators": space.n_regulators,
                            "slot_angles_deg": list(space.slot_angles_deg), "legs": list(run_cfg.env.legs)}
    if simulate and chosen is not None:
        ev = None if evs is None else evs[sl["chosen"]]  # the shortlist's evaluation, made with these samples
        more, numbers["best_design"] = _best_design_section(run, out, chosen, ckpt, task, samples, ev)
        lines += more
    if task.baseline != "sine":  # another task's baseline, or none
        if sweep is not None:
            note(f"the baseline sweep {sweep[0]} is the forward task's; this run's task is {task.name!r}: left out")
        more, base = _task_baseline_section(run_cfg, task, out, numbers.get("best_design"), baseline_phases,
                                            simulate, workers)
        lines += more
        if base:
            numbers["baseline"] = base
        sweep = None
    own_sweep = sweep is None and simulate and len(baseline_phases) > 0 and task.baseline == "sine" \
        and sine_baseline_design(space) is not None
    if own_sweep:
        from softcrawl.codesign.evaluation import baseline_sweep

        baseline_sweep(run, out / "baseline_sweep", baseline_phases, workers=workers)
        sweep = _load_sweep(out / "baseline_sweep")
    if sweep is None and task.baseline == "sine" and sine_baseline_design(space) is None:
        lines += ["", "## Expert baseline", "", no_sine_baseline(space)]
    if sweep is not None:
        lines += _baseline_section(*sweep, out, run_cfg, best_cm)
        if own_sweep and sweep[1]["best"] is not None:
            lines += _baseline_best(run_cfg, out, sweep[1])
    if sweep is not None and sweep[1]["best"] is not None:
        numbers["baseline"] = {"best_phase_deg": sweep[1]["best"]["phase_deg"],
                               "best_cm": sweep[1]["best"]["reward_cm"]}
    lines.append("")
    for key, section in extra.items():
        more, numbers[key] = section()
        lines += more
    (out / "summary.md").write_text("\n".join(lines), encoding="utf-8")
    (out / "summary.json").write_text(json.dumps(numbers, indent=1, default=float) + "\n", encoding="utf-8")


def no_sine_baseline(space) -> str:
    """Why a run on ``space`` has no forward expert baseline: one Markdown line."""
    return (f"None: the expert sine gait lags regulator 2 behind regulator 1, and this run's design space "
            f"`{space.name}` has {space.n_regulators} regulator; give a `softcrawl sweep-phase --space` output "
            "with --baseline to compare with one of its designs.")


def _task_baseline_section(cfg: TrainConfig, task: Task, out: Path, best: dict | None, phases, simulate: bool,
                           workers: int | None) -> tuple[list[str], dict]:
    """The expert-baseline section of a task other than ``forward``: the turning gait of
    :mod:`softcrawl.tasks.baselines` swept over ``phases`` (degrees) on the run's robot, floor,
    settling and episode length, written to ``out/baseline_turning.csv``, its best turn next to
    the best design's (``best``: :func:`_best_design_section`'s numbers); or a line saying the
    task has none. Returns the Markdown lines and the numbers (empty: none)."""
    lines = ["", "## Expert baseline", ""]
    if task.baseline != "turning":
        return lines + [f"The task `{task.name}` has no expert baseline."], {}
    if not (simulate and len(phases)):
        return lines + ["Not simulated (no phases, or --no-simulate)."], {}
    from softcrawl.codesign.factory import robot_factory
    from softcrawl.tasks.base import vented_return
    from softcrawl.tasks.baselines import best_turn, sweep_turning, turning_baseline_design, turning_gait

    space = cfg.env.design_space()
    turner = turning_baseline_design(space)
    if turner is None:
        return lines + [f"None: the design space `{space.name}` has no half-turn-symmetric design of two leg pairs "
                        "on regulators 1 and 2 (opposite slots 180° apart, 4 legs) to run the hand-made turning gait "
                        "on."], {}
    seconds = episode_seconds(cfg)
    results = sweep_turning(task.robots(robot_factory(cfg)), phases, seconds, cfg.env.settling(), workers=workers,
                            space=space, vent_seconds=task.vent_seconds)
    with open(out / "baseline_turning.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["phase_deg", "turned_deg", "diverged", "wall_seconds"])
        w.writerows([r.phase_deg, f"{r.turned_deg:.4f}", r.diverged, f"{r.wall_seconds:.2f}"] for r in results)
    design = ",".join(map(str, turner))
    lines += [(f"Hand-made turning gait on the symmetric `{design}` (two diagonally opposite leg pairs on regulators "
               f"1 and 2, raised-cosine waves 0-90 kPa, period 4 s, pair 2 lagging by the phase), {seconds:g} s "
               f"episodes, this run's robot ({cfg.env.robot.model} model) and floor; degrees turned counter-clockwise "
               "per phase lag:"), "", "| phase lag (deg) | turned (deg) |", "|---|---|"]
    lines += [f"| {r.phase_deg:g} | {'diverged' if r.diverged else f'{r.turned_deg:+.2f}'} |" for r in results]
    top = best_turn(results)
    numbers = {"kind": "turning", "design": design, "duration_s": seconds,
               "phases": [{"phase_deg": r.phase_deg, "turned_deg": r.turned_deg, "diverged": r.diverged}
                          for r in results]}
    if top is None:
        return lines + ["", "Every phase diverged."], numbers
    held, kept, _ = vented_return(task, task.robots(robot_factory(cfg))(turner),
                                  turning_gait(top.phase_deg, space.n_regulators), seconds, cfg.env.settling())
    numbers |= {"best_phase_deg": top.phase_deg, "best_deg": top.turned_deg, "held_at_end_deg": held,
                "kept_after_venting_deg": kept}
    lines += ["", f"- best phase lag: {top.phase_deg:g}°, {top.turned_deg:+.2f}° (the task's return; at the gait's "
                  f"end, t = {seconds:g} s: {held:+.2f}°, kept at rest after venting: {kept:+.2f}°)"]
    if best is not None and best.get("gait_deg") is not None:
        def times(deg: float) -> str:
            return f"{abs(deg) / abs(top.turned_deg):.2f}x the baseline's turn" if top.turned_deg else "the baseline did not turn"

        numbers["ratio"] = abs(best["gait_deg"]) / abs(top.turned_deg) if top.turned_deg else None
        lines.append(f"- best design `{best['design']}`, its gait ({best['gait_source']}): {best['gait_deg']:+.2f}°, "
                     f"{times(best['gait_deg'])}; the deterministic policy: {best['policy_deg']:+.2f}°, "
                     f"{times(best['policy_deg'])}")
        mine = best.get("kept_after_venting_deg")
        if mine is not None and kept and not task.vent_seconds:  # else the return is already kept at rest
            numbers["ratio_kept"] = abs(mine) / abs(kept)
            lines.append(f"- kept at rest after venting: the best design's gait {mine:+.2f}°, the baseline's "
                         f"{kept:+.2f}°: {numbers['ratio_kept']:.2f}x")
        sampled = np.asarray(best.get("sampled_deg") or [], float)
        sampled = sampled[np.isfinite(sampled)]
        if len(sampled):
            numbers["ratio_sampled_mean"] = abs(sampled.mean()) / abs(top.turned_deg) if top.turned_deg else None
            lines.append(f"- its {len(sampled)} sampled gaits, no choice made: mean {sampled.mean():+.2f}°, "
                         f"{times(sampled.mean())}")
    return lines, numbers
