"""Rendering the rig through the real lens: pinhole render + OpenCV distortion resampling.

Mitsuba has no lens distortion, and its perspective sensor cannot express
fx != fy. We render a pinhole image with focal length ``supersample * fx`` on a
canvas that covers every ray the real (distorted) image needs, then resample:
for each output pixel (u, v), ``cv2.undistortPoints`` gives the ideal normalised
ray (x, y) under the calibrated k1 k2 p1 p2 k3 model, and the pinhole canvas is
read at ``(s fx x + c, s fx y + c')``. The pipeline undoes exactly this model
with the same coefficients (glossrig.core.extraction.cylinder.undistorted_rays), so fy
enters only here.

Image formation: a sensor pixel integrates the irradiance over its area, so an
output pixel is the mean of the pinhole image over the pixel's footprint (its
square mapped through the inverse lens model). The canvas is rendered ``s``
times finer than the output (box filter: each fine pixel is an area mean) and
:meth:`LensMap.area_mean` integrates it exactly over each footprint. What is left
is the canvas's own discretisation: a fine pixel cut by an edge is spread
uniformly over its area, so an output pixel whose footprint boundary cuts that
fine pixel sees the edge displaced by a fraction of a fine pixel, depending on
the sub-pixel phase of the edge in the canvas grid. Along an edge that runs
along a pixel row or column - the holder marker's, on the nominal rig - the
phase is the same everywhere, so the displacements add up instead of averaging
out. Measured on the holder marker imaged exactly (analytic fine-pixel coverage,
no noise) through this lens map and fitted by the pose refinement, scale 0.25:
holder tilt 0.073 deg with s = 2, 0.024 deg with s = 4 (0.15: 0.063 / 0.013 deg);
the Monte Carlo coverage noise on the edges shrinks with the number of fine
pixels per output pixel as well (the twin's calibration image at scale 0.15,
sensor noise off: 0.27 deg with s = 2, 0.027 deg with s = 4) - see
validation/calibration_report.md. Hence s = 4 by default (within
:attr:`LensMap.MAX_CANVAS_MP`). The canvas gets ``ceil(spp / s^2)`` samples per
fine pixel (:meth:`LensMap.canvas_spp`), at least one: with s = 4 and the default
spp = 4 an output pixel gets 16 samples. Cost at scale 0.25: ~3x the CPU time of
s = 2 per LED render and 3.5 GB instead of 1.2 GB peak memory.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from glossrig.core.extraction.cylinder import undistorted_rays


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

    #: Default canvas supersampling - see the module docstring and tests/test_twin_lens.py.
    DEFAULT_SUPERSAMPLE = 4
    #: Largest supersampled canvas (megapixels) the default allows; beyond it the twin steps
    #: down to s = 3, 2 and finally one bilinear read (s = 1): s = 4 up to scale ~0.25
    #: (24 MP canvas, 3.5 GB peak), s = 2 up to ~0.5, a full-resolution canvas (~24 MP) at
    #: scale 1.
    MAX_CANVAS_MP = 25.0

    @classmethod
    def build(cls, camera, scale: float, margin_px: int = 3, supersample: int | None = None) -> LensMap:
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
        must not be mixed, e.g. surface positions); otherwise, with a supersampled canvas,
        the exact mean of the (piecewise constant) canvas over each output pixel's
        footprint (:meth:`area_mean`), and without supersampling one bilinear read."""
        src = np.ascontiguousarray(canvas_img)
        if nearest:
            return cv2.remap(src, self.map_x, self.map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=0)
        if self.supersample == 1:
            return cv2.remap(src, self.map_x, self.map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                             borderValue=0)
        return self.area_mean(src)

    def area_mean(self, canvas_img: np.ndarray) -> np.ndarray:
        """Mean of the canvas over each output pixel's footprint, exactly.

        The footprint of output pixel (u, v) is the rectangle centred on its ray
        (map_x, map_y) with sides |d map_x / du| x |d map_y / dv| canvas pixels (the lens
        map's local Jacobian; its off-diagonal terms, a shear below 0.5 % at the image
        corners, are left out - they do not move the footprint's centroid). The canvas
        is piecewise constant (box-filtered fine pixels), so the integral over the
        rectangle is a separable sum over the canvas pixels it overlaps, each weighted
        by its overlap length along x times along y (3 x 3 canvas pixels for a 2x
        canvas, 5 x 5 for a 4x one).

        The weights do not depend on the sub-pixel phase between canvas and output grid
        in the way the former scheme's did (an s x s grid of bilinear reads, whose
        kernel varied between the pixel square and a 1.5 px trapezoid at s = 2); on the
        holder pose the two agree (scale 0.15, s = 2: 0.278 vs 0.270 deg noise-free), the
        error that matters is the canvas's discretisation (module docstring)."""
        src = np.ascontiguousarray(canvas_img)
        tx, ty, inv_area = self._footprint_taps()
        out = None
        for ky, wy in ty:
            for kx, wx in tx:
                w = wx * wy * inv_area
                if not w.any():
                    continue
                # integer positions: INTER_NEAREST is an exact gather; outside the canvas 0
                g = cv2.remap(src, kx, ky, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
                g *= w[..., None] if g.ndim == 3 else w
                out = g if out is None else out + g
        return out

    def _footprint_taps(self):
        """Per axis, the canvas pixels (float32 integer positions) each output pixel's
        footprint overlaps and the overlap lengths; and 1 / footprint area. Cached."""
        if getattr(self, "_taps", None) is None:
            def taps(c, half):
                # canvas pixel k covers [k - 0.5, k + 0.5]; the footprint [c - half, c + half]
                lo, hi = c - half, c + half
                k0 = np.floor(lo + 0.5)
                n = int(np.ceil(2 * half.max())) + 1
                return [((k0 + m).astype(np.float32),
                         np.clip(np.minimum(hi, k0 + m + 0.5) - np.maximum(lo, k0 + m - 0.5), 0.0, None)
                         .astype(np.float32)) for m in range(n)]

            hx = 0.5 * np.abs(self.jac[0].astype(np.float64))
            hy = 0.5 * np.abs(self.jac[3].astype(np.float64))
            self._taps = (taps(self.map_x.astype(np.float64), hx), taps(self.map_y.astype(np.float64), hy),
                          (0.25 / (hx * hy)).astype(np.float32))
        return self._taps


def render_array(scene, spp: int | None = None, seed: int = 0) -> np.ndarray:
    """Render ``scene`` and return a float32 ``(h, w, c)`` numpy array."""
    from .mitsuba_env import mitsuba

    mi = mitsuba()
    img = mi.render(scene, seed=seed, spp=spp or 0)
    return np.array(img, dtype=np.float32)
