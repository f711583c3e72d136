"""Turn a target gloss image into an engraver toolpath (thesis 5.2, 7.2).

IMAGE is greyscale: its grey is the nominal scratch coverage, 0 = untouched glossy
sheet, 1 = fully scratched. With --model, IMAGE is a material map of effective
coverages and the model's effective-to-nominal function (thesis eq. 6.7) is applied
first (thesis 7.2.2, 7.2.5). The image is halftoned with discrete-line juxtaposed
halftoning (a/b = 4/7, T = 6: 43 levels), vectorised into scratch lines, rotated onto
the machine's y axis and scaled so that lines sit one scratch thickness (90 um) apart.

DIR receives halftone.png (one pixel per halftone cell, white = scratch), the machine
file (toolpath.gcode or toolpath.rml), preview.svg, preview.png, preview_render.png (the
target beside the predicted print lit by a point light and rendered from the
reproduction model's bases, thesis fig. 7.7; see glossrig.core.fabrication.appearance)
and summary.json. It warns when a colour IMAGE is turned grey and when --width-mm leaves
the halftone too few screen elements for the image's detail (with the width that would
keep it).
Nothing is written when the path would leave the bed or cut deeper than the machine
description allows, or when DIR already holds these files (unless --force; --overwrite is a deprecated
spelling of it).
"""
from __future__ import annotations

import argparse
import logging

from glossrig.cli.outputs import add_force_option, prepare_output

_log = logging.getLogger(__name__)

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
    add_force_option(parser, "existing output files in DIR")
    parser.add_argument("--overwrite", action="store_true", help=argparse.SUPPRESS)   # deprecated: --force


def run(args: argparse.Namespace) -> int:
    from glossrig.core.fabrication import fabricate

    if args.overwrite:
        _log.warning("--overwrite is deprecated; use --force")
    force = args.force or args.overwrite
    names = ("halftone.png", f"toolpath.{args.machine}", "preview.svg", "preview.png", "preview_render.png",
             "summary.json")
    prepare_output(args.out, force, kind="folder", names=names)
    p = fabricate(args.image, args.width_mm, args.out, model=args.model, machine=args.machine_file,
                  language=args.machine, overwrite=force)
    s = p.summary
    w, h = s["print_size_mm"]
    bx = s["machine_frame"]["print_bbox_mm"]
    print(f"print {w:.2f} x {h:.2f} mm, {s['grid'][0]} x {s['grid'][1]} cells of {s['cell_mm'] * 1000:.1f} um; "
          f"rotated onto the bed at x {bx[0]:.2f}..{bx[2]:.2f}, y {bx[1]:.2f}..{bx[3]:.2f} mm")
    print(f"coverage: target {s['coverage']['target_mean']:.4f}, achieved {s['coverage']['achieved']:.4f}")
    print(f"{s['segment_count']} cuts, path {s['path_length_mm'] / 1000:.2f} m "
          f"(cutting {s['cut_length_mm'] / 1000:.2f} m), estimated time {s['estimated_time_s'] / 60:.1f} min")
    r = s["preview_render"]
    _log.info(f"preview_render.png: predicted print rendered in numpy (exact for a flat sheet under one point "
              f"light); {r['lighting']['description']}; {r['model']['source']}")
    _log.info(f"wrote {', '.join(s['files'])} to {args.out}")
    return 0
