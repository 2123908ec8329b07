"""Domain randomization: per-episode draws of the physics and of the rig.

:class:`DomainRanges` holds ``(low, high)`` ranges (``None``: that quantity is not randomized;
the default is all ``None``, which changes nothing and draws nothing); :meth:`DomainRanges.draw`
draws a :class:`DomainSample` uniformly from an RNG (the env's own, at reset), and the sample is
applied to one episode as follows (units: friction, scales and gains dimensionless, offsets real
kPa, lags s):

- ``friction``: the floor's Coulomb coefficient (nominal 1.2; a new
  :class:`~softcrawl.fem.model.Model` sharing the bodies).
- ``youngs_scale``: every Young's modulus of the robot times ``s`` (silicone legs, paper layer,
  printed disk; Poisson ratios kept). The elasticity matrix is linear in E (Zienkiewicz & Taylor,
  vol. 1, eq. 6.13 and 4.14), so every element stiffness is ``s`` times the nominal one.
- ``mass_scale``: every body's mass times ``m`` (legs and disk; lumped masses, gravity loads and
  the Rayleigh mass damping follow).
- ``pressure_gain``, ``pressure_offset``: per regulator ``k`` (one value per regulator of the
  design space: ``R`` draws, 3 in the paper's space), the pressure reaching the legs is
  ``max(g_k p_k + o_k, 0)`` real kPa for the regulator output ``p_k`` (the steady-state model
  ``gain * command + offset`` of :mod:`softcrawl.hardware.regulator_model`), then the pressure
  warp of the paper (Sec. "Sim-to-real"): sim kPa ``= max(a (g_k p_k + o_k) + b, 0)``, i.e. the
  warp's slope times ``g_k`` and its intercept plus ``a o_k`` (:class:`RegulatorWarp`).
- ``tau_inflate``, ``tau_vent``: per regulator, first-order lags of the regulator output under
  physics.md's 150 kPa/s slew limit (:class:`LaggedRegulatorBank`).
- ``control_period``: every action is held ``d`` times its nominal hold, as on the real rig
  (1.067 s per nominal 1-s step; :meth:`DomainSample.action_steps`).

Young's modulus and mass (and friction) change the robot itself: :meth:`DomainSample.apply`
builds the randomized robot from the nominal one *without remeshing or reloading anything*:
each body is copied with scaled materials and mass (its element stiffnesses, which are linear in
E, and its lumped masses are re-formed from them); a reduced leg is placed again from the same
:class:`~softcrawl.reduction.model.PartReduction` on its scaled body (its RID element factors,
reduced mass and gravity load are re-formed; its *basis and ECSW weights stay those the reduction
was built with at the nominal stiffness and mass*: see ``docs/results.md`` for how far that
holds); a floating-frame disk is rebuilt on its scaled body (``K_0`` and its factorization are
re-formed, once per process per sample). A randomized robot has its own rest pose, so
:class:`~softcrawl.envs.CrawlerEnv` settles every episode whose sample is physical. Cost at the
``demo`` preset on the 2-core VM (``benchmarks/randomization.py``): 0.18-0.19 s per episode for
the new robot's reduced data and its settling (24-26 steps of 0.02 s), 8-10% of a 20-action
episode (2.0-2.3 s). The reduction stays as accurate as at the nominal stiffness for Young's
modulus scales 0.95-1.5 and mass scales 0.8-1.2; below 0.95 the exact model itself fails at
90 kPa (``benchmarks/RESULTS.md``): rebuild the reduction when the scale leaves [0.95, 1.5].

The rig quantities (pressure warp, lags, control period) leave the robot and its settled rest
state alone. :meth:`DomainRanges.rig` gives the ranges measured on the paper's rig (the
regulator fits of :data:`softcrawl.hardware.regulator_model.FITTED` and the recorded control
period, ``../shared/data/auro2023``).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from softcrawl.design.space import DEFAULT_SPACE
from softcrawl.fem.body import Body
from softcrawl.fem.materials import LinearElastic
from softcrawl.robot.actuation import PressureCalibration, RegulatorBank
from softcrawl.reduction.floating import FloatingFrameBody
from softcrawl.reduction.model import ReducedBody, reduce_body
from softcrawl.robot.assembly import Robot

#: Keys of a :class:`DomainRanges` / :class:`DomainSample`, in draw order, with the smallest
#: allowed value and whether it is allowed itself (``> 0`` or ``>= 0``; None: any finite
#: value), whether the quantity is drawn per regulator, and its unit in CSV column names.
KEYS: dict[str, tuple[float | None, bool, bool, str]] = {
    "friction": (0.0, True, False, ""),
    "youngs_scale": (0.0, False, False, ""),
    "mass_scale": (0.0, False, False, ""),
    "pressure_gain": (0.0, True, True, ""),
    "pressure_offset": (None, True, True, "_kpa"),
    "tau_inflate": (0.0, True, True, "_s"),
    "tau_vent": (0.0, True, True, "_s"),
    "control_period": (0.0, False, False, ""),
}
#: Keys that change the robot (its model and rest state), not only the rig around it.
PHYSICAL_KEYS = ("friction", "youngs_scale", "mass_scale")
#: Where the error messages say a range is set (``--set env.randomize.KEY=[low,high]``).
CONFIG_PREFIX = "env.randomize."
#: Named range sets of :meth:`DomainRanges.preset`.
PRESETS = ("off", "rig")
#: The ranges of :meth:`DomainRanges.rig`: per-regulator gain, offset (kPa) and lags (s) from the
#: smallest to the largest of the three regulators of
#: :data:`softcrawl.hardware.regulator_model.FITTED` (the fit to the recorded AuRo 2023 logs; the
#: robot package sits below :mod:`softcrawl.hardware`, so they are copied here and
#: ``tests/test_randomization.py`` checks them against the fit), and the control period factor
#: spanning the mean hold of each of the 273 recorded trials (1.062-1.070 s per nominal 1 s,
#: ``../shared/data/auro2023``).
RIG_RANGES: dict[str, tuple[float, float]] = {
    "pressure_gain": (0.9473, 1.2284),
    "pressure_offset": (-5.892, -2.516),
    "tau_inflate": (0.0267, 0.598),
    "tau_vent": (0.264, 0.691),
    "control_period": (1.062, 1.070),
}
#: Regulators of the paper's design space: the default count of per-regulator draws and columns.
PAPER_REGULATORS = DEFAULT_SPACE.n_regulators


def _check_value(key: str, v: float, what: str) -> None:
    low, inclusive, _, _ = KEYS[key]
    if not math.isfinite(v):
        raise ValueError(f"{CONFIG_PREFIX}{key}: {what} {v!r} is not finite")
    if low is not None and (v < low or (v == low and not inclusive)):
        raise ValueError(f"{CONFIG_PREFIX}{key}: {what} {v!r} must be {'>=' if inclusive else '>'} {low:g}")


@dataclass(frozen=True)
class DomainRanges:
    """Per-episode randomization ranges (module docstring): each ``(low, high)`` with
    ``low <= high`` (equal: a fixed value other than the nominal one), or None (not randomized).

    Attributes:
        friction: floor Coulomb coefficient, ``>= 0`` (nominal 1.2).
        youngs_scale: factor on every Young's modulus, ``> 0`` (nominal 1).
        mass_scale: factor on every body's mass, ``> 0`` (nominal 1).
        pressure_gain: per-regulator gain on the regulator output, ``>= 0`` (nominal 1).
        pressure_offset: per-regulator offset added to it, real kPa (nominal 0).
        tau_inflate, tau_vent: per-regulator first-order lags, s, ``>= 0`` (nominal 0: the
            pure 150 kPa/s slew limit of physics.md).
        control_period: factor on every action's hold, ``> 0`` (nominal 1; the real rig:
            1.062-1.070).

    Raises:
        ValueError: a range that is not two finite numbers with ``low <= high`` inside its
            key's bounds; the message names the key (``env.randomize.KEY``).
    """

    friction: tuple[float, float] | None = None
    youngs_scale: tuple[float, float] | None = None
    mass_scale: tuple[float, float] | None = None
    pressure_gain: tuple[float, float] | None = None
    pressure_offset: tuple[float, float] | None = None
    tau_inflate: tuple[float, float] | None = None
    tau_vent: tuple[float, float] | None = None
    control_period: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        for key in KEYS:
            r = getattr(self, key)
            if r is None:
                continue
            if isinstance(r, (str, bytes)) or not hasattr(r, "__len__") or len(r) != 2:
                raise ValueError(f"{CONFIG_PREFIX}{key} must be [low, high] or null, got {r!r}")
            if any(isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)) for v in r):
                raise ValueError(f"{CONFIG_PREFIX}{key} must be two numbers [low, high], got {r!r}")
            lo, hi = float(r[0]), float(r[1])
            _check_value(key, lo, "low")
            _check_value(key, hi, "high")
            if lo > hi:
                raise ValueError(f"{CONFIG_PREFIX}{key}: low {lo!r} > high {hi!r}")
            object.__setattr__(self, key, (lo, hi))

    @property
    def enabled(self) -> bool:
        """Whether any quantity is randomized."""
        return any(getattr(self, k) is not None for k in KEYS)

    @property
    def physical(self) -> bool:
        """Whether the robot itself is randomized (friction, Young's moduli or masses)."""
        return any(getattr(self, k) is not None for k in PHYSICAL_KEYS)

    def keys(self) -> tuple[str, ...]:
        """The randomized keys, in draw order."""
        return tuple(k for k in KEYS if getattr(self, k) is not None)

    def columns(self, n_regulators: int = PAPER_REGULATORS) -> tuple[str, ...]:
        """CSV column names of the samples of these ranges (:meth:`DomainSample.columns`) for
        a space of ``n_regulators`` regulators."""
        return tuple(_column_names(self.keys(), n_regulators))

    def draw(self, rng: np.random.Generator, n_regulators: int = PAPER_REGULATORS) -> DomainSample | None:
        """One :class:`DomainSample`: ``rng.uniform(low, high)`` for each randomized key in
        :data:`KEYS` order (``n_regulators`` draws for a per-regulator key: one per regulator of
        the design space, 3 in the paper's); None if nothing is randomized (no draw at all, so
        the RNG's stream is that of an env without randomization).

        Raises:
            ValueError: ``n_regulators < 1``.
        """
        if int(n_regulators) != n_regulators or n_regulators < 1:
            raise ValueError(f"n_regulators must be a positive integer, got {n_regulators!r}")
        if not self.enabled:
            return None
        out = {}
        for key in self.keys():
            lo, hi = getattr(self, key)
            if KEYS[key][2]:
                out[key] = tuple(float(v) for v in rng.uniform(lo, hi, int(n_regulators)))
            else:
                out[key] = float(rng.uniform(lo, hi))
        return DomainSample(**out)

    def check_steps(self, steps_per_action: int) -> None:
        """Raise ValueError if the shortest dilated hold gets less than one simulator step
        (``control_period`` low times ``steps_per_action`` < 1)."""
        if self.control_period is not None and self.control_period[0] * steps_per_action < 1:
            raise ValueError(f"{CONFIG_PREFIX}control_period: low {self.control_period[0]!r} gives actions of less "
                             f"than one simulator step at {steps_per_action} steps per action")

    @classmethod
    def rig(cls) -> DomainRanges:
        """The rig quantities as measured on the paper's rig (:data:`RIG_RANGES`): gains, offsets
        and lags spanning the three regulators fitted to the recorded logs, the control period
        spanning the recorded trials' mean hold. Friction, moduli and masses are left off (not
        measured)."""
        return cls(**RIG_RANGES)

    @classmethod
    def preset(cls, name: str) -> DomainRanges:
        """Named ranges: ``"off"`` (nothing randomized) or ``"rig"`` (:meth:`rig`).

        Raises:
            ValueError: another name.
        """
        if name == "off":
            return cls()
        if name == "rig":
            return cls.rig()
        raise ValueError(f"unknown {CONFIG_PREFIX.rstrip('.')} preset {name!r}; choose one of {PRESETS}")


def _column_names(keys, n_regulators: int) -> list[str]:
    cols = []
    for key in keys:
        unit, per_reg = KEYS[key][3], KEYS[key][2]
        cols += [f"{key}_{k}{unit}" for k in range(1, int(n_regulators) + 1)] if per_reg else [f"{key}{unit}"]
    return cols


@dataclass(frozen=True)
class DomainSample:
    """One episode's randomized quantities (module docstring; None: nominal). Per-regulator
    values are ``(R,)`` tuples, one per regulator of the design space (regulators 1..R; the
    same ``R >= 1`` for every per-regulator key); a single number is repeated ``R`` times, ``R``
    being that of the key given as a sequence, else the paper's 3 (:data:`PAPER_REGULATORS`).
    Whether ``R`` is the space's is checked where the sample meets the space
    (:meth:`check_regulators`, called by :meth:`calibration` and :meth:`regulators`).

    Raises:
        ValueError: a value outside its key's bounds (:data:`KEYS`) or not finite; per-regulator
            keys of different lengths, or an empty one.
    """

    friction: float | None = None
    youngs_scale: float | None = None
    mass_scale: float | None = None
    pressure_gain: tuple[float, ...] | None = None
    pressure_offset: tuple[float, ...] | None = None
    tau_inflate: tuple[float, ...] | None = None
    tau_vent: tuple[float, ...] | None = None
    control_period: float | None = None

    def __post_init__(self) -> None:
        given = {key: np.asarray(v, dtype=float) for key, (_, _, per_reg, _) in KEYS.items()
                 if per_reg and (v := getattr(self, key)) is not None and np.ndim(v) != 0}
        lengths = {a.shape[0] if a.ndim == 1 else 0 for a in given.values()}
        if len(lengths) > 1 or 0 in lengths:
            raise ValueError(f"{CONFIG_PREFIX}{'/'.join(given)}: need one value per regulator, the same number for "
                             f"each, got {', '.join(f'{k}={getattr(self, k)!r}' for k in given)}")
        n = lengths.pop() if lengths else PAPER_REGULATORS
        for key, (_, _, per_reg, _) in KEYS.items():
            v = getattr(self, key)
            if v is None:
                continue
            if per_reg:
                arr = given.get(key)
                arr = np.full(n, float(v)) if arr is None else arr
                for x in arr:
                    _check_value(key, float(x), "value")
                object.__setattr__(self, key, tuple(float(x) for x in arr))
            else:
                _check_value(key, float(v), "value")
                object.__setattr__(self, key, float(v))

    @property
    def n_regulators(self) -> int | None:
        """``R``, the length of the per-regulator values (None: none is set)."""
        return next((len(v) for k in KEYS if KEYS[k][2] and (v := getattr(self, k)) is not None), None)

    def check_regulators(self, n_regulators: int) -> None:
        """Raise ValueError (one line naming the key) unless every per-regulator value has one
        entry per regulator of a space of ``n_regulators`` regulators."""
        for key in KEYS:
            v = getattr(self, key)
            if KEYS[key][2] and v is not None and len(v) != n_regulators:
                raise ValueError(f"{CONFIG_PREFIX}{key}: need {n_regulators} values (one per regulator of the "
                                 f"design space), got {list(v)!r}")

    @property
    def physical(self) -> bool:
        """Whether the robot itself changes (friction, Young's moduli or masses)."""
        return any(getattr(self, k) is not None for k in PHYSICAL_KEYS)

    def as_dict(self) -> dict:
        """The randomized values (keys of :data:`KEYS` that are set; per-regulator ones as lists)."""
        return {k: (list(v) if isinstance(v, tuple) else v) for k in KEYS if (v := getattr(self, k)) is not None}

    def columns(self) -> dict[str, float]:
        """Flat ``{column: value}`` for CSV logs (per-regulator keys as ``KEY_1``..``KEY_3``,
        offsets ``..._kpa``, lags ``..._s``), randomized keys only."""
        keys = [k for k in KEYS if getattr(self, k) is not None]
        values = []
        for k in keys:
            v = getattr(self, k)
            values += list(v) if isinstance(v, tuple) else [v]
        return dict(zip(_column_names(keys, self.n_regulators or PAPER_REGULATORS), values))

    # -- applying it ------------------------------------------------------------------------
    def apply(self, robot: Robot) -> Robot:
        """The randomized robot (:func:`randomized_robot` with this sample's friction, Young's
        modulus scale and mass scale); ``robot`` itself if none of them is set."""
        if not self.physical:
            return robot
        return randomized_robot(robot, self.friction, self.youngs_scale, self.mass_scale)

    def calibration(self, base: PressureCalibration,
                    n_regulators: int = PAPER_REGULATORS) -> PressureCalibration | RegulatorWarp:
        """The real-to-sim pressure map of the episode on a space of ``n_regulators``
        regulators: ``base`` itself, or ``base`` after the per-regulator gains and offsets
        (:class:`RegulatorWarp`).

        Raises:
            ValueError: per-regulator values of another length (:meth:`check_regulators`).
        """
        self.check_regulators(n_regulators)
        if self.pressure_gain is None and self.pressure_offset is None:
            return base
        return RegulatorWarp(base, self.pressure_gain or (1.0,) * n_regulators,
                             self.pressure_offset or (0.0,) * n_regulators)

    def regulators(self, rate_kpa_s: float = 150.0, n_regulators: int = PAPER_REGULATORS) -> RegulatorBank:
        """The episode's ``n_regulators`` regulators: the nominal slew-limited
        :class:`RegulatorBank`, or a :class:`LaggedRegulatorBank` when a lag is set (an unset
        lag is 0).

        Raises:
            ValueError: per-regulator values of another length (:meth:`check_regulators`).
        """
        self.check_regulators(n_regulators)
        if self.tau_inflate is None and self.tau_vent is None:
            return RegulatorBank(n_regulators, rate_kpa_s)
        zero = (0.0,) * n_regulators
        return LaggedRegulatorBank(n_regulators, rate_kpa_s, self.tau_inflate or zero, self.tau_vent or zero)

    def action_steps(self, nominal: int, k: int) -> int:
        """Simulator steps of action ``k`` (0-based) when every action nominally takes
        ``nominal`` steps: ``round(d n (k + 1)) - round(d n k)`` with ``d = control_period``
        (round half up), so the first ``k`` actions together last ``round(d n k)`` steps: the
        dilation is exact to one step over the whole episode (a single action's hold can only
        be a whole number of steps). ``nominal`` when not randomized."""
        if self.control_period is None:
            return int(nominal)
        d = self.control_period * int(nominal)
        return math.floor(d * (k + 1) + 0.5) - math.floor(d * k + 0.5)


# -- the pieces ---------------------------------------------------------------------------------
def _scaled_material(mat: LinearElastic, s: float) -> LinearElastic:
    return mat if s == 1.0 else LinearElastic(mat.youngs_modulus * s, mat.poisson_ratio)


def scaled_body(body: Body, youngs_scale: float = 1.0, mass_scale: float = 1.0) -> Body:
    """A copy of ``body`` with every Young's modulus (tetrahedra and membrane) times
    ``youngs_scale`` and its mass times ``mass_scale`` (same mesh, cavities, collision nodes;
    element data and lumped masses are re-formed lazily). ``body`` itself if both are 1."""
    if youngs_scale == 1.0 and mass_scale == 1.0:
        return body
    membrane = body.membrane
    if membrane is not None:
        membrane = dataclasses.replace(membrane, material=_scaled_material(membrane.material, youngs_scale))
    return dataclasses.replace(body, material=_scaled_material(body.material, youngs_scale),
                               mass=body.mass * mass_scale, membrane=membrane)


def randomized_robot(robot: Robot, friction: float | None = None, youngs_scale: float | None = None,
                     mass_scale: float | None = None) -> Robot:
    """``robot`` with another floor friction, every Young's modulus times ``youngs_scale`` and
    every body's mass times ``mass_scale`` (None: unchanged). No remeshing, no reduction
    reloaded: bodies are copied (:func:`scaled_body`); reduced legs are placed again from their
    part reduction on the scaled bodies (element factors of the scaled moduli, reduced masses
    and gravity loads of the scaled masses; basis and ECSW weights unchanged); a floating-frame
    disk is rebuilt on its scaled body. ``robot.config`` records the friction and masses.

    Raises:
        ValueError: a negative or non-finite friction, a non-positive or non-finite scale.
        TypeError: a reduced body of an unknown kind.
    """
    s = 1.0 if youngs_scale is None else float(youngs_scale)
    m = 1.0 if mass_scale is None else float(mass_scale)
    for key, v in (("youngs_scale", s), ("mass_scale", m)) + ((("friction", float(friction)),) if friction is not None
                                                               else ()):
        _check_value(key, v, "value")
    model = robot.model
    bodies = tuple(scaled_body(b, s, m) for b in model.bodies)
    floor = model.floor
    if friction is not None and floor is not None:
        floor = dataclasses.replace(floor, friction=float(friction))
    new_model = dataclasses.replace(model, bodies=bodies, floor=floor)
    reduced = {}
    for i, rb in robot.reduced.items():
        if bodies[i] is model.bodies[i]:
            reduced[i] = rb
        elif isinstance(rb, ReducedBody):
            reduced[i] = reduce_body(bodies[i], rb.part, rb.rotation)
        elif isinstance(rb, FloatingFrameBody):
            reduced[i] = FloatingFrameBody(bodies[i])
        else:  # pragma: no cover - no other kind exists
            raise TypeError(f"cannot randomize a reduced body of type {type(rb).__name__}")
    c = robot.config
    config = dataclasses.replace(c, friction=floor.friction if floor is not None else c.friction,
                                 leg_mass=c.leg_mass * m, disk_mass=c.disk_mass * m)
    return dataclasses.replace(robot, model=new_model, reduced=reduced, config=config)


@dataclass(frozen=True)
class RegulatorWarp:
    """Real-to-sim pressure map with per-regulator gain and offset before the pressure warp:
    sim kPa ``= base.to_sim(max(gain_k p_k + offset_k, 0))`` for the regulator outputs ``p``
    (real kPa, last axis = regulators 1..R), i.e. ``max(a (g p + o) + b, 0)`` with the base
    warp's ``a, b`` (:class:`~softcrawl.robot.actuation.PressureCalibration`).

    Attributes:
        base: the nominal warp. gain: ``(R,)``. offset: ``(R,)`` real kPa.
    """

    base: PressureCalibration
    gain: tuple[float, ...]
    offset: tuple[float, ...]

    def to_sim(self, real_kpa):
        """Sim kPa for real regulator outputs ``real_kpa`` ``(..., R)`` (an array of that shape)."""
        real = np.maximum(np.asarray(self.gain) * np.asarray(real_kpa, dtype=float) + np.asarray(self.offset), 0.0)
        return self.base.to_sim(real)


class LaggedRegulatorBank(RegulatorBank):
    """Regulators with first-order inflate / vent lags under the slew limit.

    Per step of ``dt`` s towards command ``c`` from output ``p``:
    ``p += clip((c - p) (1 - exp(-dt / tau)), -rate dt, rate dt)`` with ``tau = tau_inflate``
    when ``c > p`` else ``tau_vent``: the exact step of ``dp/dt = (c - p) / tau`` for a
    command held over the step (the lag model of :mod:`softcrawl.hardware.regulator_model`),
    limited by the slew rate of physics.md ("Regulator dynamics"). ``tau = 0`` is no lag: the
    step is then the plain :class:`RegulatorBank` step, to the bit.

    Args:
        n: regulators. rate_kpa_s: slew-rate limit, kPa/s.
        tau_inflate, tau_vent: ``(n,)`` lags, s, ``>= 0``.

    Raises:
        ValueError: wrong shapes, negative or non-finite lags (and :class:`RegulatorBank`'s errors).
    """

    def __init__(self, n: int = 3, rate_kpa_s: float = 150.0, tau_inflate=(0.0, 0.0, 0.0),
                 tau_vent=(0.0, 0.0, 0.0)) -> None:
        super().__init__(n, rate_kpa_s)
        for name, tau in (("tau_inflate", tau_inflate), ("tau_vent", tau_vent)):
            t = np.asarray(tau, dtype=float)
            if t.shape != (self.n,) or not np.all(np.isfinite(t)) or np.any(t < 0):
                raise ValueError(f"{name} must be {self.n} finite lags >= 0 s, got {tau!r}")
            setattr(self, name, t.copy())

    def step(self, command, dt: float) -> np.ndarray:
        """Advance ``dt`` s towards ``command`` ``(n,)`` real kPa (class docstring); returns the
        applied ``(n,)``.

        Raises:
            PressureRangeError: a non-finite command or one outside [0, 90] kPa.
            ValueError: a wrong shape or a negative / non-finite ``dt``.
        """
        cmd = self._check(command, "command")
        if not (np.isfinite(dt) and dt >= 0):
            raise ValueError(f"dt must be finite and >= 0 s, got {dt}")
        tau = np.where(cmd > self.state, self.tau_inflate, self.tau_vent)
        frac = np.ones(self.n)
        lagged = tau > 0
        frac[lagged] = -np.expm1(-dt / tau[lagged])
        max_dp = self.rate_kpa_s * dt
        self.state = self.state + np.clip((cmd - self.state) * frac, -max_dp, max_dp)
        return self.state.copy()


__all__ = ["KEYS", "PAPER_REGULATORS", "PHYSICAL_KEYS", "DomainRanges", "DomainSample", "LaggedRegulatorBank",
           "RegulatorWarp", "randomized_robot", "scaled_body"]
