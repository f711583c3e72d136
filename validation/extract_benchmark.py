"""Benchmark of ``glossrig extract`` at full resolution (issue 3): seconds, megapixels
per second and peak memory, split by stage.

    python -m validation.extract_benchmark --work /tmp/bench_extract [--leds 9,10] [--repeats 3]

1. Simulates (once; reused when complete) full-resolution (scale 1.0, 6032 x 4032)
   twin captures of the sample (``sample_2_6``) and the ``lambert:0.8`` reference with
   the given middle-row LEDs x repeats x the thesis's 18 exposures, and a camera file
   (checkerboards calibrated at scale 0.25, camera matrix scaled by 4: the twin's K
   scales exactly so).
2. For each LED count k of ``--counts`` (default 1, 2 and all simulated LEDs), builds
   captures holding only the first k LEDs (manifests filtered, raw files linked,
   nothing copied) and runs the extraction of sample + reference - the function
   ``glossrig extract`` calls, with the same Parquet output - in a fresh process per k,
   with every stage timed by wrapping the pipeline's own functions, the process's peak
   resident memory (ru_maxrss) recorded after each stage, and the machine's load
   average before and after (the machine is shared: CPU seconds are the figures to read).
3. Writes the Markdown report (``--out``). With all 8 middle-row LEDs simulated
   (``--leds 9,10,5,6,7,8,11,12``) the thesis capture (8 LEDs x 3 repeats) is measured;
   with fewer it is stated as a linear extrapolation in the number of LEDs, labelled so.

Lamp positions are the rig file's nominal ones (the benchmark times the work, the
accuracy is in validation/pipeline_report.md).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

from validation.common import camera, capture
from validation.paths import RIG, ROOT

FRAME_MP = 6032 * 4032 / 1e6


def prepare(w: Path, leds: str, repeats: int) -> None:
    if not (w / "camera.json").exists():
        camera(w / "camera_q.json", w / "checker", 10, 0.25, 1)
        c = json.loads((w / "camera_q.json").read_text())
        for k in ("fx", "fy"):
            c[k] *= 4
        for k in ("cx", "cy"):
            c[k] = (c[k] + 0.5) * 4 - 0.5
        c["camera_matrix"] = [[c["fx"], 0, c["cx"]], [0, c["fy"], c["cy"]], [0, 0, 1]]
        c["image_size"] = [6032, 4032]
        (w / "camera.json").write_text(json.dumps(c))
    for name, mat, seed in (("sample", "sample_2_6", 2), ("reference", "lambert:0.8", 3)):
        capture(w / name, mat, 1.0, seed, "0", repeats, leds=leds)


def subset(src: Path, dst: Path, leds: list[int]) -> Path:
    """A capture folder with only the calibration image and ``leds``' sequences of ``src``."""
    d = json.loads((src / "capture.json").read_text())
    d["images"] = [im for im in d["images"] if im["role"] != "sequence" or im["leds"][0] in leds]
    # the manifest's rig may be relative to its folder (captures hold a rig.toml copy): point at the original
    d["rig"] = str((src / d["rig"]).resolve())
    dst.mkdir(parents=True, exist_ok=True)
    for im in d["images"]:
        link = dst / im["file"]
        if not link.exists():
            os.symlink(src / im["file"], link)
    (dst / "capture.json").write_text(json.dumps(d))
    return dst


# ----------------------------------------------------------------- measuring (child process)

STAGES = [  # (label, module, attribute); nested ones are subtracted from their parent
    ("geometry", "glossrig.core.extraction.extract", "rotation_geometry"),
    ("poses", "glossrig.core.calibration.poses", "calibrate_capture"),
    ("raw_read", "glossrig.core.calibration.raw", "read_raw"),     # via Manifest.read_raw (checksum + decode)
    ("linearise_stack", "glossrig.core.radiometry.hdr", "stack_frames"),
    ("hdr", "glossrig.core.radiometry.hdr", "hdr_from_stack"),
    ("patch_blocks", "glossrig.core.extraction.extract", "normalise_by_patch"),
    ("patch_blocks", "glossrig.core.extraction.extract", "block_values"),
    ("angles", "glossrig.core.extraction.extract", "sample_angles"),
    ("diffuse_normalise", "glossrig.core.extraction.extract", "diffuse_normalize"),
    ("write_parquet", "glossrig.core.samples", "write_samples"),
]


