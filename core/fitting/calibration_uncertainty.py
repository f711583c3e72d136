"""The calibration component of the fit's uncertainty budget (GUM Supplement 1, Monte Carlo).

Every calibration stage states its uncertainty in the file it writes:

* camera intrinsics - camera.json's ``std`` (OpenCV's ``stdDeviationsIntrinsics``:
  fx, fy, cx, cy and the distortion coefficients);
* holder and cylinder poses - ``edge_fit.std_rot_deg`` / ``std_t_mm`` of
  :func:`glossrig.core.calibration.poses.calibrate_capture` (Gauss-Newton, noise only), times
  :data:`POSE_STD_FACTOR`: the pose step errs by more than its edge fit's noise states;
* lamp positions - lamps.json's ``std_mm`` (per LED, per holder axis; a file without it
  gets :data:`LAMP_STD_MM`, see :func:`lamp_std`), drawn as **one shift common to every
  LED** and a part of the LED's own (:data:`LAMP_DRAW`, :data:`LAMP_COMMON_FRACTION`):
  ``calibrate lamps`` finds every LED through the same camera
  and cylinder pose, so a calibration's lamp errors are that geometry's and move all its
  lamps alike. Measured on the coverage study's eight scale-0.1 twin calibrations
  (validation/uncertainty_coverage.md, section 2): RMS over the calibrations of the mean
  lamp error 0.58, 1.01, 0.39 mm (holder x, y, z) against a spread about that mean of
  0.11, 0.20, 0.30 mm within a calibration, and stated 0.59, 0.84, 0.38 mm. Drawn
  independently per LED (as before 2026-11-25) the errors of several LEDs partly cancel
  in the fit: on brushed_original's scale-0.1 measurement of calibration round 1 the
  calibrated lamps alone (the twin's true camera and poses) moved alpha_y by -8.4 % and
  rho_s by -12 %, where the whole calibration component stated 3.0 % and 4.8 %.
  **Drawn with the camera that located them** where lamps.json records its geometry draws
  (:class:`LampDraws`, written by ``glossrig calibrate lamps`` since 2026-11-25) and the fit
  uses the camera.json those draws were made with: the lamps were found through that camera,
  so a camera error moves them too, and in the sample's angles the two partly cancel
  (validation/uncertainty_coverage.md, section 0: sample_0_6's lobe rotation error 2.15 mrad
  with camera and lamps both calibrated, 4.11 with the camera's error alone). Draw ``k`` of the
  fit then takes camera draw ``k`` of the lamp calibration (:func:`numbered_camera_draw`: the
  same generator, checked against the recorded focal lengths and principal point) and the lamps
  that calibration solved under it, each LED moved by its refinement noise on top; the split
  above is the rule for lamp files without that record, whose lamps are drawn independently
  of the camera;
* reference albedo - a relative standard uncertainty of its level
  (:data:`ALBEDO_U_REL`) and of its angular variation (:data:`ALBEDO_ANGULAR_U_REL`).

Propagation (GUM-S1, Monte Carlo over calibration draws): each draw perturbs the
calibration within its stated uncertainty (normal draws, independent between the stages)
and recomputes,
for the existing samples, what changes:

* the **angles**: the samples table keeps each row's pixel (``u, v``: the Bayer block's
  corner, its centre at ``u + 0.5, v + 0.5``), LED and rotation, so each row's ray is
  cast again through the perturbed intrinsics and poses, intersected with the cylinder
  and its angles recomputed towards the perturbed lamp (the code of
  :mod:`glossrig.core.extraction.cylinder`). The poses of each rotation are those the
  samples table records (``glossrig extract`` stores the ones its rows were measured with;
  :func:`recorded_poses`), else solved once from the capture's calibration image (the capture
  named in the table's provenance).
  A perturbed intrinsic matrix is not applied with the poses held: the poses are solved
  with the intrinsics, and an error of the principal point or focal length is largely
  absorbed by them (a 5 px principal-point error held against fixed poses would move
  the surface point by ~1.5 mm, its normal by degrees). Each draw therefore re-solves
  the corner PnP of both markers with the perturbed intrinsics (the corners the
  calibration found) and applies the change of the PnP pose to the refined pose.
  The intrinsics and distortion are drawn **together** by a parametric bootstrap of
  the camera calibration (:func:`camera_draw`: the board corners of the calibration's
  views, moved by noise of its own reprojection RMS, calibrated again), so each draw
  is a camera a calibration could have produced, with the correlations of fx, fy, cx,
  cy and the distortion among each other and with the views. Independent normal draws
  of fx, fy, cx, cy from OpenCV's marginal standard deviations, with the distortion
  held, made cameras no calibration produces: on a scale-0.1 twin measurement their
  spread of alpha_x was 12 times, of rho_s 17 times what the joint draws give, and the
  whole component 12-14 times the alphas' actual errors (now 1.1-1.5 times)
  (validation/uncertainty_coverage.md, section 1). A camera file without its views
  (not written by ``glossrig calibrate camera``) leaves the intrinsics undrawn, and
  the component's ``_meta`` says so.
* the **values**: a sample's value is the sample capture's over the reference
  capture's at the same pixel, LED and rotation (eq. 4.78), so the irradiance factors
  that depend on the lamp position and geometry (1/r^2, cos theta_in) cancel; what
  stays is the reference's albedo, a common scale ``(1 + e)``, ``e ~ N(0, u_albedo)``,
  and its departure from a Lambertian reflector, drawn as the multiplier
  ``1 + h_i (1 - cos theta_in - m_i) + h_o (1 - cos theta_out - m_o)`` with
  ``h ~ N(0, u_angular)`` (``m`` the means over the rows: the level is the albedo's).
* the **refit**: the point model (eq. 4.79) is refitted by least squares (Gauss-Newton,
  :func:`_refit`), warm-started from the nominal fit's parameters, on a subsample of rows (``max_rows``), for
  luminance and each colour channel; the same refit on the nominal geometry is the
  reference, so the footprint model, clipping choices and the subsample's own bias
  cancel in the difference. The weights of eq. 4.82 are recomputed from the perturbed
  angles.

The component's standard uncertainty of each parameter is the standard deviation of
the refitted parameters over the draws (rotation differences taken modulo pi), with
``n_draws - 1`` degrees of freedom. Approximations: the re-extraction is not redone
(the reference is matched at the same pixel, not at the nearest geometry; a
perturbed ray that leaves the sample drops that row for that draw); the poses' stated
uncertainty counts their noise only; 16-32 draws estimate a standard deviation to
~15-18 % (GUM-S1 7.9 asks for more where the tails matter; the budget's
Welch-Satterthwaite degrees of freedom carry it).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from glossrig.core.calibration.lamps import LAMP_STD_MM as _LAMP_STD_MM
from glossrig.core.errors import InputError
from glossrig.core.workers import in_one_blas_thread

PARAM_NAMES = ("rho_d", "rho_s", "alpha_x", "alpha_y", "lobe_rotation")
SOURCES = ("intrinsics", "poses", "lamps", "albedo")
#: How the lamp positions are drawn (module docstring): one normal shift per draw, scaled by
#: each LED's stated standard uncertainty, common to every LED.
#: Fraction of a lamp coordinate's variance that is common to every LED of a calibration, per
#: holder axis (x, y, z): the coverage study's eight scale-0.1 twin calibrations, RMS of the round's
#: mean error 0.58 / 1.01 / 0.39 mm against the LEDs' spread about it 0.11 / 0.20 / 0.30 mm
#: (validation/uncertainty_coverage.md, section 0): c^2 / (c^2 + w^2).
LAMP_COMMON_FRACTION = (0.96, 0.96, 0.63)
LAMP_DRAW = ("each LED's std_mm per holder axis, split into a shift common to every LED and the LED's own "
             f"(common variance fractions x, y, z {LAMP_COMMON_FRACTION})")
#: Per holder axis standard uncertainty (mm) of a lamp position whose file states none
#: (0.5 mm; :func:`glossrig.core.calibration.lamps.calibrate_lamps` states each lamp's own).
LAMP_STD_MM = _LAMP_STD_MM
#: The marker poses' actual error over the standard deviation their edge fit states (noise only,
#: :func:`glossrig.core.calibration.poses.calibrate_capture`), applied to every stated pose std the
#: draws use (the fit's, and calibrate lamps' through :func:`glossrig.core.calibration.lamps.geometry_draws`).
#: Measured on 16 twin captures at scale 0.1 with the true intrinsics (``python -m
#: validation.pose_scatter --scale 0.1 --per-axis --seeds 2,...,17``): the holder's RMS error about
#: its x, y, z axes 0.075, 0.14, 0.0093 deg against 0.058, 0.10, 0.008 stated - ratios 1.29, 1.40,
#: 1.16, each good to ~18 % (an RMS of 16); the coverage study's own 15 captures gave the same
#: (validation/uncertainty_coverage.md, section 0'). The sample capture's holder error is what is
#: left of the twin's errors once the calibration's are removed (same section), and with the
#: stated size rho_s's intervals covered 86 % of 56 measurements.
POSE_STD_FACTOR = 1.35
#: Relative standard uncertainty of the white reference's albedo (type B: the thesis assumes
#: 0.8 for white paper, spec/rig-facts.toml [reference]; a paper's albedo is known to a few per cent).
ALBEDO_U_REL = 0.02
#: Relative standard uncertainty of the reference's angular variation (departure from a
#: Lambertian reflector per unit of ``1 - cos theta``; type B).
ALBEDO_ANGULAR_U_REL = 0.02


#: The tag of the numbered camera draws' generators (:func:`numbered_camera_draw`): draw ``k`` of
#: stream ``seed`` uses ``numpy.random.default_rng([CAMERA_STREAM, seed, k])``.
CAMERA_STREAM = 1_634_561_392
#: A reproduced camera draw matches the recorded one when its fx, fy, cx, cy agree to this (px):
#: ``cv2.calibrateCamera`` gives the same draw to ~1e-5 px from call to call (its threads sum in
#: varying order), while two draws differ by ~1 px (scale 0.1: fx's spread 1 px).
CAMERA_MATCH_PX = 1e-3


def lamp_std(doc: dict) -> dict[int, np.ndarray]:
    """Per-LED standard uncertainty (mm, holder axes) of a lamp file's positions: its
    ``std_mm`` where it states one, else :data:`LAMP_STD_MM` (files written before the
    key existed)."""
    out = {}
    std = doc.get("std_mm") or {}
    for k in (doc.get("lamps_mm") or {}):
        s = std.get(k)
        a = np.full(3, LAMP_STD_MM) if s is None else np.broadcast_to(np.asarray(s, float), (3,)).copy()
        out[int(k)] = a
    return out


@dataclass
class CameraViews:
    """What a parametric bootstrap of the camera calibration needs (camera.json): the
    board's corner coordinates (mm), each used view's pose (rvec, tvec) and the
    calibration's reprojection RMS (px per corner)."""

    obj: np.ndarray
    rvecs: list
    tvecs: list
    rms_px: float

    @classmethod
    def from_camera_doc(cls, doc: dict) -> CameraViews | None:
        """From camera.json's ``board``, ``views`` and ``reprojection_rms_px``; None when
        the file lacks any of them (a calibration not made by ``glossrig calibrate camera``)."""
        from glossrig.core.calibration.intrinsics import board_points

        board, views = doc.get("board") or {}, doc.get("views") or []
        try:
            nx, ny = (int(v) for v in board["inner_corners"])
            obj = board_points((nx, ny), float(board["square_mm"]))
            rv = [np.asarray(v["rvec"], float).reshape(3, 1) for v in views]
            tv = [np.asarray(v["tvec_mm"], float).reshape(3, 1) for v in views]
            rms = float(doc["reprojection_rms_px"])
        except (KeyError, TypeError, ValueError):
            return None
        if len(rv) < 3 or not (math.isfinite(rms) and rms > 0):
            return None
        return cls(obj=obj, rvecs=rv, tvecs=tv, rms_px=rms)


