"""``preview_render.png`` (issue 17: the predicted print lit and rendered beside the target,
thesis fig. 7.7) and the two warnings of ``glossrig fabricate``: a colour target turned
grey, and a width that leaves the halftone too few screen elements for the image's detail.

Expected values are derived here from the extended Ward formula (thesis eq. 4.79) written
out by hand, not from the renderer: at the mirror point of the sheet the half vector is
the normal, so the Ward exponent is 0 whatever the lobe's rotation.
"""
from __future__ import annotations

import json
import logging
import math

import numpy as np
import pytest
from PIL import Image

from glossrig.cli.main import main
from glossrig.core.fabrication import load_machine, plan
from glossrig.core.fabrication.appearance import (GlossModel, Lighting, load_gloss_model, printed_coverage,
                                                   render_print)
from glossrig.core.fabrication.halftone import halftone
from glossrig.core.models.ward import WardParams

SCREEN = load_machine().screen


def _save(tmp_path, arr, name):
    p = tmp_path / name
    Image.fromarray(arr).save(p)
    return p


def _ward_at_mirror(p: WardParams, theta: float) -> float:
    """Eq. 4.79 with theta_h = 0 and theta_i = theta_o = theta."""
    return p.rho_d / math.pi + p.rho_s / (4 * math.pi * p.alpha_x * p.alpha_y * math.cos(theta))


def test_printed_coverage_of_a_constant_level_is_exactly_that_level():
    for n in (0, 5, 13, 29, 42):
        bm = halftone(np.full((60, 70), n / 42), SCREEN)
        assert np.array_equal(printed_coverage(bm, SCREEN), np.full((60, 70), n / 42))


def test_the_mirror_point_radiance_is_the_ward_peak_and_scratching_lowers_it():
    """A print of coverage 0 (base 1) and one of coverage 1 (base 2 through Table 6.4),
    point light and camera 30 deg either side, 3 sizes away: at the sheet's centre
    L = f(mirror) I cos(30 deg) / D^2 exactly; the thesis's base 2 has the lower peak."""
    model = load_gloss_model()
    assert model.effective_coverage([0.0, 1.0]).tolist() == [0.0, 1.0]
    size, light = (20.0, 20.0), Lighting()
    D, th = 3 * 20.0, math.radians(30)
    shape = (101, 101)                         # a pixel centre at the sheet's centre
    out = {}
    for ce, base in ((0.0, model.base1), (1.0, model.base2)):
        L = render_print(np.full((42, 42), ce), size, model, SCREEN, light, shape)
        expected = _ward_at_mirror(base, th) * math.cos(th) / D ** 2
        assert L[50, 50] == pytest.approx(expected, rel=1e-9)
        out[ce] = L[50, 50]
    # the model's prediction (thesis bases): more scratching, lower specular peak
    assert _ward_at_mirror(model.base2, th) < _ward_at_mirror(model.base1, th)
    assert out[1.0] < out[0.0]


def test_a_scratched_lobe_is_a_streak_across_the_scratches():
    """Light and camera on the normal: the highlight of a strongly anisotropic scratched
    base is elongated perpendicular to the scratch lines (direction (b, a) in image
    columns, rows), as on brushed metal."""
    b2 = WardParams(0.05, 0.05, 0.3, 0.03, 1.1)
    model = GlossModel(b2, b2, (0.0, 1.0), (0.0, 1.0), "test")
    L = render_print(np.ones((8, 8)), (30.0, 30.0), model, SCREEN,
                     Lighting(view_zenith_deg=0, light_zenith_deg=0, view_distance=2, light_distance=2), (201, 201))
    w = L - L.min()
    r, c = np.mgrid[0:201, 0:201]
    m = [np.sum(w * v) / w.sum() for v in (r, c)]
    cov = np.cov(np.stack([(c - m[1]).ravel(), (r - m[0]).ravel()]), aweights=w.ravel())
    evals, evecs = np.linalg.eigh(cov)
    major = evecs[:, 1]                         # (column, row) direction of the streak
    scratch = np.array([SCREEN.b, SCREEN.a]) / math.hypot(SCREEN.a, SCREEN.b)
    assert evals[1] > 4 * evals[0]
    assert abs(major @ scratch) < math.sin(math.radians(3))


