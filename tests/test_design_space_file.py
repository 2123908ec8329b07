"""Design spaces read from TOML files: the shipped paper space equals the old constants, the
algebra of other spaces (hand-counted, mirror symmetry), every malformed-file error, the
6-slot example's robot, and ``softcrawl designs --space``."""

from __future__ import annotations

import dataclasses
import itertools
import math
import os
import pickle
import re
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from softcrawl import cli
from softcrawl.design import space as default
from softcrawl.design.resolve import resolve_space
from softcrawl.envs.crawler import BuildRobot, CrawlerEnv
from softcrawl.design.spacefile import (
    InvalidDesignError,
    SpaceFileError,
    load_space,
    shipped_space_path,
)
from softcrawl.fem.materials import DRAGONSKIN_30, PAPER, PRINTED_POLYMER
from softcrawl.geometry.disk import DiskParams
from softcrawl.geometry.pneunet import PneuNetParams
from softcrawl.reduction.data import default_reduction_path
from softcrawl.robot import NO_SETTLING, Episode
from softcrawl.robot.domain import DomainRanges
from softcrawl.robot.assembly import RobotConfig, build_robot, disk_params, material, pneunet_params

PAPER_TOML = shipped_space_path("paper")
#: SHA-256 of the shipped paper reduction (``pneunet_6mm.npz``), as paper.toml names it.
SHIPPED_SHA256 = "1779cfb179a167c019356494192f9be3ed4e94e1fcb10e5979263eb8e7d7b847"
HEX6_TOML = shipped_space_path("hex6")


def _small(tmp_path: Path, mirror: bool, angles: str = "first_angle_deg = 45.0") -> Path:
    """A 4-slot space (45, 135, 225, 315 deg), 2 regulators, 1..2 legs (the paper's parts)."""
    text = PAPER_TOML.read_text()
    text = text.replace("count = 8\nfirst_angle_deg = 22.5", f"count = 4\n{angles}")
    text = text.replace("regulators = 3\nmin_legs = 3\nmax_legs = 6\nmirror_x = false",
                        f"regulators = 2\nmin_legs = 1\nmax_legs = 2\nmirror_x = {str(mirror).lower()}")
    path = tmp_path / "small.toml"
    path.write_text(text)
    return path


# ---------------------------------------------------------------------- the paper's space
def test_default_space_is_the_shipped_file_with_the_old_constants():
    space = load_space(PAPER_TOML)  # with the PneuNet geometry check
    assert space == default.DEFAULT_SPACE
    assert space.slot_angles_deg == tuple(22.5 + 45.0 * i for i in range(8)) == default.SLOT_ANGLES_DEG
    assert (space.n_slots, space.n_regulators, space.min_legs, space.max_legs) == (8, 3, 3, 6)
    assert not space.mirror_x and space.one_hot_size == 32
    assert space.n_raw_designs == len(space.raw_designs) == 41_202
    assert len(space.canonical_designs) == 6_972
    assert space.canonical_designs == default.canonical_designs()
    assert default.canonical_designs() is default.canonical_designs()
    assert re.fullmatch(r"[0-9a-f]{64}", space.sha256) and space.source == str(PAPER_TOML)
    # robots carry their space to worker processes: pickled without the enumerations (~1 kB)
    copy = pickle.loads(pickle.dumps(space))
    assert len(pickle.dumps(space)) < 4_000 and copy == space and copy.sha256 == space.sha256
    assert copy.canonical_designs == space.canonical_designs


def test_default_space_parts_are_the_robots_defaults():
    space = default.DEFAULT_SPACE
    assert RobotConfig.for_space(space) == RobotConfig()
    assert pneunet_params(space, 6.0) == PneuNetParams(mesh_size=6.0)
    assert disk_params(space, space.disk.mesh_size) == DiskParams()
    assert material(space.leg.material) is DRAGONSKIN_30 and material(space.paper_material) is PAPER
    assert material(space.disk.material) is PRINTED_POLYMER and space.paper_thickness == 1.0
    assert Path(space.reduction) == default_reduction_path()


def test_default_canonical_forms_are_the_smallest_relabellings():
    """First-appearance relabelling gives the smallest design over all 3! regulator
    permutations, on every raw design (brute force, independent of the algebra)."""
    space = default.DEFAULT_SPACE
    assert set(space.canonical_designs) == _orbit_representatives(space)


