"""Co-design throughput: SAC gradient updates per second (paper networks, CPU, 1 thread) and
crawler-env transitions per second, and from them the projected wall time of the ``paper``
preset (1M transitions, one update per transition) on this machine and on 32 cores. Prints JSON.

Projection: wall = transitions x (sim seconds per transition / cores + seconds per update):
simulation parallel over cores, learning serial in the learner process (SB3 SAC on one thread).

Components (one env in-process, SAC on a dummy env):
  OMP_NUM_THREADS=1 python benchmarks/train_throughput.py [--batch 512] [--updates 200]
       [--threads 1] [--device cpu] [--autocast none|bf16]
       [--model full|reduced --leg-mesh 16 --disk-mesh 25 --refactor-every 5 --steps-per-action 2
        --actions 20] [--design 1,0,0,2,2,0,0,0]
  Paper's env: --model reduced --leg-mesh 6 --disk-mesh 10 --steps-per-action 100

End to end (``softcrawl train`` itself: ``--preset`` (default ``paper``) with ``--n-envs`` envs in
one worker process per core, learning from the second round of transitions on, ``--rounds``
rounds):
  OMP_NUM_THREADS=1 python benchmarks/train_throughput.py --end-to-end --n-envs 96 --rounds 6
       [--stepping batched|serial|both] [--preset paper|reference|crawl|demo] [--set KEY=VALUE]
       [--no-overlap] [--learner-cost]
``--set backend='"jax"'``: all envs one batch of the JAX engine in the learner's process on JAX's
default device (``--stepping`` does not apply; ``jax_precision`` as set, float64 by default).
``--stepping``: workers step their envs' robots as one batch (``batched``, the default of
:class:`softcrawl.envs.backends.subprocess.SubprocessBackend`) or one env after another (``serial``); ``both``
runs the two one after the other in this process (same seed, same designs) and reports each and
their ratio. Each run reports the wall seconds of its gradient updates (overlapped with the
simulation unless ``--no-overlap``), the largest worker RSS and the workers' CPU seconds
(sampled every 0.5 s).
``--learner-cost`` also runs the same without any update: the learner's share of the wall time is
``1 - wall(no updates) / wall(updates)``, and the ``paper`` preset is projected from the
simulation-only rate and the learner's rate (overlapped: the larger of the two; serial: their sum).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time

import numpy as np

from softcrawl.codesign.config import SACConfig, preset
from softcrawl.design.space import validate_design
from softcrawl.envs import BuildRobot, CrawlerEnv
from softcrawl.envs.backends import SerialBackend
from softcrawl.robot import RobotConfig

# torch, stable-baselines3 and what imports them are imported in the functions that use them:
# the env workers re-run this module's top-level imports (forkserver/spawn), and the peak
# worker RSS this benchmark reports should be that of a training worker, which has no torch.


def sac_updates_per_s(batch: int, updates: int, net_arch=(400, 200, 100), device: str = "cpu",
                      autocast: str = "none") -> float:
    """Gradient updates/s of SAC on a filled replay buffer (observations 44, actions 3) on torch
    ``device``; ``autocast="bf16"`` runs the updates under ``torch.autocast`` in bfloat16 (a probe
    of what a lower-precision learner would cost: no preset trains that way)."""
    import contextlib

    import gymnasium as gym
    import torch
    from stable_baselines3.common.vec_env import DummyVecEnv

    class Dummy(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (44,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (3,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(44, np.float32), {}

        def step(self, a):
            return self.observation_space.sample(), 0.0, False, False, {}

    from softcrawl.codesign.sac import make_sac

    model = make_sac(DummyVecEnv([Dummy]), SACConfig(batch_size=batch, buffer_size=10_000, net_arch=tuple(net_arch),
                                                    device=device))
    rb, rng = model.replay_buffer, np.random.default_rng(0)
    for _ in range(2 * batch):
        o = rng.uniform(-1, 1, (1, 44)).astype(np.float32)
        rb.add(o, o, rng.uniform(-1, 1, (1, 3)), np.zeros(1), np.zeros(1), [{}])
    model._setup_learn(1)
    precision = (torch.autocast(torch.device(device).type, dtype=torch.bfloat16) if autocast == "bf16"
                 else contextlib.nullcontext())
    with precision:
        model.train(gradient_steps=5, batch_size=batch)  # warm-up
        t = time.perf_counter()
        model.train(gradient_steps=updates, batch_size=batch)
    return updates / (time.perf_counter() - t)


def env_rates(args) -> dict:
    cfg = RobotConfig(leg_mesh_size=args.leg_mesh, disk_mesh_size=args.disk_mesh, refactor_every=args.refactor_every,
                      model=args.model)
    design = validate_design(args.design)
    env = CrawlerEnv(BuildRobot(cfg), steps_per_action=args.steps_per_action, n_actions=args.actions, designs=[design])
    from softcrawl.envs.vec import DesignVecEnv

    venv = DesignVecEnv(SerialBackend([lambda: env]))
    venv.reset()  # builds the robot (not timed)
    rng = np.random.default_rng(0)
    t, n = time.perf_counter(), 0
    for _ in range(args.actions):  # one whole episode incl. the auto-reset (settling) at its end
        venv.step(rng.uniform(-1, 1, (1, 3)).astype(np.float32))
        n += 1
    dt = time.perf_counter() - t
    return {"transitions_per_s": n / dt, "sim_steps_per_s": n * args.steps_per_action / dt,
            "episode_s": dt, "nodes": int(env.episode.robot.model.n_nodes)}


class WorkerMemory:
    """Largest RSS (MB) of this process's children and the CPU seconds (user + system) each has
    used, sampled every ``period`` s in a thread (``cpu_s``: their sum at the last samples)."""

    def __init__(self, period: float = 0.5):
        import threading

        import psutil

        self.peak_mb, self._stop, self._me = 0.0, threading.Event(), psutil.Process()
        self._cpu: dict[int, float] = {}
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)

    @property
    def cpu_s(self) -> float:
        return sum(self._cpu.values())

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            for child in self._me.children(recursive=True):
                try:
                    self.peak_mb = max(self.peak_mb, child.memory_info().rss / 2**20)
                    t = child.cpu_times()
                    self._cpu[child.pid] = t.user + t.system
                except Exception:  # noqa: BLE001 - a child that just exited
                    pass

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def end_to_end(args, batched: bool = True, updates: bool = True) -> dict:
    """Transitions/s of :func:`softcrawl.codesign.training.train` (preset ``args.preset``,
    ``n_envs`` envs, learning from the second round on, or never if not ``updates``; workers
    step their robots as one batch if ``batched``), the wall seconds of its gradient updates
    (overlapped with the simulation unless ``--no-overlap``) and the peak worker RSS."""
    import tempfile

    import softcrawl.envs.backends.subprocess as subprocess_backend
    from softcrawl.codesign.config import override
    from softcrawl.codesign.training import train

    n = args.n_envs
    total = n * args.rounds
    sets = [f"n_envs={n}", f"total_steps={total}", f"sac.learning_starts={n if updates else total}",
            f"checkpoint_every={10 * total}", f"snapshot_every={n}", f"sac.overlap={str(not args.no_overlap).lower()}"]
    cfg = override(preset(args.preset), sets + list(args.set or []))
    subprocess_backend.BATCHED_WORKERS = batched
    cpu0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp, WorkerMemory() as memory:
        res = train(f"{tmp}/run", cfg, progress=True)
    sim_s_per_transition = res.wall_seconds / res.steps
    cores = os.cpu_count()
    return {"preset": args.preset, "backend": cfg.backend, "stepping": "batched" if batched else "serial", "n_envs": n,
            "transitions": res.steps, "updates": res.updates, "overlap": cfg.sac.overlap, "wall_s": res.wall_seconds,
            "transitions_per_s": res.steps / res.wall_seconds, "learner_s": res.learner_seconds,
            "learner_share_of_wall_upper_bound": res.learner_seconds / res.wall_seconds,
            "wall_s_per_transition_all_cores": sim_s_per_transition,
            "sim_steps_per_s_core": cfg.env.steps_per_action / (sim_s_per_transition * cores),
            "peak_rss_mb_learner": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "peak_rss_mb_worker": memory.peak_mb, "worker_cpu_s": memory.cpu_s,
            "learner_process_cpu_s": time.process_time() - cpu0}


def project(run: dict, updates_per_s: float, cores: int) -> dict:
    """Projected hours of the ``paper`` preset (1M transitions, one update per transition) from
    an end-to-end run without updates (simulation only, all cores) and the learner's rate: the
    simulation spreads over ``c`` cores, the learner is one thread, overlapped (max) or not (sum)."""
    total = preset("paper").total_steps
    sim = run["wall_s_per_transition_all_cores"] * cores
    return {f"{c}_cores": {"overlapped": total * max(sim / c, 1 / updates_per_s) / 3600,
                           "serial": total * (sim / c + 1 / updates_per_s) / 3600} for c in (cores, 32)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--threads", type=int, default=1, help="torch threads of the SAC updates (components)")
    p.add_argument("--updates", type=int, default=200)
    p.add_argument("--device", default="cpu", help="torch device of the SAC updates (components; end to end: "
                                                    "--set sac.device=...)")
    p.add_argument("--autocast", choices=("none", "bf16"), default="none",
                   help="components: SAC updates under torch.autocast in bfloat16 (a probe; no preset uses it)")
    p.add_argument("--model", choices=("full", "reduced"), default="full")
    p.add_argument("--leg-mesh", type=float, default=16)
    p.add_argument("--disk-mesh", type=float, default=25)
    p.add_argument("--refactor-every", type=int, default=None,
                   help="factorization reuse of the full-order bodies (default: the robot's, 1 full / 5 reduced disk)")
    p.add_argument("--steps-per-action", type=int, default=2)
    p.add_argument("--actions", type=int, default=20)
    p.add_argument("--design", default="1,0,0,2,2,0,0,0")
    p.add_argument("--end-to-end", action="store_true", help="time softcrawl train itself (paper preset)")
    p.add_argument("--n-envs", type=int, default=96)
    p.add_argument("--rounds", type=int, default=6, help="transitions per env (end to end)")
    p.add_argument("--stepping", choices=("batched", "serial", "both"), default="batched",
                   help="workers step their robots as one batch or one env after another (end to end)")
    p.add_argument("--preset", default="paper", help="end to end: the preset to time (default paper)")
    p.add_argument("--set", action="append", help="end to end: extra section.field=value settings")
    p.add_argument("--no-overlap", action="store_true", help="end to end: updates after each step, not overlapped")
    p.add_argument("--learner-cost", action="store_true",
                   help="end to end: also run without updates; report the learner's share of the wall time "
                        "and the paper preset's projection")
    args = p.parse_args()
    import torch

    torch.set_num_threads(1 if args.end_to_end else args.threads)
    if args.end_to_end:
        head = {"machine": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__}
        modes = ("serial", "batched") if args.stepping == "both" else (args.stepping,)
        runs = {mode: end_to_end(args, mode == "batched") for mode in modes}
        out = {**head, "runs": runs}
        if len(runs) == 2:
            out["batched_over_serial_transitions_per_s"] = (runs["batched"]["transitions_per_s"]
                                                            / runs["serial"]["transitions_per_s"])
        if args.learner_cost:
            last = runs[modes[-1]]
            sim_only = end_to_end(args, modes[-1] == "batched", updates=False)
            rate = sac_updates_per_s(preset(args.preset).sac.batch_size, args.updates)
            out["without_updates"] = sim_only
            out["learner_share_of_wall"] = 1 - sim_only["wall_s"] / last["wall_s"]
            out["sac_updates_per_s"] = rate
            out["paper_preset_projected_hours"] = project(sim_only, rate, os.cpu_count())
        print(json.dumps(out, indent=2))
        return
    updates = sac_updates_per_s(args.batch, args.updates, device=args.device, autocast=args.autocast)
    env = env_rates(args)
    transitions = preset("paper").total_steps
    hours = {f"{n}_cores": transitions * (1 / env["transitions_per_s"] / n + 1 / updates) / 3600
             for n in (os.cpu_count(), 32)}
    out = {"machine": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
           "torch_threads": torch.get_num_threads(), "device": args.device, "autocast": args.autocast,
           "batch": args.batch,
           "sac_updates_per_s": updates,
           "env": {**vars(args), **env}, "paper_preset_projected_hours": hours}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
