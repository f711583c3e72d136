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
from glossrig.core.fitting.calibration_uncertainty import LAMP_COMMON_FRACTION
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


def _blocks(rig, noise: str, p: WardParams = P):
    """The design's rows per LED as :func:`EB.budget_and_bound` builds them: (LED, lamp, pixels,
    angles, pixel counts, eq. 4.82 weights), and the noise model."""
    from glossrig.core.fitting.fit import peak_weight

    px = cov.pixel_geometry(rig, SCALE)
    out = []
    for i in LEDS:
        lamp = np.asarray(rig.led(i).position, float)
        a_all = cov.direction_angles(px, lamp, half=True)
        rows, w = _rows_for(a_all, a_all["lit"], p, ROWS, 3000)
        a = {k: v[rows] for k, v in a_all.items()}
        m = peak_weight(*(np.radians(a[k]) for k in ("theta_in", "phi_in", "theta_out", "phi_out")))
        out.append((i, lamp, px.subset(rows), a, w, m))
    return out, fi.noise_model(noise, rig)


def _ratio_sigma(nm, f, a, rig):
    return EB.ratio_sigma(nm, f, a["cos_in"], a["dist_in"], rig.reference.assumed_albedo / math.pi)


def test_lamp_term_equals_the_spread_of_nonlinear_refits(rig):
    """The calibration component with only the lamps (0.5 mm per axis, split as cu.LAMP_DRAW
    into a fraction f common to every LED and 1 - f each LED's own) is the root of the sum over
    the axes of f times the squared parameter shift that moving every lamp by 0.5 mm along that
    axis causes and 1 - f times those of each lamp moved alone; here those shifts come from
    full nonlinear least-squares refits, with the pipeline's weights (eq. 4.82 over the
    ratio's noise), of data computed at the moved lamps. A 0.5 mm move is ~0.1 degree of
    lamp direction, small against the lobe (2-3 degrees), so the linearisation holds to a
    few per cent: ratio in [0.9, 1.1]."""
    b = EB.design_budget(rig, [("s", P)], rotations=ROTS, led_ids=LEDS, scale=SCALE, noise="relative:0.03",
                         fisher_rows=ROWS, lamp_std_mm=0.5, **ONLY)["s"]
    blocks, nm = _blocks(rig, "relative:0.03")
    x0 = np.array([getattr(P, k) for k in fi.PARAMS])

    def refit(delta, only=None):
        def fun(x):
            p = WardParams(*x)
            out = []
            for i, lamp, sub, a, w, m in blocks:
                am = cov.direction_angles(sub, lamp + delta, half=True) if only in (None, i) else a
                for r in ROTS:
                    y = _ward(am, r, P)[0]
                    f = _ward(a, r, p)[0]
                    s = _ratio_sigma(nm, _ward(a, r, P)[0], a, rig)
                    out.append(np.sqrt(w) * m * (f - y) / s)
            return np.concatenate(out)
        return least_squares(fun, x0, x_scale=np.abs(x0) + 1e-3, xtol=1e-14, ftol=1e-14, gtol=1e-14).x - x0

    var = np.zeros(5)
    for e, f in zip(np.eye(3), LAMP_COMMON_FRACTION):
        var += f * refit(0.5 * e) ** 2
        for i in LEDS:
            var += (1 - f) * refit(0.5 * e, only=i) ** 2
    u = np.sqrt(var)
    for k, name in enumerate(fi.PARAMS):
        got = b["components"]["calibration"][name]
        assert u[k] > 0 and got > 0
        assert 0.9 < got / u[k] < 1.1, (name, got, u[k])


