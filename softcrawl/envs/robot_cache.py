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

Settled states outlive their robots: a settled state (0.3-0.6 MB: a robot's node positions and
velocities) takes 7-14x less memory than its robot, but settling again costs several times more
CPU than rebuilding the robot (three-legged, 25 mm disk: 0.22 s against ~35 ms;
``CHANGELOG.md``). So the cache also
keeps, LRU, up to ``settled_mb`` MB of settled states of designs whose robots it dropped
(default 128 MB: all 280 three-legged designs with the 25 mm disk, ~220 six-legged ones with
the 10 mm disk). Such a design's robot is rebuilt (deterministically: the same model) and starts
from the kept state, the state settling it again would give.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Hashable

_SHARED: dict[Hashable, RobotCache] = {}


#: Default memory for the settled states of designs whose robots were dropped, MB per process.
SETTLED_MB = 128.0


class RobotCache(OrderedDict):
    """LRU ``design -> (Robot, SettledState | None)`` holding at most ``envs + spare`` robots,
    where ``envs`` counts the envs attached (:meth:`attach`), and beside it an LRU of settled
    states that outlive their robots (module doc).

    Args:
        spare: robots kept beyond one per attached env (>= 1).
        settled_mb: memory for settled states kept beyond their robots, MB (>= 0; 0 keeps none).

    Raises:
        ValueError: ``spare`` not a positive integer or ``settled_mb`` negative or not finite.
    """

    def __init__(self, spare: int, settled_mb: float = SETTLED_MB):
        super().__init__()
        if int(spare) != spare or spare < 1:
            raise ValueError(f"spare must be a positive integer, got {spare!r}")
        if not 0.0 <= float(settled_mb) < float("inf"):
            raise ValueError(f"settled_mb must be a non-negative number, got {settled_mb!r}")
        self.spare, self.envs = int(spare), 0
        self.settled_bytes = int(float(settled_mb) * 1e6)
        self.settled: OrderedDict = OrderedDict()  # design -> (SettledState, bytes), LRU
        self._settled_total = 0

    def attach(self) -> RobotCache:
        """Count one more env using this cache (raises its capacity by one); returns self."""
        self.envs += 1
        return self

    def detach(self) -> None:
        """One env less (its :meth:`~softcrawl.envs.crawler.CrawlerEnv.close`); the least recently
        used robots beyond the lower capacity are dropped."""
        self.envs = max(0, self.envs - 1)
        self._trim()

    @property
    def capacity(self) -> int:
        return self.envs + self.spare

    def fetch(self, design, build: Callable):
        """``(robot, settled)`` of ``design`` (``build(design)`` and ``None`` if missing), made the
        most recently used; the least recently used beyond :attr:`capacity` are dropped."""
        robot, settled = self.pop(design, (None, None))
        if robot is None:
            robot = build(design)
            kept = self._drop_settled(design)
            settled = None if kept is None else kept[0]
        self[design] = (robot, settled)
        self._trim()
        return robot, settled

    def keep_settled(self, design, robot, settled) -> None:
        """Store ``settled`` for ``design`` if ``robot`` is still its cached robot."""
        if design in self and self[design][0] is robot:
            self[design] = (robot, settled)

    def _trim(self) -> None:
        """Drop the least recently used robots beyond :attr:`capacity`, keeping their settled
        states (within ``settled_mb``, the least recently used states dropped first)."""
        while len(self) > self.capacity:
            design, (_, settled) = self.popitem(last=False)
            if settled is None:
                continue
            size = _nbytes(settled)
            if size > self.settled_bytes:
                continue
            self.settled[design] = (settled, size)  # not there: fetch() took it out with the robot
            self._settled_total += size
            while self._settled_total > self.settled_bytes:
                self._drop_settled(next(iter(self.settled)))

    def _drop_settled(self, design):
        """Remove and return ``(settled, bytes)`` kept for ``design`` (None if none)."""
        kept = self.settled.pop(design, None)
        if kept is not None:
            self._settled_total -= kept[1]
        return kept


def _nbytes(settled) -> int:
    """Memory of a :class:`~softcrawl.robot.episode.SettledState`'s arrays, bytes (at least 1)."""
    state = getattr(settled, "state", None)
    if state is None:
        return 1
    arrays = (state.x, state.v, state.contact_nodes, state.contact_impulses, *(state.modal_velocities or ()))
    return max(1, sum(a.nbytes for a in arrays))


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
