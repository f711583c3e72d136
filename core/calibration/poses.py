"""Holder and cylinder poses from the calibration image (thesis 4.3.2, eq. 4.18-4.25).

Pipeline of :func:`calibrate_capture`:

1. read, linearise and demosaic the calibration image (thesis 4.3.1-4.3.2);
2. find the markers and their corners (:mod:`glossrig.core.calibration.marker_detect`);
3. **corner PnP** (eq. 4.18 and its cylinder analogue eq. 4.22-4.24): the
   holder pose from its marker's corners - the outer four of eq. 4.18 plus the
   white patch's four (a departure: more points, same plane) - with
   ``cv2.solvePnP`` (IPPE, the planar solver) refined by
   ``cv2.solvePnPRefineLM``; the cylinder pose from its twelve marker corners
   (SQPnP + LM), solved twice: the second time after the markers' arc-shaped
   top and bottom edges were refitted with the curvature the first pose
   predicts. The thesis uses Gao's P3P solver [20]; with 8 and 12 points a
   least-squares solver is the better choice.
4. **edge refinement** (departure, see :func:`refine_pose_edges`): both poses
   are refined against the raw CFA samples along the marker edges - for the
   holder by default the white patch's four edges (see :func:`marker_poses`),
   for the cylinder all twelve, arcs included - so the pose does not inherit
   the demosaicing and corner-extrapolation errors of step 3. On the twin at
   scale 0.25 this takes the holder tilt error from ~1.4 to ~0.1 degrees and
   the cylinder's rotation error to 0.01-0.05 degrees
   (validation/calibration_report.md);
5. frames (eq. 4.19-4.21, 4.25), with the holder frame as reference (eq. 4.19:
   the holder's own pose there is the identity).

Printed-equation errors corrected here:

* eq. 4.21 gives the camera position in the holder frame as
  ``TV_cam^cam - TV_hold^cam`` (= -t_hold). With OpenCV's convention
  ``x_cam = R_hold x_hold + t_hold`` the camera centre in the holder frame is
  ``-R_hold^T t_hold``.
* eq. 4.25 gives the cylinder translation in the holder frame as
  ``TV_cyl^cam - TV_hold^cam``; a difference of camera-frame vectors must
  still be rotated into the holder frame: ``R_hold^T (t_cyl - t_hold)``. The
  rotation ``R_hold^T R_cyl`` (= (RM_hold^cam)^-1 RM_cyl^cam) is as printed.

Conventions: ``R``, ``t`` map the named frame into the camera frame
(``x_cam = R x + t``, millimetres), as ``cv2.solvePnP`` returns them and as
``truth.json`` of the twin records them.
"""
from __future__ import annotations

from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.special import ndtr

from glossrig.core.errors import InputError
from glossrig.core.calibration.markers import cylinder_marker_angles, cylinder_marker_corners, holder_marker_corners, cylinder_marker_radius
from glossrig.core.calibration.marker_detect import SIDES, MarkerDetection, detect_markers, refine_cylinder_arcs

#: Smallest blur (px) of the edge model (keeps the profile differentiable).
SIGMA_MIN = 0.02
#: log-blur range and weak prior (log units) keeping each edge's blur identifiable.
LOG_SIGMA_RANGE = (np.log(1e-3), np.log(5.0))
LOG_SIGMA_PRIOR = (np.log(0.5), 3.0)
#: At most this many raw pixels per edge are fitted (a fixed random subset beyond).
MAX_PIXELS_PER_EDGE = 6000
#: Blur (px) of the pose-only coarse pass.
COARSE_SIGMA = 1.2
#: Order of a quad's sides (corner index pairs in UL, UR, LL, LR order).
SIDE_NAMES = ("top", "right", "bottom", "left")


# ------------------------------------------------------------------ PnP

