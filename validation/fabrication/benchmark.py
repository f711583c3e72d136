"""Benchmark (issue 6): ``glossrig fabricate`` for a 100 mm x 100 mm print at the thesis
resolution (cells of 103.7 um, lines 90 um apart) against a 10 mm x 10 mm one.

    .venv/bin/python -m validation.fabrication.benchmark [--repeats N]

Input: the centre square of the photograph that ships with matplotlib (Grace Hopper),
as grey. Timed in-process: ``fabricate`` (read, halftone, vectorise, lay out, order,
check, write the G-code, both previews and the summary into a fresh directory); the
median of N runs after one warm-up. Also times the run without previews, and one
command-line run per size (including Python start-up and imports). Writes
``benchmark.json`` next to this script.
"""
from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time
from pathlib import Path

import matplotlib
from PIL import Image

from glossrig.core.fabrication import fabricate, plan
from validation.common import glossrig

HERE = Path(__file__).resolve().parent
PHOTO = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"


def _median_time(fn, repeats: int) -> tuple[float, list[float]]:
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return statistics.median(times), times


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    results = {"machine": {"python": platform.python_version(), "cpu_count": os.cpu_count(),
                           "platform": platform.platform()}, "repeats": args.repeats, "sizes": {}}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        im = Image.open(PHOTO).convert("L")
        w, h = im.size
        s = min(w, h)
        square = tmp / "square.png"
        im.crop(((w - s) // 2, (h - s) // 2, (w - s) // 2 + s, (h - s) // 2 + s)).save(square)
        for width in (10.0, 100.0):
            counter = iter(range(10**6))
            full, full_runs = _median_time(
                lambda width=width, counter=counter: fabricate(square, width, tmp / f"out{width:g}_{next(counter)}"),
                args.repeats)
            bare, _ = _median_time(lambda width=width: plan(square, width, previews=False), args.repeats)
            p = plan(square, width, previews=False)
            t = time.perf_counter()
            glossrig("fabricate", square, "--width-mm", width, "--out", tmp / f"cli{width:g}", stdout=False,
                     stderr=False)
            cli = time.perf_counter() - t
            results["sizes"][f"{width:g}mm"] = {
                "print_size_mm": p.summary["print_size_mm"], "grid": p.summary["grid"],
                "cells": p.summary["grid"][0] * p.summary["grid"][1], "segments": p.summary["segment_count"],
                "median_fabricate_s": full, "runs_s": full_runs,
                "median_without_previews_s": bare, "cli_once_s": cli,
                "estimated_machining_time_min": p.summary["estimated_time_s"] / 60}
            print(f"{width:g} mm: median {full:.3f} s (without previews {bare:.3f} s, CLI {cli:.2f} s), "
                  f"{p.summary['grid']} cells, {p.summary['segment_count']} cuts", file=sys.stderr)
    big, small = results["sizes"]["100mm"], results["sizes"]["10mm"]
    results["ratio_100mm_over_10mm"] = {"median_fabricate": big["median_fabricate_s"] / small["median_fabricate_s"],
                                        "without_previews": big["median_without_previews_s"] / small["median_without_previews_s"],
                                        "cells": big["cells"] / small["cells"]}
    (HERE / "benchmark.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results["ratio_100mm_over_10mm"], indent=2))
    return 0


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
