"""Gibbs design distribution with an entropy-targeted temperature (``codesign.md``, "Design
distribution"; paper Sec. "Co-design").

Over a fixed list of designs (by default the 6,972 canonical designs of
:func:`softcrawl.design.space.canonical_designs`, in that order),

    p(omega) = exp(beta R_omega) / sum_omega' exp(beta R_omega'),

where ``R_omega`` is the most recent episode return of design ``omega`` (cm crawled per episode)
and ``beta >= 0`` (1/cm) is chosen at every update so that the entropy ``H(p)`` (nats) equals a
target ``H_T`` given by :class:`EntropySchedule`.

Corner cases, handled deliberately:

* **Never-tried designs.** The paper gives them ``R = 0``. When real returns are negative
  (crawling backwards is common early on) the thousands of untried designs then tie at the
  maximum and every entropy target below ``ln(#untried)`` is unreachable. The default
  ``untried="mean"`` scores an untried design with the mean of the tried designs' scores (0
  before anything is tried): neither favoured nor punished, and concentration onto good tried
  designs stays possible. ``"zero"`` reproduces the paper; ``"optimistic"`` (the maximum tried
  score) explores every design before concentrating, at the price of a high entropy floor while
  many are untried.
* **Ties at the maximum.** As ``beta -> inf`` the distribution tends to uniform over the
  ``m`` designs tied at the maximum score, so ``H >= ln m``; a lower target is clamped to
  ``ln m + floor_margin`` and the update reports ``clamped=True``.
* **Unreachable targets / beta bounds.** Targets ``>= ln n`` give ``beta = 0`` (uniform). The
  root of ``H(beta) - H_T`` is bracketed by doubling an upper bound from ``1 / std(R)`` up to
  ``beta_max``; if even ``beta_max`` leaves the entropy above the target, ``beta = beta_max``
  and ``reachable=False`` is reported. Inside the bracket :func:`scipy.optimize.brentq` finds
  the root (``H`` is continuous and non-increasing in ``beta``).
* **Numerics.** Log-probabilities use the log-sum-exp of ``beta (R - max R)``; the entropy is
  computed as ``-sum p log p`` from these log-probabilities (exact 0 contributions for p = 0).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.optimize import brentq

from softcrawl.design.space import DEFAULT_SPACE, Design
from softcrawl.design.spacefile import DesignSpace

UNTRIED_POLICIES = ("mean", "zero", "optimistic")


@dataclass(frozen=True)
class EntropySchedule:
    """Entropy target ``H_T(t)`` (nats) over environment steps ``t`` (codesign.md).

    ``H_T = h_max`` (uniform distribution, ``beta = 0``) for ``t <= t0``, then linear down to
    ``h_end`` at ``t1``, constant afterwards. Paper: ``t0 = 200K``, ``t1 = 950K`` of 1M steps.

    Attributes:
        t0, t1: environment steps (transitions), ``0 <= t0 <= t1``.
        h_max: entropy of the uniform distribution, nats (``ln n_designs``).
        h_end: final target, nats (``0 <= h_end <= h_max``).
    """

    t0: int
    t1: int
    h_max: float
    h_end: float = 0.0

    def __post_init__(self) -> None:
        if not (0 <= self.t0 <= self.t1):
            raise ValueError(f"EntropySchedule needs 0 <= t0 <= t1, got t0={self.t0}, t1={self.t1}")
        if not (math.isfinite(self.h_max) and 0 <= self.h_end <= self.h_max):
            raise ValueError(f"EntropySchedule needs 0 <= h_end <= h_max, got h_end={self.h_end}, h_max={self.h_max}")

    def target(self, t: float) -> float:
        """Target entropy (nats) at environment step ``t``."""
        if t <= self.t0:
            return self.h_max
        if t >= self.t1:
            return self.h_end
        f = (t - self.t0) / (self.t1 - self.t0)
        return self.h_max + f * (self.h_end - self.h_max)

    def uniform(self, t: float) -> bool:
        """Whether ``beta`` is forced to 0 at step ``t`` (before ``t0``)."""
        return t <= self.t0


@dataclass(frozen=True)
class BetaUpdate:
    """Outcome of :meth:`GibbsDesignDistribution.set_entropy_target`.

    Attributes:
        beta: chosen inverse temperature, 1/cm.
        entropy: entropy of the resulting distribution, nats.
        target: requested target, nats; effective_target: after clamping.
        floor: ``ln(#designs tied at the maximum score)``, the lowest reachable entropy, nats.
        clamped: the target was below the floor (raised to the floor + margin).
        reachable: False if ``beta_max`` was hit before the target was met.
    """

    beta: float
    entropy: float
    target: float
    effective_target: float
    floor: float
    clamped: bool
    reachable: bool


def log_softmax(z: np.ndarray) -> np.ndarray:
    """Numerically stable ``log(exp(z) / sum exp(z))`` of a 1-D array."""
    m = float(np.max(z))
    s = z - m
    return s - math.log(float(np.sum(np.exp(s))))


def gibbs_entropy(scores: np.ndarray, beta: float) -> float:
    """Entropy (nats) of ``p ∝ exp(beta * scores)``."""
    logp = log_softmax(beta * (scores - scores.max()))
    p = np.exp(logp)
    return float(-np.sum(p * logp))


class GibbsDesignDistribution:
    """Categorical distribution ``p ∝ exp(beta R)`` over a list of designs.

    Args:
        designs: the support, a sequence of design tuples (default: all 6,972 canonical designs
            in sorted order). Designs are stored canonicalised; duplicates are rejected.
        untried: score of never-tried designs: ``"mean"`` (default), ``"zero"`` (paper) or
            ``"optimistic"`` (see the module docstring).
        beta_max: upper bound on ``beta``, 1/cm.
        floor_margin: nats added to the tie floor ``ln m`` when a target is clamped (the
            floor itself needs ``beta = inf`` unless every design is tied).
        space: the design space whose canonical forms the designs take (default the paper's).

    Attributes:
        designs: tuple of the ``n`` designs; ``returns``: ``(n,)`` latest return of each, cm
            (NaN = never tried); ``beta``: current inverse temperature; ``last``: the last
            :class:`BetaUpdate` (None before the first).
    """

    def __init__(self, designs: Sequence[Sequence[int]] | None = None, untried: str = "mean",
                 beta_max: float = 1e6, floor_margin: float = 1e-3, space: DesignSpace = DEFAULT_SPACE):
        if untried not in UNTRIED_POLICIES:
            raise ValueError(f"untried must be one of {UNTRIED_POLICIES}, got {untried!r}")
        if not (math.isfinite(beta_max) and beta_max > 0):
            raise ValueError(f"beta_max must be positive and finite, got {beta_max}")
        if not (0 < floor_margin < 0.01):
            raise ValueError(f"floor_margin must be in (0, 0.01) nats, got {floor_margin}")
        self.space = space
        ds = space.canonical_designs if designs is None else tuple(space.canonicalize(d) for d in designs)
        if len(ds) == 0:
            raise ValueError("the design list is empty")
        if len(set(ds)) != len(ds):
            raise ValueError("the design list contains duplicates (after canonicalisation)")
        self.designs: tuple[Design, ...] = tuple(ds)
        self._index = {d: i for i, d in enumerate(self.designs)}
        self.untried, self.beta_max, self.floor_margin = untried, float(beta_max), float(floor_margin)
        self.returns = np.full(len(ds), np.nan)
        self.beta = 0.0
        self.last: BetaUpdate | None = None

    def __len__(self) -> int:
        return len(self.designs)

    @property
    def h_max(self) -> float:
        """Entropy of the uniform distribution, ``ln n`` nats."""
        return math.log(len(self.designs))

    def index(self, design: Sequence[int]) -> int:
        """Index of (the canonical form of) ``design``; ValueError if not in the support."""
        d = self.space.canonicalize(design)
        if d not in self._index:
            raise ValueError(f"design {d} is not in this distribution's support")
        return self._index[d]

    @property
    def tried(self) -> np.ndarray:
        """``(n,)`` bool: designs with at least one recorded return."""
        return ~np.isnan(self.returns)

    def scores(self) -> np.ndarray:
        """``(n,)`` scores used in the Gibbs weights: latest returns, untried ones filled in
        by the ``untried`` policy (cm)."""
        tried = self.tried
        if tried.all():
            return self.returns.copy()
        if not tried.any() or self.untried == "zero":
            fill = 0.0
        elif self.untried == "mean":
            fill = float(self.returns[tried].mean())
        else:  # optimistic
            fill = float(self.returns[tried].max())
        return np.where(tried, self.returns, fill)

    def record(self, designs: Sequence[Sequence[int]], returns: Sequence[float]) -> None:
        """Store episode returns (cm) of designs; for a design given twice the later wins
        ("most recent return"). Non-finite returns are rejected with ValueError."""
        designs = list(designs)
        r = np.asarray(returns, dtype=float).reshape(-1)
        if len(designs) != len(r):
            raise ValueError(f"{len(designs)} designs but {len(r)} returns")
        if not np.all(np.isfinite(r)):
            raise ValueError(f"returns must be finite, got {r}")
        for d, v in zip(designs, r):
            self.returns[self.index(d)] = v

    def log_probs(self, beta: float | None = None) -> np.ndarray:
        """``(n,)`` log-probabilities at ``beta`` (default: the current one)."""
        b = self.beta if beta is None else float(beta)
        s = self.scores()
        return log_softmax(b * (s - s.max()))

    def probs(self) -> np.ndarray:
        """``(n,)`` probabilities at the current ``beta`` (sum 1)."""
        return np.exp(self.log_probs())

    def entropy(self, beta: float | None = None) -> float:
        """Entropy (nats) at ``beta`` (default: the current one)."""
        logp = self.log_probs(beta)
        return float(-np.sum(np.exp(logp) * logp))

    def tie_floor(self) -> float:
        """``ln m``, ``m`` = number of designs tied at the maximum score: the infimum of H."""
        s = self.scores()
        m = int(np.sum(s >= s.max() - 1e-12 * max(1.0, abs(s.max()))))
        return math.log(m)

    def set_entropy_target(self, target: float, uniform: bool = False) -> BetaUpdate:
        """Choose ``beta`` so that ``H(p) = target`` (nats), within ~1e-6 nats when reachable.

        Args:
            target: entropy target, nats (>= 0).
            uniform: force ``beta = 0`` (schedule before ``t0``).

        Returns:
            The :class:`BetaUpdate` (also stored in ``last``).

        Raises:
            ValueError: a negative or non-finite target.
        """
        if not (math.isfinite(target) and target >= 0):
            raise ValueError(f"entropy target must be finite and >= 0 nats, got {target}")
        s = self.scores()
        s = s - s.max()
        floor = self.tie_floor()
        h_max = self.h_max
        clamped, reachable = False, True
        eff = float(target)
        if uniform or eff >= h_max - 1e-12 or floor >= h_max - 1e-12:
            beta = 0.0
        else:
            if eff < floor + self.floor_margin:
                eff, clamped = floor + self.floor_margin, True
                eff = min(h_max, eff)
            f = lambda b: gibbs_entropy(s, b) - eff
            std = float(np.std(s))
            hi = min(1.0 / std if std > 0 else 1.0, self.beta_max)
            lo = 0.0
            while f(hi) > 0 and hi < self.beta_max:
                lo, hi = hi, min(2.0 * hi, self.beta_max)
            if f(hi) > 0:
                beta, reachable = self.beta_max, False
            else:
                beta = brentq(f, lo, hi, xtol=1e-14, rtol=1e-12, maxiter=500)
        self.beta = float(beta)
        self.last = BetaUpdate(beta=self.beta, entropy=self.entropy(), target=float(target), effective_target=eff,
                               floor=floor, clamped=clamped, reachable=reachable)
        return self.last

    def sample(self, rng: np.random.Generator, n: int) -> list[Design]:
        """``n`` designs drawn i.i.d. from ``p`` with ``rng``."""
        if n < 0:
            raise ValueError(f"n must be >= 0, got {n}")
        idx = rng.choice(len(self.designs), size=n, p=self.probs())
        return [self.designs[i] for i in idx]

    def top(self, k: int = 10) -> list[tuple[Design, float, float]]:
        """The ``k`` most probable designs as ``(design, probability, latest return cm or NaN)``."""
        p = self.probs()
        order = np.lexsort((np.arange(len(p)), -p))[:k]
        return [(self.designs[i], float(p[i]), float(self.returns[i])) for i in order]

    def state_dict(self) -> dict:
        """Picklable state (support, returns, beta, settings)."""
        return {"designs": self.designs, "returns": self.returns.copy(), "beta": self.beta,
                "untried": self.untried, "beta_max": self.beta_max, "floor_margin": self.floor_margin,
                "last": self.last}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output; ValueError if the support differs."""
        if tuple(map(tuple, state["designs"])) != self.designs:
            raise ValueError("saved design distribution has a different design list")
        self.returns = np.array(state["returns"], dtype=float)
        self.beta = float(state["beta"])
        self.untried, self.beta_max = state["untried"], float(state["beta_max"])
        self.floor_margin, self.last = float(state["floor_margin"]), state["last"]
