"""Rig design: Fisher-information errors (glossrig.core.design.fisher), mounting limits,
the design sweep and selection (glossrig.core.design.placement), and the design CLI."""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from glossrig.core.design import coverage as cov
from glossrig.core.design import placement as D
from glossrig.core.design import fisher as fi
from glossrig.core.errors import InputError
from glossrig.core.runners import DaskRunner, LocalRunner
from glossrig.core.rig import load_rig
from glossrig.core.models.ward import WardParams, ward_from_angles

from helpers import assert_image_has_content

BRUSHED = WardParams(rho_d=0.173, rho_s=0.045, alpha_x=0.0354, alpha_y=0.0106, lobe_rotation=2.19)
BROAD = WardParams(rho_d=0.05, rho_s=0.3, alpha_x=0.25, alpha_y=0.12, lobe_rotation=0.4)


def _angles(n, seed=0, spread=0.6):
    rng = np.random.default_rng(seed)
    ti = rng.uniform(0.05, 1.3, n)
    to = rng.uniform(0.05, 1.3, n)
    th = rng.uniform(0.0, spread, n)
    ph = rng.uniform(0, 2 * np.pi, n)
    return ti, to, th, ph


# ----------------------------------------------------------------------------
# Fisher information
# ----------------------------------------------------------------------------

@pytest.mark.parametrize("p", [BRUSHED, BROAD])
def test_jacobian_matches_finite_differences(p):
    ti, to, th, ph = _angles(400, spread=0.15 if p is BRUSHED else 0.8)
    f, J = fi.ward_jacobian(ti, to, th, ph, p)
    np.testing.assert_allclose(f, ward_from_angles(ti, to, th, ph, p), rtol=1e-12)
    x = np.array([p.rho_d, p.rho_s, p.alpha_x, p.alpha_y, p.lobe_rotation])
    for k in range(5):
        h = 1e-6 * max(abs(x[k]), 1e-3)
        up, dn = x.copy(), x.copy()
        up[k] += h
        dn[k] -= h
        fd = (ward_from_angles(ti, to, th, ph, WardParams(*up)) - ward_from_angles(ti, to, th, ph, WardParams(*dn))) / (2 * h)
        np.testing.assert_allclose(J[:, k], fd, rtol=1e-5, atol=1e-8 * np.abs(fd).max())


def test_fisher_errors_predict_the_scatter_of_weighted_fits():
    """Cramer-Rao check: fit noisy synthetic data repeatedly by inverse-variance
    weighted least squares; the spread of the estimates is what I^-1 says."""
    from scipy.optimize import least_squares

    p = BROAD
    ti, to, th, ph = _angles(300, seed=1, spread=0.7)
    noise = fi.RelativeNoise(0.05)
    e = fi.expected_errors(ti, to, th, ph, np.cos(ti), np.full(ti.size, 300.0), p, noise)
    f0 = ward_from_angles(ti, to, th, ph, p)
    sig = noise.sigma(f0)
    rng = np.random.default_rng(7)
    x0 = np.array([p.rho_d, p.rho_s, p.alpha_x, p.alpha_y, p.lobe_rotation])
    est = []
    for _ in range(150):
        y = f0 + rng.normal(0, sig)

        def res(x, y=y):
            return (ward_from_angles(ti, to, th, ph, WardParams(*np.maximum(x[:4], 1e-6), x[4])) - y) / sig

        est.append(least_squares(res, x0, method="lm").x)
    emp = np.std(np.array(est), axis=0, ddof=1)
    pred = np.array([e.stderr[k] for k in fi.PARAMS])
    np.testing.assert_allclose(emp, pred, rtol=0.25)


def test_isotropic_lobe_rotation_is_not_identifiable():
    p = WardParams(0.1, 0.08, 0.08, 0.08, 0.0)
    ti, to, th, ph = _angles(300, spread=0.5)
    e = fi.expected_errors(ti, to, th, ph, np.cos(ti), np.full(ti.size, 300.0), p, fi.RelativeNoise(0.03))
    assert math.isinf(e.stderr["lobe_rotation"])
    assert all(math.isfinite(e.stderr[k]) for k in fi.PARAMS[:4])
    assert math.isfinite(e.geometric_mean_relative)


