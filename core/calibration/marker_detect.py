"""Finding the red markers of the calibration image and their corners (thesis 4.3.2).

Thesis steps (eq. 4.6-4.17) and what this module does instead:

* **RoI (eq. 4.6).** The thesis isolates the holder marker and the cylinder
  markers with hand-set pixel rectangles. Here no pixel region is needed: the
  red mask's contours are classified by shape. The holder marker is the red
  region with a large white hole (the white patch inside its red frame); the
  cylinder markers are the three solid red quadrilaterals that are most alike
  in size and lie on one line with gaps of about one side (rig
  ``cylinder_markers``), at the size the rig predicts relative to the holder
  marker; the hole must be bright and unsaturated (a covered or recoloured
  patch does not pass). A marker that cannot be found stops with
  :class:`InputError` naming the file.
* **HSV threshold (eq. 4.7)** as in the thesis, on the demosaiced linear image
  after a white balance on the holder marker's white patch, read where the
  rig's nominal geometry puts it (:func:`white_patch_reference`); only if that
  region is not one uniform unclipped colour, on the image's brightest
  unclipped pixels (:func:`white_balance`), which a bright coloured sample can
  outshine. The thesis thresholds an un-balanced camera image with hand-set
  limits; balancing first makes the default limits (:data:`RED_HSV`) hold for
  any camera and exposure.
* **Contours (eq. 4.8-4.10)** by Suzuki's border following (``cv2.findContours``),
  as in the thesis, with the two-level hierarchy that exposes holes.
* **Corners (eq. 4.11-4.17).** The thesis runs Harris on the filled mask and
  keeps the four mutually farthest responses - pixel-accurate at best. Here a
  4-gon fit to the contour (``cv2.approxPolyN``) gives initial corners; each
  side is then located to a small fraction of a pixel from the grey-level
  "redness" image (R - G after white balance, linear in the scene radiance, so
  the half-contrast crossing of its profile across a blurred step is the edge
  itself): profiles normal to the side every pixel, their half-level
  crossings, undistorted with the calibrated lens model (so straight 3-D edges
  are straight), fitted with a line and intersected with the neighbouring
  sides. The cylinder markers' top and bottom edges are arcs about the
  cylinder axis, curved in the image: after a first pose from straight-side
  corners, :func:`refine_cylinder_arcs` refits them as parabolas whose
  curvature that pose predicts (a fitted curvature extrapolates to the corners
  worse than a predicted one: 0.2 px against 0.5-0.9 px corner error at scale
  0.15). The holder marker's inner (white-patch) corners are found the same
  way and used as four more PnP points (the thesis uses the outer four only).
  These corners feed the thesis-style PnP; the final poses come from
  :func:`glossrig.core.calibration.poses.refine_pose_edges`, which fits the raw pixels.
* **Ordering.** The thesis sorts corners by image x and y because its camera is
  rolled 90 degrees (holder on the right). Here the "up" (holder +y) and
  "right" (holder +x) image directions come from the rig's nominal camera pose
  (:meth:`glossrig.core.rig.Camera.pose`), which reproduces the thesis's rule for
  its rig and holds for any roll; corners are assigned by angle around the
  quad's centre, so a rig within +-45 degrees of its nominal roll is ordered
  right. Order within a quad: upper-left, upper-right, lower-left, lower-right
  (thesis P1..P4, eq. 4.18); cylinder markers by increasing angle (holder +x).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from glossrig.core.errors import InputError

#: Default HSV limits of "red" (eq. 4.7) on the white-balanced linear image:
#: hue in degrees (wrapping through 0), saturation and value in [0, 1] (value
#: relative to the white reference, see :func:`white_balance`).
RED_HSV = {"hue_half_width": 25.0, "s_min": 0.45, "v_min": 0.06}

#: Side order of a quad with corners (UL, UR, LL, LR): top, right, bottom, left.
SIDES = ((0, 1), (1, 3), (3, 2), (2, 0))


# ------------------------------------------------------------------ data

@dataclass
class Quad:
    """One marker quadrilateral: ``corners`` (4, 2) distorted image pixels,
    ordered UL, UR, LL, LR; ``initial`` the polygon-fit corners before
    refinement; ``edge_points`` per side (top, right, bottom, left) the
    sub-pixel edge samples used (image px); ``side_rms`` the RMS distance (px)
    of those samples from their fitted curve."""

    corners: np.ndarray
    initial: np.ndarray
    contour: np.ndarray
    area: float
    edge_points: list = field(default_factory=list)
    side_rms: list = field(default_factory=list)
    half: float = 0.0          # half-length (px) of the edge profiles

    @property
    def centre(self) -> np.ndarray:
        return self.corners.mean(axis=0)


@dataclass
class MarkerDetection:
    """Markers found in one calibration image (see module docstring)."""

    path: str
    holder_outer: Quad
    holder_inner: Quad
    cylinder: list            # three Quads, by increasing angle on the cylinder
    white_gains: np.ndarray   # per-channel gains applied before thresholding
    white_level: float        # white reference (after gains) that V is relative to
    image_size: tuple[int, int]
    signal: np.ndarray | None = field(default=None, repr=False)   # the "redness" image the edges were read from
    contrast: float = 0.0     # smallest red/background contrast an edge profile must show

    def holder_image_points(self) -> np.ndarray:
        """(8, 2): outer UL UR LL LR, then inner UL UR LL LR."""
        return np.concatenate([self.holder_outer.corners, self.holder_inner.corners])

    def cylinder_image_points(self) -> np.ndarray:
        """(12, 2) in the order of :func:`glossrig.core.calibration.markers.cylinder_marker_corners`:
        upper row by angle, then lower row by angle."""
        upper, lower = [], []
        for q in self.cylinder:
            upper += [q.corners[0], q.corners[1]]
            lower += [q.corners[2], q.corners[3]]
        return np.array(upper + lower, np.float64)


# ------------------------------------------------------------- colour

def white_balance(rgb: np.ndarray, top_fraction: float = 0.02,
                  reference: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Per-channel gains making the white reference neutral, and its level
    after the gains. Returns (gains (3,), white level).

    ``reference`` is the raw colour of a known white (detection passes the holder
    marker's white patch, :func:`white_patch_reference`). Without one, the
    brightest unclipped pixels are taken as white: the median colour of the top
    ``top_fraction`` by green value (channels all below 0.98 of the clip
    level) - right when the white paper parts are the brightest surfaces, wrong
    when a bright coloured sample outshines them (a saturated yellow highlight
    then sets the "white", and the balanced markers are no longer red).
    """
    if reference is not None:
        ref = np.asarray(reference, np.float64).reshape(3)
        if not np.all(ref > 0):
            raise InputError(f"white reference must be positive in every channel, got {ref.tolist()}")
        return (ref[1] / ref).astype(np.float32), float(ref[1])
    a = rgb.reshape(-1, 3)
    ok = np.all(a < 0.98 * float(a.max()), axis=1) & np.all(a > 0, axis=1)
    if ok.sum() < 100:
        return np.ones(3, np.float32), float(max(a.max(), 1e-12))
    g = a[ok, 1]
    thr = np.quantile(g, 1.0 - top_fraction)
    ref = np.median(a[ok][g >= thr], axis=0)
    if not np.all(ref > 0):
        return np.ones(3, np.float32), float(max(a.max(), 1e-12))
    gains = (ref[1] / ref).astype(np.float32)
    return gains, float(ref[1])


