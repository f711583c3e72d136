"""Stock Mitsuba 3 BSDFs on the twin's sample (``--material mitsuba:FILE.xml``): the render
is the BSDF's own evaluation, the sample rotation turns its tangent frame, the truth records
the XML, and a bad file fails with exit 2 naming it."""
from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from glossrig.core.errors import InputError
from glossrig.core.extraction.cylinder import sample_angles, surface_samples
from glossrig.core.models.angles import local_direction
from glossrig.core.models.materials import MATERIALS_DIR, parse_material

from conftest import RIG

pytestmark = pytest.mark.mitsuba

CONDUCTOR = """<bsdf type="roughconductor">
    <string name="distribution" value="{dist}"/>
    <float name="alpha_u" value="{au}"/>
    <float name="alpha_v" value="{av}"/>
    <string name="material" value="Au"/>
</bsdf>
"""


def _xml(tmp_path, name, dist="ggx", au=0.12, av=0.35):
    p = tmp_path / f"{name}.xml"
    p.write_text(CONDUCTOR.format(dist=dist, au=au, av=av))
    return parse_material(f"mitsuba:{p}")


def _half_vector_pairs(n=4000, seed=0):
    """Direction pairs (light, camera) around the mirror direction, both above the surface."""
    rng = np.random.default_rng(seed)
    wi = local_direction(rng.uniform(0.05, 1.3, n), rng.uniform(0, 2 * np.pi, n))
    h = local_direction(rng.uniform(0, 0.5, n), rng.uniform(0, 2 * np.pi, n))
    wo = 2 * np.sum(wi * h, axis=-1, keepdims=True) * h - wi
    keep = wo[:, 2] > 0.05
    return wi[keep], wo[keep]


def test_render_matches_bsdf_evaluation(rig):
    """Rendered radiance on the sample = f(wi, wo) I cos(theta_in) / d^2 with f from Mitsuba's own
    evaluation of the roughconductor, at a sample rotation of 30 degrees: checks the wrapper's
    frame rotation (sign and axis) against the rig's tangent frame (thesis eq. 4.61-4.62)."""
    from glossrig.twin.mitsuba_material import MitsubaBRDF
    from glossrig.twin.scene import LED_RGB
    from glossrig.twin.virtual_rig import VirtualRig

    mat = parse_material("mitsuba:aniso_roughconductor_beckmann")
    truth = MitsubaBRDF(mat)
    vr = VirtualRig(rig, mat, scale=0.1, seed=0, effects={}, spp=4)
    vr.set_rotation(30.0)
    s = surface_samples(vr.lens.K, vr.lens.dist, vr.lens.size, vr.camera_R, vr.camera_t, np.eye(3), np.zeros(3),
                        vr.sample_radius, rig.sample_height)
    mask = np.zeros(vr.lens.size[::-1], np.uint8)
    mask[s.v, s.u] = 1
    inner = cv2.erode(mask, np.ones((5, 5), np.uint8))[s.v, s.u].astype(bool)
    led = 6
    img = vr.led_radiance(led)[..., 1]
    ang = sample_angles(s, vr.led_positions[led], 30.0)
    f = truth.eval_angles(ang["theta_in"], ang["phi_in"], ang["theta_out"], ang["phi_out"])[:, 1]
    pred = f * vr.intensity * LED_RGB[1] * np.clip(ang["cos_in"], 0, None) / (ang["dist_in"] * 1e-3) ** 2
    keep = inner & (ang["cos_out"] > 0.3) & (ang["cos_in"] > 0.2) & (pred > 0.05 * pred.max())
    got = img[s.v[keep], s.u[keep]]
    rel = np.abs(got / pred[keep] - 1)
    assert keep.sum() > 100, keep.sum()
    assert np.median(rel) < 0.02, np.median(rel)
    assert np.percentile(rel, 90) < 0.08, np.percentile(rel, 90)
    # the same pixels against the material unturned: the rotation must matter here
    ang0 = sample_angles(s, vr.led_positions[led], 0.0)
    f0 = truth.eval_angles(ang0["theta_in"], ang0["phi_in"], ang0["theta_out"], ang0["phi_out"])[:, 1]
    assert np.median(np.abs(f0[keep] / f[keep] - 1)) > 0.1
    # directions in the rig's unrotated frame with the material turned by 30 degrees: the same truth
    wi0 = local_direction(ang0["theta_in"], ang0["phi_in"])
    wo0 = local_direction(ang0["theta_out"], ang0["phi_out"])
    np.testing.assert_allclose(truth.eval(wi0, wo0, 30.0)[keep, 1], f[keep], rtol=1e-3)


def test_rotation_by_90_degrees_swaps_alpha_u_and_alpha_v(tmp_path):
    from glossrig.twin.mitsuba_material import MitsubaBRDF

    for dist in ("ggx", "beckmann"):
        a = MitsubaBRDF(_xml(tmp_path, f"uv_{dist}", dist, au=0.08, av=0.3))
        b = MitsubaBRDF(_xml(tmp_path, f"vu_{dist}", dist, au=0.3, av=0.08))
        wi, wo = _half_vector_pairs()
        fa0, fa90, fb0 = a.eval(wi, wo, 0.0), a.eval(wi, wo, 90.0), b.eval(wi, wo, 0.0)
        ok = fb0[:, 1] > 1e-3 * fb0[:, 1].max()
        assert ok.sum() > 1000
        np.testing.assert_allclose(fa90[ok], fb0[ok], rtol=1e-4)
        assert np.median(np.abs(fa0[ok, 1] / fb0[ok, 1] - 1)) > 0.5        # anisotropic: turning it matters
        # alpha_u lies along the tangent: a half vector tilted along it falls off faster
        light = local_direction(np.radians(25.0), 0.0)
        tilted = [local_direction(np.radians(8.0), np.radians(phi)) for phi in (0.0, 90.0)]
        along_u, along_v = (a.eval(light, 2 * np.dot(light, h) * h - light)[1] for h in tilted)
        assert along_u < 0.3 * along_v


