"""The co-design training driver (``softcrawl train``; codesign.md, "Each iteration").

The run folder's layout, checkpoint formats and integrity checks are those of
:mod:`softcrawl.codesign.run`; this module writes through it. A checkpoint is written after the
gradient updates of the vectorised step it is named after, so a resumed run has every update
the uninterrupted one had. A checkpoint at an episode boundary (every env just reset, as with
the ``crawl``, ``demo`` and ``smoke`` presets' checkpoints) also keeps the designs drawn for the
next episodes, and a run resumed from it continues as the uninterrupted run did (the same
episodes, to the bit, with domain randomization off: the envs' own random draws restart from
their seeds). From a checkpoint inside episodes, the running episodes are discarded (their
transitions are in the replay buffer; their returns never reach the design distribution) and
every env starts a new episode with a freshly sampled design; the counters continue. A design
whose robot did not come to rest before its episode (the env's ``info["at_rest"]``, whatever the
backend) is a warning line on stderr, once per design and call
(:func:`softcrawl.robot.episode.unsettled_warning`). The report
is not written here (``softcrawl train`` calls :func:`softcrawl.codesign.report.write_report`
afterwards).
"""

from __future__ import annotations

import contextlib
import csv
import os
import random
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from tqdm.auto import tqdm

from softcrawl.codesign.config import TrainConfig, place
from softcrawl.codesign.factory import check_reduction, make_sampler, make_vec_env
from softcrawl.codesign.randomization import DomainLog
from softcrawl.codesign.run import Run
from softcrawl.codesign.sac import make_sac, prepare_learner
from softcrawl.codesign.sampler import GibbsDesignSampler
from softcrawl.robot.episode import unsettled_warning
from softcrawl.tasks import parse_task


# -- logging callback -------------------------------------------------------------------------
def _design_str(d) -> str:
    return "".join(map(str, d)) if d is not None else ""


class CodesignCallback(BaseCallback):
    """Per step: progress bar, episode rows, codesign/* scalars, snapshots, a warning for each
    design whose robot did not come to rest before its episode (once per design); checkpoints at
    the start of the next rollout, i.e. after the step's gradient updates."""

    def __init__(self, cfg: TrainConfig, run: Run, sampler: GibbsDesignSampler, progress: bool, wall_start: float):
        super().__init__()
        self.cfg, self.run, self.sampler, self.progress = cfg, run, sampler, progress
        self.bar = None
        self.t_start = wall_start  # time.perf_counter() when this train/resume call began
        self.start_steps = 0
        self.checkpoint_due = False
        self.session_recorded = False
        #: the unit of the returns (the task's: cm, deg) in the codesign/*_return_<unit> scalars
        self.unit = parse_task(cfg.env.task).unit
        #: the designs warned about: their robot did not come to rest before an episode
        self.unsettled: set = set()

    def record_session(self) -> None:
        """This call's ``sessions.csv`` row, up to the current step (see :meth:`Run.record_session`)."""
        self.run.record_session(self.start_steps, self.num_timesteps, time.perf_counter() - self.t_start,
                                replace_last=self.session_recorded)
        self.session_recorded = True

    def _on_training_start(self) -> None:
        self.start_steps = self.num_timesteps
        self.bar = tqdm(total=self.cfg.total_steps, initial=self.num_timesteps, unit="step", desc="train",
                        disable=not self.progress, dynamic_ncols=True)
        # kept open for the whole run, closed in _on_training_end
        self.episodes = open(self.run.episodes_csv, "a", newline="")  # noqa: SIM115
        self.ep_writer = csv.writer(self.episodes)
        self.dist_file = open(self.run.distribution_csv, "a", newline="")  # noqa: SIM115
        self.dist_writer = csv.writer(self.dist_file)
        self.domain_log = DomainLog(self.run.domain_csv, self.cfg.env.randomize, self.num_timesteps,
                                    unit=self.unit, n_regulators=self.cfg.env.design_space().n_regulators)
        self.best = -np.inf

    def _on_rollout_start(self) -> None:
        if self.checkpoint_due:  # the previous step's gradient updates are done
            self.checkpoint()

    def _on_step(self) -> bool:
        t = self.num_timesteps
        self.bar.update(t - self.bar.n)
        rows = [info for info in self.locals["infos"] if "episode" in info]
        for info in rows:
            r = info["episode"]["r"]
            self.best = max(self.best, r)
            self.ep_writer.writerow([t, _design_str(info.get("design")), f"{r:.6g}", int(info.get("diverged", False))])
            self.domain_log.write(t, info)
            warning = unsettled_warning(info)
            if warning and info.get("design") not in self.unsettled:
                self.unsettled.add(info.get("design"))
                self.bar.write(f"softcrawl train: warning: design {_design_str(info.get('design'))} {warning} "
                               "(said once per design)", file=sys.stderr)
        if rows:
            up = self.sampler.distribution.last
            top = self.sampler.distribution.top(3)
            self.dist_writer.writerow([t, f"{up.beta:.6g}", f"{up.entropy:.6g}", f"{up.target:.6g}",
                                       f"{up.effective_target:.6g}", f"{up.floor:.6g}", int(up.clamped),
                                       " ".join(f"{_design_str(d)}:{p:.3g}" for d, p, _ in top)])
            self.logger.record("codesign/beta", up.beta)
            self.logger.record("codesign/entropy", up.entropy)
            self.logger.record("codesign/entropy_target", up.target)
            self.logger.record("codesign/entropy_clamped", int(up.clamped))
            self.logger.record(f"codesign/best_return_{self.unit}", self.best)
            self.logger.record(f"codesign/mean_return_{self.unit}", float(np.mean([i["episode"]["r"] for i in rows])))
            self.logger.record("codesign/top1_prob", top[0][1])
            self.logger.record("codesign/top_designs", ", ".join(f"{_design_str(d)} p={p:.3g} R={r:+.3f}"
                                                                  for d, p, r in top), exclude=("csv", "stdout"))
            self.bar.set_postfix(best=f"{self.best:+.2f}{self.unit}", H=f"{up.entropy:.2f}", refresh=False)
        every = self.cfg.snapshot_every
        if t // every > (t - self.training_env.num_envs) // every:
            self.write_snapshot()
        every = self.cfg.checkpoint_every
        if t // every > (t - self.training_env.num_envs) // every:
            self.checkpoint_due = True
        return True

    def write_snapshot(self) -> None:
        self.run.write_snapshot(self.sampler.distribution, self.num_timesteps)

    def checkpoint(self) -> None:
        if not self.episodes.closed:
            self.episodes.flush()
            self.dist_file.flush()
            self.domain_log.flush()
        self.model.flush()  # deferred (overlapped) updates of the steps done so far
        self.record_session()  # before the checkpoint: a kill after it never loses the call's time
        self.run.save_checkpoint(self.model, self.sampler, self.cfg.keep_checkpoints)
        self.checkpoint_due = False

    def _on_training_end(self) -> None:
        self.bar.close()
        self.episodes.close()
        self.dist_file.close()
        self.domain_log.close()