#: Part of the white patch (linear size about its centre) read by :func:`white_patch_reference`,
#: and the largest relative spread (MAD / median per channel) it may show to count as one white.
WHITE_PATCH_KEEP = 0.5
WHITE_PATCH_MAX_SPREAD = 0.1
#: The patch must be at least as bright (green) as this quantile of the whole image.
WHITE_PATCH_MIN_RANK = 0.8
#: Largest ratio between the raw channels of a white (the twin's camera: 1.43).
WHITE_MAX_CHANNEL_RATIO = 4.0


def white_patch_reference(rgb: np.ndarray, rig, K: np.ndarray, dist) -> np.ndarray | None:
    """Raw colour of the holder marker's white patch: the median over the central
    :data:`WHITE_PATCH_KEEP` of the patch where the rig's nominal camera pose
    (:meth:`glossrig.core.rig.Camera.pose`) and ``K``/``dist`` put it - the rig's
    geometry, not a hand-set pixel region; the central half tolerates a pose off by a
    quarter of the patch (4 mm on the thesis rig). None when that region is not one
    white: too few pixels, more than 5 % of them clipped or non-positive, a spread
    above :data:`WHITE_PATCH_MAX_SPREAD` (the region straddles the red frame or
    something else), a green level below the image's :data:`WHITE_PATCH_MIN_RANK`
    quantile (a covered patch; twin captures: 0.955 with a saturated yellow sample,
    0.970 with a white one) or raw channels further apart than
    :data:`WHITE_MAX_CHANNEL_RATIO` (a coloured cover). A coloured sample cannot pass
    for it, however bright; without it :func:`white_balance` falls back on the
    brightest pixels."""
    from glossrig.core.calibration.markers import holder_marker_corners

    R, t = rig.camera.pose()
    c = holder_marker_corners(rig, inner=True)
    c = c.mean(axis=0) + WHITE_PATCH_KEEP * (c - c.mean(axis=0))
    p, _ = cv2.projectPoints(c, cv2.Rodrigues(np.asarray(R, np.float64))[0], np.asarray(t, np.float64), K,
                             np.asarray(dist, np.float64))
    poly = np.round(p.reshape(-1, 2)[[0, 1, 3, 2]]).astype(np.int32)        # UL UR LR LL
    h, w = rgb.shape[:2]
    if np.any(poly < 0) or np.any(poly[:, 0] >= w) or np.any(poly[:, 1] >= h):
        return None
    m = np.zeros((h, w), np.uint8)
    cv2.fillConvexPoly(m, poly, 1)
    a = rgb[m > 0].astype(np.float64)
    if len(a) < 25:
        return None
    bad = np.any(a >= 0.98 * float(rgb.max()), axis=1) | np.any(a <= 0, axis=1)
    if bad.mean() > 0.05:
        return None
    a = a[~bad]
    med = np.median(a, axis=0)
    mad = np.median(np.abs(a - med), axis=0)
    if np.any(mad > WHITE_PATCH_MAX_SPREAD * med):
        return None
    if med[1] < np.quantile(rgb[::4, ::4, 1], WHITE_PATCH_MIN_RANK):
        return None
    if med.max() > WHITE_MAX_CHANNEL_RATIO * med.min():
        return None
    return med


