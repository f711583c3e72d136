"""Whether a given ``--fit`` is a fit of the diagnosed capture's material.

``glossrig diagnose --fit FIT.json`` holds the material fixed at the fit's parameters (a fit
made beforehand, typically on another capture of the same sample), so a fit of another
material must be refused. Two ways to tell, in this order:

1. **Provenance.** A fit.json records where its samples came from: ``glossrig fit`` under
   ``provenance.inputs.samples.provenance.inputs.sample`` (the capture folder ``extract``
   read), a study's fit under ``provenance.source``. When that capture's manifest is at hand,
   its sample name (the capture plan's ``sample``, else the manifest's ``material``) is compared
   with this capture's: a different name is refused, the same name accepted whatever the
   misfit. The misfit cannot decide this: an instrument effect is what diagnose is asked to
   find, and a strong one moves the data as far as another material does. Measured on the blind
   study's captures (validation/diagnose/blind_study.md): satin_rosaline's own fit missed a
   satin capture with an LED emission pattern (cos^25) by a median 53 %, while white paper's
   fit missed satin's capture without any effect by only 22 %; an ilm matte capture with an
   emission pattern was missed by its own fit by 59 % and by satin's by 22 %.
2. **Misfit**, where the provenance names no capture that can be read (a fit made from
   synthetic samples, or a capture moved away): the fit's model must describe this capture's
   thesis-normalised data to a median relative miss below :data:`FIT_MISMATCH`. A weak check,
   for the reason above; the report says which one was applied.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np

from glossrig.core.errors import InputError

#: base-model median |relative error| above which a given fit without a readable source capture
#: cannot be this capture's material
FIT_MISMATCH = 0.5


def _fit_source(prov: dict | None) -> Path | None:
    """The capture folder a fit's samples came from, as its provenance records it (or None)."""
    if not isinstance(prov, dict):
        return None
    src = prov.get("source")
    if isinstance(src, str):
        return Path(src)
    try:
        sample = prov["inputs"]["samples"]["provenance"]["inputs"]["sample"]
    except (KeyError, TypeError):
        return None
    path = sample.get("resolved") or sample.get("path") if isinstance(sample, dict) else None
    return Path(path) if isinstance(path, str) else None


def sample_name(capture_dir: Path) -> str | None:
    """A capture's sample: its plan's ``sample``, else its manifest's ``material`` (None when the
    folder holds no readable manifest)."""
    from glossrig.core.capture import MANIFEST, load_manifest

    if not (Path(capture_dir) / MANIFEST).is_file():
        return None
    try:
        man = load_manifest(capture_dir)
    except InputError:
        return None
    name = man.meta.get("sample") or man.material
    return str(name) if name else None


def check_fit(fit_path, provenance: dict | None, sample_dir, misfit: float) -> str:
    """Refuse a fit of another material (module docstring) with an InputError naming FIT; else
    return the line the diagnosis logs and reports: which check accepted it. ``misfit``: the
    fit's median relative miss of this capture's data (rows with every channel)."""
    src = _fit_source(provenance)
    if src is not None and not src.is_absolute():
        src = Path(fit_path).parent / src          # a relative source is the fit file's
    theirs = sample_name(src) if src is not None else None
    ours = sample_name(Path(sample_dir))
    if theirs is not None and ours is not None:
        if theirs != ours:
            raise InputError(f"the fit does not belong to this capture: it was made from a capture of sample "
                             f"{theirs!r} ({src}), this capture is of sample {ours!r}", path=Path(fit_path))
        return (f"fit of the same sample {ours!r} (its samples came from {src}); its model misses this capture's "
                f"data by a median {misfit:.0%}")
    if not np.isfinite(misfit) or misfit > FIT_MISMATCH:
        raise InputError(f"the fit does not belong to this capture: its model misses the measured BRDF by a "
                         f"median {misfit:.0%} (> {FIT_MISMATCH:.0%}; the fit's provenance names no capture "
                         f"whose sample could be compared)", path=Path(fit_path))
    return (f"fit checked by its misfit only (its provenance names no readable capture): a median miss of "
            f"{misfit:.0%} (<= {FIT_MISMATCH:.0%})")
