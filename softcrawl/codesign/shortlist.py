"""The run's design: a final shortlist of its most promising designs, each tried with the trained
policy's gaits (``RUN/shortlist.json``; docs/codesign.md, "The run's design").

When training ends (:func:`softcrawl.cli.train.train_and_report`), the k most promising tried
designs (k: :attr:`softcrawl.codesign.config.TrainConfig.shortlist`) are each evaluated with the
trained policy's gait candidates (:func:`softcrawl.codesign.evaluation.evaluate_policy`: the
deterministic episode and ``samples`` sampled ones, the best of them the design's gait), and
the run's design is the candidate whose gait returned most. Ties go to the earlier candidate; a
candidate whose gait diverged is never chosen; if every one diverged, the run's design is the
most probable one and ``all_diverged`` says so.

The candidates come from three rankings of the tried designs (:func:`design_rows`), each with
ties broken by probability and then by the order of the distribution's design list:

* probability: the final design distribution's p (ties: the higher latest return R, as the
  run's design was chosen before the shortlist existed);
* best: the design's best episode return in ``episodes.csv`` (diverged episodes left out);
* recent: the mean of its last :data:`RECENT_EPISODES` episode returns (diverged ones left out).

They are taken from the three in turn (the most probable, the best, the most recent, then the
second of each, ...), a design already taken skipped, up to k (:func:`rank_candidates`). So
k = 1 is the most probable design, the choice of a run trained before the shortlist existed
(a run config of format < 7 reads as k = 1, :mod:`softcrawl.codesign.migrate`).

``shortlist.json`` (:data:`SHORTLIST_FORMAT`; returns in the unit ``unit`` of the run's task,
cm or deg, in keys that name it)::

    {"format": 1, "checkpoint": "step-XXXXXXXXXX", "steps": transitions, "k": k, "samples": K,
     "unit": "cm", "chosen": index of the run's design in candidates, "all_diverged": false,
     "wall_seconds": s,
     "candidates": [{"design": [...], "rank_probability": 1, "rank_best": 2, "rank_recent": null,
                     "prob": p, "latest_cm": R, "best_cm": , "recent_cm": , "episodes": n,
                     "deterministic_cm": , "deterministic_diverged": false,
                     "sampled_cm": [K returns], "sampled_diverged": [K bools],
                     "gait_source": "deterministic" or "sample k", "gait_cm": , "gait_diverged": false,
                     "actions_kpa": [[R regulators] x n_actions], "wall_seconds": s}, ...]}

(a number that is not finite is null). It belongs to the checkpoint it was computed from: one of
another checkpoint (a run resumed and trained on) is stale and read as none
(:func:`read_shortlist`). Readers: the report (its "Shortlist" section), ``regret``,
``evaluate`` and ``deploy --run`` without a design (:func:`run_design`).
"""

from __future__ import annotations

import json
import math
import os
import time
from collections.abc import Callable
from functools import partial
from pathlib import Path

import numpy as np

from softcrawl.codesign.config import TRAIN_BOUNDS
from softcrawl.codesign.run import Run, note
from softcrawl.parallel import pool_size, run_pool

#: Format of ``shortlist.json``.
SHORTLIST_FORMAT = 1
#: Episodes of a design whose mean is its "recent" return (the last ones it had, diverged left out).
RECENT_EPISODES = 3
#: Most candidates of a shortlist (``TrainConfig.shortlist``, ``softcrawl report --shortlist``):
#: each costs a dozen episodes of simulation.
MAX_SHORTLIST = int(TRAIN_BOUNDS["shortlist"][1])
#: The three rankings, in the order candidates are taken from them (key of their rank).
RANKINGS = (("probability", "rank_probability"), ("best", "rank_best"), ("recent", "rank_recent"))


def final_distribution(run: Run, checkpoint: Path | None = None):
    """The design distribution of checkpoint ``checkpoint`` (default the newest complete one),
    a :class:`~softcrawl.codesign.distribution.GibbsDesignDistribution` over the run's space.

    Raises:
        ValueError: no complete checkpoint, or a malformed ``state.json``.
    """
    from softcrawl.codesign.distribution import GibbsDesignDistribution

    ck = run.require_checkpoint() if checkpoint is None else checkpoint
    state = run.read_checkpoint_state(ck)["sampler"]["distribution"]
    dist = GibbsDesignDistribution(state["designs"], space=run.design_space())
    dist.load_state_dict(state)
    return dist


