"""Find what the model gets wrong in a capture, name the cause and measure the gain (issue 7).

Fits the forward model to the capture (geometry from the calibrations, the
material from a Ward fit of this capture or --fit, the sensor from the raws),
then fits every named cause of the catalogue (stray_light, vignetting,
sample_rotation_offset, fresnel, led_emission, led_position_error,
sample_radius_error and the material/reference models in BRDF space;
black_level_offset, sensor_nonlinearity, led_drift in frame space; hot_pixels in
pixel space) on training folds and scores it on held-out folds split by LED, by
pixel-row halves (per-LED parameters) or by exposure. Sensor-level causes are
named first (light and geometry cannot bend the raw exposure series).
Writes REPORT_DIR/report.json ({"base_error", "verdict", "causes": [...]} sorted
by gain), report.md and the residual plots.

example:
  glossrig diagnose cap_sample --reference cap_ref --camera camera.json \\
      --lamps lamps.json --out diag/
"""
from __future__ import annotations

HELP = "diagnose a capture: residuals, named causes, held-out gain"


def add_arguments(p) -> None:
    p.add_argument("sample", help="sample capture folder")
    p.add_argument("--reference", required=True, help="reference (diffuse) capture folder")
    p.add_argument("--camera", required=True, help="camera calibration (glossrig calibrate camera)")
    p.add_argument("--lamps", required=True, help="lamp positions (glossrig calibrate lamps)")
    p.add_argument("--fit", default=None, help="a material fit from another capture (else fitted here)")
    p.add_argument("--albedo", type=float, default=0.8, help="reference albedo")
    p.add_argument("--reference-brdf", default=None,
                   help="the reference's measured BRDF (RGL .bsdf): tests the non-Lambertian reference cause")
    p.add_argument("--out", required=True, help="report folder")
    p.add_argument("--no-progress", action="store_true")


def run(args) -> int:
    from glossrig.core.diagnose import diagnose

    ref = None
    if args.reference_brdf:
        from glossrig.twin.measured_brdf import MeasuredBRDF

        ref = MeasuredBRDF(args.reference_brdf).table
    rep = diagnose(args.sample, args.reference, args.camera, args.lamps, args.out, fit=args.fit,
                   albedo=args.albedo, progress=not args.no_progress,
                   log=(lambda *a: None) if args.no_progress else print, reference_brdf=ref)
    print(f"verdict: {rep['verdict']}")
    for c in rep["causes"][:5]:
        print(f"  {c['name']:24s} {c['space']:7s} gain {c['gain']:+.2%}  significant={c['significant']}")
    print(f"report written to {args.out}")
    return 0
