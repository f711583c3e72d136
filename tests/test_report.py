"""The measurement report (issue 17): glossrig.core.report.document, glossrig.core.report.figures and
the twin's material renders.

Inputs are small and synthetic: a samples table of a known extended-Ward material at the
rig's nominal geometry (no rendering), fitted by glossrig.core.fitting.fit; a fake capture of
two LEDs x four exposures of 64 x 48 px DNGs whose HDR rate is known exactly. The
report is checked as written (every embedded image a decodable, non-constant PNG; the
Markdown's PNGs exist), its figures' axes with matplotlib, and the HTML in a real
browser (headless Chromium) when one is installed.
"""
from __future__ import annotations

import base64
import io
import json
import math
import re
import shutil
import subprocess
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from glossrig.core.errors import InputError

from conftest import RIG
from helpers import assert_image_has_content

TRUTH = dict(rho_d=0.0518, rho_s=0.0069, alpha_x=0.0595, alpha_y=0.034, lobe_rotation=2.47)   # Table 9.1, 2/6
EXPOSURES = (0.25, 0.5, 1.0, 2.0)
SIZE = (48, 64)          # rows, columns of the fake capture's images
LEDS = (9, 10)


# ------------------------------------------------------------------ fixtures

def true_rate(led: int) -> np.ndarray:
    """The HDR rate (fraction of white-black per second) the fake capture encodes: a
    ramp, one saturated patch (too bright even at 0.25 s) and one too-dark patch."""
    h, w = SIZE
    x = np.arange(w)[None, :] / w
    r = np.broadcast_to(0.02 + 0.45 * x, (h, w)).copy() * (1.0 if led == LEDS[0] else 0.5)
    r[4:12, 4:12] = 6.0                  # 6 * 0.25 s = 1.5 > 1: saturated at every exposure
    r[30:40, 50:60] = 2e-4               # 2e-4 * 2 s = 4e-4 < hdr_ml's lo = 0.002: too dark
    return r


def write_fake_capture(folder: Path, *, truth: bool = True) -> Path:
    """A capture folder (capture.json + DNGs) of LEDS x EXPOSURES at rotation 0 whose
    images are exactly ``true_rate * t`` (rounded to whole DN, clipped at the white level)."""
    from glossrig.core.atomic import atomic_write_json
    from glossrig.core.capture import ImageEntry, Manifest, image_stem
    from glossrig.core.rig import load_rig
    from glossrig.twin.dng import write_dng

    rig = load_rig(RIG)
    black, white = rig.camera.black_level, rig.camera.white_level
    folder.mkdir(parents=True)
    images = []
    t0 = datetime(2026, 1, 1, 9, 0, tzinfo=timezone.utc)
    for led in LEDS:
        for k, t in enumerate(EXPOSURES):
            y = np.clip(true_rate(led) * t, 0, None)
            dn = np.minimum(np.round(black[0] + y * (white - black[0])), white).astype(np.uint16)
            name = image_stem("sequence", rotation=0.0, leds=[led], exposure_index=k) + ".dng"
            sha = write_dng(folder / name, dn, cfa=rig.camera.cfa, black_level=tuple(black), white_level=white,
                            exposure_s=t, iso=320, aperture=11.0, time=t0)
            images.append(ImageEntry(file=name, role="sequence", leds=[led], rotation=0.0, repeat=0, exposure_s=t,
                                     iso=320, aperture=11.0, time=t0.isoformat(), sha256=sha))
    Manifest(folder=folder, rig=str(RIG), material="ward test", images=images, complete=True,
             meta={"rig_name": rig.name}).save()
    if truth:
        atomic_write_json(folder / "truth.json", {"material": {"kind": "ward", "label": "test", "ward": TRUTH}})
    return folder


@pytest.fixture(scope="module")
def measured(tmp_path_factory):
    """samples.parquet (with provenance) and fit.json of a known Ward material; a fake capture."""
    from glossrig.core.extraction.cylinder import nominal_samples
    from glossrig.core.fitting.export import write_fit_json
    from glossrig.core.fitting.fit import fit_samples
    from glossrig.core.provenance import provenance
    from glossrig.core.rig import load_rig
    from glossrig.core.samples import read_samples, ward_samples, write_samples
    from glossrig.core.models.ward import WardParams

    d = tmp_path_factory.mktemp("report")
    cap = write_fake_capture(d / "sample")
    rig = load_rig(RIG)
    geo = nominal_samples(rig, [8, 9, 10, 11], [0, 45], 0.05)
    df = ward_samples(geo, WardParams(**TRUTH), noise=0.02, seed=3, colour=(1.1, 1.0, 0.8))
    samples = write_samples(df, d / "samples.parquet",
                            provenance=provenance({"sample": cap, "rig": RIG}, {"albedo": 0.8}, tool="glossrig extract"))
    df = read_samples(samples)
    mfit = fit_samples(df, channels=("luminance", "r"), n_starts=2, refine_samples=20_000)
    fit = write_fit_json(mfit, d / "fit.json",
                         provenance=provenance({"samples": samples}, {"weighting": "mirror"}, tool="glossrig fit"))
    return {"dir": d, "capture": cap, "samples": samples, "fit": fit, "df": df}


