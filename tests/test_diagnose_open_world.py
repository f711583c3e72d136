"""glossrig diagnose, issue 14: the calibrated error model (the base model's normalised
held-out error is 1 on data it describes), material departures before instrument causes
(the flexible material model), the kind of every cause and the open-world verdict
"unexplained". Fast: synthetic residuals and the synthetic BRDF tables of
tests/test_diagnose.py (rig geometry, LEDs 6 and 9), no captures."""
from __future__ import annotations

import json

import numpy as np
import pytest

from glossrig.core.diagnose.catalogue import KINDS, BrdfModel, CauseResult, brdf_causes
from glossrig.core.diagnose.error_model import fit_misfit, huber_sigma, misfit_features, unit_scale
from glossrig.core.diagnose.flexible import describe, hat_basis
from glossrig.core.diagnose.report import final_verdict, ranking, read_report, verdict, write_report
from glossrig.core.diagnose.unexplained import (bin_factor, open_world_verdict, retested_cause,
                                                structure_test, training_bins, unexplained)

from test_diagnose import synthetic_brdf

#: the effect bound of the former in-sample open-world rule (relative spread of the bin means; it was
#: significant with chi^2 p below the level and an effect above this)
EFFECT_MIN_FORMER = 0.02


# ----------------------------------------------------------------- error model

def test_fit_misfit_recovers_the_variance_terms():
    """Residuals drawn with noise v0 plus a^2 pred^2 + b^2 lobe^2: the coefficients come back."""
    rng = np.random.default_rng(1)
    n = 40_000
    pred = rng.uniform(0.01, 1.0, n)
    lobe = pred * rng.uniform(0, 1, n) ** 3
    v0 = (0.004 * pred) ** 2
    F = misfit_features(pred, lobe, np.zeros(n))
    true = np.array([0.003 ** 2, 0.02 ** 2, 0.0])
    res = rng.normal(size=n) * np.sqrt(v0 + F @ true)
    k = fit_misfit(res, v0, F)
    assert abs(np.sqrt(k[0]) / 0.003 - 1) < 0.15 and abs(np.sqrt(k[1]) / 0.02 - 1) < 0.1, np.sqrt(k)
    s = unit_scale(res, v0, F @ k, np.ones(n, bool), 3.0)
    chi = np.mean((res / huber_sigma(np.sqrt(v0 + s * F @ k), res, 3.0)) ** 2)
    assert abs(chi - 1) < 1e-6 and 0.8 < s < 1.25, (s, chi)
    # noise alone already explains the residuals: no model-error term
    res0 = rng.normal(size=n) * np.sqrt(v0)
    assert unit_scale(res0, v0 * 1.1, F @ k, np.ones(n, bool), 3.0) == 0.0


@pytest.mark.parametrize("seed", [20, 21, 22])
def test_base_heldout_error_is_one_on_data_the_model_describes(seed):
    data, ward = synthetic_brdf(seed)
    cal = BrdfModel.build(data, ward).calibration
    assert abs(cal["heldout_error"] - 1) < 0.1, cal
    assert abs(cal["heldout_error_noise_only"] - 1) < 0.1, cal


def test_model_error_term_calibrates_a_misfit_the_noise_does_not_describe():
    """A point-sampled lobe misfit (3 % of the lobe, not in the stated HDR noise): noise alone
    gives a held-out error far above 1; with the model-error term fitted on the training LED
    the held-out error on the other LED is 1 within its spread."""
    data, ward = synthetic_brdf(23)
    t = data.table
    rng = np.random.default_rng(3)
    from glossrig.core.models.ward import WardParams, ward_from_angles

    lobe = ward_from_angles(t.theta_in, t.theta_out, t.theta_h, t.phi_h,
                            WardParams(0.0, ward.rho_s, ward.alpha_x, ward.alpha_y, ward.lobe_rotation))
    t["f"] = t["f"] + 0.03 * lobe * rng.normal(size=len(t))
    cal = BrdfModel.build(data, ward).calibration
    assert cal["heldout_error_noise_only"] > 1.5, cal
    assert abs(cal["heldout_error"] - 1) < 0.2, cal


# ----------------------------------------------------------------- flexible material model

