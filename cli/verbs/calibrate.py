"""Calibrate the rig (thesis 4.3.2).

Sub-verbs:
  camera    intrinsics (fx fy cx cy, k1 k2 p1 p2 k3) from a folder of checkerboard views
  geometry  holder and cylinder poses from a capture's calibration image (a diagnostic:
            extract and diagnose solve the same poses from each rotation's
            calibration image themselves and read no geometry.json)

Examples (twin, quarter resolution):
  glossrig simulate --target checkerboard --views 12 --scale 0.25 --seed 1 --out checker
  glossrig calibrate camera checker --out camera.json --plot camera.png
  glossrig simulate --material lambert:0.8 --leds 9 --rotations 0 --scale 0.25 --seed 2 --out cap
  glossrig calibrate geometry cap --camera camera.json --out geometry.json --diagnostic geometry.png
"""
from __future__ import annotations

import argparse

from glossrig.cli.outputs import add_force_option, prepare_output
from glossrig.cli.verbs import SubVerb

HELP = "calibrate the camera (checkerboard) or a capture's geometry (markers)"
SUBVERB_METAVAR = "WHAT"


def _parse_board(text: str | None) -> tuple[int, int] | None:
    from glossrig.core.errors import InputError

    if text is None:
        return None
    try:
        nx, ny = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--board: expected inner corners as NXxNY (e.g. 9x6), got {text!r}") from None
    return nx, ny


def add_camera_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("checker_dir", help="capture folder holding the checkerboard views")
    p.add_argument("--out", required=True, help="camera calibration JSON to write")
    p.add_argument("--board", default=None, help="inner corners NXxNY (default: the rig's [checkerboard])")
    p.add_argument("--square", type=float, default=None, help="square size in mm (default: the rig's)")
    p.add_argument("--min-views", type=int, default=None, help="fewest usable views accepted (default 5)")
    p.add_argument("--plot", default=None, help="also write a PNG of per-view errors and residuals")
    add_force_option(p, "existing --out and --plot files")
    p.add_argument("--no-progress", action="store_true")


def run_camera(args) -> int:
    from glossrig.core.calibration.intrinsics import MIN_VIEWS, calibrate_intrinsics, plot_calibration, save_camera

    prepare_output(args.out, args.force)
    if args.plot:
        prepare_output(args.plot, args.force)
    cal, report = calibrate_intrinsics(args.checker_dir, _parse_board(args.board), args.square,
                                       min_views=args.min_views or MIN_VIEWS, progress=not args.no_progress)
    save_camera(cal, report, args.out, overwrite=args.force)
    for s in report["skipped"]:
        print(f"skipped {s['file']}: {s['reason']}")
    sd = report["std"]
    print(f"{len(report['views'])} views, reprojection RMS {cal.rms_px:.3f} px")
    print(f"fx {cal.fx:.2f} +- {sd['fx']:.2f}  fy {cal.fy:.2f} +- {sd['fy']:.2f}  "
          f"cx {cal.cx:.2f} +- {sd['cx']:.2f}  cy {cal.cy:.2f} +- {sd['cy']:.2f}  (px)")
    print("k1 k2 p1 p2 k3 = " + " ".join(f"{v:.6g}" for v in cal.distortion))
    if args.plot:
        plot_calibration(cal, report, args.plot)
        print(f"plot written to {args.plot}")
    print(f"camera calibration written to {args.out}")
    return 0


def add_geometry_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("capture_dir", help="capture folder (capture.json + raw files)")
    p.add_argument("--camera", required=True, help="camera calibration JSON (glossrig calibrate camera)")
    p.add_argument("--out", required=True, help="geometry JSON to write")
    p.add_argument("--rotation", type=float, default=None, help="use the calibration image of this rotation")
    p.add_argument("--diagnostic", default=None, help="PNG with markers, corners, fitted edges and pose axes")
    p.add_argument("--holder-edges", choices=["inner", "all"], default="inner",
                   help="holder-marker edges fitted in the refinement (default: the white patch's)")
    add_force_option(p, "existing --out and --diagnostic files")


