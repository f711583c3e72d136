"""The extended Ward BRDF (thesis eq. 2.5 with the lobe rotation of eq. 4.79-4.80).

    f(wi, wo) = rho_d / pi
              + rho_s / (4 pi ax ay sqrt(cos th_i cos th_o))
                * exp(-tan^2 th_h (cos^2 a_n / ax^2 + sin^2 a_n / ay^2)),
    a_n = phi_h + lobe_rotation                                   (eq. 4.80)

Angles are in the local tangent frame (x = tangent, y = bitangent, z = normal)
of thesis section 4.3.5. Adding the lobe rotation to phi_h turns the lobe's
principal axes by -lobe_rotation about the normal. The ``mod 2 pi`` of eq. 4.80
is immaterial (cos^2, sin^2 are pi-periodic) and is dropped.

This module holds glossrig's one evaluation of the model and of its Jacobian
(:func:`ward_parts`, :func:`ward_param_jacobian`; see the section below for the
form, and :data:`EXPONENT_CAP` for the one numeric guard and how the former
copies differed).

Ward, "Measuring and modeling anisotropic reflection", SIGGRAPH 1992.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields

import numpy as np

from glossrig.core.errors import InputError

# Bounds of thesis Table 4.2 (alpha <= 0.5); rho_d, rho_s >= 0.
ALPHA_MAX = 0.5
#: Largest |lobe_rotation| accepted from a user, in radians. Table 4.2 bounds the
#: thesis's angle by [0, 360] degrees; here angles are radians, and a value beyond
#: 2 pi is almost surely degrees typed where radians were meant.
LOBE_ROTATION_MAX = 2 * math.pi


def parse_angle(text, name: str = "lobe_rotation") -> float:
    """An angle given by a user, in radians: a number (radians), or a number with an
    explicit unit, ``140deg`` or ``2.44rad``. Returns radians."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        return float(text)
    t = str(text).strip().lower()
    scale = 1.0
    for unit, k in (("deg", math.pi / 180.0), ("rad", 1.0)):
        if t.endswith(unit):
            t, scale = t[: -len(unit)].strip(), k
            break
    try:
        return float(t) * scale
    except ValueError:
        raise InputError(f"Ward parameters: {name}={text!r} is not an angle (a number in radians, or "
                         f"NUMBERdeg / NUMBERrad)") from None


def check_physical(p: WardParams, where=None, what: str = "Ward parameters") -> WardParams:
    """Reject Ward parameters outside their physical ranges, the one validator every user
    input of Ward parameters goes through (material specs and files, ``model predict
    --ward``, the reproduction model's CSV): rho_d in [0, 1], rho_s >= 0, energy
    conservation rho_d + rho_s <= 1, 0 < alpha <= 0.5 (thesis Table 4.2) and
    |lobe_rotation| <= 2 pi radians (a larger value is almost surely degrees: the error
    says so). Values computed inside glossrig (fits) are not checked here. ``where``:
    the file or argument named in the error. Returns ``p``."""
    bad = []
    if not 0.0 <= p.rho_d <= 1.0:
        bad.append(f"rho_d={p.rho_d:g} must lie in [0, 1]")
    if p.rho_s < 0:
        bad.append(f"rho_s={p.rho_s:g} must be >= 0")
    if not bad and p.rho_d + p.rho_s > 1.0:
        bad.append(f"rho_d + rho_s = {p.rho_d + p.rho_s:g} exceeds 1 (the surface would reflect more energy "
                   f"than it receives)")
    for k in ("alpha_x", "alpha_y"):
        v = getattr(p, k)
        if not 0.0 < v <= ALPHA_MAX:
            bad.append(f"{k}={v:g} must lie in (0, {ALPHA_MAX:g}] (thesis Table 4.2)")
    if abs(p.lobe_rotation) > LOBE_ROTATION_MAX:
        bad.append(f"lobe_rotation={p.lobe_rotation:g} is beyond 2 pi radians: degrees? lobe_rotation is in "
                   f"radians; write {p.lobe_rotation:g}deg to give degrees "
                   f"({math.radians(p.lobe_rotation):.4g} rad)")
    if bad:
        raise InputError(f"{what}: " + "; ".join(bad), path=where)
    return p


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
    def parse(cls, text: str) -> WardParams:
        """Parse ``rho_d=..,rho_s=..,alpha_x=..,alpha_y=..[,lobe_rotation=..]`` given by a
        user: lobe_rotation in radians unless written with a unit (``140deg``, ``2.44rad``);
        every value is checked against its physical range (:func:`check_physical`)."""
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
            if k == "lobe_rotation":
                values[k] = parse_angle(v, k)       # radians, or an explicit unit: 140deg, 2.44rad
                continue
            try:
                values[k] = float(v)
            except ValueError:
                raise InputError(f"Ward parameters: {k}={v!r} is not a number") from None
        missing = {"rho_d", "rho_s", "alpha_x", "alpha_y"} - values.keys()
        if missing:
            raise InputError(f"Ward parameters: missing {', '.join(sorted(missing))} in {text!r}")
        return check_physical(cls(**values), what=f"Ward parameters {text!r}")