def test_noise_component_is_the_scatter_of_the_pipelines_fits(rig):
    """The noise component is the sandwich covariance of the pipeline's estimator (weights of
    eq. 4.82 over the ratio's sensor noise, not inverse variances): N = 100 noisy data sets
    at the design's rows (a row standing for w pixels has noise sigma / sqrt(w)), each
    fitted by nonlinear least squares with those weights; the fits' standard deviation per
    parameter against the predicted component. The sample standard deviation of N = 100
    has a relative standard error 1 / sqrt(2 (N - 1)) = 7.1 %; the bound [0.75, 1.25] is
    3.5 of those (the linearisation's own error at 3 % noise is far below)."""
    b = EB.design_budget(rig, [("s", P)], rotations=ROTS, led_ids=LEDS, scale=SCALE, noise="relative:0.03",
                         fisher_rows=ROWS, lamp_std_mm=0.0, **ONLY)["s"]
    blocks, nm = _blocks(rig, "relative:0.03")
    x0 = np.array([getattr(P, k) for k in fi.PARAMS])
    parts = []
    for _i, _lamp, _sub, a, w, m in blocks:
        for r in ROTS:
            f0 = _ward(a, r, P)[0]
            s = _ratio_sigma(nm, f0, a, rig)
            parts.append((a, r, f0, s, np.sqrt(w) * m / s, s / np.sqrt(w)))
    rng = np.random.default_rng(7)
    fits = []
    for _ in range(100):
        ys = [f0 + sd * rng.standard_normal(f0.size) for a, r, f0, s, mult, sd in parts]

        def fun(x, ys=ys):
            p = WardParams(*x)
            return np.concatenate([mult * (_ward(a, r, p)[0] - y) for (a, r, f0, s, mult, sd), y in zip(parts, ys)])
        fits.append(least_squares(fun, x0, x_scale=np.abs(x0) + 1e-3, xtol=1e-12, ftol=1e-12).x)
    sd = np.std(np.asarray(fits), axis=0, ddof=1)
    for k, name in enumerate(fi.PARAMS):
        assert 0.75 < b["components"]["noise"][name] / sd[k] < 1.25, (name, b["components"]["noise"][name], sd[k])


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


def _camera_file(path, rig, scale: float):
    """A camera calibration as ``glossrig calibrate camera`` writes it (board views included) for
    the rig's camera at ``scale``: the views of test_calibration_uncertainty, 0.15 px RMS."""
    from test_calibration_uncertainty import _board_views

    from glossrig.core.calibration.intrinsics import FORMAT

    K, size = rig.camera.matrix(scale), [int(v) for v in rig.camera.size(scale)]
    doc = {"format": FORMAT, "version": 1, "fx": K[0, 0], "fy": K[1, 1], "cx": K[0, 2], "cy": K[1, 2],
           "camera_matrix": K.tolist(), "distortion": [float(v) for v in rig.camera.distortion],
           "image_size": size, "reprojection_rms_px": 0.15, "board": {"inner_corners": [9, 6], "square_mm": 25.0},
           "views": [{"rvec": rv.ravel().tolist(), "tvec_mm": tv.ravel().tolist()} for rv, tv in _board_views()]}
    path.write_text(json.dumps(doc))
    return path


#: ``budget_text`` prints each cell to 3 significant digits: a cell is off by at most half a unit
#: of its third digit, 0.5 % of it, and a root sum of squares of such cells by as much again
TABLE_ROUNDING = 2 * 0.005


def _printed_budget(text: str, label: str) -> dict:
    """The rows of ``budget_text``'s table (as the CLI prints it) for material ``label``:
    parameter -> the numbers of its component and combined cells (None for '-')."""
    rows = {}
    for line in text.splitlines():
        cells = line.split()
        if len(cells) == 2 + len(EB.COMPONENTS) + 1 and cells[0] == label[:24] and cells[1] in fi.PARAMS:
            rows[cells[1]] = [None if c == "-" else float(c.rstrip("%d")) for c in cells[2:]]
    return rows


