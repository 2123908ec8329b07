"""Running a crawler episode: regulators -> calibration -> FEM steps -> reward.

Per step of ``dt`` seconds (physics.md, "Time stepping" and "Pneumatic actuation"):
the gait's command (real kPa, checked against [0, 90]) goes through the rate-limited
:class:`RegulatorBank` (150 kPa/s), the applied real pressures through the
:class:`PressureCalibration` to sim kPa, and those drive one solver step. An episode
starts with ``settle_steps`` steps at zero pressure (the robot settles onto the floor),
which do not count towards the episode time; the reward is the +x displacement of the
disk's top-centre point (cm) from the end of settling to the end of the episode.

Gaits are duck-typed (anything with ``pressure_at(t) -> (3,)`` real kPa), so this module
does not import :mod:`softcrawl.gaits` (which imports :mod:`softcrawl.robot`).
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from tqdm.auto import tqdm

from softcrawl.design.space import N_REGULATORS
from softcrawl.fem.solver import SimulationDiverged
from softcrawl.fem.state import State
from softcrawl.robot.actuation import PressureCalibration, RegulatorBank
from softcrawl.robot.assembly import Robot

#: Settling steps at zero pressure before an episode (physics.md).
SETTLE_STEPS = 15
#: mm per cm (reward unit).
MM_PER_CM = 10.0


class Episode:
    """Step-by-step episode of one robot (for :func:`run_episode` and environments).

    Args:
        robot: the assembled robot.
        calibration: real-to-sim pressure map.
        settle_steps: zero-pressure steps run by :meth:`reset` (not counted in time).
        rate_kpa_s: regulator slew-rate limit, kPa/s.

    Attributes:
        state: the current :class:`State` (``t`` = episode time, 0 after :meth:`reset`).
        start: ``(3,)`` disk top-centre position after settling, mm.
        applied: ``(3,)`` applied real kPa of the regulators after the last step.
        solver: the solver (its ``stats`` describe the last step).
    """

    def __init__(self, robot: Robot, calibration: PressureCalibration = PressureCalibration(),
                 settle_steps: int = SETTLE_STEPS, rate_kpa_s: float = 150.0):
        if int(settle_steps) < 0:
            raise ValueError(f"settle_steps must be >= 0, got {settle_steps}")
        self.robot, self.calibration, self.settle_steps = robot, calibration, int(settle_steps)
        self.regulators = RegulatorBank(N_REGULATORS, rate_kpa_s)
        self.solver = robot.make_solver()
        self.state: State = robot.model.rest_state()
        self.start = robot.reward_position(self.state.x)

    @property
    def dt(self) -> float:
        return self.robot.config.dt

    @property
    def applied(self) -> np.ndarray:
        return self.regulators.state.copy()

    def reset(self) -> State:
        """Rest state, regulators at 0 kPa, ``settle_steps`` zero-pressure steps; t := 0.

        Raises:
            SimulationDiverged: if settling diverges.
        """
        self.regulators.reset()
        state = self.robot.model.rest_state()
        zero = self.robot.control(np.zeros(N_REGULATORS))
        for _ in range(self.settle_steps):
            state = self.solver.step(state, zero)
        self.state = dataclasses.replace(state, t=0.0)
        self.start = self.robot.reward_position(self.state.x)
        return self.state

    def step(self, command: np.ndarray) -> State:
        """Advance one ``dt`` with regulator commands ``(3,)`` real kPa.

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


@dataclass(frozen=True, eq=False)
class EpisodeResult:
    """Record of one episode. Row ``i`` of the per-step arrays is time ``t_i = i * dt``
    (row 0: after settling); pressures in row ``i`` are those held during the step that
    ended at ``t_i`` (row 0: zeros). If the run diverged, the arrays stop at the last
    valid state.

    Attributes:
        time: ``(n + 1,)`` s.
        position: ``(n + 1, 3)`` disk top-centre position, mm.
        commanded, applied: ``(n + 1, 3)`` regulator pressures, real kPa.
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

    @property
    def real_time_factor(self) -> float:
        """Simulated seconds per wall-clock second."""
        return self.sim_seconds / self.wall_seconds if self.wall_seconds > 0 else float("inf")


def run_episode(robot: Robot, gait, duration: float = 20.0,
                calibration: PressureCalibration = PressureCalibration(), settle_steps: int = SETTLE_STEPS,
                record_every: int | None = 1, progress: bool = True,
                on_frame: Callable[[float, np.ndarray], None] | None = None) -> EpisodeResult:
    """Simulate one open-loop episode.

    Args:
        robot: the assembled robot.
        gait: object with ``pressure_at(t) -> (3,)`` commanded real kPa (regulators 1..3),
            queried at the start ``t = k * dt`` of each step ``k``.
        duration: episode length, s (rounded to whole steps of ``robot.config.dt``).
        calibration: real-to-sim pressure map.
        settle_steps: zero-pressure steps before the episode (not counted).
        record_every: store all node positions every this many steps (and at t = 0);
            None stores none.
        progress: show a tqdm bar (steps/s, ETA) on stderr.
        on_frame: called as ``on_frame(t, x)`` (s, ``(N, 3)`` mm) for each recorded frame.

    Returns:
        The :class:`EpisodeResult`. A :class:`SimulationDiverged` (settling included) is
        caught: ``diverged=True``, ``reason`` set, arrays truncated at the last valid state.

    Raises:
        ValueError: non-positive duration or record_every.
        PressureRangeError: if the gait commands a pressure outside [0, 90] kPa.
    """
    dt = robot.config.dt
    n = int(round(duration / dt)) if np.isfinite(duration) else 0
    if n < 1:
        raise ValueError(f"duration must be at least one time step ({dt} s), got {duration} s")
    if record_every is not None and record_every < 1:
        raise ValueError(f"record_every must be >= 1 or None, got {record_every}")
    ep = Episode(robot, calibration, settle_steps)
    pos, cmd, app = np.zeros((n + 1, 3)), np.zeros((n + 1, 3)), np.zeros((n + 1, 3))
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
            cmd[k + 1] = gait.pressure_at(k * dt)
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
        diverged=bool(reason), reason=reason,
    )
