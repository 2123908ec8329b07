"""A ground-truth run (:func:`run_groundtruth`, ``softcrawl groundtruth``): the designs of a set
computed in a process pool (workers pinned to one BLAS thread), in-process, as Ray tasks
(``executor="ray"``; a task whose worker died is retried by Ray, only that design), or on a
batched engine (``engine="jax"``: :func:`jax_evaluator`) in lockstep, a bounded number of
designs in flight (:func:`~softcrawl.codesign.groundtruth.search.search_many`); each row
appended to ``results.jsonl`` as its design finishes; then the references and the outputs."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import time
from collections.abc import Callable, Sequence
from pathlib import Path

from softcrawl.codesign.config import check_bounds
from softcrawl.codesign.groundtruth.config import MAX_IN_FLIGHT, GroundTruthConfig, design_set_spec
from softcrawl.codesign.groundtruth.optimize import DesignEvaluator, optimize_design
from softcrawl.codesign.groundtruth.outputs import write_outputs
from softcrawl.codesign.groundtruth.result import DIVERGED_CM, DesignResult
from softcrawl.codesign.groundtruth.search import EvaluateMany, search_many
from softcrawl.codesign.groundtruth.store import (
    RESULTS,
    _append,
    check_folder,
    folder_lock,
    load_results,
    read_config,
    read_references,
    recorded_designs,
)
from softcrawl.codesign.migrate import CONFIG_VERSION
from softcrawl.design.resolve import write_space_copy
from softcrawl.design.space import BASELINE_DESIGN, DEFAULT_SPACE, PAPER_BEST_DESIGN, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.gaits.periodic import PeriodicGait
from softcrawl.safeio import atomic_write_text, load_json
from softcrawl.tasks import Forward

EXECUTORS = ("process", "serial", "ray")
#: Paper's reward of its best design L1 with its learned gait (codesign.md), cm per 20 s.
PAPER_L1_CM = 10.0


def _task(design: Design, cfg_dict: dict) -> dict:
    """Worker entry: one design's ground truth as a dict (picklable, module level)."""
    return optimize_design(design, GroundTruthConfig.from_dict(cfg_dict)).to_dict()


def _pin_threads(parent_pid: int | None = None) -> None:
    """Worker initializer: one BLAS thread; with ``parent_pid``, a watchdog thread that ends the
    worker when that process is gone (a killed run must not leave workers computing)."""
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ[var] = "1"
    if parent_pid is not None:
        from softcrawl.parallel import watch_parent

        watch_parent(parent_pid)
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(1)
    except ImportError:  # pragma: no cover
        pass


def _phase_sweep(cfg: GroundTruthConfig, design, gait_of) -> tuple[str, dict[str, float]]:
    """``design``'s return with ``gait_of(phase)`` at every lag of ``cfg.baseline_phases``
    (the task's unit per ``cfg.duration`` s; :data:`DIVERGED_CM` for a diverged episode):
    ``(best lag as text, {lag as text: return})``."""
    ev = DesignEvaluator(design, cfg)
    sweep = {}
    for ph in cfg.baseline_phases:
        r, div = ev(gait_of(ph), cfg.duration)
        sweep[str(ph)] = DIVERGED_CM if div else r
    return max(sweep, key=sweep.get), sweep


def references(cfg: GroundTruthConfig, progress: bool = False) -> dict:
    """Reference gaits with the run's settings: the expert baseline (design
    :data:`BASELINE_DESIGN`, smooth sine at every lag of ``cfg.baseline_phases``, best kept) and
    the paper's 3-s cycle on :data:`PAPER_BEST_DESIGN`; cm per ``cfg.duration`` s. For the
    ``turning`` task, its hand-made baseline instead (:mod:`softcrawl.tasks.baselines`:
    :func:`~softcrawl.tasks.baselines.turning_gait` on
    :data:`~softcrawl.tasks.baselines.TURNING_BASELINE_DESIGN` at every lag of
    ``cfg.baseline_phases``, the lag of the largest counter-clockwise turn kept, the ground
    truth's objective), degrees per ``cfg.duration`` s."""
    out: dict = {}
    if cfg.task_spec().name == "turning":
        if cfg.baseline_phases:
            from softcrawl.tasks.baselines import TURNING_BASELINE_DESIGN, turning_gait

            # the design is canonical: its labels stay
            best, sweep = _phase_sweep(cfg, TURNING_BASELINE_DESIGN, turning_gait)
            out["turning_baseline"] = {"design": list(TURNING_BASELINE_DESIGN), "best_phase_deg": float(best),
                                       "reward_deg": sweep[best], "sweep_deg": sweep}
        return out
    if cfg.baseline_phases:
        best, sweep = _phase_sweep(cfg, BASELINE_DESIGN, lambda ph: PeriodicGait.expert_sine(ph, hold=cfg.hold))
        out["expert_baseline"] = {"design": list(BASELINE_DESIGN), "best_phase_deg": float(best),
                                  "reward_cm": sweep[best], "sweep_cm": sweep}
    ev = DesignEvaluator(PAPER_BEST_DESIGN, cfg)
    paper = PeriodicGait.paper_cycle(hold=cfg.hold)
    r, div = ev(paper, cfg.duration)
    out["paper_l1_gait"] = {"design": list(PAPER_BEST_DESIGN), "gait": paper.to_dict(),
                            "reward_cm": DIVERGED_CM if div else r, "paper_reported_cm": PAPER_L1_CM}
    return out


