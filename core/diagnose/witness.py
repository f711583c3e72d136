"""A BRDF-space instrument cause judged by a witness outside the BRDF rows (issue 14, item 3).

Some instrument effects leave a trace where no material acts: the marker's white patch seen in
both captures (:mod:`.white_patch`: vignetting, a changed LED emission pattern) and the cylinder's
silhouette in the sample's own frames (:mod:`.silhouette`: the sample radius). Such a witness
measures the cause's size without the material; :func:`take_witness_test` then decides whether the
BRDF data, which a material's departure from its model can bend, contradict that size. One rule for
every witness, so that each names its cause the same way.
"""
from __future__ import annotations

import math

import numpy as np

from glossrig.core.diagnose.catalogue import GAIN_THRESHOLD, CauseResult, fixed_term_test

BOUND_Z = 3.0        # a BRDF-space estimate this many combined standard errors from the witness's: they disagree


def take_witness_test(c: CauseResult, m, ev: dict, pname: str, value: float, factor, extra: dict, note: str,
                      witness: str, test=None, direct: bool = False) -> bool:
    """Where the BRDF data do not contradict the witness's estimate ``value`` of ``pname`` - the model
    ``m`` with the cause at that estimate held fixed (``factor`` on every row; ``test``: a callable giving
    :func:`~glossrig.core.diagnose.catalogue.fixed_term_test`'s four results another way, for a cause
    that moves the lobe, :func:`~glossrig.core.diagnose.catalogue.fixed_made_test`) raises the error of the
    pooled rows by less than the BRDF space's threshold GAIN_THRESHOLD, the least change it tells from
    a null capture's spread (:func:`~glossrig.core.diagnose.catalogue.fixed_term_test`, its gains
    recorded; measured: on the eight-LED satin capture with a vignetting of 0.135, read 0.137 +- 0.002
    on the white patch, the material's flexible columns had taken the fall-off up and k held at the
    patch's value raised the error by 0.24 %, while a pattern the rows do not have raises it 35- to
    500-fold, tests/test_white_patch.py) - the BRDF-space cause ``c`` takes the witness's test, in
    place: its value, standard error, held-out gains (``ev``: ``se``, ``gain``, ``fold_gains``) and
    ``frame_signature`` (the free BRDF-space estimate kept as ``<pname>_brdf``). Returns whether it did.

    Where the BRDF-space cause is significant by itself and its free estimate agrees with the
    witness's (within BOUND_Z combined standard errors), its own fit is kept and the witness only
    confirms it (``frame_signature``, ``confirmed_by``): fitted on the sample's rows it predicts them
    better than the witness's estimate carried over (measured on the blind study's Ward capture with
    an emission pattern of n = 24.9: the BRDF fit reads 24.7, the patch 22.3 +- 1.8, and with the
    patch's n held the rows kept a structure along the axis that the open-world test called
    unexplained).

    ``direct``: the witness measures the cause on the sample itself (the sample's own outline is its
    radius, :mod:`.silhouette`), so the BRDF rows' test is recorded but not required: the material
    model they are scored with was fitted with the cause left out and has taken part of it up (its lobe
    width), and a second effect bends the rows further (measured on the blind study's satin capture
    with a shutter error and a radius of -0.565 mm, read -0.539 +- 0.032 mm on the outline: the rows with
    that radius held raised the error by 39 %, the free BRDF-space fit read -0.19 mm)."""
    value_b = float(c.params.get(pname, float("nan")))
    se_b = float(c.stderr.get(pname, float("nan")) or float("nan")) if isinstance(c.stderr, dict) else float("nan")
    if c.significant and np.isfinite(value_b) and abs(value_b - value) <= BOUND_Z * math.hypot(
            ev["se"], se_b if np.isfinite(se_b) else 0.0):
        c.frame_signature = True
        c.params["confirmed_by"] = witness
        c.note = (c.note + "; " if c.note else "") + (
            f"the {witness} agrees ({pname} = {value:.3g} +- {ev['se']:.2g} there, held-out gain {ev['gain']:.1%})")
        return True
    e0, e1, led_gains, pred = (test() if test is not None
                               else fixed_term_test(m, [m.diffuse(), m.cols["L"]], factor=factor))
    c.params["fixed_brdf_gain"] = gain = (e0 - e1) / e0 if e0 > 0 else 0.0
    c.params["fixed_brdf_led_gains"] = led_gains
    if not (direct or gain > -GAIN_THRESHOLD):
        return False
    c.params.update({f"{pname}_brdf": c.params.get(pname), pname: value, "fixed_by": witness, **extra})
    if isinstance(c.stderr, dict):
        c.stderr[pname] = ev["se"]
    c.base_error, c.error, c.fold_gains = 1.0, 1.0 - ev["gain"], ev["fold_gains"]
    c.prediction, c.magnitude = pred, value
    c.params["free_fit_robust"], c.robust = c.robust, None
    c.identifiable, c.frame_signature = True, True
    c.note = note
    return True


def pair_rates(ms, mr, rig_s, rig_r, rotation: float, led: int, box):
    """Both captures' HDR rates of one LED over ``box`` (full image x0, y0, x1, y1; the pipeline's own HDR,
    :func:`glossrig.core.extraction.extract.led_rate`): (rs, vs, rr, vr, cfa) of the sample capture ``ms``
    and the reference capture ``mr`` (manifests; ``rig_s``, ``rig_r`` their rigs), None where either lacks
    the LED's sequence at ``rotation``. The witnesses that compare the captures read through it."""
    from glossrig.core.extraction.extract import led_rate, led_sequence

    seq_s, seq_r = led_sequence(ms, rotation, led), led_sequence(mr, rotation, led)
    if not seq_s or not seq_r:
        return None
    rs, vs, _, cfa, _ = led_rate(ms, rig_s, seq_s, box)
    rr, vr, _, _, _ = led_rate(mr, rig_r, seq_r, box)
    return rs, vs, rr, vr, cfa


def single_leds(man, rotation: float) -> list[int]:
    """The LEDs with a sequence of their own at ``rotation`` in a capture's manifest."""
    return sorted({im.leds[0] for im in man.images if im.role == "sequence" and im.rotation == rotation
                   and len(im.leds) == 1})


def brdf_cause(causes: list[CauseResult], name: str) -> CauseResult | None:
    """The BRDF-space cause ``name`` among ``causes`` (the one a witness judges), None where not fitted."""
    return next((x for x in causes if x.name == name and x.space == "brdf"), None)


def refute(c: CauseResult, why: str) -> None:
    """Mark the BRDF-space cause ``c`` refuted by a witness (not significant), saying ``why`` in its note."""
    c.refuted = why
    c.note = (c.note + "; " if c.note else "") + why
