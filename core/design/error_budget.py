"""Expected uncertainty budget of the extended-Ward parameters a rig design would measure.

:func:`glossrig.core.design.placement.design_errors` gives the noise-only Cramer-Rao bound
(:mod:`glossrig.core.design.fisher`). What a measurement achieves is dominated by what
that bound leaves out: the calibration and the LED's block-wise fluctuation. This
module predicts the same components that ``glossrig fit``'s budget measures
(:mod:`glossrig.core.fitting.uncertainty`, GUM JCGM 100:2008), each from a stated
model of the error, propagated by linearisation at the design's rows (the pixels that
see the sample, thinned as the Fisher sum of :mod:`glossrig.core.design.placement`)
**through the estimator ``glossrig fit`` uses**: the weighted least squares of thesis
eq. 4.81 with residual multipliers ``W_i = m_i / s_i`` - ``m`` the peak weight of eq.
4.82 (:func:`glossrig.core.fitting.fit.peak_weight`, ``mirror``), ``s`` the standard
deviation ``glossrig extract`` writes as the row's ``weight`` (1 / s^2): the sensor noise
of the sample's and the reference's HDR values, of which the row is the ratio (eq.
4.78; :func:`ratio_sigma`). A change ``df`` of the data moves the parameters by

    d theta = A^-1 sum_i W_i^2 J_i^T df_i,     A = sum_i W_i^2 J_i^T J_i

(``J`` the Ward Jacobian of eq. 4.79). These weights are not inverse variances (eq.
4.82's factor, and no per-pixel LED term), so the fit's response to an error is not the
Fisher-weighted one; at the coverage study's design the difference moves the components
by tens of per cent (validation/uncertainty_coverage.md, section 3). Independent error
sources ``k`` of standard deviation ``s_k`` add ``sum_k (s_k d theta_k)^2`` to a
component's variance:

* ``noise`` - the sandwich ``A^-1 B A^-1``, ``B = sum W_i^4 sigma_i^2 J_i^T J_i``
  (:func:`glossrig.core.design.fisher.sandwich_parts`), ``sigma`` the noise model's
  (``--noise``) for the sample and the reference in quadrature;
* ``model`` - a relative gain ``g_b`` common to every sample of one LED x rotation image
  (``df = g_b f`` on block ``b``): what is left of the LED's output fluctuation (thesis
  4.3.3, fig. 4.12) after neighbour correction and patch normalisation (eq. 4.32-4.50),
  :data:`GAIN_REL` per block; the misfit ``glossrig fit`` measures with its cluster-robust
  sandwich over the same blocks;
* ``calibration`` - the LEDs' positions. Without camera views
  :data:`~glossrig.core.calibration.lamps.LAMP_STD_MM` per holder axis, mostly common to the
  LEDs, as the fit draws them (:data:`glossrig.core.fitting.calibration_uncertainty.LAMP_DRAW`),
  linearised (``df = f`` at the moved lamps ``- f``: the common part summed over every LED
  and rotation before squaring, the LED's own part per LED). With camera views the lamps are
  solved again in :class:`CalibrationDraws` as ``glossrig calibrate lamps`` solves them
  (thesis 4.3.4) under each draw's camera and poses, so that their error goes with the
  geometry's it comes from, and refitted (a lobe narrower than the lamp error's angle does
  not respond linearly: brushed_original at scale 0.1, 4 LEDs: the one-sided difference gave
  alpha_y 0.5 % at 0.5 mm and 2.0 % at 1 mm); drawing them independently of the camera
  predicted 2.5 times the lobe-rotation error the twin's calibrations made for the nearly
  isotropic sample_0_6 and sample_2_6 (validation/uncertainty_coverage.md, section 0);
  the sample's pose against camera and lamps per rotation, :data:`POSE_ROT_DEG` about
  each holder axis and :data:`POSE_T_MM` along each at scale 0.25, in proportion to the
  pixel size at other scales (the sample's points and normals moved rigidly; these figures
  carry the intrinsics' error as far as a rigid move can); or, given a camera calibration's
  views (``camera_views``), the intrinsics drawn as ``glossrig fit`` draws them
  (:class:`CalibrationDraws`, GUM-S1: the pixels' rays cast again through each drawn camera
  with the poses re-solved from the markers) and the marker poses' own errors - the holder's
  (the lamps' frame) and the cylinder's, per axis (:data:`HOLDER_POSE_NOISE_ROT_DEG` and its
  companions, measured on the twin), the sample capture's drawn afresh for every rotation and
  refitted with the rest of the draw; the reference's albedo
  (:data:`~glossrig.core.fitting.calibration_uncertainty.ALBEDO_U_REL` of rho_d and rho_s)
  and its angular variation (``df = f h (1 - cos theta - mean)`` for ``theta_in`` and
  ``theta_out``, ``h`` of :data:`~glossrig.core.fitting.calibration_uncertainty.ALBEDO_ANGULAR_U_REL`);
* ``footprint`` - the LED's finite aperture (:func:`glossrig.core.fitting.uncertainty.blur_effect`),
  counted in full as the budget does.

Combined: root sum of squares. Assumptions: the linearisation (errors small against the
lobe width; not for the intrinsics draws, which are refitted), the point model (the fit's
footprint model changes the weights' effect little; the intrinsics draws refit the
footprint-averaged model where the fit would, weighing each row by the noise of the value it
holds, :meth:`_Sums.intrinsics_variance`), no peak clipping (eq. 6.5), the green
channel's noise (in the weights a factor common to all rows, which cancels; the
luminance's noise is ~0.8 of it), without camera views the rigid-motion model of the pose
error (a pixel's ray is not re-intersected) and lamps drawn independently of the geometry
(with them, the pose errors of the lamp capture and of each rotation of the sample capture
drawn independently of one another, at the sizes measured on the twin). `design errors` against
the twin's RMS errors over 16 calibrations (validation/uncertainty_coverage.md, section 0'''; the
calibration draws an adaptive Monte Carlo, :data:`MC_REL_TOL`): 34 of the 35 ratios of the Table 9.1
materials within [0.5, 2], pooled ratios 0.94-1.18; the 35th, polyethylene's alpha_x at 2.09, lies
inside the spread that the RMS of 16 errors drawn from the design's own heavy-tailed draws has
(0.43-1.64 times their RMS, 95 %). Without camera views
the rigid pose figures fall short for rho_s on the twin: its calibration error there is
~3-5 times what they give, most of it the intrinsics' error acting at second order, which
the refitted draws reproduce (validation/uncertainty_coverage.md, section 3).
The noise-only Cramer-Rao bound of the same rows (``design_errors``' figure) comes
with the budget from :func:`budget_and_bound`, so ``glossrig design errors`` walks the
geometry once.
"""
from __future__ import annotations

import math
from dataclasses import replace
from functools import partial

import numpy as np

