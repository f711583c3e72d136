"""Per-pixel geometry of the cylinder rig (thesis 4.3.2 "2D-3D correspondences", 4.3.5).

For every camera pixel: undistort, cast a ray, intersect the sample's cylinder
(limited to the sample height), and derive normal, tangent frame and the BRDF
angles towards each lamp and the camera.

Departures from the printed thesis (docstrings of the functions say where):
* eq. 4.27 multiplies by the pixel coordinate twice; the normalised ray is
  ``((u - cx) / fx, (v - cy) / fy, 1)``.
* eq. 4.28 adds the radial factor where it should multiply, and is OpenCV's
  *forward* distortion model; rays need its inverse, which we take from
  ``cv2.undistortPoints`` (iterative inversion of the same k1 k2 p1 p2 k3 model).
* eq. 4.54 adds a translation to a direction: the axis direction is ``R @ (0,1,0)``
  alone, the axis point is the cylinder origin.
* eq. 4.55 uses the lamp position where the cylinder centre is meant.
Ray-cylinder intersection: Pharr, Jakob & Humphreys, PBRT 3rd ed., sec. 3.2.2.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from glossrig.core.models.angles import ANGLE_COLUMNS, brdf_angles, normalize, tangent_frame


def undistorted_rays(K: np.ndarray, dist, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Ray directions ``(N, 3)`` in the camera frame (z forward, unnormalised
    with z = 1) through pixel centres (u, v), undoing OpenCV's distortion."""
    pts = np.stack([np.ravel(u), np.ravel(v)], axis=-1).astype(np.float64).reshape(-1, 1, 2)
    if dist is None or not np.any(np.asarray(dist)):
        xy = np.stack([(pts[:, 0, 0] - K[0, 2]) / K[0, 0], (pts[:, 0, 1] - K[1, 2]) / K[1, 1]], axis=-1)
    else:
        crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)
        xy = cv2.undistortPoints(pts, K, np.asarray(dist, np.float64), R=np.eye(3), P=np.eye(3), criteria=crit).reshape(-1, 2)
    return np.concatenate([xy, np.ones((xy.shape[0], 1))], axis=1)


