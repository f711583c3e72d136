"""Rendering the rig through the real lens: pinhole render + OpenCV distortion resampling.

Mitsuba has no lens distortion, and its perspective sensor cannot express
fx != fy. We render a pinhole image with focal length ``fx`` on a canvas that
covers every ray the real (distorted) image needs, then resample: for each
output pixel (u, v), ``cv2.undistortPoints`` gives the ideal normalised ray
(x, y) under the calibrated k1 k2 p1 p2 k3 model, and the pinhole canvas is
read at ``(fx x + c, fx y + c')``. The pipeline undoes exactly this model with
the same coefficients (glossrig.core.cylinder.undistorted_rays), so fy enters
only here.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from glossrig.core.cylinder import undistorted_rays


@dataclass
class LensMap:
    size: tuple[int, int]              # output (w, h)
    canvas: tuple[int, int]            # pinhole canvas (w, h)
    focal: float                       # canvas focal length (px)
    map_x: np.ndarray
    map_y: np.ndarray
    K: np.ndarray                      # output camera matrix (OpenCV)
    dist: np.ndarray

    @classmethod
    def build(cls, camera, scale: float, margin_px: int = 3) -> "LensMap":
        w, h = camera.size(scale)
        K = camera.matrix(scale)
        dist = np.asarray(camera.distortion, np.float64)
        f = K[0, 0]
        # Ideal rays of every output pixel, computed in row blocks to bound memory.
        map_x = np.empty((h, w), np.float32)
        map_y = np.empty((h, w), np.float32)
        xs = np.arange(w, dtype=np.float64)
        xy_max = np.zeros(2)
        rows = []
        block = max(1, 2_000_000 // w)
        for y0 in range(0, h, block):
            y1 = min(h, y0 + block)
            vv, uu = np.meshgrid(np.arange(y0, y1, dtype=np.float64), xs, indexing="ij")
            r = undistorted_rays(K, dist, uu, vv)[:, :2].reshape(y1 - y0, w, 2)
            xy_max = np.maximum(xy_max, np.abs(r).reshape(-1, 2).max(axis=0))
            rows.append((y0, y1, r.astype(np.float32)))
        cw = 2 * int(math.ceil(xy_max[0] * f + margin_px))
        ch = 2 * int(math.ceil(xy_max[1] * f + margin_px))
        cx, cy = cw / 2 - 0.5, ch / 2 - 0.5
        for y0, y1, r in rows:
            map_x[y0:y1] = r[..., 0] * f + cx
            map_y[y0:y1] = r[..., 1] * f + cy
        return cls(size=(w, h), canvas=(cw, ch), focal=f, map_x=map_x, map_y=map_y, K=K, dist=dist)

    def apply(self, canvas_img: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Resample a pinhole canvas image into the distorted output image."""
        interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
        return cv2.remap(np.ascontiguousarray(canvas_img), self.map_x, self.map_y, interp,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)


def render_array(scene, spp: int | None = None, seed: int = 0) -> np.ndarray:
    """Render ``scene`` and return a float32 ``(h, w, c)`` numpy array."""
    from .mitsuba_env import mitsuba

    mi = mitsuba()
    img = mi.render(scene, seed=seed, spp=spp or 0)
    return np.array(img, dtype=np.float32)
