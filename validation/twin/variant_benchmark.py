"""The twin's renders on Mitsuba's variants: the CPU (``llvm_ad_rgb``) against the GPU
(``cuda_ad_rgb``), in time and in what they render.

    python -m validation.twin.variant_benchmark [--variants llvm_ad_rgb,cuda_ad_rgb] \\
        [--scales 0.25,1.0] [--repeats 3] [--renders DIR] [--capture] [--out validation/twin/variants.md]

(validation/twin/variants.md: measured on an NVIDIA H200; what stands above its generated part
is kept.) ``--capture`` also times a whole ``glossrig simulate`` of the 8 middle LEDs per variant
at the smallest scale, compares the two captures' raw files, and makes the first variant's again
to show whether a capture is the same bytes within one variant.

Each variant runs in a child process of its own (a process sets Mitsuba's variant once;
``GLOSSRIG_MITSUBA_VARIANT``, :mod:`glossrig.twin.mitsuba_env`) and measures, per scale, for one
LED (9) of the thesis rig on sample_2_6 (the twin's Ward BSDF, a Python plugin traced by
Dr.Jit): the virtual rig's set-up, the first render (the variant's JIT compilation included),
then the median over ``--repeats`` of the render alone (``mi.render`` at the twin's default
samples, a new seed each time) and of the LED's radiance as a capture takes it (render and the
lens map onto the sensor, :meth:`VirtualRig.led_radiance`). The sensor model (18 exposures, DNGs)
is left out: it runs Dr.Jit's LLVM backend whatever Mitsuba's variant
(:mod:`glossrig.twin.sensor_drjit`), and ``validation/twin/benchmark.py`` measures it.

What they render: at the smallest scale each variant's radiance of LED 9 at the render seeds 0
and 1 is kept (``--renders DIR``, ``VARIANT.npz``), and every pair of variants is compared on the
pixels that see the sample's light (above 1 % of the image's 99.9th percentile): the ratio of
their total radiance and the median relative difference per pixel, beside the same figures for
one variant at two seeds - the Monte Carlo noise of a render. Two variants agree when their
difference at the same seed is no larger than that noise (the samplers' streams need not be the
same on CPU and GPU). ``--compare A.npz B.npz`` compares two kept files (e.g. one made on a GPU
machine with one made here).

A variant that cannot run here (no CUDA device, no libLLVM 19) is reported with its error, not
a traceback.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from validation.paths import RIG, ROOT

LED = 9
#: the heading of the generated part of the report; what stands above it in --out is kept
MEASURED = "## Measured (written by the command below)"
MATERIAL = "sample_2_6"
SIGNAL_FRACTION = 0.01        # pixels above this fraction of the 99.9th percentile are compared


def child(variant: str, scales: list[float], repeats: int, renders: Path | None) -> dict:
    """The measurements of one variant in this process (its variant must be set before Mitsuba is imported)."""
    from glossrig.core.models.materials import parse_material
    from glossrig.core.rig import load_rig
    from glossrig.twin.mitsuba_env import mitsuba
    from glossrig.twin.render import render_array
    from glossrig.twin.virtual_rig import VirtualRig

    mi = mitsuba()
    if mi.variant() != variant:
        raise RuntimeError(f"asked for {variant}, Mitsuba runs {mi.variant()}")
    rig, material = load_rig(RIG), parse_material(MATERIAL)
    rows = []
    for k, scale in enumerate(sorted(scales)):
        t0 = time.perf_counter()
        vr = VirtualRig(rig, material, scale=scale, seed=0)
        setup = time.perf_counter() - t0
        vr.switch([LED])
        t0 = time.perf_counter()
        first = vr.led_radiance(LED)
        first_s = time.perf_counter() - t0
        render, radiance = [], []
        for r in range(repeats):
            t0 = time.perf_counter()
            render_array(vr.scene, seed=100 + r)
            render.append(time.perf_counter() - t0)
            vr._cache.clear()
            t0 = time.perf_counter()
            vr.led_radiance(LED)
            radiance.append(time.perf_counter() - t0)
        w, h = vr.lens.size
        rows.append({"scale": scale, "size": f"{w}x{h}", "setup_s": setup, "first_s": first_s,
                     "render_s": statistics.median(render), "radiance_s": statistics.median(radiance),
                     "runs": {"render": [round(x, 3) for x in render], "radiance": [round(x, 3) for x in radiance]}})
        if renders is not None and k == 0:
            vr1 = VirtualRig(rig, material, scale=scale, seed=1)
            vr1.switch([LED])
            renders.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(renders / f"{variant}.npz", seed0=first.astype(np.float32),
                                seed1=vr1.led_radiance(LED).astype(np.float32), scale=scale)
    from glossrig.twin import sensor_drjit

    return {"variant": variant, "rows": rows, "sensor_drjit": sensor_drjit.available()}


def compare(a: np.ndarray, b: np.ndarray, reference: np.ndarray | None = None) -> dict:
    """Total radiance ratio and median per-pixel relative difference of B against A, on the pixels
    where ``reference`` (default A) sees the sample's light."""
    ref = a if reference is None else reference
    lum = ref.mean(axis=-1)
    mask = lum > SIGNAL_FRACTION * np.percentile(lum, 99.9)
    la, lb = a.mean(axis=-1)[mask], b.mean(axis=-1)[mask]
    rel = np.abs(lb / np.maximum(la, 1e-30) - 1.0)
    return {"pixels": int(mask.sum()), "total_ratio": float(lb.sum() / la.sum()),
            "median_rel_diff": float(np.median(rel)), "p99_rel_diff": float(np.percentile(rel, 99))}


