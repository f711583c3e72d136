"""What diagnosis works on: one capture measured twice over (issue 7).

* **BRDF space** (:class:`BrdfData`): the capture run through the pipeline's own
  stages (:func:`glossrig.core.extraction.extract.measure_capture`, diffuse normalisation by
  the reference, thesis eq. 4.73-4.78), one row per (Bayer block, LED, rotation)
  with its pixel, surface point and normal, angles, the patch-normalised sample
  and reference values and the measured BRDF (Rec. 709 luminance ``y``).
* **Frame space** (:class:`FrameData`): the raw DN of every exposure of every LED
  in the crop holding the sample and the white patch, with the exposure time,
  the time stamp and the sensor's levels and noise figures taken from the files
  and the rig (thesis 4.3.1-4.3.3). A linear sensor predicts
  ``DN = black + rate * t`` per pixel; sensor and LED causes bend that line.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
import pandas as pd

from glossrig.core.capture import load_manifest
from glossrig.core.errors import InputError
from glossrig.core.extraction.extract import Measured, check_compatible, diffuse_normalize, measure_capture, measure_pair
from glossrig.core.led_fluctuations import drift_slope_rms_per_min
from glossrig.core.rig import load_rig
from glossrig.core.samples import LUMINANCE_WEIGHTS

LUMA = np.array(LUMINANCE_WEIGHTS)


@dataclass
class BrdfData:
    table: pd.DataFrame           # rows: block x LED x rotation; f = measured luminance BRDF
    measured: Measured            # the sample capture as measured (geometry per rotation)
    albedo: float
    image_size: tuple[int, int]   # full image (width, height)
    principal_point: tuple[float, float]
    patch_uv: dict[float, tuple[float, float]]  # rotation -> (u, v) of the white patch centre (full image)
    lamps: dict                   # LED id -> lamp position (holder frame, mm)
    material_fixed: bool = False  # True when the material fit comes from another capture
    camera: tuple | None = None   # (K, distortion) of the camera calibration
    #: the calibration with the reference's own BRDF applied to ``table`` (:func:`renormalise_table`); None: not applied
    reference_calibration: dict | None = None
    #: rotation -> RotationGeometry of the reference capture (its own marker detection): the white patch's
    #: pixels there (:mod:`glossrig.core.diagnose.white_patch`); None: not known
    reference_geometry: dict | None = None


@dataclass
class LedFrames:
    led: int
    rotation: float
    dn: np.ndarray          # (n_exp, h, w) float32 raw DN of the crop
    exposure_s: np.ndarray  # (n_exp,)
    time_s: np.ndarray      # (n_exp,) seconds since the capture's first sequence frame
    black: np.ndarray       # (h, w) stated black level per pixel
    origin: tuple[int, int]
    files: list = field(default_factory=list)
    cfa: np.ndarray | None = None   # 2x2 colour indices (0 R, 1 G, 2 B) of dn[..., 0:2, 0:2]; None: RGGB

    def colours(self) -> np.ndarray:
        """(h, w) colour index of every pixel of the crop (the crop keeps the CFA phase)."""
        from glossrig.core.calibration.demosaic import channel_index

        cfa = np.array([[0, 1], [1, 2]]) if self.cfa is None else np.asarray(self.cfa)
        return channel_index(self.dn.shape[1:], cfa)


@dataclass
class FrameData:
    leds: list[LedFrames]
    white: float
    e_per_dn: float         # conversion gain at the sequence ISO (e-/DN)
    read_dn: float          # read noise (DN RMS), quantisation included
    #: RMS relative slope (1/min) of a healthy LED's drift: the capture's rig file's ``[leds]`` figures
    #: (:meth:`glossrig.core.rig.Lighting.drift_slope_rms_per_min`); the LED-drift test's null
    drift_rms_per_min: float = drift_slope_rms_per_min()

    def variance(self, signal_dn) -> np.ndarray:
        """Temporal variance of a frame's DN at an expected signal above black (EMVA 1288)."""
        return np.maximum(signal_dn, 0.0) / self.e_per_dn + self.read_dn ** 2


