"""Layout (thesis eq. 5.2-5.3), cuts, ordering, checks, machine files and their read-back."""
from __future__ import annotations

import dataclasses
import io
import math
import re

import numpy as np
import pytest
from PIL import Image

from glossrig.core.errors import InputError
from glossrig.core.fabrication import load_machine, plan
from glossrig.core.fabrication.gcode import read_gcode
from glossrig.core.fabrication.halftone import halftone
from glossrig.core.fabrication.layout import Layout, cell_size_mm, make_layout
from glossrig.core.fabrication.machine import DEFAULT_MACHINE_FILE
from glossrig.core.fabrication.rasterize import iou, rasterise_bands, rasterise_cuts
from glossrig.core.fabrication.rml import read_rml
from glossrig.core.fabrication.toolpath import (best_order, check_toolpath, cuts_from_segments, naive_order,
                                                sweep_order)
from glossrig.core.fabrication.vectorize import extract_segments

MACHINE = load_machine()


def _image(tmp_path, name, arr):
    p = tmp_path / name
    Image.fromarray(np.clip(np.rint(arr * 255), 0, 255).astype(np.uint8)).save(p)
    return p


def _photo(tmp_path):
    """A procedural 'photograph': smooth shading, edges and texture (no download)."""
    y, x = np.mgrid[0:150, 0:120] / 150.0
    img = 0.5 + 0.3 * np.sin(7 * x + 3 * y) * np.cos(5 * y) + 0.2 * ((x - 0.4) ** 2 + (y - 0.5) ** 2 < 0.05)
    img += np.random.default_rng(0).normal(0, 0.05, img.shape)
    return _image(tmp_path, "photo.png", np.clip(img, 0, 1))


def _machine_file(tmp_path, **changes):
    text = DEFAULT_MACHINE_FILE.read_text()
    for key, value in changes.items():
        text, n = re.subn(rf"(?m)^{key} = [^#\n]*", f"{key} = {value} ", text)
        assert n == 1, key
    p = tmp_path / "machine.toml"
    p.write_text(text)
    return p


def test_machine_description_carries_the_thesis_figures():
    m = MACHINE
    assert m.resolution_mm == 0.01 and m.max_speed_mm_s == (100.0, 50.0, 100.0)
    assert m.cut_depth_mm == 0.02 and m.scratch_thickness_mm == 0.09
    assert (m.screen.a, m.screen.b, m.screen.T) == (4, 7, 6)
    assert m.cut_feed_mm_s <= m.max_speed_mm_s[1] and m.plunge_feed_mm_s <= m.max_speed_mm_s[2]


@pytest.mark.parametrize("changes, words", [
    ({"cut_depth_mm": "0.040"}, "deeper than the configured limit"),
    ({"cut_depth_mm": "0.025"}, "not a multiple"),
    ({"cut_feed_mm_s": "60.0"}, "exceeds the y-axis limit"),
    ({"plunge_feed_mm_s": "150.0"}, "exceeds the z-axis limit"),
    ({"cut_direction": '"x"'}, "cut_direction"),
    ({"bed_mm": "[0.0, 100.0]"}, "bed_mm"),
    ({"a": "8"}, "steeper than 1"),
])
def test_machine_description_refusals(tmp_path, changes, words):
    with pytest.raises(InputError, match=words) as e:
        load_machine(_machine_file(tmp_path, **changes))
    assert "machine.toml" in str(e.value)


