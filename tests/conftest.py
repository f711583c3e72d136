"""Shared fixtures. Mitsuba is imported through glossrig.twin.mitsuba_env, which picks
the LLVM variant when libLLVM 19 is present and falls back to scalar_rgb otherwise."""
from __future__ import annotations

from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SHARED = ROOT.parent / "shared"
RIG = ROOT / "scenes" / "thesis_rig.toml"


@pytest.fixture(scope="session")
def rig():
    from glossrig.core.rig import load_rig

    return load_rig(RIG)