# ---------------------------------------------------------------------- other spaces
def test_small_space_hand_counted(tmp_path):
    """4 slots at 45, 135, 225, 315 deg, 2 regulators, 1..2 legs.

    Raw: 1 leg: 4 slots x 2 regulators = 8; 2 legs: C(4,2) = 6 slot pairs x 2^2 = 24; 32 in all.
    Canonical (relabelling only): 1 leg: 4 (the leg on regulator 1); 2 legs: 6 pairs x
    {same regulator (1,1), different (1,2)} = 12; 16 in all.
    With mirror symmetry (45 <-> 315: slots 0 <-> 3, 135 <-> 225: 1 <-> 2): 1 leg: slot orbits
    {0,3}, {1,2}: 2; 2 legs: pair orbits {01,23}, {02,13}, {03}, {12} = 4, each with the legs
    on the same or on different regulators (for {03} and {12} the mirror swaps the two legs,
    which a relabelling undoes): 8; 10 in all.
    """
    plain = load_space(_small(tmp_path, mirror=False))
    assert plain.n_raw_designs == len(plain.raw_designs) == 32
    assert len(plain.canonical_designs) == 16
    assert plain.one_hot_size == 12
    mirrored = load_space(_small(tmp_path, mirror=True))
    assert len(mirrored.raw_designs) == 32 and len(mirrored.canonical_designs) == 10
    assert mirrored.mirror_permutation == (3, 2, 1, 0)
    assert mirrored.canonicalize((2, 0, 0, 0)) == (0, 0, 0, 1)  # slot 0 mirrored to slot 3, relabelled
    assert mirrored.canonicalize((1, 0, 2, 0)) == (0, 1, 0, 2)  # {0,2} -> {3,1}, relabelled
    assert plain.canonicalize((2, 0, 0, 0)) == (1, 0, 0, 0)


def _orbit_representatives(space) -> set:
    """Canonical forms by brute force: the smallest design over all regulator permutations
    (and the mirror), independent of the vectorised code."""
    perms = list(itertools.permutations(range(1, space.n_regulators + 1)))
    flips = [range(space.n_slots)] + ([space.mirror_permutation] if space.mirror_x else [])
    out = set()
    for d in space.raw_designs:
        images = [tuple(([0, *p])[d[i]] for i in flip) for p in perms for flip in flips]
        out.add(min(images))
    return out


def test_hex6_example_counts_match_brute_force():
    space = load_space(HEX6_TOML)
    assert (space.n_slots, space.n_regulators, space.min_legs, space.max_legs, space.mirror_x) == (6, 2, 2, 4, True)
    assert space.slot_angles_deg == (30.0, 90.0, 150.0, 210.0, 270.0, 330.0)
    assert len(space.raw_designs) == 460  # C(6,2) 4 + C(6,3) 8 + C(6,4) 16
    assert set(space.canonical_designs) == _orbit_representatives(space)
    assert len(space.canonical_designs) == 124
    unmirrored = dataclasses.replace(space, mirror_x=False)
    assert len(unmirrored.canonical_designs) == 230  # per k legs C(6,k) 2^(k-1): 30 + 80 + 120
    assert set(unmirrored.canonical_designs) == _orbit_representatives(unmirrored)
    assert space.one_hot_batch([(1, 0, 2, 0, 0, 0)]).shape == (1, 18)
    assert space.design_index((0, 0, 0, 0, 2, 2)) == 0
    with pytest.raises(InvalidDesignError, match="not in"):
        space.validate_design((3, 0, 1, 0, 0, 0))


def test_equally_spaced_angles_wrap_around(tmp_path):
    space = load_space(_small(tmp_path, mirror=True, angles="first_angle_deg = 315.0"))
    assert space.slot_angles_deg == (315.0, 45.0, 135.0, 225.0)
    assert space.mirror_permutation == (1, 0, 3, 2)


def test_mirror_of_an_asymmetric_slot_set_is_refused(tmp_path):
    path = _small(tmp_path, mirror=True, angles="angles_deg = [0.0, 100.0, 200.0, 300.0]")
    with pytest.raises(SpaceFileError, match=r"design\.mirror_x: mirror symmetry needs the slot at 260 deg"):
        load_space(path)


