"""The GPU a step is compiled for (:mod:`softcrawl.jaxsim.gpu`): its compute capability, from JAX's
device or a deviceless target configuration, and which GPUs run the engine's Pallas kernels."""

from __future__ import annotations

import warnings
from pathlib import Path

import pytest

jax = pytest.importorskip("jax")

H100 = Path(__file__).parents[1] / "benchmarks" / "gpu_targets" / "h100.pbtxt"


def test_a_target_configurations_compute_capability_is_read():
    """The shipped H100 configuration is 9.0 (its minor absent); a T4's 7.5; a configuration
    without one is refused."""
    from softcrawl.jaxsim.gpu import target_capability

    assert target_capability(H100.read_text()) == (9, 0)
    t4 = 'gpu_device_info {\n  core_count: 40\n  cuda_compute_capability {\n    major: 7\n    minor: 5\n  }\n}\n'
    assert target_capability(t4) == (7, 5)
    with pytest.raises(ValueError, match="cuda_compute_capability"):
        target_capability('gpu_device_info {\n  core_count: 40\n}\nplatform_name: "CUDA"\n')


def test_gpus_older_than_ampere_run_xlas_forms(monkeypatch):
    """XLA compiles Pallas' Triton kernels for compute capability 8.0 and up only: a T4 (7.5) and a
    V100 (7.0) get no CUDA branch (XLA's form serves them, as other platforms), an A100, H100 and
    RTX 4090 get the kernel; without a GPU or a deviceless target the kernel branch stays (it is
    only compiled for a GPU); an older GPU is told why its step is slower. A deviceless target is
    JAX's GPU where there is none."""
    from softcrawl.jaxsim import gpu

    kernel = object()
    for capability, runs in (((7, 5), False), ((7, 0), False), ((8, 0), True), ((8, 9), True), ((9, 0), True),
                             (None, True)):
        monkeypatch.setattr(gpu, "compute_capability", lambda c=capability: c)
        monkeypatch.setattr(gpu, "_warned", False)
        assert gpu.runs_kernels() == runs
        if runs:
            assert gpu.cuda_kernel(kernel) == {"cuda": kernel}
        else:
            with pytest.warns(UserWarning, match=r"compute capability {}\.{}".format(*capability)):
                assert gpu.cuda_kernel(kernel) == {}
            with warnings.catch_warnings():
                warnings.simplefilter("error")  # once a process
                assert gpu.cuda_kernel(kernel) == {}
    monkeypatch.undo()
    if all(d.platform == "cpu" for d in jax.devices()):  # no GPU here: the recorded target, else none
        try:
            gpu.set_target((7, 5))
            assert gpu.compute_capability() == (7, 5) and not gpu.runs_kernels()
        finally:
            gpu.set_target(None)
        assert gpu.compute_capability() is None


@pytest.mark.parametrize("config", sorted((H100.parent).glob("*.pbtxt")), ids=lambda p: p.stem)
def test_every_shipped_target_configuration_names_its_compute_capability(config):
    """``benchmarks/gpu_targets/``: each configuration has a CUDA compute capability, 7.5 to 12.0."""
    from softcrawl.jaxsim.gpu import target_capability

    assert (7, 5) <= target_capability(config.read_text()) <= (12, 0)