def test_design_errors_cli_states_a_usable_budget(tmp_path, capsys, rig):
    """What a user reads from ``glossrig design errors`` for a Table 9.1 material (sample_2_6):
    every parameter's combined uncertainty finite and positive; the components listed add in
    quadrature to it (in the JSON to rounding, in the printed table to its 3 digits,
    :data:`TABLE_ROUNDING`); with a camera calibration (``--camera``) the calibration
    component holds the intrinsics draws: with the same pose and lamp figures it is larger
    than without, for every parameter, by what the draws add. The noise-only bound printed
    beside it equals :func:`placement.design_errors`' (the same rows and sums: to rounding), and
    the budget's noise component is not below it (Cramer-Rao: the pipeline's weights are not
    the inverse variances, and the budget adds the reference's noise)."""
    from glossrig.cli.main import main
    from glossrig.core.design.placement import design_errors, parse_materials

    cam = _camera_file(tmp_path / "camera.json", rig, 0.05)
    base = ["design", "errors", "--rig", "thesis_rig.toml", "--materials", "sample_2_6", "--leds", "8,10",
            "--rotations", "0", "--scale", "0.05", "--pose-rot", "0.06", "--pose-t", "0.04"]
    docs, printed = {}, {}
    for name, extra in (("plain", []), ("camera", ["--camera", str(cam), "--draws", "8"])):
        out = tmp_path / f"errors_{name}.json"
        assert main([*base, *extra, "--out", str(out)]) == 0
        captured = capsys.readouterr()
        docs[name] = json.loads(out.read_text())
        printed[name] = _printed_budget(captured.out + captured.err, "sample_2_6")
    for name, doc in docs.items():
        e = doc["expected_uncertainty"]["sample_2_6"]
        assert set(e["components"]) == set(EB.COMPONENTS)
        assert set(printed[name]) == set(fi.PARAMS), printed[name]
        for k in fi.PARAMS:
            comb = e["combined"][k]
            assert comb is not None and math.isfinite(comb) and comb > 0, (name, k, comb)
            parts = [e["components"][c][k] for c in EB.COMPONENTS]
            assert all(u is not None and math.isfinite(u) and u >= 0 for u in parts), (name, k, parts)
            assert math.sqrt(sum(u * u for u in parts)) == pytest.approx(comb, rel=1e-12), (name, k)
            assert e["components"]["noise"][k] > 0 and e["components"]["calibration"][k] > 0, (name, k)
            row = printed[name][k]
            assert row[-1] is not None and row[-1] > 0, (name, k, row)
            cells = [c or 0.0 for c in row[:-1]]
            assert math.sqrt(sum(c * c for c in cells)) == pytest.approx(row[-1], rel=TABLE_ROUNDING), (name, k, row)
    with_cam = docs["camera"]["expected_uncertainty"]["sample_2_6"]
    without = docs["plain"]["expected_uncertainty"]["sample_2_6"]
    assert "8 draws of the camera calibration" in with_cam["stated"]["intrinsics"]
    assert with_cam["calibration_draws"] == 8 and 0 < max(with_cam["calibration_mc_rel_u"].values()) < 1
    assert "not drawn" in without["stated"]["intrinsics"]
    for k in fi.PARAMS:
        # the same pose, lamp, albedo figures: the difference of the variances is the draws'
        for c in ("noise", "model", "footprint"):
            assert with_cam["components"][c][k] == pytest.approx(without["components"][c][k], rel=1e-12), (c, k)
        drawn = with_cam["components"]["calibration"][k] ** 2 - without["components"]["calibration"][k] ** 2
        assert drawn > 0, (k, with_cam["components"]["calibration"][k], without["components"]["calibration"][k])
    noise_only = docs["plain"]["expected_errors"]["sample_2_6"]["stderr"]
    assert "noise-only" in docs["plain"]["stderr_kind"]
    ref = design_errors(rig, parse_materials("sample_2_6"), rotations=[0.0], led_ids=[8, 10], scale=0.05)
    for name in fi.PARAMS:
        assert noise_only[name] == pytest.approx(ref["sample_2_6"].stderr[name], rel=1e-12)
        assert without["combined"][name] > noise_only[name]
        assert without["components"]["noise"][name] >= noise_only[name]
    assert main(["design", "errors", "--rig", "thesis_rig.toml", "--materials", "sample_2_6", "--leds", "8",
                 "--pose-rot", "-1", "--scale", "0.05"]) == 2
    assert "--pose-rot" in capsys.readouterr().err
    assert main([*base, "--draws", "8"]) == 2
    assert "--draws needs --camera" in capsys.readouterr().err


#: A lobe wide against the scale-0.05 footprint (the point model's refit of its footprint-averaged
#: data stays within FOOTPRINT_REFIT_DEPARTURE): the budget's calibration refits are the point model's.
WIDE = WardParams(rho_d=0.0518, rho_s=0.0069, alpha_x=0.2, alpha_y=0.12, lobe_rotation=2.47)