@pytest.fixture(scope="module")
def report(measured):
    from glossrig.core.report.document import write_report

    d = measured["dir"]
    rng = np.random.default_rng(0)
    renders = {}
    for name in ("sphere", "cloth"):         # stand-ins for the Mitsuba renders (tested below)
        p = d / f"fake_{name}.png"
        Image.fromarray(rng.integers(0, 255, (40, 40, 3), dtype=np.uint8)).save(p)
        renders[name] = p
    export = d / "exports" / "samples.csv"
    export.parent.mkdir()
    export.write_text("theta_in,r\n0.1,0.2\n")
    html, md = write_report(d / "out", fit_json=measured["fit"], samples=measured["samples"],
                            sample_dir=measured["capture"], reference_dir=measured["capture"], renders=renders,
                            exports=[export, d / "exports" / "material.brdf"])
    return {"html": html, "md": md, "out": d / "out"}


def _imgs(html_text: str) -> list[tuple[str, int, int]]:
    out = []
    for m in re.finditer(r'<img src="([^"]+)"[^>]*width="(\d+)" height="(\d+)"', html_text):
        out.append((m.group(1), int(m.group(2)), int(m.group(3))))
    return out


# ------------------------------------------------------------------ the report as written

def test_every_html_image_is_an_embedded_non_constant_png(report):
    text = report["html"].read_text()
    assert "<img" in text and text.count("<img") == len(_imgs(text))
    imgs = _imgs(text)
    # HDR, coverage, 2 slice plots, polar, rig slices, measured vs fitted, residuals, 2 renders
    assert len(imgs) >= 10
    for src, w, h in imgs:
        assert src.startswith("data:image/png;base64,"), src[:40]
        data = base64.b64decode(src.split(",", 1)[1], validate=True)
        im = Image.open(io.BytesIO(data))
        assert im.format == "PNG"
        assert im.size == (w, h)
        assert_image_has_content(data)
    widths = sorted(w for _, w, _ in imgs)
    assert widths[-1] >= 1000 and sum(w >= 600 for w in widths) >= 8     # figures at a readable size
    assert "file:" not in text and "http://" not in text and "https://" not in text   # self-contained


def test_markdown_figures_exist_and_match_the_html(report):
    md = report["md"].read_text()
    refs = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md)
    assert len(refs) == len(_imgs(report["html"].read_text()))
    for r in refs:
        p = report["out"] / r
        assert p.suffix == ".png", r
        assert_image_has_content(p)          # figures, and the 40 px fake renders of the fixture
        assert not Path(r).is_absolute()


def test_report_sections_say_what_they_hold(report, measured):
    md = report["md"].read_text()
    html = report["html"].read_text()
    for text in (md, html):
        assert "noise-only" in text                    # the fit's standard errors keep their label
        assert "Uncertainty budget (GUM)" in text      # and the budget beside them (issue 15)
        assert "extrapolated" in text and "gu85" in text   # the fit's gloss units with their model spread
        assert "Markers and poses: not drawn" in text  # no camera.json given
        assert "Camera calibration: not given." in text
    sha_capture = json.loads((measured["capture"] / "capture.json").read_text())  # noqa: F841 (readable)
    from glossrig.core.capture import sha256_file

    # provenance: the inputs with their checksums, and what the extract step recorded
    assert sha256_file(measured["fit"])[:16] in md
    assert sha256_file(measured["samples"])[:16] in md
    assert sha256_file(measured["capture"] / "capture.json")[:16] in md
    assert "glossrig extract" in md and "glossrig fit" in md
    # capture: LEDs, exposures
    assert "0.25, 0.5, 1, 2" in md
    # truth beside the fit (truth.json of the fake capture)
    assert "Truth recorded by the twin" in md
    # exports: the present one hashed, the absent one flagged
    assert "exports/samples.csv" in md and "missing" in md


