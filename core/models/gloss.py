"""Gloss as industry measures it: specular gloss units, haze and DOI from a BRDF (issue 17).

Specular gloss (ISO 2813:2014, ASTM D523-14)
--------------------------------------------
A glossmeter lights the sample through a collimating lens from a source aperture
at angle theta from the normal and collects, through a second lens, the flux that
falls into a receptor aperture centred on the mirror direction (the same angle on
the other side, in the plane of incidence). Its reading is the ratio of that flux
to the flux from the *primary standard*, highly polished black glass of refractive
index n = 1.567 (ASTM D523: at the sodium D line, 589.3 nm; ISO 2813: at 587.6 nm;
the difference is immaterial here), which is assigned 100 gloss units (GU) at each
angle. The apertures are the angular sizes of the source image and of the receptor
field, in and perpendicular to the plane of incidence (full angles, ASTM D523
Table 1 / ISO 2813 Table 1; tolerances omitted)::

    geometry   source image (in x perp)   receptor field (in x perp)
    20 deg     0.75 x 2.5 deg             1.80 x 3.6 deg
    60 deg     0.75 x 2.5 deg             4.4  x 11.7 deg
    85 deg     0.75 x 2.5 deg             4.0  x 6.0 deg

(values as this module's author knows the standards; no copy of either standard
was at hand to check them against.)

The instrument is modelled as the radiometry of those optics: each point (p, q) of
an aperture in a lens's focal plane is one direction, ``normalize(axis + p e_in +
q e_perp)`` (gnomonic coordinates, ``|p| <= tan(in/2)``, ``|q| <= tan(perp/2)``,
``d omega = dp dq / (1 + p^2 + q^2)^(3/2)``); the source has uniform radiance over
its aperture. The instrument's reflectance of a sample of BRDF f is then::

    R = int_src int_rec f(wi, wo) cos(theta_o) dw_o cos(theta_i) dw_i
        / int_src cos(theta_i) dw_i

(the flux into the receptor over the flux the source puts on the sample), and

    GU(theta) = 100 R_sample(theta) / R_glass(theta),

with ``R_glass`` the same integral for a perfect mirror of the standard's glass:
every source direction is mirrored into the receptor (the source image is smaller
than the receptor field at each angle), so ``R_glass`` is the unpolarised Fresnel
reflectance of n = 1.567 (Born & Wolf, Principles of Optics, sec. 1.5.2) averaged
over the source aperture with weight cos(theta_i) dw_i. Spectral weighting
(CIE illuminant C and V(lambda) in the standards) is not modelled: the BRDF is the
fit of the luminance channel (Rec. 709 Y), and the standard's dispersion is ignored.
Assumptions beyond the standards: the plane of incidence lies at ``azimuth_deg``
in the sample's tangent frame (0 = the plane containing the tangent x of thesis
4.3.5), which matters for anisotropic lobes; an instrument's vignetting and
finite illuminated area are not modelled.

Integration: Gauss-Legendre over the source aperture; over the receptor, for each
source direction, Gauss-Legendre in a sinh-stretched coordinate ``u = c + s
sinh(t)`` centred on that direction's mirror image ``c`` with the lobe's width
``s``, so that lobes far narrower than the aperture (alpha down to 1e-4, the fit's
lower bound) and lobes far wider (Lambertian) are both integrated accurately with
the same number of nodes.

Haze and distinctness of image (ASTM E430-11 / ISO 13803)
--------------------------------------------------------
ASTM E430 ("abridged goniophotometry", after Tingle and Hunter) measures at 30 deg
incidence the specular reflectance ``Rs`` and the reflectances in the plane of
incidence at 0.3 deg and 2.0 deg from the specular direction (``R0.3``, ``R2``;
some instruments also 5 deg, ``R5``), and defines

    DOI  = 100 (Rs - R0.3) / Rs         (distinctness-of-image gloss)
    haze = 100 R2 / Rs                  (narrow-angle reflection haze, percent of specular)

both of which are computed here with the instrument model above. The apertures
of E430's instruments are NOT taken from the standard (not at hand): this module
assumes a source image of 0.1 deg (in plane) x 1.0 deg (perpendicular) and
receptors of 0.2 x 2.0 deg, centred at 0, 0.3, 2.0 and 5.0 deg from specular,
away from the normal. With these a perfect mirror reads DOI = 100 and haze = 0
exactly (the 0.3 deg receptor, 0.2 to 0.4 deg, clears the mirror image of the
source, within 0.05 deg), and a Lambertian surface DOI ~ 0 and haze ~ 100. The
receptor is twice the source, as in D523, so that the mirror image of the source
lies inside the specular receptor with a margin (also what keeps the quadrature
over the source accurate for lobes narrower than the apertures). ISO 13803's 20 deg
haze and its logarithmic haze units (BYK's HU) are a different scale and are not
computed. ASTM D4039's haze index
``G60 - G20`` is reported in ``detail`` (it rests on the extrapolated 60 deg gloss).

What a rig fit can say (the extrapolation)
------------------------------------------
The rig sees theta_d only from about 7 to 27 deg (:data:`RIG_THETA_D_RANGE_DEG`),
so the fitted ``rho_s`` holds the sample's Fresnel reflectance at those angles
and the lobe's behaviour towards grazing is not measured. 20 deg gloss (theta_d =
20 deg) lies inside that range; 60 and 85 deg gloss, and E430's 30 deg, do not,
and are marked ``extrapolated``. Their spread is given over four candidate models
that agree with the fitted Ward lobe where the rig sees it:

* ``ward``: the fitted extended Ward model as it is (thesis eq. 4.79-4.80,
  :func:`glossrig.core.models.ward.ward_from_angles`). This is the central value: it is
  the model the fit, the exports and the renders use. Note that Ward's
  normalisation ``1 / sqrt(cos_i cos_o)`` makes a narrow lobe's albedo fall as
  ``rho_s cos(theta_i)`` (Duer, "An improved normalization for the Ward
  reflectance model", JGT 2006), so its 85 deg gloss is low.
* ``ward_fresnel``: the Ward lobe times ``F(theta_d) / F(theta_d_ref)``, the exact
  unpolarised dielectric Fresnel reflectance for an assumed refractive index
  ``n_material`` (default 1.5, typical of coatings and polymers), normalised to 1
  at the rig's mean theta_d (:data:`RIG_THETA_D_MEAN_DEG`), so that it matches the
  data where the rig sees them (within the factor's few-percent change over
  7-27 deg) and only the extrapolation differs.
* ``ggx``: a GGX (Trowbridge-Reitz) microfacet lobe with height-correlated Smith
  masking, :func:`glossrig.core.diagnose.material_models.ggx_lobe` (Walter et al.
  2007; Heitz 2014), whose ``rho_s, alpha_x, alpha_y`` are fitted to the Ward
  lobe's values by least squares over the rig's range (:func:`ggx_from_ward`:
  theta_d in the rig's range, half vectors on an elliptical grid out to 3 lobe
  widths; lobe rotation kept), no Fresnel factor.
* ``ggx_fresnel``: that GGX lobe times the same normalised Fresnel factor (the GGX
  parameters are not refitted: the factor is within a few percent of 1 on the
  rig's range).

Every model keeps the fitted diffuse term ``rho_d / pi``. The absolute scale of
``rho_d, rho_s`` is the rig's: relative to the white reference taken as
Lambertian of albedo 0.8 (thesis eq. 4.78).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.models.ward import WardParams, ward_from_angles

#: refractive index of the primary standard, polished black glass (ISO 2813, ASTM D523)
GLASS_N = 1.567
#: theta_d the thesis rig sees (degrees): min and max over the nominal samples of the
#: thesis rig (``nominal_samples(rig, middle-row LEDs, rotations -45/0/45/90 deg)``:
#: 6.7 to 27.0 deg, checked in tests/test_gloss.py)
RIG_THETA_D_RANGE_DEG = (6.7, 27.0)
#: their mean (16.96 deg over the same samples), where the Fresnel factor of the
#: candidate models is normalised to 1
RIG_THETA_D_MEAN_DEG = 17.0
#: assumed refractive index of the measured material for the Fresnel candidates
MATERIAL_N = 1.5

MODELS = ("ward", "ward_fresnel", "ggx", "ggx_fresnel")
CENTRAL_MODEL = "ward"


@dataclass(frozen=True)
class Aperture:
    """Full angular size of a source image or receptor field (degrees)."""

    in_plane_deg: float
    perpendicular_deg: float

    def half_tan(self) -> tuple[float, float]:
        return math.tan(math.radians(self.in_plane_deg) / 2), math.tan(math.radians(self.perpendicular_deg) / 2)

    def solid_angle(self) -> float:
        """Solid angle of the rectangular field: ``4 asin(sin a sin b)`` with a, b the half-angles
        of the gnomonic rectangle (the exact solid angle of a rectangular pyramid)."""
        a, b = (math.atan(x) for x in self.half_tan())
        return 4 * math.asin(math.sin(a) * math.sin(b))


@dataclass(frozen=True)
class Geometry:
    """One instrument geometry: incidence angle, source, receptor, and the receptor's
    offset from the specular direction in the plane of incidence (away from the normal)."""

    name: str
    theta_deg: float
    source: Aperture
    receptor: Aperture
    offset_deg: float = 0.0


D523_SOURCE = Aperture(0.75, 2.5)
#: ISO 2813 / ASTM D523 geometries (see the module docstring for the values' source)
GLOSS_GEOMETRIES = {
    "gu20": Geometry("gu20", 20.0, D523_SOURCE, Aperture(1.80, 3.6)),
    "gu60": Geometry("gu60", 60.0, D523_SOURCE, Aperture(4.4, 11.7)),
    "gu85": Geometry("gu85", 85.0, D523_SOURCE, Aperture(4.0, 6.0)),
}
#: ASTM E430 at 30 deg: definitions from the standard, apertures assumed (module docstring)
E430_SOURCE = Aperture(0.1, 1.0)
E430_RECEPTOR = Aperture(0.2, 2.0)
E430_GEOMETRIES = {
    "Rs": Geometry("Rs", 30.0, E430_SOURCE, E430_RECEPTOR, 0.0),
    "R0.3": Geometry("R0.3", 30.0, E430_SOURCE, E430_RECEPTOR, 0.3),
    "R2": Geometry("R2", 30.0, E430_SOURCE, E430_RECEPTOR, 2.0),
    "R5": Geometry("R5", 30.0, E430_SOURCE, E430_RECEPTOR, 5.0),
}

ASSUMPTIONS = (
    "Specular gloss per ISO 2813 / ASTM D523 (20, 60, 85 deg; source 0.75 x 2.5 deg; receptors 1.8 x 3.6, "
    "4.4 x 11.7, 4.0 x 6.0 deg), computed from the fitted luminance BRDF by integrating it over the source "
    "and receptor apertures, relative to a perfect mirror of black glass n = 1.567 (= 100 GU). "
    "Haze = 100 R2/Rs and DOI = 100 (Rs - R0.3)/Rs per ASTM E430 at 30 deg, with assumed apertures "
    "(source 0.1 x 1.0 deg, receptors 0.2 x 2.0 deg; not from the standard). The rig sees theta_d only from about 7 to 27 deg: 60 and 85 deg "
    "gloss and the 30 deg haze/DOI are extrapolations of the fitted model (flagged 'extrapolated'); 'spread' "
    "gives them for Ward and GGX lobes, each without and with a dielectric Fresnel factor (n = {n:g}) "
    "normalised to 1 at theta_d = {td:g} deg; the top-level value is the fitted Ward model's. Plane of "
    "incidence at azimuth {az:g} deg in the sample's tangent frame. Absolute scale from the white reference "
    "taken as Lambertian of albedo 0.8 (thesis eq. 4.78).")


# ----------------------------------------------------------------------------- Fresnel

def fresnel_dielectric(cos_i, n: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance ``(Rs + Rp) / 2`` of a dielectric of refractive index
    ``n`` (from air) at incidence cosine ``cos_i`` (Born & Wolf, sec. 1.5.2)."""
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    s2 = 1.0 - c * c
    ct = np.sqrt(np.maximum(0.0, 1.0 - s2 / (n * n)))
    rs = (c - n * ct) / (c + n * ct)
    rp = (n * c - ct) / (n * c + ct)
    return 0.5 * (rs * rs + rp * rp)


