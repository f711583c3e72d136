"""Import Mitsuba with a working variant.

Dr.Jit's LLVM backend (Mitsuba's fast CPU variants) crashes with Debian 12's
default LLVM 15 and works with Debian's libllvm19. A crash cannot be caught
from Python, so the decision is made *before* Dr.Jit is imported:

1. ``DRJIT_LIBLLVM_PATH`` already set (``.ci/env.sh`` does it) -> ``llvm_ad_rgb``;
2. else a libLLVM 19 found at Debian's paths -> set the variable, ``llvm_ad_rgb``;
3. else ``scalar_rgb`` with a warning (about 12x slower with the Python Ward BSDF).

``GLOSSRIG_MITSUBA_VARIANT`` forces a variant.
"""
from __future__ import annotations

import os
import warnings
from pathlib import Path

_LLVM19 = ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", "/usr/lib/aarch64-linux-gnu/libLLVM.so.19.1",
           "/usr/lib/llvm-19/lib/libLLVM.so.19.1", "/usr/lib/llvm-19/lib/libLLVM-19.so")
_mi = None


def llvm19_path() -> str | None:
    """The libLLVM 19 that Dr.Jit's LLVM backend is to load (steps 1-2 above: the
    ``DRJIT_LIBLLVM_PATH`` already set, else the first of Debian's paths that exists, which is
    then put into ``DRJIT_LIBLLVM_PATH``), or None. Must run before Dr.Jit is first imported."""
    path = os.environ.get("DRJIT_LIBLLVM_PATH")
    if path and Path(path).exists() and "19" in Path(path).name:
        return path
    for p in _LLVM19:
        if Path(p).exists():
            os.environ["DRJIT_LIBLLVM_PATH"] = p
            return p
    return None


def choose_variant() -> str:
    forced = os.environ.get("GLOSSRIG_MITSUBA_VARIANT")
    if forced:
        return forced
    if llvm19_path() is not None:
        return "llvm_ad_rgb"
    warnings.warn("libLLVM 19 not found (Dr.Jit's LLVM backend crashes with LLVM 15): "
                  "falling back to Mitsuba's slow scalar_rgb variant. Run `source .ci/env.sh` "
                  "as root to install libllvm19.", RuntimeWarning, stacklevel=2)
    return "scalar_rgb"


def mitsuba():
    """The ``mitsuba`` module with its variant set and glossrig's plugins registered."""
    global _mi
    if _mi is None:
        import mitsuba as mi
        mi.set_variant(choose_variant())
        from . import rotated_bsdf, ward_bsdf
        ward_bsdf.register()
        rotated_bsdf.register()
        _mi = mi
    return _mi
