"""The base (Ward) fit of diagnose and ``glossrig fit`` on a channel the data show no lobe in (issue 14).

Real failure (rgl study, chm_mint_rgb): the red channel is too dark to measure wherever the
highlight is, and rises toward grazing angles elsewhere. The lobe's exponent is capped
(``glossrig.core.models.ward.EXPONENT_CAP``), so far from its peak a lobe is the floor
``exp(-200) g / (4 pi ax ay)``, ``g = 1 / sqrt(cos theta_in cos theta_out)``; with rho_s
unbounded the fit scaled that floor by ~1e81 into a grazing term, the lobe's peak (where no
sample is) reached 1e84 1/sr, the red fit filled the luminance's missing red values with it
and diagnose's held-out error became 2.4e66. Hand-built data of that kind here: every test
below fails on the fit before RHO_S_MAX and LOBE_UNSEEN (helper B's run of the old code: rho_s
8.6e80 on the channel fit, 1.2e80 on the luminance fit).
"""
from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import lsq_linear

from glossrig.core.diagnose.channels import fill_missing_channels
from glossrig.core.fitting.fit import lobe_albedos
from glossrig.core.errors import InputError
from glossrig.core.fitting.fit import RHO_S_MAX, _nnls2, fit_samples, fit_ward
from glossrig.core.models.ward import WardParams, ward_from_angles

from helpers import geometry, material, noisy

HIGHLIGHT_DEG = 4.0         # rows closer to the mirror direction than this miss the dark channel


def _grazing_channel(geo, seed=0):
    """A channel with no lobe: Lambertian 0.05 plus a rise toward grazing, 0.01 (g - 1), 2 % noise
    (the shape of chm_mint's red channel). Ward's model has no such term."""
    g = 1 / np.sqrt(np.cos(geo["theta_in"].to_numpy()) * np.cos(geo["theta_out"].to_numpy()))
    y = 0.05 / np.pi + 0.01 * (g - 1)
    return y * (1 + 0.02 * np.random.default_rng(seed).standard_normal(y.size))


@pytest.fixture(scope="module")
def geo():
    return geometry(0.04)


def test_nnls2_with_an_upper_bound_matches_a_general_bounded_solver():
    """The closed form of two-column least squares on the box a >= 0, 0 <= b <= b_max equals
    SciPy's bounded solver (lsq_linear), with the bound active or not."""
    rng = np.random.default_rng(3)
    for k in range(40):
        X = np.stack([np.full(30, 1 / np.pi), rng.random(30) ** (1 + 3 * (k % 4))], axis=1)
        z = X @ [rng.uniform(-0.2, 1), rng.uniform(-1, 8)] + 0.05 * rng.standard_normal(30)
        b_max = [0.5, 2.0, 10.0, np.inf][k % 4]
        A, B, C = _nnls2(X[:, 0] @ X[:, 0], X[:, 0] @ X[:, 1], X[:, 1] @ X[:, 1], X[:, 0] @ z, X[:, 1] @ z,
                         z @ z, b_max=b_max)
        ref = lsq_linear(X, z, bounds=([0, 0], [np.inf, b_max]), tol=1e-12)
        assert C == pytest.approx(float(np.sum((X @ ref.x - z) ** 2)), rel=1e-8, abs=1e-12)
        np.testing.assert_allclose([A, B], ref.x, rtol=1e-5, atol=1e-8)


def test_a_channel_without_a_highlight_is_fitted_with_no_lobe_not_an_off_data_spike(geo):
    """Fitted where the highlight is missing, the fit reports no lobe (the data do not see
    one) instead of a lobe with rho_s ~ 1e80 riding on the exponent's floor, and predicts
    the held-out highlight directions no higher than the largest datum it was given."""
    y = _grazing_channel(geo)
    near = np.degrees(geo["theta_h"].to_numpy()) < HIGHLIGHT_DEG
    fit = fit_ward(geo[~near], y[~near])
    assert 0 <= fit.params.rho_s <= RHO_S_MAX
    assert fit.params.rho_s == 0.0 and "rho_s" in fit.at_bound
    held = geo[near]
    pred = ward_from_angles(held["theta_in"], held["theta_out"], held["theta_h"], held["phi_h"], fit.params)
    assert np.all(np.isfinite(pred)) and pred.max() <= y[~near].max()


