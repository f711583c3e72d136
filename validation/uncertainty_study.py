"""Does the uncertainty budget cover the truth on the twin? (issue 15, first part)

    python -m validation.uncertainty_study --work /tmp/ub15/study --calibration /tmp/ub15/cal \
        --scale 0.25 --leds 8,9,10,11 --rotations=-45,0,45,90 \
        --materials sample_2_6,polyethylene,sanded_original,brushed_reproduced

Per material: a twin capture (the rig's LED fluctuations and sensor noise, ``glossrig
simulate``'s defaults) -> ``glossrig extract`` against a ``lambert:0.8`` reference with
the camera and lamp calibration of ``--calibration`` (a folder holding ``camera.json``
and ``lamps.json``, e.g. a ``glossrig demo`` output of the same scale; without it the
camera and lamps are calibrated on the twin in WORK, validation.common.calibrate) ->
the luminance fit twice, in this process: the footprint-averaged model (the default
of :func:`glossrig.core.fitting.fit.fit_samples`) and the point model
(``footprint=False``); with ``--true-calibration`` also the footprint fit of the same
capture extracted with the twin's true intrinsics and lamp positions (what is left
when the calibration is exact). The budget's LED aperture is 0 (``--led-aperture``):
the twin's LEDs are points. For each: the errors against the twin's truth (canonical form),
the budget's combined standard uncertainty (no calibration component: none is given),
error / u, and whether the 95 % interval holds the truth
(:func:`glossrig.core.fitting.uncertainty.coverage`). Writes WORK/results.json and
prints a Markdown report (``--report-only`` re-prints it from results.json).
Resumable: finished captures, extractions and fits are reused.

    python -m validation.uncertainty_study --footprint-check /tmp/ub15/r17_samples.parquet

checks the footprint-averaged fit on the footprint alone (:func:`footprint_check`).
"""
from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path

from validation.common import calibrate, capture, extract, truth_camera, truth_lamps

PARAMS = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")


def fit_one(samples: Path, truth: dict, footprint, led_aperture: float) -> dict:
    from glossrig.core.fitting.fit import fit_samples, parameter_errors
    from glossrig.core.fitting.uncertainty import coverage
    from glossrig.core.samples import read_samples

    df = read_samples(samples)
    t0 = time.perf_counter()
    f = fit_samples(df, channels=["luminance"], footprint=footprint, led_aperture=led_aperture).fits["luminance"]
    return {"time_s": time.perf_counter() - t0, "n": len(df), "params": f.params.as_dict(),
            "rel_err": parameter_errors(f.params, truth), "footprint": f.footprint,
            "uncertainty": f.uncertainty, "coverage": coverage(f.uncertainty, truth)}


def run(a) -> dict:
    from glossrig.core.capture import read_truth

    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    if a.calibration:
        cam, lamps = Path(a.calibration) / "camera.json", Path(a.calibration) / "lamps.json"
    else:
        cam, lamps = calibrate(work, a.scale, a.seed, leds=a.leds)
    res_path = work / "results.json"
    res = json.loads(res_path.read_text()) if res_path.exists() else {}
    res["_setup"] = {"scale": a.scale, "leds": a.leds, "rotations": a.rotations, "seed": a.seed,
                     "calibration": str(a.calibration or work), "led_aperture": a.led_aperture}
    ref = capture(work / "reference", "lambert:0.8", a.scale, a.seed + 2, a.rotations, leds=a.leds, echo="+")
    for k, m in enumerate(a.materials.split(",")):
        want = ["footprint", "point"] + (["footprint_true_calibration"] if a.true_calibration else [])
        if a.refit and m in res:
            for w in want:
                res[m].pop(w, None)
        if m in res and all(w in res[m] for w in want):
            continue
        cap = capture(work / m, m, a.scale, a.seed + 10 + k, a.rotations, leds=a.leds, echo="+")
        truth = read_truth(cap)["material"]["ward"]
        e = res.setdefault(m, {})
        e["truth"] = truth
        if "footprint" not in e or "point" not in e:
            sp = extract(cap, ref, cam, lamps, work / f"{m}.parquet", echo="+")
            e["footprint"] = fit_one(sp, truth, None, a.led_aperture)
            e["point"] = fit_one(sp, truth, False, a.led_aperture)
        if a.true_calibration and "footprint_true_calibration" not in e:
            # the same capture extracted with the twin's true intrinsics and lamp positions:
            # what remains is not the calibration's
            tc, tl = truth_camera(cap, work / "camera_truth.json"), truth_lamps(cap, work / "lamps_truth.json")
            sp = extract(cap, ref, tc, tl, work / f"{m}_truecal.parquet", echo="+")
            e["footprint_true_calibration"] = fit_one(sp, truth, None, a.led_aperture)
        res_path.write_text(json.dumps(res, indent=1))
    return res


#: Lobes for --footprint-check: Table 9.1's sample_2_6 and transparency_sheet, and a lobe
#: about as narrow as brushed_reproduced's (recovery.md: FWHM 0.75 / 0.85 deg).
CHECK_LOBES = {"sample_2_6": (0.0518, 0.0069, 0.0595, 0.034, 2.47),
               "transparency_sheet": (0.1198, 0.0708, 0.0031, 0.006, 3.26),
               "narrow (brushed_reproduced-like)": (0.05, 0.02, 0.0085, 0.0075, 0.3)}


