"""Pressure calibration from measurements: the paper's "pressure warp" (paper Sec. "Sim-to-real",
physics.md "Pneumatic actuation").

The authors bent one real PneuNet at known pressures, found for each the simulated pressure
that bends the model the same amount, and fitted ``sim = a * real + b`` (a = 4.0785,
b = -20.36 for their table). :func:`calibrate` does the same from a CSV of measured bends:

1. a :class:`BendCurve` gives the bend of the clamped full-order PneuNet (the
   :func:`softcrawl.verify.checks.clamped_pneunet` model: physics.md materials, paper layer,
   clamped at its inner end faces, no gravity) at a sim pressure, settled quasi-statically with
   large implicit-Euler steps (dt 0.25 s; stop when the tip angle changes by < 1e-3 deg per
   step). Bends: ``tip_angle_deg`` (tip face normal from +x toward the paper side) and
   ``tip_deflection_mm`` (tip moving toward the paper side, +). Every evaluation is cached on
   disk (``$SOFTCRAWL_CACHE_DIR/bend_curves``, keyed by the model settings);
2. for each measured bend, bracket it on a pressure grid and solve ``bend(p) = measured`` with
   Brent's method (``xtol`` 0.01 kPa);
3. least-squares line through ``(real, sim)`` with residuals; written as a JSON calibration
   file that :func:`load_calibration` turns into a :class:`PressureCalibration`.

Plausibility (:func:`check_measurements`, before any simulation; :func:`check_slope` after the
fit and when a calibration file is loaded): real pressures in ``(0, MAX_REAL_KPA]``, bends
finite and > 0 and increasing with pressure (a PneuNet bends more at a higher pressure), and
a fitted slope ``a`` in :data:`A_RANGE`.

The bend input is a CSV with a header: ``real_kpa`` and one of ``tip_angle_deg`` /
``tip_deflection_mm``, or photos with ArUco markers (:mod:`softcrawl.hardware.aruco`).
"""

from __future__ import annotations

import csv
import hashlib
import json
import math
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from softcrawl.hardware.errors import one_line
from softcrawl.robot.actuation import PressureCalibration
from softcrawl.safeio import atomic_write_text, load_json, read_text

MEASURES = ("tip_angle_deg", "tip_deflection_mm")
FORMAT = "softcrawl-calibration"
FORMAT_VERSION = 1
#: The reference calibration (physics.md): sim = 4.0785 real - 20.36.
REFERENCE = (4.0785, -20.36)
#: Highest real pressure of a bend measurement, kPa: the top of the reference bending table
#: (physics.md, 10..100 kPa), 10 kPa above the regulators' 90 kPa command range.
MAX_REAL_KPA = 100.0
#: Plausible slopes ``a`` of the warp, sim kPa per real kPa: within a factor of about 20 of the
#: reference 4.08. Pressures logged in psi instead of kPa give 6.9x the slope (28), in bar
#: 100x (408); a slope outside this range means mismatched units, bends or model.
A_RANGE = (0.2, 20.0)


@dataclass(frozen=True)
class BendModel:
    """Settings of the clamped-leg bend simulation (mm, s, deg)."""

    mesh_size: float = 8.0
    dt: float = 0.25
    ramp_s: float = 1.0
    tol_deg: float = 1e-3
    max_time_s: float = 60.0

    def key(self) -> str:
        return hashlib.sha256(json.dumps({"model": asdict(self), "v": 1}, sort_keys=True).encode()).hexdigest()[:16]