from glossrig.core.design import coverage as cov
from glossrig.core.design import fisher as fi
from glossrig.core.fitting.fit import solver_params
from glossrig.core.models.ward import WardParams
from glossrig.core.workers import in_one_blas_thread

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
#: Where the intrinsics are drawn themselves (``camera_views``): the marker poses' own error, what
#: the pose step (thesis eq. 4.3-4.25: corner PnP, then the markers' raw edges) leaves with the
#: camera known exactly, per marker - the holder's (whose frame the lamps are given in) and the
#: cylinder's, each in the camera frame - and per axis: rotation about the marker's own axes
#: (degrees, ``R_true^T R_solved``) and translation along the camera's (mm), at image scale
#: :data:`POSE_NOISE_SCALE`, in proportion to the pixel size at other scales. Measured on the twin
#: with its true intrinsics, RMS over 88 captures at scale 0.1 (their mean included): 16 of
#: ``python -m validation.pose_scatter --scale 0.1 --per-axis --seeds 2,3,...,17`` (holder 0.075,
#: 0.14, 0.0093 deg), the coverage study's 112 - 56 sample captures (0.061, 0.127, 0.0087 deg) and
#: its 16 lamp captures (0.069, 0.116, 0.0070 deg) - validation/uncertainty_coverage.md, section 0''.
#: The holder errs about its x and y axes by 1.2-1.3 times what its edge fit states (0.058, 0.10,
#: 0.008 deg), 2-8 times as much as the cylinder, whose markers wrap around it. Its error is a turn
#: about a point near its marker (the translations follow the turn: |correlation| 0.9-1.0), drawn
#: here as independent turn and translation: the lamps, ~300 mm away, move by the turn ~0.7 mm, the
#: independent translations add ~0.1 mm in quadrature. The cylinder's depth error is mostly a bias
#: common to the captures (mean 0.11 of RMS 0.115 mm), drawn per capture here (its effect on the
#: fitted parameters is small beside the holder's). A holder error moves the lamps against the
#: sample and the camera: the coverage study's sample_0_6 of round 0, extracted with the twin's
#: true camera and lamps, had its holder solved 0.36 deg off, its lobe turned by 0.38 deg and
#: rho_s 2.0 % low; with the true poses too, 0.05 deg and 0.03 % (validation/uncertainty_coverage.md,
#: section 0'). The lamp capture's holder error explains the lamp calibration's error across the
#: holder (x; correlation 0.87 over its 16 rounds x 4 LEDs). The design's former figure, 0.075 deg
#: and 0.05 mm per axis at scale 0.1 as a rigid move of the sample, was the edge fit's stated size.
HOLDER_POSE_NOISE_ROT_DEG = (0.065, 0.128, 0.0085)
HOLDER_POSE_NOISE_T_MM = (0.037, 0.063, 0.090)
CYLINDER_POSE_NOISE_ROT_DEG = (0.029, 0.017, 0.0040)
CYLINDER_POSE_NOISE_T_MM = (0.015, 0.0068, 0.115)
POSE_NOISE_SCALE = 0.1
COMPONENTS = ("noise", "model", "calibration", "footprint")
#: The calibration draws' Monte Carlo (GUM-S1 7.9, adaptive): start with :data:`MC_START_DRAWS`
#: draws and double them, for the materials not yet settled, until the Monte Carlo standard
#: uncertainty of every identifiable parameter's combined standard uncertainty is at most
#: :data:`MC_REL_TOL` of it, or :data:`MC_MAX_DRAWS` draws are reached (then the entry says it did
#: not settle). The refits' response is heavy-tailed for a lobe a holder error of ~0.3 deg shifts by
#: a third of its width: sample_0_6 at scale 0.1 (LEDs 8-11, the coverage study's round-0
#: camera), 128 draws, |alpha_y shift| median 0.15 %, 5 of 128 above 1 %; 16 draws (the former
#: fixed count) gave 0.15-0.55 % over seeds 0-7, 128 draws 0.33 % and 0.31 % (seeds 0, 1); the
#: twin's 16 calibrations 0.46 % (round 0's holder solved 0.33 deg off: -1.72 %). The 16 draws
#: also under-state their own spread (13 % relative standard uncertainty from the sample against
#: 25-45 % over seeds), hence the start at 32. 10 %: the prediction is good to +-20 % at 95 %
#: against ``design errors``' aim of a factor of 2.
MC_START_DRAWS = 32
MC_MAX_DRAWS = 256
MC_REL_TOL = 0.10


def _moved(geom: cov.PixelGeometry, R=None, t=None) -> cov.PixelGeometry:
    """The pixels' surface points and normals moved rigidly about the cylinder's centre."""
    R = np.eye(3) if R is None else R
    t = np.zeros(3) if t is None else np.asarray(t, float)
    return replace(geom, points=geom.points @ R.T + t, normals=geom.normals @ R.T, axis=R @ geom.axis)


def _ward(a: dict, rotation: float, p: WardParams):
    return fi.ward_jacobian(np.radians(a["theta_in"]), np.radians(a["theta_out"]), np.radians(a["theta_h"]),
                            np.radians(np.mod(a["phi_h"] - rotation, 360.0)), p)


#: The BRDF angles a refit needs (eq. 4.79's and eq. 4.82's).
_ANGLES = ("theta_in", "phi_in", "theta_out", "phi_out", "theta_h", "phi_h")
#: Rows of the intrinsics draws' refits, in all (as ``glossrig fit``'s calibration component:
#: :func:`glossrig.core.fitting.calibration_uncertainty.calibration_component`'s ``max_rows``).
INTRINSICS_ROWS = 20_000


#: The specular sample the lamps are calibrated with (thesis 4.3.4: a transparency sheet;
#: scenes/materials), whose capture :class:`CalibrationDraws` simulates at the design's pixels.
LAMP_SHEET = "transparency_sheet"
#: Pixels of the sheet per LED that a lamp solve of :class:`CalibrationDraws` uses (a fixed random
#: subset; ``calibrate lamps`` solves its draws on up to 20 000): the data are noise-free, so the
#: subset changes only which pixels the diffuse fit weighs. Measured at scale 0.1 (LED 8, the coverage
#: study's round 0 camera, 6 draws, lamp capture pose noise 0.075 deg / 0.05 mm; /tmp/s8/rows_check.py):
#: the solved lamp shifts agree with 20 000 pixels' to 0.018 mm, against shifts of standard deviation
#: 0.26-1.09 mm per axis, at a sixth of the CPU (0.22 against 1.26 CPU-s).
LAMP_SHEET_ROWS = 5000


