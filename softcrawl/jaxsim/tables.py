"""Design tables of the JAX engine: any design's model rows as a gather from per-slot tables, and
rested states cached on disk.

A leg's placement in a slot, the disk side of its attachment points and the disk's share of
their Delassus blocks do not depend on the other slots (:func:`softcrawl.robot.build_robot`:
every leg has the same lowest point, so the floor shift is the same for any set of legs). A
:class:`DesignTable` holds them once per design space and robot config, per slot, taken from a
few built robots whose legs cover every slot (:func:`covering_designs`); :meth:`DesignTable.rows`
then gives the :class:`~softcrawl.jaxsim.model.RobotData` of many designs at once by indexing,
without building a robot (1,024 designs of the paper's space: about 20 ms on one CPU core,
against 40 to 70 ms per design through ``build_robot`` and the robot's rows;
``benchmarks/design_tables.py``).

:class:`SettledStates` caches each design's rested :class:`~softcrawl.jaxsim.engine.State`
(the engine's settle, :func:`~softcrawl.jaxsim.engine.make_settle`) on disk, one ``.npz`` file
per design under :func:`settled_cache_dir`, so that a machine settles a design once for a given
model, rule and engine: the folder's name is a SHA-256 of everything the result depends on
(:meth:`SettledStates.key`), and each file records that key, its design and a SHA-256 of its
arrays, checked on loading; a file that fails any check is settled again (one warning line),
never trusted.
"""

from __future__ import annotations

import dataclasses
import hashlib
import io
import os
import tempfile
import warnings
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import cache, cached_property
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from softcrawl.design.spacefile import DesignSpace
from softcrawl.jaxsim import engine
from softcrawl.jaxsim.batch import in_batches, make_batch_settle, padded_size
from softcrawl.jaxsim.model import (DISK_POINT_NODES, Model, RobotData, attachment_gram, build_model, disk_inverse,
                                   leg_rows)
from softcrawl.robot.assembly import RobotConfig, build_robot
from softcrawl.robot.episode import Settling
from softcrawl.safeio import read_bytes

#: Largest settled-state file read back, bytes (a paper-space float64 state is about 25 KB).
MAX_STATE_BYTES = 64 * 1024 * 1024


def covering_designs(space: DesignSpace) -> list[tuple[int, ...]]:
    """Valid designs of ``space`` whose legs together fill every slot, all on regulator 1: the
    slots in runs of ``max_legs``, a last run shorter than ``min_legs`` topped up with the first
    slots (the paper's space: slots 0-5, then 6, 7 and 0)."""
    S, lo, hi = space.n_slots, space.min_legs, space.max_legs
    out = []
    for start in range(0, S, hi):
        slots = list(range(start, min(start + hi, S)))
        slots += [s for s in range(S) if s not in slots][:max(0, lo - len(slots))]
        out.append(tuple(int(s in slots) for s in range(S)))
    return out