def fresnel_factor(theta_d, n: float = MATERIAL_N, theta_d_ref_deg: float = RIG_THETA_D_MEAN_DEG):
    """``F(theta_d) / F(theta_d_ref)`` (:func:`fresnel_dielectric`): 1 at the rig's mean theta_d."""
    return fresnel_dielectric(np.cos(theta_d), n) / float(fresnel_dielectric(math.cos(math.radians(theta_d_ref_deg)), n))


# ----------------------------------------------------------------------------- quadrature

def _gl(n: int):
    x, w = np.polynomial.legendre.leggauss(n)
    return x, w


def _stretched_nodes(A: float, c: np.ndarray, s: float | None, n: int):
    """Nodes and weights on [-A, A] for integrands peaked at ``c`` (shape (N,)) with width ``s``:
    Gauss-Legendre in t with ``u = c + s sinh(t)``; plain Gauss-Legendre when ``s`` is None."""
    x, w = _gl(n)
    c = np.asarray(c, dtype=np.float64)[:, None]
    if s is None or s >= A:
        u = np.broadcast_to(A * x, (c.shape[0], n))
        return u, np.broadcast_to(A * w, (c.shape[0], n))
    lo, hi = np.arcsinh((-A - c) / s), np.arcsinh((A - c) / s)
    t = 0.5 * (hi + lo) + 0.5 * (hi - lo) * x
    u = c + s * np.sinh(t)
    return u, s * np.cosh(t) * 0.5 * (hi - lo) * w


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _zen_az(v):
    """Zenith (by atan2: full precision near the normal, where tan(theta_h) ~ alpha ~ 1e-4
    matters) and azimuth in [0, 2 pi) of direction arrays in the local frame."""
    return np.arctan2(np.hypot(v[..., 0], v[..., 1]), v[..., 2]), np.mod(np.arctan2(v[..., 1], v[..., 0]), 2 * np.pi)


