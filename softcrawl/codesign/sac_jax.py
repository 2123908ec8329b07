"""The JAX learner (``sac.learner = "sbx"``): SBX's SAC (the JAX port of stable-baselines3's SAC
by its maintainers) with stable-baselines3's networks and losses (:mod:`softcrawl.codesign.sac_nets`;
:mod:`softcrawl.codesign.sac` describes the algorithm and the time limit).

All gradient updates due after one vectorised step run in one compiled call: SBX samples their
``gradient_steps x batch_size`` transitions at once (from the same replay buffer, with
replacement, as the torch learner's one batch per update) and runs the updates in a
``jax.lax.fori_loop`` inside one ``jax.jit`` (critic step, target smoothing, actor and
temperature step per update).

The learner's state (networks, target networks, Adam states, temperature, JAX random keys)
is one pytree of arrays: :func:`learner_state_bytes` writes it as flax msgpack (arrays only,
nothing that can run code when read) and :func:`restore_learner_state` reads it back into a
learner built with the same config.
"""

from __future__ import annotations

import contextlib
import os
import re
from pathlib import Path

import jax
import numpy as np
from flax import serialization
from sbx import SAC
from stable_baselines3.common.logger import Logger

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.sac_common import OverlappedUpdates, sb3_arguments
from softcrawl.codesign.sac_nets import Actor, VectorCritic, actor_step, critic_step

_DEVICE = re.compile(r"(cpu|gpu|cuda)(?::(\d+))?")


def configure_threads(threads: int) -> None:
    """Threads of the learner's CPU work: XLA's intra-op thread pool (``XLA_FLAGS``, read once,
    when JAX starts its backends in this process: call this before the first learner is built)
    and torch's (SB3's replay buffer copies its samples through torch tensors). A ``XLA_FLAGS``
    that already sets ``intra_op_parallelism_threads`` is left as it is. A GPU's memory is
    allocated as the learner needs it, not 75% of it at the start (JAX's default), unless
    ``XLA_PYTHON_CLIENT_PREALLOCATE`` says otherwise."""
    import torch

    torch.set_num_threads(threads)
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    flags = os.environ.get("XLA_FLAGS", "")
    if "intra_op_parallelism_threads" not in flags:
        extra = f"intra_op_parallelism_threads={threads}"
        if threads == 1:
            extra = "--xla_cpu_multi_thread_eigen=false " + extra
        os.environ["XLA_FLAGS"] = f"{flags} {extra}".strip()


def use_compilation_cache() -> None:
    """Keep the learner's compiled XLA programs on disk (JAX's persistent compilation cache),
    so a process that builds the same learner again (``resume``, ``evaluate``, ``report``, the
    next run) loads them instead of compiling (5-10 CPU seconds for the paper's networks).
    The cache is ``$SOFTCRAWL_CACHE_DIR/jax`` or ``~/.cache/softcrawl/jax``, the user's own, as
    numba's caches are; a cache directory set through JAX's own settings is left as it is.
    Takes effect if called before the process's first compilation."""
    if jax.config.jax_compilation_cache_dir is None:
        root = Path(os.environ.get("SOFTCRAWL_CACHE_DIR") or Path.home() / ".cache" / "softcrawl")
        jax.config.update("jax_compilation_cache_dir", str(root / "jax"))
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)


def check_device(device: str) -> jax.Device:
    """The JAX device of ``sac.device``: ``"cpu"``, ``"gpu"`` / ``"gpu:N"`` (``"cuda"`` /
    ``"cuda:N"`` are read as the same).

    Raises:
        ValueError: a malformed name, no GPU that JAX can use (a CPU-only jaxlib, no CUDA
            plugin, no driver), or no GPU number N.
    """
    m = _DEVICE.fullmatch(device)
    if m is None:
        raise ValueError(f"sac.device must be 'cpu', 'gpu' or 'gpu:N' ('cuda' is read as 'gpu'), got {device!r}")
    kind, index = m.group(1), int(m.group(2) or 0)
    if kind == "cpu":
        return jax.devices("cpu")[0]
    try:
        gpus = jax.devices("gpu")
    except RuntimeError:
        gpus = []
    if not gpus:
        raise ValueError(f"sac.device={device!r}, but JAX {jax.__version__} sees no GPU (use sac.device=\"cpu\", or "
                         "install softcrawl[gpu]: jax with its CUDA plugin)")
    if index >= len(gpus):
        raise ValueError(f"sac.device={device!r}, but JAX sees {len(gpus)} GPU(s)")
    return gpus[index]


class CodesignSAC(OverlappedUpdates, SAC):
    """SBX's SAC on JAX device ``jax_device``, its updates overlapped with the simulation if
    ``overlap`` (:class:`OverlappedUpdates`).

    The critic and actor steps are :func:`~softcrawl.codesign.sac_nets.critic_step` and
    :func:`~softcrawl.codesign.sac_nets.actor_step` (stable-baselines3's losses); the
    temperature step, target smoothing and the loop over the updates are SBX's.

    The networks, optimizer states and updates are float32 whatever ``jax_enable_x64`` says
    (the JAX engine turns it on for float64 robots in the same process; SBX's update loop mixes
    Python floats into its branches, which would then trace as float64 and fail).

    Attributes:
        learner: ``"sbx"``, the ``sac.learner`` name.
        jax_device: where the networks live and the updates and actions are computed.
    """

    learner = "sbx"
    update_critic = staticmethod(critic_step)
    update_actor = staticmethod(actor_step)

    def __init__(self, *args, jax_device: jax.Device | None = None, overlap: bool = False, **kwargs):
        self.jax_device = jax_device or jax.devices("cpu")[0]
        with self.on_device():
            super().__init__(*args, **kwargs)
        self.hook_overlap(overlap)

    @contextlib.contextmanager
    def on_device(self):
        """JAX's default device :attr:`jax_device` and 32-bit types, in this thread."""
        with jax.default_device(self.jax_device), jax.enable_x64(False):
            yield

    def run_updates(self, gradient_steps: int, batch_size: int) -> None:
        """SBX's updates, in one compiled call."""
        with self.on_device():
            SAC.train(self, gradient_steps, batch_size)  # returns after reading the losses: all done

    def predict(self, observation, state=None, episode_start=None, deterministic: bool = False):
        """SB3's ``predict`` (actions in the env's action space), computed on :attr:`jax_device`."""
        with self.on_device():
            return super().predict(observation, state, episode_start, deterministic)


