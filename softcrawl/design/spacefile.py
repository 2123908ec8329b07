"""Design spaces as data: a TOML file describing the robot's body, leg slots, regulators and
actuator, read into a frozen :class:`DesignSpace` that carries the design algebra.

A *design* of a space with ``S`` slots and ``R`` regulators is a tuple of ``S`` integers:
``0`` = empty slot, ``k in 1..R`` = a leg driven by regulator ``k``, with between
``min_legs`` and ``max_legs`` legs (paper Sec. "Design space"; ``codesign.md``). Designs that
differ by a relabelling of the regulators (and, if the space asks for it, by the mirror
``theta -> -theta`` about the x axis) are the same robot; their *canonical* form is the
lexicographically smallest member of that class, which for relabelling alone is the
relabelling by order of first appearance (slot 0 first).

File layout (every key checked; unknown keys are refused; lengths mm, masses kg, angles
degrees about +z from +x, Young's moduli kPa)::

    name = "paper"                     # optional (default: the file's name without .toml): a label
    description = "..."                # optional
    [body]                             # the central disk, a cone frustum on the z axis
    bottom_radius_mm = 50.0
    top_radius_mm = 54.5
    height_mm = 18.0
    mesh_size_mm = 10.0                # default tet size of the disk (RobotConfig.disk_mesh_size)
    mass_kg = 0.075                    # or leave it out and give the material's density_kg_per_m3
    material = "printed_polymer"       # a known name, or { youngs_modulus_kpa = ..., poisson_ratio = ...,
                                       #                    density_kg_per_m3 = ... (optional) }
    [slots]
    count = 8
    first_angle_deg = 22.5             # equally spaced: first + 360 i / count (mod 360); or angles_deg = [...]
    [design]
    regulators = 3
    min_legs = 3
    max_legs = 6
    mirror_x = false                   # also identify designs mirrored about the x axis
    [actuator]                         # the PneuNet leg (softcrawl.geometry.pneunet)
    mesh_size_mm = 6.0
    mass_kg = 0.105
    material = "dragonskin30"
    paper_material = "paper"
    paper_thickness_mm = 1.0
    reduction = "softcrawl:pneunet_6mm.npz"   # optional; a .npz file: a path relative to this file's
                                              # folder, or softcrawl:NAME for one shipped in
                                              # softcrawl/reduction/data
    reduction_sha256 = "<64 hex digits>"      # optional (needs reduction): the file's SHA-256, 64 hex
                                              # digits; a reduction file with another is refused on loading
    [actuator.pneunet]                 # every PneuNetParams dimension except mesh_size, with _mm
    n_chambers = 9
    base_length_mm = 115.0
    ...

Bounds (both included; a value outside is refused in one line naming the file and the key,
before anything is built or enumerated): ``name`` 1 to :data:`MAX_NAME_LENGTH` characters,
letters, digits, ``_ . + -`` and inner spaces, starting with a letter or a digit (a name is
printed and is a folder's name); ``slots.count`` 1 to :data:`MAX_SLOTS`; ``design.regulators``
1 to :data:`MAX_REGULATORS`; at most :data:`MAX_RAW_DESIGNS` raw designs and at most
:data:`MAX_DESIGN_SLOTS` / ``count`` (counted, not enumerated); masses
:data:`MASS_BOUNDS_KG`; Young's moduli :data:`YOUNGS_BOUNDS_KPA`; Poisson's ratios (-1, 0.5);
densities :data:`DENSITY_BOUNDS`; the paper's thickness :data:`PAPER_THICKNESS_BOUNDS_MM`;
``n_chambers`` 1 to :data:`softcrawl.geometry.pneunet.MAX_CHAMBERS`; every other length
:data:`softcrawl.geometry.primitives.LENGTH_BOUNDS_MM`, mesh sizes
:data:`softcrawl.geometry.primitives.MESH_SIZE_BOUNDS_MM` and not finer than
:func:`softcrawl.geometry.primitives.check_mesh_cells` allows for the part.

The design algebra of the paper's space (the shipped ``paper.toml``) is what
:mod:`softcrawl.design.space` exposes as module functions.
"""

from __future__ import annotations

import hashlib
import itertools
import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field, fields
from functools import cached_property
from pathlib import Path

import numpy as np

from softcrawl.safeio import load_toml, read_bytes

