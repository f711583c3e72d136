"""The uncertainty budget of a Ward fit (GUM, JCGM 100:2008), per parameter and channel.

Each fitted parameter of each channel (:func:`glossrig.core.fitting.fit.fit_samples`)
gets standard uncertainties from these components, in the parameter's own unit
(``rho_d``, ``rho_s``: albedo; ``alpha_x``, ``alpha_y``: slope; ``lobe_rotation``: radians),
for the parameters in the fit's canonical form (``alpha_x >= alpha_y``, rotation in
[0, pi); the components are permuted with the axes exactly as the covariance is,
:func:`glossrig.core.fitting.fit.canonical`):

* ``noise`` - the heteroscedasticity-consistent (HC1) sandwich covariance of the fit
  (the ``<name>_stderr`` of fit.json): per-sample noise, samples taken as independent.
  Degrees of freedom ``n - 5``.
* ``model`` - what the misfit adds. Estimator: the **cluster-robust sandwich**
  (Liang & Zeger 1986, "CR1") with clusters = the samples of one LED at one sample
  rotation (the table's ``led`` x ``rotation``): the same sandwich with the score
  ``J' r`` summed within each cluster before its outer product, so residuals that are
  correlated within a cluster (a lobe shape the model misses, an LED's intensity
  error, a rotation's pose error, the unmodelled part of the footprint, which all
  act on a whole LED x rotation image at once) count with their correlation instead
  of averaging away as if independent. ``u_model^2 = max(0, var_CR - var_HC1)`` (the
  CR variance contains the independent noise too). Why this and not a block
  bootstrap over the same blocks: both estimate the same between-block variance of
  the estimate; the sandwich needs the Jacobian and residuals the fit already holds
  (one pass over the rows), the bootstrap one refit per replicate (~100 refits for a
  95 % interval): a measured budget overhead of a few per cent against a hundredfold
  fit time. Degrees of freedom ``G - 1`` for ``G`` clusters (the variance of a
  sum over G cluster scores); with few clusters the coverage factor is large
  (Student-t), as it should be. A misfit common to every cluster (the same bias in
  every image) is invisible to it, as to any resampling of the same blocks: that
  is the calibration component's business. Omitted, and said so, where the table
  has no ``led``/``rotation`` columns or fewer than 2 clusters.
* ``footprint`` - what remains of the footprint effect (each sample averages the BRDF
  over its pixels' footprint, :mod:`glossrig.core.fitting.footprint_model`), as the
  magnitude of the parameter shift it causes, linearised at the optimum
  (``dx = (J'J)^-1 J' W df``, GUM: an uncorrected systematic effect counted in full):
  the whole footprint average where the fit used the point model (with the table's
  Jacobians available), and always the **LED's finite aperture**, which no fit
  models (the twin's LED is a point; the real rig's emits through a 0.75 mm channel
  ~300 mm from the sample, ``spec/rig-facts.toml``): a uniform disc of angular
  radius ``rho`` blurs the half vector's slope with variance up to
  ``rho^2 / (16 cos^2 th_d cos^4 th_h)`` per axis, whose effect on the lobe is
  ``df = sigma^2 S (2 (u^2/ax^4 + v^2/ay^4) - 1/ax^2 - 1/ay^2)`` to second order
  (S the specular term, u, v the slopes along the lobe's axes). Type B; taken with
  8 degrees of freedom (its size known to ~25 %, GUM G.4.2).
* ``calibration`` - from an optional input: ``{channel: {param: u}}`` (or
  ``{param: {"u": u, "dof": nu}}``), standard uncertainties the calibration stages
  propagate to the parameters. Absent: the component is left out of ``components``
  and the budget's ``omitted`` says so.

Combined standard uncertainty: root sum of squares of the components (GUM 5.1.2,
the components taken as uncorrelated: they come from different sources - independent
pixel noise, block-wise misfit, the geometry of the pixels and LED, the calibration).
Expanded: ``U = k u_c`` with ``k`` Student's t at 97.5 % for the effective degrees of
freedom of the Welch-Satterthwaite formula (GUM G.4.1;
``nu_eff = u_c^4 / sum u_j^4 / nu_j``); ``interval95 = [value - U, value + U]`` in the
value's canonical form, the albedos' and alphas' lower end clipped at 0. The lobe
rotation is an angle modulo pi: its interval's ends may lie outside [0, pi) (it
wraps), and where ``U >= pi / 2`` every orientation is possible: ``[0, pi]``.
A parameter the data do not determine (infinite noise uncertainty) has ``null``
combined uncertainty and interval (the rotation: ``[0, pi]``).
"""
from __future__ import annotations

