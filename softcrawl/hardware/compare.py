"""Simulation vs reality over an episode, like the paper's figures.

Inputs: a simulation output folder (``softcrawl simulate`` / ``softcrawl evaluate``:
``trajectory.csv`` with ``t, x, cmd_1..3, applied_1..3``) and one or more real logs: a
``softcrawl deploy`` folder (``log.csv`` + ``summary.json``) or a recorded AuRo 2023 trial
(``logs-*.csv``, :func:`softcrawl.hardware.logs.read_auro_log`). Optionally one tracked-position
CSV per real log (header ``t_s,x_mm``: the disk's position along the crawl direction, e.g. from
a tracker) or a video with an ArUco marker on the disk (:mod:`softcrawl.hardware.aruco`).

Outputs (:func:`compare`): ``pressures.png`` (per regulator: commanded, simulated-applied and
sensed pressures), ``distance.png`` (x(t) of the simulation and of each tracked trial),
``compare.md`` (a Markdown summary: per log, RMS of sensed - simulated pressure per regulator,
final distances with their mean, standard deviation and range) and ``compare.json``.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from softcrawl.hardware.errors import one_line
from softcrawl.hardware.logs import read_auro_log, read_deploy_log
from softcrawl.safeio import atomic_write_text, read_text


@dataclass(frozen=True, eq=False)
class RealRun:
    """One real trial in common form: ``t_s (m,)``, ``commanded_kpa``, ``sensed_kpa`` ``(m, 3)``
    (NaN where not measured), ``name``, ``kind`` (``"deploy"`` or ``"auro2023"``), ``info``."""

    name: str
    kind: str
    t_s: np.ndarray
    commanded_kpa: np.ndarray
    sensed_kpa: np.ndarray
    info: dict


def read_real(path: str | Path) -> RealRun:
    """A deploy folder or a recorded ``logs-*.csv`` as :class:`RealRun`.

    Raises:
        FileNotFoundError; ValueError: malformed log.
    """
    path = Path(path)
    if path.is_dir():
        log = read_deploy_log(path)
        keep = log.step >= 0
        s = log.summary
        return RealRun(path.name, "deploy", log.t_s[keep], log.commanded_kpa[keep], log.sensed_kpa[keep],
                       {"status": s.get("status"), "reason": s.get("reason"), "samples": s.get("samples"),
                        "sample_hz": s.get("sample_hz_achieved"), "overruns": s.get("overruns"),
                        "simulated_rig": s.get("simulated"), "sim_hold_s": s.get("sim_hold_s"),
                        "control_period_s": s.get("control_period_s")})
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such log")
    tr = read_auro_log(path)
    # sensed at step k is the end of hold k-1: put it at t[k], with the command held since t[k-1]
    return RealRun(path.stem, "auro2023", tr.t_s, tr.commanded_kpa, tr.sensed_kpa,
                   {"status": "recorded", "steps": tr.n_steps, "mean_hold_s": float(tr.hold_s.mean())})


def read_sim(folder: str | Path) -> dict:
    """``{"t", "x", "cmd" (n, 3), "applied" (n, 3)}`` from a simulation output folder's trajectory.csv."""
    p = Path(folder) / "trajectory.csv"
    if not p.exists():
        raise FileNotFoundError(f"{p}: not found (SIM_RUN must be a `softcrawl simulate`/`evaluate` output folder)")
    rows = list(csv.DictReader(read_text(p).splitlines()))
    try:
        col = lambda n: np.array([float(r[n]) for r in rows])  # noqa: E731
        sim = {"t": col("t"), "x": col("x"), "cmd": np.stack([col(f"cmd_{k}") for k in (1, 2, 3)], 1),
               "applied": np.stack([col(f"applied_{k}") for k in (1, 2, 3)], 1)}
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{p}: not a softcrawl trajectory ({one_line(exc)[:200]})") from None
    if not rows or not all(np.isfinite(v).all() for v in sim.values()):
        raise ValueError(f"{p}: a trajectory needs at least one row of finite numbers")
    return sim


