"""``softcrawl rig``: check a rig description and its instruments.

- ``softcrawl rig check rig.toml``: validate the file, connect, identify the supply
  (``*IDN?``), read its output voltages and the sensors' absolute pressures (the atmospheric
  zero), and print what it sees. Nothing moves: the supply is set to 0 V with its outputs off.
  ``--sim`` runs the same check on the simulated rig (no hardware).
- ``softcrawl rig fit LOG_DIR``: fit the regulator model (:mod:`softcrawl.hardware.regulator_model`)
  to recorded logs and print its error on held-out logs; a file that cannot be read (malformed,
  a value that does not fit, not a regular file) is refused and listed, the others are fitted.
- ``softcrawl rig example``: print the example ``rig.toml`` shipped with softcrawl.

Exit codes: 0 all good, 1 an instrument did not answer (the supply was then read back off at
0 V, or never opened), 2 a bad rig file, 3 the supply could not be confirmed off.
"""

from __future__ import annotations

import argparse
import sys

from softcrawl.cli import bounded


def _check(args: argparse.Namespace) -> int:
    import numpy as np

    from softcrawl.hardware.config import load_rig_config
    from softcrawl.hardware.errors import RigError

    cfg = load_rig_config(args.rig)  # RigConfigError (ValueError) -> exit 2
    r, s = cfg.rig, cfg.supply
    print(f"{cfg.path}: rig {r.name!r}: limit {r.max_kpa:g} kPa, {r.control_period_s:g} s actions, "
          f"logging at {r.sample_hz:g} Hz, watchdog {r.watchdog_s:g} s, disagreement {r.disagreement_kpa:g} kPa "
          f"for {r.disagreement_s:g} s")
    for i, m in enumerate(cfg.regulators):
        print(f"  regulator {i + 1}: supply channel {m.channel}, {m.volts_per_kpa:g} V/kPa + {m.offset_v:g} V "
              f"({m.volts(r.max_kpa):.3f} V at {r.max_kpa:g} kPa; channel limit {s.max_volts[m.channel - 1]:g} V)")
    if args.sim:
        from softcrawl.hardware.simrig import SimRig

        rig = SimRig(cfg).rig
    else:
        from softcrawl.hardware.rig import open_rig

        try:
            rig = open_rig(cfg)
        except RigError as exc:
            print(f"softcrawl rig check: error: {exc}", file=sys.stderr)
            return 1
    try:
        src = rig.source
        idn = src.supply.identify()
        src.supply.remote()
        src.supply.output(False)
        src.set_kpa(np.zeros(3))
        v = src.measure_volts()
        print(f"supply ({s.address}): {idn}; outputs off; measured {', '.join(f'{x:.3f}' for x in v)} V")
        sensors = rig.sensors
        if hasattr(sensors, "read_abs"):
            z = sensors.zero()
            print(f"sensors ({cfg.sensors.kind}): atmospheric zero {', '.join(f'{x:.2f}' for x in z)} kPa absolute")
        else:
            print("sensors: none configured (deploy runs without the disagreement check)")
        src.supply.local()
    except RigError as exc:
        print(f"softcrawl rig check: error: {exc}", file=sys.stderr)
        if not rig.fail_safe().confirmed:
            print("softcrawl rig check: DANGER: could not confirm that the supply is off and at 0 V: switch it off "
                  "by hand", file=sys.stderr)
            return 3
        return 1
    finally:
        rig.close()
    print("rig check passed" + (" (simulated rig)" if args.sim else ""))
    return 0


def _fit(args: argparse.Namespace) -> int:
    import json

    from softcrawl.hardware import regulator_model as rm
    from softcrawl.hardware.logs import read_auro_logs
    from softcrawl.safeio import atomic_write_text

    good, bad = read_auro_logs(args.logs)
    if len(good) < 4:
        raise ValueError(f"{args.logs}: need >= 4 complete logs-*.csv files, found {len(good)} ({len(bad)} refused)")
    fit, held = rm.split_trials(good, args.hold_out_every)
    params = rm.fit_regulators(fit)
    err, naive = rm.prediction_errors(params, held), rm.prediction_errors([rm.RegulatorParams(1, 0, 1e-3, 1e-3)] * 3,
                                                                           held)
    print(f"{len(good)} logs ({len(bad)} refused: short or malformed); fit on {len(fit)}, held out {len(held)}")
    for i, p in enumerate(params):
        e = err["per_regulator"][i]
        print(f"  regulator {i + 1}: target = {p.gain:.4f} x command {p.offset:+.3f} kPa, inflate lag "
              f"{p.tau_inflate:.3f} s, vent lag {p.tau_vent:.3f} s; held-out RMSE {e['rmse']:.2f} kPa, "
              f"median {e['median_abs']:.2f} kPa")
    print(f"held-out one-step error over {err['n_holds']} holds: RMSE {err['rmse']:.2f} kPa, MAE {err['mae']:.2f}, "
          f"median {err['median_abs']:.2f}, 90th percentile {err['p90_abs']:.2f} (sensor = command: RMSE "
          f"{naive['rmse']:.2f}, median {naive['median_abs']:.2f})")
    for _, why in bad:  # each reason names its file
        print(f"  refused: {why}")
    if args.out:
        atomic_write_text(args.out, json.dumps({"regulators": rm.params_to_dict(params), "held_out": err,
                                                "naive_held_out": naive, "n_fit": len(fit), "n_held_out": len(held),
                                                "refused": bad}, indent=2))
        print(f"wrote {args.out}")
    return 0


def _example(args: argparse.Namespace) -> int:
    from softcrawl.hardware.config import example_rig_path

    sys.stdout.write(example_rig_path().read_text(encoding="utf-8"))
    return 0


def register(subparsers) -> None:
    """Add the ``rig`` subcommand (``check``, ``example``) to ``subparsers``."""
    p = subparsers.add_parser("rig", help="check a real rig's description and instruments",
                              description="Check a rig.toml and the instruments it names (BK 9129B supply, "
                              "Honeywell SSC sensors), or print the example rig.toml.")
    sub = p.add_subparsers(dest="rig_command", required=True)
    c = sub.add_parser("check", help="validate rig.toml, connect, identify each instrument, print what it sees")
    c.add_argument("rig", metavar="RIG.toml", help="rig description")
    c.add_argument("--sim", action="store_true", help="check against the simulated rig instead of hardware")
    c.set_defaults(func=_check)
    f = sub.add_parser("fit", help="fit the regulator model to recorded logs (AuRo 2023 format) and report "
                                   "its error on held-out logs")
    f.add_argument("logs", metavar="LOG_DIR", help="folder searched for logs-*.csv")
    f.add_argument("--hold-out-every", type=int, default=4, **bounded(2, 1000),
                   help="hold out every k-th log, sorted by path (default 4)")
    f.add_argument("--out", metavar="FILE.json", default=None, help="also write the fit and errors as JSON")
    f.set_defaults(func=_fit)
    e = sub.add_parser("example", help="print the example rig.toml")
    e.set_defaults(func=_example)
