"""Reading the project's TOML and JSON inputs (rig descriptions, materials, machine
descriptions; fits, reproduction models, calibrations) with errors that name the file
and the problem (design.md, "bad input")."""
from __future__ import annotations

import json
import math
import tomllib
from pathlib import Path

from glossrig.core.errors import InputError


def _read_parsed(path, what: str, parse, syntax_error, unreadable: str, invalid: str):
    """``parse`` of the text of ``path``; a missing file, a folder, an unreadable or
    undecodable file and a ``syntax_error`` of the parser raise :class:`InputError` naming
    the file (``unreadable``, ``invalid``: message formats with ``{what}`` and ``{e}``)."""
    path = Path(path)
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise InputError(f"{what} not found", path=path) from None
    except IsADirectoryError:
        raise InputError(f"is a directory, expected a {what}", path=path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(unreadable.format(what=what, e=e), path=path) from None
    try:
        return parse(text)
    except syntax_error as e:
        raise InputError(invalid.format(what=what, e=e), path=path) from None


def read_toml(path: str | Path, what: str) -> dict:
    """The parsed TOML table of ``path``. ``what`` names the kind of file in the errors,
    e.g. ``read_toml("x.toml", "rig file")`` on a missing file raises
    ``InputError("x.toml: rig file not found")``; a folder, an unreadable or undecodable
    file and invalid TOML (with the parser's line and column) are reported the same way."""
    return _read_parsed(path, what, tomllib.loads, tomllib.TOMLDecodeError, "cannot read {what}: {e}",
                        "{what} is not valid TOML: {e}")


def read_json(path: str | Path, what: str):
    """The parsed JSON document of ``path``; errors name the file and ``what`` it should
    be: ``read_json("fit.json", "fit file")`` on a missing file raises
    ``InputError("fit.json: fit file not found")``; a folder, an unreadable file and
    invalid JSON (``"... is not readable JSON (reason)"``) likewise."""
    return _read_parsed(path, what, json.loads, json.JSONDecodeError, "{what} is not readable JSON ({e})",
                        "{what} is not readable JSON ({e})")


def _bounds(lo: float, hi: float, lo_open: bool, hi_open: bool) -> str:
    parts = []
    if lo > -math.inf:
        parts.append(f"{'>' if lo_open else '>='} {lo:g}")
    if hi < math.inf:
        parts.append(f"{'<' if hi_open else '<='} {hi:g}")
    return " and ".join(parts)


def check_number(value, key: str, path, *, lo: float = -math.inf, hi: float = math.inf, lo_open: bool = False,
                 hi_open: bool = False, integer: bool = False):
    """``value``, read as ``key`` of the input file ``path``, as a float (an int with
    ``integer``): the one number check of the project's input files (rig, capture plan).
    A bool, a non-number (with ``integer``, a non-integer), NaN or infinity, or a value
    outside ``[lo, hi]`` (``lo_open``/``hi_open``: the bound itself is excluded) raises
    :class:`InputError` naming the file and the key, e.g. ``InputError("rig.toml:
    camera.bits must be >= 8 and <= 16, got 20")`` or ``"... repeats must be an integer
    >= 1, got 0"``."""
    bounds = _bounds(lo, hi, lo_open, hi_open)
    if integer:
        if isinstance(value, bool) or not isinstance(value, int) or not (
                (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)):
            raise InputError(f"{key} must be an integer" + (f" {bounds}" if bounds else "") + f", got {value!r}",
                             path=path)
        return value
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise InputError(f"{key} must be a number, got {value!r}", path=path)
    if not ((value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)):
        raise InputError(f"{key} must be {bounds}, got {value!r}", path=path)
    return float(value)
