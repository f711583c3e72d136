"""Gloss units (ISO 2813 / ASTM D523), haze and DOI (ASTM E430) from a BRDF: core/models/gloss.py.

Every expected value is derived here independently of the module: Fresnel's equations
in their angle form, the solid angle of a small rectangular aperture, the narrow-lobe
limits of the Ward and GGX lobes.
"""
from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from glossrig.core.models import gloss as G
from glossrig.core.errors import InputError
from glossrig.core.models.ward import WardParams

ANGLES = {"gu20": 20.0, "gu60": 60.0, "gu85": 85.0}


def fresnel_angle_form(theta_deg: float, n: float) -> float:
    """Unpolarised Fresnel reflectance from Snell's law, in the sine/tangent form."""
    ti = math.radians(theta_deg)
    tt = math.asin(math.sin(ti) / n)
    rs = (math.sin(ti - tt) / math.sin(ti + tt)) ** 2
    rp = (math.tan(ti - tt) / math.tan(ti + tt)) ** 2
    return 0.5 * (rs + rp)


def test_fresnel_matches_snell_and_brewster():
    for th in (5.0, 20.0, 45.0, 60.0, 85.0):
        assert G.fresnel_dielectric(math.cos(math.radians(th)), 1.567) == pytest.approx(fresnel_angle_form(th, 1.567), rel=1e-12)
    assert G.fresnel_dielectric(1.0, 1.567) == pytest.approx((0.567 / 2.567) ** 2, rel=1e-12)
    # at Brewster's angle p-polarised light is not reflected: R = Rs / 2
    tb = math.atan(1.5)
    rs = ((math.cos(tb) - 1.5 * math.cos(math.pi / 2 - tb)) / (math.cos(tb) + 1.5 * math.cos(math.pi / 2 - tb))) ** 2
    assert G.fresnel_dielectric(math.cos(tb), 1.5) == pytest.approx(rs / 2, rel=1e-9)
    assert float(G.fresnel_factor(math.radians(G.RIG_THETA_D_MEAN_DEG))) == pytest.approx(1.0, abs=1e-12)


def test_standard_reading_is_the_glass_fresnel_reflectance():
    for k, th in ANGLES.items():
        assert G.standard_reflectance(G.GLOSS_GEOMETRIES[k]) == pytest.approx(fresnel_angle_form(th, 1.567), rel=2e-3)


def glass_mirror_ggx(alpha: float):
    """A near-perfect mirror of the standard's glass: a GGX lobe of width ``alpha`` times the
    absolute Fresnel reflectance of n = 1.567 (a normalised microfacet lobe: its albedo
    -> F as alpha -> 0)."""
    from glossrig.core.diagnose.material_models import ggx_lobe

    def f(a):
        F = G.fresnel_dielectric(np.cos(a["theta_d"]), G.GLASS_N)
        return F * ggx_lobe(a["theta_in"], a["phi_in"], a["theta_out"], a["phi_out"], a["theta_h"], a["phi_h"],
                            a["theta_d"], alpha, alpha, 0.0)
    return f


@pytest.mark.parametrize("key", list(ANGLES))
def test_mirror_of_the_standard_glass_reads_100_gu(key):
    g = G.GLOSS_GEOMETRIES[key]
    # an ideal mirror (delta lobe), integrated exactly
    assert G.gloss_units(g, mirror=lambda c: G.fresnel_dielectric(c, G.GLASS_N)) == pytest.approx(100.0, abs=0.5)
    # a GGX lobe far narrower than the apertures, through the numerical quadrature
    # (GGX's tail beyond the ~0.26 deg margin around the source image: < 0.1 %)
    assert G.gloss_units(g, glass_mirror_ggx(1e-4), width=1e-4) == pytest.approx(100.0, abs=0.5)
    # and at a different plane of incidence (isotropic lobe: same reading)
    assert G.gloss_units(g, glass_mirror_ggx(1e-4), width=1e-4, azimuth_deg=37.0) == pytest.approx(100.0, abs=0.5)