def camera_draw(views: CameraViews, K: np.ndarray, dist: np.ndarray, size: tuple[int, int], rng):
    """One draw of the intrinsics AND distortion with their correlations (GUM-S1 by a
    parametric bootstrap of the calibration, Efron & Tibshirani 1993 ch. 6): the board
    corners each view would show under the calibrated camera (``cv2.projectPoints``),
    moved by normal noise of the calibration's own residual size (per image axis
    ``rms / sqrt(2)``, times ``sqrt(2N / (2N - p))`` for the ``p`` parameters the
    calibration fitted to its ``N`` corners), and calibrated again
    (``cv2.calibrateCamera``, thesis 4.3.1, warm-started at the nominal camera).
    The drawn ``(K, dist)`` vary together the way the calibration's errors do: an
    error of the principal point comes with the distortion and the views' poses that
    compensate it, which independent draws of fx, fy, cx, cy (OpenCV's marginal standard
    deviations) lose (module docstring; validation/uncertainty_coverage.md, section 1)."""
    import cv2

    n_pts = len(views.rvecs) * len(views.obj)
    n_par = 9 + 6 * len(views.rvecs)
    sigma = views.rms_px / math.sqrt(2.0) * math.sqrt(2 * n_pts / max(2 * n_pts - n_par, 1))
    obj = views.obj.astype(np.float32)
    img = []
    for rv, tv in zip(views.rvecs, views.tvecs):
        p, _ = cv2.projectPoints(obj.astype(np.float64), rv, tv, K, dist)
        img.append((p.reshape(-1, 2) + sigma * rng.standard_normal((len(obj), 2))).astype(np.float32).reshape(-1, 1, 2))
    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 100, 1e-12)
    _, K2, d2, _, _ = cv2.calibrateCamera([obj] * len(img), img, tuple(int(v) for v in size), K.copy(),
                                          np.asarray(dist, float).reshape(1, -1).copy(),
                                          flags=cv2.CALIB_USE_INTRINSIC_GUESS, criteria=crit)
    return np.asarray(K2, float), np.asarray(d2, float).ravel()[:5]


