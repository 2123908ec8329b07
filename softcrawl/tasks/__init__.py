"""Tasks as data: what a co-design run rewards and the floor it runs on (docs/tasks.md).

:data:`TASKS` names the shipped tasks (``forward``, the paper's and the default; ``heading``,
``turning``, ``target``, ``incline``); :func:`make_task` / :func:`parse_task` build one from a
name and settings; :class:`Task` is the interface (:mod:`softcrawl.tasks.base`). The env
(:class:`softcrawl.envs.CrawlerEnv`, ``task=``) scores its actions with it. Sits above the
robot and below the envs.
"""

from softcrawl.tasks.base import OnFloor, Task, on_floor
from softcrawl.tasks.builtin import Forward, Heading, Incline, Target, Turning, disk_yaw_deg, wrap_deg
from softcrawl.tasks.registry import DEFAULT_TASK, TASKS, make_task, parse_task

__all__ = ["DEFAULT_TASK", "TASKS", "Forward", "Heading", "Incline", "OnFloor", "Target", "Task", "Turning",
           "disk_yaw_deg", "make_task", "on_floor", "parse_task", "wrap_deg"]
