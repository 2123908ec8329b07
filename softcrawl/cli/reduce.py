"""``softcrawl reduce build|validate``: build a crawler reduction (the leg; optionally the disk),
and check it against the full model.

Examples::

    softcrawl reduce build --out pneunet_6mm.npz --workdir runs/reduce
    softcrawl reduce validate --workdir runs/reduce --out runs/reduce/validation
    softcrawl reduce validate --grid --workdir runs/reduce --out runs/reduce/grid
    softcrawl reduce build --space hex6 --out pneunet6_6mm.npz --workdir runs/reduce/hex6
    softcrawl reduce validate --space hex6 --reduction pneunet6_6mm.npz --workdir runs/reduce/hex6

``--space`` (a shipped space's name or a space file; default the paper's) picks the scenes'
slots and leg counts and the parts reduced (reduction.md, "Reducing your own part");
``validate`` then checks the space's own reduction (``[actuator] reduction``, its SHA-256 and
part) unless ``--reduction`` names another. Full-order runs live in ``--workdir`` (default
``runs/reduce``, ``runs/reduce/<space name>`` for another space) and are reused after an
interruption or by a later command with the same settings.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

from softcrawl.cli import MAX_WORKERS, bounded
from softcrawl.codesign.config import SIM_BOUNDS, TRAIN_BOUNDS
from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.design.resolve import resolve_space
from softcrawl.design.spacefile import DesignSpace
from softcrawl.fem.solver import RID_DTYPES
from softcrawl.reduction.artifact import file_sha256, load_reduction, save_reduction
from softcrawl.reduction.build import BuildSettings, build_reduction, build_reductions
from softcrawl.reduction.model import PartReduction
from softcrawl.reduction.validate import ENGINES, validate_reduction
from softcrawl.robot.assembly import REDUCED_DISKS, RobotConfig
from softcrawl.robot.output import jsonable

#: The 3 x 3 grid of the paper's appendix around its chosen (tol_modes, tol_gie).
GRID_TOL_MODES = (0.01, 0.0032, 0.001)
GRID_TOL_GIE = (0.01, 0.003, 0.001)
#: Most full-order training scenes of each kind (``--designs``, ``--gait-designs``: minutes each)
#: and perturbed runs per validation scene (``--ensemble``).
MAX_SCENES, MAX_ENSEMBLE = 1000, 100
#: A tolerance (``--tol-modes``, ``--tol-gie``, ``--disk-tol-modes``): a fraction in (0, 1].
TOLERANCE = bounded(0.0, 1.0, open_low=True)


def _settings(args: argparse.Namespace, **kw) -> BuildSettings:
    return BuildSettings(n_designs=args.designs, gait_designs=args.gait_designs, rigid=args.rigid_modes,
                         disk=args.reduce_disk, disk_tol_modes=args.disk_tol_modes, **kw)


def _describe(name: str, part: PartReduction) -> str:
    rid = part.metadata["rid"]
    text = (f"{name}: {part.n_modes} modes ({part.n_rigid} rigid), "
            f"RID {rid['tetrahedra'][0]} of {rid['tetrahedra'][1]} tetrahedra")
    if "triangles" in rid:
        text += f" and {rid['triangles'][0]} of {rid['triangles'][1]} paper triangles"
    return text


def _space(args: argparse.Namespace) -> DesignSpace:
    return resolve_space(args.space) if args.space else DEFAULT_SPACE


def _config(args: argparse.Namespace, space: DesignSpace) -> RobotConfig:
    """The space's robot settings (:meth:`RobotConfig.for_space`; the paper's: ``RobotConfig()``)
    with ``--mesh-size`` and ``--reduced-disk``."""
    mesh = {} if args.mesh_size is None else {"leg_mesh_size": args.mesh_size}
    return RobotConfig.for_space(space, reduced_disk=args.reduced_disk, **mesh)


def _workdir(args: argparse.Namespace, space: DesignSpace) -> Path:
    if args.workdir is not None:
        return Path(args.workdir)
    return Path("runs/reduce") if space == DEFAULT_SPACE else Path("runs/reduce") / space.name


def _build(args: argparse.Namespace) -> int:
    space = _space(args)
    config = _config(args, space)
    settings = _settings(args, tol_modes=args.tol_modes, tol_gie=args.tol_gie)
    reduction = build_reduction(_workdir(args, space), config, settings, args.workers, not args.no_progress, space)
    out = save_reduction(args.out, reduction, dataclasses.asdict(config))
    meta = reduction.metadata
    parts = "; ".join(_describe(name, part) for name, part in reduction.parts.items())
    print(f"wrote {out}: {parts}; {meta['wall_seconds']['total']:.0f} s, peak memory "
          f"{meta['peak_rss_mb']['with_workers']} MB with its workers (main process {meta['peak_rss_mb']['main']} MB)")
    print(f"for a space file's [actuator]: reduction = (the path of {out} relative to the space file), "
          f"reduction_sha256 = \"{file_sha256(out)}\"")
    return 0


def _markdown(report: dict) -> str:
    floor = "floor_mean_node_error_mm" in report["scenes"][0]
    head = ["scene", "mean node error (mm)", "max (mm)", "deformation error (mm)", "trajectory error (mm)"]
    head += ["chaos floor: node / deformation (mm)"] if floor else []
    head += ["reward full (cm)"] + (["full ensemble (cm)"] if floor else []) + ["reward reduced (cm)"]
    head += ["reduced ensemble (cm)", "reduced spread (mm)"] if floor else []
    head += ["s/step full", "s/step reduced"]
    lines = [f"Reduced runs on the {report['engine']} engine.", ""] if "engine" in report else []
    lines += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in report["scenes"]:
        cells = [r["scene"], f"{r['mean_node_error_mm']:.3f}", f"{r['max_node_error_mm']:.2f}",
                 f"{r['mean_deformation_error_mm']:.3f}", f"{r['mean_trajectory_error_mm']:.3f}"]
        if floor:
            cells.append(f"{r['floor_mean_node_error_mm']:.3f} / {r['floor_mean_deformation_error_mm']:.3f}")
        cells.append(f"{r['reward_full_cm']:+.3f}")
        if floor:
            rewards = r["ensemble_rewards_cm"]
            cells.append(f"{min(rewards):+.3f} .. {max(rewards):+.3f}")
        cells.append(f"{r['reward_reduced_cm']:+.3f}" + (" (inside)" if r.get("reward_in_ensemble") else ""))
        if floor:
            rewards = r["reduced_ensemble_rewards_cm"]
            cells += [f"{min(rewards):+.3f} .. {max(rewards):+.3f}", f"{r['reduced_spread_mm']:.3f}"]
        cells += [f"{r['seconds_per_step_full']:.4f}", f"{r['seconds_per_step_reduced']:.5f}"]
        lines.append("| " + " | ".join(cells) + " |")
    if floor:
        lines.append("")
        lines.append(f"Chaos floor: the mean distance of {report.get('ensemble', '')} exact full-order runs whose rest "
                     f"nodes were perturbed by {report.get('perturbation_mm', 0):g} mm to the unperturbed reference; "
                     "full ensemble: the rewards of the reference and those runs; reduced ensemble and spread: "
                     "the rewards of the reduced run and as many perturbed ones (noise projected on each leg's "
                     "basis), and the mean node distance of those to the unperturbed reduced run.")
    return "\n".join(lines) + "\n"


def _plot_grid(path: Path, rows: list[dict]) -> None:
    """Error against reduced step time per (tol_modes, tol_gie), like the paper's appendix
    figure: left the paper's node error, right the deformation error (bodies rigidly fitted)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4.2))
    FigureCanvasAgg(fig)
    axes = fig.subplots(1, 2)
    for ax, key, label in zip(axes, ("mean_node_error_mm", "mean_deformation_error_mm"),
                              ("mean node error vs full model, mm", "mean deformation error vs full model, mm")):
        for tm in sorted({r["tol_modes"] for r in rows}):
            pts = sorted((r["mean_seconds_per_step_reduced"] * 1e3, r[key], r["tol_gie"])
                         for r in rows if r["tol_modes"] == tm)
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"tol_modes {tm:g}")
            for x, y, g in pts:
                ax.annotate(f"{g:g}", (x, y), fontsize=7, textcoords="offset points", xytext=(3, 3))
        ax.set_xlabel("reduced step, ms (labels: tol_gie)")
        ax.set_ylabel(label)
        ax.set_yscale("log")
        ax.legend()
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def _validate(args: argparse.Namespace) -> int:
    space = _space(args)
    config = _config(args, space)
    workdir = _workdir(args, space)
    progress = not args.no_progress
    if args.grid and args.engine != "cpu":
        raise ValueError("--grid runs the CPU engine only")
    path = args.reduction or space.reduction
    if not args.grid and path is None:
        raise ValueError(f"the design space {space.name!r} names no reduction ([actuator] reduction): give --reduction")
    out = Path(args.out)
    if args.grid:
        out.mkdir(parents=True, exist_ok=True)
        rows = []
        for tm in GRID_TOL_MODES:
            settings = _settings(args, tol_modes=tm)
            for reduction in build_reductions(workdir, config, settings, GRID_TOL_GIE, args.workers, progress, space):
                rep = validate_reduction(reduction, config, workdir, workers=args.workers, progress=progress,
                                         ensemble=0, space=space)
                rep.update(tol_modes=tm, tol_gie=reduction.metadata["settings"]["tol_gie"])
                rows.append(rep)
                print(f"tol_modes {tm:g} tol_gie {rep['tol_gie']:g}: {rep['n_modes']} modes, RID "
                      f"{rep['rid_tetrahedra']}+{rep['rid_triangles']}, error {rep['mean_node_error_mm']:.3f} mm "
                      f"(deformation {rep['mean_deformation_error_mm']:.3f} mm), "
                      f"{rep['mean_seconds_per_step_reduced'] * 1e3:.2f} ms/step", flush=True)
        (out / "grid.json").write_text(json.dumps(jsonable(rows), indent=1) + "\n", encoding="utf-8")
        _plot_grid(out / "error_vs_time.png", rows)
        print(f"wrote {out / 'grid.json'} and {out / 'error_vs_time.png'}")
        return 0
    reduction, _ = load_reduction(path, expect=dataclasses.asdict(config),
                                  part=space.part_record(config.leg_mesh_size, config.disk_mesh_size),
                                  sha256=space.reduction_sha256 if str(path) == space.reduction else None)
    out.mkdir(parents=True, exist_ok=True)
    ensemble = args.ensemble if args.ensemble is not None else (3 if args.engine == "cpu" else 0)
    if args.engine == "jax":
        try:
            import jax
        except ImportError:
            raise ValueError("--engine jax needs JAX (pip install 'softcrawl[jax]')") from None
        jax.config.update("jax_enable_x64", args.rid_dtype == "float64")
    rep = validate_reduction(reduction, config, workdir, workers=args.workers, progress=progress,
                             ensemble=ensemble, perturbation=args.perturbation, reduced_dt=args.dt,
                             rid_dtype=args.rid_dtype, contact_max_iterations=args.contact_max_iterations,
                             leg_collision_spacing=args.leg_collision_spacing, engine=args.engine, space=space)
    rep["reduction"] = str(path)
    rep["space"] = space.name
    (out / "validation.json").write_text(json.dumps(jsonable(rep), indent=1) + "\n", encoding="utf-8")
    (out / "validation.md").write_text(_markdown(rep), encoding="utf-8")
    print(_markdown(rep))
    solve = (f"RID products in {rep['rid_dtype']}, {rep['contact_max_iterations']} Gauss-Seidel sweeps per chunk"
             if rep["engine"] == "cpu" else f"all in {rep['rid_dtype']}, the JAX engine's contact solve")
    print(f"engine {rep['engine']}: reduced dt {rep['reduced_dt']:g} s, {solve}, leg contact points "
          f"{rep['leg_collision_spacing']:g} mm apart (0: every surface node): "
          f"mean node error {rep['mean_node_error_mm']:.3f} mm "
          f"(deformation {rep['mean_deformation_error_mm']:.3f} mm); "
          f"reduced step {rep['speedup']:.0f}x faster; "
          f"wrote {out}")
    return 0


