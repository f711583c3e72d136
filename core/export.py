"""Exporting fits (design.md "Fits ... exportable as a Mitsuba material").

The material is a Mitsuba 3 scene-dictionary entry for the twin's extended-Ward
BSDF plugin ``glossrig_ward`` (``glossrig.twin.ward_bsdf``; eq. 4.79-4.80)::

    {"type": "glossrig_ward",
     "rho_d": {"type": "rgb", "value": [r, g, b]},
     "rho_s": {"type": "rgb", "value": [r, g, b]},
     "alpha_x": ..., "alpha_y": ..., "lobe_rotation": ...}   # radians

The plugin has one lobe (float alphas and rotation) with RGB albedos, so the
lobe is the luminance fit's and ``rho_d``, ``rho_s`` per channel are the
shared-lobe albedos of :class:`glossrig.core.fit.MaterialFit` (re-solved for
that lobe), not the independent per-channel fits, whose lobes differ slightly.
Plain JSON: ``mi.load_dict`` accepts it as is once the plugin is registered.
Knows nothing of Mitsuba itself (core imports neither twin nor Mitsuba).
"""
from __future__ import annotations

import json
import math
from pathlib import Path

from .errors import InputError
from .ward import WardParams

PLUGIN = "glossrig_ward"


def mitsuba_from_params(p: WardParams, rgb_rho_d=None, rgb_rho_s=None) -> dict:
    """Material dict for one set of Ward parameters; optional RGB albedos."""
    def col(v, rgb):
        vals = [float(v)] * 3 if rgb is None else [float(x) for x in rgb]
        if len(vals) != 3 or not all(math.isfinite(x) and x >= 0 for x in vals):
            raise InputError(f"RGB albedo must be three finite values >= 0, got {rgb!r}")
        return {"type": "rgb", "value": vals}

    return {"type": PLUGIN, "rho_d": col(p.rho_d, rgb_rho_d), "rho_s": col(p.rho_s, rgb_rho_s),
            "alpha_x": float(p.alpha_x), "alpha_y": float(p.alpha_y), "lobe_rotation": float(p.lobe_rotation)}


def mitsuba_material(material_fit) -> dict:
    """The ``glossrig_ward`` material of a :class:`~glossrig.core.fit.MaterialFit`."""
    s = material_fit.shared_rgb
    lobe = WardParams(rho_d=0.0, rho_s=0.0, alpha_x=s["alpha_x"], alpha_y=s["alpha_y"],
                      lobe_rotation=s["lobe_rotation"])
    return mitsuba_from_params(lobe, s["rho_d"], s["rho_s"])


def write_fit_json(material_fit, path: str | Path) -> Path:
    """Write ``material_fit.to_json()`` atomically (temporary file + rename)."""
    from .capture import atomic_write_bytes

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("output folder does not exist", path=path)
    text = json.dumps(material_fit.to_json(), indent=2, allow_nan=False)
    atomic_write_bytes(path, (text + "\n").encode())
    return path


def write_mitsuba_material(material_fit, path: str | Path) -> Path:
    """Write the Mitsuba material dict alone as JSON."""
    from .capture import atomic_write_bytes

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("output folder does not exist", path=path)
    atomic_write_bytes(path, (json.dumps(mitsuba_material(material_fit), indent=2) + "\n").encode())
    return path
