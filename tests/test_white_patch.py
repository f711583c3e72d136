"""The white patch as a witness (core/diagnose/white_patch.py, issue 14): the patch, the same surface
in the sample and reference captures, measures the vignetting and a changed LED emission pattern
between them where the BRDF data cannot tell them from the material."""
from __future__ import annotations

import copy
import json
import math

import numpy as np
import pytest

from glossrig.core.diagnose.catalogue import vignetting_factor
from glossrig.core.diagnose.white_patch import (PATCH_GAIN, apply_emission_evidence, apply_patch_evidence,
                                               emission_evidence, patch_evidence, patch_points)

from test_diagnose import fitted_brdf

SIZE, PP = (1508, 1008), (754.7, 503.4)     # the thesis rig's camera at scale 0.25
REL_NOISE = 0.005                           # each rate's relative noise (HDR of a bright white patch)


def synthetic_units(seed, k, leds=(6, 9), centre=(1172, 504), half=41, size=SIZE, pp=PP, across=0.0):
    """Both captures' patch rates: per LED a smooth irradiance pattern across the patch (the same in
    both captures), an LED output that differs between them, the sample capture's rates times
    ``1 - k_LED q`` (``k``: a number, or one per LED) and REL_NOISE on each rate. ``across``: a change
    of the LED's light between the captures that tilts the sample capture's patch by this fraction
    per patch half-width across the radius (v here), with alternating sign per LED."""
    rng = np.random.default_rng(seed)
    ks = dict(zip(leds, np.broadcast_to(np.asarray(k, float), (len(leds),))))
    vv, uu = np.mgrid[centre[1] - half:centre[1] + half, centre[0] - half:centre[0] + half]
    u, v = uu.ravel().astype(float), vv.ravel().astype(float)
    colour = np.array([[0, 1], [1, 2]])[vv.ravel() % 2, uu.ravel() % 2]
    q = vignetting_factor(u, v, size, pp)
    units = []
    for led in leds:
        pattern = (1 + 0.08 * (u - centre[0]) / half - 0.03 * ((v - centre[1]) / half) ** 2) \
            * np.array([0.6, 1.0, 0.45])[colour] * rng.uniform(500, 2000)
        rr = pattern * (1 + REL_NOISE * rng.standard_normal(len(u)))
        tilt = 1 + across * (-1) ** len(units) * (v - centre[1]) / half
        rs = pattern * rng.uniform(0.9, 1.1) * (1 - ks[led] * q) * tilt * (1 + REL_NOISE * rng.standard_normal(len(u)))
        units.append({"rotation": 0.0, "led": led, "u": u, "v": v, "colour": colour, "rs": rs, "rr": rr,
                      "vs": (REL_NOISE * rs) ** 2, "vr": (REL_NOISE * rr) ** 2})
    return units


def expected_se(units, size=SIZE, pp=PP) -> float:
    """k's standard error from the noise alone: the log ratio's variance 2 REL_NOISE^2 over the spread
    of q within each (LED, colour) group (the offsets are free)."""
    s = 0.0
    for un in units:
        q = vignetting_factor(un["u"], un["v"], size, pp)
        for c in range(3):
            qc = q[un["colour"] == c]
            s += float(np.sum((qc - qc.mean()) ** 2))
    return math.sqrt(2 * REL_NOISE ** 2 / s)


@pytest.mark.parametrize("k,seed", [(0.15, 1), (0.3, 2), (-0.2, 3)])
def test_patch_measures_the_vignetting_between_the_captures(k, seed):
    units = synthetic_units(seed, k)
    ev = patch_evidence(units, SIZE, PP)
    se = expected_se(units)
    assert ev["significant"], ev
    assert abs(ev["k"] - k) < 4 * se, (ev["k"], k, se)
    assert 0.7 * se < ev["se"] < 1.4 * se         # the stated uncertainty is the noise's
    assert all(abs(x - k) < 5 * se * math.sqrt(2) for x in ev["per_led"].values())


def test_no_vignetting_is_no_signature():
    for seed in range(10, 16):
        ev = patch_evidence(synthetic_units(seed, 0.0), SIZE, PP)
        assert not ev["significant"] and ev["gain"] < PATCH_GAIN, ev
        assert abs(ev["k"]) < 4 * expected_se(synthetic_units(seed, 0.0))


def test_a_tilt_that_differs_per_led_is_no_vignetting():
    """An LED whose emission or position changed between the captures tilts its own patch ratio:
    vignetting tilts every LED's alike, so disagreeing LEDs are no value of the lens."""
    ev = patch_evidence(synthetic_units(4, [0.35, -0.15]), SIZE, PP)
    assert not ev["significant"], ev


