"""The constraint rows of one robot in JAX and its condensed Delassus operator, assembled by blocks.

A robot's constraints (reduction.md, "Constraints"; :mod:`softcrawl.jaxsim.contact`): ``A = L F``
attachment points (``F`` per leg slot, equality, leg point minus disk point), then ``K = K_d +
L K_l`` floor contacts (normal, tangent 1, tangent 2): the disk's ``K_d`` lowest collision
points, then each leg slot's ``K_l``. The Delassus operator ``W = sum_b J_b A_b^-1 J_b^T``
(Duriez et al. 2006, sec. 4) has the block structure of who touches what:

* the disk's share involves the attachment rows and the disk's contact rows only, from its
  constant ``A_0^-1`` rotated by the floating frame (gathered node blocks);
* leg ``l``'s share involves its own ``3 F`` attachment rows and ``3 K_l`` contact rows only:
  with the leg's step matrix ``A_l = C_l C_l^T`` (Cholesky) and its ``(3 F + 3 K_l, m)`` rows
  ``J_l``, it is ``Y_l^T Y_l``, ``Y_l = C_l^-1 J_l^T``. Formed per leg this costs
  ``L (3F + 3K_l)^2 m`` multiply-adds, against ``(3A + 3K)^2 L m`` for the dense sum.

The attachments are eliminated exactly by a Schur complement (:func:`condense`): ``P = W_cb
W_bb^-1``, ``W_c = W_cc - P W_bc``, ``q_c = u_c - P u_b``, where a leg's contact rows of ``W_cb``
are non-zero in its own attachment columns only, so that both products are formed by blocks;
``W_c`` stays in its parts (:class:`softcrawl.jaxsim.schur.SchurOperator`). The contact problem
``(W_c, q_c)`` is then solved by :mod:`softcrawl.jaxsim.contact`; :func:`corrections` maps the
impulses back to velocities.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from functools import partial, reduce

import jax
import jax.numpy as jnp

from softcrawl.jaxsim import candidates, elimination
from softcrawl.jaxsim.contact import floor_contacts
from softcrawl.jaxsim.factor import inverse_spd
from softcrawl.jaxsim.frames import by_rows, homogeneous
from softcrawl.jaxsim.gpu import cuda_kernel
from softcrawl.jaxsim.model import register_pytree
from softcrawl.jaxsim.schur import SchurOperator, block_diagonal

#: Floor contact frame, rows normal, tangent 1, tangent 2 (:mod:`softcrawl.fem.solver`).
FLOOR_FRAME = ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0), (0.0, 1.0, 0.0))
#: The world axes of :data:`FLOOR_FRAME`'s rows (a permutation): ``FLOOR_FRAME @ M`` is
#: ``M[FLOOR_AXES, :]``, a gather of rows instead of a matrix product.
FLOOR_AXES = (2, 0, 1)
#: z given to the collision points of absent legs (mm): never a contact.
FAR = 1e6


@dataclass(frozen=True)
class Rows:
    """One step's constraint rows of one robot (``L`` leg slots of ``m`` modes, ``F`` attachment
    points each, ``K_d`` disk and ``K_l`` leg contact points each).

    Attributes:
        leg: ``(L, 3F + 3K_l, m)`` each leg's rows, its attachments first (leg point, world
            frame), then its contacts (contact frame :data:`FLOOR_FRAME`), modal.
        disk_aa: ``(3A, 3A)`` the disk's share among the attachment rows (``A = L F``).
        disk_ad: ``(3A, 3K_d)`` its share between the attachments and its own contacts.
        disk_dd: ``(3K_d, 3K_d)`` its share among its contacts.
        u_att: ``(3A,)`` the attachments' free velocities (disk side and drift), mm/s, without
            the legs' part; u_disk: ``(3K_d,)`` the disk contacts' (with the gap term ``g / h``);
            gap_leg: ``(L, K_l)`` the leg contacts' gap terms ``g / h``, mm/s.
        att_nodes, att_weights: ``(A, 4)`` the disk side of each attachment point.
        points: ``(K,)`` the contacts' point indices (disk collision nodes, then each leg
            slot's); active: ``(K,)`` whether each is a contact candidate.
        disk_node: ``(K_d,)`` the disk contacts' nodes.
        bilateral: ``(3A,)`` the attachment rows of present legs.
        warm: ``(K, 3)`` each contact's impulse of last step where its point was a contact
            then (0 else), mN s: the contact solve's warm start.
    """

    leg: jax.Array
    disk_aa: jax.Array
    disk_ad: jax.Array
    disk_dd: jax.Array
    u_att: jax.Array
    u_disk: jax.Array
    gap_leg: jax.Array
    att_nodes: jax.Array
    att_weights: jax.Array
    points: jax.Array
    active: jax.Array
    disk_node: jax.Array
    bilateral: jax.Array
    warm: jax.Array


register_pytree(Rows)


def _disk_gather(inverse, rows_nodes, cols_nodes):
    """Blocks ``A_0^-1[n_p, n_q]`` ``(..., 3, ..., 3)`` of node index arrays."""
    r = 3 * rows_nodes[..., None] + jnp.arange(3)
    c = 3 * cols_nodes[..., None] + jnp.arange(3)
    return inverse[r.reshape(r.shape + (1,) * c.ndim), c.reshape((1,) * r.ndim + c.shape)]


def leg_height_terms(leg, rd, q, qdot):
    """``(2, L, nc)``: the world heights of the legs' collision nodes before their placement's
    translation (mm), then their vertical velocities (mm/s). Only the third row ``u`` of each
    leg's rotation enters, ``z_n = u . (X_n + Phi_n q) (+ t_z) = [Phi_n, X_n] : (u (q, 1)^T)``,
    so that heights and velocities are one product of ``leg.coll_affine``, read as ``(nc, 3 (m +
    1))``, with the legs' ``u (x) (q, 1)`` and ``u (x) (qdot, 0)``: it writes the heights alone,
    not the nodes' three coordinates (:func:`place_heights` adds ``t_z``)."""
    up = rd.rotation[:, 2]  # (L, 3): world z = up . part-frame position
    qq = jnp.stack([homogeneous(q), homogeneous(qdot, 0.0)])
    return jnp.einsum("nam,klam->kln", leg.coll_affine, up[None, :, :, None] * qq[:, :, None, :])


