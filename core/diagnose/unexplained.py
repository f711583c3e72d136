"""Open world (issue 14, item 5): structured residual that no catalogue cause explains.

After every smooth material departure is taken out (the flexible material model of
:mod:`.flexible`), the BRDF-space residual is tested against each variable a cause could
follow - the angles (theta_h, theta_d, theta_in, theta_out, phi_h), the LED, the distance
from the optical centre, the position along the cylinder axis and the signal level - and the
frame-space residual of the linear sensor against exposure time, capture order and signal
(:func:`glossrig.core.diagnose.residuals.frame_structure`).

The criterion, stated (the causes' own, :mod:`.catalogue` and :mod:`.error_model`): structure
along a variable x is *significant* only when it predicts held-out data. The extension is a
smooth function of x - a relative correction ``pred (1 + g(x))`` with g piecewise constant on
N_BINS quantile bins of the *training* rows' x (the distinct values when there are at most
DISCRETE of them; held-out rows beyond the training range take the edge bin's value, and
a discrete value the training rows never took gets no correction) - fitted by weighted least
squares on the training folds (weights pred^2 / sigma^2, the same normalised residual every
cause is fitted with) and scored on the held-out folds, against the model it extends fitted
on the same training folds.
Folds: leave one LED out (:meth:`glossrig.core.diagnose.catalogue.BrdfModel.folds`, as every
BRDF-space cause); for the LED itself, which no held-out LED can be predicted by, the two
halves of the pixel rows (:meth:`~glossrig.core.diagnose.catalogue.BrdfModel.halves`: a
per-LED structure must hold on both sides of the cylinder). Significant iff the extended
model's held-out error, divided by the calibrated sigma of :mod:`.error_model` (noise plus the
base model's misfit term, Huber-weighted: the sigma the causes are divided by), is lower than
its base's in every fold - or every fold but the few the catalogue's sign test allows
(:func:`glossrig.core.diagnose.catalogue.consistent_folds`: one of eight to ten LEDs) - and the
pooled relative gain exceeds the BRDF space's
``threshold + penalty x (bins of g)`` (:data:`glossrig.core.diagnose.catalogue.THRESHOLDS`).
The test asks whether a cause outside the catalogue would pass the catalogue's own test.
Structure that does not transfer across LEDs - a glossy material's misfit that lands at
another image position under each LED - is therefore not significant, however small its
chi^2 p-value on 60 000 rows; an instrument effect outside the catalogue (a step of the
values along the cylinder axis, the same under every LED) is. Each entry also reports the
in-sample description of the structure: ``effect`` (the spread of the bin means of the
relative residual on all rows), ``p`` (chi^2 of the bin means of the normalised residual,
:func:`structure_test`) and the binned ``profile``; neither decides.

Frame space keeps the in-sample rule: the frame structure arrives as bins over all exposures
(:func:`glossrig.core.diagnose.residuals.frame_structure`, no folds), so a variable is
significant there when its bin means are inconsistent with zero (chi^2 beyond P_LEVEL,
Bonferroni-corrected over the frame variables) and spread by more than FRAME_EFFECT_MIN sigma.
One more frame entry comes from the frames' gains (space ``frame_gains``,
:func:`glossrig.core.diagnose.frame_gains.camera_structure`): a gain common to every LED at each
exposure time beyond the LEDs' trends and the shutter term - a camera effect that follows the
exposure setting, which neither an LED nor a shutter error makes - significant by its own chi^2
test at the 4-sigma tail, its effect the common gain's most significant step between adjacent
exposure times; not judged where a sensor cause whose terms bend the gains (a black offset, a
compression) is named. A 3 % gain on the frames of 1 s or longer spreads the pixel residual by
0.59 sigma only (under FRAME_EFFECT_MIN, on a matte twin capture's crop), while its gains'
statistic reads 1253 against 50.5.

Which model's residual: the flexible material model's for every variable (refitted on each
fold's training rows). A named BRDF-space cause must also explain what it is named for: its
residual is tested again and those entries carry ``"after": <cause>``; in BRDF space they,
not the flexible baseline's, then decide. After an instrument cause the variables are the
image and cylinder position (POSITION_VARS), which every such cause acts through: structure
that still predicts held-out LEDs there means the cause only absorbed part of an effect
outside the catalogue (a step along the cylinder axis, which a per-LED tilt of the LED
emission fits in part, was named ``led_emission`` before this rule:
tests/test_diagnose_extensions.py::test_axis_step_outside_the_catalogue_is_unexplained_along_the_axis).
After a material or reference model - the flexible one included - the variables are again
the image and cylinder position, which no material can follow, compared *within cells of the
isotropic angles*: both the base and the extended model carry a relative correction per cell
(ANGLE_BINS quantile bins of theta_h, theta_d and theta_in; fitted on the training folds by
backfitting with g), so the test asks what x adds beyond any function of the angles - on a
glossy material the image position follows the lobe angles (the highlight sits at one place
of the image per LED), and a material model's remaining misfit in the angles would otherwise
sort by it. The BRDF-space signal level is not tested again there: it is the BRDF times the
irradiance, so within an angle cell it still follows the lobe's height, and a named lobe's
remaining shape misfit predicts held-out LEDs along it (measured: after ggx_lobe on the rgl
study's cc_ibiza_sunset, +11 % held-out gain within angle cells, every fold positive); a
response error of the sensor is tested where it acts, on the raw exposure series (the
frame-space causes and the frame_signal entry). The named model's prediction is its fit on
all rows (the causes keep no per-fold prediction), the flexible one's is refitted per fold.

The verdict (:func:`open_world_verdict`): the catalogue's verdict - the best eligible
significant cause (:func:`glossrig.core.diagnose.report.verdict`) - unless held-out structure
remains that it does not explain: "unexplained" when no cause is significant but some variable
carries significant structure, when structure remains after the named BRDF-space cause (its
``after`` entries: these replace the flexible baseline's BRDF-space entries in the decision),
or when the named cause is a material or reference model while an instrument variable
(INSTRUMENT_VARS) carries significant structure - in frame space, or in BRDF
space when the named model has no prediction to test again. A named frame- or pixel-space
cause stands whatever the BRDF-space entries say (sensor causes are named first,
:func:`glossrig.core.diagnose.report.verdict`). Every entry is reported, significant or not
(report.json ``"unexplained"``).
"""
from __future__ import annotations

