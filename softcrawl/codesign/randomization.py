"""Domain randomization in co-design runs: the per-episode log of a training
run's draws and the robust evaluation of a design (``softcrawl evaluate --randomize N``).

The ranges are ``env.randomize`` of the run's :class:`~softcrawl.codesign.config.TrainConfig`
(:class:`softcrawl.robot.domain.DomainRanges`); each episode's draw is in its env's
``info["domain"]``.

``RUN/domain.csv`` (only in runs that randomize; ``episodes.csv`` keeps its format): a header
row, then one row per finished episode: ``t`` (transitions, as in ``episodes.csv``), ``design``,
``return_<unit>`` (the task's unit: ``return_cm``, ``return_deg`` for ``turning``),
``diverged`` and the drawn values (:meth:`DomainRanges.columns` for the space's ``R``
regulators: ``friction``, ``youngs_scale``, ``mass_scale``, ``pressure_gain_1..R``,
``pressure_offset_1..R_kpa``, ``tau_inflate_1..R_s``, ``tau_vent_1..R_s``, ``control_period``,
those randomized). A resumed run drops the rows after its checkpoint, as it does in
``episodes.csv``.

``softcrawl evaluate RUN --design D --randomize N --out OUT`` writes into ``OUT``:

- ``randomization.json``: run, checkpoint, design, task and unit, ranges, seed, the nominal
  return (the same policy without randomization), the N returns, their mean / std (population)
  / min / max / quartiles, divergences, and every episode's draw; return keys end in the task's
  unit (``nominal_return_cm``, ``returns_cm``, ``mean_cm``, ...; ``_deg`` for ``turning``);
- ``randomization.csv``: one row per episode (``episode``, ``return_<unit>``, ``diverged`` and the
  drawn values, columns as in ``domain.csv``);
- ``randomization.png``: the histogram of the returns with the nominal return marked.
"""

from __future__ import annotations

import csv
import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from softcrawl.codesign.config import check_randomize
from softcrawl.robot.domain import PAPER_REGULATORS, DomainRanges, DomainSample

#: Columns of ``domain.csv`` before the drawn values (a forward run's; ``return_<unit>`` in the task's unit).
DOMAIN_LOG_COLUMNS = ("t", "design", "return_cm", "diverged")


def log_columns(unit: str = "cm") -> tuple[str, ...]:
    """:data:`DOMAIN_LOG_COLUMNS` with the return in ``unit`` (the task's: ``"cm"``, ``"deg"``)."""
    return ("t", "design", f"return_{unit}", "diverged")


def _design_str(d) -> str:
    return "".join(map(str, d)) if d is not None else ""


def _flat(domain: dict) -> dict:
    """``info["domain"]`` (:meth:`DomainSample.as_dict`) as CSV columns."""
    return DomainSample(**domain).columns()


class DomainLog:
    """Writer of ``RUN/domain.csv`` (module docstring); does nothing for a run without
    randomization (then its methods are no-ops).

    Args:
        path: the CSV file (a run's :attr:`softcrawl.codesign.run.Run.domain_csv`). ranges: the run's ranges (their columns). after: transitions done
            (a resumed run: rows with a larger ``t`` are dropped; 0 for a new run).
        unit: the task's unit (the return's column). n_regulators: the space's regulators
            (the per-regulator columns).

    Raises:
        ValueError: an existing file whose header is not this run's columns.
    """

    def __init__(self, path: str | os.PathLike | None, ranges: DomainRanges | None, after: int = 0,
                 unit: str = "cm", n_regulators: int = PAPER_REGULATORS):
        self.path = None if path is None or ranges is None or not ranges.enabled else Path(path)
        self._file = self._writer = None
        if self.path is None:
            return
        self.columns = (*log_columns(unit), *ranges.columns(n_regulators))
        rows = []
        if self.path.exists() and self.path.stat().st_size > 0:
            with open(self.path, newline="", encoding="utf-8") as f:
                reader = csv.reader(f)
                header = tuple(next(reader, ()))
                if header != self.columns:
                    raise ValueError(f"{self.path}: its columns {list(header)} are not this run's {list(self.columns)}")
                rows = [r for r in reader if r and int(r[0]) <= after]
        tmp = self.path.with_suffix(".tmp")
        with open(tmp, "w", newline="", encoding="utf-8") as f:
            csv.writer(f).writerows([self.columns, *rows])
        os.replace(tmp, self.path)
        self._file = open(self.path, "a", newline="", encoding="utf-8")  # noqa: SIM115 - closed by close()
        self._writer = csv.writer(self._file)

    def write(self, t: int, info: dict) -> None:
        """One finished episode: ``info`` is the vec env's final step info (``"episode"``,
        ``"design"``, ``"diverged"``, ``"domain"``); infos without a domain are skipped."""
        if self._writer is None or "domain" not in info:
            return
        flat = _flat(info["domain"])
        self._writer.writerow([t, _design_str(info.get("design")), f"{info['episode']['r']:.6g}",
                               int(bool(info.get("diverged", False)))]
                              + [f"{flat[c]:.6g}" if c in flat else "" for c in self.columns[4:]])

    def flush(self) -> None:
        if self._file is not None and not self._file.closed:
            self._file.flush()

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