@dataclass
class _Nodes:
    """Quadrature of one geometry: ``angles`` of shape (Ns, Nr, Nr); ``w_rec`` holds
    ``cos(theta_o) dw_o``, ``w_src`` (Ns,) ``cos(theta_i) dw_i``, normalised to sum 1."""

    angles: dict
    w_rec: np.ndarray
    w_src: np.ndarray
    cos_i: np.ndarray
    mirror_inside: np.ndarray

    def integrate(self, f) -> float:
        """Instrument reflectance of BRDF values ``f`` (shape of the angles)."""
        return float(np.sum(self.w_src * np.sum(self.w_rec * f, axis=(1, 2))))


def _nodes(g: Geometry, azimuth: float, width: float | None, n_src: int = 5, n_rec: int = 32) -> _Nodes:
    th, tho = math.radians(g.theta_deg), math.radians(g.theta_deg + g.offset_deg)
    ep = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    es = np.array([-math.sin(azimuth), math.cos(azimuth), 0.0])
    z = np.array([0.0, 0.0, 1.0])
    wi0, ti = -math.sin(th) * ep + math.cos(th) * z, math.cos(th) * ep + math.sin(th) * z
    wo0, to = math.sin(tho) * ep + math.cos(tho) * z, math.cos(tho) * ep - math.sin(tho) * z
    # source: Gauss-Legendre over the gnomonic rectangle
    a, b = g.source.half_tan()
    x, w = _gl(n_src)
    P, Q = np.meshgrid(a * x, b * x, indexing="ij")
    W = np.outer(a * w, b * w)
    P, Q, W = P.ravel(), Q.ravel(), W.ravel()
    wi = _unit(wi0 + P[:, None] * ti + Q[:, None] * es)
    w_src = W / (1 + P * P + Q * Q) ** 1.5 * wi[:, 2]
    # the mirror image of each source direction, in the receptor's gnomonic coordinates
    m = wi * np.array([-1.0, -1.0, 1.0])
    mz = m @ wo0
    cp, cq = (m @ to) / mz, (m @ es) / mz
    A, B = g.receptor.half_tan()
    sp = None if width is None else 2.0 * width
    sq = None if width is None else 2.0 * width * math.cos(th)
    up, wp = _stretched_nodes(A, cp, sp, n_rec)
    uq, wq = _stretched_nodes(B, cq, sq, n_rec)
    U, V = up[:, :, None], uq[:, None, :]
    wo = _unit(wo0 + U[..., None] * to + V[..., None] * es)
    w_rec = wp[:, :, None] * wq[:, None, :] / (1 + U * U + V * V) ** 1.5 * wo[..., 2]
    wib = np.broadcast_to(wi[:, None, None, :], wo.shape)
    h = _unit(wib + wo)

    ang = {}
    ti_, pi_ = _zen_az(wi)
    ang["theta_in"] = np.broadcast_to(ti_[:, None, None], wo.shape[:-1])
    ang["phi_in"] = np.broadcast_to(pi_[:, None, None], wo.shape[:-1])
    ang["theta_out"], ang["phi_out"] = _zen_az(wo)
    ang["theta_h"], ang["phi_h"] = _zen_az(h)
    ang["theta_d"] = np.arccos(np.clip(np.sum(wib * h, axis=-1), -1.0, 1.0))
    total = w_src.sum()
    inside = (np.abs(cp) <= A) & (np.abs(cq) <= B)
    return _Nodes(ang, w_rec, w_src / total, wi[:, 2], inside)


