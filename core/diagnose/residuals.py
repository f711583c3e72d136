"""Residual structure against the variables a cause leaves its mark on (issue 7, step 2).

BRDF space: base-model residuals (normalised) binned against distance from the
optical centre, position along the cylinder axis (holder y, mm), LED id, signal
level, theta_in, theta_out, theta_h, theta_d and phi_h. Frame space: residuals
of the linear sensor binned against exposure time, capture order (time) and
signal level (DN). A flat profile means the variable carries no discrepancy.
"""
from __future__ import annotations

import numpy as np

from glossrig.core.diagnose.catalogue import BrdfModel, vignetting_factor
from glossrig.core.diagnose.frames import FrameSet, _linear_pred


def binned(x, r, n=10) -> dict:
    x, r = np.asarray(x, float), np.asarray(r, float)
    ok = np.isfinite(x) & np.isfinite(r)
    x, r = x[ok], r[ok]
    if x.size == 0:
        return {"x": [], "mean": [], "n": []}
    uniq = np.unique(x)
    if uniq.size <= 20:
        edges = None
        centres = uniq
        idx = np.searchsorted(uniq, x)
    else:
        edges = np.quantile(x, np.linspace(0, 1, n + 1))
        idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, n - 1)
        centres = 0.5 * (edges[1:] + edges[:-1])
    mean = [float(np.mean(r[idx == k])) if np.any(idx == k) else float("nan") for k in range(len(centres))]
    cnt = [int(np.sum(idx == k)) for k in range(len(centres))]
    return {"x": [float(c) for c in centres], "mean": mean, "n": cnt}


def brdf_structure(m: BrdfModel) -> dict:
    c = m.cols
    allr = np.ones(len(c["y"]), bool)
    _, pred, _ = m.solve_linear([np.full_like(c["L"], 1 / np.pi), c["L"]], allr)
    r = (c["y"] - pred) / c["sigma"]
    d = m.data
    rad = np.sqrt(vignetting_factor(c["u"] + 1.0, c["v"] + 1.0, d.image_size, d.principal_point))
    deg = np.degrees
    vars_ = {"distance_from_optical_centre (r/r_corner)": rad, "axis_position (mm)": d.table["y"].to_numpy(float)[m.rows],
             "led": c["led"], "signal (patch-normalised)": np.log10(np.maximum(c["signal"], 1e-6)),
             "theta_in (deg)": deg(c["theta_in"]), "theta_out (deg)": deg(c["theta_out"]),
             "theta_h (deg)": deg(c["theta_h"]), "theta_d (deg)": deg(c["theta_d"]), "phi_h (deg)": deg(c["phi_h"])}
    return {k: binned(v, r) for k, v in vars_.items()}


def frame_structure(fs: FrameSet) -> dict:
    xs: dict[str, list[np.ndarray]] = {"exposure_s (log10)": [], "capture order (min from sequence middle)": [], "signal (log10 DN)": []}
    rs = []
    for i in range(len(fs.Z)):
        M = fs.ok[i]
        pred = _linear_pred(fs, i, M)
        r = (fs.Z[i] - pred) / np.sqrt(fs.V[i])
        sel = M & (pred > 5)
        rs.append(r[sel])
        xs["exposure_s (log10)"].append(np.log10(fs.T[i][sel]))
        xs["capture order (min from sequence middle)"].append(fs.tau[i][sel])
        xs["signal (log10 DN)"].append(np.log10(pred[sel]))
    r = np.concatenate(rs)
    return {k: binned(np.concatenate(v), r) for k, v in xs.items()}
