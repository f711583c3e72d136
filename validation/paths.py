"""Where the studies find the repository and the shared data, with no machine paths.

The shared data (thesis tables, RGL measured BRDFs) lives in ``shared/`` beside the
checkout; ``GLOSSRIG_SHARED`` names another folder. :func:`rgl_dir` and
:func:`thesis_dir` stop with a message naming the folder they looked in when the data
is absent.
"""
from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GLOSSRIG_SHARED", ROOT.parent / "shared"))
RIG = ROOT / "scenes" / "thesis_rig.toml"          # the thesis rig, the studies' default


def _shared(rel: str, what: str) -> Path:
    d = SHARED / rel
    if not d.is_dir():
        raise SystemExit(f"{d}: {what} not found (set GLOSSRIG_SHARED to the shared/ folder)")
    return d


def rgl_dir() -> Path:
    """The RGL measured-BRDF folder (``SHARED/data/rgl``)."""
    return _shared("data/rgl", "RGL data")


def thesis_dir() -> Path:
    """The thesis's tables (``SHARED/data/thesis``: ward_params.csv, coverages.csv, ...)."""
    return _shared("data/thesis", "thesis tables")
