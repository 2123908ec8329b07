"""Co-design of body and gait (codesign.md): the Gibbs design distribution, its sampler, the
SAC learner and the training driver.

Layers (each module imports only those above it; ``tests/test_import_graph.py`` checks the
graph is acyclic): :mod:`~softcrawl.codesign.config` → :mod:`~softcrawl.codesign.distribution`,
:mod:`~softcrawl.codesign.sampler`, :mod:`~softcrawl.codesign.sac` (the learners:
:mod:`~softcrawl.codesign.sac_jax` on :mod:`~softcrawl.codesign.sac_nets`,
:mod:`~softcrawl.codesign.sac_torch`, both on :mod:`~softcrawl.codesign.sac_common`) →
:mod:`~softcrawl.codesign.checkpoints` (writing, checking, reading and rescuing a run's
checkpoints) → :mod:`~softcrawl.codesign.run` (the run folder: layout, settings, logs; the only
module that builds a run's paths) and :mod:`~softcrawl.codesign.factory` (envs, robots, sampler of a config)
→ :mod:`~softcrawl.codesign.training` (writes runs) and :mod:`~softcrawl.codesign.evaluation` →
:mod:`~softcrawl.codesign.shortlist` (the run's design) → :mod:`~softcrawl.codesign.report` (reads
runs; its training section :mod:`~softcrawl.codesign.report_training`). Training does not import
the report: ``softcrawl train`` writes it, and the shortlist, afterwards
(:func:`softcrawl.cli.train.train_and_report`). A saved
``config.json`` of an older format is read through :mod:`~softcrawl.codesign.migrate`; the ground
truth of the design space is the package :mod:`~softcrawl.codesign.groundtruth`.

Heavy modules (JAX / SBX / torch / stable-baselines3: the learners,
:mod:`softcrawl.codesign.training`, :mod:`softcrawl.codesign.report`) are not imported here.
"""

from softcrawl.codesign.distribution import (
    UNTRIED_POLICIES,
    BetaUpdate,
    EntropySchedule,
    GibbsDesignDistribution,
    gibbs_entropy,
)
from softcrawl.codesign.sampler import DesignSampler, GibbsDesignSampler

__all__ = [
    "UNTRIED_POLICIES",
    "BetaUpdate",
    "DesignSampler",
    "EntropySchedule",
    "GibbsDesignDistribution",
    "GibbsDesignSampler",
    "gibbs_entropy",
]