def instrument_reflectance(g: Geometry, brdf=None, *, width: float | None = None, mirror=None,
                           azimuth_deg: float = 0.0, n_src: int = 5, n_rec: int = 32) -> float:
    """The reflectance an instrument of geometry ``g`` reads (module docstring).

    ``brdf(angles) -> values``: a BRDF of the angle dict (``theta_in, phi_in, theta_out,
    phi_out, theta_h, phi_h, theta_d``, radians, tangent frame); ``width``: its lobe's
    width (radians, e.g. the smaller alpha; None for a smooth BRDF); ``mirror(cos_i) ->
    reflectance``: an ideal specular (delta) component, integrated exactly."""
    nd = _nodes(g, math.radians(azimuth_deg), width, n_src, n_rec)
    r = 0.0 if brdf is None else nd.integrate(brdf(nd.angles))
    if mirror is not None:
        r += float(np.sum(nd.w_src * np.asarray(mirror(nd.cos_i), float) * nd.mirror_inside))
    return r


def _glass(cos_i):
    return fresnel_dielectric(cos_i, GLASS_N)


def standard_reflectance(g: Geometry) -> float:
    """The instrument's reading of the primary standard (a perfect mirror of glass n = 1.567):
    the source-averaged Fresnel reflectance; the standards assign it 100 GU."""
    return instrument_reflectance(g, mirror=_glass)


