"""Where a vector env's crawlers run: the *backend* interface (:class:`EnvBackend`,
:mod:`~softcrawl.envs.backends.base`): ``reset`` given env indices, designs and seeds, ``step``
of all envs, ``get_attr``/``set_attr``/``call`` and ``close``.

Backends:

- :class:`SerialBackend` (:mod:`~softcrawl.envs.backends.serial`): in-process, one env after another;
- :class:`~softcrawl.envs.backends.batched.BatchedBackend`: in-process, the envs' reduced robots
  stepped as one batch (what a subprocess worker runs);
- :class:`SubprocessBackend` (:mod:`~softcrawl.envs.backends.subprocess`): ``multiprocessing``
  workers connected by pipes, each holding a contiguous chunk of the envs
  (:class:`ChunkedBackend`, :func:`env_chunks`);
- :class:`~softcrawl.envs.backends.ray.RayBackend`: Ray actors (optional extra ``softcrawl[ray]``);
- :class:`~softcrawl.envs.backends.jaxvec.JaxBackend`: in-process, the robots one batch of the JAX
  engine (:mod:`softcrawl.jaxsim`, optional extra ``softcrawl[jax]``) on JAX's default device.

:func:`make_backend` (:mod:`~softcrawl.envs.backends.factory`) picks one by name and imports
it then. The package imports neither stable-baselines3 nor torch (:mod:`softcrawl.envs.vec`
holds the SB3 ``VecEnv``): a subprocess worker imports only what stepping needs.
"""

from softcrawl.envs.backends.base import EnvBackend, StepResult
from softcrawl.envs.backends.chunked import ChunkedBackend, env_chunks
from softcrawl.envs.backends.factory import BACKENDS, make_backend
from softcrawl.envs.backends.serial import SerialBackend
from softcrawl.envs.backends.subprocess import SubprocessBackend

__all__ = ["BACKENDS", "ChunkedBackend", "EnvBackend", "SerialBackend", "StepResult", "SubprocessBackend",
           "env_chunks", "make_backend"]
