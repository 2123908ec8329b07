"""Open-loop episodes of many designs on the JAX engine: ``evaluate([(design, gait, duration), ...])``.

What :class:`softcrawl.codesign.groundtruth.DesignEvaluator` does for one design on the CPU
reduced engine (:func:`softcrawl.robot.episode.run_episode` from a cached
:func:`~softcrawl.robot.episode.settle`), for a batch of requests of many designs at once:

* each design's model rows are gathered from the space's design table
  (:class:`~softcrawl.jaxsim.tables.DesignTable`: no robot is built per design) and it is
  settled once per machine, by the CPU rule (:class:`~softcrawl.robot.episode.Settling` in
  steps of the robot's ``dt``, :func:`~softcrawl.jaxsim.engine.make_settle`); its rested state
  is kept, and cached on disk (:class:`~softcrawl.jaxsim.tables.SettledStates`);
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

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace
from softcrawl.fem.solver import SolverSettings
from softcrawl.gaits.periodic import PeriodicGait
from softcrawl.gaits.pressure import P_MAX_KPA, P_MIN_KPA, check_pressures
from softcrawl.jaxsim.batch import in_batches, padded_size, stack_padded
from softcrawl.jaxsim.engine import make_schedule_rollout
from softcrawl.jaxsim.model import engine_dtype
from softcrawl.jaxsim.tables import DesignTable, SettledStates, build_table
from softcrawl.robot.actuation import PressureCalibration
from softcrawl.robot.assembly import RobotConfig
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
    :func:`softcrawl.robot.run_episode` commands at step ``k`` (a step-waveform
    :class:`~softcrawl.gaits.periodic.PeriodicGait`'s, the ground truth's search episodes, for
    all steps at once: the same values, about 100 times faster).

    Raises:
        PressureRangeError: a command is non-finite or outside [0, 90] kPa.
    """
    if isinstance(gait, PeriodicGait) and gait.waveform == "step":
        # PeriodicGait.pressure_at's step rule for every step at once (the same float operations)
        u = (np.arange(n_steps) * dt) / gait.hold
        at = np.floor(u + 1e-9).astype(np.int64)
        cmd = np.clip(np.stack([np.asarray(p, float)[at % len(p)] for p in gait.patterns], axis=1), P_MIN_KPA,
                      P_MAX_KPA)
    else:
        cmd = np.array([gait.pressure_at(k * dt) for k in range(n_steps)], float).reshape(n_steps, -1)
    check_pressures(cmd, "gait command")
    return cmd