def footprint_check(samples: Path, noise: float = 0.01, seed: int = 0) -> str:
    """The footprint alone: each lobe of :data:`CHECK_LOBES` averaged over every sample's
    footprint at the angles of SAMPLES (an extracted table: its Jacobian from neighbouring
    blocks, the luminance kernel with a 10-point rule per pixel axis, finer than the fit's),
    with and without multiplicative noise, fitted with the point model and with the
    footprint-averaged one. Returns a Markdown table of the errors."""
    import numpy as np

    from glossrig.core.fitting.fit import fit_samples, parameter_errors
    from glossrig.core.models.footprint import footprint_average, luminance_kernel, slope_jacobian
    from glossrig.core.models.ward import WardParams
    from glossrig.core.samples import read_samples

    df = read_samples(samples)
    offs, w = luminance_kernel("RGGB", pixel_rule="gauss10")
    J = slope_jacobian(df)
    rng = np.random.default_rng(seed)
    lines = ["| lobe | noise | model | rho_d | rho_s | alpha_x | alpha_y | rotation (deg) | fit time (s) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for name, x in CHECK_LOBES.items():
        p = WardParams(*x)
        f = footprint_average(df, p, J, offs, w)
        for nz in (0.0, noise):
            y = f * (1 + nz * rng.standard_normal(f.size))
            for fp in (False, None):
                t0 = time.perf_counter()
                r = fit_samples(df.assign(r=y, g=y, b=y), channels=["luminance"], footprint=fp,
                                budget=False).fits["luminance"]
                dt = time.perf_counter() - t0
                e = parameter_errors(r.params, p)
                lines.append(f"| {name} | {100 * nz:g} % | {'point' if fp is False else 'footprint'} | "
                             + " | ".join(f"{100 * e[k]:+.3f} %" for k in ("rho_d", "rho_s", "alpha_x", "alpha_y"))
                             + f" | {e['lobe_rotation_deg']:.3f} | {dt:.1f} |")
    return "\n".join(lines)


def _fmt(v, deg=False):
    if v is None:
        return "-"
    return f"{math.degrees(v):.3g}" if deg else f"{v:.3g}"


def report(res: dict) -> str:
    lines = ["| material | model | param | rel. error (rot: deg) | error / u | u: noise, model, footprint | "
             "combined u | k | 95 % covers |", "|---|---|---|---|---|---|---|---|---|"]
    counts = {"footprint": [0, 0], "point": [0, 0], "footprint_true_calibration": [0, 0]}
    for m, r in res.items():
        if m.startswith("_"):
            continue
        for model in ("footprint", "point", "footprint_true_calibration"):
            if model not in r:
                continue
            e = r[model]
            for p in PARAMS:
                u = e["uncertainty"][p]
                c = e["coverage"][p]
                comp = u["components"]
                deg = p == "lobe_rotation"
                err = e["rel_err"]["lobe_rotation_deg"] if deg else e["rel_err"][p]
                errs = f"{err:.3f}" if deg else f"{100 * err:+.3f} %"
                if c["covered"] is not None:
                    counts[model][0] += bool(c["covered"])
                    counts[model][1] += 1
                lines.append(f"| {m} | {model} | {p} | {errs} | {_fmt(c['ratio'])} | "
                             f"{_fmt(comp.get('noise'), deg)}, {_fmt(comp.get('model'), deg)}, "
                             f"{_fmt(comp.get('footprint'), deg)} | {_fmt(u['combined'], deg)} | "
                             f"{u['coverage_factor']:.2f} | {'yes' if c['covered'] else 'NO'} |")
    lines.append("")
    for model, (k, n) in counts.items():
        if n:
            lines.append(f"- {model} model: the 95 % interval holds the truth for {k} of {n} parameter estimates.")
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="working folder (required but for --footprint-check)")
    ap.add_argument("--calibration", default=None, help="folder with camera.json and lamps.json to reuse")
    ap.add_argument("--scale", type=float, default=0.25)
    ap.add_argument("--leds", default="8,9,10,11")
    ap.add_argument("--rotations", default="-45,0,45,90")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--materials", default="sample_2_6,polyethylene,sanded_original")
    ap.add_argument("--true-calibration", action="store_true",
                    help="also extract with the twin's true camera and lamps and fit that (footprint model)")
    ap.add_argument("--led-aperture", type=float, default=0.0,
                    help="the LEDs' angular diameter for the budget (default 0: the twin's LEDs are points)")
    ap.add_argument("--refit", action="store_true", help="redo the fits (the captures and extractions are kept)")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--footprint-check", metavar="SAMPLES", default=None,
                    help="only the noise-free footprint check on the angles of an extracted table (footprint_check)")
    a = ap.parse_args(argv)
    if a.footprint_check:
        print(footprint_check(Path(a.footprint_check)))
        return {}
    if not a.work:
        ap.error("--work is required")
    if a.report_only:
        res = json.loads((Path(a.work) / "results.json").read_text())
    else:
        res = run(a)
    print(report(res))
    return res


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
