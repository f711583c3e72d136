"""The engraver and its scalpel, as data (``scenes/engraver_roland.toml``).

Figures come from thesis 5.1 (resolution 10 um, 100 mm/s in x-z, 50 mm/s in y, scalpel
depth 20 um, scratch thickness 90 um) and table 5.4 (halftone screen a/b = 4/7, T = 6);
the bed size, feeds and safe height are documented defaults (the thesis does not state
them). :func:`load_machine` checks units, ranges and the machine's limits and names the
file and key in every error.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.resources import resolve_input
from glossrig.core.rig import SCENES_DIR
from glossrig.core.toml_input import read_toml

DEFAULT_MACHINE_FILE = SCENES_DIR / "engraver_roland.toml"


@dataclass(frozen=True)
class ScreenParams:
    """Juxtaposed-halftoning screen (thesis 5.2, table 5.4; Babaei & Hersch 2013).

    Discrete lines of slope ``a/b`` stacked ``T`` deep: a screen element holds
    ``b * T`` pixels and so ``b * T + 1`` levels.
    """

    a: int
    b: int
    T: int

    @property
    def pixels(self) -> int:
        return self.b * self.T

    @property
    def levels(self) -> int:
        return self.b * self.T + 1


@dataclass(frozen=True)
class Machine:
    """A 3-axis engraver with a one-way cutting blade (thesis 5.1)."""

    path: str
    name: str
    bed_mm: tuple[float, float]
    resolution_mm: float
    max_speed_mm_s: tuple[float, float, float]     # x, y, z
    rml_units_per_mm: int
    tool: str
    cut_depth_mm: float
    max_depth_mm: float
    scratch_thickness_mm: float
    cut_direction: int                              # +1: cuts towards +y, -1: towards -y
    safe_height_mm: float
    cut_feed_mm_s: float
    plunge_feed_mm_s: float
    print_origin_mm: tuple[float, float]
    travel_band_mm: float
    screen: ScreenParams

    def quantise(self, v):
        """Round machine coordinates to the machine's step (thesis 5.1.1: 10 um)."""
        return np.round(np.asarray(v, dtype=float) / self.resolution_mm) * self.resolution_mm

    def travel_time_s(self, dx, dy):
        """Time of a straight XY move at the per-axis speed limits: the slower axis decides."""
        return np.maximum(np.abs(dx) / self.max_speed_mm_s[0], np.abs(dy) / self.max_speed_mm_s[1])


def _num(d: dict, key: str, where: str, path, *, positive: bool = True) -> float:
    if key not in d:
        raise InputError(f"[{where}] lacks {key}", path=path)
    v = d[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InputError(f"[{where}] {key} must be a finite number, got {v!r}", path=path)
    if positive and v <= 0:
        raise InputError(f"[{where}] {key} must be > 0, got {v!r}", path=path)
    return float(v)


def _pair(d: dict, key: str, where: str, path) -> tuple[float, float]:
    v = d.get(key)
    if (not isinstance(v, list) or len(v) != 2
            or not all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)):
        raise InputError(f"[{where}] {key} must be a list of two numbers, got {v!r}", path=path)
    return float(v[0]), float(v[1])


def _int(d: dict, key: str, where: str, path, minimum: int) -> int:
    v = d.get(key)
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise InputError(f"[{where}] {key} must be an integer >= {minimum}, got {v!r}", path=path)
    return v


def _on_grid(value: float, step: float) -> bool:
    return abs(value / step - round(value / step)) < 1e-6


