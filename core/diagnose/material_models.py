"""Material extensions of the thesis's model, and the reference renormalisation (issues 7 and 14).

The thesis measures a BRDF as ``f = (albedo / pi) S / R`` with a Lambertian white
reference of albedo 0.8 (eq. 4.78) and fits the extended Ward lobe (eq. 4.79-4.80).
The named departures from that model, each a parameterised extension:

* **Non-Lambertian reference** (:func:`renormalise`). Real white paper is neither
  Lambertian nor of albedo 0.8. The reference pixel records ``R ~ f_ref(wi, wo)
  cos(theta_in) E``, so the thesis's division gives ``(albedo/pi) f / f_ref``; with
  the reference's own BRDF ``f_ref`` at each sample's angles the correct value is
  ``f_meas * f_ref * pi / albedo`` (per colour channel). ``glossrig diagnose`` applies it as a
  calibration step when the reference's BRDF is supplied
  (:func:`glossrig.core.diagnose.data.renormalise_table`), never as a verdict (issue 14, item 4).
* **Lobe shape** (:func:`ggx_lobe`). Ward's lobe is a Beckmann-like Gaussian in
  tan(theta_h); measured materials have the long tails of the Trowbridge-Reitz
  (GGX) distribution (Walter et al., "Microfacet models for refraction through rough
  surfaces", EGSR 2007; anisotropic form and height-correlated Smith masking:
  Heitz, "Understanding the masking-shadowing function in microfacet-based BRDFs",
  JCGT 2014). The lobe is ``D(h) G2(wi, wo) / (4 cos theta_in cos theta_out)`` with
  the anisotropy axes turned exactly as in Ward's eq. 4.80 (``a_n = phi_h + rot``),
  so that ``(alpha_x, alpha_y, lobe_rotation)`` keep their meaning.
* **Grazing term** (:func:`grazing_factor`). The Lambertian diffuse term times Burley's
  reciprocal grazing factor (Burley, "Physically-Based Shading at Disney", SIGGRAPH 2012
  course notes): a diffuse reflection that rises (rough surfaces) or falls (smooth coatings)
  toward grazing incidence and viewing.
* **Fresnel** (:func:`schlick_ratio`). The lobe times ``F(theta_d) / F(0)`` with
  Schlick's approximation ``F = F0 + (1 - F0)(1 - cos theta_d)^5``, ``F0 = ((n-1)/(n+1))^2``
  (Schlick, "An inexpensive BRDF model for physically-based rendering", CGF 1994;
  Cook & Torrance 1982). The rig sees theta_d < ~30 deg, where the factor changes by
  < 1 % for n = 1.5: expected to be unidentifiable from its data.

:func:`fit_lobe` fits ``rho_d / pi + rho_s * lobe`` with the objective of
``glossrig fit`` (eq. 4.81-4.82, :func:`glossrig.core.fitting.fit.peak_weight`), rho_d and
rho_s solved linearly (variable projection) and the lobe's shape by trust-region
least squares. :func:`material_causes` registers the material causes (lobe shapes, grazing
term) in the diagnose catalogue. The reference's own BRDF is no cause: with it supplied,
diagnose renormalises the data with :func:`renormalise` before it tests any cause
(``glossrig diagnose --reference-brdf``, report.json ``meta.reference_calibration``).
"""
from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from glossrig.core.fitting.fit import lobe_albedos
from glossrig.core.models.ward import WardParams, ward_from_angles

ANGLES = ("theta_in", "phi_in", "theta_out", "phi_out", "theta_h", "phi_h", "theta_d")


# ------------------------------------------------------------------ models

def _axes_quadratic(phi, rot, ax, ay):
    """cos^2(phi + rot) / ax^2 + sin^2(phi + rot) / ay^2 (Ward's eq. 4.80 convention)."""
    a = phi + rot
    return np.cos(a) ** 2 / ax ** 2 + np.sin(a) ** 2 / ay ** 2


