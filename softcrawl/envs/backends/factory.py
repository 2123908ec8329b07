"""The backend named in a run's settings (``serial``, ``subprocess``, ``ray``, ``jax``), imported
only when asked for: an optional backend's dependencies (Ray, JAX) load only when it is used."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence

import gymnasium as gym

from softcrawl.envs.backends.base import EnvBackend

#: Backend name -> ``"module:class"`` and the constructor keywords it takes from
#: :func:`make_backend`'s ``n_workers``, ``ray_address`` and ``jax`` options.
BACKENDS: dict[str, tuple[str, Callable[[int | None, str | None, dict], dict]]] = {
    "serial": ("softcrawl.envs.backends.serial:SerialBackend", lambda n_workers, address, jax: {}),
    "subprocess": ("softcrawl.envs.backends.subprocess:SubprocessBackend",
                   lambda n_workers, address, jax: {"n_workers": n_workers}),
    "ray": ("softcrawl.envs.backends.ray:RayBackend",
            lambda n_workers, address, jax: {"n_actors": n_workers, "address": address}),
    "jax": ("softcrawl.envs.backends.jaxvec:JaxBackend", lambda n_workers, address, jax: dict(jax)),
}


def make_backend(kind: str, env_fns: Sequence[Callable[[], gym.Env]], n_workers: int | None = None,
                 ray_address: str | None = None, jax: dict | None = None) -> EnvBackend:
    """The backend named ``kind``: ``"serial"``, ``"subprocess"`` (``n_workers`` processes),
    ``"ray"`` (``n_workers`` actors on a local Ray, or the cluster at ``ray_address``) or
    ``"jax"`` (all envs in one JAX batch on JAX's default device with the options ``jax``:
    ``precision``, ``solver``, ``iterations`` of :class:`softcrawl.envs.backends.jaxvec.JaxBackend`).

    Raises:
        ValueError: unknown kind. ImportError: ``"ray"`` without Ray, ``"jax"`` without JAX installed.
    """
    if kind not in BACKENDS:
        raise ValueError(f"unknown env backend {kind!r} ({', '.join(BACKENDS)})")
    target, options = BACKENDS[kind]
    module, _, name = target.partition(":")
    return getattr(importlib.import_module(module), name)(env_fns, **options(n_workers, ray_address, jax or {}))