def gloss_units(g: Geometry, brdf=None, **kw) -> float:
    """``100 R_sample / R_glass`` for geometry ``g`` (keywords of :func:`instrument_reflectance`)."""
    return 100.0 * instrument_reflectance(g, brdf, **kw) / standard_reflectance(g)


def e430(brdf=None, **kw) -> dict:
    """ASTM E430's ``doi = 100 (Rs - R0.3)/Rs``, ``haze = 100 R2/Rs`` (and ``haze_5deg``, with R5)
    at 30 deg; ``None`` where ``Rs`` is 0 (a black surface has neither)."""
    R = {k: instrument_reflectance(g, brdf, **kw) for k, g in E430_GEOMETRIES.items()}
    return _e430_values(R)


def _e430_values(R: dict) -> dict:
    rs = R["Rs"]
    if not rs > 0:
        return {"haze": None, "doi": None, "haze_5deg": None}
    return {"haze": 100.0 * R["R2"] / rs, "doi": 100.0 * (rs - R["R0.3"]) / rs, "haze_5deg": 100.0 * R["R5"] / rs}


# ----------------------------------------------------------------------------- GGX from Ward

def _rig_directions(p: WardParams, n_r: int = 9, n_beta: int = 12, n_td: int = 3, n_pd: int = 6,
                    theta_d_range_deg: tuple[float, float] = RIG_THETA_D_RANGE_DEG):
    """Angle dict of direction pairs in the rig's range: half vectors on an elliptical polar
    grid in the lobe's axes out to 3 widths (tan theta_h = r alpha along each axis), theta_d
    over the rig's range, every phi_d; pairs with a direction below the horizon dropped."""
    r = np.linspace(0.0, 3.0, n_r)
    beta = np.linspace(0.0, 2 * np.pi, n_beta, endpoint=False)
    R, Bt = np.meshgrid(r, beta, indexing="ij")
    lx, ly = p.alpha_x * R * np.cos(Bt), p.alpha_y * R * np.sin(Bt)
    # lobe axes: a_n = phi_h + rot, so the lobe's x axis lies at phi_h = -rot
    c, s = math.cos(-p.lobe_rotation), math.sin(-p.lobe_rotation)
    tx, ty = (c * lx - s * ly).ravel(), (s * lx + c * ly).ravel()
    h = _unit(np.stack([tx, ty, np.ones_like(tx)], axis=-1))
    td = np.radians(np.linspace(*theta_d_range_deg, n_td))
    pd = np.linspace(0.0, 2 * np.pi, n_pd, endpoint=False)
    TD, PD = np.meshgrid(td, pd, indexing="ij")
    d = np.stack([np.sin(TD) * np.cos(PD), np.sin(TD) * np.sin(PD), np.cos(TD)], axis=-1).reshape(-1, 3)
    # rotate d from the half vector's frame (h = pole) to the local frame: Rz(phi_h) Ry(theta_h)
    th = np.arctan2(np.hypot(h[:, 0], h[:, 1]), h[:, 2])
    ph = np.arctan2(h[:, 1], h[:, 0])
    ct, st, cph, sph = np.cos(th)[:, None], np.sin(th)[:, None], np.cos(ph)[:, None], np.sin(ph)[:, None]
    x1 = ct * d[None, :, 0] + st * d[None, :, 2]
    z1 = -st * d[None, :, 0] + ct * d[None, :, 2]
    y1 = np.broadcast_to(d[None, :, 1], x1.shape)
    wi = np.stack([cph * x1 - sph * y1, sph * x1 + cph * y1, z1], axis=-1).reshape(-1, 3)
    hh = np.repeat(h, d.shape[0], axis=0)
    wo = 2 * np.sum(wi * hh, axis=-1, keepdims=True) * hh - wi
    ok = (wi[:, 2] > 1e-6) & (wo[:, 2] > 1e-6)
    wi, wo, hh = wi[ok], wo[ok], hh[ok]

    a = {}
    a["theta_in"], a["phi_in"] = _zen_az(wi)
    a["theta_out"], a["phi_out"] = _zen_az(wo)
    a["theta_h"], a["phi_h"] = _zen_az(hh)
    a["theta_d"] = np.arccos(np.clip(np.sum(wi * hh, axis=-1), -1, 1))
    return a