def run_groundtruth(designs: Sequence | None, out_dir: str | Path, cfg: GroundTruthConfig | None = None,
                    workers: int | None = None, executor: str = "process", progress: bool = True,
                    task: Callable[[Design, dict], dict] = _task, ray_address: str | None = None,
                    refs: bool = True, evaluate_many: EvaluateMany | None = None,
                    in_flight: int | None = None) -> dict:
    """Ground truth of ``designs`` into ``out_dir`` (see the module docstring); resumable.

    Everything is checked before anything is written: the folder (:func:`check_folder`), the
    settings, the designs, the reduction file and the engine
    (:meth:`GroundTruthConfig.check_engine`); a refused run leaves no folder behind (or the
    empty one it was given). The folder is locked while the run writes it (:func:`folder_lock`):
    a second run on it stops at once. ``config.json`` records the settings and the design set
    (:func:`~softcrawl.codesign.groundtruth.config.design_set_spec`, key ``"designs"``).

    Args:
        designs: designs (canonicalised; duplicates dropped); None: the set the folder records.
        out_dir: run folder (created; an existing one must hold the same config).
        cfg: settings (default :class:`GroundTruthConfig`; None on an existing folder: its own,
            and then its recorded design set: ``designs``, if given, must be that set).
            A run with settings on an existing folder (the same command again) computes
            ``designs`` and records them as the folder's set.
        workers: processes (``executor="process"``; default: CPU count) or Ray CPUs.
        executor: ``"process"`` (pool), ``"serial"`` (in-process) or ``"ray"`` (Ray tasks, local
            Ray unless ``ray_address``).
        task: ``(design, cfg dict) -> DesignResult dict`` (tests inject counting fakes).
        refs: compute ``references.json`` (expert baseline sweep, paper gait) if missing.
        evaluate_many: a batched engine (:data:`~softcrawl.codesign.groundtruth.search.EvaluateMany`;
            ``cfg.engine == "jax"`` gives :func:`jax_evaluator`'s): the unfinished designs are
            searched in lockstep in this process
            (:func:`~softcrawl.codesign.groundtruth.search.search_many`), in order of leg count
            (a batch of one leg count is not padded to another's), each row appended as its
            design finishes; ``executor``, ``workers`` and ``task`` are then not used (the
            references are still computed on the CPU).
        in_flight: designs searched at once by a batched engine (default
            :func:`default_in_flight`; it bounds the memory and sets the batch: about 10 to 50
            episodes per design in flight per call). Not a setting of the folder: a resumed run
            may take another. A killed run loses at most the designs in flight.

    Returns:
        The summary dict (also ``summary.json``).

    Raises:
        ValueError: config mismatch with an existing folder, unknown executor, ``in_flight`` not
            in 1..:data:`MAX_IN_FLIGHT` or given to the CPU engine, empty design set,
            no design set (none given, none recorded), a resumed folder given another design
            set, settings out of bounds, a bad reduction file, a folder another command wrote
            (:func:`check_folder`).
        FolderLockedError: another run is writing the folder.
    """
    if executor not in EXECUTORS:
        raise ValueError(f"executor must be one of {EXECUTORS}, got {executor!r}")
    if in_flight is not None:
        check_bounds("in_flight", in_flight, 1, MAX_IN_FLIGHT)
        if isinstance(in_flight, bool) or int(in_flight) != in_flight:
            raise ValueError(f"in_flight must be an integer, got {in_flight!r}")
    out = check_folder(out_dir)
    existing = (out / "config.json").exists()
    resume = cfg is None and existing
    check = (cfg or GroundTruthConfig()).validate() if not resume else read_config(out)
    if in_flight is not None and evaluate_many is None and check.engine != "jax":
        raise ValueError(f'in_flight sets the designs a batched engine searches at once; engine {check.engine!r} '
                         'searches one design per worker (--workers)')
    designs = None if designs is None else list(dict.fromkeys(check.design_space().canonicalize(d) for d in designs))
    if designs is not None and not designs:
        raise ValueError("empty design set")
    if designs is None and not existing:
        raise ValueError(f"{out} is a new ground truth: give its designs")
    if evaluate_many is None:
        check.check_engine()  # a bad reduction file fails here, not in a worker after the folder is written
    created = not out.exists()
    out.mkdir(parents=True, exist_ok=True)
    try:
        with folder_lock(out):
            cfg, designs = _settle_folder(out, cfg, designs, resume)
            return _compute(designs, out, cfg, workers, executor, progress, task, ray_address, refs, evaluate_many,
                            in_flight)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                out.rmdir()  # only if still empty
        raise