import numpy as np
from scipy.stats import chi2 as chi2_dist

P_LEVEL = 1e-4            # family-wise false-alarm level of the frame-space structure tests
FRAME_EFFECT_MIN = 1.0    # frame space: spread of bin means of the normalised residual (sigma)
N_BINS = 10               # quantile bins of the smooth function g(x) of the held-out test
DISCRETE = 20             # a variable with at most this many distinct values is binned by value
BACKFIT_ROUNDS = 3        # rounds of backfitting g(x) and the angle cells' correction
#: variables a material's BRDF cannot depend on (structure there is not a material departure)
#: (the LED is not one: a material's theta_d dependence sorts by LED, as each LED sees its own theta_d)
#: (nor is the BRDF-space signal level, the BRDF times the irradiance: module docstring; the frame signal is)
INSTRUMENT_VARS = ("distance_from_optical_centre", "axis_position", "exposure_s", "capture_order", "frame_signal")
#: image and cylinder position: what remains there after a named BRDF-space cause is tested again
POSITION_VARS = ("distance_from_optical_centre", "axis_position")
ANGLE_BINS = 6            # quantile bins per angle of the cells the material model's residual is compared within


def _bins(x, n=N_BINS):
    """:func:`training_bins` with every row training (``x`` finite), and each bin's centre."""
    x = np.asarray(x, float)
    idx, _ = training_bins(x, np.ones(len(x), bool), n)
    values, discrete = _bin_grid(x, n)
    return idx, values if discrete else 0.5 * (values[1:] + values[:-1])


