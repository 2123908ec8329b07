"""Test-session isolation: the suite writes only into temporary folders.

Set before any softcrawl module is imported: a fresh mesh / calibration cache
(``SOFTCRAWL_CACHE_DIR``, unless the caller set one, as CI does; a folder per test process
under pytest-xdist, so that no two processes build one entry at once) instead of
``~/.cache``, and a
temporary ``HOME`` so gmsh, matplotlib and friends keep their preference files out of the
user's home; one BLAS/OpenMP thread per process, as softcrawl's commands run
(:mod:`softcrawl.cli`; so computations in this process and in worker processes round alike);
hypothesis keeps its example database and caches in the session folder too
(not ``.hypothesis/`` in the working directory). SB3 loggers are set by :func:`softcrawl.codesign.sac.make_sac`, so no
``/tmp/SB3-*`` folders appear. The session folder is removed at the end.
"""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest

_SESSION = tempfile.mkdtemp(prefix="softcrawl-tests-")
os.environ.setdefault("SOFTCRAWL_CACHE_DIR", os.path.join(_SESSION, "cache"))
if os.environ.get("PYTEST_XDIST_WORKER"):  # a test process of several: a cache of its own
    os.environ["SOFTCRAWL_CACHE_DIR"] = os.path.join(os.environ["SOFTCRAWL_CACHE_DIR"],
                                                     os.environ["PYTEST_XDIST_WORKER"])
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ["HOME"] = os.path.join(_SESSION, "home")
os.makedirs(os.environ["HOME"], exist_ok=True)
os.environ.setdefault("MPLCONFIGDIR", os.path.join(_SESSION, "mpl"))
try:
    from hypothesis.configuration import set_hypothesis_home_dir
except ImportError:  # pragma: no cover - hypothesis is in the test extra
    pass
else:
    set_hypothesis_home_dir(os.path.join(_SESSION, "hypothesis"))


def pytest_unconfigure(config):
    shutil.rmtree(_SESSION, ignore_errors=True)


@pytest.fixture(scope="module")
def x64():
    """JAX in float64 for the module, the caller's setting restored after (softcrawl never
    switches it at import): the JAX engine's tests request it, or autouse it per module."""
    import jax

    old = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)
    yield
    jax.config.update("jax_enable_x64", old)


@pytest.fixture(scope="session")
def trained(tmp_path_factory):
    """A finished smoke training run (160 steps) with checkpoints at 40, 80, 120, 160 kept, no
    report: shared by the session, so tests only read it (or copy it: the ``run`` fixture)."""
    from softcrawl.codesign.config import override, preset
    from softcrawl.codesign.training import train

    run = tmp_path_factory.mktemp("trained") / "run"
    cfg = override(preset("smoke"), ["checkpoint_every=40", "keep_checkpoints=4", 'sac.learner="sbx"'])
    train(run, cfg, progress=False)
    return run


@pytest.fixture
def run(trained, tmp_path):
    """A private copy of the ``trained`` run, free to damage."""
    dst = tmp_path / "run"
    shutil.copytree(trained, dst, symlinks=True)
    return dst
