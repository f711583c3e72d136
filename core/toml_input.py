"""Reading the project's TOML and JSON inputs (rig descriptions, materials, machine
descriptions; fits, reproduction models, calibrations) with errors that name the file
and the problem (design.md, "bad input")."""
from __future__ import annotations

import json
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