def load_machine(path: str | Path | None = None) -> Machine:
    """Read and check a machine description (default ``scenes/engraver_roland.toml``).

    Refuses (``InputError`` naming the file and key): a missing or unreadable file, a
    cut depth beyond ``max_depth_mm`` or off the machine's 10 um grid (thesis 5.1.2:
    "we cannot use other values in between"), feeds above the axis limits of thesis
    5.1.1, a screen with slope a/b outside [0, 1] (one pixel per column, thesis 5.2).
    """
    path = resolve_input(path, "machine description") if path is not None else DEFAULT_MACHINE_FILE
    raw = read_toml(path, "machine description")
    for section in ("machine", "tool", "motion", "halftone"):
        if not isinstance(raw.get(section), dict):
            raise InputError(f"lacks the [{section}] table", path=path)
    m, t, mo, h = raw["machine"], raw["tool"], raw["motion"], raw["halftone"]

    bed = _pair(m, "bed_mm", "machine", path)
    if min(bed) <= 0:
        raise InputError(f"[machine] bed_mm must be positive, got {list(bed)}", path=path)
    res = _num(m, "resolution_mm", "machine", path)
    vmax = cast("tuple[float, float, float]", tuple(_num(m, f"max_speed_{ax}_mm_s", "machine", path) for ax in "xyz"))
    units = _int(m, "rml_units_per_mm", "machine", path, 1)

    depth = _num(t, "cut_depth_mm", "tool", path)
    max_depth = _num(t, "max_depth_mm", "tool", path)
    thickness = _num(t, "scratch_thickness_mm", "tool", path)
    if depth > max_depth + 1e-12:
        raise InputError(f"[tool] cut_depth_mm {depth} mm is deeper than the configured limit "
                         f"max_depth_mm {max_depth} mm; refusing", path=path)
    if not _on_grid(depth, res):
        raise InputError(f"[tool] cut_depth_mm {depth} mm is not a multiple of the machine's "
                         f"resolution {res} mm (thesis 5.1.2)", path=path)
    direction = t.get("cut_direction")
    if direction not in ("+y", "-y"):
        raise InputError(f"[tool] cut_direction must be \"+y\" or \"-y\", got {direction!r}", path=path)

    safe = _num(mo, "safe_height_mm", "motion", path)
    cut_feed = _num(mo, "cut_feed_mm_s", "motion", path)
    plunge = _num(mo, "plunge_feed_mm_s", "motion", path)
    if cut_feed > vmax[1]:
        raise InputError(f"[motion] cut_feed_mm_s {cut_feed} exceeds the y-axis limit "
                         f"max_speed_y_mm_s {vmax[1]} (thesis 5.1.1)", path=path)
    if plunge > vmax[2]:
        raise InputError(f"[motion] plunge_feed_mm_s {plunge} exceeds the z-axis limit "
                         f"max_speed_z_mm_s {vmax[2]} (thesis 5.1.1)", path=path)
    origin = _pair(mo, "print_origin_mm", "motion", path)
    if not (0 <= origin[0] < bed[0] and 0 <= origin[1] < bed[1]):
        raise InputError(f"[motion] print_origin_mm {list(origin)} lies outside the bed {list(bed)}", path=path)
    band = _num(mo, "travel_band_mm", "motion", path, positive=False)
    if band < 0:
        raise InputError(f"[motion] travel_band_mm must be >= 0, got {band}", path=path)

    a = _int(h, "a", "halftone", path, 0)
    b = _int(h, "b", "halftone", path, 1)
    T = _int(h, "T", "halftone", path, 1)
    if a > b:
        raise InputError(f"[halftone] slope a/b = {a}/{b} is steeper than 1; this implementation "
                         "vectorises lines with one pixel per column (0 <= a <= b)", path=path)
    if b * T > 65535:
        raise InputError(f"[halftone] screen of {b * T} pixels is too large", path=path)

    return Machine(
        path=str(path), name=str(m.get("name", path.stem)), bed_mm=bed, resolution_mm=res,
        max_speed_mm_s=vmax, rml_units_per_mm=units, tool=str(t.get("name", "tool")),
        cut_depth_mm=depth, max_depth_mm=max_depth, scratch_thickness_mm=thickness,
        cut_direction=1 if direction == "+y" else -1, safe_height_mm=safe,
        cut_feed_mm_s=cut_feed, plunge_feed_mm_s=plunge, print_origin_mm=origin,
        travel_band_mm=band, screen=ScreenParams(a, b, T))
