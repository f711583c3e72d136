"""Scratch segments -> an ordered engraver toolpath, its checks and its cost (thesis 5.1-5.2).

A :class:`Toolpath` is a list of cuts, each a straight move along the machine's y axis
at ``x`` from ``y_start`` to ``y_end``, always in the blade's cutting direction (the
scalpel "is made to cut in one direction", thesis 5.1.2). Around every cut the tool
travels at the safe height to the cut's start, plunges to the scalpel depth, cuts,
and retracts. The machine files (:mod:`.gcode`, :mod:`.rml`) are written from it.

:func:`check_toolpath` refuses, before anything is written, a path with any point off
the bed or outside the rotated print's bounding box, or deeper than the configured
limit (design.md: "a toolpath outside the machine's bed" stops with a clear message).
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.fabrication.layout import Layout
from glossrig.core.fabrication.machine import Machine
from glossrig.core.fabrication.vectorize import Segments


@dataclass(frozen=True)
class Toolpath:
    """Cuts in machine mm, in machining order; the tool starts and ends at ``home``."""

    x: np.ndarray
    y_start: np.ndarray
    y_end: np.ndarray
    home: tuple[float, float]
    cut_z: float
    safe_z: float

    def __len__(self) -> int:
        return int(self.x.size)

    def reordered(self, order: np.ndarray) -> Toolpath:
        return Toolpath(self.x[order], self.y_start[order], self.y_end[order], self.home, self.cut_z, self.safe_z)

    def travel_legs(self) -> tuple[np.ndarray, np.ndarray]:
        """XY air moves at the safe height: home -> first cut -> ... -> last cut -> home."""
        sx = np.concatenate([[self.home[0]], self.x])
        sy = np.concatenate([[self.home[1]], self.y_end])
        ex = np.concatenate([self.x, [self.home[0]]])
        ey = np.concatenate([self.y_start, [self.home[1]]])
        return ex - sx, ey - sy


def cuts_from_segments(segments: Segments, layout: Layout, machine: Machine) -> Toolpath:
    """Machine-frame cuts of ``segments`` along their centrelines (thesis 5.2, eq. 5.3).

    A segment from column ``x0`` to ``x1`` spans ``X in [x0, x1 + 1]`` on its line's
    centreline. Coordinates are put on the machine's grid: x to the nearest step (the
    layout already places every line on the grid), the two ends of a cut inwards, so
    a cut never reaches beyond its pixels (a pixel's centre is at least half a column,
    about 60 um, inside the ends; at the print's top and bottom edges, where the cut
    stops at the edge, at least 15 um).
    """
    X0 = segments.x0.astype(float)
    X1 = segments.x1.astype(float) + 1.0
    if layout.a > 0:
        # a line's centreline can leave the print through its top or bottom edge half a
        # column before its last pixel's centre; stop the cut at the edge (every pixel
        # centre of the line lies inside the print, so each stays covered)
        g = math.gcd(layout.a, layout.b)
        k = segments.k.astype(float)
        c = k + 0.5 - layout.a / (2.0 * layout.b) - (layout.b - g) / (2.0 * layout.b)   # Y(X) = c + a X / b
        X0 = np.maximum(X0, (0.0 - c) * layout.b / layout.a)
        X1 = np.minimum(X1, (layout.rows - c) * layout.b / layout.a)
    ax, ay = layout.image_to_machine(X0, layout.centreline_y(segments.k, X0))
    bx, by = layout.image_to_machine(X1, layout.centreline_y(segments.k, X1))
    res = machine.resolution_mm
    x = machine.quantise(0.5 * (ax + bx))
    lo, hi = np.minimum(ay, by), np.maximum(ay, by)
    lo = np.ceil(lo / res - 1e-9) * res
    hi = np.floor(hi / res + 1e-9) * res
    if machine.cut_direction > 0:
        start, end = lo, hi
    else:
        start, end = hi, lo
    xmin, ymin, _, _ = layout.bbox_mm()            # home: the print's lower-left bbox corner, on the grid
    home = (float(np.ceil(xmin / res - 1e-9) * res), float(np.ceil(ymin / res - 1e-9) * res))
    return Toolpath(x, start, end, home, -machine.cut_depth_mm, float(machine.quantise(machine.safe_height_mm)))


def naive_order(path: Toolpath, machine: Machine) -> np.ndarray:
    """Line after line, each line's cuts in the cutting direction (the order of thesis fig. 5.7)."""
    return np.lexsort((machine.cut_direction * path.y_start, path.x))


