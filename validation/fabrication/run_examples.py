"""Fabrication examples and checks (issue 6): regenerates the folders next to this script
and ``results.json``.

    .venv/bin/python validation/fabrication/run_examples.py

- ``gradient/``: thesis 7.2.2's gamut gradient (coverage 1 on the left down to 0 on the
  right), 40 mm wide, G-code.
- ``photo/``: a photograph (Grace Hopper, the sample image that ships with matplotlib),
  25 mm wide, G-code.
- ``gradient_etn/``: the gradient read as effective coverages through a demonstration
  reproduction model (``demo_model.json``), RML-1. Its ETN is eq. 6.7 (offset form) fitted here to the
  effective/nominal coverages the thesis reports for the second base (table 6.4); it
  stands in for the model that ``core/reproduction/model.py`` fits from measurements.

Checks, for every example: the machine file's cutting moves rasterised back onto the
halftone grid against ``halftone.png`` (IoU), every coordinate inside the bed and the
rotated print's bounding box, cutting moves at the scalpel depth and air moves at the
safe height. Also: every 8-bit constant grey halftones to exactly its nearest level
k/42; and the air time of the cut order against line-by-line order for several band
widths (the choice of ``travel_band_mm``).
"""
from __future__ import annotations

import dataclasses
import json
import sys
import tempfile
from pathlib import Path

import matplotlib
import numpy as np
from PIL import Image
from scipy.optimize import curve_fit

from glossrig.core.atomic import atomic_write_json
from glossrig.core.fabrication import fabricate, load_machine, plan
from glossrig.core.fabrication.gcode import read_gcode
from glossrig.core.fabrication.halftone import grid_shape, halftone
from glossrig.core.fabrication.layout import Layout, cell_size_mm
from glossrig.core.fabrication.pipeline import read_summary
from glossrig.core.fabrication.rasterize import iou, rasterise_cuts
from glossrig.core.fabrication.rml import read_rml
from glossrig.core.fabrication.toolpath import naive_order, sweep_order
from glossrig.core.reproduction.model import KIND as MODEL_KIND

HERE = Path(__file__).resolve().parent
PHOTO = Path(matplotlib.get_data_path()) / "sample_data" / "grace_hopper.jpg"

# thesis table 6.4, second base: fitted effective coverage -> nominal coverage of the samples
TABLE_6_4_CE = [0.0, 0.39, 0.63, 0.72, 0.76, 0.86, 1.0, 1.0]
TABLE_6_4_CN = [0.0, 0.17, 0.33, 0.4, 0.5, 0.7, 0.83, 1.0]


def eq_6_7(x, g1, g2, g3, g4):
    """Eq. 6.7 with the offset outside the fraction (the project's reading, see core/reproduction/model.py)."""
    return g1 / (g3 + np.exp(-g2 * x)) + g4


def demo_model(path: Path) -> dict:
    gamma, _ = curve_fit(eq_6_7, np.array(TABLE_6_4_CE), np.array(TABLE_6_4_CN), p0=[1, 1, 1, 0], maxfev=20000)
    rms = float(np.sqrt(np.mean((eq_6_7(np.array(TABLE_6_4_CE), *gamma) - TABLE_6_4_CN) ** 2)))
    doc = {"kind": MODEL_KIND,
           "note": "demonstration only: ETN of thesis eq. 6.7 fitted to thesis table 6.4 (second base) "
                   "by validation/fabrication/run_examples.py",
           "etn": {"form": "eq6.7-offset", "gamma": [float(g) for g in gamma], "fit_rms": rms}}
    atomic_write_json(path, doc, indent=2)
    return doc


