"""Reinforcement-learning environments of the crawler: the single-episode gymnasium env
(:mod:`softcrawl.envs.crawler`) and the design-sampling vectorised env with serial and
where they run (:mod:`softcrawl.envs.backends`) and the SB3 vector env (:mod:`softcrawl.envs.vec`, imports
stable-baselines3)."""

from softcrawl.envs.crawler import (
    DESIGN_DIM,
    HISTORY,
    N_ACTIONS,
    STATE_DIM,
    BuildRobot,
    CrawlerEnv,
    action_to_kpa,
    kpa_to_action,
)

__all__ = ["DESIGN_DIM", "HISTORY", "N_ACTIONS", "STATE_DIM", "BuildRobot", "CrawlerEnv", "action_to_kpa",
           "kpa_to_action"]