def design_rows(run: str | Path, checkpoint: Path | None = None) -> list[dict]:
    """Every design tried in the run, in the order of its distribution's design list, as dicts:
    ``design`` (tuple), ``index`` (in that list), ``latest_cm`` (its latest return R, the score
    of the Gibbs weights; every return in the run's task's unit), ``prob`` (final p),
    ``episodes``, ``mean_cm`` and ``best_cm`` (over all its episodes in ``episodes.csv``),
    ``best_ok_cm`` and ``recent_cm`` (best, and mean of the last :data:`RECENT_EPISODES`, of its
    episodes that did not diverge; NaN if none).

    Raises:
        ValueError: as :func:`final_distribution`, or a malformed ``episodes.csv``.
    """
    r = Run(run)
    dist = final_distribution(r, checkpoint)
    p = dist.probs()
    ep = r.read_episodes()
    mine: dict[tuple, list[tuple[float, bool]]] = {}
    for d, ret, bad in zip(ep["design"], ep["r"], ep["diverged"]):
        mine.setdefault(d, []).append((float(ret), bool(bad)))
    rows = []
    for i in np.flatnonzero(dist.tried):
        d = dist.designs[i]
        all_r = np.array([v for v, _ in mine.get(d, [])])
        ok = np.array([v for v, bad in mine.get(d, []) if not bad])
        rows.append({"design": d, "index": int(i), "latest_cm": float(dist.returns[i]), "prob": float(p[i]),
                     "episodes": len(all_r), "mean_cm": float(all_r.mean()) if len(all_r) else math.nan,
                     "best_cm": float(all_r.max()) if len(all_r) else math.nan,
                     "best_ok_cm": float(ok.max()) if len(ok) else math.nan,
                     "recent_cm": float(ok[-RECENT_EPISODES:].mean()) if len(ok) else math.nan})
    return rows


def by_latest(rows: list[dict]) -> list[dict]:
    """``rows`` (:func:`design_rows`) as the report's top table ranks them: by latest return R,
    ties to the earlier design."""
    return sorted(rows, key=lambda r: (-r["latest_cm"], r["index"]))


def _by_probability(row: dict) -> tuple:
    """Sort key of a :func:`design_rows` row: the more probable first, ties to the higher latest
    return, then to the earlier design."""
    return -row["prob"], -row["latest_cm"], row["index"]


def most_probable(rows: list[dict]) -> dict | None:
    """The most probable row of :func:`design_rows` (:func:`_by_probability`); None for no rows."""
    return min(rows, key=_by_probability, default=None)


def rank_candidates(rows: list[dict], k: int) -> list[dict]:
    """The shortlist's k candidates among ``rows`` (:func:`design_rows`; module docstring):
    copies of their rows with ``rank_probability``, ``rank_best`` and ``rank_recent`` (1-based;
    None where the design has no such return), in the order they were taken.

    Raises:
        ValueError: ``k`` outside 1..:data:`MAX_SHORTLIST`.
    """
    if isinstance(k, bool) or not isinstance(k, int) or not 1 <= k <= MAX_SHORTLIST:
        raise ValueError(f"the shortlist must have 1 to {MAX_SHORTLIST} candidates, got {k!r}")

    def by(key: str) -> list[dict]:  # the rows with a finite ``key``, highest first; ties: the more probable
        return sorted((r for r in rows if math.isfinite(r[key])), key=lambda r: (-r[key], -r["prob"], r["index"]))

    orders = {"probability": sorted(rows, key=_by_probability), "best": by("best_ok_cm"), "recent": by("recent_cm")}
    ranks = {name: {r["design"]: i for i, r in enumerate(order, 1)} for name, order in orders.items()}
    taken: list[tuple] = []
    for i in range(len(rows)):
        for name, _ in RANKINGS:
            order = orders[name]
            if i < len(order) and order[i]["design"] not in taken and len(taken) < k:
                taken.append(order[i]["design"])
    by_design = {r["design"]: r for r in rows}
    return [{**by_design[d], **{key: ranks[name].get(d) for name, key in RANKINGS}} for d in taken]


def gait_numbers(ev, unit: str) -> dict:
    """What ``shortlist.json`` keeps of a candidate's
    :class:`~softcrawl.codesign.evaluation.PolicyEvaluation` (returns in ``unit``)."""
    chosen = ev.chosen
    return {f"deterministic_{unit}": float(ev.returns_cm[0]), "deterministic_diverged": bool(ev.diverged[0]),
            f"sampled_{unit}": [float(v) for v in ev.sampled_returns],
            "sampled_diverged": [bool(v) for v in ev.sampled_diverged], "gait_source": ev.gait_source,
            f"gait_{unit}": float(ev.gait_return),
            "gait_diverged": bool(ev.diverged[0] if chosen is None else ev.sampled_diverged[chosen]),
            "actions_kpa": np.round(np.asarray(ev.gait_actions_kpa, float), 2).tolist()}


