"""First-order model of an electronic pressure regulator (Enfield TR-010-gs) and its fit to
recorded real runs.

Model (per regulator, continuous time, exact for piecewise-constant commands)::

    target = gain * command + offset                          (kPa)
    dp/dt  = (target - p) / tau,  tau = tau_inflate if target > p else tau_vent

so over a hold of ``T`` s: ``p <- target + (p - target) * exp(-T / tau)``. Venting through
the regulator's exhaust is slower than filling from the 400 kPa supply (the recorded data
agree: a 1-s vent leaves > 6 kPa in a quarter of the holds, issue #19).

:func:`fit_regulators` fits ``gain, offset, tau_inflate, tau_vent`` of each regulator to
recorded trials (:class:`softcrawl.hardware.logs.RecordedTrial`) by robust (Huber) least
squares on the one-step-ahead prediction of the sensor reading at the end of each hold,
starting from the sensed pressure at the start of the hold. Channels whose sensor does not
follow its command (command std >= 5 kPa but correlation with the next reading < 0.5, e.g.
an unplugged sensor) are left out and counted.

Defaults of :data:`FITTED` are the result of ``fit_regulators`` on the recorded AuRo 2023
logs, 3 of every 4 complete files (sorted by path) for fitting; ``tests/test_hardware_fit.py``
re-fits them and checks the error on the held-out quarter.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class RegulatorParams:
    """One regulator: ``target = gain * command + offset`` kPa; lags ``tau_inflate``,
    ``tau_vent`` s (> 0)."""

    gain: float = 1.0
    offset: float = 0.0
    tau_inflate: float = 0.2
    tau_vent: float = 0.4

    def __post_init__(self) -> None:
        vals = (self.gain, self.offset, self.tau_inflate, self.tau_vent)
        if not all(math.isfinite(v) for v in vals) or self.tau_inflate <= 0 or self.tau_vent <= 0:
            raise ValueError(f"regulator parameters must be finite with lags > 0 s: {self}")

    def target(self, command_kpa: float) -> float:
        """Steady-state pressure (kPa) for a command (kPa); 0 kPa command vents to 0 (clamped >= 0)."""
        return max(self.gain * command_kpa + self.offset, 0.0) if command_kpa > 0 else 0.0

    def advance(self, p_kpa: float, command_kpa: float, dt: float) -> float:
        """Pressure after holding ``command_kpa`` for ``dt`` s from ``p_kpa`` (all kPa)."""
        y = self.target(command_kpa)
        tau = self.tau_inflate if y > p_kpa else self.tau_vent
        return y + (p_kpa - y) * math.exp(-dt / tau)


def _predict(theta, c, s0, T):
    """One-step-ahead predictions of the fit (vectorised over holds; no clamping: the fit sees raw data)."""
    g, o, ti, to = theta
    y = g * c + o
    tau = np.where(y > s0, ti, to)
    return y + (s0 - y) * np.exp(-T / tau)


def usable_channels(trial, min_cmd_std: float = 5.0, min_corr: float = 0.5) -> list[int]:
    """Regulators of ``trial`` whose sensor follows the command (see module docstring);
    channels with a near-constant command (std < ``min_cmd_std``) are kept."""
    out = []
    for ch in range(3):
        c, s = trial.commanded_kpa[:-1, ch], trial.sensed_kpa[1:, ch]
        if np.std(c) < min_cmd_std:
            out.append(ch)
        elif np.std(s) > 1e-9 and np.corrcoef(c, s)[0, 1] >= min_corr:
            out.append(ch)
    return out


def holds(trials, ch: int):
    """``(command, sensed_start, hold_s, sensed_end)`` arrays over all usable holds of regulator ``ch``."""
    c, s0, T, s1 = [], [], [], []
    for tr in trials:
        if ch not in usable_channels(tr):
            continue
        c.append(tr.commanded_kpa[:-1, ch])
        s0.append(tr.sensed_kpa[:-1, ch])
        T.append(tr.hold_s)
        s1.append(tr.sensed_kpa[1:, ch])
    if not c:
        raise ValueError(f"no usable holds for regulator {ch + 1}")
    return tuple(np.concatenate(a) for a in (c, s0, T, s1))


def fit_regulators(trials) -> tuple[RegulatorParams, ...]:
    """Fit each regulator's :class:`RegulatorParams` to recorded trials (module docstring).

    Raises:
        ValueError: a regulator has no usable holds.
    """
    from scipy.optimize import least_squares

    out = []
    for ch in range(3):
        c, s0, T, s1 = holds(trials, ch)
        res = least_squares(lambda th: _predict(th, c, s0, T) - s1, [1.0, 0.0, 0.3, 0.5], loss="huber", f_scale=5.0,
                            bounds=([0.3, -30.0, 0.01, 0.01], [1.5, 30.0, 5.0, 5.0]))
        g, o, ti, to = (float(v) for v in res.x)
        out.append(RegulatorParams(g, o, ti, to))
    return tuple(out)


def prediction_errors(params, trials) -> dict:
    """One-step-ahead errors (kPa) of ``params`` (3 :class:`RegulatorParams`) on ``trials``:
    ``{"rmse", "mae", "median_abs", "p90_abs", "n_holds"}`` overall and per regulator (``"per_regulator"``)."""
    errs = []
    for ch, p in enumerate(params):
        c, s0, T, s1 = holds(trials, ch)
        errs.append(_predict((p.gain, p.offset, p.tau_inflate, p.tau_vent), c, s0, T) - s1)

    def stats(e):
        a = np.abs(e)
        return {"rmse": float(np.sqrt(np.mean(e ** 2))), "mae": float(a.mean()), "median_abs": float(np.median(a)),
                "p90_abs": float(np.percentile(a, 90)), "n_holds": int(e.size)}

    d = stats(np.concatenate(errs))
    d["per_regulator"] = [stats(e) for e in errs]
    return d


def split_trials(trials, every: int = 4):
    """``(fit, held_out)``: every ``every``-th trial (sorted by path, index ``every - 1`` mod ``every``) is held out."""
    if int(every) < 2:
        raise ValueError(f"hold out every k-th log needs k >= 2, got {every}")
    trials = sorted(trials, key=lambda t: t.path)
    return ([t for i, t in enumerate(trials) if i % every != every - 1],
            [t for i, t in enumerate(trials) if i % every == every - 1])


def params_to_dict(params) -> list[dict]:
    return [asdict(p) for p in params]


#: :func:`fit_regulators` on the recorded AuRo 2023 logs (273 complete files; fit on the 205 of
#: :func:`split_trials`, 68 held out). Held-out one-step error of the sensed pressure at the end
#: of a hold: RMSE 12.3 kPa, MAE 8.7 kPa, median 5.9 kPa over 3,819 holds (the naive "sensor =
#: command" model: RMSE 13.6, MAE 10.0, median 7.3). Regulator 1, 2, 3.
FITTED: tuple[RegulatorParams, ...] = (
    RegulatorParams(gain=1.0873, offset=-5.892, tau_inflate=0.390, tau_vent=0.691),
    RegulatorParams(gain=0.9473, offset=-4.929, tau_inflate=0.0267, tau_vent=0.596),
    RegulatorParams(gain=1.2284, offset=-2.516, tau_inflate=0.598, tau_vent=0.264),
)
