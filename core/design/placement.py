"""Geometry-based rig design: where to mount the LEDs, how many to use, and at
which rotations to wrap the sample (thesis 9.1, after the coverage of 7.1.3).

Thesis 9.1 proposes optimising the light positions "regarding the fitting of
anisotropic materials" (after Havran et al.'s coverage optimisation). Here a
design is scored by two things computed from the rig's geometry alone (no
rendering):

* its anisotropic BRDF-space coverage (:mod:`glossrig.core.design.coverage`, thesis
  7.1.3, ``lit`` samples, 1-degree bins of (theta_in, theta_out, phi_in,
  phi_out) over 90 x 90 x 360 x 360);
* the expected error of the extended-Ward parameters of target materials
  (:mod:`glossrig.core.design.fisher`): for each material the geometric mean of the
  relative standard errors from the Fisher information.

    score = ln(C / C_ref) + w_iso ln(C_iso / C_iso,ref) - lambda * mean_m ln(E_m / E_m,ref)

with the thesis rig (all its LEDs, its rotations) as the reference, so the
thesis scores 0 and a design with twice the coverage and the same errors
scores ln 2. C_iso is the isotropic coverage (theta_in, theta_out,
|phi_in - phi_out| folded, lit samples): both metrics of thesis 7.1.3 count,
and without it the anisotropic metric alone favours LEDs close to the camera
(many samples near the pole theta = 0, where 1-degree azimuth bins are small)
and gives up the large lamp-camera angles.

Search. Every LED's contribution to both terms is additive: the coverage is a
union of per-LED bin sets (a sample rotation r shifts both azimuth bins by -r,
thesis eq. 4.62, exactly for integer r) and the Fisher information is a sum
over LEDs and rotations. So the design space is first swept once: every
candidate mount (angle, height, distance on a grid within the mounting limits)
is evaluated alone for every candidate rotation and material, in parallel on
Dask (:class:`DaskRunner`) or in one process (:class:`LocalRunner`), with the
same numbers either way. The LEDs are then chosen by greedy maximum-coverage
selection (Nemhauser, Wolsey & Fisher 1978: a (1 - 1/e) guarantee for the
coverage term) followed by exchange passes, alternating with greedy selection
and exchange of the sample rotations, until nothing improves. The selection is
deterministic (ties go to the lower candidate index).

Mounting limits (:class:`MountingLimits`). The thesis rig stands on an
80 x 60 cm board (thesis 4.1.5). Its placement relative to the cylinder is not
stated; we take the 80 cm side along the camera axis from 150 mm behind the
cylinder axis to 650 mm in front (the camera at 500 mm plus its body) and the
60 cm side centred on the axis. A new LED holder is assumed: a printed
vertical post with a slot in which LED carriages clamp at any height from -40
to +120 mm (the thesis's holder has three fixed holes 13.5 mm apart, 4.1.3),
several carriages per post at least 12 mm apart. An LED is refused if its post
or carriage lies in the camera's view (the full image plus a 2 % margin; then it
neither blocks the camera's line of sight to the sample nor is seen by it), if
the light path from it to any point of the sample passes through the cylinder
holder or another LED's post, or if its post leaves the board.
"""
from __future__ import annotations

import math
import re
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from collections.abc import Callable, Sequence

import numpy as np

from glossrig.core.atomic import atomic_write
from glossrig.core.design import coverage as cov
from glossrig.core.design import fisher as fi
from glossrig.core.errors import InputError
from glossrig.core.rig import Led
from glossrig.core.models.ward import WardParams, ward_envelope, ward_geometry

ANISO_TOTAL = 90 * 90 * 360 * 360          # lit samples, no folding (coverage.Convention())
ISO_TOTAL = 90 * 90 * 180


# ----------------------------------------------------------------------------
# Mounting limits and feasibility
# ----------------------------------------------------------------------------

@dataclass(frozen=True)
class MountingLimits:
    """Where an LED may go (module docstring). Millimetres, holder frame."""

    distance_mm: tuple[float, float] = (150.0, 350.0)
    height_mm: tuple[float, float] = (-40.0, 120.0)
    board_x_mm: tuple[float, float] = (-300.0, 300.0)
    board_z_mm: tuple[float, float] = (-150.0, 650.0)
    board_margin_mm: float = 20.0
    post_radius_mm: float = 8.0
    post_clearance_mm: float = 30.0
    same_post_tol_mm: float = 1.0
    min_vertical_spacing_mm: float = 12.0
    camera_margin: float = 0.02
    max_leds: int = 16

    def __post_init__(self):
        for name in ("distance_mm", "height_mm", "board_x_mm", "board_z_mm"):
            lo, hi = getattr(self, name)
            if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
                raise InputError(f"mounting limit {name} must be an increasing pair, got {(lo, hi)}")
        if self.distance_mm[0] <= 0:
            raise InputError("mounting limit distance_mm must be positive")
        if not (1 <= self.max_leds <= 64):
            raise InputError(f"max_leds must lie in [1, 64], got {self.max_leds}")

    def to_json(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}


def board_height(rig) -> float:
    """y of the board's top face: the bottom of the cylinder holder box (rig file ``[holder]``)."""
    return rig.holder.top - rig.holder.height


def mount_position(angle_deg: float, height_mm: float, distance_mm: float) -> np.ndarray:
    """Holder-frame position of an LED ``distance_mm`` from the axis at ``angle_deg``
    from the camera direction about the axis (thesis 4.1.3), at ``height_mm``."""
    a = math.radians(angle_deg)
    return np.array([distance_mm * math.sin(a), float(height_mm), distance_mm * math.cos(a)])


def mount_of(position) -> tuple[float, float, float]:
    """(angle_deg, height_mm, distance_mm) of a holder-frame position."""
    x, y, z = (float(v) for v in position)
    return math.degrees(math.atan2(x, z)), y, math.hypot(x, z)


