"""Errors raised by the rig code. Every one of them, raised during a deploy, vents all lines to
0 kPa and turns the supply outputs off (:mod:`softcrawl.hardware.deploy`)."""

from __future__ import annotations


class RigError(RuntimeError):
    """Base class of rig faults."""


class SupplyError(RigError):
    """The supply did not answer, answered garbage, or did not take a setting after the
    retries (a lost or broken connection)."""


class SensorError(RigError):
    """A pressure sensor did not answer or reported a fault (status bits, out-of-range counts)."""


class RigConfigError(ValueError):
    """A rig configuration file is missing, malformed or unsafe (message: one line, names the file)."""


class VoltageLimitError(ValueError):
    """A voltage outside a channel's limit was about to be sent; nothing was sent."""


class SafetyTrip(RigError):
    """The deploy loop stopped the rig on purpose (watchdog, sensor/command disagreement)."""


def one_line(exc: BaseException) -> str:
    """``exc``'s message on one line (drivers' messages span lines; ours must not)."""
    return " ".join(str(exc).split()) or type(exc).__name__