@pytest.mark.parametrize("key", list(ANGLES))
def test_lambertian_reads_its_small_receptor_share(key):
    """rho/pi * cos(theta) * receptor solid angle / F_glass(theta), with the solid angle of
    a small rectangle ~ (in-plane angle) x (perpendicular angle) in radians."""
    g, th = G.GLOSS_GEOMETRIES[key], ANGLES[key]
    rho = 0.8
    omega = math.radians(g.receptor.in_plane_deg) * math.radians(g.receptor.perpendicular_deg)
    expected = 100 * rho / math.pi * math.cos(math.radians(th)) * omega / fresnel_angle_form(th, 1.567)
    got = G.gloss_units(g, lambda a: np.full(a["theta_in"].shape, rho / math.pi))
    assert got == pytest.approx(expected, rel=0.05)
    # "about 0": under 1 GU at 20 and 85 deg, about 2 GU at 60 deg (wide receptor)
    assert got < (2.5 if key == "gu60" else 1.0)


def test_lambertian_haze_and_doi():
    """A Lambertian surface reads R ~ cos(theta_o) in every E430 receptor:
    DOI = 100 (1 - cos 30.3 / cos 30), haze = 100 cos 32 / cos 30."""
    v = G.e430(lambda a: np.full(a["theta_in"].shape, 0.8 / math.pi))
    c = lambda d: math.cos(math.radians(d))
    assert v["doi"] == pytest.approx(100 * (1 - c(30.3) / c(30)), abs=0.05)
    assert v["haze"] == pytest.approx(100 * c(32) / c(30), abs=0.2)


def test_mirror_doi_100_haze_0():
    v = G.e430(mirror=lambda c: G.fresnel_dielectric(c, G.GLASS_N))
    assert v["doi"] == 100.0 and v["haze"] == 0.0


@pytest.mark.parametrize("key", list(ANGLES))
def test_narrow_ward_lobe_reads_rho_s_cos_theta(key):
    """Ward's normalisation 1/sqrt(cos_i cos_o): a lobe much narrower than the receptor
    reflects rho_s cos(theta) into it (int exp(-tan^2 th_h / a^2) dw_o = 4 cos(theta) pi a^2
    near the mirror direction), so GU = 100 rho_s cos(theta) / F_glass(theta)."""
    th = ANGLES[key]
    p = WardParams(0.0, 0.05, 1e-3, 1e-3, 0.0)
    expected = 100 * p.rho_s * math.cos(math.radians(th)) / fresnel_angle_form(th, 1.567)
    assert G.gloss_from_ward(p)["spread"][key]["models"]["ward"] == pytest.approx(expected, rel=0.01)


def test_gu20_grows_as_the_lobe_narrows_and_is_linear_in_rho_s():
    gu = [G.gloss_from_ward(WardParams(0.0, 0.05, a, a, 0.0))["gu20"] for a in (0.3, 0.1, 0.03, 0.01, 0.003)]
    assert all(b > a for a, b in zip(gu, gu[1:])), gu
    a1 = G.gloss_from_ward(WardParams(0.0, 0.02, 0.05, 0.03, 1.0))
    a2 = G.gloss_from_ward(WardParams(0.0, 0.04, 0.05, 0.03, 1.0))
    for k in ("gu20", "gu60", "gu85"):
        assert a2[k] == pytest.approx(2 * a1[k], rel=1e-9)
    # the diffuse term adds what a Lambertian surface reads
    a3 = G.gloss_from_ward(WardParams(0.4, 0.02, 0.05, 0.03, 1.0))
    lam = G.gloss_units(G.GLOSS_GEOMETRIES["gu20"], lambda a: np.full(a["theta_in"].shape, 0.4 / math.pi))
    assert a3["gu20"] - a1["gu20"] == pytest.approx(lam, rel=1e-6)


def test_doi_high_for_a_narrow_lobe_low_for_a_broad_one():
    # alpha 2e-4: at the 0.3 deg receptor's nearest edge (0.15 deg from the source image,
    # theta_h >= 1.3e-3 rad) the lobe is exp(-42) of its peak
    assert G.gloss_from_ward(WardParams(0.0, 0.05, 2e-4, 2e-4, 0.0))["doi"] > 99.9
    # alpha 0.2: the lobe changes by < 1e-3 over 0.3 deg; only cos(theta_o) changes
    assert G.gloss_from_ward(WardParams(0.0, 0.05, 0.2, 0.2, 0.0))["doi"] < 2.0
    doi = [G.gloss_from_ward(WardParams(0.0, 0.05, a, a, 0.0))["doi"] for a in (3e-4, 1e-3, 3e-3, 1e-2, 3e-2)]
    assert all(b < a for a, b in zip(doi, doi[1:])), doi
    haze = [G.gloss_from_ward(WardParams(0.0, 0.05, a, a, 0.0))["haze"] for a in (3e-3, 1e-2, 3e-2, 0.1)]
    assert all(b > a for a, b in zip(haze, haze[1:])), haze