def sweep_order(path: Toolpath, machine: Machine, candidates: int = 4) -> np.ndarray:
    """Cut order that keeps air moves short for a blade that cuts one way only.

    With one cutting direction every line ends far from where the next one starts, and
    the return (at 50 mm/s along y, thesis 5.1.1) dominates the air time. Lines whose x
    lies within one band of ``travel_band_mm`` are therefore cut together in sweeps: in
    the cutting direction, a sweep takes cuts of any line of the band that do not
    overlap, so the blade returns once per sweep instead of once per line.

    The cuts of a band, by start, are partitioned into sweeps greedily: each cut joins
    an open sweep that has ended below its start, else opens a new one. Any greedy of
    this kind opens as many sweeps as the band's largest overlap depth, the fewest
    possible. Among the open sweeps it joins the one with the cheapest air move to the
    cut (in travel time, checked over the ``candidates`` sweeps that end closest below
    the cut and the sweep holding the previous cut of its own line), so a sweep hops to
    another line only where that is faster than carrying on along its own. The sweeps
    of a band are then visited nearest-first from where the blade is, and the bands in
    x order. Band width 0 gives :func:`naive_order`.
    """
    n = len(path)
    if n == 0:
        return np.zeros(0, dtype=np.int64)
    if machine.travel_band_mm <= 0:
        return naive_order(path, machine)
    d = machine.cut_direction
    vx, vy = machine.max_speed_mm_s[:2]
    start, end = d * path.y_start, d * path.y_end             # cut coordinate, increasing along a cut
    line = np.rint(path.x / machine.resolution_mm).astype(np.int64)
    band = np.floor((path.x - path.x.min()) / machine.travel_band_mm + 1e-9).astype(np.int64)
    by_band = np.lexsort((path.x, start, band))
    eps = 0.5 * machine.resolution_mm
    bounds = np.flatnonzero(np.diff(band[by_band])) + 1
    xs_all = path.x.tolist()
    order: list[int] = []
    here = (path.home[0], d * path.home[1])
    for group in np.split(by_band, bounds):
        sweeps: list[list[int]] = []
        s_end: list[float] = []                              # per sweep: end of its last cut
        s_x: list[float] = []                                # per sweep: x of its last cut
        ends: list[float] = []                               # sorted ends of all sweeps
        owner: list[int] = []                                # sweep id of each entry of ``ends``
        of_line: dict[int, int] = {}
        for i, s, e, ln in zip(group.tolist(), start[group].tolist(), end[group].tolist(),
                               line[group].tolist()):
            x = xs_all[i]
            top = bisect.bisect_right(ends, s - eps)
            cand = owner[max(0, top - candidates):top]
            own = of_line.get(ln)
            if own is not None and s_end[own] <= s - eps and own not in cand:
                cand.append(own)
            best, best_cost = -1, math.inf
            for sid in cand:
                cost = max(abs(x - s_x[sid]) / vx, (s - s_end[sid]) / vy)
                if cost < best_cost or (cost == best_cost and s_end[sid] > s_end[best]):
                    best, best_cost = sid, cost
            if best >= 0:
                k = bisect.bisect_left(ends, s_end[best])
                while owner[k] != best:
                    k += 1
                del ends[k], owner[k]
                sweeps[best].append(i)
            else:
                best = len(sweeps)
                sweeps.append([i])
                s_end.append(e)
                s_x.append(x)
            s_end[best], s_x[best] = e, x
            of_line[ln] = best
            k = bisect.bisect_right(ends, e)
            ends.insert(k, e)
            owner.insert(k, best)
        first = np.array([sw[0] for sw in sweeps])
        last = np.array([sw[-1] for sw in sweeps])
        todo = np.ones(len(sweeps), dtype=bool)
        for _ in range(len(sweeps)):
            cost = machine.travel_time_s(path.x[first] - here[0], start[first] - here[1])
            cost[~todo] = np.inf
            j = int(np.argmin(cost))
            todo[j] = False
            order.extend(sweeps[j])
            here = (path.x[last[j]], end[last[j]])
    return np.asarray(order, dtype=np.int64)


def best_order(path: Toolpath, machine: Machine) -> tuple[np.ndarray, str]:
    """The shorter (in air time) of :func:`sweep_order` and :func:`naive_order`, and its name."""
    naive = naive_order(path, machine)
    sweep = sweep_order(path, machine)
    t_naive = machine.travel_time_s(*path.reordered(naive).travel_legs()).sum()
    t_sweep = machine.travel_time_s(*path.reordered(sweep).travel_legs()).sum()
    if t_sweep <= t_naive:
        return sweep, f"sweeps in bands of {machine.travel_band_mm:g} mm"
    return naive, "line by line"