def test_hat_basis_is_a_partition_of_unity_and_clamps():
    x = np.array([-5.0, 0.0, 0.3, 1.0, 2.5, 9.0])
    B = hat_basis(x, np.array([0.0, 1.0, 3.0]))
    np.testing.assert_allclose(B.sum(axis=1), 1.0)
    np.testing.assert_allclose(B[0], B[1])            # clamped below
    np.testing.assert_allclose(B[-1], [0, 0, 1])       # clamped above


def test_describe_names_the_variable_and_direction():
    rng = np.random.default_rng(2)
    cols = {k: rng.uniform(0, 1.2, 5000) for k in ("theta_in", "theta_out", "theta_h", "theta_d")}
    d = 0.2 * (1 - np.cos(cols["theta_in"])) + 0.002 * rng.normal(size=5000)
    r = describe(d, cols)
    assert r["variable"] == "theta_in" and r["description"] == "rises toward grazing theta_in", r


def _causes(effect_fn, seed=40):
    data, ward = synthetic_brdf(seed)
    effect_fn(data.table)
    m = BrdfModel.build(data, ward)
    return m, brdf_causes(m)


def _grazing(t):
    """A reciprocal rise toward grazing angles of a nearly diffuse material (no instrument effect)."""
    t["f"] = t["f"] * (1 + 1.5 * (1 - np.cos(t.theta_in)) * (1 - np.cos(t.theta_out)))


def test_material_departure_is_not_blamed_on_the_instrument():
    m, causes = _causes(_grazing)
    by = {c.name: c for c in causes}
    assert verdict(causes) == "flexible_material", [(c.name, round(c.gain, 3), c.eligible) for c in causes]
    assert by["flexible_material"].kind == "material" and by["flexible_material"].significant
    assert "rises toward" in by["flexible_material"].params["description"]
    for c in causes:
        if c.kind == "instrument":
            assert not c.eligible, (c.name, c.gain, c.vs_material)


def test_instrument_cause_still_wins_when_it_beats_the_material_model():
    """Vignetting (image position: no material produces it) beats the flexible model held out."""
    from test_diagnose import brdf_winner

    w, causes = brdf_winner(30, "vignetting", 0.25)
    assert w is not None and w.name == "vignetting" and w.blocked_by is None, [
        (c.name, round(c.gain, 3), c.blocked_by) for c in causes]
    assert verdict(causes) == "vignetting"


# ----------------------------------------------------------------- kinds, open world, report

def test_every_cause_has_a_kind():
    _, causes = _causes(lambda t: None, seed=41)
    kinds = {c.name: c.kind for c in causes}
    assert set(kinds.values()) <= {"instrument", "material", "reference"}
    assert kinds["stray_light"] == "instrument" and kinds["ggx_lobe"] == "material"
    assert kinds["flexible_material"] == "material"
    # the reference's BRDF is a calibration step, not a cause (tests/test_diagnose_reference.py)
    assert "reference_brdf" not in kinds and "reference_brdf" not in KINDS


def test_structure_test_flat_and_structured():
    rng = np.random.default_rng(4)
    x = rng.uniform(0, 1, 20_000)
    z = rng.normal(size=x.size)
    t = structure_test(x, z)
    assert t["p"] > 1e-4
    t = structure_test(x, z + 0.5 * (x > 0.5), 0.05 * (x > 0.5))
    assert t["p"] < 1e-10 and abs(t["effect"] - 0.05) < 0.005


def test_null_table_leaves_no_unexplained_structure():
    m, causes = _causes(lambda t: None, seed=42)
    ue = unexplained(m)
    assert not any(e["significant"] for e in ue), [(e["variable"], e["effect"], e["p"]) for e in ue]
    assert open_world_verdict(verdict(causes), None, ue) == "none"


def test_training_bins_and_bin_factor():
    """Bins come from the training rows only (held-out rows beyond their range take the edge bin, a
    value they never took none); the fitted relative correction of a noise-free step is the step."""
    x = np.r_[np.linspace(0.0, 1.0, 1000), 2.0, np.nan]
    train = np.r_[np.ones(1000, bool), False, False]
    idx, nb = training_bins(x, train)
    assert nb == 10 and idx[-2] == 9 and idx[-1] == -1 and idx[0] == 0
    d, nd = training_bins(np.array([5.0, 6.0, 7.0, 9.0]), np.array([True, True, True, False]))
    assert nd == 3 and d.tolist() == [0, 1, 2, -1]
    pred = 2.0 + np.nan_to_num(x)
    res = pred * 0.05 * (np.nan_to_num(x) >= 0.5)
    g = bin_factor(idx, nb, res, pred, np.ones_like(pred), train)
    np.testing.assert_allclose(g[:-1], 0.05 * (x[:-1] >= 0.5), atol=1e-12)
    assert g[-1] == 0.0


