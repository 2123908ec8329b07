"""A batch of fixed size whose robots change one by one: rows written into a batch by index, and
robots settled to rest in batches of a few padded sizes.

A vector env that swaps one robot's design at a reset needs only that robot's
:class:`~softcrawl.jaxsim.model.RobotData` row (gathered from a
:class:`~softcrawl.jaxsim.tables.DesignTable`) and rested state. Writing rows into the batch
(:func:`put_rows`) and settling new designs (:func:`make_batch_settle`) take arrays whose
leading size is padded to a power of four or ``B`` (:func:`padded_size`), so that a run
compiles each at most ``log4(B) + 1`` times.
"""

from __future__ import annotations

import dataclasses
import warnings
from functools import partial

import jax
import numpy as np

from softcrawl.jaxsim.engine import max_speed, rest_state
from softcrawl.jaxsim.rig import healthy


def padded_size(n: int, batch: int, base: int = 4, smallest: int = 4) -> int:
    """The smallest power of ``base`` that is ``>= max(n, smallest)``, at most ``batch``
    (``n <= batch``): the padded leading size of ``n`` rows, so that a caller compiles a few
    programs (one per size), not one per row count."""
    size = 1
    while size < max(n, smallest):
        size *= base
    return min(batch, size)


def halved_on_memory(error: BaseException, size: int, what: str) -> int:
    """The batch to try again with after ``error`` at ``size`` robots: ``size // 2`` where the
    device ran out of memory (XLA's ``RESOURCE_EXHAUSTED``) and ``size > 1``, with a warning
    naming ``what``; any other error, or one robot out of memory, is raised again.

    Raises:
        BaseException: ``error``, where it is not a device's lack of memory of a batch."""
    if size < 2 or not (isinstance(error, jax.errors.JaxRuntimeError) and "RESOURCE_EXHAUSTED" in str(error)):
        raise error
    warnings.warn(f"the device ran out of memory on {what} of {size} robots a batch; going on at {size // 2}",
                  stacklevel=2)
    return size // 2


def in_batches(items: list, largest: int, size_of, run, what: str) -> tuple[list, int]:
    """``run(chunk, size)`` (a list of one result per item of ``chunk``) for consecutive chunks of
    at most ``largest`` of ``items``, ``size = size_of(len(chunk), largest)`` the chunk's padded
    batch; where the device runs out of memory on one, ``largest`` is halved
    (:func:`halved_on_memory`) and the chunk run again. Returns every item's result, in order,
    and the largest batch at the end.

    Raises:
        BaseException: what ``run`` raises, other than a lack of memory of a batch of more than
            one robot."""
    out, start = [], 0
    while start < len(items):
        chunk = items[start:start + largest]
        size = size_of(len(chunk), largest)
        try:
            out.extend(run(chunk, size))
        except Exception as error:  # out of the device's memory: smaller batches from now on
            largest = halved_on_memory(error, size, what)
            continue
        start += len(chunk)
    return out, largest


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
    """Row ``i`` of every array of a batched pytree (numpy copies on the host: they do not keep
    the batch alive)."""
    return jax.tree_util.tree_map(lambda a: np.array(a[i]), tree)