def _settle_folder(out: Path, cfg: GroundTruthConfig | None, designs: list | None,
                   resume: bool) -> tuple[GroundTruthConfig, list]:
    """The locked folder's settings and design set (:func:`run_groundtruth`): a new folder gets
    ``space.toml`` and then ``config.json`` (``cfg``, ``designs``); an existing one's settings
    must be ``cfg`` (None: its own), its recorded set ``designs`` on ``resume`` (None: the
    recorded set), and a run with settings records ``designs`` as its set. Returns ``(the
    folder's config, the designs)``.

    Raises:
        ValueError: other settings, or another design set on ``resume``, or no set at all.
    """
    cfg_path = out / "config.json"
    if not cfg_path.exists():
        cfg = (cfg or GroundTruthConfig()).validate()
        sha = write_space_copy(out, cfg.space)  # before config.json, which marks the folder a ground truth
        from softcrawl import __version__

        _write_config(out, {"config": cfg.to_dict(), "config_version": CONFIG_VERSION, "space_sha256": sha,
                            "designs": design_set_spec(designs, cfg.design_space()), "softcrawl": __version__})
        return read_config(out), designs  # its space: the folder's copy
    saved = read_config(out)
    given = None if cfg is None else cfg.to_dict() | (  # the folder keeps its space as its own file
        {"space": saved.space} if cfg.design_space() == saved.design_space() else {})
    if given is not None and given != saved.to_dict():
        diff = {k: (v, given[k]) for k, v in saved.to_dict().items() if given[k] != v}
        raise ValueError(f"{out} holds a ground truth with other settings (saved vs given: {diff}); "
                         "use another folder")
    recorded, space = recorded_designs(out), saved.design_space()
    if designs is None:
        if recorded is None:
            raise ValueError(f"{out} records no design set (written before ground truths recorded theirs): give "
                             "its --designs")
        return saved, recorded
    if resume and recorded is not None and set(designs) != set(recorded):
        raise ValueError(f"{out} is the ground truth of the designs {_shown(recorded, space)}; --resume continues "
                         f"exactly them, not {_shown(designs, space)}: drop --designs, or run those in another "
                         "folder")
    if not resume and (recorded is None or set(designs) != set(recorded)):
        doc = load_json(out / "config.json")
        _write_config(out, {**doc, "designs": design_set_spec(designs, space)})
    return saved, designs


def _shown(designs: list, space: DesignSpace) -> str:
    """A design set for a message: its :func:`design_set_spec` (cut short) and its size."""
    spec = design_set_spec(designs, space)
    return f"{spec[:60]!r}{'...' if len(spec) > 60 else ''} ({len(designs)})"


def _write_config(out: Path, doc: dict) -> None:
    """Write ``doc`` as a ground truth's ``config.json`` (atomically)."""
    atomic_write_text(out / "config.json", json.dumps(doc, indent=2) + "\n")


