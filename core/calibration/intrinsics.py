"""Camera intrinsics from checkerboard views (thesis 4.3.2, "Intrinsic Parameters").

As in the thesis: the inner corners of a planar checkerboard seen in many
poses, their known board coordinates, and OpenCV's calibration (Zhang's method
with the k1 k2 p1 p2 k3 distortion model; ``cv2.calibrateCamera``). Details
the thesis leaves open, as done here:

* each raw view is linearised and demosaiced (thesis 4.3.1-4.3.2) and the
  corners are found on the green channel - the densest CFA channel - with
  ``cv2.findChessboardCorners`` (``cv2.findChessboardCornersSB`` as a
  fallback) on an 8-bit copy, then refined with ``cv2.cornerSubPix`` on the
  linear float image with a search window scaled to the board's square size
  in pixels (about 1/8 of it);
* a view larger than :data:`DETECT_MP` megapixels (a full-resolution 24 MP
  frame) is searched on a copy reduced by an integer factor (block means;
  ``cv2.findChessboardCornersSB`` first there) - the search on the full frame
  took seconds to minutes per view - and the corners found there are refined
  once more with ``cv2.cornerSubPix`` on the full-resolution image
  (validation/calibration_fullres.md);
* views where the board is not found are reported and skipped; after a
  first calibration, views whose reprojection RMS exceeds 3x the median (and
  1 px) are dropped as outliers and the calibration repeated; fewer than
  ``min_views`` usable views is an error;
* the result is saved as JSON (:func:`save_camera`) with its provenance
  (files and sha256) and read back, validated, by :func:`load_camera`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from glossrig.core.atomic import atomic_write_json
from glossrig.core.capture import load_manifest, now_iso
from glossrig.core.calibration.demosaic import demosaic
from glossrig.core.errors import InputError
from glossrig.core.progress import progress_enabled
from glossrig.core.toml_input import read_json
from glossrig.core.calibration.raw import linearize

#: Fewest usable checkerboard views accepted (OpenCV needs 3 for this model;
#: a handful more keep the principal point and k3 from running away).
MIN_VIEWS = 5
FORMAT = "glossrig camera calibration"
DISTORTION_NAMES = ("k1", "k2", "p1", "p2", "k3")
#: Largest image (megapixels) the chessboard search runs on; larger views are
#: searched on a reduced copy and refined at full resolution (:func:`find_board`).
#: The search on a 24 MP frame took seconds to minutes per view (issue 19); the
#: twin's views up to scale ~0.25 (1508 x 1008 px) stay on the direct route.
DETECT_MP = 2.0


@dataclass
class CameraCalibration:
    """Intrinsics at one image size: pinhole ``fx fy cx cy`` (pixel centres at
    integer coordinates, OpenCV) and distortion k1 k2 p1 p2 k3."""

    fx: float
    fy: float
    cx: float
    cy: float
    distortion: tuple[float, ...]
    image_size: tuple[int, int]          # (width, height)
    rms_px: float = float("nan")
    path: str | None = None
    meta: dict = field(default_factory=dict, repr=False)

    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        return np.asarray(self.distortion, np.float64)

    def check_size(self, size: tuple[int, int], where) -> None:
        """Stop if an image of ``size`` (w, h) is not what these intrinsics are for."""
        if tuple(int(v) for v in size) != tuple(self.image_size):
            raise InputError(f"image is {size[0]}x{size[1]} px but the camera calibration "
                             f"{self.path or ''} is for {self.image_size[0]}x{self.image_size[1]} px "
                             f"(another camera, scale or crop)", path=where)


# ------------------------------------------------------------- detection

def board_points(inner: tuple[int, int], square: float) -> np.ndarray:
    """Board coordinates (mm, z = 0) of the inner corners, row by row, as
    ``cv2.findChessboardCorners`` orders them."""
    nx, ny = inner
    return np.array([[i * square, j * square, 0.0] for j in range(ny) for i in range(nx)], np.float32)


def find_board(green: np.ndarray, inner: tuple[int, int], detect_mp: float | None = DETECT_MP) -> np.ndarray | None:
    """Sub-pixel inner corners (N, 1, 2) float32 of a checkerboard in a linear
    single-channel image, or None if the board is not found.

    An image larger than ``detect_mp`` megapixels is searched on a copy reduced
    by the smallest integer factor k that brings it within ``detect_mp`` (block
    means), and the corners found there are refined again with
    ``cv2.cornerSubPix`` on the full-resolution image. There
    ``cv2.findChessboardCornersSB`` goes first: ~0.5 s on 1.5 MP, and it finds
    boards that fill the frame, on which the classic detector - the fallback -
    fails slowly (seconds at 1.5 MP, minutes at 24 MP). If neither finds the
    board and k >= 4, ``findChessboardCornersSB`` alone once more at k // 2;
    never at full resolution. ``detect_mp=None``: search the image as it is
    (the route of images within ``detect_mp``)."""
    g = np.asarray(green, np.float32)
    size = (int(inner[0]), int(inner[1]))
    h, w = g.shape
    k = 1 if detect_mp is None else max(1, math.ceil(math.sqrt(w * h / (float(detect_mp) * 1e6))))
    if k == 1:
        return _find_board_at(g, size)
    levels = [(k, ("sb", "classic"))] + ([(k // 2, ("sb",))] if k >= 4 else [])
    for f, order in levels:
        hf, wf = h // f, w // f
        # block means: reduced pixel (i, j) covers full pixels f*i ... f*i + f - 1
        small = cv2.resize(g[:hf * f, :wf * f], (wf, hf), interpolation=cv2.INTER_AREA)
        found = _find_board_at(small, size, order)
        if found is not None:
            return _refine_corners(g, found.reshape(-1, 2).astype(np.float64) * f + (f - 1) / 2.0, size)
    return None


def _corner_spacing(corners: np.ndarray, inner: tuple[int, int]) -> float:
    """Median distance (px) between neighbouring corners, the shorter board direction."""
    c = np.asarray(corners).reshape(inner[1], inner[0], 2)
    return float(min(np.median(np.linalg.norm(np.diff(c, axis=1), axis=-1)),
                     np.median(np.linalg.norm(np.diff(c, axis=0), axis=-1))))


def _subpix(img: np.ndarray, corners: np.ndarray, spacing: float) -> np.ndarray:
    """``cv2.cornerSubPix`` with a search window of about 1/8 of the square size
    (half-width 3 to 30 px)."""
    half = int(np.clip(round(spacing / 8.0), 3, 30))
    crit = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-5)
    return cv2.cornerSubPix(img, np.asarray(corners, np.float32).reshape(-1, 1, 2), (half, half), (-1, -1), crit)


def _find_board_at(g: np.ndarray, size: tuple[int, int],
                   order: tuple[str, ...] = ("classic", "sb")) -> np.ndarray | None:
    """Search (the detectors in ``order``: ``classic`` = findChessboardCorners,
    ``sb`` = findChessboardCornersSB, exhaustive) and sub-pixel corners of the
    board in ``g`` at its own resolution."""
    hi = float(np.percentile(g, 99.5))
    if not hi > 0:
        return None
    g8 = np.clip(g * (255.0 / hi), 0, 255).astype(np.uint8)
    for detector in order:
        if detector == "classic":
            ok, corners = cv2.findChessboardCorners(g8, size,
                                                    flags=cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE)
        else:
            ok, corners = cv2.findChessboardCornersSB(g8, size,
                                                      flags=cv2.CALIB_CB_NORMALIZE_IMAGE | cv2.CALIB_CB_EXHAUSTIVE)
        if ok:
            break
    else:
        return None
    spacing = _corner_spacing(corners, size)
    # The classic detector now and then places a corner several px off, on an
    # edge where cornerSubPix cannot recover it: re-seed corners that disagree
    # with a smooth (cubic) board -> image map fitted to the others.
    corners = corners.reshape(-1, 2).astype(np.float64)
    pred, bad = _board_map_outliers(corners, size, tol=max(1.5, 0.03 * spacing))
    corners[bad] = pred[bad]
    refined = _subpix(g / hi, corners, spacing)
    _, bad = _board_map_outliers(refined.reshape(-1, 2).astype(np.float64), size, tol=max(1.0, 0.02 * spacing))
    if bad.any():
        return None
    return refined


def _refine_corners(g: np.ndarray, corners: np.ndarray, size: tuple[int, int]) -> np.ndarray | None:
    """Corners found on a reduced copy, mapped to full-resolution pixels,
    refined on the full-resolution image ``g`` (cornerSubPix is invariant to
    the image's intensity scale, so ``g`` is used as it is)."""
    spacing = _corner_spacing(corners, size)
    refined = _subpix(g, corners, spacing)
    _, bad = _board_map_outliers(refined.reshape(-1, 2).astype(np.float64), size, tol=max(1.0, 0.02 * spacing))
    if bad.any():
        return None
    return refined


def _board_map_outliers(corners: np.ndarray, inner: tuple[int, int], tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Fit image = cubic(board i, j) to the corners with iterative rejection;
    returns (predicted positions, mask of corners farther than ``tol`` px).
    A cubic absorbs perspective and lens distortion over the board to well
    below a pixel."""
    nx, ny = inner
    j, i = np.mgrid[0:ny, 0:nx]
    u, v = (i.ravel() - (nx - 1) / 2) / nx, (j.ravel() - (ny - 1) / 2) / ny
    A = np.stack([u ** a * v ** b for a in range(4) for b in range(4 - a)], axis=-1)
    keep = np.ones(len(u), bool)
    for _ in range(4):
        coef, *_ = np.linalg.lstsq(A[keep], corners[keep], rcond=None)
        pred = A @ coef
        err = np.linalg.norm(corners - pred, axis=1)
        new = err < max(tol, 4 * 1.4826 * np.median(err[keep]))
        if np.array_equal(new, keep) or new.sum() < A.shape[1] + 4:
            break
        keep = new
    return pred, err > tol


# ------------------------------------------------------------ calibration

def calibrate_intrinsics(checker_dir: str | Path, inner: tuple[int, int] | None = None, square: float | None = None,
                         min_views: int = MIN_VIEWS, progress: bool = False) -> tuple[CameraCalibration, dict]:
    """Calibrate from the ``checkerboard`` images of a capture folder.

    ``inner`` (inner corners per row, per column) and ``square`` (mm) default
    to the rig's ``[checkerboard]`` section. Returns the calibration and a
    report dict: per-view RMS, skipped views with reasons, standard
    deviations of the intrinsics, and the detected corners."""
    from tqdm import tqdm

    from glossrig.core.rig import load_rig

    man = load_manifest(checker_dir)
    views = man.select("checkerboard")
    if not views:
        raise InputError("no checkerboard images (role 'checkerboard') in the manifest", path=man.path)
    if inner is None or square is None:
        rig = load_rig(man.rig_path())
        inner = inner or rig.checkerboard.inner_corners
        square = square or rig.checkerboard.square
    if len(inner) != 2 or min(inner) < 2:
        raise InputError(f"checkerboard inner corners must be two counts >= 2, got {inner}")
    if not (square > 0 and math.isfinite(square)):
        raise InputError(f"checkerboard square must be a positive length in mm, got {square}")
    obj = board_points(inner, square)

    size: tuple[int, int] | None = None
    found, skipped = [], []
    for im in tqdm(views, desc="checkerboard", unit="view", disable=not progress_enabled(progress)):
        path = man.folder / im.file
        if not path.is_file():
            raise InputError("checkerboard image listed in the manifest is missing", path=path)
        frame = man.read_raw(im)            # checks the manifest's sha256
        digest = im.sha256
        w, h = frame.full_size
        if size is None:
            size = (w, h)
        elif (w, h) != size:
            raise InputError(f"image is {w}x{h} px but earlier views are {size[0]}x{size[1]}", path=path)
        green = demosaic(linearize(frame), frame.cfa)[..., 1]
        corners = find_board(green, inner)
        if corners is None:
            skipped.append({"file": im.file, "sha256": digest, "reason": f"{inner[0]}x{inner[1]} board not found"})
            continue
        found.append({"file": im.file, "sha256": digest, "corners": corners})
    if len(found) < min_views:
        names = ", ".join(s["file"] for s in skipped) or "none"
        raise InputError(f"only {len(found)} of {len(views)} checkerboard views are usable (need {min_views}); "
                         f"board not found in: {names}", path=man.folder)
    assert size is not None     # views is not empty: the loop read at least one image's size

    crit = (cv2.TERM_CRITERIA_COUNT + cv2.TERM_CRITERIA_EPS, 500, 1e-14)

    def run(items):
        return cv2.calibrateCameraExtended([obj] * len(items), [f["corners"] for f in items], size, None, None,
                                           flags=0, criteria=crit)

    rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = run(found)
    per_view = per_view.ravel()
    limit = max(3.0 * float(np.median(per_view)), 1.0)
    bad = [i for i, e in enumerate(per_view) if e > limit]
    if bad and len(found) - len(bad) >= min_views:
        for i in bad:
            skipped.append({"file": found[i]["file"], "sha256": found[i]["sha256"],
                            "reason": f"outlier: reprojection RMS {per_view[i]:.3f} px > {limit:.3f} px"})
        found = [f for i, f in enumerate(found) if i not in bad]
        rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = run(found)
        per_view = per_view.ravel()
    d = dist.ravel()[:5]
    std = std_in.ravel()
    cal = CameraCalibration(fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                            distortion=tuple(float(v) for v in d), image_size=size, rms_px=float(rms))
    report = {
        "source": str(Path(checker_dir)), "rig": man.rig, "created": now_iso(), "image_size": list(size),
        "board": {"inner_corners": list(inner), "square_mm": float(square)},
        "rms_px": float(rms),
        "std": {"fx": float(std[0]), "fy": float(std[1]), "cx": float(std[2]), "cy": float(std[3]),
                **{n: float(v) for n, v in zip(DISTORTION_NAMES, std[4:9])}},
        "views": [{"file": f["file"], "sha256": f["sha256"], "rms_px": float(e),
                   "rvec": r.ravel().tolist(), "tvec_mm": t.ravel().tolist()}
                  for f, e, r, t in zip(found, per_view, rvecs, tvecs)],
        "skipped": skipped,
        "min_views": int(min_views),
    }
    cal.meta = report
    report["_corners"] = [f["corners"].reshape(-1, 2) for f in found]
    report["_object"] = obj
    return cal, report


# ------------------------------------------------------------------ files

def save_camera(cal: CameraCalibration, report: dict, path: str | Path, overwrite: bool = False) -> Path:
    """Write the calibration JSON (atomically; refuses to replace a file
    unless ``overwrite``)."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise InputError("file exists; refusing to overwrite a camera calibration (use --force)", path=path)
    if not path.parent.is_dir():
        raise InputError("output folder does not exist", path=path.parent)
    doc = {"format": FORMAT, "version": 1,
           "fx": cal.fx, "fy": cal.fy, "cx": cal.cx, "cy": cal.cy,
           "camera_matrix": cal.K.tolist(),
           "distortion_model": "opencv k1 k2 p1 p2 k3",
           "distortion": list(cal.distortion),
           "image_size": list(cal.image_size),
           "reprojection_rms_px": cal.rms_px}
    doc.update({k: v for k, v in report.items() if not k.startswith("_") and k not in ("image_size", "rms_px")})
    atomic_write_json(path, doc)
    cal.path = str(path)
    return path


def _finite(d: dict, key: str, path, positive: bool = False) -> float:
    if key not in d:
        raise InputError(f"camera calibration lacks {key!r}", path=path)
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"{key} must be a finite number, got {v!r}", path=path)
    if positive and not v > 0:
        raise InputError(f"{key} must be > 0, got {v}", path=path)
    return float(v)


def load_camera(path: str | Path) -> CameraCalibration:
    """Read and validate a camera calibration written by :func:`save_camera` (the one
    reader of the file; errors name it)."""
    path = Path(path)
    if not path.is_file():
        raise InputError("camera calibration file not found", path=path)
    d = read_json(path, "camera calibration")
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise InputError(f"not a glossrig camera calibration (format must be {FORMAT!r})", path=path)
    size = d.get("image_size")
    if (not isinstance(size, list) or len(size) != 2 or any(isinstance(v, bool) or not isinstance(v, int) or v < 2
                                                             for v in size)):
        raise InputError(f"image_size must be [width, height] in pixels, got {size!r}", path=path)
    fx, fy = _finite(d, "fx", path, True), _finite(d, "fy", path, True)
    cx, cy = _finite(d, "cx", path), _finite(d, "cy", path)
    if not (0 <= cx <= size[0] and 0 <= cy <= size[1]):
        raise InputError(f"principal point ({cx:.1f}, {cy:.1f}) lies outside the {size[0]}x{size[1]} image", path=path)
    dist = d.get("distortion")
    if (not isinstance(dist, list) or len(dist) != 5
            or any(isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) for v in dist)):
        raise InputError(f"distortion must be 5 finite numbers (k1 k2 p1 p2 k3), got {dist!r}", path=path)
    if "camera_matrix" in d:
        K = np.asarray(d["camera_matrix"], dtype=float)
        want = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]])
        if K.shape != (3, 3) or not np.allclose(K, want, rtol=1e-9, atol=1e-9):
            raise InputError("camera_matrix disagrees with fx, fy, cx, cy (file edited by hand?)", path=path)
    rms = d.get("reprojection_rms_px", float("nan"))
    meta = {k: v for k, v in d.items() if k not in ("fx", "fy", "cx", "cy", "distortion", "image_size")}
    return CameraCalibration(fx=fx, fy=fy, cx=cx, cy=cy, distortion=tuple(float(v) for v in dist),
                             image_size=(int(size[0]), int(size[1])), rms_px=float(rms), path=str(path), meta=meta)


