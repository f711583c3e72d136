"""Rows that miss a colour channel in BRDF-space diagnosis (issue 14, item 1).

A channel out of the capture's dynamic range (too dark even at the longest exposure, or
saturated at the shortest) is NaN in its row (:mod:`glossrig.core.samples`); the row keeps
its other channels. Diagnosis compares the Rec. 709 luminance ``y = sum_c LUMA_c f_c``
with the base model, so a row that misses channel c gets, for that channel only, the
prediction of the base model of channel c: the lobe L of the material fit (shared by the
channels, as the luminance fit's lobe) with ``rho_d,c`` and ``rho_s,c`` solved by
non-negative weighted least squares on the rows that have the channel
(:func:`glossrig.core.fitting.fit.lobe_albedos`; thesis eq. 4.79 per
channel; the weights are ``weight_<c>``, the channel's inverse HDR variance, where the
table has them). :func:`glossrig.core.fitting.fit.fit_samples` fills luminance's gaps the
same way with each channel's own Ward fit; here the lobe is the one every cause of the
catalogue shares, so the fill adds no lobe of its own.

A predicted channel carries no measurement noise; its misfit is part of the base model's
misfit and goes into the calibrated model-error term (:mod:`.error_model`). The measured
channels' relative variance (:func:`glossrig.core.diagnose.data.luminance_relvar`, taken
relative to the luminance of the measured channels) is rescaled to the filled luminance.
Where a channel has fewer than MIN_ROWS measured rows it is taken as 0 where missing: it
is then almost always missing for being too dark, so its share of the luminance is below
its weight times the noise floor.
"""
from __future__ import annotations

import numpy as np

from glossrig.core.diagnose.data import LUMA
from glossrig.core.fitting.fit import lobe_albedos

MIN_ROWS = 50       # measured rows a channel needs for its base model to predict it elsewhere


def fill_missing_channels(t, L, relvar=None) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """``(y, relvar, info)`` for the rows of table ``t`` with the lobe values ``L`` (module
    docstring). Tables without ``r, g, b`` columns (synthetic ones holding ``f`` only) are
    returned as they are. ``info``: per channel, the rows that had it and those it was
    predicted for."""
    y0 = np.asarray(t["f"], float)
    if not all(c in t for c in "rgb"):
        return y0, relvar, {}
    rgb = t[["r", "g", "b"]].to_numpy(float).copy()
    valid = np.isfinite(rgb)
    if valid.all():
        return y0, relvar, {}
    L = np.asarray(L, float)
    info: dict = {}
    for k, c in enumerate("rgb"):
        gap = ~valid[:, k]
        if not gap.any():
            continue
        rows = valid[:, k] & np.isfinite(L)
        entry: dict[str, object] = {"rows_measured": int(rows.sum()), "rows_predicted": int(gap.sum())}
        if rows.sum() < MIN_ROWS:
            rgb[gap, k] = 0.0
            entry["predicted_by"] = f"0 (fewer than {MIN_ROWS} rows have the channel)"
        else:
            w = np.asarray(t[f"weight_{c}"], float)[rows] if f"weight_{c}" in t else np.ones(int(rows.sum()))
            sw = np.sqrt(np.where(np.isfinite(w) & (w > 0), w, 0.0))
            rho_d, rho_s, _ = lobe_albedos(L[rows], rgb[rows, k], sw)
            rgb[gap, k] = rho_d / np.pi + rho_s * L[gap]
            entry.update(predicted_by="the base model of the channel (shared lobe)", rho_d=rho_d, rho_s=rho_s)
        info[c] = entry
    y = rgb @ LUMA
    if relvar is not None:
        y_measured = np.sum(np.where(valid, LUMA * np.nan_to_num(rgb), 0.0), axis=1)
        with np.errstate(invalid="ignore", divide="ignore"):
            relvar = np.asarray(relvar, float) * np.where(y != 0, (y_measured / y) ** 2, 1.0)
    return y, relvar, info