def _lum(df, prefix=""):
    return LUMA[0] * df[prefix + "r"] + LUMA[1] * df[prefix + "g"] + LUMA[2] * df[prefix + "b"]


def load_brdf(sample_dir, reference_dir, cam, lamps, albedo: float = 0.8, progress: bool = False,
              reference: Measured | None = None, store=None, reference_brdf=None,
              reference_source: str | None = None) -> BrdfData:
    """Measure sample and reference alike and divide them (the pipeline's extraction),
    keeping the geometry columns the causes need. ``reference`` is the reference capture
    already measured with the same camera and lamps (a study reuses it across captures).
    ``store``: a :class:`glossrig.core.checkpoint.WorkStore` keeping each measured LED
    (see :func:`glossrig.core.extraction.extract.measure_capture`).

    ``reference_brdf``: callable(table) -> (n, 3) RGB BRDF of the reference at the rows'
    angles. When given, the table is calibrated with it (:func:`renormalise_table`) before
    anything else is derived from it, and ``reference_calibration`` records the step
    (``reference_source`` names where the BRDF came from)."""
    from glossrig.core.extraction.extract import camera_arrays

    if reference is None:
        # one pool for both, the reference only in the sample's units (the ones the division uses); the
        # captures are checked (check_compatible) before anything is measured
        ms, mr = measure_pair(sample_dir, reference_dir, cam, lamps, progress=progress, what="diagnose", store=store)
    else:
        check_compatible(sample_dir, reference_dir, what="diagnose")
        ms = measure_capture(sample_dir, cam, lamps, progress=progress, what="diagnose", store=store,
                             unit_prefix="sample-")
        mr = reference
    s = ms.table.copy()
    for c in "rgb":
        s[f"S_{c}"] = s[c]
        s[f"relvar_S_{c}"] = s[f"var_{c}"] / np.maximum(s[c], 1e-12) ** 2
    t = diffuse_normalize(s, mr.table, albedo=albedo)
    t = t.reset_index(drop=True)
    t["f_thesis"] = _lum(t)         # the thesis-normalised luminance (eq. 4.78), kept for a --fit's check
    cal = None
    if reference_brdf is not None:
        t, cal = renormalise_table(t, reference_brdf, albedo, source=reference_source)
    # luminance BRDF; NaN where a channel is missing (out of the capture's dynamic range): such a
    # row keeps its valid channels and BrdfModel.build predicts the missing one (issue 14, item 1)
    t["f"] = _lum(t)
    t["S"] = valid_luminance(t, "S_")
    # relative variance of the measured luminance: sample and reference HDR variances of each
    # channel (a ratio's relative variances add), combined with the Rec. 709 weights
    t["relvar"] = luminance_relvar(t, mr.table)
    complete_ok = np.isfinite(t["f"]) & (t["f"] > 0)
    partial = ~np.isfinite(t["f"]) & np.isfinite(t[["r", "g", "b"]]).any(axis=1)
    t = t[(complete_ok | partial) & np.isfinite(t["S"]) & (t["S"] > 0)].reset_index(drop=True)
    if len(t) < 200:
        raise InputError(f"only {len(t)} usable BRDF samples: too few to diagnose", path=Path(sample_dir))
    man = load_manifest(sample_dir)
    first = next(im for im in man.images if im.role == "calibration")
    fr = man.read_raw(first, crop=(0, 0, 2, 2))
    patch_uv = {}
    for rot, g in ms.geometry.items():
        ii, jj = np.nonzero(g.patch_mask)
        patch_uv[rot] = (g.crop[0] + float(jj.mean()), g.crop[1] + float(ii.mean()))
    return BrdfData(t, ms, albedo, tuple(fr.full_size), (cam.cx, cam.cy), patch_uv, dict(lamps),
                    camera=camera_arrays(cam), reference_calibration=cal, reference_geometry=mr.geometry)


