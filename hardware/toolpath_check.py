"""Checking a toolpath before a single line goes to the engraver: bed, depth, speed.

Thesis 5.1: the scratches are made by a 3-axis Roland engraver (10 um resolution,
100 mm/s in x and z, 50 mm/s in y) cutting 20 um deep into a transparency sheet; a
path that leaves the sheet's bed or cuts deeper than the tool allows ruins the sample
or the blade. The fabrication code writes G-code or Roland RML-1 files
(:mod:`glossrig.core.fabrication`); this module parses them independently - a small
interpreter of the subset a toolpath needs - and refuses the whole file, naming the
line, if any point of any move lies

* outside the bed ``[0, bed_x] x [0, bed_y]`` (work coordinates from the user origin),
* below ``-max_depth_mm`` (Z = 0 is the sheet's surface, thesis 5.1.2) or above
  ``max_height_mm`` when that is given,
* or if a feed moves an axis faster than its limit (thesis 5.1.1),

and also refuses what it cannot check: coordinate-system changes and machine-coordinate
moves (G92, G10, G28, G30, G53, G54.1.., G55-G59), R-format arcs, inverse-time feed,
relative moves from an unknown position, and instructions it does not know. Arcs
(G2/G3 with I/J in the XY plane) are checked along their whole sweep, not only at
their end points. Straight moves between two checked points stay inside the box.

Limits come from the machine description (``scenes/engraver_roland.toml``:
``[machine] bed_mm``, ``max_speed_*_mm_s``, ``rml_units_per_mm``; ``[tool]
max_depth_mm``) via :func:`load_machine_limits`, or are given directly.
"""
from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path
from collections.abc import Iterable

from glossrig.core.errors import InputError
from glossrig.core.resources import resolve_input
from glossrig.core.rig import SCENES_DIR
from glossrig.core.toml_input import read_toml

DEFAULT_MACHINE = SCENES_DIR / "engraver_roland.toml"
GCODE_SUFFIXES = {".nc", ".gcode", ".ngc", ".gc", ".tap", ".cnc"}
RML_SUFFIXES = {".rml", ".prn", ".rol"}
_EPS = 1e-6


class ToolpathError(InputError):
    """A toolpath the pre-send check refuses (names the file, the line and why)."""


@dataclass(frozen=True)
class MachineLimits:
    """The envelope a toolpath must stay in (work coordinates, mm and mm/s)."""

    bed_mm: tuple[float, float]
    max_depth_mm: float
    max_height_mm: float | None = None
    max_speed_mm_s: tuple[float, float, float] | None = None
    rml_units_per_mm: float = 100.0
    source: str = "machine limits"

    def __post_init__(self):
        if len(self.bed_mm) != 2 or min(self.bed_mm) <= 0:
            raise InputError(f"bed must be two positive sizes in mm, got {self.bed_mm}", path=self.source)
        if not self.max_depth_mm >= 0:
            raise InputError(f"max_depth_mm must be >= 0, got {self.max_depth_mm}", path=self.source)
        if self.rml_units_per_mm <= 0:
            raise InputError(f"rml_units_per_mm must be > 0, got {self.rml_units_per_mm}", path=self.source)


def load_machine_limits(path: str | Path | None = None, *, max_height_mm: float | None = None) -> MachineLimits:
    """Limits from a machine description (default ``scenes/engraver_roland.toml``)."""
    path = resolve_input(path, "machine description") if path is not None else DEFAULT_MACHINE
    raw = read_toml(path, "machine description")

    def get(section, key):
        sec = raw.get(section)
        if not isinstance(sec, dict) or key not in sec:
            raise InputError(f"lacks [{section}] {key}", path=path)
        return sec[key]

    def num(v, what):
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise InputError(f"{what} must be a non-negative number, got {v!r}", path=path)
        return float(v)

    bed = get("machine", "bed_mm")
    if not isinstance(bed, list) or len(bed) != 2:
        raise InputError(f"[machine] bed_mm must be [x, y] in mm, got {bed!r}", path=path)
    speeds = tuple(num(get("machine", f"max_speed_{a}_mm_s"), f"[machine] max_speed_{a}_mm_s") for a in "xyz")
    return MachineLimits(bed_mm=(num(bed[0], "bed_mm[0]"), num(bed[1], "bed_mm[1]")),
                         max_depth_mm=num(get("tool", "max_depth_mm"), "[tool] max_depth_mm"),
                         max_height_mm=max_height_mm, max_speed_mm_s=speeds,
                         rml_units_per_mm=num(get("machine", "rml_units_per_mm"), "[machine] rml_units_per_mm"),
                         source=str(path))