def numbered_camera_draw(views: CameraViews, K: np.ndarray, dist: np.ndarray, size: tuple[int, int],
                         seed: int, k: int):
    """Camera draw number ``k`` of stream ``seed`` (:func:`camera_draw` with a generator of its
    own, :data:`CAMERA_STREAM`): the same camera for whoever asks, so ``calibrate lamps`` and a
    fit draw the camera the lamps were solved under (:class:`LampDraws`)."""
    return camera_draw(views, K, dist, size, np.random.default_rng([CAMERA_STREAM, int(seed), int(k)]))


def camera_numbers(K: np.ndarray) -> list[float]:
    """fx, fy, cx, cy of an intrinsic matrix: what lamps.json records of each camera draw."""
    return [float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])]


@dataclass
class LampDraws:
    """The lamp calibration's own geometry draws (lamps.json ``geometry_draws``, written by
    :func:`glossrig.core.calibration.lamps.calibrate_lamps`): for each draw ``k`` the lamp
    positions solved under camera draw ``k`` of stream ``seed`` (:func:`numbered_camera_draw`)
    and the specular capture's drawn poses; each LED's refinement noise (``std_components``),
    which is its own and drawn independently."""

    seed: int
    positions: dict[int, np.ndarray]        # LED -> (n, 3) mm, holder frame
    noise_mm: dict[int, np.ndarray]         # LED -> (3,) standard uncertainty
    cameras: np.ndarray | None              # (n, 4) fx, fy, cx, cy of each draw; None: intrinsics not drawn

    @property
    def n(self) -> int:
        return int(next(iter(self.positions.values())).shape[0])

    @classmethod
    def from_doc(cls, doc: dict, camera_json, views: CameraViews | None, K, dist, size,
                 leds) -> tuple[LampDraws | None, str]:
        """The record of ``doc`` (a lamps.json) where a fit with ``camera_json`` can draw its
        camera and lamps together, else (None, why). Conditions: the record is readable and
        covers ``leds``; ``camera_json`` has the sha256 it was made with; the intrinsics were
        drawn there exactly when they can be here (``views``); and this machine reproduces the
        record's first camera draw (:data:`CAMERA_MATCH_PX`; another OpenCV could draw another)."""
        from glossrig.core.capture import sha256_file

        rec = doc.get("geometry_draws")
        if not rec:
            return None, ("the lamp file records no geometry draws (written before they were kept): lamps drawn "
                          "independently of the camera, " + LAMP_DRAW)
        try:
            seed = int(rec["seed"])
            pos = {int(k): np.asarray(v, float) for k, v in rec["lamps_mm"].items()}
            comps = doc.get("std_components") or {}
            noise = {k: np.asarray((comps.get(str(k)) or {}).get("noise_mm", [0.0, 0.0, 0.0]), float) for k in pos}
            cams = None if rec.get("cameras_fx_fy_cx_cy") is None else np.asarray(rec["cameras_fx_fy_cx_cy"], float)
            sha = str(rec["camera_sha256"])
        except (KeyError, TypeError, ValueError, AttributeError) as e:
            return None, f"the lamp file's geometry draws are unreadable ({type(e).__name__}: {e}): lamps drawn independently"
        n = {p.shape for p in pos.values()}
        if len(n) != 1 or (shape := n.pop())[0] < 2 or shape[1:] != (3,) or not all(np.isfinite(p).all()
                                                                                   for p in pos.values()):
            return None, "the lamp file's geometry draws are not n x 3 finite positions per LED: lamps drawn independently"
        if set(int(k) for k in leds) - set(pos):
            return None, "the lamp file's geometry draws lack some LEDs: lamps drawn independently"
        if sha256_file(camera_json) != sha:
            return None, (f"{camera_json} is not the camera.json the lamps were calibrated with: lamps drawn "
                          "independently of the camera")
        if (cams is None) != (views is None) or (cams is not None and cams.shape != (shape[0], 4)):
            return None, ("the lamp calibration drew the intrinsics where this fit cannot (or not where it can): "
                          "lamps drawn independently")
        if cams is not None and views is not None:
            K0, _ = numbered_camera_draw(views, K, dist, size, seed, 0)
            if np.max(np.abs(np.asarray(camera_numbers(K0)) - cams[0])) > CAMERA_MATCH_PX:
                return None, ("this machine does not reproduce the lamp calibration's camera draws (another OpenCV?): "
                              "lamps drawn independently of the camera")
        return cls(seed=seed, positions=pos, noise_mm=noise, cameras=cams), \
            f"drawn with the camera draws that located them ({shape[0]} draws recorded by calibrate lamps)"