def test_structure_that_does_not_transfer_across_leds_is_not_significant():
    """A 5 % bump in a band of distance from the optical centre that lies elsewhere under each LED
    (as a glossy material's misfit follows its highlight across the image): on all rows its bin means
    are far from zero and spread by more than the former effect bound (the former in-sample rule, chi^2
    p below its level and effect above EFFECT_MIN_FORMER, called it significant), but a function of the
    distance fitted on one LED predicts the other LED worse: not significant, and no verdict."""
    from glossrig.core.diagnose.catalogue import vignetting_factor

    data, ward = synthetic_brdf(40)
    t = data.table
    r = np.sqrt(vignetting_factor(t["u"] + 1.0, t["v"] + 1.0, data.image_size, data.principal_point))
    lo = np.where(t["led"] == t["led"].min(), np.quantile(r, 0.2), np.quantile(r, 0.6))
    t["f"] = t["f"] * (1 + 0.05 * ((r > lo) & (r < lo + 0.1 * np.ptp(r))))
    m = BrdfModel.build(data, ward)
    causes = brdf_causes(m)
    ue = unexplained(m, after=retested_cause(causes, verdict(causes)))
    e = next(x for x in ue if x["variable"] == "distance_from_optical_centre" and not x.get("after"))
    assert e["p"] < 1e-10 and e["effect"] > EFFECT_MIN_FORMER, e
    assert not e["significant"] and e["gain"] < 0 and min(e["fold_gains"]) < 0, e
    assert final_verdict(causes, ue) == verdict(causes) == "none", [(x["variable"], x["gain"]) for x in ue]


def _cause(name, gain, space="brdf", sig=True, blocked=None):
    c = CauseResult(name, space, "doc", {"x": 1.0}, {"x": 0.1}, 1.0 - gain, 1.0,
                    [gain, gain] if sig else [gain, -gain], 0)
    c.blocked_by = blocked
    return c


def test_verdict_rules_and_report_fields(tmp_path):
    flex = _cause("flexible_material", 0.4)
    ggx = _cause("ggx_lobe", 0.3)
    stray = _cause("stray_light", 0.5, blocked="flexible_material")
    assert verdict([flex, stray]) == "flexible_material"           # blocked instrument cause is not named
    assert verdict([flex, ggx, stray]) == "flexible_material"        # the material model that predicts best
    assert verdict([_cause("flexible_material", 0.2), ggx, stray]) == "ggx_lobe"
    assert [c.name for c in ranking([ggx, stray, _cause("hot_pixels", 0.2, "pixels"), flex])] == [
        "hot_pixels", "flexible_material", "ggx_lobe"]                  # sensor first, then by gain; blocked left out
    assert verdict([_cause("black_level_offset", 0.01, "frames"), flex]) == "black_level_offset"
    entry = {"variable": "axis_position", "space": "brdf", "effect": 0.05, "p": 1e-30, "significant": True}
    flat = dict(entry, variable="theta_h", effect=0.001, p=0.5, significant=False)
    assert open_world_verdict("none", None, [entry]) == "unexplained"
    assert open_world_verdict("ggx_lobe", "material", [entry]) == "unexplained"
    assert open_world_verdict("vignetting", "instrument", [entry]) == "vignetting"
    assert open_world_verdict("none", None, [flat]) == "none"
    rep = write_report(tmp_path, [flex, stray, _cause("vignetting", -0.01, sig=False)], {"brdf": 1.0}, {}, {},
                       plots=False, unexplained=[entry, flat], calibration={"heldout_error": 1.02})
    d = read_report(tmp_path)
    assert d["verdict"] == rep["verdict"] == "unexplained"
    assert {c["kind"] for c in d["causes"]} == {"material", "instrument"}
    assert [u["variable"] for u in d["unexplained"]] == ["axis_position", "theta_h"]
    assert set(d["unexplained"][0]) >= {"variable", "effect", "significant"}
    assert d["calibration"]["heldout_error"] == pytest.approx(1.02)
    assert d["ranking"] == ["flexible_material"]                      # the blocked stray light is not ranked
    assert "axis_position" in (tmp_path / "report.md").read_text()
    json.dumps(d)


