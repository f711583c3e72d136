"""``glossrig fabricate``: inputs, the reproduction model's ETN, outputs and refusals (issue 6)."""
from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from PIL import Image

from glossrig.cli.main import main
from glossrig.core.errors import InputError
from glossrig.core.reproduction.model import ETN, KIND as MODEL_KIND, load_etn
from glossrig.core.fabrication.inputs import load_coverage_image, resample
from glossrig.core.fabrication.pipeline import read_summary

FILES = {"halftone.png", "toolpath.gcode", "preview.svg", "preview.png", "preview_render.png", "summary.json"}


def _grey(tmp_path, value, shape=(90, 120), name="grey.png"):
    p = tmp_path / name
    Image.fromarray(np.full(shape, value, np.uint8)).save(p)
    return p


def _model(tmp_path, gamma, form=None, kind=MODEL_KIND, name="model.json"):
    etn = {"gamma": gamma}
    if form:
        etn["form"] = form
    p = tmp_path / name
    p.write_text(json.dumps({"kind": kind, "etn": etn, "bases": {"b1": {}, "b2": {}}}))
    return p


def _run(capsys, *argv):
    rc = main(["fabricate", *map(str, argv)])
    out = capsys.readouterr()
    return rc, out.out, out.err


def test_writes_the_five_files_and_a_constant_grey_hits_its_nearest_level(tmp_path, capsys):
    value = 77                                            # 77/255 = 0.302 -> level 13/42
    out = tmp_path / "out"
    rc, stdout, _ = _run(capsys, _grey(tmp_path, value), "--width-mm", 9.5, "--out", out)
    assert rc == 0 and set(p.name for p in out.iterdir()) == FILES
    s = read_summary(out)
    ht = np.asarray(Image.open(out / "halftone.png"))
    assert ht.shape == tuple(s["grid"]) and set(np.unique(ht)) <= {0, 255}
    k = round(value / 255 * 42)
    assert k == 13 and (ht == 255).sum() * 42 == k * ht.size          # exactly 13/42
    assert s["coverage"]["achieved"] == pytest.approx(13 / 42, abs=0)
    assert s["segment_count"] > 0 and s["path_length_mm"] > s["cut_length_mm"] > 0
    assert s["estimated_time_s"] > s["cut_length_mm"] / 20.0
    assert s["machine_frame"]["inside_bed"] and s["machine_frame"]["inside_print_bbox"]
    assert s["print_size_mm"][0] == pytest.approx(9.5, abs=0.37)
    assert "estimated time" in stdout
    svg = (out / "preview.svg").read_text()
    assert svg.startswith("<?xml") and svg.count("V") >= s["segment_count"]


def test_svg_places_the_image_where_the_layout_puts_the_print(tmp_path, capsys):
    from glossrig.core.fabrication.layout import Layout

    out = tmp_path / "o"
    assert _run(capsys, _grey(tmp_path, 128), "--width-mm", 5, "--out", out)[0] == 0
    s = read_summary(out)
    layout = Layout.from_json(s["layout"])
    m = [float(v) for v in re.search(r'matrix\(([^)]*)\)', (out / "preview.svg").read_text()).group(1).split()]
    X = np.array([0.0, layout.cols, 0.0, layout.cols])
    Y = np.array([0.0, 0.0, layout.rows, layout.rows])
    sx, sy = m[0] * X + m[2] * Y + m[4], m[1] * X + m[3] * Y + m[5]
    mx, my = layout.image_to_machine(X, Y)
    assert np.allclose(sx, mx, atol=1e-6) and np.allclose(sy, my, atol=1e-6)


def test_rml_output(tmp_path, capsys):
    out = tmp_path / "r"
    rc, _, _ = _run(capsys, _grey(tmp_path, 200), "--width-mm", 6, "--out", out, "--machine", "rml")
    assert rc == 0 and (out / "toolpath.rml").exists() and not (out / "toolpath.gcode").exists()
    text = (out / "toolpath.rml").read_text()
    assert "!PZ-2,50;" in text and "!MC0;" in text and "VS20;" in text


def test_model_applies_the_etn_before_halftoning(tmp_path, capsys):
    gamma = [0.9, 6.0, 1.0, 0.05]
    ce = 153 / 255
    etn = ETN(tuple(gamma), form="eq6.7")
    nominal = gamma[0] / ((gamma[2] + math.exp(-gamma[1] * ce)) + gamma[3])       # eq. 6.7 as printed
    assert etn(np.array(ce)) == pytest.approx(nominal)
    out = tmp_path / "m"
    rc, _, _ = _run(capsys, _grey(tmp_path, 153), "--width-mm", 7, "--out", out,
                    "--model", _model(tmp_path, gamma, form="eq6.7"))
    assert rc == 0
    s = read_summary(out)
    k = round(nominal * 42)
    assert k != round(ce * 42)                                                 # the ETN changed the level
    assert s["coverage"]["achieved"] == pytest.approx(k / 42, abs=0)
    assert s["etn"]["gamma"] == gamma


# the offset form as the project's reproduction model (core/reproduction/model.py) writes it
REPRODUCTION_ETN_FORM = "nominal_b2 = min(1, max(0, gamma[0] / (gamma[2] + exp(-gamma[1] * effective_b2)) + gamma[3]))"


