"""``softcrawl deploy``: run a gait on a rig (real or simulated), fail-safe.

Examples::

    softcrawl deploy --rig sim --run runs/smoke --design 1,0,0,2,2,0,0,0 --out deploy/sim1
    softcrawl deploy --rig sim --run runs/demo --out deploy/sim2      # the run's own design
    softcrawl deploy --rig rig.toml --actions gait.csv --out deploy/real1
    softcrawl deploy --rig rig.toml --gait sine --phase 110 --out deploy/baseline1

Writes ``log.csv`` (>= 10 Hz samples: commanded kPa, set V, measured V, sensed kPa, overrun
flags, events) and ``summary.json`` into ``--out``. The gait is range-checked (0-90 kPa and
the rig's limit) before the rig is touched. SIGINT, SIGTERM, SIGHUP and SIGQUIT stop the run
through the fail-safe (:mod:`softcrawl.hardware.deploy`). An option that would be ignored is
refused (``--n-actions`` or ``--phase`` beside ``--run`` or ``--actions``, ``--phase`` with
``--gait paper-best``, ``--seed``, ``--jitter`` or ``--sim-config`` with a real rig).

Exit codes: 0 completed (vented, outputs confirmed off); 1 the run stopped early or its log or
summary could not be written, and the rig is safe: the fail-safe vented it and read the outputs
back off (reason printed and logged), or the instruments could not be opened (nothing sent);
2 bad input (nothing sent); 3 the fail-safe could not confirm that the supply is off (it may
still be pressurising the lines: switch it off by hand).
"""

from __future__ import annotations

import argparse
import sys

import numpy as np

from softcrawl.cli import SEED_BOUNDS, bounded

GAITS = ("sine", "paper-best")
EXIT_COMPLETED, EXIT_STOPPED, EXIT_BAD_INPUT, EXIT_UNCONFIRMED = 0, 1, 2, 3
#: Most actions of a built-in gait (``--n-actions``): over a day of 1 s actions.
MAX_ACTIONS = 100_000
#: Defaults of the built-in gaits' ``--n-actions`` and ``--phase`` (degrees), and of the
#: simulated rig's ``--seed`` and ``--jitter`` (s).
N_ACTIONS, PHASE_DEG, SIM_SEED, SIM_JITTER_S = 20, 110.0, 0, 0.002


def exit_code(res) -> int:
    """The exit code of a :class:`softcrawl.hardware.deploy.DeployResult` (module docstring)."""
    if not res.fail_safe_confirmed:
        return EXIT_UNCONFIRMED
    if res.status != "completed" or res.write_errors:
        return EXIT_STOPPED
    return EXIT_COMPLETED


def _say(text: str, err: bool = False) -> None:
    """Print one line; a terminal that is gone (SIGHUP, a closed pipe) is not an error here."""
    try:
        print(text, file=sys.stderr if err else sys.stdout, flush=True)
    except OSError:
        pass


def policy_actions(run: str, design: str | None, checkpoint: str | None = None, samples: int | None = None):
    """The trained run's gait for ``design`` (None: the run's design, the best gait of its final
    shortlist or without one its most probable design,
    :func:`softcrawl.codesign.shortlist.run_design`), ``(n, R)`` real kPa (``R``: the
    regulators of the run's space), and a description dict: the best of its deterministic
    actions and ``samples`` episodes sampled from the policy (default
    :data:`~softcrawl.codesign.evaluation.GAIT_SAMPLES`: the report's gait). The one place that
    calls the co-design evaluation API.

    Raises:
        ValueError: ``checkpoint`` without ``design`` (the run's design is its last
            checkpoint's), and as :func:`~softcrawl.codesign.evaluation.evaluate_policy`.
    """
    from softcrawl.codesign.evaluation import GAIT_SAMPLES, evaluate_policy

    if design is None:
        if checkpoint is not None:
            raise ValueError("--checkpoint needs --design: the run's own design is its last checkpoint's")
        from softcrawl.codesign.shortlist import run_design

        design = run_design(run)["design"]
    ev = evaluate_policy(run, design, episodes=1, checkpoint=checkpoint,
                         samples=GAIT_SAMPLES if samples is None else samples)
    hold = ev.config.env.steps_per_action * ev.config.env.robot.dt
    return np.asarray(ev.gait_actions_kpa, dtype=float), {
        "source": "policy", "run": str(run), "checkpoint": ev.checkpoint, "design": list(ev.design),
        "gait_source": ev.gait_source, f"sim_return_{ev.unit}": ev.gait_return, "sim_hold_s": hold}


