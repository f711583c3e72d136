"""Fit the extended Ward model (thesis 4.5, eq. 4.79-4.82) to a BRDF samples table.

Fits luminance (Rec. 709 Y = 0.2126 r + 0.7152 g + 0.0722 b) and each colour
channel by weighted least squares within the bounds of Table 4.2, starting
from a data-driven grid of lobes, and reports every channel in one canonical
form: alpha_x >= alpha_y, lobe_rotation in [0, pi) radians.

fit.json holds, under "luminance", "r", "g" and "b": rho_d, rho_s, alpha_x,
alpha_y, lobe_rotation, each with <name>_stderr (null when the data do not
determine it), the covariance, residual statistics and the fit settings; and
under "mitsuba" a material for the twin's glossrig_ward BSDF.

The model fitted is eq. 4.79 averaged over each sample's footprint (its Bayer
block's read kernel and pixel areas, mapped by the local Jacobian of the half
vector, which is taken from the table's neighbouring blocks; see
glossrig.core.fitting.footprint_model) wherever the table has u, v, led and
rotation; --no-footprint fits the point model. Each channel's "footprint" says
which.

The <name>_stderr are NOISE-ONLY: they count the per-pixel noise of the samples
and exclude the calibration and model error; each channel says so in
"stderr_kind". The measurement's uncertainty is each channel's "uncertainty":
per parameter the combined standard uncertainty, a 95 % interval and the
components noise, model (misfit, cluster-robust over LED x rotation blocks),
footprint (what the model leaves of the footprint, with the LED's aperture)
and calibration (Monte Carlo over draws of the camera - intrinsics and distortion
drawn together by re-running its calibration on corners moved by its own
reprojection RMS -, the poses, the lamp positions and the reference albedo, with
the files the samples table's provenance names or --camera/--lamps/--capture;
--calibration-draws 0 leaves it out and the budget says so; or given directly
with --calibration-uncertainty); see glossrig.core.fitting.uncertainty and
glossrig.core.fitting.calibration_uncertainty. The printed summary shows the
budget table after the noise-only standard errors.

fit.json's "provenance" records the samples file (path, resolved path, sha256)
with the table's own provenance (captures, calibrations, extract options), the
fit options, the glossrig version and the git commit of the source tree.

The thesis's fit of section 6.2 is `--clip --weighting none --clip-literal`;
without --clip-literal the model is clipped too (a censored fit, see
glossrig.core.fitting.fit).

examples:
  glossrig fit samples.parquet --out fit.json
  glossrig fit samples.parquet --out fit.json --plots plots/ --clip 1.0
"""
from __future__ import annotations

import logging
from pathlib import Path

from glossrig.cli.outputs import add_force_option, prepare_output
from glossrig.core.errors import InputError

_log = logging.getLogger(__name__)

HELP = "fit the extended Ward BRDF to a samples table (thesis 4.5)"


def add_arguments(p) -> None:
    p.add_argument("samples", help="samples table (Parquet, see glossrig.core.samples)")
    p.add_argument("--out", default=None, help="fit JSON to write (default: SAMPLES with suffix .fit.json)")
    p.add_argument("--plots", metavar="DIR", default=None,
                   help="write plots (lobe and rig slices, residuals, measured vs fitted) and a rendered preview sphere")
    p.add_argument("--mitsuba", metavar="PATH", default=None, help="also write the Mitsuba material dict alone")
    p.add_argument("--channels", default="luminance,r,g,b",
                   help="comma-separated channels among luminance,r,g,b (default: all)")
    p.add_argument("--weighting", choices=("mirror", "literal", "none"), default="mirror",
                   help="eq. 4.82 weight: 'mirror' (default; difference of in and out angles), "
                        "'literal' (Rusinkiewicz theta_d, phi_d columns) or 'none'")
    p.add_argument("--clip", nargs="?", type=float, const=1.0, default=None, metavar="LEVEL",
                   help="clip BRDF values at LEVEL (eq. 6.5; default level 1.0)")
    p.add_argument("--clip-literal", action="store_true",
                   help="with --clip: fit the unclipped model to clipped data, as the thesis does")
    p.add_argument("--ignore-weight-column", action="store_true", help="do not use the table's weight column")
    p.add_argument("--starts", type=int, default=4, help="grid starts refined per channel (default 4)")
    p.add_argument("--seed", type=int, default=0, help="seed of the subset choice (default 0)")
    p.add_argument("--no-footprint", action="store_true",
                   help="fit the point model instead of the footprint-averaged one (its effect then goes into the "
                        "uncertainty budget)")
    p.add_argument("--cfa", default="RGGB", help="Bayer pattern of the camera, for the footprint (default RGGB)")
    p.add_argument("--led-aperture", type=float, default=None, metavar="RAD",
                   help="angular diameter of the LEDs' emitting area seen from the sample, radians, for the budget's "
                        "footprint component (default: 0.75 mm at 300 mm, 0.0025; 0 for point LEDs such as the twin's)")
    p.add_argument("--calibration-uncertainty", default=None, metavar="JSON",
                   help="standard uncertainties the calibration gives the parameters: "
                        '{"luminance": {"alpha_x": 1e-4, ...}, "r": {...}} (default: the budget omits calibration)')
    p.add_argument("--camera", default=None, metavar="JSON",
                   help="camera calibration for the budget's calibration component (default: the one the samples "
                        "table's provenance records)")
    p.add_argument("--lamps", default=None, metavar="JSON",
                   help="lamp positions for the calibration component (default: from the table's provenance)")
    p.add_argument("--capture", default=None, metavar="DIR",
                   help="the sample capture whose calibration images give the poses (default: from the provenance)")
    p.add_argument("--calibration-draws", type=int, default=24, metavar="N",
                   help="Monte Carlo draws of the calibration component (default 24; 0: leave it out)")
    add_force_option(p, "an existing --out or --mitsuba file and a non-empty --plots folder")
    # -q/--quiet (no progress messages) is added to every verb by glossrig.cli.main