@dataclass(frozen=True)
class Move:
    """One straight or circular move, in mm (coordinates None where still unknown)."""

    line: int
    text: str
    start: tuple[float | None, float | None, float | None]
    end: tuple[float | None, float | None, float | None]
    feed_mm_s: float | None = None      # None: rapid (machine's own speed)
    arc: tuple[float, float, bool] | None = None   # (centre x, centre y, clockwise)
    index: int = -1                     # the command (Toolpath.commands) it belongs to


@dataclass
class Toolpath:
    """A parsed toolpath: what to send (``commands``: line number, text) and its moves."""

    dialect: str
    source: str
    commands: list[tuple[int, str]] = field(default_factory=list)
    moves: list[Move] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)   # things the parser could not check
    heights: list[tuple[int, float, str]] = field(default_factory=list)   # Z settings that are not moves

    def position_after(self, command_index: int) -> tuple[float | None, float | None, float | None]:
        """Where the tool is once commands ``0..command_index`` have run (None: unknown)."""
        pos = (None, None, None)
        for m in self.moves:
            if m.index > command_index:
                break
            pos = m.end
        return pos


# ------------------------------------------------------------------ G-code

_WORD = re.compile(r"([A-Z])\s*([-+]?(?:\d+\.?\d*|\.\d+))")
_KNOWN_WORDS = set("GMXYZIJKRFSTNP")
_ALLOWED_G = {0, 1, 2, 3, 4, 17, 20, 21, 40, 49, 54, 61, 64, 80, 90, 91, 94}
_REFUSED_G = {
    10: "sets coordinate offsets", 28: "moves to a stored machine position", 30: "moves to a stored machine position",
    53: "moves in machine coordinates", 92: "shifts the coordinate system", 93: "uses inverse-time feed",
    18: "selects another arc plane", 19: "selects another arc plane", 43: "applies a tool length offset",
    38: "probes", 55: "selects another work coordinate system", 56: "selects another work coordinate system",
    57: "selects another work coordinate system", 58: "selects another work coordinate system",
    59: "selects another work coordinate system"}


def _strip_gcode(line: str) -> str:
    line = re.sub(r"\([^)]*\)", " ", line)
    return line.split(";", 1)[0].strip()


def parse_gcode(lines: Iterable[str], source: str = "<toolpath>") -> Toolpath:
    """Parse G-code (RS-274 subset GRBL runs) into moves; comments are dropped from
    the commands to send."""
    tp = Toolpath("gcode", source)
    pos: list[float | None] = [None, None, None]
    motion, absolute, scale, feed = None, True, 1.0, None   # scale: file units -> mm

    for n, raw_line in enumerate(lines, start=1):
        text = _strip_gcode(raw_line).upper()
        if not text or text == "%":
            continue
        tp.commands.append((n, text))
        body = text.lstrip("/")
        words = _WORD.findall(body)
        if re.sub(r"\s+", "", body) != "".join(a + b for a, b in words).replace(" ", ""):
            leftover = _WORD.sub("", body).strip()
            tp.problems.append(f"line {n}: cannot parse {leftover!r} in {text!r}")
            continue
        vals: dict[str, float] = {}
        gcodes = []
        for letter, num in words:
            v = float(num)
            if letter not in _KNOWN_WORDS:
                tp.problems.append(f"line {n}: word {letter} is not understood by the pre-send check")
                continue
            if letter == "G":
                gcodes.append(v)
            elif letter in vals:
                tp.problems.append(f"line {n}: word {letter} given twice")
            else:
                vals[letter] = v
        for g in gcodes:
            gi = int(g)
            if g != gi:         # G38.2, G54.1, G90.1 ...
                if abs(g - 91.1) < 1e-9:     # incremental arc centres: the default, as assumed here
                    continue
                tp.problems.append(f"line {n}: G{g:g} is not supported by the pre-send check")
                continue
            if gi in _REFUSED_G:
                tp.problems.append(f"line {n}: G{gi} {_REFUSED_G[gi]}; such a toolpath cannot be checked "
                                   "before sending")
            elif gi not in _ALLOWED_G:
                tp.problems.append(f"line {n}: G{gi} is not known to the pre-send check")
            elif gi in (0, 1, 2, 3):
                motion = gi
            elif gi == 20:
                scale = 25.4
            elif gi == 21:
                scale = 1.0
            elif gi == 90:
                absolute = True
            elif gi == 91:
                absolute = False
        if "F" in vals:
            if vals["F"] <= 0:
                tp.problems.append(f"line {n}: feed F must be > 0")
            feed = vals["F"] * scale / 60.0
        axes = [a for a in "XYZ" if a in vals]
        if not axes or any(int(g) == 4 for g in gcodes):
            continue
        if motion is None:
            tp.problems.append(f"line {n}: axis words before any G0/G1/G2/G3")
            continue
        start = tuple(pos)
        end = list(pos)
        for i, a in enumerate("XYZ"):
            if a not in vals:
                continue
            v = vals[a] * scale
            if absolute:
                end[i] = v
            elif pos[i] is None:
                tp.problems.append(f"line {n}: relative move of {a} from an unknown position")
                end[i] = None
            else:
                end[i] = pos[i] + v
        arc = None
        if motion in (2, 3):
            if "R" in vals:
                tp.problems.append(f"line {n}: R-format arcs are not supported by the pre-send check; use I/J")
            elif start[0] is None or start[1] is None:
                tp.problems.append(f"line {n}: arc from an unknown position")
            else:
                arc = (start[0] + vals.get("I", 0.0) * scale, start[1] + vals.get("J", 0.0) * scale, motion == 2)
        tp.moves.append(Move(n, text, start, tuple(end), None if motion == 0 else feed, arc, len(tp.commands) - 1))
        if motion != 0 and feed is None:
            tp.problems.append(f"line {n}: feed move before any feed rate F")
        pos = end
    return tp


