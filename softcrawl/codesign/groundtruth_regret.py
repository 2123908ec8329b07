"""Regret of a co-design run against the ground truth (``softcrawl regret``).

The run's *chosen design* is its design (:func:`softcrawl.codesign.shortlist.run_design`: the
best gait of its final shortlist, or for a run without one the most probable design of its final
design distribution, ties to the higher latest return); it is placed in a ground truth
(:mod:`softcrawl.codesign.groundtruth`): its true rank and percentile among the ground truth's
designs, its regret (best ground-truth reward − its ground-truth reward per episode of the
ground truth), and its learned policy's reward next to its ground-truth gait's. The run and the
ground truth must be of one design space and one task (:mod:`softcrawl.tasks`, its settings
included); the rewards are in the task's unit (:attr:`softcrawl.tasks.Task.unit`: cm for the
paper's ``forward``, degrees for ``turning``), and the keys of the numbers name it
(``reward_cm``, ``regret_deg``, ...).

The rewards are only comparable when the run and the ground truth simulate the same episodes;
:func:`compute_regret` lists every setting that differs (``settings_differ``) and the Markdown
says so. When they are the same and the learned gait beats the ground truth's best gait for the
chosen design (:func:`policy_beats`), the ground truth's search missed a gait there, and the
Markdown says that its rank is a lower bound.

All calls into the training-run code (:mod:`softcrawl.codesign.shortlist`,
:mod:`softcrawl.codesign.evaluation`) are in :func:`run_choice` and :func:`policy_reward`; the run
folder is read only through :class:`softcrawl.codesign.run.Run` (:func:`run_settings`).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from softcrawl.codesign.groundtruth import GroundTruthConfig, PeriodicGait, load_groundtruth
from softcrawl.tasks import DEFAULT_TASK


# -- the one place that reads a training run -----------------------------------------------------
def run_choice(run: str | Path) -> dict:
    """The run's chosen design (:func:`softcrawl.codesign.shortlist.run_design`): ``{"design",
    "source", "prob", "latest_cm", "episodes"}`` and ``"shortlist"`` (its shortlist, if it
    has one).

    Raises:
        ValueError: not a training run / no checkpoint / nothing tried / a malformed shortlist.
    """
    from softcrawl.codesign.shortlist import run_design

    return run_design(run)


def policy_reward(run: str | Path, design) -> dict:
    """The run's learned policy's gait on ``design`` (the run's settings; the best of the
    deterministic policy and :data:`~softcrawl.codesign.evaluation.GAIT_SAMPLES` episodes
    sampled from it, as the report's, :attr:`~softcrawl.codesign.evaluation.PolicyEvaluation.chosen`):
    ``{"reward_<unit>", "diverged", "gait_source", "actions_kpa", "episode_seconds", "hold_s"}``,
    its return in the unit of the run's task (``reward_cm`` for ``forward``). Read from the
    run's shortlist (:func:`softcrawl.codesign.shortlist.read_shortlist`) when it evaluated
    ``design`` with as many samples, else simulated."""
    from softcrawl.codesign.evaluation import GAIT_SAMPLES, episode_seconds, evaluate_policy
    from softcrawl.codesign.run import Run
    from softcrawl.codesign.shortlist import read_shortlist
    from softcrawl.tasks import parse_task

    shortlist = read_shortlist(run)
    done = [c for c in (shortlist or {}).get("candidates", []) if tuple(c["design"]) == tuple(design)]
    if done and shortlist["samples"] == GAIT_SAMPLES:
        cfg, u, c = Run(run).read_config(), shortlist["unit"], done[0]
        return {f"reward_{u}": c[f"gait_{u}"], "diverged": bool(c["gait_diverged"]),
                "gait_source": c.get("gait_source", "?"), "actions_kpa": c.get("actions_kpa"),
                "episode_seconds": episode_seconds(cfg), "hold_s": cfg.env.robot.dt * cfg.env.steps_per_action}
    ev = evaluate_policy(run, design, episodes=1, samples=GAIT_SAMPLES)
    e = ev.config.env
    diverged = ev.diverged[0] if ev.chosen is None else ev.sampled_diverged[ev.chosen]
    return {f"reward_{parse_task(e.task).unit}": ev.gait_return, "diverged": bool(diverged),
            "gait_source": ev.gait_source, "actions_kpa": np.asarray(ev.gait_actions_kpa).round(2).tolist(),
            "episode_seconds": episode_seconds(ev.config), "hold_s": e.robot.dt * e.steps_per_action}


def run_settings(run: str | Path) -> dict:
    """Simulation settings of a run comparable with a ground truth's (:func:`gt_settings`), read
    from the raw ``config.json`` (:meth:`softcrawl.codesign.run.Run.read_meta`, in the current
    format: :func:`softcrawl.codesign.migrate.read_settings`; so runs saved by older versions
    still compare).

    Raises:
        ValueError: not a training run, or a ``config.json`` without the settings.
    """
    from softcrawl.codesign.migrate import read_settings
    from softcrawl.codesign.run import Run

    r = Run(run)
    meta = r.read_meta()  # ValueError: not a run, or no config object
    try:
        e = read_settings("train", meta)["env"]
        robot = e["robot"]
        hold = float(robot["dt"]) * float(e["steps_per_action"])
        float(e["n_actions"])
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"{r.config_path}: no env settings robot.dt, steps_per_action, n_actions ({exc!r})") from None
    return {"model": robot.get("model", "reduced"), "leg_mesh_size": float(robot.get("leg_mesh_size", 6.0)),
            "disk_mesh_size": float(robot.get("disk_mesh_size", 10.0)), "dt": float(robot["dt"]),
            "hold_s": round(hold, 9), "episode_seconds": round(hold * float(e["n_actions"]), 9),
            "reduction": robot.get("reduction")}


def run_space(run: str | Path):
    """The run's :class:`~softcrawl.design.spacefile.DesignSpace` (its ``space.toml``; the
    paper's for a run of an older format). ValueError as :meth:`Run.read_config`."""
    from softcrawl.codesign.run import Run

    return Run(run).design_space()


def run_task(run: str | Path):
    """The run's :class:`~softcrawl.tasks.Task` (``env.task`` of its ``config.json``; ``forward``
    for a run saved before tasks existed, as :func:`run_space`). ValueError as
    :meth:`Run.read_config`."""
    from softcrawl.codesign.run import Run
    from softcrawl.tasks import parse_task

    r = Run(run)
    return parse_task(r.read_config().env.task if r.exists() else DEFAULT_TASK)
# -------------------------------------------------------------------------------------------------


def gt_settings(cfg: GroundTruthConfig) -> dict:
    """The ground truth's settings in the keys of :func:`run_settings`."""
    r = cfg.robot
    return {"model": r.model, "leg_mesh_size": float(r.leg_mesh_size), "disk_mesh_size": float(r.disk_mesh_size),
            "dt": float(r.dt), "hold_s": round(cfg.hold, 9), "episode_seconds": round(cfg.duration, 9),
            "reduction": r.reduction}


def place_design(design, gt_dir: str | Path, results: dict | None = None, unit: str | None = None) -> dict:
    """Rank of ``design`` in a ground truth: ``{"design", "reward_<u>", "rank", "of",
    "requested", "percentile", "best_design", "best_<u>", "regret_<u>", "gait"}``, ``u`` its
    task's unit (``cm`` for ``forward``, :func:`softcrawl.codesign.groundtruth.store.folder_task`;
    ``unit`` if given) (rank 1 = best, designs of equal reward share a rank; percentile = share
    of designs it beats or ties, %). Only the ground truth's valid rows count
    (:func:`softcrawl.codesign.groundtruth.read_results`; a bad row is a note naming its file
    and line): ``of`` of them, among the ``requested`` designs of the folder's recorded set
    (:func:`requested_designs`), more than ``of`` while the ground truth is unfinished.

    Args:
        results: the ground truth's results by design, if already read (else read from ``gt_dir``).

    Raises:
        ValueError: ``design`` is not in the ground truth, or the folder is not one.
    """
    from softcrawl.codesign.groundtruth.store import folder_space, folder_task

    u = folder_task(gt_dir).unit if unit is None else unit
    res = load_groundtruth(gt_dir)[1] if results is None else results
    d = folder_space(gt_dir).canonicalize(design)
    if d not in res:
        raise ValueError(f"design {','.join(map(str, d))} is not in the ground truth {gt_dir} ({len(res)} designs)")
    rewards = np.array([r.reward_cm for r in res.values()])
    mine = res[d].reward_cm
    best = max(res.values(), key=lambda r: (r.reward_cm, tuple(-v for v in r.design)))
    rank = 1 + int(np.sum(rewards > mine))
    return {"design": list(d), f"reward_{u}": mine, "rank": rank, "of": len(res),
            "requested": requested_designs(gt_dir, res), "percentile": 100.0 * float(np.mean(rewards <= mine)),
            "best_design": list(best.design), f"best_{u}": best.reward_cm, f"regret_{u}": best.reward_cm - mine,
            "gait": res[d].gait}


def requested_designs(gt_dir: str | Path, results: dict) -> int | None:
    """How many designs the ground truth ``gt_dir`` is of: its recorded design set
    (:func:`~softcrawl.codesign.groundtruth.store.recorded_designs`) with its ``results`` (by
    design), more than ``len(results)`` while it is unfinished; None for a folder that records
    no set.

    Raises:
        ValueError: as :func:`~softcrawl.codesign.groundtruth.store.recorded_designs`.
    """
    from softcrawl.codesign.groundtruth.store import recorded_designs

    recorded = recorded_designs(gt_dir)
    return None if recorded is None else len(set(recorded) | set(results))


#: Relative margin by which the learned gait's return must exceed the ground truth's for the
#: chosen design before :func:`policy_beats` says the search missed a gait: the run's env and the
#: ground truth's evaluator replay one action sequence within about 0.5% (+23.82 against +23.69 cm,
#: docs/results.md, "Ground truth").
BEATS_MARGIN = 0.02


def policy_beats(placement: dict, pol: dict, results: dict, unit: str) -> dict | None:
    """Whether the learned gait (``pol``, :func:`policy_reward`) returned more on the chosen
    design than the ground truth's best gait for it (``placement``, :func:`place_design`), by
    more than :data:`BEATS_MARGIN`: then ``{"margin_<u>": how much more, "rank": the rank that
    return would take among the other designs' ground-truth values}`` (the ground truth's search
    missed a gait, so its values are lower bounds and its rank of the choice may be too low);
    else None. Only meaningful when the run and the ground truth simulate the same episodes."""
    mine, theirs = placement[f"reward_{unit}"], pol[f"reward_{unit}"]
    if pol["diverged"] or theirs is None or not math.isfinite(theirs) or theirs <= mine + BEATS_MARGIN * abs(mine):
        return None
    d = tuple(placement["design"])
    others = np.array([r.reward_cm for k, r in results.items() if k != d])
    return {f"margin_{unit}": theirs - mine, "rank": 1 + int(np.sum(others > theirs))}


def compute_regret(run: str | Path, gt_dir: str | Path, policy: bool = True) -> dict:
    """Regret of ``run``'s chosen design in the ground truth ``gt_dir`` (module docstring).

    Args:
        policy: also roll out the learned policy on the chosen design (one episode).

    Returns:
        dict: ``run``, ``groundtruth``, ``task`` (its settings and ``unit``; left out for
        ``forward``, the paper's), ``choice`` (:func:`run_choice`, its shortlist's candidates
        as ``candidates``), ``placement`` (:func:`place_design`; with the policy and no
        setting differing, also ``policy_beats_groundtruth``, :func:`policy_beats`), ``policy``
        (:func:`policy_reward` or None), ``settings_differ`` (``{key: [run, ground truth]}``);
        a number that is not finite (a diverged policy episode's reward) is None.

    Raises:
        ValueError: not a run / ground truth, the two of different design spaces or of
            different tasks (one line naming both), or the chosen design is not in the ground
            truth.
    """
    cfg, res, _ = load_groundtruth(gt_dir)
    mine, theirs = run_space(run), cfg.design_space()
    if mine != theirs:
        raise ValueError(f"the run {run} (design space {mine.name!r}) and the ground truth {gt_dir} (design "
                         f"space {theirs.name!r}) are of different design spaces")
    task, gt_task = run_task(run), cfg.task_spec()
    if task != gt_task:
        raise ValueError(f"the run {run} (task {task.label()}) and the ground truth {gt_dir} (task "
                         f"{gt_task.label()}) are of different tasks")
    choice = run_choice(run)
    placement = place_design(choice["design"], gt_dir, res, task.unit)
    rs, gs = run_settings(run), gt_settings(cfg)
    differ = {k: [rs[k], gs[k]] for k in rs if rs[k] != gs[k]}
    pol = policy_reward(run, choice["design"]) if policy else None
    if pol is not None and not differ:
        placement["policy_beats_groundtruth"] = policy_beats(placement, pol, res, task.unit)
    from softcrawl.robot.output import jsonable  # JSON has no NaN: a number that is not finite is None

    sl = choice.pop("shortlist", None)
    choice = {**choice, "design": list(choice["design"])}
    if sl is not None:
        choice["candidates"] = [",".join(map(str, c["design"])) for c in sl["candidates"]]
    about = {} if task.name == DEFAULT_TASK else {"task": {**task.settings(), "unit": task.unit}}
    return jsonable({"run": str(run), "groundtruth": str(gt_dir), **about, "choice": choice, "placement": placement,
                     "policy": pol, "settings_differ": differ})


def regret_markdown(r: dict) -> list[str]:
    """Markdown lines of a :func:`compute_regret` dict (numbers in its task's unit; a dict
    without ``task``: cm, the forward task)."""
    p, c = r["placement"], r["choice"]
    u = r.get("task", {}).get("unit", "cm")
    d = ",".join(map(str, p["design"]))
    task = "" if r.get("task", {}).get("name", "forward") == "forward" else f", task {r['task']['name']}"
    lines = ["## Regret against the ground truth", "",
             f"Ground truth: `{r['groundtruth']}` ({p['of']} designs, best open-loop gait each{task}).", "",
             "| | |", "|---|---|",
             f"| chosen design ({_why(c)}, p = {c['prob']:.3f}) | `{d}` |",
             f"| true rank | {p['rank']} of {p['of']} (percentile {p['percentile']:.1f}) |",
             f"| its ground-truth reward | {p[f'reward_{u}']:+.2f} {u} "
             f"({PeriodicGait.from_dict(p['gait']).describe()} kPa) |",
             f"| best design | `{','.join(map(str, p['best_design']))}` {p[f'best_{u}']:+.2f} {u} |",
             f"| regret | {p[f'regret_{u}']:.2f} {u} |"]
    if r.get("policy"):
        pol = r["policy"]
        reward = "no reward" if pol[f"reward_{u}"] is None else f"{pol[f'reward_{u}']:+.2f} {u}"
        lines.append(f"| learned policy's gait on the chosen design ({pol.get('gait_source', 'deterministic')}) | "
                     f"{reward}{' (diverged)' if pol['diverged'] else ''} per {pol['episode_seconds']:g} s |")
        lines.append(f"| ground-truth gait on it | {p[f'reward_{u}']:+.2f} {u} |")
    beats = p.get("policy_beats_groundtruth")
    lines.append("")
    if (p.get("requested") or 0) > p["of"]:
        lines += [f"The ground truth is unfinished: {p['of']} of its {p['requested']} designs are done, and the "
                  "rank is among those; the designs still to come can only move it down the table.", ""]
    if beats:
        lines += [f"The learned gait returns {beats[f'margin_{u}']:.2f} {u} more on the chosen design than the "
                  "ground truth's best gait for it: the ground truth's search missed a gait, so its values are "
                  "lower bounds and the rank above may understate the choice (with the learned gait's return it "
                  f"would place {beats['rank']} of {p['of']} among the other designs' ground-truth values).", ""]
    if r["settings_differ"]:
        diffs = "; ".join(f"{k}: run {a} vs ground truth {b}" for k, (a, b) in r["settings_differ"].items())
        lines += [f"The run and the ground truth simulate different episodes ({diffs}): the rank and regret "
                  "say how good the chosen design is under the ground truth's episodes; the policy's reward "
                  "is under the run's.", ""]
    return lines


def _why(choice: dict) -> str:
    """How the run's design was chosen, for the regret table (a dict of :func:`compute_regret`
    saved before the shortlist existed has no ``source``: the most probable)."""
    if choice.get("source") == "shortlist":
        return f"the best gait of {len(choice.get('candidates', []))} shortlisted"
    return "most probable"


def regret_section(run: str | Path, gt_dir: str | Path, policy: bool = True) -> tuple[list[str], dict]:
    """For ``softcrawl report``: ``(Markdown lines, the compute_regret dict)``."""
    r = compute_regret(run, gt_dir, policy=policy)
    return regret_markdown(r), r