# ---------------------------------------------------------------------- malformed files
MALFORMED = [
    ("count = 8\n", "count = 8\ncolour = 1\n", r"slots\.colour: unknown key"),
    ('name = "paper"', 'name = "paper"\nextra = 1', r"extra: unknown key"),
    ("regulators = 3", "regulators = 0", r"design\.regulators: must lie in \[1, 16\], got 0"),
    ("regulators = 3", "regulators = 2.5", r"design\.regulators: must be an integer"),
    ("min_legs = 3", "min_legs = 7", r"design\.min_legs: 7 is more than max_legs = 6"),
    ("max_legs = 6", "max_legs = 9", r"design\.max_legs: 9 is more than the 8 slots"),
    ("mirror_x = false", 'mirror_x = "no"', r"design\.mirror_x: must be true or false"),
    ("first_angle_deg = 22.5", "first_angle_deg = 360.0", r"slots\.first_angle_deg: must lie in \[0, 360\)"),
    ("first_angle_deg = 22.5", "angles_deg = [0.0, 45.0]", r"slots\.angles_deg: must be a list of count = 8"),
    ("first_angle_deg = 22.5", "angles_deg = [0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 360.0]",
     r"slots\.angles_deg\.\[7\]: must lie in \[0, 360\)"),
    ("first_angle_deg = 22.5", "angles_deg = [0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 45.0]",
     r"slots\.angles_deg: slots 1 and 7 have the same angle 45"),
    ("first_angle_deg = 22.5", "first_angle_deg = 22.5\nangles_deg = []", r"slots: give exactly one of"),
    ("mass_kg = 0.075", "mass_kg = -1.0", r"body\.mass_kg: must lie in \[1e-06, 100\], got -1"),
    ("height_mm = 18.0\n", "", r"body\.height_mm: missing"),
    ('material = "printed_polymer"', 'material = "steel"', r"body\.material: unknown material 'steel'"),
    ('material = "printed_polymer"', "material = { youngs_modulus_kpa = 5000.0, poisson_ratio = 0.5 }",
     r"body\.material\.poisson_ratio: must lie in \(-1, 0\.5\)"),
    ('material = "printed_polymer"', "material = { youngs_modulus_kpa = 5000.0, density = 1.0 }",
     r"body\.material\.density: unknown key"),
    ('mass_kg = 0.105\nmaterial = "dragonskin30"', 'material = "dragonskin30"',
     r"actuator\.mass_kg: missing: give it or the material's density_kg_per_m3"),
    ('material = "dragonskin30"', "material = { youngs_modulus_kpa = 1160.0, poisson_ratio = 0.2, "
     "density_kg_per_m3 = 1080.0 }", r"actuator\.mass_kg: twice: give either it or the material's density"),
    ('material = "dragonskin30"', "material = { youngs_modulus_kpa = 1160.0, poisson_ratio = 0.2, "
     "density_kg_per_m3 = 0.0 }", r"actuator\.material\.density_kg_per_m3: must lie in \[1, 25000\], got 0"),
    ("n_chambers = 9", "n_chambers = 0", r"actuator\.pneunet\.n_chambers: must lie in \[1, 100\], got 0$"),
    ("wall_thickness_mm = 3.0", "wall_thickness_mm = 4.0",
     r"actuator\.pneunet: chambers must have positive size \(wall_thickness too large\)$"),
    ("base_length_mm = 115.0", "base_length_mm = 100.0",
     r"actuator\.pneunet: base must be at least as long and wide as the block$"),
    ('reduction = "softcrawl:pneunet_6mm.npz"', 'reduction = "missing.npz"', r"actuator\.reduction: no such file"),
    (f'reduction_sha256 = "{SHIPPED_SHA256}"', f'reduction_sha256 = "{SHIPPED_SHA256[:63]}"',
     r"actuator\.reduction_sha256: must be 64 hex digits, got '1779c"),
    (f'reduction_sha256 = "{SHIPPED_SHA256}"', f'reduction_sha256 = "{SHIPPED_SHA256[:63]}g"',
     r"actuator\.reduction_sha256: must be 64 hex digits"),
    (f'reduction_sha256 = "{SHIPPED_SHA256}"', "reduction_sha256 = 1779",
     r"actuator\.reduction_sha256: must be a string, got 1779"),
    ('reduction = "softcrawl:pneunet_6mm.npz"\n', "",
     r"actuator\.reduction_sha256: given without a reduction"),
    ("[actuator.pneunet]", "[actuator.pneunets]", r"actuator\.pneunets: unknown key"),
    ("[slots]", "[slot]", r"slot: unknown key"),
    ("count = 8", "count = 8 8", r"TOML"),
    ("regulators = 3", "regulators = 7", r"design: 4422642 raw designs, more than the 2000000"),
    ("mass_kg = 0.075", "mass_kg = nan", r"body\.mass_kg: must lie in \[1e-06, 100\], got nan"),
    # bounds of every count and dimension (the module docstring of softcrawl.design.spacefile)
    ("regulators = 3", "regulators = 17", r"design\.regulators: must lie in \[1, 16\], got 17$"),
    ("count = 8", "count = 129", r"slots\.count: must lie in \[1, 128\], got 129$"),
    ("count = 8", "count = 128", rf"design: {sum(math.comb(128, k) * 3**k for k in range(3, 7))} raw designs, more "
     r"than the 125000 of 128 slots"),  # counted, not enumerated
    ("bottom_radius_mm = 50.0", "bottom_radius_mm = 1e300",
     r"body\.bottom_radius_mm: must lie in \[0\.1, 1000\] mm, got 1e\+300$"),
    ("height_mm = 18.0", "height_mm = 0.01", r"body\.height_mm: must lie in \[0\.1, 1000\] mm, got 0\.01$"),
    ("mesh_size_mm = 10.0", "mesh_size_mm = 1e-9", r"body\.mesh_size_mm: must lie in \[1, 100\] mm, got 1e-09$"),
    ("mesh_size_mm = 6.0", "mesh_size_mm = 1e-9", r"actuator\.mesh_size_mm: must lie in \[1, 100\] mm, got 1e-09$"),
    ("mesh_size_mm = 6.0", "mesh_size_mm = 1e3", r"actuator\.mesh_size_mm: must lie in \[1, 100\] mm, got 1000$"),
    ("bottom_radius_mm = 50.0\ntop_radius_mm = 54.5\nheight_mm = 18.0\nmesh_size_mm = 10.0",
     "bottom_radius_mm = 500.0\ntop_radius_mm = 500.0\nheight_mm = 18.0\nmesh_size_mm = 1.0",
     r"body: mesh_size 1 mm is too fine for a part of 1000 x 1000 x 18 mm: 1\.8e\+07 cells .* at least 3\.31 mm$"),
    ("base_length_mm = 115.0", "base_length_mm = 1e300",
     r"actuator\.pneunet\.base_length_mm: must lie in \[0\.1, 1000\] mm, got 1e\+300$"),
    ("n_chambers = 9", "n_chambers = 1000", r"actuator\.pneunet\.n_chambers: must lie in \[1, 100\], got 1000$"),
    ("mass_kg = 0.105", "mass_kg = 1e300", r"actuator\.mass_kg: must lie in \[1e-06, 100\], got 1e\+300$"),
    ("paper_thickness_mm = 1.0", "paper_thickness_mm = 1e300",
     r"actuator\.paper_thickness_mm: must lie in \[0\.01, 100\], got 1e\+300$"),
    ('material = "printed_polymer"', "material = { youngs_modulus_kpa = 1e300, poisson_ratio = 0.3, "
     "density_kg_per_m3 = 1000.0 }", r"body\.material\.youngs_modulus_kpa: must lie in \[1, 1e\+09\]"),
    # names are printed and name folders: printable, one line, no path
    ('name = "paper"', 'name = "\\u001b[31mred"', r"name: '\\x1b\[31mred' is not a name \(1 to 64 characters"),
    ('name = "paper"', 'name = "abc\\u202Edef"', r"name: 'abc\\u202edef' is not a name"),
    ('name = "paper"', 'name = "a\\u0000b"', r"name: 'a\\x00b' is not a name"),
    ('name = "paper"', 'name = "../../etc"', r"name: '\.\./\.\./etc' is not a name"),
    ('name = "paper"', 'name = "two\\nlines"', r"name: 'two\\nlines' is not a name"),
    ('name = "paper"', f'name = "{"x" * 65}"', r"name: 'x{65}' is not a name"),
    ('name = "paper"', 'name = ""', r"name: '' is not a name"),
    ('reduction = "softcrawl:pneunet_6mm.npz"', 'reduction = "softcrawl:../../x.npz"',
     r"actuator\.reduction: 'softcrawl:\.\./\.\./x\.npz': a shipped reduction is a file name"),
    ('reduction = "softcrawl:pneunet_6mm.npz"', 'reduction = "leg.txt"',
     r"actuator\.reduction: 'leg\.txt' is not a \.npz reduction file \(`softcrawl reduce build` writes one\)$"),
    # what a file holds is shown escaped and short: a key or a value of control characters, a huge value
    ("count = 8\n", 'count = 8\n"\\u001b[2J" = 1\n', r"slots\.'\\x1b\[2J': unknown key"),
    ("mirror_x = false", f'mirror_x = "{"y" * 100_000}"',
     r"design\.mirror_x: must be true or false, got 'y{76}\.\.\.$"),
    ("first_angle_deg = 22.5", f"angles_deg = [{', '.join(['1.0'] * 100_000)}]",
     r"slots\.angles_deg: must be a list of count = 8 angles, got 100000 of them$"),
]