def plot_calibration(cal: CameraCalibration, report: dict, path: str | Path) -> Path:
    """PNG: per-view reprojection RMS and the corner residuals of all views."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a1, a2) = plt.subplots(1, 2, figsize=(11, 4.2))
    names = [v["file"] for v in report["views"]]
    a1.bar(range(len(names)), [v["rms_px"] for v in report["views"]], color="tab:blue")
    a1.axhline(cal.rms_px, color="k", lw=1, ls="--", label=f"overall {cal.rms_px:.3f} px")
    a1.set_xticks(range(len(names)), names, rotation=70, fontsize=7)
    a1.set_ylabel("reprojection RMS (px)")
    a1.legend()
    obj = report["_object"]
    for v, c in zip(report["views"], report["_corners"]):
        proj, _ = cv2.projectPoints(obj.astype(np.float64), np.array(v["rvec"]), np.array(v["tvec_mm"]), cal.K, cal.dist)
        r = c - proj.reshape(-1, 2)
        a2.scatter(r[:, 0], r[:, 1], s=4, alpha=0.6)
    a2.set_aspect("equal")
    a2.set_xlabel("residual x (px)")
    a2.set_ylabel("residual y (px)")
    a2.set_title(f"fx {cal.fx:.1f} fy {cal.fy:.1f} cx {cal.cx:.1f} cy {cal.cy:.1f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)