@dataclass(frozen=True, eq=False)
class DesignTable:
    """Per-slot model data of a design space's robots: what :class:`RobotData` gathers from.

    Attributes:
        space: the design space (``S`` slots, ``R`` regulators).
        parts: the shared leg and disk parts and the settings of the robots' model (a
            :class:`~softcrawl.jaxsim.model.Model` whose ``robot`` is None), in the engine's dtype.
        n_slots: ``L``, the default leg slots of :meth:`rows`.
        rotation: ``(S, 3, 3)`` part -> world of a leg in each slot; translation: ``(S, 3)`` mm.
        disk_nodes, disk_weights: ``(S, F, 4)`` the disk side of each slot's ``F`` attachment points.
        att_gram: ``(S F, S F, 3, 3)`` float64, 1/kg: ``E_p^T A_0^-1 E_q`` of every pair of the
            space's attachment points (point ``s F + a``: slot ``s``, point ``a``), from the
            disk's float64 ``A_0^-1`` (:func:`~softcrawl.jaxsim.model.attachment_gram`).
    """

    space: DesignSpace
    parts: Model
    n_slots: int
    rotation: np.ndarray
    translation: np.ndarray
    disk_nodes: np.ndarray
    disk_weights: np.ndarray
    att_gram: np.ndarray

    @property
    def dtype(self) -> np.dtype:
        """The float dtype of the rows and of :attr:`parts`."""
        return np.dtype(self.parts.disk.rest.dtype)

    @cached_property
    def _cast(self) -> tuple[np.ndarray, ...]:
        """The float tables in :attr:`dtype` (rotation, translation, weights, Gram blocks)."""
        return tuple(a.astype(self.dtype) for a in (self.rotation, self.translation, self.disk_weights, self.att_gram))

    def designs_array(self, designs) -> np.ndarray:
        """``designs`` (a ``(B, S)`` integer array, or a sequence of designs: tuples or strings)
        as a validated ``(B, S)`` int64 array (not canonicalised).

        Raises:
            InvalidDesignError: an invalid design (the first, as :meth:`DesignSpace.validate_design` names it).
        """
        space = self.space
        S = space.n_slots
        try:
            a = np.asarray(designs)
        except ValueError:  # ragged
            a = None
        if a is None or a.ndim != 2 or a.shape[1] != S or a.dtype.kind not in "iu":
            return np.array([space.validate_design(d) for d in designs], np.int64).reshape(-1, S)
        a = a.astype(np.int64)
        legs = (a > 0).sum(axis=1)
        bad = np.flatnonzero(((a < 0) | (a > space.n_regulators)).any(axis=1) | (legs < space.min_legs)
                             | (legs > space.max_legs))
        if bad.size:
            space.validate_design(a[bad[0]].tolist())  # raises, naming the fault
        return a

    def rows(self, designs, n_slots: int | None = None) -> RobotData:
        """The stacked :class:`RobotData` of ``designs`` (numpy, leading axis ``B``, floats in
        :attr:`dtype`): leg ``j`` of a design is its ``j``-th occupied slot in slot order (as
        :func:`~softcrawl.robot.build_robot` orders legs), on channel ``value - 1``; slots past
        its legs are masked as :func:`~softcrawl.jaxsim.model.build_model` pads them (identity
        rotation, zero translation, channel, nodes, weights and Gram blocks).

        Args:
            designs: ``B`` designs of the space (:meth:`designs_array`).
            n_slots: ``L`` leg slots (default :attr:`n_slots`).

        Raises:
            InvalidDesignError: an invalid design. ValueError: a design with more legs than ``L``.
        """
        d = self.designs_array(designs)
        L = self.n_slots if n_slots is None else int(n_slots)
        B, S = d.shape
        F = self.disk_nodes.shape[1]
        occupied = d > 0
        legs = occupied.sum(axis=1)
        if B and legs.max() > L:
            raise ValueError(f"a design with {legs.max()} legs does not fit the JAX batch's {L} leg slots")
        k = min(L, S)
        slot = np.zeros((B, L), np.int64)
        slot[:, :k] = np.argsort(~occupied, axis=1, kind="stable")[:, :k]  # occupied slots first, in order
        mask = np.arange(L) < legs[:, None]
        slot *= mask
        rot, trans, weights, gram = self._cast
        m3 = mask[:, :, None, None]
        rotation = np.where(m3, rot[slot], np.eye(3, dtype=self.dtype))
        translation = trans[slot] * mask[:, :, None]
        channel = (np.take_along_axis(d, slot, axis=1) - 1) * mask
        disk_nodes = self.disk_nodes[slot] * m3
        disk_weights = weights[slot] * m3
        points = (slot[:, :, None] * F + np.arange(F)).reshape(B, L * F)
        used = np.repeat(mask, F, axis=1)
        att = gram[points[:, :, None], points[:, None, :]]
        att *= (used[:, :, None] & used[:, None, :])[..., None, None]
        return RobotData(mask, rotation, translation, channel, disk_nodes, disk_weights, att)

    def model(self, designs, n_slots: int | None = None) -> Model:
        """The :class:`~softcrawl.jaxsim.model.Model` of a batch of ``designs``: :attr:`parts`
        with :meth:`rows` (JAX arrays) as its per-robot data.

        Raises:
            as :meth:`rows`.
        """
        return dataclasses.replace(self.parts, robot=jax.tree_util.tree_map(jnp.asarray, self.rows(designs, n_slots)))