# ------------------------------------------------------------------ RML-1

_RML_KNOWN = {"IN", "DF", "!MC", "!RC", "!DW", "!NR", "V", "VS", "!VZ", "F", "!PZ", "PA", "PR", "PU", "PD",
                  "Z", "H"}
_RML_MNEMONIC = re.compile(r"^(?:(!|\^)([A-Z]{2})|(VS|PA|PR|PU|PD|IN|DF)|([ZVFH]))(.*)$", re.S)


def _rml_commands(text: str) -> list[tuple[int, str]]:
    out = []
    line = 1
    cur, cur_line = [], 1
    for ch in text:
        if ch == ";":
            s = "".join(cur).strip()
            if s:
                out.append((cur_line, s))
            cur = []
            cur_line = line
            continue
        if ch == "\n":
            line += 1
            if not "".join(cur).strip():
                cur_line = line
        cur.append(ch)
    s = "".join(cur).strip()
    if s:
        out.append((cur_line, s))
    return out


def parse_rml(text: str, source: str = "<toolpath>", *, units_per_mm: float = 100.0) -> Toolpath:
    """Parse Roland RML-1 (``;``-separated instructions, coordinates in machine steps
    of ``1/units_per_mm`` mm): ``Z x,y,z`` 3-D moves; ``PU``/``PD`` moves at the
    ``!PZ z1,z2`` down/up heights; ``PA``/``PR`` absolute/relative; ``V``/``VS``/
    ``!VZ`` speeds in mm/s; ``^IN``/``^DF``, ``!MC``, ``!RC``, ``!DW``, ``!NR``, ``H``."""
    tp = Toolpath("rml", source)
    u = float(units_per_mm)
    pos: list[float | None] = [None, None, None]
    z_down, z_up = 0.0, 0.0
    absolute = True
    pen_down = False
    v3d = vs = vz = None
    for n, cmd in _rml_commands(text):
        tp.commands.append((n, cmd + ";"))
        m = _RML_MNEMONIC.match(cmd.upper().replace("\r", "").replace("\n", " ").strip())
        if not m:
            tp.problems.append(f"line {n}: unknown RML-1 instruction {cmd!r}")
            continue
        prefix, two, hp, one, rest = m.groups()
        name = (prefix + two if prefix else None) or hp or one
        if prefix == "^":
            name = two
        if name not in _RML_KNOWN:
            tp.problems.append(f"line {n}: RML-1 instruction {name!r} is not known to the pre-send check")
            continue
        rest = rest.strip()
        try:
            params = [float(x) for x in re.split(r"[,\s]+", rest) if x] if rest else []
        except ValueError:
            tp.problems.append(f"line {n}: cannot read the parameters of {cmd!r}")
            continue
        if name in ("IN", "DF"):
            absolute, pen_down = True, False
        elif name == "H":
            pos = [None, None, None]
        elif name in ("V", "VS", "!VZ", "F"):
            if len(params) != 1 or params[0] <= 0:
                tp.problems.append(f"line {n}: {name} needs one positive speed in mm/s")
                continue
            if name in ("V", "F"):
                v3d = params[0]
            elif name == "VS":
                vs = params[0]
            else:
                vz = params[0]
        elif name == "!PZ":
            if not 1 <= len(params) <= 2:
                tp.problems.append(f"line {n}: !PZ takes z1[,z2]")
                continue
            z_down = params[0] / u
            if len(params) == 2:
                z_up = params[1] / u
            tp.heights.append((n, z_down, "!PZ down height"))   # refused even if no PD follows
        elif name in ("PA", "PR", "PU", "PD"):
            if name == "PA":
                absolute = True
            elif name == "PR":
                absolute = False
            elif name == "PU":
                pen_down = False
            else:
                pen_down = True
            if len(params) % 2:
                tp.problems.append(f"line {n}: {name} needs x,y pairs")
                continue
            z = z_down if pen_down else z_up
            if not params and name in ("PU", "PD"):
                start = tuple(pos)
                pos = [pos[0], pos[1], z]
                tp.moves.append(Move(n, cmd, start, tuple(pos), vz if pen_down else None, index=len(tp.commands) - 1))
            for i in range(0, len(params), 2):
                start = tuple(pos)
                x, y = params[i] / u, params[i + 1] / u
                if not absolute:
                    if pos[0] is None or pos[1] is None:
                        tp.problems.append(f"line {n}: relative move from an unknown position")
                        pos = [None, None, z]
                        continue
                    x, y = pos[0] + x, pos[1] + y
                # the tool goes to its height first, then travels
                if pos[2] != z:
                    tp.moves.append(Move(n, cmd, start, (start[0], start[1], z), vz if pen_down else None,
                                         index=len(tp.commands) - 1))
                    start = (start[0], start[1], z)
                pos = [x, y, z]
                tp.moves.append(Move(n, cmd, start, (x, y, z), vs if pen_down else None, index=len(tp.commands) - 1))
        elif name == "Z":
            if not params or len(params) % 3:
                tp.problems.append(f"line {n}: Z needs x,y,z triples")
                continue
            for i in range(0, len(params), 3):
                start = tuple(pos)
                pos = [params[i] / u, params[i + 1] / u, params[i + 2] / u]
                tp.moves.append(Move(n, cmd, start, tuple(pos), v3d, index=len(tp.commands) - 1))
        # !MC, !RC, !DW, !NR: no motion
    return tp


