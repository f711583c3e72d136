"""End-to-end ground-truth recovery on the twin: simulate -> calibrate -> extract -> fit.

    python -m validation.pipeline_study --out /tmp/study --scale 0.25 \
        --materials sample_2_6,isotropic_glossy --rotations 0 [--repeats 1] [--fit]

Steps (each a real `glossrig` command, so this is also what a user runs):
1. checkerboard views -> `glossrig calibrate camera`;
2. a transparency-sheet capture -> `glossrig calibrate lamps`;
3. a `lambert:0.8` reference capture and one capture per material -> `glossrig extract`;
4. optionally `glossrig fit`.
Reports intrinsics, poses and lamp positions against truth.json, and the extracted
BRDF against the true BRDF at the extracted angles (median relative error where the
true value exceeds 0.05 1/sr, and its trend against theta_h). Writes report.json and
report.md in --out.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from glossrig.core.calibration.intrinsics import load_camera
from glossrig.core.calibration.lamps import load_lamps
from glossrig.core.capture import read_truth
from glossrig.core.fitting.export import read_fit_file
from validation.common import calibrate, capture, extract, fit
from validation.paths import RIG


def _by_theta_h(th_deg: np.ndarray, rel: np.ndarray, edges: np.ndarray) -> list[dict]:
    out = []
    for a, b in zip(edges, edges[1:]):
        m = (th_deg >= a) & (th_deg < b)
        if m.sum() > 20:
            out.append({"theta_h_deg": [float(a), float(b)], "median_rel_err": float(np.median(rel[m])),
                        "n": int(m.sum())})
    return out


def _trend_per_10deg(th_deg: np.ndarray, rel: np.ndarray) -> dict:
    """Least-squares slope of the relative error against theta_h (per 10 degrees) with its
    standard error (residual scatter, independent samples assumed)."""
    A = np.stack([np.ones_like(th_deg), th_deg / 10.0], axis=1)
    coef, *_ = np.linalg.lstsq(A, rel, rcond=None)
    res = rel - A @ coef
    cov = np.linalg.inv(A.T @ A) * (res @ res) / max(len(rel) - 2, 1)
    return {"slope": float(coef[1]), "stderr": float(math.sqrt(cov[1, 1]))}


def brdf_errors(samples_path: Path, truth_path: Path) -> dict:
    """Extracted luminance BRDF against the truth where the true value exceeds 0.05 1/sr:
    against the point value at the sample's four angles (the issue's figure) and against
    the footprint truth (:func:`glossrig.core.models.footprint.footprint_truth`: the point value
    averaged over the pixels the sample integrates), each binned by theta_h with a linear
    trend. A trend against the point truth that the footprint truth removes is the
    physics of an area-integrating pixel on a narrow lobe, not an extraction error."""
    from glossrig.core.models.footprint import footprint_truth
    from glossrig.core.rig import load_rig
    from glossrig.core.samples import luminance, read_samples
    from glossrig.core.models.ward import WardParams, ward_from_angles

    df = read_samples(samples_path)
    truth = read_truth(truth_path)
    w = WardParams(**truth["material"]["ward"])
    f = np.asarray(ward_from_angles(df.theta_in, df.theta_out, df.theta_h, df.phi_h, w), float)
    f_fp = footprint_truth(df, w, load_rig(RIG).camera.cfa)
    y = np.asarray(luminance(df.r, df.g, df.b), float)
    sel = (f > 0.05) & np.isfinite(y)          # NaN: a channel missing there (core/samples.py)
    rel = y[sel] / f[sel] - 1
    rel_fp = y[sel] / f_fp[sel] - 1
    th = np.degrees(df.theta_h.to_numpy()[sel])
    edges = np.linspace(0, max(th.max(), 1), 6)
    return {"n_samples": int(len(df)), "n_above_0.05": int(sel.sum()),
            "median_abs_rel_err": float(np.median(np.abs(rel))), "median_rel_err": float(np.median(rel)),
            "p95_abs_rel_err": float(np.percentile(np.abs(rel), 95)),
            "trend_vs_theta_h": _by_theta_h(th, rel, edges), "trend_per_10deg": _trend_per_10deg(th, rel),
            "footprint": {"median_abs_rel_err": float(np.median(np.abs(rel_fp))),
                          "median_rel_err": float(np.median(rel_fp)),
                          "trend_vs_theta_h": _by_theta_h(th, rel_fp, edges),
                          "trend_per_10deg": _trend_per_10deg(th, rel_fp)}}


def main(argv=None) -> dict:
    argv = list(argv) if argv is not None else sys.argv[1:]
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", required=True)
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--materials", default="sample_2_6,isotropic_glossy")
    ap.add_argument("--rotations", default="0")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--fit", action="store_true")
    ap.add_argument("--lamp-rotations", default="0", help="rotations of the specular (lamp) capture")
    ap.add_argument("--markdown", default=None, help="also write the report as Markdown here")
    a = ap.parse_args(argv)
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    report: dict = {"scale": a.scale, "rotations": a.rotations, "repeats": a.repeats}

    cam, lamps = calibrate(out, a.scale, a.seed, a.lamp_rotations, a.repeats)
    c = load_camera(cam)
    t = read_truth(out / "checker")
    K = np.array(t["camera_matrix"])
    report["intrinsics"] = {"fx_rel_err": c.fx / K[0, 0] - 1, "fy_rel_err": c.fy / K[1, 1] - 1,
                            "cx_err_px": c.cx - K[0, 2], "cy_err_px": c.cy - K[1, 2], "rms_px": c.rms_px}

    spec = out / "specular"
    L = load_lamps(lamps)
    tl = read_truth(spec)["led_positions_mm"]
    report["lamp_error_mm"] = {str(k): float(np.linalg.norm(np.subtract(v, tl[str(k)]))) for k, v in L.items()}

    ref = capture(out / "reference", "lambert:0.8", a.scale, a.seed + 2, a.rotations, a.repeats)
    report["materials"] = {}
    for k, m in enumerate(a.materials.split(",")):
        cap = capture(out / m, m, a.scale, a.seed + 10 + k, a.rotations, a.repeats)
        sp = extract(cap, ref, cam, lamps, out / f"{m}.parquet")
        entry = brdf_errors(sp, cap / "truth.json")
        if a.fit:
            fj = fit(sp, out / f"{m}.fit.json")
            f = read_fit_file(fj)
            entry["fit"] = {**f.fit.fits["luminance"].to_json(), **({"gloss": f.gloss} if f.gloss else {})}
            entry["truth"] = read_truth(cap)["material"]["ward"]
        report["materials"][m] = entry
        (out / "report.json").write_text(json.dumps(report, indent=1))     # progress survives a stop
    (out / "report.json").write_text(json.dumps(report, indent=1))
    print(json.dumps(report, indent=1))
    if a.markdown:
        Path(a.markdown).write_text(markdown(report, argv))
    return report


def markdown(r: dict, argv) -> str:
    i = r["intrinsics"]
    lines = ["# Pipeline ground-truth recovery on the twin (issue 3)", "",
             f"Command: `python -m validation.pipeline_study {' '.join(argv or sys.argv[1:])}`", "",
             f"Scale {r['scale']}, rotations {r['rotations']}, {r['repeats']} repeat(s), thesis LED fluctuations and "
             "sensor noise, reference lambert:0.8.", "",
             "| quantity | measured | target |", "|---|---|---|",
             f"| fx, fy relative error | {100 * i['fx_rel_err']:+.3f} %, {100 * i['fy_rel_err']:+.3f} % | 0.5 % |",
             f"| principal point error | ({i['cx_err_px']:+.2f}, {i['cy_err_px']:+.2f}) px | 5 px |",
             f"| reprojection RMS | {i['rms_px']:.3f} px | 0.3 px |",
             f"| lamp positions, worst of {len(r['lamp_error_mm'])} | {max(r['lamp_error_mm'].values()):.2f} mm | 2 mm |"]
    for m, e in r["materials"].items():
        lines.append(f"| {m}: BRDF median abs. rel. error where f > 0.05 ({e['n_above_0.05']} samples) | "
                     f"{100 * e['median_abs_rel_err']:.2f} % (signed {100 * e['median_rel_err']:+.2f} %) | 3 % |")
        for label, d in (("point truth", e), ("footprint truth", e.get("footprint"))):
            if d is None:
                continue
            trend = ", ".join(f"{t['theta_h_deg'][0]:.1f}-{t['theta_h_deg'][1]:.1f} deg: {100 * t['median_rel_err']:+.2f} %"
                              for t in d["trend_vs_theta_h"])
            sl = d.get("trend_per_10deg")
            slope = f"; slope {100 * sl['slope']:+.2f} +- {100 * sl['stderr']:.2f} % per 10 deg" if sl else ""
            lines.append(f"| {m}: signed error by theta_h vs {label} | {trend}{slope} | no trend |")
        if e.get("footprint"):
            lines.append(f"| {m}: median abs. rel. error vs footprint truth | "
                         f"{100 * e['footprint']['median_abs_rel_err']:.2f} % (signed {100 * e['footprint']['median_rel_err']:+.2f} %) | |")
    lines += ["", "Point truth: the true BRDF at the sample's four angles (the issue's comparison). Footprint truth: "
              "the same averaged over the pixels the sample integrates (glossrig.core.models.footprint: area pixels, the "
              "Bayer block's bilinear reads, Jacobian from neighbouring blocks). A sample's footprint spans a fraction "
              "of a degree of theta_h at this scale, comparable to a narrow lobe's width: the average lowers the peak "
              "and raises the flanks, a trend against theta_h that is the pixel's physics, not extraction error; it "
              "shrinks with the square of the pixel's angular size (full resolution: 1/16 of scale 0.25).", "",
              "Holder and cylinder poses against the truth: validation/calibration_report.md.", ""]
    return "\n".join(lines)


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