def simulate_bend(model: BendModel, p_sim: float) -> tuple[float, float]:
    """Settled ``(tip_angle_deg, tip_deflection_mm)`` of the clamped PneuNet at ``p_sim`` kPa (sim)."""
    from softcrawl.fem.solver import ImplicitEulerSolver, SolverSettings
    from softcrawl.fem.state import Control
    from softcrawl.verify.checks import clamped_pneunet

    fem = clamped_pneunet(model.mesh_size)
    mesh = fem.bodies[0].mesh
    tip = mesh.node_sets["tip"]
    near_tip = np.flatnonzero(mesh.points[:, 0] > mesh.points[:, 0].max() - 15.0)

    def measure(st):
        xt = st.x[tip]
        n = np.linalg.svd(xt - xt.mean(0), full_matrices=False)[2][-1]
        n = n if n @ (xt.mean(0) - st.x[near_tip].mean(0)) > 0 else -n
        return float(np.degrees(np.arctan2(-n[2], n[0]))), float(-(xt[:, 2] - mesh.points[tip, 2]).mean())

    solver = ImplicitEulerSolver(fem, SolverSettings(dt=model.dt))
    st = fem.rest_state()
    n_ramp = max(1, int(round(model.ramp_s / model.dt)))
    prev, k = None, 0
    while True:
        k += 1
        st = solver.step(st, Control(np.array([p_sim * min(1.0, k / n_ramp)])))
        ang, dz = measure(st)
        if k > n_ramp and prev is not None and abs(ang - prev) < model.tol_deg:
            break
        if k * model.dt > model.max_time_s:
            raise RuntimeError(f"clamped PneuNet at {p_sim:g} kPa did not settle in {model.max_time_s:g} s")
        prev = ang
    return ang, dz


def bend_cache_dir() -> Path:
    return Path(os.environ.get("SOFTCRAWL_CACHE_DIR") or Path.home() / ".cache" / "softcrawl") / "bend_curves"


class BendCurve:
    """Bend of the clamped leg vs sim pressure, cached in memory and on disk.

    Args:
        model: simulation settings.
        evaluate: ``p -> (angle_deg, deflection_mm)``; default :func:`simulate_bend` (tests inject
            an analytic one).
        cache: keep evaluations on disk (default True).

    Attributes:
        evaluations: number of simulations run by this object (cache hits do not count).
    """

    def __init__(self, model: BendModel = BendModel(), evaluate=None, cache: bool = True) -> None:
        self.model = model
        self._eval = evaluate or (lambda p: simulate_bend(model, p))
        self.path = bend_cache_dir() / f"{model.key()}.json" if cache else None
        self.points: dict[float, tuple[float, float]] = {0.0: (0.0, 0.0)}
        self.evaluations = 0
        if self.path is not None and self.path.exists():
            try:
                data = load_json(self.path)
                if data.get("model") == asdict(model):
                    self.points.update({float(p): (float(a), float(d)) for p, a, d in data["points"]})
            except (OSError, ValueError, KeyError, TypeError, AttributeError, OverflowError):
                pass  # a damaged cache is rebuilt

    def _save(self) -> None:
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(self.path, json.dumps({"model": asdict(self.model),
                                                 "points": [[p, a, d] for p, (a, d) in sorted(self.points.items())]}))

    def bend(self, p_sim: float, measure: str = "tip_angle_deg") -> float:
        """Bend (``measure``) at sim pressure ``p_sim`` kPa (>= 0)."""
        p = round(float(p_sim), 6)
        if p < 0:
            raise ValueError(f"sim pressure must be >= 0 kPa, got {p}")
        if p not in self.points:
            self.points[p] = tuple(float(v) for v in self._eval(p))
            self.evaluations += 1
            self._save()
        return self.points[p][MEASURES.index(measure)]

    def find_pressure(self, target: float, measure: str = "tip_angle_deg", p_max: float = 800.0,
                      grid_kpa: float = 50.0, xtol: float = 0.01) -> float:
        """Sim pressure (kPa) whose bend equals ``target``: bracketed on a ``grid_kpa`` grid (cached
        points first), then Brent's method.

        Raises:
            ValueError: ``target`` <= 0, beyond the bend at ``p_max``, or needing a pressure at
                which the model does not settle.
        """
        if not (math.isfinite(target) and target > 0):
            raise ValueError(f"measured bend must be > 0, got {target}")
        try:
            return self._find(target, measure, p_max, grid_kpa, xtol)
        except RuntimeError as exc:  # the model does not settle at the pressures this bend needs
            raise ValueError(f"bend {target:g} cannot be reached by the model: {one_line(exc)}") from None

    def _find(self, target: float, measure: str, p_max: float, grid_kpa: float, xtol: float) -> float:
        from scipy.optimize import brentq

        f = lambda p: self.bend(p, measure) - target  # noqa: E731
        known = sorted(self.points)
        below = [p for p in known if f(p) <= 0]
        above = [p for p in known if f(p) > 0]
        lo = max(below)
        hi = min([p for p in above if p > lo], default=None)
        while hi is None:
            nxt = (math.floor(lo / grid_kpa) + 1) * grid_kpa
            if nxt > p_max:
                raise ValueError(f"bend {target:g} is beyond the model's bend at {p_max:g} kPa "
                                 f"({self.bend(p_max, measure):.3g}): the model cannot reach it")
            if f(nxt) > 0:
                hi = nxt
            else:
                lo = nxt
        if hi - lo > grid_kpa:  # tighten a wide cached bracket on the grid first
            for g in np.arange((math.floor(lo / grid_kpa) + 1) * grid_kpa, hi, grid_kpa):
                if f(g) > 0:
                    hi = g
                    break
                lo = g
        if f(lo) == 0:
            return lo
        return float(brentq(f, lo, hi, xtol=xtol))