def test_layout_puts_lines_on_y_one_scratch_thickness_apart_on_the_machine_grid():
    layout = make_layout(60, 70, MACHINE)
    bitmap = np.ones((60, 70), bool)
    path = cuts_from_segments(extract_segments(bitmap, MACHINE.screen), layout, MACHINE)
    xs = np.unique(np.round(path.x, 6))
    assert np.allclose(np.diff(xs), 0.09, atol=1e-9)                       # pitch = scratch thickness
    assert np.allclose(xs / 0.01, np.round(xs / 0.01), atol=1e-6)          # on the 10 um grid
    # the unrounded centrelines are exactly parallel to y: both ends have the same x
    X = np.array([0.0, 70.0])
    mx, my = layout.image_to_machine(X, layout.centreline_y(5, X))
    assert mx[0] == pytest.approx(mx[1], abs=1e-9) and abs(my[1] - my[0]) > 1
    assert math.degrees(layout.theta_rad) == pytest.approx(math.degrees(math.atan(4 / 7)) - 90)
    # round trip of the frame change
    X, Y = np.random.default_rng(1).uniform(0, 60, (2, 20))
    back = layout.machine_to_image(*layout.image_to_machine(X, Y))
    assert np.allclose(back, (X, Y))
    # bbox starts at the configured print origin (plus less than one machine step)
    x0, y0, _, _ = layout.bbox_mm()
    assert 0 <= x0 - MACHINE.print_origin_mm[0] < 0.01 and y0 == pytest.approx(MACHINE.print_origin_mm[1])


def test_scaling_by_line_pitch_makes_scratched_area_equal_halftone_coverage():
    """Departure from the thesis' literal 'multiply by the scratch thickness' (layout docstring)."""
    rows, cols = 240, 238
    bitmap = np.ones((rows, cols), bool)
    seg = extract_segments(bitmap, MACHINE.screen)
    ours = make_layout(rows, cols, MACHINE)
    literal = dataclasses.replace(ours, cell_mm=MACHINE.scratch_thickness_mm)   # cell = 90 um, as printed
    areas = []
    for layout in (ours, literal):
        X0, X1 = seg.x0.astype(float), seg.x1 + 1.0
        ax, ay = layout.image_to_machine(X0, layout.centreline_y(seg.k, X0))
        bx, by = layout.image_to_machine(X1, layout.centreline_y(seg.k, X1))
        scratched = np.hypot(bx - ax, by - ay).sum() * MACHINE.scratch_thickness_mm
        areas.append(scratched / (rows * cols * layout.cell_mm ** 2))
    assert areas[0] == pytest.approx(1.0, abs=1e-9)         # full coverage scratches exactly the print
    assert areas[1] == pytest.approx(math.sqrt(65) / 7, rel=1e-9)  # literal: 15 % overlap


def test_rasteriser_matches_brute_force_for_any_direction():
    rng = np.random.default_rng(5)
    shape = (23, 31)
    p0 = rng.uniform(-2, 33, (40, 2))
    p1 = p0 + rng.normal(0, 6, (40, 2))
    width = 0.8
    got = rasterise_bands(p0, p1, width, shape)
    cy, cx = np.mgrid[0:shape[0], 0:shape[1]] + 0.5
    want = np.zeros(shape, bool)
    for a, b in zip(p0, p1):
        d = b - a
        L = np.hypot(*d)
        u = d / L
        along = (cx - a[0]) * u[0] + (cy - a[1]) * u[1]
        across = -(cx - a[0]) * u[1] + (cy - a[1]) * u[0]
        want |= (along >= 0) & (along <= L) & (np.abs(across) <= width / 2)
    assert np.array_equal(got, want)
    assert iou(got, want) == 1.0 and iou(np.zeros(3, bool), np.zeros(3, bool)) == 1.0


