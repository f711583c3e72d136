"""BRDF-space coverage of a rig design, from its geometry alone (thesis 7.1.3, fig. 7.2).

Thesis 7.1.3: the measured samples are binned at 1 degree, in the anisotropic
space (theta_in, theta_out, phi_in, phi_out) and in the isotropic space
(theta_in, theta_out, |phi_in - phi_out|); the coverage is the number of bins
holding a sample divided by the number of bins of the space. The thesis
prints 0.98 % (isotropic) and 0.1 % (anisotropic) for its rig measured with
the eight middle-row LEDs (thesis 4.2.3), but not the conventions behind the
figures. This module computes the coverage for every plausible convention so
that they can be set side by side (see ``validation/design``):

``filter``
    which pixels count as measured. ``lit``: both directions above the
    surface (what :func:`glossrig.core.extraction.cylinder.nominal_samples` keeps);
    ``between``: in addition the normal lies between the camera and lamp
    directions in the cylinder's cross-section, the pixels the thesis keeps
    in fig. 7.2 ("these points are not considered in the measurements",
    7.1.3); ``visible``: every pixel on the sample, lit or not, so theta_in
    runs over [0, 180) and the space is that large.
``dphi``
    ``folded``: |phi_in - phi_out| taken on the circle, in [0, 180] (180 bins,
    the value 180 itself in the last one); ``literal``: the plain
    |phi_in - phi_out| of azimuths in [0, 360), in [0, 360) (360 bins).
``reciprocity``
    bins identified under the swap of incident and outgoing directions
    (Helmholtz reciprocity): numerator and denominator both count classes.
``pi_fold``
    anisotropic bins identified under (phi_in, phi_out) -> (phi_in + 180,
    phi_out + 180): a lobe that is symmetric under a half turn about the
    normal (every extended-Ward lobe, thesis eq. 4.79) cannot tell them apart.
``geometry`` (chosen when collecting)
    ``corrected``: the angles of :mod:`glossrig.core.models.angles` (the project's
    geometry); ``printed``: the thesis's equations as printed, which may be
    what produced its figures: the incident vector starts at the axis point
    (eq. 4.59) and the azimuth is the unsigned angle between the tangent and
    the negated projection (eq. 4.68-4.69 with the always-zero test of
    eq. 4.70), i.e. ``180 - |phi|`` with phi signed in (-180, 180]: azimuths
    fill [0, 180] only.
``phi_bins``
    bins per azimuth in the denominator: 360 (the space as 7.1.3 defines it)
    or, for the printed geometry, 180 (the range its azimuths can reach).

Bins are ``floor(angle in degrees)``; azimuths are those of
:mod:`glossrig.core.models.angles` (counter-clockwise from the tangent, [0, 360)).
A sample rotation r turns the tangent about the normal (thesis eq. 4.62), which
subtracts r from both azimuths and leaves the zenith angles alone, so the
geometry is computed once per LED and the rotations are applied to the
azimuths.

The pixel density matters (more pixels, more occupied bins): ``scale`` is the
image scale of :meth:`glossrig.core.rig.Camera.matrix`; the thesis demosaics
to full resolution (4.3.1), i.e. ``scale = 1``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from collections.abc import Callable, Iterable, Sequence

import cv2
import numpy as np

from glossrig.core.models.angles import normalize
from glossrig.core.extraction.cylinder import surface_samples
from glossrig.core.errors import InputError

FILTERS = ("lit", "between", "visible")
GEOMETRIES = ("corrected", "printed")
DPHI_MODES = ("folded", "literal")
PRINTED = {"isotropic": 0.0098, "anisotropic": 0.001}   # thesis 7.1.3, as fractions

_T = 180            # theta_in code range (the "visible" filter reaches 180)
_TO = 90            # theta_out range (a pixel sees the sample from above)
_P = 360


# ----------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------

@dataclass(frozen=True)
class PixelGeometry:
    """The pixels that see the sample at one image scale (holder frame, mm)."""

    points: np.ndarray
    normals: np.ndarray
    camera_centre: np.ndarray
    axis: np.ndarray
    u: np.ndarray
    v: np.ndarray
    scale: float
    camera_distance: float

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def subset(self, idx) -> PixelGeometry:
        return replace(self, points=self.points[idx], normals=self.normals[idx], u=self.u[idx], v=self.v[idx])


def with_camera_distance(rig, distance_mm: float | None):
    """The rig with its camera moved along +z to ``distance_mm`` from the axis
    (the thesis rig's 500 mm is inferred, rig-facts.toml)."""
    if distance_mm is None:
        return rig
    d = float(distance_mm)
    if not (math.isfinite(d) and d > rig.cylinder_radius + 1):
        raise InputError(f"camera distance must exceed the cylinder radius ({rig.cylinder_radius} mm), got {distance_mm!r}")
    return replace(rig, camera=replace(rig.camera, distance_to_axis=d))


def sample_roi(rig, scale: float) -> tuple[int, int, int, int]:
    """Pixel box (x0, y0, x1, y1) holding the sample: the projection of its
    bounding box through the rig's lens, padded by 2 pixels."""
    cam = rig.camera
    R, t = cam.pose()
    r, h = rig.cylinder_radius, rig.sample_height
    corners = np.array([[x, y, z] for x in (-r, r) for y in (-h / 2, h / 2) for z in (-r, r)], float)
    rvec, _ = cv2.Rodrigues(R)
    img, _ = cv2.projectPoints(corners, rvec, t.astype(float), cam.matrix(scale), np.asarray(cam.distortion, float))
    img = img.reshape(-1, 2)
    w, hh = cam.size(scale)
    x0 = max(0, int(math.floor(img[:, 0].min())) - 2)
    y0 = max(0, int(math.floor(img[:, 1].min())) - 2)
    x1 = min(w, int(math.ceil(img[:, 0].max())) + 3)
    y1 = min(hh, int(math.ceil(img[:, 1].max())) + 3)
    if x1 <= x0 or y1 <= y0:
        raise InputError(f"the sample does not project into the image of rig {rig.name!r}", path=rig.path)
    return x0, y0, x1, y1


def pixel_geometry(rig, scale: float = 1.0, camera_distance: float | None = None) -> PixelGeometry:
    """Ray-cast every pixel of the nominal camera onto the sample (thesis 4.3.2,
    via :func:`glossrig.core.extraction.cylinder.surface_samples`)."""
    scale = float(scale)
    if not (math.isfinite(scale) and 0 < scale <= 1):
        raise InputError(f"pixel scale must lie in (0, 1], got {scale!r}")
    rig = with_camera_distance(rig, camera_distance)
    cam = rig.camera
    R, t = cam.pose()
    s = surface_samples(cam.matrix(scale), cam.distortion, cam.size(scale), R, t, np.eye(3), np.zeros(3),
                        rig.cylinder_radius, rig.sample_height, roi=sample_roi(rig, scale))
    if len(s.u) == 0:
        raise InputError(f"no pixel sees the sample at scale {scale}", path=rig.path)
    return PixelGeometry(points=s.points, normals=s.normals, camera_centre=np.asarray(s.camera_centre, float),
                         axis=np.asarray(s.axis, float), u=s.u, v=s.v, scale=scale,
                         camera_distance=float(cam.distance_to_axis))


def direction_angles(geom: PixelGeometry, lamp_position, incident_from_axis: bool = False,
                     half: bool = False) -> dict[str, np.ndarray]:
    """Zenith and azimuth (degrees) of the lamp and camera directions at every
    pixel, at sample rotation 0, and the masks of :data:`FILTERS`.

    Same frame as :func:`glossrig.core.extraction.cylinder.sample_angles` (thesis 4.3.5,
    corrected in :mod:`glossrig.core.models.angles`): tangent ``axis x n``,
    bitangent ``n x t``, azimuth ``atan2(<v, b>, <v, t>)`` in [0, 360).
    Only the four angles the coverage needs are computed. With
    ``incident_from_axis`` the incident vector starts at the pixel's axis point
    as thesis eq. 4.57-4.59 print it (the axis passes through the origin).
    ``half`` adds the half vector's ``theta_h``, ``phi_h`` (degrees, rotation 0)
    and the lamp distance ``dist_in`` (mm) for the Ward model."""
    lamp = np.asarray(lamp_position, float)
    P, n = geom.points, geom.normals
    start = np.outer(np.einsum("ij,j->i", P, geom.axis), geom.axis) if incident_from_axis else P
    wi = normalize(lamp[None, :] - start)
    wo = normalize(geom.camera_centre[None, :] - P)
    t = normalize(np.cross(np.broadcast_to(geom.axis, n.shape), n))
    b = np.cross(n, t)
    out = {}
    for name, w in (("in", wi), ("out", wo)):
        c = np.einsum("ij,ij->i", w, n)
        out[f"cos_{name}"] = c
        out[f"theta_{name}"] = np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))
        out[f"phi_{name}"] = np.mod(np.degrees(np.arctan2(np.einsum("ij,ij->i", w, b),
                                                          np.einsum("ij,ij->i", w, t))), 360.0)
    # Thesis 7.1.3: theta_in + theta_out equals the lamp-camera angle while the
    # normal lies between the two directions in the cross-section; the sign of
    # axis . (a x b) orders directions about the axis.
    if half:
        h = normalize(wi + wo)
        out["theta_h"] = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", h, n), -1.0, 1.0)))
        out["phi_h"] = np.mod(np.degrees(np.arctan2(np.einsum("ij,ij->i", h, b), np.einsum("ij,ij->i", h, t))), 360.0)
        out["dist_in"] = np.linalg.norm(lamp[None, :] - P, axis=-1)
    s1 = np.einsum("ij,j->i", np.cross(wo, n), geom.axis)
    s2 = np.einsum("ij,j->i", np.cross(n, wi), geom.axis)
    lit = (out["cos_in"] > 0) & (out["cos_out"] > 0)
    out["visible"] = out["cos_out"] > 0
    out["lit"] = lit
    out["between"] = lit & (s1 * s2 >= 0)
    return out


