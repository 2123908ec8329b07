"""Which forms of the step a GPU stage's timings make the default, by the rule of
``benchmarks/gpu_checks.sh``.

Reads the JSON lines ``step_cost.py --time --reference FILE`` printed for one stage's forms (the
first form is the baseline: it stored the reference; each later one was compared with it on the
same robots) and prints one JSON line per later form, then a summary line. A form becomes the
default where, at every batch size the baseline was timed at:

* it is faster (``ms_per_step``),
* its robots end within :data:`BUDGET_MM` of the baseline's (``reference_p99_robot_distance_mm``,
  the 99th percentile of each robot's largest disk-node distance; the budget between the CPU
  and JAX engines over 2 s),
* and no robot is invalid in it that the baseline keeps (``bad_robots_here_only``).

A form timed at fewer batch sizes than the baseline (its call ran out of time) is not decided.

Usage:
    python benchmarks/gpu_verdict.py OUTDIR/candidates.jsonl
"""

from __future__ import annotations

import argparse
import json
import sys

#: The largest 99th-percentile distance (mm) of a form's robots from the baseline's.
BUDGET_MM = 0.5


def forms(lines: list[dict]) -> list[tuple[dict, dict[int, dict]]]:
    """The timed lines (those with ``ms_per_step``) grouped by form, in order of first appearance:
    ``[(settings, {batch: line})]``; a form's settings are the line's entries that its
    ``form_keys`` name (``step_cost.py`` lists there the settings it measured with)."""
    grouped: dict[tuple, tuple[dict, dict[int, dict]]] = {}
    for line in lines:
        if "ms_per_step" not in line:
            continue
        if "form_keys" not in line:
            raise ValueError(f"a timed line without form_keys (batch {line.get('batch')}): not step_cost.py's")
        settings = {k: line.get(k) for k in line["form_keys"]}
        grouped.setdefault(tuple(settings.items()), (settings, {}))[1][int(line["batch"])] = line
    return list(grouped.values())


def verdicts(lines: list[dict]) -> list[dict]:
    """One verdict per form after the first (module doc): ``{"form": its settings that differ from
    the baseline's, "speedup": {batch: baseline ms / form ms}, "p99_mm": the largest over the
    batches, "extra_invalid": robots, "decided": bool, "default": bool}``.

    Raises:
        ValueError: no timed lines, or a later form's line without the comparison with the
            baseline (it was not run with ``--reference``)."""
    grouped = forms(lines)
    if not grouped:
        raise ValueError("no timed lines (ms_per_step) to judge")
    (base, base_lines), out = grouped[0], []
    for settings, timed in grouped[1:]:
        if any("reference_p99_robot_distance_mm" not in line for line in timed.values()):
            raise ValueError(f"form {settings} was not compared with the baseline (step_cost.py --reference)")
        decided = set(timed) >= set(base_lines)
        speedup = {b: base_lines[b]["ms_per_step"] / timed[b]["ms_per_step"] for b in sorted(timed) if b in base_lines}
        p99 = max(line["reference_p99_robot_distance_mm"] for line in timed.values())
        extra = sum(line["bad_robots_here_only"] for line in timed.values())
        out.append({"form": {k: v for k, v in settings.items() if v != base.get(k)},
                    "speedup": {str(b): round(v, 4) for b, v in speedup.items()}, "p99_mm": p99,
                    "extra_invalid": extra, "decided": decided,
                    "default": decided and all(v > 1 for v in speedup.values()) and p99 <= BUDGET_MM and extra == 0})
    return out


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("jsonl", help="the stage's step_cost.py lines, the baseline's first")
    args = p.parse_args(argv)
    with open(args.jsonl) as f:
        lines = [json.loads(line) for line in f if line.startswith("{")]
    try:
        judged = verdicts(lines)
    except ValueError as e:
        sys.exit(f"gpu_verdict: {e}")
    for v in judged:
        print(json.dumps(v), flush=True)
    print(json.dumps({"make_default": [v["form"] for v in judged if v["default"]],
                      "undecided": [v["form"] for v in judged if not v["decided"]]}), flush=True)


if __name__ == "__main__":
    main()