def compare_files(fa: Path, fb: Path) -> dict:
    """A against B at the same seed, beside A's and B's own seed-to-seed noise."""
    A, B = np.load(fa), np.load(fb)
    if A["seed0"].shape != B["seed0"].shape:
        raise SystemExit(f"{fa} and {fb} hold renders of other sizes: {A['seed0'].shape} and {B['seed0'].shape}")
    return {"same_seed": compare(A["seed0"], B["seed0"]), "noise_a": compare(A["seed0"], A["seed1"]),
            "noise_b": compare(B["seed0"], B["seed1"], reference=B["seed0"])}


def capture(variant: str, out: Path, scale: float) -> dict:
    """``glossrig simulate`` of the thesis rig's 8 middle LEDs (sample_2_6, seed 1, --ideal) with
    VARIANT: wall-clock seconds and the images' sha256 by file."""
    env = {**os.environ, "GLOSSRIG_MITSUBA_VARIANT": variant}
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "simulate", "--rig", str(RIG), "--material", MATERIAL,
                        "--leds", "middle", "--scale", str(scale), "--seed", "1", "--ideal", "--no-progress",
                        "--out", str(out)], env=env, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    if p.returncode:
        err = [x for x in p.stderr.strip().splitlines() if x.strip()]
        return {"variant": variant, "error": err[-1] if err else f"exit status {p.returncode}"}
    images = json.loads((out / "capture.json").read_text())["images"]
    return {"variant": variant, "scale": scale, "wall_s": wall, "sha256": {i["file"]: i["sha256"] for i in images}}


def compare_captures(a: dict, b: dict, fa: Path, fb: Path) -> dict:
    """How many images of two captures are the same bytes, and where not, the share of their raw
    values that differ and the largest difference (DN)."""
    import tifffile

    same = [f for f in a["sha256"] if b["sha256"].get(f) == a["sha256"][f]]
    other = [f for f in a["sha256"] if f in b["sha256"] and f not in same]
    frac, most = [], 0
    for f in other:
        x, y = tifffile.imread(fa / f).astype(np.int64), tifffile.imread(fb / f).astype(np.int64)
        frac.append(float(np.mean(x != y)))
        most = max(most, int(np.abs(x - y).max()))
    return {"images": len(a["sha256"]), "identical": len(same), "differing": len(other),
            "share_of_values_differing": max(frac) if frac else 0.0, "largest_dn_difference": most}