def test_fit_table_holds_the_fitted_values(report, measured):
    md = report["md"].read_text()
    fit = json.loads(measured["fit"].read_text())["luminance"]
    row = next(ln for ln in md.splitlines() if ln.startswith("| luminance |") and "+-" in ln)
    assert f"{fit['alpha_x']:.4g} +- " in row and f"{fit['rho_d']:.4g} +- " in row


def test_gloss_and_missing_inputs(measured, tmp_path):
    from glossrig.core.report.document import write_report

    html, md = write_report(tmp_path / "r", fit_json=json.loads(measured["fit"].read_text()), samples=measured["df"],
                            gloss={"gu20": 12.5, "gu60": {"value": 40.0, "extrapolated": True}}, hdr=False)
    text = md.read_text()
    assert "gu20" in text and "12.5" in text and "gu60.extrapolated" in text
    assert "HDR images: not computed" in text and "Sample: not given." in text
    assert "Renders: not rendered" in text and "Exports: not written." in text
    assert "Truth: not available" in text
    fit = json.loads(measured["fit"].read_text())
    fit["luminance"].pop("gloss", None)
    html, md = write_report(tmp_path / "g", fit_json=fit, samples=measured["df"], hdr=False)
    assert "Gloss units: not computed." in md.read_text()
    with pytest.raises(InputError, match="fit.json"):
        write_report(tmp_path / "s", fit_json=tmp_path / "nope.json", samples=measured["df"])
    with pytest.raises(InputError, match="no fitted channel"):
        write_report(tmp_path / "t", fit_json={"format": "glossrig-fit/1"}, samples=measured["df"])
    with pytest.raises(InputError, match="no fitted channel"):
        write_report(tmp_path / "u", fit_json={"format": "x"}, samples=measured["df"])


# ------------------------------------------------------------------ figures

