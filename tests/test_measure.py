"""``glossrig measure``: one command from captures to report, each step reused only when
its recorded inputs match (issue 17).

The fast route: the tiny one-LED twin captures of conftest.py (camera and lamps from the
twin's truth). The step functions of the verb are wrapped to count their calls, so a
rerun is seen to redo nothing and a changed lamps file to redo exactly the steps
downstream of it. The calibrations from captures run for real in a slow test.
"""
from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import pytest

from glossrig.cli.main import main
from glossrig.cli.verbs import measure

from conftest import RIG, camera_json_from_truth, glossrig_cli
from helpers import assert_image_has_content

STEP_FUNCS = {"camera": "_calibrate_camera", "lamps": "_calibrate_lamps", "extract": "_extract", "fit": "_fit",
              "exports": "_exports", "renders": "_renders", "recovery": "_recovery", "report": "_report"}
EXPORTS = ("material.xml", "material_stock.xml", "material.brdf", "samples.csv")
TINY_RENDER = ("--render-size", 16, "--render-spp", 1)


@pytest.fixture
def counted(monkeypatch):
    """The steps measure ran, in order (each step function wrapped to record its name)."""
    calls: list[str] = []
    for step, fn in STEP_FUNCS.items():
        real = getattr(measure, fn)

        def wrapped(*a, _real=real, _step=step, **k):
            calls.append(_step)
            return _real(*a, **k)

        monkeypatch.setattr(measure, fn, wrapped)
    return calls


def _measure(*args) -> int:
    return main(["measure", *map(str, args), "--no-progress", "-q"])


def _take(calls: list) -> list:
    out = list(calls)
    calls.clear()
    return out


@pytest.mark.mitsuba
def test_measure_writes_everything_and_redoes_exactly_what_changed(tiny_captures, tmp_path, monkeypatch, counted,
                                                                    capsys):
    caps = tiny_captures
    truth = json.loads((caps / "sample" / "truth.json").read_text())
    # --checkerboard with the calibration replaced by the truth (the real one is the slow test below):
    # the step's input is the folder's manifest, as for a real checkerboard capture
    cal_calls = []

    def fake_camera(checker, cam_path, progress):
        counted.append("camera")
        cal_calls.append(checker)
        Path(cam_path).write_text(json.dumps(camera_json_from_truth(truth)))

    monkeypatch.setattr(measure, "_calibrate_camera", fake_camera)
    lamps = tmp_path / "lamps.json"
    shutil.copy(caps / "lamps.json", lamps)
    out = tmp_path / "m"
    args = [caps / "sample", "--reference", caps / "ref", "--checkerboard", caps / "ref", "--lamps", lamps,
            "--out", out, *TINY_RENDER]

    t0 = time.perf_counter()
    assert _measure(*args) == 0
    first_s = time.perf_counter() - t0
    assert _take(counted) == ["camera", "extract", "fit", "exports", "renders", "recovery", "report"]
    for f in ("report.html", "report.md", "samples.parquet", "fit.json", "camera.json", "recovery.json"):
        assert (out / f).is_file() and (out / f).stat().st_size > 0, f
    for f in EXPORTS:
        assert (out / "exports" / f).is_file() and (out / "exports" / f).stat().st_size > 0, f
    for f in ("render_sphere.png", "render_cloth.png"):
        assert_image_has_content(out / "renders" / f, min_size=(16, 16))        # --render-size 16
    fit = json.loads((out / "fit.json").read_text())
    gloss = fit["luminance"]["gloss"]              # glossrig.core.models.gloss of the luminance fit (issue 17)
    assert {"gu20", "gu60", "gu85", "haze", "doi"} <= set(gloss)
    assert all(math.isfinite(gloss[k]) and gloss[k] >= 0 for k in ("gu20", "gu60", "gu85"))
    # the fit's budget has the calibration component, as glossrig fit's (measure's camera, lamps and capture)
    u = fit["luminance"]["uncertainty"]
    assert "calibration" not in u["budget"].get("omitted", {}), u["budget"].get("omitted")
    assert all(u[k]["components"]["calibration"] > 0 for k in ("rho_d", "rho_s", "alpha_x", "alpha_y")), u
    # the recovery table: camera and lamps are the truth, so their errors are exactly 0
    rec = json.loads((out / "recovery.json").read_text())
    assert rec["intrinsics"] == {"fx_error_percent": 0.0, "fy_error_percent": 0.0, "cx_error_px": 0.0,
                                 "cy_error_px": 0.0}
    assert rec["lamps"]["worst_error_mm"] == 0.0 and rec["lamps"]["n_leds"] == 1
    true_ward = truth["material"]["ward"]
    for k in ("rho_d", "rho_s", "alpha_x", "alpha_y"):
        assert rec["material"]["true"][k] == pytest.approx(true_ward[k])
        assert rec["material"]["error"][f"{k}_percent"] == pytest.approx(
            100 * (fit["luminance"][k] / true_ward[k] - 1), abs=1e-9)
    html = (out / "report.html").read_text()
    assert "Recovery of the calibrations" in html and "render sphere" in html
    stdout = capsys.readouterr().out
    assert "7 step(s) run, 0 reused" in stdout

    # rerun, inputs unchanged: nothing redone, nothing rewritten
    stamps = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and ".steps" not in p.parts}
    t0 = time.perf_counter()
    assert _measure(*args, "--resume") == 0
    assert _take(counted) == [] and time.perf_counter() - t0 < max(5.0, first_s / 4)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert "0 step(s) run, 7 reused" in capsys.readouterr().out

    # another lamps.json (LED 9 moved by 1 mm): extract and everything after it, not the calibration
    d = json.loads(lamps.read_text())
    d["lamps_mm"]["9"][1] += 1.0
    lamps.write_text(json.dumps(d))
    assert _measure(*args, "--resume") == 0
    assert _take(counted) == ["extract", "fit", "exports", "renders", "recovery", "report"]
    rec2 = json.loads((out / "recovery.json").read_text())
    assert rec2["lamps"]["worst_error_mm"] == pytest.approx(1.0)
    assert json.loads((out / "fit.json").read_text())["luminance"] != fit["luminance"]
    # an output edited by hand is redone; what depends on it only when the redone output differs
    (out / "recovery.json").write_text("{}")
    assert _measure(*args, "--resume") == 0
    assert _take(counted) == ["recovery"]
    assert len(cal_calls) == 1


