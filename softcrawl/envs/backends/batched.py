"""Crawler envs whose robots are stepped together: the batched backend of a worker.

:class:`BatchedBackend` holds envs like :class:`~softcrawl.envs.backends.serial.SerialBackend`, but its
:meth:`~BatchedBackend.step` advances all of them through their actions in lockstep: every
env starts its action (:meth:`CrawlerEnv.begin_action`), then for each of the
``steps_per_action`` simulator steps every live episode steps its regulators
(:meth:`Episode.next_control`) and all robots take one
:class:`~softcrawl.reduction.batch.BatchedReducedSolver` step, and finally every env closes its
action (:meth:`CrawlerEnv.end_action`: reward, observation, info). A robot that diverges
leaves the batch for the rest of the action and is reported as :meth:`CrawlerEnv.step` would
report it. Before a reset, the robots of new designs are settled to rest together as well
(:meth:`BatchedBackend.settle_together`). Each robot's arithmetic is that of its own solver, so
the transitions equal those of :class:`SerialBackend` to the last bit (tests/test_batch_env.py).

Envs whose solver is not a :class:`~softcrawl.reduction.solver.ReducedSolver` (the full-order
model) are stepped one by one with :meth:`CrawlerEnv.step`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from softcrawl.envs.backends.base import StepResult
from softcrawl.envs.backends.serial import SerialBackend
from softcrawl.envs.crawler import CrawlerEnv
from softcrawl.fem.solver import SimulationDiverged
from softcrawl.reduction.batch import BatchedReducedSolver, run_in_lockstep
from softcrawl.reduction.solver import ReducedSolver
from softcrawl.robot.episode import SettledState, settle


def batchable(env) -> bool:
    """Whether ``env``'s current episode can be stepped in a batch (a :class:`CrawlerEnv` with a
    reduced solver)."""
    return (isinstance(env, CrawlerEnv) and env.episode is not None
            and isinstance(env.episode.solver, ReducedSolver))


class BatchedBackend(SerialBackend):
    """All envs in this process, their reduced robots stepped as one batch (module doc).

    Args:
        env_fns: one zero-argument constructor per env.

    The batch solver is rebuilt only when the set of stepped episodes changes (resets,
    divergences): its cost (stacking the legs' static data) is paid once per episode round.
    """

    def __init__(self, env_fns):
        super().__init__(env_fns)
        self._batch: BatchedReducedSolver | None = None
        self._members: tuple[int, ...] = ()

    def _batch_of(self, solvers: Sequence[ReducedSolver]) -> BatchedReducedSolver:
        key = tuple(id(s) for s in solvers)
        if self._batch is None or key != self._members:
            self._batch, self._members = BatchedReducedSolver(solvers), key
        return self._batch

    def reset(self, indices, designs, seeds):
        """Reset envs ``indices`` with the given designs (None: the env chooses) and seeds; the
        robots of given designs that no env has settled yet are settled first, all together
        (:meth:`settle_together`)."""
        self.settle_together([self.envs[i] for i in indices], designs)
        return super().reset(indices, designs, seeds)

    @staticmethod
    def settle_together(envs: Sequence, designs: Sequence) -> None:
        """Settle to rest the reduced robots of ``designs[i]`` in ``envs[i]`` whose settled state
        is not cached yet, in lockstep (:func:`~softcrawl.reduction.batch.run_in_lockstep` of
        :func:`~softcrawl.robot.episode.settle`: each result is the one :meth:`CrawlerEnv.reset`
        would compute), once per design and rule, and cache the results in the envs
        (:meth:`CrawlerEnv.store_settled`). A settling that diverges is left to the env's reset,
        which reports it."""
        todo: dict = {}  # (design, rule, factory) -> (robot, [(env, design)])
        for env, design in zip(envs, designs):
            if design is None or not isinstance(env, CrawlerEnv):
                continue
            design = env.space.validate_design(design)
            robot, settled = env.cached_robot(design)
            if settled is not None or not robot.reduced:
                continue
            try:
                key = (design, env.settling, env.robot_factory)
                hash(key)
            except TypeError:  # an unhashable factory: no sharing between envs
                key = (design, env.settling, id(env))
            todo.setdefault(key, (robot, []))[1].append((env, design))
        if not todo:
            return
        jobs = list(todo.items())
        loops = [lambda s, robot=robot, rule=key[1]: settle(robot, rule, solver=s) for key, (robot, _) in jobs]
        outcomes = run_in_lockstep([robot.make_solver() for _, (robot, _) in jobs], loops)
        for (_, (_, users)), out in zip(jobs, outcomes):
            if isinstance(out, SettledState):
                # own arrays (the batch's states are views of arrays of all robots); no modal
                # velocities: an episode starts from the positions and velocities (Episode.reset)
                out = dataclasses.replace(out, state=dataclasses.replace(out.state, x=out.state.x.copy(),
                                                                         v=out.state.v.copy(), modal_velocities=None))
                for env, design in users:
                    env.store_settled(design, out)

    def step(self, actions) -> list[StepResult]:
        """Step every env with its action ``actions[i]`` ``(R,)``, one per regulator of its
        space (no auto-reset)."""
        return self.step_envs(range(len(self.envs)), actions)

    def step_envs(self, indices, actions) -> list[StepResult]:
        """Step envs ``indices`` only (env ``indices[j]`` with ``actions[j]``), their robots in
        one batch; the others wait (:meth:`~softcrawl.envs.backends.base.EnvBackend.run_episodes`)."""
        envs = self.envs
        action = dict(zip(indices, actions))
        results: dict[int, StepResult] = {}
        batched = [i for i in action if batchable(envs[i])]
        for i in sorted(set(action) - set(batched)):
            results[i] = envs[i].step(action[i])
        kpa = {i: envs[i].begin_action(action[i]) for i in batched}
        errors: dict[int, SimulationDiverged] = {}
        live = [i for i in batched if kpa[i] is not None]
        k = 0
        while True:
            live = [i for i in live if k < envs[i].steps_per_action]
            if not live:
                break
            episodes = [envs[i].episode for i in live]
            controls = [ep.next_control(kpa[i]) for i, ep in zip(live, episodes)]
            out = self._batch_of([ep.solver for ep in episodes]).step([ep.state for ep in episodes], controls)
            for i, ep, new in zip(live, episodes, out):
                if isinstance(new, SimulationDiverged):
                    errors[i] = new
                else:
                    ep.state = new
            live = [i for i in live if i not in errors]
            k += 1
        for i in batched:
            results[i] = envs[i].end_action(errors.get(i))
        return [results[i] for i in action]