def test_luminance_fill_from_a_channel_without_a_highlight_keeps_the_lobe_of_the_others(geo):
    """``glossrig fit``'s luminance (and diagnose's material fit) fills the rows a channel misses
    with that channel's own fit. Red missing in the highlight and rising toward grazing
    elsewhere, green and blue a Ward material: the luminance lobe is the material's. Tolerance:
    the luminance differs from Ward's by LUMA_r times red's unmodelled grazing rise, 0.2126 x
    0.01 (g - 1) <= 8 % of the luminance at the rig's most grazing rows, so the lobe width is
    held to 10 % and rho_s to 20 % (twice the width's, as rho_s ~ alpha^2 at the peak); the
    unbounded fit put rho_s at ~1e80."""
    truth = material("sample_2_6")
    f = ward_from_angles(geo["theta_in"], geo["theta_out"], geo["theta_h"], geo["phi_h"], truth)
    rng = np.random.default_rng(5)
    red = _grazing_channel(geo, seed=1)
    red[np.degrees(geo["theta_h"].to_numpy()) < HIGHLIGHT_DEG] = np.nan
    t = geo.assign(r=red, g=f * (1 + 0.02 * rng.standard_normal(f.size)),
                   b=f * (1 + 0.02 * rng.standard_normal(f.size)), weight=1.0)
    fit = fit_samples(t, channels=["luminance"], footprint=False, budget=False).fits["luminance"]
    p = fit.params
    assert p.rho_s <= RHO_S_MAX
    assert p.alpha_x == pytest.approx(truth.alpha_x, rel=0.1) and p.alpha_y == pytest.approx(truth.alpha_y, rel=0.1)
    assert p.rho_s == pytest.approx((1 - 0.2126) * truth.rho_s, rel=0.2)


def test_diagnose_channel_fill_gives_an_unseen_lobe_no_amplitude(geo):
    """Diagnose fills a missing channel with the shared lobe L and the channel's own rho_d, rho_s
    (bounded linear least squares). A narrow lobe (alpha 0.003) is only its exponent's floor on
    every row that has red (theta_h >= 4 deg): red gets rho_s = 0 and its fill in the highlight is
    its diffuse level, not rho_s ~ 1e81 times the lobe's peak."""
    lobe = WardParams(rho_d=0.0, rho_s=1.0, alpha_x=0.003, alpha_y=0.002, lobe_rotation=0.3)
    L = ward_from_angles(geo["theta_in"], geo["theta_out"], geo["theta_h"], geo["phi_h"], lobe)
    near = np.degrees(geo["theta_h"].to_numpy()) < HIGHLIGHT_DEG
    red = _grazing_channel(geo)
    red[near] = np.nan
    t = pd.DataFrame({"r": red, "g": 0.05 + L / 30, "b": 0.05 + L / 30})
    t["f"] = t[["r", "g", "b"]].to_numpy() @ [0.2126, 0.7152, 0.0722]
    y, _, info = fill_missing_channels(t, L)
    assert info["r"]["rho_s"] == 0.0
    filled_red = (y[near] - t[["g", "b"]].to_numpy()[near] @ [0.7152, 0.0722]) / 0.2126
    np.testing.assert_allclose(filled_red, info["r"]["rho_d"] / np.pi, rtol=1e-9)
    assert info["r"]["rho_d"] / np.pi <= np.nanmax(red)
    rd, rs, _ = lobe_albedos(L[~near], red[~near], np.ones(int((~near).sum())))
    assert (rd, rs) == (info["r"]["rho_d"], 0.0)


def test_fit_stops_with_a_clear_message_on_values_that_overflow():
    """Values far outside any BRDF's range (1e160 1/sr) overflow the least-squares sums; the fit
    says so instead of returning an infinite cost as a result."""
    g = geometry(0.25)
    with pytest.raises(InputError, match="overflow the least-squares sums"):
        fit_ward(g, noisy(g, material("sample_2_6")) * 1e160, channel="r")