def shadow_points(rig, n_around: int = 13, n_up: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Points (and normals) on the front half of the sample for the shadow checks."""
    r, h = rig.cylinder_radius, rig.sample_height
    az = np.radians(np.linspace(-85, 85, n_around))
    ys = np.linspace(-h / 2, h / 2, n_up)
    A, Y = np.meshgrid(az, ys, indexing="ij")
    n = np.stack([np.sin(A), np.zeros_like(A), np.cos(A)], -1).reshape(-1, 3)
    p = n * r
    p[:, 1] = Y.ravel()
    return p, n


def _holder_box(rig) -> tuple[np.ndarray, np.ndarray]:
    h = rig.holder
    w, d, top, hh = h.width, h.depth, h.top, h.height
    return np.array([-w / 2, top - hh, -d / 2]), np.array([w / 2, top, d / 2])


def _segments_hit_box(a: np.ndarray, b: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Slab test: does the segment a -> b (rows) pass through the box [lo, hi]?"""
    d = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - a) / d
        t2 = (hi - a) / d
    near, far = np.minimum(t1, t2), np.maximum(t1, t2)
    inside = (a >= lo) & (a <= hi)
    near = np.where(d == 0, np.where(inside, -np.inf, np.inf), near)     # parallel to the slab
    far = np.where(d == 0, np.where(inside, np.inf, -np.inf), far)
    tmin = np.max(near, axis=-1)
    tmax = np.min(far, axis=-1)
    return (tmax >= np.maximum(tmin, 0.0)) & (tmin <= 1.0)


def camera_sees(rig, positions, limits: MountingLimits = MountingLimits()) -> np.ndarray:
    """Whether the camera sees any part of each LED's post and carriage (a
    vertical cylinder of ``post_radius_mm`` from the board to the LED plus the
    radius): projected through the nominal pinhole, tested against the image
    rectangle grown by ``camera_margin`` of its width."""
    P = np.atleast_2d(np.asarray(positions, float))
    cam = rig.camera
    R, t = cam.pose()
    K = cam.matrix(1.0)
    w, h = cam.image_px
    m = limits.camera_margin * w
    yb = board_height(rig)
    seen = np.zeros(len(P), bool)
    for k, p in enumerate(P):
        top = p[1] + limits.post_radius_mm
        ys = np.linspace(min(yb, top), top, max(2, int((top - yb) / 5) + 2))
        pts = np.repeat(p[None, :], len(ys), 0)
        pts[:, 1] = ys
        xc = pts @ R.T + t
        front = xc[:, 2] > 1e-6
        if not np.any(front):
            continue
        xc = xc[front]
        u = K[0, 0] * xc[:, 0] / xc[:, 2] + K[0, 2]
        v = K[1, 1] * xc[:, 1] / xc[:, 2] + K[1, 2]
        rad = K[0, 0] * limits.post_radius_mm / xc[:, 2]
        inside = (u + rad >= -m) & (u - rad <= w + m) & (v + rad >= -m) & (v - rad <= h + m)
        seen[k] = bool(np.any(inside))
    return seen


def led_problems(rig, position, limits: MountingLimits = MountingLimits()) -> list[str]:
    """What is wrong with one LED mount on its own (empty list: nothing)."""
    p = np.asarray(position, float)
    angle, height, dist = mount_of(p)
    out = []
    lo, hi = limits.distance_mm
    if not (lo - 1e-9 <= dist <= hi + 1e-9):
        out.append(f"distance {dist:.1f} mm outside [{lo:g}, {hi:g}]")
    lo, hi = limits.height_mm
    if not (lo - 1e-9 <= height <= hi + 1e-9):
        out.append(f"height {height:.1f} mm outside [{lo:g}, {hi:g}]")
    m = limits.board_margin_mm
    if not (limits.board_x_mm[0] + m <= p[0] <= limits.board_x_mm[1] - m
            and limits.board_z_mm[0] + m <= p[2] <= limits.board_z_mm[1] - m):
        out.append(f"post at x={p[0]:.0f}, z={p[2]:.0f} mm is off the board (margin {m:g} mm)")
    if camera_sees(rig, p[None, :], limits)[0]:
        out.append("in the camera's view (would block or appear in the image)")
    sp, sn = shadow_points(rig)
    lit = np.einsum("ij,ij->i", p[None, :] - sp, sn) > 0
    if np.any(lit):
        lo_b, hi_b = _holder_box(rig)
        if np.any(_segments_hit_box(sp[lit], np.repeat(p[None, :], lit.sum(), 0), lo_b, hi_b)):
            out.append("the cylinder holder shadows part of the sample")
    return out


