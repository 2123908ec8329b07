"""The device replay buffer of episode-at-once training (:mod:`softcrawl.codesign.replay`) against
flashbax's item buffer, the maintained JAX replay buffer: the wall seconds of one round's work on
JAX's default device, alternating the two ``--repeats`` times (medians). Prints JSON.

A round: add ``--rows`` transitions (the ``paper`` preset's round: 96 envs x 20 actions) to a
buffer of ``--capacity`` rows (100K), then draw the rows of ``--updates`` batches of ``--batch``
(512) uniformly with replacement and gather them (what the compiled update reads), each side's
operations in one compiled call, the round's transitions coming from the host. flashbax is optional (``pip install flashbax``); without it only
softcrawl's buffer is timed.

    python benchmarks/replay_buffer.py [--rows 1920] [--capacity 100000] [--batch 512] [--updates 96]
        [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import time

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np

from softcrawl.codesign.replay import FIELDS, DeviceReplay, gather


def _rows(n: int, rng) -> dict[str, np.ndarray]:
    return {"observations": rng.uniform(-1, 1, (n, 44)), "next_observations": rng.uniform(-1, 1, (n, 44)),
            "actions": rng.uniform(-1, 1, (n, 3)), "rewards": rng.normal(size=n), "dones": np.zeros(n),
            "timeouts": np.zeros(n)}


def softcrawl_round(args):
    """A zero-argument round of :class:`DeviceReplay` (``add``, then rows drawn and gathered)."""
    replay = DeviceReplay(args.capacity, gym.spaces.Box(-1, 1, (44,), np.float32), gym.spaces.Box(-1, 1, (3,),
                                                                                                   np.float32))
    rows = {k: np.asarray(v, np.float32) for k, v in _rows(args.rows, np.random.default_rng(0)).items()}

    @jax.jit
    def draw(arrays, size, key):
        index = jax.random.randint(key, (args.updates, args.batch), 0, size)
        return jax.vmap(lambda i: gather(arrays, i))(index)

    key = jax.random.PRNGKey(0)

    def run():
        nonlocal key
        replay.add(rows, args.rows)
        key, sub = jax.random.split(key)
        jax.block_until_ready(draw(replay.device_arrays(), replay.size(), sub))

    return run


def flashbax_round(args):
    """The same round with flashbax's item buffer (``add_batches``; one ``sample`` per batch)."""
    import flashbax

    buf = flashbax.make_item_buffer(max_length=args.capacity, min_length=1, sample_batch_size=args.batch,
                                    add_batches=True)
    rows = {k: np.asarray(v, np.float32) for k, v in _rows(args.rows, np.random.default_rng(0)).items()}
    state = buf.init({k: jnp.asarray(v[0]) for k, v in rows.items()})
    add = jax.jit(buf.add, donate_argnums=0)

    @jax.jit
    def draw(state, key):
        samples = jax.vmap(lambda k: buf.sample(state, k).experience)(jax.random.split(key, args.updates))
        return {k: samples[k] for k in FIELDS}

    key = jax.random.PRNGKey(0)

    def run():
        nonlocal state, key
        state = add(state, jax.device_put(rows))  # from the host, as the training loop's rounds
        key, sub = jax.random.split(key)
        jax.block_until_ready(draw(state, sub))

    return run


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rows", type=int, default=1920, help="transitions added per round")
    p.add_argument("--capacity", type=int, default=100_000)
    p.add_argument("--batch", type=int, default=512)
    p.add_argument("--updates", type=int, default=96, help="batches drawn per round")
    p.add_argument("--repeats", type=int, default=5)
    args = p.parse_args()
    rounds = {"softcrawl": softcrawl_round(args)}
    try:
        rounds["flashbax"] = flashbax_round(args)
    except ImportError:
        pass
    for run in rounds.values():
        run()  # compile
    seconds = {k: [] for k in rounds}
    for _ in range(args.repeats):
        for k, run in rounds.items():
            t = time.perf_counter()
            run()
            seconds[k].append(time.perf_counter() - t)
    out = {"machine": platform.platform(), "jax": jax.__version__, "device": str(jax.devices()[0]), **vars(args),
           "round_s": {k: statistics.median(v) for k, v in seconds.items()}, "rounds_s": seconds}
    if len(rounds) == 2:
        out["flashbax_over_softcrawl"] = out["round_s"]["flashbax"] / out["round_s"]["softcrawl"]
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
