"""Each body's floor contact candidates in one kernel (:mod:`softcrawl.jaxsim.candidates`), run in
Pallas' interpreter, against XLA's choice for all bodies at once
(:func:`softcrawl.jaxsim.delassus.select_contacts`' program). The kernel inside a whole step:
tests/test_jaxsim_delassus.py."""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
import jax.numpy as jnp  # noqa: E402

FAR = 1e6


@pytest.fixture(autouse=True, scope="module")
def _float64(x64):
    """Float64 available (``x64``: tests/conftest.py); each test names its arrays' dtype."""


@pytest.mark.parametrize("dtype", ["float64", "float32"])
@pytest.mark.parametrize("nd, Kd, L, nc, Kl", [(302, 8, 6, 1179, 12), (20, 16, 3, 40, 5)])
def test_the_kernel_chooses_xlas_contacts(nd, Kd, L, nc, Kl, dtype):
    """On random robots (the paper preset's sizes: the disk's 302 collision points and 8 slots,
    six legs of 1,179 points and 12; and a small one, 16 of 20), heights on a 0.25-mm grid so
    that predicted gaps tie (some within the contact distance), last step's points partly
    loaded, one leg absent (its points at ``FAR``, none chosen active), the interpreted kernel gives XLA's choice
    (``select_contacts``' all-bodies program) exactly: indices, activity, gaps and warm starts
    (the points kept from last step bring their impulses), the same arithmetic in the same order
    (of equal predicted gaps the lowest index first, as ``lax.top_k``)."""
    from softcrawl.jaxsim.candidates import robot_candidates
    from softcrawl.jaxsim.delassus import _selected_by_xla

    rng = np.random.default_rng(nd + L)
    grid = lambda *shape: np.round(rng.uniform(-0.5, 3.0, shape) * 4) / 4  # noqa: E731
    n = nd + 10
    collision = rng.permutation(n)[:nd]
    x, v = grid(n, 3), np.where(rng.random((n, 3)) < 0.5, 0.0, np.round(rng.normal(0, 20, (n, 3))))
    legs = np.stack([grid(L, nc), np.where(rng.random((L, nc)) < 0.5, 0.0, np.round(rng.normal(0, 20, (L, nc))))])
    translation, present = grid(L, 3), np.arange(L) != L - 2
    local = [rng.choice(nd, Kd, replace=False)] + [rng.choice(nc, Kl, replace=False) for _ in range(L)]
    offsets = [0] + [nd + nc * l for l in range(L)]
    points = np.concatenate([np.where(rng.random(p.size) < 0.7, p + o, -1) for p, o in zip(local, offsets)])
    impulses = rng.normal(0, 1, (points.size, 3))
    impulses[Kd + Kl * (L - 2):Kd + Kl * (L - 1)] = 0  # the absent leg bore none
    args = [jnp.asarray(a, dtype) for a in (x, v, legs, translation)]
    args = [jnp.asarray(collision), *args, jnp.asarray(present), jnp.asarray(points), jnp.asarray(impulses, dtype)]
    rule = dict(Kd=Kd, Kl=Kl, floor_z=0.0, distance=0.5, dt=0.02)
    got = robot_candidates(*args, far=FAR, interpret=True, **rule)
    want = _selected_by_xla(*args, **rule)
    for g, w in zip(got, want):  # the indices int32 (XLA's int64 with float64 on)
        assert g.dtype == w.dtype or g.dtype == jnp.int32
        np.testing.assert_array_equal(np.asarray(g), np.asarray(w))
    idx, active, warm = np.asarray(want[0]), np.asarray(want[1]), np.asarray(want[3])
    assert active.sum() > 0 and not active[Kd + Kl * (L - 2):Kd + Kl * (L - 1)].any()
    kept = np.isin(idx, points)
    assert not kept.all() and np.all(warm[~kept] == 0) and np.count_nonzero(warm[kept]) > 0
    if nc > Kl * 20:  # ties among a leg's choices
        assert len(set(legs[0, 0][idx[Kd:Kd + Kl] - nd])) < Kl


def test_a_robot_of_other_shapes_is_refused():
    from softcrawl.jaxsim.candidates import robot_candidates

    rule = dict(far=FAR, floor_z=0.0, distance=0.5, dt=0.02, interpret=True)
    coll, x, legs = jnp.arange(10), jnp.zeros((12, 3)), jnp.zeros((2, 2, 20))
    t, on = jnp.zeros((2, 3)), jnp.ones(2, bool)
    for Kd, Kl in ((11, 2), (2, 17)):
        K = Kd + 2 * Kl
        with pytest.raises(ValueError, match="slots a body"):
            robot_candidates(coll, x, x, legs, t, on, jnp.zeros(K, int), jnp.zeros((K, 3)), Kd=Kd, Kl=Kl, **rule)
    with pytest.raises(ValueError, match="points and"):
        robot_candidates(coll, x, x, legs, t, on, jnp.zeros(5, int), jnp.zeros((6, 3)), Kd=2, Kl=2, **rule)