import math

import numpy as np

PARAM_NAMES = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")
COMPONENTS = ("noise", "model", "footprint", "calibration")
#: Angular diameter (radians) of the LED's emitting aperture seen from the sample, for
#: the footprint component: the rig's 0.75 mm channel at 300 mm (spec/rig-facts.toml).
DEFAULT_LED_APERTURE = 0.75 / 300.0
#: Degrees of freedom of the footprint component (type B, size known to ~25 %).
FOOTPRINT_DOF = 8.0
BUDGET_KIND = "GUM budget: noise (HC1 sandwich), model (cluster-robust sandwich, LED x rotation), " \
              "footprint (unmodelled footprint effect, linearised), calibration (given)"
_SWAP = [0, 1, 3, 2, 4]


def reporting_map(x_int, swapped: bool):
    """``(scale, perm)`` taking a vector in the solver's parameters ``(rho_d, rho_s,
    ln ax, ln ay, rot)`` to the reported canonical ones: multiply by ``scale``
    (``d alpha / d ln alpha = alpha``), then index with ``perm``."""
    scale = np.array([1.0, 1.0, math.exp(x_int[2]), math.exp(x_int[3]), 1.0])
    return scale, (_SWAP if swapped else list(range(5)))


def to_reported_cov(cov_int, x_int, swapped: bool) -> np.ndarray:
    scale, perm = reporting_map(x_int, swapped)
    cov = np.asarray(cov_int, float) * np.outer(scale, scale)
    return cov[np.ix_(perm, perm)]


def to_reported_vec(v_int, x_int, swapped: bool) -> np.ndarray:
    scale, perm = reporting_map(x_int, swapped)
    return (np.asarray(v_int, float) * scale)[perm]


def linearised_shift(J: np.ndarray, dy: np.ndarray, rel_tol: float = 1e-10) -> np.ndarray:
    """The least-squares parameter change ``(J'J)^+ J' dy`` that data changed by ``dy``
    (weighted, like the rows of ``J``) cause, linearised at the optimum; 0 along
    directions the data do not determine (the pseudo-inverse of the fit's sandwich)."""
    norms = np.sqrt(np.einsum("ij,ij->j", J, J))
    scale = np.where(norms > 0, norms, 1.0)
    Js = J / scale
    lam, V = np.linalg.eigh(Js.T @ Js)
    good = lam > rel_tol * max(lam.max(), 1e-300)
    g = Js.T @ dy
    return ((V[:, good] / lam[good]) @ (V[:, good].T @ g)) / scale


def led_slope_variance(a: dict, aperture: float) -> np.ndarray:
    """Per-row variance (per axis, upper bound) of the half vector's slope that an LED of
    angular diameter ``aperture`` (radians) causes (module docstring). ``a``: the rows'
    theta_in, phi_in, theta_out, phi_out, theta_h (radians)."""
    ti, pi_, to, po = a["theta_in"], a["phi_in"], a["theta_out"], a["phi_out"]
    cos_io = np.sin(ti) * np.sin(to) * np.cos(pi_ - po) + np.cos(ti) * np.cos(to)
    cos2_d = np.maximum(0.5 * (1.0 + cos_io), 1e-6)          # cos^2 th_d = (1 + wi.wo) / 2
    cos4_h = np.maximum(np.cos(a["theta_h"]), 1e-3) ** 4
    rho = 0.5 * aperture
    return rho * rho / (16.0 * cos2_d * cos4_h)


def blur_effect(parts, x_int, sigma2) -> np.ndarray:
    """Second-order change of eq. 4.79's specular term by an isotropic blur of slope
    variance ``sigma2`` per axis (module docstring); ``parts`` of
    :func:`glossrig.core.models.ward.ward_parts` at ``x_int`` (log alphas)."""
    u, v, base = parts
    ax2, ay2 = math.exp(2 * x_int[2]), math.exp(2 * x_int[3])
    S = base * x_int[1]
    return sigma2 * S * (2.0 * (u * u / (ax2 * ax2) + v * v / (ay2 * ay2)) - 1.0 / ax2 - 1.0 / ay2)


def _t97_5(dof: float) -> float:
    if not math.isfinite(dof) or dof > 1e7:
        return 1.959963984540054
    from scipy.special import stdtrit         # Student t's inverse CDF (scipy.stats costs ~2 s to import)

    return float(stdtrit(max(dof, 1.0), 0.975))


