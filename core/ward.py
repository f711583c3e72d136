"""The extended Ward BRDF (thesis eq. 2.5 with the lobe rotation of eq. 4.79-4.80).

    f(wi, wo) = rho_d / pi
              + rho_s / (4 pi ax ay sqrt(cos th_i cos th_o))
                * exp(-tan^2 th_h (cos^2 a_n / ax^2 + sin^2 a_n / ay^2)),
    a_n = phi_h + lobe_rotation                                   (eq. 4.80)

Angles are in the local tangent frame (x = tangent, y = bitangent, z = normal)
of thesis section 4.3.5. Adding the lobe rotation to phi_h turns the lobe's
principal axes by -lobe_rotation about the normal. The ``mod 2 pi`` of eq. 4.80
is immaterial (cos^2, sin^2 are pi-periodic) and is dropped.

Ward, "Measuring and modeling anisotropic reflection", SIGGRAPH 1992.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from .errors import InputError

# Bounds of thesis Table 4.2 (alpha <= 0.5); rho_d, rho_s >= 0.
ALPHA_MAX = 0.5


@dataclass(frozen=True)
class WardParams:
    """Extended Ward parameters; ``lobe_rotation`` in radians."""

    rho_d: float
    rho_s: float
    alpha_x: float
    alpha_y: float
    lobe_rotation: float = 0.0

    def __post_init__(self):
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(f"Ward parameter {f.name}={v!r} is not a finite number")
        if self.rho_d < 0 or self.rho_s < 0:
            raise InputError(f"Ward rho_d and rho_s must be >= 0 (got rho_d={self.rho_d}, rho_s={self.rho_s})")
        if not (0 < self.alpha_x and 0 < self.alpha_y):
            raise InputError(f"Ward alpha_x and alpha_y must be > 0 (got {self.alpha_x}, {self.alpha_y})")

    def as_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def parse(cls, text: str) -> "WardParams":
        """Parse ``rho_d=..,rho_s=..,alpha_x=..,alpha_y=..[,lobe_rotation=..]``."""
        values = {}
        for part in text.split(","):
            if not part.strip():
                continue
            if "=" not in part:
                raise InputError(f"Ward parameters: expected name=value, got {part!r} in {text!r}")
            k, v = part.split("=", 1)
            k = k.strip()
            if k not in {f.name for f in fields(cls)}:
                raise InputError(f"Ward parameters: unknown parameter {k!r} in {text!r}")
            try:
                values[k] = float(v)
            except ValueError:
                raise InputError(f"Ward parameters: {k}={v!r} is not a number") from None
        missing = {"rho_d", "rho_s", "alpha_x", "alpha_y"} - values.keys()
        if missing:
            raise InputError(f"Ward parameters: missing {', '.join(sorted(missing))} in {text!r}")
        return cls(**values)


def ward_from_angles(theta_in, theta_out, theta_h, phi_h, p: WardParams):
    """Eq. 4.79 from the angles (radians); arrays broadcast. Zero below the horizon."""
    theta_in, theta_out, theta_h, phi_h = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (theta_in, theta_out, theta_h, phi_h)))
    ci, co = np.cos(theta_in), np.cos(theta_out)
    valid = (ci > 0) & (co > 0)
    an = phi_h + p.lobe_rotation
    t2 = np.tan(theta_h) ** 2
    expo = -t2 * (np.cos(an) ** 2 / p.alpha_x ** 2 + np.sin(an) ** 2 / p.alpha_y ** 2)
    with np.errstate(invalid="ignore", divide="ignore"):
        spec = p.rho_s / (4 * np.pi * p.alpha_x * p.alpha_y * np.sqrt(np.where(valid, ci * co, 1.0))) * np.exp(expo)
    return np.where(valid, p.rho_d / np.pi + spec, 0.0)


def ward_local(wi, wo, p: WardParams):
    """Eq. 4.79 for unit direction arrays ``(..., 3)`` in the local frame (z = normal)."""
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    ci, co = wi[..., 2], wo[..., 2]
    valid = (ci > 0) & (co > 0)
    # tan^2 th_h cos^2 a_n = (h . u)^2 / h_z^2 with u the lobe's x axis.
    c, s = math.cos(p.lobe_rotation), math.sin(p.lobe_rotation)
    hx_rot = c * h[..., 0] - s * h[..., 1]    # |h_t| cos(phi_h + rot)
    hy_rot = s * h[..., 0] + c * h[..., 1]    # |h_t| sin(phi_h + rot)
    with np.errstate(invalid="ignore", divide="ignore"):
        expo = -((hx_rot / p.alpha_x) ** 2 + (hy_rot / p.alpha_y) ** 2) / h[..., 2] ** 2
        spec = p.rho_s / (4 * np.pi * p.alpha_x * p.alpha_y * np.sqrt(np.where(valid, ci * co, 1.0))) * np.exp(expo)
    return np.where(valid, p.rho_d / np.pi + spec, 0.0)


def ward_albedo(p: WardParams, theta_out: float, n: int = 400_000, seed: int = 0) -> float:
    """Directional albedo int f cos(th_i) dw_i at outgoing zenith ``theta_out`` (thesis eq. 2.4),
    by cosine-weighted Monte Carlo (estimate = mean(f) * pi)."""
    rng = np.random.default_rng(seed)
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    wi = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - u1))], axis=-1)
    wo = np.array([math.sin(theta_out), 0.0, math.cos(theta_out)])
    return float(np.mean(ward_local(wi, wo, p)) * np.pi)