# -- the driver -------------------------------------------------------------------------------
@dataclass
class TrainResult:
    """Outcome of :func:`train`: run folder, transitions done, wall seconds of this call,
    SAC gradient updates (all calls), wall seconds of this call's updates (overlapped with the
    simulation unless ``sac.overlap`` is off)."""

    run_dir: Path
    steps: int
    wall_seconds: float
    updates: int
    learner_seconds: float = 0.0


def _resume_point(run: Run) -> Path | None:
    """The checkpoint to resume from; None for a run that never logged anything.

    Raises:
        ValueError: the run has history but no complete checkpoint (nothing is changed).
    """
    ck = run.latest_checkpoint()
    if ck is None and run.has_history():
        raise ValueError(f"cannot resume {run.path}: it has logged history but no complete checkpoint; "
                         "nothing was changed (start a new run with another --out)")
    return ck


def train(run_dir: str | os.PathLike, cfg: TrainConfig | None = None, resume: bool = False,
          progress: bool = True, ray_address: str | None = None, placement: list[str] | None = None) -> TrainResult:
    """Train (or, with ``resume``, continue) a co-design run in ``run_dir`` (no report; see
    :func:`softcrawl.cli.train.train_and_report`).

    Args:
        run_dir: run folder; must not exist or be empty for a new run; for ``resume`` it must
            hold ``config.json`` (``cfg`` is then ignored, the saved one is used).
        cfg: the configuration (new runs).
        resume: continue from the newest complete checkpoint (:meth:`Run.latest_checkpoint`;
            from scratch if the run never logged anything).
        progress: tqdm progress bar on stderr.
        ray_address: the Ray cluster of ``backend="ray"`` (None: a local Ray); a property of
            where the run is, not of the run, so not in its config.
        placement: with ``resume``, ``"key=value"`` settings of where this session runs
            (:data:`softcrawl.codesign.config.PLACEMENT_KEYS`: the learner's device, the worker
            processes), applied to the saved config for this session only.

    The run is locked while this writes it (:meth:`Run.lock`): a second ``train`` or ``report``
    on it is refused at once. Everything is checked before anything is written: the config,
    the folder, the Ray address, the reduction file and the learner's device; a new run's
    folder is created only then, and ``config.json`` written only once the envs and sampler are
    built, so a failed start leaves no folder (or the empty one it was given) and the same
    command can be run again.

    Raises:
        ValueError: a bad config, ``run_dir`` a file or non-empty for a new run, a missing run,
            a run with history and no complete checkpoint on resume, ``placement`` without
            ``resume`` or with a setting outside ``PLACEMENT_KEYS``.
        FolderLockedError: another command is writing the run.
        NoSpaceError: a checkpoint could not be written (disk full / read-only).
    """
    run = Run(run_dir)
    if resume:
        run.read_meta()  # a training run, before its lock is taken
        with run.lock():
            cfg = place(run.read_config(), placement or [])
            ckpt = _resume_point(run)
            if ckpt is not None:
                cfg.sac.learner = run.checkpoint_learner(ckpt)  # the learner that wrote it
            _check_start(cfg, ray_address, resume)
            return _train(run, cfg, ckpt, resume, progress, ray_address)
    if cfg is None:
        raise ValueError("a new run needs a config")
    if placement:
        raise ValueError("placement applies to a resumed run; a new run takes its settings in cfg")
    cfg.validate()
    _check_new(run)
    _check_start(cfg, ray_address, resume)
    created = not run.path.exists()
    run.path.mkdir(parents=True, exist_ok=True)
    try:
        with run.lock():
            _check_new(run)  # again, locked: another run may have started in it meanwhile
            return _train(run, cfg, None, resume, progress, ray_address)
    except BaseException:
        if created:
            with contextlib.suppress(OSError):
                run.path.rmdir()  # only if still empty: a failed start leaves no folder behind
        raise


