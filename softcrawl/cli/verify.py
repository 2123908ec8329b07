"""``softcrawl verify``: run the physics checks and print a table (or JSON)."""

from __future__ import annotations

import argparse
import json
import sys


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "verify", help="check the physics against closed-form results",
        description="Run the FEM engine on problems with closed-form answers (verification.md), and the JAX "
                    "engine's contact solve on this machine's JAX device (a GPU where JAX has one: jax_incline), "
                    "and report expected vs simulated values. Exit status 1 if any check fails.")
    p.add_argument("--resolution", choices=("coarse", "medium", "fine"), default="coarse",
                   help="mesh resolution of the checks (coarse: about a minute)")
    p.add_argument("--only", nargs="+", metavar="CHECK", help="run only these checks")
    p.add_argument("--json", action="store_true", help='print {"checks": [...]} instead of a table')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from softcrawl.verify.checks import run_checks

    def show(r) -> None:
        if not args.json:
            unit = f" {r.unit}" if r.unit else ""
            bound = {"rel": f"tolerance {r.tolerance:.3g} rel", "abs": f"tolerance {r.tolerance:.3g}{unit}",
                     "min": "lower bound"}[r.mode]
            print(f"{'PASS' if r.passed else 'FAIL'}  {r.name}\n      expected {r.expected:.6g}{unit}, "
                  f"got {r.got:.6g}{unit}, {bound}", flush=True)

    if not args.json:
        print(f"softcrawl verify ({args.resolution})", flush=True)
    results = run_checks(args.resolution, args.only, on_result=show)
    n_fail = sum(not r.passed for r in results)
    if args.json:
        json.dump({"resolution": args.resolution, "checks": [r.to_dict() for r in results]}, sys.stdout, indent=1)
        print()
    else:
        print(f"{len(results) - n_fail} passed, {n_fail} failed")
    return 1 if n_fail else 0
