"""Why narrow lobes miss the recovery targets: the angular footprint of one sample (issue 4).

    python validation/recovery_footprint.py --work /tmp/recovery \
        --materials transparency_sheet,brushed_reproduced,brushed_original [--render old]

The footprint model (a sample is the BRDF averaged over the pixels of its Bayer block,
mapped into the lobe's slope domain by the local Jacobian) is
:mod:`glossrig.core.models.footprint`. A fit of the point-sampled model (eq. 4.79) to such
values is biased once the lobe (full width at half maximum ``2 alpha sqrt(ln 2)`` in
slope) is not much wider than the footprint.

Measured here, for each material's truth (the twin's truth.json) and the samples it
was extracted at (``WORK/<material>.parquet``), with ``J`` taken from the extracted
angles of neighbouring blocks (so from the calibrated geometry, not the nominal one):

* the footprint: the range of theta_h across one Bayer block (2 px along the direction
  of fastest change) and the RMS width of the whole luminance kernel, in degrees, next
  to the lobe's half-maximum width;
* how many samples fall inside the lobe's half maximum (per LED and rotation);
* the forward model: the true BRDF averaged over every sample's footprint, against the
  point value (``predicted``) and against what the pipeline extracted (``observed``);
* the parameters a fit of eq. 4.79 recovers from the footprint-averaged truth without
  any noise (``footprint-only fit``): the bias the footprint alone causes;
* for captures of the current renderer (``--render area``), the parameters the
  footprint-averaged fit (:mod:`glossrig.core.fitting.footprint_model`, ``glossrig fit``'s
  default) recovers from the same values (``footprint-model fit``): what the
  footprint leaves once the fit models it.

``--render old`` adds the twin's earlier lens resampling (one bilinear read per output
pixel from a canvas at the output resolution: on average a further 1-pixel tent) to
the kernel, for captures rendered before twin/render.py integrated the pixel area.
``--at-scale S`` predicts the same for captures at scale S (the measured Jacobian
scaled by the ratio of the scales, at the same samples).
Writes ``WORK/footprint.json`` (``WORK/footprint_at_S.json``), read by
recovery_study.py's report.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from glossrig.core.capture import read_truth
from glossrig.core.models.footprint import (exponent, footprint_average, kernel_rms_px, luminance_kernel,  # noqa: F401
                                     slope_jacobian, slopes)

LN2 = math.log(2.0)


def trend(theta_h_deg, pred, obs, n_bins: int = 6) -> list[dict]:
    """Median predicted and observed relative error (value / point truth - 1) in theta_h bins."""
    edges = np.linspace(0, max(float(theta_h_deg.max()), 1e-6), n_bins + 1)
    out = []
    for a, b in zip(edges, edges[1:]):
        k = (theta_h_deg >= a) & (theta_h_deg < b)
        if k.sum() >= 20:
            out.append({"theta_h_deg": [float(a), float(b)], "n": int(k.sum()),
                        "predicted": float(np.median(pred[k])), "observed": float(np.median(obs[k]))})
    return out


def study(work: Path, material: str, render: str, fit: bool = True, at_scale: float | None = None,
          pixel_rule: str = "midpoint") -> dict:
    """The footprint numbers of one material (module docstring). ``at_scale``: predict
    for captures at that scale instead of the one measured, by scaling the measured
    Jacobian by (measured scale / at_scale) at the same samples (the footprint shrinks
    with the pixel; the number of samples, which grows, is not modelled). ``pixel_rule``:
    the pixel-area rule of the footprint-averaged truth
    (:func:`glossrig.core.models.footprint.luminance_kernel`)."""
    from glossrig.core.fitting.fit import fit_samples, parameter_errors
    from glossrig.core.samples import luminance, read_samples
    from glossrig.core.models.ward import WardParams, ward_from_angles

    df = read_samples(work / f"{material}.parquet")
    truth_json = read_truth(work / material)
    p = WardParams(**truth_json["material"]["ward"])
    from glossrig.core.rig import default_rig_path, load_rig

    cfa = load_rig(default_rig_path()).camera.cfa            # the twin's sensor (scenes/thesis_rig.toml)
    offs, w = luminance_kernel(cfa, render, pixel_rule=pixel_rule)
    J = slope_jacobian(df)
    scale = truth_json.get("scale")
    if at_scale is not None:
        if scale is None:
            raise ValueError(f"{work / material}: truth.json has no scale; --at-scale needs it")
        J *= float(scale) / at_scale

    s = slopes(df["theta_h"].to_numpy(), df["phi_h"].to_numpy())
    q = exponent(s, p)
    inside = q < LN2                                   # inside the half maximum
    near = q < 20 * LN2                                # where the lobe is above 1e-6 of its peak
    sv = np.linalg.svd(J[near & np.all(np.isfinite(J.reshape(len(df), 4)), axis=1)], compute_uv=False)
    Jmax = sv[:, 0]                                    # slope per px along the fastest direction
    # kernel RMS along each sample's fastest direction ~ along u or v: take the larger of the two
    rms_px = max(kernel_rms_px(offs, w, (1, 0)), kernel_rms_px(offs, w, (0, 1)))
    deg = 180 / math.pi
    per_slice = df.assign(inside=inside).groupby(["led", "rotation"])["inside"].sum()
    f_meas = footprint_average(df, p, J, offs, w)
    f_point = ward_from_angles(df["theta_in"], df["theta_out"], df["theta_h"], df["phi_h"], p)
    y = np.asarray(luminance(df["r"], df["g"], df["b"]), float)
    sel = (f_point > 0.05) & np.isfinite(y)           # the report's selection (pipeline_study)
    lobe = f_point - p.rho_d / np.pi > 0.5 * f_point      # the lobe is most of the BRDF
    pred = f_meas[sel] / f_point[sel] - 1
    obs = y[sel] / f_point[sel] - 1
    out = {
        "material": material, "render": render, "pixel_rule": pixel_rule, "scale": at_scale or scale, "measured_scale": scale,
        "predicted_from_scale": scale if at_scale is not None else None,
        "truth": p.as_dict(),
        "lobe_fwhm_deg": {"alpha_x": 2 * p.alpha_x * math.sqrt(LN2) * deg, "alpha_y": 2 * p.alpha_y * math.sqrt(LN2) * deg},
        "block_span_deg": {"median": float(np.median(2 * Jmax) * deg), "p10": float(np.percentile(2 * Jmax, 10) * deg),
                           "p90": float(np.percentile(2 * Jmax, 90) * deg)},
        "kernel_rms_px": rms_px,
        "kernel_rms_deg": float(np.median(Jmax) * rms_px * deg),
        "pixel_deg": float(np.median(Jmax) * deg),
        "n_inside_half_max": int(inside.sum()),
        "n_inside_half_max_per_slice": {"median": float(per_slice.median()), "max": int(per_slice.max()),
                                        "slices": int(per_slice.size), "empty": int((per_slice == 0).sum())},
        "n_above_0.05": int(sel.sum()),
        "peak": {"point": float(f_point.max()), "footprint": float(f_meas.max()), "observed": float(np.nanmax(y))},
        "median_abs_rel_err_observed": float(np.median(np.abs(obs))),
        "median_abs_rel_err_predicted": float(np.median(np.abs(pred))),
        "median_abs_observed_minus_predicted": float(np.median(np.abs(obs - pred))),
        "trend_vs_theta_h": trend(np.degrees(df["theta_h"].to_numpy()[lobe]), f_meas[lobe] / f_point[lobe] - 1,
                                  y[lobe] / f_point[lobe] - 1),
    }
    if fit:
        # the pipeline's own fit (`glossrig fit`'s defaults: luminance, the table's weight column)
        # the point model (eq. 4.79): the bias a fit that ignores the footprint suffers
        r = fit_samples(df.assign(r=f_meas, g=f_meas, b=f_meas), channels=["luminance"],
                        footprint=False, budget=False).fits["luminance"]
        out["footprint_only_fit"] = r.params.as_dict()
        out["footprint_only_rel_err"] = parameter_errors(r.params, p)
        if render == "area" and at_scale is None:
            # the footprint-averaged model (`glossrig fit`'s default) on the same noise-free values: what is
            # left when the fit models the footprint (its kernel is the fit's own Gauss rule, the values'
            # the midpoint rule above, so this also checks the fit's quadrature)
            r = fit_samples(df.assign(r=f_meas, g=f_meas, b=f_meas), channels=["luminance"],
                            footprint=True, budget=False).fits["luminance"]
            out["footprint_model_fit"] = r.params.as_dict()
            out["footprint_model_rel_err"] = parameter_errors(r.params, p)
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--materials", default="transparency_sheet,brushed_reproduced,brushed_original")
    ap.add_argument("--render", choices=("area", "old"), default="old")
    ap.add_argument("--no-fit", action="store_true")
    ap.add_argument("--pixel-rule", default="midpoint",
                    help="pixel-area rule of the footprint-averaged truth: midpoint (1/4-px grid) or gaussN")
    ap.add_argument("--at-scale", type=float, default=None,
                    help="predict the footprint's effect at this capture scale (Jacobian scaled, same samples)")
    ap.add_argument("--out", default=None, help="default WORK/footprint.json")
    a = ap.parse_args(argv)
    work = Path(a.work)
    res = {m: study(work, m, a.render, fit=not a.no_fit, at_scale=a.at_scale, pixel_rule=a.pixel_rule)
           for m in a.materials.split(",")}
    default = work / ("footprint.json" if a.at_scale is None else f"footprint_at_{a.at_scale:g}.json")
    Path(a.out or default).write_text(json.dumps(res, indent=1))
    print(json.dumps(res, indent=1))
    return res


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