def make_sac(env, cfg: SACConfig, seed: int | None = None, cls: type[CodesignSAC] | None = None) -> CodesignSAC:
    """The SAC learner for a vectorised crawler env (a :class:`CodesignSAC`, or the subclass
    ``cls``: :class:`softcrawl.codesign.episodic.EpisodicSAC`).

    SB3's settings from ``cfg`` (:func:`~softcrawl.codesign.sac_common.sb3_arguments`: update
    ratio, temperature, time limit); the updates of a vectorised step in one compiled call.
    Networks: MLP ``cfg.net_arch`` with ReLU for the actor and both critics
    (:mod:`~softcrawl.codesign.sac_nets`); Adam (β1 0.9, β2 0.999, ε 1e-8: optax's defaults, as
    torch's) at ``cfg.policy_lr`` for the actor and the temperature and ``cfg.q_lr`` for the
    critics; updates overlapped with the simulation if
    ``cfg.overlap`` (:class:`CodesignSAC`), on JAX device ``cfg.device``. Its logger writes
    nowhere until ``set_logger`` is called (SB3's default would create ``/tmp/SB3-<date>/``).

    Raises:
        ValueError: ``cfg.device`` is not a device this JAX can use (:func:`check_device`).
    """
    use_compilation_cache()
    device = check_device(cfg.device)
    model = (cls or CodesignSAC)(
        "MlpPolicy", env, learning_rate=cfg.policy_lr, qf_learning_rate=cfg.q_lr,
        policy_kwargs={"net_arch": list(cfg.net_arch), "actor_class": Actor, "vector_critic_class": VectorCritic},
        seed=seed, overlap=cfg.overlap, jax_device=device, **sb3_arguments(env, cfg),
    )
    # a logger writing nowhere until the caller sets one: SB3's default makes /tmp/SB3-<date>/
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


# -- the learner's state as arrays ---------------------------------------------------------------
def _state_tree(model: CodesignSAC) -> dict:
    """The learner's state as a pytree: actor (parameters, Adam state, step count), critics
    (parameters, target parameters, Adam state), temperature (log α, Adam state) and the JAX
    random keys of the updates (``key``) and of the exploration noise (``policy_key``,
    ``noise_key``)."""
    p = model.policy
    return {"actor": p.actor_state, "qf": p.qf_state, "ent_coef": model.ent_coef_state,
            "key": model.key, "policy_key": p.key, "noise_key": p.noise_key}


def learner_state_bytes(model: CodesignSAC) -> bytes:
    """:func:`_state_tree` of ``model`` as flax msgpack bytes (arrays, numbers and strings only)."""
    return serialization.to_bytes(_state_tree(model))


def decode_learner_state(data: bytes) -> dict:
    """The nested dict of arrays that :func:`learner_state_bytes` wrote.

    msgpack decodes into arrays, numbers, strings and containers only: an array of Python
    objects cannot be decoded (numpy refuses ``frombuffer`` with an object dtype), and nothing
    is unpickled.

    Raises:
        ValueError: the bytes are not such a document.
    """
    try:
        raw = serialization.msgpack_restore(data)
    except Exception as exc:  # msgpack and dtype errors: all mean "not a learner state"
        raise ValueError(f"not a learner state ({_first_line(exc)})") from None
    if not isinstance(raw, dict) or set(raw) != {"actor", "qf", "ent_coef", "key", "policy_key", "noise_key"}:
        raise ValueError("not a learner state (not the document learner_state_bytes writes)")
    return raw


def restore_learner_state(model: CodesignSAC, raw: dict) -> None:
    """Put :func:`decode_learner_state` output into ``model`` (built with the same config):
    every array must have the shape of the model's own and a numeric dtype.

    Raises:
        ValueError: a learner state of another network layout or config.
    """
    target = _state_tree(model)
    try:
        restored = serialization.from_state_dict(target, raw)
    except Exception as exc:  # missing or extra keys
        raise ValueError(f"not a learner state of this config ({_first_line(exc)})") from None
    mine, theirs = jax.tree_util.tree_leaves(target), jax.tree_util.tree_leaves(restored)
    if len(mine) != len(theirs):
        raise ValueError("not a learner state of this config (another number of arrays)")
    for a, b in zip(mine, theirs):
        if np.shape(a) != np.shape(b) or np.asarray(b).dtype.kind not in "biuf":
            raise ValueError(f"not a learner state of this config (a {np.asarray(b).dtype} array of shape "
                             f"{np.shape(b)} where {np.shape(a)} was expected)")
    with model.on_device():
        restored = jax.device_put(restored, model.jax_device)
    p = model.policy
    p.actor_state, p.qf_state, model.ent_coef_state = restored["actor"], restored["qf"], restored["ent_coef"]
    model.key, p.key, p.noise_key = restored["key"], restored["policy_key"], restored["noise_key"]


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
