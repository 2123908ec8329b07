"""Co-design of body and gait (codesign.md): the Gibbs design distribution, its sampler, the
SAC learner and the training driver.

Heavy modules (torch / stable-baselines3: :mod:`softcrawl.codesign.sac`,
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