def place_heights(z, shift, present):
    """The legs' heights ``(L, nc)`` (mm): ``z`` of :func:`leg_height_terms` shifted by each leg's
    translation ``shift`` ``(L,)`` (mm), :data:`FAR` up for the absent ones (``present`` false)."""
    return jnp.where(present[:, None], z + shift[:, None], FAR)


def select_contacts(model, state, v_free, qd_free):
    """The contact points of this step: the disk's ``K_d`` and each leg's ``K_l`` lowest predicted
    gaps, last step's loaded points first (:func:`softcrawl.jaxsim.contact.floor_contacts` on the
    points with those lowered by :data:`FAR`).

    Each body gets its own rows, so that one body's landing cannot take the others'; loaded
    points stay, as in the CPU engine's contact set: a leg lying on its paper face has more
    points at the floor than rows, and a set redrawn every step chatters. Chosen as
    :data:`softcrawl.jaxsim.candidates.SELECTION` says: by XLA for all bodies at once, or in one
    kernel, one program a body; the same choice.

    Returns:
        ``(idx, active, gap, warm)``: ``(K,)`` point indices (disk collision nodes, then each leg
        slot's), whether each is a candidate, its current gap (mm), and ``(K, 3)`` its impulse of
        last step where it was a contact then (0 else), mN s.

    Raises:
        ValueError: an unknown ``candidates.SELECTION``.
    """
    st, leg, dk, rd = model.settings, model.leg, model.disk, model.robot
    args = (dk.collision, state.x, v_free, leg_height_terms(leg, rd, state.q, qd_free), rd.translation, rd.leg_mask,
            state.contact_points, state.impulses)
    rule = dict(Kd=st.disk_contacts, Kl=st.leg_contacts, floor_z=st.floor_z, distance=st.contact_distance, dt=st.dt)
    if candidates.SELECTION not in candidates.SELECTIONS:
        raise ValueError(f"candidates.SELECTION must be one of {candidates.SELECTIONS}, not {candidates.SELECTION!r}")
    if candidates.SELECTION == "xla":
        return _selected_by_xla(*args, **rule)
    if candidates.SELECTION == "interpret":
        return _selected_by_kernel(*args, **rule, interpret=True)
    return jax.lax.platform_dependent(*args, **cuda_kernel(partial(_selected_by_kernel, **rule, interpret=False)),
                                      default=partial(_selected_by_xla, **rule))


