"""Measure a material in one command: calibrate what captures are given for, extract the
BRDF samples, fit, export, render and write the report (issue 17).

  glossrig measure SAMPLE_DIR --reference REF_DIR
        (--camera camera.json | --checkerboard CHECKER_DIR)
        (--lamps lamps.json | --specular SPECULAR_DIR) --out DIR

Steps, each the core of the verb named (the capture folders are described in the
README's "Measuring"):
  camera    (with --checkerboard) intrinsics        -> DIR/camera.json    (glossrig calibrate camera)
  lamps     (with --specular) lamp positions        -> DIR/lamps.json     (glossrig calibrate lamps)
  extract   BRDF samples (thesis 4.3-4.4)           -> DIR/samples.parquet, DIR/plots/  (glossrig extract)
  fit       extended Ward (thesis 4.5), gloss units -> DIR/fit.json       (glossrig fit)
  exports   Mitsuba XML (project and stock plugins), BRDF Explorer .brdf, samples CSV
                                                    -> DIR/exports/
  renders   sphere and draped cloth of the fitted material in an environment map
            (Mitsuba 3, thesis figs. 6.2, 7.4)      -> DIR/renders/
  recovery  (twin captures only: the sample folder holds truth.json) calibrations and
            fit against the twin's truth            -> DIR/recovery.json
  report    HTML (self-contained) and Markdown      -> DIR/report.html, DIR/report.md

Every step records in DIR/.steps/STEP.json the sha256 of its inputs (a capture by its
manifest, which records every raw file's checksum; the upstream step's output among
them), its options and the glossrig version, and the digest of what it wrote. With
--resume a step is reused only when all of that matches, so a rerun with unchanged
inputs redoes nothing, and a changed input (another lamps.json, another reference)
redoes exactly the steps downstream of it; an interrupted extraction continues with the
LEDs it had finished. --force redoes every step. With neither, an existing non-empty
DIR is refused before any work.
"""
from __future__ import annotations

import argparse
import logging
from pathlib import Path

from glossrig.cli.outputs import add_force_option, prepare_output

_log = logging.getLogger(__name__)

HELP = "calibrate, extract, fit, export, render and report a material in one command (resumable)"

#: the fit settings of a measurement (glossrig fit's defaults)
FIT_OPTIONS = {"weighting": "mirror", "clip": None, "clip_model": True, "use_weight_column": True, "n_starts": 4,
               "seed": 0, "calibration_draws": 24}


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("sample_dir", metavar="SAMPLE_DIR", help="capture folder of the material")
    p.add_argument("--reference", required=True, metavar="REF_DIR",
                   help="capture folder of the diffuse reference (every LED and rotation of the sample)")
    p.add_argument("--camera", default=None, metavar="camera.json", help="camera calibration (glossrig calibrate camera)")
    p.add_argument("--checkerboard", default=None, metavar="CHECKER_DIR",
                   help="capture folder of checkerboard views: calibrate the camera from it (instead of --camera)")
    p.add_argument("--lamps", default=None, metavar="lamps.json", help="lamp positions (glossrig calibrate lamps)")
    p.add_argument("--specular", default=None, metavar="SPECULAR_DIR",
                   help="capture folder of the specular sample: calibrate the lamps from it (instead of --lamps)")
    p.add_argument("--out", required=True, metavar="DIR", help="folder for the measurement's results")
    p.add_argument("--reference-albedo", type=float, default=0.8)
    p.add_argument("--estimator", choices=["ml", "thesis"], default="ml",
                   help="HDR estimator (see glossrig extract --help)")
    p.add_argument("--render-size", type=int, default=512, help="size of the material renders in pixels")
    p.add_argument("--render-spp", type=int, default=64, help="samples per pixel of the material renders")
    add_force_option(p, "the results in an existing --out: redo every step")
    p.add_argument("--resume", action="store_true",
                   help="continue in --out: reuse the finished steps whose recorded inputs match, complete an "
                        "interrupted one, redo the rest")
    p.add_argument("--no-progress", action="store_true")


