"""Co-design throughput: SAC gradient updates per second (paper networks, CPU, 1 thread) and
crawler-env transitions per second, and from them the projected wall time of the ``paper``
preset (1M transitions, one update per transition) on this machine and on 32 cores. Prints JSON.

Projection: wall = transitions x (sim seconds per transition / cores + seconds per update):
simulation parallel over cores, learning serial in the learner process (SB3 SAC on one thread).

Components (one env in-process, SAC on a dummy env):
  OMP_NUM_THREADS=1 python benchmarks/train_throughput.py [--batch 512] [--updates 200]
       [--model full|reduced --leg-mesh 16 --disk-mesh 25 --refactor-every 5 --steps-per-action 2
        --actions 20] [--design 1,0,0,2,2,0,0,0]
  Paper's env: --model reduced --leg-mesh 6 --disk-mesh 10 --steps-per-action 100

End to end (``softcrawl train`` itself: the ``paper`` preset with ``--n-envs`` envs in one worker
process per core, learning from the second round of transitions on, ``--rounds`` rounds):
  OMP_NUM_THREADS=1 python benchmarks/train_throughput.py --end-to-end --n-envs 96 --rounds 6
       [--stepping batched|serial|both]
``--stepping``: workers step their envs' robots as one batch (``batched``, the default of
:class:`softcrawl.envs.vec.SubprocessBackend`) or one env after another (``serial``, the code
before issue 18); ``both`` runs the two one after the other in this process (same seed, same
designs) and reports each and their ratio. Each run also reports the largest worker RSS
(sampled every 0.5 s).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time

import numpy as np
import torch

from softcrawl.codesign.config import SACConfig, preset
from softcrawl.codesign.sac import make_sac
from softcrawl.design.space import validate_design
from softcrawl.envs import BuildRobot, CrawlerEnv
from softcrawl.envs.vec import DesignVecEnv, SerialBackend
from softcrawl.robot import RobotConfig


def sac_updates_per_s(batch: int, updates: int, net_arch=(400, 200, 100)) -> float:
    """Gradient updates/s of SAC on a filled replay buffer (observations 44, actions 3)."""
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    class Dummy(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (44,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (3,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(44, np.float32), {}

        def step(self, a):
            return self.observation_space.sample(), 0.0, False, False, {}

    model = make_sac(DummyVecEnv([Dummy]), SACConfig(batch_size=batch, buffer_size=10_000, net_arch=tuple(net_arch)))
    rb, rng = model.replay_buffer, np.random.default_rng(0)
    for _ in range(2 * batch):
        o = rng.uniform(-1, 1, (1, 44)).astype(np.float32)
        rb.add(o, o, rng.uniform(-1, 1, (1, 3)), np.zeros(1), np.zeros(1), [{}])
    model._setup_learn(1)
    model.train(gradient_steps=5, batch_size=batch)  # warm-up
    t = time.perf_counter()
    model.train(gradient_steps=updates, batch_size=batch)
    return updates / (time.perf_counter() - t)


def env_rates(args) -> dict:
    cfg = RobotConfig(leg_mesh_size=args.leg_mesh, disk_mesh_size=args.disk_mesh, refactor_every=args.refactor_every,
                      model=args.model)
    design = validate_design(args.design)
    env = CrawlerEnv(BuildRobot(cfg), steps_per_action=args.steps_per_action, n_actions=args.actions, designs=[design])
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
    """Largest RSS (MB) of this process's children, sampled every ``period`` s in a thread."""

    def __init__(self, period: float = 0.5):
        import threading

        import psutil

        self.peak_mb, self._stop, self._me = 0.0, threading.Event(), psutil.Process()
        self._thread = threading.Thread(target=self._run, args=(period,), daemon=True)

    def _run(self, period: float) -> None:
        while not self._stop.wait(period):
            for child in self._me.children(recursive=True):
                try:
                    self.peak_mb = max(self.peak_mb, child.memory_info().rss / 2**20)
                except Exception:  # noqa: BLE001 - a child that just exited
                    pass

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()


def end_to_end(args, batched: bool = True) -> dict:
    """Transitions/s of :func:`softcrawl.codesign.training.train` (paper preset, ``n_envs`` envs,
    learning starts after the first round; workers step their robots as one batch if
    ``batched``) and the split of its wall time into learning (``updates / sac_updates_per_s``
    measured alone) and simulation."""
    import tempfile

    import softcrawl.envs.vec as vec
    from softcrawl.codesign.config import override
    from softcrawl.codesign.training import train

    n = args.n_envs
    cfg = override(preset("paper"), [f"n_envs={n}", f"total_steps={n * args.rounds}", f"sac.learning_starts={n}",
                                     f"checkpoint_every={10 * n * args.rounds}", f"snapshot_every={n}"])
    vec.BATCHED_WORKERS = batched
    with tempfile.TemporaryDirectory() as tmp, WorkerMemory() as memory:
        res = train(f"{tmp}/run", cfg, progress=True)
    updates_per_s = sac_updates_per_s(cfg.sac.batch_size, args.updates)
    learn_s = res.updates / updates_per_s
    sim_s_per_transition = (res.wall_seconds - learn_s) / res.steps
    cores = os.cpu_count()
    total = preset("paper").total_steps
    hours = {f"{c}_cores": total * (sim_s_per_transition * cores / c + 1 / updates_per_s) / 3600 for c in (cores, 32)}
    return {"stepping": "batched" if batched else "serial", "n_envs": n, "transitions": res.steps,
            "updates": res.updates, "wall_s": res.wall_seconds,
            "transitions_per_s": res.steps / res.wall_seconds, "sac_updates_per_s": updates_per_s,
            "learning_s_estimate": learn_s, "simulation_s_per_transition_all_cores": sim_s_per_transition,
            "episode_sim_steps_per_s_core": cfg.env.steps_per_action / (sim_s_per_transition * cores),
            "peak_rss_mb_learner": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "peak_rss_mb_worker": memory.peak_mb, "paper_preset_projected_hours": hours}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--updates", type=int, default=200)
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
    args = p.parse_args()
    torch.set_num_threads(1)
    if args.end_to_end:
        head = {"machine": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__}
        if args.stepping != "both":
            print(json.dumps({**head, **end_to_end(args, args.stepping == "batched")}, indent=2))
            return
        runs = {mode: end_to_end(args, mode == "batched") for mode in ("serial", "batched")}
        ratio = runs["batched"]["transitions_per_s"] / runs["serial"]["transitions_per_s"]
        print(json.dumps({**head, "runs": runs, "batched_over_serial_transitions_per_s": ratio}, indent=2))
        return
    updates = sac_updates_per_s(args.batch, args.updates)
    env = env_rates(args)
    transitions = preset("paper").total_steps
    hours = {f"{n}_cores": transitions * (1 / env["transitions_per_s"] / n + 1 / updates) / 3600
             for n in (os.cpu_count(), 32)}
    out = {"machine": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__,
           "torch_threads": torch.get_num_threads(), "batch": args.batch, "sac_updates_per_s": updates,
           "env": {**vars(args), **env}, "paper_preset_projected_hours": hours}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