@dataclass
class CalibrationInputs:
    """The nominal calibration and its stated uncertainties (module docstring)."""

    K: np.ndarray
    dist: np.ndarray
    size: tuple[int, int]
    lamps: dict[int, np.ndarray]
    lamps_std: dict[int, np.ndarray]
    radius: float
    height: float
    poses: dict = field(default_factory=dict)     # rotation -> dict (see rotation_poses)
    albedo_u: float = ALBEDO_U_REL
    angular_u: float = ALBEDO_ANGULAR_U_REL
    sources_files: dict = field(default_factory=dict)
    camera_views: CameraViews | None = None     # for the correlated draws of the intrinsics (camera_draw)
    #: draw k's camera is numbered_camera_draw(..., camera_stream, k) (calibrate lamps' draws); None: drawn from the rng
    camera_stream: int | None = None
    lamp_draws: LampDraws | None = None         # the lamps solved under those camera draws (LampDraws)
    lamp_draws_note: str = ""


def rotation_poses(res: dict, rig) -> dict:
    """What a draw needs of one rotation's :func:`~glossrig.core.calibration.poses.calibrate_capture`
    result: refined and corner-PnP poses with their corners and stated std."""
    from glossrig.core.calibration.markers import cylinder_marker_corners, holder_marker_corners

    def part(key):
        e = res[key]
        ef = e.get("edge_fit") or {}
        return {"R": np.asarray(e["R"], float), "t": np.asarray(e["t_mm"], float),
                "R_pnp": np.asarray(e["corner_pnp"]["R"], float), "t_pnp": np.asarray(e["corner_pnp"]["t_mm"], float),
                "std_rot_deg": POSE_STD_FACTOR * np.nan_to_num(np.asarray(ef.get("std_rot_deg", [0, 0, 0]), float)),
                "std_t_mm": POSE_STD_FACTOR * np.nan_to_num(np.asarray(ef.get("std_t_mm", [0, 0, 0]), float))}

    h, c = part("holder"), part("cylinder")
    h["obj"] = np.concatenate([holder_marker_corners(rig), holder_marker_corners(rig, inner=True)])
    h["img"] = np.asarray(res["corners_px"]["holder"], float)
    h["planar"] = True
    c["obj"] = cylinder_marker_corners(rig)
    c["img"] = np.asarray(res["corners_px"]["cylinder"], float)
    c["planar"] = False
    return {"holder": h, "cylinder": c}


def load_inputs(camera_json, lamps_json, capture_dir, rotations, solved: dict | None = None) -> CalibrationInputs:
    """The calibration of a samples table: intrinsics, lamps, and each rotation's poses
    solved again from ``capture_dir``'s calibration images (seconds per rotation), except
    those of ``solved``: rotation -> the :func:`~glossrig.core.calibration.poses.calibrate_capture`
    result (of ``capture_dir`` with ``camera_json``, that rotation) a caller has already solved."""
    from glossrig.core.calibration.intrinsics import load_camera
    from glossrig.core.calibration.lamps import load_lamps
    from glossrig.core.calibration.poses import calibrate_capture
    from glossrig.core.capture import load_manifest
    from glossrig.core.rig import load_rig
    from glossrig.core.toml_input import read_json

    cam = load_camera(camera_json)
    # lamps_json None: no lamps (calibrate_lamps draws the geometry its lamps come from)
    lamps = load_lamps(lamps_json) if lamps_json is not None else {}
    ldoc = read_json(Path(lamps_json), "lamp file") if lamps_json is not None else {}
    man = load_manifest(capture_dir)
    rig = load_rig(man.rig_path())
    solved = {float(k): v for k, v in (solved or {}).items()}
    poses = {}
    for rot in rotations:
        res = solved.get(float(rot))
        if res is None:
            res = calibrate_capture(capture_dir, camera_json, rotation=float(rot))
        elif float(res["rotation"]) != float(rot):
            raise InputError(f"the poses given for rotation {float(rot):g} deg were solved for rotation "
                             f"{float(res['rotation']):g}", path=capture_dir)
        poses[float(rot)] = rotation_poses(res, rig)
    size = (int(cam.image_size[0]), int(cam.image_size[1]))
    views = CameraViews.from_camera_doc(cam.meta)
    draws, note = LampDraws.from_doc(ldoc, camera_json, views, cam.K, cam.dist, size, lamps) if lamps \
        else (None, "")
    return CalibrationInputs(K=cam.K, dist=cam.dist, size=size,
                             lamps=lamps, lamps_std=lamp_std(ldoc), radius=rig.cylinder_radius,
                             height=rig.sample_height, poses=poses,
                             sources_files={"camera": str(camera_json), "lamps": str(lamps_json),
                                            "capture": str(capture_dir)},
                             camera_views=views, camera_stream=None if draws is None else draws.seed,
                             lamp_draws=draws, lamp_draws_note=note)


