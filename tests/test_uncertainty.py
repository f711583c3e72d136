"""The uncertainty budget (core/fitting/uncertainty.py) and the footprint-averaged fit
(core/fitting/footprint_model.py): coverage over seeds on samples with a known misfit,
the footprint bias removed, fit.json round trip, the printed table."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from glossrig.cli.main import main
from glossrig.core.extraction.cylinder import nominal_samples
from glossrig.core.fitting.export import read_fit_json, write_fit_json
from glossrig.core.fitting.fit import PARAM_NAMES, fit_samples, fit_ward, parameter_errors
from glossrig.core.fitting.footprint_model import sample_footprint, table_jacobian
from glossrig.core.fitting.uncertainty import budget_table, coverage, parameter_budget, read_uncertainty
from glossrig.core.models.footprint import footprint_truth
from glossrig.core.models.ward import WardParams, ward_from_angles
from glossrig.core.rig import default_rig_path, load_rig
from glossrig.core.samples import write_samples

TRUTH = WardParams(0.0518, 0.0069, 0.0595, 0.034, 2.47)     # thesis Table 9.1, sample 2/6
N_SEEDS = 60


@pytest.fixture(scope="module")
def geometry():
    """The nominal rig's samples at scale 0.025, one row per 2x2 block (even u, v) as
    extract writes them: 8 LEDs x 4 rotations = 32 LED x rotation blocks."""
    rig = load_rig(default_rig_path())
    geo = nominal_samples(rig, rig.select_leds("middle"), [-45, 0, 45, 90], 0.025)
    return geo[(geo.u % 2 == 0) & (geo.v % 2 == 0)].reset_index(drop=True)


def _table(geo, values):
    df = geo.copy()
    for c in ("r", "g", "b"):
        df[c] = values
    df["weight"] = 1.0
    return df


def test_intervals_cover_the_truth_at_95_percent_over_seeds(geometry):
    """Samples of a known Ward material with 2 % multiplicative noise and a known misfit
    (each LED x rotation block scaled by its own gain error, 2 % RMS: an LED's
    intensity error). Over N seeds the budget's 95 % intervals must hold the truth at a
    rate consistent with 95 %: the 5 estimates of one seed share its data, so the rate
    is taken as N trials at worst, binomial standard deviation sqrt(0.95 0.05 / N),
    and the rate must lie within 3 of them. The noise-only intervals (the fit's
    stderr) must not: the misfit is what the model component is for. And the budget
    must be honest, not inflated: the RMS of error / u within [0.6, 1.5] (1 expected)."""
    groups = geometry.groupby(["led", "rotation"]).ngroup().to_numpy()
    G = int(groups.max()) + 1
    f0 = ward_from_angles(geometry.theta_in, geometry.theta_out, geometry.theta_h, geometry.phi_h, TRUTH)
    covered, noise_covered, ratios = [], [], []
    for seed in range(N_SEEDS):
        rng = np.random.default_rng(seed)
        gain = 1 + 0.02 * rng.standard_normal(G)
        y = f0 * gain[groups] * (1 + 0.02 * rng.standard_normal(f0.size))
        f = fit_ward(geometry, y, starts=[TRUTH], grid=False, groups=groups, led_aperture=0)
        c = coverage(f.uncertainty, TRUTH)
        assert f.uncertainty["budget"]["n_clusters"] == G
        for p in PARAM_NAMES:
            covered.append(c[p]["covered"])
            ratios.append(c[p]["ratio"])
            noise_covered.append(abs(c[p]["error"]) <= 1.96 * f.stderr[p])
    rate = float(np.mean(covered))
    tol = 3 * math.sqrt(0.95 * 0.05 / N_SEEDS)
    assert abs(rate - 0.95) <= tol, (rate, tol)
    assert float(np.mean(noise_covered)) < 0.95 - tol
    rms = float(np.sqrt(np.mean(np.square(ratios))))
    assert 0.6 <= rms <= 1.5, rms


def test_footprint_fit_removes_the_footprint_bias(geometry):
    """Values that are the BRDF averaged over each block's footprint (the luminance kernel
    mapped by the table's own Jacobian): the point model's fit is biased, the
    footprint-averaged fit (the default where the table has u, v, led, rotation) is not;
    the point fit's budget counts the bias in its footprint component."""
    p = WardParams(0.05, 0.02, 0.16, 0.09, 0.7)     # at scale 0.025 a pixel spans ~0.04 in slope
    geo = geometry[geometry.rotation.isin([0.0, 90.0])].reset_index(drop=True)
    y = footprint_truth(geo, p)
    fpr = sample_footprint(table_jacobian(geo))
    point = fit_ward(geo, y, starts=[p], grid=False, footprint=fpr, footprint_fit=False, led_aperture=0)
    fp = fit_ward(geo, y, starts=[p], grid=False, footprint=fpr, led_aperture=0)
    assert fp.footprint["model"] == "footprint-averaged" and point.footprint["model"] == "point"
    assert fp.footprint["rows_with_jacobian"] > 0.9 * len(geo)
    e_pt, e_fp = parameter_errors(point.params, p), parameter_errors(fp.params, p)
    assert abs(e_pt["alpha_y"]) > 0.03
    for k in ("rho_s", "alpha_x", "alpha_y"):
        assert abs(e_fp[k]) < 0.003, (k, e_fp)
    assert e_fp["lobe_rotation_deg"] < 0.1
    u = point.uncertainty["alpha_y"]["components"]["footprint"]
    err = abs(point.params.alpha_y - p.alpha_y)
    assert 0.5 * err < u < 2 * err          # the linearised footprint shift is the bias, to first order
    assert "pixel_footprint" in point.uncertainty["budget"]["footprint_parts"]


