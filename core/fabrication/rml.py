"""Roland RML-1 for a scratch :class:`~.toolpath.Toolpath`, and a reader.

RML-1 is the proprietary machine language of the thesis's Roland engraver (thesis
5.1.1: "controlled individually by its proprietary machine code language"). Subset used
(Roland, *RML-1 Programming Guideline*, 2002; coordinates in 1/100 mm, i.e. the
machine's 10 um step):

- ``IN`` initialise, ``PA`` absolute coordinates, ``!MC0`` spindle motor off (the
  scalpel drags, it does not spin);
- ``VS v`` tool-down XY speed (mm/s): the cutting feed, along y, within the y limit;
- ``!VZ v`` Z speed (mm/s): the plunge feed, within the z limit;
- ``!PZ z1,z2`` the tool-down Z (scalpel depth, <= 0) and tool-up Z (safe height, >= 0);
- ``PU x,y`` raise the tool to z2, then move; ``PD x,y`` lower the tool to z1, then move.

Per cut: ``PU`` to its start at the safe height, ``PD`` to its end at the scalpel depth.
"""
from __future__ import annotations

import re

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.fabrication.gcode import Moves
from glossrig.core.fabrication.machine import Machine
from glossrig.core.fabrication.toolpath import Toolpath


def _units(v: np.ndarray, machine: Machine) -> list[int]:
    return np.rint(np.asarray(v) * machine.rml_units_per_mm).astype(np.int64).tolist()


def write_rml(path: Toolpath, machine: Machine) -> str:
    """The RML-1 program of ``path`` (module docstring). RML-1 has no comments; what the
    file is for is recorded in ``summary.json`` next to it."""
    down, up = _units(np.array([path.cut_z, path.safe_z]), machine)
    out = ["IN;", "!MC0;", "PA;", f"VS{machine.cut_feed_mm_s:g};", f"!VZ{machine.plunge_feed_mm_s:g};",
           f"!PZ{down},{up};"]
    xs, y0, y1 = _units(path.x, machine), _units(path.y_start, machine), _units(path.y_end, machine)
    out += [f"PU{x},{a};PD{x},{b};" for x, a, b in zip(xs, y0, y1)]
    hx, hy = _units(np.array(path.home), machine)
    out += [f"PU{hx},{hy};", "!MC0;", ""]
    return "\n".join(out)


_CMD = re.compile(r"\s*(![A-Za-z]{2}|[A-Za-z]{2})([^;A-Za-z!]*)")


def read_rml(text: str, machine: Machine, source: str = "RML-1") -> Moves:
    """Straight moves of an RML-1 program in the subset written here (module docstring).

    Z moves of ``PU``/``PD`` are returned as separate moves at the current XY; the
    position before the first ``PU``/``PD`` is unknown (``nan``). Other motion commands
    (``PR``, ``Z``, ...) are refused.
    """
    scale = 1.0 / machine.rml_units_per_mm
    z_down, z_up = None, None
    vs, vz = np.nan, np.nan
    pos = [np.nan, np.nan, np.nan]
    down = False
    start, end, rapid, feeds = [], [], [], []

    def move(target, is_rapid, feed):
        nonlocal pos
        start.append(list(pos))
        end.append(list(target))
        rapid.append(is_rapid)
        feeds.append(feed)
        pos = list(target)

    for chunk in text.replace("\n", ";").split(";"):
        chunk = chunk.strip()
        if not chunk:
            continue
        m = _CMD.fullmatch(chunk)
        if not m:
            raise InputError(f"cannot parse RML-1 command {chunk!r}", path=source)
        cmd, args = m.group(1).upper(), m.group(2).strip()
        try:
            nums = [float(v) for v in args.split(",") if v.strip()] if args else []
        except ValueError:
            raise InputError(f"bad parameters in {chunk!r}", path=source) from None
        if cmd in ("IN", "PA", "!MC"):
            if cmd == "IN":
                down = False
            continue
        if cmd == "VS":
            vs = nums[0]
        elif cmd == "!VZ":
            vz = nums[0]
        elif cmd == "!PZ":
            if len(nums) != 2:
                raise InputError(f"!PZ needs two parameters: {chunk!r}", path=source)
            z_down, z_up = nums[0] * scale, nums[1] * scale
        elif cmd in ("PU", "PD"):
            if z_down is None:
                raise InputError(f"{cmd} before !PZ sets the tool heights", path=source)
            if len(nums) % 2:
                raise InputError(f"{cmd} needs x,y pairs: {chunk!r}", path=source)
            want_down = cmd == "PD"
            if want_down != down or np.isnan(pos[2]):
                z = z_down if want_down else z_up
                move([pos[0], pos[1], z], not want_down, vz if want_down else np.nan)
                down = want_down
            for x, y in zip(nums[0::2], nums[1::2]):
                move([x * scale, y * scale, pos[2]], not want_down, vs if want_down else np.nan)
        else:
            raise InputError(f"RML-1 command {cmd} is not supported by this reader", path=source)
    return Moves(np.asarray(start, float).reshape(-1, 3), np.asarray(end, float).reshape(-1, 3),
                 np.asarray(rapid, bool), np.asarray(feeds, float))