def pnp(obj: np.ndarray, img: np.ndarray, K: np.ndarray, dist, planar: bool, what: str = "",
        path: str | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Pose of 3-D points ``obj`` (N, 3) seen at ``img`` (N, 2): ``cv2.solvePnP``
    (IPPE if ``planar``, else SQPnP) followed by ``cv2.solvePnPRefineLM``.
    Returns (R (3, 3), t (3,), reprojection RMS px).

    IPPE (Collins & Bartoli 2014) is the pose of a plane z = 0; the holder marker lies in
    the plane z = 30 mm of the holder frame. OpenCV's IPPE given those points directly
    returned poses 440-500 px off on the scale-0.2 twin (the LM refinement then stopped at
    43.9 px RMS and the edge refinement found no edge), so the points are first expressed
    in their own plane's frame (centroid, principal axes: :func:`_plane_frame`), solved
    there, and the pose taken back: ``R = R_p B``, ``t = t_p - R_p B c``."""
    obj = np.ascontiguousarray(obj, np.float64).reshape(-1, 3)
    img = np.ascontiguousarray(img, np.float64).reshape(-1, 2)
    d = np.asarray(dist, np.float64)
    if planar:
        c, B = _plane_frame(obj)
        ok, rv_p, tvec = cv2.solvePnP(np.ascontiguousarray((obj - c) @ B.T * [1.0, 1.0, 0.0]), img, K, d,
                                      flags=cv2.SOLVEPNP_IPPE)
        if ok:
            R_p = cv2.Rodrigues(rv_p)[0]
            rvec = cv2.Rodrigues(R_p @ B)[0]
            tvec = tvec.reshape(3, 1) - (R_p @ B @ c).reshape(3, 1)
    else:
        ok, rvec, tvec = cv2.solvePnP(obj, img, K, d, flags=cv2.SOLVEPNP_SQPNP)
    if not ok:
        raise InputError(f"{what}: PnP found no pose for the detected corners", path=path)
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100, 1e-12)
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, d, rvec, tvec, criteria=crit)
    proj, _ = cv2.projectPoints(obj, rvec, tvec, K, d)
    rms = float(np.sqrt(np.mean(np.sum((proj.reshape(-1, 2) - img) ** 2, axis=1))))
    R = cv2.Rodrigues(rvec)[0]
    t = tvec.reshape(3)
    if t[2] <= 0:
        raise InputError(f"{what}: PnP put the marker behind the camera (corners mis-ordered?)", path=path)
    return R, t, rms


def _plane_frame(obj: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Centroid ``c`` and rotation ``B`` (rows: two in-plane axes, then the normal; det +1)
    of coplanar points, so that ``(obj - c) @ B.T`` has z = 0. Points that do not lie in
    one plane (off-plane RMS above 1e-6 of their extent) are an error of the caller."""
    c = obj.mean(axis=0)
    _, s, B = np.linalg.svd(obj - c)
    if len(s) < 3 or s[1] <= 0 or s[2] > 1e-6 * s[0]:
        raise ValueError("planar PnP: the object points are not coplanar (or are collinear)")
    if np.linalg.det(B) < 0:
        B[2] *= -1
    return c, B


# -------------------------------------------------------- edge model (3-D)

def holder_edges(rig) -> list[np.ndarray]:
    """The holder marker's 8 edges as 3-D polylines (holder frame): outer
    top, right, bottom, left, then the white patch's."""
    out = []
    for inner in (False, True):
        c = holder_marker_corners(rig, inner=inner)
        out += [np.array([c[a], c[b]]) for a, b in SIDES]
    return out


def cylinder_edges(rig, segments: int = 32) -> list[np.ndarray]:
    """The cylinder markers' 12 edges as 3-D polylines (cylinder frame), per
    marker top, right, bottom, left: top and bottom are arcs of the cylinder
    (``segments`` chords each; sag < 1e-3 mm), left and right straight lines
    along its axis (thesis eq. 4.22-4.24 geometry)."""
    cm = rig.cylinder_markers
    r = cylinder_marker_radius(rig)
    a = cylinder_marker_angles(rig)
    hu = cm.centre_height + cm.side / 2
    hl = cm.centre_height - cm.side / 2

    def arc(a0, a1, y):
        s = np.linspace(a0, a1, segments + 1)
        return np.stack([r * np.sin(s), np.full_like(s, y), r * np.cos(s)], axis=-1)

    def line(ang, y0, y1):
        return np.array([[r * np.sin(ang), y0, r * np.cos(ang)], [r * np.sin(ang), y1, r * np.cos(ang)]])

    out = []
    for k in range(cm.count):
        a0, a1 = a[2 * k], a[2 * k + 1]
        # top: UL->UR, right: UR->LR, bottom: LR->LL, left: LL->UL (as SIDES)
        out += [arc(a0, a1, hu), line(a1, hu, hl), arc(a1, a0, hl), line(a0, hl, hu)]
    return out


# ----------------------------------------------------- edge-based refinement

def _project_ideal(P: np.ndarray, R: np.ndarray, t: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pinhole projection (no distortion) of points ``P`` (N, 3) -> ideal px (N, 2)."""
    X = P @ R.T + t
    return np.stack([K[0, 0] * X[:, 0] / X[:, 2] + K[0, 2], K[1, 1] * X[:, 1] / X[:, 2] + K[1, 2]], axis=-1)


def _collect_side(lin: np.ndarray, cid: np.ndarray, K, dist, poly_img: np.ndarray, poly_ideal: np.ndarray,
                  half: float, margin: float):
    """Raw pixels whose ideal (undistorted) position lies within ``half`` px of
    the projected edge polyline and at least ``margin`` px from its ends.
    Returns (ideal px (N, 2), values, channel, segment index, along in [-1, 1])
    or None."""
    from glossrig.core.calibration.marker_detect import _ideal

    h, w = lin.shape
    lo = np.floor(poly_img.min(axis=0) - half - 2).astype(int)
    hi = np.ceil(poly_img.max(axis=0) + half + 2).astype(int)
    x0, y0 = max(lo[0], 0), max(lo[1], 0)
    x1, y1 = min(hi[0], w - 1), min(hi[1], h - 1)
    if x1 <= x0 or y1 <= y0:
        return None
    yy, xx = np.mgrid[y0:y1 + 1, x0:x1 + 1]
    xx, yy = xx.ravel(), yy.ravel()
    q = _ideal(np.stack([xx, yy], axis=-1).astype(np.float64), K, dist)
    A, B = poly_ideal[:-1], poly_ideal[1:]
    AB = B - A
    L2 = np.sum(AB ** 2, axis=1)
    tt = np.clip(((q[:, None, :] - A[None]) * AB[None]).sum(-1) / L2[None], 0, 1)
    dd = np.linalg.norm(q[:, None, :] - (A[None] + tt[..., None] * AB[None]), axis=-1)
    seg = np.argmin(dd, axis=1)
    rows = np.arange(len(q))
    cum = np.concatenate([[0.0], np.cumsum(np.sqrt(L2))])
    along = cum[seg] + tt[rows, seg] * np.sqrt(L2[seg])
    vals = lin[yy, xx]
    keep = (dd[rows, seg] < half) & (along > margin) & (along < cum[-1] - margin) & (vals < 0.98)
    if keep.sum() < 20:
        return None
    if keep.sum() > MAX_PIXELS_PER_EDGE:
        idx = np.sort(np.random.default_rng(0).choice(np.flatnonzero(keep), MAX_PIXELS_PER_EDGE, replace=False))
        keep = np.zeros_like(keep)
        keep[idx] = True
    return (q[keep], vals[keep].astype(np.float64), cid[yy[keep], xx[keep]].astype(np.int64), seg[keep],
            along[keep] / cum[-1] * 2 - 1)


def _F(z):
    """Antiderivative of the normal CDF: z Phi(z) + phi(z)."""
    return z * ndtr(z) + np.exp(-0.5 * z * z) * 0.3989422804014327


def edge_profile(d: np.ndarray, sigma, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Mean of a unit step blurred by a Gaussian of ``sigma`` px over a square
    pixel, at signed distance ``d`` of the pixel centre from the edge.

    The pixel square projects onto the edge normal as box(a) * box(b) with
    a = max(|n_x|, |n_y|), b = min(...); box(b) * Gaussian is approximated by
    a Gaussian of variance sigma^2 + b^2/12 (exact for edges along a pixel row
    or column, b = 0), and box(a) * Gaussian integrates in closed form:
    (s/a) [F((d + a/2)/s) - F((d - a/2)/s)], F(z) = z Phi(z) + phi(z)."""
    s = np.sqrt(sigma * sigma + b * b / 12.0)
    return (s / a) * (_F((d + a / 2) / s) - _F((d - a / 2) / s))


class _EdgeProblem:
    """All edge samples of one marker pose, stacked: the residual of every raw
    pixel under the blurred-step model, with the linear parameters (level,
    trend, contrast, contrast trend) of each edge x channel group solved in
    closed form (variable projection)."""

    def __init__(self, polys: list[np.ndarray], samples: list[tuple], K: np.ndarray):
        self.K = K
        self.P = np.concatenate(polys)
        starts = np.cumsum([0] + [len(p) for p in polys])
        qs, vs, us, sides, segs, groups = [], [], [], [], [], []
        gid = 0
        self.n_sides = len(polys)
        for k, (q, v, c, seg, u) in enumerate(samples):
            g = np.full(len(v), -1, np.int64)
            for ch in range(3):
                m = c == ch
                if m.sum() >= 8:
                    g[m] = gid
                    gid += 1
            keep = g >= 0
            qs.append(q[keep]); vs.append(v[keep]); us.append(u[keep]); groups.append(g[keep])
            sides.append(np.full(keep.sum(), k)); segs.append(seg[keep] + starts[k])
        self.q, self.v, self.u = np.concatenate(qs), np.concatenate(vs), np.concatenate(us)
        self.side, self.seg, self.g = np.concatenate(sides), np.concatenate(segs), np.concatenate(groups)
        self.n_groups = gid
        self.w = np.ones(gid)
        # the normal equations' entries that do not depend on the model (columns 1 and u; the
        # products with the column of ones are the other factor exactly): summed once
        g, G = self.g, gid
        self._const = {(0, 0): np.bincount(g, np.ones_like(self.v), minlength=G),
                       (0, 1): np.bincount(g, self.u, minlength=G),
                       (1, 1): np.bincount(g, self.u * self.u, minlength=G),
                       ("r", 0): np.bincount(g, self.v, minlength=G),
                       ("r", 1): np.bincount(g, self.u * self.v, minlength=G)}

    def model_phi(self, x: np.ndarray) -> np.ndarray:
        R = cv2.Rodrigues(x[:3])[0]
        p = _project_ideal(self.P, R, x[3:6], self.K)
        A = p[self.seg]
        e = p[self.seg + 1] - A
        e /= np.sqrt(np.sum(e * e, axis=1))[:, None]
        d = (self.q[:, 0] - A[:, 0]) * (-e[:, 1]) + (self.q[:, 1] - A[:, 1]) * e[:, 0]
        an0, an1 = np.abs(e[:, 1]), np.abs(e[:, 0])
        sigma = SIGMA_MIN + np.exp(np.clip(x[6:], *LOG_SIGMA_RANGE))[self.side]
        return edge_profile(d, sigma, np.maximum(an0, an1), np.minimum(an0, an1))

    def residuals(self, x: np.ndarray) -> np.ndarray:
        phi = self.model_phi(x)
        cols = (np.ones_like(phi), self.u, phi, self.u * phi)
        G, g = self.n_groups, self.g
        M = np.empty((G, 4, 4))
        r = np.empty((G, 4))
        # sum over each group of cols[i] * cols[j] (and * v): the entries without phi are
        # constant (__init__), a product with the column of ones is the other column, and
        # u * phi (i, j = 1, 2) is column 3 - the same numbers, summed once
        const = self._const
        for i in range(4):
            r[:, i] = const[("r", i)] if i < 2 else np.bincount(g, cols[i] * self.v, minlength=G)
            for j in range(i, 4):
                s: np.ndarray
                if j < 2:
                    s = const[(i, j)]
                elif i == 0 or (i, j) == (1, 2):
                    s = M[:, 0, 3] if (i, j) == (1, 2) else np.bincount(g, cols[j], minlength=G)
                else:
                    s = np.bincount(g, cols[i] * cols[j], minlength=G)
                M[:, i, j] = M[:, j, i] = s
        beta = np.linalg.solve(M + 1e-12 * np.eye(4), r[..., None])[..., 0]
        pred = sum(cols[i] * beta[g, i] for i in range(4))
        prior = (np.clip(x[6:], *LOG_SIGMA_RANGE) - LOG_SIGMA_PRIOR[0]) / LOG_SIGMA_PRIOR[1]
        return np.concatenate([self.w[g] * (self.v - pred), prior])

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """Forward differences; the blur of edge k acts on edge k's rows only,
        so one evaluation with every blur perturbed gives all blur columns."""
        f0 = self.residuals(x)
        J = np.zeros((len(f0), len(x)))
        steps = [1e-7] * 3 + [1e-5] * 3
        for j, h in enumerate(steps):
            xp = x.copy()
            xp[j] += h
            J[:, j] = (self.residuals(xp) - f0) / h
        h = 1e-6
        xp = x.copy()
        xp[6:] += h
        col = (self.residuals(xp) - f0) / h
        n = len(self.v)
        J[np.arange(n), 6 + self.side] = col[:n]
        J[n + np.arange(self.n_sides), 6 + np.arange(self.n_sides)] = col[n:]
        return J


def refine_pose_edges(lin: np.ndarray, cfa, K: np.ndarray, dist, R0: np.ndarray, t0: np.ndarray,
                      edges: list[np.ndarray], halves: list[float], path: str | None = None,
                      what: str = "marker") -> dict:
    """Refine a marker pose against the raw CFA samples along its edges.

    Departure from the thesis (which stops at corner PnP). Every raw pixel
    within ``halves[i]`` px of projected edge ``i`` (a 3-D polyline in the
    marker's frame) is modelled, in its own colour channel, as a blurred step
    across the edge: ``v = a + b u + (c + d u) S(dist; sigma_i)``, where
    ``dist`` is the pixel's signed distance from the projected edge in the
    undistorted image (calibrated lens model), ``S`` the pixel-integrated
    Gaussian-blurred step (:func:`edge_profile`), ``u`` the position along
    the edge (a linear light trend) and ``a..d`` linear parameters of each
    edge and channel. The pose (6) and one blur ``sigma_i`` per edge are found
    by Levenberg-Marquardt (``scipy.optimize.least_squares``): a pose-only pass
    with every blur fixed at :data:`COARSE_SIGMA` (a wide basin for a start a
    few px off), then pose and blurs, then again with each edge x channel group
    weighted by 1/its residual RMS (sensor noise differs by channel and level).

    Why: demosaicing interpolates the red channel of a sharp red/dark edge
    from samples 2 px apart, which shifts the edge by up to a few tenths of a
    pixel when the edge runs along a pixel row or column (as the marker edges
    do on an aligned rig); fitting the raw samples with a pixel-integrated
    edge avoids most of that, and fitting the pose to whole edges uses the
    exact shape of the cylinder markers' arcs instead of extrapolating corners
    from fitted curves.

    Returns dict(R, t, chi2_per_dof, sigma_px per edge, n_pixels,
    std_rot_deg (3,: small rotations about the marker frame's axes), std_t_mm
    (3,: camera frame) - Gauss-Newton standard deviations, which count noise
    only, not model error - moved_mm, nfev).
    """
    from glossrig.core.calibration.demosaic import channel_index
    from glossrig.core.calibration.marker_detect import _distort

    lin = np.asarray(lin, np.float32)
    cid = channel_index(lin.shape, cfa)
    rvec0 = cv2.Rodrigues(np.asarray(R0, np.float64))[0].ravel()
    t0 = np.asarray(t0, np.float64).ravel()
    R0 = cv2.Rodrigues(rvec0)[0]
    samples, polys = [], []
    for P, half in zip(edges, halves):
        P = np.asarray(P, np.float64)
        ideal = _project_ideal(P, R0, t0, K)
        length = float(np.sum(np.linalg.norm(np.diff(ideal, axis=0), axis=1)))
        margin = 3.0 + 0.3 * half
        if length < 2 * margin + 4:
            raise InputError(f"{what}: an edge is only {length:.1f} px long; too small to refine", path=path)
        sd = _collect_side(lin, cid, K, dist, _distort(ideal, K, dist), ideal, half, margin)
        if sd is None:
            raise InputError(f"{what}: too few unclipped pixels along an edge to refine the pose", path=path)
        samples.append(sd)
        polys.append(P)
    prob = _EdgeProblem(polys, samples, K)
    npx = len(prob.v)
    nfev = 0
    # coarse pass: pose only, every edge blurred by COARSE_SIGMA px - a wide basin, so a start
    # a few px off (corner PnP) cannot trade the offset for a larger blur
    ls_coarse = np.full(len(polys), np.log(COARSE_SIGMA - SIGMA_MIN))
    x = np.concatenate([rvec0, t0, ls_coarse])
    r0 = prob.residuals(x)[:npx]
    prob.w = 1.0 / np.sqrt(np.maximum(np.bincount(prob.g, r0 ** 2, minlength=prob.n_groups)
                                      / np.maximum(np.bincount(prob.g, minlength=prob.n_groups), 1), 1e-18))
    sol = least_squares(lambda p: prob.residuals(np.concatenate([p, ls_coarse])), x[:6],
                        jac=lambda p: prob.jacobian(np.concatenate([p, ls_coarse]))[:, :6], method="lm",
                        x_scale="jac", xtol=1e-8, ftol=1e-8, gtol=1e-8, max_nfev=60)
    nfev += int(sol.nfev)
    x = np.concatenate([sol.x, np.full(len(polys), np.log(0.5))])
    # fine passes: pose and blurs; each edge x channel group scaled to unit residual RMS at the
    # start (so the blur prior weighs the same throughout), then reweighted by its RMS at the
    # first optimum (sensor noise differs by channel and level)
    r0 = prob.residuals(x)[:npx]
    prob.w = prob.w / np.sqrt(np.maximum(np.bincount(prob.g, r0 ** 2, minlength=prob.n_groups)
                                         / np.maximum(np.bincount(prob.g, minlength=prob.n_groups), 1), 1e-18))
    for _pass in range(2):
        sol = least_squares(prob.residuals, x, jac=prob.jacobian, method="lm", x_scale="jac",
                            xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=200)
        x = sol.x
        nfev += int(sol.nfev)
        if _pass == 0:
            r2 = np.bincount(prob.g, sol.fun[:npx] ** 2, minlength=prob.n_groups) / np.maximum(
                np.bincount(prob.g, minlength=prob.n_groups), 1)
            prob.w = prob.w / np.sqrt(np.maximum(r2, 1e-18))
    # status 0 = the evaluation budget ran out before the (very tight) tolerances were met:
    # the pose is still the best found and is kept, flagged ``converged: false``; only a
    # failed solve (negative status, non-finite result) is an error.
    if sol.status < 0 or not np.all(np.isfinite(sol.x)):
        raise InputError(f"{what}: edge refinement did not converge ({sol.message})", path=path)
    R = cv2.Rodrigues(sol.x[:3])[0]
    t = sol.x[3:6].copy()
    n = npx
    dof = max(1, n - len(sol.x) - 4 * prob.n_groups)
    s2 = float(sol.fun[:n] @ sol.fun[:n]) / dof          # ~1 when the weights match the noise
    try:
        # pinv: a blur clipped at its floor (a very sharp edge) has a zero column and drops out
        cov = s2 * np.linalg.pinv(sol.jac.T @ sol.jac)
        # rvec -> small rotation about the marker's own axes (R = R_est exp([w]x)); the
        # rvec components themselves mean little near 180 degrees
        M = np.empty((3, 3))
        for j in range(3):
            dv = np.zeros(3)
            dv[j] = 1e-6
            A = R.T @ cv2.Rodrigues(sol.x[:3] + dv)[0]          # ~ I + [w]x
            M[:, j] = np.array([A[2, 1] - A[1, 2], A[0, 2] - A[2, 0], A[1, 0] - A[0, 1]]) / 2e-6
        cov_w = M @ cov[:3, :3] @ M.T
        std_w = np.sqrt(np.clip(np.diag(cov_w), 0, None))
        std_t = np.sqrt(np.clip(np.diag(cov)[3:6], 0, None))
    except np.linalg.LinAlgError:
        std_w = std_t = np.full(3, np.nan)
    return {"R": R, "t": t, "chi2_per_dof": s2,
            "sigma_px": (SIGMA_MIN + np.exp(np.clip(sol.x[6:], *LOG_SIGMA_RANGE))).tolist(),
            "n_pixels": int(n), "std_rot_deg": np.degrees(std_w).tolist(), "std_t_mm": std_t.tolist(),
            "moved_mm": float(np.linalg.norm(t - t0)), "nfev": nfev, "converged": bool(sol.status > 0)}


# ---------------------------------------------------------------- frames

def rotation_angle_deg(Ra: np.ndarray, Rb: np.ndarray) -> float:
    """Angle (degrees) of the rotation between ``Ra`` and ``Rb``."""
    c = (np.trace(np.asarray(Ra).T @ np.asarray(Rb)) - 1) / 2
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def relative_to_holder(R_hold: np.ndarray, t_hold: np.ndarray, R_obj: np.ndarray, t_obj: np.ndarray):
    """Pose of an object in the holder frame from both poses in the camera
    frame (thesis eq. 4.25, corrected): ``R = R_hold^T R_obj``,
    ``t = R_hold^T (t_obj - t_hold)`` - the thesis's ``t_obj - t_hold`` lacks
    the rotation into the holder frame."""
    R_hold = np.asarray(R_hold, np.float64)
    return R_hold.T @ np.asarray(R_obj, np.float64), R_hold.T @ (np.asarray(t_obj, np.float64) - np.asarray(t_hold))


def camera_in_holder(R_hold: np.ndarray, t_hold: np.ndarray):
    """Camera orientation and centre in the holder frame (thesis eq. 4.20-4.21,
    corrected): ``R_cam^hold = R_hold^T``, centre ``-R_hold^T t_hold`` (the
    thesis prints ``-t_hold``)."""
    R_hold = np.asarray(R_hold, np.float64)
    return R_hold.T, -R_hold.T @ np.asarray(t_hold, np.float64)


# ------------------------------------------------------------ the step

def _pose_dict(R, t) -> dict:
    return {"R": np.asarray(R, np.float64), "t_mm": np.asarray(t, np.float64).reshape(3),
            "rvec": cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()}


def marker_poses(lin: np.ndarray, cfa, rig, K: np.ndarray, dist, path: str = "<image>",
                 refine: bool = True, holder_edge_set: str = "inner") -> dict:
    """Holder and cylinder poses from one linearised calibration mosaic.

    ``holder_edge_set`` picks the holder-marker edges the refinement fits:
    ``"inner"`` (default: the white patch's four edges, red against white,
    where every colour channel has contrast) or ``"all"`` (also the outer
    red-on-dark edges, whose contrast is in the red channel alone, sampled
    every 2 px on a Bayer sensor; on the twin they pull the tilt off by a few
    tenths of a degree - see validation/calibration_report.md).

    Returns a dict with ``detection`` (:class:`MarkerDetection`),
    ``holder`` (R, t_mm, rvec: holder -> camera; ``corner_pnp`` the corner
    solution, ``reprojection_rms_px``, ``edge_fit``), ``cylinder`` (the same,
    cylinder -> camera), ``cylinder_in_holder`` (R, t_mm: cylinder -> holder,
    eq. 4.25 corrected) and ``camera_in_holder`` (R camera -> holder,
    ``centre_mm``; eq. 4.21 corrected)."""
    from glossrig.core.calibration.demosaic import demosaic

    if holder_edge_set not in ("inner", "all"):
        raise InputError(f"holder_edge_set must be 'inner' or 'all', got {holder_edge_set!r}")
    rgb = demosaic(lin, cfa)
    det = detect_markers(rgb, rig, K, dist, path)
    obj_h = np.concatenate([holder_marker_corners(rig), holder_marker_corners(rig, inner=True)])
    Rh, th, rms_h = pnp(obj_h, det.holder_image_points(), K, dist, True, "holder marker", path)
    obj_c = cylinder_marker_corners(rig)
    Rc, tc, rms_c = pnp(obj_c, det.cylinder_image_points(), K, dist, False, "cylinder markers", path)
    # second pass for the cylinder markers: their top/bottom edges are arcs; fit them with the
    # curvature the first pose predicts, then solve again
    edges_c = cylinder_edges(rig)
    arcs = [(_project_ideal(edges_c[4 * k], Rc, tc, K), _project_ideal(edges_c[4 * k + 2][::-1], Rc, tc, K))
            for k in range(len(det.cylinder))]
    refine_cylinder_arcs(det, arcs, K, dist)
    Rc, tc, rms_c = pnp(obj_c, det.cylinder_image_points(), K, dist, False, "cylinder markers", path)
    out: dict[str, Any] = {"detection": det,
                           "holder": dict(_pose_dict(Rh, th), corner_pnp=_pose_dict(Rh, th), reprojection_rms_px=rms_h),
                           "cylinder": dict(_pose_dict(Rc, tc), corner_pnp=_pose_dict(Rc, tc), reprojection_rms_px=rms_c)}
    if refine:
        frame_px = 0.5 * (np.sqrt(det.holder_outer.area) - np.sqrt(det.holder_inner.area))
        half_h = float(np.clip(0.4 * frame_px, 2.5, 15.0))
        edges_h = holder_edges(rig)
        if holder_edge_set == "inner":
            edges_h = edges_h[4:]
        fit_h = refine_pose_edges(lin, cfa, K, dist, Rh, th, edges_h, [half_h] * len(edges_h), path,
                                  "holder marker")
        halves_c = []
        for q in det.cylinder:
            halves_c += [float(np.clip(0.25 * np.sqrt(q.area), 2.5, 15.0))] * 4
        fit_c = refine_pose_edges(lin, cfa, K, dist, Rc, tc, edges_c, halves_c, path,
                                  "cylinder markers")
        for key, fit in (("holder", fit_h), ("cylinder", fit_c)):
            out[key].update(_pose_dict(fit["R"], fit["t"]))
            out[key]["edge_fit"] = {k: v for k, v in fit.items() if k not in ("R", "t")}
        out["holder"]["edge_fit"]["edges"] = holder_edge_set
    Rch, tch = relative_to_holder(out["holder"]["R"], out["holder"]["t_mm"], out["cylinder"]["R"],
                                  out["cylinder"]["t_mm"])
    out["cylinder_in_holder"] = {"R": Rch, "t_mm": tch}
    Rcam, ccam = camera_in_holder(out["holder"]["R"], out["holder"]["t_mm"])
    out["camera_in_holder"] = {"R": Rcam, "centre_mm": ccam}
    return out


# ---------------------------------------------------------- capture level

def calibrate_capture(capture_dir: str | Path, camera_json: str | Path, rotation: float | None = None,
                      diagnostic: str | Path | None = None, refine: bool = True,
                      holder_edge_set: str = "inner") -> dict:
    """Geometric calibration of one capture (thesis 4.3.2): holder and
    cylinder poses from its calibration image.

    ``camera_json`` is the intrinsics file of ``glossrig calibrate camera``
    (:func:`glossrig.core.calibration.intrinsics.load_camera`); its image size must match
    the capture's. ``rotation`` picks the calibration image of that sample
    rotation; by default the capture's first calibration image is used and, if
    there are several (one per rotation), each is calibrated and reported
    under ``per_rotation``. ``diagnostic``: write a PNG of the detected markers,
    corners, fitted edges and pose axes.

    Returns (numpy arrays; :func:`geometry_to_json` makes it JSON-ready)::

        file, sha256, rotation, image_size, camera (K, dist, source)
        holder:   R, t_mm, rvec (holder -> camera), corner_pnp, reprojection_rms_px, edge_fit
        cylinder: the same for cylinder -> camera
        cylinder_in_holder: R, t_mm   (eq. 4.25, translation corrected)
        camera_in_holder:   R, centre_mm (eq. 4.21, corrected)
        corners_px: holder (8, 2), cylinder (12, 2)
        per_rotation: {rotation: {...}} when the capture has several calibration images
    """
    from glossrig.core.capture import load_manifest
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.raw import linearize
    from glossrig.core.rig import load_rig

    man = load_manifest(capture_dir)
    cams = man.select("calibration")
    if not cams:
        raise InputError("no calibration image (role 'calibration') in the manifest", path=man.path)
    if rotation is not None:
        cams = [c for c in cams if float(c.rotation) == float(rotation)]
        if not cams:
            have = sorted({c.rotation for c in man.select("calibration")})
            raise InputError(f"no calibration image for rotation {rotation:g} (have {have})", path=man.path)
    camera = load_camera(camera_json)
    rig = load_rig(man.rig_path())
    results = []
    for k, im in enumerate(cams):
        path = man.folder / im.file
        if not path.is_file():
            raise InputError("calibration image listed in the manifest is missing", path=path)
        frame = man.read_raw(im)            # checks the manifest's sha256
        digest = im.sha256
        camera.check_size(frame.full_size, path)
        lin = linearize(frame)
        res = marker_poses(lin, frame.cfa, rig, camera.K, camera.dist, str(path), refine=refine,
                           holder_edge_set=holder_edge_set)
        det = res.pop("detection")
        res.update(file=im.file, sha256=digest, rotation=float(im.rotation), image_size=list(frame.full_size),
                   corners_px={"holder": det.holder_image_points(), "cylinder": det.cylinder_image_points()})
        if diagnostic is not None and k == 0:
            from glossrig.core.calibration.demosaic import demosaic

            draw_diagnostic(demosaic(lin, frame.cfa), det, res, rig, camera.K, camera.dist, diagnostic)
            res["diagnostic"] = str(diagnostic)
        results.append(res)
    out = dict(results[0])
    out["capture"] = str(Path(capture_dir))
    out["camera"] = {"K": camera.K, "dist": camera.dist, "source": str(camera_json)}
    if len(results) > 1:
        out["per_rotation"] = {f"{r['rotation']:g}": r for r in results}
    return out


def geometry_to_json(obj):
    """Recursively turn numpy arrays / scalars into lists / floats."""
    if isinstance(obj, dict):
        return {str(k): geometry_to_json(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [geometry_to_json(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


GEOMETRY_FORMAT = "glossrig geometry calibration"


def save_geometry(result: dict, path: str | Path, overwrite: bool = False) -> Path:
    """Write :func:`calibrate_capture`'s result as JSON (atomically; refuses
    to replace a file unless ``overwrite``)."""
    from glossrig.core.atomic import atomic_write_json

    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError("file exists; refusing to overwrite (use --force)", path=path)
    doc = {"format": GEOMETRY_FORMAT, "version": 1, "created": datetime.now(timezone.utc).isoformat(),
           "convention": "x_cam = R x + t (mm); cylinder_in_holder: x_holder = R x_cyl + t_mm"}
    doc.update(geometry_to_json(result))
    atomic_write_json(path, doc)
    return path


def load_geometry(path: str | Path) -> dict:
    """The document of a geometry calibration written by :func:`save_geometry` (poses as
    nested lists, ``convention`` stating the frames): the one reader of the file. Errors
    name the file."""
    from glossrig.core.toml_input import read_json

    path = Path(path)
    d = read_json(path, "geometry calibration")
    if not isinstance(d, dict) or d.get("format") != GEOMETRY_FORMAT:
        raise InputError(f"not a glossrig geometry calibration (format must be {GEOMETRY_FORMAT!r})", path=path)
    return d


# ------------------------------------------------------------ diagnostic

def _tonemap(rgb: np.ndarray, det: MarkerDetection) -> np.ndarray:
    """White-balanced, white -> 0.9, sRGB-encoded 8-bit BGR for drawing."""
    x = np.clip(rgb * det.white_gains / (det.white_level / 0.9), 0, 1)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.ascontiguousarray((srgb[..., ::-1] * 255 + 0.5).astype(np.uint8))


def draw_diagnostic(rgb: np.ndarray, det: MarkerDetection, res: dict, rig, K: np.ndarray, dist,
                    path: str | Path, zoom: int = 6) -> Path:
    """PNG: the tone-mapped calibration image with the detected marker
    outlines and numbered corners (P1..P4 per quad, thesis order), the model
    edges reprojected with the final poses, and the holder and cylinder axes
    (x red, y green, z blue; 20 mm); below it, zoomed crops of every marker
    with the same overlays drawn at sub-pixel precision."""
    img = _tonemap(rgb, det)
    dist = np.asarray(dist, np.float64)
    SH = 4                                      # cv2 fixed-point bits for sub-pixel drawing
    quads = [det.holder_outer, det.holder_inner] + list(det.cylinder)

    def fp(p, s=1.0, off=(0, 0)):
        return tuple(int(round((v - o) * s * (1 << SH))) for v, o in zip(p, off))

    def overlay(canvas, s=1.0, off=(0.0, 0.0), thick=1):
        # model edges with the final poses (magenta)
        for key, edges in (("holder", holder_edges(rig)), ("cylinder", cylinder_edges(rig))):
            R, t = res[key]["R"], res[key]["t_mm"]
            for E in edges:
                P = np.concatenate([np.linspace(E[i], E[i + 1], 8, endpoint=False) for i in range(len(E) - 1)]
                                   + [E[-1:]])
                p, _ = cv2.projectPoints(P, cv2.Rodrigues(R)[0], t, K, dist)
                pts = np.array([fp(q, s, off) for q in p.reshape(-1, 2)], np.int32)
                cv2.polylines(canvas, [pts], False, (255, 0, 255), thick, cv2.LINE_AA, shift=SH)
        for q in quads:
            c = q.corners
            for a, b in SIDES:
                cv2.line(canvas, fp(c[a], s, off), fp(c[b], s, off), (0, 255, 0), thick, cv2.LINE_AA, shift=SH)
            for i, p in enumerate(c):
                cv2.circle(canvas, fp(p, s, off), int(3 * (1 << SH)), (0, 255, 255), thick, cv2.LINE_AA, shift=SH)
                org = (int((p[0] - off[0]) * s) + 4, int((p[1] - off[1]) * s) - 4)
                cv2.putText(canvas, str(i + 1), org, cv2.FONT_HERSHEY_SIMPLEX, 0.35 * max(1, thick), (0, 255, 255),
                            1, cv2.LINE_AA)

    full = img.copy()
    overlay(full, thick=1)
    # holder axes at the holder origin; cylinder axes on its axis at the marker band
    band = np.array([0.0, rig.cylinder_markers.centre_height, 0.0])
    for key, at, length in (("holder", np.zeros(3), 20.0), ("cylinder", band, 15.0)):
        R, t = res[key]["R"], res[key]["t_mm"]
        cv2.drawFrameAxes(full, K, dist, cv2.Rodrigues(R)[0], t + R @ at, length, 2)
    h, w = full.shape[:2]
    cv2.putText(full, f"{Path(det.path).name}  holder rms {res['holder']['reprojection_rms_px']:.2f}px  "
                f"cylinder rms {res['cylinder']['reprojection_rms_px']:.2f}px (corner PnP)",
                (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 1, cv2.LINE_AA)
    # zoomed crops
    crops = []
    groups = [[det.holder_outer, det.holder_inner]] + [[q] for q in det.cylinder]
    for g in groups:
        pts = np.concatenate([q.corners for q in g])
        lo = np.floor(pts.min(axis=0) - 6).astype(int)
        hi = np.ceil(pts.max(axis=0) + 6).astype(int)
        lo = np.maximum(lo, 0)
        hi = np.minimum(hi, [w - 1, h - 1])
        crop = img[lo[1]:hi[1] + 1, lo[0]:hi[0] + 1]
        s = max(1, int(min(zoom, 300 / max(1, crop.shape[0]), 300 / max(1, crop.shape[1])) + 0.5))
        big = cv2.resize(crop, None, fx=s, fy=s, interpolation=cv2.INTER_NEAREST)
        # pixel centres of the crop sit at (i + 0.5) * s - 0.5 in the zoomed image
        overlay(big, s=s, off=(lo[0] - 0.5 + 0.5 / s, lo[1] - 0.5 + 0.5 / s), thick=1)
        crops.append(big)
    row_h = max(c.shape[0] for c in crops)
    row = np.zeros((row_h, sum(c.shape[1] for c in crops) + 8 * (len(crops) - 1), 3), np.uint8)
    x = 0
    for c in crops:
        row[:c.shape[0], x:x + c.shape[1]] = c
        x += c.shape[1] + 8
    if row.shape[1] > w:
        f = w / row.shape[1]
        row = cv2.resize(row, (w, max(1, int(row.shape[0] * f))), interpolation=cv2.INTER_AREA)
    pad = np.zeros((row.shape[0], w, 3), np.uint8)
    pad[:, :row.shape[1]] = row
    out = np.concatenate([full, pad], axis=0)
    path = Path(path)
    if not cv2.imwrite(str(path), out):
        raise InputError("could not write the diagnostic image", path=path)
    return path