class CalibrationDraws:
    """The calibration's intrinsics and lamps drawn as the calibrations make their errors, GUM-S1:
    each draw re-runs the camera calibration on its views' corners moved by noise of its
    reprojection RMS (:func:`~glossrig.core.fitting.calibration_uncertainty.camera_draw`, intrinsics and
    distortion together), re-solves the holder's and cylinder's marker PnP with the drawn
    camera (the markers' corners as the nominal camera sees them), and casts every pixel's
    ray again through it (:func:`~glossrig.core.fitting.calibration_uncertainty.row_angles`).
    The pipeline then takes each pixel's value for the angles of the drawn geometry: the
    data are the nominal angles' values, the model is evaluated at the drawn ones. This is
    the intrinsics' effect that the poses do not absorb (a rigid pose figure cannot carry
    it; validation/uncertainty_coverage.md, section 3).

    **The lamps are calibrated with the same camera** (``glossrig calibrate lamps``, thesis
    4.3.4: the highlight's mirror rays and the diffuse pattern of a specular sheet on the
    cylinder, :func:`glossrig.core.calibration.lamps._solve_lamp`), so their error is mostly the
    drawn geometry's own (lamps.py's docstring: with the true geometry the twin's lamps come out
    within 0.1-0.2 mm, with the calibrated one 0.8-2.3 mm off) and it partly cancels the
    geometry's effect on the sample's angles. Each draw therefore solves every lamp again, as
    the lamp calibration would, from the sheet's nominal values (:data:`LAMP_SHEET`'s extended
    Ward, lit by the LED, at the design's pixels, at most :data:`LAMP_SHEET_ROWS` of them) under the
    drawn camera and poses,
    the lamp capture's holder and cylinder moved by their own pose errors (``pose_rot_deg`` about
    each of the holder's axes, ``pose_t_mm`` along each camera axis, ``cylinder_rot_deg`` and
    ``cylinder_t_mm`` the cylinder's; scalars or one figure per axis), and moves the lamp by the
    solution's change from the nominal geometry's solution.

    **The sample capture's own poses** are solved from its own calibration image (one per sample
    rotation), so each draw moves them too, by errors of the same sizes drawn afresh for every
    rotation, independent of the lamp capture's: the holder's pose (the lamps' frame) and the
    cylinder's, each in the camera frame, as the pose step errs (:data:`HOLDER_POSE_NOISE_ROT_DEG`).
    A holder error moves every lamp against the sample and the camera alike, so it is neither
    a rigid move of the sample nor an error of each LED; its effect is refitted with the
    intrinsics' (the lobe's response to a tenth of a degree is not linear for narrow lobes). Measured
    on the coverage study's eight scale-0.1 calibrations (validation/uncertainty_coverage.md,
    section 0): the lamps solved so under each round's own calibrated camera reproduce the
    actual lamp errors' y component (correlation 0.95; x 0.17, where the lamp capture's pose
    dominated), and the parameter errors these draws predict match those the calibrations
    actually made, where drawing lamps independently of the camera over-predicted the lobe
    rotation of nearly isotropic lobes 2.5-fold. ``lamp_std_mm`` adds a further lamp error per
    holder axis independent of the geometry (default 0), split as the fit splits it into a shift
    common to every LED and the LED's own (:data:`~glossrig.core.fitting.calibration_uncertainty.LAMP_DRAW`;
    normal draws of their own random streams, so the camera draws do not depend on them).
    ``views``: a :class:`~glossrig.core.fitting.calibration_uncertainty.CameraViews` of a
    calibration at the design's image size; ``captures``: whose pose errors are drawn, the lamp
    capture's (``"lamps"``) and the sample capture's (``"sample"``)."""

    def __init__(self, rig, px: cov.PixelGeometry, views, n_draws: int, seed: int, lamp_std_mm: float = 0.0,
                 pose_rot_deg=0.0, pose_t_mm=0.0, cylinder_rot_deg=0.0, cylinder_t_mm=0.0,
                 captures=("lamps", "sample"), first: int = 0):
        import cv2

        from glossrig.core.calibration.markers import cylinder_marker_corners, holder_marker_corners
        from glossrig.core.errors import InputError
        from glossrig.core.fitting import calibration_uncertainty as cu
        from glossrig.core.models.materials import parse_material

        if n_draws < 2:
            raise InputError(f"the intrinsics need at least 2 draws, got {n_draws}")
        cam = rig.camera
        K, dist, size = cam.matrix(px.scale), np.asarray(cam.distortion, float), tuple(cam.size(px.scale))
        R, t = (np.asarray(x, float) for x in cam.pose())
        parts = {}
        for key, obj in (("holder", np.concatenate([holder_marker_corners(rig), holder_marker_corners(rig, inner=True)])),
                         ("cylinder", cylinder_marker_corners(rig))):
            img = cv2.projectPoints(obj.astype(np.float64), cv2.Rodrigues(R)[0], t, K, dist)[0].reshape(-1, 2)
            parts[key] = {"R": R, "t": t, "R_pnp": R, "t_pnp": t, "obj": obj, "img": img,
                          "std_rot_deg": np.zeros(3), "std_t_mm": np.zeros(3)}
        self.cal = cu.CalibrationInputs(K=K, dist=dist, size=size, lamps={}, lamps_std={},
                                        radius=rig.cylinder_radius, height=rig.sample_height, poses={0.0: parts},
                                        camera_views=views)
        rng = np.random.default_rng(seed)
        # draws first .. n_draws - 1 of the streams (the earlier ones are another pass's: budget_and_bound)
        self.first = int(first)
        self.draws = [cu.draw_calibration(self.cal, rng, ("intrinsics",))[:3] for _ in range(n_draws)][self.first:]
        # the marker poses' own errors per axis: (holder rotation (rad), translation (mm), cylinder's)
        self.pose_sd = tuple(np.broadcast_to(np.asarray(x, float), (3,)) * f for x, f in
                             ((pose_rot_deg, math.pi / 180), (pose_t_mm, 1.0), (cylinder_rot_deg, math.pi / 180),
                              (cylinder_t_mm, 1.0)))
        self.n_draws, self.captures = n_draws, tuple(captures)
        # the lamp capture's own pose errors per draw (their own stream)
        self.lamp_capture_moves = self._pose_moves(np.random.default_rng([seed, 3])) if "lamps" in self.captures \
            else [None] * len(self.draws)
        # a further lamp error (cu.LAMP_DRAW): per draw a shift common to every LED and each LED's own,
        # from streams of their own (so the camera draws do not depend on them)
        self.lamp_std, self.seed = float(lamp_std_mm), seed
        self.common_fraction = np.asarray(cu.LAMP_COMMON_FRACTION)
        self.lamp_shifts = self.lamp_std * np.sqrt(self.common_fraction) * \
            np.random.default_rng([seed, 1]).standard_normal((n_draws, 3))[self.first:]
        self.rig, self.px = rig, px
        sheet = parse_material(LAMP_SHEET).ward
        assert sheet is not None                # a Ward material (scenes/materials)
        self.sheet = sheet
        self._resolved: dict[int, np.ndarray] = {}
        self._sheets: dict[int, tuple] = {}
        # pixel centres as row_angles casts them (u + 0.5: a Bayer block's corner there)
        self.u, self.v = px.u.astype(float) - 0.5, px.v.astype(float) - 0.5
        self._nominal: dict[int, dict] = {}

    def _pose_moves(self, rng) -> list[tuple]:
        """Per draw ``((R, t) of the holder, (R, t) of the cylinder)``: each marker's pose error (the
        rotation about its own axes, the translation in the camera frame), normal with the stated
        standard deviations per axis (:data:`HOLDER_POSE_NOISE_ROT_DEG`); the draws from ``first`` on."""
        from glossrig.core.fitting.calibration_uncertainty import rotation_from_vector

        z = rng.standard_normal((self.n_draws, 4, 3))[self.first:] * np.asarray(self.pose_sd)
        return [((rotation_from_vector(a), b), (rotation_from_vector(c), d)) for a, b, c, d in z]

    @property
    def moves_sample(self) -> bool:
        """Whether the sample capture's poses are drawn (asked for, and a pose error stated)."""
        return "sample" in self.captures and any(bool(np.any(x > 0)) for x in self.pose_sd)

    @staticmethod
    def _move(poses: tuple, move) -> tuple:
        """``((R_hold, t_hold), (R_cyl, t_cyl))`` (camera frame) with each marker's pose moved by
        ``move`` (:meth:`_pose_moves`: ``R @ dR``, ``t + dt``, as the fit's draws move a pose)."""
        if move is None:
            return poses
        return tuple((R @ dR, t + dt) for (R, t), (dR, dt) in zip(poses, move))

    def _sheet(self, led: int):
        """The lamp calibration's data for ``led`` at the nominal geometry: the sheet's pixels (a
        fixed subset of at most :data:`LAMP_SHEET_ROWS`) and their values (BRDF x cos / d^2, eq. 4.79)."""
        if led in self._sheets:
            return self._sheets[led]
        lamp = np.asarray(self.rig.led(led).position, float)
        a = cov.direction_angles(self.px, lamp, half=True)
        idx = np.flatnonzero(a["lit"] & (a["cos_in"] > 0) & (a["cos_out"] > 0))
        if idx.size > LAMP_SHEET_ROWS:
            idx = np.sort(np.random.default_rng([self.seed, 4, int(led)]).choice(idx, LAMP_SHEET_ROWS, replace=False))
        f = _ward({k: v[idx] for k, v in a.items()}, 0.0, self.sheet)[0]
        values = f * a["cos_in"][idx] / (a["dist_in"][idx] * 1e-3) ** 2
        self._sheets[led] = (self.px.u[idx].astype(float), self.px.v[idx].astype(float), values,
                             float(np.hypot(lamp[0], lamp[2])))
        return self._sheets[led]

    def solve_lamp(self, led: int, K, dist, poses, move=None) -> np.ndarray:
        """The lamp position ``glossrig calibrate lamps`` finds (holder frame, mm) from the sheet's
        nominal values of ``led`` (:meth:`_sheet`) under the camera ``K, dist`` and rotation 0's
        ``poses`` ((R_hold, t_hold), (R_cyl, t_cyl)), camera frame), the markers moved by ``move``
        where given (:meth:`_move`, as :func:`~glossrig.core.fitting.calibration_uncertainty._draw_pose`)."""
        from glossrig.core.calibration.lamps import lamp_under_geometry

        u, v, values, distance = self._sheet(led)
        (Rh, th), (Rc, tc) = self._move(poses, move)
        return lamp_under_geometry(K, dist, self.cal.size, ((Rh, th), (Rc, tc)), self.cal.radius, self.cal.height,
                                   u, v, values, distance, True)

    def resolved_shifts(self, led: int) -> np.ndarray:
        """``(n_draws, 3)``: each draw's lamp solution (:meth:`solve_lamp` under the draw's camera,
        poses and the lamp capture's own pose move) minus the nominal geometry's (mm)."""
        if led not in self._resolved:
            p = self.cal.poses[0.0]
            nominal = self.solve_lamp(led, self.cal.K, self.cal.dist,
                                      ((p["holder"]["R"], p["holder"]["t"]), (p["cylinder"]["R"], p["cylinder"]["t"])))
            self._resolved[led] = np.array([self.solve_lamp(led, K, d, poses[0.0], mv) - nominal
                                            for (K, d, poses), mv in zip(self.draws, self.lamp_capture_moves)])
        return self._resolved[led]

    def angles(self, led: int, rotation_index: int = 0) -> tuple[dict, list[dict]]:
        """The nominal and each draw's BRDF angles (radians, rotation 0's frame) of every pixel of
        the design for ``led``, the sample capture's poses moved by the draw's errors for the
        sample rotation numbered ``rotation_index`` (each rotation's calibration image is solved
        on its own: :meth:`_pose_moves` of a stream per rotation); NaN where a ray misses or a
        direction is below the horizon."""
        from glossrig.core.fitting import calibration_uncertainty as cu

        lamp = np.asarray(self.rig.led(led).position, float)
        lamps = {int(led): lamp}
        n = self.u.size
        args = (self.u, self.v, np.full(n, int(led)), np.zeros(n))

        def deg(a: dict) -> dict:
            ok = a["valid"]
            return {k: np.where(ok, a[k], np.nan) for k in _ANGLES}

        if led not in self._nominal:
            self._nominal[led] = deg(cu.row_angles(self.cal, *args, lamps=lamps))
        own = self.lamp_std * np.sqrt(1 - self.common_fraction) * \
            np.random.default_rng([self.seed, 2, int(led)]).standard_normal((self.n_draws, 3))[self.first:]
        moves = self._pose_moves(np.random.default_rng([self.seed, 5, int(rotation_index)])) if self.moves_sample \
            else [None] * len(self.draws)
        drawn = [deg(cu.row_angles(self.cal, *args, K=K, dist=d, poses={0.0: self._move(p[0.0], mv)},
                                   lamps={int(led): lamp + resolved + shift + o}))
                 for (K, d, p), resolved, shift, o, mv in zip(self.draws, self.resolved_shifts(led), self.lamp_shifts,
                                                              own, moves)]
        return self._nominal[led], drawn


