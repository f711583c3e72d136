"""Find what the model gets wrong in a measured capture and name the cause (issue 7).

:func:`diagnose` fits the forward model to the capture (geometry from the
calibrations, the material from a Ward fit, the sensor from the raws' own
statistics), computes residuals in BRDF space and in frame/pixel space, fits
each named cause of :mod:`.catalogue` and :mod:`.frames` on training folds,
scores it on held-out folds (split by LED or by exposure, never by random
pixels) and names the winner, or "none" when no cause beats the stated
threshold. The BRDF-space ``stray_light`` cause is judged by the frames' dark pixels
(:mod:`.stray_light`: refuted where they are darker than its veil, named through their
frame-space signature where they carry it); the BRDF-space ``vignetting`` and ``led_emission``
causes by the marker's white patch, the same surface in the sample and reference captures
(:mod:`.white_patch`); ``sample_radius_error`` by the sample's outline in its own frames
(:mod:`.silhouette`); ``led_position_error`` by the cylinder's white marker band in both captures
(:mod:`.marker_band`). Each witness measures its cause where no material acts and judges the
BRDF-space cause by one rule (:mod:`.witness`).
:mod:`.report` writes report.json and report.md. With the reference's own BRDF
the measured table is first renormalised with it - a calibration step that is applied and
reported (``meta.reference_calibration``), not a cause (issue 14, item 4).
"""
from __future__ import annotations

import contextlib

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.progress import Elapsed
from glossrig.core.fitting.export import FitFile, read_fit_file

from glossrig.core.diagnose.catalogue import BrdfModel, brdf_causes, model_of
from glossrig.core.workers import InWorker, one_blas_thread
from glossrig.core.diagnose.data import load_brdf
from glossrig.core.diagnose.fit_check import check_fit
from glossrig.core.diagnose.frames import FrameStage, frame_stage
from glossrig.core.diagnose.report import verdict, write_report
from glossrig.core.diagnose.residuals import brdf_structure
from glossrig.core.diagnose.stray_light import apply_frame_evidence, frame_evidence
from glossrig.core.rig import load_rig
from glossrig.core.diagnose.marker_band import apply_band_evidence, band_evidence, band_rates, bending_causes
from glossrig.core.diagnose.silhouette import apply_silhouette_evidence, limb_rates, silhouette_evidence
from glossrig.core.diagnose.witness import brdf_cause
from glossrig.core.diagnose.white_patch import (apply_emission_evidence, apply_patch_evidence, emission_evidence,
                                                patch_evidence, patch_points, patch_rates)
from glossrig.core.diagnose.unexplained import retested_cause, unexplained


def load_fit(path):
    """Luminance Ward parameters of a ``glossrig fit`` JSON (read by the one reader,
    :func:`glossrig.core.fitting.export.read_fit_file`; errors name the file)."""
    return luminance_params(read_fit_file(path))


def luminance_params(ff: FitFile):
    """The luminance Ward parameters of a read fit file; refuses one without that channel."""
    lum = ff.fit.fits.get("luminance")
    if lum is None:
        raise InputError("the fit has no luminance channel (luminance Ward parameters needed)", path=ff.path)
    return lum.params


def material_fit(table):
    """The luminance Ward parameters diagnose's base model takes from the capture itself (no ``--fit``, or
    a reference BRDF given): ``glossrig fit``'s fit of the measured table, as the point model every cause
    compares with (:class:`.catalogue.BrdfModel`: ward_from_angles at the block's angles; the footprint's
    effect is part of the calibrated model-error term) and without the uncertainty budget - only the
    parameters are used (the footprint fit and the GUM budget took most of diagnose's time)."""
    from glossrig.core.fitting.fit import fit_samples

    return fit_samples(table, channels=["luminance"], footprint=False, budget=False).fits["luminance"].params