def test_etn_forms_and_contract(tmp_path):
    g = [0.9, 4.0, 1.0, 0.1]
    printed = load_etn(_model(tmp_path, g, form="eq6.7"))
    x = np.linspace(0, 1, 5)
    assert np.allclose(printed(x), 0.9 / (1.0 + np.exp(-4 * x) + 0.1))
    for i, form in enumerate(("eq6.7-offset", None, REPRODUCTION_ETN_FORM)):
        offset = load_etn(_model(tmp_path, g, form=form, name=f"m{i}.json"))
        assert offset.form == "eq6.7-offset"
        assert np.allclose(offset(x), 0.9 / (1.0 + np.exp(-4 * x)) + 0.1)
    p = tmp_path / "m3.json"
    p.write_text(json.dumps({"kind": MODEL_KIND, "etn": {"gamma1": 1, "gamma2": -1, "gamma3": 1, "gamma4": 0}}))
    assert load_etn(p).gamma == (1.0, -1.0, 1.0, 0.0)                          # thesis table 6.5's initial point


@pytest.mark.parametrize("content, words", [
    ("{not json", "model file is not readable JSON"),
    (json.dumps({"kind": "glossrig.fabrication_summary"}), "expected a reproduction model"),
    (json.dumps([1, 2]), "expected a reproduction model"),
    (json.dumps({"kind": MODEL_KIND}), "lacks the \"etn\""),
    (json.dumps({"kind": MODEL_KIND, "etn": {"gamma": [1, 2, 3]}}), "four finite numbers"),
    (json.dumps({"kind": MODEL_KIND, "etn": {"gamma": [1, 2, "x", 4]}}), "four finite numbers"),
    (json.dumps({"kind": MODEL_KIND, "etn": {"gamma": [1, 2, 3, 4], "form": "cubic"}}), "form"),
    (json.dumps({"kind": MODEL_KIND, "etn": {"gamma": [1, 1, -0.6, 0]}}), "pole"),   # 1/(e^-x - 0.6): pole at 0.51
])
def test_model_file_refusals(tmp_path, capsys, content, words):
    p = tmp_path / "bad.json"
    p.write_text(content)
    with pytest.raises(InputError, match=words) as e:
        load_etn(p)
    assert "bad.json" in str(e.value)
    out = tmp_path / "never"
    rc, _, err = _run(capsys, _grey(tmp_path, 100), "--width-mm", 5, "--out", out, "--model", p)
    assert rc != 0 and "bad.json" in err and not out.exists()


@pytest.mark.parametrize("width, words", [("0", "--width-mm"), ("-3", "--width-mm"), ("nan", "--width-mm"),
                                          ("400", "outside the bed")])
def test_bad_width(tmp_path, capsys, width, words):
    out = tmp_path / "never"
    rc, _, err = _run(capsys, _grey(tmp_path, 100), "--width-mm", width, "--out", out)
    assert rc != 0 and words in err and not out.exists()


def test_bad_images(tmp_path, capsys):
    text = tmp_path / "notes.png"
    text.write_text("this is not an image")
    rgba = tmp_path / "rgba.png"
    arr = np.zeros((10, 10, 4), np.uint8)
    arr[..., 3] = 255
    arr[0, 0, 3] = 10
    Image.fromarray(arr, "RGBA").save(rgba)
    floats = tmp_path / "f.tif"
    Image.fromarray(np.full((8, 8), 2.5, np.float32), "F").save(floats)
    for bad, words in ((text, "not a readable image"), (tmp_path / "missing.png", "not found"),
                       (rgba, "transparent"), (floats, "[0, 1]")):
        rc, _, err = _run(capsys, bad, "--width-mm", 5, "--out", tmp_path / "never")
        assert rc != 0 and bad.name in err and words in err
    assert not (tmp_path / "never").exists()


def test_greyscale_conversion(tmp_path):
    rgb = tmp_path / "rgb.png"
    Image.fromarray(np.full((4, 5, 3), (255, 0, 0), np.uint8)).save(rgb)
    assert load_coverage_image(rgb) == pytest.approx(np.full((4, 5), 76 / 255))   # ITU-R 601-2 luma of red
    deep = tmp_path / "deep.png"
    Image.fromarray(np.full((4, 5), 32768, np.uint16)).save(deep)
    assert load_coverage_image(deep) == pytest.approx(np.full((4, 5), 32768 / 65535))
    ramp = np.linspace(0, 1, 40)[None, :].repeat(30, 0)
    small = resample(ramp, (15, 20))
    assert small.shape == (15, 20) and small.mean() == pytest.approx(ramp.mean(), abs=1e-9)


def test_does_not_overwrite_without_permission(tmp_path, capsys):
    out = tmp_path / "o"
    img = _grey(tmp_path, 60)
    assert _run(capsys, img, "--width-mm", 5, "--out", out)[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    rc, _, err = _run(capsys, _grey(tmp_path, 220, name="other.png"), "--width-mm", 5, "--out", out)
    assert rc != 0 and "--force" in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert _run(capsys, _grey(tmp_path, 220, name="other.png"), "--width-mm", 5, "--out", out, "--force")[0] == 0
    assert (out / "halftone.png").read_bytes() != before["halftone.png"]
