"""Target gloss image -> engraver toolpath, end to end (thesis 5.2, 7.2.2, 7.2.5).

:func:`plan` does all the work in memory: read the image (grey = nominal coverage, or
effective coverage when a reproduction model is given, whose ETN is applied after
resampling, thesis 7.2.2/7.2.5), size the halftone grid from the print width, halftone
(juxtaposed, :mod:`.halftone`), vectorise along the discrete lines (:mod:`.vectorize`),
lay out on the machine (:mod:`.layout`, eq. 5.2-5.3), order the cuts
(:mod:`.toolpath`), check bed and depth, and render the machine file and previews,
among them ``preview_render.png``, the predicted print lit and rendered beside the
target (:mod:`.appearance`, thesis fig. 7.7). It warns (logging) when a colour image is
turned grey (:mod:`.inputs`) and when the width leaves the halftone too few screen
elements for the image's detail (:func:`.appearance.detail_loss`; the numbers are in
``summary.json`` under ``"detail"``). :func:`write` then writes them. Nothing is written when any step refuses, and existing
files are not overwritten unless asked.
"""
from __future__ import annotations

import io
import json
import logging
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

from glossrig.core.atomic import atomic_write_bytes
from glossrig.core.errors import InputError
from glossrig.core.fabrication.appearance import detail_loss, detail_warning, load_gloss_model, preview_render
from glossrig.core.fabrication.gcode import write_gcode
from glossrig.core.fabrication.halftone import coverage_levels, grid_shape, halftone
from glossrig.core.fabrication.inputs import load_coverage_image, resample
from glossrig.core.fabrication.layout import Layout, cell_size_mm, make_layout
from glossrig.core.fabrication.machine import Machine, load_machine
from glossrig.core.fabrication.preview import png_preview, svg_preview
from glossrig.core.fabrication.rml import write_rml
from glossrig.core.fabrication.toolpath import Toolpath, best_order, check_print_fits, check_toolpath, cuts_from_segments, estimate, naive_order
from glossrig.core.fabrication.vectorize import Segments, extract_segments
from glossrig.core.reproduction.model import load_etn
from glossrig.core.toml_input import read_json

LANGUAGES = {"gcode": "toolpath.gcode", "rml": "toolpath.rml"}
MAX_CELLS = 60_000_000
SUMMARY_KIND = "glossrig.fabrication_summary"

_log = logging.getLogger(__name__)


@dataclass
class Plan:
    """Everything a fabrication run writes, computed before anything is written."""

    coverage: np.ndarray            # target nominal coverage on the grid
    bitmap: np.ndarray              # halftone, True = scratch
    segments: Segments
    layout: Layout
    toolpath: Toolpath
    machine: Machine
    language: str
    summary: dict
    files: dict[str, bytes] = field(default_factory=dict)