def test_more_samples_less_error_and_mirror_weighting_is_no_better():
    ti, to, th, ph = _angles(600, seed=3)
    n = fi.RelativeNoise(0.03)
    args = (np.cos(ti), np.full(ti.size, 300.0), BROAD, n)
    half = fi.expected_errors(ti[:300], to[:300], th[:300], ph[:300], args[0][:300], args[1][:300], BROAD, n)
    full = fi.expected_errors(ti, to, th, ph, *args)
    assert all(full.stderr[k] < half.stderr[k] for k in fi.PARAMS)
    # weights as multiplicities: 300 rows counted twice == information of 600 rows with the same angles
    dbl = fi.expected_errors(ti[:300], to[:300], th[:300], ph[:300], args[0][:300], args[1][:300], BROAD, n,
                             weight=np.full(300, 2.0))
    np.testing.assert_allclose([dbl.stderr[k] * math.sqrt(2) for k in fi.PARAMS],
                               [half.stderr[k] for k in fi.PARAMS], rtol=1e-10)
    phi_in = np.random.default_rng(4).uniform(0, 2 * np.pi, 600)
    mir = fi.expected_errors(ti, to, th, ph, *args, weighting="mirror", phi_in=phi_in, phi_out=phi_in + 1.0)
    assert all(mir.stderr[k] >= full.stderr[k] * (1 - 1e-9) for k in fi.PARAMS)   # Cramer-Rao bound


def test_hdr_noise_from_the_rig(rig):
    n = fi.HdrNoise.from_rig(rig)
    f = np.array([1e-3, 0.05, 1.0, 30.0])
    rel = n.relative(f, np.full(4, 0.8), np.full(4, 300.0))
    assert np.all(rel >= n.led_rel) and np.all(np.isfinite(rel))
    assert rel[0] > rel[1] > rel[2] * 0.999          # dimmer values are noisier
    # one exposure, by hand: var(rate) = (e + D t + read^2 + K^2/12) / t^2
    one = fi.HdrNoise(electrons_per_radiance_s=1000.0, radiant_intensity_W_sr=1.0, times_s=(1.0,), conversion_gain=2.0,
                      saturation_e=1e9, read_noise_e=3.0, dark_current_e_s=0.5, led_rel=0.0)
    L = 0.2 * 1.0 * 0.5 / 0.3 ** 2
    e = 1000.0 * L
    np.testing.assert_allclose(one.relative(np.array([0.2]), np.array([0.5]), np.array([300.0]))[0],
                               math.sqrt(e + 0.5 + 9.0 + 4.0 / 12) / e, rtol=1e-12)
    sat = fi.HdrNoise(electrons_per_radiance_s=1e12, radiant_intensity_W_sr=1.0, times_s=(1.0,), conversion_gain=1.0,
                      saturation_e=100.0, read_noise_e=1.0, dark_current_e_s=0.0)
    assert np.isinf(sat.relative(np.array([1.0]), np.array([1.0]), np.array([300.0]))[0])


def test_noise_model_specs(rig):
    assert isinstance(fi.noise_model("hdr", rig), fi.HdrNoise)
    assert fi.noise_model("hdr:0.02", rig).led_rel == 0.02
    assert fi.noise_model("relative:0.05").rel == 0.05
    for bad in ("gauss", "relative:x", "relative:-1"):
        with pytest.raises(InputError):
            fi.noise_model(bad, rig)


# ----------------------------------------------------------------------------
# Mounting limits
# ----------------------------------------------------------------------------

def test_thesis_rig_is_within_the_limits(rig):
    assert D.design_problems(rig, [led.position for led in rig.leds]) == []


def test_led_problems(rig):
    lim = D.MountingLimits()
    in_view = D.led_problems(rig, D.mount_position(2.0, 0.0, 200.0), lim)
    assert any("camera" in m for m in in_view)
    assert any("distance" in m for m in D.led_problems(rig, D.mount_position(40.0, 0.0, 400.0), lim))
    assert any("height" in m for m in D.led_problems(rig, D.mount_position(40.0, 200.0, 300.0), lim))
    assert any("board" in m for m in D.led_problems(rig, D.mount_position(170.0, 0.0, 300.0), lim))
    assert D.led_problems(rig, D.mount_position(40.0, 60.0, 250.0), lim) == []
    # just outside the field of view is fine, just inside is not
    cam = rig.camera
    half = math.degrees(math.atan(cam.image_px[1] / 2 / cam.fy))
    assert D.camera_sees(rig, D.mount_position(1.0, 0.0, 150.0)[None, :])[0]
    assert not D.camera_sees(rig, D.mount_position(3 * half + 10, 0.0, 150.0)[None, :])[0]