@pytest.mark.parametrize("old, new, message", MALFORMED, ids=[m[2][:40] for m in MALFORMED])
def test_malformed_file_one_line_naming_file_and_key(tmp_path, old, new, message):
    text = PAPER_TOML.read_text()
    assert old in text
    path = tmp_path / "bad.toml"
    path.write_text(text.replace(old, new, 1))
    with pytest.raises(SpaceFileError) as info:
        load_space(path)
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(str(path)) and msg.isprintable() and len(msg) < len(str(path)) + 400, msg
    assert re.search(message, msg), msg


def test_not_a_regular_file_and_missing_file(tmp_path):
    with pytest.raises(SpaceFileError, match="regular file"):
        load_space(tmp_path)
    with pytest.raises(FileNotFoundError):
        load_space(tmp_path / "none.toml")
    with pytest.raises(FileNotFoundError, match="shipped: hex6, paper"):
        shipped_space_path("octo")


def test_a_device_or_a_fifo_as_a_space_file_is_not_a_regular_file(tmp_path):
    """``--space /dev/zero`` or a FIFO: "not a regular file" (it was "no such file"), one
    line, without reading it."""
    fifo = tmp_path / "pipe.toml"
    os.mkfifo(fifo)
    for path in (Path("/dev/zero"), fifo, tmp_path):
        with pytest.raises(SpaceFileError, match=r"not a regular file") as info:
            resolve_space(str(path))
        assert str(info.value).startswith(str(path)) and "\n" not in str(info.value)


