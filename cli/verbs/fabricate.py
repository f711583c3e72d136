"""Turn a target gloss image into an engraver toolpath (thesis 5.2, 7.2).

IMAGE is greyscale: its grey is the nominal scratch coverage, 0 = untouched glossy
sheet, 1 = fully scratched. With --model, IMAGE is a material map of effective
coverages and the model's effective-to-nominal function (thesis eq. 6.7) is applied
first (thesis 7.2.2, 7.2.5). The image is halftoned with discrete-line juxtaposed
halftoning (a/b = 4/7, T = 6: 43 levels), vectorised into scratch lines, rotated onto
the machine's y axis and scaled so that lines sit one scratch thickness (90 um) apart.

DIR receives halftone.png (one pixel per halftone cell, white = scratch), the machine
file (toolpath.gcode or toolpath.rml), preview.svg, preview.png and summary.json.
Nothing is written when the path would leave the bed or cut deeper than the machine
description allows, or when DIR already holds these files (unless --overwrite).
"""
from __future__ import annotations

import argparse
import sys

HELP = "halftone a target gloss image into scratch lines and write an engraver toolpath"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("image", metavar="IMAGE", help="greyscale target image (grey = coverage, 0..1)")
    parser.add_argument("--width-mm", type=float, required=True, metavar="W",
                        help="physical width of the print in mm")
    parser.add_argument("--out", required=True, metavar="DIR", help="output directory")
    parser.add_argument("--model", metavar="MODEL_JSON",
                        help="fitted reproduction model (model.json); IMAGE is then a map of effective coverages")
    parser.add_argument("--machine", choices=("gcode", "rml"), default="gcode",
                        help="machine language: G-code or Roland RML-1 (default gcode)")
    parser.add_argument("--machine-file", metavar="TOML", default=None,
                        help="machine description (default scenes/engraver_roland.toml)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output files in DIR")


def run(args: argparse.Namespace) -> int:
    from glossrig.core.fabrication import fabricate

    p = fabricate(args.image, args.width_mm, args.out, model=args.model, machine=args.machine_file,
                  language=args.machine, overwrite=args.overwrite)
    s = p.summary
    w, h = s["print_size_mm"]
    bx = s["machine_frame"]["print_bbox_mm"]
    print(f"print {w:.2f} x {h:.2f} mm, {s['grid'][0]} x {s['grid'][1]} cells of {s['cell_mm'] * 1000:.1f} um; "
          f"rotated onto the bed at x {bx[0]:.2f}..{bx[2]:.2f}, y {bx[1]:.2f}..{bx[3]:.2f} mm")
    print(f"coverage: target {s['coverage']['target_mean']:.4f}, achieved {s['coverage']['achieved']:.4f}")
    print(f"{s['segment_count']} cuts, path {s['path_length_mm'] / 1000:.2f} m "
          f"(cutting {s['cut_length_mm'] / 1000:.2f} m), estimated time {s['estimated_time_s'] / 60:.1f} min")
    print(f"wrote {', '.join(s['files'])} to {args.out}", file=sys.stderr)
    return 0
