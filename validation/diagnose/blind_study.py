"""Blind study of glossrig diagnose (issue 7): hidden causes at seeded random magnitudes.

    nice -n 5 python -m validation.diagnose.blind_study --work /tmp/blind --trials 55

Calibration (first run, in WORK/calibration, unless --camera, --lamps and --reference
name one of the nominal rig at scale 0.25): camera and lamps by
``validation.common.calibrate`` (12 checkerboard views, seed 1; a
transparency-sheet capture of LEDs 6 and 9, seed 2) and a lambert:0.8 reference capture
(LEDs 6 and 9, rotation 0, seed 3), all ``--ideal`` like the trials; reused by every
trial, the reference measured once. Set-up (first run): one null sample_2_6
capture (seed 999) whose Ward fit becomes the material fit passed as --fit to every
trial (a fit from another capture of the material, so a rotation offset is testable),
and whose DNGs are rewritten outside the twin for black_level_offset and
sensor_nonlinearity (glossrig.twin.rewrite_raw), and whose geometric calibration
(holder and cylinder poses) is reused by every trial. Trial k: cause ``CAUSES[k mod 11]``
(or none) at a magnitude drawn from its seed, hidden in a sample_2_6 capture (LEDs 6,
9, rotation 0, scale 0.25, --ideal, seed 1000 + k) by the twin's ``--effects`` or by
rewriting; then diagnose runs blind. Budget per trial (2 cores shared by four
engineers): BRDF rows capped at ``ROWS``, frame pixels at ``PIXELS``, rows of the
geometry causes' non-linear fits at ``FIT_ROWS``. Resumable: finished trials are kept in
WORK/trials.json; rerunning continues. After the trials, --nulls independent null captures
(seeds 5000+, WORK/nulls.json) measure each cause's null spread and null reading apart
from the trials. Each trial records the commit (and whether
core/ or twin/ had uncommitted changes) its capture and its diagnosis ran with. Writes
validation/diagnose/blind_study.md.
"""
from __future__ import annotations

import argparse
import json
import math
import shutil
import time
from datetime import datetime
from pathlib import Path

import numpy as np

from glossrig.core.capture import load_manifest, read_truth
from glossrig.core.diagnose.report import read_report
from validation.common import calibrate, capture
from validation.provenance import code_version

OUT = Path(__file__).parent / "blind_study.md"
LEDS = (6, 9)
ROWS, PIXELS, FIT_ROWS = 12_000, 3_000, 3_000
# cause -> (low, high) of the drawn magnitude (the twin catalogue's unit), how it is hidden
CAUSES = {"none": (0, 0, "twin"), "black_level_offset": (3, 15, "rewrite"),
          "sensor_nonlinearity": (0.01, 0.05, "rewrite"), "stray_light": (0.002, 0.01, "twin"),
          "vignetting": (0.1, 0.3, "twin"), "hot_pixels": (1e-4, 1e-3, "twin"), "led_drift": (0.01, 0.05, "twin"),
          "led_emission": (5.0, 30.0, "twin"), "led_position_error": (1.0, 4.0, "twin"),
          "sample_radius_error": (0.2, 1.0, "twin"), "sample_rotation_offset": (1.0, 5.0, "twin")}
SIGNED = {"sample_radius_error", "sample_rotation_offset"}
NULL_SEED = 5000      # independent null captures: seeds 5000 + j (trials use 1000 + k, the fit 999)


def simulate(out: Path, seed: int, effects: str | None = None):
    """A fresh sample_2_6 capture (LEDS, rotation 0, scale 0.25, --ideal), output captured."""
    capture(out, "sample_2_6", 0.25, seed, "0", 1, leds=",".join(map(str, LEDS)),
            extra=("--ideal", *(["--effects", effects] if effects else [])), mode="fresh", stdout=False, stderr=False)