def test_measure_needs_one_camera_and_one_lamp_source(tmp_path, capsys):
    cases = [([], "--camera camera.json and --checkerboard CHECKER_DIR"),
             (["--camera", "c.json", "--checkerboard", "chk"], "not both"),
             (["--camera", "c.json"], "--lamps lamps.json and --specular SPECULAR_DIR")]
    for extra, msg in cases:
        rc = _measure(tmp_path / "s", "--reference", tmp_path / "r", *extra, "--out", tmp_path / "o")
        err = capsys.readouterr().err
        assert rc == 2 and msg in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "o").exists()


def test_measure_refuses_an_existing_folder_and_missing_inputs(tmp_path, capsys):
    out = tmp_path / "o"
    out.mkdir()
    (out / "x").write_text("mine")
    base = [tmp_path / "s", "--reference", tmp_path / "r", "--camera", "c.json", "--lamps", "l.json"]
    assert _measure(*base, "--out", out) == 2
    err = capsys.readouterr().err
    assert str(out) in err and "--resume" in err and "--force" in err and len(err.strip().splitlines()) == 1
    assert _measure(*base, "--out", out, "--resume", "--force") == 2
    capsys.readouterr()
    assert _measure(*base, "--out", tmp_path / "new") == 2             # the sample is not a capture folder
    err = capsys.readouterr().err
    assert "capture.json" in err and str(tmp_path / "s") in err and len(err.strip().splitlines()) == 1
    assert (out / "x").read_text() == "mine"


@pytest.mark.slow
@pytest.mark.mitsuba
def test_measure_calibrates_camera_and_lamps_from_captures(tiny_captures, tmp_path):
    """--checkerboard and --specular at the tiny captures' scale: the real calibrations, whose
    results land within a few percent / millimetres of the twin's truth."""
    caps = tiny_captures
    glossrig_cli("simulate", "--rig", RIG, "--target", "checkerboard", "--views", 8, "--scale", 0.12, "--seed", 8,
                 "--no-progress", "-q", "--out", tmp_path / "checker")
    glossrig_cli("simulate", "--rig", RIG, "--material", "transparency_sheet", "--leds", "9", "--rotations", 0,
                 "--repeats", 1, "--scale", 0.12, "--spp", 1, "--seed", 9, "--no-progress", "-q",
                 "--out", tmp_path / "specular")
    out = tmp_path / "m"
    assert _measure(caps / "sample", "--reference", caps / "ref", "--checkerboard", tmp_path / "checker",
                    "--specular", tmp_path / "specular", "--out", out, *TINY_RENDER) == 0
    for f in ("camera.json", "lamps.json", "samples.parquet", "fit.json", "report.html", "report.md"):
        assert (out / f).is_file(), f
    rec = json.loads((out / "recovery.json").read_text())
    assert abs(rec["intrinsics"]["fx_error_percent"]) < 3 and abs(rec["intrinsics"]["fy_error_percent"]) < 3
    assert rec["lamps"]["n_leds"] == 1 and rec["lamps"]["worst_error_mm"] < 10
    assert math.isfinite(rec["material"]["error"]["rho_d_percent"])