def test_preview_render_has_two_panels_and_scratched_half_differs_as_predicted(tmp_path):
    """Left half unscratched, right half fully scratched. Off the highlight (the top
    corners, mirror images of each other about the plane of light and camera) the
    scratched half is brighter, as the thesis bases' rho_d (0.052 > 0.0374) predict;
    the two panels are the target and the render."""
    img = np.zeros((120, 120), np.uint8)
    img[:, 60:] = 255
    p = plan(_save(tmp_path, img, "halves.png"), 12.0)
    png = np.asarray(Image.open(__import__("io").BytesIO(p.files["preview_render.png"])))
    assert png.ndim == 3 and png.std() > 10
    info = p.summary["preview_render"]
    assert info["panels"] == ["target", "predicted print"]
    rows, cols = info["panel_px"]
    H = png.shape[0]
    assert png.shape[1] == 2 * cols + 10 and H > rows
    white_gap = png[H - rows:, cols:cols + 10]
    assert np.all(white_gap == 255)
    left, right = png[H - rows:, :cols, 0].astype(int), png[H - rows:, cols + 10:, 0].astype(int)
    assert left[:, :cols // 2 - 5].max() < 10 and left[:, cols // 2 + 5:].min() > 245    # the target as given
    k = 6
    top_left, top_right = right[:k, :k].mean(), right[:k, -k:].mean()
    assert model_rho_d_order() and top_right > top_left + 2
    assert right.max() == 255 and right.std() > 5              # a highlight, not a blank panel


def model_rho_d_order() -> bool:
    m = load_gloss_model()
    return m.base2.rho_d > m.base1.rho_d


def test_a_colour_target_warns_and_a_grey_one_does_not(tmp_path, caplog):
    rgb = np.zeros((60, 80, 3), np.uint8)
    rgb[:, :40] = (200, 30, 30)
    rgb[:, 40:] = (30, 30, 200)
    grey_rgb = np.repeat(np.linspace(0, 255, 80).astype(np.uint8)[None, :, None], 60, 0).repeat(3, 2)
    with caplog.at_level(logging.WARNING, logger="glossrig"):
        plan(_save(tmp_path, rgb, "colour.png"), 10.0, previews=False)
    msgs = [r.getMessage() for r in caplog.records if "colour" in r.getMessage()]
    assert len(msgs) == 1 and "0.299 R + 0.587 G + 0.114 B" in msgs[0] and "colour.png" in msgs[0]
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="glossrig"):
        plan(_save(tmp_path, grey_rgb, "grey_rgb.png"), 10.0, previews=False)
        plan(_save(tmp_path, grey_rgb[..., 0].copy(), "grey_l.png"), 10.0, previews=False)
    assert not [r for r in caplog.records if "colour" in r.getMessage()]


def test_fine_detail_at_a_tiny_width_warns_with_a_width_that_keeps_it(tmp_path, caplog):
    """A checkerboard of 4 px squares, 256 px across, printed 3 mm wide (about 4 screen
    elements) loses nearly all its contrast; a smooth gradient printed 20 mm wide loses
    none of note."""
    cb = ((np.indices((256, 256)) // 4).sum(0) % 2 * 255).astype(np.uint8)
    with caplog.at_level(logging.WARNING, logger="glossrig"):
        p = plan(_save(tmp_path, cb, "checker.png"), 3.0, previews=False)
    d = p.summary["detail"]
    assert d["lost_fraction"] > 0.9
    msgs = [r.getMessage() for r in caplog.records if "screen elements" in r.getMessage()]
    assert len(msgs) == 1 and "--width-mm 3 " in msgs[0]
    # the checker's period is 8 px: two elements per period (one per square) keep it
    assert d["width_to_keep_mm"] > 3.0 and d["width_to_keep_mm"] <= d["width_one_element_per_pixel_mm"] + 1e-9
    caplog.clear()
    grad = np.tile(np.linspace(0, 255, 300), (100, 1)).astype(np.uint8)
    with caplog.at_level(logging.WARNING, logger="glossrig"):
        p = plan(_save(tmp_path, grad, "grad.png"), 20.0, previews=False)
    assert p.summary["detail"]["lost_fraction"] < 0.01
    p = plan(_save(tmp_path, np.full((100, 100), 77, np.uint8), "flat.png"), 3.0, previews=False)
    assert p.summary["detail"]["lost_fraction"] == 0.0
    assert not [r for r in caplog.records if "screen elements" in r.getMessage()]


def test_the_cli_writes_preview_render_and_shows_the_warnings(tmp_path, capsys):
    rgb = np.zeros((60, 80, 3), np.uint8)
    rgb[:, :40] = (200, 30, 30)
    out = tmp_path / "out"
    rc = main(["fabricate", str(_save(tmp_path, rgb, "c.png")), "--width-mm", "8", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 0 and (out / "preview_render.png").is_file()
    assert "glossrig fabricate: warning: c.png is a colour image" in err
    s = json.loads((out / "summary.json").read_text())
    assert "preview_render.png" in s["files"] and "numpy" in s["preview_render"]["method"]
    im = Image.open(out / "preview_render.png")
    assert im.mode == "RGB" and im.size[0] > 2 * s["preview_render"]["panel_px"][1]


def test_a_model_with_bases_is_used_and_its_etn_inverted(tmp_path):
    """With a model holding bases and an ETN, the preview mixes those bases, and the
    effective coverage it predicts for the printed nominal coverage is the ETN's inverse:
    a constant effective-coverage target comes back (to the halftone's 1/42 step)."""
    b1 = {"rho_d": 0.03, "rho_s": 0.01, "alpha_x": 0.04, "alpha_y": 0.05, "lobe_rotation": 2.5}
    b2 = {"rho_d": 0.06, "rho_s": 0.02, "alpha_x": 0.2, "alpha_y": 0.03, "lobe_rotation": 2.5}
    doc = {"kind": "glossrig.reproduction_model", "etn": {"gamma": [1.2, 3.0, 1.0, -0.6]},
           "base1": {"ward": b1}, "base2": {"ward": b2}}
    mp = tmp_path / "model.json"
    mp.write_text(json.dumps(doc))
    ce = 0.5
    p = plan(_save(tmp_path, np.full((60, 70), round(ce * 255), np.uint8), "t.png"), 8.0, model=mp)
    info = p.summary["preview_render"]
    assert info["model"]["base2"] == b2 and "model.json" in info["model"]["source"]
    assert info["effective_coverage_mean"] == pytest.approx(round(ce * 255) / 255, abs=0.01)
