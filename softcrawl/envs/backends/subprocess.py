"""The subprocess backend: envs in ``multiprocessing`` workers connected by pipes.

Each worker holds a contiguous chunk of the envs (:class:`~softcrawl.envs.backends.chunked.ChunkedBackend`),
so 96 envs run on 2 cores with 2 workers; a worker steps its envs' reduced robots as one batch
(:class:`~softcrawl.envs.backends.batched.BatchedBackend`) or one env after another
(:class:`~softcrawl.envs.backends.serial.SerialBackend`), one message per action
(:meth:`~SubprocessBackend.step`) or per episode (:meth:`~SubprocessBackend.run_episodes`: the
worker runs its envs' whole episodes from the actions it is sent).

A worker imports only what stepping needs: this package imports neither stable-baselines3 nor
torch (:mod:`softcrawl.envs.vec` holds the SB3 ``VecEnv``).
"""

from __future__ import annotations

import multiprocessing as mp
import os
from collections.abc import Callable, Sequence

import cloudpickle
import gymnasium as gym
import numpy as np

from softcrawl.envs.backends.batched import BatchedBackend
from softcrawl.envs.backends.chunked import ChunkedBackend
from softcrawl.envs.backends.serial import SerialBackend
from softcrawl.parallel import default_worker_env


#: Default of :class:`SubprocessBackend`'s ``batched``: workers step their envs' reduced robots as
#: one batch (:class:`~softcrawl.envs.backends.batched.BatchedBackend`; the same transitions).
BATCHED_WORKERS = True


def _worker(remote, parent_remote, payload: bytes, batched: bool = False) -> None:
    """Worker loop: holds a chunk of envs (stepped one by one, or as one batch if ``batched``),
    answers commands from the pipe."""
    parent_remote.close()
    backend = (BatchedBackend if batched else SerialBackend)(cloudpickle.loads(payload))
    try:
        while True:
            cmd, arg = remote.recv()
            try:
                if cmd == "step":
                    out = backend.step(arg)
                elif cmd == "episodes":
                    out = backend.run_episodes(arg)
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
            (:class:`~softcrawl.envs.backends.batched.BatchedBackend`, the same transitions) instead of one
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
        default_worker_env()
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

    def _send_chunks(self, cmd: str, actions) -> None:
        """Send each worker ``(cmd, its envs' rows of actions)``, one message per worker."""
        actions = np.asarray(actions)
        for w, chunk in enumerate(self._chunks):
            self.remotes[w].send((cmd, actions[chunk]))

    def step_send(self, actions):
        self._send_chunks("step", actions)

    def step_recv(self):
        return [r for w in range(len(self._chunks)) for r in self._recv(w)]

    def run_episodes(self, actions):
        self.episodes_send(actions)
        return self.episodes_recv()

    def episodes_send(self, actions):
        """Send each worker its envs' actions of the whole episode (one message per worker)."""
        self._send_chunks("episodes", actions)

    def episodes_recv(self):
        return self.step_recv()

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
