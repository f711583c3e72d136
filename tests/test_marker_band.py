"""The cylinder's white marker band as a witness of the LED positions (core/diagnose/marker_band.py,
issue 14): the same white paper in the sample and reference captures is shaded between them as an
LED's move dictates, whatever the sample's material."""
from __future__ import annotations

import copy
import json

import numpy as np
import pytest

from glossrig.core.diagnose.marker_band import (BAND_FLOOR_MM, BAND_Z3, apply_band_evidence, band_bound, band_evidence,
                                                band_moved, band_points)

from conftest import RIG, glossrig_cli, run_shared_folder
from test_silhouette import thesis_geometry

NOISE = 0.01          # each rate's relative noise
MOVES = {6: np.array([3.0, -4.0, 2.5]), 9: np.array([-2.0, 5.0, -3.5])}


def _irr(P, X, N):
    d = P[None, :] - X
    d2 = np.sum(d * d, axis=1)
    return np.maximum(np.sum(d * N, axis=1), 0.0) / np.sqrt(d2) / d2


def band_units(rig, geom, cam, size, moves, seed, vignetting=0.0):
    """Both captures' rates over the band: white paper (albedo 0.8) with printed markers (albedo 0.04 on
    a pixel in five), lit by each LED where the rig file puts it in the reference capture and moved by
    ``moves[led]`` (mm) in the sample capture, another LED output per capture, a colour factor per
    Bayer site, NOISE on each rate; ``vignetting``: the sample capture's 1 - k q (q about the image centre)."""
    rng = np.random.default_rng(seed)
    bp = band_points(geom, cam, rig, size)
    X, N, u, v = bp["X"], bp["N"], bp["u"], bp["v"]
    colour = np.array([[0, 1], [1, 2]])[v % 2, u % 2]
    albedo = np.where(rng.random(len(u)) < 0.2, 0.04, 0.8) * np.array([0.6, 1.0, 0.45])[colour]
    w, h = size
    q = ((u - w / 2) ** 2 + (v - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    units = []
    for led in (6, 9):
        P = np.asarray(rig.led(led).position, float)
        rr = albedo * _irr(P, X, N) * 1e5 * (1 + NOISE * rng.standard_normal(len(u)))
        rs = albedo * _irr(P + moves.get(led, 0.0), X, N) * 1e5 * rng.uniform(0.9, 1.1) * (1 - vignetting * q) \
            * (1 + NOISE * rng.standard_normal(len(u)))
        ok = (rr > 0) & (rs > 0)
        units.append({"rotation": 0.0, "led": led, "X": X[ok], "N": N[ok], "colour": colour[ok],
                      "rs": rs[ok], "rr": rr[ok], "vs": (NOISE * rs[ok]) ** 2, "vr": (NOISE * rr[ok]) ** 2})
    return units


def lamps(rig):
    return {k: np.asarray(rig.led(k).position, float) for k in (6, 9)}


def test_band_measures_the_leds_moves():
    rig, geom, cam, size = thesis_geometry(0.25)
    ev = band_evidence(band_units(rig, geom, cam, size, MOVES, 1), lamps(rig))
    assert ev["significant"], ev["why_not"]
    for led, move in MOVES.items():
        p = ev["per_led"][str(led)]
        se = np.hypot(p["se_mm"], BAND_FLOOR_MM)
        assert np.all(np.abs(np.array(p["offset_mm"]) - move) < 4 * se), (led, p, move)
    true_rms = float(np.sqrt(np.mean(np.square(list(MOVES.values())))))
    assert abs(ev["magnitude"] - true_rms) < 4 * ev["se"]
    json.dumps(ev)


def test_leds_where_they_were_are_no_signature():
    rig, geom, cam, size = thesis_geometry(0.25)
    for seed in (2, 3, 4):
        ev = band_evidence(band_units(rig, geom, cam, size, {}, seed), lamps(rig))
        assert not ev["significant"], ev
        assert max(p["z"] for p in ev["per_led"].values()) < BAND_Z3
        assert not band_moved(ev["per_led"])[0]


def test_leds_moved_a_little_each_are_seen_together():
    """The two tests of no move at the 4-sigma tail (module docstring, "Test"): one LED far out, or
    every LED a little out together - each LED under its own bound but the sum of chi^2 over all of
    them beyond chi^2's bound with 3 x LEDs degrees of freedom; neither where the offsets are what
    no move gives."""
    from scipy.stats import chi2, norm

    def leds(*z):
        return {str(k): {"z": v} for k, v in enumerate(z)}

    assert band_bound(8) == pytest.approx(chi2.isf(2 * norm.sf(4.0), 24)) and 59 < band_bound(8) < 61
    assert band_moved(leds(5.0, 0.1))[0]                                   # one LED out
    spread = [2.85] * 8                                                    # each under 4.70, sum 65 > 60
    assert max(spread) < BAND_Z3 and band_moved(leds(*spread))[0]
    assert "together" in band_moved(leds(*spread))[1]
    assert not band_moved(leds(*[2.2] * 8))[0]                             # sum 38.7: no move
    assert not band_moved(leds(3.5, 3.5))[0]                               # two LEDs: sum 24.5 < 28.9
    rng = np.random.default_rng(1)
    # offsets that are noise alone (chi with 3 dof per LED): the eight LEDs' own tests and the sum's at
    # the 4-sigma tail (6.3e-5) give at most 9 x 6.3e-5 false alarms a capture, 11.4 expected in 20000;
    # more than 25 has a Poisson(11.4) chance of 2e-4
    alarms = sum(band_moved(leds(*np.sqrt(rng.chisquare(3, 8))))[0] for _ in range(20000))
    assert alarms <= 25


def test_a_bent_band_is_not_read():
    """Vignetting between the captures tilts the band's ratio too: found elsewhere (the white patch), it
    stops the band being read; unseen, the held-out halves do not agree on any move."""
    rig, geom, cam, size = thesis_geometry(0.25)
    units = band_units(rig, geom, cam, size, {}, 5, vignetting=0.2)
    ev = band_evidence(units, lamps(rig), bent_by=["vignetting"])
    assert not ev["significant"] and "vignetting" in ev["why_not"]
    ev = band_evidence(units, lamps(rig))
    assert not ev["significant"], ev


@pytest.fixture(scope="module")
def moved_brdf():
    """A Ward capture whose LEDs sit off the rig file's positions (led_position_error 3 mm per axis; this
    seed's draw moves LED 9 by (5.0, -2.0, 4.3) mm)."""
    from test_diagnose import fitted_brdf

    return fitted_brdf(47, "led_position_error", 3.0)


def _band_for(m, moves, seed):
    from glossrig.core.rig import load_rig

    rig = load_rig(RIG)
    units = band_units(rig, m.data.measured.geometry[0.0], m.data.camera, m.data.image_size, moves, seed)
    return band_evidence(units, m.data.lamps)


def test_the_band_names_the_leds_moves_and_refutes_moves_it_does_not_show(moved_brdf):
    from glossrig.core.diagnose.catalogue import model_of
    from glossrig.core.diagnose.report import verdict
    from glossrig.core.rig import load_rig
    from glossrig.twin.effects import EffectState

    m, fitted = moved_brdf
    rig = load_rig(RIG)
    es = EffectState({"led_position_error": 3.0}, 47, rig.led_ids())
    moves = {k: np.asarray(es.detail["led_offset_mm"][k], float) for k in (6, 9)}
    ev = _band_for(m, moves, 11)
    assert ev["significant"], ev["why_not"]
    causes = copy.deepcopy(fitted)
    c = next(x for x in causes if x.name == "led_position_error")
    c.identifiable = False                       # as where the BRDF rows alone do not name it
    apply_band_evidence(model_of(m, c), causes, ev)
    assert c.params["fixed_by"] == "marker band" and c.significant and c.frame_signature
    assert abs(c.magnitude - ev["magnitude"]) < 1e-12
    assert verdict(causes) == "led_position_error"
    json.dumps(c.to_json())
    # an LED the band did not measure stays where the lamp calibration puts it; the others still name the cause
    partial = copy.deepcopy(ev)
    del partial["per_led"]["6"]
    causes = copy.deepcopy(fitted)
    c = next(x for x in causes if x.name == "led_position_error")
    c.identifiable = False
    apply_band_evidence(model_of(m, c), causes, partial)
    assert c.params["fixed_by"] == "marker band" and "LED(s) 6 not measured on the band" in c.note
    # a band that shows the LEDs where they were refutes the BRDF rows' moves
    causes = copy.deepcopy(fitted)
    c = next(x for x in causes if x.name == "led_position_error")
    assert c.significant
    apply_band_evidence(model_of(m, c), causes, _band_for(m, {}, 12))
    assert c.refuted and not c.significant
    assert verdict(causes) != "led_position_error"


def _make_moved_capture(d):
    from conftest import TINY_SIM

    glossrig_cli("simulate", *TINY_SIM, "--material", "sample_2_6", "--seed", 7, "--effects",
                 "led_position_error=5", "--out", d / "sample")


def test_band_read_from_the_twins_dngs(tiny_captures, tmp_path_factory):
    """End to end on the twin's raw files (scale 0.12, LED 9): the tiny captures' reference and a sample
    capture whose LED 9 sits off its hole (led_position_error 5 mm per axis, the twin's seeded draw); the
    pipeline's own HDR of both captures over the band and the sample capture's marker calibration
    measure the move, and the untouched sample capture shows none."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.capture import load_manifest, read_truth
    from glossrig.core.diagnose.marker_band import band_rates
    from glossrig.core.extraction.extract import camera_arrays, rotation_geometry
    from glossrig.core.rig import load_rig

    d = run_shared_folder(tmp_path_factory, "moved_capture", {"seed": 7, "sigma": 5, "rig": RIG.read_text()},
                          _make_moved_capture)
    cam = load_camera(tiny_captures / "camera.json")
    out = {}
    for name, folder in (("null", tiny_captures / "sample"), ("moved", d / "sample")):
        man = load_manifest(folder)
        rig = load_rig(folder / "rig.toml")
        geom = {0.0: rotation_geometry(man, rig, cam, 0.0)}
        units = band_rates(folder, tiny_captures / "ref", geom, camera_arrays(cam), cam.image_size)
        out[name] = band_evidence(units, {9: np.asarray(rig.led(9).position, float)})
    truth = np.asarray(read_truth(d / "sample")["effects"]["detail"]["led_offset_mm"]["9"], float)
    p = out["moved"]["per_led"]["9"]
    se = np.hypot(p["se_mm"], BAND_FLOOR_MM)
    assert np.all(np.abs(np.array(p["offset_mm"]) - truth) < 4 * se), (p, truth)
    # the twin's draw (seed 7) moves LED 9 well beyond the bound, so the band must name it
    assert np.sqrt(np.sum((truth / se) ** 2)) > BAND_Z3 + 2
    assert out["moved"]["significant"], out["moved"]
    assert not out["null"]["significant"], out["null"]


def test_the_causes_that_bend_the_band_are_those_found():
    from types import SimpleNamespace

    from glossrig.core.diagnose.marker_band import bending_causes

    causes = [SimpleNamespace(name="stray_light", eligible=True), SimpleNamespace(name="ggx_lobe", eligible=True),
              SimpleNamespace(name="sensor_nonlinearity", eligible=False), SimpleNamespace(name="hot_pixels", eligible=True)]
    assert bending_causes(causes, {"significant": True}, {"significant": False}) == ["stray_light", "vignetting"]
    assert bending_causes([], None, None) == []