#: Folder of the shipped space files (package data).
SPACES_DIR = Path(__file__).with_name("spaces")
#: Prefix of a ``reduction`` value naming a reduction shipped with softcrawl.
SHIPPED_PREFIX = "softcrawl:"
#: Materials known by name (their constants: :mod:`softcrawl.fem.materials`).
KNOWN_MATERIALS = ("dragonskin30", "paper", "printed_polymer")
#: Most slots of a space (128 legs 32 mm wide fit around a disk of the largest radius, 1 m).
MAX_SLOTS = 128
#: Most regulators of a space.
MAX_REGULATORS = 16
#: Most raw designs of a space: its designs are enumerated in memory, as tuples (2,000,000
#: designs of 8 slots: about 0.3 GB and 6 s with the canonical ones).
MAX_RAW_DESIGNS = 2_000_000
#: Most raw designs times slots of a space (a space of more than 8 slots has fewer designs).
MAX_DESIGN_SLOTS = 16_000_000
#: Longest name of a space (characters).
MAX_NAME_LENGTH = 64
#: A space's name: letters, digits, ``_ . + -`` and inner spaces, starting with a letter or a digit.
NAME_PATTERN = re.compile(r"[^\W_](?:[\w.+ -]*[\w.+-])?")
#: Bounds of a part's mass, kg (a milligram to 100 kg; the paper's leg 0.105, its disk 0.075).
MASS_BOUNDS_KG = (1e-6, 100.0)
#: Bounds of a Young's modulus, kPa (a soft gel's 1 kPa to a TPa, above steel's 2e8 kPa).
YOUNGS_BOUNDS_KPA = (1.0, 1e9)
#: Bounds of a density, kg/m^3 (a foam's 1 to osmium's 22,590).
DENSITY_BOUNDS = (1.0, 25_000.0)
#: Bounds of the paper layer's thickness, mm (the paper's 1 mm layer; printer paper is 0.1 mm).
PAPER_THICKNESS_BOUNDS_MM = (0.01, 100.0)
#: Angles closer than this (degrees) are the same slot.
ANGLE_TOL_DEG = 1e-6

#: PneuNet dimensions of ``[actuator.pneunet]`` (``softcrawl.geometry.pneunet.PneuNetParams``
#: field names; all in mm except the chamber count).
PNEUNET_KEYS = ("base_length", "base_width", "base_thickness", "block_width", "block_height", "tooth_width",
                "end_tooth_width", "tooth_gap", "tooth_height", "wall_thickness", "channel_width",
                "channel_height")
#: Disk dimensions of ``[body]`` (``softcrawl.geometry.disk.DiskParams`` field names, mm).
DISK_KEYS = ("bottom_radius", "top_radius", "height")

Design = tuple[int, ...]


class InvalidDesignError(ValueError):
    """A design is malformed: wrong length, non-integer entry, value outside {0..regulators},
    or a leg count outside [min_legs, max_legs]."""


class SpaceFileError(ValueError):
    """A design-space file is malformed or inconsistent; the message is one line naming the
    file and the key."""


@dataclass(frozen=True)
class Material:
    """A linear elastic material: a known name (:data:`KNOWN_MATERIALS`), or given values.

    Attributes:
        name: the known name, or ``""`` for a material given by its constants.
        youngs_modulus_kpa: E, kPa (None for a known name).
        poisson_ratio: nu (None for a known name).
        density_kg_per_m3: rho, kg/m^3, or None (a part made of it then needs its mass).
    """

    name: str = ""
    youngs_modulus_kpa: float | None = None
    poisson_ratio: float | None = None
    density_kg_per_m3: float | None = None


@dataclass(frozen=True)
class Part:
    """One part of the robot: geometry, default mesh size, mass and material.

    Attributes:
        params: ``(name, value)`` pairs: the geometry's dimensions, mm (``DiskParams`` or
            ``PneuNetParams`` field names without ``mesh_size``; ``n_chambers`` an int).
        mesh_size: default maximum tet size, mm.
        mass: total mass, kg; None: the material's density times the part's volume.
        material: the bulk material.
    """

    params: tuple[tuple[str, float | int], ...]
    mesh_size: float
    mass: float | None
    material: Material


