"""BRDF-space coverage (glossrig.core.design.coverage, thesis 7.1.3)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from glossrig.core.design import coverage as cov
from glossrig.core.extraction.cylinder import sample_angles, surface_samples
from glossrig.core.errors import InputError

from helpers import assert_image_has_content

SCALE = 0.06


@pytest.fixture(scope="module")
def pixels(rig):
    return cov.pixel_geometry(rig, SCALE)


@pytest.fixture(scope="module")
def data(rig, pixels):
    return cov.collect(rig, pixels=pixels, rotations=[-45.0, 0.0, 45.0, 90.0])


def test_roi_keeps_every_pixel_on_the_sample(rig):
    """The projected bounding box loses no pixel that the full-image ray cast finds."""
    cam = rig.camera
    R, t = cam.pose()
    full = surface_samples(cam.matrix(SCALE), cam.distortion, cam.size(SCALE), R, t, np.eye(3), np.zeros(3),
                           rig.cylinder_radius, rig.sample_height)
    px = cov.pixel_geometry(rig, SCALE)
    assert len(px) == len(full.u) > 1000
    assert set(zip(full.u.tolist(), full.v.tolist())) == set(zip(px.u.tolist(), px.v.tolist()))


@pytest.mark.parametrize("rotation", [0.0, 45.0, -30.5, 90.0])
def test_angles_match_the_pipeline_geometry(rig, pixels, rotation):
    """Zenith/azimuth (and the rotation applied to azimuths, eq. 4.62) agree with
    glossrig.core.extraction.cylinder.sample_angles, which rotates the tangent frame."""
    from glossrig.core.extraction.cylinder import SurfaceSamples

    s = SurfaceSamples(u=pixels.u, v=pixels.v, points=pixels.points, normals=pixels.normals,
                       camera_centre=pixels.camera_centre, axis=pixels.axis)
    led = rig.led(6)
    ref = sample_angles(s, led.position, rotation)
    a = cov.direction_angles(pixels, led.position, half=True)
    ok = (ref["cos_in"] > 0.05) & (ref["cos_out"] > 0.05) & (ref["theta_in"] > 0.02) & (ref["theta_out"] > 0.02)
    np.testing.assert_allclose(a["theta_in"][ok], np.degrees(ref["theta_in"][ok]), atol=1e-9)
    np.testing.assert_allclose(a["theta_out"][ok], np.degrees(ref["theta_out"][ok]), atol=1e-9)
    for k in ("phi_in", "phi_out", "phi_h"):
        rot = cov.rotate_azimuth(a[k][ok], rotation)
        diff = np.mod(rot - np.degrees(ref[k][ok]) + 180, 360) - 180
        assert np.max(np.abs(diff)) < 1e-7, k
    np.testing.assert_allclose(a["theta_h"][ok], np.degrees(ref["theta_h"][ok]), atol=1e-9)


def test_between_filter_is_where_theta_angles_sum_to_the_lamp_camera_angle(rig, pixels):
    """Thesis 7.1.3: theta_in + theta_out is the angle between lamp and camera
    exactly while the normal lies between them; outside, the sum is larger."""
    led = rig.led(6)                         # middle row: lamp, camera and mid-height pixels coplanar
    a = cov.direction_angles(pixels, led.position)
    P = pixels.points
    wi = led.position - P
    wo = pixels.camera_centre - P
    ang = np.degrees(np.arccos(np.sum(wi * wo, 1) / np.linalg.norm(wi, axis=1) / np.linalg.norm(wo, axis=1)))
    mid = np.abs(P[:, 1]) < 0.5
    s = a["theta_in"] + a["theta_out"]
    b = mid & a["between"]
    out = mid & a["lit"] & ~a["between"]
    assert b.sum() > 10 and out.sum() > 10
    # pixels within 0.5 mm of the lamp-camera plane: coplanar to within 0.05 degree
    np.testing.assert_allclose(s[b], ang[b], atol=0.05)
    assert np.all(s[out] > ang[out] - 0.05) and np.median(s[out] - ang[out]) > 1.0
    assert np.all(a["between"] <= a["lit"]) and np.all(a["lit"] <= a["visible"])


def test_bin_codes_by_hand():
    c = cov.bin_codes(np.array([10.2, 10.7, 89.99]), np.array([20.5, 20.1, 0.0]),
                      np.array([5.0, 5.9, 359.9999]), np.array([355.0, 355.5, 0.0]))
    ti, to, pi, po = cov.decode_aniso(np.sort(c["aniso"]))
    assert list(zip(ti, to, pi, po)) == [(10, 20, 5, 355), (89, 0, 359, 0)]
    _, _, folded = cov.decode_iso(np.sort(c["iso_folded"]))
    _, _, literal = cov.decode_iso(np.sort(c["iso_literal"]))
    # |5 - 355| = 350 -> 10 on the circle; |5.9 - 355.5| = 349.6 -> 10.4; |359.9999 - 0| -> 0.0001
    assert sorted(folded.tolist()) == [0, 10]
    assert sorted(literal.tolist()) == [349, 350, 359]


def test_printed_azimuth_folds_mirror_images():
    phi = np.array([0.0, 10.0, 350.0, 180.0, 90.0, 270.0])
    np.testing.assert_allclose(cov.printed_azimuth(phi), [180.0, 170.0, 170.0, 0.0, 90.0, 90.0])


@pytest.mark.parametrize("reciprocity,pi_fold", [(False, False), (True, False), (False, True), (True, True)])
def test_burnside_counts_match_canonicalisation(reciprocity, pi_fold):
    """Enumerate every bin of a small closed sub-space (theta < 2 degrees) and
    count the classes the canonicalisation produces."""
    n = 2
    ti, to, pi, po = np.meshgrid(np.arange(n), np.arange(n), np.arange(360), np.arange(360), indexing="ij")
    codes = ((ti.ravel() * 90 + to.ravel()) * 360 + pi.ravel()) * 360 + po.ravel()
    got = len(cov.canonical_aniso(codes, reciprocity, pi_fold))
    assert got == cov.aniso_orbits(n, n, 360, reciprocity, pi_fold)


def test_iso_reciprocity_total_matches_enumeration():
    ti, to, d = np.meshgrid(np.arange(90), np.arange(90), np.arange(180), indexing="ij")
    codes = (ti.ravel() * 90 + to.ravel()) * 360 + d.ravel()
    conv = cov.Convention(reciprocity=True)
    assert len(cov.canonical_iso(codes, True)) == conv.iso_total()


def test_coverage_properties(rig, data):
    mid = rig.select_leds("middle")
    lit = cov.Convention("lit")
    c8 = cov.coverage(data, lit, mid)
    c16 = cov.coverage(data, lit)
    assert 0 < c8["isotropic"] < c16["isotropic"] < 1
    assert 0 < c8["anisotropic"] < c16["anisotropic"] < 1
    assert c16["anisotropic_total"] == 90 * 90 * 360 * 360 and c16["isotropic_total"] == 90 * 90 * 180
    # the isotropic space does not see the sample rotation; the anisotropic one does
    one = cov.coverage(data, lit, mid, rotations=[0.0])
    assert one["isotropic_bins"] == c8["isotropic_bins"]
    assert one["anisotropic_bins"] < c8["anisotropic_bins"]
    # an integer rotation shifts azimuth bins one-to-one
    for led in mid:
        assert len(data.aniso[("lit", led, 45.0)]) == len(data.aniso[("lit", led, 0.0)])
    # filters nest
    cb = cov.coverage(data, cov.Convention("between"), mid)
    assert cb["anisotropic_bins"] < c8["anisotropic_bins"] and cb["isotropic_bins"] < c8["isotropic_bins"]
    # folds never add classes than the space has and never lose occupied ones entirely
    cf = cov.coverage(data, cov.Convention("lit", pi_fold=True, reciprocity=True), mid)
    assert c8["anisotropic_bins"] / 4 <= cf["anisotropic_bins"] <= c8["anisotropic_bins"]
    per = cov.per_rotation(data, lit, mid)
    cums = [per["cumulative"][r] for r in data.rotations]
    assert cums == sorted(cums) and cums[-1] == pytest.approx(c8["anisotropic"])


def test_printed_geometry_is_refused_wrong_conventions(rig, pixels):
    d = cov.collect(rig, led_ids=[5, 6], rotations=[0.0], pixels=pixels, geometry="printed", filters=("lit",))
    c = cov.coverage(d, cov.Convention("lit", phi_bins=180))
    assert c["anisotropic_total"] == 90 * 90 * 180 * 180
    with pytest.raises(InputError, match="printed"):
        cov.coverage(d, cov.Convention("lit", pi_fold=True))
    dc = cov.collect(rig, led_ids=[5], rotations=[0.0], pixels=pixels, filters=("lit",))
    with pytest.raises(InputError, match="phi_bins=180"):
        cov.coverage(dc, cov.Convention("lit", phi_bins=180))
    with pytest.raises(InputError, match="not collected"):
        cov.coverage(dc, cov.Convention("between"))
    with pytest.raises(InputError, match="rotation 45"):
        cov.coverage(dc, rotations=[45.0])


@pytest.mark.parametrize("kw,msg", [
    (dict(filter="shadow"), "filter"), (dict(dphi="signed"), "dphi"),
    (dict(filter="visible", reciprocity=True), "reciprocity"), (dict(phi_bins=90), "phi_bins")])
def test_bad_conventions(kw, msg):
    with pytest.raises(InputError, match=msg):
        cov.Convention(**kw)


def test_bad_collect_input(rig, pixels):
    with pytest.raises(InputError, match="LED id 99"):
        cov.collect(rig, led_ids=[99], pixels=pixels)
    with pytest.raises(InputError, match="distinct"):
        cov.collect(rig, rotations=[0.0, 0.0], pixels=pixels)
    with pytest.raises(InputError, match="geometry"):
        cov.collect(rig, pixels=pixels, geometry="thesis")
    with pytest.raises(InputError, match="scale"):
        cov.pixel_geometry(rig, 1.5)
    with pytest.raises(InputError, match="camera distance"):
        cov.pixel_geometry(rig, 0.1, camera_distance=10.0)


def test_camera_distance_changes_the_pixels(rig):
    near = cov.pixel_geometry(rig, SCALE, camera_distance=450.0)
    far = cov.pixel_geometry(rig, SCALE, camera_distance=550.0)
    assert len(near) > len(far)                # closer camera, more pixels on the sample
    assert near.camera_distance == 450.0


def test_cli_coverage_writes_report(tmp_path):
    from glossrig.cli.main import main

    out = tmp_path / "cov"
    assert main(["design", "coverage", "--rig", "scenes/thesis_rig.toml", "--out", str(out),
                 "--scales", "0.05", "--quiet"]) == 0
    s = json.loads((out / "coverage.json").read_text())
    assert s["headline"]["leds"] == [5, 6, 7, 8, 9, 10, 11, 12]
    assert s["printed_pct"] == {"isotropic": 0.98, "anisotropic": 0.1}
    for f in ("coverage.md", "conventions.csv"):
        assert (out / f).stat().st_size > 0
    assert_image_has_content(out / "theta_per_led.png", aspect=6.4 / 6.0, min_size=(600, 600))
    assert_image_has_content(out / "aniso_by_rotation.png", aspect=2 * 5.2 / 4.0, min_size=(1000, 400))   # 2 designs
    import pandas as pd

    df = pd.read_csv(out / "conventions.csv")
    assert set(df.geometry) == {"corrected", "printed"} and len(df) > 50


def test_cli_coverage_bad_rig(tmp_path, capsys):
    from glossrig.cli.main import main

    assert main(["design", "coverage", "--rig", str(tmp_path / "none.toml"), "--out", str(tmp_path / "o")]) == 2
    assert "rig file not found" in capsys.readouterr().err


def test_shifted_rotation_bins_equal_direct_binning(rig, pixels, data):
    """collect() moves the rotation-0 bins for whole-degree rotations; that is
    exactly what binning the rotated azimuths gives."""
    a = cov.direction_angles(pixels, rig.led(6).position)
    m = a["lit"]
    for rot in (-45.0, 45.0, 90.0):
        direct = cov.bin_codes(a["theta_in"][m], a["theta_out"][m], cov.rotate_azimuth(a["phi_in"][m], rot),
                               cov.rotate_azimuth(a["phi_out"][m], rot))["aniso"]
        assert np.array_equal(np.sort(direct), np.sort(data.aniso[("lit", 6, rot)]))
    half = cov.collect(rig, led_ids=[6], rotations=[12.5], pixels=pixels, filters=("lit",))
    direct = cov.bin_codes(a["theta_in"][m], a["theta_out"][m], cov.rotate_azimuth(a["phi_in"][m], 12.5),
                           cov.rotate_azimuth(a["phi_out"][m], 12.5))["aniso"]
    assert np.array_equal(np.sort(direct), np.sort(half.aniso[("lit", 6, 12.5)]))
