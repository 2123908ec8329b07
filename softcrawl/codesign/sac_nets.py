"""The JAX learner's networks and its critic and actor losses, the same as stable-baselines3's
SAC (torch) given the same weights, batch and noise (``tests/test_learner.py``).

SBX's defaults differ from SB3's in two places, both replaced here:

* Initialisation. flax's ``Dense`` draws kernels from LeCun normal (variance ``1/fan_in``) and
  zero biases; torch's ``nn.Linear`` (SB3's networks) draws kernels and biases from
  ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))`` (Kaiming uniform with ``a = sqrt(5)``, variance
  ``1/(3 fan_in)``; PyTorch ``torch.nn.Linear.reset_parameters``). :class:`Linear` draws as
  torch does, so a fresh actor starts with action means near 0 and log-std near 0 (std 1), as
  the torch learner's.
* The squashed Gaussian's log-density. SBX evaluates it with TensorFlow Probability's exact
  ``Tanh`` bijector; SB3 uses ``log N(u; mu, sigma) - sum log(1 - tanh(u)^2 + 1e-6)`` on the
  pre-squash sample ``u`` (Haarnoja et al. 2018, "Soft Actor-Critic: Off-Policy Maximum Entropy
  Deep RL with a Stochastic Actor", appendix C, eq. 21, with SB3's epsilon).
  :class:`SquashedGaussian` is SB3's.

The losses (:func:`critic_step`, :func:`actor_step`) are SB3's ``SAC.train``: critic
``0.5 * sum_i mean (Q_i(s, a) - y)^2`` with ``y = r + (1 - d) gamma (min_i Q'_i(s', a') -
alpha log pi(a'|s'))``, ``a' ~ pi(.|s')``; actor ``mean(alpha log pi(a~|s) - min_i Q_i(s, a~))``
with the critics' weights held fixed (Haarnoja et al. 2018, "Soft Actor-Critic Algorithms and
Applications", eqs. 5, 7). The temperature step, the target smoothing and the loop over the
updates are SBX's (:class:`sbx.SAC`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import flax
import flax.linen as nn
import jax
import jax.numpy as jnp

#: SB3's bounds of the actor's log standard deviation (``stable_baselines3.sac.policies``).
LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0
#: SB3's epsilon in the tanh correction of the log-density (``SquashedDiagGaussianDistribution``).
TANH_EPS = 1e-6


def standard_normal(key: jax.Array, shape: tuple[int, ...], dtype) -> jnp.ndarray:
    """The exploration noise of :class:`SquashedGaussian` (``jax.random.normal``; a test
    replaces it to compare with the torch learner without noise)."""
    return jax.random.normal(key, shape, dtype)


def _torch_uniform(fan_in: int):
    bound = 1.0 / jnp.sqrt(fan_in)
    return lambda key, shape, dtype=jnp.float32: jax.random.uniform(key, shape, dtype, -bound, bound)


class Linear(nn.Module):
    """``x @ kernel + bias`` drawn as torch's ``nn.Linear``: kernel ``(fan_in, features)`` and
    bias ``(features,)`` from ``U(-1/sqrt(fan_in), 1/sqrt(fan_in))``."""

    features: int

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> jnp.ndarray:
        init = _torch_uniform(x.shape[-1])
        kernel = self.param("kernel", init, (x.shape[-1], self.features))
        bias = self.param("bias", init, (self.features,))
        return x @ kernel + bias


@flax.struct.dataclass
class SquashedGaussian:
    """``a = tanh(u)``, ``u ~ N(mean, exp(log_std)^2)`` per action component; arrays of shape
    ``(batch, action_dim)``. The interface SBX's policy calls (``sample``, ``mode``) plus
    :meth:`sample_and_log_prob`, SB3's log-density."""

    mean: jnp.ndarray
    log_std: jnp.ndarray

    def sample(self, seed: jax.Array) -> jnp.ndarray:
        return self.sample_and_log_prob(seed)[0]

    def mode(self) -> jnp.ndarray:
        return jnp.tanh(self.mean)

    def sample_and_log_prob(self, seed: jax.Array) -> tuple[jnp.ndarray, jnp.ndarray]:
        """A reparameterised sample ``a`` (``(batch, action_dim)``) and ``log pi(a)``
        (``(batch,)``): ``sum_j [log N(u_j; mean_j, std_j) - log(1 - tanh(u_j)^2 + 1e-6)]``."""
        noise = standard_normal(seed, self.mean.shape, self.mean.dtype)
        u = self.mean + jnp.exp(self.log_std) * noise
        a = jnp.tanh(u)
        log_normal = -0.5 * noise**2 - self.log_std - 0.5 * jnp.log(2 * jnp.pi)
        return a, jnp.sum(log_normal - jnp.log(1 - a**2 + TANH_EPS), axis=-1)