@pytest.mark.parametrize("lobe, refits, poses", [(P, "footprint", False), (WIDE, "point", False), (WIDE, "point", True)])
def test_intrinsics_term_equals_the_spread_of_nonlinear_refits(rig, lobe, refits, poses):
    """With a camera calibration's views the calibration component holds the intrinsics
    drawn as ``glossrig fit`` draws them (EB.CalibrationDraws, the lamps solved again under
    each). Its nominal geometry is the design's own (the pixels' rays cast again: the same
    angles to 1e-6 degree), and its spread over the draws (Gauss-Newton refits) equals that of
    this test's own nonlinear refits (SciPy's trust region, residuals assembled here with the
    pipeline's weights, the table's at the value each row holds) of the nominal data against each drawn geometry (root mean square about
    the nominal fit, the draws' mean bias kept) - the footprint-averaged
    model of each row's kernel for sample_2_6, as narrow as a scale-0.05 footprint, the point
    model for a wide lobe, as the budget decides (EB._Sums.intrinsics_variance): the same 12 draws, so no sampling error
    between the two; both converge to ~1e-8 of the parameters, against shifts of 1e-4 to
    1e-2 of them, and eq. 4.82's weights come from the drawn angles in both (the pipeline's
    table holds those): ratio in [0.99, 1.01]. (A linearisation of the same draws
    gave 0.16 for rho_s and 2.8 for alpha_y here: at a calibration's noise the angle
    errors act at second order as much as at first.) With ``poses`` the draws also move the
    markers' poses by the pose step's measured errors (EB.HOLDER_POSE_NOISE_ROT_DEG and
    companions at this scale; the geometry of a holder error:
    test_a_holder_pose_error_moves_the_lamps_against_sample_and_camera): the lamp capture's,
    through the lamps solved again, and the sample capture's, drawn afresh for each of the two
    rotations (each has its own calibration image), which the refits here take rotation by
    rotation. The pose errors act at second order too: at rotation 0 a turn of the holder about
    its x axis by +-0.05 degree moved the wide lobe's rotation by -4.1e-4 and -0.4e-4 rad."""
    from test_calibration_uncertainty import _board_views

    from glossrig.core.calibration.intrinsics import board_points
    from glossrig.core.fitting.calibration_uncertainty import CameraViews
    from glossrig.core.fitting.fit import peak_weight
    from glossrig.core.fitting.footprint_model import footprint_eval, sample_footprint
    from glossrig.core.models.ward import ward_geometry

    views = _board_views()
    cv = CameraViews(obj=board_points((9, 6), 25.0), rvecs=[v[0] for v in views], tvecs=[v[1] for v in views],
                     rms_px=0.15)
    pose = dict(pose_rot_deg=None, pose_t_mm=None) if poses else dict(pose_rot_deg=0.0, pose_t_mm=0.0)
    b = EB.design_budget(rig, [("s", lobe)], rotations=ROTS, led_ids=LEDS, scale=SCALE, noise="relative:0.03",
                         fisher_rows=ROWS, lamp_std_mm=0.0, camera_views=cv, intrinsics_draws=12, seed=3,
                         **dict(ONLY, **pose))["s"]
    assert "12 draws" in b["stated"]["intrinsics"]
    sd = b["stated"]["marker_pose_noise"]
    f = EB.POSE_NOISE_SCALE / SCALE
    for k, v in (("pose_rot_deg", EB.HOLDER_POSE_NOISE_ROT_DEG), ("pose_t_mm", EB.HOLDER_POSE_NOISE_T_MM),
                 ("cylinder_rot_deg", EB.CYLINDER_POSE_NOISE_ROT_DEG), ("cylinder_t_mm", EB.CYLINDER_POSE_NOISE_T_MM)):
        np.testing.assert_allclose(sd[k], f * np.asarray(v) if poses else 0.0)
    blocks, nm = _blocks(rig, "relative:0.03", lobe)
    px = cov.pixel_geometry(rig, SCALE)
    intr = EB.CalibrationDraws(rig, px, cv, 12, 3, **sd)
    assert intr.moves_sample == poses
    # the footprint-averaged model where the budget refitted it (the lobe as narrow as a footprint
    # at this scale): each row's kernel from the design's slope Jacobians, held at the nominal geometry
    assert b["calibration_refits"] == refits
    footprint = refits == "footprint"
    drawn_by_led, fps = {}, {}
    for i, lamp, sub, a, _w, _m in blocks:
        index = {int(k): j for j, k in enumerate(px.v * 100000 + px.u)}
        rows = np.array([index[int(k)] for k in sub.v * 100000 + sub.u])
        for ri, r in enumerate(ROTS):           # the sample capture's pose errors: each rotation's own
            nominal, drawn = intr.angles(i, ri)
            for k in ("theta_in", "theta_out", "theta_h"):
                np.testing.assert_allclose(np.degrees(nominal[k][rows]), a[k], atol=1e-6)
            drawn_by_led[(i, r)] = [{k: np.degrees(v[rows]) for k, v in ad.items()} for ad in drawn]
        a_all = cov.direction_angles(px, lamp, half=True)
        fps[i] = {r: sample_footprint(EB.pixel_slope_jacobian(px, a_all, r)[rows]) for r in ROTS}

    def model(a, r, x, fp):
        if not footprint:
            return _ward(a, r, WardParams(*x))[0]
        geo = ward_geometry(*(np.radians(a[k]) for k in ("theta_in", "theta_out", "theta_h")),
                            np.radians(np.mod(a["phi_h"] - r, 360.0)))
        return footprint_eval(geo, fp, x)

    x0 = np.array([getattr(lobe, k) for k in fi.PARAMS])
    if footprint:
        # the pixel quadrature the fit chooses for this lobe, over all the rows (FootprintModel.orders_for)
        keys = [(i, r) for i, *_ in blocks for r in ROTS]
        geo = ward_geometry(*(np.concatenate([np.radians(a[k]) for _i, _l, _s, a, _w, _m in blocks for _r in ROTS])
                              for k in ("theta_in", "theta_out", "theta_h")),
                            np.concatenate([np.radians(np.mod(a["phi_h"] - r, 360.0))
                                            for _i, _l, _s, a, _w, _m in blocks for r in ROTS]))
        joined = sample_footprint(np.concatenate([fps[i][r].J for i, r in keys]))
        orders = joined.orders_for(geo, x0)
        fps = {i: {r: fp.with_orders(orders) for r, fp in by_rot.items()} for i, by_rot in fps.items()}
    data = {(i, r): model(a, r, x0, fps[i][r]) for i, _lamp, _sub, a, _w, _m in blocks for r in ROTS}
    shifts = []
    for d in range(12):
        def fun(x, d=d):
            out = []
            for i, _lamp, _sub, a, w, _m in blocks:
                for r in ROTS:
                    ad = drawn_by_led[(i, r)][d]
                    # eq. 4.82's weight from the angles the pipeline has: the drawn ones
                    md = peak_weight(*(np.radians(ad[k]) for k in ("theta_in", "phi_in", "theta_out", "phi_out")))
                    y = data[(i, r)]
                    s = _ratio_sigma(nm, y, a, rig)          # the table weighs a row by the value it holds
                    res = np.sqrt(w) * md * (model(ad, r, x, fps[i][r]) - y) / s
                    out.append(np.where(np.isfinite(res), res, 0.0))
            return np.concatenate(out)
        shifts.append(least_squares(fun, x0, x_scale=np.abs(x0) + 1e-3, xtol=1e-14, ftol=1e-14, gtol=1e-14).x - x0)
    # the root mean square of the errors (their bias kept: EB._Sums.intrinsics_variance)
    sd = np.sqrt(np.mean(np.square(shifts), axis=0))
    # and the Monte Carlo's own standard uncertainty the budget records (budget_and_bound's adaptive
    # draws) from these independent refits: u(mean square) / (2 u_c^2), u(mean square) the standard
    # deviation of the 12 squared shifts over sqrt(12); the shifts agree to 1 % (above), their squares to 2 %
    sq = np.square(shifts)
    mc_u = sq.std(axis=0, ddof=1) / math.sqrt(len(sq))
    for k, name in enumerate(fi.PARAMS):
        got = b["components"]["calibration"][name]
        assert sd[k] > 0 and got > 0
        assert 0.99 < got / sd[k] < 1.01, (name, got, sd[k])
        assert b["calibration_mc_rel_u"][name] == pytest.approx(mc_u[k] / (2 * b["combined"][name] ** 2), rel=0.02)


