"""Geometric calibration at the brief's configuration (scale 0.25; ~4 min of twin
rendering): opt in with ``pytest -m slow tests/test_calibration_slow.py``.

Targets (issue 3) and where the twin stops them being met - numbers and causes in
validation/calibration_report.md:
* intrinsics: focal lengths within 0.5 %, principal point within 5 px, RMS < 0.3 px - met;
* poses: 0.2 mm and 0.05 deg - met, with the twin's 4x canvas (twin/render.py): holder
  0.017 / 0.036 / 0.029 deg, cylinder in holder 0.012 / 0.049 / 0.021 deg for seeds 2 / 3 / 4
  (this test's capture is seed 2). The former 2x canvas gave 0.020 / 0.136 / 0.040 deg: its
  discretisation and Monte Carlo noise on the holder marker's row/column-aligned edges.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from glossrig.core.calibration.intrinsics import CameraCalibration, calibrate_intrinsics, save_camera
from glossrig.core.calibration.poses import calibrate_capture, rotation_angle_deg

from conftest import RIG, SHARED

pytestmark = [pytest.mark.slow, pytest.mark.mitsuba]


@pytest.fixture(scope="module")
def captures(tmp_path_factory) -> tuple[Path, Path]:
    from glossrig.twin.simulate import simulate

    root = tmp_path_factory.mktemp("calib025")
    checker = simulate(str(RIG), "lambert:0.8", "9", [0.0], 1, 0.25, 1, None, root / "checker",
                       target="checkerboard", views=12, progress=False)
    sample = simulate(str(RIG), "lambert:0.8", "9", [0.0], 1, 0.25, 2, None, root / "sample", progress=False)
    return checker, sample


def test_intrinsics_targets_at_quarter_scale(captures):
    checker, _ = captures
    t = json.loads((checker / "truth.json").read_text())
    K0 = np.array(t["camera_matrix"])
    cal, report = calibrate_intrinsics(checker)
    assert abs(cal.fx / K0[0, 0] - 1) < 0.005 and abs(cal.fy / K0[1, 1] - 1) < 0.005
    assert abs(cal.cx - K0[0, 2]) < 5 and abs(cal.cy - K0[1, 2]) < 5
    assert cal.rms_px < 0.3
    assert not report["skipped"]


def _poses_with_true_camera(capture: Path, tmp_path: Path) -> tuple[dict, dict]:
    """Geometry of ``capture`` with the twin's true intrinsics (the pose step alone)."""
    t = json.loads((capture / "truth.json").read_text())
    K = np.array(t["camera_matrix"])
    cam = save_camera(CameraCalibration(K[0, 0], K[1, 1], K[0, 2], K[1, 2], tuple(t["distortion"]),
                                        tuple(t["image_size"])), {}, tmp_path / "camera.json")
    return calibrate_capture(capture, cam), t


def test_pose_targets_at_quarter_scale(captures, tmp_path):
    _, sample = captures
    g, t = _poses_with_true_camera(sample, tmp_path)
    Rh, th = np.array(t["camera_R_holder_to_camera"]), np.array(t["camera_t_mm"])
    Rci, tci = np.array(t["cylinder_R_in_holder"]), np.array(t["cylinder_t_mm"])
    # the targets; seed 2 measured: holder 0.017 deg / 0.012 mm, cylinder 0.013 deg /
    # 0.067 mm, cylinder in holder 0.012 deg / 0.060 mm
    assert np.linalg.norm(g["holder"]["t_mm"] - th) < 0.2
    assert rotation_angle_deg(g["cylinder"]["R"], Rh @ Rci) < 0.05
    assert rotation_angle_deg(g["holder"]["R"], Rh) < 0.05
    assert rotation_angle_deg(g["cylinder_in_holder"]["R"], Rci) < 0.05
    assert np.linalg.norm(g["cylinder_in_holder"]["t_mm"] - tci) < 0.1
    # the refinement beats the thesis's corner PnP by an order of magnitude in holder tilt
    assert rotation_angle_deg(g["holder"]["corner_pnp"]["R"], Rh) > 5 * rotation_angle_deg(g["holder"]["R"], Rh)


RGL_YELLOW = SHARED / "data/rgl/vch_golden_yellow_rgb.bsdf"


@pytest.mark.needs_shared("data/rgl/vch_golden_yellow_rgb.bsdf")
def test_poses_with_a_saturated_yellow_sample(tmp_path):
    """The RGL vch_golden_yellow sample (measured BRDF) on the twin, scale 0.15: its
    highlight flanks are brighter than the white paper, and balancing on the brightest
    pixels lost the markers (validation/diagnose/rgl_study.py). Balanced on the holder's
    white patch, the poses come out (measured, seed 5: holder 0.148 deg; yellow sample,
    not the lambert one of the fast tests)."""
    from glossrig.twin.simulate import simulate

    cap = simulate(str(RIG), f"measured:{RGL_YELLOW}", "9", [0.0], 1, 0.15, 5, None, tmp_path / "yellow",
                   progress=False)
    g, t = _poses_with_true_camera(cap, tmp_path)
    Rh, th = np.array(t["camera_R_holder_to_camera"]), np.array(t["camera_t_mm"])
    Rci = np.array(t["cylinder_R_in_holder"])
    assert rotation_angle_deg(g["holder"]["R"], Rh) < 0.3
    assert np.linalg.norm(g["holder"]["t_mm"] - th) < 0.2
    assert rotation_angle_deg(g["cylinder_in_holder"]["R"], Rci) < 0.3
