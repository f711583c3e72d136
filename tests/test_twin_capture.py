"""The virtual rig end to end: renders agree with the numpy BRDF, captures are real DNGs
that rawpy reads, exposure scales linearly, markers land where the truth puts them."""
from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest
import rawpy

from glossrig.core.capture import load_manifest
from glossrig.core.extraction.cylinder import sample_angles, surface_samples
from glossrig.core.calibration.markers import cylinder_marker_corners, holder_marker_corners
from glossrig.core.models.materials import parse_material
from glossrig.core.calibration.raw import demosaic, linearize, read_raw
from glossrig.core.models.ward import ward_from_angles

from conftest import RIG, SHARED

pytestmark = pytest.mark.mitsuba


def test_render_matches_numpy_ward(rig):
    """Rendered radiance on the sample = f(wi, wo) I cos(theta_in) / d^2 from core.ward
    and core.cylinder: checks the tangent frame, sample rotation, lobe rotation,
    LED placement, camera pose and lens resampling together."""
    from glossrig.twin.scene import LED_RGB
    from glossrig.twin.virtual_rig import VirtualRig

    mat = parse_material("ward:rho_d=0.05,rho_s=0.08,alpha_x=0.12,alpha_y=0.05,lobe_rotation=0.4")
    vr = VirtualRig(rig, mat, scale=0.12, seed=0, effects={}, spp=16)
    vr.set_rotation(30.0)
    for led in (6, 11):
        img = vr.led_radiance(led)[..., 1]
        s = surface_samples(vr.lens.K, vr.lens.dist, vr.lens.size, vr.camera_R, vr.camera_t, np.eye(3), np.zeros(3),
                            vr.sample_radius, rig.sample_height)
        ang = sample_angles(s, vr.led_positions[led], 30.0)
        f = ward_from_angles(ang["theta_in"], ang["theta_out"], ang["theta_h"], ang["phi_h"], mat.ward)
        pred = f * vr.intensity * LED_RGB[1] * np.clip(ang["cos_in"], 0, None) / (ang["dist_in"] * 1e-3) ** 2
        # interior pixels only: away from the sample's edges (anti-aliased), not grazing
        mask = np.zeros(img.shape, np.uint8)
        mask[s.v, s.u] = 1
        inner = cv2.erode(mask, np.ones((5, 5), np.uint8))[s.v, s.u].astype(bool)
        keep = inner & (ang["cos_out"] > 0.3) & (ang["cos_in"] > 0.2) & (pred > 1e-4)
        got = img[s.v[keep], s.u[keep]]
        rel = np.abs(got / pred[keep] - 1)
        assert keep.sum() > 500
        assert np.median(rel) < 0.01, np.median(rel)
        assert np.percentile(rel, 95) < 0.05, np.percentile(rel, 95)


@pytest.fixture(scope="module")
def quarter_capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("cap") / "sample"
    cmd = [sys.executable, "-m", "glossrig.cli.main", "simulate", "--rig", str(RIG), "--material", "sample_2_6",
           "--leds", "6,9", "--rotations", "0", "--repeats", "1", "--scale", "0.25", "--seed", "1",
           "--no-progress", "--out", str(out)]
    subprocess.run(cmd, check=True, capture_output=True, text=True)
    return out


def test_capture_layout_and_rawpy(quarter_capture, rig):
    man = load_manifest(quarter_capture)
    assert man.complete
    assert len(man.images) == 1 + 2 * 18
    assert len(list(quarter_capture.glob("*.dng"))) == 37
    assert [im.role for im in man.images].count("calibration") == 1
    man.verify(check_hashes=True)
    d = json.loads((quarter_capture / "capture.json").read_text())
    for im in d["images"]:
        for k in ("file", "role", "leds", "rotation", "repeat", "exposure_s", "iso", "aperture", "time", "sha256"):
            assert k in im
    im = man.select("sequence")[5]
    with rawpy.imread(str(quarter_capture / im.file)) as r:
        assert r.raw_image_visible.shape == (1008, 1508)
        assert list(r.black_level_per_channel) == list(rig.camera.black_level)
        assert r.white_level == rig.camera.white_level
    fr = read_raw(quarter_capture / im.file)
    assert fr.exposure_s == pytest.approx(im.exposure_s) and fr.iso == im.iso and fr.aperture == im.aperture
    truth = json.loads((quarter_capture / "truth.json").read_text())
    assert truth["material"]["ward"]["rho_d"] == pytest.approx(0.0518)


