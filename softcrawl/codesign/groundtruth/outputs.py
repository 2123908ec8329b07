"""The tables and figure of a ground-truth folder: ``groundtruth.csv`` (ranked designs),
``summary.json``, ``summary.md`` (its Markdown: top designs, the best of each leg count,
placements, references, cost) and ``ranked.png``, from the valid rows of its ``results.jsonl``."""

from __future__ import annotations

import csv
import io
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from softcrawl.codesign.groundtruth.config import GroundTruthConfig
from softcrawl.codesign.groundtruth.result import DesignResult
from softcrawl.codesign.groundtruth.store import read_config, read_references, read_results
from softcrawl.design.space import BASELINE_DESIGN, PAPER_BEST_DESIGN
from softcrawl.gaits.periodic import PeriodicGait
from softcrawl.safeio import atomic_write_text
from softcrawl.tasks import DEFAULT_TASK, Task



def _portable(config: dict, out: Path) -> dict:
    """``config`` with a ``space`` inside the folder ``out`` (its own ``space.toml``, as
    :func:`softcrawl.codesign.groundtruth.store.read_config` gives it) named relative to it, so
    the summary does not carry this machine's absolute path."""
    space = Path(str(config.get("space", "")))
    if space.is_absolute() and space.parent.resolve() == out.resolve():
        return {**config, "space": space.name}
    return config

def write_outputs(out_dir: str | Path, designs: Sequence | None = None, wall_seconds: float | None = None) -> dict:
    """Write ``groundtruth.csv``, ``ranked.png``, ``summary.json`` and ``summary.md`` (each
    replaced atomically; rewards keyed ``reward_<unit>`` in the task's unit, and for a task
    other than ``forward`` the summary's ``task``: its settings and unit) from the valid rows of
    ``results.jsonl`` (only those in ``designs`` if given; the bad rows, by file and line, in
    the summary's ``bad_rows``); returns the summary. Its ``best`` lists the 10 best designs
    (with rank and legs), ``by_legs`` each leg count's designs, best design (its rank among
    all) and median reward (:func:`summary_markdown` writes it as Markdown).

    Raises:
        ValueError: the folder's ``config.json`` is missing or not a ground truth's.
    """
    out = Path(out_dir)
    cfg = read_config(out)
    task = cfg.task_spec()
    unit = task.unit
    reward = f"reward_{unit}"  # the rewards' keys and columns are in the task's unit (cm: forward)
    done, bad = read_results(out)  # the bad rows are listed in the summary
    if designs is not None:
        keep = {cfg.design_space().canonicalize(d) for d in designs}
        done = {d: r for d, r in done.items() if d in keep}
    rows = sorted(done.values(), key=lambda r: (-r.reward_cm, r.design))
    ranks = competition_ranks([r.reward_cm for r in rows])
    table = io.StringIO()
    w = csv.writer(table)
    w.writerow(["rank", "design", reward, "cycle", "waveform", "gait_kpa", "evaluations",
                "full_evaluations", "sim_seconds", "wall_seconds", "diverged"])
    for i, r in zip(ranks, rows):
        g = PeriodicGait.from_dict(r.gait)
        w.writerow([i, ",".join(map(str, r.design)), f"{r.reward_cm:.4f}", r.cycle, r.waveform,
                    json.dumps([[round(v, 2) for v in p] for p in g.patterns]), r.evaluations,
                    r.full_evaluations, f"{r.sim_seconds:.1f}", f"{r.wall_seconds:.1f}", r.diverged])
    atomic_write_text(out / "groundtruth.csv", table.getvalue())
    refs = read_references(out) or {}
    rewards = np.array([r.reward_cm for r in rows])
    rank_of = {r.design: k for r, k in zip(rows, ranks)}

    def place(d):
        d = tuple(d)
        if d not in done:
            return None
        rank = rank_of[d]
        return {"design": list(d), reward: done[d].reward_cm, "rank": rank,
                "percentile": 100.0 * (1 - (rank - 1) / len(rows))}

    summary = {
        "designs": len(rows), "requested": len(designs) if designs is not None else len(rows),
        "config": _portable(cfg.to_dict(), out),
        "best": [{"design": list(r.design), reward: r.reward_cm, "gait": PeriodicGait.from_dict(r.gait).describe(),
                  "rank": i, "legs": _legs(r.design)} for i, r in zip(ranks[:10], rows[:10])],
        "by_legs": _by_legs(rows, ranks, reward),
        reward: {"max": float(rewards.max()) if len(rows) else None,
                      "median": float(np.median(rewards)) if len(rows) else None,
                      "min": float(rewards.min()) if len(rows) else None},
        "paper_l1": place(PAPER_BEST_DESIGN), "expert_design": place(BASELINE_DESIGN),
        "references": {k: {kk: vv for kk, vv in v.items() if kk != f"sweep_{unit}"} for k, v in refs.items()},
        "cost": {"evaluations": int(sum(r.evaluations for r in rows)),
                 "sim_seconds": float(sum(r.sim_seconds for r in rows)),
                 "cpu_seconds": float(sum(r.wall_seconds for r in rows)),
                 "cpu_seconds_per_design": float(np.mean([r.wall_seconds for r in rows])) if rows else None,
                 "this_call_wall_seconds": wall_seconds},
        "bad_rows": bad,
    }
    if task.name != DEFAULT_TASK:  # a forward ground truth's summary stays as it was
        summary["task"] = {**task.settings(), "unit": unit}
    if "turning_baseline" in refs and len(rows):
        summary["designs_beating_turning_baseline"] = int(np.sum(rewards > refs["turning_baseline"]["reward_deg"]))
    if "expert_baseline" in refs and len(rows):
        b = refs["expert_baseline"]["reward_cm"]
        summary["designs_beating_expert_baseline"] = int(np.sum(rewards > b))
    atomic_write_text(out / "summary.json", json.dumps(summary, indent=2, allow_nan=False) + "\n")
    atomic_write_text(out / "summary.md", summary_markdown(summary, cfg.design_space().name))
    if rows:
        _ranked_plot(rows, ranks, refs, out / "ranked.png", cfg, task)
    return summary


