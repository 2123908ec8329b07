"""The Ray backend: envs held by Ray actors (optional extra ``softcrawl[ray]``, ``ray>=2``).

Runs on a local Ray started here (:func:`softcrawl.parallel.ensure_ray`) unless an address of an
existing cluster is given (``"auto"`` or ``"ray://host:10001"``).

:class:`RayBackend` implements :class:`~softcrawl.envs.backends.base.EnvBackend` (``reset``,
``step``, ``get_attr``, ``set_attr``, ``call``, ``close``) with Ray actors each holding a
contiguous chunk of the envs (like the subprocess backend's workers). **Fault tolerance**:
actors are created with ``max_restarts``; the driver keeps, per env, the design and actions of
its current episode and its RNG state after the reset (a whole episode's actions, with
:meth:`RayBackend.run_episodes`). When an actor dies (``RayActorError``,
or ``ActorUnavailableError`` mid-call), Ray restarts it (fresh envs); the backend then resets
its envs with the same designs, restores their RNG states, replays the actions of the current
episodes, and re-issues the failed call. Simulation is deterministic, so the run goes on with
the same results as if nothing had happened; only that actor's episodes are re-simulated.
State changed through ``set_attr``/``call`` on a dead actor's envs is not replayed.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence

import cloudpickle
import numpy as np

from softcrawl.envs.backends.chunked import ChunkedBackend
from softcrawl.envs.backends.serial import SerialBackend
from softcrawl.parallel import default_worker_env, ensure_ray


class _EnvChunk:
    """Actor body: a :class:`SerialBackend` of some envs (constructors pickled with cloudpickle)."""

    def __init__(self, payload: bytes):
        default_worker_env()
        self.backend = SerialBackend(cloudpickle.loads(payload))

    def spaces(self):
        return self.backend.observation_space, self.backend.action_space

    def pid(self) -> int:
        return os.getpid()

    def reset(self, indices, designs, seeds):
        """The envs' reset results and their RNG states after the reset (for a replay)."""
        out = self.backend.reset(indices, designs, seeds)
        return [(o, self._rng_state(j)) for o, j in zip(out, indices)]

    def _rng_state(self, j: int):
        rng = getattr(self.backend.envs[j], "np_random", None)
        return rng.bit_generator.state if rng is not None else None

    def step(self, actions):
        return self.backend.step(actions)

    def run_episodes(self, actions):
        return self.backend.run_episodes(actions)

    def replay(self, designs, rng_states, actions):
        """Reset every env of the chunk with its design, restore its RNG state after that reset
        and re-run its episode's actions (lists of ``(3,)`` arrays); returns nothing."""
        idx = list(range(len(designs)))
        self.backend.reset(idx, designs, [None] * len(idx))
        for j, st in enumerate(rng_states):
            if st is not None:
                self.backend.envs[j].np_random.bit_generator.state = st
        for j, acts in enumerate(actions):
            for a in acts:
                self.backend.envs[j].step(a)

    def get_attr(self, name, indices):
        return self.backend.get_attr(name, indices)

    def set_attr(self, name, value, indices):
        return self.backend.set_attr(name, value, indices)

    def call(self, method, args, kwargs, indices):
        return self.backend.call(method, args, kwargs, indices)

    def close(self):
        self.backend.close()