def _check_new(run: Run) -> None:
    """Refuse a new run's folder that exists and is not an empty folder (ValueError)."""
    if not run.is_new():
        raise ValueError(f"run directory {run.path} exists and is not an empty folder "
                         "(use --resume or another --out)")


def _check_start(cfg: TrainConfig, ray_address: str | None, resume: bool) -> None:
    """What must hold before a run's envs are built: the Ray address for Ray only, a new run's
    reduction file (:func:`~softcrawl.codesign.factory.check_reduction`), the learner's threads
    and device (:func:`~softcrawl.codesign.sac.prepare_learner`). ValueError if not."""
    if ray_address is not None and cfg.backend != "ray":
        raise ValueError(f"a Ray address is used only by backend \"ray\", not {cfg.backend!r}")
    if not resume:
        check_reduction(cfg)  # a reduction of another part or model: refused before anything is built
    prepare_learner(cfg.sac)  # threads before JAX / torch start; the device before the workers start


def _train(run: Run, cfg: TrainConfig, ckpt: Path | None, resume: bool, progress: bool,
           ray_address: str | None) -> TrainResult:
    """The body of :func:`train`, its run locked and its settings checked."""
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    sampler = make_sampler(cfg)
    venv = make_vec_env(cfg, sampler, ray_address)
    wall = time.perf_counter()
    try:
        model = make_sac(venv, cfg.sac, seed=cfg.seed, rollout=cfg.rollout)
        if not resume:
            run.write_config(cfg)
        if ckpt is not None:
            run.load_checkpoint(ckpt, model, sampler)
            venv.num_transitions = model.num_timesteps
        if resume:
            run.forget_after(model.num_timesteps)
        model.set_logger(configure(str(run.logs_dir), ["csv", "tensorboard"]))
        start = model.num_timesteps
        callback = CodesignCallback(cfg, run, sampler, progress, wall_start=wall)
        remaining = cfg.total_steps - start
        if remaining > 0:
            model.learn(total_timesteps=remaining, callback=callback, reset_num_timesteps=ckpt is None and not resume,
                        log_interval=max(1, cfg.n_envs))
            model.flush()  # the last step's updates, deferred to a next step that never came
            last = run.latest_checkpoint(quiet=True)
            if last is None or run.checkpoint_steps(last) != model.num_timesteps:
                callback.write_snapshot()
                run.save_checkpoint(model, sampler, cfg.keep_checkpoints)
        result = TrainResult(run.path, model.num_timesteps, time.perf_counter() - wall, model._n_updates,
                             model.learner_seconds)
        run.record_session(start, result.steps, result.wall_seconds, replace_last=callback.session_recorded)
    finally:
        venv.close()
    return result