def build_table(space: DesignSpace, config: RobotConfig | None = None,
                factory: Callable[[tuple], object] | None = None, n_slots: int | None = None, dtype=None,
                **model_kw) -> DesignTable:
    """The :class:`DesignTable` of ``space``'s robots, from the robots of
    :func:`covering_designs` (two for the paper's space).

    Args:
        space: the design space.
        config: the robots' :class:`~softcrawl.robot.RobotConfig` (default the space's,
            :meth:`RobotConfig.for_space`), built by ``build_robot(design, config, space=space)``;
            or
        factory: ``design -> Robot`` instead (e.g. a :class:`~softcrawl.envs.CrawlerEnv`'s
            ``robot_factory``: a task's floor); it must place a slot's leg the same way
            whatever the other slots hold, as ``build_robot`` does (checked on a slot two
            covering designs share).
        n_slots: default leg slots of the rows (default the space's ``max_legs``).
        dtype: array precision (default float64 if ``jax_enable_x64`` is on, else float32).
        model_kw: :func:`~softcrawl.jaxsim.model.build_model`'s contact, calibration, rate, Delassus, Cholesky and
            floor settings.

    Raises:
        ValueError: both ``config`` and ``factory`` given; robots the JAX engine cannot step
            (not reduced, no floating-frame disk, an attachment that does not tie a leg to the
            disk: :func:`~softcrawl.jaxsim.model.build_model`'s errors); a factory that places
            a slot's leg differently in two designs.
    """
    if config is not None and factory is not None:
        raise ValueError("build_table takes a robot config or a robot factory, not both")
    if factory is None:
        config = config if config is not None else RobotConfig.for_space(space)

        def factory(design):
            return build_robot(design, config, space=space)

    robots = [factory(d) for d in covering_designs(space)]
    parts = build_model(robots, dtype=dtype, **model_kw)
    S = space.n_slots
    per_slot: dict[int, tuple] = {}
    for robot in robots:
        rows = leg_rows(robot)
        for j, leg in enumerate(robot.legs):
            new = tuple(a[j] for a in (rows[0], rows[1], rows[3], rows[4]))
            old = per_slot.setdefault(leg.slot, new)
            if not all(np.allclose(a, b, rtol=0, atol=1e-9) for a, b in zip(old, new)):
                raise ValueError(f"the robot factory places slot {leg.slot}'s leg differently in two designs: "
                                 "the JAX design table needs a leg's placement independent of the other slots")
    rotation, translation, disk_nodes, disk_weights = (np.stack([per_slot[s][i] for s in range(S)]) for i in range(4))
    F = disk_nodes.shape[1]
    nodes, weights = disk_nodes.reshape(-1, DISK_POINT_NODES), disk_weights.reshape(-1, DISK_POINT_NODES)
    inverse = np.asarray(parts.disk.inverse)
    if inverse.dtype != np.float64:  # the model's is rounded: the Gram blocks come from the float64 one
        inverse = disk_inverse(robots[0])
    gram = np.concatenate([attachment_gram(nodes[s * F:(s + 1) * F], weights[s * F:(s + 1) * F], inverse,
                                           cols=(nodes, weights)) for s in range(S)])
    return DesignTable(space, dataclasses.replace(parts, robot=None),
                       int(n_slots if n_slots is not None else space.max_legs), rotation, translation,
                       disk_nodes, disk_weights, gram)


# -- settled states ---------------------------------------------------------------------------
def settled_cache_dir() -> Path:
    """The folder of settled-state caches: ``$SOFTCRAWL_CACHE_DIR/jax_settled``, else
    ``~/.cache/softcrawl/jax_settled``."""
    return Path(os.environ.get("SOFTCRAWL_CACHE_DIR") or Path.home() / ".cache" / "softcrawl") / "jax_settled"


@dataclass(frozen=True, eq=False)
class Rested:
    """A design's rested state (numpy on the host, no batch axis).

    Attributes:
        state: the :class:`~softcrawl.jaxsim.engine.State` after settling (``t = 0``).
        steps: settling steps taken; speed: the last :func:`~softcrawl.jaxsim.engine.max_speed`, mm/s;
        ok: whether the state is valid (:func:`~softcrawl.jaxsim.rig.healthy`).
    """

    state: object
    steps: int
    speed: float
    ok: bool


@cache
def _settler(rest_speed: float, hold: int, cap: int):
    """The jitted batch settle of a rest rule (:func:`~softcrawl.jaxsim.batch.make_batch_settle`),
    one per rule in a process: its compiled programs are shared."""
    return make_batch_settle(engine.make_settle(rest_speed, hold, cap))


def _digest(arrays: dict) -> str:
    """SHA-256 of named arrays (names, dtypes, shapes and bytes, in name order)."""
    h = hashlib.sha256()
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}|{a.dtype.str}|{a.shape}|".encode())
        h.update(a.tobytes())
    return h.hexdigest()