@pytest.mark.parametrize("language", ["gcode", "rml"])
def test_machine_file_reproduces_the_halftone_and_stays_in_bed_and_print(tmp_path, language):
    p = plan(_photo(tmp_path), 12.0, language=language, previews=False)
    text = p.files["toolpath.gcode" if language == "gcode" else "toolpath.rml"].decode()
    moves = read_gcode(text) if language == "gcode" else read_rml(text, MACHINE)
    cut = moves.cutting(-0.02)
    assert cut.sum() == len(p.toolpath) > 100
    # rasterising the file's cutting moves back onto the grid gives the halftone
    halftone_png = np.asarray(Image.open(io.BytesIO(p.files["halftone.png"]))) > 127
    raster = rasterise_cuts(moves.start[cut, :2], moves.end[cut, :2], p.layout, MACHINE.scratch_thickness_mm)
    assert iou(raster, halftone_png) > 0.99
    assert iou(raster, halftone_png) == 1.0
    # every coordinate in the bed and in the rotated print's bbox (as summary.json states)
    frame = p.summary["machine_frame"]
    pts = np.concatenate([moves.start, moves.end])
    pts = pts[~np.isnan(pts[:, 0])]
    x0, y0, x1, y1 = frame["print_bbox_mm"]
    assert frame["inside_bed"] and frame["inside_print_bbox"]
    assert pts[:, 0].min() >= x0 and pts[:, 0].max() <= x1 and pts[:, 1].min() >= y0 and pts[:, 1].max() <= y1
    assert pts[:, 0].min() >= 0 and pts[:, 0].max() <= 305 and pts[:, 1].min() >= 0 and pts[:, 1].max() <= 230
    # cuts at the scalpel depth, straight along +y (the blade's one cutting direction)
    d = moves.end[cut] - moves.start[cut]
    assert np.all(d[:, 0] == 0) and np.all(d[:, 1] > 0) and np.all(moves.start[cut, 2] == -0.02)
    # air moves at the safe height; the only Z moves are plunges/retracts at a fixed XY
    xy = np.any(moves.end[:, :2] != moves.start[:, :2], axis=1) & ~np.isnan(moves.start[:, 0])
    air = xy & ~cut
    assert air.sum() >= cut.sum() and np.all(moves.end[air, 2] == 0.5) and np.all(moves.start[air, 2] == 0.5)
    assert np.all(moves.rapid[air])
    zmove = ~xy & ~np.isnan(moves.start[:, 2])
    assert set(np.round(moves.end[zmove, 2], 6)) == {-0.02, 0.5}
    # feeds within the axis limits (thesis 5.1.1)
    assert np.nanmax(moves.feed_mm_s[cut]) <= 50.0
    plunge = zmove & (moves.end[:, 2] < moves.start[:, 2])
    assert np.nanmax(moves.feed_mm_s[plunge]) <= 100.0


def test_gcode_and_rml_cut_the_same_lines(tmp_path):
    img = _photo(tmp_path)
    g = read_gcode(plan(img, 8.0, language="gcode", previews=False).files["toolpath.gcode"].decode())
    r = read_rml(plan(img, 8.0, language="rml", previews=False).files["toolpath.rml"].decode(), MACHINE)
    cg, cr = g.cutting(-0.02), r.cutting(-0.02)
    key = lambda m, c: sorted(map(tuple, np.round(np.concatenate([m.start[c], m.end[c]], 1), 4).tolist()))
    assert key(g, cg) == key(r, cr)


def test_estimate_matches_the_time_of_the_written_gcode(tmp_path):
    p = plan(_photo(tmp_path), 10.0, previews=False)
    m = read_gcode(p.files["toolpath.gcode"].decode())
    known = ~np.isnan(m.start).any(axis=1)
    d = np.abs(m.end[known] - m.start[known])
    rapid, feed = m.rapid[known], m.feed_mm_s[known]
    t_rapid = np.maximum.reduce([d[:, 0] / 100, d[:, 1] / 50, d[:, 2] / 100])[rapid].sum()
    t_feed = (np.linalg.norm(d, axis=1)[~rapid] / feed[~rapid]).sum()
    s = p.summary
    # the first air move starts from wherever the machine is; the estimate counts it from home
    dx, dy = p.toolpath.travel_legs()
    first = max(abs(dx[0]) / 100, abs(dy[0]) / 50)
    assert t_rapid + t_feed + first == pytest.approx(s["estimated_time_s"], rel=1e-9)
    cut_len = np.abs(p.toolpath.y_end - p.toolpath.y_start).sum()
    assert s["cut_length_mm"] == pytest.approx(cut_len)
    assert s["path_length_mm"] == pytest.approx(s["cut_length_mm"] + s["travel_length_mm"] + s["z_length_mm"])