def _bin_grid(xt, n: int) -> tuple[np.ndarray, bool]:
    """The bins of values ``xt`` (finite): their distinct values when at most DISCRETE (True),
    else the edges of ``n`` quantile bins (False)."""
    u = np.unique(xt)
    if u.size <= DISCRETE:
        return u, True
    return np.unique(np.quantile(xt, np.linspace(0, 1, n + 1))), False


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


def training_bins(x, train, n: int = N_BINS) -> tuple[np.ndarray, int]:
    """Bin of every row from the ``train`` rows' values of ``x``: their distinct values when at
    most DISCRETE (a row whose value the training rows never took: -1), else ``n`` quantile
    bins of them (rows beyond their range in the edge bins); -1 where x is not finite.
    Returns (index per row, number of bins)."""
    x = np.asarray(x, float)
    ok = np.isfinite(x)
    xt = x[train & ok]
    idx = np.full(len(x), -1)
    if xt.size == 0:
        return idx, 0
    grid, discrete = _bin_grid(xt, n)
    if discrete:
        j = np.clip(np.searchsorted(grid, x[ok]), 0, grid.size - 1)
        idx[ok] = np.where(grid[j] == x[ok], j, -1)
        return idx, int(grid.size)
    idx[ok] = np.clip(np.searchsorted(grid, x[ok], side="right") - 1, 0, len(grid) - 2)
    return idx, len(grid) - 1


def bin_factor(idx, nb: int, res, pred, sigma, train) -> np.ndarray:
    """Per row, the weighted least-squares relative correction of its bin: g_k minimising
    sum ((res - pred g_k) / sigma)^2 over the ``train`` rows of bin k (0 for rows without a bin
    or bins without training rows)."""
    sel = train & (idx >= 0)
    w = pred[sel] / sigma[sel] ** 2
    num = np.bincount(idx[sel], weights=w * res[sel], minlength=nb)
    den = np.bincount(idx[sel], weights=w * pred[sel], minlength=nb)
    g = np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0)
    return np.where(idx >= 0, g[np.maximum(idx, 0)], 0.0)


def _chi2(r, s) -> float:
    return float(np.mean((r / s) ** 2)) if r.size else float("nan")


def heldout_structure(m, pred, x, folds, cells=None) -> dict:
    """The held-out test of the module docstring: does a smooth function g of ``x``, fitted on
    each fold's training rows as a relative correction of ``pred`` (an array for every row, or
    callable(train) -> array: the model refitted on the fold), lower the held-out error of the
    test rows? ``cells``: per-row angle cell index; base and extension then both carry a
    correction per cell (backfitted with g). Returns the pooled base and extended held-out
    errors, the gain, the fold gains, the bins of g, the threshold and ``significant``."""
    from glossrig.core.diagnose.catalogue import THRESHOLDS, consistent_folds

    c = m.cols
    y, s = c["y"], c["sigma"]
    x = np.asarray(x, float)
    e0s = e1s = 0.0
    n, nbs, gains = 0, [], []
    for train, test in folds:
        tr, te = train & np.isfinite(x), test & np.isfinite(x)
        if not tr.any() or not te.any():
            continue
        p = np.asarray(pred(train) if callable(pred) else pred, float)
        idx, nb = training_bins(x, tr)
        h = np.zeros(len(y))
        if cells is not None:
            ncell = int(cells.max()) + 1
            h = bin_factor(cells, ncell, y - p, p, s, tr)
        base = p * (1 + h)
        g = np.zeros(len(y))
        for _ in range(BACKFIT_ROUNDS if cells is not None else 1):
            g = bin_factor(idx, nb, y - p * (1 + h), p, s, tr)
            if cells is not None:
                h = bin_factor(cells, ncell, y - p * (1 + g), p, s, tr)
        ext = p * (1 + g + h)
        e0, e1 = _chi2((y - base)[te], s[te]), _chi2((y - ext)[te], s[te])
        k = int(te.sum())
        e0s, e1s, n = e0s + e0 * k, e1s + e1 * k, n + k
        gains.append((e0 - e1) / e0 if e0 > 0 else 0.0)
        nbs.append(nb)
    t, pen = THRESHOLDS["brdf"]
    nb = max(nbs) if nbs else 0
    thr = t + pen * nb
    if n == 0 or nb < 2:
        return {"heldout_base_error": None, "heldout_error": None, "gain": None, "fold_gains": gains,
                "n_params": nb, "threshold": thr, "significant": False,
                "note": "not testable: the variable takes one value (or none) on the training rows"}
    gain = (e0s - e1s) / e0s if e0s > 0 else 0.0
    return {"heldout_base_error": e0s / n, "heldout_error": e1s / n, "gain": gain, "fold_gains": gains,
            "n_params": nb, "threshold": thr, "significant": bool(gain > thr and consistent_folds(gains))}


