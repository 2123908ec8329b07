"""Gibbs design distribution, entropy schedule and design sampler (softcrawl.codesign)."""

import math
import pickle

import numpy as np
import pytest

from softcrawl.codesign import (
    EntropySchedule,
    GibbsDesignDistribution,
    GibbsDesignSampler,
    gibbs_entropy,
)
from softcrawl.design.space import PAPER_BEST_DESIGN, canonical_designs

N = 6972


@pytest.fixture(scope="module")
def scored():
    """All designs tried, with distinct random scores (cm), one clear best."""
    rng = np.random.default_rng(0)
    d = GibbsDesignDistribution()
    r = rng.normal(0.0, 2.0, N)
    r[123] = 15.0
    d.record(d.designs, r)
    return d


def test_uniform_at_beta_zero():
    d = GibbsDesignDistribution()
    assert len(d) == N and d.designs == canonical_designs()
    up = d.set_entropy_target(d.h_max)
    assert up.beta == 0.0
    np.testing.assert_allclose(d.probs(), 1.0 / N, rtol=1e-12)
    assert abs(d.entropy() - math.log(6972)) < 1e-9
    # uniform also with returns recorded, when beta is forced to 0
    d.record([PAPER_BEST_DESIGN], [10.0])
    d.set_entropy_target(1.0, uniform=True)
    np.testing.assert_allclose(d.probs(), 1.0 / N, rtol=1e-12)


def test_entropy_meets_target_after_every_update(scored):
    d = GibbsDesignDistribution()
    d.load_state_dict(scored.state_dict())
    for target in np.linspace(d.h_max, 0.0, 40):
        up = d.set_entropy_target(float(target))
        assert up.beta >= 0
        if not up.clamped:
            assert abs(d.entropy() - target) < 0.01, (target, d.entropy())
        else:  # only the unique-max floor (ln 1 = 0) can clamp here
            assert target < 1e-3 and d.entropy() < 0.01
        assert abs(up.entropy - d.entropy()) < 1e-12


def test_monotone_concentration_on_best(scored):
    d = GibbsDesignDistribution()
    d.load_state_dict(scored.state_dict())
    p_best, betas = [], []
    for target in np.linspace(d.h_max, 0.0, 25):
        d.set_entropy_target(float(target))
        p = d.probs()
        assert d.beta == 0 or int(np.argmax(p)) == 123
        p_best.append(p[123])
        betas.append(d.beta)
    assert np.all(np.diff(p_best) >= -1e-12) and np.all(np.diff(betas) >= 0)
    assert p_best[0] == pytest.approx(1 / N) and p_best[-1] > 0.99


def test_untried_designs_mean_policy_keeps_low_targets_reachable():
    # Real returns negative: with the paper's R=0 for untried designs, the 6,962 untried ones tie at
    # the max and the floor is ln(6962); with "mean" the best tried design can take over.
    tried = list(canonical_designs()[:10])
    returns = np.linspace(-5.0, -1.0, 10)
    zero = GibbsDesignDistribution(untried="zero")
    zero.record(tried, returns)
    up = zero.set_entropy_target(1.0)
    assert up.clamped and up.floor == pytest.approx(math.log(N - 10))
    assert zero.entropy() >= math.log(N - 10) - 1e-9
    mean = GibbsDesignDistribution(untried="mean")
    mean.record(tried, returns)
    s = mean.scores()
    assert np.all(s[10:] == pytest.approx(returns.mean()))
    up = mean.set_entropy_target(1.0)
    assert not up.clamped and abs(mean.entropy() - 1.0) < 0.01
    # the best tried design is the most likely one
    assert int(np.argmax(mean.probs())) == 9
    opt = GibbsDesignDistribution(untried="optimistic")
    opt.record(tried, returns)
    assert np.all(opt.scores()[10:] == -1.0)
    # before anything is tried, every policy scores 0 and p is uniform at any target
    fresh = GibbsDesignDistribution()
    fresh.set_entropy_target(0.5)
    assert fresh.beta == 0.0 and abs(fresh.entropy() - fresh.h_max) < 1e-9


