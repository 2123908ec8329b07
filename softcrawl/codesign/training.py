"""The co-design training driver (``softcrawl train``; codesign.md, "Each iteration").

Run directory layout::

    config.json            TrainConfig + software version
    episodes.csv           t (transitions), design, return_cm, diverged  (one row per episode)
    distribution.csv       t, beta, entropy, target, effective_target, floor, clamped, top designs
    sessions.csv           one row per train/resume call: first step, last step, wall seconds, version
    snapshots/t-XXXXXXXXXX.npz   p (probabilities) and scores of all designs every snapshot_every
    logs/                  SB3 logger: progress.csv + TensorBoard events (SAC losses, alpha, codesign/*)
    checkpoints/step-XXXXXXXXXX/  model.pt (policy, critics, targets, optimizers, temperature,
                           counters, torch/numpy/python RNG), replay_buffer.pkl, state.pkl
                           (design sampler incl. its RNG); checkpoints/latest names the newest
    report/                written at the end (softcrawl.codesign.report)

Checkpoints are written into a ``.tmp`` folder renamed into place, and ``latest`` is replaced
atomically, so a run killed at any moment resumes from a complete checkpoint. On resume the
episodes that were running at the checkpoint are discarded (their transitions are in the
replay buffer; their returns never reach the design distribution) and every env starts a new
episode with a freshly sampled design; the counters continue.
"""

from __future__ import annotations

import csv
import json
import os
import pickle
import random
import shutil
import time
from dataclasses import dataclass
from functools import partial
from pathlib import Path

import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.logger import configure
from tqdm.auto import tqdm

from softcrawl import __version__
from softcrawl.codesign.config import TrainConfig
from softcrawl.codesign.distribution import EntropySchedule, GibbsDesignDistribution
from softcrawl.codesign.sac import SplitLRSAC, make_sac
from softcrawl.codesign.sampler import GibbsDesignSampler
from softcrawl.envs.crawler import BuildRobot, CrawlerEnv
from softcrawl.envs.vec import DesignVecEnv, SerialBackend, SubprocessBackend
from softcrawl.robot.assembly import RobotConfig


def robot_factory(cfg: TrainConfig):
    """Picklable ``design -> Robot`` for ``cfg.env`` (full-order or reduced model)."""
    e = cfg.env
    return BuildRobot(RobotConfig(leg_mesh_size=e.leg_mesh_size, disk_mesh_size=e.disk_mesh_size,
                                  refactor_every=e.refactor_every, dt=e.dt, model=e.model, reduction=e.reduction))


def env_fn(cfg: TrainConfig):
    """Zero-argument constructor of one :class:`CrawlerEnv` (picklable)."""
    e = cfg.env
    return partial(CrawlerEnv, robot_factory=robot_factory(cfg), steps_per_action=e.steps_per_action,
                   n_actions=e.n_actions, observe_state=e.observe_state, designs=e.designs(),
                   settling=e.settling(), max_cached=e.max_cached_robots)


def make_vec_env(cfg: TrainConfig, sampler) -> DesignVecEnv:
    """The vectorised env of ``cfg`` (serial or subprocess backend) with ``sampler``."""
    fns = [env_fn(cfg)] * cfg.n_envs
    if cfg.backend == "serial":
        backend = SerialBackend(fns)
    else:
        backend = SubprocessBackend(fns, n_workers=cfg.n_workers or None)
    venv = DesignVecEnv(backend, sampler)
    venv.seed(cfg.seed)
    return venv


def make_sampler(cfg: TrainConfig) -> GibbsDesignSampler:
    """Design distribution over ``cfg.env.designs()`` with the entropy schedule of ``cfg``."""
    dist = GibbsDesignDistribution(cfg.env.designs(), untried=cfg.design.untried, beta_max=cfg.design.beta_max)
    sched = EntropySchedule(t0=int(cfg.design.t0_fraction * cfg.total_steps),
                            t1=int(cfg.design.t1_fraction * cfg.total_steps), h_max=dist.h_max,
                            h_end=min(cfg.design.h_end, dist.h_max))
    return GibbsDesignSampler(dist, sched, seed=cfg.seed + 1)


