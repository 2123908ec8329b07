"""The replay buffer of the device-resident learner (:mod:`softcrawl.codesign.episodic`): a ring
buffer of transitions in JAX arrays on the learner's device, filled once per episode round and
sampled inside the compiled update, so no batch crosses between host and device.

It holds what stable-baselines3's ``ReplayBuffer`` holds, with its names, dtypes and meaning
(``observations``, ``next_observations``, ``actions``, ``rewards``, ``dones``, ``timeouts``:
``timeouts`` set only with ``handle_timeout_termination``, a sample's terminal flag is
``dones * (1 - timeouts)``), but flat: row ``j`` is the ``j``-th transition written (mod the
capacity ``buffer_size``), not one row per vectorised step of ``n_envs`` columns, so an episode
round whose envs took different numbers of actions (an episode ended early) adds only the
transitions that happened. Sampling is uniform with replacement over the rows written, as SB3's.

A checkpoint (:mod:`softcrawl.codesign.checkpoints`) reads and writes the arrays through the
attributes of those names, numpy arrays: reading one moves the buffer to the host, and the
next :meth:`DeviceReplay.device_arrays` moves it back (one copy of the buffer at a time, on one
side), so the arrays a checkpoint writes are the buffer, and the arrays it restores are what
the next update samples. ``pos`` (the next row to write) and ``full`` are host integers.

The buffer is this module's own rather than flashbax's item buffer (which installs with this
JAX): ``benchmarks/replay_buffer.py`` measured a round of the ``paper`` preset (1,920
transitions added from the host, 96 batches of 512 drawn and gathered) at 0.021 s here and
0.024 s with flashbax (medians of 30, a shared 2-core CPU), and flashbax adds a fixed number of
items per compiled call, so leaving out the rows of envs whose episode ended early would compile
its ``add`` anew for every count.
"""

from __future__ import annotations

from functools import partial

import jax
import numpy as np

#: The arrays of a replay buffer (SB3's names), in the order :meth:`DeviceReplay.add` takes them.
FIELDS = ("observations", "next_observations", "actions", "rewards", "dones", "timeouts")


class _Array:
    """Attribute ``name`` of a :class:`DeviceReplay`: its array on the host (moving it there)."""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, replay, owner=None):
        return self if replay is None else replay.host_arrays()[self.name]


@partial(jax.jit, donate_argnums=0)
def _write(arrays: dict, rows: dict, index: jax.Array) -> dict:
    """``arrays`` with ``rows[k][j]`` written at row ``index[j]`` (an index of ``len(array)``
    or more: dropped)."""
    return {k: arrays[k].at[index].set(rows[k], mode="drop") for k in arrays}


class DeviceReplay:
    """Ring buffer of ``buffer_size`` transitions on JAX device ``jax_device`` (module doc).

    Built by SBX's SAC as its replay buffer (stable-baselines3's ``ReplayBuffer`` signature:
    the buffer's capacity, the spaces, the torch device and ``n_envs``, which are unused,
    ``optimize_memory_usage``, which must be off, ``handle_timeout_termination``) with
    ``jax_device`` added.

    Raises:
        ValueError: ``optimize_memory_usage``, a capacity below 1, non-Box spaces.
    """

    observations = _Array()
    next_observations = _Array()
    actions = _Array()
    rewards = _Array()
    dones = _Array()
    timeouts = _Array()

    def __init__(self, buffer_size: int, observation_space, action_space, device="cpu", n_envs: int = 1,
                 optimize_memory_usage: bool = False, handle_timeout_termination: bool = True,
                 jax_device: jax.Device | None = None):
        if optimize_memory_usage:
            raise ValueError("the device replay buffer has no memory-optimised layout")
        if int(buffer_size) < 1:
            raise ValueError(f"buffer_size must be >= 1, got {buffer_size}")
        self.buffer_size, self.n_envs = int(buffer_size), n_envs
        self.handle_timeout_termination = bool(handle_timeout_termination)
        self.jax_device = jax_device or jax.devices("cpu")[0]
        c, obs, act = self.buffer_size, observation_space.shape, action_space.shape
        self._host: dict | None = {
            "observations": np.zeros((c, *obs), observation_space.dtype),
            "next_observations": np.zeros((c, *obs), observation_space.dtype),
            "actions": np.zeros((c, *act), action_space.dtype),
            **{k: np.zeros(c, np.float32) for k in ("rewards", "dones", "timeouts")}}
        self._device: dict | None = None
        self.pos, self.full = 0, False

    def size(self) -> int:
        """Transitions held."""
        return self.buffer_size if self.full else self.pos

    def host_arrays(self) -> dict[str, np.ndarray]:
        """The arrays (:data:`FIELDS`) as writable numpy arrays; the buffer is on the host until
        the next :meth:`device_arrays`."""
        if self._host is None:
            self._host = {k: np.array(v) for k, v in jax.device_get(self._device).items()}
            self._device = None
        return self._host

    def device_arrays(self) -> dict[str, jax.Array]:
        """The arrays (:data:`FIELDS`) on :attr:`jax_device`; the buffer is there until the next
        :meth:`host_arrays`."""
        if self._device is None:
            self._device = jax.device_put(self._host, self.jax_device)
            self._host = None
        return self._device

    def add(self, rows: dict[str, np.ndarray], count: int) -> None:
        """Write the first ``count`` rows of ``rows`` (:data:`FIELDS` -> arrays of one length,
        the same for every call so that one compiled write serves them all; the rest is
        padding) after the rows written so far, oldest overwritten first. ``timeouts`` are
        stored only with ``handle_timeout_termination`` (else zeros, as SB3).

        Raises:
            ValueError: missing fields, or ``count`` beyond the rows given.
        """
        if set(rows) != set(FIELDS):
            raise ValueError(f"rows must have the fields {FIELDS}, got {sorted(rows)}")
        length = len(rows["rewards"])
        if not 0 <= count <= length:
            raise ValueError(f"count must be in 0..{length}, got {count}")
        if count == 0:
            return
        rows = dict(rows)
        if not self.handle_timeout_termination:
            rows["timeouts"] = np.zeros_like(rows["timeouts"])
        c = self.buffer_size
        first = max(0, count - c)  # a round larger than the buffer: only its last c rows stay
        index = np.full(length, c, np.int32)
        index[first:count] = (self.pos + np.arange(first, count)) % c
        arrays = self.device_arrays()
        dtypes = {k: arrays[k].dtype for k in FIELDS}
        rows = {k: np.asarray(rows[k], dtypes[k]) for k in FIELDS}
        self._device = _write(arrays, jax.device_put(rows, self.jax_device), jax.device_put(index, self.jax_device))
        self.full = self.full or self.pos + count >= c
        self.pos = (self.pos + count) % c


def gather(arrays: dict, index: jax.Array) -> dict:
    """The transitions at rows ``index`` ``(B,)``: ``observations``, ``actions``,
    ``next_observations``, ``rewards`` and ``dones`` (the terminal flag
    ``dones * (1 - timeouts)``, SB3's ``ReplayBuffer._get_samples``)."""
    return {"observations": arrays["observations"][index], "actions": arrays["actions"][index],
            "next_observations": arrays["next_observations"][index], "rewards": arrays["rewards"][index],
            "dones": arrays["dones"][index] * (1 - arrays["timeouts"][index])}
