"""glossrig diagnose with the reference's own BRDF (issue 14, item 4): renormalising with it is
a calibration step that is applied and reported, never a verdict.

The tiny twin captures (conftest.tiny_captures: lambert:0.8 reference, sample_2_6, LED 9) are
diagnosed with a made-up reference BRDF ``f_ref = (albedo / pi) k_c(theta_in)``: the
calibration must multiply each channel of each row by exactly ``k_c`` at that row's angles
(thesis eq. 4.78 inverted), rescale the channel's inverse variance by ``1 / k_c^2``, record its
median effect, and fit the material to the renormalised data; no cause of kind "reference" is
tested then."""
from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from glossrig.core.diagnose.data import LUMA

ALBEDO = 0.8
#: per-channel scale of the made-up reference BRDF relative to the thesis's Lambertian 0.8
CHANNEL_SCALE = np.array([0.9, 1.0, 1.25])


def angular(t):
    """``k_c(theta_in)``: a rise of 30 % from grazing to normal incidence, per channel scaled."""
    return CHANNEL_SCALE[None, :] * (1.0 + 0.3 * np.cos(np.asarray(t["theta_in"], float)))[:, None]


def reference_brdf(t):
    return ALBEDO / np.pi * angular(t)


def constant_reference(t):
    """A Lambertian reference of albedo 1.25 x 0.8 in every channel: k = 1.25 at every row."""
    return np.full((len(t), 3), 1.25 * ALBEDO / np.pi)


def _calibration_inputs(d):
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps

    return load_camera(d / "camera.json"), load_lamps(d / "lamps.json")


@pytest.fixture(scope="module")
def measured_reference(tiny_captures):
    """The tiny reference capture measured once for this module's diagnoses (diagnose's
    ``reference_measured``: the same camera and lamps)."""
    from glossrig.core.extraction.extract import measure_capture

    return measure_capture(tiny_captures / "ref", *_calibration_inputs(tiny_captures), what="diagnose")


@pytest.mark.mitsuba
def test_reference_brdf_renormalises_every_row_and_records_it(tiny_captures, measured_reference):
    from glossrig.core.diagnose.data import load_brdf

    d = tiny_captures
    cam, lamps = _calibration_inputs(d)
    ref = measured_reference
    plain = load_brdf(d / "sample", d / "ref", cam, lamps, albedo=ALBEDO, reference=ref)
    cal = load_brdf(d / "sample", d / "ref", cam, lamps, albedo=ALBEDO, reference=ref, reference_brdf=reference_brdf,
                    reference_source="made-up")
    assert plain.reference_calibration is None
    a, b = plain.table, cal.table
    # the same rows (the made-up reference is positive everywhere, so no channel is lost)
    assert len(a) == len(b) and np.array_equal(a["theta_in"].to_numpy(), b["theta_in"].to_numpy())
    k = angular(a)
    for j, c in enumerate("rgb"):
        ok = np.isfinite(a[c].to_numpy(float))
        # each value times f_ref pi / albedo at its own angles (float64 products: exact to rounding)
        np.testing.assert_allclose(b[c].to_numpy(float)[ok], a[c].to_numpy(float)[ok] * k[ok, j], rtol=1e-12)
        # inverse variances scale by 1 / k^2 up to one common factor (both tables' weights have mean 1)
        ratio = b[f"weight_{c}"].to_numpy(float)[ok] * k[ok, j] ** 2 / a[f"weight_{c}"].to_numpy(float)[ok]
        np.testing.assert_allclose(ratio, np.median(ratio), rtol=1e-9)
    # luminance of the renormalised channels; the thesis-normalised luminance kept beside it
    full = np.isfinite(a[["r", "g", "b"]].to_numpy(float)).all(axis=1)
    np.testing.assert_allclose(b["f"].to_numpy(float)[full], (a[["r", "g", "b"]].to_numpy(float) * k)[full] @ LUMA,
                               rtol=1e-12)
    np.testing.assert_allclose(b["f_thesis"].to_numpy(float), a["f"].to_numpy(float), rtol=0, equal_nan=True)
    rec = cal.reference_calibration
    assert rec["applied"] and rec["source"] == "made-up" and rec["albedo"] == ALBEDO
    for j, c in enumerate("rgb"):
        ok = np.isfinite(a[c].to_numpy(float))
        assert rec["effect"][c]["median"] == pytest.approx(float(np.median(k[ok, j])) - 1, rel=1e-12)
        assert rec["effect"][c]["p5"] < rec["effect"][c]["median"] < rec["effect"][c]["p95"]
        assert rec["rows_made_missing"][c] == 0


