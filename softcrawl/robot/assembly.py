"""Assembling a crawler (disk + PneuNet legs in slots) into a full-order FEM model.

Placement follows physics.md ("Geometry"): a leg in the slot at angle θ is rotated +15°
about y (its outer tip dips down), translated by ``(52 cos15° + 50, 0, 52 sin15° - 4)``
and rotated by θ about z; the disk is lifted by ``2 · 52 sin15°``. The whole robot is
then shifted vertically so that its lowest node sits ``FLOOR_CLEARANCE`` above the floor
(``z = 0``); it settles onto the floor under gravity. Each leg is tied to the disk at the
4 ``"attachment"`` corners of its block by point-to-point constraints (each on the average
of the corner node and its one-ring: ``RobotConfig.attachment_patch``).

Bodies: index 0 is the disk, then one leg per occupied slot in slot order. Channels:
regulator ``k`` drives model channel ``k - 1``. The model always has
``N_REGULATORS = 3`` channels (``Model(channels=3)``), even if a design leaves a
regulator unused, so a ``Control`` always holds one pressure per regulator (see
:meth:`Robot.control`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softcrawl.design.space import N_REGULATORS, SLOT_ANGLES_DEG, Design, validate_design
from softcrawl.fem.body import Body, Cavity, Membrane
from softcrawl.fem.materials import DRAGONSKIN_30, PAPER, PRINTED_POLYMER
from softcrawl.fem.model import Attachment, Floor, Model, PointRef, embed_point
from softcrawl.fem.solver import ImplicitEulerSolver, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.geometry.disk import DiskParams, disk_mesh
from softcrawl.geometry.pneunet import PneuNetParams, pneunet_mesh

#: Leg tilt about y, degrees (outer tip down).
TILT_DEG = 15.0
#: Half length of the chambered block, mm: the leg's inner end face is at leg-local x = -52.
LEG_HALF_BLOCK = 52.0
#: Radial offset of the leg's block end from the robot axis, mm.
LEG_RADIAL_OFFSET = 50.0
#: Height of the base slab (the attachment corners' lower z), mm.
LEG_BASE_THICKNESS = 4.0
#: Gap between the robot's lowest node and the floor after placement, mm.
FLOOR_CLEARANCE = 0.01


@dataclass(frozen=True)
class RobotConfig:
    """Model settings of a crawler (defaults = physics.md reference, except the leg mesh size).

    Attributes:
        leg_mesh_size: maximum tet size of the PneuNet mesh, mm (reference 4; default 6: the
            crawl distance of the paper's best design and gait in 6 s was 0.63 / 3.57 / 3.39 cm
            at 8 / 6 / 4 mm, so 8 mm is not converged while 6 mm is within 5% of 4 mm).
        disk_mesh_size: maximum tet size of the disk mesh, mm.
        friction: Coulomb coefficient of the floor.
        dt: time step, s.
        mass_lumping: ``"uniform"`` (SOFA, reference) or ``"volume"``.
        leg_mass, disk_mass: kg.
        tilt_deg: leg tilt about y, degrees.
        rayleigh_mass, rayleigh_stiffness: Rayleigh damping coefficients (1/s, s).
        contact_distance: floor contact distance, mm.
        refactor_every: factorization reuse of the solver (1 = exact, refactorize every
            step; see :class:`softcrawl.fem.solver.SolverSettings`).
        attachment_patch: ``"ring"``: each of a leg's 4 attachment points ties the disk to
            the average of the corner node and its one-ring (the nodes sharing a tetrahedron
            with it); a single-node tie concentrates the leg's reaction in one element, which
            inverted at 4 mm meshes under full pressure. ``"node"``: the reference single-node tie.

    Raises:
        ValueError: for non-positive mesh sizes, masses or dt (friction, lumping and damping
            are checked by the FEM classes when the model is built).
    """

    leg_mesh_size: float = 6.0
    disk_mesh_size: float = 10.0
    friction: float = 1.2
    dt: float = 0.01
    mass_lumping: str = "uniform"
    leg_mass: float = 0.105
    disk_mass: float = 0.075
    tilt_deg: float = TILT_DEG
    rayleigh_mass: float = 0.1
    rayleigh_stiffness: float = 0.1
    contact_distance: float = 0.5
    refactor_every: int = 1
    attachment_patch: str = "ring"

    def __post_init__(self) -> None:
        if self.attachment_patch not in ("ring", "node"):
            raise ValueError(f"RobotConfig.attachment_patch must be 'ring' or 'node', got {self.attachment_patch!r}")
        if int(self.refactor_every) != self.refactor_every or self.refactor_every < 1:
            raise ValueError(f"RobotConfig.refactor_every must be a positive integer, got {self.refactor_every!r}")
        for name in ("leg_mesh_size", "disk_mesh_size", "dt", "leg_mass", "disk_mass"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"RobotConfig.{name} must be positive and finite, got {v!r}")


@dataclass(frozen=True)
class LegSlot:
    """One leg of a robot.

    Attributes:
        body: index of the leg's body in the model.
        slot: slot index 0..7.
        angle_deg: slot angle about +z from +x, degrees.
        regulator: pressure regulator 1..3 driving the leg.
        channel: model pressure channel (``regulator - 1``).
    """

    body: int
    slot: int
    angle_deg: float
    regulator: int
    channel: int


@dataclass(frozen=True, eq=False)
class Robot:
    """An assembled crawler: the FEM model plus what the episode runner needs to know.

    Attributes:
        model: the full-order model (disk = body 0, then legs; 3 pressure channels).
        design: the 8-slot design tuple.
        config: the settings it was built with.
        legs: one :class:`LegSlot` per leg, in slot order.
        reward_node: global node index (into ``State.x``) of the disk's top-centre node.
        disk_body: index of the disk body (0).
    """

    model: Model
    design: Design
    config: RobotConfig
    legs: tuple[LegSlot, ...]
    reward_node: int
    disk_body: int = 0

    @property
    def leg_bodies(self) -> tuple[int, ...]:
        """Body indices of the legs, in slot order."""
        return tuple(leg.body for leg in self.legs)

    @property
    def regulator_channels(self) -> dict[int, int]:
        """Regulator (1..3) -> model pressure channel (``regulator - 1``), all 3 regulators."""
        return {k: self.channel_of(k) for k in range(1, N_REGULATORS + 1)}

    @staticmethod
    def channel_of(regulator: int) -> int:
        """Model channel of regulator ``k`` (1..3): ``k - 1``. Raises ValueError otherwise."""
        if not 1 <= regulator <= N_REGULATORS:
            raise ValueError(f"regulator must be in 1..{N_REGULATORS}, got {regulator}")
        return regulator - 1

    def control(self, sim_kpa: np.ndarray) -> Control:
        """The solver input for per-regulator sim pressures.

        Args:
            sim_kpa: ``(3,)`` sim gauge pressures of regulators 1..3, kPa (after the
                real-to-sim calibration). Unused regulators have no effect.

        Returns:
            A ``Control`` with ``model.n_channels == 3`` pressures (channel = regulator - 1).

        Raises:
            ValueError: wrong shape, or a non-finite pressure.
        """
        p = np.asarray(sim_kpa, dtype=float)
        if p.shape != (N_REGULATORS,):
            raise ValueError(f"need {N_REGULATORS} regulator pressures, got shape {p.shape}")
        return Control(pressures=p.copy())

    def make_solver(self) -> ImplicitEulerSolver:
        """A fresh full-order solver for :attr:`model` with the config's time step."""
        return ImplicitEulerSolver(self.model, SolverSettings(dt=self.config.dt,
                                                              refactor_every=self.config.refactor_every))

    def reward_position(self, x: np.ndarray) -> np.ndarray:
        """``(3,)`` position (mm) of the disk's top centre given stacked positions ``x`` (N, 3)."""
        return np.asarray(x[self.reward_node], dtype=float).copy()


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def leg_transform(angle_deg: float, tilt_deg: float = TILT_DEG) -> tuple[np.ndarray, np.ndarray]:
    """Rigid placement ``p -> R p + t`` of a leg-local point into a slot (before the floor shift).

    Args:
        angle_deg: slot angle about +z, degrees.
        tilt_deg: tilt about +y, degrees (+15: the outer tip dips down).

    Returns:
        ``(R (3, 3), t (3,) mm)``: ``R = R_z(angle) R_y(tilt)``,
        ``t = R_z(angle) (52 cos(tilt) + 50, 0, 52 sin(tilt) - 4)``.
    """
    a = math.radians(tilt_deg)
    offset = np.array(
        [LEG_HALF_BLOCK * math.cos(a) + LEG_RADIAL_OFFSET, 0.0, LEG_HALF_BLOCK * math.sin(a) - LEG_BASE_THICKNESS]
    )
    rz = _rot_z(angle_deg)
    return rz @ _rot_y(tilt_deg), rz @ offset


