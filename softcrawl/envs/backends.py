"""Where a vector env's crawlers run: the *backend* interface (:class:`EnvBackend`): ``reset``
given env indices, designs and seeds, ``step`` of all envs, ``get_attr``/``set_attr``/``call``
and ``close``. Backends: :class:`SerialBackend` (in-process, tests), :class:`SubprocessBackend`
(``multiprocessing`` workers connected by pipes, each worker holding a contiguous chunk of the
envs, so 96 envs run on 2 cores with 2 workers; a worker steps its envs' reduced robots as one
batch, :class:`softcrawl.envs.batch.BatchedBackend`) and
:class:`softcrawl.envs.ray_backend.RayBackend` (Ray actors, optional extra ``softcrawl[ray]``);
:func:`make_backend` picks one by name.

This module does not import stable-baselines3 or torch (:mod:`softcrawl.envs.vec` holds the SB3
``VecEnv``): a subprocess worker imports only what stepping needs, ~185 MB less per worker.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable, Sequence

import cloudpickle
import gymnasium as gym
import numpy as np

from softcrawl.design.space import Design

StepResult = tuple[np.ndarray, float, bool, bool, dict]


class EnvBackend:
    """Where the N environments live. Subclasses implement the methods below."""

    num_envs: int
    observation_space: gym.Space
    action_space: gym.Space

    def reset(self, indices: Sequence[int], designs: Sequence[Design | None],
              seeds: Sequence[int | None]) -> list[tuple[np.ndarray, dict]]:  # pragma: no cover
        """Reset envs ``indices`` with the given designs (None: the env chooses) and seeds."""
        raise NotImplementedError

    def step(self, actions: np.ndarray) -> list[StepResult]:  # pragma: no cover
        """Step all envs with ``actions`` ``(N, 3)``; no auto-reset."""
        raise NotImplementedError

    def step_send(self, actions: np.ndarray) -> None:
        """Start :meth:`step` (backends whose envs run elsewhere start them now and return);
        finish with :meth:`step_recv`."""
        self._sent = actions

    def step_recv(self) -> list[StepResult]:
        """The results of the step started by :meth:`step_send`."""
        actions, self._sent = self._sent, None
        return self.step(actions)

    def get_attr(self, name: str, indices: Sequence[int]) -> list:  # pragma: no cover
        raise NotImplementedError

    def set_attr(self, name: str, value, indices: Sequence[int]) -> None:  # pragma: no cover
        raise NotImplementedError

    def call(self, method: str, args: tuple, kwargs: dict, indices: Sequence[int]) -> list:  # pragma: no cover
        raise NotImplementedError

    def close(self) -> None:  # pragma: no cover
        pass


class SerialBackend(EnvBackend):
    """All envs in this process, stepped one after another.

    Args:
        env_fns: one zero-argument constructor per env.
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]]):
        if len(env_fns) < 1:
            raise ValueError("need at least one env")
        self.envs = [fn() for fn in env_fns]
        self.num_envs = len(self.envs)
        self.observation_space, self.action_space = self.envs[0].observation_space, self.envs[0].action_space

    def reset(self, indices, designs, seeds):
        return [self.envs[i].reset(seed=s, options={"design": d}) for i, d, s in zip(indices, designs, seeds)]

    def step(self, actions):
        return [env.step(a) for env, a in zip(self.envs, actions)]

    def get_attr(self, name, indices):
        return [getattr(self.envs[i], name) for i in indices]

    def set_attr(self, name, value, indices):
        for i in indices:
            setattr(self.envs[i], name, value)

    def call(self, method, args, kwargs, indices):
        return [getattr(self.envs[i], method)(*args, **kwargs) for i in indices]

    def close(self):
        for env in self.envs:
            env.close()


def env_chunks(n: int, n_workers: int) -> list[list[int]]:
    """The env indices of each of ``n_workers`` workers for ``n`` envs: contiguous chunks of
    sizes differing by at most one (what :class:`ChunkedBackend` gives each worker)."""
    bounds = np.linspace(0, n, n_workers + 1).round().astype(int)
    return [list(range(bounds[w], bounds[w + 1])) for w in range(n_workers)]