def test_conflicts(rig):
    pos = np.array([D.mount_position(40.0, 0.0, 300.0),     # behind the next one
                    D.mount_position(40.0, 0.0, 150.0),
                    D.mount_position(40.0, 13.5, 300.0),    # same post as the first, 13.5 mm up
                    D.mount_position(40.0, 5.0, 300.0),     # same post, too close
                    D.mount_position(-60.0, 0.0, 250.0),
                    D.mount_position(-57.0, 0.0, 250.0)])   # posts 13 mm apart
    c = D.conflicts(rig, pos)
    assert c[0, 1] and c[1, 0]                 # the near post shadows the far LED
    assert not c[0, 2] and c[0, 3] and c[2, 3]
    assert c[4, 5] and not c[0, 4]
    assert np.array_equal(c, c.T) and not np.any(np.diag(c))


def test_mount_round_trip():
    for m in [(35.0, -20.0, 150.0), (-120.0, 100.0, 350.0)]:
        np.testing.assert_allclose(D.mount_of(D.mount_position(*m)), m, atol=1e-9)


# ----------------------------------------------------------------------------
# Sweep and selection
# ----------------------------------------------------------------------------

MATS = [("brushed", BRUSHED), ("broad", BROAD)]


@pytest.fixture(scope="module")
def setup(rig):
    return D.make_setup(rig, MATS, rotations=(-45, 0, 45, 90), coverage_scale=0.05, fisher_scale=0.05,
                        fisher_rows=800)


def test_led_codes_equal_direct_binning_at_every_rotation(rig, setup):
    led = rig.led(7)
    ev = D.evaluate_led(setup, led.position)
    data = cov.collect(rig, led_ids=[7], rotations=[-45.0, 0.0, 45.0, 90.0], pixels=setup.cov_pixels, filters=("lit",))
    for r in (-45, 0, 45, 90):
        assert np.array_equal(ev.aniso_codes([r]), np.sort(data.aniso[("lit", 7, float(r))]))
    assert np.array_equal(np.sort(ev.iso), np.sort(data.iso[("lit", 7, "folded")]))


def test_led_information_matches_direct_fisher(rig, setup):
    """The sweep's per-LED information (thinned rows with multiplicities) is close
    to the information of every lit pixel."""
    led = rig.led(10)
    ev = D.evaluate_led(setup, led.position)
    a = cov.direction_angles(setup.fisher_pixels, led.position, half=True)
    m = a["lit"]
    for j, (_, p) in enumerate(MATS):
        f, J = fi.ward_jacobian(np.radians(a["theta_in"][m]), np.radians(a["theta_out"][m]), np.radians(a["theta_h"][m]),
                                np.radians(np.mod(a["phi_h"][m] - 45, 360)), p)
        I = fi.information(J, setup.noise.sigma(f, a["cos_in"][m], a["dist_in"][m]))
        I_sweep = ev.info[setup.rotations.index(45), j]
        se = np.sqrt(np.diag(np.linalg.inv(I)))
        se_sweep = np.sqrt(np.diag(np.linalg.inv(I_sweep)))
        np.testing.assert_allclose(se_sweep, se, rtol=0.15)


def _small_pool(rig, setup, n_extra=10):
    mounts = [(a, h, 250.0) for a in (-100, -70, -40, 30, 60, 90) for h in (0.0, 60.0)]
    pos = [D.mount_position(*m) for m in mounts]
    ref = [np.asarray(rig.led(i).position) for i in rig.led_ids()]
    evals = D.evaluate_chunk(setup, pos + ref)
    n = len(pos)
    pool = D.Pool(evals=evals, conflict=np.ones((len(evals), len(evals)), bool), rotations=setup.rotations,
                  materials=MATS, lam=1.0, iso_weight=1.0)
    pool.conflict[:n, :n] = D.conflicts(rig, np.array(pos))
    ref_idx = list(range(n, len(evals)))
    pool.ref_coverage = pool.coverage_bins(ref_idx, [-45, 0, 45, 90]) / D.ANISO_TOTAL
    pool.ref_errors = pool.errors_from_information(pool.information(ref_idx, [-45, 0, 45, 90]))
    pool.ref_iso = pool.iso_bins(ref_idx) / D.ISO_TOTAL
    ok = np.zeros(len(evals), bool)
    ok[:n] = True
    return pool, ok, ref_idx


