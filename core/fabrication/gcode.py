"""G-code (RS-274, millimetres, absolute) for a scratch :class:`~.toolpath.Toolpath`, and a reader.

Per cut: ``G0`` to the cut's start at the safe height, ``G1 Z`` down to the scalpel depth
at the plunge feed, ``G1 Y`` along the cut at the cutting feed, ``G0 Z`` back to the safe
height. Feeds are ``F`` in mm/min (``G94``); the cutting feed is checked against the
y-axis limit and the plunge feed against the z-axis limit (thesis 5.1.1) when the
machine description is loaded. The scalpel is not a spindle tool: ``M5`` keeps the
spindle off. Coordinates carry two decimals: the machine's 10 um step (thesis 5.1.1).

:func:`read_gcode` parses the subset written here (``G0``/``G1`` with ``X Y Z F``,
modal), so tests and validation can check a file as a machine would run it.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.fabrication.machine import Machine
from glossrig.core.fabrication.toolpath import Toolpath


@dataclass(frozen=True)
class Moves:
    """Straight moves read back from a machine file: ``(n, 3)`` starts and ends in mm,
    whether each is a rapid/air move, and its feed in mm/s (``nan`` for rapids)."""

    start: np.ndarray
    end: np.ndarray
    rapid: np.ndarray
    feed_mm_s: np.ndarray

    def cutting(self, cut_z: float, tol: float = 1e-6) -> np.ndarray:
        """Mask of XY moves made with the tool at ``cut_z``."""
        xy = np.any(np.abs(self.end[:, :2] - self.start[:, :2]) > tol, axis=1)
        return xy & (np.abs(self.start[:, 2] - cut_z) < tol) & (np.abs(self.end[:, 2] - cut_z) < tol)


def _f(v: float) -> str:
    s = f"{v:.2f}"
    return "0.00" if s == "-0.00" else s


def _z(v: float) -> str:
    s = f"{v:.3f}"
    return "0.000" if s == "-0.000" else s


def write_gcode(path: Toolpath, machine: Machine, header: list[str] | None = None) -> str:
    """The G-code program of ``path`` (module docstring)."""
    plunge = machine.plunge_feed_mm_s * 60.0
    cut = machine.cut_feed_mm_s * 60.0
    safe, depth = _z(path.safe_z), _z(path.cut_z)
    lines = [f"; {h}" for h in (header or [])]
    lines += [f"; {machine.name}; tool: {machine.tool}; {len(path)} cuts along "
              f"{'+' if machine.cut_direction > 0 else '-'}y at Z{depth}, travel at Z{safe}",
              "G21 ; millimetres", "G90 ; absolute coordinates", "G94 ; feed in mm/min", "G17",
              "M5 ; no spindle: the scalpel cuts by dragging", f"G0 Z{safe}"]
    xs = [_f(v) for v in path.x.tolist()]
    y0 = [_f(v) for v in path.y_start.tolist()]
    y1 = [_f(v) for v in path.y_end.tolist()]
    body = [f"G0 X{x} Y{a}\nG1 Z{depth} F{plunge:.0f}\nG1 Y{b} F{cut:.0f}\nG0 Z{safe}"
            for x, a, b in zip(xs, y0, y1)]
    lines += body
    lines += [f"G0 X{_f(path.home[0])} Y{_f(path.home[1])}", "M2", ""]
    return "\n".join(lines)


_WORD = re.compile(r"([A-Za-z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")


def read_gcode(text: str, source: str = "G-code") -> Moves:
    """Straight moves of a G-code program (``G0``/``G1``, ``G90``, ``G21``; modal words).

    An axis not yet programmed has an unknown (``nan``) start. Arcs, relative and inch
    mode are refused.
    """
    pos = [np.nan, np.nan, np.nan]
    mode, feed = None, np.nan
    start, end, rapid, feeds = [], [], [], []
    for no, raw in enumerate(text.splitlines(), 1):
        line = re.sub(r"\(.*?\)", "", raw.split(";", 1)[0]).strip()
        if not line:
            continue
        words = _WORD.findall(line)
        target = list(pos)
        moved = False
        for letter, value in words:
            letter = letter.upper()
            v = float(value)
            if letter == "G":
                g = int(round(v))
                if g in (0, 1):
                    mode = g
                elif g in (2, 3, 20, 91):
                    raise InputError(f"line {no}: G{g} is not supported by this reader", path=source)
            elif letter in "XYZ":
                target["XYZ".index(letter)] = v
                moved = True
            elif letter == "F":
                feed = v / 60.0
        if moved:
            if mode is None:
                raise InputError(f"line {no}: coordinates before any G0/G1", path=source)
            start.append(list(pos))
            end.append(list(target))
            rapid.append(mode == 0)
            feeds.append(np.nan if mode == 0 else feed)
            pos = target
    return Moves(np.asarray(start, float).reshape(-1, 3), np.asarray(end, float).reshape(-1, 3),
                 np.asarray(rapid, bool), np.asarray(feeds, float))
