"""All envs of a run in one process, their robots stepped by the JAX engine as one batch on
JAX's default device (``backend="jax"``).

:class:`JaxBackend` holds the :class:`~softcrawl.envs.crawler.CrawlerEnv` objects for what they
do besides physics (drawing designs and domain samples from their RNGs at reset, actions,
history, observations, rewards, ``info``; :meth:`CrawlerEnv.begin_reset`/``end_reset`` and
``begin_action``/``end_action``) and keeps the robots in a fixed batch of ``N`` rows of the
JAX engine (:mod:`softcrawl.jaxsim`) with as many leg slots as the largest design of the envs'
design lists. A vectorised step is one compiled call for all envs
(:func:`softcrawl.jaxsim.rig.make_action_rollout`: every live env holds its action for its
steps, through its own regulators and pressure warp); so is a whole episode of every env
from its actions (:meth:`JaxBackend.run_episodes`, for open-loop policies). A reset writes the
reset envs' rows (robot data, settled state, rig) into the batch by index; the robot rows and
settled states are kept per design (LRU). The rows of the designs not kept yet are gathered from the space's
design table (:class:`~softcrawl.jaxsim.tables.DesignTable`, built once from the robots of two
or so designs), their rested states read from the machine's settled-state cache
(:class:`~softcrawl.jaxsim.tables.SettledStates`) or settled together in one call. No CPU solver
is built or stepped.

The transitions have the format and meaning of the CPU backends' (:mod:`softcrawl.envs.crawler`):
an env whose state becomes invalid (inverted elements, ``state.bad > 0``, or non-finite values)
keeps its last valid state, terminates with ``info["diverged"]`` and its ``reason``, and leaves
the other envs untouched. What differs is the physics: the JAX engine's contact solve (a fixed
number of Gauss-Seidel sweeps over fixed contact sets) against the CPU engine's exact polish
(tests/test_jax_backend.py bounds the difference), its settling rule
(:func:`~softcrawl.jaxsim.engine.make_settle`; ``info["at_rest"]``: the rule was met before the
step cap), and no runaway-speed check.

Domain randomization: the rig quantities only (:data:`softcrawl.envs.backends.jaxcheck.RANDOMIZED`);
a range of friction, Young's modulus or mass is refused (:func:`~softcrawl.envs.backends.jaxcheck.check_jax_env`).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from collections import OrderedDict
from dataclasses import dataclass

import jax
import jax.numpy as jnp
import numpy as np

from softcrawl.envs.backends.jaxcheck import check_jax_task, check_randomized, resolve_precision
from softcrawl.envs.backends.serial import SerialBackend
from softcrawl.envs.crawler import CrawlerEnv, action_to_kpa
from softcrawl.fem.solver import SimulationDiverged
from softcrawl.jaxsim.batch import padded_size, put_rows, stack_padded, take
from softcrawl.jaxsim.engine import rest_state
from softcrawl.jaxsim.rig import Rig, make_action_rollout
from softcrawl.jaxsim.tables import SettledStates, build_table
from softcrawl.robot.episode import MM_PER_CM, SettledState

#: Memory for the per-design cache of robot rows and settled states, MB (default).
CACHE_MB = 256.0


class _RewardPoint:
    """The robot as :class:`CrawlerEnv` reads it from an episode: one node, the reward point."""

    reward_node = 0

    @staticmethod
    def reward_position(x) -> np.ndarray:
        return np.asarray(x[0], dtype=float).copy()


@dataclass(frozen=True)
class PointState:
    """The reward point's position (mm) and velocity (mm/s), each ``(1, 3)``."""

    x: np.ndarray
    v: np.ndarray