def _one_of(a, b, na: str, nb: str) -> None:
    from glossrig.core.errors import InputError

    if (a is None) == (b is None):
        raise InputError(f"give one of {na} and {nb}" + (", not both" if a is not None else ""))


def _rig_of(folder):
    from glossrig.core.capture import load_manifest

    return load_manifest(folder).rig_path()


def run(args) -> int:
    from glossrig.cli.steps import StepRunner, output_digest
    from glossrig.core.capture import TRUTH
    from glossrig.core.checkpoint import capture_sha256
    from glossrig.core.errors import InputError
    from glossrig.core.fitting.export import read_fit_file
    from glossrig.core.progress import progress_enabled

    if args.force and args.resume:
        raise InputError("--resume continues the measurement in --out, --force redoes it: give one of them")
    _one_of(args.camera, args.checkerboard, "--camera camera.json", "--checkerboard CHECKER_DIR")
    _one_of(args.lamps, args.specular, "--lamps lamps.json", "--specular SPECULAR_DIR")
    if not args.reference_albedo > 0:
        raise InputError(f"--reference-albedo must be > 0, got {args.reference_albedo}")
    if args.render_size < 8 or args.render_spp < 1:
        raise InputError(f"--render-size must be >= 8 and --render-spp >= 1, got {args.render_size}, "
                         f"{args.render_spp}")
    out = prepare_output(args.out, args.force, kind="folder", resume=args.resume,
                         hint="use --resume to continue it (finished steps whose inputs match are reused) "
                              "or --force to redo every step")
    sample, ref = Path(args.sample_dir), Path(args.reference)
    checker = Path(args.checkerboard) if args.checkerboard else None
    spec = Path(args.specular) if args.specular else None
    for d in (sample, ref, checker, spec):          # every capture readable before any work
        if d is not None:
            capture_sha256(d)
    for f, what in ((args.camera, "camera calibration"), (args.lamps, "lamp calibration")):
        if f is not None and not Path(f).is_file():
            raise InputError(f"{what} file not found", path=f)
    out.mkdir(parents=True, exist_ok=True)
    prog = progress_enabled(not args.no_progress)
    truth = sample / TRUTH
    cam_path = out / "camera.json" if checker else Path(args.camera)
    lamps_path = out / "lamps.json" if spec else Path(args.lamps)
    samples_path, fit_path = out / "samples.parquet", out / "fit.json"
    exports_dir, renders_dir, recovery_path = out / "exports", out / "renders", out / "recovery.json"
    total = 5 + bool(checker) + bool(spec) + truth.is_file()
    steps = StepRunner(out, resume=args.resume, total=total, log=_log)
    log = _log.info

    if checker:
        steps.run("camera", cam_path, lambda resume: _calibrate_camera(checker, cam_path, prog),
                  files={"rig": _rig_of(checker)}, captures={"checker": checker})
    if spec:
        steps.run("lamps", lamps_path, lambda resume: _calibrate_lamps(spec, cam_path, lamps_path, prog),
                  files={"camera": cam_path, "rig": _rig_of(spec)}, captures={"specular": spec})
    steps.run("extract", [samples_path, out / "plots"],
              lambda resume: _extract(sample, ref, cam_path, lamps_path, samples_path, out / "plots", args, prog,
                                      resume),
              files={"camera": cam_path, "lamps": lamps_path, "sample_rig": _rig_of(sample),
                     "reference_rig": _rig_of(ref)},
              captures={"sample": sample, "reference": ref},
              options={"reference_albedo": args.reference_albedo, "estimator": args.estimator}, resumable=True)
    steps.run("fit", fit_path, lambda resume: _fit(samples_path, fit_path, log),
              files={"samples": samples_path}, options=FIT_OPTIONS)
    steps.run("exports", exports_dir, lambda resume: _exports(fit_path, samples_path, exports_dir),
              files={"fit": fit_path, "samples": samples_path})
    material = _material(fit_path)
    render_opts = {"material": material, "size": args.render_size, "spp": args.render_spp, "seed": 0}
    steps.run("renders", renders_dir, lambda resume: _renders(material, renders_dir, args), options=render_opts)
    recovery = None
    if truth.is_file():
        steps.run("recovery", recovery_path, lambda resume: _recovery(truth, cam_path, lamps_path, fit_path,
                                                                      recovery_path),
                  files={"truth": truth, "camera": cam_path, "lamps": lamps_path, "fit": fit_path})
        recovery = recovery_path
    report_files = {"fit": fit_path, "samples": samples_path, "camera": cam_path, "lamps": lamps_path,
                    "recovery": recovery}
    steps.run("report", [out / "report.html", out / "report.md", out / "report_figures"],
              lambda resume: _report(out, sample, ref, cam_path, lamps_path, fit_path, samples_path, exports_dir,
                                     renders_dir, recovery, log),
              files=report_files, captures={"sample": sample, "reference": ref},
              options={"exports": output_digest(exports_dir), "renders": output_digest(renders_dir)})

    fit = read_fit_file(fit_path)
    lum = fit.fit.fits.get("luminance")
    if lum is not None:
        print("luminance " + " ".join(f"{k}={getattr(lum.params, k):.4g}" for k in ("rho_d", "rho_s", "alpha_x",
                                                                                     "alpha_y", "lobe_rotation")))
    g = fit.gloss
    if g is not None:
        print("gloss     " + " ".join(f"{k}={g[k]:.3g}" if isinstance(g.get(k), (int, float)) else f"{k}=-"
                                      for k in ("gu20", "gu60", "gu85", "haze", "doi")))
    print(f"{len(steps.done)} step(s) run, {len(steps.reused)} reused; report: {out / 'report.html'}")
    return 0