def check_output(out: Path, machine) -> dict:
    s = read_summary(out)
    layout = Layout.from_json(s["layout"])
    name = s["machine_output"]
    text = (out / name).read_text()
    moves = read_gcode(text) if name.endswith(".gcode") else read_rml(text, machine)
    cut_z, safe_z = s["machine_frame"]["cut_z_mm"], s["machine_frame"]["travel_z_mm"]
    cut = moves.cutting(cut_z)
    ht = np.asarray(Image.open(out / "halftone.png")) > 127
    raster = rasterise_cuts(moves.start[cut, :2], moves.end[cut, :2], layout, machine.scratch_thickness_mm)
    pts = np.concatenate([moves.start, moves.end])
    pts = pts[~np.isnan(pts).any(axis=1)]
    x0, y0, x1, y1 = s["machine_frame"]["print_bbox_mm"]
    W, H = s["machine_frame"]["bed_mm"]
    xy = np.any(moves.end[:, :2] != moves.start[:, :2], axis=1) & ~np.isnan(moves.start[:, 0])
    air = xy & ~cut
    return {
        "iou_machine_file_vs_halftone": iou(raster, ht),
        "cutting_moves": int(cut.sum()), "segment_count": s["segment_count"],
        "inside_bed": bool(pts[:, 0].min() >= 0 and pts[:, 1].min() >= 0 and pts[:, 0].max() <= W and pts[:, 1].max() <= H),
        "inside_print_bbox": bool(pts[:, 0].min() >= x0 and pts[:, 1].min() >= y0
                                  and pts[:, 0].max() <= x1 and pts[:, 1].max() <= y1),
        "all_cuts_at_depth_along_cut_direction": bool(np.all(moves.start[cut, 2] == cut_z) and np.all(
            np.sign(moves.end[cut, 1] - moves.start[cut, 1]) == (1 if s["machine_frame"]["cut_direction"] == "+y" else -1))),
        "all_air_moves_at_safe_height": bool(np.all(moves.start[air, 2] == safe_z) and np.all(moves.end[air, 2] == safe_z)),
        "print_size_mm": s["print_size_mm"], "grid": s["grid"],
        "coverage": s["coverage"], "estimated_time_s": s["estimated_time_s"],
        "path_length_mm": s["path_length_mm"], "cut_length_mm": s["cut_length_mm"],
        "travel": s["travel"],
    }


def constant_grey_exactness(machine) -> dict:
    cell = cell_size_mm(machine.scratch_thickness_mm, machine.screen)
    rows, cols = grid_shape((100, 100), 10.0, cell, machine.screen)
    wrong = []
    for v in range(256):
        bitmap = halftone(np.full((rows, cols), v / 255.0), machine.screen)
        k = round(v / 255 * machine.screen.pixels)
        if bitmap.sum() * machine.screen.pixels != k * rows * cols:
            wrong.append(v)
    return {"grid": [rows, cols], "grey_values_tested": 256, "not_exactly_nearest_level": wrong}


def band_study(machine, inputs: dict[str, Path], width_mm: float = 50.0) -> dict:
    out = {}
    for name, img in inputs.items():
        path = plan(img, width_mm, machine=machine, previews=False).toolpath
        naive = machine.travel_time_s(*path.reordered(naive_order(path, machine)).travel_legs()).sum()
        row = {"cuts": len(path), "naive_air_time_s": float(naive)}
        for band in (1.0, 2.0, 4.0, 8.0):
            m = dataclasses.replace(machine, travel_band_mm=band)
            t = m.travel_time_s(*path.reordered(sweep_order(path, m)).travel_legs()).sum()
            row[f"band_{band:g}mm_over_naive"] = round(float(t / naive), 3)
        out[name] = row
    return out


def main() -> int:
    machine = load_machine()
    gradient = np.tile(np.linspace(1.0, 0.0, 600), (150, 1))          # thesis 7.2.2: 1 on the left -> 0
    results: dict = {}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        grad_png = tmp / "gradient.png"
        Image.fromarray(np.rint(gradient * 255).astype(np.uint8)).save(grad_png)
        model = HERE / "demo_model.json"
        results["demo_model"] = demo_model(model)["etn"]
        runs = {"gradient": (grad_png, 40.0, None, "gcode"),
                "photo": (PHOTO, 25.0, None, "gcode"),
                "gradient_etn": (grad_png, 40.0, model, "rml")}
        for name, (img, width, mdl, lang) in runs.items():
            fabricate(img, width, HERE / name, model=mdl, language=lang, overwrite=True)
            # the summary names the input; record it relative to the repository
            s_path = HERE / name / "summary.json"
            s = read_summary(s_path)
            s["input"] = "gradient.png (generated by run_examples.py)" if img == grad_png else f"matplotlib sample_data/{img.name}"
            if mdl is not None:
                s["model"] = "validation/fabrication/demo_model.json"
            s["machine_file"] = "scenes/engraver_roland.toml"
            s_path.write_text(json.dumps(s, indent=2) + "\n")
            results[name] = check_output(HERE / name, machine)
            print(f"{name}: IoU {results[name]['iou_machine_file_vs_halftone']:.6f}, "
                  f"{results[name]['segment_count']} cuts, {results[name]['estimated_time_s'] / 60:.1f} min",
                  file=sys.stderr)
        results["constant_grey_exactness"] = constant_grey_exactness(machine)
        consts = {}
        for c in (0.05, 0.3, 0.9):
            p = tmp / f"c{c}.png"
            Image.fromarray(np.full((100, 100), round(c * 255), np.uint8)).save(p)
            consts[f"constant_{c:g}"] = p
        results["travel_band_study_50mm"] = band_study(machine, {"gradient": grad_png, "photo": PHOTO, **consts})
    (HERE / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    from validation.common import run_main

    raise SystemExit(run_main(main))
