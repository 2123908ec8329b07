"""Backends whose envs are held in contiguous chunks by workers (processes or Ray actors)."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from softcrawl.envs.backends.base import EnvBackend


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