def test_a_reference_that_is_not_three_channels_per_row_is_refused():
    from glossrig.core.diagnose.data import renormalise_table
    from glossrig.core.errors import InputError

    t = {"theta_in": np.zeros(4), "r": np.ones(4), "g": np.ones(4), "b": np.ones(4)}
    with pytest.raises(InputError, match="paper.bsdf.*shape"):
        renormalise_table(pd.DataFrame(t), lambda tab: np.ones((len(tab), 2)), ALBEDO, source="paper.bsdf")


@pytest.mark.mitsuba
def test_diagnose_calibrates_with_the_reference_and_never_names_it(tiny_captures, measured_reference, tmp_path):
    """The whole diagnosis with a supplied reference BRDF: the calibration is in report.json and
    report.md, no cause of kind "reference" is among the candidates (so none can be the verdict),
    and the material is fitted to the renormalised data: with a constant ``k = 1.25`` in every
    channel the data is exactly 1.25 times the thesis-normalised data with the same relative
    weights, so the Ward fit's rho_d and rho_s are 1.25 times those without the reference and
    its lobe is the same - to the fit's convergence (relative 1e-3: the trust-region fit stops
    at a relative cost change of 1e-8, a parameter change of order sqrt(1e-8) = 1e-4 on a
    well-conditioned minimum, with a factor 10 of margin)."""
    from glossrig.core.diagnose import diagnose

    d = tiny_captures
    args = (d / "sample", d / "ref", d / "camera.json", d / "lamps.json")
    quiet = dict(albedo=ALBEDO, plots=False, log=lambda *a: None, reference_measured=measured_reference)
    plain = diagnose(*args, tmp_path / "plain", **quiet)
    rep = diagnose(*args, tmp_path / "cal", reference_brdf=constant_reference, reference_source="lambert-1.0",
                   **quiet)
    assert plain["meta"]["reference_calibration"] == {"applied": False}
    cal = rep["meta"]["reference_calibration"]
    assert cal["applied"] and cal["source"] == "lambert-1.0"
    assert all(cal["effect"][c]["median"] == pytest.approx(0.25, rel=1e-12) for c in "rgb")
    assert "refitted" in cal["fit"]
    on_disk = json.loads((tmp_path / "cal" / "report.json").read_text())
    assert on_disk["meta"]["reference_calibration"]["applied"] is True
    md = (tmp_path / "cal" / "report.md").read_text()
    assert "Reference calibration (applied, not a verdict)" in md and "lambert-1.0" in md
    assert "Reference calibration" not in (tmp_path / "plain" / "report.md").read_text()
    for r in (plain, rep):
        assert all(c["kind"] != "reference" for c in r["causes"])
        assert r["verdict"] != "reference_brdf"
    m0, m1 = plain["meta"]["material"], rep["meta"]["material"]
    for p in ("rho_d", "rho_s"):
        assert m1[p] == pytest.approx(1.25 * m0[p], rel=1e-3)
    for p in ("alpha_x", "alpha_y"):
        assert m1[p] == pytest.approx(m0[p], rel=1e-3)


def test_a_channel_the_reference_gives_no_positive_value_for_becomes_missing():
    """Where f_ref is zero or NaN the channel cannot be renormalised: missing in that row (as a dark
    channel is, :mod:`glossrig.core.samples`), counted in the record; the row keeps its other channels."""
    from glossrig.core.diagnose.data import renormalise_table

    t = pd.DataFrame({"theta_in": np.zeros(3), "r": [0.1, 0.2, 0.3], "g": [0.1, 0.2, 0.3], "b": [0.1, 0.2, 0.3]})
    ref = np.full((3, 3), ALBEDO / np.pi)
    ref[1, 0], ref[2, 2] = 0.0, np.nan
    out, rec = renormalise_table(t, lambda tab: ref, ALBEDO)
    assert np.isnan(out["r"][1]) and np.isnan(out["b"][2])
    np.testing.assert_allclose(out["g"], t["g"], rtol=1e-12)      # f_ref = albedo / pi: k = 1
    assert rec["rows_made_missing"] == {"r": 1, "g": 0, "b": 1}
