"""A batch of fixed size whose robots change one by one: per-robot rows of a
:class:`~softcrawl.jaxsim.model.Model` built without rebuilding its shared parts, rows written
into a batch by index, and robots settled to rest in batches of a few padded sizes.

:func:`~softcrawl.jaxsim.model.build_model` makes the shared leg and disk parts (the disk's
dense ``A_0^-1`` among them) every time it is called; a vector env that swaps one robot's
design at a reset needs only that robot's :class:`~softcrawl.jaxsim.model.RobotData` row
(:func:`robot_rows`). Writing rows into the batch (:func:`put_rows`) and settling new designs
(:func:`make_batch_settle`) take arrays whose leading size is padded to a power of four or
``B`` (:func:`padded_size`), so that a run compiles each at most ``log4(B) + 1`` times.
"""

from __future__ import annotations

import dataclasses
from functools import partial

import jax
import numpy as np

from softcrawl.jaxsim.engine import max_speed, rest_state
from softcrawl.jaxsim.model import RobotData, _robot_data
from softcrawl.jaxsim.rig import healthy


def robot_rows(model, robot, n_slots: int | None = None, inverse: np.ndarray | None = None) -> RobotData:
    """``robot``'s :class:`RobotData` (no batch axis, numpy, the model's float precision) for
    ``model``'s disk and ``n_slots`` leg slots (default: the model's): the row
    :func:`~softcrawl.jaxsim.model.build_model` would stack for it, without building the shared
    parts again (the disk's dense ``A_0^-1`` above all).

    Args:
        inverse: the disk's ``A_0^-1`` ``(3n, 3n)`` in float64, for the attachment Gram blocks
            (default: the model's; in float32 those blocks are then within one rounding of
            ``build_model``'s, which come from the float64 inverse).

    Raises:
        ValueError: ``robot`` has more legs than the slots, another disk mesh, or an
            attachment that does not tie a leg to the disk.
    """
    n_slots = model.robot.leg_mask.shape[-1] if n_slots is None else n_slots
    if len(robot.legs) > n_slots:
        raise ValueError(f"a design with {len(robot.legs)} legs does not fit the JAX batch's {n_slots} leg slots")
    dtype = np.dtype(model.disk.rest.dtype)
    disk = np.asarray(robot.model.bodies[robot.disk_body].mesh.points).astype(dtype)
    if not np.array_equal(disk, np.asarray(model.disk.rest)):
        raise ValueError("a robot of another disk mesh than the JAX batch's")
    rows = _robot_data(robot, n_slots, np.asarray(model.disk.inverse if inverse is None else inverse, np.float64))
    return RobotData(*(a.astype(dtype) if a.dtype.kind == "f" else a
                       for a in (getattr(rows, f.name) for f in dataclasses.fields(RobotData))))


def padded_size(n: int, batch: int, base: int = 4, smallest: int = 4) -> int:
    """The smallest power of ``base`` that is ``>= max(n, smallest)``, at most ``batch``
    (``n <= batch``): the padded leading size of ``n`` rows, so that a caller compiles a few
    programs (one per size), not one per row count."""
    size = 1
    while size < max(n, smallest):
        size *= base
    return min(batch, size)


def stack_padded(rows, size: int):
    """The pytrees ``rows`` (non-empty) stacked along a new leading axis of ``size`` (numpy),
    the last row repeated as padding."""
    rows = list(rows) + [rows[-1]] * (size - len(rows))
    return jax.tree_util.tree_map(lambda *a: np.stack(a), *rows)


@partial(jax.jit, donate_argnums=0)
def put_rows(batch, index, rows):
    """``batch`` (a pytree, leading axis ``B``) with rows ``index`` ``(k,)`` replaced by ``rows``
    (leading axis ``k``); an index of ``B`` or more writes nothing (padding). The input buffers
    are donated: use only the result."""
    return jax.tree_util.tree_map(lambda a, r: a.at[index].set(r.astype(a.dtype), mode="drop"), batch, rows)


def make_batch_settle(settle):
    """A jitted ``settle_rows(model) -> (state, steps, speed, ok)``: the robots of ``model`` (its
    per-robot rows) from :func:`~softcrawl.jaxsim.engine.rest_state` settled by ``settle`` (a
    :func:`~softcrawl.jaxsim.engine.make_settle` function), with per robot the steps taken
    ``(B,)``, the last :func:`~softcrawl.jaxsim.engine.max_speed` ``(B,)`` mm/s and whether the
    state is valid (:func:`~softcrawl.jaxsim.rig.healthy`) ``(B,)``."""

    def speed(model, rd, state):
        return max_speed(dataclasses.replace(model, robot=rd), state)

    @jax.jit
    def settle_rows(model):
        state, steps = settle(model, rest_state(model))
        fast = jax.vmap(speed, in_axes=(None, 0, 0))(dataclasses.replace(model, robot=None), model.robot, state)
        return state, steps, fast, jax.vmap(healthy)(state)

    return settle_rows


def take(tree, i: int):
    """Row ``i`` of every array of a batched pytree (numpy on the host)."""
    return jax.tree_util.tree_map(lambda a: np.asarray(a[i]), tree)

