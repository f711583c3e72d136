"""Exports of a fitted material (issue 17), each reopened by the tool that reads it.

Samples: core.ward (or the stock model's numpy formula) evaluated at the angles the
thesis rig measures (core.cylinder.nominal_samples, middle LEDs, four rotations as in
thesis 6.2) with 3 % multiplicative noise; the fit is core.fit's. Mitsuba renders
are 16 x 16 px.
"""
from __future__ import annotations

import functools
import json
import math
import re
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from glossrig.core.extraction.cylinder import nominal_samples
from glossrig.core.errors import InputError
from glossrig.core.fitting.export import mitsuba_material, read_fit_json, read_fit_provenance, write_fit_json
from glossrig.core.fitting.fit import _residual_stats, fit_samples, peak_weight
from glossrig.core.fitting.material_export import (BRDF_FILE, MATERIAL_XML, SAMPLES_CSV, SAMPLES_CSV_SIDECAR, STOCK_JSON,
                                           STOCK_PLUGINS, STOCK_XML, read_samples_csv, write_exports)
from glossrig.core.rig import default_rig_path, load_rig
from glossrig.core.samples import read_samples, ward_samples, write_samples
from glossrig.core.models.stock_bsdf import StockParams, directions, fit_stock, stock_brdf
from glossrig.core.models.ward import WardParams, ward_from_angles, ward_local

ROOT = Path(__file__).resolve().parent.parent
TRUTH = WardParams(rho_d=0.3, rho_s=0.08, alpha_x=0.12, alpha_y=0.05, lobe_rotation=0.6)
COLOUR = (1.0, 0.8, 0.6)
NOISE = 0.03


@functools.cache
def geometry() -> pd.DataFrame:
    rig = load_rig(default_rig_path())
    return nominal_samples(rig, rig.select_leds("middle"), [-45, 0, 45, 90], 0.03)


def with_values(geo, f_lum_per_channel, seed=1):
    """A samples table whose r, g, b are ``f(channel) * (1 + NOISE N(0, 1))``."""
    rng = np.random.default_rng(seed)
    df = geo.copy()
    for c in ("r", "g", "b"):
        f = f_lum_per_channel(c)
        df[c] = f * (1 + NOISE * rng.standard_normal(f.size))
    df["weight"] = 1.0
    return df


def weights(df) -> np.ndarray:
    """The Ward fit's weights (eq. 4.82, 'mirror' reading) times sqrt(weight column)."""
    return peak_weight(df["theta_in"].to_numpy(), df["phi_in"].to_numpy(), df["theta_out"].to_numpy(),
                       df["phi_out"].to_numpy()) * np.sqrt(df["weight"].to_numpy())


