"""Episode-at-once training with a device-resident learner (``rollout = "episode"``;
docs/codesign.md, "Episode-at-once training").

An open-loop policy's observation is the design's one-hot code and its own last actions
(:class:`softcrawl.envs.crawler.CrawlerEnv` without ``observe_state``): it never reads the
physics, so a whole episode's actions can be drawn when the episode starts. Training runs in
rounds of one episode of every env (:meth:`EpisodicSAC.learn`):

1. **Actions.** Every env has just been reset. Its ``n_actions`` actions come from the current
   policy in one compiled scan of the actor (:func:`episode_actions`): each step's observation
   is the design's code and the actions drawn before it, most recent first, zeros before the
   first, as :class:`~softcrawl.envs.crawler.CrawlerEnv` builds it; each action is a sample of
   the squashed Gaussian, clipped to [-1, 1] (SB3's ``predict``). The actions of the steps
   that start before ``learning_starts`` transitions are uniform random draws of the action
   space's RNG instead, in the order SB3's warm-up draws them. The action an env takes is the
   action the replay buffer keeps (the action space is [-1, 1]: SB3's rescaling is the identity).
2. **Physics.** The backend runs every env's episode from its actions
   (:meth:`softcrawl.envs.vec.DesignVecEnv.run_episodes`: one compiled call for all envs on the
   JAX backend, one message per worker on the subprocess and Ray backends); the transitions are
   those that stepping one action at a time gives for the same actions, to the bit
   (tests/test_episodic.py). An env whose episode ends early (divergence, a task's goal) waits
   for the others; every env is reset with a new design at the round's end.
3. **Bookkeeping**, per vectorised step of the round, as stable-baselines3's loop does it:
   the callback (:class:`softcrawl.codesign.training.CodesignCallback`: progress, episodes.csv,
   distribution.csv, snapshots, checkpoints due), the finished episodes' returns to the design
   sampler, SB3's episode statistics and log dumps.
4. **Replay.** The round's transitions go into the replay buffer on the learner's device
   (:class:`~softcrawl.codesign.replay.DeviceReplay`), step by step, env by env, as stepping
   adds them.
5. **Updates.** The gradient updates that fell due over the round's steps (SB3's schedule:
   ``gradient_steps`` after each vectorised step once more than ``learning_starts`` transitions
   were made) in one compiled call (:func:`device_updates`): all batches' rows drawn on the
   device, then per update the sbx learner's critic step
   (:func:`~softcrawl.codesign.sac_nets.critic_step`: SB3's loss, ``sac.timeout``'s terminal
   flags), SBX's target smoothing (``tau``), actor step
   (:func:`~softcrawl.codesign.sac_nets.actor_step`) and automatic temperature step (target
   ``sac.target_entropy``), at the split learning rates; ``jax.lax.scan`` over the updates
   (:func:`scanned_updates`). From the same weights, batches and key they give the parameters
   the per-action learner's compiled updates give (tests/test_device_learner.py). With
   ``sac.overlap`` they run while the next round's episodes run.

**Lag.** The policy acting in a round is the one at its start: the last action of an episode
misses the updates of its own round (``n_actions x gradient_steps``, 1,920 of the ``paper``
preset's 1M), and with ``sac.overlap`` those of the round before as well.

**Length.** A run is made of whole rounds: it ends at the first episode boundary at or after
``total_steps`` transitions (the ``paper`` preset: 1,000,320), and a round whose envs all
take every action adds ``n_envs x n_actions`` transitions.

**Checkpoints** are written at round boundaries (every env just reset), so a resumed run is the
uninterrupted one (tests/test_episodic.py); they hold what the per-action sbx learner's do
(:mod:`softcrawl.codesign.checkpoints`): the learner's state as flax msgpack, the device
buffer's arrays as ``replay_buffer.npz`` (flat rows, :mod:`~softcrawl.codesign.replay`), the
counters, the sampler and the RNGs as JSON.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from softcrawl.codesign.config import SACConfig
from softcrawl.codesign.replay import FIELDS, DeviceReplay, gather
from softcrawl.codesign.sac_jax import CodesignSAC, make_sac


@partial(jax.jit, static_argnames=("history",))
def episode_actions(actor_state, first_obs, key, warmup_actions, warmup, history: int):
    """The actions of every env's episode, drawn from the actor in one compiled scan.

    Args:
        actor_state: the actor's flax ``TrainState`` (:class:`~softcrawl.codesign.sac_nets.Actor`).
        first_obs: ``(N, obs_dim)`` the envs' first observations: the design's code, then
            ``history`` zero actions.
        key: JAX random key of the episode's exploration noise (one split per step).
        warmup_actions: ``(K, N, R)`` actions taken instead of the policy's at the steps
            where ``warmup`` ``(K,)`` is set.
        history: past actions in an observation.

    Returns ``(actions, observations)``: ``(N, K, R)`` in [-1, 1] and the observations they were
    drawn at, ``(N, K, obs_dim)``.
    """
    n, k_steps, r = first_obs.shape[0], warmup.shape[0], warmup_actions.shape[2]
    code = first_obs[:, :first_obs.shape[1] - history * r]

    def step(past, inputs):
        noise, random, warm = inputs
        obs = jnp.concatenate([code, past.reshape(n, history * r)], axis=1)
        action = jnp.clip(actor_state.apply_fn(actor_state.params, obs).sample(seed=noise), -1.0, 1.0)
        action = jnp.where(warm, random, action)
        if history:
            past = jnp.concatenate([action[:, None], past[:, :-1]], axis=1)
        return past, (action, obs)

    past = jnp.zeros((n, history, r), first_obs.dtype)
    _, (actions, obs) = jax.lax.scan(step, past, (jax.random.split(key, k_steps), warmup_actions, warmup))
    return actions.swapaxes(0, 1), obs.swapaxes(0, 1)


def scanned_updates(arrays: dict, index: jax.Array, key: jax.Array, qf_state, actor_state, ent_coef_state,
                    tau, target_entropy, gamma):
    """``len(index)`` SAC updates, one per row of ``index`` ``(G, B)`` (the replay rows of its
    batch), ``jax.lax.scan`` over them: per update the critic step, target smoothing, actor step
    and temperature step of the sbx learner (:class:`~softcrawl.codesign.sac_jax.CodesignSAC`:
    SB3's losses, SBX's smoothing and temperature), discount ``gamma``. Traceable.

    Returns the new critic, actor and temperature states, the next key and the last update's
    ``(actor loss, critic loss, temperature loss, temperature)``.
    """

    def update(carry, rows):
        qf, actor, ent, key = carry
        b = gather(arrays, rows)
        discounts = jnp.full(rows.shape, gamma, jnp.float32)
        qf, (qf_loss, alpha), key = CodesignSAC.update_critic(actor, qf, ent, b["observations"], b["actions"],
                                                              b["next_observations"], b["rewards"], b["dones"],
                                                              discounts, key)
        qf = CodesignSAC.soft_update(tau, qf)
        actor, qf, ent, actor_loss, ent_loss, key = CodesignSAC.update_actor_and_temperature(
            actor, qf, ent, b["observations"], target_entropy, key)
        return (qf, actor, ent, key), (actor_loss, qf_loss, ent_loss, alpha)

    (qf_state, actor_state, ent_coef_state, key), info = jax.lax.scan(
        update, (qf_state, actor_state, ent_coef_state, key), index)
    return qf_state, actor_state, ent_coef_state, key, tuple(v[-1] for v in info)


@partial(jax.jit, static_argnames=("gradient_steps", "batch_size"))
def device_updates(arrays: dict, size, key: jax.Array, qf_state, actor_state, ent_coef_state, tau, target_entropy,
                   gamma, gradient_steps: int, batch_size: int):
    """:func:`scanned_updates` of ``gradient_steps`` batches of ``batch_size`` rows drawn
    uniformly (with replacement) from the ``size`` rows of the replay ``arrays``
    (:meth:`DeviceReplay.device_arrays`), the rows' key split from ``key`` first; one compiled
    call."""
    key, rows_key = jax.random.split(key)
    index = jax.random.randint(rows_key, (gradient_steps, batch_size), 0, size)
    return scanned_updates(arrays, index, key, qf_state, actor_state, ent_coef_state, tau, target_entropy, gamma)


class EpisodicSAC(CodesignSAC):
    """The sbx learner trained a round of whole episodes at a time, its replay buffer and
    updates on its JAX device (module doc). Its state, checkpoints and ``predict`` are the sbx
    learner's (:class:`~softcrawl.codesign.sac_jax.CodesignSAC`); its env must be a
    :class:`~softcrawl.envs.vec.DesignVecEnv` of :class:`~softcrawl.envs.crawler.CrawlerEnv` s
    (``run_episodes``, ``n_actions``, ``history``).

    Raises:
        ValueError: an env without whole-episode rollouts.
    """

    rollout = "episode"

    def __init__(self, *args, jax_device: jax.Device | None = None, **kwargs):
        device = jax_device or jax.devices("cpu")[0]
        kwargs["replay_buffer_kwargs"] = {**(kwargs.get("replay_buffer_kwargs") or {}), "jax_device": device}
        super().__init__(*args, jax_device=device, replay_buffer_class=DeviceReplay, **kwargs)
        if not hasattr(self.env, "run_episodes"):
            raise ValueError(f'rollout "episode" needs a DesignVecEnv (whole episodes), got {type(self.env).__name__}')
        self.n_actions = int(self.env.get_attr("n_actions", [0])[0])
        self.history = int(self.env.get_attr("history", [0])[0])

    # -- the loop -----------------------------------------------------------------------------
    def learn(self, total_timesteps: int, callback=None, log_interval: int = 4, tb_log_name: str = "SAC",
              reset_num_timesteps: bool = True, progress_bar: bool = False):
        """Train for ``total_timesteps`` more transitions (SB3's ``learn`` arguments) in rounds of
        whole episodes, ending at the first round boundary at or beyond them (module doc). A
        callback's ``on_step`` returning False ends training after its round's transitions are
        stored, before the round's updates."""
        total, callback = self._setup_learn(total_timesteps, callback, reset_num_timesteps, tb_log_name, progress_bar)
        callback.on_training_start(locals(), globals())
        while self.num_timesteps < total:
            callback.on_rollout_start()
            if not self._round(callback, log_interval):
                break
            callback.on_rollout_end()
        callback.on_training_end()
        return self

    def _round(self, callback, log_interval: int | None) -> bool:
        """One round (module doc, steps 1-5); False if the callback asked to stop."""
        self._commit_states()
        n = self.env.num_envs
        taken = self.draw_actions(self._last_obs)
        steps = self.env.run_episodes(taken)
        rows: dict[str, list] = {k: [] for k in FIELDS}
        before, due, go_on = self._last_obs, 0, True
        for k, step in enumerate(steps):
            self.num_timesteps += int(step.live.sum())
            callback.update_locals({"infos": step.infos, "dones": step.dones, "rewards": step.rewards,
                                    "new_obs": step.obs})
            go_on = callback.on_step() and go_on
            self._update_info_buffer(step.infos, step.dones)
            after = step.obs.copy()
            for i in np.flatnonzero(step.dones):
                after[i] = step.infos[i]["terminal_observation"]
            live = step.live
            for name, value in (("observations", before[live]), ("next_observations", after[live]),
                                ("actions", taken[live, k]), ("rewards", step.rewards[live]),
                                ("dones", step.dones[live]),
                                ("timeouts", [step.infos[i]["TimeLimit.truncated"] if step.dones[i] else False
                                              for i in np.flatnonzero(live)])):
                rows[name].append(np.asarray(value))
            before = step.obs
            if self.num_timesteps > self.learning_starts:
                due += self.gradient_steps
            for _ in np.flatnonzero(step.dones):
                self._episode_num += 1
                if log_interval is not None and self._episode_num % log_interval == 0:
                    self.dump_logs()
        self._last_obs = steps[-1].obs
        self._store(rows, n * self.n_actions)
        self._update_current_progress_remaining(self.num_timesteps, self._total_timesteps)
        if go_on and due:
            self.train(gradient_steps=due, batch_size=self.batch_size)
        return go_on

    def _commit_states(self) -> None:
        """The networks', optimizers' and temperature's states and the keys as strong-typed
        arrays committed to :attr:`jax_device`, so that :func:`device_updates` and
        :func:`episode_actions` see the same argument types every round and compile once. SBX
        makes some leaves from Python scalars (weakly typed, uncommitted), and an update's
        outputs would otherwise change those types round after round."""
        def commit(tree):
            return jax.tree_util.tree_map(
                lambda a: jax.device_put(jnp.asarray(a, dtype=jnp.asarray(a).dtype), self.jax_device), tree)

        p = self.policy
        with self.on_device():
            p.qf_state, p.actor_state, self.ent_coef_state, self.key, p.noise_key = commit(
                (p.qf_state, p.actor_state, self.ent_coef_state, self.key, p.noise_key))

    def draw_actions(self, first_obs: np.ndarray) -> np.ndarray:
        """Every env's actions ``(N, n_actions, R)`` for the episodes starting at
        ``first_obs`` ``(N, obs_dim)`` (module doc, step 1): the warm-up's uniform draws where
        the step starts before ``learning_starts`` transitions, else :func:`episode_actions`
        of the current actor with the policy's next noise key (SBX's ``reset_noise``)."""
        n, r = self.env.num_envs, self.action_space.shape[0]
        warm = np.array([self.num_timesteps + k * n < self.learning_starts for k in range(self.n_actions)])
        random = np.zeros((self.n_actions, n, r), np.float32)
        for k in np.flatnonzero(warm):
            random[k] = [self.action_space.sample() for _ in range(n)]
        if warm.all():
            return np.ascontiguousarray(random.swapaxes(0, 1))
        with self.on_device():
            self.policy.reset_noise()
            actions, _ = episode_actions(self.policy.actor_state, jnp.asarray(first_obs, jnp.float32),
                                         self.policy.noise_key, random, warm, history=self.history)
        return np.asarray(actions)

    def _store(self, rows: dict[str, list], length: int) -> None:
        """The round's transitions (:data:`~softcrawl.codesign.replay.FIELDS` -> per-step
        arrays) into the replay buffer, padded to ``length`` rows (one compiled write)."""
        out = {}
        for name, parts in rows.items():
            a = np.concatenate(parts)
            out[name] = np.concatenate([a, np.zeros((length - len(a), *a.shape[1:]), a.dtype)])
        self.replay_buffer.add(out, sum(len(p) for p in rows["rewards"]))

    # -- the updates ----------------------------------------------------------------------------
    def run_updates(self, gradient_steps: int, batch_size: int) -> None:
        """``gradient_steps`` updates on the device in one compiled call (:func:`device_updates`);
        returns once they are done (their losses are read for the logs)."""
        if self.policy_delay != 1:
            raise ValueError("the device updates update the actor at every step (policy_delay 1)")
        rb, p = self.replay_buffer, self.policy
        with self.on_device():
            p.qf_state, p.actor_state, self.ent_coef_state, self.key, info = device_updates(
                rb.device_arrays(), rb.size(), self.key, p.qf_state, p.actor_state, self.ent_coef_state, self.tau,
                self.target_entropy, self.gamma, gradient_steps=gradient_steps, batch_size=batch_size)
            actor_loss, qf_loss, ent_loss, alpha = (float(v) for v in info)
        self._n_updates += gradient_steps
        self.logger.record("train/n_updates", self._n_updates, exclude="tensorboard")
        self.logger.record("train/actor_loss", actor_loss)
        self.logger.record("train/critic_loss", qf_loss)
        self.logger.record("train/ent_coef_loss", ent_loss)
        self.logger.record("train/ent_coef", alpha)


def make_episodic_sac(env, cfg: SACConfig, seed: int | None = None) -> EpisodicSAC:
    """The episode-at-once learner for vectorised crawler env ``env`` (a
    :class:`~softcrawl.envs.vec.DesignVecEnv`): the sbx learner of ``cfg``
    (:func:`softcrawl.codesign.sac_jax.make_sac`) with the device replay buffer and loop.

    Raises:
        ValueError: ``cfg.learner`` is not ``"sbx"``, ``cfg.device`` is not a device JAX can
            use, or ``env`` has no whole-episode rollouts.
    """
    if cfg.learner != "sbx":
        raise ValueError(f'rollout "episode" runs the "sbx" learner, not {cfg.learner!r}')
    return make_sac(env, cfg, seed, cls=EpisodicSAC)