def rotate_azimuth(phi_deg: np.ndarray, rotation_deg: float) -> np.ndarray:
    """Azimuth after the sample rotation (thesis eq. 4.62): turning the tangent
    by r about the normal subtracts r from every azimuth."""
    return np.mod(np.asarray(phi_deg, float) - float(rotation_deg), 360.0)


def printed_azimuth(phi_deg: np.ndarray) -> np.ndarray:
    """Azimuth as thesis eq. 4.68-4.70 print it: arccos of the tangent against
    the normalised *negated* projection, never mirrored because the test of
    eq. 4.70 is always zero: ``180 - |phi|`` with phi signed, in [0, 180]."""
    signed = np.mod(np.asarray(phi_deg, float) + 180.0, 360.0) - 180.0
    return 180.0 - np.abs(signed)


def _floor_bins(x: np.ndarray, n: int) -> np.ndarray:
    return np.clip(np.floor(x).astype(np.int64), 0, n - 1)


def bin_codes(theta_in, theta_out, phi_in, phi_out) -> dict[str, np.ndarray]:
    """1-degree bin codes (int64, unique, unsorted) of samples given in degrees:
    ``aniso`` (theta_in, theta_out, phi_in, phi_out), ``iso_folded`` and
    ``iso_literal`` (theta_in, theta_out, |phi_in - phi_out|)."""
    import pandas as pd

    ti = _floor_bins(theta_in, _T)
    to = _floor_bins(theta_out, _TO)
    pi = _floor_bins(phi_in, _P)
    po = _floor_bins(phi_out, _P)
    tt = ti * _TO + to
    d = np.abs(np.asarray(phi_in, float) - np.asarray(phi_out, float))
    folded = _floor_bins(np.minimum(d, 360.0 - d), 180)
    literal = _floor_bins(d, 360)
    return {"aniso": pd.unique((tt * _P + pi) * _P + po),
            "iso_folded": pd.unique(tt * 360 + folded),
            "iso_literal": pd.unique(tt * 360 + literal)}