def competition_ranks(rewards: Sequence[float]) -> list[int]:
    """Ranks of ``rewards`` sorted best first (length n): 1 + how many rewards are strictly
    greater, so designs of equal reward share a rank and the next rank skips ("1224" ranking),
    as :func:`softcrawl.codesign.groundtruth_regret.place_design` ranks a design.

    Raises:
        ValueError: ``rewards`` are not sorted best first.
    """
    r = np.asarray(rewards, dtype=float)
    if np.any(r[1:] > r[:-1]):
        raise ValueError("competition_ranks: rewards must be sorted best first")
    # -r ascends, so the leftmost slot of each value counts the rewards strictly greater
    return (1 + np.searchsorted(-r, -r, side="left")).tolist()


def _legs(design) -> int:
    """Legs of a design (its non-zero slots)."""
    return sum(v > 0 for v in design)


def _by_legs(rows: list[DesignResult], ranks: list[int], reward: str) -> dict[str, dict]:
    """Per leg count (a text key, ascending) of the ranked ``rows`` (their ``ranks``):
    ``designs``, ``best`` (design, ``reward``, rank among all rows, gait) and ``median`` reward."""
    out: dict[str, dict] = {}
    for legs in sorted({_legs(r.design) for r in rows}):
        mine = [i for i, r in enumerate(rows) if _legs(r.design) == legs]
        top = rows[mine[0]]
        out[str(legs)] = {"designs": len(mine), "best": {"design": list(top.design), reward: top.reward_cm,
                                                         "rank": ranks[mine[0]],
                                                         "gait": PeriodicGait.from_dict(top.gait).describe()},
                          "median": float(np.median([rows[i].reward_cm for i in mine]))}
    return out


