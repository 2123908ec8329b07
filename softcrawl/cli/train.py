"""``softcrawl train``: co-design of body and gait with SAC and the Gibbs design distribution.

Examples::

    softcrawl train --preset smoke --out runs/smoke
    softcrawl train --preset demo --out runs/demo
    softcrawl train --preset paper --out runs/paper --set sac.batch_size=256 --set env.legs=[3,4]
    softcrawl train --resume --out runs/paper          # continue a killed run
    softcrawl train --preset demo --space hex6 --set env.robot.model=\"full\" --out runs/hex6

Writes the run folder described in :mod:`softcrawl.codesign.run` (:mod:`softcrawl.codesign.training`)
and, at the end, its shortlist (the run's design, :mod:`softcrawl.codesign.shortlist`) and its
report (:mod:`softcrawl.codesign.report`; :func:`train_and_report`). The ``paper`` preset runs its
envs on the JAX backend when JAX sees a GPU (:func:`paper_backend`; one line says so), unless a
backend is given. Ctrl-C
stops the run; ``--resume`` continues it from its last checkpoint. The run is locked while it
trains (a second ``train`` or ``report`` on it is refused, naming the holder). An option and a
``--set`` of the same setting (``--task`` and ``--set env.task=...``) are refused, as is a
setting ``--set`` twice.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from softcrawl.cli import bounded
from softcrawl.codesign.config import BACKENDS, PLACEMENT_KEYS, PRESETS, TRAIN_BOUNDS, TrainConfig, override, preset
from softcrawl.robot.output import check_output_path
from softcrawl.tasks.registry import task_spec


def train_and_report(out: str | os.PathLike, cfg: TrainConfig | None = None, resume: bool = False,
                     progress: bool = True, report: bool = True, ray_address: str | None = None,
                     placement: list[str] | None = None):
    """What ``softcrawl train`` does: :func:`softcrawl.codesign.training.train` (arguments as
    there), then, with ``report``, :func:`softcrawl.codesign.report.write_report` of the run,
    which makes its shortlist (:mod:`softcrawl.codesign.shortlist`: the run's design; kept if the
    run has one of its last checkpoint), else the shortlist alone
    (:func:`~softcrawl.codesign.shortlist.make_shortlist`). Returns the :class:`TrainResult`.

    Raises:
        NoSpaceError: the disk filled up (or turned read-only) while training: the message
            names the run's last complete checkpoint (and a rescued one, if any) and how to
            continue.
        ValueError: as :func:`~softcrawl.codesign.training.train`; or the shortlist or the
            report failed after a finished training (the message says so and how to write them
            later).
    """
    from softcrawl.codesign.report import write_report
    from softcrawl.codesign.run import NoSpaceError, Run, is_no_space
    from softcrawl.codesign.training import train  # heavy: torch or JAX, stable-baselines3

    run = Run(out)
    try:
        res = train(out, cfg, resume=resume, progress=progress, ray_address=ray_address, placement=placement)
    except (NoSpaceError, OSError) as exc:
        if not isinstance(exc, NoSpaceError) and not is_no_space(exc):
            raise
        try:
            ck = run.latest_checkpoint(quiet=True)
        except (OSError, ValueError):
            ck = None
        what = str(exc) if isinstance(exc, NoSpaceError) else f"training stopped: {exc.strerror} writing {run.path}"
        kept = f"the run keeps its checkpoint {ck.name}" if ck is not None else "the run has no complete checkpoint"
        raise NoSpaceError(f"{what}; {kept}; free some space, then continue with: softcrawl train --resume "
                           f"--out {run.path}") from None
    from softcrawl.codesign.shortlist import make_shortlist

    # the report makes the shortlist (and re-simulates its choice from the shortlist's evaluation)
    what, step = (("report", lambda: write_report(res.run_dir)) if report else
                  ("shortlist", lambda: make_shortlist(res.run_dir, progress=progress)))
    try:
        step()
    except (ValueError, OSError) as exc:
        msg = " ".join(str(exc).split()) or type(exc).__name__
        raise ValueError(f"training finished ({res.steps} steps, run in {res.run_dir}) but the {what} failed: "
                         f"{msg}; write it later with: softcrawl report {res.run_dir}") from None
    return res


def paper_backend(cfg: TrainConfig, learner_device: bool = True) -> TrainConfig:
    """``cfg`` (the ``paper`` preset, no backend given) on the JAX backend when JAX sees a GPU
    and its settings run there, with its learner there too when ``learner_device`` (no
    ``sac.device`` given: the preset makes 1M updates, many times faster there; figures in
    benchmarks/RESULTS.md), said in one line on stderr; else ``cfg`` as it is (with a line
    saying why when a GPU is seen but the settings cannot run on JAX, e.g. the ``turning`` task).
    The learner's threads are set first (:func:`softcrawl.codesign.sac.prepare_learner`: JAX
    reads them once, when it starts).

    Raises:
        ValueError: as :func:`~softcrawl.codesign.sac.prepare_learner` (a ``sac.device`` the
            learner cannot use).
    """
    from softcrawl.codesign.sac import prepare_learner

    prepare_learner(cfg.sac)
    import jax

    try:
        gpus = [d for d in jax.devices() if d.platform == "gpu"]
    except RuntimeError:  # no backend JAX can start
        gpus = []
    if not gpus:
        return cfg
    try:
        on_jax = override(cfg, ['backend="jax"', *(['sac.device="gpu"'] if learner_device else [])])
    except ValueError as exc:
        print(f"softcrawl train: JAX sees a GPU, but these settings do not run on the JAX backend ({exc}); keeping "
              f"backend {cfg.backend!r}", file=sys.stderr)
        return cfg
    print(f"softcrawl train: JAX sees {len(gpus)} GPU(s) ({gpus[0].device_kind}): the paper preset runs its "
          f"{cfg.n_envs} envs on the JAX backend there{' and learns there' if learner_device else ''} (--backend "
          f"chooses another backend, --set sac.device=... another learner device)", file=sys.stderr)
    return on_jax


def _check_out(out: str) -> None:
    """``--out`` of a new run: a new folder that can be created, or an empty writable one (a
    lock file left by a killed command aside, :meth:`~softcrawl.codesign.run.Run.is_new`)."""
    from softcrawl.codesign.run import Run

    p = Path(out)
    if p.exists() or p.is_symlink():
        if not p.is_dir() or p.is_symlink():
            raise ValueError(f"{p} exists and is not a directory")
        if not Run(p).is_new():
            raise ValueError(f"run directory {p} exists and is not empty (use --resume or another --out)")
        if not os.access(p, os.W_OK | os.X_OK):
            raise ValueError(f"run directory {p} is not writable")
        return
    check_output_path(p)


def check_ray_address(backend: str, address: str | None) -> None:
    """A Ray cluster named by ``--ray-address`` must answer before any work starts
    (:func:`softcrawl.parallel.check_address`; ConnectionError if not)."""
    if backend == "ray" and address:
        from softcrawl.parallel import check_address, connect_timeout

        check_address(address, connect_timeout())


#: The options of ``train`` that set a config setting (``--set`` key: option).
OPTION_KEYS = {"total_steps": "--total-steps", "n_envs": "--n-envs", "backend": "--backend", "n_workers": "--workers",
               "seed": "--seed", "env.task": "--task", "env.space": "--space"}


def _check_conflicts(args: argparse.Namespace) -> None:
    """Refuse an option given together with a ``--set`` of its setting (one line naming both)."""
    sets = {a.split("=", 1)[0].strip(): a for a in args.set or []}
    for key, flag in OPTION_KEYS.items():
        if getattr(args, flag[2:].replace("-", "_")) is not None and key in sets:
            raise ValueError(f"{flag} and --set {sets[key]!r} both set {key}; give one")


def _run(args: argparse.Namespace) -> int:
    _check_conflicts(args)
    if args.resume:
        if any(v is not None for v in (args.total_steps, args.n_envs, args.backend, args.seed, args.preset,
                                       args.space, args.task)):
            raise ValueError("--resume uses the run's saved config.json; drop --preset and the other settings "
                             f"(only where it runs may change: --workers, --set {'|'.join(PLACEMENT_KEYS)})")
        placement = list(args.set or []) + ([f"n_workers={args.workers}"] if args.workers is not None else [])
        check_ray_address("ray", args.ray_address)
        res = train_and_report(args.out, resume=True, progress=not args.no_progress, ray_address=args.ray_address,
                               placement=placement)
    else:
        sets = list(args.set or [])
        for flag, key in ((args.total_steps, "total_steps"), (args.n_envs, "n_envs"), (args.backend, "backend"),
                          (args.workers, "n_workers"), (args.seed, "seed")):
            if flag is not None:
                sets.append(f"{key}={flag}" if key != "backend" else f'{key}="{flag}"')
        if args.task is not None:
            sets.append(f"env.task={json.dumps(task_spec(args.task, '--task'))}")
        if args.space is not None:
            sets.append(f"env.space={json.dumps(args.space)}")
        cfg = override(preset(args.preset or "demo"), sets)
        given = {a.split("=", 1)[0].strip() for a in sets}
        if args.preset == "paper" and "backend" not in given:
            cfg = paper_backend(cfg, learner_device="sac.device" not in given)
        _check_out(args.out)
        check_ray_address(cfg.backend, args.ray_address)
        res = train_and_report(args.out, cfg, progress=not args.no_progress, ray_address=args.ray_address)
    print(f"trained {res.steps} steps ({res.updates} SAC updates) in {res.wall_seconds:.1f} s; run in {res.run_dir}")
    from softcrawl.codesign.run import Run

    report = Run(res.run_dir).report_dir / "summary.md"
    if report.exists():
        print(report.read_text(encoding="utf-8"))
        print(f"report: {report}")
    return 0


def register(subparsers) -> None:
    """Add the ``train`` subcommand to ``subparsers``."""
    p = subparsers.add_parser(
        "train", help="co-design: train SAC and the design distribution",
        description="Train the design-conditioned open-loop policy (SAC) and the Gibbs design distribution "
        "(codesign.md). Presets: paper (96 envs, 1M steps), reference (paper with the authors' update "
        "schedule), crawl (28-70 min on 2 cores), demo (8-22 min on 2 cores with its report), smoke (CI, < 1 min).",
    )
    p.add_argument("--preset", choices=PRESETS, default=None, help="settings to start from (default demo)")
    p.add_argument("--out", required=True, help="run directory (new, or the run to --resume)")
    p.add_argument("--resume", action="store_true",
                   help="continue the run in --out from its last checkpoint, with its saved settings; only where "
                        "it runs may change: --workers, --set sac.device=...")
    p.add_argument("--total-steps", type=int, default=None, **bounded(*TRAIN_BOUNDS["total_steps"]),
                   help="environment transitions in total")
    p.add_argument("--n-envs", type=int, default=None, **bounded(*TRAIN_BOUNDS["n_envs"]), help="parallel environments")
    p.add_argument("--backend", choices=BACKENDS, default=None,
                   help="where envs run (default: the preset's; the paper preset's is jax when JAX sees a GPU, "
                   "else subprocess)")
    p.add_argument("--workers", type=int, default=None, **bounded(*TRAIN_BOUNDS["n_workers"]),
                   help="worker processes of the subprocess backend (0: cores)")
    p.add_argument("--seed", type=int, default=None, **bounded(*TRAIN_BOUNDS["seed"]))
    p.add_argument("--space", default=None, metavar="NAME|PATH",
                   help="design space: a shipped one (paper, the default; hex6) or a space file (TOML); "
                        "the run keeps a copy as space.toml")
    p.add_argument("--task", default=None, metavar="NAME|TABLE",
                   help="what the episodes reward (docs/tasks.md): forward (the default, the paper's), heading, "
                   "turning, target or incline, or a JSON table of its settings, e.g. "
                   "'{\"name\": \"heading\", \"heading_deg\": 90}'")
    p.add_argument("--ray-address", default=None,
                   help='Ray cluster of --backend ray / --set backend="ray" (default: start a local Ray)')
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override any setting, e.g. sac.batch_size=256, env.legs=[3], design.untried=\"zero\"")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)


def main(argv: list[str] | None = None) -> int:
    """Standalone entry (``python -m softcrawl.cli.train``), for use before the subcommand is registered."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    parser = argparse.ArgumentParser(prog="softcrawl")
    sub = parser.add_subparsers(dest="command", required=True)
    register(sub)
    args = parser.parse_args(["train", *(sys.argv[1:] if argv is None else argv)])
    from softcrawl.cli import run_command

    return run_command(args)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