def conflicts(rig, positions, limits: MountingLimits = MountingLimits()) -> np.ndarray:
    """Symmetric (n, n) matrix: LEDs i and j cannot both be mounted, because
    their posts collide (distinct posts closer than ``post_clearance_mm``, or
    carriages on one post closer than ``min_vertical_spacing_mm``) or one's post
    lies in the light path from the other to a point of the sample."""
    P = np.atleast_2d(np.asarray(positions, float))
    n = len(P)
    xz = P[:, [0, 2]]
    dxz = np.linalg.norm(xz[:, None, :] - xz[None, :, :], axis=-1)
    dy = np.abs(P[:, None, 1] - P[None, :, 1])
    same = dxz <= limits.same_post_tol_mm
    bad = (~same & (dxz < limits.post_clearance_mm)) | (same & (dy < limits.min_vertical_spacing_mm))
    sp, sn = shadow_points(rig)
    yb = board_height(rig)
    r = limits.post_radius_mm
    for i in range(n):
        lit = np.einsum("ij,ij->i", P[i][None, :] - sp, sn) > 0
        if not np.any(lit):
            continue
        a = P[i][None, :]                       # LED
        b = sp[lit]                             # sample points
        d = b - a                               # (k, 3)
        dxz_seg = d[:, [0, 2]]
        L2 = np.einsum("ij,ij->i", dxz_seg, dxz_seg)
        # closest approach (in x-z) of each segment to each other post axis
        rel = xz[:, None, :] - a[None, :, [0, 2]]         # (n, 1, 2)
        s = np.clip(np.einsum("nkj,kj->nk", np.broadcast_to(rel, (n, len(b), 2)), dxz_seg) / L2[None, :], 0, 1)
        closest = a[None, :, [0, 2]] + s[..., None] * dxz_seg[None, :, :]
        dist = np.linalg.norm(closest - xz[:, None, :], axis=-1)
        y_at = a[0, 1] + s * d[None, :, 1]
        top = P[:, 1] + r
        hit = (dist < r) & (y_at <= top[:, None]) & (y_at >= yb) & (s > 0) & (s < 1)
        blocked = np.any(hit, axis=1)
        blocked[i] = False
        blocked &= ~same[i]                     # carriages on one post are side by side
        bad[i] |= blocked
        bad[:, i] |= blocked
    np.fill_diagonal(bad, False)
    return bad


def design_problems(rig, positions, limits: MountingLimits = MountingLimits()) -> list[str]:
    """Every problem of a whole design (each LED alone, then pairs)."""
    P = np.atleast_2d(np.asarray(positions, float))
    out = []
    if len(P) > limits.max_leds:
        out.append(f"{len(P)} LEDs, the relay board switches at most {limits.max_leds}")
    for k, p in enumerate(P):
        out += [f"LED {k + 1}: {msg}" for msg in led_problems(rig, p, limits)]
    c = conflicts(rig, P, limits)
    for i, j in zip(*np.nonzero(np.triu(c))):
        out.append(f"LEDs {i + 1} and {j + 1}: posts collide or one shadows the other")
    return out


# ----------------------------------------------------------------------------
# Per-LED evaluation (the sweep)
# ----------------------------------------------------------------------------

@dataclass
class EvalSetup:
    """Everything a worker needs to evaluate LED mounts; shipped once per worker."""

    rig: object
    cov_pixels: cov.PixelGeometry
    fisher_pixels: cov.PixelGeometry
    materials: list[tuple[str, WardParams]]
    rotations: tuple[int, ...]
    noise: fi.RelativeNoise | fi.HdrNoise
    weighting: str = "fisher"
    fisher_rows: int = 6000
    diffuse_rows: int = 1500


@dataclass
class LedEval:
    """One LED mount alone: occupied bins at rotation 0 and Fisher information
    per (candidate rotation, material)."""

    position: tuple[float, ...]  # (x, y, z) mm
    base: np.ndarray      # int64 theta part of the anisotropic code (rotation-free)
    pi: np.ndarray        # int16 phi_in bin at rotation 0
    po: np.ndarray        # int16 phi_out bin at rotation 0
    iso: np.ndarray       # int64 isotropic (folded) codes
    info: np.ndarray      # (n_rot, n_mat, 5, 5)
    n_lit: int

    def aniso_codes(self, rotations: Sequence[int]) -> np.ndarray:
        """Sorted unique anisotropic codes over the given integer rotations."""
        pi = self.pi.astype(np.int64)
        po = self.po.astype(np.int64)
        parts = [self.base + ((pi - int(r)) % 360) * 360 + (po - int(r)) % 360 for r in rotations]
        return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def _rows_for(a: dict, lit: np.ndarray, p: WardParams, n_spec: int, n_diff: int):
    """Rows of the Fisher sum and the number of pixels each stands for: all
    pixels where the lobe (widest axis, any rotation) is above 1e-3 of the
    diffuse level, thinned evenly to ``n_spec``; the rest thinned to ``n_diff``."""
    idx = np.flatnonzero(lit)
    env = ward_envelope(ward_geometry(np.radians(a["theta_in"][idx]), np.radians(a["theta_out"][idx]),
                                      np.radians(a["theta_h"][idx]), 0.0), p)
    level = p.rho_d / np.pi if p.rho_d > 0 else 1e-6 * max(float(env.max(initial=0.0)), 1e-300)
    spec = env > 1e-3 * level
    rows, weights = [], []
    for sel, cap in ((idx[spec], n_spec), (idx[~spec], n_diff)):
        if sel.size == 0:
            continue
        if sel.size > cap:
            take = sel[np.unique(np.linspace(0, sel.size - 1, cap).round().astype(np.int64))]
        else:
            take = sel
        rows.append(take)
        weights.append(np.full(take.size, sel.size / take.size))
    if not rows:
        return np.zeros(0, np.int64), np.zeros(0)
    return np.concatenate(rows), np.concatenate(weights)


