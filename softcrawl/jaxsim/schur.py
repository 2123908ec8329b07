"""The condensed Delassus operator of one robot in the blocks it is formed from.

After the attachments' elimination (:func:`softcrawl.jaxsim.delassus.condense`) the contacts'
operator is a Schur complement ``W_c = W_cc - S``, ``S = W_cb W_bb^-1 W_bc``: ``W_cc`` is block
diagonal (the disk's contacts among themselves, each leg's among its own: who touches what),
``S`` dense. :class:`SchurOperator` keeps ``W_cc``'s diagonal blocks and ``S`` by the column
blocks of the same contacts, in the layout the step's products write them in, and forms ``W_c``
only where it is read: :meth:`SchurOperator.dense` for XLA's solves, or, in the GPU's solve
kernel, row block by row block from the parts (:mod:`softcrawl.jaxsim.fused`), so that the
dense operator is neither written to memory nor read from it.
"""

from __future__ import annotations

from dataclasses import dataclass

import jax
import jax.numpy as jnp


def block_diagonal(blocks) -> jax.Array:
    """The block-diagonal matrix ``(L a, L b)`` of ``blocks`` ``(L, a, b)``, formed as one product
    with the identity (no scatter, no concatenation)."""
    L, a, b = blocks.shape
    return (jnp.eye(L, dtype=blocks.dtype)[:, None, :, None] * blocks[:, :, None, :]).reshape(L * a, L * b)


@dataclass(frozen=True)
class SchurOperator:
    """``W_c = W_cc - S`` ``(3K, 3K)`` of one robot (module doc), ``K = K_d + L K_l`` contacts: the
    disk's ``K_d`` first, then each of ``L`` leg slots' ``K_l``; mm/s per mN s.

    Attributes:
        disk: ``(3K_d, 3K_d)`` ``W_cc``'s block of the disk's contacts among themselves.
        legs: ``(L, n_l, n_l)``, ``n_l >= 3K_l``: its block of each leg's contacts among themselves,
            the trailing ``3K_l`` rows and columns (the leading ones, the leg's attachments', are
            not read: each leg's whole Gram serves, uncopied).
        s_disk: ``(3K, 3K_d)`` ``S``'s columns of the disk's contacts.
        s_legs: ``(L, 3K, 3K_l)`` ``S``'s columns of each leg's contacts.
    """

    disk: jax.Array
    legs: jax.Array
    s_disk: jax.Array
    s_legs: jax.Array

    @property
    def dtype(self):
        """The parts' dtype: the operator's."""
        return self.s_disk.dtype

    @property
    def shape(self) -> tuple[int, int]:
        """``(3K, 3K)``, the formed operator's shape."""
        return (self.s_disk.shape[0],) * 2

    def dense(self) -> jax.Array:
        """``W_c`` ``(3K, 3K)``: each entry ``W_cc_ij - S_ij``, one subtraction (as the GPU kernel
        forms each entry it reads)."""
        nd, (L, n, nl) = self.disk.shape[0], self.s_legs.shape
        off = self.legs.shape[1] - nl  # the contacts' trailing rows and columns
        W_cc = jnp.zeros((n, n), self.dtype).at[:nd, :nd].set(self.disk)
        W_cc = W_cc.at[nd:, nd:].set(block_diagonal(self.legs[:, off:, off:]))
        return W_cc - jnp.concatenate([self.s_disk, self.s_legs.transpose(1, 0, 2).reshape(n, L * nl)], axis=1)


jax.tree_util.register_dataclass(SchurOperator, data_fields=["disk", "legs", "s_disk", "s_legs"], meta_fields=[])
