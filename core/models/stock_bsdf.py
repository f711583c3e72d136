"""The closest stock Mitsuba 3 material to the extended Ward model, fitted to the samples.

Why this stock model
--------------------
Mitsuba 3's stock plugins that could carry an anisotropic glossy lobe over a diffuse
base (Mitsuba 3 plugin reference, "BSDFs"):

* ``roughplastic``: diffuse + microfacet dielectric coating, but **isotropic** only
  (one ``alpha``); it cannot hold the anisotropy the rig measures.
* ``principled`` (Burley 2012/2015): anisotropic through ``roughness`` and
  ``anisotropic``, but its lobe aspect is limited to ``alpha_u / alpha_v <= 10``
  (``aspect = sqrt(1 - 0.9 anisotropic)``), its base is Disney's retro-reflective
  diffuse, and its specular carries a Schlick/dielectric Fresnel factor tied to
  ``specular`` and coupled to the diffuse weight. None of that is identifiable from
  the rig (thesis 4.3: theta_d only up to about 27 degrees), so its extra degrees of
  freedom would be extrapolated guesses.
* ``roughconductor`` is anisotropic (``alpha_u``, ``alpha_v``; ``beckmann`` or
  ``ggx``) and, with ``material="none"``, a 100 % reflecting conductor (complex index
  ``eta = 0 + 1i``, for which the conductor Fresnel reflectance is exactly 1 at every
  angle), scaled by a constant ``specular_reflectance``: a constant-albedo microfacet
  lobe, which is what Ward's ``rho_s`` is.

Hence the choice: ``blendbsdf`` (weight ``w``) of ``diffuse`` (``bsdf_0``,
reflectance ``R``) and an anisotropic ``roughconductor`` (``bsdf_1``,
``material="none"``, ``specular_reflectance S``). Its BRDF is (``blendbsdf`` mixes
its two children's values linearly, ``(1 - w) f_0 + w f_1``)::

    f(wi, wo) = rho_d / pi + rho_s * D(h) G(wi, wo, h) / (4 cos th_i cos th_o),
    rho_d = (1 - w) R,   rho_s = w S,

with ``D`` the anisotropic Beckmann or GGX distribution and ``G = G1(wi) G1(wo)`` the
separable Smith shadowing-masking of Mitsuba's ``MicrofacetDistribution``
(Walter, Marschner, Li, Torrance, "Microfacet models for refraction through rough
surfaces", EGSR 2007: eq. 25 and 33 for D, eq. 27 (Beckmann's rational
approximation, which Mitsuba uses) and eq. 34 for G1; anisotropic form of Heitz,
"Understanding the masking-shadowing function in microfacet-based BRDFs", JCGT 2014,
with ``alpha^2 tan^2 th -> (alpha_u^2 v_x^2 + alpha_v^2 v_y^2) / v_z^2``).
Beckmann's ``D = exp(-tan^2 th_h (cos^2 phi / a_u^2 + sin^2 phi / a_v^2)) /
(pi a_u a_v cos^4 th_h)`` has Ward's exponent (thesis eq. 4.79), so it is the natural
stock counterpart; both distributions are fitted and the better one is kept.

:func:`stock_brdf` evaluates this formula in numpy (so ``glossrig.core`` needs no
Mitsuba); ``tests/test_exports.py`` checks it against Mitsuba's own ``eval`` of the
plugin. :func:`fit_stock` fits it by the weighted least squares of thesis eq.
4.81-4.82, the objective of the Ward fit (:mod:`glossrig.core.fitting.fit`), so the two
residuals compare like for like.

Lobe rotation
-------------
Mitsuba's ``alpha_u`` lies along the shading frame's ``s = dp/du`` of the shape, and
no stock BSDF can turn that frame. The fit has its own lobe rotation ``rotation``
(the same convention as Ward's ``lobe_rotation``, eq. 4.80: the lobe's ``u`` axis is
the sample's tangent turned by ``-rotation`` about the normal). For
``rotation`` = 0 (or pi) nothing is to be done. Otherwise the user must turn the
surface parameterisation so that ``dp/du`` runs along the lobe's ``u`` axis: rotate
the mesh's uv coordinates by ``-rotation`` (for a ``rectangle``/``disk``, whose
``dp/du`` is its ``to_world`` x axis, prepend ``<rotate z="1" angle="-ROT_DEG"/>`` to
its ``to_world``, which turns the shape with it). ``material_stock.xml`` states the
angle in its header.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np

from glossrig.core.errors import InputError

DISTRIBUTIONS = ("beckmann", "ggx")
#: Bounds of the fitted roughness. Mitsuba accepts any alpha > 0; 1e-4 as the Ward fit
#: (:data:`glossrig.core.fitting.fit.ALPHA_MIN`), 1.0 as a roughness beyond which the lobe is
#: not glossy.
STOCK_ALPHA_MIN = 1e-4
STOCK_ALPHA_MAX = 1.0
#: Rows the non-linear search uses at most (a random subset, seeded); the albedos and
#: the reported residuals use every row.
FIT_ROWS = 20_000


@dataclass(frozen=True)
class StockParams:
    """One channel of the stock model: ``rho_d`` (= (1 - w) R), ``rho_s`` (= w S),
    ``alpha_u``, ``alpha_v`` (Mitsuba's roughness along the lobe's u and v axes),
    ``rotation`` (radians, the convention of Ward's ``lobe_rotation``) and the
    microfacet ``distribution``."""

    rho_d: float
    rho_s: float
    alpha_u: float
    alpha_v: float
    rotation: float = 0.0
    distribution: str = "beckmann"

    def __post_init__(self):
        if self.distribution not in DISTRIBUTIONS:
            raise InputError(f"stock model: distribution must be one of {', '.join(DISTRIBUTIONS)}, "
                             f"got {self.distribution!r}")
        for k in ("rho_d", "rho_s", "alpha_u", "alpha_v", "rotation"):
            v = getattr(self, k)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InputError(f"stock model: {k}={v!r} is not a finite number")
        if self.alpha_u <= 0 or self.alpha_v <= 0:
            raise InputError(f"stock model: alpha_u, alpha_v must be > 0 (got {self.alpha_u}, {self.alpha_v})")

    def as_dict(self) -> dict:
        return asdict(self)


def directions(theta, phi) -> np.ndarray:
    """Unit vectors ``(..., 3)`` of zenith ``theta`` and azimuth ``phi`` (radians) in the
    tangent frame of thesis 4.3.5 (x = tangent, y = bitangent, z = normal)."""
    theta = np.asarray(theta, np.float64)
    phi = np.asarray(phi, np.float64)
    st = np.sin(theta)
    return np.stack([st * np.cos(phi), st * np.sin(phi), np.cos(theta)], axis=-1)


def _to_lobe(v, rotation):
    """Coordinates in the lobe's frame: u = tangent turned by -rotation (eq. 4.80's
    convention, as :func:`glossrig.core.models.ward.ward_local`)."""
    c, s = math.cos(rotation), math.sin(rotation)
    return c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]


def _distribution(hx, hy, hz, au, av, kind):
    """Anisotropic microfacet normal distribution D(h) (Walter et al. 2007 eq. 25 / 33,
    anisotropic; Mitsuba's ``MicrofacetDistribution::eval``)."""
    cos2 = hz * hz
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        if kind == "beckmann":
            d = np.exp(-((hx / au) ** 2 + (hy / av) ** 2) / cos2) / (np.pi * au * av * cos2 * cos2)
        else:
            d = 1.0 / (np.pi * au * av * ((hx / au) ** 2 + (hy / av) ** 2 + cos2) ** 2)
    return np.where((d * hz > 1e-20) & (hz > 0), d, 0.0)


def _smith_g1(vx, vy, vz, v_dot_h, au, av, kind):
    """Smith's masking G1 (Walter et al. 2007 eq. 27 - Beckmann's rational approximation,
    as Mitsuba - and eq. 34 for GGX), anisotropic (Heitz 2014)."""
    xy = (au * vx) ** 2 + (av * vy) ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        t2 = xy / (vz * vz)
        if kind == "beckmann":
            a = 1.0 / np.sqrt(t2)
            g = np.where(a >= 1.6, 1.0, (3.535 * a + 2.181 * a * a) / (1.0 + 2.276 * a + 2.577 * a * a))
        else:
            g = 2.0 / (1.0 + np.sqrt(1.0 + t2))
    g = np.where(xy == 0, 1.0, g)
    return np.where(v_dot_h * vz <= 0, 0.0, g)


def specular_basis(wi, wo, alpha_u, alpha_v, rotation=0.0, distribution="beckmann") -> np.ndarray:
    """``D G / (4 cos th_i cos th_o)`` (1/sr) for unit directions ``(..., 3)`` in the
    tangent frame: the stock model's specular BRDF per unit ``rho_s``; 0 where either
    direction is at or below the horizon."""
    wi = np.asarray(wi, np.float64)
    wo = np.asarray(wo, np.float64)
    h = wi + wo
    h = h / np.linalg.norm(h, axis=-1, keepdims=True)
    ix, iy, iz = _to_lobe(wi, rotation)
    ox, oy, oz = _to_lobe(wo, rotation)
    hx, hy, hz = _to_lobe(h, rotation)
    d = _distribution(hx, hy, hz, alpha_u, alpha_v, distribution)
    g = _smith_g1(ix, iy, iz, np.sum(wi * h, -1), alpha_u, alpha_v, distribution) \
        * _smith_g1(ox, oy, oz, np.sum(wo * h, -1), alpha_u, alpha_v, distribution)
    valid = (iz > 0) & (oz > 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        f = d * g / (4.0 * np.where(valid, iz * oz, 1.0))
    return np.where(valid, f, 0.0)


def stock_brdf(wi, wo, p: StockParams) -> np.ndarray:
    """The stock model's BRDF (1/sr) at unit directions ``(..., 3)`` in the tangent frame."""
    wi = np.asarray(wi, np.float64)
    wo = np.asarray(wo, np.float64)
    valid = (wi[..., 2] > 0) & (wo[..., 2] > 0)
    spec = specular_basis(wi, wo, p.alpha_u, p.alpha_v, p.rotation, p.distribution)
    return np.where(valid, p.rho_d / np.pi + p.rho_s * spec, 0.0)


def stock_from_angles(samples, p: StockParams) -> np.ndarray:
    """:func:`stock_brdf` at the rows of a samples table (``theta_in, phi_in, theta_out,
    phi_out``, radians)."""
    wi = directions(samples["theta_in"], samples["phi_in"])
    wo = directions(samples["theta_out"], samples["phi_out"])
    return stock_brdf(wi, wo, p)


# ----------------------------------------------------------------------------
# Fitting
# ----------------------------------------------------------------------------

@dataclass
class StockFit:
    """The fitted stock material: the luminance lobe (``params``), the per-channel
    albedos of that lobe (``rgb``: ``rho_d``, ``rho_s`` lists r, g, b), and the
    residual statistics of this model and of the Ward fit on the same rows with the
    same weights (``residuals``, ``ward_residuals``: see
    :func:`glossrig.core.fitting.fit._residual_stats`; ``weighted_rmse`` is the objective of
    eq. 4.81-4.82 per unit weight)."""

    params: StockParams
    rgb: dict
    residuals: dict
    ward_residuals: dict
    candidates: dict          # distribution -> weighted_rmse of its best fit
    n_samples: int
    weighting: str

    def blend(self) -> dict:
        """The ``blendbsdf`` parameters: weight ``w`` and per-channel reflectances ``R``
        (diffuse) and ``S`` (conductor), with ``rho_d = (1 - w) R`` and ``rho_s = w S``.
        ``w = M_s / (M_s + M_d)`` with ``M`` the largest channel of each albedo, so
        that ``R, S <= M_s + M_d``, which is <= 1 whenever the albedos conserve energy."""
        rd, rs = np.asarray(self.rgb["rho_d"], float), np.asarray(self.rgb["rho_s"], float)
        md, ms = float(rd.max()), float(rs.max())
        if ms <= 0:
            return {"weight": 0.0, "R": rd.tolist(), "S": [0.0, 0.0, 0.0]}
        if md <= 0:
            return {"weight": 1.0, "R": [0.0, 0.0, 0.0], "S": rs.tolist()}
        w = ms / (ms + md)
        return {"weight": w, "R": (rd / (1 - w)).tolist(), "S": (rs / w).tolist()}

    def to_json(self) -> dict:
        """Plain JSON (non-finite statistics as ``null``)."""
        def clean(d):
            return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in d.items()}

        return {"model": "blendbsdf(diffuse, roughconductor material=none) - see glossrig.core.models.stock_bsdf",
                "params": self.params.as_dict(), "rgb": self.rgb, "blend": self.blend(),
                "residuals": clean(self.residuals), "ward_residuals": clean(self.ward_residuals),
                "candidates_weighted_rmse": clean(self.candidates), "n_samples": int(self.n_samples),
                "weighting": self.weighting, "angles": "radians"}


def _weights(df, weighting: str, use_weight_column: bool) -> np.ndarray:
    from glossrig.core.fitting.fit import peak_weight

    td = np.asarray(df["theta_d"], float) if weighting == "literal" else None
    pdd = np.asarray(df["phi_d"], float) if weighting == "literal" else None
    W = peak_weight(np.asarray(df["theta_in"], float), np.asarray(df["phi_in"], float),
                    np.asarray(df["theta_out"], float), np.asarray(df["phi_out"], float), td, pdd, mode=weighting)
    if use_weight_column and "weight" in df:
        W = W * np.sqrt(np.asarray(df["weight"], float))
    return W


def _fit_lobe(wi, wo, y, W, start, kind):
    """Variable projection (Golub & Pereyra 1973): SciPy's bounded trust-region least
    squares over (ln alpha_u, ln alpha_v, rotation), the albedos in closed form
    (:func:`glossrig.core.fitting.fit.lobe_albedos`, without its unseen-lobe rule: the
    residual must be continuous in the shape for the solver's finite differences; the rule
    applies to the albedos reported, :func:`fit_stock`). Its bound ``rho_s <= RHO_S_MAX``
    holds here too: a microfacet lobe of unit ``rho_s`` (D G / (4 cos cos) with Smith's G)
    reflects at most all the light."""
    from scipy.optimize import least_squares

    from glossrig.core.fitting.fit import lobe_albedos

    def resid(x):
        B = specular_basis(wi, wo, math.exp(x[0]), math.exp(x[1]), x[2], kind)
        a, b, _ = lobe_albedos(B, y, W, unseen_rule=False)
        return W * (y - a / np.pi - b * B)

    lo = [math.log(STOCK_ALPHA_MIN), math.log(STOCK_ALPHA_MIN), -np.inf]
    hi = [math.log(STOCK_ALPHA_MAX), math.log(STOCK_ALPHA_MAX), np.inf]
    best = None
    for au, av, rot in start:
        x0 = np.clip([math.log(au), math.log(av), rot], np.array(lo) + 1e-9, np.array(hi) - 1e-9)
        r = least_squares(resid, x0, bounds=(lo, hi), method="trf", x_scale=[0.1, 0.1, 0.05],
                          diff_step=1e-6, xtol=1e-8, ftol=1e-9, max_nfev=100)
        if best is None or r.cost < best.cost:
            best = r
    return best.x


def fit_stock(df, ward, *, weighting: str = "mirror", use_weight_column: bool = True,
              clip: float | None = None, distributions=DISTRIBUTIONS, seed: int = 0,
              fit_rows: int = FIT_ROWS) -> StockFit:
    """Fit the stock model to a samples table's luminance (Rec. 709 Y, as the Ward fit),
    then its per-channel albedos for that lobe.

    ``ward``: the Ward fit's luminance :class:`~glossrig.core.models.ward.WardParams` - the
    start of the lobe search (Beckmann's exponent is Ward's, so its lobe is the natural
    start; GGX starts there too) and the reference residual; the stock parameters are fitted, not copied. ``weighting``,
    ``use_weight_column`` and ``clip`` as the Ward fit's options (eq. 4.82 weight;
    rows whose value reaches ``clip`` are left out, as for the shared-lobe albedos).
    Each of ``distributions`` is fitted; the lowest weighted residual wins."""
    from glossrig.core.fitting.fit import _residual_stats, channel_values, lobe_albedos
    from glossrig.core.models.ward import ward_from_angles

    if len(df) == 0:
        raise InputError("stock fit: the samples table is empty")
    y_all = channel_values(df, "luminance")
    W_all = _weights(df, weighting, use_weight_column)
    keep = np.isfinite(y_all) & (W_all > 0)
    if clip is not None:
        keep &= y_all < clip
    idx = np.flatnonzero(keep)
    if idx.size < 6:
        raise InputError(f"stock fit: only {idx.size} usable samples (need at least 6)")
    wi_all = directions(df["theta_in"], df["phi_in"])
    wo_all = directions(df["theta_out"], df["phi_out"])
    sub = idx if idx.size <= fit_rows else np.sort(np.random.default_rng(seed).choice(idx, fit_rows, replace=False))
    wi, wo, y, W = wi_all[sub], wo_all[sub], y_all[sub], W_all[sub]
    ax = min(max(ward.alpha_x, STOCK_ALPHA_MIN), STOCK_ALPHA_MAX)
    ay = min(max(ward.alpha_y, STOCK_ALPHA_MIN), STOCK_ALPHA_MAX)
    starts = [(ax, ay, ward.lobe_rotation)]

    wi_k, wo_k, y_k, W_k = wi_all[idx], wo_all[idx], y_all[idx], W_all[idx]
    fits, candidates = {}, {}
    for kind in distributions:
        x = _fit_lobe(wi, wo, y, W, starts, kind)
        au, av, rot = math.exp(x[0]), math.exp(x[1]), float(x[2])
        B = specular_basis(wi_k, wo_k, au, av, rot, kind)
        a, b, _ = lobe_albedos(B, y_k, W_k)
        f = a / np.pi + b * B
        stats = _residual_stats(y_k, f, W_k, None, False)
        fits[kind] = (au, av, rot, float(a), float(b), B, stats)
        candidates[kind] = stats["weighted_rmse"]
    kind = min(candidates, key=lambda k: candidates[k])
    au, av, rot, a, b, B, stats = fits[kind]
    rot = rot % math.pi                          # D and G are pi-periodic in the rotation
    params = StockParams(rho_d=a, rho_s=b, alpha_u=au, alpha_v=av, rotation=rot, distribution=kind)
    rgb: dict[str, list[float]] = {"rho_d": [], "rho_s": []}
    for c in ("r", "g", "b"):
        yc = np.asarray(df[c], float)
        kc = keep & np.isfinite(yc)
        Bc = specular_basis(wi_all[kc], wo_all[kc], au, av, rot, kind)
        ac, bc, _ = lobe_albedos(Bc, yc[kc], W_all[kc])
        rgb["rho_d"].append(ac)
        rgb["rho_s"].append(bc)
    fw = ward_from_angles(np.asarray(df["theta_in"], float)[idx], np.asarray(df["theta_out"], float)[idx],
                          np.asarray(df["theta_h"], float)[idx], np.asarray(df["phi_h"], float)[idx], ward)
    ward_stats = _residual_stats(y_k, fw, W_k, None, False)
    return StockFit(params=params, rgb=rgb, residuals=stats, ward_residuals=ward_stats, candidates=candidates,
                    n_samples=int(idx.size), weighting=weighting)