# ----------------------------------------------------------------------------
# The one evaluation of eq. 4.79-4.80 and of its derivatives
# ----------------------------------------------------------------------------
#
# Every Ward value and Jacobian in glossrig goes through :func:`ward_parts` (the fit,
# the Fisher information of the design tools, the reproduction model, the gloss
# meters, the previews, the diagnosis); the Mitsuba plugin
# (:mod:`glossrig.twin.ward_bsdf`) is the same formula in Dr.Jit and is tested
# against :func:`ward_local`.
#
# The lobe is written with the half vector's slopes in the lobe's axes,
# ``u = tan th_h cos a_n``, ``v = tan th_h sin a_n`` (``a_n = phi_h + lobe_rotation``),
# so that the exponent is ``q = (u / ax)^2 + (v / ay)^2``. This form is well
# conditioned for any anisotropy: the double-angle form ``A + B cos 2 a_n`` the fit
# used before loses ~ax^2/ay^2 of its relative accuracy along the wide axis of a
# very anisotropic lobe (alpha 0.5 x 1e-4: ~1e-8), where this one keeps full precision.

#: The one numeric guard of the lobe's exponent: ``exp(-min(q, EXPONENT_CAP))``.
#: exp(-200) ~ 1.4e-87 is ~80 orders of magnitude below any BRDF value the rig can
#: measure (times the largest normalisation, 1/(4 pi 1e-8 * 6e-17), it is still
#: < 1e-63 1/sr), so the cap changes no physical value; it keeps the far tail of a
#: narrow lobe out of IEEE denormals (10-100x slower in exp, products and SVD), and
#: it keeps the lobe strictly positive so that the fit's Jacobian never vanishes
#: identically (a start far from the data still has a descent direction).
#: History (issue #18): the fit's and the Fisher information's copies capped q at
#: 200; :func:`ward_from_angles`, :func:`ward_local` and the reproduction model's
#: gradient did not cap (exp underflowed to 0, through denormals). The difference
#: is below 1e-63 1/sr; the cap is kept for every caller.
#: The other guard is the horizon: where ``cos th_i <= 0`` or ``cos th_o <= 0``
#: the BRDF (diffuse and specular) and its Jacobian are 0, and the normalisation
#: ``1 / sqrt(cos th_i cos th_o)`` is otherwise exact (the fit's former
#: ``sqrt(max(cos th_i cos th_o, 1e-12))`` changed the lobe within ~1e-12 rad of
#: grazing, and gave a below-horizon sample a large specular value instead of 0).
EXPONENT_CAP = 200.0


@dataclass(frozen=True)
class WardGeometry:
    """Per-sample quantities of eq. 4.79 that do not depend on the parameters
    (flat arrays; ``shape`` is the callers' broadcast shape).

    ``sx, sy``: the half vector's slopes ``tan th_h cos phi_h``, ``tan th_h sin phi_h``
    in the tangent frame; ``g = 1 / (4 pi sqrt(cos th_i cos th_o))``; ``kd``: the
    diffuse term's ``1 / pi`` (a float when every sample is above the horizon, else an
    array that is 0 below it, where ``sx, sy, g`` are 0 too)."""

    sx: np.ndarray
    sy: np.ndarray
    g: np.ndarray
    kd: float | np.ndarray
    shape: tuple = ()

    def take(self, idx) -> WardGeometry:
        kd = self.kd[idx] if isinstance(self.kd, np.ndarray) else self.kd
        sx = self.sx[idx]
        return WardGeometry(sx, self.sy[idx], self.g[idx], kd, sx.shape)

    def __len__(self) -> int:
        return int(self.sx.size)