def test_sweep_order_shortens_air_moves_and_never_loses(tmp_path):
    sparse = plan(_image(tmp_path, "sparse.png", np.full((100, 100), 0.05)), 25.0, previews=False)
    path = sparse.toolpath
    t = {}
    for name, order in (("naive", naive_order(path, MACHINE)), ("sweep", sweep_order(path, MACHINE))):
        assert np.array_equal(np.sort(order), np.arange(len(path)))                 # a permutation
        t[name] = MACHINE.travel_time_s(*path.reordered(order).travel_legs()).sum()
    assert t["sweep"] < 0.8 * t["naive"]
    for img in (_photo(tmp_path), _image(tmp_path, "mid.png", np.full((50, 50), 0.3))):
        path = plan(img, 15.0, previews=False).toolpath
        order, _ = best_order(path, MACHINE)
        legs = lambda o, path=path: MACHINE.travel_time_s(*path.reordered(o).travel_legs()).sum()
        assert legs(order) <= legs(naive_order(path, MACHINE))


def test_cut_direction_minus_y(tmp_path):
    m = load_machine(_machine_file(tmp_path, cut_direction='"-y"'))
    p = plan(_photo(tmp_path), 6.0, machine=m, previews=False)
    moves = read_gcode(p.files["toolpath.gcode"].decode())
    cut = moves.cutting(-0.02)
    assert np.all(moves.end[cut, 1] < moves.start[cut, 1])
    raster = rasterise_cuts(moves.start[cut, :2], moves.end[cut, :2], p.layout, 0.09)
    assert iou(raster, p.bitmap) == 1.0


def test_refuses_paths_off_the_bed_and_too_deep(tmp_path):
    img = _image(tmp_path, "g.png", np.full((40, 40), 0.5))
    with pytest.raises(InputError, match="outside the bed") as e:
        plan(img, 200.0, previews=False)          # rotated: ~270 x 270 mm > 305 x 230
    assert "engraver_roland.toml" in str(e.value)
    m = load_machine(_machine_file(tmp_path, print_origin_mm="[250.0, 5.0]"))
    with pytest.raises(InputError, match="outside the bed"):
        plan(img, 60.0, machine=m, previews=False)
    # a toolpath deeper than the limit is refused by the check itself
    p = plan(img, 5.0, previews=False)
    deep = dataclasses.replace(p.toolpath, cut_z=-0.05)
    with pytest.raises(InputError, match="exceeds the configured limit"):
        check_toolpath(deep, MACHINE, p.layout.bbox_mm())
    # and a path pushed off the bed by the check of the finished path
    off = dataclasses.replace(p.toolpath, x=p.toolpath.x + 300.0)
    with pytest.raises(InputError, match="outside the bed"):
        check_toolpath(off, MACHINE, p.layout.bbox_mm())
    backwards = dataclasses.replace(p.toolpath, y_start=p.toolpath.y_end, y_end=p.toolpath.y_start)
    with pytest.raises(InputError, match="cutting direction"):
        check_toolpath(backwards, MACHINE, p.layout.bbox_mm())
    check_toolpath(p.toolpath, MACHINE, p.layout.bbox_mm())


def test_layout_json_round_trip():
    layout = make_layout(36, 49, MACHINE)
    assert Layout.from_json(layout.to_json()) == layout
    with pytest.raises(InputError):
        Layout.from_json({"a": 4})
    assert layout.cell_mm == pytest.approx(cell_size_mm(0.09, MACHINE.screen))
    assert halftone(np.full((36, 49), 0.5), MACHINE.screen).shape == (36, 49)