def _selected_by_xla(collision, x, v, legs, translation, present, points, impulses, *, Kd, Kl, floor_z, distance,
                     dt):
    """:func:`select_contacts` for all bodies at once (its arguments as
    :func:`softcrawl.jaxsim.candidates.robot_candidates`')."""
    zl, vl = place_heights(legs[0], translation[:, 2], present), legs[1]
    nd, (L, nc) = collision.shape[0], zl.shape
    z, vz = jnp.concatenate([x[collision, 2], zl.reshape(-1)]), jnp.concatenate([v[collision, 2], vl.reshape(-1)])
    pts = jnp.where(points >= 0, points, z.shape[0])
    loaded = jnp.zeros(z.shape[0], bool).at[pts].max(impulses[:, 0] > 0, mode="drop")
    ranked = z - jnp.where(loaded, FAR, 0.0)
    select = partial(floor_contacts, floor_z=floor_z, distance=distance, dt=dt)
    i_d, a_d, _ = select(ranked[:nd], vz[:nd], K=Kd)
    i_l, a_l, _ = jax.vmap(partial(select, K=Kl))(ranked[nd:].reshape(L, nc), vz[nd:].reshape(L, nc))
    idx = jnp.concatenate([i_d, (i_l + nd + nc * jnp.arange(L)[:, None]).reshape(-1)])
    warm = (idx[:, None] == points[None, :]).astype(impulses.dtype) @ impulses
    return idx, jnp.concatenate([a_d, a_l.reshape(-1)]), z[idx] - floor_z, warm


def _selected_by_kernel(*args, interpret, **rule):
    """:func:`_selected_by_xla`'s choice in one kernel (:func:`softcrawl.jaxsim.candidates.robot_candidates`),
    its indices in JAX's default integer (as XLA's)."""
    idx, active, gap, warm = candidates.robot_candidates(*args, far=FAR, interpret=interpret, **rule)
    return idx.astype(jax.dtypes.canonicalize_dtype(jnp.int64)), active, gap, warm


def _turned(X, G, Y):
    """``(P, 3, Q, 3)`` the blocks ``X G_pq Y^T`` of ``G`` ``(P, 3, Q, 3)`` (``X``, ``Y`` ``(3, 3)``)
    as nine elementwise products summed: XLA fuses them with whatever forms ``G`` (a gather, a
    sum), where an einsum of 3 x 3 blocks becomes batched products of tiny matrices (on a GPU,
    library calls with transposes through memory)."""
    terms = [X[:, b][None, :, None, None] * G[:, b, :, c][:, None, :, None] * Y[:, c][None, None, None, :]
             for b in range(3) for c in range(3)]
    return reduce(operator.add, terms)


def _weighted(w, y):
    """``sum_i w[a, i] y[a, i]``: ``(A, ...)`` of the weights ``w`` ``(A, I)`` and ``y`` ``(A, I,
    ...)`` (each attachment patch's ``I`` disk nodes), as ``I`` elementwise products summed."""
    return reduce(operator.add, [w[:, i].reshape((-1,) + (1,) * (y.ndim - 2)) * y[:, i] for i in range(w.shape[1])])