class SettledStates:
    """The rested states of a :class:`DesignTable`'s designs, settled by ``settling`` and cached
    on disk (module doc): :meth:`get` reads the designs it finds and settles the others
    together, in padded batches, writing each.

    Args:
        table: the designs' table (its parts, settings and precision are the model's).
        settling: the rest rule (:class:`~softcrawl.robot.Settling`, in steps of the model's
            ``dt``; :func:`~softcrawl.jaxsim.engine.make_settle`).
        folder: the caches' folder (default :func:`settled_cache_dir`); each key a sub-folder.

    Attributes:
        settled: designs settled by this object; loaded: designs read from the disk.
        largest_batch: the batch the device's memory allowed after it ran out (None: it never did).
    """

    def __init__(self, table: DesignTable, settling: Settling = Settling(), folder: str | os.PathLike | None = None):
        self.table, self.settling = table, settling
        self.folder = Path(folder) if folder is not None else settled_cache_dir()
        hold, cap = settling.steps(table.parts.settings.dt)
        self.rule = (float(settling.rest_speed), hold, cap)
        self._settle = _settler(*self.rule)
        self._keys: dict[int, tuple[str, object, list]] = {}
        self._warned_write = False
        self.settled = self.loaded = 0
        self.largest_batch: int | None = None

    def _layout(self, n_slots: int) -> tuple[str, object, list]:
        """``(key, treedef, leaves)`` of ``n_slots`` leg slots: the cache key and the structure
        of one design's state (``jax.ShapeDtypeStruct`` leaves, no batch axis)."""
        if n_slots not in self._keys:
            model = self.table.model(np.zeros((0, self.table.space.n_slots), np.int64), n_slots)
            leaves, treedef = jax.tree_util.tree_flatten(jax.eval_shape(engine.rest_state, model))
            leaves = [jax.ShapeDtypeStruct(a.shape[1:], a.dtype) for a in leaves]
            self._keys[n_slots] = (self._key(n_slots, treedef, leaves), treedef, leaves)
        return self._keys[n_slots]

    def key(self, n_slots: int) -> str:
        """SHA-256 hex of what a rested state of ``n_slots`` leg slots depends on: the model's
        shared arrays and settings, the tables, ``n_slots``, the rest rule, the precision, the
        state's structure, :data:`softcrawl.jaxsim.engine.ENGINE_VERSION`, the JAX version
        and backend."""
        return self._layout(int(n_slots))[0]

    def _key(self, n_slots: int, treedef, leaves) -> str:
        t = self.table
        parts, parts_def = jax.tree_util.tree_flatten(t.parts)
        arrays = {f"parts{i}": np.asarray(a) for i, a in enumerate(parts)}
        arrays.update(rotation=t.rotation, translation=t.translation, disk_nodes=t.disk_nodes,
                      disk_weights=t.disk_weights, att_gram=t.att_gram)
        text = repr((str(parts_def), t.parts.settings, n_slots, self.rule, str(t.dtype), str(treedef),
                     [(a.shape, str(a.dtype)) for a in leaves], engine.ENGINE_VERSION, jax.__version__,
                     jax.default_backend()))
        return hashlib.sha256((text + _digest(arrays)).encode()).hexdigest()

    def _path(self, key: str, design: tuple) -> Path:
        name = hashlib.sha256(",".join(map(str, design)).encode()).hexdigest()[:32]
        return self.folder / key / f"{name}.npz"

    def _load(self, key: str, treedef, leaves, design: tuple) -> Rested | None:
        """The cached :class:`Rested` of ``design``, or None (no file; a bad one warned about).

        A file holds ``meta`` (the key and the SHA-256 of the other arrays), ``design``,
        ``stats`` (steps, speed, ok as float64) and ``state``: the state's leaves' bytes, in
        ``tree_leaves`` order (their shapes and dtypes are the key's)."""
        path = self._path(key, design)
        if not path.exists():
            return None
        try:
            with np.load(io.BytesIO(read_bytes(path, MAX_STATE_BYTES)), allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
            if set(arrays) != {"meta", "design", "stats", "state"} or arrays["meta"].shape != (2,):
                raise ValueError("other arrays than a settled state's")
            stored_key, stored = (str(v) for v in arrays.pop("meta"))
            if _digest({"key": np.array(stored_key), **arrays}) != stored:
                raise ValueError("its arrays do not match their SHA-256")
            if stored_key != key or arrays["design"].tolist() != list(design):
                raise ValueError("it is another model's or design's")
            buf, state, at = arrays["state"], [], 0
            if buf.dtype != np.uint8 or buf.size != sum(np.dtype(s.dtype).itemsize * int(np.prod(s.shape))
                                                        for s in leaves):
                raise ValueError("its state has another size")
            for s in leaves:
                n = int(np.prod(s.shape))
                state.append(np.frombuffer(buf, s.dtype, n, at).reshape(s.shape).copy())
                at += n * np.dtype(s.dtype).itemsize
            steps, speed, ok = arrays["stats"].tolist()
        except Exception as exc:  # anything unreadable is settled again, never trusted
            warnings.warn(f"settled-state cache entry {path} is unusable ({exc}); settling the design again",
                          stacklevel=3)
            return None
        return Rested(jax.tree_util.tree_unflatten(treedef, state), int(steps), float(speed), bool(ok))

    def _store(self, key: str, design: tuple, rested: Rested) -> None:
        """Write ``rested`` atomically (a temporary file renamed; layout: :meth:`_load`); a
        failure is warned about once."""
        path = self._path(key, design)
        state = b"".join(np.ascontiguousarray(a).tobytes() for a in jax.tree_util.tree_leaves(rested.state))
        arrays = {"design": np.asarray(design, np.int64), "stats": np.array([rested.steps, rested.speed, rested.ok],
                                                                            np.float64),
                  "state": np.frombuffer(state, np.uint8)}
        arrays["meta"] = np.array([key, _digest({"key": np.array(key), **arrays})])
        tmp = None
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=path.parent, suffix=".tmp", delete=False) as f:
                tmp = f.name
                np.savez(f, **arrays)
            os.replace(tmp, path)
        except OSError as exc:
            if tmp is not None and os.path.exists(tmp):
                os.unlink(tmp)
            if not self._warned_write:
                warnings.warn(f"could not write the settled-state cache {path.parent}: {exc}", stacklevel=3)
                self._warned_write = True

    def get(self, designs: Sequence, n_slots: int | None = None, batch: int = 64, base: int = 4,
            smallest: int = 4) -> list[Rested]:
        """The :class:`Rested` of each of ``designs`` (valid designs of the table's space, as
        tuples), in order: read from the cache, or settled now (``batch`` at a time, padded to
        :func:`~softcrawl.jaxsim.batch.padded_size` ``(n, batch, base, smallest)`` robots) and
        written to it.

        Args:
            n_slots: the leg slots of the states (default: each design's leg count; the
                designs are then settled in groups of one leg count).

        Where the device runs out of memory on a batch, the batches are halved from then on
        (:attr:`largest_batch`; a warning) and the batch settled again.

        Raises:
            InvalidDesignError: an invalid design. ValueError: a design with more legs than
                ``n_slots``. JaxRuntimeError: the device's, other than a lack of memory of a batch
                of more than one robot.
        """
        designs = [tuple(int(v) for v in d) for d in self.table.designs_array(designs)]
        out: dict[int, Rested] = {}
        missing: dict[int, list[int]] = {}
        for i, d in enumerate(designs):
            L = n_slots if n_slots is not None else sum(v > 0 for v in d)
            if sum(v > 0 for v in d) > L:
                raise ValueError(f"a design with {sum(v > 0 for v in d)} legs does not fit the JAX batch's "
                                 f"{L} leg slots")
            key, treedef, leaves = self._layout(L)
            rested = self._load(key, treedef, leaves, d)
            if rested is None:
                missing.setdefault(L, []).append(i)
            else:
                out[i] = rested
                self.loaded += 1
        for L, idx in missing.items():
            key = self._layout(L)[0]
            todo = list(dict.fromkeys(designs[i] for i in idx))

            def settle(chunk, size, L=L, key=key):
                state, steps, speed, ok = jax.device_get(
                    self._settle(self.table.model(chunk + chunk[-1:] * (size - len(chunk)), L)))
                rested = [Rested(jax.tree_util.tree_map(lambda a: np.array(a[j]), state), int(steps[j]),
                                 float(speed[j]), bool(ok[j])) for j in range(len(chunk))]
                for d, r in zip(chunk, rested):
                    self._store(key, d, r)
                    self.settled += 1
                return rested

            first = min(batch, self.largest_batch or batch)
            rested, largest = in_batches(todo, first, lambda n, b: padded_size(n, b, base, smallest), settle,
                                         "settling")
            if largest < first:
                self.largest_batch = largest
            done = dict(zip(todo, rested))
            out.update((i, done[designs[i]]) for i in idx)
        return [out[i] for i in range(len(designs))]

    def prebuild(self, designs: Sequence, n_slots: int | None = None, batch: int = 64, progress: bool = True) -> int:
        """Make sure the cache holds every one of ``designs`` (e.g. a space's
        ``canonical_designs``): read each (checking it) and settle the missing ones, ``batch``
        at a time in leg-count order, with a tqdm bar on stderr. Returns the designs settled.

        Raises:
            as :meth:`get`.
        """
        from tqdm.auto import tqdm

        designs = self.table.designs_array(designs)
        order = np.argsort((designs > 0).sum(axis=1), kind="stable")
        before = self.settled
        with tqdm(total=len(order), unit="design", desc="settling", disable=not progress) as bar:
            for start in range(0, len(order), batch):
                chunk = designs[order[start:start + batch]]
                self.get(chunk, n_slots, batch)
                bar.update(len(chunk))
        return self.settled - before