class RayBackend(ChunkedBackend):
    """Envs spread over ``n_actors`` Ray actors (contiguous chunks).

    Args:
        env_fns: one zero-argument env constructor per env (cloudpickled).
        n_actors: actors (default: ``min(len(env_fns), Ray's CPUs)``).
        address: Ray cluster address (None: local Ray, :func:`softcrawl.parallel.ensure_ray`).
        num_cpus: CPUs of a local Ray started here (None: all).
        max_restarts: restarts per actor before a death is raised (:class:`ray.exceptions.RayActorError`).

    Raises:
        ValueError: no envs. ImportError: Ray missing.
    """

    def __init__(self, env_fns: Sequence[Callable], n_actors: int | None = None, address: str | None = None,
                 num_cpus: int | None = None, max_restarts: int = 3):
        n = len(env_fns)
        if n < 1:
            raise ValueError("need at least one env")
        ray = ensure_ray(address, num_cpus)
        self._ray = ray
        cpus = int(ray.cluster_resources().get("CPU", 1))
        n_actors = max(1, min(n, n_actors or cpus))
        self._set_chunks(n, n_actors)
        cls = ray.remote(num_cpus=1, max_restarts=max_restarts, max_task_retries=0)(_EnvChunk)
        self.actors = [cls.remote(cloudpickle.dumps([env_fns[i] for i in chunk])) for chunk in self._chunks]
        self.restarts, self.max_restarts = 0, max_restarts
        self._design: list = [None] * n
        self._rng: list = [None] * n  # env RNG states after their last reset
        self._actions: list[list[np.ndarray]] = [[] for _ in range(n)]
        self._closed = False
        self.observation_space, self.action_space = ray.get(self.actors[0].spaces.remote())

    # fault handling ---------------------------------------------------------------------------
    def _recover(self, w: int) -> None:
        """Actor ``w`` died (or was unavailable mid-call) and Ray restarts it: rebuild its
        episodes by resetting its envs and replaying their actions (whatever state it was in)."""
        from ray.exceptions import ActorUnavailableError, RayActorError

        self.restarts += 1
        chunk = self._chunks[w]
        designs = [self._design[i] for i in chunk]
        if any(d is None for d in designs):  # never reset yet: nothing to replay
            return
        for _attempt in range(60):
            try:
                self._ray.get(self.actors[w].replay.remote(designs, [self._rng[i] for i in chunk],
                                                           [list(self._actions[i]) for i in chunk]))
                return
            except ActorUnavailableError:  # still restarting
                time.sleep(0.5)
            except RayActorError:
                pass
        raise RuntimeError(f"actor {w} could not be restarted")  # pragma: no cover

    def _gather(self, workers: Sequence[int], submit: Callable[[int], object]) -> list:
        """``submit(w)`` on each actor, results in order; a dead or unavailable actor is
        recovered (:meth:`_recover`) and its call re-issued. A call that fails this way may or may
        not have run on the old actor; the replay resets that state either way."""
        from ray.exceptions import ActorUnavailableError, RayActorError

        refs = {w: submit(w) for w in workers}
        out = {}
        for w in workers:
            for _attempt in range(max(2, self.max_restarts + 2)):
                try:
                    out[w] = self._ray.get(refs[w])
                    break
                except (RayActorError, ActorUnavailableError):
                    self._recover(w)
                    refs[w] = submit(w)
            else:
                raise RuntimeError(f"actor {w} kept dying")
        return [out[w] for w in workers]

    def _call(self, workers, method, args_of):
        return self._gather(workers, lambda w: getattr(self.actors[w], method).remote(*args_of(w)))

    # EnvBackend -------------------------------------------------------------------------------
    def reset(self, indices, designs, seeds):
        both = super().reset(indices, designs, seeds)
        for i, ((_, info), rng) in zip(indices, both):
            self._design[int(i)] = info.get("design")
            self._rng[int(i)] = rng
            self._actions[int(i)] = []
        return [o for o, _ in both]

    def step(self, actions):
        actions = np.asarray(actions)
        outs = self._gather(range(len(self._chunks)), lambda w: self.actors[w].step.remote(actions[self._chunks[w]]))
        for i, a in enumerate(actions):
            self._actions[i].append(a.copy())
        return [r for out in outs for r in out]

    def run_episodes(self, actions):
        """Each actor runs its envs' whole episodes from their actions (one call per actor and
        episode); a dead actor's envs are reset and the call re-issued (:meth:`_gather`), and
        each env's actions taken are kept for a later replay."""
        actions = np.asarray(actions)
        outs = self._gather(range(len(self._chunks)),
                            lambda w: self.actors[w].run_episodes.remote(actions[self._chunks[w]]))
        results = [r for out in outs for r in out]
        for i, r in enumerate(results):
            self._actions[i].extend(a.copy() for a in actions[i, :len(r)])
        return results

    def actor_pids(self) -> list[int]:
        """Process ids of the actors (tests kill one)."""
        return self._ray.get([a.pid.remote() for a in self.actors])

    def close(self):
        if self._closed:
            return
        self._closed = True
        try:
            self._ray.get([a.close.remote() for a in self.actors], timeout=30)
        except Exception:  # noqa: BLE001 - closing anyway
            pass
        for a in self.actors:
            self._ray.kill(a, no_restart=True)
