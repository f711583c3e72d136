"""`glossrig model crossval|fit|predict` end to end, on the thesis's own tables with a
small angle set (--scale 0.02 --max-angles 300) so each run takes about a second."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from glossrig.cli.main import main

from conftest import SHARED

pytestmark = pytest.mark.needs_shared("data/thesis/ward_params.csv", "data/thesis/coverages.csv")

THESIS = SHARED / "data" / "thesis"
WARD = str(THESIS / "ward_params.csv")
COV = str(THESIS / "coverages.csv")
FAST = ["--scale", "0.02", "--max-angles", "300", "--starts", "1"]
TARGET = "rho_d=0.0492,rho_s=0.0083,alpha_x=0.0835,alpha_y=0.0311,lobe_rotation=2.56"   # sample 7/10


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    out = tmp_path_factory.mktemp("model") / "model.json"
    assert main(["model", "fit", "--ward", WARD, "--coverages", COV, "--out", str(out), *FAST]) == 0
    return out


def test_fit_writes_model(model_path):
    doc = json.loads(model_path.read_text())
    assert doc["kind"] == "glossrig.reproduction_model"
    assert doc["fit"]["excluded"] == ["4/6"] and doc["fit"]["exclusion"] == "automatic"
    assert doc["base1"]["sample"] == "0/6"
    assert len(doc["etn"]["gamma"]) == 4 and "gamma[0]" in doc["etn"]["form"]


def test_predict_prints_nominal_coverage(model_path, capsys):
    assert main(["model", "predict", "--model", str(model_path), "--ward", TARGET]) == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert first.startswith("nominal coverage (base 2, scratched area fraction): ")
    assert 0.4 < float(first.rsplit(" ", 1)[1]) < 0.9          # sample 7/10 was fabricated at 0.7
    assert main(["model", "predict", "--model", str(model_path), "--ward", TARGET, "--json"]) == 0
    pr = json.loads(capsys.readouterr().out)
    assert pr["gamut"] == "in" and pr["nominal_b1"] == pytest.approx(1 - pr["nominal_b2"])


def test_predict_warns_out_of_gamut(model_path, capsys):
    sheet = "rho_d=0.1198,rho_s=0.0708,alpha_x=0.0031,alpha_y=0.006,lobe_rotation=3.26"
    assert main(["model", "predict", "--model", str(model_path), "--ward", sheet]) == 0
    err = capsys.readouterr().err
    assert "warning: target is out of the gamut" in err


def test_crossval_writes_report(tmp_path, capsys):
    cov = tmp_path / "cov.csv"
    cov.write_text("sample,nominal_b2\n0/6,0.0\n3/6,0.5\n4/6,0.67\n7/10,0.7\n5/6,0.83\n6/6,1.0\n")
    out = tmp_path / "cv.json"
    assert main(["model", "crossval", "--ward", WARD, "--coverages", str(cov), "--out", str(out), *FAST]) == 0
    doc = json.loads(out.read_text())
    assert [m["method"] for m in doc["methods"]] == [1, 2, 3]
    assert doc["outliers"] == ["4/6"]
    for m in doc["methods"]:
        assert m["error_mean"] >= 0 and m["error_std"] >= 0
        assert ("4/6" in m["used_samples"]) == (m["method"] == 2)
        assert len(m["folds"]) == len(m["used_samples"]) - 2
    assert "outliers (detected): 4/6" in capsys.readouterr().out


@pytest.mark.parametrize("cov,msg", [
    ("", "coverage table is empty"),
    ("sample,nominal\n0/6,0\n", "lacks column 'nominal_b2'"),
    ("sample,nominal_b2\n0/6,0.0\n1/6,1.5\n3/6,0.5\n6/6,1\n", "outside [0, 1]"),
    ("sample,nominal_b2\n0/6,0.0\n1/7,0.5\n3/6,0.5\n6/6,1\n", "unknown sample '1/7'"),
])
@pytest.mark.parametrize("verb", ["fit", "crossval"])
def test_bad_tables_exit_nonzero(tmp_path, capsys, verb, cov, msg):
    p = tmp_path / "cov.csv"
    p.write_text(cov)
    out = tmp_path / "out.json"
    assert main(["model", verb, "--ward", WARD, "--coverages", str(p), "--out", str(out), *FAST]) == 2
    err = capsys.readouterr().err
    assert msg in err and "cov.csv" in err
    assert not out.exists()


def test_bad_arguments_exit_nonzero(tmp_path, capsys, model_path):
    out = str(tmp_path / "m.json")
    assert main(["model", "fit", "--ward", WARD, "--coverages", COV, "--out", out, "--exclude", "9/9", *FAST]) == 2
    assert "unknown sample '9/9'" in capsys.readouterr().err
    assert main(["model", "fit", "--ward", WARD, "--coverages", COV, "--out", str(tmp_path / "no" / "m.json")]) == 2
    assert "output folder does not exist" in capsys.readouterr().err
    assert main(["model", "predict", "--model", str(tmp_path / "missing.json"), "--ward", TARGET]) == 2
    assert "model file not found" in capsys.readouterr().err
    assert main(["model", "predict", "--model", str(model_path), "--ward", "rho_d=0.05,alpha_x=0.1"]) == 2
    assert "missing" in capsys.readouterr().err
    assert main(["model", "predict", "--model", WARD, "--ward", TARGET]) == 2
    assert "model file is not readable JSON" in capsys.readouterr().err


@pytest.mark.parametrize("ward,msg", [
    ("rho_d=0.0492,rho_s=0.0083,alpha_x=0.0835,alpha_y=0.0311,lobe_rotation=140", "beyond 2 pi radians: degrees?"),
    ("rho_d=5,rho_s=0.0083,alpha_x=0.0835,alpha_y=0.0311", "rho_d=5 must lie in [0, 1]"),
    ("rho_d=0.0492,rho_s=0.0083,alpha_x=6,alpha_y=0.0311", "alpha_x=6 must lie in (0, 0.5]"),
    ("rho_d=0.7,rho_s=0.5,alpha_x=0.0835,alpha_y=0.0311", "rho_d + rho_s = 1.2 exceeds 1"),
])
def test_predict_refuses_values_out_of_range(model_path, capsys, ward, msg):
    """Issue #16: degrees for lobe_rotation, rho_d = 5 or alpha = 6 used to be predicted from."""
    assert main(["model", "predict", "--model", str(model_path), "--ward", ward]) == 2
    err = capsys.readouterr().err
    assert msg in err and "glossrig model: error:" in err, err