def test_rotated_render_swaps_alpha_u_and_alpha_v(rig, tmp_path):
    """The twin's render at sample rotation 90 of (alpha_u, alpha_v) = (a, b) is the render at
    rotation 0 of (b, a): the sample rotation reaches the stock BSDF's tangent frame."""
    from glossrig.twin.virtual_rig import VirtualRig

    def render(mat, rot):
        vr = VirtualRig(rig, mat, scale=0.08, seed=0, effects={}, spp=1)
        vr.set_rotation(rot)
        return vr.led_radiance(6)[..., 1]

    uv, vu = _xml(tmp_path, "uv", au=0.05, av=0.3), _xml(tmp_path, "vu", au=0.3, av=0.05)
    turned, swapped, unturned = render(uv, 90.0), render(vu, 0.0), render(uv, 0.0)
    lit = swapped > 0.01 * swapped.max()
    assert lit.sum() > 1000
    assert np.max(np.abs(turned - swapped)) < 1e-4 * swapped.max()
    assert np.median(np.abs(unturned[lit] / swapped[lit] - 1)) > 0.5


def test_packaged_examples_load_and_truth_rebuilds(tmp_path):
    """The shipped examples load; the truth record (XML text, sha256) rebuilds the same BRDF."""
    from glossrig.twin.mitsuba_material import MitsubaBRDF, load_bsdf

    names = sorted(p.name for p in MATERIALS_DIR.glob("*.xml"))
    assert {"aniso_roughconductor_ggx.xml", "aniso_roughconductor_beckmann.xml", "roughplastic_beckmann.xml",
            "aniso_principled.xml"} <= set(names)
    wi, wo = _half_vector_pairs(500)
    for name in names:
        mat = parse_material(f"mitsuba:{MATERIALS_DIR / name}")
        assert load_bsdf(mat) is not None
        d = json.loads(json.dumps(mat.to_json()))
        assert d["kind"] == "mitsuba" and d["xml"] == (MATERIALS_DIR / name).read_text()
        assert d["xml_sha256"] == hashlib.sha256((MATERIALS_DIR / name).read_bytes()).hexdigest()
        f = MitsubaBRDF.from_json(d).eval(wi, wo, 20.0)
        assert np.all(np.isfinite(f)) and f.max() > 0
        np.testing.assert_allclose(f, MitsubaBRDF(mat).eval(wi, wo, 20.0))
    # a bare name finds the packaged file; no version attribute is read as 3.0.0
    assert parse_material("mitsuba:aniso_roughconductor_ggx").path == str(MATERIALS_DIR / "aniso_roughconductor_ggx.xml")
    assert load_bsdf(_xml(tmp_path, "noversion")) is not None


@pytest.mark.parametrize("text, words", [
    ("<bsdf type='roughconductor'>", "well-formed"),
    ("<shape type='sphere'/>", "root element"),
    ("<bsdf type='no_such_plugin'/>", "no_such_plugin"),
    ("<bsdf type='roughplastic'><float name='alpha_u' value='0.1'/><float name='alpha_v' value='0.2'/></bsdf>",
     "anisotropic"),
])
def test_bad_xml_is_an_input_error_naming_the_file(tmp_path, text, words):
    from glossrig.twin.mitsuba_material import load_bsdf

    p = tmp_path / "bad.xml"
    p.write_text(text)
    with pytest.raises(InputError) as e:
        load_bsdf(parse_material(f"mitsuba:{p}"))
    assert str(p) in str(e.value) and words in str(e.value)
    with pytest.raises(InputError, match="not found"):
        parse_material(f"mitsuba:{tmp_path / 'missing.xml'}")


def test_cli_bad_xml_exits_2_naming_the_file(tmp_path):
    p = tmp_path / "broken.xml"
    p.write_text("<bsdf type='roughconductor'><float name='alpha_u' value='0.1'/>")
    out = tmp_path / "cap"
    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "simulate", "--rig", str(RIG), "--material",
                        f"mitsuba:{p}", "--leds", "6", "--scale", "0.05", "--no-progress", "--out", str(out)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    assert str(p) in r.stderr and "Traceback" not in r.stderr
    assert not out.exists() or not any(out.iterdir())


def test_simulate_records_the_xml_in_truth(tmp_path):
    """A whole (tiny) capture of the packaged GGX example from the CLI; truth.json holds its text."""
    out = tmp_path / "cap"
    xml = MATERIALS_DIR / "aniso_roughconductor_ggx.xml"
    r = subprocess.run([sys.executable, "-m", "glossrig.cli.main", "simulate", "--rig", str(RIG), "--material",
                        f"mitsuba:{xml}", "--leds", "6", "--rotations", "0", "--scale", "0.08", "--spp", "1",
                        "--ideal", "--no-progress", "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr
    truth = json.loads((out / "truth.json").read_text())
    m = truth["material"]
    assert m["kind"] == "mitsuba" and m["xml"] == xml.read_text()
    assert m["xml_sha256"] == hashlib.sha256(xml.read_bytes()).hexdigest()
    assert "MitsubaBRDF.from_json" in m["evaluate"]