def _num(v):
    v = float(v)
    return v if math.isfinite(v) else None


def _calibration_entry(cal: dict | None, name: str) -> tuple[float, float] | None:
    if not cal or name not in cal or cal[name] is None:
        return None
    e = cal[name]
    if isinstance(e, dict):
        return float(e["u"]), float(e.get("dof") or math.inf)
    return float(e), math.inf


def parameter_budget(name: str, value: float, comps: dict[str, tuple[float, float]]) -> dict:
    """One parameter's entry: ``comps`` maps component -> (standard uncertainty, dof)."""
    u2 = sum(u * u for u, _ in comps.values())
    uc = math.sqrt(u2) if math.isfinite(u2) else math.inf
    if math.isfinite(uc) and uc > 0:
        # Welch-Satterthwaite (GUM G.4.1) in ratios (u_i / u_c <= 1): u ** 4 itself overflows
        # for a parameter the data cannot determine (u ~ 1e80)
        den = sum((u / uc) ** 4 / dof for u, dof in comps.values() if math.isfinite(dof) and u > 0)
        dof = 1.0 / den if den > 0 else math.inf
    else:
        dof = math.inf
    k = _t97_5(dof)
    interval = [0.0, math.pi] if name == "lobe_rotation" else None     # undetermined: every orientation
    if math.isfinite(uc):
        U = k * uc
        if name == "lobe_rotation":
            interval = [0.0, math.pi] if U >= math.pi / 2 else [value - U, value + U]
        else:
            interval = [max(value - U, 0.0), value + U]
    return {"value": float(value), "combined": _num(uc), "interval95": interval, "coverage_factor": k,
            "dof": _num(dof), "components": {c: _num(u) for c, (u, _) in comps.items()}}


def channel_budget(params, cov_noise: np.ndarray, *, n: int, cov_cluster: np.ndarray | None = None,
                   n_clusters: int = 0, footprint_shifts: dict | None = None, footprint_note: str | None = None,
                   calibration: dict | None = None) -> dict:
    """The budget of one channel (module docstring), as fit.json's ``"uncertainty"``.

    ``params``: the canonical :class:`~glossrig.core.models.ward.WardParams`;
    ``cov_noise``, ``cov_cluster``: HC1 and CR1 covariances of the reported parameters
    (None: model component omitted); ``footprint_shifts``: name -> reported 5-vector of
    parameter shifts (None: footprint component omitted, ``footprint_note`` says why);
    ``calibration``: ``{param: u}`` for this channel (None: omitted)."""
    omitted = {}
    if cov_cluster is None or n_clusters < 2:
        omitted["model"] = ("no LED x rotation blocks to estimate the misfit from (the table lacks led/rotation, "
                            "or holds fewer than 2 blocks)")
    if footprint_shifts is None:
        omitted["footprint"] = footprint_note or "not evaluated"
    if not calibration:
        omitted["calibration"] = ("no calibration uncertainties given: the budget excludes the calibration "
                                  "(intrinsics, poses, lamp positions, reference albedo)")
    out: dict = {}
    fp_u = None
    if footprint_shifts is not None:
        fp_u = np.sqrt(sum(np.asarray(v, float) ** 2 for v in footprint_shifts.values())) \
            if footprint_shifts else np.zeros(5)
    for i, name in enumerate(PARAM_NAMES):
        var_n = float(cov_noise[i, i])
        un = math.sqrt(var_n) if var_n >= 0 else math.inf
        comps: dict[str, tuple[float, float]] = {"noise": (un, float(max(n - 5, 1)))}
        if "model" not in omitted:
            assert cov_cluster is not None
            var_c = float(cov_cluster[i, i])
            um = math.sqrt(max(var_c - var_n, 0.0)) if math.isfinite(var_c) and math.isfinite(var_n) else math.inf
            comps["model"] = (um, max(n_clusters - 1, 1))
        if fp_u is not None:
            comps["footprint"] = (float(fp_u[i]), FOOTPRINT_DOF)
        cal = _calibration_entry(calibration, name)
        if cal is not None:
            comps["calibration"] = cal
        elif "calibration" not in omitted:
            omitted["calibration"] = f"no calibration uncertainty given for {name}"
        out[name] = parameter_budget(name, getattr(params, name), comps)
    out["budget"] = {
        "kind": BUDGET_KIND,
        "combination": "root sum of squares of the components, taken as uncorrelated (GUM 5.1.2)",
        "coverage": "interval95 = value +- k u_c, k = Student t(0.975) at the Welch-Satterthwaite effective "
                    "degrees of freedom (GUM G.4); lobe_rotation modulo pi",
        "dof": {"noise": max(n - 5, 1), "model": max(n_clusters - 1, 1) if "model" not in omitted else None,
                "footprint": FOOTPRINT_DOF if fp_u is not None else None},
        "n_clusters": int(n_clusters),
        "footprint_parts": ({k: [_num(x) for x in v] for k, v in footprint_shifts.items()}
                            if footprint_shifts else {}),
        "omitted": omitted,
    }
    return out