def test_pool_terms_are_additive_and_reference_scores_zero(rig, setup):
    pool, ok, ref_idx = _small_pool(rig, setup)
    assert pool.score(ref_idx, [-45, 0, 45, 90]) == pytest.approx(0.0, abs=1e-12)
    I = pool.information([0, 3], [0, 45])
    I_sum = sum(pool.evals[i].info[pool.rot_idx([r])[0]] for i in (0, 3) for r in (0, 45))
    np.testing.assert_allclose(I, I_sum)
    u = pool.union([0, 3], [0, 45])
    assert len(u) <= len(pool.evals[0].aniso_codes([0, 45])) + len(pool.evals[3].aniso_codes([0, 45]))
    # batched errors equal the one-by-one errors
    batch = pool.batch_errors(np.stack([pool.information([i], [0, 45]) for i in range(4)]))
    for i in range(4):
        np.testing.assert_allclose(batch[i], pool.errors_from_information(pool.information([i], [0, 45])), rtol=1e-9)


def test_selection_improves_monotonically_and_respects_conflicts(rig, setup):
    pool, ok, _ = _small_pool(rig, setup)
    leds, traj = D.select_leds(pool, 5, [-45, 0, 45, 90], feasible=ok)
    assert len(set(leds)) == 5 and all(ok[i] for i in leds)
    assert traj == sorted(traj)                     # adding an LED never lowers the score
    assert not any(pool.conflict[i, j] for i in leds for j in leds if i != j)
    assert pool.score(leds, [-45, 0, 45, 90]) >= traj[-1] - 1e-12
    rots = D.select_rotations(pool, leds, 2)
    assert len(rots) == 2 and set(rots) <= set(setup.rotations)
    best_pair = max(((a, b) for a in setup.rotations for b in setup.rotations if a < b),
                    key=lambda rb: pool.score(leds, list(rb)))
    assert pool.score(leds, rots) == pytest.approx(pool.score(leds, list(best_pair)))
    with pytest.raises(InputError, match="compatible"):
        D.select_leds(pool, 13, [0], feasible=ok)


TINY = dict(space=D.SearchSpace(angle_step_deg=45.0, heights_mm=(0.0, 60.0), distances_mm=(250.0,),
                                rotations_deg=(-90, -45, 0, 45, 90)),
            n_rotations=2, coverage_scale=0.05, fisher_scale=0.05, chunk=3, rounds=2, progress=False)


def test_optimise_in_one_process_and_on_dask_agree(rig):
    pytest.importorskip("distributed")
    mats = [("brushed", BRUSHED)]
    local = D.optimise(rig, 3, mats, LocalRunner(), **TINY)
    runner = DaskRunner(workers=2)
    try:
        dask = D.optimise(rig, 3, mats, runner, **TINY)
    finally:
        runner.close()
    assert np.array_equal(local.positions, dask.positions)
    assert local.rotations == dask.rotations and local.score == dask.score
    assert local.errors == dask.errors and local.coverage == dask.coverage
    assert D.design_problems(rig, local.positions) == []
    assert local.score > local.trajectory[0]


def test_unreachable_scheduler_is_a_clear_error():
    pytest.importorskip("distributed")
    with pytest.raises(InputError, match="cannot reach the Dask scheduler"):
        DaskRunner(address="tcp://127.0.0.1:1", timeout_s=0.5)


def test_optimise_refuses_bad_input(rig):
    with pytest.raises(InputError, match="--leds"):
        D.optimise(rig, 17, MATS, LocalRunner(), **TINY)
    with pytest.raises(InputError, match="lambda"):
        D.optimise(rig, 2, MATS, LocalRunner(), lam=-1.0, **TINY)
    with pytest.raises(InputError, match="isotropic"):
        D.optimise(rig, 2, MATS, LocalRunner(), iso_weight=float("nan"), **TINY)
    with pytest.raises(InputError, match="whole degrees"):
        D.SearchSpace(rotations_deg=(0, 22.5))
    with pytest.raises(InputError, match="extended-Ward"):
        D.parse_materials("white_paper,reference_paper")
    with pytest.raises(InputError, match="unknown material"):
        D.parse_materials("no_such_material")
    assert [lb for lb, _ in D.parse_materials("brushed_original,ward:rho_d=0.1,rho_s=0.1,alpha_x=0.1,alpha_y=0.2,base_2")] \
        == ["brushed_original", "ward:rho_d=0.1,rho_s=0.1,alpha_x=0.1,alpha_y=0.2", "base_2"]


