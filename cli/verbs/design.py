"""Rig design from geometry alone: BRDF-space coverage (thesis 7.1.3) and LED /
rotation optimisation for coverage and expected Ward-parameter error (thesis 9.1).

sub-verbs:
  coverage   the rig's isotropic and anisotropic coverage under every binning
             convention, beside the thesis's printed 0.98 % and 0.1 %, with plots
             (theta_in/theta_out per LED as thesis fig. 7.2, anisotropic
             coverage by rotation, coverage per LED)
  optimise   sweep LED mounts and sample rotations (Dask: a local cluster by
             default, --scheduler ADDRESS for an existing one, --workers 0 for
             one process) and write the best design as a new rig file
  errors     expected extended-Ward parameter uncertainty of a rig's design for
             target materials: the combined budget (noise, model, calibration,
             footprint; glossrig.core.design.error_budget) as
             "expected_uncertainty", and the noise-only Fisher bound
             (glossrig.core.design.fisher) as "expected_errors"

examples:
  glossrig design coverage --rig scenes/thesis_rig.toml --out validation/design/coverage
  glossrig design optimise --rig scenes/thesis_rig.toml --leds 16 \\
      --materials brushed_original,sanded_original,base_2 --out scenes/optimised_rig.toml \\
      --report validation/design/optimise
"""
from __future__ import annotations

import json
import logging
import math
import sys
from pathlib import Path

from glossrig.cli.outputs import add_force_option, prepare_output
from glossrig.cli.verbs import SubVerb, _design_exposures
from glossrig.core.errors import InputError

_logger = logging.getLogger(__name__)

HELP = "rig design: BRDF-space coverage and LED/rotation optimisation (thesis 7.1.3, 9.1)"


def _log(quiet: bool):
    """Progress messages through the ``glossrig`` logger (``-q`` silences them)."""
    if quiet:
        return lambda msg: None
    return _logger.info