def lum(df) -> np.ndarray:
    return 0.2126 * df["r"].to_numpy() + 0.7152 * df["g"].to_numpy() + 0.0722 * df["b"].to_numpy()


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A Ward material fitted and exported the way ``glossrig measure`` does it: the samples
    written to and read back from Parquet, the fit saved as fit.json, the exports made
    from the fit.json path."""
    d = tmp_path_factory.mktemp("exports")
    table = ward_samples(geometry(), TRUTH, noise=NOISE, seed=1, colour=COLOUR)
    write_samples(table, d / "samples.parquet")
    df = read_samples(d / "samples.parquet")
    mf = fit_samples(df, channels=["luminance"])
    write_fit_json(mf, d / "fit.json", provenance={"tool": "test"})
    paths = write_exports(d / "fit.json", df, d / "exports")
    return {"dir": d, "out": d / "exports", "df": df, "fit": mf, "paths": paths}


# ----------------------------------------------------------------------------
# fit.json reader
# ----------------------------------------------------------------------------

def test_read_fit_json_round_trips_the_file(exported):
    doc = json.loads((exported["dir"] / "fit.json").read_text())
    back = read_fit_json(exported["dir"] / "fit.json")
    assert json.loads(json.dumps(back.to_json())) == {k: v for k, v in doc.items() if k != "provenance"}
    assert back.fits["luminance"].params == exported["fit"].fits["luminance"].params
    assert read_fit_provenance(exported["dir"] / "fit.json") == {"tool": "test"}


@pytest.mark.parametrize("text, match", [
    ("{not json", "is not readable JSON"),
    ('{"format": "other/1"}', "not a glossrig fit file"),
    ('{"format": "glossrig-fit/1", "luminance": {"rho_d": 1}}', "missing key"),
])
def test_read_fit_json_names_the_file(tmp_path, text, match):
    p = tmp_path / "fit.json"
    p.write_text(text)
    with pytest.raises(InputError, match=match) as e:
        read_fit_json(p)
    assert "fit.json" in str(e.value)
    with pytest.raises(InputError, match="not found"):
        read_fit_json(tmp_path / "missing.json")


def test_write_exports_writes_every_file(exported, tmp_path):
    names = [p.name for p in exported["paths"]]
    assert names == [MATERIAL_XML, STOCK_XML, STOCK_JSON, BRDF_FILE, SAMPLES_CSV, SAMPLES_CSV_SIDECAR]
    assert all(p.is_file() and p.parent == exported["out"] for p in exported["paths"])
    with pytest.raises(InputError, match="does not exist"):
        write_exports(exported["fit"], exported["df"], tmp_path / "no" / "exports")


# ----------------------------------------------------------------------------
# Mitsuba: material.xml (project plugin) and material_stock.xml (stock plugins)
# ----------------------------------------------------------------------------

SCENE = """<scene version="3.0.0">
    {material}
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <float name="fov" value="35"/>
        <sampler type="independent"><integer name="sample_count" value="16"/></sampler>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/>
            <rfilter type="box"/></film>
    </sensor>
    <shape type="sphere">{ref}</shape>
    <emitter type="point"><point name="position" x="2" y="2" z="3"/><rgb name="intensity" value="20"/></emitter>
</scene>"""

RENDER = r"""
import json, sys
import numpy as np
import mitsuba as mi

def render(mi, scene_xml):
    return np.array(mi.render(mi.load_string(scene_xml), seed=7))