def read_domain_log(path: str | os.PathLike) -> dict[str, np.ndarray | list]:
    """``domain.csv`` as columns: ``t`` (int64), ``design`` (strings), ``diverged`` (bool) and
    every other column (``return_<unit>`` and the draws) as float64.

    Raises:
        ValueError: a missing or malformed file (names the file and line).
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path} does not exist (the run did not randomize its domain?)")
    with open(path, newline="", encoding="utf-8") as f:
        rows = list(csv.reader(f))
    if not rows or len(rows[0]) < 4 or tuple(rows[0][:4]) != log_columns(rows[0][2].removeprefix("return_")):
        raise ValueError(f"{path}: not a domain log (header {rows[0] if rows else []})")
    header, body = rows[0], [r for r in rows[1:] if r]
    out: dict = {c: [] for c in header}
    for line, r in enumerate(body, start=2):
        if len(r) != len(header):
            raise ValueError(f"{path}, line {line}: {len(r)} fields, the header has {len(header)}")
        for c, v in zip(header, r):
            out[c].append(v)
    try:
        return {c: (np.array(v, np.int64) if c == "t" else v if c == "design" else
                    np.array(v, np.int64).astype(bool) if c == "diverged" else np.array(v, float))
                for c, v in out.items()}
    except ValueError as exc:
        raise ValueError(f"{path}: malformed value ({exc})") from None


# -- robust evaluation ------------------------------------------------------------------------
@dataclass(frozen=True)
class RandomizedEvaluation:
    """Outcome of :func:`evaluate_randomized`.

    Attributes:
        run, checkpoint: where the policy came from. design: the canonical design.
        ranges: the ranges drawn from. seed: the env RNG's seed.
        nominal_return_cm: the policy's return without randomization, in :attr:`unit`.
        returns_cm: ``(N,)`` returns of the randomized episodes, in :attr:`unit`. diverged: ``(N,)`` bool.
        domains: per episode its draw (:meth:`DomainSample.as_dict`).
        task: the run's task's settings (:meth:`softcrawl.tasks.Task.settings`). unit: its unit
            (``"cm"``, ``"deg"``). n_regulators: the run's space's regulators (the draws' columns).
    """

    run: str
    checkpoint: str
    design: tuple[int, ...]
    ranges: DomainRanges
    seed: int
    nominal_return_cm: float
    nominal_diverged: bool
    returns_cm: tuple[float, ...]
    diverged: tuple[bool, ...]
    domains: tuple[dict, ...]
    task: dict | None = None
    unit: str = "cm"
    n_regulators: int = PAPER_REGULATORS

    def stats(self) -> dict:
        """``n``, ``mean_<unit>``, ``std_<unit>`` (population), ``min_``, ``max_``, ``q25_``,
        ``median_``, ``q75_<unit>`` of the returns (:attr:`unit`), ``n_diverged``."""
        r = np.asarray(self.returns_cm, float)
        q = np.percentile(r, [25, 50, 75])
        u = self.unit
        return {"n": int(r.size), f"mean_{u}": float(r.mean()), f"std_{u}": float(r.std()), f"min_{u}": float(r.min()),
                f"max_{u}": float(r.max()), f"q25_{u}": float(q[0]), f"median_{u}": float(q[1]),
                f"q75_{u}": float(q[2]), "n_diverged": int(np.sum(self.diverged))}

    def to_dict(self) -> dict:
        """JSON-ready (``randomization.json``; ``task`` and ``unit`` only for a task other than
        ``forward``)."""
        u = self.unit
        task = {} if self.task is None or self.task.get("name") == "forward" else {"task": self.task, "unit": u}
        return {"run": self.run, "checkpoint": self.checkpoint, "design": list(self.design), **task,
                "ranges": {k: (list(v) if v is not None else None) for k, v in asdict(self.ranges).items()},
                "seed": self.seed, f"nominal_return_{u}": self.nominal_return_cm,
                "nominal_diverged": self.nominal_diverged, **self.stats(),
                f"returns_{u}": list(self.returns_cm), "diverged": list(self.diverged), "domains": list(self.domains)}


def evaluate_randomized(run: str | os.PathLike, design, episodes: int, ranges: DomainRanges | None = None,
                        seed: int = 0, checkpoint: str | os.PathLike | None = None) -> RandomizedEvaluation:
    """The trained policy (deterministic) on ``design`` over ``episodes`` randomized episodes
    (each its own draw from ``ranges``, default the run's ``env.randomize``; the env's RNG
    seeded with ``seed``), and once without randomization (the nominal return).

    Raises:
        ValueError: ``episodes < 1``, no ranges (the run did not randomize and none were
            given), ranges outside :data:`softcrawl.codesign.config.RANDOMIZE_BOUNDS`, and the
            errors of :func:`softcrawl.codesign.evaluation.evaluate_policy`.
    """
    from softcrawl.codesign.evaluation import evaluate_policy, load_run_config

    if int(episodes) != episodes or episodes < 1:
        raise ValueError(f"--randomize needs a positive number of episodes, got {episodes!r}")
    if ranges is None:
        ranges = load_run_config(run).env.randomize
    check_randomize(ranges)
    if not ranges.enabled:
        raise ValueError("no randomization ranges: the run did not randomize its domain; give some with "
                         "--set env.randomize=rig or --set env.randomize.KEY=[low,high]")
    nominal = evaluate_policy(run, design, 1, checkpoint=checkpoint)
    ev = evaluate_policy(run, design, int(episodes), checkpoint=checkpoint, randomize=ranges, seed=int(seed))
    return RandomizedEvaluation(str(run), ev.checkpoint, tuple(ev.design), ranges, int(seed),
                                float(nominal.returns_cm[0]), bool(nominal.diverged[0]),
                                tuple(float(r) for r in ev.returns_cm), tuple(bool(d) for d in ev.diverged),
                                tuple(ev.domains), ev.task.settings(), ev.unit,
                                ev.config.env.design_space().n_regulators)


def write_randomized(out: str | os.PathLike, result: RandomizedEvaluation, overwrite: bool = False) -> Path:
    """Write ``randomization.json``, ``randomization.csv`` and ``randomization.png`` (module
    docstring) into the folder ``out``, atomically
    (:func:`softcrawl.robot.output.staged_directory`). Returns ``out`` as a Path.

    Raises:
        OutputExistsError: ``out`` exists (without ``overwrite``) or is not a softcrawl output.
        OutputWriteError: disk full or read-only file system.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from softcrawl.robot.output import staged_directory

    columns, u = list(result.ranges.columns(result.n_regulators)), result.unit
    with staged_directory(out, overwrite) as tmp:
        (tmp / "randomization.json").write_text(json.dumps(result.to_dict(), indent=2) + "\n")
        with open(tmp / "randomization.csv", "w", newline="", encoding="utf-8") as f:
            w = csv.writer(f)
            w.writerow(["episode", f"return_{u}", "diverged", *columns])
            for k, (r, d, dom) in enumerate(zip(result.returns_cm, result.diverged, result.domains)):
                flat = _flat(dom)
                w.writerow([k, f"{r:.6g}", int(d), *(f"{flat[c]:.6g}" for c in columns)])
        fig = Figure(figsize=(6.0, 3.6))
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
        r = np.asarray(result.returns_cm, float)
        ax.hist(r, bins=max(5, min(30, int(np.sqrt(r.size)) + 1)), color="tab:blue", alpha=0.8,
                label=f"randomized (N = {r.size})")
        ax.axvline(result.nominal_return_cm, color="k", ls="--", label=f"nominal {result.nominal_return_cm:+.3f} {u}")
        ax.axvline(r.mean(), color="tab:red", label=f"mean {r.mean():+.3f} {u}")
        ax.set_xlabel(f"return ({u})")
        ax.set_ylabel("episodes")
        ax.set_title(f"design {','.join(map(str, result.design))}: domain-randomized returns")
        ax.legend(fontsize=8)
        fig.savefig(tmp / "randomization.png", dpi=110, bbox_inches="tight")
    return Path(out)