@dataclass(frozen=True)
class DesignSpace:
    """A design space: which robots can be built and how they are modelled.

    Attributes:
        slot_angles_deg: ``(S,)`` slot angles, degrees about +z from +x, distinct, in [0, 360).
        n_regulators: ``R >= 1`` pressure regulators (model channels).
        min_legs, max_legs: legs per design, ``1 <= min_legs <= max_legs <= S``.
        mirror_x: designs mirrored about the x axis (slot angle ``theta -> -theta``) are the
            same design (requires a mirror-symmetric slot set).
        disk: the body (``params``: bottom_radius, top_radius, height).
        leg: the actuator (``params``: ``n_chambers`` and :data:`PNEUNET_KEYS`).
        paper_material, paper_thickness: the leg's strain-limiting layer (mm).
        reduction: the actuator's reduction file (an absolute path) or None; not compared: a
            folder's copy of the file is the same reduction (``reduction_key``).
        reduction_sha256: the SHA-256 (64 lower-case hex digits) the reduction file must have,
            or None (not checked).
        name: a label. source: the file read (not compared). sha256: its checksum (not compared).
        reduction_key: what the spaces' reductions are compared by: ``"softcrawl:NAME"`` for a
            shipped one, else ``"sha256:"`` and the SHA-256 of the file's bytes; None without one.

    Raises:
        ValueError: on construction, for counts that do not fit (no slot, no regulator, legs
            outside ``1 <= min_legs <= max_legs <= S``) or ``mirror_x`` with an asymmetric
            slot set (:func:`load_space` checks every key first and names it).
    """

    slot_angles_deg: tuple[float, ...]
    n_regulators: int
    min_legs: int
    max_legs: int
    disk: Part
    leg: Part
    paper_material: Material
    paper_thickness: float
    mirror_x: bool = False
    reduction: str | None = field(default=None, compare=False)
    name: str = ""
    source: str = field(default="", compare=False)
    sha256: str = field(default="", compare=False)
    reduction_sha256: str | None = None
    reduction_key: str | None = None

    def __post_init__(self) -> None:
        s = self.n_slots
        if not s or self.n_regulators < 1 or not 1 <= self.min_legs <= self.max_legs <= s:
            raise ValueError(f"inconsistent design space: {s} slots, {self.n_regulators} regulators, "
                             f"{self.min_legs}..{self.max_legs} legs")
        if self.mirror_x:
            _mirror_permutation(self.slot_angles_deg)

    def __getstate__(self) -> dict:
        """Pickled without the cached enumerations (robots carry their space to workers)."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    # ------------------------------------------------------------------ structure
    @property
    def n_slots(self) -> int:
        """Number of leg slots ``S``."""
        return len(self.slot_angles_deg)

    @property
    def one_hot_size(self) -> int:
        """Length of a design's one-hot code: ``S * (R + 1)`` (32 for the paper's space)."""
        return self.n_slots * (self.n_regulators + 1)

    @cached_property
    def mirror_permutation(self) -> tuple[int, ...]:
        """``S`` ints: slot ``i`` at angle ``theta`` goes to the slot at ``-theta`` (mod 360).

        Raises:
            ValueError: the slot set is not symmetric about the x axis.
        """
        return _mirror_permutation(self.slot_angles_deg)

    # ------------------------------------------------------------------ single designs
    def validate_design(self, d: Sequence[int] | str) -> Design:
        """Check a design and return it as a tuple of ``S`` ints (not canonicalised).

        Args:
            d: a sequence of ``S`` integers in ``{0..R}``, or a string such as
                ``"1,0,0,2,2,0,0,1"`` (comma- and/or whitespace-separated; brackets ignored).

        Raises:
            InvalidDesignError: naming the fault (length, non-integer entry, out-of-range value
                with its slot, or the leg count).
        """
        s, r = self.n_slots, self.n_regulators
        if isinstance(d, str):
            items: list = d.strip().strip("[]()").replace(",", " ").split()
        else:
            try:
                items = list(d)
            except TypeError:
                raise InvalidDesignError(f"design must be a sequence of {s} integers, got {d!r}") from None
        if len(items) != s:
            raise InvalidDesignError(f"design must have {s} slots, got {len(items)}: {d!r}")
        out = []
        for slot, v in enumerate(items):
            iv = _as_int(v)
            if iv is None:
                raise InvalidDesignError(f"slot {slot}: {v!r} is not an integer")
            if not 0 <= iv <= r:
                raise InvalidDesignError(f"slot {slot}: value {iv} not in {{0..{r}}} (0 = empty, k = regulator k)")
            out.append(iv)
        legs = sum(v > 0 for v in out)
        if not self.min_legs <= legs <= self.max_legs:
            which = "too few" if legs < self.min_legs else "too many"
            raise InvalidDesignError(f"{which} legs: {legs} (allowed {self.min_legs} to {self.max_legs})")
        return tuple(out)

    def canonicalize(self, d: Sequence[int] | str) -> Design:
        """The canonical form of ``d``: regulators relabelled by first appearance (slot 0
        first), and with :attr:`mirror_x` the smaller of that and the relabelled mirror image.
        E.g. ``(2,0,0,1,1,0,0,2) -> (1,0,0,2,2,0,0,1)`` in the paper's space.

        Raises:
            InvalidDesignError: if ``d`` is not a valid design.
        """
        return self._canonical(self.validate_design(d))

    def is_canonical(self, d: Sequence[int] | str) -> bool:
        """Whether ``d`` equals its canonical form. Raises InvalidDesignError if invalid."""
        d = self.validate_design(d)
        return self._canonical(d) == d

    def n_legs(self, d: Sequence[int] | str) -> int:
        """Number of occupied slots. Raises InvalidDesignError if invalid."""
        return sum(v > 0 for v in self.validate_design(d))

    def regulator_groups(self, d: Sequence[int] | str) -> dict[int, list[int]]:
        """Map each regulator used by ``d`` to its slot indices (ascending), e.g.
        ``(1,0,0,2,2,0,0,1) -> {1: [0, 7], 2: [3, 4]}``. Raises InvalidDesignError if invalid."""
        groups: dict[int, list[int]] = {}
        for slot, v in enumerate(self.validate_design(d)):
            if v:
                groups.setdefault(v, []).append(slot)
        return dict(sorted(groups.items()))

    # ------------------------------------------------------------------ enumeration
    @property
    def n_raw_designs(self) -> int:
        """``sum_{k=min..max} C(S, k) R^k`` (41,202 for the paper's space), without enumerating."""
        return _raw_count(self.n_slots, self.n_regulators, self.min_legs, self.max_legs)

    @cached_property
    def raw_designs(self) -> tuple[Design, ...]:
        """All valid designs, lexicographically sorted: for each leg count its slot sets, then
        their regulators, so the work is proportional to the number of designs (not to the
        ``(R + 1)^S`` slot-value combinations)."""
        s, r = self.n_slots, self.n_regulators
        designs = []
        for k in range(self.min_legs, self.max_legs + 1):
            for slots in itertools.combinations(range(s), k):
                for values in itertools.product(range(1, r + 1), repeat=k):
                    d = [0] * s
                    for slot, v in zip(slots, values):
                        d[slot] = v
                    designs.append(tuple(d))
        designs.sort()
        return tuple(designs)

    @cached_property
    def canonical_designs(self) -> tuple[Design, ...]:
        """All canonical designs (6,972 for the paper's space), lexicographically sorted."""
        return tuple(d for d in self.raw_designs if self._canonical(d) == d)

    @cached_property
    def canonical_array(self) -> np.ndarray:
        """The canonical designs as a read-only ``(n, S)`` int8 array (row i = index i)."""
        arr = np.array(self.canonical_designs, dtype=np.int8).reshape(-1, self.n_slots)
        arr.setflags(write=False)
        return arr

    @cached_property
    def _index_map(self) -> dict[Design, int]:
        return {d: i for i, d in enumerate(self.canonical_designs)}

    def design_index(self, d: Sequence[int] | str) -> int:
        """Index of ``canonicalize(d)`` in :attr:`canonical_designs`.

        Raises:
            InvalidDesignError: if ``d`` is not a valid design.
        """
        return self._index_map[self.canonicalize(d)]

    def design_from_index(self, i: int) -> Design:
        """The canonical design with index ``i`` (``0 <= i < len(canonical_designs)``).

        Raises:
            IndexError: if ``i`` is out of range (negative indices are rejected too).
        """
        designs = self.canonical_designs
        if not 0 <= int(i) < len(designs):
            raise IndexError(f"design index {i} out of range [0, {len(designs)})")
        return designs[int(i)]

    def part_record(self, leg_mesh_size: float | None = None, disk_mesh_size: float | None = None) -> dict:
        """What a reduction of this space's parts is built for: a JSON-able record that
        :func:`softcrawl.reduction.artifact.save_reduction` stores and
        :func:`~softcrawl.reduction.artifact.load_reduction` compares (reduction.md, "Reducing
        your own part").

        Args:
            leg_mesh_size, disk_mesh_size: the tet sizes in use, mm (default: the parts' own).

        Returns:
            ``{"leg": {"params": {PneuNet dimensions (mm), "n_chambers", "mesh_size"},
            "material": {...}, "paper_material": {...}, "paper_thickness": mm}, "disk":
            {"params": {disk dimensions (mm), "mesh_size"}, "material": {...}}}``; a material is
            ``{"name", "youngs_modulus_kpa", "poisson_ratio", "density_kg_per_m3"}`` (kPa,
            kg/m^3; a known name leaves the constants None). Masses are not in it: the
            reduction's ``valid_for`` holds them.
        """
        def params(part: Part, mesh_size: float | None) -> dict:
            return {**dict(part.params), "mesh_size": float(mesh_size if mesh_size is not None else part.mesh_size)}

        return {"leg": {"params": params(self.leg, leg_mesh_size), "material": asdict(self.leg.material),
                        "paper_material": asdict(self.paper_material), "paper_thickness": self.paper_thickness},
                "disk": {"params": params(self.disk, disk_mesh_size), "material": asdict(self.disk.material)}}

    def one_hot_batch(self, designs: Iterable[Sequence[int] | str] | np.ndarray) -> np.ndarray:
        """One-hot codes, ``(n, S * (R + 1))`` float32: ``S`` slot-major blocks of length
        ``R + 1`` (value 0..R). Designs are encoded as given (not canonicalised).

        Raises:
            InvalidDesignError: if any design is invalid.
        """
        s, r = self.n_slots, self.n_regulators
        if isinstance(designs, np.ndarray) and designs.ndim == 2:
            designs = designs.tolist()
        rows = np.array([self.validate_design(d) for d in designs], dtype=np.int64).reshape(-1, s)
        out = np.zeros((len(rows), s, r + 1), dtype=np.float32)
        out[np.arange(len(rows))[:, None], np.arange(s)[None, :], rows] = 1.0
        return out.reshape(len(rows), s * (r + 1))

    def _canonical(self, d: Design) -> Design:
        """Canonical form of a valid design (see :meth:`canonicalize`)."""
        canonical = _relabel(d)
        if self.mirror_x:
            canonical = min(canonical, _relabel(tuple(d[i] for i in self.mirror_permutation)))
        return canonical


def _mirror_permutation(angles_deg: Sequence[float]) -> tuple[int, ...]:
    """``S`` ints: the slot at ``-theta`` (mod 360) for each slot at ``theta`` (degrees).

    Raises:
        ValueError: a slot has no mirror image within :data:`ANGLE_TOL_DEG`.
    """
    angles = np.asarray(angles_deg, dtype=float)
    diff = np.abs(np.mod(-angles, 360.0)[:, None] - angles[None, :])
    diff = np.minimum(diff, 360.0 - diff)
    perm = diff.argmin(axis=1)
    bad = diff[np.arange(len(angles)), perm] > ANGLE_TOL_DEG
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(f"mirror symmetry needs the slot at {-angles[i] % 360:g} deg, the mirror of slot {i} "
                         f"at {angles[i]:g} deg")
    return tuple(perm.tolist())


def _relabel(d: Design) -> Design:
    """Regulators relabelled by order of first appearance (slot 0 first): the smallest design
    among all relabellings of ``d``."""
    relabel: dict[int, int] = {0: 0}
    for v in d:
        if v not in relabel:
            relabel[v] = len(relabel)
    return tuple(relabel[v] for v in d)


def _shown(value: object, limit: int = 80) -> str:
    """``value`` for an error line: its ``repr`` (control and format characters escaped, so
    nothing from a file reaches the terminal raw), cut to ``limit`` characters."""
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def _raw_count(s: int, r: int, lo: int, hi: int) -> int:
    return sum(math.comb(s, k) * r**k for k in range(lo, hi + 1))


def _as_int(v: object) -> int | None:
    """``v`` as an int if it is an integer (int, numpy integer, integral float, digit string)."""
    if isinstance(v, (bool, np.bool_)):
        return None
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)):
        return int(v) if float(v).is_integer() else None
    if isinstance(v, str):
        try:
            return int(v)
        except ValueError:
            return None
    return None


