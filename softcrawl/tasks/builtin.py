"""The shipped tasks (docs/tasks.md): forward distance (the paper's), distance along a heading,
turning in place, reaching a target point, crawling up an incline.

Positions are the disk's top centre (``Robot.reward_position``, the paper's reward point) in
mm, rewards in cm or degrees (:attr:`Task.unit`); 1 cm = :data:`MM_PER_CM` mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from softcrawl.reduction.floating import FloatingFrameBody
from softcrawl.robot.assembly import Robot
from softcrawl.robot.episode import MM_PER_CM
from softcrawl.tasks.base import VENT_SECONDS, Task, check_number

#: Gravitational acceleration of the models, mm/s^2 (``softcrawl.fem.Model.gravity``).
G_MM_S2 = 9800.0


def _shift(episode) -> np.ndarray:
    """``(3,)`` reward point's displacement since the episode's start, mm."""
    return np.asarray(episode.robot.reward_position(episode.state.x), dtype=float) - episode.start


@dataclass(frozen=True)
class Forward(Task):
    """The paper's task: cm crawled along +x by the disk's top centre (codesign.md). The reward
    is :attr:`softcrawl.robot.episode.Episode.displacement_cm`'s increment, the same floating
    point operations as before tasks existed."""

    name: ClassVar[str] = "forward"
    baseline: ClassVar[str | None] = "sine"
    describe: ClassVar[str] = "cm crawled along +x by the disk's top centre"

    def progress(self, episode, origin) -> float:
        """+x displacement since the start, cm."""
        return episode.displacement_cm


@dataclass(frozen=True)
class Heading(Task):
    """cm crawled along the unit heading ``(cos h, sin h, 0)``: ``(dx cos h + dy sin h) / 10``.

    Attributes:
        heading_deg: ``h``, degrees counter-clockwise from +x about +z, in [-180, 180]
            (0: :class:`Forward`'s reward, to the bit).
    """

    name: ClassVar[str] = "heading"
    describe: ClassVar[str] = "cm crawled along the heading (cos h, sin h) by the disk's top centre"

    heading_deg: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "heading_deg", check_number(self.name, "heading_deg", self.heading_deg,
                                                             -180.0, 180.0, "deg"))

    def progress(self, episode, origin) -> float:
        """Displacement along the heading since the start, cm."""
        d = _shift(episode)
        h = math.radians(self.heading_deg)
        return float(d[0] * math.cos(h) + d[1] * math.sin(h)) / MM_PER_CM


def disk_yaw_deg(robot: Robot, x: np.ndarray) -> float:
    """Yaw of the robot's disk, degrees in (-180, 180], counter-clockwise about +z: the angle
    ``atan2(R[1, 0], R[0, 0])`` of the rotation ``R`` of the disk's floating frame (the
    mass-weighted best rigid fit of its nodes to their rest positions,
    :meth:`softcrawl.reduction.floating.FloatingFrameBody.rotation`: the reduced robot's own
    frame, or one made for a full-order disk).

    Args:
        robot: the robot. x: ``(N, 3)`` stacked node positions, mm.

    Returns:
        The yaw, or NaN if a disk position is not finite (the env then scores the action 0).
    """
    frame = robot.reduced.get(robot.disk_body)
    if not isinstance(frame, FloatingFrameBody):
        frame = FloatingFrameBody(robot.model.bodies[robot.disk_body])
    disk = np.asarray(x, dtype=float)[robot.model.body_slice(robot.disk_body)]
    if not np.all(np.isfinite(disk)):
        return float("nan")
    R = frame.rotation(disk)
    return math.degrees(math.atan2(R[1, 0], R[0, 0]))


def wrap_deg(angle: float) -> float:
    """``angle`` (degrees) wrapped to (-180, 180]."""
    a = math.fmod(angle, 360.0)
    if a > 180.0:
        a -= 360.0
    elif a <= -180.0:
        a += 360.0
    return a


@dataclass(frozen=True)
class Turning(Task):
    """Turning in place: degrees the disk yaws about +z, counter-clockwise positive
    (:func:`disk_yaw_deg`). The progress is the yaw since the start wrapped to (-180, 180];
    an action's reward is the wrapped change (an action turns less than half a turn), so an
    episode's return is the total (unwrapped) turn, degrees. No termination.

    The episode is scored at rest: after its last action every regulator vents for ``vent_s``
    seconds (:attr:`Task.vent_seconds`) and the last action's reward includes what springs back.
    Inflated legs whose feet stick to the floor can twist the disk elastically by several
    degrees; the twist springs back when they vent and is not a turn (docs/tasks.md, "Twist or
    turn").

    Attributes:
        vent_s: seconds vented after the last action, in [0, 60] (0: scored while the last
            action's pressure holds).
    """

    name: ClassVar[str] = "turning"
    unit: ClassVar[str] = "deg"
    baseline: ClassVar[str | None] = "turning"
    reads_disk: ClassVar[bool] = True
    describe: ClassVar[str] = "degrees the disk yaws counter-clockwise about +z, kept at rest after venting"

    vent_s: float = VENT_SECONDS

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "vent_s", check_number(self.name, "vent_s", self.vent_s, 0.0, 60.0, "s"))

    @property
    def vent_seconds(self) -> float:
        """:attr:`vent_s`."""
        return self.vent_s

    def origin(self, episode) -> float:
        """The disk's yaw at the start, degrees."""
        return disk_yaw_deg(episode.robot, episode.state.x)

    def progress(self, episode, origin) -> float:
        """Yaw since the start, degrees in (-180, 180]."""
        return wrap_deg(disk_yaw_deg(episode.robot, episode.state.x) - origin)

    def reward(self, before: float, after: float) -> float:
        """Degrees turned during the action: ``after - before`` wrapped to (-180, 180]."""
        return wrap_deg(after - before)


@dataclass(frozen=True)
class Target(Task):
    """Reaching a point: the reward is the decrease of the horizontal distance (cm) from the
    disk's top centre to the target ``(x_mm, y_mm)`` (relative to its position at the start);
    the episode ends (terminated) once that distance is at most ``radius_mm``.

    Attributes:
        x_mm, y_mm: the target relative to the start, mm (each in [-2000, 2000]).
        radius_mm: the goal's radius, mm (in (0, 1000]); the target must lie outside it.
    """

    name: ClassVar[str] = "target"
    describe: ClassVar[str] = "cm by which the distance to the target point shrank"

    x_mm: float = 200.0
    y_mm: float = 0.0
    radius_mm: float = 20.0

    def __post_init__(self) -> None:
        super().__post_init__()
        for key in ("x_mm", "y_mm"):
            object.__setattr__(self, key, check_number(self.name, key, getattr(self, key), -2000.0, 2000.0, "mm"))
        object.__setattr__(self, "radius_mm", check_number(self.name, "radius_mm", self.radius_mm, 0.0, 1000.0, "mm"))
        if self.radius_mm <= 0 or math.hypot(self.x_mm, self.y_mm) <= self.radius_mm:
            raise ValueError(f"task 'target': the target ({self.x_mm:g}, {self.y_mm:g}) mm must lie outside the "
                             f"goal radius radius_mm > 0, got {self.radius_mm:g} mm")

    def distance_mm(self, episode) -> float:
        """Horizontal distance from the disk's top centre to the target, mm."""
        d = _shift(episode)
        return math.hypot(self.x_mm - d[0], self.y_mm - d[1])

    def progress(self, episode, origin) -> float:
        """Decrease of the distance to the target since the start, cm."""
        return (math.hypot(self.x_mm, self.y_mm) - self.distance_mm(episode)) / MM_PER_CM

    def reached(self, episode, origin) -> bool:
        """Whether the distance to the target is at most ``radius_mm``."""
        return self.distance_mm(episode) <= self.radius_mm


@dataclass(frozen=True)
class Incline(Task):
    """Crawling uphill on a floor tilted by ``angle_deg`` about the y axis, rising towards +x.
    The floor stays the plane ``z = 0`` of the robot's frame and gravity tilts instead:
    ``g = 9800 (-sin a, 0, -cos a)`` mm/s^2. The reward is the uphill displacement of the disk's
    top centre (its +x displacement, as :class:`Forward`), cm.

    A robot holds on the incline only if ``tan a <= mu`` (Coulomb): an incline steeper than
    the task's ``friction`` is refused here, one steeper than the robot's friction where the
    task meets the robot (:meth:`Task.check_floor`: the training and ground-truth configs,
    ``softcrawl simulate``).

    Attributes:
        angle_deg: the incline ``a``, degrees in [0, 45] (0: a flat floor, :class:`Forward`).
    """

    name: ClassVar[str] = "incline"
    describe: ClassVar[str] = "cm crawled uphill (+x along the tilted floor) by the disk's top centre"

    angle_deg: float = 10.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "angle_deg", check_number(self.name, "angle_deg", self.angle_deg, 0.0, 45.0, "deg"))
        self.check_floor()

    def gravity(self) -> tuple[float, float, float]:
        """``(-g sin a, 0, -g cos a)`` mm/s^2."""
        a = math.radians(self.angle_deg)
        return (-G_MM_S2 * math.sin(a), 0.0, -G_MM_S2 * math.cos(a))

    def progress(self, episode, origin) -> float:
        """Uphill displacement since the start, cm."""
        return episode.displacement_cm