def _geometry(ci, co, sx, sy, shape) -> WardGeometry:
    valid = (ci > 0) & (co > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = 1.0 / (4 * np.pi * np.sqrt(np.where(valid, ci * co, 1.0)))
    if valid.all():
        return WardGeometry(sx, sy, g, 1.0 / np.pi, shape)
    return WardGeometry(np.where(valid, sx, 0.0), np.where(valid, sy, 0.0), np.where(valid, g, 0.0),
                        np.where(valid, 1.0 / np.pi, 0.0), shape)


def ward_geometry(theta_in, theta_out, theta_h, phi_h) -> WardGeometry:
    """:class:`WardGeometry` from the angles of thesis 4.3.5 (radians; arrays broadcast)."""
    ti, to, th, ph = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (theta_in, theta_out, theta_h, phi_h)))
    shape = ti.shape
    ti, to, th, ph = (a.ravel() for a in (ti, to, th, ph))
    t = np.tan(th)
    return _geometry(np.cos(ti), np.cos(to), t * np.cos(ph), t * np.sin(ph), shape)


def ward_geometry_local(wi, wo) -> WardGeometry:
    """:class:`WardGeometry` from unit direction arrays ``(..., 3)`` in the local frame
    (z = normal): ``tan th_h cos phi_h = h_x / h_z``, ``tan th_h sin phi_h = h_y / h_z``."""
    wi, wo = np.broadcast_arrays(np.asarray(wi, dtype=np.float64), np.asarray(wo, dtype=np.float64))
    shape = wi.shape[:-1]
    wi, wo = wi.reshape(-1, 3), wo.reshape(-1, 3)
    h = wi + wo
    with np.errstate(invalid="ignore", divide="ignore"):
        sx, sy = h[:, 0] / h[:, 2], h[:, 1] / h[:, 2]      # the normalisation of h cancels
    return _geometry(wi[:, 2], wo[:, 2], sx, sy, shape)


def _unpack(x, log_alpha: bool):
    """(rho_d, rho_s, alpha_x, alpha_y, rot, 1/ax^2, 1/ay^2, 1/(ax ay)) of a
    :class:`WardParams` or a vector (with ``log_alpha``: ``ln alpha_x, ln alpha_y``)."""
    if isinstance(x, WardParams):
        x = (x.rho_d, x.rho_s, x.alpha_x, x.alpha_y, x.lobe_rotation)
    rho_d, rho_s, a, b, rot = (float(v) for v in x)
    if log_alpha:
        return rho_d, rho_s, math.exp(a), math.exp(b), rot, math.exp(-2 * a), math.exp(-2 * b), math.exp(-a - b)
    return rho_d, rho_s, a, b, rot, 1.0 / (a * a), 1.0 / (b * b), 1.0 / (a * b)


def lobe_slopes(geom: WardGeometry, lobe_rotation: float):
    """``(u, v) = tan th_h (cos a_n, sin a_n)``, ``a_n = phi_h + lobe_rotation`` (eq. 4.80):
    the half vector's slopes along the lobe's axes (the tangent turned by -lobe_rotation)."""
    c, s = math.cos(lobe_rotation), math.sin(lobe_rotation)
    u = geom.sx * c
    u -= geom.sy * s
    v = geom.sx * s
    v += geom.sy * c
    return u, v


def ward_parts(geom: WardGeometry, x, *, log_alpha: bool = False):
    """Eq. 4.79 at ``x`` (a :class:`WardParams`, or ``(rho_d, rho_s, alpha_x, alpha_y,
    lobe_rotation)``; with ``log_alpha`` the alphas are given as their logarithms).
    Returns ``(f, parts)``: the flat values and the pieces :func:`ward_param_jacobian`
    reuses (``u, v`` of :func:`lobe_slopes` and the unit lobe ``g exp(-q) / (ax ay)``)."""
    rho_d, rho_s, ax, ay, rot, ix2, iy2, iaxy = _unpack(x, log_alpha)
    u, v = lobe_slopes(geom, rot)
    q = u * u
    q *= ix2
    q += (v * v) * iy2
    np.minimum(q, EXPONENT_CAP, out=q)
    np.negative(q, out=q)
    base = np.exp(q, out=q)
    base *= geom.g
    base *= iaxy                            # g exp(-q) / (ax ay): the lobe per unit rho_s
    f = base * rho_s
    f += rho_d * geom.kd
    return f, (u, v, base)