def recorded_poses(doc, camera_json, capture_dir, rotations=None) -> tuple[dict | None, str]:
    """The poses a samples table records (``df.attrs["poses"]``, written by ``glossrig extract``:
    :func:`glossrig.core.extraction.extract.recorded_geometry`) as :func:`load_inputs`' ``solved``,
    where they are the poses this calibration would solve: ``camera_json`` and ``capture_dir``'s
    rig file have the sha256 they were solved with, and for each rotation the capture's manifest
    names the same calibration image, which is there with its recorded sha256. Otherwise (None,
    why): every pose is solved again from the capture. The physically right start for the draws
    too: the poses the table's rows were measured with. ``rotations`` (the table's): those the
    record lacks are solved again, and the returned text says so. Metadata of another structure
    (damaged, or written by another version) is not used: solved again, and said."""
    from glossrig.core.capture import load_manifest, sha256_file

    if not doc:
        return None, "the samples table records no poses: solved again from the capture"
    try:
        per = {float(k): v for k, v in doc["per_rotation"].items()}
        files = {r: str(v["file"]) for r, v in per.items()}
        want = {"camera": doc["camera_sha256"], "rig": doc["rig_sha256"]}
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        return None, f"the samples table's pose record is unreadable ({type(e).__name__}: {e}): solved again"
    if not Path(camera_json).is_file() or sha256_file(camera_json) != want["camera"]:
        return None, f"{camera_json} is not the camera.json the table's poses were solved with: solved again"
    man = load_manifest(capture_dir)
    if sha256_file(man.rig_path()) != want["rig"]:
        return None, f"{man.rig_path()} is not the rig file the table's poses were solved with: solved again"
    for rot, f in files.items():
        named = [im for im in man.select("calibration") if float(im.rotation) == rot]
        img = Path(capture_dir) / f
        if len(named) != 1 or named[0].file != f or not img.is_file() or sha256_file(img) != named[0].sha256 \
                or named[0].sha256 != per[rot].get("sha256"):
            return None, f"{img} is not the calibration image the table's poses came from: solved again"
    lacking = sorted({float(r) for r in rotations or ()} - set(per))
    how = "recorded by glossrig extract (same camera.json, rig file and calibration images)"
    if lacking:
        how += f"; rotations {', '.join(f'{r:g}' for r in lacking)} not recorded: solved again"
    return per, how


def rotation_from_vector(w) -> np.ndarray:
    """The rotation matrix of rotation vector ``w`` (axis times angle, radians; Rodrigues'
    formula, ``cv2.Rodrigues``): the project's one conversion for the drawn pose errors
    (here and :mod:`glossrig.core.design.error_budget`)."""
    import cv2

    return cv2.Rodrigues(np.asarray(w, float).reshape(3, 1))[0]


def _draw_pose(p: dict, K, dist, rng, poses_on: bool, intr_on: bool):
    """One draw of a pose (camera frame): the refined pose, moved by the change of the
    corner PnP under the drawn intrinsics and by its own stated noise."""
    import cv2

    R, t = p["R"].copy(), p["t"].copy()
    if intr_on:
        flag = cv2.SOLVEPNP_ITERATIVE
        rv0 = cv2.Rodrigues(p["R_pnp"])[0]
        ok, rv, tv = cv2.solvePnP(p["obj"].astype(np.float64), p["img"].astype(np.float64), K, dist,
                                  rvec=rv0.copy(), tvec=p["t_pnp"].reshape(3, 1).copy(),
                                  useExtrinsicGuess=True, flags=flag)
        if ok:
            # the camera-frame motion x -> dR x + (t_new - dR t_pnp) that takes the PnP pose to
            # its re-solved one, applied to the refined pose
            dR = cv2.Rodrigues(rv)[0] @ p["R_pnp"].T
            R = dR @ R
            t = dR @ t + (tv.ravel() - dR @ p["t_pnp"])
    if poses_on:
        w = np.radians(p["std_rot_deg"]) * rng.standard_normal(3)
        R = R @ rotation_from_vector(w)                 # about the marker's own axes (poses.refine_pose_edges)
        t = t + p["std_t_mm"] * rng.standard_normal(3)
    return R, t


def row_angles(cal: CalibrationInputs, u, v, led, rotation, *, K=None, poses=None, lamps=None, dist=None):
    """The BRDF angles (dict of arrays, with ``cos_in``, ``cos_out``, ``valid``) of the
    rows at block centres ``(u + 0.5, v + 0.5)``, recomputed from a calibration
    (default: the nominal one): ``poses`` rotation -> ((R_hold, t_hold), (R_cyl, t_cyl))
    in the camera frame."""
    from glossrig.core.calibration.poses import relative_to_holder
    from glossrig.core.extraction.cylinder import SurfaceSamples, intersect_cylinder, sample_angles, undistorted_rays
    from glossrig.core.models.angles import ANGLE_COLUMNS, normalize

    K = cal.K if K is None else K
    dist = cal.dist if dist is None else dist
    lamps = cal.lamps if lamps is None else lamps
    n = len(u)
    out = {k: np.full(n, np.nan) for k in (*ANGLE_COLUMNS, "cos_in", "cos_out")}
    valid = np.zeros(n, bool)
    for rot in np.unique(rotation):
        rp = cal.poses.get(float(rot))
        if rp is None:
            raise InputError(f"no poses for rotation {rot:g} deg")
        if poses is not None and float(rot) in poses:
            (Rh, th), (Rc, tc) = poses[float(rot)]
        else:
            Rh, th, Rc, tc = rp["holder"]["R"], rp["holder"]["t"], rp["cylinder"]["R"], rp["cylinder"]["t"]
        R_cyl, t_cyl = relative_to_holder(Rh, th, Rc, tc)
        sel = np.flatnonzero(rotation == rot)
        d_cam = undistorted_rays(K, dist, u[sel] + 0.5, v[sel] + 0.5)
        C = -Rh.T @ th
        o_cyl = R_cyl.T @ (C - t_cyl)
        p_cyl, ok = intersect_cylinder(o_cyl, (d_cam @ Rh) @ R_cyl, cal.radius, -cal.height / 2, cal.height / 2)
        pts = p_cyl @ R_cyl.T + t_cyl
        nrm = normalize(p_cyl * np.array([1.0, 0.0, 1.0])) @ R_cyl.T
        s = SurfaceSamples(u=u[sel], v=v[sel], points=pts, normals=nrm, camera_centre=C,
                           axis=R_cyl @ np.array([0.0, 1.0, 0.0]))
        for L in np.unique(led[sel]):
            m = led[sel] == L
            if int(L) not in lamps:
                raise InputError(f"the lamp file has no LED {int(L)}")
            sub = SurfaceSamples(u=s.u[m], v=s.v[m], points=s.points[m], normals=s.normals[m],
                                 camera_centre=C, axis=s.axis)
            ang = sample_angles(sub, lamps[int(L)], float(rot))
            idx = sel[m]
            for k in out:
                out[k][idx] = ang[k]
            valid[idx] = ok[m]
    out["valid"] = valid & (out["cos_in"] > 0) & (out["cos_out"] > 0)
    return out