def test_predict_takes_an_explicit_angle_unit(model_path, capsys):
    rad = TARGET
    deg = TARGET.replace("lobe_rotation=2.56", "lobe_rotation=146.677deg")     # 2.56 rad
    assert main(["model", "predict", "--model", str(model_path), "--ward", rad, "--json"]) == 0
    a = json.loads(capsys.readouterr().out)
    assert main(["model", "predict", "--model", str(model_path), "--ward", deg, "--json"]) == 0
    b = json.loads(capsys.readouterr().out)
    assert b["nominal_b2"] == pytest.approx(a["nominal_b2"], abs=1e-3)


@pytest.mark.parametrize("verb", ["fit", "crossval"])
def test_ward_table_in_degrees_is_refused(tmp_path, capsys, verb):
    """A lobe_rotation column in degrees (Table 4.2 bounds it by 0..360) named with its file and column."""
    lines = Path(WARD).read_text().splitlines()
    out_lines = []
    for line in lines:
        if line.startswith("#") or line.startswith("name,"):
            out_lines.append(line)
            continue
        f = line.split(",")
        f[5] = f"{float(f[5]) * 180 / 3.141592653589793:.1f}"
        out_lines.append(",".join(f))
    p = tmp_path / "ward_deg.csv"
    p.write_text("\n".join(out_lines) + "\n")
    out = tmp_path / "out.json"
    assert main(["model", verb, "--ward", str(p), "--coverages", COV, "--out", str(out), *FAST]) == 2
    err = capsys.readouterr().err
    assert f"{p}: column 'lobe_rotation' holds 144.4 (row 1), beyond 2 pi: the column looks like degrees" in err, err
    assert not out.exists()