def _check_z(n: int, z: float, what: str, limits: MachineLimits) -> list[str]:
    out = []
    if z < -limits.max_depth_mm - _EPS:
        out.append(f"line {n}: {what} Z={z:.3f} mm is below the safe depth -{limits.max_depth_mm:g} mm "
                   f"(max_depth_mm, {limits.source})")
    if limits.max_height_mm is not None and z > limits.max_height_mm + _EPS:
        out.append(f"line {n}: {what} Z={z:.3f} mm is above the machine's {limits.max_height_mm:g} mm")
    return out


# ------------------------------------------------------------------ checking

def _arc_points(m: Move) -> list[tuple[float, float]]:
    """End points and every axis-extreme point the arc's sweep passes."""
    cx, cy, cw = m.arc
    sx, sy = m.start[0], m.start[1]
    ex = m.end[0] if m.end[0] is not None else sx
    ey = m.end[1] if m.end[1] is not None else sy
    r = math.hypot(sx - cx, sy - cy)
    a0 = math.atan2(sy - cy, sx - cx)
    a1 = math.atan2(ey - cy, ex - cx)
    if cw:
        sweep = (a0 - a1) % (2 * math.pi)
    else:
        sweep = (a1 - a0) % (2 * math.pi)
    if sweep < 1e-12:
        sweep = 2 * math.pi     # same start and end: a full circle
    pts = [(sx, sy), (ex, ey)]
    for k in range(4):
        a = k * math.pi / 2
        d = ((a0 - a) if cw else (a - a0)) % (2 * math.pi)
        if d <= sweep + 1e-12:
            pts.append((cx + r * math.cos(a), cy + r * math.sin(a)))
    return pts