def shift_aniso(codes: np.ndarray, rotation_deg: int) -> np.ndarray:
    """Anisotropic bins of rotation 0 moved to a whole-degree sample rotation
    (both azimuth bins minus the rotation, modulo 360)."""
    ti, to, pi, po = decode_aniso(codes)
    r = int(rotation_deg)
    return ((ti * _TO + to) * _P + (pi - r) % _P) * _P + (po - r) % _P


def decode_aniso(codes: np.ndarray):
    codes = np.asarray(codes, np.int64)
    po = codes % _P
    pi = (codes // _P) % _P
    tt = codes // (_P * _P)
    return tt // _TO, tt % _TO, pi, po


def decode_iso(codes: np.ndarray):
    codes = np.asarray(codes, np.int64)
    tt = codes // 360
    return tt // _TO, tt % _TO, codes % 360


# ----------------------------------------------------------------------------
# Collected bins of a rig and the conventions
# ----------------------------------------------------------------------------

@dataclass
class CoverageData:
    """Occupied bins per (filter, LED, rotation), with the per-LED theta histograms
    (fig. 7.2), for one rig at one pixel scale, camera distance and geometry."""

    rig_name: str
    scale: float
    camera_distance: float
    geometry: str
    led_ids: list[int]
    led_angles: dict[int, float]
    rotations: list[float]
    filters: tuple[str, ...]
    n_pixels: int
    aniso: dict = field(default_factory=dict)       # (filter, led, rot) -> codes
    iso: dict = field(default_factory=dict)         # (filter, led, dphi) -> codes (rotation-free)
    theta_hist: dict = field(default_factory=dict)  # (filter, led) -> (180, 90) int64 counts
    n_samples: dict = field(default_factory=dict)   # (filter, led) -> samples per rotation


def collect(rig, led_ids: Sequence[int] | None = None, rotations: Sequence[float] | None = None,
            scale: float = 1.0, camera_distance: float | None = None, filters: Iterable[str] = FILTERS,
            geometry: str = "corrected", pixels: PixelGeometry | None = None,
            progress: Callable[[str], None] | None = None) -> CoverageData:
    """Bin the nominal samples of ``rig`` (no rendering) for every LED, rotation and filter.

    ``led_ids`` defaults to all LEDs, ``rotations`` to the rig's sample
    rotations; ``pixels`` reuses a :func:`pixel_geometry` (then ``scale`` and
    ``camera_distance`` are its own)."""
    filters = tuple(filters)
    bad = [f for f in filters if f not in FILTERS]
    if bad or not filters:
        raise InputError(f"coverage filters must be among {', '.join(FILTERS)}, got {list(filters)}")
    if geometry not in GEOMETRIES:
        raise InputError(f"coverage geometry must be one of {', '.join(GEOMETRIES)}, got {geometry!r}")
    led_ids = list(rig.led_ids() if led_ids is None else led_ids)
    if not led_ids:
        raise InputError("coverage needs at least one LED")
    for i in led_ids:
        rig.led(i)
    rotations = [float(r) for r in (rig.sample_rotations if rotations is None else rotations)]
    if not rotations or any(not math.isfinite(r) for r in rotations) or len(set(rotations)) != len(rotations):
        raise InputError(f"sample rotations must be distinct finite numbers, got {rotations}")
    geom = pixels if pixels is not None else pixel_geometry(rig, scale, camera_distance)
    printed = geometry == "printed"
    data = CoverageData(rig_name=rig.name, scale=geom.scale, camera_distance=geom.camera_distance,
                        geometry=geometry, led_ids=led_ids, led_angles={i: rig.led(i).angle_deg for i in led_ids},
                        rotations=rotations, filters=filters, n_pixels=len(geom))
    for k, led_id in enumerate(led_ids):
        if progress:
            progress(f"LED {led_id} ({k + 1}/{len(led_ids)})")
        a = direction_angles(geom, rig.led(led_id).position, incident_from_axis=printed)
        for f in filters:
            m = a[f]
            ti, to, pi, po = a["theta_in"][m], a["theta_out"][m], a["phi_in"][m], a["phi_out"][m]
            data.n_samples[(f, led_id)] = int(m.sum())
            hist = np.bincount(_floor_bins(ti, _T) * _TO + _floor_bins(to, _TO), minlength=_T * _TO)
            data.theta_hist[(f, led_id)] = hist.reshape(_T, _TO)
            c0 = None
            for rot in rotations:
                if not printed and float(rot).is_integer() and c0 is not None:
                    # floor(phi - r) = floor(phi) - r for whole degrees: shift the bins of rotation 0
                    data.aniso[(f, led_id, rot)] = shift_aniso(c0, int(rot))
                    continue
                ri, ro = rotate_azimuth(pi, rot), rotate_azimuth(po, rot)
                if printed:
                    ri, ro = printed_azimuth(ri), printed_azimuth(ro)
                c = bin_codes(ti, to, ri, ro)
                data.aniso[(f, led_id, rot)] = c["aniso"]
                if not printed and rot == 0.0:
                    c0 = c["aniso"]
                if (f, led_id, "folded") not in data.iso:   # |phi_in - phi_out| does not depend on the rotation
                    data.iso[(f, led_id, "folded")] = c["iso_folded"]
                    data.iso[(f, led_id, "literal")] = c["iso_literal"]
                if not printed and c0 is None:
                    c0 = bin_codes(ti, to, pi, po)["aniso"]
    return data


@dataclass(frozen=True)
class Convention:
    """How samples become occupied bins and what the whole space is (module docstring)."""

    filter: str = "lit"
    dphi: str = "folded"
    reciprocity: bool = False
    pi_fold: bool = False
    phi_bins: int = 360

    def __post_init__(self):
        if self.filter not in FILTERS:
            raise InputError(f"coverage filter must be one of {', '.join(FILTERS)}, got {self.filter!r}")
        if self.dphi not in DPHI_MODES:
            raise InputError(f"dphi must be one of {', '.join(DPHI_MODES)}, got {self.dphi!r}")
        if self.reciprocity and self.filter == "visible":
            raise InputError("reciprocity folding needs both directions above the surface (filter 'lit' or 'between')")
        if self.phi_bins not in (180, 360):
            raise InputError(f"phi_bins must be 360 or 180, got {self.phi_bins!r}")
        if self.phi_bins == 180 and (self.pi_fold or self.dphi == "literal"):
            raise InputError("phi_bins=180 (printed azimuths in [0, 180]) goes with dphi 'folded' and no half-turn fold")

    @property
    def theta_in_bins(self) -> int:
        return _T if self.filter == "visible" else 90

    def iso_total(self) -> int:
        """Bins (or classes of bins) of the isotropic space (Burnside's count under the swap)."""
        d = 180 if self.dphi == "folded" else 360
        total = self.theta_in_bins * _TO * d
        if self.reciprocity:
            total = (total + 90 * d) // 2              # fixed points: theta_in = theta_out
        return total

    def aniso_total(self) -> int:
        """Bins (or orbits of bins) of the anisotropic space (:func:`aniso_orbits`)."""
        return aniso_orbits(self.theta_in_bins, _TO, self.phi_bins, self.reciprocity, self.pi_fold)

    def label(self) -> str:
        parts = [self.filter, f"dphi {self.dphi}"]
        if self.reciprocity:
            parts.append("reciprocity")
        if self.pi_fold:
            parts.append("half-turn")
        if self.phi_bins != 360:
            parts.append(f"{self.phi_bins} phi bins")
        return ", ".join(parts)

    def check(self, geometry: str) -> None:
        """Refuse the combinations that do not fit the collected geometry."""
        if geometry == "printed" and (self.pi_fold or self.dphi == "literal"):
            raise InputError("printed azimuths lie in [0, 180]: use dphi 'folded' and no half-turn fold")
        if geometry != "printed" and self.phi_bins != 360:
            raise InputError("phi_bins=180 only describes the printed geometry's azimuths")


def aniso_orbits(n_theta_in: int, n_theta_out: int, n_phi: int, reciprocity: bool, pi_fold: bool) -> int:
    """Number of classes of (theta_in, theta_out, phi_in, phi_out) bins under the
    active folds, by Burnside's lemma (mean number of bins each group element
    fixes). Half-turn: fixes none. Swap (needs n_theta_in = n_theta_out):
    theta_in = theta_out and phi_in = phi_out, n_theta * n_phi bins. Swap after
    half-turn: theta_in = theta_out and phi_out = phi_in + 180, as many."""
    full = n_theta_in * n_theta_out * n_phi * n_phi
    if reciprocity and n_theta_in != n_theta_out:
        raise InputError("reciprocity folding needs equal theta_in and theta_out ranges")
    M = n_theta_out * n_phi
    if reciprocity and pi_fold:
        return (full + M + 0 + M) // 4
    if reciprocity:
        return (full + M) // 2
    if pi_fold:
        return full // 2
    return full


def canonical_aniso(codes: np.ndarray, reciprocity: bool, pi_fold: bool) -> np.ndarray:
    """Smallest code of each bin's orbit under the active folds (unique)."""
    import pandas as pd

    ti, to, pi, po = decode_aniso(codes)
    variants = [(ti, to, pi, po)]
    if pi_fold:
        variants.append((ti, to, (pi + 180) % _P, (po + 180) % _P))
    if reciprocity:
        variants += [(b, a, q, p) for (a, b, p, q) in variants]
    best = None
    for a, b, p, q in variants:
        c = ((a * _TO + b) * _P + p) * _P + q
        best = c if best is None else np.minimum(best, c)
    return pd.unique(best)


def canonical_iso(codes: np.ndarray, reciprocity: bool) -> np.ndarray:
    import pandas as pd

    if not reciprocity:
        return codes
    ti, to, d = decode_iso(codes)
    return pd.unique(np.minimum(codes, (to * _TO + ti) * 360 + d))


def _union(arrays: list[np.ndarray]) -> np.ndarray:
    import pandas as pd

    if not arrays:
        return np.zeros(0, np.int64)
    return pd.unique(np.concatenate(arrays))


def coverage(data: CoverageData, convention: Convention = Convention(), leds: Sequence[int] | None = None,
             rotations: Sequence[float] | None = None) -> dict:
    """Isotropic and anisotropic coverage (fractions) of a subset of the collected
    LEDs and rotations under ``convention``."""
    f = convention.filter
    convention.check(data.geometry)
    if f not in data.filters:
        raise InputError(f"filter {f!r} was not collected (have {', '.join(data.filters)})")
    leds = list(data.led_ids if leds is None else leds)
    rotations = [float(r) for r in (data.rotations if rotations is None else rotations)]
    for i in leds:
        if i not in data.led_ids:
            raise InputError(f"LED {i} was not collected (have {data.led_ids})")
    for r in rotations:
        if r not in data.rotations:
            raise InputError(f"rotation {r:g} was not collected (have {data.rotations})")
    iso = canonical_iso(_union([data.iso[(f, i, convention.dphi)] for i in leds]), convention.reciprocity)
    an = _union([data.aniso[(f, i, r)] for i in leds for r in rotations])
    if convention.reciprocity or convention.pi_fold:
        an = canonical_aniso(an, convention.reciprocity, convention.pi_fold)
    it, at = convention.iso_total(), convention.aniso_total()
    return {"isotropic": len(iso) / it, "anisotropic": len(an) / at,
            "isotropic_bins": int(len(iso)), "anisotropic_bins": int(len(an)),
            "isotropic_total": int(it), "anisotropic_total": int(at)}


def per_led(data: CoverageData, convention: Convention = Convention(), rotations=None) -> dict[int, dict]:
    """Coverage of each LED alone (all given rotations)."""
    return {i: coverage(data, convention, leds=[i], rotations=rotations) for i in data.led_ids}


def per_rotation(data: CoverageData, convention: Convention = Convention(), leds=None) -> dict:
    """Anisotropic coverage of each rotation alone and cumulatively, in the order collected."""
    alone, cum = {}, {}
    for k, r in enumerate(data.rotations):
        alone[r] = coverage(data, convention, leds=leds, rotations=[r])["anisotropic"]
        cum[r] = coverage(data, convention, leds=leds, rotations=data.rotations[: k + 1])["anisotropic"]
    return {"alone": alone, "cumulative": cum}


# ----------------------------------------------------------------------------
# Plots a designer looks at
# ----------------------------------------------------------------------------

def plot_theta_coverage(data: CoverageData, path, filter: str = "lit", leds=None, title: str | None = None) -> None:
    """theta_in against theta_out of every measured pixel, one colour per LED
    (thesis fig. 7.2). Occupied 1-degree bins are drawn as squares."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    leds = list(data.led_ids if leds is None else leds)
    fig, ax = plt.subplots(figsize=(6.4, 6.0))
    cmap = plt.get_cmap("tab20" if len(leds) > 10 else "tab10")
    for k, i in enumerate(leds):
        h = data.theta_hist[(filter, i)][:90]
        ti, to = np.nonzero(h)
        ax.scatter(ti + 0.5, to + 0.5, s=2.0, marker="s", color=cmap(k % cmap.N), linewidths=0,
                   label=f"LED {i} ({data.led_angles[i]:+.0f} deg)")
    ax.set_xlim(0, 90)
    ax.set_ylim(0, 90)
    ax.set_aspect("equal")
    ax.set_xlabel("theta_in (deg)")
    ax.set_ylabel("theta_out (deg)")
    ax.set_title(title or f"{data.rig_name}: occupied theta bins per LED ({filter} pixels, scale {data.scale:g})")
    ax.legend(fontsize=6, markerscale=4, loc="upper right", ncol=2 if len(leds) > 8 else 1)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_rotation_coverage(series: dict[str, tuple[CoverageData, Convention, list | None]], path,
                           title: str = "Anisotropic coverage by sample rotation") -> None:
    """Bars: anisotropic coverage of each rotation alone; line: cumulative
    coverage as the rotations are added; one group per design."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(series), figsize=(5.2 * len(series), 4.0), squeeze=False)
    for ax, (name, (data, conv, leds)) in zip(axes[0], series.items()):
        pr = per_rotation(data, conv, leds)
        rots = data.rotations
        x = np.arange(len(rots))
        ax.bar(x, [100 * pr["alone"][r] for r in rots], color="0.6", label="rotation alone")
        ax.plot(x, [100 * pr["cumulative"][r] for r in rots], "o-", color="C3", label="cumulative")
        ax.set_xticks(x, [f"{r:+g}" for r in rots])
        ax.set_xlabel("sample rotation (deg)")
        ax.set_ylabel("anisotropic coverage (%)")
        ax.set_title(f"{name} ({conv.label()})", fontsize=9)
        ax.legend(fontsize=8)
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


def plot_per_led(rows: dict[str, dict[int, dict]], angles: dict[str, dict[int, float]], path) -> None:
    """Isotropic and anisotropic coverage of each LED alone, per design."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=False)
    width = 0.8 / max(1, len(rows))
    for k, (name, per) in enumerate(rows.items()):
        ids = list(per)
        x = np.arange(len(ids)) + k * width
        for ax, key in zip(axes, ("isotropic", "anisotropic")):
            ax.bar(x, [100 * per[i][key] for i in ids], width=width, label=name)
            ax.set_ylabel(f"{key} (%)")
    axes[0].legend(fontsize=8)
    axes[1].set_xlabel("LED index within the design")
    axes[0].set_title("Coverage of each LED alone (all sample rotations)")
    fig.tight_layout()
    fig.savefig(path, dpi=130)
    plt.close(fig)


# ----------------------------------------------------------------------------
# The table of conventions (validation/design/coverage.md)
# ----------------------------------------------------------------------------

def conventions_for(geometry: str) -> list[Convention]:
    """Every valid combination of filter, dphi, reciprocity, half-turn and phi bins."""
    out = []
    for f in FILTERS:
        for rec in (False, True):
            if rec and f == "visible":
                continue
            if geometry == "printed":
                for pb in (360, 180):
                    out.append(Convention(f, "folded", rec, False, pb))
            else:
                for dphi in DPHI_MODES:
                    for pf in (False, True):
                        out.append(Convention(f, dphi, rec, pf))
    return out


def convention_rows(data: CoverageData, led_sets: dict[str, list[int]],
                    rotation_sets: dict[str, list[float]]) -> list[dict]:
    """One row per (LED set, rotation set, convention) with both coverages (%)."""
    rows = []
    for ln, leds in led_sets.items():
        for rn, rots in rotation_sets.items():
            for conv in conventions_for(data.geometry):
                if conv.filter not in data.filters:
                    continue
                c = coverage(data, conv, leds, rots)
                rows.append({
                    "geometry": data.geometry, "camera_mm": data.camera_distance, "scale": data.scale,
                    "leds": ln, "rotations": rn, "filter": conv.filter, "dphi": conv.dphi,
                    "reciprocity": conv.reciprocity, "half_turn": conv.pi_fold, "phi_bins": conv.phi_bins,
                    "iso_pct": 100 * c["isotropic"], "aniso_pct": 100 * c["anisotropic"],
                    "iso_bins": c["isotropic_bins"], "aniso_bins": c["anisotropic_bins"],
                    "iso_total": c["isotropic_total"], "aniso_total": c["anisotropic_total"]})
    return rows


def match_score(iso_pct: float, aniso_pct: float) -> float:
    """Distance of a pair of coverages from the printed 0.98 % and 0.1 % (thesis
    7.1.3): the larger of the two absolute log10 ratios (0 = both reproduced;
    0.1 = the worse one off by 26 %)."""
    return max(abs(math.log10(iso_pct / (100 * PRINTED["isotropic"]))),
               abs(math.log10(aniso_pct / (100 * PRINTED["anisotropic"]))))