# ---------------------------------------------------------------------- reading a file
_TOP_KEYS = ("name", "description", "body", "slots", "design", "actuator")
_BODY_KEYS = tuple(f"{k}_mm" for k in DISK_KEYS) + ("mesh_size_mm", "mass_kg", "material")
_SLOTS_KEYS = ("count", "first_angle_deg", "angles_deg")
_DESIGN_KEYS = ("regulators", "min_legs", "max_legs", "mirror_x")
_ACTUATOR_KEYS = ("mesh_size_mm", "mass_kg", "material", "paper_material", "paper_thickness_mm", "reduction",
                  "reduction_sha256", "pneunet")
#: A SHA-256 checksum as written in a space file: 64 hex digits.
_SHA256_DIGITS = 64
_PNEUNET_KEYS = ("n_chambers",) + tuple(f"{k}_mm" for k in PNEUNET_KEYS)
_MATERIAL_KEYS = ("youngs_modulus_kpa", "poisson_ratio", "density_kg_per_m3")


class _Reader:
    """Checked access to the parsed TOML document of ``path``: every error is one
    :class:`SpaceFileError` line ``"<path>: <key>: <what is wrong>"``."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, key: str, message: str) -> SpaceFileError:
        return SpaceFileError(f"{self.path}: {key}: {message}")

    def table(self, doc: dict, key: str, where: str, allowed: Sequence[str], required: bool = True) -> dict | None:
        name = f"{where}.{key}" if where else key
        if key not in doc:
            if required:
                raise self.fail(name, "missing table")
            return None
        tbl = doc[key]
        if not isinstance(tbl, dict):
            raise self.fail(name, f"must be a table, got {type(tbl).__name__}")
        self.known(tbl, name, allowed)
        return tbl

    def known(self, tbl: dict, where: str, allowed: Sequence[str]) -> None:
        for k in tbl:
            if k not in allowed:
                shown = k if re.fullmatch(r"[A-Za-z0-9_-]{1,40}", k) else _shown(k)  # a bare TOML key as it is
                raise self.fail(f"{where}.{shown}" if where else shown, f"unknown key (allowed: {', '.join(allowed)})")

    def real(self, tbl: dict, key: str, where: str) -> float:
        """A number (an int or a float, not a bool), as a float; its range not checked."""
        v = self.value(tbl, key, where)
        if isinstance(v, bool) or not isinstance(v, (int, float)):
            raise self.fail(f"{where}.{key}", f"must be a number, got {_shown(v)}")
        return float(v)

    def number(self, tbl: dict, key: str, where: str, lo: float = 0.0, hi: float = math.inf,
               lo_open: bool = True, hi_open: bool = False) -> float:
        v = self.real(tbl, key, where)
        ok = (v > lo if lo_open else v >= lo) and (v < hi if hi_open else v <= hi) and math.isfinite(v)
        if not ok:
            interval = f"{'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open or hi == math.inf else ']'}"
            raise self.fail(f"{where}.{key}", f"must lie in {interval}, got {v:g}")
        return v

    def integer(self, tbl: dict, key: str, where: str, lo: int | None, hi: int | None = None) -> int:
        """An integer within ``[lo, hi]`` (``hi`` None: at least ``lo``; both None: any)."""
        v = self.value(tbl, key, where)
        if isinstance(v, bool) or not isinstance(v, int):
            raise self.fail(f"{where}.{key}", f"must be an integer, got {_shown(v)}")
        if lo is not None and hi is None and v < lo:
            raise self.fail(f"{where}.{key}", f"must be >= {lo}, got {v}")
        if hi is not None and not lo <= v <= hi:
            raise self.fail(f"{where}.{key}", f"must lie in [{lo}, {hi}], got {v}")
        return v

    def name(self, doc: dict) -> str:
        """``name``, or the file's name without its suffix; either must match
        :data:`NAME_PATTERN` in at most :data:`MAX_NAME_LENGTH` characters (printable, one
        line, a folder's name)."""
        name = self.text(doc, "name", "")
        given = name is not None
        name = name if given else self.path.stem
        if len(name) > MAX_NAME_LENGTH or not NAME_PATTERN.fullmatch(name):
            rule = (f"1 to {MAX_NAME_LENGTH} characters: letters, digits, '_', '.', '+', '-' and inner spaces, "
                    "starting with a letter or a digit")
            raise self.fail("name", f"{_shown(name)} is not a name ({rule})" if given else
                            f"missing, and the file's name {_shown(name)} is not a name ({rule}); give name = \"...\"")
        return name

    def text(self, tbl: dict, key: str, where: str, default: str | None = None) -> str | None:
        if key not in tbl:
            return default
        v = tbl[key]
        if not isinstance(v, str):
            raise self.fail(f"{where}.{key}" if where else key, f"must be a string, got {_shown(v)}")
        return v

    def value(self, tbl: dict, key: str, where: str):
        if key not in tbl:
            raise self.fail(f"{where}.{key}", "missing")
        return tbl[key]

    def material(self, tbl: dict, key: str, where: str) -> Material:
        """A known material's name, or a table of its constants within :data:`YOUNGS_BOUNDS_KPA`,
        (-1, 0.5) and :data:`DENSITY_BOUNDS`."""
        v = self.value(tbl, key, where)
        name = f"{where}.{key}"
        if isinstance(v, str):
            if v not in KNOWN_MATERIALS:
                raise self.fail(name, f"unknown material {_shown(v)} (known: {', '.join(KNOWN_MATERIALS)}; or give "
                                      f"{{ youngs_modulus_kpa = ..., poisson_ratio = ... }})")
            return Material(v)
        if not isinstance(v, dict):
            raise self.fail(name, f"must be a material name or a table, got {_shown(v)}")
        self.known(v, name, _MATERIAL_KEYS)
        density = self.number(v, "density_kg_per_m3", name, *DENSITY_BOUNDS, lo_open=False) \
            if "density_kg_per_m3" in v else None
        return Material("", self.number(v, "youngs_modulus_kpa", name, *YOUNGS_BOUNDS_KPA, lo_open=False),
                        self.number(v, "poisson_ratio", name, -1.0, 0.5, hi_open=True), density)

    def part(self, tbl: dict, where: str, params: tuple, mesh_size: float) -> Part:
        """A part with its ``mass_kg`` or, failing that, its material's density (exactly one)."""
        material = self.material(tbl, "material", where)
        has_density = material.density_kg_per_m3 is not None
        if ("mass_kg" in tbl) == has_density:
            why = "give it or the material's density_kg_per_m3" if not has_density else \
                "give either it or the material's density_kg_per_m3, not both"
            raise self.fail(f"{where}.mass_kg", f"{'missing' if not has_density else 'twice'}: {why}")
        mass = None if has_density else self.number(tbl, "mass_kg", where, *MASS_BOUNDS_KG, lo_open=False)
        return Part(params, mesh_size, mass, material)

    def dims(self, tbl: dict, where: str, dims: Sequence[str], ints: Sequence[str] = ()) -> tuple:
        """``(name, value)`` pairs of a part's integer counts and its dimensions ``<name>_mm``
        (their bounds are the geometry's: :meth:`geometry`)."""
        params = tuple((k, self.integer(tbl, k, where, None)) for k in ints)
        params += tuple((k, self.real(tbl, f"{k}_mm", where)) for k in dims)
        return params

    def slot_angles(self, tbl: dict) -> tuple[float, ...]:
        count = self.integer(tbl, "count", "slots", 1, MAX_SLOTS)  # bounded before the angles are built
        if ("angles_deg" in tbl) == ("first_angle_deg" in tbl):
            raise self.fail("slots", "give exactly one of first_angle_deg (equally spaced) and angles_deg")
        if "first_angle_deg" in tbl:
            first = self.number(tbl, "first_angle_deg", "slots", 0.0, 360.0, lo_open=False, hi_open=True)
            return tuple((first + 360.0 / count * i) % 360.0 for i in range(count))
        angles = tbl["angles_deg"]
        if not isinstance(angles, list) or len(angles) != count:
            got = f"{len(angles)} of them" if isinstance(angles, list) else _shown(angles)
            raise self.fail("slots.angles_deg", f"must be a list of count = {count} angles, got {got}")
        box = {f"[{i}]": a for i, a in enumerate(angles)}
        out = tuple(self.number(box, f"[{i}]", "slots.angles_deg", 0.0, 360.0, lo_open=False, hi_open=True)
                    for i in range(count))
        gap = np.abs(np.subtract.outer(out, out))
        gap = np.minimum(gap, 360.0 - gap) + np.eye(count) * 360.0
        if gap.min() <= ANGLE_TOL_DEG:
            i, j = np.unravel_index(gap.argmin(), gap.shape)
            raise self.fail("slots.angles_deg", f"slots {i} and {j} have the same angle {out[i]:g}")
        return out

    def reduction(self, tbl: dict) -> tuple[str | None, str | None]:
        """``(path, key)`` of the reduction (:attr:`DesignSpace.reduction`,
        :attr:`DesignSpace.reduction_key`), ``(None, None)`` without one. A file's path is
        taken relative to the space file's folder and made absolute; the file must be a
        regular file and a ``.npz`` (a zip archive); its bytes give the key."""
        ref = self.text(tbl, "reduction", "actuator")
        if ref is None:
            return None, None
        if not ref.endswith(".npz"):
            raise self.fail("actuator.reduction", f"{_shown(ref)} is not a .npz reduction file (`softcrawl reduce "
                                                  "build` writes one)")
        if ref.startswith(SHIPPED_PREFIX):  # checked when loaded: a missing one must not stop the import
            from softcrawl.reduction.data import default_reduction_path

            name = ref[len(SHIPPED_PREFIX):]
            if Path(name).name != name:
                raise self.fail("actuator.reduction", f"{_shown(ref)}: a shipped reduction is a file name, without a "
                                                      "folder")
            return str(default_reduction_path().parent / name), ref
        path = (self.path.parent / ref).absolute()
        try:
            data = read_bytes(path)
        except FileNotFoundError:
            raise self.fail("actuator.reduction", f"no such file {_shown(str(path), 300)}") from None
        except (OSError, ValueError) as exc:  # safeio's message: "<path>: <why>"
            why = " ".join(str(exc).removeprefix(f"{path}: ").split())
            raise self.fail("actuator.reduction", f"{_shown(str(path), 300)}: {why}") from None
        if not data.startswith((b"PK\x03\x04", b"PK\x05\x06")):
            raise self.fail("actuator.reduction", f"{_shown(str(path), 300)} is not a reduction file (a .npz is a zip "
                                                  "archive; `softcrawl reduce build` writes one)")
        return str(path), "sha256:" + hashlib.sha256(data).hexdigest()

    def geometry(self, disk: Part, leg: Part) -> None:
        """The parts' dimensions and mesh sizes as the geometry takes them
        (``softcrawl.geometry.disk.DiskParams``, ``softcrawl.geometry.pneunet.PneuNetParams``:
        bounds, a mesh not too fine, PneuNet dimensions that fit; imports gmsh); an error names
        the key of a field out of its bounds."""
        from softcrawl.geometry.disk import DiskParams
        from softcrawl.geometry.pneunet import PneuNetParams

        for cls, part, where, mesh_where in ((DiskParams, disk, "body", "body"),
                                             (PneuNetParams, leg, "actuator.pneunet", "actuator")):
            try:
                cls(**dict(part.params), mesh_size=part.mesh_size)
            except ValueError as exc:
                msg = str(exc).split(f": {cls.__name__}(")[0]
                field_name, _, rest = msg.partition(" must lie in ")
                if not rest:
                    raise self.fail(where, msg) from None
                key = (f"{mesh_where}.mesh_size_mm" if field_name == "mesh_size" else
                       f"{where}.{field_name}" + ("" if field_name == "n_chambers" else "_mm"))
                raise self.fail(key, f"must lie in {rest}") from None

    def reduction_sha256(self, tbl: dict) -> str | None:
        """``reduction_sha256`` lower-cased: 64 hex digits, and only beside ``reduction``."""
        digest = self.text(tbl, "reduction_sha256", "actuator")
        if digest is None:
            return None
        if "reduction" not in tbl:
            raise self.fail("actuator.reduction_sha256", "given without a reduction")
        if len(digest) != _SHA256_DIGITS or any(c not in "0123456789abcdefABCDEF" for c in digest):
            raise self.fail("actuator.reduction_sha256", f"must be {_SHA256_DIGITS} hex digits, got {_shown(digest)}")
        return digest.lower()


def load_space(path: str | Path, check_geometry: bool = True) -> DesignSpace:
    """Read a design-space file (format: module docstring) with :func:`softcrawl.safeio.load_toml`.

    Args:
        path: the TOML file.
        check_geometry: also check the parts' dimensions and mesh sizes as the geometry takes
            them: bounds, a mesh not too fine, PneuNet dimensions that fit together
            (``softcrawl.geometry.disk.DiskParams``, ``softcrawl.geometry.pneunet.PneuNetParams``;
            imports gmsh).

    Returns:
        The :class:`DesignSpace` (``source`` = the path, ``sha256`` = the file's checksum).

    Raises:
        FileNotFoundError: no such file.
        SpaceFileError: (a ValueError) one line naming the file and the key: not a regular
            file or not TOML, an unknown or missing key, a wrong type, a value out of range, or
            an inconsistent space (legs and slots, an asymmetric slot set with ``mirror_x``,
            too many designs to enumerate, part dimensions that do not fit).
    """
    path = Path(path)
    try:
        data = read_bytes(path)
        doc = load_toml(path)
    except ValueError as exc:
        raise SpaceFileError(" ".join(str(exc).split())) from None
    r = _Reader(path)
    r.known(doc, "", _TOP_KEYS)
    name = r.name(doc)
    r.text(doc, "description", "")
    body = r.table(doc, "body", "", _BODY_KEYS)
    slots = r.table(doc, "slots", "", _SLOTS_KEYS)
    design = r.table(doc, "design", "", _DESIGN_KEYS)
    act = r.table(doc, "actuator", "", _ACTUATOR_KEYS)
    pneu = r.table(act, "pneunet", "actuator", _PNEUNET_KEYS)

    angles = r.slot_angles(slots)
    regulators = r.integer(design, "regulators", "design", 1, MAX_REGULATORS)
    min_legs = r.integer(design, "min_legs", "design", 1)
    max_legs = r.integer(design, "max_legs", "design", 1)
    if min_legs > max_legs:
        raise r.fail("design.min_legs", f"{min_legs} is more than max_legs = {max_legs}")
    if max_legs > len(angles):
        raise r.fail("design.max_legs", f"{max_legs} is more than the {len(angles)} slots")
    mirror = design.get("mirror_x", False)
    if not isinstance(mirror, bool):
        raise r.fail("design.mirror_x", f"must be true or false, got {_shown(mirror)}")
    n_raw = _raw_count(len(angles), regulators, min_legs, max_legs)  # counted, not enumerated
    most = min(MAX_RAW_DESIGNS, MAX_DESIGN_SLOTS // len(angles))
    if n_raw > most:
        raise r.fail("design", f"{n_raw} raw designs, more than the {most} of {len(angles)} slots that can be "
                               "enumerated")

    disk = r.part(body, "body", r.dims(body, "body", DISK_KEYS), r.real(body, "mesh_size_mm", "body"))
    leg = r.part(act, "actuator", r.dims(pneu, "actuator.pneunet", PNEUNET_KEYS, ints=("n_chambers",)),
                 r.real(act, "mesh_size_mm", "actuator"))
    paper = r.material(act, "paper_material", "actuator")
    paper_thickness = r.number(act, "paper_thickness_mm", "actuator", *PAPER_THICKNESS_BOUNDS_MM, lo_open=False)
    if check_geometry:
        r.geometry(disk, leg)
    reduction, reduction_key = r.reduction(act)
    reduction_sha256 = r.reduction_sha256(act)
    try:
        space = DesignSpace(angles, regulators, min_legs, max_legs, disk, leg, paper, paper_thickness, mirror,
                            reduction, name, str(path), hashlib.sha256(data).hexdigest(), reduction_sha256,
                            reduction_key)
    except ValueError as exc:  # the counts are checked above: the mirror image of an asymmetric slot set
        raise r.fail("design.mirror_x", str(exc)) from None
    return space


def shipped_space_path(name: str) -> Path:
    """Path of a shipped space file (``"paper"``, ``"hex6"``).

    Raises:
        FileNotFoundError: no shipped space of that name.
    """
    path = SPACES_DIR / f"{name}.toml"
    if not path.is_file():
        known = ", ".join(sorted(p.stem for p in SPACES_DIR.glob("*.toml")))
        raise FileNotFoundError(f"no shipped design space {name!r} (shipped: {known})")
    return path
