"""``softcrawl compare SIM_RUN REAL_LOG... --out DIR``: simulation vs real runs.

``SIM_RUN`` is a ``softcrawl simulate`` / ``softcrawl evaluate`` output folder; each
``REAL_LOG`` a ``softcrawl deploy`` folder or a recorded AuRo 2023 ``logs-*.csv``. With
``--tracked`` (one ``t_s,x_mm`` CSV or ArUco video per real log, in order) the distances are
compared too.
Writes ``compare.md``, ``compare.json``, ``pressures.png`` and ``distance.png``.
"""

from __future__ import annotations

import argparse

from softcrawl.cli import bounded
from softcrawl.cli.calibrate import ARUCO_IDS


def _run(args: argparse.Namespace) -> int:
    from softcrawl.hardware.compare import compare
    from softcrawl.robot.output import check_output_path, mark_output

    out = check_output_path(args.out, args.overwrite)  # before any work: never into a stranger's folder
    res = compare(args.sim_run, args.real_logs, out, args.tracked, args.time_scale, args.marker_id,
                  args.marker_mm)
    mark_output(out)
    sp = res["spread"]
    extra = (f"; real final distances mean {sp['mean_cm']:+.2f} cm (std {sp['std_cm']:.2f}, n={sp['n']})"
             if sp else "")
    print(f"compared {len(res['logs'])} real log(s) with {args.sim_run}: sim {res['sim_final_distance_cm']:+.2f} cm"
          f"{extra}; wrote {args.out}/compare.md")
    return 0


def register(subparsers) -> None:
    """Add the ``compare`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("compare", help="compare a simulated episode with real rig logs",
                              description="Sim vs real: commanded, simulated-applied and sensed pressures per "
                              "regulator; distance vs time from tracked CSVs; spread of final distances; a Markdown "
                              "summary.")
    p.add_argument("sim_run", metavar="SIM_RUN", help="output folder of softcrawl simulate / evaluate")
    p.add_argument("real_logs", metavar="REAL_LOG", nargs="+", help="deploy folder(s) or recorded logs-*.csv")
    p.add_argument("--tracked", nargs="+", metavar="TRACK.csv|VIDEO", default=None,
                   help="one t_s,x_mm CSV or video (one ArUco marker on the disk, camera above, crawl along the "
                        "image's +x; needs softcrawl[vision]) per REAL_LOG, same order")
    p.add_argument("--marker-id", type=int, default=0, **bounded(*ARUCO_IDS),
                   help="videos: ArUco id of the disk marker (default 0)")
    p.add_argument("--marker-mm", type=float, default=30.0, **bounded(0.0, 1000.0, "mm", open_low=True),
                   help="videos: side of the disk marker, mm (default 30)")
    p.add_argument("--time-scale", type=float, default=None, **bounded(0.0, 100.0, open_low=True),
                   help="stretch simulated time by this factor (default: 1, or the rig period / the policy's "
                        "action hold when a deploy log ran a policy trained with another hold)")
    p.add_argument("--out", required=True, help="output folder (new, or with --overwrite one softcrawl wrote)")
    p.add_argument("--overwrite", action="store_true",
                   help="write into an existing output folder if it is empty or softcrawl wrote it")
    p.set_defaults(func=_run)