def lamp_draw(rng, n_leds: int) -> np.ndarray:
    """``(n_leds, 3)`` standard normal draws of the lamps' errors in units of each LED's std, per
    holder axis: ``sqrt(f) z + sqrt(1 - f) z_k`` with ``z`` one draw shared by every LED and ``z_k``
    the LED's own, ``f`` :data:`LAMP_COMMON_FRACTION` (:data:`LAMP_DRAW`)."""
    f = np.asarray(LAMP_COMMON_FRACTION)
    common = rng.standard_normal(3)
    return np.sqrt(f) * common + np.sqrt(1 - f) * rng.standard_normal((n_leds, 3))


def draw_calibration(cal: CalibrationInputs, rng, sources=SOURCES, k: int | None = None):
    """One Monte Carlo draw: (K, dist, poses, lamps, albedo scale, angular coefficients).
    The intrinsics and distortion are drawn together by :func:`camera_draw` where the
    camera file allows it (else not drawn: :func:`intrinsics_drawn`). ``k``: the draw's
    number; with ``cal.camera_stream`` the camera is :func:`numbered_camera_draw` ``k``, and
    where ``cal.lamp_draws`` holds draw ``k`` the lamps are those solved under that camera,
    each moved by its own refinement noise (:class:`LampDraws`); otherwise the lamps are
    drawn independently of the camera (:func:`lamp_draw`)."""
    K, dist = cal.K.copy(), np.asarray(cal.dist, float).copy()
    intr = intrinsics_drawn(cal, sources)
    joint = k is not None and cal.lamp_draws is not None and k < cal.lamp_draws.n
    if intr:
        assert cal.camera_views is not None
        if k is not None and cal.camera_stream is not None and (joint or cal.lamp_draws is None):
            K, dist = numbered_camera_draw(cal.camera_views, cal.K, cal.dist, cal.size, cal.camera_stream, k)
        else:
            K, dist = camera_draw(cal.camera_views, cal.K, cal.dist, cal.size, rng)
    poses = {}
    for rot, rp in cal.poses.items():
        poses[rot] = tuple(_draw_pose(rp[j], K, dist, rng, "poses" in sources, intr)
                           for j in ("holder", "cylinder"))
    if "lamps" not in sources:
        lamps = dict(cal.lamps)
    elif joint:
        assert cal.lamp_draws is not None and k is not None
        d = cal.lamp_draws
        lamps = {led: p + (d.positions[led][k] - d.positions[led].mean(axis=0))
                 + d.noise_mm[led] * rng.standard_normal(3) for led, p in cal.lamps.items()}
    else:
        lamps = {led: p + cal.lamps_std[led] * e
                 for (led, p), e in zip(cal.lamps.items(), lamp_draw(rng, len(cal.lamps)))}
    if "albedo" in sources:
        scale = 1.0 + cal.albedo_u * rng.standard_normal()
        hi, ho = cal.angular_u * rng.standard_normal(2)
    else:
        scale, hi, ho = 1.0, 0.0, 0.0
    return K, dist, poses, lamps, scale, (hi, ho)


def intrinsics_drawn(cal: CalibrationInputs, sources=SOURCES) -> bool:
    """Whether a draw varies the intrinsics: asked for, and the camera file holds the
    views a parametric bootstrap needs (:class:`CameraViews`)."""
    return "intrinsics" in sources and cal.camera_views is not None


def _refit(ang, y, sw, x0, weighting, clip, max_iter: int = 12, fp=None):
    """The point model (eq. 4.79) refitted to ``y`` at the angles ``ang`` by weighted least
    squares (eq. 4.81-4.82), from ``x0`` (solver parameters, log alphas): Gauss-Newton with
    step halving, within Table 4.2's bounds. The draws move the optimum by little, so a
    few steps from a nearby start converge (a trust-region solver's bookkeeping cost 10
    times as much here). With ``fp`` (a :class:`~glossrig.core.fitting.footprint_model.SampleFootprint`
    of these rows) the model is eq. 4.79 averaged over each row's footprint, as ``glossrig
    fit`` fits it: for a lobe about as narrow as a footprint the point model describes
    other parameters altogether, and its sensitivity to the calibration is not the fit's."""
    from glossrig.core.fitting.fit import peak_weight, solver_bounds
    from glossrig.core.fitting.footprint_model import footprint_eval
    from glossrig.core.models.ward import ward_geometry, ward_param_jacobian, ward_parts

    W = np.sqrt(sw) * peak_weight(ang["theta_in"], ang["phi_in"], ang["theta_out"], ang["phi_out"],
                                  ang.get("theta_d"), ang.get("phi_d"), mode=weighting)
    geo = ward_geometry(ang["theta_in"], ang["theta_out"], ang["theta_h"], ang["phi_h"])
    yc = y if clip is None else np.minimum(y, clip)
    lb, ub = solver_bounds()        # the fit's own bounds (rho_s <= RHO_S_MAX): a draw's refit stays in them

    def residual(x):
        if fp is not None:       # the footprint average (its Jacobian is evaluated anew below)
            f, parts = footprint_eval(geo, fp, x, log_alpha=True), None
        else:
            f, parts = ward_parts(geo, x, log_alpha=True)
        return W * ((f if clip is None else np.minimum(f, clip)) - yc), f, parts

    x = np.clip(np.asarray(x0, float), lb, ub)
    r, f, parts = residual(x)
    cost = float(r @ r)
    for _ in range(max_iter):
        J = (ward_param_jacobian(geo, x, parts, log_alpha=True) if fp is None
             else footprint_eval(geo, fp, x, jac=True, log_alpha=True)[1]) * W[:, None]
        if clip is not None:
            J[f >= clip] = 0.0
        norms = np.sqrt(np.einsum("ij,ij->j", J, J))
        scale = np.where(norms > 0, norms, 1.0)
        step = np.linalg.lstsq(J / scale, -r, rcond=1e-12)[0] / scale
        t = 1.0
        while t > 1e-4:
            xn = np.clip(x + t * step, lb, ub)
            rn, fn, pn = residual(xn)
            cn = float(rn @ rn)
            if cn <= cost:
                break
            t *= 0.5
        else:
            break
        # converged: a step below 1e-8 of the parameters (their uncertainties are > 1e-5 of
        # them) or no decrease of the cost beyond rounding
        done = np.all(np.abs(xn - x) <= 1e-8 * (1.0 + np.abs(x))) or cost - cn <= 1e-12 * cost
        x, r, f, parts, cost = xn, rn, fn, pn, cn
        if done:
            break
    return x


