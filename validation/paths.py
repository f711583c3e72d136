"""Where the studies find the repository and the shared data, with no machine paths.

The shared data (thesis tables, RGL measured BRDFs) lives in ``shared/`` beside the
checkout; ``GLOSSRIG_SHARED`` names another folder. :func:`rgl_dir` stops with a message
naming the folder it looked in when the data is absent.
"""
from __future__ import annotations

import os
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SHARED = Path(os.environ.get("GLOSSRIG_SHARED", ROOT.parent / "shared"))


def rgl_dir() -> Path:
    """The RGL measured-BRDF folder (``SHARED/data/rgl``)."""
    d = SHARED / "data" / "rgl"
    if not d.is_dir():
        raise SystemExit(f"{d}: RGL data not found (set GLOSSRIG_SHARED to the shared/ folder)")
    return d
