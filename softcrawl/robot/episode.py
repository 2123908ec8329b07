"""Running a crawler episode: regulators -> calibration -> FEM steps -> reward.

Per step of ``dt`` seconds (physics.md, "Time stepping" and "Pneumatic actuation"):
the gait's command (real kPa, checked against [0, 90]) goes through the rate-limited
:class:`RegulatorBank` (150 kPa/s), the applied real pressures through the
:class:`PressureCalibration` to sim kPa, and those drive one solver step. An episode
starts from the robot *at rest* on the floor: :func:`settle` steps it at zero pressure until
every node is slower than :attr:`Settling.rest_speed` for :attr:`Settling.hold_seconds`
(at most :attr:`Settling.max_seconds`; a robot that is still moving then is reported, not
hidden: :attr:`SettledState.at_rest` is False, and :func:`unsettled_warning` is the line the
commands print about it: a robot on an incline steeper than its floor's friction allows never
comes to rest and slides through its episode). Settling does not count towards the episode
time; the reward is the +x displacement of the disk's top-centre point (cm) from the rested
pose to the end of the episode. The settled state depends on the robot only, so callers that
run many episodes of one design keep it (:class:`Episode` takes a cached
:class:`SettledState`) and every episode starts from it with a fresh solver.

Gaits are duck-typed (anything with ``pressure_at(t) -> (R,)`` real kPa for the robot's ``R``
regulators, ``robot.model.n_channels``; 3 in the paper's space), so this module
does not import :mod:`softcrawl.gaits` (which imports :mod:`softcrawl.robot`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from softcrawl.fem.solver import SimulationDiverged
from softcrawl.fem.state import Control, State
from softcrawl.robot.actuation import PressureCalibration, RegulatorBank
from softcrawl.robot.assembly import Robot

#: mm per cm (reward unit).
MM_PER_CM = 10.0


@dataclass(frozen=True)
class Settling:
    """When zero-pressure settling before an episode ends (the paper's fixed 15 steps
    left designs that tip over mid-fall at t = 0, and the fall was scored as crawling).

    Attributes:
        rest_speed: mm/s; at rest when every node (disk and legs) is slower than this.
            Default 0.5: once a robot has landed its speed decays with a time constant of
            about 0.1 s (Rayleigh damping; measured on the one-sided ``0,0,1,0,2,2,0,0``), so
            the drift left after rest is about ``rest_speed x 0.1 s`` = 0.05 mm, 0.5% of a
            1 cm reward.
        hold_seconds: the speed must stay below ``rest_speed`` this long (s), so a robot
            passing slowly through a tipping point is not taken for resting.
        max_seconds: settling cap, s; a robot still moving then starts its episode anyway
            and is reported (``SettledState.at_rest`` False).

    Raises:
        ValueError: a non-positive ``rest_speed``, a negative or non-finite time.
    """

    rest_speed: float = 0.5
    hold_seconds: float = 0.05
    max_seconds: float = 3.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.rest_speed) and self.rest_speed > 0):
            raise ValueError(f"settling rest_speed must be a positive speed in mm/s, got {self.rest_speed!r}")
        for name in ("hold_seconds", "max_seconds"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"settling {name} must be a non-negative number of seconds, got {v!r}")

    def steps(self, dt: float) -> tuple[int, int]:
        """``(hold, cap)`` in steps of ``dt`` s (hold at least 1)."""
        return max(1, math.ceil(self.hold_seconds / dt - 1e-9)), math.ceil(self.max_seconds / dt - 1e-9)


#: No settling at all (the robot starts as assembled, mid-air): for tests of the raw model only.
NO_SETTLING = Settling(max_seconds=0.0)


@dataclass(frozen=True, eq=False)
class SettledState:
    """A robot after :func:`settle`.

    Attributes:
        state: the rested :class:`State` (``t = 0``).
        steps: settling steps taken; seconds: ``steps * dt``, s.
        rest_speed: fastest node speed at the end, mm/s.
        at_rest: whether the rest criterion was met within the cap.
    """

    state: State
    steps: int
    seconds: float
    rest_speed: float
    at_rest: bool

    def as_dict(self) -> dict:
        """The statistics (no state) for logs and summaries."""
        return {"settle_steps": self.steps, "settle_seconds": self.seconds,
                "rest_speed_mm_s": self.rest_speed, "at_rest": self.at_rest}


def unsettled_warning(settled: dict) -> str | None:
    """One line on a robot that did not come to rest before its episode, from its settling
    statistics (:meth:`SettledState.as_dict`: an env's ``info``, an :class:`EpisodeResult`'s
    ``settled``); None if it came to rest (or the statistics are missing: settling diverged).
    The episode started anyway, from a moving robot: on an incline steeper than the floor's
    friction allows (tan a > mu) the robot slides for good, and its return is mostly that slide."""
    if not settled or settled.get("at_rest", True):
        return None
    return (f"did not come to rest before its episode (still moving at {settled['rest_speed_mm_s']:.3g} mm/s after "
            f"the {settled['settle_seconds']:g} s settling cap): its return counts that motion; on a floor tilted "
            "more than its friction holds (tan a > mu) it slides for good")


def settle(robot: Robot, settling: Settling = Settling(), solver=None, state: State | None = None,
           zero: Control | None = None) -> SettledState:
    """Step ``robot`` at zero pressure until it is at rest (:class:`Settling`).

    Args:
        robot: the robot.
        settling: the rest rule.
        solver: the solver to step with; the result then carries its reduced bodies' modal
            velocities (:attr:`State.modal_velocities`), to go on stepping with it. Default: a new
            one, and the result holds positions and velocities only (the modal velocities are
            projected from them by the next solver), so that an episode started from it is the
            same whether it was computed now or cached.
        state: the start (default: the assembled rest state, mid-air).
        zero: the zero-pressure control (default: 0 kPa on every channel of ``robot.model``).

    Returns:
        The :class:`SettledState` (``at_rest`` False if the cap was reached first).

    Raises:
        SimulationDiverged: if settling diverges.
    """
    dt = robot.config.dt
    hold, cap = settling.steps(dt)
    own = solver is None
    solver = robot.make_solver() if own else solver
    state = robot.model.rest_state() if state is None else state
    zero = robot.control(np.zeros(robot.model.n_channels)) if zero is None else zero
    speed, calm, steps = float(np.sqrt(np.einsum("ij,ij->i", state.v, state.v).max())), 0, 0
    while steps < cap and calm < hold:
        state = solver.step(state, zero)
        steps += 1
        speed = float(np.sqrt(np.einsum("ij,ij->i", state.v, state.v).max()))
        calm = calm + 1 if speed < settling.rest_speed else 0
    rest = dataclasses.replace(state, t=0.0, modal_velocities=None if own else state.modal_velocities)
    return SettledState(rest, steps, steps * dt, speed,
                        calm >= hold or (cap == 0 and speed < settling.rest_speed))


class Episode:
    """Step-by-step episode of one robot (for :func:`run_episode` and environments).

    Args:
        robot: the assembled robot.
        calibration: real-to-sim pressure map.
        settling: the rest rule of :meth:`reset` (settling is not counted in time).
        rate_kpa_s: regulator slew-rate limit, kPa/s.
        settled: this robot's :class:`SettledState` from an earlier :func:`settle` with the
            same ``settling`` (a cache); None settles at the first :meth:`reset`.

    Attributes:
        state: the current :class:`State` (``t`` = episode time, 0 after :meth:`reset`).
        start: ``(3,)`` disk top-centre position after settling, mm.
        applied: ``(R,)`` applied real kPa of the robot's ``R`` regulators (3 in the paper's
            space) after the last step.
        solver: the solver (its ``stats`` describe the last step; None before :meth:`reset`).
        settled: the :class:`SettledState` episodes start from (None before the first reset).
    """

    def __init__(self, robot: Robot, calibration: PressureCalibration = PressureCalibration(),
                 settling: Settling = Settling(), rate_kpa_s: float = 150.0,
                 settled: SettledState | None = None):
        self.robot, self.calibration, self.settling = robot, calibration, settling
        self.regulators = RegulatorBank(robot.model.n_channels, rate_kpa_s)
        self.solver = None  # made by reset()
        self.settled = settled
        self.state: State = robot.model.rest_state()
        self.start = robot.reward_position(self.state.x)

    @property
    def dt(self) -> float:
        return self.robot.config.dt

    @property
    def applied(self) -> np.ndarray:
        return self.regulators.state.copy()

    def reset(self) -> State:
        """Regulators at 0 kPa, the robot at rest (:func:`settle`, once per :class:`Episode`
        unless a settled state was given), a fresh solver; t := 0. The episode starts from the
        settled positions and velocities: its reduced bodies' modal velocities are projected
        from them (:attr:`State.modal_velocities` dropped), whichever solver settled the robot.

        Raises:
            SimulationDiverged: if settling diverges.
        """
        self.regulators.reset()
        if self.settled is None:
            self.settled = settle(self.robot, self.settling)
        self.solver = self.robot.make_solver()
        self.state = dataclasses.replace(self.settled.state, modal_velocities=None)
        self.start = self.robot.reward_position(self.state.x)
        return self.state

    def step(self, command: np.ndarray) -> State:
        """Advance one ``dt`` with regulator commands ``(R,)`` real kPa (one per regulator).

        Raises:
            PressureRangeError: a command is non-finite or outside [0, 90] kPa.
            SimulationDiverged: the solver failed (the episode state is left unchanged).
        """
        applied = self.regulators.step(command, self.dt)
        self.state = self.solver.step(self.state, self.robot.control(self.calibration.to_sim(applied)))
        return self.state

    @property
    def displacement_cm(self) -> float:
        """+x displacement of the disk top centre since :meth:`reset`, cm (the episode return)."""
        return float(self.robot.reward_position(self.state.x)[0] - self.start[0]) / MM_PER_CM

    def next_control(self, command: np.ndarray) -> Control:
        """:meth:`step` without its solver step, for drivers that step many episodes' robots
        together (:mod:`softcrawl.envs.backends.batched`, which then sets :attr:`state`): the regulators
        advance one ``dt`` with commands ``(R,)`` real kPa; returns that step's solver input.

        Raises:
            PressureRangeError: a command is non-finite or outside [0, 90] kPa.
        """
        applied = self.regulators.step(command, self.dt)
        return self.robot.control(self.calibration.to_sim(applied))


@dataclass(frozen=True, eq=False)
class EpisodeResult:
    """Record of one episode. Row ``i`` of the per-step arrays is time ``t_i = i * dt``
    (row 0: after settling); pressures in row ``i`` are those held during the step that
    ended at ``t_i`` (row 0: zeros). If the run diverged, the arrays stop at the last
    valid state.

    Attributes:
        time: ``(n + 1,)`` s.
        position: ``(n + 1, 3)`` disk top-centre position, mm.
        commanded, applied: ``(n + 1, R)`` regulator pressures, real kPa (``R`` regulators of
            the robot's space).
        contacts: ``(n + 1,)`` active floor contacts.
        contact_sweeps: ``(n + 1,)`` Gauss-Seidel sweeps of the contact solve.
        factorizations: total matrix factorizations of the episode steps.
        frame_times: ``(k,)`` s, and frames: ``(k, N, 3)`` float32 positions (mm) of all
            nodes every ``record_every`` steps (empty if not recorded).
        reward_cm: +x displacement of the disk top centre, cm (up to the last valid state;
            NaN only if settling itself diverged, when the arrays are empty).
        steps: completed episode steps ``n``; sim_seconds = ``n * dt``.
        wall_seconds: wall-clock time including settling.
        diverged: whether the solver failed; reason: its message ("" otherwise).
        settled: the settling statistics (:meth:`SettledState.as_dict`; empty if settling
            diverged).
    """

    time: np.ndarray
    position: np.ndarray
    commanded: np.ndarray
    applied: np.ndarray
    contacts: np.ndarray
    contact_sweeps: np.ndarray
    factorizations: int
    frame_times: np.ndarray
    frames: np.ndarray
    reward_cm: float
    steps: int
    sim_seconds: float
    wall_seconds: float
    diverged: bool = False
    reason: str = ""
    settled: dict = dataclasses.field(default_factory=dict)

    @property
    def real_time_factor(self) -> float:
        """Simulated seconds per wall-clock second."""
        return self.sim_seconds / self.wall_seconds if self.wall_seconds > 0 else float("inf")


def run_episode(robot: Robot, gait, duration: float = 20.0,
                calibration: PressureCalibration = PressureCalibration(), settling: Settling = Settling(),
                record_every: int | None = 1, progress: bool = True,
                on_frame: Callable[[float, np.ndarray], None] | None = None,
                settled: SettledState | None = None) -> EpisodeResult:
    """Simulate one open-loop episode.

    Args:
        robot: the assembled robot.
        gait: object with ``pressure_at(t) -> (R,)`` commanded real kPa (regulators 1..R of
            the robot's space, ``R = robot.model.n_channels``), queried at the start
            ``t = k * dt`` of each step ``k``.
        duration: episode length, s (rounded to whole steps of ``robot.config.dt``).
        calibration: real-to-sim pressure map.
        settling: the rest rule before the episode (not counted; :func:`settle`).
        record_every: store all node positions every this many steps (and at t = 0);
            None stores none.
        progress: show a tqdm bar (steps/s, ETA) on stderr.
        on_frame: called as ``on_frame(t, x)`` (s, ``(N, 3)`` mm) for each recorded frame.
        settled: this robot's cached :func:`settle` result for ``settling`` (None: settle now).

    Returns:
        The :class:`EpisodeResult`. A :class:`SimulationDiverged` (settling included) is
        caught: ``diverged=True``, ``reason`` set, arrays truncated at the last valid state.

    Raises:
        ValueError: non-positive duration or record_every; a gait command that is not ``(R,)``.
        PressureRangeError: if the gait commands a pressure outside [0, 90] kPa.
    """
    dt = robot.config.dt
    n = int(round(duration / dt)) if np.isfinite(duration) else 0
    if n < 1:
        raise ValueError(f"duration must be at least one time step ({dt} s), got {duration} s")
    if record_every is not None and record_every < 1:
        raise ValueError(f"record_every must be >= 1 or None, got {record_every}")
    ep = Episode(robot, calibration, settling, settled=settled)
    n_reg = robot.model.n_channels
    pos, cmd, app = np.zeros((n + 1, 3)), np.zeros((n + 1, n_reg)), np.zeros((n + 1, n_reg))
    contacts, sweeps = np.zeros(n + 1, np.int64), np.zeros(n + 1, np.int64)
    frame_times, frames = [], []
    factorizations, done, reason = 0, -1, ""

    def record(i: int) -> None:
        x, st = ep.state.x, ep.solver.stats
        pos[i], app[i] = robot.reward_position(x), ep.applied
        contacts[i], sweeps[i] = st.n_contacts, st.contact_sweeps
        if record_every is not None and i % record_every == 0:
            frame_times.append(i * dt)
            frames.append(x.astype(np.float32))
            if on_frame is not None:
                on_frame(i * dt, x)

    wall = time.perf_counter()
    bar = tqdm(total=n, unit="step", desc="simulate", disable=not progress, dynamic_ncols=True)
    try:
        ep.reset()
        record(0)
        done = 0
        for k in range(n):
            command = np.asarray(gait.pressure_at(k * dt), dtype=float)
            if command.shape != (n_reg,):
                raise ValueError(f"the gait commands pressures of shape {command.shape} at t = {k * dt:g} s; "
                                 f"the robot has {n_reg} regulators")
            cmd[k + 1] = command
            ep.step(cmd[k + 1])
            factorizations += ep.solver.stats.factorizations
            record(k + 1)
            done = k + 1
            bar.update()
            if done % 20 == 0:
                bar.set_postfix(x_cm=f"{ep.displacement_cm:+.2f}", refresh=False)
    except SimulationDiverged as exc:
        reason = str(exc)
    finally:
        bar.close()
    wall = time.perf_counter() - wall
    m = done + 1  # valid rows (0 if settling diverged)
    reward = ep.displacement_cm if done >= 0 else float("nan")
    frames_arr = np.stack(frames) if frames else np.zeros((0, robot.model.n_nodes, 3), np.float32)
    return EpisodeResult(
        time=np.arange(m) * dt, position=pos[:m], commanded=cmd[:m], applied=app[:m],
        contacts=contacts[:m], contact_sweeps=sweeps[:m], factorizations=factorizations,
        frame_times=np.array(frame_times), frames=frames_arr, reward_cm=reward,
        steps=max(done, 0), sim_seconds=max(done, 0) * dt, wall_seconds=wall,
        diverged=bool(reason), reason=reason, settled=ep.settled.as_dict() if ep.settled else {},
    )
