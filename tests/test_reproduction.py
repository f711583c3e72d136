"""Reproduction model (thesis ch. 6, 7.2.1): core maths on synthetic data with known
answers, then the thesis's own samples (ward_params.csv, coverages.csv) on a small
angle set. The full cross-validation of Table 7.1 is the slow test at the end and
the study in validation/reproduction."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from glossrig.core.reproduction import model as R
from glossrig.core.models.angles import brdf_angles, local_direction
from glossrig.core.errors import InputError
from glossrig.core.models.ward import WardParams, ward_from_angles

from conftest import SHARED, require_shared

THESIS = SHARED / "data" / "thesis"
WARD_CSV = THESIS / "ward_params.csv"
COV_CSV = THESIS / "coverages.csv"
NEEDS_THESIS = pytest.mark.needs_shared("data/thesis/ward_params.csv", "data/thesis/coverages.csv")

BASE1 = WardParams(0.0374, 0.0064, 0.035, 0.0492, 2.52)            # thesis sample 0/6
BASE2 = WardParams(0.055, 0.026, 0.25, 0.029, 2.57)


@pytest.fixture(scope="module")
def local_angles() -> R.AngleSet:
    """A small hand-made angle set (core/models/angles.py): incident directions on a
    zenith x azimuth grid, outgoing ones at and around the mirror direction, so
    both the specular peak and the flanks are sampled."""
    rows = []
    n, t = np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0])
    for th in np.radians([5, 15, 25, 35, 45, 55]):
        for ph in np.radians(np.arange(0, 360, 30)):
            for dth in np.radians([-20, -8, -3, 0, 3, 8, 20]):
                for dph in np.radians([-10, 0, 10]):
                    wi = local_direction(th, ph)
                    wo = local_direction(np.clip(th + dth, 0.01, 1.4), ph + np.pi + dph)
                    a = brdf_angles(wi, wo, n, t)
                    rows.append([float(a[k]) for k in ("theta_in", "theta_out", "theta_h", "phi_h")])
    arr = np.array(rows)
    return R.AngleSet(*arr.T, info={"source": "test fixture"})


@pytest.fixture(scope="module")
def samples() -> R.SampleSet:
    require_shared("data/thesis/ward_params.csv", "data/thesis/coverages.csv")
    return R.load_samples(WARD_CSV, COV_CSV)


@pytest.fixture(scope="module")
def rig_angles_small() -> R.AngleSet:
    return R.rig_angles(scale=0.02, max_samples=500)


@pytest.fixture(scope="module")
def detection(samples, rig_angles_small):
    return R.detect_outliers(samples, rig_angles_small, n_starts=1)


# ------------------------------------------------------------------ maths on synthetic data

def test_ward_gradient_matches_finite_differences(local_angles):
    p = WardParams(0.05, 0.02, 0.12, 0.04, 2.3)
    g = R.ward_gradient(p, local_angles)
    x = np.array([p.rho_d, p.rho_s, p.alpha_x, p.alpha_y, p.lobe_rotation])
    for k in range(5):
        h = 1e-6 * max(abs(x[k]), 1e-3)
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        fd = (R.ward_values(WardParams(*xp), local_angles) - R.ward_values(WardParams(*xm), local_angles)) / (2 * h)
        np.testing.assert_allclose(g[:, k], fd, rtol=1e-5, atol=1e-7 * np.abs(fd).max())


def test_ward_values_use_core_ward(local_angles):
    a = local_angles
    np.testing.assert_array_equal(R.ward_values(BASE2, a), ward_from_angles(a.theta_in, a.theta_out, a.theta_h,
                                                                             a.phi_h, BASE2))


def test_clip_is_eq_6_5():
    np.testing.assert_array_equal(R.clip_values(np.array([0.5, 1.0, 3.0]), 1.0), [0.5, 1.0, 1.0])
    np.testing.assert_array_equal(R.clip_values(np.array([0.5, 3.0]), None), [0.5, 3.0])


def test_best_mix_recovers_known_coverage(local_angles):
    f1, f2 = R.ward_values(BASE1, local_angles), R.ward_values(BASE2, local_angles)
    truth = np.array([0.0, 0.2, 0.55, 1.0])
    targets = f1[None] + truth[:, None] * (f2 - f1)[None]
    np.testing.assert_allclose(R.best_mix(targets, f1, f2, None), truth, atol=1e-12)
    # beyond the bases the mix clamps to [0, 1]
    outside = np.array([f1 - 0.5 * (f2 - f1), f1 + 1.7 * (f2 - f1)])
    np.testing.assert_allclose(R.best_mix(outside, f1, f2, None), [0.0, 1.0])
    # a clip that bites takes the numeric path and still finds the coverage
    level = float(np.quantile(np.maximum(f1, f2), 0.9))
    got = R.best_mix(R.clip_values(targets, level), f1, f2, level)
    np.testing.assert_allclose(got, truth, atol=1e-4)


def test_fit_bases_recovers_a_known_second_base(local_angles):
    """Targets that are exact mixes of BASE1 and BASE2: eq. 6.6 must find BASE2 and
    the mixing ratios, started from a different material (thesis sample 6/6)."""
    f1, f2 = R.ward_values(BASE1, local_angles), R.ward_values(BASE2, local_angles)
    truth = np.array([0.0, 0.15, 0.3, 0.5, 0.7, 1.0])
    targets = f1[None] + truth[:, None] * (f2 - f1)[None]
    start = WardParams(0.0474, 0.0477, 0.4572, 0.0314, 2.58)
    bf = R.fit_bases(targets, f1, local_angles, [start], truth * 0.8 + 0.1, clip=1.0)
    got = np.array([bf.base2.rho_d, bf.base2.rho_s, bf.base2.alpha_x, bf.base2.alpha_y, bf.base2.lobe_rotation])
    want = np.array([BASE2.rho_d, BASE2.rho_s, BASE2.alpha_x, BASE2.alpha_y, BASE2.lobe_rotation])
    np.testing.assert_allclose(got, want, rtol=2e-3)
    np.testing.assert_allclose(bf.effective_b2, truth, atol=2e-3)
    assert bf.cost < 1e-10


def test_fit_etn_recovers_a_known_sigmoid():
    truth = R.ETN((0.12, 7.1, 0.11, -0.108))
    x = np.linspace(0, 1, 8)
    etn = R.fit_etn(x, truth.raw(x))
    grid = np.linspace(0, 1, 101)
    np.testing.assert_allclose(etn.raw(grid), truth.raw(grid), atol=1e-4)
    assert etn.increasing and not etn.refit_bounded


def test_etn_pole_guard():
    assert not R._pole_free((1.0, 1.0, -0.7, 0.0))       # g3 + exp(-x) crosses 0 at x = 0.36
    assert R._pole_free((1.0, 1.0, 1.0, 0.0))
    # data the unbounded fit answers with a pole: the guard refits with g3 >= 0
    x = [0, 0.25, 0.5, 0.75, 1]
    etn = R.fit_etn(x, [1, 0.1, 0.3, 0.2, 1])
    assert etn.refit_bounded and R._pole_free(etn.gamma)
    assert np.all(np.isfinite(etn.raw(np.linspace(0, 1, 1001))))


def test_etn_output_is_a_coverage():
    etn = R.ETN((4.0, 5.0, 1.0, -2.5))     # raw values run from -0.5 to 1.47
    v = etn(np.linspace(0, 1, 11))
    assert v.min() >= 0 and v.max() <= 1 and v[0] == 0 and v[-1] == 1


def test_order_outliers():
    names = ["a", "b", "c", "d", "e", "f"]
    nom = [0, 0.2, 0.4, 0.6, 0.8, 1.0]
    assert R.order_outliers(names, nom, [0, 0.1, 0.3, 0.5, 0.7, 1.0], "a") == ([], [])
    # one sample far out of order, above two that follow it (thesis 4/6: "rather close to 6/6")
    n7, nom7 = names + ["g"], [0, 0.2, 0.4, 0.5, 0.6, 0.8, 1.0]
    flagged, viol = R.order_outliers(n7, nom7, [0, 0.1, 0.3, 0.95, 0.5, 0.7, 1.0], "a")
    assert flagged == ["d"] and {v["lower_nominal"] for v in viol} == {"d"} and len(viol) == 2
    # a swap within the tolerance is a tie, not a violation
    assert R.order_outliers(names, nom, [0, 0.1, 0.33, 0.31, 0.7, 1.0], "a") == ([], [])
    # a real swap of two neighbours: either could go, so neither is flagged
    flagged, viol = R.order_outliers(names, nom, [0, 0.1, 0.5, 0.3, 0.7, 1.0], "a")
    assert flagged == [] and len(viol) == 1
    # base 1 is never flagged even when it is the odd one out
    flagged, _ = R.order_outliers(names, nom, [0.9, 0.1, 0.3, 0.5, 0.7, 1.0], "a")
    assert "a" not in flagged and flagged == ["b", "c", "d", "e"]


def test_sample_key():
    assert R.sample_key("0/6") == R.sample_key("sample_0_6") == R.sample_key(" Sample 0/6 ") == "0_6"
    assert R.sample_key("4/10") != R.sample_key("4/1")


# ------------------------------------------------------------------ input validation

def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD_COV = "sample,nominal_b2\n0/6,0.0\n1/6,0.17\n3/6,0.5\n6/6,1.0\n"


@pytest.mark.parametrize("cov,msg", [
    ("", "empty"),
    ("sample,nominal_b2\n", "no rows"),
    ("sample,coverage\n0/6,0\n", "lacks column 'nominal_b2'"),
    ("sample,nominal_b2\n0/6,zero\n1/6,0.17\n", "not a finite number"),
    ("sample,nominal_b2\n0/6,0.0\n1/6,1.2\n", "outside [0, 1]"),
    ("sample,nominal_b2\n0/6,0.0\n1/6,-0.1\n", "outside [0, 1]"),
    ("sample,nominal_b2\n0/6,0.0\n9/9,0.5\n", "unknown sample '9/9'"),
    ("sample,nominal_b2\n0/6,0.0\n0/6,0.5\n", "duplicate sample"),
    ("sample,nominal_b2\n1/6,0.17\n3/6,0.5\n", "exactly one with nominal_b2 = 0"),
    ("sample,nominal_b2,nominal_b1\n0/6,0.0,1.0\n1/6,0.17,0.5\n", "must be 1"),
    ('sample,nominal_b2\n"0/6,0.0\n', "not valid CSV"),
])
@NEEDS_THESIS
def test_bad_coverage_tables(tmp_path, cov, msg):
    p = _write(tmp_path, "cov.csv", cov)
    with pytest.raises(InputError) as e:
        R.load_samples(WARD_CSV, p)
    assert msg in str(e.value) and "cov.csv" in str(e.value)


@pytest.mark.parametrize("ward,msg", [
    ("name,rho_d,rho_s,alpha_x\nsample_0_6,0.03,0.006,0.03\n", "lacks column(s) alpha_y"),
    ("name,rho_d,rho_s,alpha_x,alpha_y\nsample_0_6,0.03,x,0.03,0.04\n", "not a finite number"),
    ("name,rho_d,rho_s,alpha_x,alpha_y\nsample_0_6,0.03,0.006,-0.03,0.04\n", "must be > 0"),
    ("name,rho_d,rho_s,alpha_x,alpha_y\nsample_0_6,0.03,0.006,0.03,0.04\n0/6,0.03,0.006,0.03,0.04\n", "duplicate"),
])
def test_bad_ward_tables(tmp_path, ward, msg):
    p = _write(tmp_path, "ward.csv", ward)
    c = _write(tmp_path, "cov.csv", GOOD_COV)
    with pytest.raises(InputError) as e:
        R.load_samples(p, c)
    assert msg in str(e.value) and "ward.csv" in str(e.value)


def test_missing_files(tmp_path):
    with pytest.raises(InputError, match="not found"):
        R.load_samples(tmp_path / "nope.csv", COV_CSV)


def test_too_few_samples(tmp_path, local_angles, samples):
    with pytest.raises(InputError, match="at least 4 samples"):
        R.fit_model(samples.subset(["0/6", "3/6", "6/6"]), local_angles)


def test_model_json_rejects_foreign_files(tmp_path):
    p = _write(tmp_path, "m.json", json.dumps({"kind": "something else"}))
    with pytest.raises(InputError, match="expected a reproduction model"):
        R.ReproductionModel.load(p)
    p = _write(tmp_path, "m2.json", "{not json")
    with pytest.raises(InputError, match="model file is not readable JSON"):
        R.ReproductionModel.load(p)
    p = _write(tmp_path, "m3.json", json.dumps({"kind": R.KIND, "etn": {"gamma": [1, 2]}}))
    with pytest.raises(InputError):
        R.ReproductionModel.load(p)


# ------------------------------------------------------------------ the thesis's samples

def test_thesis_samples_load(samples):
    assert samples.names == ("0/6", "1/6", "2/6", "4/10", "3/6", "4/6", "7/10", "5/6", "6/6")
    assert samples.base1_name == "0/6"
    assert samples.ward[0].rho_d == pytest.approx(0.0374)       # the corrected typo
    assert samples.interior() == ["1/6", "2/6", "4/10", "3/6", "4/6", "7/10", "5/6"]


def test_clip_never_bites_on_thesis_samples(samples, rig_angles_small):
    """Why methods 1 and 3 of Table 7.1 coincide here: at the rig's angles no
    fabricated sample's Ward BRDF reaches eq. 6.5's level of 1.0."""
    peak = max(float(R.ward_values(p, rig_angles_small).max()) for p in samples.ward)
    assert 0.1 < peak < R.CLIP_LEVEL


def test_outlier_detection_flags_4_6(detection):
    assert detection["flagged"] == ["4/6"]
    first = detection["rounds"][0]
    assert first["violations"] and all("4/6" in (v["lower_nominal"], v["higher_nominal"])
                                       for v in first["violations"])
    assert detection["rounds"][-1]["flagged"] == []


def test_thesis_model_is_monotone(detection):
    m = detection["model"]
    assert m.fit_info["samples"] == ["0/6", "1/6", "2/6", "4/10", "3/6", "7/10", "5/6", "6/6"]
    eff = [t["effective_b2"] for t in m.training]
    assert eff[0] == pytest.approx(0.0, abs=1e-6)                 # base 1 is sample 0/6
    assert all(b >= a - 1e-6 for a, b in zip(eff, eff[1:]))       # Table 6.4: monotone
    assert m.etn.increasing
    for t in m.training:
        assert abs(t["etn_nominal_b2"] - t["nominal_b2"]) < 0.15


def test_model_roundtrip_and_prediction(detection, tmp_path, samples):
    m = detection["model"]
    path = tmp_path / "model.json"
    m.save(path)
    doc = json.loads(path.read_text())
    assert doc["kind"] == "glossrig.reproduction_model"
    assert doc["etn"]["form"] == R.ETN_FORM and len(doc["etn"]["gamma"]) == 4
    assert set(doc["base2"]["ward"]) == {"rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation"}
    m2 = R.ReproductionModel.load(path)
    for name in ("1/6", "7/10"):
        p = samples.ward[samples.index(name)]
        a, b = m.predict(p), m2.predict(p)
        assert b.nominal_b2 == pytest.approx(a.nominal_b2, abs=1e-6)
        assert b.gamut == "in"
    # the ETN the fabrication code reads from the same file (the contract of model.json)
    np.testing.assert_allclose(R.load_etn(path)(np.array([0.2, 0.6])), m.etn(np.array([0.2, 0.6])))


def test_prediction_gamut(detection):
    m = detection["model"]
    assert m.predict(BASE1).nominal_b2 < 0.02
    sheet = WardParams(0.1198, 0.0708, 0.0031, 0.006, 3.26)       # thesis transparency sheet
    pr = m.predict(sheet)
    assert pr.gamut == "out" and pr.gamut_ratio > R.GAMUT_NEAR


def test_leave_one_out_small(samples, rig_angles_small):
    sub = samples.subset(["0/6", "1/6", "3/6", "5/6", "6/6"])
    folds = R.leave_one_out(sub, rig_angles_small, n_starts=1)
    assert [f.left_out for f in folds] == ["1/6", "3/6", "5/6"]
    for f in folds:
        assert f.error == pytest.approx(abs(f.predicted_nominal_b2 - f.nominal_b2))
        assert f.error < 0.3
    st = R.error_stats(folds)
    assert st["error_mean"] == pytest.approx(np.mean([f.error for f in folds]))
    assert st["error_std"] == pytest.approx(np.std([f.error for f in folds]))


@pytest.mark.slow
def test_table_7_1_ordering(samples):
    """Full Table 7.1 on the rig's default angle set: 4/6 is detected, and method 1
    beats method 2 as in the thesis."""
    res = R.cross_validate(samples, R.rig_angles())
    assert res["outliers"] == ["4/6"]
    e = {m["method"]: m["error_mean"] for m in res["methods"]}
    assert e[1] < e[2]
    assert math.isclose(e[1], e[3])     # eq. 6.5 never bites on the published parameters
