"""Expected uncertainty budget of the extended-Ward parameters a rig design would measure.

:func:`glossrig.core.design.placement.design_errors` gives the noise-only Cramer-Rao bound
(:mod:`glossrig.core.design.fisher`). What a measurement achieves is dominated by what
that bound leaves out: the calibration and the LED's block-wise fluctuation. This
module predicts the same components that ``glossrig fit``'s budget measures
(:mod:`glossrig.core.fitting.uncertainty`, GUM JCGM 100:2008), each from a stated
model of the error, propagated by linearisation at the design's rows (the pixels that
see the sample, thinned as the Fisher sum of :mod:`glossrig.core.design.placement`):
a change ``df`` of the data moves the least-squares parameters by

    d theta = A^-1 sum_i J_i^T df_i / sigma_i^2,     A = sum_i J_i^T J_i / sigma_i^2

(the inverse-variance fit; ``J`` the Ward Jacobian of eq. 4.79, ``sigma`` the design's
noise model). Independent error sources ``k`` of standard deviation ``s_k`` add
``sum_k (s_k d theta_k)^2`` to a component's variance:

* ``noise`` - ``A^-1`` (the Cramer-Rao bound of :mod:`~glossrig.core.design.fisher`);
* ``model`` - a relative gain ``g_b`` common to every sample of one LED x rotation image
  (``df = g_b f`` on block ``b``): what is left of the LED's output fluctuation (thesis
  4.3.3, fig. 4.12) after neighbour correction and patch normalisation (eq. 4.32-4.50),
  :data:`GAIN_REL` per block; the misfit ``glossrig fit`` measures with its cluster-robust
  sandwich over the same blocks;
* ``calibration`` - each LED's position, :data:`~glossrig.core.calibration.lamps.LAMP_STD_MM`
  per holder axis (``df = f`` at the moved lamp ``- f``, every rotation of that LED);
  the sample's pose against camera and lamps per rotation, :data:`POSE_ROT_DEG` about
  each holder axis and :data:`POSE_T_MM` along each at scale 0.25, in proportion to the
  pixel size at other scales (the sample's points and normals
  moved rigidly; an error of the intrinsics is absorbed by the poses solved with them,
  thesis 4.3.2, and enters through these figures); the reference's albedo
  (:data:`~glossrig.core.fitting.calibration_uncertainty.ALBEDO_U_REL` of rho_d and rho_s)
  and its angular variation (``df = f h (1 - cos theta - mean)`` for ``theta_in`` and
  ``theta_out``, ``h`` of :data:`~glossrig.core.fitting.calibration_uncertainty.ALBEDO_ANGULAR_U_REL`);
* ``footprint`` - the LED's finite aperture (:func:`glossrig.core.fitting.uncertainty.blur_effect`),
  counted in full as the budget does.

Combined: root sum of squares. Assumptions: the linearisation (errors small against the
lobe width), inverse-variance weights (``glossrig fit`` uses eq. 4.82's, within tens of
per cent of this), and the rigid-motion model of the pose error (a pixel's ray is not
re-intersected).
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from glossrig.core.design import coverage as cov
from glossrig.core.design import fisher as fi
from glossrig.core.models.ward import WardParams

#: Residual relative gain of one LED x rotation image after neighbour correction and patch
#: normalisation: the twin's per-frame LED jitter (0.5 %, thesis 4.3.3), taken whole.
GAIN_REL = 0.005
#: Standard uncertainty of the sample's pose per holder axis at image scale
#: :data:`POSE_SCALE`: rotation (degrees) and translation (mm) - the calibration's measured
#: errors on the twin at scale 0.25 (validation/calibration_report.md: holder and cylinder
#: rotations 0.01-0.05 deg, the holder's translation carrying the intrinsics' errors
#: 0.14 mm). The markers' edges and corners are located to a fraction of a pixel, so at
#: another scale both are taken in proportion to the pixel size, ``POSE_SCALE / scale``.
POSE_ROT_DEG = 0.05
POSE_T_MM = 0.15
POSE_SCALE = 0.25
COMPONENTS = ("noise", "model", "calibration", "footprint")


def _small_rotation(w) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


def _moved(geom: cov.PixelGeometry, R=None, t=None) -> cov.PixelGeometry:
    """The pixels' surface points and normals moved rigidly about the cylinder's centre."""
    R = np.eye(3) if R is None else R
    t = np.zeros(3) if t is None else np.asarray(t, float)
    return replace(geom, points=geom.points @ R.T + t, normals=geom.normals @ R.T, axis=R @ geom.axis)


def _ward(a: dict, rotation: float, p: WardParams):
    return fi.ward_jacobian(np.radians(a["theta_in"]), np.radians(a["theta_out"]), np.radians(a["theta_h"]),
                            np.radians(np.mod(a["phi_h"] - rotation, 360.0)), p)


def _by_param(x, mask) -> dict:
    """``{param: value}``, None where the parameter is not identifiable or not finite (JSON null)."""
    return {k: (float(v) if m and math.isfinite(v) else None) for k, v, m in zip(fi.PARAMS, x, mask)}


def _accumulator(b: dict):
    """``add(key, component, sd, vector)``: sums the vectors of one error source in ``b``."""
    def add(key, comp, sd, vec):
        e = b.setdefault(key, [comp, sd, np.zeros(5)])
        e[2] += vec
    return add


def design_budget(rig, materials, rotations=None, led_ids=None, scale: float = 0.25, noise: str = "hdr",
                  fisher_rows: int = 20000, gain_rel: float = GAIN_REL, lamp_std_mm: float | None = None,
                  pose_rot_deg: float | None = None, pose_t_mm: float | None = None, albedo_u: float | None = None,
                  angular_u: float | None = None, led_aperture: float | None = None) -> dict[str, dict]:
    """Per material label: ``{"params", "components": {component: {param: u}}, "combined":
    {param: u}, "relative": {param: u / |param| (rotation: radians)}, "stated": the error
    model}`` (module docstring)."""
    from glossrig.core.calibration.lamps import LAMP_STD_MM
    from glossrig.core.design.placement import _rows_for
    from glossrig.core.fitting.calibration_uncertainty import ALBEDO_ANGULAR_U_REL, ALBEDO_U_REL
    from glossrig.core.fitting.uncertainty import DEFAULT_LED_APERTURE, blur_effect, led_slope_variance
    from glossrig.core.models.ward import ward_geometry, ward_parts

    lamp_std = LAMP_STD_MM if lamp_std_mm is None else float(lamp_std_mm)
    pose_rot_deg = POSE_ROT_DEG * POSE_SCALE / scale if pose_rot_deg is None else float(pose_rot_deg)
    pose_t_mm = POSE_T_MM * POSE_SCALE / scale if pose_t_mm is None else float(pose_t_mm)
    albedo_u = ALBEDO_U_REL if albedo_u is None else float(albedo_u)
    angular_u = ALBEDO_ANGULAR_U_REL if angular_u is None else float(angular_u)
    aperture = DEFAULT_LED_APERTURE if led_aperture is None else float(led_aperture)
    rotations = [float(r) for r in (rig.sample_rotations if rotations is None else rotations)]
    led_ids = list(rig.led_ids() if led_ids is None else led_ids)
    px = cov.pixel_geometry(rig, scale)
    nm = fi.noise_model(noise, rig)
    rot_rad = math.radians(pose_rot_deg)
    moves = [(f"pose_rot{k}", _small_rotation(rot_rad * e), None) for k, e in enumerate(np.eye(3))] + \
            [(f"pose_t{k}", None, pose_t_mm * e) for k, e in enumerate(np.eye(3))]
    out = {}
    for label, p in materials:
        A = np.zeros((5, 5))
        # source -> (component, standard deviation, accumulated J' W df)
        b: dict[str, list] = {}

        add = _accumulator(b)

        n_rows = 0
        # the reference's angular variation (module docstring): sum J' W f g and sum J' W f
        # with the rows' mean of g = 1 - cos theta, for theta_in and theta_out
        ang_fg, ang_f, ang_g, ang_w = np.zeros((2, 5)), np.zeros(5), np.zeros(2), 0.0
        for i in led_ids:
            lamp = np.asarray(rig.led(i).position, float)
            a_all = cov.direction_angles(px, lamp, half=True)
            rows, w = _rows_for(a_all, a_all["lit"], p, fisher_rows, 3000)
            if rows.size == 0:
                continue
            sub = px.subset(rows)
            a = {k: v[rows] for k, v in a_all.items()}
            moved_lamps = [cov.direction_angles(sub, lamp + lamp_std * e, half=True) for e in np.eye(3)]
            moved_poses = [(name, cov.direction_angles(_moved(sub, R, t), lamp, half=True))
                           for name, R, t in moves]
            for r in rotations:
                f, J = _ward(a, r, p)
                sigma = nm.sigma(f, a["cos_in"], a["dist_in"])
                W = np.where(np.isfinite(sigma) & (sigma > 0), w / np.where(sigma > 0, sigma, 1.0) ** 2, 0.0)
                JW = J * W[:, None]
                A += J.T @ JW
                n_rows += int(round(w.sum()))
                add(f"gain_{i}_{r:g}", "model", gain_rel, JW.T @ f)
                for k, am in enumerate(moved_lamps):
                    add(f"lamp_{i}_{k}", "calibration", 1.0, JW.T @ (_ward(am, r, p)[0] - f))
                for name, am in moved_poses:
                    add(f"{name}_{r:g}", "calibration", 1.0, JW.T @ (_ward(am, r, p)[0] - f))
                ang_f += JW.T @ f
                for k, c in enumerate((a["cos_in"], a["cos_out"])):
                    ang_fg[k] += JW.T @ (f * (1.0 - c))
                    ang_g[k] += float(w @ (1.0 - c))
                ang_w += float(w.sum())
                if aperture > 0:
                    th = {k: np.radians(a[k]) for k in ("theta_in", "theta_out", "theta_h")}
                    th["phi_in"], th["phi_out"] = np.radians(a["phi_in"]), np.radians(a["phi_out"])
                    geo = ward_geometry(th["theta_in"], th["theta_out"], th["theta_h"],
                                        np.radians(np.mod(a["phi_h"] - r, 360.0)))
                    x_int = np.array([p.rho_d, p.rho_s, math.log(p.alpha_x), math.log(p.alpha_y), p.lobe_rotation])
                    _, parts = ward_parts(geo, x_int, log_alpha=True)
                    add("led_aperture", "footprint", 1.0, JW.T @ blur_effect(parts, x_int,
                                                                            led_slope_variance(th, aperture)))
        mask = fi.identifiable(p)
        C = fi.covariance_from_information(A, mask)
        Ci = np.where(np.isfinite(C), C, 0.0)
        var = {c: np.zeros(5) for c in COMPONENTS}
        var["noise"] = np.diag(C).copy()
        # the multiplier 1 + h (g - mean g) has the albedo's level taken out
        for k in range(2):
            vec = ang_fg[k] - (ang_g[k] / ang_w if ang_w > 0 else 0.0) * ang_f
            var["calibration"] += (angular_u * (Ci @ vec)) ** 2
        for comp, sd, vec in b.values():
            var[comp] += (sd * (Ci @ vec)) ** 2
        scale_p = fi.error_scale(p)
        var["calibration"] += (albedo_u * np.array([p.rho_d, p.rho_s, 0.0, 0.0, 0.0])) ** 2
        comps = {c: _by_param(np.sqrt(v), mask) for c, v in var.items()}
        comb = np.sqrt(sum(var.values()))
        out[label] = {
            "params": p.as_dict(), "n_samples": n_rows,
            "components": comps,
            "combined": _by_param(comb, mask),
            "relative": _by_param(comb / scale_p, mask),
            "stated": {"noise": nm.describe(), "gain_rel_per_led_rotation": gain_rel,
                       "lamp_std_mm_per_axis": lamp_std, "pose_rot_deg_per_axis": pose_rot_deg,
                       "pose_t_mm_per_axis": pose_t_mm, "albedo_u_rel": albedo_u, "albedo_angular_u_rel": angular_u,
                       "led_aperture_rad": aperture},
        }
    return out


def budget_text(budget: dict) -> str:
    """The budget of :func:`design_budget` as a text table: per material and parameter the
    components and the combined standard uncertainty, relative (rotation in degrees)."""
    lines = [f"{'material':24s} {'parameter':13s} " + " ".join(f"{c:>11s}" for c in COMPONENTS)
             + f" {'combined':>11s}"]
    for label, e in budget.items():
        for k in fi.PARAMS:
            sc = 1.0 if k == "lobe_rotation" else abs(e["params"][k]) or 1.0
            cells = [_cell(e["components"][c][k], k, sc) for c in COMPONENTS] + [_cell(e["combined"][k], k, sc)]
            lines.append(f"{label[:24]:24s} {k:13s} " + " ".join(cells))
    return "\n".join(lines)


def _cell(u: float | None, k: str, sc: float) -> str:
    if u is None or not math.isfinite(u):
        return f"{'-':>11s}"
    return f"{math.degrees(u):10.3g}d" if k == "lobe_rotation" else f"{100 * u / sc:10.3g}%"