def _by_param(x, mask) -> dict:
    """``{param: value}``, None where the parameter is not identifiable or not finite (JSON null)."""
    return {k: (float(v) if m and math.isfinite(v) else None) for k, v, m in zip(fi.PARAMS, x, mask)}


def _accumulator(b: dict):
    """``add(key, component, sd, vector)``: sums the vectors of one error source in ``b``."""
    def add(key, comp, sd, vec):
        e = b.setdefault(key, [comp, sd, np.zeros(5)])
        e[2] += vec
    return add


#: Albedo of the white reference where the rig file states none (thesis 4.4; spec/rig-facts.toml
#: ``[reference] assumed_albedo``).
REFERENCE_ALBEDO = 0.8


def ratio_sigma(nm, f, cos_in, dist_mm, reference_f: float) -> np.ndarray:
    """Standard deviation of a BRDF value that is the sample's HDR value over the reference's
    at the same pixel and lamp (thesis eq. 4.78): the relative variances add,
    ``s = f sqrt((sigma(f) / f)^2 + (sigma(f_ref) / f_ref)^2)``, ``f_ref`` the reference's
    BRDF (albedo / pi) and ``nm`` a noise model of :mod:`glossrig.core.design.fisher`
    (inf where either value has no usable exposure; NaN where ``f`` is 0)."""
    f = np.asarray(f, float)
    return _ratio(f, nm.sigma(f, cos_in, dist_mm), nm.sigma(np.full(f.shape, reference_f), cos_in, dist_mm),
                  reference_f)


def _table_weights(nm, cos_in, dist_mm, ref_sigma, reference_f: float, pixels, f) -> np.ndarray:
    """The samples table's weight of rows holding the values ``f``: ``pixels / s^2``, ``s`` the
    sensor noise of the ratio of ``f`` to the reference's (:func:`_ratio`, :func:`_sigmas`
    without the LED term, as ``glossrig extract`` weights a row by its HDR variance); 0 where
    ``f`` is not finite or ``s`` not positive."""
    f = np.asarray(f, float)
    s_tab = _ratio(f, _sigmas(nm, f, cos_in, dist_mm)[1], ref_sigma, reference_f)
    ok = np.isfinite(s_tab) & (s_tab > 0)
    return np.where(ok, pixels / np.where(ok, s_tab, 1.0) ** 2, 0.0)


