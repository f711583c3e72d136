"""Provenance records (issue #16: every output records its inputs with checksums, options,
version and source revision) and the noise-only label of the fit's standard errors.
No rendering: the end-to-end extract -> fit chain on twin captures is in test_pipeline.py."""
from __future__ import annotations

import hashlib
import json
import subprocess
from importlib.metadata import version

import pyarrow.parquet as pq
import pytest

from glossrig.cli.main import main
from glossrig.core import provenance as P
from glossrig.core.extraction.cylinder import nominal_samples
from glossrig.core.errors import InputError
from glossrig.core.rig import default_rig_path, load_rig
from glossrig.core.samples import read_provenance, read_samples, ward_samples, write_samples
from glossrig.core.models.ward import WardParams


def sha(p) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


@pytest.fixture(scope="module")
def table():
    rig = load_rig(default_rig_path())
    geo = nominal_samples(rig, rig.select_leds("middle"), [0, 90], 0.03)
    return ward_samples(geo, WardParams(0.0518, 0.0069, 0.0595, 0.034, 2.47), noise=0.03, seed=1)


def test_provenance_hashes_files_and_capture_manifests(tmp_path, monkeypatch):
    f = tmp_path / "camera.json"
    f.write_text('{"fx": 1}')
    cap = tmp_path / "cap"
    cap.mkdir()
    (cap / "capture.json").write_text('{"images": []}')
    monkeypatch.chdir(tmp_path)
    prov = P.provenance({"camera": "camera.json", "sample": "cap", "lamps": None}, {"albedo": 0.8, "p": tmp_path},
                        tool="glossrig test")
    assert prov["tool"] == "glossrig test" and prov["glossrig_version"] == version("glossrig")
    assert prov["inputs"]["camera"] == {"path": "camera.json", "resolved": str(f.resolve()), "sha256": sha(f)}
    assert prov["inputs"]["sample"]["sha256"] == sha(cap / "capture.json")
    assert prov["inputs"]["sample"]["file"] == "capture.json" and prov["inputs"]["lamps"] is None
    assert prov["options"] == {"albedo": 0.8, "p": str(tmp_path)}
    assert json.loads(json.dumps(prov)) == prov                          # plain JSON
    assert P.file_sha256(f) == sha(f)
    with pytest.raises(InputError, match="not a capture folder"):
        P.provenance({"x": tmp_path}, {})
    with pytest.raises(InputError, match="not found"):
        P.provenance({"x": tmp_path / "missing.json"}, {})


def test_source_revision_is_the_checkout_commit_and_null_without_git(tmp_path, monkeypatch):
    head = subprocess.run(["git", "-C", str(P.SOURCE_ROOT), "rev-parse", "HEAD"], capture_output=True, text=True)
    rev = P.source_revision()
    if head.returncode == 0 and (P.SOURCE_ROOT / "pyproject.toml").is_file():
        assert rev["commit"] == head.stdout.strip() and isinstance(rev["dirty"], bool)
    # installed from a wheel: no checkout around the package -> null, no error
    monkeypatch.setattr(P, "SOURCE_ROOT", tmp_path)
    assert P.source_revision() is None
    assert P.provenance({}, {})["source"] is None
    # git not installed at all -> null, no error
    monkeypatch.undo()
    monkeypatch.setenv("PATH", str(tmp_path))
    assert P.source_revision() is None


def test_samples_table_carries_its_provenance_in_the_schema_metadata(table, tmp_path):
    prov = P.provenance({}, {"estimator": "ml"}, tool="glossrig extract")
    out = write_samples(table, tmp_path / "s.parquet", provenance=prov)
    assert json.loads(pq.read_schema(out).metadata[b"glossrig.provenance"]) == prov
    assert read_samples(out).attrs["provenance"] == prov == read_provenance(out)
    plain = write_samples(table, tmp_path / "plain.parquet")
    assert read_provenance(plain) is None and read_samples(plain).attrs["provenance"] is None


def test_fit_json_records_provenance_chain_and_labels_stderr_noise_only(table, tmp_path, capsys):
    upstream = {"tool": "glossrig extract", "inputs": {"sample": {"sha256": "0" * 64}}}
    src = write_samples(table, tmp_path / "s.parquet", provenance=upstream)
    out = tmp_path / "fit.json"
    assert main(["fit", str(src), "--out", str(out), "--channels", "luminance,g", "--starts", "1",
                 "--weighting", "none", "--clip", "2.0", "-q"]) == 0
    printed = capsys.readouterr().out
    js = json.loads(out.read_text())
    prov = js["provenance"]
    assert prov["tool"] == "glossrig fit" and prov["glossrig_version"] == version("glossrig")
    assert prov["inputs"]["samples"]["sha256"] == sha(src)
    assert prov["inputs"]["samples"]["resolved"] == str(src.resolve())
    assert prov["inputs"]["samples"]["provenance"] == upstream
    given = {"channels": ["luminance", "g"], "weighting": "none", "clip": 2.0,
             "clip_literal": False, "ignore_weight_column": False, "starts": 1, "seed": 0}
    assert {k: prov["options"].get(k) for k in given} == given
    # the options of the footprint model and the uncertainty budget are recorded too (their defaults here)
    assert {"footprint", "led_aperture", "calibration_draws", "camera", "lamps"} <= set(prov["options"])
    for c in ("luminance", "g"):
        assert js[c]["stderr_kind"].startswith("noise-only") and "calibration and model error" in js[c]["stderr_kind"]
        assert js[c]["rho_d_stderr"] > 0                                  # readers of <name>_stderr keep working
    # every printed uncertainty is labelled noise-only, and the summary says it is not the uncertainty
    stderr_lines = [ln for ln in printed.splitlines() if "stderr" in ln]
    assert len(stderr_lines) == 3 and all("noise-only" in ln for ln in stderr_lines)
    assert "not the measurement's uncertainty" in printed


def test_design_errors_say_they_are_noise_only(tmp_path):
    out = tmp_path / "errors.json"
    assert main(["design", "errors", "--rig", str(default_rig_path()), "--materials", "sample_2_6", "--leds", "9",
                 "--rotations", "0", "--scale", "0.05", "--out", str(out)]) == 0
    js = json.loads(out.read_text())
    assert js["stderr_kind"].startswith("noise-only") and js["expected_errors"]["sample_2_6"]["stderr"]["rho_d"] > 0
