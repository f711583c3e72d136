"""The cylinder's outline as a witness of the sample radius (core/diagnose/silhouette.py, issue 14):
each image column's limb is where a ray grazes the sample, so the outline measures the radius
where the BRDF rows cannot tell it from the material's departure."""
from __future__ import annotations

import copy
import json
from types import SimpleNamespace

import numpy as np
import pytest

from glossrig.core.diagnose.silhouette import (COS_MIN, apply_silhouette_evidence, limb_box,
                                               silhouette_evidence)
from glossrig.core.extraction.cylinder import surface_samples

from conftest import RIG, glossrig_cli, run_shared_folder, camera_json_from_truth

NOISE = 0.01            # each rate's relative noise
SUB = 4                 # sub-pixels per pixel side: the outline's partial pixels


def thesis_geometry(scale):
    """The nominal rig's poses (cylinder frame = holder frame) and camera at ``scale``."""
    from glossrig.core.rig import load_rig

    rig = load_rig(RIG)
    R, t = rig.camera.pose()
    geom = SimpleNamespace(R_hold=R, t_hold=t, R_cyl=np.eye(3), t_cyl=np.zeros(3))
    cam = (rig.camera.matrix(scale), np.asarray(rig.camera.distortion, float))
    return rig, geom, cam, rig.camera.size(scale)


def outline_units(rig, geom, cam, size, dr, seed, leds=(6, 9)):
    """Rate mosaics over :func:`limb_box` of a Lambertian sample of radius ``rig.cylinder_radius + dr``
    (the poses the pipeline assumes), each pixel the mean of SUB x SUB sub-pixel rays (the partial
    pixels of the outline), a colour factor per Bayer site and NOISE; NaN where nothing is seen (the
    dark box, as the HDR marks it too dark)."""
    rng = np.random.default_rng(seed)
    K, dist = cam
    box, transposed = limb_box(geom, K, dist, rig.cylinder_radius, rig.sample_height, size)
    x0, y0, x1, y1 = box
    H, W = y1 - y0, x1 - x0
    # the supersampled image's pixel centres: SUB x SUB per pixel, row-major over (H SUB, W SUB)
    sv, su = np.mgrid[0:H * SUB, 0:W * SUB]
    su = (x0 - 0.5 + (su + 0.5) / SUB).ravel()
    sv = (y0 - 0.5 + (sv + 0.5) / SUB).ravel()
    hit = surface_samples(K, dist, size, geom.R_hold, geom.t_hold, geom.R_cyl, geom.t_cyl,
                          rig.cylinder_radius + dr, rig.sample_height, pixels=(su, sv))
    idx = np.round((hit.v - y0 + 0.5) * SUB - 0.5).astype(int) * (W * SUB) \
        + np.round((hit.u - x0 + 0.5) * SUB - 0.5).astype(int)
    vv, uu = np.mgrid[y0:y1, x0:x1]
    colour = np.array([[0.6, 1.0], [1.0, 0.45]])[vv % 2, uu % 2]
    units = []
    for led in leds:
        P = np.asarray(rig.led(led).position, float)
        d = P - hit.points
        d2 = np.sum(d * d, axis=1)
        L = np.maximum(np.sum(d * hit.normals, axis=1), 0.0) / np.sqrt(d2) / d2 * 1e5
        sub = np.zeros(su.size)
        sub[idx] = L
        img = sub.reshape(H, SUB, W, SUB).mean(axis=(1, 3)) * colour
        img = img * (1 + NOISE * rng.standard_normal(img.shape))
        img = np.where(img > 1e-3 * np.nanmax(img), img, np.nan)
        units.append({"rotation": 0.0, "led": led, "box": box, "transposed": transposed, "rate": img})
    return units


def lamps_of(rig, leds=(6, 9)):
    return {k: np.asarray(rig.led(k).position, float) for k in leds}


