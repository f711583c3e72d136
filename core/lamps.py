"""Lamp positions from a capture of a specular sample (thesis 4.3.4, eq. 4.51-4.53).

For each LED, the brightest HDR samples of a highly specular sample (the
thesis's transparency sheet) lie where the surface mirrors the lamp into the
camera. The mirror direction of the view vector about the normal (eq. 4.52)
points at the lamp; the lamp sits where that ray reaches the lamp's measured
distance. The thesis takes the 50 brightest pixels and averages.

Departures from the text:
* eq. 4.53 steps the distance d along the mirror ray from the surface point;
  the distance the thesis measures is from the *cylinder axis* (its LEDs stand
  at 30 cm from the axis), so we intersect the mirror ray with the cylinder of
  radius d about the calibrated axis, which is exact for that measurement;
* the 50 estimates are combined with a median (robust to a stray glint), and
  their spread is reported.
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .angles import normalize
from .capture import atomic_write_json
from .errors import InputError

N_BRIGHTEST = 50


def lamp_from_highlight(points: np.ndarray, normals: np.ndarray, camera_centre: np.ndarray, values: np.ndarray,
                        distance: float, axis_point: np.ndarray, axis_dir: np.ndarray,
                        n_brightest: int = N_BRIGHTEST) -> tuple[np.ndarray, float]:
    """Lamp position (holder frame, mm) and the spread (mm RMS) of the per-pixel estimates."""
    values = np.asarray(values, float)
    ok = np.isfinite(values)          # NaN: no valid HDR estimate (too dark / saturated throughout)
    if ok.sum() < n_brightest:
        raise InputError(f"only {int(ok.sum())} valid samples, need at least {n_brightest} for the lamp position")
    idx = np.flatnonzero(ok)[np.argsort(values[ok])[-n_brightest:]]
    P, n = points[idx], normals[idx]
    wo = normalize(camera_centre[None, :] - P)
    m = 2 * np.sum(n * wo, axis=1, keepdims=True) * n - wo                    # eq. 4.52
    a = normalize(np.asarray(axis_dir, float))
    # |(P + s m - A) - ((P + s m - A).a) a| = distance, solved for s > 0
    q = P - axis_point
    q_perp = q - (q @ a)[:, None] * a
    m_perp = m - (m @ a)[:, None] * a
    A = np.sum(m_perp ** 2, axis=1)
    B = 2 * np.sum(q_perp * m_perp, axis=1)
    C = np.sum(q_perp ** 2, axis=1) - distance ** 2
    s = (-B + np.sqrt(np.maximum(B * B - 4 * A * C, 0))) / (2 * A)
    est = P + s[:, None] * m
    lamp = np.median(est, axis=0)
    spread = float(np.sqrt(np.mean(np.sum((est - lamp) ** 2, axis=1))))
    return lamp, spread


def calibrate_lamps(specular_dir, cam, progress: bool = False) -> dict:
    """Lamp position of every LED sequenced in a capture of a specular sample."""
    from .extract import measure_capture
    from .rig import load_rig

    meas = measure_capture(specular_dir, cam, lamps=None, progress=progress)
    df = meas.table
    rig = load_rig(meas.rig_path)
    lamps, spreads = {}, {}
    lum = 0.2126 * df.r + 0.7152 * df.g + 0.0722 * df.b
    for led, sub in df.groupby("led"):
        rot = sub.rotation.iloc[0]
        sub = sub[sub.rotation == rot]
        g = meas.geometry[rot]
        axis_point = g.t_cyl
        axis_dir = g.R_cyl @ np.array([0.0, 1.0, 0.0])
        centre = -g.R_hold.T @ g.t_hold
        pts = sub[["x", "y", "z"]].to_numpy()
        nrm = sub[["nx", "ny", "nz"]].to_numpy()
        dist = float(np.hypot(rig.led(int(led)).position[0], rig.led(int(led)).position[2]))
        lamp, spread = lamp_from_highlight(pts, nrm, centre, lum[sub.index].to_numpy(), dist, axis_point, axis_dir)
        lamps[int(led)], spreads[int(led)] = lamp, spread
    return {"kind": "glossrig.lamps", "rig": rig.name, "source": str(Path(specular_dir).resolve()),
            "method": f"median of the {N_BRIGHTEST} brightest blocks' mirror rays at the rig's LED distance from the axis",
            "lamps_mm": {str(k): v.tolist() for k, v in lamps.items()},
            "spread_mm": {str(k): v for k, v in spreads.items()}}


def save_lamps(d: dict, path) -> None:
    atomic_write_json(Path(path), d)


def load_lamps(path) -> dict[int, np.ndarray]:
    p = Path(path)
    try:
        d = json.loads(p.read_text())
    except FileNotFoundError:
        raise InputError("lamp file not found", path=p) from None
    except json.JSONDecodeError as e:
        raise InputError(f"lamp file is not valid JSON: {e}", path=p) from None
    if d.get("kind") != "glossrig.lamps" or "lamps_mm" not in d:
        raise InputError("not a glossrig lamp file (kind glossrig.lamps with lamps_mm)", path=p)
    out = {}
    for k, v in d["lamps_mm"].items():
        a = np.asarray(v, float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise InputError(f"lamp {k}: expected three finite coordinates", path=p)
        out[int(k)] = a
    return out