def fit_budget(params, x_int, swapped: bool, J: np.ndarray, r: np.ndarray, cov_noise: np.ndarray, *, geo, W,
               rows: dict, groups=None, footprint=None, footprint_fitted: bool = True,
               led_aperture: float | None = None, calibration: dict | None = None) -> dict:
    """The budget of one fitted channel (module docstring) from the fit's state at its
    optimum: ``x_int`` in the solver's parameters, ``swapped`` whether the canonical form
    swapped the axes, ``J`` and ``r`` the weighted Jacobian and residuals of the
    fitted rows, ``cov_noise`` the reported (canonical) HC1 covariance; ``geo``, ``W``,
    ``rows`` (theta_in, phi_in, theta_out, phi_out, theta_h arrays) the rows' geometry,
    residual weights and angles; ``groups`` their LED x rotation labels;
    ``footprint`` their :class:`~glossrig.core.fitting.footprint_model.SampleFootprint`
    (None: the table has no Jacobian), ``footprint_fitted`` whether the fit modelled it."""
    from glossrig.core.fitting.fit import _sandwich
    from glossrig.core.fitting.footprint_model import footprint_eval
    from glossrig.core.models.ward import ward_parts

    cov_cl, G = None, 0
    if groups is not None:
        labels = np.unique(np.asarray(groups), return_inverse=True)[1].ravel()
        G = int(labels.max()) + 1 if labels.size else 0
        if G >= 2:
            cov_cl = to_reported_cov(_sandwich(J, r, groups=labels), x_int, swapped)
    shifts: dict = {}
    notes = {}
    aperture = DEFAULT_LED_APERTURE if led_aperture is None else float(led_aperture)
    f_pt, parts = ward_parts(geo, x_int, log_alpha=True)
    if aperture > 0:
        df = blur_effect(parts, x_int, led_slope_variance(rows, aperture))
        shifts["led_aperture"] = np.abs(to_reported_vec(linearised_shift(J, W * df), x_int, swapped))
    if footprint is None:
        notes["footprint_pixels"] = ("the pixel footprint is not evaluated: the samples table holds no per-sample "
                                     "Jacobian (needs u, v, led, rotation); the component counts the LED only")
    elif not footprint_fitted:
        fp = footprint.with_orders(footprint.orders_for(geo, x_int, log_alpha=True))
        df = footprint_eval(geo, fp, x_int, log_alpha=True) - f_pt
        shifts["pixel_footprint"] = np.abs(to_reported_vec(linearised_shift(J, W * df), x_int, swapped))
    out = channel_budget(params, cov_noise, n=int(r.size), cov_cluster=cov_cl, n_clusters=G,
                         footprint_shifts=shifts, calibration=calibration)
    out["budget"]["led_aperture_rad"] = aperture
    out["budget"]["footprint_modelled"] = bool(footprint is not None and footprint_fitted)
    out["budget"]["omitted"].update(notes)
    return out


# ----------------------------------------------------------------------------
# Reading a budget: coverage against a truth, the printed table
# ----------------------------------------------------------------------------

def coverage(uncertainty: dict, truth) -> dict:
    """Per parameter: ``{"error": fitted - true, "u": combined, "ratio": error / u,
    "covered": truth inside interval95}`` against a truth (WardParams or dict), both in
    canonical form; the rotation's error is taken modulo pi."""
    from glossrig.core.fitting.fit import canonical
    from glossrig.core.models.ward import WardParams

    t = truth if isinstance(truth, WardParams) else WardParams(**{k: float(truth[k]) for k in PARAM_NAMES})
    t, _ = canonical(t)
    out = {}
    for name in PARAM_NAMES:
        e = uncertainty[name]
        err = e["value"] - getattr(t, name)
        if name == "lobe_rotation":
            err = (err + math.pi / 2) % math.pi - math.pi / 2
        u, iv = e["combined"], e["interval95"]
        if u is None or iv is None:
            out[name] = {"error": err, "u": None, "ratio": None, "covered": None}
            continue
        if name == "lobe_rotation":
            covered = iv == [0.0, math.pi] or abs(err) <= (iv[1] - iv[0]) / 2
        else:
            covered = iv[0] <= getattr(t, name) <= iv[1]
        out[name] = {"error": err, "u": u, "ratio": err / u if u > 0 else math.inf, "covered": bool(covered)}
    return out