def constraint_rows(model, state, v_free, qd_free, R) -> Rows:
    """The attachment and contact rows of this step (module doc) from the free velocities
    ``v_free`` ``(n, 3)`` (disk, mm/s) and ``qd_free`` ``(L, m)`` (legs, mm/s) and the disk's
    frame ``R`` ``(3, 3)``."""
    st, leg, dk, rd = model.settings, model.leg, model.disk, model.robot
    h = st.dt
    L, m = state.q.shape
    F = leg.att_affine.shape[0]
    A = L * F
    dt = v_free.dtype
    # attachments: leg point minus disk point (3-vectors turned and weighted by elementwise sums)
    x_leg = by_rows(jnp.einsum("fam,lm->lfa", leg.att_affine, homogeneous(state.q)),
                    jnp.swapaxes(rd.rotation, 1, 2)[:, None])
    x_leg = x_leg + rd.translation[:, None]
    nodes, w = rd.disk_nodes.reshape(A, -1), rd.disk_weights.reshape(A, -1)
    drift = (x_leg.reshape(A, 3) - _weighted(w, state.x[nodes])) * jnp.repeat(rd.leg_mask, F)[:, None]
    u_att = (drift / h - _weighted(w, v_free[nodes])).reshape(-1)
    disk_aa = _turned(R, rd.att_gram.transpose(0, 2, 1, 3), R).reshape(3 * A, 3 * A)
    # contacts: the disk's, then each leg's
    nd, nc, Kd, Kl = dk.collision.shape[0], leg.coll_affine.shape[0], st.disk_contacts, st.leg_contacts
    if Kd + Kl:
        idx, active, gap, warm = select_contacts(model, state, v_free, qd_free)
    else:  # no floor
        idx, active, gap = jnp.zeros(0, jnp.int32), jnp.zeros(0, bool), jnp.zeros(0, dt)
        warm = jnp.zeros((0, 3), dt)
    DR = R[FLOOR_AXES, :]  # FLOOR_FRAME @ R
    node = dk.collision[idx[:Kd]]
    lnode = (idx[Kd:] - nd).reshape(L, Kl) % nc
    disk_dd = _turned(DR, _disk_gather(dk.inverse, node, node), DR).reshape(3 * Kd, 3 * Kd)
    disk_ad = -_turned(R, _weighted(w, _disk_gather(dk.inverse, nodes, node)), DR)  # each patch's nodes weighted
    disk_ad = disk_ad.reshape(3 * A, 3 * Kd)
    u_disk = v_free[node][:, FLOOR_AXES].at[:, 0].add(gap[:Kd] / h).reshape(-1)
    # each leg's rows [J_att; J_con] at once, (L, 3 (F + Kl), m): its attachment patches' basis rows
    # turned to the world frame (R_l; an absent leg's rows 0), its contact points' to the floor's
    # (FLOOR_FRAME R_l), by elementwise sums (one operation with the gather, not products of tiny
    # matrices and their concatenation)
    frames = jnp.concatenate([jnp.broadcast_to((rd.rotation * rd.leg_mask[:, None, None])[:, None], (L, F, 3, 3)),
                              jnp.broadcast_to(rd.rotation[:, None, FLOOR_AXES], (L, Kl, 3, 3))], axis=1)
    basis = jnp.concatenate([jnp.broadcast_to(leg.att_affine[..., :m], (L, F, 3, m)), leg.coll_affine[lnode, :, :m]],
                            axis=1)
    rows = by_rows(frames, basis[:, :, None]).reshape(L, -1, m)
    return Rows(rows, disk_aa, disk_ad, disk_dd, u_att, u_disk, gap[Kd:].reshape(L, Kl) / h, nodes, w, idx,
                active, node, jnp.repeat(rd.leg_mask, 3 * F), warm)


