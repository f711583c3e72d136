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
* the thesis's 50 brightest pixels are quantised to the pixel (block) grid: at the
  twin's quarter resolution a block spans 0.6 degrees of surface normal, i.e.
  1.2 degrees of mirror direction, about 6 mm at 300 mm. Every sample above half
  the peak is used instead, and the per-sample estimates are averaged with
  weights ``value - peak / 2``: the highlight is symmetric about the true mirror
  point, so the weighted mean lands between blocks (measured on the twin: see
  validation/pipeline_study.py). The spread of the estimates is reported.
* quantisation still limits the highlight to about 2 mm at quarter scale, because
  the highlight runs parallel to the pixel rows. The estimate is therefore refined
  with the same capture's diffuse part (:func:`refine_with_diffuse`): away from
  the highlight the sheet reflects rho_d / pi of the irradiance I cos(theta_in) / d^2,
  whose pattern over thousands of samples fixes the lamp's azimuth and height to a
  fraction of a millimetre; the lamp stays at its measured distance from the axis.

Stated uncertainty (``std_mm`` of lamps.json, per LED and holder axis; the thesis states
none): with the true geometry the twin's lamps come out within 0.1-0.2 mm (the refinement's
own noise), with the calibrated geometry 0.8-2.3 mm off at scale 0.1, the same way for
every LED of a calibration - the error is the geometry's (intrinsics, holder and cylinder
poses), which the highlight and the diffuse pattern inherit through the rays, normals and
camera centre. So the stated uncertainty is that of the geometry propagated by Monte Carlo
(GUM Supplement 1, :func:`geometry_draws`: the camera calibration redrawn by a parametric
bootstrap and the capture's poses within their stated uncertainty, as the fit's calibration
component draws them, :mod:`glossrig.core.fitting.calibration_uncertainty`) plus the
refinement's noise covariance (s^2 (J^T J)^-1), in quadrature. It scales with the pixel
size as the geometry's errors do. lamps.json keeps the draws themselves (``geometry_draws``: each
draw's lamp positions and camera), so that a fit's calibration component draws each camera
with the lamps solved under it (:class:`glossrig.core.fitting.calibration_uncertainty.LampDraws`):
the lamps' error is the camera's, and in the sample's angles the two partly cancel. Not counted: the LED's distance from the axis (taken as
measured) and whatever the poses' stated uncertainty leaves out (their edge-fit noise times
:data:`~glossrig.core.fitting.calibration_uncertainty.POSE_STD_FACTOR`; validation/uncertainty_coverage.md,
sections 0' and 2, compare stated and actual).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from glossrig.core.models.angles import normalize
from glossrig.core.atomic import atomic_write_json
from glossrig.core.toml_input import read_json
from glossrig.core.errors import InputError

N_BRIGHTEST = 50          # the least number of valid samples accepted
#: Standard uncertainty (mm, per holder axis) readers take for a lamp file that states none
#: (written before ``std_mm`` existed; type B: the twin's lamp calibration erred by 0.6-0.9 mm in
#: 3-D at scale 0.25, validation/pipeline_study.py). :func:`calibrate_lamps` states each lamp's own.
LAMP_STD_MM = 0.5
#: Draws of the geometry for the stated lamp uncertainty (:func:`geometry_draws`): 24 draws
#: estimate a standard deviation to about 15 % (1 / sqrt(2 (n - 1))).
LAMP_DRAWS = 24
#: At most this many samples per LED are solved again in each draw (a fixed random subset):
#: the draws measure how the geometry moves the solution, which a subset shows as well.
DRAW_ROWS = 20_000
PEAK_FRACTION = 0.5