@dataclass(frozen=True)
class CalibrationResult:
    """Outcome of :func:`calibrate`: ``real_kpa``, ``bend``, ``sim_kpa`` ``(k,)``; the line
    ``a``, ``b``; ``residual_kpa`` = fit - sim ``(k,)``; the bend ``measure``."""

    real_kpa: np.ndarray
    bend: np.ndarray
    sim_kpa: np.ndarray
    a: float
    b: float
    residual_kpa: np.ndarray
    measure: str
    model: BendModel

    @property
    def calibration(self) -> PressureCalibration:
        return PressureCalibration(self.a, self.b)

    def to_dict(self, source: str = "") -> dict:
        ss = float(np.sum((self.sim_kpa - self.sim_kpa.mean()) ** 2))
        return {
            "format": FORMAT, "version": FORMAT_VERSION, "map": "sim_kpa = max(a * real_kpa + b, 0)",
            "a": self.a, "b": self.b, "measure": self.measure, "source": source,
            "bend_model": asdict(self.model),
            "rms_residual_kpa": float(np.sqrt(np.mean(self.residual_kpa ** 2))),
            "max_abs_residual_kpa": float(np.max(np.abs(self.residual_kpa))),
            "r2": float(1 - np.sum(self.residual_kpa ** 2) / ss) if ss > 0 else None,
            "points": [{"real_kpa": float(r), "bend": float(m), "sim_kpa": float(s), "fit_kpa": float(s + e),
                        "residual_kpa": float(e)} for r, m, s, e in zip(self.real_kpa, self.bend, self.sim_kpa,
                                                                         self.residual_kpa)],
        }


def check_real_kpa(kpa: float, where: str) -> float:
    """A measurement's real pressure, kPa, checked to be finite and in ``(0, MAX_REAL_KPA]``.

    Raises:
        ValueError: naming ``where`` (a file and line, or a photo).
    """
    if not (math.isfinite(kpa) and 0 < kpa <= MAX_REAL_KPA):
        raise ValueError(f"{where}: real pressure {kpa:g} kPa must be in (0, {MAX_REAL_KPA:g}] kPa")
    return float(kpa)