def ggx_ndf(theta_h, phi_h, ax, ay, rot=0.0):
    """Anisotropic GGX normal distribution D(h), normalised: int D cos(theta_h) dw_h = 1."""
    c = np.cos(theta_h)
    t2 = np.tan(theta_h) ** 2
    q = 1.0 + t2 * _axes_quadratic(phi_h, rot, ax, ay)
    return 1.0 / (np.pi * ax * ay * c ** 4 * q ** 2)


def smith_lambda(theta, phi, ax, ay, rot=0.0):
    """Smith's Lambda of GGX for a direction (theta, phi); the projected roughness
    along the direction's azimuth is ``1 / sqrt(quadratic)`` (Heitz 2014, eq. 80)."""
    a2 = 1.0 / _axes_quadratic(phi, rot, ax, ay)
    return 0.5 * (np.sqrt(1.0 + a2 * np.tan(theta) ** 2) - 1.0)


def schlick_ratio(theta_d, n):
    """F(theta_d) / F(0), Schlick's Fresnel for refractive index n (1 when n is None)."""
    if n is None:
        return 1.0
    f0 = ((n - 1) / (n + 1)) ** 2
    return (f0 + (1 - f0) * (1 - np.cos(theta_d)) ** 5) / f0


def ggx_lobe(theta_in, phi_in, theta_out, phi_out, theta_h, phi_h, theta_d, ax, ay, rot=0.0, n=None):
    """Unit-albedo GGX lobe ``D G2 / (4 cos_i cos_o)`` (times Schlick's F/F0 when n is given);
    zero below the horizon. Angles in radians, arrays broadcast."""
    return _microfacet(ggx_ndf, smith_lambda, theta_in, phi_in, theta_out, phi_out, theta_h, phi_h, theta_d,
                       ax, ay, rot, n)


def _microfacet(ndf, lam, theta_in, phi_in, theta_out, phi_out, theta_h, phi_h, theta_d, ax, ay, rot, n):
    """``D G2 / (4 cos_i cos_o)`` (times F/F0 when n is given) with height-correlated Smith masking
    ``G2 = 1 / (1 + Lambda_i + Lambda_o)`` of the distribution ``ndf`` and its ``lam``."""
    ci, co = np.cos(theta_in), np.cos(theta_out)
    ok = (ci > 0) & (co > 0)
    g2 = 1.0 / (1.0 + lam(theta_in, phi_in, ax, ay, rot) + lam(theta_out, phi_out, ax, ay, rot))
    with np.errstate(divide="ignore", invalid="ignore"):
        L = ndf(theta_h, phi_h, ax, ay, rot) * g2 / (4 * np.where(ok, ci * co, 1.0))
    return np.where(ok, L * schlick_ratio(theta_d, n), 0.0)


def ward_lobe(theta_in, phi_in, theta_out, phi_out, theta_h, phi_h, theta_d, ax, ay, rot=0.0, n=None):
    """Ward's lobe of eq. 4.79 with rho_s = 1, rho_d = 0 (times F/F0 when n is given)."""
    L = ward_from_angles(theta_in, theta_out, theta_h, phi_h, WardParams(0.0, 1.0, ax, ay, rot))
    return L * schlick_ratio(theta_d, n)


def beckmann_ndf(theta_h, phi_h, ax, ay, rot=0.0):
    """Anisotropic Beckmann normal distribution, normalised: int D cos(theta_h) dw_h = 1."""
    c = np.cos(theta_h)
    return np.exp(-np.tan(theta_h) ** 2 * _axes_quadratic(phi_h, rot, ax, ay)) / (np.pi * ax * ay * c ** 4)


