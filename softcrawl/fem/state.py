"""Time-varying simulation state and control inputs (kept apart from static model data)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True, eq=False)
class State:
    """The state of all bodies of a model at one time.

    Attributes:
        x: ``(N, 3)`` node positions of all bodies stacked (see ``Model.node_offsets``), mm.
        v: ``(N, 3)`` node velocities, mm/s.
        t: time, s.
        contact_nodes: ``(k,)`` sorted global node indices of last step's contacts (solver warm start).
        contact_impulses: ``(k, 3)`` their impulses (normal, tangent1, tangent2), mN s.
        modal_velocities: the modal velocities ``qdot`` of the reduced bodies (their node
            velocities are ``Phi qdot``), one ``(L, m)`` array per modal group of the
            :class:`~softcrawl.reduction.solver.ReducedSolver` that produced the state (``L``
            bodies, ``m`` modes, mm/s: the basis is orthonormal), or None: a reduced solver then
            projects them from ``v`` (``qdot = Phi^T v``), which equals them to round-off.
            Full-order states have none. A state whose ``v`` is replaced must drop them
            (``dataclasses.replace(state, v=..., modal_velocities=None)``).
    """

    x: np.ndarray
    v: np.ndarray
    t: float = 0.0
    contact_nodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    contact_impulses: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    modal_velocities: tuple[np.ndarray, ...] | None = None

    def is_finite(self) -> bool:
        return bool(np.all(np.isfinite(self.x)) and np.all(np.isfinite(self.v)))


@dataclass(frozen=True, eq=False)
class Control:
    """Control inputs held over one step.

    Attributes:
        pressures: ``(n_channels,)`` simulated cavity gauge pressures, kPa (finite).
        forces: optional ``(N, 3)`` prescribed nodal forces on the stacked nodes, mN
            (probes and verification loads).

    Raises:
        ValueError: if a pressure or force is NaN or infinite.
    """

    pressures: np.ndarray = field(default_factory=lambda: np.zeros(1))
    forces: np.ndarray | None = None

    def __post_init__(self) -> None:
        p = np.atleast_1d(np.asarray(self.pressures, dtype=np.float64))
        if p.ndim != 1:
            raise ValueError(f"pressures must be a 1-D array, got shape {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ValueError(f"pressures must be finite, got {p.tolist()} kPa")
        object.__setattr__(self, "pressures", p)
        if self.forces is not None:
            f = np.asarray(self.forces, dtype=np.float64)
            if f.ndim != 2 or f.shape[1] != 3 or not np.all(np.isfinite(f)):
                raise ValueError("forces must be a finite (N, 3) array of nodal forces in mN")
            object.__setattr__(self, "forces", f)
