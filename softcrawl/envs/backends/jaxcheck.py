"""What the JAX vector-env backend (:mod:`softcrawl.envs.backends.jaxvec`) can run, checked
without importing JAX (a run's config is validated before any backend is built).

The JAX engine (:mod:`softcrawl.jaxsim`) steps the reduced robot with the floating-frame disk
only, and takes friction, stiffness and mass as part of its compiled model: those cannot be
drawn per episode. The rig quantities of domain randomization (pressure gains and offsets,
regulator lags, the control period) are per-env inputs of the compiled rollout.
"""

from __future__ import annotations

from softcrawl.robot.domain import DomainRanges
from softcrawl.tasks import Task

#: Float precisions of the JAX backend (``jax_enable_x64`` on for float64; ``"auto"``:
#: :func:`resolve_precision`).
PRECISIONS = ("auto", "float64", "float32")
#: Domain-randomization keys the JAX backend draws per env (:mod:`softcrawl.robot.domain`).
RANDOMIZED = ("pressure_gain", "pressure_offset", "tau_inflate", "tau_vent", "control_period")


def check_precision(precision: str) -> None:
    """Raise ValueError unless ``precision`` is one of :data:`PRECISIONS`."""
    if precision not in PRECISIONS:
        raise ValueError(f"jax_precision must be one of {PRECISIONS}, got {precision!r}")


def resolve_precision(precision: str) -> str:
    """``precision``, or for ``"auto"`` ``"float32"`` where JAX's default device is a GPU (the
    engine's float32 with full-precision products is checked there and is 1.35-1.5x faster:
    benchmarks/RESULTS.md) and ``"float64"`` elsewhere (on a CPU float64 costs little and is
    the engine validated against the CPU engine to round-off). Imports JAX.

    Raises:
        ValueError: an unknown precision."""
    check_precision(precision)
    if precision != "auto":
        return precision
    import jax

    return "float32" if jax.default_backend() == "gpu" else "float64"


def check_randomized(randomize: DomainRanges | None) -> None:
    """Raise ValueError (one line naming the settings) if ``randomize`` has a range of a
    quantity the JAX backend cannot draw per env (not in :data:`RANDOMIZED`)."""
    refused = [k for k in randomize.keys() if k not in RANDOMIZED] if randomize is not None else []
    if refused:
        raise ValueError(f'backend "jax" does not randomize {", ".join("env.randomize." + k for k in refused)} '
                         f"(part of its compiled model); it randomizes {', '.join(RANDOMIZED)}")


def check_jax_env(model: str, randomize: DomainRanges | None) -> None:
    """Raise ValueError (one line naming the setting) unless the JAX backend can run envs of
    robot model ``model`` (:data:`softcrawl.robot.assembly.MODELS`) with the randomization
    ``randomize``."""
    if model != "reduced":
        raise ValueError(f'backend "jax" steps the reduced robot only (env.model="reduced"), got env.model={model!r}')
    check_randomized(randomize)


def check_jax_task(task: Task) -> None:
    """Raise ValueError (one line) unless the JAX backend can score ``task``: it returns the
    reward point (the disk's top centre) only, so a task whose progress reads the disk's nodes
    (:attr:`softcrawl.tasks.Task.reads_disk`: ``turning``) is refused, and so is one scored at
    rest (:attr:`softcrawl.tasks.Task.vent_seconds`): its episodes do not vent."""
    if task.reads_disk:
        raise ValueError(f'backend "jax" does not run task {task.name!r}: its reward reads the disk\'s rotation '
                         'and the JAX backend returns the disk\'s top centre only; use backend "subprocess"')
    if task.vent_seconds > 0:
        raise ValueError(f'backend "jax" does not run task {task.name!r}: it is scored after venting and the JAX '
                         'backend\'s episodes do not vent; use backend "subprocess"')
