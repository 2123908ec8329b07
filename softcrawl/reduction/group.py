"""Reduced bodies that share one part (the legs of a robot), stepped together.

A :class:`ModalGroup` holds the static data of the bodies placed from one
:class:`~softcrawl.reduction.model.PartReduction`: one copy of the part's RID element data
and basis rows in the part frame, and per body its rotation, node offset, reduced mass,
gravity load, attachment rows ``H_f Phi`` and pressure channels. Its methods run the
batched compiled kernels of :mod:`softcrawl.reduction.kernels` (free motion, Delassus terms,
corrections) and expand modal velocities to nodal ones. The time-varying values (modal
velocities, the step matrices' Cholesky factors) are passed in and out; the group keeps none.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from softcrawl.fem.constraints import FixedRows
from softcrawl.fem.model import Model
from softcrawl.reduction.kernels import (accumulate_terms, accumulate_terms32, add_delassus, add_projected,
                                         add_strain_terms, cavity_forces, corrections, expand_velocities,
                                         floor_candidates, implicit_steps, point_velocity)
from softcrawl.reduction.model import ElementFactors, ReducedBody, rotate_basis


def _layout(body) -> tuple:
    """What the bodies of a group must share besides the part: materials, masses, membrane
    and cavity triangles (not the cavities' channels)."""
    mem = body.membrane
    return (body.material, body.nodal_mass.tobytes(),
            None if mem is None else (mem.material, mem.thickness, np.asarray(mem.triangles).tobytes()),
            tuple(np.asarray(c.triangles).tobytes() for c in body.cavities))


#: RID elements whose ``Z`` rows are formed at once (a chunk of all bodies' rows stays in cache).
ELEMENT_CHUNK = 64
#: Bodies whose RID terms are formed in one pass over the RID data (a group of more bodies, e.g.
#: the legs of a batch of robots, is run in blocks of this many, so a chunk of their ``Z`` rows
#: stays in cache: 8 legs x 64 elements x 6 rows x 34 modes = 0.8 MB). A body's terms do not
#: depend on the other bodies of its block (the same products in the same order).
BODY_BLOCK = 8


@dataclass(frozen=True, eq=False)
class ModalGroup:
    """Static data of reduced bodies placed from one part.

    Attributes:
        members: ``(L,)`` the bodies' indices in the model.
        offsets: ``(L,)`` their first node in the stacked state.
        n_nodes: nodes per body.
        rotations: ``(L, 3, 3)`` placement rotations (part frame -> world).
        basis: ``(3n, m)`` the part basis (part frame).
        families: the part's RID element families (part frame).
        strain_modes: ``(m',)`` the modes the families' rows hold (the others, the rigid
            translations, have no internal force or stiffness).
        mass: ``(L, m, m)`` reduced masses, kg.
        gravity: ``(L, m)`` reduced gravity loads, mN.
        cavity_triangles: ``(T, 3)`` the part's cavity triangles; cavity_local: ``(T, 3)``
            their vertices' indices into the ``c`` cavity nodes; cavity_basis: ``(3c, m)``
            the cavity nodes' basis rows; cavity_channel: ``(L, T)`` the pressure channel of
            each body's triangle.
        collision: ``(c,)`` part nodes that are floor contact candidates; collision_bound:
            ``(c,)`` the Frobenius norms of their basis rows (``|v_n| <= bound_n |qdot|``).
        fixed_rows: ``(L, 3F, m)`` world rows ``H_f Phi_b`` of each body's ``F`` attachment
            blocks; fixed_blocks: ``(L, F)`` their global block numbers.
        frame_rot: ``(L, 3, 3)`` the contact frame times each body's rotation.
    """

    members: np.ndarray
    offsets: np.ndarray
    n_nodes: int
    rotations: np.ndarray
    basis: np.ndarray
    families: tuple[ElementFactors, ...]
    strain_modes: np.ndarray
    mass: np.ndarray
    gravity: np.ndarray
    cavity_triangles: np.ndarray
    cavity_local: np.ndarray
    cavity_basis: np.ndarray
    cavity_channel: np.ndarray
    collision: np.ndarray
    collision_bound: np.ndarray
    fixed_rows: np.ndarray
    fixed_blocks: np.ndarray
    frame_rot: np.ndarray
    _work: dict = field(default_factory=dict, repr=False)  # scratch arrays of free_motion

    @classmethod
    def build(cls, model: Model, bodies: dict[int, ReducedBody], fixed: dict[int, FixedRows],
              contact_frame: np.ndarray) -> ModalGroup:
        """The group of ``bodies`` (index -> reduced body), which must share one part, one
        material and one cavity layout and have the same number of attachment blocks.

        Args:
            model: the model the bodies belong to.
            bodies: body index -> its :class:`ReducedBody`.
            fixed: body index -> its attachment rows (bodies without attachments absent).
            contact_frame: ``(3, 3)`` rows normal, tangent 1, tangent 2 of a floor contact.

        Raises:
            ValueError: the bodies do not share a part, materials, cavities or attachment count.
        """
        members = np.array(sorted(bodies), np.int64)
        rbs = [bodies[i] for i in members]
        first = rbs[0]
        part = first.part
        for rb in rbs[1:]:
            if rb.part is not part or _layout(rb.body) != _layout(first.body):
                raise ValueError("the bodies of a modal group must share a part, materials, masses and cavities")
        n_fixed = {len(fixed[i].blocks) if i in fixed else 0 for i in members}
        if len(n_fixed) != 1:
            raise ValueError(f"the bodies of a modal group must have equally many attachments, got {n_fixed}")
        n, m = part.mesh.n_nodes, part.n_modes
        Phi = part.basis
        R = np.stack([rb.rotation for rb in rbs])
        g = np.asarray(model.gravity, float)
        gravity = np.stack([Phi.T @ (rb.body.nodal_mass[:, None] * (g @ rb.rotation)[None, :]).ravel() for rb in rbs])
        cavities = first.body.cavities
        tris = (np.concatenate([np.asarray(c.triangles, np.int64) for c in cavities])
                if cavities else np.zeros((0, 3), np.int64))
        cavity_nodes, local = np.unique(tris, return_inverse=True)
        node_rows = Phi.reshape(n, 3, m)
        channel = np.stack([np.concatenate([np.full(len(c.triangles), c.channel) for c in rb.body.cavities])
                            if cavities else np.zeros(0, np.int64) for rb in rbs]).astype(np.int64)
        coll = np.asarray(first.body.collision_nodes, np.int64)
        nf = n_fixed.pop()
        rows = np.zeros((len(rbs), 3 * nf, m))
        blocks = np.zeros((len(rbs), nf), np.int64)
        for j, i in enumerate(members):
            if nf:
                # The rotated basis is formed for this product only (kept, it is 1.6 MB a leg).
                rows[j] = fixed[i].H @ rotate_basis(bodies[i].part.basis, bodies[i].rotation)
                blocks[j] = fixed[i].blocks
        return cls(members, model.node_offsets[members].astype(np.int64), n, R, Phi, first.element_factors,
                   first.strain_modes, np.stack([rb.reduced_mass for rb in rbs]), gravity, tris,
                   local.reshape(tris.shape).astype(np.int64), node_rows[cavity_nodes].reshape(-1, m), channel,
                   coll, np.linalg.norm(node_rows[coll], axis=(1, 2)), rows, blocks,
                   np.asarray(contact_frame, float) @ R)

    @classmethod
    def stack(cls, groups: list[ModalGroup], node_shift: np.ndarray, channel_shift: np.ndarray) -> ModalGroup:
        """One group of the bodies of ``groups`` (groups of separate models placed from equal
        parts, e.g. the legs of many robots), for positions and pressures stacked model after
        model: group ``i``'s nodes are shifted by ``node_shift[i]`` and its pressure channels
        by ``channel_shift[i]``. The part data (basis, RID families, cavity and collision
        nodes) are the first group's, shared; ``members`` become the bodies' positions in the
        stack. The attachment rows keep each model's own block numbers (constraints stay per
        model).

        Raises:
            ValueError: no groups, or groups of parts of different shapes.
        """
        if not groups:
            raise ValueError("need at least one group to stack")
        first = groups[0]
        for g in groups[1:]:
            if (g.basis.shape != first.basis.shape or g.strain_modes.shape != first.strain_modes.shape
                    or g.fixed_rows.shape[1:] != first.fixed_rows.shape[1:]
                    or len(g.families) != len(first.families)
                    or any(a.conn.shape != b.conn.shape for a, b in zip(g.families, first.families))):
                raise ValueError("stacked modal groups must be placed from the same part")
        cat = np.concatenate
        return cls(np.arange(sum(g.n_bodies for g in groups), dtype=np.int64),
                   cat([g.offsets + s for g, s in zip(groups, node_shift)]).astype(np.int64), first.n_nodes,
                   cat([g.rotations for g in groups]), first.basis, first.families, first.strain_modes,
                   cat([g.mass for g in groups]), cat([g.gravity for g in groups]), first.cavity_triangles,
                   first.cavity_local, first.cavity_basis,
                   cat([g.cavity_channel + s for g, s in zip(groups, channel_shift)]).astype(np.int64),
                   first.collision, first.collision_bound, cat([g.fixed_rows for g in groups]),
                   cat([g.fixed_blocks for g in groups]), cat([g.frame_rot for g in groups]))

    @property
    def n_bodies(self) -> int:
        return len(self.members)

    @property
    def n_modes(self) -> int:
        return self.basis.shape[1]

    def project(self, v: np.ndarray, bodies: np.ndarray | None = None) -> np.ndarray:
        """``(L, m)`` modal velocities ``Phi_b^T v_b`` of the stacked velocities ``v`` ``(N, 3)``
        (the basis is orthonormal); of the given ``bodies`` (positions in the group) only if
        given."""
        bodies = np.arange(self.n_bodies) if bodies is None else np.asarray(bodies)
        out = np.empty((len(bodies), self.n_modes))
        for i, j in enumerate(bodies):
            o = self.offsets[j]
            out[i] = self.basis.T @ (v[o:o + self.n_nodes] @ self.rotations[j]).ravel()
        return out

    def free_motion(self, x: np.ndarray, qdot: np.ndarray, pressures: np.ndarray, h: float, r_mass: float,
                    r_stiff: float, forces: np.ndarray | None = None,
                    rid_dtype: str = "float64") -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The linearly implicit step of every body without constraints.

        Args:
            x: ``(N, 3)`` stacked positions, mm.
            qdot: ``(L, m)`` modal velocities at the start of the step.
            pressures: ``(channels,)`` cavity pressures, kPa.
            h, r_mass, r_stiff: time step (s), Rayleigh coefficients.
            forces: optional ``(N, 3)`` prescribed nodal forces, mN.
            rid_dtype: ``"float64"`` or ``"float32"``: precision of the RID element products
                (:func:`~softcrawl.reduction.kernels.accumulate_terms32`).

        Returns:
            ``(qdot_free, chol, n_bad, positive)``: ``(L, m)`` free modal velocities, ``(L, m, m)``
            Cholesky factors of the step matrices, ``(L,)`` inverted or degenerate RID elements
            and ``(L,)`` bool whether each step matrix was positive definite.
        """
        L, m, ms = self.n_bodies, self.n_modes, len(self.strain_modes)
        single = rid_dtype == "float32"
        if (rid_dtype, "Z") not in self._work:  # scratch kept between steps (fresh pages cost more than filling them)
            rows = ELEMENT_CHUNK * max(f.factors.shape[1] for f in self.families)
            nb = min(L, BODY_BLOCK)
            self._work.update({(rid_dtype, "Z"): np.empty((nb, rows, ms), rid_dtype), "s": np.empty((nb, rows)),
                               "t": np.empty(rows)})
            if single:
                self._work["rows32"] = [f.rows.astype(np.float32) for f in self.families]
        n_bad = np.zeros(L, np.int64)
        K, load = np.zeros((L, m, m)), self.gravity.copy()
        if len(self.cavity_triangles):
            scale = np.asarray(pressures, float)[self.cavity_channel] / 3.0
            for b0 in range(0, L, BODY_BLOCK):
                b = slice(b0, min(L, b0 + BODY_BLOCK))
                if scale[b].any():
                    F = cavity_forces(x, self.offsets[b], self.rotations[b], self.cavity_triangles, self.cavity_local,
                                      len(self.cavity_basis) // 3, scale[b])
                    add_projected(F.reshape(b.stop - b0, -1), self.cavity_basis, load[b])
        if forces is not None:
            load += self.project(forces)
        Ks, fs = np.zeros((L, ms, ms), rid_dtype), np.zeros((L, ms))
        qs = np.ascontiguousarray(qdot[:, self.strain_modes])
        w = self._work
        for b0 in range(0, L, BODY_BLOCK):
            b = slice(b0, min(L, b0 + BODY_BLOCK))
            Z, s = w[(rid_dtype, "Z")][:b.stop - b0], w["s"][:b.stop - b0]
            for i, f in enumerate(self.families):
                if single:
                    accumulate_terms32(x, self.offsets[b], self.rotations[b], f.conn, f.factors, f.rest_terms,
                                       w["rows32"][i], qs[b], h + r_stiff, Z, s, Ks[b], fs[b], n_bad[b])
                else:
                    accumulate_terms(x, self.offsets[b], self.rotations[b], f.conn, f.factors, f.rest_terms, f.rows,
                                     qs[b], h + r_stiff, Z, s, w["t"], Ks[b], fs[b], n_bad[b])
        add_strain_terms(Ks.astype(np.float64, copy=False), fs, self.strain_modes, K, load)
        chol, qdot_free = np.empty((L, m, m)), np.empty((L, m))
        positive = implicit_steps(K, load, self.mass, qdot, h, r_mass, r_stiff, chol, qdot_free)
        return qdot_free, chol, n_bad, positive

    def velocities(self, qdot: np.ndarray, out: np.ndarray) -> None:
        """Write every body's world nodal velocities ``R_b Phi_p qdot_b`` (mm/s; ``qdot``:
        ``(L, m)``) into its rows of the stacked ``out`` ``(N, 3)``."""
        expand_velocities(qdot, self.basis, self.rotations, self.offsets, out)

    def add_delassus(self, W: np.ndarray, u: np.ndarray, chol: np.ndarray, qdot: np.ndarray,
                     contacts: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
        """Add the group's ``J A^-1 J^T`` to ``W`` ``(3B, 3B)`` and ``J qdot`` to ``u`` ``(3B,)``;
        ``contacts``: ``(body in group or -1, part node, global block)`` per contact."""
        add_delassus(W, u, chol, qdot, self.fixed_rows, self.fixed_blocks, self.frame_rot, self.basis, *contacts)

    def corrections(self, lam: np.ndarray, chol: np.ndarray,
                    contacts: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
        """``(L, m)`` modal velocity corrections for the impulses ``lam`` ``(3B,)``, mN s."""
        return corrections(lam, chol, self.fixed_rows, self.fixed_blocks, self.frame_rot, self.basis, *contacts)

    def floor_candidates(self, x: np.ndarray, qdot: np.ndarray, h: float, floor) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(nodes, gaps, vz)`` of the collision nodes that are floor contact candidates
        (:func:`softcrawl.reduction.kernels.floor_candidates`; ``floor``: a
        :class:`~softcrawl.fem.model.Floor`)."""
        return floor_candidates(x, self.offsets, self.collision, self.collision_bound, qdot, self._z_axes,
                                self.basis, h, floor.height, floor.contact_distance)

    @property
    def _z_axes(self) -> np.ndarray:
        """``(L, 3)`` each body's world z axis in its part frame (``R_b^T e_z``)."""
        return np.ascontiguousarray(self.rotations[:, 2, :])

    def velocity_z(self, qdot: np.ndarray, body: np.ndarray, node: np.ndarray) -> np.ndarray:
        """``(k,)`` world z velocities at ``(body in group, part node)`` points, mm/s."""
        return point_velocity(qdot, self._z_axes, self.basis, body, node)