def _floats(text: str, what: str) -> list[float]:
    try:
        vals = [float(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise InputError(f"{what}: expected comma-separated numbers, got {text!r}") from None
    if not vals or not all(math.isfinite(v) for v in vals):
        raise InputError(f"{what}: expected finite numbers, got {text!r}")
    return vals


def _out_dir(path: str, force: bool = False) -> Path:
    """Check (glossrig.cli.outputs: refused if not empty unless ``force``) and create an output folder."""
    out = Path(path)
    if out.exists() and not out.is_dir():
        raise InputError("output exists and is not a folder", path=out)
    if not out.parent.is_dir():
        raise InputError("parent folder of the output does not exist", path=out)
    prepare_output(out, force, kind="folder")
    out.mkdir(exist_ok=True)
    return out


def _command() -> str | None:
    """The command line, for the reports (``None`` when not run as ``glossrig design``)."""
    return " ".join(["glossrig", "design"] + sys.argv[2:]) if sys.argv[1:2] == ["design"] else None


# ----------------------------------------------------------------------------
# coverage
# ----------------------------------------------------------------------------

def add_coverage_arguments(p) -> None:
    p.add_argument("--rig", required=True, help="rig file (scenes/*.toml)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for coverage.json, coverage.md, conventions.csv and plots")
    p.add_argument("--scales", default="1.0,0.5,0.25",
                   help="pixel densities (image scales) to tabulate; the first is the headline (default 1.0,0.5,0.25)")
    p.add_argument("--camera-distances", default=None,
                   help="also tabulate these camera distances (mm), at the last of --scales, e.g. 450,550")
    p.add_argument("--leds", default=None,
                   help="LEDs of the headline figure (default: 'middle' if the rig has a middle row of 8 as the "
                        "thesis measured, else all)")
    add_force_option(p, "the files in a non-empty --out folder")


def run_coverage(args) -> int:
    from glossrig.core.design.coverage_report import coverage_study, write_coverage_report
    from glossrig.core.rig import load_rig

    say = _log(args.quiet)
    prepare_output(args.out, args.force, kind="folder")
    rig = load_rig(args.rig)
    out = _out_dir(args.out, args.force)
    scales = _floats(args.scales, "--scales")
    dists = _floats(args.camera_distances, "--camera-distances") if args.camera_distances else []
    study = coverage_study(rig, scales, dists, leds=args.leds, log=None if args.quiet else say)
    summary = write_coverage_report(study, out, command=_command())
    head, best = summary["headline"], summary["best_match"]
    say(f"{rig.name}: isotropic {head['isotropic_pct']:.3f} %, anisotropic {head['anisotropic_pct']:.4f} % "
        f"({head['convention']}, scale {scales[0]:g}); printed 0.98 % and 0.1 %")
    say(f"best joint match: {best['iso_pct']:.3f} % / {best['aniso_pct']:.4f} % "
        f"(off by a factor {10 ** best['match']:.2f} at worst); wrote {out}")
    return 0


# ----------------------------------------------------------------------------
# optimise
# ----------------------------------------------------------------------------

DEFAULT_MATERIALS = "brushed_original,sanded_original,base_2"


def add_optimise_arguments(p) -> None:
    p.add_argument("--rig", required=True, help="rig to improve (also the reference design and the file template)")
    p.add_argument("--leds", type=int, required=True, help="number of LEDs of the design (at most 16 relay channels)")
    p.add_argument("--materials", default=DEFAULT_MATERIALS,
                   help=f"target extended-Ward materials (names in scenes/materials or ward:... specs, lobe_rotation "
                        f"in radians or with a unit: 140deg), default {DEFAULT_MATERIALS}")
    p.add_argument("--out", required=True, help="new rig file to write (scenes/*.toml)")
    p.add_argument("--report", metavar="DIR", default=None, help="also write design.json and plots here")
    p.add_argument("--rotations", type=int, default=4, help="number of sample rotations (default 4, as the thesis)")
    p.add_argument("--scheduler", default=None, metavar="ADDRESS", help="existing Dask scheduler (tcp://host:8786)")
    p.add_argument("--workers", type=int, default=2,
                   help="worker processes of the local Dask cluster (default 2); 0 = run in this one process")
    p.add_argument("--angle-step", type=float, default=10.0, help="candidate angle grid step, degrees (default 10)")
    p.add_argument("--heights", default="-40,-20,0,20,40,80,120", help="candidate heights, mm")
    p.add_argument("--distances", default="150,250,350", help="candidate distances from the axis, mm")
    p.add_argument("--rotation-step", type=int, default=15, help="candidate sample-rotation step, whole degrees (default 15)")
    p.add_argument("--lambda", dest="lam", type=float, default=1.0,
                   help="weight of the expected-error term against the coverage term (default 1)")
    p.add_argument("--iso-weight", type=float, default=1.0,
                   help="weight of the isotropic-coverage term (default 1; 0 = anisotropic coverage and errors only)")
    p.add_argument("--scale", type=float, default=0.25, help="image scale of the sweep (default 0.25)")
    p.add_argument("--noise", default="hdr", help="noise model: hdr[:LED_REL] (default) or relative[:REL]")
    p.add_argument("--final-scale", type=float, default=1.0,
                   help="image scale of the final coverage comparison (default 1.0, full resolution)")
    add_force_option(p, "an existing output rig file and the files in a non-empty --report folder")


def run_optimise(args) -> int:
    from glossrig.core.design import placement as D
    from glossrig.core.runners import make_runner
    from glossrig.core.design.optimise_report import ScoreSettings, optimised_rig_header, write_design_report
    from glossrig.core.rig import load_rig

    say = _log(args.quiet)
    out = prepare_output(args.out, args.force)
    if args.report:
        prepare_output(args.report, args.force, kind="folder")
    rig = load_rig(args.rig)
    report = _out_dir(args.report, args.force) if args.report else None
    if args.rotation_step < 1 or 360 % args.rotation_step:
        raise InputError(f"--rotation-step must divide 360, got {args.rotation_step}")
    if args.workers < 0:
        raise InputError(f"--workers must be >= 0, got {args.workers}")
    materials = D.parse_materials(args.materials)
    space = D.SearchSpace(angle_step_deg=args.angle_step, heights_mm=tuple(_floats(args.heights, "--heights")),
                          distances_mm=tuple(_floats(args.distances, "--distances")),
                          rotations_deg=tuple(range(-180, 180, args.rotation_step)))
    limits = D.MountingLimits()
    runner = make_runner(args.scheduler, args.workers)
    say(f"sweeping on {runner.name}")
    try:
        res = D.optimise(rig, args.leds, materials, runner, space=space, limits=limits, n_rotations=args.rotations,
                         lam=args.lam, iso_weight=args.iso_weight, coverage_scale=args.scale, fisher_scale=args.scale,
                         noise=args.noise, progress=not args.quiet, log=say)
    finally:
        runner.close()
    problems = D.design_problems(rig, res.positions, limits)
    if problems:
        raise InputError("the optimised design breaks the mounting limits: " + "; ".join(problems))
    D.write_rig_toml(rig.path, res.positions, res.rotations, out,
                     header=optimised_rig_header(args.leds, args.rotations, args.materials, rig.path),
                     name="optimised", description=f"Thesis rig with {args.leds} LEDs placed by glossrig design optimise")
    say(f"wrote {out}: score {res.score:+.4f} (thesis 0), coverage x{res.coverage / res.reference['anisotropic_coverage_design_scale']:.2f}")
    if report is not None:
        settings = ScoreSettings(lam=args.lam, iso_weight=args.iso_weight, scale=args.scale, noise=args.noise)
        write_design_report(rig, load_rig(out), res, materials, report, settings, args.final_scale,
                            command=_command(), log=say)
    return 0


# ----------------------------------------------------------------------------
# errors
# ----------------------------------------------------------------------------

def add_errors_arguments(p) -> None:
    p.add_argument("--rig", required=True, help="rig file")
    p.add_argument("--materials", default=DEFAULT_MATERIALS,
                   help=f"extended-Ward materials (names or ward:... specs, lobe_rotation in radians or with a unit: "
                        f"140deg; default {DEFAULT_MATERIALS})")
    p.add_argument("--leds", default="all", help="LEDs used: all, middle, a row or ids (default all)")
    p.add_argument("--rotations", default=None, help="sample rotations, degrees (default: the rig's)")
    p.add_argument("--scale", type=float, default=0.25, help="image scale the pixels are counted at (default 0.25)")
    p.add_argument("--noise", default="hdr", help="hdr[:LED_REL] (default) or relative[:REL]")
    p.add_argument("--gain-noise", type=float, default=0.0,
                   help="residual LED gain per (LED, rotation) sequence after neighbour correction and patch "
                        "normalisation, relative standard deviation, a nuisance parameter common to the "
                        "sequence's pixels (default 0: none; use with --noise hdr:0)")
    p.add_argument("--model-gain", type=float, default=None, metavar="REL",
                   help="budget: residual relative gain of one LED x rotation image (default: "
                        "glossrig.core.design.error_budget.GAIN_REL, 0.005)")
    p.add_argument("--lamp-std", type=float, default=None, metavar="MM",
                   help="budget: lamp position standard uncertainty per axis, mm, independent of the camera (default: "
                        "glossrig.core.calibration.lamps.LAMP_STD_MM without --camera; 0 with --camera, whose draws "
                        "solve the lamps again as `calibrate lamps` would)")
    p.add_argument("--pose-rot", type=float, default=None, metavar="DEG",
                   help="budget: sample pose rotation uncertainty per axis, degrees (default 0.05 x 0.25 / --scale; "
                        "with --camera each marker's measured pose-step error per axis, "
                        "glossrig.core.design.error_budget.HOLDER_POSE_NOISE_ROT_DEG, the figure given for every axis)")
    p.add_argument("--pose-t", type=float, default=None, metavar="MM",
                   help="budget: sample pose translation uncertainty per axis, mm (default 0.15 x 0.25 / --scale; "
                        "with --camera as --pose-rot)")
    p.add_argument("--led-aperture", type=float, default=None, metavar="RAD",
                   help="budget: the LEDs' angular diameter seen from the sample (default 0.0025; 0 for points)")
    p.add_argument("--camera", default=None, metavar="CAMERA_JSON",
                   help="budget: a camera calibration (glossrig calibrate camera) at the --scale image size: its "
                        "intrinsics are drawn from its views as glossrig fit draws them, and the pose figures "
                        "default to the poses' own noise (0.03 deg, 0.02 mm x 0.25 / --scale); without it the pose "
                        "figures carry the intrinsics")
    p.add_argument("--draws", type=int, default=None, metavar="N",
                   help="budget with --camera: a fixed number of calibration draws (default: adaptive Monte Carlo, "
                        "GUM-S1 7.9: 32 draws, doubled up to 256 until each combined figure is known to 10 %% of "
                        "itself; the output records the draws and their Monte Carlo uncertainty)")
    p.add_argument("--out", default=None, help="JSON file to write (default: print)")
    add_force_option(p, "an existing --out file")


def _nonnegative(v, name):
    if v is not None and not (math.isfinite(v) and v >= 0):
        raise InputError(f"{name} must be a number >= 0, got {v!r}")
    return v


def _camera_views(path: str, size: tuple[int, int]):
    """The board views of a camera calibration (for the budget's intrinsics draws); its image
    must be the design's (``size``)."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.fitting.calibration_uncertainty import CameraViews

    cam = load_camera(path)
    if tuple(cam.image_size) != tuple(size):
        raise InputError(f"--camera: calibrated at {cam.image_size[0]}x{cam.image_size[1]} px, the design's image at "
                         f"--scale is {size[0]}x{size[1]} px", path=path)
    views = CameraViews.from_camera_doc(cam.meta)
    if views is None:
        raise InputError("--camera: the file lacks the board views (write it with glossrig calibrate camera)",
                         path=path)
    return views


def run_errors(args) -> int:
    from glossrig.core.design import placement as D
    from glossrig.core.rig import load_rig

    if args.out:
        prepare_output(args.out, args.force)
    rig = load_rig(args.rig)
    materials = D.parse_materials(args.materials)
    leds = rig.select_leds(args.leds)
    rots = _floats(args.rotations, "--rotations") if args.rotations else list(rig.sample_rotations)
    from glossrig.core.design import error_budget as EB

    for v, name in ((args.model_gain, "--model-gain"), (args.lamp_std, "--lamp-std"), (args.pose_rot, "--pose-rot"),
                    (args.pose_t, "--pose-t"), (args.led_aperture, "--led-aperture")):
        _nonnegative(v, name)
    opt = {k: v for k, v in (("gain_rel", args.model_gain), ("lamp_std_mm", args.lamp_std),
                             ("pose_rot_deg", args.pose_rot), ("pose_t_mm", args.pose_t),
                             ("led_aperture", args.led_aperture)) if v is not None}
    if args.draws is not None and args.draws < 2:
        raise InputError(f"--draws must be an integer >= 2, got {args.draws}")
    if args.draws is not None and not args.camera:
        raise InputError("--draws needs --camera (without it no calibration draws are made)")
    if args.camera:
        opt["camera_views"] = _camera_views(args.camera, tuple(rig.camera.size(args.scale)))
        opt["intrinsics_draws"] = args.draws
    # one walk over the design's pixels gives both figures
    budget, errs = EB.budget_and_bound(rig, materials, rotations=rots, led_ids=leds, scale=args.scale,
                                       noise=args.noise, bound_gain_rel=args.gain_noise, **opt)
    doc = {"rig": str(rig.path), "leds": leds, "rotations_deg": rots, "scale": args.scale, "noise": args.noise,
           "gain_noise": args.gain_noise,
           "expected_uncertainty": budget,
           "expected_uncertainty_kind": "combined standard uncertainty (noise, model, calibration, footprint; "
                                        "glossrig.core.design.error_budget, its error model under 'stated')",
           "method": "Fisher information (Cramer-Rao bound), glossrig.core.design.fisher",
           "stderr_kind": "noise-only (the --noise model and --gain-noise; excludes calibration and model error)",
           "expected_errors": {lb: e.to_json() for lb, e in errs.items()}}
    say = _log(args.quiet)
    if say:
        say("expected uncertainty (combined; the noise-only figure is expected_errors):\n" + EB.budget_text(budget))
    text = json.dumps(doc, indent=2) + "\n"
    if args.out:
        Path(args.out).write_text(text)
    else:
        sys.stdout.write(text)
    return 0


# ----------------------------------------------------------------------------
# sub-verbs (glossrig.cli.verbs): each one's help is also its --help description
# ----------------------------------------------------------------------------

def _subverb(name: str, help_: str, add, run_) -> SubVerb:
    return SubVerb(name, help_, add, run_, description=help_)


SUBVERBS = (
    _subverb("coverage", "BRDF-space coverage of a rig under every convention, with plots (thesis 7.1.3)",
             add_coverage_arguments, run_coverage),
    _subverb("optimise", "optimise LED mounts and sample rotations; write a new rig file (thesis 9.1)",
             add_optimise_arguments, run_optimise),
    _subverb("errors", "expected Ward-parameter uncertainty of a rig: the combined budget (noise, model, "
             "calibration, footprint) and the noise-only Fisher bound", add_errors_arguments, run_errors),
    SubVerb.from_module("exposures", _design_exposures, description=_design_exposures.HELP),
)
