"""Provenance of an output: what it was made from and by which code (issue #16;
design.md "every output records its provenance (inputs with checksums, options, version)").

:func:`provenance` returns one plain-JSON dict that a writer stores with its output
(``glossrig extract`` in the samples table's Parquet schema metadata, ``glossrig fit``
as the top-level ``"provenance"`` of fit.json)::

    {"tool": "glossrig extract",
     "glossrig_version": "0.1.0",                       # importlib.metadata
     "source": {"commit": "<40 hex>", "dirty": false},  # null when not a git checkout
     "inputs": {"camera": {"path": "camera.json",       # as given
                           "resolved": "/abs/camera.json",
                           "sha256": "..."},
                "sample": {"path": ..., "resolved": ..., "sha256": "...",
                           "file": "capture.json"}},     # a capture folder: its manifest's hash
     "options": {...}}

A capture folder is identified by the sha256 of its ``capture.json``: the manifest
records every raw file's sha256 and every raw read verifies it, so the manifest's hash
stands for the whole capture (the same rule as :mod:`glossrig.core.checkpoint`).

No time stamp is recorded: a resumed run must end byte-identical to an uninterrupted one.

``source`` is the git commit of the source tree the running code comes from, and
whether any tracked file of the package differs from it; it is ``null`` when glossrig
runs from an installed wheel (no checkout) or when git is missing or refuses the
folder - provenance never fails for lack of git.
"""
from __future__ import annotations

import os
import subprocess
from pathlib import Path
from typing import Any

from glossrig.core.capture import MANIFEST, sha256_file
from glossrig.core.checkpoint import _jsonable, glossrig_version
from glossrig.core.errors import InputError

#: the source checkout's root when glossrig runs from one (core/ is a top-level folder)
SOURCE_ROOT = Path(__file__).resolve().parents[1]
#: the tracked paths whose edits make a checkout "dirty" (the installed packages' sources)
PACKAGE_PATHS = ("core", "twin", "hardware", "cli", "scenes", "pyproject.toml")
#: key of the provenance JSON in a Parquet file's schema metadata
PARQUET_KEY = b"glossrig.provenance"

file_sha256 = sha256_file
"""sha256 (hex) of a file's bytes; the one implementation lives in :mod:`glossrig.core.capture`."""


def _git(*args: str) -> str | None:
    """``git -C SOURCE_ROOT args`` stdout, or None when git is missing or fails."""
    try:
        r = subprocess.run(["git", "-C", str(SOURCE_ROOT), *args], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def source_revision(paths: tuple[str, ...] = PACKAGE_PATHS, short: bool = False) -> dict | None:
    """``{"commit", "dirty"}`` of the git checkout the running code comes from, or None.

    None unless the folder holding ``core/`` is itself a git work tree's top level with
    a ``pyproject.toml`` (an installed wheel lives in site-packages, which may sit inside
    some other repository: that repository's commit says nothing about this code).
    ``dirty``: a tracked file under ``paths`` differs from the commit (untracked files
    are ignored). ``short``: the abbreviated commit."""
    if not (SOURCE_ROOT / "pyproject.toml").is_file():
        return None
    top = _git("rev-parse", "--show-toplevel")
    if not top or Path(top).resolve() != SOURCE_ROOT:
        return None
    commit = _git("rev-parse", *(["--short"] if short else []), "HEAD")
    if not commit:
        return None
    status = _git("status", "--porcelain", "--untracked-files=no", "--", *paths)
    return {"commit": commit, "dirty": None if status is None else bool(status)}


def describe_input(path: str | os.PathLike) -> dict:
    """Path as given, resolved path and sha256 of a file, or of a capture folder's manifest."""
    p = Path(path)
    d: dict[str, Any] = {"path": os.fspath(path), "resolved": str(p.resolve())}
    if p.is_dir():
        m = p / MANIFEST
        if not m.is_file():
            raise InputError(f"no {MANIFEST}: not a capture folder", path=p)
        d.update(sha256=sha256_file(m), file=MANIFEST)
    elif p.is_file():
        d["sha256"] = sha256_file(p)
    else:
        raise InputError("input not found (cannot record its checksum)", path=p)
    return d


def provenance(inputs: dict[str, str | os.PathLike | None], options: dict, tool: str | None = None) -> dict:
    """The provenance record of an output (module docstring).

    ``inputs``: name -> file or capture folder (None: not used, recorded as null).
    ``options``: every option that affects the result, as JSON values (paths become
    strings). ``tool``: the command that made the output, e.g. ``"glossrig fit"``."""
    out: dict[str, Any] = {}
    if tool:
        out["tool"] = tool
    out.update(glossrig_version=glossrig_version(), source=source_revision(),
               inputs={k: (None if v is None else describe_input(v)) for k, v in inputs.items()},
               options=_jsonable(dict(options)))
    return out