def test_write_rig_round_trip(rig, tmp_path):
    pos = np.array([D.mount_position(40.0, 60.0, 250.0), D.mount_position(-70.0, -20.0, 150.0),
                    D.mount_position(100.0, 0.0, 350.0)])
    out = D.write_rig_toml(rig.path, pos, [-30, 0, 60], tmp_path / "new.toml", header="# test\n")
    new = load_rig(out)
    assert new.name == "optimised" and new.sample_rotations == (-30.0, 0.0, 60.0)
    np.testing.assert_allclose([led.position for led in new.leds], pos, atol=0.06)
    assert [led.channel for led in new.leds] == [1, 2, 3]
    assert new.camera == rig.camera and new.sensor == rig.sensor
    with pytest.raises(InputError, match="overwrite the template"):
        D.write_rig_toml(rig.path, pos, [0], rig.path)


def test_cli_optimise_tiny(tmp_path):
    from glossrig.cli.main import main

    out = tmp_path / "r.toml"
    rep = tmp_path / "rep"
    argv = ["design", "optimise", "--rig", "scenes/thesis_rig.toml", "--leds", "3", "--materials", "base_2",
            "--out", str(out), "--report", str(rep), "--workers", "0", "--angle-step", "45", "--heights", "0,60",
            "--distances", "250", "--rotation-step", "90", "--rotations", "2", "--scale", "0.05",
            "--final-scale", "0.05", "--quiet"]
    assert main(argv) == 0
    new = load_rig(out)
    assert len(new.leds) == 3 and len(new.sample_rotations) == 2
    rep_json = json.loads((rep / "design.json").read_text())
    assert set(rep_json["rigs"]) == {"thesis_16", "thesis_middle", "optimised"}
    # figsize width / height of each figure (core/design/plots.py, core/design/coverage.py)
    aspects = {"layout.png": 12 / 5.5, "expected_errors.png": 4.5 / 4,            # one material
               "aniso_by_rotation.png": 3 * 5.2 / 4.0, "theta_per_led.png": 6.4 / 6.0}   # three rigs
    for f, aspect in aspects.items():
        assert_image_has_content(rep / f, aspect=aspect, min_size=(400, 400))
    assert main(argv) == 2                           # exists: no overwrite without --force


def test_cli_optimise_bad_input(tmp_path, capsys):
    from glossrig.cli.main import main

    base = ["design", "optimise", "--rig", "scenes/thesis_rig.toml", "--out", str(tmp_path / "r.toml"), "--workers", "0"]
    assert main(base + ["--leds", "17"]) == 2
    assert "relay" in capsys.readouterr().err
    assert main(base + ["--leds", "4", "--materials", "reference_paper"]) == 2
    assert main(base + ["--leds", "4", "--rotation-step", "7"]) == 2
    assert "divide 360" in capsys.readouterr().err


def test_sequence_gain_nuisance_equals_the_correlated_covariance_and_does_not_average_out():
    """gain_marginal_information is J^T (diag(sigma^2) + g^2 f f^T)^-1 J (Woodbury), and
    with it rho_d's relative error of a sequence levels off at the gain error instead of
    falling as 1/sqrt(pixels)."""
    from glossrig.core.design import fisher as fi
    from glossrig.core.models.ward import WardParams

    rng = np.random.default_rng(4)
    p = WardParams(0.05, 0.007, 0.06, 0.034, 2.47)
    n = 300
    ti, to = rng.uniform(0.1, 1.2, n), rng.uniform(0.1, 1.2, n)
    th, ph = rng.uniform(0, 0.4, n), rng.uniform(0, 2 * np.pi, n)
    f, J = fi.ward_jacobian(ti, to, th, ph, p)
    sigma = 0.01 * f
    g = 0.004
    direct = J.T @ np.linalg.solve(np.diag(sigma ** 2) + g * g * np.outer(f, f), J)
    np.testing.assert_allclose(fi.gain_marginal_information(J, sigma, f, g), direct, rtol=1e-6, atol=1e-9 * direct.max())
    np.testing.assert_array_equal(fi.gain_marginal_information(J, sigma, f, 0.0), fi.information(J, sigma))
    # a Lambertian-only parameter: rho_d's error from N pixels of one sequence
    Jd = np.full((1, 1), 1 / np.pi)                          # f = rho_d / pi, one row standing for npx pixels
    fd = np.array([0.05 / np.pi])
    for npx in (1e3, 1e6):
        w = np.array([npx])
        I0 = fi.information(Jd, 0.01 * fd, w)[0, 0]
        Ig = fi.gain_marginal_information(Jd, 0.01 * fd, fd, g, w)[0, 0]
        rel0, relg = 1 / np.sqrt(I0) / 0.05, 1 / np.sqrt(Ig) / 0.05
        assert rel0 == pytest.approx(0.01 / np.sqrt(npx))
        assert relg == pytest.approx(np.hypot(g, rel0), rel=1e-6)