def peak_gb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024 ** 2


def measure(sample: Path, reference: Path, camera: Path, out_json: Path) -> None:
    import importlib

    import numpy as np

    secs, cpu, calls, peak_after, crop = {}, {}, {}, {}, []

    def wrap(label, fn):
        def timed(*a, **k):
            t0, c0 = time.perf_counter(), time.process_time()
            try:
                res = fn(*a, **k)
                if label == "geometry":
                    crop.append(list(res.crop))
                return res
            finally:
                secs[label] = secs.get(label, 0.0) + time.perf_counter() - t0
                cpu[label] = cpu.get(label, 0.0) + time.process_time() - c0
                calls[label] = calls.get(label, 0) + 1
                peak_after[label] = peak_gb()
        return timed

    for label, mod, attr in STAGES:
        m = importlib.import_module(mod)
        setattr(m, attr, wrap(label, getattr(m, attr)))
    from glossrig.core import samples
    from glossrig.core.extraction.extract import extract_samples
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.rig import load_rig

    cam = load_camera(camera)
    lamps = {l.id: np.array(l.position) for l in load_rig(RIG).leds}
    base = peak_gb()
    load0 = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    df = extract_samples(sample, reference, cam, lamps)
    pq = out_json.with_suffix(".parquet")
    samples.write_samples(df, pq)
    total, total_cpu = time.perf_counter() - t0, time.process_time() - c0
    out_json.write_text(json.dumps({"seconds": secs, "cpu_seconds": cpu, "total_cpu_s": total_cpu, "calls": calls, "peak_gb_after": peak_after, "total_s": total,
                                    "peak_gb": peak_gb(), "peak_gb_after_imports": base, "rows": len(df),
                                    "parquet_mb": pq.stat().st_size / 1e6, "crops": crop,
                                    "load_average": [load0, os.getloadavg()[0]]}))


# ----------------------------------------------------------------- report

LABELS = {
    "poses": "calibration image: read, demosaic, markers, poses (eq. 4.1-4.25)",
    "geometry_rest": "crop, white-patch mask, ray casting (eq. 4.26-4.30)",
    "raw_read": "raw read + crop (sha256 check, rawpy, EXIF checks)",
    "linearise_stack": "linearise + combine repeats (eq. 4.1-4.2, 4.31)",
    "hdr": "neighbour correction + HDR (eq. 4.32-4.44)",
    "patch_blocks": "patch normalisation + Bayer-block values (eq. 4.45-4.50)",
    "angles": "angles (4.3.5)",
    "diffuse_normalise": "diffuse normalisation, KD-tree (4.4)",
    "write_parquet": "write Parquet",
}