def whole_captures(variants: list[str], scale: float) -> dict:
    """``--capture``: a whole capture per variant (:func:`capture`), the first two compared, and the
    first variant's made again (is a capture the same bytes within one variant?)."""
    import tempfile

    out: dict = {"scale": scale, "captures": [], "comparison": None, "repeat": None}
    with tempfile.TemporaryDirectory(prefix="glossrig-variants-") as d:
        for v in variants:
            print(f"{v}: whole capture ...", flush=True)
            out["captures"].append(capture(v, Path(d) / v, scale))
        done = [c for c in out["captures"] if "error" not in c]
        if len(done) >= 2:
            out["comparison"] = compare_captures(done[0], done[1], Path(d) / done[0]["variant"],
                                                 Path(d) / done[1]["variant"])
        if done:
            v = done[0]["variant"]
            again = capture(v, Path(d) / f"{v}.again", scale)
            if "error" not in again:
                out["repeat"] = {"variant": v, **compare_captures(done[0], again, Path(d) / v, Path(d) / f"{v}.again")}
    return out


def machine() -> str:
    import shutil

    gpu = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version", "--format=csv,noheader"],
                         capture_output=True, text=True) if shutil.which("nvidia-smi") else None
    name = gpu.stdout.strip() if gpu is not None and gpu.returncode == 0 else "no GPU"
    return f"{os.cpu_count()} CPU cores, {name}; load average {os.getloadavg()[0]:.2f}"


