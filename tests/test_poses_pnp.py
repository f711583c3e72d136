"""The holder marker's corner PnP (core/calibration/poses.py ``pnp``) at several image scales.

The holder marker lies in the plane z = 30 mm of the holder frame. OpenCV's IPPE given
those points directly put the pose hundreds of pixels off; the LM refinement rescued it
most of the time but not always (on the scale-0.2 twin it stopped at 43.9 px RMS and
``calibrate lamps`` failed with "too few unclipped pixels along an edge"). The solver now
works in the points' own plane frame.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from glossrig.core.calibration.markers import holder_marker_corners
from glossrig.core.calibration.poses import _plane_frame, pnp
from glossrig.core.rig import default_rig_path, load_rig

#: The twin's camera at full resolution (truth.json of a capture, divided by its scale) and
#: its holder pose (holder -> camera).
K_FULL = np.array([[15684.6177, 0, 3011.5], [0, 15706.9933, 2011.5], [0, 0, 1.0]])
DIST = np.array([0.347129348, 4.40188132, -0.00313664067, -0.000732801325, -76.3604996])
R_NOMINAL = np.array([[0, -1, 0], [-1, 0, 0], [0, 0, -1.0]])
NOISE_PX = 0.1          # corner noise per image axis (the twin's corners: PnP RMS ~0.2 px)


@pytest.mark.parametrize("scale", [0.1, 0.2, 0.5])
def test_holder_pnp_finds_the_pose_at_any_scale(scale):
    rig = load_rig(default_rig_path())
    obj = np.concatenate([holder_marker_corners(rig), holder_marker_corners(rig, inner=True)])
    K = K_FULL * np.array([scale, scale, 1.0])[:, None]
    rng = np.random.default_rng(7)
    n, p = 2 * len(obj), 6
    # residual RMS of a least-squares fit of p parameters to n noisy coordinates:
    # NOISE_PX sqrt((n - p) / n) per axis, sqrt(2) of it per corner; 3 times that bounds it
    rms_bound = 3 * NOISE_PX * np.sqrt(2 * (n - p) / n)
    for _ in range(20):
        R = cv2.Rodrigues(np.radians(rng.normal(0, 1, 3)))[0] @ R_NOMINAL
        t = np.array([0, 0, 500.0]) + rng.normal(0, 2, 3)
        img = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, DIST)[0].reshape(-1, 2)
        R_hat, t_hat, rms = pnp(obj, img + rng.normal(0, NOISE_PX, img.shape), K, DIST, True, "holder marker")
        assert rms < rms_bound
        # the pose itself: noise-free corners give it to solver precision
        R0, t0, rms0 = pnp(obj, img, K, DIST, True, "holder marker")
        assert rms0 < 1e-6 and np.abs(t0 - t).max() < 1e-5 and np.abs(R0 - R).max() < 1e-8


def test_plane_frame_rejects_points_off_one_plane():
    rig = load_rig(default_rig_path())
    obj = np.concatenate([holder_marker_corners(rig), holder_marker_corners(rig, inner=True)])
    c, B = _plane_frame(obj)
    assert np.abs(((obj - c) @ B.T)[:, 2]).max() < 1e-9 and np.isclose(np.linalg.det(B), 1.0)
    bent = obj.copy()
    bent[0, 2] += 1.0
    with pytest.raises(ValueError, match="coplanar"):
        _plane_frame(bent)
