"""Twin confirmation of the rig design and of the exposure plans (issue 8).

    python -m validation.design.twin_study exposures --work /tmp/design_twin25 --scale 0.25 \\
        --materials sample_2_6,brushed_original --seeds 1,2,3
    python -m validation.design.twin_study rigs --work /tmp/design_twin25 --scale 0.25 \\
        --materials sample_2_6 --seeds 1,2
    python -m validation.design.twin_study report --work /tmp/design_twin25 --scale 0.25   # -> twin.md

(`exposures` and `rigs` may run at the same time; scale 0.125 fails the holder-marker
pose refinement, validation/design/README.md section 5.)

Every capture is made by a real `glossrig` command on the twin (thesis LED jitter and
drift, sensor noise, DNGs), then `glossrig extract` against a lambert:0.8 reference
of the same rig and `glossrig fit`; errors are fitted/true - 1 (luminance fit) and the
lobe rotation's error modulo pi. Camera intrinsics and lamp positions are the twin's
truth (written in the pipeline's own camera.json / lamps.json formats), so the
comparisons isolate the design and the exposures; their own recovery is
validation/calibration_report.md and validation/recovery.md. Poses, HDR,
normalisation and fit run as for a real capture.

exposures: the thesis rig's 8 middle LEDs at rotation 0; the thesis's full plan
(`glossrig simulate`: 3 sequences of the 18 exposures of table 4.1) against the plan
of `glossrig design exposures` (run through `glossrig capture` on the twin
backends, planned for the twin's scale: ``--capture-scale``), same seeds (same renders
and LED fluctuation streams).

rigs: the thesis rig as measured (8 middle LEDs, rotations -45/0/45/90; ``thesis``), the
thesis hardware with all 16 LEDs (``thesis16``) and scenes/optimised_rig.toml (16 LEDs, its
rotations; ``optimised``) - ``--rigs`` picks among them - each captured with its
`glossrig design exposures` plan (same noise target) and compared with the Fisher
predictions of `glossrig design errors` at the same scale: independent pixels, and
with each sequence's residual LED gain as a nuisance parameter of the size the
planner predicts for the plan.

Re-running resumes: finished captures, extractions and fits are reused.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from glossrig.core.atomic import atomic_write_text
from glossrig.core.capture import capture_complete, load_manifest, read_truth
from glossrig.core.errors import InputError
from glossrig.core.fitting.export import read_fit_json
from glossrig.core.fitting.fit import parameter_errors
from validation.common import GlossrigFailed, capture, extract, fit, glossrig, needs_capture, truth_camera, truth_lamps
from validation.paths import RIG as THESIS
from validation.paths import ROOT

HERE = Path(__file__).resolve().parent
OPTIMISED = ROOT / "scenes/optimised_rig.toml"
RIGS = {"thesis": (THESIS, "middle"), "thesis16": (THESIS, "all"), "optimised": (OPTIMISED, "all")}
PARAMS = ("rho_d", "rho_s", "alpha_x", "alpha_y")
REF_SEED = 100


def planned_capture(out: Path, rig: Path, material: str, leds: str, rotations: str, scale: float,
                    seed: int) -> tuple[Path, dict]:
    """`glossrig design exposures` for the material, then that plan on the twin backends."""
    plan, report = out.with_suffix(".plan.toml"), out.with_suffix(".plan.json")
    if report.exists():
        kept = check_plan(plan, rig, material, leds, rotations, scale, seed)
        made_with = (load_manifest(out).meta.get("plan") or {}).get("sha256") if capture_complete(out) else None
        if made_with is not None and made_with != kept.text_sha256:
            raise InputError(f"the complete capture here was not made with the plan {plan} (its manifest records "
                             f"plan sha256 {made_with!r}); remove it or choose another --work (nothing was changed)",
                             path=out / "capture.json")
    if not report.exists():
        glossrig("design", "exposures", "--rig", rig, "--material", material, "--leds", leds,
                 f"--rotations={rotations}", "--capture-scale", scale, "--seed", seed, "--out", plan,
                 "--report", report)
    if needs_capture(out):
        # the plan's own [twin] table (material, --capture-scale, --seed) drives the twin
        glossrig("capture", "--plan", plan, "--lights", "twin", "--camera", "twin", "--out", out, "--no-progress")
    return out, json.loads(report.read_text())


def check_plan(plan: Path, rig: Path, material: str, leds: str, rotations: str, scale: float, seed: int):
    """The plan kept in WORK (a :class:`~glossrig.hardware.plan.CapturePlan`), reused only for the
    capture it was made for: its rig, LEDs, rotations and [twin] material, scale and seed must be
    the ones asked for now (a study run again into WORK with another ``--scale``, say), else an
    InputError names the plan file and every difference."""
    from glossrig.core.rig import load_rig
    from glossrig.hardware.plan import load_plan

    p, r = load_plan(plan), load_rig(rig)
    want = {"rig": str(Path(r.path).resolve()), "leds": list(r.select_leds(leds)),
            "rotations": [float(r) for r in rotations.split(",")], "material": material, "scale": float(scale),
            "seed": int(seed)}
    have = {"rig": str(Path(p.rig_path).resolve()), "leds": list(p.leds), "rotations": list(p.rotations),
            "material": p.twin.get("material"), "scale": float(p.twin.get("scale", float("nan"))),
            "seed": p.twin.get("seed")}
    diff = [f"{k}: plan {have[k]!r}, now {want[k]!r}" for k in want if have[k] != want[k]]
    if diff:
        raise InputError(f"the plan kept here was made for another capture ({'; '.join(diff)}); remove it (and its "
                         ".plan.json and capture) or choose another --work (nothing was changed)", path=plan)
    return p


def truth_calibration(capture: Path, work: Path) -> tuple[Path, Path]:
    """camera.json and lamps.json holding the twin's true intrinsics and lamp positions."""
    return truth_camera(capture, work / "camera_truth.json"), truth_lamps(capture, work / "lamps_truth.json")