def test_a_tilt_across_the_radius_is_no_vignetting():
    """A changed LED emission pattern tilts the patch along the radius too (on the thesis rig the
    patch lies along the cylinder axis, where the pattern falls off), and the LEDs may agree on it;
    its tilt across the radius, where vignetting is flat, gives it away. A tilt of 0.2 % per
    half-width is ~10 standard errors of the gradient (REL_NOISE, 6724 pixels per LED)."""
    ev = patch_evidence(synthetic_units(6, 0.2, across=0.002), SIZE, PP)
    assert not ev["significant"] and "not radial" in ev["why_not"], ev
    assert max(abs(z) for z in ev["tangential_z"].values()) > 5
    ev = patch_evidence(synthetic_units(6, 0.2), SIZE, PP)
    assert ev["significant"] and max(abs(z) for z in ev["tangential_z"].values()) < 5, ev


def test_a_hot_pixel_in_the_patch_is_left_out():
    units = synthetic_units(5, 0.2)
    units[0]["rs"][100] *= 40.0
    ev = patch_evidence(units, SIZE, PP)
    assert ev["outliers"] >= 1 and ev["significant"]
    assert abs(ev["k"] - 0.2) < 4 * expected_se(units)


@pytest.fixture(scope="module")
def vignetted_brdf():
    """A Ward capture with vignetting 0.2, its BRDF-space causes fitted."""
    return fitted_brdf(41, "vignetting", 0.2)


def _patch_units_for(m, k, seed):
    u0, v0 = (int(round(x)) for x in m.data.patch_uv[0.0])
    return synthetic_units(seed, k, centre=(u0, v0), half=20, size=m.data.image_size, pp=m.data.principal_point)


def test_the_patch_names_vignetting_with_its_k(vignetted_brdf):
    from glossrig.core.diagnose.catalogue import model_of
    from glossrig.core.diagnose.report import verdict

    m, causes = vignetted_brdf
    causes = copy.deepcopy(causes)
    units = _patch_units_for(m, 0.2, 42)
    ev = patch_evidence(units, m.data.image_size, m.data.principal_point)
    vig = next(c for c in causes if c.name == "vignetting")
    assert vig.significant                          # the Ward capture's BRDF rows name it themselves
    k_brdf = vig.params["k"]
    apply_patch_evidence(model_of(m, vig), causes, ev)
    # they agree with the patch, so their own fit stays and the patch confirms it
    assert vig.frame_signature and vig.params["confirmed_by"] == "patch" and vig.params["k"] == k_brdf
    assert abs(vig.params["k_patch"] - 0.2) < 4 * expected_se(units, m.data.image_size, m.data.principal_point)
    assert verdict(causes) == "vignetting"
    json.dumps(vig.to_json())                      # report.json can hold it
    # where the BRDF-space fit is not significant by itself, the cause takes the patch's test and value
    causes = copy.deepcopy(vignetted_brdf[1])
    vig = next(c for c in causes if c.name == "vignetting")
    vig.identifiable = False                        # as on a real material whose misfit flattens its profile
    apply_patch_evidence(model_of(m, vig), causes, ev)
    assert vig.frame_signature and vig.params["fixed_by"] == "patch" and vig.significant
    assert abs(vig.magnitude - 0.2) < 4 * expected_se(units, m.data.image_size, m.data.principal_point)
    assert verdict(causes) == "vignetting"


def test_a_flat_patch_refutes_a_brdf_space_vignetting(vignetted_brdf):
    """The BRDF data call for k = 0.2, the patch shows none between the captures: what the BRDF data
    read as vignetting is not the lens (here: the test's own construction; on a real capture a
    material's departure), so it is refuted and not named."""
    from glossrig.core.diagnose.catalogue import model_of
    from glossrig.core.diagnose.report import verdict

    m, causes = vignetted_brdf
    causes = copy.deepcopy(causes)
    vig = next(c for c in causes if c.name == "vignetting")
    assert vig.significant                          # the BRDF-space fit alone names it
    ev = patch_evidence(_patch_units_for(m, 0.0, 43), m.data.image_size, m.data.principal_point)
    apply_patch_evidence(model_of(m, vig), causes, ev)
    assert vig.refuted and not vig.significant
    assert verdict(causes) != "vignetting"


