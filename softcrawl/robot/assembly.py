"""Assembling a crawler (disk + PneuNet legs in slots) into an FEM model (full-order, or with
reduced parts when ``RobotConfig.model == "reduced"``).

Placement follows physics.md ("Geometry"): a leg in the slot at angle θ is rotated +15°
about y (its outer tip dips down), translated by ``(52 cos15° + 50, 0, 52 sin15° - 4)``
and rotated by θ about z; the disk is lifted by ``2 · 52 sin15°``. The whole robot is
then shifted vertically so that its lowest node sits ``FLOOR_CLEARANCE`` above the floor
(``z = 0``); it settles onto the floor under gravity. Each leg is tied to the disk at the
4 ``"attachment"`` corners of its block by point-to-point constraints (each on the average
of the corner node and its one-ring: ``RobotConfig.attachment_patch``).

Bodies: index 0 is the disk, then one leg per occupied slot in slot order. Channels:
regulator ``k`` drives model channel ``k - 1``. The model always has one channel per
regulator of the design space (3 in the paper's: ``Model(channels=3)``), even if a design
leaves a regulator unused, so a ``Control`` always holds one pressure per regulator (see
:meth:`Robot.control`). The slots, the parts' geometry and their materials come from the
design space (:class:`softcrawl.design.spacefile.DesignSpace`; default the paper's, whose
leg gives the 52 and 4 mm above).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace, Material
from softcrawl.fem.body import Body, Cavity, Membrane
from softcrawl.fem.materials import DRAGONSKIN_30, PAPER, PRINTED_POLYMER, LinearElastic
from softcrawl.fem.model import Attachment, Floor, Model, PointRef, embed_point
from softcrawl.fem.solver import CONTACT_MAX_ITERATIONS, RID_DTYPES, ImplicitEulerSolver, SolverSettings
from softcrawl.fem.state import Control
from softcrawl.geometry.disk import DiskParams, disk_mesh
from softcrawl.geometry.mesh import TetMesh, collision_nodes, spaced_nodes
from softcrawl.geometry.pneunet import PneuNetParams, pneunet_mesh
from softcrawl.reduction.floating import FloatingFrameBody
from softcrawl.reduction.model import ReducedBody, RobotReduction, reduce_body
from softcrawl.reduction.solver import ReducedSolver

#: Leg tilt about y, degrees (outer tip down).
TILT_DEG = 15.0
#: The paper's leg and disk (a design space's robots use their own parts' values):
#: half length of the chambered block, mm: the leg's inner end face is at leg-local x = -52;
LEG_HALF_BLOCK = 52.0
#: radial offset of the leg's block end from the robot axis, mm (the disk's bottom radius);
LEG_RADIAL_OFFSET = 50.0
#: height of the base slab (the attachment corners' lower z), mm.
LEG_BASE_THICKNESS = 4.0
#: Gap between the robot's lowest node and the floor after placement, mm.
FLOOR_CLEARANCE = 0.01
#: Cubic metres per cubic millimetre (density kg/m^3 times mesh volume mm^3 -> kg).
M3_PER_MM3 = 1e-9
#: The materials a space file may name (:data:`softcrawl.design.spacefile.KNOWN_MATERIALS`).
NAMED_MATERIALS = {"dragonskin30": DRAGONSKIN_30, "paper": PAPER, "printed_polymer": PRINTED_POLYMER}


MODELS = ("full", "reduced")
REDUCED_DISKS = ("floating", "corotational")
REDUCED_DISK_REFACTOR_EVERY = 5


@dataclass(frozen=True)
class RobotConfig:
    """Model settings of a crawler (defaults = physics.md reference, except the leg mesh size).

    Attributes:
        leg_mesh_size: maximum tet size of the PneuNet mesh, mm (reference 4; default 6: the
            crawl distance of the paper's best design and gait in 6 s was 0.63 / 3.57 / 3.39 cm
            at 8 / 6 / 4 mm, so 8 mm is not converged while 6 mm is within 5% of 4 mm).
        disk_mesh_size: maximum tet size of the disk mesh, mm (default 10: 337 nodes; a
            reduction with a disk part only accepts the size it was built for). 25 gives 127
            nodes, near the paper's coarse 86-node disk, a 1.3x faster reduced step and the
            same 20 s paper-best crawl (+11.69 cm full-order exact with either), but the exact
            full-order model with it diverged on one of the 8 reduction training scenes, which
            it passes at 10 mm: at full pressure, two elements under a 1 mm gap between teeth
            of a leg were squeezed from 4% of their volume to inverted in 0.12 s; without
            tooth-tooth self-contact neighbouring teeth may overlap, and the corotational
            linear material has no volumetric barrier.
        friction: Coulomb coefficient of the floor.
        dt: time step, s.
        mass_lumping: ``"uniform"`` (SOFA, reference) or ``"volume"``.
        leg_mass, disk_mass: kg.
        tilt_deg: leg tilt about y, degrees.
        rayleigh_mass, rayleigh_stiffness: Rayleigh damping coefficients (1/s, s).
        contact_distance: floor contact distance, mm.
        refactor_every: factorization reuse of the full-order corotational bodies (1 = exact,
            refactorize every step; see :class:`softcrawl.fem.solver.SolverSettings`). ``None``:
            1 for the full model (the exact reference); :data:`REDUCED_DISK_REFACTOR_EVERY` for
            a reduced model whose only full-order body is the corotational disk (its factorization and
            attachment compliance columns were 35% of the reduced step; between
            refactorizations its free motion is still solved to 1e-9 by preconditioned CG, its
            contact compliance lags). Paper-best design and gait, 20 s: +11.44 / +11.22 /
            +10.76 cm with the disk refactorized every 1 / 5 / 10 steps, full model +11.69 cm.
        model: ``"full"`` (full-order bodies) or ``"reduced"`` (legs, and the disk if the
            reduction has a disk part, reduced with POD + ECSW from ``reduction``; the
            reduction's meshes replace the ones ``leg_mesh_size`` and ``disk_mesh_size`` would
            give, and those sizes must be the ones it was built for).
        reduction: path of the reduction file for ``model="reduced"`` (None: the one
            shipped with softcrawl, :func:`softcrawl.reduction.default_reduction_path`: 6 mm
            legs, no disk part).
        reduced_disk: the disk of a reduced model whose reduction has no disk part:
            ``"floating"`` (default; all its nodes, linear elastic in one floating frame,
            :class:`softcrawl.reduction.floating.FloatingFrameBody`: one constant
            factorization) or ``"corotational"`` (the full-order corotational disk,
            refactorized every ``refactor_every`` steps: a 1.45x slower reduced step). With
            full-order legs, the floating disk's distance to the exact corotational model on
            the 4 validation scenes was 0.69 mm (mean over nodes and frames), below the full
            model's own floor (1.52 mm with factorizations reused for 5 steps); paper-best
            design and gait over 20 s: +11.31 cm against +11.69 cm.
        rid_dtype: precision of the reduced legs' RID element products: ``"float64"`` (the
            reference) or ``"float32"`` (1.5x faster RID terms; see
            :class:`softcrawl.fem.solver.SolverSettings`). Ignored by full-order bodies.
        contact_max_iterations: Gauss-Seidel sweep limit of the contact solve, per chunk
            (physics.md reference: 250; :class:`softcrawl.fem.solver.SolverSettings`).
        leg_collision_spacing: the legs' floor contact points, mm: ``0`` (the reference) makes
            every outer-surface node a candidate (1,179 per 6 mm leg); a positive spacing keeps
            a subset of them no two closer than it (:func:`softcrawl.geometry.mesh.spaced_nodes`,
            farthest-point sampling from the corners: 459 nodes at 4 mm, 158 at 6 mm), like the
            paper's simplified collision surface (physics.md). Fewer contacts per reduced leg
            make its contact problems smaller and better conditioned, but nodes between the
            points may sink a little. ``softcrawl reduce validate --dt 0.02 --rid-dtype float32
            --contact-max-iterations 100`` against the exact full-order model: 4 mm gives a mean
            node error of 0.978 mm and a baseline reward error of 4.8% (every node: 0.955 mm,
            0.3%), for a 1.23x cheaper landing and 1.10x cheaper episode steps; 5, 6, 8, 10 and
            12 mm fail the 1 mm target (1.27 to 2.02 mm). Not used by any preset
            (``CHANGELOG.md``).
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
    refactor_every: int | None = None
    rid_dtype: str = "float64"
    contact_max_iterations: int = CONTACT_MAX_ITERATIONS
    leg_collision_spacing: float = 0.0
    attachment_patch: str = "ring"
    model: str = "full"
    reduction: str | None = None
    reduced_disk: str = "floating"

    @classmethod
    def for_space(cls, space: DesignSpace, **settings) -> RobotConfig:
        """The settings of a space's robots: its parts' default mesh sizes and masses
        (``leg_mesh_size``, ``disk_mesh_size``, ``leg_mass``, ``disk_mass``), then ``settings``
        (any field, those four included). ``for_space(DEFAULT_SPACE) == RobotConfig()``.

        A part given by its material's density weighs ``rho * V`` with ``V`` the volume of its
        mesh at the config's mesh size (meshed here; exact for the box-built PneuNet, the
        faceted frustum for the disk), so that the FEM body has the material's density.

        Raises:
            ValueError: as the constructor; TypeError for an unknown setting; MeshError.
        """
        config = cls(**{"leg_mesh_size": space.leg.mesh_size, "disk_mesh_size": space.disk.mesh_size, **settings})
        meshes = {"leg_mass": (space.leg, lambda: pneunet_mesh(pneunet_params(space, config.leg_mesh_size))),
                  "disk_mass": (space.disk, lambda: disk_mesh(disk_params(space, config.disk_mesh_size)))}
        masses = {key: part.mass if part.mass is not None else
                  part.material.density_kg_per_m3 * mesh().volume() * M3_PER_MM3
                  for key, (part, mesh) in meshes.items() if key not in settings}
        return dataclasses.replace(config, **masses)

    def __post_init__(self) -> None:
        if self.model not in MODELS:
            raise ValueError(f"RobotConfig.model must be one of {MODELS}, got {self.model!r}")
        if self.reduced_disk not in REDUCED_DISKS:
            raise ValueError(f"RobotConfig.reduced_disk must be one of {REDUCED_DISKS}, got {self.reduced_disk!r}")
        if self.attachment_patch not in ("ring", "node"):
            raise ValueError(f"RobotConfig.attachment_patch must be 'ring' or 'node', got {self.attachment_patch!r}")
        if self.rid_dtype not in RID_DTYPES:
            raise ValueError(f"RobotConfig.rid_dtype must be one of {RID_DTYPES}, got {self.rid_dtype!r}")
        n = self.contact_max_iterations
        if isinstance(n, bool) or int(n) != n or n < 1:
            raise ValueError(f"RobotConfig.contact_max_iterations must be a positive integer, "
                             f"got {self.contact_max_iterations!r}")
        if not (math.isfinite(self.leg_collision_spacing) and self.leg_collision_spacing >= 0):
            raise ValueError(f"RobotConfig.leg_collision_spacing must be >= 0 mm, got {self.leg_collision_spacing!r}")
        if self.refactor_every is not None and (int(self.refactor_every) != self.refactor_every
                                                or self.refactor_every < 1):
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
        slot: slot index (0..7 in the paper's space).
        angle_deg: slot angle about +z from +x, degrees.
        regulator: pressure regulator driving the leg (1..R of the space; ``channel + 1``).
        channel: model pressure channel (``regulator - 1``).
        rotation: ``(3, 3)`` rotation placing the leg-local frame in the world
            (``R_z(angle) R_y(tilt)``, see :func:`leg_transform`).
    """

    body: int
    slot: int
    angle_deg: float
    regulator: int
    channel: int
    rotation: np.ndarray = field(default_factory=lambda: np.eye(3), compare=False)


@dataclass(frozen=True, eq=False)
class Robot:
    """An assembled crawler: the FEM model plus what the episode runner needs to know.

    Attributes:
        model: the full-order model (disk = body 0, then legs; one pressure channel per
            regulator of the space).
        design: the design tuple (one value per slot of the space).
        config: the settings it was built with.
        legs: one :class:`LegSlot` per leg, in slot order.
        reward_node: global node index (into ``State.x``) of the disk's top-centre node.
        disk_body: index of the disk body (0).
        reduced: body index -> :class:`ReducedBody` (POD + ECSW) or
            :class:`FloatingFrameBody` for reduced bodies (empty: full-order).
        space: the design space it belongs to (slots, regulators, parts).
    """

    model: Model
    design: Design
    config: RobotConfig
    legs: tuple[LegSlot, ...]
    reward_node: int
    disk_body: int = 0
    reduced: Mapping[int, ReducedBody | FloatingFrameBody] = field(default_factory=dict)
    space: DesignSpace = DEFAULT_SPACE

    @property
    def leg_bodies(self) -> tuple[int, ...]:
        """Body indices of the legs, in slot order."""
        return tuple(leg.body for leg in self.legs)

    @property
    def regulator_channels(self) -> dict[int, int]:
        """Regulator (1..R) -> model pressure channel (``regulator - 1``), every regulator of the space."""
        return {k: k - 1 for k in range(1, self.space.n_regulators + 1)}

    def channel_of(self, regulator: int) -> int:
        """Model channel of regulator ``k`` (1..R of the robot's space): ``k - 1``.

        Raises:
            ValueError: ``k`` outside 1..R.
        """
        n = self.space.n_regulators
        if not 1 <= regulator <= n:
            raise ValueError(f"regulator must be in 1..{n} (the regulators of the space {self.space.name!r}), "
                             f"got {regulator}")
        return regulator - 1

    def control(self, sim_kpa: np.ndarray) -> Control:
        """The solver input for per-regulator sim pressures.

        Args:
            sim_kpa: ``(n_channels,)`` sim gauge pressures, kPa (after the real-to-sim
                calibration): regulators 1..R of the space. Unused regulators have no effect.

        Returns:
            A ``Control`` with ``model.n_channels`` pressures (channel = regulator - 1).

        Raises:
            ValueError: wrong shape, or a non-finite pressure.
        """
        p = np.asarray(sim_kpa, dtype=float)
        if p.shape != (self.model.n_channels,):
            raise ValueError(f"need {self.model.n_channels} regulator pressures, got shape {p.shape}")
        return Control(pressures=p.copy())

    def make_solver(self) -> ImplicitEulerSolver:
        """A fresh solver for :attr:`model` with the config's time step (reduced if
        :attr:`reduced` is not empty)."""
        c = self.config
        corotational_disk = self.reduced and self.disk_body not in self.reduced
        reuse = c.refactor_every or (REDUCED_DISK_REFACTOR_EVERY if corotational_disk else 1)
        settings = SolverSettings(dt=c.dt, refactor_every=reuse, rid_dtype=c.rid_dtype,
                                  contact_max_iterations=int(c.contact_max_iterations))
        if self.reduced:
            return ReducedSolver(self.model, dict(self.reduced), settings)
        return ImplicitEulerSolver(self.model, settings)

    def reward_position(self, x: np.ndarray) -> np.ndarray:
        """``(3,)`` position (mm) of the disk's top centre given stacked positions ``x`` (N, 3)."""
        return np.asarray(x[self.reward_node], dtype=float).copy()


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def leg_transform(angle_deg: float, tilt_deg: float = TILT_DEG, half_block: float = LEG_HALF_BLOCK,
                  base_thickness: float = LEG_BASE_THICKNESS,
                  radial_offset: float = LEG_RADIAL_OFFSET) -> tuple[np.ndarray, np.ndarray]:
    """Rigid placement ``p -> R p + t`` of a leg-local point into a slot (before the floor shift).

    Args:
        angle_deg: slot angle about +z, degrees.
        tilt_deg: tilt about +y, degrees (+15: the outer tip dips down).
        half_block: half the PneuNet's chambered-block length ``h``, mm (52 for the paper's leg).
        base_thickness: the PneuNet's base slab thickness ``b``, mm (4 for the paper's leg).
        radial_offset: the disk's bottom radius ``r``, mm (50 for the paper's disk).

    Returns:
        ``(R (3, 3), t (3,) mm)``: ``R = R_z(angle) R_y(tilt)``,
        ``t = R_z(angle) (h cos(tilt) + r, 0, h sin(tilt) - b)`` (physics.md, "Geometry").
    """
    a = math.radians(tilt_deg)
    offset = np.array([half_block * math.cos(a) + radial_offset, 0.0, half_block * math.sin(a) - base_thickness])
    rz = _rot_z(angle_deg)
    return rz @ _rot_y(tilt_deg), rz @ offset


def build_robot(design, config: RobotConfig = RobotConfig(), leg_mesh: TetMesh | None = None,
                disk_mesh_local: TetMesh | None = None, space: DesignSpace = DEFAULT_SPACE) -> Robot:
    """Assemble the model of a design (reduced if ``config.model == "reduced"``).

    Args:
        design: one value per slot of ``space``, 0 or a regulator (paper's space: 8 values in
            {0..3}; a sequence or a string such as ``"1,0,0,2,2,0,0,1"``).
        config: model settings (for a space other than the paper's, build it with
            :meth:`RobotConfig.for_space` to get the space's masses and mesh sizes).
        leg_mesh: the PneuNet mesh in leg-local coordinates (default: meshed by gmsh at
            ``config.leg_mesh_size``; a reduced model always uses its reduction's mesh).
        disk_mesh_local: the unplaced disk mesh (default: gmsh at ``config.disk_mesh_size``,
            or the reduction's disk mesh).
        space: the design space: slots, regulators, the disk's and the legs' geometry and materials.

    Returns:
        The :class:`Robot` (disk = body 0, legs in slot order, ``4 * n_legs`` attachments,
        one channel per regulator of the space; lowest node at ``z = FLOOR_CLEARANCE`` above
        the floor at ``z = 0``).

    Raises:
        InvalidDesignError: if the design is invalid.
        ValueError: for invalid settings; MeshError if meshing fails.
    """
    design = space.validate_design(design)
    legs = [(slot, reg - 1) for slot, reg in enumerate(design) if reg]
    return assemble_robot(legs, config, space.n_regulators, design, leg_mesh, disk_mesh_local, space)


def reduce_robot(robot: Robot, reduction: RobotReduction) -> Robot:
    """The reductor: the same robot with every leg replaced by the leg reduction rotated to its
    slot's pose (reduction.md, "Design-reconfigurable reduction") and the disk replaced by
    the reduction's disk part if it has one, else by a :class:`FloatingFrameBody` if
    ``robot.config.reduced_disk == "floating"``.

    Raises:
        ValueError: the robot's leg or disk mesh is not the reduction's.
    """
    bodies = robot.model.bodies
    reduced = {leg.body: reduce_body(bodies[leg.body], reduction.leg, leg.rotation) for leg in robot.legs}
    if reduction.disk is not None:
        reduced[robot.disk_body] = reduce_body(bodies[robot.disk_body], reduction.disk, np.eye(3))
    elif robot.config.reduced_disk == "floating":
        reduced[robot.disk_body] = FloatingFrameBody(bodies[robot.disk_body])
    return dataclasses.replace(robot, reduced=reduced, config=dataclasses.replace(robot.config, model="reduced"))


def assemble_robot(legs: Sequence[tuple[int, int]], config: RobotConfig = RobotConfig(), n_channels: int | None = None,
                   design: Design | None = None, leg_mesh: TetMesh | None = None,
                   disk_mesh_local: TetMesh | None = None, space: DesignSpace = DEFAULT_SPACE) -> Robot:
    """Assemble a disk with legs in any slots on any pressure channels (no design-space rules).

    Used by :func:`build_robot` and, for training and validating reductions, for robots
    outside the design space (one or two legs, one channel per leg).

    Args:
        legs: ``(slot, channel)`` per leg, slots distinct slots of ``space``.
        config: model settings.
        n_channels: pressure channels of the model (default: one more than the highest used).
        design: the design tuple recorded in the robot (default: slot -> channel + 1).
        leg_mesh: the leg-local PneuNet mesh (default: gmsh at ``config.leg_mesh_size``).
        disk_mesh_local: the unplaced disk mesh (default: gmsh at ``config.disk_mesh_size``).
            A reduced model always uses its reduction's meshes.
        space: slot angles, the parts' geometry (mesh sizes from ``config``) and materials,
            and the reduction a reduced model uses when ``config.reduction`` is None.

    Raises:
        ValueError: a slot outside the space's or repeated, a negative channel, no legs; a
            reduced model of a space that names no reduction, or whose reduction's leg is
            not the space's PneuNet.
    """
    reduction = None
    if config.model == "reduced":
        reduction = _space_reduction(space, config)
        leg_mesh = reduction.leg.mesh
        if reduction.disk is not None:
            disk_mesh_local = reduction.disk.mesh
    legs = sorted((int(s), int(c)) for s, c in legs)
    slots_used = [s for s, _ in legs]
    if not legs or len(set(slots_used)) != len(legs) or not all(0 <= s < space.n_slots for s in slots_used):
        raise ValueError(f"legs need distinct slots in 0..{space.n_slots - 1}, got {slots_used}")
    if min(c for _, c in legs) < 0:
        raise ValueError(f"pressure channels must be >= 0, got {[c for _, c in legs]}")
    if design is None:
        design = tuple(dict(legs).get(s, -1) + 1 for s in range(space.n_slots))
    leg_params = pneunet_params(space, config.leg_mesh_size)
    leg_local = leg_mesh if leg_mesh is not None else pneunet_mesh(leg_params)
    disk_shape = disk_params(space, config.disk_mesh_size)
    disk_local = disk_mesh_local if disk_mesh_local is not None else disk_mesh(disk_shape)
    half_block = leg_params.block_length / 2
    lift = 2 * half_block * math.sin(math.radians(config.tilt_deg))
    angles = space.slot_angles_deg

    parts = [(disk_local, np.eye(3), np.array([0.0, 0.0, lift]))]
    parts += [(leg_local, *leg_transform(angles[slot], config.tilt_deg, half_block, leg_params.base_thickness,
                                         disk_shape.bottom_radius)) for slot, _ in legs]
    z_min = min(float((m.points @ R.T + t)[:, 2].min()) for m, R, t in parts)
    shift = np.array([0.0, 0.0, FLOOR_CLEARANCE - z_min])
    disk, *leg_meshes = [m.transformed(R, t + shift) for m, R, t in parts]

    disk_body = Body(disk, material(space.disk.material), config.disk_mass, mass_lumping=config.mass_lumping,
                     name="disk")
    leg_collision = None  # the mesh's own collision nodes
    if config.leg_collision_spacing:  # the same local nodes in every leg (legs share one reduced part)
        leg_collision = spaced_nodes(leg_local.points, collision_nodes(leg_local), config.leg_collision_spacing)
    bodies, leg_slots, attachments = [disk_body], [], []
    for (slot, channel), mesh, (_, R, _) in zip(legs, leg_meshes, parts[1:]):
        index = len(bodies)
        bodies.append(Body(
            mesh, material(space.leg.material), config.leg_mass, mass_lumping=config.mass_lumping,
            membrane=Membrane(mesh.surfaces["paper"], material(space.paper_material), space.paper_thickness),
            cavities=(Cavity(mesh.surfaces["cavity"], channel=channel),),
            collision_nodes=leg_collision, name=f"leg{slot}",
        ))
        leg_slots.append(LegSlot(index, slot, angles[slot], channel + 1, channel, R))
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
        channels=n_channels,
    )
    reward_node = int(model.node_offsets[0] + disk.node_sets["top_centre"][0])
    robot = Robot(model, tuple(design), config, tuple(leg_slots), reward_node, space=space)
    return reduce_robot(robot, reduction) if reduction is not None else robot