def calibration(work: Path, a) -> tuple[str, str, str]:
    """Camera, lamps and reference: the given ones, or the study's own calibration of the
    nominal rig in WORK/calibration (resumable)."""
    given = [a.camera, a.lamps, a.reference]
    if all(given):
        return a.camera, a.lamps, a.reference
    if any(given):
        raise SystemExit("give all of --camera, --lamps and --reference, or none")
    out = work / "calibration"
    out.mkdir(parents=True, exist_ok=True)
    leds = ",".join(map(str, LEDS))
    cam, lamps = calibrate(out, 0.25, 1, leds=leds, extra=("--ideal",))
    ref = capture(out / "reference", "lambert:0.8", 0.25, 3, "0", 1, leds=leds, extra=("--ideal",))
    return str(cam), str(lamps), str(ref)


def setup(work: Path, a):
    """The shared null capture and its material fit."""
    null = work / "null_base"
    fit = work / "fit.json"
    if not fit.exists():
        from glossrig.core.diagnose.data import load_brdf
        from glossrig.core.fitting.fit import fit_samples
        from glossrig.core.calibration.intrinsics import load_camera
        from glossrig.core.calibration.lamps import load_lamps

        simulate(null, 999)
        d = load_brdf(null, a.reference, load_camera(a.camera), load_lamps(a.lamps))
        w = fit_samples(d.table, channels=["luminance"]).fits["luminance"].params
        fit.write_text(json.dumps({"luminance": w.as_dict(), "source": str(null)}))
    return null, fit


def one_calibration(null: Path, camera):
    """Every trial's capture is measured with the null capture's geometric calibration
    (holder and cylinder poses; the same camera and rig in every trial), computed once:
    the pose refinement is ~40 s a capture, more than the rest of a trial's diagnosis."""
    import glossrig.core.calibration.poses as poses

    original = poses.calibrate_capture
    cache = {}

    def calibrate_capture(capture_dir, camera_json, rotation=None, **kw):
        key = (str(camera_json), rotation)
        if key not in cache:
            cache[key] = original(null, camera_json, rotation=rotation, **kw)
        return cache[key]

    poses.calibrate_capture = calibrate_capture


def true_magnitude(cause: str, value: float, cap: Path) -> float:
    """The hidden magnitude in the unit diagnose reports it in."""
    if cause == "black_level_offset":   # raw files hold integers: a rewrite adds round(value) DN
        return float(round(value))
    t = read_truth(cap) if (cap / "truth.json").exists() else {}
    if cause == "led_position_error":
        off = t["effects"]["detail"]["led_offset_mm"]
        return float(np.sqrt(np.mean([np.square(off[str(k)]) for k in LEDS])))
    if cause == "led_drift":   # largest |gain slope| (1/min) at the middle of an LED's sequence
        det = t["effects"]["detail"]
        man = load_manifest(cap)
        t0 = datetime.fromisoformat(t["clock_start"])
        out = []
        for k in LEDS:
            ts = [(datetime.fromisoformat(im.time) - t0).total_seconds() for im in man.images
                  if im.role == "sequence" and im.leds == [k]]
            tm = 0.5 * (min(ts) + max(ts))
            P, ph = det["drift_period_s"][str(k)], det["drift_phase"][str(k)]
            out.append(abs(value * 2 * math.pi / P * 60 * math.cos(2 * math.pi * tm / P + ph)))
        return float(max(out))
    return value


def run_diagnose(cap: Path, out: Path, a, fit: Path, ref) -> dict:
    """glossrig diagnose on one capture with the study's budget; a capture the pipeline
    refuses is a failed trial, kept as such."""
    import glossrig.core.diagnose.catalogue as catalogue
    import glossrig.core.diagnose.frames as frames
    import glossrig.core.diagnose.geometry as geometry
    from glossrig.core.diagnose import diagnose
    from glossrig.core.errors import InputError

    catalogue.MAX_BRDF_ROWS, frames.MAX_PIXELS, geometry.FIT_ROWS = ROWS, PIXELS, FIT_ROWS
    try:
        return diagnose(cap, a.reference, a.camera, a.lamps, out, fit=fit, log=lambda *x: None,
                        reference_measured=ref, plots=False)
    except InputError as e:
        return {"verdict": "refused", "causes": [], "error": str(e)}