@dataclass(frozen=True)
class DelassusBlocks:
    """The condensed Delassus operator ``W_c = W_cc - W_cb W_bb^-1 W_bc`` of one robot kept in its
    blocks (:func:`condense`), applied without forming it: ``W_c @ y`` (:meth:`__matmul__`) reads
    ``3K_d^2 + L (3K_l)^2 + 2 (3A 3K_d + L 3F 3K_l) + (3A)^2`` numbers, 22,176 for the paper
    preset's robots (``K_d`` 8, ``L`` 6, ``K_l`` 12, ``F`` 4) against ``(3K)^2 = 57,600`` of the
    dense ``W_c``: an iterative solve that streams its operator from memory every iteration (a
    GPU's at thousands of robots) moves 2.6 times fewer bytes.

    Attributes:
        disk: ``(3K_d, 3K_d)`` the disk's contacts among themselves; legs: ``(L, 3K_l, 3K_l)``
            each leg's contacts among themselves (``W_cc``, block diagonal).
        disk_att: ``(3A, 3K_d)`` and legs_att: ``(L, 3F, 3K_l)``: ``W_bc``, the attachments
            against the disk's contacts (dense) and each leg's against its own contacts.
        att_inv: ``(3A, 3A)`` ``W_bb^-1``.
    """

    disk: jax.Array
    legs: jax.Array
    disk_att: jax.Array
    legs_att: jax.Array
    att_inv: jax.Array

    def __matmul__(self, y):
        """``W_c y`` ``(3K,)``, mm/s, of contact impulses ``y`` ``(3K,)``, mN s (the disk's contacts
        first, then each leg's): the Schur complement of the module doc, term by term."""
        nd = self.disk.shape[0]
        L, F3, Kl3 = self.legs_att.shape
        yd, yl = y[:nd], y[nd:].reshape(L, Kl3)
        t = self.att_inv @ (self.disk_att @ yd + jnp.einsum("lbk,lk->lb", self.legs_att, yl).reshape(-1))
        return jnp.concatenate([self.disk @ yd - self.disk_att.T @ t,
                                (jnp.einsum("lij,lj->li", self.legs, yl)
                                 - jnp.einsum("lbk,lb->lk", self.legs_att, t.reshape(L, F3))).reshape(-1)])


register_pytree(DelassusBlocks)


@dataclass(frozen=True)
class Condensed:
    """The contact problem of one robot after the attachments' elimination (:func:`condense`).

    Attributes:
        schur: the contacts' Delassus operator ``W_c`` (mm/s per mN s) in its parts
            (:class:`~softcrawl.jaxsim.schur.SchurOperator`; :attr:`W` formed); q: ``(3K,)``
            their velocities at zero contact impulse, mm/s.
        x_u: ``(3A,)`` ``W_bb^-1 u_b``, mN s, and P: ``(3K, 3A)`` ``W_cb W_bb^-1``: the
            attachment impulses are ``-(x_u + P^T lam_c)``.
        Y: ``(L, m, 3F + 3K_l)`` each leg's ``C_l^-1 J_l^T`` (velocity corrections).
        blocks: ``W_c`` in its factors (:class:`DelassusBlocks`).
    """

    schur: SchurOperator
    q: jax.Array
    x_u: jax.Array
    P: jax.Array
    Y: jax.Array
    blocks: DelassusBlocks

    @property
    def W(self) -> jax.Array:
        """``(3K, 3K)`` the contacts' Delassus operator, formed (:meth:`SchurOperator.dense`)."""
        return self.schur.dense()


register_pytree(Condensed)