def material(m: Material) -> LinearElastic:
    """The FEM material of a space file's material: the named constant of
    :mod:`softcrawl.fem.materials` (:data:`NAMED_MATERIALS`), or one built from its E (kPa) and nu."""
    return NAMED_MATERIALS[m.name] if m.name else LinearElastic(m.youngs_modulus_kpa, m.poisson_ratio)


def pneunet_params(space: DesignSpace, mesh_size: float) -> PneuNetParams:
    """The space's PneuNet dimensions with tet size ``mesh_size`` (mm).

    Raises:
        ValueError: the dimensions do not fit together (:class:`PneuNetParams`).
    """
    return PneuNetParams(**dict(space.leg.params), mesh_size=mesh_size)


def disk_params(space: DesignSpace, mesh_size: float) -> DiskParams:
    """The space's disk dimensions with tet size ``mesh_size`` (mm)."""
    return DiskParams(**dict(space.disk.params), mesh_size=mesh_size)


def _space_reduction(space: DesignSpace, config: RobotConfig) -> RobotReduction:
    """The reduction of a reduced model: ``config.reduction``, else the space's.

    Raises:
        ValueError: the space names none, or the file does not match ``config``, was built for
            another part than the space's (dimensions, mesh size, materials, paper layer), or,
            being the space's own, has another SHA-256 than its ``reduction_sha256``
            (:func:`softcrawl.reduction.artifact.load_reduction`).
    """
    from softcrawl.reduction.artifact import load_reduction

    path = config.reduction or space.reduction
    if path is None:
        raise ValueError(f"the design space {space.name!r} ({space.source or 'no file'}) names no reduction "
                         f"([actuator] reduction) and the config none: use the full-order model")
    reduction, _ = load_reduction(path, expect=dataclasses.asdict(config),
                                  part=space.part_record(config.leg_mesh_size, config.disk_mesh_size),
                                  sha256=space.reduction_sha256 if str(path) == space.reduction else None)
    return reduction
