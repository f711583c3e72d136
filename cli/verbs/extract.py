"""Extract BRDF samples from a capture (thesis 4.3-4.4).

Reads SAMPLE_DIR and REF_DIR (capture folders: capture.json + raw files; never
truth.json), the camera calibration (glossrig calibrate camera) and the lamp
positions (glossrig calibrate lamps), and writes the BRDF samples table
(Parquet; columns theta_in, phi_in, theta_out, phi_out, theta_h, phi_h,
theta_d, phi_d in radians in the tangent frame of thesis 4.3.5, r, g, b in
1/sr, weight, u, v, led, rotation in degrees; weight_r, weight_g, weight_b per channel).

A colour channel without a valid HDR value in a block (too dark at the longest
exposure, saturated at the shortest, in the sample or the reference) is NaN there;
the block keeps its other channels (glossrig.core.samples). Which channels ran out
of dynamic range, at which LED, rotation and angles, and the exposure that would
have fixed them, is logged (a warning per LED and channel from 5 % of its lit
blocks) and, with --plots, written to PLOTS/dynamic_range.json and
PLOTS/dynamic_range.png.

The reference is a diffuse sample captured on the same rig with the same LEDs
and rotations; it is treated as Lambertian with --reference-albedo (thesis 4.4:
white paper, 0.8).

Each LED of each capture is kept, once measured, in the work folder OUT.partial/
(with the sha256 of both manifests, the rig, the camera file, the lamp positions,
the options and the glossrig version). An interrupted run continues with the same
command plus --resume: the LEDs whose recorded inputs match are reused, the rest
are measured, and the table equals an uninterrupted run's. Without --resume an
earlier work folder is discarded. OUT.partial/ is removed once OUT is written.

With --follow the capture SAMPLE_DIR may still be being taken (glossrig capture or
glossrig simulate writing it; the reference must be complete): each LED of each
rotation is measured as soon as the manifest lists its calibration image and all its
planned sequence files, the rest when the capture is marked complete, so the table is
written moments after the last exposure and equals a plain extract of the finished
capture (glossrig.core.extraction.follow). Units are kept in OUT.follow/. If no new
image arrives for --idle-timeout seconds (an interrupted capture) it stops with exit
status 2: resume the capture and rerun with --follow --resume, which reuses them.

The table records its provenance in its Parquet schema metadata (key
glossrig.provenance; pyarrow.parquet.read_schema(OUT).metadata): the paths and
sha256 of both manifests (each lists every raw file's sha256), of the rig files,
camera.json and lamps.json, the options --reference-albedo and --estimator, the
glossrig version and the git commit of the source tree (null when installed).
"""
from __future__ import annotations

import argparse

from glossrig.cli.outputs import add_force_option, prepare_output
from glossrig.core.errors import InputError

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
    add_force_option(p, "an existing --out file and a non-empty --plots folder")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run: reuse the LEDs already measured in OUT.partial/ when their "
                        "recorded inputs match")
    p.add_argument("--follow", action="store_true",
                   help="SAMPLE_DIR is still being captured: measure each LED as soon as its files are recorded and "
                        "write the table when the capture completes")
    p.add_argument("--idle-timeout", type=float, default=None, metavar="S",
                   help="with --follow: stop (exit 2, resumable) when no new image has arrived for S seconds "
                        "(default 900)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="processes measuring LEDs at once (default: every usable core; 1: one process); the "
                        "table is the same for any number")
    p.add_argument("--no-progress", action="store_true")


def _provenance(args, sample, reference) -> dict:
    """What the table was made from (stored in its Parquet schema metadata): both
    captures (by their manifests, ``sample`` and ``reference``), the rig files they name,
    the camera and lamp calibrations, the options that change the values, the version and
    source revision."""
    from glossrig.core.provenance import provenance

    return provenance({"sample": args.sample_dir, "reference": args.reference,
                       "sample_rig": sample.rig_path(), "reference_rig": reference.rig_path(),
                       "camera": args.camera, "lamps": args.lamps},
                      {"reference_albedo": args.reference_albedo, "estimator": args.estimator},
                      tool="glossrig extract")


def run(args) -> int:
    from pathlib import Path

    from glossrig.core.capture import load_manifest
    from glossrig.core.checkpoint import WorkStore, work_folder_for
    from glossrig.core.extraction.extract import check_compatible, extract_samples, measurement_fingerprint
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps
    from glossrig.core.samples import write_samples

    resume = getattr(args, "resume", False)
    follow = getattr(args, "follow", False)
    idle = getattr(args, "idle_timeout", None)
    if idle is not None and not follow:
        raise InputError("--idle-timeout applies to --follow only")
    prepare_output(args.out, args.force, resume=resume)
    if args.plots:
        prepare_output(args.plots, args.force, kind="folder", resume=resume)
    cam = load_camera(args.camera)
    lamps = load_lamps(args.lamps)
    if follow:
        from glossrig.core.extraction.follow import IDLE_TIMEOUT_S, follow_extract

        df, stores, ms, mr = follow_extract(args.sample_dir, args.reference, cam, lamps, args.out,
                                            albedo=args.reference_albedo, estimator=args.estimator, resume=resume,
                                            idle_timeout_s=IDLE_TIMEOUT_S if idle is None else idle,
                                            progress=not args.no_progress, plots=args.plots,
                                            workers=getattr(args, "workers", None))   # ms, mr: as it read them
    else:
        ms, mr = load_manifest(args.sample_dir), load_manifest(args.reference)       # read once, passed on
        check_compatible(ms, mr)
        # the stored units are measurements: the albedo (applied after them) is not among their inputs
        fp = measurement_fingerprint(ms, mr, cam, lamps, estimator=args.estimator)
        stores = [WorkStore(work_folder_for(args.out), fp, resume=resume)]
        df = extract_samples(ms, mr, cam, lamps, albedo=args.reference_albedo,
                             estimator=args.estimator, progress=not args.no_progress, plots=args.plots,
                             store=stores[0], workers=getattr(args, "workers", None))
    write_samples(df, Path(args.out), provenance=_provenance(args, ms, mr))
    for store in stores:
        store.remove()
    print(f"{len(df)} BRDF samples written to {args.out}")
    return 0