def beckmann_lambda(theta, phi, ax, ay, rot=0.0):
    """Smith's Lambda of the Beckmann distribution, Walter et al. (2007) rational fit (eq. 27)
    of ``(erf-based exact form)``, with the projected roughness along the direction's azimuth."""
    alpha = 1.0 / np.sqrt(_axes_quadratic(phi, rot, ax, ay))
    with np.errstate(divide="ignore"):
        a = 1.0 / np.maximum(alpha * np.tan(theta), 1e-12)
    lam = (1 - 1.259 * a + 0.396 * a * a) / (3.535 * a + 2.181 * a * a)
    return np.where(a < 1.6, lam, 0.0)


def beckmann_lobe(theta_in, phi_in, theta_out, phi_out, theta_h, phi_h, theta_d, ax, ay, rot=0.0, n=None):
    """Cook-Torrance lobe with the Beckmann distribution (Cook & Torrance 1982, Walter et al. 2007):
    ``D G2 / (4 cos_i cos_o)``, height-correlated Smith masking (times Schlick's F/F0 when n is given)."""
    return _microfacet(beckmann_ndf, beckmann_lambda, theta_in, phi_in, theta_out, phi_out, theta_h, phi_h, theta_d,
                       ax, ay, rot, n)


LOBES: dict[str, Callable[..., np.ndarray]] = {"ward": ward_lobe, "ggx": ggx_lobe, "beckmann": beckmann_lobe}
#: range of Burley's F_D90 (:func:`grazing_factor`) the grazing_lobe cause searches: from a diffuse term that
#: vanishes at grazing (0) to an eight-fold rise, beyond Burley's 0.5 + 2 roughness (at most 2.5)
GRAZING_F90_RANGE = (0.0, 8.0)


def grazing_factor(theta_in, theta_out, f90):
    """Burley's diffuse factor ``[1 + (F_D90 - 1)(1 - cos theta_in)^5] [1 + (F_D90 - 1)(1 - cos theta_out)^5]``
    (Burley, "Physically-Based Shading at Disney", SIGGRAPH 2012 course notes, sec. 5.3): 1 at
    normal incidence and viewing, F_D90 at grazing on each side; reciprocal. Burley sets
    ``F_D90 = 0.5 + 2 roughness cos^2 theta_d``; here F_D90 is the free parameter."""
    gi = 1.0 + (f90 - 1.0) * (1.0 - np.cos(theta_in)) ** 5
    go = 1.0 + (f90 - 1.0) * (1.0 - np.cos(theta_out)) ** 5
    return gi * go


def renormalise(rgb, reference_rgb, albedo: float = 0.8):
    """Undo the thesis's Lambertian-reference assumption: ``f = f_meas * f_ref * pi / albedo``
    per channel, with the reference's own BRDF ``f_ref`` at the same angles (eq. 4.78 inverted)."""
    return np.asarray(rgb, float) * np.asarray(reference_rgb, float) * np.pi / albedo


# ------------------------------------------------------------------ fitting

@dataclass
class LobeFit:
    kind: str
    rho_d: float
    rho_s: float
    alpha_x: float
    alpha_y: float
    lobe_rotation: float
    n: float | None = None
    stderr: dict = field(default_factory=dict)
    cost: float = float("nan")
    f90: float | None = None        # Burley's grazing factor on the diffuse term (:func:`grazing_factor`)

    def predict(self, a: dict) -> np.ndarray:
        L = LOBES[self.kind](*(a[k] for k in ANGLES), self.alpha_x, self.alpha_y, self.lobe_rotation, self.n)
        d = self.rho_d / np.pi
        if self.f90 is not None:
            d = d * grazing_factor(a["theta_in"], a["theta_out"], self.f90)
        return d + self.rho_s * L

    def as_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("kind", "rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation", "n",
                                           "f90")}
        d["stderr"] = self.stderr
        return d

    @classmethod
    def from_ward(cls, w: WardParams) -> LobeFit:
        return cls("ward", w.rho_d, w.rho_s, w.alpha_x, w.alpha_y, w.lobe_rotation)


