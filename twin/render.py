"""Rendering the rig through the real lens: pinhole render + OpenCV distortion resampling.

Mitsuba has no lens distortion, and its perspective sensor cannot express
fx != fy. We render a pinhole image with focal length ``supersample * fx`` on a
canvas that covers every ray the real (distorted) image needs, then resample:
for each output pixel (u, v), ``cv2.undistortPoints`` gives the ideal normalised
ray (x, y) under the calibrated k1 k2 p1 p2 k3 model, and the pinhole canvas is
read at ``(s fx x + c, s fx y + c')``. The pipeline undoes exactly this model
with the same coefficients (glossrig.core.cylinder.undistorted_rays), so fy
enters only here.

Image formation: a sensor pixel integrates the irradiance over its area, so an
output pixel is the mean of the pinhole image over the pixel's footprint (its
square mapped through the inverse lens model). :meth:`LensMap.apply`
approximates that area integral by an ``n x n`` grid of sub-pixel positions
(mapped through the local Jacobian of the lens map) read bilinearly from a
canvas rendered ``s`` times finer (box filter, i.e. fine-pixel area means).
Reading one bilinear sample per output pixel from a canvas at the output
resolution - the previous scheme - blurs by the interpolation kernel with a
sub-pixel phase that is nearly constant along an edge running along a pixel
row or column, which moves such edges by up to 0.067 px at scale 0.25; with
s = n = 2 the largest shift is 0.013 px (``tests/test_twin_lens.py``: exact
area-coverage canvases near the image corners at four sub-pixel phases, fitted
with the pose refinement's edge model). The sample budget is kept: the canvas
gets ``ceil(spp / s^2)`` samples per fine pixel (:meth:`LensMap.canvas_spp`);
the 4x larger film and the four reads cost ~2.3x the CPU time of a render
(1.1 s instead of 0.5 s per LED at scale 0.25).
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
    supersample: int = 1               # canvas pixels per output pixel (each axis)
    jac: np.ndarray | None = None      # (4, h, w) d(map_x, map_y)/d(u, v) of the lens map

    #: Default canvas supersampling (and sub-pixel grid) - see tests/test_twin_lens.py.
    DEFAULT_SUPERSAMPLE = 2
    #: Largest supersampled canvas (megapixels) the default allows; beyond it (scale > ~0.6)
    #: the twin falls back to one bilinear read: a 2x canvas at full resolution (~100 MP)
    #: more than doubles the render's memory (measured 0.42 -> 0.93 GB at scale 0.25).
    MAX_CANVAS_MP = 40.0

    @classmethod
    def build(cls, camera, scale: float, margin_px: int = 3, supersample: int | None = None) -> "LensMap":
        """Lens map of ``camera`` at ``scale``; the canvas is ``supersample`` times finer
        than the output (default :attr:`DEFAULT_SUPERSAMPLE` within :attr:`MAX_CANVAS_MP`;
        1 = no supersampling)."""
        w, h = camera.size(scale)
        if supersample is None:
            ss = cls.DEFAULT_SUPERSAMPLE
            while ss > 1 and w * h * ss * ss / 1e6 > cls.MAX_CANVAS_MP:
                ss -= 1
        else:
            ss = int(supersample)
        if ss < 1:
            raise ValueError(f"supersample must be >= 1, got {ss}")
        K = camera.matrix(scale)
        dist = np.asarray(camera.distortion, np.float64)
        f = K[0, 0] * ss
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
        jac = None
        if ss > 1:
            # the lens map is smooth (its second derivative is ~1e-5 canvas px per px^2), so
            # across one output pixel it is its tangent map to far below 1e-3 px
            jac = np.empty((4, h, w), np.float32)
            jac[1], jac[0] = np.gradient(map_x)      # d/dv, d/du
            jac[3], jac[2] = np.gradient(map_y)
        return cls(size=(w, h), canvas=(cw, ch), focal=f, map_x=map_x, map_y=map_y, K=K, dist=dist,
                   supersample=ss, jac=jac)

    def canvas_spp(self, spp: int) -> int:
        """Samples per canvas pixel that give at least ``spp`` samples per output pixel."""
        return max(1, math.ceil(spp / self.supersample ** 2))

    def apply(self, canvas_img: np.ndarray, nearest: bool = False) -> np.ndarray:
        """Resample a pinhole canvas image into the distorted output image.

        ``nearest``: the canvas value at each output pixel's centre ray (for data that
        must not be mixed, e.g. surface positions); otherwise the pixel-area mean, from
        ``s x s`` sub-pixel positions read bilinearly (see the module docstring)."""
        src = np.ascontiguousarray(canvas_img)
        remap = lambda mx, my, interp: cv2.remap(src, mx, my, interp, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        if nearest:
            return remap(self.map_x, self.map_y, cv2.INTER_NEAREST)
        n = self.supersample
        if n == 1:
            return remap(self.map_x, self.map_y, cv2.INTER_LINEAR)
        out = None
        offsets = [(k + 0.5) / n - 0.5 for k in range(n)]      # python floats keep the maps float32
        for dv in offsets:
            for du in offsets:
                img = remap(self.map_x + self.jac[0] * du + self.jac[1] * dv,
                            self.map_y + self.jac[2] * du + self.jac[3] * dv, cv2.INTER_LINEAR)
                if out is None:
                    out = img.astype(np.float32)
                else:
                    out += img
        out /= n * n
        return out


def render_array(scene, spp: int | None = None, seed: int = 0) -> np.ndarray:
    """Render ``scene`` and return a float32 ``(h, w, c)`` numpy array."""
    from .mitsuba_env import mitsuba

    mi = mitsuba()
    img = mi.render(scene, seed=seed, spp=spp or 0)
    return np.array(img, dtype=np.float32)