def test_sensor_only_noise_is_the_merge_s_own_and_the_led_term_adds_in_quadrature():
    """The second figure is the HDR merge's sensor noise itself (what extract writes as a row's
    variance), the first that and the LED fluctuation in quadrature. The values span the rig's
    range and far below it: at f = 1e-170 1/sr the merge's relative error (~1e170, finite)
    squared overflows, which the former sqrt(shot**2) (and sqrt(shot**2 + led**2)) turned into inf."""
    nm = fi.HdrNoise.from_rig(load_rig(default_rig_path()), led_rel=0.02)
    f = np.array([1e-170, 1e-6, 1e-2, 0.3, 3.0, 300.0])
    cos_in, dist = np.full(f.shape, 0.8), np.full(f.shape, 300.0)
    r, r0 = nm.relative_with_sensor_only(f, cos_in, dist)
    sensor = nm.sensor_relative(nm.electron_rate(f, cos_in, dist))
    assert np.all(np.isfinite(sensor[:-1])) and sensor[0] > 1e150
    np.testing.assert_array_equal(r0, sensor)
    np.testing.assert_array_equal(r, np.hypot(sensor, 0.02))
    assert np.all(r0 <= r) and np.array_equal(nm.relative(f, cos_in, dist), r)


def test_calibration_draws_move_every_lamp_by_one_shift(rig):
    """CalibrationDraws' further lamp error (cu.LAMP_DRAW): each draw's angles for every LED are
    the pixels' rays through that draw's camera towards the LED as the lamp calibration solves
    it under that camera, moved by the shift common to every LED (non-zero) plus the LED's own;
    the camera draws and the lamps solved under them do not depend on that error (their own
    random streams)."""
    from test_calibration_uncertainty import _board_views

    from glossrig.core.calibration.intrinsics import board_points
    from glossrig.core.fitting import calibration_uncertainty as cu
    from glossrig.core.fitting.calibration_uncertainty import CameraViews

    views = _board_views()
    cv = CameraViews(obj=board_points((9, 6), 25.0), rvecs=[v[0] for v in views], tvecs=[v[1] for v in views],
                     rms_px=0.15)
    px = cov.pixel_geometry(rig, SCALE)
    with_lamps = EB.CalibrationDraws(rig, px, cv, 3, 5, lamp_std_mm=0.7)
    without = EB.CalibrationDraws(rig, px, cv, 3, 5)
    # the same camera draws: apart by far less than the draws differ from each other (OpenCV's
    # calibration does not repeat bitwise, and under load not even to 1e-6)
    Ks = np.array([d[0] for d in without.draws])
    ds = np.array([np.ravel(d[1]) for d in without.draws])
    for (K1, d1, _), (K0, d0, _) in zip(with_lamps.draws, without.draws):
        assert np.all(np.abs(K1 - K0) <= 1e-3 * Ks.std(axis=0) + 1e-12)
        assert np.all(np.abs(np.ravel(d1) - np.ravel(d0)) <= 1e-3 * ds.std(axis=0) + 1e-12)
    n = with_lamps.u.size
    for led in LEDS[:2]:
        _, drawn = with_lamps.angles(led)
        pos = np.asarray(rig.led(led).position, float)
        f = np.asarray(cu.LAMP_COMMON_FRACTION)
        own = 0.7 * np.sqrt(1 - f) * np.random.default_rng([5, 2, led]).standard_normal((3, 3))
        resolved = with_lamps.resolved_shifts(led)
        # the same lamp calibration under the same camera draws: apart by what those are (see above)
        assert np.all(np.abs(resolved - without.resolved_shifts(led)) <= 1e-3 * resolved.std(axis=0) + 1e-12)
        for (K, d, poses), res, shift, o, got in zip(with_lamps.draws, resolved, with_lamps.lamp_shifts, own, drawn):
            want = cu.row_angles(with_lamps.cal, with_lamps.u, with_lamps.v, np.full(n, led), np.zeros(n), K=K,
                                 dist=d, poses=poses, lamps={led: pos + res + shift + o})
            ok = want["valid"]
            np.testing.assert_allclose(got["theta_in"][ok], want["theta_in"][ok], atol=1e-12)
            assert np.linalg.norm(shift) > 0