def _material(name, gain, folds, robust_gain):
    """A material-model cause with held-out ``gain`` (squared normalised), per-fold gains ``folds`` and a
    robust (median relative residual) held-out gain ``robust_gain``."""
    c = CauseResult(name, "brdf", "doc", {}, {}, 1.0 - gain, 1.0, list(folds), 0)
    c.robust = {"base": 0.1, "error": 0.1 * (1 - robust_gain), "gain": robust_gain, "fold_gains": []}
    return c


#: the flexible material model's held-out fold gains on the rgl study's ilm_l3_37_matte_rgb (8 middle-row
#: LEDs; pooled gain 0.136, threshold 0.042; its departure from Ward is +57 % against the true BRDF): one
#: LED, predicted by extrapolation from LEDs all on one side of it in theta_d, loses
MATTE_FOLDS = [0.305, 0.166, 0.069, 0.197, -0.091, 0.039, 0.092, 0.413]


def test_one_extrapolating_led_fold_does_not_veto_a_material_departure():
    """A material departure that gains held-out on 7 of 8 LEDs and loses on the one predicted by
    extrapolation is named (sign test at 5 %: 7 of 8 has p = 0.035); under the former every-fold rule
    it was not, and the verdict was "none". Two failed folds of 8 (p = 0.145), one of 7 or fewer, and
    one of the two folds of a two-LED capture (the null captures of validation/diagnose/
    calibration_check.md) still veto."""
    flex = _material("flexible_material", 0.136, MATTE_FOLDS, 0.05)
    assert not all(g > 0 for g in MATTE_FOLDS)                       # the former rule's veto
    assert flex.significant and verdict([flex]) == "flexible_material"

    from glossrig.core.diagnose.catalogue import FOLD_SIGN_ALPHA, allowed_failed_folds, consistent_folds

    assert FOLD_SIGN_ALPHA == 0.05
    assert [allowed_failed_folds(n) for n in range(1, 13)] == [0] * 7 + [1, 1, 1, 2, 2]
    two = list(MATTE_FOLDS)
    two[7] = -0.04
    assert not consistent_folds(two) and not _material("flexible_material", 0.136, two, 0.05).significant
    assert not consistent_folds(MATTE_FOLDS[1:]) and not consistent_folds([0.3, -0.1])
    assert consistent_folds([0.3, 0.1]) and not consistent_folds([])
    # the fold rule does not lower the pooled threshold: 7 of 8 positive folds but a pooled gain below it
    assert not _material("flexible_material", 0.015, MATTE_FOLDS, 0.05).significant


#: the grazing term's held-out fold gains on the rgl study's chm_mint_rgb (8 middle-row LEDs, pooled gain
#: 0.285, threshold 0.022; +39.2 % against the true BRDF, the best extension): squared normalised score, and
#: median relative residual per LED (robust gain 0.398)
MINT_FOLDS = [0.298, 0.451, 0.412, -0.306, -1.516, 0.395, 0.513, 0.391]
MINT_ROBUST_FOLDS = [0.082, 0.201, 0.47, 0.443, 0.494, 0.455, 0.361, 0.217]


