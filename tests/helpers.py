"""Helpers shared by several test modules (importable as ``helpers``: pytest puts ``tests/`` on
``sys.path``)."""

from __future__ import annotations


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
        model = make_sac(venv, cfg.sac, seed=cfg.seed)
        r.load_checkpoint(r.latest_checkpoint(), model, sampler)
    finally:
        venv.close()
    return model, sampler, r


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
    of its ``model`` (set it) made while a step is in flight (between send and receive)."""
    from softcrawl.envs.backends import SerialBackend

    class Spy(SerialBackend):
        model, during, before = None, 0, 0

        def step_send(self, actions):
            super().step_send(actions)
            self.before = self.model._n_updates

        def step_recv(self):
            self.during += self.model._n_updates - self.before
            return super().step_recv()

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