def null_capture(j: int, work: Path, a, fit: Path, ref) -> dict:
    """Independent null capture j (seed NULL_SEED + j, no trial's seed): the null spread of
    every cause's gain and fitted magnitude, measured apart from the trials."""
    cap = work / f"n{j:02d}"
    t0 = time.time()
    code = {"capture": code_version(), "diagnose": a.diagnose_code}
    simulate(cap, NULL_SEED + j)
    rep = run_diagnose(cap, work / f"n{j:02d}_report", a, fit, ref)
    for f in cap.glob("*.dng"):
        f.unlink()
    return {"null": j, "seed": NULL_SEED + j, "verdict": rep["verdict"], "time_s": time.time() - t0, "code": code,
            "causes": {c["name"]: {"gain": c["gain"], "magnitude": c["magnitude"], "significant": c["significant"],
                                   "threshold": c["threshold"]} for c in rep["causes"]}}


def trial(k: int, work: Path, a, null: Path, fit: Path, ref) -> dict:
    rng = np.random.default_rng([2026, k])
    names = list(CAUSES)
    cause = names[k % len(names)]
    lo, hi, how = CAUSES[cause]
    value = float(rng.uniform(lo, hi)) if cause != "none" else 0.0
    if cause in SIGNED and rng.random() < 0.5:
        value = -value
    cap = work / f"t{k:03d}"
    t0 = time.time()
    code = {"capture": code_version(), "diagnose": a.diagnose_code}
    if how == "rewrite":
        from glossrig.twin.rewrite_raw import rewrite_capture

        if cap.exists():
            shutil.rmtree(cap)
        rewrite_capture(null, cap, cause, value)
    else:
        simulate(cap, 1000 + k, f"{cause}={value:.6g}" if cause != "none" else None)
    rep = run_diagnose(cap, work / f"t{k:03d}_report", a, fit, ref)
    c = next((c for c in rep["causes"] if c["name"] == cause), None)
    res = {"trial": k, "truth": cause, "value": value, "true_magnitude": true_magnitude(cause, value, cap),
           "verdict": rep["verdict"], "estimate": c["magnitude"] if c else None,
           "gain": c["gain"] if c else None, "significant": c["significant"] if c else None,
           "top": [(x["name"], round(x["gain"], 4), x["significant"]) for x in rep["causes"][:4]],
           "time_s": time.time() - t0, "code": code, **({"error": rep["error"]} if "error" in rep else {})}
    if how != "rewrite":
        for f in cap.glob("*.dng"):          # keep truth and manifest, drop the raw files
            f.unlink()
    return res