class JaxEpisode:
    """What :class:`CrawlerEnv` reads of its :class:`~softcrawl.robot.episode.Episode` (the
    reward point's state, the regulators' outputs, ``start``, ``dt``, ``settled``) for a robot
    that lives in a :class:`JaxBackend`'s batch.

    Args:
        dt: simulator step, s. point: ``(2, 3)`` the settled reward point's position (mm) and
            velocity (mm/s). settled: the settling statistics (None: settling diverged).
        n_regulators: ``R``, the regulators of the env's design space.
    """

    robot = _RewardPoint()

    def __init__(self, dt: float, point: np.ndarray, settled: SettledState | None, n_regulators: int):
        self.dt, self.settled = dt, settled
        self.update(point, np.zeros(n_regulators))
        self.start = self.state.x[0].copy()

    def reset(self) -> None:
        """Raises SimulationDiverged if the robot's settling diverged."""
        if self.settled is None:
            raise SimulationDiverged("invalid state (JAX engine: inverted elements or non-finite values)", 0.0)

    def update(self, point: np.ndarray, applied: np.ndarray) -> None:
        """The state after an action: ``point`` ``(2, 3)`` as in the constructor, ``applied``
        ``(R,)`` regulator outputs, real kPa."""
        point = np.asarray(point, dtype=float)
        self.state = PointState(point[:1].copy(), point[1:].copy())
        self.applied = np.asarray(applied, dtype=float).copy()

    @property
    def displacement_cm(self) -> float:
        """+x displacement of the reward point since the reset, cm."""
        return float(self.state.x[0, 0] - self.start[0]) / MM_PER_CM


@dataclass(frozen=True, eq=False)
class _Design:
    """A design's cached rows: robot data (numpy), settled state (numpy), settling statistics
    (None: diverged) and the settled reward point ``(2, 3)``; bytes: their memory."""

    rows: object
    state: object
    settled: SettledState | None
    point: np.ndarray
    bytes: int


def _nbytes(tree) -> int:
    return sum(np.asarray(a).nbytes for a in jax.tree_util.tree_leaves(tree))