def _ratio(f: np.ndarray, sigma_f: np.ndarray, sigma_ref: np.ndarray, reference_f: float) -> np.ndarray:
    """:func:`ratio_sigma` from the noise model's standard deviations of the sample's value
    ``f`` and of the reference's ``reference_f`` (evaluated once by the caller)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return f * np.hypot(sigma_f / f, sigma_ref / reference_f)


def _sigmas(nm, f, cos_in, dist_mm) -> tuple[np.ndarray, np.ndarray]:
    """The noise model's standard deviation of ``f`` and the one without its per-pixel LED term
    (what the fit weights by), the HDR merge evaluated once
    (:meth:`~glossrig.core.design.fisher.HdrNoise.relative_with_sensor_only`); a noise model
    without an LED term gives its one figure twice."""
    f = np.asarray(f, float)
    with np.errstate(divide="ignore", invalid="ignore"):     # as ratio_sigma evaluates them
        if not isinstance(nm, fi.HdrNoise):
            s = nm.sigma(f, cos_in, dist_mm)
            return s, s
        r, r0 = nm.relative_with_sensor_only(f, cos_in, dist_mm)
        return r * f, r0 * f


def design_budget(rig, materials, **kw) -> dict[str, dict]:
    """Per material label: ``{"params", "components": {component: {param: u}}, "combined":
    {param: u}, "relative": {param: u / |param| (rotation: radians)}, "stated": the error
    model}`` (module docstring); keywords as :func:`budget_and_bound`."""
    return budget_and_bound(rig, materials, **kw)[0]


# one BLAS thread (core.workers.one_blas_thread): the refits of the calibration draws and the lamps'
# re-solves are the fit's small least squares
@in_one_blas_thread
def budget_and_bound(rig, materials, *, intrinsics_draws: int | None = None, mc_rel_tol: float = MC_REL_TOL,
                     mc_max_draws: int = MC_MAX_DRAWS, **kw) -> tuple[dict[str, dict], dict[str, fi.ExpectedError]]:
    """:func:`design_budget`'s budget and, from the same walk over the design's pixels, the
    noise-only Cramer-Rao bound of each material: ``{label: ExpectedError}`` equal to
    :func:`glossrig.core.design.placement.design_errors` with ``gain_rel=bound_gain_rel``
    (the same rows, noise model and :func:`~glossrig.core.design.fisher.gain_marginal_information`).
    Keywords as :func:`_budget_pass`.

    With camera views the calibration draws are a Monte Carlo whose size is chosen adaptively
    (GUM-S1, JCGM 101:2008, 7.9; :data:`MC_REL_TOL`): :data:`MC_START_DRAWS` draws, doubled for the
    materials whose combined standard uncertainty is not yet known to ``mc_rel_tol`` of itself
    (the Monte Carlo standard uncertainty of the draws' mean square, ``_Sums.intrinsics_variance``,
    propagated to the combined figure) up to ``mc_max_draws``; a doubled pass keeps the earlier
    draws (the same random streams, extended). Each material's entry records ``calibration_draws``,
    ``calibration_mc_rel_u`` per parameter and ``calibration_mc_settled``. ``intrinsics_draws``
    fixes the number of draws instead (no adaptation)."""
    if kw.get("camera_views") is None or intrinsics_draws is not None:
        return _budget_pass(rig, materials, intrinsics_draws=intrinsics_draws or MC_START_DRAWS, **kw)[:2]
    n = MC_START_DRAWS
    out, bound, sums = _budget_pass(rig, materials, intrinsics_draws=n, **kw)
    while True:
        for e in out.values():
            e["calibration_mc_settled"] = _mc_settled(e, mc_rel_tol)
        todo = [(label, p) for label, p in materials if not out[label]["calibration_mc_settled"]]
        if not todo or 2 * n > mc_max_draws:
            return out, bound
        # the next n draws only, pooled with the earlier ones' sums
        more, _, more_sums = _budget_pass(rig, todo, intrinsics_draws=2 * n, first_draw=n,
                                          mc_prior={label: sums[label] for label, _ in todo}, **kw)
        out.update(more)
        sums.update(more_sums)
        n *= 2


def _mc_settled(entry: dict, tol: float) -> bool:
    """Whether every identifiable parameter's combined standard uncertainty is known to ``tol``
    of itself (``calibration_mc_rel_u``; a parameter without one counts as settled)."""
    return all(u is None or u <= tol for u in (entry.get("calibration_mc_rel_u") or {}).values())


def _budget_pass(rig, materials, rotations=None, led_ids=None, scale: float = 0.25, noise: str = "hdr",
                 fisher_rows: int = 20000, gain_rel: float = GAIN_REL, lamp_std_mm: float | None = None,
                 pose_rot_deg: float | None = None, pose_t_mm: float | None = None,
                 albedo_u: float | None = None, angular_u: float | None = None,
                 led_aperture: float | None = None, camera_views=None, intrinsics_draws: int = MC_START_DRAWS,
                 seed: int = 0, bound_gain_rel: float = 0.0, first_draw: int = 0, mc_prior: dict | None = None):
    """One walk over the design's pixels (:func:`budget_and_bound`) with ``intrinsics_draws``
    calibration draws, of which the first ``first_draw`` were refitted by an earlier pass whose
    sums ``mc_prior`` gives per material (``(count, sum of squares, sum of their squares)`` of the
    refits' shifts, :meth:`_Sums.intrinsics_variance`). Returns the budget, the bound and each
    material's sums."""
    from glossrig.core.calibration.lamps import LAMP_STD_MM
    from glossrig.core.design.placement import _rows_for
    from glossrig.core.fitting.calibration_uncertainty import (ALBEDO_ANGULAR_U_REL, ALBEDO_U_REL,
                                                                LAMP_COMMON_FRACTION, rotation_from_vector)
    from glossrig.core.fitting.fit import peak_weight
    from glossrig.core.fitting.uncertainty import DEFAULT_LED_APERTURE, blur_effect, led_slope_variance
    from glossrig.core.models.ward import ward_geometry, ward_parts

    # with camera views the lamps are solved again under each camera draw (CalibrationDraws): no
    # independent lamp error unless one is stated
    lamp_std = (LAMP_STD_MM if camera_views is None else 0.0) if lamp_std_mm is None else float(lamp_std_mm)
    # the sample's pose: without camera views a rigid move per holder axis (linearised, carrying the
    # intrinsics' error); with them each marker's own pose error per axis, drawn with the camera and
    # refitted (CalibrationDraws); a stated figure is taken for every axis of both markers
    if camera_views is None:
        pose_rot_deg = POSE_ROT_DEG * POSE_SCALE / scale if pose_rot_deg is None else float(pose_rot_deg)
        pose_t_mm = POSE_T_MM * POSE_SCALE / scale if pose_t_mm is None else float(pose_t_mm)
        marker_sd = None
    else:
        f = POSE_NOISE_SCALE / scale
        marker_sd = {k: f * np.asarray(v, float) if given is None else np.full(3, float(given)) for k, v, given in
                     (("pose_rot_deg", HOLDER_POSE_NOISE_ROT_DEG, pose_rot_deg),
                      ("pose_t_mm", HOLDER_POSE_NOISE_T_MM, pose_t_mm),
                      ("cylinder_rot_deg", CYLINDER_POSE_NOISE_ROT_DEG, pose_rot_deg),
                      ("cylinder_t_mm", CYLINDER_POSE_NOISE_T_MM, pose_t_mm))}
        pose_rot_deg = pose_t_mm = 0.0          # no rigid move: the poses are in the draws
    albedo_u = ALBEDO_U_REL if albedo_u is None else float(albedo_u)
    angular_u = ALBEDO_ANGULAR_U_REL if angular_u is None else float(angular_u)
    aperture = DEFAULT_LED_APERTURE if led_aperture is None else float(led_aperture)
    rotations = [float(r) for r in (rig.sample_rotations if rotations is None else rotations)]
    led_ids = list(rig.led_ids() if led_ids is None else led_ids)
    ref_albedo = rig.reference.assumed_albedo if rig.reference is not None else REFERENCE_ALBEDO
    ref_f = ref_albedo / math.pi
    px = cov.pixel_geometry(rig, scale)
    nm = fi.noise_model(noise, rig)
    intr = CalibrationDraws(rig, px, camera_views, intrinsics_draws, seed, lamp_std, **marker_sd, first=first_draw) \
        if marker_sd is not None else None
    rot_rad = math.radians(pose_rot_deg)
    moves = [(f"pose_rot{k}", rotation_from_vector(rot_rad * e), None) for k, e in enumerate(np.eye(3))] + \
            [(f"pose_t{k}", None, pose_t_mm * e) for k, e in enumerate(np.eye(3))] if intr is None else []
    acc = {label: _Sums((mc_prior or {}).get(label)) for label, _ in materials}
    for i in led_ids:
        lamp = np.asarray(rig.led(i).position, float)
        a_all = cov.direction_angles(px, lamp, half=True)
        # the draws' angles per sample rotation (its own pose errors), or one set for all without them
        a_intr = None if intr is None else [intr.angles(i, k) for k in range(len(rotations))] if intr.moves_sample \
            else [intr.angles(i)] * len(rotations)
        slope_jac: dict[float, np.ndarray] = {}         # per rotation, for the intrinsics refits' footprint
        for label, p in materials:
            s = acc[label]
            rows, w = _rows_for(a_all, a_all["lit"], p, fisher_rows, 3000)
            if rows.size == 0:
                continue
            sub = px.subset(rows)
            a = {k: v[rows] for k, v in a_all.items()}
            # eq. 4.82's weight depends on differences of the angles: the same at every rotation
            m = peak_weight(*(np.radians(a[k]) for k in ("theta_in", "phi_in", "theta_out", "phi_out")))
            moved_lamps = [cov.direction_angles(sub, lamp + lamp_std * e, half=True) for e in np.eye(3)] \
                if intr is None else []
            moved_poses = [(name, cov.direction_angles(_moved(sub, R, t), lamp, half=True)) for name, R, t in moves]
            add = _accumulator(s.b)
            # the noise model at these rows, evaluated once: the reference's (every rotation alike)
            # and, per rotation, the sample's, with and without the LED term
            ref_sig, ref_sig_w = _sigmas(nm, np.full(rows.size, ref_f), a["cos_in"], a["dist_in"])
            for ri, r in enumerate(rotations):
                f, J = _ward(a, r, p)
                sig, sig_w = _sigmas(nm, f, a["cos_in"], a["dist_in"])
                s.info += fi.gain_marginal_information(J, sig, f, bound_gain_rel, w)
                s_tab = _ratio(f, sig_w, ref_sig_w, ref_f)          # the table's weight (sensor noise)
                ok = np.isfinite(s_tab) & (s_tab > 0)
                mult = np.where(ok, m / np.where(ok, s_tab, 1.0), 0.0)
                A_b, B_b = fi.sandwich_parts(J, _ratio(f, sig, ref_sig, ref_f), mult, w)
                s.A += A_b
                s.B += B_b
                JW = J * (w * mult ** 2)[:, None]
                s.n_rows += int(round(w.sum()))
                add(f"gain_{i}_{r:g}", "model", gain_rel, JW.T @ f)
                for k, am in enumerate(moved_lamps):     # none where the lamps are drawn with the camera
                    vec = JW.T @ (_ward(am, r, p)[0] - f)       # the common part moves every lamp alike
                    add(f"lamp_{k}", "calibration", math.sqrt(LAMP_COMMON_FRACTION[k]), vec)
                    add(f"lamp_{i}_{k}", "calibration", math.sqrt(1 - LAMP_COMMON_FRACTION[k]), vec)
                for name, am in moved_poses:
                    add(f"{name}_{r:g}", "calibration", 1.0, JW.T @ (_ward(am, r, p)[0] - f))
                if a_intr is not None:
                    # the refits' rows thinned evenly to INTRINSICS_ROWS in all, each standing for the rest
                    step = max(1, math.ceil(rows.size * len(led_ids) * len(rotations) / INTRINSICS_ROWS))
                    # the table's weights at the values a row holds (the refits' data: the point
                    # model's or the footprint average, _Sums.intrinsics_variance)
                    weights = partial(_table_weights, nm, a["cos_in"][::step], a["dist_in"][::step],
                                      ref_sig_w[::step], ref_f, w[::step] * step)
                    if r not in slope_jac:
                        slope_jac[r] = pixel_slope_jacobian(px, a_all, r)
                    s.add_intrinsics_rows(a_intr[ri], rows[::step], r, p, weights, slope_jac[r][rows[::step]])
                s.ang_f += JW.T @ f
                for k, c in enumerate((a["cos_in"], a["cos_out"])):
                    s.ang_fg[k] += JW.T @ (f * (1.0 - c))
                    s.ang_g[k] += float(w @ (1.0 - c))
                s.ang_w += float(w.sum())
                if aperture > 0:
                    th = {k: np.radians(a[k]) for k in ("theta_in", "theta_out", "theta_h", "phi_in", "phi_out")}
                    geo = ward_geometry(th["theta_in"], th["theta_out"], th["theta_h"],
                                        np.radians(np.mod(a["phi_h"] - r, 360.0)))
                    x_int = solver_params(p)
                    _, parts = ward_parts(geo, x_int, log_alpha=True)
                    add("led_aperture", "footprint", 1.0, JW.T @ blur_effect(parts, x_int,
                                                                            led_slope_variance(th, aperture)))
    stated = {"noise": nm.describe(), "estimator": "eq. 4.81 with residual multipliers m / s: m the mirror peak "
              "weight of eq. 4.82, s the sensor noise of the sample and the reference (the table's weight)",
              "reference_albedo": ref_albedo, "gain_rel_per_led_rotation": gain_rel,
              "lamp_std_mm_per_axis": lamp_std, "pose_rot_deg_per_axis": pose_rot_deg,
              "pose_t_mm_per_axis": pose_t_mm,
              "marker_pose_noise": None if marker_sd is None else {k: [float(x) for x in v] for k, v in marker_sd.items()},
              "albedo_u_rel": albedo_u, "albedo_angular_u_rel": angular_u,
              "led_aperture_rad": aperture,
              "intrinsics": (f"{intrinsics_draws} draws of the camera calibration (parametric bootstrap of its "
                             f"{len(camera_views.rvecs)} views, reprojection RMS {camera_views.rms_px:g} px), poses "
                             f"re-solved from the markers and moved by the pose step's own errors (marker_pose_noise), "
                             f"the sample's for each rotation, the lamps solved again by the lamp calibration under each "
                             f"draw ({LAMP_SHEET}, its capture's holder moved by the pose noise) plus {lamp_std:g} mm "
                             "per axis independent of the geometry (cu.LAMP_DRAW), refitted" if camera_views is not None else
                             "not drawn (no camera calibration views given): carried by the pose figures")}
    out, bound, sums = {}, {}, {}
    for label, p in materials:
        s = acc[label]
        mask = fi.identifiable(p)
        bound[label] = fi.summarise(p, fi.covariance_from_information(s.info, mask), s.n_rows)
        C = fi.covariance_from_information(s.A, mask)
        Ci = np.where(np.isfinite(C), C, 0.0)
        var = {c: np.zeros(5) for c in COMPONENTS}
        var["noise"] = np.diag(fi.sandwich_covariance(s.A, s.B, mask)).copy()
        # the multiplier 1 + h (g - mean g) has the albedo's level taken out
        for k in range(2):
            vec = s.ang_fg[k] - (s.ang_g[k] / s.ang_w if s.ang_w > 0 else 0.0) * s.ang_f
            var["calibration"] += (angular_u * (Ci @ vec)) ** 2
        for comp, sd, vec in s.b.values():
            var[comp] += (sd * (Ci @ vec)) ** 2
        refits, mc_u = None, None
        if s.intr_rows:
            var["calibration"] += s.intrinsics_variance(p)
            refits = "footprint" if s.footprint_refits else "point"
        var["calibration"] += (albedo_u * np.array([p.rho_d, p.rho_s, 0.0, 0.0, 0.0])) ** 2
        total = sum(var.values())
        comb = np.sqrt(total)
        if s.intr_rows:
            # the Monte Carlo's standard uncertainty of the combined figure: u(mean square) / (2 u_c^2)
            with np.errstate(divide="ignore", invalid="ignore"):
                mc_u = _by_param(s.intrinsics_mc_u / (2.0 * total), mask & (total > 0))
        out[label] = {"params": p.as_dict(), "n_samples": s.n_rows,
                      "components": {c: _by_param(np.sqrt(v), mask) for c, v in var.items()},
                      "combined": _by_param(comb, mask), "relative": _by_param(comb / fi.error_scale(p), mask),
                      "calibration_refits": refits,
                      "calibration_draws": s.mc_sums[0] if s.mc_sums is not None else None,
                      "calibration_mc_rel_u": mc_u, "stated": stated}
        sums[label] = s.mc_sums
    return out, bound, sums


class _Sums:
    """One material's sums over the design's rows (:func:`budget_and_bound`)."""

    def __init__(self, mc_prior: tuple | None = None) -> None:
        self.A, self.B, self.info = np.zeros((5, 5)), np.zeros((5, 5)), np.zeros((5, 5))
        #: the calibration draws refitted by earlier passes: (count, sum of squared shifts, sum of their squares)
        self.mc_prior = mc_prior
        self.mc_sums: tuple | None = None
        self.b: dict[str, list] = {}           # source -> [component, standard deviation, sum W^2 J' df]
        self.n_rows = 0
        # the reference's angular variation (module docstring): sum W^2 J' f g and W^2 J' f with
        # the rows' mean of g = 1 - cos theta, for theta_in and theta_out
        self.ang_fg, self.ang_f, self.ang_g, self.ang_w = np.zeros((2, 5)), np.zeros(5), np.zeros(2), 0.0
        # the intrinsics draws' rows (CalibrationDraws): [(nominal angles, values, weights, drawn angles per draw)]
        self.intr_rows: list[tuple] = []
        self.footprint_refits = False           # whether intrinsics_variance refitted the footprint model
        #: the Monte Carlo standard uncertainty of intrinsics_variance's mean square (per parameter)
        self.intrinsics_mc_u = np.zeros(5)

    def add_intrinsics_rows(self, a_intr, rows, rotation: float, p: WardParams, table_weights, slope_jac) -> None:
        """Keep one (LED, rotation)'s rows for :meth:`intrinsics_variance`: the nominal and
        drawn angles (azimuths turned by the sample rotation, thesis eq. 4.62), the nominal
        data (the point model of ``p``), the table's weights as a function of the values the
        rows hold (``table_weights(f)``: pixel count / s^2, :func:`_table_weights`) and the rows'
        slope Jacobians (:func:`pixel_slope_jacobian`)."""
        nominal, drawn = a_intr
        r = np.radians(rotation)

        def take(a):
            out = {k: a[k][rows] for k in _ANGLES}
            for k in ("phi_in", "phi_out", "phi_h"):
                out[k] = np.mod(out[k] - r, 2 * np.pi)
            return out

        nom = take(nominal)
        y = _ward({k: np.degrees(v) for k, v in nom.items()}, 0.0, p)[0]
        self.intr_rows.append((nom, y, table_weights, [take(a) for a in drawn], slope_jac))

    def intrinsics_variance(self, p: WardParams) -> np.ndarray:
        """Mean square of the fitted parameters' errors over the calibration draws
        (:class:`CalibrationDraws`: intrinsics, poses re-solved with them and moved by the pose
        step's own errors, the lamps solved again under them; GUM-S1): each error the nominal
        data refitted at the draw's angles by the pipeline's weighted least squares (the
        Gauss-Newton refit of :mod:`glossrig.core.fitting.calibration_uncertainty`, eq.
        4.81-4.82, warm-started), minus the same refit at the nominal angles; a row a draw
        loses (its ray misses, a direction below the horizon) is left out of that refit. Not
        linearised: at a calibration's noise the drawn angle errors (~0.1 degree) move rho_s
        and the alphas at second order as much as at first (a blur-like bias), which a
        linearisation misses (tests/test_design_budget.py). That bias is an error of every
        measurement, so it is kept: the mean square about 0 (variance plus squared mean), not the
        variance about the draws' mean. The sample capture's pose errors make it: sample_0_6 at
        scale 0.1 (LEDs 8-11), the twin's solved poses against its true ones, true camera and
        lamps, rho_s -2.0 % to +0.01 % over 7 rounds, 6 of them low (validation/uncertainty_coverage.md,
        section 0); the draws' variance alone gave 0.53 %, their mean square 0.73 %, the rounds' 0.79 %.

        **The footprint, as the fit decides it** (:func:`~glossrig.core.fitting.calibration_uncertainty.calibration_component`
        with ``footprint``): the data are the lobe averaged over each row's footprint (a 2x2 Bayer
        block's luminance kernel over the pixel's slope Jacobian,
        :func:`~glossrig.core.fitting.footprint_model.footprint_eval`), and where the point
        model's refit of them departs from the lobe by more than
        :data:`~glossrig.core.fitting.calibration_uncertainty.FOOTPRINT_REFIT_DEPARTURE`
        every refit is of the footprint-averaged model (the footprint held at the nominal
        geometry), as ``glossrig fit`` fits such a lobe; otherwise the point model of the
        point data. For a lobe as narrow as a footprint the footprint model's parameters answer
        the calibration far more strongly: brushed_original at scale 0.1 (alpha_y 0.0106), its
        twin measurements' rows refitted at the true against the calibrated geometry moved
        alpha_y by -8.4 % and -12.1 % (rounds 1 and 3) with the footprint model, -1.5 % and
        -2.9 % with the point model; the fits' actual errors were -8.4 % and -11.5 %. The
        footprint average is taken with the pixel quadrature the fit chooses for the lobe
        (:meth:`~glossrig.core.fitting.footprint_model.SampleFootprint.orders_for`).

        **The weights are the table's at the values its rows hold** (:func:`_table_weights`):
        ``glossrig extract`` weighs a row by the variance of what it measured, the footprint
        average where the refits fit the footprint model. Weighing such a row by the point
        model's value instead (as the design did before 2026-11-25) over-weights the flanks of a
        lobe as narrow as a footprint, where the point model falls far below the average and
        the refit answers a geometry error most steeply. Measured on brushed_original at scale
        0.1, the holder pose error of the coverage study's round-0 capture (0.25 degree): its
        capture extracted and fitted with the solved against the twin's true poses (true camera
        and lamps) moved rho_s, alpha_x, alpha_y by 5.5, 0.33, 3.2 %; this refit on that
        capture's own rows by 4.6, 0.24, 2.7 % with the table's weights and by 15.9, 2.0, 9.4 %
        with weights 1 / f^2 at the point model's values f; the design's rows by 16, 3.0, 10 % before this
        change and 3.5, 0.04, 1.7 % after it (rounds 3 and 7: actual 3.8, 0.50, 2.5 % and 7.5,
        0.97, 5.2 %; the design 2.7, 0.29, 1.4 % and 5.0, 0.49, 3.1 %)."""
        from glossrig.core.fitting.calibration_uncertainty import _point_model_departs, _refit, _reported
        from glossrig.core.fitting.footprint_model import footprint_eval, sample_footprint
        from glossrig.core.models.ward import ward_geometry

        nom = {k: np.concatenate([e[0][k] for e in self.intr_rows]) for k in _ANGLES}
        y = np.concatenate([e[1] for e in self.intr_rows])
        fp_all = sample_footprint(np.concatenate([e[4] for e in self.intr_rows]))
        x0 = solver_params(p)
        # the footprint average of the lobe at every row (the fit's pixel quadrature for it)
        have = np.isfinite(nom["theta_in"]) & np.isfinite(y)
        geo = ward_geometry(*(nom[k][have] for k in ("theta_in", "theta_out", "theta_h", "phi_h")))
        fp_have = fp_all.take(np.flatnonzero(have))
        fp_have = fp_have.with_orders(fp_have.orders_for(geo, x0, log_alpha=True))
        y_fp = np.full(y.size, np.nan)
        y_fp[have] = footprint_eval(geo, fp_have, x0, log_alpha=True)
        fp_all = fp_all.with_orders(fp_have.orders)
        bounds = np.cumsum([0] + [e[1].size for e in self.intr_rows])

        def table_weights(values):
            # the table's weight of each row is that of the value it holds (_table_weights)
            return np.concatenate([e[2](values[a:b]) for e, a, b in zip(self.intr_rows, bounds[:-1], bounds[1:])])

        sw_fp = table_weights(y_fp)
        ok_fp = have & (sw_fp > 0)
        point = _refit({k: v[ok_fp] for k, v in nom.items()}, y_fp[ok_fp], sw_fp[ok_fp], x0, "mirror", None)
        use_fp = _point_model_departs(_reported(point, x0), x0)
        self.footprint_refits = use_fp
        data_all = y_fp if use_fp else y
        sw = sw_fp if use_fp else table_weights(y)
        ok0 = have & (sw > 0)
        n0 = {k: v[ok0] for k, v in nom.items()}
        fp0 = fp_all.take(np.flatnonzero(ok0))
        data = data_all[ok0]
        base = _refit(n0, data, sw[ok0], x0, "mirror", None, fp=fp0 if use_fp else None)
        shifts = []
        for d in range(len(self.intr_rows[0][3])):
            ang = {k: np.concatenate([e[3][d][k] for e in self.intr_rows]) for k in _ANGLES}
            ok = np.isfinite(ang["theta_in"][ok0])
            x = _refit({k: v[ok0][ok] for k, v in ang.items()}, data[ok], sw[ok0][ok], base, "mirror", None,
                       fp=fp0.take(np.flatnonzero(ok)) if use_fp else None)
            shifts.append(_reported(x, x0) - _reported(base, x0))
        sq = np.square(shifts)
        count, s1, s2 = self.mc_prior if self.mc_prior is not None else (0, np.zeros(5), np.zeros(5))
        count, s1, s2 = count + len(sq), s1 + sq.sum(axis=0), s2 + np.square(sq).sum(axis=0)
        self.mc_sums = (count, s1, s2)
        mean = s1 / count
        # the mean square's own Monte Carlo standard uncertainty (budget_and_bound's adaptive draws)
        self.intrinsics_mc_u = np.sqrt(np.maximum(s2 - count * mean ** 2, 0.0) / max(count - 1, 1) / count)
        return mean


def pixel_slope_jacobian(px: cov.PixelGeometry, a: dict, rotation: float) -> np.ndarray:
    """``(n, 2, 2)`` d(slope)/d(u, v) of the half vector at every design pixel for one LED's
    angles ``a`` (degrees, :func:`glossrig.core.design.coverage.direction_angles`) at sample
    ``rotation`` (degrees), as ``glossrig extract``'s table gives it to the fit
    (:func:`glossrig.core.models.footprint.slope_jacobian` over the 2x2 Bayer blocks, 2 px apart,
    whose corners are the even pixels): each pixel takes its block's; NaN where the block's
    corner pixel does not see the sample (no footprint: the point model)."""
    import pandas as pd

    from glossrig.core.models.footprint import slope_jacobian

    u, v = np.asarray(px.u, int), np.asarray(px.v, int)
    corner = np.flatnonzero((u % 2 == 0) & (v % 2 == 0))
    table = pd.DataFrame({"u": u[corner], "v": v[corner], "led": 0, "rotation": 0.0,
                          "theta_h": np.radians(a["theta_h"][corner]),
                          "phi_h": np.radians(np.mod(a["phi_h"][corner] - rotation, 360.0))})
    Jb = slope_jacobian(table)
    bu, bv = u // 2, v // 2
    grid = np.full((bv.max() + 1, bu.max() + 1), -1, np.int64)
    grid[bv[corner], bu[corner]] = np.arange(corner.size)
    at = grid[bv, bu]
    out = np.full((u.size, 2, 2), np.nan)
    out[at >= 0] = Jb[at[at >= 0]]
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
        if e.get("calibration_draws"):
            worst = max((u for u in (e.get("calibration_mc_rel_u") or {}).values() if u is not None), default=0.0)
            lines.append(f"{label[:24]:24s} calibration: {e['calibration_draws']} Monte Carlo draws, their standard "
                         f"uncertainty at most {100 * worst:.0f} % of a combined figure"
                         + ("" if e.get("calibration_mc_settled", True) else " (NOT settled: more draws needed)"))
    return "\n".join(lines)


def _cell(u: float | None, k: str, sc: float) -> str:
    if u is None or not math.isfinite(u):
        return f"{'-':>11s}"
    return f"{math.degrees(u):10.3g}d" if k == "lobe_rotation" else f"{100 * u / sc:10.3g}%"