def extract_fit(capture: Path, ref: Path, cam: Path, lamps: Path) -> dict:
    """Fitted luminance parameters and their errors against the truth."""
    sp = extract(capture, ref, cam, lamps, capture.with_suffix(".parquet"))
    fj = fit(sp, capture.with_suffix(".fit.json"), "--channels", "luminance")
    p = read_fit_json(fj).fits["luminance"].params
    f = {k: getattr(p, k) for k in (*PARAMS, "lobe_rotation")}
    t = read_truth(capture)["material"]["ward"]
    err = parameter_errors(f, t)
    return {"fit": f, "error": err}


def try_extract_fit(capture: Path, ref: Path, cam: Path, lamps: Path) -> dict:
    """:func:`extract_fit`, with a failure recorded (and the reason kept) instead of ending the study."""
    try:
        return extract_fit(capture, ref, cam, lamps)
    except GlossrigFailed as e:
        return {"failed": f"{e.verb} exited with {e.returncode} (its message is in the study's log)"}


def capture_minutes(capture: Path) -> float:
    """The capture's simulated wall time (exposures + the per-shot overhead) from the manifest."""
    from datetime import datetime

    ims = load_manifest(capture).images
    t = sorted(datetime.fromisoformat(i.time) for i in ims)
    last = max(ims, key=lambda i: datetime.fromisoformat(i.time))
    from glossrig.hardware.plan import THESIS_OVERHEAD_S
    return ((t[-1] - t[0]).total_seconds() + last.exposure_s + THESIS_OVERHEAD_S) / 60.0