def renormalise_table(t: pd.DataFrame, reference_brdf, albedo: float, source: str | None = None
                      ) -> tuple[pd.DataFrame, dict]:
    """Calibrate a thesis-normalised table with the reference's own BRDF (issue 14, item 4).

    The thesis divides by a Lambertian white of albedo 0.8 (eq. 4.78, ``f = (albedo/pi) S / R``);
    the reference pixel records ``R ~ f_ref(wi, wo) cos(theta_in) E``, so the division leaves
    ``(albedo/pi) f / f_ref``. Each channel is multiplied by ``k_c = f_ref,c pi / albedo`` at
    the row's angles (:func:`glossrig.core.diagnose.material_models.renormalise`); its inverse
    variance ``weight_<c>`` (of the BRDF value, :func:`~glossrig.core.extraction.extract.normalize_unit`)
    by ``1 / k_c^2`` - f_ref is taken as exact, so relative variances are unchanged - and
    ``weight`` is recomputed as their mean over the valid channels and rescaled to mean 1
    (:func:`~glossrig.core.extraction.extract.scale_weights`). A channel whose ``f_ref`` is not a
    positive finite number becomes missing (NaN) in that row, as a dark channel is.

    Returns the new table and the record of the step: ``effect`` is, per channel, the median
    relative change ``k_c - 1`` of the data over the rows with the channel, with its 5-95 %
    spread (the spread is the angular part a fitted rho_d, rho_s cannot absorb)."""
    from glossrig.core.diagnose.material_models import renormalise
    from glossrig.core.extraction.extract import scale_weights

    ref = np.asarray(reference_brdf(t), float)
    if ref.shape != (len(t), 3):
        raise InputError(f"the reference BRDF gave an array of shape {ref.shape} for {len(t)} rows (expected "
                         f"({len(t)}, 3) RGB values)", path=Path(source) if source else None)
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(ref) & (ref > 0)
    k = np.where(ok, renormalise(np.ones_like(ref), np.where(ok, ref, 1.0), albedo), np.nan)
    t = t.copy()
    effect, lost = {}, {}
    w = np.zeros(len(t))
    nw = np.zeros(len(t))
    for j, c in enumerate("rgb"):
        had = np.isfinite(t[c].to_numpy(float))
        t[c] = t[c].to_numpy(float) * k[:, j]
        if f"weight_{c}" in t:
            t[f"weight_{c}"] = t[f"weight_{c}"].to_numpy(float) / k[:, j] ** 2
            wc = t[f"weight_{c}"].to_numpy(float)
            valid = np.isfinite(t[c].to_numpy(float)) & np.isfinite(wc)
            w += np.where(valid, wc, 0.0)
            nw += valid
        kc = k[had & ok[:, j], j]
        lost[c] = int(np.sum(had & ~ok[:, j]))
        effect[c] = ({"median": float(np.median(kc) - 1), "p5": float(np.percentile(kc, 5) - 1),
                      "p95": float(np.percentile(kc, 95) - 1)} if kc.size else None)
    if "weight" in t and all(f"weight_{c}" in t for c in "rgb"):
        with np.errstate(invalid="ignore", divide="ignore"):
            t["weight"] = np.where(nw > 0, w / np.maximum(nw, 1), np.nan)
        t = scale_weights(t)
    cal = {"applied": True, "source": source,
           "formula": "f = f_meas * f_ref * pi / albedo per channel at each row's angles (thesis eq. 4.78 inverted)",
           "albedo": float(albedo), "effect": effect, "effect_unit": "relative change of the data (k_c - 1)",
           "rows_made_missing": lost}
    return t, cal


