"""The stated uncertainty of a calibrated lamp position (core/calibration/lamps.py).

``refine_with_diffuse`` states the noise covariance of its solve (``noise_cov_mm2``,
s^2 (J^T J)^-1 mapped to the holder frame); here it is compared with the scatter of the
refined position over independent noise realisations of the same synthetic capture.
The geometry part of the stated uncertainty (draws of the camera calibration and poses)
is checked against the twin's truth in validation/uncertainty_coverage.md (section 2).
"""
from __future__ import annotations

import numpy as np

from glossrig.core.calibration.lamps import refine_with_diffuse

RADIUS, DISTANCE = 25.8, 300.0          # the rig's sample radius and LED distance from the axis (mm)
REPEATS = 30
NOISE = 0.004                           # shot-noise-like: sd of a value v is NOISE sqrt(v) (relative units)


def _surface():
    phi, y = np.meshgrid(np.radians(np.linspace(-70, 70, 140)), np.linspace(-20, 20, 40))
    n = np.stack([np.sin(phi), np.zeros_like(phi), np.cos(phi)], axis=-1).reshape(-1, 3)
    return RADIUS * n + np.stack([np.zeros(phi.size), y.ravel(), np.zeros(phi.size)], axis=-1), n


def test_refinement_noise_covariance_matches_the_scatter_of_refits():
    pts, nrm = _surface()
    az = np.radians(30.0)
    lamp = np.array([DISTANCE * np.sin(az), 5.0, DISTANCE * np.cos(az)])
    d = lamp - pts
    r2 = np.sum(d * d, axis=1)
    clean = 1e4 * np.maximum(np.sum(d * nrm, axis=1) / np.sqrt(r2), 0) / r2
    ok = clean > 0
    pts, nrm, clean = pts[ok], nrm[ok], clean[ok]
    axis_point, axis_dir = np.zeros(3), np.array([0.0, 1.0, 0.0])
    start = lamp + np.array([1.5, -1.0, -0.5])
    rng = np.random.default_rng(3)
    est, stated = [], []
    scale = np.sqrt(clean.mean())
    for _ in range(REPEATS):
        v = clean + NOISE * scale * np.sqrt(clean / clean.mean()) * rng.standard_normal(clean.size)
        L, st = refine_with_diffuse(start, pts, nrm, v, DISTANCE, axis_point, axis_dir)
        est.append(L)
        stated.append(np.sqrt(np.diag(st["noise_cov_mm2"])))
    est = np.asarray(est)
    scatter = est.std(axis=0, ddof=1)
    stated_mean = np.mean(stated, axis=0)
    # an sd from REPEATS refits is uncertain by 1 / sqrt(2 (REPEATS - 1)) = 13 %: 3 of those
    # each way bounds the ratio (0.6, 1.65)
    rel = 3 / np.sqrt(2 * (REPEATS - 1))
    ratio = stated_mean / scatter
    assert np.all(ratio > 1 - rel) and np.all(ratio < 1 / (1 - rel)), (stated_mean, scatter)
    # unbiased to within the scatter: the mean over the refits is the true lamp
    assert np.all(np.abs(est.mean(axis=0) - lamp) < 4 * scatter / np.sqrt(REPEATS) + 1e-9)


def test_calibrate_lamps_draws_default_is_the_cores_and_the_help_shows_it():
    """``calibrate lamps --draws`` defaults to :data:`LAMP_DRAWS` and its help states that
    value (it once said 24 over a default of None, with the core filling it in)."""
    from glossrig.cli.main import build_parser
    from glossrig.core.calibration.lamps import LAMP_DRAWS

    parser = build_parser()
    args = parser.parse_args(["calibrate", "lamps", "spec", "--camera", "c.json", "--out", "l.json"])
    assert args.draws == LAMP_DRAWS and args.seed == 0
    lamps = next(a for a in parser._actions if a.dest == "verb").choices["calibrate"]
    sub = next(a for a in lamps._actions if a.dest == "subverb").choices["lamps"]
    text = " ".join(sub.format_help().split())
    assert f"stated uncertainty (default: {LAMP_DRAWS})" in text and "(default: 0)" in text, text