def choose(candidates: list[dict], unit: str) -> int | None:
    """Index of the candidate whose gait returned most (``gait_<unit>``; ties: the earlier one;
    a diverged or non-finite gait never), or None if there is none."""
    best, pick = -math.inf, None
    for i, c in enumerate(candidates):
        ret = c.get(f"gait_{unit}")
        if not c.get("gait_diverged") and ret is not None and math.isfinite(ret) and ret > best:
            best, pick = ret, i
    return pick


def compute_shortlist(run: str | Path, k: int, samples: int, evaluate: Callable | None = None,
                      progress: bool = False, workers: int | None = None) -> tuple[dict, list]:
    """The shortlist of ``run``'s newest complete checkpoint (module docstring), not written.

    Args:
        k: candidates (1..:data:`MAX_SHORTLIST`).
        samples: episodes sampled from the stochastic policy per candidate
            (:func:`~softcrawl.codesign.evaluation.evaluate_policy`'s ``samples``).
        evaluate: ``(run, design, checkpoint=, samples=) -> PolicyEvaluation`` (default
            :func:`~softcrawl.codesign.evaluation.evaluate_policy`), run in this process.
        progress: a line on stderr per candidate evaluated, as each finishes.
        workers: processes evaluating the candidates (1: this process; None: the run's
            ``n_workers``, whose 0 is the CPU count; never more than the candidates). Each candidate's
            evaluation is a fresh policy and env seeded alike wherever it runs, so the shortlist
            is the same to the bit for any ``workers`` on one machine; the evaluations of other
            processes come back without their env (:meth:`PolicyEvaluation.with_env
            <softcrawl.codesign.evaluation.PolicyEvaluation.with_env>` rebuilds it). A given
            ``evaluate`` always runs here.

    Returns:
        ``(the shortlist.json dict, the candidates' PolicyEvaluations)``.

    Raises:
        ValueError: ``k`` out of range, no checkpoint, no design tried, a malformed run file,
            and what ``evaluate`` raises.
    """
    from softcrawl.codesign.evaluation import evaluate_policy
    from softcrawl.robot.output import jsonable
    from softcrawl.tasks import parse_task

    r = Run(run)
    ck = r.require_checkpoint()
    rows = design_rows(r.path, ck)
    if not rows:
        raise ValueError(f"{r.path}: no design has been tried yet; nothing to shortlist")
    cands = rank_candidates(rows, k)
    cfg = r.read_config()
    unit = parse_task(cfg.env.task).unit
    evs, walls, start = [None] * len(cands), [0.0] * len(cands), time.perf_counter()

    def finished(result: tuple) -> None:
        i, ev, wall = result
        evs[i], walls[i] = ev, wall
        if progress:
            done = sum(e is not None for e in evs)
            note(f"shortlist {done}/{len(cands)}: {','.join(map(str, cands[i]['design']))}: gait "
                 f"({ev.gait_source}) {ev.gait_return:+.3f} {unit} ({wall:.0f} s)")

    tasks = [(i, r.path, c["design"], ck, samples) for i, c in enumerate(cands)]
    workers = 1 if evaluate is not None else pool_size(cfg.n_workers if workers is None else workers, len(tasks))
    run_pool(partial(_evaluate, evaluate or evaluate_policy, workers > 1), workers, tasks, finished)
    out = [{"design": list(c["design"]), **{key: c[key] for _, key in RANKINGS}, "prob": c["prob"],
            f"latest_{unit}": c["latest_cm"], f"best_{unit}": c["best_ok_cm"], f"recent_{unit}": c["recent_cm"],
            "episodes": c["episodes"], **gait_numbers(ev, unit), "wall_seconds": round(wall, 2)}
           for c, ev, wall in zip(cands, evs, walls)]
    pick = choose(out, unit)
    data = {"format": SHORTLIST_FORMAT, "checkpoint": ck.name, "steps": r.checkpoint_steps(ck), "k": k,
            "samples": samples, "unit": unit, "chosen": 0 if pick is None else pick, "all_diverged": pick is None,
            "wall_seconds": round(time.perf_counter() - start, 2), "candidates": out}
    return jsonable(data), evs


def _evaluate(evaluate: Callable, detach: bool, i: int, run: Path, design, checkpoint: Path, samples: int) -> tuple:
    """Task of :func:`compute_shortlist`: ``(i, candidate i's PolicyEvaluation, wall s)``, without
    its env if ``detach`` (in a worker process, to come back from it: there JAX is kept to the
    CPU, ``JAX_PLATFORMS=cpu`` unless set, where the evaluation computes anyway, so that no worker
    opens a GPU)."""
    if detach:
        os.environ.setdefault("JAX_PLATFORMS", "cpu")
    t0 = time.perf_counter()
    ev = evaluate(run, design, checkpoint=checkpoint, samples=samples)
    return i, (ev.detached() if detach else ev), time.perf_counter() - t0


