"""Juxtaposed halftoning and vectorisation (thesis 5.2; Babaei & Hersch 2013)."""
from __future__ import annotations

import math

import numpy as np
import pytest

from glossrig.core.errors import InputError
from glossrig.core.fabrication.halftone import (coverage_levels, grid_shape, halftone, line_index,
                                                line_offsets, lookup_screen_image, screen_library,
                                                screen_position)
from glossrig.core.fabrication.layout import cell_size_mm
from glossrig.core.fabrication.machine import ScreenParams
from glossrig.core.fabrication.vectorize import extract_segments, line_pattern

THESIS = ScreenParams(4, 7, 6)
SCREENS = [THESIS, ScreenParams(2, 5, 3), ScreenParams(0, 4, 2), ScreenParams(3, 3, 2), ScreenParams(6, 9, 4)]


def test_thesis_screen_has_42_pixels_and_43_levels():
    assert THESIS.pixels == 42 and THESIS.levels == 43
    lib = screen_library(THESIS)
    assert lib.shape == (43, 42)
    assert np.array_equal(lib.sum(axis=1), np.arange(43))
    assert np.all(lib[:-1] <= lib[1:])               # each level adds pixels, never removes


@pytest.mark.parametrize("screen", SCREENS, ids=str)
def test_screen_elements_are_parallelograms_of_bT_distinct_positions(screen):
    rows, cols = 5 * screen.T + 3, 4 * screen.b + 2
    k = line_index((rows, cols), screen)
    x = np.arange(cols)[None, :].repeat(rows, 0)
    element = np.floor_divide(x, screen.b) * 10_000 + np.floor_divide(k, screen.T)
    pos = screen_position((rows, cols), screen)
    for e in np.unique(element):
        sel = element == e
        if sel.sum() == screen.pixels:                # elements entirely inside the image
            assert sorted(pos[sel].tolist()) == list(range(screen.pixels))
    # the element next to the right is the same parallelogram shifted by (b, a)
    ys, xs = np.nonzero(element == element[screen.T, 0])
    assert set(zip(ys + screen.a, xs + screen.b)) <= set(zip(*np.nonzero(element == element[screen.T + screen.a, screen.b])))


@pytest.mark.parametrize("screen", SCREENS, ids=str)
def test_line_pattern_read_from_halftone_of_one_over_T_matches_the_discrete_line(screen):
    # thesis eq. 5.1: the grey 1/T fills exactly one discrete line per screen, whose
    # pattern the vectoriser must follow
    pattern = line_pattern(screen)
    assert np.array_equal(pattern, line_offsets(screen.b, screen))
    if screen == THESIS:
        assert pattern.tolist() == [0, 0, 1, 1, 2, 2, 3]


def test_level_b_is_one_full_discrete_line_per_screen():
    img = lookup_screen_image(7, THESIS)
    assert (img == 1).sum() == 7
    filled = np.argwhere(img == 1)
    assert filled[:, 1].tolist() == list(range(7))      # one pixel per column...
    assert filled[:, 0].tolist() == [0, 0, 1, 1, 2, 2, 3]  # ...on the line of slope 4/7
    bitmap = halftone(np.full((60, 70), 7 / 42), THESIS)
    k = line_index(bitmap.shape, THESIS)
    assert np.array_equal(bitmap, np.mod(k, 6) == 0)


def test_nearest_level():
    n = np.arange(43)
    assert np.array_equal(coverage_levels(n / 42 + 0.49 / 42, THESIS), n)
    assert np.array_equal(coverage_levels(np.clip(n / 42 - 0.49 / 42, 0, 1), THESIS), n)
    assert coverage_levels(np.array([-0.3, 1.7]), THESIS).tolist() == [0, 42]
    with pytest.raises(InputError):
        coverage_levels(np.array([np.nan]), THESIS)


@pytest.mark.parametrize("g", [0.0, 1 / 42, 0.1234, 0.25, 0.5, 0.61, 0.77, 41.4 / 42, 1.0])
def test_constant_grey_halftones_to_exactly_the_nearest_level(g):
    cell = cell_size_mm(0.09, THESIS)
    for width in (3.0, 11.3):
        rows, cols = grid_shape((200, 300), width, cell, THESIS)
        bitmap = halftone(np.full((rows, cols), g), THESIS)
        k = round(g * 42)
        assert bitmap.sum() * 42 == k * rows * cols       # exactly k/42, no rounding
        assert bitmap.mean() == pytest.approx(k / 42, abs=0)


def test_juxtaposition_each_pixel_takes_its_own_levels_lookup_screen():
    """A pixel's halftone value depends on its own level and position only (thesis fig. 5.3)."""
    rng = np.random.default_rng(3)
    rows, cols = 48, 63
    a, b = rng.uniform(size=2)
    mask = rng.uniform(size=(rows, cols)) < 0.5
    mixed = halftone(np.where(mask, a, b), THESIS)
    expected = np.where(mask, halftone(np.full((rows, cols), a), THESIS), halftone(np.full((rows, cols), b), THESIS))
    assert np.array_equal(mixed, expected)


def test_grid_shape_keeps_whole_screens_and_the_aspect_ratio():
    cell = cell_size_mm(0.09, THESIS)
    rows, cols = grid_shape((600, 512), 100.0, cell, THESIS)
    assert cols % 7 == 0 and rows % 6 == 0
    assert abs(cols * cell - 100.0) <= 3.5 * cell
    assert rows / cols == pytest.approx(600 / 512, abs=6 / cols)


@pytest.mark.parametrize("screen", SCREENS, ids=str)
def test_segments_round_trip_and_are_maximal_runs(screen):
    rng = np.random.default_rng(7)
    for bitmap in (rng.uniform(size=(41, 57)) < 0.4,
                   halftone(rng.uniform(size=(40, 56)), screen),
                   np.ones((12, 20), bool), np.zeros((5, 9), bool)):
        seg = extract_segments(bitmap, screen)
        assert np.array_equal(seg.rasterise(bitmap.shape, screen), bitmap)
        assert seg.pixel_count == bitmap.sum()
        assert np.all(seg.x1 >= seg.x0)
        same_line = seg.k[1:] == seg.k[:-1]
        assert not np.any(same_line & (seg.x0[1:] == seg.x1[:-1] + 1))   # runs are not split


def test_full_lines_of_a_constant_screen_are_single_segments():
    rows, cols = 60, 70
    bitmap = halftone(np.full((rows, cols), 14 / 42), THESIS)       # two full lines per screen
    seg = extract_segments(bitmap, THESIS)
    k = line_index((rows, cols), THESIS)
    lines = np.unique(k[np.mod(k, 6) < 2])
    assert len(seg) == lines.size and np.array_equal(np.sort(seg.k), lines)
    # a line's single segment spans every column in which it is inside the image
    for kk, x0, x1 in zip(seg.k, seg.x0, seg.x1):
        cols_in = np.flatnonzero(np.any(k == kk, axis=0))
        assert (x0, x1) == (cols_in.min(), cols_in.max())


def test_rejects_bad_input():
    with pytest.raises(InputError):
        halftone(np.zeros((0, 4)), THESIS)
    with pytest.raises(InputError):
        halftone(np.zeros(5), THESIS)
    with pytest.raises(InputError):
        line_pattern(ScreenParams(1, 3, 1))
    with pytest.raises(InputError):
        lookup_screen_image(43, THESIS)
    assert math.isclose(cell_size_mm(0.09, THESIS), 0.09 * math.sqrt(65) / 7)