class ChunkedBackend(EnvBackend):
    """Envs in contiguous chunks, one chunk per worker (a process or a Ray actor): the chunking,
    and ``reset`` / ``get_attr`` / ``set_attr`` / ``call`` sent to the workers that own the
    given envs. Subclasses implement :meth:`_call` (and ``step``, ``close``)."""

    def _set_chunks(self, n: int, n_workers: int) -> None:
        self.num_envs = n
        self._chunks = env_chunks(n, n_workers)
        self._owner = {i: (w, j) for w, chunk in enumerate(self._chunks) for j, i in enumerate(chunk)}

    def _call(self, workers: Sequence[int], method: str, args_of: Callable[[int], tuple]) -> list:
        """``method(*args_of(w))`` on each worker ``w`` of ``workers``; their results in order."""
        raise NotImplementedError  # pragma: no cover

    def _by_worker(self, indices: Sequence[int]) -> dict[int, list[tuple[int, int]]]:
        """``worker -> [(position in indices, local index)]``."""
        groups: dict[int, list[tuple[int, int]]] = {}
        for pos, i in enumerate(indices):
            w, j = self._owner[int(i)]
            groups.setdefault(w, []).append((pos, j))
        return groups

    def _scatter(self, indices, method: str, make_args: Callable[[list[tuple[int, int]]], tuple]) -> list:
        groups = self._by_worker(indices)
        workers = list(groups)
        outs = self._call(workers, method, lambda w: make_args(groups[w]))
        result: list = [None] * len(indices)
        for w, out in zip(workers, outs):
            for (pos, _), o in zip(groups[w], out if out is not None else [None] * len(groups[w])):
                result[pos] = o
        return result

    def reset(self, indices, designs, seeds):
        return self._scatter(indices, "reset", lambda g: ([j for _, j in g], [designs[p] for p, _ in g],
                                                          [seeds[p] for p, _ in g]))

    def get_attr(self, name, indices):
        return self._scatter(indices, "get_attr", lambda g: (name, [j for _, j in g]))

    def set_attr(self, name, value, indices):
        self._scatter(indices, "set_attr", lambda g: (name, value, [j for _, j in g]))

    def call(self, method, args, kwargs, indices):
        return self._scatter(indices, "call", lambda g: (method, args, kwargs, [j for _, j in g]))


#: Default of :class:`SubprocessBackend`'s ``batched``: workers step their envs' reduced robots as
#: one batch (:class:`softcrawl.envs.batch.BatchedBackend`; same transitions, issue 18).
BATCHED_WORKERS = True


def _worker(remote, parent_remote, payload: bytes, batched: bool = False) -> None:
    """Worker loop: holds a chunk of envs (stepped one by one, or as one batch if ``batched``),
    answers commands from the pipe."""
    parent_remote.close()
    if batched:
        from softcrawl.envs.batch import BatchedBackend  # imports this module

        backend = BatchedBackend(cloudpickle.loads(payload))
    else:
        backend = SerialBackend(cloudpickle.loads(payload))
    try:
        while True:
            cmd, arg = remote.recv()
            try:
                if cmd == "step":
                    out = backend.step(arg)
                elif cmd == "reset":
                    out = backend.reset(*arg)
                elif cmd == "spaces":
                    out = (backend.observation_space, backend.action_space)
                elif cmd == "get_attr":
                    out = backend.get_attr(*arg)
                elif cmd == "set_attr":
                    out = backend.set_attr(*arg)
                elif cmd == "call":
                    out = backend.call(*arg)
                elif cmd == "close":
                    backend.close()
                    remote.send(("ok", None))
                    break
                else:
                    raise ValueError(f"unknown command {cmd!r}")
                remote.send(("ok", out))
            except Exception as exc:  # noqa: BLE001 - forwarded to the parent
                remote.send(("error", exc))
    except (EOFError, KeyboardInterrupt):
        pass
    finally:
        remote.close()


