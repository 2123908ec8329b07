"""The PneuNet bending actuator (one leg), built with OpenCASCADE and meshed by gmsh.

Leg-local frame: x along the leg, y across, z up; ``z = 0`` is the bottom (paper,
strain-limiting) face. Units are mm. The body is a base slab, a chambered block centred
on it, and a row of teeth on the block (a wide tooth at each end, ``n_chambers`` narrow
teeth between them, separated by gaps). Each narrow tooth holds one chamber; an air
channel along the bottom of the block connects the chambers into one closed cavity.

With the default (reference) dimensions: base 115 x 32 x 4, block 104 x 20 x 9, end teeth
11 x 20 x 7, nine teeth 8 x 20 x 7 with 1 mm gaps, chambers 2 x 14 x 13, channel
81 x 2 x 2; solid volume 43,072 mm^3, cavity volume 3,528 mm^3.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from functools import partial

import gmsh
import numpy as np

from softcrawl.geometry.io import cached_mesh
from softcrawl.geometry.mesh import MeshError, TetMesh, boundary_triangles
from softcrawl.geometry.primitives import (
    boundary_nodes,
    check_mesh_cells,
    check_part_fields,
    geom_tol,
    nodes_at,
    nodes_on_plane,
    occ_tet_mesh,
)


#: Most chambers of a PneuNet (the paper's has 9).
MAX_CHAMBERS = 100


@dataclass(frozen=True)
class PneuNetParams:
    """PneuNet dimensions, mm. "Length" is along x, "width" across (y), "height"/"thickness" in z.

    The chambers have uniform walls: ``wall_thickness`` to the tooth faces in x and y
    and to the tooth top (the roof); their size follows (see :attr:`chamber_size`).

    Attributes:
        n_chambers: number of chambers (= narrow teeth).
        base_length, base_width, base_thickness: the base slab, centred on x = y = 0.
        block_width, block_height: the lower, unslotted part of the chambered block on the
            base; its length follows from the teeth (see :attr:`block_length`).
        tooth_width: x extent of each narrow (chamber) tooth.
        end_tooth_width: x extent of each of the two solid end teeth.
        tooth_gap: x gap between neighbouring teeth (also between end and narrow teeth).
        tooth_height: height of the teeth above the block.
        wall_thickness: chamber wall and roof thickness.
        channel_width, channel_height: cross-section of the air channel on the base; it
            runs over ``n_chambers`` tooth pitches, centred (see :attr:`channel_length`).
        mesh_size: maximum tetrahedron size, mm.

    Raises:
        TypeError: on construction, if ``n_chambers`` is not an integer.
        ValueError: on construction, one line: ``n_chambers`` outside ``1..``:data:`MAX_CHAMBERS`,
            a length outside :data:`~softcrawl.geometry.primitives.LENGTH_BOUNDS_MM`, a mesh
            size outside :data:`~softcrawl.geometry.primitives.MESH_SIZE_BOUNDS_MM` or too fine
            for the leg (:func:`~softcrawl.geometry.primitives.check_mesh_cells`), or dimensions
            that do not fit (chambers wider than their teeth, a channel that does not fit in the
            block, ...).
    """

    n_chambers: int = 9
    base_length: float = 115.0
    base_width: float = 32.0
    base_thickness: float = 4.0
    block_width: float = 20.0
    block_height: float = 9.0
    tooth_width: float = 8.0
    end_tooth_width: float = 11.0
    tooth_gap: float = 1.0
    tooth_height: float = 7.0
    wall_thickness: float = 3.0
    channel_width: float = 2.0
    channel_height: float = 2.0
    mesh_size: float = 4.0

    def __post_init__(self) -> None:
        check_part_fields(self, {"n_chambers": (1, MAX_CHAMBERS)})
        checks = {
            "chambers must have positive size (wall_thickness too large)": min(self.chamber_size) > 0,
            "base must be at least as long and wide as the block": self.base_length >= self.block_length
            and self.base_width >= self.block_width,
            "channel must be narrower and lower than the chambers": self.channel_width < self.chamber_size[1]
            and self.channel_height < self.chamber_size[2],
            "channel must be lower than the block": self.channel_height < self.block_height,
        }
        for message, ok in checks.items():
            if not ok:
                raise ValueError(f"{message}: {self}")
        height = self.base_thickness + self.block_height + self.tooth_height
        check_mesh_cells((self.base_length, self.base_width, height), self.mesh_size)  # the base is the widest

    @property
    def pitch(self) -> float:
        """Tooth pitch along x, mm."""
        return self.tooth_width + self.tooth_gap

    @property
    def block_length(self) -> float:
        """x extent of the chambered block (end teeth, narrow teeth and all gaps), mm."""
        n = self.n_chambers
        return 2 * self.end_tooth_width + n * self.tooth_width + (n + 1) * self.tooth_gap

    @property
    def chamber_size(self) -> tuple[float, float, float]:
        """``(x, y, z)`` size of each chamber, mm; z measured from the base top."""
        w = self.wall_thickness
        return (self.tooth_width - 2 * w, self.block_width - 2 * w, self.block_height + self.tooth_height - w)

    @property
    def channel_length(self) -> float:
        """x extent of the air channel, mm."""
        return self.n_chambers * self.pitch


Box = tuple[np.ndarray, np.ndarray]  # (lo, hi) corners, mm


def _boxes(p: PneuNetParams) -> tuple[list[Box], list[Box]]:
    """``(solid, cavity)`` lists of axis-aligned boxes ``(lo, hi)``; body = union(solid) - union(cavity)."""
    xb, w = p.block_length / 2, p.block_width / 2
    z0 = p.base_thickness
    z1 = z0 + p.block_height
    z2 = z1 + p.tooth_height
    cx, cy, cz = p.chamber_size

    def box(lo, hi):
        return np.array(lo, float), np.array(hi, float)

    solid = [
        box((-p.base_length / 2, -p.base_width / 2, 0), (p.base_length / 2, p.base_width / 2, z0)),
        box((-xb, -w, z0), (xb, w, z1)),
        box((-xb, -w, z1), (-xb + p.end_tooth_width, w, z2)),
        box((xb - p.end_tooth_width, -w, z1), (xb, w, z2)),
    ]
    lc, wc = p.channel_length / 2, p.channel_width / 2
    cavity = [box((-lc, -wc, z0), (lc, wc, z0 + p.channel_height))]
    for k in range(p.n_chambers):
        x0 = -xb + p.end_tooth_width + p.tooth_gap + k * p.pitch
        solid.append(box((x0, -w, z1), (x0 + p.tooth_width, w, z2)))
        xc = x0 + p.tooth_width / 2
        cavity.append(box((xc - cx / 2, -cy / 2, z0), (xc + cx / 2, cy / 2, z0 + cz)))
    return solid, cavity


def _build_occ(p: PneuNetParams) -> None:
    """Add the PneuNet body to the current gmsh model as one OCC volume, synchronised."""
    occ = gmsh.model.occ
    solid, cavity = ([(3, occ.addBox(*lo, *(hi - lo))) for lo, hi in boxes] for boxes in _boxes(p))
    body, _ = occ.fuse(solid[:1], solid[1:])
    body, _ = occ.cut(body, cavity)
    occ.synchronize()
    if len(body) != 1:
        raise MeshError(f"PneuNet body is not a single solid ({len(body)} volumes): {p}")


def _build_mesh(p: PneuNetParams) -> TetMesh:
    points, tets = occ_tet_mesh("pneunet", partial(_build_occ, p), p.mesh_size)
    tol = geom_tol(points)
    tris = boundary_triangles(tets)
    centroids = points[tris].mean(axis=1)
    in_cavity = np.zeros(len(tris), dtype=bool)
    for lo, hi in _boxes(p)[1]:
        in_cavity |= np.all((centroids >= lo - tol) & (centroids <= hi + tol), axis=1)
    outer = tris[~in_cavity]
    xb, w = p.block_length / 2, p.block_width / 2
    z_low, z_top = p.base_thickness, p.base_thickness + p.block_height + p.tooth_height
    corners = [(-xb, -w, z_low), (-xb, w, z_low), (-xb, -w, z_top), (-xb, w, z_top)]
    return TetMesh(
        points,
        tets,
        surfaces={
            "cavity": tris[in_cavity][:, [0, 2, 1]],  # flip: out of the air, into the solid
            "paper": outer[np.all(np.abs(points[outer, 2]) <= tol, axis=1)],
            "boundary": outer,
        },
        node_sets={
            "collision": boundary_nodes(outer),
            "attachment": nodes_at(points, corners),
            "tip": nodes_on_plane(points, 0, p.base_length / 2),
        },
        params=asdict(p),
    )


def pneunet_mesh(params: PneuNetParams = PneuNetParams(), cache: bool = True) -> TetMesh:
    """Tetrahedral mesh of a PneuNet leg in its leg-local frame (see module docstring).

    Args:
        params: dimensions and mesh size, mm.
        cache: reuse / store the mesh in the on-disk cache (:func:`softcrawl.geometry.io.cached_mesh`).

    Returns:
        A :class:`TetMesh` (points mm) with surfaces ``"cavity"`` (channel and chambers,
        normals into the solid, so the enclosed volume is positive), ``"paper"`` (the
        ``z = 0`` face, normals -z) and ``"boundary"`` (outer surface without the cavity,
        outward); node sets ``"collision"`` (outer-surface nodes), ``"attachment"`` (the 4
        corners of the block's inner end face ``x = -block_length/2``, in the order
        ``(-y, base top), (+y, base top), (-y, tooth top), (+y, tooth top)``) and ``"tip"``
        (nodes on the outer end face ``x = +base_length/2``); ``params`` = ``asdict(params)``.

    Raises:
        MeshError: if the geometry or the mesh is malformed (e.g. the body falls apart).
    """
    build = partial(_build_mesh, params)
    return cached_mesh("pneunet", asdict(params), build) if cache else build()
