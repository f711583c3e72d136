"""Vectorisation: the halftone bitmap -> scratch segments along the discrete lines (thesis 5.2).

Thesis 5.2 ("Vectorization", figs. 5.5-5.7): the pattern of one discrete line is read
from the halftone of the grey ``1/T`` (eq. 5.1), which fills exactly one line per
screen; the line is extended over the image width and shifted down to every
y-coordinate; masking the halftone with each line leaves a 1-D array per line, and its
runs of filled pixels are the segments to scratch.

:func:`line_pattern` does the pattern extraction exactly as the thesis describes (and a
test checks it against the closed form ``floor(a x / b)`` of
:mod:`~glossrig.core.fabrication.halftone`). :func:`extract_segments` computes the same
per-line runs without building one mask per line: it labels every filled pixel with
its line ``k = y - floor(a x / b)`` and splits each line's pixels into runs of
consecutive columns, which is the masked 1-D array of fig. 5.7, run by run.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.fabrication.halftone import halftone, line_offsets
from glossrig.core.fabrication.machine import ScreenParams


@dataclass(frozen=True)
class Segments:
    """Scratch segments on the halftone grid: line ``k`` from column ``x0`` to ``x1`` (inclusive)."""

    k: np.ndarray
    x0: np.ndarray
    x1: np.ndarray

    def __len__(self) -> int:
        return int(self.k.size)

    @property
    def pixel_count(self) -> int:
        return int(np.sum(self.x1 - self.x0 + 1))

    def rasterise(self, shape: tuple[int, int], screen: ScreenParams) -> np.ndarray:
        """The bitmap these segments cover on the discrete lines (inverse of :func:`extract_segments`)."""
        out = np.zeros(shape, dtype=bool)
        n = self.x1 - self.x0 + 1
        seg = np.repeat(np.arange(len(self)), n)
        start = np.repeat(np.cumsum(n) - n, n)
        x = self.x0[seg] + (np.arange(seg.size) - start)
        y = self.k[seg] + line_offsets(shape[1], screen)[x]
        out[y, x] = True
        return out


def line_pattern(screen: ScreenParams) -> np.ndarray:
    """Pattern of one discrete line (thesis 5.2, fig. 5.5, eq. 5.1).

    Halftones the constant grey ``b / (b T) = 1/T``, which fills exactly one discrete
    line per screen, then starts at the upper-left pixel of a screen and follows the
    filled pixels column by column, recording their heights. Returns ``b`` relative
    y-coordinates. Needs ``T >= 2`` (for ``T = 1`` the grey 1/T fills everything and
    there is no line to follow).
    """
    if screen.T < 2:
        raise InputError("the line pattern of eq. 5.1 can only be read from a screen with T >= 2")
    rows, cols = screen.T * (screen.a // screen.T + 2), screen.b
    bitmap = halftone(np.full((rows, cols), 1.0 / screen.T), screen)
    if not bitmap[0, 0]:
        raise InputError("halftone of 1/T does not start a line at the screen's upper-left pixel")
    pattern = [0]
    for x in range(1, cols):
        below = np.flatnonzero(bitmap[pattern[-1]:, x])   # lines run down-right, one pixel per column
        if below.size == 0:
            raise InputError(f"discrete line of slope {screen.a}/{screen.b} breaks at column {x}")
        pattern.append(pattern[-1] + int(below[0]))
    return np.asarray(pattern, dtype=np.int64)


def extract_segments(bitmap: np.ndarray, screen: ScreenParams) -> Segments:
    """Runs of filled pixels along every discrete line of ``bitmap`` (thesis 5.2, fig. 5.7).

    Returned in line order, each line's runs left to right.
    """
    bitmap = np.asarray(bitmap, dtype=bool)
    if bitmap.ndim != 2:
        raise InputError(f"halftone must be 2-D, got shape {bitmap.shape}")
    ys, xs = np.nonzero(bitmap)
    if ys.size == 0:
        empty = np.zeros(0, dtype=np.int64)
        return Segments(empty, empty.copy(), empty.copy())
    k = ys.astype(np.int64) - line_offsets(bitmap.shape[1], screen)[xs]
    order = np.lexsort((xs, k))
    k, xs = k[order], xs[order].astype(np.int64)
    new = np.ones(k.size, dtype=bool)
    new[1:] = (k[1:] != k[:-1]) | (xs[1:] != xs[:-1] + 1)
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], k.size) - 1
    return Segments(k[starts], xs[starts], xs[ends])