def ward_param_jacobian(geom: WardGeometry, x, parts=None, *, log_alpha: bool = False) -> np.ndarray:
    """Fortran-ordered ``(n, 5)`` derivatives of eq. 4.79 by ``(rho_d, rho_s, alpha_x,
    alpha_y, lobe_rotation)`` (with ``log_alpha``: by ``ln alpha_x, ln alpha_y``),
    reusing ``parts`` of :func:`ward_parts` at the same ``x`` when given. With S the
    specular term and ``u, v`` of :func:`lobe_slopes`:

        df/drho_d = 1/pi,  df/drho_s = S / rho_s,
        df/dln ax = S (2 u^2 / ax^2 - 1),   df/dax = df/dln ax / ax,
        df/dln ay = S (2 v^2 / ay^2 - 1),   df/day = df/dln ay / ay,
        df/drot   = 2 S u v (1/ax^2 - 1/ay^2)   (= S tan^2 th_h sin 2a_n (1/ax^2 - 1/ay^2)).

    0 below the horizon. Columns contiguous: cheap to fill, and what LAPACK wants."""
    rho_d, rho_s, ax, ay, rot, ix2, iy2, iaxy = _unpack(x, log_alpha)
    if parts is None:
        _, parts = ward_parts(geom, x, log_alpha=log_alpha)
    u, v, base = parts
    JT = np.empty((5, base.size))
    JT[0] = geom.kd
    JT[1] = base
    S = base * rho_s
    r = JT[2]
    np.multiply(u, u, out=r)
    r *= 2 * ix2
    r -= 1.0
    r *= S
    r = JT[3]
    np.multiply(v, v, out=r)
    r *= 2 * iy2
    r -= 1.0
    r *= S
    r = JT[4]
    np.multiply(u, v, out=r)
    r *= S
    r *= 2 * (ix2 - iy2)
    if not log_alpha:
        JT[2] /= ax
        JT[3] /= ay
    return JT.T


def ward_eval(geom: WardGeometry, x, *, jac: bool = False, log_alpha: bool = False):
    """Eq. 4.79 at ``x`` (see :func:`ward_parts`) in the callers' shape, and with ``jac``
    its flat ``(n, 5)`` Jacobian (:func:`ward_param_jacobian`)."""
    f, parts = ward_parts(geom, x, log_alpha=log_alpha)
    if not jac:
        return f.reshape(geom.shape)
    return f.reshape(geom.shape), ward_param_jacobian(geom, x, parts, log_alpha=log_alpha)


def ward_unit_lobes(geom: WardGeometry, alpha_x, alpha_y, lobe_rotation: float) -> np.ndarray:
    """``(k, n)`` specular lobes per unit rho_s, ``g exp(-q) / (ax ay)``, of ``k`` lobe
    shapes ``(alpha_x[j], alpha_y[j])`` at one rotation (the fit's start grid)."""
    ax, ay = np.asarray(alpha_x, float), np.asarray(alpha_y, float)
    u, v = lobe_slopes(geom, lobe_rotation)
    u *= u
    v *= v
    Q = np.multiply.outer(1 / ax ** 2, u)
    Q += np.multiply.outer(1 / ay ** 2, v)
    np.minimum(Q, EXPONENT_CAP, out=Q)
    np.negative(Q, out=Q)
    np.exp(Q, out=Q)
    Q *= geom.g
    Q *= (1 / (ax * ay))[:, None]
    return Q


def ward_envelope(geom: WardGeometry, p: WardParams) -> np.ndarray:
    """The largest specular term of ``p`` over every lobe rotation (the lobe turned so
    that its widest axis points at each sample): ``rho_s g exp(-tan^2 th_h / amax^2) /
    (ax ay)``, ``amax = max(ax, ay)``; same guards as :func:`ward_parts`."""
    amax = max(p.alpha_x, p.alpha_y)
    q = np.minimum((geom.sx ** 2 + geom.sy ** 2) / amax ** 2, EXPONENT_CAP)
    return (p.rho_s / (p.alpha_x * p.alpha_y) * geom.g * np.exp(-q)).reshape(geom.shape)


def ward_from_angles(theta_in, theta_out, theta_h, phi_h, p: WardParams):
    """Eq. 4.79 from the angles (radians); arrays broadcast. Zero below the horizon."""
    return ward_eval(ward_geometry(theta_in, theta_out, theta_h, phi_h), p)


def ward_local(wi, wo, p: WardParams):
    """Eq. 4.79 for unit direction arrays ``(..., 3)`` in the local frame (z = normal)."""
    return ward_eval(ward_geometry_local(wi, wo), p)


def ward_albedo(p: WardParams, theta_out: float, n: int = 400_000, seed: int = 0) -> float:
    """Directional albedo int f cos(th_i) dw_i at outgoing zenith ``theta_out`` (thesis eq. 2.4),
    by cosine-weighted Monte Carlo (estimate = mean(f) * pi)."""
    rng = np.random.default_rng(seed)
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    wi = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(0.0, 1 - u1))], axis=-1)
    wo = np.array([math.sin(theta_out), 0.0, math.cos(theta_out)])
    return float(np.mean(ward_local(wi, wo, p)) * np.pi)
