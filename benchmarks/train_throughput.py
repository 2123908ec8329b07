"""Co-design throughput: SAC gradient updates per second (paper networks, CPU, 1 thread) and
crawler-env transitions per second, and from them the projected wall time of the ``paper``
preset (1M transitions, one update per transition) on this machine and on 32 cores. Prints JSON.

Projection: wall = transitions x (sim seconds per transition / cores + seconds per update):
simulation parallel over cores, learning serial in the learner process (SB3 SAC on one thread).

Usage: OMP_NUM_THREADS=1 python benchmarks/train_throughput.py [--batch 512] [--updates 200]
       [--model full|reduced --leg-mesh 16 --disk-mesh 25 --refactor-every 5 --steps-per-action 2
        --actions 20] [--design 1,0,0,2,2,0,0,0]
Paper's env: --model reduced --leg-mesh 6 --disk-mesh 10 --steps-per-action 100
"""

from __future__ import annotations

import argparse
import json
import os
import platform
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
    args = p.parse_args()
    torch.set_num_threads(1)
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