def test_signal_doubles_with_exposure(quarter_capture):
    """In pixels unclipped in both frames, mean signal above black doubles when the exposure
    doubles (within shot noise and the 0.5 % LED jitter)."""
    man = load_manifest(quarter_capture)
    seq = sorted((im for im in man.select("sequence") if im.leds == [9]), key=lambda im: im.exposure_s)
    ratios = []
    for a, b in zip(seq, seq[1:]):
        if not b.exposure_s / a.exposure_s == pytest.approx(2.0, rel=0.02):
            continue
        la, lb = linearize(read_raw(quarter_capture / a.file)), linearize(read_raw(quarter_capture / b.file))
        ok = (la > 0.02) & (lb < 0.9)
        if ok.sum() < 2000:
            continue
        ratios.append(lb[ok].mean() / la[ok].mean())
    assert len(ratios) >= 8
    assert np.all(np.abs(np.array(ratios) - 2.0) < 0.04), ratios


def _refine(gray, pts):
    p = pts.astype(np.float32).reshape(-1, 1, 2).copy()
    cv2.cornerSubPix(gray, p, (4, 4), (-1, -1), (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-4))
    return p.reshape(-1, 2)


def test_marker_corners_land_within_one_pixel(quarter_capture):
    """Corners projected from the ground-truth pose and intrinsics sit on the rendered
    corners (found by OpenCV's sub-pixel corner refinement) within 1 px at scale 0.25."""
    truth = json.loads((quarter_capture / "truth.json").read_text())
    man = load_manifest(quarter_capture)
    fr = read_raw(quarter_capture / man.select("calibration")[0].file)
    rgb = demosaic(linearize(fr), fr.cfa)
    K, dist = np.array(truth["camera_matrix"]), np.array(truth["distortion"])
    R, t = np.array(truth["camera_R_holder_to_camera"]), np.array(truth["camera_t_mm"])
    rvec = cv2.Rodrigues(R)[0]
    from glossrig.core.rig import load_rig

    rig = load_rig(RIG)
    checks = [(holder_marker_corners(rig), rgb[..., 0]), (holder_marker_corners(rig, inner=True), rgb[..., 1]),
              (cylinder_marker_corners(rig), rgb[..., 1])]
    errs = []
    for pts3, chan in checks:
        proj, _ = cv2.projectPoints(pts3, rvec, t, K, dist)
        proj = proj.reshape(-1, 2)
        gray = cv2.GaussianBlur((chan / chan.max()).astype(np.float32), (0, 0), 0.7)
        found = _refine(gray, proj)
        errs.append(np.linalg.norm(found - proj, axis=1))
    errs = np.concatenate(errs)
    assert len(errs) == 4 + 4 + 12
    assert errs.max() < 1.0, errs


def test_bad_input_clear_errors(tmp_path):
    def run(*args):
        return subprocess.run([sys.executable, "-m", "glossrig.cli.main", "simulate", "--no-progress", *args],
                              capture_output=True, text=True)

    r = run("--material", "unobtainium", "--out", str(tmp_path / "a"))
    assert r.returncode == 2 and "unknown material 'unobtainium'" in r.stderr
    r = run("--material", "ward:rho_d=-0.1,rho_s=0.1,alpha_x=0.1,alpha_y=0.1", "--out", str(tmp_path / "b"))
    assert r.returncode == 2 and "rho_d" in r.stderr
    r = run("--leds", "17", "--out", str(tmp_path / "c"))
    assert r.returncode == 2 and "LED id 17" in r.stderr
    r = run("--effects", "led_drift=5", "--out", str(tmp_path / "d"))
    assert r.returncode == 2 and "led_drift" in r.stderr
    (tmp_path / "afile").write_text("")
    r = run("--out", str(tmp_path / "afile" / "cap"))      # parent is a file: cannot be created
    assert r.returncode == 2 and "cannot write here" in r.stderr and "is a file" in r.stderr
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "x").write_text("keep me")
    r = run("--out", str(tmp_path / "full"))
    assert r.returncode == 2 and "not empty" in r.stderr
    assert (tmp_path / "full" / "x").read_text() == "keep me"
    for d in "abcd":
        assert not (tmp_path / d / "capture.json").exists()


@pytest.mark.needs_shared("data/rgl/vch_golden_yellow_rgb.bsdf")
def test_measured_rgl_material_simulates(tmp_path):
    """A real measured BRDF (RGL, Dupuy & Jakob 2018) through Mitsuba's `measured` plugin;
    negative radiance from its RGB interpolation is clamped and counted in the truth."""
    out = tmp_path / "cap"
    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "simulate", "--rig", str(RIG), "--material",
                        f"measured:{SHARED / 'data/rgl/vch_golden_yellow_rgb.bsdf'}", "--leds", "9", "--rotations", "0",
                        "--scale", "0.08", "--seed", "1", "--no-progress", "--out", str(out)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr[-2000:]
    truth = json.loads((out / "truth.json").read_text())
    assert truth["material"]["kind"] == "measured"
    w, h = truth["image_size"]
    assert all(v < 0.02 * w * h for v in truth["negative_radiance_pixels_clamped"].values())
    man = load_manifest(out)
    longest = max(man.select("sequence"), key=lambda im: im.exposure_s)
    assert linearize(read_raw(out / longest.file)).max() == 1.0      # the sample is lit and seen