def _reported(x, x_ref) -> np.ndarray:
    """Solver vector -> reported (rho_d, rho_s, alpha_x, alpha_y, rot) with the rotation
    taken to within pi/2 of the reference's."""
    rot = x[4] + ((x_ref[4] - x[4] + math.pi / 2) // math.pi) * math.pi
    return np.array([x[0], x[1], math.exp(x[2]), math.exp(x[3]), rot])


# one BLAS thread (core.workers.one_blas_thread): the refits solve 20 000 x 5 least squares; measured
# 1.9-2.2 CPU-s with one thread against 6.0-6.2 with OpenBLAS's default threads on the 2-core machine
# under load (24 draws x 4 channels, the same draws; u within 3e-5 relative: reductions in another
# order; /tmp/s8/calcheck.py)
@in_one_blas_thread
def calibration_component(df, fits: dict, cal: CalibrationInputs, *, n_draws: int = 24, max_rows: int = 20_000,
                          seed: int = 0, weighting: str = "mirror", clip: float | None = None,
                          use_weight_column: bool = True, sources=SOURCES, footprint: bool = False) -> dict:
    """The calibration component (module docstring): ``{channel: {param: {"u": u, "dof":
    n_draws - 1}}}`` for the channels of ``fits`` (channel -> WardFit or WardParams, in
    canonical form), plus ``"_meta"`` (draws, rows, sources, shift samples). ``df``: the
    samples table (``u, v, led, rotation``, angles, ``r, g, b``, optionally ``weight``).
    ``footprint``: refit the footprint-averaged model (as ``glossrig fit`` does by
    default; each row's footprint from the whole table's neighbouring blocks, held at
    the nominal geometry: it moves with the calibration at second order only)."""
    from glossrig.core.fitting.fit import channel_values, solver_params
    from glossrig.core.models.ward import WardParams

    need = ("u", "v", "led", "rotation")
    missing = [c for c in need if c not in df]
    if missing:
        raise InputError(f"calibration uncertainty: the samples table lacks {', '.join(missing)}")
    if n_draws < 2:
        raise InputError(f"calibration uncertainty needs at least 2 draws, got {n_draws}")
    rng = np.random.default_rng(seed)
    sw_all = np.asarray(df["weight"], float) if (use_weight_column and "weight" in df) else np.ones(len(df))
    rows = np.flatnonzero(sw_all > 0)
    if rows.size > max_rows:
        rows = np.sort(rng.choice(rows, max_rows, replace=False))
    sub = df.iloc[rows]
    u, v = sub["u"].to_numpy(float), sub["v"].to_numpy(float)
    led, rot = sub["led"].to_numpy(), sub["rotation"].to_numpy(float)
    sw = sw_all[rows]
    ys = {c: channel_values(sub, c) for c in fits}
    # a channel missing in a row (NaN, glossrig.core.samples) leaves that row out of its refits
    fin = {c: np.isfinite(y) for c, y in ys.items()}
    x0 = {c: solver_params(f if isinstance(f, WardParams) else f.params) for c, f in fits.items()}
    nominal = row_angles(cal, u, v, led, rot)
    ang_dev = _angle_check(nominal, sub)
    ok0 = nominal["valid"]
    fps: dict = {}              # the channels whose draws refit the footprint model, and their footprints
    table_fp = None
    base, start = {}, {}
    for c in fits:
        okc = ok0 & fin[c]
        start[c] = _refit(_take(nominal, okc), ys[c][okc], sw[okc], x0[c], weighting, clip)
        if footprint and _point_model_departs(_reported(start[c], x0[c]), x0[c]):
            if table_fp is None:                     # the table's footprints, once, when first needed
                table_fp = _table_footprint(df, rows)
            if table_fp is not False:
                fps[c] = _channel_footprint(table_fp, c, nominal, x0[c])
                start[c] = _refit(_take(nominal, okc), ys[c][okc], sw[okc], x0[c], weighting, clip,
                                  fp=fps[c].take(okc))
        base[c] = _reported(start[c], x0[c])
    shifts: dict[str, list] = {c: [] for c in fits}
    for k in range(n_draws):
        K, dist, poses, lamps, scale, (hi, ho) = draw_calibration(cal, rng, sources, k=k)
        ang = row_angles(cal, u, v, led, rot, K=K, poses=poses, lamps=lamps, dist=dist)
        ok = ang["valid"] & ok0
        mult = scale
        if hi or ho:
            gi, go = 1 - ang["cos_in"][ok], 1 - ang["cos_out"][ok]
            mult = scale * (1 + hi * (gi - gi.mean()) + ho * (go - go.mean()))
        a = _take(ang, ok)
        for c in fits:
            fpc = fps.get(c)
            if fin[c][ok].all():
                x = _refit(a, ys[c][ok] * mult, sw[ok], start[c], weighting, clip,
                           fp=None if fpc is None else fpc.take(ok))
            else:
                keep = fin[c][ok]
                x = _refit({k: v[keep] for k, v in a.items()}, (ys[c][ok] * mult)[keep], sw[ok][keep], start[c],
                           weighting, clip, fp=None if fpc is None else fpc.take(np.flatnonzero(ok)[keep]))
            shifts[c].append(_reported(x, x0[c]) - base[c])
    out: dict = {}
    for c in fits:
        S = np.asarray(shifts[c])
        u_ = S.std(axis=0, ddof=1)
        out[c] = {name: {"u": float(u_[i]), "dof": float(n_draws - 1)} for i, name in enumerate(PARAM_NAMES)}
    model = (f"footprint-averaged refits for {', '.join(fps)} (the point model departs from their lobes by more than "
             f"{FOOTPRINT_REFIT_DEPARTURE:.0%}), point-model refits otherwise" if fps else "point-model refits")
    out["_meta"] = {"method": f"Monte Carlo over calibration draws (GUM-S1), warm-started {model}",
                    "n_draws": int(n_draws), "rows": int(rows.size), "sources": list(sources), "seed": int(seed),
                    "intrinsics_drawn": intrinsics_drawn(cal, sources),
                    "nominal_angle_max_dev_rad": ang_dev, "files": dict(cal.sources_files),
                    "stated": {"intrinsics_reprojection_rms_px":
                               None if cal.camera_views is None else cal.camera_views.rms_px,
                               "lamps_std_mm": {str(k): s.tolist() for k, s in cal.lamps_std.items()},
                               "lamps_draw": LAMP_DRAW if cal.lamp_draws is None else
                               f"draws 0-{min(n_draws, cal.lamp_draws.n) - 1}: the lamps calibrate lamps solved under "
                               f"the same camera draw, plus each LED's refinement noise"
                               + (f"; draws {cal.lamp_draws.n}-{n_draws - 1}: {LAMP_DRAW}"
                                  if n_draws > cal.lamp_draws.n else ""),
                               "lamps_with_camera": cal.lamp_draws_note,
                               "poses_std": f"the edge fits' stated std times {POSE_STD_FACTOR}",
                               "albedo_u_rel": cal.albedo_u, "albedo_angular_u_rel": cal.angular_u}}
    return out


#: the point model's own optimum departing from the footprint fit's lobe (rho_s, alpha_x or
#: alpha_y) by more than this: the draws refit the footprint-averaged model (it costs about
#: twice as much). Below it the lobe is wider than a footprint and the point model's
#: sensitivity to the calibration equals the footprint model's to that relative order
#: (the bias itself cancels in the draws' differences, module docstring).
FOOTPRINT_REFIT_DEPARTURE = 0.05


def _point_model_departs(point_reported: np.ndarray, x0: np.ndarray) -> bool:
    """Whether the nominal point-model refit (reported form) departs from the fit's lobe
    ``x0`` (solver form) by more than :data:`FOOTPRINT_REFIT_DEPARTURE`."""
    lobe = np.array([x0[1], math.exp(x0[2]), math.exp(x0[3])])
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.abs(point_reported[1:4] / lobe - 1)
    return bool(np.any(~np.isfinite(rel)) or np.max(rel) > FOOTPRINT_REFIT_DEPARTURE)


def _table_footprint(df, rows):
    """The :class:`~glossrig.core.fitting.footprint_model.SampleFootprint` of the subsampled
    ``rows`` (each row's from the whole table's neighbouring blocks), or False where the table
    has none (not on extract's grid of Bayer blocks)."""
    from glossrig.core.fitting.footprint_model import sample_footprint, table_jacobian

    Jt = table_jacobian(df)
    return False if Jt is None else sample_footprint(np.asarray(Jt)[rows])


def _channel_footprint(table_fp, channel: str, nominal: dict, x0c):
    """``table_fp`` for ``channel``'s read kernel, with the pixel quadrature its nominal lobe
    ``x0c`` needs (as ``fit_ward`` chooses it)."""
    from glossrig.core.models.ward import ward_geometry

    ok = nominal["valid"]
    geo = ward_geometry(nominal["theta_in"][ok], nominal["theta_out"][ok], nominal["theta_h"][ok],
                        nominal["phi_h"][ok])
    fp = table_fp.for_channel(channel)
    return fp.with_orders(fp.take(ok).orders_for(geo, x0c, log_alpha=True))


def _take(ang: dict, ok) -> dict:
    return {k: a[ok] for k, a in ang.items() if k != "valid"}


def _angle_check(nominal: dict, sub) -> float | None:
    """Largest difference between the recomputed nominal angles and the table's (radians;
    theta columns): the recomputation reproduces the extraction's geometry."""
    ok = nominal["valid"]
    devs = [np.nanmax(np.abs(nominal[k][ok] - sub[k].to_numpy(float)[ok]))
            for k in ("theta_in", "theta_out", "theta_h") if k in sub and ok.any()]
    return float(max(devs)) if devs else None


def add_calibration(uncertainty: dict, cal: dict | None, note: str | None = None) -> dict:
    """A channel's budget (fit.json's ``"uncertainty"``, :func:`glossrig.core.fitting.uncertainty.channel_budget`)
    with the calibration component ``cal`` (``{param: {"u", "dof"}}``) put in and each
    parameter's combination, coverage factor and interval recomputed; ``cal`` None: the
    budget unchanged but for ``note`` in its ``omitted``."""
    from glossrig.core.fitting.uncertainty import FOOTPRINT_DOF, parameter_budget

    out = dict(uncertainty)
    budget = dict(out.get("budget") or {})
    omitted = dict(budget.get("omitted") or {})
    if cal is None:
        if note:
            omitted["calibration"] = note
        budget["omitted"] = omitted
        out["budget"] = budget
        return out
    dofs = dict(budget.get("dof") or {})
    dof_of = {"noise": dofs.get("noise"), "model": dofs.get("model"), "footprint": dofs.get("footprint", FOOTPRINT_DOF)}
    for name in PARAM_NAMES:
        e = out[name]
        comps = {}
        for k, uval in (e.get("components") or {}).items():
            if k == "calibration" or uval is None:
                continue
            d = dof_of.get(k)
            comps[k] = (float(uval), float(d) if d else math.inf)
        comps["calibration"] = (float(cal[name]["u"]), float(cal[name].get("dof") or math.inf))
        out[name] = parameter_budget(name, e["value"], comps)
    omitted.pop("calibration", None)
    budget["omitted"] = omitted
    dofs["calibration"] = float(cal[PARAM_NAMES[0]].get("dof") or math.inf)
    budget["dof"] = dofs
    out["budget"] = budget
    return out