def test_result_contract_and_spread():
    p = WardParams(0.0518, 0.0069, 0.0595, 0.034, 2.47)      # thesis Table 9.1, sample 2/6
    t = time.perf_counter()
    r = G.gloss_from_ward(p)
    dt = time.perf_counter() - t
    for k in ("gu20", "gu60", "gu85", "haze", "doi"):
        assert isinstance(r[k], float) and math.isfinite(r[k])
        s = r["spread"][k]
        assert s["value"] == r[k] == s["models"]["ward"]
        assert s["min"] <= s["value"] <= s["max"] and set(s["models"]) == set(G.MODELS)
    assert r["spread"]["gu20"]["extrapolated"] is False
    assert r["spread"]["gu60"]["extrapolated"] and r["spread"]["gu85"]["extrapolated"]
    # where the rig sees the lobe (theta_d = 20 deg) the candidate models agree within a few %;
    # at 85 deg they differ by far more (Fresnel and Ward's normalisation are not identifiable)
    s20, s85 = r["spread"]["gu20"], r["spread"]["gu85"]
    assert s20["max"] / s20["min"] < 1.05
    assert s85["max"] / s85["min"] > 3
    assert "1.567" in r["assumptions"] and "extrapolat" in r["assumptions"]
    assert r["detail"]["ggx"]["rel_rms"] < 0.2
    json.dumps(r, allow_nan=False)
    assert dt < 1.0       # ~0.15 s on one core; generous for a shared machine
    # a dict works as well as WardParams
    assert G.gloss_from_ward(p.as_dict())["gu20"] == r["gu20"]


def test_bad_input():
    with pytest.raises(InputError):
        G.gloss_from_ward({"rho_d": 0.1})
    with pytest.raises(InputError):
        G.gloss_from_ward("ward:rho_d=0.1")
    with pytest.raises(InputError):
        G.gloss_from_ward(WardParams(0.1, 0.1, 0.1, 0.1), n_material=0.9)
    black = G.gloss_from_ward(WardParams(0.0, 0.0, 0.1, 0.1))
    assert black["gu20"] == 0.0 and black["haze"] is None and black["doi"] is None
    json.dumps(black, allow_nan=False)


def test_rig_theta_d_range_constants():
    from glossrig.core.extraction.cylinder import nominal_samples
    from glossrig.core.rig import default_rig_path, load_rig

    rig = load_rig(default_rig_path())
    td = np.degrees(nominal_samples(rig, rig.select_leds("middle"), [-45, 0, 45, 90], 0.025)["theta_d"])
    lo, hi = G.RIG_THETA_D_RANGE_DEG
    assert td.min() == pytest.approx(lo, abs=0.5) and td.max() == pytest.approx(hi, abs=0.5)
    assert td.mean() == pytest.approx(G.RIG_THETA_D_MEAN_DEG, abs=0.5)


def test_fit_json_has_the_gloss_keys(tmp_path):
    from glossrig.core.extraction.cylinder import nominal_samples
    from glossrig.core.fitting.export import write_fit_json
    from glossrig.core.fitting.fit import fit_samples
    from glossrig.core.rig import default_rig_path, load_rig
    from glossrig.core.samples import ward_samples

    truth = WardParams(0.0518, 0.0069, 0.0595, 0.034, 2.47)
    rig = load_rig(default_rig_path())
    geo = nominal_samples(rig, rig.select_leds("middle"), [-45, 0, 45, 90], 0.025)
    df = ward_samples(geo, truth, noise=0.02, seed=3)
    fit = fit_samples(df, channels=["luminance"])
    path = write_fit_json(fit, tmp_path / "fit.json")
    js = json.loads(path.read_text())
    gl = js["luminance"]["gloss"]
    for k in ("gu20", "gu60", "gu85", "haze", "doi"):
        assert isinstance(gl[k], float)
    assert gl["spread"]["gu85"]["extrapolated"] is True and "assumptions" in gl
    # the fit recovers the truth's 20 deg gloss (the fit's lobe is within a few % of the truth's)
    assert gl["gu20"] == pytest.approx(G.gloss_from_ward(truth)["gu20"], rel=0.05)