def test_budget_components_combination_and_rotation_interval():
    e = parameter_budget("rho_s", 0.01, {"noise": (3e-4, 1000), "model": (4e-4, 9)})
    assert e["combined"] == pytest.approx(5e-4)
    nu = 5e-4 ** 4 / (3e-4 ** 4 / 1000 + 4e-4 ** 4 / 9)                       # Welch-Satterthwaite
    assert e["dof"] == pytest.approx(nu)
    assert e["interval95"] == pytest.approx([0.01 - e["coverage_factor"] * 5e-4, 0.01 + e["coverage_factor"] * 5e-4])
    assert 2.0 < e["coverage_factor"] < 2.3
    r = parameter_budget("lobe_rotation", 0.05, {"noise": (0.1, 1e6)})
    assert r["interval95"][0] < 0 < r["interval95"][1]                          # wraps through 0 (mod pi)
    assert parameter_budget("lobe_rotation", 1.0, {"noise": (2.0, 1e6)})["interval95"] == [0.0, math.pi]
    assert parameter_budget("alpha_x", 0.01, {"noise": (1.0, 1e6)})["interval95"][0] == 0.0
    assert parameter_budget("rho_d", 0.1, {"noise": (math.inf, 1e6)})["interval95"] is None
    assert parameter_budget("lobe_rotation", 0.1, {"noise": (math.inf, 1e6)})["interval95"] == [0.0, math.pi]


def test_canonical_swap_permutes_the_budget(geometry):
    """A truth written with alpha_x < alpha_y: the fit reports the canonical form, and the
    budget's alpha_x is the wide axis's (its interval holds the wide truth)."""
    p = WardParams(0.05, 0.01, 0.03, 0.07, 0.4)
    rng = np.random.default_rng(3)
    y = ward_from_angles(geometry.theta_in, geometry.theta_out, geometry.theta_h, geometry.phi_h, p)
    y = y * (1 + 0.01 * rng.standard_normal(y.size))
    f = fit_ward(geometry, y, starts=[p], grid=False, led_aperture=0)
    u = f.uncertainty
    assert u["alpha_x"]["value"] == pytest.approx(0.07, rel=0.01)
    assert u["alpha_x"]["interval95"][0] < 0.07 < u["alpha_x"]["interval95"][1]
    assert u["alpha_x"]["components"]["noise"] == pytest.approx(f.stderr["alpha_x"])
    assert coverage(u, p)["lobe_rotation"]["error"] == pytest.approx(0, abs=0.01)
    assert "model" in u["budget"]["omitted"]            # no blocks given


