"""Blind study of glossrig diagnose (issue 7): hidden causes at seeded random magnitudes.

    python validation/diagnose/blind_study.py --work /tmp/blind --trials 50 \
        --camera camera.json --lamps lamps.json --reference REF_DIR

Each trial draws a cause (or none) and a magnitude from its seed, makes a sample_2_6
capture (LEDs 6,9, rotation 0, scale 0.25): twin effects through `glossrig simulate
--effects`, black_level_offset and sensor_nonlinearity by rewriting the DNGs of a null
capture (glossrig.core.diagnose.hide), then runs `glossrig diagnose` blind. Resumable:
every finished trial is kept in WORK/trials.json; rerunning continues. Writes the
confusion matrix, top-1 accuracy and false-alarm rate to validation/diagnose/blind_study.md.
"""
from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
RIG = ROOT / "scenes/thesis_rig.toml"
# cause -> (low, high) of the drawn magnitude, and how it is hidden
CAUSES = {"none": (0, 0, "twin"), "black_level_offset": (4, 15, "rewrite"),
          "sensor_nonlinearity": (0.02, 0.05, "rewrite"), "stray_light": (0.002, 0.006, "twin"),
          "vignetting": (0.1, 0.3, "twin"), "hot_pixels": (2e-4, 1e-3, "twin"), "led_drift": (0.02, 0.08, "twin")}


def glossrig(*args):
    subprocess.run([sys.executable, "-m", "glossrig.cli.main", *map(str, args)], check=True, capture_output=True)


def trial(k: int, work: Path, a) -> dict:
    rng = np.random.default_rng([2026, k])
    names = list(CAUSES)
    cause = names[k % len(names)]
    lo, hi, how = CAUSES[cause]
    value = float(rng.uniform(lo, hi)) if cause != "none" else 0.0
    cap = work / f"t{k:03d}"
    sim = ["simulate", "--rig", RIG, "--material", "sample_2_6", "--leds", "6,9", "--rotations", 0, "--repeats", 1,
           "--scale", 0.25, "--seed", 1000 + k, "--ideal", "--no-progress"]
    if cap.exists():
        import shutil

        shutil.rmtree(cap)
    if how == "twin" and cause != "none":
        glossrig(*sim, "--effects", f"{cause}={value:.6g}", "--out", cap)
    elif how == "twin":
        glossrig(*sim, "--out", cap)
    else:
        from glossrig.core.diagnose.hide import rewrite_capture

        glossrig(*sim, "--out", work / f"t{k:03d}_null")
        rewrite_capture(work / f"t{k:03d}_null", cap, cause, value)
    rep_dir = work / f"t{k:03d}_report"
    glossrig("diagnose", cap, "--reference", a.reference, "--camera", a.camera, "--lamps", a.lamps,
             "--out", rep_dir, "--no-progress")
    rep = json.loads((rep_dir / "report.json").read_text())
    top = next((c for c in rep["causes"] if c["name"] == cause), None)
    return {"trial": k, "truth": cause, "value": value, "verdict": rep["verdict"],
            "estimate": top["magnitude"] if top else None}


def summarise(trials: list[dict]) -> str:
    names = list(CAUSES)
    verdicts = sorted({t["verdict"] for t in trials} | set(names))
    M = {(t, v): 0 for t in names for v in verdicts}
    for t in trials:
        M[(t["truth"], t["verdict"])] += 1
    acc = np.mean([t["truth"] == t["verdict"] for t in trials]) if trials else float("nan")
    nulls = [t for t in trials if t["truth"] == "none"]
    fa = np.mean([t["verdict"] != "none" for t in nulls]) if nulls else float("nan")
    L = ["# diagnose blind study", "", f"trials completed: {len(trials)}", f"top-1 accuracy: {acc:.1%}",
         f"false-alarm rate (null captures): {fa:.1%} of {len(nulls)}", "", "truth \\ verdict | " +
         " | ".join(verdicts), "|".join(["---"] * (len(verdicts) + 1))]
    for t in names:
        L.append(f"{t} | " + " | ".join(str(M[(t, v)]) for v in verdicts))
    return "\n".join(L) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--camera", required=True)
    ap.add_argument("--lamps", required=True)
    ap.add_argument("--reference", required=True)
    a = ap.parse_args(argv)
    work = Path(a.work)
    work.mkdir(parents=True, exist_ok=True)
    store = work / "trials.json"
    done = json.loads(store.read_text()) if store.exists() else []
    have = {t["trial"] for t in done}
    for k in range(a.trials):
        if k in have:
            continue
        done.append(trial(k, work, a))
        store.write_text(json.dumps(done, indent=1))
        (Path(__file__).parent / "blind_study.md").write_text(summarise(done))
        print(done[-1], flush=True)
    (Path(__file__).parent / "blind_study.md").write_text(summarise(done))


if __name__ == "__main__":
    main()