def red_mask(rgb_balanced: np.ndarray, white: float, hsv: dict | None = None) -> np.ndarray:
    """Thesis eq. 4.7: 1 where hue, saturation and value lie within the red
    limits (:data:`RED_HSV` unless ``hsv`` overrides), on a white-balanced
    linear image whose white reference is ``white``."""
    lim = dict(RED_HSV, **(hsv or {}))
    img = np.clip(rgb_balanced / np.float32(white), 0, 1).astype(np.float32)
    h, s, v = cv2.split(cv2.cvtColor(img, cv2.COLOR_RGB2HSV))   # float: H in [0, 360)
    hw = lim["hue_half_width"]
    hue_ok = (h <= hw) | (h >= 360.0 - hw)
    m = hue_ok & (s >= lim["s_min"]) & (v >= lim["v_min"])
    return m.astype(np.uint8)


# ------------------------------------------------------- contours -> quads

@dataclass
class _Blob:
    contour: np.ndarray
    area: float
    hole: np.ndarray | None
    hole_area: float
    poly: np.ndarray           # (4, 2) initial corners (cyclic order)
    fill: float                # contour area / 4-gon area
    touches_border: bool


def _quad4(contour: np.ndarray) -> tuple[np.ndarray, float]:
    poly = cv2.approxPolyN(contour, 4).reshape(-1, 2).astype(np.float64)
    if len(poly) != 4:
        return poly, 0.0
    a_poly = abs(cv2.contourArea(poly.astype(np.float32)))
    a = abs(cv2.contourArea(contour))
    return poly, (a / a_poly if a_poly > 0 else 0.0)


