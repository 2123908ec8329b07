"""``softcrawl calibrate BENDS.csv --out DIR``: the paper's pressure warp from measured bends.

``BENDS.csv`` has a header ``real_kpa,tip_angle_deg`` (or ``real_kpa,tip_deflection_mm``) and
one row per measurement of one real PneuNet clamped at its inner end; or give a folder of
side-on photos with ArUco markers (:mod:`softcrawl.hardware.aruco`). For each, the clamped
full-order leg is simulated to find the sim pressure giving the same bend (root finding,
cached in ``$SOFTCRAWL_CACHE_DIR/bend_curves``); an affine least-squares fit
``sim = a * real + b`` follows. Writes ``calibration.json`` (give it to ``--calibration``),
``calibration.png`` (the paper-style plot) and prints the fit with its residuals.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from softcrawl.cli import bounded

#: ArUco ids of the markers' dictionary, ``DICT_4X4_50`` (:mod:`softcrawl.hardware.aruco`).
ARUCO_IDS = (0, 49)


def _run(args: argparse.Namespace) -> int:
    from softcrawl.hardware.calibration import (BendCurve, BendModel, calibrate, check_measurements, plot_calibration,
                                                read_bends_csv, write_calibration)

    if Path(args.bends).is_dir():  # photos with ArUco markers
        from softcrawl.hardware.aruco import bends_from_photos

        real, bend = bends_from_photos(args.bends, args.base_id, args.tip_id)
        measure = "tip_angle_deg"
    else:
        real, bend, measure = read_bends_csv(args.bends)
    check_measurements(real, bend)  # implausible input is refused before --out is created
    out = Path(args.out)
    if out.exists() and (out / "calibration.json").exists() and not args.overwrite:
        raise ValueError(f"{out}/calibration.json exists (use --overwrite)")
    out.mkdir(parents=True, exist_ok=True)
    curve = BendCurve(BendModel(mesh_size=args.mesh_size), cache=not args.no_cache)
    res = calibrate(real, bend, measure, curve, progress=not args.no_progress)
    path = write_calibration(res, out / "calibration.json", source=str(args.bends))
    plot_calibration(res, out / "calibration.png")
    d = res.to_dict()
    print(f"sim = {res.a:.4f} * real {res.b:+.3f} kPa (clamped >= 0); rms residual {d['rms_residual_kpa']:.3f} kPa, "
          f"max {d['max_abs_residual_kpa']:.3f} kPa; {curve.evaluations} simulations ({len(curve.points)} cached)")
    for p in d["points"]:
        print(f"  real {p['real_kpa']:7.2f} kPa  bend {p['bend']:8.3f}  ->  sim {p['sim_kpa']:8.2f} kPa  "
              f"(fit {p['fit_kpa']:8.2f}, residual {p['residual_kpa']:+.2f})")
    print(f"wrote {path} and {out / 'calibration.png'}")
    return 0


def register(subparsers) -> None:
    """Add the ``calibrate`` subcommand to ``subparsers``."""
    p = subparsers.add_parser("calibrate", help="fit the sim-to-real pressure warp from measured PneuNet bends",
                              description="For each measured bend of a real clamped PneuNet, find the sim pressure "
                              "that bends the full-order model as much; fit sim = a * real + b; write "
                              "calibration.json (for --calibration) and calibration.png.")
    p.add_argument("bends", metavar="BENDS.csv|PHOTO_DIR",
                   help="CSV with header real_kpa,tip_angle_deg (or tip_deflection_mm), or a folder of side-on "
                        "photos named <kPa>kpa*.jpg with ArUco markers (DICT_4X4_50) on the clamp and the tip "
                        "(needs softcrawl[vision])")
    p.add_argument("--base-id", type=int, default=0, **bounded(*ARUCO_IDS),
                   help="photos: ArUco id of the clamp marker (default 0)")
    p.add_argument("--tip-id", type=int, default=1, **bounded(*ARUCO_IDS),
                   help="photos: ArUco id of the tip marker (default 1)")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--mesh-size", type=float, default=8.0, **bounded(3.0, 20.0, "mm"),
                   help="leg mesh size of the bend model, mm (default 8)")
    p.add_argument("--no-cache", action="store_true", help="do not read or write the bend cache")
    p.add_argument("--overwrite", action="store_true", help="replace an existing calibration.json in --out")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=_run)