def test_a_material_model_may_carry_the_fold_rule_on_its_robust_folds():
    """A material model that lowers the median relative residual on every held-out LED is consistent even
    where two LEDs' squared normalised scores lose (chm_mint's grazing term: named instead of a Beckmann
    lobe that gains +12.7 % against the truth); an instrument cause with the same figures is not - its
    evidence is structure, not a better typical row. Two failed robust folds of 8 still veto, and the
    pooled threshold and a positive robust gain are still required."""
    from glossrig.core.diagnose.catalogue import consistent_folds

    assert not consistent_folds(MINT_FOLDS)                           # the squared score alone vetoes
    graze = _material("grazing_lobe", 0.285, MINT_FOLDS, 0.398)
    graze.robust["fold_gains"] = list(MINT_ROBUST_FOLDS)
    assert graze.folds_consistent and graze.significant
    beck = _material("beckmann_lobe", 0.056, [0.036, 0.072, 0.134, -0.49, 0.2, 0.166, 0.143, 0.041], 0.116)
    assert verdict([beck, graze]) == "grazing_lobe"
    stray = CauseResult("stray_light", "brdf", "doc", {}, {}, 1.0 - 0.285, 1.0, list(MINT_FOLDS), 1)
    stray.robust = dict(graze.robust)
    assert stray.kind == "instrument" and not stray.significant
    two = list(MINT_ROBUST_FOLDS)
    two[0] = two[1] = -0.05
    graze.robust["fold_gains"] = two
    assert not graze.folds_consistent and not graze.significant
    # consistent robust folds do not lower the other requirements: each case fails on that requirement alone
    low = _material("grazing_lobe", 0.015, MINT_FOLDS, 0.398)            # pooled gain below the threshold
    worse = _material("grazing_lobe", 0.285, MINT_FOLDS, -0.01)          # median residual not lowered
    for c in (low, worse):
        c.robust["fold_gains"] = list(MINT_ROBUST_FOLDS)
        assert c.folds_consistent and not c.significant


def _heldout(pooled, fold_errors, rel_residuals):
    """A HeldOut of 8 folds of 10 rows at y = 1, each fold's prediction 1 + its relative residual."""
    from glossrig.core.diagnose.catalogue import HeldOut

    preds = []
    for k, r in enumerate(rel_residuals):
        test = np.zeros(80, bool)
        test[10 * k:10 * k + 10] = True
        preds.append((test, np.full(80, 1.0 + r)))
    return HeldOut(pooled, list(fold_errors), preds)


def test_the_material_an_instrument_cause_is_fitted_on_passes_the_material_rule():
    """instrument_bases judges a candidate material as a material cause is judged: chm_mint's grazing term
    (squared normalised score lost on LEDs 8 and 9, median relative residual lowered on all 8) passes, so the
    instrument causes are fitted on it, not on the Ward lobe whose misfit they could take up. Two failed
    robust folds, a median residual not lowered, or a pooled gain under the threshold each still fail."""
    from glossrig.core.diagnose.catalogue import THRESHOLDS, passes_as_material

    t, pen = THRESHOLDS["brdf"]
    thr = t + pen * 1                                   # the grazing term: one extra parameter
    y = np.ones(80)
    ward = _heldout(1.0, [1.0] * 8, [0.2] * 8)
    graze = _heldout(1 - 0.285, [1 - g for g in MINT_FOLDS], [0.2 * (1 - g) for g in MINT_ROBUST_FOLDS])
    assert passes_as_material(ward, graze, y, thr)
    two = list(MINT_ROBUST_FOLDS)
    two[0] = two[1] = -0.05
    assert not passes_as_material(ward, _heldout(1 - 0.285, graze.folds, [0.2 * (1 - g) for g in two]), y, thr)
    # consistent normalised folds but the median relative residual raised: not a better material
    assert not passes_as_material(ward, _heldout(0.7, [0.7] * 8, [0.21] * 8), y, thr)
    # every fold and the median improved, pooled gain under the threshold
    assert not passes_as_material(ward, _heldout(1 - thr / 2, [1 - thr / 2] * 8, [0.1] * 8), y, thr)
    assert passes_as_material(ward, _heldout(1 - 2 * thr, [1 - 2 * thr] * 8, [0.1] * 8), y, thr)


def test_material_models_are_ranked_by_the_robust_heldout_gain():
    """Among significant material models the one that lowers the median held-out relative residual most
    is named - the issue's measure against the true BRDF - not the one with the largest squared
    normalised gain (the rgl study's cc_ibiza_sunset: flexible 0.819, GGX 0.784 held-out; against the
    truth GGX +67.8 %, flexible +32.9 %). A material model that lowers the squared score but not the
    median relative residual is not significant; an eligible instrument cause still comes before the
    material models, and causes without a robust score keep the order by gain."""
    flex = _material("flexible_material", 0.819, [0.8] * 8, 0.30)
    ggx = _material("ggx_lobe", 0.784, [0.78] * 8, 0.55)
    assert verdict([flex, ggx]) == "ggx_lobe"
    assert [c.name for c in ranking([flex, ggx])] == ["ggx_lobe", "flexible_material"]
    worse = _material("beckmann_lobe", 0.065, [0.05] * 8, -0.02)
    assert not worse.significant and verdict([worse]) == "none"
    vig = _cause("vignetting", 0.9)
    assert vig.kind == "instrument" and verdict([flex, ggx, vig]) == "vignetting"
    assert verdict([_cause("flexible_material", 0.4), _cause("ggx_lobe", 0.3)]) == "flexible_material"


