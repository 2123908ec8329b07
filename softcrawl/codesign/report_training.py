"""The training part of a co-design run's report (:mod:`softcrawl.codesign.report`): what the
paper's reward-histogram figure (``fig:reward_hist``) shows, and where the paper's own designs
fall in the run.

* ``reward_histogram.png``: over training (x: steps), the latest returns of the tried designs
  (y, the task's unit) weighted by the design distribution p (renormalised over the tried
  designs), from the run's ``snapshots/``, the best return so far as a red line (diverged
  episodes left out) and a dotted line where each of the modes held longest first became the
  mode;
* ``reward_histogram_points.png`` and a table: that histogram at :data:`HISTOGRAM_POINTS` points
  of training, with the p-weighted mean return, the most probable design and the best so far;
* the mode switches (:func:`mode_switches`: when the most probable design changed, from
  ``distribution.csv``), a table and ``mode_switches.png`` (pictures of the designs that were
  the mode longest);
* ``returns.png``: episode returns over training with a running mean;
* the paper's five best learned designs L1-L5 (:data:`PAPER_DESIGNS`) placed in the run's
  ranking and, given a ground truth, in its ranking (:func:`paper_designs_section`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from softcrawl.codesign.run import Run, note
from softcrawl.codesign.shortlist import by_latest
from softcrawl.design.picture import plot_design
from softcrawl.design.space import DEFAULT_SPACE, PAPER_BEST_DESIGN

#: Points of training the report draws the weighted reward histogram at (snapshots evenly spread).
HISTOGRAM_POINTS = 5
#: Most modes pictured (the designs that were the most probable longest; the report lists every
#: mode switch).
MAX_PICTURED_MODES = 6


def _read_snapshots(run: Run) -> list[dict]:
    """The run's readable snapshots, oldest first (an unreadable one is a note and left out)."""
    data = []
    for s in run.snapshots():
        try:
            data.append(run.read_snapshot(s))
        except ValueError as exc:
            note(f"{exc}; left out of the reward histogram")
    return data