def angle_arrays(t) -> dict:
    return {k: np.asarray(t[k], float) for k in ANGLES}


def fit_weights(t) -> np.ndarray:
    """Residual multipliers of ``glossrig fit``: eq. 4.82 (mirror reading) times sqrt(weight column)."""
    from glossrig.core.fitting.fit import peak_weight

    a = angle_arrays(t)
    W = peak_weight(a["theta_in"], a["phi_in"], a["theta_out"], a["phi_out"])
    if "weight" in t:
        W = W * np.sqrt(np.asarray(t["weight"], float))
    return W


def fit_lobe(a: dict, y, W, kind: str = "ggx", start=(0.1, 0.1, 0.0), n=None, fit_n: bool = False,
             uncertainty: bool = True) -> LobeFit:
    """Fit ``rho_d/pi + rho_s * lobe`` to y (weighted by W, as eq. 4.81). The lobe's
    ``ln alpha_x, ln alpha_y, rot`` (and n when ``fit_n``) by trust-region least squares,
    rho_d and rho_s by non-negative linear least squares at each step. Standard errors:
    HC1 sandwich (:func:`glossrig.core.fitting.fit._sandwich`) of all parameters at the optimum."""
    from glossrig.core.fitting.fit import _sandwich

    y, W = np.asarray(y, float), np.asarray(W, float)
    lobe = LOBES[kind]

    def shape(x):
        return np.exp(x[0]), np.exp(x[1]), x[2], (x[3] if fit_n else n)

    def res(x):
        ax, ay, rot, nn = shape(x)
        L = lobe(*(a[k] for k in ANGLES), ax, ay, rot, nn)
        rd, rs, _ = lobe_albedos(L, y, W)
        return W * (rd / np.pi + rs * L - y)

    x0 = [math.log(start[0]), math.log(start[1]), start[2]] + ([1.5] if fit_n else [])
    lb = [math.log(1e-3)] * 2 + [-np.inf] + ([1.05] if fit_n else [])
    ub = [math.log(1.0)] * 2 + [np.inf] + ([4.0] if fit_n else [])
    best = None
    for x_init in (x0, [x0[1], x0[0], x0[2] + math.pi / 2] + x0[3:]):
        # a start from another model's fit may lie outside this lobe's range (on the white paper the
        # Ward fit ends with rho_s ~ 0 and alpha_y = 1e-4, which nothing constrains): start a factor 2
        # inside the range, not on a bound, where the lobe is degenerate (a spike or flat), NNLS sets
        # rho_s = 0 and the gradient in alpha vanishes
        x_start = np.array(x_init, float)
        x_start[:2] = np.clip(x_start[:2], lb[0] + math.log(2), ub[0] - math.log(2))
        if fit_n:
            x_start[3] = min(max(x_start[3], lb[3]), ub[3])
        r = least_squares(res, x_start, bounds=(lb, ub), x_scale=[0.3, 0.3, 0.3] + ([0.3] if fit_n else []))
        if best is None or r.cost < best.cost:
            best = r
    assert best is not None             # the loop ran twice
    ax, ay, rot, nn = shape(best.x)
    if ax < ay:     # canonical form of glossrig fit: alpha_x >= alpha_y, rotation in [0, pi)
        ax, ay, rot = ay, ax, rot + np.pi / 2
    rot = float(np.mod(rot, np.pi))
    L = lobe(*(a[k] for k in ANGLES), ax, ay, rot, nn)
    rd, rs, _ = lobe_albedos(L, y, W)
    f = LobeFit(kind, rd, rs, ax, ay, rot, nn, cost=float(2 * best.cost / max(len(y), 1)))
    if uncertainty:
        names = ["rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation"] + (["n"] if fit_n else [])
        p0 = np.array([rd, rs, ax, ay, rot] + ([nn] if fit_n else []))

        def full(p):
            L = lobe(*(a[k] for k in ANGLES), p[2], p[3], p[4], p[5] if fit_n else n)
            return W * (p[0] / np.pi + p[1] * L)

        base = full(p0)
        J = np.empty((len(y), len(p0)))
        for i in range(len(p0)):
            h = 1e-6 * max(abs(p0[i]), 1e-3)
            p = p0.copy()
            p[i] += h
            J[:, i] = (full(p) - base) / h
        cov = _sandwich(J, base - W * y)
        f.stderr = {k: float(np.sqrt(cov[i, i])) if np.isfinite(cov[i, i]) else float("inf")
                    for i, k in enumerate(names)}
    return f