@pytest.mark.parametrize("dr,seed", [(0.6, 1), (-0.4, 2)])
def test_outline_measures_the_sample_radius(dr, seed):
    rig, geom, cam, size = thesis_geometry(0.25)
    ev = silhouette_evidence(outline_units(rig, geom, cam, size, dr, seed), {0.0: geom}, cam,
                             rig.cylinder_radius, rig.sample_height, lamps_of(rig))
    assert ev["significant"], ev["why_not"]
    assert abs(ev["dr"] - dr) < 4 * ev["se"], (ev["dr"], dr, ev["se"])
    # the stated uncertainty is the edge model's quarter pixel (0.15 mm of radius a pixel at scale 0.25)
    assert 0.02 < ev["se"] < 0.06
    assert all(p["cos_in"] >= COS_MIN for p in ev["units"])
    json.dumps(ev)                                   # report.json can hold it


def test_a_camera_turned_by_a_quarter_scans_the_rows():
    """The same rig seen by a camera turned 90 degrees about its optical axis: the cylinder's axis runs
    along the image's v, the limbs along its rows (``transposed``), and the radius is measured alike."""
    rig, geom, (K, _), (w, h) = thesis_geometry(0.25)
    turn = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])      # x' = -y, y' = x
    turned = SimpleNamespace(R_hold=turn @ geom.R_hold, t_hold=turn @ geom.t_hold, R_cyl=geom.R_cyl,
                             t_cyl=geom.t_cyl)
    K2 = np.array([[K[1, 1], 0.0, h - 1 - K[1, 2]], [0.0, K[0, 0], K[0, 2]], [0.0, 0.0, 1.0]])
    cam = (K2, np.zeros(5))
    units = outline_units(rig, turned, cam, (h, w), 0.5, 9)
    assert units[0]["transposed"]
    ev = silhouette_evidence(units, {0.0: turned}, cam, rig.cylinder_radius, rig.sample_height, lamps_of(rig))
    assert ev["significant"], ev["why_not"]
    assert abs(ev["dr"] - 0.5) < 4 * ev["se"], (ev["dr"], ev["se"])


def test_report_md_says_what_the_outline_measured():
    from glossrig.core.diagnose.report import _witness_lines

    rig, geom, cam, size = thesis_geometry(0.25)
    ev = silhouette_evidence(outline_units(rig, geom, cam, size, 0.6, 10), {0.0: geom}, cam,
                             rig.cylinder_radius, rig.sample_height, lamps_of(rig))
    text = "\n".join(_witness_lines({"sample_radius_silhouette": ev, "vignetting_patch": None}))
    assert f"dr = {ev['dr']:.3g} +- {ev['se']:.2g} mm" in text and "no material produces" in text
    assert "white patch" not in text


def test_the_nominal_radius_is_no_signature():
    rig, geom, cam, size = thesis_geometry(0.25)
    for seed in (3, 4, 5):
        ev = silhouette_evidence(outline_units(rig, geom, cam, size, 0.0, seed), {0.0: geom}, cam,
                                 rig.cylinder_radius, rig.sample_height, lamps_of(rig))
        assert not ev["significant"] and abs(ev["dr"]) < 4 * ev["se"], ev


def test_a_limb_the_led_grazes_or_leaves_dark_is_not_measured():
    """LED 9 of the thesis rig grazes the upper limb (cos theta_in ~ 0.2) and leaves the lower one in
    the dark: its edges are a terminator and a steeply falling radiance, not the outline."""
    rig, geom, cam, size = thesis_geometry(0.25)
    ev = silhouette_evidence(outline_units(rig, geom, cam, size, 0.6, 6, leds=(9,)), {0.0: geom}, cam,
                             rig.cylinder_radius, rig.sample_height, lamps_of(rig, (9,)))
    assert ev is None


@pytest.fixture(scope="module")
def radius_brdf():
    """A Ward capture whose sample radius is 0.6 mm over the rig file's, its BRDF-space causes fitted."""
    from test_diagnose import fitted_brdf

    return fitted_brdf(45, "sample_radius_error", 0.6)