def test_calibration_component_from_input_and_round_trip(geometry, tmp_path):
    geo = geometry[geometry.rotation == 0.0].reset_index(drop=True)
    df = _table(geo, ward_from_angles(geo.theta_in, geo.theta_out, geo.theta_h, geo.phi_h, TRUTH)
                * (1 + 0.02 * np.random.default_rng(1).standard_normal(len(geo))))
    cal = {"luminance": {"alpha_x": 1e-3, "rho_d": {"u": 2e-4, "dof": 10}}}
    mf = fit_samples(df, channels=["luminance", "r"], calibration=cal, footprint=False)
    lum, r = mf.fits["luminance"].uncertainty, mf.fits["r"].uncertainty
    assert lum["alpha_x"]["components"]["calibration"] == 1e-3
    assert lum["alpha_x"]["combined"] >= 1e-3
    assert "calibration" not in lum["rho_s"]["components"]
    assert "calibration" in r["budget"]["omitted"] and "calibration" not in r["alpha_x"]["components"]
    path = write_fit_json(mf, tmp_path / "fit.json")
    doc = json.loads(path.read_text())
    for ch in ("luminance", "r"):
        for k in PARAM_NAMES:
            e = doc[ch]["uncertainty"][k]
            assert set(e) >= {"combined", "interval95", "components"}
            assert {"noise", "model", "footprint"} <= set(e["components"])
            assert doc[ch][f"{k}_stderr"] == pytest.approx(e["components"]["noise"])    # old name kept
    back = read_fit_json(path)
    assert back.fits["luminance"].uncertainty == mf.fits["luminance"].uncertainty
    assert back.to_json()["luminance"]["uncertainty"] == doc["luminance"]["uncertainty"]
    assert back.fits["luminance"].footprint == mf.fits["luminance"].footprint
    bad = json.loads(json.dumps(doc["luminance"]["uncertainty"]))
    bad["alpha_x"]["combined"] = -1
    with pytest.raises(ValueError):
        read_uncertainty(bad)


def test_cli_prints_the_budget_table(geometry, tmp_path, capsys):
    geo = geometry[geometry.rotation == 0.0].reset_index(drop=True)
    y = ward_from_angles(geo.theta_in, geo.theta_out, geo.theta_h, geo.phi_h, TRUTH)
    src = write_samples(_table(geo, y * (1 + 0.02 * np.random.default_rng(2).standard_normal(y.size))),
                        tmp_path / "s.parquet")
    cal = tmp_path / "cal.json"
    cal.write_text(json.dumps({"luminance": {"alpha_y": 2e-4}}))
    out = tmp_path / "fit.json"
    assert main(["fit", str(src), "--out", str(out), "--channels", "luminance", "--calibration-uncertainty",
                 str(cal), "--quiet"]) == 0
    text = capsys.readouterr().out
    assert "uncertainty budget" in text
    rows = [ln for ln in text.splitlines() if ln.startswith("luminance ") and ln.split()[1] in PARAM_NAMES]
    assert [ln.split()[1] for ln in rows] == list(PARAM_NAMES)
    assert "95 % interval" in text
    fit = read_fit_json(out).fits["luminance"]
    assert fit.footprint["model"] == "footprint-averaged"
    assert fit.uncertainty["alpha_y"]["components"]["calibration"] == 2e-4
    assert budget_table({"luminance": fit}) in text


def test_budget_of_an_undetermined_parameter_does_not_overflow():
    """A parameter the data cannot determine (a red lobe rotation of a nearly isotropic
    lobe: u ~ 1e80 rad) gave OverflowError in Welch-Satterthwaite's u ** 4 and stopped
    `glossrig fit` with a traceback; its budget is now the whole half-circle."""
    from glossrig.core.fitting.uncertainty import parameter_budget

    b = parameter_budget("lobe_rotation", 1.0, {"noise": (1e80, 1e4), "model": (1e-3, 5.0)})
    assert b["interval95"] == [0.0, math.pi]
    assert b["dof"] is not None and b["dof"] > 1e3        # the dominant component's dof
    b = parameter_budget("alpha_x", 0.1, {"noise": (0.003, 100.0), "model": (0.004, 4.0)})
    # Welch-Satterthwaite by hand: u_c^4 / sum(u_i^4 / nu_i)
    assert b["dof"] == pytest.approx(0.005 ** 4 / (0.003 ** 4 / 100 + 0.004 ** 4 / 4), rel=1e-9)
