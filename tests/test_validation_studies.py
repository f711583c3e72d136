"""The blind study's trial plan and the witness table read back from a study's reports
(validation/diagnose: blind_study.py, witness_check.py)."""
from __future__ import annotations

import json

import pytest

from validation.diagnose import blind_study, witness_check


def test_a_rotation_is_hidden_only_in_a_material_that_turns():
    """An isotropic real material turned about its normal is the same BRDF (the twin refuses the
    effect): the trial keeps the slot's other causes, with the magnitudes of every run."""
    m, hidden, absent = blind_study.draw(36)
    assert m == "sample_2_6" and set(hidden) == {"sample_rotation_offset"} and not absent
    for k in (37, 38):
        m, hidden, absent = blind_study.draw(k)
        assert m != "sample_2_6" and hidden == {} and set(absent) == {"sample_rotation_offset"}
    m, hidden, absent = blind_study.draw(58)
    assert set(hidden) == {"channel_response"} and set(absent) == {"sample_rotation_offset"}
    lo, hi, _ = blind_study.CAUSES["channel_response"]
    assert lo <= hidden["channel_response"] <= hi
    # the two-effect slot of the Ward material hides both
    assert set(blind_study.draw(57)[1]) == {"channel_response", "sample_rotation_offset"}


def test_a_reused_null_capture_keeps_the_code_it_was_made_with(tmp_path, monkeypatch):
    """--rediagnose diagnoses the kept null captures again: their records must still say which code
    made each capture (before, a reused null's capture version was written as unknown)."""
    from types import SimpleNamespace

    made = {"commit": "0123abc", "dirty": False}
    monkeypatch.setattr(blind_study, "has_raws", lambda cap: True)      # the capture is kept
    a = SimpleNamespace(no_diagnose=True, diagnose_code={"commit": "fedcba9", "dirty": False})
    rec = blind_study.null_capture(1, tmp_path, a, {}, None, prev={"null": 1, "code": {"capture": made}})
    assert rec["capture_reused"] and rec["code"]["capture"] == made
    # no earlier record: the version is not known, and the record says so rather than guessing
    assert blind_study.null_capture(1, tmp_path, a, {}, None)["code"]["capture"] is None


def _report(folder, verdict, dr, se, sig):
    folder.mkdir(parents=True)
    (folder / "report.json").write_text(json.dumps({
        "verdict": verdict, "ranking": [verdict], "causes": [{"name": "sample_radius_error", "refuted": None}],
        "meta": {"sample_radius_silhouette": {"dr": dr, "se": se, "significant": sig, "why_not": None if sig else "x"},
                 "led_position_band": None}}))


def test_witness_table_reads_a_studys_reports(tmp_path, capsys):
    trials = [{"trial": 0, "material": "m", "hidden": {}, "true_magnitude": {}},
              {"trial": 1, "material": "m", "hidden": {"sample_radius_error": 0.5},
               "true_magnitude": {"sample_radius_error": 0.5}}]
    (tmp_path / "trials.json").write_text(json.dumps(trials))
    _report(tmp_path / "t000_report", "none", 0.01, 0.03, False)
    _report(tmp_path / "t001_report", "sample_radius_error", 0.52, 0.03, True)
    assert witness_check.main([str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "captures hiding no sample_radius_error: 1; a signature named in 0" in out
    assert "| t001 | m | sample_radius_error | +0.500 | +0.520 | 0.030 | yes | sample_radius_error |" in out
    dst = tmp_path / "w.md"
    dst.write_text("kept")
    with pytest.raises(SystemExit) as e:
        witness_check.main([str(tmp_path), "--out", str(dst)])
    assert e.value.code == 2 and dst.read_text() == "kept"