def lamp_from_highlight(points: np.ndarray, normals: np.ndarray, camera_centre: np.ndarray, values: np.ndarray,
                        distance: float, axis_point: np.ndarray, axis_dir: np.ndarray,
                        n_brightest: int = N_BRIGHTEST) -> tuple[np.ndarray, float]:
    """Lamp position (holder frame, mm) and the spread (mm RMS) of the per-pixel estimates."""
    values = np.asarray(values, float)
    ok = np.isfinite(values)          # NaN: no valid HDR estimate (too dark / saturated throughout)
    if ok.sum() < n_brightest:
        raise InputError(f"only {int(ok.sum())} valid samples, need at least {n_brightest} for the lamp position")
    peak = values[ok].max()
    idx = np.flatnonzero(ok & (values >= PEAK_FRACTION * peak))
    if len(idx) < 3:
        idx = np.flatnonzero(ok)[np.argsort(values[ok])[-n_brightest:]]
    wts = np.maximum(values[idx] - PEAK_FRACTION * peak, 0) + 1e-12
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
    lamp = np.average(est, axis=0, weights=wts)
    spread = float(np.sqrt(np.average(np.sum((est - lamp) ** 2, axis=1), weights=wts)))
    return lamp, spread


def _on_cylinder(azimuth: float, height: float, distance: float, axis_point, axis_dir, ref_dir):
    a = normalize(np.asarray(axis_dir, float))
    e1 = normalize(ref_dir - (ref_dir @ a) * a)
    e2 = np.cross(a, e1)
    return axis_point + height * a + distance * (np.cos(azimuth) * e1 + np.sin(azimuth) * e2)