def test_lamps_are_solved_again_with_the_geometry_they_are_calibrated_with(rig):
    """CalibrationDraws solves each lamp again under the drawn geometry, as ``glossrig calibrate
    lamps`` would with that camera (lamps._solve_lamp on the sheet's values at the same pixels),
    so the lamps' error goes with the geometry's. Checked on a geometry error whose effect is
    known exactly: the holder and the cylinder turned together by 0.2 degree about the cylinder's
    axis (a common pose error of both captures). In the holder frame the camera and every ray
    then turn by -0.2 degree about the axis and the cylinder maps onto itself, so the lamp
    calibration must return its nominal solution turned by the same rotation, and the sample's
    angles at the design's pixels, with that lamp, must equal the nominal ones. Exact in exact
    arithmetic (the same pixels and values select the same highlight and diffuse samples), the
    bound is the diffuse refinement's stopping rule: least_squares stops when a step is below
    xtol = 1e-8 of the scaled parameters (azimuth / 1e-3 rad, height / 0.1 mm, gain / 0.01, a norm
    of ~1e3), i.e. an azimuth step of ~1e-8 rad, 3e-6 mm at the LED's 300 mm: 1e-5 mm against a
    turn of 300 mm x 0.2 degree = 1.05 mm, and 1e-5 mm / 300 mm ~ 3e-8 rad, bounded by 1e-7 rad,
    for the angles (measured when written: 3e-11 mm and 4e-13 rad); the lamps held where they were
    (drawn independently of the geometry, as before) move theta_in by 3.8e-3 rad."""
    from test_calibration_uncertainty import _board_views

    from glossrig.core.calibration.intrinsics import board_points
    from glossrig.core.fitting import calibration_uncertainty as cu

    views = _board_views()
    cv = cu.CameraViews(obj=board_points((9, 6), 25.0), rvecs=[v[0] for v in views], tvecs=[v[1] for v in views],
                        rms_px=0.15)
    px = cov.pixel_geometry(rig, SCALE)
    draws = EB.CalibrationDraws(rig, px, cv, 2, 5)
    p = draws.cal.poses[0.0]
    (Rh, th), (Rc, tc) = (p["holder"]["R"], p["holder"]["t"]), (p["cylinder"]["R"], p["cylinder"]["t"])
    axis = draws.cal.poses[0.0]["holder"]["R"].T @ Rc @ np.array([0.0, 1.0, 0.0])     # holder frame
    turn = cu.rotation_from_vector(math.radians(0.2) * axis)
    turned = ((Rh @ turn, th), (Rc @ turn, tc))
    n = draws.u.size
    for led in LEDS:
        nominal = draws.solve_lamp(led, draws.cal.K, draws.cal.dist, ((Rh, th), (Rc, tc)))
        solved = draws.solve_lamp(led, draws.cal.K, draws.cal.dist, turned)
        expected = turn.T @ nominal
        assert np.linalg.norm(expected - nominal) > 1.0                 # the turn moves the lamp 1.05 mm
        assert np.linalg.norm(solved - expected) < 1e-5, (led, solved, expected)
        pos = np.asarray(rig.led(led).position, float)
        args = (draws.u, draws.v, np.full(n, led), np.zeros(n))
        a0 = cu.row_angles(draws.cal, *args, lamps={led: pos})
        a1 = cu.row_angles(draws.cal, *args, poses={0.0: turned}, lamps={led: pos + solved - nominal})
        held = cu.row_angles(draws.cal, *args, poses={0.0: turned}, lamps={led: pos})
        ok = a0["valid"] & a1["valid"] & held["valid"]
        assert ok.sum() > 1000
        for k in ("theta_in", "theta_out", "theta_h"):
            assert np.max(np.abs(a1[k][ok] - a0[k][ok])) < 1e-7, (led, k)
        assert np.max(np.abs(held["theta_in"][ok] - a0["theta_in"][ok])) > 1e-3