# -- checkpoints ------------------------------------------------------------------------------
def latest_checkpoint(run_dir: Path) -> Path | None:
    """The newest complete checkpoint folder of a run, or None."""
    ptr = Path(run_dir) / "checkpoints" / "latest"
    if not ptr.exists():
        return None
    path = Path(run_dir) / "checkpoints" / ptr.read_text().strip()
    return path if path.is_dir() else None


def save_checkpoint(run_dir: Path, model: SplitLRSAC, sampler: GibbsDesignSampler, keep: int = 2) -> Path:
    """Write a complete checkpoint atomically (see the module docstring); returns its folder."""
    root = Path(run_dir) / "checkpoints"
    root.mkdir(parents=True, exist_ok=True)
    name = f"step-{model.num_timesteps:010d}"
    tmp = root / f"{name}.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir()
    torch.save({
        "policy": model.policy.state_dict(),
        "actor_optimizer": model.actor.optimizer.state_dict(),
        "critic_optimizer": model.critic.optimizer.state_dict(),
        "log_ent_coef": model.log_ent_coef.detach().clone(),
        "ent_coef_optimizer": model.ent_coef_optimizer.state_dict(),
        "num_timesteps": model.num_timesteps, "n_updates": model._n_updates, "episode_num": model._episode_num,
        "torch_rng": torch.get_rng_state(), "numpy_rng": np.random.get_state(), "python_rng": random.getstate(),
    }, tmp / "model.pt")
    with open(tmp / "replay_buffer.pkl", "wb") as f:
        pickle.dump(model.replay_buffer, f, protocol=pickle.HIGHEST_PROTOCOL)
    with open(tmp / "state.pkl", "wb") as f:
        pickle.dump({"sampler": sampler.state_dict(), "version": __version__}, f)
    final = root / name
    shutil.rmtree(final, ignore_errors=True)
    os.replace(tmp, final)
    ptr_tmp = root / "latest.tmp"
    ptr_tmp.write_text(name)
    os.replace(ptr_tmp, root / "latest")
    old = sorted(p for p in root.glob("step-*") if p.is_dir() and not p.name.endswith(".tmp"))
    for p in old[:-keep]:
        shutil.rmtree(p, ignore_errors=True)
    return final


def load_checkpoint(path: Path, model: SplitLRSAC, sampler: GibbsDesignSampler) -> None:
    """Restore a checkpoint written by :func:`save_checkpoint` into a freshly built model/sampler."""
    ck = torch.load(Path(path) / "model.pt", weights_only=False)
    model.policy.load_state_dict(ck["policy"])
    model.actor.optimizer.load_state_dict(ck["actor_optimizer"])
    model.critic.optimizer.load_state_dict(ck["critic_optimizer"])
    with torch.no_grad():
        model.log_ent_coef.copy_(ck["log_ent_coef"])
    model.ent_coef_optimizer.load_state_dict(ck["ent_coef_optimizer"])
    model.num_timesteps, model._n_updates, model._episode_num = ck["num_timesteps"], ck["n_updates"], ck["episode_num"]
    torch.set_rng_state(ck["torch_rng"])
    np.random.set_state(ck["numpy_rng"])
    random.setstate(ck["python_rng"])
    with open(Path(path) / "replay_buffer.pkl", "rb") as f:
        model.replay_buffer = pickle.load(f)
    with open(Path(path) / "state.pkl", "rb") as f:
        sampler.load_state_dict(pickle.load(f)["sampler"])
    model._last_obs = None  # forces env.reset() in learn(): fresh episodes


# -- logging callback -------------------------------------------------------------------------
def _design_str(d) -> str:
    return "".join(map(str, d)) if d is not None else ""