def read_tracked(path: str | Path, marker_id: int = 0, marker_mm: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s, x_mm)`` from a tracked-position CSV (header ``t_s,x_mm``; extra columns ignored) or
    a video with one ArUco marker on the disk (:func:`softcrawl.hardware.aruco.track_video`).

    Raises:
        FileNotFoundError; ValueError: bad header, non-numeric rows, < 2 samples, time not increasing.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such tracked file")
    from softcrawl.hardware.aruco import VIDEO_SUFFIXES

    if path.suffix.lower() in VIDEO_SUFFIXES:
        from softcrawl.hardware.aruco import track_video

        return track_video(path, marker_id, marker_mm)
    r = csv.DictReader(read_text(path).splitlines())
    if not r.fieldnames or "t_s" not in r.fieldnames or "x_mm" not in r.fieldnames:
        raise ValueError(f"{path}: header must contain t_s and x_mm, got {str(r.fieldnames)[:200]}")
    try:
        a = np.array([[float(row["t_s"]), float(row["x_mm"])] for row in r])
    except (ValueError, TypeError):
        raise ValueError(f"{path}, line {r.line_num}: non-numeric t_s / x_mm") from None
    if len(a) < 2 or not np.isfinite(a).all() or np.any(np.diff(a[:, 0]) <= 0):
        raise ValueError(f"{path}: need >= 2 finite samples with increasing t_s")
    return a[:, 0], a[:, 1]


def _rms(a) -> float | None:
    a = np.asarray(a, float)
    a = a[np.isfinite(a)]
    return float(np.sqrt(np.mean(a ** 2))) if a.size else None