def refine_with_diffuse(lamp0: np.ndarray, points: np.ndarray, normals: np.ndarray, values: np.ndarray,
                        distance: float, axis_point: np.ndarray, axis_dir: np.ndarray,
                        exclude_deg: float = 6.0) -> tuple[np.ndarray, dict]:
    """Refine a lamp position with the diffusely reflected light of the same capture.

    Model: value = k * cos(theta_in) / d^2 (Lambertian part of the sample; the patch
    normalisation is a per-LED constant absorbed in k). Samples whose mirror
    direction lies within ``exclude_deg`` of the first estimate (the specular lobe)
    are left out. Free parameters: the lamp's azimuth about the axis, its height
    along it, and k; its distance from the axis stays the measured one. Returns the
    refined position and fit statistics (rms relative residual, samples used).
    """
    from scipy.optimize import least_squares

    a = normalize(np.asarray(axis_dir, float))
    v = np.asarray(values, float)
    ok = np.isfinite(v) & (v > 0)
    P, n, v = points[ok], normals[ok], v[ok]
    q0 = lamp0 - axis_point
    h0 = float(q0 @ a)
    ref = q0 - h0 * a
    # leave out the lobe: samples whose normal is within exclude_deg/2 of the mirror normal
    wi0 = normalize(lamp0 - P)
    keep = np.ones(len(P), bool)
    if len(P):
        bright = np.argsort(v)[-max(10, len(v) // 1000):]
        hmed = np.median(n[bright], axis=0)
        keep = np.degrees(np.arccos(np.clip(n @ normalize(hmed), -1, 1))) > exclude_deg / 2
    P, n, v, wi0 = P[keep], n[keep], v[keep], wi0[keep]
    if len(P) < 200:
        raise InputError(f"only {len(P)} diffuse samples to refine the lamp position with")

    def model(x):
        L = _on_cylinder(x[0], x[1], distance, axis_point, a, ref)
        d = L - P
        r2 = np.sum(d * d, axis=1)
        cos = np.sum(d * n, axis=1) / np.sqrt(r2)
        return np.maximum(cos, 0) / r2

    # leave out grazing light (the terminator is where a small error in the normal matters most)
    cos0 = np.sum(wi0 * n, axis=1)
    P, n, v = P[cos0 > 0.15], n[cos0 > 0.15], v[cos0 > 0.15]
    m0 = model([0.0, h0])
    k0 = float(np.median(v / m0))
    sig = np.sqrt(v)           # shot-noise-like weights; a robust loss downweights stray samples

    def resid(x):
        return (x[2] * k0 * model(x[:2]) - v) / sig

    r0 = resid([0.0, h0, 1.0])
    scale = 1.4826 * np.median(np.abs(r0 - np.median(r0))) + 1e-12
    res = least_squares(resid, [0.0, h0, 1.0], x_scale=[1e-3, 0.1, 0.01], loss="soft_l1", f_scale=scale,
                        method="trf")
    L = _on_cylinder(res.x[0], res.x[1], distance, axis_point, a, ref)
    fit = res.x[2] * k0 * model(res.x[:2])
    rms = float(np.median(np.abs(fit / v - 1)))
    # noise covariance of (azimuth, height): s^2 (J^T J)^-1 from least_squares' loss-scaled
    # Jacobian and robust cost (s^2 = 2 cost / (n - p), the residual variance where the
    # soft-L1 loss is quadratic), mapped to the holder frame by dL/d(azimuth, height)
    J = np.asarray(res.jac, float)
    s2 = 2 * float(res.cost) / max(len(res.fun) - 3, 1)
    cov_x = s2 * np.linalg.pinv(J.T @ J)[:2, :2]
    h = 1e-6
    G = np.stack([(_on_cylinder(res.x[0] + h, res.x[1], distance, axis_point, a, ref) - L) / h, a], axis=1)
    return L, {"median_abs_rel_residual": rms, "samples": int(len(P)), "shift_mm": float(np.linalg.norm(L - lamp0)),
               "noise_cov_mm2": (G @ cov_x @ G.T).tolist()}


def _solve_lamp(pts, nrm, centre, vals, distance, axis_point, axis_dir, refine: bool):
    """One LED's lamp position from its samples (surface points, normals, camera centre:
    holder frame): the highlight estimate (:func:`lamp_from_highlight`), then, with
    ``refine``, the diffuse refinement (:func:`refine_with_diffuse`). Returns (lamp,
    spread of the highlight estimates, highlight estimate, refinement statistics or None)."""
    hl, spread = lamp_from_highlight(pts, nrm, centre, vals, distance, axis_point, axis_dir)
    if not refine:
        return hl, spread, hl, None
    lamp, stats = refine_with_diffuse(hl, pts, nrm, vals, distance, axis_point, axis_dir)
    return lamp, spread, hl, stats


def geometry_draws(camera_json, specular_dir, units: list[dict], refine: bool = True, n_draws: int = LAMP_DRAWS,
                   seed: int = 0, solved: dict | None = None) -> tuple[dict[int, np.ndarray], np.ndarray | None]:
    """The lamp positions solved again under ``n_draws`` draws of the geometry they were
    found with (GUM Supplement 1, Monte Carlo): the camera calibration (intrinsics and
    distortion together, a parametric bootstrap of the calibration) and the specular
    capture's holder and cylinder poses within their stated uncertainty, as
    :func:`glossrig.core.fitting.calibration_uncertainty.draw_calibration` draws them for a
    fit. Each draw casts every sample's ray again (:func:`glossrig.core.extraction.cylinder.surface_samples`),
    keeps its measured value, and repeats the solve (:func:`_solve_lamp`) in the drawn
    holder frame, on at most :data:`DRAW_ROWS` samples per LED. ``units``: per LED ``led,
    rotation, u, v`` (block corners, centre at ``+ 0.5``), ``values``, ``distance``.
    Draw ``k``'s camera is :func:`~glossrig.core.fitting.calibration_uncertainty.numbered_camera_draw`
    ``k`` of stream ``seed``, so a fit can draw the same camera with these lamps
    (:class:`~glossrig.core.fitting.calibration_uncertainty.LampDraws`).
    Returns LED -> (n_draws, 3) positions (mm), and the drawn cameras' fx, fy, cx, cy
    (``(n_draws, 4)``), or None where the intrinsics were not drawn (the camera file lacks the
    calibration's views, :class:`~glossrig.core.fitting.calibration_uncertainty.CameraViews`).
    ``solved``: rotation -> the capture's :func:`~glossrig.core.calibration.poses.calibrate_capture`
    result where the caller has it (those rotations are not solved again,
    :func:`~glossrig.core.fitting.calibration_uncertainty.load_inputs`).
    """
    from glossrig.core.fitting.calibration_uncertainty import (camera_numbers, draw_calibration, intrinsics_drawn,
                                                                load_inputs)

    cal = load_inputs(camera_json, None, specular_dir, sorted({float(x["rotation"]) for x in units}), solved=solved)
    cal.camera_stream = int(seed)
    rng = np.random.default_rng(seed)
    sub = []
    for x in units:
        n = len(x["values"])
        idx = np.sort(rng.choice(n, DRAW_ROWS, replace=False)) if n > DRAW_ROWS else np.arange(n)
        sub.append({**x, "u": np.asarray(x["u"])[idx], "v": np.asarray(x["v"])[idx],
                    "values": np.asarray(x["values"])[idx]})
    out: dict[int, list] = {int(x["led"]): [] for x in units}
    cams = []
    for k in range(n_draws):
        K, dist, poses, *_ = draw_calibration(cal, rng, ("intrinsics", "poses"), k=k)
        cams.append(camera_numbers(K))
        for x in sub:
            out[int(x["led"])].append(lamp_under_geometry(
                K, dist, cal.size, poses[float(x["rotation"])], cal.radius, cal.height,
                x["u"] + 0.5, x["v"] + 0.5, x["values"], x["distance"], refine))
    return {k: np.asarray(v) for k, v in out.items()}, (np.asarray(cams) if intrinsics_drawn(cal) else None)


def lamp_under_geometry(K, dist, size, poses, radius: float, height: float, u, v, values, distance,
                        refine: bool = True) -> np.ndarray:
    """The lamp position (holder frame, mm) :func:`_solve_lamp` finds from a sheet's ``values`` at
    pixel centres ``u, v`` when the camera is ``K, dist`` (image ``size``) and the poses are
    ``((R_hold, t_hold), (R_cyl, t_cyl))`` (camera frame): the rays cast again through that
    geometry and intersected with the cylinder. The one implementation of "solve a lamp again
    under another geometry", for :func:`geometry_draws` and the design's
    :class:`glossrig.core.design.error_budget.CalibrationDraws`."""
    from glossrig.core.calibration.poses import relative_to_holder
    from glossrig.core.extraction.cylinder import surface_samples

    (Rh, th), (Rc, tc) = poses
    R_cyl, t_cyl = relative_to_holder(Rh, th, Rc, tc)
    s = surface_samples(K, dist, size, Rh, th, R_cyl, t_cyl, radius, height, pixels=(u, v))
    # surface_samples keeps the rays that meet the sample, in order: find them by pixel
    W = float(size[0]) + 1.0
    keep = np.isin(np.asarray(v) * W + np.asarray(u), s.v * W + s.u)
    lamp, *_ = _solve_lamp(s.points, s.normals, s.camera_centre, np.asarray(values)[keep], distance, t_cyl,
                           s.axis, refine)
    return lamp


def calibrate_lamps(specular_dir, cam, progress: bool = False, refine: bool = True, n_draws: int = LAMP_DRAWS,
                    seed: int = 0) -> dict:
    """Lamp position of every LED sequenced in a capture of a specular sample, with its
    standard uncertainty per holder axis (``std_mm``): the spread of the positions
    solved again under draws of the geometry they were found with (:func:`geometry_draws`)
    and the noise of the diffuse refinement (its residual-based covariance), combined in
    quadrature. The LED's distance from the axis is the rig's measured one, taken as exact.

    A capture that cannot serve stops before any image is read: one without exposure
    sequences (a checkerboard capture) or one whose manifest labels a Lambertian
    material (``lambert:...``: no highlight to find the lamp from)."""
    from glossrig.core.capture import load_manifest, sha256_file
    from glossrig.core.extraction.extract import measure_capture
    from glossrig.core.rig import load_rig

    if n_draws < 2:
        raise InputError(f"the lamp uncertainty needs at least 2 draws of the geometry, got {n_draws}")
    man = load_manifest(specular_dir)
    man.require_sequences("calibrate lamps", "SPECULAR_DIR")
    if str(man.material).strip().lower().startswith("lambert"):
        raise InputError(f"SPECULAR_DIR is a capture of a diffuse material ({man.material}); calibrate lamps needs "
                         f"a capture of a specular sample (a highlight per LED)", path=man.folder)
    meas = measure_capture(specular_dir, cam, lamps=None, progress=progress, name="SPECULAR_DIR",
                           what="calibrate lamps")
    df = meas.table
    rig = load_rig(meas.rig_path)
    lamps, spreads, highlight, stats, units = {}, {}, {}, {}, []
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
        vals = lum[sub.index].to_numpy()
        lamp, spread, hl, st = _solve_lamp(pts, nrm, centre, vals, dist, axis_point, axis_dir, refine)
        highlight[int(led)] = hl.tolist()
        if st is not None:
            stats[int(led)] = st
            if st["shift_mm"] > 15:
                raise InputError(f"LED {led}: the diffuse refinement moved the lamp {st['shift_mm']:.1f} mm "
                                 "from the highlight estimate; the specular capture looks wrong", path=specular_dir)
        lamps[int(led)], spreads[int(led)] = lamp, spread
        units.append({"led": int(led), "rotation": float(rot), "u": sub["u"].to_numpy(float),
                      "v": sub["v"].to_numpy(float), "values": vals, "distance": dist})
    # the poses the measurement solved, where its geometry keeps them (RotationGeometry.poses): the
    # draws start from those instead of solving each rotation's calibration image again
    solved = {rot: g.poses for rot, g in meas.geometry.items() if g.poses is not None}
    drawn, cams = geometry_draws(cam.path, specular_dir, units, refine, n_draws, seed, solved=solved)
    intr = cams is not None
    std, parts = {}, {}
    for k, lamp in lamps.items():
        geo = drawn[k].std(axis=0, ddof=1)
        noise = np.sqrt(np.clip(np.diag(stats[k]["noise_cov_mm2"]), 0, None)) if k in stats else np.zeros(3)
        std[str(k)] = np.sqrt(geo ** 2 + noise ** 2).tolist()
        parts[str(k)] = {"geometry_mm": geo.tolist(), "noise_mm": noise.tolist(),
                         "draws_mean_minus_nominal_mm": (drawn[k].mean(axis=0) - lamp).tolist()}
    return {"kind": "glossrig.lamps", "rig": rig.name, "source": str(Path(specular_dir).resolve()),
            "method": "highlight-weighted mean of the mirror rays of every sample above half the peak, "
                      "intersected with the LED's distance from the axis (thesis 4.3.4), then refined "
                      "with the sample's diffuse reflection" if refine else
                      "highlight-weighted mean of the mirror rays (thesis 4.3.4)",
            "lamps_mm": {str(k): v.tolist() for k, v in lamps.items()},
            "spread_mm": {str(k): v for k, v in spreads.items()},
            "std_mm": std,
            "std_basis": f"standard uncertainty per holder axis: the spread of the positions solved again under "
                         f"{n_draws} draws of the " + ("camera calibration and the " if intr else "") +
                         "specular capture's poses (GUM-S1), and the diffuse refinement's noise, in quadrature; "
                         + ("" if intr else "the intrinsics not drawn (the camera file holds no calibration "
                                            "views); ") +
                         "the LED's distance from the axis taken as exact. spread_mm is the spread of the "
                         "per-pixel highlight estimates, not this",
            "std_components": parts, "std_draws": {"n": int(n_draws), "seed": int(seed), "intrinsics_drawn": intr},
            # the draws themselves, so that a fit draws each camera with the lamps solved under it
            # (calibration_uncertainty.LampDraws; the camera.json's sha256 says which camera they belong to)
            "geometry_draws": {"seed": int(seed), "camera_sha256": sha256_file(cam.path),
                               "cameras_fx_fy_cx_cy": None if cams is None else cams.tolist(),
                               "lamps_mm": {str(k): v.tolist() for k, v in drawn.items()}},
            "highlight_estimate_mm": {str(k): v for k, v in highlight.items()},
            "diffuse_refinement": {str(k): v for k, v in stats.items()}}


def save_lamps(d: dict, path) -> None:
    atomic_write_json(Path(path), d)


def load_lamps(path) -> dict[int, np.ndarray]:
    """The lamp positions (mm, holder frame) of a lamp file written by :func:`save_lamps`,
    by LED id: the one reader of the file (errors name it)."""
    p = Path(path)
    d = read_json(p, "lamp file")
    if not isinstance(d, dict) or d.get("kind") != "glossrig.lamps" or not isinstance(d.get("lamps_mm"), dict):
        raise InputError("not a glossrig lamp file (kind glossrig.lamps with lamps_mm)", path=p)
    out = {}
    for k, v in d["lamps_mm"].items():
        a = np.asarray(v, float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise InputError(f"lamp {k}: expected three finite coordinates", path=p)
        out[int(k)] = a
    return out