def run_geometry(args) -> int:
    import cv2
    import numpy as np

    from glossrig.core.calibration.poses import calibrate_capture, save_geometry

    prepare_output(args.out, args.force)
    if args.diagnostic:
        prepare_output(args.diagnostic, args.force)

    res = calibrate_capture(args.capture_dir, args.camera, rotation=args.rotation, diagnostic=args.diagnostic,
                            holder_edge_set=args.holder_edges)
    save_geometry(res, args.out, overwrite=args.force)
    h, c = res["holder"], res["cylinder_in_holder"]
    cam = res["camera_in_holder"]["centre_mm"]
    ang = np.degrees(np.linalg.norm(cv2.Rodrigues(c["R"])[0]))
    print(f"{res['file']}: holder t = {np.round(h['t_mm'], 3).tolist()} mm (camera frame), "
          f"corner reprojection RMS {h['reprojection_rms_px']:.3f} px")
    print(f"cylinder in holder: t = {np.round(c['t_mm'], 3).tolist()} mm, rotation {ang:.3f} deg")
    print(f"camera centre in holder frame: {np.round(cam, 2).tolist()} mm")
    if args.diagnostic:
        print(f"diagnostic image written to {args.diagnostic}")
    print(f"geometry written to {args.out}")
    return 0


def add_lamps_arguments(p: argparse.ArgumentParser) -> None:
    from glossrig.core.calibration.lamps import LAMP_DRAWS

    p.add_argument("specular_dir", help="capture folder of the specular sample")
    p.add_argument("--camera", required=True, help="camera.json from glossrig calibrate camera")
    p.add_argument("--out", required=True, help="lamps.json to write")
    # the defaults are the core's and the help formatter (glossrig.cli.main) shows them
    p.add_argument("--draws", type=int, default=LAMP_DRAWS,
                   help="draws of the camera calibration and poses for each lamp's stated uncertainty")
    p.add_argument("--seed", type=int, default=0, help="seed of those draws")
    add_force_option(p, "an existing --out file")
    p.add_argument("--no-progress", action="store_true")


def run_lamps(args) -> int:
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import calibrate_lamps, save_lamps

    prepare_output(args.out, args.force)
    d = calibrate_lamps(args.specular_dir, load_camera(args.camera), progress=not args.no_progress,
                        n_draws=args.draws, seed=args.seed)
    save_lamps(d, args.out)
    for k, v in d["lamps_mm"].items():
        print(f"LED {k}: {[round(x, 2) for x in v]} mm, standard uncertainty "
              f"{[round(x, 2) for x in d['std_mm'][k]]} mm per holder axis "
              f"(spread of the highlight estimates {d['spread_mm'][k]:.2f} mm)")
    print(f"lamp positions written to {args.out}")
    return 0


SUBVERBS = (
    SubVerb("camera", "intrinsics from checkerboard views", add_camera_arguments, run_camera,
            description="Camera intrinsics from the checkerboard images (role 'checkerboard') of a capture "
                        "folder: OpenCV corner detection and calibrateCamera (k1 k2 p1 p2 k3). Views where "
                        "the board is not found are reported and skipped."),
    SubVerb("geometry", "holder and cylinder poses from a capture's calibration image (diagnostic: for "
                        "checking; extract does not read its output)", add_geometry_arguments, run_geometry,
            description="Find the holder marker and the three cylinder markers in the calibration image, "
                        "solve their poses (PnP, refined on the raw edges) and express the cylinder and camera "
                        "in the holder frame (thesis eq. 4.18-4.25). A diagnostic step: glossrig extract and "
                        "glossrig diagnose solve the same poses from each rotation's calibration image "
                        "themselves and read no geometry JSON; use this to check the markers and poses "
                        "(--diagnostic draws them) before measuring."),
    SubVerb("lamps", "lamp positions from a capture of a specular sample", add_lamps_arguments, run_lamps,
            description="Lamp positions (thesis 4.3.4): for every sequenced LED, the mirror rays of the "
                        "highlight's samples of a highly specular sample (the transparency sheet), intersected "
                        "with the LEDs' measured distance from the cylinder axis, refined with the sample's "
                        "diffuse reflection. Each lamp's standard uncertainty (lamps.json std_mm, per holder "
                        "axis) is the spread of the positions solved again under --draws draws of the camera "
                        "calibration and the capture's poses, with the refinement's noise."),
)