def condense(rows: Rows, inv_chol, qd_free, cholesky: str = "library") -> Condensed:
    """The condensed contact problem (module doc) of ``rows`` with the inverses ``inv_chol``
    ``(L, m, m)`` of the legs' step-matrix Cholesky factors (lower; ``C_l^-1``) and free modal
    velocities ``qd_free`` ``(L, m)``.

    The attachment block ``W_bb`` is positive definite for attachments of distinct disk nodes;
    rows of absent legs are identity rows with zero impulse. Its inverse is formed from its
    Cholesky factor's (:func:`softcrawl.jaxsim.factor.inverse_spd` in the form ``cholesky``), so
    that ``P`` and ``S = P W_bc`` are products, by the blocks of ``W_cb`` and ``W_bc``
    (:func:`softcrawl.jaxsim.elimination.products`).
    """
    L, n_leg, m = rows.leg.shape
    F3 = rows.u_att.shape[0] // L
    Y = jnp.einsum("lmk,lik->lmi", inv_chol, rows.leg)  # C_l^-1 J_l^T, (L, m, n_leg)
    G = jnp.einsum("lmi,lmj->lij", Y, Y)  # each leg's share, (L, n_leg, n_leg)
    u_leg = jnp.einsum("lim,lm->li", rows.leg, qd_free)  # legs' part of the free velocities
    dt = G.dtype
    # attachments: the disk's dense share plus each leg's diagonal block
    W_bb = rows.disk_aa + block_diagonal(G[:, :F3, :F3])
    m_b = rows.bilateral
    W_bb = jnp.where(m_b[:, None] & m_b[None, :], W_bb, jnp.eye(L * F3, dtype=dt))
    u_b = jnp.where(m_b, rows.u_att + u_leg[:, :F3].reshape(-1), 0)
    W_inv = inverse_spd(W_bb, cholesky)
    # P = W_cb W_bb^-1 and S = P W_bc by the blocks of W_cb and W_bc (a leg's contact rows use its own
    # attachments only), q_c and x_u: XLA's products or one kernel (elimination.FORM)
    u_c = jnp.concatenate([rows.u_disk, (u_leg[:, F3:] + _gap_rows(rows.gap_leg)).reshape(-1)])
    P, s_disk, s_legs, q_c, x_u = elimination.products(W_inv, rows.disk_ad, G, m_b, u_b, u_c)
    W_bd, W_bl = elimination.attachment_blocks(rows.disk_ad, G, m_b)
    return Condensed(SchurOperator(rows.disk_dd, G, s_disk, s_legs), q_c, x_u, P, Y,
                     DelassusBlocks(rows.disk_dd, G[:, F3:, F3:], W_bd, W_bl, W_inv))


def _gap_rows(gap):
    """``(L, 3K_l)`` the gap terms ``g / h`` ``(L, K_l)`` on the normal rows."""
    return jnp.stack([gap, jnp.zeros_like(gap), jnp.zeros_like(gap)], axis=-1).reshape(gap.shape[0], -1)


def corrections(model, rows: Rows, cond: Condensed, inv_chol, lam_c, R):
    """Velocity corrections of the impulses: ``(dq (L, m), dv (n, 3))`` for the contact impulses
    ``lam_c`` ``(3K,)`` (mN s): the attachment impulses by back-substitution, each leg's
    ``A_l^-1 J_l^T lam_l = C_l^-T Y_l lam_l`` (``inv_chol`` as :func:`condense`'s), the disk's
    ``A_0^-1`` of its body-frame impulses.

    Returns:
        ``(dq, dv, lam_b)``: modal velocity changes (mm/s), disk node velocity changes (mm/s,
        world frame) and the attachment impulses ``(3A,)``, mN s.
    """
    L = rows.leg.shape[0]
    F3 = rows.u_att.shape[0] // L
    Kd3 = rows.disk_dd.shape[0]
    lam_b = -(cond.x_u + lam_c @ cond.P)
    lam_leg = jnp.concatenate([lam_b.reshape(L, F3), lam_c[Kd3:].reshape(L, rows.leg.shape[1] - F3)], axis=1)
    r = jnp.einsum("lmi,li->lm", cond.Y, lam_leg)
    dq = jnp.einsum("lkm,lk->lm", inv_chol, r)
    dk = model.disk
    dt = lam_c.dtype
    att = (-rows.att_weights[:, :, None] * by_rows(lam_b.reshape(-1, 3), R)[:, None, :]).reshape(-1, 3)
    con = by_rows(lam_c[:Kd3].reshape(Kd3 // 3, 3), R[FLOOR_AXES, :])
    f_body = jnp.zeros((dk.rest.shape[0], 3), dt).at[jnp.concatenate([rows.att_nodes.reshape(-1), rows.disk_node])].add(
        jnp.concatenate([att, con]))  # one scatter, attachments then contacts
    dv = by_rows((dk.inverse @ f_body.reshape(-1)).reshape(-1, 3), R.T)
    return dq, dv, lam_b
