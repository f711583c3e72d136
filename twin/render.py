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
        1 = no supersampling).

        Built once per (camera, scale, margin, supersample) in a process (issue 19: a full-
        resolution map takes most of a virtual rig's set-up): the last
        :attr:`CACHE_SIZE` maps are kept and shared, their arrays read-only."""
        key = (camera, float(scale), int(margin_px), supersample)
        hit = _LENS_CACHE.pop(key, None)
        if hit is None:
            hit = cls._build(camera, scale, margin_px, supersample)
            for a in (hit.map_x, hit.map_y, hit.K, hit.dist, hit.jac):
                if a is not None:
                    a.flags.writeable = False
        _LENS_CACHE[key] = hit                          # most recently used last
        while len(_LENS_CACHE) > cls.CACHE_SIZE:
            _LENS_CACHE.pop(next(iter(_LENS_CACHE)))
        return hit

    #: Lens maps kept by :meth:`build` (a full-resolution one holds ~0.2 GB).
    CACHE_SIZE = 2

    @classmethod
    def _build(cls, camera, scale: float, margin_px: int, supersample: int | None) -> LensMap:
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
        xy_max = np.zeros(2)
        rows = []
        block = max(1, 2_000_000 // w)
        rays = _IdealRays(K, dist, w, h)
        for y0 in range(0, h, block):
            y1 = min(h, y0 + block)
            r = rays.block(y0, y1)
            xy_max = np.maximum(xy_max, [np.abs(r[..., 0]).max(), np.abs(r[..., 1]).max()])
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


_LENS_CACHE: dict[tuple, LensMap] = {}


class _IdealRays:
    """Ideal (undistorted) normalised rays (x, y) of every output pixel, as
    :func:`glossrig.core.extraction.cylinder.undistorted_rays` gives them, without its cost on
    24 MP (issue 19: 30 s of cv2.undistortPoints at full resolution): exact rays on a grid of
    every :attr:`GRID`-th pixel, bilinear interpolation between them as the starting point,
    then Newton's method on OpenCV's distortion model (k1 k2 p1 p2 k3; G. Bradski, A. Kaehler,
    "Learning OpenCV", O'Reilly 2008, ch. 11) with its analytic Jacobian. The start is within
    ~1e-7 of the root and Newton converges quadratically, so :attr:`ITERATIONS` steps reach
    float64 rounding; pixels whose residual stays above :attr:`TOL` (none on the thesis lens)
    are solved by cv2 as before. Other distortion models are left to cv2 throughout."""

    GRID = 16
    ITERATIONS = 2
    TOL = 1e-12          # distorted normalised coordinates (~1e-8 px at full resolution)

    def __init__(self, K, dist, w: int, h: int):
        self.K, self.dist, self.w = K, np.asarray(dist, np.float64), w
        self.newton = self.dist.size <= 5 and K[0, 1] == 0
        if self.newton:
            self.gx = np.unique(np.r_[np.arange(0, w, self.GRID), w - 1]).astype(np.float64)
            self.gy = np.unique(np.r_[np.arange(0, h, self.GRID), h - 1]).astype(np.float64)
            vv, uu = np.meshgrid(self.gy, self.gx, indexing="ij")
            r = undistorted_rays(K, self.dist, uu, vv)
            self.nodes = r[:, 0].reshape(vv.shape), r[:, 1].reshape(vv.shape)
            u = np.arange(w, dtype=np.float64)
            self.ix = np.clip(np.searchsorted(self.gx, u, side="right") - 1, 0, len(self.gx) - 2)
            self.tx = (u - self.gx[self.ix]) / (self.gx[self.ix + 1] - self.gx[self.ix])

    def block(self, y0: int, y1: int) -> np.ndarray:
        """(y1 - y0, w, 2) rays of rows y0..y1-1."""
        w = self.w
        v = np.arange(y0, y1, dtype=np.float64)
        if not self.newton:
            vv, uu = np.meshgrid(v, np.arange(w, dtype=np.float64), indexing="ij")
            return undistorted_rays(self.K, self.dist, uu, vv)[:, :2].reshape(y1 - y0, w, 2)
        iy = np.clip(np.searchsorted(self.gy, v, side="right") - 1, 0, len(self.gy) - 2)
        ty = ((v - self.gy[iy]) / (self.gy[iy + 1] - self.gy[iy]))[:, None]
        start = []
        for nodes in self.nodes:
            col = nodes[iy] * (1 - ty) + nodes[iy + 1] * ty             # (rows, grid columns)
            start.append(col[:, self.ix] * (1 - self.tx) + col[:, self.ix + 1] * self.tx)
        x, y = start
        K = self.K
        xd = np.broadcast_to((np.arange(w, dtype=np.float64) - K[0, 2]) / K[0, 0], x.shape)
        yd = np.broadcast_to(((v - K[1, 2]) / K[1, 1])[:, None], x.shape)
        for _ in range(self.ITERATIONS):
            (ex, ey), (j11, j12, j22) = self._residual(x, y, xd, yd, jacobian=True)
            det = j11 * j22 - j12 * j12
            x = x - (j22 * ex - j12 * ey) / det
            y = y - (j11 * ey - j12 * ex) / det
        ex, ey = self._residual(x, y, xd, yd)
        out = np.stack([x, y], axis=-1)
        bad = np.maximum(np.abs(ex), np.abs(ey)) > self.TOL
        if bad.any():
            rr, cc = np.nonzero(bad)
            out[rr, cc] = undistorted_rays(self.K, self.dist, cc.astype(np.float64), v[rr])[:, :2]
        return out

    def _residual(self, x, y, xd, yd, jacobian: bool = False):
        """distort(x, y) - (xd, yd) under OpenCV's model, and its Jacobian (J11, J12 = J21, J22)."""
        k1, k2, p1, p2, k3 = np.r_[self.dist, np.zeros(5 - self.dist.size)]
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xy = x * y
        ex = x * radial + 2 * p1 * xy + p2 * (r2 + 2 * x * x) - xd
        ey = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * xy - yd
        if not jacobian:
            return ex, ey
        d = 2 * (k1 + r2 * (2 * k2 + 3 * k3 * r2))                 # 2 d(radial)/d(r2)
        j11 = radial + x * x * d + 2 * p1 * y + 6 * p2 * x
        j12 = xy * d + 2 * p1 * x + 2 * p2 * y
        j22 = radial + y * y * d + 6 * p1 * y + 2 * p2 * x
        return (ex, ey), (j11, j12, j22)


def render_array(scene, spp: int | None = None, seed: int = 0) -> np.ndarray:
    """Render ``scene`` and return a float32 ``(h, w, c)`` numpy array."""
    from .mitsuba_env import mitsuba

    mi = mitsuba()
    img = mi.render(scene, seed=seed, spp=spp or 0)
    return np.array(img, dtype=np.float32)


#: Samples per output pixel of the twin's renders unless asked otherwise (``glossrig simulate --spp``).
DEFAULT_SPP = 4
#: Canvas samples across the narrower width ``alpha`` of a lobe that :func:`lobe_resolving_spp`
#: asks for (see there).
SAMPLES_PER_LOBE_WIDTH = 7.0


def lobe_resolving_spp(rig, scale: float, alpha_min: float, spp: int = DEFAULT_SPP,
                       supersample: int | None = None) -> int:
    """Samples per output pixel that resolve a glossy lobe of narrower width ``alpha_min``
    (Ward's alpha, radians of half-vector slope) at ``scale``: at least ``spp``, and enough
    that the canvas's random samples lie ~1 / :data:`SAMPLES_PER_LOBE_WIDTH` of ``alpha_min``
    apart across the cylinder, where the surface normal turns fastest.

    Why: a sensor pixel integrates exactly; the twin estimates that integral by Monte Carlo
    (the ``independent`` sampler, ``ceil(spp / s^2)`` samples per canvas pixel, module
    docstring). Where one pixel's footprint spans a good part of the lobe, its value is a
    noisy estimate of the lobe's average - a per-pixel error the real rig has not. One
    output pixel turns the normal by ``(D - R) / (f_x R)`` (camera at ``D`` from the axis,
    cylinder radius ``R``, ``f_x`` at ``scale``; at the view's centre, more off-centre), so
    a canvas pixel's samples are ``(D - R) / (f_x R s sqrt(n))`` apart with ``n`` samples each.
    Measured on the coverage study's brushed_original (alpha_y 0.0106) at scale 0.1, round 7
    (validation/uncertainty_coverage.md, section 3): alpha_y came out -14.1 % with 1 sample
    per canvas pixel (3.6 per alpha), -2.1 % with 4 (7.2 per alpha), -0.8 % with 16; rho_s
    -20 %, -8.6 %, -6.8 %. At scale 0.1 a lobe wider than alpha 0.0205 needs 1."""
    ss = LensMap.DEFAULT_SUPERSAMPLE if supersample is None else int(supersample)
    cam = rig.camera
    turn = (cam.distance_to_axis - rig.cylinder_radius) / (float(cam.matrix(scale)[0, 0]) * rig.cylinder_radius)
    n = math.ceil((SAMPLES_PER_LOBE_WIDTH * turn / (ss * float(alpha_min))) ** 2 - 1e-9)
    return int(spp) if n <= math.ceil(int(spp) / ss ** 2) else n * ss * ss     # spp already gives n per canvas pixel
