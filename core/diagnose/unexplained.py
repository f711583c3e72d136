"""Open world (issue 14, item 5): structured residual that no catalogue cause explains.

After every smooth material departure is taken out (the flexible material model of
:mod:`.flexible`, fitted on all rows), the BRDF-space residuals, normalised by the
calibrated sigma of :mod:`.error_model`, are binned against each variable a cause could
follow - the angles (theta_h, theta_d, theta_in, theta_out, phi_h), the LED, the
distance from the optical centre, the position along the cylinder axis and the signal
level - and the frame-space residuals of the linear sensor against exposure time,
capture order and signal (:func:`glossrig.core.diagnose.residuals.frame_structure`).

A variable carries *significant* structure when its bin means are inconsistent with zero
(chi^2 of the bin means, ``sum n_k m_k^2`` on as many degrees of freedom as bins, beyond
the Bonferroni-corrected level P_LEVEL over all variables tested) **and** the effect is
large: in BRDF space the spread of the bins' mean relative residual exceeds EFFECT_MIN,
in frame space the spread of the bins' mean normalised residual exceeds
FRAME_EFFECT_MIN (sigma units). The verdict is "unexplained" when such structure
remains and no eligible named cause is significant, or when the verdict would be a
material cause (which cannot act on image position, the LED, the signal level or the
exposure) while structure remains in one of those instrument variables.
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2 as chi2_dist

P_LEVEL = 1e-4            # family-wise false-alarm level of the structure tests
EFFECT_MIN = 0.02         # BRDF space: spread of bin means of the relative residual
FRAME_EFFECT_MIN = 1.0    # frame space: spread of bin means of the normalised residual (sigma)
#: variables a material's BRDF cannot depend on (structure there is not a material departure)
#: (the LED is not one: a material's theta_d dependence sorts by LED, as each LED sees its own theta_d)
INSTRUMENT_VARS = ("distance_from_optical_centre", "axis_position", "signal", "exposure_s", "capture_order")


def _bins(x, n=10):
    x = np.asarray(x, float)
    u = np.unique(x[np.isfinite(x)])
    if u.size <= 20:
        return np.searchsorted(u, x), u
    edges = np.unique(np.quantile(x[np.isfinite(x)], np.linspace(0, 1, n + 1)))
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, len(edges) - 2)
    return idx, 0.5 * (edges[1:] + edges[:-1])


def structure_test(x, z, rel=None, n_bins=10) -> dict:
    """Bin ``z`` (normalised residuals) against ``x``: the chi^2 of the bin means (unit
    variance under the null) and the effect, the spread of the bin means of ``rel``
    (relative residuals; ``z`` itself when None)."""
    x, z = np.asarray(x, float), np.asarray(z, float)
    rel = z if rel is None else np.asarray(rel, float)
    ok = np.isfinite(x) & np.isfinite(z) & np.isfinite(rel)
    idx, centres = _bins(x[ok], n_bins)
    z, rel = z[ok], rel[ok]
    stat, means, cnt = 0.0, [], []
    for k in range(len(centres)):
        s = idx == k
        if s.sum() < 5:
            means.append(float("nan"))
            cnt.append(int(s.sum()))
            continue
        stat += float(s.sum() * z[s].mean() ** 2)
        means.append(float(rel[s].mean()))
        cnt.append(int(s.sum()))
    dof = max(sum(1 for c in cnt if c >= 5), 1)
    mm = np.array(means, float)
    effect = float(np.nanmax(mm) - np.nanmin(mm)) if np.isfinite(mm).any() else 0.0
    return {"chi2": stat, "dof": dof, "p": float(chi2_dist.sf(stat, dof)), "effect": effect,
            "x": [float(c) for c in centres], "mean": means, "n": cnt}


def brdf_variables(m) -> dict:
    from glossrig.core.diagnose.catalogue import vignetting_factor

    c, d = m.cols, m.data
    deg = np.degrees
    return {"theta_h": deg(c["theta_h"]), "theta_d": deg(c["theta_d"]), "theta_in": deg(c["theta_in"]),
            "theta_out": deg(c["theta_out"]), "phi_h": deg(c["phi_h"]), "led": c["led"],
            "distance_from_optical_centre": np.sqrt(vignetting_factor(c["u"] + 1.0, c["v"] + 1.0, d.image_size,
                                                                      d.principal_point)),
            "axis_position": d.table["y"].to_numpy(float)[m.rows] if "y" in d.table else np.full(len(c["y"]), np.nan),
            "signal": np.log10(np.maximum(c["signal"], 1e-6))}


def unexplained(m, frame_structure: dict | None = None) -> list[dict]:
    """One entry per variable: ``{"variable", "space", "effect", "p", "significant", ...}``."""
    c = m.cols
    pred = getattr(m, "flexible_prediction", None)
    if pred is None:
        from glossrig.core.diagnose.flexible import fit_flexible

        _, pred = fit_flexible(m, np.ones(len(c["y"]), bool))
    res = c["y"] - pred
    z = res / c["sigma"]
    rel = res / np.maximum(np.abs(pred), 1e-9)
    vars_ = brdf_variables(m)
    frame_vars = {"exposure_s": "exposure_s (log10)", "capture_order": "capture order (min from sequence middle)",
                  "frame_signal": "signal (log10 DN)"}
    n_tests = len(vars_) + (len(frame_vars) if frame_structure else 0)
    level = P_LEVEL / max(n_tests, 1)
    out = []
    for k, x in vars_.items():
        t = structure_test(x, z, rel)
        out.append({"variable": k, "space": "brdf", "effect": t["effect"], "effect_unit": "relative BRDF residual",
                    "p": t["p"], "significant": bool(t["p"] < level and t["effect"] > EFFECT_MIN),
                    "profile": {"x": t["x"], "mean": t["mean"], "n": t["n"]}})
    for k, key in (frame_vars.items() if frame_structure else ()):
        b = (frame_structure or {}).get(key)
        if not b or not b.get("n"):
            continue
        mean, n = np.asarray(b["mean"], float), np.asarray(b["n"], float)
        g = np.isfinite(mean) & (n >= 5)
        stat = float(np.sum(n[g] * mean[g] ** 2))
        p = float(chi2_dist.sf(stat, max(int(g.sum()), 1)))
        eff = float(mean[g].max() - mean[g].min()) if g.any() else 0.0
        out.append({"variable": k, "space": "frames", "effect": eff, "effect_unit": "normalised DN residual (sigma)",
                    "p": p, "significant": bool(p < level and eff > FRAME_EFFECT_MIN),
                    "profile": {"x": b["x"], "mean": b["mean"], "n": b["n"]}})
    return out


def open_world_verdict(named: str, kind: str | None, entries: list[dict]) -> str:
    """``named`` (the catalogue's verdict) or "unexplained" (rule in the module docstring)."""
    sig = [e for e in entries if e["significant"]]
    if not sig:
        return named
    if named == "none":
        return "unexplained"
    if kind in ("material", "reference") and any(e["variable"] in INSTRUMENT_VARS or e["variable"] == "frame_signal"
                                                 for e in sig):
        return "unexplained"
    return named
