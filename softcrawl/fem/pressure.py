"""Pneumatic cavity pressure as a follower load.

Each cavity triangle ``t`` (oriented with its normal out of the air, into the wall) gets
the nodal load ``p * A_t * n_t / 3`` on each of its vertices, recomputed on the deformed
geometry every evaluation. For a closed cavity this equals ``p * dV/dx`` with
``V = sum_t x0 . (x1 x x2) / 6`` (physics.md, "Pneumatic actuation"; SOFA SoftRobots
``SurfacePressureConstraint``).
"""

from __future__ import annotations

import numpy as np


def area_normals(x: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """``(k, 3)`` area-weighted normals ``(x1 - x0) x (x2 - x0) / 2``, mm^2."""
    p = x[triangles]
    return 0.5 * np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def pressure_forces(x: np.ndarray, triangles: np.ndarray, pressure: float) -> np.ndarray:
    """Nodal follower forces of a uniform pressure on oriented triangles.

    Args:
        x: ``(n, 3)`` current node positions, mm.
        triangles: ``(k, 3)`` cavity triangles, normals pointing into the solid.
        pressure: gauge pressure, kPa.

    Returns:
        ``(n, 3)`` forces, mN (kPa * mm^2).
    """
    fn = (pressure / 3.0) * area_normals(x, triangles)
    out = np.zeros((len(x), 3))
    idx = triangles.ravel()
    for c in range(3):
        out[:, c] = np.bincount(idx, weights=np.repeat(fn[:, c], 3), minlength=len(x))
    return out


def enclosed_volume(x: np.ndarray, triangles: np.ndarray) -> float:
    """Volume enclosed by a closed, consistently oriented triangle surface, mm^3
    (divergence theorem; positive when normals point out of the enclosed region)."""
    p = x[triangles]
    return float(np.einsum("ij,ij->", p[:, 0], np.cross(p[:, 1], p[:, 2])) / 6.0)
