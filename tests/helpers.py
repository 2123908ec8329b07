"""Helpers shared by several test modules (importable as ``helpers``: pytest puts ``tests/`` on
``sys.path``)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import numpy as np


def benchmark_module(name: str):
    """The script ``benchmarks/NAME.py`` loaded as a module (``benchmarks/`` is no package),
    for tests of its functions."""
    path = Path(__file__).resolve().parents[1] / "benchmarks" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"benchmark_{name}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def restored_learner(run):
    """``(model, sampler, Run)``: a freshly built learner and design sampler of the training run
    in folder ``run``, with its newest complete checkpoint loaded (the envs are closed again)."""
    from softcrawl.codesign.factory import make_sampler, make_vec_env
    from softcrawl.codesign.run import Run
    from softcrawl.codesign.sac import make_sac

    r = Run(run)
    cfg = r.read_config()
    sampler = make_sampler(cfg)
    venv = make_vec_env(cfg, sampler)
    try:
        model = make_sac(venv, cfg.sac, seed=cfg.seed, rollout=cfg.rollout)
        r.load_checkpoint(r.latest_checkpoint(), model, sampler)
    finally:
        venv.close()
    return model, sampler, r


class Evil:
    """Unpickling this creates ``self.marker``: proof that a file ran code when loaded."""

    def __init__(self, marker: Path):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def rehash(ck: Path) -> None:
    """Recompute a checkpoint's manifest (a crafted folder can do that too)."""
    from softcrawl.codesign.run import _sha256

    m = json.loads((ck / "manifest.json").read_text())
    m["files"] = {f: _sha256(ck / f) for f in m["files"]}
    (ck / "manifest.json").write_text(json.dumps(m))


def file_tree(root: Path) -> dict:
    """``{relative path: size in bytes (-1 for a folder)}`` of everything below ``root``."""
    return {str(p.relative_to(root)): (p.stat().st_size if p.is_file() else -1) for p in root.rglob("*")}


def one_line_error(capsys, rc: int, *needles: str) -> str:
    """Assert a CLI refusal: exit code 2, one stderr line without traceback, containing each
    of ``needles``; returns the line."""
    err = capsys.readouterr().err.strip()
    assert rc == 2, err
    assert "\n" not in err and "Traceback" not in err, err
    for n in needles:
        assert n in err, err
    return err


def fake_sim_run(folder: Path, actions, hold=1.0, dt=0.01, speed_mm_s=2.0) -> Path:
    """A minimal ``softcrawl simulate``-style output ``folder`` with a trajectory.csv of the gait
    ``actions (n, 3)`` kPa held ``hold`` s each, sampled every ``dt`` s: commanded pressures, applied
    ones rate-limited to 150 kPa/s, x moving at ``speed_mm_s``."""
    folder.mkdir(parents=True)
    n = int(round(len(actions) * hold / dt))
    rows, p = [], np.zeros(3)
    for k in range(n + 1):
        t = k * dt
        cmd = actions[min(int((t - 1e-9) / hold), len(actions) - 1)] if k else np.zeros(3)
        p = p + np.clip(cmd - p, -150 * dt, 150 * dt)
        rows.append([t, speed_mm_s * t, 0, 30, *cmd, *p, 10])
    head = "t,x,y,z,cmd_1,cmd_2,cmd_3,applied_1,applied_2,applied_3,contacts"
    np.savetxt(folder / "trajectory.csv", np.array(rows), delimiter=",", header=head, comments="", fmt="%.6g")
    return folder


