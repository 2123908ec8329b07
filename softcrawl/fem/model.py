"""A full-order model: bodies, the constraints between them, the floor, and global settings.

All of it is static data; see :class:`softcrawl.fem.state.State` for what changes in time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from softcrawl.fem.body import Body
from softcrawl.fem.state import State


@dataclass(frozen=True)
class Floor:
    """A flat rigid floor ``z = height`` with Coulomb friction.

    Attributes:
        height: z of the floor plane, mm.
        friction: Coulomb coefficient mu (>= 0), one value (no static/kinetic split).
        contact_distance: a node closer than this (before or after the free motion) becomes
            a contact candidate, mm (physics.md: 0.5 mm).

    Raises:
        ValueError: negative or non-finite friction or contact distance.
    """

    height: float = 0.0
    friction: float = 1.2
    contact_distance: float = 0.5

    def __post_init__(self) -> None:
        if not (math.isfinite(self.friction) and self.friction >= 0):
            raise ValueError(f"friction coefficient must be >= 0, got {self.friction!r}")
        if not (math.isfinite(self.contact_distance) and self.contact_distance >= 0):
            raise ValueError(f"contact distance must be >= 0, got {self.contact_distance!r} mm")


@dataclass(frozen=True, eq=False)
class PointRef:
    """A material point of a body: a weighted combination of its nodes (barycentric mapping).

    Attributes:
        body: index of the body in the model.
        nodes: ``(k,)`` local node indices.
        weights: ``(k,)`` weights summing to 1.
    """

    body: int
    nodes: np.ndarray
    weights: np.ndarray


@dataclass(frozen=True, eq=False)
class Attachment:
    """A bilateral point-to-point equality constraint: ``x(a) = x(b)`` (3 rows)."""

    a: PointRef
    b: PointRef


def embed_point(body_index: int, body: Body, position: np.ndarray) -> PointRef:
    """Map a world point to barycentric weights in the body's closest tetrahedron.

    A point outside the mesh is extrapolated from the tetrahedron whose centroid is nearest
    (as SOFA's BarycentricMapping does).

    Args:
        body_index: index of ``body`` in the model.
        body: the body.
        position: ``(3,)`` world position in the rest configuration, mm.
    """
    pts, tets = body.mesh.points, body.mesh.tets
    p = np.asarray(position, float)
    node_d = np.linalg.norm(pts - p, axis=1)
    if node_d.min() < 1e-9:
        return PointRef(body_index, np.array([int(node_d.argmin())]), np.ones(1))
    X = pts[tets]
    Dm = (X[:, 1:] - X[:, :1]).transpose(0, 2, 1)
    lam = np.linalg.solve(Dm, (p - X[:, 0])[:, :, None])[:, :, 0]
    bary = np.concatenate([1 - lam.sum(1, keepdims=True), lam], axis=1)
    inside = np.flatnonzero(bary.min(1) >= -1e-9)
    e = inside[0] if len(inside) else int(np.linalg.norm(X.mean(1) - p, axis=1).argmin())
    return PointRef(body_index, tets[e].copy(), bary[e].copy())


@dataclass(frozen=True, eq=False)
class Model:
    """Static data of a full-order multi-body model.

    Attributes:
        bodies: the deformable bodies; their nodes are stacked in this order in the state.
        attachments: equality constraints between bodies.
        floor: the floor, or None.
        gravity: ``(3,)`` mm/s^2 (default ``(0, 0, -9800)``).
        rayleigh_mass: Rayleigh mass coefficient r_M, 1/s (physics.md: 0.1).
        rayleigh_stiffness: Rayleigh stiffness coefficient r_K, s (physics.md: 0.1).
        channels: number of pressure channels a ``Control`` must hold; None = one more than
            the highest channel a cavity uses (at least 1). A robot declares all its
            regulators even when a design leaves one unused.

    Raises:
        ValueError: negative damping, a non-finite gravity, an attachment naming a missing
            body, or fewer channels than the cavities use.
    """

    bodies: tuple[Body, ...]
    attachments: tuple[Attachment, ...] = ()
    floor: Floor | None = None
    gravity: tuple[float, float, float] = (0.0, 0.0, -9800.0)
    rayleigh_mass: float = 0.1
    rayleigh_stiffness: float = 0.1
    channels: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "bodies", tuple(self.bodies))
        object.__setattr__(self, "attachments", tuple(self.attachments))
        if not self.bodies:
            raise ValueError("a model needs at least one body")
        if not (self.rayleigh_mass >= 0 and self.rayleigh_stiffness >= 0):
            raise ValueError(
                f"Rayleigh coefficients must be >= 0, got r_M={self.rayleigh_mass}, r_K={self.rayleigh_stiffness}"
            )
        if not np.all(np.isfinite(self.gravity)) or len(self.gravity) != 3:
            raise ValueError(f"gravity must be 3 finite numbers, got {self.gravity!r}")
        self.n_channels  # validates the channel count
        for att in self.attachments:
            for ref in (att.a, att.b):
                if not 0 <= ref.body < len(self.bodies):
                    raise ValueError(f"attachment refers to body {ref.body}, model has {len(self.bodies)}")

    @cached_property
    def node_offsets(self) -> np.ndarray:
        """``(n_bodies + 1,)``: body ``i`` owns global nodes ``offsets[i]:offsets[i+1]``."""
        return np.concatenate([[0], np.cumsum([b.n_nodes for b in self.bodies])]).astype(np.int64)

    @property
    def n_nodes(self) -> int:
        return int(self.node_offsets[-1])

    @cached_property
    def n_channels(self) -> int:
        """Number of pressure channels of a ``Control`` (see ``channels``)."""
        used = 1 + max((c.channel for b in self.bodies for c in b.cavities), default=0)
        if self.channels is None:
            return used
        if self.channels < used:
            raise ValueError(f"model declares {self.channels} pressure channels but its cavities use {used}")
        return self.channels

    @property
    def total_mass(self) -> float:
        return float(sum(b.mass for b in self.bodies))

    def body_slice(self, i: int) -> slice:
        return slice(int(self.node_offsets[i]), int(self.node_offsets[i + 1]))

    def rest_state(self) -> State:
        """All bodies at rest in their mesh positions, zero velocity, t = 0."""
        x = np.concatenate([b.mesh.points for b in self.bodies])
        return State(x=x, v=np.zeros_like(x), t=0.0)

    def point_position(self, x: np.ndarray, ref: PointRef) -> np.ndarray:
        """``(3,)`` position of a material point given the stacked positions ``x`` (N, 3)."""
        return ref.weights @ x[self.body_slice(ref.body)][ref.nodes]