def read_uncertainty(obj) -> dict | None:
    """A channel's ``"uncertainty"`` as fit.json holds it (None: the file has none),
    checked: every parameter's ``combined`` a number >= 0 or null, ``interval95`` two
    numbers or null, ``components`` numbers >= 0 or null. Raises ValueError."""
    if obj is None:
        return None
    if not isinstance(obj, dict):
        raise ValueError("uncertainty must be an object")

    def number(v, what):
        if v is None:
            return None
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise ValueError(f"uncertainty: {what} must be a number >= 0 or null, got {v!r}")
        return float(v)

    out = dict(obj)
    for name in PARAM_NAMES:
        e = obj.get(name)
        if not isinstance(e, dict) or not isinstance(e.get("components"), dict):
            raise ValueError(f"uncertainty.{name} must be an object with combined, interval95 and components")
        e = dict(e)
        e["combined"] = number(e.get("combined"), f"{name}.combined")
        iv = e.get("interval95")
        if iv is not None:
            if not (isinstance(iv, list) and len(iv) == 2 and all(isinstance(v, (int, float)) for v in iv)):
                raise ValueError(f"uncertainty: {name}.interval95 must be [lo, hi] or null, got {iv!r}")
            iv = [float(v) for v in iv]
        e["interval95"] = iv
        e["components"] = {k: number(v, f"{name}.components.{k}") for k, v in e["components"].items()}
        out[name] = e
    return out


def _g(v, unit_deg=False, digits: int = 3) -> str:
    if v is None:
        return "-"
    return f"{math.degrees(v):.{digits}g}d" if unit_deg else f"{v:.{digits}g}"


def significant_digits(value: float, u) -> int:
    """Significant digits that show ``value`` to about a tenth of ``u``."""
    if u is None or not u > 0 or value == 0:
        return 4
    return int(min(10, max(3, math.ceil(math.log10(abs(value) / u)) + 2)))


def budget_table(fits: dict) -> str:
    """The budget of every channel as a text table (the ``glossrig fit`` summary):
    ``fits``: channel -> :class:`~glossrig.core.fitting.fit.WardFit`. Rotation in
    degrees (suffix d)."""
    head = (f"{'channel':9s} {'parameter':13s} {'value':>11s} {'noise':>8s} {'model':>8s} {'footprint':>9s} "
            f"{'calib.':>8s} {'combined':>8s} {'k':>5s}  95 % interval")
    lines = [head]
    omitted: set[str] = set()
    for ch, f in fits.items():
        unc = getattr(f, "uncertainty", None)
        if not unc:
            lines.append(f"{ch:9s} (no uncertainty budget)")
            continue
        for name in PARAM_NAMES:
            e = unc[name]
            deg = name == "lobe_rotation"
            c = e["components"]
            iv = e["interval95"]
            n = significant_digits(e["value"], e["combined"])
            ivs = "-" if iv is None else f"[{_g(iv[0], deg, n)}, {_g(iv[1], deg, n)}]"
            lines.append(f"{ch:9s} {name:13s} {_g(e['value'], deg, n):>11s} {_g(c.get('noise'), deg):>8s} "
                         f"{_g(c.get('model'), deg):>8s} {_g(c.get('footprint'), deg):>9s} "
                         f"{_g(c.get('calibration'), deg):>8s} {_g(e['combined'], deg):>8s} "
                         f"{e['coverage_factor']:5.2f}  {ivs}")
        omitted.update(f"{k}: {v}" for k, v in unc.get("budget", {}).get("omitted", {}).items())
    lines.append("standard uncertainties in each parameter's unit (rotation in degrees, d); combined = root sum of "
                 "squares; 95 % interval = value +- k combined (Student t, Welch-Satterthwaite)")
    lines += [f"omitted - {o}" for o in sorted(omitted)]
    return "\n".join(lines)