def fresnel_profile(a: dict, y, W, folds, grid, kind: str = "ggx", start=(0.1, 0.1, 0.0)) -> dict:
    """Held-out error of the lobe with Schlick's factor at each fixed n of ``grid``:
    fitted on each fold's training rows, scored (weighted mean squared residual) on its
    test rows. A flat profile means the data cannot tell n apart."""
    err = np.zeros(len(grid))
    fits = []
    for j, nn in enumerate(grid):
        tot = 0.0
        for train, test in folds:
            sub = {k: v[train] for k, v in a.items()}
            f = fit_lobe(sub, y[train], W[train], kind, start, n=nn, uncertainty=False)
            pred = f.predict({k: v[test] for k, v in a.items()})
            tot += float(np.sum((W[test] * (pred - y[test])) ** 2))
        err[j] = tot / sum(int(t.sum()) for _, t in folds)
        fits.append(fit_lobe(a, y, W, kind, start, n=nn, uncertainty=False))
    return {"grid": [float(g) for g in grid], "error": err.tolist(), "fits": fits}


# ------------------------------------------------------------------ diagnose causes

#: training rows (random, seeded) a fold's lobe fit uses, for speed (the fitted parameters' noise grows
#: as sqrt(training rows / LOBE_FIT_ROWS)); held-out errors use every test row
LOBE_FIT_ROWS = 8_000


def _refit_cause(m, a, kind, start):
    """Held-out scores of a lobe of ``kind`` refitted per fold (shape and rho_d, rho_s; on at most
    LOBE_FIT_ROWS of the fold's training rows), against the base model (Ward lobe of the fit, rho_d
    and rho_s re-solved per fold on all its training rows). Returns (error, base error, fold gains,
    fit on all rows, robust score of :class:`glossrig.core.diagnose.catalogue.RobustScore`)."""
    from glossrig.core.diagnose.catalogue import RobustScore, chi2

    c = m.cols
    one = np.full_like(c["L"], 1 / np.pi)
    y, sig = c["y"], c["sigma"]
    e0s = e1s = 0.0
    gains = []
    robust = RobustScore()
    n_tot = 0
    rng = np.random.default_rng(0)
    for train, test in m.folds():
        rows = np.flatnonzero(train)
        if rows.size > LOBE_FIT_ROWS:
            rows = np.sort(rng.choice(rows, LOBE_FIT_ROWS, replace=False))
        sub = {k: v[rows] for k, v in a.items()}
        f = fit_lobe(sub, y[rows], 1 / sig[rows], kind, start, uncertainty=False)
        p1 = f.predict(a)
        _, p0, _ = m.solve_linear([one, c["L"]], train)
        e0, e1 = chi2((y - p0)[test], sig[test]), chi2((y - p1)[test], sig[test])
        robust.add(y, p0, p1, test)
        e0s, e1s, n_tot = e0s + e0 * test.sum(), e1s + e1 * test.sum(), n_tot + test.sum()
        gains.append((e0 - e1) / e0)
    return e1s / n_tot, e0s / n_tot, gains, fit_lobe(a, y, 1 / sig, kind, start), robust.result()


#: the lobe-model causes of :func:`material_cause` (the flexible model is :mod:`.flexible`'s)
LOBE_CAUSES = ("ggx_lobe", "beckmann_lobe", "grazing_lobe")


