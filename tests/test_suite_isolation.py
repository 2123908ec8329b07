"""The test suite writes only into temporary folders (HOME, caches, SB3 loggers)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def test_tests_write_only_into_temp_dirs(tmp_path, monkeypatch):
    import pwd

    import gmsh

    from softcrawl.geometry.io import cache_dir, cached_mesh
    from softcrawl.geometry.mesh import TetMesh
    from softcrawl.geometry.primitives import occ_tet_mesh

    real_home = Path(pwd.getpwuid(os.getuid()).pw_dir).resolve()
    home = Path(os.environ["HOME"]).resolve()
    assert home != real_home and home.is_relative_to(Path(tempfile.gettempdir()).resolve())
    cache = Path(os.environ["SOFTCRAWL_CACHE_DIR"]).resolve()
    assert not cache.is_relative_to(real_home / ".cache")

    # gmsh writes FLTK preferences into $HOME at every initialise: into the session's HOME
    prefs = real_home / ".fltk" / "fltk.org" / "fltk.prefs"
    stamp = prefs.stat().st_mtime_ns if prefs.exists() else None

    def box():
        gmsh.model.occ.addBox(0, 0, 0, 10, 10, 10)
        gmsh.model.occ.synchronize()

    params = {"box": 10, "test": tmp_path.name}

    def build():
        points, tets = occ_tet_mesh("box", box, 5.0)
        return TetMesh(points, tets, {}, {}, params)

    cached_mesh("issue20-box", params, build)
    assert (prefs.stat().st_mtime_ns if prefs.exists() else None) == stamp
    assert (home / ".fltk").exists()
    # the mesh cache entry went into the session's cache
    assert cache_dir().resolve() == cache and list(cache.glob("issue20-box-*.vtu"))
    import gymnasium as gym
    from stable_baselines3.common.vec_env import DummyVecEnv

    from softcrawl.codesign.config import SACConfig
    from softcrawl.codesign.sac import make_sac

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    model = make_sac(DummyVecEnv([lambda: gym.make("Pendulum-v1")]),
                     SACConfig(learning_starts=5, batch_size=4, buffer_size=50, net_arch=(8,)))
    model.learn(10)
    assert not list(tmp_path.glob("SB3-*"))
