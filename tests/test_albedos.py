"""The one bounded two-column albedo solve of a fixed lobe (glossrig.core.fitting.fit.lobe_albedos):
thesis eq. 4.81 is linear in rho_d and rho_s, bounded by energy conservation (eq. 2.4, RHO_S_MAX),
and a lobe the data do not see (LOBE_UNSEEN) is none, with rho_d re-solved alone. Used by the
shared-lobe albedos of glossrig fit, the stock microfacet fit and diagnose's material models."""
from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import lsq_linear

from glossrig.core.fitting.fit import LOBE_UNSEEN, RHO_S_MAX, lobe_albedos, peak_weight, shared_lobe_albedos
from glossrig.core.models.ward import WardParams, ward_from_angles
from glossrig.core.samples import ward_samples

from helpers import geometry

# Relative tolerance of two evaluations of the same weighted sums over n <= 1e5 rows in different
# orders: numpy's pairwise summation errs by ~eps log2(n) ~ 4e-15 per sum; 1e-10 leaves a margin of
# 1e4 for the few sums and the quadratic's cancellation (the cost is a difference of sums ~ zz).
SUMS_RTOL = 1e-10


def _plain(L, y, W):
    """The bounded solve without the unseen rule (the former solve of all three users)."""
    return lobe_albedos(L, y, W, unseen_rule=False)


def test_a_seen_lobe_gets_the_bounded_least_squares_albedos():
    """Against SciPy's general bounded solver (lsq_linear, tol 1e-12) on lobes seen by the data,
    with the optimum inside the box and on the bound rho_s = RHO_S_MAX."""
    rng = np.random.default_rng(4)
    x = np.linspace(-1, 1, 300)
    L = 40 * np.exp(-x ** 2 / 0.02)
    W = rng.uniform(0.2, 1.5, x.size)
    for rho_s in (0.4, 10.0):                       # inside; beyond the bound
        y = 0.3 / np.pi + rho_s * L + rng.normal(0, 0.01, x.size)
        a, b, cost = lobe_albedos(L, y, W)
        ref = lsq_linear(W[:, None] * np.c_[np.full(x.size, 1 / np.pi), L], W * y,
                         bounds=([0, 0], [np.inf, RHO_S_MAX]), tol=1e-12)
        assert (a, b) == pytest.approx(tuple(ref.x), rel=1e-7, abs=1e-9)
        assert cost == pytest.approx(np.sum((W * (y - a / np.pi - b * L)) ** 2), rel=SUMS_RTOL)
        assert b == (RHO_S_MAX if rho_s > RHO_S_MAX else pytest.approx(rho_s, rel=0.01))


def test_an_unseen_lobe_is_none_and_rho_d_is_solved_alone():
    """A lobe column ~1e-9 on every row (its peak where no row is) following a faint trend of the
    data: the bounded solve alone puts rho_s on its bound (and the lobe's peak would be extrapolated
    from nothing); the one solve reports no lobe and the diffuse level of the data alone, with that
    level's cost. A lobe 10x above the unseen level is kept."""
    rng = np.random.default_rng(5)
    g = 1 / rng.uniform(0.2, 1.0, 400)              # like 1 / sqrt(cos_in cos_out)
    L = 1e-9 * g
    W = rng.uniform(0.2, 1.5, g.size)
    y = 0.25 / np.pi * (1 + 0.01 * (g - g.mean())) + rng.normal(0, 1e-4, g.size)
    assert _plain(L, y, W)[1] == RHO_S_MAX
    assert RHO_S_MAX * np.max(L) <= LOBE_UNSEEN * np.max(y)
    a, b, cost = lobe_albedos(L, y, W)
    assert b == 0.0
    assert a == pytest.approx(np.average(np.pi * y, weights=W * W), rel=SUMS_RTOL)
    assert cost == pytest.approx(np.sum((W * (y - a / np.pi)) ** 2), rel=SUMS_RTOL)
    # rows of zero weight take no part, in the unseen test either
    Wz = np.r_[W, 0.0]
    assert lobe_albedos(np.r_[L, 1.0], np.r_[y, 1e6], Wz) == pytest.approx((a, b, cost), rel=SUMS_RTOL)
    # seen (barely): b L reaches 10 LOBE_UNSEEN of the data on one row
    L_seen = L.copy()
    L_seen[0] = 10 * LOBE_UNSEEN * np.max(np.abs(y)) / RHO_S_MAX
    assert lobe_albedos(L_seen, y, W) == _plain(L_seen, y, W)


def test_shared_lobe_albedos_report_no_lobe_for_a_channel_that_does_not_see_it():
    """glossrig fit's shared-lobe albedos (eq. 4.81 per channel for the luminance fit's lobe), on
    the rows where a narrow lobe (alpha 1e-3) of unit rho_s is below 2e-9 1/sr: red holds that lobe
    with rho_s 1e3 (at most 2e-6 of red's diffuse level), green and blue none. The bounded solve alone
    gives red rho_s = RHO_S_MAX (the lobe's peak, where no row is, then extrapolated); the one solve
    reports no lobe in any channel, and each channel's weighted diffuse level."""
    lobe = WardParams(0.0, 1.0, 1e-3, 1e-3, 0.0)
    geo = geometry(0.04)
    unit = ward_from_angles(geo["theta_in"], geo["theta_out"], geo["theta_h"], geo["phi_h"], lobe)
    geo = geo[unit < 2e-9].reset_index(drop=True)
    none = WardParams(0.25, 0.0, 0.1, 0.1, 0.0)
    df = ward_samples(geo, {"r": WardParams(0.25, 1e3, 1e-3, 1e-3, 0.0), "g": none, "b": none})
    W = peak_weight(*(np.asarray(df[k], float) for k in ("theta_in", "phi_in", "theta_out", "phi_out")))
    L = ward_from_angles(df["theta_in"], df["theta_out"], df["theta_h"], df["phi_h"], lobe)
    assert _plain(L, np.asarray(df["r"], float), W)[1] == RHO_S_MAX
    out = shared_lobe_albedos(df, lobe)
    assert out["rho_s"] == [0.0, 0.0, 0.0]
    for c, rd in zip("rgb", out["rho_d"]):
        assert rd == pytest.approx(np.average(np.pi * np.asarray(df[c], float), weights=W * W), rel=SUMS_RTOL)
