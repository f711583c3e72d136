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

A named BRDF-space cause (other than the flexible model itself) must explain what it is
named for: the residual of its own extended model (fitted on all rows) is binned again and
the entries are reported with ``"after": <cause>``; in BRDF space these entries, not the
flexible model's, then decide. For an instrument cause the variables are the image and
cylinder position (POSITION_VARS), which every such cause acts through: structure that
remains there means the cause only absorbed part of an effect outside the catalogue
(a step of the values along the cylinder axis, which a per-LED tilt of the LED emission fits
in part, was named ``led_emission`` before this rule; now it is "unexplained" along the axis:
tests/test_diagnose_extensions.py::test_axis_step_outside_the_catalogue_is_unexplained_along_the_axis),
so the verdict is "unexplained" with that variable, not a wrong named cause. Position only: an instrument model carries no
material freedom, so its residual keeps any material departure in the angles and the signal
level. For a named material or reference model the variables are the BRDF-space instrument
variables (position and signal level), which no material can follow: a material model that
explains the data better than the flexible one - a grazing rise of the diffuse term follows
theta_in and theta_out, not the flexible model's theta_h - leaves none there, while the
flexible model's residual may still sort by the signal level (a synthetic grazing term is
named ``grazing_lobe``, not "unexplained":
tests/test_diagnose_extensions.py::test_grazing_lobe_found_with_its_parameter).
After a material model the residual is compared *within cells of the isotropic angles*
(ANGLE_BINS quantile bins of theta_h, theta_d and theta_in; each row minus its cell's mean):
on a glossy material the image position and the signal level follow the lobe angles (the
highlight sits at one place of the image per LED), so a named model's remaining misfit in the
angles also sorts by position and signal (without the cells, the rgl study's golden yellow
got "unexplained" instead of ggx_lobe, the best extension against the truth; the study's
current verdicts: validation/diagnose/rgl_study.md). What an instrument does to position
varies within an angle cell, as the LEDs and rotations see the same angles at other places.
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
#: image and cylinder position: what remains there after a named instrument cause is tested again
POSITION_VARS = ("distance_from_optical_centre", "axis_position")
#: ... and after a named material or reference model: position and the signal level
MATERIAL_AFTER_VARS = POSITION_VARS + ("signal",)
ANGLE_BINS = 6            # quantile bins per angle of the cells the material model's residual is compared within


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


def unexplained(m, frame_structure: dict | None = None, after=None) -> list[dict]:
    """One entry per variable: ``{"variable", "space", "effect", "p", "significant", ...}``;
    ``after``: the named BRDF-space cause (a :class:`~glossrig.core.diagnose.catalogue.CauseResult`
    with its ``prediction``), whose residual is tested again against POSITION_VARS (an instrument
    cause) or MATERIAL_AFTER_VARS (module docstring)."""
    c = m.cols
    pred = getattr(m, "flexible_prediction", None)
    if pred is None:
        from glossrig.core.diagnose.flexible import fit_flexible

        _, pred = fit_flexible(m, np.ones(len(c["y"]), bool))
    vars_ = brdf_variables(m)
    frame_vars = {"exposure_s": "exposure_s (log10)", "capture_order": "capture order (min from sequence middle)",
                  "frame_signal": "signal (log10 DN)"}
    again = after is not None and getattr(after, "prediction", None) is not None
    names = (POSITION_VARS if getattr(after, "kind", "instrument") == "instrument" else MATERIAL_AFTER_VARS) \
        if again else ()
    n_tests = len(vars_) + (len(frame_vars) if frame_structure else 0) + len(names)
    level = P_LEVEL / max(n_tests, 1)
    out = _brdf_entries(m, pred, vars_, level)
    if again:
        out += _brdf_entries(m, after.prediction, {k: vars_[k] for k in names}, level, after=after.name,
                             partial_angles=getattr(after, "kind", "instrument") != "instrument")
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


def retested_cause(causes: list, named: str):
    """The cause whose own residual :func:`unexplained` tests again (its ``after``): the catalogue's
    verdict ``named`` (:func:`glossrig.core.diagnose.report.verdict`) when it is a BRDF-space cause
    with a prediction at every row, other than the flexible model (whose residual is the baseline
    every entry already tests); else None."""
    c = next((c for c in causes if c.name == named), None)
    if c is None or c.space != "brdf" or c.name == "flexible_material" or c.prediction is None:
        return None
    return c


def angle_cells(m, n: int = ANGLE_BINS) -> np.ndarray:
    """Cell index of each row in the isotropic angles: ``n`` quantile bins of theta_h, theta_d and
    theta_in each (n^3 cells)."""
    idx = np.zeros(len(m.cols["y"]), int)
    for k in ("theta_h", "theta_d", "theta_in"):
        x = np.asarray(m.cols[k], float)
        edges = np.unique(np.quantile(x, np.linspace(0, 1, n + 1)))
        idx = idx * n + np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n - 1)
    return idx


def _within_cells(x, cells) -> np.ndarray:
    """``x`` minus the mean of its angle cell."""
    cnt = np.bincount(cells)
    mean = np.bincount(cells, weights=x) / np.maximum(cnt, 1)
    return x - mean[cells]


def _brdf_entries(m, pred, vars_: dict, level: float, after: str | None = None,
                  partial_angles: bool = False) -> list[dict]:
    """Structure tests of the BRDF-space residual ``y - pred`` against each of ``vars_``;
    ``partial_angles``: within angle cells (:func:`angle_cells`, module docstring)."""
    c = m.cols
    res = c["y"] - pred
    z = res / c["sigma"]
    rel = res / np.maximum(np.abs(pred), 1e-9)
    if partial_angles:
        cells = angle_cells(m)
        z, rel = _within_cells(z, cells), _within_cells(rel, cells)
    out = []
    for k, x in vars_.items():
        t = structure_test(x, z, rel)
        e = {"variable": k, "space": "brdf", "effect": t["effect"], "effect_unit": "relative BRDF residual",
             "p": t["p"], "significant": bool(t["p"] < level and t["effect"] > EFFECT_MIN),
             "profile": {"x": t["x"], "mean": t["mean"], "n": t["n"]}}
        if after:
            e["after"] = after
        if partial_angles:
            e["within_angle_cells"] = True
        out.append(e)
    return out


def open_world_verdict(named: str, kind: str | None, entries: list[dict]) -> str:
    """``named`` (the catalogue's verdict) or "unexplained" (rule in the module docstring)."""
    sig = [e for e in entries if e["significant"]]
    if not sig:
        return named
    if named == "none":
        return "unexplained"
    after = [e for e in entries if e.get("after") == named]
    if after:
        # in BRDF space the named cause's own residual decides (module docstring)
        if any(e["significant"] for e in after):
            return "unexplained"
        sig = [e for e in sig if e.get("space") != "brdf"]
    if kind in ("material", "reference") and any(e["variable"] in INSTRUMENT_VARS or e["variable"] == "frame_signal"
                                                 for e in sig):
        return "unexplained"
    return named