# ------------------------------------------------------------------ the steps (each the core of a verb)

def _calibrate_camera(checker, cam_path, progress: bool) -> None:
    """glossrig calibrate camera CHECKER_DIR (the rig's board, at least MIN_VIEWS views)."""
    from glossrig.core.calibration.intrinsics import MIN_VIEWS, calibrate_intrinsics, save_camera

    cal, report = calibrate_intrinsics(checker, None, None, min_views=MIN_VIEWS, progress=progress)
    save_camera(cal, report, cam_path, overwrite=True)
    for s in report["skipped"]:
        _log.warning(f"checkerboard view skipped: {s['file']}: {s['reason']}")
    _log.info(f"camera: {len(report['views'])} views, reprojection RMS {cal.rms_px:.3f} px, fx {cal.fx:.2f} "
              f"fy {cal.fy:.2f} cx {cal.cx:.2f} cy {cal.cy:.2f} px")


def _calibrate_lamps(spec, cam_path, lamps_path, progress: bool) -> None:
    """glossrig calibrate lamps SPECULAR_DIR (thesis 4.3.4)."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import calibrate_lamps, save_lamps

    d = calibrate_lamps(spec, load_camera(cam_path), progress=progress)
    save_lamps(d, lamps_path)
    _log.info(f"lamps: {len(d['lamps_mm'])} LED positions")


def _extract(sample, ref, cam_path, lamps_path, samples_path, plots, args, progress: bool, resume: bool) -> None:
    """glossrig extract (thesis 4.3-4.4): finished LEDs kept in samples.parquet.partial/ for a resume."""
    from glossrig.core.checkpoint import WorkStore, work_folder_for
    from glossrig.core.extraction.extract import check_compatible, extract_samples, measurement_fingerprint
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps
    from glossrig.core.provenance import provenance
    from glossrig.core.samples import write_samples

    cam = load_camera(cam_path)
    lamps = load_lamps(lamps_path)
    check_compatible(sample, ref)
    fp = measurement_fingerprint(sample, ref, cam, lamps, estimator=args.estimator)
    store = WorkStore(work_folder_for(samples_path), fp, resume=resume)
    df = extract_samples(sample, ref, cam, lamps, albedo=args.reference_albedo, estimator=args.estimator,
                         progress=progress, plots=plots, store=store)
    prov = provenance({"sample": sample, "reference": ref, "sample_rig": _rig_of(sample), "reference_rig": _rig_of(ref),
                       "camera": cam_path, "lamps": lamps_path},
                      {"reference_albedo": args.reference_albedo, "estimator": args.estimator},
                      tool="glossrig measure (extract)")
    write_samples(df, samples_path, provenance=prov)
    store.remove()
    _log.info(f"extract: {len(df)} BRDF samples")


def _fit(samples_path, fit_path, log) -> None:
    """glossrig fit with its defaults (thesis 4.5): every channel, and the uncertainty budget with the
    calibration component drawn from this measurement's camera.json, lamps.json and sample capture
    (the ones the samples table's provenance names), as ``glossrig fit`` adds it
    (:func:`glossrig.cli.verbs.fit.add_calibration_component`)."""
    from glossrig.cli.verbs.fit import add_calibration_component
    from glossrig.core.fitting.export import write_fit_json
    from glossrig.core.fitting.fit import CHANNELS, fit_samples
    from glossrig.core.provenance import provenance
    from glossrig.core.samples import read_samples

    df = read_samples(samples_path)
    o = FIT_OPTIONS
    mfit = fit_samples(df, channels=CHANNELS, weighting=o["weighting"], clip=o["clip"], clip_model=o["clip_model"],
                       use_weight_column=o["use_weight_column"], source=str(samples_path), n_starts=o["n_starts"],
                       seed=o["seed"], log=log)
    add_calibration_component(df, mfit, log, draws=o["calibration_draws"], seed=o["seed"], weighting=o["weighting"],
                              clip=o["clip"], use_weight_column=o["use_weight_column"])
    prov = provenance({"samples": samples_path}, {"channels": list(CHANNELS), **o}, tool="glossrig measure (fit)")
    prov["inputs"]["samples"]["provenance"] = df.attrs.get("provenance")
    write_fit_json(mfit, fit_path, provenance=prov)


def _exports(fit_path, samples_path, exports_dir) -> None:
    from glossrig.core.fitting.material_export import write_exports
    from glossrig.core.samples import read_samples

    written = write_exports(fit_path, read_samples(samples_path), exports_dir)
    _log.info(f"exports: {', '.join(p.name for p in written)}")


def _material(fit_path) -> dict:
    """The fitted material as the twin's glossrig_ward dict (what the renders show)."""
    from glossrig.core.fitting.export import mitsuba_material, read_fit_json

    return mitsuba_material(read_fit_json(fit_path))


def _renders(material: dict, renders_dir, args) -> None:
    """Sphere and cloth of the fitted material (glossrig.twin.material_renders; Mitsuba lives in the twin)."""
    from glossrig.core.errors import InputError

    try:
        from glossrig.twin.material_renders import render_material_views
    except ImportError as e:
        _log.warning(f"renders skipped: the twin is not available ({e})")
        return
    try:
        written = render_material_views(material, renders_dir, size=args.render_size, spp=args.render_spp, seed=0)
    except InputError as e:
        _log.warning(f"renders skipped: {e}")
        return
    _log.info(f"renders: {', '.join(p.name for p in written.values())}")


def _recovery(truth, cam_path, lamps_path, fit_path, recovery_path) -> None:
    from glossrig.core.atomic import atomic_write_json
    from glossrig.core.report.recovery import recovery_table

    rec = recovery_table(truth, camera_json=cam_path, lamps_json=lamps_path, fit_json=fit_path)
    atomic_write_json(recovery_path, rec, allow_nan=False)


def _report(out, sample, ref, cam_path, lamps_path, fit_path, samples_path, exports_dir, renders_dir, recovery,
            log) -> None:
    from glossrig.core.report.document import write_report
    from glossrig.core.report.recovery import read_recovery

    renders = {k: renders_dir / f"render_{k}.png" for k in ("sphere", "cloth")}
    renders = {k: p for k, p in renders.items() if p.is_file()}
    exports = sorted(p for p in exports_dir.iterdir() if p.is_file()) if exports_dir.is_dir() else []
    write_report(out, fit_json=fit_path, samples=samples_path, sample_dir=sample, reference_dir=ref,
                 camera_json=cam_path, lamps_json=lamps_path, renders=renders,
                 recovery=read_recovery(recovery) if recovery else None, exports=exports, log=log)