@dataclass(frozen=True, eq=False)
class SettledDesign:
    """A design's rested state (numpy on the host, no batch axis).

    Attributes:
        legs: leg count (its group, and the leg slots of its state);
        state: the rested :class:`~softcrawl.jaxsim.engine.State` (``t = 0``);
        start_x: x of the disk's top-centre node at rest, mm; steps: settling steps;
        at_rest: whether the rest rule was met before the cap; diverged: whether settling did
            (:func:`~softcrawl.jaxsim.rig.healthy` false).
    """

    legs: int
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
            the next power of two. Where the device runs out of memory on a batch, it is halved
            and the batch run again (a warning; :func:`softcrawl.jaxsim.batch.halved_on_memory`),
            settling included.
        diverged_cm: the score of a diverged episode
            (:data:`softcrawl.codesign.groundtruth.DIVERGED_CM`).
        leg_contacts, disk_contacts, solver, iterations: the contact solve (:func:`build_model`).
        space: the design space of the designs (their slots, regulators and parts; its
            design table is built from ``build_robot(design, config, space=space)``, so
            ``config`` is that space's, :meth:`~softcrawl.robot.RobotConfig.for_space`).
        settled_folder: the settled-state cache's folder (default
            :func:`~softcrawl.jaxsim.tables.settled_cache_dir`).

    Attributes:
        settles: designs made ready so far (each once): settled now, or read from the
        settled-state cache; episodes, sim_seconds: episodes run and their simulated seconds;
        robot_steps: robot-steps computed, padding included; table, states: the space's
        :class:`~softcrawl.jaxsim.tables.DesignTable` and
        :class:`~softcrawl.jaxsim.tables.SettledStates` (None until the first design is
        prepared; ``states.settled`` and ``states.loaded`` count the designs settled and read).

    Raises:
        ValueError: a config that is not reduced, an unknown precision, float64 without
            ``jax_enable_x64``, or a ``max_batch`` that is not a power of two.
    """

    def __init__(self, config: RobotConfig, precision: str = "float32", settling: Settling = Settling(),
                 calibration: PressureCalibration = PressureCalibration(), rate_kpa_s: float = 150.0,
                 max_batch: int = 64, diverged_cm: float = -100.0, leg_contacts: int = 12,
                 disk_contacts: int = 8, solver: str = "apgd", iterations: int | None = None,
                 space: DesignSpace = DEFAULT_SPACE, settled_folder: str | os.PathLike | None = None):
        if config.model != "reduced" or config.reduced_disk != "floating":
            raise ValueError("the JAX engine steps reduced robots with a floating disk "
                             f"(RobotConfig(model='reduced')), got model={config.model!r}, "
                             f"reduced_disk={config.reduced_disk!r}")
        dtype = engine_dtype(precision)
        if max_batch < 1 or max_batch & (max_batch - 1):
            raise ValueError(f"max_batch must be a power of two, got {max_batch}")
        self.config, self.precision, self.settling, self.space = config, precision, settling, space
        self.max_batch, self.diverged_cm = int(max_batch), float(diverged_cm)
        self._model_kw = dict(leg_contacts=leg_contacts, disk_contacts=disk_contacts, solver=solver,
                              iterations=iterations, dtype=dtype, calibration=calibration, rate_kpa_s=rate_kpa_s)
        self._settled_folder = settled_folder
        self._rollout = make_schedule_rollout()
        self.table: DesignTable | None = None  # built with the first design
        self.states: SettledStates | None = None
        self._designs: dict[Design, SettledDesign] = {}
        self.settles, self.episodes, self.sim_seconds, self.robot_steps = 0, 0, 0.0, 0

    def settled(self, design) -> SettledDesign:
        """The cached :class:`SettledDesign` of ``design`` (settled now if new)."""
        self.prepare([design])
        return self._designs[self.space.canonicalize(design)]

    def prepare(self, designs: Sequence) -> None:
        """Settle the designs not ready yet (or read them from the settled-state cache), in
        batches of one leg count; the design table is built with the first.

        Raises:
            InvalidDesignError: an invalid design.
        """
        new = [d for d in dict.fromkeys(self.space.canonicalize(d) for d in designs) if d not in self._designs]
        if not new:
            return
        if self.table is None:
            self.table = build_table(self.space, self.config, **self._model_kw)
            self.states = SettledStates(self.table, self.settling, self._settled_folder)
        cap = self.states.rule[2]
        node = self.table.parts.disk.reward_node
        for d, r in zip(new, self.states.get(new, batch=self.max_batch, base=2, smallest=1)):
            self._designs[d] = SettledDesign(sum(v > 0 for v in d), r.state, float(r.state.x[node, 0]), r.steps,
                                             r.steps < cap, not r.ok)
            self.settles += 1

    def forget(self, designs: Sequence) -> None:
        """Drop the rested states of ``designs`` from memory (designs whose episodes are done; a
        later request prepares them again, from the settled-state cache), so that a long run
        holds only the designs in use.

        Raises:
            InvalidDesignError: an invalid design.
        """
        for d in designs:
            self._designs.pop(self.space.canonicalize(d), None)

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
                JaxRuntimeError: the device's, other than a lack of memory of a batch of more
                than one robot (those halve ``max_batch``).
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
            results, self.max_batch = in_batches(
                idx, self.max_batch, lambda k, b: padded_size(k, b, 2, 1),
                lambda chunk, _: self._run([designs[j] for j in chunk], [commands[j] for j in chunk]), "episodes")
            for j, result in zip(idx, results):
                out[j] = result
            self.episodes += len(idx)
            self.sim_seconds += len(idx) * n * dt
        return out

    def _run(self, designs: list[Design], commands: list[np.ndarray]) -> list[tuple[float, bool]]:
        """One padded batch of episodes of equal length and leg count (ready designs)."""
        size = padded_size(len(designs), self.max_batch, 2, 1)
        pad = size - len(designs)
        designs, commands = designs + designs[-1:] * pad, commands + commands[-1:] * pad
        ready = [self._designs[d] for d in designs]
        model = self.table.model(designs, ready[0].legs)
        state = stack_padded([d.state for d in ready], size)
        dtype = state.x.dtype
        final, peak, _ = self._rollout(model, state, jnp.asarray(np.stack(commands), dtype))
        self.robot_steps += size * commands[0].shape[0]
        x = np.asarray(final.x[:, model.disk.reward_node, 0], float)
        bad = np.asarray(final.bad) > 0
        fast = np.asarray(peak, float) > SolverSettings.max_speed
        out = []
        for b, d in enumerate(ready[:size - pad]):
            reward = (x[b] - d.start_x) / MM_PER_CM
            diverged = bool(d.diverged or bad[b] or fast[b] or not math.isfinite(reward))
            out.append((self.diverged_cm if diverged else float(reward), diverged))
        return out
