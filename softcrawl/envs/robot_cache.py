"""Built robots and their settled states, cached per design (LRU).

A :class:`~softcrawl.envs.crawler.CrawlerEnv` keeps its robots in a :class:`RobotCache`: its own,
or (``share_robots=True``, what training's env constructors ask for) the one cache of its
process for its robot factory and settling rule, shared by all such envs of the process. A
robot is static data (:class:`~softcrawl.robot.assembly.Robot`: model, legs, reduction) and
a settled state is only read (solvers return new states), so envs can share both; each episode
still gets its own solver.

Why share: a subprocess worker of the ``paper`` preset runs 48 envs; with a private cache of 16
robots each (~3.8 MB per robot with the 10 mm disk) a long run would hold up to 768 robots,
~3 GB, per worker. A shared cache holds one robot per env in use plus ``spare`` others.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable

_SHARED: dict[Hashable, RobotCache] = {}


class RobotCache(OrderedDict):
    """LRU ``design -> (Robot, SettledState | None)`` holding at most ``envs + spare`` robots,
    where ``envs`` counts the envs attached (:meth:`attach`).

    Args:
        spare: robots kept beyond one per attached env (>= 1).
    """

    def __init__(self, spare: int):
        super().__init__()
        if int(spare) != spare or spare < 1:
            raise ValueError(f"spare must be a positive integer, got {spare!r}")
        self.spare, self.envs = int(spare), 0

    def attach(self) -> RobotCache:
        """Count one more env using this cache (raises its capacity by one); returns self."""
        self.envs += 1
        return self

    def detach(self) -> None:
        """One env less (its :meth:`~softcrawl.envs.crawler.CrawlerEnv.close`); the least recently
        used robots beyond the lower capacity are dropped."""
        self.envs = max(0, self.envs - 1)
        while len(self) > self.capacity:
            self.popitem(last=False)

    @property
    def capacity(self) -> int:
        return self.envs + self.spare

    def fetch(self, design, build: Callable):
        """``(robot, settled)`` of ``design`` (``build(design)`` and ``None`` if missing), made the
        most recently used; the least recently used beyond :attr:`capacity` are dropped."""
        robot, settled = self.pop(design, (None, None))
        if robot is None:
            robot = build(design)
        self[design] = (robot, settled)
        while len(self) > self.capacity:
            self.popitem(last=False)
        return robot, settled

    def keep_settled(self, design, robot, settled) -> None:
        """Store ``settled`` for ``design`` if ``robot`` is still its cached robot."""
        if design in self and self[design][0] is robot:
            self[design] = (robot, settled)


def process_cache(factory: Callable, settling: Hashable, spare: int) -> RobotCache:
    """This process's cache for robots of ``factory`` settled by ``settling`` (created with
    ``spare`` on first use; an unhashable factory gets a cache of its own)."""
    key = (factory, settling)
    try:
        hash(key)
    except TypeError:
        return RobotCache(spare)
    cache = _SHARED.get(key)
    if cache is None:
        cache = _SHARED[key] = RobotCache(spare)
    return cache