def gain_table(trials: list[dict], work: Path | None) -> list[str]:
    """Per cause: the held-out gain its model reaches on null captures (the null spread) and on
    the trials hiding it, against its threshold - the measurement behind every miss."""
    if work is None:
        return []
    reps = {}
    for t in trials:
        f = work / f"t{t['trial']:03d}_report" / "report.json"
        if f.exists():
            reps[t["trial"]] = {c["name"]: c for c in read_report(f)["causes"]}
    if not reps:
        return []
    for t in trials:
        if t["truth"] != "none" and (work / f"t{t['trial']:03d}").exists():
            t["true_magnitude"] = true_magnitude(t["truth"], t["value"], work / f"t{t['trial']:03d}")
    nulls = [reps[t["trial"]] for t in trials if t["truth"] == "none" and t["trial"] in reps]
    ind = json.loads((work / "nulls.json").read_text()) if (work / "nulls.json").exists() else []
    L = ["", "## Gains: null spread against the hidden cause", "",
         "Held-out relative gain of each cause's model on the null captures (max; the study's null trials and, "
         f"apart, {len(ind)} independent null captures of seeds {NULL_SEED}+) and on the trials that hide "
         "it (min / median / max), with its significance threshold (space threshold + penalty x extra "
         "parameters) and how often it was significant when hidden; the magnitude each cause's model fits on "
         "the independent nulls (mean +- sd: what it reads where nothing is hidden).", "",
         "| cause | threshold | null max | independent null max | hidden min | hidden median | hidden max "
         "| significant when hidden | magnitude error median (max) | magnitude on nulls |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for name in [n for n in CAUSES if n != "none"]:
        hid = [reps[t["trial"]][name] for t in trials if t["truth"] == name and t["trial"] in reps
               and name in reps[t["trial"]]]
        nul = [r[name]["gain"] for r in nulls if name in r]
        if not hid:
            continue
        g = [c["gain"] for c in hid]
        thr = max(c["threshold"] for c in hid)
        rel = [abs(t["estimate"] - t["true_magnitude"]) / abs(t["true_magnitude"]) for t in trials
               if t["truth"] == name and t["estimate"] is not None and t["true_magnitude"]]
        merr = f"{float(np.median(rel)):.1%} ({max(rel):.1%})" if rel else "-"
        nmax = f"{max(nul):.3%}" if nul else "-"
        ig = [n["causes"][name]["gain"] for n in ind if name in n["causes"]]
        imax = f"{max(ig):.3%}" if ig else "-"
        im = [n["causes"][name]["magnitude"] for n in ind if name in n["causes"]]
        im = [x for x in im if isinstance(x, (int, float))]
        imag = f"{np.mean(im):.3g} +- {np.std(im, ddof=1):.2g}" if len(im) > 1 else "-"
        L.append(f"| {name} | {thr:.3%} | {nmax} | {imax} | {min(g):.3%} | {float(np.median(g)):.3%} | {max(g):.3%} | "
                 f"{sum(c['significant'] for c in hid)}/{len(hid)} | {merr} | {imag} |")
    if ind:
        fa = [n for n in ind if n["verdict"] != "none"]
        L += ["", f"Independent null captures: {len(fa)} of {len(ind)} gave a cause ("
              + (", ".join(f"seed {n['seed']}: {n['verdict']}" for n in fa) or "all 'none'") + ")."]
    return L


def provenance(trials: list[dict]) -> str:
    """Which code the captures and diagnoses ran with (trials.json records it per trial)."""
    def fmt(key):
        seen = {}
        for t in trials:
            c = t.get("code", {}).get(key)
            label = "unrecorded" if c is None else c["commit"] + (" + uncommitted core/twin changes" if c["dirty"] else "")
            seen.setdefault(label, []).append(t["trial"])
        return "; ".join(f"{lab} ({len(ks)} trials, {min(ks)}-{max(ks)})" for lab, ks in seen.items())
    return f"Code: captures at {fmt('capture')}; diagnoses at {fmt('diagnose')}."


def summarise(trials: list[dict], work: Path | None = None) -> str:
    gains = gain_table(trials, work)       # also refreshes the hidden magnitudes from the captures
    names = list(CAUSES)
    verdicts = names + sorted({t["verdict"] for t in trials} - set(names))
    M = {(t, v): 0 for t in names for v in verdicts}
    for t in trials:
        M[(t["truth"], t["verdict"])] += 1
    acc = np.mean([t["truth"] == t["verdict"] for t in trials]) if trials else float("nan")
    nulls = [t for t in trials if t["truth"] == "none"]
    fa = np.mean([t["verdict"] != "none" for t in nulls]) if nulls else float("nan")
    L = ["# diagnose blind study", "",
         "Regenerate everything - calibration, trials, independent null captures, this file (resumable; on the "
         "shared 2-core machine calibration took ~3 min, a trial 16-62 s, an independent null 2-3 min):", "",
         "    nice -n 5 python -m validation.diagnose.blind_study --work /tmp/blind --trials 55", "",
         f"Set-up: sample_2_6 on the thesis rig, LEDs {LEDS}, rotation 0, scale 0.25, `--ideal`; one nominal "
         "camera/lamp calibration and lambert:0.8 reference for all trials (the study's own, WORK/calibration, unless "
         "given); material fit from one null capture "
         "(--fit), whose poses are reused by every trial; black offset and non-linearity rewritten into that "
         "capture's DNGs outside the twin. "
         f"Budget: BRDF rows <= {ROWS}, frame pixels <= {PIXELS}, geometry-fit rows <= {FIT_ROWS}.", "",
         provenance(trials), "",
         f"trials completed: {len(trials)}  ", f"top-1 accuracy: {acc:.1%}  ",
         f"false-alarm rate (null captures): {fa:.1%} of {len(nulls)} (targets: >= 90 %, <= 5 %)", "",
         "## Confusion matrix (rows: hidden cause, columns: verdict)", "",
         "truth \\ verdict | " + " | ".join(verdicts), "|".join(["---"] * (len(verdicts) + 1))]
    for t in names:
        L.append(f"{t} | " + " | ".join(str(M[(t, v)]) for v in verdicts))
    L += ["", "## Magnitudes (hidden vs recovered by the true cause's model)", "",
          "| trial | cause | hidden | recovered | gain of true cause | verdict | top causes (gain) |",
          "|---|---|---|---|---|---|---|"]
    for t in sorted(trials, key=lambda t: (t["truth"], t["trial"])):
        est = "" if t["estimate"] is None else f"{t['estimate']:.4g}"
        g = "" if t["gain"] is None else f"{t['gain']:.2%}"
        top = ", ".join(f"{n} {gg:.1%}{'*' if s else ''}" for n, gg, s in t["top"])
        L.append(f"| {t['trial']} | {t['truth']} | {t['true_magnitude']:.4g} | {est} | {g} | {t['verdict']} | {top} |")
    L += ["", "`*` = significant (held-out gain above threshold + penalty in every fold)."]
    L += gains
    return "\n".join(L) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--trials", type=int, default=55)
    ap.add_argument("--camera", help="camera.json of the nominal rig at scale 0.25 (default: the study's own)")
    ap.add_argument("--lamps", help="lamps.json of the same calibration")
    ap.add_argument("--reference", help="lambert:0.8 reference capture (LEDs 6 and 9 at rotation 0 or a superset)")
    ap.add_argument("--nulls", type=int, default=6, help="independent null captures after the trials")
    ap.add_argument("--summary-only", action="store_true", help="rewrite the Markdown from WORK/trials.json")
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    store = work / "trials.json"
    done = json.loads(store.read_text()) if store.exists() else []
    if not a.summary_only:
        # import every diagnosis module now: the study runs for an hour and must use one version
        import glossrig.core.diagnose.geometry  # noqa: F401
        import glossrig.core.diagnose.material_models  # noqa: F401
        from glossrig.core.extraction.extract import measure_capture
        from glossrig.core.calibration.intrinsics import load_camera
        from glossrig.core.calibration.lamps import load_lamps

        a.camera, a.lamps, a.reference = calibration(work, a)
        a.diagnose_code = code_version()      # the diagnosis modules are imported once, now
        null, fit = setup(work, a)
        ref = measure_capture(a.reference, load_camera(a.camera), load_lamps(a.lamps))
        one_calibration(null, a.camera)
        have = {t["trial"] for t in done}
        for k in range(a.trials):
            if k in have:
                continue
            done.append(trial(k, work, a, null, fit, ref))
            store.write_text(json.dumps(done, indent=1))
            OUT.write_text(summarise(done, work))
            print(json.dumps(done[-1]), flush=True)
        nstore = work / "nulls.json"
        nulls = json.loads(nstore.read_text()) if nstore.exists() else []
        for j in range(a.nulls):
            if j in {n["null"] for n in nulls}:
                continue
            nulls.append(null_capture(j, work, a, fit, ref))
            nstore.write_text(json.dumps(nulls, indent=1))
            print(json.dumps({k: v for k, v in nulls[-1].items() if k != "causes"}), flush=True)
    OUT.write_text(summarise(done, work))


if __name__ == "__main__":
    main()