def _ward_lobe(a: dict, p: WardParams):
    """The fitted Ward lobe alone (rho_d = 0) through the project's one evaluation of eq. 4.79."""
    lobe = WardParams(0.0, p.rho_s, p.alpha_x, p.alpha_y, p.lobe_rotation)
    return ward_from_angles(a["theta_in"], a["theta_out"], a["theta_h"], a["phi_h"], lobe)


def _ggx_lobe(a: dict, ax: float, ay: float, rot: float):
    from glossrig.core.diagnose.material_models import ggx_lobe   # reused; imported here to keep this module light

    return ggx_lobe(a["theta_in"], a["phi_in"], a["theta_out"], a["phi_out"], a["theta_h"], a["phi_h"],
                    a["theta_d"], ax, ay, rot)


def ggx_from_ward(p: WardParams) -> dict:
    """GGX lobe parameters that best reproduce the Ward lobe of ``p`` where the rig sees it.

    Least squares of ``rho_s' L_ggx(alpha_x', alpha_y') - L_ward`` over :func:`_rig_directions`
    (theta_d in the rig's range, half vectors out to three lobe widths), the lobe rotation
    kept, ``rho_s'`` solved linearly for each (alpha_x', alpha_y'), which are fitted in log
    space from Ward's alphas (scipy's trust-region least squares). Returns ``rho_s, alpha_x,
    alpha_y, lobe_rotation`` and ``rel_rms`` (the misfit relative to the Ward lobe's rms)."""
    from scipy.optimize import least_squares

    a = _rig_directions(p)
    y = _ward_lobe(a, WardParams(0.0, 1.0, p.alpha_x, p.alpha_y, p.lobe_rotation))

    def lin(x):
        G = _ggx_lobe(a, math.exp(x[0]), math.exp(x[1]), p.lobe_rotation)
        k = float(G @ y) / max(float(G @ G), 1e-300)
        return G, k

    def res(x):
        G, k = lin(x)
        return k * G - y

    x0 = np.log([p.alpha_x, p.alpha_y])
    lo, hi = math.log(1e-5), math.log(2.0)
    sol = least_squares(res, x0, bounds=([lo, lo], [hi, hi]), x_scale=1.0, xtol=1e-6, ftol=1e-8, max_nfev=60)
    G, k = lin(sol.x)
    rel = float(np.sqrt(np.mean((k * G - y) ** 2)) / max(np.sqrt(np.mean(y * y)), 1e-300))
    return {"rho_s": k * p.rho_s, "alpha_x": float(math.exp(sol.x[0])), "alpha_y": float(math.exp(sol.x[1])),
            "lobe_rotation": float(p.lobe_rotation), "rel_rms": rel}