def test_patch_rates_read_from_rewritten_dngs(tiny_captures, tmp_path):
    """End to end on real DNG files: the tiny twin capture's raws rewritten with a vignetting of 0.3
    (outside the twin, glossrig.twin.rewrite_raw); the pipeline's own HDR of both captures' patches
    measures it, and the untouched capture shows none."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.capture import load_manifest
    from glossrig.core.extraction.extract import rotation_geometry
    from glossrig.core.diagnose.white_patch import patch_rates
    from glossrig.core.rig import load_rig
    from glossrig.twin.rewrite_raw import rewrite_capture

    d = tiny_captures
    cam = load_camera(d / "camera.json")
    rewrite_capture(d / "sample", tmp_path / "vig", "vignetting", 0.3)

    def geometry(folder):
        man = load_manifest(folder)
        return {0.0: rotation_geometry(man, load_rig(folder / "rig.toml"), cam, 0.0)}

    ref = geometry(d / "ref")
    out = {}
    for name, folder in (("null", d / "sample"), ("vig", tmp_path / "vig")):
        units = patch_rates(folder, d / "ref", geometry(folder), ref)
        man = load_manifest(folder)
        fr = man.read_raw(next(im for im in man.images if im.role == "calibration"), crop=(0, 0, 2, 2))
        w, h = fr.full_size
        # the rewrite's fall-off is about the image centre; diagnose's about the calibrated principal point
        out[name] = patch_evidence(units, (w, h), ((w - 1) / 2, (h - 1) / 2))
    assert out["vig"]["significant"], out["vig"]
    assert abs(out["vig"]["k"] - 0.3) < 4 * out["vig"]["se"], out["vig"]
    assert not out["null"]["significant"] and abs(out["null"]["k"]) < 4 * out["null"]["se"], out["null"]


# ----------------------------------------------------------------- the LED emission pattern

def emission_units(data, seed, n=0.0, k=0.0, es_seed=None):
    """Patch units of a synthetic BRDF capture (tests/test_diagnose.synthetic_brdf): the pixels around its
    patch centre, their points on the marker's plane (:func:`patch_points`), the sample capture's rates
    times the twin's cos^n emission pattern of ``EffectState`` (seed ``es_seed``: the tilt directions) and
    ``1 - k q``."""
    from glossrig.core.rig import load_rig
    from glossrig.twin.effects import EffectState

    u0, v0 = (int(round(x)) for x in data.patch_uv[0.0])
    units = synthetic_units(seed, k, leds=tuple(sorted(data.lamps)), centre=(u0, v0), half=20,
                            size=data.image_size, pp=data.principal_point)
    patch_points(units, data)
    if n > 0:
        rig = load_rig(data.measured.rig_path)
        es = EffectState({"led_emission": n}, es_seed, rig.led_ids())
        for un in units:
            f = es.emission_factor(un["led"], np.asarray(rig.led(un["led"]).position, float), un["X"])
            un["rs"] = un["rs"] * f
            un["vs"] = un["vs"] * f ** 2
    return units


@pytest.fixture(scope="module")
def emission_brdf():
    """A Ward capture whose LEDs emit as cos^15 about their (tilted) axes, its BRDF-space causes fitted."""
    return fitted_brdf(44, "led_emission", 15.0)


def test_patch_measures_the_emission_pattern(emission_brdf):
    m, _ = emission_brdf
    lamps = m.data.lamps
    ev = emission_evidence(emission_units(m.data, 50, n=15.0, es_seed=44), lamps, m.data.image_size,
                           m.data.principal_point)
    assert ev["significant"], ev
    assert abs(ev["n"] - 15.0) < 4 * ev["se"], ev
    assert ev["se"] < 5.0                            # the patch measures n, not just a tilt
    for seed, k in ((51, 0.0), (52, 0.25)):          # no change, and vignetting: no emission pattern
        ev = emission_evidence(emission_units(m.data, seed, k=k), lamps, m.data.image_size, m.data.principal_point)
        assert not ev["significant"], (k, ev)


def test_the_patch_names_the_emission_pattern_where_the_brdf_data_agree(emission_brdf):
    from glossrig.core.diagnose.catalogue import model_of
    from glossrig.core.diagnose.report import verdict

    m, causes = emission_brdf
    causes = copy.deepcopy(causes)
    ev = emission_evidence(emission_units(m.data, 53, n=15.0, es_seed=44), m.data.lamps, m.data.image_size,
                           m.data.principal_point)
    c = next(x for x in causes if x.name == "led_emission")
    assert c.significant
    apply_emission_evidence(model_of(m, c), causes, ev)
    assert c.frame_signature and c.params["confirmed_by"] == "patch"
    assert verdict(causes) == "led_emission"
    json.dumps(c.to_json())
    causes = copy.deepcopy(emission_brdf[1])
    c = next(x for x in causes if x.name == "led_emission")
    c.identifiable = False                          # the BRDF rows alone do not name it
    apply_emission_evidence(model_of(m, c), causes, ev)
    assert c.frame_signature and c.params["fixed_by"] == "patch" and c.params["fixed_brdf_gain"] > 0
    assert abs(c.magnitude - 15.0) < 4 * ev["se"]
    assert verdict(causes) == "led_emission"


def test_an_emission_pattern_the_brdf_data_do_not_show_is_not_named(vignetted_brdf):
    """The patch shows a pattern, the BRDF rows (a capture without one) get worse with it held fixed:
    the patch alone names nothing."""
    from glossrig.core.diagnose.catalogue import model_of

    m, causes = vignetted_brdf
    causes = copy.deepcopy(causes)
    ev = emission_evidence(emission_units(m.data, 54, n=40.0, es_seed=44), m.data.lamps, m.data.image_size,
                           m.data.principal_point)
    assert ev["significant"]
    c = next(x for x in causes if x.name == "led_emission")
    apply_emission_evidence(model_of(m, c), causes, ev)
    assert not c.frame_signature and c.params["fixed_brdf_gain"] < 0