def test_a_holder_pose_error_moves_the_lamps_against_sample_and_camera(rig):
    """The sample capture's holder pose error (EB.CalibrationDraws, ``captures=("sample",)``) is
    what the pipeline makes of a holder solved off by (dR, dt) while the cylinder's markers give
    its pose right: the lamps are given in the holder's frame, so every lamp sits, against the
    true sample and camera, at ``dR L + R_hold^T dt`` instead of ``L``. The draws' angles must
    equal the angles of the draw's geometry without the move and with each lamp so moved - an
    identity of rigid motions, exact up to rounding (bound 1e-9 rad against angle changes of
    ~1e-3 rad from a 0.2 degree turn)."""
    from test_calibration_uncertainty import _board_views

    from glossrig.core.calibration.intrinsics import board_points
    from glossrig.core.fitting import calibration_uncertainty as cu

    views = _board_views()
    cv = cu.CameraViews(obj=board_points((9, 6), 25.0), rvecs=[v[0] for v in views], tvecs=[v[1] for v in views],
                        rms_px=0.15)
    px = cov.pixel_geometry(rig, SCALE)
    draws = EB.CalibrationDraws(rig, px, cv, 3, 7, pose_rot_deg=(0.1, 0.2, 0.05), pose_t_mm=(0.05, 0.1, 0.2),
                                captures=("sample",))
    assert draws.moves_sample and all(m is None for m in draws.lamp_capture_moves)
    moves = draws._pose_moves(np.random.default_rng([7, 5, 1]))     # rotation 1's stream
    n = draws.u.size
    for led in LEDS:
        nominal, drawn = draws.angles(led, 1)
        lamp = np.asarray(rig.led(led).position, float)
        for (K, dist, poses), resolved, got, ((dR, dt), _cyl) in zip(draws.draws, draws.resolved_shifts(led), drawn,
                                                                      moves):
            Rh = poses[0.0][0][0]
            moved = dR @ (lamp + resolved) + Rh.T @ dt
            want = cu.row_angles(draws.cal, draws.u, draws.v, np.full(n, led), np.zeros(n), K=K, dist=dist,
                                 poses=poses, lamps={led: moved})
            held = cu.row_angles(draws.cal, draws.u, draws.v, np.full(n, led), np.zeros(n), K=K, dist=dist,
                                 poses=poses, lamps={led: lamp + resolved})
            ok = want["valid"] & np.isfinite(got["theta_in"])
            assert ok.sum() > 1000
            for k in ("theta_in", "phi_in", "theta_out", "theta_h", "phi_h"):
                assert np.max(np.abs(got[k][ok] - want[k][ok])) < 1e-9, (led, k)
            assert np.max(np.abs(held["theta_in"][ok] - want["theta_in"][ok])) > 1e-3