def check_toolpath(tp: Toolpath, limits: MachineLimits, max_reported: int = 8) -> None:
    """Raise :class:`ToolpathError` (naming the file and lines) if ``tp`` leaves
    ``limits`` anywhere or holds something the check cannot vouch for."""
    problems = list(tp.problems)
    for line, z, what in tp.heights:
        problems.extend(_check_z(line, z, what, limits))
    bx, by = limits.bed_mm
    vmax = limits.max_speed_mm_s
    for m in tp.moves:
        if m.arc:
            cx, cy, _ = m.arc
            ex = m.end[0] if m.end[0] is not None else m.start[0]
            ey = m.end[1] if m.end[1] is not None else m.start[1]
            r0, r1 = math.hypot(m.start[0] - cx, m.start[1] - cy), math.hypot(ex - cx, ey - cy)
            if abs(r0 - r1) > 0.005 + 0.001 * r0:
                problems.append(f"line {m.line}: arc end point is not on the arc's circle (radius {r0:.3f} mm at "
                                f"the start, {r1:.3f} mm at the end) in {m.text!r}")
                continue
            pts = _arc_points(m)
        else:   # a move that keeps X or Y keeps the verdict of the move that set it
            pts = [(m.end[0] if m.end[0] != m.start[0] else None, m.end[1] if m.end[1] != m.start[1] else None)]
        for x, y in pts:
            if x is not None and not -_EPS <= x <= bx + _EPS:
                problems.append(f"line {m.line}: X={x:.3f} mm is outside the bed (0..{bx:g} mm) in {m.text!r}")
                break
            if y is not None and not -_EPS <= y <= by + _EPS:
                problems.append(f"line {m.line}: Y={y:.3f} mm is outside the bed (0..{by:g} mm) in {m.text!r}")
                break
        if m.end[2] is not None and (m.end[2] != m.start[2] or m.start[2] is None):
            problems.extend(_check_z(m.line, m.end[2], "move to", limits))
        if vmax is not None and m.feed_mm_s is not None and None not in m.start and None not in m.end:
            d = [m.end[i] - m.start[i] for i in range(3)]
            length = math.sqrt(sum(c * c for c in d))
            if m.arc is None and length > 0:
                for i, axis in enumerate("XYZ"):
                    v = m.feed_mm_s * abs(d[i]) / length
                    if v > vmax[i] * (1 + 1e-6):
                        problems.append(f"line {m.line}: feed {m.feed_mm_s:g} mm/s moves {axis} at {v:.1f} mm/s, "
                                        f"above the machine's {vmax[i]:g} mm/s (thesis 5.1.1)")
            elif m.arc is not None and m.feed_mm_s > max(vmax[0], vmax[1]) * (1 + 1e-6):
                problems.append(f"line {m.line}: arc feed {m.feed_mm_s:g} mm/s is above the machine's X/Y limits")
    if problems:
        shown = problems[:max_reported]
        more = f" (and {len(problems) - max_reported} more)" if len(problems) > max_reported else ""
        raise ToolpathError("toolpath refused before sending anything: " + "; ".join(shown) + more, path=tp.source)


def read_toolpath(toolpath, *, dialect: str | None = None, units_per_mm: float = 100.0,
                  source: str | None = None) -> Toolpath:
    """A :class:`Toolpath` from a file path, a text or a list of lines. ``dialect``
    ("gcode" / "rml") defaults from the file suffix."""
    if isinstance(toolpath, Toolpath):
        return toolpath
    if isinstance(toolpath, Path) or (isinstance(toolpath, str) and "\n" not in toolpath and ";" not in toolpath
                                      and Path(toolpath).suffix.lower() in GCODE_SUFFIXES | RML_SUFFIXES):
        path = Path(toolpath)
        try:
            text = path.read_text(encoding="ascii")
        except FileNotFoundError:
            raise InputError("toolpath file not found", path=path) from None
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(f"cannot read the toolpath: {e}", path=path) from None
        if dialect is None:
            suf = path.suffix.lower()
            dialect = "gcode" if suf in GCODE_SUFFIXES else "rml" if suf in RML_SUFFIXES else None
        source = source or str(path)
    else:
        text = toolpath if isinstance(toolpath, str) else "\n".join(toolpath)
        source = source or "<toolpath>"
    if dialect == "gcode":
        return parse_gcode(text.splitlines(), source)
    if dialect == "rml":
        return parse_rml(text, source, units_per_mm=units_per_mm)
    raise InputError(f"cannot tell whether the toolpath is G-code or RML-1 (suffix: {sorted(GCODE_SUFFIXES)} or "
                     f"{sorted(RML_SUFFIXES)})", path=source)
