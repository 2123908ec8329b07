"""The JAX backend's whole episodes (:meth:`softcrawl.envs.backends.jaxvec.JaxBackend.run_episodes`:
all envs' episodes in one compiled call) against its own per-action steps, with the rig's
randomization (per-env regulators, warp and dilated actions) and an env whose robot diverges."""

import dataclasses

import numpy as np
import pytest

jax = pytest.importorskip("jax")

BEST = (1, 0, 0, 2, 2, 0, 0, 0)  # 3 legs on two regulators
FOUR = (1, 0, 2, 0, 1, 0, 3, 0)  # 4 legs on three regulators


@pytest.fixture(scope="module", autouse=True)
def _x64(x64):
    """float64 for the module (the backend sets it; the caller's setting is restored after)."""


def test_whole_episodes_on_the_jax_backend_are_its_per_action_steps():
    """Two envs (3 and 4 legs), three 0.5-s actions each with the rig's randomization: the
    transitions of the one-call episodes are those of three :meth:`step` calls from the same
    reset (observations and flags to the bit, rewards, positions and pressures to 1e-9: the
    same compiled step, scanned). Env 1's robot spoiled (an inverted element) before its
    episode: it ends at its first action, diverged, with reward 0, and env 0's episode is
    unchanged."""
    from softcrawl.codesign.config import override, preset
    from softcrawl.codesign.factory import env_fn
    from softcrawl.envs.backends import make_backend

    cfg = override(preset("smoke"), ['backend="jax"', "env.steps_per_action=50", "env.n_actions=3",
                                     "env.legs=[3, 4]", "env.randomize=rig"])
    actions = np.random.default_rng(0).uniform(-1, 1, (2, 3, 3)).astype(np.float32)
    b = make_backend("jax", [env_fn(cfg)] * 2)
    try:
        b.reset(range(2), [BEST, FOUR], (0, 1))
        per_action = [b.step(actions[:, k]) for k in range(3)]
        b.reset(range(2), [BEST, FOUR], (0, 1))
        episodes = b.run_episodes(actions)
        b.reset(range(2), [BEST, FOUR], (0, 1))
        b._state = dataclasses.replace(b._state, bad=b._state.bad.at[1].set(1))
        spoiled = b.run_episodes(actions)
    finally:
        b.close()
    assert [len(e) for e in episodes] == [3, 3] and [len(e) for e in spoiled] == [3, 1]
    for i in range(2):
        for k, (o, r, term, trunc, info) in enumerate(episodes[i]):
            o_ref, r_ref, term_ref, trunc_ref, info_ref = per_action[k][i]
            np.testing.assert_array_equal(o, o_ref)
            assert (term, trunc) == (term_ref, trunc_ref) == (False, k == 2)
            assert r == pytest.approx(r_ref, abs=1e-9) and abs(r) > 0
            assert set(info) == set(info_ref) and info["domain"] == info_ref["domain"]
            for key in ("disk_position_mm", "applied_kpa", "commanded_kpa"):
                np.testing.assert_allclose(info[key], info_ref[key], rtol=0, atol=1e-9)
    for (o, r, *_), (o_ref, r_ref, *_) in zip(spoiled[0], episodes[0]):
        np.testing.assert_array_equal(o, o_ref)
        assert r == r_ref
    _, reward, term, trunc, info = spoiled[1][0]
    assert term and not trunc and info["diverged"] and "JAX engine" in info["reason"] and reward == 0.0
