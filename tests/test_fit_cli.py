"""``glossrig fit``: end to end on a small samples table; bad input; Mitsuba export."""
from __future__ import annotations

import json
import math

import numpy as np
import pandas as pd
import pytest

from glossrig.cli.main import main
from glossrig.core.extraction.cylinder import nominal_samples
from glossrig.core.fitting.fit import PARAM_NAMES
from glossrig.core.rig import default_rig_path, load_rig
from glossrig.core.samples import write_samples, ward_samples
from glossrig.core.models.ward import WardParams

from helpers import assert_image_has_content

TRUTH = WardParams(0.0518, 0.0069, 0.0595, 0.034, 2.47)     # thesis Table 9.1, sample 2/6


@pytest.fixture(scope="module")
def samples_path(tmp_path_factory):
    rig = load_rig(default_rig_path())
    geo = nominal_samples(rig, rig.select_leds("middle"), [-45, 0, 45, 90], 0.025)
    df = ward_samples(geo, TRUTH, noise=0.03, seed=2, colour=(1.2, 1.0, 0.7))
    return write_samples(df, tmp_path_factory.mktemp("fitcli") / "samples.parquet")


def test_cli_writes_fit_json_with_every_channel(samples_path, tmp_path, capsys):
    out = tmp_path / "fit.json"
    mat = tmp_path / "material.json"
    assert main(["fit", str(samples_path), "--out", str(out), "--mitsuba", str(mat), "--quiet"]) == 0
    js = json.loads(out.read_text())
    for c, k in (("luminance", 0.2126 * 1.2 + 0.7152 + 0.0722 * 0.7), ("r", 1.2), ("g", 1.0), ("b", 0.7)):
        ch = js[c]
        for name in PARAM_NAMES:
            assert isinstance(ch[name], float)
            assert isinstance(ch[f"{name}_stderr"], float) and ch[f"{name}_stderr"] > 0
        assert ch["alpha_x"] >= ch["alpha_y"] and 0 <= ch["lobe_rotation"] < math.pi
        assert ch["rho_d"] == pytest.approx(TRUTH.rho_d * k, rel=0.03)
        assert ch["alpha_x"] == pytest.approx(TRUTH.alpha_x, rel=0.1)
        assert ch["lobe_rotation"] == pytest.approx(TRUTH.lobe_rotation, abs=math.radians(3))
        assert ch["residuals"]["n"] > 1000 and ch["converged"]
    m = js["mitsuba"]
    assert m["type"] == "glossrig_ward" and m["rho_d"]["type"] == "rgb"
    assert m["rho_d"]["value"][0] == pytest.approx(TRUTH.rho_d * 1.2, rel=0.03)
    assert json.loads(mat.read_text()) == m
    assert "luminance" in capsys.readouterr().out


def test_cli_plots(samples_path, tmp_path):
    plots = tmp_path / "plots"
    out = tmp_path / "fit.json"
    assert main(["fit", str(samples_path), "--out", str(out), "--plots", str(plots), "--channels", "luminance",
                 "--clip", "--weighting", "none", "--quiet"]) == 0
    js = json.loads(out.read_text())
    assert js["options"]["clip"] == 1.0 and js["luminance"]["weighting"] == "none"
    names = sorted(p.name for p in plots.iterdir())
    # figsize width / height (core/fitting/fit_plots.py); rig_slices' grid follows the data
    for kind, aspect in (("lobe_slices", 12 / 4.8), ("rig_slices", None), ("residuals", 12 / 4.8),
                         ("measured_vs_fitted", 6.6 / 5.8)):
        assert f"luminance_{kind}.png" in names
        assert_image_has_content(plots / f"luminance_{kind}.png", aspect=aspect, min_size=(500, 400))
    assert "r" not in js
    import importlib.util

    if importlib.util.find_spec("glossrig.twin.ward_bsdf") is not None:
        assert_image_has_content(plots / "preview_sphere.png", size=(160, 160))    # render_preview's default size


@pytest.mark.mitsuba
def test_exported_material_loads_and_renders_through_the_twin(samples_path, tmp_path):
    pytest.importorskip("glossrig.twin.ward_bsdf")
    from PIL import Image

    from glossrig.core.fitting.export import mitsuba_from_params
    from glossrig.twin.material_renders import render_preview
    from glossrig.twin.mitsuba_env import mitsuba

    mi = mitsuba()
    mat = mitsuba_from_params(TRUTH, [0.06, 0.05, 0.035], [0.008, 0.007, 0.005])
    bsdf = mi.load_dict(mat)
    params = mi.traverse(bsdf)
    assert float(params["alpha_x"][0]) == pytest.approx(TRUTH.alpha_x)
    assert float(params["lobe_rotation"][0]) == pytest.approx(TRUTH.lobe_rotation)
    assert list(np.ravel(params["rho_d"])) == pytest.approx([0.06, 0.05, 0.035])
    path = render_preview(mat, tmp_path / "sphere.png", size=64, spp=16)
    img = np.asarray(Image.open(path), dtype=float)
    assert img.shape == (64, 64, 3)
    centre, corner = img[28:36, 28:36].mean(), img[:6, :6].mean()
    assert abs(centre - corner) > 5        # the sphere stands out from the background
    assert img[..., 0].mean() > img[..., 2].mean()   # reddish albedo


def test_cli_bad_input_exits_non_zero_naming_the_file(tmp_path, capsys):
    empty = tmp_path / "empty.parquet"
    cols = ["theta_in", "phi_in", "theta_out", "phi_out", "theta_h", "phi_h", "theta_d", "phi_d", "r", "g", "b",
            "weight", "u", "v", "led", "rotation"]
    pd.DataFrame({c: pd.Series([], dtype=float) for c in cols}).to_parquet(empty)
    out = tmp_path / "fit.json"
    assert main(["fit", str(empty), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(empty) in err and "empty" in err
    assert not out.exists()

    garbage = tmp_path / "garbage.parquet"
    garbage.write_bytes(b"PAR1 this is not parquet")
    assert main(["fit", str(garbage), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert str(garbage) in err and "Parquet" in err

    partial = tmp_path / "partial.parquet"
    pd.DataFrame({"theta_in": [0.1, 0.2], "r": [0.1, 0.2]}).to_parquet(partial)
    assert main(["fit", str(partial), "--out", str(out)]) == 2
    assert "missing column" in capsys.readouterr().err

    assert main(["fit", str(tmp_path / "absent.parquet"), "--out", str(out)]) == 2
    assert "not found" in capsys.readouterr().err
    assert not out.exists()


def test_cli_bad_options(samples_path, tmp_path, capsys):
    out = tmp_path / "fit.json"
    assert main(["fit", str(samples_path), "--out", str(out), "--channels", "luminance,x"]) == 2
    assert "--channels" in capsys.readouterr().err
    assert main(["fit", str(samples_path), "--out", str(tmp_path / "no" / "fit.json")]) == 2
    assert "output folder does not exist" in capsys.readouterr().err
    assert main(["fit", str(samples_path), "--out", str(out), "--clip", "-1"]) == 2
    assert not out.exists()
