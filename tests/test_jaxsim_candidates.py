"""Each body's floor contact candidates in one kernel (:mod:`softcrawl.jaxsim.candidates`), run in
Pallas' interpreter, against XLA's choice (:func:`softcrawl.jaxsim.contact.floor_contacts` on
the lowered heights). The kernel inside a whole step: tests/test_jaxsim_delassus.py."""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

FAR = 1e6


@pytest.fixture(autouse=True, scope="module")
def _float64(x64):
    """Float64 available (``x64``: tests/conftest.py); each test names its arrays' dtype."""


def _xla_choice(z, vz, prev, held, K, floor_z, distance, dt):
    """The XLA program's choice for one body (:func:`softcrawl.jaxsim.delassus.select_contacts`):
    last step's loaded points lowered by ``FAR``, then ``floor_contacts``; the gaps of the points'
    own heights."""
    from softcrawl.jaxsim.contact import floor_contacts

    P = z.shape[0]
    loaded = jnp.zeros(P, bool).at[jnp.where(prev >= 0, prev, P)].max(held, mode="drop")
    idx, active, _ = floor_contacts(z - jnp.where(loaded, FAR, 0.0), vz, floor_z, distance, K, dt=dt)
    return idx, active, z[idx] - floor_z


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("P, K", [(1179, 12), (302, 8), (20, 16)])
def test_a_bodys_kernel_chooses_xlas_points(P, K, dtype):
    """On 6 random bodies a size (a leg's 1,179 points and 12 slots, the disk's 302 and 8, 20
    and 16), heights on a 0.25-mm grid so that predicted gaps tie (some within the contact
    distance, some loaded last step, one body all at ``FAR``: an absent leg's), the interpreted
    kernel gives XLA's indices, activity and gaps exactly: the same arithmetic, the same order
    (of equal predicted gaps the lowest index first, as ``lax.top_k``)."""
    from softcrawl.jaxsim.candidates import body_candidates

    rng = np.random.default_rng(P + K)
    for b in range(6):
        z = np.round(rng.uniform(-0.5, 3.0, P) * 4) / 4 if b < 5 else np.full(P, FAR)
        vz = np.where(rng.random(P) < 0.5, 0.0, np.round(rng.normal(0, 20, P)))
        prev = np.where(rng.random(K) < 0.7, rng.choice(P, K, replace=False), -1)
        held = rng.random(K) < 0.6
        args = (jnp.asarray(z, dtype), jnp.asarray(vz, dtype), jnp.asarray(prev), jnp.asarray(held))
        want = _xla_choice(*args, K, 0.0, 0.5, 0.02)
        got = body_candidates(*args, K=K, far=FAR, floor_z=0.0, distance=0.5, dt=0.02, interpret=True)
        for g, w in zip(got, want):  # the indices int32 (XLA's int64 with float64 on)
            assert g.dtype == w.dtype or g.dtype == jnp.int32
            np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
        if b == 0:
            assert np.sum(np.asarray(want[1])) > 0 and len(set(np.round(z - 0.0, 2)[np.asarray(want[0])])) < K


def test_a_batch_of_bodies_is_one_program_each():
    """Under ``jax.vmap`` (the step's legs and robots) each body's choice is its own."""
    from softcrawl.jaxsim.candidates import body_candidates

    rng = np.random.default_rng(1)
    z, vz = jnp.asarray(rng.uniform(0, 2, (3, 50))), jnp.asarray(rng.normal(0, 5, (3, 50)))
    prev, held = jnp.asarray(rng.choice(50, (3, 4))), jnp.asarray(rng.random((3, 4)) < 0.5)

    def one(*a):
        return body_candidates(*a, K=4, far=FAR, floor_z=0.0, distance=0.5, dt=0.02, interpret=True)

    batch = jax.vmap(one)(z, vz, prev, held)
    for r in range(3):
        for a, b in zip(batch, one(z[r], vz[r], prev[r], held[r])):
            np.testing.assert_array_equal(np.asarray(a[r]), np.asarray(b))


def test_a_body_with_more_slots_than_lanes_or_points_is_refused():
    from softcrawl.jaxsim.candidates import body_candidates

    z = jnp.zeros(10)
    for K in (0, 11, 17):
        with pytest.raises(ValueError, match="K <= min"):
            body_candidates(z, z, jnp.zeros(K, int), jnp.zeros(K, bool), K=K, far=FAR, floor_z=0.0, distance=0.5,
                            dt=0.02, interpret=True)
    with pytest.raises(ValueError, match="prev and held"):
        body_candidates(z, z, jnp.zeros(3, int), jnp.zeros(4, bool), K=4, far=FAR, floor_z=0.0, distance=0.5,
                        dt=0.02, interpret=True)