def _ok_returns(ep: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(t, r)`` of the logged episodes that did not diverge (a diverged episode's return is
    its motion before the blow-up, not a reward)."""
    ok = ~ep["diverged"]
    return ep["t"][ok], ep["r"][ok]


def _best_so_far(ep: dict, t: int) -> float:
    """The best return of the episodes (not diverged) logged by step ``t``; NaN if none."""
    et, er = _ok_returns(ep)
    mine = er[et <= t]
    return float(mine.max()) if len(mine) else float("nan")


def _edges(data: list[dict], ep: dict) -> np.ndarray:
    """40 equal return bins spanning every snapshot's tried scores and every episode's return
    (diverged ones left out)."""
    allr = np.concatenate([d["scores"][d["tried"]] for d in data] + [_ok_returns(ep)[1]])
    lo, hi = (float(allr.min()), float(allr.max())) if allr.size else (0.0, 1.0)
    return np.linspace(lo, max(hi, lo + 1e-3), 41)


def _weighted_histogram(d: dict, edges: np.ndarray) -> np.ndarray:
    """A snapshot's tried designs' latest returns histogrammed over ``edges``, weighted by p
    (renormalised over the tried designs): ``(len(edges) - 1,)`` probability mass."""
    w = d["p"][d["tried"]].astype(float)
    if w.sum() <= 0:
        return np.zeros(len(edges) - 1)
    return np.histogram(d["scores"][d["tried"]], bins=edges, weights=w / w.sum())[0]


def _histogram_figure(data: list[dict], ep: dict, path: Path, unit: str = "cm",
                      switches: list[dict] = ()) -> bool:
    """The weighted reward histogram over training (the paper's ``fig:reward_hist``): x steps,
    y latest return, colour the probability mass, the best return so far as a line, and the
    labelled modes (:func:`mode_switches`, pictured in ``mode_switches.png``) as dotted lines
    where each first became the mode. False (nothing drawn) without snapshots."""
    from matplotlib.figure import Figure

    if not data:
        return False
    ts = np.array([int(d["t"]) for d in data])
    edges = _edges(data, ep)
    img = np.stack([_weighted_histogram(d, edges) for d in data], axis=1)
    fig = Figure(figsize=(7, 4))
    ax = fig.add_subplot()
    mesh = ax.pcolormesh(np.concatenate([[0], ts]), edges, img, cmap="viridis", shading="flat")
    fig.colorbar(mesh, ax=ax, label="probability mass (design distribution)")
    et, er = _ok_returns(ep)
    if len(er):
        ax.step(et, np.maximum.accumulate(er), where="post", color="tab:red", label="best so far")
        ax.legend(loc="lower right")
    for sw in _pictured(switches):
        ax.axvline(sw["t"], color="w", ls=":", lw=1)
        ax.annotate(sw["label"], (sw["t"], edges[-1]), color="w", fontsize=8, ha="left", va="top")
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"latest return R ({unit} per episode)")
    ax.set_title("Returns weighted by the design distribution")
    fig.savefig(path, dpi=110, bbox_inches="tight")
    return True


def histogram_points(data: list[dict], ep: dict, n: int = HISTOGRAM_POINTS) -> list[dict]:
    """The weighted reward histogram at ``n`` points of training (snapshots evenly spread, the
    first and the last included): per point ``t`` (steps), ``edges`` (``(41,)`` returns, the
    run's unit) and ``mass`` (``(40,)``, :func:`_weighted_histogram`), ``mean`` (the
    p-weighted mean latest return of the tried designs), ``mode`` (the index of the most
    probable design in the distribution's list; None while it is uniform) and its ``p``,
    ``tried`` (designs) and ``best_so_far``."""
    if not data:
        return []
    edges = _edges(data, ep)
    out = []
    for j in sorted(set(np.linspace(0, len(data) - 1, min(n, len(data))).round().astype(int))):
        d = data[j]
        tried = np.flatnonzero(d["tried"])
        w = d["p"][tried].astype(float)
        mode = int(np.argmax(d["p"]))
        out.append({"t": int(d["t"]), "edges": edges, "mass": _weighted_histogram(d, edges),
                    "mean": float(np.dot(w, d["scores"][tried]) / w.sum()) if w.sum() > 0 else float("nan"),
                    "mode": None if np.ptp(d["p"]) == 0 else mode, "p": float(d["p"][mode]), "tried": int(len(tried)),
                    "best_so_far": _best_so_far(ep, int(d["t"]))})
    return out


def _points_figure(points: list[dict], path: Path, unit: str = "cm") -> None:
    """One panel per point of :func:`histogram_points`: the probability mass per return bin
    (horizontal bars), the best return so far as a red line."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(2.2 * len(points) + 0.6, 3.6))
    axes = fig.subplots(1, len(points), sharey=True, squeeze=False)[0]
    for ax, pt in zip(axes, points):
        e = pt["edges"]
        ax.barh(e[:-1], pt["mass"], height=np.diff(e), align="edge", color="tab:blue")
        if np.isfinite(pt["best_so_far"]):
            ax.axhline(pt["best_so_far"], color="tab:red", lw=1)
        ax.set_title(f"step {pt['t']:,}", fontsize=9)
        ax.set_xlim(0, 1)
        ax.set_xlabel("mass")
    axes[0].set_ylabel(f"latest return R ({unit})")
    fig.suptitle("Returns weighted by the design distribution at points of training (red: best so far)",
                 fontsize=10)
    fig.savefig(path, dpi=110, bbox_inches="tight")


def mode_switches(dist: dict) -> list[dict]:
    """When the most probable design changed (the paper's "mode switches"), from
    ``distribution.csv`` (:meth:`Run.read_distribution`): a row names a mode once beta > 0 (after
    the uniform phase) and its first design is more probable than its second as logged (a tie
    names none). Each switch is ``{"t", "design", "p", "held_steps"}`` (steps until the next
    switch, or to the last row) and ``"label"``: ``"M<i>"`` for the :data:`MAX_PICTURED_MODES`
    designs that were the mode longest in all (ties: the later), numbered by when they first
    became it, on every switch to them; None for the others."""
    out: list[dict] = []
    for t, beta, top in zip(dist["t"], dist["beta"], dist["top"]):
        if beta <= 0 or not top or (len(top) > 1 and top[0][1] <= top[1][1]):
            continue
        if not out or out[-1]["design"] != top[0][0]:
            out.append({"t": int(t), "design": top[0][0], "p": top[0][1]})
    end = int(dist["t"][-1]) if len(dist["t"]) else 0
    held: dict[tuple, int] = {}
    last: dict[tuple, int] = {}
    for i, (a, b) in enumerate(zip(out, out[1:] + [None])):
        a["held_steps"] = (end if b is None else b["t"]) - a["t"]
        held[a["design"]] = held.get(a["design"], 0) + a["held_steps"]
        last[a["design"]] = i
    longest = sorted(held, key=lambda d: (-held[d], -last[d]))[:MAX_PICTURED_MODES]
    first = sorted(longest, key=lambda d: next(i for i, sw in enumerate(out) if sw["design"] == d))
    labels = {d: f"M{i}" for i, d in enumerate(first, 1)}
    for sw in out:
        sw["label"] = labels.get(sw["design"])
    return out


def _pictured(switches: list[dict]) -> list[dict]:
    """The first switch to each labelled mode (:func:`mode_switches`), in time order."""
    seen, out = set(), []
    for sw in switches:
        if sw["label"] is not None and sw["label"] not in seen:
            seen.add(sw["label"])
            out.append(sw)
    return out


def _modes_figure(switches: list[dict], path: Path, space) -> None:
    """The labelled modes' designs side by side (:func:`mode_switches`), with the step each
    first became the mode and how long it was in all."""
    from matplotlib.figure import Figure

    shown = _pictured(switches)
    fig = Figure(figsize=(2.4 * len(shown), 2.9))
    for ax, sw in zip(fig.subplots(1, len(shown), squeeze=False)[0], shown):
        plot_design(sw["design"], ax=ax, space=space)
        held = sum(s["held_steps"] for s in switches if s["design"] == sw["design"])
        ax.set_title(f"{sw['label']}: from step {sw['t']:,}\n{','.join(map(str, sw['design']))}, "
                     f"{held:,} steps", fontsize=8)
        legend = ax.get_legend()
        if legend is not None:
            legend.remove()
    fig.savefig(path, dpi=100, bbox_inches="tight")


def training_section(r: Run, ep: dict, out: Path, unit: str, space, designs) -> tuple[list[str], dict]:
    """The report's "Training" section: the weighted reward histogram over training
    (``reward_histogram.png``) and at points of it (``reward_histogram_points.png``, a table),
    the mode switches (a table, ``mode_switches.png``) and the returns (``returns.png``);
    Markdown lines and the numbers for ``summary.json``. ``designs``: the distribution's design
    list (``env.designs()`` of the run's config), which the snapshots' arrays follow."""
    data = _read_snapshots(r)
    try:
        switches = mode_switches(r.read_distribution())
    except ValueError as exc:
        note(f"{exc}; no mode switches in the report")
        switches = []
    lines = ["", "## Training", ""]
    if _histogram_figure(data, ep, out / "reward_histogram.png", unit, switches):
        lines += ["![reward histogram weighted by the design distribution](reward_histogram.png)", ""]
    points = histogram_points(data, ep)
    if points:
        _points_figure(points, out / "reward_histogram_points.png", unit)
        lines += ["The design distribution at points of training (its snapshots): the p-weighted mean latest return "
                  "of the tried designs, the most probable design, the best episode so far (diverged ones left out).",
                  "", f"| step | tried designs | weighted mean R ({unit}) | most probable (p) | best so far ({unit}) |",
                  "|---|---|---|---|---|"]
    def mode(pt) -> str | None:
        ok = pt["mode"] is not None and all(len(d["p"]) == len(designs) for d in data)
        return ",".join(map(str, designs[pt["mode"]])) if ok else None

    for pt in points:
        m = mode(pt)
        m = "uniform" if pt["mode"] is None else "?" if m is None else f"`{m}`"
        lines.append(f"| {pt['t']:,} | {pt['tried']} | {pt['mean']:+.3f} | {m} ({pt['p']:.3g}) | "
                     f"{pt['best_so_far']:+.3f} |")
    if points:
        lines += ["", "![reward histogram at points of training](reward_histogram_points.png)", ""]
    lines += ["### Mode switches", ""]
    if not switches:
        lines.append("None: no design was more probable than every other after the uniform phase.")
    else:
        _modes_figure(switches, out / "mode_switches.png", space)
        n = len(_pictured(switches))
        lines += [f"When the most probable design changed after the uniform phase ({len(switches)} "
                  f"{'time' if len(switches) == 1 else 'times'}; M: "
                  f"{'the design that was' if n == 1 else f'the {n} designs that were'} the mode longest, pictured "
                  "below and marked in the histogram where each first became it):", "",
                  "| | from step | design | p | held (steps) |", "|---|---|---|---|---|"]
        for sw in switches:
            lines.append(f"| {sw['label'] or ''} | {sw['t']:,} | `{','.join(map(str, sw['design']))}` | {sw['p']:.3g} | "
                         f"{sw['held_steps']:,} |")
        lines += ["", "![mode switches](mode_switches.png)"]
    _returns_figure(ep, out / "returns.png", unit)
    lines += ["", "![episode returns](returns.png)"]
    numbers = {"points": [{k: v for k, v in pt.items() if k not in ("edges", "mass", "mode")}
                          | {"mode": mode(pt)}
                          for pt in points],
               "mode_switches": [{**sw, "design": ",".join(map(str, sw["design"]))} for sw in switches]}
    return lines, numbers


def _returns_figure(ep: dict, path: Path, unit: str = "cm") -> None:
    from matplotlib.figure import Figure

    fig = Figure(figsize=(7, 3.5))
    ax = fig.add_subplot()
    if len(ep["r"]):
        ax.plot(ep["t"], ep["r"], ".", ms=3, alpha=0.4, label="episode return")
        w = max(1, len(ep["r"]) // 20)
        run_mean = np.convolve(ep["r"], np.ones(w) / w, mode="valid")
        ax.plot(ep["t"][w - 1:], run_mean, color="k", label=f"running mean ({w})")
        ax.legend()
    ax.set_xlabel("environment steps")
    ax.set_ylabel(f"return ({unit})")
    fig.savefig(path, dpi=110, bbox_inches="tight")


#: The paper's five best learned designs, "L1-L5 in order of decreasing reward" (its Results;
#: pictured in its figure ``fig:comparison_reward``, which its source does not hold): ``(name,
#: design in the paper's space or None, what its text says of it)``. The text names one design,
#: L1's (``1,0,0,2,2,0,0,0``: one front leg at 22.5° on regulator 1, rear legs at 157.5° and
#: 202.5° on regulator 2, docs/codesign.md); of L2-L5 it tells only what is kept here, too
#: little to name a design.
PAPER_DESIGNS: tuple[tuple[str, tuple[int, ...] | None, str], ...] = (
    ("L1", PAPER_BEST_DESIGN, "the paper's best; its run converged on it about halfway through training"),
    ("L2", None, "asymmetric"),
    ("L3", None, "symmetric, regulator 3 driving one leg only"),
    ("L4", None, "asymmetric"),
    ("L5", None, "asymmetric; the design the distribution first specialised to after 200K steps"),
)


def paper_designs_section(rows: list[dict], cfg, groundtruth: str | Path | None = None,
                          unit: str = "cm") -> tuple[list[str], list]:
    """Where the paper's designs (:data:`PAPER_DESIGNS`) fall in the run: their rank among its
    tried designs by latest return R (the order of the report's top table; ``rows``:
    :func:`softcrawl.codesign.shortlist.design_rows`), their R, best episode (``unit``) and final p; with
    ``groundtruth`` (a ``softcrawl groundtruth`` folder of the paper's space) their rank and
    reward in it (:func:`softcrawl.codesign.groundtruth_regret.place_design`). A run of another
    design space has a line saying so. Returns the Markdown lines and the numbers (a dict per
    design) for ``summary.json``.

    Raises:
        ValueError: ``groundtruth`` is not a ground-truth folder.
    """
    space = cfg.env.design_space()
    lines = ["", "## The paper's designs (L1-L5)", ""]
    if space != DEFAULT_SPACE:
        return lines + [f"The paper's designs are of its own design space; this run's is `{space.name}`."], []
    ranked = by_latest(rows)
    place, gt_size = _groundtruth_placer(groundtruth)
    in_play = set(cfg.env.designs())
    lines += [("The paper's five best learned designs (its Results, in order of decreasing reward), placed among "
               f"this run's {len(ranked)} tried designs by latest return R (as the top table)"
               + (f" and in the ground truth `{groundtruth}` ({gt_size})." if place else ".")
               + " Its source names L1's design only; L2-L5 are pictured in a figure it does not hold."), "",
              f"| | design | the paper says | rank here | R ({unit}) | best ({unit}) | p |"
              f"{' ground truth: rank, reward |' if place else ''}",
              f"|---|---|---|---|---|---|---|{'---|' if place else ''}"]
    numbers = []
    for name, design, says in PAPER_DESIGNS:
        num = {"name": name, "design": None if design is None else ",".join(map(str, design))}
        if design is None:
            cells = ["not named", says, "-", "-", "-", "-"]
        else:
            d = space.canonicalize(design)
            at = next((i for i, r in enumerate(ranked, 1) if r["design"] == d), None)
            if at is None:
                why = "not in play" if d not in in_play else "never tried"
                cells = [f"`{num['design']}`", says, why, "-", "-", "-"]
                num["run"] = why
            else:
                r = ranked[at - 1]
                cells = [f"`{num['design']}`", says, f"{at} of {len(ranked)}", f"{r['latest_cm']:+.3f}",
                         f"{r['best_cm']:+.3f}", f"{r['prob']:.3g}"]
                num |= {"rank": at, "of": len(ranked), "latest": r["latest_cm"], "best": r["best_cm"], "prob": r["prob"]}
        if place:
            gt = place(design)
            num["groundtruth"] = gt
            cells.append("-" if gt is None else f"{gt['rank']} of {gt['of']}, {gt['reward']:+.2f} {gt['unit']}")
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
        numbers.append(num)
    return lines, numbers


def _groundtruth_placer(groundtruth):
    """``(place, size)`` of a ground truth of the paper's space: ``place(design) -> {"rank",
    "of", "reward", "unit"}`` (None for a design it lacks) and its number of designs in words
    (``"N designs"``, or ``"N of its M designs: unfinished"``); ``(None, "")`` without one, or
    with one of another space (a note says so)."""
    if groundtruth is None:
        return None, ""
    from softcrawl.codesign.groundtruth import load_groundtruth
    from softcrawl.codesign.groundtruth.store import folder_space
    from softcrawl.codesign.groundtruth_regret import place_design, requested_designs

    if folder_space(groundtruth) != DEFAULT_SPACE:
        note(f"the ground truth {groundtruth} is not of the paper's design space: the paper's designs are not "
             "placed in it")
        return None, ""
    cfg, res, _ = load_groundtruth(groundtruth)
    unit = cfg.task_spec().unit

    def place(design):
        if design is None or DEFAULT_SPACE.canonicalize(design) not in res:
            return None
        p = place_design(design, groundtruth, res, unit)
        return {"rank": p["rank"], "of": p["of"], "reward": p[f"reward_{unit}"], "unit": unit}

    requested = requested_designs(groundtruth, res) or len(res)
    size = f"{len(res)} designs" if requested == len(res) else f"{len(res)} of its {requested} designs: unfinished"
    return place, size
