"""Checkerboard corners of a large view: the search on a reduced copy and the
sub-pixel refinement at full resolution (glossrig.core.calibration.intrinsics.find_board,
issue 19), on a synthetic board with known corners. The full-resolution twin views are
measured by validation/calibration_fullres.py."""
from __future__ import annotations

import cv2
import numpy as np

from glossrig.core.calibration import intrinsics

INNER = (9, 6)


def _board_image(size=(960, 640), seed=0) -> tuple[np.ndarray, np.ndarray]:
    """A 9x6-inner-corner board seen in perspective, slightly blurred, with noise.
    Returns (image, true corners (54, 2) in cv2's row-by-row order; pixel centres at
    integer coordinates).

    Anti-aliased analytically: across each line of the pattern the checker ramps
    linearly over one pixel (the signed distance in pixels through the homography's
    gradient), so each inner corner is a point-symmetric X-junction centred on its
    true position - a supersampled render would shift the edges by its fine grid's
    sampling error."""
    w, h = size
    nx, ny = INNER
    # board units: inner corner (i, j) at (i, j); the card's outer corners -> image,
    # turned by 17 deg and foreshortened
    card = np.array([[-2, -2], [nx + 1, -2], [nx + 1, ny + 1], [-2, ny + 1]], np.float32)
    quad = np.array([[232, 35], [836, 251], [736, 576], [116, 418]], np.float32)
    H = cv2.getPerspectiveTransform(card, quad)
    Hi = np.linalg.inv(H)
    X, Y = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    d = Hi[2, 0] * X + Hi[2, 1] * Y + Hi[2, 2]
    board = []
    for r in (0, 1):
        b = (Hi[r, 0] * X + Hi[r, 1] * Y + Hi[r, 2]) / d
        grad = np.hypot((Hi[r, 0] - b * Hi[2, 0]) / d, (Hi[r, 1] - b * Hi[2, 1]) / d)
        dist_px = np.abs(b - np.round(b)) / grad
        # +-1 by the cell's parity, ramping to 0 on the lines
        board.append((b, np.where(np.floor(b) % 2 == 0, 1.0, -1.0) * np.minimum(1.0, 2.0 * dist_px)))
    (bx, sx), (by, sy) = board
    img = np.full((h, w), 0.3)                                                  # background
    img[(bx > -2) & (bx < nx + 1) & (by > -2) & (by < ny + 1)] = 0.85          # white card
    pattern = (bx > -1) & (bx < nx) & (by > -1) & (by < ny)
    img[pattern] = (0.44 + 0.41 * sx * sy)[pattern]                             # dark 0.03 / white 0.85
    img = cv2.GaussianBlur(img.astype(np.float32), (0, 0), 0.8)
    img += np.random.default_rng(seed).normal(0, 0.005, img.shape).astype(np.float32)
    pts = np.array([[i, j] for j in range(ny) for i in range(nx)], np.float64)
    truth = cv2.perspectiveTransform(pts.reshape(-1, 1, 2), H).reshape(-1, 2)
    return img, truth


def _error(found: np.ndarray, truth: np.ndarray) -> float:
    """Largest corner error (px), in whichever of the two orders cv2 numbered the board."""
    c = found.reshape(-1, 2).astype(np.float64)
    return min(float(np.abs(c - t).max()) for t in (truth, truth[::-1]))


def test_reduced_search_and_full_resolution_refinement_find_the_true_corners(monkeypatch):
    img, truth = _board_image()
    seen = []

    def spy(search):
        def run(image, *a, **k):
            seen.append(image.shape)
            return search(image, *a, **k)
        return run

    for name in ("findChessboardCorners", "findChessboardCornersSB"):
        monkeypatch.setattr(cv2, name, spy(getattr(cv2, name)))
    detect_mp = 0.05                 # a 0.61 MP image -> searched at 1/4: 240 x 160 px
    found = intrinsics.find_board(img, INNER, detect_mp=detect_mp)
    assert found is not None and found.shape == (54, 1, 2)
    assert seen and all(s[0] * s[1] <= detect_mp * 1e6 for s in seen), seen
    assert seen[0] == (160, 240)
    assert _error(found, truth) < 0.1
    # the same corners as the search at full resolution (numbered from either end)
    direct = intrinsics.find_board(img, INNER, detect_mp=None)
    assert direct is not None
    assert seen[-1] == img.shape
    assert _error(found, direct.reshape(-1, 2)) < 0.05


def test_reduced_search_finds_no_board_in_a_blank_view():
    blank = np.full((640, 960), 0.4, np.float32) + np.random.default_rng(1).normal(0, 0.005, (640, 960)).astype(
        np.float32)
    assert intrinsics.find_board(blank, INNER, detect_mp=0.01) is None
