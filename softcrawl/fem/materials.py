"""Linear elastic material laws (small strain, used in the corotational frame).

Units: Young's modulus in kPa (= kg mm^-1 s^-2), so stiffness times mm gives mN.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LinearElastic:
    """Isotropic linear elastic material.

    Attributes:
        youngs_modulus: E in kPa, > 0.
        poisson_ratio: nu, in (-1, 0.5).

    Raises:
        ValueError: if E is not positive and finite, or nu is outside (-1, 0.5).
    """

    youngs_modulus: float
    poisson_ratio: float

    def __post_init__(self) -> None:
        E, nu = self.youngs_modulus, self.poisson_ratio
        if not (math.isfinite(E) and E > 0):
            raise ValueError(f"Young's modulus must be positive and finite, got E = {E!r} kPa")
        if not (math.isfinite(nu) and -1.0 < nu < 0.5):
            raise ValueError(f"Poisson ratio must lie in (-1, 0.5), got nu = {nu!r}")

    @property
    def lame(self) -> tuple[float, float]:
        """Lamé parameters (lambda, mu) in kPa."""
        E, nu = self.youngs_modulus, self.poisson_ratio
        return E * nu / ((1 + nu) * (1 - 2 * nu)), E / (2 * (1 + nu))

    def elasticity_3d(self) -> np.ndarray:
        """``(6, 6)`` isotropic elasticity matrix D (Voigt order xx, yy, zz, xy, yz, zx,
        engineering shear strains), kPa. Source: Zienkiewicz & Taylor, *The FEM*, vol. 1, eq. 6.13."""
        lam, mu = self.lame
        D = np.zeros((6, 6))
        D[:3, :3] = lam
        D[np.arange(3), np.arange(3)] += 2 * mu
        D[np.arange(3, 6), np.arange(3, 6)] = mu
        return D

    def elasticity_plane_stress(self) -> np.ndarray:
        """``(3, 3)`` plane-stress elasticity matrix (xx, yy, xy with engineering shear), kPa.
        Source: Zienkiewicz & Taylor, vol. 1, eq. 4.14."""
        E, nu = self.youngs_modulus, self.poisson_ratio
        c = E / (1 - nu**2)
        return c * np.array([[1.0, nu, 0.0], [nu, 1.0, 0.0], [0.0, 0.0, (1 - nu) / 2]])


#: DragonSkin 30 silicone of the PneuNet legs (physics.md): E from Shore 30A.
DRAGONSKIN_30 = LinearElastic(1160.0, 0.2)
#: The strain-limiting paper layer (membrane triangles, 1 mm thick).
PAPER = LinearElastic(2320.0, 0.49)
#: The 3D-printed disk.
PRINTED_POLYMER = LinearElastic(5000.0, 0.3)