def _provenance(args, src: Path, channels: list[str], df) -> dict:
    """fit.json's provenance: the samples file, its own recorded provenance (the chain
    back to the captures; null for a table written without one) and every option that
    changes the fit."""
    from glossrig.core.provenance import provenance

    prov = provenance({"samples": src},
                      {"channels": channels, "weighting": args.weighting, "clip": args.clip,
                       "clip_literal": args.clip_literal, "ignore_weight_column": args.ignore_weight_column,
                       "starts": args.starts, "seed": args.seed, "footprint": not args.no_footprint,
                       "cfa": args.cfa, "led_aperture": args.led_aperture,
                       "calibration_uncertainty": args.calibration_uncertainty, "camera": args.camera,
                       "lamps": args.lamps, "capture": args.capture, "calibration_draws": args.calibration_draws},
                      tool="glossrig fit")
    prov["inputs"]["samples"]["provenance"] = df.attrs.get("provenance")
    return prov


def run(args) -> int:
    from glossrig.core.fitting.export import write_fit_json, write_mitsuba_material
    from glossrig.core.fitting.fit import CHANNELS, STDERR_KIND, fit_samples
    from glossrig.core.fitting.uncertainty import budget_table
    from glossrig.core.samples import read_samples

    log = _log.info
    channels = [c.strip() for c in args.channels.split(",") if c.strip()]
    bad = [c for c in channels if c not in CHANNELS]
    if bad or not channels:
        raise InputError(f"--channels: expected some of {', '.join(CHANNELS)}, got {args.channels!r}")
    if args.starts < 1:
        raise InputError(f"--starts must be >= 1, got {args.starts}")
    if args.clip is not None and not (args.clip > 0):
        raise InputError(f"--clip level must be > 0, got {args.clip}")
    src = Path(args.samples)
    out = Path(args.out) if args.out else src.with_suffix(".fit.json")
    prepare_output(out, args.force)
    if args.mitsuba:
        prepare_output(args.mitsuba, args.force)
    if args.plots:
        prepare_output(args.plots, args.force, kind="folder")
    if args.led_aperture is not None and not (args.led_aperture >= 0):
        raise InputError(f"--led-aperture must be >= 0 radians, got {args.led_aperture}")
    calibration = _calibration_uncertainty(args.calibration_uncertainty)
    df = read_samples(src)
    if log:
        log(f"{src}: {len(df)} samples")
    mfit = fit_samples(df, channels=channels, weighting=args.weighting, clip=args.clip,
                       clip_model=not args.clip_literal, use_weight_column=not args.ignore_weight_column,
                       source=str(src), n_starts=args.starts, seed=args.seed, log=log,
                       footprint=False if args.no_footprint else None, cfa=args.cfa, led_aperture=args.led_aperture,
                       calibration=calibration)
    if calibration is None:
        add_calibration_component(df, mfit, log, draws=args.calibration_draws, seed=args.seed,
                                  weighting=args.weighting, clip=args.clip,
                                  use_weight_column=not args.ignore_weight_column, camera=args.camera,
                                  lamps=args.lamps, capture=args.capture)
    write_fit_json(mfit, out, provenance=_provenance(args, src, channels, df))
    if log:
        log(f"wrote {out}")
    if args.mitsuba:
        write_mitsuba_material(mfit, args.mitsuba)
    if args.plots:
        from glossrig.core.fitting.export import mitsuba_material
        from glossrig.core.fitting.fit_plots import write_plots

        written = write_plots(df, mfit, args.plots)
        try:
            from glossrig.twin.material_renders import render_preview   # Mitsuba lives in the twin

            written.append(render_preview(mitsuba_material(mfit), Path(args.plots) / "preview_sphere.png"))
        except (ImportError, InputError) as e:
            _log.warning(f"preview sphere skipped: {e}")
        if log:
            log(f"wrote {len(written)} figures to {args.plots}")
    for c, f in mfit.fits.items():
        p = f.params
        print(f"{c:9s} rho_d={p.rho_d:.4g} rho_s={p.rho_s:.4g} alpha_x={p.alpha_x:.4g} alpha_y={p.alpha_y:.4g} "
              f"lobe_rotation={p.lobe_rotation:.4f} rad  rms_rel={f.residuals['rms_relative']:.3g}")
        print(f"{'':9s} noise-only stderr: " + " ".join(
            f"{k}={f.stderr[k]:.2g}" for k in ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")))
        if not f.converged:
            _log.warning(f"{c}: the solver stopped at its evaluation limit before converging "
                         "(see 'converged' and the standard errors in the fit JSON)")
        if f.at_bound:
            _log.warning(f"{c}: {', '.join(f.at_bound)} at a bound of Table 4.2; "
                         "the standard errors assume an interior optimum")
    print(f"stderr = {STDERR_KIND}: not the measurement's uncertainty")
    print()
    print("uncertainty budget (GUM):")
    print(budget_table(mfit.fits))
    return 0


def _calibration_uncertainty(path) -> dict | None:
    """--calibration-uncertainty: ``{channel: {param: u}}`` (u >= 0, or ``{"u": u, "dof": nu}``)."""
    from glossrig.core.fitting.fit import CHANNELS, PARAM_NAMES
    from glossrig.core.toml_input import read_json

    if path is None:
        return None
    doc = read_json(Path(path), "calibration uncertainty file")
    if not isinstance(doc, dict) or not set(doc) <= set(CHANNELS):
        raise InputError(f"expected an object with some of the channels {', '.join(CHANNELS)}", path=path)
    for ch, params in doc.items():
        if not isinstance(params, dict) or not set(params) <= set(PARAM_NAMES):
            raise InputError(f"{ch}: expected an object with some of {', '.join(PARAM_NAMES)}", path=path)
        for k, v in params.items():
            u = v.get("u") if isinstance(v, dict) else v
            if isinstance(u, bool) or not isinstance(u, (int, float)) or not u >= 0:
                raise InputError(f"{ch}.{k}: a standard uncertainty must be a number >= 0, got {v!r}", path=path)
    return doc


def _calibration_files(df, camera, lamps, capture) -> tuple[dict | None, str]:
    """camera.json, lamps.json and the sample capture for the calibration component: the
    options, else the paths the samples table's provenance records; (None, why) if any
    is missing."""
    prov = (df.attrs.get("provenance") or {}).get("inputs") or {}

    def pick(opt, key):
        if opt:
            return opt
        e = prov.get(key) or {}
        return e.get("resolved") or e.get("path")

    files = {"camera": pick(camera, "camera"), "lamps": pick(lamps, "lamps"), "capture": pick(capture, "sample")}
    lacking = [k for k, v in files.items() if not v or not Path(v).exists()]
    if lacking:
        return None, (f"calibration not included: {', '.join(lacking)} not found (give --camera, --lamps, --capture "
                      "or a samples table whose provenance names them)")
    return files, ""


def add_calibration_component(df, mfit, log, *, draws: int, seed: int, weighting: str, clip, use_weight_column: bool,
                              camera=None, lamps=None, capture=None) -> None:
    """Each channel's budget gets the calibration component (shared with ``glossrig measure``'s fit step)
    (:mod:`glossrig.core.fitting.calibration_uncertainty`: ``draws`` Monte Carlo draws refitted with the
    fit's ``weighting``, ``clip`` and weight column) where the calibration files - ``camera``, ``lamps``,
    ``capture``, else those the samples table's provenance names - can be found; else its ``omitted``
    says why."""
    from glossrig.core.fitting.calibration_uncertainty import (add_calibration, calibration_component, load_inputs,
                                                              recorded_poses)

    if draws == 0:
        files, why = None, "calibration not included (--calibration-draws 0)"
    elif draws < 2:
        raise InputError(f"--calibration-draws must be 0 or >= 2, got {draws}")
    else:
        files, why = _calibration_files(df, camera, lamps, capture)
    if files is None:
        for f in mfit.fits.values():
            if f.uncertainty is not None:
                f.uncertainty = add_calibration(f.uncertainty, None, why)
        _log.warning(why)
        return
    rotations = sorted(df["rotation"].unique())
    solved, poses_from = recorded_poses(df.attrs.get("poses"), files["camera"], files["capture"], rotations)
    if log:
        log(f"calibration component: {draws} draws (poses of {files['capture']}: {poses_from})")
    cal = load_inputs(files["camera"], files["lamps"], files["capture"], rotations, solved=solved)
    if log:
        log(f"calibration component: lamps {cal.lamp_draws_note}")
    comp = calibration_component(df, {c: f.params for c, f in mfit.fits.items()}, cal,
                                 n_draws=draws, seed=seed, weighting=weighting, clip=clip,
                                 use_weight_column=use_weight_column,
                                 footprint=any((f.footprint or {}).get("model") == "footprint-averaged"
                                               for f in mfit.fits.values()))
    for c, f in mfit.fits.items():
        if f.uncertainty is not None:
            f.uncertainty = add_calibration(f.uncertainty, comp[c])
            f.uncertainty["budget"]["calibration"] = {**comp["_meta"], "poses": poses_from}