def material_causes(m) -> list:
    """Causes of the catalogue for the material models (BRDF space, leave-one-LED-out folds of
    :class:`glossrig.core.diagnose.catalogue.BrdfModel`): :func:`material_cause` of each of LOBE_CAUSES."""
    return [material_cause(m, name) for name in LOBE_CAUSES]


def material_cause(m, name: str):
    """One material cause of LOBE_CAUSES fitted and scored on ``m`` (also on data an instrument cause's
    effect was taken out of: :func:`glossrig.core.diagnose.catalogue.explain_material`)."""
    from glossrig.core.diagnose.catalogue import CauseResult, _scalar_cause

    c = m.cols
    t = m.data.table.iloc[m.rows]
    a = angle_arrays(t)
    w = m.lobe
    start = (w.alpha_x, w.alpha_y, w.lobe_rotation)
    names = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")
    if name in ("ggx_lobe", "beckmann_lobe"):
        if name == "ggx_lobe":
            kind, unit = "ggx", "GGX roughness, radians"
            doc = ("Microfacet lobe shape: Ward's Gaussian lobe (eq. 4.79) replaced by the anisotropic GGX / "
                   "Trowbridge-Reitz lobe D G2 / (4 cos_i cos_o) with height-correlated Smith masking (Walter et al. "
                   "2007, Heitz 2014), axes turned as in eq. 4.80. Real glossy surfaces have GGX's long tails: the "
                   "Ward fit then underestimates the tails and overshoots the flanks of the peak.")
        else:
            kind, unit = "beckmann", "Beckmann roughness, radians"
            doc = ("Cook-Torrance lobe: Ward's lobe replaced by the microfacet lobe D G2 / (4 cos_i cos_o) with the "
                   "anisotropic Beckmann distribution and its height-correlated Smith masking (Cook & Torrance 1982; "
                   "Walter et al. 2007, Lambda by their rational fit), axes turned as in eq. 4.80. Ward's lobe is a "
                   "Beckmann-like Gaussian in tan(theta_h) without masking and with a 1/sqrt(cos_i cos_o) factor: the "
                   "two part at grazing angles and on rough lobes, where masking removes light.")
        e1, e0, gains, f, robust = _refit_cause(m, a, kind, start)
        return CauseResult(name, "brdf", doc, dict({k: getattr(f, k) for k in names}, unit=unit),
                           f.stderr, e1, e0, gains, 0, magnitude=f.alpha_x, prediction=f.predict(a), robust=robust)
    if name != "grazing_lobe":
        raise ValueError(f"no material cause {name!r}")
    # ---- a diffuse term with a grazing factor (Burley 2012): one parameter, F_D90
    doc = ("Grazing term: the diffuse part rho_d / pi times Burley's factor [1 + (F_D90 - 1)(1 - cos theta_in)^5]"
           "[1 + (F_D90 - 1)(1 - cos theta_out)^5] (Burley, \"Physically-Based Shading at Disney\", 2012, sec. 5.3), "
           "the Ward lobe kept. A Lambertian diffuse term (eq. 4.79) is constant; measured diffuse reflection of "
           "rough surfaces rises toward grazing incidence and viewing (retro-reflection of rough facets, "
           "Oren & Nayar 1994), that of smooth dielectric coatings falls (the Fresnel loss of light entering and "
           "leaving the surface). F_D90 > 1 is a rise, < 1 a fall; Burley ties it to the roughness, "
           "F_D90 = 0.5 + 2 r cos^2 theta_d, here it is fitted. One parameter, reciprocal.")
    one = np.full_like(c["L"], 1 / np.pi)
    return _scalar_cause(m, "grazing_lobe", doc,
                         lambda f90: ([one * grazing_factor(c["theta_in"], c["theta_out"], f90), c["L"]], None),
                         GRAZING_F90_RANGE, "F_D90", "diffuse factor at grazing incidence and viewing")