def test_calibration_draws_grow_until_their_monte_carlo_settles(rig, monkeypatch):
    """The calibration draws are an adaptive Monte Carlo (GUM-S1 7.9, ``EB.budget_and_bound``): a
    material whose combined figure is not yet known to ``mc_rel_tol`` gets twice the draws, the
    earlier ones kept and pooled, up to ``mc_max_draws``. The pooled passes give exactly what one
    pass over as many draws gives (the same random streams), a tolerance no figure meets stops at
    the cap and says it did not settle, a tolerance every figure meets stops at the first pass. (The
    recorded Monte Carlo uncertainty against independent refits of the same draws:
    test_intrinsics_term_equals_the_spread_of_nonlinear_refits.)"""
    from test_calibration_uncertainty import _board_views

    from glossrig.core.calibration.intrinsics import board_points
    from glossrig.core.fitting.calibration_uncertainty import CameraViews

    views = _board_views()
    cv = CameraViews(obj=board_points((9, 6), 25.0), rvecs=[v[0] for v in views], tvecs=[v[1] for v in views],
                     rms_px=0.15)
    monkeypatch.setattr(EB, "MC_START_DRAWS", 3)
    kw = dict(rotations=[0.0], led_ids=[8], scale=SCALE, noise="relative:0.03", fisher_rows=ROWS, lamp_std_mm=0.0,
              camera_views=cv, seed=5, **{**ONLY, "pose_rot_deg": None, "pose_t_mm": None})
    mats = [("s", P), ("w", WIDE)]
    capped = EB.design_budget(rig, mats, mc_rel_tol=0.0, mc_max_draws=12, **kw)
    one_pass = EB.design_budget(rig, mats, intrinsics_draws=12, **kw)
    loose = EB.design_budget(rig, mats, mc_rel_tol=math.inf, **kw)
    # "exactly" up to OpenCV's calibrateCamera, which is not bit-reproducible from run to run (its
    # threads): the same draw's camera differs by ~1e-7 relative and its lamp solution by ~1e-4 mm
    # (of shifts ~1 mm), so a figure by ~1e-4 relative at most; an unpooled or mis-streamed draw
    # would move it by its own Monte Carlo uncertainty (per cent)
    for label, _ in mats:
        c, o = capped[label], one_pass[label]
        assert c["calibration_draws"] == 12 and c["calibration_mc_settled"] is False
        assert "12 draws" in c["stated"]["intrinsics"]
        assert loose[label]["calibration_draws"] == 3 and loose[label]["calibration_mc_settled"] is True
        for k in fi.PARAMS:
            assert c["combined"][k] == pytest.approx(o["combined"][k], rel=1e-3), (label, k)
            assert c["calibration_mc_rel_u"][k] == pytest.approx(o["calibration_mc_rel_u"][k], rel=1e-2), (label, k)
            assert 0 < c["calibration_mc_rel_u"][k] < 1, (label, k)
