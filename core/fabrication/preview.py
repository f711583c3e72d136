"""Previews of a scratch toolpath over its input: ``preview.svg`` and ``preview.png`` (design.md,
"Toolpaths: machine files plus an SVG/PNG preview").

- SVG, in machine millimetres: the bed's edge, the rotated print's bounding box, the
  target coverage image placed exactly where the layout puts it (thesis eq. 5.3), every
  cut as a line one scratch thickness wide, and the air moves in machining order.
- PNG, four panels: the target coverage; the cuts drawn as scratches of their physical
  width back in the image frame (white = scratched: it should look like the target);
  a zoom on the centre with every cut as a red line over the target; the print on
  the machine bed (machine frame).
"""
from __future__ import annotations

import base64
import io
import math

import cv2
import numpy as np
from PIL import Image

from glossrig.core.fabrication.layout import Layout
from glossrig.core.fabrication.machine import Machine
from glossrig.core.fabrication.toolpath import Toolpath


def _png_bytes(grey: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(np.clip(np.rint(grey * 255), 0, 255).astype(np.uint8), mode="L").save(buf, format="PNG")
    return buf.getvalue()


def _n(v: float) -> str:
    return f"{v:.3f}".rstrip("0").rstrip(".")


def svg_preview(coverage: np.ndarray, layout: Layout, path: Toolpath, machine: Machine, title: str) -> str:
    """SVG of the toolpath over the target coverage, in machine mm (module docstring)."""
    xmin, ymin, xmax, ymax = layout.bbox_mm()
    margin = 0.05 * max(xmax - xmin, ymax - ymin) + 1.0
    vx0, vy0 = min(xmin, path.home[0]) - margin, min(ymin, path.home[1]) - margin
    vx1, vy1 = max(xmax, path.home[0]) + margin, ymax + margin
    W, H = vx1 - vx0, vy1 - vy0
    th = layout.theta_rad
    s = layout.cell_mm
    c, sn = math.cos(th), math.sin(th)
    # image frame (X right, Y down, cells) -> machine mm: s R diag(1, -1) (X, Y) + s R (0, rows) + offset
    mat = (s * c, s * sn, s * sn, -s * c,
           -s * sn * layout.rows + layout.offset_mm[0], s * c * layout.rows + layout.offset_mm[1])
    img = base64.b64encode(_png_bytes(coverage)).decode("ascii")
    cuts = " ".join(f"M{_n(x)} {_n(a)}V{_n(b)}" for x, a, b in
                    zip(path.x.tolist(), path.y_start.tolist(), path.y_end.tolist()))
    sx = np.concatenate([[path.home[0]], path.x]).tolist()
    sy = np.concatenate([[path.home[1]], path.y_end]).tolist()
    ex = np.concatenate([path.x, [path.home[0]]]).tolist()
    ey = np.concatenate([path.y_start, [path.home[1]]]).tolist()
    travel = " ".join(f"M{_n(a)} {_n(b)}L{_n(c_)} {_n(d)}" for a, b, c_, d in zip(sx, sy, ex, ey))
    font = max(W, H) / 60
    bw, bh = machine.bed_mm
    return "\n".join([
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" xmlns:xlink="http://www.w3.org/1999/xlink" '
        f'width="{_n(W)}mm" height="{_n(H + 3 * font)}mm" viewBox="{_n(vx0)} {_n(-vy1 - 3 * font)} {_n(W)} {_n(H + 3 * font)}">',
        f'<title>{title}</title>',
        f'<rect x="{_n(vx0)}" y="{_n(-vy1 - 3 * font)}" width="{_n(W)}" height="{_n(H + 3 * font)}" fill="white"/>',
        f'<text x="{_n(vx0 + font)}" y="{_n(-vy1 - 1.5 * font)}" font-size="{_n(font)}" font-family="sans-serif">'
        f'{title}: {len(path)} cuts; machine frame (mm), y up; red: cuts ({machine.cut_direction:+d}y), '
        f'blue: air moves</text>',
        '<g transform="scale(1,-1)">',
        f'<rect x="0" y="0" width="{_n(bw)}" height="{_n(bh)}" fill="none" stroke="black" stroke-width="{_n(font / 8)}"/>',
        f'<image width="{layout.cols}" height="{layout.rows}" preserveAspectRatio="none" '
        f'style="image-rendering:pixelated" transform="matrix({" ".join(f"{v:.9g}" for v in mat)})" '
        f'xlink:href="data:image/png;base64,{img}" href="data:image/png;base64,{img}" opacity="0.6"/>',
        f'<rect x="{_n(xmin)}" y="{_n(ymin)}" width="{_n(xmax - xmin)}" height="{_n(ymax - ymin)}" fill="none" '
        f'stroke="grey" stroke-dasharray="{_n(font / 2)}" stroke-width="{_n(font / 10)}"/>',
        f'<path d="{cuts}" fill="none" stroke="#d0021b" stroke-opacity="0.8" '
        f'stroke-width="{_n(machine.scratch_thickness_mm)}" stroke-linecap="butt"/>',
        f'<path d="{travel}" fill="none" stroke="#1f5fbf" stroke-opacity="0.35" stroke-width="{_n(font / 40)}"/>',
        '</g>', '</svg>', ""])


def _panel(img: np.ndarray, title: str) -> np.ndarray:
    """``img`` under a white strip holding ``title``."""
    strip = np.full((28, img.shape[1], 3), 255, np.uint8)
    cv2.putText(strip, title, (6, 19), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    return np.concatenate([strip, img], axis=0)


def _draw_cuts(shape_px: tuple[int, int], p0: np.ndarray, p1: np.ndarray, width_px: float,
               supersample: int = 4) -> np.ndarray:
    """Cuts as bands ``width_px`` wide on a ``shape_px`` canvas, area-averaged from a
    ``supersample``-times finer drawing, so that grey = scratched fraction of a pixel."""
    h, w = shape_px
    canvas = np.zeros((h * supersample, w * supersample), np.uint8)
    if p0.shape[0]:
        shift = 4
        pts = np.stack([p0, p1], 1) * supersample * (1 << shift)
        thick = max(1, int(round(width_px * supersample)))
        cv2.polylines(canvas, list(np.rint(pts).astype(np.int32)), False, 255, thick, cv2.LINE_8, shift)
    return cv2.resize(canvas, (w, h), interpolation=cv2.INTER_AREA)


def png_preview(coverage: np.ndarray, layout: Layout, path: Toolpath, machine: Machine,
                height_px: int = 640) -> np.ndarray:
    """Four-panel RGB preview, ``height_px`` tall: the target coverage; the cuts of the
    toolpath drawn as scratches of their physical width in the image frame (white =
    scratched, so it should look like the target); a zoom of the central region with
    every cut as a red line over the target; the print on the machine bed."""
    rows, cols = coverage.shape
    scale = height_px / rows
    w = max(1, int(round(cols * scale)))
    grey8 = (np.clip(coverage, 0, 1) * 255).astype(np.uint8)
    grey = cv2.resize(grey8, (w, height_px), interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_NEAREST)
    target = cv2.cvtColor(grey, cv2.COLOR_GRAY2RGB)

    ax, ay = layout.machine_to_image(path.x, path.y_start)
    bx, by = layout.machine_to_image(path.x, path.y_end)
    p0, p1 = np.stack([ax, ay], 1), np.stack([bx, by], 1)
    band = machine.scratch_thickness_mm / layout.cell_mm           # scratch width in cells
    scratched = cv2.cvtColor(_draw_cuts((height_px, w), p0 * scale, p1 * scale, band * scale), cv2.COLOR_GRAY2RGB)

    # zoom: a window of about 24 x 24 cells around the centre, >= 20 px per cell
    zc = min(24, rows, cols)
    zr0, zc0 = (rows - zc) // 2, (cols - zc) // 2
    zs = max(20, height_px // zc)
    zoom_px = zc * zs
    zoom = cv2.cvtColor(cv2.resize(grey8[zr0:zr0 + zc, zc0:zc0 + zc], (zoom_px, zoom_px),
                                   interpolation=cv2.INTER_NEAREST), cv2.COLOR_GRAY2RGB)
    zoom = (zoom.astype(np.float32) * 0.7 + 40).astype(np.uint8)
    off = np.array([zc0, zr0], float)
    inside = ((np.minimum(p0[:, 0], p1[:, 0]) < zc0 + zc) & (np.maximum(p0[:, 0], p1[:, 0]) > zc0)
              & (np.minimum(p0[:, 1], p1[:, 1]) < zr0 + zc) & (np.maximum(p0[:, 1], p1[:, 1]) > zr0))
    if np.any(inside):
        shift = 4
        pts = np.stack([p0[inside] - off, p1[inside] - off], 1) * zs * (1 << shift)
        cv2.polylines(zoom, list(np.rint(pts).astype(np.int32)), False, (220, 20, 30),
                      max(1, int(round(0.4 * band * zs))), cv2.LINE_AA, shift)
    zoom = cv2.resize(zoom, (height_px, height_px), interpolation=cv2.INTER_AREA)
    r0, c0 = int(round(zr0 * scale)), int(round(zc0 * scale))
    r1, c1 = int(round((zr0 + zc) * scale)), int(round((zc0 + zc) * scale))
    cv2.rectangle(scratched, (c0, r0), (max(c0 + 1, c1 - 1), max(r0 + 1, r1 - 1)), (220, 20, 30), 1)

    # the print on the bed, machine frame (y up)
    bw, bh = machine.bed_mm
    ms = (height_px - 40) / bh
    bed = np.full((height_px, max(1, int(round(bw * ms)) + 40), 3), 255, np.uint8)

    def to_px(mx, my):
        return np.stack([20 + np.asarray(mx) * ms, height_px - 20 - np.asarray(my) * ms], -1)

    cv2.rectangle(bed, tuple(np.rint(to_px(0, bh)).astype(int)), tuple(np.rint(to_px(bw, 0)).astype(int)),
                  (235, 235, 235), -1)
    cv2.rectangle(bed, tuple(np.rint(to_px(0, bh)).astype(int)), tuple(np.rint(to_px(bw, 0)).astype(int)),
                  (0, 0, 0), 1)
    th = layout.theta_rad
    c, sn = math.cos(th), math.sin(th)
    A = np.array([[c, sn, -sn * layout.rows], [sn, -c, c * layout.rows]]) * layout.cell_mm
    A[:, 2] += layout.offset_mm
    to = np.array([[ms, 0, 20], [0, -ms, height_px - 20]])
    M = to[:, :2] @ A
    M[:, 2] = to[:, :2] @ A[:, 2] + to[:, 2]
    size = (bed.shape[1], bed.shape[0])
    warped = cv2.warpAffine(grey8, M, size, flags=cv2.INTER_AREA, borderValue=0)
    mask = cv2.warpAffine(np.full(coverage.shape, 255, np.uint8), M, size, flags=cv2.INTER_NEAREST) > 0
    bed[mask] = np.stack([warped] * 3, -1)[mask]
    corners = np.rint(to_px(*layout.corners_mm().T)).astype(np.int32)
    cv2.polylines(bed, [corners], True, (220, 20, 30), 1, cv2.LINE_AA)
    x0, y0, x1, y1 = layout.bbox_mm()
    cv2.rectangle(bed, tuple(np.rint(to_px(x0, y1)).astype(int)), tuple(np.rint(to_px(x1, y0)).astype(int)),
                  (120, 120, 120), 1)

    gap = np.full((height_px + 28, 8, 3), 255, np.uint8)
    return np.concatenate([
        _panel(target, "target coverage (white = scratch)"), gap,
        _panel(scratched, f"{len(path)} cuts as scratches"), gap,
        _panel(zoom, f"zoom: cuts over target, {zc} x {zc} cells"), gap,
        _panel(bed, f"bed {bw:g} x {bh:g} mm, y up; print bbox {x1 - x0:.1f} x {y1 - y0:.1f} mm")], axis=1)