# ----------------------------------------------------------------------------- the API

def _params(params) -> WardParams:
    if isinstance(params, WardParams):
        return params
    if isinstance(params, dict):
        try:
            return WardParams(**{k: float(params[k]) for k in ("rho_d", "rho_s", "alpha_x", "alpha_y")},
                              lobe_rotation=float(params.get("lobe_rotation", 0.0)))
        except KeyError as e:
            raise InputError(f"gloss: Ward parameters lack {e.args[0]}") from None
        except (TypeError, ValueError) as e:
            raise InputError(f"gloss: Ward parameters are not numbers: {e}") from None
    raise InputError(f"gloss: expected Ward parameters (WardParams or a dict), got {type(params).__name__}")


def _model_readings(nd: _Nodes, p: WardParams, ggx: dict, n_material: float, theta_d_ref_deg: float) -> dict:
    a = nd.angles
    diffuse = p.rho_d / math.pi * nd.integrate(np.ones_like(nd.w_rec))
    F = fresnel_factor(a["theta_d"], n_material, theta_d_ref_deg)
    W = _ward_lobe(a, p)
    G = ggx["rho_s"] * _ggx_lobe(a, ggx["alpha_x"], ggx["alpha_y"], ggx["lobe_rotation"])
    return {"ward": diffuse + nd.integrate(W), "ward_fresnel": diffuse + nd.integrate(W * F),
            "ggx": diffuse + nd.integrate(G), "ggx_fresnel": diffuse + nd.integrate(G * F)}


def _spread(models: dict, extrapolated: bool) -> dict:
    vals = [v for v in models.values() if v is not None]
    return {"value": models[CENTRAL_MODEL], "min": min(vals) if vals else None, "max": max(vals) if vals else None,
            "models": dict(models), "extrapolated": bool(extrapolated)}