def test_a_space_without_a_name_takes_its_files_name(tmp_path):
    path = tmp_path / "my space-2.toml"
    path.write_text(PAPER_TOML.read_text().replace('name = "paper"\n', ""))
    space = load_space(path)
    assert space.name == "my space-2" and space == dataclasses.replace(default.DEFAULT_SPACE, name="my space-2")
    bad = tmp_path / "-x\u202e.toml"
    bad.write_text(path.read_text())
    with pytest.raises(SpaceFileError, match=r"name: missing, and the file's name '-x\\u202e' is not a name .*; "
                                             r"give name = \"\.\.\.\"$"):
        load_space(bad)


def test_a_reduction_that_is_not_a_npz_archive_is_one_line(tmp_path):
    """A file named .npz that is not a zip archive: refused when the space is read, in one line
    (numpy's advice to load it "unsafely" with allow_pickle never shows)."""
    (tmp_path / "leg.npz").write_text("not a reduction")
    path = tmp_path / "s.toml"
    path.write_text(PAPER_TOML.read_text().replace('"softcrawl:pneunet_6mm.npz"', '"leg.npz"'))
    with pytest.raises(SpaceFileError, match=r"actuator\.reduction: '.*leg\.npz' is not a reduction file \(a \.npz is "
                                             r"a zip archive; `softcrawl reduce build` writes one\)$") as info:
        load_space(path)
    assert "pickle" not in str(info.value)
    (tmp_path / "leg.npz").unlink()
    (tmp_path / "leg.npz").mkdir()
    with pytest.raises(SpaceFileError, match=r"actuator\.reduction: '.*leg\.npz': not a regular file$"):
        load_space(path)


def test_a_reduction_is_compared_by_its_bytes_and_its_path_made_absolute(tmp_path, monkeypatch):
    """Two spaces naming the same reduction bytes at other paths are the same space; other
    bytes are another space. A relative path is taken from the space file's folder, whatever
    the working folder."""
    for folder in ("a", "b"):
        (tmp_path / folder).mkdir()
        shutil.copy(default_reduction_path(), tmp_path / folder / "leg.npz")
        (tmp_path / folder / "s.toml").write_text(PAPER_TOML.read_text().replace('"softcrawl:pneunet_6mm.npz"',
                                                                                 '"leg.npz"'))
    monkeypatch.chdir(tmp_path / "a")
    a = load_space("s.toml")
    monkeypatch.chdir(tmp_path)
    b = load_space(tmp_path / "b" / "s.toml")
    assert a.reduction == str(tmp_path / "a" / "leg.npz") and a == b and a != default.DEFAULT_SPACE
    assert a.reduction_key == "sha256:" + SHIPPED_SHA256 and default.DEFAULT_SPACE.reduction_key == \
        "softcrawl:pneunet_6mm.npz"
    (tmp_path / "b" / "leg.npz").write_bytes(default_reduction_path().read_bytes() + b"\0")
    assert load_space(tmp_path / "b" / "s.toml") != a


# ---------------------------------------------------------------------- bounds before any work
def test_enumeration_by_leg_count_is_the_brute_force_one(tmp_path):
    """Designs enumerated by leg count (slot sets, then their regulators) are those of all
    slot-value combinations, in the same (lexicographic) order: design indices are kept."""
    for space in (default.DEFAULT_SPACE, load_space(HEX6_TOML), load_space(_small(tmp_path, mirror=True))):
        s, r = space.n_slots, space.n_regulators
        assert space.raw_designs == tuple(d for d in itertools.product(range(r + 1), repeat=s)
                                          if space.min_legs <= s - d.count(0) <= space.max_legs)