def write_shortlist(run: str | Path, data: dict) -> None:
    """Write ``data`` (:func:`compute_shortlist`) as the run's ``shortlist.json``, atomically."""
    from softcrawl.safeio import atomic_write_text

    atomic_write_text(Run(run).shortlist_json, json.dumps(data, indent=1, allow_nan=False) + "\n")


def make_shortlist(run: str | Path, k: int | None = None, samples: int | None = None, force: bool = False,
                   progress: bool = True, workers: int | None = None) -> dict:
    """The run's shortlist, computed and written (the run locked, :meth:`Run.lock`) unless a
    fresh one with ``k`` candidates is there already (``force``: always). What
    ``softcrawl train`` does when training ends.

    Args:
        k: candidates (default: the run's ``shortlist`` setting).
        samples: sampled episodes per candidate (default
            :data:`~softcrawl.codesign.evaluation.GAIT_SAMPLES`).
        workers: processes evaluating the candidates (:func:`compute_shortlist`; None: the run's
            ``n_workers``).

    Raises:
        ValueError: as :func:`compute_shortlist` and :func:`read_shortlist`.
        FolderLockedError: another command is writing the run.
    """
    from softcrawl.codesign.evaluation import GAIT_SAMPLES

    r = Run(run)
    r.read_meta()  # a training run, before its lock is taken
    with r.lock():
        k = r.read_config().shortlist if k is None else k
        samples = GAIT_SAMPLES if samples is None else samples
        have = read_shortlist(r.path)
        if have is not None and not force and have["k"] == k and have["samples"] == samples:
            return have
        data, _ = compute_shortlist(r.path, k, samples, progress=progress, workers=workers)
        write_shortlist(r.path, data)
        return data


def read_shortlist(run: str | Path) -> dict | None:
    """The run's ``shortlist.json`` if it is of its newest complete checkpoint; None if there
    is none (a run trained before the shortlist existed) or it is stale (module docstring).

    Raises:
        ValueError: a malformed file (named), or as :meth:`Run.require_checkpoint`.
    """
    from softcrawl.safeio import load_json

    r = Run(run)
    path = r.shortlist_json
    if not path.exists() and not path.is_symlink():
        return None
    try:
        data = load_json(path)
        if data.get("format") != SHORTLIST_FORMAT:
            raise ValueError(f"format {data.get('format')!r}, this softcrawl reads {SHORTLIST_FORMAT}")
        _require(data, ("checkpoint", "k", "samples", "unit", "chosen", "all_diverged", "candidates"))
        cands, space = data["candidates"], r.design_space()
        if not isinstance(cands, list) or not cands or not 0 <= data["chosen"] < len(cands):
            raise ValueError("no candidates, or 'chosen' is not one of them")
        for c in cands:
            _require(c, ("design", f"gait_{data['unit']}", "gait_diverged"))
            c["design"] = list(space.validate_design(c["design"]))
    except (OSError, ValueError, TypeError, AttributeError) as exc:
        raise ValueError(f"{path}: not a shortlist of this run ({exc})") from None
    if data["checkpoint"] != r.require_checkpoint().name:
        return None
    return data


def _require(obj: dict, keys) -> None:
    """ValueError naming the first of ``keys`` that ``obj`` (a JSON object) lacks."""
    missing = [k for k in keys if k not in obj]
    if missing:
        raise ValueError(f"no {missing[0]!r}")


def run_design(run: str | Path) -> dict:
    """The run's design: ``{"design" (tuple), "source", "prob", "latest_cm", "episodes"}`` and,
    from a shortlist, ``"shortlist"`` (its :func:`read_shortlist` dict). ``source`` is
    ``"shortlist"`` (the best gait of its candidates) or ``"most probable"`` (no fresh
    shortlist: the choice before the shortlist existed, said on stderr).

    Raises:
        ValueError: not a training run, no complete checkpoint, no design tried yet, a malformed
            run file.
    """
    rows = design_rows(run)
    if not rows:
        raise ValueError(f"{run}: no design has been tried yet")
    sl = read_shortlist(run)
    if sl is None:
        note(f"{run} has no shortlist of its last checkpoint (shortlist.json; trained before it existed, or "
             "stopped before it was written): its design is the most probable one")
        row = most_probable(rows)
        return {"design": tuple(row["design"]), "source": "most probable", "prob": row["prob"],
                "latest_cm": row["latest_cm"], "episodes": row["episodes"]}
    design = tuple(sl["candidates"][sl["chosen"]]["design"])
    row = next((r for r in rows if r["design"] == design), None)
    if row is None:
        raise ValueError(f"{Run(run).shortlist_json}: its chosen design {','.join(map(str, design))} was never "
                         "tried in this run")
    return {"design": design, "source": "shortlist", "prob": row["prob"], "latest_cm": row["latest_cm"],
            "episodes": row["episodes"], "shortlist": sl}