def unexplained(m, frame_structure: dict | None = None, after=None, after_model=None) -> list[dict]:
    """One entry per variable: ``{"variable", "space", "effect", "significant", "gain",
    "threshold", "fold_gains", "split", "p", "profile", ...}`` (module docstring); ``after``: the
    named BRDF-space cause (a :class:`~glossrig.core.diagnose.catalogue.CauseResult` with its
    ``prediction``), whose residual is tested again against POSITION_VARS (within angle cells
    after a material or reference model); ``after_model``: the model ``after`` was fitted on, whose
    noise its entries are judged with (an instrument cause's conditioned model,
    :func:`glossrig.core.diagnose.catalogue.instrument_bases`; default ``m``)."""
    from glossrig.core.diagnose.flexible import fit_flexible

    c = m.cols

    def flexible(train):
        return fit_flexible(m, train)[1]

    pred_all = getattr(m, "flexible_prediction", None)
    if pred_all is None:
        pred_all = flexible(np.ones(len(c["y"]), bool))
    vars_ = brdf_variables(m)
    again = after is not None and getattr(after, "prediction", None) is not None
    material = getattr(after, "kind", "instrument") != "instrument"
    names = POSITION_VARS if again else ()
    out = _brdf_entries(m, flexible, pred_all, vars_)
    if again:
        pa = flexible if after.name == "flexible_material" else after.prediction
        # after.prediction: the cause fitted on all rows (the flexible one's equals pred_all, flexible_cause)
        out += _brdf_entries(after_model if after_model is not None else m, pa, after.prediction,
                             {k: vars_[k] for k in names}, after=after.name, partial_angles=material)
    return out + frame_entries(frame_structure)


def frame_entries(frame_structure: dict | None) -> list[dict]:
    """The frame-space entries of :func:`unexplained` (module docstring): the linear sensor's residual binned
    by exposure time, capture order and signal (:func:`glossrig.core.diagnose.residuals.frame_structure`,
    in-sample rule), and the frame gains' structure common to the LEDs per exposure time
    (:func:`glossrig.core.diagnose.frame_gains.camera_structure`, its own test)."""
    from glossrig.core.diagnose.frame_gains import CAMERA_KEY

    out: list[dict] = []
    frame_vars = {"exposure_s": "exposure_s (log10)", "capture_order": "capture order (min from sequence middle)",
                  "frame_signal": "signal (log10 DN)"}
    n_frame = len(frame_vars) if frame_structure else 0
    level = P_LEVEL / max(n_frame, 1)
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
                    "split": "none (in-sample chi^2 of the bin means, module docstring)",
                    "profile": {"x": b["x"], "mean": b["mean"], "n": b["n"]}})
    cam = (frame_structure or {}).get(CAMERA_KEY)
    if cam is not None:
        out.append({"variable": "exposure_s", "space": "frame_gains", "effect": cam["effect"],
                    "effect_unit": "relative gain common to the LEDs (its largest step between exposure times)",
                    "p": float(chi2_dist.sf(cam["chi2"], cam["dof"])), "significant": cam["significant"],
                    "split": "none (in-sample chi^2 drop of the frame gains' fit, frame_gains.camera_structure)",
                    "note": cam["note"], "profile": {"x": cam["x"], "mean": cam["mean"], "n": cam["n"]}})
    return out