@pytest.mark.parametrize("count, regulators, legs, expect", [
    (100, 2, 1, "raw designs:       200"),  # it enumerated the 3^100 slot-value combinations: a hang
    (32, 9, 1, "raw designs:       288"),  # 10^32 combinations
    (1_000_000_000, 2, 1, r"slots\.count: must lie in \[1, 128\], got 1000000000"),  # it built 1e9 angles first
    (128, 2, 64, r"design: \d+ raw designs, more than the 125000 of 128 slots that can be enumerated"),
])
def test_designs_count_within_a_time_and_a_memory_limit(tmp_path, count, regulators, legs, expect):
    """``softcrawl designs count`` in a process of at most 1 GiB of address space, for 60 s:
    a space of many slots is counted at once (its designs enumerated by leg count), or refused
    in one line before anything is allocated (no MemoryError traceback, no OOM kill, no hang)."""
    path = _space_of(tmp_path, count, regulators, legs, legs)

    def limit_memory():
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))

    done = subprocess.run([sys.executable, "-m", "softcrawl.cli", "designs", "count", "--space", str(path)],
                          capture_output=True, text=True, timeout=60, preexec_fn=limit_memory,
                          env={**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"})
    if expect.startswith("raw designs"):
        assert done.returncode == 0 and expect in done.stdout, done.stderr
    else:
        err = done.stderr.strip()
        assert done.returncode == 2 and len(err.splitlines()) == 1 and re.search(expect, err), err


def _space_of(tmp_path: Path, count: int, regulators: int, min_legs: int, max_legs: int) -> Path:
    """hex6 with ``count`` slots, ``regulators`` and ``min_legs..max_legs`` legs, no mirror."""
    text = HEX6_TOML.read_text().replace("count = 6", f"count = {count}")
    text = text.replace("regulators = 2\nmin_legs = 2\nmax_legs = 4\nmirror_x = true",
                        f"regulators = {regulators}\nmin_legs = {min_legs}\nmax_legs = {max_legs}\nmirror_x = false")
    path = tmp_path / f"s{count}x{regulators}.toml"
    path.write_text(text)
    return path


def test_part_dimensions_and_mesh_sizes_are_bounded():
    """A mesh size far below a millimetre gave gmsh an edge node count past a C int: a coarse
    mesh without an error (1e-9 mm: the disk had 37 nodes); a huge dimension an OpenCASCADE
    exception. Both are refused in one line when the part is described, before gmsh runs."""
    for bad, message in ((dict(mesh_size=1e-9), r"^mesh_size must lie in \[1, 100\] mm, got 1e-09$"),
                         (dict(bottom_radius=1e300), r"^bottom_radius must lie in \[0\.1, 1000\] mm, got 1e\+300$"),
                         (dict(height=math.nan), r"^height must lie in"),
                         (dict(bottom_radius=500.0, mesh_size=1.0), r"^mesh_size 1 mm is too fine for a part of 1000")):
        with pytest.raises(ValueError, match=message):
            DiskParams(**bad)
    for bad, message in ((dict(n_chambers=101), r"^n_chambers must lie in \[1, 100\], got 101$"),
                         (dict(tooth_gap=math.inf), r"^tooth_gap must lie in \[0\.1, 1000\] mm, got inf$"),
                         (dict(mesh_size=0.5), r"^mesh_size must lie in \[1, 100\] mm, got 0\.5$")):
        with pytest.raises(ValueError, match=message):
            PneuNetParams(**bad)
    assert DiskParams(mesh_size=1.0).mesh_size == 1.0 and PneuNetParams(mesh_size=100).mesh_size == 100.0


# ---------------------------------------------------------------------- robots of a space
def _check_placement(robot, disk_radius: float) -> None:
    """The base-top corners ``(-h, +-10, b)`` of each leg's inner end (b = 4 mm), tilted by
    15 deg about y and moved by ``(h cos15 + r, 0, h sin15 - b)`` (physics.md, "Geometry", r =
    the disk's bottom radius), lie at radius ``r + b sin15`` and ``b (1 - cos15)`` below the
    disk's bottom face (lifted by ``2 h sin15``); rounding only (1e-9 mm)."""
    tilt = np.radians(15.0)
    disk_bottom = robot.model.bodies[0].mesh.points[:, 2].min()
    for leg in robot.legs:
        mesh = robot.model.bodies[leg.body].mesh
        inner = mesh.points[mesh.node_sets["attachment"][:2]]
        u = np.array([np.cos(np.radians(leg.angle_deg)), np.sin(np.radians(leg.angle_deg))])
        assert np.allclose(inner[:, :2] @ u, disk_radius + 4.0 * np.sin(tilt), rtol=0, atol=1e-9)
        assert np.allclose(inner[:, 2], disk_bottom - 4.0 * (1 - np.cos(tilt)), rtol=0, atol=1e-9)


def test_hex6_full_order_robot_builds():
    """The 6-slot example's robot: 6-chamber legs (half block h = 38.5 mm) at the space's
    angles on 2 channels, placed on the disk's rim, and the space's masses."""
    space = load_space(HEX6_TOML)
    config = RobotConfig.for_space(space, leg_mesh_size=12.0, disk_mesh_size=25.0)
    assert (config.leg_mass, config.disk_mass) == (0.08, 0.075)
    robot = build_robot("1,0,2,0,1,0", config, space=space)
    assert robot.model.n_channels == 2 and robot.regulator_channels == {1: 0, 2: 1}
    assert [(leg.slot, leg.angle_deg, leg.channel) for leg in robot.legs] == [(0, 30.0, 0), (2, 150.0, 1),
                                                                            (4, 270.0, 0)]
    leg_params = pneunet_params(space, 12.0)
    assert robot.model.bodies[1].mesh.params == dataclasses.asdict(leg_params)
    assert leg_params.n_chambers == 6 and leg_params.block_length == 77.0
    _check_placement(robot, 50.0)
    assert min(b.mesh.points[:, 2].min() for b in robot.model.bodies) == pytest.approx(0.01, abs=1e-12)
    with pytest.raises(InvalidDesignError):
        build_robot("1,0,0,2,2,0,0,1", config, space=space)
    with pytest.raises(ValueError, match=r"leg_mesh_size: 6\.0 in the reduction, 12\.0 in use"):  # its own is 6 mm
        build_robot("1,0,2,0,1,0", dataclasses.replace(config, model="reduced"), space=space)


def test_legs_follow_the_disk_radius(tmp_path):
    path = tmp_path / "wide.toml"
    path.write_text(PAPER_TOML.read_text().replace("bottom_radius_mm = 50.0\ntop_radius_mm = 54.5",
                                                   "bottom_radius_mm = 60.0\ntop_radius_mm = 64.5"))
    space = load_space(path)
    robot = build_robot(default.BASELINE_DESIGN, RobotConfig.for_space(space, leg_mesh_size=12.0,
                                                                       disk_mesh_size=25.0), space=space)
    assert robot.model.bodies[0].mesh.params["bottom_radius"] == 60.0
    _check_placement(robot, 60.0)


def test_mass_from_density(tmp_path):
    """A leg given by its material's density weighs rho V: the paper's PneuNet has a solid
    volume of 43,072 mm^3 (physics.md; boxes, so its mesh volume is exact up to rounding)."""
    path = tmp_path / "dense.toml"
    path.write_text(PAPER_TOML.read_text().replace(
        'mass_kg = 0.105\nmaterial = "dragonskin30"',
        "material = { youngs_modulus_kpa = 1160.0, poisson_ratio = 0.2, density_kg_per_m3 = 1080.0 }"))
    space = load_space(path)
    assert space.leg.mass is None and space.leg.material.density_kg_per_m3 == 1080.0
    config = RobotConfig.for_space(space, leg_mesh_size=12.0, disk_mesh_size=25.0)
    assert config.leg_mass == pytest.approx(1080.0 * 43_072e-9, rel=1e-12)
    assert config.disk_mass == 0.075 and RobotConfig.for_space(space, leg_mass=0.2).leg_mass == 0.2
    assert material(space.leg.material) == DRAGONSKIN_30


def test_hex6_robot_rests_on_the_floor():
    """0.5 s at zero pressure on the space's 2 regulators (coarse meshes): no penetration
    beyond the contact distance, and the floor carries the weight (within 5% as for the
    paper's robot in test_robot.py; measured 0.14%)."""
    space = load_space(HEX6_TOML)
    robot = build_robot("1,0,2,0,1,0", RobotConfig.for_space(space, leg_mesh_size=12.0, disk_mesh_size=25.0),
                        space=space)
    ep = Episode(robot, settling=NO_SETTLING)
    ep.reset()
    with pytest.raises(ValueError):
        ep.step(np.zeros(3))
    for _ in range(50):
        state = ep.step(np.zeros(2))
        assert state.x[:, 2].min() > -0.5
    assert ep.solver.stats.normal_force == pytest.approx(robot.model.total_mass * 9800.0, rel=0.05)


def test_env_of_the_hex6_space():
    """The env's designs, one-hot (6 x 3), actions (2 regulators) and robots come from its space."""
    space = load_space(HEX6_TOML)
    factory = BuildRobot(RobotConfig.for_space(space, leg_mesh_size=12.0, disk_mesh_size=25.0), space)
    env = CrawlerEnv(factory, steps_per_action=2, n_actions=2, observe_state=True, settling=NO_SETTLING, space=space)
    assert env.designs == space.canonical_designs and len(env.designs) == 124
    assert env.action_space.shape == (2,) and env.observation_space.shape == (18 + 2 * 4 + 8,)
    obs, info = env.reset(seed=0, options={"design": (0, 2, 1, 0, 0, 1)})
    assert info["design"] == (0, 2, 1, 0, 0, 1) and obs.shape == (34,)
    assert np.array_equal(obs[:18], space.one_hot_batch([(0, 2, 1, 0, 0, 1)])[0])
    obs, reward, terminated, truncated, info = env.step(np.array([1.0, -1.0]))
    assert obs.shape == (34,) and np.isfinite(reward) and not terminated
    assert np.array_equal(obs[18:20], [1.0, -1.0]) and info["commanded_kpa"].tolist() == [90.0, 0.0]
    with pytest.raises(ValueError, match="action must be 2 finite numbers"):
        env.step(np.zeros(3))
    with pytest.raises(InvalidDesignError):
        env.reset(options={"design": default.BASELINE_DESIGN})
    # randomization draws per regulator of the space (tests/test_other_spaces.py runs it)
    assert CrawlerEnv(factory, space=space, randomize=DomainRanges(friction=(1.0, 1.2))).randomize.friction == (1.0, 1.2)


def test_reduction_of_another_pneunet_is_refused(tmp_path):
    """The shipped reduction (9 chambers) named by a space of 6-chamber legs: refused when a
    reduced robot is built, naming the dimensions that differ."""
    text = HEX6_TOML.read_text().replace("mass_kg = 0.08", "mass_kg = 0.105")  # the reduction's leg mass
    text = re.sub(r"^reduction(_sha256)? = .*\n", "", text, flags=re.M)  # hex6's own reduction
    text = text.replace('paper_thickness_mm = 1.0', 'paper_thickness_mm = 1.0\nreduction = "softcrawl:pneunet_6mm.npz"')
    path = tmp_path / "hex6_wrong_reduction.toml"
    path.write_text(text)
    space = load_space(path)
    assert Path(space.reduction) == default_reduction_path()
    config = RobotConfig.for_space(space, model="reduced")
    with pytest.raises(ValueError, match=r"another PneuNet .*base_length: 115\.0 != 88\.0.*n_chambers: 9 != 6"):
        build_robot("1,0,2,0,1,0", config, space=space)


# ---------------------------------------------------------------------- the CLI
@pytest.fixture
def designs_cli(monkeypatch):
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("softcrawl.cli.designs",))
    return cli.main


def test_cli_designs_space(designs_cli, capsys, tmp_path):
    assert designs_cli(["designs", "count", "--space", str(HEX6_TOML)]) == 0
    out = capsys.readouterr().out
    assert "space hex6: 6 slots, 2 regulators, 2..4 legs, mirror about x" in out
    assert "raw designs:       460" in out and "canonical designs: 124" in out
    assert designs_cli(["designs", "list", "--space", str(HEX6_TOML), "--legs", "2"]) == 0
    assert len(capsys.readouterr().out.splitlines()) == 18
    png = tmp_path / "h.png"
    assert designs_cli(["designs", "show", "--space", str(HEX6_TOML), "0,2,1,0,0,1", "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "canonical:  0,1,2,0,0,2" in out and "slot 5 at 330 deg: 1" in out and png.exists()


def test_cli_designs_bad_space_one_line_writes_nothing(designs_cli, capsys, tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text(PAPER_TOML.read_text().replace("max_legs = 6", "max_legs = 9"))
    before = sorted(tmp_path.iterdir())
    png = tmp_path / "never.png"
    assert designs_cli(["designs", "show", "--space", str(bad), "1,0,0,2,2,0,0,1", "--png", str(png)]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and len(captured.err.strip().splitlines()) == 1
    assert "design.max_legs" in captured.err and str(bad) in captured.err
    assert sorted(tmp_path.iterdir()) == before


def test_cli_designs_never_prints_a_raw_control_character(designs_cli, capsys, tmp_path):
    """A name of escape sequences, a right-to-left override or a NUL is refused, and the
    refusal shows it escaped: nothing raw reaches the terminal."""
    for name in ("\\u001b]0;owned\\u0007", "abc\\u202Etxt.exe", "a\\u0000b"):
        path = tmp_path / "evil.toml"
        path.write_text(PAPER_TOML.read_text().replace('name = "paper"', f'name = "{name}"'))
        assert designs_cli(["designs", "count", "--space", str(path)]) == 2
        captured = capsys.readouterr()
        assert captured.out == "" and "is not a name" in captured.err
        assert captured.err.isprintable() or captured.err.rstrip("\n").isprintable(), captured.err
