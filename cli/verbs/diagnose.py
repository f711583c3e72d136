"""Find what the model gets wrong in a capture, name the cause and measure the gain (issue 7).

Fits the forward model to the capture (geometry from the calibrations, the
material from a Ward fit of this capture or --fit, the sensor from the raws),
then fits every named cause of the catalogue (stray_light, vignetting,
sample_rotation_offset, fresnel, led_emission, led_position_error,
sample_radius_error and the material models - ggx_lobe, beckmann_lobe,
grazing_lobe, flexible_material - in BRDF space; black_level_offset,
sensor_nonlinearity, channel_response, shutter_error, led_drift in frame space;
hot_pixels in pixel space) on training folds and scores it on held-out folds split by LED, by
pixel-row halves (per-LED parameters) or by exposure. Residuals are divided by a
calibrated error model (HDR noise plus a model-error term fitted on the training
folds). Sensor-level causes are named first (light and geometry cannot bend the
raw exposure series); a BRDF-space instrument cause must also beat a flexible
material model on held-out LEDs. The verdict is "unexplained" when structured
residual remains that no cause explains (also when it remains in image or cylinder
position after the named instrument cause). A row that misses a colour channel
(out of the capture's dynamic range) keeps its other channels; the missing one is
predicted by that channel's base model (report.json meta.missing_channels).
The verdict is the first of the eligible causes ranked sensor-level first, then by
held-out gain (report.json "ranking"). With --reference-brdf, every sample is first
renormalised with the reference's own BRDF at its angles (a calibration step, applied
and reported in meta.reference_calibration, never a verdict).
Writes REPORT_DIR/report.json ({"base_error", "calibration", "verdict", "ranking",
"causes": [... each with its "kind"], "unexplained": [...]}, causes sorted by
gain), report.md and the residual plots.

Each finished stage (every LED of the sample and reference measurements, the
material fit, the BRDF-space causes, the frame-space causes) is kept in the work
folder REPORT_DIR.partial/ with the sha256 of every input (both manifests, the
rig, camera, lamps, --fit and --reference-brdf files), the options and the
glossrig version. An interrupted run continues with the same command plus
--resume: stages whose recorded inputs match are reused and the report equals an
uninterrupted run's (meta.time_s apart). Without --resume an earlier work folder
is discarded. The work folder is removed once the report is written.

Progress: every stage says on stderr when it is done, with the elapsed wall and
CPU time (``glossrig diagnose: ...``); where no progress bar is drawn (stderr not a
terminal) each measured LED of the sample and the reference gets its own line.
--no-progress (or -q) silences them.

example:
  glossrig diagnose cap_sample --reference cap_ref --camera camera.json \\
      --lamps lamps.json --out diag/
"""
from __future__ import annotations

import logging

from glossrig.cli.outputs import add_force_option, prepare_output

_log = logging.getLogger(__name__)

HELP = "diagnose a capture: residuals, named causes, held-out gain"


def add_arguments(p) -> None:
    p.add_argument("sample", help="sample capture folder")
    p.add_argument("--reference", required=True, help="reference (diffuse) capture folder")
    p.add_argument("--camera", required=True, help="camera calibration (glossrig calibrate camera)")
    p.add_argument("--lamps", required=True, help="lamp positions (glossrig calibrate lamps)")
    p.add_argument("--fit", default=None, help="a material fit from another capture (else fitted here)")
    p.add_argument("--albedo", type=float, default=0.8, help="reference albedo")
    p.add_argument("--reference-brdf", default=None,
                   help="the reference's measured BRDF (RGL .bsdf): renormalise every sample with it before the "
                        "causes are tested (a calibration step, reported in report.json meta.reference_calibration)")
    p.add_argument("--out", required=True, help="report folder")
    add_force_option(p, "the files in a non-empty --out folder")
    p.add_argument("--resume", action="store_true",
                   help="continue an interrupted run: reuse the stages finished in REPORT_DIR.partial/ when "
                        "their recorded inputs match")
    p.add_argument("--no-progress", action="store_true")


def logged_store(store_cls, say, elapsed, units: dict[str, list[tuple[float, int]]]):
    """A subclass of the work store ``store_cls`` that says each measured (LED, rotation) unit as it
    is saved: ``say`` gets "measured sample LED 5 at rotation 0 (3 of 8) (41 s, CPU 6 s)".
    ``units``: each capture's (rotation, LED) units (``{"sample": [...], "reference": [...]}``,
    :func:`glossrig.core.extraction.extract.capture_units`), known by the names extract saves
    them under (:func:`glossrig.core.extraction.extract.unit_name`); ``elapsed`` the time text
    (:class:`glossrig.core.progress.Elapsed`). Progress lines for a run whose stderr is not a
    terminal, where no bar is drawn."""
    from glossrig.core.extraction.extract import unit_name

    named = {unit_name(f"{kind}-", rot, led): (kind, rot, led) for kind, us in units.items() for rot, led in us}

    class Logged(store_cls):
        def __init__(self, *a, **k):
            super().__init__(*a, **k)
            self.done: dict[str, int] = {}

        def save(self, name, value):
            super().save(name, value)
            if name in named:
                kind, rot, led = named[name]
                k = self.done[kind] = self.done.get(kind, 0) + 1
                say(f"measured {kind} LED {led} at rotation {rot:g} ({k} of {len(units[kind])}) ({elapsed})")
    return Logged


def run(args) -> int:
    from pathlib import Path

    from glossrig.core.capture import load_manifest
    from glossrig.core.checkpoint import WorkStore, work_folder_for
    from glossrig.core.extraction.extract import capture_units
    from glossrig.core.progress import Elapsed, progress_enabled
    from glossrig.core.diagnose import diagnose
    from glossrig.core.extraction.extract import measurement_fingerprint
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps

    prepare_output(args.out, args.force, kind="folder", resume=getattr(args, "resume", False))
    ref = None
    if args.reference_brdf:
        from glossrig.twin.measured_brdf import MeasuredBRDF

        ref = MeasuredBRDF(args.reference_brdf).table
    # a missing --fit file is left to diagnose's own message; it is hashed only when present
    extra = {"fit": args.fit if args.fit and Path(args.fit).is_file() else None,
             "reference_brdf": args.reference_brdf}
    fp = measurement_fingerprint(args.sample, args.reference, load_camera(args.camera), load_lamps(args.lamps),
                                 files=extra, estimator="ml", albedo=args.albedo, fit_given=bool(args.fit))
    say = (lambda *a: None) if args.no_progress else _log.info
    elapsed = Elapsed()
    store_cls = WorkStore
    if not args.no_progress and not progress_enabled():
        # no bar on a pipe or a log file: one line per measured LED instead of minutes of silence
        # the reference is measured in the sample's units only (extract.measure_pair)
        pair = capture_units(load_manifest(args.sample))
        units = {"sample": pair, "reference": pair}
        say(f"measuring the sample ({len(units['sample'])} LED x rotation units) and the reference "
            f"({len(units['reference'])})")
        store_cls = logged_store(WorkStore, say, elapsed, units)
    store = store_cls(work_folder_for(args.out), fp, resume=getattr(args, "resume", False), log=say)
    rep = diagnose(args.sample, args.reference, args.camera, args.lamps, args.out, fit=args.fit,
                   albedo=args.albedo, progress=not args.no_progress, log=say, reference_brdf=ref, store=store)
    store.remove()
    print(f"verdict: {rep['verdict']}")
    for c in rep["causes"][:5]:
        print(f"  {c['name']:24s} {c['space']:7s} gain {c['gain']:+.2%}  significant={c['significant']}")
    print(f"report written to {args.out}")
    return 0
