"""Co-design algorithms against the ground truth (issue 21): best-found ground-truth reward vs
simulated seconds, over seeds, with spread.

    python benchmarks/codesign_algorithms.py --groundtruth GT --seeds 3 --budget-seconds 20000 \\
        --algorithms random,tpe,ga [--runs RUN ...] --out DIR

The design space is the ground truth's design set; episodes use its simulation settings (the
reduced model; ``--duration`` shortens them for CI-scale runs). ``--runs`` adds Gibbs-SAC of the
paper post hoc: each training run's ``episodes.csv`` replayed (one run per seed). Prints JSON
(per algorithm: the incumbent's ground-truth reward at the end, mean/min/max over seeds;
the first simulated second at which the best ground-truth design was the incumbent; an incumbent
chosen by short-episode returns can move away from it again) and writes
``DIR/codesign_algorithms.json`` and ``DIR/codesign_algorithms.png``.

    python benchmarks/codesign_algorithms.py --groundtruth GT --merge DIR1 DIR2 ... --out DIR

merges results computed separately (e.g. one algorithm per process) into one JSON and plot.

Resumable: each finished (algorithm, seed) run is kept as ``DIR/traces/<algorithm>-<seed>.json``
(its incumbents per simulated second and its settings) and not recomputed when the command is
run again with the same settings (other settings: an error). The incumbents are graded against
the ground truth when the summary is written, so ``--designs 3`` lets the algorithms run while
the ground truth of those designs is still being computed: run the command again once it is
complete to grade them all.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

from softcrawl.codesign.algorithms import (  # noqa: E402
    ALGORITHMS,
    GibbsSACReplay,
    SimEvaluator,
    best_so_far_on_grid,
    make_algorithm,
    run_algorithm,
)
from softcrawl.codesign.groundtruth import load_groundtruth, parse_designs  # noqa: E402


def compare(gt: str | Path, algorithms, seeds: int, budget_seconds: float, runs=(), duration=None,
            evals_per_design: int = 24, cycles=(3, 4), evaluate=None, progress: bool = True,
            designs: str | None = None, out: str | Path | None = None) -> dict:
    """Run each algorithm ``seeds`` times (and replay ``runs``); returns the traces and a summary.

    ``evaluate``: ``(design, gait, duration) -> cm`` (default: the reduced model with the ground
    truth's settings, :class:`SimEvaluator`). ``designs``: the design set searched, as
    ``softcrawl groundtruth --designs`` reads it (default: the ground truth's finished designs).
    ``out``: keep each finished run in ``out/traces`` and reuse it (module doc).

    Raises:
        ValueError: an unknown algorithm, or a kept run with other settings.
    """
    cfg, res, _ = load_groundtruth(gt)
    gt_cm = {d: r.reward_cm for d, r in res.items()}
    space = sorted(set(parse_designs(designs))) if designs else sorted(res)
    settings = {"groundtruth_config": cfg.to_dict(), "designs": [list(d) for d in space],
                "budget_seconds": budget_seconds, "duration": duration, "evals_per_design": evals_per_design,
                "cycles": list(cycles)}
    kept = Path(out) / "traces" if out is not None else None
    traces: dict[str, list] = {}
    for name in algorithms:
        if name not in ALGORITHMS:
            raise ValueError(f"unknown algorithm {name!r} (choose from {ALGORITHMS})")
        for seed in range(seeds):
            path = kept / f"{name}-{seed}.json" if kept is not None else None
            if path is not None and path.exists():
                saved = json.loads(path.read_text())
                if saved.get("settings") != settings:
                    raise ValueError(f"{path} was computed with other settings; use another --out")
                traces.setdefault(name, []).append(saved["trace"])
                continue
            t0 = time.perf_counter()
            ev = evaluate or SimEvaluator(cfg)
            algo = make_algorithm(name, space, cfg, seed, evals_per_design, cycles, duration)
            tr = run_algorithm(algo, ev, gt_cm, budget_seconds)
            tr["seed"], tr["wall_seconds"] = seed, time.perf_counter() - t0
            traces.setdefault(name, []).append(tr)
            if path is not None:
                path.parent.mkdir(parents=True, exist_ok=True)
                tmp = path.with_suffix(".tmp")
                tmp.write_text(json.dumps(_no_nan({"settings": settings, "trace": tr})) + "\n")
                os.replace(tmp, path)
            if progress:
                print(f"{name} seed {seed}: {tr['episodes']} episodes, final incumbent "
                      f"{tr['incumbent'][-1]} ({tr['wall_seconds']:.0f} s)", file=sys.stderr)
    for i, run in enumerate(runs):
        algo = GibbsSACReplay(run, space)
        tr = run_algorithm(algo, None, gt_cm, budget_seconds)
        tr["seed"], tr["run"] = i, str(run)
        traces.setdefault("gibbs-sac", []).append(tr)
    return summarize(str(gt), len(space), budget_seconds, traces, gt_cm)


def summarize(gt: str, n_designs: int, budget_seconds: float, traces: dict, gt_cm: dict) -> dict:
    """The result of :func:`compare` from its traces (``algorithm -> [trace per seed]``), each
    incumbent graded (again) with ``gt_cm`` (ground-truth reward per design, cm; NaN where
    unknown): a run kept from before the ground truth was complete gets its missing grades."""
    best_cm = max(gt_cm.values())
    for trs in traces.values():
        for t in trs:
            t["gt_cm"] = [float(gt_cm.get(tuple(inc), np.nan)) if inc else np.nan for inc in t["incumbent"]]
    summary = {}
    for name, trs in traces.items():
        final = np.array([t["gt_cm"][-1] if t["gt_cm"] else np.nan for t in trs], float)
        known = final[np.isfinite(final)]  # incumbents not (yet) in the ground truth are left out
        reach = []
        for t in trs:
            hit = [s for s, g in zip(t["sim_seconds"], t["gt_cm"]) if g == best_cm]
            reach.append(hit[0] if hit else None)
        mean = float(known.mean()) if len(known) else None
        summary[name] = {"seeds": len(trs), "graded_seeds": len(known), "final_gt_cm_mean": mean,
                         "final_gt_cm_min": float(known.min()) if len(known) else None,
                         "final_gt_cm_max": float(known.max()) if len(known) else None,
                         "final_regret_cm_mean": best_cm - mean if len(known) else None,
                         "sim_seconds": [t["sim_seconds"][-1] if t["sim_seconds"] else 0.0 for t in trs],
                         "first_sim_seconds_best_design_chosen": reach}
    return {"groundtruth": gt, "designs": n_designs, "groundtruth_designs": len(gt_cm), "best_gt_cm": best_cm,
            "budget_seconds": budget_seconds, "summary": summary, "traces": traces}


def merge(gt: str | Path, paths) -> dict:
    """One result from several ``codesign_algorithms.json`` (e.g. one algorithm per process),
    graded with the ground truth ``gt``."""
    parts = [json.loads((Path(p) / "codesign_algorithms.json").read_text()) for p in paths]
    traces: dict = {}
    for part in parts:
        if part["designs"] != parts[0]["designs"]:
            raise ValueError("results over different design sets cannot be merged")
        for name, trs in part["traces"].items():
            traces.setdefault(name, []).extend(trs)
    _, res, _ = load_groundtruth(gt)
    return summarize(str(gt), parts[0]["designs"], max(p["budget_seconds"] for p in parts), traces,
                     {d: r.reward_cm for d, r in res.items()})


def _no_nan(x):
    """JSON-safe copy: NaN -> None."""
    if isinstance(x, float):
        return None if x != x else x
    if isinstance(x, dict):
        return {k: _no_nan(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_no_nan(v) for v in x]
    return x


def plot(result: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    t_max = max(max(t["sim_seconds"][-1] for t in trs if t["sim_seconds"]) for trs in result["traces"].values())
    grid = np.linspace(0, t_max, 400)
    for i, (name, trs) in enumerate(result["traces"].items()):
        ys = np.array([best_so_far_on_grid(t, grid) for t in trs])
        with np.errstate(all="ignore"):
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                mean, lo, hi = np.nanmean(ys, 0), np.nanmin(ys, 0), np.nanmax(ys, 0)
        ax.plot(grid, mean, color=f"C{i}", label=f"{name} (mean of {len(trs)}, band min-max)")
        ax.fill_between(grid, lo, hi, color=f"C{i}", alpha=0.12, lw=0)
    ax.axhline(result["best_gt_cm"], color="k", ls="--", lw=1, label="best design (ground truth)")
    ax.set_xlabel("simulated seconds")
    ax.set_ylabel("ground-truth reward of the incumbent (cm)")
    ax.set_title(f"Co-design algorithms on {result['designs']} designs")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--groundtruth", required=True)
    p.add_argument("--algorithms", default="random,tpe,ga")
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--budget-seconds", type=float, default=20_000.0, help="simulated seconds per algorithm run")
    p.add_argument("--runs", nargs="*", default=[], help="Gibbs-SAC training runs to replay (one per seed)")
    p.add_argument("--duration", type=float, default=None, help="episode s (default: the ground truth's)")
    p.add_argument("--evals-per-design", type=int, default=24, help="random search: CMA-ES episodes per design")
    p.add_argument("--cycles", default="3,4")
    p.add_argument("--designs", default=None,
                   help='design set searched, e.g. "3" (default: the ground truth\'s finished designs)')
    p.add_argument("--out", default="codesign_algorithms")
    p.add_argument("--merge", nargs="+", metavar="DIR", help="merge earlier results (their --out folders) instead")
    a = p.parse_args(argv)
    if a.merge:
        res = merge(a.groundtruth, a.merge)
        out = Path(a.out)
        out.mkdir(parents=True, exist_ok=True)
        plot(res, out / "codesign_algorithms.png")
        (out / "codesign_algorithms.json").write_text(json.dumps(_no_nan(res), indent=1) + "\n")
        print(json.dumps({k: v for k, v in _no_nan(res).items() if k != "traces"}, indent=2))
        return 0
    try:
        if a.seeds < 1 or a.budget_seconds <= 0:
            raise ValueError("--seeds must be >= 1 and --budget-seconds > 0")
        algos = [s for s in a.algorithms.split(",") if s]
        res = compare(a.groundtruth, algos, a.seeds, a.budget_seconds, a.runs, a.duration, a.evals_per_design,
                      tuple(int(c) for c in a.cycles.split(",")), designs=a.designs, out=a.out)
    except ValueError as exc:
        print(f"codesign_algorithms: error: {exc}", file=sys.stderr)
        return 2
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    plot(res, out / "codesign_algorithms.png")
    res = _no_nan(res)
    (out / "codesign_algorithms.json").write_text(json.dumps(res, indent=1) + "\n")
    print(json.dumps({k: v for k, v in res.items() if k != "traces"}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
