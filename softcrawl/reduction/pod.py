"""Snapshot POD with rigid modes (reduction.md, "Building Phi").

Snapshots are displacements ``u = x - X`` (not mean-centred). The rigid modes are put in
first; their projection is removed from every snapshot; the SVD of the rest gives the POD
modes, truncated by the tail energy ``sqrt(sum_{k>=m} s_k^2 / sum_k s_k^2) <= tol_modes``;
``[rigid, U[:, :m]]`` is orthonormalised by QR (Sirovich 1987, method of snapshots;
Goury & Duriez 2018, sec. IV).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

RIGID_MODES = ("translations", "rigid")
#: Singular values below this fraction of the largest are round-off of the snapshot Gram
#: matrix (its eigenvalues carry errors of ~1e-16 of the largest, i.e. ~1e-8 in s).
_GRAM_NOISE = 1e-7


def rigid_modes(points: np.ndarray, kind: str = "translations") -> np.ndarray:
    """``(3n, 3)`` unit translations, or ``(3n, 6)`` translations plus infinitesimal rotations
    about the centroid (``kind="rigid"``), not yet orthonormal.

    Raises:
        ValueError: unknown kind.
    """
    if kind not in RIGID_MODES:
        raise ValueError(f"rigid modes must be one of {RIGID_MODES}, got {kind!r}")
    n = len(points)
    modes = [np.tile(np.eye(3)[k], n) for k in range(3)]
    if kind == "rigid":
        r = points - points.mean(0)
        for k in range(3):
            modes.append(np.cross(np.eye(3)[k], r).ravel())
    return np.stack(modes, axis=1)


@dataclass(frozen=True, eq=False)
class PODBasis:
    """Result of :func:`pod_basis`.

    Attributes:
        basis: ``(3n, n_rigid + n_pod)`` orthonormal columns.
        n_rigid: rigid modes first in ``basis``.
        singular_values: ``(S,)`` all singular values of the rigid-free snapshots, descending.
        tail_energy: the tail-energy ratio achieved (<= ``tol_modes``).
    """

    basis: np.ndarray
    n_rigid: int
    singular_values: np.ndarray
    tail_energy: float

    @property
    def n_pod(self) -> int:
        return self.basis.shape[1] - self.n_rigid


def truncation_rank(singular_values: np.ndarray, tol_modes: float) -> int:
    """Smallest ``m`` with ``sqrt(sum_{k>=m} s_k^2 / sum_k s_k^2) <= tol_modes``."""
    e = np.asarray(singular_values, float) ** 2
    total = e.sum()
    if total <= 0:
        return 0
    tail = np.sqrt(np.maximum(total - np.cumsum(e), 0.0) / total)  # tail[m-1] = energy beyond m modes
    return int(np.argmax(tail <= tol_modes)) + 1 if np.any(tail <= tol_modes) else len(e)


def pod_basis(snapshots: np.ndarray, points: np.ndarray, tol_modes: float, rigid: str = "translations",
              max_modes: int | None = None) -> PODBasis:
    """Build an orthonormal basis from displacement snapshots.

    Args:
        snapshots: ``(S, n, 3)`` displacements in the part's frame, mm (any float dtype).
        points: ``(n, 3)`` rest positions of the part, mm (for rotation modes).
        tol_modes: tail-energy tolerance in (0, 1) (reduction.md; reference 0.0032); modes
            with singular values below 1e-7 of the largest are dropped as round-off.
        rigid: ``"translations"`` (3 modes, the reference) or ``"rigid"`` (6: + rotations).
        max_modes: cap on POD modes.

    Raises:
        ValueError: bad shapes, non-finite snapshots or tolerance out of range.
    """
    S = np.asarray(snapshots, dtype=np.float64)
    if S.ndim != 3 or S.shape[1:] != points.shape or len(S) == 0:
        raise ValueError(f"snapshots must be (S, {points.shape[0]}, 3), got {S.shape}")
    if not np.all(np.isfinite(S)):
        raise ValueError("snapshots contain NaN or inf")
    if not 0 < tol_modes < 1:
        raise ValueError(f"tol_modes must be in (0, 1), got {tol_modes}")
    T, _ = np.linalg.qr(rigid_modes(points, rigid))
    A = S.reshape(len(S), -1).T  # (3n, S)
    A = A - T @ (T.T @ A)
    # Method of snapshots: the eigenvectors of A^T A give the left singular vectors of A.
    lam, V = np.linalg.eigh(A.T @ A)
    lam, V = lam[::-1], V[:, ::-1]
    s = np.sqrt(np.maximum(lam, 0.0))
    m = truncation_rank(s, tol_modes)
    if max_modes is not None:
        m = min(m, int(max_modes))
    keep = s[:m] > s[0] * _GRAM_NOISE if m else np.zeros(0, bool)
    U = (A @ V[:, :m][:, keep]) / s[:m][keep]
    Q, R = np.linalg.qr(np.hstack([T, U]))
    Q = Q * np.sign(np.diag(R))[None, :]  # deterministic signs
    e = s**2
    tail = float(np.sqrt(e[m:].sum() / e.sum())) if e.sum() > 0 else 0.0
    return PODBasis(Q, T.shape[1], s, tail)