def save(work: Path, key: str, entry) -> None:
    """Add one entry to work/results.json (under a lock: `exposures` and `rigs` may run at once)."""
    import fcntl

    p = work / "results.json"
    with open(work / "results.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        d = json.loads(p.read_text()) if p.exists() else {}
        d[key] = entry
        atomic_write_text(p, json.dumps(d, indent=1))


def run_exposures(a) -> None:
    work = Path(a.work) / "exposures"
    work.mkdir(parents=True, exist_ok=True)
    ref = capture(work / "reference", "lambert:0.8", a.scale, REF_SEED, "0", 1, leds="middle", rig=THESIS)
    cam, lamps = truth_calibration(ref, work)
    for m in a.materials.split(","):
        for s in map(int, a.seeds.split(",")):
            full = capture(work / f"{m}_s{s}_full", m, a.scale, s, "0", 3, leds="middle", rig=THESIS)
            res_full = try_extract_fit(full, ref, cam, lamps)
            plan, rep = planned_capture(work / f"{m}_s{s}_plan", THESIS, m, "middle", "0", a.scale, s)
            res_plan = try_extract_fit(plan, ref, cam, lamps)
            save(Path(a.work), f"exposures/{m}/{s}", {
                "full": {**res_full, "minutes": capture_minutes(full), "images": len(list(full.glob("*.dng")))},
                "plan": {**res_plan, "minutes": capture_minutes(plan), "images": len(list(plan.glob("*.dng"))),
                         "exposures": {str(e["led"]): e["exposures_s"] for e in rep["leds"]},
                         "time_s_per_rotation": rep["time_s_per_rotation"]}})
            print(f"[twin_study] exposures {m} seed {s} done", flush=True)


def run_rigs(a) -> None:
    """Material by material and seed by seed, both rigs in turn (a partial run compares like with like)."""
    from glossrig.core.rig import load_rig

    setup = {}
    for name in a.rigs.split(","):
        if name not in RIGS:
            raise SystemExit(f"--rigs: unknown rig {name!r} (have {', '.join(RIGS)})")
        rig, leds = RIGS[name]
        work = Path(a.work) / "rigs" / name
        work.mkdir(parents=True, exist_ok=True)
        rots = ",".join(f"{r:g}" for r in load_rig(rig).sample_rotations)
        setup[name] = (rig, leds, rots, work)
    for m in a.materials.split(","):
        for s in map(int, a.seeds.split(",")):
            for name, (rig, leds, rots, work) in setup.items():
                ref, _ = planned_capture(work / "reference", rig, "lambert:0.8", leds, rots, a.scale, REF_SEED)
                cam, lamps = truth_calibration(ref, work)
                cap, rep = planned_capture(work / f"{m}_s{s}", rig, m, leds, rots, a.scale, s)
                res = try_extract_fit(cap, ref, cam, lamps)
                res["minutes"] = capture_minutes(cap)
                fisher = work / f"{m}.fisher.json"
                if not fisher.exists():
                    glossrig("design", "errors", "--rig", rig, "--materials", m, "--leds", leds, "--scale", a.scale,
                             "--out", fisher)
                res["fisher_relative"] = json.loads(fisher.read_text())["expected_errors"][m]["relative"]
                # the same with each sequence's residual LED gain as a nuisance parameter, of the size the
                # exposure planner predicts for this plan (RMS over LEDs of its pixel-weighted RMS)
                g = math.sqrt(np.mean([e["gain_noise_rms"] ** 2 for e in rep["leds"]]))
                fisher_g = work / f"{m}_s{s}.fisher_gain.json"
                if not fisher_g.exists():
                    glossrig("design", "errors", "--rig", rig, "--materials", m, "--leds", leds, "--scale", a.scale,
                             "--noise", "hdr:0", "--gain-noise", g, "--out", fisher_g)
                res["gain_noise"] = g
                res["fisher_gain_relative"] = json.loads(fisher_g.read_text())["expected_errors"][m]["relative"]
                save(Path(a.work), f"rigs/{name}/{m}/{s}", res)
                print(f"[twin_study] rigs {name} {m} seed {s} done", flush=True)


def rms(xs) -> float:
    xs = [x for x in xs if x is not None and math.isfinite(x)]
    return math.sqrt(sum(x * x for x in xs) / len(xs)) if xs else math.nan


def report(a) -> str:
    d = json.loads((Path(a.work) / "results.json").read_text())
    cols = (*PARAMS, "lobe_rotation_deg")

    def fmt(k, v):
        return f"{v:.2f}" if k == "lobe_rotation_deg" else f"{100 * v:+.2f} %"

    lines = ["# Twin confirmation of the design and the exposure plans (issue 8)", "",
             f"Commands: `python -m validation.design.twin_study exposures|rigs --work {a.work} --scale {a.scale} "
             "--materials ... --seeds ...`, then `... report --work ...` (this file). Truth intrinsics and lamp "
             "positions (the design is compared, not the calibration); thesis LED jitter and drift and sensor "
             "noise on; luminance fit; errors fitted/true - 1, lobe rotation in degrees modulo pi.", ""]
    ex = {k.split("/", 1)[1]: v for k, v in d.items() if k.startswith("exposures/")}
    if ex:
        lines += ["## Exposure plan against the thesis's full plan (thesis rig, 8 middle LEDs, rotation 0)", "",
                  "The twin's canvas (sub-pixels per output pixel edge, truth.json `supersample`) is listed: "
                  "the twin moved from 2 to 4 while the study ran; plan and full plan of a seed are compared "
                  "on the same canvas; the reference capture they are normalised by is one for all.", "",
                  "| material | seed | plan | images | capture (min) | canvas | " + " | ".join(cols) + " |",
                  "|---|---|---|---|---|---|" + "---|" * len(cols)]
        for key, v in sorted(ex.items()):
            m, s = key.split("/")
            for which in ("full", "plan"):
                e = v[which]
                truth = Path(a.work) / "exposures" / f"{m}_s{s}_{which}" / "truth.json"
                canvas = read_truth(truth).get("supersample", "?") if truth.exists() else "?"
                lines.append(f"| {m} | {s} | {which} | {e['images']} | {e['minutes']:.1f} | {canvas} | "
                             + (" | ".join(fmt(k, e["error"][k]) for k in cols) if "error" in e else
                                f"failed: {e['failed']} |" + " |" * (len(cols) - 1)) + " |")
        ex = {k: v for k, v in ex.items() if "error" in v["full"] and "error" in v["plan"]}
        lines += ["", f"RMS over the {len(ex)} material/seed pairs where both captures were extracted:", "",
                  "| plan | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]
        for which in ("full", "plan"):
            lines.append(f"| {which} | " + " | ".join(
                (f"{rms([v[which]['error'][k] for v in ex.values()]):.2f}" if k == "lobe_rotation_deg" else
                 f"{100 * rms([v[which]['error'][k] for v in ex.values()]):.2f} %") for k in cols) + " |")
        lines += ["", "Plan minus full plan, paired by material and seed (same renders and LED streams): mean and "
                  "largest absolute difference, against the seed scatter of each plan (standard deviation over "
                  "seeds within a material, pooled over materials: the random part of its errors):", "",
                  "| | " + " | ".join(cols) + " |", "|---|" + "---|" * len(cols)]

        def unit(k, x):
            return f"{x:.3f}" if k == "lobe_rotation_deg" else f"{100 * x:.3f} %"

        diff = {k: [v["plan"]["error"][k] - v["full"]["error"][k] for v in ex.values()] for k in cols}
        def pooled_sd(which):
            by_m: dict = {}
            for key, v in ex.items():
                by_m.setdefault(key.split("/")[0], []).append(v[which]["error"])
            out = {}
            for k in cols:
                ss = [(len(es) - 1, float(np.var([e[k] for e in es], ddof=1))) for es in by_m.values() if len(es) > 1]
                out[k] = math.sqrt(sum(n * x for n, x in ss) / sum(n for n, _ in ss)) if ss else math.nan
            return out

        lines.append("| mean (plan - full) | " + " | ".join(unit(k, float(np.mean(diff[k]))) for k in cols) + " |")
        lines.append("| largest abs(plan - full) | " + " | ".join(unit(k, float(np.max(np.abs(diff[k])))) for k in cols)
                     + " |")
        for which in ("full", "plan"):
            sd = pooled_sd(which)
            lines.append(f"| seed scatter, {which} | " + " | ".join(unit(k, sd[k]) for k in cols) + " |")
        lines.append("")
    rg = {k.split("/", 1)[1]: v for k, v in d.items() if k.startswith("rigs/")}
    if rg:
        lines += ["## The thesis rig (8 middle LEDs: `thesis`; all 16: `thesis16`) against the optimised 16-LED rig", "",
                  "Per rig and material: RMS over seeds of the recovered errors (Monte Carlo), their scatter "
                  "between seeds (standard deviation, the random part) and the Fisher predictions (relative "
                  "standard error, same scale): `indep.` with independent pixels (sensor noise + 1 % LED "
                  "fluctuation per pixel, `glossrig design errors`), `gain` with sensor noise per pixel and one "
                  "residual LED gain per (LED, rotation) sequence as a nuisance parameter (`--noise hdr:0 "
                  "--gain-noise G`, G the exposure planner's predicted RMS frame-gain error of the capture's plan).",
                  "",
                  "| rig | material | seeds | capture (min) | " + " | ".join(cols) + " | scatter " +
                  " | scatter ".join(PARAMS) + " | indep. " + " | indep. ".join(PARAMS) + " | G | gain " +
                  " | gain ".join(PARAMS) + " |",
                  "|---|---|---|---|" + "---|" * (len(cols) + 3 * len(PARAMS) + 1)]
        groups: dict = {}
        failed = [k for k, v in rg.items() if "error" not in v]
        for key, v in rg.items():
            rig, m, s = key.split("/")
            if "error" in v:
                groups.setdefault((rig, m), []).append(v)
        for (rig, m), vs in sorted(groups.items(), key=lambda kv: (kv[0][1], kv[0][0])):
            errs = " | ".join((f"{rms([v['error'][k] for v in vs]):.2f}" if k == "lobe_rotation_deg"
                               else f"{100 * rms([v['error'][k] for v in vs]):.2f} %") for k in cols)
            fis = " | ".join(f"{100 * vs[0]['fisher_relative'][k]:.3f} %" for k in PARAMS)
            if all("fisher_gain_relative" in v for v in vs):
                fis += f" | {100 * rms([v['gain_noise'] for v in vs]):.3f} % | " + " | ".join(
                    f"{100 * rms([v['fisher_gain_relative'][k] for v in vs]):.3f} %" for k in PARAMS)
            else:
                fis += " | - |" + " - |" * (len(PARAMS) - 1) + " -"
            sc = " | ".join((f"{100 * np.std([v['error'][k] for v in vs], ddof=1):.3f} %" if len(vs) > 1 else "-")
                            for k in PARAMS)
            lines.append(f"| {rig} | {m} | {len(vs)} | {np.mean([v['minutes'] for v in vs]):.1f} | {errs} | {sc} | "
                         f"{fis} |")
        lines += ["", f"Extraction failed for: {', '.join(failed) if failed else 'none'}.", ""]
    text = "\n".join(lines)
    Path(a.out).write_text(text)
    print(text)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("exposures", "rigs", "report"))
    ap.add_argument("--work", required=True)
    ap.add_argument("--scale", type=float, default=0.125)
    ap.add_argument("--materials", default="sample_2_6,brushed_original")
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--rigs", default="thesis,optimised", help=f"rigs to capture, of {', '.join(RIGS)}")
    ap.add_argument("--out", default=str(HERE / "twin.md"))
    a = ap.parse_args()
    {"exposures": run_exposures, "rigs": run_rigs, "report": report}[a.what](a)


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