def report(runs: dict[int, dict], args) -> str:
    k_max = max(runs)
    r = runs[k_max]
    x0, y0, x1, y1 = r["crops"][0]
    crop = (x1 - x0, y1 - y0)
    frames_per_led = 2 * args.repeats * 18               # sample + reference
    n_frames = {k: k * frames_per_led for k in runs}
    n_cal = 2

    loads = ", ".join(f"{k} LED{'s' if k > 1 else ''} {runs[k]['load_average'][0]:.1f} / "
                      f"{runs[k]['load_average'][1]:.1f}" for k in sorted(runs) if "load_average" in runs[k])

    def stage(run, key, what="cpu_seconds"):
        s = run[what]
        if key == "geometry_rest":
            return s.get("geometry", 0) - s.get("poses", 0)
        return s.get(key, 0.0)

    lines = ["# `glossrig extract` at full resolution (6032 x 4032, 24.3 MP)", "",
             "Command (simulates the captures once, then runs one measuring process per LED count):", "",
             f"    nice -n 5 python -m validation.extract_benchmark --work {args.work} --leds {args.leds} "
             f"--repeats {args.repeats} --counts {args.counts}", "",
             f"Measured: twin captures at scale 1.0 of `sample_2_6` and the `lambert:0.8` reference, LEDs "
             f"{args.leds} x {args.repeats} repeats x 18 exposures each (48 MB DNGs), one rotation; the "
             f"extraction of sample + reference as `glossrig extract` runs it (same function, same Parquet "
             f"output), for the first k LEDs of that list. Each raw file is decoded whole by rawpy and cropped "
             f"to {crop[0]} x {crop[1]} px ({crop[0] * crop[1] / 1e6:.2f} MP: the sample and the holder's "
             f"white patch).", "",
             f"The machine has {os.cpu_count()} cores and was shared with other work while this ran (load "
             f"average at the start / end of each measuring process: {loads}); the {k_max}-LED run's wall "
             f"time was {r['total_s'] / r['total_cpu_s']:.1f}x its CPU time. The CPU seconds (all threads of "
             "the process; `time.process_time`) are the figures to read; rates below are per CPU second. On "
             "an unshared machine the wall time would be about the CPU time plus file reading, less where "
             "numpy/OpenCV use both cores.", "",
             "## Measured, by stage (CPU seconds)", "",
             "| stage | " + " | ".join(f"{k} LED{'s' if k > 1 else ''}" for k in sorted(runs)) +
             f" | rate ({k_max} LEDs) | wall s ({k_max} LEDs) | peak RSS after stage ({k_max} LEDs) |",
             "|---|" + "---|" * len(runs) + "---|---|---|"]
    for key, label in LABELS.items():
        vals = " | ".join(f"{stage(runs[k], key):.1f}" for k in sorted(runs))
        c = stage(r, key)
        if key == "poses":
            rate = f"{n_cal * FRAME_MP / c:.2f} MP/s ({n_cal} calibration images)"
        elif key in ("raw_read", "linearise_stack", "hdr", "patch_blocks"):
            rate = (f"{n_frames[k_max] * FRAME_MP / c:.0f} MP/s of raw frames ({n_frames[k_max]}), "
                    f"{n_frames[k_max] * crop[0] * crop[1] / 1e6 / c:.0f} MP/s of cropped pixels")
        else:
            rate = ""
        pk = r["peak_gb_after"].get("geometry" if key == "geometry_rest" else key)
        lines.append(f"| {label} | {vals} | {rate} | {stage(r, key, 'seconds'):.0f} | "
                     + (f"{pk:.2f} GB |" if pk is not None else "|"))
    other = {k: runs[k]["total_cpu_s"] - sum(stage(runs[k], key) for key in LABELS) for k in runs}
    wall_other = r["total_s"] - sum(stage(r, key, "seconds") for key in LABELS)
    lines.append("| other (manifests, checks, tables) | " + " | ".join(f"{other[k]:.1f}" for k in sorted(runs))
                 + f" | | {wall_other:.0f} | |")
    lines.append("| **total** | " + " | ".join(f"**{runs[k]['total_cpu_s']:.1f}**" for k in sorted(runs)) +
                 f" | {(n_frames[k_max] + n_cal) * FRAME_MP / r['total_cpu_s']:.0f} MP/s of all raw frames | "
                 f"{r['total_s']:.0f} | |")
    lines += ["", "| LEDs | raw files read (sample + reference) | CPU s | wall s | peak RSS GB | rows |",
              "|---|---|---|---|---|---|"]
    for k in sorted(runs):
        lines.append(f"| {k} | {n_frames[k] + n_cal} | {runs[k]['total_cpu_s']:.1f} | {runs[k]['total_s']:.0f} | "
                     f"{runs[k]['peak_gb']:.2f} | {runs[k]['rows']} |")
    ks = sorted(runs)
    if len(ks) >= 2:
        pairs = list(zip(ks[:-1], ks[1:]))
        lines += ["", "## Cost per added LED", "",
                  f"Increments between successive measured runs, per added LED (sample + reference, "
                  f"{frames_per_led} raw files each). A stage whose increment grows from one interval to the next "
                  "grows faster than the number of LEDs.", "",
                  "| stage | " + " | ".join(f"{a} -> {b} LEDs" for a, b in pairs) + " |",
                  "|---|" + "---|" * len(pairs)]
        for key, label in LABELS.items():
            lines.append(f"| {label} | " + " | ".join(
                f"{(stage(runs[b], key) - stage(runs[a], key)) / (b - a):+.1f} CPU s" for a, b in pairs) + " |")
        lines.append("| **total** | " + " | ".join(
            f"**{(runs[b]['total_cpu_s'] - runs[a]['total_cpu_s']) / (b - a):+.1f} CPU s**" for a, b in pairs) + " |")
        lines.append("| peak memory | " + " | ".join(
            f"{(runs[b]['peak_gb'] - runs[a]['peak_gb']) / (b - a):+.2f} GB" for a, b in pairs) + " |")
        lines += ["", f"The raw frames are streamed (one LED's {args.repeats * 18} cropped frames at a time), but the "
                  f"per-block table of every LED is kept until the diffuse normalisation (sample and reference, "
                  f"~{r['rows'] // k_max / 1e3:.0f}k rows per LED and capture), so memory grows with the LEDs and "
                  f"peaks in the KD-tree stage. The Parquet output is {r['parquet_mb'] / k_max:.0f} MB per LED "
                  f"({r['rows'] // k_max} rows)."]
        n8 = 8 * frames_per_led + n_cal
        if 8 in runs:
            r8 = runs[8]
            lines += ["", "## A thesis capture (8 LEDs x 3 repeats x 18 exposures), measured", "",
                      f"Sample + reference, {n8} raw files, {n8 * FRAME_MP:.0f} MP: **{r8['total_cpu_s']:.0f} CPU s "
                      f"({r8['total_cpu_s'] / 60:.1f} min) per rotation, {n8 * FRAME_MP / r8['total_cpu_s']:.0f} MP/s "
                      f"per CPU second, peak memory {r8['peak_gb']:.2f} GB** (of the machine's 24 GB); "
                      f"wall {r8['total_s']:.0f} s on the shared machine."]
        else:
            a, b = pairs[-1]
            per_led = (runs[b]["total_cpu_s"] - runs[a]["total_cpu_s"]) / (b - a)
            dpk = (runs[b]["peak_gb"] - runs[a]["peak_gb"]) / (b - a)
            t8 = runs[b]["total_cpu_s"] + (8 - b) * per_led
            lines += ["", "## Extrapolated to a thesis capture (not measured)", "",
                      f"**Linear extrapolation from the {a}- and {b}-LED runs to 8 LEDs x 3 repeats x 18 exposures** "
                      f"(sample + reference, {n8} raw files, {n8 * FRAME_MP:.0f} MP): **{t8:.0f} CPU s "
                      f"({t8 / 60:.1f} min) per rotation, {n8 * FRAME_MP / t8:.0f} MP/s per CPU second, "
                      f"{runs[b]['peak_gb'] + (8 - b) * dpk:.1f} GB peak** - not measured, and a lower bound where a "
                      "stage grows faster than linearly: simulate all 8 middle-row LEDs to measure it."]
    lines += ["", "At scale 1.0 the twin renders each output pixel from one read of its pinhole canvas "
              "(`twin/render.py`, `LensMap.MAX_CANVAS_MP`); the extraction's cost does not depend on that."]
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", required=True)
    ap.add_argument("--leds", default="9,10", help="middle-row LEDs to simulate (comma-separated)")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--counts", default="1,2,all",
                    help="LED counts to measure (first k of --leds), comma-separated; 'all' = every LED of --leds")
    ap.add_argument("--out", default=str(ROOT / "validation/extract_benchmark.md"))
    ap.add_argument("--measure", nargs=4, metavar=("SAMPLE", "REF", "CAMERA", "OUT_JSON"), help=argparse.SUPPRESS)
    a = ap.parse_args()
    if a.measure:
        measure(*map(Path, a.measure))
        return
    w = Path(a.work)
    w.mkdir(parents=True, exist_ok=True)
    prepare(w, a.leds, a.repeats)
    leds = [int(x) for x in a.leds.split(",")]
    counts = sorted({len(leds) if c == "all" else int(c) for c in a.counts.split(",")})
    if not counts or counts[0] < 1 or counts[-1] > len(leds):
        ap.error(f"--counts {a.counts}: each count must be 1..{len(leds)} (the LEDs of --leds)")
    runs = {}
    for k in counts:
        res = w / f"bench_{k}led.json"
        if not res.exists():
            s = subset(w / "sample", w / f"sample_{k}led", leds[:k])
            r = subset(w / "reference", w / f"reference_{k}led", leds[:k])
            subprocess.run([sys.executable, "-m", "validation.extract_benchmark", "--work", str(w), "--measure", str(s),
                            str(r), str(w / "camera.json"), str(res)], check=True)
        runs[k] = json.loads(res.read_text())
        print(k, "LEDs:", json.dumps(runs[k]))
    text = report(runs, a)
    Path(a.out).write_text(text)
    print(text)


if __name__ == "__main__":
    main()
