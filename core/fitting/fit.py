"""Fitting the extended Ward model to BRDF samples (thesis 4.5, 6.2).

The model is thesis eq. 4.79-4.80 (:mod:`glossrig.core.models.ward`); the objective is
the weighted least squares of eq. 4.81,

    min  sum_i  v_i * ( w_i * (I_i - f(theta_in, theta_out, theta_h, phi_h)) )^2

with ``w_i`` the peak-emphasising weight of eq. 4.82 (see :func:`peak_weight`)
and ``v_i`` the samples table's own ``weight`` column (inverse-variance-like,
1 when unknown), within the bounds of Table 4.2: ``rho_d, rho_s >= 0``,
``0 < alpha <= 0.5``, and ``rho_s <= RHO_S_MAX`` (energy conservation, eq. 2.4; see
:data:`RHO_S_MAX` for why the fit needs that bound). ``alpha`` is kept above ``ALPHA_MIN = 1e-4`` (Table 4.2
says 0, where the model is undefined; a lobe of slope width 1e-4 is far below
anything the rig can resolve). Table 4.2 bounds the rotation by 0..360 (degrees;
Table 6.3: 0..2 pi); it is reported in radians in [0, pi), which loses nothing
(eq. 4.79 is pi-periodic in it).

Departures from the thesis, and why:

* **Weight (eq. 4.82).** Its ``theta_d, phi_d`` are never defined in the thesis;
  read as the difference of the incident and outgoing angles the weight does
  what the text says (highest at the mirror configuration, reciprocal), read as
  Rusinkiewicz's difference angles it does not (:func:`peak_weight`). The
  former is the default, the latter available as ``weighting="literal"``.
* **Optimiser.** The thesis ran Matlab's ``fmincon`` from random starts and had
  to hand-pick the lobe rotation's start (section 6.2), because
  ``(alpha_x, alpha_y, rot)`` and ``(alpha_y, alpha_x, rot + pi/2)`` are the
  same lobe (and ``rot`` is only defined modulo pi). Here the start is found
  from the data: ``rho_d`` and ``rho_s`` enter the model linearly, so for every
  lobe shape on a grid over the *canonical* half of the shape space
  (``alpha_x >= alpha_y``, ``rot`` in [0, pi)) the best non-negative
  ``(rho_d, rho_s)`` has a closed form (variable projection, Golub & Pereyra
  1973). The best few distinct grid lobes are refined with a bounded
  trust-region least-squares solver (SciPy ``least_squares``, method ``trf``)
  using the analytic Jacobian, in ``(rho_d, rho_s, ln alpha_x, ln alpha_y, rot)``
  with ``rot`` unbounded so that no start is trapped at the symmetry line, on a
  subset of the samples; the best is polished on all samples (Levenberg-
  Marquardt on the normal equations, :func:`_polish_lm`) and reported in the
  canonical form (below).
* **Canonical form.** ``alpha_x >= alpha_y`` and ``lobe_rotation`` in [0, pi):
  the x axis of the lobe is its wider axis. Most of Table 9.1 is already in
  this form; e.g. sample 0/6 (``alpha_x < alpha_y``, 2.52 rad) becomes
  ``(0.0492, 0.035, 2.52 + pi/2 - pi)``. Standard errors and the covariance
  are permuted with the axes, so they describe the reported parameters.
* **Uncertainties.** The weights of eq. 4.82 are not inverse variances and
  measured noise is heteroscedastic (roughly proportional to the value), so the
  covariance is the heteroscedasticity-consistent sandwich estimator
  ``(J'J)^-1 J' diag(r^2) J (J'J)^-1 * n/(n-p)`` (White 1980, "HC1") of the
  weighted Jacobian ``J`` and residuals ``r`` at the optimum. It treats samples
  as independent; neighbouring pixels of a real capture are not, so real-data
  errors are lower bounds. Directions of parameter space the data do not
  constrain (e.g. the rotation of an isotropic lobe, the lobe of a material
  with ``rho_s = 0``) get an infinite standard error instead of a number.
  These standard errors count only the per-pixel noise of the samples: they
  exclude the calibration (geometry, lamp positions, reference) and model
  error, which dominate a real measurement, so they are **not** the
  measurement's uncertainty. Every channel of fit.json says so in
  ``stderr_kind`` (:data:`STDERR_KIND`); the measurement's uncertainty is the
  channel's ``uncertainty``, a GUM budget of noise, model misfit, footprint and
  calibration (:mod:`glossrig.core.fitting.uncertainty`).
* **Footprint.** Each sample of ``glossrig extract`` is the BRDF averaged over
  its Bayer block's read kernel and pixel areas; where the table allows
  (:func:`fit_samples`), the model fitted is eq. 4.79 averaged the same way
  (:mod:`glossrig.core.fitting.footprint_model`), which removes the bias of
  fitting the point model to such values (validation/recovery.md: +1 % on
  alpha_y at scale 0.25, far more for lobes about as narrow as a footprint).
* **Clipping (eq. 6.5).** The thesis clips the measured values at 1.0 and fits
  the unclipped model to them, which pulls the lobe down and wide wherever the
  model exceeds 1. With ``clip`` set, the model is clipped too (a censored fit):
  samples whose data and model are both above the level contribute nothing,
  exactly as section 6.2 intends ("the fitting procedure focuses more on the
  peripheral reflections"). ``clip_model=False`` gives the literal thesis fit.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from collections.abc import Callable, Iterable
from typing import Any

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.workers import in_one_blas_thread
from glossrig.core.samples import LUMINANCE_WEIGHTS, luminance
from glossrig.core.models.ward import (ALPHA_MAX, WardGeometry, WardParams, ward_geometry, ward_param_jacobian, ward_parts,
                   ward_unit_lobes)
from glossrig.core.fitting.footprint_model import SampleFootprint, footprint_eval

PARAM_NAMES = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")
ALPHA_MIN = 1e-4
#: Upper bound of ``rho_s`` in the fit (thesis Table 4.2 sets none). Why one is needed: the
#: lobe's exponent is capped at :data:`glossrig.core.models.ward.EXPONENT_CAP`, so far from its
#: peak a lobe is not 0 but the floor ``exp(-200) g / (4 pi ax ay)`` with ``g = 1 / sqrt(cos
#: theta_in cos theta_out)``. With ``rho_s`` unbounded the fit could scale that floor by ~1e80
#: into a finite term proportional to ``g`` (a rise toward grazing angles that is no part of eq.
#: 4.79), while the lobe's own peak, between the samples, reached 1e80 1/sr: a channel without
#: a measured highlight (issue 14: chm_mint's red channel, dark wherever the highlight is) was
#: fitted with ``rho_s = 1.1e81``, which then filled the luminance's missing red values and
#: made diagnose's held-out error 2.4e66. The bound is energy conservation (thesis eq. 2.4):
#: a Ward lobe of unit ``rho_s`` reflects at least 0.586 of the light at normal viewing
#: (``alpha = 0.5``; :func:`glossrig.core.models.ward.ward_albedo`, 0.97 at ``alpha = 0.1``),
#: so a physical lobe has ``rho_s <= 1 / 0.586 = 1.7``; the factor 2 above that leaves room
#: for data whose scale is off through the reference (the thesis assumes albedo 0.8, eq. 4.78;
#: the real white paper has 0.84). The floor is then below
#: ``RHO_S_MAX exp(-200) / (4 pi ALPHA_MIN^2) g = 4e-80 g`` 1/sr, no value the rig can see.
#: A fit that ends on the bound lists ``rho_s`` in ``at_bound``.
RHO_S_MAX = 3.5
#: A lobe whose value is at most this fraction of the largest datum at every row is one the data
#: do not see (the criterion ``at_bound`` applies to a negligible lobe); :func:`fit_ward` reports
#: no lobe then (rho_s = 0) instead of the arbitrary peak the solver left it with.
LOBE_UNSEEN = 1e-6
CHANNELS = ("luminance", "r", "g", "b")
WEIGHTINGS = ("mirror", "literal", "none")
CANONICAL_FORM = "alpha_x >= alpha_y, lobe_rotation in [0, pi) radians"
#: what the ``<name>_stderr`` values of a fit count (fit.json, the ``glossrig fit`` summary)
STDERR_KIND = "noise-only (per-pixel noise; excludes calibration and model error)"

_GRID_ALPHAS = np.geomspace(0.002, ALPHA_MAX, 13)
_GRID_ROTATIONS = np.arange(12) * (np.pi / 12)


# ----------------------------------------------------------------------------
# Weights (eq. 4.82)
# ----------------------------------------------------------------------------

def peak_weight(theta_in, phi_in, theta_out, phi_out, theta_d=None, phi_d=None, mode: str = "mirror") -> np.ndarray:
    """The weight of thesis eq. 4.82,

        w = 1/2 (1 - |phi_d - pi| / pi) + 1/2 (1 - theta_d / (pi/2)),

    meant to weight samples "closer to the peak reflection" higher.

    The thesis never defines ``theta_d`` and ``phi_d`` (section 4.3.5 computes
    only in, out and half angles). Read as Rusinkiewicz's difference angles
    (the samples table's ``theta_d, phi_d``; ``mode="literal"``) the weight is
    not what the text says: ``theta_d`` is half the angle between light and
    camera, set by the rig's geometry and unrelated to the specular peak, and
    ``|phi_d - pi|`` is not reciprocal (swapping light and camera turns phi_d
    into phi_d + pi and the weight of the first term from 1/2 to 0).

    The reading that does what the text says (``mode="mirror"``, the default)
    takes ``d`` as the difference of the incident and outgoing angles:
    ``theta_d = |theta_in - theta_out|`` and ``phi_d = (phi_in - phi_out) mod 2 pi``.
    Then ``(phi_d - pi)`` is the azimuthal distance from the mirror azimuth,
    written exactly as the thesis does, ``w = 1`` at the perfect mirror
    configuration and decreases away from it, and ``w`` is reciprocal.
    ``mode="none"`` gives unit weights (thesis 6.2 fits clipped data unweighted).
    """
    if mode == "none":
        return np.ones(np.shape(theta_in))
    if mode == "mirror":
        td = np.abs(np.asarray(theta_in, float) - np.asarray(theta_out, float))
        pd_ = np.mod(np.asarray(phi_in, float) - np.asarray(phi_out, float), 2 * np.pi)
    elif mode == "literal":
        if theta_d is None or phi_d is None:
            raise InputError("weighting 'literal' needs the theta_d and phi_d columns")
        td, pd_ = np.asarray(theta_d, float), np.asarray(phi_d, float)
    else:
        raise InputError(f"weighting must be one of {', '.join(WEIGHTINGS)}, got {mode!r}")
    w = 0.5 * (1 - np.abs(pd_ - np.pi) / np.pi) + 0.5 * (1 - td / (0.5 * np.pi))
    return np.clip(w, 0.0, 1.0)


# ----------------------------------------------------------------------------
# Model and analytic Jacobian in the solver's parameters
# ----------------------------------------------------------------------------

@dataclass
class _Data:
    """Per-sample quantities of the objective that do not depend on the parameters:
    eq. 4.79's geometry (:class:`glossrig.core.models.ward.WardGeometry`) and the data."""

    geo: WardGeometry
    W: np.ndarray       # residual multiplier sqrt(v) * w (eq. 4.81-4.82)
    y: np.ndarray       # measured values (clipped if clipping)
    fp: SampleFootprint | None = None   # set: the model is the footprint average (footprint_model)

    def take(self, idx) -> _Data:
        return _Data(self.geo.take(idx), self.W[idx], self.y[idx], None if self.fp is None else self.fp.take(idx))

    def __len__(self):
        return self.y.size


def _make_data(theta_in, theta_out, theta_h, phi_h, values, W, clip) -> _Data:
    y = np.asarray(values, float)
    if clip is not None:
        y = np.minimum(y, clip)
    return _Data(geo=ward_geometry(theta_in, theta_out, theta_h, phi_h), W=np.asarray(W, float), y=y)


def solver_params(p: WardParams) -> np.ndarray:
    """The solver's parameter vector of ``p``: ``(rho_d, rho_s, ln alpha_x, ln alpha_y, rot)``."""
    return np.array([p.rho_d, p.rho_s, math.log(p.alpha_x), math.log(p.alpha_y), p.lobe_rotation])


def _model(x: np.ndarray, d: _Data, jac: bool = False):
    """Eq. 4.79 at ``x = (rho_d, rho_s, ln alpha_x, ln alpha_y, rot)`` and, with
    ``jac``, its Fortran-ordered (n, 5) Jacobian (columns in the order of ``x``):
    the project's one evaluation, :func:`glossrig.core.models.ward.ward_parts` and
    :func:`glossrig.core.models.ward.ward_param_jacobian` with ``log_alpha``; averaged
    over each sample's footprint where ``d.fp`` is set (:mod:`glossrig.core.fitting.footprint_model`)."""
    if d.fp is not None:
        return footprint_eval(d.geo, d.fp, x, jac=jac, log_alpha=True)
    f, parts = ward_parts(d.geo, x, log_alpha=True)
    if not jac:
        return f
    return f, ward_param_jacobian(d.geo, x, parts, log_alpha=True)


def _residual_fn(d: _Data, clip, clip_model):
    """Weighted residuals ``W (f - y)`` (eq. 4.81; censored model with ``clip``)
    and their Jacobian. The solver asks for the Jacobian at the point whose
    residuals it has just accepted, so the pieces of that evaluation are kept
    and the exponential is not computed twice."""
    censor = clip is not None and clip_model
    last: dict[str, Any] = {}

    def fun(x):
        if d.fp is not None:            # footprint average: its Jacobian is evaluated anew in jac
            f = footprint_eval(d.geo, d.fp, x, log_alpha=True)
        else:
            f, parts = ward_parts(d.geo, x, log_alpha=True)
            last.update(x=np.array(x, float), f=f, parts=parts)
        fc = np.minimum(f, clip) if censor else f
        return d.W * (fc - d.y)

    def jac(x):
        if d.fp is not None:
            f, J = footprint_eval(d.geo, d.fp, x, jac=True, log_alpha=True)
            J *= d.W[:, None]
            if censor:
                J[f >= clip] = 0.0
            return J
        if "x" in last and np.array_equal(last["x"], x):
            f, parts = last["f"], last["parts"]
        else:
            f, parts = ward_parts(d.geo, x, log_alpha=True)
        J = ward_param_jacobian(d.geo, x, parts, log_alpha=True)
        J *= d.W[:, None]
        if censor:
            J[f >= clip] = 0.0
        return J

    return fun, jac


# ----------------------------------------------------------------------------
# Data-driven initialisation (variable projection over a lobe grid)
# ----------------------------------------------------------------------------

def _grid_lobes():
    lobes = []
    for i, ax in enumerate(_GRID_ALPHAS):
        for ay in _GRID_ALPHAS[: i + 1]:
            rots = [0.0] if ay == ax else _GRID_ROTATIONS
            for rot in rots:
                lobes.append((ax, ay, rot))
    return np.array(lobes)


def solver_bounds() -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of the solver's parameters (rho_d, rho_s, ln alpha_x, ln alpha_y,
    rotation): Table 4.2's, with ``ALPHA_MIN`` and ``RHO_S_MAX`` (module docstring). Every refit
    of eq. 4.81 (this module's, the calibration draws') uses these."""
    return (np.array([0.0, 0.0, math.log(ALPHA_MIN), math.log(ALPHA_MIN), -np.inf]),
            np.array([np.inf, RHO_S_MAX, math.log(ALPHA_MAX), math.log(ALPHA_MAX), np.inf]))


def _nnls2(uu, uv, vv, uz, vz, zz, b_max: float = math.inf):
    """Closed-form bounded least squares for two columns (vectorised over lobes):
    minimise zz - 2 a uz - 2 b vz + a^2 uu + 2 a b uv + b^2 vv over a >= 0, 0 <= b <= b_max.
    The cost is a convex quadratic, so its minimum over the box is the unconstrained one
    where that lies inside, else the best of the minima along the edges a = 0, b = 0 and
    b = b_max (each a convex 1-D minimum clipped to the edge)."""
    def cost(a, b):
        return zz - 2 * a * uz - 2 * b * vz + a * a * uu + 2 * a * b * uv + b * b * vv

    det = uu * vv - uv * uv
    with np.errstate(divide="ignore", invalid="ignore"):
        a = np.where(det > 0, (vv * uz - uv * vz) / det, -1.0)
        b = np.where(det > 0, (uu * vz - uv * uz) / det, -1.0)
        b_only = np.where(vv > 0, np.clip(vz / vv, 0.0, b_max), 0.0)
    a_only = np.maximum(uz / uu, 0.0)
    ok = (a >= 0) & (b >= 0) & (b <= b_max)
    c_full = np.where(ok, cost(np.where(ok, a, 0), np.where(ok, b, 0)), np.inf)
    c_a, c_b = cost(a_only, 0.0), cost(0.0, b_only)
    cands_a = [np.where(ok, a, 0), a_only, np.zeros_like(a_only)]
    cands_b = [np.where(ok, b, 0), np.zeros_like(b_only), b_only]
    costs = [c_full, c_a, c_b]
    if math.isfinite(b_max):        # the edge b = b_max
        a_top = np.maximum((uz - b_max * uv) / uu, 0.0)
        cands_a.append(a_top * np.ones_like(b_only))
        cands_b.append(np.full_like(b_only, b_max))
        costs.append(cost(a_top, b_max) * np.ones_like(b_only))
    best = np.argmin(np.stack(np.broadcast_arrays(*costs)), axis=0)
    A = np.choose(best, np.broadcast_arrays(*cands_a))
    B = np.choose(best, np.broadcast_arrays(*cands_b))
    C = np.choose(best, np.broadcast_arrays(*costs))
    return A, B, C


def lobe_albedos(L, y, W, *, b_max: float = RHO_S_MAX, unseen_rule: bool = True) -> tuple[float, float, float]:
    """The albedos of a fixed lobe: ``(rho_d, rho_s, cost)`` minimising
    ``sum (W (y - rho_d / pi - rho_s L))^2`` over ``rho_d >= 0``, ``0 <= rho_s <= b_max``.

    Thesis eq. 4.79 (and every stock or extended lobe of the same form, ``rho_d / pi + rho_s
    L``) is linear in the two albedos, so for a fixed lobe shape ``L`` (the lobe of unit
    ``rho_s`` at each row) the weighted least squares of eq. 4.81 over them is a two-column
    bounded problem, solved in closed form by :func:`_nnls2`. The upper bound is energy
    conservation (thesis eq. 2.4, :data:`RHO_S_MAX`): a lobe of unit ``rho_s`` reflects about
    (a microfacet lobe at most) all the light; unbounded, a lobe that is ~0 on every row (its
    peak where no row is) takes any amplitude, and its far tail (for Ward's lobe the floor of
    the capped exponent, :data:`glossrig.core.models.ward.EXPONENT_CAP`) was fitted with
    ``rho_s ~ 1e80``. Bounded, such a lobe is still unseen by the data (``rho_s L`` below
    :data:`LOBE_UNSEEN` of the largest datum on every row of positive weight) and any ``rho_s``
    fits about as well: it is then reported as none (``rho_s = 0``, as :func:`fit_ward` does),
    so that the lobe's peak is never extrapolated where no row is, and ``rho_d`` is re-solved
    alone (the weighted mean of ``pi y``, clipped at 0), with its cost. Rows of zero weight
    take no part (their ``y`` must still be finite). ``unseen_rule=False``: the bounded
    solve alone, a continuous function of ``L`` (the inner solve of a variable projection,
    whose outer solver differentiates the residual numerically; the rule's jump, up to
    LOBE_UNSEEN of the data, would read as a slope there)."""
    L, y, W = np.asarray(L, float), np.asarray(y, float), np.asarray(W, float)
    W2 = W * W
    uu, uz, zz = np.sum(W2) / np.pi ** 2, np.sum(W2 * y) / np.pi, np.sum(W2 * y * y)
    a, b, cost = _nnls2(uu, np.sum(W2 * L) / np.pi, np.sum(W2 * L * L), uz, np.sum(W2 * y * L), zz, b_max=b_max)
    seen = W2 > 0
    if unseen_rule and b > 0 and seen.any() and b * np.max(np.abs(L[seen])) <= LOBE_UNSEEN * np.max(np.abs(y[seen])):
        a, b = max(np.pi * np.sum(W2 * y) / np.sum(W2), 0.0), 0.0
    # The cost of the chosen albedos from the residuals themselves: the quadratic form of the sums
    # (zz - 2 a uz + ...) cancels to ~eps zz, which for a tall lobe over small noise is ~1e-10 of
    # the cost (the grid search, comparing thousands of lobes, keeps the sums).
    cost = np.sum(W2 * (y - a / np.pi - b * L) ** 2) if np.isfinite(cost) else cost
    return float(a), float(b), float(cost)


def _grid_search(d: _Data, keep=None):
    """Cost of the best non-negative (rho_d, rho_s) for every grid lobe.

    Per rotation, the unit lobes of every (ax, ay) pair come from
    :func:`glossrig.core.models.ward.ward_unit_lobes` as one (pairs, samples) array."""
    if keep is not None:
        d = d.take(keep)
    W2 = d.W ** 2
    W2y = W2 * d.y
    uu = W2.sum() / np.pi ** 2
    uz = W2y.sum() / np.pi
    zz = (W2y * d.y).sum()
    lobes = _grid_lobes()
    out = np.empty((len(lobes), 3))
    for rot in np.unique(lobes[:, 2]):
        rows = np.flatnonzero(lobes[:, 2] == rot)
        Q = ward_unit_lobes(d.geo, lobes[rows, 0], lobes[rows, 1], float(rot))
        uv = (Q @ W2) / np.pi
        vz = Q @ W2y
        np.square(Q, out=Q)
        vv = Q @ W2
        a, b, cost = _nnls2(uu, uv, vv, uz, vz, zz, b_max=RHO_S_MAX)
        out[rows] = np.stack([a, b, cost], axis=1)
    return lobes, out


def _distinct_starts(lobes, sol, k):
    order = np.argsort(sol[:, 2])
    chosen = []
    for i in order:
        ax, ay, rot = lobes[i]
        far = True
        for j in chosen:
            bx, by, brot = lobes[j]
            dshape = abs(math.log(ax / bx)) + abs(math.log(ay / by))
            drot = abs((rot - brot + np.pi / 2) % np.pi - np.pi / 2)
            if dshape < 0.6 and (drot < np.pi / 7 or ax / ay < 1.5):
                far = False
                break
        if far:
            chosen.append(i)
        if len(chosen) == k:
            break
    starts = []
    for i in chosen:
        ax, ay, rot = lobes[i]
        rho_d, rho_s = sol[i, 0], sol[i, 1]
        starts.append(np.array([rho_d, rho_s, math.log(ax), math.log(ay), rot]))
    return starts


# ----------------------------------------------------------------------------
# Canonical form and uncertainties
# ----------------------------------------------------------------------------

def canonical(params: WardParams, covariance: np.ndarray | None = None):
    """The canonical form of a lobe (``alpha_x >= alpha_y``, rotation in [0, pi)).

    ``(ax, ay, rot)`` and ``(ay, ax, rot + pi/2)`` are the same BRDF (eq. 4.79:
    ``cos^2(a + pi/2) = sin^2 a``), and ``rot`` matters only modulo pi. A
    covariance in the order of :data:`PARAM_NAMES` is permuted with the axes.
    Returns ``(params, covariance)``."""
    ax, ay, rot = params.alpha_x, params.alpha_y, params.lobe_rotation
    cov = None if covariance is None else np.array(covariance, dtype=float)
    if ax < ay:
        ax, ay, rot = ay, ax, rot + np.pi / 2
        if cov is not None:
            perm = [0, 1, 3, 2, 4]
            cov = cov[np.ix_(perm, perm)]
    rot = float(np.mod(rot, np.pi))
    if rot >= np.pi:        # mod can round up to pi itself
        rot = 0.0
    p = WardParams(rho_d=params.rho_d, rho_s=params.rho_s, alpha_x=ax, alpha_y=ay, lobe_rotation=rot)
    return p, cov


def parameter_errors(fit, truth) -> dict[str, float]:
    """Errors of fitted extended-Ward parameters against the truth: ``rho_d``,
    ``rho_s``, ``alpha_x``, ``alpha_y`` relative (fitted / true - 1) and
    ``lobe_rotation_deg``, the absolute rotation error in degrees modulo pi.
    Both are compared in :func:`canonical` form, so a truth written with
    ``alpha_x < alpha_y`` (Table 9.1's sample 0/6) meets the fit's axes.
    ``fit`` and ``truth``: :class:`WardParams` or dicts holding its fields."""
    def params(x) -> WardParams:
        return x if isinstance(x, WardParams) else WardParams(**{k: float(x[k]) for k in PARAM_NAMES})

    f, _ = canonical(params(fit))
    t, _ = canonical(params(truth))
    out = {k: getattr(f, k) / getattr(t, k) - 1 for k in ("rho_d", "rho_s", "alpha_x", "alpha_y")}
    d = (f.lobe_rotation - t.lobe_rotation) % math.pi
    out["lobe_rotation_deg"] = math.degrees(min(d, math.pi - d))
    return out


def _sandwich(J: np.ndarray, r: np.ndarray, rel_tol: float = 1e-10, groups=None) -> np.ndarray:
    """HC1 sandwich covariance of least-squares parameters; inf along directions
    the data do not determine (eigenvalues of the scaled J'J below ``rel_tol``).
    With ``groups`` (one integer label per row, 0..G-1): the cluster-robust "CR1"
    sandwich, whose meat sums the score ``J' r`` within each group first
    (Liang & Zeger 1986; factor ``G/(G-1) (n-1)/(n-p)``)."""
    n, p = J.shape
    norms = np.sqrt(np.einsum("ij,ij->j", J, J))
    scale = np.where(norms > 0, norms, 1.0)
    Js = J / scale
    A = Js.T @ Js
    lam, V = np.linalg.eigh(A)
    good = lam > rel_tol * max(lam.max(), 1e-300)
    Ainv = (V[:, good] / lam[good]) @ V[:, good].T
    Jr = Js * r[:, None]
    if groups is None:
        meat = Jr.T @ Jr
        cov = Ainv @ meat @ Ainv * (n / max(n - p, 1))
    else:
        G = int(np.max(groups)) + 1
        S = np.stack([np.bincount(groups, weights=Jr[:, j], minlength=G) for j in range(p)], axis=1)
        meat = S.T @ S
        cov = Ainv @ meat @ Ainv * (G / max(G - 1, 1) * (n - 1) / max(n - p, 1))
    cov = cov / np.outer(scale, scale)
    undetermined = np.zeros(p, bool)
    for i in np.flatnonzero(~good):
        undetermined |= np.abs(V[:, i]) > 1e-6
    undetermined |= norms == 0
    cov[undetermined, :] = np.nan
    cov[:, undetermined] = np.nan
    for i in np.flatnonzero(undetermined):
        cov[i, i] = np.inf
    return cov


# ----------------------------------------------------------------------------
# Results
# ----------------------------------------------------------------------------

@dataclass
class WardFit:
    """One fitted channel, in the canonical form (see :func:`canonical`)."""

    channel: str
    params: WardParams
    stderr: dict[str, float]            # inf where the data do not determine the parameter
    covariance: np.ndarray              # order PARAM_NAMES; NaN rows/cols where undetermined
    residuals: dict[str, float]
    at_bound: list[str]
    n_samples: int
    weighting: str
    clip: float | None
    clip_model: bool
    cost: float
    converged: bool
    n_starts: int
    time_s: float
    history: list[dict] = field(default_factory=list, repr=False)
    footprint: dict | None = None       # how the model treats the samples' footprint (footprint_model)
    uncertainty: dict | None = None     # the GUM budget (glossrig.core.fitting.uncertainty), plain JSON

    def to_json(self) -> dict:
        """Plain-JSON dict: the parameters, ``<name>_stderr`` for each (``null``
        when infinite; noise-only, named in ``stderr_kind``), covariance, residual
        statistics and fit settings."""
        def num(v):
            v = float(v)
            return v if math.isfinite(v) else None

        d: dict[str, Any] = {k: float(getattr(self.params, k)) for k in PARAM_NAMES}
        for k in PARAM_NAMES:
            d[f"{k}_stderr"] = num(self.stderr[k])
        d["stderr_kind"] = STDERR_KIND          # the stderr and covariance are not the measurement's uncertainty
        d["covariance"] = [[num(v) for v in row] for row in self.covariance]
        d["covariance_order"] = list(PARAM_NAMES)
        d["residuals"] = {k: num(v) if isinstance(v, float) else v for k, v in self.residuals.items()}
        d.update(at_bound=list(self.at_bound), n_samples=int(self.n_samples), weighting=self.weighting,
                 clip=self.clip, clip_model=self.clip_model, cost=float(self.cost), converged=bool(self.converged),
                 n_starts=int(self.n_starts), time_s=round(float(self.time_s), 4))
        if self.footprint is not None:
            d["footprint"] = self.footprint
        if self.uncertainty is not None:
            d["uncertainty"] = self.uncertainty
        return d


def _residual_stats(y, f, W, clip, clip_model, n_params=5) -> dict:
    """Residual statistics of the fit (measured minus fitted, unweighted unless named)."""
    fm = np.minimum(f, clip) if (clip is not None and clip_model) else f
    res = y - fm
    n = y.size
    wres = W * res
    W2 = W * W
    ybar = np.sum(W2 * y) / max(np.sum(W2), 1e-300)
    ss_tot = float(np.sum(W2 * (y - ybar) ** 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(res) / np.abs(fm)
    rel = rel[np.isfinite(rel)]
    return {
        "n": int(n),
        "n_clipped": int(np.sum(y >= clip)) if clip is not None else 0,
        "rmse": float(np.sqrt(np.mean(res ** 2))),
        "weighted_rmse": float(np.sqrt(np.sum(wres ** 2) / max(np.sum(W2), 1e-300))),
        "mean": float(np.mean(res)),
        "max_abs": float(np.max(np.abs(res))),
        "median_abs_relative": float(np.median(rel)) if rel.size else float("nan"),
        "rms_relative": float(np.sqrt(np.mean(rel ** 2))) if rel.size else float("nan"),
        "r_squared_weighted": float(1 - np.sum(wres ** 2) / ss_tot) if ss_tot > 0 else float("nan"),
        "chi2_per_dof": float(np.sum(wres ** 2) / max(n - n_params, 1)),
    }


# ----------------------------------------------------------------------------
# The fit
# ----------------------------------------------------------------------------

def _arrays(samples) -> dict[str, np.ndarray]:
    need = ("theta_in", "phi_in", "theta_out", "phi_out", "theta_h", "phi_h")
    try:
        return {k: np.asarray(samples[k], dtype=float) for k in need}
    except KeyError as e:
        raise InputError(f"samples lack the column {e.args[0]!r}") from None


# one BLAS thread: its linear algebra is on tall n x 5 matrices (core.workers.one_blas_thread)
@in_one_blas_thread
def fit_ward(samples, values, *, channel: str = "values", weighting: str = "mirror",
             sample_weight=None, clip: float | None = None, clip_model: bool = True,
             starts: Iterable[WardParams] | None = None, grid: bool = True, n_starts: int = 4,
             refine_samples: int = 50_000, grid_samples: int = 10_000, seed: int = 0,
             ftol: float = 1e-9, max_nfev: int = 60, log: Callable[[str], None] | None = None,
             footprint: SampleFootprint | None = None, footprint_fit: bool = True, groups=None,
             budget: bool = True, calibration: dict | None = None, led_aperture: float | None = None) -> WardFit:
    """Fit the extended Ward model (eq. 4.79-4.80) to one channel by the weighted
    least squares of eq. 4.81-4.82, within the bounds of Table 4.2.

    ``samples``: a mapping/DataFrame with theta_in, phi_in, theta_out, phi_out,
    theta_h, phi_h (and theta_d, phi_d for ``weighting="literal"``), radians.
    ``values``: BRDF values (1/sr). ``sample_weight``: the table's ``weight``
    column (rows with 0 are dropped). ``weighting``: see :func:`peak_weight`.
    ``clip``: the level of eq. 6.5 (thesis: 1.0), ``clip_model``: censored fit
    (default) or the thesis's literal one (module docstring).
    ``starts``: extra starting points (any form; they are refined alongside the
    ``n_starts`` best grid lobes, or alone with ``grid=False``).
    The starts are refined on at most ``refine_samples`` rows (the largest
    values plus a random subset); the best is then polished on all rows.
    Deterministic for a given ``seed``.

    ``footprint``: the samples' footprints (:mod:`glossrig.core.fitting.footprint_model`,
    one row per sample); with ``footprint_fit`` the model fitted is eq. 4.79 averaged
    over each footprint (the pixel-area quadrature chosen for the start's lobe and
    refined for the optimum's), else the point model, and the footprint's effect
    goes into the budget. ``budget``: compute the uncertainty budget
    (:mod:`glossrig.core.fitting.uncertainty`) with ``groups`` (one label per sample:
    the LED x rotation blocks of the model component; None: omitted),
    ``calibration`` (``{param: u}`` of this channel; None: omitted) and
    ``led_aperture`` (the LED's angular diameter in radians; None: the rig's,
    :data:`glossrig.core.fitting.uncertainty.DEFAULT_LED_APERTURE`; 0: a point LED).
    """
    t0 = time.perf_counter()
    say = log or (lambda msg: None)
    a = _arrays(samples)
    y = np.asarray(values, dtype=float).ravel()
    n_all = y.size
    if n_all == 0:
        raise InputError(f"{channel}: no samples to fit")
    if y.size != a["theta_in"].size:
        raise InputError(f"{channel}: {y.size} values for {a['theta_in'].size} samples")
    if not np.all(np.isfinite(y)):
        raise InputError(f"{channel}: values hold NaN or infinite entries")
    if clip is not None and not (math.isfinite(clip) and clip > 0):
        raise InputError(f"clip level must be a positive number, got {clip!r}")
    td: np.ndarray | None
    pd_: np.ndarray | None
    if weighting == "literal":
        try:
            td, pd_ = np.asarray(samples["theta_d"], float), np.asarray(samples["phi_d"], float)
        except KeyError:
            raise InputError("weighting 'literal' needs the theta_d and phi_d columns") from None
    else:
        td = pd_ = None
    w = peak_weight(a["theta_in"], a["phi_in"], a["theta_out"], a["phi_out"], td, pd_, mode=weighting)
    v = np.ones(n_all) if sample_weight is None else np.asarray(sample_weight, float).ravel()
    if v.size != n_all or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise InputError(f"{channel}: sample weights must be {n_all} finite values >= 0")
    W = np.sqrt(v) * w
    use = W > 0
    if footprint is not None and len(footprint) != n_all:
        raise InputError(f"{channel}: {len(footprint)} footprints for {n_all} samples")
    if groups is not None:
        groups = np.asarray(groups).ravel()
        if groups.size != n_all:
            raise InputError(f"{channel}: {groups.size} block labels for {n_all} samples")
    if not use.all():
        a = {k: x[use] for k, x in a.items()}
        y, W = y[use], W[use]
        footprint = None if footprint is None else footprint.take(use)
        groups = None if groups is None else groups[use]
    n = y.size
    if n < 5:
        raise InputError(f"{channel}: {n} samples with a non-zero weight; the Ward model has 5 parameters")
    d = _make_data(a["theta_in"], a["theta_out"], a["theta_h"], a["phi_h"], y, W, clip)
    rng = np.random.default_rng(seed)

    # Start points: data-driven grid (variable projection) + user starts.
    cand = [solver_params(p) for p in (starts or [])]
    if grid:
        grid_idx = _subset(d, grid_samples, rng, clip)
        lobes, sol = _grid_search(d, grid_idx)
        cand += _distinct_starts(lobes, sol, n_starts)
    if not cand:
        raise InputError("no starting point: give starts or enable the grid")
    lb, ub = solver_bounds()
    yscale = max(float(np.max(np.abs(d.y))), 1e-12)

    def prepare(x):
        # strictly inside the bounds; rho_s = 0 would leave the lobe without a gradient
        x = np.array(x, float)
        x[0] = max(x[0], 1e-6 * yscale)
        x[1] = min(max(x[1], 1e-4 * yscale * ALPHA_MIN), RHO_S_MAX * (1 - 1e-9))
        x[2:4] = np.clip(x[2:4], lb[2] + 1e-9, ub[2] - 1e-9)
        return x

    from scipy.optimize import least_squares

    def solve(fun, jac, x0, n_rows):
        return least_squares(fun, x0, jac=jac, bounds=(lb, ub), method="trf", x_scale="jac", ftol=ftol,
                             xtol=ftol, gtol=ftol, max_nfev=max_nfev, callback=_Stall(n_rows))

    idx_sub = None if n <= refine_samples else _subset(d, refine_samples, rng, None)
    sub = d if idx_sub is None else d.take(idx_sub)
    fun, jac = _residual_fn(sub, clip, clip_model)
    history = []
    best = None
    results = []
    for k, x0 in enumerate(cand):
        t1 = time.perf_counter()
        r = solve(fun, jac, prepare(x0), len(sub))
        history.append({"stage": "start", "start": [float(v) for v in x0], "x": [float(v) for v in r.x],
                        "cost": float(r.cost), "nfev": int(r.nfev), "status": int(r.status), "rows": len(sub),
                        "time_s": time.perf_counter() - t1})
        say(f"{channel}: start {k + 1}/{len(cand)} cost {r.cost:.6g} ({r.nfev} evaluations)")
        results.append(r)
        if best is None or r.cost < best.cost:
            best = r
    assert best is not None             # cand is not empty (checked above)
    if footprint is not None and footprint_fit:
        # The footprint-averaged model, from the two best distinct point-model optima (on the
        # same subset), each with the pixel quadrature its lobe needs; then polished below.
        chosen: list = []
        for r0 in sorted(results, key=lambda r: r.cost):
            if all(np.max(np.abs(r0.x[2:4] - c.x[2:4])) > 0.05 or abs((r0.x[4] - c.x[4] + np.pi / 2) % np.pi
                                                                      - np.pi / 2) > 0.05 for c in chosen):
                chosen.append(r0)
            if len(chosen) == 2:
                break
        fp_best = None
        for r0 in chosen:
            orders = footprint.orders_for(d.geo, r0.x, log_alpha=True)
            fp_o = footprint.with_orders(orders)
            sub = _Data(d.geo, d.W, d.y, fp_o) if idx_sub is None else _Data(sub.geo, sub.W, sub.y, fp_o.take(idx_sub))
            fun, jac = _residual_fn(sub, clip, clip_model)
            t1 = time.perf_counter()
            r = solve(fun, jac, prepare(r0.x), len(sub))
            history.append({"stage": "footprint start", "orders": list(orders), "start": [float(v) for v in r0.x],
                            "x": [float(v) for v in r.x], "cost": float(r.cost), "nfev": int(r.nfev),
                            "status": int(r.status), "rows": len(sub), "time_s": time.perf_counter() - t1})
            say(f"{channel}: footprint model from a point optimum, cost {r.cost:.6g} ({r.nfev} evaluations)")
            if fp_best is None or r.cost < fp_best[0].cost:
                fp_best = (r, fp_o, fun, jac, sub)
        assert fp_best is not None
        best, fp_o, fun, jac, sub = fp_best
        d = _Data(d.geo, d.W, d.y, fp_o)
        if idx_sub is None:
            sub = d
    if sub is not d:
        fun, jac = _residual_fn(d, clip, clip_model)
        x0 = best.x
        t1 = time.perf_counter()
        best = _polish_lm(fun, jac, x0, lb, ub, n, max_nfev)
        method = "lm"
        if best.status <= 0 or _near_bound(best.x, lb, ub):
            best = solve(fun, jac, best.x, n)
            method = "trf"
        history.append({"stage": "polish", "method": method, "start": [float(v) for v in x0],
                        "x": [float(v) for v in best.x], "cost": float(best.cost), "nfev": int(best.nfev),
                        "status": int(best.status), "rows": n, "time_s": time.perf_counter() - t1})
        say(f"{channel}: polished on all {n} samples, cost {best.cost:.6g} ({best.nfev} evaluations)")
    for _ in range(2):      # a lobe narrower than the start's: finer pixel quadrature, polish again
        if d.fp is None:
            break
        need = d.fp.orders_for(d.geo, best.x, log_alpha=True)
        if all(a_ <= b_ for a_, b_ in zip(need, d.fp.orders)):
            break
        d = _Data(d.geo, d.W, d.y, d.fp.with_orders(tuple(max(a_, b_) for a_, b_ in zip(need, d.fp.orders))))
        fun, jac = _residual_fn(d, clip, clip_model)
        x0, t1 = best.x, time.perf_counter()
        best = _polish_lm(fun, jac, x0, lb, ub, n, max_nfev)
        if best.status <= 0 or _near_bound(best.x, lb, ub):
            best = solve(fun, jac, best.x, n)
        assert d.fp is not None
        history.append({"stage": "footprint quadrature", "orders": list(d.fp.orders), "start": [float(v) for v in x0],
                        "x": [float(v) for v in best.x], "cost": float(best.cost), "nfev": int(best.nfev),
                        "status": int(best.status), "rows": n, "time_s": time.perf_counter() - t1})
        say(f"{channel}: pixel quadrature {d.fp.orders} for the narrower lobe, cost {best.cost:.6g}")
    x = np.array(best.x, float)
    if x[1] > 0 and float(np.max(np.abs(_model(np.r_[0.0, x[1:]], d)))) <= LOBE_UNSEEN * yscale:
        # a lobe the data do not see: below LOBE_UNSEEN of the data at every row, its peak where no row is. Any
        # (rho_s, alpha) of such a lobe fits equally well (the trust region may have carried rho_s anywhere along
        # that flat direction), and its off-data peak would be an extrapolation without data: the data
        # determine no lobe, reported as rho_s = 0 (at_bound; the lobe's shape then has an infinite standard error)
        history.append({"stage": "lobe unseen", "x": [float(v) for v in x], "rows": n})
        say(f"{channel}: the fitted lobe is below {LOBE_UNSEEN:g} of the data at every sample (its peak lies where "
            f"no sample is): no lobe, rho_s = 0")
        x[1] = 0.0
    f_fit = _model(x, d)
    if not (np.all(np.isfinite(x)) and math.isfinite(float(best.cost)) and np.all(np.isfinite(f_fit))):
        # the bounds keep every parameter finite on finite data; what is left is an overflow of the data's own scale
        raise InputError(f"{channel}: the Ward fit ended on non-finite parameters or model values "
                         f"({', '.join(f'{v:.4g}' for v in x)}; cost {float(best.cost):.4g}): the values (largest "
                         f"{yscale:.4g}) overflow the least-squares sums; give BRDF values in 1/sr")

    # Uncertainty (sandwich) in the solver's parameters -> reported parameters.
    r = fun(x)
    J = jac(x)          # reuses the exponentials of fun(x)
    cov_int = _sandwich(J, r)
    ax, ay = math.exp(x[2]), math.exp(x[3])
    dvec = np.array([1.0, 1.0, ax, ay, 1.0])           # d alpha / d ln alpha = alpha
    cov = cov_int * np.outer(dvec, dvec)                # elementwise: inf and NaN stay where they are
    raw = WardParams(rho_d=float(x[0]), rho_s=float(x[1]), alpha_x=ax, alpha_y=ay, lobe_rotation=float(x[4]))
    params, cov = canonical(raw, cov)
    stderr = {k: float(np.sqrt(cov[i, i])) if cov[i, i] >= 0 else float("inf") for i, k in enumerate(PARAM_NAMES)}
    at_bound = []       # the solver stays strictly inside: "at" = negligible next to the data
    if x[0] / np.pi <= 1e-6 * yscale:
        at_bound.append("rho_d")
    if x[1] / (4 * np.pi * ax * ay) <= LOBE_UNSEEN * yscale:
        at_bound.append("rho_s")
    elif x[1] >= RHO_S_MAX * (1 - 1e-6):
        at_bound.append("rho_s")
        say(f"{channel}: rho_s ends on its bound {RHO_S_MAX:g} (energy conservation with a factor 2 for the data's "
            f"scale, RHO_S_MAX): the lobe is not a physical one, or the data's scale is off")
    for name, lx in (("alpha_x", math.log(params.alpha_x)), ("alpha_y", math.log(params.alpha_y))):
        if lx <= lb[2] + 1e-6 or lx >= ub[2] - 1e-6:
            at_bound.append(name)
    stats = _residual_stats(d.y, f_fit, d.W, clip, clip_model)
    stats["n_dropped_zero_weight"] = int(n_all - n)
    unc = None
    if budget:
        from glossrig.core.fitting.uncertainty import fit_budget

        t1 = time.perf_counter()
        unc = fit_budget(params, x, raw.alpha_x < raw.alpha_y, J, r, cov, geo=d.geo, W=d.W, rows=a, groups=groups,
                         footprint=footprint, footprint_fitted=d.fp is not None, led_aperture=led_aperture,
                         calibration=calibration)
        unc["budget"]["time_s"] = round(time.perf_counter() - t1, 4)
    fp_info = d.fp.describe() if d.fp is not None else {"model": "point", "rows": n, "rows_with_jacobian":
                                                        0 if footprint is None else footprint.n_with_jacobian}
    return WardFit(channel=channel, params=params, stderr=stderr, covariance=cov, residuals=stats,
                   at_bound=at_bound, n_samples=n, weighting=weighting, clip=clip, clip_model=clip_model,
                   cost=float(best.cost), converged=bool(best.status > 0 or best.status == -2), n_starts=len(cand),
                   time_s=time.perf_counter() - t0, history=history, footprint=fp_info, uncertainty=unc)


def _near_bound(x, lb, ub, tol=1e-6):
    return bool(np.any((x - lb < tol * np.maximum(1.0, np.abs(lb))) | (ub - x < tol * np.maximum(1.0, np.abs(ub)))))


def _polish_lm(fun, jac, x0, lb, ub, n_rows, max_nfev):
    """Levenberg-Marquardt (Marquardt 1963) on the 5 x 5 normal equations, for the
    final pass over all samples from the subset's optimum, which is already
    close: each step costs one residual and one Jacobian evaluation plus
    ``J'J`` (one pass), against the several passes and the tall SVD of a
    trust-region iteration (measured: ~5x faster on 5 million samples). Steps
    are clipped into the bounds; a result on a bound (or a failure) is handed
    back to the bounded trust-region solver by the caller. Stops when a step
    lowers chi-square by less than 0.02 (see :class:`_Stall`), or when the
    quadratic model predicts less than that: with millions of rows the
    rounding error of the cost sum is of that order, and evaluating such steps
    only collects rejections."""
    from scipy.linalg import LinAlgError, cho_factor, cho_solve
    from scipy.optimize import OptimizeResult

    x = np.array(x0, float)
    r = fun(x)
    cost = 0.5 * float(r @ r)
    nfev, lam, status = 1, 1e-4, 0
    while nfev < max_nfev:
        J = jac(x)
        H = J.T @ J
        g = J.T @ r
        D = np.sqrt(np.diag(H))
        D[D == 0] = 1.0
        Hs, gs = H / np.outer(D, D), g / D
        improved = done = False
        while nfev < max_nfev:
            try:
                step = -cho_solve(cho_factor(Hs + lam * np.eye(5)), gs) / D
            except (LinAlgError, ValueError):
                lam *= 10
                if lam > 1e10:
                    break
                continue
            xn = np.clip(x + step, lb, ub)
            st = xn - x
            predicted = -float(g @ st) - 0.5 * float(st @ H @ st)
            if predicted <= 0.01 * cost / max(n_rows, 1):
                done = True                 # the quadratic model sees nothing left to gain
                break
            rn = fun(xn)
            nfev += 1
            cn = 0.5 * float(rn @ rn)
            if cn < cost:
                gain = cost - cn
                x, r, cost = xn, rn, cn
                lam = max(lam / 10, 1e-12)
                improved = True
                break
            lam *= 10
            if lam > 1e10:
                done = True                 # no downhill step at any damping: at the optimum
                break
        if not improved:
            status = 1 if done else 0
            break
        if gain <= 0.01 * cost / max(n_rows, 1):
            status = 1
            break
    return OptimizeResult(x=x, cost=cost, nfev=nfev, status=status)




class _Stall:
    """Stops the solver (``StopIteration``, status -2) once three iterations have
    lowered the cost by less than ``0.01 * cost / n``. With the cost
    ``1/2 sum r^2 ~ n sigma^2 / 2``, that is a chi-square change below 0.02: a
    parameter change of one standard error changes chi-square by 1, so what is
    left is far below the uncertainty. Where the data do not determine a direction (the lobe of a
    material with ``rho_s`` -> 0, the rotation of an isotropic lobe) the trust
    region otherwise keeps creeping along it until ``max_nfev``."""

    def __init__(self, n):
        self.n = max(int(n), 1)
        self.costs = []

    def __call__(self, intermediate_result):
        self.costs.append(float(intermediate_result.cost))
        if len(self.costs) > 3 and self.costs[-4] - self.costs[-1] <= 0.01 * self.costs[-1] / self.n:
            raise StopIteration


def _subset(d: _Data, m: int, rng, clip):
    """At most ``m`` rows for the start search: the largest weighted values (a
    fifth, so that a narrow peak is always represented) plus a uniform random
    subset. With ``clip``, clipped rows are left out (their model value is
    censored and the linear projection of the grid search does not hold)."""
    n = len(d)
    ok = np.ones(n, bool) if clip is None else d.y < clip
    idx_ok = np.flatnonzero(ok)
    if idx_ok.size < 5:
        idx_ok = np.arange(n)
    if idx_ok.size <= m:
        return idx_ok
    k_top = m // 5
    score = (d.W * d.y)[idx_ok]
    top = idx_ok[np.argpartition(-score, k_top)[:k_top]]
    rest = rng.choice(idx_ok, m - k_top, replace=False)
    return np.unique(np.concatenate([top, rest]))


# ----------------------------------------------------------------------------
# A material: luminance and every colour channel
# ----------------------------------------------------------------------------

@dataclass
class MaterialFit:
    """Fits of luminance and r, g, b, and the RGB albedos of a shared lobe.

    ``shared_rgb`` holds ``rho_d`` and ``rho_s`` per channel (r, g, b) for the
    luminance fit's lobe (``alpha_x, alpha_y, lobe_rotation``): the two
    albedos enter eq. 4.79 linearly, so given the lobe they are the
    non-negative linear least-squares solution of eq. 4.81 per channel. A
    renderer's BSDF with one lobe and RGB albedos (the twin's ``glossrig_ward``)
    takes these; the independent per-channel fits are what was measured."""

    fits: dict[str, WardFit]
    shared_rgb: dict
    source: str | None = None
    options: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        from glossrig.core.fitting.export import mitsuba_material

        out: dict[str, Any] = {"format": "glossrig-fit/1", "model": "extended Ward (thesis eq. 4.79-4.80)",
                               "canonical_form": CANONICAL_FORM, "angles": "radians",
                               "luminance_definition": "Y = 0.2126 r + 0.7152 g + 0.0722 b (Rec. 709 / sRGB, linear)",
                               "source": self.source, "options": self.options}
        for k, f in self.fits.items():
            out[k] = f.to_json()
        if "luminance" in self.fits:
            # gloss as industry measures it (ISO 2813 / ASTM D523 GU, ASTM E430 haze and DOI), issue 17
            from glossrig.core.models.gloss import gloss_from_ward

            out["luminance"]["gloss"] = gloss_from_ward(self.fits["luminance"].params)
        out["shared_lobe_rgb"] = self.shared_rgb
        out["mitsuba"] = mitsuba_material(self)
        return out


def channel_values(df, channel: str) -> np.ndarray:
    """BRDF values of ``channel`` (``r``, ``g``, ``b`` or ``luminance``, Rec. 709 Y);
    NaN where the channel (for luminance: one of r, g, b) is missing
    (:mod:`glossrig.core.samples`; :func:`fit_samples` fills luminance's gaps)."""
    if channel == "luminance":
        return luminance(df["r"], df["g"], df["b"])
    if channel in ("r", "g", "b"):
        return np.asarray(df[channel], float)
    raise InputError(f"channel must be one of {', '.join(CHANNELS)}, got {channel!r}")


def shared_lobe_albedos(df, lobe: WardParams, *, weighting: str = "mirror", clip: float | None = None,
                        sample_weight=None, footprint: SampleFootprint | None = None) -> dict:
    """Per-channel non-negative ``rho_d, rho_s`` for a fixed lobe (eq. 4.81 is
    linear in them; :func:`lobe_albedos`: ``rho_s <= RHO_S_MAX``, a lobe the channel's
    data do not see is none). Rows the clip level censors are left out, and so are the rows a
    channel is missing in (NaN, :mod:`glossrig.core.samples`) from that channel's.
    ``sample_weight``: one weight per row, or ``{channel: weights}``. With ``footprint``
    (one per row) the lobe is averaged over each channel's footprint, as fitted."""
    a = _arrays(df)
    td = np.asarray(df["theta_d"], float) if weighting == "literal" else None
    pdd = np.asarray(df["phi_d"], float) if weighting == "literal" else None
    W0 = peak_weight(a["theta_in"], a["phi_in"], a["theta_out"], a["phi_out"], td, pdd, mode=weighting)
    W = W0
    if sample_weight is not None and not isinstance(sample_weight, dict):
        W = W0 * np.sqrt(np.asarray(sample_weight, float))
    unit = WardParams(rho_d=0.0, rho_s=1.0, alpha_x=lobe.alpha_x, alpha_y=lobe.alpha_y,
                      lobe_rotation=lobe.lobe_rotation)
    d = _make_data(a["theta_in"], a["theta_out"], a["theta_h"], a["phi_h"], np.zeros(W.size), W, None)
    B = _model(solver_params(unit), d)
    out: dict[str, list[float]] = {"rho_d": [], "rho_s": []}
    for c in ("r", "g", "b"):
        if footprint is not None:
            fp_c = footprint.for_channel(c)
            fp_c = fp_c.with_orders(fp_c.orders_for(d.geo, solver_params(unit), log_alpha=True))
            B = _model(solver_params(unit), _Data(d.geo, d.W, d.y, fp_c))
        y = np.asarray(df[c], float)
        Wc = W0 * np.sqrt(np.asarray(sample_weight[c], float)) if isinstance(sample_weight, dict) else W
        Wc = np.where(np.isfinite(y) & np.isfinite(Wc), Wc, 0.0)
        y = np.where(Wc > 0, y, 0.0)
        if clip is not None:
            Wc = Wc * (y < clip)
        A, Bs, _ = lobe_albedos(B, y, Wc)
        out["rho_d"].append(A)
        out["rho_s"].append(Bs)
    return out


def fit_samples(df, *, channels: Iterable[str] = CHANNELS, weighting: str = "mirror",
                clip: float | None = None, clip_model: bool = True, use_weight_column: bool = True,
                source: str | None = None, log: Callable[[str], None] | None = None,
                footprint: bool | None = None, cfa: str = "RGGB", budget: bool = True,
                calibration: dict | None = None, led_aperture: float | None = None, **kw) -> MaterialFit:
    """Fit luminance and each colour channel of a samples table (see
    :mod:`glossrig.core.samples`) independently with :func:`fit_ward`; the
    luminance fit's lobe also serves as an extra start for the colour channels.
    Keyword arguments are passed on to :func:`fit_ward`.

    Missing channels (NaN, :mod:`glossrig.core.samples`): a colour channel is fitted on
    the rows that have it, with its own weights (``weight_<c>`` where the table has
    them, :func:`glossrig.core.samples.channel_weight`, else ``weight``). Luminance
    needs all three: a row with a missing channel contributes the luminance of its
    measured channels and, for the missing one, that channel's own fit at the row's
    geometry (a dark channel is predicted where it could not be measured; a saturated
    one where it was clipped). So every row the table has enters the luminance fit,
    and its diffuse level is not taken from the highlight alone, which is where the
    rows with every channel are when one channel is dark (issue 14). Those channels are
    fitted first for that; a channel with too few rows to fit is taken as 0 where it is
    missing (it is almost always missing for being too dark: its luminance share is then
    below its weight times the noise floor). ``options["missing_channels"]`` of the
    result counts the rows, what each channel fit had and what luminance did.

    ``footprint``: fit the footprint-averaged model (:mod:`glossrig.core.fitting.footprint_model`:
    each sample is the BRDF averaged over its Bayer block's read kernel and pixel areas,
    mapped by the Jacobian of its half-vector slope, which is taken from the table's
    neighbouring blocks; ``cfa`` the Bayer pattern). None (default): on where the
    table has what that needs (``u, v, led, rotation``, rows on the 2-px grid of Bayer
    blocks that ``glossrig extract`` writes: u, v even), else the point model;
    False: the point model (the footprint's effect then goes into the budget); True:
    required. ``budget``: each channel's GUM uncertainty budget
    (:mod:`glossrig.core.fitting.uncertainty`; the model component's blocks are the
    table's LED x rotation), ``calibration``: ``{channel: {param: u}}`` standard
    uncertainties from the calibration (absent: that component is omitted, and the
    budget says so), ``led_aperture``: the LED's angular diameter for the footprint
    component (radians; None: the rig's 0.75 mm at 300 mm; 0: a point LED)."""
    from glossrig.core.fitting.footprint_model import FOOTPRINT_COLUMNS, sample_footprint, table_jacobian

    from glossrig.core.samples import channel_weight, valid_channels

    channels = list(channels)
    if not channels:
        raise InputError("no channel to fit")
    sw = np.asarray(df["weight"], float) if (use_weight_column and "weight" in df) else None
    valid = valid_channels(df)
    complete = valid.all(axis=1)
    Jt = table_jacobian(df) if (footprint is not False or budget) else None     # budget: the point fit's footprint
    if footprint is True and Jt is None:
        raise InputError(f"footprint fit: the samples table lacks one of {', '.join(FOOTPRINT_COLUMNS)}, or its "
                         "rows are not one per 2x2 Bayer block (u, v even) as glossrig extract writes them")
    fp_base = sample_footprint(Jt, "luminance", cfa) if Jt is not None else None
    groups = (df.groupby(["led", "rotation"], sort=True).ngroup().to_numpy()
              if ("led" in df and "rotation" in df) else None)
    fits: dict[str, WardFit] = {}
    user_starts = list(kw.pop("starts", None) or [])
    missing_info: dict[str, Any] = {"rows": int(np.size(complete)), "rows_with_every_channel": int(complete.sum())}

    def fit_one(c: str, **extra) -> WardFit:
        starts = list(user_starts)
        if "luminance" in fits:
            starts.append(fits["luminance"].params)
        fp_c = None if fp_base is None else fp_base.for_channel(c)
        if c == "luminance":
            y, rows, w = lum, lum_rows, sw
        else:
            k = "rgb".index(c)
            y, rows = channel_values(df, c), valid[:, k]
            w = channel_weight(df, c) if sw is not None else None
            missing_info[c] = {"rows": int(rows.sum())}
        sel = None if rows.all() else np.flatnonzero(rows)
        if sel is not None:
            if sel.size == 0:
                raise InputError(f"{c}: the channel is missing in every row of the samples table (out of the "
                                 f"capture's dynamic range; see the extraction's dynamic_range.json)")
            y, w = y[sel], None if w is None else w[sel]
            fp_c = None if fp_c is None else fp_c.take(sel)
        f = fit_ward(df if sel is None else df.iloc[sel], y, channel=c, weighting=weighting, sample_weight=w,
                     clip=clip, clip_model=clip_model, starts=starts, log=log, footprint=fp_c,
                     footprint_fit=footprint is not False, groups=groups if groups is None or sel is None
                     else groups[sel], budget=extra.pop("budget", budget), calibration=(calibration or {}).get(c),
                     led_aperture=led_aperture, **{**kw, **extra})
        if log:
            p = f.params
            log(f"{c}: rho_d={p.rho_d:.4g} rho_s={p.rho_s:.4g} alpha_x={p.alpha_x:.4g} "
                f"alpha_y={p.alpha_y:.4g} rotation={p.lobe_rotation:.4g} rad ({f.time_s:.1f} s"
                + ("" if sel is None else f", {sel.size} of {np.size(complete)} rows: the rest miss the channel") + ")")
        return f

    lum = channel_values(df, "luminance")
    lum_rows = complete
    if "luminance" in channels and not complete.all():
        # luminance where a channel is missing: that channel's own fit predicts it (docstring)
        helpers: dict[str, WardFit | None] = {}
        for k, c in enumerate("rgb"):
            if valid[:, k].all():
                continue
            try:
                helpers[c] = fits[c] = fit_one(c) if c in channels else fit_one(c, budget=False)
            except InputError as e:
                helpers[c] = None
                missing_info[c] = {"rows": int(valid[:, k].sum()), "fit_failed": str(e)}
        from glossrig.core.models.ward import ward_from_angles

        vals = np.stack([channel_values(df, c) for c in "rgb"], axis=1)
        for c, f in helpers.items():
            k = "rgb".index(c)
            gap = ~valid[:, k]
            vals[gap, k] = 0.0 if f is None else ward_from_angles(
                df["theta_in"].to_numpy()[gap], df["theta_out"].to_numpy()[gap], df["theta_h"].to_numpy()[gap],
                df["phi_h"].to_numpy()[gap], f.params)
        lum = luminance(vals[:, 0], vals[:, 1], vals[:, 2])
        lum_rows = valid.any(axis=1)
        missing_info["luminance"] = {
            "rows": int(lum_rows.sum()), "rows_with_predicted_channels": int((lum_rows & ~complete).sum()),
            "predicted_by": {c: "0 (too few rows to fit the channel)" if f is None else
                             "the channel's own fit (point model)" for c, f in helpers.items()}}
        for c in list(fits):
            if c not in channels:
                del fits[c]
    order = sorted((c for c in channels if c not in fits), key=lambda c: c != "luminance")
    for c in order:
        fits[c] = fit_one(c)
    lobe_fit = fits.get("luminance") or next(iter(fits.values()))
    shared = shared_lobe_albedos(df, lobe_fit.params, weighting=weighting, clip=clip,
                                 sample_weight=None if sw is None else {c: channel_weight(df, c) for c in "rgb"},
                                 footprint=fp_base if footprint is not False else None)
    shared.update(alpha_x=lobe_fit.params.alpha_x, alpha_y=lobe_fit.params.alpha_y,
                  lobe_rotation=lobe_fit.params.lobe_rotation, lobe_from=lobe_fit.channel)
    opts: dict[str, Any] = {"weighting": weighting, "clip": clip, "clip_model": clip_model, "use_weight_column": use_weight_column,
            "luminance_weights": list(LUMINANCE_WEIGHTS), "footprint": fp_base is not None and footprint is not False,
            "cfa": cfa, "budget": budget, "led_aperture": led_aperture}
    opts.update({k: v for k, v in kw.items() if isinstance(v, (int, float, str, bool))})
    if not complete.all():
        opts["missing_channels"] = missing_info
    return MaterialFit(fits={c: fits[c] for c in channels}, shared_rgb=shared, source=source, options=opts)