def groundtruth_of_tried(run: Path, folder: Path) -> list[tuple]:
    """A finished ground truth in ``folder`` of the designs training run ``run`` tried, with
    made-up rewards: a design's reward (cm) is its index in the returned list (the run's
    designs, most probable first)."""
    from softcrawl.codesign.groundtruth import DesignResult, GroundTruthConfig, PeriodicGait, run_groundtruth
    from softcrawl.codesign.report import top_designs

    tried = [tuple(row["design"]) for row in top_designs(run, 10**6)]
    score = {d: float(i) for i, d in enumerate(tried)}
    fake = lambda d, _cfg: DesignResult(tuple(d), score[tuple(d)], PeriodicGait.paper_cycle().to_dict(), 3, "step",
                                        10, 2, 80.0, 0.1).to_dict()
    run_groundtruth(tried, folder, GroundTruthConfig(baseline_phases=()), executor="serial", task=fake,
                    progress=False, refs=False)
    return tried


def tiny_env_class():
    """A gymnasium env class of 5-step episodes with the crawler's spaces (44 observations, 3
    actions; reward: the first action component)."""
    import gymnasium as gym
    import numpy as np

    class Tiny(gym.Env):
        observation_space = gym.spaces.Box(-1, 1, (44,), np.float32)
        action_space = gym.spaces.Box(-1, 1, (3,), np.float32)

        def reset(self, *, seed=None, options=None):
            self.k = 0
            return np.zeros(44, np.float32), {}

        def step(self, a):
            self.k += 1
            return np.full(44, 0.1 * self.k, np.float32), float(a[0]), False, self.k >= 5, {}

    return Tiny


def update_spy(fns):
    """A serial backend of env factories ``fns`` that counts, in ``during``, the gradient updates
    of its ``model`` (set it) made while a step or a round of episodes is in flight (between
    send and receive)."""
    from softcrawl.envs.backends import SerialBackend

    class Spy(SerialBackend):
        model, during, before = None, 0, 0

        def _mark_sent(self):
            self.before = self.model._n_updates

        def _count_received(self):
            self.during += self.model._n_updates - self.before

        def step_send(self, actions):
            super().step_send(actions)
            self._mark_sent()

        def step_recv(self):
            self._count_received()
            return super().step_recv()

        def episodes_send(self, actions):
            super().episodes_send(actions)
            self._mark_sent()

        def episodes_recv(self):
            self._count_received()
            return super().episodes_recv()

    return Spy(fns)


def filled_learner(make_sac, cfg, n: int = 64):
    """``make_sac`` of ``cfg`` (seed 0) on one tiny env, its replay buffer holding ``n`` random
    transitions (seed 0), ready for ``train``."""
    import numpy as np

    from softcrawl.envs.backends import SerialBackend
    from softcrawl.envs.vec import DesignVecEnv

    model = make_sac(DesignVecEnv(SerialBackend([tiny_env_class()])), cfg, seed=0)
    rng = np.random.default_rng(0)
    for _ in range(n):
        o = rng.uniform(-1, 1, (1, 44)).astype(np.float32)
        model.replay_buffer.add(o, o, rng.uniform(-1, 1, (1, 3)), rng.uniform(-1, 1, 1), np.zeros(1), [{}])
    model._setup_learn(1)
    return model


def continued_and_restored(module, cfg):
    """``(a, b)``: learner ``a`` of ``module`` (:mod:`softcrawl.codesign.sac_jax` or
    ``sac_torch``) after 5 + 5 updates; ``b`` built fresh, given ``a``'s state written after its
    first 5 (``learner_state_bytes`` -> ``decode_learner_state`` -> ``restore_learner_state``)
    and numpy's RNG of that moment (as a checkpoint restores it), then 5 updates."""
    import numpy as np

    a = filled_learner(module.make_sac, cfg)
    np.random.seed(1)
    a.train(gradient_steps=5, batch_size=cfg.batch_size)
    data, rng = module.learner_state_bytes(a), np.random.get_state()
    a.train(gradient_steps=5, batch_size=cfg.batch_size)
    b = filled_learner(module.make_sac, cfg)
    module.restore_learner_state(b, module.decode_learner_state(data))
    np.random.set_state(rng)
    b.train(gradient_steps=5, batch_size=cfg.batch_size)
    return a, b