def register(subparsers) -> None:
    """Add ``reduce build`` and ``reduce validate``."""
    p = subparsers.add_parser("reduce", help="build and validate the leg (and disk) reduction (POD + ECSW)")
    sub = p.add_subparsers(dest="reduce_command", required=True)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--space", default=None, metavar="NAME|FILE",
                        help="design space: a shipped one's name (paper, hex6) or a space file (default: the "
                             "paper's); its slots, leg counts and parts make the scenes")
    common.add_argument("--workdir", default=None,
                        help="full-order runs, reused (default runs/reduce; runs/reduce/<space name> for a space "
                             "other than the paper's)")
    common.add_argument("--mesh-size", type=float, default=None, **bounded(*SIM_BOUNDS["leg_mesh_size"]),
                        help="leg mesh size, mm (default: the space's, 6 for the paper's)")
    common.add_argument("--designs", type=int, default=BuildSettings.n_designs, **bounded(1, MAX_SCENES),
                        help="training designs")
    common.add_argument("--gait-designs", type=int, default=BuildSettings.gait_designs, **bounded(0, MAX_SCENES),
                        help=f"crawling training scenes (sine gaits) besides the Gray-code walks (default "
                             f"{BuildSettings.gait_designs}; 0: the paper's training set)")
    common.add_argument("--rigid-modes", choices=("translations", "rigid"), default=BuildSettings.rigid,
                        help="rigid modes of the leg basis")
    common.add_argument("--reduce-disk", action="store_true",
                        help="reduce the disk too by POD + ECSW (default: no disk part, the disk is then set by "
                             "--reduced-disk; see BuildSettings.disk for why)")
    common.add_argument("--disk-tol-modes", type=float, default=BuildSettings.disk_tol_modes, **TOLERANCE,
                        help="POD tail-energy tolerance of the disk (after its 6 rigid modes)")
    common.add_argument("--reduced-disk", choices=REDUCED_DISKS, default=RobotConfig.reduced_disk,
                        help="the reduced robot's disk when the reduction has no disk part "
                             "(see RobotConfig.reduced_disk)")
    common.add_argument("--workers", type=int, default=None, **bounded(1, MAX_WORKERS),
                        help="processes (default: CPU count)")
    common.add_argument("--no-progress", action="store_true")
    b = sub.add_parser("build", parents=[common], help="snapshots -> POD -> Galerkin runs -> ECSW; writes --out")
    b.add_argument("--out", required=True, help="reduction file to write (.npz)")
    b.add_argument("--tol-modes", type=float, default=BuildSettings.tol_modes, **TOLERANCE,
                   help="POD tail-energy tolerance")
    b.add_argument("--tol-gie", type=float, default=BuildSettings.tol_gie, **TOLERANCE,
                   help="ECSW relative residual tolerance")
    b.set_defaults(func=_build)
    v = sub.add_parser("validate", parents=[common], help="compare with the full model on 4 held-out scenes")
    v.add_argument("--reduction", default=None,
                   help="reduction file (default: the space's [actuator] reduction; the shipped one for the paper's)")
    v.add_argument("--out", default="runs/reduce/validation", help="report directory")
    v.add_argument("--grid", action="store_true", help="3 x 3 grid over (tol_modes, tol_gie) with a plot")
    v.add_argument("--ensemble", type=int, default=None, **bounded(0, MAX_ENSEMBLE),
                   help="perturbed exact full-order runs per scene (the chaos floor and reward spread) and as "
                        "many perturbed reduced runs (the reduced model's own spread); 0: none (default 3 with "
                        "--engine cpu, 0 with jax, which has none)")
    v.add_argument("--perturbation", type=float, default=1e-6, **bounded(0.0, 1.0, "mm", open_low=True),
                   help="initial node noise of those runs, mm (default 1e-6)")
    v.add_argument("--dt", type=float, default=None, **bounded(*SIM_BOUNDS["dt"]),
                   help="the reduced model's time step, s (default: the reference 0.01; must divide or be a "
                        "multiple of the 0.02 s frame spacing); the full-order references stay exact at 0.01 s")
    v.add_argument("--rid-dtype", choices=RID_DTYPES, default="float64",
                   help="precision of the reduced model's RID element products (default float64); with "
                        "--engine jax, of the whole JAX engine")
    v.add_argument("--engine", choices=ENGINES, default="cpu",
                   help="the reduced runs' engine: cpu (the reduced solver) or jax (softcrawl.jaxsim: its "
                        "contact settings, --contact-max-iterations unused; wall times include compiling)")
    v.add_argument("--contact-max-iterations", type=int, default=RobotConfig.contact_max_iterations,
                   **bounded(*TRAIN_BOUNDS["env.robot.contact_max_iterations"]),
                   help="the reduced model's Gauss-Seidel sweep limit per chunk (default: the reference 250)")
    v.add_argument("--leg-collision-spacing", type=float, default=0.0,
                   **bounded(*TRAIN_BOUNDS["env.robot.leg_collision_spacing"]),
                   help="the reduced model's leg contact points, mm apart (default 0: every surface node, "
                        "the reference; see RobotConfig.leg_collision_spacing)")
    v.set_defaults(func=_validate)
