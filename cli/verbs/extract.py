"""Extract BRDF samples from a capture (thesis 4.3-4.4).

Reads SAMPLE_DIR and REF_DIR (capture folders: capture.json + raw files; never
truth.json), the camera calibration (glossrig calibrate camera) and the lamp
positions (glossrig calibrate lamps), and writes the BRDF samples table
(Parquet; columns theta_in, phi_in, theta_out, phi_out, theta_h, phi_h,
theta_d, phi_d in radians in the tangent frame of thesis 4.3.5, r, g, b in
1/sr, weight, u, v, led, rotation in degrees).

The reference is a diffuse sample captured on the same rig with the same LEDs
and rotations; it is treated as Lambertian with --reference-albedo (thesis 4.4:
white paper, 0.8).
"""
from __future__ import annotations

import argparse

HELP = "extract BRDF samples from a sample capture and a diffuse reference capture"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sample_dir", metavar="SAMPLE_DIR")
    p.add_argument("--reference", required=True, metavar="REF_DIR")
    p.add_argument("--camera", required=True, help="camera.json from glossrig calibrate camera")
    p.add_argument("--lamps", required=True, help="lamps.json from glossrig calibrate lamps")
    p.add_argument("--out", required=True, help="samples table to write (.parquet)")
    p.add_argument("--reference-albedo", type=float, default=0.8)
    p.add_argument("--estimator", choices=["ml", "thesis"], default="ml",
                   help="HDR estimator: maximum likelihood for a shot-noise-limited sensor (default) or eq. 4.44 as printed")
    p.add_argument("--plots", default=None, help="folder for diagnostic images")
    p.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    from pathlib import Path

    from glossrig.core.extract import check_compatible, extract_samples
    from glossrig.core.intrinsics import load_camera
    from glossrig.core.lamps import load_lamps
    from glossrig.core.samples import write_samples

    cam = load_camera(args.camera)
    lamps = load_lamps(args.lamps)
    check_compatible(args.sample_dir, args.reference)
    df = extract_samples(args.sample_dir, args.reference, cam, lamps, albedo=args.reference_albedo,
                         estimator=args.estimator, progress=not args.no_progress, plots=args.plots)
    write_samples(df, Path(args.out))
    print(f"{len(df)} BRDF samples written to {args.out}")
    return 0
