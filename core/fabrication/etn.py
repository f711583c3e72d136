"""The effective-to-nominal (ETN) function of a fitted reproduction model (thesis 6.1-6.2).

A material map holds, per pixel, the effective coverage ``ce^{b2}`` of the second
(scratched) base: the mixing ratio of the two base BRDFs that best reproduces the
pixel's material (eq. 6.1-6.3). What the engraver must scratch is the nominal coverage
``cn^{b2} = f^{etn}(ce^{b2})`` (eq. 6.4), with the sigmoid-like ETN of eq. 6.7,
fitted by eq. 6.8. Thesis 7.2.2 and 7.2.5 apply it to every pixel before halftoning.

Eq. 6.7 is printed as ``f(x) = g1 / ((g3 + exp(-g2 x)) + g4)``, in which ``g3`` and
``g4`` can only act through their sum; the likely intent, which the project's
reproduction model (``core/reproduction/model.py``) fits, is a sigmoid with an offset,
``g1 / (g3 + exp(-g2 x)) + g4``. Both are read; the model names its form (below) and
the offset form is the default. Nominal coverages outside [0, 1] are clipped by the
caller (and counted in ``summary.json``).

The model file (``model.json``) is written by the reproduction-model fit; this module
reads only what fabrication needs, without importing that code::

    {
      "kind": "glossrig.reproduction_model",
      "etn": {
        "gamma": [g1, g2, g3, g4],    # or "gamma1" ... "gamma4"
        "form": "eq6.7-offset"        # optional, the default: g1 / (g3 + exp(-g2 x)) + g4
                                      # "eq6.7": as printed, g1 / ((g3 + exp(-g2 x)) + g4);
                                      # core/reproduction/model.py's formula string for the offset
                                      # form is recognised too
      },
      ...                             # anything else (bases, fit statistics) is ignored here
    }
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from glossrig.core.errors import InputError
from glossrig.core.toml_input import read_json

MODEL_KIND = "glossrig.reproduction_model"
FORMS = ("eq6.7-offset", "eq6.7")
# the offset form as core/reproduction/model.py spells it (its ETN_FORM), whitespace removed
_OFFSET_FORMULA = "gamma[0]/(gamma[2]+exp(-gamma[1]*effective_b2))+gamma[3]"
_PRINTED_FORMULA = "gamma[0]/((gamma[2]+exp(-gamma[1]*effective_b2))+gamma[3])"


def _form(value) -> str | None:
    """Canonical form name of an ``etn.form`` value, or None when it is not recognised."""
    if value is None:
        return "eq6.7-offset"
    if not isinstance(value, str):
        return None
    if value in FORMS:
        return value
    compact = "".join(value.split())
    if _PRINTED_FORMULA in compact:
        return "eq6.7"
    if _OFFSET_FORMULA in compact:
        return "eq6.7-offset"
    return None


@dataclass(frozen=True)
class Etn:
    """ETN of eq. 6.7 with parameters ``gamma = (g1, g2, g3, g4)`` (thesis table 6.5)."""

    gamma: tuple[float, float, float, float]
    form: str = "eq6.7-offset"
    source: str = ""

    def __call__(self, effective: np.ndarray) -> np.ndarray:
        g1, g2, g3, g4 = self.gamma
        x = np.asarray(effective, dtype=np.float64)
        with np.errstate(over="ignore", divide="ignore", invalid="ignore"):
            if self.form == "eq6.7":
                return g1 / ((g3 + np.exp(-g2 * x)) + g4)
            return g1 / (g3 + np.exp(-g2 * x)) + g4

    def check_on_unit_interval(self) -> None:
        """Refuse parameters whose ETN has a pole or non-finite values for ``ce`` in [0, 1]:
        the denominator ``c + exp(-g2 x)`` is monotonic in ``x``, so it has no zero in [0, 1]
        when it has the same non-zero sign at both ends."""
        g1, g2, g3, g4 = self.gamma
        c = g3 + g4 if self.form == "eq6.7" else g3
        ends = np.array([c + 1.0, c + math.exp(-g2)]) if abs(g2) < 700 else np.array([np.nan, np.nan])
        if not np.all(np.isfinite(ends)) or ends[0] * ends[1] <= 0:
            raise InputError(f"ETN with gamma {list(self.gamma)} ({self.form}) has a pole or overflows "
                             "for effective coverages in [0, 1]", path=self.source or None)


def load_etn(path: str | Path) -> Etn:
    """Read the ETN of a reproduction model file (module docstring for the JSON expected).

    Refuses, naming the file: a missing or non-JSON file, a file of another ``kind``,
    a missing ``etn`` object, parameters that are not four finite numbers, an unknown
    form, an ETN with a pole on [0, 1].
    """
    path = Path(path)
    doc = read_json(path, "model file")
    if not isinstance(doc, dict) or doc.get("kind") != MODEL_KIND:
        kind = doc.get("kind") if isinstance(doc, dict) else type(doc).__name__
        raise InputError(f"expected a reproduction model (\"kind\": \"{MODEL_KIND}\"), got kind {kind!r}", path=path)
    etn = doc.get("etn")
    if not isinstance(etn, dict):
        raise InputError("reproduction model lacks the \"etn\" object (thesis eq. 6.7 parameters)", path=path)
    if "gamma" in etn:
        gamma = etn["gamma"]
    else:
        gamma = [etn.get(f"gamma{i}") for i in range(1, 5)]
    if (not isinstance(gamma, list) or len(gamma) != 4
            or not all(isinstance(g, (int, float)) and not isinstance(g, bool) and math.isfinite(g) for g in gamma)):
        raise InputError(f"etn parameters must be four finite numbers (\"gamma\": [g1, g2, g3, g4]), got {gamma!r}",
                         path=path)
    form = _form(etn.get("form"))
    if form is None:
        raise InputError(f"etn form must be one of {list(FORMS)} (or the formula "
                         f"{_OFFSET_FORMULA!r}), got {etn.get('form')!r}", path=path)
    out = Etn(tuple(float(g) for g in gamma), form, str(path))
    out.check_on_unit_interval()
    return out
