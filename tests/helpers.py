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
