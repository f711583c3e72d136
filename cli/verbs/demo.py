"""The main job: simulate a capture on the virtual rig, run the pipeline, fit, and report
how well the ground truth was recovered.

Steps (each is a glossrig verb a user can run alone):
  1. checkerboard views on the twin        -> glossrig calibrate camera
  2. a transparency-sheet capture          -> glossrig calibrate lamps   (thesis 4.3.4)
  3. a lambert:0.8 reference capture and a capture of MATERIAL (middle-row LEDs, the 18
     exposures of Table 4.1, the rig's LED fluctuations and sensor noise, real DNGs)
                                           -> glossrig extract           (thesis 4.3-4.4)
  4. the extended-Ward fit                 -> glossrig fit               (thesis 4.5)
  5. the fitted parameters against the truth the twin recorded in truth.json.
Finished steps are reused when the demo is run again with the same --out.
"""
from __future__ import annotations

import argparse

HELP = "simulate, calibrate, extract and fit on the virtual rig; report ground-truth recovery"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", help="working folder for the demo's captures and results")
    p.add_argument("--material", default="sample_2_6", help="the sample (see glossrig simulate --help)")
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--rotations", default="0")
    p.add_argument("--seed", type=int, default=1)


def run(args) -> int:
    import json
    import math
    from pathlib import Path

    from glossrig.cli.main import main as glossrig
    from glossrig.core.errors import GlossrigError
    from glossrig.core.rig import default_rig_path

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rig = str(default_rig_path())

    def step(done: Path, *argv):
        if done.exists():
            print(f"[demo] reusing {done}")
            return
        print(f"[demo] glossrig {' '.join(map(str, argv))}")
        if glossrig([str(a) for a in argv]) != 0:
            raise GlossrigError(f"demo step failed: glossrig {argv[0]}")

    def capture(name, material, seed):
        d = out / name
        step(d / "truth.json", "simulate", "--rig", rig, "--material", material, "--leds", "middle",
             f"--rotations={args.rotations}", "--repeats", 1, "--scale", args.scale, "--seed", seed, "--out", d)
        return d

    step(out / "checker" / "truth.json", "simulate", "--rig", rig, "--target", "checkerboard", "--views", 12,
         "--scale", args.scale, "--seed", args.seed, "--out", out / "checker")
    step(out / "camera.json", "calibrate", "camera", out / "checker", "--out", out / "camera.json")
    spec = capture("specular", "transparency_sheet", args.seed + 1)
    step(out / "lamps.json", "calibrate", "lamps", spec, "--camera", out / "camera.json", "--out", out / "lamps.json")
    ref = capture("reference", "lambert:0.8", args.seed + 2)
    sample = capture("sample", args.material, args.seed + 3)
    step(out / "samples.parquet", "extract", sample, "--reference", ref, "--camera", out / "camera.json",
         "--lamps", out / "lamps.json", "--out", out / "samples.parquet", "--plots", out / "plots")
    step(out / "fit.json", "fit", out / "samples.parquet", "--out", out / "fit.json", "--plots", out / "plots")

    truth = json.loads((sample / "truth.json").read_text())["material"]
    fit = json.loads((out / "fit.json").read_text())["luminance"]
    cam = json.loads((out / "camera.json").read_text())
    K = json.loads((out / "checker" / "truth.json").read_text())["camera_matrix"]
    lamps = json.loads((out / "lamps.json").read_text())["lamps_mm"]
    true_leds = json.loads((spec / "truth.json").read_text())["led_positions_mm"]
    lamp_err = max(math.dist(v, true_leds[k]) for k, v in lamps.items())
    print("\n[demo] ground-truth recovery on the twin")
    print(f"  intrinsics: fx {100 * (cam['fx'] / K[0][0] - 1):+.3f} %, fy {100 * (cam['fy'] / K[1][1] - 1):+.3f} %, "
          f"principal point ({cam['cx'] - K[0][2]:+.2f}, {cam['cy'] - K[1][2]:+.2f}) px")
    print(f"  lamp positions: worst error {lamp_err:.2f} mm over {len(lamps)} LEDs")
    if "ward" not in truth:
        print(f"  material {truth['label']} is not a Ward material; fitted: "
              + ", ".join(f"{k}={fit[k]:.4g}" for k in ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")))
        return 0
    w = truth["ward"]
    print(f"  {'parameter':<14}{'true':>10}{'fitted':>10}{'error':>10}")
    for k in ("rho_d", "rho_s", "alpha_x", "alpha_y"):
        print(f"  {k:<14}{w[k]:>10.4g}{fit[k]:>10.4g}{100 * (fit[k] / w[k] - 1):>+9.1f}%")
    d = (fit["lobe_rotation"] - w["lobe_rotation"]) % math.pi
    print(f"  {'lobe_rotation':<14}{w['lobe_rotation']:>10.4g}{fit['lobe_rotation']:>10.4g}"
          f"{math.degrees(min(d, math.pi - d)):>9.2f} deg")
    print(f"  results in {out}: fit.json, samples.parquet, plots/")
    return 0