def test_material_causes_carry_the_robust_heldout_score():
    """Every material model of the pipeline reports its robust held-out score; on a grazing rise the
    flexible model lowers the median held-out relative residual."""
    _, causes = _causes(_grazing)
    by = {c.name: c for c in causes}
    for name in ("flexible_material", "ggx_lobe", "beckmann_lobe", "grazing_lobe", "fresnel"):
        r = by[name].robust
        assert r is not None and set(r) >= {"base", "error", "gain", "fold_gains"}, name
        assert len(r["fold_gains"]) == len(by[name].fold_gains), name
    assert by["flexible_material"].robust_gain > 0, by["flexible_material"].robust
    assert json.dumps(by["flexible_material"].to_json()["robust"])


# ----------------------------------------------------------------- Beckmann / Cook-Torrance lobe

def test_beckmann_lobe_is_normalised_reciprocal_and_fitted():
    from glossrig.core.diagnose.material_models import beckmann_lobe, beckmann_ndf, fit_lobe

    from test_material_models import _angles, _args, _rig_like
    from glossrig.core.models.angles import local_direction

    th = np.linspace(0, np.pi / 2, 4001)[1:-1]
    ph = np.linspace(0, 2 * np.pi, 721)[:-1]
    T, P = np.meshgrid(th, ph, indexing="ij")
    total = np.trapezoid((beckmann_ndf(T, P, 0.3, 0.1, 0.7) * np.cos(T) * np.sin(T)).sum(axis=1)
                         * (2 * np.pi / len(ph)), th)
    assert abs(total - 1) < 0.01, total
    rng = np.random.default_rng(1)
    wi = local_direction(rng.uniform(0, 1.4, 3000), rng.uniform(0, 2 * np.pi, 3000))
    wo = local_direction(rng.uniform(0, 1.4, 3000), rng.uniform(0, 2 * np.pi, 3000))
    np.testing.assert_allclose(beckmann_lobe(*_args(_angles(wi, wo)), 0.2, 0.07, 0.9),
                               beckmann_lobe(*_args(_angles(wo, wi)), 0.2, 0.07, 0.9), rtol=1e-9)
    a = _rig_like(3000, np.random.default_rng(5))
    y = 0.5 / np.pi + 0.3 * beckmann_lobe(*_args(a), 0.3, 0.15, 0.3)
    f = fit_lobe(a, y, np.ones_like(y), "beckmann", start=(0.1, 0.1, 0.0))
    assert abs(f.alpha_x / 0.3 - 1) < 0.01 and abs(f.alpha_y / 0.15 - 1) < 0.01 and abs(f.rho_d / 0.5 - 1) < 0.01


# ----------------------------------------------------------------- shutter (exposure-time) error

def test_shutter_error_found_with_magnitude():
    from glossrig.core.diagnose.frames import frame_causes

    from test_diagnose import synthetic_frames, winner

    delta = float(np.random.default_rng(8).uniform(2e-5, 8e-5))        # 8-32 % of the shortest exposure
    causes = frame_causes(synthetic_frames(8, shutter=delta))
    w = winner(causes)
    assert w is not None and w.name == "shutter_error" and w.kind == "instrument", [
        (c.name, round(c.gain, 5), c.significant) for c in causes]
    assert abs(w.params["delta_s"] - delta) < 0.15 * delta, (w.params, delta)
    assert winner(frame_causes(synthetic_frames(9))) is None