class CodesignCallback(BaseCallback):
    """Per step: progress bar, episode rows, codesign/* scalars, snapshots, checkpoints."""

    def __init__(self, cfg: TrainConfig, run_dir: Path, sampler: GibbsDesignSampler, progress: bool = True):
        super().__init__()
        self.cfg, self.run_dir, self.sampler, self.progress = cfg, Path(run_dir), sampler, progress
        self.bar = None
        self.t_start = time.perf_counter()
        self.start_steps = 0

    def _on_training_start(self) -> None:
        self.start_steps = self.num_timesteps
        self.bar = tqdm(total=self.cfg.total_steps, initial=self.num_timesteps, unit="step", desc="train",
                        disable=not self.progress, dynamic_ncols=True)
        # kept open for the whole run, closed in _on_training_end
        self.episodes = open(self.run_dir / "episodes.csv", "a", newline="")  # noqa: SIM115
        self.ep_writer = csv.writer(self.episodes)
        self.dist_file = open(self.run_dir / "distribution.csv", "a", newline="")  # noqa: SIM115
        self.dist_writer = csv.writer(self.dist_file)
        self.best = -np.inf

    def _on_step(self) -> bool:
        t = self.num_timesteps
        self.bar.update(t - self.bar.n)
        rows = [info for info in self.locals["infos"] if "episode" in info]
        for info in rows:
            r = info["episode"]["r"]
            self.best = max(self.best, r)
            self.ep_writer.writerow([t, _design_str(info.get("design")), f"{r:.6g}", int(info.get("diverged", False))])
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
            self.logger.record("codesign/best_return_cm", self.best)
            self.logger.record("codesign/mean_return_cm", float(np.mean([i["episode"]["r"] for i in rows])))
            self.logger.record("codesign/top1_prob", top[0][1])
            self.logger.record("codesign/top_designs", ", ".join(f"{_design_str(d)} p={p:.3g} R={r:+.3f}"
                                                                  for d, p, r in top), exclude=("csv", "stdout"))
            self.bar.set_postfix(best=f"{self.best:+.2f}cm", H=f"{up.entropy:.2f}", refresh=False)
        every = self.cfg.snapshot_every
        if t // every > (t - self.training_env.num_envs) // every:
            self.write_snapshot()
        every = self.cfg.checkpoint_every
        if t // every > (t - self.training_env.num_envs) // every:
            self.checkpoint()
        return True

    def write_snapshot(self) -> None:
        d = self.sampler.distribution
        (self.run_dir / "snapshots").mkdir(exist_ok=True)
        np.savez_compressed(self.run_dir / "snapshots" / f"t-{self.num_timesteps:010d}.npz",
                            p=d.probs().astype(np.float32), scores=d.scores().astype(np.float32),
                            tried=d.tried, t=self.num_timesteps)

    def checkpoint(self) -> None:
        self.episodes.flush()
        self.dist_file.flush()
        save_checkpoint(self.run_dir, self.model, self.sampler, self.cfg.keep_checkpoints)

    def _on_training_end(self) -> None:
        self.bar.close()
        self.episodes.close()
        self.dist_file.close()


# -- the driver -------------------------------------------------------------------------------
@dataclass
class TrainResult:
    """Outcome of :func:`train`: run folder, transitions done, wall seconds of this call,
    SAC gradient updates, best episode return seen by this call (cm)."""

    run_dir: Path
    steps: int
    wall_seconds: float
    updates: int


