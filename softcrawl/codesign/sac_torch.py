"""The torch learner (``sac.learner = "torch"``): stable-baselines3's SAC with separate policy
and Q learning rates (:mod:`softcrawl.codesign.sac` describes the algorithm and the time limit).

Its state is written with ``torch.save`` and read with ``torch.load(weights_only=True)``
(tensors and plain containers only; a pickle of anything else is refused).
"""

from __future__ import annotations

import io

import torch

from stable_baselines3 import SAC
from stable_baselines3.common.logger import Logger

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.sac_common import OverlappedUpdates, sb3_arguments


class SplitLRSAC(OverlappedUpdates, SAC):
    """SAC whose critic optimizer uses ``q_learning_rate`` (a float); the actor and the entropy
    temperature use ``learning_rate`` (SB3's).

    Updates are overlapped with the simulation if ``overlap`` (:class:`OverlappedUpdates`).

    The actor's step differentiates the critics' Q values with respect to the action only: the
    critics' weights are frozen from their optimizer's step to the actor optimizer's step
    (optimizer hooks), so the actor's backward pass skips their weight gradients, which SB3
    computes and then discards (about 11% of an update's matrix products; updates 1.15-1.19x
    faster, ``CHANGELOG.md``, and the same to the bit, ``tests/test_learner_torch.py``).
    Everything else is SB3's SAC.

    Attributes:
        learner: ``"torch"``, the ``sac.learner`` name.
    """

    learner = "torch"

    def __init__(self, *args, q_learning_rate: float | None = None, overlap: bool = False, **kwargs):
        self.q_learning_rate = q_learning_rate
        super().__init__(*args, **kwargs)
        self.hook_overlap(overlap)
        self.critic.optimizer.register_step_post_hook(lambda *_: self._critic_weight_grads(False))
        self.actor.optimizer.register_step_post_hook(lambda *_: self._critic_weight_grads(True))

    def _critic_weight_grads(self, on: bool) -> None:
        for p in self.critic.parameters():
            p.requires_grad_(on)

    def run_updates(self, gradient_steps: int, batch_size: int) -> None:
        """SB3's updates."""
        self._critic_weight_grads(True)  # in case an interrupted update left them frozen
        SAC.train(self, gradient_steps, batch_size)

    def _update_learning_rate(self, optimizers) -> None:
        critic_opt = self.critic.optimizer
        super()._update_learning_rate([o for o in optimizers if o is not critic_opt])
        if self.q_learning_rate is not None:
            for group in critic_opt.param_groups:
                group["lr"] = float(self.q_learning_rate)
            self.logger.record("train/q_learning_rate", float(self.q_learning_rate))


def configure_threads(threads: int) -> None:
    """torch's intra-op threads of the learner."""
    torch.set_num_threads(threads)


def check_device(device: str) -> None:
    """Raise ValueError unless torch can place tensors on ``device`` ("cpu", "cuda", "cuda:N";
    "gpu" / "gpu:N" are read as "cuda" / "cuda:N")."""
    device = _torch_device(device)
    if device == "cpu":
        return
    if not torch.cuda.is_available():
        raise ValueError(f"sac.device={device!r}, but torch {torch.__version__} sees no CUDA GPU "
                         "(use sac.device=cpu, or install a CUDA build of torch)")
    index = int(device.partition(":")[2] or 0)
    if index >= torch.cuda.device_count():
        raise ValueError(f"sac.device={device!r}, but torch sees {torch.cuda.device_count()} CUDA GPU(s)")


def make_sac(env, cfg: SACConfig, seed: int | None = None) -> SplitLRSAC:
    """The SAC learner for a vectorised crawler env.

    SB3's settings from ``cfg`` (:func:`~softcrawl.codesign.sac_common.sb3_arguments`: update
    ratio, temperature, time limit). Networks: MLP ``cfg.net_arch`` with ReLU for the actor and
    both critics; Adam(β1 0.9, β2 0.999); updates overlapped with the simulation if
    ``cfg.overlap`` (:class:`SplitLRSAC`), on torch device ``cfg.device``. Its logger writes
    nowhere until ``set_logger`` is called (SB3's default would create ``/tmp/SB3-<date>/``).

    Raises:
        ValueError: ``cfg.device`` is a GPU this torch cannot use.
    """
    check_device(cfg.device)
    model = SplitLRSAC(
        "MlpPolicy", env, learning_rate=cfg.policy_lr, q_learning_rate=cfg.q_lr,
        policy_kwargs={"net_arch": list(cfg.net_arch), "optimizer_kwargs": {"betas": (0.9, 0.999)}},
        seed=seed, device=_torch_device(cfg.device), overlap=cfg.overlap, **sb3_arguments(env, cfg),
    )
    # a logger writing nowhere until the caller sets one: SB3's default makes /tmp/SB3-<date>/
    model.set_logger(Logger(folder=None, output_formats=[]))
    return model


def _torch_device(device: str) -> str:
    return device.replace("gpu", "cuda")


_STATE_KEYS = {"policy", "actor_optimizer", "critic_optimizer", "log_ent_coef", "ent_coef_optimizer", "torch_rng"}


def learner_state_bytes(model: SplitLRSAC) -> bytes:
    """The learner's state (policy and critics with their targets, Adam states, log temperature,
    torch's RNG) as ``torch.save`` bytes of tensors and plain containers."""
    buf = io.BytesIO()
    torch.save({
        "policy": model.policy.state_dict(),
        "actor_optimizer": model.actor.optimizer.state_dict(),
        "critic_optimizer": model.critic.optimizer.state_dict(),
        "log_ent_coef": model.log_ent_coef.detach().clone(),
        "ent_coef_optimizer": model.ent_coef_optimizer.state_dict(),
        "torch_rng": torch.get_rng_state(),
    }, buf)
    return buf.getvalue()


def decode_learner_state(data: bytes) -> dict:
    """The dict that :func:`learner_state_bytes` wrote, read with ``torch.load(weights_only=True)``
    on the CPU (nothing but tensors and plain containers is unpickled).

    Raises:
        ValueError: not such a document.
    """
    try:
        raw = torch.load(io.BytesIO(data), weights_only=True, map_location="cpu")
    except Exception as exc:  # UnpicklingError (refused), zip and EOF errors
        raise ValueError(f"not a tensors-only checkpoint ({_first_line(exc)})") from None
    if not isinstance(raw, dict) or set(raw) != _STATE_KEYS:
        raise ValueError("not a learner state (not the document learner_state_bytes writes)")
    return raw


def restore_learner_state(model: SplitLRSAC, raw: dict) -> None:
    """Put :func:`decode_learner_state` output into ``model`` (built with the same config) and
    set torch's RNG.

    Raises:
        ValueError: a learner state of another network layout or config.
    """
    try:
        model.policy.load_state_dict(raw["policy"])
        model.actor.optimizer.load_state_dict(raw["actor_optimizer"])
        model.critic.optimizer.load_state_dict(raw["critic_optimizer"])
        with torch.no_grad():
            model.log_ent_coef.copy_(raw["log_ent_coef"])
        model.ent_coef_optimizer.load_state_dict(raw["ent_coef_optimizer"])
        torch.set_rng_state(raw["torch_rng"])
    except Exception as exc:  # state_dict keys and shapes, RNG state type
        raise ValueError(f"not a learner state of this config ({_first_line(exc)})") from None


def _first_line(exc: BaseException) -> str:
    return str(exc).splitlines()[0][:200] if str(exc) else type(exc).__name__
