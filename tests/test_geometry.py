"""Tests of softcrawl.geometry: PneuNet, disk, shell and box meshes, mesh I/O and the cache."""

from __future__ import annotations

import json
from dataclasses import asdict

import gmsh
import numpy as np
import pytest

from softcrawl.geometry import (
    DiskParams,
    MeshError,
    PneuNetParams,
    TetMesh,
    box_mesh,
    disk_mesh,
    pneunet_mesh,
    read_mesh,
    spherical_shell_octant,
    write_mesh,
)
from softcrawl.geometry.io import cached_mesh
from softcrawl.geometry.mesh import boundary_triangles

COARSE = 8.0


def enclosed_volume(points: np.ndarray, tris: np.ndarray) -> float:
    """Divergence-theorem volume of a closed triangle surface (positive for outward normals)."""
    p = points[tris]
    return float(np.einsum("ij,ij->i", p[:, 0], np.cross(p[:, 1], p[:, 2])).sum() / 6)


def normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """``(k, 3)`` area-weighted (x2) triangle normals."""
    p = points[tris]
    return np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])


def assert_closed_and_consistent(tris: np.ndarray) -> None:
    """Every edge is used by exactly two triangles, once in each direction."""
    directed = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    assert len(np.unique(directed, axis=0)) == len(directed)
    _, counts = np.unique(np.sort(directed, axis=1), axis=0, return_counts=True)
    assert np.all(counts == 2)


def assert_meshes_equal(a: TetMesh, b: TetMesh) -> None:
    assert np.array_equal(a.points, b.points) and np.array_equal(a.tets, b.tets)
    assert a.surfaces.keys() == b.surfaces.keys() and a.node_sets.keys() == b.node_sets.keys()
    for name in a.surfaces:
        assert np.array_equal(a.surfaces[name], b.surfaces[name])
    for name in a.node_sets:
        assert np.array_equal(a.node_sets[name], b.node_sets[name])
    assert a.params == b.params


@pytest.fixture(scope="module")
def leg() -> TetMesh:
    return pneunet_mesh(PneuNetParams(mesh_size=COARSE), cache=False)


# --- PneuNet -----------------------------------------------------------------------------


def test_pneunet_volumes(leg):
    assert leg.volume() == pytest.approx(43072.0, rel=5e-3)
    assert enclosed_volume(leg.points, leg.surfaces["cavity"]) == pytest.approx(3528.0, rel=5e-3)
    # The outer surface encloses solid + air.
    assert enclosed_volume(leg.points, leg.surfaces["boundary"]) == pytest.approx(43072.0 + 3528.0, rel=5e-3)


def test_pneunet_surfaces_partition_the_boundary(leg):
    cavity, outer = leg.surfaces["cavity"], leg.surfaces["boundary"]
    assert_closed_and_consistent(cavity)  # channel and chambers form one closed cavity
    assert_closed_and_consistent(outer)
    every = boundary_triangles(leg.tets)
    assert len(cavity) + len(outer) == len(every)
    assert np.array_equal(np.unique(leg.node_sets["collision"]), np.unique(outer))
    assert not np.intersect1d(np.unique(cavity), np.unique(outer)).size


def test_pneunet_paper_face(leg):
    paper = leg.surfaces["paper"]
    n = normals(leg.points, paper)
    assert np.all(leg.points[paper, 2] == 0.0)
    assert np.allclose(n[:, :2], 0.0) and np.all(n[:, 2] < 0)
    assert 0.5 * -n[:, 2].sum() == pytest.approx(115 * 32)


def test_pneunet_attachment_and_tip(leg):
    expected = [(-52, -10, 4), (-52, 10, 4), (-52, -10, 20), (-52, 10, 20)]
    assert np.array_equal(leg.points[leg.node_sets["attachment"]], np.array(expected, float))
    tip = leg.points[leg.node_sets["tip"]]
    assert len(tip) >= 4 and np.all(tip[:, 0] == 57.5)
    assert leg.params == asdict(PneuNetParams(mesh_size=COARSE))