class JaxBackend(SerialBackend):
    """All envs in this process, their robots one JAX batch (module doc).

    Args:
        env_fns: one zero-argument constructor per env, each giving a :class:`CrawlerEnv` of a
            reduced robot with the floating-frame disk; all with the same robot factory,
            settling rule, pressure calibration and design space (any slots and regulators whose
            leg has a reduction).
        precision: ``"float64"`` (sets ``jax_enable_x64``), ``"float32"`` (clears it) or
            ``"auto"`` (float32 on a GPU, float64 elsewhere:
            :func:`~softcrawl.envs.backends.jaxcheck.resolve_precision`). JAX's setting is
            process-wide: set here, once, never at import.
        solver, iterations: the engine's contact solve (:func:`~softcrawl.jaxsim.model.build_model`;
            for ``"pgs"`` without ``iterations``, the robots' ``contact_max_iterations`` sweeps).
        cache_mb: memory of the per-design cache of robot rows and settled states, MB (at
            least one design per env is kept).

    Raises:
        ValueError: no env, an env that is not a :class:`CrawlerEnv`, envs that differ in robot
            factory, settling or calibration, randomization the JAX engine cannot draw, a task it
            cannot score (:func:`~softcrawl.envs.backends.jaxcheck.check_jax_task`), an
            unknown precision, a robot model the JAX engine cannot step (not reduced, no
            floating-frame disk).
    """

    def __init__(self, env_fns, precision: str = "auto", solver: str = "apgd", iterations: int | None = None,
                 cache_mb: float = CACHE_MB):
        precision = resolve_precision(precision)
        super().__init__(env_fns)
        envs = self.envs
        first = envs[0]
        if not all(isinstance(env, CrawlerEnv) for env in envs):
            raise ValueError('backend "jax" runs CrawlerEnv environments only')
        for env in envs:
            check_randomized(env.randomize)
            check_jax_task(env.task)
            if (env.robot_factory, env.settling, env.calibration) != (first.robot_factory, first.settling,
                                                                      first.calibration):
                raise ValueError('backend "jax" needs envs of one robot factory, settling rule and calibration')
            if env.space != first.space:
                raise ValueError('backend "jax" needs envs of one design space')
        jax.config.update("jax_enable_x64", precision == "float64")
        self.precision = precision
        n = self.num_envs
        lists = {id(env.designs): env.designs for env in envs}.values()  # envs share their lists
        slots = max(sum(v > 0 for v in d) for designs in lists for d in designs)
        if solver == "pgs" and iterations is None:
            iterations = first.robot_factory(first.designs[0]).config.contact_max_iterations
        self._table = build_table(first.space, factory=first.robot_factory, n_slots=slots,
                                  calibration=first.calibration, solver=solver, iterations=iterations)
        self._model = self._table.model([first.designs[0]] * n)
        self._dtype = np.dtype(self._model.disk.rest.dtype)
        self._state = rest_state(self._model)
        self._n_reg = first.space.n_regulators
        ones, zeros = np.ones((n, self._n_reg), self._dtype), np.zeros((n, self._n_reg), self._dtype)
        self._rig = jax.tree_util.tree_map(jnp.asarray, Rig(ones, zeros, zeros, zeros))
        self._dt = float(self._model.settings.dt)
        self._steps_max = max(self._longest_action(env) for env in envs)
        rollout = make_action_rollout(self._steps_max)
        node = self._model.disk.reward_node

        @jax.jit
        def advance(model, rig, state, command, steps):
            state, diverged = rollout(model, rig, state, command, steps)
            point = jnp.stack([state.x[:, node], state.v[:, node]], axis=1)
            return state, diverged, point, state.pressure, state.t

        self._advance = advance

        @jax.jit
        def episode(model, rig, state, command, steps):
            def action(carry, inputs):
                state, dead = carry
                state, diverged = rollout(model, rig, state, inputs[0], jnp.where(dead, 0, inputs[1]))
                point = jnp.stack([state.x[:, node], state.v[:, node]], axis=1)
                return (state, dead | diverged), (diverged, point, state.pressure, state.t)

            start = (state, jnp.zeros(steps.shape[0], bool))
            (state, _), outputs = jax.lax.scan(action, start, (command.swapaxes(0, 1), steps.T))
            return state, outputs

        self._episode = episode
        self._settled = SettledStates(self._table, first.settling)
        self._cap = self._settled.rule[2]
        self._cache: OrderedDict = OrderedDict()  # design -> _Design, LRU
        self._cache_mb = float(cache_mb)
        self._pending = None
        self._episodes: list[JaxEpisode | None] = [None] * n
        device = jax.devices()[0]
        print(f'softcrawl: backend "jax": {n} envs in one batch ({slots} leg slots) on {device.platform}:{device.id} '
              f"({device.device_kind}), {precision}, contact solve {solver} x {self._model.settings.iterations}",
              file=sys.stderr)

    @property
    def settings(self):
        """The engine's :class:`~softcrawl.jaxsim.model.Settings` (step, floor, contact solve)."""
        return self._model.settings

    @staticmethod
    def _longest_action(env: CrawlerEnv) -> int:
        """Most simulator steps of one action of ``env`` (the control-period dilation rounds
        ``d n`` steps to whole ones: at most ``floor(d_max n) + 1``)."""
        n = env.nominal_steps_per_action
        period = env.randomize.control_period if env.randomize is not None else None
        return n if period is None else math.floor(period[1] * n) + 1

    # -- designs ------------------------------------------------------------------------
    def _settle_designs(self, designs: list) -> list[_Design]:
        """The cache entries of ``designs`` (distinct): their rows gathered from the design
        table, their rested states read from the settled-state cache or settled together."""
        rows = self._table.rows(designs)
        node = self._model.disk.reward_node
        out = []
        for j, rested in enumerate(self._settled.get(designs, self._table.n_slots, batch=self.num_envs)):
            r, s = take(rows, j), rested.state
            settled = None
            if rested.ok:
                k = rested.steps
                settled = SettledState(None, k, k * self._dt, rested.speed, k < self._cap)
            out.append(_Design(r, s, settled, np.stack([s.x[node], s.v[node]]), _nbytes(r) + _nbytes(s)))
        return out

    def _designs(self, designs: list) -> list[_Design]:
        """The cache entries of ``designs`` (the missing ones settled together, first)."""
        new = list(dict.fromkeys(d for d in designs if d not in self._cache))
        if new:
            self._cache.update(zip(new, self._settle_designs(new)))
        out = []
        for d in designs:
            self._cache.move_to_end(d)
            out.append(self._cache[d])
        keep = max(self.num_envs, int(self._cache_mb * 1e6 / max(1, out[0].bytes)))
        while len(self._cache) > keep:
            self._cache.popitem(last=False)
        return out

    # -- EnvBackend -----------------------------------------------------------------------
    def reset(self, indices, designs, seeds):
        """Reset envs ``indices``: each env draws its design (unless given) and domain sample
        (:meth:`CrawlerEnv.begin_reset`); the designs' rows and settled states (cached, or
        settled now, together) and the samples' rigs are written into the batch; returns each
        env's ``(obs, info)`` (:meth:`CrawlerEnv.end_reset`)."""
        indices = list(indices)
        if not indices:
            return []
        drawn = [self.envs[i].begin_reset(seed=s, options={"design": d}) for i, d, s in zip(indices, designs, seeds)]
        entries = self._designs(drawn)
        rigs = [self._rig_of(self.envs[i]) for i in indices]
        size = padded_size(len(indices), self.num_envs)
        index = np.full(size, self.num_envs, np.int32)
        index[:len(indices)] = indices
        rows = (stack_padded([e.rows for e in entries], size), stack_padded([e.state for e in entries], size),
                stack_padded(rigs, size))
        robot, self._state, self._rig = put_rows((self._model.robot, self._state, self._rig), index, rows)
        self._model = dataclasses.replace(self._model, robot=robot)
        out = []
        for i, e in zip(indices, entries):
            self._episodes[i] = JaxEpisode(self._dt, e.point, e.settled, self._n_reg)
            out.append(self.envs[i].end_reset(self._episodes[i]))
        return out

    def _rig_of(self, env: CrawlerEnv):
        """The :class:`~softcrawl.jaxsim.rig.Rig` row ``(R,)`` per field of ``env``'s domain sample."""
        s, n = env.domain, self._n_reg
        pick = (lambda v, nominal: np.asarray(v if v is not None else (nominal,) * n, self._dtype))
        if s is None:
            return Rig(pick(None, 1.0), pick(None, 0.0), pick(None, 0.0), pick(None, 0.0))
        return Rig(pick(s.pressure_gain, 1.0), pick(s.pressure_offset, 0.0), pick(s.tau_inflate, 0.0),
                   pick(s.tau_vent, 0.0))

    def step(self, actions):
        """Step every env with its action ``actions[i]`` ``(R,)``: one compiled call for all live
        envs, then each env's transition (no auto-reset)."""
        return self._finish(*self._launch(actions))

    def step_send(self, actions) -> None:
        """Start :meth:`step`: the envs' actions are taken and the batch's rollout is dispatched
        (JAX runs it asynchronously: the learner's updates overlap it); :meth:`step_recv` waits."""
        self._pending = self._launch(actions)

    def step_recv(self):
        pending, self._pending = self._pending, None
        return self._finish(*pending)

    def _launch(self, actions):
        """Begin every env's action and dispatch the rollout of the live ones; returns
        ``(steps, outputs)`` (outputs None: no env is live)."""
        command = np.zeros((self.num_envs, self._n_reg), self._dtype)
        steps = np.zeros(self.num_envs, np.int32)
        for i, (env, a) in enumerate(zip(self.envs, actions)):
            kpa = env.begin_action(a)
            if kpa is not None:
                command[i], steps[i] = kpa, env.steps_per_action
        if steps.max() > self._steps_max:  # pragma: no cover - _longest_action bounds it
            raise RuntimeError(f"an action of {steps.max()} steps exceeds the compiled {self._steps_max}")
        if not steps.any():
            return steps, None
        self._state, *outputs = self._advance(self._model, self._rig, self._state, command, steps)
        return steps, outputs

    # -- whole episodes (open-loop policies) ------------------------------------------------
    def run_episodes(self, actions):
        """Every env's whole episode from its start (all envs just reset) with its actions
        ``actions[i]`` ``(n_actions, R)``: one compiled call for all envs and the whole episode
        (``jax.lax.scan`` of :func:`~softcrawl.jaxsim.rig.make_action_rollout` over the actions;
        an env that diverged waits, as :meth:`step` leaves it), then each env's transitions,
        those of ``n_actions`` :meth:`step` calls with the same actions (the same
        :class:`CrawlerEnv` calls on the same per-action outputs), up to the end of its episode.

        Raises:
            ValueError: ``actions`` not ``(N, n_actions, R)`` finite numbers.
        """
        return self._finish_episodes(*self._launch_episodes(actions))

    def episodes_send(self, actions) -> None:
        """Start :meth:`run_episodes`: the whole episode's rollout is dispatched (JAX runs it
        asynchronously); :meth:`episodes_recv` waits."""
        self._pending = self._launch_episodes(actions)

    def episodes_recv(self):
        pending, self._pending = self._pending, None
        return self._finish_episodes(*pending)

    def _launch_episodes(self, actions):
        """Check ``actions``, dispatch the episodes' rollout; returns ``(actions, outputs)``."""
        actions = np.asarray(actions, dtype=np.float32)
        n_actions = {env.n_actions for env in self.envs}
        if (actions.ndim != 3 or len(n_actions) != 1 or actions.shape != (self.num_envs, *n_actions, self._n_reg)
                or not np.all(np.isfinite(actions))):
            raise ValueError(f"actions must be ({self.num_envs}, n_actions {sorted(n_actions)}, {self._n_reg}) finite "
                             f"numbers in [-1, 1], got an array of shape {actions.shape}")
        steps = np.array([env.episode_steps() if ep is not None and ep.settled is not None else [0] * env.n_actions
                          for env, ep in zip(self.envs, self._episodes)], np.int32)
        if steps.max() > self._steps_max:  # pragma: no cover - _longest_action bounds it
            raise RuntimeError(f"an action of {steps.max()} steps exceeds the compiled {self._steps_max}")
        command = action_to_kpa(np.clip(actions, -1.0, 1.0)).astype(self._dtype)
        self._state, outputs = self._episode(self._model, self._rig, self._state, command, steps)
        return actions, outputs

    def _finish_episodes(self, actions, outputs):
        """Each env's transitions once the rollout :meth:`_launch_episodes` dispatched is done."""
        diverged, point, applied, t = jax.device_get(outputs)  # (n_actions, N, ...)
        results = []
        for i, env in enumerate(self.envs):
            out = []
            for k, a in enumerate(actions[i]):
                error = None
                if env.begin_action(a) is not None:
                    self._episodes[i].update(point[k, i], applied[k, i])
                    if diverged[k, i]:
                        error = SimulationDiverged("invalid state (JAX engine: inverted elements or non-finite values)",
                                                   float(t[k, i]) + self._dt)
                out.append(env.end_action(error))
                if out[-1][2] or out[-1][3]:
                    break
            results.append(out)
        return results

    def _finish(self, steps, outputs):
        """Each env's transition once the rollout :meth:`_launch` dispatched is done."""
        if outputs is None:
            return [env.end_action() for env in self.envs]
        diverged, point, applied, t = jax.device_get(outputs)
        results = []
        for i, env in enumerate(self.envs):
            error = None
            if steps[i]:
                self._episodes[i].update(point[i], applied[i])
                if diverged[i]:
                    error = SimulationDiverged("invalid state (JAX engine: inverted elements or non-finite values)",
                                               float(t[i]) + self._dt)
            results.append(env.end_action(error))
        return results