def compare(sim_run: str | Path, real_logs, out: str | Path, tracked=None, time_scale: float | None = None,
            marker_id: int = 0, marker_mm: float = 30.0) -> dict:
    """Write the comparison (module docstring) into ``out``; returns the ``compare.json`` dict.

    Args:
        tracked: None or one tracked CSV or video per real log (same order; ``None`` entries allowed).
        marker_id, marker_mm: videos: the disk marker's ArUco id and side length, mm.
        time_scale: multiply simulated time by this (real s per sim s). Default: 1, or, when a
            deploy log ran a policy whose simulated action hold ``sim_hold_s`` differs from the
            rig's ``control_period_s``, their ratio (so action k lines up with action k).

    Raises:
        ValueError: no real logs, or a tracked list of the wrong length; errors of the readers.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    real_logs = list(real_logs)
    if not real_logs:
        raise ValueError("need at least one real log")
    tracked = list(tracked) if tracked else [None] * len(real_logs)
    if len(tracked) != len(real_logs):
        raise ValueError(f"got {len(tracked)} tracked files for {len(real_logs)} real logs (give one per log)")
    sim = read_sim(sim_run)
    runs = [read_real(p) for p in real_logs]
    if time_scale is None:
        time_scale = 1.0
        for r in runs:
            h, period = r.info.get("sim_hold_s"), r.info.get("control_period_s")
            if h and period and abs(h - period) > 1e-9:
                time_scale = period / h
                break
    if not (math.isfinite(time_scale) and time_scale > 0):
        raise ValueError(f"time scale must be finite and > 0, got {time_scale}")
    sim["t"] = sim["t"] * time_scale
    tracks = [read_tracked(p, marker_id, marker_mm) if p else None for p in tracked]
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)

    # pressures
    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    rows = []
    for k, ax in enumerate(axes):
        ax.step(sim["t"], sim["cmd"][:, k], where="pre", color="k", ls="--", lw=1, label="commanded (sim)")
        ax.plot(sim["t"], sim["applied"][:, k], color="k", lw=1.5, label="simulated applied")
        for j, r in enumerate(runs):
            ax.plot(r.t_s, r.sensed_kpa[:, k], ".-" if r.kind == "auro2023" else "-", ms=3, lw=0.8,
                    color=f"C{j}", label=f"sensed: {r.name}")
        ax.set_ylabel(f"regulator {k + 1} (kPa)")
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7, ncol=2)
    axes[-1].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(out / "pressures.png", dpi=110)
    plt.close(fig)
    for r in runs:
        sim_at = np.stack([np.interp(r.t_s, sim["t"], sim["applied"][:, k]) for k in range(3)], 1)
        # zero-order hold: the sim row at time t carries the command applied during (t - dt, t], so a
        # command sent at real time t is the one of the first sim row after t
        i = np.clip(np.searchsorted(sim["t"], r.t_s, side="right"), 0, len(sim["t"]) - 1)
        cmd_at = sim["cmd"][i]
        rows.append({
            "log": r.name, "kind": r.kind, **r.info,
            "rms_sensed_minus_sim_kpa": [_rms(r.sensed_kpa[:, k] - sim_at[:, k]) for k in range(3)],
            "rms_sensed_minus_commanded_kpa": [_rms(r.sensed_kpa[:, k] - r.commanded_kpa[:, k]) for k in range(3)],
            "max_command_mismatch_kpa": float(np.nanmax(np.abs(r.commanded_kpa - cmd_at))),
        })

    # distances
    sim_final_cm = float(sim["x"][-1] - sim["x"][0]) / 10.0
    finals = []
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.plot(sim["t"], (sim["x"] - sim["x"][0]) / 10.0, "k", lw=2, label="simulation")
    for j, (r, tr) in enumerate(zip(runs, tracks)):
        if tr is None:
            continue
        t, x = tr
        ax.plot(t - t[0], (x - x[0]) / 10.0, color=f"C{j}", label=r.name)
        finals.append(float(x[-1] - x[0]) / 10.0)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("distance along +x (cm)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out / "distance.png", dpi=110)
    plt.close(fig)
    spread = None
    if finals:
        f = np.array(finals)
        spread = {"n": int(f.size), "mean_cm": float(f.mean()), "std_cm": float(f.std(ddof=1)) if f.size > 1 else 0.0,
                  "min_cm": float(f.min()), "max_cm": float(f.max()),
                  "real_over_sim": float(f.mean() / sim_final_cm) if sim_final_cm != 0 else None}
    result = {"sim_run": str(sim_run), "sim_final_distance_cm": sim_final_cm, "sim_time_scale": time_scale,
              "logs": rows,
              "real_final_distances_cm": finals, "spread": spread}
    atomic_write_text(out / "compare.json", json.dumps(result, indent=2, default=str) + "\n")
    atomic_write_text(out / "compare.md", markdown(result))
    return result


def _f(v, fmt=".1f") -> str:
    return "-" if v is None or (isinstance(v, float) and not math.isfinite(v)) else format(v, fmt)


def markdown(r: dict) -> str:
    """The Markdown summary of a :func:`compare` result."""
    lines = [f"# Simulation vs real: `{r['sim_run']}`", "",
             f"Simulated final distance: **{r['sim_final_distance_cm']:+.2f} cm**.", ""]
    if r.get("sim_time_scale", 1.0) != 1.0:
        lines += [f"Simulated time is stretched by {r['sim_time_scale']:g} so that its actions line up with the "
                  "rig's control period (the policy was trained with a different action hold).", ""]
    lines += [
             "## Pressures", "",
             "RMS of sensed - simulated-applied pressure per regulator (kPa), and of sensed - commanded.", "",
             "| log | kind | status | RMS sensed-sim 1 / 2 / 3 | RMS sensed-cmd 1 / 2 / 3 | gait mismatch (kPa) |",
             "|---|---|---|---|---|---|"]
    for row in r["logs"]:
        a = " / ".join(_f(v) for v in row["rms_sensed_minus_sim_kpa"])
        b = " / ".join(_f(v) for v in row["rms_sensed_minus_commanded_kpa"])
        lines.append(f"| {row['log']} | {row['kind']} | {row.get('status')} | {a} | {b} | "
                     f"{_f(row['max_command_mismatch_kpa'])} |")
    if any(row["max_command_mismatch_kpa"] > 1.0 for row in r["logs"]):
        lines += ["", "A gait mismatch above 1 kPa means the real log did not run the simulated gait."]
    lines += ["", "![pressures](pressures.png)", "", "## Distance", ""]
    sp = r["spread"]
    if sp:
        lines += [f"Real final distances ({sp['n']} trials): " + ", ".join(f"{d:+.2f}" for d in
                                                                          r["real_final_distances_cm"]) + " cm; "
                  f"mean {sp['mean_cm']:+.2f} cm, std {sp['std_cm']:.2f} cm, range [{sp['min_cm']:+.2f}, "
                  f"{sp['max_cm']:+.2f}] cm; real / sim = {_f(sp['real_over_sim'], '.2f')}.", ""]
    else:
        lines += ["No tracked positions were given (`--tracked`), so only the simulated distance is shown.", ""]
    lines += ["![distance](distance.png)", ""]
    return "\n".join(lines)
