"""Tangent frames and BRDF angles (thesis section 4.3.5, corrected).

The thesis's printed equations are wrong in several places; this module does
the geometry right and says where it departs:

* eq. 4.59 starts the incident vector at the axis point; it starts at the
  surface point: ``wi = normalize(P_lamp - P_surface)``.
* eq. 4.64 leaves the halfway vector unnormalised; here ``h = normalize(wi + wo)``.
* eq. 4.68 projects with the wrong sign (``<v,n> n - v``); the tangential part
  of v is ``v - <v,n> n``.
* eq. 4.70 takes ``(v x n) . n`` which is always zero; the counter-clockwise
  test is the sign of ``<v_t, b>`` with the bitangent ``b = n x t``, so that
  ``phi = atan2(<v, b>, <v, t>)`` in [0, 2 pi).

Difference angles follow Rusinkiewicz, "A new change of variables for
efficient BRDF representation", EGWR 1998: rotate so that h is the pole,
then theta_d, phi_d are the zenith and azimuth of wi in that frame.
"""
from __future__ import annotations

import numpy as np

ANGLE_COLUMNS = ("theta_in", "phi_in", "theta_out", "phi_out", "theta_h", "phi_h", "theta_d", "phi_d")


def normalize(v: np.ndarray) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def rotate_about(v: np.ndarray, axis: np.ndarray, angle) -> np.ndarray:
    """Rodrigues rotation of v about the unit ``axis`` by ``angle`` (right-handed)."""
    angle = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(angle)[..., None], np.sin(angle)[..., None]
    k = axis
    return v * c + np.cross(k, v) * s + k * np.sum(k * v, axis=-1, keepdims=True) * (1 - c)


def tangent_frame(normal: np.ndarray, axis: np.ndarray, rotation_rad) -> tuple[np.ndarray, np.ndarray]:
    """Tangent and bitangent of a point on the cylinder (thesis eq. 4.61-4.63).

    The tangent is ``axis x normal`` (it runs around the cylinder), rotated about
    the normal by the sample rotation (eq. 4.62; positive = counter-clockwise
    seen from outside, right-hand rule about the normal). Bitangent ``= n x t``.
    """
    n = normalize(normal)
    t0 = normalize(np.cross(np.broadcast_to(axis, n.shape), n))
    t = rotate_about(t0, n, np.broadcast_to(np.asarray(rotation_rad, dtype=np.float64), n.shape[:-1]))
    b = np.cross(n, t)
    return t, b


def _zenith_azimuth(v, n, t, b):
    z = np.clip(np.sum(v * n, axis=-1), -1.0, 1.0)
    theta = np.arccos(z)
    phi = np.mod(np.arctan2(np.sum(v * b, axis=-1), np.sum(v * t, axis=-1)), 2 * np.pi)
    return theta, phi


def brdf_angles(wi: np.ndarray, wo: np.ndarray, n: np.ndarray, t: np.ndarray) -> dict[str, np.ndarray]:
    """The eight BRDF angles (radians) of unit directions wi (to the light) and wo
    (to the camera) in the frame (t, b = n x t, n). Shapes ``(..., 3)``."""
    wi, wo, n, t = (np.asarray(a, dtype=np.float64) for a in (wi, wo, n, t))
    b = np.cross(n, t)
    h = normalize(wi + wo)
    out = {}
    out["theta_in"], out["phi_in"] = _zenith_azimuth(wi, n, t, b)
    out["theta_out"], out["phi_out"] = _zenith_azimuth(wo, n, t, b)
    out["theta_h"], out["phi_h"] = _zenith_azimuth(h, n, t, b)
    # Difference frame: rotate (t, b, n) about n by phi_h, then about the new
    # bitangent by theta_h, so that h becomes the pole.
    th, ph = out["theta_h"], out["phi_h"]
    t1 = rotate_about(t, n, ph)
    b1 = np.cross(n, t1)
    n2 = h
    t2 = rotate_about(t1, b1, th)
    b2 = np.cross(n2, t2)
    out["theta_d"], out["phi_d"] = _zenith_azimuth(wi, n2, t2, b2)
    return out


def local_direction(theta, phi) -> np.ndarray:
    """Unit vector in the local frame (x = tangent, y = bitangent, z = normal)."""
    theta, phi = np.broadcast_arrays(np.asarray(theta, float), np.asarray(phi, float))
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)