def _png(arr: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(arr).save(buf, format="PNG", optimize=False)
    return buf.getvalue()


def plan(image: str | Path, width_mm: float, *, model: str | Path | None = None,
         machine: Machine | str | Path | None = None, language: str = "gcode",
         previews: bool = True) -> Plan:
    """Compute a fabrication run (module docstring). Raises ``InputError`` on bad input."""
    if language not in LANGUAGES:
        raise InputError(f"--machine must be one of {sorted(LANGUAGES)}, got {language!r}")
    try:
        width_mm = float(width_mm)
    except (TypeError, ValueError):
        raise InputError(f"--width-mm must be a number of millimetres, got {width_mm!r}") from None
    if not math.isfinite(width_mm) or width_mm <= 0:
        raise InputError(f"--width-mm must be a positive number of millimetres, got {width_mm:g}")
    m = machine if isinstance(machine, Machine) else load_machine(machine)
    etn = load_etn(model) if model is not None else None
    gloss = load_gloss_model(model, etn) if previews else None      # preview_render.png (appearance.py)
    grey = load_coverage_image(image)

    cell = cell_size_mm(m.scratch_thickness_mm, m.screen)
    rows, cols = grid_shape(grey.shape, width_mm, cell, m.screen)
    if rows * cols > MAX_CELLS:
        raise InputError(f"--width-mm {width_mm:g}: a {cols * cell:.0f} x {rows * cell:.0f} mm print needs "
                         f"{rows} x {cols} halftone cells of {cell * 1000:.1f} um (limit {MAX_CELLS})")
    layout = make_layout(rows, cols, m)
    check_print_fits(layout, m)
    detail = detail_loss(grey, (rows, cols), m.screen, cell)
    if (msg := detail_warning(detail, width_mm)) is not None:
        _log.warning(msg)
    grid = resample(grey, (rows, cols))
    clipped = 0
    if etn is not None:
        nominal = etn.raw(grid)                                # clipped below, and counted
        if not np.all(np.isfinite(nominal)):
            raise InputError("ETN gives non-finite nominal coverages for this image", path=model)
        clipped = int(np.count_nonzero((nominal < 0) | (nominal > 1)))
        coverage = np.clip(nominal, 0.0, 1.0)
    else:
        coverage = grid

    bitmap = halftone(coverage, m.screen)
    segments = extract_segments(bitmap, m.screen)
    path = cuts_from_segments(segments, layout, m)
    naive = path.reordered(naive_order(path, m))
    order, order_name = best_order(path, m)
    path = path.reordered(order)
    bbox = layout.bbox_mm()
    check_toolpath(path, m, bbox)

    retract = m.max_speed_mm_s[2] if language == "gcode" else m.plunge_feed_mm_s
    est = estimate(path, m, retract)
    est_naive = estimate(naive, m, retract)
    levels = coverage_levels(coverage, m.screen)
    xs = np.concatenate([path.x, [path.home[0]]])
    ys = np.concatenate([path.y_start, path.y_end, [path.home[1]]])
    W, H = m.bed_mm
    summary = {
        "kind": SUMMARY_KIND,
        "input": str(image), "model": None if model is None else str(model),
        "etn": None if etn is None else {"gamma": list(etn.gamma), "form": etn.form,
                                         "clipped_pixels": clipped},
        "machine_file": m.path, "machine": m.name, "language": language,
        "machine_output": LANGUAGES[language],
        "requested_width_mm": width_mm,
        "print_size_mm": list(layout.size_mm),
        "grid": [rows, cols], "cell_mm": cell,
        "screen": {"a": m.screen.a, "b": m.screen.b, "T": m.screen.T,
                   "pixels": m.screen.pixels, "levels": m.screen.levels},
        **est.to_json(),
        "travel": {"order": order_name,
                   "travel_length_mm": est.travel_length_mm, "travel_time_s": est.travel_time_s,
                   "naive_line_by_line_travel_length_mm": est_naive.travel_length_mm,
                   "naive_line_by_line_travel_time_s": est_naive.travel_time_s},
        "coverage": {"target_mean": float(coverage.mean()),
                     "nearest_level_mean": float(levels.mean() / m.screen.pixels),
                     "achieved": float(bitmap.mean()),
                     "scratched_cells": int(np.count_nonzero(bitmap))},
        "machine_frame": {
            "bed_mm": [W, H],
            "print_bbox_mm": list(bbox),
            "path_bbox_mm": [float(xs.min()), float(ys.min()), float(xs.max()), float(ys.max())],
            "inside_bed": bool(xs.min() >= 0 and ys.min() >= 0 and xs.max() <= W and ys.max() <= H),
            "inside_print_bbox": bool(xs.min() >= bbox[0] - 1e-9 and ys.min() >= bbox[1] - 1e-9
                                      and xs.max() <= bbox[2] + 1e-9 and ys.max() <= bbox[3] + 1e-9),
            "home_mm": list(path.home),
            "cut_direction": "+y" if m.cut_direction > 0 else "-y",
            "cut_z_mm": path.cut_z, "travel_z_mm": path.safe_z, "max_depth_mm": m.max_depth_mm,
            "cut_feed_mm_s": m.cut_feed_mm_s, "plunge_feed_mm_s": m.plunge_feed_mm_s,
            "scratch_thickness_mm": m.scratch_thickness_mm,
        },
        "layout": layout.to_json(),
    }
    p = Plan(coverage, bitmap, segments, layout, path, m, language, summary)
    header = [f"glossrig fabricate {Path(image).name}: {layout.size_mm[0]:.2f} x {layout.size_mm[1]:.2f} mm print, "
              f"{rows} x {cols} cells of {cell * 1000:.1f} um, screen a/b={m.screen.a}/{m.screen.b} T={m.screen.T}"]
    code = write_gcode(path, m, header) if language == "gcode" else write_rml(path, m)
    p.files = {"halftone.png": _png(np.where(bitmap, 255, 0).astype(np.uint8)),
               LANGUAGES[language]: code.encode("ascii")}
    if previews:
        title = f"glossrig fabricate {Path(image).name}"
        p.files["preview.svg"] = svg_preview(coverage, layout, path, m, title).encode("utf-8")
        p.files["preview.png"] = _png(png_preview(coverage, layout, path, m))
        label = ("target (grey = effective coverage)" if etn is not None
                 else "target (grey = coverage, white = scratched)")
        assert gloss is not None            # loaded above when previews is set
        render, summary["preview_render"] = preview_render(grey, bitmap, m.screen, layout.size_mm, gloss,
                                                           target_label=label)
        p.files["preview_render.png"] = _png(render)
    summary["detail"] = detail
    summary["files"] = sorted([*p.files, "summary.json"])
    p.files["summary.json"] = (json.dumps(summary, indent=2) + "\n").encode("utf-8")
    return p


def read_summary(path: str | Path) -> dict:
    """The ``summary.json`` of a fabrication run (:func:`plan`, :func:`write`; ``path``: the
    file or the output folder): the one reader of the file. Errors name the file."""
    path = Path(path)
    if path.is_dir():
        path = path / "summary.json"
    d = read_json(path, "fabrication summary")
    if not isinstance(d, dict) or d.get("kind") != SUMMARY_KIND:
        got = d.get("kind") if isinstance(d, dict) else type(d).__name__
        raise InputError(f"not a fabrication summary (kind {got!r}, expected {SUMMARY_KIND!r})", path=path)
    return d


def write(p: Plan, out_dir: str | Path, *, overwrite: bool = False) -> list[Path]:
    """Write a plan's files into ``out_dir`` (created if needed).

    Refuses, before writing anything, when any of the files exists and ``overwrite`` is
    false (design.md: nothing already written is lost or overwritten). Each file is
    written atomically (:func:`glossrig.core.atomic.atomic_write_bytes`).
    """
    out = Path(out_dir)
    if out.exists() and not out.is_dir():
        raise InputError("--out exists and is not a directory", path=out)
    existing = [name for name in p.files if (out / name).exists()]
    if existing and not overwrite:
        raise InputError(f"would overwrite {', '.join(sorted(existing))} (use --force to overwrite); nothing written", path=out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for name, data in p.files.items():
        written.append(atomic_write_bytes(out / name, data))
    return written


def fabricate(image, width_mm, out_dir, *, model=None, machine=None, language="gcode",
              overwrite: bool = False) -> Plan:
    """:func:`plan` then :func:`write`; returns the plan (its ``summary`` is ``summary.json``)."""
    p = plan(image, width_mm, model=model, machine=machine, language=language)
    write(p, out_dir, overwrite=overwrite)
    return p