def test_pneunet_other_dimensions():
    p = PneuNetParams(n_chambers=5, wall_thickness=2.0, tooth_gap=1.5, mesh_size=10.0)
    mesh = pneunet_mesh(p, cache=False)
    lx, ly = p.block_length, p.block_width
    cx, cy, cz = p.chamber_size
    solid = (
        p.base_length * p.base_width * p.base_thickness
        + lx * ly * p.block_height
        + (2 * p.end_tooth_width + 5 * p.tooth_width) * ly * p.tooth_height
    )
    cavity = 5 * cx * cy * cz + (p.channel_length - 5 * cx) * p.channel_width * p.channel_height
    assert mesh.volume() == pytest.approx(solid - cavity, rel=5e-3)
    assert enclosed_volume(mesh.points, mesh.surfaces["cavity"]) == pytest.approx(cavity, rel=5e-3)
    assert np.allclose(mesh.points[mesh.node_sets["attachment"]][:, 0], -lx / 2)
    assert not gmsh.isInitialized()


@pytest.mark.parametrize(
    "kwargs", [{"n_chambers": 0}, {"wall_thickness": 4.0}, {"mesh_size": 0.0}, {"channel_height": 14.0}]
)
def test_pneunet_params_validated(kwargs):
    with pytest.raises(ValueError):
        PneuNetParams(**kwargs)


# --- disk, shell, box ----------------------------------------------------------------------


def test_disk():
    p = DiskParams()
    mesh = disk_mesh(p, cache=False)
    frustum = np.pi * p.height * (p.bottom_radius**2 + p.bottom_radius * p.top_radius + p.top_radius**2) / 3
    assert mesh.volume() == pytest.approx(frustum, rel=1e-2)
    assert mesh.volume() < frustum  # faceting cuts the curved side inwards
    assert np.array_equal(mesh.points[mesh.node_sets["top_centre"]], [[0.0, 0.0, p.height]])
    boundary = mesh.surfaces["boundary"]
    assert_closed_and_consistent(boundary)
    assert enclosed_volume(mesh.points, boundary) == pytest.approx(mesh.volume())
    assert np.array_equal(mesh.node_sets["collision"], np.unique(boundary))


def test_spherical_shell_octant():
    a, b = 10.0, 20.0
    mesh = spherical_shell_octant(a, b, 3.0)
    assert mesh.volume() == pytest.approx(np.pi / 6 * (b**3 - a**3), rel=2e-2)
    cavity = mesh.surfaces["cavity"]
    assert np.allclose(np.linalg.norm(mesh.points[cavity], axis=2), a)
    n = normals(mesh.points, cavity)
    centroids = mesh.points[cavity].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", n, centroids) > 0)  # radially outward, into the solid
    assert 0.5 * np.linalg.norm(n, axis=1).sum() == pytest.approx(np.pi * a**2 / 2, rel=2e-2)
    for axis, c in enumerate("xyz"):
        nodes = mesh.node_sets[f"sym_{c}"]
        assert len(nodes) > 10 and np.allclose(mesh.points[nodes, axis], 0.0)
    with pytest.raises(ValueError):
        spherical_shell_octant(2.0, 1.0, 1.0)


def test_box_mesh():
    size, div, origin = (2.0, 3.0, 1.5), (2, 3, 4), (1.0, -1.0, 0.5)
    mesh = box_mesh(size, div, origin)
    assert mesh.n_nodes == 3 * 4 * 5 and mesh.n_tets == 6 * 2 * 3 * 4
    assert np.all(mesh.volumes() > 0)
    assert mesh.volume() == pytest.approx(np.prod(size), rel=1e-12)
    boundary = mesh.surfaces["boundary"]
    # Conforming: only the 2 triangles per boundary quad are unshared.
    assert len(boundary) == 4 * (2 * 3 + 3 * 4 + 2 * 4)
    assert_closed_and_consistent(boundary)
    assert enclosed_volume(mesh.points, boundary) == pytest.approx(np.prod(size))
    assert np.allclose(mesh.points[mesh.node_sets["x0"], 0], 1.0) and len(mesh.node_sets["x0"]) == 4 * 5
    assert np.allclose(mesh.points[mesh.node_sets["x1"], 0], 3.0) and len(mesh.node_sets["x1"]) == 4 * 5
    assert np.allclose(mesh.points[mesh.node_sets["z0"], 2], 0.5) and len(mesh.node_sets["z0"]) == 3 * 4
    assert len(mesh.node_sets["collision"]) == mesh.n_nodes - 1 * 2 * 3
    with pytest.raises(ValueError):
        box_mesh((1, 1, 1), (0, 1, 1))