@dataclass(frozen=True)
class Estimate:
    """Path length and machining time; acceleration and controller overheads are ignored."""

    segment_count: int
    cut_length_mm: float
    travel_length_mm: float
    z_length_mm: float
    cut_time_s: float
    travel_time_s: float
    z_time_s: float

    @property
    def path_length_mm(self) -> float:
        return self.cut_length_mm + self.travel_length_mm + self.z_length_mm

    @property
    def time_s(self) -> float:
        return self.cut_time_s + self.travel_time_s + self.z_time_s

    def to_json(self) -> dict:
        return {"segment_count": self.segment_count, "path_length_mm": self.path_length_mm,
                "cut_length_mm": self.cut_length_mm, "travel_length_mm": self.travel_length_mm,
                "z_length_mm": self.z_length_mm, "estimated_time_s": self.time_s,
                "time_breakdown_s": {"cut": self.cut_time_s, "travel": self.travel_time_s,
                                     "plunge_retract": self.z_time_s},
                "note": "straight moves at the programmed feeds (travel at the per-axis limits of "
                        "thesis 5.1.1); acceleration is ignored"}


def estimate(path: Toolpath, machine: Machine, retract_speed_mm_s: float) -> Estimate:
    """Length and time of ``path``: cuts at the cutting feed, air moves at the axis limits
    (the slower axis decides), plunges at the plunge feed, retracts at ``retract_speed_mm_s``."""
    cut = np.abs(path.y_end - path.y_start)
    dx, dy = path.travel_legs()
    travel = np.hypot(dx, dy)
    hop = path.safe_z - path.cut_z
    n = len(path)
    return Estimate(
        segment_count=n, cut_length_mm=float(cut.sum()), travel_length_mm=float(travel.sum()),
        z_length_mm=2 * n * hop, cut_time_s=float(cut.sum() / machine.cut_feed_mm_s),
        travel_time_s=float(machine.travel_time_s(dx, dy).sum()),
        z_time_s=n * (hop / machine.plunge_feed_mm_s + hop / retract_speed_mm_s))


def check_toolpath(path: Toolpath, machine: Machine, bbox: tuple[float, float, float, float]) -> None:
    """Refuse a path that leaves the bed or the print's bounding box, or cuts too deep."""
    if -path.cut_z > machine.max_depth_mm + 1e-9:
        raise InputError(f"cut depth {-path.cut_z:.3f} mm exceeds the configured limit "
                         f"{machine.max_depth_mm:.3f} mm; nothing written", path=machine.path)
    if path.safe_z <= 0:
        raise InputError(f"safe height {path.safe_z} mm is not above the sheet; nothing written", path=machine.path)
    if np.any(machine.cut_direction * (path.y_end - path.y_start) <= 0):
        raise InputError("internal error: a cut does not run in the blade's cutting direction; nothing written")
    xs = np.concatenate([path.x, path.x, [path.home[0]]])
    ys = np.concatenate([path.y_start, path.y_end, [path.home[1]]])
    W, H = machine.bed_mm
    tol = 1e-6
    if (xs.min() < -tol or ys.min() < -tol or xs.max() > W + tol or ys.max() > H + tol):
        raise InputError(
            f"toolpath spans x {xs.min():.2f}..{xs.max():.2f} mm, y {ys.min():.2f}..{ys.max():.2f} mm "
            f"(rotated print {bbox[2] - bbox[0]:.2f} x {bbox[3] - bbox[1]:.2f} mm at "
            f"({bbox[0]:.2f}, {bbox[1]:.2f})), outside the bed 0..{W:g} x 0..{H:g} mm; nothing written",
            path=machine.path)
    if (xs.min() < bbox[0] - tol or xs.max() > bbox[2] + tol
            or ys.min() < bbox[1] - tol or ys.max() > bbox[3] + tol):
        raise InputError("internal error: the toolpath leaves the rotated print's bounding box; nothing written")


def check_print_fits(layout: Layout, machine: Machine) -> None:
    """Refuse, before any work, a print whose rotated bounding box leaves the bed."""
    x0, y0, x1, y1 = layout.bbox_mm()
    W, H = machine.bed_mm
    if x0 < -1e-6 or y0 < -1e-6 or x1 > W + 1e-6 or y1 > H + 1e-6:
        w, h = layout.size_mm
        raise InputError(
            f"a {w:.1f} x {h:.1f} mm print, rotated by {math.degrees(layout.theta_rad):.1f} deg onto the "
            f"machine's y axis, covers x {x0:.2f}..{x1:.2f}, y {y0:.2f}..{y1:.2f} mm: outside the bed "
            f"0..{W:g} x 0..{H:g} mm; nothing written", path=machine.path)
