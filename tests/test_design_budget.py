"""The expected uncertainty budget of a rig design (glossrig.core.design.error_budget)."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from glossrig.core.design import coverage as cov
from glossrig.core.design import error_budget as EB
from glossrig.core.design import fisher as fi
from glossrig.core.design.placement import _rows_for
from glossrig.core.models.ward import WardParams
from glossrig.core.rig import default_rig_path, load_rig

P = WardParams(rho_d=0.0518, rho_s=0.0069, alpha_x=0.0595, alpha_y=0.034, lobe_rotation=2.47)   # sample_2_6
SCALE, LEDS, ROTS, ROWS = 0.05, [8, 10], [0.0, 90.0], 1500
ONLY = dict(gain_rel=0.0, pose_rot_deg=0.0, pose_t_mm=0.0, albedo_u=0.0, angular_u=0.0, led_aperture=0.0)


@pytest.fixture(scope="module")
def rig():
    return load_rig(default_rig_path())


def _ward(a, r, p):
    return EB._ward(a, r, p)


def test_lamp_term_equals_the_spread_of_nonlinear_refits(rig):
    """The calibration component with only the lamps (0.5 mm per axis) is the root sum of
    squares of the parameter shifts that moving each lamp by 0.5 mm along each axis
    causes; here those shifts come from full nonlinear least-squares refits of data
    computed at the moved lamp. A 0.5 mm move is ~0.1 degree of lamp direction, small
    against the lobe (2-3 degrees), so the linearisation holds to a few per cent:
    ratio in [0.9, 1.1]."""
    b = EB.design_budget(rig, [("s", P)], rotations=ROTS, led_ids=LEDS, scale=SCALE, noise="relative:0.03",
                         fisher_rows=ROWS, lamp_std_mm=0.5, **ONLY)["s"]
    px = cov.pixel_geometry(rig, SCALE)
    nm = fi.noise_model("relative:0.03", rig)
    blocks = []
    for i in LEDS:
        lamp = np.asarray(rig.led(i).position, float)
        a_all = cov.direction_angles(px, lamp, half=True)
        rows, w = _rows_for(a_all, a_all["lit"], P, ROWS, 3000)
        sub = px.subset(rows)
        a = {k: v[rows] for k, v in a_all.items()}
        blocks.append((i, lamp, sub, a, w))
    x0 = np.array([getattr(P, k) for k in fi.PARAMS])

    def refit(moved_led, delta):
        def fun(x):
            p = WardParams(*x)
            out = []
            for i, lamp, sub, a, w in blocks:
                am = cov.direction_angles(sub, lamp + delta, half=True) if i == moved_led else a
                for r in ROTS:
                    y = _ward(am, r, P)[0]
                    f = _ward(a, r, p)[0]
                    s = nm.sigma(_ward(a, r, P)[0], a["cos_in"], a["dist_in"])
                    out.append(np.sqrt(w) * (f - y) / s)
            return np.concatenate(out)
        return least_squares(fun, x0, x_scale=np.abs(x0) + 1e-3, xtol=1e-14, ftol=1e-14, gtol=1e-14).x - x0

    var = np.zeros(5)
    for i in LEDS:
        for e in np.eye(3):
            var += refit(i, 0.5 * e) ** 2
    u = np.sqrt(var)
    for k, name in enumerate(fi.PARAMS):
        got = b["components"]["calibration"][name]
        assert u[k] > 0 and got > 0
        assert 0.9 < got / u[k] < 1.1, (name, got, u[k])


def test_components_scale_with_their_stated_errors_and_combine(rig):
    """Each component is linear in the error it is stated for (the model term in the
    residual gain, the footprint term in the aperture squared), and the combined one is
    their root sum of squares; the albedo adds its relative uncertainty to rho_d, rho_s."""
    kw = dict(rotations=ROTS, led_ids=LEDS, scale=SCALE, noise="relative:0.03", fisher_rows=ROWS)
    one = EB.design_budget(rig, [("s", P)], **{**ONLY, "gain_rel": 0.005}, lamp_std_mm=0.0, **kw)["s"]
    two = EB.design_budget(rig, [("s", P)], **{**ONLY, "gain_rel": 0.010}, lamp_std_mm=0.0, **kw)["s"]
    for name in fi.PARAMS:
        assert two["components"]["model"][name] == pytest.approx(2 * one["components"]["model"][name], rel=1e-9)
        assert one["components"]["calibration"][name] == 0.0
    full = EB.design_budget(rig, [("s", P)], **kw)["s"]
    for name in fi.PARAMS:
        rss = math.sqrt(sum(full["components"][c][name] ** 2 for c in EB.COMPONENTS))
        assert full["combined"][name] == pytest.approx(rss, rel=1e-12)
    alb = EB.design_budget(rig, [("s", P)], **{**ONLY, "albedo_u": 0.02}, lamp_std_mm=0.0, **kw)["s"]
    assert alb["components"]["calibration"]["rho_d"] == pytest.approx(0.02 * P.rho_d, rel=1e-12)
    assert alb["components"]["calibration"]["alpha_x"] == 0.0


def test_design_errors_cli_reports_both_figures(tmp_path, capsys):
    from glossrig.cli.main import main

    out = tmp_path / "errors.json"
    assert main(["design", "errors", "--rig", "thesis_rig.toml", "--materials", "sample_2_6", "--leds", "8,10",
                 "--rotations", "0", "--scale", "0.05", "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    noise_only = doc["expected_errors"]["sample_2_6"]["stderr"]
    comb = doc["expected_uncertainty"]["sample_2_6"]
    assert "noise-only" in doc["stderr_kind"]
    for name in fi.PARAMS:
        assert comb["combined"][name] > noise_only[name]
        assert comb["components"]["noise"][name] == pytest.approx(noise_only[name], rel=0.05)
    assert main(["design", "errors", "--rig", "thesis_rig.toml", "--materials", "sample_2_6", "--leds", "8",
                 "--pose-rot", "-1", "--scale", "0.05"]) == 2
    assert "--pose-rot" in capsys.readouterr().err