def summary_markdown(summary: dict, space: str = "paper") -> str:
    """Markdown of a :func:`write_outputs` summary (``summary.md``): the count, the top designs,
    the best of each leg count, the paper's L1 and the expert's design placed, the references
    and the cost; rewards in the summary's task's unit. ``space``: the design space's name."""
    task = summary.get("task", {"name": DEFAULT_TASK, "unit": "cm"})
    u = task["unit"]
    reward = f"reward_{u}"
    cfg = summary["config"]
    lines = [f"# Ground truth: {summary['designs']} of {summary['requested']} designs", "",
             f"Design space `{space}`, task `{task['name']}`; each design's best open-loop periodic gait (CMA-ES, "
             f"cycles {', '.join(map(str, cfg['cycles']))}, {cfg['evals_per_cycle']} episodes each), its reward "
             f"in {u} per {cfg['duration']:g} s, engine `{cfg.get('engine', 'cpu')}`. Full ranking: "
             "`groundtruth.csv`.", ""]

    def text(design) -> str:
        return f"`{','.join(map(str, design))}`"

    if summary["best"]:
        lines += ["## Top designs", "", f"| rank | design | legs | reward ({u}) | gait (kPa) |",
                  "|---|---|---|---|---|"]
        lines += [f"| {b['rank']} | {text(b['design'])} | {b['legs']} | {b[reward]:+.2f} | {b['gait']} |"
                  for b in summary["best"]]
        lines += ["", "## Best of each leg count", "",
                  f"| legs | designs | best design | reward ({u}) | its rank | median ({u}) |",
                  "|---|---|---|---|---|---|"]
        lines += [f"| {legs} | {g['designs']} | {text(g['best']['design'])} | {g['best'][reward]:+.2f} | "
                  f"{g['best']['rank']} | {g['median']:+.2f} |" for legs, g in summary["by_legs"].items()]
        lines.append("")
    placed = [(name, summary.get(key))
              for key, name in (("paper_l1", "paper's L1"), ("expert_design", "expert's design"))]
    if any(p for _, p in placed):
        lines += ["## Placements", ""]
        lines += [f"- {name} {text(p['design'])}: rank {p['rank']} of {summary['designs']} "
                  f"({p[reward]:+.2f} {u}, percentile {p['percentile']:.1f})" for name, p in placed if p]
        lines.append("")
    if summary["references"]:
        lines += ["## References", ""]
        lines += [f"- {name.replace('_', ' ')}: "
                  + (f"{text(ref['design'])} " if isinstance(ref.get("design"), list) else "")
                  + f"{ref[reward]:+.2f} {u}" for name, ref in summary["references"].items()]
        lines.append("")
    cost = summary["cost"]
    lines += ["## Cost", "", f"{cost['evaluations']} episodes, {cost['sim_seconds']:.0f} simulated s, "
              f"{cost['cpu_seconds']:.0f} s of search time summed over the designs"
              + (f"; this call {cost['this_call_wall_seconds']:.0f} s of wall time"
                 if cost["this_call_wall_seconds"] is not None else "") + "."]
    if summary["bad_rows"]:
        lines += ["", f"{len(summary['bad_rows'])} bad rows of `results.jsonl` left out (`summary.json` lists them)."]
    return "\n".join(lines) + "\n"


def _ranked_plot(rows: list[DesignResult], ranks: list[int], refs: dict, path: Path, cfg: GroundTruthConfig,
                 task: Task) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.array([x.reward_cm for x in rows])
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(np.arange(1, len(r) + 1), r, ".-", color="0.4", ms=4, lw=0.8, label="designs (best gait)")
    for i, x in enumerate(rows):
        if x.design == PAPER_BEST_DESIGN:
            ax.plot(i + 1, x.reward_cm, "o", color="C3", ms=9, label=f"paper L1 1,0,0,2,2,0,0,0 (rank {ranks[i]})")
        if x.design == BASELINE_DESIGN:
            ax.plot(i + 1, x.reward_cm, "s", color="C0", ms=8, label=f"expert design (rank {ranks[i]})")
    if "expert_baseline" in refs:
        b = refs["expert_baseline"]
        ax.axhline(b["reward_cm"], color="C0", ls="--", lw=1,
                   label=f"expert baseline (sine, {b['best_phase_deg']:.0f} deg): {b['reward_cm']:+.2f} cm")
    if "turning_baseline" in refs:
        b = refs["turning_baseline"]
        ax.axhline(b["reward_deg"], color="C0", ls="--", lw=1,
                   label=f"turning baseline ({b['best_phase_deg']:.0f} deg lag): {b['reward_deg']:+.2f} deg")
    if "paper_l1_gait" in refs:
        ax.axhline(refs["paper_l1_gait"]["reward_cm"], color="C3", ls=":", lw=1,
                   label=f"paper L1 with paper's 3-s gait: {refs['paper_l1_gait']['reward_cm']:+.2f} cm")
    ax.set_xlabel("rank")
    ax.set_ylabel(f"reward ({task.unit} per {cfg.duration:g} s)")
    what = "" if task.name == DEFAULT_TASK else f", task {task.label()}"
    ax.set_title(f"Ground truth: {len(r)} designs, best gait each (reduced model{what})")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)
