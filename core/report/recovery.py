"""Ground-truth recovery of a twin measurement: the calibrations and the fit against the
truth the twin recorded (``truth.json`` of a simulated capture; the pipeline itself never
reads it - this is an evaluation, made after the measurement, for the report and the demo).

:func:`recovery_table` compares

* the camera intrinsics (``camera.json``) with the twin's ``camera_matrix``: focal lengths
  as relative errors (percent), the principal point as pixel offsets;
* the lamp positions (``lamps.json``) with the twin's ``led_positions_mm``: the Euclidean
  error of every calibrated LED and the worst one;
* the luminance fit (``fit.json``) with the simulated extended-Ward material, both in the
  canonical form of :func:`glossrig.core.fitting.fit.canonical` (``alpha_x >= alpha_y``, rotation
  modulo pi), as :func:`glossrig.core.fitting.fit.parameter_errors` does: relative errors of
  rho_d, rho_s, alpha_x, alpha_y, the rotation's absolute error in degrees.

:func:`format_recovery` gives the lines ``glossrig demo`` prints.
"""
from __future__ import annotations

import math
from pathlib import Path

from glossrig.core.errors import InputError

FORMAT = "glossrig-recovery/1"
PARAMS = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")


def recovery_table(truth_json, *, camera_json=None, lamps_json=None, fit_json=None) -> dict:
    """The recovery table of a measurement of a twin capture (module docstring): a JSON
    dict with ``"intrinsics"``, ``"lamps"`` and ``"material"`` (each present when its
    input is given). ``truth_json``: the sample capture's ``truth.json``. Each file is
    read by its one reader (errors name the file)."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps
    from glossrig.core.capture import read_truth
    from glossrig.core.fitting.export import read_fit_json
    from glossrig.core.fitting.fit import canonical, parameter_errors
    from glossrig.core.models.ward import WardParams

    truth = read_truth(truth_json)
    out: dict = {"format": FORMAT}
    if camera_json is not None and "camera_matrix" in truth:
        cam = load_camera(camera_json)
        K = truth["camera_matrix"]
        out["intrinsics"] = {
            "fx_error_percent": 100.0 * (cam.fx / K[0][0] - 1.0),
            "fy_error_percent": 100.0 * (cam.fy / K[1][1] - 1.0),
            "cx_error_px": cam.cx - K[0][2], "cy_error_px": cam.cy - K[1][2]}
    if lamps_json is not None and "led_positions_mm" in truth:
        lamps = load_lamps(lamps_json)
        true_leds = truth["led_positions_mm"]
        per = {str(k): math.dist(v, true_leds[str(k)]) for k, v in lamps.items() if str(k) in true_leds}
        out["lamps"] = {"worst_error_mm": max(per.values()) if per else None, "n_leds": len(per),
                        "error_mm": per}
    if fit_json is not None:
        lum = read_fit_json(fit_json).fits.get("luminance")
        mat = truth.get("material") or {}
        m: dict = {"label": mat.get("label", mat.get("kind"))}
        if lum is not None:
            m["fitted"] = {k: float(getattr(lum.params, k)) for k in PARAMS}
            if isinstance(mat.get("ward"), dict):
                t, _ = canonical(WardParams(**{k: float(mat["ward"][k]) for k in PARAMS}))
                err = parameter_errors(m["fitted"], t)
                m["true"] = {k: getattr(t, k) for k in PARAMS}
                m["error"] = {**{f"{k}_percent": 100.0 * err[k] for k in PARAMS[:4]},
                              "lobe_rotation_deg": err["lobe_rotation_deg"]}
        out["material"] = m
    return out


def read_recovery(path: str | Path) -> dict:
    """A recovery table written as ``recovery.json`` (``glossrig measure`` / ``demo``; a
    :func:`recovery_table`): the one reader of the file. Errors name the file."""
    from glossrig.core.toml_input import read_json

    path = Path(path)
    d = read_json(path, "recovery table")
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        got = d.get("format") if isinstance(d, dict) else type(d).__name__
        raise InputError(f"not a glossrig recovery table (format {got!r}, expected {FORMAT!r})", path=path)
    return d


def format_recovery(rec: dict) -> list[str]:
    """The demo's printed table of a :func:`recovery_table` (one string per line)."""
    lines = ["", "ground-truth recovery on the twin"]
    i = rec.get("intrinsics")
    if i:
        lines.append(f"  intrinsics: fx {i['fx_error_percent']:+.3f} %, fy {i['fy_error_percent']:+.3f} %, "
                     f"principal point ({i['cx_error_px']:+.2f}, {i['cy_error_px']:+.2f}) px")
    lp = rec.get("lamps")
    if lp and lp.get("worst_error_mm") is not None:
        lines.append(f"  lamp positions: worst error {lp['worst_error_mm']:.2f} mm over {lp['n_leds']} LEDs")
    m = rec.get("material") or {}
    fit = m.get("fitted")
    if fit and "true" not in m:
        lines.append(f"  material {m.get('label')} is not a Ward material; fitted: "
                     + ", ".join(f"{k}={fit[k]:.4g}" for k in PARAMS))
    elif fit:
        w, e = m["true"], m["error"]
        lines.append(f"  {'parameter':<14}{'true':>10}{'fitted':>10}{'error':>10}")
        for k in PARAMS[:4]:
            lines.append(f"  {k:<14}{w[k]:>10.4g}{fit[k]:>10.4g}{e[k + '_percent']:>+9.1f}%")
        lines.append(f"  {'lobe_rotation':<14}{w['lobe_rotation']:>10.4g}{fit['lobe_rotation']:>10.4g}"
                     f"{e['lobe_rotation_deg']:>9.2f} deg")
    return lines