def evaluate_led(setup: EvalSetup, position) -> LedEval:
    """Coverage bins and Fisher information of one LED mount (no rendering)."""
    pos = np.asarray(position, float)
    same = setup.fisher_pixels is setup.cov_pixels
    a = cov.direction_angles(setup.cov_pixels, pos, half=same)
    m = a["lit"]
    ti = cov._floor_bins(a["theta_in"][m], 90)
    to = cov._floor_bins(a["theta_out"][m], 90)
    pi = cov._floor_bins(a["phi_in"][m], 360)
    po = cov._floor_bins(a["phi_out"][m], 360)
    codes = np.unique(((ti * 90 + to) * 360 + pi) * 360 + po)
    base = (codes // (360 * 360)) * (360 * 360)
    c_pi = ((codes // 360) % 360).astype(np.int16)
    c_po = (codes % 360).astype(np.int16)
    d = np.abs(a["phi_in"][m] - a["phi_out"][m])
    iso = np.unique((ti * 90 + to) * 360 + cov._floor_bins(np.minimum(d, 360 - d), 180))   # as coverage.bin_codes
    fa = a if same else cov.direction_angles(setup.fisher_pixels, pos, half=True)
    flit = fa["lit"]
    info = np.zeros((len(setup.rotations), len(setup.materials), 5, 5))
    for j, (_, p) in enumerate(setup.materials):
        rows, w = _rows_for(fa, flit, p, setup.fisher_rows, setup.diffuse_rows)
        if rows.size == 0:
            continue
        ti_r = np.radians(fa["theta_in"][rows])
        to_r = np.radians(fa["theta_out"][rows])
        th_r = np.radians(fa["theta_h"][rows])
        ph0 = fa["phi_h"][rows]
        cos_in = fa["cos_in"][rows]
        dist = fa["dist_in"][rows]
        for k, r in enumerate(setup.rotations):
            f, J = fi.ward_jacobian(ti_r, to_r, th_r, np.radians(np.mod(ph0 - r, 360.0)), p)
            sigma = setup.noise.sigma(f, cos_in, dist)
            if setup.weighting == "fisher":
                info[k, j] = fi.information(J, sigma, w)
            else:
                raise InputError(f"design sweeps use weighting 'fisher', got {setup.weighting!r}")
    return LedEval(position=tuple(float(v) for v in pos), base=base, pi=c_pi, po=c_po, iso=iso, info=info,
                   n_lit=int(m.sum()))


def evaluate_chunk(setup: EvalSetup, positions) -> list[LedEval]:
    return [evaluate_led(setup, p) for p in positions]


# ----------------------------------------------------------------------------
# Candidates and the selection
# ----------------------------------------------------------------------------

@dataclass(frozen=True)
class SearchSpace:
    """The grid of candidate mounts and rotations swept."""

    angle_step_deg: float = 10.0
    heights_mm: tuple[float, ...] = (-40.0, -20.0, 0.0, 20.0, 40.0, 80.0, 120.0)
    distances_mm: tuple[float, ...] = (150.0, 250.0, 350.0)
    rotations_deg: tuple[int, ...] = tuple(range(-180, 180, 15))

    def __post_init__(self):
        if not (0 < self.angle_step_deg <= 90):
            raise InputError(f"angle step must lie in (0, 90] degrees, got {self.angle_step_deg}")
        if not self.heights_mm or not self.distances_mm or not self.rotations_deg:
            raise InputError("the search space needs heights, distances and rotations")
        if any(float(r) != int(r) for r in self.rotations_deg) or len(set(self.rotations_deg)) != len(self.rotations_deg):
            raise InputError("candidate rotations must be distinct whole degrees (bins shift exactly)")

    def mounts(self) -> list[tuple[float, float, float]]:
        n = int(round(360 / self.angle_step_deg))
        angles = [-180.0 + k * 360.0 / n for k in range(n)]
        return [(a, h, d) for d in self.distances_mm for h in self.heights_mm for a in angles]


@dataclass
class Pool:
    """Evaluated candidate LEDs, their pairwise conflicts and the score's references."""

    evals: list[LedEval]
    conflict: np.ndarray
    rotations: tuple[int, ...]
    materials: list[tuple[str, WardParams]]
    lam: float
    ref_coverage: float = 1.0
    ref_errors: np.ndarray | None = None
    priors: np.ndarray | None = None
    iso_weight: float = 0.0
    ref_iso: float = 1.0

    def __post_init__(self):
        self.priors = np.stack([fi.weak_prior(p) for _, p in self.materials])
        self.masks = [fi.identifiable(p) for _, p in self.materials]
        self.scales = np.stack([fi.error_scale(p) for _, p in self.materials])
        self._rot_index = {r: k for k, r in enumerate(self.rotations)}

    def rot_idx(self, rotations) -> list[int]:
        try:
            return [self._rot_index[int(r)] for r in rotations]
        except KeyError as e:
            raise InputError(f"rotation {e.args[0]} is not among the swept rotations") from None

    # --- the two terms
    def information(self, leds: Sequence[int], rotations: Sequence[int]) -> np.ndarray:
        ri = self.rot_idx(rotations)
        tot = np.zeros((len(self.materials), 5, 5))
        for i in leds:
            tot += self.evals[i].info[ri].sum(axis=0)
        return tot

    def errors_from_information(self, I: np.ndarray) -> np.ndarray:
        """(n_mat,) geometric-mean relative errors (weak prior added)."""
        assert self.priors is not None          # set in __post_init__
        out = np.empty(len(self.materials))
        for j in range(len(self.materials)):
            c = fi.covariance_from_information(I[j], self.masks[j], self.priors[j])
            rel = np.sqrt(np.diag(c)) / self.scales[j]
            out[j] = float(np.exp(np.mean(np.log(rel[self.masks[j]]))))
        return out

    def batch_errors(self, I_batch: np.ndarray) -> np.ndarray:
        """Geometric-mean relative errors for a batch of information matrices
        (n, n_mat, 5, 5) -> (n, n_mat), vectorised (prior added)."""
        assert self.priors is not None          # set in __post_init__
        n = I_batch.shape[0]
        out = np.empty((n, len(self.materials)))
        for j in range(len(self.materials)):
            m = self.masks[j]
            A = (I_batch[:, j] + self.priors[j])[:, m][:, :, m]
            d = np.sqrt(np.einsum("nii->ni", A))
            S = A / (d[:, :, None] * d[:, None, :])
            inv = np.linalg.inv(S) / (d[:, :, None] * d[:, None, :])
            var = np.einsum("nii->ni", inv)
            rel = np.sqrt(np.maximum(var, 1e-300)) / self.scales[j][m]
            out[:, j] = np.exp(np.mean(np.log(rel), axis=1))
        return out

    def coverage_bins(self, leds: Sequence[int], rotations: Sequence[int]) -> int:
        return int(len(self.union(leds, rotations)))

    def union(self, leds, rotations) -> np.ndarray:
        parts = [self.evals[i].aniso_codes(rotations) for i in leds]
        return np.unique(np.concatenate(parts)) if parts else np.zeros(0, np.int64)

    def iso_bins(self, leds: Sequence[int]) -> int:
        parts = [self.evals[i].iso for i in leds]
        return int(len(np.unique(np.concatenate(parts)))) if parts else 0

    def score_parts(self, cov_frac: float, errors: np.ndarray, iso_frac: float | None = None) -> float:
        e = np.mean(np.log(np.asarray(errors) / self.ref_errors))
        s = math.log(max(cov_frac, 1e-300) / self.ref_coverage) - self.lam * float(e)
        if self.iso_weight:
            assert iso_frac is not None, "score_parts needs iso_frac when iso_weight is set"
            s += self.iso_weight * math.log(max(iso_frac, 1e-300) / self.ref_iso)
        return s

    def score(self, leds, rotations) -> float:
        c = self.coverage_bins(leds, rotations) / ANISO_TOTAL
        iso = self.iso_bins(leds) / ISO_TOTAL if self.iso_weight else None
        return self.score_parts(c, self.errors_from_information(self.information(leds, rotations)), iso)


def _new_bins(codes: np.ndarray, covered: np.ndarray, owner: np.ndarray | None = None, n_sel: int = 0):
    """Bins of ``codes`` not in the sorted ``covered``; with ``owner`` (the
    selected LED that alone covers each covered bin, or -1) also, per selected
    LED, how many of ``codes`` only it covers (what removing it would free)."""
    if covered.size == 0:
        return codes.size, (np.zeros(n_sel, np.int64) if owner is not None else None)
    k = np.searchsorted(covered, codes)
    k = np.minimum(k, covered.size - 1)
    present = covered[k] == codes
    new = int(codes.size - present.sum())
    if owner is None:
        return new, None
    o = owner[k[present]]
    return new, np.bincount(o[o >= 0], minlength=n_sel)


def _state(pool: Pool, leds: list[int], rotations):
    """Sorted covered bins and the owner index (in ``leds``) of singly covered ones."""
    if not leds:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    arrs = [pool.evals[i].aniso_codes(rotations) for i in leds]
    allc = np.concatenate(arrs)
    who = np.concatenate([np.full(a.size, k) for k, a in enumerate(arrs)])
    order = np.argsort(allc, kind="stable")
    allc, who = allc[order], who[order]
    uniq, start, counts = np.unique(allc, return_index=True, return_counts=True)
    owner = np.where(counts == 1, who[start], -1)
    return uniq, owner


def select_leds(pool: Pool, n: int, rotations, start: list[int] | None = None, feasible: np.ndarray | None = None,
                log: Callable[[str], None] | None = None, max_passes: int = 3) -> tuple[list[int], list[float]]:
    """Greedy selection of ``n`` LEDs for the given rotations, then exchange
    passes (replace one selected LED by the best compatible candidate while
    the score improves). Returns the LEDs and the score after each greedy step."""
    say = log or (lambda m: None)
    N = len(pool.evals)
    feasible = np.ones(N, bool) if feasible is None else feasible
    ri = pool.rot_idx(rotations)
    cand_info = np.stack([ev.info[ri].sum(axis=0) for ev in pool.evals])   # (N, n_mat, 5, 5)
    cand_codes = [ev.aniso_codes(rotations) for ev in pool.evals]
    cand_iso = [np.sort(ev.iso) for ev in pool.evals]
    sel = list(start or [])
    trajectory = []

    def best_addition(sel_now: list[int], exclude: set[int]) -> tuple[int, float]:
        covered, _ = _state(pool, sel_now, rotations)
        iso_cov = (np.unique(np.concatenate([pool.evals[i].iso for i in sel_now])) if sel_now
                   else np.zeros(0, np.int64))
        ok = feasible.copy()
        for i in sel_now:
            ok &= ~pool.conflict[i]
            ok[i] = False
        for i in exclude:
            ok[i] = False
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return -1, -math.inf
        base_I = pool.information(sel_now, rotations)
        errs = pool.batch_errors(base_I[None] + cand_info[idx])
        gains = np.array([_new_bins(cand_codes[i], covered)[0] for i in idx])
        if pool.iso_weight:
            iso_g = [(iso_cov.size + _new_bins(cand_iso[i], iso_cov)[0]) / ISO_TOTAL for i in idx]
        else:
            iso_g = [None] * idx.size
        scores = np.array([pool.score_parts((covered.size + g) / ANISO_TOTAL, e, ig)
                           for g, e, ig in zip(gains, errs, iso_g)])
        k = int(np.argmax(scores))
        return int(idx[k]), float(scores[k])

    while len(sel) < n:
        i, s = best_addition(sel, set())
        if i < 0:
            raise InputError(f"only {len(sel)} compatible LED mounts fit the limits; asked for {n}")
        sel.append(i)
        trajectory.append(s)
        say(f"greedy: LED {len(sel)}/{n} at {_fmt_mount(pool.evals[i].position)}, score {s:+.4f}")
    current = pool.score(sel, rotations)
    for _npass in range(max_passes):
        improved = False
        for k in range(len(sel)):
            rest = sel[:k] + sel[k + 1:]
            i, s = best_addition(rest, {sel[k]})
            if i >= 0 and s > current + 1e-9:
                say(f"exchange: {_fmt_mount(pool.evals[sel[k]].position)} -> {_fmt_mount(pool.evals[i].position)}, "
                    f"score {current:+.4f} -> {s:+.4f}")
                sel[k] = i
                current = s
                improved = True
        if not improved:
            break
    return sel, trajectory


def select_rotations(pool: Pool, leds: list[int], k: int, start: Sequence[int] | None = None,
                     log: Callable[[str], None] | None = None, max_passes: int = 3) -> list[int]:
    """Greedy choice of ``k`` sample rotations among the swept ones for fixed
    LEDs (from ``start`` if given), then exchange passes."""
    say = log or (lambda m: None)
    cands = list(pool.rotations)
    codes = {r: np.unique(np.concatenate([pool.evals[i].aniso_codes([r]) for i in leds])) for r in cands}
    info = {r: pool.information(leds, [r]) for r in cands}

    iso = pool.iso_bins(leds) / ISO_TOTAL if pool.iso_weight else None    # no rotation changes it

    def sc(rots):
        c = len(np.unique(np.concatenate([codes[r] for r in rots]))) / ANISO_TOTAL
        return pool.score_parts(c, pool.errors_from_information(sum(info[r] for r in rots)), iso)

    sel = [int(r) for r in (start or [])][:k]
    while len(sel) < k:
        best = max((r for r in cands if r not in sel), key=lambda r: (sc(sel + [r]), -cands.index(r)))
        sel.append(best)
    current = sc(sel)
    for _ in range(max_passes):
        improved = False
        for j in range(len(sel)):
            for r in cands:
                if r in sel:
                    continue
                trial = sel[:j] + [r] + sel[j + 1:]
                s = sc(trial)
                if s > current + 1e-9:
                    say(f"rotations: {sel[j]:+d} -> {r:+d}, score {current:+.4f} -> {s:+.4f}")
                    sel, current, improved = trial, s, True
        if not improved:
            break
    return sorted(sel)


def greedy_order(pool: Pool, leds: list[int], rotations) -> list[dict]:
    """Order the chosen LEDs greedily (each next one adds the most score) and
    report score, coverage and errors of every prefix: what fewer LEDs would
    give, against the capture time each LED costs (thesis 4.2.3)."""
    rest = list(leds)
    chosen: list[int] = []
    rows = []
    while rest:
        best = max(rest, key=lambda i: (pool.score(chosen + [i], rotations), -i))
        chosen.append(best)
        rest.remove(best)
        errs = pool.errors_from_information(pool.information(chosen, rotations))
        rows.append({"n_leds": len(chosen), "mount": dict(zip(("angle_deg", "height_mm", "distance_mm"),
                                                                mount_of(pool.evals[best].position))),
                     "score": pool.score(chosen, rotations),
                     "anisotropic_coverage": pool.coverage_bins(chosen, rotations) / ANISO_TOTAL,
                     "isotropic_coverage": pool.iso_bins(chosen) / ISO_TOTAL,
                     "geometric_mean_relative_error": {lb: float(e) for (lb, _), e in zip(pool.materials, errs)}})
    return rows


def _fmt_mount(pos) -> str:
    a, h, d = mount_of(pos)
    return f"(angle {a:+.0f} deg, height {h:+.0f} mm, distance {d:.0f} mm)"


# ----------------------------------------------------------------------------
# The whole optimisation
# ----------------------------------------------------------------------------

@dataclass
class DesignResult:
    positions: np.ndarray
    rotations: list[int]
    score: float
    coverage: float
    iso_coverage: float
    errors: dict[str, float]
    reference: dict
    trajectory: list[float]
    prefixes: list[dict]
    runner: str
    n_candidates: int
    n_feasible: int
    timings: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        return {"mounts": [dict(zip(("angle_deg", "height_mm", "distance_mm"), mount_of(p))) for p in self.positions],
                "rotations_deg": list(self.rotations), "score": self.score,
                "anisotropic_coverage_design_scale": self.coverage,
                "isotropic_coverage_design_scale": self.iso_coverage,
                "geometric_mean_relative_error": self.errors, "reference": self.reference,
                "greedy_trajectory": self.trajectory, "prefixes": self.prefixes, "runner": self.runner,
                "n_candidates": self.n_candidates, "n_feasible": self.n_feasible, "timings_s": self.timings}


def parse_materials(spec: str) -> list[tuple[str, WardParams]]:
    """Comma-separated material specs (:func:`glossrig.core.models.materials.parse_material`);
    each must be an extended-Ward material."""
    from glossrig.core.models.materials import parse_material

    out = []
    for part in _split_ward(spec):
        m = parse_material(part)
        if m.kind != "ward":
            raise InputError(f"material {part!r} is {m.kind}; the expected parameter error needs an extended-Ward material")
        assert m.ward is not None               # a Ward material has its parameters
        out.append((m.label, m.ward))
    if not out:
        raise InputError("no target material given")
    labels = [lb for lb, _ in out]
    if len(set(labels)) != len(labels):
        raise InputError(f"duplicate target materials in {spec!r}")
    return out


def _split_ward(spec: str) -> list[str]:
    """Split a list that may hold ``ward:a=..,b=..`` specs (whose own commas
    separate parameters): a new item starts at a part without '='."""
    items: list[str] = []
    for part in spec.split(","):
        part = part.strip()
        if not part:
            continue
        if items and "=" in part and not part.startswith("ward:") and items[-1].startswith("ward:"):
            items[-1] += "," + part
        else:
            items.append(part)
    return items


def make_setup(rig, materials, rotations: Sequence[int], coverage_scale: float = 0.25, fisher_scale: float = 0.25,
               noise: str = "hdr", fisher_rows: int = 6000) -> EvalSetup:
    cpx = cov.pixel_geometry(rig, coverage_scale)
    fpx = cpx if fisher_scale == coverage_scale else cov.pixel_geometry(rig, fisher_scale)
    return EvalSetup(rig=rig, cov_pixels=cpx, fisher_pixels=fpx, materials=list(materials),
                     rotations=tuple(int(r) for r in rotations), noise=fi.noise_model(noise, rig),
                     fisher_rows=fisher_rows)


def _chunks(items: list, size: int) -> list[list]:
    return [items[k:k + size] for k in range(0, len(items), size)]


def optimise(rig, n_leds: int, materials, runner, space: SearchSpace = SearchSpace(),
             limits: MountingLimits = MountingLimits(), n_rotations: int = 4, lam: float = 1.0, iso_weight: float = 1.0,
             coverage_scale: float = 0.25, fisher_scale: float = 0.25, noise: str = "hdr",
             reference_leds: Sequence[int] | None = None, chunk: int = 16, rounds: int = 3,
             progress: bool = True, log: Callable[[str], None] | None = None) -> DesignResult:
    """Sweep the candidate mounts (on ``runner``), then select LEDs and rotations
    (module docstring). The reference is ``rig`` itself with ``reference_leds``
    (default: all its LEDs) and its sample rotations."""
    say = log or (lambda m: None)
    t0 = time.perf_counter()
    if not (1 <= n_leds <= limits.max_leds):
        raise InputError(f"--leds must lie in [1, {limits.max_leds}] (relay channels), got {n_leds}")
    if not (1 <= n_rotations <= len(space.rotations_deg)):
        raise InputError(f"number of rotations must lie in [1, {len(space.rotations_deg)}], got {n_rotations}")
    if not (math.isfinite(lam) and lam >= 0):
        raise InputError(f"lambda must be >= 0, got {lam}")
    if not (math.isfinite(iso_weight) and iso_weight >= 0):
        raise InputError(f"isotropic-coverage weight must be >= 0, got {iso_weight}")
    rig_rots = [float(r) for r in rig.sample_rotations]
    if any(r != int(r) for r in rig_rots):
        raise InputError(f"the reference rig's rotations must be whole degrees, got {rig_rots}", path=rig.path)
    ref_rots = [int(r) for r in rig_rots]
    rotations = tuple(sorted(set(space.rotations_deg) | set(ref_rots)))
    setup = make_setup(rig, materials, rotations, coverage_scale, fisher_scale, noise)
    mounts = space.mounts()
    positions = [mount_position(*m) for m in mounts]
    feasible = np.array([not led_problems(rig, p, limits) for p in positions])
    say(f"{len(mounts)} candidate mounts, {int(feasible.sum())} within the limits")
    ref_ids = list(rig.led_ids() if reference_leds is None else reference_leds)
    ref_pos = [np.asarray(rig.led(i).position, float) for i in ref_ids]
    todo = [p for p, ok in zip(positions, feasible) if ok] + ref_pos
    t1 = time.perf_counter()
    results = runner.map(evaluate_chunk, _chunks(todo, chunk), shared=setup, desc="design sweep",
                         progress=progress, unit="chunk")
    evals_all = [e for ch in results for e in ch]
    t2 = time.perf_counter()
    n_feas = int(feasible.sum())
    evals = evals_all[:n_feas]
    ref_evals = evals_all[n_feas:]
    cand_pos = np.array([e.position for e in evals])
    conflict = conflicts(rig, cand_pos, limits)
    pool = Pool(evals=evals + ref_evals, conflict=np.zeros((1, 1), bool), rotations=rotations,
                materials=list(materials), lam=lam, iso_weight=iso_weight)
    nall = len(pool.evals)
    full_conf = np.ones((nall, nall), bool)
    full_conf[:n_feas, :n_feas] = conflict
    pool.conflict = full_conf
    ref_idx = list(range(n_feas, nall))
    ref_cov = pool.coverage_bins(ref_idx, ref_rots) / ANISO_TOTAL
    ref_err = pool.errors_from_information(pool.information(ref_idx, ref_rots))
    pool.ref_coverage, pool.ref_errors = ref_cov, ref_err
    pool.ref_iso = pool.iso_bins(ref_idx) / ISO_TOTAL
    say(f"reference {rig.name} ({len(ref_ids)} LEDs, rotations {ref_rots}): anisotropic coverage "
        f"{100 * ref_cov:.4f} % at scale {coverage_scale:g}, errors "
        + ", ".join(f"{lb} {e:.3g}" for (lb, _), e in zip(materials, ref_err)))
    cand_ok = np.zeros(nall, bool)
    cand_ok[:n_feas] = True
    rots = list(ref_rots)[:n_rotations]
    if len(rots) < n_rotations:
        rots += [r for r in rotations if r not in rots][: n_rotations - len(rots)]
    leds, traj = select_leds(pool, n_leds, rots, feasible=cand_ok, log=say)
    for _rnd in range(rounds):
        new_rots = select_rotations(pool, leds, n_rotations, start=rots, log=say)
        if new_rots == sorted(rots):
            break
        rots = new_rots
        new_leds, _ = select_leds(pool, n_leds, rots, start=leds, feasible=cand_ok, log=say)
        if new_leds == leds:
            break
        leds = new_leds
    order = sorted(leds, key=lambda i: (mount_of(pool.evals[i].position)[0], mount_of(pool.evals[i].position)[1]))
    score = pool.score(order, rots)
    c = pool.coverage_bins(order, rots) / ANISO_TOTAL
    c_iso = pool.iso_bins(order) / ISO_TOTAL
    errs = pool.errors_from_information(pool.information(order, rots))
    prefixes = greedy_order(pool, order, rots)
    t3 = time.perf_counter()
    ref = {"leds": ref_ids, "rotations_deg": ref_rots, "anisotropic_coverage_design_scale": ref_cov,
           "isotropic_coverage_design_scale": pool.ref_iso,
           "geometric_mean_relative_error": {lb: float(e) for (lb, _), e in zip(materials, ref_err)}}
    return DesignResult(positions=np.array([pool.evals[i].position for i in order]), rotations=list(rots),
                        score=float(score), coverage=float(c), iso_coverage=float(c_iso),
                        errors={lb: float(e) for (lb, _), e in zip(materials, errs)}, reference=ref,
                        trajectory=[float(x) for x in traj], prefixes=prefixes, runner=getattr(runner, "name", "?"),
                        n_candidates=len(mounts), n_feasible=n_feas,
                        timings={"setup": t1 - t0, "sweep": t2 - t1, "selection": t3 - t2})


# ----------------------------------------------------------------------------
# Evaluating a finished design, and writing it
# ----------------------------------------------------------------------------

def design_errors(rig, materials, rotations=None, led_ids=None, scale: float = 0.25, noise: str = "hdr",
                  fisher_rows: int = 20000, gain_rel: float = 0.0) -> dict[str, fi.ExpectedError]:
    """Expected standard errors (Fisher information, :mod:`glossrig.core.design.fisher`)
    of each material for a rig's LEDs and rotations, at image ``scale``;
    ``gain_rel`` > 0: each (LED, rotation) sequence has an unknown residual gain of
    that relative standard deviation (:func:`~glossrig.core.design.fisher.gain_marginal_information`)."""
    rotations = [float(r) for r in (rig.sample_rotations if rotations is None else rotations)]
    led_ids = list(rig.led_ids() if led_ids is None else led_ids)
    px = cov.pixel_geometry(rig, scale)
    nm = fi.noise_model(noise, rig)
    info = {lb: np.zeros((5, 5)) for lb, _ in materials}
    nrows = {lb: 0 for lb, _ in materials}
    for i in led_ids:
        a = cov.direction_angles(px, rig.led(i).position, half=True)
        for lb, p in materials:
            rows, w = _rows_for(a, a["lit"], p, fisher_rows, 3000)
            for r in rotations:
                f, J = fi.ward_jacobian(np.radians(a["theta_in"][rows]), np.radians(a["theta_out"][rows]),
                                        np.radians(a["theta_h"][rows]),
                                        np.radians(np.mod(a["phi_h"][rows] - r, 360.0)), p)
                sigma = nm.sigma(f, a["cos_in"][rows], a["dist_in"][rows])
                info[lb] += fi.gain_marginal_information(J, sigma, f, gain_rel, w)
                nrows[lb] += int(round(w.sum()))
    return {lb: fi.summarise(p, fi.covariance_from_information(info[lb], fi.identifiable(p)), nrows[lb])
            for lb, p in materials}


def design_rig(rig, positions, rotations, name: str = "optimised"):
    """A :class:`~glossrig.core.rig.Rig` with the designed LEDs (ids and relay
    channels 1..n) and sample rotations."""
    leds = []
    for k, p in enumerate(np.asarray(positions, float)):
        a, h, d = mount_of(p)
        row = "middle" if abs(h) < 1e-9 else ("upper" if h > 0 else "lower")
        leds.append(Led(id=k + 1, row=row, angle_deg=a, channel=k + 1, name=_led_name(a, h, d),
                        gpio=_gpio(rig, k + 1), position=(float(p[0]), float(p[1]), float(p[2]))))
    return replace(rig, name=name, leds=tuple(leds), sample_rotations=tuple(float(r) for r in rotations))


def _led_name(a: float, h: float, d: float) -> str:
    return f"a{a:+.0f}h{h:+.0f}d{d:.0f}"


def _gpio(rig, channel: int) -> int:
    """GPIO pin of a relay channel in the rig being redesigned (the wiring stays)."""
    for led in rig.leds:
        if led.channel == channel:
            return led.gpio
    return -1


def write_rig_toml(template_path, positions, rotations, out_path, header: str = "", name: str = "optimised",
                   description: str | None = None) -> Path:
    """Copy the template rig file with its LED table, sample rotations, name and
    description replaced; per-LED ``distance`` and ``height`` keys carry the
    mounts (:func:`glossrig.core.rig.load_rig`). Refuses to overwrite the template."""
    from glossrig.core.rig import load_rig

    template_path, out_path = Path(template_path), Path(out_path)
    if out_path.resolve() == template_path.resolve():
        raise InputError("refusing to overwrite the template rig file", path=out_path)
    if not out_path.parent.is_dir():
        raise InputError("output folder does not exist", path=out_path)
    text = template_path.read_text()
    rig = load_rig(template_path)
    m = re.search(r"^table = \[\n.*?^\]\n", text, flags=re.S | re.M)
    if not m:
        raise InputError("no 'table = [' ... ']' block under [leds] to replace", path=template_path)
    lines = ["table = ["]
    for k, p in enumerate(np.asarray(positions, float)):
        a, h, d = mount_of(p)
        row = "middle" if abs(h) < 1e-9 else ("upper" if h > 0 else "lower")
        lines.append(f'  {{ id = {k + 1}, row = "{row}", angle = {a:.1f}, distance = {d:.1f}, height = {h:.1f}, '
                     f'channel = {k + 1}, name = "{_led_name(a, h, d)}", gpio = {_gpio(rig, k + 1)} }},')
    lines.append("]\n")
    text = text[:m.start()] + "\n".join(lines) + text[m.end():]
    rot_txt = "[" + ", ".join(f"{float(r):.1f}" for r in rotations) + "]"
    text, nsub = re.subn(r"^sample_rotations = \[[^\]]*\]", f"sample_rotations = {rot_txt}", text, flags=re.M)
    if nsub != 1:
        raise InputError("no exposures.sample_rotations line to replace", path=template_path)
    text = re.sub(r'^name = "[^"]*"', f'name = "{name}"', text, count=1, flags=re.M)
    if description is not None:
        text = re.sub(r'^description = "[^"]*"', f'description = "{description}"', text, count=1, flags=re.M)
    text = header + text
    def fill(tmp: Path) -> None:
        tmp.write_text(text)
        load_rig(tmp)                 # what we wrote must load

    return atomic_write(out_path, fill)