def _truncate_csv(path: Path, t_max: int) -> None:
    """Drop rows with t > t_max (episodes logged after the checkpoint we resume from)."""
    if not path.exists():
        return
    with open(path, newline="") as f:
        rows = [r for r in csv.reader(f) if r and int(r[0]) <= t_max]
    tmp = path.with_suffix(".tmp")
    with open(tmp, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    os.replace(tmp, path)


def _forget_after(run_dir: Path, t: int) -> None:
    """Resume bookkeeping: drop episode/distribution rows and snapshots logged after step ``t``
    (the killed run's work past its checkpoint) and keep the SB3 ``progress.csv`` of the earlier
    part as ``progress-<k>.csv`` (SB3 would overwrite it)."""
    for name in ("episodes.csv", "distribution.csv"):
        _truncate_csv(run_dir / name, t)
    for snap in (run_dir / "snapshots").glob("t-*.npz") if (run_dir / "snapshots").exists() else []:
        if int(snap.stem.split("-")[1]) > t:
            snap.unlink()
    progress = run_dir / "logs" / "progress.csv"
    if progress.exists():
        k = len(list(progress.parent.glob("progress-*.csv")))
        os.replace(progress, progress.with_name(f"progress-{k}.csv"))


def train(run_dir: str | os.PathLike, cfg: TrainConfig | None = None, resume: bool = False,
          progress: bool = True, report: bool = True) -> TrainResult:
    """Train (or, with ``resume``, continue) a co-design run in ``run_dir``.

    Args:
        run_dir: run folder; must not exist or be empty for a new run; for ``resume`` it must
            hold ``config.json`` (``cfg`` is then ignored, the saved one is used).
        cfg: the configuration (new runs).
        resume: continue from ``checkpoints/latest`` (from scratch if there is none yet).
        progress: tqdm progress bar on stderr.
        report: write ``report/`` at the end.

    Raises:
        ValueError: a bad config, a non-empty ``run_dir`` for a new run, or a missing one on resume.
    """
    run_dir = Path(run_dir)
    if resume:
        if not (run_dir / "config.json").exists():
            raise ValueError(f"cannot resume: {run_dir / 'config.json'} not found")
        cfg = TrainConfig.from_dict(json.loads((run_dir / "config.json").read_text())["config"])
    else:
        if cfg is None:
            raise ValueError("a new run needs a config")
        cfg.validate()
        if run_dir.exists() and any(run_dir.iterdir()):
            raise ValueError(f"run directory {run_dir} exists and is not empty (use --resume or another --out)")
        run_dir.mkdir(parents=True, exist_ok=True)
        (run_dir / "config.json").write_text(json.dumps({"version": __version__, "config": cfg.to_dict()}, indent=2))
    torch.set_num_threads(1)
    random.seed(cfg.seed)
    np.random.seed(cfg.seed)
    torch.manual_seed(cfg.seed)
    sampler = make_sampler(cfg)
    venv = make_vec_env(cfg, sampler)
    wall = time.perf_counter()
    try:
        model = make_sac(venv, cfg.sac, seed=cfg.seed)
        ckpt = latest_checkpoint(run_dir) if resume else None
        if ckpt is not None:
            load_checkpoint(ckpt, model, sampler)
            venv.num_transitions = model.num_timesteps
        if resume:
            _forget_after(run_dir, model.num_timesteps)
        model.set_logger(configure(str(run_dir / "logs"), ["csv", "tensorboard"]))
        start = model.num_timesteps
        callback = CodesignCallback(cfg, run_dir, sampler, progress)
        remaining = cfg.total_steps - start
        if remaining > 0:
            model.learn(total_timesteps=remaining, callback=callback, reset_num_timesteps=ckpt is None and not resume,
                        log_interval=max(1, cfg.n_envs))
            if latest_checkpoint(run_dir) is None or latest_checkpoint(run_dir).name != f"step-{model.num_timesteps:010d}":
                callback.write_snapshot()
                save_checkpoint(run_dir, model, sampler, cfg.keep_checkpoints)
        result = TrainResult(run_dir, model.num_timesteps, time.perf_counter() - wall, model._n_updates)
        with open(run_dir / "sessions.csv", "a", newline="") as f:
            csv.writer(f).writerow([start, result.steps, f"{result.wall_seconds:.1f}", __version__])
    finally:
        venv.close()
    if report:
        from softcrawl.codesign.report import write_report

        write_report(run_dir)
    return result