def test_unexplained_variables_are_ordered_by_held_out_gain():
    """The variables "unexplained" names, strongest first by held-out gain, not by the in-sample effect
    (the blind study's axis step on sample_2_6: phi_h and the axis position spread alike in sample, 0.0534 and
    0.0530, the axis position predicts the held-out LED better, 0.904 against 0.893); the named cause's own
    residual's entries (``after``) decide first."""
    from glossrig.core.diagnose.unexplained import deciding_variables

    e = [{"variable": "phi_h", "significant": True, "gain": 0.893, "effect": 0.0534, "space": "brdf"},
         {"variable": "axis_position", "significant": True, "gain": 0.904, "effect": 0.0530, "space": "brdf"},
         {"variable": "theta_h", "significant": False, "gain": 0.95, "effect": 0.2, "space": "brdf"}]
    assert deciding_variables("none", None, e) == ["axis_position", "phi_h"]
    after = [dict(e[0], after="led_emission", gain=0.01), dict(e[1], after="led_emission", gain=0.76)]
    assert deciding_variables("led_emission", "instrument", e + after)[0] == "axis_position"
    after = [dict(e[0], after="led_emission", gain=0.5)]
    assert deciding_variables("led_emission", "instrument", e + after) == ["phi_h", "axis_position"]


def _robust_material(name, folds, robust_folds):
    """A significant material model with its held-out fold gains and robust fold gains (robust gain: their mean)."""
    c = _material(name, float(np.mean(folds)), folds, float(np.mean(robust_folds)))
    c.robust["fold_gains"] = list(robust_folds)
    return c


def test_the_flexible_model_must_beat_the_best_named_model_significantly():
    """The flexible model comes first only when its robust fold gains beat the best named model's in a
    one-sided paired t-test at 5 % (report.parsimonious). The fold gains are those of the rgl study's
    diagnoses (validation/diagnose/rgl_study.md, 8 middle-row LEDs): on vch_golden_yellow the flexible
    model led GGX by 2 points of robust gain with t = 1.2 (against the truth GGX was as good or better), so GGX
    is named; on ilm_l3_37_matte it led by 5 points with t = 2.1 (against the truth +88 % against +22 %),
    so it stays first. A named model that leads is not moved, nor is anything but the material models."""
    from glossrig.core.diagnose.report import parsimonious

    vch_flex = _robust_material("flexible_material", [0.565, 0.721, 0.76, 0.734, 0.807, 0.751, 0.814, 0.686],
                                [0.32, 0.514, 0.734, 0.733, 0.664, 0.751, 0.673, 0.333])
    vch_ggx = _robust_material("ggx_lobe", [0.572, 0.816, 0.786, 0.778, 0.72, 0.822, 0.856, 0.732],
                               [-0.676, 0.589, 0.785, 0.721, 0.497, 0.777, 0.765, -0.019])
    assert vch_flex.robust_gain > vch_ggx.robust_gain and vch_flex.eligible and vch_ggx.eligible
    assert [c.name for c in ranking([vch_flex, vch_ggx])] == ["ggx_lobe", "flexible_material"]
    matte_flex = _robust_material("flexible_material", [0.276, 0.154, 0.143, 0.337, -0.048, 0.228, 0.152, 0.294],
                                  [0.581, 0.725, 0.667, 0.722, 0.728, 0.677, 0.715, 0.743])
    matte_ggx = _robust_material("ggx_lobe", [0.232, 0.097, 0.121, 0.302, 0.314, 0.201, 0.113, 0.182],
                                 [0.552, 0.669, 0.701, 0.515, 0.471, 0.613, 0.734, 0.683])
    assert verdict([matte_ggx, matte_flex]) == "flexible_material"
    # the paired test, not the gap: the same mean lead with folds that agree less is not significant
    d = np.array(matte_flex.robust["fold_gains"]) - np.array(matte_ggx.robust["fold_gains"])
    noisy = _robust_material("flexible_material", matte_flex.fold_gains,
                             list(np.array(matte_ggx.robust["fold_gains"]) + d.mean() + 3 * (d - d.mean())))
    assert noisy.robust_gain == pytest.approx(matte_flex.robust_gain)
    assert verdict([matte_ggx, noisy]) == "ggx_lobe"
    assert parsimonious([vch_ggx, vch_flex]) == [vch_ggx, vch_flex]
    vig = _cause("vignetting", 0.9)
    assert [c.name for c in ranking([vch_flex, vig, vch_ggx])] == ["vignetting", "ggx_lobe", "flexible_material"]