def report(results: list[dict], comparisons: dict, args, where: str, caps: dict | None = None) -> str:
    lines = [MEASURED, "",
             f"Command: `python -m validation.twin.variant_benchmark --variants {args.variants} --scales {args.scales} "
             f"--repeats {args.repeats}{' --capture' if args.capture else ''}`; machine: {where}; the twin's sensor "
             "model: " + ", ".join(f"{r['variant']}: " + ("Dr.Jit LLVM kernel" if r.get("sensor_drjit") else
                                                          "NumPy reference path (libLLVM 19 absent)")
                                   for r in results if "error" not in r) + f". LED {LED} of the thesis rig, {MATERIAL} (the twin's "
             "Ward BSDF, a Python plugin), the twin's default samples per pixel; medians of "
             f"{args.repeats} runs in one process per variant.", "",
             "| variant | scale | image | set-up (s) | first render incl. JIT (s) | render (s) | "
             "radiance on the sensor (s) |", "|---|---|---|---|---|---|---|"]
    for res in results:
        if "error" in res:
            lines.append(f"| {res['variant']} | - | - | - | - | - | did not run: {res['error']} |")
            continue
        for r in res["rows"]:
            lines.append(f"| {res['variant']} | {r['scale']} | {r['size']} | {r['setup_s']:.2f} | {r['first_s']:.2f} | "
                         f"{r['render_s']:.3f} | {r['radiance_s']:.3f} |")
    ok = {res["variant"]: res for res in results if "error" not in res}
    if len(ok) >= 2:
        a, b = list(ok)[:2]
        lines += ["", f"Ratios {a} / {b} (medians of this run):", ""]
        for ra, rb in zip(ok[a]["rows"], ok[b]["rows"]):
            lines.append(f"- scale {ra['scale']}: render {ra['render_s'] / rb['render_s']:.3g}x, radiance on the sensor "
                         f"{ra['radiance_s'] / rb['radiance_s']:.3g}x, first render {ra['first_s'] / rb['first_s']:.3g}x")
        lines += ["", "(The scales run in one process per variant, smallest first: the first render of a larger "
                  "scale finds the variant's kernels compiled.)"]
    if comparisons:
        lines += ["", "What they render (LED 9 at the smallest scale; pixels above 1 % of the 99.9th percentile):", "",
                  "| pair | pixels | total radiance ratio - 1 | relative difference per pixel: median | 99th "
                  "percentile |", "|---|---|---|---|---|"]
        for name, c in comparisons.items():
            for key, label in (("same_seed", f"{name}, seed 0"), ("noise_a", f"{name.split(' vs ')[0]}, seed 0 vs 1"),
                               ("noise_b", f"{name.split(' vs ')[-1]}, seed 0 vs 1")):
                x = c[key]
                lines.append(f"| {label} | {x['pixels']} | {x['total_ratio'] - 1:+.1e} | {x['median_rel_diff']:.1e} | "
                             f"{x['p99_rel_diff']:.1e} |")
    if caps:
        lines += ["", f"Whole captures (`glossrig simulate --leds middle --scale {caps['scale']} --seed 1 "
                  f"--ideal`, {MATERIAL}: 8 LEDs, the calibration image and 8 x 18 exposures, DNGs written; the "
                  "sensor model runs on the CPU in every variant), wall-clock seconds of the command:", ""]
        for c in caps["captures"]:
            lines.append(f"- {c['variant']}: " + (f"did not run: {c['error']}" if "error" in c else
                                                   f"{c['wall_s']:.1f} s, {len(c['sha256'])} images"))
        rep = caps["repeat"]
        if rep:
            lines.append(f"- {rep['variant']} made again in the same way: {rep['identical']} of {rep['images']} images "
                         "the same bytes")
        cmp_ = caps["comparison"]
        if cmp_:
            lines.append(f"- the two captures: {cmp_['identical']} of {cmp_['images']} images the same bytes; in the "
                         f"{cmp_['differing']} others at most {cmp_['share_of_values_differing']:.2e} of the raw values "
                         f"differ, by at most {cmp_['largest_dn_difference']} DN")
    lines += ["", "Single runs (s): " + "; ".join(
        f"{res['variant']} scale {r['scale']}: {r['runs']}" for res in ok.values() for r in res["rows"]), ""]
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--variants", default="llvm_ad_rgb,cuda_ad_rgb")
    ap.add_argument("--scales", default="0.25,1.0")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--renders", help="folder for each variant's kept renders (VARIANT.npz)")
    ap.add_argument("--out", default=str(ROOT / "validation/twin/variants.md"))
    ap.add_argument("--json", help="also write the figures as JSON")
    ap.add_argument("--capture", action="store_true",
                    help="also time a whole 8-LED capture per variant (the smallest scale) and compare its raw files")
    ap.add_argument("--compare", nargs=2, metavar=("A.npz", "B.npz"), help="compare two kept render files and stop")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    scales = [float(s) for s in a.scales.split(",")]
    if a.compare:
        print(json.dumps(compare_files(Path(a.compare[0]), Path(a.compare[1])), indent=1))
        return 0
    if a.child:
        print(json.dumps(child(a.child, scales, a.repeats, Path(a.renders) if a.renders else None)))
        return 0
    results = []
    for v in a.variants.split(","):
        cmd = [sys.executable, "-m", "validation.twin.variant_benchmark", "--child", v, "--scales", a.scales,
               "--repeats", str(a.repeats), *(["--renders", a.renders] if a.renders else [])]
        env = {**os.environ, "GLOSSRIG_MITSUBA_VARIANT": v}
        print(f"{v} ...", flush=True)
        p = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=ROOT)
        if p.returncode:
            err = [x for x in p.stderr.strip().splitlines() if x.strip()]
            results.append({"variant": v, "error": err[-1] if err else f"exit status {p.returncode}"})
            print(f"{v}: did not run: {results[-1]['error']}", flush=True)
        else:
            results.append(json.loads(p.stdout.strip().splitlines()[-1]))
    caps = whole_captures([r["variant"] for r in results if "error" not in r], min(scales)) if a.capture else None
    comparisons = {}
    if a.renders:
        ok = [r["variant"] for r in results if "error" not in r]
        for i, x in enumerate(ok):
            for y in ok[i + 1:]:
                comparisons[f"{x} vs {y}"] = compare_files(Path(a.renders) / f"{x}.npz", Path(a.renders) / f"{y}.npz")
    text = report(results, comparisons, a, machine(), caps)
    out = Path(a.out)
    old = out.read_text() if out.exists() else "# The twin's renders on Mitsuba's variants\n\n"
    out.write_text(old.split(MEASURED)[0].rstrip() + "\n\n" + text)
    if a.json:
        Path(a.json).write_text(json.dumps({"results": results, "comparisons": comparisons, "captures": caps},
                                           indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