def test_gmsh_state_of_caller_is_kept():
    gmsh.initialize(readConfigFiles=False, interruptible=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.add("mine")
        gmsh.option.setNumber("Mesh.MeshSizeMax", 123.0)
        disk_mesh(DiskParams(mesh_size=20.0), cache=False)
        assert gmsh.isInitialized() and gmsh.model.getCurrent() == "mine"
        assert gmsh.option.getNumber("Mesh.MeshSizeMax") == 123.0
    finally:
        gmsh.finalize()


# --- I/O and cache -------------------------------------------------------------------------


def test_io_round_trip_is_exact(leg, tmp_path):
    path = tmp_path / "leg.vtu"
    write_mesh(leg, path)
    assert_meshes_equal(read_mesh(path), leg)
    # Unsorted node set order and an empty surface survive too.
    box = box_mesh((1, 2, 3), (1, 2, 3))
    surfaces = {**box.surfaces, "none": np.zeros((0, 3))}
    odd = TetMesh(box.points, box.tets, surfaces, {"order": [5, 0, 3]}, {"a": [1, 2.5]})
    write_mesh(odd, tmp_path / "odd.vtu")
    assert_meshes_equal(read_mesh(tmp_path / "odd.vtu"), odd)
    with pytest.raises(ValueError):
        write_mesh(leg, tmp_path / "leg.msh")


def test_io_rejects_mismatched_files(tmp_path):
    write_mesh(box_mesh(), tmp_path / "a.vtu")
    write_mesh(box_mesh((2, 2, 2)), tmp_path / "b.vtu")
    (tmp_path / "a.json").write_text((tmp_path / "b.json").read_text())
    with pytest.raises(MeshError):
        read_mesh(tmp_path / "a.vtu")


def test_cache_hit_and_corrupt_entry(tmp_path, monkeypatch):
    monkeypatch.setenv("SOFTCRAWL_CACHE_DIR", str(tmp_path / "cache"))
    calls = []

    def build():
        calls.append(1)
        return box_mesh((1, 2, 3), (2, 2, 2))

    params = {"size": [1.0, 2.0, 3.0], "divisions": [2, 2, 2], "origin": [0.0, 0.0, 0.0]}
    first = cached_mesh("box", params, build)
    second = cached_mesh("box", params, build)
    assert len(calls) == 1
    assert_meshes_equal(first, second)

    (vtu,) = (tmp_path / "cache").glob("box-*.vtu")
    vtu.write_bytes(vtu.read_bytes()[: len(vtu.read_bytes()) // 2])
    with pytest.warns(UserWarning, match="corrupt"):
        third = cached_mesh("box", params, build)
    assert len(calls) == 2
    assert_meshes_equal(third, first)
    assert_meshes_equal(read_mesh(vtu), first)  # the entry was repaired

    vtu.with_suffix(".json").write_text("{not json")
    with pytest.warns(UserWarning, match="corrupt"):
        cached_mesh("box", params, build)
    assert len(calls) == 3
    assert json.loads(vtu.with_suffix(".json").read_text())["params"] == params


def test_pneunet_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SOFTCRAWL_CACHE_DIR", str(tmp_path))
    p = PneuNetParams(mesh_size=10.0)
    built = pneunet_mesh(p)
    assert len(list(tmp_path.glob("pneunet-*.vtu"))) == 1
    assert_meshes_equal(pneunet_mesh(p), built)
    assert_meshes_equal(pneunet_mesh(p, cache=False), built)  # gmsh is deterministic
    assert len(list(tmp_path.glob("disk-*.vtu"))) == 0


def test_spaced_nodes_are_a_spaced_cover_of_the_candidates():
    """``spaced_nodes``: no two chosen nodes closer than the spacing, every candidate within the
    spacing of a chosen one (farthest-point sampling stops only then), the same set on every
    call, all candidates at spacing 0, and a bad spacing refused."""
    from softcrawl.geometry.mesh import spaced_nodes

    rng = np.random.default_rng(3)
    points = rng.uniform(0.0, 40.0, (600, 3))
    candidates = np.arange(0, 600, 2)
    for spacing in (3.0, 7.5, 20.0):
        chosen = spaced_nodes(points, candidates, spacing)
        assert np.isin(chosen, candidates).all() and np.all(np.diff(chosen) > 0)
        d = np.linalg.norm(points[chosen][:, None] - points[chosen][None], axis=2)
        assert d[~np.eye(len(chosen), dtype=bool)].min() >= spacing
        cover = np.linalg.norm(points[candidates][:, None] - points[chosen][None], axis=2).min(axis=1)
        assert cover.max() < spacing
        np.testing.assert_array_equal(chosen, spaced_nodes(points, candidates, spacing))
    np.testing.assert_array_equal(spaced_nodes(points, candidates[::-1], 0.0), candidates)
    with pytest.raises(ValueError, match="spacing"):
        spaced_nodes(points, candidates, float("nan"))
