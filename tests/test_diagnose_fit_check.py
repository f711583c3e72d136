"""diagnose --fit: a fit of another sample is refused by its provenance, a fit of the same sample
is accepted whatever an instrument effect does to the misfit (core/diagnose/fit_check.py)."""
import json

import pytest

from glossrig.core.diagnose.fit_check import FIT_MISMATCH, check_fit, sample_name
from glossrig.core.errors import InputError


def _capture(folder, material, sample=None):
    folder.mkdir()
    doc = {"rig": "rig.toml", "material": material, "complete": True, "images": []}
    if sample is not None:
        doc["sample"] = sample
    (folder / "capture.json").write_text(json.dumps(doc))
    return folder


def _extract_provenance(capture):
    """What ``glossrig fit`` records: the samples' own provenance naming the capture extract read."""
    return {"tool": "glossrig fit", "inputs": {"samples": {"path": "s.parquet", "provenance": {
        "inputs": {"sample": {"file": "capture.json", "path": str(capture), "resolved": str(capture)}}}}}}


def test_same_sample_is_accepted_at_any_misfit(tmp_path):
    """The blind study's case: satin's own fit missed a satin capture with an LED emission pattern by
    53 % (> FIT_MISMATCH), which the misfit check refused."""
    fit_cap = _capture(tmp_path / "null", "satin_rosaline_rgb", sample="satin_rosaline_rgb")
    here = _capture(tmp_path / "trial", "satin_rosaline_rgb", sample="satin_rosaline_rgb")
    line = check_fit(tmp_path / "fit.json", {"source": str(fit_cap)}, here, 0.53)
    assert "same sample 'satin_rosaline_rgb'" in line and "53%" in line
    assert check_fit(tmp_path / "fit.json", _extract_provenance(fit_cap), here, 3.0)


def test_another_sample_is_refused_even_when_its_misfit_is_small(tmp_path):
    """White paper's fit missed a satin capture by only 22 % (< FIT_MISMATCH): the misfit alone let it through."""
    fit_cap = _capture(tmp_path / "paper", "rgl:paper_white_rgb")
    here = _capture(tmp_path / "satin", "rgl:satin_rosaline_rgb")
    with pytest.raises(InputError) as e:
        check_fit(tmp_path / "fit.json", _extract_provenance(fit_cap), here, 0.22)
    msg = str(e.value)
    assert "does not belong" in msg and "paper_white" in msg and "satin_rosaline" in msg and "fit.json" in msg


def test_without_a_readable_source_the_misfit_decides(tmp_path):
    here = _capture(tmp_path / "cap", "sample_2_6")
    gone = {"source": str(tmp_path / "moved_away")}
    assert "misfit only" in check_fit(tmp_path / "f.json", gone, here, FIT_MISMATCH * 0.9)
    for prov in (gone, None, {"tool": "glossrig fit"}):
        with pytest.raises(InputError, match="does not belong"):
            check_fit(tmp_path / "f.json", prov, here, FIT_MISMATCH * 1.1)
    with pytest.raises(InputError, match="does not belong"):
        check_fit(tmp_path / "f.json", None, here, float("nan"))


def test_sample_name_prefers_the_plan_s_sample(tmp_path):
    assert sample_name(_capture(tmp_path / "a", "ward:rho_d=0.2", sample="tile 3")) == "tile 3"
    assert sample_name(_capture(tmp_path / "b", "brushed_original")) == "brushed_original"
    assert sample_name(tmp_path / "missing") is None