def dict_scene(mi, material):
    # The same scene as SCENE, the material given as a mi.load_dict dict.
    return mi.load_dict({"type": "scene", "integrator": {"type": "path", "max_depth": 2},
        "sensor": {"type": "perspective", "fov": 35,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": 16},
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "sphere": {"type": "sphere", "bsdf": material},
        "light": {"type": "point", "position": [2, 2, 3], "intensity": {"type": "rgb", "value": 20}}})
"""


def scene_with(path: Path, id: str) -> str:
    return SCENE.format(material=f'<include filename="{path}"/>', ref=f'<ref id="{id}"/>')


@pytest.mark.mitsuba
def test_material_xml_renders_as_the_mitsuba_material_dict(exported):
    """Mitsuba loads material.xml (glossrig_ward registered) and renders, with the same
    seed, the image of the dict core.export.mitsuba_material gives."""
    from glossrig.twin.mitsuba_env import mitsuba

    mi = mitsuba()
    ns: dict = {}
    exec(RENDER, ns)
    img_xml = ns["render"](mi, scene_with(exported["out"] / MATERIAL_XML, "material"))
    img_dict = np.array(mi.render(ns["dict_scene"](mi, mitsuba_material(exported["fit"])), seed=7))
    assert img_xml.mean() > 1e-3, "blank render"
    np.testing.assert_allclose(img_xml, img_dict, rtol=1e-5, atol=1e-7)
    # the XML holds exactly the dict's parameters
    bsdf = ET.parse(exported["out"] / MATERIAL_XML).getroot().find("bsdf")
    assert bsdf.get("type") == "glossrig_ward" and bsdf.get("id") == "material"
    m = mitsuba_material(exported["fit"])
    for el in bsdf:
        want = m[el.get("name")]
        got = [float(x) for x in el.get("value").split(",")]
        assert got == (want["value"] if isinstance(want, dict) else [want]), el.get("name")


@pytest.mark.mitsuba
def test_material_stock_xml_loads_with_stock_plugins_only(exported):
    """In a fresh process with no glossrig plugin registered (material.xml fails to load
    there), material_stock.xml loads and renders a non-blank image, the same as the dict
    material_stock.json records."""
    out = exported["out"]
    types = {el.get("type") for el in ET.parse(out / STOCK_XML).getroot().iter() if el.get("type")}
    assert types <= set(STOCK_PLUGINS), types
    script = RENDER + f"""
from glossrig.twin.mitsuba_env import choose_variant
mi.set_variant(choose_variant())
SCENE = {SCENE!r}
try:
    mi.load_string(SCENE.format(material='<include filename="{out / MATERIAL_XML}"/>', ref='<ref id="material"/>'))
    project_loads = True
except Exception:
    project_loads = False
img = render(mi, SCENE.format(material='<include filename="{out / STOCK_XML}"/>', ref='<ref id="material_stock"/>'))
ref = np.array(mi.render(dict_scene(mi, json.load(open("{out / STOCK_JSON}"))["mitsuba"]), seed=7))
print(json.dumps({{"project_loads": project_loads, "mean": float(img.mean()), "finite": bool(np.isfinite(img).all()),
                  "max_diff": float(np.abs(img - ref).max())}}))
"""
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    res = json.loads(r.stdout.strip().splitlines()[-1])
    assert not res["project_loads"], "glossrig_ward was registered in the stock process"
    assert res["finite"] and res["mean"] > 1e-3, res
    assert res["max_diff"] <= 1e-5, res


@pytest.mark.mitsuba
def test_stock_numpy_model_is_mitsubas_blendbsdf(exported):
    """core.stock_bsdf's formula against Mitsuba's own eval of the exported stock material
    (material_stock.json's dict), per channel, at random directions (lobe rotation 0: the
    stock plugin's alpha_u runs along s)."""
    import drjit as dr

    from glossrig.twin.mitsuba_env import mitsuba

    mi = mitsuba()
    doc = json.loads((exported["out"] / STOCK_JSON).read_text())
    m = doc["mitsuba"]
    bsdf = mi.load_dict(m)
    rng = np.random.default_rng(3)
    v = rng.normal(size=(2, 3000, 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.05
    wi, wo = v / np.linalg.norm(v, axis=-1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, len(wi))
    si.wi = mi.Vector3f(*wi.T)
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    got = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo.T)))
    got = got if got.shape[0] == len(wi) else got.T
    w, c1 = m["weight"], m["bsdf_1"]
    for ch in range(3):
        rd = (1 - w) * m["bsdf_0"]["reflectance"]["value"][ch]
        rs = w * c1["specular_reflectance"]["value"][ch]
        assert rd == pytest.approx(doc["rgb"]["rho_d"][ch], rel=1e-12)
        assert rs == pytest.approx(doc["rgb"]["rho_s"][ch], rel=1e-12)
        p = StockParams(rd, rs, c1["alpha_u"], c1["alpha_v"], 0.0, c1["distribution"])
        np.testing.assert_allclose(got[:, ch], stock_brdf(wi, wo, p) * wo[:, 2], rtol=2e-4, atol=1e-7)


def test_stock_rotation_convention_matches_ward():
    """The stock model's rotation turns the lobe as Ward's lobe_rotation does (eq. 4.80):
    evaluating with rotation r equals evaluating with 0 in coordinates turned by r."""
    rng = np.random.default_rng(4)
    v = rng.normal(size=(2, 500, 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.05
    wi, wo = v / np.linalg.norm(v, axis=-1, keepdims=True)
    r = 0.7
    R = np.array([[math.cos(r), -math.sin(r), 0], [math.sin(r), math.cos(r), 0], [0, 0, 1.0]])
    p = StockParams(0.2, 0.1, 0.15, 0.04, r)
    p0 = StockParams(0.2, 0.1, 0.15, 0.04, 0.0)
    np.testing.assert_allclose(stock_brdf(wi, wo, p), stock_brdf(wi @ R.T, wo @ R.T, p0), rtol=1e-12)
    w = WardParams(0.2, 0.1, 0.15, 0.04, r)
    w0 = WardParams(0.2, 0.1, 0.15, 0.04, 0.0)
    np.testing.assert_allclose(ward_local(wi, wo, w), ward_local(wi @ R.T, wo @ R.T, w0), rtol=1e-12)


# ----------------------------------------------------------------------------
# The stock fit
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("kind", ["beckmann", "ggx"])
def test_stock_fit_recovers_a_stock_truth(kind):
    """Samples of a known stock material: the fit finds its distribution and parameters,
    and its weighted residual is at most the truth's own (the noise's: the truth is in
    the fitted family and the fit minimises that objective), hence at most the Ward fit's
    (which is at least the noise's less its p/n overfit)."""
    truth = StockParams(rho_d=0.25, rho_s=0.07, alpha_u=0.15, alpha_v=0.06, rotation=0.5, distribution=kind)
    geo = geometry()
    wi, wo = directions(geo["theta_in"], geo["phi_in"]), directions(geo["theta_out"], geo["phi_out"])
    k = dict(zip("rgb", COLOUR))
    df = with_values(geo, lambda c: stock_brdf(wi, wo, StockParams(truth.rho_d * k[c], truth.rho_s * k[c],
                                                                     truth.alpha_u, truth.alpha_v, truth.rotation,
                                                                     kind)))
    ward = fit_samples(df, channels=["luminance"]).fits["luminance"]
    s = fit_stock(df, ward.params)
    q = s.params
    lum_k = 0.2126 * k["r"] + 0.7152 * k["g"] + 0.0722 * k["b"]     # luminance of the colour
    assert q.distribution == kind
    assert q.rho_d == pytest.approx(truth.rho_d * lum_k, rel=0.03)
    assert q.rho_s == pytest.approx(truth.rho_s * lum_k, rel=0.05)
    assert q.alpha_u == pytest.approx(truth.alpha_u, rel=0.05)
    assert q.alpha_v == pytest.approx(truth.alpha_v, rel=0.05)
    assert abs((q.rotation - truth.rotation + math.pi / 2) % math.pi - math.pi / 2) < math.radians(2)
    for ch, kc in zip(range(3), COLOUR):
        assert s.rgb["rho_d"][ch] == pytest.approx(truth.rho_d * kc, rel=0.03)
    f_truth = stock_brdf(wi, wo, StockParams(truth.rho_d * lum_k, truth.rho_s * lum_k, truth.alpha_u,
                                             truth.alpha_v, truth.rotation, kind))
    noise_wrmse = _residual_stats(lum(df), f_truth, weights(df), None, False)["weighted_rmse"]
    assert s.residuals["weighted_rmse"] <= noise_wrmse * (1 + 1e-3)
    n = len(df)
    assert s.residuals["weighted_rmse"] <= s.ward_residuals["weighted_rmse"] * (1 + 1e-3) / (1 - 5 / n)
    assert s.ward_residuals["weighted_rmse"] == pytest.approx(ward.residuals["weighted_rmse"], rel=1e-9)


def test_stock_fit_of_a_ward_material_is_bounded(exported):
    """Samples of a Ward material (the exported one): the stock fit is fitted, not copied -
    its weighted residual is below that of the stock model with Ward's parameters copied
    (same lobe, rho's and rotation, Beckmann), which by the triangle inequality is at most
    the noise's residual plus the two models' difference at those parameters; the bound
    derived so from the truth is checked, and the stock residual against the Ward fit's
    is reported by material_stock.json."""
    df = exported["df"]
    doc = json.loads((exported["out"] / STOCK_JSON).read_text())
    wi, wo = directions(df["theta_in"], df["phi_in"]), directions(df["theta_out"], df["phi_out"])
    lum_k = 0.2126 * COLOUR[0] + 0.7152 * COLOUR[1] + 0.0722 * COLOUR[2]
    t = WardParams(TRUTH.rho_d * lum_k, TRUTH.rho_s * lum_k, TRUTH.alpha_x, TRUTH.alpha_y, TRUTH.lobe_rotation)
    y, W = lum(df), weights(df)
    f_ward = ward_from_angles(df["theta_in"], df["theta_out"], df["theta_h"], df["phi_h"], t)
    f_copy = stock_brdf(wi, wo, StockParams(t.rho_d, t.rho_s, t.alpha_x, t.alpha_y, t.lobe_rotation))

    def wrmse(a, b):
        return _residual_stats(a, b, W, None, False)["weighted_rmse"]

    copied = wrmse(y, f_copy)
    bound = wrmse(y, f_ward) + wrmse(f_ward, f_copy)
    assert copied <= bound * (1 + 1e-12)
    stock, ward = doc["residuals"]["weighted_rmse"], doc["ward_residuals"]["weighted_rmse"]
    assert stock < copied
    assert stock <= bound
    assert ward == pytest.approx(exported["fit"].fits["luminance"].residuals["weighted_rmse"], rel=1e-9)
    assert doc["params"]["alpha_u"] != t.alpha_x and doc["params"]["rho_s"] != t.rho_s


# ----------------------------------------------------------------------------
# BRDF Explorer
# ----------------------------------------------------------------------------

def parse_brdf(text: str) -> dict:
    """BRDF Explorer's reader (wdas/brdf BRDFBase::loadBRDF): first line ``analytic``;
    blank and ``#`` lines skipped; ``::begin NAME`` / ``::end NAME`` sections, not nested;
    parameters ``float NAME MIN MAX DEFAULT``, ``color NAME R G B``, ``bool NAME V``."""
    lines = text.splitlines()
    assert lines[0].split()[0] == "analytic"
    params, sections, cur = {}, {}, None
    for ln in lines[1:]:
        t = ln.strip()
        if not t or t.startswith("#"):
            continue
        tok = t.split()
        if tok[0] == "::begin":
            assert cur is None, "nested section"
            cur = tok[1]
            sections[cur] = []
        elif tok[0] == "::end":
            assert tok[1] == cur, f"::end {tok[1]} closes {cur}"
            cur = None
        elif cur == "parameters":
            if tok[0] == "float":
                assert len(tok) == 5
                params[tok[1]] = ("float", *map(float, tok[2:]))
            elif tok[0] == "color":
                assert len(tok) == 5
                params[tok[1]] = ("color", *map(float, tok[2:]))
            elif tok[0] == "bool":
                params[tok[1]] = ("bool", int(tok[2]))
            else:
                raise AssertionError(f"unknown parameter type in {t!r}")
        else:
            sections[cur].append(ln)
    assert cur is None, "unterminated section"
    return {"params": params, "shader": "\n".join(sections.get("shader", []))}


def glsl_to_python(shader: str, params: dict):
    """The BRDF function of the shader as Python, for the tiny GLSL subset it uses
    (declarations ``float|vec3 NAME = EXPR;``, ``if (COND) return EXPR;``, ``return EXPR;``)."""
    m = re.search(r"vec3 BRDF\(\s*vec3 L,\s*vec3 V,\s*vec3 N,\s*vec3 X,\s*vec3 Y\s*\)\s*\{(.*)\}", shader, re.S)
    assert m, "no vec3 BRDF(vec3 L, vec3 V, vec3 N, vec3 X, vec3 Y)"
    py = ["def BRDF(L, V, N, X, Y):"]
    for stmt in m.group(1).split(";"):
        stmt = " ".join(stmt.split())
        if not stmt:
            continue
        if d := re.fullmatch(r"(?:float|vec3) (\w+) = (.+)", stmt):
            py.append(f"    {d[1]} = {d[2]}")
        elif d := re.fullmatch(r"if \((.+)\) return (.+)", stmt):
            py.append(f"    if {d[1].replace('||', ' or ').replace('&&', ' and ')}: return {d[2]}")
        elif d := re.fullmatch(r"return (.+)", stmt):
            py.append(f"    return {d[1]}")
        else:
            raise AssertionError(f"statement outside the tested GLSL subset: {stmt!r}")
    ns = {"dot": lambda a, b: float(np.dot(a, b)), "normalize": lambda v: v / np.linalg.norm(v),
          "vec3": lambda *a: np.array(a * 3 if len(a) == 1 else a, float),
          "cos": math.cos, "sin": math.sin, "exp": math.exp, "sqrt": math.sqrt}
    for k, v in params.items():
        ns[k] = np.array(v[1:], float) if v[0] == "color" else v[3]
    exec("\n".join(py), ns)
    return ns["BRDF"]


def test_brdf_file_parses_with_the_fitted_defaults_and_wards_formula(exported):
    parsed = parse_brdf((exported["out"] / BRDF_FILE).read_text())
    p = parsed["params"]
    m = mitsuba_material(exported["fit"])
    for k in ("alpha_x", "alpha_y", "lobe_rotation"):
        kind, lo, hi, default = p[k]
        assert kind == "float" and lo <= default <= hi
        assert default == m[k]
    for k in ("rho_d", "rho_s"):
        assert p[k][0] == "color" and list(p[k][1:]) == m[k]["value"]
    assert "vec3 BRDF(" in parsed["shader"]
    brdf = glsl_to_python(parsed["shader"], p)
    # core.ward per channel, at random directions, in a random tangent frame
    rng = np.random.default_rng(5)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    X, Y, N = q[:, 0], q[:, 1], np.cross(q[:, 0], q[:, 1])
    v = rng.normal(size=(2, 300, 3))
    v[..., 2] = np.abs(v[..., 2]) + 0.05
    wi, wo = v / np.linalg.norm(v, axis=-1, keepdims=True)
    frame = np.stack([X, Y, N], axis=1)               # local -> world
    got = np.array([brdf(frame @ a, frame @ b, N, X, Y) for a, b in zip(wi, wo)])
    for ch in range(3):
        w = WardParams(m["rho_d"]["value"][ch], m["rho_s"]["value"][ch], m["alpha_x"], m["alpha_y"],
                       m["lobe_rotation"])
        np.testing.assert_allclose(got[:, ch], ward_local(wi, wo, w), rtol=1e-10)
    assert np.all(brdf(-N, N, N, X, Y) == 0)           # light below the surface


@pytest.mark.skipif(shutil.which("glslangValidator") is None, reason="glslangValidator (glslang-tools) not installed")
def test_brdf_shader_compiles_as_glsl_410(exported, tmp_path):
    """The shader inside BRDF Explorer's fragment template (``#version 410``, one uniform
    per parameter, as BRDFBase::loadShaderFromFile inserts them) compiles."""
    parsed = parse_brdf((exported["out"] / BRDF_FILE).read_text())
    uniforms = "\n".join(f"uniform {'float' if v[0] == 'float' else 'vec3' if v[0] == 'color' else 'bool'} {k};"
                         for k, v in parsed["params"].items())
    src = (f"#version 410\nout vec4 fragColor;\n{uniforms}\n{parsed['shader']}\n"
           "void main(void) { fragColor = vec4(BRDF(vec3(0, 0, 1), vec3(0, 0.6, 0.8), vec3(0, 0, 1), "
           "vec3(1, 0, 0), vec3(0, 1, 0)), 1.0); }\n")
    f = tmp_path / "brdf.frag"
    f.write_text(src)
    r = subprocess.run(["glslangValidator", str(f)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stdout + r.stderr


# ----------------------------------------------------------------------------
# samples.csv
# ----------------------------------------------------------------------------

def test_samples_csv_reads_back_as_the_parquet_table(exported):
    parquet = read_samples(exported["dir"] / "samples.parquet")
    plain = pd.read_csv(exported["out"] / SAMPLES_CSV)
    pd.testing.assert_frame_equal(plain, parquet, check_dtype=False, check_exact=True)
    back = read_samples_csv(exported["out"] / SAMPLES_CSV)
    pd.testing.assert_frame_equal(back, parquet, check_exact=True)
    side = json.loads((exported["out"] / SAMPLES_CSV_SIDECAR).read_text())
    units = {c["name"]: c["unit"] for c in side["columns"]}
    assert units["theta_in"] == "radian" and units["r"] == "1/sr" and units["rotation"] == "degree"


def test_exports_of_a_fit_without_a_luminance_channel(exported, tmp_path):
    """A fit of colour channels only: the Ward reference is the shared lobe with the
    luminance of its RGB albedos (eq. 4.79 is linear in them), as good as the luminance fit."""
    from dataclasses import replace

    mf = read_fit_json(exported["dir"] / "fit.json")
    mf.fits = {"g": replace(mf.fits["luminance"], channel="g")}
    paths = write_exports(mf, exported["df"], tmp_path / "exports")
    doc = json.loads(paths[2].read_text())
    lum_fit = exported["fit"].fits["luminance"].residuals["weighted_rmse"]
    assert doc["ward_residuals"]["weighted_rmse"] == pytest.approx(lum_fit, rel=0.02)
