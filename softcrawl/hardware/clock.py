"""Clocks for the deploy loop: the real monotonic clock and a simulated one.

Both have ``now() -> s`` (monotonic, arbitrary origin) and ``sleep(s)``. The simulated clock
advances only when slept on or when a simulated instrument charges I/O time
(:meth:`SimClock.advance`), so a 20-s episode on the simulated rig runs in well under a second;
``jitter_s`` adds a random lateness (exponential, mean ``jitter_s``) to every sleep, like a
non-real-time OS does.
"""

from __future__ import annotations

import time

import numpy as np


class MonotonicClock:
    """``time.monotonic`` / ``time.sleep`` (never the wall clock: it can jump)."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)


class SimClock:
    """Simulated monotonic time, s.

    Args:
        jitter_s: mean extra lateness of each sleep, s (exponential distribution; 0 = none).
        seed: random seed of the jitter.
    """

    def __init__(self, jitter_s: float = 0.0, seed: int | None = 0) -> None:
        if not (np.isfinite(jitter_s) and jitter_s >= 0):
            raise ValueError(f"jitter_s must be finite and >= 0 s, got {jitter_s}")
        self.t = 0.0
        self.jitter_s = float(jitter_s)
        self._rng = np.random.default_rng(seed)
        self._listeners = []

    def now(self) -> float:
        return self.t

    def on_advance(self, fn) -> None:
        """Call ``fn(t_old, t_new)`` whenever time advances (the simulated plant integrates there)."""
        self._listeners.append(fn)

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` (>= 0) of simulated time pass."""
        if seconds < 0:
            raise ValueError(f"cannot go back in time ({seconds} s)")
        t0, self.t = self.t, self.t + float(seconds)
        for fn in self._listeners:
            fn(t0, self.t)

    def sleep(self, seconds: float) -> None:
        extra = self._rng.exponential(self.jitter_s) if self.jitter_s > 0 else 0.0
        self.advance(max(float(seconds), 0.0) + extra)
