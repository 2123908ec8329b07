"""What a closed-form check reports (:class:`CheckResult`) and how a check's model may be made
wrong on purpose (:class:`ModelScales`): shared by the FEM engine's checks
(:mod:`softcrawl.verify.checks`) and the JAX engine's (:mod:`softcrawl.verify.jax_contact`)."""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from softcrawl.fem.materials import LinearElastic


@dataclass(frozen=True)
class ModelScales:
    """Factors on the parameters of the model a check simulates; the closed-form side keeps
    the nominal values. All 1 (``NOMINAL``) is the check itself; other values give a wrong
    model, which a strong check must reject.

    Attributes:
        youngs_modulus: on every Young's modulus the check's bodies use.
        poisson_ratio: on every Poisson ratio.
        friction: on the floor's Coulomb coefficient.
        gravity: on the gravitational acceleration.
        load: on the applied cavity pressure and point loads.
    """

    youngs_modulus: float = 1.0
    poisson_ratio: float = 1.0
    friction: float = 1.0
    gravity: float = 1.0
    load: float = 1.0

    def material(self, material: LinearElastic) -> LinearElastic:
        """``material`` with the scaled Young's modulus and Poisson ratio."""
        return LinearElastic(material.youngs_modulus * self.youngs_modulus, material.poisson_ratio * self.poisson_ratio)


NOMINAL = ModelScales()


@dataclass(frozen=True)
class CheckResult:
    """One verified quantity.

    Attributes:
        name: what is checked.
        expected: closed-form value.
        got: simulated value.
        tolerance: ``softcrawl verify``'s acceptance bound on ``|got - expected|``: relative to
            ``|expected|`` (mode "rel") or absolute (mode "abs"); unused in mode "min".
        unit: unit of expected/got.
        mode: "rel", "abs", or "min" (``expected`` is a lower bound: pass iff got >= expected).
    """

    name: str
    expected: float
    got: float
    tolerance: float
    unit: str = ""
    mode: str = "rel"

    @property
    def error(self) -> float:
        e = abs(self.got - self.expected)
        if self.mode == "min":
            return max(0.0, self.expected - self.got)
        return e / abs(self.expected) if self.mode == "rel" else e

    @property
    def passed(self) -> bool:
        return bool(np.isfinite(self.got) and self.error <= self.tolerance)

    def to_dict(self) -> dict:
        d = asdict(self)
        d["pass"] = self.passed
        return d
