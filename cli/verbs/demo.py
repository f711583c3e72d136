"""The main job on the virtual rig: simulate a capture and check what was written.

Today this simulates a thesis-style capture of a Table 9.1 material on the Mitsuba
twin (middle-row LEDs, 18 exposures, the rig's LED fluctuations and sensor noise),
then verifies the capture as the pipeline will read it: every DNG through
rawpy/LibRaw with its checksum, and the raw signal's linearity in exposure time.
The measurement pipeline (extract -> fit -> ground-truth recovery) joins this job
as its stages land (issues 3 and 4).
"""
from __future__ import annotations

import argparse

HELP = "simulate a capture on the virtual rig and report on it (the README's main job)"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="demo_out", help="folder for the demo's capture(s)")
    p.add_argument("--material", default="sample_2_6")
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--seed", type=int, default=1)


def run(args) -> int:
    import shutil
    from pathlib import Path

    import numpy as np

    from glossrig.core.capture import load_manifest
    from glossrig.core.raw import linearize, read_raw
    from glossrig.core.rig import default_rig_path
    from glossrig.twin.simulate import simulate

    out = Path(args.out) / "sample"
    if out.exists():
        shutil.rmtree(out)     # the demo's own scratch folder
    print(f"[demo] simulating {args.material} on the twin at scale {args.scale} -> {out}")
    simulate(default_rig_path(), args.material, "middle", [0.0], 1, args.scale, args.seed, None, out)
    man = load_manifest(out)
    man.verify(check_hashes=True)
    print(f"[demo] {len(man.images)} DNGs, checksums verified, manifest complete={man.complete}")
    seq = sorted((im for im in man.select("sequence") if im.leds == [9]), key=lambda im: im.exposure_s)
    worst = 0.0
    for a, b in zip(seq, seq[1:]):
        la, lb = linearize(read_raw(out / a.file)), linearize(read_raw(out / b.file))
        # select well above the noise floor: selecting on a noisy value biases the ratio
        ok = (la > 0.05) & (lb < 0.9)
        if ok.sum() > 1000:
            r = (lb[ok].mean() / la[ok].mean()) / (b.exposure_s / a.exposure_s)
            worst = max(worst, abs(r - 1))
    print(f"[demo] raw signal linear in exposure time: worst deviation {100 * worst:.2f} % "
          "between neighbouring exposures (LED jitter 0.5 % + shot noise)")
    return 0