def test_hdr_per_led_recovers_the_encoded_rate(measured):
    from glossrig.core.report.figures import hdr_per_led

    hdrs = hdr_per_led(measured["capture"])
    assert [h.led for h in hdrs] == list(LEDS)
    for h in hdrs:
        r = true_rate(h.led)
        blocks = r.reshape(SIZE[0] // 2, 2, SIZE[1] // 2, 2).mean(axis=(1, 3))
        ok = np.isfinite(h.image)
        # every block away from the two special patches is valid and exact to the DN rounding
        assert ok[8:14, 8:20].all()
        np.testing.assert_allclose(h.image[ok & ~h.saturated & ~h.dark], blocks[ok & ~h.saturated & ~h.dark],
                                   rtol=5e-3)
        assert h.saturated[2:6, 2:6].all() and not h.saturated[15:, :].any()
        assert h.dark[15:20, 25:30].all()
        # 8 x 8 px at the white level in the shortest exposure; more in the longest (ramp above 0.5 /s)
        assert h.saturated_at_shortest == pytest.approx(64 / (SIZE[0] * SIZE[1]))
        over = (np.clip(r * EXPOSURES[-1], 0, None) * (15520 - 600) + 600 >= 15520 - 0.5).mean()
        assert h.saturated_at_longest == pytest.approx(over, abs=1 / (SIZE[0] * SIZE[1]))
        assert h.exposures_s == list(EXPOSURES)


def test_hdr_of_a_decimated_capture_is_the_hdr_of_the_kept_blocks(measured):
    from glossrig.core.report.figures import hdr_per_led

    full = hdr_per_led(measured["capture"], leds=[LEDS[0]])[0]
    dec = hdr_per_led(measured["capture"], leds=[LEDS[0]], max_width=32)[0]     # 64 px wide: every 2nd block
    assert dec.image.shape == (SIZE[0] // 4, SIZE[1] // 4) and dec.pixels_per_block == 4
    # equal up to the image-wide LED-jitter gain of eq. 4.32-4.38, estimated from fewer pixels
    np.testing.assert_allclose(dec.image, full.image[::2, ::2], rtol=1e-4)
    np.testing.assert_array_equal(dec.saturated, full.saturated[::2, ::2])


def test_in_plane_geometry_against_hand_values():
    import pandas as pd

    from glossrig.core.report.figures import model_in_plane, signed_in_plane
    from glossrig.core.models.ward import WardParams

    t = np.radians
    df = pd.DataFrame({"theta_out": t([30.0, 30.0, 30.0]), "phi_in": t([10.0, 10.0, 10.0]),
                       "phi_out": t([190.0, 10.0, 100.0])})
    off, signed = signed_in_plane(df)
    np.testing.assert_allclose(off, [0, 0, t(30.0)], atol=1e-12)          # 90 deg azimuth: fully out of plane
    np.testing.assert_allclose(signed[:2], [t(30.0), -t(30.0)])
    # isotropic Ward at the mirror direction: theta_h = 0, f = rho_d/pi + rho_s / (4 pi a^2 cos theta)
    p = WardParams(0.1, 0.2, 0.05, 0.05, 0.0)
    f = model_in_plane(p, t(40.0), 0.3, np.array([t(40.0)]))
    assert f[0] == pytest.approx(0.1 / math.pi + 0.2 / (4 * math.pi * 0.05 ** 2 * math.cos(t(40.0))), rel=1e-12)
    # back-scatter side at the same zenith: theta_h = 40 deg, far down the lobe
    b = model_in_plane(p, t(40.0), 0.3, np.array([-t(40.0)]))
    assert b[0] == pytest.approx(0.1 / math.pi + 0.2 / (4 * math.pi * 0.05 ** 2 * math.cos(t(40.0)))
                                 * math.exp(-math.tan(t(40.0)) ** 2 / 0.05 ** 2), rel=1e-9)


def _text_boxes(fig):
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    return r


def _check_figure(fig, name):
    """Every non-polar data axes has labelled x and y axes with a unit in parentheses,
    and no two tick labels of one axis overlap."""
    r = _text_boxes(fig)
    checked = 0
    for ax in fig.axes:
        if not ax.get_visible() or not ax.axison or ax.name == "polar":
            continue
        if ax.get_label() == "<colorbar>":
            assert "(" in ax.get_ylabel() or "(" in ax.get_xlabel() or ax.get_ylabel(), name
            continue
        xl, yl = ax.get_xlabel(), ax.get_ylabel()
        assert xl and "(" in xl, (name, "x label", xl)
        shared = ax.get_shared_y_axes().get_siblings(ax)
        assert (yl and "(" in yl) or len(shared) > 1, (name, "y label", yl)
        for labels in (ax.get_xticklabels() + ax.get_xticklabels(minor=True),
                       ax.get_yticklabels() + ax.get_yticklabels(minor=True)):
            shown = [t for t in labels if t.get_visible() and t.get_text()]
            boxes = [t.get_window_extent(r) for t in shown]
            for i in range(len(boxes)):
                for j in range(i + 1, len(boxes)):
                    assert not boxes[i].overlaps(boxes[j]), (name, "overlapping tick labels",
                                                             shown[i].get_text(), shown[j].get_text())
        checked += 1
    return checked


def test_figures_have_labelled_axes_and_no_overlapping_ticks(measured, tmp_path, monkeypatch):
    from glossrig.core.fitting import fit_plots
    from glossrig.core.report import figures as report_figures
    from glossrig.core.fitting.export import fit_from_doc
    from glossrig.core.models.ward import WardParams

    captured = {}
    plt = report_figures._plt()
    real_close = plt.close

    def keep(fig=None):                     # keep the figures for inspection instead of closing them
        if fig is not None and not isinstance(fig, str):
            captured[id(fig)] = fig
        else:
            real_close(fig)

    monkeypatch.setattr(plt, "close", keep)
    df = measured["df"]
    fit = fit_from_doc(json.loads(measured["fit"].read_text())).fits["luminance"]
    paths = {
        "slices": report_figures.plot_incidence_slices(df, fit, tmp_path / "s.png", truth=WardParams(**TRUTH)),
        "coverage": report_figures.plot_coverage(df, tmp_path / "c.png"),
        "polar": report_figures.plot_polar_lobe(fit, tmp_path / "p.png"),
        "hdr": report_figures.plot_hdr_per_led(report_figures.hdr_per_led(measured["capture"]), tmp_path / "h.png"),
        "lobe": fit_plots.plot_lobe_slices(df, fit, tmp_path / "l.png"),
        "rig": fit_plots.plot_rig_slices(df, fit, tmp_path / "r.png"),
        "residuals": fit_plots.plot_residuals(df, fit, tmp_path / "res.png"),
        "mvf": fit_plots.plot_measured_vs_fitted(df, fit, tmp_path / "m.png"),
    }
    figs = list(captured.values())
    assert len(figs) == len(paths)
    by_name = dict(zip(paths, figs))
    for name, fig in by_name.items():
        w, h = Image.open(paths[name]).size
        assert w >= 600, (name, w)
        if name != "polar":
            assert _check_figure(fig, name) >= 1, name
    sl = [ax for ax in by_name["slices"].axes if ax.get_visible() and ax.axison]
    assert sl and all("theta" in ax.get_xlabel() and "deg" in ax.get_xlabel() for ax in sl)
    assert "1/sr" in sl[0].get_ylabel() and sl[0].get_yscale() == "log"
    # the fitted and the true curve are both drawn in every panel
    assert all(len(ax.get_lines()) >= 3 for ax in sl)
    cbar = [ax for ax in by_name["hdr"].axes if ax.get_label() == "<colorbar>"]
    assert len(cbar) == 1 and "log10" in cbar[0].get_ylabel()
    for fig in figs:
        real_close(fig)


# ------------------------------------------------------------------ in a real browser

def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        p = shutil.which(name)
        if p:
            return p
    return None


def test_report_renders_in_headless_chromium(report, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip("headless Chromium is not installed (apt-get install chromium): the browser check needs it")
    url = report["html"].resolve().as_uri()
    common = [exe, "--headless", "--disable-gpu", "--no-sandbox", f"--user-data-dir={tmp_path / 'profile'}",
              "--hide-scrollbars", "--allow-file-access-from-files"]
    shot = tmp_path / "shot.png"
    subprocess.run([*common, f"--screenshot={shot}", "--window-size=1280,4000", url], capture_output=True,
                   timeout=120)
    assert shot.is_file(), "Chromium wrote no screenshot"
    a = np.asarray(Image.open(shot).convert("RGB"), float)
    assert a.shape[:2] == (4000, 1280)
    assert a.std() > 20
    assert (a.min(axis=2) < 200).mean() > 0.05          # not a blank white page
    dom = subprocess.run([*common, "--virtual-time-budget=10000", "--dump-dom", url], capture_output=True, text=True,
                         timeout=120).stdout
    n = len(_imgs(report["html"].read_text()))
    m = re.search(r'data-images-loaded="(\d+)/(\d+)"', dom)
    assert m, "the page's load script did not run"
    assert (int(m.group(1)), int(m.group(2))) == (n, n), "an image did not load"


# ------------------------------------------------------------------ the twin's renders

@pytest.mark.mitsuba
def test_sphere_and_cloth_renders_show_the_material(tmp_path):
    pytest.importorskip("mitsuba")
    from glossrig.core.fitting.export import mitsuba_from_params
    from glossrig.core.models.ward import WardParams
    from glossrig.twin.material_renders import environment_map, render_material_views

    env = environment_map(64)
    assert env.shape == (32, 64, 3) and env.min() > 0 and env.max() > 10      # softboxes far above the sky
    glossy = mitsuba_from_params(WardParams(0.05, 0.3, 0.12, 0.04, 0.0))
    matte = mitsuba_from_params(WardParams(0.7, 0.0, 0.2, 0.2, 0.0))
    a = render_material_views(glossy, tmp_path / "g", size=48, spp=8)
    b = render_material_views(matte, tmp_path / "m", size=48, spp=8)
    for kind in ("sphere", "cloth"):
        x = np.asarray(Image.open(a[kind]).convert("RGB"), float)
        y = np.asarray(Image.open(b[kind]).convert("RGB"), float)
        assert x.shape == y.shape == (48, 48, 3)
        assert x.std() > 5 and y.std() > 2, kind                       # not blank
        assert np.abs(x - y).mean() > 10, kind                         # the material shows
        # the matte albedo 0.7 is brighter on average than the dark glossy sheet
        c = slice(16, 32)
        assert y[c, c].mean() > x[c, c].mean(), kind


@pytest.mark.mitsuba
def test_cloth_tangent_follows_the_weave():
    """Mitsuba builds the shading frame from dp/du: the tangent at the cloth's centre is
    its weave direction (+x), projected onto the tangent plane."""
    pytest.importorskip("mitsuba")
    from glossrig.twin.material_renders import _cloth_mesh, cloth_height
    from glossrig.twin.mitsuba_env import mitsuba

    mi = mitsuba()
    mesh = _cloth_mesh(mi, {"type": "diffuse"}, 64)
    scene = mi.load_dict({"type": "scene", "cloth": mesh})
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(0.1, 5.0, -0.2), mi.Vector3f(0, -1, 0)))
    s = np.array(si.sh_frame.s).ravel()
    z, gx, gy = cloth_height(0.1, 0.2)
    t = np.array([1.0, float(gx), 0.0])
    t /= np.linalg.norm(t)
    assert abs(float(np.dot(s, t))) > 0.99
