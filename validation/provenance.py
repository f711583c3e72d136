"""Which code a study's stages ran with: the commit, and whether core/ or twin/ differed
from it (uncommitted edits). Studies are resumable, so a report may combine stages run at
different commits; each study records them and states them in its report."""
from __future__ import annotations

import json
from pathlib import Path

from glossrig.core.atomic import atomic_write_text

ROOT = Path(__file__).resolve().parents[1]


def code_version() -> dict | None:
    """The commit the working tree is at, and whether core/ or twin/ differ from it
    (:func:`glossrig.core.provenance.source_revision`, the one implementation that
    outputs record too); None when the code does not run from a git checkout."""
    from glossrig.core.provenance import source_revision

    return source_revision(paths=("core", "twin"), short=True)


def describe(v: dict | None) -> str:
    if not v:
        return "not recorded"
    return v["commit"] + (" (core/twin modified)" if v.get("dirty") else "")


def record(path: Path, key: str) -> None:
    """Add ``key`` -> the current code version to the JSON file ``path`` (created if missing)."""
    d = json.loads(path.read_text()) if path.exists() else {}
    d[key] = code_version()
    atomic_write_text(path, json.dumps(d, indent=1))