def valid_luminance(df, prefix="") -> np.ndarray:
    """Rec. 709 luminance of each row's valid (finite) channels, renormalised by the weights of
    those channels (``sum_valid LUMA_c x_c / sum_valid LUMA_c``): a signal level for rows that
    miss a channel; NaN where none is valid."""
    x = df[[prefix + "r", prefix + "g", prefix + "b"]].to_numpy(float)
    ok = np.isfinite(x)
    w = np.where(ok, LUMA, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(ok.any(axis=1), np.sum(w * np.nan_to_num(x), axis=1) / w.sum(axis=1), np.nan)


def luminance_relvar(t: pd.DataFrame, reference: pd.DataFrame) -> np.ndarray:
    """Relative variance of each row's luminance BRDF ``y = sum_c LUMA_c f_c`` from the HDR
    variances of the sample (``relvar_S_<c>``) and of the reference row that
    :func:`~glossrig.core.extraction.extract.diffuse_normalize` divided by (its nearest
    geometry in the same LED and rotation): ``var y = sum_c LUMA_c^2 f_c^2 (var S_c / S_c^2 +
    var R_c / R_c^2)``. A missing channel (NaN) contributes nothing."""
    from scipy.spatial import cKDTree

    from glossrig.core.extraction.extract import _dirs

    rel_r = np.full((len(t), 3), np.nan)
    for (led, rot), idx in t.groupby(["led", "rotation"]).indices.items():
        r = reference[(reference.led == led) & (reference.rotation == rot)]
        if r.empty:
            continue
        _, j = cKDTree(_dirs(r)).query(_dirs(t.iloc[idx]))
        for k, c in enumerate("rgb"):
            R = r[c].to_numpy(float)[j]
            rel_r[idx, k] = r[f"var_{c}"].to_numpy(float)[j] / np.maximum(R, 1e-12) ** 2
    f = t[["r", "g", "b"]].to_numpy(float)
    rel_s = t[["relvar_S_r", "relvar_S_g", "relvar_S_b"]].to_numpy(float)
    var = np.nansum((LUMA * f) ** 2 * (rel_s + np.nan_to_num(rel_r, nan=0.0)), axis=1)
    y = np.nansum(LUMA * f, axis=1)
    return var / np.maximum(y, 1e-12) ** 2


def _seconds(ts: str) -> float:
    try:
        return datetime.fromisoformat(ts).timestamp()
    except (TypeError, ValueError):
        raise InputError(f"bad time stamp {ts!r} in the manifest") from None


def load_frames(sample_dir, measured: Measured) -> FrameData:
    """Raw DN of each LED's exposure sequence (first repeat) in the measured crop."""
    man = load_manifest(sample_dir)
    rig = load_rig(man.rig_path())
    sen = rig.sensor
    seq_all = man.select("sequence")
    t0 = min(_seconds(im.time) for im in seq_all)
    leds, white, iso = [], None, None
    for rot, g in sorted(measured.geometry.items()):
        for led in sorted({im.leds[0] for im in man.select("sequence", rotation=rot)}):
            seq = [im for im in man.select("sequence", rotation=rot) if im.leds == [led] and im.repeat == 0]
            seq.sort(key=lambda im: im.exposure_s)
            frames = [man.read_raw(im, crop=g.crop) for im in seq]
            f0 = frames[0]
            h, w = f0.mosaic.shape
            black = np.tile(np.asarray(f0.black, float).reshape(2, 2), (h // 2 + 1, w // 2 + 1))[:h, :w]
            white, iso = f0.white, seq[0].iso
            leds.append(LedFrames(led, rot, np.stack([f.mosaic.astype(np.float32) for f in frames]),
                                  np.array([im.exposure_s for im in seq]),
                                  np.array([_seconds(im.time) - t0 for im in seq]), black, f0.origin,
                                  [im.file for im in seq], np.asarray(f0.cfa)))
    if white is None or iso is None:
        raise InputError("no single-LED sequence frames with an ISO in the manifest", path=man.path)
    k = sen.electrons_per_dn_iso100 * 100.0 / float(iso)
    read = float(np.sqrt((sen.read_noise_e / k) ** 2 + 1.0 / 12.0))
    return FrameData(leds, float(white), k, read, rig.lighting.drift_slope_rms_per_min())
