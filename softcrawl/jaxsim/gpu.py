"""The NVIDIA GPU a step is compiled for, and whether it runs the engine's Pallas kernels.

The engine's kernels (the contact solve, the factors, the RID terms, the contact candidates, the
attachments' elimination: :mod:`softcrawl.jaxsim.fused`, :mod:`~softcrawl.jaxsim.factor`,
:mod:`~softcrawl.jaxsim.ridkernel`, :mod:`~softcrawl.jaxsim.candidates`,
:mod:`~softcrawl.jaxsim.elimination`) are Pallas kernels in Triton form, and XLA compiles Triton
kernels for Ampere GPUs and newer only (compute capability 8.0 and up; on a T4 or a V100 it
fails: "Triton support is only enabled for Ampere GPUs (compute capability 8.0) and up"). Each
kernel form therefore goes through :func:`cuda_kernel`: the kernel where the GPU runs it, XLA's
form of the same step on older GPUs (with a warning), as on platforms other than CUDA.

The GPU is JAX's first CUDA device; where JAX has none, the GPU a deviceless compilation
targets (:func:`softcrawl.jaxsim.cost.deviceless_gpu` records it from its target
configuration), and else none: then a kernel form is assumed to run (the CUDA branch of
``jax.lax.platform_dependent`` is only compiled for a GPU).
"""

from __future__ import annotations

import re
import warnings

#: The oldest compute capability whose GPUs run Pallas' Triton kernels (XLA's rule, above).
TRITON_FROM = (8, 0)

_target: tuple[int, int] | None = None
_warned = False


def target_capability(config: str) -> tuple[int, int]:
    """``(major, minor)`` compute capability of an XLA ``GpuTargetConfig`` in protobuf text format
    (``benchmarks/gpu_targets/``; ``cuda_compute_capability { major: 9 }``, an absent minor
    0).

    Raises:
        ValueError: a configuration without a CUDA compute capability.
    """
    m = re.search(r"cuda_compute_capability\s*\{([^}]*)\}", config)
    if m is None:
        raise ValueError("the GPU target configuration has no cuda_compute_capability")
    field = dict(re.findall(r"(major|minor)\s*:\s*(\d+)", m.group(1)))
    if "major" not in field:
        raise ValueError("the GPU target configuration's cuda_compute_capability has no major")
    return int(field["major"]), int(field.get("minor", 0))


def set_target(capability: tuple[int, int] | None) -> None:
    """Record the compute capability a deviceless compilation targets (None: none)."""
    global _target
    _target = None if capability is None else (int(capability[0]), int(capability[1]))


def compute_capability() -> tuple[int, int] | None:
    """``(major, minor)`` of JAX's first CUDA GPU, else of the deviceless target
    (:func:`set_target`), else None."""
    import jax

    try:
        devices = jax.local_devices(backend="cuda")
    except RuntimeError:  # no CUDA backend
        devices = []
    if devices and getattr(devices[0], "compute_capability", None):
        major, minor = str(devices[0].compute_capability).split(".")[:2]
        return int(major), int(minor)
    return _target


def runs_kernels() -> bool:
    """Whether the GPU (:func:`compute_capability`) runs the engine's Pallas kernels (True where
    there is none: the module doc)."""
    capability = compute_capability()
    return capability is None or capability >= TRITON_FROM


def cuda_kernel(kernel) -> dict:
    """``{"cuda": kernel}`` for ``jax.lax.platform_dependent`` where the GPU runs the kernels
    (:func:`runs_kernels`), else ``{}`` (its ``default`` branch then serves CUDA too) and a
    warning, once a process: the step is slower there."""
    global _warned
    if runs_kernels():
        return {"cuda": kernel}
    if not _warned:
        _warned = True
        warnings.warn("this GPU (compute capability {}.{}) compiles no Pallas kernels (Triton needs 8.0 or newer): "
                      "the JAX engine runs XLA's forms of its kernels, slower".format(*compute_capability()),
                      stacklevel=2)
    return {}


def kernel_precision(dtype, algorithm: str | None, interpret: bool):
    """The ``precision`` of a Pallas kernel's products on arrays of ``dtype``: the
    ``jax.lax.DotAlgorithmPreset`` named ``algorithm`` (TF32 passes on the tensor cores) for
    float32 compiled for a GPU, else full precision (float64, ``algorithm`` None, and Pallas'
    interpreter: a CPU has no TF32)."""
    import jax.numpy as jnp
    from jax import lax

    if dtype == jnp.float32 and algorithm is not None and not interpret:
        return lax.DotAlgorithmPreset[algorithm]
    return (lax.Precision.HIGHEST, lax.Precision.HIGHEST)