def check_measurements(real_kpa, bend) -> tuple[np.ndarray, np.ndarray]:
    """``(real_kpa (k,), bend (k,))`` checked for plausibility: k >= 2 pairs, pressures in
    ``(0, MAX_REAL_KPA]`` and not all equal, bends finite and > 0 and increasing with pressure
    (every bend at a higher pressure is larger than every bend at a lower one).

    Raises:
        ValueError: naming the first implausible point.
    """
    real = np.asarray(real_kpa, dtype=float)
    bend = np.asarray(bend, dtype=float)
    if real.ndim != 1 or real.shape != bend.shape or real.size < 2:
        raise ValueError(f"need >= 2 paired measurements, got shapes {real.shape} and {bend.shape}")
    for i, (r, m) in enumerate(zip(real, bend)):
        check_real_kpa(r, f"measurement {i + 1}")
        if not (math.isfinite(m) and m > 0):
            raise ValueError(f"measurement {i + 1}: bend {m:g} must be finite and > 0")
    if np.ptp(real) == 0:
        raise ValueError(f"all measurements are at {real[0]:g} kPa: need at least 2 pressures")
    order = np.lexsort((bend, real))
    r, m = real[order], bend[order]
    for j in range(1, r.size):
        lower = r < r[j]
        if lower.any() and m[lower].max() >= m[j]:
            i = int(np.flatnonzero(lower)[np.argmax(m[lower])])
            raise ValueError(f"bends must increase with pressure: {m[i]:g} at {r[i]:g} kPa but {m[j]:g} at "
                             f"{r[j]:g} kPa")
    return real, bend


def check_slope(a: float, where: str) -> None:
    """Raise ValueError (naming ``where``) unless the warp's slope ``a`` is in :data:`A_RANGE`."""
    lo, hi = A_RANGE
    if not (math.isfinite(a) and lo <= a <= hi):
        raise ValueError(f"{where}: slope a = {a:.4g} sim kPa per real kPa is outside the plausible [{lo:g}, "
                         f"{hi:g}] (reference {REFERENCE[0]:g}): check the units of the pressures and bends")


def read_bends_csv(path: str | Path) -> tuple[np.ndarray, np.ndarray, str]:
    """``(real_kpa (k,), bend (k,), measure)`` from a CSV with header ``real_kpa,<measure>``
    (a UTF-8 byte-order mark is accepted).

    Raises:
        FileNotFoundError; ValueError: not a regular text file, bad header, a value that is not a
            finite number, a pressure outside ``(0, MAX_REAL_KPA]``, a bend <= 0, < 2 points
            (each naming the file and line).
    """
    path = Path(path)
    text = read_text(path, max_bytes=16 * 1024 * 1024)
    rows = [(i, r) for i, r in enumerate(csv.reader(text.splitlines()), start=1) if any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"{path}: empty")
    head = [c.strip() for c in rows[0][1]]
    if len(head) != 2 or head[0] != "real_kpa" or head[1] not in MEASURES:
        raise ValueError(f"{path}: header must be real_kpa,<{'|'.join(MEASURES)}>, got {','.join(head)}")
    vals = []
    for i, r in rows[1:]:
        try:
            x, y = (float(c) for c in r)
        except ValueError:
            raise ValueError(f"{path}, line {i}: expected 2 numbers, got {r!r}") from None
        check_real_kpa(x, f"{path}, line {i}")
        if not (math.isfinite(y) and y > 0):
            raise ValueError(f"{path}, line {i}: bend must be finite and > 0, got {r!r}")
        vals.append((x, y))
    if len(vals) < 2:
        raise ValueError(f"{path}: need at least 2 measurements, got {len(vals)}")
    a = np.array(vals)
    return a[:, 0], a[:, 1], head[1]