def _evidence_for(m, dr, seed):
    from glossrig.core.rig import load_rig

    rig = load_rig(RIG)
    geom = m.data.measured.geometry[0.0]
    K, dist = m.data.camera
    size = m.data.image_size
    units = outline_units(rig, geom, (K, dist), size, dr, seed)
    return silhouette_evidence(units, {0.0: geom}, (K, dist), rig.cylinder_radius, rig.sample_height, m.data.lamps)


def test_the_outline_names_the_radius_and_refutes_one_it_does_not_show(radius_brdf):
    from glossrig.core.diagnose.catalogue import model_of
    from glossrig.core.diagnose.report import verdict

    m, fitted = radius_brdf
    causes = copy.deepcopy(fitted)
    c = next(x for x in causes if x.name == "sample_radius_error")
    ev = _evidence_for(m, 0.6, 7)
    assert ev["significant"], ev["why_not"]
    apply_silhouette_evidence(model_of(m, c), causes, ev)
    assert c.frame_signature and c.significant
    assert abs(c.magnitude - 0.6) < 4 * max(ev["se"], c.stderr["dr_mm"]), (c.magnitude, ev["se"])
    assert verdict(causes) == "sample_radius_error"
    json.dumps(c.to_json())
    # where the BRDF rows alone do not name it (a real material's misfit), the outline's value and test hold
    causes = copy.deepcopy(fitted)
    c = next(x for x in causes if x.name == "sample_radius_error")
    c.identifiable = False
    apply_silhouette_evidence(model_of(m, c), causes, ev)
    assert c.params["fixed_by"] == "silhouette" and c.significant and c.params["fixed_brdf_gain"] > 0
    assert abs(c.magnitude - 0.6) < 4 * ev["se"]
    assert verdict(causes) == "sample_radius_error"
    # an outline at the rig file's radius refutes the BRDF rows' radius
    causes = copy.deepcopy(fitted)
    c = next(x for x in causes if x.name == "sample_radius_error")
    assert c.significant
    apply_silhouette_evidence(model_of(m, c), causes, _evidence_for(m, 0.0, 8))
    assert c.refuted and not c.significant
    assert verdict(causes) != "sample_radius_error"


def _make_radius_capture(d):
    glossrig_cli("simulate", "--rig", RIG, "--repeats", 1, "--scale", 0.12, "--spp", 1, "--rotations", 0,
                 "--leds", "6", "--no-progress", "--ideal", "--material", "sample_2_6", "--seed", 8,
                 "--effects", "sample_radius_error=0.8", "--out", d / "sample")
    t = json.loads((d / "sample" / "truth.json").read_text())
    (d / "camera.json").write_text(json.dumps(camera_json_from_truth(t)))


def test_outline_read_from_the_twins_dngs(tmp_path_factory):
    """End to end on the twin's raw files: a sample 0.8 mm thicker than the rig file says, LED 6 lighting
    the lower limb, scale 0.12 (0.3 mm of radius a pixel): the pipeline's own HDR of the box around the
    outline and the capture's own marker calibration measure it."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.capture import load_manifest
    from glossrig.core.diagnose.silhouette import limb_rates
    from glossrig.core.extraction.extract import camera_arrays, rotation_geometry
    from glossrig.core.rig import load_rig

    d = run_shared_folder(tmp_path_factory, "radius_capture", {"seed": 8, "dr": 0.8, "rig": RIG.read_text()},
                          _make_radius_capture)
    cam = load_camera(d / "camera.json")
    man = load_manifest(d / "sample")
    rig = load_rig(d / "sample" / "rig.toml")
    geom = {0.0: rotation_geometry(man, rig, cam, 0.0)}
    units = limb_rates(d / "sample", geom, camera_arrays(cam), cam.image_size)
    ev = silhouette_evidence(units, geom, camera_arrays(cam), rig.cylinder_radius, rig.sample_height,
                             {6: np.asarray(rig.led(6).position, float)})
    assert ev is not None and ev["significant"], ev
    assert abs(ev["dr"] - 0.8) < 4 * ev["se"], (ev["dr"], ev["se"])
