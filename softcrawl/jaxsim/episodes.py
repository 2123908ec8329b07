"""Open-loop episodes of many designs on the JAX engine: ``evaluate([(design, gait, duration), ...])``.

What :class:`softcrawl.codesign.groundtruth.DesignEvaluator` does for one design on the CPU
reduced engine (:func:`softcrawl.robot.episode.run_episode` from a cached
:func:`~softcrawl.robot.episode.settle`), for a batch of requests of many designs at once:

* each design is built (:func:`softcrawl.robot.build_robot`) and settled once, by the CPU rule
  (:class:`~softcrawl.robot.episode.Settling` in steps of the robot's ``dt``,
  :func:`~softcrawl.jaxsim.engine.make_settle`); its model rows and rested state are cached;
* each request's regulator commands are computed on the host exactly as ``run_episode``
  commands them, ``gait.pressure_at(k dt)`` for step ``k`` (real kPa, range-checked);
* requests are grouped by leg count (a 3-legged batch is not padded to 6 legs) and episode
  length, and each group runs as batches padded to a power of two
  (:func:`~softcrawl.jaxsim.engine.make_schedule_rollout`: one compiled program per leg count,
  batch size and length);
* the reward is the +x displacement of the disk's top-centre node from the rested pose, cm; an
  episode diverged when an element inverted, a value went non-finite or a node outran the CPU
  engine's divergence speed (:attr:`softcrawl.fem.solver.SolverSettings.max_speed`), or when
  its design's settling did; it then scores ``diverged_cm``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.fem.solver import SolverSettings
from softcrawl.gaits.pressure import check_pressures
from softcrawl.jaxsim.batch import padded_size, robot_rows, stack_padded, take
from softcrawl.jaxsim.engine import make_schedule_rollout, make_settle, rest_state
from softcrawl.jaxsim.model import Model, build_model, disk_inverse, engine_dtype
from softcrawl.robot.actuation import PressureCalibration
from softcrawl.robot.assembly import RobotConfig, build_robot
from softcrawl.robot.episode import MM_PER_CM, Settling

def episode_steps(duration: float, dt: float) -> int:
    """Steps of an episode of ``duration`` s at ``dt`` s, as :func:`softcrawl.robot.run_episode`
    rounds it.

    Raises:
        ValueError: a duration shorter than one step, or not finite.
    """
    n = int(round(duration / dt)) if math.isfinite(duration) else 0
    if n < 1:
        raise ValueError(f"duration must be at least one time step ({dt} s), got {duration} s")
    return n


def gait_commands(gait, n_steps: int, dt: float) -> np.ndarray:
    """``(n_steps, R)`` real kPa: row ``k`` is ``gait.pressure_at(k dt)``, what
    :func:`softcrawl.robot.run_episode` commands at step ``k``.

    Raises:
        PressureRangeError: a command is non-finite or outside [0, 90] kPa.
    """
    cmd = np.array([gait.pressure_at(k * dt) for k in range(n_steps)], float).reshape(n_steps, -1)
    check_pressures(cmd, "gait command")
    return cmd


@dataclass(frozen=True, eq=False)
class SettledDesign:
    """A design's cached model rows and rested state (numpy on the host, no batch axis).

    Attributes:
        legs: leg count (its group); rows: its :class:`~softcrawl.jaxsim.model.RobotData`;
        state: the rested :class:`~softcrawl.jaxsim.engine.State` (``t = 0``);
        start_x: x of the disk's top-centre node at rest, mm; steps: settling steps;
        at_rest: whether the rest rule was met before the cap; diverged: whether settling did.
    """

    legs: int
    rows: object
    state: object
    start_x: float
    steps: int
    at_rest: bool
    diverged: bool


class JaxEvaluator:
    """Batched open-loop episodes of many designs on the JAX engine (module doc).

    Args:
        config: the reduced robots' :class:`~softcrawl.robot.RobotConfig` (``model="reduced"``,
            floating disk: what :func:`~softcrawl.jaxsim.model.build_model` steps).
        precision: ``"float32"`` or ``"float64"`` (the latter needs ``jax_enable_x64``, which the
            caller sets).
        settling: the rest rule before each episode (:func:`softcrawl.robot.settle`'s).
        calibration, rate_kpa_s: the real-to-sim pressure warp and the regulators' slew, kPa/s.
        max_batch: largest batch of one call (a power of two); smaller groups are padded to
            the next power of two.
        diverged_cm: the score of a diverged episode
            (:data:`softcrawl.codesign.groundtruth.DIVERGED_CM`).
        leg_contacts, disk_contacts, sweeps: the contact solve (:func:`build_model`).
        space: the design space of the designs (their slots, regulators and parts; built with
            ``build_robot(design, config, space=space)``, so ``config`` is that space's,
            :meth:`~softcrawl.robot.RobotConfig.for_space`).

    Attributes:
        settles: designs settled so far (each once); episodes, sim_seconds: episodes run and
        their simulated seconds; robot_steps: robot-steps computed, padding included.

    Raises:
        ValueError: a config that is not reduced, an unknown precision, float64 without
            ``jax_enable_x64``, or a ``max_batch`` that is not a power of two.
    """

    def __init__(self, config: RobotConfig, precision: str = "float32", settling: Settling = Settling(),
                 calibration: PressureCalibration = PressureCalibration(), rate_kpa_s: float = 150.0,
                 max_batch: int = 64, diverged_cm: float = -100.0, leg_contacts: int = 12,
                 disk_contacts: int = 8, sweeps: int = 100, space: DesignSpace = DEFAULT_SPACE):
        if config.model != "reduced" or config.reduced_disk != "floating":
            raise ValueError("the JAX engine steps reduced robots with a floating disk "
                             f"(RobotConfig(model='reduced')), got model={config.model!r}, "
                             f"reduced_disk={config.reduced_disk!r}")
        dtype = engine_dtype(precision)
        if max_batch < 1 or max_batch & (max_batch - 1):
            raise ValueError(f"max_batch must be a power of two, got {max_batch}")
        self.config, self.precision, self.settling, self.space = config, precision, settling, space
        self.max_batch, self.diverged_cm = int(max_batch), float(diverged_cm)
        self._model_kw = dict(leg_contacts=leg_contacts, disk_contacts=disk_contacts, sweeps=sweeps,
                              dtype=dtype, calibration=calibration, rate_kpa_s=rate_kpa_s)
        hold, cap = settling.steps(config.dt)
        self._settle = make_settle(settling.rest_speed, hold, cap)
        self._rollout = make_schedule_rollout()
        self._parts: Model | None = None  # the shared leg, disk and settings (robot rows None)
        self._inverse: np.ndarray | None = None  # the disk's A_0^-1, float64 (exact attachment rows)
        self._designs: dict[Design, SettledDesign] = {}
        self.settles, self.episodes, self.sim_seconds, self.robot_steps = 0, 0, 0.0, 0

    def settled(self, design) -> SettledDesign:
        """The cached :class:`SettledDesign` of ``design`` (settled now if new)."""
        self.prepare([design])
        return self._designs[self.space.canonicalize(design)]

    def _model(self, rows) -> Model:
        return dataclasses.replace(self._parts, robot=rows)

    def prepare(self, designs: Sequence) -> None:
        """Build and settle the designs not cached yet, in batches of one leg count.

        Raises:
            InvalidDesignError: an invalid design.
        """
        _, cap = self.settling.steps(self.config.dt)
        new: dict[int, list] = {}
        for d in dict.fromkeys(self.space.canonicalize(d) for d in designs):
            if d in self._designs:
                continue
            robot = build_robot(d, self.config, space=self.space)
            if self._parts is None:  # the shared parts, built once
                self._parts = dataclasses.replace(build_model([robot], **self._model_kw), robot=None)
                self._inverse = disk_inverse(robot)
            legs = len(robot.legs)
            new.setdefault(legs, []).append((d, robot_rows(self._parts, robot, legs, self._inverse)))
        for legs, items in new.items():
            for i in range(0, len(items), self.max_batch):
                chunk = items[i:i + self.max_batch]
                model = self._model(stack_padded([r for _, r in chunk], padded_size(len(chunk), self.max_batch, 2, 1)))
                state, steps = self._settle(model, rest_state(model))
                node = model.disk.reward_node
                for b, (d, rows) in enumerate(chunk):
                    st = take(state, b)
                    n = int(steps[b])
                    self._designs[d] = SettledDesign(
                        legs, rows, st, float(st.x[node, 0]), n, n < cap,
                        bool(int(st.bad) > 0 or not np.isfinite(st.x).all()))
                    self.settles += 1

    def evaluate(self, requests: Sequence[tuple]) -> list[tuple[float, bool]]:
        """``(reward_cm, diverged)`` of each ``(design, gait, duration)`` request, in order.

        Args:
            requests: designs (one value per slot of the space, or a string), gaits
                (``pressure_at(t) -> (R,)`` real kPa, ``R`` the space's regulators) and episode
                lengths (s, rounded to whole steps of ``config.dt``).

        Returns:
            Per request the +x crawl of the disk's top centre, cm, and whether the episode
            diverged (its reward then ``diverged_cm``).

        Raises:
            InvalidDesignError: an invalid design. ValueError: a duration under one step, a gait
                that does not command ``R`` pressures. PressureRangeError: a gait commands a
                pressure outside [0, 90] kPa. All are raised before anything is simulated.
        """
        dt = self.config.dt
        designs = [self.space.canonicalize(d) for d, _, _ in requests]
        steps = [episode_steps(float(T), dt) for _, _, T in requests]
        commands = [gait_commands(g, n, dt) for (_, g, _), n in zip(requests, steps)]
        n_reg = self.space.n_regulators
        for (_, g, _), c in zip(requests, commands):
            if c.shape[1] != n_reg:
                raise ValueError(f"gait {g!r} commands {c.shape[1]} pressures; the space {self.space.name!r} has "
                                 f"{n_reg} regulators")
        self.prepare(designs)
        groups: dict[tuple[int, int], list[int]] = {}
        for i, (d, n) in enumerate(zip(designs, steps)):
            groups.setdefault((self._designs[d].legs, n), []).append(i)
        out: list[tuple[float, bool]] = [(self.diverged_cm, True)] * len(requests)
        for (_, n), idx in groups.items():
            for i in range(0, len(idx), self.max_batch):
                chunk = idx[i:i + self.max_batch]
                for j, result in zip(chunk, self._run([self._designs[designs[j]] for j in chunk],
                                                      [commands[j] for j in chunk])):
                    out[j] = result
                self.episodes += len(chunk)
                self.sim_seconds += len(chunk) * n * dt
        return out

    def _run(self, designs: list[SettledDesign], commands: list[np.ndarray]) -> list[tuple[float, bool]]:
        """One padded batch of episodes of equal length and leg count."""
        size = padded_size(len(designs), self.max_batch, 2, 1)
        pad = size - len(designs)
        designs, commands = designs + designs[-1:] * pad, commands + commands[-1:] * pad
        model = self._model(stack_padded([d.rows for d in designs], size))
        state = stack_padded([d.state for d in designs], size)
        dtype = state.x.dtype
        final, peak, _ = self._rollout(model, state, jnp.asarray(np.stack(commands), dtype))
        self.robot_steps += size * commands[0].shape[0]
        x = np.asarray(final.x[:, model.disk.reward_node, 0], float)
        bad = np.asarray(final.bad) > 0
        fast = np.asarray(peak, float) > SolverSettings.max_speed
        out = []
        for b, d in enumerate(designs[:size - pad]):
            reward = (x[b] - d.start_x) / MM_PER_CM
            diverged = bool(d.diverged or bad[b] or fast[b] or not math.isfinite(reward))
            out.append((self.diverged_cm if diverged else float(reward), diverged))
        return out