class SubprocessBackend(ChunkedBackend):
    """Envs spread over ``n_workers`` processes (contiguous chunks), talked to through pipes.

    Args:
        env_fns: one zero-argument constructor per env (pickled with cloudpickle, so lambdas work).
        n_workers: worker processes (default: ``min(len(env_fns), os.cpu_count())``).
        start_method: ``multiprocessing`` start method (default ``"forkserver"`` where available,
            else ``"spawn"``; ``fork`` is unsafe once torch has started threads).
        batched: each worker steps its envs' reduced robots as one batch
            (:class:`softcrawl.envs.batch.BatchedBackend`, the same transitions) instead of one
            env after another (default :data:`BATCHED_WORKERS`).

    Worker processes inherit ``OMP_NUM_THREADS`` etc. (set to 1 here if unset). An exception
    in a worker is re-raised in the parent.
    """

    def __init__(self, env_fns: Sequence[Callable[[], gym.Env]], n_workers: int | None = None,
                 start_method: str | None = None, batched: bool | None = None):
        n = len(env_fns)
        if n < 1:
            raise ValueError("need at least one env")
        n_workers = min(n, n_workers or os.cpu_count() or 1)
        if n_workers < 1:
            raise ValueError(f"n_workers must be >= 1, got {n_workers}")
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            os.environ.setdefault(var, "1")
        if start_method is None:
            start_method = "forkserver" if "forkserver" in mp.get_all_start_methods() else "spawn"
        ctx = mp.get_context(start_method)
        self._set_chunks(n, n_workers)
        self.remotes, self.processes = [], []
        for chunk in self._chunks:
            remote, work_remote = ctx.Pipe()
            payload = cloudpickle.dumps([env_fns[i] for i in chunk])
            proc = ctx.Process(target=_worker, args=(work_remote, remote, payload,
                                                     BATCHED_WORKERS if batched is None else bool(batched)),
                               daemon=True)
            proc.start()
            work_remote.close()
            self.remotes.append(remote)
            self.processes.append(proc)
        self._closed = False
        self.observation_space, self.action_space = self._call([0], "spaces", lambda j: None)[0]

    def _recv(self, w: int):
        status, out = self.remotes[w].recv()
        if status == "error":
            raise out
        return out

    def _call(self, workers: Sequence[int], cmd: str, arg_of: Callable[[int], object]) -> list:
        for w in workers:
            self.remotes[w].send((cmd, arg_of(w)))
        return [self._recv(w) for w in workers]

    def step(self, actions):
        self.step_send(actions)
        return self.step_recv()

    def step_send(self, actions):
        actions = np.asarray(actions)
        for w, chunk in enumerate(self._chunks):
            self.remotes[w].send(("step", actions[chunk]))

    def step_recv(self):
        return [r for w in range(len(self._chunks)) for r in self._recv(w)]

    def close(self):
        if self._closed:
            return
        self._closed = True
        for remote in self.remotes:
            try:
                remote.send(("close", None))
                remote.recv()
            except (BrokenPipeError, EOFError, OSError):
                pass
        for proc in self.processes:
            proc.join(timeout=10)
            if proc.is_alive():
                proc.terminate()


def make_backend(kind: str, env_fns: Sequence[Callable[[], gym.Env]], n_workers: int | None = None,
                 ray_address: str | None = None) -> EnvBackend:
    """The backend named ``kind``: ``"serial"``, ``"subprocess"`` (``n_workers`` processes) or
    ``"ray"`` (``n_workers`` actors on a local Ray, or the cluster at ``ray_address``).

    Raises:
        ValueError: unknown kind. ImportError: ``"ray"`` without Ray installed.
    """
    if kind == "serial":
        return SerialBackend(env_fns)
    if kind == "subprocess":
        return SubprocessBackend(env_fns, n_workers=n_workers)
    if kind == "ray":
        from softcrawl.envs.ray_backend import RayBackend

        return RayBackend(env_fns, n_actors=n_workers, address=ray_address)
    raise ValueError(f"unknown env backend {kind!r} (serial, subprocess, ray)")
