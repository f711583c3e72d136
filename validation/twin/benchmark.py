"""Benchmark of the virtual rig (issue 2): seconds per single-LED render and per derived
18-exposure sequence at scales 0.25 and 1.0, and peak memory of a full-scale capture of
one LED (calibration image + one 18-exposure sequence).

    python -m validation.twin.benchmark [--repeats 3] [--out validation/twin/benchmark.md]

Times are medians over ``--repeats`` runs in this process (first-render JIT compilation
is reported separately); the full-scale capture runs `glossrig simulate` in a child
process whose peak RSS is read from the kernel (ru_maxrss of the child).
"""
from __future__ import annotations

import argparse
import resource
import statistics
import tempfile
import time
from pathlib import Path

from validation.common import capture
from validation.paths import RIG, ROOT


def bench_scale(scale: float, repeats: int) -> dict:
    from glossrig.core.models.materials import parse_material
    from glossrig.core.rig import load_rig
    from glossrig.twin.sensor import frame_rng
    from glossrig.twin.virtual_rig import VirtualRig

    rig = load_rig(RIG)
    t0 = time.perf_counter()
    vr = VirtualRig(rig, parse_material("sample_2_6"), scale=scale, seed=0)
    setup = time.perf_counter() - t0
    t0 = time.perf_counter()
    vr.led_radiance(9)
    first = time.perf_counter() - t0
    renders, seqs = [], []
    for k in range(repeats):
        vr._cache.clear()
        t0 = time.perf_counter()
        rad = vr.led_radiance(9)
        renders.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        for i, t in enumerate(rig.exposure_times_s):
            vr.sensor.expose(rad, t, rig.sequence_iso, rig.sequence_aperture, frame_rng(k, i))
        seqs.append(time.perf_counter() - t0)
    w, h = vr.lens.size
    return {"scale": scale, "size": f"{w}x{h}", "setup_s": setup, "first_render_s": first,
            "render_s": statistics.median(renders), "sequence_s": statistics.median(seqs)}


def full_capture_memory() -> dict:
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        capture(Path(d) / "cap", "sample_2_6", 1.0, 0, "0", 1, leds="9", mode="fresh", stdout=False, stderr=False)
        wall = time.perf_counter() - t0
        peak_kb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
        n = len(list((Path(d) / "cap").glob("*.dng")))
    return {"wall_s": wall, "peak_rss_gb": peak_kb / 1024 ** 2, "dngs": n}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--out", default=str(ROOT / "validation/twin/benchmark.md"))
    a = ap.parse_args()
    from glossrig.twin.mitsuba_env import choose_variant

    rows = [bench_scale(s, a.repeats) for s in (0.25, 1.0)]
    mem = full_capture_memory()
    lines = ["# Virtual rig benchmark", "",
             f"Command: `python -m validation.twin.benchmark --repeats {a.repeats}`; Mitsuba variant "
             f"`{choose_variant()}`, 4 spp, box filter, one LED, material sample_2_6. Medians of {a.repeats} runs.", "",
             "| scale | image | scene set-up (s) | first render incl. JIT (s) | render, one LED (s) | 18-exposure sequence from it (s) |",
             "|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['scale']} | {r['size']} | {r['setup_s']:.2f} | {r['first_render_s']:.2f} | "
                     f"{r['render_s']:.2f} | {r['sequence_s']:.2f} |")
    lines += ["", f"Ratio full/quarter: render {rows[1]['render_s'] / rows[0]['render_s']:.1f}x, "
              f"sequence {rows[1]['sequence_s'] / rows[0]['sequence_s']:.1f}x (pixel ratio 16x).", "",
              "Full-scale capture of one LED (calibration image = 16 single-LED renders, plus one 18-exposure "
              f"sequence, {mem['dngs']} DNGs written): {mem['wall_s']:.0f} s wall, peak RSS "
              f"{mem['peak_rss_gb']:.2f} GB (limit of this machine: 24 GB).", ""]
    Path(a.out).write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