def build_robot(design, config: RobotConfig = RobotConfig()) -> Robot:
    """Assemble the full-order model of a design.

    Args:
        design: 8 slot values in {0..3} (sequence or string such as ``"1,0,0,2,2,0,0,1"``).
        config: model settings.

    Returns:
        The :class:`Robot` (disk = body 0, legs in slot order, ``4 * n_legs`` attachments,
        3 channels; lowest node at ``z = FLOOR_CLEARANCE`` above the floor at ``z = 0``).

    Raises:
        InvalidDesignError: if the design is invalid.
        ValueError: for invalid settings; MeshError if meshing fails.
    """
    design = validate_design(design)
    leg_local = pneunet_mesh(PneuNetParams(mesh_size=config.leg_mesh_size))
    disk_local = disk_mesh(DiskParams(mesh_size=config.disk_mesh_size))
    lift = 2 * LEG_HALF_BLOCK * math.sin(math.radians(config.tilt_deg))

    slots = [(slot, reg) for slot, reg in enumerate(design) if reg]
    parts = [(disk_local, np.eye(3), np.array([0.0, 0.0, lift]))]
    parts += [(leg_local, *leg_transform(SLOT_ANGLES_DEG[slot], config.tilt_deg)) for slot, _ in slots]
    z_min = min(float((m.points @ R.T + t)[:, 2].min()) for m, R, t in parts)
    shift = np.array([0.0, 0.0, FLOOR_CLEARANCE - z_min])
    disk, *leg_meshes = [m.transformed(R, t + shift) for m, R, t in parts]

    disk_body = Body(disk, PRINTED_POLYMER, config.disk_mass, mass_lumping=config.mass_lumping, name="disk")
    bodies, legs, attachments = [disk_body], [], []
    for (slot, reg), mesh in zip(slots, leg_meshes):
        index = len(bodies)
        bodies.append(Body(
            mesh, DRAGONSKIN_30, config.leg_mass, mass_lumping=config.mass_lumping,
            membrane=Membrane(mesh.surfaces["paper"], PAPER, 1.0),
            cavities=(Cavity(mesh.surfaces["cavity"], channel=Robot.channel_of(reg)),),
            name=f"leg{slot}",
        ))
        legs.append(LegSlot(index, slot, SLOT_ANGLES_DEG[slot], reg, Robot.channel_of(reg)))
        for node in mesh.node_sets["attachment"]:
            patch = (np.unique(mesh.tets[np.any(mesh.tets == node, axis=1)])
                     if config.attachment_patch == "ring" else np.array([node]))
            weights = np.full(len(patch), 1.0 / len(patch))
            attachments.append(Attachment(
                PointRef(index, patch, weights),
                embed_point(0, disk_body, weights @ mesh.points[patch]),
            ))
    model = Model(
        tuple(bodies), tuple(attachments),
        floor=Floor(0.0, config.friction, config.contact_distance),
        rayleigh_mass=config.rayleigh_mass, rayleigh_stiffness=config.rayleigh_stiffness,
        channels=N_REGULATORS,
    )
    reward_node = int(model.node_offsets[0] + disk.node_sets["top_centre"][0])
    return Robot(model, design, config, tuple(legs), reward_node)
