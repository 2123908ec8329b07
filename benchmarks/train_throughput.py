"""Co-design throughput: SAC gradient updates per second of the learner (paper networks, batch
512) and crawler-env transitions per second, and from them the projected wall time of the
``paper`` preset (1M transitions, one update per transition) on this machine and on 32 cores.
Prints JSON.

Learners (``--learner``, ``sac.learner``): ``sbx`` (SBX's SAC on JAX, all gradient steps of a
vectorised step in one compiled call: ``--grad-steps``, default 96 = the paper's envs) and
``torch`` (stable-baselines3's SAC with the split learning rates and the critics' weights frozen
during the actor's step); ``both`` (the default) measures them in one run, alternating
``--repeats`` blocks of ``--updates`` updates each, and reports their ratio per wall second and
per CPU second of this process (the latter is what a shared machine cannot skew: one thread,
``--threads``, each). XLA may still run the Python thread and its compute thread side by side:
pin the process to one core (``taskset -c 1 ...``) to measure "one CPU thread".

Arithmetic bound (``arithmetic`` in the output, with ``--no-env``): the floating-point operations of
one update, counted by XLA's cost analysis of the JAX learner's compiled update
(``flops_per_update``; about 1.91 GFLOP for the paper's networks at batch 512: critic, actor and
target passes), the float32 matrix-product rate of this core at the networks' layer shapes for
numpy's BLAS, torch and XLA (``matmul_gflops``, the threads as set), and from the fastest of them
the updates per CPU second no learner can exceed on this core (``bound_updates_per_s``) and each
learner's share of it (``share_of_bound``, from its updates per CPU second).

Projection: wall = transitions x (sim seconds per transition / cores + seconds per update):
simulation parallel over cores, learning serial in the learner process.

Components (one env in-process, SAC on a dummy env):
  OMP_NUM_THREADS=1 python benchmarks/train_throughput.py [--learner both|sbx|torch] [--batch 512]
       [--updates 192] [--grad-steps 96] [--repeats 3] [--threads 1] [--device cpu|gpu|gpu:N]
       [--model full|reduced --leg-mesh 16 --disk-mesh 25 --refactor-every 5 --steps-per-action 2
        --actions 20] [--design 1,0,0,2,2,0,0,0] [--no-env]
  Paper's env: --model reduced --leg-mesh 6 --disk-mesh 10 --steps-per-action 100
  The learner on a GPU: --learner sbx --device gpu --no-env

End to end (``softcrawl train`` itself: ``--preset`` (default ``paper``) with ``--n-envs`` envs in
one worker process per core, learning from the second round of transitions on, ``--rounds``
rounds; ``--learner both`` runs the torch learner, then the JAX one, same seed, one after the other):
  OMP_NUM_THREADS=1 python benchmarks/train_throughput.py --end-to-end --n-envs 96 --rounds 6
       [--learner sbx|torch|both] [--stepping batched|serial|both] [--preset paper|reference|crawl|demo]
       [--set KEY=VALUE] [--no-overlap] [--learner-cost]
``--set backend='"jax"'``: all envs one batch of the JAX engine in the learner's process on JAX's
default device (``--stepping`` does not apply; ``jax_precision`` as set, float64 by default).
``--stepping``: workers step their envs' robots as one batch (``batched``, the default of
:class:`softcrawl.envs.backends.subprocess.SubprocessBackend`) or one env after another (``serial``); ``both``
runs the two one after the other in this process (same seed, same designs) and reports each and
their ratio. Each run reports the wall seconds of its gradient updates (overlapped with the
simulation unless ``--no-overlap``), the learner process's CPU seconds, the largest worker RSS and
the workers' CPU seconds (sampled every 0.5 s); ``learner_cpu_share`` is the learner process's
share of all CPU seconds used.
``--learner-cost`` also runs the same without any update: the learner's share of the wall time is
``1 - wall(no updates) / wall(updates)``, and the ``paper`` preset is projected from the
simulation-only rate and the learner's rate (overlapped: the larger of the two; serial: their sum).

The two training loops on the JAX backend (``softcrawl train`` itself, ``backend="jax"`` on JAX's
default device, the learner's ``sac.device`` as set): episode-at-once (``rollout="episode"``: every
env's whole episode in one compiled call, replay buffer and updates on the learner's device) and
per-action (``rollout="action"``: SB3's loop), one after the other in this process, same seed, at
each of ``--jax-envs`` env counts, ``--episodes`` rounds of one episode per env each, learning from
the second round on (``--set backend=...`` times another backend the same way):
  python benchmarks/train_throughput.py --jax-loops [--jax-envs 96,1024] [--episodes 2] [--preset paper]
       [--rollouts action,episode]
       [--set KEY=VALUE]
Each run reports its end-to-end transitions/s (``transitions_per_s``: all transitions over the
call's wall time, start-up, settling and compilation included) and ``steady_transitions_per_s``
(the transitions after the first round over the wall time since its end: updates included),
``round_s`` (the wall seconds from the end of each round's episodes to the end of the next
round's: one round's updates and the next one's episodes; one that compiled something stands
out) and ``median_round_transitions_per_s`` (a round's transitions over the median of those:
the rate of a long run once nothing compiles any more),
robot steps per second, the learner's wall seconds and its updates; ``episode_over_action`` is the
ratio of the two loops' steady rates. On a CPU the JAX engine makes a few dozen robot steps per
second, so shrink the episode there (this machine's figures in benchmarks/RESULTS.md):
  python benchmarks/train_throughput.py --jax-loops --preset crawl --set env.n_actions=2 \
       env.steps_per_action=1 env.settle_max_seconds=0.04
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import time
from dataclasses import replace

import numpy as np

from softcrawl.codesign.config import SACConfig, preset
from softcrawl.design.space import validate_design
from softcrawl.envs import BuildRobot, CrawlerEnv
from softcrawl.envs.backends import SerialBackend
from softcrawl.robot import RobotConfig

# JAX, torch, stable-baselines3 and what imports them are imported in the functions that use
# them: the env workers re-run this module's top-level imports (forkserver/spawn), and the peak
# worker RSS this benchmark reports should be that of a training worker, which has neither.


def _learner_on_dummy(learner: str, batch: int, net_arch, device: str):
    """A learner of kind ``learner`` ("sbx" or "torch") on a one-env dummy with the crawler's
    spaces (observations 44, actions 3) and a replay buffer of 4 batches of random data."""
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.sac import make_sac

    class Dummy(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (44,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (3,), np.float32)

        def reset(self, *, seed=None, options=None):
            return np.zeros(44, np.float32), {}

        def step(self, a):
            return self.observation_space.sample(), 0.0, False, False, {}

    cfg = SACConfig(batch_size=batch, buffer_size=10_000, net_arch=tuple(net_arch), device=device, overlap=False,
                    learner=learner)
    model = make_sac(DummyVecEnv([Dummy]), cfg, seed=0)
    rb, rng = model.replay_buffer, np.random.default_rng(0)
    for _ in range(4 * batch):
        o = rng.uniform(-1, 1, (1, 44)).astype(np.float32)
        rb.add(o, o, rng.uniform(-1, 1, (1, 3)), np.zeros(1), np.zeros(1), [{}])
    model._setup_learn(1)
    return model


def sac_updates_per_s(learners, batch: int, updates: int, grad_steps: int = 96, repeats: int = 1,
                      net_arch=(400, 200, 100), device: str = "cpu") -> dict:
    """Gradient updates per wall second and per CPU second of this process for each learner of
    ``learners`` (``"sbx"``, ``"torch"``), on the device ``device`` (torch's ``cuda`` for
    ``gpu``), in ``repeats`` rounds that alternate the learners (each round runs ``updates``
    updates of each: the JAX one in calls of ``grad_steps`` compiled updates, the torch one as
    SB3 makes them). Medians over the rounds; the first call of each (compilation,
    warm-up) is not timed."""
    models = {k: _learner_on_dummy(k, batch, net_arch, device) for k in learners}
    per_call = {k: grad_steps if k == "sbx" else updates for k in learners}
    for k, m in models.items():
        m.train(gradient_steps=per_call[k], batch_size=batch)  # compile / warm up
    wall, cpu = {k: [] for k in learners}, {k: [] for k in learners}
    for _ in range(repeats):
        for k, m in models.items():
            calls = max(1, updates // per_call[k])
            t, c = time.perf_counter(), time.process_time()
            for _ in range(calls):
                m.train(gradient_steps=per_call[k], batch_size=batch)  # returns when its updates are done
            wall[k].append(calls * per_call[k] / (time.perf_counter() - t))
            cpu[k].append(calls * per_call[k] / (time.process_time() - c))
    out = {k: {"updates_per_s": statistics.median(wall[k]), "updates_per_cpu_s": statistics.median(cpu[k]),
               "rounds_updates_per_s": wall[k], "grad_steps_per_call": per_call[k]} for k in learners}
    if len(learners) == 2:
        out["sbx_over_torch"] = {
            "updates_per_s": out["sbx"]["updates_per_s"] / out["torch"]["updates_per_s"],
            "updates_per_cpu_s": out["sbx"]["updates_per_cpu_s"] / out["torch"]["updates_per_cpu_s"],
            "rounds_updates_per_s": [a / b for a, b in zip(wall["sbx"], wall["torch"])]}
    return out


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


def end_to_end(args, batched: bool = True, updates: bool = True, learner: str = "sbx") -> dict:
    """Transitions/s of :func:`softcrawl.codesign.training.train` (preset ``args.preset``,
    ``n_envs`` envs, learning from the second round on, or never if not ``updates``; workers
    step their robots as one batch if ``batched``; the ``learner``, "sbx" or "torch"), the wall
    seconds of its gradient updates (overlapped with the simulation unless ``--no-overlap``),
    the CPU seconds of the learner process and of the workers, and the peak worker RSS."""
    import tempfile

    import softcrawl.envs.backends.subprocess as subprocess_backend
    from softcrawl.codesign.config import override
    from softcrawl.codesign.training import train

    n = args.n_envs
    total = n * args.rounds
    sets = [f"n_envs={n}", f"total_steps={total}", f"sac.learning_starts={n if updates else total}",
            f"checkpoint_every={10 * total}", f"snapshot_every={n}", f"sac.overlap={str(not args.no_overlap).lower()}"]
    cfg = override(preset(args.preset), sets + list(args.set or []))
    cfg = replace(cfg, sac=replace(cfg.sac, learner=learner))
    subprocess_backend.BATCHED_WORKERS = batched
    cpu0 = time.process_time()
    with tempfile.TemporaryDirectory() as tmp, WorkerMemory() as memory:
        res = train(f"{tmp}/run", cfg, progress=True)
    sim_s_per_transition = res.wall_seconds / res.steps
    cores = os.cpu_count()
    learner_cpu = time.process_time() - cpu0
    return {"preset": args.preset, "learner": learner, "backend": cfg.backend,
            "stepping": "batched" if batched else "serial", "n_envs": n,
            "transitions": res.steps, "updates": res.updates, "overlap": cfg.sac.overlap, "wall_s": res.wall_seconds,
            "transitions_per_s": res.steps / res.wall_seconds, "learner_s": res.learner_seconds,
            "learner_share_of_wall_upper_bound": res.learner_seconds / res.wall_seconds,
            "wall_s_per_transition_all_cores": sim_s_per_transition,
            "sim_steps_per_s_core": cfg.env.steps_per_action / (sim_s_per_transition * cores),
            "peak_rss_mb_learner": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "peak_rss_mb_worker": memory.peak_mb, "worker_cpu_s": memory.cpu_s,
            "learner_process_cpu_s": learner_cpu, "learner_cpu_share": learner_cpu / (learner_cpu + memory.cpu_s)}


def jax_loops(args) -> dict:
    """Transitions/s of both training loops on the JAX backend at each of ``args.jax_envs`` env
    counts (module docstring): ``"episode/N"`` and ``"action/N"`` runs and
    ``"episode_over_action/N"``, the ratio of their steady rates."""
    import tempfile

    import softcrawl.codesign.training as training
    from softcrawl.codesign.config import override

    stamps: list[tuple[float, int]] = []
    on_step = training.CodesignCallback._on_step

    def stamped(callback):
        stamps.append((time.perf_counter(), callback.num_timesteps))
        return on_step(callback)

    training.CodesignCallback._on_step = stamped
    out = {}
    try:
        for n in args.jax_envs:
            for rollout in args.rollouts:
                cfg = override(override(preset(args.preset), ['backend="jax"']),
                               [f"n_envs={n}", f'rollout="{rollout}"', *(args.set or [])])
                per_round = n * cfg.env.n_actions
                total = per_round * args.episodes
                cfg = override(cfg, [f"total_steps={total}", f"sac.learning_starts={per_round}",
                                     f"checkpoint_every={10 * total}", f"snapshot_every={per_round}"])
                stamps.clear()
                with tempfile.TemporaryDirectory() as tmp:
                    res = training.train(f"{tmp}/run", cfg, progress=False)
                t1 = max(t for t, steps in stamps if steps <= per_round)
                steady = (res.steps - per_round) / (stamps[-1][0] - t1) if res.steps > per_round else None
                ends = [max(t for t, steps in stamps if steps <= k * per_round) for k in range(1, args.episodes + 1)
                        if any(steps <= k * per_round for _, steps in stamps)]
                rounds = np.diff(ends).tolist()
                out[f"{rollout}/{n}"] = {
                    "rollout": rollout, "n_envs": n, "transitions": res.steps, "wall_s": res.wall_seconds,
                    "transitions_per_s": res.steps / res.wall_seconds, "steady_transitions_per_s": steady,
                    "round_s": rounds,
                    "median_round_transitions_per_s": per_round / float(np.median(rounds)) if rounds else None,
                    "robot_steps_per_s": res.steps * cfg.env.steps_per_action / res.wall_seconds,
                    "updates": res.updates, "learner_s": res.learner_seconds, "n_actions": cfg.env.n_actions,
                    "steps_per_action": cfg.env.steps_per_action, "preset": args.preset, "set": args.set or [],
                    "device": _jax_device()}
            if len(args.rollouts) == 2:
                a, e = out[f"action/{n}"]["steady_transitions_per_s"], out[f"episode/{n}"]["steady_transitions_per_s"]
                out[f"episode_over_action/{n}"] = e / a if a and e else None
    finally:
        training.CodesignCallback._on_step = on_step
    return out


def _jax_device() -> str:
    import jax

    d = jax.devices()[0]
    return f"{d.platform}:{d.id} ({d.device_kind})"


def project(run: dict, updates_per_s: float, cores: int) -> dict:
    """Projected hours of the ``paper`` preset (1M transitions, one update per transition) from
    an end-to-end run without updates (simulation only, all cores) and the learner's rate: the
    simulation spreads over ``c`` cores, the learner is one thread, overlapped (max) or not (sum)."""
    total = preset("paper").total_steps
    sim = run["wall_s_per_transition_all_cores"] * cores
    return {f"{c}_cores": {"overlapped": total * max(sim / c, 1 / updates_per_s) / 3600,
                           "serial": total * (sim / c + 1 / updates_per_s) / 3600} for c in (cores, 32)}


def _sbx_update_flops(batch: int, net_arch, device: str) -> float:
    """Floating-point operations of one compiled update of the JAX learner (XLA's cost analysis
    of SBX's ``_train`` with one gradient step), FLOP."""
    model = _learner_on_dummy("sbx", batch, net_arch, device)
    calls = []
    model._train = lambda *a, _train=model._train: calls.append(a) or _train(*a)
    model.train(gradient_steps=1, batch_size=batch)
    jitted = next(k.__dict__["_train"].__func__ for k in type(model).__mro__ if "_train" in k.__dict__)
    with model.on_device():
        cost = jitted.lower(type(model), *calls[0]).compile().cost_analysis()
    return float((cost[0] if isinstance(cost, list) else cost)["flops"])


def matmul_gflops(batch: int, net_arch, obs_dim: int = 44, act_dim: int = 3, seconds: float = 0.5) -> dict:
    """float32 matrix-product rate, GFLOP per CPU second of this process, of numpy's BLAS, torch
    and XLA (jitted) on the forward shapes of the critic's layers (``batch x (obs + act) ->
    net_arch``), their FLOPs summed over the layers, on the threads each library is set to (one:
    per CPU second is per thread, what a shared machine cannot skew), all on the CPU."""
    import jax
    import torch

    dims = (obs_dim + act_dim, *net_arch)
    rng = np.random.default_rng(0)
    xs = [rng.standard_normal((batch, a)).astype(np.float32) for a in dims[:-1]]
    ws = [rng.standard_normal((a, b)).astype(np.float32) for a, b in zip(dims[:-1], dims[1:])]
    flops = sum(2.0 * batch * a * b for a, b in zip(dims[:-1], dims[1:]))
    jit_layers = jax.jit(lambda xs, ws: [x @ w for x, w in zip(xs, ws)])
    txs, tws = [torch.from_numpy(x) for x in xs], [torch.from_numpy(w) for w in ws]
    cpu = jax.devices("cpu")[0]  # not JAX's default device: on a GPU machine that is the GPU
    jxs, jws = [jax.device_put(x, cpu) for x in xs], [jax.device_put(w, cpu) for w in ws]
    kernels = {"numpy": lambda: [x @ w for x, w in zip(xs, ws)],
               "torch": lambda: [x @ w for x, w in zip(txs, tws)],
               "jax": lambda: jax.block_until_ready(jit_layers(jxs, jws))}
    out = {}
    for name, run in kernels.items():
        run()
        n, t = 0, time.process_time()
        while time.process_time() - t < seconds:
            run()
            n += 1
        out[name] = n * flops / (time.process_time() - t) / 1e9
    return out


def arithmetic_bound(rates: dict, batch: int, net_arch, device: str) -> dict:
    """The updates/s this core's fastest float32 matrix product allows (module docstring)."""
    flops = _sbx_update_flops(batch, net_arch, device)
    gflops = matmul_gflops(batch, net_arch)
    bound = max(gflops.values()) * 1e9 / flops
    return {"flops_per_update": flops, "matmul_gflops": gflops, "bound_updates_per_s": bound,
            "share_of_bound": {k: rates[k]["updates_per_cpu_s"] / bound for k in ("sbx", "torch") if k in rates}}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--learner", choices=("both", "sbx", "torch"), default="both",
                   help="the JAX learner (sbx), the torch one, or both in one run")
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--threads", type=int, default=1, help="CPU threads of the learners (XLA's and torch's)")
    p.add_argument("--updates", type=int, default=192, help="updates per learner and round (components)")
    p.add_argument("--grad-steps", type=int, default=96,
                   help="the JAX learner's gradient steps per compiled call (components; end to end: n_envs)")
    p.add_argument("--repeats", type=int, default=3, help="rounds alternating the learners (components)")
    p.add_argument("--device", default="cpu", help="JAX device of the SAC updates: cpu, gpu, gpu:N (components; "
                                                    "end to end: --set sac.device=...)")
    p.add_argument("--no-env", action="store_true", help="components: the learners only, no env")
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
    p.add_argument("--jax-loops", action="store_true",
                   help="time both training loops (episode-at-once, per-action) on the JAX backend")
    p.add_argument("--rollouts", type=lambda v: v.split(","), default=["action", "episode"],
                   help="--jax-loops: the loops timed (action, episode or both, comma-separated)")
    p.add_argument("--jax-envs", type=lambda v: [int(x) for x in v.split(",")], default=[96, 1024],
                   help="--jax-loops: env counts, comma-separated (default 96,1024)")
    p.add_argument("--episodes", type=int, default=2, help="--jax-loops: rounds of one episode per env")
    p.add_argument("--learner-cost", action="store_true",
                   help="end to end: also run without updates; report the learner's share of the wall time "
                        "and the paper preset's projection")
    args = p.parse_args()
    import jax
    import torch

    from softcrawl.codesign.sac import learner_module

    for name in ("sbx", "torch"):
        learner_module(name).configure_threads(1 if args.end_to_end or args.jax_loops else args.threads)
    learners = ("torch", "sbx") if args.learner == "both" else (args.learner,)
    head = {"machine": platform.platform(), "cpus": os.cpu_count(), "torch": torch.__version__, "jax": jax.__version__,
            "threads": 1 if args.end_to_end or args.jax_loops else args.threads}
    if args.jax_loops:
        print(json.dumps({**head, "runs": jax_loops(args)}, indent=2))
        return
    if args.end_to_end:
        modes = ("serial", "batched") if args.stepping == "both" else (args.stepping,)
        runs = {f"{mode}/{k}": end_to_end(args, mode == "batched", learner=k) for mode in modes for k in learners}
        out = {**head, "runs": runs}
        if len(modes) == 2:
            out["batched_over_serial_transitions_per_s"] = {
                k: runs[f"batched/{k}"]["transitions_per_s"] / runs[f"serial/{k}"]["transitions_per_s"]
                for k in learners}
        if len(learners) == 2:
            out["sbx_over_torch_transitions_per_s"] = {
                mode: runs[f"{mode}/sbx"]["transitions_per_s"] / runs[f"{mode}/torch"]["transitions_per_s"]
                for mode in modes}
        if args.learner_cost:
            sim_only = end_to_end(args, modes[-1] == "batched", updates=False, learner=learners[-1])
            rates = sac_updates_per_s(learners, preset(args.preset).sac.batch_size, args.updates, args.grad_steps)
            out["without_updates"] = sim_only
            out["learner_share_of_wall"] = {k: 1 - sim_only["wall_s"] / runs[f"{modes[-1]}/{k}"]["wall_s"]
                                            for k in learners}
            out["sac"] = rates
            out["paper_preset_projected_hours"] = {k: project(sim_only, rates[k]["updates_per_s"], os.cpu_count())
                                                   for k in learners}
        print(json.dumps(out, indent=2))
        return
    rates = sac_updates_per_s(learners, args.batch, args.updates, args.grad_steps, args.repeats, device=args.device)
    out = {**head, "device": args.device, "batch": args.batch, "sac": rates}
    if args.no_env and args.device == "cpu":
        out["arithmetic"] = arithmetic_bound(rates, args.batch, (400, 200, 100), args.device)
    if not args.no_env:
        env = env_rates(args)
        transitions = preset("paper").total_steps
        out["env"] = {**vars(args), **env}
        out["paper_preset_projected_hours"] = {
            k: {f"{n}_cores": transitions * (1 / env["transitions_per_s"] / n + 1 / rates[k]["updates_per_s"]) / 3600
                for n in (os.cpu_count(), 32)} for k in learners}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