def calibrate(real_kpa, bend, measure: str = "tip_angle_deg", curve: BendCurve | None = None,
              progress: bool = False) -> CalibrationResult:
    """Match each measured bend to a sim pressure and fit the affine warp (module docstring).

    Args:
        real_kpa, bend: ``(k,)`` measured pairs (kPa; deg or mm per ``measure``), k >= 2.
        curve: the bend model (default :class:`BendCurve` with default settings).

    Raises:
        ValueError: implausible input (:func:`check_measurements`, before any simulation), a
            bend the model cannot reach, or a fitted slope outside :data:`A_RANGE`.
    """
    if measure not in MEASURES:
        raise ValueError(f"measure must be one of {MEASURES}, got {measure!r}")
    real, bend = check_measurements(real_kpa, bend)
    curve = curve or BendCurve()
    it = bend
    if progress:
        from tqdm import tqdm

        it = tqdm(bend, desc="matching bends", unit="point")
    sim = np.array([curve.find_pressure(float(b), measure) for b in it])
    cal = PressureCalibration.from_table(real, sim)
    check_slope(cal.a, "the fitted warp")
    return CalibrationResult(real, bend, sim, cal.a, cal.b, cal.a * real + cal.b - sim, measure, curve.model)


def write_calibration(result: CalibrationResult, path: str | Path, source: str = "") -> Path:
    """Write the calibration file (JSON, :func:`load_calibration` reads it), atomically."""
    path = Path(path)
    atomic_write_text(path, json.dumps(result.to_dict(source), indent=2) + "\n")
    return path


def load_calibration(path: str | Path) -> PressureCalibration:
    """Read a calibration file written by ``softcrawl calibrate`` into a :class:`PressureCalibration`.

    Raises:
        FileNotFoundError: no such file.
        ValueError: not a regular file of at most 1 MB, not JSON, nested too deeply, not a
            softcrawl calibration, a / b missing or not finite, or a slope outside
            :data:`A_RANGE` (one line naming the file).
    """
    path = Path(path)
    try:
        data = load_json(path, max_bytes=1 << 20)
    except FileNotFoundError:
        raise FileNotFoundError(f"{path}: calibration file not found") from None
    except ValueError as exc:
        raise ValueError(f"not a JSON calibration file: {one_line(exc)}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path}: not a softcrawl calibration file (format must be {FORMAT!r})")
    if data.get("version") != FORMAT_VERSION:
        raise ValueError(f"{path}: calibration format version {data.get('version')!r} is not {FORMAT_VERSION}")
    try:
        a, b = data["a"], data["b"]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in (a, b)):
            raise TypeError
        cal = PressureCalibration(float(a), float(b))
    except (KeyError, TypeError, ValueError, OverflowError):
        raise ValueError(f"{path}: calibration needs finite numbers a and b") from None
    if cal.a <= 0:
        raise ValueError(f"{path}: slope a must be > 0 (more real pressure bends more), got {cal.a}")
    check_slope(cal.a, str(path))
    return cal


def plot_calibration(result: CalibrationResult, path: str | Path) -> Path:
    """Paper-style figure: matched sim pressure vs real pressure with the fitted line (and the
    reference line), residuals below; PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(5.5, 6), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    x = np.linspace(0, max(result.real_kpa.max() * 1.05, 1), 100)
    ax.plot(result.real_kpa, result.sim_kpa, "o", label="measured bend matched in simulation")
    ax.plot(x, np.maximum(result.a * x + result.b, 0), "-",
            label=f"fit: sim = {result.a:.4f} real {result.b:+.2f}")
    ax.plot(x, np.maximum(REFERENCE[0] * x + REFERENCE[1], 0), "--", color="0.5",
            label=f"paper: sim = {REFERENCE[0]} real {REFERENCE[1]:+.2f}")
    ax.set_ylabel("simulated pressure (kPa)")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    ax.set_title(f"Pressure calibration ({result.measure})")
    ax2.axhline(0, color="0.5", lw=0.8)
    ax2.plot(result.real_kpa, result.residual_kpa, "o")
    ax2.set_xlabel("real pressure (kPa)")
    ax2.set_ylabel("residual (kPa)")
    ax2.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)
