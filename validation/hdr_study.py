"""HDR estimators on the twin: the thesis's regression (eq. 4.39-4.44) against the
inverse-variance fit through the origin (glossrig.core.radiometry.hdr.hdr_ml).

For each material, one rotation and a few LEDs, the virtual rig shoots the thesis
exposure table (Table 4.1, ISO 320, f/11) ``--repeats`` times with the rig's default
LED fluctuations (jitter N(1, 0.005) per frame, 1 % slow drift) exactly as
``glossrig simulate`` does (``VirtualRig.shoot``: DNG files), the pipeline reads them
back (``read_raw`` -> ``stack_frames``, eq. 4.31) and estimates the HDR rate with:

* A  thesis as printed: printed neighbour correction (eq. 4.32-4.38) + printed regression;
* B  printed regression after the fixed (robust) neighbour correction;
* C  glossrig: fixed neighbour correction + hdr_ml (shot and read noise weights);
* D  C with shot-noise weights only (read noise 0): does read-noise weighting matter?
* E  hdr_ml without any neighbour correction: what the correction gains;
* F  C with the upper validity limit 0.9 instead of 0.95: what the top exposure is worth.

Truth per pixel: the noise-free linear value per second, (expected photo-electrons
in 1 s + dark current) / K / (white - black), scaled by the LED output of the
reference (centre) exposure's frames, which the corrected sequence is referenced to
and which patch normalisation later divides out. Pixels are binned into deciles of
the true rate among those the exposure table can measure (an expected value in
[0.002, 0.9] at some exposure). Per bin: median and 95th percentile of the absolute
relative error, the bias (mean relative error) and the failures (thesis 0 / NaN).

    DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 \
    .venv/bin/python validation/hdr_study.py --out validation/hdr_report.md
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

MATERIALS = ["sample_2_6", "transparency_sheet", "lambert:0.8", "ward:rho_d=0.04,rho_s=0,alpha_x=0.1,alpha_y=0.1"]
METHODS = {
    "A": "thesis as printed (printed correction + regression)",
    "B": "thesis regression, fixed correction",
    "C": "glossrig: fixed correction + hdr_ml",
    "D": "hdr_ml, shot-noise weights only",
    "E": "hdr_ml, no neighbour correction",
    "F": "C with upper limit hi = 0.9 instead of 0.95",
}
LO, HI = 0.002, 0.9


def simulate_sequences(rig, material_spec: str, leds, rotation: float, repeats: int, scale: float, seed: int,
                       workdir: Path):
    """Shoot the sequences on the twin; yield (led, stack, truth_rate, ref_gain, shot_gains)."""
    from glossrig.core.radiometry.hdr import stack_frames
    from glossrig.core.models.materials import parse_material
    from glossrig.core.calibration.raw import read_raw
    from glossrig.twin.effects import rig_fluctuations
    from glossrig.twin.sensor import frame_rng
    from glossrig.twin.virtual_rig import VirtualRig

    vr = VirtualRig(rig, parse_material(material_spec), scale=scale, seed=seed, effects=rig_fluctuations(rig))
    vr.set_rotation(rotation)
    times = rig.exposure_times_s
    iso, ap = rig.sequence_iso, rig.sequence_aperture
    s = vr.sensor
    K = s.conversion_gain(iso)
    rng_range = s.white_level - float(np.mean(s.black_level))
    for led in leds:
        vr.switch([led])
        rad = vr.led_radiance(led)
        truth = (s.expected_electrons(rad, 1.0, ap).astype(np.float64) + s.dark_current_e_s) / K / rng_range
        frames, reps, gains = [], [], np.empty((repeats, len(times)))
        for rep in range(repeats):
            for k, t in enumerate(times):
                # the LED gain VirtualRig.shoot will draw: the first draw of this frame's generator
                gains[rep, k] = vr.effects.led_gain(led, vr.clock_s, frame_rng(vr.seed, vr.frame))
                f = workdir / f"{material_spec.split(':')[0]}_led{led}_rep{rep}_e{k:02d}.dng"
                vr.shoot(f, t, iso, ap)
                frames.append(read_raw(f, exposure_s=t, iso=iso, aperture=ap))
                reps.append(rep)
                f.unlink()
        stack = stack_frames(frames, reps, exposures_s=times)
        ref = len(times) // 2
        yield led, stack, truth, float(gains[:, ref].mean()), gains


def estimates(stack, noise):
    from glossrig.core.radiometry.hdr import NoiseModel, hdr_ml, hdr_thesis, neighbour_correct

    t, m, clip = stack.exposure_s, stack.repeats, stack.clipped
    printed, rep_p = neighbour_correct(stack.images, t, clipped=clip, method="thesis")
    fixed, rep_f = neighbour_correct(stack.images, t, clipped=clip, method="robust")
    out = {}
    a = hdr_thesis(printed, t).astype(np.float64)
    out["A"] = (np.where(a == 0, np.nan, a), None)
    b = hdr_thesis(fixed, t).astype(np.float64)
    out["B"] = (np.where(b == 0, np.nan, b), None)
    c = hdr_ml(fixed, t, noise, repeats=m, clipped=clip)
    out["C"] = (c.rate.astype(np.float64), c.variance.astype(np.float64))
    d = hdr_ml(fixed, t, NoiseModel(noise.electrons_full_scale, 0.0), repeats=m, clipped=clip)
    out["D"] = (d.rate.astype(np.float64), None)
    e = hdr_ml(stack.images, t, noise, repeats=m, clipped=clip)
    out["E"] = (e.rate.astype(np.float64), None)
    f = hdr_ml(fixed, t, noise, repeats=m, clipped=clip, hi=0.9)
    out["F"] = (f.rate.astype(np.float64), None)
    return out, rep_p, rep_f, c


def stats(err: np.ndarray) -> tuple[float, float, float, int]:
    ok = np.isfinite(err)
    e = err[ok]
    if e.size == 0:
        return np.nan, np.nan, np.nan, int((~ok).sum())
    return float(np.median(np.abs(e))), float(np.percentile(np.abs(e), 95)), float(np.mean(e)), int((~ok).sum())


def pct(x: float) -> str:
    return "n/a" if not np.isfinite(x) else f"{100 * x:.2f}"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scale", type=float, default=0.1)
    p.add_argument("--leds", default="8,10")
    p.add_argument("--rotation", type=float, default=0.0)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--materials", default=";".join(MATERIALS), help="';'-separated material specs")
    p.add_argument("--out", type=Path, default=None, help="write the Markdown report here")
    args = p.parse_args(argv)

    from glossrig.core.radiometry.hdr import NoiseModel
    from glossrig.core.rig import default_rig_path, load_rig

    rig = load_rig(default_rig_path())
    leds = rig.select_leds(args.leds)
    noise = NoiseModel.from_rig(rig)
    t_lo, t_hi = rig.exposure_times_s[0], rig.exposure_times_s[-1]
    measurable = (LO / t_hi, HI / t_lo)
    t0 = time.time()
    lines: list[str] = []
    pooled = {k: [] for k in METHODS}
    pooled_truth = []
    z_all = []
    corr_lines = []
    for spec in args.materials.split(";"):
        errs = {k: [] for k in METHODS}
        truths = []
        with tempfile.TemporaryDirectory(prefix="hdr_study_") as tmp:
            for led, stack, truth, gref, gains in simulate_sequences(rig, spec, leds, args.rotation, args.repeats,
                                                                     args.scale, args.seed, Path(tmp)):
                est, rep_p, rep_f, c = estimates(stack, noise)
                tr = truth * gref
                sel = (truth >= measurable[0]) & (truth <= measurable[1])
                truths.append(truth[sel])
                for k, (r, _) in est.items():
                    errs[k].append((r / tr - 1.0)[sel])
                zz = ((c.rate - tr) / np.sqrt(c.variance))[sel]
                z_all.append(zz[np.isfinite(zz)])
                # image-wide gain of each combined exposure relative to the reference, before/after correction
                g = gains.mean(axis=0)
                dev_none = np.abs(g / gref - 1)
                done = np.array([k not in rep_f.skipped for k in range(g.size)])
                dev_fixed = np.abs(g * rep_f.factor / gref - 1)[done]
                dev_print = np.abs(g * rep_p.factor / gref - 1)
                corr_lines.append(f"| {spec} | {led} | {100 * np.median(dev_none):.2f} / {100 * dev_none.max():.2f} | "
                                  f"{100 * np.median(dev_fixed):.3f} / {100 * dev_fixed.max():.3f} | "
                                  f"{100 * np.median(dev_print):.2f} / {100 * dev_print.max():.2f} | "
                                  f"{', '.join(str(i) for i in sorted(rep_f.skipped)) or '-'} |")
                print(f"{spec} LED {led}: done ({time.time() - t0:.0f} s)", file=sys.stderr)
        truth_all = np.concatenate(truths)
        err_all = {k: np.concatenate(v) for k, v in errs.items()}
        pooled_truth.append(truth_all)
        for k in METHODS:
            pooled[k].append(err_all[k])
        edges = np.quantile(truth_all, np.linspace(0, 1, 11))
        lines += [f"### {spec}", "",
                  f"{truth_all.size} measurable pixels (LEDs {args.leds}, rotation {args.rotation:g} deg). "
                  "Relative error in %: median |e| / 95th pct |e| / bias (mean e); fail = pixels with no value.", "",
                  "| decile | true rate (1/s) | A thesis as printed | fail | B thesis regr., fixed corr. | fail | "
                  "C glossrig | fail |",
                  "|---|---|---|---|---|---|---|---|"]
        for d in range(10):
            inb = (truth_all >= edges[d]) & ((truth_all < edges[d + 1]) if d < 9 else (truth_all <= edges[d + 1]))
            row = [f"{d + 1}", f"{edges[d]:.3g}-{edges[d + 1]:.3g}"]
            for k in ("A", "B", "C"):
                med, p95, bias, fail = stats(err_all[k][inb])
                row += [f"{pct(med)} / {pct(p95)} / {pct(bias)}", f"{fail}"]
            lines.append("| " + " | ".join(row) + " |")
        lines.append("")
    # summary over all materials
    summary = ["| method | median abs(e) % | 95th pct abs(e) % | bias % | worst decile bias % | fail |", "|---|---|---|---|---|---|"]
    truth_all = np.concatenate(pooled_truth)
    for k, label in METHODS.items():
        e = np.concatenate(pooled[k])
        med, p95, bias, fail = stats(e)
        # worst per-material decile bias
        worst = 0.0
        off = 0
        for tr in pooled_truth:
            ee = e[off:off + tr.size]
            off += tr.size
            edges = np.quantile(tr, np.linspace(0, 1, 11))
            for d in range(10):
                inb = (tr >= edges[d]) & ((tr < edges[d + 1]) if d < 9 else (tr <= edges[d + 1]))
                b = stats(ee[inb])[2]
                if np.isfinite(b) and abs(b) > abs(worst):
                    worst = b
        summary.append(f"| {k}: {label} | {pct(med)} | {pct(p95)} | {pct(bias)} | {pct(worst)} | {fail} |")
    # darkest / brightest decile of every material, pooled
    ends = {}
    for k in METHODS:
        e = np.concatenate(pooled[k])
        lo_e, hi_e, mid_e, off = [], [], [], 0
        for tr in pooled_truth:
            ee = e[off:off + tr.size]
            off += tr.size
            q1, q9 = np.quantile(tr, [0.1, 0.9])
            lo_e.append(ee[tr < q1])
            hi_e.append(ee[tr > q9])
            mid_e.append(ee[(tr >= q1) & (tr <= q9)])
        ends[k] = [stats(np.concatenate(x)) for x in (lo_e, mid_e, hi_e)]

    def cmp(k1, k2, part, i, name):
        a, b = ends[k1][part][i], ends[k2][part][i]
        return f"{name} {pct(a)} % -> {pct(b)} %"

    findings = [
        "## Findings", "",
        f"* Thesis as printed (A) -> glossrig (C), all materials pooled: median |e| "
        f"{pct(stats(np.concatenate(pooled['A']))[0])} % -> {pct(stats(np.concatenate(pooled['C']))[0])} %, "
        f"95th percentile {pct(stats(np.concatenate(pooled['A']))[1])} % -> "
        f"{pct(stats(np.concatenate(pooled['C']))[1])} %.",
        f"* Darkest decile (each material's, pooled), A -> C: {cmp('A', 'C', 0, 0, 'median |e|')}, "
        f"{cmp('A', 'C', 0, 1, '95th pct')}, {cmp('A', 'C', 0, 2, 'bias')}. The printed regression keeps only "
        f"the positive noise of nearly black exposures (0 < SI, after linearisation clipped the negative ones) "
        f"and fits an intercept; the fit through the origin on exposures chosen by expected value does neither.",
        f"* Middle eight deciles, B (printed regression after the fixed correction) -> C: "
        f"{cmp('B', 'C', 1, 0, 'median |e|')}, {cmp('B', 'C', 1, 1, '95th pct')}, {cmp('B', 'C', 1, 2, 'bias')}. "
        f"With this sensor's noise the unweighted fit is not far from efficient once the exposures are well "
        f"exposed; the estimator's gain is at the ends of the range and in the bias.",
        f"* Brightest decile, A -> C: {cmp('A', 'C', 2, 0, 'median |e|')}, {cmp('A', 'C', 2, 2, 'bias')}; the "
        f"thesis returns 0 for pixels with fewer than 4 unclipped exposures (the transparency sheet's highlight), "
        f"hdr_ml measures them.",
        "* The printed eq. 4.36 multiplies the jitter instead of removing it: with it the exposures' gain "
        "errors grow to ~2 % (table below); the fixed factor brings the corrected exposures to a few 0.01 %. "
        "For hdr_ml the correction is worth little (E vs C), because a fit over many exposures averages the "
        "jitter anyway (it still removes a worst-decile bias of ~0.1 %). A vs B isolates the printed correction, "
        "B vs C the regression: the former dominates the median error, the latter the dark-end bias.",
        "* Read-noise weighting (C vs D) changes nothing measurable with the lower limit 0.002: kept for "
        "noisier cameras. The upper limit 0.95 instead of 0.9 (F) keeps the longest unclipped exposure of "
        "more pixels, each doubling of exposure carrying as much information as all shorter ones.",
        "* glossrig's failures are pixels within noise of the measurable floor (expected value 0.002 at 30 s) "
        "whose estimate falls below it: NaN with status TOO_DARK, where the thesis returns a biased number.", ""]
    z = np.concatenate(z_all)
    elapsed = time.time() - t0
    cmd = ("DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1 .venv/bin/python validation/hdr_study.py "
           + " ".join(a for a in (argv if argv is not None else sys.argv[1:])))
    head = [
        "# HDR estimators on the twin (issue 3)", "",
        "Generated by `validation/hdr_study.py` (see its docstring for the set-up):", "",
        f"    {cmd}", "",
        f"Twin: thesis rig, scale {args.scale}, {len(rig.exposure_times_s)} exposures "
        f"{t_lo:g}-{t_hi:g} s at ISO {rig.sequence_iso}, f/{rig.sequence_aperture:g}, {args.repeats} repeats, "
        f"default LED fluctuations (jitter 0.5 % per frame, drift 1 %), seed {args.seed}; frames written as DNG "
        f"by VirtualRig.shoot and read back with read_raw. Noise model from the rig: "
        f"{noise.electrons_full_scale:.0f} e- per white-black range, read sigma {noise.read_sigma:.2e}. "
        f"Measurable rates: {measurable[0]:.3g}-{measurable[1]:.3g} per s. Run time {elapsed:.0f} s.", "",
        "Truth = noise-free rate x the reference exposure's mean LED gain (what patch normalisation divides "
        "out). Errors are relative, e = estimate / truth - 1, over pixels both estimators could measure; "
        "'fail' counts pixels left without a value (thesis: 0, glossrig: NaN with a status).", "",
        "## Summary (all materials pooled)", "", *summary, "", *findings,
        f"Variance estimate of C: the normalised error (C - truth) / sqrt(variance) has standard deviation "
        f"{np.std(z):.2f} and median |z| {np.median(np.abs(z)):.2f} over {z.size} pixels (1.00 and 0.67 if the "
        f"variance were exact; the residual image-wide LED gain of skipped exposures is not in it).", "",
        "## Neighbour correction: image-wide gain error of the 18 combined exposures", "",
        "Median / max over exposures of |gain / reference gain - 1| in %: all 18 exposures before "
        "correction, the exposures the fixed correction corrected, all exposures after the printed "
        "eq. 4.36; last column: exposures the fixed correction left uncorrected for want of 100 "
        "well-exposed pixels (at scale 0.1 the short exposures see too few bright pixels; they only "
        "matter for the brightest pixels).", "",
        "| material | LED | none | fixed | printed eq. 4.36 | skipped |", "|---|---|---|---|---|---|",
        *corr_lines, "",
        "## Per material and brightness decile", "", *lines]
    text = "\n".join(head) + "\n"
    if args.out:
        args.out.write_text(text)
        print(f"wrote {args.out}", file=sys.stderr)
    else:
        print(text)
    return 0


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