def diagnose(sample_dir, reference_dir, camera, lamps, out, fit=None, albedo: float = 0.8,
             progress: bool = False, log=print, reference_brdf=None, reference_measured=None,
             plots: bool = True, store=None, reference_source: str | None = None) -> dict:
    """``reference_brdf``: callable(samples table) -> (n, 3) RGB BRDF of the reference at the
    rows' angles (e.g. :meth:`glossrig.twin.measured_brdf.MeasuredBRDF.table`). When it is
    given, renormalising with it is a calibration step, not a cause (issue 14, item 4): the
    measured table is renormalised first, ``f = f_meas f_ref pi / albedo`` per channel
    (thesis eq. 4.78 inverted, :func:`glossrig.core.diagnose.data.renormalise_table`), the base
    material is fitted to the renormalised data and every cause is tested on it; report.json's
    ``meta.reference_calibration`` records the step and its effect and report.md says it.
    Without it the data keeps the thesis normalisation and no reference cause is tested (the
    reference's angular shape cannot be told from the material's without its BRDF).
    ``reference_source``: where the reference BRDF came from (a file), for the record; taken
    from the callable's object (``MeasuredBRDF.path``) when not given.
    ``reference_measured``: the reference capture already measured
    (:func:`glossrig.core.extraction.extract.measure_capture`) with the same camera and lamps.

    ``fit``: a ``glossrig fit`` JSON from another capture of the material. It must predict this
    capture's material (:func:`glossrig.core.diagnose.fit_check.check_fit`: the sample its
    provenance names, else a median miss below its FIT_MISMATCH), and its lobe is then
    kept fixed (``material_fixed``, which makes a sample rotation offset identifiable). A fit is
    made on thesis-normalised data, so with a reference BRDF its lobe carries the reference's
    angular error: it is then only checked against the thesis-normalised data, the material is
    refitted to the renormalised data (the lobe comes from this capture, ``material_fixed``
    stays False) and ``meta.reference_calibration.fit`` says so.

    ``store``: a :class:`glossrig.core.checkpoint.WorkStore` fingerprinted with every input
    of this diagnosis; each finished stage is kept there and reused (every LED of the
    sample and reference measurements, the material fit, the BRDF-space causes, the
    frame-space causes with their residual structure), so an interrupted diagnosis
    resumes and writes the same report (its ``meta.time_s`` apart)."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps
    from glossrig.core.models.ward import ward_from_angles

    clock = Elapsed()
    took = clock.__str__          # wall and this process's CPU time since the start

    stage = store.get_or_compute if store is not None else (lambda name, compute: compute())
    # the fit file read once, first: a bad one stops diagnose before the measuring
    fit_file = read_fit_file(fit) if fit is not None else None
    if fit_file is not None:
        luminance_params(fit_file)
    cam = load_camera(camera)
    lp = load_lamps(lamps)
    if reference_brdf is not None and reference_source is None:
        src = getattr(getattr(reference_brdf, "__self__", None), "path", None)
        reference_source = str(src) if src is not None else getattr(reference_brdf, "__qualname__", "given")
    data = load_brdf(sample_dir, reference_dir, cam, lp, albedo=albedo, progress=progress,
                     reference=reference_measured, store=store, reference_brdf=reference_brdf,
                     reference_source=reference_source)
    log(f"measured {len(data.table)} BRDF samples ({took()})")
    cal = data.reference_calibration
    if cal is not None:
        log("reference calibration: data renormalised with the reference's own BRDF, median change "
            + ", ".join(f"{c} {e['median']:+.1%}" for c, e in cal["effect"].items() if e))
    t = data.table
    fit_check = None
    if fit_file is not None:
        w = luminance_params(fit_file)
        f = ward_from_angles(t.theta_in, t.theta_out, t.theta_h, t.phi_h, w)
        rel = float(np.nanmedian(np.abs(t.f_thesis / np.maximum(f, 1e-9) - 1)))      # rows with every channel
        fit_check = check_fit(fit, fit_file.provenance, sample_dir, rel)
        log(fit_check)
        data.material_fixed = cal is None
    if cal is not None:
        cal["fit"] = ("material refitted to the renormalised data" + (
            " (the given --fit, made on thesis-normalised data, was only checked against this capture)"
            if fit is not None else ""))
    if not data.material_fixed:
        w = stage("material_fit", lambda: material_fit(t))
    log(f"material: {w} ({took()})")
    m = BrdfModel.build(data, w)
    for ch, e in m.channel_fill.items():
        log(f"channel {ch} missing in {e['rows_predicted']} of {len(m.rows)} rows (out of the capture's dynamic "
            f"range): kept, predicted by {e['predicted_by']}")
    log(f"base model's normalised held-out error {m.calibration.get('heldout_error', float('nan')):.3g} "
        f"(noise alone {m.calibration.get('heldout_error_noise_only', float('nan')):.3g}); fitting the BRDF-space causes")
    # the frame-space stage (the raws, the sensor and LED causes) runs in a worker process beside the
    # BRDF-space causes: on a 2-core machine the two share the cores instead of taking turns
    bg = FrameStage(sample_dir, data.measured) if store is None or not store.has("frame_stage") else None
    # the white patch in both captures (vignetting's signature, white_patch.py): its raws read in a third process
    patch_args = (str(sample_dir), str(reference_dir), data.measured.geometry, data.reference_geometry or {})
    pw = InWorker(patch_rates, *patch_args) if store is None or not store.has("patch_rates") else None
    # the sample's outline in its own frames (the sample radius's signature, silhouette.py): read after the
    # BRDF-space causes (a box around the sample, 0.5-3 s for two to eight LEDs)
    with bg if bg is not None else contextlib.nullcontext(), pw if pw is not None else contextlib.nullcontext():
        causes = stage("brdf_causes", lambda: brdf_causes(m, log=log))
        log(f"BRDF-space causes done{'; waiting for the frame-space causes' if bg is not None else ''} ({took()})")
        fcauses, fstructure, veil = stage("frame_stage", lambda: bg.result() if bg is not None
                                          else frame_stage(sample_dir, data.measured, log=log))
        units = stage("patch_rates", lambda: pw.result() if pw is not None else patch_rates(*patch_args))
    camera = data.camera
    limbs = (stage("limb_rates", lambda: limb_rates(str(sample_dir), data.measured.geometry, camera,
                                                    data.image_size))
             if camera is not None else [])
    # the white marker band on the cylinder in both captures (the LED positions' signature, marker_band.py)
    band = (stage("band_rates", lambda: band_rates(str(sample_dir), str(reference_dir), data.measured.geometry,
                                                  camera, data.image_size)) if camera is not None else [])
    # stray light judged by the frames' dark pixels: refuted where they are darker than its veil,
    # named through its frame-space signature where they carry it (stray_light.py)
    stray = frame_evidence(veil, t, data.lamps)
    with one_blas_thread():
        apply_frame_evidence(model_of(m, next((c for c in causes if c.name == "stray_light"), None)), causes, stray)
    if stray is not None:
        log(f"stray light in the frames' dark pixels: s = {stray['s']:.3g} +- {stray['se']:.2g}")
    # the white patch in both captures: vignetting and a changed LED emission pattern (white_patch.py)
    vig = patch_evidence(units, data.image_size, data.principal_point)
    emission = None
    if data.camera is not None:
        patch_points(units, data)
        emission = emission_evidence(units, data.lamps, data.image_size, data.principal_point)
    with one_blas_thread():
        apply_patch_evidence(model_of(m, next((c for c in causes if c.name == "vignetting"), None)), causes, vig,
                             emission)
        apply_emission_evidence(model_of(m, next((c for c in causes if c.name == "led_emission"), None)), causes,
                                emission)
    rig_s = load_rig(data.measured.rig_path)
    outline = (silhouette_evidence(limbs, data.measured.geometry, data.camera, rig_s.cylinder_radius,
                                   rig_s.sample_height, data.lamps) if data.camera is not None else None)
    with one_blas_thread():
        apply_silhouette_evidence(model_of(m, brdf_cause(causes, "sample_radius_error")),
                                  causes, outline)
    moved = band_evidence(band, data.lamps, bending_causes(causes + fcauses, vig, emission))
    with one_blas_thread():
        apply_band_evidence(model_of(m, brdf_cause(causes, "led_position_error")), causes,
                            moved)
    if moved is not None:
        log(f"LED positions from the marker band: RMS move {moved['magnitude']:.3g} +- {moved['se']:.2g} mm"
            f"{'' if moved['significant'] else ' (no signature: ' + str(moved['why_not']) + ')'}")
    if outline is not None:
        log(f"sample radius from the outline: dr = {outline['dr']:+.3g} +- {outline['se']:.2g} mm"
            f"{'' if outline['significant'] else ' (no signature: ' + str(outline['why_not']) + ')'}")
    for what, ev, p in (("vignetting", vig, "k"), ("an LED emission pattern", emission, "n")):
        if ev is not None:
            log(f"{what} in the white patch (sample against reference): {p} = {ev[p]:.3g} +- {ev['se']:.2g}, "
                f"held-out gain {ev['gain']:.2%}{'' if ev['significant'] else ' (no signature: ' + str(ev['why_not']) + ')'}")
    causes = causes + fcauses
    log(f"frame-space causes done ({took()})")
    structure = {"brdf": brdf_structure(m), "frames": fstructure}
    base: dict[str, float] = {}
    for c in causes:
        base.setdefault(c.space, c.base_error)
    meta = {"sample": str(sample_dir), "reference": str(reference_dir), "camera": str(camera), "lamps": str(lamps),
            "fit": str(fit) if fit else None, "fit_check": fit_check, "material": w.as_dict(),
            "material_from_capture": fit is None,
            "stray_light_frames": stray,
            "vignetting_patch": vig, "led_emission_patch": emission, "sample_radius_silhouette": outline,
            "led_position_band": moved,
            "n_brdf_rows": int(len(m.rows)), "leds": sorted(int(x) for x in np.unique(t.led)),
            "missing_channels": m.channel_fill, "reference_calibration": cal or {"applied": False},
            "splits": {"brdf": "leave one LED out (per-LED parameters or one LED: the two halves of the pixel rows)",
                       "frames": "even / odd exposure index", "pixels": "even / odd exposure index (pixel set found under every LED)"},
            "time_s": clock.seconds()[0]}
    # a named BRDF-space cause must leave no structure where no material acts (unexplained.py)
    named = retested_cause(causes, verdict(causes))
    with one_blas_thread():
        # an instrument cause was fitted on the conditioned model (catalogue.instrument_bases): its residual is
        # tested with that model's noise
        open_world = unexplained(m, fstructure, after=named, after_model=model_of(m, named))
    log(f"residual structure tested against {len(open_world)} variables; "
        f"{sum(e['significant'] for e in open_world)} carry structure no cause explains")
    rep = write_report(out, causes, base, structure, meta, plots=plots, unexplained=open_world,
                       calibration=m.calibration)
    return rep