def _extrapolated(g: Geometry) -> bool:
    """Whether the geometry's theta_d (the incidence angle at specular) lies outside the rig's range."""
    lo, hi = RIG_THETA_D_RANGE_DEG
    return not lo <= g.theta_deg <= hi


def gloss_from_ward(params, *, azimuth_deg: float = 0.0, n_material: float = MATERIAL_N,
                    theta_d_ref_deg: float = RIG_THETA_D_MEAN_DEG) -> dict:
    """Gloss units at 20, 60, 85 deg, haze and DOI of a fitted extended Ward BRDF.

    ``params``: :class:`WardParams` or a dict with ``rho_d, rho_s, alpha_x, alpha_y[,
    lobe_rotation]`` (the luminance fit). Returns plain JSON::

        {"gu20", "gu60", "gu85", "haze", "doi":   central values (the fitted Ward model), floats
         "spread": {quantity: {"value", "min", "max", "models": {model: value}, "extrapolated"}},
         "assumptions": str, "detail": {...}}

    (module docstring for the standards, the instrument model and the candidate models).
    ``haze`` and ``doi`` are ``None`` for a black surface (``Rs = 0``)."""
    p = _params(params)
    if not (math.isfinite(azimuth_deg) and n_material > 1.0 and 0.0 <= theta_d_ref_deg < 90.0):
        raise InputError(f"gloss: bad options azimuth_deg={azimuth_deg!r}, n_material={n_material!r}, "
                         f"theta_d_ref_deg={theta_d_ref_deg!r}")
    az = math.radians(azimuth_deg)
    ggx = ggx_from_ward(p)
    width = min(p.alpha_x, p.alpha_y)
    spread, std = {}, {}
    for key, g in GLOSS_GEOMETRIES.items():
        nd = _nodes(g, az, width)
        std[key] = float(np.sum(nd.w_src * _glass(nd.cos_i) * nd.mirror_inside))   # = standard_reflectance(g)
        R = _model_readings(nd, p, ggx, n_material, theta_d_ref_deg)
        spread[key] = _spread({m: 100.0 * R[m] / std[key] for m in MODELS}, _extrapolated(g))
    readings = {k: _model_readings(_nodes(g, az, width), p, ggx, n_material, theta_d_ref_deg)
                for k, g in E430_GEOMETRIES.items()}
    per_model = {m: _e430_values({k: readings[k][m] for k in readings}) for m in MODELS}
    for q in ("haze", "doi", "haze_5deg"):
        spread[q] = _spread({m: per_model[m][q] for m in MODELS}, _extrapolated(E430_GEOMETRIES["Rs"]))
    out = {k: spread[k]["value"] for k in ("gu20", "gu60", "gu85", "haze", "doi")}
    out["spread"] = spread
    out["assumptions"] = ASSUMPTIONS.format(n=n_material, td=theta_d_ref_deg, az=azimuth_deg)
    out["detail"] = {
        "central_model": CENTRAL_MODEL,
        "standard": {"glass_n": GLASS_N, "reflectance": std},
        "geometries": {k: {"theta_deg": g.theta_deg, "source_deg": [g.source.in_plane_deg, g.source.perpendicular_deg],
                           "receptor_deg": [g.receptor.in_plane_deg, g.receptor.perpendicular_deg],
                           "receptor_offset_deg": g.offset_deg}
                       for k, g in {**GLOSS_GEOMETRIES, **E430_GEOMETRIES}.items()},
        "azimuth_deg": float(azimuth_deg),
        "rig_theta_d_range_deg": list(RIG_THETA_D_RANGE_DEG),
        "fresnel": {"n_material": float(n_material), "theta_d_ref_deg": float(theta_d_ref_deg)},
        "ggx": ggx,
        "haze_d4039": {m: spread["gu60"]["models"][m] - spread["gu20"]["models"][m] for m in MODELS},
    }
    return out