class Actor(nn.Module):
    """SB3's SAC actor: MLP ``net_arch`` with ``activation_fn``, then linear heads for the mean
    and the log standard deviation (clipped to [-20, 2]) of :class:`SquashedGaussian`.
    Observations ``(batch, obs_dim)``."""

    net_arch: Sequence[int]
    action_dim: int
    activation_fn: Callable[[jnp.ndarray], jnp.ndarray] = nn.relu

    @nn.compact
    def __call__(self, x: jnp.ndarray) -> SquashedGaussian:
        x = x.reshape((x.shape[0], -1))
        for n in self.net_arch:
            x = self.activation_fn(Linear(n)(x))
        mean = Linear(self.action_dim)(x)
        return SquashedGaussian(mean, jnp.clip(Linear(self.action_dim)(x), LOG_STD_MIN, LOG_STD_MAX))


class Critic(nn.Module):
    """One Q network: MLP ``net_arch`` on ``[obs, action]``, a linear output ``(batch, 1)``."""

    net_arch: Sequence[int]
    activation_fn: Callable[[jnp.ndarray], jnp.ndarray] = nn.relu

    @nn.compact
    def __call__(self, obs: jnp.ndarray, action: jnp.ndarray) -> jnp.ndarray:
        x = jnp.concatenate([obs.reshape((obs.shape[0], -1)), action], -1)
        for n in self.net_arch:
            x = self.activation_fn(Linear(n)(x))
        return Linear(1)(x)


class VectorCritic(nn.Module):
    """``n_critics`` independent :class:`Critic` s (``nn.vmap`` over their parameters): Q values
    ``(n_critics, batch, 1)``. ``dropout_rate`` and ``use_layer_norm`` are accepted for SBX's
    policy and must be off (SB3's critics have neither)."""

    net_arch: Sequence[int]
    n_critics: int = 2
    activation_fn: Callable[[jnp.ndarray], jnp.ndarray] = nn.relu
    dropout_rate: float | None = None
    use_layer_norm: bool = False

    @nn.compact
    def __call__(self, obs: jnp.ndarray, action: jnp.ndarray) -> jnp.ndarray:
        if self.dropout_rate or self.use_layer_norm:
            raise ValueError("the critics have neither dropout nor layer norm")
        critics = nn.vmap(Critic, variable_axes={"params": 0}, split_rngs={"params": True},
                          in_axes=None, out_axes=0, axis_size=self.n_critics)
        return critics(self.net_arch, self.activation_fn)(obs, action)


@jax.jit
def critic_step(actor_state, qf_state, ent_coef_state, observations, actions, next_observations,
                rewards, dones, discounts, key):
    """One Adam step of the critics on SB3's soft Bellman loss (module docstring). Batch arrays:
    ``observations`` / ``next_observations`` ``(B, obs_dim)``, ``actions`` ``(B, action_dim)``,
    ``rewards``, ``dones`` (true terminals only), ``discounts`` ``(B,)``. Returns the new
    critic state, ``(loss, alpha)`` and the next key (SBX's ``update_critic`` signature)."""
    key, noise_key = jax.random.split(key)
    next_actions, next_log_prob = actor_state.apply_fn(actor_state.params, next_observations).sample_and_log_prob(
        noise_key)
    alpha = ent_coef_state.apply_fn({"params": ent_coef_state.params})
    next_q = jnp.min(qf_state.apply_fn(qf_state.target_params, next_observations, next_actions), axis=0)
    next_q = next_q - alpha * next_log_prob[:, None]
    target = jax.lax.stop_gradient(rewards[:, None] + (1 - dones[:, None]) * discounts[:, None] * next_q)

    def loss(params):
        return 0.5 * ((qf_state.apply_fn(params, observations, actions) - target) ** 2).mean(axis=(1, 2)).sum()

    value, grads = jax.value_and_grad(loss)(qf_state.params)
    return qf_state.apply_gradients(grads=grads), (value, alpha), key


@jax.jit
def actor_step(actor_state, qf_state, ent_coef_state, observations, key):
    """One Adam step of the actor on SB3's loss (module docstring), the critics' weights fixed.
    Returns the new actor state, the critic state (unchanged), the loss, the next key and the
    batch's entropy estimate ``-mean log pi`` (SBX's ``update_actor`` signature)."""
    key, noise_key = jax.random.split(key)
    alpha = ent_coef_state.apply_fn({"params": ent_coef_state.params})

    def loss(params):
        actions, log_prob = actor_state.apply_fn(params, observations).sample_and_log_prob(noise_key)
        q = jnp.min(qf_state.apply_fn(qf_state.params, observations, actions), axis=0)
        return (alpha * log_prob[:, None] - q).mean(), -log_prob.mean()

    (value, entropy), grads = jax.value_and_grad(loss, has_aux=True)(actor_state.params)
    return actor_state.apply_gradients(grads=grads), qf_state, value, key, entropy
