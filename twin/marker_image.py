"""The holder marker imaged without Monte Carlo: a reference for the renderer's image formation.

The canvas (pinhole, ``LensMap.focal``) holds each fine pixel's exact area
coverage of the red frame and the white patch; :meth:`LensMap.apply` then images
it through the lens exactly as the twin's renders are, and the sensor's
noise-free response (or one noisy exposure) makes the raw mosaic. On the nominal
rig the marker faces the camera squarely, so its edges are canvas rows and
columns and a fine pixel's coverage is the product of its coverages along x and
y - exact away from the corners, which the pose refinement leaves out
(:func:`glossrig.core.calibration.poses.refine_pose_edges` margins). Used by
tests/test_twin_lens.py and validation/calibration_study.py to separate the
canvas discretisation from Monte Carlo and sensor noise.
"""
from __future__ import annotations

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.calibration.markers import holder_marker_corners

#: Radiances (W m^-2 sr^-1, RGB) at the holder in the twin's calibration image (scale 0.15,
#: seed 2, all LEDs): dark holder, red frame, white patch.
HOLDER_RADIANCE = {"holder": (0.17, 0.21, 0.25), "red": (2.73, 0.25, 0.29), "white": (3.9, 4.87, 5.75)}


def holder_marker_radiance(rig, lens, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(h, w, 3) radiance of the holder marker seen with pose ``R``, ``t`` (holder ->
    camera, mm) through ``lens`` (a :class:`glossrig.twin.render.LensMap`)."""
    R, t = np.asarray(R, np.float64), np.asarray(t, np.float64)
    cw, ch = lens.canvas

    def coverage(inner: bool) -> np.ndarray:
        X = holder_marker_corners(rig, inner=inner) @ R.T + t
        x = X[:, 0] / X[:, 2] * lens.focal + cw / 2 - 0.5
        y = X[:, 1] / X[:, 2] * lens.focal + ch / 2 - 0.5
        if len(np.unique(np.round(x, 6))) != 2 or len(np.unique(np.round(y, 6))) != 2:
            raise InputError("marker_image: the holder marker must face the camera squarely "
                             "(edges along canvas rows and columns)")

        def along(lo, hi, n):
            k = np.arange(n)
            return np.clip(np.minimum(hi, k + 0.5) - np.maximum(lo, k - 0.5), 0.0, 1.0)

        return np.outer(along(y.min(), y.max(), ch), along(x.min(), x.max(), cw)).astype(np.float32)

    bg, red, white = (np.asarray(HOLDER_RADIANCE[k], np.float32) for k in ("holder", "red", "white"))
    img = np.empty((ch, cw, 3), np.float32)
    img[:] = bg
    img += (red - bg) * coverage(False)[..., None]
    img += (white - red) * coverage(True)[..., None]
    return lens.apply(img)


def holder_marker_mosaic(rig, lens, R: np.ndarray, t: np.ndarray, rng: np.random.Generator | None = None):
    """Linear raw mosaic (the calibration exposure of ``rig``) of
    :func:`holder_marker_radiance`: the sensor's noise-free response, or one noisy
    exposure drawn with ``rng``."""
    from glossrig.core.calibration.raw import linearize_mosaic
    from .sensor import SensorModel

    S = SensorModel.from_rig(rig)
    rad = holder_marker_radiance(rig, lens, R, t)
    args = (rad, rig.calibration_time_s, rig.calibration_iso, rig.calibration_aperture)
    dn = S.expected_dn(*args) if rng is None else S.expose(*args, rng)
    return linearize_mosaic(dn, S.black_2x2(), S.white_level)