def gait_actions(args: argparse.Namespace, n_regulators: int):
    """``(actions (n, R) kPa, description)`` from --run / --actions / --gait; ``--actions`` is
    read with ``n_regulators`` columns (the rig's regulators: a file of another width is one
    ValueError line naming the file and its line, before anything moves). ``--n-actions`` and
    ``--phase`` shape the built-in gaits only: with ``--run`` or ``--actions`` they are refused,
    as ``--design``, ``--checkpoint`` and ``--samples`` are without ``--run``."""
    builtin = args.run is None and args.actions is None
    for flag, value in (("--n-actions", args.n_actions), ("--phase", args.phase)):
        if value is not None and not builtin:
            raise ValueError(f"{flag} shapes a built-in gait (--gait); it goes without "
                             f"{'--run' if args.run is not None else '--actions'}")
    if args.phase is not None and args.gait != "sine":
        raise ValueError(f"--phase is the sine gait's lag; --gait {args.gait} has none")
    n = N_ACTIONS if args.n_actions is None else args.n_actions
    if args.run is not None:
        return policy_actions(args.run, args.design, args.checkpoint, args.samples)
    if args.design is not None or args.checkpoint is not None or args.samples is not None:
        raise ValueError("--design, --checkpoint and --samples go with --run")
    if args.actions is not None:
        from softcrawl.gaits import read_actions_csv

        return (read_actions_csv(args.actions, n_regulators=n_regulators).actions,
                {"source": "actions", "file": str(args.actions)})
    from softcrawl.gaits import SineGait, paper_best_gait

    if args.gait == "sine":
        phase = PHASE_DEG if args.phase is None else args.phase
        g = SineGait(phase_deg=phase)
        return np.array([g.pressure_at(float(k)) for k in range(n)]), {"source": "sine", "phase_deg": phase}
    return paper_best_gait(n_actions=n).actions, {"source": "paper-best"}


def _run(args: argparse.Namespace) -> int:
    from softcrawl.hardware.config import example_rig_path, load_rig_config
    from softcrawl.hardware.deploy import check_regulators, deploy, validate_actions
    from softcrawl.hardware.errors import RigError

    sim = args.rig == "sim"
    if not sim:
        given = [f for f, v in (("--sim-config", args.sim_config), ("--seed", args.seed), ("--jitter", args.jitter))
                 if v is not None]
        if given:
            raise ValueError(f"{', '.join(given)} set the simulated rig (--rig sim), not {args.rig}")
    cfg = load_rig_config(args.sim_config or example_rig_path()) if sim else load_rig_config(args.rig)
    calibration = None
    if args.calibration is not None:
        from softcrawl.hardware.calibration import load_calibration

        calibration = load_calibration(args.calibration)
    if args.run is not None:  # before the policy is rolled out: a space for another rig is refused at once
        from softcrawl.codesign.run import Run

        space = Run(args.run).design_space()
        check_regulators(space.n_regulators, len(cfg.regulators), f"run {args.run} (design space {space.name!r})")
    actions, meta = gait_actions(args, len(cfg.regulators))
    actions = validate_actions(actions, cfg.rig.max_kpa)  # refuse before anything moves
    if calibration is not None:
        meta["calibration"] = {"file": str(args.calibration), "a": calibration.a, "b": calibration.b,
                               "sim_kpa": calibration.to_sim(actions).tolist()}
    if sim:
        from softcrawl.hardware.simrig import SimRig

        rig = SimRig(cfg, seed=SIM_SEED if args.seed is None else args.seed,
                     jitter_s=SIM_JITTER_S if args.jitter is None else args.jitter).rig
    else:
        from softcrawl.hardware.rig import open_rig

        try:
            rig = open_rig(cfg)
        except RigError as exc:
            print(f"softcrawl deploy: error: {exc}", file=sys.stderr)
            return EXIT_STOPPED
    meta["rig_config"] = cfg.path
    hold = meta.get("sim_hold_s")
    if hold is not None and abs(hold - cfg.rig.control_period_s) > 1e-9:
        print(f"softcrawl deploy: warning: the policy was trained with {hold:g} s actions; the rig holds each for "
              f"{cfg.rig.control_period_s:g} s", file=sys.stderr)
    res = deploy(rig, actions, args.out, meta=meta, progress=not args.no_progress)
    sm = res.summary
    _say(f"{res.status}: {sm['n_actions']} actions on {rig.name}, {sm['samples']} samples "
         f"({sm['sample_hz_achieved'] or 0:.1f} Hz), {sm['overruns']} overruns; wrote {res.out}")
    if res.status != "completed":
        _say(f"softcrawl deploy: stopped by the fail-safe: {res.reason} ({'; '.join(res.fail_safe)})", err=True)
    for e in res.write_errors:
        _say(f"softcrawl deploy: error: {e}", err=True)
    code = exit_code(res)
    if code == EXIT_UNCONFIRMED:
        _say("softcrawl deploy: DANGER: the fail-safe could not confirm that the supply is off and at 0 V; it may "
             "still pressurise the lines: switch the supply off by hand", err=True)
    return code


