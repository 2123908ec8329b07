"""The design sampler of co-design: a :class:`GibbsDesignDistribution` driven by an
:class:`EntropySchedule`, living in the learner's process (codesign.md, "Each iteration").

Vectorised environments (:class:`softcrawl.envs.DesignVecEnv`) call :meth:`observe` with the
finished episodes and then :meth:`sample` for the designs of the next episodes, so the returns
of the episodes that just ended are in ``p`` before new designs are drawn.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from softcrawl.codesign.distribution import (
    BetaUpdate,
    EntropySchedule,
    GibbsDesignDistribution,
)
from softcrawl.design.space import Design


class DesignSampler:
    """Interface of a design sampler (anything with these two methods works)."""

    def sample(self, n: int) -> list[Design]:  # pragma: no cover - interface
        raise NotImplementedError

    def observe(self, designs: Sequence[Design], returns: Sequence[float], diverged: Sequence[bool],
                timestep: int) -> None:  # pragma: no cover - interface
        raise NotImplementedError


class GibbsDesignSampler(DesignSampler):
    """Samples designs from a Gibbs distribution whose entropy follows a schedule.

    Args:
        distribution: the design distribution (updated in place).
        schedule: entropy target over environment steps.
        seed: seed of the sampler's own ``numpy`` Generator.

    A diverged episode is recorded with score ``min(partial return, 0)`` cm: a numerically
    exploding design must not look good because of the motion before the blow-up.

    Attributes:
        history: list of ``(timestep, BetaUpdate)`` of all updates since construction/restore.
    """

    def __init__(self, distribution: GibbsDesignDistribution, schedule: EntropySchedule, seed: int | None = None):
        self.distribution, self.schedule = distribution, schedule
        self.rng = np.random.default_rng(seed)
        self.timestep = 0
        self.update_beta(0)

    def update_beta(self, timestep: int) -> BetaUpdate:
        """Set ``beta`` for the schedule's target at ``timestep`` environment steps."""
        self.timestep = int(timestep)
        return self.distribution.set_entropy_target(self.schedule.target(timestep), self.schedule.uniform(timestep))

    def observe(self, designs, returns, diverged, timestep: int) -> None:
        """Record finished episodes (returns in cm) and update ``beta`` for ``timestep``."""
        r = [min(float(v), 0.0) if dv else float(v) for v, dv in zip(returns, diverged)]
        if designs:
            self.distribution.record(designs, r)
        self.update_beta(timestep)

    def sample(self, n: int) -> list[Design]:
        """``n`` designs drawn i.i.d. from the current distribution."""
        return self.distribution.sample(self.rng, n)

    def state_dict(self) -> dict:
        return {"distribution": self.distribution.state_dict(), "rng": self.rng.bit_generator.state,
                "timestep": self.timestep}

    def load_state_dict(self, state: dict) -> None:
        self.distribution.load_state_dict(state["distribution"])
        self.rng.bit_generator.state = state["rng"]
        self.timestep = int(state["timestep"])
