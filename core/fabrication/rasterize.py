"""Cuts in machine mm -> the halftone grid again: the check that a machine file scratches
what the halftone asks for (issue 6: intersection over union with ``halftone.png``).

A scratch is modelled as the band swept by the blade: a rectangle along the cut, one
scratch thickness wide (thesis 5.1.2: 90 um), with square ends. A halftone cell counts as
scratched when its centre lies inside a band. The cuts are mapped back with the inverse
of the layout (thesis eq. 5.3 undone, :meth:`~.layout.Layout.machine_to_image`), so the
check covers the rotation, shift, scale and the machine's 10 um rounding.
"""
from __future__ import annotations

import math

import numpy as np

from glossrig.core.fabrication.layout import Layout


def _raster_shallow(p0: np.ndarray, p1: np.ndarray, half_width: float, shape: tuple[int, int]):
    """Cells whose centres lie in the bands around segments with ``|dX| >= |dY|``.

    Walks the columns each band touches; in a column, the band spans less than
    ``2 * half_width * sqrt(2)`` rows, and each candidate row is tested exactly.
    """
    rows, cols = shape
    d = p1 - p0
    length = np.hypot(d[:, 0], d[:, 1])
    keep = length > 0
    p0, d, length = p0[keep], d[keep], length[keep]
    if p0.shape[0] == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    u = d / length[:, None]
    lo = np.floor(np.minimum(p0[:, 0], p0[:, 0] + d[:, 0]) - half_width).astype(np.int64)
    hi = np.ceil(np.maximum(p0[:, 0], p0[:, 0] + d[:, 0]) + half_width).astype(np.int64)
    lo, hi = np.clip(lo, 0, cols), np.clip(hi, 0, cols)
    n = np.maximum(hi - lo, 0)
    seg = np.repeat(np.arange(p0.shape[0]), n)
    first = np.repeat(np.cumsum(n) - n, n)
    x = lo[seg] + (np.arange(seg.size) - first)
    cx = x + 0.5
    yc = p0[seg, 1] + (cx - p0[seg, 0]) * d[seg, 1] / d[seg, 0]
    reach = half_width / np.abs(u[seg, 0])
    out_x, out_y = [], []
    spread = int(math.ceil(2 * half_width * math.sqrt(2))) + 2
    base = np.floor(yc - reach - 0.5).astype(np.int64)
    for j in range(spread + 1):
        y = base + j
        ok = (y >= 0) & (y < rows)
        vx = cx - p0[seg, 0]
        vy = (y + 0.5) - p0[seg, 1]
        along = vx * u[seg, 0] + vy * u[seg, 1]
        across = -vx * u[seg, 1] + vy * u[seg, 0]
        ok &= (along >= 0) & (along <= length[seg]) & (np.abs(across) <= half_width)
        out_x.append(x[ok])
        out_y.append(y[ok])
    return np.concatenate(out_y), np.concatenate(out_x)


def rasterise_bands(p0: np.ndarray, p1: np.ndarray, width: float, shape: tuple[int, int]) -> np.ndarray:
    """Boolean grid of the cells whose centres lie within ``width/2`` of segments ``p0 -> p1``
    (image-frame cell coordinates ``(X, Y)``, ``(n, 2)`` each), measured across the segment
    and between its ends."""
    p0, p1 = np.asarray(p0, float).reshape(-1, 2), np.asarray(p1, float).reshape(-1, 2)
    out = np.zeros(shape, dtype=bool)
    d = p1 - p0
    shallow = np.abs(d[:, 0]) >= np.abs(d[:, 1])
    ys, xs = _raster_shallow(p0[shallow], p1[shallow], width / 2, shape)
    out[ys, xs] = True
    # steep segments: the same walk with the axes swapped
    xs, ys = _raster_shallow(p0[~shallow][:, ::-1], p1[~shallow][:, ::-1], width / 2, shape[::-1])
    out[ys, xs] = True
    return out


def rasterise_cuts(start_mm: np.ndarray, end_mm: np.ndarray, layout: Layout, thickness_mm: float) -> np.ndarray:
    """Cuts given in machine mm (``(n, 2)`` XY starts and ends) as scratched halftone cells."""
    start_mm, end_mm = np.asarray(start_mm, float).reshape(-1, 2), np.asarray(end_mm, float).reshape(-1, 2)
    a = np.stack(layout.machine_to_image(start_mm[:, 0], start_mm[:, 1]), axis=1)
    b = np.stack(layout.machine_to_image(end_mm[:, 0], end_mm[:, 1]), axis=1)
    return rasterise_bands(a, b, thickness_mm / layout.cell_mm, (layout.rows, layout.cols))


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks (1.0 when both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union