def jax_evaluator(cfg: GroundTruthConfig):
    """The batched JAX engine of ``cfg``: a :class:`softcrawl.jaxsim.episodes.JaxEvaluator` of
    ``cfg``'s design space and robot, on the forward task's floor, in ``cfg.robot.rid_dtype``,
    batches of at most ``cfg.jax_batch``, diverged episodes scored :data:`DIVERGED_CM`; its
    ``evaluate`` is an :data:`EvaluateMany`. float64 turns on ``jax_enable_x64`` for the process.

    Raises:
        ImportError: JAX is not installed (``pip install "softcrawl[jax]"``).
    """
    try:
        import jax
    except ImportError as exc:
        raise ImportError('engine "jax" needs JAX: pip install "softcrawl[jax]" (or "softcrawl[gpu]")') from exc
    from softcrawl.jaxsim.episodes import JaxEvaluator

    if cfg.robot.rid_dtype == "float64":
        jax.config.update("jax_enable_x64", True)
    task = cfg.task_spec()  # forward (GroundTruthConfig.validate refuses the others): its floor's friction
    robot = cfg.robot_config() if task.friction is None else dataclasses.replace(cfg.robot_config(),
                                                                                 friction=task.friction)
    return JaxEvaluator(robot, precision=cfg.robot.rid_dtype, max_batch=cfg.jax_batch,
                        diverged_cm=DIVERGED_CM, space=cfg.design_space())


def default_in_flight(cfg: GroundTruthConfig) -> int:
    """Designs a batched engine searches at once unless told (:func:`run_groundtruth`):
    ``cfg.jax_batch // 16`` (at least 1), so that a call's screening episodes (a round is 10 to 50
    episodes per design) fill about one to three batches of ``cfg.jax_batch``."""
    return max(1, cfg.jax_batch // 16)


def _compute(designs: list, out: Path, cfg: GroundTruthConfig, workers, executor, progress, task, ray_address,
             refs, evaluate_many, in_flight) -> dict:
    """The body of :func:`run_groundtruth` once the folder is locked and its settings known."""
    done = load_results(out)
    todo = [d for d in designs if d not in done]
    res_path = out / RESULTS
    cd, space, unit = cfg.to_dict(), cfg.design_space(), cfg.task_spec().unit
    wall = time.perf_counter()
    from tqdm.auto import tqdm

    bar = tqdm(total=len(designs), initial=len(designs) - len(todo), desc="ground truth", unit="design",
               disable=not progress, dynamic_ncols=True)
    forget = None
    if todo and evaluate_many is None and cfg.engine == "jax":
        engine = jax_evaluator(cfg)
        evaluate_many, forget = engine.evaluate, engine.forget
    post: dict = {}  # the bar's postfix: the last reward; with a batched engine, episodes and their rate

    def finish(d_result: dict) -> None:
        r = DesignResult.from_dict(d_result, space=space)  # a worker's dict: DesignResult.to_dict()
        _append(res_path, r, unit)
        done[r.design] = r
        if forget is not None:
            forget([r.design])
        post["last"] = f"{r.reward_cm:+.2f}{unit}"
        bar.set_postfix(post, refresh=False)
        bar.update()

    def counted(requests):
        replies = evaluate_many(requests)
        post["episodes"] = post.get("episodes", 0) + len(requests)
        post["episodes/s"] = f"{post['episodes'] / (time.perf_counter() - wall):.1f}"
        bar.set_postfix(post)
        return replies

    if todo:
        if evaluate_many is not None:
            todo.sort(key=lambda d: sum(v > 0 for v in d))  # stable: the set's order within a leg count
            for r in search_many(todo, cfg, counted, space, in_flight or default_in_flight(cfg)):
                finish(r.to_dict())
        elif executor == "serial":
            for d in todo:
                finish(task(d, cd))
        elif executor == "process":
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            _pin_threads()  # inherited by the workers before they import numpy
            n = max(1, min(len(todo), workers or os.cpu_count() or 1))
            method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
            pool = ProcessPoolExecutor(n, mp_context=mp.get_context(method), initializer=_pin_threads,
                                       initargs=(os.getpid(),))
            try:
                futs = [pool.submit(task, d, cd) for d in todo]
                for fut in as_completed(futs):
                    finish(fut.result())
            except BaseException:  # Ctrl-C or a failed design: do not wait for the running ones
                pool.shutdown(wait=False, cancel_futures=True)
                raise
            pool.shutdown()
        else:
            from softcrawl.parallel import ray_map

            for res in ray_map(task, [(d, cd) for d in todo], address=ray_address, num_cpus=workers):
                finish(res)
    bar.close()
    ref_path = out / "references.json"
    if refs and read_references(out) is None and space == DEFAULT_SPACE and (
            cfg.task_spec() == Forward() or cfg.task_spec().name == "turning"):
        # designs and gaits of the paper's space: the forward task's on its floor, or the turning baseline
        atomic_write_text(ref_path, json.dumps(references(cfg), indent=2, allow_nan=False) + "\n")
    return write_outputs(out, designs, time.perf_counter() - wall)