def _blobs(mask: np.ndarray, min_area: float) -> list[_Blob]:
    contours, hier = cv2.findContours(mask, cv2.RETR_CCOMP, cv2.CHAIN_APPROX_NONE)
    if hier is None:
        return []
    hier = hier[0]
    h, w = mask.shape
    out = []
    for i, c in enumerate(contours):
        if hier[i][3] != -1:
            continue                                   # a hole; handled with its parent
        area = abs(cv2.contourArea(c))
        if area < min_area or len(c) < 8:
            continue
        # largest hole of this outer contour
        hole, hole_area = None, 0.0
        j = hier[i][2]
        while j != -1:
            ha = abs(cv2.contourArea(contours[j]))
            if ha > hole_area:
                hole, hole_area = contours[j], ha
            j = hier[j][0]
        poly, fill = _quad4(c)
        x, y, bw, bh = cv2.boundingRect(c)
        border = x <= 1 or y <= 1 or x + bw >= w - 1 or y + bh >= h - 1
        out.append(_Blob(c, area, hole, hole_area, poly, fill, border))
    return out


def _directions(up: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    up = np.asarray(up, np.float64)
    right = np.asarray(right, np.float64)
    return up / np.linalg.norm(up), right / np.linalg.norm(right)


def order_corners(pts: np.ndarray, up: np.ndarray, right: np.ndarray) -> np.ndarray:
    """Corners of a quad (any order) -> UL, UR, LL, LR (thesis P1..P4) given the
    image directions of the holder's +y (``up``) and +x (``right``).

    Each corner's angle about the centre in the (right, up) basis is matched
    to UR 45, UL 135, LL -135, LR -45 degrees by the best cyclic shift, so the
    order is right for quads turned by up to 45 degrees from nominal."""
    up, right = _directions(up, right)
    p = np.asarray(pts, np.float64).reshape(4, 2)
    d = p - p.mean(axis=0)
    ang = np.degrees(np.arctan2(d @ up, d @ right))
    by_angle = np.argsort(ang)
    targets = np.array([-135.0, -45.0, 45.0, 135.0])        # LL, LR, UR, UL
    best, best_cost = None, np.inf
    for shift in range(4):
        idx = np.roll(by_angle, shift)
        diff = (ang[idx] - targets + 180.0) % 360.0 - 180.0
        cost = float(np.sum(diff ** 2))
        if cost < best_cost:
            best, best_cost = idx, cost
    assert best is not None, "corner angles are not finite"
    ll, lr, ur, ul = best
    return p[[ul, ur, ll, lr]]


# -------------------------------------------------------- edge refinement

def _ideal(pts: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    """Distorted image px -> ideal (undistorted) pinhole px with the same K."""
    p = np.asarray(pts, np.float64).reshape(-1, 1, 2)
    if dist is None or not np.any(dist):
        return p.reshape(-1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
    return cv2.undistortPoints(p, K, np.asarray(dist, np.float64), R=np.eye(3), P=K, criteria=crit).reshape(-1, 2)


def _distort(pts: np.ndarray, K: np.ndarray, dist) -> np.ndarray:
    """Ideal pinhole px -> distorted image px (OpenCV model)."""
    p = np.asarray(pts, np.float64).reshape(-1, 2)
    if dist is None or not np.any(dist):
        return p
    xn = np.c_[(p[:, 0] - K[0, 2]) / K[0, 0], (p[:, 1] - K[1, 2]) / K[1, 1], np.ones(len(p))]
    out, _ = cv2.projectPoints(xn, np.zeros(3), np.zeros(3), K, np.asarray(dist, np.float64))
    return out.reshape(-1, 2)


def _edge_samples(signal: np.ndarray, a: np.ndarray, b: np.ndarray, half: float, margin: float,
                  step: float = 1.0, dt: float = 0.25, min_contrast: float = 0.0) -> np.ndarray:
    """Sub-pixel edge positions along the side a->b of ``signal`` (a linear
    image with a blurred step across the side): at every ``step`` px along the
    side (leaving ``margin`` px at each corner), the profile along the normal
    over +-``half`` px is read (bilinear), its two plateaus taken as the
    medians of its outer quarters, and the half-level crossing nearest the
    side located by linear interpolation. Returns (N, 2) image px."""
    d = b - a
    length = float(np.linalg.norm(d))
    if length < 2 * margin + 2:
        return np.empty((0, 2))
    d /= length
    n = np.array([-d[1], d[0]])
    along = np.arange(margin, length - margin + 1e-9, step)
    s = np.arange(-half, half + 1e-9, dt)
    px = a[0] + along[:, None] * d[0] + s[None, :] * n[0]
    py = a[1] + along[:, None] * d[1] + s[None, :] * n[1]
    prof = cv2.remap(signal, px.astype(np.float32), py.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)
    q = max(2, len(s) // 4)
    lo = np.median(prof[:, :q], axis=1)
    hi = np.median(prof[:, -q:], axis=1)
    mid = 0.5 * (lo + hi)
    rel = prof - mid[:, None]
    sign = np.signbit(rel)
    cross = sign[:, 1:] != sign[:, :-1]                  # crossing between k and k+1
    centre = len(s) // 2
    k_idx = np.arange(len(s) - 1)
    dist_to_centre = np.where(cross, np.abs(k_idx - centre + 0.5), np.inf)
    k = np.argmin(dist_to_centre, axis=1)
    rows = np.arange(len(along))
    valid = np.isfinite(dist_to_centre[rows, k]) & (np.abs(hi - lo) > min_contrast)
    r0, r1 = rel[rows, k], rel[rows, k + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        frac = np.where(r1 != r0, r0 / (r0 - r1), 0.5)
    off = s[k] + frac * dt
    pts = np.stack([a[0] + along * d[0] + off * n[0], a[1] + along * d[1] + off * n[1]], axis=-1)
    return pts[valid]


class _SideCurve:
    """v = c0 + c1 u + c2 u^2 in a local frame (origin o = chord midpoint, unit
    direction e from a to b, normal m). ``c2`` is given (None = straight side):
    only offset and slope are fitted, with iterative 3.5-sigma (MAD) rejection."""

    def __init__(self, pts: np.ndarray, a: np.ndarray, b: np.ndarray, c2: float | None = None):
        self.o = 0.5 * (a + b)
        e = b - a
        self.e = e / np.linalg.norm(e)
        self.m = np.array([-self.e[1], self.e[0]])
        u, v = self._uv(pts)
        c2 = 0.0 if c2 is None else float(c2)
        v = v - c2 * u * u
        keep = np.ones(len(u), bool)
        for _ in range(3):
            A = np.stack([np.ones(keep.sum()), u[keep]], axis=-1)
            coef, *_ = np.linalg.lstsq(A, v[keep], rcond=None)
            res = v - (coef[0] + coef[1] * u)
            sig = 1.4826 * np.median(np.abs(res[keep])) + 1e-6
            new = np.abs(res) < 3.5 * sig
            if new.sum() < 5 or np.array_equal(new, keep):
                break
            keep = new
        self.coef = np.array([coef[0], coef[1], c2])
        self.rms = float(np.sqrt(np.mean(res[keep] ** 2)))
        self.n_used = int(keep.sum())

    def _uv(self, p):
        d = np.asarray(p, np.float64).reshape(-1, 2) - self.o
        return d @ self.e, d @ self.m

    def f(self, p):
        u, v = self._uv(p)
        c = self.coef
        return float(v[0] - (c[0] + c[1] * u[0] + c[2] * u[0] ** 2)), self.m - (c[1] + 2 * c[2] * u[0]) * self.e


def side_curvature(corner_a: np.ndarray, corner_b: np.ndarray, curve: np.ndarray) -> float:
    """c2 of ``curve`` ((N, 2) points, e.g. a projected 3-D arc, ideal px) in the
    local frame of the chord ``corner_a`` -> ``corner_b`` used by :func:`refine_quad`."""
    o = 0.5 * (corner_a + corner_b)
    e = (corner_b - corner_a) / np.linalg.norm(corner_b - corner_a)
    m = np.array([-e[1], e[0]])
    d = np.asarray(curve, np.float64) - o
    u, v = d @ e, d @ m
    return float(np.polyfit(u, v, 2)[0])


def _intersect(c1: _SideCurve, c2: _SideCurve, p0: np.ndarray) -> np.ndarray:
    p = np.asarray(p0, np.float64).copy()
    for _ in range(20):
        f1, g1 = c1.f(p)
        f2, g2 = c2.f(p)
        J = np.array([g1, g2])
        try:
            dp = np.linalg.solve(J, -np.array([f1, f2]))
        except np.linalg.LinAlgError:
            break
        p += dp
        if np.linalg.norm(dp) < 1e-10:
            break
    return p


def refine_quad(signal: np.ndarray, corners: np.ndarray, K: np.ndarray, dist, half: float, path: str, what: str,
                min_contrast: float = 0.0, curvature: tuple | None = None) -> tuple[np.ndarray, list, list]:
    """Sub-pixel corners of an ordered quad (UL, UR, LL, LR) from its sides'
    edge samples (see module docstring). ``curvature[i]`` is None for a side
    (top, right, bottom, left) that is straight in the undistorted image, or
    the c2 of its parabola there (:func:`side_curvature`; the cylinder
    markers' arcs, predicted from a first pose - with few samples per side a
    fitted curvature extrapolates worse to the corners than a predicted one).
    Returns (corners (4, 2) image px, edge samples per side, fit RMS per side
    in ideal px)."""
    c = np.asarray(corners, np.float64)
    curvature = curvature or (None,) * 4
    curves, samples, rms = [], [], []
    ideal_c = _ideal(c, K, dist)
    for i, (ia, ib) in enumerate(SIDES):
        a, b = c[ia], c[ib]
        length = float(np.linalg.norm(b - a))
        margin = 2.0 + half * 0.25 + 0.06 * length
        pts = _edge_samples(signal, a, b, half, margin, min_contrast=min_contrast)
        if len(pts) < 5:
            raise InputError(f"{what}: side {('top', 'right', 'bottom', 'left')[i]} has only {len(pts)} usable "
                             f"edge samples (marker too small, blurred or partly hidden)", path=path)
        curves.append(_SideCurve(_ideal(pts, K, dist), ideal_c[ia], ideal_c[ib], curvature[i]))
        samples.append(pts)
        rms.append(curves[-1].rms)
    out = np.empty((4, 2))
    # corner k is where the two sides that meet there cross
    meet = {0: (0, 3), 1: (0, 1), 3: (1, 2), 2: (2, 3)}
    for k, (s1, s2) in meet.items():
        out[k] = _intersect(curves[s1], curves[s2], ideal_c[k])
    out = _distort(out, K, dist)
    moved = np.linalg.norm(out - c, axis=1) if np.all(np.isfinite(out)) else np.array([np.inf])
    if moved.max() > max(3.0, 0.5 * half):
        raise InputError(f"{what}: corner refinement moved a corner by {moved.max():.1f} px from the polygon fit; "
                         f"the marker's edges are not clean", path=path)
    return out, samples, rms


# ----------------------------------------------------------------- finding

def _nominal_directions(rig, K, dist, point_holder: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Image directions of holder +y and +x at ``point_holder`` under the
    rig's nominal camera pose (projected 1 mm steps)."""
    R, t = rig.camera.pose()
    p = np.asarray(point_holder, np.float64)
    obj = np.array([p, p + [0, 1.0, 0], p + [1.0, 0, 0]])
    img, _ = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, K, np.asarray(dist, np.float64))
    img = img.reshape(-1, 2)
    return img[1] - img[0], img[2] - img[0]


def detect_markers(rgb: np.ndarray, rig, K: np.ndarray, dist, path: str = "<image>",
                   hsv: dict | None = None) -> MarkerDetection:
    """Find the holder marker and the three cylinder markers in a demosaiced
    linear calibration image ``rgb`` (H, W, 3) and refine their corners.

    ``K``/``dist`` are the calibrated intrinsics (used to undistort edge
    samples), ``rig`` supplies marker proportions and the nominal camera
    orientation. Raises :class:`InputError` naming ``path`` when a marker is
    missing, hidden, cut by the image border or ambiguous.
    """
    rgb = np.asarray(rgb, np.float32)
    if rgb.ndim != 3 or rgb.shape[2] != 3:
        raise InputError(f"calibration image must be RGB (H, W, 3), got shape {rgb.shape}", path=path)
    h, w = rgb.shape[:2]
    if not np.all(np.isfinite(rgb)) or float(rgb.max()) <= 0:
        raise InputError("calibration image is empty (all black) or holds non-finite values", path=path)
    gains, white = white_balance(rgb, reference=white_patch_reference(rgb, rig, K, dist))
    bal = rgb * gains
    mask = red_mask(bal, white, hsv)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    min_area = max(16.0, 2e-5 * h * w)
    blobs = _blobs(mask, min_area)
    redness = np.ascontiguousarray((bal[..., 0] - bal[..., 1]) / np.float32(white))

    hm = rig.holder.marker
    frame_ratio = hm.frame / hm.outer_width
    hole_ratio = (1 - 2 * frame_ratio) ** 2                       # white patch / outer area
    holders = [b for b in blobs if b.hole is not None and len(b.poly) == 4 and b.fill > 0.85
               and 0.4 * hole_ratio < b.hole_area / b.area < min(0.95, 2.0 * hole_ratio)]
    if not holders:
        raise InputError(f"holder marker not found: no red square frame around a white patch among "
                         f"{len(blobs)} red regions (hidden, out of view, or not lit?)", path=path)
    hsv = cv2.cvtColor(np.clip(bal / np.float32(white), 0, 1).astype(np.float32), cv2.COLOR_RGB2HSV)

    def white_inside(b) -> bool:
        """The hole is the white patch: bright and unsaturated (median over its interior)."""
        m: np.ndarray = np.zeros(mask.shape, np.uint8)
        cv2.drawContours(m, [b.hole], -1, 1, thickness=cv2.FILLED)
        m = cv2.erode(m, np.ones((3, 3), np.uint8))
        if m.sum() < 4:
            return False
        s, v = np.median(hsv[..., 1][m > 0]), np.median(hsv[..., 2][m > 0])
        return bool(s < 0.3 and v > 0.25)

    holders = [b for b in holders if white_inside(b)]
    if not holders:
        raise InputError("holder marker not found: the red square frame does not hold a white patch "
                         "(patch covered or marker replaced?)", path=path)
    holder = max(holders, key=lambda b: b.area)
    if holder.touches_border:
        raise InputError("holder marker touches the image border (partly out of view)", path=path)
    assert holder.hole is not None              # holders all have one (filtered above)
    hole_poly, hole_fill = _quad4(holder.hole)
    if len(hole_poly) != 4 or hole_fill < 0.85:
        raise InputError("holder marker's white patch is not a clean quadrilateral (marker partly hidden?)",
                         path=path)

    # --- orientation from the rig's nominal camera pose
    centre_h = np.array([0.0, hm.centre_y, rig.holder.depth / 2])
    up_h, right_h = _nominal_directions(rig, K, dist, centre_h)
    outer0 = order_corners(holder.poly, up_h, right_h)
    inner0 = order_corners(hole_poly, up_h, right_h)
    side_out = np.sqrt(holder.area)
    frame_px = 0.5 * (np.sqrt(holder.area) - np.sqrt(holder.hole_area))
    half_h = float(np.clip(0.4 * frame_px, 2.0, 15.0))
    contrast = 0.25 * float(np.median(redness[cv2.erode(mask, np.ones((3, 3), np.uint8)) > 0])) if mask.any() else 0.0
    oc, osamp, orms = refine_quad(redness, outer0, K, dist, half_h, path, "holder marker (outer edge)", contrast)
    ic, isamp, irms = refine_quad(redness, inner0, K, dist, half_h, path, "holder marker (white patch)", contrast)
    holder_outer = Quad(oc, outer0, holder.contour, holder.area, osamp, orms)
    holder_inner = Quad(ic, inner0, holder.hole, holder.hole_area, isamp, irms)

    # --- cylinder markers: solid quads of the predicted size, three in a row
    cm = rig.cylinder_markers
    side_ratio = cm.side / hm.outer_width
    expect = (side_ratio * side_out) ** 2
    cands = [b for b in blobs if b is not holder and len(b.poly) == 4 and b.fill > 0.8
             and b.hole_area < 0.1 * b.area and 0.25 * expect < b.area < 4.0 * expect and not b.touches_border]
    n_needed = cm.count
    if len(cands) < n_needed:
        seen = len([b for b in blobs if b is not holder])
        raise InputError(f"cylinder markers: found {len(cands)} of {n_needed} red squares of the expected size "
                         f"(~{np.sqrt(expect):.0f} px side; {seen} other red regions) - a marker is hidden, "
                         f"out of view or not lit", path=path)
    centre_c = np.array([0.0, cm.centre_height, rig.cylinder_radius])
    up_c, right_c = _nominal_directions(rig, K, dist, centre_c)
    best = _best_row(cands, n_needed, side_ratio * side_out, path)
    best.sort(key=lambda b: float(np.mean(b.poly, axis=0) @ (right_c / np.linalg.norm(right_c))))
    quads = []
    for k, b in enumerate(best):
        init = order_corners(b.poly, up_c, right_c)
        half_c = float(np.clip(0.25 * np.sqrt(b.area), 2.0, 15.0))
        # first pass: all sides straight; refine_cylinder_arcs redoes the arcs once a pose is known
        cc, cs, cr = refine_quad(redness, init, K, dist, half_c, path, f"cylinder marker {k + 1}", contrast)
        quads.append(Quad(cc, init, b.contour, b.area, cs, cr, half=half_c))
    return MarkerDetection(path=str(path), holder_outer=holder_outer, holder_inner=holder_inner, cylinder=quads,
                           white_gains=gains, white_level=white, image_size=(w, h), signal=redness,
                           contrast=contrast)


def refine_cylinder_arcs(det: MarkerDetection, arcs_ideal: list, K: np.ndarray, dist) -> None:
    """Redo the cylinder markers' corners with the curvature of their top and
    bottom arcs predicted by a first pose: ``arcs_ideal[k]`` = (top, bottom)
    arcs of marker k projected into the undistorted image (N, 2). Updates
    ``det.cylinder`` in place."""
    assert det.signal is not None, "refine_cylinder_arcs needs the detection's signal image"
    for k, q in enumerate(det.cylinder):
        ic = _ideal(q.corners, K, dist)
        top, bottom = arcs_ideal[k]
        curv = (side_curvature(ic[0], ic[1], top), None, side_curvature(ic[3], ic[2], bottom), None)
        cc, cs, cr = refine_quad(det.signal, q.corners, K, dist, q.half, det.path, f"cylinder marker {k + 1}",
                                 det.contrast, curvature=curv)
        q.corners, q.edge_points, q.side_rms = cc, cs, cr


def _best_row(cands: list, n: int, side_px: float, path: str) -> list:
    """The ``n`` candidates most like a row of equal squares with one-side gaps:
    similar areas, centres on a line, neighbours about two sides apart."""
    from itertools import combinations

    best, best_cost = None, np.inf
    for combo in combinations(cands, n):
        areas = np.array([b.area for b in combo])
        cen = np.array([b.poly.mean(axis=0) for b in combo])
        size = np.sqrt(areas.mean())
        # principal direction of the centres; order along it
        d = cen - cen.mean(axis=0)
        _, _, vt = np.linalg.svd(d)
        along = d @ vt[0]
        across = d @ vt[1] if len(vt) > 1 else np.zeros(n)
        o = np.argsort(along)
        gaps = np.diff(along[o]) / size
        cost = (np.std(np.log(areas)) * 4 + np.sqrt(np.mean(across ** 2)) / size * 4
                + np.mean(np.abs(gaps - 2.0)) + abs(np.log(size / side_px)))
        if cost < best_cost:
            best, best_cost = list(combo), cost
    if best is None or best_cost > 3.0:        # best is None only while best_cost is inf
        raise InputError(f"cylinder markers: no {n} red squares form the expected row (best match cost "
                         f"{best_cost:.2f}); a marker is hidden or something red is in view", path=path)
    return best