def retested_cause(causes: list, named: str):
    """The cause whose own residual :func:`unexplained` tests again (its ``after``): the catalogue's
    verdict ``named`` (:func:`glossrig.core.diagnose.report.verdict`) when it is a BRDF-space cause
    with a prediction at every row (the flexible material model included: its residual is then
    tested within angle cells); else None."""
    c = next((c for c in causes if c.name == named), None)
    if c is None or c.space != "brdf" or c.prediction is None:
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


def _brdf_entries(m, pred, pred_all, vars_: dict, after: str | None = None,
                  partial_angles: bool = False) -> list[dict]:
    """Held-out structure tests (:func:`heldout_structure`) of the residual of ``pred`` (array or
    callable(train), refitted per fold) against each of ``vars_``, with the in-sample description
    of the residual of ``pred_all`` (the model on all rows: effect, p, profile);
    ``partial_angles``: within angle cells (:func:`angle_cells`, module docstring)."""
    c = m.cols
    res = c["y"] - pred_all
    z = res / c["sigma"]
    rel = res / np.maximum(np.abs(pred_all), 1e-9)
    cells = angle_cells(m) if partial_angles else None
    if cells is not None:
        z, rel = _within_cells(z, cells), _within_cells(rel, cells)
    folds, halves = m.folds(), m.halves()
    if callable(pred):
        # the model refitted once per fold, shared by every variable
        fitted = {}
        refit = pred

        def pred(train):
            key = train.tobytes()
            if key not in fitted:
                fitted[key] = refit(train)
            return fitted[key]
    out = []
    for k, x in vars_.items():
        t = structure_test(x, z, rel)
        # one LED: m.folds() are the pixel-row halves too
        split = "halves" if k == "led" or len(np.unique(c["led"])) < 2 else "leds"
        h = heldout_structure(m, pred, x, halves if split == "halves" else folds, cells)
        e = {"variable": k, "space": "brdf", "effect": t["effect"], "effect_unit": "relative BRDF residual",
             "p": t["p"], "significant": h["significant"], "gain": h["gain"], "threshold": h["threshold"],
             "fold_gains": h["fold_gains"], "n_params": h["n_params"],
             "split": ("the two halves of the pixel rows" if split == "halves" else "leave one LED out"),
             "profile": {"x": t["x"], "mean": t["mean"], "n": t["n"]}}
        if "note" in h:
            e["note"] = h["note"]
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
    if kind in ("material", "reference") and any(e["variable"] in INSTRUMENT_VARS for e in sig):
        return "unexplained"
    return named


def deciding_variables(named: str, kind: str | None, entries: list[dict]) -> list[str]:
    """The variables that carry the structure the verdict "unexplained" stands on, the strongest first: the
    significant entries :func:`open_world_verdict` decided by - the named BRDF-space cause's own residual's
    (``after``) where it was tested again, else every significant entry - ordered by their held-out gain
    (frame-space entries, which have none, by their effect after the BRDF-space ones). The in-sample effect
    does not order them: correlated variables (phi_h and the axis position on a cylinder lit from above)
    spread alike in sample, while the held-out gain says which one predicts the held-out LEDs."""
    sig = [e for e in entries if e["significant"]]
    after = [e for e in sig if e.get("after") == named]
    use = after or sig
    if kind in ("material", "reference") and not after:
        use = [e for e in sig if e["variable"] in INSTRUMENT_VARS] or sig
    rest = [e for e in sig if e not in use]

    def order(es):
        return sorted(es, key=lambda e: (e.get("gain") is None, -(e.get("gain") or 0.0), -e["effect"]))
    seen: list[str] = []
    for e in order(use) + order(rest):
        if e["variable"] not in seen:
            seen.append(e["variable"])
    return seen