def intersect_cylinder(origin: np.ndarray, dirs: np.ndarray, radius: float, y_min: float, y_max: float):
    """Nearest intersection of rays with the cylinder x^2 + z^2 = r^2 (axis = y),
    limited to y_min < y < y_max (thesis 4.3.2: only the sample height counts).

    Returns (points (N,3), valid (N,)). Rays from outside the cylinder hit its
    front face first; a ray whose front hit is outside the height window does
    not count (the back face is hidden by the cylinder itself)."""
    o = np.asarray(origin, np.float64)
    d = np.asarray(dirs, np.float64)
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = 2 * (o[0] * d[:, 0] + o[2] * d[:, 2])
    c = o[0] ** 2 + o[2] ** 2 - radius ** 2
    disc = b * b - 4 * a * c
    hit = (disc >= 0) & (a > 0)
    sq = np.sqrt(np.where(hit, disc, 0.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (-b - sq) / (2 * a)
    hit &= t0 > 0
    p = o[None, :] + t0[:, None] * d
    valid = hit & (p[:, 1] > y_min) & (p[:, 1] < y_max)
    return p, valid


@dataclass
class SurfaceSamples:
    """Pixels that see the sample: pixel coords, surface points and normals (holder frame)."""

    u: np.ndarray
    v: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    camera_centre: np.ndarray
    axis: np.ndarray


def surface_samples(K, dist, size: tuple[int, int], R_world_cam, t_world_cam, R_cyl_world, t_cyl_world,
                    radius: float, height: float, roi: tuple[int, int, int, int] | None = None,
                    pixels: tuple[np.ndarray, np.ndarray] | None = None,
                    footprint_half_px: float | None = None) -> SurfaceSamples:
    """Intersect pixel rays with the sample (thesis eq. 4.26-4.30, corrected).

    Poses are OpenCV-style: ``x_cam = R_world_cam @ x_world + t_world_cam`` and
    ``x_world = R_cyl_world @ x_cyl + t_cyl_world`` (world = holder frame).
    By default every pixel centre of the image (or of ``roi`` = (x0, y0, x1, y1))
    is cast; ``pixels = (u, v)`` casts rays through those (sub-pixel) positions
    instead, e.g. the centres of 2x2 Bayer blocks. ``u, v`` of the result keep
    the dtype of the input positions.

    ``footprint_half_px = h`` keeps a position only when the rays through the four corners
    of its footprint, ``(u +- h, v +- h)``, meet the sample too: a 2x2 Bayer block
    (``h = 1``) whose centre ray hits the sample but that straddles the cylinder's
    silhouette or the sample's upper or lower edge mixes sample and background in its
    four pixels. The thesis keeps a block by its centre ray alone (4.3.2); on the twin
    those straddling blocks' diffuse values were 3-88 % off (scale 0.1, the outermost
    block column on either side; validation/uncertainty_coverage.md, section 3).
    """
    if pixels is None:
        w, h = size
        x0, y0, x1, y1 = roi if roi is not None else (0, 0, w, h)
        vv, uu = np.mgrid[y0:y1, x0:x1]
        u, v = uu.ravel(), vv.ravel()
    else:
        u, v = (np.asarray(a).ravel() for a in pixels)
    Rwc = np.asarray(R_world_cam, float)
    C_world = -Rwc.T @ np.asarray(t_world_cam, float)
    Rcw = np.asarray(R_cyl_world, float)
    tcw = np.asarray(t_cyl_world, float)
    o_cyl = Rcw.T @ (C_world - tcw)

    def cast(uu: np.ndarray, vv: np.ndarray):
        d_cyl = (undistorted_rays(K, dist, uu, vv) @ Rwc) @ Rcw      # R^T d per row, into the cylinder frame
        return intersect_cylinder(o_cyl, d_cyl, radius, -height / 2, height / 2)

    uf, vf = u.astype(np.float64), v.astype(np.float64)
    p_cyl, valid = cast(uf, vf)
    if footprint_half_px is not None:
        for du in (-footprint_half_px, footprint_half_px):
            for dv in (-footprint_half_px, footprint_half_px):
                idx = np.flatnonzero(valid)
                valid[idx[~cast(uf[idx] + du, vf[idx] + dv)[1]]] = False
    p_cyl = p_cyl[valid]
    n_cyl = normalize(p_cyl * np.array([1.0, 0.0, 1.0]))
    pts = p_cyl @ Rcw.T + tcw
    nrm = n_cyl @ Rcw.T
    if pixels is None:
        u, v = u.astype(np.int32), v.astype(np.int32)
    return SurfaceSamples(u=u[valid], v=v[valid], points=pts, normals=nrm,
                          camera_centre=C_world, axis=Rcw @ np.array([0.0, 1.0, 0.0]))


def sample_angles(s: SurfaceSamples, lamp_position, rotation_deg: float) -> dict[str, np.ndarray]:
    """BRDF angles of every surface sample for one lamp and sample rotation.

    wi runs from the surface point to the lamp (the thesis's eq. 4.59 starts it at
    the axis point), wo from the surface point to the camera (eq. 4.60)."""
    wi = normalize(np.asarray(lamp_position, float)[None, :] - s.points)
    wo = normalize(s.camera_centre[None, :] - s.points)
    t, _ = tangent_frame(s.normals, s.axis, np.deg2rad(rotation_deg))
    ang = brdf_angles(wi, wo, s.normals, t)
    ang["cos_in"] = np.sum(wi * s.normals, axis=-1)
    ang["cos_out"] = np.sum(wo * s.normals, axis=-1)
    ang["dist_in"] = np.linalg.norm(np.asarray(lamp_position, float)[None, :] - s.points, axis=-1)
    return ang


def nominal_samples(rig, led_ids, rotations_deg, scale: float = 0.25):
    """The BRDF samples the rig measures, from its nominal geometry alone (no rendering).

    One row per (pixel on the sample, LED, rotation) with both directions above
    the surface: the angle columns of design.md (radians, tangent frame of
    thesis 4.3.5), ``u, v`` (pixel at ``scale``), ``led``, ``rotation`` (deg),
    and the surface point ``x, y, z`` (mm, holder frame).
    """
    import pandas as pd

    cam = rig.camera
    R, t = cam.pose()
    s = surface_samples(cam.matrix(scale), cam.distortion, cam.size(scale), R, t, np.eye(3), np.zeros(3),
                        rig.cylinder_radius, rig.sample_height)
    frames = []
    for rot in rotations_deg:
        for led_id in led_ids:
            ang = sample_angles(s, rig.led(led_id).position, rot)
            keep = (ang["cos_in"] > 0) & (ang["cos_out"] > 0)
            df = pd.DataFrame({k: ang[k][keep] for k in ANGLE_COLUMNS})
            df["u"], df["v"] = s.u[keep], s.v[keep]
            df["led"], df["rotation"] = led_id, float(rot)
            df["x"], df["y"], df["z"] = s.points[keep, 0], s.points[keep, 1], s.points[keep, 2]
            frames.append(df)
    return pd.concat(frames, ignore_index=True)
