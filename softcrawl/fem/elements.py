"""Rest-state element data: linear tetrahedra and constant-strain membrane triangles.

Everything here is computed once from the rest mesh (vectorised numpy) and then used by
the corotational kernels in :mod:`softcrawl.fem.kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from softcrawl.fem.kernels import ROTATION_METHODS, rest_frames
from softcrawl.fem.materials import LinearElastic


@dataclass(frozen=True, eq=False)
class ElementSet:
    """Rest data of one family of corotational elements on one body.

    Attributes:
        conn: ``(m, k)`` node indices (k = 4 tetrahedra, 3 membrane triangles).
        rest: ``(m, k, 3)`` rest node positions, mm.
        stiffness: ``(m, 3k, 3k)`` rest element stiffness in the rest world frame, mN/mm.
        frames: ``(m, 3, 3)`` rest frames (``"large"``) or ``D_m^-1`` (``"polar"``).
        method: kernel rotation method code (see ``ROTATION_METHODS``).
        measure: ``(m,)`` element volumes (mm^3) or areas (mm^2).
    """

    conn: np.ndarray
    rest: np.ndarray
    stiffness: np.ndarray
    frames: np.ndarray
    method: int
    measure: np.ndarray

    @property
    def n_elements(self) -> int:
        return len(self.conn)


def _dof_conn(conn: np.ndarray) -> np.ndarray:
    """``(m, 3k)`` degree-of-freedom indices (3 per node, xyz interleaved)."""
    return (3 * conn[:, :, None] + np.arange(3)).reshape(len(conn), -1)


def tetrahedra(points: np.ndarray, tets: np.ndarray, material: LinearElastic, method: str = "large") -> ElementSet:
    """Linear (constant-strain) tetrahedra: ``K_e = V B^T D B``.

    Source: Zienkiewicz & Taylor, *The Finite Element Method*, vol. 1, sec. 6.3.

    Args:
        points: ``(n, 3)`` rest positions, mm.
        tets: ``(m, 4)`` positively oriented tetrahedra.
        material: the linear elastic law.
        method: ``"large"`` (SOFA's frame) or ``"polar"``.

    Raises:
        ValueError: unknown method, or a degenerate/inverted tetrahedron.
    """
    if method not in ROTATION_METHODS:
        raise ValueError(f"unknown rotation method {method!r}; choose from {sorted(ROTATION_METHODS)}")
    X = points[tets]  # (m, 4, 3)
    Dm = (X[:, 1:] - X[:, :1]).transpose(0, 2, 1)  # columns are edges
    vol = np.linalg.det(Dm) / 6.0
    if np.any(vol <= 0):
        raise ValueError(f"{int(np.sum(vol <= 0))} inverted or degenerate tetrahedra in the rest mesh")
    Dm_inv = np.linalg.inv(Dm)
    grads = np.concatenate([-Dm_inv.sum(axis=1, keepdims=True), Dm_inv], axis=1)  # (m, 4, 3): grad N_a
    m = len(tets)
    B = np.zeros((m, 6, 12))
    for a in range(4):
        gx, gy, gz = grads[:, a, 0], grads[:, a, 1], grads[:, a, 2]
        c = 3 * a
        B[:, 0, c], B[:, 1, c + 1], B[:, 2, c + 2] = gx, gy, gz
        B[:, 3, c], B[:, 3, c + 1] = gy, gx
        B[:, 4, c + 1], B[:, 4, c + 2] = gz, gy
        B[:, 5, c], B[:, 5, c + 2] = gz, gx
    D = material.elasticity_3d()
    K = vol[:, None, None] * (B.transpose(0, 2, 1) @ D @ B)
    frames = rest_frames(points, tets) if method == "large" else np.ascontiguousarray(Dm_inv)
    return ElementSet(tets, np.ascontiguousarray(X), K, frames, ROTATION_METHODS[method], vol)


def membrane_triangles(
    points: np.ndarray, triangles: np.ndarray, material: LinearElastic, thickness: float
) -> ElementSet:
    """Constant-strain plane-stress membrane triangles (no bending stiffness).

    In the triangle's rest frame (e1, e2, n) the in-plane stiffness is
    ``K_2 = t A B^T D_ps B`` (6 x 6); it is embedded in 9 x 9 with zero normal stiffness and
    rotated to the rest world frame. Source: Zienkiewicz & Taylor vol. 1, sec. 4.2 (CST);
    SOFA ``TriangularFEMForceField``.

    Args:
        points: ``(n, 3)`` rest positions, mm.
        triangles: ``(m, 3)`` node indices.
        material: plane-stress law.
        thickness: membrane thickness, mm (> 0).

    Raises:
        ValueError: non-positive thickness or a degenerate triangle.
    """
    if not thickness > 0:
        raise ValueError(f"membrane thickness must be positive, got {thickness!r} mm")
    X = points[triangles]
    F0 = rest_frames(points, triangles)  # rows e1, e2, n
    local = (X - X[:, :1]) @ F0.transpose(0, 2, 1)  # (m, 3, 3) coordinates in the frame
    x, y = local[:, :, 0], local[:, :, 1]
    area2 = (x[:, 1] - x[:, 0]) * (y[:, 2] - y[:, 0]) - (x[:, 2] - x[:, 0]) * (y[:, 1] - y[:, 0])
    if np.any(area2 <= 0):
        raise ValueError(f"{int(np.sum(area2 <= 0))} degenerate membrane triangles")
    b = np.stack([y[:, 1] - y[:, 2], y[:, 2] - y[:, 0], y[:, 0] - y[:, 1]], axis=1) / area2[:, None]
    c = np.stack([x[:, 2] - x[:, 1], x[:, 0] - x[:, 2], x[:, 1] - x[:, 0]], axis=1) / area2[:, None]
    m = len(triangles)
    B = np.zeros((m, 3, 9))  # strains from local 3D displacements (z components unused)
    for a in range(3):
        B[:, 0, 3 * a] = b[:, a]
        B[:, 1, 3 * a + 1] = c[:, a]
        B[:, 2, 3 * a] = c[:, a]
        B[:, 2, 3 * a + 1] = b[:, a]
    area = area2 / 2
    K_local = (thickness * area)[:, None, None] * (B.transpose(0, 2, 1) @ material.elasticity_plane_stress() @ B)
    T = np.zeros((m, 9, 9))  # blockdiag(F0): world -> local
    for a in range(3):
        T[:, 3 * a : 3 * a + 3, 3 * a : 3 * a + 3] = F0
    K = T.transpose(0, 2, 1) @ K_local @ T
    return ElementSet(triangles, np.ascontiguousarray(X), K, F0, ROTATION_METHODS["large"], area)


@dataclass(frozen=True, eq=False)
class SparsePattern:
    """A CSR sparsity pattern of a body's ``3n x 3n`` matrices and where element entries go.

    Attributes:
        indptr, indices: CSR structure (sorted, no duplicates).
        maps: one ``(m, (3k)^2)`` int64 array per element set: data positions of entries.
        diag: ``(3n,)`` data positions of the diagonal.
    """

    n_dof: int
    indptr: np.ndarray
    indices: np.ndarray
    maps: tuple[np.ndarray, ...]
    diag: np.ndarray

    @property
    def nnz(self) -> int:
        return len(self.indices)

    def matrix(self, data: np.ndarray) -> sp.csr_matrix:
        """A CSR matrix with this pattern and ``data`` (no copy of the structure arrays)."""
        return sp.csr_matrix((data, self.indices, self.indptr), shape=(self.n_dof, self.n_dof))


def sparse_pattern(n_nodes: int, element_sets: list[ElementSet]) -> SparsePattern:
    """Build the union CSR pattern of the given element sets plus the diagonal."""
    n_dof = 3 * n_nodes
    rows, cols, sizes = [], [], []
    for es in element_sets:
        d = _dof_conn(es.conn)
        nd = d.shape[1]
        rows.append(np.repeat(d, nd, axis=1).ravel())
        cols.append(np.tile(d, (1, nd)).ravel())
        sizes.append(rows[-1].size)
    rows.append(np.arange(n_dof))
    cols.append(np.arange(n_dof))
    keys = np.concatenate(rows).astype(np.int64) * n_dof + np.concatenate(cols)
    uniq, inverse = np.unique(keys, return_inverse=True)
    r, c = np.divmod(uniq, n_dof)
    indptr = np.zeros(n_dof + 1, dtype=np.int64)
    np.cumsum(np.bincount(r, minlength=n_dof), out=indptr[1:])
    maps, start = [], 0
    for es, size in zip(element_sets, sizes):
        maps.append(inverse[start : start + size].reshape(es.n_elements, -1).astype(np.int64))
        start += size
    diag = inverse[start:].astype(np.int64)
    return SparsePattern(n_dof, indptr, c.astype(np.int32), tuple(maps), diag)