def register(subparsers) -> None:
    """Add the ``deploy`` subcommand to ``subparsers``."""
    from softcrawl.codesign.evaluation import MAX_SAMPLES
    p = subparsers.add_parser("deploy", help="run a gait on a real or simulated rig (fail-safe)",
                              description="Run a gait (a trained run's policy for a design, an action CSV, or a "
                              "built-in gait) on a rig at one action per control period; log at >= 10 Hz to "
                              "--out/log.csv plus summary.json. Any fault vents all lines and turns the outputs off.")
    p.add_argument("--rig", required=True, metavar="RIG.toml|sim", help="rig description, or 'sim' for the "
                   "simulated rig (regulators fitted to recorded real runs)")
    p.add_argument("--sim-config", metavar="RIG.toml", default=None,
                   help="with --rig sim: the rig description to simulate (default: the shipped example)")
    src = p.add_mutually_exclusive_group()
    src.add_argument("--run", default=None, help="trained co-design run: deploy its policy for --design (default: "
                     "the run's design, the best gait of its final shortlist)")
    src.add_argument("--actions", metavar="FILE.csv", default=None,
                     help="action CSV p1,...,pR, one column per regulator of the rig (real kPa per action)")
    src.add_argument("--gait", choices=GAITS, default="sine", help="built-in gait (default sine)")
    p.add_argument("--design", default=None, help="with --run: comma-separated slot values (8 in the paper's space; "
                   "as many as the run's space has slots; default: the run's design)")
    p.add_argument("--checkpoint", default=None, help="with --run: checkpoint folder (default: the latest)")
    p.add_argument("--samples", type=int, default=None, metavar="K", **bounded(0, MAX_SAMPLES),
                   help="with --run: episodes sampled from the stochastic policy; the gait is the best of them and "
                   f"the deterministic one, as the report's (default 11; 0: the deterministic one; at most {MAX_SAMPLES})")
    p.add_argument("--phase", type=float, default=None, **bounded(-360.0, 360.0, "deg"),
                   help=f"sine gait: lag of regulator 2, degrees (default {PHASE_DEG:g})")
    p.add_argument("--n-actions", type=int, default=None, **bounded(1, MAX_ACTIONS),
                   help=f"built-in gaits: number of actions (default {N_ACTIONS}, at most {MAX_ACTIONS})")
    p.add_argument("--calibration", metavar="FILE.json", default=None,
                   help="pressure calibration from `softcrawl calibrate` (recorded with the log: the sim "
                        "pressures the commands correspond to)")
    p.add_argument("--out", required=True, help="output folder for log.csv and summary.json")
    p.add_argument("--seed", type=int, default=None, **bounded(*SEED_BOUNDS),
                   help=f"simulated rig: noise and jitter seed (default {SIM_SEED})")
    p.add_argument("--jitter", type=float, default=None, **bounded(0.0, 1.0, "s"),
                   help=f"simulated rig: mean sleep jitter, s (default {SIM_JITTER_S:g})")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)