def test_ties_at_max_clamp_to_floor():
    d = GibbsDesignDistribution()
    r = np.zeros(N)
    r[:5] = 3.0  # five designs tied at the top
    d.record(d.designs, r)
    up = d.set_entropy_target(0.2)
    assert up.clamped and up.floor == pytest.approx(math.log(5))
    assert abs(d.entropy() - math.log(5)) < 0.01 and up.reachable
    np.testing.assert_allclose(d.probs()[:5], 0.2, atol=1e-3)


def test_unreachable_target_hits_beta_max():
    d = GibbsDesignDistribution(beta_max=1e-3)
    r = np.zeros(N)
    r[0] = 1.0
    d.record(d.designs, r)
    up = d.set_entropy_target(1.0)
    assert not up.reachable and d.beta == 1e-3 and d.entropy() > 1.0


def test_large_scores_are_stable():
    d = GibbsDesignDistribution(beta_max=1e12)
    r = np.linspace(0, 1e6, N)
    d.record(d.designs, r)
    for t in (8.0, 2.0, 0.1):
        d.set_entropy_target(t)
        assert np.all(np.isfinite(d.probs())) and abs(d.entropy() - t) < 0.01
    assert gibbs_entropy(np.array([0.0, 0.0]), 1e300) == pytest.approx(math.log(2))


def test_bad_input():
    with pytest.raises(ValueError):
        GibbsDesignDistribution(untried="pessimistic")
    d = GibbsDesignDistribution()
    with pytest.raises(ValueError):
        d.set_entropy_target(-1.0)
    with pytest.raises(ValueError):
        d.record([PAPER_BEST_DESIGN], [float("nan")])
    with pytest.raises(ValueError):
        d.record([PAPER_BEST_DESIGN], [1.0, 2.0])
    small = GibbsDesignDistribution(designs=[(1, 1, 1, 0, 0, 0, 0, 0), (1, 2, 3, 0, 0, 0, 0, 0)])
    with pytest.raises(ValueError):
        small.index((1, 1, 1, 1, 0, 0, 0, 0))
    with pytest.raises(ValueError):
        GibbsDesignDistribution(designs=[(1, 1, 1, 0, 0, 0, 0, 0), (2, 2, 2, 0, 0, 0, 0, 0)])
    with pytest.raises(ValueError):
        EntropySchedule(t0=10, t1=5, h_max=1.0)


def test_schedule():
    s = EntropySchedule(t0=200_000, t1=950_000, h_max=math.log(N))
    assert s.target(0) == s.target(200_000) == math.log(N) and s.uniform(100)
    assert s.target(575_000) == pytest.approx(math.log(N) / 2)
    assert s.target(950_000) == 0.0 == s.target(10**7) and not s.uniform(200_001)


def test_sampler_state_roundtrip_and_divergence():
    sched = EntropySchedule(t0=0, t1=100, h_max=math.log(N))
    a = GibbsDesignSampler(GibbsDesignDistribution(), sched, seed=3)
    ds = a.sample(50)
    a.observe(ds, np.arange(50.0), [False] * 49 + [True], timestep=60)
    assert a.distribution.returns[a.distribution.index(ds[-1])] <= 0.0  # diverged: min(r, 0)
    assert abs(a.distribution.entropy() - sched.target(60)) < 0.01
    state = pickle.loads(pickle.dumps(a.state_dict()))
    b = GibbsDesignSampler(GibbsDesignDistribution(), sched, seed=99)
    b.load_state_dict(state)
    assert b.distribution.beta == a.distribution.beta and b.timestep == 60
    np.testing.assert_array_equal(b.distribution.returns, a.distribution.returns)
    assert b.sample(20) == a.sample(20)
