"""Exporting fits (design.md "Fits ... exportable as a Mitsuba material").

The material is a Mitsuba 3 scene-dictionary entry for the twin's extended-Ward
BSDF plugin ``glossrig_ward`` (``glossrig.twin.ward_bsdf``; eq. 4.79-4.80)::

    {"type": "glossrig_ward",
     "rho_d": {"type": "rgb", "value": [r, g, b]},
     "rho_s": {"type": "rgb", "value": [r, g, b]},
     "alpha_x": ..., "alpha_y": ..., "lobe_rotation": ...}   # radians

The plugin has one lobe (float alphas and rotation) with RGB albedos, so the
lobe is the luminance fit's and ``rho_d``, ``rho_s`` per channel are the
shared-lobe albedos of :class:`glossrig.core.fitting.fit.MaterialFit` (re-solved for
that lobe), not the independent per-channel fits, whose lobes differ slightly.
Plain JSON: ``mi.load_dict`` accepts it as is once the plugin is registered.
Knows nothing of Mitsuba itself (core imports neither twin nor Mitsuba).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from glossrig.core.errors import InputError
from glossrig.core.models.ward import WardParams

if TYPE_CHECKING:
    from glossrig.core.fitting.fit import MaterialFit

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
    """The ``glossrig_ward`` material of a :class:`~glossrig.core.fitting.fit.MaterialFit`."""
    s = material_fit.shared_rgb
    lobe = WardParams(rho_d=0.0, rho_s=0.0, alpha_x=s["alpha_x"], alpha_y=s["alpha_y"],
                      lobe_rotation=s["lobe_rotation"])
    return mitsuba_from_params(lobe, s["rho_d"], s["rho_s"])


def write_fit_json(material_fit, path: str | Path, provenance: dict | None = None) -> Path:
    """Write ``material_fit.to_json()`` atomically (temporary file + rename).

    ``provenance`` (:func:`glossrig.core.provenance.provenance`; for ``glossrig fit``
    it holds the samples table's own provenance, the chain back to the raw captures)
    becomes the top-level ``"provenance"`` object."""
    from glossrig.core.atomic import atomic_write_json

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("output folder does not exist", path=path)
    doc = material_fit.to_json()
    if provenance is not None:
        doc["provenance"] = provenance
    return atomic_write_json(path, doc, indent=2, allow_nan=False)


def write_mitsuba_material(material_fit, path: str | Path) -> Path:
    """Write the Mitsuba material dict alone as JSON."""
    from glossrig.core.atomic import atomic_write_json

    path = Path(path)
    if not path.parent.is_dir():
        raise InputError("output folder does not exist", path=path)
    return atomic_write_json(path, mitsuba_material(material_fit), indent=2)


FIT_FORMAT = "glossrig-fit/1"


@dataclass(frozen=True)
class FitFile:
    """A ``fit.json`` as :func:`read_fit_file` reads it: the fit, and what the writer adds
    to the fit's own fields."""

    fit: MaterialFit
    provenance: dict | None         # the top-level "provenance" object (write_fit_json)
    gloss: dict | None              # the luminance fit's gloss units as written ("luminance"."gloss")
    path: Path


def read_fit_file(path: str | Path) -> FitFile:
    """Read a ``fit.json`` (:func:`write_fit_json`): the one reader of the format. The fit
    is :func:`fit_from_doc`'s (see :func:`read_fit_json`); errors name the file."""
    from glossrig.core.toml_input import read_json

    path = Path(path)
    doc = read_json(path, "fit file")
    fit = fit_from_doc(doc, path)
    lum = doc.get("luminance")
    gloss = lum.get("gloss") if isinstance(lum, dict) else None
    prov = doc.get("provenance")
    return FitFile(fit, prov if isinstance(prov, dict) else None, gloss if isinstance(gloss, dict) else None, path)


def read_fit_json(path: str | Path) -> MaterialFit:
    """Read a ``fit.json`` (:func:`write_fit_json`) back into a
    :class:`~glossrig.core.fitting.fit.MaterialFit` (:func:`read_fit_file`).

    Every channel the file holds (``luminance``, ``r``, ``g``, ``b``) becomes a
    :class:`~glossrig.core.fitting.fit.WardFit` with its parameters, standard errors (``null``
    -> infinite: undetermined), covariance (``null`` -> NaN), residual statistics and
    settings; ``shared_lobe_rgb``, ``source`` and ``options`` are kept, so
    ``read_fit_json(p).to_json()`` equals the file's content apart from keys added
    after the fit (``provenance``, and any other top-level or per-channel extras, which
    are ignored here; read the file's ``provenance`` with :func:`read_fit_provenance`).
    Errors name the file."""
    return read_fit_file(path).fit


def fit_from_doc(doc, path: str | Path | None = None):
    """The :class:`~glossrig.core.fitting.fit.MaterialFit` of a parsed fit.json document (what
    :func:`read_fit_json` reads; ``path`` only names the file in errors)."""
    import numpy as np

    from glossrig.core.fitting.fit import CHANNELS, PARAM_NAMES, MaterialFit, WardFit
    from glossrig.core.fitting.uncertainty import read_uncertainty

    path = Path(path) if path is not None else None
    if not isinstance(doc, dict) or doc.get("format") != FIT_FORMAT:
        got = doc.get("format") if isinstance(doc, dict) else type(doc).__name__
        raise InputError(f"not a glossrig fit file (format {got!r}, expected {FIT_FORMAT!r})", path=path)

    def inf(v):
        return math.inf if v is None else float(v)

    def nan(v):
        return math.nan if v is None else float(v)

    fits = {}
    try:
        for ch in CHANNELS:
            d = doc.get(ch)
            if d is None:
                continue
            params = WardParams(**{k: float(d[k]) for k in PARAM_NAMES})
            order = d.get("covariance_order", list(PARAM_NAMES))
            if list(order) != list(PARAM_NAMES):
                raise ValueError(f"covariance_order {order!r} is not {list(PARAM_NAMES)!r}")
            cov = np.array([[nan(v) for v in row] for row in d["covariance"]], dtype=np.float64)
            if cov.shape != (len(PARAM_NAMES),) * 2:
                raise ValueError(f"covariance of shape {cov.shape}, expected 5 x 5")
            res = {k: (math.nan if v is None else v) for k, v in d["residuals"].items()}
            fits[ch] = WardFit(channel=ch, params=params, stderr={k: inf(d[f"{k}_stderr"]) for k in PARAM_NAMES},
                               covariance=cov, residuals=res, at_bound=list(d["at_bound"]),
                               n_samples=int(d["n_samples"]), weighting=str(d["weighting"]), clip=d["clip"],
                               clip_model=bool(d["clip_model"]), cost=float(d["cost"]),
                               converged=bool(d["converged"]), n_starts=int(d["n_starts"]),
                               time_s=float(d["time_s"]), footprint=d.get("footprint"),
                               uncertainty=read_uncertainty(d.get("uncertainty")))
        if not fits:
            raise ValueError(f"no fitted channel (expected one of {', '.join(CHANNELS)})")
        shared = dict(doc["shared_lobe_rgb"])
        for k in ("rho_d", "rho_s"):
            shared[k] = [float(v) for v in shared[k]]
            if len(shared[k]) != 3:
                raise ValueError(f"shared_lobe_rgb.{k} must hold three values")
        for k in ("alpha_x", "alpha_y", "lobe_rotation"):
            shared[k] = float(shared[k])
    except InputError as e:
        raise InputError(f"bad fit file: {e}", path=path) from None
    except (KeyError, TypeError, ValueError, AttributeError) as e:
        what = f"missing key {e.args[0]!r}" if isinstance(e, KeyError) else str(e)
        raise InputError(f"not a glossrig fit file: {what}", path=path) from None
    return MaterialFit(fits=fits, shared_rgb=shared, source=doc.get("source"), options=dict(doc.get("options") or {}))


def read_fit_provenance(path: str | Path) -> dict | None:
    """The ``"provenance"`` object of a ``fit.json`` (None when the file has none)."""
    return read_fit_file(path).provenance
